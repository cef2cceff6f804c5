"""Infrared albedo of surfaces: uniform materials, procedural textures (concrete, carpet), and their placement.

Albedo is the Lambertian reflectance at the projector's 850 nm, in [0, 1]; the imagers see radiance
L = albedo E / pi for an irradiance E (:mod:`.imagers`).

Textures
--------
A :class:`Texture` is a function of the surface point, so the left and right imagers (and every
frame) see the same pattern on the surface. Coordinates are chosen per point by the dominant axis of
its map-frame normal (tri-planar mapping): a floor (normal along z) is textured in (x, y), a wall
facing x in (y, z), one facing y in (x, z)::

    albedo(s) = mean (1 + contrast F(s) + weave_contrast W(s))

* F is fractional value noise on a square lattice: octave k = 0 .. octaves - 1 has lattice spacing
  a_k = wavelength_m / 2^k and amplitude proportional to a_k^hurst, normalised so that |F| <= 1.
  Each octave is uniform random values in [-1, 1] at the lattice nodes (a fixed table indexed by a
  hash of the node and the seed), blended with the quintic fade 6t^5 - 15t^4 + 10t^3 (C2-smooth).
  Its spectrum: most power of octave k near spatial frequency 1 / a_k, the octaves' power falling
  as a_k^(2 hurst), i.e. a 2-D power spectral density ~ f^-(2 hurst + 2) between 1 / wavelength_m
  and 2^(octaves - 1) / wavelength_m, white below.
* W = cos(2 pi s_1 / p) cos(2 pi s_2 / p) is a square weave of period p = ``weave_period_m`` (carpet
  loops; 0 = none).

Bounds are checked when a material is made: mean (1 +- (contrast + weave_contrast)) must lie in [0, 1],
else ValueError naming the material.

Placement
---------
A :class:`MaterialMap` gives every surface point one material; the first rule that applies wins:

1. the scene's own materials, by what the point belongs to (the renderer's primitive index,
   ``noise_model.sim.render_depth(..., return_index=True)``): a primitive's ``material``, or the
   scene's ``ground_material`` for the ground plane -- where they are not None;
2. axis-aligned regions of the map frame, in order;
3. the ground rule: points within ``ground_tol_m`` of z = ``ground_z``;
4. the default.

Without a primitive index (or when the scene carries no material) only rules 2-4 apply, so a scene
without materials looks the same either way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from ...numba_config import JIT, resolve_threads, threads

__all__ = [
    "Uniform", "Texture", "MaterialMap", "concrete", "carpet", "white_wall", "fbm", "fbm_reference",
    "triplanar_coordinates", "check_albedo", "as_material",
]

_TABLE_BITS = 16
_TABLE_MASK = (1 << _TABLE_BITS) - 1
# odd 32-bit constants of the lattice hash (spatial hashing as in Teschner et al. 2003)
_HX, _HY, _HK = 73856093, 19349663, 83492791


def check_albedo(value, name: str) -> float:
    """An albedo as a float in [0, 1]; else ValueError naming it."""
    try:
        a = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"albedo of {name} must be a number, got {value!r}") from None
    if not (0.0 <= a <= 1.0):
        raise ValueError(f"albedo of {name} must lie in [0, 1], got {a!r}")
    return a


def _table(seed: int) -> np.ndarray:
    return np.random.default_rng([0x5EED, int(seed)]).uniform(-1.0, 1.0, 1 << _TABLE_BITS)


# ---------------------------------------------------------------------------------------------
# value-noise fBm (numba + NumPy reference)
# ---------------------------------------------------------------------------------------------


@njit(**JIT)
def _fade(t):
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


@njit(**JIT)
def _node(ix, iy, k, table):
    h = (ix * _HX) ^ (iy * _HY) ^ (k * _HK)
    return table[h & _TABLE_MASK]


@njit(**JIT)
def _fbm_at(a, b, inv_spacing, weights, table):
    acc = 0.0
    for k in range(inv_spacing.shape[0]):
        u = a * inv_spacing[k]
        v = b * inv_spacing[k]
        fu = np.floor(u)
        fv = np.floor(v)
        ix = np.int64(fu)
        iy = np.int64(fv)
        tu = _fade(u - fu)
        tv = _fade(v - fv)
        v00 = _node(ix, iy, k, table)
        v10 = _node(ix + 1, iy, k, table)
        v01 = _node(ix, iy + 1, k, table)
        v11 = _node(ix + 1, iy + 1, k, table)
        top = v00 + tu * (v10 - v00)
        bottom = v01 + tu * (v11 - v01)
        acc += weights[k] * (top + tv * (bottom - top))
    return acc


@njit(parallel=True, **JIT)
def _fbm_kernel(s, inv_spacing, weights, table, out):
    for i in prange(s.shape[0]):
        a = s[i, 0]
        b = s[i, 1]
        if not (np.isfinite(a) and np.isfinite(b)):
            out[i] = np.nan
        else:
            out[i] = _fbm_at(a, b, inv_spacing, weights, table)


@njit(parallel=True, **JIT)
def _texture_kernel(p, nrm, inv_spacing, weights, table, mean, contrast, weave_k, weave_contrast, code, c, out):
    """Tri-planar coordinates, fBm and weave of :class:`Texture` in one pass (see Texture.evaluate_reference).

    With c >= 0 only the points of material code c are evaluated (NaN where code < 0, the rest untouched)."""
    for i in prange(p.shape[0]):
        if c >= 0 and code[i] != c:
            if code[i] < 0:
                out[i] = np.nan
            continue
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            out[i] = np.nan
            continue
        ax, ay, az = abs(nrm[i, 0]), abs(nrm[i, 1]), abs(nrm[i, 2])
        ax = ax if np.isfinite(ax) else 0.0
        ay = ay if np.isfinite(ay) else 0.0
        az = az if np.isfinite(az) else 0.0
        if az >= ay and az >= ax:
            s1, s2 = x, y
        elif ay >= ax:
            s1, s2 = x, z
        else:
            s1, s2 = y, z
        rel = contrast * _fbm_at(s1, s2, inv_spacing, weights, table)
        if weave_k > 0.0:
            rel += weave_contrast * np.cos(weave_k * s1) * np.cos(weave_k * s2)
        out[i] = min(1.0, max(0.0, mean * (1.0 + rel)))


@njit(parallel=True, **JIT)
def _uniform_kernel(p, value, out):
    for i in prange(p.shape[0]):
        out[i] = value if (np.isfinite(p[i, 0]) and np.isfinite(p[i, 1]) and np.isfinite(p[i, 2])) else np.nan


_NO_CODES = np.zeros(0, np.int32)   # the code array of an unmasked texture evaluation (never read)
_COUNT_CHUNKS = 64        # fixed chunks of the code count (integer sums: any thread count gives the same)


@njit(parallel=True, **JIT)
def _count_codes(code, n_codes):
    """Points per material code (codes < 0 left out), counted over fixed chunks in parallel."""
    n = code.shape[0]
    partial = np.zeros((_COUNT_CHUNKS, n_codes), np.int64)
    for k in prange(_COUNT_CHUNKS):
        for i in range(k * n // _COUNT_CHUNKS, (k + 1) * n // _COUNT_CHUNKS):
            if code[i] >= 0:
                partial[k, code[i]] += 1
    counts = np.zeros(n_codes, np.int64)
    for k in range(_COUNT_CHUNKS):
        for c in range(n_codes):
            counts[c] += partial[k, c]
    return counts


@njit(parallel=True, **JIT)
def _fill_kernel(code, c, value, out):
    """``value`` at the points of material code c, NaN where code < 0, the rest untouched."""
    for i in prange(code.shape[0]):
        if code[i] == c:
            out[i] = value
        elif code[i] < 0:
            out[i] = np.nan


@njit(**JIT)
def _position_code(x, y, z, lo, hi, ground_z, tol, use_ground):
    """Rules 2-4 of the module docstring: region index, len(lo) for the ground, len(lo) + 1 default."""
    n_regions = lo.shape[0]
    for r in range(n_regions):
        if lo[r, 0] <= x <= hi[r, 0] and lo[r, 1] <= y <= hi[r, 1] and lo[r, 2] <= z <= hi[r, 2]:
            return r
    if use_ground and abs(z - ground_z) <= tol:
        return n_regions
    return n_regions + 1


@njit(parallel=True, **JIT)
def _assign_kernel(p, lo, hi, ground_z, tol, use_ground, out):
    """Material code per point by position (:func:`_position_code`); -1 where the point is NaN."""
    for i in prange(p.shape[0]):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            out[i] = -1
            continue
        out[i] = _position_code(x, y, z, lo, hi, ground_z, tol, use_ground)


@njit(parallel=True, **JIT)
def _assign_indexed_kernel(p, index, prim_code, ground_code, lo, hi, ground_z, tol, use_ground, out):
    """Material code per point with the scene's materials first (rule 1): prim_code[index] for a
    primitive (index >= 0), ground_code for the ground plane (index -1), where they are >= 0; then
    :func:`_position_code`; -1 where the point is NaN."""
    for i in prange(p.shape[0]):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            out[i] = -1
            continue
        k = index[i]
        code = -1
        if k >= 0:
            code = prim_code[k]
        elif k == -1:
            code = ground_code
        if code < 0:
            code = _position_code(x, y, z, lo, hi, ground_z, tol, use_ground)
        out[i] = code


def _octaves(wavelength_m: float, octaves: int, hurst: float):
    spacing = wavelength_m / 2.0 ** np.arange(octaves)
    weights = (spacing / wavelength_m) ** hurst
    return 1.0 / spacing, weights / weights.sum()


def fbm(s, wavelength_m: float, octaves: int, hurst: float, seed: int = 0, nthreads: int | None = None) -> np.ndarray:
    """Fractional value noise F in [-1, 1] at 2-D surface coordinates (numba).

    Parameters
    ----------
    s : ndarray, shape (N, 2)
        Surface coordinates [m] (see :func:`triplanar_coordinates`); NaN rows give NaN.
    wavelength_m : float
        Lattice spacing of the coarsest octave [m].
    octaves : int
        Number of octaves (each halves the spacing).
    hurst : float
        Octave amplitudes proportional to spacing^hurst.
    seed : int
        Selects the random lattice values.
    nthreads : int, optional
        numba threads; the result does not depend on it.

    Returns
    -------
    ndarray, shape (N,)
        F, the weighted octave sum of the module docstring.
    """
    pts = np.ascontiguousarray(s, dtype=np.float64).reshape(-1, 2)
    inv, w = _octaves(wavelength_m, octaves, hurst)
    out = np.empty(len(pts))
    with threads(resolve_threads(nthreads)):
        _fbm_kernel(pts, inv, w, _table(seed), out)
    return out


def fbm_reference(s, wavelength_m: float, octaves: int, hurst: float, seed: int = 0) -> np.ndarray:
    """NumPy reference of :func:`fbm`."""
    pts = np.asarray(s, dtype=np.float64).reshape(-1, 2)
    inv, w = _octaves(wavelength_m, octaves, hurst)
    table = _table(seed)
    ok = np.isfinite(pts).all(axis=1)
    a = np.where(ok, pts[:, 0], 0.0)
    b = np.where(ok, pts[:, 1], 0.0)
    acc = np.zeros(len(pts))

    def node(ix, iy, k):
        return table[((ix * _HX) ^ (iy * _HY) ^ (k * _HK)) & _TABLE_MASK]

    def fade(t):
        return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)

    for k in range(len(inv)):
        u, v = a * inv[k], b * inv[k]
        fu, fv = np.floor(u), np.floor(v)
        ix, iy = fu.astype(np.int64), fv.astype(np.int64)
        tu, tv = fade(u - fu), fade(v - fv)
        top = node(ix, iy, k) + tu * (node(ix + 1, iy, k) - node(ix, iy, k))
        bottom = node(ix, iy + 1, k) + tu * (node(ix + 1, iy + 1, k) - node(ix, iy + 1, k))
        acc += w[k] * (top + tv * (bottom - top))
    acc[~ok] = np.nan
    return acc


def triplanar_coordinates(points_map, normals_map) -> np.ndarray:
    """Surface coordinates (N, 2) [m]: the two map axes across the normal's dominant axis.

    normal mostly along z -> (x, y); along x -> (y, z); along y -> (x, z). NaN rows stay NaN.
    """
    p = np.asarray(points_map, dtype=np.float64).reshape(-1, 3)
    n = np.abs(np.asarray(normals_map, dtype=np.float64).reshape(-1, 3))
    n = np.where(np.isfinite(n), n, 0.0)
    axis = np.argmax(n[:, ::-1], axis=1)                     # ties prefer z, then y (floors first)
    axis = 2 - axis
    first = np.where(axis == 0, p[:, 1], p[:, 0])
    second = np.where(axis == 2, p[:, 1], p[:, 2])
    return np.stack([first, second], axis=1)


# ---------------------------------------------------------------------------------------------
# materials
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Uniform:
    """One albedo everywhere (a painted wall, a board)."""

    albedo: float
    name: str = "uniform"

    def __post_init__(self):
        object.__setattr__(self, "albedo", check_albedo(self.albedo, self.name))

    def evaluate(self, points_map, normals_map, nthreads: int | None = None, out=None) -> np.ndarray:
        """Albedo (N,) at surface points (N, 3) with normals (N, 3), map frame; NaN where the point is NaN (numba).

        ``out`` is an optional (N,) float64 buffer to write into.
        """
        p = np.ascontiguousarray(points_map, dtype=np.float64).reshape(-1, 3)
        out = _out(out, len(p))
        with threads(resolve_threads(nthreads)):
            _uniform_kernel(p, self.albedo, out)
        return out

    def evaluate_reference(self, points_map, normals_map) -> np.ndarray:
        """NumPy reference of :meth:`evaluate`."""
        p = np.asarray(points_map, dtype=np.float64).reshape(-1, 3)
        return np.where(np.isfinite(p).all(axis=1), self.albedo, np.nan)


@dataclass(frozen=True)
class Texture:
    """A procedural albedo texture (module docstring): mean (1 + contrast F + weave_contrast W).

    Attributes
    ----------
    name : str
        Named in error messages.
    mean : float
        Mean albedo.
    contrast : float
        Peak relative amplitude of the fBm F.
    wavelength_m : float
        Coarsest lattice spacing of F [m].
    octaves : int
        Octaves of F.
    hurst : float
        Octave amplitude exponent.
    weave_period_m, weave_contrast : float
        Period [m] and relative amplitude of the square weave W (0 = none).
    seed : int
        Selects the lattice values.
    """

    name: str
    mean: float
    contrast: float
    wavelength_m: float
    octaves: int = 4
    hurst: float = 0.5
    weave_period_m: float = 0.0
    weave_contrast: float = 0.0
    seed: int = 0

    def __post_init__(self):
        check_albedo(self.mean, self.name)
        for attr in ("contrast", "weave_contrast", "weave_period_m"):
            v = float(getattr(self, attr))
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{attr} of {self.name} must be finite and >= 0, got {v!r}")
        if not (math.isfinite(self.wavelength_m) and self.wavelength_m > 0.0):
            raise ValueError(f"wavelength_m of {self.name} must be > 0, got {self.wavelength_m!r}")
        if int(self.octaves) != self.octaves or self.octaves < 1:
            raise ValueError(f"octaves of {self.name} must be an integer >= 1, got {self.octaves!r}")
        amp = self.contrast + (self.weave_contrast if self.weave_period_m > 0 else 0.0)
        check_albedo(self.mean * (1.0 + amp), f"{self.name} (brightest point, mean x (1 + amplitudes))")
        check_albedo(self.mean * (1.0 - amp), f"{self.name} (darkest point, mean x (1 - amplitudes))")

    def evaluate(self, points_map, normals_map, nthreads: int | None = None, out=None) -> np.ndarray:
        """Albedo (N,) at surface points (N, 3) with normals (N, 3), map frame; NaN where the point is NaN (numba).

        ``out`` is an optional (N,) float64 buffer to write into.
        """
        p = np.ascontiguousarray(points_map, dtype=np.float64).reshape(-1, 3)
        n = np.ascontiguousarray(normals_map, dtype=np.float64).reshape(-1, 3)
        inv, w = _octaves(self.wavelength_m, self.octaves, self.hurst)
        k = 2.0 * np.pi / self.weave_period_m if self.weave_period_m > 0 and self.weave_contrast > 0 else 0.0
        out = _out(out, len(p))
        with threads(resolve_threads(nthreads)):
            _texture_kernel(p, n, inv, w, _table(self.seed), float(self.mean), float(self.contrast), k,
                            float(self.weave_contrast), _NO_CODES, -1, out)
        return out

    def _evaluate_where(self, p, n, code, c: int, nthreads: int, out) -> None:
        """:meth:`evaluate` at the points of material code c only (p, n (N, 3) float64), into ``out``."""
        inv, w = _octaves(self.wavelength_m, self.octaves, self.hurst)
        k = 2.0 * np.pi / self.weave_period_m if self.weave_period_m > 0 and self.weave_contrast > 0 else 0.0
        with threads(nthreads):
            _texture_kernel(p, n, inv, w, _table(self.seed), float(self.mean), float(self.contrast), k,
                            float(self.weave_contrast), code, int(c), out)

    def evaluate_reference(self, points_map, normals_map) -> np.ndarray:
        """NumPy reference of :meth:`evaluate`."""
        s = triplanar_coordinates(points_map, normals_map)
        rel = self.contrast * fbm_reference(s, self.wavelength_m, self.octaves, self.hurst, self.seed)
        if self.weave_period_m > 0 and self.weave_contrast > 0:
            k = 2.0 * np.pi / self.weave_period_m
            rel += self.weave_contrast * np.cos(k * s[:, 0]) * np.cos(k * s[:, 1])
        return np.clip(self.mean * (1.0 + rel), 0.0, 1.0)


def concrete(seed: int = 0) -> Texture:
    """A grey concrete floor: albedo 0.35 +- 60 %, fBm from 8 mm down to 2 mm, hurst 0.5.

    Strength and scale fitted to the temporal noise of a real D435 over a concrete lab floor (the
    aims_slam recording, docs/physical-d435.md): they stand for every static modulation of the dots
    that is fixed to the surface (albedo, polish, micro-relief).
    """
    return Texture("concrete", mean=0.35, contrast=0.60, wavelength_m=0.008, octaves=3, hurst=0.5, seed=seed)


def carpet(seed: int = 1) -> Texture:
    """A dark loop carpet: albedo 0.22, a 4 mm square weave (+- 35 %) over fBm from 8 mm to 2 mm (+- 30 %)."""
    return Texture("carpet", mean=0.22, contrast=0.30, wavelength_m=0.008, octaves=3, hurst=0.3,
                   weave_period_m=0.004, weave_contrast=0.35, seed=seed)


def white_wall() -> Uniform:
    """Matte white paint: albedo 0.8 at 850 nm."""
    return Uniform(0.8, "white wall")


def as_material(value, name: str):
    """``value`` as a material: a :class:`Uniform` or :class:`Texture` as it is, a number as a uniform
    albedo in [0, 1] called ``name``; anything else is a ValueError naming ``name``."""
    if isinstance(value, (Uniform, Texture)):
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a Uniform, a Texture or an albedo in [0, 1], got {value!r}")
    return Uniform(check_albedo(value, name), name)


def _scene_codes(scene, first_code: int):
    """The scene's own materials (rule 1) as codes from ``first_code``.

    Returns (materials, prim_code (n_primitives,) int64, ground_code): each distinct material once,
    the code of each primitive's material (-1 = none) and of the ground's (-1 = none).
    """
    found: list = []

    def code(mat) -> int:
        if mat is None:
            return -1
        for j, m in enumerate(found):
            if m is mat or m == mat:
                return first_code + j
        found.append(mat)
        return first_code + len(found) - 1

    prim_code = np.array([code(getattr(p, "material", None)) for p in scene.primitives], dtype=np.int64)
    ground_code = code(getattr(scene, "ground_material", None))
    return found, prim_code, ground_code


@dataclass(frozen=True)
class MaterialMap:
    """Materials of a scene by position (module docstring).

    Attributes
    ----------
    default : Uniform or Texture
        Everything not matched below.
    ground : Uniform, Texture or None
        Points within ``ground_tol_m`` of z = ``ground_z`` (the scene's ground plane).
    regions : tuple of (min_xyz, max_xyz, material)
        Axis-aligned boxes of the map frame [m], tested in order before the ground.
    ground_z : float or None
        Height of the ground plane [m] (None: no ground rule).
    ground_tol_m : float
        Tolerance of the ground rule [m].
    """

    default: object = field(default_factory=lambda: Uniform(0.5, "default"))
    ground: object = None
    regions: tuple = ()
    ground_z: float | None = 0.0
    ground_tol_m: float = 1e-3

    def __post_init__(self):
        regions = []
        for k, item in enumerate(self.regions):
            try:
                lo, hi, mat = item
            except (TypeError, ValueError):
                raise ValueError(f"region {k} must be (min_xyz, max_xyz, material)") from None
            lo = np.asarray(lo, dtype=np.float64).reshape(3)
            hi = np.asarray(hi, dtype=np.float64).reshape(3)
            if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi >= lo)):
                raise ValueError(f"region {k} needs finite corners with max >= min, got {lo}, {hi}")
            _check_material(mat, f"region {k}")
            regions.append((tuple(lo), tuple(hi), mat))
        object.__setattr__(self, "regions", tuple(regions))
        _check_material(self.default, "default")
        if self.ground is not None:
            _check_material(self.ground, "ground")

    def evaluate(self, points_map, normals_map, nthreads: int | None = None, out=None,
                 index=None, scene=None) -> np.ndarray:
        """Albedo (N,) of surface points (N, 3) with normals (N, 3) [map frame]; NaN where the point is NaN.

        ``out`` is an optional (N,) float64 buffer (reused from frame to frame). Each material is evaluated
        at its own points only.
        ``index`` (N,) int, the renderer's primitive index of each point (k >= 0: ``scene.primitives[k]``,
        -1: the ground plane, -2: no hit), with ``scene``, applies the scene's own materials first
        (rule 1 of the module docstring).
        """
        p = np.ascontiguousarray(points_map, dtype=np.float64).reshape(-1, 3)
        nrm = np.ascontiguousarray(normals_map, dtype=np.float64).reshape(-1, 3)
        n = resolve_threads(nthreads)
        lo = np.array([r[0] for r in self.regions], dtype=np.float64).reshape(-1, 3)
        hi = np.array([r[1] for r in self.regions], dtype=np.float64).reshape(-1, 3)
        use_ground = self.ground is not None and self.ground_z is not None
        gz, tol = float(self.ground_z) if use_ground else 0.0, float(self.ground_tol_m)
        code = np.empty(len(p), np.int32)
        materials = [r[2] for r in self.regions] + [self.ground, self.default]
        idx = _check_index(index, scene, len(p))
        if idx is not None:
            extra, prim_code, ground_code = _scene_codes(scene, len(materials))
            materials += extra
            with threads(n):
                _assign_indexed_kernel(p, idx, prim_code, ground_code, lo, hi, gz, tol, use_ground, code)
        else:
            with threads(n):
                _assign_kernel(p, lo, hi, gz, tol, use_ground, code)
        with threads(n):
            present = np.flatnonzero(_count_codes(code, len(materials)))
        out = _out(out, len(p))
        if len(present) == 1:                      # one material for every surface point (NaN stays NaN)
            return materials[present[0]].evaluate(p, nrm, n, out=out)
        if len(present) == 0:
            out.fill(np.nan)
            return out
        for c in present:                          # each material at its own points, written in place
            if isinstance(materials[c], Uniform):
                with threads(n):
                    _fill_kernel(code, int(c), materials[c].albedo, out)
            else:
                materials[c]._evaluate_where(p, nrm, code, int(c), n, out)
        return out

    def evaluate_reference(self, points_map, normals_map, index=None, scene=None) -> np.ndarray:
        """NumPy reference of :meth:`evaluate` (the rules by masks, each material's own reference)."""
        p = np.asarray(points_map, dtype=np.float64).reshape(-1, 3)
        nrm = np.asarray(normals_map, dtype=np.float64).reshape(-1, 3)
        out = np.full(len(p), np.nan)
        todo = np.isfinite(p).all(axis=1)
        idx = _check_index(index, scene, len(p))
        if idx is not None:
            owners = [(idx == k, prim.material) for k, prim in enumerate(scene.primitives)]
            owners.append((idx == -1, scene.ground_material))
            for m, mat in owners:
                m = m & todo
                if mat is not None and m.any():
                    out[m] = mat.evaluate_reference(p[m], nrm[m])
                    todo &= ~m
        for lo, hi, mat in self.regions:
            m = todo & np.all((p >= lo) & (p <= hi), axis=1)
            if m.any():
                out[m] = mat.evaluate_reference(p[m], nrm[m])
                todo &= ~m
        if self.ground is not None and self.ground_z is not None:
            m = todo & (np.abs(p[:, 2] - self.ground_z) <= self.ground_tol_m)
            if m.any():
                out[m] = self.ground.evaluate_reference(p[m], nrm[m])
                todo &= ~m
        if todo.any():
            out[todo] = self.default.evaluate_reference(p[todo], nrm[todo])
        return out


def _check_index(index, scene, n: int):
    """The primitive index as a contiguous int32 (n,) array, or None when rule 1 does not apply."""
    if index is None and scene is None:
        return None
    if index is None or scene is None:
        raise ValueError("give the primitive index and the scene together (or neither)")
    idx = np.ascontiguousarray(index, dtype=np.int32).reshape(-1)
    if idx.shape != (n,):
        raise ValueError(f"index must hold one primitive index per point ({n}), got {idx.size}")
    if idx.size and (idx.min() < -2 or idx.max() >= len(scene.primitives)):
        raise ValueError(f"index must lie in [-2, {len(scene.primitives) - 1}] (the scene's primitives, "
                         f"-1 ground, -2 no hit), got [{idx.min()}, {idx.max()}]")
    if not getattr(scene, "has_materials", False):
        return None
    return idx


def _out(buf, n: int) -> np.ndarray:
    if buf is not None and buf.shape == (n,) and buf.dtype == np.float64 and buf.flags.c_contiguous:
        return buf
    return np.empty(n)


def _check_material(mat, where: str) -> None:
    if not isinstance(mat, (Uniform, Texture)):
        raise ValueError(f"material of {where} must be a Uniform or a Texture, got {type(mat).__name__}")
