"""Fits of the disparity effects: ``disparity_noise``, ``disparity_quantization``, ``depth_bias``.

* disparity_noise: method of moments on the temporal variance in disparity units.
* disparity_quantization: the coarsest 2^-bits px lattice the depth values lie on, searched at the f B
  the device uses (:func:`disparity_lattice` reports it).
* depth_bias: linear regression of the real on the base simulation's trimmed-mean disparities.
* frame_offset: method of moments on the variance over frames of each frame's mean disparity deviation.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.stats import trim_mean

from ...checks import check_scalar_range
from ...d435 import D435, SensorModel
from ...sim.effects.base import check_sensor_model
from ..capture_data import check_captures
from ._common import (
    _MAX_SAMPLE_PX, _base_sims, _check_rois, _disp_sigma, _frame, _interior, _median, _nominal, _pixels,
    _plane_residual, _robust_mean_square, _robust_temporal_var, _roi, _sample_mask, _sigma_ref_px, _temporal_min_count,
)
from .spec import FitSpec, select_captures

__all__ = ["disparity_lattice", "LATTICE_FB_RANGE", "frame_offset_variance"]


# ---- disparity_noise -------------------------------------------------------------------------------
def _fit_disparity_noise(real, base, model, rois=None, **_):
    """Method of moments on the temporal variance in disparity units.

    The effect adds an independent N(0, s^2) to each pixel's disparity every frame, so the per-pixel
    temporal variance of d = f B / z grows by s^2 at every distance and angle. Per capture (interior
    pixels), v_real - v_base estimates s^2 (robust two-pass variance, :func:`_robust_temporal_var`);
    captures are combined with the inverse variance of that estimate, w ~ N (F - 1) / (v_base + s^2)^2
    (iterated), so far and grazing captures, whose reference noise is large, count little.

    A capture of one frame has no temporal variance: its frame's spatial variance about the target's
    best plane in disparity (:func:`_plane_residual`, :func:`_robust_mean_square`; weight N) stands in.
    One frame cannot tell noise that changes every frame from a static pattern or a correlated field
    (static_pattern, correlated_noise): their excess spatial variance is attributed to s too, so on
    single frames s is the excess disparity spread of a frame, an upper bound of the temporal part.
    Captures of two frames use both (a pixel needs its two values).
    """
    vr, vb, n = [], [], []
    for c, b in zip(real, base):
        g = c.geometry
        m = _sample_mask(g, model, roi=_roi(rois, g))
        fb = g.fb_px_m
        zt = _nominal(g, model)[0][m]
        sd = np.sqrt((_sigma_ref_px(g, model, m) * fb / zt ** 2) ** 2 + 0.05 ** 2)
        if c.n_frames >= 2:
            mc = _temporal_min_count(c.n_frames)
            a, na = _robust_temporal_var(fb / _pixels(c, m), sd, mc)
            s, ns = _robust_temporal_var(fb / _pixels(b, m), sd, mc)
            ok = np.isfinite(a) & np.isfinite(s)
            if ok.sum() < 50:
                continue
            vr.append(float(np.mean(a[ok])))
            vb.append(float(np.mean(s[ok])))
            n.append(float(ok.sum()) * (c.n_frames - 1))
        else:
            sdi = np.ones(m.shape)
            sdi[m] = sd
            with np.errstate(divide="ignore", invalid="ignore"):
                pr = _plane_residual(fb / c.frame_m(0), m, sdi)
                pb = _plane_residual(fb / b.frame_m(0), m, sdi)
            if pr is None or pb is None:
                continue
            a, ka = _robust_mean_square(pr[0][m], sd)
            s, kb = _robust_mean_square(pb[0][m], sd)
            if min(ka.sum(), kb.sum()) < 50:
                continue
            vr.append(a)
            vb.append(s)
            n.append(float(min(ka.sum(), kb.sum())))
    if not vr:
        raise ValueError("disparity_noise: no capture with >= 50 interior pixels with data (>= 3 values per "
                         "pixel over the frames, both of a 2-frame capture, or the one frame)")
    vr, vb, n = np.array(vr), np.array(vb), np.array(n, dtype=float)
    s2 = 0.0
    for _ in range(4):
        w = n / (vb + max(s2, 0.0)) ** 2
        s2 = float(np.sum(w * (vr - vb)) / np.sum(w))
    return {"s_px": float(math.sqrt(max(s2, 1e-8)))}


# ---- disparity_quantization -----------------------------------------------------------------------
def _lattice_member(k, A):
    """Whether depth unit k is round(A / n) for an integer n > 0 (A = f B 2^bits / depth_scale)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        hi = np.floor(A / (k - 0.5))
        return hi * (k + 0.5) >= A


