"""Ray-cast visibility clean-up: remove cells that a ray to a measured point passed below.

A sensor ray from the camera centre to a measured point crosses free space. A known cell whose
surface the ray passes clearly *below* cannot be there any more (a person who walked away, a box
that was moved, a spurious spike): it is cleared. Every cell a ray crosses also learns a free-space
bound (the ``upper_bound`` layer): the terrain there is below the ray.

Semantics, run once per frame right after the frame's fusion (cells updated in this frame have
``time == stamp``). Cell indices are those of :mod:`elevmap.map.grid` (global lattice gx = floor(x / res)).

1. **Which rays.** Only points inside the map window cast rays (a point outside has no cell). For
   every cell that received points this frame, one ray goes to that cell's *lowest* point of the
   frame (as ANYbotics' ``lowest_scan_point``): the lowest point's ray is the one that passes lowest
   over the cells in front, so it clears the most. Ties in height go to the point with the smaller
   index. The rays are ordered by the map index (i, j) of their cell (row-major) and every
   ``stride``-th is kept, starting with the first (``stride=1``: all).
2. **Traversal.** A ray from the sensor origin o to the point p is traversed in 2-D through the
   global lattice, exactly (Amanatides & Woo): with u = x / res, v = y / res, the ray crosses the
   cell border u = k at t = (k - u_o) / (u_p - u_o) (likewise for v), t in [0, 1] along the ray;
   the cells it visits are those between consecutive crossings, in order, from the sensor's cell to
   the point's cell. A ray through a lattice corner steps diagonally (both crossings at the same t),
   so it touches neither of the two side cells. A cell is entered at t_in and left at t_out; the
   ray's height in it ranges over [z(t_in), z(t_out)], z(t) = z_o + t (z_p - z_o), and the HIGHER of
   the two is the ray's *ceiling* in that cell (the whole ray segment inside the cell is below it).
   The point's own cell and the cells within one cell of it (Chebyshev distance <= 1 in global
   indices: the surface is there) are excluded; as both indices move monotonically towards the
   point's cell, the traversal simply stops there. Only cells inside the window count: a ray whose
   origin is outside the window starts where it enters the window (t_in of its first cell is the
   entry crossing).
3. **Ceiling.** The frame's ceiling of a cell is the minimum over the rays of their ceilings there.
4. **Clearing.** A known cell (finite elevation) that was NOT updated in this frame (time != stamp)
   and whose ceiling < elevation - 3 sqrt(variance) is cleared: all its layers take their unknown
   values (``layers.UNKNOWN_VALUES``: NaN, points = 0), then its ``upper_bound`` is set to the
   ceiling (the free-space bound stays valid). The count of cleared cells is returned.
5. **Upper bound.** Every other crossed cell (known or not, updated this frame or not) gets
   upper_bound = min(upper_bound, ceiling), a NaN upper_bound counting as +inf.

Determinism: the per-cell lowest point and the per-cell ceiling are accumulated race-free into
``PARTIALS`` fixed partial grids (points cut into fixed contiguous ranges; rays dealt round-robin
to the partials) and merged per cell in a fixed order; both are exact minima with a fixed tie
rule, so the result is the same bit for bit whatever the thread count.
:func:`visibility_cleanup_reference` computes the same thing in plain NumPy/Python, ray by ray, from
the merged list of border crossings (no DDA); the tests hold the two equal. The heights z(t) and the
threshold elevation - 3 sigma may differ in the last bit between the two (the compiler may fuse a
multiply-add), never the cells visited nor the crossing times.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from noise_model.numba_config import JIT, resolve_threads, threads

from .fusion import LOW_K, LOW_Z, PARTIALS, neighbour_excess, touched_box
from .layers import (
    ELEVATION, LAYERS, NEIGHBOUR_SPREAD, SPREAD, TIME, UNKNOWN_VALUES, UPPER_BOUND, VARIANCE, clear_sums,
)

__all__ = ["visibility_cleanup", "visibility_cleanup_box", "visibility_cleanup_reference"]


#: Rays are dealt to the partial ceiling grids in blocks of this many consecutive rays (neighbouring
#: rays cross the same cells: cache locality), round-robin (every partial gets near and far rays).
_RAY_BLOCK = 16


# ---------------------------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------------------------
def _check_inputs(data, geometry, sensor_origin_map, points_map, stamp, stride):
    """Validate everything but the finiteness of the points (the kernel checks that while reading
    them, before it changes anything; the reference checks it here)."""
    n = geometry.n
    if not isinstance(data, np.ndarray) or data.shape != (len(LAYERS), n, n) or data.dtype != np.float64:
        raise ValueError(f"data must be a float64 array of shape ({len(LAYERS)}, {n}, {n}), got "
                         f"{getattr(data, 'shape', None)} {getattr(data, 'dtype', type(data).__name__)}")
    o = np.asarray(sensor_origin_map)
    if o.shape != (3,) or not (np.issubdtype(o.dtype, np.floating) or np.issubdtype(o.dtype, np.integer)):
        raise ValueError(f"sensor_origin_map must be 3 numbers [m], got shape {o.shape} dtype {o.dtype}")
    o = o.astype(np.float64)
    if not np.all(np.isfinite(o)):
        raise ValueError(f"sensor_origin_map must be finite, got {o!r}")
    if float(np.abs(o[:2]).max()) / geometry.resolution_m >= 2.0 ** 50:      # cell indices must stay exact
        raise ValueError(f"sensor_origin_map {o!r} is implausibly far from the map origin [m]")
    p = np.asarray(points_map)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points_map must have shape (N, 3), got {p.shape}")
    if np.issubdtype(p.dtype, np.integer):
        p = p.astype(np.float64)
    elif not np.issubdtype(p.dtype, np.floating):
        raise ValueError(f"points_map must be floating point metres, got dtype {p.dtype}")
    if p.dtype != np.float64:
        p = p.astype(np.float64)       # any memory layout will do: the mapper's (N, 3) views are F-ordered
    if len(p) >= 2 ** 31 - 1:
        raise ValueError(f"points_map has {len(p)} points; at most 2**31 - 2 per frame")
    if isinstance(stride, (bool, np.bool_)) or not isinstance(stride, (int, np.integer)):
        raise ValueError(f"stride must be an int >= 1, got {stride!r}")
    if int(stride) < 1:
        raise ValueError(f"stride must be >= 1, got {stride!r}")
    try:
        s = float(stamp)
    except (TypeError, ValueError):
        raise ValueError(f"stamp must be a number [s], got {stamp!r}") from None
    if not math.isfinite(s):
        raise ValueError(f"stamp must be finite, got {stamp!r}")
    return o, p, int(stride), s


#: Rays end this many of the point's own height standard deviations above it (ANYbotics: 3).
ENDPOINT_MARGIN_SIGMAS = 3.0


def _check_margin(height_var, margin_sigmas, n_points):
    """Validated (variances, margin); without variances the margin is 0 (rays end at the points)."""
    m = float(margin_sigmas)
    if not (math.isfinite(m) and m >= 0.0):
        raise ValueError(f"margin_sigmas must be finite and >= 0, got {margin_sigmas!r}")
    if height_var is None:
        return np.zeros(1), 0.0
    v = np.asarray(height_var, dtype=np.float64)
    if v.shape != (n_points,):
        raise ValueError(f"height_var must have shape ({n_points},), got {v.shape}")
    if n_points and not (np.all(np.isfinite(v)) and float(v.min()) >= 0.0):
        raise ValueError("height_var must be finite and >= 0 [m^2]")
    return np.ascontiguousarray(v), m


def _nonfinite_error(p):
    bad = int((~np.isfinite(p)).any(axis=1).sum())
    return ValueError(f"points_map has {bad} non-finite row(s); drop invalid points first")


# ---------------------------------------------------------------------------------------------
# numba
# ---------------------------------------------------------------------------------------------
@njit(inline="always", **JIT)
def _axis_start(u0, du):
    """Step direction and starting cell of a ray along one axis (cell units); a ray moving down from a
    border starts in the cell below it."""
    if du > 0.0:
        return 1, np.int64(math.floor(u0))
    if du < 0.0:
        return -1, np.int64(math.ceil(u0)) - 1
    return 0, np.int64(math.floor(u0))


@njit(**JIT)
def _t_leave(i, s, u0, rdu):
    """Ray parameter at which the ray leaves cell ``i`` along an axis walked in direction ``s``."""
    b = i + 1 if s > 0 else i
    return (b - u0) * rdu


@njit(**JIT)
def _advance(i, s, e, u0, du, rdu, T):
    """The axis cell after applying every border crossing with t <= T (exact, by the crossing times)."""
    est = math.floor(u0 + T * du)           # a guess, corrected below against the crossing times
    if s > 0:
        est = min(max(est, i), e)
    else:
        est = max(min(est, i), e)
    k = np.int64(est)
    while k != i and _t_leave(k - s, s, u0, rdu) > T:
        k -= s
    while k != e and _t_leave(k, s, u0, rdu) <= T:
        k += s
    return k


@njit(**JIT)
def _cast(ceil, ox, oy, oz, px, py, pz, res, gx0, gy0, n, i0, i1, j0, C):
    """Walk one ray (Amanatides & Woo) and lower ``ceil`` by the ray's ceilings: ``ceil`` holds the cells of
    map rows i0.. and columns j0..j0 + C - 1 in row-major order (they must hold every cell the ray crosses
    in the window: those between the window's cell nearest the origin and the point's cell)."""
    u0 = ox / res
    v0 = oy / res
    ue = px / res
    ve = py / res
    ex = np.int64(math.floor(ue))
    ey = np.int64(math.floor(ve))
    du = ue - u0
    dv = ve - v0
    dz = pz - oz
    inf = np.inf
    sx, ix = _axis_start(u0, du)        # per axis: step direction and the starting cell
    sy, iy = _axis_start(v0, dv)
    if max(abs(ix - ex), abs(iy - ey)) <= 1:
        return
    rdu = 1.0 / du if sx != 0 else 0.0
    rdv = 1.0 / dv if sy != 0 else 0.0
    # origin outside the window: jump to where the ray enters it (the endpoint is inside)
    T = 0.0
    if ix < gx0:
        T = max(T, (gx0 - u0) * rdu)
    elif ix >= gx0 + n:
        T = max(T, (gx0 + n - u0) * rdu)
    if iy < gy0:
        T = max(T, (gy0 - v0) * rdv)
    elif iy >= gy0 + n:
        T = max(T, (gy0 + n - v0) * rdv)
    if T > 0.0:
        if sx != 0:
            ix = _advance(ix, sx, ex, u0, du, rdu, T)
        if sy != 0:
            iy = _advance(iy, sy, ey, v0, dv, rdv, T)
    i = ix - gx0
    j = iy - gy0
    if not (i >= i0 and i <= i1 and j >= j0 and j < j0 + C):     # cannot happen (the region holds the ray)
        return
    # from here on the ray stays inside the window: both indices move monotonically towards the
    # endpoint's cell, which is inside
    k = (i - i0) * C + (j - j0)                           # row-major index in the region
    dkx = sx * C
    # borders through which the ray leaves the current cell (exact small integers as floats)
    bx = float(ix + 1) if sx > 0 else float(ix)
    by = float(iy + 1) if sy > 0 else float(iy)
    tx = (bx - u0) * rdu if ix != ex else inf
    ty = (by - v0) * rdv if iy != ey else inf
    z_in = oz + T * dz
    while max(abs(ix - ex), abs(iy - ey)) > 1:
        t_out = min(tx, ty)
        z_out = oz + t_out * dz
        c = max(z_in, z_out)
        if c < ceil[k]:
            ceil[k] = c
        z_in = z_out
        # step the axis whose border comes first; both at a lattice corner (equal times)
        if tx <= t_out:
            ix += sx
            bx += sx
            k += dkx
            tx = (bx - u0) * rdu if ix != ex else inf
        if ty <= t_out:
            iy += sy
            by += sy
            k += sy
            ty = (by - v0) * rdv if iy != ey else inf


@njit(inline="always", **JIT)
def _zend(pts, zvar, margin, k):
    """Height of ray k's end: the point raised by ``margin`` of its own standard deviations."""
    return pts[k, 2] + margin * math.sqrt(zvar[k]) if margin > 0.0 else pts[k, 2]


