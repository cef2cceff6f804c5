"""The live Foxglove server: a bounded WebSocket client on the loopback receives the map within 2 s.

The client below speaks just enough of RFC 6455 and of the Foxglove WebSocket protocol
(``foxglove.sdk.v1``: serverInfo, advertise, subscribe, binary message data) to subscribe to the map
topics; every wait is bounded by a deadline.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import socket
import struct
import threading
import time

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="foxglove-sdk (the foxglove extra) not installed")

from elevmap import ElevationMap, FusionParams  # noqa: E402
from elevmap.ros.bagout import BAG_LAYERS, GRID_TOPIC, MAP_TOPIC  # noqa: E402
from elevmap.ros.live import HOST, FoxgloveServer  # noqa: E402
from elevmap.ros.msgs import GRID, GRID_MAP, typestore  # noqa: E402

#: The must-show bound: map messages arrive within this after subscribing [s].
RECEIVE_WITHIN_S = 2.0
_GUID = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11"


class WsClient:
    """A minimal WebSocket client (text and binary frames, ping/pong), every read bounded by ``deadline``."""

    def __init__(self, port: int, deadline: float):
        self.deadline = deadline
        self.sock = socket.create_connection((HOST, port), timeout=self._left())
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: {HOST}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                           f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                           "Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self._recv(1)
        lines = head.decode().split("\r\n")
        assert lines[0].split()[1] == "101", lines[0]
        headers = {k.lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:] if ln)}
        accept = base64.b64encode(hashlib.sha1((key + _GUID).encode()).digest()).decode()
        assert headers["sec-websocket-accept"] == accept
        assert headers["sec-websocket-protocol"] == "foxglove.sdk.v1"

    def _left(self) -> float:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("deadline passed")
        return left

    def _recv(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            self.sock.settimeout(self._left())
            chunk = self.sock.recv(n - len(out))
            if not chunk:
                raise ConnectionError("server closed the connection")
            out += chunk
        return out

    def send_text(self, text: str) -> None:
        payload = text.encode()
        mask = os.urandom(4)
        n = len(payload)
        head = bytes([0x81]) + (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n))
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))

    def recv(self) -> tuple[int, bytes]:
        """(opcode, payload) of the next data frame (fragments joined; pings answered)."""
        data, first = b"", None
        while True:
            b0, b1 = self._recv(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._recv(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._recv(8))[0]
            payload = self._recv(n)
            op = b0 & 0x0F
            if op == 0x9:                                    # ping
                self.sock.sendall(bytes([0x8A, 0x80 | len(payload)]) + b"\0\0\0\0" + payload)
                continue
            if op == 0x8:
                raise ConnectionError("server closed the WebSocket")
            first = op if first is None else first
            data += payload
            if b0 & 0x80:
                return first, data

    def close(self):
        self.sock.close()


def _map():
    em = ElevationMap(2.0, 0.05, fusion_params=FusionParams(min_points=1))
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.9, 0.9, size=(500, 2))
    em.update(np.column_stack([xy, 0.1 * np.sin(3 * xy[:, 0])]), np.full(500, 1e-4), stamp=12.5)
    return em


def test_a_local_client_receives_the_map_within_two_seconds():
    emap = _map()
    try:
        server = FoxgloveServer(0)
    except ValueError as exc:
        pytest.skip(f"cannot bind a loopback port here: {exc}")
    stop = threading.Event()
    try:
        assert server.url.startswith("ws://127.0.0.1:")
        client = WsClient(server.port, time.monotonic() + 5.0)
        channels = {}
        while not {MAP_TOPIC, GRID_TOPIC} <= set(channels):
            op, payload = client.recv()
            if op == 0x1:
                msg = json.loads(payload)
                if msg.get("op") == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
        for topic, name in ((MAP_TOPIC, GRID_MAP), (GRID_TOPIC, GRID)):
            assert channels[topic]["encoding"] == "cdr" and channels[topic]["schemaEncoding"] == "ros2msg"
            assert channels[topic]["schemaName"] == name and "uint32 column_count" in channels[GRID_TOPIC]["schema"]
        subs = {1: MAP_TOPIC, 2: GRID_TOPIC}
        client.send_text(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": k, "channelId": channels[t]["id"]} for k, t in subs.items()]}))
        t_sub = time.monotonic()
        client.deadline = t_sub + RECEIVE_WITHIN_S

        def publish():                                  # the mapping loop's side: a map every 50 ms
            while not stop.is_set():
                server.publish_map(emap)
                stop.wait(0.05)

        threading.Thread(target=publish, daemon=True).start()
        got = {}
        while len(got) < 2:
            op, payload = client.recv()
            if op == 0x2 and payload[0] == 0x01:
                sub, log_time = struct.unpack_from("<IQ", payload, 1)
                got.setdefault(subs[sub], (time.monotonic() - t_sub, log_time, payload[13:]))
        client.close()
    finally:
        stop.set()
        server.close()
    print(f"map messages received {max(v[0] for v in got.values()) * 1000:.0f} ms after subscribing")
    assert max(v[0] for v in got.values()) < RECEIVE_WITHIN_S
    store = typestore(2)
    gm = store.deserialize_cdr(got[MAP_TOPIC][2], GRID_MAP)
    assert got[MAP_TOPIC][1] == 12_500_000_000 and gm.header.stamp.sec == 12
    expected = emap.to_grid_map(BAG_LAYERS)
    for name, arr in zip(gm.layers, gm.data):
        np.testing.assert_array_equal(arr.data, expected["data"][name])
    grid = store.deserialize_cdr(got[GRID_TOPIC][2], GRID)
    assert grid.column_count == emap.n and [f.name for f in grid.fields] == list(BAG_LAYERS)


def _listening_addresses(port: int) -> list[str]:
    """Local IPv4/IPv6 addresses (hex, as the kernel lists them) of sockets listening on ``port`` (Linux)."""
    out = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = open(table).read().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            local, state = line.split()[1], line.split()[3]
            addr, _, p = local.partition(":")
            if state == "0A" and int(p, 16) == port:
                out.append(addr)
    return out


def test_the_server_listens_on_the_loopback_only():
    try:
        server = FoxgloveServer(0)
    except ValueError as exc:
        pytest.skip(f"cannot bind a loopback port here: {exc}")
    try:
        with pytest.raises(ValueError, match="is the port in use"):
            FoxgloveServer(server.port)
        if not os.path.exists("/proc/net/tcp"):
            pytest.skip("no /proc/net/tcp to read the listening address from")
        assert _listening_addresses(server.port) == ["0100007F"]          # 127.0.0.1, and nothing else
    finally:
        server.close()


def test_cli_run_serves_foxglove_while_mapping(tmp_path, capsys):
    from elevmap.cli import main
    from rosbag_scenes import write_bag

    bag = write_bag(tmp_path / "scene.bag", "bag")
    assert main(["run", str(bag), "--foxglove", "0", "--map-rate", "5", "--no-progress"]) == 0
    captured = capsys.readouterr()
    assert "Foxglove: open a connection to ws://127.0.0.1:" in captured.err
    assert '"foxglove": {' in captured.out and "8 frames mapped, 0 skipped" in captured.out
    assert main(["run", str(bag), "--foxglove", "70000", "--no-progress"]) == 2
    assert "port must be an integer in 0..65535" in capsys.readouterr().err
