"""elevmap compare: alternative noise models (hand-worked values), depth effects (their statistics), the
comparison's report, identical frames for every mapper, and bad arguments."""

import hashlib
import json
import math

import numpy as np
import pytest

import noise_model as nm
from conftest import random_pose_cov, random_transform
from elevmap import Mapper
from elevmap.cli import main
from elevmap.commands.compare import COMPARE_MAX_VARIANCE, MAPPERS, REPORT_KEYS, most_confident, run_compare
from elevmap.commands.compare_args import parse_effects, parse_reality, parse_settings
from noise_model.alternatives import anybotics_d435, constant, make_variance_model, quadratic
from noise_model.sim.effects import correlated_noise, depth_bias, gaussian_random_field, make_effect

# camera looking along map +x, level: camera x (right) = map -y, camera y (down) = map -z, z = map +x
R_LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
# camera looking straight down: camera x = map x, camera y = map -y, camera z = map -z
R_DOWN = np.diag([1.0, -1.0, -1.0])


def pose(R, t=(0.0, 0.0, 0.0)):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


# ---------------------------------------------------------------------------------------------
# alternative variance models
# ---------------------------------------------------------------------------------------------
def test_constant_and_quadratic_hand_worked():
    p = np.array([[0.0, 0.0, 1.0], [0.3, -0.2, 2.0], [1.0, 1.0, 3.0]])
    hv, hc = constant()(p, pose(R_LEVEL, (1, 2, 3)), None)
    np.testing.assert_allclose(hv, 0.0004)                        # (2 cm)^2
    np.testing.assert_allclose(hc, [[0.0004, 0.0, 0.0004]] * 3)
    hv, _ = constant(0.05)(p, np.eye(4), np.eye(6))                 # pose covariance ignored
    np.testing.assert_allclose(hv, 0.0025)
    # elevation_mapping_cupy: 0.05 z^2 with z the sensor-frame depth, whatever the pose
    hv, hc = quadratic()(p, pose(R_DOWN, (0, 0, 5)), None)
    np.testing.assert_allclose(hv, [0.05, 0.2, 0.45])
    np.testing.assert_allclose(hc[:, 0], hv)
    np.testing.assert_allclose(hc[:, 1], 0.0)
    hv, _ = quadratic(0.01)(p, pose(R_LEVEL), None)
    np.testing.assert_allclose(hv, [0.01, 0.04, 0.09])


def test_anybotics_d435_hand_worked():
    m = anybotics_d435()
    # straight down, depth 1 m: sigma_N = 0.000611 + 0.003587 * (1 - 0.3515)^2 = 0.00211954...
    sN = 0.000611 + 0.003587 * 0.6485 ** 2
    assert sN == pytest.approx(0.0021195, abs=1e-7)
    hv, hc = m(np.array([[0.0, 0.0, 1.0]]), pose(R_DOWN, (0, 0, 1)), None)
    assert hv[0] == pytest.approx(sN ** 2, rel=1e-12)
    # lateral 0.01576 m on both horizontal axes
    np.testing.assert_allclose(hc[0], [0.01576 ** 2, 0.0, 0.01576 ** 2], rtol=1e-12)
    # level camera, depth 2 m: the height is along camera y -> sigma_L^2 = (0.03152)^2 = 9.935e-4;
    # map x is the optical axis -> sigma_N(2)^2, sigma_N(2) = 0.000611 + 0.003587 * 1.6485^2 = 0.0103589
    hv, hc = m(np.array([[0.0, 0.0, 2.0]]), pose(R_LEVEL), None)
    assert hv[0] == pytest.approx(9.935104e-4, rel=1e-6)
    assert hc[0, 0] == pytest.approx(0.0103589 ** 2, rel=1e-4)
    assert hc[0, 2] == pytest.approx(9.935104e-4, rel=1e-6)
    assert hc[0, 1] == pytest.approx(0.0, abs=1e-15)
    # + rotation term: 0.01 rad (std) about map y, lever arm 2 m along map x -> + (0.02 m)^2 on the height
    P = np.zeros((6, 6))
    P[4, 4] = 1e-4
    P[0, 0] = 1.0                      # translation: left out, as ANYbotics does
    hv2, hc2 = m(np.array([[0.0, 0.0, 2.0]]), pose(R_LEVEL), P)
    assert hv2[0] - hv[0] == pytest.approx(4e-4, rel=1e-9)
    np.testing.assert_allclose(hc2, hc, atol=1e-15)                 # rot about y moves a point on x only in z


def test_anybotics_d435_matches_to_map_frame_convention(rng):
    """Sensor covariance rotated, plus the rotation block through the package's pose Jacobian."""
    T = random_transform(rng)
    p = rng.uniform([-1, -1, 0.3], [1, 1, 3.0], (20, 3))
    P = random_pose_cov(rng)
    z = p[:, 2]
    sN = 0.000611 + 0.003587 * (z - 0.3515) ** 2
    sL = 0.01576 * z
    cov_cam = np.zeros((20, 3, 3))
    cov_cam[:, 0, 0], cov_cam[:, 1, 1], cov_cam[:, 2, 2] = sL ** 2, sL ** 2, sN ** 2
    Prot = np.zeros((6, 6))
    Prot[3:, 3:] = P[3:, 3:]
    ref = nm.to_map_frame(cov_cam, p, T, Prot)
    hv, hc = anybotics_d435()(p, T, P)
    np.testing.assert_allclose(hv, ref[:, 2, 2], rtol=1e-10)
    np.testing.assert_allclose(hc, np.stack([ref[:, 0, 0], ref[:, 0, 1], ref[:, 1, 1]], 1), rtol=1e-9, atol=1e-18)


