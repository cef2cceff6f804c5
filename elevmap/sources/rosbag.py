"""Depth frames from ROS bags: ROS 1 ``.bag``, ROS 2 bag folders (``metadata.yaml`` + ``.db3``/``.mcap``)
and bare ``.mcap`` or ``.db3`` files, read with the pure-Python ``rosbags`` (no ROS installation).

What is read
------------
* **Depth**: every ``sensor_msgs/Image`` topic whose encoding is ``16UC1``, ``mono16`` (millimetres,
  or the RealSense SDK's ``Depth Units`` option when the bag records it) or ``32FC1`` (metres), and
  every ``sensor_msgs/CompressedImage`` topic in image_transport's ``compressedDepth`` format. Each
  depth topic is one camera (named by its topic), so several depth topics map into one map.
* **Intrinsics**: the ``sensor_msgs/CameraInfo`` topic of the same image size that shares the longest
  leading part of its name with the depth topic (``/cam/depth/image_rect_raw`` ->
  ``/cam/depth/camera_info``; a RealSense SDK bag's ``.../Depth_0/info/camera_info``).
* **Poses**, in this order of preference:

  1. odometry (``nav_msgs/Odometry`` or ``geometry_msgs/PoseWithCovarianceStamped``) when the bag has
     it and no other ``map_frame`` is asked for: ``T_map_cam = T_map_base(stamp) @ T_base_cam``,
     with ``T_base_cam`` from the transforms (the base frame is the odometry's ``child_frame_id`` or
     ``base_frame``) and the message's 6 x 6 covariance carried to the camera as the pose covariance;
  2. ``/tf`` and ``/tf_static``: the chain from ``map_frame`` (default: the root of the image frame's
     tree) to the image's ``frame_id`` at the image stamp (:class:`elevmap.ros.tf.TfBuffer`,
     interpolated, never extrapolated beyond its tolerance);
  3. none: a static camera (``T_map_cam`` None), as for a RealSense SDK recording.

Frames that cannot be mapped (no camera info, no transform at the stamp, an image of another size
than its camera info) are skipped and counted in :attr:`RosbagSource.skipped`; :meth:`RosbagSource.summary`
reports them. A bag that cannot be read, a depth topic with an unknown encoding, or a bag with no
depth topic at all is a ``ValueError`` naming the file (and the topic).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..frame import Frame
from ..ros.convert import (
    DEPTH_ENCODINGS, MM_PER_UNIT_DEPTH_SCALE, camera_info_to_K, compressed_depth_to_depth, image_to_depth,
    pose_with_covariance, stamp_seconds, transform_to_matrix,
)
from ..ros.tf import TF_TOLERANCE_S, TfBuffer, TransformUnavailable
from .base import FrameSource

__all__ = ["RosbagSource", "is_ros_bag", "is_realsense_recording", "BAG_SUFFIXES", "carry_pose_cov"]

#: File suffixes of bags this source reads (a folder with metadata.yaml is a ROS 2 bag too).
BAG_SUFFIXES = (".bag", ".mcap", ".db3")

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF = "tf2_msgs/msg/TFMessage"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"
#: The RealSense SDK records its depth sensor's metres per unit under ``<sensor>/option/Depth Units/value``
#: (a Float32 in its ROS 1 .bag, a String under ``Depth_Units`` in its ROS 2 .db3).
_REALSENSE_DEPTH_UNITS = ("/option/Depth Units/value", "/option/Depth_Units/value")
#: The RealSense SDK's .db3 stamps images with the recording time and keeps the sensor's timestamp [ms] in a
#: String beside them, ``<stream>/image/metadata``: ``"...;timestamp=66.666667;..."``.
_REALSENSE_METADATA = "/metadata"


def is_ros_bag(path) -> bool:
    """A ``.bag``/``.mcap``/``.db3`` file, or a folder with ``metadata.yaml`` (a ROS 2 bag)."""
    p = Path(path)
    return (p.is_file() and p.suffix.lower() in BAG_SUFFIXES) or (p.is_dir() and (p / "metadata.yaml").is_file())


def _open_reader(path: Path):
    """An opened rosbags AnyReader of the bag, or a ValueError naming the file."""
    from rosbags.highlevel import AnyReader

    from ..ros.msgs import typestore

    is1 = path.is_file() and path.suffix.lower() == ".bag"
    try:
        reader = AnyReader([path], default_typestore=typestore(1 if is1 else 2))
        reader.open()
    except Exception as exc:                            # rosbags raises several types for a damaged file
        raise ValueError(f"{path}: cannot read the bag, it is truncated, corrupt or not a ROS bag "
                         f"({type(exc).__name__}: {exc})") from None
    return reader


def is_realsense_recording(path) -> bool:
    """Whether a ``.bag``/``.db3`` is a RealSense SDK recording (its ``/device_0/...`` topic layout)."""
    p = Path(path)
    if not (p.is_file() and p.suffix.lower() in (".bag", ".db3")):
        return False
    try:
        reader = _open_reader(p)
    except ValueError:
        return False
    try:
        return any(c.topic.startswith("/device_0/") for c in reader.connections)
    finally:
        reader.close()


def _messages(reader, connections, path):
    """(connection, bag time [ns], message) of the connections in bag order; a damaged bag is a ValueError."""
    it = reader.messages(connections=connections)
    while True:
        try:
            conn, t, raw = next(it)
            msg = reader.deserialize(raw, conn.msgtype)
        except StopIteration:
            return
        except Exception as exc:
            raise ValueError(f"{path}: the bag is truncated or corrupt (reading {type(exc).__name__}: {exc})") from None
        yield conn, t, msg


def _common_prefix(a: str, b: str) -> int:
    """Number of leading topic-name components ``a`` and ``b`` share."""
    n = 0
    for x, y in zip(a.strip("/").split("/"), b.strip("/").split("/")):
        if x != y:
            break
        n += 1
    return n


def carry_pose_cov(pose_cov_base, T_map_base, T_base_cam) -> np.ndarray:
    """The 6 x 6 pose covariance of the camera from that of the base it is rigidly mounted on.

    With the pose error of ``Frame.pose_cov`` (translation rho and rotation phi about the map axes,
    applied about the body's origin: ``T = (Exp(phi) R, t + rho)``), the camera at lever arm
    ``a = R_map_base t_base_cam`` moves by ``rho + phi x a``: its error is ``J xi`` with
    ``J = [[I, -[a]x], [0, I]]``, so ``Sigma_cam = J Sigma_base J^T``.
    """
    a = T_map_base[:3, :3] @ T_base_cam[:3, 3]
    J = np.eye(6)
    J[:3, 3:] = -np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return J @ np.asarray(pose_cov_base, dtype=np.float64) @ J.T


class _Odometry:
    """Stamped poses and covariances of an odometry topic, interpolated like the transforms."""

    def __init__(self, topic, frame_id, child_frame_id, stamps, poses, covs, tolerance):
        from .poses import PoseTrack

        order = np.argsort(stamps, kind="stable")
        stamps = np.asarray(stamps, dtype=np.float64)[order]
        keep = np.concatenate([[True], np.diff(stamps) > 0])        # a repeated stamp keeps its first pose
        self.topic, self.frame_id, self.child_frame_id, self.tolerance = topic, frame_id, child_frame_id, tolerance
        self.stamps = stamps[keep]
        self.track = PoseTrack(np.asarray(poses)[order][keep], self.stamps, source=f"odometry {topic}")
        self.covs = np.asarray(covs)[order][keep]

    def at(self, stamp: float) -> tuple[np.ndarray, np.ndarray]:
        """(T_map_base, pose_cov) at ``stamp``; the covariance linear between the samples around it."""
        try:
            T = self.track.at(stamp, tolerance=self.tolerance)[0]
        except ValueError as exc:
            raise TransformUnavailable(str(exc)) from None
        s = self.stamps
        if s.size == 1 or stamp <= s[0]:
            return T, self.covs[0]
        if stamp >= s[-1]:
            return T, self.covs[-1]
        i = int(np.searchsorted(s, stamp, side="right") - 1)
        a = (stamp - s[i]) / (s[i + 1] - s[i])
        return T, (1 - a) * self.covs[i] + a * self.covs[i + 1]


class RosbagSource(FrameSource):
    """Depth frames of a ROS bag (see the module docstring for what is read and how).

    Parameters
    ----------
    path : str or Path
        A ROS 1 ``.bag``, a ROS 2 bag folder, or a bare ``.mcap``/``.db3``.
    depth_topics : str or sequence of str, optional
        The depth topics to map (default: every depth topic found).
    map_frame : str, optional
        The map frame of the poses (default: the odometry's frame, else the root of the transform tree).
    base_frame : str, optional
        The robot's frame the odometry poses (default: the odometry's ``child_frame_id``).
    tf_tolerance : float
        Extrapolation tolerance of transforms and odometry [s].

    Attributes
    ----------
    topics : dict
        Every depth topic found: {topic: {"type", "encoding", "width", "height", "messages",
        "frame_id", "camera_info" (topic or None), "K", "depth_scale", "problem" (plain words or None)}}.
    pose_source : str
        ``"odometry <topic>"``, ``"tf"`` or ``"none"`` (static camera).
    map_frame : str or None
    skipped : collections.Counter
        {(topic, reason): frames} of the last iteration.
    frames_read : int
        Frames yielded by the last iteration.
    """

    def __init__(self, path, *, depth_topics=None, map_frame: str | None = None, base_frame: str | None = None,
                 tf_tolerance: float = TF_TOLERANCE_S):
        self.path = Path(path)
        if not self.path.exists():
            raise ValueError(f"{self.path}: no such file or folder")
        if not is_ros_bag(self.path):
            raise ValueError(f"{self.path}: not a ROS bag (a .bag, .mcap or .db3 file, or a folder with metadata.yaml)")
        self.skipped: Counter = Counter()
        self.frames_read = 0
        self._base_frame = base_frame
        reader = _open_reader(self.path)
        try:
            self._inspect(reader, depth_topics, map_frame, base_frame, tf_tolerance)
        finally:
            reader.close()

    # -------------------------------------------------------------------------------- discovery

    def _inspect(self, reader, depth_topics, map_frame, base_frame, tol):
        path = self.path
        conns = reader.connections
        self.all_topics = {c.topic: c.msgtype for c in conns}
        self.topics = {}
        self._sensor_stamps = {}
        infos = {}
        depth_units = {}
        self.tf = TfBuffer(tol)
        odometry = {}
        wanted = (None if depth_topics is None else [depth_topics] if isinstance(depth_topics, str)
                  else list(depth_topics))
        for c in conns:
            if c.msgtype in (IMAGE, COMPRESSED):
                first = next(_messages(reader, [c], path), None)
                if first is None:
                    continue
                msg = first[2]
                if c.msgtype == IMAGE:
                    enc = str(msg.encoding)
                    if enc not in DEPTH_ENCODINGS:
                        if wanted is not None and c.topic in wanted:
                            raise ValueError(f"{path}: topic {c.topic} has image encoding {enc!r}, not depth "
                                             f"({', '.join(DEPTH_ENCODINGS)})")
                        continue
                    width, height = int(msg.width), int(msg.height)
                else:
                    enc = str(msg.format)
                    if "compressedDepth" not in enc and not c.topic.endswith("compressedDepth"):
                        if wanted is not None and c.topic in wanted:
                            raise ValueError(f"{path}: topic {c.topic} is a compressed image in format {enc!r}, "
                                             "not compressedDepth")
                        continue
                    width = height = None
                entry = self.topics.setdefault(c.topic, {
                    "type": c.msgtype, "encoding": enc, "width": width, "height": height, "messages": 0,
                    "frame_id": str(msg.header.frame_id).lstrip("/"), "camera_info": None, "K": None,
                    "depth_scale": None, "problem": None})
                entry["messages"] += c.msgcount
            elif c.msgtype == CAMERA_INFO:
                first = next(_messages(reader, [c], path), None)
                if first is not None:
                    infos[c.topic] = first[2]
            elif c.topic.endswith(_REALSENSE_DEPTH_UNITS) and c.msgtype in ("std_msgs/msg/Float32",
                                                                            "std_msgs/msg/String"):
                first = next(_messages(reader, [c], path), None)
                try:
                    # a float32 option in the SDK (its .db3 writes it as text with 6 decimals)
                    scale = float(np.float32(first[2].data)) if first is not None else None
                except ValueError:
                    scale = None
                if scale is not None and 0 < scale <= 0.1:
                    depth_units[c.topic.rsplit("/option/", 1)[0]] = scale
            elif (c.msgtype == "std_msgs/msg/String" and c.topic.endswith("/image" + _REALSENSE_METADATA)
                  and c.topic.startswith("/device_")):
                stamps = self._sensor_stamps.setdefault(c.topic[: -len(_REALSENSE_METADATA)], {})
                for _, t, msg in _messages(reader, [c], path):
                    fields = dict(kv.partition("=")[::2] for kv in str(msg.data).split(";") if "=" in kv)
                    try:
                        stamps[t] = float(fields["timestamp"]) / 1000.0
                    except (KeyError, ValueError):
                        pass
        tf_conns = [c for c in conns if c.msgtype == TF]
        for conn, t, msg in _messages(reader, tf_conns, path) if tf_conns else ():
            static = "tf_static" in conn.topic
            for tr in msg.transforms:
                where = f"{path}: {conn.topic} {tr.header.frame_id} -> {tr.child_frame_id}"
                T = transform_to_matrix(tr.transform, where)
                if static:
                    self.tf.add_static(tr.header.frame_id, tr.child_frame_id, T)
                else:
                    self.tf.add(tr.header.frame_id, tr.child_frame_id, stamp_seconds(tr.header.stamp), T)
        odo_conns = [c for c in conns if c.msgtype in (ODOMETRY, POSE_COV)]
        for conn, t, msg in _messages(reader, odo_conns, path) if odo_conns else ():
            where = f"{path}: {conn.topic}"
            T, cov = pose_with_covariance(msg.pose, where)
            o = odometry.setdefault(conn.topic, {"frame_id": str(msg.header.frame_id).lstrip("/"),
                                                 "child": str(getattr(msg, "child_frame_id", "")).lstrip("/"),
                                                 "stamps": [], "poses": [], "covs": []})
            o["stamps"].append(stamp_seconds(msg.header.stamp))
            o["poses"].append(T)
            o["covs"].append(cov)

        if wanted is not None:
            missing = [t for t in wanted if t not in self.topics]
            if missing:
                kinds = ", ".join(f"{t}: {self.all_topics.get(t) or 'not in the bag'}" for t in missing)
                raise ValueError(f"{path}: no depth topic {', '.join(missing)} ({kinds}); "
                                 f"depth topics found: {', '.join(self.topics) or 'none'}")
            self.topics = {t: self.topics[t] for t in wanted}
        if not self.topics:
            images = sorted(t for t, k in self.all_topics.items() if k in (IMAGE, COMPRESSED))
            raise ValueError(f"{path}: no depth topic (sensor_msgs/Image in {', '.join(DEPTH_ENCODINGS)}, or "
                             f"CompressedImage in compressedDepth); image topics: {', '.join(images) or 'none'}")

        for topic, e in self.topics.items():
            self._match_camera_info(topic, e, infos)
            e["depth_scale"] = next((s for ns, s in depth_units.items() if topic.startswith(ns + "/")),
                                    MM_PER_UNIT_DEPTH_SCALE)
        self._choose_poses(odometry, map_frame, base_frame, tol)

    def _match_camera_info(self, topic, e, infos):
        best, best_n = None, 0
        for info_topic in sorted(infos):
            msg = infos[info_topic]
            if e["width"] is not None and (int(msg.width), int(msg.height)) != (e["width"], e["height"]):
                continue
            n = _common_prefix(topic, info_topic)
            if n > best_n:
                best, best_n = info_topic, n
        if best is None:
            e["problem"] = "no camera info (no sensor_msgs/CameraInfo topic beside it" + (
                f" of {e['width']}x{e['height']})" if e["width"] else ")")
            return
        e["camera_info"] = best
        try:
            K, w, h = camera_info_to_K(infos[best], f"{self.path}: {best}")
        except ValueError as exc:
            e["problem"] = f"unusable camera info: {exc}"
            return
        e["K"], e["width"], e["height"] = K, w, h

    def _choose_poses(self, odometry, map_frame, base_frame, tol):
        self.odometry = None
        self.map_frame = None if map_frame is None else str(map_frame).lstrip("/")
        usable = {t: o for t, o in odometry.items() if self.map_frame in (None, o["frame_id"])}
        if usable:
            topic = sorted(usable)[0]
            o = usable[topic]
            base = str(base_frame).lstrip("/") if base_frame else o["child"]
            if not base:
                raise ValueError(f"{self.path}: {topic} ({POSE_COV}) does not name the robot's frame; "
                                 "give it as the base frame (--base-frame)")
            self.odometry = _Odometry(topic, o["frame_id"], base, o["stamps"], o["poses"], o["covs"], tol)
            self.map_frame = o["frame_id"]
            self.pose_source = f"odometry {topic}"
            for e in self.topics.values():
                if e["problem"] is None and e["frame_id"] != base and not (
                        e["frame_id"] in self.tf.frames and base in self.tf.frames
                        and self.tf.can_connect(base, e["frame_id"])):
                    e["problem"] = (f"no transform from the base frame {base!r} to the image frame "
                                    f"{e['frame_id']!r}")
            return
        if self.tf.frames:
            self.pose_source = "tf"
            for e in self.topics.values():
                frame = e["frame_id"]
                if frame not in self.tf.frames:
                    e["problem"] = e["problem"] or f"no transform to the image frame {frame!r}"
                    continue
                root = self.tf.root(frame)
                if self.map_frame is None:
                    self.map_frame = root
                if not self.tf.can_connect(self.map_frame, frame):
                    e["problem"] = e["problem"] or (f"no transform from the map frame {self.map_frame!r} to the "
                                                    f"image frame {frame!r}")
            return
        if self.map_frame is not None:
            raise ValueError(f"{self.path}: map frame {self.map_frame!r} asked for, but the bag has neither /tf nor "
                             f"odometry ({ODOMETRY}, {POSE_COV})")
        self.pose_source = "none"

    def chain(self, topic: str) -> list[str] | None:
        """The frames from the map frame to a depth topic's image frame (None when not connected)."""
        e = self.topics[topic]
        if self.pose_source == "none":
            return None
        start = self.odometry.child_frame_id if self.odometry else self.map_frame
        frame = e["frame_id"]
        if frame == start:
            return [start] if not self.odometry else [self.map_frame, start]
        if frame not in self.tf.frames or start not in self.tf.frames or not self.tf.can_connect(start, frame):
            return None
        return ([self.map_frame] if self.odometry else []) + self.tf.path(start, frame)

    # -------------------------------------------------------------------------------- frames

    def __repr__(self) -> str:
        return f"RosbagSource({str(self.path)!r}, {len(self.topics)} depth topic(s), poses: {self.pose_source})"

    def _pose(self, e, stamp):
        """(T_map_cam, pose_cov) of an image at ``stamp``; TransformUnavailable when there is none."""
        if self.pose_source == "none":
            return None, None
        frame = e["frame_id"]
        if self.odometry is not None:
            T_map_base, cov = self.odometry.at(stamp)
            base = self.odometry.child_frame_id
            T_base_cam = np.eye(4) if frame == base else self.tf.lookup(base, frame, stamp)
            return T_map_base @ T_base_cam, carry_pose_cov(cov, T_map_base, T_base_cam)
        return self.tf.lookup(self.map_frame, frame, stamp), None

    def _frames(self) -> Iterator[Frame]:
        self.skipped = Counter()
        self.frames_read = 0
        reader = _open_reader(self.path)
        try:
            conns = [c for c in reader.connections if c.topic in self.topics and c.msgtype in (IMAGE, COMPRESSED)]
            for conn, t, msg in _messages(reader, conns, self.path):
                if self._closed:
                    return
                topic = conn.topic
                e = self.topics[topic]
                where = f"{self.path}: {topic}"
                if e["K"] is None:
                    self.skipped[(topic, "no camera info")] += 1
                    continue
                if e["problem"] is not None:
                    self.skipped[(topic, e["problem"])] += 1
                    continue
                if conn.msgtype == IMAGE:
                    depth = image_to_depth(msg, where)
                else:
                    depth = compressed_depth_to_depth(msg, where)
                if depth.shape != (e["height"], e["width"]):
                    self.skipped[(topic, "image size differs from its camera info")] += 1
                    continue
                stamp = stamp_seconds(msg.header.stamp)
                sensor = next((s[t] for ns, s in self._sensor_stamps.items() if topic.startswith(ns) and t in s), None)
                if sensor is not None:                # a RealSense SDK .db3: the sensor's own timestamp
                    stamp = sensor
                elif stamp == 0.0:                    # no header stamp: the time the bag recorded it
                    stamp = t * 1e-9
                try:
                    T, cov = self._pose(e, stamp)
                except TransformUnavailable:
                    self.skipped[(topic, "no transform at its stamp")] += 1
                    continue
                scale = e["depth_scale"] if depth.dtype == np.uint16 else None
                yield Frame(depth=depth, K=e["K"], depth_scale=scale, stamp=stamp, T_map_cam=T, pose_cov=cov,
                            camera=topic, index=self.frames_read)
                self.frames_read += 1
        finally:
            reader.close()
        if self.frames_read == 0 and self.skipped:
            why = "; ".join(f"{topic}: {n} with {reason}" for (topic, reason), n in sorted(self.skipped.items()))
            raise ValueError(f"{self.path}: every depth frame was skipped ({why}); `elevmap bag-info` says what "
                             "is missing")

    def summary(self) -> dict:
        """What the last iteration read: frames mapped, frames skipped per topic and reason, the pose source."""
        skipped = {}
        for (topic, reason), n in sorted(self.skipped.items()):
            skipped.setdefault(topic, {})[reason] = n
        return {"bag": str(self.path), "pose_source": self.pose_source, "map_frame": self.map_frame,
                "depth_topics": {t: e["messages"] for t, e in self.topics.items()},
                "frames_mapped": self.frames_read, "frames_skipped": int(sum(self.skipped.values())),
                "skipped": skipped}

    def info(self) -> dict:
        """What the bag holds for mapping, for ``elevmap bag-info``: topics, camera infos, transforms, problems."""
        topics = {}
        for t, e in self.topics.items():
            chain = self.chain(t)
            topics[t] = {"type": e["type"], "encoding": e["encoding"], "messages": e["messages"],
                         "size": None if e["width"] is None else [e["width"], e["height"]],
                         "frame_id": e["frame_id"], "camera_info": e["camera_info"],
                         "K": None if e["K"] is None else np.asarray(e["K"]).tolist(),
                         "depth_scale": None if "32FC1" in e["encoding"] else e["depth_scale"],
                         "chain": chain, "problem": e["problem"]}
        return {"bag": str(self.path), "topics": dict(sorted(self.all_topics.items())), "depth": topics,
                "pose_source": self.pose_source, "map_frame": self.map_frame,
                "frames": sorted(self.tf.frames), "tf_tolerance_s": self.tf.tolerance}
