"""Runs interrupted by a signal keep the previous outputs byte-identical and leave no temporary file.

Each command first writes its outputs once; then the same command with ``--overwrite`` is started as a
separate process and signalled at chosen points of its work (recognised by its temporary files, never by
timing): SIGINT, SIGTERM and SIGHUP must remove every temporary and exit with 128 + the signal; SIGKILL
may leave temporaries, which the next run writing the same output removes before anything else.
"""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from elevmap.fileio import TEMP_TAG

DEADLINE_S = 240.0


#: compare's cache of rendered walks (beside its report): neither an output nor a temporary.
CACHE = "elevmap-compare-work"


def tree(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and CACHE not in p.relative_to(folder).parts}


def temporaries(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if TEMP_TAG in p.name]


def elevmap(cwd: Path, *argv) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "elevmap.cli", *argv, "--no-progress"], cwd=cwd,
                          capture_output=True, text=True, timeout=DEADLINE_S)


def interrupt(cwd: Path, argv, sig, ready) -> tuple[int, str]:
    """Start ``elevmap argv``, wait until ``ready(cwd)`` is true, send ``sig``; (exit status, stderr)."""
    proc = subprocess.Popen([sys.executable, "-m", "elevmap.cli", *argv, "--no-progress"], cwd=cwd,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    try:
        while not ready(cwd):
            if proc.poll() is not None:
                pytest.fail(f"the run ended (status {proc.returncode}) before the point to interrupt it: "
                            f"{proc.stderr.read()[-1000:]}")
            if time.monotonic() - t0 > DEADLINE_S:
                pytest.fail("the run never reached the point to interrupt it")
            time.sleep(0.02)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=DEADLINE_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, err


def temp_holding(name: str, min_files: int = 0, min_bytes: int = 0):
    """Ready when a temporary of output ``name`` exists holding >= min_files files (a folder) or >= min_bytes."""
    def ready(cwd: Path) -> bool:
        for p in cwd.iterdir():
            if p.name.startswith(f".{name}.{TEMP_TAG}-"):
                try:
                    if p.is_dir():
                        return sum(1 for q in p.iterdir() if q.suffix == ".npy") >= min_files
                    return p.stat().st_size >= min_bytes
                except FileNotFoundError:
                    return False
        return False
    return ready


def check_signals(tmp_path: Path, argv, points, next_run) -> None:
    """Every (signal, ready) of ``points`` on a run of ``argv``; outputs unchanged; temporaries gone at once
    (SIGINT/TERM/HUP) or after ``next_run`` (SIGKILL)."""
    before = tree(tmp_path)
    for sig, ready in points:
        status, err = interrupt(tmp_path, argv, sig, ready)
        if sig == signal.SIGKILL:
            assert status == -signal.SIGKILL
            res = elevmap(tmp_path, *next_run)
            assert res.returncode == 2 and "pass --overwrite" in res.stderr, res.stderr
        else:
            assert status == 128 + sig, err
            assert "Traceback" not in err and f"interrupted ({signal.Signals(sig).name})" in err, err
        assert temporaries(tmp_path) == [], (signal.Signals(sig).name, temporaries(tmp_path))
        assert tree(tmp_path) == before, f"{signal.Signals(sig).name} changed the previous outputs"


def test_simulate_capture_set_interrupted(tmp_path):
    """simulate --grid paper --overwrite: the previous set whole after SIGINT/TERM/HUP/KILL at several points."""
    first = elevmap(tmp_path, "simulate", "--grid", "paper", "--frames", "2", "--out", "set")
    assert first.returncode == 0, first.stderr
    argv = ["simulate", "--grid", "paper", "--frames", "4", "--seed", "5", "--out", "set", "--overwrite"]
    check_signals(tmp_path, argv, [
        (signal.SIGINT, temp_holding("set", 5)),
        (signal.SIGTERM, temp_holding("set", 60)),
        (signal.SIGHUP, temp_holding("set", 0)),
        (signal.SIGKILL, temp_holding("set", 30)),
    ], next_run=["simulate", "--grid", "paper", "--frames", "2", "--out", "set"])


def test_run_with_recording_and_report_interrupted(tmp_path):
    """run --rrd --json --overwrite: the previous recording and report byte-identical."""
    first = elevmap(tmp_path, "run", "sim:stairs", "--frames", "2", "--rrd", "r.rrd", "--json", "r.json")
    assert first.returncode == 0, first.stderr
    argv = ["run", "sim:stairs", "--frames", "300", "--rrd", "r.rrd", "--json", "r.json", "--overwrite"]
    check_signals(tmp_path, argv, [
        (signal.SIGINT, temp_holding("r.rrd", min_bytes=1)),
        (signal.SIGTERM, temp_holding("r.rrd", min_bytes=600_000)),
        (signal.SIGHUP, temp_holding("r.rrd", min_bytes=0)),
        (signal.SIGKILL, temp_holding("r.rrd", min_bytes=300_000)),
    ], next_run=["run", "sim:stairs", "--frames", "1", "--rrd", "r.rrd", "--json", "r.json"])


def test_compare_interrupted(tmp_path):
    """compare --json --rrd --overwrite: the previous report and recording byte-identical."""
    first = elevmap(tmp_path, "compare", "--frames", "2", "--mappers", "paper,constant", "--json", "c.json",
                    "--rrd", "c.rrd")
    assert first.returncode == 0, first.stderr
    argv = ["compare", "--frames", "60", "--mappers", "paper,constant", "--json", "c.json", "--rrd", "c.rrd",
            "--overwrite"]
    check_signals(tmp_path, argv, [
        (signal.SIGINT, temp_holding("c.rrd", min_bytes=0)),
        (signal.SIGTERM, temp_holding("c.rrd", min_bytes=100_000)),
        (signal.SIGKILL, temp_holding("c.rrd", min_bytes=200_000)),
    ], next_run=["compare", "--frames", "1", "--json", "c.json", "--rrd", "c.rrd"])


def test_a_killed_two_rename_swap_is_undone_by_the_next_run(tmp_path):
    """Where the system lacks an atomic exchange, a folder output is swapped by two renames; killed between
    them, the previous folder sits aside under a temporary name and the next run moves it back."""
    from elevmap.fileio import _temp_name, remove_leftovers

    out = tmp_path / "set"
    out.mkdir()
    (out / "captures.json").write_text("{}")
    before = tree(tmp_path)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    aside = Path(str(_temp_name(out, ".old")).replace(f"-{os.getpid()}-", f"-{pid}-"))
    new = Path(str(_temp_name(out)).replace(f"-{os.getpid()}-", f"-{pid}-"))
    out.rename(aside)
    new.mkdir()
    (new / "captures.json").write_text('{"new": 1}')
    remove_leftovers(out)
    assert tree(tmp_path) == before and temporaries(tmp_path) == []


def test_folder_swap_without_an_atomic_exchange(tmp_path, monkeypatch):
    """The two-rename swap (systems without renameat2): the new folder replaces the old whole; a failure
    inside the block keeps the old one."""
    import elevmap.fileio as fileio

    monkeypatch.setattr(fileio, "_exchange", lambda a, b: False)
    out = tmp_path / "set"
    out.mkdir()
    (out / "captures.json").write_text("old")
    with pytest.raises(RuntimeError):
        with fileio.atomic_folder(out) as tmp:
            (tmp / "captures.json").write_text("new")
            raise RuntimeError("failed before the end")
    assert tree(tmp_path) == {"set/captures.json": hashlib.sha256(b"old").hexdigest()}
    with fileio.atomic_folder(out) as tmp:
        (tmp / "captures.json").write_text("new")
    assert tree(tmp_path) == {"set/captures.json": hashlib.sha256(b"new").hexdigest()}
    assert temporaries(tmp_path) == []


def test_a_finalizer_that_fails_after_an_interruption_prints_nothing(capsys):
    """A signal that lands inside a constructor (rerun's RecordingStream before its native stream exists)
    leaves an object whose finalizer fails when the exception is dropped, after the block has been left;
    the user sees the one-line message, not Python's 'Exception ignored' traceback."""
    import gc

    from elevmap import fileio

    class HalfBuilt:
        def __init__(self):
            os.kill(os.getpid(), signal.SIGINT)         # delivered before the next bytecode
            self.inner = 1

        def __del__(self):
            self.inner                                  # noqa: B018  (AttributeError: never set)

    seen = []
    hook = sys.unraisablehook
    sys.unraisablehook = seen.append                    # what would be printed
    try:
        try:
            with fileio.handle_signals():
                HalfBuilt()
        except fileio.Interrupted:
            pass
        else:
            raise AssertionError("the signal did not interrupt the block")
        gc.collect()                                    # the half-built object is gone with the exception
        assert seen == []
    finally:
        fileio._pending_signal = None
        sys.unraisablehook = hook
