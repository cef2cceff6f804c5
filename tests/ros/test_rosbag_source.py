"""The ROS bag source: bags written here with rosbags (ROS 1 .bag, ROS 2 .db3 and .mcap with zstd, a bare .mcap,
compressedDepth with odometry, two cameras) mapped to the floor and the box top within 5 mm; skipped
frames counted; damaged bags and missing topics as clear errors; the real RealSense SDK recording read
without pyrealsense2, as the RealSense source reads it."""

from __future__ import annotations

import numpy as np
import pytest

from elevmap.pipeline import MappingConfig, run_mapping
from elevmap.sources.rosbag import RosbagSource, carry_pose_cov
from rosbag_scenes import (
    BOX_TOP_M, BOX_XY, N_FRAMES, ODOM_COV, T0, BagBuilder, T_base_cam, T_map_base, depth_m, frame_stamps,
    unmappable_extras, write_bag,
)

from conftest import REALDATA

CONFIG = MappingConfig(length_m=4.0, resolution_m=0.04, follow=False)
#: The floor and the box top must come out within this of the truth [m].
TOL_M = 0.005
_NAMES = {"bag": "scene.bag", "db3": "scene_db3", "mcap": "scene_mcap", "bare_mcap": "scene.mcap"}


def map_bag(path, **kw):
    src = RosbagSource(path, **kw)
    with src:
        out = run_mapping(src, CONFIG, show_progress=False)
    return src, out


