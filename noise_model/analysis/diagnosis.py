"""Sim-to-real gap: statistics per stratum, the real-vs-real noise floor, normalised gaps, and effect selection.

Maths only (NumPy, SciPy, numba); the orchestration (capture sets, simulation, reports, rerun) lives
in ``elevmap/gap.py``. The method follows ``shared/notes/depth-effects.md`` section 5 and the gap
report of ``shared/specs/capture-set.md``.

Captures and strata
-------------------
A capture (:class:`GapCapture`) is a static planar target seen by a static camera for F frames: its
noise-free depth ``z_true`` (H, W) [m], incidence angle ``theta`` [rad], region labels (those of
``noise_model.analysis.capture_data``: interior, left/right board edges, left invalid band, background), the
paper's sigma_z(z_true, theta) [m] and f b [px m] (focal length times baseline). Each capture falls
into one *distance bin* and one *angle bin* (its target's distance_m and incidence angle); inside it,
pixels fall into one cell of a 3 x 3 grid over the image (``image_cell`` [row, col], row 0 at the top)
and into at most one *region* (``left_band``, ``interior``, ``edge_left``, ``edge_right``). A stratum
is (distance bin, angle bin, image cell) or (distance bin, angle bin, region); captures sharing the
bins are pooled.

Statistics (per stratum; r = z - z_true [m] on pixels with data where the geometry has a surface,
u = r / sigma_z the residual in units of the paper's sigma; the moments and correlations use the core
values |u| <= CORE_SIGMAS = 10, the tails are left to ``tail_rate`` and ``residual_w1``):

``bias_m``          mean of r [m] (E4, E5).
``temporal_std_m``  RMS over pixels of the per-pixel standard deviation over frames [m], from pairs of
                    frames: sigma_t^2 = sum (r_f - r_g)^2 / (2 n_pairs) over pixels valid in both f, g;
                    a static per-pixel pattern cancels (E10). Needs >= 2 frames.
``spatial_std_m``   standard deviation of a frame's residual about its mean over the stratum [m],
                    pooled over frames (includes any static pattern).
``corr_length_px``  integral correlation scale of a frame's normalised residual (u minus its mean over
                    the frame's 3 x 3 cell) [px]: sum over lags h = 1..4 of rho(h), the mean of the
                    correlations along u and along v. White noise gives 0; a Gaussian correlation
                    exp(-h^2 / 2 l^2) gives sum_h exp(-h^2 / 2 l^2) (2.77 px for l = 3 px) (E9).
``lattice``         mean of cos(2 pi * 32 f b / z) over pixels with data: the concentration of the
                    disparity on the 1/32-px lattice (E2; coarser 2^-b lattices, b <= 5, concentrate
                    too); ~0 for continuous disparities, 1 when every disparity is on the lattice.
``fill_rate``       fraction of the pixels with a surface that have data (E6, E11).
``residual_w1``     Wasserstein-1 distance between the real and simulated distributions of u
                    (clipped to +-6.5, binned every 0.25) [sigma_z]; its ``real`` / ``sim`` values are
                    the standard deviations of u.
``tail_rate``       fraction of pixels with data whose |u| > 4 (outliers, flying pixels).

Gap, noise floor and bootstrap
------------------------------
For a statistic s and stratum k, d = |s_real - s_sim| (for ``residual_w1``: the W1 distance itself).
The noise floor sigma_0 is the root mean square of d between two random halves of the *real* frames
(``n_splits`` random half-splits), scaled from half-size to full-size samples by
kappa = sqrt((1/F_real + 1/F_sim) / (1/n_A + 1/n_B)), and never below the statistic's resolution
:data:`MIN_FLOOR`. The normalised gap is::

    gap = max(0, d / sigma_0 - Z_FLOOR)        (Z_FLOOR = 2)

0 means real and sim are as close as two halves of the real data are to each other, within the 95 %
band of real-vs-real differences; 1 means one more floor sigma beyond that band. Frames are
resampled, never pixels: every statistic is a ratio of sums that are linear in per-frame weights
(or, for the temporal standard deviation, a quadratic form over frame pairs), so a half-split or a
bootstrap replicate is just another row of frame weights (:class:`FrameSampling`).

Aggregate gap G: the mean over statistics of the mean over that statistic's strata (each statistic
weighs the same). Significance of the baseline: G_real_vs_sim is compared with G computed for each
real-vs-real half-split (leave-one-out floor); significant when it exceeds their (1 - alpha) quantile
and :data:`MIN_SIGNIFICANT_GAP`. The floor's own estimation noise (it comes from F frames) makes
d / sigma_0 t-distributed; sigma_0 is scaled by sqrt(df / (df - 2)), df = F - 1, so that E z^2 = 1
under the null (measured on reference simulations: 1.25 before, 1.0 after). A single-frame capture
set has no real-vs-real floor: it is taken from the reference simulation instead (sim-vs-sim halves
of ``n_floor_frames`` simulated frames), and the report says so.

Effect selection
----------------
:class:`Diagnosis` holds the real captures (fit and held-out split, whole captures) and two callables,
``simulate(ids, effects, n_frames)`` and ``fit(name, base_effects)``. Forward selection: every candidate
effect is fitted on the fit captures and simulated (common random numbers: each capture's noise seed
is the same in every model), the one that lowers the fit gap most is added if it shrinks the held-out
gap significantly (paired bootstrap over frames: at least 1 - alpha of the replicates shrink, and by at
least ``min_shrink`` of the baseline held-out gap); repeat while the remaining gap is significant.
Ablation then removes each selected effect again and reports whether the held-out gap grows
significantly (confirmed) or not.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from ..numba_config import JIT

from ..checks import check_intrinsics, check_positive_scalar
from ..d435 import D435, SensorModel, _axial_sigma_unchecked

__all__ = [
    "STATISTICS", "STAT_UNITS", "REGIONS", "LOCAL_STRATA", "MIN_FLOOR", "Z_FLOOR", "MIN_SIGNIFICANT_GAP",
    "GapCapture", "make_gap_capture", "FrameSampling", "frame_sampling", "capture_sums", "capture_sums_reference",
    "Binning", "pool_sums", "statistic_values", "Floor", "make_floor", "GapResult", "compare", "shrink_test",
    "Diagnosis", "DiagnosisResult", "SelectionConfig", "wasserstein1_hist", "aggregate_by", "PlaneFit", "fit_plane",
    "HIST_EDGES", "HIST_CENTRES", "LAGS_PX", "LATTICE_STEPS_PER_PX", "TAIL_SIGMAS", "CORE_SIGMAS", "MAX_RANGE_M",
    "Z_CAP", "MIN_COUNT",
]

#: The statistics, in report order.
STATISTICS = ("bias_m", "temporal_std_m", "spatial_std_m", "corr_length_px", "lattice", "fill_rate",
              "residual_w1", "tail_rate")
#: Units of each statistic's real / sim values.
STAT_UNITS = {"bias_m": "m", "temporal_std_m": "m", "spatial_std_m": "m", "corr_length_px": "px",
              "lattice": "1", "fill_rate": "1", "residual_w1": "sigma_z", "tail_rate": "1"}
#: Smallest noise floor of each statistic (its practical resolution): a difference smaller than this
#: is not worth a model change, however many pixels measured it. [units of the statistic]
MIN_FLOOR = {"bias_m": 1e-4, "temporal_std_m": 5e-5, "spatial_std_m": 5e-5, "corr_length_px": 0.02,
             "lattice": 0.005, "fill_rate": 0.002, "residual_w1": 0.01, "tail_rate": 2e-4}
#: Multiples of the floor that count as "as close as two halves of the real data" (95 % band).
Z_FLOOR = 2.0
#: A baseline aggregate gap below this is never called significant (practical threshold).
MIN_SIGNIFICANT_GAP = 0.05

#: Region codes of ``noise_model.analysis.capture_data.CaptureGeometry.regions`` and their report names.
REGION_NONE, REGION_INTERIOR, REGION_EDGE_LEFT, REGION_EDGE_RIGHT, REGION_LEFT_BAND, REGION_BACKGROUND = range(6)
REGIONS = {REGION_LEFT_BAND: "left_band", REGION_INTERIOR: "interior", REGION_EDGE_LEFT: "edge_left",
           REGION_EDGE_RIGHT: "edge_right"}
_REGION_ORDER = (REGION_INTERIOR, REGION_EDGE_LEFT, REGION_EDGE_RIGHT, REGION_LEFT_BAND)
#: Local strata of a capture: the 9 image cells (row-major), then the 4 regions.
LOCAL_STRATA = tuple(("image_cell", (r, c)) for r in range(3) for c in range(3)) + tuple(
    ("region", REGIONS[g]) for g in _REGION_ORDER)
_K = len(LOCAL_STRATA)
_REGION_LOCAL = {g: 9 + i for i, g in enumerate(_REGION_ORDER)}

#: Lags of the spatial correlation [px], along u (image x) and along v (image y).
LAGS_PX = (1, 2, 3, 4)
#: Disparity steps per pixel of the quantisation lattice (D435: 5 fractional bits).
LATTICE_STEPS_PER_PX = 32
#: |u| beyond this many sigma_z is a tail event.
TAIL_SIGMAS = 4.0
#: Bias, standard deviations, correlation and the temporal pairs use the *core* values |u| <= this
#: (a Gaussian loses nothing); larger residuals (flying pixels, gross errors, a board edge that moved
#: onto the background) are counted by ``tail_rate`` and ``residual_w1`` only, so that one frame's
#: metre-sized residuals cannot swamp the moments.
CORE_SIGMAS = 10.0
#: Histogram of u: 0.25-sigma bins over [-6, 6] plus an underflow and an overflow bin.
HIST_EDGES = np.linspace(-6.0, 6.0, 49)
HIST_CENTRES = np.concatenate([[-6.5], 0.5 * (HIST_EDGES[1:] + HIST_EDGES[:-1]), [6.5]])
_NB = len(HIST_CENTRES)
_TAIL_BINS = np.abs(HIST_CENTRES) > TAIL_SIGMAS

# columns of the per-frame linear sums
_C_NGEOM, _C_NVALID, _C_SR, _C_SR2, _C_QSP, _C_DFSP, _C_COS, _C_NCORE = range(8)
_C_P = 8                                  # 8 columns: P(u, h) for h in LAGS, then P(v, h)
_C_Q = _C_P + 2 * len(LAGS_PX)            # 8 columns: Q likewise
_C_HIST = _C_Q + 2 * len(LAGS_PX)
_N_LIN = _C_HIST + _NB
# columns after applying frame weights: the linear ones, then the temporal quadratic forms
_C_TD = _N_LIN
_C_TN = _N_LIN + 1
N_COLS = _N_LIN + 2

#: Surfaces farther than this [m] are left out of the statistics (beyond the D435's range).
MAX_RANGE_M = 10.0
#: Fewest pixel-frames (or pixel pairs) for a statistic to be defined in a stratum.
MIN_COUNT = 100


# ---------------------------------------------------------------------------------------------
# captures
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class GapCapture:
    """What the gap statistics need to know about one capture (static camera and target).

    Attributes
    ----------
    id : str
    z_true_m : ndarray, shape (H, W), float64
        Noise-free z-depth [m] of the surface each pixel sees; NaN where there is none (or outside
        the region of interest).
    sigma_m : ndarray, shape (H, W), float64
        The paper's sigma_z(z_true, theta) [m]; NaN where ``z_true_m`` is.
    regions : ndarray, shape (H, W), int8
        Region codes (``REGION_*``; those of ``noise_model.analysis.capture_data``).
    fb_px_m : float
        f b: focal length [px] times baseline [m] (disparity = f b / z [px]).
    distance_m : float
        The target's distance [m] (for the distance bin).
    angle_deg : float
        The target's incidence angle [deg] (for the angle bin).
    kind : str
        ``wall``, ``board`` or ``plane`` (a plane fitted to a region of a real frame).
    """

    id: str
    z_true_m: np.ndarray
    sigma_m: np.ndarray
    regions: np.ndarray
    fb_px_m: float
    distance_m: float
    angle_deg: float
    kind: str = "wall"

    @property
    def shape(self) -> tuple[int, int]:
        return self.z_true_m.shape


def make_gap_capture(capture_id: str, z_true_m, theta_rad, regions, K, baseline_m: float, distance_m: float,
                     angle_deg: float, kind: str = "wall", model: SensorModel = D435, roi=None) -> GapCapture:
    """Build a :class:`GapCapture` from a rendered geometry.

    Parameters
    ----------
    capture_id : str
    z_true_m, theta_rad : array_like, shape (H, W)
        Noise-free z-depth [m] and incidence angle [rad]; NaN where nothing is hit.
    regions : array_like, shape (H, W), integer
        Region codes (0 none, 1 interior, 2 left edge, 3 right edge, 4 left band, 5 background).
    K : array_like, shape (3, 3)
        Intrinsics [px].
    baseline_m : float
        Stereo baseline [m].
    distance_m, angle_deg : float
        Distance [m] and incidence angle [deg] of the target (strata bins).
    kind : str
    model : SensorModel
        The model whose sigma_z normalises residuals.
    roi : array_like of bool, shape (H, W), optional
        Only these pixels count (e.g. the region a plane was fitted to); None = all.

    Raises
    ------
    ValueError
        Shapes that differ, non-float depth, depth that is not metres, bad intrinsics.
    """
    z = np.asarray(z_true_m)
    th = np.asarray(theta_rad)
    if z.ndim != 2 or not np.issubdtype(z.dtype, np.floating):
        raise ValueError(f"z_true_m must be a 2-D float image [m], got {z.dtype} {z.shape}")
    if th.shape != z.shape:
        raise ValueError(f"theta_rad must have z_true_m's shape {z.shape}, got {th.shape}")
    reg = np.asarray(regions)
    if reg.shape != z.shape or not np.issubdtype(reg.dtype, np.integer):
        raise ValueError(f"regions must be an integer image of shape {z.shape}, got {reg.dtype} {reg.shape}")
    if z.shape[0] < 3 or z.shape[1] < 3:
        raise ValueError(f"image too small for a 3 x 3 grid of cells: {z.shape}")
    zf = z.astype(np.float64)
    finite = np.isfinite(zf)
    if finite.any() and (zf[finite].min() <= 0 or float(np.median(zf[finite])) > 100.0):
        raise ValueError("z_true_m must be in metres and > 0 where finite")
    with np.errstate(invalid="ignore"):
        finite &= zf <= MAX_RANGE_M                    # grazing rays far beyond the camera's range
    Kc = check_intrinsics(K)
    b = check_positive_scalar(baseline_m, "baseline_m", upper=2.0, unit=" m")
    geom = finite & np.isfinite(th)
    if roi is not None:
        r = np.asarray(roi)
        if r.shape != z.shape or r.dtype != bool:
            raise ValueError(f"roi must be a boolean image of shape {z.shape}, got {r.dtype} {r.shape}")
        geom &= r
    zt = np.where(geom, zf, np.nan)
    sig = np.full(z.shape, np.nan)
    sig[geom] = _axial_sigma_unchecked(zt[geom], th.astype(np.float64)[geom], model)
    reg8 = np.where(geom, reg, REGION_NONE).astype(np.int8)
    return GapCapture(str(capture_id), zt, sig, reg8, float(Kc[0, 0]) * b, float(distance_m), float(angle_deg),
                      str(kind))


# ---------------------------------------------------------------------------------------------
# frame weights: full sample, half-splits, bootstrap
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FrameSampling:
    """Rows of frame weights applied to every capture's per-frame sums.

    Row 0 is the full sample (all weights 1); rows ``halves[s, 0]`` and ``halves[s, 1]`` are the two
    halves of random split s (weights 0/1, equal sizes ``half_size``); rows ``boot`` are bootstrap
    replicates (multiplicities of frames drawn with replacement).

    Attributes
    ----------
    weights : ndarray, shape (R, F), float64
    halves : ndarray, shape (S, 2), int
    boot : ndarray, shape (B,), int
    n_frames : int
    half_size : int
    """

    weights: np.ndarray
    halves: np.ndarray
    boot: np.ndarray
    n_frames: int
    half_size: int

    @property
    def n_rows(self) -> int:
        return self.weights.shape[0]


def frame_sampling(n_frames: int, seed: int = 0, n_splits: int = 64, n_boot: int = 64) -> FrameSampling:
    """Full sample, ``n_splits`` random half-splits and ``n_boot`` bootstrap replicates of F frames.

    With F = 1 there are no splits and no replicates (single-frame statistics only). With odd F one
    random frame is left out of each split so that the halves have equal sizes floor(F / 2).
    """
    F = int(n_frames)
    if F < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames!r}")
    rng = np.random.default_rng([int(seed), F, 7])
    rows = [np.ones(F)]
    halves, boot = [], []
    if F >= 2:
        h = F // 2
        for _ in range(int(n_splits)):
            perm = rng.permutation(F)
            a, b = np.zeros(F), np.zeros(F)
            a[perm[:h]] = 1.0
            b[perm[h:2 * h]] = 1.0
            halves.append((len(rows), len(rows) + 1))
            rows += [a, b]
        rng_boot = np.random.default_rng([int(seed), F, 11])      # independent of n_splits
        for _ in range(int(n_boot)):
            boot.append(len(rows))
            rows.append(np.bincount(rng_boot.integers(0, F, F), minlength=F).astype(np.float64))
    else:
        h = 0
    return FrameSampling(np.array(rows), np.array(halves, dtype=np.int64).reshape(-1, 2),
                         np.array(boot, dtype=np.int64), F, h)


# ---------------------------------------------------------------------------------------------
# per-capture sums
# ---------------------------------------------------------------------------------------------
def _cell_bounds(n: int) -> np.ndarray:
    return np.array([0, int(round(n / 3)), int(round(2 * n / 3)), n], dtype=np.int64)


def _check_depth_stack(cap: GapCapture, depth_m) -> np.ndarray:
    d = np.asarray(depth_m)
    if d.ndim != 3 or d.shape[1:] != cap.shape:
        raise ValueError(f"capture {cap.id!r}: depth must have shape (F, {cap.shape[0]}, {cap.shape[1]}), "
                         f"got {d.shape}")
    if d.shape[0] < 1:
        raise ValueError(f"capture {cap.id!r}: depth has no frames")
    if not np.issubdtype(d.dtype, np.floating):
        raise ValueError(f"capture {cap.id!r}: depth must be float metres (NaN = no data), got {d.dtype}")
    top = float(np.max(d, where=np.isfinite(d), initial=-np.inf))
    if top > 100.0:
        raise ValueError(f"capture {cap.id!r}: depth holds values up to {top:.1f}: it must be in metres")
    return d


def _frame_sums_reference(cap: GapCapture, depth_m: np.ndarray):
    """Per-frame linear sums (F, K, _N_LIN) and temporal pair matrices D, N (K, F, F), in plain NumPy."""
    F, H, W = depth_m.shape
    zt, sig = cap.z_true_m, cap.sigma_m
    geom = np.isfinite(zt)
    rb, cb = _cell_bounds(H), _cell_bounds(W)
    cell = (np.searchsorted(rb, np.arange(H), side="right") - 1)[:, None] * 3 + \
           (np.searchsorted(cb, np.arange(W), side="right") - 1)[None, :]
    local_region = np.full((H, W), -1, dtype=np.int64)
    for g, k in _REGION_LOCAL.items():
        local_region[cap.regions == g] = k
    labels = [cell, local_region]
    z = depth_m.astype(np.float64)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(z) & (z > 0) & geom[None]
    r_all = np.where(valid, z - np.where(geom, zt, 0.0)[None], 0.0)
    u_all = np.where(valid, r_all / np.where(geom, sig, 1.0)[None], 0.0)
    core = valid & (np.abs(u_all) <= CORE_SIGMAS)       # moments, correlations and pairs: core values only
    r = np.where(core, r_all, 0.0)
    u = np.where(core, u_all, 0.0)
    lin = np.zeros((F, _K, _N_LIN))

    def add(col, values, mask=None):
        for lab in labels:
            for k in range(_K):
                m = lab == k
                if mask is not None:
                    m = m & mask
                if m.any():
                    lin[:, k, col] += values[:, m].sum(axis=1) if values.ndim == 3 else values[m].sum() * np.ones(F)

    add(_C_NGEOM, np.broadcast_to(geom.astype(np.float64), (F, H, W)))
    add(_C_NVALID, valid.astype(np.float64))
    add(_C_NCORE, core.astype(np.float64))
    add(_C_SR, r)
    add(_C_SR2, r * r)
    with np.errstate(divide="ignore", invalid="ignore"):
        phase = np.where(valid, LATTICE_STEPS_PER_PX * cap.fb_px_m / np.where(valid, z, 1.0), 0.0)
    add(_C_COS, np.where(valid, np.cos(2 * np.pi * np.mod(phase, 1.0)), 0.0))
    n = lin[:, :, _C_NCORE]
    s1 = lin[:, :, _C_SR]
    with np.errstate(divide="ignore", invalid="ignore"):
        q = lin[:, :, _C_SR2] - np.where(n > 0, s1 * s1 / n, 0.0)
    lin[:, :, _C_QSP] = np.where(n >= 2, np.maximum(q, 0.0), 0.0)
    lin[:, :, _C_DFSP] = np.where(n >= 2, n - 1, 0.0)
    # u minus its mean over the frame's 3 x 3 cell
    uc = u.copy()
    for k in range(9):
        m = cell == k
        nk = core[:, m].sum(axis=1)
        mean = np.where(nk > 0, u[:, m].sum(axis=1) / np.maximum(nk, 1), 0.0)
        uc[:, m] -= mean[:, None]
    uc[~core] = 0.0
    vf = core.astype(np.float64)
    for axis in (0, 1):
        for j, h in enumerate(LAGS_PX):
            pos = axis * len(LAGS_PX) + j
            prod = np.zeros((F, H, W))
            qq = np.zeros((F, H, W))
            if axis == 0:               # along u: pixel (v, x) with (v, x + h)
                a, b = uc[:, :, :W - h], uc[:, :, h:]
                va, vb = vf[:, :, :W - h], vf[:, :, h:]
                prod[:, :, :W - h] = a * b
                qq[:, :, :W - h] = 0.5 * (a * a * vb + b * b * va)
            else:                       # along v: pixel (y, u) with (y + h, u)
                a, b = uc[:, :H - h, :], uc[:, h:, :]
                va, vb = vf[:, :H - h, :], vf[:, h:, :]
                prod[:, :H - h, :] = a * b
                qq[:, :H - h, :] = 0.5 * (a * a * vb + b * b * va)
            add(_C_P + pos, prod)
            add(_C_Q + pos, qq)
    binidx = np.searchsorted(HIST_EDGES, u_all, side="right")    # 0 = underflow, _NB - 1 = overflow
    for bidx in range(_NB):
        add(_C_HIST + bidx, (valid & (binidx == bidx)).astype(np.float64))
    # temporal pair matrices
    cnt = core.sum(axis=0)
    mean_p = np.where(cnt > 0, r.sum(axis=0) / np.maximum(cnt, 1), 0.0)
    rc = np.where(core, r - mean_p[None], 0.0)
    D = np.zeros((_K, F, F))
    N = np.zeros((_K, F, F))
    for lab in labels:
        for k in range(_K):
            m = lab == k
            if not m.any():
                continue
            V = vf[:, m]
            A = rc[:, m]
            B = A * A
            N[k] += V @ V.T
            M = B @ V.T
            D[k] += M + M.T - 2.0 * (A @ A.T)
    return lin, D, N


#: Buckets of the numba kernel: each pixel belongs to one (cell, region) pair, 9 cells x (no region + 4).
_NREG1 = len(_REGION_ORDER) + 1
_NBUCKET = 9 * _NREG1


@njit(parallel=True, **JIT)
def _frame_sums_kernel(z, zt, inv_sig, geom, cell, bucket, phase_k, edges, lags, core_sig, lin, D,
                       N):  # pragma: no cover - compiled
    """numba: per-frame sums lin (F, B, _N_LIN) and pair matrices D, N (B, F, F) per bucket (zeroed by
    the caller); B buckets = (cell, region) pairs, so each pixel is accumulated once (the strata are sums
    of buckets, formed by the caller). Columns _C_QSP, _C_DFSP are left 0 (they are not linear in the
    buckets). See :func:`_frame_sums_reference`.

    Frames are independent (prange over frames, each writes its own lin[f]); the pair matrices are
    summed over image rows split into fixed blocks, one partial result per block, then reduced in
    block order, so the result does not depend on the thread count.
    """
    F, H, W = z.shape
    B = lin.shape[1]
    nlag = lags.shape[0]
    nb = edges.shape[0] + 1
    e0 = edges[0]
    e1 = edges[nb - 2]
    inv_step = (nb - 2) / (e1 - e0)
    two_pi = 2.0 * math.pi
    for f in prange(F):
        u = np.zeros((H, W))
        v = np.zeros((H, W), dtype=np.bool_)
        csum = np.zeros(9)
        ccnt = np.zeros(9)
        lf = lin[f]
        for y in range(H):
            for x in range(W):
                if not geom[y, x]:
                    continue
                k = bucket[y, x]
                lf[k, 0] += 1.0
                zz = z[f, y, x]
                if not (zz > 0.0):                          # NaN fails zz > 0
                    continue
                r = zz - zt[y, x]
                uu = r * inv_sig[y, x]
                # histogram bin = number of edges <= uu (searchsorted, side right), edges uniform
                if uu < e0:
                    b = 0
                elif uu >= e1:
                    b = nb - 1
                else:
                    b = int((uu - e0) * inv_step) + 1
                    if b > nb - 2:
                        b = nb - 2
                    while b > 1 and uu < edges[b - 1]:
                        b -= 1
                    while b < nb - 1 and uu >= edges[b]:
                        b += 1
                lf[k, 1] += 1.0
                t = phase_k / zz                                 # disparity in lattice steps
                lf[k, 6] += math.cos(two_pi * (t - math.floor(t)))
                lf[k, _C_HIST + b] += 1.0
                if abs(uu) > core_sig:                       # a tail value: only fill, lattice, histogram
                    continue
                c = cell[y, x]
                v[y, x] = True
                u[y, x] = uu
                csum[c] += uu
                ccnt[c] += 1.0
                lf[k, 7] += 1.0
                lf[k, 2] += r
                lf[k, 3] += r * r
        for c in range(9):
            if ccnt[c] > 0:
                csum[c] = csum[c] / ccnt[c]
        for y in range(H):                                   # u minus its cell's mean, in place
            for x in range(W):
                if v[y, x]:
                    u[y, x] -= csum[cell[y, x]]
        for y in range(H):
            for x in range(W):
                if not v[y, x]:
                    continue
                k = bucket[y, x]
                a = u[y, x]
                for j in range(nlag):
                    h = lags[j]
                    if x + h < W and v[y, x + h]:
                        bb = u[y, x + h]
                        lf[k, _C_P + j] += a * bb
                        lf[k, _C_Q + j] += 0.5 * (a * a + bb * bb)
                    if y + h < H and v[y + h, x]:
                        bb = u[y + h, x]
                        lf[k, _C_P + nlag + j] += a * bb
                        lf[k, _C_Q + nlag + j] += 0.5 * (a * a + bb * bb)
    if F < 2:
        return
    nblk = 16
    Dp = np.zeros((nblk, B, F, F))
    Np = np.zeros((nblk, B, F, F))
    for bk in prange(nblk):
        y0 = (H * bk) // nblk
        y1 = (H * (bk + 1)) // nblk
        rr = np.zeros(F)
        idx = np.zeros(F, dtype=np.int64)
        for y in range(y0, y1):
            for x in range(W):
                if not geom[y, x]:
                    continue
                n = 0
                zt0 = zt[y, x]
                isg = inv_sig[y, x]
                for f in range(F):
                    zz = z[f, y, x]
                    if zz > 0.0:
                        rf = zz - zt0
                        if abs(rf * isg) <= core_sig:
                            idx[n] = f
                            rr[n] = rf
                            n += 1
                if n < 2:
                    continue
                Dc = Dp[bk, bucket[y, x]]
                Nc = Np[bk, bucket[y, x]]
                for a in range(n):
                    fa = idx[a]
                    ra = rr[a]
                    for b in range(a + 1, n):
                        dd = ra - rr[b]
                        Dc[fa, idx[b]] += dd * dd
                        Nc[fa, idx[b]] += 1.0
    for bk in range(nblk):
        for k in range(B):
            for f in range(F):
                for e in range(f + 1, F):
                    D[k, f, e] += Dp[bk, k, f, e]
                    D[k, e, f] += Dp[bk, k, f, e]
                    N[k, f, e] += Np[bk, k, f, e]
                    N[k, e, f] += Np[bk, k, f, e]


def _bucket_to_strata(x: np.ndarray, axis: int) -> np.ndarray:
    """Sum (cell, region) buckets along ``axis`` into the local strata (9 cells, then the 4 regions)."""
    x = np.moveaxis(x, axis, 0)
    xb = x.reshape((9, _NREG1) + x.shape[1:])
    out = np.concatenate([xb.sum(axis=1), xb[:, 1:].sum(axis=0)], axis=0)
    return np.moveaxis(out, 0, axis)


def _frame_sums_fast(cap: GapCapture, depth_m: np.ndarray):
    """The sums of :func:`_frame_sums_reference` in one numba pass (off-diagonal N only: its diagonal,
    a frame paired with itself, never enters a statistic)."""
    F, H, W = depth_m.shape
    geom = np.isfinite(cap.z_true_m)
    rb, cb = _cell_bounds(H), _cell_bounds(W)
    cell = (np.repeat(np.arange(3), np.diff(rb))[:, None] * 3 + np.repeat(np.arange(3), np.diff(cb))[None, :])
    reg1 = np.zeros((H, W), dtype=np.int64)                 # 0: no region, 1 + i: _REGION_ORDER[i]
    for i, g in enumerate(_REGION_ORDER):
        reg1[cap.regions == g] = 1 + i
    bucket = np.ascontiguousarray(cell * _NREG1 + reg1, dtype=np.int64)
    zt = np.where(geom, cap.z_true_m, 0.0)
    inv_sig = np.where(geom, 1.0 / np.where(geom, cap.sigma_m, 1.0), 0.0)
    lin_b = np.zeros((F, _NBUCKET, _N_LIN))
    D_b = np.zeros((_NBUCKET, F, F))
    N_b = np.zeros((_NBUCKET, F, F))
    z = np.ascontiguousarray(depth_m, dtype=np.float64)
    _frame_sums_kernel(z, zt, inv_sig, geom, np.ascontiguousarray(cell, dtype=np.int64), bucket,
                       LATTICE_STEPS_PER_PX * cap.fb_px_m, HIST_EDGES,
                       np.asarray(LAGS_PX, dtype=np.int64), CORE_SIGMAS, lin_b, D_b, N_b)
    lin = _bucket_to_strata(lin_b, 1)
    n, s1 = lin[:, :, _C_NCORE], lin[:, :, _C_SR]
    with np.errstate(invalid="ignore", divide="ignore"):
        q = lin[:, :, _C_SR2] - np.where(n > 0, s1 * s1 / np.maximum(n, 1), 0.0)
    lin[:, :, _C_QSP] = np.where(n >= 2, np.maximum(q, 0.0), 0.0)
    lin[:, :, _C_DFSP] = np.where(n >= 2, n - 1, 0.0)
    return lin, _bucket_to_strata(D_b, 0), _bucket_to_strata(N_b, 0)


def _apply_rows(lin, D, N, weights) -> np.ndarray:
    """Per-frame sums (F, K, _N_LIN) and pair matrices (K, F, F) -> row sums (R, K, N_COLS)."""
    W = np.asarray(weights, dtype=np.float64)
    out = np.empty((W.shape[0], lin.shape[1], N_COLS))
    out[:, :, :_N_LIN] = np.einsum("rf,fkc->rkc", W, lin)
    out[:, :, _C_TD] = np.einsum("rf,kfg,rg->rk", W, D, W)
    diagN = np.einsum("kff->kf", N)
    out[:, :, _C_TN] = np.einsum("rf,kfg,rg->rk", W, N, W) - np.einsum("rf,kf->rk", W * W, diagN)
    return out


def capture_sums(cap: GapCapture, depth_m, sampling: FrameSampling) -> np.ndarray:
    """Sums of one capture per row of frame weights and local stratum.

    Parameters
    ----------
    cap : GapCapture
    depth_m : array_like, shape (F, H, W), float
        Depth [m]; NaN (or <= 0) = no data.
    sampling : FrameSampling
        Rows of frame weights for F frames.

    Returns
    -------
    ndarray, shape (R, len(LOCAL_STRATA), N_COLS), float64
    """
    d = _check_depth_stack(cap, depth_m)
    if sampling.n_frames != d.shape[0]:
        raise ValueError(f"capture {cap.id!r}: {d.shape[0]} frames but the sampling is for {sampling.n_frames}")
    lin, D, N = _frame_sums_fast(cap, d)
    return _apply_rows(lin, D, N, sampling.weights)


def capture_sums_reference(cap: GapCapture, depth_m, sampling: FrameSampling) -> np.ndarray:
    """:func:`capture_sums` computed stratum by stratum with boolean masks (slow; for the tests)."""
    d = _check_depth_stack(cap, depth_m)
    lin, D, N = _frame_sums_reference(cap, d)
    return _apply_rows(lin, D, N, sampling.weights)


# ---------------------------------------------------------------------------------------------
# strata across captures
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Binning:
    """Distance and angle bins of the strata: [i w, (i + 1) w) for bin i.

    Attributes
    ----------
    distance_width_m : float
        Width of a distance bin [m] (default 0.2).
    angle_width_deg : float
        Width of an incidence-angle bin [deg] (default 15).
    """

    distance_width_m: float = 0.2
    angle_width_deg: float = 15.0

    def bins(self, cap: GapCapture) -> tuple[int, int]:
        d = int(math.floor(round(cap.distance_m / self.distance_width_m, 9)))
        a = int(math.floor(round(cap.angle_deg / self.angle_width_deg, 9)))
        return d, a

    def stratum(self, key: tuple[int, int, int]) -> dict:
        """The report's stratum of a global key (distance bin, angle bin, local stratum)."""
        d, a, k = key
        w, aw = self.distance_width_m, self.angle_width_deg
        kind, val = LOCAL_STRATA[k]
        out = {"distance_m": [round(d * w, 6), round((d + 1) * w, 6)],
               "angle_deg": [round(a * aw, 6), round((a + 1) * aw, 6)]}
        out[kind] = list(val) if kind == "image_cell" else val
        return out


