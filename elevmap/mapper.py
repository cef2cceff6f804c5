"""Depth frames -> noise model -> elevation map: the mapper a legged robot runs per frame.

One call per frame: :func:`noise_model.depth_to_map_points` (numba: deprojection, incidence angles,
depth edges, D435 covariances in the map frame with pose uncertainty) then the map's fusion kernel
(numba) and, with the sensor origin known, its visibility clean-up. Several cameras feed one map, each
with its own intrinsics, extrinsics and noise model (ANYmal carries four D435s).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

import noise_model as nm
from noise_model.checks import check_intrinsics, check_positive_scalar, check_transform
from noise_model.d435 import SensorModel
from noise_model.kernels import MAX_DEPTH_M, MIN_DEPTH_M
from noise_model.valid_margin import (DEFAULT_VALID_MARGIN_PX, check_valid_margin_px, drop_valid_margin,
                                     drop_valid_margin_reference)

from .map.elevation_map import ElevationMap

__all__ = ["Camera", "Mapper"]


@dataclass
class Camera:
    """One depth camera on the robot.

    Attributes
    ----------
    name : str
    K : ndarray, shape (3, 3)
        Depth-stream intrinsics [px].
    width, height : int
        Image size [px].
    T_base_cam : ndarray, shape (4, 4)
        Extrinsics: maps camera-frame points into the robot's base frame.
    model : noise_model.SensorModel
        Its noise model (the paper's D435 by default; a user's own fit otherwise).
    depth_scale : float or None
        Metres per unit of its uint16 depth (None for float metres).
    min_depth_m, max_depth_m : float
        Valid depth range [m].
    variance_model : callable, optional
        Another point-noise model in place of the paper's (for comparisons):
        ``f(points_cam (N, 3), T_map_cam (4, 4), pose_cov (6, 6) or None) -> (height_var (N,),
        horizontal_cov (N, 3))`` in the map frame [m^2]. None: the paper's model (numba kernel).
    bin_at_plane : bool
        Place each point's x, y where its ray meets the local plane (in a window of two surfaces: the
        nearer of that and the surface median), as :func:`noise_model.depth_to_map_points` does by default;
        False: at the measured depth.
    valid_margin_px : int
        Pixels with data within this many columns of a no-data pixel or of the image's left or right
        border are dropped before the noise model (:mod:`noise_model.valid_margin`): there the stereo
        matcher's window was cut short and edge fattening puts near-surface points beyond hidden step
        edges. 0 keeps every pixel (a camera that is not a stereo matcher, or depth already filtered).
    """

    name: str
    K: np.ndarray
    width: int
    height: int
    T_base_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    model: SensorModel = nm.D435
    depth_scale: float | None = 0.001
    min_depth_m: float = MIN_DEPTH_M
    max_depth_m: float = MAX_DEPTH_M
    variance_model: object = None
    bin_at_plane: bool = True
    valid_margin_px: int = DEFAULT_VALID_MARGIN_PX

    def __post_init__(self):
        self.K = check_intrinsics(self.K, f"camera {self.name!r} K")
        self.T_base_cam = check_transform(self.T_base_cam, f"camera {self.name!r} T_base_cam")
        if int(self.width) < 1 or int(self.height) < 1:
            raise ValueError(f"camera {self.name!r}: image size must be positive, got {self.width}x{self.height}")
        self.width, self.height = int(self.width), int(self.height)
        if self.depth_scale is not None:
            self.depth_scale = check_positive_scalar(self.depth_scale, "depth_scale", upper=0.1, unit=" m per unit")
        if not isinstance(self.model, SensorModel):
            raise ValueError(f"camera {self.name!r}: model must be a noise_model.SensorModel")
        if self.variance_model is not None and not callable(self.variance_model):
            raise ValueError(f"camera {self.name!r}: variance_model must be callable")
        if not isinstance(self.bin_at_plane, (bool, np.bool_)):
            raise ValueError(f"camera {self.name!r}: bin_at_plane must be True or False, got {self.bin_at_plane!r}")
        self.valid_margin_px = check_valid_margin_px(self.valid_margin_px, f"camera {self.name!r}: valid_margin_px")


class Mapper:
    """Fuses depth frames of one or more cameras into an :class:`ElevationMap`.

    Parameters
    ----------
    emap : ElevationMap, optional
        The map to feed (a default 8 m x 8 m map at 0.04 m when None).
    cameras : iterable of Camera, optional
        Cameras; more can be added with :meth:`add_camera`.
    nthreads : int, optional
        numba threads (numba's setting by default).

    Examples
    --------
    >>> mapper = Mapper()
    >>> mapper.add_camera(Camera("front", nm.D435.intrinsics(848, 480), 848, 480, T_base_cam))  # doctest: +SKIP
    >>> mapper.integrate("front", depth_u16, T_map_base=T, pose_cov=P, stamp=t)                  # doctest: +SKIP
    >>> mapper.map.height_at([1.0, 0.0])                                                         # doctest: +SKIP
    """

    def __init__(self, emap: ElevationMap | None = None, cameras=(), *, nthreads: int | None = None):
        self.map = ElevationMap() if emap is None else emap
        if not isinstance(self.map, ElevationMap):
            raise ValueError("emap must be an elevmap.ElevationMap")
        self.nthreads = nthreads
        self.cameras: dict[str, Camera] = {}
        self._workspaces: dict[str, nm.Workspace] = {}
        self.last_timing: dict = {}
        self.last_points: nm.MapPoints | None = None     # the last frame's points (views, until the next frame)
        for cam in cameras:
            self.add_camera(cam)

    def add_camera(self, camera: Camera) -> None:
        """Register a camera (its name must be new)."""
        if not isinstance(camera, Camera):
            raise ValueError("add_camera takes an elevmap.Camera")
        if camera.name in self.cameras:
            raise ValueError(f"a camera named {camera.name!r} is already registered")
        self.cameras[camera.name] = camera
        self._workspaces[camera.name] = nm.Workspace(camera.height, camera.width)

    def integrate(self, camera: str, depth, *, T_map_cam=None, T_map_base=None, pose_cov=None,
                  stamp: float | None = None, impl: str = "numba") -> dict:
        """Fuse one depth frame of ``camera`` into the map.

        Parameters
        ----------
        camera : str
            Name of a registered camera.
        depth : array_like, shape (height, width)
            uint16 depth units (the camera's ``depth_scale``) or float metres.
        T_map_cam, T_map_base : array_like, shape (4, 4)
            Exactly one: the camera's pose in the map frame, or the robot base's pose (then
            T_map_cam = T_map_base @ camera.T_base_cam).
        pose_cov : array_like, shape (6, 6), optional
            Covariance of the camera pose (translation then rotation, map frame, about the camera
            centre; see :func:`noise_model.to_map_frame`).
        stamp : float, optional
            Frame time [s].
        impl : {"numba", "numpy"}
            The compiled kernels or their NumPy references.

        Returns
        -------
        dict
            points, cells updated and cleared, and the time of each stage [ms].
        """
        if camera not in self.cameras:
            raise ValueError(f"unknown camera {camera!r}; registered: {sorted(self.cameras)}")
        cam = self.cameras[camera]
        if (T_map_cam is None) == (T_map_base is None):
            raise ValueError("give exactly one of T_map_cam and T_map_base")
        if T_map_cam is None:
            T_map_cam = check_transform(T_map_base, "T_map_base") @ cam.T_base_cam
        T_map_cam = check_transform(T_map_cam, "T_map_cam")
        d = np.asarray(depth)
        if d.shape != (cam.height, cam.width):
            raise ValueError(f"camera {camera!r} gives {cam.height}x{cam.width} depth, got shape {d.shape}")
        scale = cam.depth_scale if d.dtype == np.uint16 else None
        if impl not in ("numba", "numpy"):
            raise ValueError(f"impl must be 'numba' or 'numpy', got {impl!r}")
        t0 = time.perf_counter()
        if cam.valid_margin_px and d.dtype in (np.uint16, np.float32, np.float64):
            d = (drop_valid_margin(d, cam.valid_margin_px, nthreads=self.nthreads) if impl == "numba"
                 else drop_valid_margin_reference(d, cam.valid_margin_px))
        # a model that states one frame's whole error (SensorModel.frame_noise) is fused with it
        model = cam.model.for_map()
        kwargs = dict(depth_scale=scale, model=model, min_depth_m=cam.min_depth_m, max_depth_m=cam.max_depth_m,
                      bin_at_plane=cam.bin_at_plane)
        if impl == "numba":
            pts = nm.depth_to_map_points(d, cam.K, T_map_cam, pose_cov, workspace=self._workspaces[camera],
                                         nthreads=self.nthreads, **kwargs)
        else:
            pts = nm.depth_to_map_points_reference(d, cam.K, T_map_cam, pose_cov, **kwargs)
        if cam.variance_model is not None:
            points_cam = (pts.points_map - T_map_cam[:3, 3]) @ T_map_cam[:3, :3]
            hvar, hcov = cam.variance_model(points_cam, T_map_cam, pose_cov)
            hvar = np.asarray(hvar, dtype=np.float64)
            hcov = np.asarray(hcov, dtype=np.float64)
            if hvar.shape != (len(points_cam),) or hcov.shape != (len(points_cam), 3):
                raise ValueError(f"camera {camera!r}: variance_model returned shapes {hvar.shape}, {hcov.shape}")
            if not (np.all(np.isfinite(hvar)) and np.all(hvar > 0)):
                raise ValueError(f"camera {camera!r}: variance_model returned non-finite or non-positive variances")
            pts = nm.MapPoints(pts.points_map, hvar, hcov, pts.pixel)
        t1 = time.perf_counter()
        if stamp is None:
            stamp = float(self.map.frames)
        stamp = float(stamp)
        if not np.isfinite(stamp):
            raise ValueError(f"stamp must be finite, got {stamp!r}")
        # the noise kernel counted the values out of the map's range as it wrote them: with none (and no
        # variance_model, whose points are not counted) the map need not check them again
        # the camera's model states its per-frame error (noise_model.SensorModel.frame_error): the map takes
        # each frame's information per cell from it; a variance_model replaces the model's noise altogether
        frame_error = (model.frame_error(float(cam.K[0, 0]))
                       if cam.variance_model is None and model.has_frame_error else None)
        stats = self.map._update_validated(pts.points_map, pts.height_var, pts.horizontal_cov, stamp,
                                           T_map_cam[:3, 3].copy(), impl, check=pts.n_outside != 0,
                                           frame_error=frame_error)
        t2 = time.perf_counter()
        stats.update(points=int(len(pts.pixel)), noise_ms=1e3 * (t1 - t0), fusion_ms=1e3 * (t2 - t1),
                     total_ms=1e3 * (t2 - t0))
        self.last_timing = stats
        self.last_points = pts
        return stats
