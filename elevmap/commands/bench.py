"""``elevmap bench``: per-frame timings of the compiled kernels against their NumPy references.

Speed is measured here, never in the test suite. Each record is the median over many frames after
warm-up (numba compilation excluded), with the NumPy reference measured in the same run on the same
frames, so ratios are comparable across machines. The physical D435 (``stereo``: render both infrared
images and the projector's view, sensor noise, matching) has no NumPy reference of the whole chain
(its stages' references are compared in the tests); its records carry the time each frame may take,
``target_ms`` (:data:`STEREO_TARGET_MS`), instead.
"""

from __future__ import annotations

import os
import platform
import time

import numba
import numpy as np

import noise_model as nm
from noise_model.kernels import STAGES, depth_to_map_points_by_stage
from noise_model.numba_config import resolve_threads
from noise_model.sim import (
    DEFAULT_T_BASE_CAM, Scene, camera_extrinsics, render_depth, render_depth_reference, render_floor,
    render_planar_target, walk,
)
from noise_model.valid_margin import drop_valid_margin

from ..map import fusion, queries
from ..map.elevation_map import ElevationMap
from ..map.floor import FloorWorkspace, fuse_floor, fuse_floor_reference
from ..mapper import Camera, Mapper
from .bench_run import RUN_ROUNDS, bench_run, run_lines

__all__ = ["bench_scene", "floor_scene", "update_scene", "run_bench", "format_table", "GROUPS", "STEREO_TARGET_MS"]

SIZES = ((848, 480), (424, 240))
#: The pose covariance every bench frame is mapped with: 1 cm of translation, 3 mrad of rotation, diagonal
#: (translation [m^2], rotation [rad^2]), as an odometry's.
POSE_COV = np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5])


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
    return d, 0.001, K, T, POSE_COV.copy()


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


GROUPS = ("noise", "mapper", "physical", "update", "move_to", "height_scan", "first_frame", "render", "stereo", "ros",
          "run")
MAPPER_SIZES = ((1280, 720), (848, 480), (424, 240))
#: Sizes of the ``update`` and ``floor`` records (points per frame: every pixel of the image).
UPDATE_SIZES = ((848, 480), (424, 240))
#: Frames of the ``run`` records' recording (848x480 at 30 Hz), at most (``--frames`` when fewer, at least 10).
RUN_FRAMES = 90
#: The physical D435's time budget per frame [ms] at each size (width, height) on a 2-core machine.
STEREO_TARGET_MS = {(424, 240): 150.0, (848, 480): 600.0}
#: Timed frames of the physical D435 per size, at most (a frame takes a tenth of a second or more).
STEREO_MAX_FRAMES = 10


def floor_scene(width: int, height: int, seed: int = 0):
    """A legged robot's view: the floor from a D435 0.45 m up, pitched 30 deg down, paper noise, 2 % holes.

    Returns (depth uint16, K, T_map_cam, pose_cov)."""
    rng = np.random.default_rng(seed)
    K = nm.D435.intrinsics(width, height)
    T = camera_extrinsics((0.0, 0.0, 0.45), pitch_down_deg=30.0)
    z, theta = render_floor(K, width, height, T, max_range_m=6.0)
    hit = np.isfinite(z)
    z = np.where(hit, z + rng.normal(size=z.shape) * nm.axial_sigma(np.where(hit, z, 1.0), np.where(hit, theta, 0.0)),
                 0.0)
    d = np.clip(np.round(np.maximum(z, 0.0) / 0.001), 0, 65535).astype(np.uint16)
    d[rng.random(d.shape) < 0.02] = 0
    return d, K, T, POSE_COV.copy()


