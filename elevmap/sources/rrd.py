"""Replay depth frames from a rerun recording (.rrd).

Any recording with a ``DepthImage`` under a ``Pinhole`` replays: the depth image's entity (or its
nearest ancestor) holds the pinhole, and the camera pose is the composition of the ``Transform3D``
of every entity from the root down to the depth entity (``relation`` honoured), taken latest-at the
frame's time on the replay timeline. So recordings made with rerun's own RealSense example replay too.
The recording's root frame is the map frame.

The recordings this project writes (:func:`elevmap.pipeline.run_mapping`) also carry each frame's
intrinsics, pose, pose covariance, stamp and depth scale as float64 ``AnyValues`` under
``meta/<camera>``; with those the replay is bit-exact (rerun stores transforms and pinholes as
float32). They also name the valid-region margin each camera was mapped with (:attr:`RrdSource.valid_margins_px`),
which :func:`elevmap.pipeline.run_mapping` applies again.
"""

from __future__ import annotations

import bisect
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from noise_model.valid_margin import MAX_VALID_MARGIN_PX

from ..frame import Frame

__all__ = ["RrdSource", "read_rrd_frames"]

# rerun ChannelDatatype codes (rerun.components.ImageFormat.channel_datatype)
_DTYPES = {6: np.uint8, 7: np.int8, 8: np.uint16, 9: np.int16, 10: np.uint32, 11: np.int32, 33: np.float16,
           34: np.float32, 35: np.float64}
_TRANSFORM = ("Transform3D:translation", "Transform3D:quaternion", "Transform3D:mat3x3", "Transform3D:relation",
              "Transform3D:scale")
_META = ("K", "T_map_cam", "pose_cov", "stamp", "depth_scale", "index", "valid_margin_px")


def _camera_name(entity: str) -> str:
    """'/world/front/depth' -> 'front': the camera a depth entity belongs to, as the recordings name it."""
    e = entity.strip("/")
    return e.split("/")[-2] if e.count("/") >= 1 else e


def _parent_chain(entity: str) -> list[str]:
    """'/a/b/c' -> ['/', '/a', '/a/b', '/a/b/c']."""
    parts = [p for p in entity.split("/") if p]
    return ["/"] + ["/" + "/".join(parts[: k + 1]) for k in range(len(parts))]


class _Series:
    """Values of one component of one entity: static, and per time on the replay timeline."""

    def __init__(self):
        self.static = None
        self.times: list[int] = []
        self.values: list = []

    def add(self, t, value):
        if t is None:
            self.static = value
        else:
            k = bisect.bisect_right(self.times, t)
            self.times.insert(k, t)
            self.values.insert(k, value)

    def latest_at(self, t):
        k = bisect.bisect_right(self.times, t)
        if k:
            return self.values[k - 1]
        return self.static


def _load(path: Path, timeline: str | None):
    try:
        from rerun.chunk import RrdReader
    except ImportError as exc:      # pragma: no cover - rerun is a dependency
        raise ValueError(f"{path}: reading .rrd needs rerun-sdk ({exc})") from None
    store: dict = defaultdict(lambda: defaultdict(_Series))
    depth_timelines = []
    try:
        with warnings.catch_warnings():     # a truncated file has no footer: rerun warns, then fails below
            warnings.simplefilter("ignore")
            reader = RrdReader(str(path))
        for ch in reader.stream():
            rb = ch.to_record_batch()
            names = rb.schema.names
            comps = [c for c in names if c.startswith(("DepthImage:", "EncodedDepthImage:", "Pinhole:"))
                     or c in _TRANSFORM or c in _META]
            if not comps:
                continue
            tl = timeline
            if not ch.is_static:
                if tl is None:
                    tl = "frame" if "frame" in ch.timeline_names else next(
                        (t for t in ch.timeline_names if t != "log_time"), None)
                if ("DepthImage:buffer" in names or "EncodedDepthImage:blob" in names) and tl is not None:
                    depth_timelines.append(tl)
                if tl is None or tl not in names:
                    continue
                idx = rb.column(tl).to_pylist()
            else:
                idx = [None] * rb.num_rows
            for c in comps:
                col = rb.column(c)
                for r in range(rb.num_rows):
                    if col[r].is_valid:
                        store[ch.entity_path][c].add(idx[r], col[r])
    except ValueError:
        raise
    except Exception as exc:       # rerun raises its own errors on truncated or corrupt files
        raise ValueError(f"{path}: not a readable rerun recording ({type(exc).__name__}: {exc})") from None
    return store, depth_timelines


def _to_numpy(value) -> np.ndarray:
    """A pyarrow list scalar (possibly nested) -> flat float64/uint8 array."""
    v = value.values if hasattr(value, "values") else value
    try:
        return np.array(v.flatten().to_numpy(zero_copy_only=False))
    except AttributeError:
        return np.array(v.to_numpy(zero_copy_only=False))


