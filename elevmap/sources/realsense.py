"""Intel RealSense depth through pyrealsense2: recordings (.bag / .db3), the live camera, and a writer.

* :class:`RealSenseFileSource` plays a RealSense SDK recording, ROS1 ``.bag`` (``#ROSBAG V2.0``, written
  by SDK <= 2.57) or ROS2 rosbag2 ``.db3`` (SDK >= 2.58), **not in real time**: the player waits for
  the reader, so no frame is dropped however slow the consumer is. Only the depth stream is decoded.
* :class:`LiveRealSenseSource` streams depth from a connected camera.
* :func:`record_db3` writes depth frames to a ``.db3`` through a pyrealsense2 software device and
  recorder (SDK 2.58+ records only ``.db3``), atomically.

Every source yields :class:`elevmap.frame.Frame` records: ``depth`` uint16 depth units (0 = no data),
``K`` the depth stream's pinhole intrinsics [px], ``depth_scale`` [m/unit] read from the depth
sensor, ``stamp`` the frame's timestamp [s] (``rs2_frame.get_timestamp()`` / 1000, in the frame's own
timestamp domain, usually the camera's hardware clock), ``index`` 0, 1, ... in playback order,
``T_map_cam`` None (static camera; attach poses with :func:`elevmap.sources.poses.with_poses`).

pyrealsense2 is imported only inside these functions. It needs the system library libusb-1.0; when the
import fails, :class:`RealSenseUnavailable` (an ``ImportError`` and a ``ValueError``) says what to install.
"""

from __future__ import annotations

import gc
import os
import re
import sqlite3
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from noise_model.checks import check_intrinsics, check_positive_scalar

from ..fileio import new_file_mode, new_temp_file, release_temp, remove_leftovers
from ..frame import Frame
from .base import FrameSource

__all__ = [
    "RealSenseFileSource",
    "LiveRealSenseSource",
    "record_db3",
    "import_pyrealsense2",
    "RealSenseUnavailable",
    "NoRealSenseDevice",
    "RECORDING_SUFFIXES",
]

#: File name suffixes of RealSense SDK recordings.
RECORDING_SUFFIXES = (".bag", ".db3")

#: Longest wait for the first frame of a recording [ms] (the player needs a moment to start).
_FIRST_FRAME_TIMEOUT_MS = 5000
#: Poll interval while playing [ms]; the end of a file is a timeout while the player is stopped.
_POLL_MS = 100
#: A player that is still "playing" but delivers nothing for this long is reported as stalled [s].
_STALL_S = 10.0


class RealSenseUnavailable(ImportError, ValueError):
    """pyrealsense2 cannot be imported (not installed, or its system library libusb-1.0 is missing)."""


class NoRealSenseDevice(ValueError, RuntimeError):
    """No (matching) RealSense camera is connected."""


def import_pyrealsense2():
    """Import and return the ``pyrealsense2`` module, or say clearly what is missing.

    Raises
    ------
    RealSenseUnavailable
        If the import fails: with the hint to install libusb-1.0 (Debian/Ubuntu:
        ``apt-get install libusb-1.0-0``) when that is the cause, or to ``pip install pyrealsense2``.
    """
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        msg = str(exc)
        if "libusb" in msg:
            raise RealSenseUnavailable(
                f"pyrealsense2 needs the system library libusb-1.0, which is missing ({msg}); install it "
                "(Debian/Ubuntu: apt-get install libusb-1.0-0) to read RealSense cameras and .bag/.db3 files"
            ) from exc
        raise RealSenseUnavailable(
            f"cannot import pyrealsense2 ({msg}); install it with `pip install pyrealsense2` and the system "
            "library libusb-1.0 (Debian/Ubuntu: apt-get install libusb-1.0-0) to read RealSense cameras "
            "and .bag/.db3 files"
        ) from exc
    if not hasattr(rs, "pipeline"):  # a namespace package without the compiled module
        raise RealSenseUnavailable(
            "pyrealsense2 was found but has no compiled module (pipeline missing); reinstall it with "
            "`pip install --force-reinstall pyrealsense2` and install libusb-1.0 "
            "(Debian/Ubuntu: apt-get install libusb-1.0-0)"
        )
    return rs


# ------------------------------------------------------------------------------------------------
# helpers shared by the file and the live source


