"""Scenes of planes for the physical D435: walls, boards, floors at any orientation, and their ray cast.

The validation against real recordings (:mod:`.realdata`) needs their geometry exactly: a wall fitted
to a real frame (any normal, not only the vertical targets of ``noise_model.sim.Scene``), a floor
under a camera with pitch and roll, a panel ending at a vertical edge. :class:`PlanarScene` holds such
surfaces and :func:`render_planar` ray-casts them with the signature of
``noise_model.sim.render_depth`` (so ``StereoD435(renderer=render_planar)`` renders them).

Frames and units
----------------
Surfaces are given in the scene's frame (the "map" frame of :class:`.pipeline.StereoD435`, where the
materials are evaluated); a camera pose ``T_map_cam`` maps camera-frame points (x right, y down,
z forward) into it. Lengths in metres, angles in radians unless named ``_deg``.

Surfaces
--------
A :class:`PlaneSurface` is the plane n . p = n . c through the point c with unit normal n; with a
width and a height it is the rectangle c + s a + t b, |s| <= width / 2, |t| <= height / 2, with a the
unit ``u_axis`` (made orthogonal to n) and b = n x a. Surfaces are two-sided. A ray p = o + t d with
d = R (u', v', 1) (u' = (u - cx) / fx, v' = (v - cy) / fy: t is the z-depth) meets a plane at
t = n . (c - o) / (n . d); the pixel keeps the nearest hit with 0 < t <= ``max_range_m``. For a
concave corner (a room's wall and floor, two walls) the nearest hit of the two unbounded planes is the
visible one, so the corner needs no bounds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["PlaneSurface", "PlanarScene", "render_planar", "plane_from_camera"]


def _unit(v, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or not np.linalg.norm(a) > 0:
        raise ValueError(f"{name} must be a finite, non-zero 3-vector, got {v!r}")
    return a / np.linalg.norm(a)


@dataclass(frozen=True)
class PlaneSurface:
    """An unbounded plane, or a rectangle on it (module docstring).

    Attributes
    ----------
    normal : (3,) array_like
        Normal of the plane (normalised here), scene frame.
    point_m : (3,) array_like
        A point of the plane [m]; the rectangle's centre when it is bounded.
    width_m, height_m : float or None
        Extent of the rectangle along ``u_axis`` and along normal x u_axis [m]; both None = unbounded.
    u_axis : (3,) array_like or None
        Direction of the rectangle's width (its component along the normal is removed); default: the
        scene's x axis, or y when the normal is along x.
    name : str
        Named in error messages.
    """

    normal: tuple
    point_m: tuple
    width_m: float | None = None
    height_m: float | None = None
    u_axis: tuple | None = None
    name: str = "plane"

    def __post_init__(self):
        n = _unit(self.normal, f"{self.name}: normal")
        c = np.asarray(self.point_m, dtype=np.float64).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise ValueError(f"{self.name}: point_m must be a finite 3-vector, got {self.point_m!r}")
        object.__setattr__(self, "normal", tuple(n.tolist()))
        object.__setattr__(self, "point_m", tuple(c.tolist()))
        if (self.width_m is None) != (self.height_m is None):
            raise ValueError(f"{self.name}: give both width_m and height_m (a rectangle) or neither (a plane)")
        if self.width_m is not None:
            for key in ("width_m", "height_m"):
                v = getattr(self, key)
                if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                    raise ValueError(f"{self.name}: {key} must be finite and > 0, got {v!r}")
            a = np.array([0.0, 1.0, 0.0]) if self.u_axis is None and abs(n[0]) > 0.9 else \
                np.array([1.0, 0.0, 0.0]) if self.u_axis is None else _unit(self.u_axis, f"{self.name}: u_axis")
            a = a - (a @ n) * n
            if not np.linalg.norm(a) > 1e-9:
                raise ValueError(f"{self.name}: u_axis must not be parallel to the normal")
            object.__setattr__(self, "u_axis", tuple((a / np.linalg.norm(a)).tolist()))

    @property
    def bounded(self) -> bool:
        return self.width_m is not None

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """The rectangle's in-plane unit axes (a, b = n x a)."""
        a = np.asarray(self.u_axis)
        return a, np.cross(np.asarray(self.normal), a)