def update_scene(width: int, height: int):
    """Map-frame points as a user with their own point clouds passes them to ``ElevationMap.update``: a floor and
    three boxes (0.15-0.3 m) seen by a D435 0.5 m up, pitched 40 deg down, every pixel valid, noise-free.

    Returns (points_map (N, 3) float64 row-ordered [m], height_var (N,) = 0.05 z^2 [m^2] with z the depth
    (elevation_mapping_cupy's default point variance), T_map_cam (4, 4)).
    """
    from noise_model.geometry import deproject
    from noise_model.sim import Box

    scene = Scene([Box(centre=(1.2, 0.3, 0.1), size=(0.4, 0.4, 0.2)),
                   Box(centre=(1.6, -0.4, 0.15), size=(0.5, 0.3, 0.3)),
                   Box(centre=(2.2, 0.2, 0.075), size=(0.6, 0.6, 0.15), yaw_deg=25.0)], ground_z=0.0)
    K = nm.D435.intrinsics(width, height)
    T = camera_extrinsics((0.0, 0.0, 0.5), pitch_down_deg=40.0)
    z, _ = render_depth(scene, K, width, height, T, max_range_m=20.0)
    points_cam = deproject(z, K).reshape(-1, 3)
    points_map = np.ascontiguousarray(points_cam @ T[:3, :3].T + T[:3, 3])
    return points_map, 0.05 * z.reshape(-1) ** 2, T


def _record(name, width, height, impl, ms, items, frames, threads, **extra):
    r = {"name": name, "width": width, "height": height, "impl": impl, "median_ms": round(ms, 4),
         "points_per_s": round(items / (ms * 1e-3)) if ms > 0 else None, "points": items, "frames": frames,
         "threads": threads}
    r.update(extra)
    return r


def _stage_ms(d, K, T, P, scale, ws, frames, n, bar) -> dict:
    """{stage: median ms} of the noise kernel's stages, each launched and timed alone, on one frame."""
    seconds = {stage: [] for stage in STAGES}

    def staged():          # the same kernels launched one at a time, each stage timed alone
        for stage, sec in depth_to_map_points_by_stage(d, K, T, P, depth_scale=scale, workspace=ws,
                                                       nthreads=n)[1].items():
            seconds[stage].append(sec)

    _median_ms(staged, frames, 2, bar)
    return {stage: round(1e3 * float(np.median(sec[2:])), 4) for stage, sec in seconds.items()}


def _bench_noise(frames, reference_frames, n, bar):
    """The noise kernel on :func:`bench_scene`'s board next to its NumPy reference, each stage timed alone; the
    numba records also carry ``mapper_frame_stages`` [ms] and ``mapper_frame_points``: the same stages on the
    mapper's frame (:func:`floor_scene` after the mapper's valid-region margin), so that what makes the two
    frames' costs differ (points per frame, windows of two surfaces that take the medians) is read off one run."""
    out = []
    for width, height in SIZES:
        d, scale, K, T, P = bench_scene(width, height)
        ws = nm.Workspace(height, width)
        npts = len(nm.depth_to_map_points(d, K, T, P, depth_scale=scale, workspace=ws, nthreads=n).pixel)
        fast = _median_ms(lambda: nm.depth_to_map_points(d, K, T, P, depth_scale=scale, workspace=ws,
                                                         nthreads=n), frames, 5, bar)
        stages = _stage_ms(d, K, T, P, scale, ws, frames, n, bar)
        fd, fK, fT, fP = floor_scene(width, height)
        fd = drop_valid_margin(fd, Camera("d435", fK, width, height).valid_margin_px, nthreads=n)
        mapper_frame_points = len(nm.depth_to_map_points(fd, fK, fT, fP, depth_scale=0.001, workspace=ws,
                                                         nthreads=n).pixel)
        mapper_frame_stages = _stage_ms(fd, fK, fT, fP, 0.001, ws, frames, n, bar)
        ref = _median_ms(lambda: nm.depth_to_map_points_reference(d, K, T, P, depth_scale=scale),
                         reference_frames, 1, bar)
        out.append(_record("noise", width, height, "numba", fast, npts, frames, n, stages=stages,
                           mapper_frame_stages=mapper_frame_stages, mapper_frame_points=mapper_frame_points))
        out.append(_record("noise", width, height, "numpy", ref, npts, reference_frames, 1))
    return out


