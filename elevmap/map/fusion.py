"""Per-cell Kalman fusion of one frame of map-frame points, in information form (docs/fusion.md).

Gate: each of the frame's points is tested against its cell's prior (h, P) with the Mahalanobis
distance |z - h| / sqrt(sigma^2 + P) (threshold 2.5 by default). P is the variance of the cell's fused
mean: its ``variance`` without what the neighbourhood adds (:func:`neighbour_excess`).

Update: the accepted points are summed in information form, W = sum w_i and WZ = sum w_i z_i, and
combined once with the prior:

    P_post = 1 / (1/P + W),   h_post = P_post (h/P + WZ),

which is the sequential Kalman update without its order dependence. An unknown cell takes the
frame's weighted mean WZ / W and variance 1 / W.

Random-effects prior: where the cell's points scatter about its height more than their variances
allow (its spread tau^2 > 0, see ``spread_alpha``), each new point is weighted w_i = 1/(sigma_i^2 +
tau^2), and the prior, the mean of the n points fused so far, has variance at least tau^2 m / n with
m this frame's points in the cell: what a mean of n points that scatter by tau^2 can know when they
come m at a time and a frame's points share their error (the level an edge's lateral noise shows
them, a correlated depth error), i.e. tau^2 per frame's worth of points. Without that floor a cell
initialised by one wrong point (a far depth outlier with a small stated sigma) keeps its fixed-effect
variance against the random-effects weights of every later point and stays near the outlier through
dozens of points; with tau^2 / n (every point independent) a cell follows the mean of all its points
and lags a change by many frames.

A new point's tau^2 is the larger of the cell's spread and its neighbourhood spread
(:mod:`elevmap.map.neighbours`), as in the cell's variance: where neighbouring cells disagree (a step, a
band of points bled over an edge, the far field) a point may well belong to the neighbour's level, so
its stated sigma over-states what it says about this cell, and weights flatten there, towards an
equal-weight mean that a few points binned in the wrong cell cannot dominate.

Spread: tau^2 of a cell is the DerSimonian-Laird estimate over all the points that reached it since its
last reset, accepted by the gate or not, with their own weights 1 / sigma_i^2 (the ``info_sum``,
``info_sq_sum`` and ``scatter`` layers keep its running sums); it counts only where the scatter is
significant (``spread_alpha``) and large (``spread_ratio``).

Change: a single outlier (or a few) is ignored. When a cell's rejected points are at least
``change_min_points`` and outnumber its accepted ones, the terrain has changed (a box put down, a
step): the prior's variance is inflated by the squared distance to the rejected points' mean, so that
the next frame's points pass the gate and pull the cell over; when the inflated variance exceeds
``max_variance``, the cell is re-initialised from the rejected points at once. The inflation comes
after this frame's accepted points are fused with the prior as it was: inflating first would let the
few accepted points of a frame that looks like a change (a well-known cell reached by a handful of
too-near points, some of them inside the gate) pull the cell to them at once.

Information cap (correlated pixels): with ``max_points_per_frame = n_eff`` a frame adds at most the
information of n_eff average points to a cell (its weights are scaled by n_eff / n when n > n_eff),
because neighbouring D435 pixels share their errors and hundreds of them are not hundreds of
independent measurements.

Per-frame error of the camera's model (``frame_error = (l, r)``, from
:meth:`noise_model.SensorModel.frame_error`): a frame's error has variance r times the points' modelled
variance and a Gaussian correlation length of l pixels. The n points a frame puts in a cell are its
pixels there, taken as a square patch of side a = sqrt(n) px; with rho(h) = exp(-h^2 / (2 l^2)) separable
in rows and columns, the variance of their mean is sigma^2 rho_bar(a)^2 with rho_bar(a) the mean of
rho(|i - j|) over pairs of a row's pixels, so the patch holds

    n_eff = min(n, max(1, (W(a) / S(a))^2)),   S(a) = a + 2 sum_{1 <= k < a} (a - k) rho(k),
                                                W(a) = S(a) with rho = 1,

independent samples (:func:`effective_samples`), and the frame's sums in the cell are scaled by
n_eff / (n r), after the cap (n_eff <= ``max_points_per_frame``). l = 0 and r = 1 (a model without a
measured per-frame error: the paper's, a reference) leave the sums as they are. An elongated patch (a
grazing view) holds more independent samples than the square of its area: the rule then understates the
frame's information, the safe side.

After the update variances are clamped below at ``min_variance``; a cell whose variance exceeds
``max_variance`` becomes unknown.

Parallel accumulation is race-free: the points are cut into ``PARTIALS`` fixed contiguous ranges,
each summed into its own partial grid, and the partial grids are merged per cell in a fixed order,
so the result is the same bit for bit whatever the thread count. Partial grids are reset lazily
(a per-cell frame stamp), and the merge runs over the rows and columns the frame's points reached
only, so a frame costs work only around the cells it touches. A cell's prior (its height, the
variance the gate uses and the weight's tau^2) is read from the layers once per partial grid, when the
grid first meets the cell in a frame, and kept beside its sums.

The kernel checks each point's values in the same pass (:func:`elevmap.map.settings.check_point_values`
is its NumPy reference), as it loads them: the pass writes only the partial grids, so a frame with a bad
point leaves the map as it was, and the check costs a few comparisons per point instead of several passes
over the arrays.
:func:`elevmap.map.fusion_reference.fuse_frame_reference` computes the same update with NumPy (bincount);
the tests hold the two equal. The settings, :class:`FusionParams`, live in :mod:`elevmap.map.fusion_params`
(imported here too).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from noise_model.formulas import dersimonian_laird_tau2, reduced_chi2_quantile
from noise_model.numba_config import JIT, resolve_threads, threads

from .fusion_params import REMOVED_PARAMS, FusionParams, check_frame_error
from .neighbours import interleaved
from .settings import MAX_COORDINATE_M, MAX_POINT_VARIANCE, MIN_HEIGHT_VARIANCE, check_point_values
from .layers import (
    ELEVATION, HVAR_X, HVAR_XY, HVAR_Y, MAX_HEIGHT, MIN_HEIGHT, NEIGHBOUR_SPREAD, INFO_SQ_SUM, INFO_SUM, POINTS,
    SCATTER, SPREAD, TIME, UPPER_BOUND, VARIANCE, clear_sums,
)

__all__ = ["FusionParams", "FusionWorkspace", "fuse_frame", "touched_box", "PARTIALS", "REMOVED_PARAMS",
           "effective_samples", "check_frame_error"]

#: Number of partial grids (fixed, so that the summation order never depends on the thread count).
PARTIALS = 8
# fields per partial grid and cell: the cell's prior as the frame found it (height, the gate's variance P,
# the weight's tau^2), then the sums, those every point adds first, and the lowest ray end for the
# visibility clean-up (its height and its point's index)
(PR_H, PR_VG, PR_T2, A_W0, A_WZ0, A_WZZ0, A_WW0, A_W, A_WZ, A_N, A_ZMIN, A_ZMAX, H_X, H_XY, H_Y, R_W, R_WZ, R_N,
 R_ZMIN, R_ZMAX, LOW_Z, LOW_K) = range(22)
NACC = 22

def effective_samples(n, ell):
    """Independent samples among n pixels of a square patch whose errors have the Gaussian correlation
    length ``ell`` [px] (module docstring; NumPy, n an array of counts >= 0; ``ell`` 0: n itself).

    Lags beyond 6 l (rho < 2e-8) are left out of S(a), as in the kernel's :func:`_effective_samples`."""
    n = np.asarray(n, dtype=np.float64)
    if not ell > 0.0:
        return n.copy()
    a = np.sqrt(n)
    S = a.copy()
    W = a.copy()
    inv = 1.0 / (2.0 * ell * ell)
    kmax = int(math.ceil(float(a.max()))) if a.size else 0
    for k in range(1, kmax):
        t = np.maximum(a - k, 0.0)
        W += 2.0 * t
        if k <= 6.0 * ell:
            S += 2.0 * t * math.exp(-k * k * inv)
    with np.errstate(invalid="ignore", divide="ignore"):
        g = np.where(S > 0.0, W / S, 1.0)
    return np.where(n > 1.0, np.minimum(n, np.maximum(1.0, g * g)), n)


