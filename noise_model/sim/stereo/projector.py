"""The D435's infrared dot projector: a fixed pseudo-random pattern, its irradiance on surfaces, shadows.

Frames and units
----------------
The projector frame has the camera's orientation (x right, y down, z forward) and sits at
``offset_m`` along the left imager's x axis, between the two imagers (:class:`Projector`). Directions
are given by their tangent-plane coordinates (a, b) = (x / z, y / z). Powers in W, irradiance in W/m^2,
angles in rad.

Pattern
-------
About 5,000 dots over the projector's field of view (AMS/Princeton Optronics VCSEL array behind a
diffractive element; Intel, "Projectors for D400 Series"). :class:`DotPattern` lays them out as a
jittered grid in (a, b): the field is cut into about ``n_dots`` equal cells, ``n_dots`` of them are
chosen at random and each gets one dot at a random point of its inner ``jitter`` fraction, so that
dots never merge (as on a VCSEL array) but form no lattice a matcher could alias on. Dot k carries
the power P_k = (P / n) m_k with m_k log-normal of mean 1 and log-sd ``power_spread``. The pattern
is fixed by ``seed``: the same dots in every frame, so errors that depend on where dots fall are
static, as on a real D435.

Irradiance
----------
Each dot is a Gaussian beam of angular standard deviation sigma (``dot_sigma_rad``), radiant
intensity I_k(theta) = P_k / (2 pi sigma^2) exp(-theta^2 / (2 sigma^2)) [W/sr] at angle theta from
its axis. A surface point at X (projector frame, distance r = |X|) with unit normal n receives::

    E(X) = cos_i / r^2  sum_k I_k(theta_k),     cos_i = max(0, -n . X / r)

(inverse-square fall-off, cosine of incidence; back faces get nothing). theta_k^2 is taken as the
squared chord between the unit directions, 2 - 2 u . v_k (equal to theta^2 to fourth order); each
Gaussian is cut at ``cutoff_sigmas`` sigma and lowered by its value there, exp(-cutoff^2 / 2), so that
it reaches zero continuously (the dot loses a fraction below 1e-3 of its power at 4 sigma).

Shadows
-------
A point is lit only if the projector sees it. :meth:`Projector.irradiance` takes the occlusion as
``None`` (no shadows), a callable ``lit(points_proj) -> bool (N,)``, or a :class:`ProjectorView`:
the scene's z-depth rendered from the projector (for example by
``noise_model.sim.render_depth(scene, K, width, height, T_map_proj)`` with
:meth:`Projector.view_intrinsics` and :meth:`Projector.pose_in_map`). With a view, a point is lit
when its projector z-depth is at most the largest of the four depths around its image position plus
a bias (``bias_rel`` z + ``bias_m``, against self-shadowing on slanted surfaces); pixels with no
hit do not occlude, points outside the view are lit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ...numba_config import JIT, resolve_threads, threads

__all__ = [
    "DotPattern", "Projector", "ProjectorView", "irradiance_reference", "shadow_mask", "shadow_mask_reference",
    "D435_PROJECTOR_HFOV_DEG", "D435_PROJECTOR_VFOV_DEG",
]

#: Projector field of view [deg]: wide enough that dots reach every edge of the 848x480 infrared
#: image (about 90 x 59 deg) from the projector's offset, as in the D435's own infrared images.
D435_PROJECTOR_HFOV_DEG = 91.0
D435_PROJECTOR_VFOV_DEG = 65.0


def _positive(value, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name} must be finite and > 0, got {v!r}")
    return v


@dataclass(frozen=True)
class DotPattern:
    """The projector's fixed dot pattern (module docstring).

    Attributes
    ----------
    n_dots : int
        Number of dots (about 5,000 on a D435).
    hfov_deg, vfov_deg : float
        Field of view the dots cover [deg].
    dot_sigma_rad : float
        Angular standard deviation of one dot [rad] (2 mrad: with the lens blur and the pixel, the
        dot profiles of the D435's own infrared images; docs/physical-d435.md).
    power_w : float
        Total optical power in the dots [W] (laser power 150 mW, the default setting).
    power_spread : float
        Log-normal sd of the dots' relative powers (0 = all equal).
    jitter : float
        Fraction of its cell in which a dot may lie (0 = a regular grid, 1 = anywhere in the cell).
    seed : int
        Fixes the pattern.
    """

    n_dots: int = 5000
    hfov_deg: float = D435_PROJECTOR_HFOV_DEG
    vfov_deg: float = D435_PROJECTOR_VFOV_DEG
    dot_sigma_rad: float = 2.0e-3
    power_w: float = 0.150
    power_spread: float = 0.25
    jitter: float = 0.8
    seed: int = 0

    def __post_init__(self):
        if isinstance(self.n_dots, bool) or int(self.n_dots) != self.n_dots or self.n_dots <= 0:
            raise ValueError(f"dot count n_dots must be an integer > 0, got {self.n_dots!r}")
        for name in ("dot_sigma_rad", "power_w"):
            _positive(getattr(self, name), name)
        for name, hi in (("hfov_deg", 170.0), ("vfov_deg", 170.0)):
            v = _positive(getattr(self, name), name)
            if v >= hi:
                raise ValueError(f"{name} must be below {hi} deg, got {v}")
        if not (0.0 <= self.power_spread < 5.0):
            raise ValueError(f"power_spread must lie in [0, 5), got {self.power_spread!r}")
        if not (0.0 <= self.jitter <= 1.0):
            raise ValueError(f"jitter must lie in [0, 1], got {self.jitter!r}")

    def tangent_extent(self) -> tuple[float, float]:
        """Half-widths (a_max, b_max) of the field in tangent-plane coordinates."""
        return math.tan(math.radians(self.hfov_deg) / 2.0), math.tan(math.radians(self.vfov_deg) / 2.0)

    def dots(self) -> tuple[np.ndarray, np.ndarray]:
        """Dot directions and powers.

        Returns
        -------
        directions : ndarray, shape (n_dots, 3)
            Unit vectors of the dot axes in the projector frame.
        powers_w : ndarray, shape (n_dots,)
            Optical power of each dot [W]; they sum to about ``power_w``.
        """
        rng = np.random.default_rng([0xD07, int(self.seed)])
        a_max, b_max = self.tangent_extent()
        n = int(self.n_dots)
        rows = max(1, int(round(math.sqrt(n * b_max / a_max))))
        cols = max(1, int(math.ceil(n / rows)))
        cells = rng.choice(rows * cols, size=n, replace=False)
        r, c = np.divmod(cells, cols)
        ca, cb = 2 * a_max / cols, 2 * b_max / rows
        a = -a_max + (c + 0.5 + self.jitter * rng.uniform(-0.5, 0.5, n)) * ca
        b = -b_max + (r + 0.5 + self.jitter * rng.uniform(-0.5, 0.5, n)) * cb
        v = np.stack([a, b, np.ones(n)], axis=1)
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        m = np.exp(rng.normal(-0.5 * self.power_spread ** 2, self.power_spread, n)) if self.power_spread > 0 \
            else np.ones(n)
        return v, self.power_w / n * m


@dataclass(frozen=True)
class ProjectorView:
    """The scene's z-depth seen from the projector, for shadows (module docstring).

    Attributes
    ----------
    depth_m : ndarray, shape (H, W)
        z-depth [m] in the projector frame; NaN = nothing hit.
    K : ndarray, shape (3, 3)
        Intrinsics of that render [px].
    bias_rel, bias_m : float
        A point is lit when z <= max(4 neighbours) + bias_rel z + bias_m.
    """

    depth_m: np.ndarray
    K: np.ndarray
    bias_rel: float = 0.01
    bias_m: float = 0.002


@njit(parallel=True, **JIT)
def _shadow_kernel(pts, depth, intr, bias_rel, bias_m, lit):
    h, w = depth.shape
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    for i in prange(pts.shape[0]):
        z = pts[i, 2]
        if not (z > 0.0):
            lit[i] = False
            continue
        u = fx * pts[i, 0] / z + cx
        v = fy * pts[i, 1] / z + cy
        if not (u >= 0.0 and v >= 0.0 and u <= w - 1 and v <= h - 1):
            lit[i] = True
            continue
        u0 = min(int(np.floor(u)), w - 2) if w > 1 else 0
        v0 = min(int(np.floor(v)), h - 2) if h > 1 else 0
        zmax = -1.0
        seen = False
        for dv in range(2 if h > 1 else 1):
            for du in range(2 if w > 1 else 1):
                zz = depth[v0 + dv, u0 + du]
                if np.isfinite(zz):
                    seen = True
                    if zz > zmax:
                        zmax = zz
        lit[i] = (not seen) or z <= zmax + bias_rel * z + bias_m


def _view_arrays(view: ProjectorView):
    depth = np.ascontiguousarray(view.depth_m, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"ProjectorView depth must be 2-D, got shape {depth.shape}")
    K = np.asarray(view.K, dtype=np.float64)
    if K.shape != (3, 3) or not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError("ProjectorView K must be a 3x3 camera matrix with positive focal lengths")
    return depth, np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])


def shadow_mask(points_proj, view: ProjectorView, nthreads: int | None = None) -> np.ndarray:
    """Which points (N, 3) [projector frame, m] the projector lights, from a depth view (numba)."""
    pts = np.ascontiguousarray(points_proj, dtype=np.float64).reshape(-1, 3)
    depth, intr = _view_arrays(view)
    lit = np.empty(len(pts), np.bool_)
    with threads(resolve_threads(nthreads)):
        _shadow_kernel(pts, depth, intr, float(view.bias_rel), float(view.bias_m), lit)
    return lit


def shadow_mask_reference(points_proj, view: ProjectorView) -> np.ndarray:
    """NumPy reference of :func:`shadow_mask`."""
    pts = np.asarray(points_proj, dtype=np.float64).reshape(-1, 3)
    depth, (fx, fy, cx, cy) = _view_arrays(view)
    h, w = depth.shape
    z = pts[:, 2]
    lit = np.ones(len(pts), bool)
    front = z > 0.0
    lit[~front] = False
    with np.errstate(divide="ignore", invalid="ignore"):
        u = fx * pts[:, 0] / z + cx
        v = fy * pts[:, 1] / z + cy
    inside = front & (u >= 0) & (v >= 0) & (u <= w - 1) & (v <= h - 1)
    u0 = np.minimum(np.floor(np.where(inside, u, 0)).astype(int), max(w - 2, 0))
    v0 = np.minimum(np.floor(np.where(inside, v, 0)).astype(int), max(h - 2, 0))
    nodes = [depth[v0 + dv, u0 + du] for dv in range(2 if h > 1 else 1) for du in range(2 if w > 1 else 1)]
    stack = np.stack(nodes)
    seen = np.isfinite(stack).any(axis=0)
    zmax = np.where(np.isfinite(stack), stack, -1.0).max(axis=0)
    ok = (~seen) | (z <= zmax + view.bias_rel * z + view.bias_m)
    lit[inside] = ok[inside]
    return lit


@njit(parallel=True, **JIT)
def _irradiance_kernel(pts, nrm, lit, dirs, peak, inv_2s2, cut2, floor, cell, n_a, n_b, a0, b0, cstart, out):
    """E(X) of the module docstring. ``dirs`` and ``peak`` are in cell order (cell id = ib n_a + ia, then
    dot index), dots of cell c at cstart[c] .. cstart[c + 1] - 1; the cells ia0 .. ia1 of one grid row are
    one contiguous run, so each row of the lookup window is a single loop over dots."""
    for i in prange(pts.shape[0]):
        x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            out[i] = np.nan
            continue
        if not (z > 0.0) or not lit[i]:
            out[i] = 0.0
            continue
        r2 = x * x + y * y + z * z
        r = np.sqrt(r2)
        cos_i = -(nrm[i, 0] * x + nrm[i, 1] * y + nrm[i, 2] * z) / r
        if not (cos_i > 0.0):
            out[i] = 0.0
            continue
        ux, uy, uz = x / r, y / r, z / r
        a = x / z
        b = y / z
        reach = 1.1 * np.sqrt(cut2) * (1.0 + a * a + b * b)
        ia0 = max(0, int(np.floor((a - reach - a0) / cell)))
        ia1 = min(n_a - 1, int(np.floor((a + reach - a0) / cell)))
        ib0 = max(0, int(np.floor((b - reach - b0) / cell)))
        ib1 = min(n_b - 1, int(np.floor((b + reach - b0) / cell)))
        s = 0.0
        if ia1 >= ia0:
            for ib in range(ib0, ib1 + 1):
                for j in range(cstart[ib * n_a + ia0], cstart[ib * n_a + ia1 + 1]):
                    t2 = 2.0 - 2.0 * (ux * dirs[j, 0] + uy * dirs[j, 1] + uz * dirs[j, 2])
                    if t2 <= cut2:
                        s += peak[j] * (np.exp(-t2 * inv_2s2) - floor)
        out[i] = s * cos_i / r2


@dataclass(frozen=True)
class Projector:
    """A dot projector at ``offset_m`` along the left imager's x axis (module docstring).

    Attributes
    ----------
    pattern : DotPattern
        The dots.
    offset_m : float
        Position along the camera x axis [m], from the left imager (0.025: midway to the right imager).
    cutoff_sigmas : float
        Dots farther than this many sigma from a point are left out.
    speckle_contrast : float
        Contrast of the laser speckle each imager sees on the dots, fresh every frame (applied by
        :func:`.imagers.expose`); 0 = an incoherent source. 0.4 brings the temporal disparity noise
        of a projector-lit wall to the D435's (Intel's typical 0.08 px; docs/physical-d435.md).
    """

    pattern: DotPattern = DotPattern()
    offset_m: float = 0.025
    cutoff_sigmas: float = 4.0
    speckle_contrast: float = 0.4

    def __post_init__(self):
        if not isinstance(self.pattern, DotPattern):
            raise ValueError(f"pattern must be a DotPattern, got {type(self.pattern).__name__}")
        if not math.isfinite(self.offset_m):
            raise ValueError(f"offset_m must be finite, got {self.offset_m!r}")
        _positive(self.cutoff_sigmas, "cutoff_sigmas")
        if not (math.isfinite(self.speckle_contrast) and 0.0 <= self.speckle_contrast < 10.0):
            raise ValueError(f"speckle_contrast must lie in [0, 10), got {self.speckle_contrast!r}")
        dirs, powers = self.pattern.dots()
        sigma = self.pattern.dot_sigma_rad
        cut2 = (self.cutoff_sigmas * sigma) ** 2
        a_max, b_max = self.pattern.tangent_extent()
        reach = 1.1 * math.sqrt(cut2) * (1.0 + a_max ** 2 + b_max ** 2)
        cell = max(1.1 * math.sqrt(cut2), 1e-6)          # the reach on the axis: a few cells per lookup
        a0, b0 = -a_max - reach, -b_max - reach
        n_a = int(math.ceil((2 * (a_max + reach)) / cell)) + 1
        n_b = int(math.ceil((2 * (b_max + reach)) / cell)) + 1
        ia = np.clip(np.floor((dirs[:, 0] / dirs[:, 2] - a0) / cell).astype(np.int64), 0, n_a - 1)
        ib = np.clip(np.floor((dirs[:, 1] / dirs[:, 2] - b0) / cell).astype(np.int64), 0, n_b - 1)
        cid = ib * n_a + ia
        order = np.argsort(cid, kind="stable")
        cstart = np.searchsorted(cid[order], np.arange(n_a * n_b + 1)).astype(np.int64)
        peak = powers / (2.0 * math.pi * sigma ** 2)
        tables = dict(dirs=np.ascontiguousarray(dirs), peak=peak,
                      inv_2s2=1.0 / (2.0 * sigma ** 2), cut2=cut2, floor=math.exp(-cut2 / (2.0 * sigma ** 2)),
                      cell=cell, n_a=n_a, n_b=n_b, a0=a0, b0=b0, cstart=cstart,
                      cell_dirs=np.ascontiguousarray(dirs[order]), cell_peak=np.ascontiguousarray(peak[order]))
        object.__setattr__(self, "_tables", tables)

    # -- geometry --------------------------------------------------------------------------------
    def pose_in_camera(self) -> np.ndarray:
        """T_cam_proj (4, 4): projector frame -> left-imager frame (a translation along x)."""
        T = np.eye(4)
        T[0, 3] = self.offset_m
        return T

    def pose_in_map(self, T_map_cam) -> np.ndarray:
        """T_map_proj (4, 4) from the left imager's pose T_map_cam."""
        return np.asarray(T_map_cam, dtype=np.float64) @ self.pose_in_camera()

    def view_intrinsics(self, width: int, height: int) -> np.ndarray:
        """K (3, 3) [px] of a (width x height) render that covers the pattern's field (for shadows)."""
        a_max, b_max = self.pattern.tangent_extent()
        f = min((width - 1) / (2.0 * a_max), (height - 1) / (2.0 * b_max))
        return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])

    # -- radiometry ------------------------------------------------------------------------------
    def irradiance(self, points_proj, normals_proj, occlusion=None, nthreads: int | None = None,
                   out=None) -> np.ndarray:
        """Projector irradiance E [W/m^2] on surface points (numba).

        Parameters
        ----------
        points_proj : ndarray, shape (N, 3)
            Surface points in the projector frame [m]; NaN rows = no surface (E = NaN).
        normals_proj : ndarray, shape (N, 3)
            Unit surface normals in the projector frame.
        occlusion : None, callable or ProjectorView
            Shadows (module docstring): None lights every point facing the projector.
        nthreads : int, optional
            numba threads; the result does not depend on it.
        out : ndarray, shape (N,), float64, optional
            Buffer to write into (reused from frame to frame).

        Returns
        -------
        ndarray, shape (N,)
            E(X) of the module docstring; 0 in shadow, behind the projector or on back faces.
        """
        pts = np.ascontiguousarray(points_proj, dtype=np.float64).reshape(-1, 3)
        nrm = np.ascontiguousarray(normals_proj, dtype=np.float64).reshape(-1, 3)
        if nrm.shape != pts.shape:
            raise ValueError(f"normals_proj must have the shape of points_proj {pts.shape}, got {nrm.shape}")
        n = resolve_threads(nthreads)
        lit = _lit(pts, occlusion, n)
        t = self._tables
        if out is None or out.shape != (len(pts),) or out.dtype != np.float64 or not out.flags.c_contiguous:
            out = np.empty(len(pts))
        with threads(n):
            _irradiance_kernel(pts, nrm, lit, t["cell_dirs"], t["cell_peak"], t["inv_2s2"], t["cut2"], t["floor"],
                               t["cell"], t["n_a"], t["n_b"], t["a0"], t["b0"], t["cstart"], out)
        return out


