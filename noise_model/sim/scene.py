"""Scenes of primitives, a numba ray caster for the D435, the reference noise, walks and odometry drift.

Frames and units
----------------
Map frame x forward, y left, z up [m]; camera frame x right, y down, z forward (RealSense/OpenCV);
``T_a_b`` maps points of frame b into frame a. Depth is z-depth (distance along the optical axis),
not ray length. Angles of primitives (``yaw_deg``, ``heading_deg``) are degrees about map z,
counter-clockwise from map +x.

Primitives (all solids are closed sets; the first hit along a ray is its smallest t >= 0 in any solid)
--------------------------------------------------------------------------------------------------
* ground plane ``Scene(ground_z=...)``: the half-space z <= ground_z (None: no ground).
* :class:`Box`: centre (3,), size (3,), yaw. A yawed box.
* :class:`Stairs`: solid steps. Local frame: origin ``start`` (the bottom of the first riser, in the
  middle of the flight), x along ``heading_deg``, z up. Step k = 0..count-1 is the box
  [k run, (k+1) run] x [-width/2, width/2] x [0, (k+1) rise]; the flight's top is count * rise.
* :class:`Ramp`: the convex prism (wedge) 0 <= z <= rise x / length over
  [0, length] x [-width/2, width/2] in its local frame (origin ``start``, x along the heading),
  with a vertical back face at x = length.
* :class:`HeightField`: heights on a regular grid (node (i, j) at origin + (i, j) resolution, i along
  map +x), axis-aligned. The surface is **exactly bilinear** in each cell (the ray/patch intersection
  is a quadratic in t, solved in closed form), the same surface ``height_at`` interpolates. The solid
  is base_z <= z <= h(x, y) over the grid's rectangle, with vertical side walls.
* :class:`Target`: a vertical rectangle of zero thickness (a board), two-sided, facing ``yaw_deg``.
  It has no footprint, so ``height_at`` ignores it.

Rendering (:func:`render_depth`)
--------------------------------
The ray of pixel (u, v) is d = R ((u - cx)/fx, (v - cy)/fy, 1) from the camera centre, so its
parameter t *is* the z-depth. Boxes, steps and the ramp use slab tests in their local frame (exact);
stairs are traversed step by step inside their bounding box (the NumPy reference instead tests every
step as its own box); height fields are traversed cell by cell, in the order the ray crosses them,
with a max-height level per 8 x 8 cells and per cell for empty-space skipping (the reference tests
every cell the ray's segment can touch, by brute force). Per primitive, a conservative image rectangle
(its bounding box projected) limits the pixels tested. Rules:

* theta is the angle between the hit face's normal and the optical axis, in [0, pi/2].
* Hits with z > ``max_range_m`` are no data (NaN). Exact ties between primitives go to the first in
  the order ground, box-like primitives (in the scene's order), height fields.
* A camera inside a solid (below the ground, inside a box/step/ramp, under a height field's surface,
  boundaries included) is blinded: every pixel is NaN (a real D435 reads 0 below its minimum range).
* Grazing rays: slabs are closed, so a ray lying in a face's plane and inside the other slabs hits
  (at the next face it meets, or at that face's edge); a ray parallel to a slab and outside it misses.

Noise (:func:`add_noise`)
-------------------------
The reference simulation of ``shared/specs/capture-set.md``: z = z_true + N(0, sigma_z(z_true,
theta)^2), independent per pixel, then ``effects`` (see below), then round(z / depth_scale) as uint16,
0 where there is no hit, z <= 0, z is not finite, or the value does not fit in uint16. ``model=None``
adds no noise (only the quantisation). The standard normals are drawn for the whole image (one
``rng.normal(0, 1, (H, W))`` call per frame), as ``sim.simulate_target_frames`` draws them, so both
give the same frames from the same generator.

Effect hook contract: ``effect(z, theta, rng, context) -> z``.

* ``z``: (H, W) float64, metric z-depth after the noise and the effects before, NaN = no data. The
  effect may modify it in place and return it, or return a new array.
* ``theta``: (H, W) float64 true incidence angles [rad], NaN where nothing is hit; read only.
* ``rng``: the simulation's ``numpy.random.Generator``; draw from it only (reproducibility).
* ``context``: dict with at least ``K`` (3, 3) [px], ``width``, ``height`` [px], ``index`` (frame
  number, 0 outside a walk), ``depth_scale`` [m/unit] and ``z_true`` (H, W) [m] (read only);
  :func:`simulate_walk` adds ``stamp`` [s] and ``T_map_cam`` (true pose).
* Must return an array of shape (H, W) (any float dtype); values <= 0 or NaN mean no data.

Trajectories
------------
:func:`walk` moves a level base (yaw only) along a polyline at constant speed, its heading along the
current segment; the base is ``base_height_m`` above the terrain. The default camera mount
:data:`DEFAULT_T_BASE_CAM` puts the camera 0.30 m ahead of and 0.05 m above the base origin, pitched
30 deg down: with the base at its nominal height :data:`NOMINAL_BASE_HEIGHT_M` = 0.40 m above the
ground, the camera is 0.45 m above the ground. :func:`odometry_drift` integrates noisy increments
(a random walk per metre travelled) and propagates their first-order covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Iterator, Sequence

import numpy as np
from numba import njit, prange

from ..checks import check_intrinsics, check_positive_scalar, check_transform, check_transforms
from ..covariance import skew
from ..d435 import D435, SensorModel, _axial_sigma_unchecked
from ..numba_config import JIT, resolve_threads, threads
from .targets import camera_extrinsics

__all__ = [
    "Box",
    "Stairs",
    "Ramp",
    "HeightField",
    "Target",
    "Scene",
    "render_depth",
    "render_depth_reference",
    "add_noise",
    "walk",
    "odometry_drift",
    "camera_pose_cov",
    "simulate_walk",
    "NOMINAL_BASE_HEIGHT_M",
    "DEFAULT_T_BASE_CAM",
    "HF_BLOCK",
]


#: Nominal height of the base origin above the terrain [m].
NOMINAL_BASE_HEIGHT_M = 0.40
#: Default camera mount T_base_cam: 0.30 m ahead, 0.05 m above the base origin, pitched 30 deg down,
#: so 0.45 m above the ground when the base is at :data:`NOMINAL_BASE_HEIGHT_M`.
DEFAULT_T_BASE_CAM = camera_extrinsics((0.30, 0.0, 0.05), pitch_down_deg=30.0)
DEFAULT_T_BASE_CAM.setflags(write=False)

#: Cells per side of a height field's coarse max-height block (empty-space skipping).
HF_BLOCK = 8

# primitive kinds in the packed arrays
_BOX, _STAIRS, _RAMP = 0, 1, 2
_LIMIT_M = 1.0e4          # coordinates and sizes beyond this are taken for a units mistake


# ---------------------------------------------------------------------------------------------
# validation helpers
# ---------------------------------------------------------------------------------------------
def _vector(value, n_allowed, name: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numbers, got {value!r}") from None
    if a.ndim != 1 or a.shape[0] not in n_allowed:
        raise ValueError(f"{name} must have {' or '.join(map(str, n_allowed))} components, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} has non-finite entries: {a.tolist()}")
    if float(np.abs(a).max(initial=0.0)) > _LIMIT_M:
        raise ValueError(f"{name} = {a.tolist()} is implausibly far (> {_LIMIT_M:g} m); check its units")
    return a


def _finite(value, name: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise ValueError(f"{name} must be finite, got {x!r}")
    return x


def _start3(start, name: str) -> np.ndarray:
    a = _vector(start, (2, 3), name)
    return np.array([a[0], a[1], 0.0 if a.shape[0] == 2 else a[2]])


def _rng(rng) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator (seed it: np.random.default_rng(seed))")
    return rng


def _image_size(width, height) -> tuple[int, int]:
    out = []
    for value, name in ((width, "width"), (height, "height")):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise ValueError(f"{name} must be an integer number of pixels, got {value!r}")
        if not 1 <= int(value) <= 16384:
            raise ValueError(f"{name} must be in [1, 16384] px, got {value}")
        out.append(int(value))
    return out[0], out[1]


# ---------------------------------------------------------------------------------------------
# primitives
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Box:
    """A solid box, yawed about map z.

    Parameters
    ----------
    centre : (3,) array_like
        Centre in the map frame [m] (a box resting on z = 0 has centre z = size z / 2).
    size : (3,) array_like
        Edge lengths along its own x, y (yawed) and map z [m], all > 0.
    yaw_deg : float
        Rotation about map z [deg].
    """

    centre: tuple
    size: tuple
    yaw_deg: float = 0.0

    def __post_init__(self):
        c = _vector(self.centre, (3,), "Box.centre")
        s = _vector(self.size, (3,), "Box.size")
        if np.any(s <= 0):
            raise ValueError(f"Box.size must be > 0 in every axis [m], got {s.tolist()}")
        object.__setattr__(self, "centre", tuple(c.tolist()))
        object.__setattr__(self, "size", tuple(s.tolist()))
        object.__setattr__(self, "yaw_deg", _finite(self.yaw_deg, "Box.yaw_deg"))

    def _pack(self):
        h = 0.5 * np.asarray(self.size)
        return _BOX, np.asarray(self.centre), self.yaw_deg, -h, h, (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Stairs:
    """A flight of solid steps (see the module docstring for the geometry).

    Parameters
    ----------
    start : (2,) or (3,) array_like
        Bottom of the first riser, middle of the flight, map frame [m]; z defaults to 0.
    heading_deg : float
        Direction of ascent about map z [deg].
    rise, run : float
        Height and depth of one step [m], > 0.
    count : int
        Number of steps, >= 1.
    width : float
        Width of the flight [m], > 0.
    """

    start: tuple
    heading_deg: float = 0.0
    rise: float = 0.17
    run: float = 0.29
    count: int = 6
    width: float = 1.2

    def __post_init__(self):
        object.__setattr__(self, "start", tuple(_start3(self.start, "Stairs.start").tolist()))
        object.__setattr__(self, "heading_deg", _finite(self.heading_deg, "Stairs.heading_deg"))
        for name in ("rise", "run", "width"):
            object.__setattr__(self, name, check_positive_scalar(getattr(self, name), f"Stairs.{name}",
                                                                 upper=100.0, unit=" m"))
        c = self.count
        if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or not 1 <= c <= 10000:
            raise ValueError(f"Stairs.count must be an integer in [1, 10000], got {self.count!r}")
        object.__setattr__(self, "count", int(self.count))

    @property
    def top(self) -> float:
        """Height of the top step above the start [m]."""
        return self.count * self.rise

    @property
    def length(self) -> float:
        """Horizontal length of the flight [m]."""
        return self.count * self.run

    def _pack(self):
        lo = np.array([0.0, -0.5 * self.width, 0.0])
        hi = np.array([self.length, 0.5 * self.width, self.top])
        return _STAIRS, np.asarray(self.start), self.heading_deg, lo, hi, (self.run, self.rise, float(self.count))

    def steps(self) -> list[Box]:
        """The steps as boxes (what the NumPy reference renders)."""
        c, s = math.cos(math.radians(self.heading_deg)), math.sin(math.radians(self.heading_deg))
        out = []
        for k in range(self.count):
            lx, lz = (k + 0.5) * self.run, 0.5 * (k + 1) * self.rise
            centre = (self.start[0] + c * lx, self.start[1] + s * lx, self.start[2] + lz)
            out.append(Box(centre, (self.run, self.width, (k + 1) * self.rise), self.heading_deg))
        return out


@dataclass(frozen=True)
class Ramp:
    """A solid wedge rising along its heading (see the module docstring).

    Parameters
    ----------
    start : (2,) or (3,) array_like
        Middle of the ramp's bottom front edge, map frame [m]; z defaults to 0.
    heading_deg : float
        Direction of ascent [deg].
    length, width, rise : float
        Horizontal length, width and total rise [m], > 0.
    """

    start: tuple
    heading_deg: float = 0.0
    length: float = 3.0
    width: float = 2.0
    rise: float = 0.5

    def __post_init__(self):
        object.__setattr__(self, "start", tuple(_start3(self.start, "Ramp.start").tolist()))
        object.__setattr__(self, "heading_deg", _finite(self.heading_deg, "Ramp.heading_deg"))
        for name in ("length", "width", "rise"):
            object.__setattr__(self, name, check_positive_scalar(getattr(self, name), f"Ramp.{name}",
                                                                 upper=1000.0, unit=" m"))

    @property
    def slope(self) -> float:
        return self.rise / self.length

    def _pack(self):
        lo = np.array([0.0, -0.5 * self.width, 0.0])
        hi = np.array([self.length, 0.5 * self.width, self.rise])
        return _RAMP, np.asarray(self.start), self.heading_deg, lo, hi, (self.slope, self.length, 0.0)


@dataclass(frozen=True)
class Target:
    """A vertical planar target (a board of zero thickness), two-sided.

    Parameters
    ----------
    centre : (3,) array_like
        Centre of the board, map frame [m].
    width, height : float
        Horizontal and vertical extent [m], > 0.
    yaw_deg : float
        Direction of the board's normal about map z [deg] (0: the board faces map +x, i.e. a camera
        looking along -x sees it head-on; the board is two-sided, so one looking along +x does too).
    """

    centre: tuple
    width: float = 1.0
    height: float = 1.0
    yaw_deg: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "centre", tuple(_vector(self.centre, (3,), "Target.centre").tolist()))
        for name in ("width", "height"):
            object.__setattr__(self, name, check_positive_scalar(getattr(self, name), f"Target.{name}",
                                                                 upper=1000.0, unit=" m"))
        object.__setattr__(self, "yaw_deg", _finite(self.yaw_deg, "Target.yaw_deg"))

    def _pack(self):
        h = np.array([0.0, 0.5 * self.width, 0.5 * self.height])
        return _BOX, np.asarray(self.centre), self.yaw_deg, -h, h, (0.0, 0.0, 0.0)


@dataclass(frozen=True, eq=False)
class HeightField:
    """Heights on a regular, axis-aligned grid; the surface is bilinear in each cell.

    Parameters
    ----------
    heights : array_like, shape (nx, ny)
        Height [m] of node (i, j) at (origin[0] + i resolution, origin[1] + j resolution); i along
        map +x. nx, ny >= 2.
    origin : (2,) array_like
        Map-frame xy of node (0, 0) [m].
    resolution : float
        Node spacing [m], > 0.
    base_z : float, optional
        Bottom of the solid [m] (default: the lowest height); must not exceed any height.
    """

    heights: np.ndarray
    origin: tuple = (0.0, 0.0)
    resolution: float = 0.02
    base_z: float | None = None
    _cell_max: np.ndarray = field(init=False, repr=False)
    _block_max: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        h = np.asarray(self.heights)
        if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
            raise ValueError(f"HeightField.heights must be a 2-D array with at least 2 x 2 nodes, got shape {h.shape}")
        if not (np.issubdtype(h.dtype, np.floating) or np.issubdtype(h.dtype, np.integer)):
            raise ValueError(f"HeightField.heights must be real numbers [m], got dtype {h.dtype}")
        h = np.array(h, dtype=np.float64, order="C")
        if not np.all(np.isfinite(h)):
            raise ValueError(f"HeightField.heights has {int((~np.isfinite(h)).sum())} non-finite value(s)")
        if float(np.abs(h).max()) > 1000.0:
            raise ValueError(f"HeightField.heights reach {float(np.abs(h).max()):.1f}: heights must be in metres")
        h.setflags(write=False)
        object.__setattr__(self, "heights", h)
        object.__setattr__(self, "origin", tuple(_vector(self.origin, (2,), "HeightField.origin").tolist()))
        res = check_positive_scalar(self.resolution, "HeightField.resolution", upper=100.0, unit=" m")
        object.__setattr__(self, "resolution", res)
        base = float(h.min()) if self.base_z is None else _finite(self.base_z, "HeightField.base_z")
        if base > float(h.min()):
            raise ValueError(f"HeightField.base_z = {base} is above the lowest height {float(h.min())}")
        object.__setattr__(self, "base_z", base)
        cm = np.maximum(np.maximum(h[:-1, :-1], h[1:, :-1]), np.maximum(h[:-1, 1:], h[1:, 1:]))
        ncx, ncy = cm.shape
        nbx, nby = -(-ncx // HF_BLOCK), -(-ncy // HF_BLOCK)
        pad = np.full((nbx * HF_BLOCK, nby * HF_BLOCK), -np.inf)
        pad[:ncx, :ncy] = cm
        bm = pad.reshape(nbx, HF_BLOCK, nby, HF_BLOCK).max(axis=(1, 3))
        object.__setattr__(self, "_cell_max", np.ascontiguousarray(cm))
        object.__setattr__(self, "_block_max", np.ascontiguousarray(bm))

    @classmethod
    def from_function(cls, fn: Callable, x_range, y_range, resolution: float = 0.02,
                      base_z: float | None = None) -> "HeightField":
        """Sample z = fn(x, y) onto a grid covering ``x_range`` x ``y_range`` [m].

        ``fn`` takes two arrays of the same shape (map x and y [m]) and returns heights [m] of that
        shape. The grid's nodes start at the ranges' lower ends and step by ``resolution`` up to (and
        covering) their upper ends.
        """
        if not callable(fn):
            raise ValueError(f"fn must be callable z = fn(x, y), got {fn!r}")
        res = check_positive_scalar(resolution, "resolution", upper=100.0, unit=" m")
        xr = _vector(x_range, (2,), "x_range")
        yr = _vector(y_range, (2,), "y_range")
        if not (xr[1] > xr[0] and yr[1] > yr[0]):
            raise ValueError(f"x_range and y_range must be increasing, got {xr.tolist()}, {yr.tolist()}")
        nx = int(math.ceil((xr[1] - xr[0]) / res - 1e-9)) + 1
        ny = int(math.ceil((yr[1] - yr[0]) / res - 1e-9)) + 1
        if nx * ny > 50_000_000:
            raise ValueError(f"height field of {nx} x {ny} nodes is too large; raise resolution")
        X, Y = np.meshgrid(xr[0] + res * np.arange(nx), yr[0] + res * np.arange(ny), indexing="ij")
        z = np.asarray(fn(X, Y), dtype=np.float64)
        if z.shape != X.shape:
            raise ValueError(f"fn returned shape {z.shape}, expected {X.shape} (the shape of its inputs)")
        return cls(z, (xr[0], yr[0]), res, base_z)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x0, x1, y0, y1) of the grid's rectangle [m]."""
        nx, ny = self.heights.shape
        x0, y0 = self.origin
        return x0, x0 + (nx - 1) * self.resolution, y0, y0 + (ny - 1) * self.resolution

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Bilinear height at (M, 2) map points [m]; NaN outside the grid's (closed) rectangle."""
        nx, ny = self.heights.shape
        gx = (xy[:, 0] - self.origin[0]) / self.resolution
        gy = (xy[:, 1] - self.origin[1]) / self.resolution
        inside = (gx >= 0) & (gx <= nx - 1) & (gy >= 0) & (gy <= ny - 1)
        i = np.clip(np.floor(gx), 0, nx - 2).astype(np.int64)
        j = np.clip(np.floor(gy), 0, ny - 2).astype(np.int64)
        i[~inside] = 0
        j[~inside] = 0
        s = np.where(inside, gx - i, 0.0)
        r = np.where(inside, gy - j, 0.0)
        h = self.heights
        z = (h[i, j] * (1 - s) * (1 - r) + h[i + 1, j] * s * (1 - r) + h[i, j + 1] * (1 - s) * r
             + h[i + 1, j + 1] * s * r)
        return np.where(inside, z, np.nan)


