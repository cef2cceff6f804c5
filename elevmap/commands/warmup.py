"""``elevmap warmup``: compile every numba kernel the commands use, once, into the cache later runs load.

Every kernel is compiled with ``cache=True`` (:data:`noise_model.numba_config.JIT`): numba keeps the machine
code on disk and a new process loads it instead of compiling again. Where it keeps it:

* ``NUMBA_CACHE_DIR`` when that variable is set (``.ci/run`` sets it to ``.numba_cache`` in the clone);
* otherwise a ``__pycache__`` folder beside each source file (``noise_model/__pycache__``,
  ``elevmap/map/__pycache__``, ...; an editable install keeps them in the source tree), or numba's per-user
  cache folder when the source folder is not writable.

A cold cache costs tens of seconds of compilation in the first command that maps; the Makefile runs this
warm-up once after installing, with the environment later commands have, so that ``elevmap demo`` and every
command after it start mapping at once. Each group runs the public entry points on small synthetic frames
with every input type the sources hand over (uint16 depth units, float32 and float64 metres), so the
compiled signatures are the ones real runs ask for. A second warm-up compiles nothing: it loads each
kernel from the cache, and says so.

Compilation events are counted from numba's own per-dispatcher statistics (``Dispatcher.stats``:
``cache_misses`` = compiled, ``cache_hits`` = loaded from the cache) over every dispatcher of the loaded
``noise_model`` and ``elevmap`` modules.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["WARMUP_GROUPS", "WarmupStep", "warmup_steps", "run_warmup", "kernel_counts", "cache_location"]

#: The groups of :func:`run_warmup`, in order: the mapping chain every mapping command runs, the simulator of
#: ``demo``, ``simulate`` and ``compare``, the physical D435 (``--sensor stereo``, ``--reality stereo``).
WARMUP_GROUPS = ("mapping", "simulator", "stereo")


@dataclass(frozen=True)
class WarmupStep:
    """One warm-up step: a group, a label shown while it runs and the work that compiles its kernels."""

    group: str
    label: str
    run: Callable[[int], None]


def _dispatchers():
    """Every numba dispatcher held by a loaded module of ``noise_model`` or ``elevmap`` (ids deduplicated)."""
    from numba.core.dispatcher import Dispatcher

    seen = {}
    for name, module in list(sys.modules.items()):
        if module is None or not (name == "noise_model" or name.startswith(("noise_model.", "elevmap"))):
            continue
        for value in list(vars(module).values()):
            if isinstance(value, Dispatcher):
                seen[id(value)] = value
    return list(seen.values())


def kernel_counts() -> tuple[int, int]:
    """(compiled, loaded from the cache) so far in this process, summed over every signature of every
    dispatcher of the loaded ``noise_model`` and ``elevmap`` modules (numba's ``Dispatcher.stats``)."""
    compiled = loaded = 0
    for d in _dispatchers():
        stats = d.stats
        compiled += sum(stats.cache_misses.values())
        loaded += sum(stats.cache_hits.values())
    return compiled, loaded


def cache_location() -> str:
    """Where numba keeps this process's compiled kernels, in words."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        return f"{os.path.abspath(env)} (NUMBA_CACHE_DIR)"
    from .. import mapper  # noqa: F401  (loads the mapping kernels' modules)

    paths = sorted({d.stats.cache_path for d in _dispatchers()})
    example = f" (e.g. {paths[0]})" if paths else ""
    return f"__pycache__ folders beside the sources{example}"


# ---------------------------------------------------------------------------------------------------------
# The work of each group: public entry points on small synthetic frames
# ---------------------------------------------------------------------------------------------------------
#: Size of the synthetic frames [px]: small (the kernels compile per input type, not per size).
_WIDTH, _HEIGHT = 96, 60


def _floor_frame():
    """A floor seen from 0.45 m, pitched 30 deg down: (depth uint16 [mm], K, T_map_cam, pose_cov)."""
    import noise_model as nm
    from noise_model.sim import camera_extrinsics, render_floor

    K = nm.D435.intrinsics(848, 480)
    K = K * np.array([[_WIDTH / 848], [_HEIGHT / 480], [1.0]])
    T = camera_extrinsics((0.0, 0.0, 0.45), pitch_down_deg=30.0)
    z, _ = render_floor(K, _WIDTH, _HEIGHT, T, max_range_m=6.0)
    z = np.where(np.isfinite(z), z, 0.0)
    z = z + 0.002 * np.sin(np.arange(z.size).reshape(z.shape))        # not exactly planar: every branch runs
    depth = np.clip(np.round(z / 0.001), 0, 65535).astype(np.uint16)
    depth[::7, ::5] = 0
    return depth, K, T, np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5])


def _map_frames(model, dtype, nthreads: int) -> None:
    """Map the synthetic frame with ``model``, as uint16 units or float32 / float64 metres (``dtype``), with and
    without the visibility clean-up, then query the map the ways the commands do.

    The pose covariance is diagonal, absent, and (uint16 frames only, as recordings and ROS bags give them) full:
    the noise kernel compiles a loop per form, and odometry's covariance is full."""
    from ..map.elevation_map import ElevationMap
    from ..mapper import Camera, Mapper

    depth, K, T, P = _floor_frame()
    d = depth if dtype == np.uint16 else np.where(depth > 0, depth * 0.001, np.nan).astype(dtype)
    covs = (P, None)
    if dtype == np.uint16:
        P_full = P.copy()
        P_full[0, 5] = P_full[5, 0] = 1e-6
        covs = covs + (P_full,)
    for cleanup in (True, False):
        emap = ElevationMap(4.0, 0.04, visibility_cleanup=cleanup, nthreads=nthreads)
        mapper = Mapper(emap, [Camera("warmup", K, _WIDTH, _HEIGHT, model=model)], nthreads=nthreads)
        for k, pose_cov in enumerate(covs):
            emap.move_to(T[:2, 3] + 0.04 * k)
            mapper.integrate("warmup", d, T_map_cam=T, pose_cov=pose_cov, stamp=0.1 * (k + 1))
    emap.predict(np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5]), T_map_base=T, dt=0.1)
    emap.fused_map()
    emap.height_at(np.array([[0.5, 0.0], [1.0, 0.2]]))
    emap.height_scan(np.eye(4), "legged_gym")


