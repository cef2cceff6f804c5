"""Walks: base trajectories over a scene, odometry drift, and the depth frames of a simulated walk.

Frames: map x forward, y left, z up [m]; base frame x forward, y left, z up; camera x right, y down,
z forward. ``T_a_b`` maps points of frame b into frame a. Pose covariances are 6 x 6, translation
[m^2] then rotation [rad^2], map frame (the convention of ``noise_model.to_map_frame``).

:func:`walk` moves a level base (yaw only) along a polyline at constant speed, its heading along the
current segment; the base is ``base_height_m`` above the terrain. The default camera mount
:data:`DEFAULT_T_BASE_CAM` puts the camera 0.30 m ahead of and 0.05 m above the base origin, pitched
30 deg down: with the base at its nominal height :data:`NOMINAL_BASE_HEIGHT_M` = 0.40 m above the
ground, the camera is 0.45 m above the ground. :func:`odometry_drift` integrates noisy increments
(a random walk per metre travelled) and propagates their first-order covariance. :func:`simulate_walk`
renders each frame from the true camera pose (:func:`~noise_model.sim.render.render_depth`), adds the
reference noise (:func:`~noise_model.sim.noise.add_noise`) -- or, with ``sensor="stereo"``, lets the
physical D435 of :mod:`noise_model.sim.stereo` make the frame -- and reports the true or the drifted pose.
"""

from __future__ import annotations

import math
from typing import Callable, Iterator, Sequence

import numpy as np

from ..checks import check_intrinsics, check_positive_scalar, check_transform, check_transforms
from ..covariance import skew
from ..d435 import D435, SensorModel
from ..numba_config import resolve_threads
from ._checks import _LIMIT_M, _finite, _image_size, _rng
from .noise import add_noise
from .render import render_depth
from .scene import Scene
from .targets import camera_extrinsics

__all__ = ["walk", "odometry_drift", "camera_pose_cov", "simulate_walk", "NOMINAL_BASE_HEIGHT_M",
           "DEFAULT_T_BASE_CAM"]


#: Nominal height of the base origin above the terrain [m].
NOMINAL_BASE_HEIGHT_M = 0.40
#: Default camera mount T_base_cam: 0.30 m ahead, 0.05 m above the base origin, pitched 30 deg down,
#: so 0.45 m above the ground when the base is at :data:`NOMINAL_BASE_HEIGHT_M`.
DEFAULT_T_BASE_CAM = camera_extrinsics((0.30, 0.0, 0.05), pitch_down_deg=30.0)
DEFAULT_T_BASE_CAM.setflags(write=False)


