"""Source -> mapper -> map -> viewer: the loop behind ``elevmap run``, ``replay`` and ``demo``.

Frames come from any source (:mod:`elevmap.sources`); each is fused by a :class:`Mapper` into a
robot-centric :class:`ElevationMap`; when the frames carry the true terrain (the simulator), the map
is scored against it; with a recording path every frame goes to rerun through :mod:`elevmap.viz`
(imported only then), laid out so that :class:`elevmap.sources.rrd.RrdSource` replays it bit-exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from noise_model.d435 import D435, SensorModel

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
    log_every, mesh_every : int
        Log the frame every k frames; the map meshes every k logged frames.
    max_points, max_ellipsoids : int
        Sub-sampled points and covariance ellipsoids logged per frame.
    png_depth : bool
        Log uint16 depth losslessly PNG-compressed (replays bit-exact, about half the size).
    sensor_model : str
        A sensor model file (``elevmap-sensor-model/1`` or ``/2``, as ``elevmap characterize`` writes
        it) for every camera of the run; "" = the paper's D435.
    """

    length_m: float = 8.0
    resolution_m: float = 0.04
    fusion: FusionParams = FusionParams()
    visibility_cleanup: bool = True
    follow: bool = True
    score_every: int = 1
    log_every: int = 1
    mesh_every: int = 20
    max_points: int = 4000
    max_ellipsoids: int = 300
    png_depth: bool = True
    sensor_model: str = ""

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
        if not isinstance(self.sensor_model, str):
            raise ValueError(f"sensor_model must be a file path (a string), got {self.sensor_model!r}")

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
                callbacks=()) -> dict:
    """Map a sequence of :class:`Frame` records; optionally record everything to rerun.

    Parameters
    ----------
    frames : iterable of Frame
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

    Raises
    ------
    ValueError
        A frame that is not a :class:`Frame`, a camera changing its intrinsics, or no frame at all (an
        empty source is an error, not an empty map).

    Returns
    -------
    dict
        frames, per-frame timing [ms] (median, p95, mean), final map statistics and, with a truth,
        its error (:func:`map_error`), plus the map itself under "map" (an ElevationMap).
    """
    from tqdm import tqdm

    emap = ElevationMap(config.length_m, config.resolution_m, fusion_params=config.fusion,
                        visibility_cleanup=config.visibility_cleanup, nthreads=nthreads)
    mapper = Mapper(emap, nthreads=nthreads)
    model = SensorModel.load(config.sensor_model) if config.sensor_model else D435
    recording = None
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
        for frame in tqdm(frames, total=total, desc="mapping", unit="frame", disable=not show_progress):
            if not isinstance(frame, Frame):
                raise ValueError(f"sources must yield elevmap.frame.Frame records, got {type(frame).__name__}")
            if frame.camera not in mapper.cameras:
                mapper.add_camera(Camera(frame.camera, frame.K, frame.width, frame.height,
                                         depth_scale=frame.depth_scale, model=model))
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
            fn = truth_fn or frame.truth.get("height")
            score = None
            if fn is not None and (n_frames % config.score_every == 0):
                score = map_error(emap, fn)
                scores.append(score)
            if logger is not None and n_frames % config.log_every == 0:
                logger.log(n_frames, frame, T, emap, mapper, stats, score, trail, first_stamp)
            for callback in callbacks:
                callback(frame, T, emap)
            n_frames += 1
        if n_frames == 0:
            raise ValueError("the source gave no depth frames: nothing to map")
        final = map_error(emap, truth_fn or _last_truth(frame if n_frames else None)) if (
            n_frames and (truth_fn or _last_truth(frame))) else None
        if logger is not None and n_frames:
            logger.final(emap, final)
    except BaseException as exc:
        if recording is not None:
            recording.__exit__(type(exc), exc, exc.__traceback__)
        raise
    if recording is not None:
        recording.__exit__(None, None, None)
    t = np.array(times) if times else np.array([math.nan])
    out = {"frames": n_frames, "ms_per_frame_median": float(np.median(t)), "ms_per_frame_p95": float(np.percentile(t, 95)),
           "ms_per_frame_mean": float(np.mean(t)), "known_fraction": emap.known_fraction(),
           "map_cells": emap.n ** 2, "resolution_m": emap.resolution_m, "map": emap}
    if final is not None:
        out["error"] = final
    if rrd_path is not None:
        out["rrd"] = str(rrd_path)
    return out


def _last_truth(frame):
    return None if frame is None else frame.truth.get("height")


class _Logger:
    """Everything a mapping run sends to rerun (through elevmap.viz, the project's rerun package)."""

    def __init__(self, rec, config: MappingConfig, notes):
        from . import viz

        self.viz = viz
        self.rec = rec
        self.config = config
        self.cameras = set()
        self.logged = 0
        viz.log_world_frame(rec, "world")
        self.has_notes = bool(notes)
        if notes:
            viz.log_text(rec, "notes", notes)

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
                      depth_scale=frame.depth_scale, index=frame.index)
        viz.log_trail(rec, "world/trail", np.array(trail))
        pts = mapper.last_points
        if pts is not None and len(pts.pixel):
            k = np.linspace(0, len(pts.pixel) - 1, min(self.config.max_points, len(pts.pixel))).astype(np.int64)
            p = np.asarray(pts.points_map)[k]
            viz.log_points(rec, "world/points", p, colors=viz.colormap(p[:, 2], *viz.robust_range(p[:, 2])), radii=0.005)
            k = k[:: max(1, len(k) // self.config.max_ellipsoids)]
            hc = np.asarray(pts.horizontal_cov)[k]
            cov = np.zeros((len(k), 3, 3))
            cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 0], cov[:, 1, 1] = hc[:, 0], hc[:, 1], hc[:, 1], hc[:, 2]
            cov[:, 2, 2] = np.asarray(pts.height_var)[k]
            viz.log_covariance_ellipsoids(rec, "world/points_cov", np.asarray(pts.points_map)[k], cov)
        viz.log_scalar(rec, "plots/time/ms_per_frame", stats["total_ms"])
        viz.log_scalar(rec, "plots/cells/known", int(np.isfinite(emap.data[0]).sum()))
        var = emap.data[1][np.isfinite(emap.data[1])]
        if var.size:
            viz.log_scalar(rec, "plots/metres/mean_sigma", float(np.mean(np.sqrt(var))))
        if score is not None and score["known_cells"]:
            viz.log_scalar(rec, "plots/metres/median_abs_error", score["median_abs_m"])
            viz.log_scalar(rec, "plots/fraction/coverage_2sigma", score["coverage_2sigma"])
        if self.logged % self.config.mesh_every == 0:
            self._meshes(emap)
        self.logged += 1

    def _meshes(self, emap):
        viz = self.viz
        xs, ys = emap.cell_centres()
        h = emap.known_layer("elevation")
        sigma = np.sqrt(emap.known_layer("variance"))
        viz.log_height_mesh(self.rec, "world/map/elevation", xs, ys, h, viz.colormap(h, *viz.robust_range(h)))
        viz.log_height_mesh(self.rec, "world/map/sigma", xs, ys, h, viz.colormap(sigma, 0.001, 0.1, log=True))

    def final(self, emap, error):
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
