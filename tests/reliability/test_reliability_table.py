"""Hostile but realistic input, one row per defect of the reliability campaign (D1-D19).

Each row builds its inputs in a fresh folder, runs a command line (in process, through ``elevmap.cli.main``)
or an API call, and checks what a user cares about: the exit status or the exception, the words the one-line
message must hold, and that no output and no temporary file was left behind while every file that was
there before is byte-identical afterwards.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from elevmap.cli import main
from elevmap.fileio import TEMP_TAG

K_SMALL = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])
CAMERA = {"model": "D435", "width": 16, "height": 12, "fx": 12.0, "fy": 12.0, "ppx": 7.5, "ppy": 5.5,
          "depth_scale": 0.001}


def tree(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (hidden ones too) -> sha256 of its bytes."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def temporaries(folder: Path) -> list[str]:
    return [str(p.relative_to(folder)) for p in folder.rglob("*") if TEMP_TAG in p.name]


# -- inputs --------------------------------------------------------------------------------------


def a_capture_set(folder: Path, captures=None, camera=None) -> Path:
    """A valid one-capture set, then ``captures`` / ``camera`` replace its entries as given (raw JSON)."""
    folder.mkdir(parents=True, exist_ok=True)
    depth = np.full((2, 12, 16), 1000, np.uint16)
    np.save(folder / "wall.npy", depth)
    entry = {"id": "wall", "depth": "wall.npy", "target": {"kind": "wall", "distance_m": 1.0}}
    doc = {"format": "d435-captures/1", "camera": camera or CAMERA, "captures": [entry] if captures is None
           else captures}
    (folder / "captures.json").write_text(json.dumps(doc))
    return folder


def a_corrupt_db3(folder: Path) -> Path:
    """A 10-frame .db3 whose second depth message has its first byte flipped (SQLite intact)."""
    from elevmap.sources.realsense import record_db3

    rng = np.random.default_rng(0)
    frames = [(1000 + rng.integers(0, 50, (48, 64))).astype(np.uint16) for _ in range(10)]
    path = record_db3(folder / "walk.db3", frames, K_SMALL)
    con = sqlite3.connect(path)
    (topic,), = con.execute("SELECT id FROM topics WHERE name LIKE '%Depth_0/image/data%'")
    rows = con.execute("SELECT id, data FROM messages WHERE topic_id = ? ORDER BY timestamp", (topic,)).fetchall()
    mid, data = rows[1]
    data = bytearray(data)
    data[0] ^= 0x10
    con.execute("UPDATE messages SET data = ? WHERE id = ?", (bytes(data), mid))
    con.commit()
    con.close()
    return path


def a_map_file(folder: Path, layer: str, value: float) -> Path:
    """A saved map with ``layer`` set to ``value`` in its known cells (written past the map's own checks)."""
    from elevmap import ElevationMap
    from elevmap.map.layers import LAYERS

    m = ElevationMap(1.0, 0.25)
    m.update(np.array([[0.1, 0.1, 0.1]] * 5), np.full(5, 1e-4))
    path = folder / "map.npz"
    m.save(path)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    known = np.isfinite(arrays["data"][0])
    arrays["data"][LAYERS.index(layer)][known] = value
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)
    return path


def an_rrd_with_meter_zero(folder: Path) -> Path:
    import rerun as rr

    path = folder / "m0.rrd"
    rec = rr.RecordingStream("elevmap-test")
    rec.save(str(path))
    rec.log("world/cam/depth", rr.Pinhole(focal_length=60.0, width=64, height=48), static=True)
    rec.set_time("frame", sequence=0)
    rec.log("world/cam/depth", rr.DepthImage(np.full((48, 64), 1000, np.uint16), meter=0.0))
    rec.flush()
    rec.disconnect()
    return path


def a_png_folder_with_truncated_intrinsics(folder: Path) -> Path:
    import cv2

    d = folder / "pngs"
    d.mkdir()
    for k in range(2):
        cv2.imwrite(str(d / f"{k:06d}.png"), np.full((48, 64), 1000, np.uint16))
    (d / "intrinsics.json").write_text('{"width": 64, "height": 48, "intrinsic_matrix": [60.0, 0')
    return d