#: Relative range of the search over f B of the lattice fit (+-1 %): the depth is f B / d with the
#: device's own f B, which can differ from the calibration's K[0, 0] * baseline_m the capture set
#: states (a baseline of 49.8 mm instead of the nominal 50 mm is -0.4 %); the lattice f B / (n 2^-b)
#: moves by k * rel depth units at value k, so it is found only at the right f B.
LATTICE_FB_RANGE = 0.01
_LATTICE_BITS = tuple(range(2, 11))
#: Captures the lattice is read from (those of the disparity_quantization fit).
_LATTICE_NEEDS = ("wall", "board")


def _camera_key(g):
    return (int(g.width), int(g.height), tuple(float(x) for x in np.round(np.asarray(g.K).ravel(), 6)),
            float(g.depth_scale), float(g.baseline_m))


def _lattice_hists(real, base, model, rois):
    """Per capture: (id, camera key, distinct depth units k, real counts, base counts, f B / depth_scale)."""
    hists = []
    for c, b in zip(real, base):
        g = c.geometry
        m = _sample_mask(g, model, 2 * _MAX_SAMPLE_PX, _roi(rois, g))
        kr = np.round(_pixels(c, m) / g.depth_scale)
        kb = np.round(_pixels(b, m) / g.depth_scale)
        kr = kr[np.isfinite(kr)].astype(np.int64)
        kb = kb[np.isfinite(kb)].astype(np.int64)
        kr, kb = kr[kr > 0], kb[kb > 0]
        if kr.size == 0 or kb.size == 0:
            continue
        top = int(max(kr.max(), kb.max())) + 1
        hr, hb = np.bincount(kr, minlength=top), np.bincount(kb, minlength=top)
        k = np.flatnonzero((hr > 0) | (hb > 0))
        hists.append((c.id, _camera_key(g), k.astype(np.float64), hr[k].astype(np.float64),
                      hb[k].astype(np.float64), g.fb_px_m / g.depth_scale))
    return hists


def _lattice_counts(k, h, Aq, rels):
    """Sum of the counts h (K,) of the depth units k (K,) that lie on the lattice round(Aq (1 + rel) / n),
    n = 1, 2, ..., for every rel of the uniform grid ``rels`` (R,) (:func:`_lattice_member` at each rel).

    Unit k is on it when k - 1/2 <= Aq (1 + rel) / n <= k + 1/2 for some n (one n at most where the
    lattice is >= 2 units apart): an interval of rel per (k, n), summed on the grid by differences.
    """
    if rels.size == 1:
        return np.array([float(np.sum(h[_lattice_member(k, Aq * (1.0 + rels[0]))]))])
    r0, step, R = float(rels[0]), float(rels[1] - rels[0]), rels.size
    nlo = np.ceil(Aq * (1.0 + r0) / (k + 0.5))
    nhi = np.floor(Aq * (1.0 + float(rels[-1])) / (k - 0.5))
    cnt = np.maximum(nhi - nlo + 1.0, 0.0).astype(np.int64)
    if cnt.sum() == 0:
        return np.zeros(R)
    idx = np.repeat(np.arange(k.size), cnt)
    n = nlo[idx] + (np.arange(idx.size) - np.repeat(np.cumsum(cnt) - cnt, cnt))
    kk, w = k[idx], h[idx]
    lo = n * (kk - 0.5) / Aq - 1.0
    hi = n * (kk + 0.5) / Aq - 1.0
    i0 = np.maximum(np.ceil((lo - r0) / step - 1e-9), 0).astype(np.int64)
    i1 = np.minimum(np.floor((hi - r0) / step + 1e-9), R - 1).astype(np.int64)
    ok = i0 <= i1
    diff = np.bincount(i0[ok], weights=w[ok], minlength=R + 1) - np.bincount(i1[ok] + 1, weights=w[ok],
                                                                               minlength=R + 1)
    return np.cumsum(diff)[:R]