def _transform(entity_store, t) -> np.ndarray:
    """The 4x4 parent-from-child transform of one entity at time t (identity when none is logged)."""
    T = np.eye(4)
    tr = entity_store.get("Transform3D:translation")
    q = entity_store.get("Transform3D:quaternion")
    m = entity_store.get("Transform3D:mat3x3")
    rel = entity_store.get("Transform3D:relation")
    found = False
    if tr is not None and (v := tr.latest_at(t)) is not None:
        T[:3, 3] = _to_numpy(v)[:3]
        found = True
    if q is not None and (v := q.latest_at(t)) is not None:
        T[:3, :3] = Rotation.from_quat(_to_numpy(v)[:4]).as_matrix()        # xyzw
        found = True
    elif m is not None and (v := m.latest_at(t)) is not None:
        T[:3, :3] = _to_numpy(v)[:9].reshape(3, 3).T                        # stored column-major
        found = True
    if found and rel is not None and (v := rel.latest_at(t)) is not None:
        code = v.as_py() if hasattr(v, "as_py") else v
        code = code[0] if isinstance(code, list) else code
        if code in (2, "ChildFromParent"):
            T = np.linalg.inv(T)
    return T


class RrdSource:
    """Depth frames of a rerun recording, as :class:`Frame` records.

    Parameters
    ----------
    path : path-like
        The .rrd file.
    entity : str, optional
        The depth-image entity to replay (e.g. "/world/camera/depth"); every depth entity when None
        (frames of several cameras are interleaved by time).
    timeline : str, optional
        The replay timeline ("frame" when the recording has it, else its first non-log timeline).

    Attributes
    ----------
    valid_margins_px : dict of str to int
        The valid-region margin [px] each camera was mapped with, for the cameras whose frames carry this
        project's exact values (``meta/<camera>``): the one logged with the camera's first frame, or 0 when
        none is logged (the recording was made before the margin existed, when every pixel was mapped).
        Cameras of other recordings are not listed.

    Raises
    ------
    ValueError
        The file is missing, truncated or corrupt, holds no depth image under a pinhole, or names a margin
        that is not an integer in [0, ``MAX_VALID_MARGIN_PX``].
    """

    def __init__(self, path, entity: str | None = None, timeline: str | None = None):
        self.path = Path(path)
        if not self.path.is_file():
            raise ValueError(f"{self.path}: no such recording")
        store, tls = _load(self.path, timeline)
        depth_entities = sorted(e for e, comps in store.items()
                                if "DepthImage:buffer" in comps or "EncodedDepthImage:blob" in comps)
        if entity is not None:
            e = "/" + entity.strip("/")
            if e not in depth_entities:
                raise ValueError(f"{self.path}: no depth images at {entity!r}; depth entities: {depth_entities}")
            depth_entities = [e]
        if not depth_entities:
            raise ValueError(f"{self.path}: the recording holds no DepthImage")
        self._store = store
        self.timeline = timeline or (tls[0] if tls else None)
        self._items = []
        for e in depth_entities:
            pin = next((a for a in reversed(_parent_chain(e)) if "Pinhole:image_from_camera" in store.get(a, {})),
                       None)
            if pin is None:
                raise ValueError(f"{self.path}: depth images at {e} are under no Pinhole (no intrinsics)")
            series = store[e]["DepthImage:buffer" if "DepthImage:buffer" in store[e] else "EncodedDepthImage:blob"]
            for t in series.times:
                self._items.append((t, e, pin))
        self._items.sort()
        self.entities = depth_entities
        self.valid_margins_px = {}
        for t, e, _ in self._items:
            camera = _camera_name(e)
            meta = store.get(f"/meta/{camera}", {})
            if camera in self.valid_margins_px or not meta:
                continue
            v = meta["valid_margin_px"].latest_at(t) if "valid_margin_px" in meta else None
            if v is None:
                self.valid_margins_px[camera] = 0
                continue
            m = _to_numpy(v)
            if m.size != 1 or not np.isfinite(m[0]) or m[0] != np.round(m[0]) or not 0 <= m[0] <= MAX_VALID_MARGIN_PX:
                raise ValueError(f"{self.path}: meta/{camera} valid_margin_px is {m.tolist()}; one integer in "
                                 f"[0, {MAX_VALID_MARGIN_PX}] [px] expected")
            self.valid_margins_px[camera] = int(m[0])

    def __len__(self) -> int:
        return len(self._items)

    def __iter__(self):
        for k, (t, e, pin) in enumerate(self._items):
            yield self._frame(k, t, e, pin)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        self._items = []

    def _decode_png(self, e, t):
        import cv2

        s = self._store
        blob = _to_numpy(s[e]["EncodedDepthImage:blob"].latest_at(t)).astype(np.uint8)
        depth = cv2.imdecode(blob, cv2.IMREAD_UNCHANGED)
        if depth is None or depth.ndim != 2:
            raise ValueError(f"{self.path}: the encoded depth image at {e}, time {t}, does not decode")
        m = s[e].get("EncodedDepthImage:meter")
        meter = float(_to_numpy(m.latest_at(t))[0]) if m is not None and m.latest_at(t) is not None else 1000.0
        return depth, meter

    def _frame(self, k, t, e, pin) -> Frame:
        s = self._store
        if "EncodedDepthImage:blob" in s[e] and "DepthImage:buffer" not in s[e]:
            depth, meter = self._decode_png(e, t)
            return self._finish(k, t, e, pin, depth, meter)
        fmt_v = s[e]["DepthImage:format"].latest_at(t)
        buf_v = s[e]["DepthImage:buffer"].latest_at(t)
        if fmt_v is None:
            raise ValueError(f"{self.path}: depth image at {e}, time {t}, has no format")
        fmt = fmt_v[0].as_py() if hasattr(fmt_v, "__getitem__") else fmt_v.as_py()
        dtype = _DTYPES.get(int(fmt["channel_datatype"]))
        if dtype is None:
            raise ValueError(f"{self.path}: depth image at {e} has unsupported channel type {fmt['channel_datatype']}")
        raw = _to_numpy(buf_v[0] if hasattr(buf_v, "__getitem__") and not hasattr(buf_v, "values") else buf_v)
        data = np.frombuffer(raw.astype(np.uint8).tobytes(), dtype=dtype)
        if data.size != fmt["width"] * fmt["height"]:
            raise ValueError(f"{self.path}: depth image at {e}, time {t}, has {data.size} values for "
                             f"{fmt['width']}x{fmt['height']}")
        depth = data.reshape(fmt["height"], fmt["width"]).copy()
        meter_v = s[e].get("DepthImage:meter")
        meter = float(_to_numpy(meter_v.latest_at(t))[0]) if meter_v is not None and meter_v.latest_at(t) is not None \
            else 1000.0
        return self._finish(k, t, e, pin, depth, meter)

    def _finish(self, k, t, e, pin, depth, meter) -> Frame:
        s = self._store
        if not (np.isfinite(meter) and meter > 0):
            raise ValueError(f"{self.path}: depth image at {e} has meter = {meter}; it must be finite and > 0 "
                             "(depth units per metre)")
        camera = _camera_name(e)
        meta = s.get(f"/meta/{camera}", {})
        exact = {name: meta[name].latest_at(t) for name in _META if name in meta}
        exact = {k2: _to_numpy(v) for k2, v in exact.items() if v is not None}
        for name, size in (("K", 9), ("T_map_cam", 16), ("pose_cov", 36)):
            if name in exact and exact[name].size != size:
                raise ValueError(f"{self.path}: meta/{camera} {name} holds {exact[name].size} numbers, not {size}")
        if "K" in exact:
            K = exact["K"].reshape(3, 3)
        else:
            K = _to_numpy(s[pin]["Pinhole:image_from_camera"].latest_at(t)).reshape(3, 3).T   # column-major
            K[np.abs(K) < 1e-12] = 0.0
        if "T_map_cam" in exact:
            T = exact["T_map_cam"].reshape(4, 4)
        else:
            T = np.eye(4)
            for a in _parent_chain(e):
                if a in s:
                    T = T @ _transform(s[a], t)
            if not np.all(np.isfinite(T)):
                raise ValueError(f"{self.path}: the transform of {e} at frame {k} is not finite")
            T[:3, :3] = Rotation.from_matrix(T[:3, :3]).as_matrix()     # re-orthonormalise float32 rotations
        pose_cov = exact["pose_cov"].reshape(6, 6) if "pose_cov" in exact else None
        stamp = float(exact["stamp"][0]) if "stamp" in exact else float(t)
        if depth.dtype == np.uint16:
            scale = float(exact["depth_scale"][0]) if "depth_scale" in exact else 1.0 / meter
        else:
            depth = (depth.astype(np.float64) / meter).astype(np.float32) if meter != 1.0 else depth
            scale = None
        if depth.dtype not in (np.uint16, np.float32, np.float64):
            raise ValueError(f"{self.path}: depth image at {e} has dtype {depth.dtype}; uint16 or float expected")
        index = int(exact["index"][0]) if "index" in exact else k
        return Frame(depth, K, scale, stamp, T_map_cam=T, pose_cov=pose_cov, camera=camera, index=index)


def read_rrd_frames(path, entity: str | None = None) -> list[Frame]:
    """All depth frames of a recording (see :class:`RrdSource`)."""
    with RrdSource(path, entity) as src:
        return list(src)
