"""The command line: subcommands, JSON reports, errors; and the package layering rules."""

import json
import subprocess
import sys

import pytest

from elevmap.cli import main


def test_bench_writes_one_record_per_kernel_size_and_implementation(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["bench", "--only", "noise,move_to,height_scan", "--frames", "3", "--reference-frames", "1",
                 "--json", str(out), "--no-progress"]) == 0
    report = json.loads(out.read_text())
    keys = {(r["name"], r["width"], r["height"], r["impl"]) for r in report["results"]}
    assert keys == {("noise", 848, 480, "numba"), ("noise", 848, 480, "numpy"),
                    ("noise", 424, 240, "numba"), ("noise", 424, 240, "numpy"),
                    ("move_to", 200, 200, "numpy"), ("height_scan", 395, 1, "numba"), ("height_scan", 395, 1, "numpy")}
    for r in report["results"]:
        assert r["median_ms"] > 0 and r["points_per_s"] > 0
    from noise_model.kernels import STAGES

    for r in report["results"]:
        if r["name"] == "noise":
            assert r["points"] > 0.9 * r["width"] * r["height"] * 0.5
        if r["name"] == "noise" and r["impl"] == "numba":     # each stage of the kernel timed alone
            assert set(r["stages"]) == set(STAGES) and all(t > 0 for t in r["stages"].values())
            # ... and on the mapper's floor frame, which loses the rows beyond its range: fewer points
            assert set(r["mapper_frame_stages"]) == set(STAGES) and all(t > 0 for t in r["mapper_frame_stages"].values())
            assert 0 < r["mapper_frame_points"] < r["points"]
    printed = capsys.readouterr().out
    assert "speed-up" in printed and "stages alone" in printed and "the mapper's floor frame" in printed
    assert [p.name for p in tmp_path.iterdir()] == ["bench.json"]


def test_bench_times_the_mapper_on_the_physical_d435s_frame():
    # the mapper on depth whose noise emerges from stereo matching, next to its NumPy reference, with the
    # noise kernel's stages on that frame and how much of it takes the two-surface path (424x240 only: fast)
    from elevmap.commands.bench import _bench_physical, format_table
    from noise_model.kernels import STAGES

    rows = _bench_physical(1, 1, 1, None, sizes=((424, 240),))
    names = ("mapper_physical", "mapper_physical_cleanup")
    assert {(r["name"], r["impl"]) for r in rows} == {(name, impl) for name in names for impl in ("numba", "numpy")}
    for r in rows:
        assert r["median_ms"] > 0 and r["points"] > 0 and r["noise_ms"] > 0 and r["fusion_ms"] > 0
    first = next(r for r in rows if r["name"] == "mapper_physical" and r["impl"] == "numba")
    assert set(first["stages"]) == set(STAGES) and 0.0 <= first["mixed_share"] <= 1.0
    assert all(r["points"] == first["points"] for r in rows)            # the same frame for every record
    text = format_table({"results": rows, "machine": {"cpu": "x", "cores": 2, "threads": 1, "threading_layer": "omp",
                                                      "numba": "0", "numpy": "0"}})
    assert "the physical D435's frame" in text and "windows of two surfaces" in text


def test_bad_arguments_are_reported_not_raised(capsys):
    assert main(["bench", "--frames", "0"]) == 2
    assert "must be >= 1" in capsys.readouterr().err
    assert main(["bench", "--only", "nonsense"]) == 2
    assert "unknown bench group" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["no-such-command"])


def test_characterize_from_the_command_line(tmp_path, capsys):
    from elevmap.commands.simulate import simulate_capture_set

    # six settings of the paper's grid, 4 frames each: enough for the command's plumbing (the fit's
    # accuracy is tested in test_characterize.py)
    grid = [(d, y) for d in (0.6, 1.0, 1.4) for y in (0.0, 30.0)]
    simulate_capture_set(tmp_path / "set", grid=grid, n_frames=4, show_progress=False)
    out = tmp_path / "report.json"
    code = main(["characterize", str(tmp_path / "set"), "--json", str(out), "--figures", str(tmp_path / "figs"),
                 "--no-progress"])
    assert code == 0
    report = json.loads(out.read_text())
    assert len(report["fit"]["coefficients"]) == 4 and len(report["fit"]["stderr"]) == 4
    assert {c["id"] for c in report["captures"]} == {f"board_z{d:.2f}_y{int(y):02d}" for d, y in grid}
    assert (tmp_path / "report.model.json").exists() and any((tmp_path / "figs").glob("*.png"))
    assert "sigma_z" in capsys.readouterr().out
    assert main(["characterize", str(tmp_path / "set"), "--json", str(out), "--no-progress"]) == 2   # no overwrite
    assert "exists" in capsys.readouterr().err


def test_characterize_help_explains_the_recording_protocol():
    res = subprocess.run([sys.executable, "-m", "elevmap.cli", "characterize", "--help"], capture_output=True,
                         text=True)
    assert res.returncode == 0
    for words in ("tripod", "laser distance meter", "0.4 to 2.1 m", "100 frames", "captures.json"):
        assert words in res.stdout


def test_console_script_has_help():
    res = subprocess.run([sys.executable, "-m", "elevmap.cli", "--help"], capture_output=True, text=True)
    assert res.returncode == 0
    for cmd in ("demo", "bench"):
        assert cmd in res.stdout


