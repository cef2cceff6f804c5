"""Planar targets seen by a posed D435: the one reference simulation of their frames, and the physical one.

Conventions are those of the capture-set format (docs/capture-set-format.md): camera frame x right,
y down, z forward; depth is z, not ray length. Pixel (u, v) = (column, row), 0-based, integer
coordinates at pixel centres. A target's centre is c = (0, 0, distance_m) and its axes are the
columns of R = R_y(yaw) R_x(pitch); a board spans c + s R e_x + t R e_y for |s| <= width/2,
|t| <= height/2, its normal is R e_z; a wall is the unbounded plane. A board may stand before a
fronto-parallel background wall.

* :func:`render_planar_target`, :func:`render_floor`: noise-free z-depth and incidence angle.
* :class:`CaptureGeometry`: one capture of the capture-set format (intrinsics K [px], image size,
  depth scale [m/unit], baseline [m], the target); it renders itself and labels every pixel with a
  *region* (:meth:`CaptureGeometry.regions`).
* :func:`simulate_target`: the reference simulation of a planar target, the one every caller uses
  (:func:`simulate_target_frames` takes the target as arguments, and
  ``noise_model.analysis.capture_data.simulate_capture`` adds the capture's context for the effects).
* :func:`simulate_target_stereo`: the same capture seen by the physical D435
  (:mod:`noise_model.sim.stereo`), its target expressed as a :class:`~noise_model.sim.scene.Scene`
  (:meth:`CaptureGeometry.scene`); chosen explicitly, the reference stays the default everywhere.

The reference simulation
------------------------
Per frame and pixel (docs/noise-model.md): each frame a board's left edge shifts along the board's
x axis by N(0, sigma_L^2) and its right edge by N(0, sigma_R^2); then
z = z_true + N(0, sigma_z(z_true, theta)^2), independent per pixel and frame
(:func:`noise_model.sim.noise.add_noise`); then the optional effects; the result is
round(z / depth_scale) as uint16, 0 (no data) where there is no hit or z <= 0. Nothing else: the
effects the paper leaves out belong to :mod:`noise_model.sim.effects`.

Far pixels, one rule for every caller: where the true depth is beyond what a uint16 depth can hold,
z_true > min(100 m, 65535 depth_scale) (100 m is the largest true depth
:func:`~noise_model.sim.noise.add_noise` accepts), the pixel has no hit (0), and so does a noisy depth
beyond 65535 units. A D435 reports no data there. Simulating such pixels would give readings that
mean nothing: a grazing ray of a steep wall meets it hundreds of metres away, where sigma_z
(quadratic in z, unbounded as theta nears 90 deg) spreads the draws over the whole range, and a clip
to 65535 would look like a valid depth at the end of the range.

Regions (int8 codes, :meth:`CaptureGeometry.regions`)
-----------------------------------------------------
``REGION_NONE`` = 0
    No hit (a board's surroundings without background), or within ``edge_px`` rows of a board's top
    or bottom edge (horizontal depth edges: neither interior nor a left/right edge; left out of
    region statistics).
``REGION_INTERIOR`` = 1
    The target (wall, or board away from its edges).
``REGION_EDGE_LEFT`` = 2, ``REGION_EDGE_RIGHT`` = 3
    Pixels (on the board and on the background side) whose distance from the board's nominal left
    (right) vertical edge is at most 2.5 lateral sigmas (the reference simulation shifts the edges
    each frame by N(0, sigma_L^2), N(0, sigma_R^2) along the board: 99 % of the edges stay inside)
    plus ``edge_px`` columns (edge fattening / flying pixels reach a few px beyond the edge).
``REGION_LEFT_BAND`` = 4
    The D435's left invalid band (E6 of docs/depth-effects.md): the left imager is the reference
    and its leftmost columns have no counterpart in the right image, so columns u < f B / z_true (the
    pixel's true disparity [px]) plus a margin have no depth. The region takes ``left_margin_px``
    (default 10 px at 424 x 240, scaled with the image width) beyond f B / z_true, more than the
    matcher's margin w0 ~ 4-10 px at 848 x 480, so a real band lies inside it.
``REGION_BACKGROUND`` = 5
    The background wall behind a board, away from the board's edges.

Precedence: left band > top/bottom exclusion > left/right edges > interior / background.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..checks import check_intrinsics, check_positive_scalar
from ..d435 import D435, SensorModel
from ._checks import _rng
from .noise import noisy_frame, prepare_noise
from .scene import Scene, Target

__all__ = ["target_rotation", "camera_extrinsics", "render_planar_target", "render_floor", "CaptureGeometry",
           "simulate_target", "simulate_target_frames", "simulate_target_stereo", "REGION_NONE", "REGION_INTERIOR",
           "REGION_EDGE_LEFT",
           "REGION_EDGE_RIGHT", "REGION_LEFT_BAND", "REGION_BACKGROUND", "REGION_NAMES", "LEFT_BAND_MARGIN_PX_424",
           "EDGE_PX_424", "LATERAL_EDGE_SIGMAS"]

REGION_NONE = 0
REGION_INTERIOR = 1
REGION_EDGE_LEFT = 2
REGION_EDGE_RIGHT = 3
REGION_LEFT_BAND = 4
REGION_BACKGROUND = 5
#: Region code -> the name used in gap reports (``stratum.region``); 0 is not a region.
REGION_NAMES = {REGION_INTERIOR: "interior", REGION_EDGE_LEFT: "edge_left", REGION_EDGE_RIGHT: "edge_right",
                REGION_LEFT_BAND: "left_band", REGION_BACKGROUND: "background"}

#: Default margin of the left-band region beyond f B / z_true at 424 px width [px] (scaled with the
#: width: 20 px at 848 x 480), above the matcher's own margin (E6: w0 ~ 4-10 px at 848).
LEFT_BAND_MARGIN_PX_424 = 10.0
#: Default width of the edge zones beyond the lateral-noise band, and of the top/bottom exclusion, at
#: 424 px width [px] (scaled with the width).
EDGE_PX_424 = 6
#: Edge zones reach this many lateral sigmas (sigma_L, sigma_R of the model) from the nominal edge.
LATERAL_EDGE_SIGMAS = 2.5


# ---------------------------------------------------------------------------------------------
# noise-free renders
# ---------------------------------------------------------------------------------------------
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


# ---------------------------------------------------------------------------------------------
# the capture geometry
# ---------------------------------------------------------------------------------------------
def _float(value, where: str, *, positive: bool = False) -> float:
    if isinstance(value, bool):
        raise ValueError(f"{where} must be a number, got {value!r}")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where} must be a number, got {value!r}") from None
    if not math.isfinite(x) or (positive and x <= 0):
        raise ValueError(f"{where} must be a finite{' positive' if positive else ''} number, got {value!r}")
    return x


@dataclass(frozen=True, eq=False)
class CaptureGeometry:
    """What is known of one capture: camera intrinsics and target (docs/capture-set-format.md).

    Attributes
    ----------
    id : str
        The capture's id.
    K : ndarray, shape (3, 3)
        Intrinsics of the depth stream [px] (rectified, no distortion).
    width, height : int
        Image size [px].
    depth_scale : float
        Metres per depth unit [m/unit].
    baseline_m : float
        Stereo baseline B [m].
    target : dict
        The capture-set target: ``kind`` ("wall" or "board"), ``distance_m`` [m], ``yaw_deg``, ``pitch_deg``
        [deg], and for a board ``width_m``, ``height_m`` [m].
    background_m : float or None
        z of a fronto-parallel wall behind a board [m]; None = nothing (those pixels have no hit).
    """

    id: str
    K: np.ndarray
    width: int
    height: int
    depth_scale: float
    baseline_m: float
    target: dict
    background_m: float | None = None
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False, hash=False)

    def __post_init__(self):
        if not isinstance(self.id, str) or not self.id:
            raise ValueError(f"id must be a non-empty string, got {self.id!r}")
        K = check_intrinsics(self.K, f"{self.id}: K")
        K.flags.writeable = False
        object.__setattr__(self, "K", K)
        for key in ("width", "height"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= int(v) <= 8192:
                raise ValueError(f"{self.id}: {key} must be an integer number of pixels in [1, 8192], got {v!r}")
            object.__setattr__(self, key, int(v))
        object.__setattr__(self, "depth_scale", check_positive_scalar(self.depth_scale, f"{self.id}: depth_scale",
                                                                      upper=0.1, unit=" m per unit"))
        object.__setattr__(self, "baseline_m", check_positive_scalar(self.baseline_m, f"{self.id}: baseline_m",
                                                                     upper=2.0, unit=" m"))
        if not isinstance(self.target, Mapping):
            raise ValueError(f"{self.id}: target must be a dict, got {type(self.target).__name__}")
        t = dict(self.target)
        kind = t.get("kind")
        if kind not in ("wall", "board"):
            raise ValueError(f"{self.id}: target 'kind' must be 'wall' or 'board', got {kind!r}")
        if "distance_m" not in t:
            raise ValueError(f"{self.id}: target is missing 'distance_m'")
        t["distance_m"] = check_positive_scalar(t["distance_m"], f"{self.id}: target distance_m", upper=100.0,
                                                unit=" m")
        for key in ("yaw_deg", "pitch_deg"):
            t[key] = _float(t.get(key, 0.0) if t.get(key) is not None else 0.0, f"{self.id}: target {key}")
            if abs(t[key]) >= 90.0:
                raise ValueError(f"{self.id}: target {key} must be in (-90, 90) deg, got {t[key]!r}")
        if kind == "board":
            for key in ("width_m", "height_m"):
                if t.get(key) is None:
                    raise ValueError(f"{self.id}: a board target needs '{key}'")
                t[key] = check_positive_scalar(t[key], f"{self.id}: target {key}", upper=100.0, unit=" m")
        object.__setattr__(self, "target", t)
        if self.background_m is not None:
            bg = check_positive_scalar(self.background_m, f"{self.id}: background_m", upper=100.0, unit=" m")
            if bg <= t["distance_m"]:
                raise ValueError(f"{self.id}: background_m = {bg} must be behind the target (> distance_m)")
            object.__setattr__(self, "background_m", bg)
        z, _ = self.render()
        if not np.isfinite(z).any():
            raise ValueError(f"{self.id}: the camera cannot see the target (no pixel hits it)")

    # -------------------------------------------------------------------------------------------
    @property
    def fb_px_m(self) -> float:
        """f B: disparity [px] times depth [m] (fx [px] times the baseline [m])."""
        return float(self.K[0, 0]) * self.baseline_m

    @property
    def kind(self) -> str:
        return self.target["kind"]

    @property
    def distance_m(self) -> float:
        return float(self.target["distance_m"])

    @property
    def yaw_deg(self) -> float:
        return float(self.target["yaw_deg"])

    @property
    def pitch_deg(self) -> float:
        return float(self.target["pitch_deg"])

    def render(self, edge_shift_m=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free z-depth and incidence angle of every pixel (the render of :func:`simulate_target`).

        Parameters
        ----------
        edge_shift_m : (float, float)
            Shift of a board's left and right edges along its own x axis [m] (ignored for walls).

        Returns
        -------
        z_true : ndarray, shape (height, width), float64
            z of the first hit [m]; NaN = no hit.
        theta : ndarray, shape (height, width), float64
            Angle between the hit surface's normal and the optical axis [rad]; NaN = no hit.
        """
        t = self.target
        shift = tuple(float(e) for e in edge_shift_m)
        if shift == (0.0, 0.0) and "nominal" in self._cache:
            z, th = self._cache["nominal"]
            return z.copy(), th.copy()
        z, th = render_planar_target(self.K, self.width, self.height, t["distance_m"], t["yaw_deg"], t["pitch_deg"],
                                     t["kind"], t.get("width_m"), t.get("height_m"), self.background_m, shift)
        if shift == (0.0, 0.0):
            self._cache["nominal"] = (z.copy(), th.copy())
        return z, th

    def scene(self, max_range_m: float = 10.0, material=None, background_material=None):
        """The capture as a scene of primitives and a camera pose, for the physical D435.

        The target becomes a :class:`~noise_model.sim.scene.Target` at the map point (0, 0, 1) facing
        map -x (board axes R e_x, R e_y, R e_z -> map y, -z, -x); a wall is a target reaching beyond
        ``max_range_m`` in every direction. The camera's pose follows from the target's pose in the
        camera frame (c = (0, 0, distance_m), axes R): T_map_cam = T_map_board T_cam_board^-1. A
        background wall is a second target, fronto-parallel to the camera at z = ``background_m``; the
        scene's targets stand vertical, so that needs a level optical axis (pitch 0). No ground.

        Parameters
        ----------
        max_range_m : float
            Range the scene must cover [m] (the camera's render range).
        material, background_material : Uniform, Texture, float or None
            Infrared materials of the target and the background (default: white paint, albedo 0.8).

        Returns
        -------
        scene : Scene
        T_map_cam : ndarray, shape (4, 4)

        Raises
        ------
        ValueError
            A background behind a pitched target.
        """
        from .stereo.materials import white_wall

        rng_m = check_positive_scalar(max_range_m, "max_range_m", upper=1000.0, unit=" m")
        t = self.target
        R = target_rotation(t["yaw_deg"], t["pitch_deg"])
        T_cam_board = np.eye(4)
        T_cam_board[:3, :3] = R
        T_cam_board[:3, 3] = (0.0, 0.0, t["distance_m"])
        T_map_board = np.eye(4)
        T_map_board[:3, :3] = np.column_stack([(0.0, 1.0, 0.0), (0.0, 0.0, -1.0), (-1.0, 0.0, 0.0)])
        T_map_board[:3, 3] = (0.0, 0.0, 1.0)
        T_map_cam = T_map_board @ np.linalg.inv(T_cam_board)
        T_map_cam[3] = (0.0, 0.0, 0.0, 1.0)
        mat = white_wall() if material is None else material
        if self.kind == "board":
            target = Target((0.0, 0.0, 1.0), t["width_m"], t["height_m"], 0.0, mat)
        else:
            reach = 2.0 * (t["distance_m"] + 2.0 * rng_m) + 2.0
            target = Target((0.0, 0.0, 1.0), reach, reach, 0.0, mat)
        prims = [target]
        if self.background_m is not None:
            axis = T_map_cam[:3, 2]
            if abs(axis[2]) > 1e-9:
                raise ValueError(f"{self.id}: a background wall behind a target pitched by {t['pitch_deg']} deg "
                                 f"cannot be built from the scene's vertical targets; use pitch 0")
            bg = self.background_m
            half_w = bg * max(self.K[0, 2], self.width - self.K[0, 2]) / self.K[0, 0]
            half_h = bg * max(self.K[1, 2], self.height - self.K[1, 2]) / self.K[1, 1]
            centre = T_map_cam[:3, 3] + bg * axis
            prims.append(Target(tuple(centre), 2.4 * half_w + 4.0 * self.baseline_m + 1.0, 2.4 * half_h + 1.0,
                                math.degrees(math.atan2(axis[1], axis[0])),
                                white_wall() if background_material is None else background_material))
        return Scene(prims, ground_z=None), T_map_cam

    def board_coordinates(self) -> tuple[np.ndarray, np.ndarray]:
        """Coordinates (s, t) [m] on the target's plane of every pixel's ray (board frame axes R e_x, R e_y).

        NaN where the ray does not meet the (unbounded) plane in front of the camera.
        """
        t = self.target
        R = target_rotation(t["yaw_deg"], t["pitch_deg"])
        n = R[:, 2]
        D = t["distance_m"]
        u = (np.arange(self.width) - self.K[0, 2]) / self.K[0, 0]
        v = (np.arange(self.height) - self.K[1, 2]) / self.K[1, 1]
        rx, ry = np.meshgrid(u, v)
        with np.errstate(divide="ignore", invalid="ignore"):
            tr = n[2] * D / (n[0] * rx + n[1] * ry + n[2])
        tr = np.where(np.isfinite(tr) & (tr > 0), tr, np.nan)
        px, py, pz = tr * rx, tr * ry, tr - D
        s = px * R[0, 0] + py * R[1, 0] + pz * R[2, 0]
        tt = px * R[0, 1] + py * R[1, 1] + pz * R[2, 1]
        return s, tt

    def plane_depth(self) -> np.ndarray:
        """z [m] of the target's unbounded plane along every pixel's ray; NaN where it is behind the camera."""
        t = self.target
        R = target_rotation(t["yaw_deg"], t["pitch_deg"])
        n = R[:, 2]
        u = (np.arange(self.width) - self.K[0, 2]) / self.K[0, 0]
        v = (np.arange(self.height) - self.K[1, 2]) / self.K[1, 1]
        rx, ry = np.meshgrid(u, v)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = n[2] * t["distance_m"] / (n[0] * rx + n[1] * ry + n[2])
        return np.where(np.isfinite(z) & (z > 0), z, np.nan)

    def default_left_margin_px(self) -> float:
        return LEFT_BAND_MARGIN_PX_424 * self.width / 424.0

    def default_edge_px(self) -> int:
        return max(2, int(round(EDGE_PX_424 * self.width / 424.0)))

    def regions(self, left_margin_px: float | None = None, edge_px: int | None = None,
                model: SensorModel = D435) -> np.ndarray:
        """Region code of every pixel (see the module docstring), from the nominal (unshifted) geometry.

        Parameters
        ----------
        left_margin_px : float, optional
            Left band: columns u < f B / z_true + this [px] (default 10 px at 424 wide, scaled).
        edge_px : int, optional
            Width added to the edge zones beyond 2.5 lateral sigmas, and of the top/bottom exclusion
            [px] (default 6 at 424 wide, scaled).
        model : SensorModel
            Its sigma_L, sigma_R [m] set the edge zones' half-width along the board.

        Returns
        -------
        ndarray, shape (height, width), int8
        """
        lm = self.default_left_margin_px() if left_margin_px is None else _float(left_margin_px, "left_margin_px")
        ep = self.default_edge_px() if edge_px is None else int(edge_px)
        if ep < 0:
            raise ValueError(f"edge_px must be >= 0, got {edge_px!r}")
        key = ("regions", lm, ep, float(model.sigma_L), float(model.sigma_R))
        if key in self._cache:
            return self._cache[key].copy()
        z, _ = self.render()
        hit = np.isfinite(z)
        out = np.zeros((self.height, self.width), dtype=np.int8)
        if self.kind == "wall":
            out[hit] = REGION_INTERIOR
        else:
            s, tt = self.board_coordinates()
            w2, h2 = self.target["width_m"] / 2.0, self.target["height_m"] / 2.0
            with np.errstate(invalid="ignore"):
                board = np.isfinite(s) & (np.abs(s) <= w2) & (np.abs(tt) <= h2) & hit
                if self.background_m is not None:
                    # board pixels are where the render hits the board, not the background
                    board &= z < self.background_m - 1e-9
            out[hit] = REGION_BACKGROUND
            out[board] = REGION_INTERIOR
            aL, aR = LATERAL_EDGE_SIGMAS * model.sigma_L, LATERAL_EDGE_SIGMAS * model.sigma_R
            with np.errstate(invalid="ignore"):
                rows_in = np.isfinite(tt) & (np.abs(tt) <= h2)
                zone_l = rows_in & (np.abs(s + w2) <= aL)
                zone_r = rows_in & (np.abs(s - w2) <= aR)
            zone_l = _dilate_columns(zone_l, ep) & hit
            zone_r = _dilate_columns(zone_r, ep) & hit
            # where both zones meet (a narrow or far board) the nearer edge wins
            both = zone_l & zone_r
            with np.errstate(invalid="ignore"):
                nearer_left = np.abs(s + w2) <= np.abs(s - w2)
            zone_l &= ~both | nearer_left
            zone_r &= ~both | ~nearer_left
            out[zone_l] = REGION_EDGE_LEFT
            out[zone_r] = REGION_EDGE_RIGHT
            # top / bottom edges: rows within ep of a vertical change of the board mask
            if ep > 0:
                hi_ = _dilate_rows(board, ep)
                lo_ = ~_dilate_rows(~board, ep)
                out[hi_ & ~lo_ & hit] = REGION_NONE
        u = np.arange(self.width)[None, :]
        with np.errstate(invalid="ignore", divide="ignore"):
            band = hit & (u < self.fb_px_m / z + lm)
        out[band] = REGION_LEFT_BAND
        self._cache[key] = out.copy()
        return out

    @classmethod
    def from_capture_set_entry(cls, camera: Mapping, capture: Mapping) -> "CaptureGeometry":
        """A geometry from the ``camera`` dict and one entry of ``captures`` of ``captures.json``.

        ``camera`` needs ``width``, ``height``, ``fx``, ``fy``, ``ppx``, ``ppy`` [px], ``depth_scale``
        [m/unit]; ``baseline_m`` [m] defaults to the D435's 0.050. ``capture`` needs ``id`` and
        ``target``; ``background_m`` defaults to None. Unknown keys are ignored.

        Raises
        ------
        ValueError
            A missing or bad key, named with the capture.
        """
        if not isinstance(camera, Mapping):
            raise ValueError(f"camera must be a dict, got {type(camera).__name__}")
        if not isinstance(capture, Mapping):
            raise ValueError(f"capture must be a dict, got {type(capture).__name__}")
        cid = capture.get("id")
        if not isinstance(cid, str) or not cid:
            raise ValueError(f"capture is missing a string 'id': {dict(capture)!r}")
        for key in ("width", "height", "fx", "fy", "ppx", "ppy", "depth_scale"):
            if camera.get(key) is None:
                raise ValueError(f"{cid}: camera is missing required key '{key}'")
        fx = _float(camera["fx"], f"{cid}: camera fx", positive=True)
        fy = _float(camera["fy"], f"{cid}: camera fy", positive=True)
        cx = _float(camera["ppx"], f"{cid}: camera ppx")
        cy = _float(camera["ppy"], f"{cid}: camera ppy")
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        w, h = camera["width"], camera["height"]
        for key, v in (("width", w), ("height", h)):
            if isinstance(v, bool) or not float(v).is_integer():
                raise ValueError(f"{cid}: camera {key} must be an integer, got {v!r}")
        baseline = camera.get("baseline_m")
        target = capture.get("target")
        if not isinstance(target, Mapping):
            raise ValueError(f"{cid}: capture is missing a 'target' object")
        return cls(id=cid, K=K, width=int(w), height=int(h), depth_scale=camera["depth_scale"],
                   baseline_m=D435.baseline_m if baseline is None else baseline, target=dict(target),
                   background_m=capture.get("background_m"))