def _lattice_group_scan(group, bits: int, rel_range: float):
    """One camera's captures at one lattice: the relative f B error rel (grid over +-rel_range, fine
    enough to move the lattice by <= 1/4 unit at the largest value) that puts most real values on the
    lattice; returns dict(rel, mr, nr, mb, nb, score, alias) or None when no value is testable.

    Only values where the lattice is >= 2 units apart are tested (k^2 / (2^b A) >= 2). The score is
    L = (f - f0) / (1 - f0) (f, f0: fractions of the real and the base values on the lattice); among
    rel within 0.02 of the best score, the one nearest 0 (the stated f B) is kept: over a narrow range
    of depths the lattice repeats every ``alias`` ~ 1 / (mean disparity in lattice steps) in rel.
    """
    q = 2.0 ** bits
    parts = []
    for _, _, k, hr, hb, A in group:
        sel = k * k / (q * A) >= 2.0
        if sel.any():
            parts.append((k[sel], hr[sel], hb[sel], A * q))
    if not parts:
        return None
    kmax = max(float(p[0].max()) for p in parts)
    nsteps = int(min(20000, max(2, math.ceil(rel_range * 4.0 * kmax))))
    rels = np.linspace(-rel_range, rel_range, 2 * nsteps + 1) if rel_range > 0 else np.zeros(1)
    mr = np.zeros(rels.size)
    mb = np.zeros(rels.size)
    nr = nb = 0.0
    tsum = tn = 0.0
    for k, hr, hb, Aq in parts:
        mr += _lattice_counts(k, hr, Aq, rels)
        mb += _lattice_counts(k, hb, Aq, rels)
        nr += float(hr.sum())
        nb += float(hb.sum())
        tsum += float(np.sum(hr * Aq / k))
        tn += float(hr.sum())
    if nr <= 0 or nb <= 0:
        return None
    fr, f0 = mr / nr, mb / nb
    with np.errstate(divide="ignore", invalid="ignore"):
        score = np.where(f0 < 0.95, (fr - f0) / (1.0 - f0), -np.inf)
    best = float(np.max(score))
    near = np.flatnonzero(score >= best - 0.02)
    i = int(near[np.argmin(np.abs(rels[near]))])
    return {"rel": float(rels[i]), "mr": float(mr[i]), "nr": nr, "mb": float(mb[i]), "nb": nb,
            "score": float(score[i]), "alias": float(tn / tsum) if tsum > 0 else float("nan")}


def _lattice_scan(hists, rel_range: float = LATTICE_FB_RANGE):
    """The lattice fit: (bits or None, {bits: [(ids, key, group scan), ...]}, tested), tested = whether any
    b had >= 500 testable real and base values; see _fit_disparity_quantization."""
    groups: dict = {}
    for h in hists:
        groups.setdefault(h[1], []).append(h)
    scans = {}
    tested = False
    for bits in _LATTICE_BITS:
        rows = []
        for key, grp in groups.items():
            r = _lattice_group_scan(grp, bits, rel_range)
            if r is not None:
                rows.append(([h[0] for h in grp], key, r))
        scans[bits] = rows
        nr = sum(r["nr"] for _, _, r in rows)
        nb = sum(r["nb"] for _, _, r in rows)
        if nr < 500 or nb < 500:
            continue
        fr = sum(r["mr"] for _, _, r in rows) / nr
        f0 = sum(r["mb"] for _, _, r in rows) / nb
        if f0 >= 0.95:
            continue
        tested = True
        if (fr - f0) / (1.0 - f0) >= 0.7:
            return bits, scans, True
    return None, scans, tested


