"""Capture sets (format ``d435-captures/1``): planar-target recordings, read and written.

The format is specified in ``docs/capture-set-format.md``: a folder with ``captures.json`` and one
depth file per capture, a ``.npy`` of uint16 (frames, height, width) depth units (0 = no data) or a
RealSense SDK recording (``.bag`` / ``.db3``)::

    {"format": "d435-captures/1",
     "camera": {"model": "D435", "width": 848, "height": 480, "fx": 425.0, "fy": 425.0,
                "ppx": 423.5, "ppy": 239.5, "depth_scale": 0.001, "baseline_m": 0.050},
     "captures": [{"id": "wall_z1.00_y00", "depth": "wall_z1.00_y00.npy",
                   "target": {"kind": "wall", "distance_m": 1.0, "yaw_deg": 0.0, "pitch_deg": 0.0},
                   "background_m": null}, ...]}

Required keys (a missing one is a ``ValueError`` naming the capture and the key):

* top level: ``format`` (= ``"d435-captures/1"``), ``camera``, ``captures``;
* ``camera``: ``width``, ``height`` [px], ``fx``, ``fy``, ``ppx``, ``ppy`` [px], ``depth_scale`` [m/unit]
  (``model`` and ``baseline_m`` [m] are optional);
* each capture: ``id``, ``depth``, ``target`` with ``kind`` (``wall``, ``board`` or ``plane``); a wall
  or board ``distance_m`` [m], a board also ``width_m`` and ``height_m`` [m], ``yaw_deg`` / ``pitch_deg``
  [deg] default to 0, ``background_m`` [m] to null; a plane ``normal`` (3 numbers, unit length, pointing
  towards the camera: ``normal[2] < 0``) and ``offset_m`` > 0 [m] (the plane n . p + offset_m = 0).
* optional per capture: ``mask``, a PNG file of the capture's size, non-zero where a pixel sees the
  target (without one, every pixel the target covers); ``geometry``, ``"measured"`` (the default: the
  target's pose from a tape or laser meter) or ``"fitted"`` (from a plane fit to the frames themselves,
  so statistics against the true distance mean nothing for it).

Unknown keys are kept (``Capture.extra``, ``CaptureSet.extra``) and written back. A target the
camera cannot see is an error: ``distance_m <= 0``, an unknown kind, a board without a positive
width/height, a plane seen edge-on (normal perpendicular to the optical axis), a background not
behind the target. Camera frame: x right, y down, z forward.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..fileio import atomic_output, json_ready, write_json_atomic
from ..frame import Frame

__all__ = ["FORMAT", "Capture", "CaptureSet", "read_capture_set", "write_capture_set", "CAPTURES_JSON",
           "GEOMETRIES", "capture_set_files"]

FORMAT = "d435-captures/1"
CAPTURES_JSON = "captures.json"
CAMERA_REQUIRED = ("width", "height", "fx", "fy", "ppx", "ppy", "depth_scale")
CAPTURE_REQUIRED = ("id", "depth", "target")
TARGET_KINDS = ("wall", "board", "plane")
#: Values of a capture's ``geometry`` key: how its target's pose is known.
GEOMETRIES = ("measured", "fitted")
DEPTH_SUFFIXES = (".npy", ".bag", ".db3")
_CAPTURE_KEYS = ("id", "depth", "target", "background_m", "mask", "geometry")
#: |normal| of a plane target may differ from 1 by this much (numbers rounded when written by hand).
_NORMAL_TOL = 1e-3
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

#: Differences between captures.json and a recording's own intrinsics below these are not reported.
_PX_TOL = 1e-3
_SCALE_RTOL = 1e-5


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _finite(v) -> bool:
    """A finite number (an integer too large for a float is not)."""
    try:
        return math.isfinite(float(v))
    except OverflowError:
        return False


def _number(d: dict, key: str, where: str, *, positive: bool = False, default=None, required: bool = True):
    if key not in d or d[key] is None:
        if required:
            raise ValueError(f"{where}: missing required key '{key}'")
        return default
    v = d[key]
    if not _is_number(v) or not _finite(v):
        raise ValueError(f"{where}: '{key}' must be a finite number, got {v!r}")
    if positive and float(v) <= 0:
        raise ValueError(f"{where}: '{key}' must be > 0, got {v!r}")
    return float(v)


def _check_camera(camera, where: str) -> dict:
    if not isinstance(camera, dict):
        raise ValueError(f"{where}: 'camera' must be an object, got {type(camera).__name__}")
    w = f"{where}: camera"
    for key in ("width", "height"):
        v = camera.get(key)
        if key not in camera:
            raise ValueError(f"{w}: missing required key '{key}'")
        if not _is_number(v) or not _finite(v) or float(v) != int(v) or int(v) < 1:
            raise ValueError(f"{w}: '{key}' must be a positive integer [px], got {v!r}")
    for key in ("fx", "fy"):
        if _number(camera, key, w, positive=True) < 1.0:
            raise ValueError(f"{w}: '{key}' = {camera[key]!r} px is below 1 px: not a camera's focal length")
    for key in ("ppx", "ppy"):
        _number(camera, key, w)
    scale = _number(camera, "depth_scale", w, positive=True)
    if scale > 0.1:
        raise ValueError(f"{w}: 'depth_scale' = {scale} m per unit is implausible (D435: 0.001)")
    _number(camera, "baseline_m", w, positive=True, required=False)
    return camera


def _check_target(target, where: str, background_m) -> None:
    if not isinstance(target, dict):
        raise ValueError(f"{where}: 'target' must be an object, got {type(target).__name__}")
    w = f"{where}: target"
    if "kind" not in target:
        raise ValueError(f"{w}: missing required key 'kind'")
    kind = target["kind"]
    if kind not in TARGET_KINDS:
        raise ValueError(f"{w}: unknown kind {kind!r} (expected 'wall', 'board' or 'plane'); the camera cannot "
                         "see it")
    if kind == "plane":
        _check_plane_target(target, w, where, background_m)
        return
    d = _number(target, "distance_m", w)
    if d <= 0:
        raise ValueError(f"{w}: 'distance_m' = {d} m: the camera cannot see a target at or behind its centre "
                         "(distance must be > 0)")
    yaw = _number(target, "yaw_deg", w, default=0.0, required=False)
    pitch = _number(target, "pitch_deg", w, default=0.0, required=False)
    nz = math.cos(math.radians(yaw)) * math.cos(math.radians(pitch))
    if abs(nz) < 1e-9:
        raise ValueError(f"{w}: yaw_deg {yaw}, pitch_deg {pitch} turn the target edge-on: the camera cannot see it")
    if kind == "board":
        for key in ("width_m", "height_m"):
            if key not in target or target[key] is None:
                raise ValueError(f"{w}: a board needs '{key}' (missing required key)")
            _number(target, key, w, positive=True)
    if background_m is not None:
        if not _is_number(background_m) or not _finite(background_m) or background_m <= 0:
            raise ValueError(f"{where}: 'background_m' must be null or a number > 0 [m], got {background_m!r}")
        if float(background_m) <= d:
            raise ValueError(f"{where}: 'background_m' = {background_m} m is not behind the target at "
                             f"{d} m; it would hide it")


def _check_plane_target(target: dict, w: str, where: str, background_m) -> None:
    """A ``plane`` target: unit ``normal`` towards the camera, ``offset_m`` > 0, no background."""
    if "normal" not in target:
        raise ValueError(f"{w}: missing required key 'normal'")
    m = target["normal"]
    if not isinstance(m, (list, tuple)) or len(m) != 3 or not all(_is_number(x) and _finite(x)
                                                                   for x in m):
        raise ValueError(f"{w}: 'normal' must be 3 finite numbers, got {m!r}")
    norm = math.sqrt(sum(float(x) ** 2 for x in m))
    if abs(norm - 1.0) > _NORMAL_TOL:
        raise ValueError(f"{w}: 'normal' {list(m)} must have unit length, it has {norm:.6g}")
    if float(m[2]) >= 0:
        raise ValueError(f"{w}: 'normal' {list(m)} must point towards the camera (normal[2] < 0); "
                         "the camera cannot see the plane's front")
    off = _number(target, "offset_m", w)
    if off <= 0:
        raise ValueError(f"{w}: 'offset_m' = {off} m must be > 0 (the camera's distance to the plane)")
    if background_m is not None:
        raise ValueError(f"{where}: 'background_m' is for a board; a plane target has none (got {background_m!r})")


def _png_size(path: Path, where: str) -> tuple[int, int]:
    """(width, height) [px] of a PNG from its IHDR chunk, without decoding it."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(24)
    except FileNotFoundError:
        raise ValueError(f"{where}: 'mask' file {path} does not exist") from None
    except OSError as exc:
        raise ValueError(f"{where}: 'mask' file {path} cannot be read ({exc})") from None
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise ValueError(f"{where}: 'mask' file {path} is not a PNG image")
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def _check_mask_name(d: dict, w: str) -> str | None:
    mask = d.get("mask")
    if mask is None:
        return None
    if not isinstance(mask, str) or not mask:
        raise ValueError(f"{w}: 'mask' must be a PNG file name, got {mask!r}")
    if Path(mask).suffix.lower() != ".png":
        raise ValueError(f"{w}: 'mask' file {mask!r} must be a .png")
    return mask