@njit(parallel=True, **JIT)
def _lowest_kernel(n, gx0, gy0, res, pts, zvar, margin, P, i0, i1, j0, j1, best):
    """Step 1 over the region of map rows i0..i1 and columns j0..j1, which holds every point's cell in the
    window and the window's cell nearest the sensor origin (so every cell a ray crosses); its cells are
    indexed row-major, c = (i - i0) C + (j - j0). ``best[c]`` receives the index of the cell's lowest
    point (-1: none). Returns -1 when a point is not finite (nothing written to the map), else 0."""
    C = j1 - j0 + 1
    nn = (i1 - i0 + 1) * C
    N = pts.shape[0]
    # 1. per-partial lowest point of each cell (region order), points in fixed contiguous ranges
    low = np.empty((P, nn), dtype=np.int32)          # point indices (N < 2**31, checked)
    lowz = np.empty((P, nn))                         # their ray-end heights (no sqrt recomputed)
    bad = np.zeros(P, dtype=np.int64)
    for p in prange(P):
        lp = low[p]
        lz = lowz[p]
        for c in range(nn):
            lp[c] = -1
        lo = (N * p) // P
        hi = (N * (p + 1)) // P
        nbad = 0
        for k in range(lo, hi):
            if not (math.isfinite(pts[k, 0]) and math.isfinite(pts[k, 1]) and math.isfinite(pts[k, 2])):
                nbad += 1
                continue
            fi = math.floor(pts[k, 0] / res) - gx0
            fj = math.floor(pts[k, 1] / res) - gy0
            if not (fi >= i0 and fi <= i1 and fj >= j0 and fj <= j1):     # the region lies in the window
                continue
            c = (int(fi) - i0) * C + int(fj) - j0
            zk = _zend(pts, zvar, margin, k)
            if lp[c] < 0 or zk < lz[c]:                 # k increases: ties keep the smaller index
                lp[c] = np.int32(k)
                lz[c] = zk
        bad[p] = nbad
    if bad.sum() > 0:
        return -1                                   # non-finite points: nothing has been changed
    # merge in partial order: (z, index) lexicographic minimum
    for c in prange(nn):
        b = np.int64(-1)
        zb = np.inf
        for p in range(P):
            k = low[p, c]
            if k >= 0:
                zk = lowz[p, c]
                if b < 0 or zk < zb or (zk == zb and k < b):
                    b = k
                    zb = zk
        best[c] = b
    return 0


