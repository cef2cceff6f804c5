"""A folder of 16-bit depth PNGs with intrinsics and an optional pose file.

The layout written by Open3D's and polylidar-realsense's recorders (and many others)::

    depth/00000000_1580908150203.png     # uint16 depth units, one frame per file
    depth/00000001_1580908153638.png
    camera_intrinsic.json                # {"width", "height", "intrinsic_matrix": 9 numbers, column-major}
    trajectory.log                       # optional poses (Open3D .log or TUM)

:class:`DepthFolderSource` takes the image folder or its parent (then ``depth/``), and finds the
intrinsics file there when none is given. Pose files are never picked up implicitly: pass one.
Frames are the ``*.png`` files of the folder in natural name order (``f2`` before ``f10``).
**Stamps**: when every file name holds a Unix time as its last digit run (13 digits = milliseconds,
10 = seconds, 16 = microseconds, 19 = nanoseconds, e.g. ``00000003_1580908154938.png``), the stamp is
that time in seconds since the epoch; otherwise ``index / fps``.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from noise_model.checks import check_intrinsics, check_positive_scalar

from ..frame import Frame
from .base import FrameSource, natural_key
from .poses import PoseAttacher

__all__ = ["DepthFolderSource", "find_intrinsics", "read_intrinsics", "stamp_from_name"]

#: digits of a Unix time in the given unit -> units per second
_EPOCH_DIGITS = {10: 1, 13: 1000, 16: 1_000_000, 19: 1_000_000_000}


def stamp_from_name(name: str) -> float | None:
    """The Unix time [s] a file name holds as its last digit run, or None.

    ``00000003_1580908154938.png`` -> 1580908154.938 (13 digits: milliseconds); 10, 16 and 19 digits
    are read as seconds, microseconds and nanoseconds; ``1580908154.938.png`` (a decimal number with a
    10-digit integer part) as seconds. Any other name (``000003.png``, ``depth_12.png``) gives None.
    """
    stem = Path(name).stem
    m = re.search(r"(\d+)\.(\d+)$", stem)
    if m and len(m.group(1)) == 10:
        return float(m.group(0))
    runs = re.findall(r"\d+", stem)
    if not runs:
        return None
    last = runs[-1]
    per_second = _EPOCH_DIGITS.get(len(last))
    if per_second is None:
        return None
    return int(last) / per_second


def read_intrinsics(intrinsics) -> tuple[np.ndarray, int | None, int | None]:
    """Intrinsics from a file or a value.

    Parameters
    ----------
    intrinsics : str or Path or dict or array_like
        * a JSON file in Open3D's ``PinholeCameraIntrinsic`` format:
          ``{"width": W, "height": H, "intrinsic_matrix": [fx, 0, 0, 0, fy, 0, cx, cy, 1]}``
          (the 3 x 3 matrix, column-major), or with keys ``fx, fy, ppx, ppy`` (``width``, ``height``);
        * such a dict;
        * a 3 x 3 camera matrix K [px].

    Returns
    -------
    K : ndarray, shape (3, 3)
        [px].
    width, height : int or None
        Image size [px] when given.
    """
    where = "intrinsics"
    if isinstance(intrinsics, (str, Path)):
        where = str(intrinsics)
        try:
            intrinsics = json.loads(Path(intrinsics).read_text())
        except FileNotFoundError:
            raise ValueError(f"{where}: no such intrinsics file") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{where}: not a readable JSON intrinsics file ({exc})") from None
    if isinstance(intrinsics, dict):
        d = intrinsics
        try:
            if "intrinsic_matrix" in d:
                m = np.asarray(d["intrinsic_matrix"], dtype=np.float64)
                if m.size != 9:
                    raise ValueError(f"{where}: intrinsic_matrix must hold 9 numbers (column-major 3x3), "
                                     f"got {m.size}")
                K = m.reshape(3, 3, order="F") if m.ndim == 1 else m
            elif all(k in d for k in ("fx", "fy", "ppx", "ppy")):
                K = np.array([[d["fx"], 0.0, d["ppx"]], [0.0, d["fy"], d["ppy"]], [0.0, 0.0, 1.0]], dtype=np.float64)
            else:
                raise ValueError(f"{where}: expected 'intrinsic_matrix' (Open3D) or 'fx', 'fy', 'ppx', 'ppy'; "
                                 f"got keys {sorted(d)}")
            width = int(d["width"]) if d.get("width") is not None else None
            height = int(d["height"]) if d.get("height") is not None else None
        except (TypeError, ValueError) as exc:
            if str(exc).startswith(where):
                raise
            raise ValueError(f"{where}: bad intrinsics ({exc})") from None
        K = check_intrinsics(K, f"{where}: K")
        for name, v in (("width", width), ("height", height)):
            if v is not None and v < 1:
                raise ValueError(f"{where}: {name} must be >= 1, got {v}")
        return K, width, height
    return check_intrinsics(intrinsics, "intrinsics K"), None, None


def _pngs(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted((p for p in folder.iterdir() if p.suffix.lower() == ".png" and p.is_file()),
                  key=lambda p: natural_key(p.name))


def _looks_like_intrinsics(path: Path) -> bool:
    try:
        d = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError):
        return False
    return isinstance(d, dict) and ("intrinsic_matrix" in d or all(k in d for k in ("fx", "fy", "ppx", "ppy")))


def _json_problem(path: Path) -> str | None:
    """Why a .json file does not parse (empty, truncated, not text), or None when it does."""
    try:
        json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        return str(exc) or type(exc).__name__
    return None


def find_intrinsics(folder) -> Path:
    """The one intrinsics JSON file next to a folder of depth PNGs.

    Looks in ``folder`` and, when it is named ``depth``, in its parent, for ``*.json`` files holding
    ``intrinsic_matrix`` (Open3D) or ``fx, fy, ppx, ppy``.

    Raises
    ------
    ValueError
        None found, or several (then name the one to use).
    """
    folder = Path(folder)
    places = [folder] + ([folder.parent] if folder.name.lower() == "depth" else [])
    candidates = [p for place in places for p in sorted(place.glob("*.json"))]
    found = [p for p in candidates if _looks_like_intrinsics(p)]
    if not found:
        unreadable = [f"{p} ({problem})" for p in candidates if (problem := _json_problem(p))]
        if unreadable:
            raise ValueError(f"{folder}: no readable intrinsics JSON file; " + "; ".join(unreadable)
                             + " is not valid JSON (truncated?)")
        raise ValueError(f"{folder}: no intrinsics JSON file found (Open3D PinholeCameraIntrinsic format); "
                         "pass intrinsics=FILE.json or a 3x3 K")
    if len(found) > 1:
        raise ValueError(f"{folder}: several intrinsics files ({', '.join(str(p) for p in found)}); "
                         "pass the one to use as intrinsics=")
    return found[0]


class DepthFolderSource(FrameSource):
    """Frames from a folder of 16-bit depth PNGs.

    Parameters
    ----------
    folder : str or Path
        Folder holding the ``*.png`` depth images (uint16 depth units, 0 = no data), one per frame,
        or a folder whose ``depth/`` subfolder holds them (Open3D's layout).
    intrinsics : str or Path or dict or array_like, optional
        See :func:`read_intrinsics`: an Open3D ``PinholeCameraIntrinsic`` JSON file, a dict, or K.
        When it gives width/height, every image must have that size. Default: the one intrinsics
        JSON next to the images (:func:`find_intrinsics`).
    poses : str or Path or PoseTrack, optional
        Pose file (TUM or Open3D .log, see :mod:`elevmap.sources.poses`) or a track; each frame gets
        ``T_map_cam = T_map_pose @ pose @ T_pose_cam`` at its stamp (stamped track) or index (per-frame
        track, e.g. a plain Open3D .log, which must then hold exactly one pose per image). Without
        poses ``T_map_cam`` is None: a static camera (the identity).
    depth_scale : float
        Metres per depth unit [m/unit] (0.001 for RealSense's default).
    fps : float
        Frame rate [Hz] for stamps when the file names hold no time (``stamp = index / fps``).
    T_pose_cam, T_map_pose : array_like, shape (4, 4), optional
        Extrinsics applied with the poses (default identity); for polylidar-realsense's T265
        trajectories ``T265_T_POSE_CAM`` and ``T_MAP_T265WORLD`` of :mod:`elevmap.sources.poses`.
    pose_tolerance : float
        Frames up to this far [s] outside a stamped track's span take its end pose.
    camera : str
        Name put into each frame's ``camera`` field.

    Raises
    ------
    ValueError
        Naming the folder or file: no such folder, no PNG in it, bad intrinsics, stamps in the names that
        do not increase, a per-frame pose file with another number of poses; while iterating, an image
        that cannot be read, is not single-channel 16-bit, or does not match the intrinsics' size.
    """

    def __init__(self, folder, intrinsics=None, poses=None, depth_scale: float = 0.001, *, fps: float = 30.0,
                 T_pose_cam=None, T_map_pose=None, pose_tolerance: float = 0.0, camera: str = "camera"):
        root = Path(folder)
        if not root.is_dir():
            raise ValueError(f"{root}: no such folder")
        self.folder = root
        sub = root / "depth"
        if sub.is_dir() and _pngs(sub):                 # Open3D / polylidar layout: root/depth/*.png; the
            self.folder = sub                           # root's own PNGs are then colour or figures
        self.files = _pngs(self.folder)
        if not self.files:
            raise ValueError(f"{root}: no .png depth images in the folder (nor in {root.name}/depth)")
        if intrinsics is None:
            intrinsics = find_intrinsics(self.folder)
        self.intrinsics_source = str(intrinsics) if isinstance(intrinsics, (str, Path)) else None
        self.K, self.width, self.height = read_intrinsics(intrinsics)
        self.depth_scale = check_positive_scalar(depth_scale, "depth_scale", upper=0.1, unit=" m per unit")
        self.fps = check_positive_scalar(fps, "fps")
        self.camera = str(camera)
        names = [stamp_from_name(p.name) for p in self.files]
        if all(s is not None for s in names):
            self.stamps = np.array(names, dtype=np.float64)
            self.stamps_from_names = True
            bad = np.flatnonzero(np.diff(self.stamps) <= 0)
            if bad.size:
                k = int(bad[0]) + 1
                raise ValueError(f"{self.files[k]}: its time stamp {float(self.stamps[k])!r} s does not follow "
                                 f"{self.files[k - 1].name} ({float(self.stamps[k - 1])!r} s)")
        else:
            self.stamps = np.arange(len(self.files)) / self.fps
            self.stamps_from_names = False
        self._attach = None
        self.track = None
        if poses is not None:
            self._attach = PoseAttacher(poses, T_pose_cam, T_map_pose, pose_tolerance, len(self.files))
            self.track = self._attach.track
            if self.track.stamped:  # fail now, not after half the frames
                self.track.at(self.stamps, tolerance=pose_tolerance)

    def __len__(self) -> int:
        return len(self.files)

    def __repr__(self) -> str:
        return f"DepthFolderSource({str(self.folder)!r}, {len(self)} frames)"

    def read(self, index: int) -> np.ndarray:
        """Depth image ``index``: uint16 (H, W) depth units."""
        try:
            import cv2
        except ImportError as exc:
            raise ImportError(f"reading PNG depth images needs OpenCV ({exc}); "
                              "install it with `pip install opencv-python-headless`") from exc
        path = self.files[index]
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{path}: cannot read the image (missing, truncated or not a PNG)")
        if img.dtype != np.uint16 or img.ndim != 2:
            chans = 1 if img.ndim == 2 else img.shape[2]
            raise ValueError(f"{path}: not a 16-bit single-channel depth image ({img.dtype}, {chans} channel(s))")
        if self.width is not None and img.shape[1] != self.width or self.height is not None and \
                img.shape[0] != self.height:
            raise ValueError(f"{path}: image is {img.shape[1]}x{img.shape[0]} but the intrinsics are "
                             f"{self.width}x{self.height}")
        return img

    def _raw_frames(self) -> Iterator[Frame]:
        for k in range(len(self.files)):
            if self._closed:
                return
            yield Frame(depth=self.read(k), K=self.K, depth_scale=self.depth_scale, stamp=float(self.stamps[k]),
                        camera=self.camera, index=k)

    def _frames(self) -> Iterator[Frame]:
        return self._raw_frames() if self._attach is None else self._attach.attach(self._raw_frames())