def seen_floor(emap, yaws=(0.0,)) -> np.ndarray:
    """Cells in which some pixel of some frame saw the floor (not those in the box's shadow)."""
    seen = np.zeros((emap.n, emap.n), dtype=bool)
    xs, _ = emap.cell_centres()
    lo, res = xs[0] - emap.resolution_m / 2, emap.resolution_m
    v, u = np.mgrid[0:120, 0:160]
    for s in frame_stamps():
        for yaw in yaws:
            T = T_map_base(s) @ T_base_cam(yaw)
            z = depth_m(T)
            p = np.stack([(u - 79.5) / 100.0 * z, (v - 59.5) / 100.0 * z, z, np.ones_like(z)], -1) @ T.T
            p = p[np.isfinite(z) & (np.abs(p[..., 2]) < 1e-6)]
            i, j = ((p[:, 0] - lo) // res).astype(int), ((p[:, 1] - lo) // res).astype(int)
            ok = (i >= 0) & (i < emap.n) & (j >= 0) & (j < emap.n)
            seen[i[ok], j[ok]] = True
    return seen


def assert_floor_and_box(emap, tol=TOL_M, yaws=(0.0,)):
    """Known cells well inside the box top within ``tol`` of 0.2 m; known floor cells the camera saw, three cells
    or more from the box, within tol of 0 (the cells in the box's shadow hold its edge, the map's edge band)."""
    xs, ys = emap.cell_centres()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    h = emap.known_layer("elevation")
    known = np.isfinite(h)
    dx, dy = np.abs(X - BOX_XY[0]), np.abs(Y - BOX_XY[1])
    res = emap.resolution_m
    top = known & (dx <= 0.2 - 2 * res) & (dy <= 0.2 - 2 * res)
    floor = known & ((dx >= 0.2 + 3 * res) | (dy >= 0.2 + 3 * res)) & seen_floor(emap, yaws)
    assert top.sum() >= 20 and floor.sum() >= 300, (top.sum(), floor.sum())
    assert np.abs(h[top] - BOX_TOP_M).max() < tol
    assert np.abs(h[floor]).max() < tol


@pytest.mark.parametrize("kind", ["bag", "db3", "mcap", "bare_mcap"])
def test_every_bag_container_maps_the_floor_and_the_box(tmp_path, kind):
    path = write_bag(tmp_path / _NAMES[kind], kind)
    src, out = map_bag(path)
    assert src.pose_source == "tf" and src.map_frame == "map"
    assert out["frames"] == N_FRAMES and src.summary()["frames_skipped"] == 0
    assert_floor_and_box(out["map"])


def test_compressed_depth_with_odometry_carries_the_pose_covariance(tmp_path):
    path = write_bag(tmp_path / "odo.mcap", "bare_mcap", depth="compressed", poses="odometry")
    src = RosbagSource(path)
    assert src.pose_source == "odometry /odom" and src.map_frame == "odom"
    frames = list(src)
    assert len(frames) == N_FRAMES
    f = frames[3]
    s = frame_stamps()[3]
    assert f.stamp == pytest.approx(s)
    T_mb, T_bc = T_map_base(s), T_base_cam()
    np.testing.assert_allclose(f.T_map_cam, T_mb @ T_bc, atol=1e-9)
    # the camera sits at lever arm a = R t_bc from the base: a yaw error psi moves it by psi x a
    a = T_mb[:3, :3] @ T_bc[:3, 3]
    np.testing.assert_allclose(f.pose_cov, carry_pose_cov(ODOM_COV, T_mb, T_bc), rtol=1e-9, atol=1e-15)
    # phi x a = (pitch a_z - yaw a_y, yaw a_x - roll a_z, ...): x moves with pitch and yaw, y with roll and yaw
    var_roll, var_pitch, var_yaw = np.diag(ODOM_COV)[3:]
    expected_xx = ODOM_COV[0, 0] - 2 * a[1] * ODOM_COV[0, 5] + a[1] ** 2 * var_yaw + a[2] ** 2 * var_pitch
    assert f.pose_cov[0, 0] == pytest.approx(expected_xx, rel=1e-9)
    assert f.pose_cov[1, 1] == pytest.approx(ODOM_COV[1, 1] + a[0] ** 2 * var_yaw + a[2] ** 2 * var_roll, rel=1e-9)
    np.testing.assert_array_equal(f.depth, np.where(np.isfinite(depth_m(T_mb @ T_bc)),
                                                    np.round(depth_m(T_mb @ T_bc) * 1000), 0).astype(np.uint16))
    with src:
        out = run_mapping(src, CONFIG, show_progress=False)
    assert_floor_and_box(out["map"])


def test_carried_covariance_by_monte_carlo(rng):
    """J Sigma J^T against the scatter of cameras carried by sampled base pose errors."""
    from scipy.spatial.transform import Rotation

    T_mb, T_bc = T_map_base(T0 + 0.3), T_base_cam(20.0)
    xi = rng.multivariate_normal(np.zeros(6), ODOM_COV, size=200_000)
    R = Rotation.from_rotvec(xi[:, 3:]).as_matrix() @ T_mb[:3, :3]
    t_cam = np.einsum("nij,j->ni", R, T_bc[:3, 3]) + T_mb[:3, 3] + xi[:, :3]
    d = t_cam - (T_mb @ T_bc)[:3, 3]
    emp = np.cov(np.hstack([d, xi[:, 3:]]).T)
    # 200 000 samples: each entry within a few standard errors, sqrt((S_ii S_jj + S_ij^2) / n) < 0.5 % of the scale
    scale = np.sqrt(np.outer(np.diag(emp), np.diag(emp)))
    assert np.all(np.abs(emp - carry_pose_cov(ODOM_COV, T_mb, T_bc)) <= 0.015 * scale)


def test_two_depth_topics_are_two_cameras_in_one_map(tmp_path):
    path = write_bag(tmp_path / "two", "db3", cameras=(("front", 0.0), ("left", 25.0)))
    src, out = map_bag(path)
    assert sorted(src.topics) == ["/front/depth/image_rect_raw", "/left/depth/image_rect_raw"]
    assert out["frames"] == 2 * N_FRAMES
    assert_floor_and_box(out["map"], yaws=(0.0, 25.0))
    src1 = RosbagSource(path, depth_topics=["/left/depth/image_rect_raw"])
    assert list(src1.topics) == ["/left/depth/image_rect_raw"]
    assert {f.camera for f in src1} == {"/left/depth/image_rect_raw"} and src1.frames_read == N_FRAMES


@pytest.mark.parametrize("encoding", ["32FC1", "16UC1_be_padded"])
def test_float_and_big_endian_padded_images_read_as_written(tmp_path, encoding):
    path = write_bag(tmp_path / "enc.bag", "bag", depth=encoding)
    frames = list(RosbagSource(path))
    s = frame_stamps()[5]
    z = depth_m(T_map_base(s) @ T_base_cam())
    if encoding == "32FC1":
        assert frames[5].depth.dtype == np.float32 and frames[5].depth_scale is None
        np.testing.assert_array_equal(frames[5].depth, z.astype(np.float32))
    else:
        np.testing.assert_array_equal(frames[5].depth, np.where(np.isfinite(z), np.round(z * 1000), 0))
        assert frames[5].depth_scale == 0.001


def test_frames_that_cannot_be_mapped_are_skipped_and_counted(tmp_path):
    path = write_bag(tmp_path / "skips.bag", "bag", extra=unmappable_extras)
    src, out = map_bag(path)
    s = src.summary()
    assert out["frames"] == s["frames_mapped"] == N_FRAMES
    assert s["frames_skipped"] == 4
    assert s["skipped"] == {"/camera/depth/image_rect_raw": {"no transform at its stamp": 1},
                            "/rear/depth/image_rect_raw": {"no camera info": 3}}
    info = src.info()
    assert "/camera/color/image_raw" not in info["depth"]                   # rgb8 is not depth
    assert info["depth"]["/rear/depth/image_rect_raw"]["problem"].startswith("no camera info")
    assert info["depth"]["/camera/depth/image_rect_raw"]["chain"] == [
        "map", "base_link", "camera_link", "camera_depth_optical_frame"]
    with pytest.raises(ValueError, match=r"skips.bag: every depth frame was skipped \(/rear.*3 with no camera info"):
        list(RosbagSource(path, depth_topics="/rear/depth/image_rect_raw"))
    with pytest.raises(ValueError, match=r"topic /camera/color/image_raw has image encoding 'rgb8', not depth"):
        RosbagSource(path, depth_topics="/camera/color/image_raw")
    with pytest.raises(ValueError, match=r"no depth topic /nope \(/nope: not in the bag\)"):
        RosbagSource(path, depth_topics=["/nope"])
    with pytest.raises(ValueError, match=r"9 with no transform from the map frame 'odom' to the image frame"):
        list(RosbagSource(path, map_frame="odom"))


def test_damaged_bags_and_bags_without_depth_are_clear_errors(tmp_path):
    path = write_bag(tmp_path / "whole.bag", "bag")
    data = path.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"cut\.bag: cannot read the bag, it is truncated, corrupt"):
        RosbagSource(cut)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n" + bytes(100))
    with pytest.raises(ValueError, match=r"junk\.mcap: .*(truncated|corrupt)"):
        RosbagSource(junk)

    tf_only = tmp_path / "tf_only.bag"
    b = BagBuilder(1)
    from rosbags.rosbag1 import Writer

    with Writer(tf_only) as w:
        c = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=b.ts)
        w.write(c, 1, b.ts.serialize_ros1(b.tf(0.0, "map", "base", np.eye(4)), "tf2_msgs/msg/TFMessage"))
    with pytest.raises(ValueError, match=r"tf_only\.bag: no depth topic .*image topics: none"):
        RosbagSource(tf_only)
    with pytest.raises(ValueError, match="not a ROS bag"):
        RosbagSource(tmp_path)


