"""Capture data for the sim-to-real gap diagnosis: a capture's geometry, its frames, its simulation.

A capture (docs/capture-set-format.md, format ``d435-captures/1``) is a planar target (a wall, or a
board before an optional fronto-parallel background wall) recorded for N frames by a camera on a
tripod. This module holds, without any I/O (the readers live in ``elevmap.sources.captures``):

* :class:`CaptureGeometry` (from :mod:`noise_model.sim.targets`, where it is rendered and simulated):
  the camera intrinsics K [px], image size, depth scale [m/unit], baseline [m] and the target, built
  from the dicts of ``captures.json``, with its pixel *regions* and their codes ``REGION_*``.
* :class:`CaptureData`: a geometry and its frames as metric depth (F, H, W) [m], NaN = no data, with
  the capture's optional pixel mask and whether its geometry was measured or fitted.
* :func:`capture_geometry`: the geometry of a captures.json entry, any target kind: a ``plane``
  target (a fitted plane) becomes the wall whose plane it is (:func:`~.planes.plane_pose`).
* :func:`simulate_capture`: the reference simulation of a capture
  (:func:`noise_model.sim.targets.simulate_target`), with the capture's id and regions in the
  context of the effects.

Frames: camera x right, y down, z forward; depth is z (along the optical axis), not ray length.
Pixel (u, v) = (column, row), 0-based, integer coordinates at pixel centres.

Effect context
--------------
:func:`simulate_capture` calls each effect as ``effect(z, theta, rng, context)`` with ``context``:
``K`` (3, 3) [px], ``width``, ``height`` [px], ``index`` (frame index), ``depth_scale`` [m/unit],
``z_true`` (H, W) [m] (this frame's, read only; boards move their edges each frame), ``baseline_m``
[m], ``capture_id`` (str), ``regions`` (H, W) int8 (the nominal regions, read only) and ``z_ref``
(H, W) [m] (the depth after the reference noise, before any effect; read only).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..checks import check_positive_scalar
from ..d435 import D435, SensorModel
from ..sim.targets import (
    EDGE_PX_424, LATERAL_EDGE_SIGMAS, LEFT_BAND_MARGIN_PX_424, REGION_BACKGROUND, REGION_EDGE_LEFT, REGION_EDGE_RIGHT,
    REGION_INTERIOR, REGION_LEFT_BAND, REGION_NAMES, REGION_NONE, CaptureGeometry, simulate_target,
)

__all__ = ["CaptureGeometry", "CaptureData", "capture_geometry", "simulate_capture", "check_captures", "GEOMETRIES",
           "units_to_depth_m",
           "REGION_NONE", "REGION_INTERIOR", "REGION_EDGE_LEFT", "REGION_EDGE_RIGHT", "REGION_LEFT_BAND",
           "REGION_BACKGROUND", "REGION_NAMES", "LEFT_BAND_MARGIN_PX_424", "EDGE_PX_424", "LATERAL_EDGE_SIGMAS"]


#: How a capture's target pose is known: "measured" (tape or laser meter) or "fitted" (a plane fit to the
#: frames themselves, which absorbs any bias or scale error: statistics against the true distance are
#: meaningless for it).
GEOMETRIES = ("measured", "fitted")


def capture_geometry(camera: Mapping, capture: Mapping) -> CaptureGeometry:
    """The :class:`CaptureGeometry` of a captures.json entry, for any target kind.

    A ``wall`` or ``board`` is :meth:`CaptureGeometry.from_capture_set_entry`. A ``plane`` target
    (``normal`` m towards the camera, ``offset_m``: m . p + offset_m = 0) is the unbounded wall with the
    same plane: normal n = -m / |m| = R_y(yaw) R_x(pitch) e_z, centre on the optical axis at
    distance_m = offset_m / n_z (:func:`noise_model.analysis.planes.plane_pose`), so it renders the
    same depth and incidence angle at every pixel.

    Parameters
    ----------
    camera : mapping
        The ``camera`` object of captures.json.
    capture : mapping
        One entry of ``captures``.

    Returns
    -------
    CaptureGeometry

    Raises
    ------
    ValueError
        A bad target, named with the capture's id.
    """
    from .planes import plane_pose, target_plane

    if not isinstance(capture, Mapping):
        raise ValueError(f"capture must be a dict, got {type(capture).__name__}")
    target = capture.get("target")
    if isinstance(target, Mapping) and target.get("kind") == "plane":
        cid = capture.get("id")
        try:
            d, yaw, pitch = plane_pose(target_plane(target))
        except ValueError as exc:
            raise ValueError(f"{cid}: {exc}") from None
        if capture.get("background_m") is not None:
            raise ValueError(f"{cid}: a plane target has no background_m")
        capture = {**capture, "target": {"kind": "wall", "distance_m": d, "yaw_deg": yaw, "pitch_deg": pitch}}
    return CaptureGeometry.from_capture_set_entry(camera, capture)


class CaptureData:
    """A capture's geometry and frames, with its mask and how its geometry is known.

    Frames made from depth units (:meth:`from_units`: recordings, simulations) are kept as those units
    (uint16 as recorded: a quarter of the memory of metres in float64, and exact); :attr:`depth_m`
    converts them to metres on each access, :meth:`frame_m` and :meth:`pixels_m` only the part asked for.
    Frames given in metres are kept as float64.

    Parameters
    ----------
    geometry : CaptureGeometry
    depth_m : ndarray, shape (F, H, W), float
        Metric z-depth [m]; NaN = no data.
    mask : ndarray of bool, shape (H, W), or None
        True where a pixel sees the target (captures.json's ``mask``); None = every pixel the target
        covers. Statistics use only the mask's pixels.
    geometry_origin : str
        captures.json's ``geometry``: "measured" (default) or "fitted" (:data:`GEOMETRIES`). With fitted
        geometry, statistics against the true distance (bias, scale, absolute error) are not computed:
        the plane fit absorbs them.

    Attributes
    ----------
    geometry, mask, geometry_origin
        As given (checked).
    depth_m : ndarray, shape (F, H, W), float64
        Metric z-depth [m]; NaN = no data (a new array on each access when the frames are units).
    """

    __slots__ = ("geometry", "mask", "geometry_origin", "_depth", "_units")

    def __init__(self, geometry: CaptureGeometry, depth_m, mask: np.ndarray | None = None,
                 geometry_origin: str = "measured"):
        if not isinstance(geometry, CaptureGeometry):
            raise ValueError(f"geometry must be a CaptureGeometry, got {type(geometry).__name__}")
        g = geometry
        d = np.asarray(depth_m)
        if d.ndim != 3 or d.shape[1:] != (g.height, g.width) or d.shape[0] < 1:
            raise ValueError(f"{g.id}: depth_m must have shape (frames >= 1, {g.height}, {g.width}), got {d.shape}")
        if not np.issubdtype(d.dtype, np.floating):
            raise ValueError(f"{g.id}: depth_m must be floating-point metres (NaN = no data), got dtype {d.dtype}")
        d = d.astype(np.float64, copy=False)
        if np.isinf(d).any():
            raise ValueError(f"{g.id}: depth_m has infinite values (no data must be NaN)")
        with np.errstate(invalid="ignore"):
            if (d <= 0).any():
                raise ValueError(f"{g.id}: depth_m has values <= 0 (no data must be NaN)")
            top = np.nanmax(d) if np.isfinite(d).any() else 0.0
        if top > 100.0:
            raise ValueError(f"{g.id}: depth_m holds values up to {top:.1f}: depth must be in metres")
        self._set(g, d, None, mask, geometry_origin)

    def _set(self, g, depth, units, mask, geometry_origin) -> None:
        """Store the frames (metres or units, already checked) and check the mask and the origin."""
        self.geometry, self._depth, self._units = g, depth, units
        if geometry_origin not in GEOMETRIES:
            raise ValueError(f"{g.id}: geometry_origin must be 'measured' or 'fitted', got {geometry_origin!r}")
        self.geometry_origin = geometry_origin
        if mask is not None:
            m = np.asarray(mask)
            if m.dtype != bool or m.shape != (g.height, g.width):
                raise ValueError(f"{g.id}: mask must be a boolean image of shape ({g.height}, {g.width}), "
                                 f"got {m.dtype} {m.shape}")
            if not m.any():
                raise ValueError(f"{g.id}: mask selects no pixel")
            mask = m
        self.mask = mask

    def __repr__(self) -> str:
        return (f"CaptureData({self.id!r}, {self.n_frames} frames {self.geometry.width}x{self.geometry.height}, "
                f"mask={'none' if self.mask is None else int(self.mask.sum())} px, {self.geometry_origin})")

    # -- the frames ---------------------------------------------------------------------------
    @property
    def depth_m(self) -> np.ndarray:
        """Metric z-depth (F, H, W) float64 [m], NaN = no data."""
        if self._units is not None:
            return units_to_depth_m(self._units, self.geometry.depth_scale)
        return self._depth

    def frame_m(self, index: int) -> np.ndarray:
        """Frame ``index``'s metric z-depth (H, W) float64 [m], NaN = no data."""
        if self._units is not None:
            return units_to_depth_m(self._units[index], self.geometry.depth_scale)
        return self._depth[index]

    def pixels_m(self, mask: np.ndarray) -> np.ndarray:
        """Every frame's metric z-depth at the pixels of ``mask`` (bool (H, W)): (F, mask.sum()) float64 [m]."""
        if self._units is not None:
            return units_to_depth_m(self._units[:, mask], self.geometry.depth_scale)
        return self._depth[:, mask]

    def interior(self, max_depth_m: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
        """The pixels that see the target's interior, and the true depth.

        Interior = the geometry's ``interior`` region (not an edge band, the left invalid band or the
        background), a finite true depth below ``max_depth_m`` (beyond it the render is the empty scene),
        and inside :attr:`mask` when there is one: the pixels on which per-capture statistics (lag
        covariances, temporal and static sigmas) are read.

        Returns
        -------
        mask : ndarray of bool, shape (H, W)
        z_true_m : ndarray, shape (H, W), float64
            The rendered true z-depth [m] of every pixel (NaN where the target is not hit).
        """
        max_depth_m = check_positive_scalar(max_depth_m, f"{self.id}: max_depth_m", unit=" m")
        g = self.geometry
        z_true_m, _ = g.render()
        m = (g.regions() == REGION_INTERIOR) & np.isfinite(z_true_m) & (z_true_m < max_depth_m)
        if self.mask is not None:
            m &= self.mask
        return m, z_true_m

    def has_data(self) -> np.ndarray:
        """bool (F, H, W): True where a frame has a depth."""
        if self._units is not None:
            return self._units != 0
        return np.isfinite(self._depth)

    def with_geometry(self, geometry: CaptureGeometry, mask: np.ndarray | None) -> "CaptureData":
        """The same frames (shared, not copied) under another geometry of the same camera and size, e.g. a
        capture's pixels in one depth band as a capture of their own, with ``mask``."""
        g0 = self.geometry
        if not isinstance(geometry, CaptureGeometry) or (geometry.height, geometry.width) != (g0.height, g0.width) \
                or geometry.depth_scale != g0.depth_scale:
            raise ValueError(f"{self.id}: the new geometry must be a CaptureGeometry of the same image size and "
                             "depth scale")
        out = CaptureData.__new__(CaptureData)
        out._set(geometry, self._depth, self._units, mask, self.geometry_origin)
        return out

    @property
    def is_fitted(self) -> bool:
        """True when the target's pose comes from a plane fit to the frames."""
        return self.geometry_origin == "fitted"

    @property
    def plane(self):
        """The target's plane (:class:`noise_model.analysis.planes.Plane`: n . p = offset_m [m], n_z > 0)."""
        from .planes import target_plane

        return target_plane(self.geometry.target)

    def target_pixels(self) -> np.ndarray:
        """bool (H, W): the pixels whose statistics count: the mask, else every pixel the target covers."""
        if self.mask is not None:
            return self.mask.copy()
        z, _ = self.geometry.render()
        return np.isfinite(z)

    @property
    def id(self) -> str:
        return self.geometry.id

    @property
    def n_frames(self) -> int:
        return int((self._units if self._units is not None else self._depth).shape[0])

    @classmethod
    def from_capture_entry(cls, camera: Mapping, capture: Mapping, depth_units: np.ndarray,
                           mask: np.ndarray | None = None) -> "CaptureData":
        """A capture from its captures.json entry (:func:`capture_geometry`, its ``geometry`` key), its
        frames in depth units (:meth:`from_units`) and its mask, bool (H, W) or None."""
        origin = capture.get("geometry") if isinstance(capture, Mapping) else None
        return cls.from_units(capture_geometry(camera, capture), depth_units, mask=mask,
                              geometry_origin="measured" if origin is None else origin)

    @classmethod
    def from_units(cls, geometry: CaptureGeometry, depth_units: np.ndarray, *, mask: np.ndarray | None = None,
                   geometry_origin: str = "measured") -> "CaptureData":
        """Frames from depth units: depth_m = units * depth_scale, 0 -> NaN.

        Parameters
        ----------
        geometry : CaptureGeometry
        depth_units : ndarray, shape (F, H, W) or (H, W), unsigned or signed integers
            Depth units of ``geometry.depth_scale`` (uint16 as recorded); 0 = no data.
        mask : ndarray of bool, shape (H, W), optional
        geometry_origin : str
            "measured" or "fitted" (see the class).
        """
        if not isinstance(geometry, CaptureGeometry):
            raise ValueError(f"geometry must be a CaptureGeometry, got {type(geometry).__name__}")
        a = np.asarray(depth_units)
        if not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"{geometry.id}: depth units must be integers (uint16), got dtype {a.dtype}")
        if a.ndim == 2:
            a = a[None]
        if a.ndim != 3 or a.shape[1:] != (geometry.height, geometry.width):
            raise ValueError(f"{geometry.id}: depth units must have shape (frames, {geometry.height}, "
                             f"{geometry.width}), got {np.asarray(depth_units).shape}")
        if a.size and int(a.min()) < 0:
            raise ValueError(f"{geometry.id}: depth units must be >= 0, got {int(a.min())}")
        if a.shape[0] < 1:
            raise ValueError(f"{geometry.id}: depth units have no frames")
        top = int(a.max()) * geometry.depth_scale if a.size else 0.0
        if top > 100.0:
            raise ValueError(f"{geometry.id}: depth units reach {top:.1f} m: depth must be in metres (check "
                             "depth_scale)")
        if int(a.max()) <= 65535 and a.dtype != np.uint16:
            a = a.astype(np.uint16)
        units = np.array(a, copy=True)                       # the caller's array may change later
        units.flags.writeable = False
        out = cls.__new__(cls)
        out._set(geometry, None, units, mask, geometry_origin)
        return out


def units_to_depth_m(depth_units: np.ndarray, depth_scale: float) -> np.ndarray:
    """Metric depth (same shape, float64) [m] of depth units: units * depth_scale, NaN where 0 (no data).

    No checks: ``depth_units`` is a non-negative integer array, ``depth_scale`` [m/unit] a positive float
    (:meth:`CaptureData.from_units` checks them; a simulation's uint16 frames are so by construction).
    """
    a = np.asarray(depth_units)
    d = a.astype(np.float64) * depth_scale
    d[a == 0] = np.nan
    return d



def check_captures(captures, name: str = "real", *, allow_empty: bool = False) -> list:
    """Validate real captures: a CaptureData or a sequence of them, with distinct ids.

    Returns
    -------
    list of CaptureData

    Raises
    ------
    ValueError
        An item is not a CaptureData, two share an id, or (unless ``allow_empty``) there is none.
    """
    items = [captures] if isinstance(captures, CaptureData) else list(captures)
    if not items and not allow_empty:
        raise ValueError(f"no {name} captures")
    for k, c in enumerate(items):
        if not isinstance(c, CaptureData):
            raise ValueError(f"{name}[{k}] must be a noise_model.analysis.capture_data.CaptureData, "
                             f"got {type(c).__name__}")
    ids = [c.id for c in items]
    if len(set(ids)) != len(ids):
        raise ValueError(f"{name} captures must have distinct ids")
    return items



def simulate_capture(geometry: CaptureGeometry, n_frames: int, rng: np.random.Generator, model: SensorModel = D435,
                     effects=()) -> np.ndarray:
    """The reference simulation of a capture, plus effects; uint16 depth units (F, H, W).

    :func:`noise_model.sim.targets.simulate_target` (same draws, same far-pixel rule) with the
    capture's ``capture_id`` and nominal ``regions`` (``geometry.regions(model=model)``, read only)
    added to the effects' context (see the module docstring).

    Parameters
    ----------
    geometry : CaptureGeometry
    n_frames : int
        Frames, >= 1.
    rng : numpy.random.Generator
        The only source of randomness (effects draw from it too).
    model : SensorModel
        Axial and lateral noise of the reference simulation (the paper's D435 by default).
    effects : sequence of callables
        ``effect(z, theta, rng, context) -> z`` (:mod:`noise_model.sim.effects`), applied in the order given.

    Returns
    -------
    ndarray, shape (n_frames, height, width), uint16
    """
    effects = tuple(effects or ())
    context = None
    if isinstance(geometry, CaptureGeometry) and isinstance(model, SensorModel) and model.family == "disparity" \
            and model.frame_fx_px is None:
        model = model.with_focal(float(geometry.K[0, 0]))      # its sigma_z in metres needs the frame's f
    if effects and isinstance(geometry, CaptureGeometry) and isinstance(model, SensorModel):
        regions = geometry.regions(model=model)
        regions.flags.writeable = False
        context = {"capture_id": geometry.id, "regions": regions}
    return simulate_target(geometry, n_frames, rng, model, effects, context)