def pool_sums(captures: Sequence[GapCapture], sums: Sequence[np.ndarray], binning: Binning):
    """Add the captures' sums into global strata (distance bin, angle bin, local stratum).

    Parameters
    ----------
    captures : sequence of GapCapture
    sums : sequence of ndarray, shape (R, len(LOCAL_STRATA), N_COLS)
        :func:`capture_sums` of each capture (same rows).
    binning : Binning

    Returns
    -------
    keys : list of (int, int, int)
        Global strata, sorted.
    pooled : ndarray, shape (R, len(keys), N_COLS)
    """
    if len(captures) != len(sums) or not captures:
        raise ValueError("pool_sums needs one sums array per capture, and at least one capture")
    R = sums[0].shape[0]
    bins = [binning.bins(c) for c in captures]
    keys = sorted({(d, a, k) for d, a in bins for k in range(_K)})
    index = {key: i for i, key in enumerate(keys)}
    pooled = np.zeros((R, len(keys), N_COLS))
    for (d, a), s in zip(bins, sums):
        if s.shape[0] != R:
            raise ValueError("all captures' sums must have the same rows of frame weights")
        idx = [index[(d, a, k)] for k in range(_K)]
        pooled[:, idx, :] += s
    return keys, pooled


_SCALAR_STATS = tuple(s for s in STATISTICS if s != "residual_w1")


