"""The model fits of ``elevmap characterize`` and their predictions of another capture set.

:func:`fit_families` turns the measured captures into measurements (one per capture, or one per depth
bin where a mask or plane target gives the region) and fits both families of sigma_z to them: the
paper's (:func:`noise_model.analysis.characterization.fit_axial_model`) and the disparity family
(:func:`noise_model.analysis.family_fit.fit_disparity_model`), with both families' held-out errors over
blocks of distance and angle (:func:`noise_model.analysis.family_fit.heldout_errors`), which choose the
family written as the model file. :func:`predict_capture_set` compares the fitted models and the paper's
published one with another capture set's measured axial noise.
"""

from __future__ import annotations

import math

import numpy as np

import noise_model as nm
from noise_model.analysis import characterization as ch, family_fit as ff
from noise_model.d435 import D435

__all__ = ["fit_families", "predict_capture_set", "PREDICTION_FACTOR", "measure_frame_error", "frame_error_row", "frame_error_report", "fit_frame_noise",
           "with_frame_error"]

#: The fit's comparison grid: the paper's distances and angles.
_GRID_Z = np.round(np.arange(0.4, 2.1 + 1e-9, 0.1), 2)
_GRID_THETA_DEG = np.arange(0.0, 75.0 + 1e-9, 15.0)
#: Paper sigma_z below this [m]: where the fit is compared (beyond it the paper's own data are sparse).
_COMPARE_BELOW_M = 0.05


def _fit_points(records, max_rel_noise: float) -> list[dict]:
    """The measurements the fits use: one per capture (its region's axial noise), or for a capture whose
    region is given by a mask or a plane target, one per depth bin; those whose noise exceeds max_rel_noise
    of the depth are left out with a note."""
    pts = []
    for r in records:
        if not r.get("axial_sigma_m"):
            continue
        th = math.radians(r["theta_deg"])
        if r.get("axial_bins"):
            cand = [(f"{r['id']} z {b['z_range_m'][0]:g}-{b['z_range_m'][1]:g} m", b["z_m"], b["sigma_z_m"])
                    for b in r["axial_bins"] if b["sigma_z_m"]]
        else:
            cand = [(r["id"], r["z_m"], r["axial_sigma_m"])]
        for name, z, sig in cand:
            if sig > max_rel_noise * z:
                r["notes"].setdefault("fit", (f"not fitted: sigma_z is {100 * sig / z:.0f}% of the depth at {z:.2f} m "
                                              f"(> {100 * max_rel_noise:.0f}%): depths below zero are lost and the "
                                              "target blends with what is behind it, so the noise cannot be measured "
                                              "reliably"))
                continue
            pts.append({"name": name, "id": r["id"], "z_m": float(z), "theta_rad": th, "sigma_m": float(sig),
                        "fx_px": float(r.get("fx_px") or 0.0)})
    return pts


