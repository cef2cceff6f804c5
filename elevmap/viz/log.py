"""The project's single rerun module: every ``rerun`` call of elevmap lives here.

The functions take plain NumPy arrays plus an entity path and never import the mapping or noise-model
internals, so the maths stays testable without rerun and this module can follow rerun's API changes
alone (rerun-sdk 0.41 is pinned: it renames its API every minor release).

Frames and entity paths
-----------------------
Entity paths mirror frames: data logged at an entity is expressed in that entity's frame.

* ``world``: the map frame, right-handed, z up (:func:`log_world_frame`), in metres.
* ``world/camera_<i>``: a camera frame (RealSense/OpenCV: x right, y down, z forward), placed by a
  ``Transform3D`` holding ``T_world_cam`` (maps camera-frame points into ``world``).
* ``world/camera_<i>/depth``: the pinhole (intrinsics, ``camera_xyz=RDF``) and its depth image.
* ``plots/<name>``: static 2-D charts drawn by :func:`log_series_plot` on a canvas of
  :data:`PLOT_CANVAS` units (not metres).

Files
-----
:func:`open_recording` writes the ``.rrd`` to a hidden temporary file in the destination folder and
renames it over the destination only when the recording is finalised without error, so a failed or
interrupted run never leaves a partial file at the destination and never damages a file that was
already there (a *successful* run does replace it).
"""

from __future__ import annotations

import math
import os
import tempfile
import warnings
from collections.abc import Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from scipy.spatial.transform import Rotation

__all__ = [
    "AtomicRecording",
    "open_recording",
    "log_world_frame",
    "log_transform",
    "log_camera",
    "log_depth",
    "log_points",
    "ellipsoid_parameters",
    "log_covariance_ellipsoids",
    "log_scalar",
    "set_time",
    "log_text",
    "log_series_plot",
    "colormap",
    "default_blueprint",
    "log_height_mesh",
    "log_trail",
    "log_exact",
    "log_depth_png",
    "robust_range",
    "PLOT_CANVAS",
    "PLOT_VISUAL_BOUNDS",
    "SERIES_COLORS",
    "log_rgb_image",
    "map_image",
    "compare_blueprint",
]


# ---------------------------------------------------------------------------------------------
# Recordings written atomically
# ---------------------------------------------------------------------------------------------
class AtomicRecording:
    """A rerun recording saved atomically to ``path`` (and/or streamed to a spawned viewer).

    Use it as a context manager; ``with`` yields the :class:`rerun.RecordingStream` to log to::

        with open_recording("demo.rrd", "elevmap") as rec:
            log_points(rec, "world/points", points_world)

    On a normal exit the stream is flushed, the file sink closed (footer written), the temporary
    file fsync'ed and renamed over ``path`` with :func:`os.replace`. On an exception (including
    ``KeyboardInterrupt``) the temporary file is deleted and ``path`` is left untouched.
    Without ``with``, call :meth:`finalise` or :meth:`abort` yourself. A process killed outright
    (SIGKILL, power loss) can leave a hidden ``.<name>.<random>.part`` file, never a partial ``path``.

    With ``spawn=True`` the ``rerun`` viewer executable must be on PATH (it is in the venv's
    ``bin``). If the viewer is unreachable (no display, closed early) :meth:`finalise` warns
    (``RuntimeWarning``) and still writes the file.

    Attributes
    ----------
    recording : rerun.RecordingStream
        The stream to log to.
    path : str or None
        Absolute destination of the ``.rrd`` file (None: viewer only).
    tmp_path : str or None
        The temporary file being written, in the same folder as ``path``; None once closed.
    """

    def __init__(self, path, application_id: str, recording_id: str | None = None, spawn: bool = False,
                 blueprint: rrb.Blueprint | None = None):
        if path is None and not spawn:
            raise ValueError("open_recording needs a path, spawn=True, or both")
        self.path = None if path is None else os.path.abspath(os.fspath(path))
        self.tmp_path = None
        self._closed = False
        self._viewer = bool(spawn)
        if self.path is not None:
            if os.path.isdir(self.path):
                raise IsADirectoryError(f"{self.path} is a directory, not an .rrd file path")
            directory = os.path.dirname(self.path)
            fd, self.tmp_path = tempfile.mkstemp(prefix=f".{os.path.basename(self.path)}.", suffix=".part",
                                                 dir=directory)
            os.close(fd)
        try:
            self.recording = rr.RecordingStream(application_id, recording_id=recording_id)
            sinks = []
            if self.tmp_path is not None:
                sinks.append(rr.FileSink(self.tmp_path))
            if spawn:
                self.recording.spawn(connect=False)
                sinks.append(rr.GrpcSink())
            self.recording.set_sinks(*sinks, default_blueprint=blueprint)
        except BaseException:
            self._remove_tmp()
            raise

    # -- context manager ----------------------------------------------------------------------
    def __enter__(self) -> rr.RecordingStream:
        return self.recording

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.finalise()
        else:
            self.abort()
        return False

    # -- closing ------------------------------------------------------------------------------
    def finalise(self, timeout_sec: float = 120.0) -> str | None:
        """Flush, close the sinks and atomically move the file into place.

        Returns
        -------
        str or None
            The destination path, or None when recording to a viewer only.
        """
        if self._closed:
            return self.path
        try:
            try:
                self.recording.flush(timeout_sec=timeout_sec)
            except RuntimeError as exc:
                # A viewer that died or never started must not cost the user the file: the gRPC sink
                # fails the flush, the file sink is unaffected and is closed by disconnect() below.
                if not (self._viewer and "grpc" in str(exc).lower()):
                    raise
                warnings.warn(f"rerun viewer unreachable ({exc}); the recording file is still written",
                              RuntimeWarning, stacklevel=2)
            self.recording.disconnect()          # closes the file sink and writes the footer
            if self.tmp_path is not None:
                with open(self.tmp_path, "rb") as fh:
                    os.fsync(fh.fileno())
                os.chmod(self.tmp_path, _new_file_mode(self.path))
                os.replace(self.tmp_path, self.path)
                self.tmp_path = None
                _fsync_dir(os.path.dirname(self.path))
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return self.path

    close = finalise

    def abort(self) -> None:
        """Close the stream and delete the temporary file; ``path`` is not touched."""
        if self._closed:
            return
        self._closed = True
        try:
            self.recording.disconnect()
        except Exception:  # noqa: BLE001 - cleaning up after a failure; the original error matters
            pass
        finally:
            self._remove_tmp()

    def _remove_tmp(self) -> None:
        if self.tmp_path is not None:
            try:
                os.unlink(self.tmp_path)
            except FileNotFoundError:
                pass
            self.tmp_path = None