def _intrinsics_dict(intr) -> dict:
    return {
        "width": int(intr.width),
        "height": int(intr.height),
        "fx": float(intr.fx),
        "fy": float(intr.fy),
        "ppx": float(intr.ppx),
        "ppy": float(intr.ppy),
        "model": str(intr.model).rsplit(".", 1)[-1],
        "coeffs": [float(c) for c in intr.coeffs],
    }


def _K(intr: dict) -> np.ndarray:
    return np.array([[intr["fx"], 0.0, intr["ppx"]], [0.0, intr["fy"], intr["ppy"]], [0.0, 0.0, 1.0]])


def _device_info(rs, dev) -> dict:
    info = {}
    for key, field in (("name", rs.camera_info.name), ("serial", rs.camera_info.serial_number),
                       ("firmware", rs.camera_info.firmware_version), ("product_id", rs.camera_info.product_id)):
        try:
            info[key] = dev.get_info(field) if dev.supports(field) else None
        except RuntimeError:
            info[key] = None
    return info


def _warn_distortion(intr: dict, where: str) -> None:
    if any(abs(c) > 0 for c in intr["coeffs"]):
        warnings.warn(f"{where}: the depth stream has distortion ({intr['model']}, coeffs {intr['coeffs']}); "
                      "frames are mapped as an undistorted pinhole", stacklevel=3)


def _depth_image(frame) -> np.ndarray:
    """Copy a pyrealsense2 depth frame's pixels out of the SDK's frame pool: uint16 (H, W)."""
    return np.array(np.asanyarray(frame.get_data()), dtype=np.uint16, copy=True)


# ------------------------------------------------------------------------------------------------


_DEPTH_TOPIC = re.compile(r"/Depth_\d+/image/data(/compressedDepth)?$")


def db3_depth_messages(path) -> int | None:
    """Depth images a RealSense ``.db3`` lists in its SQLite ``messages`` table (None: not a .db3, not
    readable as one, or several depth streams).

    A corrupted message makes the SDK's player stop early without an error; comparing the frames played
    with this count turns that into one. The file is opened read-only and immutable (no journal is written).
    """
    path = Path(path)
    if path.suffix.lower() != ".db3":
        return None
    try:
        con = sqlite3.connect(f"file:{path.resolve().as_posix()}?mode=ro&immutable=1", uri=True)
        try:
            topics = [(i, name) for i, name in con.execute("SELECT id, name FROM topics")
                      if _DEPTH_TOPIC.search(name)]
            if len(topics) != 1:
                return None
            (count,), = con.execute("SELECT COUNT(*) FROM messages WHERE topic_id = ?", (topics[0][0],))
        finally:
            con.close()
    except sqlite3.Error:
        return None
    return int(count)


