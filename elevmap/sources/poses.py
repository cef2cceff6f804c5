"""Camera poses from a file, interpolated to each frame, and attached to any source.

Two pose file formats are read by :func:`read_pose_file`:

* **TUM** text (``.txt``, ``.tum``, ...): one pose per line, ``timestamp tx ty tz qx qy qz qw``
  (stamp [s], translation [m], unit quaternion scalar-last); ``#`` starts a comment. Each line is
  ``T_world_body``: it maps body-frame points into the world frame.
* **Open3D .log** (``.log``): per pose a header line of integers (``id id count``; some writers add
  more fields, e.g. polylidar-realsense a timestamp in ms), then four lines of the 4 x 4 matrix.
  Without stamps, the k-th matrix belongs to the k-th frame (by index). ``log_stamp_scale`` turns
  the header's 4th field into stamps: ``stamp = field * log_stamp_scale`` [s].

:meth:`PoseTrack.at` interpolates a stamped track: positions linearly, rotations by slerp
(``R0 exp(a log(R0^T R1))``, what :class:`scipy.spatial.transform.Slerp` computes). **Outside the
track's time span** a stamp is an error (``ValueError``), except within ``tolerance`` seconds of either
end, where it takes the end pose (clamped, never extrapolated). Stamps must be strictly increasing in
the file.

:func:`with_poses` wraps any source of :class:`~elevmap.frame.Frame` and attaches
``T_map_cam = T_map_pose @ track(stamp) @ T_pose_cam`` to every frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from noise_model.checks import check_transform

from ..frame import Frame
from .base import FrameSource

__all__ = [
    "PoseTrack",
    "read_pose_file",
    "with_poses",
    "PosedSource",
    "PoseAttacher",
    "T265_T_POSE_CAM",
    "T_MAP_T265WORLD",
]

#: Largest |R R^T - I| accepted in a pose file; rotations within it are projected onto SO(3).
ORTHONORMAL_TOL = 1e-3

#: D400 optical frame (x right, y down, z forward) in a T265 pose frame (x right, y up, z backward),
#: ignoring the lever arm between the two cameras: the convention of polylidar-realsense
#: (``H_t265_d400 = diag(1, -1, -1, 1)``). Use as ``T_pose_cam`` with T265 trajectories.
T265_T_POSE_CAM = np.diag([1.0, -1.0, -1.0, 1.0])

#: The T265 world frame (y up, -z the initial heading, x right) as seen from an elevation map frame
#: (x forward, y left, z up): ``p_map = T_MAP_T265WORLD @ p_t265world``. Use as ``T_map_pose``.
T_MAP_T265WORLD = np.array([[0.0, 0.0, -1.0, 0.0],
                            [-1.0, 0.0, 0.0, 0.0],
                            [0.0, 1.0, 0.0, 0.0],
                            [0.0, 0.0, 0.0, 1.0]])


def _project_rotations(R: np.ndarray) -> np.ndarray:
    """Nearest rotations (polar decomposition) of near-rotation matrices (N, 3, 3)."""
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


@dataclass(frozen=True)
class PoseTrack:
    """A sequence of poses ``T_world_body`` (4 x 4), stamped or per frame index.

    Attributes
    ----------
    poses : ndarray, shape (N, 4, 4)
        ``T_world_body``: maps body-frame points into the track's world frame [m]. Rotations within
        ``ORTHONORMAL_TOL`` of orthonormal are accepted and projected onto SO(3) (nearest rotation).
    stamps : ndarray, shape (N,), or None
        Strictly increasing times [s]; None for a per-frame-index track (Open3D .log).
    source : str
        Where the track came from (file name), for messages.
    """

    poses: np.ndarray
    stamps: np.ndarray | None = None
    source: str = "poses"

    def __post_init__(self):
        P = np.asarray(self.poses, dtype=np.float64)
        if P.ndim != 3 or P.shape[1:] != (4, 4) or P.shape[0] < 1:
            raise ValueError(f"{self.source}: poses must have shape (N, 4, 4), N >= 1, got {P.shape}")
        bad = ~np.all(np.isfinite(P), axis=(1, 2))
        bad |= ~np.all(np.abs(P[:, 3] - [0.0, 0.0, 0.0, 1.0]) <= 1e-6, axis=1)
        R = P[:, :3, :3]
        with np.errstate(invalid="ignore"):
            err = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
            bad |= ~(err <= ORTHONORMAL_TOL) | ~(np.linalg.det(R) > 0)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            check_transform(P[k], f"{self.source}: pose {k}", tol=ORTHONORMAL_TOL)  # raises with the reason
            raise ValueError(f"{self.source}: pose {k} is not a rigid transform")
        P = P.copy()
        P[:, :3, :3] = _project_rotations(R)
        P[:, 3] = [0.0, 0.0, 0.0, 1.0]
        P.flags.writeable = False
        object.__setattr__(self, "poses", P)
        if self.stamps is not None:
            s = np.asarray(self.stamps, dtype=np.float64)
            if s.shape != (P.shape[0],):
                raise ValueError(f"{self.source}: {P.shape[0]} poses but stamps of shape {s.shape}")
            if not np.all(np.isfinite(s)):
                raise ValueError(f"{self.source}: non-finite stamps")
            bad = np.flatnonzero(np.diff(s) <= 0)
            if bad.size:
                k = int(bad[0]) + 1
                raise ValueError(f"{self.source}: stamps must be strictly increasing; pose {k} at {float(s[k])!r} s "
                                 f"follows {float(s[k - 1])!r} s")
            s = s.copy()
            s.flags.writeable = False
            object.__setattr__(self, "stamps", s)

    def __len__(self) -> int:
        return self.poses.shape[0]

    @property
    def stamped(self) -> bool:
        return self.stamps is not None

    @property
    def span(self) -> tuple[float, float]:
        """(first, last) stamp [s] of a stamped track."""
        if self.stamps is None:
            raise ValueError(f"{self.source}: the track has no stamps (poses are per frame index)")
        return float(self.stamps[0]), float(self.stamps[-1])

    def at(self, stamps, *, tolerance: float = 0.0) -> np.ndarray:
        """Poses at the given times, interpolated.

        Parameters
        ----------
        stamps : float or array_like, shape (M,)
            Times [s], in the track's clock.
        tolerance : float
            Stamps up to this far [s] before the first or after the last pose take that end pose;
            further out is an error.

        Returns
        -------
        ndarray, shape (M, 4, 4)
            ``T_world_body`` at each stamp: translation linear in time between the two poses around
            it, rotation by slerp; a stamp equal to a pose's stamp gives that pose.

        Raises
        ------
        ValueError
            The track has no stamps, or a stamp lies outside ``[first - tolerance, last + tolerance]``.
        """
        if self.stamps is None:
            raise ValueError(f"{self.source}: the track has no stamps (poses are per frame index); use at_index")
        s = np.atleast_1d(np.asarray(stamps, dtype=np.float64))
        if s.ndim != 1:
            raise ValueError(f"stamps must be a scalar or 1-D, got shape {s.shape}")
        if not np.all(np.isfinite(s)):
            raise ValueError("stamps must be finite")
        t = self.stamps
        tol = float(tolerance)
        out_of_span = (s < t[0] - tol) | (s > t[-1] + tol)
        if out_of_span.any():
            bad = s[out_of_span][0]
            raise ValueError(f"{self.source}: stamp {float(bad)!r} s is outside the pose track's span "
                             f"[{float(t[0])!r}, {float(t[-1])!r}] s (tolerance {tol} s)")
        s = np.clip(s, t[0], t[-1])
        out = np.empty((s.size, 4, 4))
        out[:] = np.eye(4)
        if t.size == 1:
            out[:] = self.poses[0]
            return out
        from scipy.spatial.transform import Rotation

        i = np.clip(np.searchsorted(t, s, side="right") - 1, 0, t.size - 2)
        a = (s - t[i]) / (t[i + 1] - t[i])
        p0, p1 = self.poses[i, :3, 3], self.poses[i + 1, :3, 3]
        out[:, :3, 3] = p0 + a[:, None] * (p1 - p0)
        # slerp between the two poses around each stamp: R0 exp(a log(R0^T R1)) (what Slerp does)
        R0 = Rotation.from_matrix(self.poses[i, :3, :3])
        step = (R0.inv() * Rotation.from_matrix(self.poses[i + 1, :3, :3])).as_rotvec()
        out[:, :3, :3] = (R0 * Rotation.from_rotvec(a[:, None] * step)).as_matrix()
        exact = np.flatnonzero(s == t[i])  # on a pose: that pose exactly (not through quaternions)
        out[exact] = self.poses[i[exact]]
        exact = np.flatnonzero(s == t[i + 1])
        out[exact] = self.poses[i[exact] + 1]
        return out

    def at_index(self, indices) -> np.ndarray:
        """Poses of the given frame indices (for a per-frame track, e.g. an Open3D .log): (M, 4, 4)."""
        k = np.atleast_1d(np.asarray(indices))
        if k.ndim != 1 or not np.issubdtype(k.dtype, np.integer):
            raise ValueError(f"indices must be integers, got {indices!r}")
        bad = (k < 0) | (k >= len(self))
        if bad.any():
            raise ValueError(f"{self.source}: frame index {int(k[bad][0])} has no pose (the file has "
                             f"{len(self)} poses)")
        return self.poses[k].copy()


# ------------------------------------------------------------------------------------------------
# readers


def _numbers(text: str, path: Path, lineno: int, n: int | None, what: str) -> list[float]:
    try:
        vals = [float(x) for x in text.replace(",", " ").split()]
    except ValueError:
        raise ValueError(f"{path}, line {lineno}: not numbers: {text.strip()!r} (expected {what})") from None
    if n is not None and len(vals) != n:
        raise ValueError(f"{path}, line {lineno}: {len(vals)} numbers, expected {n} ({what})")
    if not all(np.isfinite(vals)):
        raise ValueError(f"{path}, line {lineno}: non-finite value in {text.strip()!r}")
    return vals


def _read_tum(path: Path, lines: list[str]) -> PoseTrack:
    from scipy.spatial.transform import Rotation

    stamps, poses, where = [], [], []
    what = "timestamp tx ty tz qx qy qz qw"
    for lineno, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        v = _numbers(text, path, lineno, 8, what)
        q = np.array(v[4:8])
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > 1e-2:
            raise ValueError(f"{path}, line {lineno}: quaternion (qx qy qz qw) has norm {norm:.4g}, not 1")
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
        T[:3, 3] = v[1:4]
        stamps.append(v[0])
        poses.append(T)
        where.append(lineno)
    if not poses:
        raise ValueError(f"{path}: no poses (expected lines '{what}')")
    s = _increasing(path, stamps, where)
    return PoseTrack(np.array(poses), s, str(path))


def _increasing(path, stamps, lines) -> np.ndarray:
    """The stamps as an array; ValueError naming the file and line of the first that does not increase."""
    s = np.array(stamps, dtype=np.float64)
    bad = np.flatnonzero(np.diff(s) <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise ValueError(f"{path}, line {lines[k]}: timestamp {float(s[k])!r} does not increase "
                         f"(previous {float(s[k - 1])!r})")
    return s


def _scaled(value: float, scale: float) -> float:
    """value * scale, as value / n when scale = 1/n (so 1580908154939 * 1e-3 is 1580908154.939 exactly)."""
    inv = 1.0 / scale
    n = round(inv)
    return value / n if n >= 1 and abs(inv - n) <= 1e-9 * inv else value * scale


def _read_log(path: Path, lines: list[str], log_stamp_scale: float | None) -> PoseTrack:
    rows = [(k, ln.strip()) for k, ln in enumerate(lines, 1) if ln.strip()]
    if not rows:
        raise ValueError(f"{path}: no poses (expected Open3D .log blocks: a header line, then 4 matrix rows)")
    if len(rows) % 5:
        raise ValueError(f"{path}, line {rows[-1][0]}: the file ends inside a pose block ({len(rows)} non-empty "
                         "lines; each pose is a header line and 4 matrix rows)")
    poses, stamps = [], []
    for b in range(0, len(rows), 5):
        hline, header = rows[b]
        h = _numbers(header, path, hline, None, "a header line of integers 'id id count'")
        if len(h) < 3 or len(h) > 8:
            raise ValueError(f"{path}, line {hline}: a header line of 3 integers ('id id count') expected, "
                             f"got {header!r}")
        if log_stamp_scale is not None:
            if len(h) < 4:
                raise ValueError(f"{path}, line {hline}: no 4th header field to read a timestamp from")
            stamps.append(_scaled(h[3], log_stamp_scale))
        M = np.array([_numbers(rows[b + r][1], path, rows[b + r][0], 4, "4 numbers of a matrix row")
                      for r in range(1, 5)])
        if not np.allclose(M[3], [0, 0, 0, 1], atol=1e-6):
            raise ValueError(f"{path}, line {rows[b + 4][0]}: last matrix row must be 0 0 0 1, got {M[3].tolist()}")
        err = float(np.abs(M[:3, :3] @ M[:3, :3].T - np.eye(3)).max())
        if err > ORTHONORMAL_TOL or np.linalg.det(M[:3, :3]) <= 0:
            raise ValueError(f"{path}, lines {rows[b + 1][0]}-{rows[b + 3][0]}: not a rotation "
                             f"(|R R^T - I| = {err:.2e}, det {np.linalg.det(M[:3, :3]):.3f})")
        M[3] = [0.0, 0.0, 0.0, 1.0]
        poses.append(M)
    s = None
    if log_stamp_scale is not None:
        s = _increasing(path, stamps, [rows[5 * k][0] for k in range(len(stamps))])
    return PoseTrack(np.array(poses), s, str(path))


def read_pose_file(path, *, fmt: str | None = None, log_stamp_scale: float | None = None) -> PoseTrack:
    """Read a pose file: TUM text or Open3D .log.

    Parameters
    ----------
    path : str or Path
        The file.
    fmt : {"tum", "log"}, optional
        Format; default from the suffix (``.log`` -> Open3D log, anything else -> TUM).
    log_stamp_scale : float, optional
        For a .log: read the header line's 4th field as a timestamp, times this factor [s per unit]
        (1e-3 for polylidar-realsense's milliseconds). Default: no stamps, poses per frame index.

    Returns
    -------
    PoseTrack
        Poses ``T_world_body`` as in the file (rotations projected onto SO(3): the nearest rotation,
        a change of the order of the file's rounding); stamps [s] or None.

    Raises
    ------
    ValueError
        Naming the file and the line: unreadable, wrong number of values, not numbers, a quaternion
        that is not unit, a matrix that is not a rigid transform, stamps that do not increase.
    """
    path = Path(path)
    if fmt is None:
        fmt = "log" if path.suffix.lower() == ".log" else "tum"
    if fmt not in ("tum", "log"):
        raise ValueError(f"fmt must be 'tum' or 'log', got {fmt!r}")
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ValueError(f"{path}: no such pose file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the pose file ({exc})") from None
    lines = text.splitlines()
    return _read_log(path, lines, log_stamp_scale) if fmt == "log" else _read_tum(path, lines)


def _as_track(track) -> PoseTrack:
    if isinstance(track, PoseTrack):
        return track
    if isinstance(track, (str, Path)):
        return read_pose_file(track)
    raise ValueError(f"poses must be a PoseTrack or a pose file path, got {type(track).__name__}")


class PoseAttacher:
    """Computes ``T_map_cam = T_map_pose @ track(frame) @ T_pose_cam`` for frames (shared by the sources).

    Parameters are those of :func:`with_poses`; ``n_frames`` (when known) is checked against a
    per-index track.
    """

    def __init__(self, track, T_pose_cam=None, T_map_pose=None, tolerance: float = 0.0,
                 n_frames: int | None = None):
        self.track = _as_track(track)
        self.T_pose_cam = check_transform(np.eye(4) if T_pose_cam is None else T_pose_cam, "T_pose_cam")
        self.T_map_pose = check_transform(np.eye(4) if T_map_pose is None else T_map_pose, "T_map_pose")
        self.tolerance = float(tolerance)
        if not self.track.stamped and n_frames is not None and n_frames != len(self.track):
            raise ValueError(f"{self.track.source}: {len(self.track)} poses (one per frame index) for a "
                             f"source of {n_frames} frames")

    def pose_of(self, frame: Frame) -> np.ndarray:
        """``T_map_cam`` (4, 4) of a frame: the track at its stamp (or index) composed with the extrinsics."""
        if self.track.stamped:
            T = self.track.at(frame.stamp, tolerance=self.tolerance)[0]
        else:
            T = self.track.at_index(frame.index)[0]
        return self.T_map_pose @ T @ self.T_pose_cam

    def attach(self, frames) -> Iterator[Frame]:
        """Yield each frame with its pose (any previous pose replaced, ``pose_cov`` kept)."""
        for frame in frames:
            yield frame.with_pose(self.pose_of(frame), frame.pose_cov)


class PosedSource(FrameSource):
    """A source whose frames carry ``T_map_cam`` from a pose track (see :func:`with_poses`)."""

    def __init__(self, source, track, T_pose_cam=None, *, T_map_pose=None, tolerance: float = 0.0):
        self.source = source
        try:
            n = len(source)
        except TypeError:
            n = None
        self._attach = PoseAttacher(track, T_pose_cam, T_map_pose, tolerance, n)
        self.track = self._attach.track

    def __len__(self) -> int:
        return len(self.source)

    def __repr__(self) -> str:
        return f"with_poses({self.source!r}, {self.track.source!r})"

    def _frames(self) -> Iterator[Frame]:
        return self._attach.attach(self.source)

    def close(self) -> None:
        close = getattr(self.source, "close", None)
        if close is not None:
            close()
        super().close()


def with_poses(source, track, T_pose_cam=np.eye(4), *, T_map_pose=None, tolerance: float = 0.0) -> PosedSource:
    """Attach poses from a track to every frame of a source.

    Parameters
    ----------
    source : iterable of Frame
        Any source (closed together with the wrapper).
    track : PoseTrack or str or Path
        The poses (a path is read with :func:`read_pose_file`). A stamped track is interpolated at each
        frame's ``stamp`` (same clock, [s]); a per-index track (Open3D .log) gives frame k the k-th pose.
    T_pose_cam : array_like, shape (4, 4)
        The camera's (depth optical frame: x right, y down, z forward) pose in the tracked body frame.
    T_map_pose : array_like, shape (4, 4), optional
        The track's world frame in the map frame (x forward, y left, z up); default identity.
    tolerance : float
        Frames up to this far [s] outside the track's span take the end pose; further is a ValueError.

    Returns
    -------
    PosedSource
        Yields each frame with ``T_map_cam = T_map_pose @ T_world_body(stamp) @ T_pose_cam`` (any
        pose the frame had is replaced; its ``pose_cov`` is kept).
    """
    return PosedSource(source, track, T_pose_cam, T_map_pose=T_map_pose, tolerance=tolerance)