def _dilate_columns(mask: np.ndarray, r: int) -> np.ndarray:
    out = mask.copy()
    for k in range(1, r + 1):
        out[:, k:] |= mask[:, :-k]
        out[:, :-k] |= mask[:, k:]
    return out


def _dilate_rows(mask: np.ndarray, r: int) -> np.ndarray:
    out = mask.copy()
    for k in range(1, r + 1):
        out[k:, :] |= mask[:-k, :]
        out[:-k, :] |= mask[k:, :]
    return out


# ---------------------------------------------------------------------------------------------
# the reference simulation
# ---------------------------------------------------------------------------------------------
class _RecordReference:
    """First hook of :func:`simulate_target` with effects: stores the depth after the reference noise
    as ``context['z_ref']`` (read only), for effects that rescale the reference noise."""

    def __call__(self, z, theta, rng, context):
        ro = np.array(z, dtype=np.float64, copy=True)
        ro.flags.writeable = False
        context["z_ref"] = ro
        return z


def simulate_target(geometry: CaptureGeometry, n_frames: int, rng: np.random.Generator, model: SensorModel = D435,
                    effects=(), context: dict | None = None) -> np.ndarray:
    """Frames of a planar target under the reference simulation of the paper's model, plus effects.

    Per frame f (the module docstring states the model and the far-pixel rule):

    1. a board's edges shift: (dL, dR) = (N(0, sigma_L^2), N(0, sigma_R^2)), two draws from ``rng``,
       left first (a wall draws nothing);
    2. (z_true, theta) = ``geometry.render((dL, dR))``;
    3. z_true > z_max = min(100 m, 65535 depth_scale) becomes no hit (NaN);
    4. :func:`noise_model.sim.noise.add_noise`: z = z_true + sigma_z(z_true, theta) n with one
       ``rng.normal(0, 1, (H, W))``, then ``effects`` in order, then round(z / depth_scale) as uint16.

    So ``rng`` gives 2 + H W draws per board frame and H W per wall frame, before whatever the effects
    draw; with no effects the frames do not depend on anything else.

    Parameters
    ----------
    geometry : CaptureGeometry
        The target, camera and depth scale.
    n_frames : int
        Frames, >= 1.
    rng : numpy.random.Generator
        The only source of randomness (effects draw from it too).
    model : SensorModel
        Axial and lateral noise of the reference simulation (the paper's D435 by default).
    effects : sequence of callables
        ``effect(z, theta, rng, context) -> z`` (:mod:`noise_model.sim.effects`), applied in the order
        given to each frame's metric depth after the reference noise and before the rounding. Their
        context: ``K`` (3, 3) [px], ``width``, ``height`` [px], ``index`` (frame), ``depth_scale``
        [m/unit], ``z_true`` (H, W) [m] (this frame's, read only: boards move their edges each frame),
        ``baseline_m`` [m] (the geometry's), ``z_ref`` (H, W) [m] (the depth after the reference
        noise, before any effect; read only), and the entries of ``context``.
    context : dict, optional
        Extra entries of the effects' context (e.g. a capture's id and regions).

    Returns
    -------
    ndarray, shape (n_frames, height, width), uint16
        Depth units of ``geometry.depth_scale`` [m]; 0 = no data.
    """
    if not isinstance(geometry, CaptureGeometry):
        raise ValueError(f"geometry must be a CaptureGeometry, got {type(geometry).__name__}")
    _rng(rng)
    if not isinstance(model, SensorModel):
        raise ValueError(f"model must be a noise_model.SensorModel, got {type(model).__name__}")
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise ValueError(f"n_frames must be an integer >= 1, got {n_frames!r}")
    effects = tuple(effects or ())
    for k, e in enumerate(effects):
        if not callable(e):
            raise ValueError(f"effects[{k}] is not callable: {e!r}")
    if context is not None and not isinstance(context, dict):
        raise ValueError(f"context must be a dict or None, got {type(context).__name__}")
    g = geometry
    out = np.zeros((int(n_frames), g.height, g.width), dtype=np.uint16)
    z_max = min(100.0, 65535 * g.depth_scale)
    frame_effects = (_RecordReference(),) + effects if effects else None
    static = None                                  # a wall renders the same every frame: prepared once
    for f in range(int(n_frames)):
        ctx = {"K": g.K, "index": f, "baseline_m": g.baseline_m, **(context or {})} if effects else None
        if static is None:
            if g.kind == "board":
                shift = (rng.normal(0.0, model.sigma_L), rng.normal(0.0, model.sigma_R))
                z_true, theta = g.render(shift)
            else:
                z_true, theta = g.render()
            far = z_true > z_max                   # beyond what a uint16 depth can hold: no data
            if far.any():
                z_true = np.where(far, np.nan, z_true)
                theta = np.where(far, np.nan, theta)
            prepared = prepare_noise(z_true, theta, model, frame_effects, g.depth_scale, ctx)
            if g.kind != "board":
                static = prepared
        else:
            prepared = static
        out[f] = noisy_frame(prepared, rng, ctx)
    return out


