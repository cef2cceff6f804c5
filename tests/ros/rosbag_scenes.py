"""Small ROS bags written with rosbags for the tests: a camera moving over a floor and a box.

The scene: the floor z = 0 and a box 0.4 x 0.4 x 0.2 m centred at (1.5, 0, 0.1) (top at 0.2 m). A robot
(``base_link``) drives 0.35 m along x with a little sideways sway and yaw; its depth camera sits 0.8 m
up, pitched 40 deg down, looking along +x. Depth is rendered noise-free by the simulator's NumPy
reference ray caster and written as millimetres (16UC1), metres (32FC1) or compressedDepth PNG.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np
from PIL import Image
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from noise_model.sim import Box, Scene
from noise_model.sim.render import render_depth_reference

W, H = 160, 120
K = np.array([[100.0, 0.0, 79.5], [0.0, 100.0, 59.5], [0.0, 0.0, 1.0]])
SCENE = Scene([Box((1.5, 0.0, 0.1), (0.4, 0.4, 0.2))], ground_z=0.0)
BOX_TOP_M = 0.2
BOX_XY = (1.5, 0.0)
T0 = 100.0
FRAME_DT = 0.1
N_FRAMES = 8
TF_DT = 0.02


def rot_z(yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def T_map_base(t: float) -> np.ndarray:
    """The robot's pose at time t [s]: 0.35 m along x over the frames, a sway in y and yaw."""
    a = (t - T0) / (FRAME_DT * (N_FRAMES - 1))
    T = np.eye(4)
    T[:3, :3] = rot_z(0.05 * np.sin(3 * a))
    T[:3, 3] = [0.35 * a, 0.05 * np.sin(2 * a), 0.0]
    return T


def T_base_cam(yaw_deg: float = 0.0) -> np.ndarray:
    """The camera's optical frame (x right, y down, z forward) in base_link: 0.8 m up, pitched 40 deg down."""
    p = np.deg2rad(40.0)
    z = np.array([np.cos(p), 0.0, -np.sin(p)])
    x = np.array([0.0, -1.0, 0.0])
    T = np.eye(4)
    T[:3, :3] = rot_z(np.deg2rad(yaw_deg)) @ np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = [0.1, 0.0, 0.8]
    return T


#: The static chain base_link -> camera_link -> camera_depth_optical_frame (camera_link: no rotation).
T_BASE_LINK = np.eye(4)
T_BASE_LINK[:3, 3] = [0.1, 0.0, 0.8]


def depth_m(T_map_cam) -> np.ndarray:
    """Noise-free z-depth [m] of the scene (NaN = no hit)."""
    return render_depth_reference(SCENE, K, W, H, T_map_cam, max_range_m=6.0)[0]


def frame_stamps():
    return [T0 + k * FRAME_DT for k in range(N_FRAMES)]


def _quat(R):
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()