@njit(**JIT)
def _effective_samples(n, ell):
    """:func:`effective_samples` of one count (numba)."""
    if not ell > 0.0 or n <= 1.0:
        return n
    a = math.sqrt(n)
    S = a
    W = a
    inv = 1.0 / (2.0 * ell * ell)
    k = 1
    while k < a:
        t = a - k
        W += 2.0 * t
        if k <= 6.0 * ell:
            S += 2.0 * t * math.exp(-k * k * inv)
        k += 1
    g = W / S
    return min(n, max(1.0, g * g))


@njit(**JIT)
def _information_scale(n, cap, ell, ratio):
    """The factor on a frame's sums of n points in a cell: n_eff / (n r), n_eff = the effective samples
    (:func:`_effective_samples`) capped at ``cap`` (> 0); 1 for n = 0."""
    if n <= 0.0:
        return 1.0
    ne = _effective_samples(n, ell)
    if cap > 0.0 and ne > cap:
        ne = cap
    return ne / (n * ratio)


#: Memory of :class:`FusionWorkspace` per map cell [bytes]: PARTIALS x (NACC float64 sums + an int64 stamp).
WORKSPACE_BYTES_PER_CELL = PARTIALS * (NACC * 8 + 8)


class FusionWorkspace:
    """Partial grids of the fusion kernel, kept across frames (reset lazily by frame stamps)."""

    def __init__(self, n: int):
        self.n = int(n)
        self.acc = np.zeros((PARTIALS, self.n * self.n, NACC))
        self.stamp = np.full((PARTIALS, self.n * self.n), -1, dtype=np.int64)
        self.frame = 0
        #: per partial grid of the last frame: points that failed the check, first and last map row and column
        self.boxes = np.empty((PARTIALS, 5), dtype=np.int64)