def _fit_disparity_quantization(real, base, model, rois=None, **_):
    """The coarsest disparity lattice the depth values lie on, at the f B the device uses.

    For bits b = 2..10, the depth units k the lattice f B / (n 2^-b) can produce (:func:`_lattice_member`)
    are tested where that lattice is >= 2 units apart at the value itself (k^2 u / (2^b f B) >= 2, where
    its density among the integers is <= 1/2), on the histograms of the interior's depth units: the
    fraction f_b of real values on it is compared with the base simulation's f0_b (continuous
    disparities, only the unit rounding): score L_b = (f_b - f0_b) / (1 - f0_b), 1 when every value is
    on the lattice, <= ~1/2 when the data's lattice is finer. The estimate is the smallest b with
    L_b >= 0.7 (finer lattices contain coarser ones, so every b above it also scores ~1); 10 when none
    does (no lattice visible: at 424 x 240 a 10-bit lattice is < 0.4 mm at 2 m); ValueError when no b
    has 500 values to test (every target nearer than the depth unit resolves the lattice).

    f B: the lattice is f B / (n 2^-b) with the device's f B, which may differ from the capture's
    K[0, 0] * baseline_m by a fraction of a percent (a 0.2 % error moves the 1/32 px lattice by a whole
    step at 1.6 m at 848 x 480 and hides it). So the captures are grouped by camera (same intrinsics,
    size, depth scale and baseline) and each group's f B is searched over +-:data:`LATTICE_FB_RANGE`
    (:func:`_lattice_group_scan`; f0 at the same f B); f_b and f0_b pool the groups at their own f B,
    so captures of different cameras (e.g. a 424 x 240 stream, whose depth is not on the 848 x 480
    lattice) neither hide nor fake another's lattice. :func:`disparity_lattice` reports the f B found;
    ``fb_rel`` is the relative f B of the camera with the most tested values (0 without a lattice).
    Works on single frames unchanged (it counts values, not frames).
    """
    hists = _lattice_hists(real, base, model, rois)
    if not hists:
        raise ValueError("disparity_quantization: no valid depth in the captures' interiors")
    bits, scans, tested = _lattice_scan(hists)
    if not tested:
        raise ValueError("disparity_quantization: fewer than 500 depth values where a 2^-b px lattice is >= 2 "
                         "depth units apart (targets too near for the depth unit, or too few pixels): no lattice "
                         "can be tested")
    rel = 0.0
    if bits is not None and scans.get(bits):
        # the effect has one f B: that of the camera with the most tested values
        _, _, r = max(scans[bits], key=lambda row: row[2]["nr"])
        rel = float(r["rel"])
    return {"subpixel_bits": 10 if bits is None else bits, "fb_rel": rel}


def disparity_lattice(real: Sequence, model: SensorModel = D435, base_effects=(), *, seed: int = 0,
                      cache: dict | None = None, rois: Mapping | None = None,
                      rel_range: float = LATTICE_FB_RANGE) -> dict:
    """The disparity lattice of real captures and the f B [px m] it is found at (the fit of
    ``disparity_quantization``, with its details).

    Parameters
    ----------
    real, model, base_effects, seed, cache, rois
        As for :func:`~noise_model.analysis.effect_fits.fit_effect` (wall and board captures are used).
    rel_range : float
        Relative half-range of the f B search, in [0, 0.05] (0: the stated f B only).

    Returns
    -------
    dict
        ``subpixel_bits`` (int, or None when no lattice is visible) and ``cameras``: one entry per
        camera (captures with the same intrinsics, size, depth scale, baseline) with ``captures`` (ids),
        ``fb_px_m_stated`` (K[0, 0] * baseline_m), ``fb_px_m`` (where the lattice of ``subpixel_bits``
        is found; the stated one when no lattice), ``fb_rel`` (fb / stated - 1), ``score`` (fraction of
        the values on the lattice above chance: 1 = all, ~0 = none), ``values`` (depth values tested) and
        ``alias_rel``: over a narrow range of depths the lattice repeats every ~alias_rel in f B, so the
        f B is determined only modulo it (the value nearest the stated one is reported); captures at
        several distances remove the ambiguity.

    Raises
    ------
    ValueError
        No usable capture or no valid depth, bad input.
    """
    check_sensor_model(model)
    real = check_captures(real, allow_empty=True)
    rel_range = check_scalar_range(rel_range, "rel_range", 0.0, 0.05)
    rois = _check_rois(rois, real)
    use = select_captures(_LATTICE_NEEDS, real)
    if not use:
        raise ValueError("disparity_lattice needs wall or board captures; none given")
    base = _base_sims(use, model, list(base_effects or ()), int(seed), {} if cache is None else cache)
    hists = _lattice_hists(use, base, model, rois)
    if not hists:
        raise ValueError("disparity_lattice: no valid depth in the captures' interiors")
    bits, scans, _ = _lattice_scan(hists, rel_range)
    show = scans[bits] if bits is not None else scans[_LATTICE_BITS[-1]]
    by_key = {key: (ids, r) for ids, key, r in show}
    cams = []
    seen = set()
    for h in hists:
        if h[1] in seen:
            continue
        seen.add(h[1])
        ids = [x[0] for x in hists if x[1] == h[1]]
        g = next(c.geometry for c in use if c.id == ids[0])
        fb0 = float(g.fb_px_m)
        r = by_key.get(h[1], (None, None))[1]
        rel = r["rel"] if (r is not None and bits is not None) else 0.0
        cams.append({"captures": ids, "fb_px_m_stated": fb0, "fb_px_m": fb0 * (1.0 + rel), "fb_rel": rel,
                     "score": None if r is None else r["score"], "values": 0 if r is None else int(r["nr"]),
                     "alias_rel": None if r is None else r["alias"]})
    return {"subpixel_bits": bits, "cameras": cams}


