"""The committed recording replays, and the examples run on it."""

import runpy
import sys
from pathlib import Path

import numpy as np

from elevmap.pipeline import run_mapping
from elevmap.sources.rrd import RrdSource

ROOT = Path(__file__).resolve().parents[2]
RECORDING = ROOT / "recordings" / "stairs_walk.rrd"


def test_the_committed_recording_is_small_and_replays():
    assert RECORDING.stat().st_size <= 5_000_000
    with RrdSource(RECORDING) as src:
        frames = list(src)
        assert src.valid_margins_px == {"front": 0}      # made before the margin: a replay maps every pixel
    assert len(frames) == 24 and frames[0].depth.shape == (240, 424)
    assert all(f.T_map_cam is not None for f in frames)
    out = run_mapping(frames, show_progress=False)
    assert out["map"].known_fraction() > 0.15


def test_controller_feed_example(capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["controller_feed.py", str(RECORDING)])
    runpy.run_path(str(ROOT / "examples" / "controller_feed.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "height scans of 395 samples at 50 Hz" in out


def test_record_walk_example_refuses_to_overwrite(tmp_path, monkeypatch):
    out = tmp_path / "walk.rrd"
    out.write_bytes(b"keep me")
    monkeypatch.setattr(sys, "argv", ["record_walk.py", "--out", str(out), "--frames", "2"])
    try:
        runpy.run_path(str(ROOT / "examples" / "record_walk.py"), run_name="__main__")
    except SystemExit as exc:
        assert "exists" in str(exc)
    assert out.read_bytes() == b"keep me"
    monkeypatch.setattr(sys, "argv", ["record_walk.py", "--out", str(out), "--frames", "2", "--overwrite"])
    runpy.run_path(str(ROOT / "examples" / "record_walk.py"), run_name="__main__")
    assert len(list(RrdSource(out))) == 2
    assert np.isfinite(out.stat().st_size)


def test_sim_to_real_map_gap_example(capsys):
    # the gap's fitted effects, plugged into the walk simulator, bring the simulated map's statistics
    # to those of the "real" one (seeded: the same numbers every run)
    ns = runpy.run_path(str(ROOT / "examples" / "sim_to_real_map_gap.py"))
    out = ns["main"](["--frames", "10", "--capture-frames", "8"])
    assert {e["name"] for e in out["fitted"]} == {name for name, _ in ns["HIDDEN"]}
    assert out["capture_shrink_heldout"] > 0.6
    sig = out["map"]["mean_sigma_m"]
    assert sig["gap_fitted"] < 0.5 * sig["gap_reference"]
    assert "shrink" in capsys.readouterr().out