@pytest.mark.realdata
def test_the_realsense_sdk_recording_reads_as_the_realsense_source_reads_it(realdata):
    """lrs_unittest_bag_d435 through the bag source: the SDK's depth (bit for bit), intrinsics, depth unit."""
    import json

    path = realdata / "lrs_unittest_bag_d435" / "single_depth_color_640x480.bag"
    src = RosbagSource(path)
    frames = list(src)
    fig = json.loads((realdata / "lrs_unittest_bag_d435" / "figures.json").read_text())
    fx, fy, cx, cy = fig["K"]
    for f in frames:
        np.testing.assert_array_equal(f.K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
        assert f.depth_scale == fig["info"]["depth_scale"] and f.depth.shape == (480, 640) and f.T_map_cam is None
    try:
        from elevmap.sources.realsense import RealSenseFileSource

        rs_frames = list(RealSenseFileSource(path))
    except ImportError:
        pytest.skip("pyrealsense2 (or libusb-1.0) not available: compared with figures.json only")
    assert [f.stamp for f in frames] == [f.stamp for f in rs_frames]
    for a, b in zip(frames, rs_frames):
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.K, b.K)
        assert a.depth_scale == b.depth_scale


@pytest.mark.realdata
def test_open_source_keeps_sdk_playback_and_takes_ros_options(realdata):
    from elevmap.sources.open import open_source

    path = str(realdata / "lrs_unittest_bag_d435" / "single_depth_color_640x480.bag")
    assert type(open_source(path, depth_topics=["/device_0/sensor_0/Depth_0/image/data"])).__name__ == "RosbagSource"
    with pytest.raises(ValueError, match="are options of ROS bag sources"):
        open_source(str(REALDATA / "lrs_unittest_bag_d435"), map_frame="map")


