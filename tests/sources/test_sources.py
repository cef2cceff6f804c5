"""Data sources: RealSense .bag/.db3, capture sets, PNG folders, pose files.

Genuine recordings are read from the REALDATA folder of tests/conftest.py (the ``realdata`` fixture skips
where it is absent) and never copied into the project; files the tests make live in ``tmp_path``.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from elevmap.frame import Frame
from elevmap.sources import (
    CaptureSet, DepthFolderSource, LiveRealSenseSource, PoseTrack, RealSenseFileSource, read_capture_set,
    read_pose_file, record_db3, with_poses, write_capture_set,
)
from elevmap.sources.folder import read_intrinsics, stamp_from_name
from elevmap.sources.poses import T265_T_POSE_CAM, T_MAP_T265WORLD

try:
    import pyrealsense2 as rs
except ImportError:  # not installed, or libusb-1.0 missing: the RealSense tests skip, the others run
    rs = None
needs_rs = pytest.mark.skipif(rs is None, reason="pyrealsense2 (or its system library libusb-1.0) not available")
try:
    import cv2  # noqa: F401
except ImportError:
    cv2 = None
needs_cv2 = pytest.mark.skipif(cv2 is None, reason="OpenCV (opencv-python-headless) not available")
from conftest import REALDATA

BAG = Path("lrs_unittest_bag_d435") / "single_depth_color_640x480.bag"
POLY = Path("polylidar_d435i_floor_filtered")
K64 = np.array([[60.0, 0.0, 31.5], [0.0, 61.25, 23.75], [0.0, 0.0, 1.0]])


def _figures(realdata, folder):
    return json.loads((realdata / folder / "figures.json").read_text())


def _summary(depth_u16: np.ndarray, scale: float) -> dict:
    v = depth_u16[depth_u16 > 0].astype(np.float64) * scale
    return {"valid_frac": float(np.mean(depth_u16 > 0)), "depth_min_m": v.min(), "depth_max_m": v.max(),
            "depth_p01_m": np.percentile(v, 1), "depth_median_m": np.percentile(v, 50),
            "depth_p99_m": np.percentile(v, 99)}


# ------------------------------------------------------------------------------------------------
# RealSense recordings


@pytest.fixture(scope="module")
def bag_frames():
    if rs is None:
        pytest.skip("pyrealsense2 (or its system library libusb-1.0) not available")
    path = REALDATA / BAG
    if not path.is_file():
        pytest.skip(f"genuine D435 recording not available at {path}")
    with RealSenseFileSource(path) as src:
        return src, list(src)


@pytest.mark.realdata
def test_real_bag_intrinsics_scale_device(bag_frames, realdata):
    src, _ = bag_frames
    i = src.intrinsics
    assert (i["width"], i["height"]) == (640, 480)
    assert i["fx"] == pytest.approx(390.4315, abs=1e-3) and i["fy"] == pytest.approx(390.4315, abs=1e-3)
    assert i["ppx"] == pytest.approx(331.3879, abs=1e-3) and i["ppy"] == pytest.approx(242.1873, abs=1e-3)
    assert i["model"] == "brown_conrady" and i["coeffs"] == [0.0] * 5
    np.testing.assert_allclose(src.K, [[i["fx"], 0, i["ppx"]], [0, i["fy"], i["ppy"]], [0, 0, 1]])
    assert src.depth_scale == pytest.approx(0.001, rel=1e-6)
    assert src.fps == 6
    fig = _figures(realdata, BAG.parent)
    assert src.device_info["name"] == fig["info"]["name"] == "Intel RealSense D435"
    assert src.device_info["serial"] == fig["info"]["serial"]
    assert src.device_info["firmware"] == fig["info"]["fw"]
    np.testing.assert_allclose([i["fx"], i["fy"], i["ppx"], i["ppy"]], fig["K"], atol=1e-9)
    assert src.depth_scale == pytest.approx(fig["info"]["depth_scale"], rel=1e-12)


@pytest.mark.realdata
def test_real_bag_frames(bag_frames, realdata):
    """Every depth frame of the file, 640x480 uint16, with the figures.json statistics.

    The file holds TWO depth frames (#169, #170) and one colour frame (#162); librealsense's own
    test says so too ("the recording holds more than one depth frame"). PROVENANCE/figures.json
    describe one frame because they were measured with a depth+colour pipeline whose syncer emits a
    single frameset (#170). This source plays depth only and drops nothing, so it yields both;
    figures.json's numbers are those of the second.
    """
    src, frames = bag_frames
    assert len(frames) == 2
    for k, f in enumerate(frames):
        assert isinstance(f, Frame) and f.index == k
        assert f.depth.dtype == np.uint16 and f.depth.shape == (480, 640)
        assert f.depth_scale == src.depth_scale and f.T_map_cam is None
        np.testing.assert_array_equal(f.K, src.K)
    assert frames[0].stamp == pytest.approx(360.815089, abs=1e-6)
    assert frames[1].stamp - frames[0].stamp == pytest.approx(1 / 6, abs=1e-3)  # 6 fps, consecutive
    fig = _figures(realdata, BAG.parent)["summary"]
    got = _summary(frames[1].depth, src.depth_scale)
    assert got["valid_frac"] == pytest.approx(fig["valid_frac"], abs=1e-9)
    for key in ("depth_min_m", "depth_max_m", "depth_p01_m", "depth_median_m", "depth_p99_m"):
        assert got[key] == pytest.approx(fig[key], abs=1e-6), key
    first = _summary(frames[0].depth, src.depth_scale)  # the earlier frame: same scene, a little different
    assert first["valid_frac"] == pytest.approx(fig["valid_frac"], abs=1e-3)
    assert not np.array_equal(frames[0].depth, frames[1].depth)


@needs_rs
@pytest.mark.realdata
def test_real_bag_iterates_again_and_closes(realdata):
    src = RealSenseFileSource(realdata / BAG)
    a = next(iter(src))
    b = next(iter(src))  # each iteration starts from the first frame
    np.testing.assert_array_equal(a.depth, b.depth)
    src.close()
    with pytest.raises(ValueError, match="closed"):
        iter(src)


@needs_rs
@pytest.mark.realdata
def test_truncated_bag_is_an_error_naming_the_file(realdata, tmp_path):
    data = (realdata / BAG).read_bytes()
    bad = tmp_path / "half.bag"
    bad.write_bytes(data[: len(data) // 2])
    yielded = []
    with pytest.raises(ValueError, match=r"half\.bag.*(truncated|corrupt)"):
        for f in RealSenseFileSource(bad):
            yielded.append(f)
    assert yielded == []
    end = tmp_path / "no_index.bag"  # all but the last bytes (the index at the end)
    end.write_bytes(data[:-100])
    with pytest.raises(ValueError, match="no_index.bag"):
        RealSenseFileSource(end)


@needs_rs
def test_bad_recording_files(tmp_path):
    with pytest.raises(ValueError, match=r"missing\.bag: no such file"):
        RealSenseFileSource(tmp_path / "missing.bag")
    junk = tmp_path / "junk.db3"
    junk.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(ValueError, match=r"junk\.db3: cannot open"):
        RealSenseFileSource(junk)
    empty = tmp_path / "empty.bag"
    empty.write_bytes(b"")
    with pytest.raises(ValueError, match=r"empty\.bag"):
        RealSenseFileSource(empty)
    other = tmp_path / "depth.npy"
    other.write_bytes(b"x")
    with pytest.raises(ValueError, match=r"depth\.npy: not a RealSense recording"):
        RealSenseFileSource(other)


def _record_colour_only(path: Path) -> None:
    """A .db3 with one RGB8 stream and no depth (software device + recorder)."""
    W, H = 32, 24
    dev = rs.software_device()
    s = dev.add_sensor("RGB Camera")
    vs = rs.video_stream()
    vs.type, vs.index, vs.uid = rs.stream.color, 0, 0
    vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = W, H, 30, 3, rs.format.rgb8
    i = rs.intrinsics()
    i.width, i.height, i.ppx, i.ppy, i.fx, i.fy = W, H, 16.0, 12.0, 30.0, 30.0
    i.model, i.coeffs = rs.distortion.none, [0.0] * 5
    vs.intrinsics = i
    s.add_video_stream(vs)
    rec = rs.recorder(str(path), dev)
    rsn = rec.query_sensors()[0]
    q = rs.frame_queue(10)
    rsn.open(rsn.get_stream_profiles()[0])
    rsn.start(q)
    prof = s.get_stream_profiles()[0].as_video_stream_profile()
    img = np.zeros((H, W, 3), np.uint8)
    for k in range(2):
        f = rs.software_video_frame()
        f.pixels, f.bpp, f.stride = img, 3, W * 3
        f.timestamp, f.domain, f.frame_number, f.profile = k * 33.3, rs.timestamp_domain.hardware_clock, k + 1, prof
        s.on_video_frame(f)
        q.wait_for_frame(2000)
    rsn.stop()
    rsn.close()
    del rsn, rec


@needs_rs
def test_recording_without_depth_stream(tmp_path):
    path = tmp_path / "colour.db3"
    _record_colour_only(path)
    with pytest.raises(ValueError, match=r"colour\.db3: the recording has no depth"):
        RealSenseFileSource(path)


@needs_rs
def test_db3_round_trip_bit_exact(tmp_path, rng):
    depth = rng.integers(0, 65536, size=(5, 48, 64), dtype=np.uint16)
    depth[:, :3] = 0  # holes
    path = record_db3(tmp_path / "rt.db3", depth, K64, depth_scale=0.001, fps=15)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rt.db3"]  # no temporary left behind
    with RealSenseFileSource(path) as src:
        i = src.intrinsics
        assert (i["width"], i["height"]) == (64, 48)
        np.testing.assert_allclose(src.K, K64, rtol=1e-7)
        assert src.depth_scale == pytest.approx(0.001, rel=1e-6)
        assert src.fps == 15
        assert src.device_info["name"] == "Intel RealSense D435 (software)"
        frames = list(src)
    got = np.stack([f.depth for f in frames])
    assert got.dtype == np.uint16
    np.testing.assert_array_equal(got, depth)
    np.testing.assert_allclose([f.stamp for f in frames], np.arange(5) / 15, atol=1e-6)
    assert [f.index for f in frames] == list(range(5))


@needs_rs
def test_db3_stamps_scale_and_no_overwrite(tmp_path, rng):
    depth = rng.integers(0, 65536, size=(3, 8, 10), dtype=np.uint16)
    K = np.array([[9.0, 0, 4.5], [0, 9.0, 3.5], [0, 0, 1]])
    stamps = np.array([10.0, 10.25, 11.0])
    p = record_db3(tmp_path / "s.db3", list(depth), K, depth_scale=0.0001, stamps=stamps, compress=False)
    with RealSenseFileSource(p) as src:
        assert src.depth_scale == pytest.approx(1e-4, rel=1e-6)
        frames = list(src)
    np.testing.assert_array_equal(np.stack([f.depth for f in frames]), depth)
    np.testing.assert_allclose([f.stamp for f in frames], stamps, atol=1e-6)
    before = p.read_bytes()
    with pytest.raises(ValueError, match="exists"):
        record_db3(p, depth, K)
    assert p.read_bytes() == before
    with pytest.raises(ValueError, match=r"\.db3"):
        record_db3(tmp_path / "x.bag", depth, K)
    with pytest.raises(ValueError, match="uint16"):
        record_db3(tmp_path / "f.db3", depth.astype(np.float32), K)
    with pytest.raises(ValueError, match="frames, H, W"):
        record_db3(tmp_path / "f.db3", depth[0], K)
    assert sorted(q.name for q in tmp_path.iterdir()) == ["s.db3"]


@needs_rs
def test_live_source_without_camera():
    if rs.context().query_devices().size() > 0:
        pytest.skip("a RealSense camera is connected; this test checks the no-camera message")
    with pytest.raises((ValueError, RuntimeError), match="no RealSense camera is connected"):
        LiveRealSenseSource()


def test_missing_pyrealsense2_says_what_to_install(monkeypatch):
    from elevmap.sources import realsense

    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # makes the import fail
    with pytest.raises(ImportError, match=r"libusb-1\.0.*apt-get install libusb-1\.0-0"):
        realsense.import_pyrealsense2()

    class NoLibusb:  # what a machine without libusb sees
        def find_spec(self, name, path=None, target=None):
            if name == "pyrealsense2":
                raise ImportError("libusb-1.0.so.0: cannot open shared object file: No such file or directory")
            return None

    monkeypatch.delitem(sys.modules, "pyrealsense2")
    monkeypatch.setattr(sys, "meta_path", [NoLibusb()] + sys.meta_path)
    with pytest.raises(ValueError, match=r"needs the system library libusb-1\.0.*apt-get install libusb-1\.0-0"):
        realsense.import_pyrealsense2()


# ------------------------------------------------------------------------------------------------
# capture sets

CAMERA = {"model": "D435", "width": 16, "height": 12, "fx": 14.5, "fy": 14.25, "ppx": 7.5, "ppy": 5.5,
          "depth_scale": 0.001, "baseline_m": 0.05, "note": "an unknown key"}


def _captures(rng):
    wall = {"id": "wall_z1.00_y00", "depth": "wall_z1.00_y00.npy",
            "target": {"kind": "wall", "distance_m": 1.0, "yaw_deg": 0.0, "pitch_deg": 0.0},
            "background_m": None}
    board = {"id": "board_z0.80_y30",
             "target": {"kind": "board", "distance_m": 0.8, "yaw_deg": 30.0, "pitch_deg": -5.5,
                        "width_m": 0.6, "height_m": 0.9, "colour": "white"},
             "background_m": 3.0, "operator": "me"}
    return [(wall, rng.integers(0, 65536, (4, 12, 16), dtype=np.uint16)),
            (board, rng.integers(0, 65536, (2, 12, 16), dtype=np.uint16))]


def test_capture_set_round_trip_exact(tmp_path, rng):
    caps = _captures(rng)
    out = tmp_path / "session"
    written = write_capture_set(out, CAMERA, caps, extra={"session": "lab 3"})
    assert sorted(p.name for p in out.iterdir()) == ["board_z0.80_y30.npy", "captures.json", "wall_z1.00_y00.npy"]
    cs = read_capture_set(out)
    assert isinstance(cs, CaptureSet) and cs.ids == ["wall_z1.00_y00", "board_z0.80_y30"]
    assert cs.camera == CAMERA and cs.extra == {"session": "lab 3"}
    doc = json.loads((out / "captures.json").read_text())
    assert doc["format"] == "d435-captures/1" and doc["camera"] == CAMERA
    for (d, arr), cap in zip(caps, cs.captures):
        expected = dict(d, depth=d.get("depth", f"{d['id']}.npy"))
        assert cap.to_dict() == expected
        got = cs.load_depth(cap.id)
        assert got.dtype == np.uint16 and got.shape == arr.shape
        np.testing.assert_array_equal(got, arr)
    board = cs.capture("board_z0.80_y30")
    assert board.extra == {"operator": "me"} and board.target["colour"] == "white"
    assert board["id"] == board.id and dict(board) == board.to_dict()  # also a read-only dict
    assert (board.kind, board.distance_m, board.yaw_deg, board.pitch_deg, board.background_m) == \
        ("board", 0.8, 30.0, -5.5, 3.0)
    frames = list(cs.frames("wall_z1.00_y00"))
    assert [f.index for f in frames] == [0, 1, 2, 3]
    np.testing.assert_allclose([f.stamp for f in frames], np.arange(4) / 30)
    np.testing.assert_array_equal(frames[2].depth, caps[0][1][2])
    np.testing.assert_array_equal(frames[0].K, [[14.5, 0, 7.5], [0, 14.25, 5.5], [0, 0, 1]])
    assert frames[0].depth_scale == 0.001 and frames[0].camera == "D435"
    assert written.to_dict() == cs.to_dict()
    # a second write of the same set is refused, and leaves the files alone
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with pytest.raises(ValueError, match="overwrite"):
        write_capture_set(out, CAMERA, caps)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    caps2 = [(caps[0][0], np.zeros((1, 12, 16), np.uint16))]
    write_capture_set(out, CAMERA, caps2, overwrite=True)
    assert read_capture_set(out).ids == ["wall_z1.00_y00"]
    assert read_capture_set(out).load_depth("wall_z1.00_y00").shape == (1, 12, 16)


def _edit_json(folder: Path, edit) -> None:
    path = folder / "captures.json"
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


@pytest.mark.parametrize("edit, match", [
    (lambda d: d["captures"][1].pop("target"), r"capture 'board_z0\.80_y30': missing required key 'target'"),
    (lambda d: d["captures"][0].pop("depth"), r"capture 'wall_z1\.00_y00': missing required key 'depth'"),
    (lambda d: d["captures"][1]["target"].pop("width_m"), r"capture 'board_z0\.80_y30'.*'width_m'"),
    (lambda d: d["captures"][0]["target"].update(distance_m=0.0), r"capture 'wall_z1\.00_y00'.*distance_m"),
    (lambda d: d["captures"][0]["target"].update(kind="sphere"), r"capture 'wall_z1\.00_y00'.*unknown kind"),
    (lambda d: d["camera"].pop("fx"), r"camera: missing required key 'fx'"),
    (lambda d: d.update(format="d435-captures/2"), r"'format' is 'd435-captures/2'"),
    (lambda d: d.pop("format"), r"missing required key 'format'"),
    (lambda d: d["camera"].update(width=17), r"capture 'wall_z1\.00_y00'.*do not match the camera's 17x12"),
    (lambda d: d["captures"][1].update(id="wall_z1.00_y00"), r"'id' is used twice"),
    (lambda d: d["captures"][1].update(background_m=0.5), r"capture 'board_z0\.80_y30'.*'background_m'"),
])
def test_capture_set_invalid_json(tmp_path, rng, edit, match):
    write_capture_set(tmp_path, CAMERA, _captures(rng))
    _edit_json(tmp_path, edit)
    with pytest.raises(ValueError, match=match):
        read_capture_set(tmp_path)


def test_capture_set_bad_npy(tmp_path, rng):
    write_capture_set(tmp_path, CAMERA, _captures(rng))
    npy = tmp_path / "board_z0.80_y30.npy"
    data = npy.read_bytes()
    npy.write_bytes(data[:-7])
    with pytest.raises(ValueError, match=r"capture 'board_z0\.80_y30'.*board_z0\.80_y30\.npy.*truncated"):
        read_capture_set(tmp_path)
    np.save(npy, np.zeros((2, 12, 16), np.float32))
    with pytest.raises(ValueError, match=r"capture 'board_z0\.80_y30'.*dtype float32"):
        read_capture_set(tmp_path)
    np.save(npy, np.zeros((12, 16), np.uint16))
    with pytest.raises(ValueError, match=r"capture 'board_z0\.80_y30'.*shape \(12, 16\)"):
        read_capture_set(tmp_path)
    npy.unlink()
    with pytest.raises(ValueError, match=r"capture 'board_z0\.80_y30'.*does not exist"):
        read_capture_set(tmp_path)
    (tmp_path / "captures.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"captures\.json: not valid JSON"):
        read_capture_set(tmp_path)
    with pytest.raises(ValueError, match=r"captures\.json: no such file"):
        read_capture_set(tmp_path / "nowhere")


@pytest.mark.parametrize("change, match", [
    (lambda c: c[1][0]["target"].pop("height_m"), r"capture 'board_z0\.80_y30'.*'height_m'"),
    (lambda c: c[1][0]["target"].update(distance_m=-1.0), r"capture 'board_z0\.80_y30'.*distance_m"),
    (lambda c: c[1][0]["target"].update(yaw_deg=90.0), r"capture 'board_z0\.80_y30'.*edge-on"),
    (lambda c: c[0][0].pop("target"), r"capture 'wall_z1\.00_y00': missing required key 'target'"),
    (lambda c: c.__setitem__(1, (c[1][0], c[1][1].astype(np.int32))), r"capture 'board_z0\.80_y30'.*dtype int32"),
    (lambda c: c.__setitem__(1, (c[1][0], c[1][1][:, :, :8])), r"capture 'board_z0\.80_y30'.*8x12"),
    (lambda c: c[1][0].update(depth="../escape.npy"), r"capture 'board_z0\.80_y30'.*plain file name"),
    (lambda c: c[1][0].update(depth="board.db3"), r"capture 'board_z0\.80_y30'.*must end in \.npy"),
    (lambda c: c[1][0].update(id="wall_z1.00_y00", depth="other.npy"), r"'id' is used twice"),
])
def test_failed_write_writes_nothing(tmp_path, rng, change, match):
    caps = [(dict(d, target=dict(d["target"])), a) for d, a in _captures(rng)]
    change(caps)
    out = tmp_path / "set"
    with pytest.raises(ValueError, match=match):
        write_capture_set(out, CAMERA, caps)
    assert not out.exists() or list(out.iterdir()) == []


def test_failed_write_part_way_removes_what_it_wrote(tmp_path, rng, monkeypatch):
    from elevmap.sources import captures as mod

    def boom(path, obj):
        raise OSError("disk full")

    monkeypatch.setattr(mod, "write_json_atomic", boom)
    with pytest.raises(OSError, match="disk full"):
        write_capture_set(tmp_path / "set", CAMERA, _captures(rng))
    assert list((tmp_path / "set").iterdir()) == []


@needs_rs
def test_capture_set_with_db3_capture(tmp_path, rng):
    depth = rng.integers(1, 65536, (3, 12, 16), dtype=np.uint16)
    K_file = np.array([[15.0, 0, 7.5], [0, 14.25, 5.5], [0, 0, 1]])  # fx differs from captures.json
    record_db3(tmp_path / "wall.db3", depth, K_file, fps=6)
    cap = {"id": "wall", "depth": "wall.db3", "target": {"kind": "wall", "distance_m": 2.0}, "background_m": None}
    cs = write_capture_set(tmp_path, CAMERA, [(cap, None)])
    assert cs.capture("wall").is_recording
    with pytest.warns(UserWarning, match=r"capture 'wall'.*fx 15\.0 \(captures\.json: 14\.5\)"):
        got = cs.load_depth("wall")
    np.testing.assert_array_equal(got, depth)
    assert len(cs.mismatches) == 1 and "recording's values are used" in cs.mismatches[0]
    frames = list(cs.frames("wall"))
    np.testing.assert_allclose(frames[0].K, K_file, rtol=1e-7)  # the file's intrinsics win
    np.testing.assert_allclose([f.stamp for f in frames], np.arange(3) / 6, atol=1e-6)
    assert cs.camera_for("wall")["fx"] == 15.0 and cs.camera_for("wall")["ppx"] == 7.5
    with pytest.raises(ValueError, match=r"capture 'gone'.*does not exist"):
        write_capture_set(tmp_path / "other", CAMERA, [(dict(cap, id="gone", depth="gone.db3"), None)])


# ------------------------------------------------------------------------------------------------
# PNG folders


@needs_cv2
@pytest.mark.realdata
def test_polylidar_folder_with_poses(realdata):
    root = realdata / POLY
    track = read_pose_file(root / "trajectory.log")
    assert len(track) == 7 and not track.stamped
    with DepthFolderSource(root / "depth", root / "camera_intrinsic_rgb_424.json", root / "trajectory.log") as src:
        assert len(src) == 7 and src.stamps_from_names
        np.testing.assert_allclose(src.K, [[307.8533935546875, 0, 204.47328186035156],
                                           [0, 307.8641357421875, 121.65782165527344], [0, 0, 1]])
        frames = list(src)
    assert len(frames) == 7
    assert frames[0].stamp == 1580908150.203 and frames[3].stamp == 1580908154.939
    assert all(np.diff([f.stamp for f in frames]) > 0)
    first = np.loadtxt(root / "trajectory.log", skiprows=1, max_rows=4)
    np.testing.assert_allclose(frames[0].T_map_cam, first, atol=1e-7)
    for f, P in zip(frames, track.poses):
        assert f.depth.dtype == np.uint16 and f.depth.shape == (240, 424) and f.depth_scale == 0.001
        np.testing.assert_array_equal(f.T_map_cam, P)
    fig = _figures(realdata, POLY)["summary"]
    got = _summary(np.stack([f.depth for f in frames]), 0.001)
    assert got["valid_frac"] == pytest.approx(fig["valid_frac"], abs=1e-9)
    for key in ("depth_min_m", "depth_max_m", "depth_p01_m", "depth_median_m", "depth_p99_m"):
        assert got[key] == pytest.approx(fig[key], abs=1e-6), key
    per_frame = [round(float(np.mean(f.depth > 0)), 4) for f in frames]
    assert per_frame == _figures(realdata, POLY)["summary"]["valid_frac_per_frame"]
    # the dataset's root folder works too: images in depth/, the one intrinsics JSON found next to them
    with DepthFolderSource(root) as src:
        assert src.folder == root / "depth" and src.intrinsics_source.endswith("camera_intrinsic_rgb_424.json")
        np.testing.assert_array_equal(next(iter(src)).depth, frames[0].depth)
        assert next(iter(src)).T_map_cam is None  # pose files are never picked up implicitly


@needs_cv2
@pytest.mark.realdata
def test_polylidar_t265_poses_put_the_floor_level(realdata):
    """With the T265 conventions the floor comes out horizontal at one height in the map frame.

    trajectory.log holds T265 poses (T265 body in the T265 world frame, y up). The depth camera is
    T265_T_POSE_CAM in the T265 body (polylidar's H_t265_d400); T_MAP_T265WORLD makes z up.
    """
    root = realdata / POLY
    planes = _figures(realdata, POLY)["floor_plane_per_frame"]
    src = DepthFolderSource(root / "depth", root / "camera_intrinsic_rgb_424.json", root / "trajectory.log",
                            T_pose_cam=T265_T_POSE_CAM, T_map_pose=T_MAP_T265WORLD)
    heights = []
    with src:
        for f in src:
            if f.index == 0:  # its "floor" fit in figures.json is a wall (normal horizontal)
                continue
            n = np.array(planes[f.index]["plane_normal"])
            R, t = f.T_map_cam[:3, :3], f.T_map_cam[:3, 3]
            assert (R @ n)[2] > 0.99  # the floor's normal points up
            heights.append((R @ (n * planes[f.index]["plane_offset_m"]) + t)[2])
            # and the bottom image rows, deprojected, lie on it
            z = f.depth_m()[200:236, 100:324]
            v, u = np.mgrid[200:236, 100:324]
            p = np.stack([(u - f.K[0, 2]) / f.K[0, 0] * z, (v - f.K[1, 2]) / f.K[1, 1] * z, z], -1).reshape(-1, 3)
            assert -0.9 < np.median((p @ R.T + t)[:, 2]) < -0.7
    assert np.ptp(heights) < 0.03 and -0.8 < np.mean(heights) < -0.74


@needs_cv2
@pytest.mark.realdata
def test_polylidar_raw_t265_track_interpolated(realdata):
    """The full-rate T265 log (stamps [ms] in the header's 4th field) interpolated at the depth stamps."""
    root = realdata / POLY
    raw = read_pose_file(root / "raw_trajectory_t265.log", log_stamp_scale=1e-3)
    log = read_pose_file(root / "trajectory.log", log_stamp_scale=1e-3)
    assert raw.stamped and len(raw) == 4601
    np.testing.assert_array_equal(raw.at(log.stamps), log.poses)  # those poses are in the raw log
    per_index = read_pose_file(root / "trajectory.log")
    with DepthFolderSource(root / "depth", root / "camera_intrinsic_rgb_424.json", raw) as src:
        for f, P in zip(src, per_index.poses):
            assert np.linalg.norm(f.T_map_cam[:3, 3] - P[:3, 3]) < 2e-3  # within 12 ms of motion
            cos = (np.trace(f.T_map_cam[:3, :3] @ P[:3, :3].T) - 1) / 2
            assert math.degrees(math.acos(min(1.0, cos))) < 0.5


def _png(path: Path, img: np.ndarray) -> None:
    assert cv2.imwrite(str(path), img)


@needs_cv2
def test_folder_root_with_a_colour_picture_reads_its_depth_subfolder(tmp_path, rng):
    """A dataset root holding a figure PNG beside depth/ (the aims_slam layout) maps depth/."""
    (tmp_path / "depth").mkdir()
    img = rng.integers(1, 65536, (6, 8), dtype=np.uint16)
    _png(tmp_path / "depth" / "0.png", img)
    _png(tmp_path / "figure.png", np.zeros((6, 8, 3), np.uint8))
    with DepthFolderSource(tmp_path, [[5.0, 0, 3.5], [0, 5.0, 2.5], [0, 0, 1]]) as src:
        assert src.folder == tmp_path / "depth"
        (frame,) = list(src)
    np.testing.assert_array_equal(frame.depth, img)


@needs_cv2
def test_folder_without_stamps_natural_order_and_errors(tmp_path, rng):
    d = tmp_path / "depth"
    d.mkdir()
    imgs = {k: rng.integers(0, 65536, (6, 8), dtype=np.uint16) for k in (1, 2, 10)}
    for k, img in imgs.items():
        _png(d / f"frame_{k}.png", img)
    K = [[5.0, 0, 3.5], [0, 5.0, 2.5], [0, 0, 1]]
    with DepthFolderSource(d, K, fps=10) as src:
        assert len(src) == 3 and not src.stamps_from_names
        frames = list(src)
    assert [f.index for f in frames] == [0, 1, 2]
    np.testing.assert_allclose([f.stamp for f in frames], [0.0, 0.1, 0.2])
    for f, k in zip(frames, (1, 2, 10)):  # frame_10 after frame_2
        np.testing.assert_array_equal(f.depth, imgs[k])
        assert f.T_map_cam is None  # no pose file: a static camera
    intr = tmp_path / "intr.json"
    intr.write_text(json.dumps({"width": 9, "height": 6, "intrinsic_matrix": [5, 0, 0, 0, 5, 0, 3.5, 2.5, 1]}))
    with pytest.raises(ValueError, match=r"frame_1\.png: image is 8x6 but the intrinsics are 9x6"):
        list(DepthFolderSource(d, intr))
    _png(d / "frame_3.png", np.zeros((6, 8), np.uint8))
    with pytest.raises(ValueError, match=r"frame_3\.png: not a 16-bit single-channel depth image"):
        list(DepthFolderSource(d, K))
    (d / "frame_3.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(ValueError, match=r"frame_3\.png: cannot read"):
        list(DepthFolderSource(d, K))
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="empty: no .png depth images"):
        DepthFolderSource(empty, K)
    with pytest.raises(ValueError, match="no such folder"):
        DepthFolderSource(tmp_path / "nope", K)
    assert DepthFolderSource(d).intrinsics_source == str(intr)  # found next to depth/
    alone = tmp_path / "alone"
    alone.mkdir()
    _png(alone / "a.png", imgs[1])
    with pytest.raises(ValueError, match=r"alone: no intrinsics JSON file found"):
        DepthFolderSource(alone)
    (tmp_path / "b.json").write_text(json.dumps({"fx": 5, "fy": 5, "ppx": 3.5, "ppy": 2.5}))
    with pytest.raises(ValueError, match=r"several intrinsics files .*b\.json.*intr\.json"):
        DepthFolderSource(tmp_path)  # finds depth/ and looks next to it


@needs_cv2
def test_folder_pose_count_must_match(tmp_path, rng):
    d = tmp_path / "depth"
    d.mkdir()
    for k in range(3):
        _png(d / f"{k:08d}.png", rng.integers(0, 65536, (4, 5), dtype=np.uint16))
    log = tmp_path / "two.log"
    log.write_text("".join(f"{k} {k} {k + 1}\n1 0 0 {k}\n0 1 0 0\n0 0 1 0\n0 0 0 1\n" for k in range(2)))
    with pytest.raises(ValueError, match=r"two\.log: 2 poses \(one per frame index\) for a source of 3 frames"):
        DepthFolderSource(d, np.diag([4.0, 4.0, 1.0]) + [[0, 0, 2], [0, 0, 1.5], [0, 0, 0]], log)


def test_stamps_from_names_and_intrinsics_formats():
    assert stamp_from_name("00000003_1580908154938.png") == 1580908154.938
    assert stamp_from_name("1580908154.png") == 1580908154.0
    assert stamp_from_name("d_1580908154.250.png") == 1580908154.25
    assert stamp_from_name("1580908154938123456.png") == pytest.approx(1580908154.938123456)
    assert stamp_from_name("00000003.png") is None and stamp_from_name("depth.png") is None
    K, w, h = read_intrinsics({"width": 424, "height": 240, "intrinsic_matrix": [300, 0, 0, 0, 301, 0, 200, 120, 1]})
    np.testing.assert_array_equal(K, [[300, 0, 200], [0, 301, 120], [0, 0, 1]])
    assert (w, h) == (424, 240)
    K2, _, _ = read_intrinsics({"fx": 300, "fy": 301, "ppx": 200, "ppy": 120})
    np.testing.assert_array_equal(K, K2)
    with pytest.raises(ValueError, match="intrinsic_matrix must hold 9 numbers"):
        read_intrinsics({"intrinsic_matrix": [1, 2, 3]})


# ------------------------------------------------------------------------------------------------
# poses


def _Rz(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def test_pose_interpolation_by_hand():
    T0, T1 = np.eye(4), np.eye(4)
    T0[:3, 3] = [1.0, 0.0, 0.0]
    T1[:3, :3] = _Rz(90.0)
    T1[:3, 3] = [3.0, 4.0, -6.0]
    track = PoseTrack(np.stack([T0, T1]), np.array([10.0, 12.0]))
    mid = track.at(11.0)[0]
    np.testing.assert_allclose(mid[:3, 3], [2.0, 2.0, -3.0], atol=1e-12)  # position midway
    np.testing.assert_allclose(mid[:3, :3], _Rz(45.0), atol=1e-12)  # half the angle
    quarter = track.at([10.5])[0]
    np.testing.assert_allclose(quarter[:3, 3], [1.5, 1.0, -1.5], atol=1e-12)
    np.testing.assert_allclose(quarter[:3, :3], _Rz(22.5), atol=1e-12)
    ends = track.at([10.0, 12.0])  # on a pose: exactly the stored pose (rotations projected onto SO(3))
    np.testing.assert_array_equal(ends, track.poses)
    np.testing.assert_allclose(ends, [T0, T1], atol=1e-15)
    # outside the span: an error, unless within the tolerance (then the end pose, not extrapolated)
    with pytest.raises(ValueError, match=r"stamp 12\.5 s is outside the pose track's span \[10\.0, 12\.0\]"):
        track.at([11.0, 12.5])
    with pytest.raises(ValueError, match="outside"):
        track.at(9.9)
    np.testing.assert_array_equal(track.at(12.5, tolerance=0.5)[0], track.poses[1])
    np.testing.assert_array_equal(track.at(9.8, tolerance=0.5)[0], track.poses[0])
    with pytest.raises(ValueError, match="no stamps"):
        PoseTrack(np.stack([T0, T1])).at(11.0)
    with pytest.raises(ValueError, match="frame index 2 has no pose"):
        PoseTrack(np.stack([T0, T1])).at_index(2)


def test_pose_interpolation_matches_scipy_slerp(rng):
    from scipy.spatial.transform import Rotation, Slerp

    n = 40
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, :3, :3] = Rotation.random(n, random_state=7).as_matrix()
    P[:, :3, 3] = rng.normal(size=(n, 3))
    t = np.cumsum(rng.uniform(0.05, 1.0, n))
    track = PoseTrack(P, t)
    s = np.sort(rng.uniform(t[0], t[-1], 500))
    got = track.at(s)
    np.testing.assert_allclose(got[:, :3, :3], Slerp(t, Rotation.from_matrix(track.poses[:, :3, :3]))(s).as_matrix(),
                               atol=1e-12)
    for k in range(3):
        np.testing.assert_allclose(got[:, k, 3], np.interp(s, t, P[:, k, 3]), atol=1e-12)


def test_tum_parsing(tmp_path):
    path = tmp_path / "traj.txt"
    s = math.sqrt(0.5)
    path.write_text("# timestamp tx ty tz qx qy qz qw\n\n"
                    "100.0 1 2 3 0 0 0 1\n"
                    f"100.5 4 5 6 0 0 {s} {s}   # 90 deg about z\n")
    track = read_pose_file(path)
    assert track.stamped and len(track) == 2
    np.testing.assert_array_equal(track.stamps, [100.0, 100.5])
    np.testing.assert_allclose(track.poses[0], [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(track.poses[1][:3, :3], _Rz(90.0), atol=1e-12)
    np.testing.assert_allclose(track.at(100.25)[0][:3, :3], _Rz(45.0), atol=1e-12)
    np.testing.assert_allclose(track.at(100.25)[0][:3, 3], [2.5, 3.5, 4.5])


@pytest.mark.parametrize("text, match", [
    ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n", r"line 2: 7 numbers, expected 8"),
    ("# c\n1 0 0 0 0 0 0 1\n2 0 0 x 0 0 0 1\n", r"line 3: not numbers"),
    ("1 0 0 0 0 0 0 2\n", r"line 1: quaternion .* norm 2"),
    ("1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", r"line 2: timestamp 1\.0 does not increase"),
    ("1 0 0 nan 0 0 0 1\n", r"line 1: non-finite"),
    ("# only a comment\n", r"no poses"),
])
def test_bad_tum_files(tmp_path, text, match):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=rf"bad\.txt.*{match}"):
        read_pose_file(path)


def test_log_parsing(tmp_path):
    path = tmp_path / "t.log"
    R = _Rz(30.0)
    rows = "\n".join(" ".join(f"{v:.17g}" for v in row) for row in np.c_[R, [1, 2, 3]])
    path.write_text(f"0 0 1 1000\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n1 1 2 1500\n{rows}\n0 0 0 1\n")
    track = read_pose_file(path)
    assert not track.stamped and len(track) == 2
    np.testing.assert_allclose(track.poses[1][:3, :3], R, atol=1e-15)
    np.testing.assert_array_equal(track.poses[1][:3, 3], [1, 2, 3])
    stamped = read_pose_file(path, log_stamp_scale=1e-3)
    np.testing.assert_array_equal(stamped.stamps, [1.0, 1.5])
    np.testing.assert_allclose(stamped.at(1.25)[0][:3, :3], _Rz(15.0), atol=1e-12)


@pytest.mark.parametrize("text, match", [
    ("0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n", r"line 4: the file ends inside a pose block"),
    ("0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1\n0 0 0 1\n", r"line 4: 3 numbers, expected 4"),
    ("0 0 1\n2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", r"lines 2-4: not a rotation"),
    ("0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 1 1\n", r"line 5: last matrix row must be 0 0 0 1"),
    ("a b c\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", r"line 1: not numbers"),
])
def test_bad_log_files(tmp_path, text, match):
    path = tmp_path / "bad.log"
    path.write_text(text)
    with pytest.raises(ValueError, match=rf"bad\.log.*{match}"):
        read_pose_file(path)
    with pytest.raises(ValueError, match=r"nope\.log: no such pose file"):
        read_pose_file(tmp_path / "nope.log")


class _ListSource:
    """A minimal source: frames from a list (no file)."""

    def __init__(self, frames):
        self.frames, self.closed = frames, False

    def __iter__(self):
        return iter(self.frames)

    def __len__(self):
        return len(self.frames)

    def close(self):
        self.closed = True


def test_with_poses_wraps_any_source(tmp_path):
    K = np.array([[5.0, 0, 2.0], [0, 5.0, 1.5], [0, 0, 1]])
    frames = [Frame(np.full((3, 4), 1000, np.uint16), K, 0.001, stamp=10.0 + 0.5 * k, index=k) for k in range(3)]
    T0, T1 = np.eye(4), np.eye(4)
    T1[:3, :3], T1[:3, 3] = _Rz(90.0), [2.0, 0.0, 0.0]
    track = PoseTrack(np.stack([T0, T1]), np.array([10.0, 11.0]), "hand")
    T_pose_cam = np.eye(4)
    T_pose_cam[:3, 3] = [0.0, 0.0, 0.5]
    src = _ListSource(frames)
    with with_poses(src, track, T_pose_cam) as posed:
        assert len(posed) == 3
        out = list(posed)
    assert src.closed
    for f, T in zip(out, track.at([10.0, 10.5, 11.0])):
        np.testing.assert_allclose(f.T_map_cam, T @ T_pose_cam, atol=1e-12)
    np.testing.assert_allclose(out[1].T_map_cam[:3, 3], [1.0, 0.0, 0.5], atol=1e-12)
    late = [Frame(frames[0].depth, K, 0.001, stamp=11.2)]
    with pytest.raises(ValueError, match="outside"):
        list(with_poses(_ListSource(late), track))
    assert list(with_poses(_ListSource(late), track, tolerance=0.25))[0].T_map_cam is not None
    per_index = PoseTrack(np.stack([T0, T1]))
    with pytest.raises(ValueError, match=r"2 poses \(one per frame index\) for a source of 3 frames"):
        with_poses(_ListSource(frames), per_index)
    log = tmp_path / "p.log"
    log.write_text("".join(f"{k} {k} {k + 1}\n1 0 0 {k}\n0 1 0 0\n0 0 1 0\n0 0 0 1\n" for k in range(3)))
    got = [f.T_map_cam[0, 3] for f in with_poses(_ListSource(frames), log)]
    assert got == [0.0, 1.0, 2.0]


def test_the_sources_package_exports_every_source_lazily():
    import subprocess

    code = ("import sys, elevmap.sources as S\n"
            "heavy = [m for m in ('rerun', 'cv2', 'pyrealsense2', 'noise_model.sim') if m in sys.modules]\n"
            "names = ['RrdSource', 'SimulatedWalk', 'open_source', 'read_viewer_raw', 'RealSenseFileSource',\n"
            "         'DepthFolderSource', 'read_capture_set', 'with_poses']\n"
            "missing = [n for n in names if not hasattr(S, n) or n not in S.__all__]\n"
            "import elevmap\n"
            "missing += [n for n in ('open_source', 'run_mapping', 'MappingConfig') if not hasattr(elevmap, n)]\n"
            "print(heavy, missing); sys.exit(1 if heavy or missing else 0)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