@njit(parallel=True, **JIT)
def _lowest_from_fusion(acc, acc_stamp, fid, low_z, low_k, n, sx, sy, i0, i1, j0, j1, best):
    """Step 1 from the fusion's partial grids of this frame (stamp ``fid``; fields ``low_z``, ``low_k``:
    each partial's lowest ray end in a cell and its point), merged in partial order to the same (z, index)
    lexicographic minimum as :func:`_lowest_kernel`, over the same region."""
    C = j1 - j0 + 1
    P = acc.shape[0]
    for i in prange(i0, i1 + 1):
        bi = i + sx
        if bi >= n:
            bi -= n
        for j in range(j0, j1 + 1):
            bj = j + sy
            if bj >= n:
                bj -= n
            c = bi * n + bj
            b = np.int64(-1)
            zb = np.inf
            for p in range(P):
                if acc_stamp[p, c] == fid and acc[p, c, low_k] >= 0.0:
                    k = np.int64(acc[p, c, low_k])
                    zk = acc[p, c, low_z]
                    if b < 0 or zk < zb or (zk == zb and k < b):
                        b = k
                        zb = zk
            best[(i - i0) * C + j - j0] = b


@njit(parallel=True, **JIT)
def _cast_kernel(data, gx0, gy0, res, pts, zvar, margin, ox, oy, oz, stamp, stride, P, i0, i1, j0, j1, best):
    """Steps 2-5 over the region of :func:`_lowest_kernel`, from each cell's lowest point ``best``."""
    n = data.shape[1]
    C = j1 - j0 + 1
    nn = (i1 - i0 + 1) * C
    sx = gx0 % n
    sy = gy0 % n
    # 2. rays: cells with points in map order (row-major in the region is map order), every stride-th
    nr = 0
    for c in range(nn):
        if best[c] >= 0:
            nr += 1
    rays = np.empty((nr + stride - 1) // stride, dtype=np.int64)
    r = 0
    m = 0
    for c in range(nn):
        if best[c] >= 0:
            if r % stride == 0:
                rays[m] = best[c]
                m += 1
            r += 1
    # 3. cast, rays dealt to the partial ceiling grids in blocks, round-robin
    ceil = np.empty((P, nn))
    for p in prange(P):
        cp = ceil[p]
        for c in range(nn):
            cp[c] = np.inf
        for b0 in range(p * _RAY_BLOCK, m, P * _RAY_BLOCK):
            for q in range(b0, min(b0 + _RAY_BLOCK, m)):
                k = rays[q]
                _cast(cp, ox, oy, oz, pts[k, 0], pts[k, 1], _zend(pts, zvar, margin, k), res, gx0, gy0, n, i0, i1,
                      j0, C)
    # 4. merge and apply
    cleared = 0
    for c in prange(nn):
        cm = ceil[0, c]
        for p in range(1, P):
            cm = min(cm, ceil[p, c])
        if cm == np.inf:
            continue
        bi = c // C + i0 + sx
        if bi >= n:
            bi -= n
        bj = c % C + j0 + sy
        if bj >= n:
            bj -= n
        h = data[ELEVATION, bi, bj]
        # the cell's own variance, without its neighbourhood's disagreement (which is about where an edge
        # lies, not about whether this cell's height is right)
        if (not np.isnan(h)) and data[TIME, bi, bj] != stamp and cm < h - 3.0 * math.sqrt(
                data[VARIANCE, bi, bj] - neighbour_excess(data, bi, bj)):
            for layer in range(data.shape[0]):
                data[layer, bi, bj] = np.nan
            clear_sums(data, bi, bj)
            data[UPPER_BOUND, bi, bj] = cm
            cleared += 1
        else:
            ub = data[UPPER_BOUND, bi, bj]
            if np.isnan(ub) or cm < ub:
                data[UPPER_BOUND, bi, bj] = cm
    return cleared


# ---------------------------------------------------------------------------------------------
# public entries
# ---------------------------------------------------------------------------------------------
def visibility_cleanup(data, geometry, sensor_origin_map, points_map, stamp, stride=1, nthreads=None,
                       height_var=None, margin_sigmas: float = ENDPOINT_MARGIN_SIGMAS) -> int:
    """Clear cells that rays to this frame's points pass below; lower the upper bounds (numba).

    Parameters
    ----------
    data : ndarray, shape (len(LAYERS), n, n), float64
        The map's layers in buffer order; modified in place.
    geometry : elevmap.map.grid.GridGeometry
        The window ``data`` is stored for.
    sensor_origin_map : (3,) array_like
        Camera centre in the map frame [m].
    points_map : array_like, shape (N, 3)
        This frame's points in the map frame [m] (finite).
    stamp : float
        This frame's stamp: cells with ``time == stamp`` were updated in this frame and are kept.
    stride : int
        Keep every ``stride``-th ray (one ray per cell, see the module docstring).
    nthreads : int, optional
        numba threads (numba's setting by default); the result does not depend on it.
    height_var : array_like, shape (N,), optional
        Height variance of each point [m^2]. With it, each ray ends at z + margin_sigmas sigma
        instead of z (ANYbotics uses the lowest z + 3 sigma): a point measured too low must not
        clear the surface it was measured on.
    margin_sigmas : float
        See ``height_var``.

    Returns
    -------
    int
        The number of cells cleared.
    """
    o, p, stride, stamp = _check_inputs(data, geometry, sensor_origin_map, points_map, stamp, stride)
    zvar, margin = _check_margin(height_var, margin_sigmas, len(p))
    nt = resolve_threads(nthreads)
    if len(p) == 0:
        return 0
    box = touched_box(geometry, p)
    if box is None:                     # no point in the window: no ray
        if not np.all(np.isfinite(p)):
            raise _nonfinite_error(p)
        return 0
    return visibility_cleanup_box(data, geometry, o, p, stamp, box, stride, nt, zvar, margin)


def visibility_cleanup_box(data, geometry, origin, points_map, stamp, box, stride, nthreads, zvar, margin,
                           fused=None) -> int:
    """:func:`visibility_cleanup` on checked inputs, given the first and last map row and column of the cells
    holding points, ``box`` = (i0, i1, j0, j1) (as :func:`elevmap.map.fusion.fuse_frame` returns it): the
    kernel then works on the rows and columns between them and the sensor origin only. ``zvar`` is the
    points' height variance [m^2] (any array when ``margin`` = 0).

    ``fused`` = (workspace.acc, workspace.stamp, workspace.frame) of the fusion of these very points with
    ``low_margin=margin`` (:func:`elevmap.map.fusion.fuse_frame`): each cell's lowest point is then taken
    from its partial grids instead of a pass over the points."""
    n = geometry.n
    i0, i1, j0, j1 = (int(v) for v in box)
    if not (0 <= i0 <= i1 < n and 0 <= j0 <= j1 < n):
        raise ValueError(f"box must be (first row, last row, first column, last column) within [0, {n - 1}], "
                         f"got {box!r}")
    (oi, oj), _ = geometry.map_index(np.asarray(origin, dtype=np.float64)[:2])
    oi, oj = min(max(int(oi), 0), n - 1), min(max(int(oj), 0), n - 1)    # where a ray from outside enters
    region = (min(i0, oi), max(i1, oi), min(j0, oj), max(j1, oj))
    best = np.empty((region[1] - region[0] + 1) * (region[3] - region[2] + 1), dtype=np.int64)
    g = geometry
    with threads(resolve_threads(nthreads)):
        if fused is not None:
            acc, acc_stamp, fid = fused
            sx, sy = g.start_index
            _lowest_from_fusion(acc, acc_stamp, fid, LOW_Z, LOW_K, n, int(sx), int(sy), *region, best)
        elif _lowest_kernel(n, g.gx0, g.gy0, g.resolution_m, points_map, zvar, float(margin), PARTIALS, *region,
                            best) < 0:
            raise _nonfinite_error(points_map)
        return int(_cast_kernel(data, g.gx0, g.gy0, g.resolution_m, points_map, zvar, float(margin),
                                float(origin[0]), float(origin[1]), float(origin[2]), float(stamp), int(stride),
                                PARTIALS, *region, best))


def _ray_cells(o, pt, res):
    """Cells visited by the ray o -> pt in global indices with their (t_in, t_out), from the merged
    border crossings (plain NumPy): arrays gx, gy, t_in, t_out, in order along the ray."""
    cells = []
    crossings = []
    for a in range(2):
        u0, ue = o[a] / res, pt[a] / res
        du = ue - u0
        e = math.floor(ue)
        if du > 0:
            start = math.floor(u0)
            borders = np.arange(start + 1, e + 1)          # entering cell k at border k
        elif du < 0:
            start = math.ceil(u0) - 1
            borders = np.arange(start, e, -1)              # leaving cell k into k - 1 at border k
        else:
            start = math.floor(u0)
            borders = np.arange(0)
        rdu = 1.0 / du if du != 0 else 0.0
        cells.append(start)
        crossings.append(((borders - u0) * rdu, 1 if du > 0 else -1))
    (tx, sx), (ty, sy) = crossings
    events = np.unique(np.concatenate([tx, ty]))           # sorted; equal times step both axes at once
    ix = cells[0] + sx * np.searchsorted(tx, events, side="right")
    iy = cells[1] + sy * np.searchsorted(ty, events, side="right")
    gx = np.concatenate([[cells[0]], ix])
    gy = np.concatenate([[cells[1]], iy])
    t_in = np.concatenate([[0.0], events])
    t_out = np.concatenate([events, [1.0]])
    return gx.astype(np.int64), gy.astype(np.int64), t_in, t_out


def visibility_cleanup_reference(data, geometry, sensor_origin_map, points_map, stamp, stride=1,
                                 nthreads=None, height_var=None,
                                 margin_sigmas: float = ENDPOINT_MARGIN_SIGMAS) -> int:
    """Plain NumPy/Python reference of :func:`visibility_cleanup` (slow; ``nthreads`` is ignored)."""
    o, p, stride, stamp = _check_inputs(data, geometry, sensor_origin_map, points_map, stamp, stride)
    zvar, margin = _check_margin(height_var, margin_sigmas, len(p))
    if margin > 0.0:
        p = p.copy()
        p[:, 2] += margin * np.sqrt(zvar)
    resolve_threads(nthreads)
    if not np.all(np.isfinite(p)):
        raise _nonfinite_error(p)
    g = geometry
    n, res = g.n, g.resolution_m
    if len(p) == 0:
        return 0
    # 1. lowest point per cell (map order); rays in map order, every stride-th
    ij, inside = g.map_index(p[:, :2])
    idx = np.flatnonzero(inside)
    cell = ij[idx, 0] * n + ij[idx, 1]
    order = np.lexsort((idx, p[idx, 2], cell))             # by cell, then z, then point index
    first = np.ones(len(order), dtype=bool)
    first[1:] = cell[order][1:] != cell[order][:-1]
    lowest = idx[order][first]                             # one point per cell, cells ascending
    rays = lowest[::stride]
    # 2.-3. per-cell ceiling, ray by ray
    ceiling = np.full((n, n), np.inf)                      # map order
    for k in rays:
        pt = p[k]
        gx, gy, t_in, t_out = _ray_cells(o, pt, res)
        ex, ey = math.floor(pt[0] / res), math.floor(pt[1] / res)
        i, j = gx - g.gx0, gy - g.gy0
        keep = (np.maximum(np.abs(gx - ex), np.abs(gy - ey)) > 1) & (i >= 0) & (i < n) & (j >= 0) & (j < n)
        dz = pt[2] - o[2]
        c = np.maximum(o[2] + t_in * dz, o[2] + t_out * dz)
        np.minimum.at(ceiling, (i[keep], j[keep]), c[keep])
    # 4.-5. apply, in buffer order
    ceil_b = g.wrap(ceiling)
    crossed = np.isfinite(ceil_b)
    h, t, ub = data[ELEVATION], data[TIME], data[UPPER_BOUND]
    s = np.where(data[SPREAD] > 0, data[SPREAD], 0.0)
    v = data[VARIANCE] - np.maximum(np.where(data[NEIGHBOUR_SPREAD] > 0, data[NEIGHBOUR_SPREAD], 0.0) - s, 0.0)
    with np.errstate(invalid="ignore"):
        clear = crossed & np.isfinite(h) & (t != stamp) & (ceil_b < h - 3.0 * np.sqrt(v))
        lower = crossed & ~clear & (np.isnan(ub) | (ceil_b < ub))
    new_ub = np.where(clear | lower, ceil_b, ub)
    data[:, clear] = np.array(UNKNOWN_VALUES)[:, None]
    data[UPPER_BOUND] = new_ub
    return int(clear.sum())