@dataclass(frozen=True)
class PlanarScene:
    """Surfaces of a scene (scene frame); rendered by :func:`render_planar`.

    Attributes
    ----------
    surfaces : tuple of PlaneSurface
    """

    surfaces: tuple

    def __post_init__(self):
        s = tuple(self.surfaces)
        if not s:
            raise ValueError("a PlanarScene needs at least one surface")
        for k, x in enumerate(s):
            if not isinstance(x, PlaneSurface):
                raise ValueError(f"surface {k} must be a PlaneSurface, got {type(x).__name__}")
        object.__setattr__(self, "surfaces", s)


def render_planar(scene: PlanarScene, K, width: int, height: int, T_map_cam, max_range_m: float = 10.0,
                  return_index: bool = False):
    """Noise-free z-depth and incidence angle of a :class:`PlanarScene` (NumPy; module docstring).

    Parameters
    ----------
    scene : PlanarScene
    K : array_like, shape (3, 3)
        Intrinsics [px].
    width, height : int
        Image size [px].
    T_map_cam : array_like, shape (4, 4)
        Camera pose in the scene frame.
    max_range_m : float
        Hits farther than this z-depth are no data [m].
    return_index : bool
        Also return the index of the surface each pixel sees (-1: none).

    Returns
    -------
    z_true : ndarray, shape (height, width)
        z-depth of the nearest hit [m]; NaN = none.
    theta : ndarray, shape (height, width)
        Angle between the surface normal and the optical axis [rad], in [0, pi/2]; NaN where z is.
    index : ndarray, shape (height, width), int32
        Only with ``return_index``.
    """
    if not isinstance(scene, PlanarScene):
        raise ValueError(f"scene must be a PlanarScene, got {type(scene).__name__}")
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(T_map_cam, dtype=np.float64)
    if K.shape != (3, 3) or T.shape != (4, 4):
        raise ValueError("K must be 3x3 and T_map_cam 4x4")
    R, o = T[:3, :3], T[:3, 3]
    u = (np.arange(int(width)) - K[0, 2]) / K[0, 0]
    v = (np.arange(int(height)) - K[1, 2]) / K[1, 1]
    # ray direction per unit z-depth, scene frame: d = R (u', v', 1) = R[:, 0] u' + R[:, 1] v' + R[:, 2]
    best = np.full((int(height), int(width)), np.inf)
    index = np.full(best.shape, -1, np.int32)
    cos_axis = np.full(best.shape, np.nan)
    for k, s in enumerate(scene.surfaces):
        n = np.asarray(s.normal)
        nd = (n @ R[:, 1]) * v[:, None] + (n @ R[:, 0]) * u[None, :] + n @ R[:, 2]      # n . d
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (n @ (np.asarray(s.point_m) - o)) / nd
        hit = np.isfinite(t) & (t > 0) & (t <= max_range_m) & (t < best)
        if s.bounded and hit.any():
            a, b = s.axes()
            rel = o - np.asarray(s.point_m)                         # p - c = rel + t d
            da = (a @ R[:, 0]) * u[None, :] + (a @ R[:, 1]) * v[:, None] + a @ R[:, 2]
            db = (b @ R[:, 0]) * u[None, :] + (b @ R[:, 1]) * v[:, None] + b @ R[:, 2]
            with np.errstate(invalid="ignore"):
                hit &= (np.abs(a @ rel + t * da) <= s.width_m / 2) & (np.abs(b @ rel + t * db) <= s.height_m / 2)
        best = np.where(hit, t, best)
        index[hit] = k
        cos_axis[hit] = abs(n @ R[:, 2])
    z = np.where(np.isfinite(best), best, np.nan)
    theta = np.where(np.isfinite(z), np.arccos(np.minimum(1.0, cos_axis)), np.nan)
    return (z, theta, index) if return_index else (z, theta)


def plane_from_camera(normal_cam, offset_m: float, T_map_cam=None, name: str = "plane") -> PlaneSurface:
    """The unbounded plane n . p = offset (camera frame, e.g. a plane fitted to a real frame) in the scene frame.

    ``T_map_cam`` (default identity) maps camera-frame points into the scene frame.
    """
    n = _unit(normal_cam, f"{name}: normal")
    T = np.eye(4) if T_map_cam is None else np.asarray(T_map_cam, dtype=np.float64)
    p = n * float(offset_m)                                           # the plane's point nearest the camera
    return PlaneSurface(tuple(T[:3, :3] @ n), tuple(T[:3, :3] @ p + T[:3, 3]), name=name)