def simulate_target_frames(K, width: int, height: int, distance_m: float, n_frames: int,
                           rng: np.random.Generator, *, yaw_deg: float = 0.0, pitch_deg: float = 0.0,
                           kind: str = "wall", width_m: float | None = None, height_m: float | None = None,
                           background_m: float | None = None, depth_scale: float = 0.001,
                           model: SensorModel = D435, effects=()) -> np.ndarray:
    """:func:`simulate_target` of a target given by its parameters (the camera's baseline is the model's).

    Parameters
    ----------
    rng : numpy.random.Generator
        Required, so that every simulation is seeded by its caller.
    n_frames : int
        Number of frames, >= 1.
    effects : sequence of callables, optional
        Depth effects (:mod:`noise_model.sim.effects`), with the context of :func:`simulate_target`.
    (others as :func:`render_planar_target` and :class:`CaptureGeometry`)

    Returns
    -------
    ndarray, shape (n_frames, height, width), uint16
        Depth units of ``depth_scale`` [m]; 0 = no data.
    """
    nf = int(n_frames)
    if nf < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    target = {"kind": kind, "distance_m": distance_m, "yaw_deg": yaw_deg, "pitch_deg": pitch_deg}
    if kind == "board":
        target.update(width_m=width_m, height_m=height_m)
    geometry = CaptureGeometry("target", K, width, height, depth_scale, model.baseline_m, target, background_m)
    return simulate_target(geometry, nf, rng, model, effects)     # which checks rng