def test_variance_models_validate_inputs():
    with pytest.raises(ValueError, match="sigma_m"):
        constant(-1.0)
    with pytest.raises(ValueError, match="factor"):
        quadratic(float("nan"))
    with pytest.raises(ValueError, match="lateral_factor"):
        anybotics_d435(lateral_factor=0.0)
    with pytest.raises(ValueError, match="unknown variance model"):
        make_variance_model("gaussian")
    with pytest.raises(ValueError, match="no parameter"):
        make_variance_model("constant", sigma=0.1)
    m = quadratic()
    with pytest.raises(ValueError, match="points_cam"):
        m(np.zeros((3, 2)), np.eye(4), None)
    with pytest.raises(ValueError, match="z > 0"):
        m(np.array([[0.0, 0.0, -1.0]]), np.eye(4), None)
    with pytest.raises(ValueError, match="T_map_cam"):
        m(np.array([[0.0, 0.0, 1.0]]), np.eye(3), None)
    with pytest.raises(ValueError, match="pose_cov"):
        m(np.array([[0.0, 0.0, 1.0]]), np.eye(4), -np.eye(6))


# ---------------------------------------------------------------------------------------------
# effects
# ---------------------------------------------------------------------------------------------
def _plane(width=424, height=240, z0=1.0):
    return np.full((height, width), z0), np.zeros((height, width))


def _lag_corr(r, h, axis):
    """Correlation of (frames, H, W) residuals between pixels h apart along axis 1 (rows) or 2 (columns)."""
    a = r - r.mean()
    if axis == 2:
        return float(np.mean(a[:, :, h:] * a[:, :, :-h]) / np.mean(a * a))
    return float(np.mean(a[:, h:, :] * a[:, :-h, :]) / np.mean(a * a))


def test_correlated_noise_has_the_documented_std_and_correlation_length():
    K = nm.D435.intrinsics(424, 240)
    z_true, theta = _plane()
    rng = np.random.default_rng(7)
    eff = correlated_noise(sigma_m=0.01, length_px=3.0)
    res = np.stack([nm.add_noise(z_true, theta, rng, model=None, effects=[eff], context={"K": K}) * 0.001 - z_true
                    for _ in range(8)])
    assert res.std() == pytest.approx(0.01, rel=0.05)               # 1 mm quantisation adds 0.3 % variance
    for axis in (1, 2):
        assert _lag_corr(res, 3, axis) == pytest.approx(math.exp(-0.5), abs=0.05)
        assert _lag_corr(res, 6, axis) == pytest.approx(math.exp(-2.0), abs=0.05)
        # fitted correlation length from lags 1..6: rho(h) = exp(-h^2 / (2 l^2))
        hs = np.arange(1, 7)
        rho = np.array([_lag_corr(res, h, axis) for h in hs])
        ok = rho > 0.05
        ell = math.sqrt(np.sum(hs[ok] ** 4) / np.sum(hs[ok] ** 2 * -2.0 * np.log(rho[ok])))
        assert ell == pytest.approx(3.0, rel=0.1)
    # a fresh field every frame
    assert abs(np.corrcoef(res[0].ravel(), res[1].ravel())[0, 1]) < 0.05


def test_correlated_noise_proportional_to_sigma_z_and_its_field():
    z_true, theta = _plane(z0=2.0)
    theta[:] = np.radians(30.0)
    rng = np.random.default_rng(3)
    eff = correlated_noise(sigma_z_fraction=0.5, length_px=2.0)
    assert eff.params == {"sigma_z_fraction": 0.5, "length_px": 2.0}
    assert correlated_noise().params == {"sigma_z_fraction": 1.0, "length_px": 3.0}
    ctx = {"K": nm.D435.intrinsics(424, 240), "z_true": z_true}
    out = np.stack([eff(z_true.copy(), theta, rng, ctx) - z_true for _ in range(4)])
    assert out.std() == pytest.approx(0.5 * nm.axial_sigma(2.0, np.radians(30.0)), rel=0.05)
    # NaN (no data) stays NaN
    z = z_true.copy()
    z[:10] = np.nan
    assert np.isnan(eff(z, theta, rng, ctx)[:10]).all()
    g = gaussian_random_field((300, 300), 4.0, np.random.default_rng(1))
    assert g.shape == (300, 300) and g.std() == pytest.approx(1.0, rel=0.1)


def test_depth_bias_mean_error_equals_the_formula():
    K = nm.D435.intrinsics(424, 240)
    fb = K[0, 0] * 0.05
    rng = np.random.default_rng(5)
    for z0 in (0.8, 1.5, 3.0):
        z_true, theta = _plane(z0=z0)
        expected = 0.98 * fb / (fb / z0 + 0.1) - z0           # scale 0.98, offset 0.1 px
        eff = depth_bias(scale=0.98, offset_px=0.1)
        # without noise: exact up to the 1 mm quantisation
        d = nm.add_noise(z_true, theta, rng, model=None, effects=[eff], context={"K": K})
        assert abs(d * 0.001 - z_true - expected).max() <= 0.0005 + 1e-12
        # with the paper's noise: the mean error over the image
        d = nm.add_noise(z_true, theta, rng, effects=[eff], context={"K": K})
        err = d[d > 0] * 0.001 - z0
        assert err.mean() == pytest.approx(expected, abs=4 * err.std() / math.sqrt(err.size) + 3e-4)
    # first order: (scale - 1) z - z^2 offset / (f b)
    assert 0.98 * fb / (fb / 1.0 + 0.1) - 1.0 == pytest.approx(-0.02 - 0.1 / fb, rel=0.02)
    with pytest.raises(ValueError, match="context\\['K'\\]"):
        eff(z_true.copy(), theta, rng, {})


