"""Characterise a depth camera the way Ahn et al. (2019) did: the maths, on plain arrays.

A capture is N depth frames of a planar target (a board or a wall) seen by a camera on a tripod
(capture-set format ``d435-captures/1``, see docs/capture-set-format.md). The image processing that
finds the target lives in :mod:`noise_model.analysis.detection` and the plane fits in
:mod:`noise_model.analysis.planes`; this module turns the pixels the detection selects into the
paper's figures:

* **Axial noise** (:func:`axial_noise`, the paper's section IV): the pixel-wise temporal standard
  deviation of each depth value about a plane fitted to the central region, aggregated robustly over
  the region's pixels. The deviation is measured *along the pixel's ray in depth* (z - z_plane), the
  quantity the model's sigma_z describes (``z = z_true + N(0, sigma_z^2)`` along the optical axis, see
  docs/noise-model.md); the orthogonal point-to-plane distance of the same deviation is smaller by
  |n . (u', v', 1)| (cos theta on the optical axis) and is reported beside it.
* **Lateral noise** (:func:`edge_positions`, :func:`lateral_noise`): the spread of a board's left or
  right edge pixels about a line fitted along the edge over all frames, in pixels and in metres along
  the board (across the edge); sigma_L / sigma_R over many captures by :func:`lateral_percentile`.
* **Systematic error** (:func:`known_plane`, :func:`systematic_error`, :func:`eq1_rms_error`): the RMS
  error of the mean of the frames against the known (tape- or laser-measured) target, next to the
  paper's equation (1), e = d^2 s / (f b).
* **The model fit** (:func:`fit_axial_model`): sigma_z = c0 + c1 z + c2 z^2 + c_theta z^(3/2) theta /
  (pi/2 - theta)^2 by weighted least squares (``scipy.optimize.curve_fit``), with standard errors and
  the fit residual; :func:`model_from_fit` turns it into a :class:`noise_model.SensorModel` that
  ``SensorModel.save`` / ``SensorModel.load`` persist, so a user's own fit replaces the paper's.

Camera frame: x right, y down, z forward (RealSense / OpenCV); depth is z, not ray length. Normalised
pixel coordinates are u' = (u - cx) / fx, v' = (v - cy) / fy, so a pixel's ray is z (u', v', 1).
NumPy and SciPy only: no OpenCV, rerun or elevmap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import optimize, stats

from ..checks import check_positive_scalar
from ..d435 import D435, SensorModel, expected_rms_error
from ..formulas import angle_gain, dersimonian_laird_tau2, sigma_z_from_gain
from ..sim.targets import target_rotation
from .family_fit import check_axial_points
from .planes import Plane

__all__ = [
    "AxialFit",
    "axial_noise",
    "edge_positions",
    "lateral_noise",
    "lateral_percentile",
    "known_plane",
    "systematic_error",
    "eq1_rms_error",
    "axial_model",
    "fit_axial_model",
    "model_from_fit",
    "axial_noise_bins",
    "LATERAL_PERCENTILE",
    "DEPTH_BIN_M",
    "MIN_BIN_PIXELS",
]

#: sigma_L and sigma_R are this percentile of the captures' lateral noise (the paper's choice).
LATERAL_PERCENTILE = 90.0


# ------------------------------------------------------------------------------------------------
# axial noise


def _check_samples(samples, m: int, name="samples_m") -> np.ndarray:
    s = np.asarray(samples)
    if s.ndim != 2 or s.shape[1] != m:
        raise ValueError(f"{name} must have shape (frames, {m}), got {s.shape}")
    if not np.issubdtype(s.dtype, np.floating):
        raise ValueError(f"{name} must be floating-point metres (NaN = no data), got dtype {s.dtype}")
    top = float(np.max(s, where=np.isfinite(s), initial=0.0))
    if top > 100.0:
        raise ValueError(f"{name} holds values up to {top:.1f}: depth must be in metres")
    return s


def _pixel_variances(samples_m, up, vp, plane: Plane, min_valid_fraction: float, frame_correction: bool):
    """Steps 1-3 of :func:`axial_noise`: (out, good, var_p, n_g) with ``out`` its result dict without the sigmas
    (``reason`` set when not measurable, then var_p is None), ``good`` (M,) the pixels used, ``var_p`` their
    chi-square-median-scaled temporal variances [m^2] and ``n_g`` their valid frame counts."""
    up = np.asarray(up, dtype=np.float64).ravel()
    vp = np.asarray(vp, dtype=np.float64).ravel()
    if up.shape != vp.shape:
        raise ValueError(f"up and vp must have the same shape, got {up.shape} and {vp.shape}")
    s = _check_samples(samples_m, up.size)
    N, M = s.shape
    z_pl = plane.depth_at(up, vp)
    valid = np.isfinite(s) & (s > 0) & np.isfinite(z_pl)[None, :]
    out = {"sigma_z_m": None, "stderr_m": None, "plane_distance_sigma_m": None,
           "z_m": float(np.nanmedian(z_pl)) if np.isfinite(z_pl).any() else None,
           "theta_rad": plane.theta_rad, "n_frames": int(N), "n_pixels": 0,
           "invalid_fraction": float(1.0 - valid.mean()) if valid.size else 1.0, "reason": None}
    if N < 2:
        out["reason"] = f"the temporal standard deviation needs >= 2 frames, the capture has {N}"
        return out, None, None, None
    e = np.where(valid, s - z_pl[None, :], np.nan)
    dof_loss = 0.0
    if frame_correction:
        A = np.stack([np.ones(M), up, vp], axis=1)
        w = z_pl * z_pl
        for f in range(N):
            ok = valid[f]
            if ok.sum() < 10:
                continue
            y = e[f, ok] / w[ok]
            # one clipped refit keeps a few wild samples from tilting the frame's plane
            coef, *_ = np.linalg.lstsq(A[ok], y, rcond=None)
            r = y - A[ok] @ coef
            mad = 1.4826 * np.median(np.abs(r - np.median(r)))
            keep = np.abs(r) <= max(5.0 * mad, 1e-12)
            if keep.sum() >= 10:
                coef, *_ = np.linalg.lstsq(A[ok][keep], y[keep], rcond=None)
            e[f] -= w * (A @ coef)
        dof_loss = 3.0
    n_p = valid.sum(axis=0)
    need = max(2, int(math.ceil(float(min_valid_fraction) * N)))
    good = n_p >= need
    out["n_pixels"] = int(good.sum())
    if good.sum() < 10:
        out["reason"] = (f"only {int(good.sum())} pixels of the region are valid in >= {need} of {N} frames "
                         "(need 10)")
        return out, good, None, None
    eg = e[:, good]
    var_p = np.nanvar(eg, axis=0, ddof=1)
    n_g = n_p[good]
    var_p = var_p * (n_g - 1) / stats.chi2.median(n_g - 1)
    if dof_loss:
        m_eff = max(float(np.median(valid[:, good].sum(axis=1))), dof_loss + 1.0)
        var_p = var_p * m_eff / (m_eff - dof_loss)
    return out, good, var_p, n_g


def _sigma_from_variances(var_p, n_g, depth_scale) -> tuple[float, float]:
    """Step 4 of :func:`axial_noise` over a set of pixels: (sigma [m], its relative standard error) from the
    median of their variances, Sheppard's correction applied where the noise exceeds one depth unit."""
    var = float(np.median(var_p))
    if depth_scale is not None:
        q = check_positive_scalar(depth_scale, "depth_scale", upper=0.1, unit=" m per unit")
        if var > q * q:
            var -= q * q / 12.0
    sigma = math.sqrt(max(var, 0.0))
    n_med = float(np.median(n_g))
    # median of M chi2-scaled variances: sd ~ sqrt(pi/2) var sqrt(2/(n-1)) / sqrt(M); sigma's is half
    rel_se = 0.5 * math.sqrt(math.pi / 2.0) * math.sqrt(2.0 / max(n_med - 1.0, 1.0)) / math.sqrt(var_p.size)
    return sigma, rel_se