def _paper(dtype):
    def run(nthreads: int) -> None:
        from noise_model.d435 import D435

        _map_frames(D435, dtype, nthreads)
    return run


def _mapping_disparity(nthreads: int) -> None:
    import dataclasses

    from noise_model.d435 import D435

    model = dataclasses.replace(D435, name="warmup-disparity", family="disparity")
    for dtype in (np.uint16, np.float32, np.float64):
        _map_frames(model, dtype, nthreads)


def _simulator(nthreads: int) -> None:
    from ..sources.simulated import SimulatedWalk

    for scene in ("demo", "rough"):
        for _ in SimulatedWalk(scene, n_frames=1, width=424, height=240):
            pass


def _stereo(nthreads: int) -> None:
    """A walk frame with each matcher preset, and a board before a wall as ``simulate --grid --sensor stereo``
    makes it (the board's textured materials)."""
    from noise_model.d435 import D435
    from noise_model.sim import CaptureGeometry, simulate_target_stereo
    from noise_model.sim.stereo import PRESETS, StereoD435

    from ..sources.simulated import SimulatedWalk

    for preset in sorted(PRESETS):
        for _ in SimulatedWalk("demo", n_frames=1, width=424, height=240, sensor="stereo", preset=preset):
            pass
    K = D435.intrinsics(424, 240)
    camera = {"width": 424, "height": 240, "fx": float(K[0, 0]), "fy": float(K[1, 1]), "ppx": float(K[0, 2]),
              "ppy": float(K[1, 2]), "depth_scale": 0.001, "baseline_m": D435.baseline_m}
    entry = {"id": "warmup", "background_m": 3.0, "target": {"kind": "board", "distance_m": 1.0, "yaw_deg": 30.0,
                                                             "pitch_deg": 0.0, "width_m": 0.6, "height_m": 0.9}}
    geometry = CaptureGeometry.from_capture_set_entry(camera, entry)
    simulate_target_stereo(geometry, 1, np.random.default_rng(0),
                           camera=StereoD435(424, 240, K=K, baseline_m=D435.baseline_m, nthreads=nthreads))


