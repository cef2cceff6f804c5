"""What `elevmap run --rrd` logs: every frame's depth and pose, the views at the stated rate; the map does not
depend on what is logged."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pytest
from rerun.chunk import RrdReader

from elevmap import pipeline
from elevmap.cli import main
from elevmap.frame import Frame
from elevmap.pipeline import MappingConfig, run_mapping
from elevmap.sources.rrd import read_rrd_frames
from noise_model import D435
from noise_model.sim.targets import camera_extrinsics, render_floor

W, H = 106, 60
K = D435.intrinsics(424, 240) * np.array([[0.25], [0.25], [1.0]])


def floor_frames(n, rate_hz=30.0, seed=0):
    """n frames of a floor, the camera moving 2 cm per frame, stamped at ``rate_hz``."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        T = camera_extrinsics((0.02 * i, 0.0, 0.45), 30.0, 2.0 * i)
        z, _ = render_floor(K, W, H, T)
        z = z + rng.normal(0, 0.004, z.shape)
        d = np.where(np.isfinite(z), np.round(z / 0.001), 0).astype(np.uint16)
        out.append(Frame(d, K, 0.001, 50.0 + i / rate_hz, T_map_cam=T, pose_cov=np.eye(6) * 1e-6, index=i,
                         camera="front"))
    return out


def logged_frames(path) -> dict:
    """entity -> component -> sorted frame indices at which it was logged (the "frame" timeline)."""
    out = defaultdict(lambda: defaultdict(list))
    for ch in RrdReader(str(path)).stream():
        if ch.is_static or "frame" not in ch.timeline_names:
            continue
        rb = ch.to_record_batch()
        frames = rb.column("frame").to_pylist()
        for name in rb.schema.names:
            if ":" not in name:
                continue
            col = rb.column(name)
            for r, f in enumerate(frames):
                if col[r].is_valid:
                    out[ch.entity_path][name].append(f)
    return {e: {c: sorted(v) for c, v in comps.items()} for e, comps in out.items()}


def test_depth_every_frame_views_at_the_stated_rate_and_the_map_is_the_same(tmp_path):
    frames = floor_frames(12)                     # 30 Hz stamps: 10 Hz views = every third frame
    cfg = MappingConfig(length_m=3.0, view_rate_hz=10.0, mesh_every=2)
    path = tmp_path / "run.rrd"
    logged = run_mapping(frames, cfg, rrd_path=path, show_progress=False)
    plain = run_mapping(frames, cfg, show_progress=False)
    np.testing.assert_array_equal(logged["map"].data, plain["map"].data)
    got = logged_frames(path)
    assert got["/world/front/depth"]["DepthImage:buffer"] == list(range(12))      # raw depth by default
    assert got["/world/front"]["Transform3D:translation"] == list(range(12))
    assert got["/plots/time/ms_per_frame"]["Scalars:scalars"] == list(range(12))
    assert got["/world/points/front"]["Points3D:positions"] == [0, 3, 6, 9]
    assert got["/world/points_cov/front"]["Ellipsoids3D:centers"] == [0, 3, 6, 9]
    assert got["/plots/cells/known"]["Scalars:scalars"] == [0, 3, 6, 9]
    assert got["/world/map/elevation"]["Mesh3D:vertex_positions"] == [0, 6, 11]   # every 2nd view, and the end
    # the replay maps the same frames into the same map
    again = run_mapping(read_rrd_frames(path), cfg, show_progress=False)
    np.testing.assert_array_equal(again["map"].data, plain["map"].data)
    # the split of the run's time adds up
    s = logged["seconds"]
    assert s["logging"] > 0 and plain["seconds"]["logging"] == 0
    assert sum(v for k, v in s.items() if k != "total") <= s["total"] + 1e-9
    assert logged["frames_per_s"] == pytest.approx(12 / s["total"])


def test_a_view_rate_above_the_frame_rate_logs_every_frame_and_png_depth_replays(tmp_path):
    frames = floor_frames(5)
    path = tmp_path / "run.rrd"
    run_mapping(frames, MappingConfig(length_m=3.0, view_rate_hz=1000.0, png_depth=True), rrd_path=path,
                show_progress=False)
    got = logged_frames(path)
    assert got["/world/points/front"]["Points3D:positions"] == list(range(5))
    assert got["/world/front/depth"]["EncodedDepthImage:blob"] == list(range(5))
    for f, g in zip(frames, read_rrd_frames(path)):
        np.testing.assert_array_equal(f.depth, g.depth)


