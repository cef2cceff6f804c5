"""Neighbourhood spread: the disagreement of a cell's neighbours, added to its variance (docs/fusion.md).

A cell's fused variance P (``variance`` minus the larger of its two spreads) says how well its points
pin down their mean if they are independent, unbiased and land in the right cell. Near a step edge and
in the far field of a D435 they often do not: the depth noise along a grazing ray is decimetres, so
points of one level land in cells of the other, and cells near an edge hold errors of decimetres with P
of millimetres squared. Such errors are not visible inside a cell, whose points agree with each other,
but they are visible between cells: neighbouring heights scatter far more than their variances allow.

For every known cell c, over the known cells j within ``radius`` cells (a (2 radius + 1)^2 window,
c included) with weights w_j = 1 / P_j, the DerSimonian-Laird random-effects estimator
(:func:`noise_model.formulas.dersimonian_laird_tau2`)

    m = sum w_j h_j / sum w_j,   Q = sum w_j (h_j - m)^2,
    tau_n^2 = max(Q - (k - 1), 0) / (S1 - S2 / S1),   S1 = sum w_j, S2 = sum w_j^2,

(k the number of known cells in the window; 0 when k < 2) is the variance of the true heights about
the window's mean beyond the cells' own variances. By default (``estimator="paule_mandel"``) it is
refined to the Paule-Mandel estimator, the root of the generalised Q statistic

    Q(tau^2) = sum w_j (h_j - m)^2 = k - 1,   w_j = 1 / (P_j + tau^2),   m = sum w_j h_j / sum w_j,

solved by safeguarded Newton steps on 1 / Q (linear in tau^2 when the P_j are equal; a step below
``PM_STEP_TOL`` of tau^2 is the last) from the cell's last root (a warm start) or the DerSimonian-Laird
value (Q decreases in tau^2; dQ/dtau^2 =
-sum w_j^2 (h_j - m)^2), where Q(0) > k - 1 (elsewhere both are 0); with equal P the two coincide.
Why: a D435 map's P span four decades (near cells (1 mm)^2, far cells centimetres), and
DerSimonian-Laird's weights are then the precise cells': in a window of a floor and a box top it sees
the spread as the few precise cells do, and often falls below half the true spread
(``tests/map/test_neighbours.py``), which makes a cell beside a box confident. Paule-Mandel weighs the
cells by 1 / (P_j + tau^2), evenly once the spread exceeds their own variances (Veroniki et al. 2016,
Res. Synth. Methods 7: 55-79, recommend it over DerSimonian-Laird). It costs an evaluation of Q over each
cell's window per Newton step (``elevmap bench``); the first, which settles nearly every cell of a frame
(a warm start is one small step from the root), runs for a row's cells side by side.

The result is stored as ``neighbour_spread`` and the cell's variance becomes P + max(spread,
neighbour_spread): the height at the centre of a cell in a window whose cells disagree is uncertain by
that disagreement. The fusion's gate and prior work on the variance without it
(:func:`elevmap.map.fusion.neighbour_excess`; the visibility clean-up too); a new point's weight
1 / (sigma^2 + tau^2) takes tau^2 = max(spread, neighbour_spread), so the heights depend on it through
the weights of later points only.

The window sums are separable (along the rows, then down the columns); heights enter them relative to
the mean height of the known cells of the cells' windows (sampled every 8th row and column), so that the
sums stay well conditioned however high the map lies. Cells with a non-finite or non-positive P contribute nothing.
Only the window of cells touched by a frame (plus ``radius``) is recomputed: the others'
neighbourhoods did not change. :func:`update_neighbour_spread_reference` computes the same thing with
NumPy (the same sums in the same order, the same Newton steps); the tests hold the two equal.

What it cannot see: a band of cells that agree with each other and are all wrong (a sliver of a step's
top binned into the floor cell beside it, with nothing of the floor seen around it).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from noise_model.formulas import dersimonian_laird_tau2
from noise_model.numba_config import JIT, resolve_threads, threads

from .layers import ELEVATION, NEIGHBOUR_SPREAD, SPREAD, VARIANCE

__all__ = ["update_neighbour_spread", "update_neighbour_spread_reference", "fused_variance", "interleaved"]

#: Paule-Mandel convergence: |Q(tau^2) - (k - 1)| <= PM_TOL (k - 1).
PM_TOL = 1e-10
#: At most this many evaluations of Q per cell.
PM_MAX_STEPS = 100
#: Paule-Mandel convergence by the step: a Newton step below PM_STEP_TOL tau^2 is taken and is the last.
#: Newton's error after a step is of the order of the step's square (a fraction of it: ~1e-4 of tau^2 at
#: most here), far below tau^2's own sampling uncertainty (a relative sqrt(2 / (k - 1)), 16 % over 81
#: cells). Between frames a cell's root moves by a few percent of itself, so a warm start from the last
#: frame's root is one such step away: one evaluation of Q per cell instead of two.
PM_STEP_TOL = 3e-2
#: The estimators of the neighbourhood spread (``FusionParams.neighbour_estimator``).
ESTIMATORS = ("paule_mandel", "dersimonian_laird")

#: noise_model.formulas.dersimonian_laird_tau2, compiled.
_dersimonian_laird_tau2 = njit(**JIT)(dersimonian_laird_tau2)


def fused_variance(data) -> np.ndarray:
    """P = variance - max(spread, neighbour_spread) per cell (NaN spreads count as 0), buffer order.

    Parameters
    ----------
    data : ndarray, shape (len(LAYERS), n, n)

    Returns
    -------
    ndarray, shape (n, n) [m^2]
        NaN where the cell is unknown.
    """
    s = np.where(data[SPREAD] > 0, data[SPREAD], 0.0)
    nb = np.where(data[NEIGHBOUR_SPREAD] > 0, data[NEIGHBOUR_SPREAD], 0.0)
    return data[VARIANCE] - np.maximum(s, nb)


@njit(**JIT)
def interleaved(q, n, T):
    """The q-th of n rows (0 <= q < n) in the order 0, T, 2 T, ..., 1, T + 1, ..., T - 1, 2 T - 1, ...: a
    parallel loop over q hands each of its T threads a contiguous range of q, which then holds every T-th
    row. Why: the work per row grows across the map (a camera's view widens with distance), so contiguous
    blocks of rows leave the thread with the far rows most of the work (docs/fusion.md)."""
    k = np.int64(q)                            # a parallel loop's index may be unsigned
    n = np.int64(n)
    T = np.int64(T)
    for m in range(T):
        cnt = (n - m + T - 1) // T
        if k < cnt:
            return m + k * T
        k -= cnt
    return k


@njit(**JIT)
def _cell(data, bi, bj):
    """(height, fused variance P, spread) of buffer cell (bi, bj); NaN spreads count as 0."""
    s = data[SPREAD, bi, bj]
    s = s if s > 0.0 else 0.0
    nb = data[NEIGHBOUR_SPREAD, bi, bj]
    nb = nb if nb > 0.0 else 0.0
    return data[ELEVATION, bi, bj], data[VARIANCE, bi, bj] - max(s, nb), s


@njit(**JIT)
def _paule_mandel_step(y, p, k, t, w):
    """One evaluation at tau^2 = t over k cells (heights y relative to a reference [m], variances p
    [m^2]): Q(t) = sum w (y - m)^2 and D = sum w^2 (y - m)^2 = -dQ/dt, w = 1 / (p + t) (kept in the
    buffer w), in two passes (the mean first) so that Q keeps its precision where w reaches 1e6."""
    s1 = 0.0
    sy = 0.0
    for q in range(k):
        wq = 1.0 / (p[q] + t)
        w[q] = wq
        s1 += wq
        sy += wq * y[q]
    m = sy / s1
    qq = 0.0
    dd = 0.0
    for q in range(k):
        d = y[q] - m
        e = w[q] * d * d
        qq += e
        dd += w[q] * e
    return qq, dd


@njit(**JIT)
def _paule_mandel(y, p, k, t0, w, lo=0.0, hi=np.inf, steps=PM_MAX_STEPS):
    """Paule-Mandel tau^2 [m^2] of k cells: the root of Q(t) = sum w (y - m)^2 = k - 1, w = 1 / (p + t),
    from t0 (the cell's last root, else the DerSimonian-Laird value) by Newton's method on
    1 / Q(t) = 1 / (k - 1), which is linear in t when the p are equal (one step then;
    t += Q (Q - (k - 1)) / ((k - 1) D)), kept inside a bracket [lo, hi] (known to hold the root) that it
    bisects when a step leaves it. Q decreases in t; the caller ensures Q(0) > k - 1, so the root is
    positive. Converged when |Q - (k - 1)| <= PM_TOL (k - 1), the bracket is below 1e-12 of t, or after a
    Newton step (inside the bracket) below PM_STEP_TOL t, which is taken (at most ``steps`` evaluations)."""
    t = t0
    km1 = k - 1.0
    for _ in range(steps):
        qq, dd = _paule_mandel_step(y, p, k, t, w)
        t, lo, hi, done = _paule_mandel_next(qq, dd, km1, t, lo, hi)
        if done:
            break
    return t


@njit(inline="always", **JIT)
def _paule_mandel_next(qq, dd, km1, t, lo, hi):
    """One safeguarded Newton step of :func:`_paule_mandel` from Q(t) = qq, -dQ/dt = dd: returns the next
    t, the new bracket and whether the solve has converged (t is then the root)."""
    f = qq - km1
    if abs(f) <= PM_TOL * km1:
        return t, lo, hi, True
    if f > 0.0:
        lo = t
    else:
        hi = t
    if hi - lo <= 1e-12 * t:
        return t, lo, hi, True
    tn = t + qq * f / (km1 * dd) if dd > 0.0 else np.inf
    if not (tn > lo and tn < hi):
        tn = 0.5 * (lo + hi) if hi < np.inf else 2.0 * t
    elif abs(tn - t) <= PM_STEP_TOL * t:
        return tn, lo, hi, True               # a converged Newton step
    return tn, lo, hi, False


@njit(**JIT)
def _paule_mandel_cell(Hl, Pl, ii, c, r, t0, hw, pw, ww, lo, hi, steps):
    """Gather the counting cells of the window whose top-left is (ii, c) in the padded copies Hl, Pl
    (heights relative to the reference, P; P = inf where a cell does not count) into hw, pw (branch
    free: every cell is written, the next one overwrites it if it does not count) and return their
    Paule-Mandel tau^2, started at t0 inside the bracket [lo, hi], in at most ``steps`` evaluations."""
    k = 0
    for a in range(ii, ii + 2 * r + 1):
        for b in range(c, c + 2 * r + 1):
            hw[k] = Hl[a, b]
            pw[k] = Pl[a, b]
            k += Pl[a, b] < np.inf
    return _paule_mandel(hw, pw, k, t0, ww, lo, hi, steps)


#: Cells whose first Paule-Mandel evaluation runs side by side (one block of a row at a time).
PM_BLOCK = 64


@njit(**JIT)
def _pm_sums(Hl, Pl, ii, b0, nb, r, t, cen, s):
    """The sums of :func:`_paule_mandel_row` for the nb cells from column b0, heights taken relative to each
    cell's centre cen (w = 1 / (P + t), y = h - cen): s[0] = sum w, s[1] = sum w y, s[2] = sum w y^2,
    s[3] = sum w^2, s[4] = sum w^2 y, s[5] = sum w^2 y^2. Each inner loop reads and writes few arrays,
    through slices, so that the compiler vectorises it."""
    L = 2 * r + 1
    tb = t[b0:b0 + nb]
    cb = cen[b0:b0 + nb]
    s0 = s[0]
    s1 = s[1]
    s2 = s[2]
    s3 = s[3]
    s4 = s[4]
    s5 = s[5]
    for c in range(nb):
        s0[c] = 0.0
        s1[c] = 0.0
        s2[c] = 0.0
        s3[c] = 0.0
        s4[c] = 0.0
        s5[c] = 0.0
    for a in range(L):
        prow = Pl[ii + a, b0:]
        hrow = Hl[ii + a, b0:]
        for b in range(L):
            pr = prow[b:]
            hr = hrow[b:]
            for c in range(nb):
                w = 1.0 / (pr[c] + tb[c])
                y = hr[c] - cb[c]
                wy = w * y
                ww = w * w
                s0[c] += w
                s1[c] += wy
                s2[c] += wy * y
                s3[c] += ww
                s4[c] += ww * y
                s5[c] += ww * y * y


@njit(**JIT)
def _paule_mandel_row(Hl, Pl, ii, c0, c1, r, t, cen, qq, dd, s):
    """The first evaluation of Q and D (:func:`_paule_mandel_step`) for the cells c0..c1-1 of one row at once,
    each at its own t[c]: the windows of neighbouring cells are neighbouring columns of the padded copies
    Hl, Pl (top-left row ii), so each window offset is one contiguous loop over the cells, which the compiler
    vectorises (a cell that does not count has P = inf, so w = 0 and it adds exact zeros). One pass: with
    y = h - cen and the mean m = cen + sum w y / sum w,

        Q = sum w y^2 - (sum w y)^2 / sum w,   D = sum w^2 y^2 - 2 (m - cen) sum w^2 y + (m - cen)^2 sum w^2,

    which keep their precision because cen, the window's DerSimonian-Laird mean, lies near m (both are
    weighted means of the same heights). Each cell's sums run over its window in row order, one offset
    after the other, whatever the block. Results go to qq[c], dd[c]; ``s`` has 6 rows of PM_BLOCK."""
    for b0 in range(c0, c1, PM_BLOCK):
        nb = min(PM_BLOCK, c1 - b0)
        _pm_sums(Hl, Pl, ii, b0, nb, r, t, cen, s)
        for c in range(nb):
            mc = s[1, c] / s[0, c]
            qq[b0 + c] = s[2, c] - mc * s[1, c]
            dd[b0 + c] = s[5, c] - 2.0 * mc * s[4, c] + mc * mc * s[3, c]


@njit(parallel=True, **JIT)
def _neighbour_kernel(data, sx, sy, i0, i1, j0, j1, radius, ref, paule_mandel, T):
    """Map rows i0..i1, columns j0..j1 (inclusive, map index); buffer start (sx, sy); heights taken
    relative to ref [m]. The window sums are separable: along each row first (pass A, over the rows the
    windows reach), then down the columns (pass B); rows and columns beyond the map are zero padding.
    Paule-Mandel's first evaluation runs for a row's cells side by side (:func:`_paule_mandel_row`); the
    few cells it does not settle continue one by one. Each cell writes only itself (pass B reads only A,
    pass A's copies of the heights and P, and its own layers): race-free, and the same whatever the thread
    count. Rows are shared among the T threads interleaved (thread m takes rows m, m + T, ...: see
    :func:`interleaved`), each thread with its own scratch rows.

    Only the span of each row between its first and last counting cell is summed (pass A: the columns
    whose windows reach the span; pass B: the span of the row's own cells, the only ones it writes): the
    frame's cells fill a camera's view, a trapezoid that covers a fraction of its bounding box. The sums
    left out are sums of zeros, so the result is the same as over the whole box, bit for bit (a sum that
    starts at +0 and adds +0 stays the same). The loops that the compiler vectorises run over slices from
    index 0."""
    n = data.shape[1]
    r = radius
    C = j1 - j0 + 1
    W = C + 2 * r                            # padded columns: map columns j0 - r .. j1 + r
    R = i1 - i0 + 1 + 2 * r                  # padded rows of A: map rows i0 - r .. i1 + r
    A = np.empty((5, R, C))                  # each row set to zero by the thread that sums it
    Hl = np.empty((R, W))                    # the heights and P of the padded window, read by the
    Pl = np.empty((R, W))                    # Paule-Mandel solve (P = inf: the cell does not count)
    span = np.empty((R, 2), dtype=np.int64)  # each padded row's first and last counting column (first > last: none)
    for m in prange(T):
        q = np.zeros((5, W))
        for ii in range(m, R, T):
            span[ii, 0] = W
            span[ii, 1] = -1
            for f in range(5):
                Af = A[f, ii]
                for c in range(C):
                    Af[c] = 0.0
            hrow = Hl[ii]
            prow = Pl[ii]
            for c in range(W):
                hrow[c] = 0.0
                prow[c] = np.inf
            i = i0 - r + ii
            if i < 0 or i >= n:
                continue                     # beyond the map: zero
            bi = i + sx
            if bi >= n:
                bi -= n
            lo = W
            hi = -1
            for c in range(W):
                j = j0 - r + c
                if j < 0 or j >= n:
                    continue
                bj = j + sy
                if bj >= n:
                    bj -= n
                h, p, _ = _cell(data, bi, bj)
                if np.isnan(h) or not (p > 0.0 and p < np.inf):
                    continue
                w = 1.0 / p
                d = h - ref
                q[0, c] = w
                q[1, c] = w * w
                q[2, c] = w * d
                q[3, c] = w * d * d
                q[4, c] = 1.0
                Hl[ii, c] = d
                Pl[ii, c] = p
                lo = min(lo, c)
                hi = c
            span[ii, 0] = lo
            span[ii, 1] = hi
            if hi < 0:
                continue
            ca = max(lo - 2 * r, 0)          # the columns whose windows reach the span
            cb = min(hi, C - 1)
            for f in range(5):
                Af = A[f, ii, ca:cb + 1]
                for t in range(2 * r + 1):
                    qf = q[f, ca + t:cb + 1 + t]
                    for c in range(cb + 1 - ca):
                        Af[c] += qf[c]
                qf = q[f, lo:hi + 1]         # zero again for the thread's next row
                for c in range(hi + 1 - lo):
                    qf[c] = 0.0
    L = 2 * r + 1
    NR = i1 - i0 + 1
    for m in prange(T):
        B = np.zeros((5, C))
        hw = np.empty(L * L)
        pw = np.empty(L * L)
        ww = np.empty(L * L)
        t0 = np.ones(C)                      # where each cell's solve starts (1: not solved, a dummy)
        solve = np.zeros(C, dtype=np.bool_)
        qq = np.empty(C)
        dd = np.empty(C)
        cen = np.zeros(C)                    # each cell's centre for the one-pass sums: its window's mean
        buf = np.empty((6, PM_BLOCK))
        for qi in range(m, NR, T):
            i = i0 + qi
            bi = i + sx
            if bi >= n:
                bi -= n
            ca = max(span[qi + r, 0] - r, 0)     # the row's counting cells (unpadded columns)
            cb = min(span[qi + r, 1] - r, C - 1)
            if ca > cb:
                continue
            for t in range(L):
                for f in range(5):
                    Bf = B[f, ca:cb + 1]
                    Af = A[f, qi + t, ca:cb + 1]
                    for c in range(cb + 1 - ca):
                        Bf[c] += Af[c]
            c0 = C
            c1 = 0
            for c in range(ca, cb + 1):
                bj = j0 + c + sy
                if bj >= n:
                    bj -= n
                h0, p0, s = _cell(data, bi, bj)
                if np.isnan(h0) or not (p0 > 0.0 and p0 < np.inf):
                    continue
                s1 = B[0, c]
                s2 = B[1, c]
                sh = B[2, c]
                shh = B[3, c]
                k = B[4, c]
                tau2 = 0.0
                if k >= 2.0:
                    qd = shh - sh * sh / s1
                    den = s1 - s2 / s1
                    if den > 0.0 and qd > k - 1.0:
                        tau2 = _dersimonian_laird_tau2(qd - (k - 1.0), s1, s2)
                        if paule_mandel:
                            prev = data[NEIGHBOUR_SPREAD, bi, bj]        # the last frame's root: a warm start
                            t0[c] = prev if (prev > 0.0 and prev < np.inf) else tau2
                            solve[c] = True
                            c0 = min(c0, c)
                            c1 = c + 1
                if not solve[c]:
                    data[NEIGHBOUR_SPREAD, bi, bj] = tau2
                    data[VARIANCE, bi, bj] = p0 + max(s, tau2)
            if c0 < c1:
                for c in range(c0, c1):
                    if solve[c]:
                        cen[c] = B[2, c] / B[0, c]
                _paule_mandel_row(Hl, Pl, qi, c0, c1, r, t0, cen, qq, dd, buf)
                for c in range(c0, c1):
                    if not solve[c]:
                        continue
                    bj = j0 + c + sy
                    if bj >= n:
                        bj -= n
                    h0, p0, s = _cell(data, bi, bj)
                    tau2, lo, hi, done = _paule_mandel_next(qq[c], dd[c], B[4, c] - 1.0, t0[c], 0.0, np.inf)
                    if not done:
                        tau2 = _paule_mandel_cell(Hl, Pl, qi, c, r, tau2, hw, pw, ww, lo, hi, PM_MAX_STEPS - 1)
                    data[NEIGHBOUR_SPREAD, bi, bj] = tau2
                    data[VARIANCE, bi, bj] = p0 + max(s, tau2)
                for c in range(c0, c1):      # back to the dummies for the thread's next row
                    solve[c] = False
                    t0[c] = 1.0
                    cen[c] = 0.0
            for f in range(5):
                Bf = B[f, ca:cb + 1]
                for c in range(cb + 1 - ca):
                    Bf[c] = 0.0


def _window(geometry, rows, cols, radius):
    n = geometry.n
    i0, i1 = max(int(rows[0]) - radius, 0), min(int(rows[1]) + radius, n - 1)
    j0, j1 = max(int(cols[0]) - radius, 0), min(int(cols[1]) + radius, n - 1)
    return i0, i1, j0, j1


def _check(data, geometry, rows, cols, radius, estimator):
    n = geometry.n
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {ESTIMATORS}, got {estimator!r}")
    if not isinstance(data, np.ndarray) or data.dtype != np.float64 or data.ndim != 3 or data.shape[1:] != (n, n):
        raise ValueError(f"data must be a float64 layer stack of shape (L, {n}, {n})")
    if isinstance(radius, bool) or not isinstance(radius, (int, np.integer)) or not 1 <= radius <= 10:
        raise ValueError(f"radius must be an integer in [1, 10] cells, got {radius!r}")
    rows = (0, n - 1) if rows is None else rows
    cols = (0, n - 1) if cols is None else cols
    for name, r in (("rows", rows), ("cols", cols)):
        if len(r) != 2 or not (0 <= int(r[0]) <= int(r[1]) <= n - 1):
            raise ValueError(f"{name} must be (first, last) map indices within [0, {n - 1}], got {r!r}")
    return rows, cols


def update_neighbour_spread(data, geometry, radius: int = 2, rows=None, cols=None, nthreads=None,
                            estimator: str = "paule_mandel") -> None:
    """Recompute ``neighbour_spread`` and ``variance`` of the known cells in a window, in place.

    Parameters
    ----------
    data : ndarray, shape (len(LAYERS), n, n)
        The map's layers (buffer order).
    geometry : GridGeometry
    radius : int
        Half-width of the neighbourhood [cells] (1 to 10).
    rows, cols : (int, int), optional
        First and last map index (inclusive) of the cells whose neighbourhoods changed (default the
        whole map); the cells within ``radius`` of them are recomputed.
    nthreads : int, optional
        numba threads.
    estimator : {"paule_mandel", "dersimonian_laird"}
        The estimator of tau_n^2 (module docstring).
    """
    rows, cols = _check(data, geometry, rows, cols, radius, estimator)
    n = resolve_threads(nthreads)
    with threads(n):
        _update_window(data, geometry, int(radius), rows, cols, n, estimator)


def _update_window(data, geometry, radius, rows, cols, n, estimator):
    """:func:`update_neighbour_spread` on checked inputs, inside the caller's ``threads(n)`` (``n`` resolved)."""
    i0, i1, j0, j1 = _window(geometry, rows, cols, radius)
    sx, sy = geometry.start_index
    sx, sy = int(sx), int(sy)
    last = geometry.n - 1
    ref = _reference_height(data, sx, sy, max(i0 - radius, 0), min(i1 + radius, last), max(j0 - radius, 0),
                            min(j1 + radius, last))
    _neighbour_kernel(data, sx, sy, i0, i1, j0, j1, radius, ref, estimator == "paule_mandel", n)


@njit(**JIT)
def _reference_height(data, sx, sy, i0, i1, j0, j1) -> float:
    """A height near the window's [m]: the mean of the known cells of every 8th row and column of map rows
    i0..i1 and columns j0..j1 (buffer start (sx, sy)), else of all its cells, 0 when none is known. Heights
    enter the sums relative to it, so that w (h - ref)^2 stays small where the map lies far above its
    origin; it looks at the window only, so that its cost follows the cells a frame touched, not the map."""
    n = data.shape[1]
    for step in (8, 1):
        s = 0.0
        k = 0
        for i in range(i0, i1 + 1, step):
            bi = i + sx
            if bi >= n:
                bi -= n
            for j in range(j0, j1 + 1, step):
                bj = j + sy
                if bj >= n:
                    bj -= n
                h = data[ELEVATION, bi, bj]
                if not np.isnan(h):
                    s += h
                    k += 1
        if k:
            return s / k
    return 0.0


def _paule_mandel_reference(y, p, cells, r, t0):
    """NumPy reference of the kernel's Paule-Mandel solve: the same safeguarded Newton steps, for all
    cells at once.

    Parameters
    ----------
    y, p : ndarray, shape (n, n)
        Heights relative to the reference [m] and fused variances [m^2] in map order (p = inf where a
        cell does not count).
    cells : ndarray of int, shape (m, 2)
        Map indices of the cells to solve (their DerSimonian-Laird tau^2 is positive).
    r : int
    t0 : ndarray, shape (m,)
        Where to start [m^2]: the cell's last root, else its DerSimonian-Laird tau^2.

    Returns
    -------
    ndarray, shape (m,) [m^2]
    """
    n = y.shape[0]
    offs = np.arange(-r, r + 1)
    a = cells[:, 0, None, None] + offs[None, :, None]            # (m, 2r+1, 1)
    b = cells[:, 1, None, None] + offs[None, None, :]            # (m, 1, 2r+1)
    inside = (a >= 0) & (a < n) & (b >= 0) & (b < n)
    ac, bc = np.clip(a, 0, n - 1), np.clip(b, 0, n - 1)
    Y = np.where(inside, y[ac, bc], 0.0).reshape(len(cells), -1)
    Pw = np.where(inside, p[ac, bc], np.inf).reshape(len(cells), -1)
    Y = np.where(np.isfinite(Pw), Y, 0.0)
    km1 = np.isfinite(Pw).sum(axis=1) - 1.0
    t = t0.astype(float).copy()
    lo = np.zeros_like(t)
    hi = np.full_like(t, np.inf)
    active = np.ones(len(t), dtype=bool)
    for _ in range(PM_MAX_STEPS):
        idx = np.flatnonzero(active)
        if not len(idx):
            break
        w = 1.0 / (Pw[idx] + t[idx, None])
        m = np.sum(w * Y[idx], axis=1) / np.sum(w, axis=1)
        e = w * (Y[idx] - m[:, None]) ** 2
        qq = np.sum(e, axis=1)
        f = qq - km1[idx]
        dd = np.sum(w * e, axis=1)
        ti = t[idx]
        done = np.abs(f) <= PM_TOL * km1[idx]
        lo_i = np.where(f > 0, ti, lo[idx])
        hi_i = np.where(f > 0, hi[idx], ti)
        done |= hi_i - lo_i <= 1e-12 * ti
        with np.errstate(divide="ignore", invalid="ignore"):
            tn = np.where(dd > 0, ti + qq * f / (km1[idx] * dd), np.inf)
        bad = ~((tn > lo_i) & (tn < hi_i))
        small = ~done & ~bad & (np.abs(tn - ti) <= PM_STEP_TOL * ti)      # a converged Newton step: taken, last
        tn = np.where(bad, np.where(np.isfinite(hi_i), 0.5 * (lo_i + hi_i), 2.0 * ti), tn)
        lo[idx], hi[idx] = lo_i, hi_i
        t[idx] = np.where(done, ti, tn)
        active[idx] = ~(done | small)
    return t


def update_neighbour_spread_reference(data, geometry, radius: int = 2, rows=None, cols=None,
                                      estimator: str = "paule_mandel") -> None:
    """NumPy reference of :func:`update_neighbour_spread`: the same separable window sums, in map order,
    and the same Paule-Mandel steps."""
    rows, cols = _check(data, geometry, rows, cols, radius, estimator)
    i0, i1, j0, j1 = _window(geometry, rows, cols, radius)
    n = geometry.n
    r = radius
    sx, sy = geometry.start_index
    ref = _reference_height(data, int(sx), int(sy), max(i0 - r, 0), min(i1 + r, n - 1), max(j0 - r, 0),
                            min(j1 + r, n - 1))
    P = geometry.unwrap(fused_variance(data))
    H = geometry.unwrap(data[ELEVATION])
    ok = ~np.isnan(H) & (P > 0) & (P < np.inf)
    w = np.where(ok, 1.0 / np.where(ok, P, 1.0), 0.0)
    d = np.where(ok, H - ref, 0.0)
    q = np.stack([w, w * w, w * d, w * d * d, ok.astype(float)])
    # the rows and columns the windows reach (zero beyond them and beyond the map), summed along the
    # rows, then down the columns, taps in the kernel's order
    a0, a1 = max(i0 - r, 0), min(i1 + r, n - 1)
    b0, b1 = max(j0 - r, 0), min(j1 + r, n - 1)
    q[:, :a0] = 0.0
    q[:, a1 + 1:] = 0.0
    q[:, :, :b0] = 0.0
    q[:, :, b1 + 1:] = 0.0
    qp = np.zeros((5, n, n + 2 * r))
    qp[:, :, r:r + n] = q
    A = np.zeros((5, n, n))
    for t in range(2 * r + 1):
        A += qp[:, :, t:t + n]
    Ap = np.zeros((5, n + 2 * r, n))
    Ap[:, r:r + n] = A
    B = np.zeros((5, n, n))
    for t in range(2 * r + 1):
        B += Ap[:, t:t + n]
    s1, s2, sh, shh, k = B
    with np.errstate(invalid="ignore", divide="ignore"):
        qq = shh - sh * sh / s1
        den = s1 - s2 / s1
        positive = (k >= 2) & (den > 0) & (qq > k - 1)
        tau2 = np.where(positive, dersimonian_laird_tau2(qq - (k - 1), s1, s2), 0.0)
    region = np.zeros((n, n), dtype=bool)
    region[i0:i1 + 1, j0:j1 + 1] = True
    if estimator == "paule_mandel":
        cells = np.argwhere(region & ok & positive)
        if len(cells):
            ci, cj = cells[:, 0], cells[:, 1]
            prev = geometry.unwrap(data[NEIGHBOUR_SPREAD])[ci, cj]          # the last root: a warm start
            t0 = np.where((prev > 0) & (prev < np.inf), prev, tau2[ci, cj])
            tau2[ci, cj] = _paule_mandel_reference(H - ref, np.where(ok, P, np.inf), cells, r, t0)
    upd = geometry.wrap(region & ok)
    tau2 = geometry.wrap(tau2)
    s = np.where(data[SPREAD] > 0, data[SPREAD], 0.0)
    Pb = geometry.wrap(P)
    data[NEIGHBOUR_SPREAD] = np.where(upd, tau2, data[NEIGHBOUR_SPREAD])
    data[VARIANCE] = np.where(upd, Pb + np.maximum(s, tau2), data[VARIANCE])