def fit_families(records, camera: dict, max_rel_noise: float) -> tuple[dict | None, str | None, ch.AxialFit | None,
                                                                      dict]:
    """Fit both families to the measured captures of a characterisation.

    Parameters
    ----------
    records : list of dict
        :func:`elevmap.commands.characterize.characterize_capture` records (their notes get the reasons a
        measurement was left out).
    camera : dict
        The capture set's camera (``fx`` [px], ``baseline_m`` [m]).
    max_rel_noise : float
        Measurements whose sigma_z exceeds this fraction of their depth are left out.

    Returns
    -------
    tuple
        (the paper family's fit as a report dict or None, the reason it is None, its AxialFit, ``families``)
        with ``families`` holding ``disparity`` (its fit dict or None), ``disparity_reason``, ``heldout``,
        ``better``, ``_disparity`` (the DisparityFit) and ``n_points``.
    """
    pts = _fit_points(records, max_rel_noise)
    baseline = float(camera.get("baseline_m") or D435.baseline_m)
    fam = {"disparity": None, "disparity_reason": None, "heldout": None, "better": None, "_disparity": None,
           "n_points": len(pts)}
    z = np.array([p["z_m"] for p in pts])
    th = np.array([p["theta_rad"] for p in pts])
    s = np.array([p["sigma_m"] for p in pts])
    fx = np.array([p["fx_px"] or float(camera["fx"]) for p in pts])
    if pts:
        dfit = ff.fit_disparity_model(z, th, s, fx, baseline)
        fam["_disparity"] = dfit
        fam["disparity"] = {**dfit.to_dict(), "form": "sigma_z = z^2 (s0 + s1 theta^2) / (f B)  [m; z in m, theta in "
                                                     "rad, s0 in px, s1 in px/rad^2, f in px, B in m]",
                            "measurements": [p["name"] for p in pts]}
        fam["heldout"] = ff.heldout_errors(z, th, s, fx, baseline)
        fam["better"] = fam["heldout"]["better"]
    else:
        fam["disparity_reason"] = "no capture's axial noise was measured"
    if len(pts) < ff.MIN_PAPER_POINTS:
        return None, (f"fitting sigma_z(z, theta) in the paper's form needs axial noise from at least "
                      f"{ff.MIN_PAPER_POINTS} captures or depth bins with >= 2 frames, got {len(pts)}"), None, fam
    try:
        fit = ch.fit_axial_model(z, th, s)
    except (ValueError, RuntimeError) as exc:
        return None, f"the fit failed: {exc}", None, fam
    for p, used in zip(pts, fit.inliers):
        if not used:
            r = next(r for r in records if r["id"] == p["id"])
            pred = float(fit.sigma_z(p["z_m"], p["theta_rad"]))
            r["notes"]["fit"] = (f"left out of the paper-family fit ({p['name']}): {1000 * p['sigma_m']:.2f} mm "
                                 f"against {1000 * pred:.2f} mm from the other measurements' fit")
    Zg, Tg = np.meshgrid(_GRID_Z, np.radians(_GRID_THETA_DEG), indexing="ij")
    paper = nm.axial_sigma(Zg, Tg)
    mine = fit.sigma_z(Zg, Tg)
    below = paper < _COMPARE_BELOW_M
    rel = np.abs(mine - paper) / paper
    d = fit.to_dict()
    d.update({
        "form": "sigma_z = c0 + c1 z + c2 z^2 + c_theta z^(3/2) theta / (pi/2 - theta)^2  [m; z in m, theta in rad]",
        "captures": sorted({p["id"] for p, used in zip(pts, fit.inliers) if used}),
        "left_out": [p["name"] for p, used in zip(pts, fit.inliers) if not used],
        "paper_coefficients": list(D435.axial_coefficients),
        "vs_paper": {"grid": "z 0.4 to 2.1 m every 0.1 m x theta 0 to 75 deg every 15 deg",
                     "max_rel_diff_where_paper_below_0.05m": float(rel[below].max()),
                     "median_rel_diff_where_paper_below_0.05m": float(np.median(rel[below]))},
    })
    return d, None, fit, fam


#: A fitted model's prediction of another set is within this factor of the measured noise when the
#: ratio measured / predicted lies in [1 / PREDICTION_FACTOR, PREDICTION_FACTOR].
PREDICTION_FACTOR = 1.25