def write(folder: Path, name: str, text: str) -> Path:
    p = folder / name
    p.write_text(text)
    return p


# -- the table -----------------------------------------------------------------------------------
# (defect, setup(tmp) -> dict of names, command line (names in braces) or API call(tmp, names),
#  expected exit status or exception type, words the message must hold)

def _cli(*argv):
    return list(argv)


ROWS = [
    ("D1 a .db3 with one corrupted byte", lambda t: {"src": a_corrupt_db3(t)},
     _cli("run", "{src}", "--json", "{t}/out.json"), 2, ["played back 1 of the 10 depth frames", "corrupt"]),
    ("D3 a map file with NaN variances", lambda t: {"m": a_map_file(t, "variance", np.nan)},
     lambda t, n: __import__("elevmap").ElevationMap.load(n["m"]), ValueError, ["map.npz", "variance"]),
    ("D3 a map file with negative variances", lambda t: {"m": a_map_file(t, "variance", -0.01)},
     lambda t, n: __import__("elevmap").ElevationMap.load(n["m"]), ValueError, ["variance", "> 0"]),
    ("D3 a map file with zero variances", lambda t: {"m": a_map_file(t, "variance", 0.0)},
     lambda t, n: __import__("elevmap").ElevationMap.load(n["m"]), ValueError, ["variance"]),
    ("D3 a map file with infinite heights", lambda t: {"m": a_map_file(t, "elevation", np.inf)},
     lambda t, n: __import__("elevmap").ElevationMap.load(n["m"]), ValueError, ["'elevation'", "infinite"]),
    ("D4 bench --json onto an existing file", lambda t: {"old": write(t, "b.json", '{"mine": 1}')},
     _cli("bench", "--only", "move_to", "--frames", "2", "--reference-frames", "1", "--json", "{old}"), 2,
     ["exists; pass --overwrite"]),
    ("D4 demo --rrd onto an existing file", lambda t: {"old": write(t, "demo.rrd", "precious")},
     _cli("demo", "--frames", "2", "--rrd", "{old}", "--no-progress"), 2, ["exists; pass --overwrite"]),
    ("D4 gap --json onto its previous report", lambda t: {"old": write(t, "gap.json", '{"format": "d435-gap/1"}')},
     _cli("gap", "--selftest", "--json", "{old}", "--no-progress"), 2, ["exists; pass --overwrite"]),
    ("D5 run --json P --rrd P", lambda t: {},
     _cli("run", "sim:stairs", "--frames", "2", "--json", "{t}/out.x", "--rrd", "{t}/out.x"), 2, ["same file"]),
    ("D6 run --json onto the --poses file", lambda t: {"p": write(t, "poses.txt", "0 0 0 0 0 0 0 1\n")},
     _cli("run", "sim:stairs", "--frames", "2", "--poses", "{p}", "--json", "{p}", "--overwrite"), 2,
     ["poses.txt is an input", "refusing to overwrite"]),
    ("D6 run --rrd onto the --config file", lambda t: {"c": write(t, "cfg.toml", "[map]\nlength_m = 4.0\n")},
     _cli("run", "sim:stairs", "--frames", "2", "--config", "{c}", "--rrd", "{c}", "--overwrite"), 2,
     ["cfg.toml is an input"]),
    ("D6 characterize --json onto the set's captures.json", lambda t: {"s": a_capture_set(t / "set")},
     _cli("characterize", "{s}", "--json", "{s}/captures.json", "--overwrite", "--no-progress"), 2,
     ["captures.json is an input"]),
    ("D6 compare --json onto its --sim-effects report", lambda t: {"g": write(t, "gap.json", "{}")},
     _cli("compare", "--frames", "2", "--sim-effects", "{g}", "--json", "{g}", "--overwrite"), 2, ["is an input"]),
    ("D7 score_every = 0", lambda t: {"c": write(t, "z.toml", "[map]\nscore_every = 0\n")},
     _cli("run", "sim:stairs", "--frames", "2", "--config", "{c}"), 2, ["z.toml", "score_every", ">= 1", "0"]),
    ("D7 log_every = 0", lambda t: {"c": write(t, "z.toml", "[map]\nlog_every = 0\n")},
     _cli("run", "sim:stairs", "--frames", "2", "--config", "{c}"), 2, ["log_every", ">= 1"]),
    ("D7 mesh_every = 0", lambda t: {"c": write(t, "z.toml", "[map]\nmesh_every = 0\n")},
     _cli("run", "sim:stairs", "--frames", "2", "--config", "{c}"), 2, ["mesh_every"]),
    ("D7 max_ellipsoids = 0", lambda t: {"c": write(t, "z.toml", "[map]\nmax_ellipsoids = 0\n")},
     _cli("run", "sim:stairs", "--frames", "2", "--config", "{c}"), 2, ["max_ellipsoids"]),
    ("D7 max_points = -5", lambda t: {"c": write(t, "z.toml", "[map]\nmax_points = -5\n")},
     _cli("run", "sim:stairs", "--frames", "2", "--config", "{c}"), 2, ["max_points", "-5"]),
    ('D7 follow = "false"', lambda t: {"c": write(t, "z.toml", '[map]\nfollow = "false"\n')},
     _cli("run", "sim:stairs", "--frames", "2", "--config", "{c}"), 2, ["follow must be true or false", "'false'"]),
    ('D7 visibility_cleanup = "no"', lambda t: {"c": write(t, "z.toml", '[map]\nvisibility_cleanup = "no"\n')},
     _cli("run", "sim:stairs", "--frames", "2", "--config", "{c}"), 2, ["visibility_cleanup must be true or false"]),
    ('D7 scatter_inflation = "no"', lambda t: {"c": write(t, "z.toml", '[map.fusion]\nscatter_inflation = "no"\n')},
     _cli("run", "sim:stairs", "--frames", "2", "--config", "{c}"), 2, ["scatter_inflation must be true or false"]),
    ("D7 resolution_m = true", lambda t: {"c": write(t, "z.toml", "[map]\nresolution_m = true\n")},
     _cli("run", "sim:stairs", "--frames", "2", "--config", "{c}"), 2, ["resolution_m must be a number", "True"]),
    ('D7 min_horizontal_variance = "x"',
     lambda t: {"c": write(t, "z.toml", '[map.fusion]\nmin_horizontal_variance = "x"\n')},
     _cli("run", "sim:stairs", "--frames", "2", "--config", "{c}"), 2, ["z.toml", "min_horizontal_variance", "'x'"]),
    ("D9 --rrd into a missing folder", lambda t: {},
     _cli("run", "sim:stairs", "--frames", "2", "--rrd", "{t}/nowhere/x.rrd"), 2, ["folder does not exist"]),
    ("D9 --rrd is a folder", lambda t: {"d": (t / "adir").mkdir() or t / "adir"},
     _cli("run", "sim:stairs", "--frames", "2", "--rrd", "{d}"), 2, ["is a directory"]),
    ("D9 simulate --out names a file", lambda t: {"f": write(t, "afile", "x")},
     _cli("simulate", "--grid", "paper", "--frames", "1", "--out", "{f}", "--overwrite"), 2,
     ["is a file, not a folder"]),
    ("D9 simulate --out a folder holding other files", lambda t: {"f": write(t, "notes.txt", "x")},
     _cli("simulate", "--grid", "paper", "--frames", "1", "--out", "{t}"), 2, ["holds other files", "notes.txt"]),
    ("D2 simulate --overwrite onto a set that also holds a user's file",
     lambda t: {"s": a_capture_set(t / "set"), "_": write(t / "set", "notes.txt", "mine")},
     _cli("simulate", "--grid", "paper", "--frames", "1", "--out", "{s}", "--overwrite"), 2,
     ["also holds files that are not part of it", "notes.txt"]),
    ("D2 simulate onto an existing set without --overwrite", lambda t: {"s": a_capture_set(t / "set")},
     _cli("simulate", "--grid", "paper", "--frames", "1", "--out", "{s}"), 2,
     ["already holds a capture set", "--overwrite"]),
    ("D9 --json on a full disk", lambda t: {}, "full-disk", 1, ["No space left on device"]),
    ("D10 a map needing 45 GiB (API)", lambda t: {},
     lambda t, n: __import__("elevmap").ElevationMap(800.0, 0.04), ValueError, ["GiB", "above the limit"]),
    ("D10 length_m = 800 in a config", lambda t: {"c": write(t, "z.toml", "[map]\nlength_m = 800.0\n")},
     _cli("run", "sim:stairs", "--frames", "2", "--config", "{c}"), 2, ["z.toml", "20000 x 20000", "GiB"]),
    ("D11 move_to 1e18 m", lambda t: {},
     lambda t, n: __import__("elevmap").ElevationMap(2.0, 0.1).move_to([1e18, 0.0]), ValueError, ["1e+18 m", "beyond"]),
    ("D11 a pose file 1e18 m away", lambda t: {"p": write(t, "tum.txt", "0 0 0 0 0 0 0 1\n10 1e18 0 0 0 0 0 1\n")},
     _cli("run", "sim:stairs", "--frames", "2", "--poses", "{p}", "--json", "{t}/o.json"), 2,
     ["camera position of frame", "beyond"]),
    ("D12 a height of 1e152 m", lambda t: {},
     lambda t, n: __import__("elevmap").ElevationMap(2.0, 0.1).update(np.array([[0.5, 0.5, 1e152]] * 5),
                                                                        np.full(5, 1e-4)),
     ValueError, ["points_map", "beyond"]),
    ("D13 a variance of 1e-100 m^2", lambda t: {},
     lambda t, n: __import__("elevmap").ElevationMap(2.0, 0.1).update(np.array([[0.5, 0.5, 0.9375]]),
                                                                        np.array([1e-100])),
     ValueError, ["height_var", "below the smallest variance"]),
    ("D14 a capture set without captures", lambda t: {"s": a_capture_set(t / "set", captures=[])},
     _cli("run", "{s}", "--json", "{t}/o.json"), 2, ["no depth frames"]),
    ("D15 an .rrd whose depth has meter = 0", lambda t: {"r": an_rrd_with_meter_zero(t)},
     _cli("run", "{r}", "--json", "{t}/o.json"), 2, ["m0.rrd", "meter = 0.0"]),
    ("D15 captures.json nested 100,000 deep", lambda t: {"s": a_capture_set(t / "set")} | {
        "_": write(t / "set", "captures.json", "[" * 100_000 + "]" * 100_000)},
     _cli("run", "{s}"), 2, ["captures.json", "nested too deeply"]),
    ("D15 a width of 1e400", lambda t: {"s": a_capture_set(t / "set", camera={**CAMERA, "width": 10 ** 400})},
     _cli("run", "{s}"), 2, ["'width' must be a positive integer"]),
    ("D16 fx = 1e-300 in captures.json", lambda t: {"s": a_capture_set(t / "set", camera={**CAMERA, "fx": 1e-300})},
     _cli("run", "{s}"), 2, ["captures.json", "'fx'", "below 1 px"]),
    ("D16 K with fx = 1e-300 (API)", lambda t: {},
     lambda t, n: __import__("elevmap").Camera("c", np.diag([1e-300, 1e-300, 1.0]), 64, 48), ValueError,
     ["focal lengths must be >= 1 px"]),
    ("D16 a truncated intrinsics file", lambda t: {"d": a_png_folder_with_truncated_intrinsics(t)},
     _cli("run", "{d}"), 2, ["intrinsics.json", "not valid JSON"]),
    ("D17 SIGTERM inside an atomic write", lambda t: {}, "sigterm", Exception, []),
    ("unclear error: move_to with strings", lambda t: {},
     lambda t, n: __import__("elevmap").ElevationMap(2.0, 0.1).move_to(["a", "b"]), ValueError, ["centre_xy", "'a'"]),
    ("unclear error: a stamp that is a word", lambda t: {},
     lambda t, n: __import__("elevmap").ElevationMap(2.0, 0.1).update(np.zeros((1, 3)), np.full(1, 1e-3),
                                                                        stamp="yesterday"),
     ValueError, ["stamp", "'yesterday'"]),
    ("unclear error: a binary config file",
     lambda t: {"c": (t / "b.toml").write_bytes(b"\xff\xfe\x00") and t / "b.toml"},
     _cli("run", "sim:stairs", "--frames", "2", "--config", "{c}"), 2, ["b.toml", "not valid TOML"]),
    ("D19 a depth file outside the set", lambda t: {"s": a_capture_set(t / "set", captures=[
        {"id": "w", "depth": "../other/x.npy", "target": {"kind": "wall", "distance_m": 1.0}}])},
     _cli("run", "{s}"), 2, ["'../other/x.npy' is not inside the capture set's folder"]),
    ("D19 an absolute depth path", lambda t: {"s": a_capture_set(t / "set", captures=[
        {"id": "w", "depth": str(t / "set" / "wall.npy"), "target": {"kind": "wall", "distance_m": 1.0}}])},
     _cli("characterize", "{s}", "--json", "{t}/r.json"), 2, ["is not inside the capture set's folder"]),
]


