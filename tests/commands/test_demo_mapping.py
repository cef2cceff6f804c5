"""The mapping demo end to end: simulate -> map -> .rrd -> replay gives the same map."""

import numpy as np
import pytest

from elevmap.cli import main
from elevmap.commands.demo import run_mapping_demo
from elevmap.pipeline import MappingConfig, run_mapping
from elevmap.sources.rrd import RrdSource


def test_demo_writes_a_recording_that_replays_to_the_same_map(tmp_path):
    path = tmp_path / "demo.rrd"
    summary = run_mapping_demo(path, seed=1, n_frames=8, show_progress=False)
    assert path.is_file() and summary["frames"] == 8
    err = summary["error"]
    assert err["known_cells"] > 1000 and np.isfinite(err["median_abs_m"]) and err["median_abs_m"] < 0.1
    with RrdSource(path) as src:
        replayed = run_mapping(src, MappingConfig(), show_progress=False)
    np.testing.assert_array_equal(replayed["map"].data, summary["map"].data)


def test_cli_demo_prints_the_error_and_replaces_files_only_with_overwrite(tmp_path, capsys):
    path = tmp_path / "demo.rrd"
    assert main(["demo", "--rrd", str(path), "--frames", "3", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "median |error|" in out and "ms per frame" in out and path.is_file()
    before = path.read_bytes()
    assert main(["demo", "--rrd", str(path), "--frames", "3", "--no-progress"]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err and path.read_bytes() == before
    assert main(["demo", "--rrd", str(path), "--frames", "3", "--no-progress", "--overwrite"]) == 0


def test_cli_run_refuses_to_overwrite_and_replay_needs_rrd(tmp_path, capsys):
    out = tmp_path / "walk.rrd"
    out.write_bytes(b"a user's recording")
    assert main(["run", "sim:stairs", "--frames", "2", "--rrd", str(out), "--no-progress"]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert out.read_bytes() == b"a user's recording"
    assert main(["replay", "sim:stairs"]) == 2
    assert "replay takes a rerun recording" in capsys.readouterr().err
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[map]\nlength_m = 4.0\nsize = 3\n")
    assert main(["run", "sim:stairs", "--frames", "2", "--config", str(cfg), "--no-progress"]) == 2
    assert "unknown mapping setting(s) ['size']" in capsys.readouterr().err
    cfg.write_text("[map]\nlength_m = 4.0\n[map.fusion]\nmax_points_per_frame = 20.0\n")
    js = tmp_path / "run.json"
    assert main(["run", "sim:slope", "--frames", "2", "--config", str(cfg), "--json", str(js), "--no-progress"]) == 0
    assert '"frames": 2' in js.read_text()


def test_demo_writes_its_picture_beside_the_recording(tmp_path):
    path = tmp_path / "walk.rrd"
    summary = run_mapping_demo(path, seed=1, n_frames=3, show_progress=False)
    png = tmp_path / "walk.png"
    assert summary["png"] == str(png) and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["walk.png", "walk.rrd"]
    assert png.stat().st_size < 300_000


def test_demo_on_the_physical_d435_maps_the_same_walk_and_replays_to_the_same_map(tmp_path, capsys):
    phys = run_mapping_demo(tmp_path / "phys.rrd", seed=1, n_frames=4, show_progress=False, png=False,
                            sensor="stereo")
    ref = run_mapping_demo(tmp_path / "ref.rrd", seed=1, n_frames=4, show_progress=False, png=False)
    assert phys["sensor"] == "stereo" and ref["sensor"] == "reference" and phys["frames"] == 4
    # the same walk and terrain, seen by another camera: a map as good, from other depth
    assert phys["error"]["known_cells"] > 1000 and phys["error"]["median_abs_m"] < 0.05
    assert not np.array_equal(phys["map"].layer("elevation"), ref["map"].layer("elevation"))
    with RrdSource(tmp_path / "phys.rrd") as src:
        replayed = run_mapping(src, MappingConfig(), show_progress=False)
    np.testing.assert_array_equal(replayed["map"].data, phys["map"].data)
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--sensor", "lidar", "--rrd", str(tmp_path / "x.rrd")])
    assert exc.value.code == 2 and "invalid choice: 'lidar'" in capsys.readouterr().err
    assert not (tmp_path / "x.rrd").exists()


def test_demo_maps_with_a_users_sensor_model(tmp_path):
    from noise_model import D435

    model = tmp_path / "disp.model.json"
    D435.with_disparity(0.02).save(model)            # a quarter of the disparity family's usual sigma_d
    mine = run_mapping_demo(tmp_path / "mine.rrd", seed=1, n_frames=3, show_progress=False, png=False,
                            sensor="stereo", model=model)
    paper = run_mapping_demo(tmp_path / "paper.rrd", seed=1, n_frames=3, show_progress=False, png=False,
                             sensor="stereo")
    known = mine["map"].is_known() & paper["map"].is_known()
    assert known.sum() > 1000
    var_mine, var_paper = mine["map"].layer("variance")[known], paper["map"].layer("variance")[known]
    assert np.median(var_mine) < np.median(var_paper)            # the model file, not the paper's, was used
