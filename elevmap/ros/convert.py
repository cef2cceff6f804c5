"""Conversions between ROS messages and the arrays elevmap works with, both ways.

Messages are rosbags message objects (``typestore.types[...]``, as a reader yields them or
:mod:`elevmap.ros.msgs` builds them); ROS 1 and ROS 2 spellings are both read (``K``/``k``,
``D``/``d``, ``nanosec``/``nsec``). The functions that read a message take ``where`` (file and topic)
and raise ``ValueError`` naming it, the field and what is wrong.

Depth conventions (REP 118): ``16UC1``/``mono16`` images hold millimetres (0 = no data), ``32FC1``
metres (NaN or 0 = no data). image_transport's ``compressedDepth`` format is a 12-byte header
(int32 ``format``, float32 ``depthQuantA``, float32 ``depthQuantB``) followed by a PNG: of the 16-bit
depth itself for ``16UC1``, of the quantised inverse depth ``q = A / z + B`` for ``32FC1`` (decoded
as ``z = A / (q - B)``, q = 0 meaning no data).
"""

from __future__ import annotations

import io
import math
import struct

import numpy as np

from noise_model.checks import check_transform

from .msgs import GRID, GRID_MAP, typestore

__all__ = [
    "stamp_seconds", "time_message", "image_to_depth", "compressed_depth_to_depth", "camera_info_to_K",
    "transform_to_matrix", "pose_to_matrix", "matrix_to_transform", "matrix_to_pose", "pose_with_covariance",
    "grid_map_message", "grid_message", "grid_map_from_message", "DEPTH_ENCODINGS", "MM_PER_UNIT_DEPTH_SCALE",
]

#: Image encodings read as depth, and the element type of each.
DEPTH_ENCODINGS = {"16UC1": np.uint16, "mono16": np.uint16, "32FC1": np.float32}
#: Metres per unit of a 16-bit depth image (REP 118: millimetres).
MM_PER_UNIT_DEPTH_SCALE = 0.001
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def stamp_seconds(stamp) -> float:
    """A ``builtin_interfaces/Time`` (or ROS 1 ``time``) as seconds [s]."""
    nsec = getattr(stamp, "nanosec", None)
    if nsec is None:
        nsec = stamp.nsec
    return float(stamp.sec) + 1e-9 * float(nsec)


def time_message(seconds: float, ros_version: int = 2):
    """Seconds [s] (>= 0, finite) as a ``builtin_interfaces/Time`` of the store of ``ros_version``."""
    s = float(seconds)
    if not math.isfinite(s) or s < 0:
        raise ValueError(f"a ROS time must be finite and >= 0 s, got {seconds!r}")
    ns = int(round(s * 1e9))
    return typestore(ros_version).types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000,
                                                                         nanosec=ns % 1_000_000_000)


