"""A live Foxglove view of a mapping run: a WebSocket server on 127.0.0.1 (foxglove-sdk, the ``foxglove`` extra).

Foxglove (or Lichtblick) connects to ``ws://127.0.0.1:PORT`` with the WebSocket protocol
``foxglove.sdk.v1`` and sees, in ROS 2 messages (CDR with their ``ros2msg`` schemas):

* :data:`~elevmap.ros.bagout.MAP_TOPIC`: the map as ``grid_map_msgs/msg/GridMap``;
* :data:`~elevmap.ros.bagout.GRID_TOPIC`: the same layers as ``foxglove_msgs/msg/Grid`` (the 3D panel
  draws the terrain from its ``elevation`` field);
* ``/tf``: the map to each camera's frame;
* ``/<camera>/depth``: each camera's depth image (``sensor_msgs/msg/Image``, ``16UC1`` or ``32FC1``).

The server binds the loopback interface only: a mapping run is not exposed to the network. Messages
are serialised only while a client subscribes to their topic, so an idle server costs nothing per frame.
"""

from __future__ import annotations

import math

import numpy as np

from .bagout import BAG_LAYERS, GRID_TOPIC, MAP_TOPIC, TF_TOPIC, camera_frame_id
from .convert import grid_map_message, grid_message, matrix_to_transform, time_message
from .msgs import GRID, GRID_MAP, message_definition, typestore

__all__ = ["FoxgloveServer", "HOST", "DEFAULT_PORT", "import_foxglove"]

#: The only interface the server listens on.
HOST = "127.0.0.1"
#: Foxglove's default port.
DEFAULT_PORT = 8765
_IMAGE = "sensor_msgs/msg/Image"
_TF = "tf2_msgs/msg/TFMessage"


def import_foxglove():
    """Import foxglove-sdk, or say how to install it (a ValueError, as for any missing optional part)."""
    try:
        import foxglove
    except ImportError as exc:
        raise ValueError(f"the live Foxglove view needs foxglove-sdk ({exc}); install it with "
                         "`pip install 'elevmap[foxglove]'` or `pip install foxglove-sdk`") from None
    return foxglove


class FoxgloveServer:
    """Serve the map, depth images and transforms to Foxglove while a source is mapped.

    Parameters
    ----------
    port : int
        TCP port on 127.0.0.1 (0: any free port; :attr:`port` tells which).
    map_frame : str
        Frame of the map and parent of the camera transforms.
    layers : sequence of str
        Layers of the GridMap and Grid messages.

    Raises
    ------
    ValueError
        foxglove-sdk is missing, or the port cannot be bound (in use).
    """

    def __init__(self, port: int = DEFAULT_PORT, *, map_frame: str = "map", layers=BAG_LAYERS):
        if not isinstance(port, (int, np.integer)) or not 0 <= int(port) <= 65535:
            raise ValueError(f"the Foxglove port must be an integer in 0..65535, got {port!r}")
        fg = import_foxglove()
        self.map_frame = str(map_frame)
        self.layers = tuple(layers)
        self.store = typestore(2)
        self.context = fg.Context()
        try:
            self.server = fg.start_server(name="elevmap", host=HOST, port=int(port), context=self.context)
        except Exception as exc:                          # the SDK reports a bind failure as its own error type
            raise ValueError(f"cannot start the Foxglove server on {HOST}:{port} ({exc}); "
                             "is the port in use?") from None
        self._fg = fg
        self._channels = {}
        self.map_channel = self._channel(MAP_TOPIC, GRID_MAP)
        self.grid_channel = self._channel(GRID_TOPIC, GRID)
        self.tf_channel = self._channel(TF_TOPIC, _TF)
        self.maps_sent = 0

    @property
    def port(self) -> int:
        return int(self.server.port)

    @property
    def url(self) -> str:
        return f"ws://{HOST}:{self.port}"

    def _channel(self, topic: str, msgtype: str):
        text, _ = message_definition(msgtype, 2)
        schema = self._fg.Schema(name=msgtype, encoding="ros2msg", data=text.encode())
        ch = self._fg.Channel(topic, schema=schema, message_encoding="cdr", context=self.context)
        self._channels[topic] = ch
        return ch

    @staticmethod
    def _ns(stamp: float) -> int:
        return int(round(max(float(stamp), 0.0) * 1e9)) if math.isfinite(stamp) else 0

    def publish_map(self, emap, stamp: float | None = None) -> bool:
        """Send the map (GridMap and Grid) to subscribed clients; False when none subscribes."""
        if not (self.map_channel.has_sinks() or self.grid_channel.has_sinks()):
            return False
        grid = emap.to_grid_map(self.layers, frame_id=self.map_frame)
        s = grid["stamp"] if stamp is None else float(stamp)
        grid["stamp"] = s if math.isfinite(s) and s >= 0 else 0.0
        t = self._ns(grid["stamp"])
        if self.map_channel.has_sinks():
            self.map_channel.log(bytes(self.store.serialize_cdr(grid_map_message(grid, 2), GRID_MAP)), log_time=t)
        if self.grid_channel.has_sinks():
            self.grid_channel.log(bytes(self.store.serialize_cdr(grid_message(grid, 2), GRID)), log_time=t)
        self.maps_sent += 1
        return True

    def publish_transform(self, child_frame: str, T_map_child, stamp: float) -> None:
        """Send ``T_map_child`` on /tf."""
        if not self.tf_channel.has_sinks():
            return
        t = self.store.types
        header = t["std_msgs/msg/Header"](stamp=time_message(max(stamp, 0.0)), frame_id=self.map_frame)
        tr = t["geometry_msgs/msg/TransformStamped"](header=header, child_frame_id=str(child_frame),
                                                     transform=matrix_to_transform(T_map_child))
        self.tf_channel.log(bytes(self.store.serialize_cdr(t[_TF](transforms=[tr]), _TF)), log_time=self._ns(stamp))

    def publish_depth(self, camera: str, depth: np.ndarray, stamp: float) -> None:
        """Send a depth image (uint16 units as ``16UC1``, float metres as ``32FC1``) on ``/<camera>/depth``."""
        frame_id = camera_frame_id(camera)
        topic = f"/{frame_id}/depth"
        ch = self._channels.get(topic) or self._channel(topic, _IMAGE)
        if not ch.has_sinks():
            return
        d = np.ascontiguousarray(depth, dtype=np.uint16 if depth.dtype == np.uint16 else np.float32)
        enc = "16UC1" if d.dtype == np.uint16 else "32FC1"
        t = self.store.types
        header = t["std_msgs/msg/Header"](stamp=time_message(max(stamp, 0.0)), frame_id=frame_id)
        msg = t[_IMAGE](header=header, height=d.shape[0], width=d.shape[1], encoding=enc, is_bigendian=0,
                        step=d.shape[1] * d.itemsize, data=d.astype(d.dtype.newbyteorder("<")).view(np.uint8).ravel())
        ch.log(bytes(self.store.serialize_cdr(msg, _IMAGE)), log_time=self._ns(stamp))

    def close(self) -> None:
        """Stop the server (clients are disconnected). Safe to call more than once."""
        if self.server is not None:
            self.server.stop()
            self.server = None
        for ch in self._channels.values():
            ch.close()
        self._channels.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
