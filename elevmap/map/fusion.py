"""Per-cell Kalman fusion of one frame of map-frame points, in information form.

For each cell, the frame's points are gated against the cell's prior (h, sigma_p^2) with the
Mahalanobis distance |z - h| / sqrt(sigma^2 + sigma_p^2) (threshold 2.5 by default). The accepted
points are summed in information form, W = sum 1/sigma_i^2 and WZ = sum z_i/sigma_i^2, and combined
once with the prior:

    sigma_post^2 = 1 / (1/sigma_p^2 + W),   h_post = sigma_post^2 (h/sigma_p^2 + WZ),

which is the sequential Kalman update without its order dependence. An unknown cell takes the
frame's weighted mean and 1/W.

Random-effects prior: where the cell's points scatter about its height more than their variances
allow (its spread tau^2 > 0, see ``spread_alpha``), each new point is weighted 1/(sigma^2 + tau^2) and
the prior, the mean of the n points fused so far, has variance at least tau^2 m / n with m this
frame's points in the cell: what a mean of n points that scatter by tau^2 can know when they come
m at a time and a frame's points share their error (the level an edge's lateral noise shows them, a
correlated depth error), i.e. tau^2 per frame's worth of points. Without that floor a cell
initialised by one wrong point (a far depth outlier with a small stated sigma) kept its fixed-effect
variance against the random-effects weights of every later point: measured on the simulated boxes
walk, a box top stayed at -0.33 m through 50 points at its true 0.25 m. With tau^2 / n (each point
independent) the cell followed the mean of all its points, and a cell at a box's edge still read
0.12 m ten frames after the box was taken away.

A new point's tau^2 is the larger of the cell's spread and its neighbourhood spread
(:mod:`elevmap.map.neighbours`), as in the cell's variance: where neighbouring cells disagree (a step, a
band of points bled over an edge, the far field) a point may well belong to the neighbour's level, so
its stated sigma over-states what it says about this cell, and weights flatten there, towards an
equal-weight mean that a few points binned in the wrong cell cannot dominate. Measured (``elevmap
compare``, 60 frames, seed 0, paper mapper, stairs / boxes): RMSE 28.9 -> 28.8 / 55.4 -> 55.2 mm,
1-sigma 0.736 -> 0.733 / 0.720 -> 0.719, 2-sigma 0.957 -> 0.957 / 0.925 -> 0.928.

Change: a single outlier (or a few) is ignored. When a cell's rejected points are at least
``change_min_points`` and outnumber its accepted ones, the terrain has changed (a box put down, a
step): the prior's variance is inflated by the squared distance to the rejected points' mean, so that
the next frame's points pass the gate and pull the cell over; when the inflated variance exceeds
``max_variance``, the cell is re-initialised from the rejected points at once. The inflation comes
after this frame's accepted points are fused with the prior as it was: inflating first let the few
accepted points of a frame that looked like a change pull the cell to them at once (a floor cell of
1616 points at the lower image border, reached in its last frame by 14 points 4-9 cm too near, 3 of
them inside the gate, read +56 mm). Measured (``elevmap compare``, 60 frames, seed 0, paper mapper;
stairs / boxes / slope / rough): RMSE 26.7 -> 26.4 / 54.6 -> 54.8 / 29.3 -> 29.2 / 18.8 -> 18.6 mm,
2-sigma 0.956 -> 0.959 / 0.926 -> 0.928, NLL -2.89 -> -2.90 / -2.33 -> -2.34.

Information cap (correlated pixels): with ``max_points_per_frame = n_eff`` a frame adds at most the
information of n_eff average points to a cell (its weights are scaled by n_eff / n when n > n_eff),
because neighbouring D435 pixels share their errors and hundreds of them are not hundreds of
independent measurements.

After the update variances are clamped below at ``min_variance``; a cell whose variance exceeds
``max_variance`` becomes unknown.

Parallel accumulation is race-free: the points are cut into ``PARTIALS`` fixed contiguous ranges,
each summed into its own partial grid, and the partial grids are merged per cell in a fixed order,
so the result is the same bit for bit whatever the thread count. Partial grids are reset lazily
(a per-cell frame stamp), so a frame costs work only in the cells it touches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np
from numba import njit, prange

from noise_model.numba_config import JIT, resolve_threads, threads

from .neighbours import ESTIMATORS
from .layers import (
    ELEVATION, HVAR_X, HVAR_XY, HVAR_Y, LAYERS, MAX_HEIGHT, MIN_HEIGHT, NEIGHBOUR_SPREAD, INFO_SQ_SUM,
    INFO_SUM, POINTS, SCATTER, SPREAD, TIME, UPPER_BOUND, VARIANCE, ZERO_WHEN_UNKNOWN, clear_sums,
)

__all__ = ["FusionParams", "FusionWorkspace", "fuse_frame", "fuse_frame_reference", "PARTIALS"]


#: Normal quantile of the significance level (1e-4) at which scatter inflates a frame's variance.
CHI2_Z = 3.719

#: Number of partial grids (fixed, so that the summation order never depends on the thread count).
PARTIALS = 8
# accumulator fields per partial grid and cell
(A_W, A_WZ, A_N, A_ZMIN, A_ZMAX, R_W, R_WZ, R_N, R_ZMIN, R_ZMAX, H_X, H_XY, H_Y, A_WZZ, A_W0, A_WZ0, A_WZZ0,
 A_WW0) = range(18)
NACC = 18


@dataclass(frozen=True)
class FusionParams:
    """Parameters of the measurement update.

    Attributes
    ----------
    mahalanobis_threshold : float
        Gate on |z - h| / sqrt(sigma^2 + sigma_p^2) [-].
    min_variance, max_variance : float
        Clamp of the cell variance [m^2]; above ``max_variance`` a cell becomes unknown: 0.04 (sigma
        20 cm) by default, a consumer's "no height rather than one that uncertain" (``elevmap compare``
        runs every mapper with 1, elevation_mapping_cupy's, so that the ceiling does not decide which
        cells each noise model is scored on; ANYbotics' code uses 9e-4). The floor, (1 mm)^2 (the
        D435's depth unit), is what a D435 can say about the height at a 4 cm cell's centre however
        many points it fuses; without one a cell of precise near-range points claims 0.2 mm
        (measured with ``elevmap compare``, before the neighbourhood spread: the stairs' mean NLL
        3579 with a 1e-8 floor, 68 with 9e-6). It was (3 mm)^2, ANYbotics' default, until the
        neighbourhood spread took over the cover of binning errors that the floor had given; then
        the near cells it held were covered at 1 sigma 0.82-0.86 of the time. Measured (60 frames,
        seed 0, paper mapper, stairs / boxes, Paule-Mandel neighbourhood spread): 1-sigma 0.734 /
        0.742, 0.728 / 0.728, 0.721 / 0.720 with (3, 1.5, 1 mm)^2; 2-sigma 0.961 / 0.938, 0.960 /
        0.936, 0.958 / 0.934; mean NLL over the stairs, boxes, slope and rough walks -2.68, -2.73,
        -2.74. A user whose real D435 adds calibration error the simulation lacks should raise it
        (``elevmap gap`` fits a depth bias and a static pattern among its effects).
    min_horizontal_variance : float or None
        Floor of the horizontal variances [m^2]; (resolution / 2)^2 when None (as ANYbotics).
    max_horizontal_variance : float
        Ceiling of the horizontal variances [m^2].
    change_min_points : int
        Rejected points needed (and more than accepted) before a cell is taken to have changed.
    max_points_per_frame : float or None
        The information cap n_eff (None: off).
    scatter_inflation : bool
        Divide a frame's information in a cell by the reduced chi-square of its accepted points,
        chi2 = sum w (z - z_mean)^2 / (n - 1), when it is significant (above its 1 - 1e-4 quantile under
        the noise model, Wilson-Hilferty approximation): points that scatter more than their
        stated variances allow (two surfaces in one cell, points bled over an edge, underestimated
        noise) must not make the cell confident.
    spread_alpha : float or None
        Significance level of the spread test: a cell's points scatter about its height more than
        their modelled noise allows (chi-square above its 1 - spread_alpha quantile) -> tau^2 > 0
        (DerSimonian-Laird), added to the cell's variance. 0.5 (default): the plain DerSimonian-Laird
        estimator, any excess counts; smaller: only a significant excess. None: no spread (tau^2 = 0).
        Measured on the simulated stairs / boxes walks (``elevmap compare``, 60 frames): 2-sigma
        coverage 0.91 / 0.81 with 0.5, 0.90 / 0.79 with 0.1, 0.86 / 0.75 with 1e-3, 0.75 / 0.58 without.
    spread_ratio : float
        The spread counts only where a cell's points scatter about its height more than
        ``spread_ratio`` times their modelled variance (reduced chi-square Q / (n - 1)): a second
        surface in the cell, points bled over an edge. Below, the excess is the noise model
        misjudging its own sigma (the estimated incidence angle's error, unmodelled effects): it
        averages out in the cell's mean, and adding it as tau^2 made such cells' sigma several times
        too large. 20 by default; 1: any significant excess counts. Measured (``elevmap compare``, 60
        frames, seed 0, paper mapper) with the binning of mixed windows (``noise_model.mixed_windows``):
        the mean NLL over the stairs, boxes, slope and rough walks is -2.065, -2.150, -2.180, -2.190,
        -2.197, -2.197 with 1.5, 3, 5, 10, 20, 50 (1 / 2-sigma coverage stairs 0.783 / 0.961 ->
        0.729 / 0.952, boxes 0.765 / 0.933 -> 0.698 / 0.912 from 1.5 to 20): it levels off from 10.
        Before that binning, when nearer binning everywhere biased the near cells, 1.5 was set (stairs
        0.728 / 0.932, boxes 0.712 / 0.911).
    neighbour_radius : int
        Half-width [cells] of the neighbourhood whose disagreement is added to a cell's variance
        (``neighbour_spread``, see :mod:`elevmap.map.neighbours`); 0: off. 4 (a 9 x 9 window, 0.36 m at
        4 cm) by default. The heights depend on it only through the weights of later points (the
        module docstring). Measured on the simulated walks (``elevmap compare``, 60 frames, seed 0,
        paper mapper; stairs / boxes / slope / rough):
        mean NLL 68.8 / 3.6 / 128 / -2.7 with 0, 32.6 / 0.0 / - / - with 2, 16.5 / -1.0 / 6.4 / -2.7 with
        4; 2-sigma coverage 0.907 / 0.857 / 0.854 / 0.970 with 0 -> 0.950 / 0.914 / 0.913 / 0.980 with 4
        (1-sigma 0.77 / 0.72 / 0.73 / 0.81 -> 0.81 / 0.78 / 0.79 / 0.84); measured when it was added,
        before ``min_points``, ``spread_ratio`` and nearer binning (README: the current figures).
    neighbour_estimator : {"paule_mandel", "dersimonian_laird"}
        The estimator of the neighbourhood spread (:mod:`elevmap.map.neighbours`): Paule-Mandel (default),
        or DerSimonian-Laird, which its weights 1 / P make the precise cells' alone.
    min_points : int
        Points a cell must have fused (``points`` layer) before it is reported: below, the map keeps and
        fuses it but :meth:`ElevationMap.is_known`, the queries, the exports, the fused map and the scores
        treat it as unknown. A cell one or two pixels have seen holds a tail draw or a sliver of a
        neighbouring level as often as not. 3 by default; 1 reports every fused cell. Measured on the
        simulated walks (``elevmap compare``, 60 frames, seed 0, paper mapper, stairs / boxes; 1 -> 3):
        RMSE 68.6 -> 58.8 / 85.1 -> 70.4 mm, mean NLL 16.5 -> -2.3 / -1.02 -> -1.15, 2-sigma coverage
        0.950 -> 0.959 / 0.914 -> 0.929, known cells 31.0 -> 28.4 % / 51.9 -> 46.8 %; measured when it
        was added, before ``spread_ratio`` and nearer binning (README: the current figures).
    """

    mahalanobis_threshold: float = 2.5
    min_variance: float = 1e-6
    max_variance: float = 0.04
    min_horizontal_variance: float | None = None
    max_horizontal_variance: float = 0.5
    change_min_points: int = 3
    max_points_per_frame: float | None = None
    scatter_inflation: bool = True
    spread_alpha: float | None = 0.5
    spread_ratio: float = 20.0
    neighbour_radius: int = 4
    neighbour_estimator: str = "paule_mandel"
    min_points: int = 3

    def __post_init__(self):
        for name in ("mahalanobis_threshold", "min_variance", "max_variance", "max_horizontal_variance"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        if self.min_variance >= self.max_variance:
            raise ValueError("min_variance must be below max_variance")
        if self.min_horizontal_variance is not None and not (
                math.isfinite(self.min_horizontal_variance) and self.min_horizontal_variance > 0):
            raise ValueError(f"min_horizontal_variance must be finite and > 0, got {self.min_horizontal_variance!r}")
        if int(self.change_min_points) < 1:
            raise ValueError(f"change_min_points must be >= 1, got {self.change_min_points!r}")
        if self.max_points_per_frame is not None and not (
                math.isfinite(self.max_points_per_frame) and self.max_points_per_frame >= 1):
            raise ValueError(f"max_points_per_frame must be None or >= 1, got {self.max_points_per_frame!r}")
        if self.spread_alpha is not None and not (isinstance(self.spread_alpha, (int, float))
                                                  and 1e-12 <= self.spread_alpha <= 0.5):
            raise ValueError(f"spread_alpha must be None or in [1e-12, 0.5], got {self.spread_alpha!r}")
        if not (isinstance(self.spread_ratio, (int, float)) and math.isfinite(self.spread_ratio)
                and 1.0 <= self.spread_ratio <= 1e6):
            raise ValueError(f"spread_ratio must be in [1, 1e6], got {self.spread_ratio!r}")
        r = self.neighbour_radius
        if isinstance(r, bool) or not isinstance(r, (int, np.integer)) or not 0 <= r <= 10:
            raise ValueError(f"neighbour_radius must be an integer in [0, 10] cells, got {r!r}")
        if self.neighbour_estimator not in ESTIMATORS:
            raise ValueError(f"neighbour_estimator must be one of {ESTIMATORS}, got {self.neighbour_estimator!r}")
        m = self.min_points
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or not 1 <= m <= 10000:
            raise ValueError(f"min_points must be an integer in [1, 10000], got {m!r}")

    def array(self, resolution_m: float) -> np.ndarray:
        """Packed for the kernels: thr, min_var, max_var, min_hvar, max_hvar, change_min, cap (0 = off),
        scatter inflation (0/1), spread z (normal quantile of 1 - spread_alpha; -1 = off), spread ratio."""
        min_h = (resolution_m / 2) ** 2 if self.min_horizontal_variance is None else self.min_horizontal_variance
        return np.array([self.mahalanobis_threshold, self.min_variance, self.max_variance, min_h,
                         self.max_horizontal_variance, float(self.change_min_points),
                         0.0 if self.max_points_per_frame is None else float(self.max_points_per_frame),
                         1.0 if self.scatter_inflation else 0.0,
                         -1.0 if self.spread_alpha is None else NormalDist().inv_cdf(1.0 - self.spread_alpha),
                         float(self.spread_ratio)])


class FusionWorkspace:
    """Partial grids of the fusion kernel, kept across frames (reset lazily by frame stamps)."""

    def __init__(self, n: int):
        self.n = int(n)
        self.acc = np.zeros((PARTIALS, self.n * self.n, NACC))
        self.stamp = np.full((PARTIALS, self.n * self.n), -1, dtype=np.int64)
        self.frame = 0


# ---------------------------------------------------------------------------------------------
# numba
# ---------------------------------------------------------------------------------------------
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
    significant (above its 1 - SPREAD_ALPHA quantile under the noise model, Wilson-Hilferty) and the
    points scatter more than ``ratio`` times their modelled variance (Q / (n - 1) > ratio); else 0."""
    den = s1 - s2 / s1
    if n < 2.0 or not den > 0.0:           # one point (or equal weights of one): no spread to see
        return 0.0
    k = n - 1.0
    if not excess + k > ratio * k:
        return 0.0
    c = 1.0 - 2.0 / (9.0 * k) + spread_z * math.sqrt(2.0 / (9.0 * k))
    if not excess + k > k * c * c * c:
        return 0.0
    return max(excess, 0.0) / den


@njit(**JIT)
def _nbr_excess(data, bi, bj):
    """max(neighbour_spread - spread, 0) of a cell (NaN -> 0): what the neighbourhood adds to its variance
    beyond its own spread; the fusion works on the variance without it."""
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
                params, WZZ, W0, WZ0, WZZ0, WW0):
    """Combine one cell's frame sums with its prior and write the cell (see the module docstring)."""
    thr, min_var, max_var, min_h, max_h, change_min, cap, inflate = (
        params[0], params[1], params[2], params[3], params[4], params[5], params[6], params[7])
    spread_z = params[8]
    ratio = params[9]
    h = data[ELEVATION, bi, bj]
    known = not np.isnan(h)
    tau2 = data[SPREAD, bi, bj]
    if not tau2 >= 0.0:                # NaN (unknown cell)
        tau2 = 0.0
    h_prior = h
    v = data[VARIANCE, bi, bj] - tau2 - _nbr_excess(data, bi, bj)  # variance of the fused mean
    if known and tau2 > 0.0 and data[POINTS, bi, bj] > 0.0:   # a mean of n points that scatter by tau^2
        v = max(v, tau2 * max(N + Nr, 1.0) / data[POINTS, bi, bj])  # in frames of m: tau^2 m / n
    if inflate > 0.0 and N >= 2.0:
        chi2 = (WZZ - WZ * WZ / W) / (N - 1.0)
        k = N - 1.0           # chi2 > its 1 - 1e-4 quantile (Wilson-Hilferty), per degree of freedom
        q = 1.0 - 2.0 / (9.0 * k) + CHI2_Z * math.sqrt(2.0 / (9.0 * k))
        if chi2 > q * q * q:
            W /= chi2
            WZ /= chi2
    if cap > 0.0 and N > cap:
        s = cap / N
        W *= s
        WZ *= s
    if cap > 0.0 and Nr > cap:
        s = cap / Nr
        Wr *= s
        WZr *= s
    reset = False
    updated = False
    changed = known and Nr >= change_min and Nr > N
    inflation = 0.0
    if changed:
        mr = WZr / Wr
        inflation = (mr - h) * (mr - h)      # added after this frame's accepted points are fused
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
            ip = 1.0 / v
            v = 1.0 / (ip + W)
            h = (ip * h + WZ) * v
            data[MIN_HEIGHT, bi, bj] = min(data[MIN_HEIGHT, bi, bj], zmin)
            data[MAX_HEIGHT, bi, bj] = max(data[MAX_HEIGHT, bi, bj], zmax)
            data[POINTS, bi, bj] += N
        else:
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
    v = max(v, min_var)
    if v > max_var:
        for layer in range(data.shape[0]):
            data[layer, bi, bj] = np.nan
        clear_sums(data, bi, bj)
        return
    nb = data[NEIGHBOUR_SPREAD, bi, bj]
    nb = nb if (known and not reset and nb > 0.0) else 0.0    # a new or re-initialised cell: none yet
    data[ELEVATION, bi, bj] = h
    data[VARIANCE, bi, bj] = v + max(tau2, nb)
    data[SPREAD, bi, bj] = tau2
    data[NEIGHBOUR_SPREAD, bi, bj] = nb
    ub = data[UPPER_BOUND, bi, bj]
    if ub < h:                     # the terrain rose above an old free-space bound: the bound is stale
        data[UPPER_BOUND, bi, bj] = np.nan


