"""Scenes of primitives: the ground truth the simulator renders and the map is scored against.

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

Materials
---------
Every primitive takes an optional infrared ``material`` and the scene a ``ground_material``: a
``Uniform`` or ``Texture`` of :mod:`noise_model.sim.stereo.materials`, or a number, read as a uniform
albedo (Lambertian reflectance at the projector's 850 nm, in [0, 1]; anything else is a ValueError
naming the primitive). Only the physical D435 (:mod:`noise_model.sim.stereo`) reads them, through the
renderer's primitive index (``render_depth(..., return_index=True)``); None (the default) leaves a
surface to that camera's own :class:`~noise_model.sim.stereo.materials.MaterialMap` (white walls and
boxes, a concrete ground unless it is told otherwise). The reference simulation ignores materials.

Ground truth
------------
:meth:`Scene.height_at` is the highest top surface of any primitive over a point (footprints are
closed sets); :meth:`Scene.contains` tests points against the solids. Rendering is in
:mod:`noise_model.sim.render`, which reads the scene through :attr:`Scene.packed`: flat arrays of the
box-like primitives (one kind code and 14 floats each: origin, cos/sin of the yaw, local bounds,
kind-specific extras) and of the height fields (nodes, per-cell and per-block maxima).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..checks import check_positive_scalar
from ._checks import _LIMIT_M, _finite, _rng, _start3, _vector

__all__ = ["Box", "Stairs", "Ramp", "HeightField", "Target", "Scene", "HF_BLOCK"]


#: Cells per side of a height field's coarse max-height block (empty-space skipping).
HF_BLOCK = 8

# primitive kinds in the packed arrays
_BOX, _STAIRS, _RAMP = 0, 1, 2


def _material(value, where: str):
    """None, or the infrared material ``value`` (a number is a uniform albedo in [0, 1]); else ValueError."""
    if value is None:
        return None
    from .stereo.materials import as_material      # the stereo package loads only when a material is given

    return as_material(value, where)


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
    material : Uniform, Texture, float or None
        Infrared material of its faces (module docstring).
    """

    centre: tuple
    size: tuple
    yaw_deg: float = 0.0
    material: object = None

    def __post_init__(self):
        object.__setattr__(self, "material", _material(self.material, "Box.material"))
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
    material : Uniform, Texture, float or None
        Infrared material of the steps (module docstring).
    """

    start: tuple
    heading_deg: float = 0.0
    rise: float = 0.17
    run: float = 0.29
    count: int = 6
    width: float = 1.2
    material: object = None

    def __post_init__(self):
        object.__setattr__(self, "material", _material(self.material, "Stairs.material"))
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
            out.append(Box(centre, (self.run, self.width, (k + 1) * self.rise), self.heading_deg, self.material))
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
    material : Uniform, Texture, float or None
        Infrared material of its faces (module docstring).
    """

    start: tuple
    heading_deg: float = 0.0
    length: float = 3.0
    width: float = 2.0
    rise: float = 0.5
    material: object = None

    def __post_init__(self):
        object.__setattr__(self, "material", _material(self.material, "Ramp.material"))
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
    material : Uniform, Texture, float or None
        Infrared material of both sides (module docstring).
    """

    centre: tuple
    width: float = 1.0
    height: float = 1.0
    yaw_deg: float = 0.0
    material: object = None

    def __post_init__(self):
        object.__setattr__(self, "material", _material(self.material, "Target.material"))
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
    material : Uniform, Texture, float or None
        Infrared material of its surface and side walls (module docstring).
    """

    heights: np.ndarray
    origin: tuple = (0.0, 0.0)
    resolution: float = 0.02
    base_z: float | None = None
    material: object = None
    _cell_max: np.ndarray = field(init=False, repr=False)
    _block_max: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "material", _material(self.material, "HeightField.material"))
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
                      base_z: float | None = None, material=None) -> "HeightField":
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
        return cls(z, (xr[0], yr[0]), res, base_z, material)

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
        # index into scene.primitives of each box-like primitive and each height field
        self.box_index = np.array([k for k, p in enumerate(scene.primitives) if not isinstance(p, HeightField)],
                                  dtype=np.int32)
        self.field_index = np.array([k for k, p in enumerate(scene.primitives) if isinstance(p, HeightField)],
                                    dtype=np.int32)
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
    ground_material : Uniform, Texture, float or None
        Infrared material of the ground plane (module docstring); None leaves it to the camera.

    Notes
    -----
    Convenience scenes: :meth:`stairs_scene`, :meth:`box_field`, :meth:`slope`, :meth:`rough`, or
    by name with :meth:`named` (``"stairs"``, ``"boxes"``, ``"slope"``, ``"rough"``). Ground truth:
    :meth:`height_at`, :meth:`height_grid`; :meth:`contains` tests points against the solids.
    """

    #: Names accepted by :meth:`named`.
    NAMES = ("stairs", "boxes", "slope", "rough")

    _KINDS = (Box, Stairs, Ramp, HeightField, Target)

    def __init__(self, primitives: Sequence = (), ground_z: float | None = 0.0, ground_material=None):
        prims = tuple(primitives)
        for k, p in enumerate(prims):
            if not isinstance(p, self._KINDS):
                raise ValueError(f"primitives[{k}] must be a Box, Stairs, Ramp, HeightField or Target, "
                                 f"got {type(p).__name__}")
        self._primitives = prims
        self._ground_z = None if ground_z is None else _finite(ground_z, "ground_z")
        if self._ground_z is not None and abs(self._ground_z) > _LIMIT_M:
            raise ValueError(f"ground_z = {self._ground_z} is implausibly far; check its units")
        self._ground_material = _material(ground_material, "Scene.ground_material")
        self._packed = None

    @property
    def primitives(self) -> tuple:
        """The primitives, in tie-breaking order (read only: make a new scene to change them)."""
        return self._primitives

    @property
    def ground_z(self) -> float | None:
        """Height of the ground plane [m], or None."""
        return self._ground_z

    @property
    def ground_material(self):
        """Infrared material of the ground plane, or None (the camera's choice)."""
        return self._ground_material

    @property
    def has_materials(self) -> bool:
        """Whether the ground or any primitive carries its own infrared material."""
        return self._ground_material is not None or any(p.material is not None for p in self._primitives)

    def __repr__(self) -> str:
        kinds = ", ".join(type(p).__name__ for p in self.primitives)
        return f"Scene(ground_z={self.ground_z}, primitives=[{kinds}])"

    def with_primitives(self, *primitives) -> "Scene":
        """A new scene with ``primitives`` appended (the same ground and ground material)."""
        return Scene(self.primitives + tuple(primitives), self.ground_z, self._ground_material)

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
