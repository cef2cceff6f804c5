"""Sources of depth frames (all I/O lives here): each yields :class:`elevmap.frame.Frame` records.

Every source is a context manager and an iterable of frames (``len()`` where the number of frames is
known without decoding them). pyrealsense2 and OpenCV are imported only by the functions that need
them, so this package imports without them.

* :mod:`.realsense` -- RealSense .bag/.db3 recordings (:class:`RealSenseFileSource`), the live camera
  (:class:`LiveRealSenseSource`), and a .db3 writer (:func:`record_db3`).
* :mod:`.captures` -- capture sets, format ``d435-captures/1`` (:func:`read_capture_set`,
  :func:`write_capture_set`).
* :mod:`.folder` -- a folder of 16-bit depth PNGs with intrinsics and poses (:class:`DepthFolderSource`).
* :mod:`.poses` -- TUM / Open3D .log pose files (:func:`read_pose_file`), interpolation
  (:class:`PoseTrack`), and :func:`with_poses` to attach them to any source.
"""

from .captures import Capture, CaptureSet, read_capture_set, write_capture_set
from .folder import DepthFolderSource, read_intrinsics
from .poses import PoseTrack, read_pose_file, with_poses
from .realsense import (
    LiveRealSenseSource, NoRealSenseDevice, RealSenseFileSource, RealSenseUnavailable, record_db3,
)

__all__ = [
    "Capture",
    "CaptureSet",
    "DepthFolderSource",
    "LiveRealSenseSource",
    "NoRealSenseDevice",
    "PoseTrack",
    "RealSenseFileSource",
    "RealSenseUnavailable",
    "read_capture_set",
    "read_intrinsics",
    "read_pose_file",
    "record_db3",
    "with_poses",
    "write_capture_set",
]