def predict_capture_set(other, measured, model, fit, dfit, camera: dict) -> dict:
    """The axial noise of another capture set against the models' sigma_z.

    Compared: the model written, each family as fitted, and the paper's published model. Per depth bin where
    a mask or plane target gives the capture's region, else per capture: the prediction is the median over
    the bin's pixels of sigma_z at the pixel's plane depth, the plane's incidence angle and the capture's
    focal length; ratio = measured / predicted.

    Parameters
    ----------
    other : elevmap.sources.captures.CaptureSet
    measured : list of dict
        :func:`elevmap.commands.characterize.characterize_capture` of each of ``other``'s captures.
    model : SensorModel or None
        The model written.
    fit : AxialFit or None
        The paper family's fit.
    dfit : DisparityFit or None
        The disparity family's fit.
    camera : dict
        The fitted set's camera (its ``baseline_m``).
    """
    models = {"paper_published": D435}
    if model is not None:
        models["model"] = model
    baseline = float(camera.get("baseline_m") or D435.baseline_m)
    if fit is not None:
        models["paper_fitted"] = D435.with_coefficients(fit.coefficients, name="paper family, fitted")
    if dfit is not None:
        models["disparity_fitted"] = D435.with_disparity(dfit.s0, dfit.s1, baseline_m=baseline,
                                                         name="disparity family, fitted")
    out = {"captures_dir": str(other.folder), "factor": PREDICTION_FACTOR,
           "models": {k: {"name": m.name, "family": m.family} for k, m in models.items()},
           "captures": [], "failures": []}
    for rec in measured:
        if "failed" in rec:
            out["failures"].append({"id": rec["id"], "reason": rec["failed"]})
            continue
        if not rec.get("axial_sigma_m"):
            out["failures"].append({"id": rec["id"], "reason": rec["notes"].get("axial", "no axial noise")})
            continue
        theta = math.radians(rec["theta_deg"])
        fx = float(rec["fx_px"])
        bins = rec.get("_axial_bins") or [{"z_range_m": None, "z_m": rec["z_m"], "sigma_z_m": rec["axial_sigma_m"],
                                           "n_pixels": rec["region_pixels"], "_z_pixels_m": np.array([rec["z_m"]])}]
        rows = []
        for b in bins:
            zp = np.asarray(b["_z_pixels_m"], dtype=np.float64)
            pred = {k: float(np.median(nm.axial_sigma(zp, theta, m, fx_px=fx))) for k, m in models.items()}
            # a fit extrapolated beyond its data may predict sigma_z <= 0 there: no ratio
            rows.append({"z_range_m": b["z_range_m"], "z_m": b["z_m"], "n_pixels": b["n_pixels"],
                         "real_sigma_m": b["sigma_z_m"], "predicted_sigma_m": pred,
                         "ratio": {k: (b["sigma_z_m"] / v if v > 0 else None) for k, v in pred.items()}})
        out["captures"].append({"id": rec["id"], "kind": rec["kind"], "geometry": rec.get("geometry"),
                                "theta_deg": rec["theta_deg"], "bins": rows})
    return out


def measure_frame_error(cs, caps, depths=None) -> dict:
    """The per-frame error of the capture set's captures ``caps`` and its pooled figures
    (:mod:`noise_model.analysis.frame_error`).

    A capture that cannot be measured (too few frames, not its plane) is left out with its reason. A
    ``plane`` target (a fitted plane seen through its mask) is measured as the wall of that plane; captures
    of fitted geometry are measured like measured ones (the static part is taken about the best plane of
    the frames' mean, which a fitted geometry gives as well as a measured one).

    Parameters
    ----------
    cs : elevmap.sources.captures.CaptureSet
    caps : sequence of elevmap.sources.captures.Capture
    depths : iterable of ndarray, optional
        Each capture's frames as :meth:`CaptureSet.load_depth` gives them, in the order of ``caps``
        (a caller that has read them already); read from the set when omitted.

    Returns
    -------
    dict
        ``pooled`` (:func:`noise_model.analysis.frame_error.pooled_frame_error`), ``fx_px`` (the stream's
        focal length), ``captures`` (rows), ``skipped`` (``id`` and ``reason``), ``method``.
    """
    rows, skipped = [], []
    depths = (cs.load_depth(cap.id) for cap in caps) if depths is None else depths
    for cap, depth in zip(caps, depths):
        row, skip = frame_error_row(cs, cap, depth)
        (rows if skip is None else skipped).append(row if skip is None else skip)
    return frame_error_report(cs, rows, skipped)


