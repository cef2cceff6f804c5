"""The map written to a ROS bag while it is built: ``grid_map_msgs/GridMap``, ``foxglove_msgs/Grid`` and ``/tf``.

The output's name chooses the format and the message layout:

=========================  ==================================================================
path                       written
=========================  ==================================================================
``NAME.bag``               a ROS 1 bag, LZ4 chunks; GridMap in the ROS 1 layout (header in GridMapInfo)
``NAME.mcap``              one MCAP file (ROS 2 CDR, schemas embedded, uncompressed); ROS 2 layout
``NAME`` (no suffix)       a ROS 2 bag folder (``metadata.yaml`` + ``NAME.db3``, zstd per message); ROS 2
                           layout
=========================  ==================================================================

Topics: :data:`MAP_TOPIC` (GridMap), :data:`GRID_TOPIC` (Grid of the same layers, which Foxglove
and Lichtblick draw as a height field from its ``elevation`` field) and ``/tf`` (the map to each
camera's frame at every frame). Everything is written in a temporary folder beside the output, named and
registered by :mod:`elevmap.fileio` (so an interrupted run removes it, and a killed run's leftover is
recognised), and moved onto the output by :meth:`MapBagWriter.close`; :meth:`MapBagWriter.abort` leaves
nothing behind.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from .convert import grid_map_message, grid_message, matrix_to_transform, time_message
from .msgs import GRID, GRID_MAP, typestore

__all__ = ["MapBagWriter", "BAG_LAYERS", "MAP_TOPIC", "GRID_TOPIC", "TF_TOPIC", "bag_layout", "camera_frame_id"]

#: Layers written (grid_map's basic layers first).
BAG_LAYERS = ("elevation", "variance", "min_height", "max_height", "upper_bound", "points", "time")
MAP_TOPIC = "/elevation_map"
GRID_TOPIC = "/elevation_map/grid"
TF_TOPIC = "/tf"


def bag_layout(path) -> tuple[str, int]:
    """(``"bag"`` | ``"mcap"`` | ``"db3"``, ROS version) of an output path; a ValueError for another suffix."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".bag":
        return "bag", 1
    if suffix == ".mcap":
        return "mcap", 2
    if suffix == "":
        return "db3", 2
    raise ValueError(f"{path}: a map bag is NAME.bag (ROS 1), NAME.mcap (ROS 2) or NAME, a ROS 2 bag folder with "
                     f"a .db3 (not {suffix!r})")


def camera_frame_id(camera: str) -> str:
    """The tf frame name of a camera (its name without the leading slash, slashes as underscores)."""
    name = str(camera).strip("/").replace("/", "_")
    return name or "camera"


