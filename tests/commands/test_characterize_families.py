"""`elevmap characterize` with both model families: plane targets with masks and fitted geometry, the
disparity family's fit, held-out blocks, the model file and the prediction of another capture set; and,
with the genuine aims_slam recording, the wall-to-floor prediction."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import noise_model as nm
from elevmap.commands.characterize import format_summary, run_characterize
from elevmap.sources.captures import write_capture_set

W, H, F = 160, 120, 100.0
CAMERA = {"model": "D435", "width": W, "height": H, "fx": F, "fy": F, "ppx": (W - 1) / 2, "ppy": (H - 1) / 2,
          "depth_scale": 0.001, "baseline_m": 0.05}
#: The simulated camera: sigma_d = 0.06 + 0.05 theta^2 px.
TRUE = nm.D435.with_disparity(0.06, 0.05, baseline_m=0.05)


def _plane(normal_to_camera, offset_m):
    m = np.asarray(normal_to_camera, dtype=float)
    return m / np.linalg.norm(m), float(offset_m)


def _frames(rng, normal, offset, model, n_frames, mask_rows=None):
    """Depth frames (uint16 mm) of the plane m . p + offset = 0 with per-pixel noise of ``model`` at the plane's
    angle to the optical axis, and its mask (the rows given, where the plane is within 0.3-4 m)."""
    v, u = np.mgrid[0:H, 0:W]
    ray = np.stack([(u - CAMERA["ppx"]) / F, (v - CAMERA["ppy"]) / F, np.ones((H, W))], axis=-1)
    denom = -(ray @ normal)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(denom > 1e-6, offset / denom, np.nan)
    mask = np.isfinite(z) & (z > 0.3) & (z < 4.0)
    if mask_rows is not None:
        mask &= (v >= mask_rows[0]) & (v < mask_rows[1])
    theta = math.acos(abs(normal[2]))
    zt = np.where(mask, z, 1.0)
    sig = nm.axial_sigma(zt, theta, model, fx_px=F)
    d = zt[None] + sig[None] * rng.standard_normal((n_frames, H, W))
    depth = np.where(mask[None] & (d > 0), np.round(d / 0.001), 0).astype(np.uint16)
    return depth, mask


def _write_set(folder, rng, planes, model=TRUE, n_frames=12):
    caps = []
    for cid, (normal, offset, rows) in planes.items():
        n, o = _plane(normal, offset)
        depth, mask = _frames(rng, n, o, model, n_frames, rows)
        caps.append(({"id": cid, "target": {"kind": "plane", "normal": list(n), "offset_m": o},
                      "geometry": "fitted"}, depth, mask))
    return write_capture_set(folder, CAMERA, caps)


#: A wall seen at 20 deg, a second wall at 45 deg and a floor seen at 65 deg (normals towards the camera).
FIT_PLANES = {
    "wall20": ((math.sin(math.radians(20)), 0.0, -math.cos(math.radians(20))), 1.0, None),
    "wall45": ((-math.sin(math.radians(45)), 0.0, -math.cos(math.radians(45))), 1.6, None),
    "floor65": ((0.0, -math.sin(math.radians(65)), -math.cos(math.radians(65))), 0.6, (62, 120)),
}


def test_characterize_fits_both_families_on_plane_captures_and_predicts_another_set(tmp_path):
    rng = np.random.default_rng(2)
    _write_set(tmp_path / "fit", rng, FIT_PLANES)
    _write_set(tmp_path / "other", rng, {"floor70": ((0.0, -math.sin(math.radians(70)), -math.cos(math.radians(70))),
                                                     0.63, (66, 120))}, n_frames=8)
    report = run_characterize(tmp_path / "fit", json_path=tmp_path / "r.json", show_progress=False,
                              predict_dir=tmp_path / "other")
    d = report["fit_disparity"]
    assert d["s0_px"] == pytest.approx(0.06, rel=0.1) and d["s1_px_per_rad2"] == pytest.approx(0.05, rel=0.3)
    assert report["family"] == "disparity"
    # fitted geometry: no systematic error, and the report says so
    assert {s["id"] for s in report["skipped_statistics"]} == set(FIT_PLANES)
    for c in report["captures"]:
        assert c["systematic"]["rms_error_m"] is None and "fitted" in c["notes"]["systematic"]
        assert c["lateral_left_m"] is None and c["notes"]["lateral_left"] == "a plane has no edges" and c["axial_bins"]
    # the model file is the disparity family and reads back as written
    model = nm.SensorModel.load(tmp_path / "r.model.json")
    assert model.family == "disparity" and model.disparity_sigma_px == pytest.approx((d["s0_px"], d["s1_px_per_rad2"]))
    assert model.to_dict() == {k: v for k, v in report["model"].items() if k != "lateral_from"}
    # the other set's floor, per depth bin: the fitted disparity model within 10 %, the paper's far off
    bins = report["prediction"]["captures"][0]["bins"]
    assert len(bins) >= 5
    for b in bins:
        assert b["ratio"]["model"] == pytest.approx(1.0, abs=0.1)
        assert b["ratio"]["paper_published"] < 0.2
    text = format_summary(report)
    assert "disparity" in text and "floor70" in text and "geometry fitted" in text
    on_disk = json.loads((tmp_path / "r.json").read_text())
    assert on_disk["family"] == "disparity" and "_z_pixels_m" not in json.dumps(on_disk)


def test_only_and_predict_check_their_inputs_before_writing(tmp_path):
    rng = np.random.default_rng(4)
    _write_set(tmp_path / "set", rng, {"wall20": FIT_PLANES["wall20"]}, n_frames=4)
    with pytest.raises(ValueError, match="nope"):
        run_characterize(tmp_path / "set", json_path=tmp_path / "r.json", show_progress=False, only="wall20,nope")
    with pytest.raises(ValueError, match="captures.json"):
        run_characterize(tmp_path / "set", json_path=tmp_path / "r.json", show_progress=False,
                         predict_dir=tmp_path / "missing")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["set"]
    # one plane at one angle: the disparity family with s1 fixed
    report = run_characterize(tmp_path / "set", show_progress=False, only="wall20")
    assert report["only"] == ["wall20"] and report["family"] == "disparity"
    assert report["fit_disparity"]["s1_fixed"] and report["model"]["format"] == "elevmap-sensor-model/2"


# ------------------------------------------------------------------------------------------------
# the genuine aims_slam recording: a model fitted on the wall predicts the floors

#: The capture ids `elevmap captures` gives the aims_slam stretches (ordered by mask size; checked below
#: by the planes' normals): the white wall and the concrete floor of frames 141-156, the floor of frames 1-8.
AIMS_WALL, AIMS_FLOORS = "f141-156_plane1", ("f141-156_plane2", "f1-8_plane1")
#: The floor's depth bins the prediction is judged on [m].
AIMS_BINS_M = (0.6, 1.9)


_AIMS = {}


@pytest.fixture
def aims_prediction(realdata, tmp_path_factory):
    """``elevmap captures DEPTH --frames 141-156,1-8`` then ``elevmap characterize SET --only WALL --predict SET``,
    the two commands docs/noise-model.md gives for this figure (run once for the tests that read it)."""
    if "result" not in _AIMS:
        _AIMS["result"] = _run_aims(realdata, tmp_path_factory.mktemp("aims"))
    return _AIMS["result"]


def _run_aims(realdata, out):
    from elevmap.cli import main

    assert main(["captures", str(realdata / "aims_slam_d435_robot_floor" / "depth"), "--frames", "141-156,1-8",
                 "--out", str(out / "set"), "--intrinsics", "383.8,383.8,321.7,238.2"]) == 0
    assert main(["characterize", str(out / "set"), "--only", AIMS_WALL, "--json", str(out / "wall.json"),
                 "--predict", str(out / "set"), "--no-progress"]) == 0
    report = json.loads((out / "wall.json").read_text())
    rows = {}
    for c in report["prediction"]["captures"]:
        rows[c["id"]] = [b for b in c["bins"] if b["z_range_m"][0] >= AIMS_BINS_M[0] - 1e-9
                         and b["z_range_m"][1] <= AIMS_BINS_M[1] + 1e-9]
    return report, rows, out


def test_aims_slam_wall_model_predicts_both_floors_within_a_factor_of_two(aims_prediction):
    """The wall of frames 141-156 alone (one incidence angle, so s1 is fixed at 0) gives sigma_d between 0.07
    and 0.09 px; over the floors' depth bins 0.6-1.9 m its sigma_z is within a factor of two of the measured
    one, and never below it, where the paper's published model states 33 or more times the measured sigma."""
    report, rows, out = aims_prediction
    caps = {c["id"]: c for c in report["prediction"]["captures"]}
    assert abs(caps[AIMS_WALL]["theta_deg"] - 27.3) < 2.0                 # figures.json: the wall's plane
    assert all(abs(caps[f]["theta_deg"] - 70.5) < 2.0 for f in AIMS_FLOORS)
    assert report["family"] == "disparity" and report["only"] == [AIMS_WALL]
    d = report["fit_disparity"]
    assert 0.07 < d["s0_px"] < 0.09 and d["s1_px_per_rad2"] == 0.0 and "fixed at 0" in d["s1_fixed"]
    assert report["skipped_statistics"][0]["id"] == AIMS_WALL               # fitted geometry: no bias or scale
    model = nm.SensorModel.load(out / "wall.model.json")
    assert model.family == "disparity" and model.s0 == pytest.approx(d["s0_px"])
    for f in AIMS_FLOORS:
        assert len(rows[f]) == 13
        for b in rows[f]:
            assert 0.5 <= b["ratio"]["model"] <= 1.0, (f, b["z_range_m"], b["ratio"])
            assert b["ratio"]["paper_published"] < 1 / 33, (f, b["z_range_m"], b["ratio"])