@njit(parallel=True, **JIT)
def _fuse_kernel(data, gx0, gy0, res, x, y, z, var, hcov, has_h, stamp, params, acc, acc_stamp, fid):
    n = data.shape[1]
    P = acc.shape[0]
    N = x.shape[0]
    thr2 = params[0] * params[0]
    sx = gx0 % n
    sy = gy0 % n
    inf = np.inf
    for p in prange(P):
        lo = (N * p) // P
        hi = (N * (p + 1)) // P
        for k in range(lo, hi):
            fi = math.floor(x[k] / res) - gx0
            fj = math.floor(y[k] / res) - gy0
            if not (fi >= 0.0 and fi < n and fj >= 0.0 and fj < n):
                continue
            bi = int(fi) + sx
            if bi >= n:
                bi -= n
            bj = int(fj) + sy
            if bj >= n:
                bj -= n
            c = bi * n + bj
            if acc_stamp[p, c] != fid:
                acc_stamp[p, c] = fid
                for f in range(NACC):
                    acc[p, c, f] = 0.0
                acc[p, c, A_ZMIN] = inf
                acc[p, c, R_ZMIN] = inf
                acc[p, c, A_ZMAX] = -inf
                acc[p, c, R_ZMAX] = -inf
            zk = z[k]
            vk = var[k]
            t2 = _weight_tau2(data, bi, bj)
            w0 = 1.0 / vk
            w = 1.0 / (vk + t2) if t2 > 0.0 else w0     # unknown cell: its own weight
            h = data[ELEVATION, bi, bj]
            d = zk - h
            acc[p, c, A_W0] += w0          # every point, accepted or not, for the spread
            acc[p, c, A_WZ0] += w0 * zk
            acc[p, c, A_WZZ0] += w0 * zk * zk
            acc[p, c, A_WW0] += w0 * w0
            if (not np.isnan(h)) and d * d > thr2 * (vk + (data[VARIANCE, bi, bj] - _nbr_excess(data, bi, bj))):
                acc[p, c, R_W] += w
                acc[p, c, R_WZ] += w * zk
                acc[p, c, R_N] += 1.0
                acc[p, c, R_ZMIN] = min(acc[p, c, R_ZMIN], zk)
                acc[p, c, R_ZMAX] = max(acc[p, c, R_ZMAX], zk)
            else:
                acc[p, c, A_W] += w
                acc[p, c, A_WZ] += w * zk
                acc[p, c, A_WZZ] += w * zk * zk
                acc[p, c, A_N] += 1.0
                acc[p, c, A_ZMIN] = min(acc[p, c, A_ZMIN], zk)
                acc[p, c, A_ZMAX] = max(acc[p, c, A_ZMAX], zk)
                if has_h:
                    acc[p, c, H_X] += w * hcov[k, 0]
                    acc[p, c, H_XY] += w * hcov[k, 1]
                    acc[p, c, H_Y] += w * hcov[k, 2]
    touched = 0
    for c in prange(n * n):
        W = WZ = WZZ = Nn = Wr = WZr = Nr = Hx = Hxy = Hy = W0 = WZ0 = WZZ0 = WW0 = 0.0
        zmin = zminr = inf
        zmax = zmaxr = -inf
        seen = False
        for p in range(P):
            if acc_stamp[p, c] == fid:
                seen = True
                W += acc[p, c, A_W]
                WZ += acc[p, c, A_WZ]
                WZZ += acc[p, c, A_WZZ]
                W0 += acc[p, c, A_W0]
                WZ0 += acc[p, c, A_WZ0]
                WZZ0 += acc[p, c, A_WZZ0]
                WW0 += acc[p, c, A_WW0]
                Nn += acc[p, c, A_N]
                zmin = min(zmin, acc[p, c, A_ZMIN])
                zmax = max(zmax, acc[p, c, A_ZMAX])
                Wr += acc[p, c, R_W]
                WZr += acc[p, c, R_WZ]
                Nr += acc[p, c, R_N]
                zminr = min(zminr, acc[p, c, R_ZMIN])
                zmaxr = max(zmaxr, acc[p, c, R_ZMAX])
                Hx += acc[p, c, H_X]
                Hxy += acc[p, c, H_XY]
                Hy += acc[p, c, H_Y]
        if not seen:
            continue
        touched += 1
        if W > 0.0:
            Hx /= W
            Hxy /= W
            Hy /= W
        _merge_cell(data, c // n, c % n, W, WZ, Nn, zmin, zmax, Wr, WZr, Nr, zminr, zmaxr, Hx, Hxy, Hy, has_h,
                    stamp, params, WZZ, W0, WZ0, WZZ0, WW0)
    return touched