class RealSenseFileSource(FrameSource):
    """Depth frames of a RealSense SDK recording (.bag or .db3), played back not in real time.

    Parameters
    ----------
    path : str or Path
        The recording: ROS1 ``.bag`` (SDK <= 2.57) or ROS2 ``.db3`` (SDK >= 2.58).
    width, height : int, optional
        Resolution of the depth stream to play [px]; needed only when the recording holds several
        depth streams. A recording without a depth stream of that size is an error.
    camera : str, optional
        Name put into each frame's ``camera`` field (default: ``"camera"``).

    Attributes
    ----------
    intrinsics : dict
        The depth stream's intrinsics: ``width``, ``height`` [px], ``fx``, ``fy``, ``ppx``, ``ppy`` [px],
        ``model`` (distortion model name, e.g. ``"brown_conrady"``), ``coeffs`` (5 floats).
    K : ndarray, shape (3, 3)
        The same as a pinhole camera matrix [px].
    depth_scale : float
        Metres per depth unit, read from the recorded depth sensor [m/unit].
    fps : int
        Nominal frame rate of the depth stream [Hz].
    device_info : dict
        ``name``, ``serial``, ``firmware``, ``product_id`` of the recorded device (None where the
        recording does not hold it).

    Raises
    ------
    ValueError
        Naming the file: it is missing, is not a .bag/.db3, is truncated or corrupt (pyrealsense2 cannot
        open it), has no depth stream (of the requested size), or (while iterating) plays back no
        depth frame at all, or stalls.
    RealSenseUnavailable
        pyrealsense2 (or libusb-1.0) is not installed.

    Notes
    -----
    Frames are yielded in recording order, every depth frame of the file (the player runs not in real
    time, and only the depth stream is enabled, so no frame is dropped by syncing with colour).
    ``len()`` is not defined: the number of frames is known only after decoding them. Each iteration
    plays the file from the start.
    """

    def __init__(self, path, *, width: int | None = None, height: int | None = None, camera: str = "camera"):
        self.path = Path(path)
        self.camera = str(camera)
        self._pipes: list = []
        if self.path.suffix.lower() not in RECORDING_SUFFIXES:
            raise ValueError(f"{self.path}: not a RealSense recording (expected a .bag or .db3 file)")
        if not self.path.is_file():
            raise ValueError(f"{self.path}: no such file" if not self.path.exists() else f"{self.path}: not a file")
        rs = import_pyrealsense2()
        try:
            dev = rs.context().load_device(str(self.path))
        except RuntimeError as exc:
            raise ValueError(f"{self.path}: cannot open the RealSense recording, the file is truncated, corrupt "
                             f"or not a RealSense .bag/.db3 (pyrealsense2: {exc})") from None
        try:
            self.device_info = _device_info(rs, dev)
            found = []
            chosen = None
            for sensor in dev.query_sensors():
                for prof in sensor.get_stream_profiles():
                    if prof.stream_type() != rs.stream.depth or prof.format() != rs.format.z16:
                        continue
                    vp = prof.as_video_stream_profile()
                    found.append((vp.width(), vp.height()))
                    if chosen is None and (width is None or vp.width() == width) and (
                            height is None or vp.height() == height):
                        chosen = (sensor, vp)
            if chosen is None:
                if not found:
                    raise ValueError(f"{self.path}: the recording has no depth (Z16) stream")
                raise ValueError(f"{self.path}: no depth stream of {width}x{height}; the recording has "
                                 f"{', '.join(f'{w}x{h}' for w, h in found)}")
            sensor, vp = chosen
            self.intrinsics = _intrinsics_dict(vp.get_intrinsics())
            self.fps = int(vp.fps())
            try:
                scale = sensor.as_depth_sensor().get_depth_scale()
            except RuntimeError as exc:
                raise ValueError(f"{self.path}: the depth sensor has no depth scale ({exc})") from None
            self.depth_scale = check_positive_scalar(scale, f"{self.path}: depth scale", upper=0.1, unit=" m")
        finally:
            del dev
        self.K = _K(self.intrinsics)
        _warn_distortion(self.intrinsics, str(self.path))

    def __repr__(self) -> str:
        i = self.intrinsics
        return f"RealSenseFileSource({str(self.path)!r}, {i['width']}x{i['height']} @ {self.fps} Hz)"

    def _frames(self) -> Iterator[Frame]:
        rs = import_pyrealsense2()
        i = self.intrinsics
        cfg = rs.config()
        try:
            cfg.enable_device_from_file(str(self.path), repeat_playback=False)
            cfg.enable_stream(rs.stream.depth, i["width"], i["height"], rs.format.z16, self.fps)
            pipe = rs.pipeline()
            # resolve first so that the player is switched to non-real-time before it starts
            resolved = cfg.resolve(rs.pipeline_wrapper(pipe))
            resolved.get_device().as_playback().set_real_time(False)
            profile = pipe.start(cfg)
        except RuntimeError as exc:
            raise ValueError(f"{self.path}: cannot play the recording (pyrealsense2: {exc})") from None
        self._pipes.append(pipe)
        try:
            player = profile.get_device().as_playback()
            player.set_real_time(False)
            n = 0
            last = None
            waited = 0.0
            while not self._closed:
                ok, frames = pipe.try_wait_for_frames(_FIRST_FRAME_TIMEOUT_MS if n == 0 else _POLL_MS)
                if not ok:
                    if n == 0:
                        raise ValueError(
                            f"{self.path}: the recording played back no depth frame (empty, or written by a "
                            "newer RealSense SDK than this pyrealsense2 can decode)")
                    if player.current_status() == rs.playback_status.stopped:
                        ok, frames = pipe.try_wait_for_frames(_POLL_MS)  # one still in flight?
                        if not ok:
                            expected = db3_depth_messages(self.path)
                            if expected is not None and n < expected:
                                raise ValueError(f"{self.path}: played back {n} of the {expected} depth frames "
                                                 "its messages table lists: the recording is corrupt")
                            return
                    else:
                        waited += _POLL_MS / 1000.0
                        if waited > _STALL_S:
                            raise ValueError(f"{self.path}: playback stalled after {n} frames")
                        continue
                waited = 0.0
                depth = frames.get_depth_frame()
                if not depth:
                    continue
                key = (depth.get_frame_number(), depth.get_timestamp())
                if key == last:  # the same frame delivered twice
                    continue
                last = key
                img = _depth_image(depth)
                yield Frame(depth=img, K=self.K, depth_scale=self.depth_scale, stamp=key[1] / 1000.0,
                            camera=self.camera, index=n)
                n += 1
        finally:
            self._stop(pipe)

    def _stop(self, pipe) -> None:
        if pipe in self._pipes:
            self._pipes.remove(pipe)
            try:
                pipe.stop()
            except RuntimeError:
                pass

    def close(self) -> None:
        for pipe in list(self._pipes):
            self._stop(pipe)
        super().close()


