"""ROS interoperability without ROS: message conversions, transforms, grid maps out, a live Foxglove view.

Everything here works through the pure-Python ``rosbags`` (message (de)serialisation and bags) and,
for the live view, ``foxglove-sdk`` (the ``foxglove`` extra); both are imported only inside this
package and :mod:`elevmap.sources.rosbag`.

* :mod:`.msgs` -- grid_map_msgs (ROS 1 and ROS 2 layouts) and foxglove_msgs definitions, and the type
  stores that know them (:func:`typestore`).
* :mod:`.convert` -- image, compressedDepth and camera-info messages to arrays and intrinsics;
  transforms and poses with covariance to matrices; the map to ``GridMap`` and ``foxglove_msgs/Grid``.
* :mod:`.tf` -- :class:`TfBuffer`, a tf2-like buffer with interpolation and a stated extrapolation
  tolerance.
* :mod:`.bagout` -- :class:`MapBagWriter`: the map as GridMap + Grid + /tf in a ``.bag``, ``.mcap``
  or ``.db3`` bag.
* :mod:`.live` -- :class:`FoxgloveServer`: the map, depth and transforms streamed to Foxglove on
  127.0.0.1.

A user's own ROS 2 node needs a few lines (``examples/ros2_node.py``)::

    from elevmap.ros import image_to_depth, camera_info_to_K, grid_map_message
    depth = image_to_depth(msg)                          # uint16 mm or float32 m
    K, w, h = camera_info_to_K(info)
    msg = grid_map_message(emap.to_grid_map(frame_id="map"), ros_version=2)
"""

from __future__ import annotations

import importlib

_NAMES = {
    "typestore": "msgs", "message_definition": "msgs", "GRID_MAP_ROS1_MD5": "msgs",
    "stamp_seconds": "convert", "time_message": "convert", "image_to_depth": "convert",
    "compressed_depth_to_depth": "convert", "camera_info_to_K": "convert", "transform_to_matrix": "convert",
    "pose_to_matrix": "convert", "matrix_to_transform": "convert", "matrix_to_pose": "convert",
    "pose_with_covariance": "convert", "grid_map_message": "convert", "grid_message": "convert",
    "grid_map_from_message": "convert",
    "TfBuffer": "tf", "TransformUnavailable": "tf", "TF_TOLERANCE_S": "tf",
    "MapBagWriter": "bagout", "BAG_LAYERS": "bagout",
    "FoxgloveServer": "live",
}

__all__ = sorted(_NAMES)


def __getattr__(name: str):
    module = _NAMES.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_NAMES))
