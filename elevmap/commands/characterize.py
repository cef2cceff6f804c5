"""``elevmap characterize``: a D435's own noise model from a capture set, the way Ahn et al. (2019) did.

:func:`run_characterize` reads a capture set (``d435-captures/1``: ``.npy`` frames or RealSense
``.bag`` / ``.db3`` recordings, any resolution), finds the planar target in each capture
(:mod:`noise_model.analysis.detection`: bilateral filter, Canny edges, the board's quadrilateral), measures
axial noise, lateral noise, the plane-fit residual and the systematic error
(:mod:`noise_model.analysis.characterization`), fits sigma_z(z, theta) in the paper's form, and writes:

* the JSON report (``--json``), atomically;
* the fitted model, ``<json stem>.model.json`` next to the report unless ``model_path`` says otherwise
  (format ``elevmap-sensor-model/1``, ``/2`` for the disparity family, ``/3`` when it carries a per-frame
  error; ``noise_model.SensorModel.load`` reads each, so the mapper, the simulator and the gap diagnosis
  can use it in place of the paper's). The per-frame error: the axial model is fitted to the per-pixel
  temporal sigma, and the file also carries how much larger one frame's error is once the static pattern
  a static capture cannot see is added, and its correlation length in pixels
  (:mod:`noise_model.analysis.frame_error`), from which the map takes a frame's information per cell;
* the paper's figures as PNG files (``--figures DIR``) and in a rerun recording (``--rrd``).

A capture whose target cannot be found is listed under ``failures`` with the reason; the others still
run. A capture may carry ``"region_px": {"rows": [r0, r1], "cols": [c0, c1]}`` (half-open, like
Python slices) to give the central region instead of detecting it (a board's edges are still looked
for). Input that is not a valid capture set, or a depth file that cannot be read, raises
``ValueError`` before anything is written.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

import noise_model as nm
from noise_model.analysis import characterization as ch, planes
from noise_model.d435 import D435

from noise_model.reporting import check_names

from ..fileio import check_outputs, json_ready, write_json_atomic
from .characterize_models import (fit_families, fit_frame_noise, frame_error_report, frame_error_row,
                                  predict_capture_set, with_frame_error)
from .protocol import PROTOCOL  # the recording protocol (also in ``elevmap characterize --help``)

__all__ = ["run_characterize", "characterize_capture", "format_summary", "figure_series", "plane_distance_panels",
           "PROTOCOL", "REPORT_FORMAT", "FIGURE_FILES", "default_model_path"]

REPORT_FORMAT = "elevmap-characterize/1"

#: PNG files written into ``figures_dir``.
FIGURE_FILES = {
    "systematic_error": "fig2_systematic_error.png",
    "axial_variance": "fig3_axial_variance.png",
    "plane_distance": "fig4_plane_distance.png",
    "lateral_noise": "lateral_noise.png",
}


#: Depth band of a detected region: plane depths within this fraction of the region's median depth,
#: so sigma_z (which grows with z^1.5 to z^2) is the same over the region's pixels.
DEPTH_BAND_REL = 0.05
#: Captures whose sigma_z exceeds this fraction of their depth are measured but not fitted.
MAX_REL_NOISE = 0.2
#: Frames used for the per-pixel median image the target is detected on.
DETECTION_FRAMES = 31
#: Frames processed at once where whole windows of frames are held in memory.
_CHUNK_FRAMES = 16
#: Frames whose single-frame plane-fit residual is computed (evenly spaced).
RESIDUAL_FRAMES = 5


def default_model_path(json_path) -> Path:
    """``<json stem>.model.json`` next to the report."""
    p = Path(json_path)
    return p.with_name(p.stem + ".model.json")


# ------------------------------------------------------------------------------------------------
# one capture


def _region_box(cap):
    r = cap.extra.get("region_px")
    if r is None:
        return None
    if not isinstance(r, dict) or "rows" not in r or "cols" not in r:
        raise ValueError(f"capture '{cap.id}': 'region_px' must be {{\"rows\": [r0, r1], \"cols\": [c0, c1]}}, "
                         f"got {r!r}")
    return r["rows"], r["cols"]


def _to_metres(a, scale: float) -> np.ndarray:
    a = np.asarray(a)
    out = a.astype(np.float32) * np.float32(scale)
    out[a == 0] = np.nan
    return out


def _median_image(depth, scale: float, n_max: int) -> np.ndarray:
    """Per-pixel median [m] of up to ``n_max`` evenly spaced frames (NaN where more than half have no
    depth), in blocks of rows to bound memory."""
    N, H, W = depth.shape
    idx = np.unique(np.round(np.linspace(0, N - 1, min(N, n_max))).astype(int))
    out = np.empty((H, W), dtype=np.float32)
    step = max(1, (1 << 22) // max(1, idx.size * W))
    for r0 in range(0, H, step):
        z = _to_metres(depth[idx, r0:r0 + step], scale)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(z, axis=0) if z.shape[0] > 1 else z[0]
        med[np.isnan(z).mean(axis=0) > 0.5] = np.nan
        out[r0:r0 + step] = med
    return out


def _lateral_edge(depth, scale, K, plane, band, ref, W) -> dict:
    """Per-frame edge positions of one vertical edge of a board and their spread.

    A window around the edge (up to the board's middle on one side, as far on the other, within the
    image) is cut from every frame; a pixel is on the board when its depth is nearer to the board's plane
    than to what lies behind the edge (the median image beyond the edge, row by row); with nothing behind
    (no depth there), when it is within max(4 sigma, 10 %) of the plane. The count of board pixels per row
    places the edge (:func:`noise_model.analysis.characterization.edge_positions`); positions are mapped onto
    the board's plane, across the edge, for the spread in metres.
    """
    side = band.side
    rows = band.rows
    c = band.column_at(rows)
    w_in = int(max(4, math.ceil(band.half_width_px)))
    dist_border = float(np.min(c + 0.5)) if side == "left" else float(np.min(W - 0.5 - c))
    w_out = int(min(w_in, math.floor(dist_border)))
    if w_out < 3:
        return {"reason": f"the {side} edge is within {max(dist_border, 0):.0f} px of the image border"}
    cb = np.round(c).astype(np.int64)       # window edge near the boundary (c is at a pixel boundary +-0.5)
    start = cb - w_out if side == "left" else cb - w_in + 1
    n_win = w_in + w_out
    start = np.clip(start, 0, W - n_win)
    cols = start[:, None] + np.arange(n_win)[None, :]
    up, vp = planes.normalised_coordinates(K, cols, np.broadcast_to(rows[:, None], cols.shape))
    z_pl = plane.depth_at(up, vp)
    if not np.isfinite(z_pl).any():
        return {"reason": f"the {side} edge's rays miss the board's fitted plane"}
    z_pl32 = z_pl.astype(np.float32)
    off = cols - c[:, None]                 # > 0: right of the edge
    board_side = off > 0 if side == "left" else off < 0
    outer = (off < -2) if side == "left" else (off > 2)
    # what lies behind the edge: the median image beyond it, per row (NaN: no depth there)
    ref_crop = np.where(outer, ref[rows[:, None], cols], np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        behind_row = np.nanmedian(ref_crop, axis=1)
    have_behind = np.isfinite(ref_crop).sum() > 0.5 * outer.sum()
    near_z = z_pl[np.abs(off) < 2]
    near_z = near_z[np.isfinite(near_z)]
    z_edge = float(np.median(near_z)) if near_z.size else float(np.nanmedian(z_pl))
    behind_all = float(np.nanmedian(ref_crop)) if have_behind else float("nan")
    if have_behind:
        behind_row = np.where(np.isfinite(behind_row), behind_row, behind_all).astype(np.float32)

    def classify(f0, f1):
        """(deviation from the plane, nearer to the plane than to what is behind) of frames f0..f1."""
        crop = _to_metres(depth[f0:f1, rows[:, None], cols], scale)
        dev = crop - z_pl32[None]
        if have_behind:
            closer = np.abs(dev) < np.abs(crop - behind_row[None, :, None])
        else:
            closer = np.isfinite(dev)
        return dev, closer

    # the board's noise next to the edge (the half of the board side nearer to the edge), from a few frames
    N = depth.shape[0]
    near_half = board_side & (np.abs(off) <= 0.5 * w_in)
    d_in = []
    for f in np.unique(np.round(np.linspace(0, N - 1, min(N, 16))).astype(int)):
        dev, closer = classify(f, f + 1)
        d = dev[0][near_half & closer[0]]
        d_in.append(d[np.isfinite(d)])
    d_in = np.concatenate(d_in)
    if d_in.size < 20:
        return {"reason": f"the board next to its {side} edge has no depth"}
    sigma_edge = float(1.4826 * np.median(np.abs(d_in - np.median(d_in))))
    if have_behind:
        gap = float(abs(behind_all - z_edge))
        if gap < 8.0 * sigma_edge:
            return {"reason": f"what lies beyond the board's {side} edge is only {100 * gap:.1f} cm from the "
                              f"board's plane, less than 8 sigma_z of the board there ({100 * sigma_edge:.1f} cm)"}
        thr = 0.5 * gap
    else:
        thr = max(4.0 * sigma_edge, 0.1 * z_edge)
    pos, sat = [], []
    for f0 in range(0, N, _CHUNK_FRAMES):           # in chunks of frames: bounded memory at any resolution
        dev, closer = classify(f0, min(N, f0 + _CHUNK_FRAMES))
        on = np.isfinite(dev) & (closer if have_behind else (np.abs(dev) < thr))
        p_, s_ = ch.edge_positions(on, side, start)
        pos.append(p_)
        sat.append(s_)
    pos, sat = np.concatenate(pos), np.concatenate(sat)
    # positions on the board's plane, across the edge [m]
    u1, v1 = planes.normalised_coordinates(K, c, rows)
    P1 = planes.points_from_depth(plane.depth_at(u1, v1), u1, v1)
    ok = np.isfinite(P1).all(axis=1)
    if ok.sum() < 2:
        return {"reason": f"the {side} edge's rays miss the board's plane"}
    along = P1[ok][-1] - P1[ok][0]
    across = np.cross(plane.normal, along)
    nrm = float(np.linalg.norm(across))
    if nrm == 0:
        return {"reason": f"the {side} edge is degenerate"}
    across /= nrm
    u2, _ = planes.normalised_coordinates(K, c + 1.0, rows)
    P2 = planes.points_from_depth(plane.depth_at(u2, v1), u2, v1)
    ok2 = ok & np.isfinite(P2).all(axis=1)
    step = (P2[ok2] - P1[ok2]) @ across
    if ok2.any() and np.mean(step) < 0:     # orient: metres grow with the column, as the pixels do
        across, step = -across, -step
    m_per_px = float(np.mean(step)) if ok2.any() else float("nan")
    upos, vpos = planes.normalised_coordinates(K, pos, np.broadcast_to(rows[None, :], pos.shape))
    pos_m = planes.points_from_depth(plane.depth_at(upos, vpos), upos, vpos) @ across
    if not (np.isfinite(m_per_px) and 0.0 < m_per_px < 1.0):
        return {"reason": f"the board's plane is too oblique at its {side} edge ({m_per_px:.3g} m per px)"}
    out = ch.lateral_noise(pos, sat, rows, m_per_px, position_m=pos_m)
    out["threshold_m"] = thr
    out["sigma_z_edge_m"] = sigma_edge
    return out


class _GivenRegion:
    """The target's pixels as the capture set gives them (its mask, or for a plane target every pixel), in
    place of a detected board: no edges, no corners."""

    def __init__(self, region_mask, reason=None):
        self.ok = reason is None
        self.reason = reason
        self.region_mask = region_mask
        self.target_mask = region_mask
        self.edges = {}
        self.edge_reasons = {}
        self.corners = None


def _given_region(ref, mask) -> _GivenRegion:
    region = np.isfinite(ref) if mask is None else (np.asarray(mask, dtype=bool) & np.isfinite(ref))
    if region.sum() < 10:
        return _GivenRegion(region, "the capture's mask holds fewer than 10 pixels with depth in most frames")
    return _GivenRegion(region)


def characterize_capture(cs, cap, keep_image: bool = False, detection_frames: int = DETECTION_FRAMES,
                         depth=None) -> dict:
    """Measure one capture of a capture set.

    Parameters
    ----------
    cs : elevmap.sources.captures.CaptureSet
    cap : elevmap.sources.captures.Capture
    keep_image : bool
        Also return the per-pixel distance of the frames' mean to the fitted plane (Fig. 4) as
        ``_plane_distance_image`` (float32 (H, W) [m], NaN off the target).
    depth : ndarray, optional
        The capture's frames as ``cs.load_depth(cap.id)`` gives them (a caller that has read them
        already); read from the set when omitted.

    Returns
    -------
    dict
        ``{"id", "failed": reason}`` when the target is not found; otherwise the capture's record
        (see :func:`run_characterize`).

    Notes
    -----
    The target is detected on the per-pixel median of up to ``detection_frames`` frames (the paper
    detects it per frame; with a fixed camera and target the median is the same board with sharp edges
    and less noise). The central region's plane is fitted along the rays to the per-pixel median; a
    detected region keeps the pixels whose plane depth is within 5 % of the region's median depth (so
    sigma_z is uniform over it), and pixels with any sample beyond 5 robust standard deviations of the
    plane (something else seen in some frame: the board's moving edge, a flying pixel) are left out of
    the axial noise. The single-frame plane-fit residual (Intel's "RMS error"; the realdata figures) is
    the total-least-squares fit with inliers within 2 % of the depth, on up to 5 frames (RMS over them):
    it truncates noise larger than 2 % of the depth (steep angles, far), where the axial sigma is the
    measure to read.
    """
    from noise_model.analysis.detection import detect_target

    cam = cs.camera_for(cap.id) if cap.is_recording else cs.camera
    K = np.array([[float(cam["fx"]), 0.0, float(cam["ppx"])], [0.0, float(cam["fy"]), float(cam["ppy"])],
                  [0.0, 0.0, 1.0]])
    scale = float(cam["depth_scale"])
    depth = cs.load_depth(cap.id) if depth is None else depth
    N, H, W = depth.shape
    ref = _median_image(depth, scale, detection_frames)
    mask = cs.load_mask(cap.id)
    masked = mask is not None or cap.kind == "plane"
    if masked:
        det = _given_region(ref, mask)
    else:
        det = detect_target(ref, cap.kind, (K[0, 2], K[1, 2]), region_box=_region_box(cap))
    if not det.ok:
        return {"id": cap.id, "failed": det.reason}
    vv, uu = np.nonzero(det.region_mask)
    up, vp = planes.normalised_coordinates(K, uu, vv)
    samples = _to_metres(depth[:, vv, uu], scale).astype(np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med_z = np.nanmedian(samples, axis=0) if N > 1 else samples[0]
        mean_z = np.nanmean(samples, axis=0)
    good = np.isfinite(med_z) & (np.isfinite(samples).mean(axis=0) >= 0.5)
    if good.sum() < 10:
        return {"id": cap.id, "failed": "the target's central region has fewer than 10 pixels with depth"}
    # the region's plane, fitted along the rays to the per-pixel median (robust to frames in which
    # something else, e.g. the board's moving edge, covers a pixel)
    try:
        pf = planes.fit_plane_rays(med_z[good], up[good], vp[good])
    except ValueError as exc:
        return {"id": cap.id, "failed": f"no plane in the central region ({exc})"}
    plane = pf.plane
    z_pl = plane.depth_at(up, vp)
    band = good & np.isfinite(z_pl)
    band[np.flatnonzero(good)[~pf.inliers]] = False
    if band.sum() < 10:
        return {"id": cap.id, "failed": "fewer than 10 pixels of the central region lie on its plane"}
    z_c = float(np.median(z_pl[band]))
    if _region_box(cap) is None and not masked:
        band &= np.abs(z_pl - z_c) <= DEPTH_BAND_REL * z_c
    # pixels that see something other than the plane in some frame (a sample beyond 5 robust sigma). A
    # given region may span many depths (a floor): there the deviations are compared in disparity units,
    # dz / z^2, whose noise is nearly the same at every depth, so that far pixels are not all "wild"
    dev = samples[:, band] - z_pl[band][None, :]
    unit = 1.0
    if masked:
        unit = (z_pl[band] / z_c) ** 2
        dev = dev / unit[None, :]
    fin = np.isfinite(dev)
    sig = 1.4826 * float(np.median(np.abs(dev[fin] - np.median(dev[fin])))) if fin.any() else 0.0
    with np.errstate(invalid="ignore"):
        wild = np.any(fin & (np.abs(dev) > 5.0 * np.maximum(sig, 0.5 * scale / unit)), axis=0)
    clean = band.copy()
    clean[np.flatnonzero(band)[wild]] = False
    notes = {}
    if clean.sum() < max(10, 0.2 * band.sum()):
        notes["axial"] = (f"{100 * wild.mean():.0f}% of the central region's pixels see something off the board's "
                          "plane in some frames (its edges moving into the region?)")

    # single-frame plane-fit residual (spatial noise, Intel's "RMS error" measurement)
    idx = np.unique(np.round(np.linspace(0, N - 1, min(N, RESIDUAL_FRAMES))).astype(int))
    stds, mads, fracs = [], [], []
    for f in idx:
        zf = samples[f, band]
        okf = np.isfinite(zf)
        if okf.sum() < 10:
            continue
        try:
            fit_f = planes.fit_plane_robust(planes.points_from_depth(zf[okf], up[band][okf], vp[band][okf]))
        except ValueError:
            continue
        stds.append(fit_f.residual_std_m)
        mads.append(fit_f.residual_mad_sigma_m)
        fracs.append(fit_f.n_inliers / okf.size)

    keep = clean if "axial" not in notes else band
    bins = None
    if "axial" in notes:
        axial = {"sigma_z_m": None, "stderr_m": None, "plane_distance_sigma_m": None, "z_m": z_c,
                 "invalid_fraction": float(1.0 - np.isfinite(samples[:, band]).mean()), "reason": notes["axial"]}
    else:
        axial = ch.axial_noise(samples[:, keep], up[keep], vp[keep], plane, depth_scale=scale)
        if masked:
            bins = ch.axial_noise_bins(samples[:, keep], up[keep], vp[keep], plane, depth_scale=scale)
    t = cap.target
    baseline = float(cs.camera.get("baseline_m") or D435.baseline_m)
    if cap.is_fitted:
        # the target's distance is itself a fit to these frames: their error against it is zero by construction
        syst = {"rms_error_m": None, "mean_error_m": None, "n_pixels": 0, "eq1_m": None}
        notes["systematic"] = ("skipped: the capture's geometry is fitted to its own frames, so there is no measured "
                               "distance to compare against (bias and scale are absorbed by the fit)")
    else:
        known = ch.known_plane(cap.distance_m, cap.yaw_deg, cap.pitch_deg)
        syst = ch.systematic_error(mean_z[keep], known.depth_at(up[keep], vp[keep]))
        syst["eq1_m"] = float(ch.eq1_rms_error(cap.distance_m, K[0, 0], W, baseline, D435.subpixel))

    rec = {
        "id": cap.id, "kind": cap.kind, "distance_m": cap.distance_m, "yaw_deg": cap.yaw_deg,
        "pitch_deg": cap.pitch_deg, "width": int(W), "height": int(H), "n_frames": int(N),
        "z_m": axial["z_m"], "theta_deg": math.degrees(plane.theta_rad), "region_pixels": int(keep.sum()),
        "region_given": _region_box(cap) is not None,
        "axial_sigma_m": axial["sigma_z_m"], "axial_sigma_stderr_m": axial["stderr_m"],
        "plane_distance_sigma_m": axial["plane_distance_sigma_m"],
        "invalid_fraction": axial["invalid_fraction"],
        "paper_sigma_z_m": float(nm.axial_sigma(axial["z_m"], plane.theta_rad)) if axial["z_m"] else None,
        "plane_residual_std_m": float(np.sqrt(np.mean(np.square(stds)))) if stds else None,
        "plane_residual_mad_sigma_m": float(np.median(mads)) if mads else None,
        "plane_inlier_fraction": float(np.mean(fracs)) if fracs else None,
        "plane_normal": [float(x) for x in plane.normal], "plane_offset_m": float(plane.offset_m),
        "systematic": syst,
        "lateral_left_m": None, "lateral_right_m": None, "lateral_left_px": None, "lateral_right_px": None,
        "lateral_left_stderr_m": None, "lateral_right_stderr_m": None,
        "corners_px": None if det.corners is None else det.corners.round(1).tolist(),
        "notes": notes,
        "target": t,
        "geometry": cap.geometry,
        "fx_px": float(K[0, 0]),
        "axial_bins": None if bins is None else [{k: v for k, v in b.items() if not k.startswith("_")}
                                                 for b in bins["bins"]],
    }
    if bins is not None:
        rec["_axial_bins"] = bins["bins"]
        if bins["reason"]:
            rec["notes"]["axial_bins"] = bins["reason"]
    if axial["reason"]:
        rec["notes"]["axial"] = axial["reason"]
    if keep.sum() < band.sum():
        rec["region_pixels_off_plane"] = int(band.sum() - keep.sum())
    for side in ("left", "right"):
        edge = det.edges.get(side)
        if cap.kind in ("wall", "plane"):
            rec["notes"][f"lateral_{side}"] = f"a {cap.kind} has no edges"
            continue
        if edge is None:
            rec["notes"][f"lateral_{side}"] = det.edge_reasons.get(side, "edge not found")
            continue
        lat = _lateral_edge(depth, scale, K, plane, edge, ref, W)
        if lat.get("sigma_m") is None:
            rec["notes"][f"lateral_{side}"] = lat.get("reason")
            continue
        rec[f"lateral_{side}_m"] = lat["sigma_m"]
        rec[f"lateral_{side}_px"] = lat["sigma_px"]
        rec[f"lateral_{side}_stderr_m"] = lat["stderr_m"]
        rec[f"lateral_{side}_detail"] = {k: lat[k] for k in ("between_px", "within_px", "n_frames", "n_censored",
                                                             "dof", "n_rows", "slope", "m_per_px", "threshold_m",
                                                             "sigma_z_edge_m")}
    if keep_image:
        tv, tu = np.nonzero(det.target_mask)
        tup, tvp = planes.normalised_coordinates(K, tu, tv)
        acc = np.zeros(tv.size)
        cnt = np.zeros(tv.size)
        for f0 in range(0, N, _CHUNK_FRAMES):
            zc_ = _to_metres(depth[f0:f0 + _CHUNK_FRAMES, tv, tu], scale)
            fin = np.isfinite(zc_)
            acc += np.where(fin, zc_, 0.0).sum(axis=0)
            cnt += fin.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            zt = np.where(cnt > 0, acc / cnt, np.nan)
        img = np.full((H, W), np.nan, dtype=np.float32)
        img[tv, tu] = plane.distance(planes.points_from_depth(zt, tup, tvp))
        rec["_plane_distance_image"] = img
        rec["_region_mask"] = det.region_mask
    return rec


# ------------------------------------------------------------------------------------------------
# the whole set


def _lateral_usable(r) -> bool:
    """A capture's lateral noise counts for sigma_L / sigma_R when its axial noise was measured and is at
    most MAX_REL_NOISE of the depth: beyond that the board's fitted plane, which maps the edge's pixels
    to metres, is too uncertain (at grazing angles a small tilt error changes metres per pixel a lot)."""
    s, z = r.get("axial_sigma_m"), r.get("z_m")
    return s is not None and z is not None and s <= MAX_REL_NOISE * z


def _lateral_summary(records, side: str) -> dict:
    rows = [r for r in records if r.get(f"lateral_{side}_m") is not None]
    for r in rows:
        if not _lateral_usable(r):
            r["notes"][f"lateral_{side}_summary"] = (
                "not used for sigma_L / sigma_R: the board's axial noise is unmeasured or above "
                f"{100 * MAX_REL_NOISE:.0f}% of the depth, so its plane (which converts pixels to metres) is uncertain")
    rows = [r for r in rows if _lateral_usable(r)]
    s = np.array([r[f"lateral_{side}_m"] for r in rows])
    px = np.array([r[f"lateral_{side}_px"] for r in rows])
    k = np.array([r[f"lateral_{side}_detail"]["dof"] for r in rows])
    m = ch.lateral_percentile(s, k, ch.LATERAL_PERCENTILE)
    mp = ch.lateral_percentile(px, k, ch.LATERAL_PERCENTILE)
    return {"value_m": m["value_m"], "value_px": mp["value_m"], "raw_percentile_m": m["raw_percentile_m"],
            "mean_m": m["mean_m"], "relative_spread": m["tau_log"], "n": m["n"]}


def run_characterize(captures_dir, json_path=None, rrd_path=None, figures_dir=None, *, model_path=None,
                     overwrite: bool = False, show_progress: bool = True, spawn: bool = False,
                     predict_dir=None, only=None) -> dict:
    """Characterise a camera from a capture set: per-capture noise, the sigma_z fit, sigma_L / sigma_R.

    Parameters
    ----------
    captures_dir : path
        The capture set's folder (``captures.json`` and its depth files).
    json_path : path, optional
        The JSON report, written atomically.
    rrd_path : path, optional
        A rerun recording of the figures.
    figures_dir : path, optional
        Folder for the PNG figures (:data:`FIGURE_FILES`); created if needed.
    model_path : path, optional
        Where the fitted model goes; default ``<json stem>.model.json`` next to ``json_path`` (no model
        file without either). Written only when the fit succeeds.
    overwrite : bool
        Replace existing output files (otherwise an existing one is an error, before any work; the
        missing folders of the outputs are created). See :func:`elevmap.fileio.check_outputs`.
    show_progress : bool
        A tqdm progress bar over the captures.
    spawn : bool
        Also stream the figures to a rerun viewer.
    predict_dir : path, optional
        Another capture set whose axial noise the fitted models predict (``prediction`` in the report).
    only : str or sequence of str, optional
        Characterise only these captures of the set (comma-separated ids): e.g. the wall of a stretch,
        whose model then predicts the floor with ``predict_dir``.

    Returns
    -------
    dict
        The report: ``format``, ``captures_dir``, ``camera``, ``fit`` (the paper's family: ``coefficients``
        [c0, c1, c2, c_theta], ``stderr``, ``residual_rms_rel``, ``residual_rms_m``, ``n``, ``vs_paper``; None
        with ``fit_reason`` when it cannot be fitted), ``fit_disparity`` (the disparity family: ``s0_px``,
        ``s1_px_per_rad2``, ``stderr``, ``s1_fixed``...; None with ``fit_disparity_reason``), ``heldout``
        (:func:`noise_model.analysis.family_fit.heldout_errors`), ``family`` (the family of the model written:
        the one with the smaller held-out error), ``skipped_statistics`` (captures with fitted geometry and
        what was not computed for them), ``frame_error`` (the per-frame error a map sees beyond the
        per-pixel temporal sigma, and its correlation length, which the model file carries:
        :func:`elevmap.commands.characterize_models.measure_frame_error`), ``prediction`` (with
        ``predict_dir``), ``sigma_L_m``, ``sigma_R_m``, ``sigma_L_px``,
        ``sigma_R_px`` (90th percentiles; None when no edge was measurable), ``lateral`` (details),
        ``captures`` (one record per measured capture: ``id``, ``axial_sigma_m``, ``lateral_left_m``,
        ``lateral_right_m``, their ``_px`` and ``_stderr_m`` versions, ``plane_residual_std_m``,
        ``systematic``..., null where not measurable and the reason under ``notes``), ``failures``
        (``id`` and ``reason``), ``model_path``, ``figures``, ``rrd``.
    """
    from tqdm import tqdm

    from ..sources.captures import read_capture_set

    cs = read_capture_set(captures_dir)
    other = None if predict_dir is None else read_capture_set(predict_dir)
    if model_path is None and json_path is not None:
        model_path = default_model_path(json_path)
    fig_paths = {k: Path(figures_dir) / v for k, v in FIGURE_FILES.items()} if figures_dir is not None else {}
    check_outputs({"json_path": json_path, "model_path": model_path, "rrd_path": rrd_path,
                   **{f"figure {k}": p for k, p in fig_paths.items()}}, overwrite,
                  inputs=[cs.folder / "captures.json", *(c.path for c in cs.captures)], create_folders=True)
    if not cs.captures:
        raise ValueError(f"{cs.folder}: the capture set holds no captures")
    selected = cs.captures
    if only is not None:
        ids = check_names(only, "--only", allowed=cs.ids, what="capture")
        selected = [c for c in cs.captures if c.id in ids]

    keep_images = rrd_path is not None or figures_dir is not None or spawn
    records, failures, fe_rows, fe_skipped = [], [], [], []
    for cap in tqdm(selected, desc="characterize", unit="capture", disable=not show_progress):
        depth = cs.load_depth(cap.id)           # read once: the record and the per-frame error share it
        rec = characterize_capture(cs, cap, keep_image=keep_images, depth=depth)
        if "failed" in rec:
            failures.append({"id": rec["id"], "reason": rec["failed"]})
            continue
        records.append(rec)
        row, skip = frame_error_row(cs, cap, depth)
        (fe_rows if skip is None else fe_skipped).append(row if skip is None else skip)

    fit_d, fit_reason, fit, fam = fit_families(records, cs.camera, MAX_REL_NOISE)
    frame_error = frame_error_report(cs, fe_rows, fe_skipped)
    lat_l, lat_r = _lateral_summary(records, "left"), _lateral_summary(records, "right")
    report = {
        "format": REPORT_FORMAT,
        "captures_dir": str(cs.folder),
        "only": None if only is None else [c.id for c in selected],
        "camera": cs.camera,
        "camera_mismatches": list(cs.mismatches),
        "fit": fit_d,
        "fit_reason": fit_reason,
        "fit_disparity": fam["disparity"],
        "fit_disparity_reason": fam["disparity_reason"],
        "heldout": fam["heldout"],
        "family": None,
        "skipped_statistics": [
            {"id": r["id"], "statistics": ["systematic error (bias, scale)"], "reason": r["notes"]["systematic"]}
            for r in records if r.get("geometry") == "fitted"],
        "sigma_L_m": lat_l["value_m"], "sigma_R_m": lat_r["value_m"],
        "sigma_L_px": lat_l["value_px"], "sigma_R_px": lat_r["value_px"],
        "lateral": {"percentile": ch.LATERAL_PERCENTILE,
                    "method": "per capture, the spread of the edge's pixels about a line fitted along it over "
                              "all frames; sigma_L / sigma_R = the 90th percentile over the captures after "
                              "removing each capture's sampling error (empirical-Bayes shrinkage of log variances)",
                    "left": lat_l, "right": lat_r, "paper_sigma_L_m": D435.sigma_L, "paper_sigma_R_m": D435.sigma_R},
        "frame_error": frame_error,
        "captures": [{k: v for k, v in r.items() if not k.startswith("_")} for r in records],
        "failures": failures,
        "model_path": None, "figures": [], "rrd": None,
    }
    model = None
    better = fam["better"] if fam["better"] is not None else ("paper" if fit is not None else None)
    if better == "paper" and fit is None:
        better = "disparity"
    if better is not None:
        cam = cs.camera
        dfit = fam["_disparity"]
        model = ch.model_from_fit(
            None if fit is None else fit.coefficients, lat_l["value_m"], lat_r["value_m"],
            name=f"{cam.get('model') or 'D435'} (characterised from {cs.folder.name}, {better} family)",
            baseline_m=cam.get("baseline_m"), mode=(int(cam["width"]), int(cam["height"]), float(cam["fx"])),
            disparity=None if better == "paper" else (dfit.s0, dfit.s1))
        frame_noise, why = fit_frame_noise(records, frame_error, better, cam, MAX_REL_NOISE)
        report["frame_error"]["frame_noise"], report["frame_error"]["frame_noise_reason"] = frame_noise, why
        model = with_frame_error(model, frame_error, frame_noise)
        report["family"] = better
        report["model"] = model.to_dict()
        report["model"]["lateral_from"] = {
            "sigma_L": "measured" if lat_l["value_m"] is not None else "the paper (no left edge measured)",
            "sigma_R": "measured" if lat_r["value_m"] is not None else "the paper (no right edge measured)"}
    else:
        report["model"] = None
    if other is not None:
        measured = [characterize_capture(other, cap) for cap in tqdm(other.captures, desc="predict", unit="capture",
                                                                      disable=not show_progress)]
        report["prediction"] = predict_capture_set(other, measured, model, fit, fam["_disparity"], cs.camera)
    # outputs last, the JSON report at the very end; on failure the files this call created are removed
    created = []
    try:
        if model is not None and model_path is not None:
            Path(model_path).parent.mkdir(parents=True, exist_ok=True)
            if not Path(model_path).exists():
                created.append(Path(model_path))
            model.save(model_path)
            report["model_path"] = str(model_path)
        if figures_dir is not None:
            from ..viz import plots

            Path(figures_dir).mkdir(parents=True, exist_ok=True)
            created += [p for p in fig_paths.values() if not p.exists()]
            series = figure_series(report)
            plots.plot_systematic_error(series, fig_paths["systematic_error"])
            plots.plot_axial_variance(series, fig_paths["axial_variance"])
            plots.plot_plane_distance(plane_distance_panels(records), fig_paths["plane_distance"])
            plots.plot_lateral_noise(series, fig_paths["lateral_noise"])
            report["figures"] = [str(p) for p in fig_paths.values()]
        if rrd_path is not None or spawn:
            if rrd_path is not None:
                Path(rrd_path).parent.mkdir(parents=True, exist_ok=True)
                if not Path(rrd_path).exists():
                    created.append(Path(rrd_path))
            _write_rrd(report, records, rrd_path, spawn)
            report["rrd"] = None if rrd_path is None else str(rrd_path)
        if json_path is not None:
            write_json_atomic(json_path, json_ready(report))
    except BaseException:
        for p in created:
            p.unlink(missing_ok=True)
        raise
    return report


# ------------------------------------------------------------------------------------------------
# figures data (shared by plots.py and the rerun recording)


def figure_series(report: dict) -> dict:
    """Plain arrays of the figures: Fig. 2 (systematic error vs distance with eq. (1)), Fig. 3 (variance
    vs distance per angle with the fitted and the paper's curves) and the lateral noise per capture.

    Fig. 2 uses the ``wall`` captures when there are any (the paper's), else all captures, at the
    smallest angle measured. ``lateral[side]`` holds the captures used for sigma_L / sigma_R,
    ``lateral[side + "_unused"]`` those left out (noise too large for the plane to convert pixels).
    """
    caps = report["captures"]
    measured = [c for c in caps if c.get("geometry", "measured") != "fitted"]     # fitted: no systematic error
    walls = [c for c in measured if c["kind"] == "wall"]
    base = walls or measured
    fig2 = {"kind": "wall" if walls else "board", "distance_m": [], "rms_error_m": [], "residual_m": [],
            "eq1_m": [], "theta_deg": None}
    if base:
        t0 = min(round(c["yaw_deg"]) for c in base)
        sel = sorted((c for c in base if round(c["yaw_deg"]) == t0), key=lambda c: c["distance_m"])
        fig2.update(theta_deg=float(t0), distance_m=[c["distance_m"] for c in sel],
                    rms_error_m=[c["systematic"]["rms_error_m"] for c in sel],
                    residual_m=[c["plane_residual_std_m"] for c in sel],
                    eq1_m=[c["systematic"]["eq1_m"] for c in sel])
    angles = sorted({int(round(c["yaw_deg"])) for c in caps if c.get("axial_sigma_m")})
    fig3 = {"angles_deg": angles, "points": {}, "curve_z_m": list(np.linspace(0.3, 2.2, 60)), "fitted": {},
            "paper": {}}
    coef = report["fit"]["coefficients"] if report.get("fit") else None
    zc = np.asarray(fig3["curve_z_m"])
    for a in angles:
        sel = [c for c in caps if c.get("axial_sigma_m") and int(round(c["yaw_deg"])) == a]
        fig3["points"][a] = ([c["z_m"] for c in sel], [c["axial_sigma_m"] ** 2 for c in sel])
        th = float(np.median([math.radians(c["theta_deg"]) for c in sel]))
        fig3["paper"][a] = list(nm.axial_sigma(zc, th) ** 2)
        if coef:
            fig3["fitted"][a] = list(ch.axial_model(zc, th, *coef) ** 2)
    lat = {}
    for side in ("left", "right"):
        used = [c for c in caps if c.get(f"lateral_{side}_m") and _lateral_usable(c)]
        unused = [c for c in caps if c.get(f"lateral_{side}_m") and not _lateral_usable(c)]
        lat[side] = ([c["distance_m"] for c in used], [c[f"lateral_{side}_m"] for c in used])
        lat[f"{side}_unused"] = ([c["distance_m"] for c in unused], [c[f"lateral_{side}_m"] for c in unused])
    lat.update({
           "sigma_L_m": report.get("sigma_L_m"), "sigma_R_m": report.get("sigma_R_m"),
           "paper_sigma_L_m": D435.sigma_L, "paper_sigma_R_m": D435.sigma_R})
    return {"fig2": fig2, "fig3": fig3, "lateral": lat}


def plane_distance_panels(records, n_max: int = 6) -> list[tuple[str, np.ndarray, float]]:
    """Fig. 4 panels: (capture id, per-pixel distance image [m], colour range [m]) of up to ``n_max``
    captures at the smallest angle, spread over the distances (walls first, as the paper). The colour
    range is the 98th percentile of |distance| over the central region (the board's moving edges, where
    the mean of the frames mixes board and background, would otherwise set it)."""
    have = [r for r in records if "_plane_distance_image" in r]
    walls = [r for r in have if r["kind"] == "wall"]
    base = walls or have
    if not base:
        return []
    t0 = min(round(r["yaw_deg"]) for r in base)
    sel = sorted((r for r in base if round(r["yaw_deg"]) == t0), key=lambda r: r["distance_m"])
    if len(sel) > n_max:
        sel = [sel[int(round(i))] for i in np.linspace(0, len(sel) - 1, n_max)]
    return [(r["id"], r["_plane_distance_image"], _colour_range(r)) for r in sel]


def _colour_range(r) -> float:
    img, region = r["_plane_distance_image"], r["_region_mask"]
    v = np.abs(img[region & np.isfinite(img)])
    if not v.size:
        v = np.abs(img[np.isfinite(img)])
    return float(max(np.percentile(v, 98), 1e-4)) if v.size else 1e-3


def _write_rrd(report, records, rrd_path, spawn) -> None:
    from .. import viz

    series = figure_series(report)
    panels = [(r["id"], r["_plane_distance_image"], _colour_range(r)) for r in records
              if "_plane_distance_image" in r]
    with viz.open_recording(rrd_path, "elevmap_characterize", spawn=spawn) as rec:
        viz.log_characterisation(rec, series, panels, _summary_markdown(report))


def format_summary(report: dict) -> str:
    """A few lines for the terminal: the fit against the paper, sigma_L / sigma_R, failures, outputs."""
    n_ok, n_bad = len(report["captures"]), len(report["failures"])
    lines = [f"{n_ok} captures measured, {n_bad} not found"]
    fit = report.get("fit")
    if fit:
        c, e, pc = fit["coefficients"], fit["stderr"], fit["paper_coefficients"]
        lines.append("sigma_z = c0 + c1 z + c2 z^2 + c_theta z^1.5 theta/(pi/2-theta)^2, fitted on "
                     f"{fit['n']} measurements (residual {100 * fit['residual_rms_rel']:.1f}% RMS):")
        for name, v, s_, p in zip(("c0", "c1", "c2", "c_theta"), c, e, pc):
            lines.append(f"  {name:8s} {v:11.6g} +- {s_:.2g}   (paper {p:g})")
        vp = fit["vs_paper"]
        lines.append("  vs the paper where its sigma_z < 5 cm: "
                     f"max {100 * vp['max_rel_diff_where_paper_below_0.05m']:.1f}%"
                     f", median {100 * vp['median_rel_diff_where_paper_below_0.05m']:.1f}%")
    else:
        lines.append(f"no fit of the paper's family: {report.get('fit_reason')}")
    dfit = report.get("fit_disparity")
    if dfit:
        lines.append(f"sigma_z = z^2 (s0 + s1 theta^2) / (f B), fitted on {dfit['n']} measurements (residual "
                     f"{100 * dfit['residual_rms_rel']:.1f}% RMS): s0 {dfit['s0_px']:.4f} px, s1 "
                     f"{dfit['s1_px_per_rad2']:.4f} px/rad^2" + (f" ({dfit['s1_fixed']})" if dfit["s1_fixed"] else ""))
    held = report.get("heldout")
    if held:
        parts = [f"{fam} {100 * v['rms_log_error']:.0f}% ({v['n_predicted']} measurements)"
                 for fam, v in held["families"].items() if v["rms_log_error"] is not None]
        lines.append("held-out error (RMS of log measured/predicted, blocks of distance and angle): "
                     + (", ".join(parts) or "no block could be predicted"))
    if report.get("family"):
        lines.append(f"model written: the {report['family']} family")
    for sk in report.get("skipped_statistics", []):
        lines.append(f"  {sk['id']}: no {', '.join(sk['statistics'])}: geometry fitted")
    pred = report.get("prediction")
    if pred:
        names = list(pred["models"])
        lines.append(f"prediction of {pred['captures_dir']} (measured / predicted sigma_z per depth bin):")
        lines.append("  capture            z [m]       real [mm]  " + "  ".join(f"{n:>16s}" for n in names))
        for c in pred["captures"]:
            for b in c["bins"]:
                zr = "whole" if b["z_range_m"] is None else f"{b['z_range_m'][0]:.1f}-{b['z_range_m'][1]:.1f}"
                lines.append(f"  {c['id'][:18]:18s} {zr:11s} {1000 * b['real_sigma_m']:8.2f}  "
                             + "  ".join(f"{b['ratio'][n]:16.3f}" if b["ratio"][n] is not None else
                                         f"{'sigma <= 0':>16s}" for n in names))
        for f in pred["failures"]:
            lines.append(f"  not measured: {f['id']}: {f['reason']}")
    for side in ("L", "R"):
        v, px = report.get(f"sigma_{side}_m"), report.get(f"sigma_{side}_px")
        lines.append(f"sigma_{side} (90th percentile): " + ("not measured" if v is None else
                                                           f"{1000 * v:.1f} mm ({px:.2f} px)"))
    for f in report["failures"]:
        lines.append(f"  not found: {f['id']}: {f['reason']}")
    for key, what in (("model_path", "model"), ("rrd", "recording")):
        if report.get(key):
            lines.append(f"wrote {what} {report[key]}")
    if report.get("figures"):
        lines.append(f"wrote {len(report['figures'])} figures to {Path(report['figures'][0]).parent}")
    return "\n".join(lines)


def _summary_markdown(report: dict) -> str:
    lines = ["# Characterisation", "", f"captures: {len(report['captures'])} measured, "
             f"{len(report['failures'])} failed", ""]
    fit = report.get("fit")
    if fit:
        names = ("c0", "c1", "c2", "c_theta")
        lines += ["| coefficient | fitted | stderr | paper |", "|---|---|---|---|"]
        lines += [f"| {n} | {c:.6g} | {s:.2g} | {p:.6g} |" for n, c, s, p in
                  zip(names, fit["coefficients"], fit["stderr"], fit["paper_coefficients"])]
        lines += ["", f"fit residual: {100 * fit['residual_rms_rel']:.1f} % RMS (relative), "
                  f"{1000 * fit['residual_rms_m']:.2f} mm RMS"]
    else:
        lines += [f"no fit: {report.get('fit_reason')}"]
    for side, key in (("L", "sigma_L_m"), ("R", "sigma_R_m")):
        v = report.get(key)
        lines.append(f"- sigma_{side}: " + ("not measured" if v is None else f"{1000 * v:.1f} mm "
                                            f"({report[key.replace('_m', '_px')]:.2f} px)"))
    for f in report["failures"]:
        lines.append(f"- failed `{f['id']}`: {f['reason']}")
    return "\n".join(lines)