def axial_noise(samples_m, up, vp, plane: Plane, depth_scale: float | None = None,
                min_valid_fraction: float = 0.5, frame_correction: bool = True) -> dict:
    """Axial noise of one capture: pixel-wise temporal standard deviation about a plane, aggregated.

    1. Each sample's deviation from the plane along its pixel's ray, e = z - z_plane(u', v') [m].
    2. Per frame, a first-order plane motion is removed: e / z_plane^2 = a + b u' + c v' fitted by
       least squares (a plane n . p = d moved slightly changes 1/z by a linear function of (u', v')), so
       a tripod's common-mode vibration is not counted as noise; the 3 parameters per frame cost
       3 / M of the variance, which is given back.
    3. Per pixel, the unbiased variance over its valid frames, divided by the median of its
       chi-square distribution (``(n - 1) / chi2.median(n - 1)``), so that the **median over the
       pixels** estimates sigma_z^2 without bias for Gaussian noise and ignores a minority of bad
       pixels (flying pixels, the odd background pixel).
    4. Rounding to the depth unit adds depth_scale^2 / 12 of variance (Sheppard's correction), which
       is removed where the noise exceeds one unit.

    Parameters
    ----------
    samples_m : array_like, shape (N, M)
        Depth [m] of the region's M pixels in N frames; NaN = no data.
    up, vp : array_like, shape (M,)
        Normalised coordinates of the pixels.
    plane : Plane
        The region's plane (fitted to the mean of the frames).
    depth_scale : float, optional
        Depth unit [m] of the recording, for Sheppard's correction (none when None).
    min_valid_fraction : float
        A pixel counts only when valid in at least this fraction of the frames (and in 2).
    frame_correction : bool
        Remove each frame's plane motion (step 2).

    Returns
    -------
    dict
        ``sigma_z_m`` (along the ray in depth, the model's sigma_z), ``stderr_m`` (its sampling error,
        taking the pixels as independent), ``plane_distance_sigma_m`` (the same noise as orthogonal
        distance to the plane), ``z_m`` (median plane depth of the pixels), ``theta_rad`` (the plane's
        incidence angle), ``n_frames``, ``n_pixels`` (pixels used), ``invalid_fraction`` (of all
        samples). ``sigma_z_m`` is None (with ``reason``) when fewer than 2 frames or 10 pixels qualify.
    """
    out, good, var_p, n_g = _pixel_variances(samples_m, up, vp, plane, min_valid_fraction, frame_correction)
    if var_p is None:
        return out
    up = np.asarray(up, dtype=np.float64).ravel()
    vp = np.asarray(vp, dtype=np.float64).ravel()
    sigma, rel_se = _sigma_from_variances(var_p, n_g, depth_scale)
    cosine = np.abs(plane.normal[0] * up[good] + plane.normal[1] * vp[good] + plane.normal[2])
    out.update(sigma_z_m=sigma, stderr_m=sigma * rel_se,
               plane_distance_sigma_m=sigma * float(np.median(cosine)))
    return out


