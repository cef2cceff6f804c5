"""The physical D435 wired into the simulator: materials by primitive, capture sets, walks, the sim source,
compare, the validation command and the bench; seeded frames; bad input named."""

import json

import numpy as np
import pytest

from elevmap.cli import main
from noise_model import D435
from noise_model.sim import (
    HIT_GROUND, HIT_NONE, Box, CaptureGeometry, Scene, Target, render_depth, simulate_target_stereo, simulate_walk,
)
from noise_model.sim.stereo import materials as MT
from noise_model.sim.stereo.pipeline import StereoD435
from noise_model.sim.stereo.projector import DotPattern, Projector
from noise_model.sim.targets import camera_extrinsics

T_CAM = camera_extrinsics((0.0, 0.0, 1.0), pitch_down_deg=0.0)     # looking along map +x, 1 m up
K424 = D435.intrinsics(424, 240)


def wall(z, material=None):
    return Scene([Target(centre=(z, 0.0, 1.0), width=8 * z + 2, height=6 * z + 2, material=material)], ground_z=None)


@pytest.fixture(scope="module")
def cam():
    return StereoD435(424, 240)


def board_geometry(distance=1.0, yaw=30.0, pitch=0.0, background=3.0, kind="board"):
    target = {"kind": kind, "distance_m": distance, "yaw_deg": yaw, "pitch_deg": pitch}
    if kind == "board":
        target.update(width_m=0.6, height_m=0.9)
    return CaptureGeometry("c", K424, 424, 240, 0.001, 0.05, target, background)


# ---------------------------------------------------------------------------------------------
# materials by primitive
# ---------------------------------------------------------------------------------------------
def test_material_map_by_primitive_matches_its_reference(rng):
    scene = Scene([Box((2.0, 0.0, 0.5), (1.0, 1.0, 1.0), material=0.1), Box((3.0, 1.0, 0.5), (1.0, 1.0, 1.0)),
                   Target((4.0, 0.0, 1.0), material=MT.carpet())], ground_z=0.0, ground_material=MT.concrete(3))
    mmap = MT.MaterialMap(default=MT.white_wall(), ground=MT.concrete(),
                          regions=(((2.5, 0.5, 0.0), (3.5, 1.5, 1.0), MT.Uniform(0.6, "crate")),))
    n = 4000
    p = rng.uniform([-1, -2, -0.1], [5, 2, 1.5], (n, 3))
    p[rng.random(n) < 0.3, 2] = 0.0                                  # on the ground plane
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    idx = rng.integers(HIT_NONE, 3, n).astype(np.int32)
    p[idx == HIT_NONE] = np.nan
    got = mmap.evaluate(p, nrm, index=idx, scene=scene)
    ref = mmap.evaluate_reference(p, nrm, index=idx, scene=scene)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    assert np.all(got[idx == 0] == 0.1)                              # the box's own albedo wins over the map
    c = MT.carpet().evaluate_reference(p[idx == 2], nrm[idx == 2])
    np.testing.assert_allclose(got[idx == 2], c, atol=1e-12)
    g = (idx == HIT_GROUND)
    np.testing.assert_allclose(got[g], MT.concrete(3).evaluate_reference(p[g], nrm[g]), atol=1e-12)
    # the primitive without a material falls back to the map's rules: region, ground, default
    one = idx == 1
    expect = mmap.evaluate_reference(p[one], nrm[one])
    np.testing.assert_allclose(got[one], expect, atol=1e-12)
    # a scene without materials: the index changes nothing
    plain = Scene([Box((2.0, 0.0, 0.5), (1.0, 1.0, 1.0))] * 3)
    np.testing.assert_array_equal(mmap.evaluate(p, nrm, index=idx, scene=plain), mmap.evaluate(p, nrm))
    with pytest.raises(ValueError, match="together"):
        mmap.evaluate(p, nrm, index=idx)
    with pytest.raises(ValueError, match="index must lie in"):
        mmap.evaluate(p, nrm, index=np.full(n, 7, np.int32), scene=scene)


