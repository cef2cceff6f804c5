"""Replaying rerun recordings: the project's own bit-exact, other layouts through their transforms."""

import numpy as np
import pytest
import rerun as rr

from elevmap.frame import Frame
from elevmap.pipeline import MappingConfig, run_mapping
from elevmap.sources.rrd import RrdSource, read_rrd_frames
from noise_model import D435
from noise_model.sim.targets import camera_extrinsics, render_floor

W, H = 212, 120
K = D435.intrinsics(424, 240) * np.array([[0.5], [0.5], [1.0]])


def floor_frames(n, rng, pose_cov=True):
    out = []
    for i in range(n):
        T = camera_extrinsics((0.05 * i, 0.01 * i, 0.45), 30.0, 3.0 * i)
        z, _ = render_floor(K, W, H, T)
        z = z + rng.normal(0, 0.005, z.shape)
        d = np.where(np.isfinite(z), np.round(z / 0.001), 0).astype(np.uint16)
        P = np.diag([1e-4, 2e-4, 3e-4, 1e-5, 2e-5, 3e-5]) * (i + 1) if pose_cov else None
        out.append(Frame(d, K, 0.001, 1000.0 + 0.0333 * i, T_map_cam=T, pose_cov=P, index=i, camera="front"))
    return out


def test_own_recordings_replay_bit_exact_and_map_the_same(tmp_path, rng):
    frames = floor_frames(5, rng)
    path = tmp_path / "walk.rrd"
    cfg = MappingConfig(length_m=4.0, mesh_every=2)
    first = run_mapping(frames, cfg, rrd_path=path, show_progress=False)
    back = read_rrd_frames(path)
    assert len(back) == 5
    for f, g in zip(frames, back):
        for name in ("depth", "K", "T_map_cam", "pose_cov"):
            np.testing.assert_array_equal(getattr(f, name), getattr(g, name))
        assert (f.stamp, f.depth_scale, f.index, f.camera) == (g.stamp, g.depth_scale, g.index, g.camera)
    again = run_mapping(back, cfg, show_progress=False)
    np.testing.assert_array_equal(first["map"].data, again["map"].data)


def test_a_recording_laid_out_like_reruns_realsense_example_replays(tmp_path, rng):
    frame = floor_frames(3, rng)[2]
    path = tmp_path / "realsense.rrd"
    rec = rr.RecordingStream("rerun_example_live_depth_sensor")
    rec.save(str(path))
    rec.log("realsense", rr.ViewCoordinates.RDF, static=True)
    T_cam_map = np.linalg.inv(frame.T_map_cam)                      # logged child-from-parent
    rec.log("realsense/depth", rr.Transform3D(translation=T_cam_map[:3, 3], mat3x3=T_cam_map[:3, :3],
                                              relation=rr.TransformRelation.ChildFromParent), static=True)
    rec.log("realsense/depth/image", rr.Pinhole(image_from_camera=K, resolution=[W, H]), static=True)
    for i in range(2):
        rec.set_time("frame_nr", sequence=i)
        rec.log("realsense/depth/image", rr.DepthImage(frame.depth, meter=1000.0))
    rec.flush()
    del rec
    src = RrdSource(path)
    assert len(src) == 2 and src.timeline == "frame_nr"
    g = next(iter(src))
    np.testing.assert_array_equal(g.depth, frame.depth)
    np.testing.assert_allclose(g.K, K, rtol=1e-6)
    np.testing.assert_allclose(g.T_map_cam, frame.T_map_cam, atol=1e-6)
    assert g.depth_scale == pytest.approx(0.001)
    assert src.valid_margins_px == {}             # not this project's: the run's margin applies


def test_bad_recordings_name_the_file_and_the_problem(tmp_path, rng):
    path = tmp_path / "walk.rrd"
    run_mapping(floor_frames(2, rng), MappingConfig(length_m=2.0), rrd_path=path, show_progress=False)
    data = path.read_bytes()
    cut = tmp_path / "cut.rrd"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="cut.rrd: not a readable rerun recording"):
        RrdSource(cut)
    with pytest.raises(ValueError, match="no such recording"):
        RrdSource(tmp_path / "missing.rrd")
    nodepth = tmp_path / "nodepth.rrd"
    rec = rr.RecordingStream("x")
    rec.save(str(nodepth))
    rec.log("world/points", rr.Points3D(np.zeros((3, 3))))
    rec.flush()
    del rec
    with pytest.raises(ValueError, match="nodepth.rrd: the recording holds no DepthImage"):
        RrdSource(nodepth)
    nopin = tmp_path / "nopinhole.rrd"
    rec = rr.RecordingStream("x")
    rec.save(str(nopin))
    rec.set_time("frame", sequence=0)
    rec.log("world/depth", rr.DepthImage(np.ones((4, 5), np.uint16), meter=1000.0))
    rec.flush()
    del rec
    with pytest.raises(ValueError, match="under no Pinhole"):
        RrdSource(nopin)
    with pytest.raises(ValueError, match="no depth images at"):
        RrdSource(path, entity="world/other/depth")