def _full_disk(tmp_path, monkeypatch, capsys):
    """ENOSPC while the JSON report is written: one line, exit 1, no file (os.write is what fails)."""
    import elevmap.fileio as fileio

    real_replace = os.replace

    def no_space(src, dst):
        if TEMP_TAG in str(src):
            raise OSError(28, "No space left on device", str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(fileio.os, "replace", no_space)
    return main(["run", "sim:slope", "--frames", "1", "--json", str(tmp_path / "o.json"), "--no-progress"])


def _sigterm(tmp_path):
    """SIGTERM arriving inside an atomic write under handle_signals: Interrupted, temporary removed."""
    from elevmap.fileio import Interrupted, atomic_output, handle_signals

    with pytest.raises(Interrupted) as info:
        with handle_signals(), atomic_output(tmp_path / "out.json") as tmp:
            tmp.write_text("half")
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(10_000):            # the handler runs between bytecodes, at once
                pass
            raise AssertionError("SIGTERM did not interrupt the block")
    assert info.value.signum == signal.SIGTERM
    return 0


@pytest.mark.parametrize("case, setup, action, expected, words", ROWS, ids=[r[0] for r in ROWS])
def test_hostile_input_gives_a_clear_error_and_leaves_nothing(tmp_path, monkeypatch, capsys, case, setup, action,
                                                              expected, words):
    names = setup(tmp_path)
    before = tree(tmp_path)
    capsys.readouterr()
    message = ""
    if action == "full-disk":
        assert _full_disk(tmp_path, monkeypatch, capsys) == expected
        message = capsys.readouterr().err
    elif action == "sigterm":
        _sigterm(tmp_path)
    elif callable(action):
        with pytest.raises(expected) as info:
            action(tmp_path, names)
        message = str(info.value)
    else:
        argv = [a.format(t=tmp_path, **names) for a in action]
        argv += [] if "--no-progress" in argv else ["--no-progress"]
        assert main(argv) == expected, capsys.readouterr().err
        message = capsys.readouterr().err
        assert message.count("\n") == 1 and "Traceback" not in message, message
    for w in words:
        assert w in message, f"{w!r} not in {message!r}"
    assert tree(tmp_path) == before, "a file was written, changed or left behind"
    assert temporaries(tmp_path) == []


def test_outputs_honour_the_umask(tmp_path):
    """D18: reports, maps, figures and capture sets get 0o666 / 0o777 minus the umask (here 027)."""
    from elevmap import ElevationMap
    from elevmap.commands.simulate import simulate_capture_set

    old = os.umask(0o027)
    try:
        assert main(["run", "sim:slope", "--frames", "1", "--json", str(tmp_path / "r.json"), "--no-progress"]) == 0
        ElevationMap(1.0, 0.25).save(tmp_path / "m.npz")
        simulate_capture_set(tmp_path / "set", [(1.0, 0.0)], n_frames=1, show_progress=False)
    finally:
        os.umask(old)
    for p in (tmp_path / "r.json", tmp_path / "m.npz", tmp_path / "set" / "captures.json",
              tmp_path / "set" / "board_z1.00_y00.npy"):
        assert p.stat().st_mode & 0o777 == 0o640, p
    assert (tmp_path / "set").stat().st_mode & 0o777 == 0o750


def test_a_failed_capture_set_run_keeps_the_previous_set_whole(tmp_path, monkeypatch):
    """D2 in process: the simulation fails at the third capture of an --overwrite run."""
    import elevmap.commands.simulate as S

    grid = [(1.0, 0.0), (1.2, 0.0), (1.4, 0.0), (1.6, 0.0)]
    S.simulate_capture_set(tmp_path / "set", grid, n_frames=2, seed=0, show_progress=False)
    before = tree(tmp_path)
    calls = []
    real = S.simulate_target

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("the simulation failed here")
        return real(*args, **kwargs)

    monkeypatch.setattr(S, "simulate_target", failing)
    with pytest.raises(RuntimeError, match="failed here"):
        S.simulate_capture_set(tmp_path / "set", grid, n_frames=2, seed=5, overwrite=True, show_progress=False)
    assert tree(tmp_path) == before and temporaries(tmp_path) == []


def test_json_reports_are_strict_json(tmp_path):
    """D14: no NaN token in a report (a JavaScript reader refuses it); NaN is written as null."""
    from elevmap.fileio import write_json_atomic

    write_json_atomic(tmp_path / "r.json", {"ms": float("nan"), "ok": 1.5, "list": [float("inf")]})
    text = (tmp_path / "r.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"ms": None, "ok": 1.5, "list": [None]}


def test_two_mappers_in_two_threads_under_the_workqueue_layer():
    """D8: numba's workqueue layer aborts the process on concurrent parallel launches; the lock in
    noise_model.numba_config.threads serialises them, and both threads get the sequential result."""
    code = textwrap.dedent("""
        import threading, numpy as np, numba
        from elevmap import Camera, ElevationMap, Mapper
        from elevmap.sources import open_source
        frames = list(open_source("sim:slope", frames=3))
        def work(out, k):
            m = ElevationMap(4.0, 0.04); mp = Mapper(m); f = frames[0]
            mp.add_camera(Camera(f.camera, f.K, f.width, f.height, depth_scale=f.depth_scale))
            for f in frames:
                mp.integrate(f.camera, f.depth, T_map_cam=f.T_map_cam, pose_cov=f.pose_cov, stamp=f.stamp)
            out[k] = m.data.copy()
        out, seq = {}, {}
        ts = [threading.Thread(target=work, args=(out, k)) for k in range(2)]
        [t.start() for t in ts]; [t.join() for t in ts]
        work(seq, 0)
        same = all(np.array_equal(out[k], seq[0], equal_nan=True) for k in range(2))
        print(numba.threading_layer(), same)
    """)
    env = dict(os.environ, NUMBA_THREADING_LAYER="workqueue")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.split() == ["workqueue", "True"]


def test_a_read_only_folder_is_refused_before_any_work(tmp_path, capsys):
    """D9: --rrd and --json into a folder nobody may write (mode 0o555, or immutable where the tests run as
    root): one line naming the folder, before the mapping starts."""
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    immutable = False
    try:
        if os.access(ro, os.W_OK):                  # root ignores the mode bits
            res = subprocess.run(["chattr", "+i", str(ro)], capture_output=True)
            if res.returncode != 0:
                pytest.skip("no read-only folder can be made here (root, and chattr +i is refused)")
            immutable = True
        for option in ("--rrd", "--json"):
            assert main(["run", "sim:stairs", "--frames", "2", option, str(ro / "x"), "--no-progress"]) == 2
            err = capsys.readouterr().err
            assert "cannot write in its folder" in err and str(ro) in err and "Traceback" not in err
        assert list(ro.iterdir()) == []
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(ro)], check=True)
        ro.chmod(0o755)
