"""elevmap.ros: message definitions and conversions, hand-worked values and round trips."""

from __future__ import annotations

import io
import struct

import numpy as np
import pytest
from PIL import Image

from elevmap.ros import convert as cv
from elevmap.ros.msgs import GRID, GRID_MAP, GRID_MAP_ROS1_MD5, message_definition, typestore
from rosbag_scenes import BagBuilder


def test_ros1_grid_map_md5_is_the_one_ros_computes():
    """A ROS 1 subscriber accepts a GridMap only with this md5; rosbags computes it from our definitions."""
    assert message_definition(GRID_MAP, 1)[1] == GRID_MAP_ROS1_MD5 == "95681e052b1f73bf87b7eb984382b401"
    assert message_definition("tf2_msgs/msg/TFMessage", 1)[1] == "94810edda583a504dfda3829e70d7eec"


def test_grid_map_layouts_put_the_header_where_grid_map_does():
    ros1, ros2 = (message_definition(GRID_MAP, v)[0].split("=" * 80)[0].split() for v in (1, 2))
    assert ros1[:2] == ["grid_map_msgs/GridMapInfo", "info"]             # ROS 1: header inside GridMapInfo
    assert ros2[:4] == ["std_msgs/Header", "header", "grid_map_msgs/GridMapInfo", "info"]
    info1 = typestore(1).get_msgdef("grid_map_msgs/msg/GridMapInfo").fields
    info2 = typestore(2).get_msgdef("grid_map_msgs/msg/GridMapInfo").fields
    assert [f[0] for f in info1] == ["header", "resolution", "length_x", "length_y", "pose"]
    assert [f[0] for f in info2] == ["resolution", "length_x", "length_y", "pose"]


def test_foxglove_grid_fields_match_the_sdk_schema():
    """Our foxglove_msgs/Grid has the fields, in order, of the foxglove.Grid schema foxglove-sdk ships."""
    foxglove = pytest.importorskip("foxglove", reason="foxglove-sdk (the foxglove extra) not installed")
    from foxglove.messages import Grid

    schema = Grid.get_schema().data
    names = [f[0] for f in typestore(2).get_msgdef(GRID).fields]
    assert names == ["timestamp", "frame_id", "pose", "column_count", "cell_size", "row_stride", "cell_stride",
                     "fields", "data"]
    grid_part = schema[schema.index(b"foxglove/Grid.proto"):]
    at = [grid_part.index(b"R" + bytes([len(n)]) + n.encode()) if n != "frame_id" else grid_part.index(b"frameId")
          for n in ("timestamp", "frame_id", "pose")] + [grid_part.index(b"\n" + bytes([len(n)]) + n.encode())
                                                       for n in names[3:]]
    assert at == sorted(at)
    pef = typestore(2).get_msgdef("foxglove_msgs/msg/PackedElementField").fields
    assert [f[0] for f in pef] == ["name", "offset", "type"]


def test_image_to_depth_honours_step_and_endianness():
    b = BagBuilder(2)
    z = np.array([[0.5, np.nan, 1.234], [2.0, 0.001, 65.535]])
    for big in (False, True):
        msg = b.image(0.0, "f", z, "16UC1", bigendian=big, pad=3)
        assert msg.step == 3 * 2 + 3
        d = cv.image_to_depth(msg)
        assert d.dtype == np.uint16 and d.dtype.isnative
        np.testing.assert_array_equal(d, [[500, 0, 1234], [2000, 1, 65535]])
    f = cv.image_to_depth(b.image(0.0, "f", z, "32FC1", bigendian=True, pad=2))
    assert f.dtype == np.float32
    np.testing.assert_array_equal(f, z.astype(np.float32))
    mono = b.image(0.0, "f", z, "16UC1")
    mono.encoding = "mono16"
    np.testing.assert_array_equal(cv.image_to_depth(mono), [[500, 0, 1234], [2000, 1, 65535]])


def test_image_errors_name_the_topic_and_field():
    b = BagBuilder(2)
    msg = b.image(0.0, "f", np.ones((2, 3)), "16UC1")
    msg.encoding = "rgb8"
    with pytest.raises(ValueError, match=r"x.bag: /cam: image encoding 'rgb8' is not depth"):
        cv.image_to_depth(msg, "x.bag: /cam")
    msg = b.image(0.0, "f", np.ones((2, 3)), "16UC1")
    msg.step = 4
    with pytest.raises(ValueError, match="step 4 bytes is shorter than a row"):
        cv.image_to_depth(msg)
    msg = b.image(0.0, "f", np.ones((2, 3)), "16UC1")
    msg.data = msg.data[:-1]
    with pytest.raises(ValueError, match="11 bytes, 6 x 2 rows need 12"):
        cv.image_to_depth(msg)