def _new_file_mode(path: str) -> int:
    """Permissions for the finished file: those of the file it replaces, else 0o666 minus the umask.

    (``tempfile.mkstemp`` creates the temporary file 0o600.)
    """
    try:
        return os.stat(path).st_mode & 0o7777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def _fsync_dir(directory: str) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def open_recording(path, application_id: str, recording_id: str | None = None, spawn: bool = False,
                   blueprint: rrb.Blueprint | None = None) -> AtomicRecording:
    """Open a recording that is written atomically to ``path`` and/or streamed to a new viewer.

    Parameters
    ----------
    path : str or os.PathLike or None
        Destination ``.rrd`` file. Data goes to a hidden temporary file in the same folder
        (``.<name>.<random>.part``) until :meth:`AtomicRecording.finalise`. None: no file.
    application_id : str
        rerun application id (the viewer keys blueprints on it).
    recording_id : str, optional
        rerun recording id; random when None.
    spawn : bool
        Also start a rerun viewer and stream to it.
    blueprint : rerun.blueprint.Blueprint, optional
        Default layout stored with the recording (see :func:`default_blueprint`).

    Returns
    -------
    AtomicRecording
        A context manager; ``with open_recording(...) as rec`` gives the ``rr.RecordingStream``.

    Raises
    ------
    ValueError
        If neither ``path`` nor ``spawn`` is given.
    FileNotFoundError
        If the destination folder does not exist (raised before anything is logged).
    """
    return AtomicRecording(path, application_id, recording_id=recording_id, spawn=spawn, blueprint=blueprint)


# ---------------------------------------------------------------------------------------------
# Frames, cameras and images
# ---------------------------------------------------------------------------------------------
def log_world_frame(rec: rr.RecordingStream, entity: str = "world") -> None:
    """Declare ``entity`` a right-handed, z-up frame (the map frame), static."""
    rec.log(entity, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)