def statistic_values(pooled: np.ndarray):
    """Statistics from pooled sums.

    Parameters
    ----------
    pooled : ndarray, shape (R, K, N_COLS)

    Returns
    -------
    values : ndarray, shape (R, len(STATISTICS), K)
        NaN where a statistic is undefined (too few pixels, frames or pairs). For ``residual_w1`` the
        value is the standard deviation of the clipped normalised residual.
    hist : ndarray, shape (R, K, len(HIST_CENTRES))
        Normalised histogram of u (NaN rows where undefined).
    """
    p = pooled
    with np.errstate(divide="ignore", invalid="ignore"):
        n_geom, n, nc = p[..., _C_NGEOM], p[..., _C_NVALID], p[..., _C_NCORE]
        ok = n >= MIN_COUNT
        okc = nc >= MIN_COUNT
        vals = np.full((p.shape[0], len(STATISTICS), p.shape[1]), np.nan)
        vals[:, 5] = np.where(n_geom >= MIN_COUNT, n / n_geom, np.nan)
        vals[:, 0] = np.where(okc, p[..., _C_SR] / nc, np.nan)
        tn = p[..., _C_TN]
        vals[:, 1] = np.where(tn >= MIN_COUNT, np.sqrt(np.maximum(p[..., _C_TD], 0.0) / (2.0 * tn)), np.nan)
        df = p[..., _C_DFSP]
        vals[:, 2] = np.where(df >= MIN_COUNT, np.sqrt(p[..., _C_QSP] / df), np.nan)
        nl = len(LAGS_PX)
        P = p[..., _C_P:_C_P + 2 * nl]
        Q = p[..., _C_Q:_C_Q + 2 * nl]
        rho = np.where(Q > 0, P / Q, np.nan)
        vals[:, 3] = np.where(okc & (Q.min(axis=-1) > 0), 0.5 * (rho[..., :nl].sum(-1) + rho[..., nl:].sum(-1)),
                              np.nan)
        vals[:, 4] = np.where(ok, p[..., _C_COS] / n, np.nan)
        h = p[..., _C_HIST:_C_HIST + _NB]
        tot = h.sum(-1)
        hist = np.where((tot >= MIN_COUNT)[..., None], h / tot[..., None], np.nan)
        m1 = (hist * HIST_CENTRES).sum(-1)
        vals[:, 6] = np.sqrt(np.maximum((hist * HIST_CENTRES ** 2).sum(-1) - m1 * m1, 0.0))
        vals[:, 7] = hist[..., _TAIL_BINS].sum(-1)
    return vals, hist