# ---------------------------------------------------------------------------------------------
# public entries
# ---------------------------------------------------------------------------------------------
def _cells(geom_n, gx0, gy0, res, x, y):
    """Buffer cell index of each point and the mask of those inside the window (NumPy)."""
    fi = np.floor(x / res) - gx0
    fj = np.floor(y / res) - gy0
    inside = (fi >= 0) & (fi < geom_n) & (fj >= 0) & (fj < geom_n)
    bi = (fi[inside].astype(np.int64) + gx0) % geom_n
    bj = (fj[inside].astype(np.int64) + gy0) % geom_n
    return bi * geom_n + bj, inside


def fuse_frame(data, geometry, points_map, height_var, horizontal_cov, stamp, params: FusionParams,
               workspace: FusionWorkspace, nthreads=None) -> int:
    """Fuse one frame into ``data`` (len(LAYERS), n, n) in place (numba); returns the cells touched.

    Inputs are assumed validated by the caller (``ElevationMap.update``).
    """
    n = resolve_threads(nthreads)
    has_h = horizontal_cov is not None
    h = horizontal_cov if has_h else np.zeros((1, 3))
    workspace.frame += 1
    with threads(n):
        return int(_fuse_kernel(data, geometry.gx0, geometry.gy0, geometry.resolution_m, points_map[:, 0],
                                points_map[:, 1], points_map[:, 2], height_var, h, has_h, float(stamp),
                                params.array(geometry.resolution_m), workspace.acc, workspace.stamp,
                                workspace.frame))


