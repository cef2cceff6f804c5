"""``elevmap bench``: per-frame timings of the compiled kernels against their NumPy references.

Speed is measured here, never in the test suite. Each record is the median over many frames after
warm-up (numba compilation excluded), with the NumPy reference measured in the same run on the same
frames, so ratios are comparable across machines.
"""

from __future__ import annotations

import os
import platform
import time

import numba
import numpy as np

import noise_model as nm
from noise_model.sim import camera_extrinsics, render_planar_target

__all__ = ["bench_scene", "run_bench", "format_table"]

SIZES = ((848, 480), (424, 240))


def bench_scene(width: int, height: int, seed: int = 0):
    """A representative D435 frame: a board at 1.2 m (yawed 30 deg) before a wall at 2.5 m, paper noise,
    2 % holes; returns (depth uint16, depth_scale, K, T_map_cam, pose_cov)."""
    rng = np.random.default_rng(seed)
    K = nm.D435.intrinsics(width, height)
    z, theta = render_planar_target(K, width, height, 1.2, 30.0, 10.0, kind="board", width_m=1.0, height_m=0.8,
                                    background_m=2.5)
    z = z + rng.normal(size=z.shape) * nm.axial_sigma(z, theta)
    d = np.round(z / 0.001).astype(np.uint16)
    d[rng.random(d.shape) < 0.02] = 0
    T = camera_extrinsics((0.3, 0.0, 0.45), pitch_down_deg=30.0)
    P = np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5])
    return d, 0.001, K, T, P


def _median_ms(fn, frames: int, warmup: int, progress=None) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(frames):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        if progress is not None:
            progress.update(1)
    return 1e3 * float(np.median(times))


def run_bench(frames: int = 200, reference_frames: int = 10, nthreads: int | None = None,
              show_progress: bool = True) -> dict:
    """Time ``noise_model.depth_to_map_points`` (numba, workspace reused) and its NumPy reference.

    Returns
    -------
    dict
        ``{"results": [{"name", "width", "height", "impl", "median_ms", "points_per_s", "frames",
        "threads"}, ...], "machine": {...}}``.
    """
    from tqdm import tqdm

    n = nm.kernels.resolve_threads(nthreads)
    total = len(SIZES) * (frames + reference_frames)
    results = []
    with tqdm(total=total, desc="bench", unit="frame", disable=not show_progress, leave=False) as bar:
        for width, height in SIZES:
            d, scale, K, T, P = bench_scene(width, height)
            ws = nm.Workspace(height, width)
            npts = len(nm.depth_to_map_points(d, K, T, P, depth_scale=scale, workspace=ws, nthreads=n).pixel)
            fast = _median_ms(lambda: nm.depth_to_map_points(d, K, T, P, depth_scale=scale, workspace=ws,
                                                             nthreads=n), frames, 5, bar)
            ref = _median_ms(lambda: nm.depth_to_map_points_reference(d, K, T, P, depth_scale=scale),
                             reference_frames, 1, bar)
            for impl, ms, nf in (("numba", fast, frames), ("numpy", ref, reference_frames)):
                results.append({"name": "noise", "width": width, "height": height, "impl": impl,
                                "median_ms": round(ms, 4), "points_per_s": round(npts / (ms * 1e-3)),
                                "points": npts, "frames": nf, "threads": n if impl == "numba" else 1})
    return {"results": results, "machine": machine_info(n)}


def machine_info(nthreads: int) -> dict:
    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "threads": nthreads, "python": platform.python_version(),
            "numpy": np.__version__, "numba": numba.__version__, "threading_layer": _threading_layer()}


def _threading_layer() -> str:
    try:
        return numba.threading_layer()
    except ValueError:
        return "not initialised"


def format_table(report: dict) -> str:
    """A plain-text table of a bench report, with the numba/NumPy speed-up per kernel and size."""
    rows = report["results"]
    lines = [f"{'kernel':<10}{'size':>10}{'impl':>8}{'median ms':>12}{'Mpoints/s':>12}{'speed-up':>10}"]
    for r in rows:
        ref = next((x for x in rows if x["name"] == r["name"] and x["width"] == r["width"]
                    and x["height"] == r["height"] and x["impl"] == "numpy"), None)
        speed = f"{ref['median_ms'] / r['median_ms']:.1f}x" if ref and r["impl"] != "numpy" else ""
        lines.append(f"{r['name']:<10}{r['width']:>5}x{r['height']:<4}{r['impl']:>8}{r['median_ms']:>12.3f}"
                     f"{r['points_per_s'] / 1e6:>12.1f}{speed:>10}")
    m = report["machine"]
    lines.append(f"machine: {m['cpu']}, {m['cores']} cores, {m['threads']} numba threads ({m['threading_layer']}),"
                 f" numba {m['numba']}, numpy {m['numpy']}")
    return "\n".join(lines)