def test_a_failed_run_leaves_no_recording_and_keeps_an_old_one(tmp_path, rng):
    path = tmp_path / "walk.rrd"
    path.write_bytes(b"an older recording")

    def broken():
        yield from floor_frames(2, rng)
        raise RuntimeError("camera unplugged")

    with pytest.raises(RuntimeError, match="camera unplugged"):
        run_mapping(broken(), MappingConfig(length_m=2.0), rrd_path=path, show_progress=False)
    assert path.read_bytes() == b"an older recording"
    assert [p.name for p in tmp_path.iterdir()] == ["walk.rrd"]


def test_a_replay_applies_the_margin_the_recording_names(tmp_path, rng):
    frames = floor_frames(4, rng)
    path = tmp_path / "m3.rrd"
    cfg = MappingConfig(length_m=4.0, valid_margin_px=3)
    first = run_mapping(frames, cfg, rrd_path=path, show_progress=False)
    src = RrdSource(path)
    assert src.valid_margins_px == {"front": 3}
    again = run_mapping(src, MappingConfig(length_m=4.0), show_progress=False)    # the margin from the file
    np.testing.assert_array_equal(first["map"].data, again["map"].data)
    default = run_mapping(frames, MappingConfig(length_m=4.0), show_progress=False)
    assert not np.array_equal(first["map"].data, default["map"].data, equal_nan=True)   # 3 px is not 5 px
    forced = run_mapping(RrdSource(path), MappingConfig(length_m=4.0, valid_margin_px=5), show_progress=False)
    np.testing.assert_array_equal(default["map"].data, forced["map"].data)      # a set margin wins


def test_a_recording_that_names_no_margin_replays_with_none(tmp_path, rng, monkeypatch):
    from elevmap import viz

    log_exact = viz.log_exact

    def old_meta(rec, entity, static=False, **arrays):            # the meta of recordings before the margin
        arrays.pop("valid_margin_px")
        log_exact(rec, entity, static=static, **arrays)

    frames = floor_frames(3, rng)
    path = tmp_path / "old.rrd"
    monkeypatch.setattr(viz, "log_exact", old_meta)
    run_mapping(frames, MappingConfig(length_m=4.0, valid_margin_px=0), rrd_path=path, show_progress=False)
    monkeypatch.setattr(viz, "log_exact", log_exact)
    src = RrdSource(path)
    assert src.valid_margins_px == {"front": 0}
    replayed = run_mapping(src, MappingConfig(length_m=4.0), show_progress=False)
    unmasked = run_mapping(frames, MappingConfig(length_m=4.0, valid_margin_px=0), show_progress=False)
    np.testing.assert_array_equal(replayed["map"].data, unmasked["map"].data)


def test_a_bad_recorded_margin_names_the_file_and_the_field(tmp_path, rng, monkeypatch):
    from elevmap import viz

    log_exact = viz.log_exact

    def bad_meta(rec, entity, static=False, **arrays):
        log_exact(rec, entity, static=static, **{**arrays, "valid_margin_px": 2.5})

    path = tmp_path / "bad.rrd"
    monkeypatch.setattr(viz, "log_exact", bad_meta)
    run_mapping(floor_frames(1, rng), MappingConfig(length_m=2.0), rrd_path=path, show_progress=False)
    with pytest.raises(ValueError, match=r"bad.rrd: meta/front valid_margin_px is \[2.5\]"):
        RrdSource(path)
    with pytest.raises(ValueError, match="valid_margin_px must be an integer"):
        MappingConfig(valid_margin_px=17)
    with pytest.raises(ValueError, match="valid_margin_px must be an integer"):
        MappingConfig.from_dict({"valid_margin_px": "5"})