def fuse_frame_reference(data, geometry, points_map, height_var, horizontal_cov, stamp,
                         params: FusionParams) -> int:
    """NumPy reference of :func:`fuse_frame`: the same update, vectorised with bincount."""
    g = geometry
    n = g.n
    p = params.array(g.resolution_m)
    thr, min_var, max_var, min_h, max_h, change_min, cap, inflate, spread_z, ratio = p
    x, y, z = points_map[:, 0], points_map[:, 1], points_map[:, 2]
    c, inside = _cells(n, g.gx0, g.gy0, g.resolution_m, x, y)
    z, var = z[inside], height_var[inside]
    hc = None if horizontal_cov is None else horizontal_cov[inside]
    flat = data.reshape(len(LAYERS), n * n)            # a view: writes go to data
    tau2_old = np.where(flat[SPREAD] > 0, flat[SPREAD], 0.0)      # NaN (unknown) -> 0
    nb_old = np.where(flat[NEIGHBOUR_SPREAD] > 0, flat[NEIGHBOUR_SPREAD], 0.0)
    excess = np.maximum(nb_old - tau2_old, 0.0)      # the neighbourhood's part of the variance (see _nbr_excess)
    h0, v0 = flat[ELEVATION, c], (flat[VARIANCE] - excess)[c]
    rej = ~np.isnan(h0) & ((z - h0) ** 2 > thr * thr * (var + v0))
    acc = ~rej
    t2 = np.maximum(tau2_old, nb_old)[c]            # see _weight_tau2
    w0 = 1.0 / var
    w = np.where(t2 > 0, 1.0 / (var + t2), w0)
    m = n * n

    def bc(mask, weights=None):
        return np.bincount(c[mask], weights=None if weights is None else weights[mask], minlength=m).astype(float)

    def extreme(mask, fn, init):
        out = np.full(m, init)
        fn.at(out, c[mask], z[mask])
        return out

    W, WZ, N = bc(acc, w), bc(acc, w * z), bc(acc)
    WZZ = bc(acc, w * z * z)
    every = np.ones_like(acc)
    W0, WZ0, WZZ0, WW0 = bc(every, w0), bc(every, w0 * z), bc(every, w0 * z * z), bc(every, w0 * w0)
    Wr, WZr, Nr = bc(rej, w), bc(rej, w * z), bc(rej)
    zmin, zmax = extreme(acc, np.minimum, np.inf), extreme(acc, np.maximum, -np.inf)
    zminr, zmaxr = extreme(rej, np.minimum, np.inf), extreme(rej, np.maximum, -np.inf)
    seen = (N + Nr) > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        if hc is not None:
            Hx, Hxy, Hy = (bc(acc, w * hc[:, k]) / W for k in range(3))
        if inflate > 0:
            k = np.maximum(N - 1, 1)
            chi2 = np.where(N >= 2, (WZZ - WZ * WZ / W) / k, 0.0)
            q = (1.0 - 2.0 / (9.0 * k) + CHI2_Z * np.sqrt(2.0 / (9.0 * k))) ** 3
            f = np.where(chi2 > q, chi2, 1.0)
            W, WZ = W / f, WZ / f
        if cap > 0:
            s = np.where(N > cap, cap / np.maximum(N, 1), 1.0)
            W, WZ = W * s, WZ * s
            sr = np.where(Nr > cap, cap / np.maximum(Nr, 1), 1.0)
            Wr, WZr = Wr * sr, WZr * sr
        h, v = flat[ELEVATION].copy(), flat[VARIANCE] - tau2_old - excess
        known = ~np.isnan(h)
        npo = flat[POINTS]
        v = np.where(known & (tau2_old > 0) & (npo > 0),
                     np.maximum(v, tau2_old * np.maximum(N + Nr, 1.0) / np.where(npo > 0, npo, 1.0)), v)
        change = seen & known & (Nr >= change_min) & (Nr > N)
        mr = WZr / Wr
        inflation = np.where(change, (mr - h) ** 2, 0.0)     # added after the fusion (see _merge_cell)
        reset = change & (v + inflation > max_var)
        fuse = seen & ~reset & (N > 0)
        fuse_known = fuse & known
        fuse_new = fuse & ~known
        v_post = np.where(fuse_known, 1.0 / (1.0 / v + W), np.where(fuse_new, 1.0 / W, v))
        h_post = np.where(fuse_known, (h / v + WZ) * v_post, np.where(fuse_new, WZ / W, h))
        h_post = np.where(reset, mr, h_post)
        v_post = np.where(reset, 1.0 / Wr, v_post)
        v_post = np.where(change & ~reset, v_post + inflation, v_post)
        # spread statistics (see _spread_update)
        mb = WZ0 / W0
        qb = np.maximum(WZZ0 - WZ0 * mb, 0.0)
        # continued where the cell was known and fused; fresh (this frame's points only) where it is new
        # or was reset
        s1o = np.where(fuse_known, flat[INFO_SUM], 0.0)
        s2o = np.where(fuse_known, flat[INFO_SQ_SUM], 0.0)
        qo = np.where(fuse_known, flat[SCATTER], 0.0)
        Nall = N + Nr
        q = np.where(s1o > 0, qo + qb + s1o * W0 / (s1o + W0) * (mb - h) ** 2 - Nall, qb - (Nall - 1.0))
        s1, s2 = s1o + W0, s2o + WW0
        den = s1 - s2 / s1
        npts = np.where(fuse_known, flat[POINTS], 0.0) + Nall
        kk = np.maximum(npts - 1.0, 1.0)
        crit = kk * (1.0 - 2.0 / (9.0 * kk) + spread_z * np.sqrt(2.0 / (9.0 * kk))) ** 3
        tau2_new = np.where((spread_z >= 0) & (npts >= 2) & (den > 0) & (q + kk > crit) & (q + kk > ratio * kk),
                            np.maximum(q, 0.0) / den,
                            0.0)
    on = spread_z >= 0
    stats = (reset | fuse) & on
    tau2 = np.where(stats, tau2_new, np.where(reset, 0.0, tau2_old))
    L = flat
    L[INFO_SUM] = np.where(stats, s1, np.where(reset, 0.0, L[INFO_SUM]))
    L[INFO_SQ_SUM] = np.where(stats, s2, np.where(reset, 0.0, L[INFO_SQ_SUM]))
    L[SCATTER] = np.where(stats, q, np.where(reset, 0.0, L[SCATTER]))
    L[MIN_HEIGHT] = np.where(reset, zminr, np.where(fuse_known, np.minimum(L[MIN_HEIGHT], zmin),
                                                     np.where(fuse_new, zmin, L[MIN_HEIGHT])))
    L[MAX_HEIGHT] = np.where(reset, zmaxr, np.where(fuse_known, np.maximum(L[MAX_HEIGHT], zmax),
                                                     np.where(fuse_new, zmax, L[MAX_HEIGHT])))
    L[POINTS] = np.where(reset, Nr, np.where(fuse_known, L[POINTS] + N, np.where(fuse_new, N, L[POINTS])))
    if hc is not None:
        hx, hy, hxy = np.clip(Hx, min_h, max_h), np.clip(Hy, min_h, max_h), Hxy
    else:
        hx, hy, hxy = min_h, min_h, 0.0
    upd = reset | fuse
    L[HVAR_X] = np.where(reset, min_h, np.where(fuse, hx, L[HVAR_X]))
    L[HVAR_Y] = np.where(reset, min_h, np.where(fuse, hy, L[HVAR_Y]))
    L[HVAR_XY] = np.where(reset, 0.0, np.where(fuse, hxy, L[HVAR_XY]))
    L[TIME] = np.where(upd, float(stamp), L[TIME])
    L[UPPER_BOUND] = np.where(reset | fuse_new, np.nan, L[UPPER_BOUND])
    write = upd | change
    v_post = np.where(write, np.maximum(v_post, min_var), v_post)
    expire = write & (v_post > max_var)
    L[ELEVATION] = np.where(write, h_post, L[ELEVATION])
    nb = np.where(known & ~reset, nb_old, 0.0)
    L[VARIANCE] = np.where(write, v_post + np.maximum(tau2, nb), L[VARIANCE])
    L[SPREAD] = np.where(write, tau2, L[SPREAD])
    L[NEIGHBOUR_SPREAD] = np.where(write, nb, L[NEIGHBOUR_SPREAD])
    with np.errstate(invalid="ignore"):
        stale = write & (L[UPPER_BOUND] < L[ELEVATION])
    L[UPPER_BOUND] = np.where(stale, np.nan, L[UPPER_BOUND])
    L[:, expire] = np.nan
    for name in ZERO_WHEN_UNKNOWN:
        L[LAYERS.index(name), expire] = 0.0
    return int(seen.sum())