def test_effects_validate_and_reproduce_from_the_seed():
    with pytest.raises(ValueError, match="not both"):
        correlated_noise(sigma_m=0.01, sigma_z_fraction=1.0)
    with pytest.raises(ValueError, match="length_px"):
        correlated_noise(length_px=0)
    with pytest.raises(ValueError, match="scale"):
        depth_bias(scale=-1)
    with pytest.raises(ValueError, match="unknown effect"):
        make_effect("speckle")
    with pytest.raises(ValueError, match="no parameter"):
        make_effect("depth_bias", offset=1.0)
    z_true, theta = _plane(width=64, height=48)
    K = nm.D435.intrinsics(424, 240)
    a = nm.add_noise(z_true, theta, np.random.default_rng(1), effects=[correlated_noise()], context={"K": K})
    b = nm.add_noise(z_true, theta, np.random.default_rng(1), effects=[correlated_noise()], context={"K": K})
    np.testing.assert_array_equal(a, b)


def test_parse_effects():
    assert parse_effects(None) == [] and parse_effects("none") == []
    e = parse_effects("correlated_noise:length_px=5:sigma_z_fraction=0.5,depth_bias")
    assert [x.name for x in e] == ["correlated_noise", "depth_bias"]
    assert e[0].params == {"sigma_z_fraction": 0.5, "length_px": 5.0}
    e = parse_effects("correlated_noise:length_px=5,sigma_m=0.01,depth_bias:scale=1.01")
    assert e[0].params == {"sigma_m": 0.01, "length_px": 5.0} and e[1].params["scale"] == 1.01
    for bad, msg in (("fog", "unknown effect"), ("depth_bias:scale", "key=value"), ("scale=1", "no effect name"),
                     ("depth_bias:scale=abc", "not a number"), ("depth_bias,,", "empty")):
        with pytest.raises(ValueError, match=msg):
            parse_effects(bad)


# ---------------------------------------------------------------------------------------------
# the comparison
# ---------------------------------------------------------------------------------------------
def test_compare_cli_writes_the_report_table_and_recording(tmp_path, capsys):
    out, rrd = tmp_path / "report.json", tmp_path / "compare.rrd"
    names = ["paper", "disparity", "quadratic", "anybotics_d435", "constant", "paper_capped"]
    args = ["compare", "--scene", "stairs", "--frames", "3", "--sim-effects", "correlated_noise,depth_bias:scale=1.01",
            "--seed", "2", "--json", str(out), "--rrd", str(rrd), "--no-progress", "--mappers", ",".join(names)]
    assert main(args) == 0
    text = capsys.readouterr().out
    for name in names:
        assert name in text
    report = json.loads(out.read_text())
    assert report["scene"] == "stairs" and report["frames"] == 3 and report["seed"] == 2
    assert list(report["mappers"]) == names
    for name, m in report["mappers"].items():
        for k in REPORT_KEYS:
            assert k in m, (name, k)
            assert m[k] is None or isinstance(m[k], (int, float)), (name, k)
        assert 0 <= m["coverage_1sigma"] <= m["coverage_2sigma"] <= 1
        assert 0 < m["known_fraction"] <= 1 and m["ms_per_frame"] > 0 and m["mean_sigma_m"] > 0
        assert math.isfinite(m["nll"]) and m["rmse_m"] >= 0
        assert m["frames_digest"] == report["frames_digest"]
    assert report["mappers"]["paper_capped"]["model"]["max_points_per_frame"] == report["cap"]
    assert report["mappers"]["paper"]["model"]["max_points_per_frame"] is None
    assert [e["name"] for e in report["sim_effects"]] == ["correlated_noise", "depth_bias"]
    assert report["sim_effects"][1]["params"]["scale"] == 1.01
    assert report["common"]["cells"] > 0 and set(report["common"]["mappers"]) == set(names)
    # equal coverage: as many cells as the mapper that knows fewest
    assert report["matched"]["cells"] == min(m["known_cells"] for m in report["mappers"].values())
    assert set(report["matched"]["mappers"]) == set(names) and "matched:" in text
    assert report["map"]["fusion"]["max_variance"] == COMPARE_MAX_VARIANCE
    assert report["mappers"]["disparity"]["model"]["params"] == {"sigma_d_px": 0.08}
    # the edge band: known cells of some mapper in the band, each mapper's share of them
    assert report["edge_band_cells"] > 0
    for m in report["mappers"].values():
        assert 0 < m["edge_known_fraction"] <= 1 and m["edge_cells"] <= report["edge_band_cells"]
        assert 0 <= m["edge_coverage_1sigma"] <= m["edge_coverage_2sigma"] <= 1
    assert rrd.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["compare.rrd", "report.json"]
    assert report["frames_cached"] is False
    # no silent overwrite
    assert main(args) == 2
    assert "--overwrite" in capsys.readouterr().err