def _as_transform(T, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{name} must be a finite 4x4 homogeneous transform, got shape {T.shape}")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) <= 0:
        raise ValueError(f"{name} rotation part is not a proper rotation")
    return T


def log_transform(rec: rr.RecordingStream, entity: str, T_parent_child, static: bool = False) -> None:
    """Place the frame ``entity`` in its parent's frame.

    Parameters
    ----------
    T_parent_child : array_like, shape (4, 4)
        Maps points of the child frame (``entity``) into the parent frame: p_parent = R p_child + t
        (t [m]). Stored by rerun as float32 translation + quaternion (x, y, z, w).
    static : bool
        Log as static (timeless) data.
    """
    T = _as_transform(T_parent_child, "T_parent_child")
    q_xyzw = Rotation.from_matrix(T[:3, :3]).as_quat()
    rec.log(entity, rr.Transform3D(translation=T[:3, 3], quaternion=q_xyzw), static=static)


def log_camera(rec: rr.RecordingStream, entity: str, K, width: int, height: int, T_parent_cam=None,
               static: bool = True, image_plane_distance: float | None = None) -> None:
    """Log a pinhole camera (RealSense/OpenCV axes: x right, y down, z forward = RDF).

    Parameters
    ----------
    entity : str
        Where the pinhole goes, e.g. ``world/camera_0/depth``; log the depth image there too.
    K : array_like, shape (3, 3)
        Intrinsics [px] (fx, fy, cx, cy; pixel-centre convention).
    width, height : int
        Image size [px].
    T_parent_cam : array_like, shape (4, 4), optional
        Pose of the camera in the parent entity's frame (p_parent = R p_cam + t, t [m]); when given
        it is logged at ``entity`` as a Transform3D (applied before the pinhole).
    static : bool
        Calibration is static by default.
    image_plane_distance : float, optional
        Size of the drawn frustum [m].
    """
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be a finite 3x3 camera matrix with fx, fy > 0, got {K!r}")
    if T_parent_cam is not None:
        log_transform(rec, entity, T_parent_cam, static=static)
    rec.log(entity, rr.Pinhole(image_from_camera=K, resolution=[int(width), int(height)],
                               camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=image_plane_distance),
            static=static)


def log_depth(rec: rr.RecordingStream, entity: str, depth, meter: float | None = None,
              depth_range: tuple[float, float] | None = None, static: bool = False) -> None:
    """Log a depth image under a pinhole.

    Parameters
    ----------
    depth : array_like, shape (H, W)
        uint16 depth units (0 = no data; give ``meter``) or float metres (NaN/inf/<= 0 = no data).
    meter : float, optional
        Depth units per metre, e.g. 1000 for a D435 at its default 1 mm scale (= 1 / depth_scale).
        Ignored (1.0) for float metres.
    depth_range : (float, float), optional
        Colour-map range in depth units of the logged image.
    static : bool
        Log as static data.
    """
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ValueError(f"depth must be a 2-D image (H, W), got shape {d.shape}")
    if np.issubdtype(d.dtype, np.integer):
        if meter is None:
            raise ValueError("integer depth needs meter= (depth units per metre, 1000 for 1 mm units)")
        img = d
    elif np.issubdtype(d.dtype, np.floating):
        img = np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
        meter = 1.0
    else:
        raise ValueError(f"depth must be integer units or float metres, got dtype {d.dtype}")
    rec.log(entity, rr.DepthImage(img, meter=float(meter), depth_range=depth_range), static=static)


def log_points(rec: rr.RecordingStream, entity: str, points, colors=None, radii=None,
               static: bool = False) -> None:
    """Log 3-D points.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points [m] in the frame of ``entity``; rows with non-finite values are dropped.
    colors : array_like, shape (N, 3) or (N, 4) uint8, or (3,)/(4,), optional
    radii : float or array_like, shape (N,), optional
        Point radii [m].
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {p.shape}")
    keep = np.isfinite(p).all(axis=1)
    c = None
    if colors is not None:
        c = np.asarray(colors)
        if c.ndim == 2:
            if c.shape[0] != len(p):
                raise ValueError(f"colors must have one row per point ({len(p)}), got {c.shape}")
            c = c[keep]
    r = None
    if radii is not None:
        r = np.asarray(radii, dtype=np.float32)
        if r.ndim == 1:
            if r.shape[0] != len(p):
                raise ValueError(f"radii must have one value per point ({len(p)}), got {r.shape}")
            r = r[keep]
    rec.log(entity, rr.Points3D(p[keep].astype(np.float32), colors=c, radii=r), static=static)


def ellipsoid_parameters(covs, n_sigma: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Half sizes and orientations of the n-sigma ellipsoids of 3x3 covariances.

    Parameters
    ----------
    covs : array_like, shape (N, 3, 3)
        Symmetric positive semi-definite covariances [m^2].
    n_sigma : float
        Scale: half sizes are n_sigma standard deviations along the principal axes.

    Returns
    -------
    half_sizes : ndarray, shape (N, 3) [m]
        n_sigma sqrt(eigenvalues) (negative round-off eigenvalues clipped to 0).
    quaternions_xyzw : ndarray, shape (N, 4)
        Rotations whose columns are the eigenvectors (made proper rotations, det = +1), so
        cov = R diag((half_sizes / n_sigma)^2) R^T.
    """
    C = np.asarray(covs, dtype=np.float64)
    if C.ndim != 3 or C.shape[1:] != (3, 3):
        raise ValueError(f"covs must have shape (N, 3, 3), got {C.shape}")
    if not np.all(np.isfinite(C)):
        raise ValueError("covs has non-finite entries")
    if len(C) == 0:
        return np.zeros((0, 3)), np.zeros((0, 4))
    ev, evec = np.linalg.eigh(0.5 * (C + np.swapaxes(C, 1, 2)))
    evec = evec.copy()
    evec[np.linalg.det(evec) < 0, :, 0] *= -1.0
    half = float(n_sigma) * np.sqrt(np.clip(ev, 0.0, None))
    return half, Rotation.from_matrix(evec).as_quat()


def log_covariance_ellipsoids(rec: rr.RecordingStream, entity: str, centers, covs, n_sigma: float = 2.0,
                              colors=None, fill_mode: str = "solid", static: bool = False) -> None:
    """Log the n-sigma ellipsoids of per-point covariances.

    Parameters
    ----------
    centers : array_like, shape (N, 3)
        Ellipsoid centres [m] in the frame of ``entity``.
    covs : array_like, shape (N, 3, 3)
        Covariances [m^2] expressed in the same frame.
    n_sigma : float
        Half sizes are ``n_sigma`` standard deviations (2: about 74 % of a 3-D Gaussian's mass).
    colors : array_like, shape (N, 3) uint8 or (3,), optional
    fill_mode : {"solid", "major_wireframe", "dense_wireframe"}
    """
    c = np.asarray(centers, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"centers must have shape (N, 3), got {c.shape}")
    if np.asarray(covs).shape[:1] != (len(c),):
        raise ValueError(f"covs must have shape ({len(c)}, 3, 3), got {np.asarray(covs).shape}")
    half, q = ellipsoid_parameters(covs, n_sigma)
    rec.log(entity, rr.Ellipsoids3D(centers=c.astype(np.float32), half_sizes=half.astype(np.float32),
                                    quaternions=q.astype(np.float32), colors=colors, fill_mode=fill_mode),
            static=static)


# ---------------------------------------------------------------------------------------------
# Scalars, time and text
# ---------------------------------------------------------------------------------------------
def set_time(rec: rr.RecordingStream, timeline: str, *, sequence: int | None = None,
             seconds: float | None = None, timestamp_ns: int | None = None) -> None:
    """Set the current time of ``timeline``: a frame index, a duration [s] or a timestamp [ns]."""
    given = [x is not None for x in (sequence, seconds, timestamp_ns)]
    if sum(given) != 1:
        raise ValueError("give exactly one of sequence, seconds, timestamp_ns")
    if sequence is not None:
        rec.set_time(timeline, sequence=int(sequence))
    elif seconds is not None:
        rec.set_time(timeline, duration=float(seconds))
    else:
        rec.set_time(timeline, timestamp=np.datetime64(int(timestamp_ns), "ns"))


def log_scalar(rec: rr.RecordingStream, entity: str, value) -> None:
    """Log one scalar (or a few, one per series) at the current time, for a time-series plot."""
    rec.log(entity, rr.Scalars(np.atleast_1d(np.asarray(value, dtype=np.float64))))


def log_text(rec: rr.RecordingStream, entity: str, markdown: str, static: bool = True) -> None:
    """Log a Markdown note (shown by a text-document view)."""
    rec.log(entity, rr.TextDocument(markdown, media_type=rr.MediaType.MARKDOWN), static=static)


# ---------------------------------------------------------------------------------------------
# Colours
# ---------------------------------------------------------------------------------------------
# 17 samples of each map at 0, 16, ..., 255 (taken from OpenCV's COLORMAP_TURBO / COLORMAP_VIRIDIS).
_CMAP_X = np.array([0, 16, 32, 48, 64, 80, 96, 112, 128, 143, 159, 175, 191, 207, 223, 239, 255]) / 255.0
_CMAPS = {
    "turbo": np.array([[48, 18, 59], [64, 64, 162], [70, 107, 227], [66, 148, 255], [40, 188, 235],
                       [24, 221, 194], [50, 242, 152], [109, 254, 98], [164, 252, 60], [203, 237, 52],
                       [236, 209, 58], [253, 174, 53], [251, 129, 34], [236, 83, 15], [210, 49, 5],
                       [172, 23, 1], [122, 4, 3]], dtype=np.float64),
    "viridis": np.array([[68, 1, 84], [72, 24, 106], [71, 45, 123], [66, 64, 134], [59, 82, 139],
                         [51, 99, 141], [44, 114, 142], [38, 130, 142], [33, 145, 140], [31, 159, 136],
                         [39, 173, 129], [61, 188, 116], [92, 200, 99], [129, 211, 77], [170, 220, 50],
                         [213, 226, 26], [253, 231, 37]], dtype=np.float64),
}


def colormap(values, vmin: float, vmax: float, name: str = "turbo", log: bool = False,
             nan_color=(128, 128, 128)) -> np.ndarray:
    """Map values to RGB colours (piecewise-linear turbo or viridis; no matplotlib).

    Parameters
    ----------
    values : array_like, any shape
    vmin, vmax : float
        Values at the two ends of the map; values outside are clipped. With ``log=True`` both
        must be > 0 and the map is linear in log10(value).
    name : {"turbo", "viridis"}
    nan_color : (3,) uint8
        Colour of non-finite values (and of values <= 0 with ``log=True``).

    Returns
    -------
    ndarray, shape values.shape + (3,), uint8
    """
    if name not in _CMAPS:
        raise ValueError(f"unknown colormap {name!r}; use one of {sorted(_CMAPS)}")
    v = np.asarray(values, dtype=np.float64)
    lo, hi = float(vmin), float(vmax)
    if log:
        if lo <= 0 or hi <= 0:
            raise ValueError("log colormap needs vmin, vmax > 0")
        with np.errstate(divide="ignore", invalid="ignore"):
            v = np.where(v > 0, np.log10(v), np.nan)
        lo, hi = math.log10(lo), math.log10(hi)
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise ValueError(f"need finite vmin < vmax, got {vmin}, {vmax}")
    ok = np.isfinite(v)
    t = np.clip((np.where(ok, v, lo) - lo) / (hi - lo), 0.0, 1.0)
    table = _CMAPS[name]
    rgb = np.stack([np.interp(t, _CMAP_X, table[:, k]) for k in range(3)], axis=-1)
    rgb[~ok] = np.asarray(nan_color, dtype=np.float64)
    return np.round(rgb).astype(np.uint8)


# ---------------------------------------------------------------------------------------------
# Static 2-D charts
# ---------------------------------------------------------------------------------------------
#: Size (width, height) of the chart canvas of :func:`log_series_plot`, in canvas units (y down).
PLOT_CANVAS = (1000.0, 600.0)
#: Visual bounds (x_range, y_range) of a 2-D view showing a whole chart with its labels.
PLOT_VISUAL_BOUNDS = ((-125.0, 1190.0), (-95.0, 720.0))

#: Default curve colours (RGB uint8), cycled.
SERIES_COLORS = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                           [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]],
                          dtype=np.uint8)


def _nice_ticks(lo: float, hi: float, n: int = 6) -> np.ndarray:
    span = hi - lo
    raw = span / max(n, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=10 * mag)
    first = math.ceil(lo / step - 1e-9) * step
    return np.arange(first, hi + 1e-9 * span, step)


def _fmt_tick(v: float) -> str:
    if v == 0:
        return "0"
    if abs(v) >= 1e6 or abs(v) < 1e-3:
        return f"{v:.0e}"
    return f"{v:g}"


