"""Normalised gaps: the real-vs-real noise floor, real against one simulated model, the shrink test.

For a statistic s (:mod:`.sums`) and stratum k, d = |s_real - s_sim| (for ``residual_w1``: the W1
distance itself). The noise floor sigma_0 is the root mean square of d between two random halves of the
*real* frames (``n_splits`` random half-splits), scaled from half-size to full-size samples by
kappa = sqrt((1/F_real + 1/F_sim) / (1/n_A + 1/n_B)), and never below the statistic's resolution
:data:`MIN_FLOOR`. The normalised gap is::

    gap = max(0, d / sigma_0 - Z_FLOOR)        (Z_FLOOR = 2)

0 means real and sim are as close as two halves of the real data are to each other, within the 95 %
band of real-vs-real differences; 1 means one more floor sigma beyond that band.

Aggregate gap G: the mean over statistics of the mean over that statistic's strata (each statistic
weighs the same). Significance of the baseline: G_real_vs_sim is compared with G computed for each
real-vs-real half-split (leave-one-out floor); significant when it exceeds their (1 - alpha) quantile
and :data:`MIN_SIGNIFICANT_GAP`. The floor's own estimation noise (it comes from F frames) makes
d / sigma_0 t-distributed; sigma_0 is scaled by sqrt(df / (df - 2)), df = F - 1, so that E z^2 = 1
under the null. A single-frame capture set has no real-vs-real floor: it is taken from the reference
simulation instead (sim-vs-sim halves of ``n_floor_frames`` simulated frames), and the report says so.

Whether a model change helped is a paired bootstrap over frames (:func:`shrink_test`): replicate b
draws the same frames for the real data and, with common random numbers, for both models.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .strata import Binning
from .sums import STATISTICS, FrameSampling, statistic_values, wasserstein1_hist

__all__ = ["MIN_FLOOR", "Z_FLOOR", "MIN_SIGNIFICANT_GAP", "Z_CAP", "Floor", "make_floor", "GapResult", "compare",
           "shrink_test", "aggregate_by", "realisation_variance"]

#: Smallest noise floor of each statistic (its practical resolution): a difference smaller than this
#: is not worth a model change, however many pixels measured it. [units of the statistic]
MIN_FLOOR = {"bias_m": 1e-4, "temporal_std_m": 5e-5, "spatial_std_m": 5e-5, "corr_length_px": 0.02,
             "lattice": 0.005, "fill_rate": 0.002, "residual_w1": 0.01, "tail_rate": 2e-4}
#: Multiples of the floor that count as "as close as two halves of the real data" (95 % band).
Z_FLOOR = 2.0
#: A baseline aggregate gap below this is never called significant (practical threshold).
MIN_SIGNIFICANT_GAP = 0.05

_W1 = STATISTICS.index("residual_w1")
#: :data:`MIN_FLOOR` as an array over :data:`STATISTICS`.
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
               floor_pooled=None, floor_sampling: FrameSampling | None = None, exclude=None,
               exclude_reason: str = "") -> Floor:
    """The noise floor from split halves of the real frames (or, for single-frame real data, of a
    reference simulation: ``floor_pooled`` with its ``floor_sampling``).

    kappa scales the RMS difference between halves of h frames to the expected difference between
    F_real real and F_sim simulated frames: kappa = sqrt((1/F_real + 1/F_sim) / (2/h)).

    ``exclude`` (bool (len(STATISTICS), len(keys)), optional) marks entries that are not computed
    (e.g. the bias of strata holding captures whose geometry was fitted to their own frames, where
    the fit absorbs it); a statistic excluded everywhere is listed as unavailable with ``exclude_reason``.
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
    # freedom: E[(d / sigma0)^2] = df / (df - 2), not 1. Scale that back out.
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
    excluded = np.zeros(defined.shape, dtype=bool) if exclude is None else np.asarray(exclude, dtype=bool)
    if excluded.shape != defined.shape:
        raise ValueError(f"exclude must have shape {defined.shape}, got {excluded.shape}")
    defined &= ~excluded
    w = _weights(defined)
    g_null = (w[None] * np.where(defined[None] & np.isfinite(z_null), np.maximum(z_null - Z_FLOOR, 0.0), 0.0)
              ).sum(axis=(1, 2))
    unavailable = {}
    for s, name in enumerate(STATISTICS):
        if not defined[s].any():
            if excluded[s].any() and not (np.isfinite(rv[0, s]) & np.isfinite(sigma0[s]) & ~excluded[s]).any():
                unavailable[name] = exclude_reason or "not computed"
            elif name == "temporal_std_m" and real_sampling.n_frames < 2:
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


def realisation_variance(keys, sim_pooled: np.ndarray, other_pooled: np.ndarray) -> np.ndarray:
    """Variance of the bias over the realisations of a model's static fields, per stratum.

    A static field (a pattern drawn once per capture) makes the bias of an image cell the field's mean
    over the cell: a value of its realisation, whose expectation is 0. Two halves of the real frames
    share the real field, so the noise floor does not hold this spread, and a model whose field is
    right in every statistical respect still differs from the real data by it. Two simulations of the
    model that differ only in the fields' realisation (``sim_pooled``, ``other_pooled``; same frame
    noise) give (v1 - v2)^2 / 2 per stratum, averaged over the local strata (image cells, regions) of
    each (distance, angle) bin to steady the one-pair estimate. Only the bias gets it: the other
    statistics (spreads, correlation, histograms) depend on the realisation to second order only, and
    widening their floor would let a too strong field hide its own misfit.

    Returns
    -------
    ndarray, shape (n_stats, K)
        Variance in the statistic's units: the bias row, 0 elsewhere and where undefined.
    """
    v1, h1 = statistic_values(sim_pooled[:1])
    v2, h2 = statistic_values(other_pooled[:1])
    r = 0.5 * _distances(v1, h1, v2, h2)[0] ** 2
    r = np.where(np.isfinite(r), r, np.nan)
    out = np.zeros(r.shape)
    groups: dict = {}
    for k, key in enumerate(keys):
        groups.setdefault(tuple(key[:2]), []).append(k)
    b = STATISTICS.index("bias_m")
    for idx in groups.values():
        v = r[b, idx]
        out[b, idx] = float(np.mean(v[np.isfinite(v)])) if np.isfinite(v).any() else 0.0
    return out


def compare(floor: Floor, real_sampling: FrameSampling, sim_pooled: np.ndarray, sim_sampling: FrameSampling,
            alpha: float = 0.05, extra_var: np.ndarray | None = None) -> GapResult:
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
    extra_var : ndarray, shape (n_stats, K), optional
        A spread of the model's own beyond the noise floor, added to sigma0^2 (e.g. the variance over
        the realisations of its static fields, :func:`realisation_variance`).
    """
    sv, sh = statistic_values(sim_pooled)
    rv, rh = floor.real_values, floor.real_hist
    defined, sig0 = floor.defined, floor.sigma0
    if extra_var is not None:
        sig0 = np.sqrt(sig0 ** 2 + np.asarray(extra_var))

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