def test_every_mapper_gets_the_same_frames(monkeypatch):
    seen = {}
    orig = Mapper.integrate

    def spy(self, camera, depth, **kw):
        key = id(self)                                              # one Mapper per mapper of the comparison
        h = hashlib.sha256(np.ascontiguousarray(depth).tobytes())
        h.update(np.asarray(kw["T_map_cam"]).tobytes())
        seen.setdefault(key, []).append(h.hexdigest())
        return orig(self, camera, depth, **kw)

    monkeypatch.setattr(Mapper, "integrate", spy)
    fitted = nm.D435.with_coefficients((0.002, 0.001, 0.004, 0.02))
    report = run_compare("boxes", 2, seed=1, sim_effects="correlated_noise", show_progress=False,
                         fitted_model=fitted)
    assert list(report["mappers"]) == list(MAPPERS)
    assert len(seen) == len(MAPPERS)
    sequences = list(seen.values())
    assert all(s == sequences[0] for s in sequences) and len(sequences[0]) == 2
    assert len(set(sequences[0])) == 2                                 # two different frames
    assert {m["frames_digest"] for m in report["mappers"].values()} == {report["frames_digest"]}


def test_mapper_subset_and_the_cap(tmp_path):
    report = run_compare("slope", 2, mappers="paper,paper_capped", cap=2, show_progress=False)
    assert list(report["mappers"]) == ["paper", "paper_capped"]
    assert report["cap"] == 2.0
    assert report["mappers"]["paper_capped"]["model"]["max_points_per_frame"] == 2.0
    # undefined scores (NaN, e.g. no step edges in view) are written as null: strict JSON
    from elevmap.commands.compare import json_ready

    report["mappers"]["paper"]["edge_rmse_m"] = float("nan")
    text = json.dumps(json_ready(report), allow_nan=False)
    assert json.loads(text)["mappers"]["paper"]["edge_rmse_m"] is None


def test_most_confident_by_hand():
    v = np.array([[4.0, 1.0, 3.0],
                  [1.0, 9.0, 0.5]])
    known = np.array([[True, True, True],
                      [True, False, True]])
    assert most_confident(v, known, 0).sum() == 0
    # 0.5, then the two 1.0 in flat order; 9.0 is unknown and never chosen
    np.testing.assert_array_equal(most_confident(v, known, 2), [[False, True, False], [False, False, True]])
    np.testing.assert_array_equal(most_confident(v, known, 3), [[False, True, False], [True, False, True]])
    np.testing.assert_array_equal(most_confident(v, known, 5), known)
    with pytest.raises(ValueError, match="n must be"):
        most_confident(v, known, 6)
    with pytest.raises(ValueError, match="n must be an integer"):
        most_confident(v, known, 2.5)
    with pytest.raises(ValueError, match="differ in shape"):
        most_confident(v, known[:, :2], 1)
    with pytest.raises(ValueError, match="finite"):
        most_confident(np.where(known, np.nan, 1.0), known, 1)
    with pytest.raises(ValueError, match="boolean"):
        most_confident(v, known.astype(int), 1)


def test_matched_scores_are_each_mappers_most_confident_cells_and_the_ceiling_is_set():
    report = run_compare("stairs", 3, mappers="paper,quadratic", show_progress=False)
    known = {n: m["known_cells"] for n, m in report["mappers"].items()}
    n = report["matched"]["cells"]
    assert n == min(known.values()) > 0
    # the mapper that knows fewest cells is scored over all of them: its matched scores are its own
    fewest = min(known, key=known.get)
    own, matched = report["mappers"][fewest], report["matched"]["mappers"][fewest]
    for k in ("rmse_m", "p95_abs_m", "nll", "coverage_1sigma", "coverage_2sigma"):
        assert matched[k] == pytest.approx(own[k], rel=1e-12), k
    assert report["map"]["fusion"]["max_variance"] == COMPARE_MAX_VARIANCE
    from elevmap.map.fusion import FusionParams
    from elevmap.pipeline import MappingConfig

    own_ceiling = run_compare("stairs", 1, mappers="quadratic", max_variance=None, show_progress=False,
                              config=MappingConfig(fusion=FusionParams(max_variance=0.02)))
    assert own_ceiling["map"]["fusion"]["max_variance"] == 0.02
    # a ceiling the quadratic model's far points exceed leaves it fewer cells
    low = run_compare("stairs", 3, mappers="quadratic", max_variance=0.01, show_progress=False)
    assert low["mappers"]["quadratic"]["known_cells"] < known["quadratic"]
    for bad in (0.0, -1.0, float("inf"), "x"):
        with pytest.raises(ValueError, match="max_variance"):
            run_compare("stairs", 1, mappers="paper", max_variance=bad, show_progress=False)


@pytest.mark.parametrize("args, message", [
    (["--scene", "moon"], "unknown scene"),
    (["--sim-effects", "fog"], "unknown effect"),
    (["--sim-effects", "depth_bias:tilt=2"], "no parameter"),
    (["--mappers", "paper,gaussian"], "unknown mapper"),
    (["--cap", "0.5"], "cap"),
    (["--frames", "0"], "--frames"),
    (["--size", "100x100"], "no default intrinsics"),
    (["--max-variance", "-1"], "max_variance"),
])
def test_bad_arguments_exit_2_with_a_message(tmp_path, capsys, args, message):
    assert main(["compare", "--json", str(tmp_path / "r.json"), "--frames", "1", "--no-progress"] + args) == 2
    err = capsys.readouterr().err
    assert message in err and err.startswith("elevmap compare: error:")
    assert list(tmp_path.iterdir()) == []           # refused before any work: no report, no fitted model