def test_noise_model_imports_no_io_or_visualisation():
    code = ("import sys, noise_model; bad = [m for m in ('elevmap', 'rerun', 'pyrealsense2', 'cv2') "
            "if m in sys.modules]; print(bad); sys.exit(1 if bad else 0)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_elevmap_core_imports_no_realsense():
    code = ("import sys, elevmap, elevmap.cli, elevmap.commands.bench; "
            "sys.exit(1 if 'pyrealsense2' in sys.modules else 0)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_name_lists_of_the_options_name_the_problem():
    from noise_model.reporting import check_names

    assert check_names(" a, b ", "--x", ["a", "b", "c"]) == ["a", "b"]
    assert check_names(["c"], "--x", ["a", "b", "c"]) == ["c"]
    with pytest.raises(ValueError, match="unknown mapper 'd'; mappers: a, b"):
        check_names("a,d", "--mappers", ["a", "b"], "mapper")
    with pytest.raises(ValueError, match="names a capture twice"):
        check_names("a,a", "--heldout", None, "capture")
    with pytest.raises(ValueError, match="give comma-separated effects"):
        check_names("a,,b", "--effects", None, "effect")
    with pytest.raises(ValueError, match="--heldout must be comma-separated captures or a list"):
        check_names(3, "--heldout", None, "capture")


def test_help_builds_without_numba_or_rerun():
    code = ("import sys\nfrom elevmap.cli import build_parser\nbuild_parser().format_help()\n"
            "bad = [m for m in ('numba', 'rerun', 'noise_model') if m in sys.modules]\nprint(bad)\n"
            "sys.exit(1 if bad else 0)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
    res = subprocess.run([sys.executable, "-m", "elevmap.cli", "compare", "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "correlated_noise" in res.stdout and "e.g. --sim-effects" in res.stdout


def test_user_messages_name_the_viewer_not_a_virtualenv():
    from pathlib import Path

    src = (Path(__file__).resolve().parents[2] / "elevmap" / "cli.py").read_text()
    assert ".venv" not in src and "rerun {" in src


def test_one_output_policy(tmp_path):
    from elevmap.fileio import check_outputs

    data = tmp_path / "captures.json"
    data.write_text("{}")
    old = tmp_path / "old.json"
    old.write_text("{}")
    got = check_outputs({"--json": tmp_path / "r.json", "--rrd": None}, inputs=[data])
    assert got == {"--json": tmp_path / "r.json", "--rrd": None}
    for outputs, kwargs, message in [
        ({"--json": data}, dict(overwrite=True, inputs=[data]), "is an input of this run; refusing to overwrite"),
        ({"--json": tmp_path}, {}, "is a directory"),
        ({"--rrd": tmp_path / "no" / "r.rrd"}, {}, "folder does not exist"),
        ({"--json": tmp_path / "a.x", "--rrd": tmp_path / "a.x"}, {}, "different files"),
        ({"--json": old}, {}, "exists; pass --overwrite"),
        ({"--json": old / "r.json"}, dict(create_folders=True), "is a file, not a folder"),
    ]:
        with pytest.raises(ValueError, match=message):
            check_outputs(outputs, **kwargs)
    assert check_outputs({"--json": old}, overwrite=True)["--json"] == old
    assert check_outputs({"f": tmp_path / "new" / "f.png"}, create_folders=True)["f"] == tmp_path / "new" / "f.png"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["captures.json", "old.json"]


def test_gap_refuses_an_existing_report_without_overwrite(tmp_path, capsys):
    out = tmp_path / "gap.json"
    out.write_text('{"format": "d435-gap/1"}')
    assert main(["gap", str(tmp_path), "--json", str(out), "--no-progress"]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert main(["gap", "--selftest", "--json", str(out), "--no-progress", "--effects", "invalid_band"]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert out.read_text() == '{"format": "d435-gap/1"}'


def test_run_with_a_sensor_model_file(tmp_path, capsys):
    """`run --model` and `[map] sensor_model` (relative to the config file) map with that model."""
    import numpy as np

    from noise_model import D435

    D435.with_disparity(0.08).save(tmp_path / "disp.model.json")
    (tmp_path / "map.toml").write_text('[map]\nsensor_model = "disp.model.json"\n')
    runs = {}
    for name, extra in (("paper", []), ("option", ["--model", str(tmp_path / "disp.model.json")]),
                        ("config", ["--config", str(tmp_path / "map.toml")])):
        out = tmp_path / f"{name}.json"
        assert main(["run", "sim:stairs", "--frames", "2", "--no-progress", "--json", str(out), *extra]) == 0
        runs[name] = json.loads(out.read_text())
    assert runs["option"]["error"] == runs["config"]["error"]
    assert runs["option"]["error"]["coverage_2sigma"] != runs["paper"]["error"]["coverage_2sigma"]
    capsys.readouterr()
    assert main(["run", "sim:stairs", "--frames", "2", "--model", str(tmp_path / "absent.json")]) == 2
    assert "absent.json: no such sensor model file" in capsys.readouterr().err
    assert np.isfinite(runs["option"]["error"]["median_abs_m"])