def _time_mapper(d, camera, T, P, cleanup, impl, nf, n, bar):
    """A Mapper with one camera on an 8 m map at 0.04 m (``cleanup``: the visibility clean-up on) fed the same
    frame ``d`` over and over: (median ms per frame, points per frame, {"noise_ms", "fusion_ms"}: the frame's
    split into the noise model and the map (fusion, clean-up, neighbourhood spread), the mapper)."""
    mapper = Mapper(ElevationMap(8.0, 0.04, visibility_cleanup=cleanup, nthreads=n), [camera], nthreads=n)
    k = [0]
    split = {"noise_ms": [], "fusion_ms": []}

    def frame():
        k[0] += 1
        stats = mapper.integrate(camera.name, d, T_map_cam=T, pose_cov=P, stamp=0.033 * k[0], impl=impl)
        for key, values in split.items():
            values.append(stats[key])
        return stats

    npts = frame()["points"]
    ms = _median_ms(frame, nf, 2 if impl == "numba" else 0, bar)
    parts = {key: round(float(np.median(values[-nf:])), 4) for key, values in split.items()}
    return ms, npts, parts, mapper


def _bench_mapper(frames, reference_frames, n, bar):
    out = []
    for width, height in MAPPER_SIZES:
        d, K, T, P = floor_scene(width, height)
        camera = Camera("d435", K, width, height)
        for name, cleanup in (("mapper", False), ("mapper_cleanup", True)):
            for impl, nf in (("numba", frames), ("numpy", reference_frames)):
                ms, npts, parts, mapper = _time_mapper(d, camera, T, P, cleanup, impl, nf, n, bar)
                if impl == "numba":        # the noise model's first pass alone: the valid-region margin
                    margin = camera.valid_margin_px
                    parts["margin_ms"] = round(_median_ms(lambda: drop_valid_margin(d, margin, nthreads=n), nf, 2), 4)
                out.append(_record(name, width, height, impl, ms, npts, nf, n if impl == "numba" else 1,
                                   map_cells=mapper.map.n ** 2, resolution_m=0.04, **parts))
    return out


def _box_view():
    """The physical D435's bench scene: the floor and a 0.3 m box, seen from 0.45 m up, pitched 30 deg down
    (a legged robot's view). Returns (scene, T_map_cam)."""
    from noise_model.sim import Box

    scene = Scene([Box(centre=(1.5, 0.2, 0.15), size=(0.4, 0.4, 0.3))], ground_z=0.0)
    return scene, camera_extrinsics((0.0, 0.0, 0.45), pitch_down_deg=30.0)


def physical_scene(width: int, height: int, seed: int = 0):
    """A legged robot's view as the physical D435 makes it (:func:`_box_view`, the ``stereo`` records' scene;
    projector, infrared pair and matching, so that its noise, correlated over a few pixels, emerges instead of
    being drawn per pixel).

    Returns (depth uint16 [mm], K, T_map_cam, pose_cov), as :func:`floor_scene`."""
    from noise_model.sim.stereo import StereoD435

    scene, T = _box_view()
    cam = StereoD435(width, height)
    depth = cam.depth_frame(scene, T, np.random.default_rng(seed))
    return depth, np.asarray(cam.K, dtype=np.float64), T, POSE_COV.copy()


def _bench_physical(frames, reference_frames, n, bar, sizes=SIZES):
    """The mapper (valid-region margin, noise model, fusion and spreads; ``mapper_physical_cleanup``: and the
    visibility clean-up) on :func:`physical_scene`'s frame next to its NumPy reference. The ``mapper_physical``
    numba records also carry the noise kernel's stages timed alone on that frame (``stages``) and the share of
    valid pixels the noise model finds in windows of two surfaces (``mixed_share``).

    This is the mapper's cost on depth whose noise the sensor model did not write: the ``mapper`` records' floor
    carries the paper's noise, drawn pixel by pixel, under which almost no window is mixed."""
    out = []
    for width, height in sizes:
        d, K, T, P = physical_scene(width, height)
        cam = Camera("d435", K, width, height)
        dm = drop_valid_margin(d, cam.valid_margin_px, nthreads=n)
        valid = dm > 0
        mixed = nm.mixed_windows(nm.deproject(np.where(valid, dm * 0.001, np.nan), K))
        share = float(mixed[valid].mean()) if valid.any() else 0.0
        ws = nm.Workspace(height, width)
        stages = _stage_ms(dm, K, T, P, 0.001, ws, frames, n, bar)
        for name, cleanup in (("mapper_physical", False), ("mapper_physical_cleanup", True)):
            for impl, nf in (("numba", frames), ("numpy", reference_frames)):
                ms, npts, parts, mapper = _time_mapper(d, cam, T, P, cleanup, impl, nf, n, bar)
                extra = dict(stages=stages, mixed_share=round(share, 4)) if impl == "numba" and not cleanup else {}
                out.append(_record(name, width, height, impl, ms, npts, nf, n if impl == "numba" else 1,
                                   map_cells=mapper.map.n ** 2, resolution_m=0.04, **parts, **extra))
    return out