def test_json_is_required_and_outputs_are_checked_first(tmp_path, capsys):
    assert main(["compare", "--frames", "1"]) == 2
    assert "--json" in capsys.readouterr().err
    args = ["compare", "--frames", "1", "--json", str(tmp_path / "r.json"), "--no-progress"]
    assert main(args + ["--rrd", str(tmp_path / "no" / "such" / "c.rrd")]) == 2
    assert "folder does not exist" in capsys.readouterr().err
    assert main(args + ["--rrd", str(tmp_path / "r.json")]) == 2
    assert "different files" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_sim_effects_from_a_gap_report(tmp_path):
    # the effects a gap diagnosis selected, with their fitted parameters, drive the walk simulator
    report = {"format": "d435-gap/1", "effects": [
        {"name": "invalid_band", "params": {"margin_px": 3.0}},
        {"name": "depth_bias", "params": {"scale": 0.995, "offset_px": 0.02}}]}
    path = tmp_path / "gap.json"
    path.write_text(json.dumps(report))
    effects = parse_effects(str(path))
    assert [e.name for e in effects] == ["depth_bias", "invalid_band"]          # the simulator's order
    assert effects[0].params["scale"] == 0.995 and effects[1].params["margin_px"] == 3.0
    out = tmp_path / "r.json"
    assert main(["compare", "--scene", "boxes", "--frames", "3", "--mappers", "paper", "--sim-effects", str(path),
                 "--json", str(out), "--no-progress"]) == 0
    r = json.loads(out.read_text())
    assert [e["name"] for e in r["sim_effects"]] == ["depth_bias", "invalid_band"]
    with pytest.raises(ValueError, match="gap report"):
        parse_effects(str(tmp_path / "missing.json"))


def test_reality_a_gap_report_is_the_reference_plus_its_effects(tmp_path):
    report = {"format": "d435-gap/1", "effects": [{"name": "depth_bias", "params": {"scale": 0.99, "offset_px": 0.0}}]}
    path = tmp_path / "gap.json"
    path.write_text(json.dumps(report))
    r = parse_reality(str(path))
    assert r["kind"] == "gap" and r["sensor"] == "reference" and r["gap_report"] == str(path)
    assert [e.name for e in r["effects"]] == ["depth_bias"] and len(r["effects_digest"]) == 64
    assert parse_reality("stereo")["effects"] == [] and parse_reality("reference")["effects_digest"] is None
    # the same walk as --sim-effects GAP.json, frame for frame
    a = run_compare("boxes", 2, mappers="paper", reality=str(path), show_progress=False)
    b = run_compare("boxes", 2, mappers="paper", sim_effects=str(path), show_progress=False)
    assert a["frames_digest"] == b["frames_digest"] and a["reality"] == "gap" and b["reality"] == "reference"
    for bad, kw, msg in (("moon", {}, "unknown reality"), ("stereo", {"sim_effects": "depth_bias"}, "no sim effects"),
                         (str(path), {"sim_effects": "depth_bias"}, "not both"),
                         (str(tmp_path / "none.json"), {}, "gap report")):
        with pytest.raises(ValueError, match=msg):
            parse_reality(bad, **kw)
    with pytest.raises(ValueError, match="fitted mapper"):
        run_compare("boxes", 1, mappers="fitted", show_progress=False)


def test_the_work_folder_caches_the_walk_and_the_fitted_model(tmp_path):
    """The second run reads the frames from the cache, identical; the fitted model is characterised once on
    the paper's grid simulated with the reality (two frames per capture here) and read back."""
    from elevmap.commands.compare_work import WorkDir

    work = WorkDir(tmp_path / "work")
    first = run_compare("stairs", 2, mappers="paper", show_progress=False, work_dir=work)
    again = run_compare("stairs", 2, mappers="paper", show_progress=False, work_dir=work)
    assert not first["frames_cached"] and again["frames_cached"]
    assert again["frames_digest"] == first["frames_digest"]
    assert again["mappers"]["paper"]["rmse_m"] == first["mappers"]["paper"]["rmse_m"]
    other = run_compare("stairs", 2, seed=1, mappers="paper", show_progress=False, work_dir=work)
    assert not other["frames_cached"] and other["frames_digest"] != first["frames_digest"]
    model, info = work.fitted_model("reference", sensor="reference", n_frames=2)
    assert not info["cached"] and model.family in ("paper", "disparity")
    model2, info2 = work.fitted_model("reference", sensor="reference", n_frames=2)
    assert info2["cached"] and model2 == model
    # a model fitted on the reference simulation of the paper's model is near the paper's at 1 m, head-on
    assert nm.axial_sigma(1.0, 0.0, model.with_focal(300.0) if model.family == "disparity" else model) == \
        pytest.approx(nm.axial_sigma(1.0, 0.0), rel=0.3)
    with pytest.raises(ValueError, match="is a file"):
        WorkDir(tmp_path / "work" / "frames" / next(p.name for p in (tmp_path / "work" / "frames").iterdir()))


