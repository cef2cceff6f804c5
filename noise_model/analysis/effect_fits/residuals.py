"""Fits of the residual effects: ``outliers``, ``axial_refit``.

* outliers: maximum likelihood on the tails of the disparity residual, beyond the core's extent.
* axial_refit: least squares of the per-pixel variance on the paper's four sigma_z terms, fitting only
  the coefficients the captures' distances and angles determine.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.optimize import least_squares, minimize_scalar, nnls
from scipy.special import ndtr

from ...d435 import axial_sigma_unchecked
from ...formulas import angle_gain
from ._common import (
    _MAX_SAMPLE_PX, _base_sims, _disp_sigma, _frame, _median, _nominal, _pixels, _plane_residual, _robust_mean_square,
    _robust_temporal_var, _roi, _sample_mask, _temporal_min_count,
)
from .spec import FitSpec


# ---- outliers -------------------------------------------------------------------------------------
def _fit_outliers(real, base, model, rois=None, **_):
    """Maximum likelihood on the tails of the disparity residual.

    Per capture (interior, <= 60 deg) and pixel i: r = d - d_true minus the base simulation's mean
    residual as a linear function of d_true (a depth bias among the base effects shifts the core);
    the core scale is sigma_i = k s_i, s_i the reference's disparity noise at the pixel
    (sigma_z f B / z^2 with the unit rounding) and k the larger of 1.4826 MAD(r / s_i) over the
    capture (robust: the core, not the outliers) and the base's RMS of r / s_i (a disparity lattice can
    make the MAD 0); tails are |r| > T_i = max(10 k, 1.5 q) s_i, q the base's 99.99 % quantile of
    |r / s_i|: the core has nothing there. An outlier's error X ~ N(0, S_i^2), S_i^2 = s^2 + sigma_i^2,
    is seen as a tail with probability Q_i = P(|X| > T_i, X > -(d_i - d_min)) (below, d + X is beyond
    the uint16 range: no data, not seen). s maximises the likelihood of the tail residuals
    conditional on being seen (1-D bounded search); then fraction = (real tails - base tails) /
    sum_i Q_i n_i, n_i the pixel's valid frames in the base simulation. Single frames: the same counts
    over pixels (nothing temporal is used); fewer than 5 tail values in all: fraction 1e-6 (none).
    """
    caps = []
    for c, b in zip(real, base):
        g = c.geometry
        z, th, _, fb = _nominal(g, model)
        if np.nanmax(th) > math.radians(60.5):
            continue
        m = _sample_mask(g, model, 2 * _MAX_SAMPLE_PX, _roi(rois, g))
        if m.sum() < 100:
            continue
        zt = z[m]
        dt = fb / zt
        sd = _disp_sigma(zt, th[m], _frame(model, g), g.depth_scale, fb)
        rr = fb / _pixels(c, m) - dt
        rb = fb / _pixels(b, m) - dt
        okb = np.isfinite(rb)
        if okb.sum() < 100 or np.isfinite(rr).sum() < 100:
            continue
        # the base's mean residual, linear in d_true
        X = np.column_stack([np.ones(int(okb.sum())), np.broadcast_to(dt, rb.shape)[okb]])
        coef = np.linalg.lstsq(X, rb[okb], rcond=None)[0]
        centre = coef[0] + coef[1] * dt
        rr, rb = rr - centre, rb - centre
        fin = (rr / sd)[np.isfinite(rr)]
        sub = fin if fin.size <= 300_000 else fin[:: fin.size // 300_000 + 1]
        k = 1.4826 * _median(np.abs(sub - _median(sub)))
        fbs = np.abs(rb / sd)[okb]
        kb = float(np.sqrt(np.mean(fbs ** 2)))                          # base core (lattices too)
        kq = float(np.quantile(fbs, 0.9999))                            # base core's extent
        sc = max(k, kb) * sd                                            # (N,)
        T = max(10.0 * max(k, kb), 1.5 * kq) * sd
        with np.errstate(invalid="ignore"):
            tmask = np.isfinite(rr) & (np.abs(rr) > T)
            nb_tail = float(np.sum(okb & (np.abs(rb) > T)))
        pix = np.broadcast_to(np.arange(rr.shape[1]), rr.shape)
        d_lim = dt - fb / (65535 * g.depth_scale)                        # X below -d_lim: no data
        caps.append(dict(tail=rr[tmask], tpix=pix[tmask], sc=sc, T=T, dlim=d_lim, nb=nb_tail,
                         nvalid=okb.sum(axis=0).astype(float)))
    if not caps:
        raise ValueError("outliers: needs captures at <= 60 deg with >= 100 interior pixels with data")
    if sum(cp["tail"].size for cp in caps) < 5:
        return {"fraction": 1e-6, "sigma_px": 1.0}

    def seen(s, sc, T, dlim):
        S = np.sqrt(s * s + sc * sc)
        up = ndtr(-T / S)
        return up + np.maximum(up - ndtr(-dlim / S), 0.0), S

    def nll(logs):
        s = math.exp(logs)
        ll = 0.0
        for cp in caps:
            t = cp["tpix"]
            Q, S = seen(s, cp["sc"][t], cp["T"][t], cp["dlim"][t])
            ll += float(np.sum(-0.5 * (cp["tail"] / S) ** 2 - np.log(S) - np.log(np.maximum(Q, 1e-300))))
        return -ll

    r = minimize_scalar(nll, bounds=(math.log(0.01), math.log(50.0)), method="bounded", options={"xatol": 1e-5})
    s = math.exp(r.x)
    num = sum(cp["tail"].size - cp["nb"] for cp in caps)
    den = sum(float(np.sum(seen(s, cp["sc"], cp["T"], cp["dlim"])[0] * cp["nvalid"])) for cp in caps)
    return {"fraction": float(min(max(num / den, 1e-6), 0.5)), "sigma_px": float(s)}


# ---- axial_refit ----------------------------------------------------------------------------------
#: Scale of the coefficients of axial_refit's second base simulation (inside the quieter units' range,
#: where the base effects' variance is interpolated rather than extrapolated).
_AXIAL_SCALE2 = 0.6


#: axial_refit: the bins' mean true depths must span this ratio for c0, c1, c2 to be fitted separately,
#: and the share of the angle term in the reference sigma must vary by this much between bins for
#: c_theta to be told from them.
_AXIAL_Z_RATIO = 2.0
_AXIAL_ANGLE_SHARE = 0.3


def _closed_form_base(base_effects, zz, dtrue, fb, depth_scale):
    """The base effects' share of the per-pixel temporal variance of z, in closed form: v = f sigma^2 + e.

    For bins where the base simulations cannot give f and e (the reference noise truncated at grazing
    angles), from the effects' parameters (Effect objects with ``name`` and ``params``), at the bin's
    true depths zz (N,) [m] and disparities dtrue (N,) [px]:

    * ``correlated_noise``: a fresh field of fraction k of the sigma_z in effect each frame adds
      k^2 sigma^2 to every pixel's temporal variance (f += k^2), or ``sigma_m``^2 to e;
    * ``depth_bias``: z' = scale f B / (d + offset) scales the noise before it by
      scale (d / (d + offset))^2 (the share of sigma^2 times its square, the bin's mean);
    * ``disparity_noise``, ``frame_offset``: s^2 in disparity, z^4 s^2 / (f B)^2 in depth (e);
    * ``disparity_quantization``: the lattice's step^2 / 12 in disparity (Sheppard: the noise is wide
      against the step where this is used);
    * static fields (``static_pattern``, ``static_noise``), masks and edge effects: nothing temporal on a
      target's interior; ``outliers``: left to the robust variance.

    Plus the depth unit's rounding, depth_scale^2 / 12. Returns (f, e [m^2]).
    """
    k2, e_m, e_px, gain = 0.0, 0.0, 0.0, 1.0
    for eff in base_effects or ():
        name, p = getattr(eff, "name", None), getattr(eff, "params", {})
        if name == "correlated_noise":
            if p.get("sigma_m") is not None:
                e_m += float(p["sigma_m"]) ** 2
            else:
                k2 += float(p["sigma_z_fraction"]) ** 2
        elif name == "depth_bias":
            gain = float(np.mean((float(p["scale"]) * (dtrue / (dtrue + float(p["offset_px"]))) ** 2) ** 2))
        elif name == "disparity_noise":
            e_px += float(p["s_px"]) ** 2
        elif name == "frame_offset":
            e_px += float(p["sigma_px"]) ** 2
        elif name == "disparity_quantization":
            e_px += (2.0 ** -int(p["subpixel_bits"])) ** 2 / 12.0
    e = e_m + e_px * float(np.mean(zz ** 4)) / fb ** 2 + depth_scale ** 2 / 12.0
    # the depth bias acts first (ORDER): it scales the refitted noise, not the correlated field after it
    return gain + k2, e


def _pixel_variances(c, m, sref, fb, zs):
    """Per-pixel variance estimates of z [m^2] at the mask's pixels and the number of values behind each
    (N,): the robust temporal variance (:func:`_robust_temporal_var`) with >= 2 frames; with one frame,
    the squared residual about the frame's best disparity plane (z - f B / plane, :func:`_plane_residual`),
    NaN beyond 6 robust sigmas (:func:`_robust_mean_square`); zs (N,) the pixels' true depths [m].
    Returns (v (N,), degrees of freedom per value)."""
    if c.n_frames >= 2:
        v, _ = _robust_temporal_var(_pixels(c, m), sref, _temporal_min_count(c.n_frames))
        return v, c.n_frames - 1
    sc = np.ones(m.shape)
    sc[m] = sref * fb / np.maximum(zs, 1e-6) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        pr = _plane_residual(fb / c.frame_m(0), m, sc)
    if pr is None:
        return np.full(int(m.sum()), np.nan), 1
    with np.errstate(divide="ignore", invalid="ignore"):
        r = c.frame_m(0)[m] - fb / pr[1][m]
    _, keep = _robust_mean_square(r, sref)
    return np.where(keep, r * r, np.nan), 1


def _fit_axial_refit(real, base, model, base_effects=(), seed=0, cache=None, rois=None, **_):
    """Least squares of the temporal variance on the paper's four terms.

    Per capture and quartile of z_true (interior pixels): v the mean robust per-pixel temporal variance
    of z (:func:`_robust_temporal_var`) in the real data and in the base simulation, and the mean
    reference sigma_ref^2. The base effects act on the variance as v = f sigma^2 + e (e: depth-unit
    rounding, added noise; f: a scale, e.g. a depth bias's); with base effects, a second base
    simulation with every coefficient x 0.6 (common random numbers) gives f and e per bin; without,
    f = 1 and e = depth_scale^2 / 12 (the rounding's variance, Sheppard: exact for sigma >~ 0.6 units;
    the base simulation's own sampling noise stays out). Then y = (v_real - e) / f estimates sigma_new^2. The model of y
    is the bin's mean of sigma(c)^2 = (c0 + c1 z + c2 z^2 + c_theta z^1.5 theta / (pi/2 - theta)^2)^2
    over its pixels; residuals (model - y) / sd(y), sd(y)^2 ~ 2 (v_real^2 + v_base^2) / (n (F - 1)) (v_base
    only where the base simulations give f and e: a base far noisier than the real data, the paper's
    angle term at grazing angles, must not take the weight from those bins),
    non-negative coefficients (bounded least squares started from the non-negative linear fit of
    sqrt(y)). Bins whose real sigma exceeds 15 % of z are left out; where the reference's sigma does
    (its noise is truncated at z <= 0 there, so the base simulations cannot give f and e), f and e are
    the base effects' share in closed form (:func:`_closed_form_base`: 1 + k^2 for a correlated field of
    k sigma_z, nothing for a static one, the disparity noises' z^4 s^2 / (f B)^2, the rounding), so that a
    real camera quieter than the paper's angle term at grazing angles still constrains the fit, and the
    variance the base effects add there is not counted as white.

    Single frames: a capture of one frame has no temporal variance; the squared residual of its frame
    about the target's best plane (:func:`_pixel_variances`) stands in, pixel by pixel (the paper's own
    plane-fit sigma). Assumption: the spatial spread of one frame is all per-frame noise; a static
    pattern or a correlated field in it (not separable from one frame) is fitted into sigma too.

    What the captures determine: the four coefficients only when the bins span distances (mean true
    depths a factor >= :data:`_AXIAL_Z_RATIO` apart) and angles (the angle term's share of the
    reference sigma differs by >= :data:`_AXIAL_ANGLE_SHARE` between bins, e.g. 0 and >= 30 deg). If
    not, fewer parameters are fitted and the others follow the paper's shape: distances but no angles:
    c0, c1, c2 free and c_theta = the paper's times the ratio of the fitted to the paper's distance
    term at the bins' median depth; angles but one distance range: the distance term is the paper's
    times one factor a, c_theta free; neither: every coefficient is the paper's times one factor a
    (the noise's magnitude at the captures' distances and angles).
    """
    base2 = None
    if base_effects:
        model2 = replace(model, axial_coefficients=tuple(_AXIAL_SCALE2 * float(c) for c in model.axial_coefficients))
        base2 = _base_sims(real, model2, base_effects, seed, {} if cache is None else cache)
    bins, ys, sds, zmean, share = [], [], [], [], []
    ct = model.theta_max_rad
    cref = np.array([float(v) for v in model.axial_coefficients])
    for k, (c, b) in enumerate(zip(real, base)):
        g = c.geometry
        z, th, _, fb = _nominal(g, model)
        m = _sample_mask(g, model, roi=_roi(rois, g))
        if m.sum() < 50:
            continue
        zs, ts = z[m], np.minimum(np.abs(th[m]), ct)
        sref = axial_sigma_unchecked(zs, ts, _frame(model, g))
        vr, dof = _pixel_variances(c, m, sref, fb, zs)
        vb, _ = _pixel_variances(b, m, sref, fb, zs)
        vb2 = _pixel_variances(base2[k], m, _AXIAL_SCALE2 * sref, fb, zs)[0] if base2 is not None else None
        edges = np.quantile(zs, [0.0, 0.25, 0.5, 0.75, 1.0])
        for i in range(4):
            sel = (zs >= edges[i]) & ((zs <= edges[i + 1]) if i == 3 else (zs < edges[i + 1]))
            sel &= np.isfinite(vr) & np.isfinite(vb)
            if vb2 is not None:
                sel &= np.isfinite(vb2)
            if sel.sum() < 20:
                continue
            s2 = float(np.mean(sref[sel] ** 2))
            v_r, v_b = float(np.mean(vr[sel])), float(np.mean(vb[sel]))
            zz, tt = zs[sel], ts[sel]
            truncated = float(np.max(sref[sel])) > 0.15 * float(np.min(zz))
            if vb2 is not None and not truncated:
                f = (float(np.mean(vb2[sel])) - v_b) / ((_AXIAL_SCALE2 ** 2 - 1.0) * s2)
                if not f > 0.05:
                    continue
                e = v_b - f * s2
            else:
                # where the reference noise is truncated at z <= 0 the base simulations cannot give f and e,
                # but the real variance still measures sigma: the base effects' share in closed form (only the
                # rounding without base effects)
                f, e = _closed_form_base(base_effects, zz, fb / zz, fb, g.depth_scale)
            y2 = (v_r - e) / f
            if y2 <= 0 or math.sqrt(y2) > 0.15 * float(np.mean(zz)):
                continue
            gth = zz * np.sqrt(zz) * angle_gain(tt, 1.0)   # the regressor of the angle coefficient
            bins.append(np.column_stack([np.ones_like(zz), zz, zz * zz, gth]))
            ys.append(y2)
            # the base's variance enters y only through f and e (base effects); otherwise only the real one
            v_base = v_b if (vb2 is not None and not truncated) else 0.0
            sds.append(math.sqrt(2.0 * (v_r ** 2 + v_base ** 2) / (sel.sum() * max(dof, 1))) / f)
            zmean.append(float(np.mean(zz)))
            share.append(float(np.mean(cref[3] * gth / sref[sel])))
    if not ys:
        raise ValueError("axial_refit: no bin of >= 20 interior pixels with a usable variance (>= 2 values per "
                         "pixel over the frames or one frame's plane residual; sigma < 15 % of z)")
    y, sd = np.array(ys), np.array(sds)
    Bm = np.array([Bk.mean(axis=0) for Bk in bins])
    Ball = np.concatenate(bins)
    ids = np.repeat(np.arange(len(bins)), [len(Bk) for Bk in bins])
    cnt = np.bincount(ids).astype(float)
    dist_free = max(zmean) / min(zmean) >= _AXIAL_Z_RATIO
    angle_free = max(share) - min(share) >= _AXIAL_ANGLE_SHARE
    scale = np.array([1e-3, 1e-3, 1e-3, 1e-2])
    if dist_free and angle_free and len(ys) >= 4:
        c_lin, _ = nnls(Bm / np.sqrt(y)[:, None], np.ones_like(y))

        def resid(cc):
            s2 = (Ball @ cc) ** 2
            return (np.bincount(ids, weights=s2) / cnt - y) / sd

        x0 = np.maximum(c_lin, 1e-7)
        r = least_squares(lambda q: resid(q * scale), x0 / scale, bounds=(0.0, np.inf), method="trf")
        c0, c1, c2, cth = (float(v) for v in r.x * scale)
        return {"c0": max(c0, 1e-6), "c1": c1, "c2": c2, "c_theta": cth}
    # fewer parameters: c = coefficients(q)
    zmed = float(np.median(zmean))
    dref = cref[0] + cref[1] * zmed + cref[2] * zmed ** 2
    if dist_free and len(ys) >= 3:
        def coef(q):
            cd = q[:3] * scale[:3]
            return np.append(cd, cref[3] * (cd[0] + cd[1] * zmed + cd[2] * zmed ** 2) / dref)
        c_lin, _ = nnls(Bm[:, :3] / np.sqrt(y)[:, None], np.ones_like(y))
        x0 = np.maximum(c_lin, 1e-7) / scale[:3]
    elif angle_free and len(ys) >= 2:
        def coef(q):
            return np.array([q[0] * cref[0], q[0] * cref[1], q[0] * cref[2], q[1] * scale[3]])
        a0 = float(np.median(np.sqrt(y) / np.maximum(Bm @ cref, 1e-12)))
        x0 = np.array([a0, a0 * cref[3] / scale[3]])
    else:
        def coef(q):
            return q[0] * cref
        x0 = np.array([float(np.median(np.sqrt(y) / np.maximum(Bm @ cref, 1e-12)))])

    def resid_q(q):
        s2 = (Ball @ coef(q)) ** 2
        return (np.bincount(ids, weights=s2) / cnt - y) / sd

    r = least_squares(resid_q, np.maximum(x0, 1e-7), bounds=(0.0, np.inf), method="trf")
    c0, c1, c2, cth = (float(v) for v in coef(r.x))
    return {"c0": max(c0, 1e-6), "c1": c1, "c2": c2, "c_theta": cth}


#: Registry records (:class:`~.spec.FitSpec`) of this module's fits.
SPECS = (
    FitSpec("outliers", _fit_outliers, needs=("wall", "board"),
            tolerance={"fraction": ("rel", 0.1), "sigma_px": ("rel", 0.1)},
            tolerance_single_frame={"fraction": ("rel", 0.2), "sigma_px": ("rel", 0.1)}),
    # needs distances from ~0.5 to ~2 m and angles from 0 to >= 45 deg (the angle term)
    FitSpec("axial_refit", _fit_axial_refit, needs=("wall", "board"),
            tolerance={"c0": ("abs", 0.0002), "c1": ("abs", 0.0003), "c2": ("abs", 0.0002), "c_theta": ("abs", 0.001)},
            tolerance_single_frame={"c0": ("abs", 0.0003), "c1": ("abs", 0.0005), "c2": ("abs", 0.0003),
                                    "c_theta": ("abs", 0.0004)}),
)
