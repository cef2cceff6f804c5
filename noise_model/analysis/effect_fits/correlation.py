"""Fits of the correlated effects: ``correlated_noise``, ``static_pattern``, ``static_noise``.

Both fit A exp(-h^2 / (2 l^2)) to the excess (real minus base) lag covariance of a residual
(:func:`fit_gaussian_cov`): correlated_noise that of the per-frame residual about the temporal mean
(which removes everything static), static_pattern that of the temporal-mean residual (which keeps only
what is static). On single frames both read the frame's residual about its best plane, and cannot tell
one from the other.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ...d435 import axial_sigma_unchecked
from ...numba_config import JIT
from ._common import _base_sigma_model, _interior, _median, _nominal, _plane_residual, _roi, _temporal_median
from .spec import FitSpec


# ---- lag covariances ------------------------------------------------------------------------------
@njit(**JIT)
def _row_dot(a, b, n):  # pragma: no cover - compiled
    """sum a_i b_i over i < n, in float64."""
    s = 0.0
    for i in range(n):
        s += np.float64(a[i]) * np.float64(b[i])
    return s


@njit(**JIT)
def _lag_sums_kernel(x, lags, out):  # pragma: no cover - compiled
    """numba: :func:`_lag_sums_reference` into ``out`` (zeroed by the caller), row by row: each row's
    products with the rows h below and with itself shifted by h, for every lag while the rows are in cache."""
    F, H, W = x.shape
    for f in range(F):
        for y in range(H):
            row = x[f, y]
            for j in range(lags.shape[0]):
                h = lags[j]
                if h == 0:
                    out[j] += _row_dot(row, row, W)
                    continue
                s = 0.0
                if h < W:
                    s += _row_dot(row[:W - h], row[h:], W - h)
                if y + h < H:
                    s += _row_dot(row, x[f, y + h], W)
                out[j] += s


def _lag_sums_reference(x, lags) -> np.ndarray:
    """Sum over frames and pixels of x_p x_{p+h} for pixel pairs h apart along rows and along columns
    (x_p^2 once for h = 0), per lag h of ``lags``; x (F, H, W) float (float64 products)."""
    out = []
    for h in lags:
        if h == 0:
            out.append(float(np.einsum("ijk,ijk->", x, x, dtype=np.float64)))
        else:
            s = float(np.einsum("ijk,ijk->", x[:, :, h:], x[:, :, :-h], dtype=np.float64))
            s += float(np.einsum("ijk,ijk->", x[:, h:, :], x[:, :-h, :], dtype=np.float64))
            out.append(s)
    return np.array(out)


def _lag_sums(x, lags) -> np.ndarray:
    """:func:`_lag_sums_reference` by the numba kernel: (len(lags),) float64, lags non-negative integers."""
    lg = np.asarray(lags, dtype=np.int64)
    out = np.zeros(lg.size)
    _lag_sums_kernel(np.ascontiguousarray(x), lg, out)
    return out


def lag_cov(x, mask, lags):
    """Mean of x_p x_{p+h} over frames and over pixel pairs h apart (rows and columns) both in mask and
    finite in x (F, H, W); returns (cov (len(lags),), n_pairs).

    The products are summed row by row (:func:`_lag_sums`, no product image is made), and when every
    frame has the same valid pixels the pairs are counted once on one frame and multiplied by F.
    """
    valid = np.isfinite(x) & mask[None]
    xf = np.where(valid, x, 0.0)
    F = x.shape[0]
    if F == 1 or bool((valid == valid[:1]).all()):
        vf, mult = valid[:1].astype(np.float64), float(F)
    else:
        vf, mult = valid.astype(np.float64), 1.0
    s = _lag_sums(xf, lags)
    n = mult * _lag_sums(vf, lags)
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = np.where(n > 0, s / np.where(n > 0, n, 1.0), np.nan)
    return cov, n


def fit_gaussian_cov(lags, excess, weights=None, lmin=0.3, lmax=60.0):
    """A exp(-h^2 / (2 l^2)) fitted to excess covariances (grid in l, A in closed form, A >= 0)."""
    lags = np.asarray(lags, dtype=float)
    w = np.ones_like(lags) if weights is None else np.asarray(weights, dtype=float)
    best = (np.inf, 0.0, 1.0)
    for ell in np.exp(np.linspace(math.log(lmin), math.log(lmax), 400)):
        rho = np.exp(-lags ** 2 / (2 * ell * ell))
        A = max(float(np.sum(w * excess * rho) / np.sum(w * rho * rho)), 0.0)
        sse = float(np.sum(w * (excess - A * rho) ** 2))
        if sse < best[0]:
            best = (sse, A, ell)
    return best[1], best[2]


def typical_capture_fit(rows, lags, use=slice(None), lmin=0.5, lmax=80.0):
    """A exp(-h^2 / (2 l^2)) of the typical capture: each capture's excess covariance fitted on its own
    (:func:`fit_gaussian_cov`), then the median over captures of A and of l.

    A static error whose size the effect cannot express varies from capture to capture (on a physical
    D435 it grows with the incidence angle and the disparity gradient, several-fold at 60-75 deg): a
    covariance pooled by pair counts is a mean of variances, dominated by the few captures where it is
    largest, and gives every capture a field larger than most of them show. The median over captures
    is the size of the typical capture (the one a median over captures of the direct measurement
    compares with) and equals the pooled one when the field is the same in every capture. Lengths of
    captures with no excess (A = 0, where l is undefined) are left out of the length's median.

    Parameters
    ----------
    rows : sequence of (excess, pairs)
        Per capture, the excess lag covariance (len(lags),) and its pair counts; captures with a
        non-finite excess at a lag of ``use`` are left out.
    lags : array (L,)
        Lags [px].
    use : slice or index array
        The lags fitted (lag 0 is left out where white noise adds to it).
    lmin, lmax : float
        Range of l [px].

    Returns
    -------
    (A, l) : float, float
        A >= 0 in the excess's units; (0, lmin) when no capture qualifies.
    """
    lags = np.asarray(lags, dtype=float)
    amps, lengths = [], []
    for exc, n in rows:
        e, w = np.asarray(exc, dtype=float)[use], np.asarray(n, dtype=float)[use]
        if not (np.all(np.isfinite(e)) and np.all(w > 0)):
            continue
        A, ell = fit_gaussian_cov(lags[use], e, lmin=lmin, lmax=lmax)
        amps.append(A)
        if A > 0:
            lengths.append(ell)
    if not amps:
        return 0.0, float(lmin)
    return float(np.median(amps)), float(np.median(lengths)) if lengths else float(lmin)


# ---- correlated_noise -----------------------------------------------------------------------------
_CORR_LAGS = (0, 1, 2, 3, 4, 6, 8, 11)
#: Frames whose lag products the correlated-noise fit averages (the temporal mean uses all of them).
_CORR_FRAMES = 6


def _lag_cov_masked(x, w, lags):
    """:func:`lag_cov` for x (F, H, W) that is 0 where the weights w (F, H, W) (0/1, float32) are 0."""
    s = _lag_sums(x, lags)
    n = _lag_sums(w, lags)
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = np.where(n > 0, s / np.where(n > 0, n, 1.0), np.nan)
    return cov, n


def _standardised_residuals(c, m, sig, nf):
    """(z - temporal mean) / sigma over the first nf frames at the mask's pixels, values more than 8
    sigma from the pixel's temporal median left out (0, weight 0) and the mean taken without them;
    returns (x, w) float32 (nf, H, W)."""
    z = c.depth_m
    med = _temporal_median(z)
    with np.errstate(invalid="ignore"):
        keep = (np.abs(z - med) <= 8.0 * sig) & m[None]
    n = keep.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(keep, z, 0.0).sum(axis=0) / np.maximum(n, 1)
    k = keep[:nf]
    x = np.where(k, (z[:nf] - mean) / sig, 0.0).astype(np.float32)
    return x, k.astype(np.float32)


def _remove_frame_offset(x, w, q):
    """x (F, H, W) less, per frame, its least-squares multiple of q (H, W) over the weighted pixels
    (w (F, H, W) 0/1): a_t = sum w x q / sum w q^2, x_t - a_t q where w > 0. With q the depth change of a
    unit disparity offset in units of x (z^2 / (f B sigma)), this removes a frame-wide disparity offset
    (the ``frame_offset`` effect) and leaves a field correlated over a few pixels almost whole."""
    num = np.einsum("thw,thw,hw->t", w, x, q, dtype=np.float64)
    den = np.einsum("thw,hw->t", w, q * q, dtype=np.float64)
    a = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return (x - (a[:, None, None] * q[None] * w)).astype(np.float32)


def _spatial_standardised_residual(c, m, sig, fb):
    """One-frame counterpart of :func:`_standardised_residuals`: (z - z_plane) / sigma at the mask's
    pixels, z_plane = f B / (the frame's best disparity plane, :func:`_plane_residual`), values more
    than 8 sigma from the median left out (0, weight 0); returns (x, w) float32 (1, H, W) or None."""
    with np.errstate(divide="ignore", invalid="ignore"):
        pr = _plane_residual(fb / c.frame_m(0), m)
    if pr is None:
        return None
    z = c.frame_m(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (z - fb / pr[1]) / sig
        keep = m & np.isfinite(x)
        med = _median(x[keep]) if keep.any() else 0.0
        keep &= np.abs(x - med) <= 8.0
    return (np.where(keep, x, 0.0).astype(np.float32)[None], keep.astype(np.float32)[None])


def _fit_correlated_noise(real, base, model, rois=None, base_effects=(), **_):
    """Excess lag covariance of the per-frame residuals, in units of sigma_z.

    Per capture (interior pixels valid in every frame; captures up to 60 deg, below the truncation of
    the reference noise at grazing angles), x = (z - temporal mean) / sigma_z(z_true, theta), sigma_z
    that of the base's axial noise (the refitted one when ``base_effects`` hold an ``axial_refit``, which
    the effect then scales with: :func:`_base_sigma_model`), values
    more than 8 sigma from the pixel's temporal median (outliers) left out of the mean and the sums: the
    temporal mean removes everything static. The effect adds f g with g a unit field of correlation
    rho(h), so x's lag covariance (over the first 6 frames) grows by f^2 (1 - 1/F) rho(h). Each frame's
    frame-wide disparity offset is removed first, in the real data and in the base alike
    (:func:`_remove_frame_offset`): a per-frame offset (``frame_offset``) is a correlation of infinite
    length, which the field's length would otherwise stretch to take. The
    real-minus-base covariances at lags 0-11 px (rows and columns), divided by (1 - 1/F) and pooled
    over captures by pair counts, give f^2 and l (:func:`fit_gaussian_cov`) from lags 1-11: lag 0 also
    holds any white excess (disparity_noise, or a white axial noise in the base larger or smaller than
    the real one, as an ``axial_refit`` fitted before this effect was in the model is), which would
    otherwise flatten or sharpen the field's fitted shape.

    A capture of one frame has no temporal mean: x is its frame's residual about the target's best
    plane (:func:`_spatial_standardised_residual`), whose lag covariance grows by f^2 rho(h). Assumption: one frame cannot tell a field drawn afresh
    every frame from a static one (static_pattern) or from a static share of it, so on single frames
    the whole excess spatial correlation is attributed to this effect (the temporal share is not
    identifiable; it is 1 here).
    """
    num, den, nF = np.zeros(len(_CORR_LAGS)), np.zeros(len(_CORR_LAGS)), 0
    for c, b in zip(real, base):
        g = c.geometry
        z, th, _, fb = _nominal(g, model)
        if np.nanmax(th) > math.radians(60.5):
            continue
        m = (_interior(g, model, _roi(rois, g)) & c.has_data().all(axis=0)
             & b.has_data().all(axis=0))
        if m.sum() < 100:
            continue
        sig = np.where(m, axial_sigma_unchecked(np.where(m, z, 1.0), np.where(m, th, 0.0),
                                                _base_sigma_model(model, base_effects, g)), 1.0)
        if c.n_frames >= 2:
            nf = min(c.n_frames, _CORR_FRAMES)
            q = np.where(m, z * z / (fb * sig), 0.0)
            xr, wr = _standardised_residuals(c, m, sig, nf)
            xb, wb = _standardised_residuals(b, m, sig, nf)
            xr, xb = _remove_frame_offset(xr, wr, q), _remove_frame_offset(xb, wb, q)
            gain = 1.0 - 1.0 / c.n_frames
        else:
            rr = _spatial_standardised_residual(c, m, sig, fb)
            rb = _spatial_standardised_residual(b, m, sig, fb)
            if rr is None or rb is None:
                continue
            (xr, wr), (xb, wb) = rr, rb
            gain = 1.0
        cr, n = _lag_cov_masked(xr, wr, _CORR_LAGS)
        cb, _ = _lag_cov_masked(xb, wb, _CORR_LAGS)
        ok = np.isfinite(cr) & np.isfinite(cb)
        num[ok] += n[ok] * (cr[ok] - cb[ok]) / gain
        den[ok] += n[ok]
        nF += 1
    if not nF or not (den > 0).all():
        raise ValueError("correlated_noise: needs captures at <= 60 deg with >= 100 interior pixels valid in "
                         "every frame")
    # lag 0 holds any white excess too (a refitted or extra white noise): the field is fitted on lags >= 1
    lags, exc = np.array(_CORR_LAGS)[1:], (num / den)[1:]
    A, ell = fit_gaussian_cov(lags, exc)
    return {"sigma_z_fraction": float(math.sqrt(max(A, 1e-8))), "length_px": float(ell)}


# ---- static_pattern -------------------------------------------------------------------------------
_STATIC_LAGS = (0, 1, 2, 3, 4, 6, 8, 11, 15, 20, 26)


def _single_frame_residual(c, m, fb):
    """One frame's disparity minus its best plane (:func:`_plane_residual`), values more than 8 robust
    sigmas from 0 (outliers) set to NaN; None when fewer than 50 pixels have data."""
    with np.errstate(divide="ignore", invalid="ignore"):
        pr = _plane_residual(fb / c.frame_m(0), m)
    if pr is None:
        return None
    r = pr[0]
    ok = np.isfinite(r)
    s = 1.4826 * _median(np.abs(r[ok]))
    if s > 0:
        r = np.where(np.abs(r) <= 8.0 * s, r, np.nan)
    return r


def _fit_static_pattern(real, base, model, rois=None, **_):
    """Excess lag covariance of the temporal-mean disparity residual.

    Per capture (interior pixels): the temporal mean of d = f B / z minus the true disparity, minus its
    best plane in (u, v) (a depth bias maps a plane's affine disparity to another affine disparity, so
    it leaves nothing); its lag covariance less the temporal share (:func:`static_lag_cov`: the
    deviations' lag covariance / (F - 1)), so that a temporal noise unlike the base's does not read as
    static. The pattern adds sigma_px^2 rho(h) to it; the base simulation's is subtracted. sigma_px^2 and
    the length are the typical capture's (:func:`typical_capture_fit`: each capture fitted on its own, the
    median over captures), so that captures whose static error is far larger than the rest's (grazing
    angles on a physical D435) do not set the pattern of all. The pattern's realisation is
    not recovered (its ``seed`` is returned as 0).

    A capture of one frame: the "temporal mean" is its frame (the residual about its best plane fitted
    robustly, values beyond 8 robust sigmas left out, :func:`_single_frame_residual`), and lag 0 is left
    out of the fit when any capture has one frame (white noise adds there: the base's is subtracted,
    but any extra white noise of the real data would read as a pattern). Assumption: one frame cannot
    tell a static pattern from a field drawn afresh every frame (correlated_noise): on single frames
    the whole excess spatial correlation of the frame is attributed to the static pattern.
    """
    rows = []
    single = False
    for c, b in zip(real, base):
        g = c.geometry
        z, _, _, fb = _nominal(g, model)
        m = _interior(g, model, _roi(rois, g))
        with np.errstate(divide="ignore", invalid="ignore"):
            dtrue = fb / z
        if c.n_frames >= 2:
            sr = static_lag_cov(c, m, fb, dtrue, np.ones(z.shape), _STATIC_LAGS)
            sb = static_lag_cov(b, m, fb, dtrue, np.ones(z.shape), _STATIC_LAGS)
            if sr is None or sb is None:
                continue
            (cr, n), (cb, _) = sr, sb
        else:
            rr = _single_frame_residual(c, m, fb)
            rb = _single_frame_residual(b, m, fb)
            if rr is None or rb is None:
                continue
            single = True
            cr, n = lag_cov(rr[None], m, _STATIC_LAGS)
            cb, _ = lag_cov(rb[None], m, _STATIC_LAGS)
        if not (np.all(np.isfinite(cr)) and np.all(np.isfinite(cb))):
            continue
        rows.append((cr - cb, n))
    if not rows:
        raise ValueError("static_pattern: no capture with >= 50 interior pixels with data (in half its frames)")
    use = slice(1, None) if single else slice(None)
    A, ell = typical_capture_fit(rows, _STATIC_LAGS, use, lmin=0.5, lmax=80.0)
    return {"sigma_px": float(math.sqrt(max(A, 1e-10))), "length_px": float(ell), "seed": 0}


# ---- static_noise ---------------------------------------------------------------------------------
_STATIC_NOISE_LAGS = (0, 1, 2, 3, 4, 6, 8, 11, 15, 20, 26, 34, 44)


def static_lag_cov(c, m, fb, dtrue, scale, lags):
    """The static part's lag covariance of the disparity residual in units of ``scale``, told apart from
    the temporal part's share of the temporal mean.

    On the mask's pixels with data in every frame: r = the temporal mean of d = f B / z minus the true
    disparity, minus its best plane in (u, v); dev_t = d_t - the temporal mean. With a static part s and
    a temporal part e_t of lag covariances S(h) and T(h), E[r r'] = S(h) + T(h) / F and
    E[dev_t dev_t'] = T(h) (1 - 1/F), so S(h) = cov(r) - cov(dev) / (F - 1) whatever the temporal part is
    (white, correlated, stronger or weaker than the model's): with few frames, the temporal noise left
    in the mean is not read as a static pattern. Pixels with a value more than 8 robust sigmas from the
    pixel's mean, or a mean more than 8 robust sigmas from the plane (outliers), are left out.

    Returns (S (len(lags),), pairs (len(lags),)) or None when fewer than 100 pixels qualify.
    """
    F = c.n_frames
    d = fb / c.depth_m
    ok = m & np.all(np.isfinite(d), axis=0)
    if ok.sum() < 100:
        return None
    mean = np.where(ok, d.mean(axis=0), np.nan)
    vv, uu = np.nonzero(ok)
    A = np.column_stack([np.ones(vv.size), uu, vv]).astype(np.float64)
    y = (mean - dtrue)[ok]
    coef = np.linalg.lstsq(A, y, rcond=None)[0]
    sc = np.where(scale[ok] > 0, scale[ok], 1.0)
    x_mean = (y - A @ coef) / sc
    x_dev = (d[:, ok] - mean[ok]) / sc
    s_dev = 1.4826 * _median(np.abs(x_dev))
    s_mean = 1.4826 * _median(np.abs(x_mean - _median(x_mean)))
    keep = np.all(np.abs(x_dev) <= 8.0 * max(s_dev, 1e-12), axis=0) & (np.abs(x_mean) <= 8.0 * max(s_mean, 1e-12))
    if keep.sum() < 100:
        return None
    km = np.zeros(ok.shape, dtype=bool)
    km[vv[keep], uu[keep]] = True
    rm = np.zeros(ok.shape)
    rm[vv, uu] = x_mean
    rd = np.zeros((F,) + ok.shape)
    rd[:, vv, uu] = x_dev
    cm, n = lag_cov(rm[None], km, lags)
    cd, _ = lag_cov(rd, km, lags)
    return cm - cd / (F - 1), n


def _fit_static_noise(real, base, model, rois=None, base_effects=(), **_):
    """Excess static lag covariance of the disparity residual in units of the model's sigma_d.

    Per capture (interior pixels): sigma_d = sigma_z(z_true, theta) f B / z_true^2, the base's axial noise
    in disparity (the refitted one when ``base_effects`` hold an ``axial_refit``, :func:`_base_sigma_model`,
    which the field then scales with); the static part's lag covariance of the residual over sigma_d, told apart from the
    temporal noise left in the temporal mean (:func:`static_lag_cov`), so that neither a different
    temporal level nor a temporal correlation reads as static with few frames. The field adds
    sigma_z_fraction^2 rho(h) to it; the base simulation's is subtracted (it holds what the effects
    already selected make static). The fraction and length are the typical capture's
    (:func:`typical_capture_fit`: each capture fitted on its own, the median over captures): the
    field's size follows sigma_d, and a static error that grows faster than sigma_d in some captures
    (with the incidence angle, on a physical D435) would otherwise, pooled by pair counts, give every
    capture the size of the few where it is largest. The field's realisation is not recovered (``seed`` 0).

    A capture of one frame cannot tell the static part from the temporal one: its residual about the
    target's best plane, over sigma_d, is read as static, and lag 0 is left out of the fit (white
    noise adds there).
    """
    rows = []
    single = False
    for c, b in zip(real, base):
        g = c.geometry
        z, th, _, fb = _nominal(g, model)
        m = _interior(g, model, _roi(rois, g))
        with np.errstate(divide="ignore", invalid="ignore"):
            dtrue = fb / z
            sd = np.where(m, axial_sigma_unchecked(np.where(m, z, 1.0), np.where(m, th, 0.0),
                                                   _base_sigma_model(model, base_effects, g))
                          * fb / np.where(m, z, 1.0) ** 2, 1.0)
        if c.n_frames >= 2:
            sr = static_lag_cov(c, m, fb, dtrue, sd, _STATIC_NOISE_LAGS)
            sb = static_lag_cov(b, m, fb, dtrue, sd, _STATIC_NOISE_LAGS)
            if sr is None or sb is None:
                continue
            (cr, n), (cb, _) = sr, sb
        else:
            rr = _single_frame_residual(c, m, fb)
            rb = _single_frame_residual(b, m, fb)
            if rr is None or rb is None:
                continue
            cr, n = lag_cov((rr / sd)[None], m, _STATIC_NOISE_LAGS)
            cb, _ = lag_cov((rb / sd)[None], m, _STATIC_NOISE_LAGS)
            single = True
        rows.append((cr - cb, n))
    use = slice(1, None) if single else slice(None)
    if not any(np.all(np.isfinite(e[use])) and np.all(n[use] > 0) for e, n in rows):
        raise ValueError("static_noise: no capture with >= 100 interior pixels with data in every frame")
    A, ell = typical_capture_fit(rows, _STATIC_NOISE_LAGS, use, lmin=0.5, lmax=80.0)
    return {"sigma_z_fraction": float(math.sqrt(max(A, 1e-10))), "length_px": float(ell), "seed": 0}


#: Registry records (:class:`~.spec.FitSpec`) of this module's fits.
SPECS = (
    FitSpec("correlated_noise", _fit_correlated_noise, needs=("wall", "board"),
            tolerance={"sigma_z_fraction": ("rel", 0.05), "length_px": ("rel", 0.05)},
            tolerance_single_frame={"sigma_z_fraction": ("rel", 0.03), "length_px": ("rel", 0.06)}),
    # needs large interiors (walls): a board's interior holds few cells of the pattern
    FitSpec("static_pattern", _fit_static_pattern, needs=("wall", "board"),
            tolerance={"sigma_px": ("rel", 0.1), "length_px": ("rel", 0.15)},
            tolerance_single_frame={"sigma_px": ("rel", 0.05), "length_px": ("rel", 0.16)}),
    FitSpec("static_noise", _fit_static_noise, needs=("wall", "board"),
            tolerance={"sigma_z_fraction": ("rel", 0.1), "length_px": ("rel", 0.15)},
            tolerance_single_frame={"sigma_z_fraction": ("rel", 0.05), "length_px": ("rel", 0.16)}),
)