# ---------------------------------------------------------------------------------------------
# numba
# ---------------------------------------------------------------------------------------------
#: noise_model.formulas, compiled: the DerSimonian-Laird tau^2 and the Wilson-Hilferty quantile per
#: degree of freedom.
_dersimonian_laird_tau2 = njit(**JIT)(dersimonian_laird_tau2)
_reduced_chi2_quantile = njit(**JIT)(reduced_chi2_quantile)


@njit(**JIT)
def _spread_update(data, bi, bj, known, h_prior, N, W0, WZ0, WZZ0, WW0, spread_z, ratio):
    """Add a frame's points in the cell to its spread statistics; return the new tau^2.

    N, W0, WZ0, WZZ0, WW0 are the frame's count and sums of w, w z, w z^2 and w^2 over all its points
    in the cell (accepted by the gate or not), with the points' own weights w = 1/sigma^2. The
    scatter about the cell's height is accumulated with the parallel-axis rule (the frame's own
    scatter plus its mean's distance to the prior height) and stored as its excess over its
    expectation under the noise model, Q - (n - 1); tau^2 follows the DerSimonian-Laird moment
    estimator (see the module docstring).
    """
    mb = WZ0 / W0
    qb = max(WZZ0 - WZ0 * mb, 0.0)
    s1 = data[INFO_SUM, bi, bj] if known else 0.0
    s2 = data[INFO_SQ_SUM, bi, bj] if known else 0.0
    if s1 > 0.0:
        # Q - (n - 1) grows by the frame's own Q_b, its mean's distance S1 W0 / (S1 + W0) (m_b - h)^2 and -N
        excess = data[SCATTER, bi, bj] + qb + s1 * W0 / (s1 + W0) * (mb - h_prior) * (mb - h_prior) - N
    else:
        excess = qb - (N - 1.0)
    s1 += W0
    s2 += WW0
    n = (data[POINTS, bi, bj] if known else 0.0) + N     # POINTS is updated after this call
    data[INFO_SUM, bi, bj] = s1
    data[INFO_SQ_SUM, bi, bj] = s2
    data[SCATTER, bi, bj] = excess
    return _dl_tau2(excess, n, s1, s2, spread_z, ratio)


@njit(**JIT)
def _dl_tau2(excess, n, s1, s2, spread_z, ratio):
    """DerSimonian-Laird tau^2 = (Q - (n - 1)) / (S1 - S2 / S1) from the excess Q - (n - 1), where Q is
    significant (above its 1 - spread_alpha quantile under the noise model, Wilson-Hilferty; ``spread_z``
    is the normal quantile of 1 - spread_alpha) and the points scatter more than ``ratio`` times their
    modelled variance (Q / (n - 1) > ratio); else 0."""
    if n < 2.0 or not s1 - s2 / s1 > 0.0:           # one point (or the weight of one): no spread to see
        return 0.0
    k = n - 1.0
    if not excess + k > ratio * k:                   # Q / (n - 1) > ratio
        return 0.0
    if not excess + k > _reduced_chi2_quantile(k, spread_z) * k:     # Q > chi2_{n-1, 1 - alpha}
        return 0.0
    return _dersimonian_laird_tau2(excess, s1, s2)


@njit(**JIT)
def neighbour_excess(data, bi, bj):
    """What the neighbourhood adds to a cell's variance beyond its own spread [m^2] (numba).

    The cell's variance is P + max(spread, neighbour_spread), so this is max(neighbour_spread - spread, 0)
    (NaN spreads count as 0). The gate and the prior of the fusion, and the visibility clean-up's
    threshold, work on the variance without it: the neighbourhood's disagreement says how uncertain the
    height at the cell's centre is, not how far the cell's own points may scatter.

    Parameters
    ----------
    data : ndarray, shape (len(LAYERS), n, n)
        The map's layers, buffer order.
    bi, bj : int
        Buffer index of the cell.
    """
    t = data[SPREAD, bi, bj]
    t = t if t > 0.0 else 0.0
    nb = data[NEIGHBOUR_SPREAD, bi, bj]
    return nb - t if nb > t else 0.0


@njit(**JIT)
def _weight_tau2(data, bi, bj):
    """tau^2 of a new point's weight 1 / (sigma^2 + tau^2): the larger of the cell's spread and its
    neighbourhood spread (NaN, unknown: 0), as in the cell's variance."""
    t = data[SPREAD, bi, bj]
    nb = data[NEIGHBOUR_SPREAD, bi, bj]
    return max(t if t > 0.0 else 0.0, nb if nb > 0.0 else 0.0)