def _lit(pts, occlusion, nthreads) -> np.ndarray:
    if occlusion is None:
        return np.ones(len(pts), np.bool_)
    if isinstance(occlusion, ProjectorView):
        return shadow_mask(pts, occlusion, nthreads)
    if callable(occlusion):
        lit = np.asarray(occlusion(pts), dtype=bool).reshape(-1)
        if lit.shape != (len(pts),):
            raise ValueError(f"the occlusion callable must return one bool per point ({len(pts)}), got {lit.shape}")
        return np.ascontiguousarray(lit)
    raise ValueError(f"occlusion must be None, a callable or a ProjectorView, got {type(occlusion).__name__}")


def irradiance_reference(projector: Projector, points_proj, normals_proj, occlusion=None) -> np.ndarray:
    """NumPy reference of :meth:`Projector.irradiance`: every dot against every point (small N only)."""
    pts = np.asarray(points_proj, dtype=np.float64).reshape(-1, 3)
    nrm = np.asarray(normals_proj, dtype=np.float64).reshape(-1, 3)
    if occlusion is None:
        lit = np.ones(len(pts), bool)
    elif isinstance(occlusion, ProjectorView):
        lit = shadow_mask_reference(pts, occlusion)
    else:
        lit = np.asarray(occlusion(pts), dtype=bool).reshape(-1)
    t = projector._tables
    finite = np.isfinite(pts).all(axis=1)
    p = np.where(finite[:, None], pts, 1.0)
    r = np.linalg.norm(p, axis=1)
    u = p / r[:, None]
    t2 = 2.0 - 2.0 * (u @ t["dirs"].T)
    s = np.where(t2 <= t["cut2"], t["peak"][None, :] * (np.exp(-t2 * t["inv_2s2"]) - t["floor"]), 0.0).sum(axis=1)
    cos_i = -(nrm * p).sum(axis=1) / r
    e = np.where((cos_i > 0.0) & lit & (p[:, 2] > 0.0), s * cos_i / r ** 2, 0.0)
    return np.where(finite, e, np.nan)