def _check_mask_image(img, camera: dict, where: str, what: str) -> np.ndarray:
    """A decoded mask image -> bool (H, W): non-zero in any channel = the target."""
    H, W = int(camera["height"]), int(camera["width"])
    a = np.asarray(img)
    if a.ndim == 3:
        a = (a != 0).any(axis=2)
    if a.ndim != 2:
        raise ValueError(f"{where}: 'mask' {what} has shape {np.asarray(img).shape}; expected ({H}, {W})")
    if a.shape != (H, W):
        raise ValueError(f"{where}: 'mask' {what} is {a.shape[1]}x{a.shape[0]}, not the camera's {W}x{H}")
    return a != 0


def _npy_header(path: Path, where: str):
    """(shape, dtype, fortran_order) of a .npy, checking that the file holds all its data."""
    try:
        with open(path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
            elif version == (2, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
            else:
                raise ValueError(f"unsupported .npy format version {version}")
            offset = fh.tell()
    except FileNotFoundError:
        raise ValueError(f"{where}: depth file {path} does not exist") from None
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"{where}: depth file {path} is not a readable .npy ({exc})") from None
    if dtype.hasobject:
        raise ValueError(f"{where}: depth file {path} holds Python objects, not uint16 depth")
    need = offset + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    size = path.stat().st_size
    if size < need:
        raise ValueError(f"{where}: depth file {path} is truncated ({size} bytes, the header announces "
                         f"{shape} {dtype} = {need} bytes)")
    return tuple(shape), dtype, fortran


def _check_depth_array(shape, dtype, camera: dict, where: str, what: str) -> None:
    H, W = int(camera["height"]), int(camera["width"])
    if np.dtype(dtype).kind != "u" or np.dtype(dtype).itemsize != 2:
        raise ValueError(f"{where}: 'depth' {what} has dtype {np.dtype(dtype)}; expected uint16 depth units")
    if len(shape) != 3 or shape[0] < 1:
        raise ValueError(f"{where}: 'depth' {what} has shape {shape}; expected (frames >= 1, {H}, {W})")
    if tuple(shape[1:]) != (H, W):
        raise ValueError(f"{where}: 'depth' {what} has shape {shape}: frames of {shape[2]}x{shape[1]} do not "
                         f"match the camera's {W}x{H}")


@dataclass(frozen=True)
class Capture(Mapping):
    """One capture of a capture set (attributes, or read-only dict access to its captures.json entry).

    ``capture.id`` and ``capture["id"]`` are the same; ``dict(capture)`` is :meth:`to_dict`.

    Attributes
    ----------
    id : str
        Identifier (unique within the set).
    depth : str
        The depth file as written in captures.json (relative to the folder).
    path : Path
        That file, resolved against the capture set's folder.
    target : dict
        ``kind``, ``distance_m`` [m], ``yaw_deg``, ``pitch_deg`` [deg], for a board ``width_m``,
        ``height_m`` [m]; for a plane ``normal`` (towards the camera) and ``offset_m`` [m] (as in the
        file; unknown keys kept).
    background_m : float or None
        z [m] of a fronto-parallel wall behind a board; None = nothing.
    extra : dict
        Unknown keys of the capture, kept.
    mask : str or None
        The mask PNG as written in captures.json (relative to the folder); None = every pixel the
        target covers.
    mask_path : Path or None
        That file, resolved against the capture set's folder.
    geometry : str
        ``"measured"`` (the default) or ``"fitted"``: how the target's pose is known.
    """

    id: str
    depth: str
    path: Path
    target: dict
    background_m: float | None = None
    extra: dict = field(default_factory=dict)
    mask: str | None = None
    mask_path: Path | None = None
    geometry: str = "measured"

    @property
    def kind(self) -> str:
        return self.target["kind"]

    @property
    def is_fitted(self) -> bool:
        """True when the target's pose comes from a plane fit to the frames (``geometry`` "fitted")."""
        return self.geometry == "fitted"

    @property
    def plane(self):
        """The target's plane, :class:`noise_model.analysis.planes.Plane`: n . p = offset_m [m] with the
        normal n pointing away from the camera (n_z > 0), so a ``plane`` target's file ``normal`` is -n."""
        from noise_model.analysis.planes import target_plane

        return target_plane(self.target)

    def _pose(self) -> tuple[float, float, float]:
        """(distance_m, yaw_deg, pitch_deg): the file's, or for a plane target the equivalent wall's."""
        if self.kind == "plane":
            from noise_model.analysis.planes import plane_pose

            return plane_pose(self.plane)
        return (float(self.target["distance_m"]), float(self.target.get("yaw_deg") or 0.0),
                float(self.target.get("pitch_deg") or 0.0))

    @property
    def distance_m(self) -> float:
        """z [m] where the target's plane meets the optical axis."""
        return self._pose()[0]

    @property
    def yaw_deg(self) -> float:
        return self._pose()[1]

    @property
    def pitch_deg(self) -> float:
        return self._pose()[2]

    @property
    def is_recording(self) -> bool:
        """True for a RealSense .bag/.db3 depth file, False for .npy."""
        return self.path.suffix.lower() in (".bag", ".db3")

    def to_dict(self) -> dict:
        """The capture as in captures.json."""
        d = {"id": self.id, "depth": self.depth, "target": self.target, "background_m": self.background_m}
        if self.mask is not None:
            d["mask"] = self.mask
        if self.geometry != "measured":
            d["geometry"] = self.geometry
        return {**d, **self.extra}

    # read-only mapping of the captures.json entry
    def __getitem__(self, key):
        return self.to_dict()[key]

    def __iter__(self):
        return iter(self.to_dict())

    def __len__(self) -> int:
        return len(self.to_dict())


def _parse_capture(d, k: int, camera: dict, folder: Path, where: str, *, check_file: bool = True) -> Capture:
    if not isinstance(d, dict):
        raise ValueError(f"{where}: capture #{k} must be an object, got {type(d).__name__}")
    if "id" not in d:
        raise ValueError(f"{where}: capture #{k}: missing required key 'id'")
    cid = d["id"]
    if not isinstance(cid, str) or not cid:
        raise ValueError(f"{where}: capture #{k}: 'id' must be a non-empty string, got {cid!r}")
    w = f"{where}: capture '{cid}'"
    for key in CAPTURE_REQUIRED:
        if key not in d:
            raise ValueError(f"{w}: missing required key '{key}'")
    depth = d["depth"]
    if not isinstance(depth, str) or not depth:
        raise ValueError(f"{w}: 'depth' must be a file name, got {depth!r}")
    if Path(depth).suffix.lower() not in DEPTH_SUFFIXES:
        raise ValueError(f"{w}: 'depth' file {depth!r} must be a .npy, .bag or .db3")
    background = d.get("background_m")
    _check_target(d["target"], w, background)
    mask = _check_mask_name(d, w)
    geometry = d.get("geometry")
    geometry = "measured" if geometry is None else geometry
    if geometry not in GEOMETRIES:
        raise ValueError(f"{w}: 'geometry' must be 'measured' or 'fitted', got {geometry!r}")
    for key, name in (("depth", depth), ("mask", mask)):       # (the writer asks for a plain name instead)
        if check_file and name is not None and not _inside_folder(name):
            raise ValueError(f"{w}: '{key}' file {name!r} is not inside the capture set's folder (an absolute path "
                             "or one through '..'); name a file in the folder")
    path = folder / depth
    mask_path = None if mask is None else folder / mask
    if check_file:
        if Path(depth).suffix.lower() == ".npy":
            shape, dtype, _ = _npy_header(path, w)
            _check_depth_array(shape, dtype, camera, w, f"file {path}")
        elif not path.is_file():
            raise ValueError(f"{w}: 'depth' file {path} does not exist")
        if mask_path is not None:
            mw, mh = _png_size(mask_path, w)
            if Path(depth).suffix.lower() == ".npy" and (mw, mh) != (int(camera["width"]), int(camera["height"])):
                raise ValueError(f"{w}: 'mask' file {mask_path} is {mw}x{mh}, not the camera's "
                                 f"{camera['width']}x{camera['height']}")
    extra = {key: v for key, v in d.items() if key not in _CAPTURE_KEYS}
    return Capture(cid, depth, path, d["target"], None if background is None else float(background), extra,
                   mask, mask_path, geometry)


def _inside_folder(name: str) -> bool:
    """A file name relative to the capture set's folder that stays inside it: not absolute, no '..' part
    (a set must not read, and a user must not be led to share, files from elsewhere)."""
    p = Path(name)
    return not (p.is_absolute() or p.drive or ".." in p.parts or "\\" in name)


def _check_unique(captures: list[Capture], where: str) -> None:
    seen, files = set(), {}
    for c in captures:
        if c.id in seen:
            raise ValueError(f"{where}: capture '{c.id}': 'id' is used twice")
        seen.add(c.id)
        key = os.path.normpath(c.depth)
        if key in files:
            raise ValueError(f"{where}: capture '{c.id}': 'depth' file {c.depth!r} is also capture "
                             f"'{files[key]}''s")
        files[key] = c.id


class CaptureSet:
    """A capture set read from a folder (see :func:`read_capture_set`).

    Attributes
    ----------
    folder : Path
    camera : dict
        As in captures.json (``width``, ``height``, ``fx``, ``fy``, ``ppx``, ``ppy`` [px],
        ``depth_scale`` [m/unit], optional ``model``, ``baseline_m`` [m], unknown keys kept).
    captures : list of Capture
    extra : dict
        Unknown top-level keys of captures.json.
    mismatches : list of str
        Differences found between captures.json's camera and a .bag/.db3 capture's own intrinsics or
        depth scale (the file's values win); filled as recordings are loaded.
    """

    def __init__(self, folder, camera: dict, captures: list[Capture], extra: dict | None = None):
        self.folder = Path(folder)
        self.camera = camera
        self.captures = list(captures)
        self.extra = dict(extra or {})
        self.mismatches: list[str] = []
        self._by_id = {c.id: c for c in self.captures}

    def __repr__(self) -> str:
        return f"CaptureSet({str(self.folder)!r}, {len(self.captures)} captures)"

    def __len__(self) -> int:
        return len(self.captures)

    def __iter__(self):
        return iter(self.captures)

    @property
    def ids(self) -> list[str]:
        return [c.id for c in self.captures]

    @property
    def width(self) -> int:
        return int(self.camera["width"])

    @property
    def height(self) -> int:
        return int(self.camera["height"])

    @property
    def depth_scale(self) -> float:
        """Metres per depth unit [m/unit] of the .npy captures."""
        return float(self.camera["depth_scale"])

    @property
    def K(self) -> np.ndarray:
        """The camera's 3 x 3 pinhole matrix [px] (of the .npy captures)."""
        c = self.camera
        return np.array([[float(c["fx"]), 0.0, float(c["ppx"])], [0.0, float(c["fy"]), float(c["ppy"])],
                         [0.0, 0.0, 1.0]])

    def capture(self, capture_id: str) -> Capture:
        try:
            return self._by_id[capture_id]
        except KeyError:
            raise ValueError(f"{self.folder}: no capture '{capture_id}' (captures: {self.ids})") from None

    def to_dict(self) -> dict:
        """The whole set as in captures.json."""
        return {"format": FORMAT, "camera": self.camera, "captures": [c.to_dict() for c in self.captures],
                **self.extra}

    # -- depth ------------------------------------------------------------------------------------

    def _recording(self, cap: Capture):
        from .realsense import RealSenseFileSource

        src = RealSenseFileSource(cap.path)
        cam = self.camera
        intr = src.intrinsics
        found = []
        for key in ("width", "height", "fx", "fy", "ppx", "ppy"):
            if abs(float(intr[key]) - float(cam[key])) > _PX_TOL:
                found.append(f"{key} {intr[key]!r} (captures.json: {cam[key]!r})")
        if abs(src.depth_scale - float(cam["depth_scale"])) > _SCALE_RTOL * float(cam["depth_scale"]):
            found.append(f"depth_scale {src.depth_scale!r} (captures.json: {cam['depth_scale']!r})")
        if found:
            msg = (f"{self.folder}: capture '{cap.id}': {cap.path.name} has its own " + ", ".join(found)
                   + "; the recording's values are used")
            if msg not in self.mismatches:
                self.mismatches.append(msg)
                warnings.warn(msg, stacklevel=3)
        return src

    def camera_for(self, capture_id: str) -> dict:
        """The camera that applies to a capture: captures.json's, or a recording's own intrinsics and scale."""
        cap = self.capture(capture_id)
        if not cap.is_recording:
            return dict(self.camera)
        with self._recording(cap) as src:
            i = src.intrinsics
            return {**self.camera, **{k: i[k] for k in ("width", "height", "fx", "fy", "ppx", "ppy")},
                    "depth_scale": src.depth_scale}

    def load_mask(self, capture_id: str) -> np.ndarray | None:
        """A capture's mask: bool (H, W), True where a pixel sees the target; None when it has none.

        The PNG may be 8- or 16-bit, grey or colour: a pixel is the target's where any channel is non-zero.
        Its size must be the capture's (a recording's own, for a .bag/.db3 capture).
        """
        cap = self.capture(capture_id)
        if cap.mask_path is None:
            return None
        where = f"{self.folder}: capture '{cap.id}'"
        _png_size(cap.mask_path, where)
        import cv2

        img = cv2.imread(str(cap.mask_path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{where}: 'mask' file {cap.mask_path} cannot be decoded (truncated or not a PNG)")
        camera = self.camera_for(cap.id) if cap.is_recording else self.camera
        return _check_mask_image(img, camera, where, f"file {cap.mask_path}")

    def load_depth(self, capture_id: str) -> np.ndarray:
        """All frames of a capture: uint16 (frames, H, W) depth units (0 = no data).

        A .npy is memory-mapped (read-only); a .bag/.db3 is decoded through
        :class:`~elevmap.sources.realsense.RealSenseFileSource` (its own intrinsics and depth scale win,
        a difference from captures.json is warned about and listed in :attr:`mismatches`).
        """
        cap = self.capture(capture_id)
        where = f"{self.folder}: capture '{cap.id}'"
        if not cap.is_recording:
            shape, dtype, _ = _npy_header(cap.path, where)
            _check_depth_array(shape, dtype, self.camera, where, f"file {cap.path}")
            arr = np.load(cap.path, mmap_mode="r")
            return arr if arr.dtype == np.uint16 else arr.astype(np.uint16)
        with self._recording(cap) as src:
            frames = [f.depth for f in src]
        return np.stack(frames)

    def frames(self, capture_id: str, *, fps: float | None = None, camera: str | None = None) -> Iterator[Frame]:
        """The frames of a capture as :class:`~elevmap.frame.Frame` records (static camera: no pose).

        For a .npy, stamps are ``index / fps`` [s] with ``fps`` from the argument, else the camera's
        optional ``fps`` key, else 30; for a .bag/.db3 they are the recording's own. ``camera`` names the
        frames' camera (default: the camera's ``model``, else ``"camera"``).
        """
        cap = self.capture(capture_id)
        name = camera if camera is not None else str(self.camera.get("model") or "camera")
        if cap.is_recording:
            src = self._recording(cap)
            src.camera = name
            with src:
                yield from src
            return
        rate = float(fps if fps is not None else self.camera.get("fps") or 30.0)
        depth = self.load_depth(capture_id)
        K, scale = self.K, self.depth_scale
        for k in range(depth.shape[0]):
            yield Frame(depth=np.array(depth[k]), K=K, depth_scale=scale, stamp=k / rate, camera=name, index=k)


def _write_mask_png(path: Path, mask: np.ndarray) -> None:
    """Write a bool (H, W) mask as an 8-bit grey PNG (255 = the target, 0 = not), atomically."""
    import cv2

    ok, buf = cv2.imencode(".png", np.where(mask, 255, 0).astype(np.uint8))
    if not ok:
        raise ValueError(f"{path}: the mask could not be encoded as PNG")
    with atomic_output(path) as tmp:
        tmp.write_bytes(buf.tobytes())


def capture_set_files(folder) -> list[str] | None:
    """The names of the files of the capture set in ``folder``: captures.json, its depth files and masks.

    None when the folder holds no readable captures.json (it is not a capture set). Used to tell a capture
    set, which a command may replace whole, from a folder that also holds other files.
    """
    index = Path(folder) / CAPTURES_JSON
    if not index.is_file():
        return None
    try:
        doc = json.loads(index.read_text())
        names = [c[key] for c in doc["captures"] for key in ("depth", "mask") if key in c]
    except (OSError, ValueError, RecursionError, TypeError, KeyError):
        return None
    return [CAPTURES_JSON, *(n for n in names if isinstance(n, str))]


def read_capture_set(folder) -> CaptureSet:
    """Read a capture set (format ``d435-captures/1``) from a folder holding ``captures.json``.

    Parameters
    ----------
    folder : str or Path
        The capture set's folder (or its captures.json).

    Returns
    -------
    CaptureSet

    Raises
    ------
    ValueError
        Naming the file, the capture and the key: no captures.json, invalid JSON, wrong ``format``,
        a missing required key, a target the camera cannot see, a missing depth file, a .npy whose
        shape or dtype does not match the camera, or that is truncated. (.bag/.db3 files are opened
        only when loaded.)
    """
    folder = Path(folder)
    if folder.name == CAPTURES_JSON and folder.is_file():
        folder = folder.parent
    path = folder / CAPTURES_JSON
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file ({folder} is not a capture set)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    except RecursionError:
        raise ValueError(f"{path}: JSON nested too deeply to be a capture set") from None
    return _from_dict(doc, folder, str(path), check_files=True)


def _from_dict(doc, folder: Path, where: str, *, check_files: bool) -> CaptureSet:
    if not isinstance(doc, dict):
        raise ValueError(f"{where}: must hold a JSON object, got {type(doc).__name__}")
    for key in ("format", "camera", "captures"):
        if key not in doc:
            raise ValueError(f"{where}: missing required key '{key}'")
    if doc["format"] != FORMAT:
        raise ValueError(f"{where}: 'format' is {doc['format']!r}, expected {FORMAT!r}")
    camera = _check_camera(doc["camera"], where)
    if not isinstance(doc["captures"], list):
        raise ValueError(f"{where}: 'captures' must be a list, got {type(doc['captures']).__name__}")
    caps = [_parse_capture(d, k, camera, folder, where, check_file=check_files)
            for k, d in enumerate(doc["captures"])]
    _check_unique(caps, where)
    extra = {k: v for k, v in doc.items() if k not in ("format", "camera", "captures")}
    return CaptureSet(folder, camera, caps, extra)


def write_capture_set(folder, camera: dict, captures, *, overwrite: bool = False, extra: dict | None = None,
                      ) -> CaptureSet:
    """Write a capture set: captures.json and one .npy per capture, each file atomically.

    Parameters
    ----------
    folder : str or Path
        Output folder (created if needed).
    camera : dict
        The camera entry (see the module docstring): ``width``, ``height``, ``fx``, ``fy``, ``ppx``,
        ``ppy`` [px], ``depth_scale`` [m/unit], optional ``model``, ``baseline_m``; unknown keys kept.
    captures : list of (dict, ndarray or None) or (dict, ndarray or None, ndarray or None)
        Each capture's entry (``id``, ``target``, optional ``background_m``, ``geometry``, ``depth`` =
        file name, default ``"<id>.npy"``, ``mask`` = file name, unknown keys kept), its depth, uint16
        (frames, height, width), and optionally its mask, bool (height, width) (True = the target),
        written as an 8-bit PNG (0 / 255) named by ``mask``, default ``"<id>_mask.png"``. With None
        instead of a depth array, ``depth`` must name a file already in the folder (e.g. a .db3 you
        recorded), which is referenced, not written; likewise a ``mask`` name without a mask array.
    overwrite : bool
        Replace an existing captures.json / .npy of the same names. Without it, a folder that already
        holds a capture set, or any file this call would write, is an error and nothing is written.
    extra : dict, optional
        Further top-level keys for captures.json.

    Returns
    -------
    CaptureSet
        The set as read back from the folder.

    Raises
    ------
    ValueError
        Naming the capture and the key, before anything is written: invalid camera, missing key,
        invalid target, depth not uint16 (frames, height, width) for the camera, a mask not (height,
        width), duplicate ids or files, a file name that is not a plain name in the folder, existing
        files without ``overwrite``.
        If writing fails part way, the files this call created are removed again.
    """
    folder = Path(folder)
    where = f"{folder / CAPTURES_JSON}"
    camera = json_ready(dict(camera)) if isinstance(camera, dict) else camera
    camera = _check_camera(camera, where)
    if isinstance(captures, (str, bytes)) or not hasattr(captures, "__iter__"):
        raise ValueError("captures must be a list of (capture dict, depth array) pairs")
    entries, arrays, masks = [], [], []
    for k, item in enumerate(captures):
        try:
            d, arr, *rest = item
        except (TypeError, ValueError):
            raise ValueError(f"captures[{k}] must be a (capture dict, depth array) pair") from None
        if len(rest) > 1:
            raise ValueError(f"captures[{k}] must be (capture dict, depth array[, mask array]), got {len(item)} items")
        mask_arr = rest[0] if rest else None
        if not isinstance(d, dict):
            raise ValueError(f"captures[{k}]: the capture must be a dict, got {type(d).__name__}")
        d = json_ready(dict(d))
        cid = d.get("id")
        if isinstance(cid, str) and cid:
            if "/" in cid or "\\" in cid or cid.startswith("."):
                raise ValueError(f"{where}: capture '{cid}': 'id' must be usable as a file name")
            d.setdefault("depth", f"{cid}.npy")
            if mask_arr is not None:
                d.setdefault("mask", f"{cid}_mask.png")
        d.setdefault("background_m", None)
        cap = _parse_capture(d, k, camera, folder, where, check_file=False)
        name = cap.depth
        if Path(name).name != name or name.startswith("."):
            raise ValueError(f"{where}: capture '{cap.id}': 'depth' must be a plain file name in the folder, "
                             f"got {name!r}")
        w = f"{where}: capture '{cap.id}'"
        if arr is None:
            # reference a file already in the folder
            ref = {key: v for key, v in d.items() if not (key == "mask" and mask_arr is not None)}
            _parse_capture(ref, k, camera, folder, where, check_file=True)
        else:
            if not name.lower().endswith(".npy"):
                raise ValueError(f"{w}: 'depth' {name!r} must end in .npy: arrays are written as .npy")
            if not isinstance(arr, np.ndarray):
                raise ValueError(f"{w}: depth must be a numpy array, got {type(arr).__name__}")
            _check_depth_array(arr.shape, arr.dtype, camera, w, "array")
        if cap.mask is not None and (Path(cap.mask).name != cap.mask or cap.mask.startswith(".")):
            raise ValueError(f"{w}: 'mask' must be a plain file name in the folder, got {cap.mask!r}")
        if mask_arr is not None:
            if cap.mask is None:
                raise ValueError(f"{w}: a mask array needs a capture id or a 'mask' file name")
            m = np.asarray(mask_arr)
            if m.dtype != bool:
                raise ValueError(f"{w}: the mask must be a boolean array (True = the target), got dtype {m.dtype}")
            mask_arr = _check_mask_image(m, camera, w, "array")
            if not mask_arr.any():
                raise ValueError(f"{w}: the mask selects no pixel")
        elif cap.mask is not None and arr is not None:    # reference an existing PNG
            mw, mh = _png_size(cap.mask_path, w)
            if (mw, mh) != (camera["width"], camera["height"]):
                raise ValueError(f"{w}: 'mask' file {cap.mask_path} is {mw}x{mh}, not the camera's "
                                 f"{camera['width']}x{camera['height']}")
        entries.append(cap)
        arrays.append(arr)
        masks.append(mask_arr)
    _check_unique(entries, where)
    written_masks: dict[str, str] = {}
    for cap, m in zip(entries, masks):
        if m is None:
            continue
        if cap.mask in written_masks:
            raise ValueError(f"{where}: capture '{cap.id}': 'mask' file {cap.mask!r} is also written for capture "
                             f"'{written_masks[cap.mask]}'")
        written_masks[cap.mask] = cap.id

    json_path = folder / CAPTURES_JSON
    targets = ([json_path] + [c.path for c, a in zip(entries, arrays) if a is not None]
               + [c.mask_path for c, m in zip(entries, masks) if m is not None])
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{folder} exists and is not a folder")
    if not overwrite:
        existing = [p for p in targets if p.exists()]
        if existing:
            raise ValueError(f"{folder}: would overwrite {', '.join(p.name for p in existing)} "
                             "(an existing capture set?); pass overwrite=True to replace them")
    created = [p for p in targets if not p.exists()]
    doc = {"format": FORMAT, "camera": camera, "captures": [c.to_dict() for c in entries],
           **json_ready(dict(extra or {}))}
    try:
        json.dumps(doc)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: not JSON-serialisable ({exc})") from None
    folder.mkdir(parents=True, exist_ok=True)
    try:
        for cap, arr in zip(entries, arrays):
            if arr is None:
                continue
            with atomic_output(cap.path) as tmp:
                with open(tmp, "wb") as fh:
                    np.save(fh, np.ascontiguousarray(arr, dtype=np.uint16), allow_pickle=False)
        for cap, m in zip(entries, masks):
            if m is not None:
                _write_mask_png(cap.mask_path, m)
        write_json_atomic(json_path, doc)  # last: the set exists only once all its files do
    except BaseException:
        for p in created:
            try:
                p.unlink()
            except FileNotFoundError:
                pass
        raise
    return read_capture_set(folder)