@njit(**JIT)
def _merge_cell(data, bi, bj, W, WZ, N, zmin, zmax, Wr, WZr, Nr, zminr, zmaxr, Hx, Hxy, Hy, has_h, stamp,
                params, W0, WZ0, WZZ0, WW0):
    """Combine one cell's frame sums with its prior and write the cell (see the module docstring).

    W, WZ, N: sums of w, w z and the count over the frame's accepted points in the cell
    (w = 1 / (sigma^2 + tau^2)); Wr, WZr, Nr: the same over its rejected points; W0, WZ0, WZZ0, WW0:
    sums of w0, w0 z, w0 z^2, w0^2 over all its points with their own weights w0 = 1 / sigma^2 (for the
    spread); zmin .. zmaxr: their extremes; Hx, Hxy, Hy: the accepted points' weighted mean horizontal
    covariance. ``v`` below is P, the variance of the cell's fused mean.
    """
    min_var, max_var, min_h, max_h, change_min, cap = params[1], params[2], params[3], params[4], params[5], params[6]
    spread_z = params[7]
    ratio = params[8]
    ell, fratio = params[9], params[10]
    h = data[ELEVATION, bi, bj]
    known = not np.isnan(h)
    tau2 = data[SPREAD, bi, bj]
    if not tau2 >= 0.0:                # NaN (unknown cell)
        tau2 = 0.0
    h_prior = h
    # P = variance - spread - neighbour excess = variance - max(spread, neighbour_spread)
    v = data[VARIANCE, bi, bj] - tau2 - neighbour_excess(data, bi, bj)
    if known and tau2 > 0.0 and data[POINTS, bi, bj] > 0.0:
        # random-effects prior: a mean of n points that scatter by tau^2, m at a time: P >= tau^2 m / n
        v = max(v, tau2 * max(N + Nr, 1.0) / data[POINTS, bi, bj])
    # information cap and the frame's error: W, WZ *= n_eff / (N r), n_eff = min(effective samples, cap)
    if cap > 0.0 or ell > 0.0 or fratio != 1.0:
        s = _information_scale(N, cap, ell, fratio)
        if s != 1.0:
            W *= s
            WZ *= s
        s = _information_scale(Nr, cap, ell, fratio)
        if s != 1.0:
            Wr *= s
            WZr *= s
    reset = False
    updated = False
    changed = known and Nr >= change_min and Nr > N
    inflation = 0.0
    if changed:
        # change: P += (m_r - h)^2 with m_r = WZr / Wr the rejected points' mean, after this frame's fusion;
        # beyond max_variance the cell restarts from the rejected points: h = m_r, P = 1 / Wr
        mr = WZr / Wr
        inflation = (mr - h) * (mr - h)
        if v + inflation > max_var:
            reset = True
            h = mr
            v = 1.0 / Wr
            data[MIN_HEIGHT, bi, bj] = zminr
            data[MAX_HEIGHT, bi, bj] = zmaxr
            data[POINTS, bi, bj] = Nr
            data[HVAR_X, bi, bj] = min_h
            data[HVAR_Y, bi, bj] = min_h
            data[HVAR_XY, bi, bj] = 0.0
            data[UPPER_BOUND, bi, bj] = np.nan
            data[TIME, bi, bj] = stamp
            tau2 = 0.0                         # the spread statistics start again from this frame's points
            if spread_z >= 0.0:
                tau2 = _spread_update(data, bi, bj, False, h, N + Nr, W0, WZ0, WZZ0, WW0, spread_z, ratio)
            else:
                clear_sums(data, bi, bj)
                data[POINTS, bi, bj] = Nr
            updated = True
    if not reset and N > 0.0:
        if spread_z >= 0.0:
            tau2 = _spread_update(data, bi, bj, known, h_prior, N + Nr, W0, WZ0, WZZ0, WW0, spread_z, ratio)
        if known:
            # P_post = 1 / (1/P + W);  h_post = P_post (h/P + WZ)
            ip = 1.0 / v
            v = 1.0 / (ip + W)
            h = (ip * h + WZ) * v
            data[MIN_HEIGHT, bi, bj] = min(data[MIN_HEIGHT, bi, bj], zmin)
            data[MAX_HEIGHT, bi, bj] = max(data[MAX_HEIGHT, bi, bj], zmax)
            data[POINTS, bi, bj] += N
        else:
            # an unknown cell: the frame's weighted mean, P = 1 / W;  h = WZ / W
            v = 1.0 / W
            h = WZ * v
            data[MIN_HEIGHT, bi, bj] = zmin
            data[MAX_HEIGHT, bi, bj] = zmax
            data[POINTS, bi, bj] = N
            data[UPPER_BOUND, bi, bj] = np.nan
        hx, hxy, hy = min_h, 0.0, min_h
        if has_h:
            hx = min(max(Hx, min_h), max_h)
            hy = min(max(Hy, min_h), max_h)
            hxy = Hxy
        data[HVAR_X, bi, bj] = hx
        data[HVAR_Y, bi, bj] = hy
        data[HVAR_XY, bi, bj] = hxy
        data[TIME, bi, bj] = stamp
        updated = True
    if changed and not reset:
        v += inflation
    if not updated and not changed:       # only a few rejected points: the cell stays as it was
        return
    # clamp: P >= min_variance; P > max_variance -> unknown
    v = max(v, min_var)
    if v > max_var:
        for layer in range(data.shape[0]):
            data[layer, bi, bj] = np.nan
        clear_sums(data, bi, bj)
        return
    nb = data[NEIGHBOUR_SPREAD, bi, bj]
    nb = nb if (known and not reset and nb > 0.0) else 0.0    # a new or re-initialised cell: none yet
    # variance = P + max(spread, neighbour_spread)
    data[ELEVATION, bi, bj] = h
    data[VARIANCE, bi, bj] = v + max(tau2, nb)
    data[SPREAD, bi, bj] = tau2
    data[NEIGHBOUR_SPREAD, bi, bj] = nb
    ub = data[UPPER_BOUND, bi, bj]
    if ub < h:                     # the terrain rose above an old free-space bound: the bound is stale
        data[UPPER_BOUND, bi, bj] = np.nan