def test_a_primitives_material_reaches_the_infrared_images(cam):
    default = cam.render(wall(1.0), T_CAM)
    explicit = cam.render(wall(1.0, material=MT.white_wall()), T_CAM)     # the map's default, named
    np.testing.assert_array_equal(default.projector_left, explicit.projector_left)
    dark = cam.render(wall(1.0, material=0.2), T_CAM)
    ratio = np.median(dark.projector_left[:, 100:300]) / np.median(default.projector_left[:, 100:300])
    assert ratio == pytest.approx(0.2 / 0.8, rel=1e-6)                    # radiance = albedo x irradiance
    # a dark box on a white wall: darker where the box is, the wall unchanged around it
    scene = wall(1.5).with_primitives(Box((1.2, 0.0, 1.0), (0.2, 0.4, 0.4), material=0.05))
    ir = cam.render(scene, T_CAM, with_truth=True)
    _, _, idx = render_depth(scene, cam.K, 424, 240, T_CAM, return_index=True)
    on_box = idx == 1
    assert on_box.sum() > 500
    assert np.median(ir.rate_left[on_box]) < 0.2 * np.median(ir.rate_left[~on_box])


# ---------------------------------------------------------------------------------------------
# capture sets
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("geometry", [
    dict(distance=1.2, yaw=30.0, background=3.0), dict(distance=0.8, yaw=-45.0, pitch=20.0, background=None),
    dict(kind="wall", distance=1.5, yaw=75.0, background=None), dict(kind="wall", distance=1.0, yaw=10.0, pitch=-30.0,
                                                                    background=None)])
def test_a_capture_as_a_scene_renders_as_the_capture(geometry):
    g = board_geometry(**geometry)
    scene, T = g.scene(max_range_m=10.0)
    z, th = render_depth(scene, K424, 424, 240, T, max_range_m=10.0)
    z0, th0 = g.render()
    seen = np.isfinite(z0) & (z0 <= 10.0)
    np.testing.assert_array_equal(np.isfinite(z), seen)
    np.testing.assert_allclose(z[seen], z0[seen], atol=1e-9)
    np.testing.assert_allclose(th[seen], th0[seen], atol=1e-9)


def test_capture_frames_of_the_physical_d435_are_seeded(cam):
    g = board_geometry(1.0, 20.0, 0.0, 3.0)
    a = simulate_target_stereo(g, 2, np.random.default_rng(5), camera=cam)
    b = simulate_target_stereo(g, 2, np.random.default_rng(5), camera=cam)
    assert a.shape == (2, 240, 424) and a.dtype == np.uint16
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a[0], a[1])                           # fresh noise each frame
    centre = a[:, 110:130, 200:224].astype(float)                   # the middle of the board, 1 m away
    assert np.median(centre[centre > 0]) == pytest.approx(1000, abs=15)
    far = a[0, 5:40, 300:420].astype(float)                         # the wall behind, at 3 m
    assert np.median(far[far > 0]) == pytest.approx(3000, rel=0.03)


def test_capture_set_with_the_physical_sensor(tmp_path, cam):
    from elevmap.commands.simulate import simulate_capture_set
    from elevmap.sources.captures import read_capture_set

    out = tmp_path / "caps"
    simulate_capture_set(out, [(1.0, 0.0)], n_frames=2, seed=4, show_progress=False, sensor="stereo")
    cs = read_capture_set(out)
    d = cs.load_depth("board_z1.00_y00")
    assert d.shape == (2, 240, 424) and d.dtype == np.uint16
    doc = json.loads((out / "captures.json").read_text())
    assert "physical" in doc["camera"]["model"] and doc["simulation"]["sensor"] == "stereo"
    again = tmp_path / "again"
    simulate_capture_set(again, [(1.0, 0.0)], n_frames=2, seed=4, show_progress=False, sensor="stereo")
    np.testing.assert_array_equal(read_capture_set(again).load_depth("board_z1.00_y00"), d)
    with pytest.raises(ValueError, match="unknown sensor"):
        simulate_capture_set(tmp_path / "x", [(1.0, 0.0)], n_frames=1, show_progress=False, sensor="lidar")
    with pytest.raises(ValueError, match="not a D435 depth mode"):
        simulate_capture_set(tmp_path / "y", [(1.0, 0.0)], n_frames=1, width=320, height=200, show_progress=False,
                             sensor="stereo")
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