def wasserstein1_hist(a, b) -> np.ndarray:
    """W1 distance between histograms over :data:`HIST_CENTRES` (last axis) [sigma_z]: the area
    between the two cumulative distributions."""
    ca = np.cumsum(a, axis=-1)[..., :-1]
    cb = np.cumsum(b, axis=-1)[..., :-1]
    return (np.abs(ca - cb) * np.diff(HIST_CENTRES)).sum(-1)


# ---------------------------------------------------------------------------------------------
# gaps
# ---------------------------------------------------------------------------------------------
_W1 = STATISTICS.index("residual_w1")
_MIN_FLOOR = np.array([MIN_FLOOR[s] for s in STATISTICS])
#: Largest normalised difference recorded (and the value used when the simulation cannot produce a
#: statistic that the real data has).
Z_CAP = 1e3


def _distances(vals_a, hist_a, vals_b, hist_b) -> np.ndarray:
    """|a - b| per statistic and stratum, W1 for the residual distribution; (..., n_stats, K)."""
    d = np.abs(vals_a - vals_b)
    w1 = wasserstein1_hist(hist_a, hist_b)              # (..., K)
    d[..., _W1, :] = w1
    return d


@dataclass
class Floor:
    """The real-vs-real noise floor of one set of captures.

    Attributes
    ----------
    keys : list of (int, int, int)
        Global strata.
    sigma0 : ndarray, shape (n_stats, K)
        Floor of |real - sim| at full sample sizes (NaN: undefined).
    defined : ndarray of bool, shape (n_stats, K)
        Entries that take part in the gap (real value and floor defined).
    weights : ndarray, shape (n_stats, K)
        Aggregation weights (sum 1): each statistic weighs the same, its strata equally.
    null_g : ndarray, shape (S,)
        Aggregate gap of each real-vs-real half-split (leave-one-out floor): the null distribution.
    real_values : ndarray, shape (R, n_stats, K)
    real_hist : ndarray, shape (R, K, nb)
    source : str
        ``real halves`` or ``simulation halves`` (single-frame real data).
    unavailable : dict
        Statistic -> why it could not be computed anywhere.
    """

    keys: list
    sigma0: np.ndarray
    defined: np.ndarray
    weights: np.ndarray
    null_g: np.ndarray
    real_values: np.ndarray
    real_hist: np.ndarray
    source: str
    unavailable: dict = field(default_factory=dict)