def test_jittered_stamps_give_one_view_per_slot_and_the_trail_has_no_gaps(tmp_path, monkeypatch):
    monkeypatch.setattr(pipeline, "TRAIL_PIECE", 4)
    jitter = np.array([0.0, 0.004, -0.003, 0.002, -0.004, 0.003, 0.0, -0.002, 0.004, 0.001, -0.001])
    frames = [Frame(f.depth, f.K, f.depth_scale, f.stamp + j, T_map_cam=f.T_map_cam, index=f.index, camera="front")
              for f, j in zip(floor_frames(11, rate_hz=20.0), jitter)]
    path = tmp_path / "run.rrd"
    run_mapping(frames, MappingConfig(length_m=3.0, view_rate_hz=5.0), rrd_path=path, show_progress=False)
    got = logged_frames(path)
    # 20 Hz frames, 5 Hz views: slots [0, 0.2), [0.2, 0.4), ... after the first stamp; frame 4 is 4 ms early
    assert got["/world/points/front"]["Points3D:positions"] == [0, 5, 8]
    strips = []
    for ch in RrdReader(str(path)).stream():
        if ch.entity_path.startswith("/world/trail/"):
            rb = ch.to_record_batch()
            for r in range(rb.num_rows):
                strips.append((int(ch.entity_path.rsplit("/", 1)[1]), rb.column("frame")[r].as_py(),
                               np.array(rb.column("LineStrips3D:strips")[r].as_py()[0])))
    last = {}
    for piece, frame, strip in sorted(strips, key=lambda s: (s[0], s[1])):
        last[piece] = strip                                   # what the viewer shows at the end
    path_xy = np.concatenate([last[0]] + [last[p][1:] for p in sorted(last)[1:]])
    np.testing.assert_allclose(path_xy[:, 0], 0.02 * np.arange(11), atol=1e-6)


def test_every_camera_of_a_robot_gets_its_own_views(tmp_path):
    frames = []
    for f in floor_frames(6):                      # two cameras, same stamps, interleaved: left first
        for cam in ("left", "right"):
            frames.append(Frame(f.depth, f.K, f.depth_scale, f.stamp, T_map_cam=f.T_map_cam, index=f.index,
                                camera=cam))
    path = tmp_path / "run.rrd"
    run_mapping(frames, MappingConfig(length_m=3.0, view_rate_hz=10.0), rrd_path=path, show_progress=False)
    got = logged_frames(path)
    assert got["/world/points/left"]["Points3D:positions"] == [0, 6]
    assert got["/world/points/right"]["Points3D:positions"] == [1, 7]
    assert got["/plots/cells/known"]["Scalars:scalars"] == [0, 6]
    assert got["/world/right/depth"]["DepthImage:buffer"] == list(range(1, 12, 2))


def test_view_rate_option_and_bad_values(tmp_path, capsys):
    path = tmp_path / "sim.rrd"
    assert main(["run", "sim:stairs", "--frames", "3", "--rrd", str(path), "--view-rate", "5", "--no-progress"]) == 0
    assert "frames/s end to end" in capsys.readouterr().out
    assert logged_frames(path)["/world/points/front"]["Points3D:positions"] == [0, 2]      # 10 Hz walk, 5 Hz views
    assert main(["run", "sim:stairs", "--frames", "1", "--view-rate", "0", "--no-progress"]) == 2
    assert "view_rate_hz must be > 0.0" in capsys.readouterr().err
    assert main(["run", "sim:stairs", "--frames", "1", "--threads", "0", "--no-progress"]) == 2
    assert "nthreads must be in [1," in capsys.readouterr().err
    assert main(["run", "sim:stairs", "--frames", "1", "--threads", "1", "--no-progress"]) == 0
    with pytest.raises(ValueError, match="view_rate_hz"):
        MappingConfig(view_rate_hz=float("inf"))


def test_valid_margin_option_and_config_key_reach_the_camera(tmp_path, capsys, monkeypatch):
    seen = []
    camera = pipeline.Camera

    def spy(*args, **kwargs):
        seen.append(kwargs["valid_margin_px"])
        return camera(*args, **kwargs)

    monkeypatch.setattr(pipeline, "Camera", spy)
    path = tmp_path / "walk.rrd"
    assert main(["run", "sim:stairs", "--frames", "1", "--rrd", str(path), "--valid-margin", "2",
                 "--no-progress"]) == 0
    assert main(["replay", str(path), "--no-progress"]) == 0                  # the recording's margin
    config = tmp_path / "map.toml"
    config.write_text("[map]\nvalid_margin_px = 0\n")
    assert main(["replay", str(path), "--config", str(config), "--no-progress"]) == 0
    assert main(["replay", str(path), "--config", str(config), "--valid-margin", "7", "--no-progress"]) == 0
    assert seen == [2, 2, 0, 7]
    capsys.readouterr()
    assert main(["run", "sim:stairs", "--frames", "1", "--valid-margin", "-1", "--no-progress"]) == 2
    assert "valid_margin_px must be an integer in [0, 16]" in capsys.readouterr().err