def log_series_plot(rec: rr.RecordingStream, entity: str, xs, ys, *, names: Sequence[str] | None = None,
                    colors=None, x_label: str = "", y_label: str = "", title: str = "",
                    x_range: tuple[float, float] | None = None, y_range: tuple[float, float] | None = None,
                    log_y: bool = False, dashed: Sequence[bool] | None = None, static: bool = True) -> None:
    """Draw static curves as a 2-D chart (axes, ticks, labels, legend) with ``LineStrips2D``.

    Points outside the axis ranges are not drawn (the curve is cut there).

    The chart is drawn on a canvas of :data:`PLOT_CANVAS` units (y down, as in 2-D views) and is
    visible whatever the selected timeline; show it in a ``Spatial2DView`` with
    :data:`PLOT_VISUAL_BOUNDS` (:func:`default_blueprint` does so for ``plot_entities``).
    Sub-entities: ``<entity>/frame`` (axes and ticks), ``<entity>/tick_labels``, ``<entity>/curves``,
    ``<entity>/legend``.

    Parameters
    ----------
    xs : array_like, shape (M,), or a sequence of C arrays
        Abscissae, shared by all curves or one array per curve.
    ys : array_like, shape (C, M) or (M,), or a sequence of C arrays
        Ordinates; non-finite values (and values <= 0 with ``log_y``) break a curve.
    names : sequence of C str, optional
        Legend entries.
    colors : array_like, shape (C, 3) uint8, optional
    x_range, y_range : (float, float), optional
        Axis limits; the data's extent by default. With ``log_y`` the y limits must be > 0.
    log_y : bool
        Logarithmic y axis (decade ticks).
    dashed : sequence of C bool, optional
        Draw these curves dashed.
    """
    y_list = [np.asarray(y, dtype=np.float64).ravel() for y in (ys if _is_ragged(ys) else np.atleast_2d(ys))]
    C = len(y_list)
    if _is_ragged(xs) or (np.ndim(xs) == 2):
        x_list = [np.asarray(x, dtype=np.float64).ravel() for x in xs]
    else:
        x_list = [np.asarray(xs, dtype=np.float64).ravel()] * C
    if len(x_list) != C or any(len(x) != len(y) for x, y in zip(x_list, y_list)):
        raise ValueError("xs and ys must give one abscissa per ordinate for every curve")
    names = [f"series {k}" for k in range(C)] if names is None else [str(n) for n in names]
    if len(names) != C:
        raise ValueError(f"{len(names)} names for {C} curves")
    cols = SERIES_COLORS[np.arange(C) % len(SERIES_COLORS)] if colors is None else np.asarray(colors, np.uint8)
    dashed = [False] * C if dashed is None else [bool(d) for d in dashed]

    def fy(y):
        if not log_y:
            return y
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(y > 0, np.log10(y), np.nan)

    all_x = np.concatenate(x_list)
    all_y = np.concatenate([fy(y) for y in y_list])
    xlo, xhi = x_range if x_range is not None else (np.nanmin(all_x), np.nanmax(all_x))
    if y_range is not None:
        ylo, yhi = fy(np.asarray(y_range, dtype=np.float64))
    else:
        ylo, yhi = np.nanmin(all_y), np.nanmax(all_y)
        if log_y:
            ylo, yhi = math.floor(ylo), math.ceil(yhi)
    if not (np.isfinite([xlo, xhi, ylo, yhi]).all() and xhi > xlo and yhi > ylo):
        raise ValueError("cannot derive finite axis ranges from the data; give x_range / y_range")
    Wc, Hc = PLOT_CANVAS

    def to_canvas(x, y):
        return np.stack([(x - xlo) / (xhi - xlo) * Wc, Hc - (y - ylo) / (yhi - ylo) * Hc], axis=-1)

    # axes, grid and ticks
    frame = [np.array([[0, 0], [Wc, 0], [Wc, Hc], [0, Hc], [0, 0]], dtype=np.float64)]
    grid = []
    labels_pos, labels_txt = [], []
    for xt in _nice_ticks(xlo, xhi):
        cx = (xt - xlo) / (xhi - xlo) * Wc
        frame.append(np.array([[cx, Hc], [cx, Hc + 10]]))
        grid.append(np.array([[cx, 0], [cx, Hc]]))
        labels_pos.append([cx, Hc + 14])
        labels_txt.append(_fmt_tick(xt))
    if log_y:
        yt_list = np.arange(math.ceil(ylo - 1e-9), math.floor(yhi + 1e-9) + 1)
        ytxt = [_fmt_tick(10.0 ** k) for k in yt_list]
    else:
        yt_list = _nice_ticks(ylo, yhi)
        ytxt = [_fmt_tick(v) for v in yt_list]
    for yt, txt in zip(yt_list, ytxt):
        cy = Hc - (yt - ylo) / (yhi - ylo) * Hc
        frame.append(np.array([[-10, cy], [0, cy]]))
        grid.append(np.array([[0, cy], [Wc, cy]]))
        labels_pos.append([-60, cy])
        labels_txt.append(txt)
    rec.log(f"{entity}/frame", rr.LineStrips2D(frame, colors=[200, 200, 200], radii=1.0, draw_order=1.0),
            static=static)
    rec.log(f"{entity}/grid", rr.LineStrips2D(grid, colors=[90, 90, 90], radii=0.5, draw_order=0.5),
            static=static)
    labels_pos += [[Wc / 2, Hc + 50], [60, -25], [Wc / 2, -68]]
    labels_txt += [x_label, y_label, title]
    rec.log(f"{entity}/tick_labels", rr.Points2D(np.asarray(labels_pos, dtype=np.float32), labels=labels_txt,
                                                 radii=0.1, colors=[220, 220, 220], show_labels=True),
            static=static)

    # curves, clipped to the axes; breaks at non-finite values
    strips, strip_cols, legend_pos = [], [], []
    for k, (x, y) in enumerate(zip(x_list, y_list)):
        yy = fy(y)
        ok = np.isfinite(x) & np.isfinite(yy) & (x >= xlo) & (x <= xhi) & (yy >= ylo) & (yy <= yhi)
        pts = to_canvas(x, yy)
        runs = np.split(np.arange(len(x)), np.flatnonzero(np.diff(ok.astype(np.int8)) != 0) + 1)
        last = None
        for run in runs:
            if len(run) < 2 or not ok[run[0]]:
                continue
            seg = pts[run]
            if dashed[k]:
                seg_list = _dash(seg, 14.0)
            else:
                seg_list = [seg]
            strips += seg_list
            strip_cols += [cols[k]] * len(seg_list)
            last = seg[-1]
        legend_pos.append(last if last is not None else [Wc, 0])
    if strips:
        rec.log(f"{entity}/curves", rr.LineStrips2D(strips, colors=np.asarray(strip_cols), radii=2.0,
                                                    draw_order=2.0), static=static)
    legend_pos = np.asarray(legend_pos, dtype=np.float64) + [8.0, 0.0]
    legend_pos[:, 1] = _spread(legend_pos[:, 1], min_gap=min(70.0, Hc / max(C, 1)), lo=0.0, hi=Hc)
    rec.log(f"{entity}/legend", rr.Points2D(legend_pos.astype(np.float32), labels=names, colors=cols,
                                            radii=4.0, show_labels=True, draw_order=3.0), static=static)