def test_settings_switch_fusion_rules_off_for_every_mapper():
    assert parse_settings(None) == {} and parse_settings("") == {}
    s = parse_settings("spread_alpha=none,neighbour_radius=0,visibility_cleanup=false,min_variance=4e-6,"
                       "bin_at_plane=false,neighbour_estimator=dersimonian_laird")
    assert s == {"spread_alpha": None, "neighbour_radius": 0, "visibility_cleanup": False, "min_variance": 4e-6,
                 "bin_at_plane": False, "neighbour_estimator": "dersimonian_laird"}
    assert isinstance(s["neighbour_radius"], int)
    r = run_compare("stairs", 2, mappers="paper,quadratic", show_progress=False,
                    settings="neighbour_radius=0,visibility_cleanup=false")
    assert r["map"]["fusion"]["neighbour_radius"] == 0 and r["map"]["visibility_cleanup"] is False
    assert r["settings"] == {"neighbour_radius": 0, "visibility_cleanup": False}
    # binning at the measured depth moves points: another map from the same frames
    b = run_compare("stairs", 2, mappers="paper", show_progress=False, settings="bin_at_plane=false")
    assert b["frames_digest"] == r["frames_digest"] and b["settings"] == {"bin_at_plane": False}
    assert b["mappers"]["paper"]["rmse_m"] != run_compare("stairs", 2, mappers="paper",
                                                           show_progress=False)["mappers"]["paper"]["rmse_m"]
    for bad, msg in (("gate=3", "unknown setting"), ("neighbour_radius", "KEY=VALUE"),
                     ("visibility_cleanup=yes", "true or false"), ("min_points=x", "not a number")):
        with pytest.raises(ValueError, match=msg):
            parse_settings(bad)
    with pytest.raises(ValueError, match="neighbour_radius"):
        run_compare("stairs", 1, mappers="paper", show_progress=False, settings="neighbour_radius=-1")


def test_valid_margin_setting_reaches_every_camera():
    s = parse_settings("valid_margin_px=8")
    assert s == {"valid_margin_px": 8} and isinstance(s["valid_margin_px"], int)
    a = run_compare("stairs", 1, mappers="paper", show_progress=False, settings="valid_margin_px=0")
    b = run_compare("stairs", 1, mappers="paper", show_progress=False, settings="valid_margin_px=8")
    assert b["settings"] == {"valid_margin_px": 8} and b["frames_digest"] == a["frames_digest"]
    # 16 of 424 columns and the left invalid band's rim dropped: fewer cells known
    assert b["mappers"]["paper"]["known_cells"] < a["mappers"]["paper"]["known_cells"]
    with pytest.raises(ValueError, match="valid_margin_px"):
        run_compare("stairs", 1, mappers="paper", show_progress=False, settings="valid_margin_px=17")


def test_edge_profile_by_hand():
    from elevmap.commands.compare import edge_profile

    truth = np.zeros((1, 20))
    truth[0, 10:] = 0.3                              # a step between columns 9 and 10: band = columns 7..12
    h = truth.copy()
    h[0, 9] = 0.3                                    # the upper level bled one cell over the edge
    h[0, 0] = 0.5                                    # a flying pixel 7 cells from the band
    h[0, 19] = np.nan                                # unknown
    v = np.full((1, 20), 0.01 ** 2)
    rings = edge_profile(h, v, truth)
    assert [r["rings"] for r in rings] == [[0, 0], [1, 3], [4, 8], [9, None]]
    assert [r["cells"] for r in rings] == [6, 6, 7, 0]         # 19 known: band 7..12, rings 4..6 and 13..15, rest
    assert rings[0]["mean_error_m"] == pytest.approx(0.3 / 6) and rings[0]["large_errors"] == 1
    assert rings[0]["coverage_2sigma"] == pytest.approx(5 / 6)
    assert rings[2]["rmse_m"] == pytest.approx(np.sqrt(0.25 / 7)) and rings[2]["large_errors"] == 1
    nll0 = 0.5 * np.log(2 * np.pi * 1e-4)
    assert rings[1]["nll_sum"] == pytest.approx(6 * nll0) and math.isnan(rings[3]["rmse_m"])


def test_floor_profile_by_hand():
    from elevmap.commands.compare import edge_profile, floor_profile

    truth = np.zeros((1, 6))
    h = np.array([[0.0005, 0.0015, 0.003, 0.01, np.nan, 0.0]])
    v = np.array([[1e-6, 1.05e-6, 1e-6, 4e-4, 1e-6, 2e-6]])       # cells 0-2 at the floor (1 mm)^2, 3 and 5 not
    fl = floor_profile(h, v, truth, 1e-6)
    assert fl["cells"] == 3 and fl["fraction"] == pytest.approx(3 / 5)
    assert fl["coverage_1sigma"] == pytest.approx(1 / 3) and fl["coverage_2sigma"] == pytest.approx(2 / 3)
    assert fl["rmse_m"] == pytest.approx(np.sqrt((0.0005 ** 2 + 0.0015 ** 2 + 0.003 ** 2) / 3))
    assert floor_profile(h, v, truth, 1e-9)["cells"] == 0 and math.isnan(floor_profile(h, v, truth, 1e-9)["rmse_m"])
    assert edge_profile(h, v, truth)[3]["coverage_1sigma"] == pytest.approx(3 / 5)   # no step: all in the last ring