def frame_error_row(cs, cap, depth) -> tuple[dict | None, dict | None]:
    """One capture's per-frame error (:func:`noise_model.analysis.frame_error.capture_frame_error`) from its
    frames ``depth`` (depth units (F, H, W), as :meth:`CaptureSet.load_depth` gives them): (row, None), or
    (None, ``{"id", "reason"}``) when the capture cannot be measured."""
    from noise_model.analysis.capture_data import CaptureData
    from noise_model.analysis.frame_error import capture_frame_error

    camera = cs.camera_for(cap.id) if cap.is_recording else cs.camera
    try:
        c = CaptureData.from_capture_entry(camera, cap.to_dict(), np.asarray(depth), cs.load_mask(cap.id))
    except ValueError as exc:
        return None, {"id": cap.id, "reason": str(exc)}
    row = capture_frame_error(c)
    if row["reason"] is not None:
        return None, {"id": cap.id, "reason": row["reason"]}
    return row, None


def frame_error_report(cs, rows, skipped) -> dict:
    """The report of :func:`measure_frame_error` from its per-capture ``rows`` and ``skipped`` entries."""
    from noise_model.analysis.frame_error import pooled_frame_error

    return {"pooled": pooled_frame_error(rows), "fx_px": float(cs.camera["fx"]), "captures": rows,
            "skipped": skipped,
            "method": "per capture, the disparity error's temporal lag covariance (frame-wide offset removed) "
                      "plus its static part's (the temporal mean about its best plane, less the temporal "
                      "share) plus the frame-wide offset's variance (covariance over frames of the mean error "
                      "of the target's left and right thirds), which a map sees as each frame's error; "
                      "ratio = total / temporal variance at lag 0, Gaussian correlation length over "
                      "lags 1-11 px where the lag-1 correlation is >= 0.1 (else 0); medians over captures"}


def fit_frame_noise(records, frame_error: dict, family: str, camera: dict, max_rel_noise: float):
    """sigma_z of one frame's whole error fitted in ``family``: each measured capture's axial sigma times
    the square root of its per-frame variance ratio (:func:`measure_frame_error`), fitted as the axial
    model is (:func:`fit_families`). Returns the family's parameters ((c0, c1, c2, c_theta) or (s0, s1))
    and None, or None and the reason."""
    ratio = {r["id"]: r["ratio"] for r in frame_error["captures"]}
    recs = [dict(r, axial_sigma_m=r["axial_sigma_m"] * math.sqrt(ratio[r["id"]]), axial_bins=None,
                 notes=dict(r.get("notes") or {}))
            for r in records if r.get("axial_sigma_m") and r["id"] in ratio]
    if not recs:
        return None, "no capture has both an axial sigma and a per-frame error"
    _, reason, fit, fam = fit_families(recs, camera, max_rel_noise)
    if family == "paper":
        return (None, reason) if fit is None else (tuple(float(c) for c in fit.coefficients), None)
    d = fam["_disparity"]
    return (None, fam["disparity_reason"] or "the disparity fit failed") if d is None else ((d.s0, d.s1), None)


def with_frame_error(model, frame_error: dict, frame_noise=None):
    """``model`` carrying the pooled per-frame error of :func:`measure_frame_error` and the per-frame sigma_z
    ``frame_noise`` (:func:`fit_frame_noise`) (unchanged when none was measured)."""
    from dataclasses import replace

    p = frame_error["pooled"]
    if model is None or not p["n_captures"]:
        return model
    ell = float(p["error_correlation_px"])
    return replace(model, frame_variance_ratio=float(p["frame_variance_ratio"]), error_correlation_px=ell,
                   error_correlation_fx_px=frame_error["fx_px"] if ell > 0.0 else None, frame_noise=frame_noise)