def _bench_update(frames, reference_frames, n, bar):
    """``ElevationMap.update`` of map-frame points (:func:`update_scene`) next to its NumPy reference and the
    compute floor (:func:`elevmap.map.floor.fuse_floor`: information-form sums per cell, nothing else) on the same
    points, and each stage of the update timed alone (``stages`` [ms]): the check of the points' values (the first
    pass with it less without it), gating and accumulation (the first pass), the cell merge (spread, change rule,
    bounds; the fusion less its first pass), the neighbourhood spread, and the visibility clean-up (an update with
    the camera's origin, as the mapper runs it, less one without: ``cleanup_ms`` is the update with it)."""
    from noise_model.numba_config import threads

    out = []
    for width, height in UPDATE_SIZES:
        pts, var, T = update_scene(width, height)
        origin = T[:3, 3].copy()
        emap = ElevationMap(8.0, 0.04, nthreads=n)
        k = [0]

        def update(impl="numba", m=emap, sensor_origin=None):
            k[0] += 1
            return m.update(pts, var, stamp=0.033 * k[0], sensor_origin_map=sensor_origin, impl=impl)

        extra = dict(map_cells=emap.n ** 2, resolution_m=0.04, layout="row-ordered (N, 3)")
        # without and with the clean-up frame by frame, so that both see the same state of the machine
        paired = {"without": [], "with": []}

        def pair():
            for key, o in (("without", None), ("with", origin)):
                t0 = time.perf_counter()
                update(sensor_origin=o)
                paired[key].append(time.perf_counter() - t0)

        _median_ms(pair, frames, 3, bar)
        ms, ms_cleanup = (1e3 * float(np.median(paired[key][-frames:])) for key in ("without", "with"))
        fp, g, ws = emap.fusion_params, emap.geometry, emap._ws
        packed = fp.array(g.resolution_m)
        with threads(n):
            box = fusion.accumulate(emap.data, g, pts, var, None, packed, ws)
            stage = {"gating_accumulation": _median_ms(lambda: fusion.accumulate(emap.data, g, pts, var, None, packed,
                                                                                 ws, check=False), frames, 3, bar)}
            checked = _median_ms(lambda: fusion.accumulate(emap.data, g, pts, var, None, packed, ws), frames, 3, bar)
        fused = _median_ms(lambda: fusion.fuse_frame(emap.data, g, pts, var, None, 0.033 * k[0], fp, ws, n), frames,
                           3, bar)
        stage["validation"] = max(checked - stage["gating_accumulation"], 0.0)
        stage["cell_merge"] = max(fused - checked, 0.0)
        stage["neighbour_spread"] = _median_ms(lambda: emap._neighbours(box, None, "numba"), frames, 3, bar)
        stage["cleanup"] = max(ms_cleanup - ms, 0.0)
        stages = {key: round(stage[key], 4) for key in ("validation", "gating_accumulation", "cell_merge",
                                                        "neighbour_spread", "cleanup")}
        ref_map = ElevationMap(8.0, 0.04, nthreads=n)
        ref = _median_ms(lambda: update("numpy", ref_map), reference_frames, 1, bar)
        floor_map = ElevationMap(8.0, 0.04, nthreads=n)
        fws = FloorWorkspace(floor_map.n)
        floor = _median_ms(lambda: fuse_floor(floor_map.data, floor_map.geometry, pts, var, fws, n), frames, 3, bar)
        floor_ref = _median_ms(lambda: fuse_floor_reference(floor_map.data, floor_map.geometry, pts, var),
                               reference_frames, 1, bar)
        npts = len(pts)
        out += [_record("update", width, height, "numba", ms, npts, frames, n, stages=stages,
                        cleanup_ms=round(ms_cleanup, 4), floor_ratio=round(ms / floor, 2), **extra),
                _record("update", width, height, "numpy", ref, npts, reference_frames, 1, **extra),
                _record("floor", width, height, "numba", floor, npts, frames, n, **extra),
                _record("floor", width, height, "numpy", floor_ref, npts, reference_frames, 1, **extra)]
    return out