class LiveRealSenseSource(FrameSource):
    """Depth frames from a connected RealSense camera (depth stream only).

    Parameters
    ----------
    serial : str, optional
        Serial number of the camera to use; default: the first one found.
    width, height : int
        Depth resolution [px] (848 x 480 is Intel's recommended D435 mode).
    fps : int
        Frame rate [Hz].
    camera : str, optional
        Name put into each frame's ``camera`` field (default: the serial number).
    timeout_ms : int
        Longest wait for one frame [ms]; longer is an error (camera unplugged).

    Attributes
    ----------
    intrinsics, K, depth_scale, device_info
        As for :class:`RealSenseFileSource`, read from the running stream.

    Raises
    ------
    NoRealSenseDevice
        (a ``ValueError`` and a ``RuntimeError``) when no camera, or none with ``serial``, is connected.
    ValueError
        When the camera cannot stream the requested mode.

    Notes
    -----
    Streaming starts in the constructor and stops on :meth:`close`. Iteration yields frames until
    the source is closed; frames are stamped with the camera's timestamp [s]. ``len()`` is not defined.
    """

    def __init__(self, serial: str | None = None, width: int = 848, height: int = 480, fps: int = 30, *,
                 camera: str | None = None, timeout_ms: int = 5000):
        rs = import_pyrealsense2()
        devices = rs.context().query_devices()
        if devices.size() == 0:
            raise NoRealSenseDevice(
                "no RealSense camera is connected (pyrealsense2 finds 0 devices): plug the D435 into a USB 3 "
                "port; on Linux install Intel's udev rules (librealsense config/99-realsense-libusb.rules) or "
                "run as root; to process a recording use RealSenseFileSource(path)")
        serials = [d.get_info(rs.camera_info.serial_number) for d in devices
                   if d.supports(rs.camera_info.serial_number)]
        if serial is not None and str(serial) not in serials:
            raise NoRealSenseDevice(f"no RealSense camera with serial {serial} is connected; connected: {serials}")
        self.timeout_ms = int(timeout_ms)
        self._index = 0
        cfg = rs.config()
        if serial is not None:
            cfg.enable_device(str(serial))
        cfg.enable_stream(rs.stream.depth, int(width), int(height), rs.format.z16, int(fps))
        self._pipe = rs.pipeline()
        try:
            profile = self._pipe.start(cfg)
        except RuntimeError as exc:
            raise ValueError(f"cannot start RealSense depth at {width}x{height} @ {fps} Hz on "
                             f"{serial or 'the first camera'} (pyrealsense2: {exc})") from None
        dev = profile.get_device()
        self.device_info = _device_info(rs, dev)
        self.intrinsics = _intrinsics_dict(profile.get_stream(rs.stream.depth).as_video_stream_profile()
                                           .get_intrinsics())
        self.K = _K(self.intrinsics)
        self.fps = int(fps)
        self.depth_scale = float(dev.first_depth_sensor().get_depth_scale())
        self.camera = camera if camera is not None else (self.device_info.get("serial") or "camera")

    def __repr__(self) -> str:
        return f"LiveRealSenseSource(serial={self.device_info.get('serial')!r})"

    def _frames(self) -> Iterator[Frame]:
        while not self._closed:
            try:
                frames = self._pipe.wait_for_frames(self.timeout_ms)
            except RuntimeError as exc:
                if self._closed:
                    return
                raise RuntimeError(f"RealSense camera {self.device_info.get('serial')}: no frame within "
                                   f"{self.timeout_ms} ms ({exc}); is it still connected?") from None
            depth = frames.get_depth_frame()
            if not depth:
                continue
            yield Frame(depth=_depth_image(depth), K=self.K, depth_scale=self.depth_scale,
                        stamp=depth.get_timestamp() / 1000.0, camera=self.camera, index=self._index)
            self._index += 1

    def close(self) -> None:
        if not self._closed and getattr(self, "_pipe", None) is not None:
            try:
                self._pipe.stop()
            except RuntimeError:
                pass
        super().close()