@njit(inline="always", **JIT)
def _open_cell(data, acc, acc_stamp, p, c, bi, bj, fid):
    """Make partial grid p's entry of cell c (buffer index bi, bj) current for frame ``fid``: on its first
    point of the frame, zero its sums and read the cell's prior (height, the gate's variance, the weight's
    tau^2) from the layers once."""
    if acc_stamp[p, c] != fid:
        acc_stamp[p, c] = fid
        a = acc[p, c]
        for f in range(NACC):
            a[f] = 0.0
        a[A_ZMIN] = np.inf
        a[R_ZMIN] = np.inf
        a[A_ZMAX] = -np.inf
        a[R_ZMAX] = -np.inf
        a[LOW_Z] = np.inf
        a[LOW_K] = -1.0
        a[PR_H] = data[ELEVATION, bi, bj]
        a[PR_VG] = data[VARIANCE, bi, bj] - neighbour_excess(data, bi, bj)
        a[PR_T2] = _weight_tau2(data, bi, bj)


#: Horizontal covariances checked at a time, just before the pass sums their points (a block's values are then in
#: the cache).
CHECK_BLOCK = 256


@njit(**JIT)
def _count_bad_hcov(hx, hxy, hy, k0, k1):
    """Number of the points k0..k1-1 whose horizontal covariance fails the check: finite, with xx, yy >= 0
    (NaN fails every comparison). A loop without branches (& rather than and), which the compiler vectorises."""
    inf = np.inf
    bad = 0
    for k in range(k0, k1):
        h0 = hx[k]
        h2 = hy[k]
        ok = (h0 >= 0.0) & (h0 < inf) & (h2 >= 0.0) & (h2 < inf) & (abs(hxy[k]) < inf)
        bad += not ok
    return bad


