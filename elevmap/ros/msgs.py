"""Message definitions the ROS package writes, and the rosbags type stores that know them.

``rosbags`` serialises any message type from its ``.msg`` text. Its built-in stores hold the
standard packages (std_msgs, geometry_msgs, sensor_msgs, nav_msgs, tf2_msgs); this module adds

* ``grid_map_msgs/GridMap`` and ``GridMapInfo`` of ANYbotics' grid_map, in both layouts: ROS 1
  (``master``: the header inside ``GridMapInfo``) and ROS 2 (``humble`` and later: the header in
  ``GridMap``, ``GridMapInfo`` without one). The ROS 1 definitions hash to the md5 ROS computes,
  :data:`GRID_MAP_ROS1_MD5`, which a ROS 1 subscriber checks before it accepts a message;
* ``foxglove_msgs/Grid``, ``PackedElementField`` and ``Vector2`` (foxglove-sdk's ``schemas/ros1``
  and ``schemas/ros2``; the fields and their order are those of the ``foxglove.Grid`` schema the
  foxglove-sdk package ships), which Foxglove and Lichtblick draw as a height field.

The ``.msg`` texts below are the field lines of those files (comments left out: they do not enter the
md5 nor the serialised bytes).
"""

from __future__ import annotations

import functools

__all__ = ["GRID_MAP_ROS1", "GRID_MAP_ROS2", "FOXGLOVE_ROS1", "FOXGLOVE_ROS2", "GRID_MAP_ROS1_MD5",
           "GRID_MAP", "GRID_MAP_INFO", "GRID", "TF_MESSAGE", "typestore", "message_definition", "serialize"]

#: Type names (rosbags spells every type ``pkg/msg/Name``, ROS 1 types too).
GRID_MAP = "grid_map_msgs/msg/GridMap"
GRID_MAP_INFO = "grid_map_msgs/msg/GridMapInfo"
GRID = "foxglove_msgs/msg/Grid"

#: md5 of ``grid_map_msgs/GridMap`` as ROS 1 computes it (``rosmsg md5 grid_map_msgs/GridMap``).
GRID_MAP_ROS1_MD5 = "95681e052b1f73bf87b7eb984382b401"

_GRID_MAP_FIELDS = """\
string[] layers
string[] basic_layers
std_msgs/Float32MultiArray[] data
uint16 outer_start_index
uint16 inner_start_index
"""

_INFO_FIELDS = """\
float64 resolution
float64 length_x
float64 length_y
geometry_msgs/Pose pose
"""

#: grid_map_msgs, ROS 1 layout (ANYbotics/grid_map ``master``).
GRID_MAP_ROS1 = {
    GRID_MAP_INFO: "std_msgs/Header header\n" + _INFO_FIELDS,
    GRID_MAP: "grid_map_msgs/GridMapInfo info\n" + _GRID_MAP_FIELDS,
}

#: grid_map_msgs, ROS 2 layout (ANYbotics/grid_map ``humble``, ``jazzy``, ``rolling``).
GRID_MAP_ROS2 = {
    GRID_MAP_INFO: _INFO_FIELDS,
    GRID_MAP: "std_msgs/Header header\ngrid_map_msgs/GridMapInfo info\n" + _GRID_MAP_FIELDS,
}

_PACKED_ELEMENT_FIELD = """\
string name
uint32 offset
uint8 UNKNOWN=0
uint8 UINT8=1
uint8 INT8=2
uint8 UINT16=3
uint8 INT16=4
uint8 UINT32=5
uint8 INT32=6
uint8 FLOAT32=7
uint8 FLOAT64=8
uint8 type
"""

_GRID_FIELDS = """\
string frame_id
geometry_msgs/Pose pose
uint32 column_count
foxglove_msgs/Vector2 cell_size
uint32 row_stride
uint32 cell_stride
foxglove_msgs/PackedElementField[] fields
uint8[] data
"""

_VECTOR2 = "float64 x\nfloat64 y\n"

#: tf2_msgs/TFMessage, which rosbags' ROS 1 store lacks (ROS 1 md5 94810edda583a504dfda3829e70d7eec).
TF_MESSAGE = {"tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms\n"}

#: foxglove_msgs, ROS 1 (``time`` stamp).
FOXGLOVE_ROS1 = {
    "foxglove_msgs/msg/Vector2": _VECTOR2,
    "foxglove_msgs/msg/PackedElementField": _PACKED_ELEMENT_FIELD,
    GRID: "time timestamp\n" + _GRID_FIELDS,
}

#: foxglove_msgs, ROS 2 (``builtin_interfaces/Time`` stamp).
FOXGLOVE_ROS2 = {
    "foxglove_msgs/msg/Vector2": _VECTOR2,
    "foxglove_msgs/msg/PackedElementField": _PACKED_ELEMENT_FIELD,
    GRID: "builtin_interfaces/Time timestamp\n" + _GRID_FIELDS,
}


@functools.cache
def typestore(ros_version: int):
    """A rosbags type store of ROS 1 (noetic) or ROS 2 (humble) with grid_map_msgs and foxglove_msgs added.

    Parameters
    ----------
    ros_version : {1, 2}
        Which layout of ``grid_map_msgs`` to register (and which standard store to start from).

    Returns
    -------
    rosbags.typesys.store.Typestore
        Shared between calls (types are only ever added at creation).
    """
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if ros_version not in (1, 2):
        raise ValueError(f"ros_version must be 1 or 2, got {ros_version!r}")
    store = get_typestore(Stores.ROS1_NOETIC if ros_version == 1 else Stores.ROS2_HUMBLE)
    types = {}
    for name, text in {**(GRID_MAP_ROS1 if ros_version == 1 else GRID_MAP_ROS2),
                       **(FOXGLOVE_ROS1 if ros_version == 1 else FOXGLOVE_ROS2)}.items():
        types.update(get_types_from_msg(text, name))
    if "tf2_msgs/msg/TFMessage" not in store.types:
        types.update(get_types_from_msg(TF_MESSAGE["tf2_msgs/msg/TFMessage"], "tf2_msgs/msg/TFMessage"))
    store.register(types)
    return store


def message_definition(typename: str, ros_version: int) -> tuple[str, str]:
    """The full definition text of a type with its dependencies (ROS's ``MSG:`` separated form), and its md5.

    This is what a ROS 1 bag's connection header and an MCAP ``ros2msg`` schema hold; the md5 is the
    ROS 1 hash (meaningful for ``ros_version=1``).
    """
    return typestore(ros_version).generate_msgdef(typename, ros_version=ros_version)


def serialize(msg, ros_version: int) -> memoryview:
    """A message of :func:`typestore` ``(ros_version)`` in ROS 1 wire format or CDR (ROS 2)."""
    store = typestore(ros_version)
    if ros_version == 1:
        return store.serialize_ros1(msg, msg.__msgtype__)
    return store.serialize_cdr(msg, msg.__msgtype__)