def _bench_move_to(frames, n, bar):
    m = ElevationMap(8.0, 0.04, nthreads=n)
    m.data[:] = 1.0
    k = [0]

    def step():                       # one cell diagonally per call, as a walking robot's map moves
        k[0] += 1
        m.move_to((0.04 * k[0], 0.04 * k[0]))

    ms = _median_ms(step, frames, 5, bar)
    return [_record("move_to", m.n, m.n, "numpy", ms, 2 * m.n, frames, 1, map_cells=m.n ** 2, shift_cells=[1, 1])]


def _bench_height_scan(frames, n, bar):
    m = ElevationMap(8.0, 0.04, nthreads=n)
    xs, ys = m.cell_centres()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    m.update(np.column_stack([X.ravel(), Y.ravel(), 0.1 * np.sin(X.ravel()) * np.cos(Y.ravel())]),
             np.full(X.size, 1e-4))
    T = np.eye(4)
    feet = np.array([[0.3, 0.2, -0.45], [0.3, -0.2, -0.45], [-0.3, 0.2, -0.45], [-0.3, -0.2, -0.45]])
    scan = m.height_scan(T, "foot_rings", feet_base=feet)
    xy = np.vstack([scan.points_map, m.height_scan(T, "legged_gym").points_map])     # 208 + 187 samples
    out = []
    for impl, fn, nf in (("numba", queries.height_at, frames), ("numpy", queries.height_at_reference, frames)):
        ms = _median_ms(lambda: fn(m, xy), nf, 5, bar)
        out.append(_record("height_scan", len(xy), 1, impl, ms, len(xy), nf, n if impl == "numba" else 1,
                           patterns="foot_rings (4 feet) + legged_gym"))
    return out


def _bench_render(frames, n, bar):
    """``render_depth`` of the stairs scene at 848x480 (numba) against its NumPy reference (1 frame)."""
    scene = Scene.stairs_scene()
    K = nm.D435.intrinsics(848, 480)
    T = walk([[0.0, 0.0], [1.0, 0.0]], scene=scene)[0] @ DEFAULT_T_BASE_CAM
    hits = int(np.isfinite(render_depth(scene, K, 848, 480, T, nthreads=n)[0]).sum())
    fast = _median_ms(lambda: render_depth(scene, K, 848, 480, T, nthreads=n), frames, 5, bar)
    ref = _median_ms(lambda: render_depth_reference(scene, K, 848, 480, T), 1, 0, bar)
    return [_record("render", 848, 480, "numba", fast, hits, frames, n, scene="stairs"),
            _record("render", 848, 480, "numpy", ref, hits, 1, 1, scene="stairs")]


def _bench_stereo(frames, n, bar):
    """The physical D435 per frame at 424x240 and 848x480 on :func:`_box_view` (render at the pose, then sensor
    noise and matching)."""
    from noise_model.sim.stereo import StereoD435

    scene, T = _box_view()
    out = []
    for (width, height), target in STEREO_TARGET_MS.items():
        cam = StereoD435(width, height, nthreads=n)
        rng = np.random.default_rng(0)
        parts = {"render": [], "match": []}

        def frame():
            t0 = time.perf_counter()
            ir = cam.render(scene, T)
            t1 = time.perf_counter()
            cam.frame(ir, rng)
            parts["render"].append(t1 - t0)
            parts["match"].append(time.perf_counter() - t1)

        nf = min(frames, STEREO_MAX_FRAMES)
        ms = _median_ms(frame, nf, 1, bar)
        valid = int((cam.frame(cam.render(scene, T), rng).depth > 0).sum())
        out.append(_record("stereo", width, height, "numba", ms, valid, nf, n, target_ms=target,
                           render_ms=round(1e3 * float(np.median(parts["render"][-nf:])), 4),
                           noise_and_match_ms=round(1e3 * float(np.median(parts["match"][-nf:])), 4)))
    return out


