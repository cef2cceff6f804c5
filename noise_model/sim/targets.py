"""D435 simulation: planar targets rendered with the reference simulation of the paper's model.

Conventions are those of the capture-set format (``shared/specs/capture-set.md``): camera frame x
right, y down, z forward; depth is z, not ray length. A target's centre is c = (0, 0, distance_m) and
its axes are the columns of R = R_y(yaw) R_x(pitch); a board spans c + s R e_x + t R e_y for
|s| <= width/2, |t| <= height/2, its normal is R e_z; a wall is the unbounded plane.

The reference simulation, per frame and pixel: z = z_true + N(0, sigma_z(z_true, theta)^2),
independent per pixel and frame; each frame the board's left edge shifts along the board's x axis by
N(0, sigma_L^2) and its right edge by N(0, sigma_R^2); the result is round(z / depth_scale) as uint16,
0 where there is no hit or z <= 0. Nothing else: the effects the paper leaves out belong elsewhere.
"""

from __future__ import annotations

import math

import numpy as np

from ..checks import check_intrinsics, check_positive_scalar
from ..d435 import D435, SensorModel, _axial_sigma_unchecked

__all__ = ["target_rotation", "camera_extrinsics", "render_planar_target", "render_floor", "simulate_target_frames"]


def target_rotation(yaw_deg: float = 0.0, pitch_deg: float = 0.0) -> np.ndarray:
    """R = R_y(yaw) R_x(pitch): the target's axes in the camera frame (columns), shape (3, 3)."""
    a, b = math.radians(float(yaw_deg)), math.radians(float(pitch_deg))
    Ry = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(b), -math.sin(b)], [0.0, math.sin(b), math.cos(b)]])
    return Ry @ Rx


def camera_extrinsics(position_m=(0.0, 0.0, 0.45), pitch_down_deg: float = 30.0, yaw_deg: float = 0.0) -> np.ndarray:
    """T_map_cam of a camera looking along the map's heading ``yaw_deg``, pitched down.

    Map frame: x forward, y left, z up. Camera frame: x right, y down, z forward. With yaw 0 and
    pitch 0 the optical axis is map +x, image right is map -y and image down is map -z.

    Parameters
    ----------
    position_m : (3,) array_like
        Camera centre in the map frame [m].
    pitch_down_deg : float
        Downward pitch of the optical axis [deg].
    yaw_deg : float
        Heading about map z [deg].

    Returns
    -------
    ndarray, shape (4, 4)
    """
    p, y = math.radians(float(pitch_down_deg)), math.radians(float(yaw_deg))
    cp, sp, cy, sy = math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    z_cam = np.array([cp * cy, cp * sy, -sp])       # optical axis
    x_cam = np.array([sy, -cy, 0.0])                # image right
    y_cam = np.cross(z_cam, x_cam)                  # image down
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x_cam, y_cam, z_cam])
    T[:3, 3] = np.asarray(position_m, dtype=np.float64)
    return T


def _rays(K, width, height):
    u = (np.arange(width) - K[0, 2]) / K[0, 0]
    v = (np.arange(height) - K[1, 2]) / K[1, 1]
    return np.broadcast_to(u[None, :], (height, width)), np.broadcast_to(v[:, None], (height, width))


def render_planar_target(K, width: int, height: int, distance_m: float, yaw_deg: float = 0.0,
                         pitch_deg: float = 0.0, kind: str = "wall", width_m: float | None = None,
                         height_m: float | None = None, background_m: float | None = None,
                         edge_shift_m: tuple[float, float] = (0.0, 0.0)):
    """Noise-free z-depth and incidence angle of a planar target.

    Parameters
    ----------
    K : array_like, shape (3, 3)
        Intrinsics [px].
    width, height : int
        Image size [px].
    distance_m : float
        z of the target's centre [m].
    yaw_deg, pitch_deg : float
        Target rotation (capture-set convention) [deg].
    kind : {"wall", "board"}
        Unbounded plane, or a ``width_m`` x ``height_m`` rectangle.
    background_m : float, optional
        A fronto-parallel wall at this z behind a board; None = nothing there.
    edge_shift_m : (float, float)
        Shift of the board's left and right edges along its own x axis [m] (lateral noise).

    Returns
    -------
    z_true : ndarray, shape (height, width) [m]
        NaN where the ray hits nothing.
    theta : ndarray, shape (height, width) [rad]
        Angle between the hit surface's normal and the optical axis; NaN where nothing is hit.
    """
    K = check_intrinsics(K)
    D = check_positive_scalar(distance_m, "distance_m", upper=100.0, unit=" m")
    if kind not in ("wall", "board"):
        raise ValueError(f"kind must be 'wall' or 'board', got {kind!r}")
    R = target_rotation(yaw_deg, pitch_deg)
    n = R[:, 2]
    rx, ry = _rays(K, int(width), int(height))
    denom = n[0] * rx + n[1] * ry + n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (n[2] * D) / denom          # n . c / n . d with c = (0, 0, D), d = (rx, ry, 1)
    hit = np.isfinite(t) & (t > 0)
    if kind == "board":
        if width_m is None or height_m is None:
            raise ValueError("a board needs width_m and height_m")
        w = check_positive_scalar(width_m, "width_m", upper=100.0, unit=" m")
        h = check_positive_scalar(height_m, "height_m", upper=100.0, unit=" m")
        px, py, pz = t * rx, t * ry, t - D
        s = px * R[0, 0] + py * R[1, 0] + pz * R[2, 0]
        tt = px * R[0, 1] + py * R[1, 1] + pz * R[2, 1]
        dl, dr = (float(e) for e in edge_shift_m)
        hit &= (s >= -w / 2 + dl) & (s <= w / 2 + dr) & (np.abs(tt) <= h / 2)
    z = np.where(hit, t, np.nan)
    theta = np.where(hit, math.atan2(math.hypot(n[0], n[1]), abs(n[2])), np.nan)
    if background_m is not None:
        bg = check_positive_scalar(background_m, "background_m", upper=100.0, unit=" m")
        behind = ~hit
        z = np.where(behind, bg, z)
        theta = np.where(behind, 0.0, theta)
    return z, theta