def _spread(y: np.ndarray, min_gap: float, lo: float, hi: float) -> np.ndarray:
    """Move label heights ``y`` apart by at least ``min_gap`` (order kept), staying within [lo, hi]."""
    order = np.argsort(y, kind="stable")
    ys = y[order].astype(np.float64).copy()
    for k in range(1, len(ys)):
        ys[k] = max(ys[k], ys[k - 1] + min_gap)
    overflow = ys[-1] - hi if len(ys) else 0.0
    if overflow > 0:
        ys[-1] -= overflow
        for k in range(len(ys) - 2, -1, -1):
            ys[k] = min(ys[k], ys[k + 1] - min_gap)
    ys = np.maximum(ys, lo)
    out = np.empty_like(ys)
    out[order] = ys
    return out


def _is_ragged(a) -> bool:
    return isinstance(a, (list, tuple)) and len(a) > 0 and np.ndim(a[0]) == 1


def _dash(seg: np.ndarray, dash: float) -> list:
    """Cut a polyline into dashes of length ``dash`` separated by gaps of the same length."""
    d = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(seg, axis=0), axis=1))])
    out = []
    s = 0.0
    while s < d[-1]:
        e = min(s + dash, d[-1])
        t = np.concatenate([[s], d[(d > s) & (d < e)], [e]])
        out.append(np.stack([np.interp(t, d, seg[:, 0]), np.interp(t, d, seg[:, 1])], axis=1))
        s += 2 * dash
    return out


# ---------------------------------------------------------------------------------------------
# Layout
# ---------------------------------------------------------------------------------------------
def default_blueprint(depth_entities: Sequence[str] = (), plot_entities: Sequence[str] = (),
                      time_series_entities: Sequence[str] = (), text_entities: Sequence[str] = (),
                      world: str = "world", timeline: str | None = None, hidden_entities: Sequence[str] = (),
                      eye_position=None, eye_look_target=None) -> rrb.Blueprint:
    """The default viewer layout: 3-D ``world`` on the left, depth images and plots on the right.

    Parameters
    ----------
    depth_entities : sequence of str
        Pinhole entities holding depth images (``world/camera_<i>/depth``), one 2-D view each.
    plot_entities : sequence of str
        Charts drawn by :func:`log_series_plot`, one 2-D view each, framed by PLOT_VISUAL_BOUNDS.
    time_series_entities : sequence of str
        Subtrees of ``Scalars`` (from :func:`log_scalar`), one time-series view each.
    text_entities : sequence of str
        Markdown notes (from :func:`log_text`), shown under the 3-D view.
    world : str
        Root of the 3-D view.
    timeline : str, optional
        Timeline selected in the time panel.
    hidden_entities : sequence of str
        Entities of the 3-D view hidden at start (full paths; the user can switch them on).
    eye_position, eye_look_target : array_like, shape (3,), optional
        Initial 3-D eye position and the point it looks at, in the ``world`` frame [m].
    """
    eye = None
    if eye_position is not None and eye_look_target is not None:
        eye = rrb.EyeControls3D(position=np.asarray(eye_position, dtype=np.float64),
                                look_target=np.asarray(eye_look_target, dtype=np.float64), eye_up=[0.0, 0.0, 1.0])
    overrides = {e: rrb.EntityBehavior(visible=False) for e in hidden_entities}
    left = [rrb.Spatial3DView(origin=world, name=world, eye_controls=eye, overrides=overrides or None)]
    left += [rrb.TextDocumentView(origin=e, name=e.rsplit("/", 1)[-1]) for e in text_entities]
    left_c = rrb.Vertical(*left, row_shares=[3] + [1] * (len(left) - 1)) if len(left) > 1 else left[0]
    right = []
    if depth_entities:
        views = [rrb.Spatial2DView(origin=e, name=e.strip("/").split("/")[-2] if "/" in e.strip("/") else e)
                 for e in depth_entities]
        right.append(rrb.Grid(*views, grid_columns=2 if len(views) > 1 else 1))
    (xb, yb) = PLOT_VISUAL_BOUNDS
    for e in plot_entities:
        right.append(rrb.Spatial2DView(origin=e, name=e.rsplit("/", 1)[-1],
                                       visual_bounds=rrb.VisualBounds2D(x_range=xb, y_range=yb)))
    right += [rrb.TimeSeriesView(origin=e, name=e.rsplit("/", 1)[-1]) for e in time_series_entities]
    parts = [rrb.Horizontal(left_c, rrb.Vertical(*right), column_shares=[3, 2]) if right else left_c]
    parts.append(rrb.TimePanel(state="collapsed", timeline=timeline))
    return rrb.Blueprint(*parts, collapse_panels=False)


# ---------------------------------------------------------------------------------------------
# Mapping views
# ---------------------------------------------------------------------------------------------
def log_height_mesh(rec: rr.RecordingStream, entity: str, x_centres, y_centres, height, colors,
                    static: bool = False) -> int:
    """Log a height field as a triangle mesh over its known cells.

    Parameters
    ----------
    x_centres, y_centres : array_like, shape (n,), (m,)
        Cell-centre coordinates of rows and columns [m], map frame.
    height : array_like, shape (n, m)
        Height per cell [m]; NaN cells are left out (a quad needs its four corners known).
    colors : array_like, shape (n, m, 3), uint8
        Colour per cell.

    Returns
    -------
    int
        Number of triangles logged.
    """
    h = np.asarray(height, dtype=np.float64)
    xs, ys = np.asarray(x_centres, dtype=np.float64), np.asarray(y_centres, dtype=np.float64)
    if h.shape != (len(xs), len(ys)):
        raise ValueError(f"height must have shape ({len(xs)}, {len(ys)}), got {h.shape}")
    c = np.asarray(colors, dtype=np.uint8).reshape(h.size, -1)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    known = np.isfinite(h)
    quad = known[:-1, :-1] & known[1:, :-1] & known[:-1, 1:] & known[1:, 1:]
    if not quad.any():
        rec.log(entity, rr.Clear(recursive=False), static=static)
        return 0
    n, m = h.shape
    idx = np.arange(n * m).reshape(n, m)
    a, b, cc, d = idx[:-1, :-1][quad], idx[1:, :-1][quad], idx[:-1, 1:][quad], idx[1:, 1:][quad]
    tris = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, cc], 1)])
    used, inverse = np.unique(tris, return_inverse=True)
    verts = np.column_stack([X.ravel()[used], Y.ravel()[used], np.nan_to_num(h.ravel()[used])]).astype(np.float32)
    rec.log(entity, rr.Mesh3D(vertex_positions=verts, triangle_indices=inverse.reshape(-1, 3).astype(np.uint32),
                              vertex_colors=c[used]), static=static)
    return int(len(tris))


def log_trail(rec: rr.RecordingStream, entity: str, positions, color=(255, 200, 0), radius: float = 0.01) -> None:
    """The path travelled so far as one line strip; positions (K, 3) [m], map frame."""
    p = np.asarray(positions, dtype=np.float32)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"positions must have shape (K, 3), got {p.shape}")
    rec.log(entity, rr.LineStrips3D([p], colors=[color], radii=[radius]))


def log_exact(rec: rr.RecordingStream, entity: str, static: bool = False, **arrays) -> None:
    """Log float64 arrays losslessly as ``AnyValues`` (rerun's transforms and pinholes are float32).

    The project's own recordings keep each frame's K, pose, pose covariance, stamp and depth scale
    here, so that a replay reproduces the mapped frames bit for bit.
    """
    values = {k: np.atleast_1d(np.asarray(v, dtype=np.float64)).ravel() for k, v in arrays.items() if v is not None}
    rec.log(entity, rr.AnyValues(**values), static=static)