# ------------------------------------------------------------------------------------------------


def _frames_u16(depth_frames_u16) -> list[np.ndarray]:
    if isinstance(depth_frames_u16, np.ndarray):
        if depth_frames_u16.ndim == 2:
            raise ValueError("depth_frames_u16 must be (frames, H, W); wrap a single image as image[None]")
        frames = list(depth_frames_u16) if depth_frames_u16.ndim == 3 else None
        if frames is None:
            raise ValueError(f"depth_frames_u16 must have shape (frames, H, W), got {depth_frames_u16.shape}")
    elif isinstance(depth_frames_u16, Iterable):
        frames = [np.asarray(f) for f in depth_frames_u16]
    else:
        raise ValueError(f"depth_frames_u16 must be an array (frames, H, W), got {type(depth_frames_u16).__name__}")
    if not frames:
        raise ValueError("depth_frames_u16 holds no frame")
    shape = frames[0].shape
    for k, f in enumerate(frames):
        if f.dtype != np.uint16:
            raise ValueError(f"depth frame {k} has dtype {f.dtype}; record_db3 writes uint16 depth units")
        if f.ndim != 2 or f.shape != shape:
            raise ValueError(f"depth frame {k} has shape {f.shape}; all frames must be 2-D and {shape}")
    if shape[0] < 1 or shape[1] < 1:
        raise ValueError(f"depth frames are empty, shape {shape}")
    return [np.ascontiguousarray(f) for f in frames]