def warmup_steps(groups=WARMUP_GROUPS) -> list[WarmupStep]:
    """The steps of the chosen groups (see :data:`WARMUP_GROUPS`), in order."""
    groups = tuple(groups)
    unknown = [g for g in groups if g not in WARMUP_GROUPS]
    if unknown:
        raise ValueError(f"unknown warm-up group(s) {unknown}; choose from {', '.join(WARMUP_GROUPS)}")
    steps = [WarmupStep("mapping", "noise model and map, uint16 depth units (cameras, bags)", _paper(np.uint16)),
             WarmupStep("mapping", "noise model, float32 depth in metres (recordings)", _paper(np.float32)),
             WarmupStep("mapping", "noise model, float64 depth in metres", _paper(np.float64)),
             WarmupStep("mapping", "noise model, the disparity family", _mapping_disparity),
             WarmupStep("simulator", "simulated walks (ray caster, reference noise)", _simulator),
             WarmupStep("stereo", "the physical D435 (projector, infrared pair, matcher)", _stereo)]
    return [s for s in steps if s.group in groups]


def run_warmup(groups=WARMUP_GROUPS, nthreads: int | None = None, out=None) -> dict:
    """Run the warm-up steps of ``groups``, printing one line per step as it finishes.

    Parameters
    ----------
    groups : iterable of str
        Which of :data:`WARMUP_GROUPS` to warm.
    nthreads : int, optional
        numba threads of the work (compiled code does not depend on it).
    out : file or False, optional
        Where the progress lines go (standard output by default); ``False``: nowhere.

    Returns
    -------
    dict
        ``steps``: per step its label, ``compiled`` and ``loaded`` (functions compiled / loaded from the
        cache) and ``seconds``; totals ``compiled``, ``loaded``, ``seconds``; ``cache``: where the cache is.
    """
    from noise_model.numba_config import resolve_threads

    steps = warmup_steps(groups)
    n = resolve_threads(nthreads)
    stream = sys.stdout if out is None else out
    say = (lambda text, end="\n": None) if stream is False else (
        lambda text, end="\n": (stream.write(text + end), stream.flush()))
    cache = cache_location()
    say(f"numba cache: {cache}")
    t_start = time.perf_counter()
    records = []
    for k, step in enumerate(steps, 1):
        say(f"[{k}/{len(steps)}] {step.label} ... ", end="")
        c0, l0 = kernel_counts()
        t0 = time.perf_counter()
        step.run(n)
        seconds = time.perf_counter() - t0
        c1, l1 = kernel_counts()
        rec = {"group": step.group, "label": step.label, "compiled": c1 - c0, "loaded": l1 - l0,
               "seconds": round(seconds, 3)}
        records.append(rec)
        say(f"{_counts_text(rec['compiled'], rec['loaded'])} in {seconds:.1f} s")
    total = {"compiled": sum(r["compiled"] for r in records), "loaded": sum(r["loaded"] for r in records)}
    seconds = time.perf_counter() - t_start
    say(f"warm-up done in {seconds:.1f} s: {_counts_text(total['compiled'], total['loaded'])}"
        + ("" if total["compiled"] else " (the cache was already warm)"))
    return {"steps": records, **total, "seconds": round(seconds, 3), "cache": cache}


def _counts_text(compiled: int, loaded: int) -> str:
    parts = []
    if compiled:
        parts.append(f"compiled {compiled} function{'s' * (compiled != 1)}")
    if loaded:
        parts.append(f"loaded {loaded} from the cache")
    return ", ".join(parts) or "nothing new (already in this process)"