def _compressed(fmt, header, png_array):
    buf = io.BytesIO()
    Image.fromarray(png_array).save(buf, format="PNG")
    b = BagBuilder(2)
    return b.t["sensor_msgs/msg/CompressedImage"](header=b.header(0.0, "f"), format=fmt,
                                                   data=np.frombuffer(header + buf.getvalue(), np.uint8))


def test_compressed_depth_16bit_and_inverse_depth():
    mm = np.array([[0, 1000, 65535], [1, 2500, 400]], dtype=np.uint16)
    d = cv.compressed_depth_to_depth(_compressed("16UC1; compressedDepth png", struct.pack("<iff", 0, 0, 0), mm))
    np.testing.assert_array_equal(d, mm)
    # 32FC1: image_transport stores q = A / z + B; with A = 100 and B = -10, z = 2 m gives q = 40
    A, B = 100.0, -10.0
    q = np.array([[40, 0], [90, 15]], dtype=np.uint16)
    z = cv.compressed_depth_to_depth(_compressed("32FC1; compressedDepth", struct.pack("<iff", 0, A, B), q))
    np.testing.assert_allclose(z, [[2.0, np.nan], [1.0, 4.0]], rtol=1e-6)


def test_compressed_depth_errors():
    hdr = struct.pack("<iff", 0, 0, 0)
    with pytest.raises(ValueError, match="codec 'rvl' is not supported"):
        cv.compressed_depth_to_depth(_compressed("16UC1; compressedDepth rvl", hdr, np.zeros((2, 2), np.uint16)))
    with pytest.raises(ValueError, match="is not compressedDepth"):
        cv.compressed_depth_to_depth(_compressed("jpeg", hdr, np.zeros((2, 2), np.uint16)))
    with pytest.raises(ValueError, match="not 16-bit single-channel"):
        cv.compressed_depth_to_depth(_compressed("16UC1; compressedDepth png", hdr, np.zeros((2, 2), np.uint8)))
    msg = _compressed("16UC1; compressedDepth png", hdr, np.zeros((2, 2), np.uint16))
    msg.data = msg.data[:20]
    with pytest.raises(ValueError, match="does not decode"):
        cv.compressed_depth_to_depth(msg, "b.mcap: /d")
    msg.data = msg.data[12:]
    with pytest.raises(ValueError, match="b.mcap: /d: compressedDepth data .* not a 12-byte header and a PNG"):
        cv.compressed_depth_to_depth(msg, "b.mcap: /d")


def test_camera_info_K_of_ros1_and_ros2():
    K = np.array([[383.5, 0, 320.25], [0, 383.0, 241.5], [0, 0, 1]])
    for v in (1, 2):
        got, w, h = cv.camera_info_to_K(BagBuilder(v).camera_info(0.0, "f", K, 640, 480))
        np.testing.assert_array_equal(got, K)
        assert (w, h) == (640, 480)
    with pytest.raises(ValueError, match="focal lengths fx=0.0"):
        cv.camera_info_to_K(BagBuilder(2).camera_info(0.0, "f", np.zeros((3, 3)), 640, 480))


def test_transforms_and_poses_hand_worked():
    b = BagBuilder(2)
    s = np.sqrt(0.5)
    tr = b.t["geometry_msgs/msg/Transform"](translation=b.t["geometry_msgs/msg/Vector3"](1.0, 2.0, 3.0),
                                             rotation=b.t["geometry_msgs/msg/Quaternion"](0.0, 0.0, 2 * s, 2 * s))
    T = cv.transform_to_matrix(tr)                      # 90 deg about z (quaternion given at norm 2)
    np.testing.assert_allclose(T, [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(cv.transform_to_matrix(cv.matrix_to_transform(T)), T, atol=1e-12)
    np.testing.assert_allclose(cv.pose_to_matrix(cv.matrix_to_pose(T, 1)), T, atol=1e-12)
    tr.rotation.w = tr.rotation.z = 0.0
    with pytest.raises(ValueError, match="norm 0.0; it is not a rotation"):
        cv.transform_to_matrix(tr)


def test_pose_with_covariance_reads_ros_order_and_rejects_bad_covariances():
    b = BagBuilder(2)
    cov = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]) * 1e-4
    cov[0, 5] = cov[5, 0] = 1e-5
    msg = b.t["geometry_msgs/msg/PoseWithCovariance"](pose=b.pose(np.eye(4)), covariance=cov.ravel())
    T, got = cv.pose_with_covariance(msg)
    np.testing.assert_array_equal(got, cov)
    msg.covariance[1] = 1.0                             # (0, 1) without (1, 0)
    with pytest.raises(ValueError, match="not symmetric"):
        cv.pose_with_covariance(msg)
    msg.covariance = -np.eye(6).ravel()
    with pytest.raises(ValueError, match="negative variance"):
        cv.pose_with_covariance(msg)