def _weights(defined: np.ndarray) -> np.ndarray:
    w = np.zeros(defined.shape)
    per_stat = defined.sum(axis=1)
    used = per_stat > 0
    for s in np.flatnonzero(used):
        w[s, defined[s]] = 1.0 / per_stat[s]
    return w / max(int(used.sum()), 1)


def make_floor(keys, real_pooled, real_sampling: FrameSampling, n_sim_frames: int,
               floor_pooled=None, floor_sampling: FrameSampling | None = None) -> Floor:
    """The noise floor from split halves of the real frames (or, for single-frame real data, of a
    reference simulation: ``floor_pooled`` with its ``floor_sampling``).

    kappa scales the RMS difference between halves of h frames to the expected difference between
    F_real real and F_sim simulated frames: kappa = sqrt((1/F_real + 1/F_sim) / (2/h)).
    """
    rv, rh = statistic_values(real_pooled)
    if real_sampling.halves.size:
        fv, fh, fs, source = rv, rh, real_sampling, "real halves"
    else:
        if floor_pooled is None or floor_sampling is None or not floor_sampling.halves.size:
            raise ValueError("single-frame real data needs a simulated floor (floor_pooled with half-splits)")
        fv, fh = statistic_values(floor_pooled)
        fs, source = floor_sampling, "simulation halves (the real captures have one frame each)"
    A, B = fs.halves[:, 0], fs.halves[:, 1]
    d = _distances(fv[A], fh[A], fv[B], fh[B])                     # (S, n_stats, K)
    kappa = math.sqrt((1.0 / real_sampling.n_frames + 1.0 / n_sim_frames) / (2.0 / fs.half_size))
    # sigma0 is estimated from fs.n_frames frames, so d / sigma0 is t-like with df = n - 1 degrees of
    # freedom: E[(d / sigma0)^2] = df / (df - 2), not 1. Scale that back out (measured on reference
    # simulations: mean z^2 1.25 before, 1.0 after).
    df = fs.n_frames - 1
    t_scale = math.sqrt(df / (df - 2.0)) if df > 2 else 1.0
    finite = np.isfinite(d)
    cnt = finite.sum(axis=0)
    ss = np.where(finite, d * d, 0.0)
    tot = ss.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(tot / cnt)
        sigma0 = np.where(cnt >= 2, np.maximum(kappa * t_scale * rms, _MIN_FLOOR[:, None]), np.nan)
        # null: each split against the floor of the other splits (leave-one-out); its z has E z^2 = 1
        loo = np.sqrt((tot[None] - ss) / (cnt[None] - finite))
        sig_loo = np.maximum(kappa * loo, _MIN_FLOOR[None, :, None])
        z_null = np.minimum(kappa * d / sig_loo, Z_CAP)
    defined = np.isfinite(rv[0]) & np.isfinite(sigma0)
    w = _weights(defined)
    g_null = (w[None] * np.where(defined[None] & np.isfinite(z_null), np.maximum(z_null - Z_FLOOR, 0.0), 0.0)
              ).sum(axis=(1, 2))
    unavailable = {}
    for s, name in enumerate(STATISTICS):
        if not defined[s].any():
            if name == "temporal_std_m" and real_sampling.n_frames < 2:
                unavailable[name] = "needs >= 2 frames per capture (the real captures have 1)"
            elif not np.isfinite(rv[0, s]).any():
                unavailable[name] = "too few pixels with data in every stratum"
            else:
                unavailable[name] = "no noise floor (too few frames)"
    return Floor(list(keys), sigma0, defined, w, g_null, rv, rh, source, unavailable)


