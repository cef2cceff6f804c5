"""The gap statistics of a capture: per-frame sums (numba kernel + NumPy reference), frame weights, pooling.

Statistics (per stratum, see :mod:`.strata`; r = z - z_true [m] on pixels with data where the geometry
has a surface, u = r / sigma_z the residual in units of the paper's sigma; the moments and
correlations use the core values |u| <= :data:`CORE_SIGMAS`, the tails are left to ``tail_rate`` and
``residual_w1``). The E-numbers are the sections of docs/depth-effects.md each statistic detects.

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

Frames are resampled, never pixels: every statistic is a ratio of sums that are linear in per-frame
weights (or, for the temporal standard deviation, a quadratic form over frame pairs), so a half-split
or a bootstrap replicate is just another row of frame weights (:class:`FrameSampling`). One pass over a
capture's frames (:func:`capture_sums`) gives every row's sums; :func:`pool_sums` adds captures into
global strata and :func:`statistic_values` turns the sums into the statistics.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ...numba_config import JIT
from .strata import N_LOCAL, REGION_LOCAL, REGION_ORDER, Binning, GapCapture

__all__ = ["STATISTICS", "STAT_UNITS", "LAGS_PX", "LATTICE_STEPS_PER_PX", "TAIL_SIGMAS", "CORE_SIGMAS",
           "HIST_EDGES", "HIST_CENTRES", "N_COLS", "MIN_COUNT", "FrameSampling", "frame_sampling",
           "check_depth_stack", "capture_sums", "capture_sums_reference", "pool_sums", "statistic_values",
           "wasserstein1_hist"]

#: The statistics, in report order.
STATISTICS = ("bias_m", "temporal_std_m", "spatial_std_m", "corr_length_px", "lattice", "fill_rate",
              "residual_w1", "tail_rate")
#: Units of each statistic's real / sim values.
STAT_UNITS = {"bias_m": "m", "temporal_std_m": "m", "spatial_std_m": "m", "corr_length_px": "px",
              "lattice": "1", "fill_rate": "1", "residual_w1": "sigma_z", "tail_rate": "1"}

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

# columns of the per-frame linear sums: pixels with a surface, with data, sum r, sum r^2, the spatial
# quadratic form and its degrees of freedom, sum cos(lattice phase), core pixels
_C_NGEOM, _C_NVALID, _C_SR, _C_SR2, _C_QSP, _C_DFSP, _C_COS, _C_NCORE = range(8)
_C_P = 8                                  # 8 columns: P(u, h) for h in LAGS, then P(v, h)
_C_Q = _C_P + 2 * len(LAGS_PX)            # 8 columns: Q likewise
_C_HIST = _C_Q + 2 * len(LAGS_PX)
_N_LIN = _C_HIST + _NB
# columns after applying frame weights: the linear ones, then the temporal quadratic forms
_C_TD = _N_LIN
_C_TN = _N_LIN + 1
N_COLS = _N_LIN + 2

#: Fewest pixel-frames (or pixel pairs) for a statistic to be defined in a stratum.
MIN_COUNT = 100


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
    """Boundaries [0, n/3, 2n/3, n] (rounded) of the 3 image cells along an axis of n pixels."""
    return np.array([0, int(round(n / 3)), int(round(2 * n / 3)), n], dtype=np.int64)


def check_depth_stack(cap: GapCapture, depth_m) -> np.ndarray:
    """``depth_m`` as an array after checking it is a float stack (F >= 1, H, W) of metres matching ``cap``.

    Raises
    ------
    ValueError
        Wrong shape, no frames, integer depth, values that cannot be metres (> 100).
    """
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
    for g, k in REGION_LOCAL.items():
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
    lin = np.zeros((F, N_LOCAL, _N_LIN))

    def add(col, values, mask=None):
        for lab in labels:
            for k in range(N_LOCAL):
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
    D = np.zeros((N_LOCAL, F, F))
    N = np.zeros((N_LOCAL, F, F))
    for lab in labels:
        for k in range(N_LOCAL):
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
_NREG1 = len(REGION_ORDER) + 1
_NBUCKET = 9 * _NREG1
#: Row blocks of the kernel's pair matrices (fixed, so that the sums do not depend on the thread count).
_N_ROW_BLOCKS = 16
#: Slots of the kernel's per-frame table of lattice cosines by depth value (a power of 2).
_COS_SLOTS_LOG2 = 14
_COS_HASH_MUL = np.uint64(0x9E3779B97F4A7C15)          # Fibonacci hashing of the depth's bit pattern
_COS_HASH_SHIFT = np.uint64(64 - _COS_SLOTS_LOG2)


def _bucket_runs(bucket: np.ndarray, geom: np.ndarray, n_blocks: int = _N_ROW_BLOCKS):
    """Runs of pixels with a surface and the same bucket along each image row, in raster order.

    Parameters
    ----------
    bucket : ndarray, shape (H, W), int
        Bucket of each pixel (>= 0).
    geom : ndarray, shape (H, W), bool
        Pixels with a surface (the others belong to no run).
    n_blocks : int
        Row blocks: rows [H b / n_blocks, H (b + 1) / n_blocks) form block b.

    Returns
    -------
    run_y, run_x0, run_x1, run_k : ndarray, shape (R,), int64
        Row, first column, one past the last column, bucket of each run.
    block_runs : ndarray, shape (n_blocks + 1,), int64
        The runs of block b are ``block_runs[b]:block_runs[b + 1]``.
    """
    H, W = bucket.shape
    flat = np.where(geom, bucket, -1).ravel()
    start = np.ones(flat.size, dtype=bool)
    start[1:] = flat[1:] != flat[:-1]
    start[::W] = True                                     # a run never crosses a row end
    first = np.flatnonzero(start)
    end = np.append(first[1:], flat.size)
    keep = flat[first] >= 0
    first, end = first[keep], end[keep]
    run_y, run_x0 = first // W, first % W
    row_of_block = (H * np.arange(n_blocks + 1)) // n_blocks
    block_runs = np.searchsorted(run_y, row_of_block, side="left")
    return (run_y.astype(np.int64), run_x0.astype(np.int64), (run_x0 + end - first).astype(np.int64),
            flat[first].astype(np.int64), block_runs.astype(np.int64))


@njit(**JIT)
def _pair_sums(a, va, b, vb, n):  # pragma: no cover - compiled
    """sum a_i b_i and sum (a_i^2 vb_i + b_i^2 va_i) over i < n (a, b zero where va, vb are 0)."""
    sp = 0.0
    sq = 0.0
    for i in range(n):
        sp += a[i] * b[i]
        sq += a[i] * a[i] * vb[i] + b[i] * b[i] * va[i]
    return sp, sq


@njit(parallel=True, **JIT)
def _frame_sums_kernel(z, zbits, zt, inv_sig, run_y, run_x0, run_x1, run_k, block_runs, nreg1, phase_k, edges,
                       lags, core_sig, lin, D, N):  # pragma: no cover - compiled
    """numba: per-frame sums lin (F, B, _N_LIN) and pair matrices D, N (B, F, F) per bucket (zeroed by
    the caller); B buckets = (cell, region) pairs, bucket k in cell k // nreg1, so each pixel is
    accumulated once (the strata are sums of buckets, formed by the caller). Columns _C_QSP, _C_DFSP
    are left 0 (they are not linear in the buckets). See :func:`_frame_sums_reference`.

    The pixels are visited as runs (:func:`_bucket_runs`: along a row, the same bucket): each run's
    sums are formed in local variables and added to its bucket once, and the lag and pair sums are
    loops over a run's contiguous pixels, which the compiler vectorises. ``zbits`` is ``z`` viewed as
    uint64: a per-frame direct-mapped table keyed by the depth value holds the lattice cosine of the
    depth values met before (depth in depth units takes few distinct values); a cached entry is used
    only when its depth equals the pixel's exactly, so every cosine is the one computed for that depth.

    Frames are independent (prange over frames, each writes its own lin[f]); the pair matrices are
    summed over row blocks (``block_runs``), one partial result per block, then reduced in block
    order, so the result does not depend on the thread count.
    """
    F, H, W = z.shape
    B = lin.shape[1]
    nlag = lags.shape[0]
    nrun = run_y.shape[0]
    nb = edges.shape[0] + 1
    e0 = edges[0]
    e1 = edges[nb - 2]
    inv_step = (nb - 2) / (e1 - e0)
    two_pi = 2.0 * math.pi
    nslot = 1 << _COS_SLOTS_LOG2
    for f in prange(F):
        u = np.zeros((H, W))
        vf = np.zeros((H, W))                            # 1.0 where u holds a core value
        csum = np.zeros(9)
        ccnt = np.zeros(9)
        table = np.zeros((nslot, 2))                    # (depth, cosine); depth -1 = empty
        table[:, 0] = -1.0
        lf = lin[f]
        for i in range(nrun):
            y = run_y[i]
            x0 = run_x0[i]
            x1 = run_x1[i]
            k = run_k[i]
            s_valid = 0.0
            s_cos = 0.0
            s_core = 0.0
            s_r = 0.0
            s_r2 = 0.0
            s_u = 0.0
            for x in range(x0, x1):
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
                s_valid += 1.0
                slot = np.intp((zbits[f, y, x] * _COS_HASH_MUL) >> _COS_HASH_SHIFT)
                if table[slot, 0] == zz:
                    cs = table[slot, 1]
                else:
                    t = phase_k / zz                                 # disparity in lattice steps
                    cs = math.cos(two_pi * (t - math.floor(t)))
                    table[slot, 0] = zz
                    table[slot, 1] = cs
                s_cos += cs
                lf[k, _C_HIST + b] += 1.0
                if abs(uu) > core_sig:                       # a tail value: only fill, lattice, histogram
                    continue
                vf[y, x] = 1.0
                u[y, x] = uu
                s_u += uu
                s_core += 1.0
                s_r += r
                s_r2 += r * r
            lf[k, _C_NGEOM] += x1 - x0
            lf[k, _C_NVALID] += s_valid
            lf[k, _C_COS] += s_cos
            lf[k, _C_NCORE] += s_core
            lf[k, _C_SR] += s_r
            lf[k, _C_SR2] += s_r2
            c = k // nreg1
            csum[c] += s_u
            ccnt[c] += s_core
        for c in range(9):
            if ccnt[c] > 0:
                csum[c] = csum[c] / ccnt[c]
        for i in range(nrun):                                # u minus its cell's mean, in place
            y = run_y[i]
            mean = csum[run_k[i] // nreg1]
            for x in range(run_x0[i], run_x1[i]):
                if vf[y, x] != 0.0:
                    u[y, x] -= mean
        for i in range(nrun):                                # lag products: the pair belongs to (y, x)'s bucket
            y = run_y[i]
            x0 = run_x0[i]
            x1 = run_x1[i]
            k = run_k[i]
            ua = u[y, x0:x1]
            va = vf[y, x0:x1]
            for j in range(nlag):
                h = lags[j]
                xe = min(x1, W - h)
                if xe > x0:                                  # along u: (y, x) with (y, x + h)
                    sp, sq = _pair_sums(ua, va, u[y, x0 + h:xe + h], vf[y, x0 + h:xe + h], xe - x0)
                    lf[k, _C_P + j] += sp
                    lf[k, _C_Q + j] += 0.5 * sq
                if y + h < H:                                # along v: (y, x) with (y + h, x)
                    sp, sq = _pair_sums(ua, va, u[y + h, x0:x1], vf[y + h, x0:x1], x1 - x0)
                    lf[k, _C_P + nlag + j] += sp
                    lf[k, _C_Q + nlag + j] += 0.5 * sq
    if F < 2:
        return
    nblk = block_runs.shape[0] - 1
    Dp = np.zeros((nblk, B, F, F))
    Np = np.zeros((nblk, B, F, F))
    for bk in prange(nblk):
        rr = np.zeros((F, W))                 # a run's core residuals per frame, 0 elsewhere
        vv = np.zeros((F, W))                 # 1.0 where rr holds a core residual
        cnt = np.zeros(W)
        for i in range(block_runs[bk], block_runs[bk + 1]):
            y = run_y[i]
            x0 = run_x0[i]
            n = run_x1[i] - x0
            k = run_k[i]
            for x in range(n):
                cnt[x] = 0.0
            for f in range(F):
                for x in range(n):
                    zz = z[f, y, x0 + x]
                    ok = False
                    rf = 0.0
                    if zz > 0.0:
                        rf = zz - zt[y, x0 + x]
                        ok = abs(rf * inv_sig[y, x0 + x]) <= core_sig
                    rr[f, x] = rf if ok else 0.0
                    vv[f, x] = 1.0 if ok else 0.0
                    cnt[x] += 1.0 if ok else 0.0
            nfull = 0
            for x in range(n):
                if cnt[x] == F:
                    nfull += 1
            Dc = Dp[bk, k]
            Nc = Np[bk, k]
            if nfull == n:                    # every pixel of the run pairs every frame with every other
                for a in range(F):
                    for b in range(a + 1, F):
                        s = 0.0
                        for x in range(n):
                            dd = rr[a, x] - rr[b, x]
                            s += dd * dd
                        Dc[a, b] += s
                        Nc[a, b] += n
            else:                             # pairs of frames where both have a core value
                for a in range(F):
                    for b in range(a + 1, F):
                        s = 0.0
                        s_n = 0.0
                        for x in range(n):
                            w = vv[a, x] * vv[b, x]
                            dd = rr[a, x] - rr[b, x]
                            s += dd * dd * w
                            s_n += w
                        Dc[a, b] += s
                        Nc[a, b] += s_n
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
    reg1 = np.zeros((H, W), dtype=np.int64)                 # 0: no region, 1 + i: REGION_ORDER[i]
    for i, g in enumerate(REGION_ORDER):
        reg1[cap.regions == g] = 1 + i
    run_y, run_x0, run_x1, run_k, block_runs = _bucket_runs(cell * _NREG1 + reg1, geom)
    zt = np.where(geom, cap.z_true_m, 0.0)
    inv_sig = np.where(geom, 1.0 / np.where(geom, cap.sigma_m, 1.0), 0.0)
    lin_b = np.zeros((F, _NBUCKET, _N_LIN))
    D_b = np.zeros((_NBUCKET, F, F))
    N_b = np.zeros((_NBUCKET, F, F))
    z = np.ascontiguousarray(depth_m, dtype=np.float64)
    _frame_sums_kernel(z, z.view(np.uint64), zt, inv_sig, run_y, run_x0, run_x1, run_k, block_runs, _NREG1,
                       LATTICE_STEPS_PER_PX * cap.fb_px_m, HIST_EDGES, np.asarray(LAGS_PX, dtype=np.int64),
                       CORE_SIGMAS, lin_b, D_b, N_b)
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
    d = check_depth_stack(cap, depth_m)
    if sampling.n_frames != d.shape[0]:
        raise ValueError(f"capture {cap.id!r}: {d.shape[0]} frames but the sampling is for {sampling.n_frames}")
    lin, D, N = _frame_sums_fast(cap, d)
    return _apply_rows(lin, D, N, sampling.weights)


def capture_sums_reference(cap: GapCapture, depth_m, sampling: FrameSampling) -> np.ndarray:
    """:func:`capture_sums` computed stratum by stratum with boolean masks (slow; for the tests)."""
    d = check_depth_stack(cap, depth_m)
    lin, D, N = _frame_sums_reference(cap, d)
    return _apply_rows(lin, D, N, sampling.weights)


# ---------------------------------------------------------------------------------------------
# strata across captures
# ---------------------------------------------------------------------------------------------
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
    keys = sorted({(d, a, k) for d, a in bins for k in range(N_LOCAL)})
    index = {key: i for i, key in enumerate(keys)}
    pooled = np.zeros((R, len(keys), N_COLS))
    for (d, a), s in zip(bins, sums):
        if s.shape[0] != R:
            raise ValueError("all captures' sums must have the same rows of frame weights")
        idx = [index[(d, a, k)] for k in range(N_LOCAL)]
        pooled[:, idx, :] += s
    return keys, pooled


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