# ---------------------------------------------------------------------------------------------
# walks, the sim source, compare
# ---------------------------------------------------------------------------------------------
def test_a_walk_seen_by_the_physical_d435_is_seeded():
    scene = Scene.stairs_scene()

    def frames(seed, **kw):
        return list(simulate_walk(scene, K424, 424, 240, n_frames=2, rng=np.random.default_rng(seed), **kw))

    a, b = frames(1, sensor="stereo"), frames(1, sensor="stereo")
    ref = frames(1)
    for fa, fb, fr in zip(a, b, ref):
        np.testing.assert_array_equal(fa["depth"], fb["depth"])
        np.testing.assert_array_equal(fa["T_map_cam"], fr["T_map_cam"])          # the same walk
        assert fa["depth"].dtype == np.uint16 and not np.array_equal(fa["depth"], fr["depth"])
        z = fa["depth"][fa["depth"] > 0]
        assert (fa["depth"] > 0).mean() > 0.5 and z.min() * 1e-3 >= D435.intrinsics(424, 240)[0, 0] * 0.05 / 126
    assert not np.array_equal(a[0]["depth"], frames(2, sensor="stereo")[0]["depth"])
    with pytest.raises(ValueError, match="makes its own noise"):
        frames(1, sensor="stereo", noise="none")
    with pytest.raises(ValueError, match="sensor must be"):
        frames(1, sensor="lidar")
    with pytest.raises(ValueError, match="must have the walk's size"):
        frames(1, sensor=StereoD435(848, 480))


def test_the_sim_source_takes_the_sensor_in_its_string():
    from elevmap.sources.open import SOURCE_HELP, open_source

    assert "sim:SCENE?sensor=stereo" in SOURCE_HELP
    src = open_source("sim:slope?sensor=stereo&preset=high_accuracy", frames=1, seed=3)
    assert src.sensor == "stereo" and src.preset == "high_accuracy"
    f = next(iter(src))
    assert f.depth.dtype == np.uint16 and f.depth.shape == (240, 424)
    again = next(iter(open_source("sim:slope?sensor=stereo&preset=high_accuracy", frames=1, seed=3)))
    np.testing.assert_array_equal(f.depth, again.depth)
    assert open_source("sim:slope", frames=1).sensor == "reference"
    for spec, message in [("sim:slope?sensor=sonar", "unknown sensor"), ("sim:slope?colour=red", "unknown option"),
                          ("sim:slope?sensor", "KEY=VALUE"), ("sim:slope?preset=default", "option of sensor=stereo"),
                          ("sim:slope?sensor=stereo&preset=ultra", "unknown matcher preset"),
                          ("sim:slope?sensor=stereo&sensor=stereo", "given twice")]:
        with pytest.raises(ValueError, match=message):
            open_source(spec, frames=1)


def test_compare_with_the_physical_d435_as_reality(tmp_path, capsys):
    from elevmap.commands.compare import run_compare

    r = run_compare("slope", 2, mappers="paper", reality="stereo", show_progress=False)
    assert r["reality"] == "stereo" and r["preset"] == "default" and r["frames"] == 2
    assert r["mappers"]["paper"]["known_fraction"] > 0
    assert run_compare("slope", 1, mappers="paper", show_progress=False)["reality"] == "reference"
    with pytest.raises(ValueError, match="takes no sim effects"):
        run_compare("slope", 1, mappers="paper", reality="stereo", sim_effects="depth_bias", show_progress=False)
    args = ["compare", "--frames", "1", "--json", str(tmp_path / "r.json"), "--no-progress", "--mappers", "paper"]
    assert main(args + ["--reality", "stereo", "--sim-effects", "depth_bias"]) == 2
    assert "takes no sim effects" in capsys.readouterr().err
    assert main(args + ["--preset", "high_accuracy"]) == 2
    assert "--preset goes with --reality stereo" in capsys.readouterr().err
    assert not (tmp_path / "r.json").exists()