@dataclass
class GapResult:
    """Real vs one simulated model over one set of captures.

    Attributes
    ----------
    floor : Floor
    sim_values : ndarray, shape (R_sim, n_stats, K)
    d : ndarray, shape (n_stats, K)
        |real - sim| (W1 for the residual distribution) at full samples.
    z : ndarray, shape (n_stats, K)
        d / sigma0 (capped at Z_CAP; Z_CAP where the simulation cannot produce a defined statistic).
    gap : ndarray, shape (n_stats, K)
        max(0, z - Z_FLOOR) on defined entries, 0 elsewhere.
    G : float
        Aggregate gap (weighted mean of ``gap``).
    G_boot : ndarray, shape (B,)
        Aggregate gap of each bootstrap replicate over frames (paired across models).
    p_value : float
        Fraction of real-vs-real splits whose aggregate gap reaches G (with the +1 correction).
    significant : bool
        G above the (1 - alpha) quantile of the real-vs-real aggregate gaps and above
        :data:`MIN_SIGNIFICANT_GAP`.
    """

    floor: Floor
    sim_values: np.ndarray
    d: np.ndarray
    z: np.ndarray
    gap: np.ndarray
    G: float
    G_boot: np.ndarray
    p_value: float
    significant: bool

    def entries(self, binning: Binning, only_positive: bool = False) -> list[dict]:
        """``where`` entries ranked by gap (then z), largest first."""
        fl = self.floor
        s_idx, k_idx = np.nonzero(fl.defined)
        order = np.lexsort((-self.z[s_idx, k_idx], -self.gap[s_idx, k_idx]))
        out = []
        for i in order:
            s, k = int(s_idx[i]), int(k_idx[i])
            g = float(self.gap[s, k])
            if only_positive and g <= 0:
                continue
            out.append({"statistic": STATISTICS[s], "stratum": binning.stratum(fl.keys[k]),
                        "real": _num(fl.real_values[0, s, k]), "sim": _num(self.sim_values[0, s, k]),
                        "gap": g, "z": _num(self.z[s, k]), "floor": _num(fl.sigma0[s, k]),
                        "weight": float(fl.weights[s, k])})
        return out


def _num(x):
    x = float(x)
    return x if math.isfinite(x) else None


def compare(floor: Floor, real_sampling: FrameSampling, sim_pooled: np.ndarray, sim_sampling: FrameSampling,
            alpha: float = 0.05) -> GapResult:
    """Normalised gaps between the real data (summarised in ``floor``) and one simulated model.

    Parameters
    ----------
    floor : Floor
        From :func:`make_floor` over the same captures and strata.
    real_sampling, sim_sampling : FrameSampling
        Rows of the real and simulated sums (bootstrap replicate b pairs real row boot[b], or the
        full row for single-frame data, with sim row boot[b]).
    sim_pooled : ndarray, shape (R_sim, K, N_COLS)
    alpha : float
        Significance level of the baseline test.
    """
    sv, sh = statistic_values(sim_pooled)
    rv, rh = floor.real_values, floor.real_hist
    defined, sig0 = floor.defined, floor.sigma0

    def gaps(real_rows, sim_rows):
        d = _distances(rv[real_rows], rh[real_rows], sv[sim_rows], sh[sim_rows])
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.minimum(d / sig0, Z_CAP)
        z = np.where(np.isfinite(z), z, Z_CAP)                 # real defined, sim not: as far as it gets
        g = np.where(defined, np.maximum(z - Z_FLOOR, 0.0), 0.0)
        return d, z, g

    d, z, g = gaps(0, 0)
    G = float((floor.weights * g).sum())
    nb = sim_sampling.boot.size
    if nb:
        rrows = real_sampling.boot[:nb] if real_sampling.boot.size >= nb else np.zeros(nb, dtype=np.int64)
        _, _, gb = gaps(rrows, sim_sampling.boot)
        G_boot = (floor.weights[None] * gb).sum(axis=(1, 2))
    else:
        G_boot = np.zeros(0)
    S = floor.null_g.size
    p = (1.0 + float((floor.null_g >= G).sum())) / (1.0 + S) if S else math.nan
    q = float(np.quantile(floor.null_g, 1.0 - alpha)) if S else math.inf
    significant = bool(S and G > q and G > MIN_SIGNIFICANT_GAP)
    return GapResult(floor, sv, np.where(defined, d, np.nan), np.where(defined, z, np.nan), g, G, G_boot, p,
                     significant)


def shrink_test(before: GapResult, after: GapResult, alpha: float = 0.05) -> dict:
    """Paired bootstrap over frames: does ``after`` have a smaller aggregate gap than ``before``?

    Returns
    -------
    dict
        ``delta`` (G_before - G_after at full samples), ``fraction`` (of replicates with a smaller gap
        after), ``significant`` (fraction >= 1 - alpha and delta > 0).
    """
    delta = before.G - after.G
    if before.G_boot.size and after.G_boot.size == before.G_boot.size:
        frac = float(np.mean(before.G_boot - after.G_boot > 0))
    else:
        frac = 1.0 if delta > 0 else 0.0
    return {"delta": float(delta), "fraction": frac, "significant": bool(delta > 0 and frac >= 1.0 - alpha)}


def aggregate_by(result: GapResult, binning: Binning, by: str) -> dict:
    """Weighted mean gap grouped by ``statistic``, ``distance_m``, ``angle_deg``, ``image_cell`` or
    ``region`` (the share of the aggregate each group carries is ``weight``).

    Returns
    -------
    dict
        group label -> {"gap": weighted mean gap of the group, "share": its part of G (sums to 1 when G > 0)}.
    """
    fl = result.floor
    acc: dict = {}
    for s in range(len(STATISTICS)):
        for k in np.flatnonzero(fl.defined[s]):
            if by == "statistic":
                label = STATISTICS[s]
            else:
                st = binning.stratum(fl.keys[k])
                if by not in st:
                    continue
                v = st[by]
                label = f"{v[0]:g}-{v[1]:g}" if by in ("distance_m", "angle_deg") else (
                    f"[{v[0]}, {v[1]}]" if by == "image_cell" else v)
            w = fl.weights[s, k]
            a = acc.setdefault(label, [0.0, 0.0])
            a[0] += w * result.gap[s, k]
            a[1] += w
    total = sum(a[0] for a in acc.values())
    return {lab: {"gap": a[0] / a[1] if a[1] > 0 else 0.0, "share": a[0] / total if total > 0 else 0.0}
            for lab, a in sorted(acc.items(), key=lambda kv: -kv[1][0])}


