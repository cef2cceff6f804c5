"""Capture data for the sim-to-real gap diagnosis: what is known of a capture, its frames, its simulation.

A capture (``shared/specs/capture-set.md``, format ``d435-captures/1``) is a planar target (a wall, or
a board before an optional fronto-parallel background wall) recorded for N frames by a camera on a
tripod. This module holds, without any I/O (the readers live in ``elevmap.sources.captures``):

* :class:`CaptureGeometry`: the camera intrinsics K [px], image size, depth scale [m/unit], baseline
  [m] and the target, built from the dicts of ``captures.json``; it renders the noise-free z-depth
  and incidence angle (:meth:`CaptureGeometry.render`) and labels every pixel with a *region*
  (:meth:`CaptureGeometry.regions`): interior of the target, near a board's left or right edge, the
  D435's left invalid band, the background.
* :class:`CaptureData`: a geometry and its frames as metric depth (F, H, W) [m], NaN = no data.
* :func:`simulate_capture`: the spec's REFERENCE SIMULATION of a capture (steps 1-5: ray cast, theta,
  z = z_true + N(0, sigma_z(z_true, theta)^2) independent per pixel and frame, board edges shifted
  each frame by N(0, sigma_L^2) / N(0, sigma_R^2) along the board's x axis, round(z / depth_scale) as
  uint16), plus optional effects (:mod:`noise_model.sim.effects`) applied in order to each frame's metric
  depth before the rounding, through the hook of :func:`noise_model.sim.scene.add_noise`.

Frames: camera x right, y down, z forward; depth is z (along the optical axis), not ray length.
Pixel (u, v) = (column, row), 0-based, integer coordinates at pixel centres.

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
    The D435's left invalid band (E6 of ``shared/notes/depth-effects.md``): the left imager is the
    reference and its leftmost columns have no counterpart in the right image, so columns
    u < f B / z_true (the pixel's true disparity [px]) plus a margin have no depth. The region takes
    ``left_margin_px`` (default 10 px at 424 x 240, scaled with the image width) beyond f B / z_true, more
    than the matcher's margin w0 ~ 4-10 px at 848 x 480, so a real band lies inside it.
``REGION_BACKGROUND`` = 5
    The background wall behind a board, away from the board's edges.

Precedence: left band > top/bottom exclusion > left/right edges > interior / background.

Effect context
--------------
:func:`simulate_capture` calls each effect as ``effect(z, theta, rng, context)`` with ``context``:
``K`` (3, 3) [px], ``width``, ``height`` [px], ``index`` (frame index), ``depth_scale`` [m/unit],
``z_true`` (H, W) [m] (this frame's, read only; boards move their edges each frame), ``baseline_m``
[m], ``capture_id`` (str), ``regions`` (H, W) int8 (the nominal regions above, read only) and
``z_ref`` (H, W) [m] (the depth after the reference noise, before any effect; read only).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..checks import check_intrinsics, check_positive_scalar
from ..d435 import D435, SensorModel
from ..sim.targets import render_planar_target, target_rotation

__all__ = ["CaptureGeometry", "CaptureData", "simulate_capture", "check_captures", "REGION_NONE", "REGION_INTERIOR",
           "REGION_EDGE_LEFT", "REGION_EDGE_RIGHT", "REGION_LEFT_BAND", "REGION_BACKGROUND", "REGION_NAMES",
           "LEFT_BAND_MARGIN_PX_424", "EDGE_PX_424", "LATERAL_EDGE_SIGMAS"]

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
    """What is known of one capture: camera intrinsics and target (capture-set spec).

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
        The spec's target: ``kind`` ("wall" or "board"), ``distance_m`` [m], ``yaw_deg``, ``pitch_deg``
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
        """Noise-free z-depth and incidence angle (spec steps 1-2).

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


@dataclass
class CaptureData:
    """A capture's geometry and frames.

    Attributes
    ----------
    geometry : CaptureGeometry
    depth_m : ndarray, shape (F, H, W), float64
        Metric z-depth [m]; NaN = no data.
    """

    geometry: CaptureGeometry
    depth_m: np.ndarray

    def __post_init__(self):
        if not isinstance(self.geometry, CaptureGeometry):
            raise ValueError(f"geometry must be a CaptureGeometry, got {type(self.geometry).__name__}")
        g = self.geometry
        d = np.asarray(self.depth_m)
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
        self.depth_m = d

    @property
    def id(self) -> str:
        return self.geometry.id

    @property
    def n_frames(self) -> int:
        return int(self.depth_m.shape[0])

    @classmethod
    def from_units(cls, geometry: CaptureGeometry, depth_units: np.ndarray) -> "CaptureData":
        """Frames from depth units: depth_m = units * depth_scale, 0 -> NaN.

        Parameters
        ----------
        geometry : CaptureGeometry
        depth_units : ndarray, shape (F, H, W) or (H, W), unsigned or signed integers
            Depth units of ``geometry.depth_scale`` (uint16 as recorded); 0 = no data.
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
        d = a.astype(np.float64) * geometry.depth_scale
        d[a == 0] = np.nan
        return cls(geometry, d)


