"""The D435 ray caster: noise-free z-depth and incidence angle of a :class:`~noise_model.sim.scene.Scene`.

Frames: map x forward, y left, z up [m]; camera x right, y down, z forward; ``T_map_cam`` maps
camera-frame points into the map frame. Depth is z-depth, not ray length.

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
* With ``return_index=True`` each pixel also names what it hit (the key by which the physical D435
  of :mod:`noise_model.sim.stereo` gives each primitive its own material): k >= 0 is
  ``scene.primitives[k]``, :data:`HIT_GROUND` (-1) the ground plane, :data:`HIT_NONE` (-2) no hit
  (z NaN: nothing within range, or the camera is blinded). The index follows the same tie rule as
  the depth.
* Hits with z > ``max_range_m`` are no data (NaN). Exact ties between primitives go to the first in
  the order ground, box-like primitives (in the scene's order), height fields.
* A camera inside a solid (below the ground, inside a box/step/ramp, under a height field's surface,
  boundaries included) is blinded: every pixel is NaN (a real D435 reads 0 below its minimum range).
* Grazing rays: slabs are closed, so a ray lying in a face's plane and inside the other slabs hits
  (at the next face it meets, or at that face's edge); a ray parallel to a slab and outside it misses.

:func:`render_depth` is the numba kernel (rows in parallel; the result does not depend on the thread
count); :func:`render_depth_reference` computes the same thing in NumPy by independent traversals, and
the tests hold the two equal.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..checks import check_intrinsics, check_positive_scalar, check_transform
from ..numba_config import JIT, resolve_threads, threads
from ._checks import _LIMIT_M, _image_size
from .scene import _RAMP, HF_BLOCK, HeightField, Scene, Stairs

__all__ = ["render_depth", "render_depth_reference", "HIT_GROUND", "HIT_NONE"]

#: Primitive index of a pixel that hit the ground plane (``return_index=True``).
HIT_GROUND = -1
#: Primitive index of a pixel that hit nothing (``return_index=True``; its z is NaN).
HIT_NONE = -2

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
                   max_range, z_out, th_out, pidx, hfidx, want_idx, idx_out):
    """Fill z_out, th_out (H, W) row by row (rows[ii] is the ii-th row computed: interleaved so that
    numba's contiguous split of the prange gives each thread rows from all over the image); with
    ``want_idx`` also idx_out (H, W): the scene index of what each pixel hit (pidx[k] of box-like
    primitive k, hfidx[k] of height field k), HIT_GROUND or HIT_NONE."""
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
            bidx = -2
            if has_ground and dz < 0.0:
                best = (gz - oz) / dz
                bth = gth
                bidx = -1
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
                    bidx = pidx[k]
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
                    bidx = hfidx[k]
                    lim = min(best, max_range)
            if best > 0.0 and best <= max_range:
                z_out[v, u] = best
                th_out[v, u] = bth
            else:
                z_out[v, u] = nan
                th_out[v, u] = nan
                bidx = -2
            if want_idx:
                idx_out[v, u] = bidx


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


def _blinded(width, height, return_index):
    out = np.full((height, width), np.nan), np.full((height, width), np.nan)
    return out + (np.full((height, width), HIT_NONE, dtype=np.int32),) if return_index else out


def render_depth(scene: Scene, K, width: int, height: int, T_map_cam, max_range_m: float = 10.0,
                 nthreads: int | None = None, return_index: bool = False) -> tuple[np.ndarray, ...]:
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
    return_index : bool
        Also return what each pixel hit.

    Returns
    -------
    z_true : ndarray, shape (height, width), float64
        z-depth of the first hit [m] (distance along the optical axis, not ray length); NaN = no hit,
        beyond ``max_range_m``, or the camera is inside a solid.
    theta : ndarray, shape (height, width), float64
        Angle between the hit surface's normal and the optical axis [rad], in [0, pi/2]; NaN where
        z_true is NaN.
    index : ndarray, shape (height, width), int32
        Only with ``return_index``: k >= 0 for ``scene.primitives[k]``, :data:`HIT_GROUND` (-1) for the
        ground plane, :data:`HIT_NONE` (-2) where z_true is NaN.
    """
    K, width, height, T, max_range, inside = _prepare_render(scene, K, width, height, T_map_cam, max_range_m)
    n = resolve_threads(nthreads)
    if inside:
        return _blinded(width, height, return_index)
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
    idx = np.empty((height, width) if return_index else (1, 1), dtype=np.int32)
    with threads(n):
        _render_kernel(intr, T, rows, ground, pk.kinds, pk.pf, ptab, prect, pk.hfi, pk.hff, hftab, hfrect,
                       pk.hv, pk.cm, pk.bm, max_range, z, th, pk.box_index, pk.field_index, bool(return_index), idx)
    return (z, th, idx) if return_index else (z, th)


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
                           max_range_m: float = 10.0, return_index: bool = False) -> tuple[np.ndarray, ...]:
    """NumPy reference of :func:`render_depth` (slow; same arguments and results).

    Independent of the kernel's traversals: stairs are rendered as their steps (one box each) and
    height fields by brute force over every cell a ray's segment can touch; no image-space culling;
    theta from per-pixel normal vectors.
    """
    K, width, height, T, max_range, inside = _prepare_render(scene, K, width, height, T_map_cam, max_range_m)
    if inside:
        return _blinded(width, height, return_index)
    R, o = T[:3, :3], T[:3, 3]
    u = (np.arange(width) - K[0, 2]) / K[0, 0]
    v = (np.arange(height) - K[1, 2]) / K[1, 1]
    U, V = np.meshgrid(u, v)
    d = np.stack([U.ravel(), V.ravel(), np.ones(U.size)], axis=1) @ R.T        # (N, 3), t = z-depth
    N = d.shape[0]
    best = np.full(N, np.inf)
    normal = np.full((N, 3), np.nan)
    index = np.full(N, HIT_NONE, dtype=np.int32)

    def update(t, nrm, k):
        better = t < best
        best[better] = t[better]
        normal[better] = nrm[better] if nrm.ndim == 2 else nrm
        index[better] = k

    if scene.ground_z is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(d[:, 2] < 0, (scene.ground_z - o[2]) / d[:, 2], np.inf)
        update(t, np.array([0.0, 0.0, 1.0]), HIT_GROUND)
    for k, p in enumerate(scene.primitives):
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
            update(t, nrm, k)
    for k, f in enumerate(scene.primitives):
        if isinstance(f, HeightField):
            t, nrm = _field_reference(f, o, d, max_range)
            update(t, nrm, k)
    ok = (best > 0) & (best <= max_range)
    z = np.where(ok, best, np.nan).reshape(height, width)
    theta = np.where(ok, _theta_of(np.nan_to_num(normal), R[:, 2]), np.nan).reshape(height, width)
    if return_index:
        return z, theta, np.where(ok, index, HIT_NONE).astype(np.int32).reshape(height, width)
    return z, theta

