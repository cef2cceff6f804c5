"""``elevmap compare``: one simulated walk, the same frames through several mappers, scored against the truth.

Does the noise model make the map better, and can its variances be trusted? A simulated D435 walks
through a scene (:class:`elevmap.sources.simulated.SimulatedWalk`). Its reality is one of:

* ``"reference"`` (the default): the reference simulation of the paper's model, plus optional effects of
  :mod:`noise_model.sim.effects` that make it harder than the model (``sim_effects``);
* ``"stereo"``: the physical D435 of :mod:`noise_model.sim.stereo` (projector, infrared pair and D4
  matcher, a noise nobody wrote as a formula; it takes no effects);
* a gap report ``GAP.json`` (``elevmap gap --json``): the reference simulation plus the effects the gap
  diagnosis selected, as fitted.

The frames are rendered once and fed, unchanged, to each mapper:

* ``paper``: the paper's model with full covariance propagation (``Camera`` without a
  ``variance_model``: the numba kernel);
* ``fitted``: the model ``elevmap characterize`` fits on the paper's grid of captures simulated with the
  same reality (:mod:`elevmap.commands.compare_work`), or a model file the caller gives: the workflow of
  a user with their own camera;
* ``disparity``: the disparity family at sigma_d = :data:`DISPARITY_SIGMA_PX` px, Intel's typical
  subpixel RMS (``D435.with_disparity``);
* ``quadratic``: elevation_mapping_cupy's variance = 0.05 z^2 (:func:`noise_model.alternatives.quadratic`);
* ``anybotics_d435``: ANYbotics' D435 preset (:func:`noise_model.alternatives.anybotics_d435`);
* ``constant``: one isotropic sigma for every point, 2 cm (:func:`noise_model.alternatives.constant`);
* ``<name>_capped`` (``fitted_capped``, ``paper_capped``, ...): that mapper with the per-frame
  information cap ``FusionParams(max_points_per_frame=cap)`` (default :data:`DEFAULT_CAP` = 1).

Every mapper has the same map settings (:class:`elevmap.pipeline.MappingConfig`: 8 m at 0.04 m, visibility
clean-up, re-centred on the camera every frame); a capped mapper differs from its base only in the cap. At
the end of the walk each map is scored by :func:`elevmap.pipeline.map_error` against the true height at the
centres of its known cells (:func:`closed_truth`: a centre on a step's edge is scored against the upper
side, as the scene's closed footprints define it), plus the mean sigma over its known cells (sharpness), the
known-cell fraction, the step-edge band's scores (the cells within two cells of a step: error, coverage,
NLL, and the fraction of the band's seen cells the mapper knows) and the median time per frame
(``Mapper.integrate``: noise model + fusion + clean-up; the alternatives' time includes the paper's kernel,
which still deprojects the points, plus their NumPy hook; frames go to the mappers interleaved, so a busy
machine slows them alike; the scores: :mod:`elevmap.commands.compare_scores`). Mappers know different cells,
so the same scores are also given over the cells known to *all* mappers (``common``) and at equal coverage
(``matched``: each mapper's N known cells of smallest variance, N the fewest known cells of any mapper; one
point of a sparsification curve). Every mapper runs with the variance ceiling :data:`COMPARE_MAX_VARIANCE`
(elevation_mapping_cupy's 1 m^2) unless the caller sets another: the map's default ceiling would take a
pessimistic model's far cells away and score it on its near cells only. Several seeds:
:mod:`elevmap.commands.compare_seeds`.

Report (JSON, NaN written as null)::

    {"scene": str, "frames": int, "seed": int, "width": int, "height": int,
     "reality": "reference" | "stereo" | "gap", "gap_report": str | null, "preset": str | null,
     "sim_effects": [{"name": str, "params": {...}}, ...], "cap": float,
     "map": {"length_m", "resolution_m", "visibility_cleanup", "follow", "fusion": {...}},
     "frames_digest": sha256 hex, "frames_cached": bool,
     "mappers": {name: {"rmse_m", "p95_abs_m", "nll", "coverage_1sigma", "coverage_2sigma",
                        "mean_sigma_m", "edge_rmse_m", "flat_rmse_m", "known_fraction", "ms_per_frame",
                        "median_abs_m", "mean_error_m", "flat_coverage_2sigma", "known_cells",
                        "edge_cells", "edge_coverage_1sigma", "edge_coverage_2sigma", "edge_nll",
                        "edge_mean_error_m", "edge_known_fraction", "ms_per_frame_p95", "frames_digest",
                        "confident_errors" (cells off by > 0.1 m and > 4 sigma: compare_scores.confident_errors),
                        "edge_profile": [{"rings", "cells", "rmse_m", "mean_error_m", "coverage_1sigma",
                                          "coverage_2sigma", "nll_sum", "large_errors"}, ...] (edge_profile),
                        "variance_floor": {"cells", "fraction", "rmse_m", "coverage_1sigma",
                                           "coverage_2sigma"} (floor_profile),
                        "model": {...}}, ...},
     "edge_band_cells": int (the band's cells some mapper knows),
     "common": {"cells": int, "mappers": {name: {"rmse_m", "p95_abs_m", "nll", "coverage_1sigma",
                                                 "coverage_2sigma", "mean_sigma_m"}}},
     "matched": {"cells": int, "mappers": {name: {same keys as common}}},
     "render_ms_per_frame": float}

Units: metres, square metres for variances, milliseconds; coverages are fractions in [0, 1]; ``nll``
is the mean Gaussian negative log-likelihood of the true height under each cell's (height,
variance), in nats. ``frames_digest`` is a SHA-256 over every frame's depth, pose and pose covariance
as each mapper received them: equal for all mappers. The recording: :mod:`elevmap.commands.compare_output`.
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass

import numpy as np

import noise_model as nm
from noise_model.alternatives import make_variance_model
from noise_model.checks import check_positive_scalar

from ..map.elevation_map import ElevationMap
from ..frame import Frame
from ..fileio import check_outputs, json_ready
from ..map.fusion import FusionParams
from ..mapper import Camera, Mapper
from ..pipeline import MappingConfig
from .compare_args import REALITIES, apply_settings, camera_settings, parse_mappers, parse_reality, parse_settings
from .compare_scores import (EDGE_RINGS, FLOOR_MARGIN, common_scores, edge_known_fractions, edge_profile,
                             floor_profile, matched_scores, most_confident, score_map, truth_grid)

__all__ = ["MAPPERS", "BASE_MAPPERS", "ALL_MAPPERS", "SCENES", "DEFAULT_CAP", "DISPARITY_SIGMA_PX",
           "COMPARE_MAX_VARIANCE", "REPORT_KEYS", "EDGE_RINGS", "edge_profile", "FLOOR_MARGIN", "floor_profile",
           "run_compare", "render_walk",
           "MapperSpec", "mapper_specs",
           "json_ready", "frames_digest",
           "most_confident", "closed_truth", "TRUTH_BOUNDARY_TOL_M"]

#: Mappers without a cap, in report order.
BASE_MAPPERS = ("paper", "fitted", "disparity", "quadratic", "anybotics_d435", "constant")
#: Every mapper name: the base mappers and each with the information cap (``<name>_capped``).
ALL_MAPPERS = BASE_MAPPERS + tuple(f"{b}_capped" for b in BASE_MAPPERS)
#: The default mappers of a comparison, in report order: every base mapper and the cap on the fitted one.
MAPPERS = BASE_MAPPERS + ("fitted_capped",)
#: Scenes of a comparison (those of :class:`elevmap.sources.simulated.SimulatedWalk`).
SCENES = ("stairs", "boxes", "slope", "rough", "demo")
#: sigma_d of the ``disparity`` mapper [px]: Intel's typical subpixel RMS of the D4 matcher on a
#: textured target (librealsense's depth-quality notes), the one number a user finds without measuring.
DISPARITY_SIGMA_PX = 0.08
#: The per-frame information cap of the ``_capped`` mappers: a frame adds to a cell at most the
#: information of n_eff = 1 average point. Why 1: (a) physics: with the D435's error correlation of
#: about 3 px at 848 x 480, a 4 cm cell at 1 m holds about one independent sample per frame
#: (docs/depth-effects.md, E9); (b) precedent: elevation_mapping_cupy averages a frame's points per cell,
#: so that N points reduce the variance as much as one; (c) the comparisons of docs/calibration.md. The
#: map's own default is no cap (``FusionParams.max_points_per_frame = None``; docs/calibration.md says why).
DEFAULT_CAP = 1.0
#: The variance ceiling ``FusionParams.max_variance`` [m^2] of every mapper of a comparison, unless the
#: caller sets it: elevation_mapping_cupy's own (its ``parameter.py`` default). The map's default
#: (0.04 m^2, sigma 0.2 m) is a consumer's "no height rather than one uncertain by more than 20 cm"; in a
#: comparison it would decide the scores instead of the noise models, since each mapper is scored over
#: its own known cells and a model that states large variances loses its far cells to the ceiling
#: (quadratic's 0.05 z^2 per point exceeds 0.04 m^2 beyond 0.9 m, so it would be scored on its near cells
#: only), while the paper mapper's own scores barely move (docs/calibration.md).
COMPARE_MAX_VARIANCE = 1.0
#: The keys every mapper's entry of the report has.
REPORT_KEYS = ("rmse_m", "p95_abs_m", "nll", "coverage_1sigma", "coverage_2sigma", "mean_sigma_m", "edge_rmse_m",
               "flat_rmse_m", "known_fraction", "ms_per_frame", "edge_coverage_2sigma", "edge_known_fraction",
               "confident_errors")


@dataclass(frozen=True)
class MapperSpec:
    """How one mapper of a comparison is built.

    Attributes
    ----------
    name : str
    variance_model : callable or None
        The camera's ``variance_model`` hook (None: the noise model ``model`` through the numba kernel).
    fusion : FusionParams
    description : dict
        What the report says about it (model name, parameters, source, cap).
    model : noise_model.SensorModel
        The camera's sensor model (the paper's D435 unless fitted or of the disparity family).
    """

    name: str
    variance_model: object
    fusion: FusionParams
    description: dict
    model: object = nm.D435


def mapper_specs(names=MAPPERS, cap: float = DEFAULT_CAP, fusion: FusionParams | None = None,
                 fitted_model=None, fitted_info: dict | None = None) -> list[MapperSpec]:
    """The mappers ``names`` with the map's fusion parameters ``fusion`` (the capped ones add ``cap``).

    Parameters
    ----------
    names : sequence of str
        Names of :data:`ALL_MAPPERS`.
    cap : float
        n_eff of the capped mappers (>= 1).
    fusion : FusionParams, optional
    fitted_model : noise_model.SensorModel, optional
        The model of ``fitted`` (required when it or ``fitted_capped`` is asked for).
    fitted_info : dict, optional
        Where it came from, for the report.

    Raises
    ------
    ValueError
        Unknown mapper name, a cap below 1, or ``fitted`` without a model.
    """
    fusion = FusionParams() if fusion is None else fusion
    if not isinstance(fusion, FusionParams):
        raise ValueError("fusion must be an elevmap.FusionParams")
    cap = _check_cap(cap)
    out = []
    for name in names:
        if name not in ALL_MAPPERS:
            raise ValueError(f"unknown mapper {name!r}; mappers: {', '.join(ALL_MAPPERS)}")
        base = name[: -len("_capped")] if name.endswith("_capped") else name
        f = _replace(fusion, max_points_per_frame=cap) if name != base else fusion
        vm, model = None, nm.D435
        if base == "paper":
            desc = {"name": "paper", "source": "Ahn et al. 2019, full covariance propagation (noise_model kernel)",
                    "params": {}}
        elif base == "fitted":
            if fitted_model is None:
                raise ValueError("the fitted mapper needs a model: elevmap characterize's model file, or a work "
                                 "folder to fit one in")
            if not isinstance(fitted_model, nm.SensorModel):
                raise ValueError("fitted_model must be a noise_model.SensorModel")
            model = fitted_model
            desc = {"name": "fitted", "source": "elevmap characterize on the paper's grid simulated with this reality",
                    "params": fitted_model.to_dict(), **({"fit": fitted_info} if fitted_info else {})}
        elif base == "disparity":
            model = nm.D435.with_disparity(DISPARITY_SIGMA_PX)
            desc = {"name": "disparity", "source": "disparity family, Intel's typical subpixel RMS",
                    "params": {"sigma_d_px": DISPARITY_SIGMA_PX}}
        else:
            vm = make_variance_model(base)
            desc = {"name": vm.name, "source": vm.source, "params": dict(vm.params)}
        desc["max_points_per_frame"] = f.max_points_per_frame
        out.append(MapperSpec(name, vm, f, desc, model))
    return out


def _replace(params, **changes):
    """A copy of the frozen dataclass ``params`` (FusionParams, MappingConfig) with ``changes``."""
    from dataclasses import replace

    return replace(params, **changes)


def _check_max_variance(value) -> float:
    return check_positive_scalar(value, "max_variance", unit=" m^2")


def _check_cap(cap) -> float:
    try:
        c = float(cap)
    except (TypeError, ValueError):
        raise ValueError(f"cap must be a number >= 1, got {cap!r}") from None
    if not math.isfinite(c) or c < 1:
        raise ValueError(f"cap (points per cell and frame) must be finite and >= 1, got {cap!r}")
    return c


# ---------------------------------------------------------------------------------------------
# frames
# ---------------------------------------------------------------------------------------------
def render_walk(scene: str = "stairs", n_frames: int | None = None, seed: int = 0, effects=(),
                width: int = 424, height: int = 240, show_progress: bool = False, reality: str = "reference",
                preset: str = "default", work=None, reality_key: str | None = None):
    """Render a simulated walk once (or read it from a work folder's cache).

    Parameters
    ----------
    scene : str
        One of :data:`SCENES`.
    n_frames : int, optional
        Frames (the whole path by default: 113 at 10 Hz and 0.5 m/s).
    seed : int
        Seed of the scene, the noise and the effects.
    effects : sequence of Effect
        Extra depth effects on top of the paper's reference noise (reference reality only).
    width, height : int
        D435 depth mode [px].
    reality : {"reference", "stereo"}
        The reference simulation of the paper's model, or the physical D435.
    preset : str
        Matcher preset of the physical D435.
    work : elevmap.commands.compare_work.WorkDir, optional
        Cache the frames there (keyed by ``reality_key``, the scene, seed, size and frames).
    reality_key : str, optional
        The reality's name in the cache (:func:`elevmap.commands.compare_work.reality_key`); required with
        ``work``.

    Returns
    -------
    frames : list of Frame
    walk : SimulatedWalk
        Its ``truth_height(xy)`` gives the true terrain [m]; ``walk.frames_cached`` says whether the
        frames came from the cache.
    """
    from tqdm import tqdm

    from ..sources.simulated import SimulatedWalk

    _check_walk(scene, n_frames, seed, width, height)
    effects = list(effects or ())
    for e in effects:
        if not callable(e):
            raise ValueError(f"effects must be callables (noise_model.sim.effects), got {e!r}")
    if reality not in REALITIES:
        raise ValueError(f"unknown sensor reality {reality!r}; realities: {', '.join(REALITIES)}")
    if reality == "stereo" and effects:
        raise ValueError("the stereo reality makes its own noise: it takes no sim effects")
    walk = SimulatedWalk(scene, n_frames=None if n_frames is None else int(n_frames), seed=int(seed),
                         width=int(width), height=int(height), effects=effects or None, sensor=reality,
                         preset=preset)

    def render():
        frames = list(tqdm(walk, total=len(walk), desc="rendering", unit="frame", disable=not show_progress))
        if n_frames is not None and len(frames) < n_frames:
            raise ValueError(f"the {scene} walk has only {len(frames)} frames, asked for {n_frames}")
        return frames

    if work is None:
        frames, walk.frames_cached = render(), False
    else:
        if not reality_key:
            raise ValueError("a cached walk needs its reality's key")
        params = {"reality": reality_key, "scene": scene, "seed": int(seed), "width": int(width),
                  "height": int(height), "frames": None if n_frames is None else int(n_frames),
                  "preset": preset if reality == "stereo" else None}
        frames, walk.frames_cached = work.frames(params, render)
    return frames, walk


def _check_walk(scene, n_frames, seed, width, height) -> None:
    """The walk's arguments (before any work)."""
    if scene not in SCENES:
        raise ValueError(f"unknown scene {scene!r}; scenes: {', '.join(SCENES)}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    if n_frames is not None and (isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer))
                                 or n_frames < 1):
        raise ValueError(f"frames must be a positive integer, got {n_frames!r}")
    for v, name in ((width, "width"), (height, "height")):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 16 <= v <= 4096:
            raise ValueError(f"{name} must be an integer in [16, 4096] px, got {v!r}")


def _digest_update(h, frame: Frame) -> None:
    h.update(np.ascontiguousarray(frame.depth).tobytes())
    h.update(np.ascontiguousarray(frame.T_map_cam).tobytes())
    if frame.pose_cov is not None:
        h.update(np.ascontiguousarray(frame.pose_cov).tobytes())


def frames_digest(frames) -> str:
    """SHA-256 over every frame's depth, pose and pose covariance."""
    h = hashlib.sha256()
    for f in frames:
        _digest_update(h, f)
    return h.hexdigest()


#: Distance [m] within which a point counts as on a footprint's boundary when the truth is scored: far below
#: any cell or scene dimension, far above the rounding of coordinates of metres (about 1e-15 m).
TRUTH_BOUNDARY_TOL_M = 1e-9


def closed_truth(truth_height, tol_m: float = TRUTH_BOUNDARY_TOL_M):
    """The true height with footprints as closed sets whatever the rounding of the coordinates.

    A scene's height at a point is the highest top surface whose footprint holds the point, footprints
    being closed sets (:meth:`noise_model.sim.Scene.height_at`), so a point on a step's edge has the
    upper side's height: the top of the riser, which is what an elevation map stores there. A cell
    centre that lies on an edge by construction (the stairs' landing ends at x = 4.74 m, a cell centre)
    can miss the footprint by a rounding error, and the cell would be scored against the lower side. The
    height returned is the highest of ``truth_height`` at the point and at the 8 points ``tol_m`` away
    along x, y and the diagonals (NaN only where all nine are NaN); a point farther than ``tol_m`` from
    every edge gets ``truth_height``'s own value within ``tol_m`` times the terrain's slope.

    Parameters
    ----------
    truth_height : callable
        (M, 2) map points [m] -> (M,) heights [m].
    tol_m : float
        Boundary tolerance [m], in (0, 1e-3].

    Returns
    -------
    callable
        (M, 2) map points [m] -> (M,) heights [m].
    """
    if not callable(truth_height):
        raise ValueError(f"truth_height must be callable, got {type(truth_height).__name__}")
    tol = check_positive_scalar(tol_m, "tol_m", upper=1e-3, unit=" m")
    offsets = np.array([(dx, dy) for dx in (-tol, 0.0, tol) for dy in (-tol, 0.0, tol) if dx or dy])

    def truth(xy):
        xy = np.asarray(xy, dtype=np.float64)
        out = np.asarray(truth_height(xy), dtype=np.float64)
        for off in offsets:
            out = np.fmax(out, np.asarray(truth_height(xy + off), dtype=np.float64))
        return out

    return truth


class _CachedTruth:
    """truth_height with a memo of the last grids asked for (every mapper scores the same cells)."""

    def __init__(self, fn, size: int = 4):
        self.fn, self.size, self.cache = fn, size, []

    def __call__(self, xy):
        xy = np.asarray(xy, dtype=np.float64)
        key = (xy.shape, xy[:1].tobytes(), xy[-1:].tobytes(), hashlib.sha1(xy.tobytes()).digest())
        for k, v in self.cache:
            if k == key:
                return v
        v = np.asarray(self.fn(xy), dtype=np.float64)
        self.cache = ([(key, v)] + self.cache)[: self.size]
        return v


# ---------------------------------------------------------------------------------------------
# running
# ---------------------------------------------------------------------------------------------
class _Run:
    """One mapper's state during a comparison."""

    def __init__(self, spec: MapperSpec, config: MappingConfig, nthreads):
        self.spec = spec
        self.emap = ElevationMap(config.length_m, config.resolution_m, fusion_params=spec.fusion,
                                 visibility_cleanup=config.visibility_cleanup, nthreads=nthreads)
        self.mapper = Mapper(self.emap, nthreads=nthreads)
        self.times: list[float] = []
        self.digest = hashlib.sha256()


def _map_frames(frames, specs, config: MappingConfig, *, nthreads=None, show_progress=False, on_frame=None,
                camera: dict | None = None):
    """Feed every frame to every mapper, interleaved (frame k to all mappers, then frame k + 1).

    Interleaving exposes all mappers alike to whatever else the machine is doing, so their times
    stay comparable; the order of the mappers rotates from frame to frame.

    Returns
    -------
    list of _Run
        Per mapper: its map, per-frame times [ms] (``Mapper.integrate``'s total) and the digest of
        the frames it received.
    """
    from tqdm import tqdm

    runs = [_Run(spec, config, nthreads) for spec in specs]
    for k, frame in enumerate(tqdm(frames, desc="mapping", unit="frame", disable=not show_progress)):
        if not isinstance(frame, Frame):
            raise ValueError(f"frames must be elevmap.frame.Frame records, got {type(frame).__name__}")
        T = frame.T_map_cam
        if T is None:
            raise ValueError(f"frame {k} has no pose (T_map_cam); a comparison needs posed frames")
        r = k % len(runs)
        for run in runs[r:] + runs[:r]:
            if frame.camera not in run.mapper.cameras:
                run.mapper.add_camera(Camera(frame.camera, frame.K, frame.width, frame.height,
                                             depth_scale=frame.depth_scale, model=run.spec.model,
                                             variance_model=run.spec.variance_model, **(camera or {})))
            if config.follow:
                run.emap.move_to(T[:2, 3])
            _digest_update(run.digest, frame)
            stats = run.mapper.integrate(frame.camera, frame.depth, T_map_cam=T, pose_cov=frame.pose_cov,
                                         stamp=frame.stamp)
            run.times.append(stats["total_ms"])
            if on_frame is not None:
                on_frame(run.spec.name, k, run.emap)
    return runs


def run_compare(scene: str = "stairs", n_frames: int | None = None, *, seed: int = 0, sim_effects=None,
                mappers=None, cap: float = DEFAULT_CAP, width: int = 424, height: int = 240,
                config: MappingConfig | None = None, max_variance: float | None = COMPARE_MAX_VARIANCE,
                rrd_path=None, show_progress: bool = True, nthreads: int | None = None, reality: str = "reference",
                preset: str = "default", work_dir=None, fitted_model=None, fit_dir=None, settings=None) -> dict:
    """One simulated walk, the same frames through several mappers, each scored against the truth.

    Parameters
    ----------
    scene : str
        One of :data:`SCENES` (stairs, boxes, slope, rough, demo).
    n_frames : int, optional
        Frames of the walk (default: the whole path).
    seed : int
        Seed of the scene, noise and effects.
    sim_effects : str or sequence of Effect or str, optional
        Effects added to the reference reality (see :func:`elevmap.commands.compare_args.parse_effects`).
    mappers : str or sequence of str, optional
        Names of :data:`ALL_MAPPERS` (default :data:`MAPPERS`, in that order).
    cap : float
        The information cap n_eff of the capped mappers (>= 1).
    width, height : int
        D435 depth mode [px] (default 424 x 240, the decimated stream ANYmal maps from).
    config : MappingConfig, optional
        Map settings shared by every mapper (default ``MappingConfig()``).
    max_variance : float or None
        The mappers' variance ceiling ``FusionParams.max_variance`` [m^2], replacing the one of
        ``config`` (default :data:`COMPARE_MAX_VARIANCE`); None keeps ``config``'s.
    rrd_path : path, optional
        Write a rerun recording there (atomically; an existing file is replaced, its folder must exist).
    show_progress : bool
        Progress bars.
    nthreads : int, optional
        numba threads.
    reality : str
        ``"reference"`` (default), ``"stereo"`` (the physical D435, no ``sim_effects``) or a gap report's
        path (:func:`elevmap.commands.compare_args.parse_reality`).
    preset : str
        Matcher preset of the physical D435 ("default", "high_accuracy").
    work_dir : path or WorkDir, optional
        Work folder (:mod:`elevmap.commands.compare_work`): the walk's frames are cached there, and the
        ``fitted`` mapper's model is characterised there when ``fitted_model`` is not given.
    fitted_model : noise_model.SensorModel or path, optional
        The ``fitted`` mapper's model (a model file of ``elevmap characterize``); default: fitted in
        ``work_dir`` (or ``fit_dir``) on the paper's grid simulated with this reality.
    fit_dir : path or WorkDir, optional
        Work folder for the fitted model only (no frames cached), when ``work_dir`` is None.
    settings : str or dict, optional
        Map settings applied to ``config`` for every mapper (``--set``,
        :func:`elevmap.commands.compare_args.parse_settings`): the fusion rules switched off or changed, to
        measure what each buys.

    Returns
    -------
    dict
        The report (module docstring); NaN where a score is undefined (e.g. no step edges).
    """
    from .compare_work import WorkDir, reality_key

    config = MappingConfig() if config is None else config
    if not isinstance(config, MappingConfig):
        raise ValueError("config must be an elevmap.pipeline.MappingConfig")
    if max_variance is not None:
        config = _replace(config, fusion=_replace(config.fusion, max_variance=_check_max_variance(max_variance)))
    settings = parse_settings(settings)
    config = apply_settings(config, settings)
    names = parse_mappers(mappers)
    real = parse_reality(reality, sim_effects)
    effects = real["effects"]
    _check_walk(scene, n_frames, seed, width, height)
    _check_cap(cap)
    nm.D435.intrinsics(int(width), int(height))                   # a depth mode with default intrinsics
    if real["sensor"] == "stereo":
        from noise_model.sim.stereo.matcher import preset as matcher_preset

        matcher_preset(preset).check_size(width, height)        # before a capture set is simulated for it
    work = None if work_dir is None else (work_dir if isinstance(work_dir, WorkDir) else WorkDir(work_dir))
    key = reality_key(real["kind"], preset, real["effects_digest"])
    fitted_info = None
    if any(n.split("_capped")[0] == "fitted" for n in names):
        fit_work = work if work is not None or fit_dir is None else (
            fit_dir if isinstance(fit_dir, WorkDir) else WorkDir(fit_dir))
        fitted_model, fitted_info = _fitted(fitted_model, fit_work, real, key, preset, width, height, show_progress)
    specs = mapper_specs(names, cap, config.fusion, fitted_model, fitted_info)
    check_outputs({"rrd_path": rrd_path}, overwrite=True)       # the command line has refused existing files
    t0 = time.perf_counter()
    frames, walk = render_walk(scene, n_frames, seed, effects, width, height, show_progress, real["sensor"], preset,
                               work=work, reality_key=key)
    render_ms = 1e3 * (time.perf_counter() - t0) / max(1, len(frames))
    truth = _CachedTruth(closed_truth(walk.truth_height))
    digest = frames_digest(frames)
    logger = None
    if rrd_path is not None:
        from .compare_output import CompareLogger

        logger = CompareLogger(rrd_path, names, frames, show_progress)
    results, maps = {}, {}
    try:
        on_frame = None if logger is None else logger.frame_callback(truth)
        runs = _map_frames(frames, specs, config, nthreads=nthreads, show_progress=show_progress, on_frame=on_frame,
                           camera=camera_settings(settings))
        unchanged = frames_digest(frames) == digest
        for run in runs:
            got = run.digest.hexdigest()
            if got != digest or not unchanged:
                raise RuntimeError(f"mapper {run.spec.name!r} did not get the rendered frames unchanged")
            score = score_map(run.emap, truth, run.times)
            score["frames_digest"] = got
            score["model"] = run.spec.description
            results[run.spec.name] = score
            maps[run.spec.name] = run.emap
        band_cells, band_known = edge_known_fractions(maps, truth)
        tr = truth_grid(next(iter(maps.values())), truth)
        for name, frac in band_known.items():
            results[name]["edge_known_fraction"] = frac
            results[name]["edge_profile"] = edge_profile(maps[name].known_layer("elevation"),
                                                         maps[name].known_layer("variance"), tr)
            results[name]["variance_floor"] = floor_profile(maps[name].known_layer("elevation"),
                                                            maps[name].known_layer("variance"), tr,
                                                            maps[name].fusion_params.min_variance)
        common = common_scores(maps, truth)
        matched = matched_scores(maps, truth)
        report = {"scene": scene, "frames": len(frames), "seed": int(seed), "width": int(width),
                  "height": int(height), "reality": real["kind"], "gap_report": real["gap_report"],
                  "preset": preset if real["sensor"] == "stereo" else None,
                  "sim_effects": [{"name": e.name, "params": dict(e.params)} for e in effects],
                  "cap": _check_cap(cap), "settings": settings,
                  "map": {"length_m": config.length_m, "resolution_m": config.resolution_m,
                          "visibility_cleanup": config.visibility_cleanup, "follow": config.follow,
                          "fusion": {k: getattr(config.fusion, k) for k in config.fusion.__dataclass_fields__}},
                  "frames_digest": digest, "frames_cached": bool(walk.frames_cached), "mappers": results,
                  "edge_band_cells": band_cells, "common": common, "matched": matched,
                  "render_ms_per_frame": render_ms}
        if logger is not None:
            logger.final(maps, truth, walk, report)
    except BaseException as exc:
        if logger is not None:
            logger.abort(exc)
        raise
    if logger is not None:
        logger.close()
        report["rrd"] = str(rrd_path)
    return report


def _fitted(fitted_model, work, real: dict, key: str, preset: str, width: int, height: int, show_progress: bool):
    """The ``fitted`` mapper's model and its report entry: a given model (or model file), else the one
    characterised in the work folder on the paper's grid simulated with this reality."""
    if fitted_model is not None:
        if isinstance(fitted_model, nm.SensorModel):
            return fitted_model, {"model_path": None, "family": fitted_model.family}
        model = nm.SensorModel.load(fitted_model)
        return model, {"model_path": str(fitted_model), "family": model.family}
    if work is None:
        raise ValueError("the fitted mapper needs a model file (--fitted-model) or a work folder (--work) to "
                         "characterise one in")
    if real["effects"] and real["sensor"] == "reference":
        raise ValueError("the fitted mapper on a reality with effects needs a model file (--fitted-model): "
                         "characterise a capture set simulated with those effects")
    return work.fitted_model(key, sensor=real["sensor"], preset=preset, width=width, height=height,
                             show_progress=show_progress)

