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
``band_margin_px`` / ``band_dark_margin_px``
    The left invalid band's width beyond f B / z (E6) and how much wider it is on a surface darker than
    its frame's exposure level. Per row of a wall, or of a board's background, at <= 30 deg whose surface
    reaches column 0: u0 the first column with data in at least half the frames, y = u0 - f B / z_true
    - 1/2 (the band's edge lies between columns u0 - 1 and u0, so its middle is the estimate, as the fit
    takes the middle of the gap) and s the darkness there
    (:func:`noise_model.sim.effects.coverage.band_darkness`); per capture the medians of y and s. Pooled:
    the line y = margin + dark_margin s by least squares over the captures when their s spans 0.2;
    otherwise the median of y and no dark margin (NaN).
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

from ...sim.effects.coverage import band_darkness
from ..capture_data import REGION_BACKGROUND, REGION_INTERIOR, REGION_LEFT_BAND
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
        ``temporal_length_px``, ``static_length_px``, ``frame_offset_px``, ``band_margin_px`` and
        ``band_darkness`` (walls and boards' backgrounds at <= 30 deg: the medians of y and s of the module
        docstring), ``steps_px`` (the spacings of consecutive distinct disparities, an array).
    """
    g = c.geometry
    fb = g.fb_px_m
    m, z = c.interior()
    nan = float("nan")
    row = {"id": c.id, "kind": g.kind, "distance_m": float(g.distance_m),
           "angle_deg": float(math.degrees(math.acos(min(1.0, abs(math.cos(math.radians(g.yaw_deg))
                                                                   * math.cos(math.radians(g.pitch_deg))))))),
           "temporal_sigma_d_px": nan, "static_sigma_d_px": nan, "temporal_length_px": nan,
           "static_length_px": nan, "frame_offset_px": nan, "band_margin_px": nan, "band_darkness": nan,
           "steps_px": np.zeros(0)}
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
    if (g.kind == "wall" or g.background_m is not None) and row["angle_deg"] <= 30.0 + 1e-6:
        reg = g.regions()
        z_all, theta = g.render()
        dark = band_darkness(z_all, theta)
        own = REGION_INTERIOR if g.kind == "wall" else REGION_BACKGROUND
        margins, darks = [], []
        valid = np.mean(c.has_data(), axis=0) >= 0.5
        for v in range(g.height):
            surf = np.isfinite(z_all[v]) & ((reg[v] == own) | (reg[v] == REGION_LEFT_BAND))
            if c.mask is not None:
                surf &= c.mask[v]
            if not surf[0]:
                continue
            reach = int(np.argmin(surf)) if not surf.all() else surf.size      # the surface from column 0 on
            cols = np.flatnonzero(valid[v, :reach])
            if cols.size:
                u0 = int(cols[0])
                margins.append(u0 - fb / z_all[v, u0] - 0.5)
                darks.append(dark[v, u0])
        if margins:
            row["band_margin_px"] = float(np.median(margins))
            row["band_darkness"] = float(np.median(darks))
    return row


#: Width [deg] of the incidence-angle bins of the final model's ratios (the diagnosis's binning).
_ANGLE_BIN_DEG = 15


#: The captures' band darkness must span this much for the pooled dark margin (as the fit's
#: noise_model.analysis.effect_fits.coverage._DARK_MIN_SPREAD).
_DARK_MIN_SPREAD = 0.2


def _band_line(rows) -> tuple[float, float]:
    """(margin, dark margin) of the pooled band measurement (module docstring); NaN where undefined."""
    y = np.array([r["band_margin_px"] for r in rows], dtype=float)
    x = np.array([r["band_darkness"] for r in rows], dtype=float)
    ok = np.isfinite(y) & np.isfinite(x)
    y, x = y[ok], x[ok]
    if not y.size:
        return float("nan"), float("nan")
    if x.max() - x.min() < _DARK_MIN_SPREAD:
        return float(np.median(y)), float("nan")
    slope, intercept = np.polyfit(x, y, 1)
    return float(intercept), float(slope)


def direct_measurements(captures) -> dict:
    """The direct measurements of a capture set: per capture (:func:`capture_measurements`) and pooled.

    ``captures`` is any iterable of CaptureData (a generator keeps one capture in memory at a time).

    Pooled: ``disparity_step_px`` (median spacing of distinct disparities over the captures at >= 1 m),
    ``band_margin_px`` and ``band_dark_margin_px`` (the line over the walls and boards' backgrounds, module
    docstring), the medians over captures of the sigmas and lengths.
    """
    rows = [capture_measurements(c) for c in captures]
    steps = [r["steps_px"] for r in rows if r["distance_m"] >= 1.0 and r["steps_px"].size]
    allsteps = np.concatenate(steps) if steps else np.zeros(0)
    small = allsteps[allsteps > 1e-4]

    def med(key, pick=lambda r: True):
        v = np.array([r[key] for r in rows if pick(r)], dtype=float)
        v = v[np.isfinite(v)]
        return float(np.median(v)) if v.size else float("nan")

    margin, dark = _band_line(rows)
    pooled = {"disparity_step_px": float(np.median(small)) if small.size else float("nan"),
              "band_margin_px": margin, "band_dark_margin_px": dark,
              "temporal_sigma_d_px": med("temporal_sigma_d_px"), "static_sigma_d_px": med("static_sigma_d_px"),
              "temporal_length_px": med("temporal_length_px"), "static_length_px": med("static_length_px"),
              "frame_offset_px": med("frame_offset_px")}
    for r in rows:
        r.pop("steps_px")
    return {"pooled": pooled, "captures": rows}


def check_fitted(effects: Sequence[Mapping], direct: Mapping, model_direct: Mapping | None = None,
                 tolerance: float = TOLERANCE, heldout_ids: Sequence[str] | None = None) -> list[dict]:
    """Each fitted parameter that has a direct meaning, next to its direct measurement.

    Parameters
    ----------
    effects : sequence of {"name", "params"}
        The effects selected by the diagnosis (its report's ``effects``).
    direct : mapping
        :func:`direct_measurements` of the real captures.
    model_direct : mapping, optional
        :func:`direct_measurements` of the final model's simulation of the same captures: the temporal
        and static sigma_d are compared capture by capture (the median ratio), since several effects
        shape them; and by incidence angle (the medians within 15 deg bins), since an error whose size
        follows the angle otherwise than the model's shows only there.
    tolerance : float
        Relative difference within which a parameter agrees.
    heldout_ids : sequence of str, optional
        The diagnosis's held-out captures: the final model's ratios are then also given over the fit and
        the held-out captures apart, since a held-out recording may differ from the fitted one in what no
        fit can see (its own static error, say).

    Returns
    -------
    list of dict
        ``quantity``, ``effect``, ``fitted``, ``direct``, ``ratio`` (fitted / direct), ``agrees``; the
        final model's rows also ``ratio_p10_p90``, ``ratio_by_angle`` (list of {``angle_deg``: [lo, hi],
        ``ratio``, ``captures``}, bins of :data:`_ANGLE_BIN_DEG` with at least one capture) and, with
        ``heldout_ids``, ``ratio_by_split`` ({"fit"|"heldout": {``ratio``, ``captures``}}, the parts with
        at least one capture).
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
            if math.isfinite(p.get("band_dark_margin_px", float("nan"))):
                add("band_dark_margin_px", name, params.get("dark_margin_px", 0.0), p["band_dark_margin_px"])
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
            pairs = [(sim[r["id"]][key] / r[key], r["angle_deg"], r["id"]) for r in direct["captures"]
                     if r["id"] in sim and r[key] > 0]
            pairs = [(x, a, i) for x, a, i in pairs if math.isfinite(x)]
            ratios = np.array([x for x, _, _ in pairs])
            if ratios.size:
                angles = np.array([a for _, a, _ in pairs])
                lo = np.minimum(np.floor(angles / _ANGLE_BIN_DEG + 1e-9), 89 // _ANGLE_BIN_DEG)
                by_angle = [{"angle_deg": [float(b * _ANGLE_BIN_DEG), float((b + 1) * _ANGLE_BIN_DEG)],
                             "ratio": float(np.median(ratios[lo == b])), "captures": int(np.sum(lo == b))}
                            for b in np.unique(lo)]
                q = float(np.median(ratios))
                rows.append({"quantity": f"{key} (final model / real, median over captures)",
                             "effect": "+".join(e["name"] for e in effects) or "reference", "fitted": q,
                             "direct": 1.0, "ratio": q, "agrees": bool(abs(q - 1.0) <= tolerance),
                             "ratio_p10_p90": [float(np.percentile(ratios, 10)), float(np.percentile(ratios, 90))],
                             "ratio_by_angle": by_angle})
                if heldout_ids is not None:
                    held_set = set(heldout_ids)
                    held = np.array([i in held_set for _, _, i in pairs])
                    rows[-1]["ratio_by_split"] = {
                        part: {"ratio": float(np.median(ratios[sel])), "captures": int(np.sum(sel))}
                        for part, sel in (("fit", ~held), ("heldout", held)) if np.any(sel)}
    return rows
