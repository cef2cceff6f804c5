"""``elevmap bag-info BAG`` and the ROS consumers of ``elevmap run``: ``--bag-out`` and ``--foxglove``.

* :func:`run_bag_info` / :func:`format_bag_info`: what a bag holds for mapping (depth topics with
  their camera info, frames, the chain of transforms to the map frame) and, in plain words, what is
  missing.
* :class:`BagOutput`: a ``run_mapping`` callback writing the map at ``--map-rate`` Hz (and the camera
  poses every frame) through :class:`elevmap.ros.bagout.MapBagWriter`; the final map is written at
  :meth:`BagOutput.finish`, and the bag appears only then (atomic).
* :class:`LiveOutput`: a ``run_mapping`` callback streaming the map at ``--map-rate`` Hz, each
  depth image and the camera poses to Foxglove (:class:`elevmap.ros.live.FoxgloveServer`).
"""

from __future__ import annotations

import math

__all__ = ["run_bag_info", "format_bag_info", "BagOutput", "LiveOutput", "DEFAULT_MAP_RATE_HZ"]

#: Maps written or sent per second of the source's time by default [Hz].
DEFAULT_MAP_RATE_HZ = 2.0


def run_bag_info(path, *, depth_topics=None, map_frame=None, base_frame=None) -> dict:
    """Inspect a bag as ``elevmap run`` would read it (:meth:`elevmap.sources.rosbag.RosbagSource.info`)."""
    from ..sources.rosbag import RosbagSource

    src = RosbagSource(path, depth_topics=depth_topics, map_frame=map_frame, base_frame=base_frame)
    return src.info()


def format_bag_info(info: dict) -> str:
    """The inspection as text: every depth topic, then what is missing for it in plain words."""
    lines = [f"{info['bag']}: {len(info['topics'])} topics, {len(info['depth'])} depth topic(s)"]
    src = info["pose_source"]
    lines.append("poses: " + {"tf": f"/tf and /tf_static, map frame {info['map_frame']!r}",
                              "none": "none (no /tf, no odometry): a static camera"}.get(
        src, f"{src} (map frame {info['map_frame']!r})"))
    ok = 0
    for topic, d in info["depth"].items():
        size = "x".join(map(str, d["size"])) if d["size"] else "size from the first frame"
        lines.append(f"  {topic}  [{d['type'].split('/')[-1]} {d['encoding']}, {size}, {d['messages']} frames, "
                     f"frame {d['frame_id']!r}]")
        lines.append(f"    camera info: {d['camera_info'] or 'MISSING'}")
        if d["K"] is not None:
            K = d["K"]
            lines.append(f"    intrinsics: fx {K[0][0]:.2f}, fy {K[1][1]:.2f}, cx {K[0][2]:.2f}, cy {K[1][2]:.2f} px"
                         + (f"; depth unit {d['depth_scale']:g} m" if d["depth_scale"] else ""))
        if d["chain"]:
            lines.append(f"    transforms: {' -> '.join(d['chain'])}")
        if d["problem"]:
            lines.append(f"    cannot be mapped: {d['problem']}")
        else:
            ok += 1
    lines.append(f"{ok} of {len(info['depth'])} depth topic(s) can be mapped"
                 + ("" if src == "none" else f" (transforms held at most {1000 * info['tf_tolerance_s']:g} ms "
                                             "beyond their recorded span)"))
    return "\n".join(lines)


class _RateGate:
    """True for the first stamp and then whenever ``1 / rate`` seconds have passed since the last True.

    Several cameras interleave their stamps, so a stamp a little before the last one is normal and
    passes no gate; a jump back by more than a period (a source played again) starts over.
    """

    def __init__(self, rate_hz: float):
        r = float(rate_hz)
        if not math.isfinite(r) or r <= 0:
            raise ValueError(f"--map-rate must be a positive number of Hz, got {rate_hz!r}")
        self.period = 1.0 / r
        self.last = None

    def __call__(self, stamp: float) -> bool:
        if self.last is None or stamp - self.last >= self.period - 1e-9 or stamp < self.last - self.period:
            self.last = stamp
            return True
        return False


class BagOutput:
    """Write the map at a rate and every camera pose to a bag while mapping (a ``run_mapping`` callback).

    Parameters
    ----------
    path : path
        ``.bag`` (ROS 1), ``.mcap`` or a folder name (ROS 2); see :mod:`elevmap.ros.bagout`.
    map_frame : str
    rate_hz : float
        Maps per second of the source's time.
    """

    def __init__(self, path, *, map_frame: str = "map", rate_hz: float = DEFAULT_MAP_RATE_HZ):
        from ..ros.bagout import MapBagWriter

        self.gate = _RateGate(rate_hz)
        self.writer = MapBagWriter(path, map_frame=map_frame)
        self.last_written = None
        self.last_stamp = None

    def __call__(self, frame, T_map_cam, emap) -> None:
        from ..ros.bagout import camera_frame_id

        stamp = max(frame.stamp, 0.0)
        self.writer.write_transform(camera_frame_id(frame.camera), T_map_cam, stamp)
        self.last_stamp = stamp
        if self.gate(stamp):
            self.writer.write_map(emap, stamp)
            self.last_written = stamp

    def finish(self, emap) -> dict:
        """Write the final map (unless it was just written) and move the bag into place."""
        if self.last_stamp is not None and self.last_written != self.last_stamp:
            self.writer.write_map(emap, self.last_stamp)
        path = self.writer.close()
        return {"path": str(path), "maps": self.writer.maps_written, "transforms": self.writer.transforms_written,
                "ros_version": self.writer.ros_version}

    def abort(self) -> None:
        self.writer.abort()


class LiveOutput:
    """Stream the map (at a rate), each depth image and the camera poses to Foxglove (a ``run_mapping`` callback)."""

    def __init__(self, port: int, *, map_frame: str = "map", rate_hz: float = DEFAULT_MAP_RATE_HZ):
        from ..ros.live import FoxgloveServer

        self.gate = _RateGate(rate_hz)
        self.server = FoxgloveServer(port, map_frame=map_frame)

    def __call__(self, frame, T_map_cam, emap) -> None:
        from ..ros.bagout import camera_frame_id

        stamp = max(frame.stamp, 0.0)
        self.server.publish_transform(camera_frame_id(frame.camera), T_map_cam, stamp)
        self.server.publish_depth(frame.camera, frame.depth, stamp)
        if self.gate(stamp):
            self.server.publish_map(emap, stamp)

    def finish(self, emap) -> dict:
        self.server.publish_map(emap)
        out = {"url": self.server.url, "maps_sent": self.server.maps_sent}
        self.server.close()
        return out

    def abort(self) -> None:
        self.server.close()
