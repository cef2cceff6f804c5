"""What every fit shares: the base simulations, the captures' nominal geometry and pixel samples, robust
per-pixel and per-frame statistics.

A fit compares a statistic between the real captures and the *base* simulation of the same captures
(:func:`_base_sims`: the reference simulation plus the effects already selected, seeded per capture so
that every fit sees the same random numbers) on the target's interior pixels (:func:`_interior`,
thinned by :func:`_sample_mask`). Temporal statistics (:func:`_robust_temporal_var`) have a one-frame
counterpart about the target's best plane (:func:`_plane_residual`, :func:`_robust_mean_square`).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping

import numpy as np

from ...d435 import axial_sigma_unchecked
from ...sim.effects import canonical_order
from ...sim.effects.base import frame_model
from ..capture_data import REGION_INTERIOR, CaptureData, simulate_capture


def _check_rois(rois, real) -> dict:
    """{id: bool (H, W)} for the captures of ``real`` that have a region of interest (checked)."""
    if rois is None:
        return {}
    if not isinstance(rois, Mapping):
        raise ValueError(f"rois must be a mapping capture id -> boolean image, got {type(rois).__name__}")
    out = {}
    for c in real:
        if c.id not in rois or rois[c.id] is None:
            continue
        r = np.asarray(rois[c.id])
        g = c.geometry
        if r.dtype != bool or r.shape != (g.height, g.width):
            raise ValueError(f"rois[{c.id!r}] must be a boolean image of shape ({g.height}, {g.width}), "
                             f"got {r.dtype} {r.shape}")
        out[c.id] = r
    return out


def _base_sims(real, model, base_effects, seed, cache) -> list:
    """The base simulation of each capture of ``real``: CaptureData with as many frames, simulated by
    :func:`noise_model.analysis.capture_data.simulate_capture` with ``model`` and ``base_effects`` (in
    canonical order), seeded by ``[seed, crc32(capture id)]`` (common random numbers across fits);
    cached in ``cache`` by capture, frames, effects, seed and model."""
    effects = canonical_order(base_effects)
    ekey = tuple(repr(e) for e in effects)
    mkey = (model.name, tuple(float(c) for c in model.axial_coefficients), float(model.sigma_L),
            float(model.sigma_R))
    out = []
    for c in real:
        g = c.geometry
        key = ("base", g.id, id(g), c.n_frames, ekey, seed, mkey)
        if key not in cache:
            rng = np.random.default_rng([seed, zlib.crc32(g.id.encode("utf-8"))])
            cache[key] = CaptureData.from_units(g, simulate_capture(g, c.n_frames, rng, model, effects))
        out.append(cache[key])
    return out


def _nominal(g, model):
    """Nominal z_true, theta, regions, f B of a geometry (cached on it)."""
    key = ("fit_nominal", float(model.sigma_L), float(model.sigma_R))
    if key not in g._cache:
        z, th = g.render()
        g._cache[key] = (z, th, g.regions(model=model), g.fb_px_m)
    return g._cache[key]


#: The fits use target pixels up to this true depth [m] (a steep wall reaches hundreds of metres in the
#: image corners, where the depth is noise and the uint16 range truncates it).
FIT_MAX_Z_M = 10.0


def _roi(rois, g):
    """The capture's region of interest (bool (H, W)) or None."""
    return rois.get(g.id) if rois else None


def _interior(g, model, roi=None):
    """Interior pixels of the target (region INTERIOR) with z_true <= FIT_MAX_Z_M, on a board also
    4 lateral sigmas from its left and right edges (cached); only those in ``roi`` when given."""
    if roi is not None:
        return _interior(g, model) & roi
    key = ("fit_interior", float(model.sigma_L), float(model.sigma_R))
    if key not in g._cache:
        z, th, reg, fb = _nominal(g, model)
        with np.errstate(invalid="ignore"):
            m = (reg == REGION_INTERIOR) & (z <= FIT_MAX_Z_M)
            if g.kind == "board":
                # a board's left/right edges move by N(0, sigma^2) each frame: keep 4 sigma away from them
                s, _ = g.board_coordinates()
                w2 = g.target["width_m"] / 2.0
                m &= (s + w2 > 4.0 * model.sigma_L) & (w2 - s > 4.0 * model.sigma_R)
        g._cache[key] = m
    return g._cache[key]