# ---------------------------------------------------------------------------------------------
# diagnosis: baseline, forward selection, ablation
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SelectionConfig:
    """Settings of the forward selection.

    Attributes
    ----------
    alpha : float
        Significance level: the baseline test, and the paired bootstrap of a shrink (at least
        1 - alpha of the replicates must shrink).
    min_shrink : float
        An effect must also shrink the held-out gap by at least this fraction of the baseline
        held-out gap.
    max_effects : int
        At most this many effects are selected.
    prune : bool
        From the second round on, only candidates that shrank the fit gap in the previous round are
        tried again (saves time; an effect that did not help before rarely helps after another).
    """

    alpha: float = 0.05
    min_shrink: float = 0.05
    max_effects: int = 4
    prune: bool = True


def _model_key(effects) -> tuple:
    return tuple((name, tuple(sorted((k, _hashable(v)) for k, v in params.items()))) for name, params in effects)


def _hashable(v):
    if isinstance(v, (list, tuple)):
        return tuple(_hashable(x) for x in v)
    if isinstance(v, np.generic):
        return v.item()
    return v


@dataclass
class DiagnosisResult:
    """What :meth:`Diagnosis.run` found.

    Attributes
    ----------
    report : dict
        ``baseline``, ``where``, ``rounds``, ``effects``, ``final``, ``unavailable``, ``floor_source``
        (JSON-ready; the orchestrator adds ``format``, ``real``, ``split``).
    baseline_all, final_all : GapResult
        Reference model and final model against all captures.
    baseline_heldout, final_heldout : GapResult
    selected : list of (str, dict)
        The effects selected, in order, with their fitted parameters.
    captures : dict
        id -> GapCapture (fit captures first, then held-out).
    """

    report: dict
    baseline_all: GapResult
    final_all: GapResult
    baseline_heldout: GapResult
    final_heldout: GapResult
    selected: list
    captures: dict = field(default_factory=dict)


class Diagnosis:
    """Real captures against simulated models: baseline gap, forward selection of effects, ablation.

    Parameters
    ----------
    captures : sequence of GapCapture
    real_depth : mapping id -> ndarray (F, H, W) float [m]
        The real frames (NaN = no data). Captures with more frames than the fewest are cut to it.
    fit_ids, heldout_ids : sequence of str
        Whole captures used to fit effects and to validate them (disjoint). With no held-out capture
        the fit captures validate (the report says so).
    simulate : callable
        ``simulate(ids, effects, n_frames) -> {id: ndarray (n_frames, H, W) float [m]}``: the reference
        simulation plus ``effects`` (list of (name, params)), each capture seeded the same way in every
        model (common random numbers).
    fit : callable or None
        ``fit(name, base_effects) -> params``: an effect's parameters fitted on the fit captures on top
        of ``base_effects``. None: baseline only.
    binning : Binning
    n_splits, n_boot : int
        Real-vs-real half-splits (noise floor) and bootstrap replicates over frames.
    seed : int
        Seed of the splits and replicates.
    config : SelectionConfig
    progress : callable, optional
        ``progress(message)`` after every simulated model.
    """

    def __init__(self, captures: Sequence[GapCapture], real_depth, fit_ids, heldout_ids, simulate: Callable,
                 fit: Callable | None = None, *, binning: Binning = Binning(), n_splits: int = 64, n_boot: int = 64,
                 seed: int = 0, config: SelectionConfig = SelectionConfig(), progress: Callable | None = None,
                 n_floor_frames: int = 8):
        self.captures = {c.id: c for c in captures}
        if len(self.captures) != len(captures) or not captures:
            raise ValueError("captures must be non-empty with unique ids")
        fit_ids, heldout_ids = [str(i) for i in fit_ids], [str(i) for i in heldout_ids]
        for i in fit_ids + heldout_ids:
            if i not in self.captures:
                raise ValueError(f"unknown capture id {i!r}")
        if set(fit_ids) & set(heldout_ids):
            raise ValueError(f"fit and held-out captures overlap: {sorted(set(fit_ids) & set(heldout_ids))}")
        if not fit_ids:
            raise ValueError("no fit captures")
        self.fit_ids, self.heldout_ids = fit_ids, heldout_ids
        self.validation_ids = heldout_ids if heldout_ids else fit_ids
        self.all_ids = fit_ids + heldout_ids
        frames = {}
        for i in self.all_ids:
            if i not in real_depth:
                raise ValueError(f"no real depth for capture {i!r}")
            frames[i] = _check_depth_stack(self.captures[i], real_depth[i])
        self.n_frames = min(d.shape[0] for d in frames.values())
        self.cut_frames = sorted(i for i, d in frames.items() if d.shape[0] > self.n_frames)
        self.simulate, self.fit = simulate, fit
        self.binning, self.config, self.progress = binning, config, progress
        self.seed = int(seed)
        F = self.n_frames
        self.single_frame = F < 2
        self.n_sim_frames = F if F >= 2 else int(n_floor_frames)
        self.real_sampling = frame_sampling(F, seed, n_splits, n_boot)
        self.sim_sampling = frame_sampling(self.n_sim_frames, seed + 1, n_splits if self.single_frame else 0, n_boot)
        self.real_sums = {i: capture_sums(self.captures[i], d[:F], self.real_sampling) for i, d in frames.items()}
        self._sums: dict = {}
        self._floors: dict = {}
        self.n_simulated = 0

    # -- evaluation ---------------------------------------------------------------------------
    def _ensure(self, effects, ids):
        key = _model_key(effects)
        store = self._sums.setdefault(key, {})
        missing = [i for i in ids if i not in store]
        if missing:
            depth = self.simulate(missing, list(effects), self.n_sim_frames)
            for i in missing:
                if i not in depth:
                    raise ValueError(f"simulate returned no depth for capture {i!r}")
                store[i] = capture_sums(self.captures[i], depth[i], self.sim_sampling)
            self.n_simulated += len(missing)
            if self.progress is not None:
                names = "+".join(n for n, _ in effects) or "reference"
                self.progress(f"{names} ({len(missing)} captures)")
        return store

    def floor(self, ids) -> Floor:
        key = tuple(ids)
        if key not in self._floors:
            caps = [self.captures[i] for i in ids]
            keys, real = pool_sums(caps, [self.real_sums[i] for i in ids], self.binning)
            if self.single_frame:
                store = self._ensure([], ids)
                _, fl = pool_sums(caps, [store[i] for i in ids], self.binning)
                self._floors[key] = make_floor(keys, real, self.real_sampling, self.n_sim_frames, fl,
                                               self.sim_sampling)
            else:
                self._floors[key] = make_floor(keys, real, self.real_sampling, self.n_sim_frames)
        return self._floors[key]

    def evaluate(self, effects, ids) -> GapResult:
        """The gap of the model reference + ``effects`` over the captures ``ids``."""
        fl = self.floor(ids)
        store = self._ensure(effects, ids)
        caps = [self.captures[i] for i in ids]
        _, sim = pool_sums(caps, [store[i] for i in ids], self.binning)
        return compare(fl, self.real_sampling, sim, self.sim_sampling, self.config.alpha)

    def forget(self, keep) -> None:
        """Drop cached simulations of models not in ``keep`` (lists of effects)."""
        keys = {_model_key(e) for e in keep} | {_model_key([])}
        for k in list(self._sums):
            if k not in keys:
                del self._sums[k]

    # -- the whole diagnosis ------------------------------------------------------------------
    def run(self, candidates: Sequence[str] = ()) -> DiagnosisResult:
        """Baseline, forward selection over ``candidates`` (effect names) and ablation."""
        cfg = self.config
        b_all = self.evaluate([], self.all_ids)
        b_fit = self.evaluate([], self.fit_ids)
        b_val = self.evaluate([], self.validation_ids)
        baseline = {"gap_fit": b_fit.G, "gap_heldout": b_val.G, "gap_all": b_all.G,
                    "significant": b_all.significant, "p_value": b_all.p_value,
                    "significant_fit": b_fit.significant, "significant_heldout": b_val.significant,
                    "null_gap_p95": float(np.percentile(b_all.floor.null_g, 95)) if b_all.floor.null_g.size else None}
        selected: list = []
        rounds: list = []
        effects_out: list = []
        cur_fit, cur_val = b_fit, b_val
        remaining = list(dict.fromkeys(candidates))
        stop_reason = "no candidate effects" if not remaining else None
        if self.fit is None and remaining:
            stop_reason = "no fit function: baseline only"
            remaining = []
        if remaining and not (b_all.significant or b_fit.significant or b_val.significant):
            stop_reason = "no significant gap: the reference model is within the real-vs-real noise floor"
            remaining = []
        while remaining and len(selected) < cfg.max_effects:
            tried = []
            for name in remaining:
                entry = {"name": name}
                try:
                    params = dict(self.fit(name, list(selected)))
                    model = selected + [(name, params)]
                    r = self.evaluate(model, self.fit_ids)
                except ValueError as exc:          # no usable fit, or parameters the effect refuses
                    entry.update(error=str(exc), gap_fit_after=None, shrink_fit=None)
                    tried.append((entry, None, None))
                    continue
                entry.update(params=params, gap_fit_after=r.G,
                             shrink_fit=1.0 - r.G / cur_fit.G if cur_fit.G > 0 else 0.0)
                tried.append((entry, model, r))
            ok = [t for t in tried if t[2] is not None]
            ok.sort(key=lambda t: t[2].G)
            rnd = {"round": len(rounds) + 1, "gap_fit_before": cur_fit.G, "gap_heldout_before": cur_val.G,
                   "candidates": [t[0] for t in ok] + [t[0] for t in tried if t[2] is None]}
            rounds.append(rnd)
            if not ok or ok[0][2].G >= cur_fit.G:
                stop_reason = "no candidate shrinks the fit gap"
                break
            entry, model, r_fit = ok[0]
            r_val = self.evaluate(model, self.validation_ids)
            test = shrink_test(cur_val, r_val, cfg.alpha)
            big_enough = test["delta"] >= cfg.min_shrink * b_val.G
            rnd["chosen"] = entry["name"]
            rnd["heldout_test"] = {**test, "gap_heldout_after": r_val.G, "min_delta": cfg.min_shrink * b_val.G}
            if not (test["significant"] and big_enough):
                rnd["accepted"] = False
                stop_reason = (f"best candidate {entry['name']} does not shrink the held-out gap significantly "
                               f"(shrinks in {100 * test['fraction']:.0f} % of replicates, by {test['delta']:.3g})")
                break
            rnd["accepted"] = True
            selected = model
            effects_out.append({"name": entry["name"], "params": entry["params"], "gap_fit_after": r_fit.G,
                                "gap_heldout_after": r_val.G,
                                "shrink_heldout": 1.0 - r_val.G / b_val.G if b_val.G > 0 else 0.0,
                                "shrink_test": test})
            prev_fit = cur_fit.G
            cur_fit, cur_val = r_fit, r_val
            if cfg.prune:
                remaining = [t[0]["name"] for t in ok[1:] if t[2].G < prev_fit]
            else:
                remaining = [t[0]["name"] for t in tried if t[0]["name"] != entry["name"]]
            self.forget([selected])
            if not (r_fit.significant or r_val.significant):
                stop_reason = "remaining gap within the real-vs-real noise floor"
                break
            if not remaining:
                stop_reason = "no candidate left that shrank the fit gap"
        if stop_reason is None:
            stop_reason = f"reached the maximum of {cfg.max_effects} effects"
        # ablation: remove each selected effect again
        for i, e in enumerate(effects_out):
            without = selected[:i] + selected[i + 1:]
            r = self.evaluate(without, self.validation_ids)
            test = shrink_test(r, cur_val, cfg.alpha)
            e["ablation"] = {"gap_heldout_without": r.G, "delta": test["delta"], "fraction": test["fraction"],
                             "confirmed": test["significant"]}
        f_all = self.evaluate(selected, self.all_ids)
        final = {"gap_heldout": cur_val.G, "shrink_heldout": 1.0 - cur_val.G / b_val.G if b_val.G > 0 else 0.0,
                 "unexplained_fraction": cur_val.G / b_val.G if b_val.G > 0 else 0.0,
                 "gap_fit": cur_fit.G, "gap_all": f_all.G, "significant": f_all.significant,
                 "p_value": f_all.p_value,
                 "where_unexplained": f_all.entries(self.binning, only_positive=True)}
        report = {"baseline": baseline, "where": b_all.entries(self.binning, only_positive=False),
                  "effects": effects_out, "final": final, "rounds": rounds, "stop_reason": stop_reason,
                  "floor_source": b_all.floor.source, "unavailable": dict(b_all.floor.unavailable),
                  "frames": self.n_frames, "sim_frames": self.n_sim_frames,
                  "validation": "held-out captures" if self.heldout_ids else
                                "fit captures (no held-out capture: shrink is not independent)",
                  "by": {by: aggregate_by(b_all, self.binning, by)
                         for by in ("statistic", "region", "image_cell", "distance_m", "angle_deg")},
                  "by_final": {by: aggregate_by(f_all, self.binning, by)
                               for by in ("statistic", "region", "image_cell", "distance_m", "angle_deg")}}
        if self.cut_frames:
            report["frames_cut"] = {"to": self.n_frames, "captures": self.cut_frames}
        return DiagnosisResult(report, b_all, f_all, b_val, cur_val, list(selected),
                               {i: self.captures[i] for i in self.all_ids})


