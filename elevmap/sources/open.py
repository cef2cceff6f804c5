"""Open any source from a command-line style specification.

============================  ====================================================================
SOURCE                        what it opens
============================  ====================================================================
``live`` / ``live:SERIAL``    a connected RealSense camera (848x480 at 30 fps by default)
``FILE.bag``, ``.db3``        a RealSense SDK recording, played back without dropping frames (by the
                              ROS bag source when pyrealsense2 is missing or a ROS option is given)
``FILE.bag``, ``.mcap``,      a ROS bag (ROS 1 .bag, ROS 2 folder with metadata.yaml, bare .mcap/.db3):
``FOLDER`` (metadata.yaml)    depth images with their camera info, poses from /tf or odometry
                              (--depth-topic, --map-frame, --base-frame)
``FILE.rrd``                  a rerun recording with a DepthImage under a Pinhole
``FOLDER`` (captures.json)    a capture set (``d435-captures/1``): every capture's frames in turn
``FOLDER`` (PNG files)        16-bit depth PNGs + intrinsics JSON (+ a pose file)
``sim:SCENE``                 the simulator walking a robot through SCENE (demo, stairs, boxes,
                              slope, rough), seen by the reference simulation of the paper's model
``sim:SCENE?sensor=stereo``   the same walk seen by the physical D435 (projector, infrared pair, D4
                              matcher: its noise emerges); ``&preset=high_accuracy`` selects the
                              matcher's other preset
============================  ====================================================================

A pose file (TUM text or Open3D .log) attaches poses to any source, interpolated to each frame's
stamp; without one a source's own poses are used, or the camera is static.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["open_source", "SOURCE_HELP"]

SOURCE_HELP = __doc__


def open_source(spec: str, *, poses=None, intrinsics=None, frames: int | None = None, seed: int = 0,
                T_pose_cam=None, depth_topics=None, map_frame: str | None = None, base_frame: str | None = None):
    """Open the source ``spec`` (see the module docstring); returns an iterable of Frame records.

    Parameters
    ----------
    spec : str
        The source.
    poses : path, optional
        A pose file (TUM or Open3D .log) for any source.
    intrinsics : path, optional
        Intrinsics JSON for a PNG folder (found in the folder when not given).
    frames : int, optional
        Number of frames of a simulated walk.
    seed : int
        Seed of a simulated walk.
    T_pose_cam : (4, 4), optional
        Pose of the camera in the pose file's frame (identity by default).
    depth_topics, map_frame, base_frame : optional
        Options of a ROS bag (:class:`elevmap.sources.rosbag.RosbagSource`); an error for other sources.
    """
    ros = {k: v for k, v in (("depth_topics", depth_topics), ("map_frame", map_frame), ("base_frame", base_frame))
           if v is not None}
    src = _open(spec, intrinsics=intrinsics, frames=frames, seed=seed, ros=ros)
    if poses is not None:
        from .poses import read_pose_file, with_poses

        src = with_poses(src, read_pose_file(poses), **({} if T_pose_cam is None else {"T_pose_cam": T_pose_cam}))
    return src


def _open(spec: str, *, intrinsics, frames, seed, ros):
    if spec == "live" or spec.startswith("live:"):
        from .realsense import LiveRealSenseSource

        serial = spec.split(":", 1)[1] if ":" in spec else None
        return LiveRealSenseSource(serial=serial or None)
    if spec.startswith("sim:"):
        from .simulated import SimulatedWalk

        scene, options = _sim_spec(spec)
        return SimulatedWalk(scene, n_frames=frames, seed=seed, **options)
    path = Path(spec)
    if not path.exists():
        raise ValueError(f"{spec}: no such file or folder (nor 'live', 'live:SERIAL' or 'sim:SCENE')")
    suffix = path.suffix.lower()
    from .rosbag import RosbagSource, is_realsense_recording, is_ros_bag

    if is_ros_bag(path):
        if not ros and suffix in (".bag", ".db3") and is_realsense_recording(path) and _has_pyrealsense2():
            from .realsense import RealSenseFileSource

            return RealSenseFileSource(path)
        return RosbagSource(path, **ros)
    if ros:
        raise ValueError(f"{spec}: {', '.join(ros)} are options of ROS bag sources (.bag, .mcap, .db3, a bag folder)")
    if path.is_file():
        if suffix == ".rrd":
            from .rrd import RrdSource

            return RrdSource(path)
        raise ValueError(f"{spec}: unknown source type {suffix!r} (.bag, .db3, .rrd, a folder, live, sim:SCENE)")
    if (path / "captures.json").is_file():
        from .captures import read_capture_set

        cs = read_capture_set(path)
        return _CaptureFrames(cs)
    if any(path.rglob("*.png")):
        from .folder import DepthFolderSource

        return DepthFolderSource(path, intrinsics)
    raise ValueError(f"{spec}: a folder with neither captures.json nor depth PNGs")


def _has_pyrealsense2() -> bool:
    """Whether pyrealsense2 imports (RealSense recordings are then played by the SDK itself)."""
    from .realsense import RealSenseUnavailable, import_pyrealsense2

    try:
        import_pyrealsense2()
    except RealSenseUnavailable:
        return False
    return True


#: Options of a ``sim:SCENE?KEY=VALUE&...`` source and the SimulatedWalk argument each sets.
_SIM_OPTIONS = {"sensor": "sensor", "preset": "preset"}


def _sim_spec(spec: str) -> tuple[str, dict]:
    """``sim:SCENE[?KEY=VALUE[&KEY=VALUE]]`` -> (SCENE, SimulatedWalk keyword arguments)."""
    body = spec.split(":", 1)[1]
    scene, _, query = body.partition("?")
    options = {}
    for item in filter(None, query.split("&")):
        key, eq, value = item.partition("=")
        if not eq or not value:
            raise ValueError(f"{spec}: options of a sim source are KEY=VALUE, got {item!r}")
        if key not in _SIM_OPTIONS:
            raise ValueError(f"{spec}: unknown option {key!r} of a sim source; options: {', '.join(_SIM_OPTIONS)}")
        if _SIM_OPTIONS[key] in options:
            raise ValueError(f"{spec}: option {key!r} given twice")
        options[_SIM_OPTIONS[key]] = value
    if "preset" in options and options.get("sensor") != "stereo":
        raise ValueError(f"{spec}: preset is an option of sensor=stereo")
    return scene, options


class _CaptureFrames:
    """Every capture of a capture set, one after the other (each is a static camera)."""

    def __init__(self, capture_set):
        self.capture_set = capture_set

    def __iter__(self):
        for c in self.capture_set.captures:
            yield from self.capture_set.frames(c["id"])

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None