#: Time one map may take to become a ROS message [ms]: a 200 x 200 map with 8 layers, from the map to bytes.
ROS_TARGET_MS = 2.0
#: The layers of the ROS records (the eight first of the map's layers).
_ROS_LAYERS = 8


def _bench_ros(frames, n, bar):
    """A 200 x 200 map (8 m at 4 cm) with 8 layers, after one floor frame, to a ROS message's bytes: the export
    (``to_grid_map``), then the ``grid_map_msgs/GridMap`` (ROS 2 CDR and ROS 1) and ``foxglove_msgs/Grid``."""
    from ..map.layers import LAYERS
    from ..ros.convert import grid_map_message, grid_message
    from ..ros.msgs import serialize

    d, K, T, P = floor_scene(848, 480)
    emap = ElevationMap(8.0, 0.04, nthreads=n)
    Mapper(emap, [Camera("d435", K, 848, 480)], nthreads=n).integrate("d435", d, T_map_cam=T, pose_cov=P, stamp=1.0)
    layers = LAYERS[:_ROS_LAYERS]
    cells = emap.n * emap.n * len(layers)
    cases = {"ros_export": lambda: emap.to_grid_map(layers),
             "ros_gridmap_ros2": lambda: serialize(grid_map_message(emap.to_grid_map(layers), 2), 2),
             "ros_gridmap_ros1": lambda: serialize(grid_map_message(emap.to_grid_map(layers), 1), 1),
             "ros_grid": lambda: serialize(grid_message(emap.to_grid_map(layers), 2), 2)}
    out = []
    for name, fn in cases.items():
        ms = _median_ms(fn, frames, 3, bar)
        extra = {} if name == "ros_export" else {"target_ms": ROS_TARGET_MS, "bytes": len(fn())}
        out.append(_record(name, emap.n, emap.n, "python" if extra else "numpy", ms, cells, frames, n,
                           layers=len(layers), **extra))
    return out


_FIRST_FRAME = r"""
import time
t0 = time.perf_counter()
import numpy as np
from elevmap import Camera, ElevationMap, Mapper
from elevmap.commands.bench import floor_scene
d, K, T, P = floor_scene(848, 480)
mapper = Mapper(ElevationMap(8.0, 0.04), [Camera("d435", K, 848, 480)])
t1 = time.perf_counter()
mapper.integrate("d435", d, T_map_cam=T, pose_cov=P, stamp=0.0)
t2 = time.perf_counter()
print(t2 - t1, t2 - t0)
"""


def _bench_first_frame(bar):
    """First frame of a fresh process, with an empty numba cache (cold) and then with it filled (warm)."""
    import subprocess
    import sys
    import tempfile

    out = []
    with tempfile.TemporaryDirectory(prefix="elevmap-numba-cache-") as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for name in ("first_frame_cold", "first_frame_warm"):
            t0 = time.perf_counter()
            res = subprocess.run([sys.executable, "-c", _FIRST_FRAME], env=env, capture_output=True, text=True)
            wall = time.perf_counter() - t0
            if res.returncode != 0:
                raise RuntimeError(f"{name} failed: {res.stderr.strip()[-500:]}")
            first, since_start = (float(v) for v in res.stdout.split())
            out.append({"name": name, "width": 848, "height": 480, "impl": "numba", "seconds": round(first, 3),
                        "seconds_since_import": round(since_start, 3), "process_seconds": round(wall, 3)})
            bar.update(1)
    return out


