"""Direct measurements of the depth effects in a capture set, to check the diagnosis's fitted parameters.

The diagnosis (:func:`noise_model.analysis.diagnosis.diagnose`) states every effect as a parameter fitted
to make the reference simulation look like the real captures. Where a parameter has a meaning of its
own, it can also be read off the captures directly, with no simulation: this module does that, and
:func:`check_fitted` puts each fitted parameter next to its direct measurement.

Direct measurements, on each capture's target interior (``noise_model.analysis.capture_data``
regions; d = f B / z the disparity [px], F frames):

``disparity_step_px``
    The lattice the disparities sit on (E2): the median spacing of consecutive distinct disparity values
    of the captures at >= 1 m, where the depth unit is finer than one disparity step.
``band_margin_px``
    The left invalid band's width beyond f B / z (E6): per row of a wall at <= 30 deg, the first column
    with data in at least half the frames, minus f B / z_true there; the median over rows and walls.
``temporal_sigma_d_px`` / ``static_sigma_d_px``
    The per-pixel standard deviation over frames (root mean square over pixels), and the standard
    deviation of the per-pixel mean about its best plane with the temporal share removed (E1, E10).
``frame_offset_px``
    The frame-wide part of the temporal noise: the standard deviation over frames of each frame's mean
    deviation from the temporal mean over the interior.
``temporal_length_px`` / ``static_length_px``
    Correlation lengths l of exp(-h^2 / (2 l^2)) fitted to the lag correlation of the per-frame
    deviations from the temporal mean less the frame-wide part, and of the static part (the temporal
    mean's lag covariance minus the temporal share, as the static fits read it) (E9, E10).

Units: px of the captures' stream, m. No files, no simulation of its own: the caller passes the captures
and, for :func:`check_fitted`, the same measurements on the final model's simulation where a figure
(sigma_d) is a property of the whole model rather than of one parameter.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from ..capture_data import REGION_INTERIOR, REGION_LEFT_BAND
from ..effect_fits.correlation import _STATIC_NOISE_LAGS, fit_gaussian_cov, lag_cov, static_lag_cov

__all__ = ["capture_measurements", "direct_measurements", "check_fitted", "TOLERANCE"]

#: A fitted parameter agrees with its direct measurement when within this relative difference.
TOLERANCE = 0.25
_LAGS = _STATIC_NOISE_LAGS


def _length(cov):
    """Gaussian correlation length [px] of a lag covariance over :data:`_LAGS` (lag 0 first)."""
    if not (np.all(np.isfinite(cov)) and cov[0] > 0):
        return float("nan")
    _, ell = fit_gaussian_cov(np.array(_LAGS[1:]), cov[1:] / cov[0], lmin=0.3, lmax=80.0)
    return float(ell)


def capture_measurements(c) -> dict:
    """The direct measurements of one capture (``CaptureData`` with >= 2 frames; NaN where undefined).

    Returns
    -------
    dict
        ``id``, ``kind``, ``distance_m``, ``angle_deg``, ``temporal_sigma_d_px``, ``static_sigma_d_px``,
        ``temporal_length_px``, ``static_length_px``, ``frame_offset_px``, ``band_margin_px`` (walls at
        <= 30 deg), ``steps_px`` (the
        spacings of consecutive distinct disparities, an array).
    """
    g = c.geometry
    fb = g.fb_px_m
    m, z = c.interior()
    nan = float("nan")
    row = {"id": c.id, "kind": g.kind, "distance_m": float(g.distance_m),
           "angle_deg": float(math.degrees(math.acos(min(1.0, abs(math.cos(math.radians(g.yaw_deg))
                                                                   * math.cos(math.radians(g.pitch_deg))))))),
           "temporal_sigma_d_px": nan, "static_sigma_d_px": nan, "temporal_length_px": nan,
           "static_length_px": nan, "frame_offset_px": nan, "band_margin_px": nan, "steps_px": np.zeros(0)}
    F = c.n_frames
    with np.errstate(divide="ignore", invalid="ignore"):
        d = fb / c.depth_m
        dtrue = fb / z
    ok = m & np.all(np.isfinite(d), axis=0)
    if F >= 2 and ok.sum() >= 100:
        dev = d[:, ok] - d[:, ok].mean(axis=0)
        st = float(np.sqrt(np.mean(dev ** 2) * F / (F - 1)))
        row["temporal_sigma_d_px"] = st
        offset = dev.mean(axis=1)
        row["frame_offset_px"] = float(np.sqrt(np.sum(offset ** 2) / (F - 1)))
        dev = dev - offset[:, None]
        S = static_lag_cov(c, m, fb, dtrue, np.ones(z.shape), _LAGS)
        if S is not None:
            row["static_sigma_d_px"] = float(math.sqrt(max(S[0][0], 0.0)))
            row["static_length_px"] = _length(S[0])
        x = np.zeros((F,) + ok.shape)
        x[:, ok] = dev
        cov, _ = lag_cov(x, ok, _LAGS)
        row["temporal_length_px"] = _length(cov)
    vals = d[:, m]
    vals = np.unique(np.round(vals[np.isfinite(vals)], 6))
    if vals.size >= 3:
        row["steps_px"] = np.diff(vals)
    if g.kind == "wall" and row["angle_deg"] <= 30.0 + 1e-6:
        reg = g.regions()
        margins = []
        valid = np.mean(c.has_data(), axis=0) >= 0.5
        for v in range(g.height):
            surf = np.isfinite(z[v]) & ((reg[v] == REGION_INTERIOR) | (reg[v] == REGION_LEFT_BAND))
            if c.mask is not None:
                surf &= c.mask[v]
            cols = np.flatnonzero(valid[v] & surf)
            if cols.size and surf[0]:
                u0 = int(cols[0])
                margins.append(u0 - fb / z[v, u0])
        if margins:
            row["band_margin_px"] = float(np.median(margins))
    return row


def direct_measurements(captures) -> dict:
    """The direct measurements of a capture set: per capture (:func:`capture_measurements`) and pooled.

    ``captures`` is any iterable of CaptureData (a generator keeps one capture in memory at a time).

    Pooled: ``disparity_step_px`` (median spacing of distinct disparities over the captures at >= 1 m),
    ``band_margin_px`` (median over the walls), the medians over captures of the sigmas and lengths.
    """
    rows = [capture_measurements(c) for c in captures]
    steps = [r["steps_px"] for r in rows if r["distance_m"] >= 1.0 and r["steps_px"].size]
    allsteps = np.concatenate(steps) if steps else np.zeros(0)
    small = allsteps[allsteps > 1e-4]

    def med(key, pick=lambda r: True):
        v = np.array([r[key] for r in rows if pick(r)], dtype=float)
        v = v[np.isfinite(v)]
        return float(np.median(v)) if v.size else float("nan")

    pooled = {"disparity_step_px": float(np.median(small)) if small.size else float("nan"),
              "band_margin_px": med("band_margin_px"),
              "temporal_sigma_d_px": med("temporal_sigma_d_px"), "static_sigma_d_px": med("static_sigma_d_px"),
              "temporal_length_px": med("temporal_length_px"), "static_length_px": med("static_length_px"),
              "frame_offset_px": med("frame_offset_px")}
    for r in rows:
        r.pop("steps_px")
    return {"pooled": pooled, "captures": rows}


def check_fitted(effects: Sequence[Mapping], direct: Mapping, model_direct: Mapping | None = None,
                 tolerance: float = TOLERANCE) -> list[dict]:
    """Each fitted parameter that has a direct meaning, next to its direct measurement.

    Parameters
    ----------
    effects : sequence of {"name", "params"}
        The effects selected by the diagnosis (its report's ``effects``).
    direct : mapping
        :func:`direct_measurements` of the real captures.
    model_direct : mapping, optional
        :func:`direct_measurements` of the final model's simulation of the same captures: the temporal
        sigma_d is compared capture by capture (the median ratio), since several effects shape it.
    tolerance : float
        Relative difference within which a parameter agrees.

    Returns
    -------
    list of dict
        ``quantity``, ``effect``, ``fitted``, ``direct``, ``ratio`` (fitted / direct), ``agrees``.
    """
    p = direct["pooled"]
    rows = []

    def add(quantity, effect, fitted, measured):
        ratio = fitted / measured if measured and math.isfinite(measured) else float("nan")
        rows.append({"quantity": quantity, "effect": effect, "fitted": float(fitted), "direct": float(measured),
                     "ratio": float(ratio), "agrees": bool(math.isfinite(ratio) and abs(ratio - 1.0) <= tolerance)})

    for e in effects:
        name, params = e["name"], e["params"]
        if name == "disparity_quantization":
            add("disparity_step_px", name, 2.0 ** -int(params["subpixel_bits"]), p["disparity_step_px"])
        elif name == "invalid_band":
            add("band_margin_px", name, params["margin_px"], p["band_margin_px"])
        elif name == "correlated_noise":
            add("temporal_length_px", name, params["length_px"], p["temporal_length_px"])
        elif name in ("static_pattern", "static_noise"):
            add("static_length_px", name, params["length_px"], p["static_length_px"])
            if name == "static_pattern":
                add("static_sigma_d_px", name, params["sigma_px"], p["static_sigma_d_px"])
        elif name == "frame_offset":
            add("frame_offset_px", name, params["sigma_px"], p["frame_offset_px"])
    if model_direct is not None:
        sim = {r["id"]: r for r in model_direct["captures"]}
        for key in ("temporal_sigma_d_px", "static_sigma_d_px"):
            ratios = [sim[r["id"]][key] / r[key] for r in direct["captures"] if r["id"] in sim and r[key] > 0]
            ratios = np.array([x for x in ratios if math.isfinite(x)])
            if ratios.size:
                q = float(np.median(ratios))
                rows.append({"quantity": f"{key} (final model / real, median over captures)",
                             "effect": "+".join(e["name"] for e in effects) or "reference", "fitted": q,
                             "direct": 1.0, "ratio": q, "agrees": bool(abs(q - 1.0) <= tolerance),
                             "ratio_p10_p90": [float(np.percentile(ratios, 10)), float(np.percentile(ratios, 90))]})
    return rows