def log_depth_png(rec: rr.RecordingStream, entity: str, depth_u16, meter: float, static: bool = False) -> None:
    """Log uint16 depth losslessly PNG-compressed (``EncodedDepthImage``); about half the size of raw
    noisy depth and a tenth of smooth depth. ``meter``: depth units per metre (1000 for 1 mm)."""
    import cv2

    d = np.asarray(depth_u16)
    if d.dtype != np.uint16 or d.ndim != 2:
        raise ValueError(f"depth must be a 2-D uint16 image, got {d.dtype} {d.shape}")
    ok, png = cv2.imencode(".png", d)
    if not ok:
        raise ValueError("PNG encoding of the depth image failed")
    rec.log(entity, rr.EncodedDepthImage(blob=png.tobytes(), media_type="image/png", meter=float(meter)),
            static=static)


# ---------------------------------------------------------------------------------------------
# Comparisons (elevmap compare)
# ---------------------------------------------------------------------------------------------
def log_rgb_image(rec: rr.RecordingStream, entity: str, rgb, static: bool = False) -> None:
    """Log an RGB image (H, W, 3) uint8, e.g. a map layer coloured with :func:`colormap`."""
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
        raise ValueError(f"rgb must be an (H, W, 3) uint8 image, got {a.dtype} {a.shape}")
    rec.log(entity, rr.Image(np.ascontiguousarray(a), color_model="RGB"), static=static)


def map_image(layer) -> np.ndarray:
    """A map layer in map-index order (i along +x, j along +y) as an image seen from above with +x up
    and +y to the left: ``layer[::-1, ::-1]`` (row 0 = largest x, column 0 = largest y)."""
    a = np.asarray(layer)
    if a.ndim < 2:
        raise ValueError(f"layer must be at least 2-D, got shape {a.shape}")
    return a[::-1, ::-1]


def compare_blueprint(map_views: Sequence[str], image_grids: Sequence[tuple[str, Sequence[str]]] = (),
                      time_series_entities: Sequence[str] = (), text_entities: Sequence[str] = (),
                      depth_entities: Sequence[str] = (), timeline: str | None = None,
                      hidden_entities: Sequence[str] = (), eye_position=None, eye_look_target=None) -> rrb.Blueprint:
    """Layout of a comparison: one 3-D view per map side by side, image grids in tabs, notes and plots.

    Parameters
    ----------
    map_views : sequence of str
        Roots of the 3-D views (one per mapper, e.g. ``maps/paper``), in a grid; each is z-up.
    image_grids : sequence of (str, sequence of str)
        Tabs of 2-D views: a tab name and the image entities shown in a grid in that tab.
    time_series_entities : sequence of str
        Subtrees of scalars (:func:`log_scalar`), one time-series view each.
    text_entities : sequence of str
        Markdown notes (:func:`log_text`).
    depth_entities : sequence of str
        Pinhole entities with depth images, one 2-D view each.
    timeline : str, optional
        Timeline selected in the time panel.
    hidden_entities : sequence of str
        Entities hidden at start in the 3-D views.
    eye_position, eye_look_target : array_like, shape (3,), optional
        The same initial eye for every 3-D view [m].
    """
    eye = None
    if eye_position is not None and eye_look_target is not None:
        eye = rrb.EyeControls3D(position=np.asarray(eye_position, dtype=np.float64),
                                look_target=np.asarray(eye_look_target, dtype=np.float64), eye_up=[0.0, 0.0, 1.0])
    views3d = []
    for origin in map_views:
        hidden = {e: rrb.EntityBehavior(visible=False) for e in hidden_entities if e.startswith(origin + "/")}
        views3d.append(rrb.Spatial3DView(origin=origin, name=origin.rsplit("/", 1)[-1], eye_controls=eye,
                                         overrides=hidden or None))
    cols = 3 if len(views3d) > 4 else 2
    tabs = [rrb.Grid(*views3d, grid_columns=cols, name="maps")] if views3d else []
    for name, entities in image_grids:
        views = [rrb.Spatial2DView(origin=e, name=e.rsplit("/", 1)[-1]) for e in entities]
        if views:
            tabs.append(rrb.Grid(*views, grid_columns=3 if len(views) > 4 else 2, name=name))
    left = rrb.Tabs(*tabs, active_tab=0) if len(tabs) > 1 else tabs[0]
    right = [rrb.TextDocumentView(origin=e, name=e.rsplit("/", 1)[-1]) for e in text_entities]
    right += [rrb.Spatial2DView(origin=e, name=e.strip("/").split("/")[-2] if "/" in e.strip("/") else e)
              for e in depth_entities]
    right += [rrb.TimeSeriesView(origin=e, name=e.rsplit("/", 1)[-1]) for e in time_series_entities]
    parts = [rrb.Horizontal(left, rrb.Vertical(*right), column_shares=[3, 2]) if right else left]
    parts.append(rrb.TimePanel(state="collapsed", timeline=timeline))
    return rrb.Blueprint(*parts, collapse_panels=False)