class MapBagWriter:
    """Write maps (and camera poses) to a bag; atomic: the output appears only when :meth:`close` succeeds.

    Parameters
    ----------
    path : str or Path
        The output (see the module docstring); it must not exist (the caller applies the output policy).
    map_frame : str
        Frame of the map and parent of the camera transforms.
    layers : sequence of str
        Layers of the GridMap and Grid messages.
    """

    def __init__(self, path, *, map_frame: str = "map", layers=BAG_LAYERS):
        self.path = Path(path)
        self.kind, self.ros_version = bag_layout(self.path)
        if self.path.exists() and self.kind == "db3":
            raise ValueError(f"{self.path} exists; a bag folder is never replaced, give a new name")
        self.map_frame = str(map_frame)
        self.layers = tuple(layers)
        self.store = typestore(self.ros_version)
        from ..fileio import new_temp_file, release_temp

        self._tmpdir = new_temp_file(self.path, ".d")            # a registered temporary name, made a folder
        self._tmpdir.unlink()
        self._tmpdir.mkdir(mode=0o700)
        self._release = release_temp
        self._inner = self._tmpdir / self.path.name
        self.maps_written = 0
        self.transforms_written = 0
        try:
            if self.kind == "bag":
                from rosbags.rosbag1 import Writer

                self.writer = Writer(self._inner)
                self.writer.set_compression(Writer.CompressionFormat.LZ4)     # unknown cells (NaN) pack well
            else:
                from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

                plugin = StoragePlugin.MCAP if self.kind == "mcap" else StoragePlugin.SQLITE3
                self.writer = Writer(self._inner, version=9, storage_plugin=plugin)
                if self.kind == "db3":                # a bare .mcap has no metadata.yaml to declare it
                    self.writer.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
            self.writer.open()
            self._map = self._connect(MAP_TOPIC, GRID_MAP)
            self._grid = self._connect(GRID_TOPIC, GRID)
            self._tf = self._connect(TF_TOPIC, "tf2_msgs/msg/TFMessage")
        except BaseException:
            release_temp(self._tmpdir, remove=True)
            raise

    def _connect(self, topic, msgtype):
        return self.writer.add_connection(topic, msgtype, typestore=self.store)

    def _serialise(self, msg, msgtype):
        if self.ros_version == 1:
            return self.store.serialize_ros1(msg, msgtype)
        return self.store.serialize_cdr(msg, msgtype)

    @staticmethod
    def _ns(stamp: float) -> int:
        s = float(stamp)
        if not math.isfinite(s) or s < 0:
            raise ValueError(f"a bag time must be finite and >= 0 s, got {stamp!r}")
        return int(round(s * 1e9))

    def write_map(self, emap, stamp: float | None = None) -> None:
        """Write the map's GridMap and Grid at ``stamp`` [s] (default: its last update)."""
        grid = emap.to_grid_map(self.layers, frame_id=self.map_frame)
        stamp = grid["stamp"] if stamp is None else float(stamp)
        if not math.isfinite(stamp):
            stamp = 0.0
        grid["stamp"] = stamp
        t = self._ns(stamp)
        self.writer.write(self._map, t, self._serialise(grid_map_message(grid, self.ros_version), GRID_MAP))
        self.writer.write(self._grid, t, self._serialise(grid_message(grid, self.ros_version), GRID))
        self.maps_written += 1

    def write_transform(self, child_frame: str, T_map_child, stamp: float) -> None:
        """Write ``T_map_child`` on /tf at ``stamp`` [s]."""
        t = self.store.types
        kw = {"seq": 0} if self.ros_version == 1 else {}
        header = t["std_msgs/msg/Header"](**kw, stamp=time_message(stamp, self.ros_version), frame_id=self.map_frame)
        tr = t["geometry_msgs/msg/TransformStamped"](header=header, child_frame_id=str(child_frame),
                                                     transform=matrix_to_transform(T_map_child, self.ros_version))
        msg = t["tf2_msgs/msg/TFMessage"](transforms=[tr])
        self.writer.write(self._tf, self._ns(stamp), self._serialise(msg, "tf2_msgs/msg/TFMessage"))
        self.transforms_written += 1

    def close(self) -> Path:
        """Finish the bag and move it onto the output path; returns that path."""
        from ..fileio import new_file_mode

        try:
            self.writer.close()
            if self.kind == "db3":
                if self.path.exists():
                    raise ValueError(f"{self.path} appeared while the map was written; the bag is not moved there")
                os.chmod(self._inner, new_file_mode(self.path, folder=True))
                os.rename(self._inner, self.path)
            else:
                src = self._inner if self.kind == "bag" else next(self._inner.glob("*.mcap"))
                os.chmod(src, new_file_mode(self.path))
                os.replace(src, self.path)
        finally:
            self._release(self._tmpdir, remove=True)
        return self.path

    def abort(self) -> None:
        """Drop everything written; the output path is left as it was."""
        try:
            self.writer.close()
        except Exception:                                  # the bag is thrown away whatever state it is in
            pass
        self._release(self._tmpdir, remove=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()