def render_floor(K, width: int, height: int, T_map_cam, floor_z: float = 0.0, max_range_m: float = 10.0):
    """Noise-free z-depth and incidence angle of the horizontal floor z = ``floor_z`` (map frame).

    Parameters
    ----------
    K : array_like, shape (3, 3)
        Intrinsics [px].
    width, height : int
        Image size [px].
    T_map_cam : array_like, shape (4, 4)
        Camera pose: maps camera-frame points into the map frame (z up).
    floor_z : float
        Height of the floor [m].
    max_range_m : float
        Hits farther than this (z-depth) are no data [m].

    Returns
    -------
    z_true, theta : ndarray, shape (height, width)
        z-depth [m] and angle between the floor normal and the optical axis [rad]; NaN where the
        ray misses the floor.
    """
    K = check_intrinsics(K)
    T = np.asarray(T_map_cam, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    rx, ry = _rays(K, int(width), int(height))
    dz = R[2, 0] * rx + R[2, 1] * ry + R[2, 2]          # map-z change per unit of camera z
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (float(floor_z) - t[2]) / dz
    hit = np.isfinite(z) & (z > 0) & (z <= float(max_range_m))
    theta = math.acos(min(1.0, abs(R[2, 2])))
    return np.where(hit, z, np.nan), np.where(hit, theta, np.nan)


def simulate_target_frames(K, width: int, height: int, distance_m: float, n_frames: int,
                           rng: np.random.Generator, *, yaw_deg: float = 0.0, pitch_deg: float = 0.0,
                           kind: str = "wall", width_m: float | None = None, height_m: float | None = None,
                           background_m: float | None = None, depth_scale: float = 0.001,
                           model: SensorModel = D435, effects=()) -> np.ndarray:
    """Frames of a planar target under the reference simulation of the paper's model.

    Parameters
    ----------
    rng : numpy.random.Generator
        Required, so that every simulation is seeded by its caller.
    n_frames : int
        Number of frames.
    effects : sequence of callables, optional
        Depth effects (:mod:`noise_model.sim.effects`), ``effect(z, theta, rng, context) -> z``, applied in
        order to each frame's metric depth after the reference noise and before the rounding, through
        the hook of :func:`noise_model.sim.scene.add_noise` (context: ``K``, ``width``, ``height``,
        ``index`` = frame, ``depth_scale``, ``z_true``, ``baseline_m`` = the model's); true depths
        beyond the uint16 range are then no data. With no effects the frames, and the draws from
        ``rng``, are those of the reference simulation alone.
        :func:`noise_model.analysis.capture_data.simulate_capture` does the same for a capture with a richer
        context (capture id, regions).
    (others as :func:`render_planar_target`)

    Returns
    -------
    ndarray, shape (n_frames, height, width), uint16
        Depth units of ``depth_scale`` [m]; 0 = no data.
    """
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator (seed it: np.random.default_rng(seed))")
    scale = check_positive_scalar(depth_scale, "depth_scale", upper=0.1, unit=" m per unit")
    nf = int(n_frames)
    if nf < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    effects = tuple(effects or ())
    for k, e in enumerate(effects):
        if not callable(e):
            raise ValueError(f"effects[{k}] is not callable: {e!r}")
    out = np.zeros((nf, int(height), int(width)), dtype=np.uint16)
    static = None
    for f in range(nf):
        if kind == "board":
            shift = (rng.normal(0.0, model.sigma_L), rng.normal(0.0, model.sigma_R))
            z_true, theta = render_planar_target(K, width, height, distance_m, yaw_deg, pitch_deg, kind, width_m,
                                                 height_m, background_m, shift)
        else:
            if static is None:
                static = render_planar_target(K, width, height, distance_m, yaw_deg, pitch_deg, kind, width_m,
                                              height_m, background_m)
            z_true, theta = static
        if effects:
            from .scene import add_noise

            far = z_true > min(100.0, 65535 * scale)       # beyond what a uint16 depth can hold: no data
            if far.any():
                z_true, theta = np.where(far, np.nan, z_true), np.where(far, np.nan, theta)
            out[f] = add_noise(z_true, theta, rng, model, effects, scale,
                               {"K": check_intrinsics(K), "index": f, "baseline_m": model.baseline_m})
            continue
        hit = np.isfinite(z_true)
        sigma = np.zeros_like(z_true)
        sigma[hit] = _axial_sigma_unchecked(z_true[hit], theta[hit], model)
        z = z_true + rng.normal(0.0, 1.0, z_true.shape) * sigma
        units = np.where(hit & (z > 0), np.round(z / scale), 0.0)
        out[f] = np.clip(units, 0, 65535).astype(np.uint16)
    return out