def _byte_array(data) -> np.ndarray:
    """A message's ``uint8[]`` as a uint8 array: NumPy (rosbags), bytes or array.array (rclpy), or a list."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    return np.asarray(data, dtype=np.uint8)


def _check_image_size(height, width, where):
    if int(height) < 1 or int(width) < 1:
        raise ValueError(f"{where}: image size {width}x{height} is empty")


def image_to_depth(msg, where: str = "image") -> np.ndarray:
    """A ``sensor_msgs/Image`` of depth as an array, its row ``step`` and ``is_bigendian`` honoured.

    Parameters
    ----------
    msg : sensor_msgs/Image
        Encoding ``16UC1`` or ``mono16`` (depth units, 0 = no data) or ``32FC1`` (metres).
    where : str
        File and topic, for messages.

    Returns
    -------
    ndarray, shape (height, width)
        uint16 depth units, or float32 metres; a native-endian copy (the message may be freed).

    Raises
    ------
    ValueError
        Another encoding, a step shorter than a row, or data shorter than ``step * height``.
    """
    enc = str(msg.encoding)
    if enc not in DEPTH_ENCODINGS:
        raise ValueError(f"{where}: image encoding {enc!r} is not depth; expected one of {', '.join(DEPTH_ENCODINGS)}")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    _check_image_size(h, w, where)
    dtype = np.dtype(DEPTH_ENCODINGS[enc]).newbyteorder(">" if msg.is_bigendian else "<")
    row = w * dtype.itemsize
    if step < row:
        raise ValueError(f"{where}: step {step} bytes is shorter than a row of {w} {enc} pixels ({row} bytes)")
    data = _byte_array(msg.data)
    if data.size < step * h:
        raise ValueError(f"{where}: image data has {data.size} bytes, {step} x {h} rows need {step * h}")
    rows = data[: step * h].reshape(h, step)[:, :row]
    return np.ascontiguousarray(rows).view(dtype).reshape(h, w).astype(dtype.newbyteorder("="))


def compressed_depth_to_depth(msg, where: str = "image") -> np.ndarray:
    """A ``sensor_msgs/CompressedImage`` in image_transport's ``compressedDepth`` format as an array.

    Parameters
    ----------
    msg : sensor_msgs/CompressedImage
        ``format`` such as ``"16UC1; compressedDepth png"`` or ``"32FC1; compressedDepth"``; ``data``
        the 12-byte header and a PNG.

    Returns
    -------
    ndarray, shape (H, W)
        uint16 depth units (``16UC1``), or float32 metres (``32FC1``, NaN = no data).

    Raises
    ------
    ValueError
        Not ``compressedDepth``, another depth encoding or codec (e.g. RVL), a header without a PNG
        after it, or a PNG that does not decode to a 16-bit single-channel image.
    """
    fmt = str(msg.format)
    head, _, rest = fmt.partition(";")
    enc = head.strip()
    if "compressedDepth" not in rest and "compressedDepth" not in fmt:
        raise ValueError(f"{where}: compressed image format {fmt!r} is not compressedDepth")
    codec = rest.replace("compressedDepth", "").strip() or "png"
    if codec != "png":
        raise ValueError(f"{where}: compressedDepth codec {codec!r} is not supported (only png)")
    if enc not in ("16UC1", "32FC1"):
        raise ValueError(f"{where}: compressedDepth of encoding {enc!r}; expected 16UC1 or 32FC1")
    raw = _byte_array(msg.data).tobytes()
    if len(raw) < 12 + len(_PNG_SIGNATURE) or raw[12:12 + len(_PNG_SIGNATURE)] != _PNG_SIGNATURE:
        raise ValueError(f"{where}: compressedDepth data ({len(raw)} bytes) is not a 12-byte header and a PNG")
    _, quant_a, quant_b = struct.unpack("<iff", raw[:12])
    from PIL import Image

    try:
        with Image.open(io.BytesIO(raw[12:])) as img:
            img.load()
            mode = img.mode
            q = np.asarray(img)
    except (OSError, ValueError, SyntaxError) as exc:
        raise ValueError(f"{where}: the compressedDepth PNG does not decode ({exc})") from None
    if q.ndim != 2 or not mode.startswith("I;16"):
        raise ValueError(f"{where}: the compressedDepth PNG is {mode} of shape {q.shape}, not 16-bit single-channel")
    q = np.ascontiguousarray(q, dtype=np.uint16)
    _check_image_size(q.shape[0], q.shape[1], where)
    if enc == "16UC1":
        return q
    if not (math.isfinite(quant_a) and math.isfinite(quant_b)) or quant_a <= 0:
        raise ValueError(f"{where}: compressedDepth quantisation A={quant_a}, B={quant_b} is not usable")
    z = np.full(q.shape, np.nan, dtype=np.float32)
    valid = q > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        z[valid] = (quant_a / (q[valid].astype(np.float32) - quant_b)).astype(np.float32)
    z[~np.isfinite(z) | (z <= 0)] = np.nan
    return z


def camera_info_to_K(msg, where: str = "camera_info") -> tuple[np.ndarray, int, int]:
    """The pinhole matrix of a ``sensor_msgs/CameraInfo`` (ROS 1 ``K``, ROS 2 ``k``) and its image size.

    Returns
    -------
    K : ndarray, shape (3, 3)
        [px]; the depth image is taken as rectified (a D435 depth stream is).
    width, height : int
        [px].

    Raises
    ------
    ValueError
        K not finite, a focal length <= 0, or a bottom row other than (0, 0, 1).
    """
    k = getattr(msg, "k", None)
    if k is None:
        k = msg.K
    K = np.asarray(k, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(K)):
        raise ValueError(f"{where}: K has non-finite entries: {K.ravel().tolist()}")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"{where}: K has focal lengths fx={K[0, 0]}, fy={K[1, 1]}; both must be > 0 "
                         "(an uncalibrated camera publishes zeros)")
    if not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"{where}: K's last row is {K[2].tolist()}, not (0, 0, 1)")
    return K, int(msg.width), int(msg.height)


def _quaternion_matrix(q, where: str) -> np.ndarray:
    x, y, z, w = (float(q.x), float(q.y), float(q.z), float(q.w))
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(n) or n < 1e-6:
        raise ValueError(f"{where}: quaternion ({x}, {y}, {z}, {w}) has norm {n}; it is not a rotation")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _matrix(translation, rotation, where: str) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _quaternion_matrix(rotation, where)
    T[:3, 3] = [float(translation.x), float(translation.y), float(translation.z)]
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{where}: translation ({T[0, 3]}, {T[1, 3]}, {T[2, 3]}) is not finite")
    return T


def transform_to_matrix(transform, where: str = "transform") -> np.ndarray:
    """A ``geometry_msgs/Transform`` as a 4 x 4 matrix ``T_parent_child`` (quaternion normalised)."""
    return _matrix(transform.translation, transform.rotation, where)


def pose_to_matrix(pose, where: str = "pose") -> np.ndarray:
    """A ``geometry_msgs/Pose`` as a 4 x 4 matrix ``T_frame_body``."""
    return _matrix(pose.position, pose.orientation, where)


def _quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix, w >= 0."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    return float(x), float(y), float(z), float(w)


def matrix_to_transform(T, ros_version: int = 2):
    """A 4 x 4 rigid transform as a ``geometry_msgs/Transform``."""
    T = check_transform(T, "T")
    t = typestore(ros_version).types
    x, y, z, w = _quaternion(T[:3, :3])
    return t["geometry_msgs/msg/Transform"](translation=t["geometry_msgs/msg/Vector3"](*map(float, T[:3, 3])),
                                             rotation=t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))


def matrix_to_pose(T, ros_version: int = 2):
    """A 4 x 4 rigid transform as a ``geometry_msgs/Pose``."""
    T = check_transform(T, "T")
    t = typestore(ros_version).types
    x, y, z, w = _quaternion(T[:3, :3])
    return t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](*map(float, T[:3, 3])),
                                        orientation=t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))


#: Relative asymmetry tolerated in a covariance before it is called not symmetric.
_COV_SYMMETRY_TOL = 1e-6


def pose_with_covariance(msg, where: str = "pose") -> tuple[np.ndarray, np.ndarray]:
    """A ``geometry_msgs/PoseWithCovariance`` as ``T_frame_body`` (4, 4) and its covariance (6, 6).

    ROS orders the covariance (x, y, z, rotation about x, y, z) with the rotation about the fixed
    axes of the message's frame, which is the pose error elevmap uses (``Frame.pose_cov``).

    Raises
    ------
    ValueError
        The covariance is not 36 finite numbers, is not symmetric, or has a negative diagonal.
    """
    T = pose_to_matrix(msg.pose, where)
    cov = np.asarray(msg.covariance, dtype=np.float64)
    if cov.size != 36 or not np.all(np.isfinite(cov)):
        raise ValueError(f"{where}: pose covariance must be 36 finite numbers, got {cov.size} "
                         f"({int(np.sum(~np.isfinite(cov)))} non-finite)")
    cov = cov.reshape(6, 6)
    scale = max(float(np.abs(cov).max()), 1e-300)
    if np.abs(cov - cov.T).max() > _COV_SYMMETRY_TOL * scale:
        raise ValueError(f"{where}: pose covariance is not symmetric")
    if np.any(np.diag(cov) < 0):
        raise ValueError(f"{where}: pose covariance has a negative variance: diag {np.diag(cov).tolist()}")
    return T, 0.5 * (cov + cov.T)


def _header(ros_version: int, stamp: float, frame_id: str):
    t = typestore(ros_version).types
    kw = {"seq": 0} if ros_version == 1 else {}
    return t["std_msgs/msg/Header"](**kw, stamp=time_message(stamp, ros_version), frame_id=str(frame_id))


def grid_map_message(grid: dict, ros_version: int = 2):
    """A ``grid_map_msgs/GridMap`` message from the content :func:`elevmap.map.grid_map.to_grid_map` returns.

    Parameters
    ----------
    grid : dict
        ``emap.to_grid_map(...)``: layers already float32, grid_map's index order, column-major.
    ros_version : {1, 2}
        ROS 1 layout (header in ``GridMapInfo``) or ROS 2 layout (header in ``GridMap``).

    Returns
    -------
    grid_map_msgs/msg/GridMap
        Of the type store :func:`elevmap.ros.msgs.typestore` ``(ros_version)``; the map's centre is
        the pose's position (z = 0, identity orientation), the stamp the map's last update (0 before
        any).
    """
    t = typestore(ros_version).types
    stamp = grid["stamp"] if math.isfinite(grid["stamp"]) else 0.0
    header = _header(ros_version, stamp, grid["frame_id"])
    pose = t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=grid["position"][0],
                                                                             y=grid["position"][1], z=0.0),
                                        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    info_kw = dict(resolution=grid["resolution"], length_x=grid["length_x"], length_y=grid["length_y"], pose=pose)
    info = t["grid_map_msgs/msg/GridMapInfo"](**({"header": header} if ros_version == 1 else {}), **info_kw)
    Dim, Layout, F32 = (t["std_msgs/msg/MultiArrayDimension"], t["std_msgs/msg/MultiArrayLayout"],
                        t["std_msgs/msg/Float32MultiArray"])
    layout = Layout(dim=[Dim(label=d["label"], size=d["size"], stride=d["stride"]) for d in grid["layout"]],
                    data_offset=0)
    data = [F32(layout=layout, data=np.asarray(grid["data"][name], dtype=np.float32)) for name in grid["layers"]]
    kw = dict(info=info, layers=list(grid["layers"]), basic_layers=list(grid["basic_layers"]), data=data,
              outer_start_index=grid["outer_start_index"], inner_start_index=grid["inner_start_index"])
    if ros_version == 2:
        kw = {"header": header, **kw}
    return t[GRID_MAP](**kw)


def grid_map_from_message(msg) -> dict:
    """The layers of a ``grid_map_msgs/GridMap`` (either layout) in map-index order.

    Returns
    -------
    dict
        ``frame_id``, ``stamp`` [s], ``resolution`` [m], ``length`` (x, y) [m], ``position`` (x, y) [m],
        ``layers`` {name: float32 (rows, cols)} with ``[i, j]`` the cell centred at
        ``x = position_x - length_x/2 + res (i + 1/2)``, ``y = position_y - length_y/2 + res (j + 1/2)``
        (grid_map's circular-buffer start indices undone).
    """
    header = msg.header if hasattr(msg, "header") else msg.info.header
    info = msg.info
    out = {"frame_id": header.frame_id, "stamp": stamp_seconds(header.stamp), "resolution": info.resolution,
           "length": (info.length_x, info.length_y), "position": (info.pose.position.x, info.pose.position.y),
           "layers": {}}
    for name, arr in zip(msg.layers, msg.data):
        dims = arr.layout.dim
        if len(dims) != 2 or dims[0].label != "column_index":
            raise ValueError(f"GridMap layer {name!r}: layout {[d.label for d in dims]} is not column-major "
                             "(column_index, row_index)")
        cols, rows = int(dims[0].size), int(dims[1].size)
        M = np.asarray(arr.data, dtype=np.float32)[arr.layout.data_offset:].reshape(cols, rows).T
        M = np.roll(M, (-int(msg.outer_start_index), -int(msg.inner_start_index)), axis=(0, 1))
        out["layers"][name] = M[::-1, ::-1]
    return out


#: PackedElementField.FLOAT32.
_FLOAT32 = 7


def grid_message(grid: dict, ros_version: int = 2):
    """A ``foxglove_msgs/Grid`` of every layer of a grid_map content (one float32 field per layer).

    The Grid's pose is its corner at (position - length/2, 0) with identity orientation; its data are
    row-major with x along a row: the element of row j, column i is the cell centred at
    ``corner + res (i + 1/2, j + 1/2)``, so Foxglove draws each cell where the map has it.
    """
    t = typestore(ros_version).types
    n_rows, n_cols = grid["size"]
    names = list(grid["layers"])
    cell = np.empty((n_cols, n_rows, len(names)), dtype="<f4")         # [j (y), i (x), field]
    for k, name in enumerate(names):
        # column-major grid_map data reshaped (cols, rows) is M^T; flipping both gives layer^T, i.e. [j, i]
        cell[:, :, k] = np.asarray(grid["data"][name], dtype=np.float32).reshape(n_cols, n_rows)[::-1, ::-1]
    res = grid["resolution"]
    corner_x = grid["position"][0] - grid["length_x"] / 2
    corner_y = grid["position"][1] - grid["length_y"] / 2
    pose = t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=corner_x, y=corner_y, z=0.0),
                                        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    field = t["foxglove_msgs/msg/PackedElementField"]
    stamp = grid["stamp"] if math.isfinite(grid["stamp"]) else 0.0
    return t[GRID](timestamp=time_message(stamp, ros_version), frame_id=grid["frame_id"], pose=pose,
                   column_count=n_rows, cell_size=t["foxglove_msgs/msg/Vector2"](x=res, y=res),
                   row_stride=4 * len(names) * n_rows, cell_stride=4 * len(names),
                   fields=[field(name=name, offset=4 * k, type=_FLOAT32) for k, name in enumerate(names)],
                   data=cell.reshape(-1).view(np.uint8))
