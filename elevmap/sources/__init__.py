"""Sources of depth frames (all I/O lives here): each yields :class:`elevmap.frame.Frame` records.

Every source is a context manager and an iterable of frames (``len()`` where the number of frames is
known without decoding them). :func:`open_source` opens any of them from a command-line style string.

* :mod:`.open` -- :func:`open_source` (``live``, ``.bag``/``.db3``, ``.rrd``, capture sets, PNG folders,
  ``sim:SCENE``).
* :mod:`.realsense` -- RealSense .bag/.db3 recordings (:class:`RealSenseFileSource`), the live camera
  (:class:`LiveRealSenseSource`), and a .db3 writer (:func:`record_db3`).
* :mod:`.rosbag` -- ROS 1 .bag, ROS 2 bag folders (.db3 / .mcap) and bare .mcap files, read without ROS
  through the ``rosbags`` package (:class:`RosbagSource`; :func:`is_ros_bag`, :func:`is_realsense_recording`).
* :mod:`.rrd` -- rerun recordings with a depth image under a pinhole (:class:`RrdSource`), such as those
  ``elevmap run --rrd`` writes.
* :mod:`.captures` -- capture sets, format ``d435-captures/1`` (:func:`read_capture_set`,
  :func:`write_capture_set`).
* :mod:`.folder` -- a folder of 16-bit depth PNGs with intrinsics and poses (:class:`DepthFolderSource`).
* :mod:`.viewer_raw` -- raw depth frames exported by the RealSense Viewer (:func:`read_viewer_raw`).
* :mod:`.poses` -- TUM / Open3D .log pose files (:func:`read_pose_file`), interpolation
  (:class:`PoseTrack`), and :func:`with_poses` to attach them to any source.
* :mod:`.simulated` -- the simulator walking a robot through a scene (:class:`SimulatedWalk`).

Every name is imported on first use (PEP 562), so ``import elevmap.sources`` loads none of
pyrealsense2, OpenCV, rerun or the simulator; each is imported only by the source that needs it.
"""

from __future__ import annotations

import importlib

#: Public name -> the submodule that defines it.
_NAMES = {
    "open_source": "open",
    "SOURCE_HELP": "open",
    "Capture": "captures",
    "CaptureSet": "captures",
    "read_capture_set": "captures",
    "write_capture_set": "captures",
    "DepthFolderSource": "folder",
    "read_intrinsics": "folder",
    "PoseTrack": "poses",
    "read_pose_file": "poses",
    "with_poses": "poses",
    "LiveRealSenseSource": "realsense",
    "NoRealSenseDevice": "realsense",
    "RealSenseFileSource": "realsense",
    "RealSenseUnavailable": "realsense",
    "record_db3": "realsense",
    "RosbagSource": "rosbag",
    "is_ros_bag": "rosbag",
    "is_realsense_recording": "rosbag",
    "RrdSource": "rrd",
    "read_rrd_frames": "rrd",
    "SimulatedWalk": "simulated",
    "read_viewer_raw": "viewer_raw",
    "viewer_raw_metadata": "viewer_raw",
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