#: Width [m] of the depth bins of :func:`axial_noise_bins`.
DEPTH_BIN_M = 0.1
#: A depth bin with fewer pixels than this is left out (its median variance would scatter too much).
MIN_BIN_PIXELS = 100


def axial_noise_bins(samples_m, up, vp, plane: Plane, depth_scale: float | None = None, bin_m: float = DEPTH_BIN_M,
                     min_pixels: int = MIN_BIN_PIXELS, min_valid_fraction: float = 0.5,
                     frame_correction: bool = True) -> dict:
    """Axial noise of one capture per depth bin: :func:`axial_noise` over the pixels of each bin of plane depth.

    A plane seen at a grazing angle (a floor from a robot) spans a wide range of depths, over which sigma_z
    changes many times over; one median over all its pixels would say little. The pixels' temporal
    variances (steps 1-3 of :func:`axial_noise`, the frame correction fitted over the whole region) are
    grouped by their plane depth into bins ``bin_m`` wide (edges at multiples of ``bin_m``), and each
    bin's sigma is the median of its variances with Sheppard's correction (step 4).

    Parameters
    ----------
    samples_m, up, vp, plane, depth_scale, min_valid_fraction, frame_correction
        As :func:`axial_noise`.
    bin_m : float
        Bin width [m].
    min_pixels : int
        Bins with fewer usable pixels are left out.

    Returns
    -------
    dict
        ``bins``: one dict per bin, nearest first: ``z_range_m`` [lo, hi), ``z_m`` (median plane depth of its
        pixels), ``sigma_z_m``, ``stderr_m``, ``n_pixels``, and ``_z_pixels_m`` (the plane depth of each of its
        pixels, for predictions); ``theta_rad`` (the plane's incidence angle), ``n_frames``, ``n_pixels``,
        ``reason`` (why there are no bins, else None).
    """
    width = check_positive_scalar(bin_m, "bin_m", upper=10.0, unit=" m")
    out, good, var_p, n_g = _pixel_variances(samples_m, up, vp, plane, min_valid_fraction, frame_correction)
    res = {"bins": [], "theta_rad": plane.theta_rad, "n_frames": out["n_frames"], "n_pixels": out["n_pixels"],
           "reason": out["reason"]}
    if var_p is None:
        return res
    up = np.asarray(up, dtype=np.float64).ravel()
    vp = np.asarray(vp, dtype=np.float64).ravel()
    z_pl = plane.depth_at(up[good], vp[good])
    k = np.floor(z_pl / width + 1e-9).astype(np.int64)
    for b in np.unique(k):
        sel = k == b
        if sel.sum() < max(10, int(min_pixels)):
            continue
        sigma, rel_se = _sigma_from_variances(var_p[sel], n_g[sel], depth_scale)
        res["bins"].append({"z_range_m": [round(float(b * width), 9), round(float((b + 1) * width), 9)],
                            "z_m": float(np.median(z_pl[sel])), "sigma_z_m": sigma, "stderr_m": sigma * rel_se,
                            "n_pixels": int(sel.sum()), "_z_pixels_m": z_pl[sel]})
    if not res["bins"]:
        res["reason"] = f"no depth bin of {width:g} m holds {max(10, int(min_pixels))} usable pixels"
    return res


# ------------------------------------------------------------------------------------------------
# lateral noise