def simulate_target_stereo(geometry: CaptureGeometry, n_frames: int, rng: np.random.Generator,
                           preset: str = "default", camera=None) -> np.ndarray:
    """Frames of a planar target seen by the physical D435 (:mod:`noise_model.sim.stereo`).

    The capture becomes a scene (:meth:`CaptureGeometry.scene`), rendered once (the camera is static)
    and matched ``n_frames`` times with fresh sensor noise drawn from ``rng``; the dot pattern and the
    materials are fixed, so a seed gives the same frames every run.

    Parameters
    ----------
    geometry : CaptureGeometry
        The target, camera and depth scale; its image size must be a D435 depth mode.
    n_frames : int
        Frames, >= 1.
    rng : numpy.random.Generator
        The sensor noise.
    preset : str
        The matcher's preset ("default", "high_accuracy").
    camera : noise_model.sim.stereo.StereoD435, optional
        The camera (default: the geometry's size, intrinsics, baseline and depth scale, with ``preset``);
        its size and intrinsics must be the geometry's.

    Returns
    -------
    ndarray, shape (n_frames, height, width), uint16
        Depth units of ``geometry.depth_scale`` [m]; 0 = no data.
    """
    from .stereo.pipeline import StereoD435

    if not isinstance(geometry, CaptureGeometry):
        raise ValueError(f"geometry must be a CaptureGeometry, got {type(geometry).__name__}")
    _rng(rng)
    g = geometry
    if camera is None:
        camera = StereoD435(g.width, g.height, K=g.K, baseline_m=g.baseline_m, matcher=preset,
                            depth_unit_m=g.depth_scale)
    elif not isinstance(camera, StereoD435):
        raise ValueError(f"camera must be a StereoD435, got {type(camera).__name__}")
    elif (camera.width, camera.height) != (g.width, g.height) or not np.allclose(camera.K, g.K) \
            or camera.depth_unit_m != g.depth_scale:
        raise ValueError(f"{g.id}: the camera's size, intrinsics and depth unit must be the capture's")
    scene, T_map_cam = g.scene(max_range_m=camera.max_range_m)
    return camera.frames(scene, T_map_cam, n_frames, rng)