def run_bench(frames: int = 200, reference_frames: int = 10, nthreads: int | None = None,
              show_progress: bool = True, groups=GROUPS) -> dict:
    """Time the compiled kernels and their NumPy references in the same run.

    Parameters
    ----------
    frames, reference_frames : int
        Timed calls per record for the numba kernels / the NumPy references (the mapper's NumPy
        reference takes at most 3: it needs about a second per 848x480 frame; the physical D435 at
        most :data:`STEREO_MAX_FRAMES`).
    nthreads : int, optional
        numba threads (all by default).
    groups : iterable of str
        Which of ``GROUPS`` to run.

    Returns
    -------
    dict
        ``{"results": [{"name", "width", "height", "impl", "median_ms", "points_per_s", "frames",
        "threads", ...}, ...], "machine": {...}}``; the ``noise`` numba records carry ``stages`` [ms], each stage of
        :data:`noise_model.kernels.STAGES` timed alone, and ``mapper_frame_stages`` [ms], ``mapper_frame_points``:
        the same on the mapper's floor frame (:func:`_bench_noise`); ``run``/``run_rrd`` records ``frames_per_s`` end to end and
        ``split_ms`` (:mod:`elevmap.commands.bench_run`); the ``update`` numba records ``stages`` [ms] (the map's
        fusion stage by stage, :func:`_bench_update`), ``floor_ratio`` (to the ``floor`` record of the same points)
        and ``cleanup_ms``; the ``mapper*`` records ``noise_ms`` and ``fusion_ms`` (a frame's split; the numba ones
        also ``margin_ms``, the valid-region margin of ``noise_ms`` timed alone);
        ``mapper_physical*`` records the same on the physical D435's frame, the first numba ones with ``stages``
        and ``mixed_share`` (:func:`_bench_physical`); ``first_frame_*`` records carry ``seconds``, ``stereo``
        records ``target_ms``, ``render_ms`` and ``noise_and_match_ms`` (points: its valid pixels).
    """
    from tqdm import tqdm

    groups = tuple(groups)
    unknown = set(groups) - set(GROUPS)
    if unknown:
        raise ValueError(f"unknown bench group(s) {sorted(unknown)}; choose from {', '.join(GROUPS)}")
    n = resolve_threads(nthreads)
    map_ref = min(reference_frames, 3)
    total = (("noise" in groups) * len(SIZES) * (3 * frames + reference_frames)
             + ("mapper" in groups) * len(MAPPER_SIZES) * 2 * (frames + map_ref)
             + ("physical" in groups) * len(SIZES) * (3 * frames + 2 * map_ref)
             + ("update" in groups) * len(UPDATE_SIZES) * (6 * frames + 2 * reference_frames)
             + ("move_to" in groups) * frames + ("height_scan" in groups) * 2 * frames
             + ("first_frame" in groups) * 2 + ("render" in groups) * (frames + 1) + ("run" in groups) * 2 * RUN_ROUNDS
             + ("stereo" in groups) * len(STEREO_TARGET_MS) * min(frames, STEREO_MAX_FRAMES)
             + ("ros" in groups) * 4 * frames)
    results = []
    with tqdm(total=total, desc="bench", unit="call", disable=not show_progress, leave=False) as bar:
        if "noise" in groups:
            results += _bench_noise(frames, reference_frames, n, bar)
        if "mapper" in groups:
            results += _bench_mapper(frames, map_ref, n, bar)
        if "physical" in groups:
            results += _bench_physical(frames, map_ref, n, bar)
        if "update" in groups:
            results += _bench_update(frames, reference_frames, n, bar)
        if "move_to" in groups:
            results += _bench_move_to(frames, n, bar)
        if "height_scan" in groups:
            results += _bench_height_scan(frames, n, bar)
        if "first_frame" in groups:
            results += _bench_first_frame(bar)
        if "render" in groups:
            results += _bench_render(frames, n, bar)
        if "stereo" in groups:
            results += _bench_stereo(frames, n, bar)
        if "ros" in groups:
            results += _bench_ros(frames, n, bar)
        if "run" in groups:
            results += bench_run(max(10, min(frames, RUN_FRAMES)), n, bar)
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
    """A plain-text table of a bench report, with the numba/NumPy speed-up per record."""
    rows = report["results"]
    lines = [f"{'record':<24}{'size':>11}{'impl':>7}{'median ms':>11}{'Mpoints/s':>11}{'speed-up':>10}"]
    for r in rows:
        size = f"{r['width']}x{r['height']}"
        if "seconds" in r:
            lines.append(f"{r['name']:<24}{size:>11}{r['impl']:>7}{'':>11}{'':>11}   first frame {r['seconds']:.2f} s"
                         f" (process {r['process_seconds']:.1f} s)")
            continue
        ref = next((x for x in rows if x["name"] == r["name"] and x["width"] == r["width"]
                    and x["height"] == r["height"] and x["impl"] == "numpy"), None)
        speed = f"{ref['median_ms'] / r['median_ms']:.1f}x" if ref and r["impl"] != "numpy" else ""
        if "target_ms" in r:
            speed = f"<= {r['target_ms']:.0f}"
        pps = "" if r.get("points_per_s") is None else f"{r['points_per_s'] / 1e6:.2f}"
        lines.append(f"{r['name']:<24}{size:>11}{r['impl']:>7}{r['median_ms']:>11.3f}{pps:>11}{speed:>10}")
    for r in rows:
        if r["name"] == "noise" and r["impl"] == "numba" and "stages" in r:
            st = ", ".join(f"{k} {v:.2f}" for k, v in r["stages"].items())
            lines.append(f"noise {r['width']}x{r['height']}: stages alone [ms]: {st} (sum "
                         f"{sum(r['stages'].values()):.2f})")
            if "mapper_frame_stages" in r:
                st = ", ".join(f"{k} {v:.2f}" for k, v in r["mapper_frame_stages"].items())
                lines.append(f"noise {r['width']}x{r['height']}, the mapper's floor frame "
                             f"({r['mapper_frame_points']} points, "
                             f"the board {r['points']}): stages alone [ms]: {st} (sum "
                             f"{sum(r['mapper_frame_stages'].values()):.2f})")
    for r in rows:
        if r["name"] == "mapper_physical" and r["impl"] == "numba" and "stages" in r:
            st = ", ".join(f"{k} {v:.2f}" for k, v in r["stages"].items())
            lines.append(f"mapper_physical {r['width']}x{r['height']}: the physical D435's frame "
                         f"({r['points']} points, {100 * r['mixed_share']:.0f} % of them in windows of two surfaces); "
                         f"noise kernel's stages alone [ms]: {st} (sum {sum(r['stages'].values()):.2f})")
    for r in rows:
        if r["name"].startswith("mapper") and r["impl"] == "numba" and "fusion_ms" in r:
            margin = f" (valid-region margin {r['margin_ms']:.2f} ms)" if "margin_ms" in r else ""
            lines.append(f"{r['name']} {r['width']}x{r['height']}: noise model {r['noise_ms']:.2f} ms{margin}, map "
                         f"{r['fusion_ms']:.2f} ms")
        if r["name"] == "update" and r["impl"] == "numba":
            st = ", ".join(f"{k} {v:.2f}" for k, v in r["stages"].items())
            lines.append(f"update {r['width']}x{r['height']}: {r['floor_ratio']:.1f}x the floor; with clean-up "
                         f"{r['cleanup_ms']:.2f} ms; stages alone [ms]: {st}")
    lines += run_lines(rows)
    if any(r["name"] == "stereo" for r in rows):
        lines.append("stereo: the physical D435, one frame (render, sensor noise, matching); "
                     "last column: its budget [ms]")
    if any(r["name"].startswith("ros_") for r in rows):
        lines.append("ros_*: a 200x200 map with 8 layers: the export (to_grid_map), then from the map to the bytes "
                     "of a GridMap (ROS 2, ROS 1) or foxglove Grid; last column: the budget [ms]")
    m = report["machine"]
    lines.append(f"machine: {m['cpu']}, {m['cores']} cores, {m['threads']} numba threads ({m['threading_layer']}),"
                 f" numba {m['numba']}, numpy {m['numpy']}")
    return "\n".join(lines)