# ---------------------------------------------------------------------------------------------
# a plane fitted to a region of real frames (captures without a known target)
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PlaneFit:
    """A plane n . X = c in the camera frame fitted to a region of depth frames.

    Attributes
    ----------
    normal : ndarray, shape (3,)
        Unit normal, oriented with c >= 0 [camera frame: x right, y down, z forward].
    offset_m : float
        c [m].
    inliers : ndarray of bool, shape (H, W)
        Pixels of the region within the threshold of the plane in the first frame.
    residual_std_m : float
        Standard deviation of the inliers' distances to the plane [m].
    incidence_deg : float
        Angle between the normal and the optical axis [deg].
    """

    normal: np.ndarray
    offset_m: float
    inliers: np.ndarray
    residual_std_m: float
    incidence_deg: float


def fit_plane(depth_m, K, roi, *, threshold_rel: float = 0.02, iterations: int = 300, seed: int = 0) -> PlaneFit:
    """RANSAC plane through the region's valid pixels of the first frame, refitted by SVD on its inliers.

    Parameters
    ----------
    depth_m : array_like, shape (F, H, W) or (H, W), float
        Depth [m], NaN = no data (only the first frame is used).
    K : array_like, shape (3, 3)
        Intrinsics [px].
    roi : array_like of bool, shape (H, W)
        The region (e.g. a fronto-parallel board or a wall).
    threshold_rel : float
        Inlier threshold as a fraction of the depth (2 %: a few sigma_z at 1-3 m).
    iterations : int
        RANSAC samples.
    seed : int

    Raises
    ------
    ValueError
        Fewer than 100 valid pixels in the region, bad shapes.
    """
    d = np.asarray(depth_m, dtype=np.float64)
    d = d[0] if d.ndim == 3 else d
    if d.ndim != 2:
        raise ValueError(f"depth_m must be (F, H, W) or (H, W), got {np.asarray(depth_m).shape}")
    r = np.asarray(roi)
    if r.shape != d.shape or r.dtype != bool:
        raise ValueError(f"roi must be a boolean image of shape {d.shape}")
    Kc = check_intrinsics(K)
    th = check_positive_scalar(threshold_rel, "threshold_rel", upper=0.5)
    H, W = d.shape
    vv, uu = np.nonzero(r & np.isfinite(d) & (d > 0))
    if vv.size < 100:
        raise ValueError(f"the region has {vv.size} pixels with data; a plane fit needs >= 100")
    z = d[vv, uu]
    P = np.column_stack([(uu - Kc[0, 2]) * z / Kc[0, 0], (vv - Kc[1, 2]) * z / Kc[1, 1], z])
    rng = np.random.default_rng(seed)
    best, best_n = None, -1
    for _ in range(int(iterations)):
        idx = rng.choice(P.shape[0], 3, replace=False)
        a, b, c = P[idx]
        n = np.cross(b - a, c - a)
        nn = np.linalg.norm(n)
        if nn < 1e-12:
            continue
        n /= nn
        inl = np.abs(P @ n - n @ a) < th * z
        cnt = int(inl.sum())
        if cnt > best_n:
            best, best_n = inl, cnt
    if best is None:
        raise ValueError("plane fit failed: the region's points are degenerate")
    for _ in range(2):
        Q = P[best]
        cen = Q.mean(axis=0)
        n = np.linalg.svd(Q - cen, full_matrices=False)[2][-1]
        c = float(n @ cen)
        best = np.abs(P @ n - c) < th * z
    Q = P[best]
    cen = Q.mean(axis=0)
    n = np.linalg.svd(Q - cen, full_matrices=False)[2][-1]
    c = float(n @ cen)
    if c < 0:
        n, c = -n, -c
    dist = P[best] @ n - c
    mask = np.zeros((H, W), dtype=bool)
    mask[vv[best], uu[best]] = True
    return PlaneFit(n, c, mask, float(np.std(dist)), float(np.degrees(np.arccos(min(1.0, abs(n[2]))))))