# ---------------------------------------------------------------------------------------------
# the scene
# ---------------------------------------------------------------------------------------------
class _Packed:
    """A scene as flat arrays for the kernels (built once per scene)."""

    def __init__(self, scene: "Scene"):
        box_like = [p for p in scene.primitives if not isinstance(p, HeightField)]
        self.fields = [p for p in scene.primitives if isinstance(p, HeightField)]
        n = len(box_like)
        self.kinds = np.zeros(n, dtype=np.int64)
        self.pf = np.zeros((n, 14))
        for k, p in enumerate(box_like):
            kind, origin, yaw, lo, hi, extra = p._pack()
            a = math.radians(yaw)
            self.kinds[k] = kind
            self.pf[k] = [*origin, math.cos(a), math.sin(a), *lo, *hi, *extra]
        self.ground = np.array([0.0 if scene.ground_z is None else 1.0,
                                0.0 if scene.ground_z is None else scene.ground_z])
        nh = len(self.fields)
        self.hfi = np.zeros((nh, 7), dtype=np.int64)     # nx, ny, off_h, off_cell, off_block, nbx, nby
        self.hff = np.zeros((nh, 5))                     # x0, y0, res, base, hmax
        hv, cm, bm = [np.zeros(0)], [np.zeros(0)], [np.zeros(0)]
        oh = oc = ob = 0
        for k, f in enumerate(self.fields):
            nx, ny = f.heights.shape
            nbx, nby = f._block_max.shape
            self.hfi[k] = [nx, ny, oh, oc, ob, nbx, nby]
            self.hff[k] = [f.origin[0], f.origin[1], f.resolution, f.base_z, float(f.heights.max())]
            hv.append(f.heights.ravel())
            cm.append(f._cell_max.ravel())
            bm.append(f._block_max.ravel())
            oh += nx * ny
            oc += f._cell_max.size
            ob += f._block_max.size
        self.hv, self.cm, self.bm = (np.ascontiguousarray(np.concatenate(a)) for a in (hv, cm, bm))
        self.box_corners = self._box_corners()
        self.field_corners = self._field_corners()

    def _box_corners(self) -> np.ndarray:
        """(n, 8, 3) corners of each box-like primitive's bounding box, map frame [m]."""
        pf = self.pf
        out = np.empty((len(pf), 8, 3))
        for k in range(len(pf)):
            lo, hi = pf[k, 5:8], pf[k, 8:11]
            c, s = pf[k, 3], pf[k, 4]
            loc = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
            out[k, :, 0] = pf[k, 0] + c * loc[:, 0] - s * loc[:, 1]
            out[k, :, 1] = pf[k, 1] + s * loc[:, 0] + c * loc[:, 1]
            out[k, :, 2] = pf[k, 2] + loc[:, 2]
        return out

    def _field_corners(self) -> np.ndarray:
        out = np.empty((len(self.fields), 8, 3))
        for k, f in enumerate(self.fields):
            x0, x1, y0, y1 = f.extent
            out[k] = [[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (f.base_z, float(f.heights.max()))]
        return out


class Scene:
    """Terrain made of primitives in the map frame (z up): the ground truth of a simulated walk.

    Parameters
    ----------
    primitives : sequence
        :class:`Box`, :class:`Stairs`, :class:`Ramp`, :class:`HeightField`, :class:`Target`. Exact
        ties in rendering go to the ground, then the other primitives in this order, then the
        height fields in this order.
    ground_z : float or None
        Height of the ground plane (the solid half-space below it) [m]; None = no ground.

    Notes
    -----
    Convenience scenes: :meth:`stairs_scene`, :meth:`box_field`, :meth:`slope`, :meth:`rough`, or
    by name with :meth:`named` (``"stairs"``, ``"boxes"``, ``"slope"``, ``"rough"``). Ground truth:
    :meth:`height_at`, :meth:`height_grid`; :meth:`contains` tests points against the solids.
    """

    #: Names accepted by :meth:`named`.
    NAMES = ("stairs", "boxes", "slope", "rough")

    _KINDS = (Box, Stairs, Ramp, HeightField, Target)

    def __init__(self, primitives: Sequence = (), ground_z: float | None = 0.0):
        prims = tuple(primitives)
        for k, p in enumerate(prims):
            if not isinstance(p, self._KINDS):
                raise ValueError(f"primitives[{k}] must be a Box, Stairs, Ramp, HeightField or Target, "
                                 f"got {type(p).__name__}")
        self._primitives = prims
        self._ground_z = None if ground_z is None else _finite(ground_z, "ground_z")
        if self._ground_z is not None and abs(self._ground_z) > _LIMIT_M:
            raise ValueError(f"ground_z = {self._ground_z} is implausibly far; check its units")
        self._packed = None

    @property
    def primitives(self) -> tuple:
        """The primitives, in tie-breaking order (read only: make a new scene to change them)."""
        return self._primitives

    @property
    def ground_z(self) -> float | None:
        """Height of the ground plane [m], or None."""
        return self._ground_z

    def __repr__(self) -> str:
        kinds = ", ".join(type(p).__name__ for p in self.primitives)
        return f"Scene(ground_z={self.ground_z}, primitives=[{kinds}])"

    def with_primitives(self, *primitives) -> "Scene":
        """A new scene with ``primitives`` appended."""
        return Scene(self.primitives + tuple(primitives), self.ground_z)

    @property
    def packed(self) -> _Packed:
        """The scene as flat arrays for the kernels (built on first use)."""
        if self._packed is None:
            self._packed = _Packed(self)
        return self._packed

    # -- convenience scenes (``--scene stairs|boxes|slope|rough``) -------------------------------
    @classmethod
    def named(cls, name: str, rng: np.random.Generator | None = None) -> "Scene":
        """The convenience scene called ``name`` (one of :attr:`NAMES`) with its defaults; ``boxes``
        and ``rough`` are random and need ``rng``."""
        if name == "stairs":
            return cls.stairs_scene()
        if name == "boxes":
            return cls.box_field(rng)
        if name == "slope":
            return cls.slope()
        if name == "rough":
            return cls.rough(rng)
        raise ValueError(f"unknown scene {name!r}; choose from {', '.join(cls.NAMES)}")

    @classmethod
    def stairs_scene(cls, start_x_m: float = 1.5, rise_m: float = 0.17, run_m: float = 0.29, count: int = 6,
                     width_m: float = 1.2, landing_m: float = 1.5) -> "Scene":
        """Ground at 0, a flight of ``count`` steps starting ``start_x_m`` ahead (along +x), a landing.

        The landing is a box as wide as the flight, ``landing_m`` deep, level with the top step.
        """
        st = Stairs((start_x_m, 0.0), 0.0, rise_m, run_m, count, width_m)
        landing_m = check_positive_scalar(landing_m, "landing_m", upper=100.0, unit=" m")
        land = Box((start_x_m + st.length + 0.5 * landing_m, 0.0, 0.5 * st.top), (landing_m, width_m, st.top))
        return cls([st, land], ground_z=0.0)

    @classmethod
    def box_field(cls, rng: np.random.Generator, n_boxes: int = 15, x_range=(1.0, 6.0), y_range=(-2.5, 2.5),
                  height_range=(0.05, 0.30), size_range=(0.2, 0.8)) -> "Scene":
        """Ground at 0 and ``n_boxes`` random yawed boxes resting on it (heights 0.05-0.3 m by default)."""
        rng = _rng(rng)
        if isinstance(n_boxes, bool) or not isinstance(n_boxes, (int, np.integer)) or not 0 <= n_boxes <= 10000:
            raise ValueError(f"n_boxes must be an integer in [0, 10000], got {n_boxes!r}")
        ranges = {}
        for name, r in (("x_range", x_range), ("y_range", y_range), ("height_range", height_range),
                        ("size_range", size_range)):
            a = _vector(r, (2,), name)
            if a[1] < a[0]:
                raise ValueError(f"{name} must be (low, high), got {a.tolist()}")
            ranges[name] = a
        if ranges["height_range"][0] <= 0 or ranges["size_range"][0] <= 0:
            raise ValueError("height_range and size_range must be > 0 [m]")
        boxes = []
        for _ in range(int(n_boxes)):
            x, y = rng.uniform(*ranges["x_range"]), rng.uniform(*ranges["y_range"])
            sx, sy = rng.uniform(*ranges["size_range"], size=2)
            h = rng.uniform(*ranges["height_range"])
            boxes.append(Box((x, y, 0.5 * h), (sx, sy, h), rng.uniform(0.0, 180.0)))
        return cls(boxes, ground_z=0.0)

    @classmethod
    def slope(cls, angle_deg: float = 10.0, start_x_m: float = 1.5, length_m: float = 3.0, width_m: float = 2.5,
              top_m: float = 2.0) -> "Scene":
        """Ground at 0, a ramp of ``angle_deg`` rising along +x from ``start_x_m``, a level top."""
        a = check_positive_scalar(angle_deg, "angle_deg", upper=80.0, unit=" deg")
        ramp = Ramp((start_x_m, 0.0), 0.0, length_m, width_m, length_m * math.tan(math.radians(a)))
        top_m = check_positive_scalar(top_m, "top_m", upper=100.0, unit=" m")
        top = Box((start_x_m + length_m + 0.5 * top_m, 0.0, 0.5 * ramp.rise), (top_m, width_m, ramp.rise))
        return cls([ramp, top], ground_z=0.0)

    @classmethod
    def rough(cls, rng: np.random.Generator, relief_m: float = 0.05, correlation_m: float = 0.25,
              x_range=(-2.0, 10.0), y_range=(-6.0, 6.0), resolution_m: float = 0.02) -> "Scene":
        """A smooth random height field: white noise smoothed over ``correlation_m`` (Gaussian sigma),
        scaled to heights in [0, ``relief_m``]; ground at 0 beyond the field."""
        from scipy.ndimage import gaussian_filter

        rng = _rng(rng)
        relief = check_positive_scalar(relief_m, "relief_m", upper=10.0, unit=" m")
        corr = check_positive_scalar(correlation_m, "correlation_m", upper=100.0, unit=" m")
        res = check_positive_scalar(resolution_m, "resolution_m", upper=10.0, unit=" m")
        xr = _vector(x_range, (2,), "x_range")
        yr = _vector(y_range, (2,), "y_range")
        if not (xr[1] > xr[0] and yr[1] > yr[0]):
            raise ValueError(f"x_range and y_range must be increasing, got {xr.tolist()}, {yr.tolist()}")
        nx = int(round((xr[1] - xr[0]) / res)) + 1
        ny = int(round((yr[1] - yr[0]) / res)) + 1
        if nx * ny > 50_000_000:
            raise ValueError(f"height field of {nx} x {ny} nodes is too large; raise resolution_m")
        g = gaussian_filter(rng.standard_normal((nx, ny)), corr / res, mode="reflect")
        g = (g - g.min()) / max(float(g.max() - g.min()), 1e-300) * relief
        return cls([HeightField(g, (xr[0], yr[0]), res, base_z=0.0)], ground_z=0.0)

    # -- ground truth ------------------------------------------------------------------------------
    def _local(self, xy: np.ndarray, k: int):
        pf = self.packed.pf[k]
        dx, dy = xy[:, 0] - pf[0], xy[:, 1] - pf[1]
        return pf[3] * dx + pf[4] * dy, -pf[4] * dx + pf[3] * dy

    def height_at(self, xy) -> np.ndarray:
        """True terrain height: the highest top surface of any primitive over each point.

        Parameters
        ----------
        xy : array_like, shape (M, 2) or (2,)
            Map-frame points [m].

        Returns
        -------
        ndarray, shape (M,)
            Height [m], NaN where no primitive covers the point (footprints are closed sets; a
            vertical :class:`Target` has no footprint).
        """
        try:
            a = np.asarray(xy, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"xy must be numbers with shape (M, 2), got {xy!r}") from None
        if a.ndim == 1 and a.shape == (2,):
            a = a[None, :]
        if a.ndim != 2 or a.shape[1] != 2:
            raise ValueError(f"xy must have shape (M, 2), got {np.shape(xy)}")
        if not np.all(np.isfinite(a)):
            raise ValueError("xy has non-finite entries")
        out = np.full(len(a), -np.inf)
        if self.ground_z is not None:
            out[:] = self.ground_z
        pk = self.packed
        for k in range(len(pk.pf)):
            pf = pk.pf[k]
            if pk.kinds[k] == _BOX and pf[5] == pf[8]:          # a Target: no footprint
                continue
            lx, ly = self._local(a, k)
            inside = (lx >= pf[5]) & (lx <= pf[8]) & (ly >= pf[6]) & (ly <= pf[9])
            if pk.kinds[k] == _BOX:
                top = np.full(len(a), pf[2] + pf[10])
            elif pk.kinds[k] == _STAIRS:
                run, rise, count = pf[11], pf[12], int(pf[13])
                step = np.clip(np.floor(lx / run), 0, count - 1)
                top = pf[2] + (step + 1) * rise
            else:
                top = pf[2] + pf[11] * lx
            out = np.where(inside, np.maximum(out, top), out)
        for f in pk.fields:
            h = f.height_at(a)
            out = np.where(np.isfinite(h), np.maximum(out, h), out)
        return np.where(np.isfinite(out), out, np.nan)

    def height_grid(self, x_centres, y_centres) -> np.ndarray:
        """:meth:`height_at` on a grid: shape (len(x_centres), len(y_centres)), [i, j] at
        (x_centres[i], y_centres[j]) (the map-index order of ``docs/conventions.md``) [m]."""
        xs = np.asarray(x_centres, dtype=np.float64)
        ys = np.asarray(y_centres, dtype=np.float64)
        if xs.ndim != 1 or ys.ndim != 1:
            raise ValueError(f"x_centres and y_centres must be 1-D, got shapes {xs.shape}, {ys.shape}")
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        return self.height_at(np.column_stack([X.ravel(), Y.ravel()])).reshape(X.shape)

    def contains(self, points) -> np.ndarray:
        """Whether map points (M, 3) [m] lie inside (or on) any solid; targets have no volume."""
        try:
            p = np.asarray(points, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"points must be numbers with shape (M, 3), got {points!r}") from None
        if p.ndim == 1 and p.shape == (3,):
            p = p[None, :]
        if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
            raise ValueError(f"points must be finite with shape (M, 3), got {np.shape(points)}")
        out = np.zeros(len(p), dtype=bool)
        if self.ground_z is not None:
            out |= p[:, 2] <= self.ground_z
        pk = self.packed
        for k in range(len(pk.pf)):
            pf = pk.pf[k]
            if pk.kinds[k] == _BOX and pf[5] == pf[8]:
                continue
            lx, ly = self._local(p[:, :2], k)
            lz = p[:, 2] - pf[2]
            inside = ((lx >= pf[5]) & (lx <= pf[8]) & (ly >= pf[6]) & (ly <= pf[9]) & (lz >= pf[7])
                      & (lz <= pf[10]))
            if pk.kinds[k] == _STAIRS:
                step = np.clip(np.floor(lx / pf[11]), 0, int(pf[13]) - 1)
                inside &= lz <= (step + 1) * pf[12]
            elif pk.kinds[k] == _RAMP:
                inside &= lz <= pf[11] * lx
            out |= inside
        for f in pk.fields:
            h = f.height_at(p[:, :2])
            out |= np.isfinite(h) & (p[:, 2] >= f.base_z) & (p[:, 2] <= np.where(np.isfinite(h), h, -np.inf))
        return out


# ---------------------------------------------------------------------------------------------
# numba ray casting
# ---------------------------------------------------------------------------------------------
@njit(**JIT)
def _slab(o, d, lo, hi):
    """Entry and exit t of the ray o + t d through the closed slab lo <= x <= hi."""
    if d == 0.0:
        if lo <= o and o <= hi:
            return -np.inf, np.inf
        return np.inf, -np.inf
    t1 = (lo - o) / d
    t2 = (hi - o) / d
    if d > 0.0:
        return t1, t2
    return t2, t1


@njit(**JIT)
def _boxlike_hit(kind, lox, loy, loz, ldx, ldy, ldz, bx0, by0, bz0, bx1, by1, bz1, p0, p1, p2, t_limit):
    """First hit (t, face) of a ray, in a primitive's local frame, with a box, stairs or ramp.

    face: 0..5 = -x, +x, -y, +y, -z, +z of the local frame, 6 = the ramp's slope; -1 = the ray
    starts inside; t = inf for a miss."""
    tn, tf = _slab(lox, ldx, bx0, bx1)
    face = 0 if ldx > 0.0 else 1
    a, b = _slab(loy, ldy, by0, by1)
    if a > tn:
        tn = a
        face = 2 if ldy > 0.0 else 3
    if b < tf:
        tf = b
    a, b = _slab(loz, ldz, bz0, bz1)
    if a > tn:
        tn = a
        face = 4 if ldz > 0.0 else 5
    if b < tf:
        tf = b
    if kind == 2:       # ramp: the half-space z <= slope x
        g0 = loz - p0 * lox
        g1 = ldz - p0 * ldx
        if g1 == 0.0:
            if g0 > 0.0:
                return np.inf, -1
        else:
            tq = -g0 / g1
            if g1 < 0.0:
                if tq > tn:
                    tn = tq
                    face = 6
            elif tq < tf:
                tf = tq
    if tn > tf or tf < 0.0 or tn > t_limit:
        return np.inf, -1
    if tn < 0.0:
        tn = 0.0
        face = -1
    if kind != 1:
        return tn, face
    # stairs: walk the step columns the ray crosses inside the bounding box
    run = p0
    rise = p1
    count = np.int64(p2)
    t0 = tn
    k = np.int64(math.floor((lox + ldx * t0) / run))
    k = min(max(k, 0), count - 1)
    while True:
        if ldx > 0.0:
            te = ((k + 1) * run - lox) / ldx
        elif ldx < 0.0:
            te = (k * run - lox) / ldx
        else:
            te = np.inf
        if te > tf:
            te = tf
        top = (k + 1) * rise
        if loz + ldz * t0 <= top:
            return t0, face
        if loz + ldz * te <= top:
            th = (top - loz) / ldz
            return min(max(th, t0), te), 5
        if te >= tf or te > t_limit:
            return np.inf, -1
        if ldx > 0.0:
            k += 1
            face = 0
        else:
            k -= 1
            face = 1
        if k < 0 or k >= count:
            return np.inf, -1
        t0 = te


@njit(**JIT)
def _bilinear_first_tau(h00, h10, h01, h11, s, r, zin, gdx, gdy, dz, tau_max):
    """Smallest tau in [0, tau_max] where the ray is on or under the bilinear patch; -1 if none.

    (s, r): the ray's cell coordinates at tau = 0, zin its z; per unit tau it moves (gdx, gdy) cells
    and dz metres. f(tau) = h(s + gdx tau, r + gdy tau) - (zin + dz tau) = C + B tau + A tau^2."""
    a1 = h10 - h00
    a2 = h01 - h00
    a3 = h11 - h10 - h01 + h00
    C = h00 + a1 * s + a2 * r + a3 * s * r - zin
    if C >= 0.0:
        return 0.0
    B = a1 * gdx + a2 * gdy + a3 * (s * gdy + r * gdx) - dz
    A = a3 * gdx * gdy
    if A == 0.0:
        if B > 0.0:
            tau = -C / B
            if tau <= tau_max:
                return tau
        return -1.0
    disc = B * B - 4.0 * A * C
    if disc < 0.0:
        return -1.0
    sq = math.sqrt(disc)
    q = -0.5 * (B + sq) if B >= 0.0 else -0.5 * (B - sq)
    r1 = q / A
    r2 = C / q if q != 0.0 else np.inf
    lo = min(r1, r2)
    hi = max(r1, r2)
    if lo >= 0.0 and lo <= tau_max:
        return lo
    if hi >= 0.0 and hi <= tau_max:
        return hi
    return -1.0


@njit(**JIT)
def _surface_theta(a1, a2, a3, s, r, res, ax, ay, az):
    hx = (a1 + a3 * r) / res
    hy = (a2 + a3 * s) / res
    c = abs(az - hx * ax - hy * ay) / math.sqrt(1.0 + hx * hx + hy * hy)
    return math.acos(min(c, 1.0))


@njit(**JIT)
def _floor_index(x, lo, hi):
    k = np.int64(math.floor(x))
    return min(max(k, lo), hi)


@njit(**JIT)
def _index_range(p0, p1, gd, lo, hi):
    """Cells [start .. stop] (inclusive, in steps of step) that a ray moving gd per unit t crosses
    from grid coordinate p0 to p1, clamped to [lo, hi]; one extra cell at each end when it moves,
    so that rounding at a cell border cannot drop a cell (cells it misses have empty intervals)."""
    a = _floor_index(p0, lo, hi)
    b = _floor_index(p1, lo, hi)
    if gd > 0.0:
        return max(a - 1, lo), min(b + 1, hi), 1
    if gd < 0.0:
        return min(a + 1, hi), max(b - 1, lo), -1
    return a, a, 1


@njit(**JIT)
def _interval(go, gd, b0, b1, t0, t1):
    """[t0, t1] intersected with the ray's t-interval inside b0 <= go + gd t <= b1."""
    if gd == 0.0:
        return t0, t1
    a = (b0 - go) / gd
    b = (b1 - go) / gd
    if gd < 0.0:
        a, b = b, a
    return max(a, t0), min(b, t1)


@njit(**JIT)
def _field_hit(hv, cm, bm, nx, ny, oh, oc, ob, nbx, nby, x0, y0, res, base, hmax, tab,
               ox, oy, oz, dx, dy, dz, ax, ay, az, t_limit):
    """First hit (t, theta) of a ray with a height field; t = inf for a miss.

    Cells are visited in the order the ray crosses them: block columns along the ray's x, blocks
    along its y, then the cells of a block likewise; a block or cell is skipped when the ray's lowest
    z over it is above its maximum height."""
    ncx = nx - 1
    ncy = ny - 1
    gox = (ox - x0) / res
    goy = (oy - y0) / res
    gdx = dx / res
    gdy = dy / res
    tn, tf = _slab(gox, gdx, 0.0, ncx)
    face = 0 if gdx > 0.0 else 1
    a, b = _slab(goy, gdy, 0.0, ncy)
    if a > tn:
        tn = a
        face = 2 if gdy > 0.0 else 3
    if b < tf:
        tf = b
    a, b = _slab(oz, dz, base, hmax)
    if a > tn:
        tn = a
        face = 4 if dz > 0.0 else 5
    if b < tf:
        tf = b
    if tn > tf or tf < 0.0:
        return np.inf, np.nan
    ta = max(tn, 0.0)
    tb = min(tf, t_limit)
    if ta > tb:
        return np.inf, np.nan
    B = HF_BLOCK
    Ia, Ib, sI = _index_range((gox + gdx * ta) / B, (gox + gdx * tb) / B, gdx, 0, nbx - 1)
    for I in range(Ia, Ib + sI, sI):
        xl = I * B
        xh = min(xl + B, ncx)
        c0, c1 = _interval(gox, gdx, xl, xh, ta, tb)
        if c0 > c1:
            continue
        Ja, Jb, sJ = _index_range((goy + gdy * c0) / B, (goy + gdy * c1) / B, gdy, 0, nby - 1)
        for J in range(Ja, Jb + sJ, sJ):
            yl = J * B
            yh = min(yl + B, ncy)
            e0, e1 = _interval(goy, gdy, yl, yh, c0, c1)
            if e0 > e1:
                continue
            if min(oz + dz * e0, oz + dz * e1) > bm[ob + I * nby + J]:
                continue
            ia, ib, si = _index_range(gox + gdx * e0, gox + gdx * e1, gdx, xl, xh - 1)
            for i in range(ia, ib + si, si):
                f0, f1 = _interval(gox, gdx, i, i + 1, e0, e1)
                if f0 > f1:
                    continue
                ja, jb, sj = _index_range(goy + gdy * f0, goy + gdy * f1, gdy, yl, yh - 1)
                for j in range(ja, jb + sj, sj):
                    g0, g1 = _interval(goy, gdy, j, j + 1, f0, f1)
                    if g0 > g1:
                        continue
                    if min(oz + dz * g0, oz + dz * g1) > cm[oc + i * ncy + j]:
                        continue
                    h00 = hv[oh + i * ny + j]
                    h01 = hv[oh + i * ny + j + 1]
                    h10 = hv[oh + (i + 1) * ny + j]
                    h11 = hv[oh + (i + 1) * ny + j + 1]
                    s = min(max(gox + gdx * g0 - i, 0.0), 1.0)
                    r = min(max(goy + gdy * g0 - j, 0.0), 1.0)
                    tau = _bilinear_first_tau(h00, h10, h01, h11, s, r, oz + dz * g0, gdx, gdy, dz, g1 - g0)
                    if tau < 0.0:
                        continue
                    t = g0 + tau
                    if tau == 0.0 and g0 == tn and face <= 4:
                        return t, tab[face]
                    return t, _surface_theta(h10 - h00, h01 - h00, h11 - h10 - h01 + h00, s + gdx * tau,
                                             r + gdy * tau, res, ax, ay, az)
    return np.inf, np.nan


@njit(parallel=True, **JIT)
def _render_kernel(intr, T, rows, ground, kinds, pf, ptab, prect, hfi, hff, hftab, hfrect, hv, cm, bm,
                   max_range, z_out, th_out):
    """Fill z_out, th_out (H, W) row by row (rows[ii] is the ii-th row computed: interleaved so that
    numba's contiguous split of the prange gives each thread rows from all over the image)."""
    H, W = z_out.shape
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    R00, R01, R02 = T[0, 0], T[0, 1], T[0, 2]
    R10, R11, R12 = T[1, 0], T[1, 1], T[1, 2]
    R20, R21, R22 = T[2, 0], T[2, 1], T[2, 2]
    ox, oy, oz = T[0, 3], T[1, 3], T[2, 3]
    ax, ay, az = R02, R12, R22
    has_ground = ground[0] > 0.5
    gz = ground[1]
    gth = ground[2]
    n = kinds.shape[0]
    nh = hfi.shape[0]
    lo = np.empty((n, 3))
    for k in range(n):
        px = ox - pf[k, 0]
        py = oy - pf[k, 1]
        lo[k, 0] = pf[k, 3] * px + pf[k, 4] * py
        lo[k, 1] = -pf[k, 4] * px + pf[k, 3] * py
        lo[k, 2] = oz - pf[k, 2]
    nan = np.nan
    inf = np.inf
    for ii in prange(H):
        v = rows[ii]
        act = np.empty(n, dtype=np.int64)
        na = 0
        for k in range(n):
            if prect[k, 2] <= v and v <= prect[k, 3]:
                act[na] = k
                na += 1
        hact = np.empty(nh, dtype=np.int64)
        nha = 0
        for k in range(nh):
            if hfrect[k, 2] <= v and v <= hfrect[k, 3]:
                hact[nha] = k
                nha += 1
        vp = (v - cy) / fy
        b0 = R01 * vp + R02
        b1 = R11 * vp + R12
        b2 = R21 * vp + R22
        for u in range(W):
            up = (u - cx) / fx
            dx = R00 * up + b0
            dy = R10 * up + b1
            dz = R20 * up + b2
            best = inf
            bth = nan
            if has_ground and dz < 0.0:
                best = (gz - oz) / dz
                bth = gth
            lim = min(best, max_range)
            for m in range(na):
                k = act[m]
                if u < prect[k, 0] or u > prect[k, 1]:
                    continue
                c = pf[k, 3]
                s = pf[k, 4]
                t, face = _boxlike_hit(kinds[k], lo[k, 0], lo[k, 1], lo[k, 2], c * dx + s * dy, -s * dx + c * dy,
                                       dz, pf[k, 5], pf[k, 6], pf[k, 7], pf[k, 8], pf[k, 9], pf[k, 10],
                                       pf[k, 11], pf[k, 12], pf[k, 13], lim)
                if t < best:
                    best = t
                    bth = ptab[k, face] if face >= 0 else nan
                    lim = min(best, max_range)
            for m in range(nha):
                k = hact[m]
                if u < hfrect[k, 0] or u > hfrect[k, 1]:
                    continue
                t, th = _field_hit(hv, cm, bm, hfi[k, 0], hfi[k, 1], hfi[k, 2], hfi[k, 3], hfi[k, 4], hfi[k, 5],
                                   hfi[k, 6], hff[k, 0], hff[k, 1], hff[k, 2], hff[k, 3], hff[k, 4], hftab[k],
                                   ox, oy, oz, dx, dy, dz, ax, ay, az, lim)
                if t < best:
                    best = t
                    bth = th
                    lim = min(best, max_range)
            if best > 0.0 and best <= max_range:
                z_out[v, u] = best
                th_out[v, u] = bth
            else:
                z_out[v, u] = nan
                th_out[v, u] = nan


# ---------------------------------------------------------------------------------------------
# per-frame set-up shared by the kernel and the reference
# ---------------------------------------------------------------------------------------------
_LOCAL_NORMALS = np.array([[-1.0, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]])


def _theta_of(normals: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Angle [rad] between unit normals (..., 3) and the optical axis (3,)."""
    return np.arccos(np.minimum(np.abs(normals @ axis), 1.0))


def _yawed_normals(c: float, s: float, slope: float) -> np.ndarray:
    """(7, 3) map-frame outward normals of a yawed primitive's faces (6 = the ramp's slope)."""
    loc = np.vstack([_LOCAL_NORMALS, np.array([-slope, 0.0, 1.0]) / math.hypot(slope, 1.0)])
    out = loc.copy()
    out[:, 0] = c * loc[:, 0] - s * loc[:, 1]
    out[:, 1] = s * loc[:, 0] + c * loc[:, 1]
    return out


def _image_rects(corners: np.ndarray, K, width, height, T, max_range) -> np.ndarray:
    """(n, 4) int64 conservative pixel rectangles [u0, u1, v0, v1] of bounding boxes (n, 8, 3);
    u0 > u1 for a box no pixel can hit."""
    out = np.empty((len(corners), 4), dtype=np.int64)
    full = np.array([0, width - 1, 0, height - 1])
    R, t = T[:3, :3], T[:3, 3]
    for k in range(len(corners)):
        pc = (corners[k] - t) @ R
        z = pc[:, 2]
        if np.all(z <= 0.0) or np.all(z > max_range):
            out[k] = [1, 0, 1, 0]
            continue
        if np.any(z <= 1e-9):
            out[k] = full
            continue
        u = K[0, 0] * pc[:, 0] / z + K[0, 2]
        v = K[1, 1] * pc[:, 1] / z + K[1, 2]
        r = np.array([math.floor(u.min()) - 1, math.ceil(u.max()) + 1, math.floor(v.min()) - 1,
                      math.ceil(v.max()) + 1], dtype=np.float64)
        if r[1] < 0 or r[0] > width - 1 or r[3] < 0 or r[2] > height - 1:
            out[k] = [1, 0, 1, 0]
            continue
        out[k] = [max(r[0], 0), min(r[1], width - 1), max(r[2], 0), min(r[3], height - 1)]
    return out


def _prepare_render(scene, K, width, height, T_map_cam, max_range_m):
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a Scene, got {type(scene).__name__}")
    K = check_intrinsics(K)
    width, height = _image_size(width, height)
    T = check_transform(T_map_cam)
    max_range = check_positive_scalar(max_range_m, "max_range_m", upper=1000.0, unit=" m")
    if float(np.abs(T[:3, 3]).max()) > _LIMIT_M:
        raise ValueError(f"T_map_cam translation {T[:3, 3].tolist()} is implausibly far; check its units")
    inside = bool(scene.contains(T[:3, 3])[0])
    return K, width, height, T, max_range, inside


def _blinded(width, height):
    return np.full((height, width), np.nan), np.full((height, width), np.nan)


def render_depth(scene: Scene, K, width: int, height: int, T_map_cam, max_range_m: float = 10.0,
                 nthreads: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free z-depth and incidence angle of a scene seen by a pinhole camera (numba).

    Parameters
    ----------
    scene : Scene
        The terrain (map frame, z up).
    K : array_like, shape (3, 3)
        Intrinsics [px] (any D435 mode, e.g. ``D435.intrinsics(848, 480)``).
    width, height : int
        Image size [px].
    T_map_cam : array_like, shape (4, 4)
        Camera pose: maps camera-frame points (x right, y down, z forward) into the map frame.
    max_range_m : float
        Hits farther than this z-depth are no data [m].
    nthreads : int, optional
        numba threads (numba's current setting by default); the result does not depend on it.

    Returns
    -------
    z_true : ndarray, shape (height, width), float64
        z-depth of the first hit [m] (distance along the optical axis, not ray length); NaN = no hit,
        beyond ``max_range_m``, or the camera is inside a solid.
    theta : ndarray, shape (height, width), float64
        Angle between the hit surface's normal and the optical axis [rad], in [0, pi/2]; NaN where
        z_true is NaN.
    """
    K, width, height, T, max_range, inside = _prepare_render(scene, K, width, height, T_map_cam, max_range_m)
    n = resolve_threads(nthreads)
    if inside:
        return _blinded(width, height)
    pk = scene.packed
    axis = T[:3, 2]
    ptab = np.zeros((len(pk.pf), 7))
    for k in range(len(pk.pf)):
        ptab[k] = _theta_of(_yawed_normals(pk.pf[k, 3], pk.pf[k, 4], pk.pf[k, 11] if pk.kinds[k] == _RAMP else 0.0),
                            axis)
    hftab = np.tile(_theta_of(_LOCAL_NORMALS, axis), (len(pk.fields), 1))
    prect = _image_rects(pk.box_corners, K, width, height, T, max_range)
    hfrect = _image_rects(pk.field_corners, K, width, height, T, max_range)
    ground = np.array([pk.ground[0], pk.ground[1], math.acos(min(abs(axis[2]), 1.0))])
    rows = np.concatenate([np.arange(k, height, n) for k in range(n)]).astype(np.int64)
    intr = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    z = np.empty((height, width))
    th = np.empty((height, width))
    with threads(n):
        _render_kernel(intr, T, rows, ground, pk.kinds, pk.pf, ptab, prect, pk.hfi, pk.hff, hftab, hfrect,
                       pk.hv, pk.cm, pk.bm, max_range, z, th)
    return z, th


# ---------------------------------------------------------------------------------------------
# NumPy reference
# ---------------------------------------------------------------------------------------------
def _slab_np(o, d, lo, hi):
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d
        t2 = (hi - o) / d
    inside = (lo <= o) & (o <= hi)
    near = np.where(d > 0, t1, t2)
    far = np.where(d > 0, t2, t1)
    near = np.where(d == 0, np.where(inside, -np.inf, np.inf), near)
    far = np.where(d == 0, np.where(inside, np.inf, -np.inf), far)
    return near, far


def _box_np(lo_o, ld, bmin, bmax):
    """Vectorised closed slab test in a local frame: (tn, tf, face) per ray."""
    tn, tf = _slab_np(lo_o[0], ld[0], bmin[0], bmax[0])
    face = np.where(ld[0] > 0, 0, 1)
    for a in (1, 2):
        n_, f_ = _slab_np(lo_o[a], ld[a], bmin[a], bmax[a])
        better = n_ > tn
        face = np.where(better, np.where(ld[a] > 0, 2 * a, 2 * a + 1), face)
        tn = np.where(better, n_, tn)
        tf = np.minimum(tf, f_)
    return tn, tf, face


def _first_tau_np(h00, h10, h01, h11, s, r, zin, gdx, gdy, dz, tau_max):
    """Vectorised :func:`_bilinear_first_tau`."""
    a1, a2 = h10 - h00, h01 - h00
    a3 = h11 - h10 - h01 + h00
    C = h00 + a1 * s + a2 * r + a3 * s * r - zin
    B = a1 * gdx + a2 * gdy + a3 * (s * gdy + r * gdx) - dz
    A = a3 * gdx * gdy
    out = np.full(C.shape, -1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        lin = -C / B
        lin_ok = (A == 0) & (B > 0) & (lin <= tau_max)
        disc = B * B - 4.0 * A * C
        sq = np.sqrt(np.maximum(disc, 0.0))
        q = np.where(B >= 0, -0.5 * (B + sq), -0.5 * (B - sq))
        r1 = q / A
        r2 = np.where(q != 0, C / q, np.inf)
    lo, hi = np.minimum(r1, r2), np.maximum(r1, r2)
    quad = (A != 0) & (disc >= 0)
    lo_ok = quad & (lo >= 0) & (lo <= tau_max)
    hi_ok = quad & ~lo_ok & (hi >= 0) & (hi <= tau_max)
    out = np.where(lin_ok, lin, out)
    out = np.where(lo_ok, lo, out)
    out = np.where(hi_ok, hi, out)
    return np.where(C >= 0, 0.0, out)


def _field_reference(f: HeightField, o, d, max_range):
    """Brute force over every cell a ray's clipped segment can touch: (t, normal (N, 3))."""
    N = d.shape[0]
    nx, ny = f.heights.shape
    ncx, ncy = nx - 1, ny - 1
    res = f.resolution
    gox, goy = (o[0] - f.origin[0]) / res, (o[1] - f.origin[1]) / res
    gdx, gdy, dz = d[:, 0] / res, d[:, 1] / res, d[:, 2]
    hmax = float(f.heights.max())
    tn, tf, face = _box_np((np.full(N, gox), np.full(N, goy), np.full(N, o[2])), (gdx, gdy, dz),
                           (0.0, 0.0, f.base_z), (ncx, ncy, hmax))
    ta = np.maximum(tn, 0.0)
    tb = np.minimum(tf, max_range)
    best = np.full(N, np.inf)
    normal = np.full((N, 3), np.nan)
    live = np.flatnonzero((tn <= tf) & (tf >= 0) & (ta <= tb))
    if live.size == 0:
        return best, normal
    h = f.heights
    gx_a, gx_b = gox + gdx[live] * ta[live], gox + gdx[live] * tb[live]
    i_lo = np.clip(np.floor(np.minimum(gx_a, gx_b)) - 1, 0, ncx - 1).astype(np.int64)
    i_hi = np.clip(np.floor(np.maximum(gx_a, gx_b)) + 1, 0, ncx - 1).astype(np.int64)
    for i in range(int(i_lo.min()), int(i_hi.max()) + 1):
        sel = live[(i_lo <= i) & (i <= i_hi)]
        if sel.size == 0:
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            tx1, tx2 = (i - gox) / gdx[sel], (i + 1 - gox) / gdx[sel]
        par = gdx[sel] == 0
        x_in = i == min(max(math.floor(gox), 0), ncx - 1)     # a ray along a cell border: the kernel's cell
        c0 = np.where(par, np.where(x_in, ta[sel], np.inf), np.maximum(np.minimum(tx1, tx2), ta[sel]))
        c1 = np.where(par, np.where(x_in, tb[sel], -np.inf), np.minimum(np.maximum(tx1, tx2), tb[sel]))
        ok = c0 <= c1
        sel, c0, c1 = sel[ok], c0[ok], c1[ok]
        if sel.size == 0:
            continue
        gy_a, gy_b = goy + gdy[sel] * c0, goy + gdy[sel] * c1
        j_lo = np.clip(np.floor(np.minimum(gy_a, gy_b)) - 1, 0, ncy - 1).astype(np.int64)
        j_hi = np.clip(np.floor(np.maximum(gy_a, gy_b)) + 1, 0, ncy - 1).astype(np.int64)
        for step in range(int((j_hi - j_lo).max()) + 1):
            j = j_lo + step
            m = j <= j_hi
            rs, j, cc0, cc1 = sel[m], j[m], c0[m], c1[m]
            with np.errstate(divide="ignore", invalid="ignore"):
                ty1, ty2 = (j - goy) / gdy[rs], (j + 1 - goy) / gdy[rs]
            par = gdy[rs] == 0
            y_in = j == min(max(math.floor(goy), 0), ncy - 1)
            g0 = np.where(par, np.where(y_in, cc0, np.inf), np.maximum(np.minimum(ty1, ty2), cc0))
            g1 = np.where(par, np.where(y_in, cc1, -np.inf), np.minimum(np.maximum(ty1, ty2), cc1))
            ok = g0 <= g1
            rs, j, g0, g1 = rs[ok], j[ok], g0[ok], g1[ok]
            if rs.size == 0:
                continue
            h00, h01, h10, h11 = h[i, j], h[i, j + 1], h[i + 1, j], h[i + 1, j + 1]
            s = np.clip(gox + gdx[rs] * g0 - i, 0.0, 1.0)
            r = np.clip(goy + gdy[rs] * g0 - j, 0.0, 1.0)
            tau = _first_tau_np(h00, h10, h01, h11, s, r, o[2] + dz[rs] * g0, gdx[rs], gdy[rs], dz[rs], g1 - g0)
            t = g0 + tau
            better = (tau >= 0) & (t < best[rs])
            if not better.any():
                continue
            rs, t, tau, g0 = rs[better], t[better], tau[better], g0[better]
            s, r = s[better] + gdx[rs] * tau, r[better] + gdy[rs] * tau
            a1, a2 = (h10 - h00)[better], (h01 - h00)[better]
            a3 = (h11 - h10 - h01 + h00)[better]
            hx, hy = (a1 + a3 * r) / res, (a2 + a3 * s) / res
            nrm = np.column_stack([-hx, -hy, np.ones_like(hx)]) / np.sqrt(1 + hx * hx + hy * hy)[:, None]
            wall = (tau == 0) & (g0 == tn[rs]) & (face[rs] <= 4)
            nrm[wall] = _LOCAL_NORMALS[face[rs][wall]]
            best[rs] = t
            normal[rs] = nrm
    return best, normal


def render_depth_reference(scene: Scene, K, width: int, height: int, T_map_cam,
                           max_range_m: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """NumPy reference of :func:`render_depth` (slow; same arguments and results).

    Independent of the kernel's traversals: stairs are rendered as their steps (one box each) and
    height fields by brute force over every cell a ray's segment can touch; no image-space culling;
    theta from per-pixel normal vectors.
    """
    K, width, height, T, max_range, inside = _prepare_render(scene, K, width, height, T_map_cam, max_range_m)
    if inside:
        return _blinded(width, height)
    R, o = T[:3, :3], T[:3, 3]
    u = (np.arange(width) - K[0, 2]) / K[0, 0]
    v = (np.arange(height) - K[1, 2]) / K[1, 1]
    U, V = np.meshgrid(u, v)
    d = np.stack([U.ravel(), V.ravel(), np.ones(U.size)], axis=1) @ R.T        # (N, 3), t = z-depth
    N = d.shape[0]
    best = np.full(N, np.inf)
    normal = np.full((N, 3), np.nan)

    def update(t, nrm):
        better = t < best
        best[better] = t[better]
        normal[better] = nrm[better] if nrm.ndim == 2 else nrm

    if scene.ground_z is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(d[:, 2] < 0, (scene.ground_z - o[2]) / d[:, 2], np.inf)
        update(t, np.array([0.0, 0.0, 1.0]))
    for p in scene.primitives:
        if isinstance(p, HeightField):
            continue
        boxes = p.steps() if isinstance(p, Stairs) else [p]
        for b in boxes:
            kind, origin, yaw, lo, hi, extra = b._pack()
            c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
            rel = o - origin
            lo_o = (c * rel[0] + s * rel[1], -s * rel[0] + c * rel[1], rel[2])
            ld = (c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2])
            tn, tf, face = _box_np(lo_o, ld, lo, hi)
            if kind == _RAMP:
                slope = extra[0]
                g0 = lo_o[2] - slope * lo_o[0]
                g1 = ld[2] - slope * ld[0]
                with np.errstate(divide="ignore", invalid="ignore"):
                    tq = -g0 / g1
                enter = (g1 < 0) & (tq > tn)
                face = np.where(enter, 6, face)
                tn = np.where(enter, tq, tn)
                tf = np.where((g1 > 0) & (tq < tf), tq, tf)
                tf = np.where((g1 == 0) & (g0 > 0), -np.inf, tf)
            hit = (tn <= tf) & (tf >= 0)
            t = np.where(hit, np.maximum(tn, 0.0), np.inf)
            nrm = _yawed_normals(c, s, extra[0] if kind == _RAMP else 0.0)[face]
            update(t, nrm)
    for f in scene.primitives:
        if isinstance(f, HeightField):
            t, nrm = _field_reference(f, o, d, max_range)
            update(t, nrm)
    ok = (best > 0) & (best <= max_range)
    z = np.where(ok, best, np.nan).reshape(height, width)
    theta = np.where(ok, _theta_of(np.nan_to_num(normal), R[:, 2]), np.nan).reshape(height, width)
    return z, theta


# ---------------------------------------------------------------------------------------------
# noise
# ---------------------------------------------------------------------------------------------
def add_noise(z_true, theta, rng: np.random.Generator, model: SensorModel | None = D435,
              effects: Sequence[Callable] | None = None, depth_scale: float = 0.001,
              context: dict | None = None) -> np.ndarray:
    """A depth frame from a noise-free render: the reference simulation of the paper's model.

    Parameters
    ----------
    z_true : array_like, shape (H, W)
        Noise-free z-depth [m]; NaN = no hit.
    theta : array_like, shape (H, W)
        Incidence angle [rad], finite wherever z_true is.
    rng : numpy.random.Generator
        Source of all randomness (required).
    model : SensorModel or None
        Axial noise sigma_z(z_true, theta) of this model; None = no noise (only quantisation).
    effects : sequence of callables, optional
        ``effect(z, theta, rng, context) -> z`` applied in order to the noisy metric depth before
        quantisation (contract in the module docstring).
    depth_scale : float
        Metres per depth unit (D435 default 0.001).
    context : dict, optional
        Extra context for the effects (``K``, ``index``, ...); ``width``, ``height``,
        ``depth_scale``, ``z_true`` are filled in; ``K`` defaults to None and ``index`` to 0.

    Returns
    -------
    ndarray, shape (H, W), uint16
        round(z / depth_scale); 0 = no data (no hit, z <= 0, not finite, or beyond 65535 units).
    """
    z_t = np.asarray(z_true)
    th = np.asarray(theta)
    if z_t.ndim != 2 or z_t.shape[0] < 1 or z_t.shape[1] < 1:
        raise ValueError(f"z_true must be a 2-D image (H, W), got shape {z_t.shape}")
    if not np.issubdtype(z_t.dtype, np.floating):
        raise ValueError(f"z_true must be floating-point metres (NaN = no hit), got dtype {z_t.dtype}")
    if th.shape != z_t.shape:
        raise ValueError(f"theta must have z_true's shape {z_t.shape}, got {th.shape}")
    if not np.issubdtype(th.dtype, np.floating):
        raise ValueError(f"theta must be floating-point radians, got dtype {th.dtype}")
    z_t = z_t.astype(np.float64, copy=False)
    th = th.astype(np.float64, copy=False)
    rng = _rng(rng)
    scale = check_positive_scalar(depth_scale, "depth_scale", upper=0.1, unit=" m per unit")
    if model is not None and not isinstance(model, SensorModel):
        raise ValueError(f"model must be a SensorModel or None, got {type(model).__name__}")
    effects = tuple(effects or ())
    for k, e in enumerate(effects):
        if not callable(e):
            raise ValueError(f"effects[{k}] is not callable: {e!r}")
    hit = ~np.isnan(z_t)
    zh = z_t[hit]
    if zh.size:
        if not np.all(np.isfinite(zh)) or float(zh.min()) <= 0:
            raise ValueError("z_true must be finite and > 0 [m] where it is not NaN")
        if float(zh.max()) > 100.0:
            raise ValueError(f"z_true holds values up to {float(zh.max()):.1f}: z_true must be in metres")
        tt = th[hit]
        if not np.all(np.isfinite(tt)):
            raise ValueError("theta must be finite wherever z_true is a hit")
        if float(np.abs(tt).max()) > np.pi:
            raise ValueError(f"theta holds values up to {float(np.abs(tt).max()):.1f}: theta must be in radians")
    if model is None:
        z = z_t.copy()
    else:
        sigma = np.zeros_like(z_t)
        sigma[hit] = _axial_sigma_unchecked(zh, th[hit], model)
        z = z_t + rng.normal(0.0, 1.0, z_t.shape) * sigma
    if effects:
        if context is not None and not isinstance(context, dict):
            raise ValueError(f"context must be a dict or None, got {type(context).__name__}")
        th_ro = th.view()
        th_ro.flags.writeable = False
        z_ro = z_t.view()
        z_ro.flags.writeable = False
        ctx = {"K": None, "index": 0}
        ctx.update(context or {})
        ctx.update(width=z_t.shape[1], height=z_t.shape[0], depth_scale=scale, z_true=z_ro)
        for k, e in enumerate(effects):
            out = np.asarray(e(z, th_ro, rng, ctx))
            if out.shape != z_t.shape or not np.issubdtype(out.dtype, np.floating):
                raise ValueError(f"effects[{k}] must return a float array of shape {z_t.shape}, got "
                                 f"{out.dtype} {out.shape}")
            z = out.astype(np.float64, copy=False)
    with np.errstate(invalid="ignore"):
        units = np.round(z / scale)
        ok = np.isfinite(units) & (z > 0) & (units <= 65535)
    return np.where(ok, units, 0.0).astype(np.uint16)


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
                  nthreads: int | None = None) -> Iterator[dict]:
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
        The reference simulation of the paper's model (with ``model``), or quantisation only.
    effects : sequence of callables, optional
        Extra effects, see :func:`add_noise`.
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
            z, theta = render_depth(scene, K, width, height, T_true, max_range_m, nthreads)
            stamp = i / rate
            ctx = {"K": K, "index": i, "stamp": stamp, "T_map_cam": T_true}
            depth = add_noise(z, theta, rng, noise_model, effects, scale, ctx)
            cov = None if base_covs is None else camera_pose_cov(base_covs[i], reported[i], Tbc)
            yield {"depth": depth, "depth_scale": scale, "K": K.copy(), "T_map_cam": T_rep,
                   "T_map_cam_true": T_true, "pose_cov": cov, "stamp": stamp, "index": i,
                   "T_map_base": reported[i].copy(), "T_map_base_true": poses[i].copy(), "T_base_cam": Tbc.copy()}

    return frames()