# ---- depth_bias -----------------------------------------------------------------------------------
def _trim_mean(x, cut=0.1):
    """Mean of the finite values of x with the fraction ``cut`` cut off at each end (NaN if none)."""
    x = x[np.isfinite(x)]
    return float(trim_mean(x, cut)) if x.size else float("nan")


#: depth_bias: the captures' true depths must span this ratio (largest / smallest bin) for the scale and
#: the disparity offset to be told apart; below it the bias is one number per distance (a scale).
_BIAS_Z_RATIO = 1.5


def _fit_depth_bias(real, base, model, rois=None, **_):
    """Linear regression in disparity.

    The effect maps each disparity d (reference noise and base effects included) to
    d' = (d + offset_px) / scale, an affine map; trimmed means commute with it. Per capture and per
    quartile of the true disparity (interior pixels), the 10 %-trimmed mean of the real disparities is
    regressed on that of the base simulation: slope 1 / scale, intercept offset_px / scale.

    Scale and offset differ only in how the bias grows with distance ((scale - 1) z vs z^2 offset / (f B)),
    so they are told apart only by captures at different distances: when the bins' true depths span
    less than a factor :data:`_BIAS_Z_RATIO` (a single distance, or a few close ones), the bias is
    fitted as a scale alone (offset_px = 0: the regression through the origin), which reproduces the
    bias at the captures' distances but not its growth beyond them. Single frames: the trimmed means of
    one frame (nothing temporal is used). A capture whose target geometry was itself fitted to its
    depths (a plane fitted to a region of a frame) has no bias by construction: scale ~1.
    """
    xs, ys, ws, zs = [], [], [], []
    for c, b in zip(real, base):
        g = c.geometry
        m = _sample_mask(g, model, roi=_roi(rois, g))
        if m.sum() < 20:
            continue
        z, _, _, fb = _nominal(g, model)
        dt = fb / z[m]
        edges = np.quantile(dt, [0.0, 0.25, 0.5, 0.75, 1.0])
        dr, db = fb / _pixels(c, m), fb / _pixels(b, m)
        for i in range(4):
            sel = (dt >= edges[i]) & (dt <= edges[i + 1]) if i == 3 else (dt >= edges[i]) & (dt < edges[i + 1])
            if sel.sum() < 20:
                continue
            y, x = _trim_mean(dr[:, sel].ravel()), _trim_mean(db[:, sel].ravel())
            if math.isfinite(x) and math.isfinite(y) and x > 0 and y > 0:
                xs.append(x)
                ys.append(y)
                ws.append(float(sel.sum()))
                zs.append(float(np.median(fb / dt[sel])))
    if not xs:
        raise ValueError("depth_bias: no capture with >= 20 interior pixels with data")
    xs, ys, ws = np.array(xs), np.array(ys), np.array(ws)
    if len(xs) < 2 or np.ptp(xs) < 1e-6 or max(zs) / min(zs) < _BIAS_Z_RATIO:
        slope = float(np.sum(ws * xs * ys) / np.sum(ws * xs * xs))      # through the origin: a scale
        return {"scale": float(1.0 / slope), "offset_px": 0.0, "baseline_m": float(real[0].geometry.baseline_m)}
    X = np.column_stack([xs, np.ones_like(xs)]) * np.sqrt(ws)[:, None]
    slope, icpt = np.linalg.lstsq(X, ys * np.sqrt(ws), rcond=None)[0]
    scale = 1.0 / slope
    return {"scale": float(scale), "offset_px": float(icpt * scale), "baseline_m": float(real[0].geometry.baseline_m)}