@pytest.mark.parametrize("compress", [True, False])
def test_a_realsense_sdk_db3_reads_as_the_sdk_plays_it(tmp_path, compress):
    """The SDK's own .db3 (compressedDepth or raw): depth bit for bit, intrinsics, depth unit and sensor stamps."""
    try:
        from elevmap.sources.realsense import RealSenseFileSource, record_db3
        import_ok = __import__("pyrealsense2").pipeline is not None
    except (ImportError, AttributeError):
        import_ok = False
    if not import_ok:
        pytest.skip("pyrealsense2 (or libusb-1.0) not available to write a RealSense .db3")
    rng = np.random.default_rng(0)
    depth = rng.integers(300, 3000, size=(3, 60, 80)).astype(np.uint16)
    depth[:, :4] = 0
    K = np.array([[80.0, 0.0, 39.5], [0.0, 80.0, 29.5], [0.0, 0.0, 1.0]])
    path = record_db3(tmp_path / "sdk.db3", list(depth), K, depth_scale=0.001, fps=15, compress=compress)
    frames = list(RosbagSource(path))
    sdk = list(RealSenseFileSource(path))
    assert len(frames) == len(sdk) == 3
    for a, b, d in zip(frames, sdk, depth):
        np.testing.assert_array_equal(a.depth, d)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.K, b.K)
        assert (a.depth_scale, a.stamp) == (b.depth_scale, b.stamp)


def test_pose_with_covariance_stamped_needs_the_base_frame(tmp_path):
    path = write_bag(tmp_path / "pose.bag", "bag", poses="pose_cov")
    with pytest.raises(ValueError, match=r"/pose \(geometry_msgs/msg/PoseWithCovarianceStamped\) does not name the "
                                         r"robot's frame; give it as the base frame \(--base-frame\)"):
        RosbagSource(path)
    src = RosbagSource(path, base_frame="base_link")
    assert src.pose_source == "odometry /pose" and src.map_frame == "odom"
    f = list(src)[2]
    s = frame_stamps()[2]
    np.testing.assert_allclose(f.T_map_cam, T_map_base(s) @ T_base_cam(), atol=1e-9)
    np.testing.assert_allclose(f.pose_cov, carry_pose_cov(ODOM_COV, T_map_base(s), T_base_cam()), rtol=1e-9,
                               atol=1e-15)