def _robust_temporal_var(x, scale=None, min_count: int = 3):
    """Per-pixel temporal variance (ddof 1) of x (F, N), NaN = missing, after dropping values more than
    6 robust sigmas from the pixel's mean (outliers), in two passes. The robust sigma of a pixel is
    ``scale`` (N,) (its expected noise, e.g. the model's; 1 if None) times the median absolute
    deviation of the residuals divided by their scales, pooled over the pixels. Returns
    (var (N,), count (N,)); var is NaN where fewer than ``min_count`` (>= 2) values remain."""
    v = np.isfinite(x)
    x0 = np.where(v, x, 0.0)
    n = v.sum(axis=0)
    sc = np.ones(x.shape[1]) if scale is None else np.where(np.asarray(scale) > 0, np.asarray(scale), 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        m = x0.sum(axis=0) / n
        r = np.abs(x0 - m) / sc
    rs = r[v]
    if rs.size == 0:
        return np.full(x.shape[1], np.nan), np.zeros(x.shape[1], dtype=int)
    sub = rs if rs.size <= 200_000 else rs[:: rs.size // 200_000 + 1]
    s = 1.4826 * _median(sub)
    if not s > 0:
        s = float(np.std(sub)) or 1.0
    with np.errstate(invalid="ignore"):
        keep = v & (r <= 6.0 * s)
    xk = np.where(keep, x0, 0.0)
    n2 = keep.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        m2 = xk.sum(axis=0) / n2
        var = np.where(keep, (x0 - m2) ** 2, 0.0).sum(axis=0) / np.maximum(n2 - 1, 1)
    var[n2 < max(int(min_count), 2)] = np.nan
    return var, n2


def _median(a) -> float:
    """float(np.median(a)) of a float64 array (all of it), the same value, by one partition at the middle.

    For even n the median is the mean of the order statistics n/2 - 1 and n/2: ``np.partition(a, n // 2)``
    places the latter and leaves every smaller value before it, whose maximum is the former (NumPy's
    median partitions at both, which costs several single partitions). NaN when ``a`` holds a NaN or
    nothing, as np.median; other dtypes go to np.median itself.
    """
    a = np.asarray(a)
    if a.dtype != np.float64 or a.size == 0:
        return float(np.median(a))
    a = a.ravel(order="K")                         # memory order: no copy, and the median ignores order
    if np.isnan(a).any():
        return float("nan")
    k = a.size // 2
    p = np.partition(a, k)
    if a.size % 2:
        return float(p[k])
    return float((p[:k].max() + p[k]) / 2.0)


def _temporal_median(x):
    """np.median(x, axis=0) of x (F, ...) float, the same values: the middle of each pixel's sorted
    values (the mean of the two middle ones for even F), NaN where a value is NaN; by a sort along the
    frame axis, which is faster than the median's partition along that strided axis."""
    x = np.asarray(x)
    F = x.shape[0]
    s = np.sort(x, axis=0)                          # NaN sorts last
    med = s[F // 2].copy() if F % 2 else (s[F // 2 - 1] + s[F // 2]) / 2.0
    med[np.isnan(s[-1])] = np.nan
    return med


def _temporal_min_count(n_frames: int) -> int:
    """Values a pixel needs for its temporal variance: 3, or every frame of a 2-frame capture."""
    return 3 if n_frames >= 3 else 2


def _plane_residual(d, m, scale=None):
    """One frame's disparity d (H, W) [px] minus its best plane a + b u + c v over the mask's pixels with
    data, fitted by least squares, then refitted (twice at most) without the pixels more than 6 robust
    sigmas from the plane (outliers; robust sigma: ``scale`` (H, W) times 1.4826 MAD of r / scale).

    A plane target's true disparity is affine in (u, v), and so is any depth bias's image of it (a
    scale and a disparity offset), so the residual holds the frame's noise and patterns only. Returns
    (r (H, W) [px] with NaN outside the mask or without data, plane (H, W) [px] over the whole image),
    or None when fewer than 50 pixels have data.
    """
    ok = m & np.isfinite(d)
    vv, uu = np.nonzero(ok)
    if vv.size < 50:
        return None
    A = np.column_stack([np.ones(vv.size), uu, vv]).astype(np.float64)
    y = d[ok]
    sc = np.ones(vv.size) if scale is None else np.where(scale[ok] > 0, scale[ok], 1.0)
    coef = np.linalg.lstsq(A, y, rcond=None)[0]
    for _ in range(2):
        r = (y - A @ coef) / sc
        med = _median(r)
        mad = 1.4826 * _median(np.abs(r - med))
        if not mad > 0:
            break
        keep = np.abs(r - med) <= 6.0 * mad
        if keep.sum() < 50 or keep.all():
            break
        coef = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
    H, W = d.shape
    plane = coef[0] + coef[1] * np.arange(W)[None, :] + coef[2] * np.arange(H)[:, None]
    out = np.full(d.shape, np.nan)
    out[ok] = y - A @ coef
    return out, plane


def _robust_mean_square(r, scale=None):
    """Mean of r^2 (N,) over the values within 6 robust sigmas of 0 (robust sigma: ``scale`` (N,) times
    1.4826 MAD of r / scale), the spatial counterpart of :func:`_robust_temporal_var`; returns
    (mean square, kept (N,) bool). NaN values are left out."""
    r = np.asarray(r, dtype=np.float64)
    v = np.isfinite(r)
    sc = np.ones(r.shape) if scale is None else np.where(np.asarray(scale) > 0, np.asarray(scale), 1.0)
    if not v.any():
        return float("nan"), v
    a = np.abs(r[v] / sc[v])
    s = 1.4826 * _median(a)
    if not s > 0:
        s = float(np.std(a)) or 1.0
    keep = np.zeros(r.shape, dtype=bool)
    keep[v] = a <= 6.0 * s
    return float(np.mean(r[keep] ** 2)) if keep.any() else float("nan"), keep


def _frame(model, g):
    """``model`` bound to the capture's focal length when it is of the disparity family
    (:func:`noise_model.sim.effects.base.frame_model`)."""
    return frame_model(model, float(g.K[0, 0]))


def _base_sigma_model(model, base_effects, g):
    """The model whose sigma_z the base simulation's white axial noise has, bound to the capture's focal
    length: the refitted one of an ``axial_refit`` among ``base_effects`` (it replaces the reference's
    noise, and the effects after it scale with its sigma), else ``model``."""
    out = model
    for e in base_effects or ():
        if getattr(e, "name", None) == "axial_refit" and getattr(e, "new_model", None) is not None:
            out = e.new_model
    return _frame(out, g)


def _sigma_ref_px(g, model, mask):
    """The model's sigma_z [m] at the mask's pixels (z_true, theta of the nominal render)."""
    z, th, _, _ = _nominal(g, model)
    return axial_sigma_unchecked(z[mask], th[mask], _frame(model, g))


#: Pixels per capture used by the per-pixel statistics (a fixed stride through the interior).
_MAX_SAMPLE_PX = 30_000


def _sample_mask(g, model, max_px: int = _MAX_SAMPLE_PX, roi=None):
    """The interior pixels of a capture (those in ``roi`` when given), thinned by a fixed stride to at
    most ``max_px`` (cached)."""
    key = ("fit_sample", float(model.sigma_L), float(model.sigma_R), int(max_px))
    if roi is not None:
        key = key + (zlib.crc32(np.packbits(roi).tobytes()),)
    if key not in g._cache:
        m = _interior(g, model, roi)
        idx = np.flatnonzero(m)
        if idx.size > max_px:
            idx = idx[:: int(math.ceil(idx.size / max_px))]
        out = np.zeros(m.shape, dtype=bool)
        out.flat[idx] = True
        g._cache[key] = out
    return g._cache[key]


def _pixels(c, mask):
    """Frames of c at the mask's pixels: (F, N) depth [m]."""
    return c.pixels_m(mask)


def _disp_sigma(z, th, model, depth_scale, fb):
    """Disparity noise [px] of the reference at depth z with the unit rounding: sqrt(s_d^2 + q^2 / 12);
    a disparity-family ``model`` must be bound to the frame (:func:`_frame`)."""
    s = axial_sigma_unchecked(np.asarray(z, dtype=float), np.asarray(th, dtype=float), model)
    q = fb * depth_scale / np.asarray(z, dtype=float) ** 2
    return np.sqrt((s * fb / np.asarray(z, dtype=float) ** 2) ** 2 + q * q / 12.0)