class BagBuilder:
    """Messages of one bag, ROS 1 or ROS 2 (its type store and field spellings)."""

    def __init__(self, ros_version: int):
        self.ros1 = ros_version == 1
        self.ts = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if "tf2_msgs/msg/TFMessage" not in self.ts.types:           # rosbags' ROS 1 store lacks tf2_msgs
            self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                "tf2_msgs/msg/TFMessage"))
        self.t = self.ts.types

    def time(self, s):
        ns = int(round(s * 1e9))
        return self.t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)

    def header(self, s, frame):
        kw = {"seq": 0} if self.ros1 else {}
        return self.t["std_msgs/msg/Header"](**kw, stamp=self.time(s), frame_id=frame)

    def transform(self, T):
        q = _quat(T[:3, :3])
        return self.t["geometry_msgs/msg/Transform"](
            translation=self.t["geometry_msgs/msg/Vector3"](*map(float, T[:3, 3])),
            rotation=self.t["geometry_msgs/msg/Quaternion"](*map(float, q)))

    def pose(self, T):
        q = _quat(T[:3, :3])
        return self.t["geometry_msgs/msg/Pose"](position=self.t["geometry_msgs/msg/Point"](*map(float, T[:3, 3])),
                                                 orientation=self.t["geometry_msgs/msg/Quaternion"](*map(float, q)))

    def tf(self, s, parent, child, T):
        tr = self.t["geometry_msgs/msg/TransformStamped"](header=self.header(s, parent), child_frame_id=child,
                                                          transform=self.transform(T))
        return self.t["tf2_msgs/msg/TFMessage"](transforms=[tr])

    def camera_info(self, s, frame, K=K, width=W, height=H):
        P = np.zeros(12)
        P[[0, 1, 2, 4, 5, 6, 10]] = [K[0, 0], 0, K[0, 2], K[1, 1], K[1, 2], 0, 1]
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        arrays = {"D": np.zeros(5), "K": np.asarray(K, float).ravel(), "R": np.eye(3).ravel(), "P": P}
        if not self.ros1:
            arrays = {k.lower(): v for k, v in arrays.items()}
        return self.t["sensor_msgs/msg/CameraInfo"](header=self.header(s, frame), height=height, width=width,
                                                     distortion_model="plumb_bob", **arrays, binning_x=0,
                                                     binning_y=0, roi=roi)

    def image(self, s, frame, z, encoding="16UC1", bigendian=False, pad=0):
        if encoding == "32FC1":
            a = np.where(np.isfinite(z), z, np.nan).astype(">f4" if bigendian else "<f4")
        else:
            a = np.where(np.isfinite(z), np.round(z * 1000), 0).astype(">u2" if bigendian else "<u2")
        rows = a.view(np.uint8).reshape(a.shape[0], -1)
        data = np.concatenate([rows, np.full((rows.shape[0], pad), 0xAB, np.uint8)], axis=1).ravel()
        return self.t["sensor_msgs/msg/Image"](header=self.header(s, frame), height=a.shape[0], width=a.shape[1],
                                                encoding=encoding, is_bigendian=int(bigendian),
                                                step=rows.shape[1] + pad, data=data)

    def compressed_depth(self, s, frame, z):
        mm = np.where(np.isfinite(z), np.round(z * 1000), 0).astype(np.uint16)
        buf = io.BytesIO()
        Image.fromarray(mm).save(buf, format="PNG")
        data = struct.pack("<iff", 0, 0.0, 0.0) + buf.getvalue()
        return self.t["sensor_msgs/msg/CompressedImage"](header=self.header(s, frame),
                                                          format="16UC1; compressedDepth png",
                                                          data=np.frombuffer(data, np.uint8))

    def odometry(self, s, T, cov):
        t = self.t
        twist = t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](linear=t["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
                                               angular=t["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0)),
            covariance=np.zeros(36))
        return t["nav_msgs/msg/Odometry"](header=self.header(s, "odom"), child_frame_id="base_link",
                                          pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(T),
                                                                                         covariance=cov.ravel()),
                                          twist=twist)


#: The odometry's pose covariance: 1 cm, 1 cm, 0.5 cm, 0.2, 0.2, 0.5 deg, with an x-yaw correlation.
ODOM_COV = np.diag([1e-4, 1e-4, 2.5e-5, np.deg2rad(0.2) ** 2, np.deg2rad(0.2) ** 2, np.deg2rad(0.5) ** 2])
ODOM_COV[0, 5] = ODOM_COV[5, 0] = 0.5 * np.sqrt(ODOM_COV[0, 0] * ODOM_COV[5, 5])


def write_bag(path, kind: str = "bag", *, depth: str = "16UC1", poses: str = "tf", cameras=(("camera", 0.0),),
              extra=None) -> Path:
    """Write a bag of the scene.

    kind: "bag" (ROS 1), "db3" (ROS 2 folder, sqlite3), "mcap" (ROS 2 folder, MCAP, zstd per message),
    "bare_mcap" (one MCAP file). depth: "16UC1", "32FC1", "16UC1_be_padded" or "compressed".
    poses: "tf" (/tf map -> base_link and /tf_static to the camera), "odometry" (nav_msgs/Odometry
    odom -> base_link with ODOM_COV, /tf_static only) or "pose_cov" (the same poses as
    geometry_msgs/PoseWithCovarianceStamped, which names no child frame). cameras: (name, yaw deg) of each depth camera.
    extra(builder, write) may write more messages: write(topic, msgtype, stamp, msg).
    """
    path = Path(path)
    b = BagBuilder(1 if kind == "bag" else 2)
    msgs = []

    def write(topic, msgtype, stamp, msg):
        msgs.append((topic, msgtype, stamp, msg))

    for name, yaw in cameras:
        T_link_opt = np.linalg.inv(T_BASE_LINK) @ T_base_cam(yaw)
        write("/tf_static", "tf2_msgs/msg/TFMessage", T0 - 1.0,
              b.tf(T0 - 1.0, "base_link", f"{name}_link", T_BASE_LINK))
        write("/tf_static", "tf2_msgs/msg/TFMessage", T0 - 1.0,
              b.tf(T0 - 1.0, f"{name}_link", f"{name}_depth_optical_frame", T_link_opt))
    t = T0 - 0.1
    while t <= T0 + FRAME_DT * (N_FRAMES - 1) + 0.1 + 1e-9:
        if poses == "tf":
            write("/tf", "tf2_msgs/msg/TFMessage", t, b.tf(t, "map", "base_link", T_map_base(t)))
        elif poses == "pose_cov":
            msg = b.t["geometry_msgs/msg/PoseWithCovarianceStamped"](
                header=b.header(t, "odom"), pose=b.t["geometry_msgs/msg/PoseWithCovariance"](
                    pose=b.pose(T_map_base(t)), covariance=ODOM_COV.ravel()))
            write("/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", t, msg)
        else:
            write("/odom", "nav_msgs/msg/Odometry", t, b.odometry(t, T_map_base(t), ODOM_COV))
        t += TF_DT
    for s in frame_stamps():
        for name, yaw in cameras:
            frame = f"{name}_depth_optical_frame"
            z = depth_m(T_map_base(s) @ T_base_cam(yaw))
            ns = f"/{name}/depth"
            write(f"{ns}/camera_info", "sensor_msgs/msg/CameraInfo", s, b.camera_info(s, frame))
            if depth == "compressed":
                write(f"{ns}/image_rect_raw/compressedDepth", "sensor_msgs/msg/CompressedImage", s,
                      b.compressed_depth(s, frame, z))
            elif depth == "16UC1_be_padded":
                write(f"{ns}/image_rect_raw", "sensor_msgs/msg/Image", s, b.image(s, frame, z, "16UC1", True, 6))
            else:
                write(f"{ns}/image_rect_raw", "sensor_msgs/msg/Image", s, b.image(s, frame, z, depth))
    if extra is not None:
        extra(b, write)
    msgs.sort(key=lambda m: m[2])
    serialise = b.ts.serialize_ros1 if b.ros1 else b.ts.serialize_cdr
    if kind == "bag":
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        folder = path if kind != "bare_mcap" else path.with_suffix("")
        plugin = StoragePlugin.SQLITE3 if kind == "db3" else StoragePlugin.MCAP
        writer = Writer(folder, version=9, storage_plugin=plugin)
        if kind == "mcap":
            writer.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    conns = {}
    with writer:
        for topic, msgtype, stamp, msg in msgs:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=b.ts)
            writer.write(conns[topic], int(round(stamp * 1e9)), serialise(msg, msgtype))
    if kind == "bare_mcap":
        inner = next(folder.glob("*.mcap"))
        inner.rename(path)
        for f in folder.iterdir():
            f.unlink()
        folder.rmdir()
    return path


def unmappable_extras(b: BagBuilder, write):
    """A depth topic without camera info, and one /camera frame 1 s after the last transform."""
    late = T0 + 0.1 * N_FRAMES + 1.0
    z = depth_m(T_map_base(T0) @ T_base_cam())
    for s in frame_stamps()[:3]:
        write("/rear/depth/image_rect_raw", "sensor_msgs/msg/Image", s, b.image(s, "rear_optical", z[::2, ::2]))
    write("/camera/depth/image_rect_raw", "sensor_msgs/msg/Image", late, b.image(late, "camera_depth_optical_frame", z))
    write("/camera/color/image_raw", "sensor_msgs/msg/Image", T0, b.t["sensor_msgs/msg/Image"](
        header=b.header(T0, "color"), height=1, width=1, encoding="rgb8", is_bigendian=0, step=3,
        data=np.zeros(3, np.uint8)))