# ---------------------------------------------------------------------------------------------
# the command line: simulate --sensor stereo, --validate, bench
# ---------------------------------------------------------------------------------------------
def test_simulate_command_with_the_physical_sensor(tmp_path, capsys):
    assert main(["simulate", "--grid", "paper", "--sensor", "stereo", "--size", "320x200", "--frames", "1",
                 "--out", str(tmp_path / "c"), "--no-progress"]) == 2
    assert "not a D435 depth mode" in capsys.readouterr().err
    assert main(["simulate", "--grid", "paper", "--preset", "high_accuracy", "--out", str(tmp_path / "c")]) == 2
    assert "--preset goes with --sensor stereo" in capsys.readouterr().err
    assert main(["simulate", "--grid", "paper", "--sensor", "stereo", "--preset", "ultra", "--frames", "1",
                 "--out", str(tmp_path / "c"), "--no-progress"]) == 2
    assert "unknown matcher preset" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()
    rrd = tmp_path / "w.rrd"
    assert main(["simulate", "--walk", "slope", "--sensor", "stereo", "--frames", "1", "--rrd", str(rrd),
                 "--no-progress"]) == 0
    assert rrd.is_file()


def test_validate_runs_the_validation_module(tmp_path, capsys, monkeypatch):
    from noise_model.sim.stereo import validation

    calls = []
    monkeypatch.setattr(validation, "main", lambda argv=None: calls.append(argv) or 0)
    out = tmp_path / "v.json"
    assert main(["simulate", "--sensor", "stereo", "--validate", str(tmp_path), "--json", str(out),
                 "--frames", "3"]) == 0
    assert calls[-1] == ["--realdata", str(tmp_path), "--json", str(out), "--frames", "3"]
    assert main(["simulate", "--sensor", "stereo", "--validate"]) == 0
    assert calls[-1] == []
    for args, message in [(["--validate"], "give --sensor stereo"),
                          (["--sensor", "stereo", "--validate", "--walk", "stairs"], "takes no --grid"),
                          (["--sensor", "stereo", "--validate", str(tmp_path / "none")], "no such folder"),
                          (["--walk", "stairs", "--json", str(out)], "--json goes with --validate")]:
        assert main(["simulate"] + args) == 2
        assert message in capsys.readouterr().err
    assert len(calls) == 2


def test_bench_records_the_physical_d435_at_both_sizes(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["bench", "--only", "stereo", "--frames", "1", "--json", str(out), "--no-progress"]) == 0
    recs = json.loads(out.read_text())["results"]
    assert {(r["name"], r["width"], r["height"]) for r in recs} == {("stereo", 424, 240), ("stereo", 848, 480)}
    for r in recs:
        assert r["median_ms"] > 0 and r["target_ms"] == {424: 150.0, 848: 600.0}[r["width"]]
        assert r["render_ms"] > 0 and r["noise_and_match_ms"] > 0 and r["points"] > 0
    assert "budget" in capsys.readouterr().out


# ---------------------------------------------------------------------------------------------
# bad input names itself
# ---------------------------------------------------------------------------------------------
def test_bad_input_gives_a_value_error_naming_it(cam):
    with pytest.raises(ValueError, match="no surface in view"):
        cam.render(Scene([Box((-3.0, 0.0, 1.0), (1.0, 1.0, 1.0))], ground_z=None), T_CAM)    # behind the camera
    with pytest.raises(ValueError, match=r"albedo of Box.material must lie in \[0, 1\]"):
        Box((2.0, 0.0, 1.0), (1.0, 1.0, 1.0), material=1.2)
    with pytest.raises(ValueError, match="Scene.ground_material"):
        Scene(ground_material=-0.5)
    with pytest.raises(ValueError, match="albedo of rubber"):
        MT.Uniform(-0.1, "rubber")
    for b in (0.0, -0.05):
        with pytest.raises(ValueError, match="baseline_m"):
            StereoD435(424, 240, baseline_m=b)
    for n in (0, -10):
        with pytest.raises(ValueError, match="n_dots"):
            Projector(DotPattern(n_dots=n))
    with pytest.raises(ValueError, match="not a D435 depth mode"):
        StereoD435(320, 200)
    with pytest.raises(ValueError, match="not a D435 depth mode"):
        simulate_target_stereo(CaptureGeometry("odd", D435.intrinsics(424, 240), 400, 240, 0.001, 0.05,
                                               {"kind": "wall", "distance_m": 1.0}), 1, np.random.default_rng(0))
    with pytest.raises(ValueError, match="pitched by 20.0 deg"):
        board_geometry(1.0, 0.0, 20.0, 3.0).scene()
    with pytest.raises(ValueError, match="rng must be a numpy.random.Generator"):
        simulate_target_stereo(board_geometry(), 1, 0)