#: Registry records (:class:`~.spec.FitSpec`) of this module's fits.
# ---- frame_offset ----------------------------------------------------------------------------------
def frame_offset_variance(c, m, weight) -> float:
    """The variance over frames of a capture's frame-wide disparity offset [px^2] (NaN when undefined).

    On the mask's pixels with data in every frame: dev_t = d_t - the pixel's temporal mean (d = f B / z
    [px]); pixels with a deviation beyond 8 robust sigmas of ``weight``-scaled deviations in any frame
    (outliers) left out; o_t = sum_i w_i dev_t,i / sum_i w_i with w_i = ``weight`` (H, W) (e.g. the
    inverse of the pixel's expected noise variance: any weights give a common offset exactly, these the
    least noise from the rest). Returns sum_t o_t^2 / (F - 1): the offset's variance plus the
    weighted mean's share of the per-pixel noise. Needs >= 2 frames and >= 100 pixels (else NaN).
    """
    F = c.n_frames
    if F < 2:
        return float("nan")
    with np.errstate(divide="ignore", invalid="ignore"):
        d = c.geometry.fb_px_m / c.pixels_m(m)
    ok = np.all(np.isfinite(d), axis=0)
    if ok.sum() < 100:
        return float("nan")
    d, w = d[:, ok], weight[m][ok]
    dev = d - d.mean(axis=0)
    a = np.abs(dev) * np.sqrt(w)
    s = 1.4826 * _median(a)
    keep = np.all(a <= 8.0 * max(s, 1e-12), axis=0)
    if keep.sum() < 100:
        return float("nan")
    o = dev[:, keep] @ w[keep] / float(np.sum(w[keep]))
    return float(np.sum(o * o) / (F - 1))


def _fit_frame_offset(real, base, model, rois=None, **_):
    """Method of moments on the variance over frames of the frame-wide disparity offset.

    The effect adds sigma_px n_t to every pixel's disparity in frame t, so the variance over frames of a
    frame's weighted mean deviation from the temporal mean (:func:`frame_offset_variance`, weights
    1 / s_i^2 with s_i the reference's disparity noise at the pixel, :func:`_disp_sigma`) grows by
    sigma_px^2 whatever the per-pixel noise is; the base simulation's (the per-pixel noise's share, and
    any offset the base effects make) is subtracted. Per capture (interior pixels with data in every
    frame), v_real - v_base; pooled with weights F - 1 (the degrees of freedom of each variance), then
    sigma_px = sqrt(max(pooled, 0)).

    Single frames: a frame-wide offset of one frame is a depth bias of that frame (the target's plane
    moves), so one frame cannot give it: ValueError.
    """
    num = den = 0.0
    single = False
    for c, b in zip(real, base):
        if c.n_frames < 2:
            single = True
            continue
        g = c.geometry
        z, th, _, fb = _nominal(g, model)
        m = _interior(g, model, _roi(rois, g))
        if m.sum() < 100:
            continue
        w = np.zeros(m.shape)
        ts = np.minimum(np.abs(th[m]), model.theta_max_rad)
        w[m] = 1.0 / _disp_sigma(z[m], ts, _frame(model, g), g.depth_scale, fb) ** 2
        vr, vb = frame_offset_variance(c, m, w), frame_offset_variance(b, m, w)
        if not (np.isfinite(vr) and np.isfinite(vb)):
            continue
        num += (c.n_frames - 1) * (vr - vb)
        den += c.n_frames - 1
    if not den:
        if single:
            raise ValueError("frame_offset: needs captures of >= 2 frames (one frame cannot tell a frame-wide "
                             "offset from a depth bias)")
        raise ValueError("frame_offset: no capture with >= 100 interior pixels with data in every frame")
    return {"sigma_px": float(math.sqrt(max(num / den, 1e-16)))}


SPECS = (
    FitSpec("disparity_noise", _fit_disparity_noise, needs=("wall", "board"),
            tolerance={"s_px": ("rel", 0.05)},
            tolerance_single_frame={"s_px": ("rel", 0.03)}),
    # needs depth where the 2^-bits lattice is >= 2 depth units apart (at 424 x 240 and 1 mm units:
    # z >= 0.82 m for 5 bits, 1.16 m for 6)
    FitSpec("disparity_quantization", _fit_disparity_quantization, needs=_LATTICE_NEEDS,
            tolerance={"subpixel_bits": ("abs", 0)},
            tolerance_single_frame={"subpixel_bits": ("abs", 0)}),
    # needs distances spanning >= 1.5x (_BIAS_Z_RATIO) to tell the scale from the offset
    FitSpec("depth_bias", _fit_depth_bias, needs=("wall", "board"),
            tolerance={"scale": ("abs", 0.001), "offset_px": ("abs", 0.006)},
            tolerance_single_frame={"scale": ("abs", 0.002), "offset_px": ("abs", 0.02)}),
    # needs >= 2 frames per capture: nothing on single frames
    FitSpec("frame_offset", _fit_frame_offset, needs=("wall", "board"),
            tolerance={"sigma_px": ("rel", 0.25)},
            tolerance_single_frame={}),
)