def test_a_cell_centred_on_a_steps_edge_is_scored_against_the_upper_side():
    from elevmap.commands.compare import closed_truth
    from elevmap.sources.simulated import SimulatedWalk

    # a landing whose closed footprint ends at x = 4.74 m, tested as a box is: |x - centre| <= half size
    centre_x = 1.5 + 6 * 0.29 + 0.5 * 1.5
    assert abs(4.74 - centre_x) > 0.75               # rounding puts the cell centre 4.74 just outside

    def step(xy):
        return np.where(np.abs(xy[:, 0] - centre_x) <= 0.75, 1.02, 0.0)

    xy = np.array([[4.74, 0.0], [4.70, 0.0], [4.78, 0.0], [4.74 + 2e-9, 0.0]])
    assert step(xy).tolist() == [0.0, 1.02, 0.0, 0.0]
    assert closed_truth(step)(xy).tolist() == [1.02, 1.02, 0.0, 0.0]
    # a corner missed in x and y alike, and NaN only where every sample is NaN
    corner = lambda xy: np.where((xy[:, 0] <= 1.0 - 1e-12) & (xy[:, 1] <= 1.0 - 1e-12), 0.3, np.nan)
    assert closed_truth(corner)(np.array([[1.0, 1.0], [0.5, 0.5]])).tolist() == [0.3, 0.3]
    assert np.isnan(closed_truth(corner)(np.array([[1.1, 1.0]]))[0])
    # the default stairs walk: the landing's far edge lies on a column of cell centres
    walk = SimulatedWalk("stairs", n_frames=1)
    xy = np.array([[4.74, 0.0], [4.74, 0.6], [4.74, 0.62], [1.5, 0.0], [2.66, 0.3], [7.0, 1.0]])
    assert walk.truth_height(xy)[0] == 0.0
    np.testing.assert_allclose(closed_truth(walk.truth_height)(xy), [1.02, 1.02, 0.0, 0.17, 0.85, 0.0], atol=1e-12)
    with pytest.raises(ValueError, match="tol_m"):
        closed_truth(step, tol_m=0.01)
    with pytest.raises(ValueError, match="callable"):
        closed_truth(3.0)


def test_seed_summary_and_criteria_by_hand():
    from elevmap.commands.compare_seeds import SUMMARY_KEYS, criteria, format_seeds_table, summarise

    def run(a_rmse, a_nll, a_c1, a_c2, b_rmse, b_nll):
        base = {k: 0.5 for k in SUMMARY_KEYS}
        return {"mappers": {"a": {**base, "rmse_m": a_rmse, "nll": a_nll, "coverage_1sigma": a_c1,
                                  "coverage_2sigma": a_c2, "edge_rmse_m": None},
                            "b": {**base, "rmse_m": b_rmse, "nll": b_nll, "coverage_1sigma": 0.9,
                                  "coverage_2sigma": 0.99, "edge_rmse_m": None}}}

    runs = [run(0.030, -2.0, 0.70, 0.95, 0.029, -1.0), run(0.020, -3.0, 0.60, 0.90, 0.020, -1.5),
            run(0.050, -1.0, 0.72, 0.96, 0.040, -2.5)]
    s = summarise(runs)
    assert s["a"]["rmse_m"]["median"] == 0.030 and s["a"]["rmse_m"]["min"] == 0.020 and s["a"]["rmse_m"]["max"] == 0.05
    assert s["a"]["coverage_2sigma"]["median"] == 0.95 and s["a"]["nll"]["values"] == [-2.0, -3.0, -1.0]
    assert math.isnan(s["a"]["edge_rmse_m"]["median"])               # no step edges in any walk
    c = criteria(s)
    # a: median RMSE 30 mm against b's 29 mm (+3.4 %), NLL -2.0 < -1.5, coverages in their bands
    assert c["a"]["all"] and c["a"]["rmse_vs_best"] == pytest.approx(0.030 / 0.029 - 1)
    assert not c["b"]["coverage_2sigma"] and not c["b"]["lowest_nll"] and c["b"]["rmse_within_5pct"]
    slow = summarise([run(0.031, -2.0, 0.70, 0.95, 0.029, -1.0)])
    assert not criteria(slow)["a"]["rmse_within_5pct"]                # +6.9 %
    table = format_seeds_table({"scene": "stairs", "seeds": [0, 1, 2], "frames": [113] * 3, "width": 424,
                                "height": 240, "reality": "stereo", "preset": "default", "summary": s, "criteria": c})
    assert "30.0 [20.0, 50.0]" in table and "all met" in table
    assert "coverage_2sigma, coverage_1sigma, lowest_nll missed" in table



def test_seed_summary_of_the_rmse_on_the_cells_every_mapper_knows():
    """The summary takes common_rmse_m from each run's common scores; its criterion is reported beside the
    verdict, which stays the one on each mapper's own cells."""
    from elevmap.commands.compare_seeds import SUMMARY_KEYS, criteria, format_seeds_table, summarise

    def run(own_a, own_b, common_a, common_b):
        base = {k: 0.5 for k in SUMMARY_KEYS if k != "common_rmse_m"}
        return {"mappers": {"a": {**base, "rmse_m": own_a, "nll": -2.0, "coverage_1sigma": 0.70,
                                  "coverage_2sigma": 0.95},
                            "b": {**base, "rmse_m": own_b, "nll": -1.0, "coverage_1sigma": 0.70,
                                  "coverage_2sigma": 0.95}},
                "common": {"cells": 10, "mappers": {"a": {"rmse_m": common_a}, "b": {"rmse_m": common_b}}}}

    # a knows fewer, harder cells: +10 % on its own cells, +4 % on the cells both know
    runs = [run(0.055, 0.050, 0.052, 0.050), run(0.044, 0.040, 0.0416, 0.040), run(0.066, 0.060, 0.0624, 0.060)]
    s = summarise(runs)
    assert s["a"]["common_rmse_m"]["values"] == [0.052, 0.0416, 0.0624]
    assert s["a"]["common_rmse_m"]["median"] == 0.052
    c = criteria(s)
    assert not c["a"]["rmse_within_5pct"] and c["a"]["rmse_vs_best"] == pytest.approx(0.1)
    assert c["a"]["common_rmse_within_5pct"] and c["a"]["common_rmse_vs_best"] == pytest.approx(0.04)
    assert not c["a"]["all"]                                            # the verdict is on the own cells
    assert c["b"]["common_rmse_vs_best"] == 0.0
    table = format_seeds_table({"scene": "stairs", "seeds": [0, 1, 2], "frames": [113] * 3, "width": 424,
                                "height": 240, "reality": "stereo", "preset": "default", "summary": s, "criteria": c})
    assert "52.0 [41.6, 62.4]" in table and "rmse_within_5pct missed" in table
    # a run without common scores (a single mapper knows no cells in common with none): NaN, no criterion met
    lone = summarise([{"mappers": {"a": {k: 0.5 for k in SUMMARY_KEYS if k != "common_rmse_m"}}}])
    assert math.isnan(lone["a"]["common_rmse_m"]["median"])
    assert not criteria(lone)["a"]["common_rmse_within_5pct"]