def edge_positions(on_target, side: str, start_col) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel edge position per frame and row from a window of pixels classified on/off target.

    The window of each row holds W pixels starting at column ``start_col[r]``; the target lies to the
    right of a ``left`` edge and to the left of a ``right`` edge. The edge is placed where the count of
    on-target pixels says (a count is robust to isolated misclassified pixels): for a left edge at
    ``start + W - count - 0.5``, for a right edge at ``start + count - 0.5`` (pixel centres at integer
    columns, so this is the boundary between the last off- and the first on-target pixel).

    Parameters
    ----------
    on_target : array_like of bool, shape (N, R, W)
        Per frame, row and window pixel: does it belong to the target?
    side : {"left", "right"}
    start_col : array_like of int, shape (R,)
        First column of each row's window [px].

    Returns
    -------
    position_px : ndarray, shape (N, R)
        Edge column [px].
    saturated : ndarray of int8, shape (N, R)
        0 where the edge lies inside the window; -1 where it lies at or left of the window (its
        position is then only an upper bound), +1 at or right of it (a lower bound).
    """
    a = np.asarray(on_target)
    if a.ndim != 3 or a.dtype != bool:
        raise ValueError(f"on_target must be a boolean array (frames, rows, window), got {a.dtype} {a.shape}")
    if side not in ("left", "right"):
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")
    start = np.asarray(start_col)
    if start.shape != (a.shape[1],):
        raise ValueError(f"start_col must have shape ({a.shape[1]},), got {start.shape}")
    W = a.shape[2]
    count = a.sum(axis=2)
    sat = np.zeros(count.shape, dtype=np.int8)
    if side == "left":
        pos = start[None, :] + W - count - 0.5
        sat[count == W] = -1
        sat[count == 0] = 1
    else:
        pos = start[None, :] + count - 0.5
        sat[count == 0] = -1
        sat[count == W] = 1
    return pos.astype(np.float64), sat


def _censored_normal(x, lower, upper) -> tuple[float, float]:
    """ML mean and standard deviation of a normal sample, some values known only as <= lower[k]
    (left-censored) or >= upper[k] (right-censored)."""
    x = np.asarray(x, dtype=np.float64)
    lower = np.asarray(lower, dtype=np.float64)
    upper = np.asarray(upper, dtype=np.float64)
    mu0 = float(np.mean(x))
    sd0 = float(np.std(x, ddof=1)) if x.size > 1 else 0.0
    if lower.size == 0 and upper.size == 0:
        return mu0, sd0
    if not sd0 > 0:
        sd0 = float(np.std(np.concatenate([x, lower, upper]))) or 1.0

    # standardised units, so the simplex starts at a sensible size whatever the data's scale
    xs, lo, hi = (x - mu0) / sd0, (lower - mu0) / sd0, (upper - mu0) / sd0

    def nll(theta):
        mu, ls = theta
        sd = math.exp(ls)
        v = -np.sum(stats.norm.logpdf(xs, mu, sd))
        v -= np.sum(stats.norm.logcdf((lo - mu) / sd))
        v -= np.sum(stats.norm.logsf((hi - mu) / sd))
        return v

    res = optimize.minimize(nll, [0.0, 0.0], method="Nelder-Mead",
                            options={"xatol": 1e-7, "fatol": 1e-10, "maxiter": 4000,
                                     "initial_simplex": [[0.0, 0.0], [0.5, 0.0], [0.0, 0.5]]})
    res_x = (mu0 + sd0 * res.x[0], math.log(sd0) + res.x[1])
    n = x.size + lower.size + upper.size
    return float(res_x[0]), float(math.exp(res_x[1]) * math.sqrt(n / max(n - 1, 1)))


def _edge_spread(pos, sat, rows):
    """Line fit over all frames, frame offsets (censored-normal variance) and within-frame variance.

    Returns (between_sd, within_var, n_used, n_censored, offsets, slope) or a reason string."""
    N, R = pos.shape
    ok = (sat == 0) & np.isfinite(pos)
    censored = (1.0 - ok.mean(axis=1)) > 0.5
    use = ~censored
    vv = np.broadcast_to(rows, pos.shape)
    m = ok & use[:, None]
    A = np.stack([vv[m], np.ones(int(m.sum()))], axis=1)
    (a, b), *_ = np.linalg.lstsq(A, pos[m], rcond=None)
    line = a * rows + b
    r = np.where(m, pos - line[None, :], np.nan)
    offsets = np.nanmean(r[use], axis=1)
    resid = r[use] - offsets[:, None]
    n_within = int(np.isfinite(resid).sum())
    dof = n_within - int(use.sum()) - 2
    within_var = float(np.nansum(resid * resid) / dof) if dof > 0 else 0.0
    lower, upper = [], []
    for f in np.flatnonzero(censored):
        fin = np.isfinite(pos[f])
        if not fin.any():
            continue
        lim = float(np.mean(pos[f][fin] - line[fin]))
        if np.sum(sat[f]) < 0:          # the edge left the window on its low side: offset <= lim
            lower.append(lim)
        else:
            upper.append(lim)
    _, between = _censored_normal(offsets, lower, upper)
    return between, within_var, int(use.sum()), int(censored.sum()), offsets, float(a)


def lateral_noise(position_px, saturated, rows, m_per_px: float, min_frames: int = 2, position_m=None) -> dict:
    """Lateral noise of one vertical edge of a board over the frames of a capture.

    A line u = a v + b is fitted to the edge positions of all frames (rows with the corners removed);
    each frame's offset from it is the mean over its rows, and the **spread of the edge pixels about the
    line** is sigma^2 = (variance of the frame offsets) + (pooled variance of the pixels about their
    frame's offset). Frames whose edge left the window (more than half of their rows saturated: the edge
    moved out of the image, or beyond the window) are censored observations, not dropped: the offsets'
    variance is a censored-normal maximum-likelihood estimate. Edge positions are whole pixels, which
    adds 1/12 px^2; Sheppard's correction removes it where the spread reaches a pixel.

    The same statistics of ``position_m`` (the positions mapped onto the target's plane, across the
    edge) give sigma in metres; without it, sigma_px x ``m_per_px``. Mapping each position keeps the
    metres exact where the image scale changes across the edge's motion (a board seen obliquely and
    near, whose edge moves by many pixels).

    Parameters
    ----------
    position_px, saturated : ndarray, shape (N, R)
        From :func:`edge_positions`.
    rows : array_like, shape (R,)
        Image row of each column of those arrays [px].
    m_per_px : float
        Metres along the target, across the edge, per pixel of edge motion along an image row, at the
        edge [m/px] (Sheppard's correction in metres; the conversion without ``position_m``).
    min_frames : int
        Fewer uncensored frames than this: not measurable.
    position_m : array_like, shape (N, R), optional
        Edge positions on the target across the edge [m] (NaN where the ray misses the plane).

    Returns
    -------
    dict
        ``sigma_px``, ``sigma_m`` (None with ``reason`` when not measurable), ``stderr_m``,
        ``between_px`` (standard deviation of the frame offsets), ``within_px`` (of the pixels about
        their frame's offset), ``n_frames``, ``n_censored``, ``dof`` (uncensored frames - 1, the
        degrees of freedom of sigma for :func:`lateral_percentile`), ``n_rows``, ``slope`` (du/dv),
        ``m_per_px``, ``frame_offsets_px`` (uncensored frames' offsets from the line).
    """
    pos = np.asarray(position_px, dtype=np.float64)
    sat = np.asarray(saturated)
    rows = np.asarray(rows, dtype=np.float64)
    if pos.ndim != 2 or sat.shape != pos.shape or rows.shape != (pos.shape[1],):
        raise ValueError(f"position_px, saturated (N, R) and rows (R,) do not match: {pos.shape}, {sat.shape}, "
                         f"{rows.shape}")
    mpp = check_positive_scalar(m_per_px, "m_per_px", upper=10.0, unit=" m/px")
    pos_m = None
    if position_m is not None:
        pos_m = np.asarray(position_m, dtype=np.float64)
        if pos_m.shape != pos.shape:
            raise ValueError(f"position_m must have the shape of position_px {pos.shape}, got {pos_m.shape}")
    N, R = pos.shape
    out = {"sigma_px": None, "sigma_m": None, "stderr_m": None, "between_px": None, "within_px": None,
           "n_frames": int(N), "n_censored": 0, "dof": None, "n_rows": int(R), "slope": None, "m_per_px": mpp,
           "frame_offsets_px": [], "reason": None}
    if R < 3:
        out["reason"] = f"the edge spans only {R} rows once the corners are removed"
        return out
    n_use = int(((1.0 - (sat == 0).mean(axis=1)) <= 0.5).sum())
    if n_use < max(2, int(min_frames)):
        out["reason"] = (f"the edge stays inside the image in only {n_use} of {N} frames "
                         f"(need {max(2, int(min_frames))})")
        return out
    between, within_var, n_eff, n_cens, offsets, slope = _edge_spread(pos, sat, rows)
    total = between * between + within_var
    sheppard = total >= 1.0
    if sheppard:
        total -= 1.0 / 12.0
    sigma_px = math.sqrt(max(total, 0.0))
    if pos_m is None:
        sigma_m = sigma_px * mpp
    else:
        b_m, w_m, *_ = _edge_spread(pos_m, np.where(np.isfinite(pos_m), sat, 1).astype(np.int8), rows)
        tm = b_m * b_m + w_m - (mpp * mpp / 12.0 if sheppard else 0.0)
        sigma_m = math.sqrt(max(tm, 0.0))
    out.update(sigma_px=sigma_px, sigma_m=sigma_m, stderr_m=sigma_m / math.sqrt(2.0 * max(n_eff - 1, 1)),
               between_px=float(between), within_px=math.sqrt(within_var), n_censored=n_cens,
               dof=int(n_eff - 1), slope=slope, frame_offsets_px=[float(o) for o in offsets])
    return out


def lateral_percentile(sigmas_m, dof, q: float = LATERAL_PERCENTILE) -> dict:
    """The q-th percentile of the captures' lateral noise, with their sampling error removed.

    Each capture's estimate s_i (a standard deviation with k_i degrees of freedom) scatters about its
    true value; the raw percentile of the s_i therefore grows with the sampling error (for identical true
    values and k = 19 it is biased up by about 1.28 / sqrt(2 k) = 21 % at q = 90). The estimates are
    compared on the log-variance scale, where the sampling error no longer depends on the value:
    y_i = log s_i^2 - (digamma(k_i / 2) - log(k_i / 2)) is unbiased for log sigma_i^2 with variance
    v_i = trigamma(k_i / 2). The spread of the true values beyond the sampling errors, tau^2, is the
    DerSimonian-Laird moment estimate (:func:`noise_model.formulas.dersimonian_laird_tau2`); each y_i is
    shrunk towards the precision-weighted mean by tau^2 / (tau^2 + v_i) (empirical Bayes) and the
    percentile of the shrunk values estimates the percentile of the true values. With tau = 0 (all
    captures alike) it is their weighted geometric mean.

    Parameters
    ----------
    sigmas_m : array_like, shape (K,)
        Per-capture lateral noise [m] (or [px]); non-finite or non-positive entries are ignored.
    dof : array_like, shape (K,)
        Degrees of freedom of each estimate (frames used - 1), >= 1.
    q : float
        Percentile in [0, 100].

    Returns
    -------
    dict
        ``value_m`` (None when no capture), ``raw_percentile_m`` (of the s_i as they are), ``mean_m``
        (exp of the weighted mean of log sigma), ``tau_log`` (tau^2 on the log-variance scale, as a
        relative spread of sigma: sqrt(tau^2) / 2), ``n``.
    """
    from scipy import special

    s = np.asarray(sigmas_m, dtype=np.float64).ravel()
    k = np.asarray(dof, dtype=np.float64).ravel()
    if s.shape != k.shape:
        raise ValueError(f"sigmas_m and dof must have the same shape, got {s.shape} and {k.shape}")
    if not 0.0 <= float(q) <= 100.0:
        raise ValueError(f"q must be a percentile in [0, 100], got {q}")
    keep = np.isfinite(s) & (s > 0) & np.isfinite(k) & (k >= 1)
    s, k = s[keep], k[keep]
    out = {"value_m": None, "raw_percentile_m": None, "mean_m": None, "tau_log": None, "n": int(s.size)}
    if s.size == 0:
        return out
    y = np.log(s * s) - (special.digamma(0.5 * k) - np.log(0.5 * k))
    v = special.polygamma(1, 0.5 * k)
    w = 1.0 / v
    mean_w = float(np.sum(w * y) / np.sum(w))
    tau2 = 0.0
    if s.size > 1:
        s1, s2 = float(np.sum(w)), float(np.sum(w * w))
        excess = float(np.sum(w * (y - mean_w) ** 2)) - (s.size - 1)         # Cochran's Q - (K - 1)
        tau2 = float(dersimonian_laird_tau2(excess, s1, s2)) if s1 - s2 / s1 > 0 else 0.0
    w2 = 1.0 / (v + tau2)
    mean = float(np.sum(w2 * y) / np.sum(w2))
    shrunk = mean + tau2 / (tau2 + v) * (y - mean)
    out.update(value_m=float(np.exp(0.5 * np.percentile(shrunk, q))), raw_percentile_m=float(np.percentile(s, q)),
               mean_m=float(np.exp(0.5 * mean)), tau_log=0.5 * math.sqrt(tau2))
    return out


# ------------------------------------------------------------------------------------------------
# systematic error


def known_plane(distance_m: float, yaw_deg: float = 0.0, pitch_deg: float = 0.0) -> Plane:
    """The target plane of a capture as measured by hand: centre (0, 0, distance_m), normal R e_z with
    R = R_y(yaw) R_x(pitch) (capture-set convention)."""
    d = check_positive_scalar(distance_m, "distance_m", upper=100.0, unit=" m")
    n = target_rotation(yaw_deg, pitch_deg)[:, 2]
    if n[2] < 0:
        n = -n
    if abs(n[2]) < 1e-9:
        raise ValueError(f"yaw {yaw_deg} deg, pitch {pitch_deg} deg turn the target edge-on")
    return Plane(n, float(n[2] * d))


def systematic_error(mean_depth_m, known_depth_m) -> dict:
    """Systematic depth error: the mean of the frames against the known target depth.

    Parameters
    ----------
    mean_depth_m, known_depth_m : array_like, shape (M,)
        Per pixel, the mean of the frames' depth and the known plane's depth [m]; non-finite ignored.

    Returns
    -------
    dict
        ``rms_error_m`` = sqrt(mean((mean - known)^2)), ``mean_error_m`` (the bias, mean - known),
        ``n_pixels``; None values when no pixel is finite in both.
    """
    a = np.asarray(mean_depth_m, dtype=np.float64).ravel()
    b = np.asarray(known_depth_m, dtype=np.float64).ravel()
    if a.shape != b.shape:
        raise ValueError(f"mean_depth_m and known_depth_m must have the same shape, got {a.shape}, {b.shape}")
    ok = np.isfinite(a) & np.isfinite(b)
    if not ok.any():
        return {"rms_error_m": None, "mean_error_m": None, "n_pixels": 0}
    d = a[ok] - b[ok]
    return {"rms_error_m": float(np.sqrt(np.mean(d * d))), "mean_error_m": float(np.mean(d)),
            "n_pixels": int(ok.sum())}


def eq1_rms_error(distance_m, fx_px: float, width_px: int, baseline_m: float = 0.050, subpixel: float = 0.08):
    """The paper's equation (1) for a camera with focal length ``fx_px``: e = d^2 s / (f b) [m].

    :func:`noise_model.d435.expected_rms_error` with the field of view that gives this focal length.
    """
    fx = check_positive_scalar(fx_px, "fx_px", upper=1e5, unit=" px")
    w = check_positive_scalar(width_px, "width_px", upper=1e5, unit=" px")
    hfov = math.degrees(2.0 * math.atan(0.5 * w / fx))
    return expected_rms_error(distance_m, subpixel=subpixel, baseline=baseline_m, width_px=w, hfov_deg=hfov)


# ------------------------------------------------------------------------------------------------
# the model fit


def axial_model(z, theta, c0, c1, c2, c_theta):
    """sigma_z = c0 + c1 z + c2 z^2 + c_theta z^(3/2) theta / (pi/2 - theta)^2 [m] (no angle cap), for any
    coefficients: :func:`noise_model.formulas.sigma_z_from_gain` with :func:`noise_model.formulas.angle_gain`.

    Parameters
    ----------
    z, theta : array_like
        Depth [m] and incidence angle [rad] in [0, pi/2) (broadcast together).
    c0, c1, c2, c_theta : float
        Coefficients [m], [-], [1/m], [m^-1/2].
    """
    z = np.asarray(z, dtype=np.float64)
    t = np.asarray(theta, dtype=np.float64)
    return sigma_z_from_gain(z, angle_gain(t, c_theta), c0, c1, c2)


@dataclass(frozen=True)
class AxialFit:
    """The paper's functional form fitted to measured axial noise.

    Attributes
    ----------
    coefficients : tuple of 4 floats
        (c0 [m], c1 [-], c2 [1/m], c_theta [m^-1/2]).
    stderr : tuple of 4 floats
        Their standard errors (from the fit's covariance, scaled by the residual).
    residual_rms_rel : float
        Root mean square of (measured - fitted) / fitted over the captures [-].
    residual_rms_m : float
        Root mean square of measured - fitted [m].
    n : int
        Captures fitted.
    inliers : ndarray of bool, shape (K,)
        Which of the captures given were fitted (the others disagreed with them).
    """

    coefficients: tuple
    stderr: tuple
    residual_rms_rel: float
    residual_rms_m: float
    n: int
    inliers: np.ndarray = None

    def sigma_z(self, z, theta=0.0):
        """The fitted sigma_z [m] at depth z [m] and incidence angle theta [rad]."""
        return axial_model(z, theta, *self.coefficients)

    def to_dict(self) -> dict:
        return {"coefficients": [float(c) for c in self.coefficients], "stderr": [float(s) for s in self.stderr],
                "residual_rms_rel": self.residual_rms_rel, "residual_rms_m": self.residual_rms_m, "n": self.n}


def fit_axial_model(z_m, theta_rad, sigma_m, p0=None, iterations: int = 3, robust: bool = True) -> AxialFit:
    """Fit sigma_z(z, theta) = c0 + c1 z + c2 z^2 + c_theta z^(3/2) theta / (pi/2 - theta)^2.

    Weighted least squares with ``scipy.optimize.curve_fit``: the sampling error of a measured standard
    deviation is proportional to it, so each capture's residual is taken relative to the fitted value
    (iteratively reweighted: weights from the previous fit, starting from the measured values, so that a
    capture measured low is not favoured). Standard errors come from the covariance scaled by the
    residual (``absolute_sigma=False``): they include the model's misfit, not only sampling error.

    With ``robust`` (and at least 8 captures), a first fit with a soft-L1 loss finds the captures whose
    relative residual exceeds max(4 robust sigma, 10 %) (a capture whose target was partly hidden, a
    wrong distance in captures.json); the final least-squares fit leaves them out (``AxialFit.inliers``).

    Parameters
    ----------
    z_m, theta_rad, sigma_m : array_like, shape (K,)
        Per capture: depth [m] (> 0), incidence angle [rad] in [0, pi/2), measured sigma_z [m] (> 0).
        K >= 5.
    p0 : sequence of 4 floats, optional
        Start (the paper's coefficients by default).
    iterations : int
        Reweighting rounds.
    robust : bool
        Leave out captures that disagree with the others (see above).

    Returns
    -------
    AxialFit
    """
    z, t, s = check_axial_points(z_m, theta_rad, sigma_m)
    if z.size < 5:
        raise ValueError(f"fitting 4 coefficients needs at least 5 captures with axial noise, got {z.size}")
    p = np.asarray(D435.axial_coefficients if p0 is None else p0, dtype=np.float64)
    if p.shape != (4,):
        raise ValueError(f"p0 must hold 4 coefficients, got {p.shape}")
    X = np.vstack([z, t])

    def f(X, c0, c1, c2, ct):
        return axial_model(X[0], X[1], c0, c1, c2, ct)

    def fit_once(mask, p_start, robust):
        wfrom = s[mask].copy()
        pp, cov = p_start, None
        for _ in range(max(1, int(iterations))):
            kw = {"method": "trf", "loss": "soft_l1", "f_scale": 0.05} if robust else {}
            pp, cov = optimize.curve_fit(f, X[:, mask], s[mask], p0=pp, sigma=wfrom, absolute_sigma=False,
                                         maxfev=20000, **kw)
            pred_m = f(X[:, mask], *pp)
            if np.all(pred_m > 0):
                wfrom = pred_m
        return pp, cov

    inl = np.ones(s.size, dtype=bool)
    if robust and s.size >= 8:
        # a robust (soft-L1) fit of the relative residuals finds captures that disagree with the rest
        p_r, _ = fit_once(inl, p, True)
        pred = f(X, *p_r)
        with np.errstate(invalid="ignore", divide="ignore"):
            rel = (s - pred) / pred
        mad = 1.4826 * float(np.median(np.abs(rel - np.median(rel))))
        inl = np.isfinite(rel) & (np.abs(rel) <= max(4.0 * mad, 0.1))
        if inl.sum() < 5:
            inl = np.ones(s.size, dtype=bool)
        p = p_r
    p, pcov = fit_once(inl, p, False)
    pred = f(X, *p)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = (s - pred) / pred
    stderr = np.sqrt(np.diag(pcov)) if pcov is not None and np.all(np.isfinite(pcov)) else np.full(4, np.nan)
    return AxialFit(tuple(float(c) for c in p), tuple(float(e) for e in stderr),
                    float(np.sqrt(np.mean(rel[inl] ** 2))), float(np.sqrt(np.mean((s - pred)[inl] ** 2))),
                    int(inl.sum()), inl)


def model_from_fit(coefficients, sigma_L_m: float | None = None, sigma_R_m: float | None = None,
                   name: str = "D435 (own characterisation)", base: SensorModel = D435,
                   baseline_m: float | None = None, mode: tuple[int, int, float] | None = None,
                   disparity: tuple[float, float] | None = None) -> SensorModel:
    """A :class:`noise_model.SensorModel` holding a user's own fit (save it with ``SensorModel.save``).

    Parameters
    ----------
    coefficients : sequence of 4 floats or None
        (c0, c1, c2, c_theta) from :func:`fit_axial_model` (None: ``base``'s, for a disparity model whose
        paper-family coefficients were not fitted).
    sigma_L_m, sigma_R_m : float, optional
        Lateral noise [m]; ``base``'s where None (not measured: walls only).
    name : str
    base : SensorModel
        Everything else (subpixel, angle cap, other modes' fields of view) is taken from it.
    baseline_m : float, optional
        The camera's stereo baseline [m].
    mode : (width, height, fx), optional
        The characterised depth mode and its focal length [px]: its horizontal field of view
        2 atan(width / (2 fx)) replaces the default of that mode.
    disparity : (s0, s1), optional
        sigma_d(theta) = s0 + s1 theta^2 [px] (:func:`noise_model.analysis.family_fit.fit_disparity_model`):
        the model is then of the disparity family.
    """
    changes = {"name": str(name)}
    if sigma_L_m is not None:
        changes["sigma_L"] = check_positive_scalar(sigma_L_m, "sigma_L_m", upper=10.0, unit=" m")
    if sigma_R_m is not None:
        changes["sigma_R"] = check_positive_scalar(sigma_R_m, "sigma_R_m", upper=10.0, unit=" m")
    if baseline_m is not None:
        changes["baseline_m"] = check_positive_scalar(baseline_m, "baseline_m", upper=2.0, unit=" m")
    model = base.with_coefficients(base.axial_coefficients if coefficients is None else coefficients, **changes)
    if disparity is not None:
        model = model.with_disparity(float(disparity[0]), float(disparity[1]), name=model.name)
    if mode is not None:
        w, h, fx = int(mode[0]), int(mode[1]), check_positive_scalar(mode[2], "fx", upper=1e5, unit=" px")
        hfov = dict(model.hfov_deg)
        hfov[(w, h)] = math.degrees(2.0 * math.atan(0.5 * w / fx))
        model = replace(model, hfov_deg=hfov)
    return model