def test_aims_slam_wall_has_a_static_error_correlated_over_several_pixels(aims_prediction):
    """The per-frame error on a genuine D435: the wall's static error (about its plane, the frames' mean) adds
    about two thirds of its temporal variance (ratio 1.66), correlated over about 7.6 px at f = 383.8 px (4.2 px at
    the compare's f = 212 px, where the physical D435 simulation gives 4.06 px); the model file carries both."""
    report, _, out = aims_prediction
    fe = report["frame_error"]
    assert fe["pooled"]["n_captures"] == 1 and fe["captures"][0]["id"] == AIMS_WALL and fe["skipped"] == []
    assert 1.4 < fe["pooled"]["frame_variance_ratio"] < 2.0
    assert 6.0 < fe["pooled"]["error_correlation_px"] < 9.5
    model = nm.SensorModel.load(out / "wall.model.json")
    assert model.error_correlation_fx_px == pytest.approx(383.8)
    assert 3.2 < model.error_correlation_px * 212.0 / model.error_correlation_fx_px < 5.2


def test_aims_slam_floor_map_sigmas_from_the_wall_model_are_honest_and_the_papers_overstate(aims_prediction):
    """examples/real_floor_calibration.py on the frames 1-8 floor, held out from the wall's model: from one frame
    the wall-fitted map covers the floor's cells within 2.5 m at 2 sigma (0.97) without the paper's excess (whose
    median sigma is 5 times the cells' RMSE, 1-sigma 1.00); beyond 2.5 m the far floor's smooth error is not in
    either model (docs/calibration.md, the map on a genuine D435)."""
    import runpy

    _, _, out = aims_prediction
    ex = runpy.run_path(str(Path(__file__).resolve().parents[2] / "examples" / "real_floor_calibration.py"))
    cs = ex["read_capture_set"](out / "set")
    wall = nm.SensorModel.load(out / "wall.model.json")
    near_fit, far_fit = ex["floor_scores"](cs, "f1-8_plane1", wall, frames=1)
    near_paper, _ = ex["floor_scores"](cs, "f1-8_plane1", nm.D435, frames=1)
    assert near_fit["cells"] > 1000 and abs(near_fit["mean_error_m"]) < 0.002
    assert 0.65 <= near_fit["coverage_1sigma"] <= 0.9 and near_fit["coverage_2sigma"] >= 0.95
    assert 0.7 < near_fit["median_sigma_m"] / near_fit["rmse_m"] < 1.5
    assert near_paper["coverage_1sigma"] > 0.99 and near_paper["median_sigma_m"] > 4 * near_paper["rmse_m"]
    assert far_fit["mean_error_m"] < -0.004 and far_fit["coverage_1sigma"] < 0.68
    with pytest.raises(ValueError, match="no capture"):
        ex["floor_scores"](cs, "nope", wall)
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match="frames"):
            ex["floor_scores"](cs, "f1-8_plane1", wall, frames=bad)


@pytest.mark.xfail(strict=True, reason="the white wall's disparity noise is larger than the concrete floor's at the same "
                                       "depth, which no sigma_d(theta) fitted on the wall alone can know (docs/"
                                       "noise-model.md, the disparity family on a real D435)")
def test_aims_slam_wall_model_predicts_the_floors_within_25_percent(aims_prediction):
    """The target: median measured / median predicted sigma_z within [0.8, 1.25] in every floor depth bin."""
    _, rows, _ = aims_prediction
    for f in AIMS_FLOORS:
        for b in rows[f]:
            assert 0.8 <= b["ratio"]["model"] <= 1.25, (f, b["z_range_m"], b["ratio"]["model"])