def robust_range(values) -> tuple[float, float]:
    """(2nd, 98th) percentile of the finite values, for colour scales; (0, 1) when there are none."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if not v.size:
        return 0.0, 1.0
    lo, hi = np.percentile(v, [2, 98])
    return float(lo), float(max(hi, lo + 1e-3))


# --- characterisation (issue 6)
# The figures of `elevmap characterize` (Ahn et al. 2019: Fig. 2, 3, 4 and the lateral noise) as 2-D
# charts, the per-capture distance-to-plane images on a ``capture`` timeline, and a summary note.
def log_characterisation(rec: rr.RecordingStream, series: dict, plane_images: Sequence[tuple[str, np.ndarray]],
                         summary_markdown: str, send_blueprint: bool = True) -> None:
    """Log the characterisation figures.

    Parameters
    ----------
    series : dict
        ``elevmap.commands.characterize.figure_series(report)``: ``fig2`` (distances [m], RMS error of the mean of the
        frames, single-frame residual and eq. (1) [m]), ``fig3`` (per angle [deg]: points (z [m], variance
        [m^2]), fitted and paper curves over ``curve_z_m``), ``lateral`` (per side: distances [m] and lateral
        noise [m]; sigma_L, sigma_R and the paper's [m]).
    plane_images : sequence of (str, ndarray (H, W)) or (str, ndarray (H, W), float)
        Per capture, the distance of each pixel to the fitted plane [m] (NaN off the target), and optionally
        the colour range [m]; one image per step of the ``capture`` timeline at
        ``characterize/plane_distance``, coloured blue (in front of the plane) to red (behind it) over
        +-the range (default: the 98th percentile of |distance|).
    summary_markdown : str
        The note shown beside the charts (``characterize/summary``).

    Entities: ``characterize/fig2_systematic_error``, ``characterize/fig3_axial_variance``,
    ``characterize/lateral_noise`` (charts, in mm and mm^2), ``characterize/plane_distance`` (image),
    ``characterize/summary`` (text).
    """
    f2, f3, lat = series["fig2"], series["fig3"], series["lateral"]
    plots = []
    if f2["distance_m"]:
        d = np.asarray(f2["distance_m"], dtype=np.float64)

        def mm(v):
            return 1000.0 * np.array([np.nan if x is None else x for x in v], dtype=np.float64)

        e = "characterize/fig2_systematic_error"
        log_series_plot(rec, e, d, [mm(f2["rms_error_m"]), mm(f2["residual_m"]), mm(f2["eq1_m"])],
                        names=["RMS error of the frames' mean", "single-frame plane residual", "eq. (1)"],
                        x_label="distance [m]", y_label="error [mm]", dashed=[False, False, True],
                        title=f"Fig. 2: systematic error ({f2['kind']})")
        plots.append(e)
    if f3["angles_deg"]:
        xs, ys, names, colors, dashed = [], [], [], [], []
        zc = np.asarray(f3["curve_z_m"], dtype=np.float64)
        for k, a in enumerate(f3["angles_deg"]):
            col = SERIES_COLORS[k % len(SERIES_COLORS)]
            z, v = f3["points"][a]
            order = np.argsort(z)
            xs.append(np.asarray(z, dtype=np.float64)[order])
            ys.append(1e6 * np.asarray(v, dtype=np.float64)[order])
            names.append(f"{a} deg measured")
            colors.append(col)
            dashed.append(False)
            if a in f3["fitted"]:
                xs.append(zc)
                ys.append(1e6 * np.asarray(f3["fitted"][a], dtype=np.float64))
                names.append(f"{a} deg fit")
                colors.append(col)
                dashed.append(False)
            xs.append(zc)
            ys.append(1e6 * np.asarray(f3["paper"][a], dtype=np.float64))
            names.append(f"{a} deg paper")
            colors.append(col)
            dashed.append(True)
        e = "characterize/fig3_axial_variance"
        allv = np.concatenate([y[np.isfinite(y) & (y > 0)] for y in ys])
        lo, hi = (10.0 ** np.floor(np.log10(allv.min())), 10.0 ** np.ceil(np.log10(allv.max()))) if allv.size \
            else (1e-1, 1e1)
        log_series_plot(rec, e, xs, ys, names=names, colors=np.asarray(colors, dtype=np.uint8), dashed=dashed,
                        x_label="depth z [m]", y_label="sigma_z^2 [mm^2]", log_y=True, y_range=(lo, hi),
                        x_range=(float(zc.min()), float(zc.max())),
                        title="Fig. 3: axial variance (measured, fit, paper dashed)")
        plots.append(e)
    xs, ys, names, dashed = [], [], [], []
    for side, key, pkey in (("left", "sigma_L_m", "paper_sigma_L_m"), ("right", "sigma_R_m", "paper_sigma_R_m")):
        d, v = lat[side]
        if d:
            # median over the captures at each distance (angles differ), so the curve does not zigzag
            d_arr, v_arr = np.round(np.asarray(d, dtype=np.float64), 3), np.asarray(v, dtype=np.float64)
            du = np.unique(d_arr)
            xs.append(du)
            ys.append(1000.0 * np.array([np.median(v_arr[d_arr == x]) for x in du]))
            names.append(f"{side} edge (median per distance)")
            dashed.append(False)
        ends = np.array([0.3, 2.2])
        if lat[key] is not None:
            xs.append(ends)
            ys.append(np.full(2, 1000.0 * lat[key]))
            names.append(f"{key[:7]} {1000 * lat[key]:.1f} mm")
            dashed.append(False)
        xs.append(ends)
        ys.append(np.full(2, 1000.0 * lat[pkey]))
        names.append(f"paper {key[:7]}")
        dashed.append(True)
    if any("edge" in n for n in names):
        e = "characterize/lateral_noise"
        log_series_plot(rec, e, xs, ys, names=names, dashed=dashed, x_label="distance [m]",
                        y_label="lateral noise [mm]", title="Lateral noise of the board's edges")
        plots.append(e)
    img_entity = "characterize/plane_distance"
    for k, item in enumerate(plane_images):
        cid, img = item[0], item[1]
        a = np.asarray(img, dtype=np.float64)
        if a.ndim != 2:
            raise ValueError(f"plane image of {cid} must be 2-D, got shape {a.shape}")
        if len(item) > 2:
            e = float(item[2])
        else:
            v = np.abs(a[np.isfinite(a)])
            e = float(np.percentile(v, 98)) if v.size else 1e-3
        set_time(rec, "capture", sequence=k)
        log_rgb_image(rec, img_entity, colormap(a, -max(e, 1e-6), max(e, 1e-6), "turbo"))
        log_text(rec, "characterize/capture", f"`{cid}`: distance to the plane, +-{1000 * e:.1f} mm "
                                              "(blue in front, red behind)", static=False)
    log_text(rec, "characterize/summary", summary_markdown)
    if send_blueprint:
        rec.send_blueprint(characterisation_blueprint(plots, img_entity if plane_images else None))


def characterisation_blueprint(plot_entities: Sequence[str], image_entity: str | None = None) -> rrb.Blueprint:
    """Layout of a characterisation: the charts in tabs on the left; the distance-to-plane image (stepped
    along the ``capture`` timeline), the capture's note and the summary on the right."""
    (xb, yb) = PLOT_VISUAL_BOUNDS
    charts = [rrb.Spatial2DView(origin=e, name=e.rsplit("/", 1)[-1],
                                visual_bounds=rrb.VisualBounds2D(x_range=xb, y_range=yb)) for e in plot_entities]
    right = []
    if image_entity is not None:
        right.append(rrb.Spatial2DView(origin=image_entity, name="distance to the plane"))
        right.append(rrb.TextDocumentView(origin="characterize/capture", name="capture"))
    right.append(rrb.TextDocumentView(origin="characterize/summary", name="summary"))
    left = rrb.Tabs(*charts, active_tab=0) if len(charts) > 1 else (charts[0] if charts else None)
    parts = [rrb.Horizontal(left, rrb.Vertical(*right), column_shares=[3, 2]) if left is not None
             else rrb.Vertical(*right)]
    parts.append(rrb.TimePanel(state="collapsed", timeline="capture"))
    return rrb.Blueprint(*parts, collapse_panels=False)


# --- gap diagnosis (issue 7)
# `elevmap gap`: the gap per stratum as labelled bar charts (before / after the selected effects), the
# real and simulated residual and fill images of a capture side by side on a ``capture`` timeline, and
# the summary. Bars are thick 2-D lines on a canvas (rerun's BarChart has no category labels).
GAP_BAR_ROW = 28.0
GAP_BAR_WIDTH = 1000.0
GAP_SERIES_COLORS = np.array([[214, 39, 40], [44, 160, 44], [31, 119, 180]], dtype=np.uint8)


def gap_bar_bounds(n_rows: int) -> tuple[tuple[float, float], tuple[float, float]]:
    """Visual bounds (x_range, y_range) of a chart of :func:`log_gap_bars` with ``n_rows`` rows."""
    return (-520.0, GAP_BAR_WIDTH + 160.0), (-70.0, n_rows * GAP_BAR_ROW + 40.0)


def log_gap_bars(rec: rr.RecordingStream, entity: str, labels: Sequence[str], values, *,
                 series_names: Sequence[str] = ("before", "after"), title: str = "", static: bool = True) -> None:
    """Horizontal grouped bars with category labels, on a log(1 + gap) axis.

    Parameters
    ----------
    labels : sequence of N str
        One row per category (e.g. a statistic in a stratum), drawn top to bottom.
    values : array_like, shape (S, N)
        S series (e.g. the gap before and after the selected effects), >= 0; NaN draws nothing.
    series_names : sequence of S str
    title : str

    Sub-entities: ``<entity>/bars`` (thick LineStrips2D), ``<entity>/values``, ``<entity>/labels``, ``<entity>/axis``, ``<entity>/legend``.
    Show it in a Spatial2DView with :func:`gap_bar_bounds`.
    """
    v = np.atleast_2d(np.asarray(values, dtype=np.float64))
    labels = [str(s) for s in labels]
    S, N = v.shape
    if N != len(labels):
        raise ValueError(f"{len(labels)} labels for {N} values per series")
    if len(series_names) != S:
        raise ValueError(f"{len(series_names)} series names for {S} series")
    top = float(np.nanmax(v)) if np.isfinite(v).any() else 1.0
    decades = max(1, int(math.ceil(math.log10(1.0 + max(top, 1e-9)))))

    def x_of(g):
        return GAP_BAR_WIDTH * np.log10(1.0 + np.maximum(g, 0.0)) / decades

    h = GAP_BAR_ROW / (S + 1)
    centers, halves, colors, vals = [], [], [], []
    for s in range(S):
        for i in range(N):
            if not np.isfinite(v[s, i]):
                continue
            x = float(x_of(v[s, i]))
            y = i * GAP_BAR_ROW + (s + 0.5) * h + 0.5 * h
            centers.append([x / 2.0, y])
            halves.append([max(x / 2.0, 0.5), 0.45 * h])
            colors.append(GAP_SERIES_COLORS[s % len(GAP_SERIES_COLORS)])
            vals.append(f"{v[s, i]:.3g}")
    if centers:
        # a bar is a thick line from 0 to its value (Boxes2D are outlines only)
        strips = [np.array([[0.0, c[1]], [2.0 * c[0], c[1]]]) for c in centers]
        rec.log(f"{entity}/bars", rr.LineStrips2D(strips, colors=np.asarray(colors),
                                                  radii=np.asarray([hh[1] for hh in halves], dtype=np.float32),
                                                  draw_order=2.0), static=static)
        tips = np.asarray(centers, dtype=np.float32) * [2.0, 1.0] + [40.0, 0.0]
        rec.log(f"{entity}/values", rr.Points2D(tips, labels=vals, radii=0.1, colors=np.asarray(colors),
                                                show_labels=True, draw_order=3.0), static=static)
    rec.log(f"{entity}/labels", rr.Points2D(np.array([[-260.0, (i + 0.5) * GAP_BAR_ROW] for i in range(N)],
                                                     dtype=np.float32),
                                            labels=labels, radii=0.1, colors=[220, 220, 220], show_labels=True),
            static=static)
    ticks = [0.0] + [10.0 ** k for k in range(decades + 1)]
    axis = [np.array([[0.0, -8.0], [GAP_BAR_WIDTH, -8.0]])] + [np.array([[float(x_of(t)), -14.0], [float(x_of(t)), -8.0]])
                                                              for t in ticks]
    rec.log(f"{entity}/axis", rr.LineStrips2D(axis, colors=[200, 200, 200], radii=1.0), static=static)
    rec.log(f"{entity}/tick_labels", rr.Points2D(np.array([[float(x_of(t)), -30.0] for t in ticks] +
                                                          [[GAP_BAR_WIDTH / 2.0, -58.0]], dtype=np.float32),
                                                 labels=[_fmt_tick(t) for t in ticks] + [title], radii=0.1,
                                                 colors=[220, 220, 220], show_labels=True), static=static)
    leg = np.array([[GAP_BAR_WIDTH + 60.0, 20.0 + 30.0 * s] for s in range(S)], dtype=np.float32)
    rec.log(f"{entity}/legend", rr.Points2D(leg, labels=list(series_names), radii=6.0,
                                            colors=GAP_SERIES_COLORS[np.arange(S) % len(GAP_SERIES_COLORS)],
                                            show_labels=True), static=static)


def log_gap_images(rec: rr.RecordingStream, step: int, images: dict, note: str, *, residual_range_m: float,
                   timeline: str = "capture") -> None:
    """One capture's images at step ``step`` of ``timeline``.

    Parameters
    ----------
    images : dict
        ``residual/<model>`` -> (H, W) mean residual over the frames [m] (NaN: no data), coloured blue
        (nearer than the truth) to red (farther) over +-``residual_range_m``; ``fill/<model>`` -> (H, W)
        fraction of frames with data, coloured 0 (dark) to 1 (yellow). Logged at ``gap/<key>``.
    note : str
        Markdown logged at ``gap/capture``.
    """
    set_time(rec, timeline, sequence=int(step))
    e = max(float(residual_range_m), 1e-6)
    for key, img in images.items():
        a = np.asarray(img, dtype=np.float64)
        if a.ndim != 2:
            raise ValueError(f"image {key} must be 2-D, got shape {a.shape}")
        if key.startswith("residual/"):
            rgb = colormap(a, -e, e, "turbo")
        elif key.startswith("fill/"):
            rgb = colormap(a, 0.0, 1.0, "viridis")
        else:
            raise ValueError(f"image keys start with residual/ or fill/, got {key!r}")
        log_rgb_image(rec, f"gap/{key}", rgb)
    log_text(rec, "gap/capture", note, static=False)


def gap_blueprint(bar_charts: Sequence[tuple[str, int]], image_keys: Sequence[str],
                  text_entity: str = "gap/summary") -> rrb.Blueprint:
    """Layout of a gap diagnosis: the bar charts in tabs on the left; the residual and fill images (a grid,
    stepped along the ``capture`` timeline), the capture's note and the summary on the right.

    Parameters
    ----------
    bar_charts : sequence of (entity, n_rows)
    image_keys : sequence of str
        Keys of :func:`log_gap_images` (``residual/real`` ...), in grid order.
    """
    charts = []
    for e, n in bar_charts:
        xb, yb = gap_bar_bounds(n)
        charts.append(rrb.Spatial2DView(origin=e, name=e.rsplit("/", 1)[-1],
                                        visual_bounds=rrb.VisualBounds2D(x_range=xb, y_range=yb)))
    right = []
    if image_keys:
        right.append(rrb.Grid(*[rrb.Spatial2DView(origin=f"gap/{k}", name=k) for k in image_keys],
                              grid_columns=3 if len(image_keys) > 4 else 2))
        right.append(rrb.TextDocumentView(origin="gap/capture", name="capture"))
    right.append(rrb.TextDocumentView(origin=text_entity, name="summary"))
    left = rrb.Tabs(*charts, active_tab=0) if len(charts) > 1 else (charts[0] if charts else None)
    parts = [rrb.Horizontal(left, rrb.Vertical(*right, row_shares=[3, 1, 2][:len(right)]), column_shares=[1, 1])
             if left is not None else rrb.Vertical(*right)]
    parts.append(rrb.TimePanel(state="collapsed", timeline="capture"))
    return rrb.Blueprint(*parts, collapse_panels=False)
