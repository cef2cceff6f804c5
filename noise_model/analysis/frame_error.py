"""What one frame's depth error looks like to a map: its size against the modelled sigma, and its correlation.

The axial model is fitted to the per-pixel *temporal* standard deviation of static captures
(:func:`noise_model.analysis.characterization.axial_noise`). A map built by a moving camera sees more:

* a **static** error pattern (the stereo matcher's fixed response to the projector's texture and the
  imagers' pixels) is the same in every frame of a static capture, so its temporal standard deviation
  cannot see it, yet a moving camera sees each terrain cell through other pixels in every frame: to the
  map it is part of each frame's error. Per-frame error variance = temporal + static;
* that error is **correlated across the image** over a few pixels (the matcher's window), so the m
  pixels one frame puts in a map cell are fewer than m independent samples.

Per capture (interior pixels of the target, disparity d = f B / z [px], F frames; the lag covariances
of :mod:`noise_model.analysis.effect_fits.correlation`, which the gap's direct measurements use too):

    T(h) = lag covariance of d_t - mean_t(d) less each frame's mean over the interior, times F / (F - 1)
    S(h) = the static part's lag covariance (the temporal mean's residual about its best plane, less the
           temporal share T(h) / F)
    O    = the frame-wide offset's variance: the covariance over frames of the mean of d_t - mean_t(d) over
           the interior's left third of columns with its mean over the right third
    C(h) = T(h) + S(h),  ratio = (C(0) + O) / T(0),  rho(h) = C(h) / C(0)

and the Gaussian correlation length l of rho(h) = exp(-h^2 / (2 l^2)) over the lags 1-11 px, where the
lag-1 correlation is at least :data:`MIN_LAG1_CORRELATION` (below, the pixels count as independent:
l = 0). The residual is taken about the best plane of the temporal mean, so a capture of fitted
geometry (no measured distance) is measured the same way: a plane fitted to its own frames absorbs the
board-scale error, not a pattern a few pixels across.

The frame-wide offset (every pixel of a frame off by the same disparity) is part of each frame's error
as a map sees it: a cell's points of one frame share it, and the next frame draws another. The axial
model's fit removes it (it removes each frame's plane motion), so the ratio carries it. It is measured
as a covariance of two disjoint parts of the frame, not as the variance of the frame's mean, because
that variance also holds the pixels' own noise averaged over the interior; the middle third between the
two parts keeps the pixel-scale correlation (a few px) out of the covariance. The correlation length
describes the pixel-scale part C only: the offset is common to the whole frame, and a map cell's points
of one frame lie within a few correlation lengths, where the offset adds to C(h) at every lag alike.

Pooled over captures (:func:`pooled_frame_error`): the medians of the ratio and of the length (captures
with no correlation count as 0).

NumPy only; no files.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from .effect_fits.correlation import fit_gaussian_cov, lag_cov, static_lag_cov

__all__ = ["FRAME_ERROR_LAGS", "MIN_LAG1_CORRELATION", "MIN_FRAMES", "MAX_RATIO", "capture_frame_error",
           "frame_offset_covariance", "pooled_frame_error"]

#: Lags [px] of the correlation: the span of a map cell's pixels (a 4 cm cell is 2-20 px across).
FRAME_ERROR_LAGS = (0, 1, 2, 3, 4, 6, 8, 11)
#: Fewest frames a capture needs: the temporal lag covariance of 2-4 frames is too rough to divide by (a
#: recording whose frames repeat has none at all).
MIN_FRAMES = 5
#: Largest per-frame over temporal variance ratio taken as a measurement: beyond, the "static" part is not
#: a noise pattern but the target itself (not a plane, something in front of it).
MAX_RATIO = 100.0
#: Lag-1 correlation below which a capture's pixels count as independent (length 0). Independent pixels
#: give |rho(1)| of about 1 / sqrt(pairs) (< 0.01 on a capture's thousands of pixels x frames); the
#: Gaussian fit on such noise returns any length at all.
MIN_LAG1_CORRELATION = 0.1


def capture_frame_error(c) -> dict:
    """The per-frame error of one capture (``CaptureData``; measured with >= :data:`MIN_FRAMES` frames).

    Returns
    -------
    dict
        ``id``, ``distance_m``, ``temporal_var_d_px2`` (T(0)), ``static_var_d_px2`` (S(0), >= 0),
        ``offset_var_d_px2`` (O, >= 0; :func:`frame_offset_covariance`), ``ratio`` ((C(0) + O) / T(0), >= 1),
        ``rho`` (rho(h) over :data:`FRAME_ERROR_LAGS`), ``length_px`` (0 when not correlated); ``reason``
        (str) and NaN values when fewer than 100 interior pixels have data in every frame, the capture has
        fewer than :data:`MIN_FRAMES` frames or the ratio exceeds :data:`MAX_RATIO`.
    """
    g = c.geometry
    nan = float("nan")
    row = {"id": c.id, "distance_m": float(g.distance_m), "temporal_var_d_px2": nan, "static_var_d_px2": nan,
           "offset_var_d_px2": nan, "ratio": nan, "rho": [nan] * len(FRAME_ERROR_LAGS), "length_px": nan,
           "reason": None}
    F = c.n_frames
    m, z = c.interior()
    fb = g.fb_px_m
    if m.any():                 # the interior's bounding box: the lag sums need nothing outside it
        rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
        box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        m, z = m[box], z[box]
        c = SimpleNamespace(n_frames=F, depth_m=c.depth_m[(slice(None),) + box])
    with np.errstate(divide="ignore", invalid="ignore"):
        d = fb / c.depth_m
        dtrue = fb / z
    ok = m & np.all(np.isfinite(d), axis=0)
    if F < MIN_FRAMES or ok.sum() < 100:
        row["reason"] = (f"{int(ok.sum())} interior pixels with data in all {F} frames (need 100 and "
                         f"{MIN_FRAMES} frames)")
        return row
    dev = d[:, ok] - d[:, ok].mean(axis=0)
    dev_mean = dev.mean(axis=1)
    dev -= dev_mean[:, None]
    x = np.zeros((F,) + ok.shape)
    x[:, ok] = dev
    T, _ = lag_cov(x, ok, FRAME_ERROR_LAGS)
    T = T * F / (F - 1)
    S = static_lag_cov(c, m, fb, dtrue, np.ones(z.shape), FRAME_ERROR_LAGS)
    S = np.zeros_like(T) if S is None else S[0]
    if not S[0] > 0.0:                      # no static part measurable: none
        S = np.zeros_like(T)
    C = T + S
    if not (np.all(np.isfinite(C)) and T[0] > 0.0):
        row["reason"] = "the lag covariances are not finite"
        return row
    if C[0] / T[0] > MAX_RATIO:
        row["reason"] = (f"the error about the target's plane is {C[0] / T[0]:.0f} times its temporal variance: "
                         "the target is not the plane the capture names")
        return row
    rho = C / C[0]
    offset = frame_offset_covariance(dev + dev_mean[:, None], np.nonzero(ok)[1])
    row.update(temporal_var_d_px2=float(T[0]), static_var_d_px2=float(S[0]), offset_var_d_px2=offset,
               ratio=float((C[0] + offset) / T[0]), rho=[float(r) for r in rho])
    if rho[1] < MIN_LAG1_CORRELATION:
        row["length_px"] = 0.0
    else:
        _, ell = fit_gaussian_cov(np.array(FRAME_ERROR_LAGS[1:], dtype=float), rho[1:], lmin=0.3, lmax=80.0)
        row["length_px"] = float(ell)
    return row


def frame_offset_covariance(dev_px, cols) -> float:
    """Variance [px^2] of the error every pixel of a frame shares (the frame-wide offset), as a covariance.

    Not :func:`noise_model.analysis.effect_fits.disparity.frame_offset_variance`: that one is the variance
    over frames of a frame's weighted mean deviation, which also holds the mean's share of the pixels' own
    noise, and the ``frame_offset`` fit subtracts a base simulation's to remove it. A per-frame error
    measured on a capture alone has no base to subtract, so it needs an estimate free of that share.

    Parameters
    ----------
    dev_px : ndarray, shape (F, M)
        Each of M pixels' disparity in F frames less its mean over the frames [px] (F >= 2).
    cols : ndarray of int, shape (M,)
        The pixels' image columns.

    Returns
    -------
    float
        cov_t(a_t, b_t) >= 0, a_t and b_t frame t's mean of ``dev_px`` over the pixels in the left and the
        right third of the columns (module docstring): the pixels' own noise, independent between the two
        parts, leaves the covariance unbiased where the variance of the frame's mean would hold it. 0 when
        a part is empty or the covariance is negative (an offset too small to measure).
    """
    dev_px = np.asarray(dev_px, dtype=np.float64)
    cols = np.asarray(cols)
    if dev_px.ndim != 2 or cols.shape != (dev_px.shape[1],) or dev_px.shape[0] < 2:
        raise ValueError(f"dev_px must have shape (frames >= 2, pixels) and cols one column per pixel, got "
                         f"{dev_px.shape} and {cols.shape}")
    if not np.all(np.isfinite(dev_px)):
        raise ValueError("dev_px must be finite (the pixels with data in every frame)")
    lo, hi = np.quantile(cols, [1.0 / 3.0, 2.0 / 3.0]) if cols.size else (0.0, 0.0)
    left, right = cols < lo, cols > hi
    if not (left.any() and right.any()):
        return 0.0
    a, b = dev_px[:, left].mean(axis=1), dev_px[:, right].mean(axis=1)
    cov = float(np.sum((a - a.mean()) * (b - b.mean())) / (dev_px.shape[0] - 1))
    return max(cov, 0.0)


def pooled_frame_error(rows) -> dict:
    """The medians over captures of :func:`capture_frame_error`'s rows that hold a measurement.

    Returns
    -------
    dict
        ``frame_variance_ratio`` (>= 1), ``error_correlation_px`` (0: not correlated), ``n_captures``;
        None values (and ``n_captures`` 0) when no capture holds one.
    """
    good = [r for r in rows if math.isfinite(r.get("ratio", float("nan")))]
    if not good:
        return {"frame_variance_ratio": None, "error_correlation_px": None, "n_captures": 0}
    ratio = float(np.median([r["ratio"] for r in good]))
    ell = float(np.median([r["length_px"] for r in good]))
    return {"frame_variance_ratio": max(ratio, 1.0), "error_correlation_px": ell, "n_captures": len(good)}
