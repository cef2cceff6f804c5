"""`elevmap characterize`: a D435's own noise model from a capture set, as Ahn et al. (2019) did.

Unit tests of the maths (noise_model.analysis.planes, noise_model.analysis.characterization) and the
target detection (noise_model.analysis.detection) on synthetic data with known answers, the must-show
on a capture set simulated with the reference model at the paper's grid (and with 20 % of it removed),
and the plane-fit residuals of two genuine D435 recordings against their figures.json.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import replace

import numpy as np
import pytest

import noise_model as nm
from noise_model.analysis import characterization as ch, planes
from noise_model.analysis.detection import detect_target
from noise_model.sim.targets import render_planar_target, simulate_target_frames

PAPER = nm.D435
#: The must-show runs on the paper's grid with this many frames per capture (see the module docstring of
#: the test below: the estimators are unbiased, so fewer frames only widen the scatter, which stays far
#: inside the tolerances; the paper's 100 frames per capture are too slow for a test).
GRID_FRAMES = 10


# ------------------------------------------------------------------------------------------------
# planes, axial noise


def _plane_pixels(K, W, H, plane, box):
    (r0, r1), (c0, c1) = box
    vv, uu = np.mgrid[r0:r1, c0:c1]
    up, vp = planes.normalised_coordinates(K, uu.ravel(), vv.ravel())
    return up, vp, plane.depth_at(up, vp)


def test_plane_fits_recover_a_known_plane_despite_outliers(rng):
    K = PAPER.intrinsics(424, 240)
    true = ch.known_plane(1.2, yaw_deg=40.0, pitch_deg=-10.0)
    up, vp, z = _plane_pixels(K, 424, 240, true, ((60, 180), (150, 270)))
    zn = z + rng.normal(0.0, 0.01, z.size)                  # noise along the rays
    out = rng.random(z.size) < 0.2                          # 20 % of the pixels see something else
    zn[out] += rng.uniform(0.3, 1.0, out.sum())
    for fit in (planes.fit_plane_rays(zn, up, vp), planes.fit_plane_robust(planes.points_from_depth(zn, up, vp))):
        assert math.degrees(math.acos(float(fit.plane.normal @ true.normal))) < 0.5
        assert fit.plane.offset_m == pytest.approx(true.offset_m, abs=2e-3)
        assert fit.inliers[out].mean() < 0.01 and fit.inliers[~out].mean() > 0.95
    assert planes.fit_plane_rays(zn, up, vp).plane.theta_rad == pytest.approx(true.theta_rad, abs=0.01)
    with pytest.raises(ValueError, match="shape"):
        planes.fit_plane_robust(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="metres"):
        planes.fit_plane_rays(zn * 1000.0, up, vp)


def test_axial_noise_is_the_models_sigma_z_along_the_ray_not_the_distance_to_the_plane(rng):
    """The reference simulation adds N(0, sigma_z^2) to z; the distance to a plane at 60 deg moves by only
    cos(60 deg) of that. The estimator returns sigma_z (so the fit gives the paper's coefficients) and
    reports the orthogonal spread beside it; a tripod's common-mode vibration is not counted."""
    K = PAPER.intrinsics(424, 240)
    plane = ch.known_plane(1.0, yaw_deg=60.0)
    up, vp, z = _plane_pixels(K, 424, 240, plane, ((90, 150), (190, 234)))
    sigma, N = 0.02, 40
    vib = rng.normal(0.0, 0.02, (N, 1))                     # each frame moves the whole plane in depth
    samples = np.round((z[None, :] * (1 + vib) + rng.normal(0.0, sigma, (N, z.size))) / 0.001) * 0.001
    a = ch.axial_noise(samples, up, vp, plane, depth_scale=0.001)
    assert a["sigma_z_m"] == pytest.approx(sigma, rel=0.03)
    assert a["stderr_m"] < 0.01 * sigma
    assert a["plane_distance_sigma_m"] == pytest.approx(sigma * 0.5, rel=0.05)     # cos(60 deg)
    assert a["theta_rad"] == pytest.approx(math.radians(60.0))
    plain = ch.axial_noise(samples, up, vp, plane, depth_scale=0.001, frame_correction=False)
    assert plain["sigma_z_m"] > 1.2 * sigma                 # the vibration would have been counted
    one = ch.axial_noise(samples[:1], up, vp, plane)
    assert one["sigma_z_m"] is None and ">= 2 frames" in one["reason"]
    with pytest.raises(ValueError, match="floating-point metres"):
        ch.axial_noise(samples.astype(np.int64), up, vp, plane)
    with pytest.raises(ValueError, match="shape"):
        ch.axial_noise(samples[:, :-1], up, vp, plane)


# ------------------------------------------------------------------------------------------------
# lateral noise


def _edge_windows(shifts_px, n_rows=40, width=60, centre=30.0):
    """Left-edge windows: pixel column c is on the board when c >= the frame's boundary."""
    cols = np.arange(width)
    e = centre + np.asarray(shifts_px)[:, None, None]
    on = np.broadcast_to(cols[None, None, :] >= e, (len(shifts_px), n_rows, width)).copy()
    return on, np.zeros(n_rows, dtype=np.int64)


def test_lateral_noise_measures_the_edges_motion_and_handles_edges_leaving_the_view(rng):
    shifts = rng.normal(0.0, 4.0, 400)                      # 4 px per frame
    on, start = _edge_windows(shifts)
    pos, sat = ch.edge_positions(on, "left", start)
    assert not sat.any()
    assert np.abs(pos[:, 0] - (30.0 + shifts)).max() <= 0.5 + 1e-9          # the boundary to half a pixel
    lat = ch.lateral_noise(pos, sat, np.arange(40), m_per_px=0.01)
    assert lat["sigma_px"] == pytest.approx(np.std(shifts, ddof=1), rel=0.02)
    assert lat["sigma_m"] == pytest.approx(0.01 * lat["sigma_px"])
    # a window that ends 5 px left of the mean edge: 11 % of the frames see the edge leave it (censored)
    on, start = _edge_windows(shifts, width=35, centre=5.0)
    pos, sat = ch.edge_positions(on, "left", start)
    lost = (sat == -1).all(axis=1)
    assert 0.05 < lost.mean() < 0.2
    lat = ch.lateral_noise(pos, sat, np.arange(40), m_per_px=0.01)
    assert lat["n_censored"] == lost.sum()
    assert lat["sigma_px"] == pytest.approx(4.0, rel=0.08)
    assert np.std(shifts[~lost], ddof=1) < 0.9 * 4.0        # dropping them instead would bias it low
    with pytest.raises(ValueError, match="boolean"):
        ch.edge_positions(on.astype(np.uint8), "left", start)


def test_lateral_percentile_removes_each_captures_sampling_error(rng):
    k = np.full(80, 9.0)                                    # 10 frames per capture
    s = np.sqrt(rng.chisquare(9, 80) / 9.0)                 # all captures truly 1.0
    p = ch.lateral_percentile(s, k)
    assert p["raw_percentile_m"] > 1.15                     # the raw 90th percentile is biased up
    assert p["value_m"] == pytest.approx(1.0, rel=0.06)
    true = np.exp(rng.normal(0.0, 0.3, 200))                # captures that really differ
    s = true * np.sqrt(rng.chisquare(99, 200) / 99.0)
    p = ch.lateral_percentile(s, np.full(200, 99.0))
    assert p["value_m"] == pytest.approx(np.percentile(true, 90), rel=0.08)
    assert ch.lateral_percentile([], [])["value_m"] is None


# ------------------------------------------------------------------------------------------------
# systematic error, the fit, the model


def test_known_plane_systematic_error_and_equation_1():
    p = ch.known_plane(1.0, yaw_deg=30.0)
    assert p.depth_at(0.0, 0.0) == pytest.approx(1.0)
    assert p.theta_rad == pytest.approx(math.radians(30.0))
    s = ch.systematic_error([1.01, 0.99, 1.02], [1.0, 1.0, 1.0])
    assert s["rms_error_m"] == pytest.approx(math.sqrt((1e-4 + 1e-4 + 4e-4) / 3))
    assert s["mean_error_m"] == pytest.approx(0.02 / 3)
    # the realdata PROVENANCE: z^2 0.08 / (425.8 x 0.050) = 10.0 mm at 1.63 m
    assert ch.eq1_rms_error(1.63, 425.849, 848) == pytest.approx(1.63 ** 2 * 0.08 / (425.849 * 0.05))
    assert ch.eq1_rms_error(1.63, 425.849, 848) == pytest.approx(0.0100, abs=5e-5)


def test_fit_returns_the_coefficients_of_noisy_measurements_and_leaves_out_a_bad_capture(rng, tmp_path):
    z, th = np.meshgrid(np.arange(0.4, 2.15, 0.1), np.radians(np.arange(0, 76, 15)), indexing="ij")
    z, th = z.ravel(), th.ravel()
    s = nm.axial_sigma(z, th)
    keep = s < 0.2 * z
    z, th, s = z[keep], th[keep], s[keep] * (1.0 + rng.normal(0.0, 0.01, keep.sum()))
    s[7] *= 2.0                                             # a capture whose board was partly hidden
    fit = ch.fit_axial_model(z, th, s)
    assert not fit.inliers[7] and fit.inliers.sum() == len(s) - 1
    grid_z, grid_t = np.meshgrid(np.arange(0.4, 2.15, 0.1), np.radians(np.arange(0, 76, 15)))
    rel = np.abs(fit.sigma_z(grid_z, grid_t) / nm.axial_sigma(grid_z, grid_t) - 1)
    assert rel.max() < 0.03
    assert fit.residual_rms_rel == pytest.approx(0.01, rel=0.3)
    assert all(e > 0 for e in fit.stderr)
    assert abs(fit.coefficients[3] - PAPER.c_theta) < 4 * fit.stderr[3]
    # the fit as a SensorModel, saved and loaded, replaces the paper's wherever a model is taken
    model = ch.model_from_fit(fit.coefficients, 0.01, 0.012, baseline_m=0.05, mode=(848, 480, 425.0))
    model.save(tmp_path / "mine.model.json")
    back = nm.SensorModel.load(tmp_path / "mine.model.json")
    assert back == model
    assert nm.axial_sigma(1.3, 0.4, model=back) == pytest.approx(float(fit.sigma_z(1.3, 0.4)))
    assert back.sigma_L == 0.01 and back.focal_px(848, 480) == pytest.approx(425.0)
    with pytest.raises(ValueError, match="at least 5"):
        ch.fit_axial_model(z[:4], th[:4], s[:4])
    with pytest.raises(ValueError, match="radians"):
        ch.fit_axial_model(z, np.degrees(th), s)


# ------------------------------------------------------------------------------------------------
# detection


def test_detection_finds_the_boards_quadrilateral_edges_and_central_region(rng):
    W, H = 424, 240
    K = PAPER.intrinsics(W, H)
    still = replace(PAPER, sigma_L=1e-6, sigma_R=1e-6)     # edges that do not move
    frames = simulate_target_frames(K, W, H, 1.0, 15, rng, kind="board", width_m=0.6, height_m=0.9,
                                    background_m=3.0, model=still)
    z = frames.astype(np.float32) * 0.001
    z[frames == 0] = np.nan
    det = detect_target(np.nanmedian(z, axis=0), "board", (K[0, 2], K[1, 2]))
    assert det.ok, det.reason
    f, cx, cy = K[0, 0], K[0, 2], K[1, 2]
    true = np.array([[cx - 0.3 * f, cy - 0.45 * f], [cx + 0.3 * f, cy - 0.45 * f],
                     [cx + 0.3 * f, cy + 0.45 * f], [cx - 0.3 * f, cy + 0.45 * f]])
    assert np.abs(det.corners - true).max() < 3.0                # the corners only bound the edges and region
    left, right = det.edges["left"], det.edges["right"]
    assert left.column_at(120) == pytest.approx(cx - 0.3 * f, abs=1.0)
    assert right.column_at(120) == pytest.approx(cx + 0.3 * f, abs=1.0)
    span = true[3, 1] - true[0, 1]                          # corners removed: 15 % at both ends
    assert left.rows.min() >= true[0, 1] + 0.14 * span and left.rows.max() <= true[3, 1] - 0.14 * span
    vv, uu = np.nonzero(det.region_mask)
    assert np.abs(uu - cx).max() <= 0.21 * 0.6 * f and np.abs(vv - cy).max() <= 0.21 * 0.9 * f
    assert det.target_mask[det.region_mask].all()


def test_detection_reports_why_a_target_is_not_found(rng):
    W, H = 424, 240
    K = PAPER.intrinsics(W, H)
    wall, _ = render_planar_target(K, W, H, 1.5, kind="wall")
    det = detect_target(wall.astype(np.float32), "board", (K[0, 2], K[1, 2]))
    assert not det.ok and "no board outline" in det.reason
    det = detect_target(wall.astype(np.float32), "wall", (K[0, 2], K[1, 2]))
    assert det.ok and det.edges == {"left": None, "right": None} and det.region_mask.sum() > 1000
    det = detect_target(np.zeros((H, W), np.float32), "board", (K[0, 2], K[1, 2]))
    assert not det.ok and "have depth" in det.reason
    wide, _ = render_planar_target(K, W, H, 0.4, yaw_deg=45.0, kind="board", width_m=0.6, height_m=0.9,
                                   background_m=3.0)
    det = detect_target(wide.astype(np.float32), "board", (K[0, 2], K[1, 2]))
    assert det.ok and det.edges["right"] is None and "image border" in det.edge_reasons["right"]
    with pytest.raises(ValueError, match="floating-point metres"):
        detect_target((wall * 1000).astype(np.uint16), "wall", (K[0, 2], K[1, 2]))
    with pytest.raises(ValueError, match="kind"):
        detect_target(wall.astype(np.float32), "disc", (K[0, 2], K[1, 2]))


# ------------------------------------------------------------------------------------------------
# the must-show: the paper's grid, simulated with the reference model


@pytest.fixture(scope="module")
def paper_grid_set(tmp_path_factory):
    from elevmap.commands.simulate import simulate_capture_set

    out = tmp_path_factory.mktemp("paper_grid")
    simulate_capture_set(out, "paper", n_frames=GRID_FRAMES, seed=11, show_progress=False)
    return out


def _check_against_paper(report, tol_sigma_z, tol_lateral):
    coef = report["fit"]["coefficients"]
    mine = replace(PAPER, axial_coefficients=tuple(coef))
    z, th = np.meshgrid(np.round(np.arange(0.4, 2.15, 0.1), 2), np.radians(np.arange(0, 76, 15)))
    paper = nm.axial_sigma(z, th)
    below = paper < 0.05
    rel = np.abs(nm.axial_sigma(z, th, model=mine) / paper - 1)[below]
    assert rel.max() < tol_sigma_z, (rel.max(), coef)
    assert report["sigma_L_m"] == pytest.approx(PAPER.sigma_L, rel=tol_lateral)
    assert report["sigma_R_m"] == pytest.approx(PAPER.sigma_R, rel=tol_lateral)
    return rel.max()


def test_paper_grid_gives_back_the_papers_model(paper_grid_set, tmp_path):
    """Must-show: the fitted sigma_z within 10 % of the paper's wherever it is below 0.05 m, sigma_L and
    sigma_R within 15 % (here with 10 frames per capture)."""
    from elevmap.commands.characterize import run_characterize

    rep = run_characterize(paper_grid_set, json_path=tmp_path / "r.json", show_progress=False)
    _check_against_paper(rep, 0.10, 0.15)
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["fit"]["coefficients"] == rep["fit"]["coefficients"] and len(doc["fit"]["stderr"]) == 4
    assert doc["fit"]["residual_rms_rel"] < 0.05
    assert doc["sigma_L_px"] > 1 and doc["sigma_R_px"] > 1
    by_id = {c["id"]: c for c in doc["captures"]}
    assert len(by_id) + len(doc["failures"]) == 108
    assert all(f["reason"] for f in doc["failures"]) and all(f["id"].endswith("y75") for f in doc["failures"])
    c = by_id["board_z1.00_y00"]
    assert c["axial_sigma_m"] == pytest.approx(nm.axial_sigma(1.0, 0.0), rel=0.05)
    assert c["lateral_left_m"] > 0 and c["lateral_right_m"] > 0 and c["lateral_left_px"] > 1
    # near and turned, a board's near edge leaves the view: null, with the reason
    out_of_view = [c for c in doc["captures"] if "image border" in c["notes"].get("lateral_right", "")]
    assert out_of_view and all(c["lateral_right_m"] is None and c["distance_m"] <= 0.6 for c in out_of_view)
    # the fitted model, next to the report, loads and holds the fit
    model = nm.SensorModel.load(tmp_path / "r.model.json")
    assert list(model.axial_coefficients) == rep["fit"]["coefficients"]
    # data of the paper's model: its family predicts held-out blocks of distance and angle better
    assert rep["family"] == "paper" and model.family == "paper"
    held = rep["heldout"]["families"]
    assert held["paper"]["rms_log_error_common"] < held["disparity"]["rms_log_error_common"]
    assert model.sigma_L == rep["sigma_L_m"] and model.sigma_R == rep["sigma_R_m"]
    # the reference simulation's pixels are independent and have no static error: the per-frame error is
    # the temporal one (ratio 1 within the static estimate's noise, no correlation), and the map's sigma_z
    # is the temporal fit's
    fe = doc["frame_error"]
    assert fe["pooled"]["n_captures"] >= 100 and fe["pooled"]["error_correlation_px"] == 0.0
    assert fe["pooled"]["frame_variance_ratio"] == pytest.approx(1.0, abs=0.01)
    assert model.error_correlation_px == 0.0 and model.frame_noise is not None
    assert nm.axial_sigma(1.0, 0.5, model=model.for_map()) == pytest.approx(nm.axial_sigma(1.0, 0.5, model=model),
                                                                             rel=0.02)


def test_paper_grid_with_a_fifth_of_the_captures_removed(paper_grid_set, tmp_path):
    from elevmap.commands.characterize import run_characterize
    from elevmap.sources.captures import read_capture_set, write_capture_set

    cs = read_capture_set(paper_grid_set)
    keep = sorted(np.random.default_rng(5).choice(len(cs.captures), 86, replace=False))
    for k in keep:                                          # the same recordings, linked
        os.symlink(cs.captures[k].path, tmp_path / cs.captures[k].depth)
    write_capture_set(tmp_path, cs.camera, [(cs.captures[k].to_dict(), None) for k in keep])
    rep = run_characterize(tmp_path, show_progress=False)
    assert len(rep["captures"]) + len(rep["failures"]) == 86
    _check_against_paper(rep, 0.15, 0.15)


# ------------------------------------------------------------------------------------------------
# a small capture set end to end: failures, outputs, no overwriting


def test_failures_are_reported_and_the_rest_runs_with_all_outputs(tmp_path):
    from elevmap.commands.characterize import FIGURE_FILES, run_characterize
    from elevmap.commands.simulate import simulate_capture_set
    from elevmap.sources.captures import write_capture_set

    sim = simulate_capture_set(tmp_path / "sim", [(0.6, 0.0), (1.0, 0.0), (1.4, 0.0), (0.8, 30.0), (1.2, 45.0),
                                                  (1.0, 60.0)], n_frames=8, seed=3, show_progress=False)
    K = sim.K
    blank = np.zeros((8, 240, 424), np.uint16)              # the camera saw nothing
    wall, _ = render_planar_target(K, 424, 240, 1.5, kind="wall")
    wall_frames = np.repeat(np.round(wall / 0.001).astype(np.uint16)[None], 8, axis=0)
    caps = [(c.to_dict(), None) for c in sim.captures]
    board = {"kind": "board", "distance_m": 1.5, "width_m": 0.6, "height_m": 0.9}
    caps += [({"id": "blank", "target": board}, blank), ({"id": "no_board", "target": board}, wall_frames)]
    for c in sim.captures:
        os.symlink(c.path, tmp_path / c.depth)
    write_capture_set(tmp_path, sim.camera, caps)
    out = tmp_path / "out"
    rep = run_characterize(tmp_path, json_path=out / "rep.json", rrd_path=out / "rep.rrd",
                           figures_dir=out / "figs", show_progress=False)
    reasons = {f["id"]: f["reason"] for f in rep["failures"]}
    assert set(reasons) == {"blank", "no_board"}
    assert "have depth" in reasons["blank"] and "no board outline" in reasons["no_board"]
    assert len(rep["captures"]) == 6 and rep["fit"] is not None
    for name in FIGURE_FILES.values():
        assert (out / "figs" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "rep.rrd").stat().st_size > 1000 and (out / "rep.model.json").is_file()
    assert json.loads((out / "rep.json").read_text())["failures"] == rep["failures"]
    before = (out / "rep.json").read_bytes()
    with pytest.raises(ValueError, match="exists"):
        run_characterize(tmp_path, json_path=out / "rep.json", show_progress=False)
    assert (out / "rep.json").read_bytes() == before


def test_a_truncated_depth_file_is_an_error_before_anything_is_written(tmp_path):
    from elevmap.commands.characterize import run_characterize
    from elevmap.commands.simulate import simulate_capture_set

    cs = simulate_capture_set(tmp_path, [(1.0, 0.0)], n_frames=3, show_progress=False)
    p = cs.captures[0].path
    p.write_bytes(p.read_bytes()[:-1000])
    with pytest.raises(ValueError, match="truncated"):
        run_characterize(tmp_path, json_path=tmp_path / "r.json", show_progress=False)
    assert not (tmp_path / "r.json").exists() and not (tmp_path / "r.model.json").exists()


# ------------------------------------------------------------------------------------------------
# genuine D435 recordings (single frames, a given region): the plane-fit residual of figures.json


def _single_region_set(folder, camera, capture, depth=None):
    from elevmap.sources.captures import write_capture_set

    return write_capture_set(folder, camera, [(capture, depth)])


@pytest.mark.realdata
def test_viewer_raw_board_residual_matches_the_figures(realdata, tmp_path):
    from elevmap.commands.characterize import run_characterize
    from elevmap.sources.viewer_raw import read_viewer_raw

    src = realdata / "opf_d435i_viewer_raw"
    fig = json.loads((src / "figures.json").read_text())["big_board_plane"]
    depth, K, meta = read_viewer_raw(src / "001_big_depth.raw")
    assert depth.shape == (480, 848) and K[0, 0] == pytest.approx(425.849243)
    camera = {"model": "D435i", "width": 848, "height": 480, "fx": K[0, 0], "fy": K[1, 1], "ppx": K[0, 2],
              "ppy": K[1, 2], "depth_scale": 0.001}
    # PROVENANCE: the board on the easel, rows 20-190, cols 300-430, at ~1.63 m
    cap = {"id": "easel_board", "target": {"kind": "wall", "distance_m": 1.63},
           "region_px": {"rows": [20, 190], "cols": [300, 430]}}
    _single_region_set(tmp_path, camera, cap, depth[None])
    rep = run_characterize(tmp_path, show_progress=False)
    c = rep["captures"][0]
    assert c["plane_residual_std_m"] == pytest.approx(fig["residual_std_mm"] / 1000.0, rel=0.10)
    assert c["plane_residual_mad_sigma_m"] == pytest.approx(fig["residual_mad_sigma_mm"] / 1000.0, rel=0.10)
    assert c["theta_deg"] == pytest.approx(fig["incidence_angle_deg"], abs=1.0)
    assert c["axial_sigma_m"] is None and "2 frames" in c["notes"]["axial"]
    assert rep["fit"] is None and "at least 5" in rep["fit_reason"]


@pytest.mark.realdata
def test_realsense_bag_wall_residual_matches_the_figures(realdata, tmp_path):
    from elevmap.commands.characterize import run_characterize

    src = realdata / "lrs_unittest_bag_d435"
    doc = json.loads((src / "figures.json").read_text())
    fig = doc["yellow_wall_plane"]
    fx, fy, ppx, ppy = doc["K"]
    camera = {"model": "D435", "width": 640, "height": 480, "fx": fx, "fy": fy, "ppx": ppx, "ppy": ppy,
              "depth_scale": 0.001}
    os.symlink(src / "single_depth_color_640x480.bag", tmp_path / "wall.bag")
    # PROVENANCE: the yellow wall, rows 10-260, cols 20-300, ~1.8 m
    cap = {"id": "yellow_wall", "depth": "wall.bag", "target": {"kind": "wall", "distance_m": 1.78},
           "region_px": {"rows": [10, 260], "cols": [20, 300]}}
    _single_region_set(tmp_path, camera, cap)
    rep = run_characterize(tmp_path, show_progress=False)
    c = rep["captures"][0]
    assert c["plane_residual_std_m"] == pytest.approx(fig["residual_std_mm"] / 1000.0, rel=0.10)
    assert c["theta_deg"] == pytest.approx(fig["incidence_angle_deg"], abs=1.0)
    assert c["lateral_left_m"] is None and c["notes"]["lateral_left"] == "a wall has no edges"


def test_realsense_recordings_at_640x480_are_characterised_like_npy(tmp_path, rng):
    """The same analysis on .db3 recordings (RealSense SDK) at another of the spec's resolutions."""
    from elevmap.commands.characterize import run_characterize
    from elevmap.sources.captures import write_capture_set
    from elevmap.sources.realsense import record_db3

    W, H = 640, 480
    K = PAPER.intrinsics(W, H)
    caps = []
    for d, yaw in ((0.6, 0.0), (1.0, 0.0), (1.4, 30.0), (0.8, 45.0), (1.2, 15.0)):
        frames = simulate_target_frames(K, W, H, d, 6, rng, yaw_deg=yaw, kind="board", width_m=0.6, height_m=0.9,
                                        background_m=3.0)
        name = f"board_{d:.1f}_{yaw:.0f}.db3"
        record_db3(tmp_path / name, frames, K, 0.001)
        caps.append(({"id": name[:-4], "depth": name, "target": {"kind": "board", "distance_m": d, "yaw_deg": yaw,
                                                                  "width_m": 0.6, "height_m": 0.9}}, None))
    camera = {"width": W, "height": H, "fx": K[0, 0], "fy": K[1, 1], "ppx": K[0, 2], "ppy": K[1, 2],
              "depth_scale": 0.001}
    write_capture_set(tmp_path, camera, caps)
    rep = run_characterize(tmp_path, show_progress=False)
    assert not rep["failures"] and not rep["camera_mismatches"]
    for c in rep["captures"]:
        assert c["n_frames"] == 6
        assert c["axial_sigma_m"] == pytest.approx(c["paper_sigma_z_m"], rel=0.05)
        assert c["lateral_left_m"] > 0.005 and c["lateral_right_m"] > 0.005
    assert rep["fit"]["vs_paper"]["max_rel_diff_where_paper_below_0.05m"] < 0.10


def test_a_static_error_pattern_is_measured_and_carried_by_the_model_file(tmp_path):
    """A static field of one temporal sigma over l = 4 px added to simulated captures: the report's per-frame
    variance ratio is about 2, its correlation length about 4 px, and the model file (/3) carries both and
    a per-frame sigma_z about sqrt(2) times the temporal one."""
    from scipy import ndimage

    from elevmap.commands.characterize import run_characterize
    from elevmap.commands.simulate import simulate_capture_set
    from elevmap.sources.captures import write_capture_set

    grid = [(0.6, 0.0), (0.8, 15.0), (1.0, 0.0), (1.2, 30.0), (1.4, 15.0), (1.0, 45.0)]
    sim = simulate_capture_set(tmp_path / "sim", grid, n_frames=8, seed=4, show_progress=False)
    rng = np.random.default_rng(8)
    caps = []
    for c in sim.captures:
        units = np.load(c.path)
        z = np.where(units > 0, units * 0.001, np.nan)
        field = ndimage.gaussian_filter(rng.standard_normal(z.shape[1:]), 4.0 / math.sqrt(2.0))
        sig = nm.axial_sigma(c.distance_m, math.radians(c.yaw_deg))
        z = z + sig * field / field.std()
        caps.append((c.to_dict(), np.where(np.isfinite(z), np.round(z / 0.001), 0).astype(np.uint16)))
    write_capture_set(tmp_path, sim.camera, caps)
    rep = run_characterize(tmp_path, json_path=tmp_path / "r.json", show_progress=False)
    fe = rep["frame_error"]["pooled"]
    assert fe["n_captures"] == 6
    # measured on the frames the records read, the same as measuring the set on its own
    from elevmap.commands.characterize_models import measure_frame_error
    from elevmap.sources.captures import read_capture_set
    cs = read_capture_set(tmp_path)
    alone = json.loads(json.dumps(measure_frame_error(cs, cs.captures), default=float))
    assert alone == {k: v for k, v in json.loads(json.dumps(rep["frame_error"], default=float)).items() if k in alone}
    assert fe["frame_variance_ratio"] == pytest.approx(2.0, rel=0.15)
    assert fe["error_correlation_px"] == pytest.approx(4.0, rel=0.2)
    doc = json.loads((tmp_path / "r.model.json").read_text())
    assert doc["format"] == "elevmap-sensor-model/3"
    model = nm.SensorModel.load(tmp_path / "r.model.json")
    assert model.error_correlation_fx_px == pytest.approx(sim.K[0, 0])
    ratio = nm.axial_sigma(1.0, 0.3, model=model.for_map()) / nm.axial_sigma(1.0, 0.3, model=model)
    assert ratio == pytest.approx(math.sqrt(2.0), rel=0.15)