def test_confidently_wrong_cells_by_hand():
    from elevmap.commands.compare_scores import confident_errors

    truth = np.zeros((1, 6))
    # a phantom foothold (1 m off, sigma 2 mm); 0.2 m off but a sigma of 0.1 m (it warned); 0.05 m off at
    # sigma 1 mm (wrong, but not by a step); 0.15 m off at sigma 3 cm (5 sigma); unknown; exact
    h = np.array([[1.0, 0.2, 0.05, -0.15, np.nan, 0.0]])
    v = np.array([[0.002 ** 2, 0.1 ** 2, 0.001 ** 2, 0.03 ** 2, 1e-6, 1e-6]])
    assert confident_errors(h, v, truth) == 2
    assert confident_errors(h, v, np.full((1, 6), np.nan)) == 0             # no truth, nothing counted
    with pytest.raises(ValueError, match="one shape"):
        confident_errors(h, v[:, :5], truth)


def test_seeds_run_each_seed_and_the_cli(tmp_path, capsys):
    out = tmp_path / "r.json"
    assert main(["compare", "--scene", "boxes", "--frames", "2", "--seeds", "2", "--seed", "3", "--mappers",
                 "paper,constant", "--json", str(out), "--no-progress"]) == 0
    r = json.loads(out.read_text())
    assert r["seeds"] == [3, 4] and [x["seed"] for x in r["runs"]] == [3, 4]
    assert r["runs"][0]["frames_digest"] != r["runs"][1]["frames_digest"]
    vals = [x["mappers"]["paper"]["rmse_m"] for x in r["runs"]]
    assert r["summary"]["paper"]["rmse_m"]["median"] == pytest.approx(np.median(vals))
    assert set(r["criteria"]) == {"paper", "constant"}
    wrong = [x["mappers"]["paper"]["confident_errors"] for x in r["runs"]]
    assert all(isinstance(w, int) and w >= 0 for w in wrong)
    assert r["summary"]["paper"]["confident_errors"]["max"] == max(wrong)
    out_text = capsys.readouterr().out
    assert "medians over the seeds" in out_text and "wrong: known cells off by more than 0.1 m and 4 sigma" in out_text
    assert main(["compare", "--frames", "1", "--seeds", "0", "--json", str(tmp_path / "x.json"),
                 "--no-progress"]) == 2
    assert main(["compare", "--frames", "1", "--seeds", "2", "--rrd", str(tmp_path / "x.rrd"), "--json",
                 str(tmp_path / "x.json"), "--no-progress"]) == 2


# ---------------------------------------------------------------------------------------------
# the calibration must-show on the default walks (seed 0, 60 frames, 424x240; docs/calibration.md)
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("scene", ["stairs", "boxes"])
def test_with_reality_equal_to_the_model_the_paper_mapper_is_calibrated_and_best(scene):
    """Reality = the paper's model: the paper mapper's 2-sigma coverage in [0.93, 0.97], 1-sigma in
    [0.64, 0.73], the lowest mean NLL of all mappers, and an RMSE within 5 % of the best other's."""
    r = run_compare(scene, 60, show_progress=False,
                    mappers="paper,disparity,quadratic,anybotics_d435,constant,paper_capped")["mappers"]
    paper = r["paper"]
    assert 0.93 <= paper["coverage_2sigma"] <= 0.97
    assert 0.64 <= paper["coverage_1sigma"] <= 0.73
    others = [m for name, m in r.items() if name != "paper"]
    assert paper["nll"] < min(m["nll"] for m in others)
    assert paper["rmse_m"] <= 1.05 * min(m["rmse_m"] for m in others)


@pytest.mark.parametrize("scene", ["stairs", "boxes"])
def test_correlated_noise_costs_calibration_and_the_cap_keeps_two_sigma(scene):
    """Spatially correlated noise in the simulated reality: the paper mapper loses accuracy and
    likelihood against the model's own reality, and paper_capped keeps 2-sigma coverage >= 0.90."""
    plain = run_compare(scene, 60, show_progress=False, mappers=["paper", "paper_capped"])["mappers"]
    corr = run_compare(scene, 60, show_progress=False, mappers=["paper", "paper_capped"],
                       sim_effects="correlated_noise")["mappers"]
    assert corr["paper"]["rmse_m"] > 1.2 * plain["paper"]["rmse_m"]
    assert corr["paper"]["nll"] > plain["paper"]["nll"] + 0.5
    assert corr["paper_capped"]["coverage_2sigma"] >= 0.90
