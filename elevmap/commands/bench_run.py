"""The ``run`` records of ``elevmap bench``: ``elevmap run`` on an 848x480 recording, end to end.

A simulated walk through the demo scene (boxes, then steps) at 848x480 and 30 frames/s is written to a rerun
recording in a temporary folder, raw uint16 depth as a camera streams it. It is then mapped as ``elevmap run
RECORDING [--rrd OUT]`` maps it (:func:`elevmap.pipeline.run_mapping` on :class:`elevmap.sources.rrd.RrdSource`,
the default :class:`elevmap.pipeline.MappingConfig`), with a recording written to the temporary folder
(``run_rrd``) and without (``run``), alternately over :data:`RUN_ROUNDS` rounds. Frames per second are counted
end to end: from opening the source to the output recording in place, over every frame. The split per frame
says where the time goes: ``source`` (reading and decoding the frames), ``mapping`` (the mapper), ``logging``
(rerun, the recording's closing included), and ``open`` (reading the recording's index before the first frame).
"""

from __future__ import annotations

import os
import tempfile
import time

import numpy as np

__all__ = ["bench_run", "run_lines", "RUN_TARGET_FPS", "RUN_ROUNDS", "RUN_SIZE", "RUN_RATE_HZ"]

#: Frames per second ``elevmap run`` must keep end to end at 848x480 (the D435's rate at that size).
RUN_TARGET_FPS = 30.0
#: Alternating rounds (with the recording, without) of which the median is reported.
RUN_ROUNDS = 3
#: Size [px] and frame rate [Hz] of the recording.
RUN_SIZE = (848, 480)
RUN_RATE_HZ = 30.0


def _write_source(path, n_frames: int, nthreads) -> None:
    """The simulated walk's frames to ``path`` (raw depth, every frame, as ``elevmap run --rrd`` lays it out)."""
    from ..pipeline import MappingConfig, run_mapping
    from ..sources.simulated import SimulatedWalk

    width, height = RUN_SIZE
    walk = SimulatedWalk("demo", n_frames=n_frames, width=width, height=height, rate_hz=RUN_RATE_HZ)
    run_mapping(walk, MappingConfig(), rrd_path=path, show_progress=False, nthreads=nthreads)


def _map_once(source_path, out_path, nthreads) -> dict:
    from ..pipeline import MappingConfig, run_mapping
    from ..sources.rrd import RrdSource

    t0 = time.perf_counter()
    src = RrdSource(source_path)
    t_open = time.perf_counter() - t0
    with src:
        summary = run_mapping(src, MappingConfig(), rrd_path=out_path, show_progress=False, total=len(src),
                              nthreads=nthreads)
    wall = time.perf_counter() - t0
    n = summary["frames"]
    split = {k: 1e3 * v / n for k, v in summary["seconds"].items() if k in ("source", "mapping", "logging")}
    return {"frames": n, "frames_per_s": n / wall, "open_ms": 1e3 * t_open, "split": split,
            "bytes": os.path.getsize(out_path) if out_path is not None else None}


def bench_run(n_frames: int, nthreads: int, bar=None) -> list[dict]:
    """``run_rrd`` and ``run`` records (see the module docstring) over a recording of ``n_frames`` frames.

    Each record: ``median_ms`` = 1000 / frames per second end to end, ``frames_per_s``, ``target_ms`` (1000 /
    :data:`RUN_TARGET_FPS`), ``split_ms`` per frame (``open``, ``source``, ``mapping``, ``logging``), and for
    ``run_rrd`` the recording's ``bytes_per_frame``; the medians over :data:`RUN_ROUNDS` rounds.
    """
    width, height = RUN_SIZE
    rounds = {"run_rrd": [], "run": []}
    with tempfile.TemporaryDirectory(prefix="elevmap-bench-run-") as tmp:
        source = os.path.join(tmp, "walk.rrd")
        _write_source(source, n_frames, nthreads)
        for _ in range(RUN_ROUNDS):
            for name in rounds:
                out = os.path.join(tmp, "out.rrd") if name == "run_rrd" else None
                rounds[name].append(_map_once(source, out, nthreads))
                if bar is not None:
                    bar.update(1)
    records = []
    for name, runs in rounds.items():
        fps = float(np.median([r["frames_per_s"] for r in runs]))
        split = {"open": float(np.median([r["open_ms"] for r in runs]))}
        split.update({k: float(np.median([r["split"][k] for r in runs])) for k in ("source", "mapping", "logging")})
        rec = {"name": name, "width": width, "height": height, "impl": "numba", "median_ms": round(1e3 / fps, 4),
               "points_per_s": None, "frames": runs[0]["frames"], "threads": nthreads,
               "frames_per_s": round(fps, 2), "target_ms": round(1e3 / RUN_TARGET_FPS, 4),
               "target_frames_per_s": RUN_TARGET_FPS, "rounds": RUN_ROUNDS, "source_rate_hz": RUN_RATE_HZ,
               "split_ms": {k: round(v, 3) for k, v in split.items()}}
        if name == "run_rrd":
            rec["bytes_per_frame"] = int(np.median([r["bytes"] / r["frames"] for r in runs]))
        records.append(rec)
    return records


def run_lines(rows) -> list[str]:
    """The table's lines explaining the ``run`` records: frames per second and the split per frame."""
    lines = []
    for r in rows:
        if r["name"] not in ("run", "run_rrd"):
            continue
        s = r["split_ms"]
        what = "with --rrd (the recording in a temporary folder)" if r["name"] == "run_rrd" else "without logging"
        lines.append(f"{r['name']} {r['width']}x{r['height']}: {r['frames_per_s']:.1f} frames/s end to end {what} "
                     f"(target {r['target_frames_per_s']:.0f}); per frame [ms]: source {s['source']:.2f}, mapper "
                     f"{s['mapping']:.2f}, logging {s['logging']:.2f}; opening the recording {s['open']:.0f} ms "
                     f"for {r['frames']} frames")
    return lines