# ---------------------------------------------------------------------------------------------
# trajectories
# ---------------------------------------------------------------------------------------------
def _yaw_pose(x, y, z, yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [x, y, z]
    return T


def walk(path_xy, speed_mps: float = 0.5, rate_hz: float = 30.0, base_height_m: float = NOMINAL_BASE_HEIGHT_M,
         scene: Scene | None = None, terrain_window_m: float = 0.5) -> np.ndarray:
    """Base poses along a polyline at constant speed, heading along the path.

    Parameters
    ----------
    path_xy : array_like, shape (M, 2)
        Waypoints in the map frame [m], M >= 2, no zero-length segments.
    speed_mps : float
        Speed along the path [m/s].
    rate_hz : float
        Frame rate [Hz]: poses are ``speed_mps / rate_hz`` apart along the path, the first at the
        first waypoint, the last at or before the end.
    base_height_m : float
        Height of the base origin above the terrain [m].
    scene : Scene, optional
        Terrain to follow; None = flat ground at z = 0.
    terrain_window_m : float
        The terrain height is the mean of ``scene.height_at`` over 9 points spread over this length
        along the heading, centred on the base (a legged base spans its feet); 0 = right under it.

    Returns
    -------
    ndarray, shape (N, 4, 4)
        T_map_base of each frame: level (yaw only), heading = direction of the current segment (at a
        waypoint, the next segment's), z = terrain height + ``base_height_m``.
    """
    try:
        p = np.asarray(path_xy, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"path_xy must be numbers with shape (M, 2), got {path_xy!r}") from None
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 2:
        raise ValueError(f"path_xy must have shape (M, 2) with M >= 2 waypoints, got {np.shape(path_xy)}")
    if not np.all(np.isfinite(p)):
        raise ValueError("path_xy has non-finite entries")
    if float(np.abs(p).max()) > _LIMIT_M:
        raise ValueError("path_xy is implausibly far (> 1e4 m); check its units")
    seg = np.diff(p, axis=0)
    lengths = np.hypot(seg[:, 0], seg[:, 1])
    if np.any(lengths <= 0):
        raise ValueError(f"path_xy has zero-length segment(s) at waypoint(s) {np.flatnonzero(lengths <= 0).tolist()}")
    speed = check_positive_scalar(speed_mps, "speed_mps", upper=20.0, unit=" m/s")
    rate = check_positive_scalar(rate_hz, "rate_hz", upper=10000.0, unit=" Hz")
    hb = check_positive_scalar(base_height_m, "base_height_m", upper=10.0, unit=" m")
    if scene is not None and not isinstance(scene, Scene):
        raise ValueError(f"scene must be a Scene or None, got {type(scene).__name__}")
    window = float(terrain_window_m)
    if not math.isfinite(window) or window < 0 or window > 100:
        raise ValueError(f"terrain_window_m must be in [0, 100] m, got {terrain_window_m!r}")
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    step = speed / rate
    n = int(math.floor(cum[-1] / step * (1 + 1e-12))) + 1
    if n > 10_000_000:
        raise ValueError(f"the walk would have {n} poses; lower rate_hz or shorten the path")
    s = np.minimum(np.arange(n) * step, cum[-1])
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    frac = (s - cum[k]) / lengths[k]
    xy = p[k] + frac[:, None] * seg[k]
    yaw = np.arctan2(seg[k, 1], seg[k, 0])
    if scene is None:
        ground = np.zeros(n)
    else:
        offs = np.linspace(-0.5 * window, 0.5 * window, 9) if window > 0 else np.zeros(1)
        pts = xy[:, None, :] + offs[None, :, None] * np.stack([np.cos(yaw), np.sin(yaw)], axis=1)[:, None, :]
        h = scene.height_at(pts.reshape(-1, 2)).reshape(n, len(offs))
        bad = np.all(np.isnan(h), axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"the scene has no terrain under pose {i} at xy = {xy[i].round(3).tolist()}")
        ground = np.nanmean(h, axis=1)
    return np.stack([_yaw_pose(xy[i, 0], xy[i, 1], ground[i] + hb, yaw[i]) for i in range(n)])


def odometry_drift(poses, rng: np.random.Generator, sigma_xy_per_m: float = 0.02,
                   sigma_yaw_per_m: float = 0.01, sigma_z_per_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """What odometry would report along true base poses: noisy increments, integrated.

    Each step's increment U_k = T_{k-1}^-1 T_k (base frame) is corrupted by a small base-frame error:
    a translation N(0, diag(sxy^2, sxy^2, sz^2) ds) and a yaw N(0, syaw^2 ds), ds = the step's length
    [m]; the reported pose is T'_k = T'_{k-1} U_k E_k with T'_0 = T_0. The error is a random walk in
    the distance travelled: straight ahead without yaw error, sigma_xy after d metres is
    sigma_xy_per_m sqrt(d); yaw errors add lateral error growing as d^(3/2).

    Parameters
    ----------
    poses : array_like, shape (N, 4, 4)
        True T_map_base.
    rng : numpy.random.Generator
        Required.
    sigma_xy_per_m : float
        Horizontal translation noise density [m / sqrt(m)], >= 0.
    sigma_yaw_per_m : float
        Yaw noise density [rad / sqrt(m)], >= 0.
    sigma_z_per_m : float
        Vertical translation noise density [m / sqrt(m)], >= 0.

    Returns
    -------
    drifted : ndarray, shape (N, 4, 4)
        Reported T_map_base.
    covs : ndarray, shape (N, 6, 6)
        First-order covariance of each reported pose's error, translation [m^2] then rotation
        [rad^2], map frame, rotation about the base origin (the convention of
        ``noise_model.to_map_frame``: T' = (Exp(phi) R, t + rho)); zero for the first pose, growing
        with the distance travelled.
    """
    P = check_transforms(poses, "poses")
    rng = _rng(rng)
    sig = []
    for value, name in ((sigma_xy_per_m, "sigma_xy_per_m"), (sigma_yaw_per_m, "sigma_yaw_per_m"),
                        (sigma_z_per_m, "sigma_z_per_m")):
        x = _finite(value, name)
        if x < 0 or x > 10:
            raise ValueError(f"{name} must be in [0, 10], got {x}")
        sig.append(x)
    sxy, syaw, sz = sig
    n = len(P)
    out = np.empty_like(P)
    covs = np.zeros((n, 6, 6))
    out[0] = P[0]
    C = np.zeros((6, 6))
    for k in range(1, n):
        U = np.linalg.solve(P[k - 1], P[k])
        delta = P[k, :3, 3] - P[k - 1, :3, 3]
        ds = float(np.linalg.norm(delta))
        e = rng.normal(size=4) * np.sqrt(ds) * np.array([sxy, sxy, sz, syaw])
        E = _yaw_pose(e[0], e[1], e[2], e[3])
        out[k] = out[k - 1] @ U @ E
        # first order: rho_k = rho_{k-1} - [delta]_x phi_{k-1} + R_k n_t, phi_k = phi_{k-1} + R_k n_r
        F = np.eye(6)
        F[:3, 3:] = -skew(delta)
        G = np.zeros((6, 6))
        G[:3, :3] = P[k, :3, :3]
        G[3:, 3:] = P[k, :3, :3]
        Q = np.diag(np.array([sxy, sxy, sz, 0.0, 0.0, syaw]) ** 2 * ds)
        C = F @ C @ F.T + G @ Q @ G.T
        covs[k] = 0.5 * (C + C.T)
    # re-orthonormalise the rotations (products of many 4x4s drift from SO(3) at 1e-15 per step)
    u, _, vt = np.linalg.svd(out[:, :3, :3])
    out[:, :3, :3] = u @ vt
    return out, covs


def camera_pose_cov(base_cov, T_map_base, T_base_cam) -> np.ndarray:
    """A base pose covariance moved to the camera centre: J C J^T, J = [[I, -[a]_x], [0, I]],
    a = R_map_base t_base_cam (the rotation error swings the camera about the base origin).

    Parameters
    ----------
    base_cov : array_like, shape (6, 6)
        Covariance of T_map_base (translation then rotation, map frame, about the base origin).
    T_map_base, T_base_cam : array_like, shape (4, 4)

    Returns
    -------
    ndarray, shape (6, 6)
        Covariance of T_map_cam about the camera centre (what ``noise_model.to_map_frame`` takes).
    """
    from ..checks import check_pose_cov

    C = check_pose_cov(base_cov, "base_cov")
    Tb = check_transform(T_map_base, "T_map_base")
    Tc = check_transform(T_base_cam, "T_base_cam")
    J = np.eye(6)
    J[:3, 3:] = -skew(Tb[:3, :3] @ Tc[:3, 3])
    out = J @ C @ J.T
    return 0.5 * (out + out.T)


# ---------------------------------------------------------------------------------------------
# walks through a scene
# ---------------------------------------------------------------------------------------------
def simulate_walk(scene: Scene, K, width: int, height: int, n_frames: int | None = None, path=None,
                  rng: np.random.Generator | None = None, *, noise: str = "reference",
                  effects: Sequence[Callable] | None = None, drift: bool = False, model: SensorModel = D435,
                  T_base_cam=None, speed_mps: float = 0.5, rate_hz: float = 30.0,
                  base_height_m: float = NOMINAL_BASE_HEIGHT_M, follow_terrain: bool = True,
                  terrain_window_m: float = 0.5, max_range_m: float = 10.0, depth_scale: float = 0.001,
                  sigma_xy_per_m: float = 0.02, sigma_yaw_per_m: float = 0.01,
                  nthreads: int | None = None, sensor="reference", preset: str = "default") -> Iterator[dict]:
    """Depth frames of a camera on a robot walking through a scene.

    Parameters
    ----------
    scene : Scene
    K : array_like, shape (3, 3)
        Depth-stream intrinsics [px].
    width, height : int
        Image size [px].
    n_frames : int, optional
        Number of frames. Without ``path``: a straight walk along map +x from the origin, long enough
        for them. With ``path``: at most this many frames of it.
    path : array_like, shape (M, 2), optional
        Waypoints [m] (see :func:`walk`).
    rng : numpy.random.Generator
        Required: drift and noise draw from it, in frame order (drift first, for the whole walk).
    noise : {"reference", "none"}
        With the reference sensor: the paper's model (with ``model``), or quantisation only.
    effects : sequence of callables, optional
        Extra effects of the reference sensor, see :func:`add_noise`.
    drift : bool
        Report odometry poses (:func:`odometry_drift`) instead of the true ones.
    model : SensorModel
        Noise model of ``noise="reference"``.
    T_base_cam : array_like, shape (4, 4), optional
        Camera mount (default :data:`DEFAULT_T_BASE_CAM`: 0.45 m above the ground at nominal height).
    speed_mps, rate_hz, base_height_m, terrain_window_m
        See :func:`walk`; ``follow_terrain=False`` keeps the base at ``base_height_m`` above z = 0.
    max_range_m : float
        Render range [m].
    depth_scale : float
        Metres per depth unit.
    sigma_xy_per_m, sigma_yaw_per_m : float
        Drift densities (see :func:`odometry_drift`).
    nthreads : int, optional
        numba threads for rendering.
    sensor : "reference", "stereo" or noise_model.sim.stereo.StereoD435
        What makes the depth: the ray-cast depth plus the reference noise (default), or the physical
        D435 (``"stereo"``: ``StereoD435(width, height, K=K, matcher=preset)`` with this walk's range
        and depth unit; or a camera of your own, of this size and intrinsics), each frame rendered at
        its pose with fresh sensor noise from ``rng``. The physical sensor makes its own noise, so it
        takes neither ``noise="none"``, ``effects`` nor ``model``.
    preset : str
        Matcher preset of ``sensor="stereo"`` ("default", "high_accuracy").

    Returns
    -------
    generator of dict
        Per frame: ``depth`` (H, W) uint16, ``depth_scale`` [m/unit], ``K`` (3, 3), ``T_map_cam``
        (4, 4) as reported (drifted if ``drift``), ``T_map_cam_true``, ``pose_cov`` (6, 6) of the
        reported camera pose about the camera centre (None without drift), ``stamp`` [s] =
        index / rate_hz, ``index``; also ``T_map_base``, ``T_map_base_true`` and ``T_base_cam``.
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a Scene, got {type(scene).__name__}")
    K = check_intrinsics(K)
    width, height = _image_size(width, height)
    rng = _rng(rng)
    if noise not in ("reference", "none"):
        raise ValueError(f"noise must be 'reference' or 'none', got {noise!r}")
    if not isinstance(model, SensorModel):
        raise ValueError(f"model must be a SensorModel, got {type(model).__name__}")
    Tbc = DEFAULT_T_BASE_CAM.copy() if T_base_cam is None else check_transform(T_base_cam, "T_base_cam")
    scale = check_positive_scalar(depth_scale, "depth_scale", upper=0.1, unit=" m per unit")
    check_positive_scalar(max_range_m, "max_range_m", upper=1000.0, unit=" m")
    resolve_threads(nthreads)
    effects = tuple(effects or ())
    for k, e in enumerate(effects):
        if not callable(e):
            raise ValueError(f"effects[{k}] is not callable: {e!r}")
    stereo = _stereo_camera(sensor, preset, K, width, height, max_range_m, scale, nthreads)
    if stereo is not None and (noise != "reference" or effects or model is not D435):
        raise ValueError("the physical D435 (sensor='stereo') makes its own noise: it takes no noise='none', "
                         "effects or model")
    nf = None
    if n_frames is not None:
        if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
            raise ValueError(f"n_frames must be a positive integer, got {n_frames!r}")
        nf = int(n_frames)
    speed = check_positive_scalar(speed_mps, "speed_mps", upper=20.0, unit=" m/s")
    rate = check_positive_scalar(rate_hz, "rate_hz", upper=10000.0, unit=" Hz")
    if path is None:
        if nf is None:
            raise ValueError("give n_frames, path, or both")
        path = np.array([[0.0, 0.0], [speed * nf / rate, 0.0]])
    poses = walk(path, speed, rate, base_height_m, scene if follow_terrain else None, terrain_window_m)
    if nf is not None:
        poses = poses[:nf]
    if drift:
        reported, base_covs = odometry_drift(poses, rng, sigma_xy_per_m, sigma_yaw_per_m)
    else:
        reported, base_covs = poses, None
    noise_model = model if noise == "reference" else None

    def frames():
        for i in range(len(poses)):
            T_true = poses[i] @ Tbc
            T_rep = reported[i] @ Tbc
            stamp = i / rate
            if stereo is not None:
                depth = stereo.depth_frame(scene, T_true, rng)
            else:
                z, theta = render_depth(scene, K, width, height, T_true, max_range_m, nthreads)
                ctx = {"K": K, "index": i, "stamp": stamp, "T_map_cam": T_true}
                depth = add_noise(z, theta, rng, noise_model, effects, scale, ctx)
            cov = None if base_covs is None else camera_pose_cov(base_covs[i], reported[i], Tbc)
            yield {"depth": depth, "depth_scale": scale, "K": K.copy(), "T_map_cam": T_rep,
                   "T_map_cam_true": T_true, "pose_cov": cov, "stamp": stamp, "index": i,
                   "T_map_base": reported[i].copy(), "T_map_base_true": poses[i].copy(), "T_base_cam": Tbc.copy()}

    return frames()


def _stereo_camera(sensor, preset, K, width, height, max_range_m, depth_scale, nthreads):
    """The physical D435 of a walk (``sensor`` of :func:`simulate_walk`), or None for the reference sensor."""
    if isinstance(sensor, str) and sensor == "reference":
        return None
    from .stereo.pipeline import StereoD435       # loads the physical model only when it is asked for

    if isinstance(sensor, StereoD435):
        if (sensor.width, sensor.height) != (width, height) or not np.allclose(sensor.K, K) \
                or sensor.depth_unit_m != depth_scale:
            raise ValueError(f"the stereo camera ({sensor.width}x{sensor.height}, depth unit {sensor.depth_unit_m} m) "
                             f"must have the walk's size {width}x{height}, K and depth_scale {depth_scale} m")
        return sensor
    if isinstance(sensor, str) and sensor == "stereo":
        return StereoD435(width, height, K=K, matcher=preset, max_range_m=float(max_range_m),
                          depth_unit_m=depth_scale, nthreads=nthreads)
    raise ValueError(f"sensor must be 'reference', 'stereo' or a StereoD435, got {sensor!r}")
