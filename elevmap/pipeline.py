"""Source -> mapper -> map -> viewer: the loop behind ``elevmap run``, ``replay`` and ``demo``.

Frames come from any source (:mod:`elevmap.sources`); each is fused by a :class:`Mapper` into a
robot-centric :class:`ElevationMap`; when the frames carry the true terrain (the simulator), the map
is scored against it; with a recording path every frame goes to rerun through :mod:`elevmap.viz`
(imported only then), laid out so that :class:`elevmap.sources.rrd.RrdSource` replays it bit-exact, and the
views of the map (points, ellipsoids, trail, statistics, meshes) at ``MappingConfig.view_rate_hz`` per second
of the frames' stamps.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from noise_model.d435 import D435, SensorModel
from noise_model.valid_margin import DEFAULT_VALID_MARGIN_PX, check_valid_margin_px

from .map.elevation_map import BYTES_PER_CELL, ElevationMap
from .frame import Frame
from .map.fusion import FusionParams
from .map.settings import check_bool, check_coordinates, check_int, check_map_memory, check_real
from .mapper import Camera, Mapper

__all__ = ["MappingConfig", "run_mapping", "map_error", "edge_band"]


@dataclass(frozen=True)
class MappingConfig:
    """Settings of a mapping run.

    Attributes
    ----------
    length_m, resolution_m : float
        Map size and cell size [m].
    fusion : FusionParams
        Measurement update parameters.
    visibility_cleanup : bool
        Clear cells rays pass below.
    follow : bool
        Re-centre the map on the camera every frame (robot-centric).
    score_every : int
        Score against the truth every k frames (and at the last).
    log_every : int
        Log the frame (depth, pose, exact values: what a replay maps) every k frames.
    view_rate_hz : float
        The views of the map (points with their covariance ellipsoids, the trail, the map's statistics
        plots) are logged at most this many times per second of the source's time: the frames of a 30 or
        90 Hz camera each go to the recording, but redrawing 4000 points and the map for each would cost
        more than mapping them. One view per slot of ``1 / view_rate_hz`` s of frame stamps (the first
        frame of each slot), so the output depends on the stamps only, never on the machine's speed.
        What is mapped does not depend on it.
    mesh_every : int
        The map meshes every k logged views (and at the end).
    max_points, max_ellipsoids : int
        Sub-sampled points and covariance ellipsoids logged per view.
    png_depth : bool
        Log uint16 depth losslessly PNG-compressed: smaller files (a little on noisy depth, much on smooth
        depth), but zlib encoding on the mapping thread costs more per 848x480 frame than the mapper itself,
        while raw depth (the default) is one copy that rerun compresses with LZ4 on its own thread. Both
        replay bit-exact.
    sensor_model : str
        A sensor model file (``elevmap-sensor-model/1``, ``/2`` or ``/3`` with its per-frame error, as
        ``elevmap characterize`` writes it) for every camera of the run; "" = the paper's D435.
    valid_margin_px : int or None
        Every camera's valid-region margin [px] (:attr:`elevmap.mapper.Camera.valid_margin_px`): depth pixels
        within this many columns of a no-data pixel or of the image's left or right border are dropped,
        where a stereo matcher's window was cut short. 0 for depth that is not straight from a stereo
        matcher or is already filtered. None: the margin a recording of this project names for its camera
        (so that a replay maps exactly what was mapped; 0 for a recording that names none, made before the
        margin existed), else ``DEFAULT_VALID_MARGIN_PX``.
    """

    length_m: float = 8.0
    resolution_m: float = 0.04
    fusion: FusionParams = FusionParams()
    visibility_cleanup: bool = True
    follow: bool = True
    score_every: int = 1
    log_every: int = 1
    view_rate_hz: float = 10.0
    mesh_every: int = 20
    max_points: int = 4000
    max_ellipsoids: int = 300
    png_depth: bool = False
    sensor_model: str = ""
    valid_margin_px: int | None = None

    def __post_init__(self):
        """Types and ranges of every setting, before any work (a file's ``"false"`` or ``0`` included)."""
        check_real(self.resolution_m, "resolution_m", 0.0, lo_open=True, unit=" [m]")
        check_real(self.length_m, "length_m", self.resolution_m, unit=" [m]")
        if not isinstance(self.fusion, FusionParams):
            raise ValueError(f"fusion must be a FusionParams ([map.fusion] table), got {self.fusion!r}")
        for name in ("visibility_cleanup", "follow", "png_depth"):
            check_bool(getattr(self, name), name)
        for name in ("score_every", "log_every", "mesh_every", "max_points", "max_ellipsoids"):
            check_int(getattr(self, name), name, 1)
        check_real(self.view_rate_hz, "view_rate_hz", 0.0, lo_open=True, unit=" [Hz]")
        if not isinstance(self.sensor_model, str):
            raise ValueError(f"sensor_model must be a file path (a string), got {self.sensor_model!r}")
        if self.valid_margin_px is not None:
            object.__setattr__(self, "valid_margin_px", check_valid_margin_px(self.valid_margin_px, "valid_margin_px"))

    @classmethod
    def from_dict(cls, d: dict) -> "MappingConfig":
        """From a TOML/JSON table: ``[map]`` keys of this class plus a ``[map.fusion]`` sub-table."""
        known = {f for f in cls.__dataclass_fields__}
        bad = set(d) - known
        if bad:
            raise ValueError(f"unknown mapping setting(s) {sorted(bad)}; known: {sorted(known)}")
        d = dict(d)
        if "fusion" in d:
            f = d["fusion"]
            if not isinstance(f, dict):
                raise ValueError("[map.fusion] must be a table")
            fknown = set(FusionParams.__dataclass_fields__)
            if set(f) - fknown:
                raise ValueError(f"unknown fusion setting(s) {sorted(set(f) - fknown)}; known: {sorted(fknown)}")
            d["fusion"] = FusionParams(**f)
        config = cls(**d)
        n = int(round(config.length_m / config.resolution_m))
        check_map_memory(n, BYTES_PER_CELL, config.resolution_m)      # before any frame is read
        return config


#: A truth jump larger than this between neighbouring cell centres is a step edge [m].
EDGE_JUMP_M = 0.05
#: Cells within this many cells of a step edge form the edge band.
EDGE_BAND_CELLS = 2


def edge_band(truth) -> np.ndarray:
    """The cells within ``EDGE_BAND_CELLS`` (4-connected steps) of a step edge of the true terrain.

    Parameters
    ----------
    truth : ndarray, shape (H, W) [m]
        The true height at the cell centres.

    Returns
    -------
    ndarray of bool, shape (H, W)
        True where a cell or a cell up to ``EDGE_BAND_CELLS`` away has a 4-neighbour whose true height
        differs by more than ``EDGE_JUMP_M``.
    """
    truth = np.asarray(truth, dtype=np.float64)
    if truth.ndim != 2:
        raise ValueError(f"truth must be a 2-D grid of heights, got shape {truth.shape}")
    jump = np.zeros(truth.shape, dtype=bool)
    dx = np.abs(np.diff(truth, axis=0)) > EDGE_JUMP_M
    dy = np.abs(np.diff(truth, axis=1)) > EDGE_JUMP_M
    jump[:-1] |= dx
    jump[1:] |= dx
    jump[:, :-1] |= dy
    jump[:, 1:] |= dy
    band = jump.copy()
    for _ in range(EDGE_BAND_CELLS):
        grown = band.copy()
        grown[1:] |= band[:-1]
        grown[:-1] |= band[1:]
        grown[:, 1:] |= band[:, :-1]
        grown[:, :-1] |= band[:, 1:]
        band = grown
    return band


def map_error(emap: ElevationMap, truth_height) -> dict:
    """The map against the true terrain at the centres of its known cells.

    Cells within ``EDGE_BAND_CELLS`` of a step edge (a truth jump above ``EDGE_JUMP_M`` between
    neighbouring cell centres, :func:`edge_band`) are scored apart from flat cells: there a cell holds
    both levels while its centre has one, so their errors measure edge sharpness, not the noise model.

    Parameters
    ----------
    truth_height : callable
        xy (M, 2) [m] -> true height (M,) [m], map frame.

    Returns
    -------
    dict
        rmse_m, median_abs_m, p95_abs_m, mean_error_m (bias), coverage_1sigma, coverage_2sigma,
        nll (mean negative log-likelihood), known_cells; flat_rmse_m, flat_coverage_2sigma,
        edge_rmse_m, edge_mean_error_m, edge_coverage_1sigma, edge_coverage_2sigma, edge_nll,
        edge_cells (the known cells of the edge band).
    """
    h, v = emap.layer("elevation"), emap.layer("variance")
    known = emap.is_known()
    keys = ("rmse_m", "median_abs_m", "p95_abs_m", "mean_error_m", "coverage_1sigma", "coverage_2sigma", "nll",
            "flat_rmse_m", "flat_coverage_2sigma", "edge_rmse_m", "edge_mean_error_m", "edge_coverage_1sigma",
            "edge_coverage_2sigma", "edge_nll")
    if not known.any():
        return {**{k: math.nan for k in keys}, "known_cells": 0, "edge_cells": 0}
    xs, ys = emap.cell_centres()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    truth = np.asarray(truth_height(np.column_stack([X.ravel(), Y.ravel()])), dtype=np.float64).reshape(h.shape)
    band = edge_band(truth)
    err = (h - truth)[known]
    var = v[known]
    z = np.abs(err) / np.sqrt(var)
    nll = 0.5 * np.log(2 * np.pi * var) + 0.5 * err ** 2 / var
    edge = band[known]

    def rmse(mask):
        return float(np.sqrt(np.mean(err[mask] ** 2))) if mask.any() else math.nan

    def mean(a, mask):
        return float(np.mean(a[mask])) if mask.any() else math.nan

    return {"rmse_m": rmse(np.ones_like(edge)), "median_abs_m": float(np.median(np.abs(err))),
            "p95_abs_m": float(np.percentile(np.abs(err), 95)), "mean_error_m": float(np.mean(err)),
            "coverage_1sigma": float(np.mean(z <= 1.0)), "coverage_2sigma": float(np.mean(z <= 2.0)),
            "nll": float(np.mean(nll)),
            "flat_rmse_m": rmse(~edge), "flat_coverage_2sigma": mean(z <= 2.0, ~edge),
            "edge_rmse_m": rmse(edge), "edge_mean_error_m": mean(err, edge),
            "edge_coverage_1sigma": mean(z <= 1.0, edge), "edge_coverage_2sigma": mean(z <= 2.0, edge),
            "edge_nll": mean(nll, edge), "known_cells": int(known.sum()), "edge_cells": int(edge.sum())}


def run_mapping(frames, config: MappingConfig = MappingConfig(), *, rrd_path=None, spawn: bool = False,
                truth_height=None, show_progress: bool = True, total: int | None = None,
                application_id: str = "elevmap", nthreads: int | None = None, notes: str | None = None,
                callbacks=(), recorded_margins_px=None) -> dict:
    """Map a sequence of :class:`Frame` records; optionally record everything to rerun.

    Parameters
    ----------
    frames : iterable of Frame
        A source that replays a recording of this project (:class:`elevmap.sources.rrd.RrdSource`) also
        names the valid-region margin each camera was mapped with (its ``valid_margins_px``).
    config : MappingConfig
    rrd_path : path, optional
        Write a rerun recording there (atomically: nothing is left if the run fails).
    spawn : bool
        Also stream to a rerun viewer.
    truth_height : callable, optional
        xy (M, 2) -> true height (M,) [m]; else taken from each frame's ``truth["height"]``.
    show_progress : bool
        A progress bar (tqdm).
    total : int, optional
        Number of frames, for the progress bar.
    callbacks : sequence of callable
        Consumers of the map as it is built (a bag writer, a live view): each is called as
        ``callback(frame, T_map_cam, emap)`` after every frame is fused, ``T_map_cam`` the pose used.
    recorded_margins_px : mapping of str to int, optional
        The valid-region margin [px] per camera name that the frames were recorded with; default: the
        ``valid_margins_px`` of ``frames`` when it has one. Used where ``config.valid_margin_px`` is None;
        cameras it does not name take ``DEFAULT_VALID_MARGIN_PX``.

    Raises
    ------
    ValueError
        A frame that is not a :class:`Frame`, a camera changing its intrinsics, or no frame at all (an
        empty source is an error, not an empty map).

    Returns
    -------
    dict
        frames, per-frame timing [ms] (median, p95, mean), final map statistics and, with a truth,
        its error (:func:`map_error`), plus the map itself under "map" (an ElevationMap); ``frames_per_s``
        end to end (from the recording's opening to its file in place) and ``seconds``: ``total`` and its
        parts ``source`` (waiting for frames: reading, decoding, simulating), ``mapping`` (the mapper),
        ``scoring`` (against the truth), ``logging`` (rerun, the recording's closing included) and
        ``callbacks``.
    """
    from tqdm import tqdm

    emap = ElevationMap(config.length_m, config.resolution_m, fusion_params=config.fusion,
                        visibility_cleanup=config.visibility_cleanup, nthreads=nthreads)
    mapper = Mapper(emap, nthreads=nthreads)
    model = SensorModel.load(config.sensor_model) if config.sensor_model else D435
    if recorded_margins_px is None:
        recorded_margins_px = getattr(frames, "valid_margins_px", None) or {}
    recording = None
    clock = {"source": 0.0, "mapping": 0.0, "scoring": 0.0, "logging": 0.0, "callbacks": 0.0}
    t_start = time.perf_counter()
    if rrd_path is not None or spawn:
        from . import viz

        recording = viz.open_recording(rrd_path, application_id, spawn=spawn)
    times, scores, trail = [], [], []
    truth_fn = truth_height
    n_frames = 0
    first_stamp = None
    try:
        rec = recording.__enter__() if recording is not None else None
        logger = _Logger(rec, config, notes) if rec is not None else None
        if recording is not None:
            clock["logging"] += time.perf_counter() - t_start
        source = tqdm(frames, total=total, desc="mapping", unit="frame", disable=not show_progress)
        for frame in _timed(source, clock):
            if not isinstance(frame, Frame):
                raise ValueError(f"sources must yield elevmap.frame.Frame records, got {type(frame).__name__}")
            t0 = time.perf_counter()
            if frame.camera not in mapper.cameras:
                margin = config.valid_margin_px
                if margin is None:
                    margin = recorded_margins_px.get(frame.camera, DEFAULT_VALID_MARGIN_PX)
                mapper.add_camera(Camera(frame.camera, frame.K, frame.width, frame.height,
                                         depth_scale=frame.depth_scale, model=model, valid_margin_px=margin))
            cam = mapper.cameras[frame.camera]
            if not np.array_equal(cam.K, frame.K):
                raise ValueError(f"camera {frame.camera!r} changed its intrinsics at frame {frame.index}")
            T = np.eye(4) if frame.T_map_cam is None else frame.T_map_cam
            check_coordinates(T[:3, 3], f"the camera position of frame {frame.index} (T_map_cam)")
            if first_stamp is None:
                first_stamp = frame.stamp
            if config.follow:
                emap.move_to(T[:2, 3])
            stats = mapper.integrate(frame.camera, frame.depth, T_map_cam=T, pose_cov=frame.pose_cov,
                                     stamp=frame.stamp)
            times.append(stats["total_ms"])
            trail.append(T[:3, 3].copy())
            t1 = time.perf_counter()
            clock["mapping"] += t1 - t0
            fn = truth_fn or frame.truth.get("height")
            score = None
            if fn is not None and (n_frames % config.score_every == 0):
                score = map_error(emap, fn)
                scores.append(score)
            t2 = time.perf_counter()
            clock["scoring"] += t2 - t1
            if logger is not None and n_frames % config.log_every == 0:
                logger.log(n_frames, frame, T, emap, mapper, stats, score, trail, first_stamp)
            t3 = time.perf_counter()
            if logger is not None:
                clock["logging"] += t3 - t2
            for callback in callbacks:
                callback(frame, T, emap)
            clock["callbacks"] += time.perf_counter() - t3
            n_frames += 1
        if n_frames == 0:
            raise ValueError("the source gave no depth frames: nothing to map")
        t0 = time.perf_counter()
        final = map_error(emap, truth_fn or _last_truth(frame if n_frames else None)) if (
            n_frames and (truth_fn or _last_truth(frame))) else None
        t1 = time.perf_counter()
        clock["scoring"] += t1 - t0
        if logger is not None and n_frames:
            logger.final(emap, final, trail)
    except BaseException as exc:
        if recording is not None:
            recording.__exit__(type(exc), exc, exc.__traceback__)
        raise
    if recording is not None:
        recording.__exit__(None, None, None)
    t_end = time.perf_counter()
    if recording is not None:
        clock["logging"] += t_end - t1
    t = np.array(times) if times else np.array([math.nan])
    wall = t_end - t_start
    out = {"frames": n_frames, "ms_per_frame_median": float(np.median(t)), "ms_per_frame_p95": float(np.percentile(t, 95)),
           "ms_per_frame_mean": float(np.mean(t)), "known_fraction": emap.known_fraction(),
           "map_cells": emap.n ** 2, "resolution_m": emap.resolution_m, "map": emap,
           "frames_per_s": n_frames / wall if wall > 0 else math.nan,
           "seconds": {"total": wall, **clock}}
    if final is not None:
        out["error"] = final
    if rrd_path is not None:
        out["rrd"] = str(rrd_path)
    return out


def _timed(frames, clock: dict):
    """Yield the frames of ``frames``, adding the time each takes to arrive to ``clock["source"]`` [s]."""
    it = iter(frames)
    while True:
        t0 = time.perf_counter()
        try:
            frame = next(it)
        except StopIteration:
            clock["source"] += time.perf_counter() - t0
            return
        clock["source"] += time.perf_counter() - t0
        yield frame


def _last_truth(frame):
    return None if frame is None else frame.truth.get("height")


#: Points per logged piece of the trail: the trail is logged as pieces of at most this many positions, only
#: the last one re-logged at each view, so a long run's trail costs the same per view as a short one's.
TRAIL_PIECE = 256


class _Logger:
    """Everything a mapping run sends to rerun (through elevmap.viz, the project's rerun package).

    Every logged frame: the time, the camera pose, the depth image and the exact values a replay needs
    (``meta/<camera>``: intrinsics, pose, pose covariance, stamp, depth scale, index and the camera's
    valid-region margin), and the mapper's time per frame. At most ``view_rate_hz`` times per second of
    frame stamps (:meth:`view_due`): each camera's points with their ellipsoids (``world/points/<camera>``,
    ``world/points_cov/<camera>``: each camera has its own slots, so every camera of a robot is drawn), and
    the trail, the map's statistics and, every ``mesh_every`` views, the map meshes.
    """

    def __init__(self, rec, config: MappingConfig, notes):
        from . import viz

        self.viz = viz
        self.rec = rec
        self.config = config
        self.cameras = set()
        self.logged = 0
        self.views = 0
        self._slots = {}
        self._trail_piece = 0
        viz.log_world_frame(rec, "world")
        self.has_notes = bool(notes)
        if notes:
            viz.log_text(rec, "notes", notes)

    def view_due(self, key, stamp: float, first_stamp: float) -> bool:
        """Whether the frame stamped ``stamp`` [s] opens a new view slot of ``key`` (a camera, or None for the
        map): slot k holds the stamps in [k, k + 1) / view_rate_hz after the run's first frame; a stamp
        earlier than the last view's (a source whose clock restarts) opens one too. A millionth of a slot of
        tolerance keeps frames stamped exactly on the slot boundaries (a 10 Hz camera at 10 Hz views) in
        their own slots despite rounding."""
        slot = math.floor((stamp - first_stamp) * self.config.view_rate_hz + 1e-6)
        if self._slots.get(key) == slot:
            return False
        self._slots[key] = slot
        return True

    def log(self, i, frame: Frame, T, emap, mapper, stats, score, trail, first_stamp):
        viz, rec = self.viz, self.rec
        cam = frame.camera
        if cam not in self.cameras:
            self.cameras.add(cam)
            viz.log_camera(rec, f"world/{cam}/depth", frame.K, frame.width, frame.height, static=True)
            self._blueprint()
        viz.set_time(rec, "frame", sequence=i)
        viz.set_time(rec, "time", seconds=frame.stamp - first_stamp)
        viz.log_transform(rec, f"world/{cam}", T)
        if frame.depth.dtype == np.uint16 and self.config.png_depth:
            viz.log_depth_png(rec, f"world/{cam}/depth", frame.depth, meter=1.0 / frame.depth_scale)
        else:
            meter = None if frame.depth_scale is None else 1.0 / frame.depth_scale
            viz.log_depth(rec, f"world/{cam}/depth", frame.depth, meter=meter)
        viz.log_exact(rec, f"meta/{cam}", K=frame.K, T_map_cam=T, pose_cov=frame.pose_cov, stamp=frame.stamp,
                      depth_scale=frame.depth_scale, index=frame.index,
                      valid_margin_px=mapper.cameras[cam].valid_margin_px)
        viz.log_scalar(rec, "plots/time/ms_per_frame", stats["total_ms"])
        self.logged += 1
        if self.view_due(cam, frame.stamp, first_stamp):
            self._points(cam, mapper.last_points)
        if self.view_due(None, frame.stamp, first_stamp):
            self._view(emap, score, trail)

    def _points(self, cam, pts):
        viz, rec = self.viz, self.rec
        if pts is not None and len(pts.pixel):
            k = np.linspace(0, len(pts.pixel) - 1, min(self.config.max_points, len(pts.pixel))).astype(np.int64)
            p = np.asarray(pts.points_map)[k]
            viz.log_points(rec, f"world/points/{cam}", p, colors=viz.colormap(p[:, 2], *viz.robust_range(p[:, 2])),
                           radii=0.005)
            k = k[:: max(1, len(k) // self.config.max_ellipsoids)]
            hc = np.asarray(pts.horizontal_cov)[k]
            cov = np.zeros((len(k), 3, 3))
            cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 0], cov[:, 1, 1] = hc[:, 0], hc[:, 1], hc[:, 1], hc[:, 2]
            cov[:, 2, 2] = np.asarray(pts.height_var)[k]
            viz.log_covariance_ellipsoids(rec, f"world/points_cov/{cam}", np.asarray(pts.points_map)[k], cov)

    def _view(self, emap, score, trail):
        viz, rec = self.viz, self.rec
        self._trail(trail)
        viz.log_scalar(rec, "plots/cells/known", int(np.isfinite(emap.data[0]).sum()))
        var = emap.data[1][np.isfinite(emap.data[1])]
        if var.size:
            viz.log_scalar(rec, "plots/metres/mean_sigma", float(np.mean(np.sqrt(var))))
        if score is not None and score["known_cells"]:
            viz.log_scalar(rec, "plots/metres/median_abs_error", score["median_abs_m"])
            viz.log_scalar(rec, "plots/fraction/coverage_2sigma", score["coverage_2sigma"])
        if self.views % self.config.mesh_every == 0:
            self._meshes(emap)
        self.views += 1

    def _trail(self, trail):
        """Log the trail's last piece, after the pieces completed since the last view (each once, whole).
        Piece j holds positions [j P - 1, (j + 1) P) (P = :data:`TRAIL_PIECE`): consecutive pieces share one
        position, so the drawn path has no gaps."""
        piece = (len(trail) - 1) // TRAIL_PIECE
        for j in range(self._trail_piece, piece + 1):
            lo, hi = max(0, j * TRAIL_PIECE - 1), min(len(trail), (j + 1) * TRAIL_PIECE)
            self.viz.log_trail(self.rec, f"world/trail/{j}", np.array(trail[lo:hi]))
        self._trail_piece = piece

    def _meshes(self, emap):
        viz = self.viz
        xs, ys = emap.cell_centres()
        h = emap.known_layer("elevation")
        sigma = np.sqrt(emap.known_layer("variance"))
        viz.log_height_mesh(self.rec, "world/map/elevation", xs, ys, h, viz.colormap(h, *viz.robust_range(h)))
        viz.log_height_mesh(self.rec, "world/map/sigma", xs, ys, h, viz.colormap(sigma, 0.001, 0.1, log=True))

    def final(self, emap, error, trail):
        """The end of the run: the whole trail and the final map's meshes, whatever the view rate."""
        self._trail(trail)
        self._meshes(emap)
        if error is not None:
            self.viz.log_text(self.rec, "result", "\n".join(f"- {k}: {v:.4g}" for k, v in error.items()))

    def _blueprint(self):
        bp = self.viz.default_blueprint(
            depth_entities=[f"world/{c}/depth" for c in sorted(self.cameras)],
            time_series_entities=["plots/time", "plots/cells", "plots/metres", "plots/fraction"],
            text_entities=["notes"] if self.has_notes else [], world="world", timeline="frame",
            hidden_entities=["world/map/sigma", "world/points_cov"])
        self.rec.send_blueprint(bp)