class _RecordReference:
    """First hook of :func:`simulate_capture`: stores the depth after the reference noise as ``z_ref``."""

    def __call__(self, z, theta, rng, context):
        ro = np.array(z, dtype=np.float64, copy=True)
        ro.flags.writeable = False
        context["z_ref"] = ro
        return z


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
            raise ValueError(f"{name}[{k}] must be a noise_model.analysis.capture_data.CaptureData, got {type(c).__name__}")
    ids = [c.id for c in items]
    if len(set(ids)) != len(ids):
        raise ValueError(f"{name} captures must have distinct ids")
    return items


def simulate_capture(geometry: CaptureGeometry, n_frames: int, rng: np.random.Generator, model: SensorModel = D435,
                     effects=()) -> np.ndarray:
    """The spec's reference simulation of a capture, plus effects; uint16 depth units (F, H, W).

    Per frame: for a board, the left and right edges shift along the board by N(0, sigma_L^2) and
    N(0, sigma_R^2) (two draws from ``rng``, left first); the noise-free render (z_true, theta); then
    :func:`noise_model.sim.scene.add_noise` draws z = z_true + N(0, sigma_z^2) (one ``rng.normal`` over the
    image), applies ``effects`` in order to the metric depth with the context of the module docstring,
    and rounds to depth units (0 = no data). Where the true depth is beyond what the uint16 can hold
    (65535 units, or 100 m), there is no hit (a steep wall seen at grazing angles reaches hundreds of
    metres). With no effects this is, draw for draw, the frames of
    :func:`noise_model.sim.targets.simulate_target_frames` for the same generator (except at such pixels,
    which that function clips to 65535).

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
    from ..sim.scene import add_noise

    if not isinstance(geometry, CaptureGeometry):
        raise ValueError(f"geometry must be a CaptureGeometry, got {type(geometry).__name__}")
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator (seed it: np.random.default_rng(seed))")
    if not isinstance(model, SensorModel):
        raise ValueError(f"model must be a noise_model.SensorModel, got {type(model).__name__}")
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise ValueError(f"n_frames must be an integer >= 1, got {n_frames!r}")
    effects = tuple(effects or ())
    for k, e in enumerate(effects):
        if not callable(e):
            raise ValueError(f"effects[{k}] is not callable: {e!r}")
    g = geometry
    out = np.zeros((int(n_frames), g.height, g.width), dtype=np.uint16)
    regions = None
    z_max = min(100.0, 65535 * g.depth_scale)
    if effects:
        regions = g.regions(model=model)
        regions.flags.writeable = False
    for f in range(int(n_frames)):
        if g.kind == "board":
            shift = (rng.normal(0.0, model.sigma_L), rng.normal(0.0, model.sigma_R))
            z_true, theta = g.render(shift)
        else:
            z_true, theta = g.render()
        far = z_true > z_max                       # beyond what a uint16 depth can hold: no data
        if far.any():
            z_true = np.where(far, np.nan, z_true)
            theta = np.where(far, np.nan, theta)
        if effects:
            ctx = {"K": g.K, "index": f, "baseline_m": g.baseline_m, "capture_id": g.id, "regions": regions}
            out[f] = add_noise(z_true, theta, rng, model, (_RecordReference(),) + effects, g.depth_scale, ctx)
        else:
            out[f] = add_noise(z_true, theta, rng, model, None, g.depth_scale)
    return out
