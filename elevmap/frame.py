"""The frame record every source yields: one depth image with everything needed to map it.

Data flows one way: source -> :class:`Frame` -> points and covariances -> map -> consumers/viewer.
Sources live in :mod:`elevmap.sources`; this module holds only the record and its validation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from noise_model.checks import check_depth, check_intrinsics, check_pose_cov, check_transform
from noise_model.geometry import depth_to_metres

__all__ = ["Frame"]


@dataclass(frozen=True)
class Frame:
    """One depth frame.

    Attributes
    ----------
    depth : ndarray, shape (H, W)
        uint16 depth units (``depth_scale`` [m/unit], 0 = no data) or float32/float64 metres.
    K : ndarray, shape (3, 3)
        Depth-stream intrinsics [px] (pinhole; the D435 depth stream is rectified).
    depth_scale : float or None
        Metres per unit of uint16 depth; None for float depth.
    stamp : float
        Time [s] (sensor or recording time; monotonic within a source).
    T_map_cam : ndarray, shape (4, 4), or None
        Camera pose: maps camera-frame points into the map frame; None when the source has no
        pose (then the camera is static: the identity, unless a pose file is given).
    pose_cov : ndarray, shape (6, 6), or None
        Covariance of that pose (translation then rotation, map frame, about the camera centre).
    camera : str
        Name of the camera that took it (several cameras may feed one map).
    index : int
        Frame number within its source.
    truth : dict
        Optional ground truth from a simulator, e.g. ``{"height": callable or array}``.
    """

    depth: np.ndarray
    K: np.ndarray
    depth_scale: float | None
    stamp: float
    T_map_cam: np.ndarray | None = None
    pose_cov: np.ndarray | None = None
    camera: str = "camera"
    index: int = 0
    truth: dict = field(default_factory=dict)

    def __post_init__(self):
        d, scale = check_depth(self.depth, self.depth_scale, "Frame.depth")
        object.__setattr__(self, "depth", d)
        object.__setattr__(self, "depth_scale", scale if d.dtype == np.uint16 else None)
        object.__setattr__(self, "K", check_intrinsics(self.K, "Frame.K"))
        if self.T_map_cam is not None:
            object.__setattr__(self, "T_map_cam", check_transform(self.T_map_cam, "Frame.T_map_cam"))
        if self.pose_cov is not None:
            object.__setattr__(self, "pose_cov", check_pose_cov(self.pose_cov, "Frame.pose_cov"))
        s = float(self.stamp)
        if not math.isfinite(s):
            raise ValueError(f"Frame.stamp must be finite, got {self.stamp!r}")
        object.__setattr__(self, "stamp", s)

    @property
    def height(self) -> int:
        return self.depth.shape[0]

    @property
    def width(self) -> int:
        return self.depth.shape[1]

    def depth_m(self) -> np.ndarray:
        """Depth in metres (float64), NaN where there is no data."""
        return depth_to_metres(self.depth, self.depth_scale)

    def with_pose(self, T_map_cam, pose_cov=None) -> "Frame":
        """A copy with another pose."""
        return replace(self, T_map_cam=T_map_cam, pose_cov=pose_cov)
