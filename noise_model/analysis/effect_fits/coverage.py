"""Fits of the coverage effects: ``invalid_band``, ``dropout``.

* invalid_band: least-squares threshold on the missing fraction against u - f B / z_true less the dark
  margin times the pixel's darkness (the dark margin by a search over a grid).
* dropout: binomial maximum likelihood of P(no data | z, theta), then the blob length from pairs of holes.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import minimize, minimize_scalar
from scipy.special import expit, logit, ndtr, ndtri, owens_t

from ...sim.effects.coverage import DROPOUT_THETA_MAX_RAD
from ._common import _interior, _nominal, _pixels, _roi
from .spec import FitSpec


# ---- invalid_band ---------------------------------------------------------------------------------
#: Grid of dark_margin_px tried by the invalid_band fit [px] (0 to 4 px every 0.05 px, then refined).
_DARK_GRID_PX = np.linspace(0.0, 4.0, 81)
#: The fit only tries a dark margin when some pixel near the band is darker than its frame's level by
#: this much (band_darkness); otherwise dark_margin_px is 0 (the captures cannot tell it).
_DARK_MIN_SPREAD = 0.2


def _band_threshold(cs, a, a0):
    """Least-squares step of the missing fraction over c: (loss, margin, width of the gap the margin is the
    middle of) (see :func:`_fit_invalid_band`)."""
    order = np.argsort(cs, kind="stable")
    cs, a, a0 = cs[order], a[order], a0[order]
    left = np.concatenate([[0.0], np.cumsum((a - 1.0) ** 2)])        # pixels 0..k-1 in the band
    right = np.concatenate([np.cumsum(((a - a0) ** 2)[::-1])[::-1], [0.0]])
    tot = left + right
    tot[1:-1][cs[1:] == cs[:-1]] = np.inf                  # a step only between distinct values of c
    k = int(np.argmin(tot))
    if k == 0:
        margin, width = cs[0] - 0.5, 1.0
    elif k == cs.size:
        margin, width = cs[-1] + 0.5, 1.0
    else:
        margin, width = 0.5 * (cs[k - 1] + cs[k]), cs[k] - cs[k - 1]
    return float(tot[k]), float(margin), float(width)


def _fit_invalid_band(real, base, model, rois=None, **_):
    """Least-squares threshold on the missing fraction, with the dark margin by a search over a grid.

    Every hit pixel has c = u - f B / z_true (columns beyond its own disparity) and a darkness s
    (:func:`noise_model.sim.effects.coverage.band_darkness` of its frame's true depth and angle); the
    effect removes the pixels with c - dark_margin s < margin. For a given dark margin k, over the pixels
    with c < 60 px of all captures, the margin minimising sum (a - 1)^2 over c - k s < margin plus
    sum (a - a0)^2 over the others (a, a0: the pixel's missing fraction over the frames in the real data
    and in the base simulation) is found by sorting c - k s; the estimate is the middle of the gap
    between the two values around the step (never between equal values: pixels of one c are on one
    side). (k, margin) is the centroid of the region of least loss over the grid of k (:data:`_DARK_GRID_PX`,
    then a grid ten times finer around it), each k weighted by the width of its margin's gap: noise-free
    captures whose backgrounds share one disparity fit a whole region equally (each capture's first column
    only bounds margin + k s to one column), and its centroid is the estimate of least expected squared
    error; k = 0 when no pixel is
    darker than :data:`_DARK_MIN_SPREAD` (walls alone: nothing tells k from the margin). Single frames:
    the fractions are 0 or 1 (nothing temporal is used).
    """
    from ...sim.effects.coverage import band_darkness

    cs, ss, a, a0 = [], [], [], []
    for c, b in zip(real, base):
        z, th, _, fb = _nominal(c.geometry, model)
        u = np.arange(c.geometry.width)[None, :]
        with np.errstate(invalid="ignore", divide="ignore"):
            cc = u - fb / z
        m = np.isfinite(cc) & (cc < 60.0)
        if _roi(rois, c.geometry) is not None:
            m &= _roi(rois, c.geometry)
        if not m.any():
            continue
        cs.append(cc[m])
        ss.append(band_darkness(z, th)[m])
        a.append(np.mean(~np.isfinite(_pixels(c, m)), axis=0))
        a0.append(np.mean(~np.isfinite(_pixels(b, m)), axis=0))
    if not cs:
        raise ValueError("invalid_band: no pixel near the left band")
    cs, ss, a, a0 = (np.concatenate(x) for x in (cs, ss, a, a0))
    if not np.any(ss >= _DARK_MIN_SPREAD):
        return {"margin_px": _band_threshold(cs, a, a0)[1], "dark_margin_px": 0.0}

    def best(grid):
        fits = np.array([_band_threshold(cs - k * ss, a, a0) for k in grid])
        tied = fits[:, 0] <= fits[:, 0].min() * (1.0 + 1e-9) + 1e-12
        w = fits[tied, 2]                                 # the centroid of the (k, margin) region that fits best
        return float(np.sum(grid[tied] * w) / np.sum(w)), float(np.sum(fits[tied, 1] * w) / np.sum(w))

    k, _ = best(_DARK_GRID_PX)
    step = float(_DARK_GRID_PX[1] - _DARK_GRID_PX[0])
    k, margin = best(np.unique(np.clip(np.linspace(k - 2 * step, k + 2 * step, 41), 0.0, None)))
    return {"margin_px": margin, "dark_margin_px": k}


# ---- dropout --------------------------------------------------------------------------------------
def _bvn_same(t, rho):
    """P(X < t, Y < t) for a standard bivariate normal with correlation rho (Owen's T)."""
    rho = np.clip(rho, -0.999999, 0.999999)
    a = np.sqrt((1.0 - rho) / (1.0 + rho))
    return ndtr(t) - 2.0 * owens_t(t, a)


#: dropout: the bins' true depths must span this ratio for k_z, and -ln cos(theta) this range (0.1:
#: 0 to 25 deg) for k_theta, to be fitted; otherwise the slope is 0 (the level is fitted alone).
_DROPOUT_Z_RATIO = 1.5
_DROPOUT_X_RANGE = 0.1


def _fit_dropout(real, base, model, rois=None, **_):
    """Binomial maximum likelihood for P(z, theta), then the blob length from pairs of holes.

    1. Per capture and bin of z_true 3 % wide (interior pixels): n pixel-frames, y missing in the real
       data, a0 the missing fraction in the base simulation. P(missing) = 1 - (1 - p)(1 - a0) with
       p = sigmoid(b0 + k_z (z - 1) - k_theta ln cos theta); (b0, k_z, k_theta) by maximum likelihood
       (L-BFGS from a least-squares start on the logits). p_1m = sigmoid(b0).
    2. A pixel is dropped when a Gaussian field g < t = Phi^-1(p), so two pixels h apart are both
       dropped with probability Phi2(t, t; rho(h)), rho(h) = exp(-h^2 / (2 l^2)) (Owen's T). The
       observed fraction of pixel pairs (lags 1, 2, 3 along rows and columns) both missing, per bin,
       is matched by l (bounded 1-D search, least squares weighted by the binomial variance).

    What the captures determine: k_z only when the bins' true depths span a factor
    :data:`_DROPOUT_Z_RATIO`, k_theta only when -ln cos(theta) spans :data:`_DROPOUT_X_RANGE` (0 to
    25 deg); otherwise that slope is fixed at 0 and p_1m is the level seen at the captures' distances
    (or angles), not an extrapolation to 1 m. The coefficients are bounded by the factory's ranges
    (|k| <= 20, p_1m in [1e-9, 1 - 1e-9]): a capture with no hole at all (perfect separation) drives a
    slope to its bound, not to infinity. Single frames: counts over pixels; nothing is temporal (the
    holes of one frame cannot tell static holes from flickering ones: both are the effect's).
    """
    rows = []      # z, x, n, y, a0, per bin
    pair_bins = []  # t-index, per lag: (n_pairs, both)
    per_cap = []
    for c, b in zip(real, base):
        g = c.geometry
        z, th, _, _ = _nominal(g, model)
        m = _interior(g, model, _roi(rois, g))
        if m.sum() < 50:
            continue
        zs = z[m]
        x = -np.log(np.cos(np.minimum(np.abs(th[m]), DROPOUT_THETA_MAX_RAD)))
        miss_r = ~c.has_data()
        miss_b = ~b.has_data()
        # bins 3 % wide in z (P varies little inside one)
        _, binid = np.unique(np.floor(np.log(zs) / 0.03).astype(np.int64), return_inverse=True)
        binid = binid.ravel()
        nbin = int(binid.max()) + 1
        F = c.n_frames
        cnt = np.bincount(binid, minlength=nbin).astype(float)
        yr = np.bincount(binid, weights=miss_r[:, m].sum(axis=0), minlength=nbin)
        yb = np.bincount(binid, weights=miss_b[:, m].sum(axis=0), minlength=nbin)
        zsum = np.bincount(binid, weights=zs, minlength=nbin)
        xsum = np.bincount(binid, weights=x, minlength=nbin)
        keep = cnt >= 10
        newid = np.full(nbin, -1, dtype=np.int64)
        newid[keep] = np.arange(int(keep.sum())) + len(rows)
        for i in np.flatnonzero(keep):
            rows.append((zsum[i] / cnt[i], xsum[i] / cnt[i], cnt[i] * F, yr[i], yb[i] / (cnt[i] * F)))
        binmap = np.full(m.shape, -1, dtype=np.int64)
        binmap[m] = newid[binid]
        per_cap.append((miss_r, binmap))
    if not rows:
        raise ValueError("dropout: no capture with >= 50 interior pixels (bins of >= 10 pixels)")
    R = np.array(rows)
    zb, xb, nb, yb, a0 = R.T
    a0 = np.clip(a0, 0.0, 0.999)
    pobs = np.clip(yb / nb, 0.5 / nb, 1 - 0.5 / nb)
    p0 = np.clip(1.0 - (1.0 - pobs) / (1.0 - a0), 1e-4, 1 - 1e-4)
    X = np.column_stack([np.ones_like(zb), zb - 1.0, xb])
    free = np.array([True, zb.max() / zb.min() >= _DROPOUT_Z_RATIO and len(rows) >= 3,
                     np.ptp(xb) >= _DROPOUT_X_RANGE and len(rows) >= 3])
    if free.all():
        Xf = X
    else:
        Xf = X[:, free]
    w = np.sqrt(nb * p0 * (1 - p0))
    bf0 = np.linalg.lstsq(Xf * w[:, None], logit(p0) * w, rcond=None)[0]
    lim = np.array([logit(1 - 1e-9), 20.0, 20.0])[free]
    bf0 = np.clip(bf0, -lim, lim)

    def nll(bf):
        p = expit(Xf @ bf)
        P = np.clip(1.0 - (1.0 - p) * (1.0 - a0), 1e-12, 1 - 1e-12)
        return -float(np.sum(yb * np.log(P) + (nb - yb) * np.log1p(-P)))

    if free.all():
        res = minimize(nll, bf0, method="L-BFGS-B")
        bf = res.x if res.success or res.fun <= nll(bf0) else bf0
        if not np.all(np.abs(bf) <= lim):          # a separated design: keep the slopes in range
            res = minimize(nll, bf0, method="L-BFGS-B", bounds=list(zip(-lim, lim)))
            bf = res.x if res.success or res.fun <= nll(bf0) else bf0
    else:
        res = minimize(nll, bf0, method="L-BFGS-B", bounds=list(zip(-lim, lim)))
        bf = res.x if res.success or res.fun <= nll(bf0) else bf0
    beta = np.zeros(3)
    beta[free] = bf
    # 2. length from pairs of holes
    tfull = ndtri(np.clip(expit(X @ beta), 1e-9, 1 - 1e-9))       # threshold per bin (row of R)
    nbins = tfull.size
    obs, npairs, tt, lags = [], [], [], []
    for miss_r, binmap in per_cap:
        for h in (1, 2, 3):
            for axis in (1, 2):
                if axis == 2:
                    b1, b2 = binmap[:, :-h], binmap[:, h:]
                    m1, m2 = miss_r[:, :, :-h], miss_r[:, :, h:]
                else:
                    b1, b2 = binmap[:-h, :], binmap[h:, :]
                    m1, m2 = miss_r[:, :-h, :], miss_r[:, h:, :]
                ok = (b1 >= 0) & (b1 == b2)
                if not ok.any():
                    continue
                both = (m1 & m2)[:, ok].sum(axis=0)              # per pair over frames
                ids = b1[ok]
                cnt = np.bincount(ids, minlength=nbins) * miss_r.shape[0]
                bsum = np.bincount(ids, weights=both, minlength=nbins)
                sel = (cnt > 0) & np.isfinite(tfull)
                obs.append(bsum[sel] / cnt[sel])
                npairs.append(cnt[sel])
                tt.append(tfull[sel])
                lags.append(np.full(int(sel.sum()), float(h)))
    if not obs or sum(a.size for a in obs) == 0:
        raise ValueError("dropout: no pair of neighbouring interior pixels for the blob length")
    obs, npairs, tt, lags = (np.concatenate(a) for a in (obs, npairs, tt, lags))

    def loss(logl):
        ell = math.exp(logl)
        pred = _bvn_same(tt, np.exp(-lags ** 2 / (2 * ell * ell)))
        var = np.maximum(pred * (1 - pred), 1e-6) / npairs
        return float(np.sum((obs - pred) ** 2 / var))

    r = minimize_scalar(loss, bounds=(math.log(0.3), math.log(40.0)), method="bounded",
                        options={"xatol": 1e-4})
    return {"p_1m": float(expit(beta[0])), "k_z": float(beta[1]), "k_theta": float(beta[2]),
            "length_px": float(math.exp(r.x))}


#: Registry records (:class:`~.spec.FitSpec`) of this module's fits.
SPECS = (
    # planar targets at several distances: the 0.5 px tolerance is the step between consecutive values
    # of c = u - f B / z, which several distances make fine
    # the dark margin needs pixels near the band darker than their frame's level (a far background
    # beside a nearer board): the self-test draws it on boards before a background. Their backgrounds
    # share one disparity, so each board's first column bounds margin + dark_margin s to one column, and
    # the darkest and the brightest board (s 0.92 and 0.05) leave the dark margin within 1 / (0.92 - 0.05)
    # = 1.15 px of the centroid: its tolerance is that bound, not a multiple of the errors seen
    FitSpec("invalid_band", _fit_invalid_band, needs=("wall", "board", "board+background"),
            tolerance={"margin_px": ("abs", 0.5), "dark_margin_px": ("abs", 1.2)},
            tolerance_single_frame={"margin_px": ("abs", 0.5), "dark_margin_px": ("abs", 1.2)}),
    # needs angles up to >= 45 deg too: k_theta is poorly determined by angles up to 30 deg alone
    FitSpec("dropout", _fit_dropout, needs=("wall", "board"),
            tolerance={"p_1m": ("rel", 0.1), "k_z": ("abs", 0.1), "k_theta": ("abs", 0.2), "length_px": ("rel", 0.1)},
            tolerance_single_frame={"p_1m": ("rel", 0.06), "k_z": ("abs", 0.07), "k_theta": ("abs", 0.3),
                                    "length_px": ("rel", 0.4)}),
)