@njit(parallel=True, **JIT)
def _accumulate_kernel(data, gx0, gy0, res, x, y, z, var, hx, hxy, hy, has_h, params, acc, acc_stamp, fid, check, box,
                       low_margin, T):
    """Pass 1, per partial grid over its fixed range of points: check the points' values (``check``), gate
    each point against its cell's prior and sum it into the cell's partial grid. Writes only ``acc``,
    ``acc_stamp`` and ``box`` (per partial: points that failed the check, first and last map row and column
    reached): a point that fails the check is summed too (its sums are garbage), and the caller then raises
    before anything reaches the map. With ``low_margin`` >= 0 it also keeps each cell's lowest ray end for the
    visibility clean-up: the least z + low_margin sigma, ties to the smaller point index.

    Consecutive points of a depth image mostly fall in the same cell: a run of points in one cell is
    summed in registers and added to the partial grid when the run ends (the order of the additions is
    fixed by the points' order, so the result does not depend on the thread count), and a point well
    inside the previous point's cell skips the divisions of floor(x / res) (the same cell, exactly).
    The partial grids are dealt to the T threads interleaved (:func:`elevmap.map.neighbours.interleaved`):
    a depth image's far rows come first and cost more per point (shorter runs).

    The check (:func:`elevmap.map.settings.check_point_values`: coordinates within MAX_COORDINATE_M,
    MIN_HEIGHT_VARIANCE <= v <= MAX_POINT_VARIANCE, horizontal covariance finite with xx, yy >= 0) costs a
    few branch-free comparisons per point on values the pass loads anyway: z and v of every point; x and y
    only of the points outside the window, because a point inside it lies within the window's bounds, which
    are within MAX_COORDINATE_M unless the map lies at its edge (then every point's x and y are compared).
    NaN fails every comparison. The horizontal covariances are checked a block of CHECK_BLOCK points at a
    time, just before the pass sums them."""
    n = data.shape[1]
    P = acc.shape[0]
    N = x.shape[0]
    thr2 = params[0] * params[0]
    sx = gx0 % n
    sy = gy0 % n
    inf = np.inf
    big = MAX_COORDINATE_M
    # a point whose cell lies in the window has |x|, |y| below the window's farthest edge (one cell of
    # margin for the rounding of x / res); within MAX_COORDINATE_M, the check need not compare them
    edge = (max(abs(gx0), abs(gx0 + n), abs(gy0), abs(gy0 + n)) + 1.0) * res * (1.0 + 1e-9)
    check_xy = check and not edge <= big
    check_h = check and has_h
    for qp in prange(P):
        p = interleaved(qp, P, T)
        a0 = b0 = n
        a1 = b1 = -1
        nbad = 0
        cur = -1
        h = vg = t2 = 0.0
        w0s = wz0s = wzz0s = ww0s = ws = wzs = ns = hxs = hxys = hys = rws = rwzs = rns = 0.0
        zmn = rzmn = lowz = inf
        zmx = rzmx = -inf
        lowk = -1.0
        xk = yk = zk = vk = 0.0
        i = j = bi = bj = c = 0
        cx0 = cx1 = cy0 = cy1 = 0.0            # the current cell's interior (empty: none yet)
        end = (N * (p + 1)) // P
        next_check = 0
        for k in range((N * p) // P, end + 1):
            last = k == end
            if not last:
                if check_h and k >= next_check:
                    next_check = min(k + CHECK_BLOCK, end)
                    nbad += _count_bad_hcov(hx, hxy, hy, k, next_check)
                xk = x[k]
                yk = y[k]
                zk = z[k]
                vk = var[k]
                if check:
                    nbad += not ((abs(zk) <= big) & (vk >= MIN_HEIGHT_VARIANCE) & (vk <= MAX_POINT_VARIANCE))
                    if check_xy:
                        nbad += not ((abs(xk) <= big) & (abs(yk) <= big))
                # the cell of the previous point when this one lies inside that cell's interior shrunk by a
                # relative 1e-9 (floor(x / res) cannot round across a border there: the division's rounding
                # error is ~1e-16 of x / res); else floor(x / res) as everywhere else in the map
                if not (xk >= cx0 and xk < cx1 and yk >= cy0 and yk < cy1):
                    fi = math.floor(xk / res) - gx0
                    fj = math.floor(yk / res) - gy0
                    if not (fi >= 0.0 and fi < n and fj >= 0.0 and fj < n):
                        if check and not check_xy:      # outside the window (NaN and inf land here too)
                            nbad += not ((abs(xk) <= big) & (abs(yk) <= big))
                        continue
                    i = int(fi)
                    j = int(fj)
                    bi = i + sx
                    if bi >= n:
                        bi -= n
                    bj = j + sy
                    if bj >= n:
                        bj -= n
                    c = bi * n + bj
                    gx = float(i + gx0)
                    gy = float(j + gy0)
                    mx = 1e-9 * max(abs(gx), abs(gx + 1.0), 1.0) * res
                    my = 1e-9 * max(abs(gy), abs(gy + 1.0), 1.0) * res
                    cx0 = gx * res + mx
                    cx1 = (gx + 1.0) * res - mx
                    cy0 = gy * res + my
                    cy1 = (gy + 1.0) * res - my
            if last or c != cur:
                if cur >= 0:                         # the run in cell cur ends: add it to the partial grid
                    a = acc[p, cur]
                    a[A_W0] += w0s
                    a[A_WZ0] += wz0s
                    a[A_WZZ0] += wzz0s
                    a[A_WW0] += ww0s
                    a[A_W] += ws
                    a[A_WZ] += wzs
                    a[A_N] += ns
                    a[A_ZMIN] = min(a[A_ZMIN], zmn)
                    a[A_ZMAX] = max(a[A_ZMAX], zmx)
                    a[H_X] += hxs
                    a[H_XY] += hxys
                    a[H_Y] += hys
                    a[R_W] += rws
                    a[R_WZ] += rwzs
                    a[R_N] += rns
                    a[R_ZMIN] = min(a[R_ZMIN], rzmn)
                    a[R_ZMAX] = max(a[R_ZMAX], rzmx)
                    if lowz < a[LOW_Z]:                  # earlier points have smaller indices: ties keep them
                        a[LOW_Z] = lowz
                        a[LOW_K] = lowk
                if last:
                    break
                a0 = min(a0, i)
                a1 = max(a1, i)
                b0 = min(b0, j)
                b1 = max(b1, j)
                _open_cell(data, acc, acc_stamp, p, c, bi, bj, fid)
                cur = c
                h = acc[p, c, PR_H]
                vg = acc[p, c, PR_VG]
                t2 = acc[p, c, PR_T2]
                w0s = wz0s = wzz0s = ww0s = ws = wzs = ns = hxs = hxys = hys = rws = rwzs = rns = 0.0
                zmn = rzmn = lowz = inf
                zmx = rzmx = -inf
                lowk = -1.0
            if low_margin >= 0.0 and zk < lowz:          # the ray's end is at z or above it
                ze = zk + low_margin * math.sqrt(vk) if low_margin > 0.0 else zk
                if ze < lowz:                            # k increases: ties keep the smaller index
                    lowz = ze
                    lowk = k
            w0 = 1.0 / vk
            w = 1.0 / (vk + t2) if t2 > 0.0 else w0     # unknown cell: its own weight
            d = zk - h
            w0s += w0          # every point, accepted or not, for the spread
            wz0s += w0 * zk
            wzz0s += w0 * zk * zk
            ww0s += w0 * w0
            if (not np.isnan(h)) and d * d > thr2 * (vk + vg):
                rws += w
                rwzs += w * zk
                rns += 1.0
                rzmn = min(rzmn, zk)
                rzmx = max(rzmx, zk)
            else:
                ws += w
                wzs += w * zk
                ns += 1.0
                zmn = min(zmn, zk)
                zmx = max(zmx, zk)
                if has_h:
                    hxs += w * hx[k]
                    hxys += w * hxy[k]
                    hys += w * hy[k]
        box[p, 0] = nbad
        box[p, 1] = a0
        box[p, 2] = a1
        box[p, 3] = b0
        box[p, 4] = b1


@njit(parallel=True, **JIT)
def _merge_kernel(data, sx, sy, has_h, stamp, params, acc, acc_stamp, fid, pbox, i0, i1, T):
    """Pass 2, per map row of the touched rows i0..i1 (buffer start (sx, sy)): merge each cell's partial grids
    in their fixed order and write the cell (:func:`_merge_cell`). ``pbox`` holds each partial grid's first
    and last map row and column reached (columns 1-4, as pass 1 writes them): a row visits only the partial
    grids whose rows hold it, over the columns they reach. Rows are shared among the T threads interleaved
    (thread tm takes rows tm, tm + T, ...: :func:`elevmap.map.neighbours.interleaved`), each thread with its
    own scratch. Returns the cells touched."""
    n = data.shape[1]
    P = acc.shape[0]
    inf = np.inf
    touched = 0
    for tm in prange(T):                         # thread tm: rows i0 + tm, i0 + tm + T, ...
        ps = np.empty(P, dtype=np.int64)         # the partial grids that reached row i, in their order
        for qi in range(tm, i1 - i0 + 1, T):
            i = i0 + qi
            bi = i + sx
            if bi >= n:
                bi -= n
            npart = 0
            ja = n
            jb = -1
            for p in range(P):
                if pbox[p, 1] <= i and i <= pbox[p, 2]:
                    ps[npart] = p
                    npart += 1
                    ja = min(ja, pbox[p, 3])
                    jb = max(jb, pbox[p, 4])
            for j in range(ja, jb + 1):
                bj = j + sy
                if bj >= n:
                    bj -= n
                c = bi * n + bj
                W = WZ = Nn = Wr = WZr = Nr = Hx = Hxy = Hy = W0 = WZ0 = WZZ0 = WW0 = 0.0
                zmin = zminr = inf
                zmax = zmaxr = -inf
                seen = False
                for m in range(npart):
                    p = ps[m]
                    if acc_stamp[p, c] == fid:
                        seen = True
                        a = acc[p, c]
                        W += a[A_W]
                        WZ += a[A_WZ]
                        W0 += a[A_W0]
                        WZ0 += a[A_WZ0]
                        WZZ0 += a[A_WZZ0]
                        WW0 += a[A_WW0]
                        Nn += a[A_N]
                        zmin = min(zmin, a[A_ZMIN])
                        zmax = max(zmax, a[A_ZMAX])
                        Wr += a[R_W]
                        WZr += a[R_WZ]
                        Nr += a[R_N]
                        zminr = min(zminr, a[R_ZMIN])
                        zmaxr = max(zmaxr, a[R_ZMAX])
                        Hx += a[H_X]
                        Hxy += a[H_XY]
                        Hy += a[H_Y]
                if not seen:
                    continue
                touched += 1
                if W > 0.0:
                    Hx /= W
                    Hxy /= W
                    Hy /= W
                _merge_cell(data, bi, bj, W, WZ, Nn, zmin, zmax, Wr, WZr, Nr, zminr, zmaxr, Hx, Hxy, Hy, has_h,
                            stamp, params, W0, WZ0, WZZ0, WW0)
    return touched


# ---------------------------------------------------------------------------------------------
# public entries
# ---------------------------------------------------------------------------------------------
def fuse_frame(data, geometry, points_map, height_var, horizontal_cov, stamp, params: FusionParams,
               workspace: FusionWorkspace, nthreads=None, low_margin=None, check=True,
               frame_error=None) -> tuple[int, tuple | None]:
    """Fuse one frame into ``data`` (len(LAYERS), n, n) in place (numba).

    Parameters
    ----------
    data : ndarray, shape (len(LAYERS), n, n)
        The map's layers, buffer order.
    geometry : elevmap.map.grid.GridGeometry
    points_map : ndarray, shape (N, 3), float64
        Map-frame points [m], any memory layout (shape and dtype checked by the caller).
    height_var : ndarray, shape (N,), float64
        Height variance of each point [m^2].
    horizontal_cov : ndarray, shape (N, 3), float64, or None
        (Sigma_xx, Sigma_xy, Sigma_yy) of each point [m^2].
    stamp : float
        Time of the frame [s], finite.
    params : FusionParams
    workspace : FusionWorkspace
    nthreads : int, optional
    low_margin : float, optional
        Also keep each cell's lowest ray end, z + low_margin sigma, in the workspace for the visibility
        clean-up (:func:`elevmap.map.visibility.visibility_cleanup_fused`).
    check : bool
        Check each point's values (default). False only for points whose producer has counted, as it wrote
        them, that none is out of range (:attr:`noise_model.MapPoints.n_outside` == 0): the check is the
        largest single part of the pass, and an unchecked bad value would reach the map.
    frame_error : (float, float), optional
        The frame's error correlation length [px] and variance ratio (module docstring); None: none.

    Returns
    -------
    touched : int
        Cells that received points.
    box : (i0, i1, j0, j1) or None
        First and last map row and column of those cells (None: none).

    Raises
    ------
    ValueError
        A point's values are out of range (:func:`elevmap.map.settings.check_point_values` names it); the
        map is then unchanged.
    """
    n = resolve_threads(nthreads)
    with threads(n):
        return fuse_frame_in_threads(data, geometry, points_map, height_var, horizontal_cov, stamp, params,
                                     workspace, n, low_margin, check, frame_error)


def fuse_frame_in_threads(data, geometry, points_map, height_var, horizontal_cov, stamp, params, workspace, n,
                          low_margin, check, frame_error):
    """:func:`fuse_frame` for a caller that has already set numba's threads (``with threads(n)``, ``n`` the
    resolved count, passed in for the merge kernel): :class:`elevmap.map.elevation_map.ElevationMap`'s update
    sets them once for all its kernels, since every change of numba's thread setting costs a call. The
    arguments are :func:`fuse_frame`'s, checked by the caller."""
    has_h = horizontal_cov is not None
    pa = params.array(geometry.resolution_m, frame_error)
    box = accumulate(data, geometry, points_map, height_var, horizontal_cov, pa, workspace, check=check,
                     low_margin=low_margin)
    if box is None:
        return 0, None
    sx, sy = geometry.start_index
    touched = _merge_kernel(data, int(sx), int(sy), has_h, float(stamp), pa, workspace.acc, workspace.stamp,
                            workspace.frame, workspace.boxes, box[0], box[1], n)
    return int(touched), box


def accumulate(data, geometry, points_map, height_var, horizontal_cov, packed_params, workspace, check=True,
               low_margin=None):
    """The fusion's first pass alone (numba, the caller's thread setting): check the points, gate them and
    sum them into the workspace's partial grids for a new frame (and the lowest ray ends with
    ``low_margin``, see :func:`fuse_frame`). ``data`` is not changed. Returns the touched cells' first and
    last map row and column (i0, i1, j0, j1), or None; a ValueError naming the problem when a point fails
    the check (``check=False`` skips it: for points counted in range by their producer, see
    :func:`fuse_frame`, and for timing the check apart)."""
    has_h = horizontal_cov is not None
    h = horizontal_cov if has_h else np.zeros((1, 3))
    workspace.frame += 1
    box = workspace.boxes
    _accumulate_kernel(data, geometry.gx0, geometry.gy0, geometry.resolution_m, points_map[:, 0], points_map[:, 1],
                       points_map[:, 2], height_var, h[:, 0], h[:, 1], h[:, 2], has_h, packed_params, workspace.acc,
                       workspace.stamp, workspace.frame, bool(check), box, -1.0 if low_margin is None else float(low_margin),
                       numba.get_num_threads())
    bad, i0, i1, j0, j1 = zip(*box.tolist())         # per partial grid (a few Python ints: cheaper than NumPy)
    if sum(bad) > 0:
        check_point_values(points_map, height_var, horizontal_cov)
        raise ValueError("points_map, height_var or horizontal_cov hold values out of range")   # not reached
    if max(i1) < 0:
        return None
    return min(i0), max(i1), min(j0), max(j1)


def touched_box(geometry, points_map) -> tuple | None:
    """First and last map row and column (i0, i1, j0, j1) of the cells that points fall in (NumPy);
    None when none lies in the window."""
    g = geometry
    fi = np.floor(points_map[:, 0] / g.resolution_m) - g.gx0
    fj = np.floor(points_map[:, 1] / g.resolution_m) - g.gy0
    inside = (fi >= 0) & (fi < g.n) & (fj >= 0) & (fj < g.n)
    if not inside.any():
        return None
    fi, fj = fi[inside], fj[inside]
    return int(fi.min()), int(fi.max()), int(fj.min()), int(fj.max())
