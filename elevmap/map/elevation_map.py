"""The robot-centric 2.5-D elevation map: named float layers on a moving grid, NaN = unknown.

Conventions (frames, cells, map and buffer indices) are those of :mod:`elevmap.map.grid`; the layers are
those of :mod:`elevmap.map.layers`. The state is one float64 array ``data`` of shape (len(LAYERS), n, n)
in *buffer* order; :meth:`ElevationMap.layer` returns a layer in map-index order (row i grows with x,
column j with y).
"""

from __future__ import annotations

import contextlib
import math

import numpy as np

from noise_model.numba_config import resolve_threads, threads

from . import fusion, fusion_reference, grid_map, neighbours, prediction, queries, storage, visibility
from .grid import GridGeometry
from .layers import LAYERS, POINTS, UNKNOWN_VALUES
from .settings import check_coordinates, check_map_memory

__all__ = ["ElevationMap", "BYTES_PER_CELL"]

#: Memory of one cell [bytes]: its float64 layers and the fusion's partial grids (:class:`fusion.FusionWorkspace`).
BYTES_PER_CELL = 8 * len(LAYERS) + fusion.WORKSPACE_BYTES_PER_CELL


class ElevationMap:
    """A square, robot-centric elevation map fused from map-frame points by per-cell Kalman updates.

    Parameters
    ----------
    length_m : float
        Side length [m] (rounded to whole cells).
    resolution_m : float
        Cell size [m].
    centre_xy : (2,) array_like
        Initial centre in the map frame [m].
    fusion_params : elevmap.map.fusion.FusionParams, optional
        Gate, variance bounds, change detection and information cap.
    visibility_cleanup : bool
        Clear cells that rays to measured points pass below (needs ``sensor_origin_map`` in
        :meth:`update`).
    cleanup_stride : int
        Cast a ray to one point in every ``cleanup_stride`` of the lowest points per cell.
    nthreads : int, optional
        numba threads for the kernels (numba's setting by default).

    Examples
    --------
    >>> m = ElevationMap(length_m=8.0, resolution_m=0.04)
    >>> m.update(points_map, height_var, stamp=0.0)           # doctest: +SKIP
    >>> h, var = m.height_at([[1.0, 0.5]])                    # doctest: +SKIP
    """

    def __init__(self, length_m: float = 8.0, resolution_m: float = 0.04, centre_xy=(0.0, 0.0), *,
                 fusion_params: fusion.FusionParams | None = None, visibility_cleanup: bool = True,
                 cleanup_stride: int = 1, nthreads: int | None = None):
        self.geometry = GridGeometry.centred(length_m, resolution_m, centre_xy)
        n = self.geometry.n
        check_map_memory(n, BYTES_PER_CELL, self.geometry.resolution_m)
        self.data = np.empty((len(LAYERS), n, n))
        self.data[:] = np.array(UNKNOWN_VALUES)[:, None, None]
        self.fusion_params = fusion.FusionParams() if fusion_params is None else fusion_params
        if not isinstance(self.fusion_params, fusion.FusionParams):
            raise ValueError("fusion_params must be an elevmap.map.fusion.FusionParams")
        self.visibility_cleanup = bool(visibility_cleanup)
        if int(cleanup_stride) < 1:
            raise ValueError(f"cleanup_stride must be >= 1, got {cleanup_stride!r}")
        self.cleanup_stride = int(cleanup_stride)
        self.nthreads = nthreads
        self.frames = 0
        self.last_stamp = float("nan")
        self._ws = fusion.FusionWorkspace(n)

    # -- geometry --------------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Cells per side."""
        return self.geometry.n

    @property
    def resolution_m(self) -> float:
        return self.geometry.resolution_m

    @property
    def length_m(self) -> float:
        return self.geometry.length_m

    @property
    def centre_xy(self) -> np.ndarray:
        """Centre of the map in the map frame [m]."""
        return self.geometry.centre_xy

    def cell_centres(self):
        """(x of rows, y of columns) of the cell centres in map-index order [m]."""
        return self.geometry.cell_centres()

    # -- layers ----------------------------------------------------------------------------------
    def layer(self, name: str) -> np.ndarray:
        """A copy of layer ``name`` in map-index order: ``layer[i, j]``, i along +x, j along +y."""
        return self.geometry.unwrap(self.data[self._layer_index(name)])

    def layers(self) -> dict:
        """All layers in map-index order (copies)."""
        unwrapped = self.geometry.unwrap(self.data)
        return {name: unwrapped[k] for k, name in enumerate(LAYERS)}

    def known_layer(self, name: str) -> np.ndarray:
        """A layer as consumers see it: :meth:`layer` with NaN wherever the cell is not known."""
        return np.where(self.is_known(), self.layer(name), np.nan)

    def is_known(self) -> np.ndarray:
        """Boolean mask of known cells, map-index order: a height, and at least
        ``fusion_params.min_points`` points fused into it."""
        return self.geometry.unwrap(self._known_buffer())

    def _known_buffer(self) -> np.ndarray:
        """:meth:`is_known` in buffer order."""
        return np.isfinite(self.data[0]) & (self.data[POINTS] >= self.fusion_params.min_points)

    @staticmethod
    def _layer_index(name: str) -> int:
        try:
            return LAYERS.index(name)
        except ValueError:
            raise ValueError(f"unknown layer {name!r}; layers are {', '.join(LAYERS)}") from None

    def clear(self) -> None:
        """Forget everything (all cells unknown)."""
        self.data[:] = np.array(UNKNOWN_VALUES)[:, None, None]

    # -- update ----------------------------------------------------------------------------------
    def update(self, points_map, height_var, stamp: float | None = None, sensor_origin_map=None,
               horizontal_cov=None, *, impl: str = "numba", frame_error=None) -> dict:
        """Fuse one frame of map-frame points.

        Parameters
        ----------
        points_map : array_like, shape (N, 3)
            Points in the map frame [m], any memory layout; all finite (drop invalid points first) and within
            ``settings.MAX_COORDINATE_M``.
        height_var : array_like, shape (N,)
            Variance of each point's height [m^2], in [``settings.MIN_HEIGHT_VARIANCE``,
            ``settings.MAX_POINT_VARIANCE``].
        stamp : float, optional
            Time of the frame [s] (the ``time`` layer); the frame counter when None.
        sensor_origin_map : (3,) array_like, optional
            Camera centre in the map frame [m]; with it, visibility clean-up runs (when enabled).
        horizontal_cov : array_like, shape (N, 3), optional
            (Sigma_xx, Sigma_xy, Sigma_yy) of each point [m^2] for the horizontal-variance layers.
        impl : {"numba", "numpy"}
            The compiled kernel or its NumPy reference.
        frame_error : (float, float), optional
            The frame's error correlation length [px] and variance ratio, which scale its information per
            cell (:mod:`elevmap.map.fusion`; :meth:`noise_model.SensorModel.frame_error` gives them for a
            camera); None: the points' variances are the whole error and the points independent.

        Returns
        -------
        dict
            ``{"cells_updated": int, "cells_cleared": int}``.

        Raises
        ------
        ValueError
            A shape, dtype or value out of range, naming the array and what is wrong
            (:func:`elevmap.map.settings.check_point_values`); the map is then unchanged.
        """
        p = np.asarray(points_map)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points_map must have shape (N, 3), got {p.shape}")
        if p.dtype.kind not in "fiu":              # floating or integer
            raise ValueError(f"points_map must be floating point metres, got dtype {p.dtype}")
        p = p.astype(np.float64, copy=False)       # any memory layout: the fusion reads it column by column
        n_pts = len(p)
        var = np.asarray(height_var)
        if var.shape != (n_pts,):
            raise ValueError(f"height_var must have shape ({n_pts},), got {var.shape}")
        if var.dtype.kind != "f":
            raise ValueError(f"height_var must be floating point [m^2], got dtype {var.dtype}")
        var = var.astype(np.float64, copy=False)
        hcov = None
        if horizontal_cov is not None:
            hcov = np.asarray(horizontal_cov, dtype=np.float64)
            if hcov.shape != (n_pts, 3):
                raise ValueError(f"horizontal_cov must have shape ({n_pts}, 3), got {hcov.shape}")
        if stamp is None:
            stamp = float(self.frames)
        try:
            stamp = float(stamp)
        except (TypeError, ValueError):
            raise ValueError(f"stamp must be a finite number [s], got {stamp!r}") from None
        if not math.isfinite(stamp):
            raise ValueError(f"stamp must be finite, got {stamp!r}")
        origin = None
        if sensor_origin_map is not None:
            origin = np.asarray(sensor_origin_map, dtype=np.float64)
            if origin.shape != (3,) or not np.all(np.isfinite(origin)):
                raise ValueError(f"sensor_origin_map must be 3 finite numbers [m], got {sensor_origin_map!r}")
            check_coordinates(origin, "sensor_origin_map")
        if impl not in ("numba", "numpy"):
            raise ValueError(f"impl must be 'numba' or 'numpy', got {impl!r}")
        # the values of the points (finite, coordinates and variances in range) are checked by the fusion
        # (numba: in its first pass, before it changes anything; numpy: check_point_values first)
        fusion.check_frame_error(frame_error)
        return self._update_validated(p, var, hcov, stamp, origin, impl, frame_error=frame_error)

    def _update_validated(self, p, var, hcov, stamp: float, origin, impl: str = "numba", check: bool = True,
                          frame_error=None) -> dict:
        """:meth:`update` on inputs whose shapes and dtypes are checked (the fusion checks their values unless
        ``check`` is False: points whose producer counted none out of range, see :func:`fusion.fuse_frame`)."""
        if impl == "numba":
            n = resolve_threads(self.nthreads)
            with threads(n):               # numba's thread count set once for the update's kernels
                touched, box, cleared = self._update_kernels(p, var, hcov, stamp, origin, impl, check, frame_error,
                                                             n)
        else:
            touched, box, cleared = self._update_kernels(p, var, hcov, stamp, origin, impl, check, frame_error)
        self.frames += 1
        self.last_stamp = stamp
        return {"cells_updated": touched, "cells_cleared": cleared}

    def _update_kernels(self, p, var, hcov, stamp, origin, impl, check, frame_error, n=None):
        """The fusion, the clean-up and the neighbourhood spread of :meth:`_update_validated` (numba: inside its
        ``threads(n)``). Returns (cells touched, their box or None, cells cleared)."""
        clean = origin is not None and self.visibility_cleanup
        if impl == "numba":
            # with the clean-up to come, the fusion's pass keeps each cell's lowest ray end for it
            touched, box = fusion.fuse_frame_in_threads(self.data, self.geometry, p, var, hcov, stamp,
                                                        self.fusion_params, self._ws, n,
                                                        visibility.ENDPOINT_MARGIN_SIGMAS if clean else None,
                                                        check, frame_error)
        else:
            touched, box = fusion_reference.fuse_frame_reference(self.data, self.geometry, p, var, hcov, stamp,
                                                       self.fusion_params, frame_error)
        cleared = 0
        if clean and box is not None:
            cleared = self._visibility(origin, p, var, stamp, impl, box)
        if self.fusion_params.neighbour_radius and box is not None:
            self._neighbours(box, origin if cleared else None, impl, n)
        return touched, box, cleared

    def _neighbours(self, box, origin, impl, n=None) -> None:
        """Recompute the neighbourhood spread around the cells this frame touched: ``box`` (i0, i1, j0, j1),
        their first and last map row and column, with the camera's cell when visibility cleared cells on
        the rays (clipped to the window: a ray enters the window between the camera and its point). ``n``: numba's
        threads, already set by the caller (None: set them here)."""
        i0, i1, j0, j1 = box
        if origin is not None:
            (oi, oj), _ = self.geometry.map_index(origin[:2])
            last = self.geometry.n - 1
            oi, oj = min(max(int(oi), 0), last), min(max(int(oj), 0), last)
            i0, i1, j0, j1 = min(i0, oi), max(i1, oi), min(j0, oj), max(j1, oj)
        rows, cols = (i0, i1), (j0, j1)
        if impl == "numba":
            with threads(self.nthreads) if n is None else contextlib.nullcontext(n) as n:
                neighbours._update_window(self.data, self.geometry, self.fusion_params.neighbour_radius, rows, cols,
                                          n, self.fusion_params.neighbour_estimator)
        else:
            neighbours.update_neighbour_spread_reference(self.data, self.geometry,
                                                         self.fusion_params.neighbour_radius, rows, cols,
                                                         self.fusion_params.neighbour_estimator)

    def _visibility(self, origin, points_map, height_var, stamp, impl, box) -> int:
        """The clean-up of a fused frame (points checked; ``box``: the cells they reached, from the fusion)."""
        if impl == "numba":
            return visibility.visibility_cleanup_box(self.data, self.geometry, origin, points_map, stamp, box,
                                                     self.cleanup_stride, self.nthreads, height_var,
                                                     visibility.ENDPOINT_MARGIN_SIGMAS,
                                                     (self._ws.acc, self._ws.stamp, self._ws.frame))
        return visibility.visibility_cleanup_reference(self.data, self.geometry, origin, points_map, stamp,
                                                       stride=self.cleanup_stride, height_var=height_var)

    # -- robot-centric motion --------------------------------------------------------------------
    def move_to(self, xy) -> dict:
        """Re-centre the map at the lattice point nearest ``xy`` [m] (map frame), without copying.

        Cells that stay keep their data and their buffer slot; cells that enter become unknown.

        Returns
        -------
        dict
            ``{"shift_cells": (dx, dy), "cleared_rows": int, "cleared_cols": int}``.
        """
        new = self.geometry.moved_to(xy)
        rows, cols = self.geometry.uncovered_by_move(new)
        unknown = np.array(UNKNOWN_VALUES)
        if len(rows):
            self.data[:, rows, :] = unknown[:, None, None]
        if len(cols):
            self.data[:, :, cols] = unknown[:, None, None]
        shift = (new.gx0 - self.geometry.gx0, new.gy0 - self.geometry.gy0)
        self.geometry = new
        return {"shift_cells": shift, "cleared_rows": int(len(rows)), "cleared_cols": int(len(cols))}

    def known_fraction(self) -> float:
        """Fraction of known cells."""
        return float(self._known_buffer().mean())

    # -- prediction and fused map (elevmap.map.prediction) -------------------------------------------
    def predict(self, relative_pose_cov=None, T_map_base=None, dt=None, time_variance_rate: float = 0.0, *,
                impl: str = "numba") -> dict:
        """Process-noise step before a frame: see :func:`elevmap.map.prediction.predict`.

        ``impl="numpy"`` runs the NumPy reference. Returns ``{"cells_expired": int}``.
        """
        if impl not in ("numba", "numpy"):
            raise ValueError(f"impl must be 'numba' or 'numpy', got {impl!r}")
        fn = prediction.predict if impl == "numba" else prediction.predict_reference
        return fn(self, relative_pose_cov, T_map_base, dt, time_variance_rate)

    def fused_map(self, *, impl: str = "numba") -> dict:
        """EM's ellipse-weighted fused layers, map-index order: see :func:`elevmap.map.prediction.fused_map`."""
        if impl not in ("numba", "numpy"):
            raise ValueError(f"impl must be 'numba' or 'numpy', got {impl!r}")
        return prediction.fused_map(self) if impl == "numba" else prediction.fused_map_reference(self)

    # -- queries (elevmap.map.queries), grid_map export (elevmap.map.grid_map), files (elevmap.map.storage) --
    def height_at(self, xy):
        """Height [m] and variance [m^2] at map-frame points (2,) or (M, 2); see :func:`.queries.height_at`."""
        return queries.height_at(self, xy)

    def height_scan(self, T_map_base, pattern="legged_gym", feet_base=None, fill=float("nan")):
        """Heights on a scan pattern around the base; see :func:`elevmap.map.queries.height_scan`."""
        return queries.height_scan(self, T_map_base, pattern=pattern, feet_base=feet_base, fill=fill)

    def to_grid_map(self, layers=None, *, frame_id: str = "map") -> dict:
        """grid_map message content; see :func:`elevmap.map.grid_map.to_grid_map`."""
        return grid_map.to_grid_map(self, layers, frame_id=frame_id)

    def save(self, path) -> None:
        """Write the map to one .npz file atomically; see :func:`elevmap.map.storage.save`."""
        storage.save(self, path)

    @classmethod
    def load(cls, path) -> "ElevationMap":
        """Read a map written by :meth:`save`; see :func:`elevmap.map.storage.load`."""
        return storage.read_map(path, cls)

    def __repr__(self) -> str:
        c = self.centre_xy
        return (f"ElevationMap({self.n}x{self.n} cells of {self.resolution_m} m, centre ({c[0]:.2f}, {c[1]:.2f}), "
                f"{100 * self.known_fraction():.1f}% known, {int(self.data[POINTS].sum())} points fused)")