def record_db3(path, depth_frames_u16, K, depth_scale: float = 0.001, fps: int = 30, *, stamps=None,
               name: str = "Intel RealSense D435 (software)", serial: str = "000000000000",
               compress: bool = True, overwrite: bool = False) -> Path:
    """Write depth frames to a RealSense SDK ``.db3`` recording (pyrealsense2 software device + recorder).

    The file plays back through :class:`RealSenseFileSource` (or any RealSense tool of SDK >= 2.59)
    bit-exact, with these intrinsics and depth scale.

    Parameters
    ----------
    path : str or Path
        Output file; must end in ``.db3`` (SDK 2.58+ records only ROS2 rosbag2).
    depth_frames_u16 : ndarray, shape (frames, H, W), uint16, or iterable of (H, W) uint16
        Depth in units of ``depth_scale`` (0 = no data).
    K : array_like, shape (3, 3)
        Pinhole intrinsics of the depth stream [px]; recorded as Brown-Conrady with zero coefficients
        (the D435 depth stream is rectified).
    depth_scale : float
        Metres per depth unit [m/unit] (stored as float32 by the SDK: 0.001 reads back as
        0.0010000000474974513).
    fps : int
        Nominal frame rate of the stream [Hz]; also sets the default timestamps.
    stamps : array_like, shape (frames,), optional
        Frame timestamps [s], strictly increasing; default ``k / fps``.
    name, serial : str
        Device name and serial number written into the recording.
    compress : bool
        Let the SDK compress depth (lossless, its default) or store it raw.
    overwrite : bool
        Replace an existing file at ``path``; otherwise an existing file is an error.

    Returns
    -------
    Path
        ``path``. The recording is written to a temporary ``.<name>.elevmap-tmp-<pid>-<random>.db3`` in the
        same folder and renamed onto ``path`` only once it is complete, so ``path`` is never left
        half-written (the leftover of a killed run is removed by the next call,
        :func:`elevmap.fileio.remove_leftovers`).
    """
    path = Path(path)
    if path.suffix.lower() != ".db3":
        raise ValueError(f"{path}: a RealSense recording written by pyrealsense2 >= 2.58 must end in .db3")
    if path.exists() and not overwrite:
        raise ValueError(f"{path} exists; pass overwrite=True to replace it")
    if path.is_dir():
        raise ValueError(f"{path} is a directory")
    frames = _frames_u16(depth_frames_u16)
    K = check_intrinsics(K, "K")
    scale = check_positive_scalar(depth_scale, "depth_scale", upper=0.1, unit=" m per unit")
    if int(fps) != fps or fps <= 0:
        raise ValueError(f"fps must be a positive integer, got {fps!r}")
    fps = int(fps)
    n = len(frames)
    if stamps is None:
        stamps_ms = np.arange(n) * (1000.0 / fps)
    else:
        s = np.asarray(stamps, dtype=np.float64)
        if s.shape != (n,):
            raise ValueError(f"stamps must have shape ({n},), got {s.shape}")
        if not np.all(np.isfinite(s)) or np.any(np.diff(s) <= 0):
            raise ValueError("stamps must be finite and strictly increasing [s]")
        stamps_ms = s * 1000.0
    H, W = frames[0].shape
    rs = import_pyrealsense2()

    path.parent.mkdir(parents=True, exist_ok=True)
    remove_leftovers(path)
    tmp = new_temp_file(path, ".db3")   # named so that a killed run's leftover is recognised and removed
    tmp.unlink()  # the recorder creates the file itself
    try:
        dev = rs.software_device()
        dev.register_info(rs.camera_info.name, str(name))
        dev.register_info(rs.camera_info.serial_number, str(serial))
        sensor = dev.add_sensor("Stereo Module")
        sensor.add_read_only_option(rs.option.depth_units, scale)  # makes it a depth sensor with a scale
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = rs.stream.depth, 0, 0
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = W, H, fps, 2, rs.format.z16
        intr = rs.intrinsics()
        intr.width, intr.height = W, H
        intr.fx, intr.fy, intr.ppx, intr.ppy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        intr.model = rs.distortion.brown_conrady
        intr.coeffs = [0.0] * 5
        vs.intrinsics = intr
        sensor.add_video_stream(vs)
        try:
            rec = rs.recorder(str(tmp), dev, bool(compress))
            rec_sensor = rec.query_sensors()[0]
            queue = rs.frame_queue(max(2, n))
            rec_sensor.open(rec_sensor.get_stream_profiles()[0])
            rec_sensor.start(queue)
            profile = sensor.get_stream_profiles()[0].as_video_stream_profile()
            for k, d in enumerate(frames):  # inject through the software sensor
                f = rs.software_video_frame()
                f.pixels = d
                f.bpp = 2
                f.stride = W * 2
                f.timestamp = float(stamps_ms[k])
                f.domain = rs.timestamp_domain.hardware_clock
                f.frame_number = k + 1
                f.profile = profile
                f.depth_units = scale
                sensor.on_video_frame(f)
                queue.wait_for_frame(5000)  # recorded; drain so the queue never drops one
            rec_sensor.stop()
            rec_sensor.close()
        except RuntimeError as exc:
            raise RuntimeError(f"{path}: recording failed (pyrealsense2: {exc})") from None
        del rec_sensor, rec, queue, sensor, dev  # closing the recorder finalises the file
        gc.collect()
        try:  # the file must open as a recording before it replaces anything
            check = rs.context().load_device(str(tmp))
            del check
        except RuntimeError as exc:
            raise RuntimeError(f"{path}: the recording just written does not open (pyrealsense2: {exc})") from None
        if path.exists() and not overwrite:
            raise ValueError(f"{path} appeared while recording; not replaced (the recording is discarded)")
        os.chmod(tmp, new_file_mode(path))
        os.replace(tmp, path)
        release_temp(tmp)
    except BaseException:
        release_temp(tmp, remove=True)
        for p in (Path(str(tmp) + "-journal"), Path(str(tmp) + "-wal"), Path(str(tmp) + "-shm")):
            try:
                p.unlink()
            except FileNotFoundError:
                pass
        raise
    return path

