"""`elevmap warmup`: compiles into the cache later processes load, says what it did, and is idempotent."""

from __future__ import annotations

import io
import os
import subprocess
import sys

import pytest

from elevmap.cli import main
from elevmap.commands.warmup import WARMUP_GROUPS, kernel_counts, run_warmup, warmup_steps


def test_the_mapping_group_warms_the_cache_a_new_process_then_compiles_nothing():
    buf = io.StringIO()
    first = run_warmup(["mapping"], out=buf)          # compiles, or loads what this process has not loaded yet
    text = buf.getvalue()
    assert text.splitlines()[0].startswith("numba cache: ")
    steps = warmup_steps(["mapping"])
    for k, step in enumerate(steps, 1):
        assert f"[{k}/{len(steps)}] {step.label} ... " in text
    assert "the disparity family" in steps[-1].label
    assert text.rstrip().splitlines()[-1].startswith("warm-up done in ")
    assert [s["label"] for s in first["steps"]] == [s.label for s in warmup_steps(["mapping"])]
    # in this process everything is compiled now: a second run has nothing to compile or load
    again = run_warmup(["mapping"], out=False)
    assert (again["compiled"], again["loaded"]) == (0, 0)
    # and a new process with the same cache loads every kernel instead of compiling it
    env = dict(os.environ)
    res = subprocess.run([sys.executable, "-m", "elevmap.cli", "warmup", "--only", "mapping"], env=env,
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    last = res.stdout.rstrip().splitlines()[-1]
    assert "compiled" not in last and "loaded" in last and last.endswith("(the cache was already warm)"), res.stdout


def test_counts_only_grow_and_bad_groups_are_refused(capsys):
    compiled, loaded = kernel_counts()
    assert compiled >= 0 and loaded >= 0
    with pytest.raises(ValueError, match="unknown warm-up group"):
        warmup_steps(["mapping", "gpu"])
    assert main(["warmup", "--only", "mapping,gpu"]) == 2
    assert "unknown warm-up group(s) ['gpu']" in capsys.readouterr().err
    assert {s.group for s in warmup_steps()} == set(WARMUP_GROUPS)