def _small_map():
    from elevmap import ElevationMap, FusionParams

    # 4 x 4 cells, x 0.8..1.2, y -2.2..-1.8
    em = ElevationMap(0.4, 0.1, centre_xy=(1.0, -2.0), fusion_params=FusionParams(min_points=1))
    em.update(np.array([[0.85, -2.15, 0.3], [1.15, -1.85, 0.7], [1.15, -2.15, 0.5]]), np.full(3, 1e-4), stamp=7.25)
    return em


def test_grid_map_message_round_trip_both_layouts():
    em = _small_map()
    grid = em.to_grid_map(["elevation", "variance", "points"], frame_id="odom")
    for v in (1, 2):
        store = typestore(v)
        msg = cv.grid_map_message(grid, v)
        raw = store.serialize_ros1(msg, GRID_MAP) if v == 1 else store.serialize_cdr(msg, GRID_MAP)
        back = store.deserialize_ros1(raw, GRID_MAP) if v == 1 else store.deserialize_cdr(raw, GRID_MAP)
        for name, arr in zip(back.layers, back.data):
            np.testing.assert_array_equal(arr.data, grid["data"][name])       # NaN in the same cells
        got = cv.grid_map_from_message(back)
        assert got["frame_id"] == "odom" and got["stamp"] == 7.25 and got["position"] == (1.0, -2.0)
        h = em.known_layer("elevation")                  # map-index order [i (x), j (y)]
        np.testing.assert_array_equal(got["layers"]["elevation"], h.astype(np.float32))
        assert got["layers"]["elevation"][0, 0] == np.float32(0.3)        # cell centred at (0.85, -2.15)
        assert got["layers"]["elevation"][3, 3] == np.float32(0.7)        # (1.15, -1.85)


def test_grid_message_places_each_cell_at_its_position():
    em = _small_map()
    grid = em.to_grid_map(["elevation", "variance"])
    msg = cv.grid_message(grid, 2)
    assert (msg.pose.position.x, msg.pose.position.y) == pytest.approx((0.8, -2.2))
    assert msg.column_count == 4 and msg.cell_stride == 8 and msg.row_stride == 32
    assert [f.name for f in msg.fields] == ["elevation", "variance"] and msg.fields[1].offset == 4
    data = np.asarray(msg.data, np.uint8).view("<f4").reshape(4, 4, 2)          # [row j (y), column i (x)]
    for (x, y, z) in [(0.85, -2.15, 0.3), (1.15, -1.85, 0.7), (1.15, -2.15, 0.5)]:
        i = int((x - msg.pose.position.x) / msg.cell_size.x)
        j = int((y - msg.pose.position.y) / msg.cell_size.y)
        assert data[j, i, 0] == np.float32(z)
    assert np.isnan(data[1, 1, 0])
    assert msg.timestamp.sec == 7 and msg.timestamp.nanosec == 250_000_000


def test_messages_with_bytes_data_as_rclpy_gives_them():
    """rclpy holds uint8[] as bytes or array.array; the conversions read them as they read rosbags' arrays."""
    import array

    b = BagBuilder(2)
    msg = b.image(0.0, "f", np.array([[0.5, 1.0]]), "16UC1")
    for data in (bytes(msg.data), array.array("B", bytes(msg.data))):
        msg.data = data
        np.testing.assert_array_equal(cv.image_to_depth(msg), [[500, 1000]])
    c = _compressed("16UC1; compressedDepth png", struct.pack("<iff", 0, 0, 0), np.array([[7, 8]], np.uint16))
    c.data = bytes(c.data)
    np.testing.assert_array_equal(cv.compressed_depth_to_depth(c), [[7, 8]])
