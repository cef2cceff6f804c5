"""``elevmap compare``: one simulated walk, the same frames through several mappers, scored against the truth.

Does the paper's noise model make the map better, and can its variances be trusted? A simulated D435
walks through a scene (:class:`elevmap.sources.simulated.SimulatedWalk`). Its reality is either the
reference simulation of the paper's model, plus optional effects of :mod:`noise_model.sim.effects` that
make it harder than the model (``reality="reference"``, the default), or the physical D435 of
:mod:`noise_model.sim.stereo` (``reality="stereo"``: projector, infrared pair and D4 matcher, a noise
nobody wrote as a formula; it takes no effects). The frames are rendered once and fed, unchanged, to
each mapper:

* ``paper``: the paper's model with full covariance propagation (``Camera`` without a
  ``variance_model``: the numba kernel);
* ``constant``: one isotropic sigma for every point, 2 cm (:func:`noise_model.alternatives.constant`);
* ``quadratic``: elevation_mapping_cupy's variance = 0.05 z^2 (:func:`noise_model.alternatives.quadratic`);
* ``anybotics_d435``: ANYbotics' D435 preset (:func:`noise_model.alternatives.anybotics_d435`);
* ``paper_capped``: the paper's model with the per-frame information cap
  ``FusionParams(max_points_per_frame=cap)`` (default :data:`DEFAULT_CAP` = 1).

Every mapper has the same map settings (:class:`elevmap.pipeline.MappingConfig`: 8 m at 0.04 m,
visibility clean-up, re-centred on the camera every frame); ``paper_capped`` differs from ``paper``
only in the cap. At the end of the walk each map is scored by :func:`elevmap.pipeline.map_error`
against the true height at the centres of its known cells, plus the mean sigma over its known cells
(sharpness), the known-cell fraction and the median time per frame (``Mapper.integrate``: noise
model + fusion + clean-up; the alternatives' time includes the paper's kernel, which still
deprojects the points, plus their NumPy hook; frames go to the mappers interleaved, so a busy
machine slows them alike). Mappers know different cells, so the same scores are also given over the
cells known to *all* mappers (``common``) and at equal coverage (``matched``: each mapper's N known
cells of smallest variance, N the fewest known cells of any mapper; one point of a sparsification
curve). Every mapper runs with the variance ceiling :data:`COMPARE_MAX_VARIANCE` (elevation_mapping_cupy's
1 m^2) unless the caller sets another: the map's default ceiling would take a pessimistic model's far
cells away and score it on its near cells only.

Report (JSON, NaN written as null)::

    {"scene": str, "frames": int, "seed": int, "width": int, "height": int,
     "reality": "reference" | "stereo", "preset": str | null (the stereo matcher's preset),
     "sim_effects": [{"name": str, "params": {...}}, ...], "cap": float,
     "map": {"length_m", "resolution_m", "visibility_cleanup", "follow", "fusion": {...}},
     "frames_digest": sha256 hex,
     "mappers": {name: {"rmse_m", "p95_abs_m", "nll", "coverage_1sigma", "coverage_2sigma",
                        "mean_sigma_m", "edge_rmse_m", "flat_rmse_m", "known_fraction", "ms_per_frame",
                        "median_abs_m", "mean_error_m", "flat_coverage_2sigma", "known_cells",
                        "edge_cells", "ms_per_frame_p95", "frames_digest", "model": {...}}, ...},
     "common": {"cells": int, "mappers": {name: {"rmse_m", "p95_abs_m", "nll", "coverage_1sigma",
                                                 "coverage_2sigma", "mean_sigma_m"}}},
     "matched": {"cells": int, "mappers": {name: {same keys as common}}},
     "render_ms_per_frame": float}

Units: metres, square metres for variances, milliseconds; coverages are fractions in [0, 1]; ``nll``
is the mean Gaussian negative log-likelihood of the true height under each cell's (height,
variance), in nats. ``frames_digest`` is a SHA-256 over every frame's depth, pose and pose covariance
as each mapper received them: equal for all mappers.

Recording (``rrd_path``; entity paths)::

    maps                        ViewCoordinates z up
    maps/truth/elevation        the true terrain over the final map's cells (mesh, coloured by height)
    maps/<mapper>/elevation     each final map, coloured by height (hidden at start)
    maps/<mapper>/error         each final map, coloured by its signed error (blue below, red above
                                the truth, +-ERROR_COLOR_RANGE_M)
    maps/<mapper>/trail         the camera's path
    errors/<mapper>             signed error image (map seen from above, +x up, +y left)
    zscores/<mapper>            |error| / sigma image (0 to 4)
    camera/depth                the depth frames (PNG-compressed)
    plots/<metric>/<mapper>     RMSE, 2-sigma coverage and mean sigma over the frames
    result                      the table
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass

import numpy as np

from noise_model.alternatives import make_variance_model
from noise_model.checks import check_positive_scalar
from noise_model.reporting import check_names
from noise_model.sim.effects import EFFECTS, Effect, make_effect

from ..map.elevation_map import ElevationMap
from ..frame import Frame
from ..fileio import check_outputs, json_ready
from ..map.fusion import FusionParams
from ..mapper import Camera, Mapper
from ..pipeline import MappingConfig, map_error

__all__ = ["MAPPERS", "SCENES", "REALITIES", "DEFAULT_CAP", "COMPARE_MAX_VARIANCE", "REPORT_KEYS", "run_compare",
           "render_walk", "parse_effects", "effects_help", "parse_mappers", "format_table", "MapperSpec",
           "mapper_specs", "json_ready", "frames_digest", "most_confident"]

#: Mappers in report order.
MAPPERS = ("paper", "constant", "quadratic", "anybotics_d435", "paper_capped")
#: Scenes of a comparison (those of :class:`elevmap.sources.simulated.SimulatedWalk`).
SCENES = ("stairs", "boxes", "slope", "rough", "demo")
#: Simulated realities: the reference simulation of the paper's model, or the physical D435.
REALITIES = ("reference", "stereo")
#: The per-frame information cap of ``paper_capped``: a frame adds to a cell at most the information of
#: n_eff = 1 average point. Why 1: (a) physics: with the D435's error correlation of about 3 px at
#: 848 x 480, a 4 cm cell at 1 m holds about one independent sample per frame (docs/depth-effects.md,
#: E9); (b) precedent: elevation_mapping_cupy averages a frame's points per cell, so that N points
#: reduce the variance as much as one; (c) in comparisons the 2-sigma coverage rises as the cap goes
#: down to 1 while the RMSE barely moves (docs/calibration.md). The map's own default is no cap
#: (``FusionParams.max_points_per_frame = None``): its spreads measure the excess scatter the cap only
#: guesses, and the cap pushes 1-sigma coverage out of its band (docs/calibration.md).
DEFAULT_CAP = 1.0
#: The variance ceiling ``FusionParams.max_variance`` [m^2] of every mapper of a comparison, unless the
#: caller sets it: elevation_mapping_cupy's own (its ``parameter.py`` default). The map's default
#: (0.04 m^2, sigma 0.2 m) is a consumer's "no height rather than one uncertain by more than 20 cm"; in a
#: comparison it would decide the scores instead of the noise models, since each mapper is scored over
#: its own known cells and a model that states large variances loses its far cells to the ceiling
#: (quadratic's 0.05 z^2 per point exceeds 0.04 m^2 beyond 0.9 m, so it would be scored on its near cells
#: only), while the paper mapper's own scores barely move (docs/calibration.md).
COMPARE_MAX_VARIANCE = 1.0
#: The keys every mapper's entry of the report has (the issue's schema).
REPORT_KEYS = ("rmse_m", "p95_abs_m", "nll", "coverage_1sigma", "coverage_2sigma", "mean_sigma_m", "edge_rmse_m",
               "flat_rmse_m", "known_fraction", "ms_per_frame")
#: Colour range of the signed error meshes and images [m].
ERROR_COLOR_RANGE_M = 0.10
#: Colour range of the z-score images |error| / sigma.
ZSCORE_COLOR_RANGE = (0.0, 4.0)


@dataclass(frozen=True)
class MapperSpec:
    """How one mapper of a comparison is built.

    Attributes
    ----------
    name : str
    variance_model : callable or None
        The camera's ``variance_model`` hook (None: the paper's model, numba kernel).
    fusion : FusionParams
    description : dict
        What the report says about it (model name, parameters, source, cap).
    """

    name: str
    variance_model: object
    fusion: FusionParams
    description: dict


def mapper_specs(names=MAPPERS, cap: float = DEFAULT_CAP, fusion: FusionParams | None = None) -> list[MapperSpec]:
    """The mappers ``names`` with the map's fusion parameters ``fusion`` (``paper_capped`` adds ``cap``).

    Raises
    ------
    ValueError
        Unknown mapper name, or a cap below 1.
    """
    fusion = FusionParams() if fusion is None else fusion
    if not isinstance(fusion, FusionParams):
        raise ValueError("fusion must be an elevmap.FusionParams")
    cap = _check_cap(cap)
    out = []
    for name in names:
        if name not in MAPPERS:
            raise ValueError(f"unknown mapper {name!r}; mappers: {', '.join(MAPPERS)}")
        if name in ("paper", "paper_capped"):
            f = fusion if name == "paper" else _replace(fusion, max_points_per_frame=cap)
            desc = {"name": "paper", "source": "Ahn et al. 2019, full covariance propagation (noise_model kernel)",
                    "params": {}, "max_points_per_frame": f.max_points_per_frame}
            out.append(MapperSpec(name, None, f, desc))
        else:
            vm = make_variance_model(name)
            desc = {"name": vm.name, "source": vm.source, "params": dict(vm.params),
                    "max_points_per_frame": fusion.max_points_per_frame}
            out.append(MapperSpec(name, vm, fusion, desc))
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
# arguments
# ---------------------------------------------------------------------------------------------
def _number(text: str, where: str):
    t = text.strip()
    if t.lower() in ("none", "null"):
        return None
    try:
        v = float(t)
    except ValueError:
        raise ValueError(f"{where}: {text!r} is not a number") from None
    return v


def effects_help() -> str:
    """One line per effect of :data:`noise_model.sim.effects.EFFECTS`: its name and default parameters."""
    import inspect

    lines = []
    width = max(len(n) for n in EFFECTS)
    for name, factory in EFFECTS.items():
        params = [f"{k}={v.default!r}" if v.default is not None else f"{k}=..." for k, v in
                  inspect.signature(factory).parameters.items()
                  if k not in ("model",) and v.default is not inspect.Parameter.empty]
        lines.append(f"  {name:{width}s}  {', '.join(params)}")
    return "\n".join(lines)


def parse_effects(spec) -> list[Effect]:
    """Effects from a ``--sim-effects`` string or a sequence of effects / names.

    The string is a comma-separated list of effect names (:data:`noise_model.sim.effects.EFFECTS`), each
    optionally followed by ``:key=value`` overrides of its defaults, several separated by ``:`` or by
    commas: ``correlated_noise``, ``correlated_noise:length_px=5:sigma_z_fraction=0.5,depth_bias``,
    ``correlated_noise:length_px=5,sigma_z_fraction=0.5``. ``none`` or an empty string: no effect.
    A path ending in ``.json``: the effects of a gap report (``elevmap gap --json``), with their
    fitted parameters, in the simulator's canonical order (their pixel parameters are in the pixels
    of the diagnosed stream: simulate the walk at that resolution).

    Returns
    -------
    list of Effect

    Raises
    ------
    ValueError
        Unknown effect or parameter, malformed override, bad value.
    """
    if spec is None:
        return []
    if isinstance(spec, Effect):
        return [spec]
    if not isinstance(spec, str):
        out = []
        for item in spec:
            if isinstance(item, Effect):
                out.append(item)
            elif isinstance(item, str):
                out += parse_effects(item)
            else:
                raise ValueError(f"sim effects must be names or noise_model.sim.effects.Effect objects, got {item!r}")
        return out
    text = spec.strip()
    if text.lower() in ("", "none"):
        return []
    if text.lower().endswith(".json"):          # the effects a gap diagnosis selected and fitted
        from noise_model.sim.effects import canonical_order, effects_from_report

        return canonical_order(effects_from_report(text))
    entries: list[tuple[str, dict]] = []
    for token in (t.strip() for t in text.split(",")):
        if not token:
            raise ValueError(f"--sim-effects {spec!r}: empty entry")
        parts = [p.strip() for p in token.split(":")]
        if "=" in parts[0]:
            if not entries:
                raise ValueError(f"--sim-effects {spec!r}: {token!r} has no effect name before it")
            name, overrides = entries[-1][0], parts
        else:
            name, overrides = parts[0], parts[1:]
            if name not in EFFECTS:
                raise ValueError(f"unknown effect {name!r}; effects: {', '.join(EFFECTS)}")
            entries.append((name, {}))
        for kv in overrides:
            if kv.count("=") != 1 or not kv.split("=")[0].strip():
                raise ValueError(f"--sim-effects: override {kv!r} of {name} must be key=value")
            k, v = (s.strip() for s in kv.split("="))
            entries[-1][1][k] = _number(v, f"{name}:{k}")
    return [make_effect(name, **params) for name, params in entries]


def parse_mappers(spec) -> tuple[str, ...]:
    """Mapper names from a comma-separated string or a sequence (None: all of :data:`MAPPERS`)."""
    if spec is None:
        return MAPPERS
    return tuple(check_names(spec, "--mappers", MAPPERS, "mapper"))


# ---------------------------------------------------------------------------------------------
# frames
# ---------------------------------------------------------------------------------------------
def render_walk(scene: str = "stairs", n_frames: int | None = None, seed: int = 0, effects=(),
                width: int = 424, height: int = 240, show_progress: bool = False, reality: str = "reference",
                preset: str = "default"):
    """Render a simulated walk once.

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

    Returns
    -------
    frames : list of Frame
    walk : SimulatedWalk
        Its ``truth_height(xy)`` gives the true terrain [m].
    """
    from tqdm import tqdm

    from ..sources.simulated import SimulatedWalk

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
    effects = list(effects or ())
    for e in effects:
        if not callable(e):
            raise ValueError(f"effects must be callables (noise_model.sim.effects), got {e!r}")
    _check_reality(reality, effects)
    walk = SimulatedWalk(scene, n_frames=None if n_frames is None else int(n_frames), seed=int(seed),
                         width=int(width), height=int(height), effects=effects or None, sensor=reality,
                         preset=preset)
    frames = list(tqdm(walk, total=len(walk), desc="rendering", unit="frame", disable=not show_progress))
    if n_frames is not None and len(frames) < n_frames:
        raise ValueError(f"the {scene} walk has only {len(frames)} frames, asked for {n_frames}")
    return frames, walk


def _check_reality(reality, effects) -> None:
    if reality not in REALITIES:
        raise ValueError(f"unknown reality {reality!r}; realities: {', '.join(REALITIES)}")
    if reality == "stereo" and effects:
        raise ValueError("the stereo reality makes its own noise: it takes no sim effects")


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
# scoring
# ---------------------------------------------------------------------------------------------
def _cell_scores(h, v, truth, mask) -> dict:
    keys = ("rmse_m", "p95_abs_m", "nll", "coverage_1sigma", "coverage_2sigma", "mean_sigma_m")
    if not mask.any():
        return {k: math.nan for k in keys}
    err = (h - truth)[mask]
    var = v[mask]
    z = np.abs(err) / np.sqrt(var)
    return {"rmse_m": float(np.sqrt(np.mean(err ** 2))), "p95_abs_m": float(np.percentile(np.abs(err), 95)),
            "nll": float(np.mean(0.5 * np.log(2 * np.pi * var) + 0.5 * err ** 2 / var)),
            "coverage_1sigma": float(np.mean(z <= 1.0)), "coverage_2sigma": float(np.mean(z <= 2.0)),
            "mean_sigma_m": float(np.mean(np.sqrt(var)))}


def _truth_grid(emap: ElevationMap, truth) -> np.ndarray:
    xs, ys = emap.cell_centres()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    return np.asarray(truth(np.column_stack([X.ravel(), Y.ravel()])), dtype=np.float64).reshape(X.shape)


def _score(emap: ElevationMap, truth, times) -> dict:
    err = map_error(emap, truth)
    var = emap.layer("variance")
    known = emap.is_known()
    t = np.asarray(times, dtype=np.float64) if len(times) else np.array([math.nan])
    out = {"rmse_m": err["rmse_m"], "p95_abs_m": err["p95_abs_m"], "nll": err["nll"],
           "coverage_1sigma": err["coverage_1sigma"], "coverage_2sigma": err["coverage_2sigma"],
           "mean_sigma_m": float(np.mean(np.sqrt(var[known]))) if known.any() else math.nan,
           "edge_rmse_m": err["edge_rmse_m"], "flat_rmse_m": err["flat_rmse_m"],
           "known_fraction": emap.known_fraction(), "ms_per_frame": float(np.median(t)),
           "median_abs_m": err["median_abs_m"], "mean_error_m": err["mean_error_m"],
           "flat_coverage_2sigma": err["flat_coverage_2sigma"], "known_cells": err["known_cells"],
           "edge_cells": err["edge_cells"], "ms_per_frame_p95": float(np.percentile(t, 95))}
    return out


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


def _map_frames(frames, specs, config: MappingConfig, *, nthreads=None, show_progress=False, on_frame=None):
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
                                             depth_scale=frame.depth_scale, variance_model=run.spec.variance_model))
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
                preset: str = "default") -> dict:
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
        Effects added to the simulated reality (see :func:`parse_effects`).
    mappers : str or sequence of str, optional
        Subset of :data:`MAPPERS` (default all, in that order).
    cap : float
        The information cap n_eff of ``paper_capped`` (>= 1).
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
    reality : {"reference", "stereo"}
        What makes the walk's depth: the reference simulation of the paper's model (default), or the
        physical D435 (no ``sim_effects`` then).
    preset : str
        Matcher preset of the physical D435 ("default", "high_accuracy").

    Returns
    -------
    dict
        The report (module docstring); NaN where a score is undefined (e.g. no step edges).
    """
    config = MappingConfig() if config is None else config
    if not isinstance(config, MappingConfig):
        raise ValueError("config must be an elevmap.pipeline.MappingConfig")
    if max_variance is not None:
        config = _replace(config, fusion=_replace(config.fusion, max_variance=_check_max_variance(max_variance)))
    names = parse_mappers(mappers)
    specs = mapper_specs(names, cap, config.fusion)
    effects = parse_effects(sim_effects)
    _check_reality(reality, effects)
    if scene not in SCENES:
        raise ValueError(f"unknown scene {scene!r}; scenes: {', '.join(SCENES)}")
    check_outputs({"rrd_path": rrd_path}, overwrite=True)       # the command line has refused existing files
    t0 = time.perf_counter()
    frames, walk = render_walk(scene, n_frames, seed, effects, width, height, show_progress, reality, preset)
    render_ms = 1e3 * (time.perf_counter() - t0) / max(1, len(frames))
    truth = _CachedTruth(walk.truth_height)
    digest = frames_digest(frames)
    logger = _CompareLogger(rrd_path, names, frames, show_progress) if rrd_path is not None else None
    results, maps = {}, {}
    try:
        on_frame = None if logger is None else logger.frame_callback(truth)
        runs = _map_frames(frames, specs, config, nthreads=nthreads, show_progress=show_progress, on_frame=on_frame)
        unchanged = frames_digest(frames) == digest
        for run in runs:
            got = run.digest.hexdigest()
            if got != digest or not unchanged:
                raise RuntimeError(f"mapper {run.spec.name!r} did not get the rendered frames unchanged")
            score = _score(run.emap, truth, run.times)
            score["frames_digest"] = got
            score["model"] = run.spec.description
            results[run.spec.name] = score
            maps[run.spec.name] = run.emap
        common = _common_scores(maps, truth)
        matched = _matched_scores(maps, truth)
        report = {"scene": scene, "frames": len(frames), "seed": int(seed), "width": int(width),
                  "height": int(height), "reality": reality, "preset": preset if reality == "stereo" else None,
                  "sim_effects": [{"name": e.name, "params": dict(e.params)} for e in effects],
                  "cap": _check_cap(cap),
                  "map": {"length_m": config.length_m, "resolution_m": config.resolution_m,
                          "visibility_cleanup": config.visibility_cleanup, "follow": config.follow,
                          "fusion": {k: getattr(config.fusion, k) for k in config.fusion.__dataclass_fields__}},
                  "frames_digest": digest, "mappers": results, "common": common,
                  "matched": matched,
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


def _common_scores(maps: dict, truth) -> dict:
    if not maps:
        return {"cells": 0, "mappers": {}}
    first = next(iter(maps.values()))
    xs, ys = first.cell_centres()
    for name, m in maps.items():
        a, b = m.cell_centres()
        if not (np.array_equal(a, xs) and np.array_equal(b, ys)):
            raise RuntimeError(f"map of {name!r} is not on the same cells as the others")
    tr = _truth_grid(first, truth)
    mask = np.ones(tr.shape, dtype=bool)
    for m in maps.values():
        mask &= m.is_known()
    return {"cells": int(mask.sum()),
            "mappers": {name: _cell_scores(m.known_layer("elevation"), m.known_layer("variance"), tr, mask)
                        for name, m in maps.items()}}


def most_confident(variance, known, n: int) -> np.ndarray:
    """Mask of the ``n`` known cells of smallest variance (ties: the lower flat index first).

    Parameters
    ----------
    variance : ndarray, shape (H, W) [m^2]
    known : ndarray of bool, shape (H, W)
    n : int
        0 <= n <= known.sum().

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    variance = np.asarray(variance, dtype=np.float64)
    known = np.asarray(known)
    if known.dtype != bool:
        raise ValueError(f"known must be a boolean mask, got dtype {known.dtype}")
    if variance.shape != known.shape:
        raise ValueError(f"variance {variance.shape} and known {known.shape} differ in shape")
    idx = np.flatnonzero(known)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 0 <= n <= idx.size:
        raise ValueError(f"n must be an integer in [0, {idx.size}] (the known cells), got {n!r}")
    if not np.all(np.isfinite(variance.ravel()[idx])):
        raise ValueError("variance must be finite in known cells")
    keep = idx[np.argsort(variance.ravel()[idx], kind="stable")[:n]]
    out = np.zeros(known.size, dtype=bool)
    out[keep] = True
    return out.reshape(known.shape)


def _matched_scores(maps: dict, truth) -> dict:
    """Scores at equal coverage: each mapper over its N most confident known cells (smallest variance),
    N the fewest known cells of any mapper. What a consumer gets who keeps the N cells its map trusts
    most; a model whose variances rank its cells by their error well scores better."""
    if not maps:
        return {"cells": 0, "mappers": {}}
    n = min(int(m.is_known().sum()) for m in maps.values())
    tr = _truth_grid(next(iter(maps.values())), truth)
    out = {}
    for name, m in maps.items():
        v = m.layer("variance")
        out[name] = _cell_scores(m.layer("elevation"), v, tr, most_confident(v, m.is_known(), n))
    return {"cells": n, "mappers": out}


# ---------------------------------------------------------------------------------------------
# output
# ---------------------------------------------------------------------------------------------
def _fmt(v, scale=1.0, digits=1):
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v * scale:.{digits}f}"


def format_table(report: dict) -> str:
    """The report as a plain-text table (mm, %, ms)."""
    eff = ", ".join(f"{e['name']}({', '.join(f'{k}={v:g}' for k, v in e['params'].items() if v is not None)})"
                    for e in report["sim_effects"]) or "none"
    reality = report.get("reality", "reference")
    if reality == "stereo":
        reality += f" (preset {report.get('preset')})"
    head = (f"scene {report['scene']}, {report['frames']} frames {report['width']}x{report['height']}, "
            f"seed {report['seed']}, reality {reality}, sim effects: {eff}, paper_capped cap {report['cap']:g}")
    cols = ("mapper", "RMSE", "p95|e|", "NLL", "cov1s", "cov2s", "mean s", "edge", "flat", "known", "ms/fr",
            "| common:", "RMSE", "NLL", "cov2s", "| matched:", "RMSE", "NLL", "cov2s")
    rows = []
    common = report.get("common", {}).get("mappers", {})
    matched = report.get("matched", {}).get("mappers", {})
    for name, m in report["mappers"].items():
        c, q = common.get(name, {}), matched.get(name, {})
        rows.append((name, _fmt(m["rmse_m"], 1e3), _fmt(m["p95_abs_m"], 1e3), _fmt(m["nll"], 1, 2),
                     _fmt(m["coverage_1sigma"], 100), _fmt(m["coverage_2sigma"], 100), _fmt(m["mean_sigma_m"], 1e3),
                     _fmt(m["edge_rmse_m"], 1e3), _fmt(m["flat_rmse_m"], 1e3), _fmt(m["known_fraction"], 100),
                     _fmt(m["ms_per_frame"], 1, 2), "|", _fmt(c.get("rmse_m"), 1e3), _fmt(c.get("nll"), 1, 2),
                     _fmt(c.get("coverage_2sigma"), 100), "|", _fmt(q.get("rmse_m"), 1e3), _fmt(q.get("nll"), 1, 2),
                     _fmt(q.get("coverage_2sigma"), 100)))
    widths = [max(len(str(r[k])) for r in rows + [cols]) for k in range(len(cols))]
    line = lambda r: "  ".join(str(x).ljust(w) if k == 0 else str(x).rjust(w)  # noqa: E731
                               for k, (x, w) in enumerate(zip(r, widths)))
    units = ("", "mm", "mm", "", "%", "%", "mm", "mm", "mm", "%", "ms", "", "mm", "", "%", "", "mm", "", "%")
    out = [head, line(cols), line(units)] + [line(r) for r in rows]
    out.append(f"common: the {report.get('common', {}).get('cells', 0)} cells known to every mapper; "
               f"matched: each mapper's {report.get('matched', {}).get('cells', 0)} most confident cells "
               "(the fewest any mapper knows); ideal coverage 68.3 % (1 sigma) and 95.4 % (2 sigma); "
               "NLL in nats (lower is better)")
    return "\n".join(out)


class _CompareLogger:
    """Everything a comparison sends to rerun (through elevmap.viz)."""

    def __init__(self, path, names, frames, show_progress):
        from .. import viz

        self.viz = viz
        self.names = list(names)
        self.recording = viz.open_recording(path, "elevmap_compare")
        self.rec = self.recording.__enter__()
        try:
            self._start(frames)
        except BaseException as exc:
            self.abort(exc)
            raise

    def _start(self, frames):
        viz = self.viz
        viz.log_world_frame(self.rec, "maps")
        for name in ["truth"] + self.names:
            viz.log_world_frame(self.rec, f"maps/{name}")
        f0 = frames[0]
        viz.log_camera(self.rec, "camera/depth", f0.K, f0.width, f0.height, static=True)
        self.trail = np.array([f.T_map_cam[:3, 3] for f in frames])
        for k, f in enumerate(frames):
            viz.set_time(self.rec, "frame", sequence=k)
            if f.depth.dtype == np.uint16:
                viz.log_depth_png(self.rec, "camera/depth", f.depth, meter=1.0 / f.depth_scale)
            else:
                viz.log_depth(self.rec, "camera/depth", f.depth)

    def frame_callback(self, truth):
        viz, rec = self.viz, self.rec

        def on_frame(name, k, emap):
            viz.set_time(rec, "frame", sequence=k)
            err = map_error(emap, truth)
            if err["known_cells"]:
                viz.log_scalar(rec, f"plots/rmse_m/{name}", err["rmse_m"])
                viz.log_scalar(rec, f"plots/coverage_2sigma/{name}", err["coverage_2sigma"])
                var = emap.known_layer("variance")
                viz.log_scalar(rec, f"plots/mean_sigma_m/{name}", float(np.nanmean(np.sqrt(var))))
        return on_frame

    def final(self, maps, truth, walk, report):
        viz, rec = self.viz, self.rec
        viz.set_time(rec, "frame", sequence=report["frames"] - 1)
        first = next(iter(maps.values()))
        xs, ys = first.cell_centres()
        tr = _truth_grid(first, truth)
        lo, hi = viz.robust_range(tr)
        viz.log_height_mesh(rec, "maps/truth/elevation", xs, ys, tr, viz.colormap(tr, lo, hi))
        viz.log_trail(rec, "maps/truth/trail", self.trail)
        e = ERROR_COLOR_RANGE_M
        for name, emap in maps.items():
            h, v = emap.known_layer("elevation"), emap.known_layer("variance")
            err = h - tr
            viz.log_height_mesh(rec, f"maps/{name}/elevation", xs, ys, h, viz.colormap(h, lo, hi))
            viz.log_height_mesh(rec, f"maps/{name}/error", xs, ys, h, viz.colormap(err, -e, e))
            viz.log_trail(rec, f"maps/{name}/trail", self.trail)
            viz.log_rgb_image(rec, f"errors/{name}", viz.map_image(viz.colormap(err, -e, e)))
            with np.errstate(invalid="ignore"):
                zs = np.abs(err) / np.sqrt(v)
            viz.log_rgb_image(rec, f"zscores/{name}", viz.map_image(viz.colormap(zs, *ZSCORE_COLOR_RANGE)))
        table = format_table(json_ready(report))
        notes = (f"# elevmap compare\n\n```\n{table}\n```\n\nMaps: `maps/<mapper>/error` is each final map coloured "
                 f"by its signed error (blue: below the truth, green: right, red: above; +-{e * 100:.0f} cm); "
                 f"`elevation` (hidden) by height. Tabs: signed error images and |error|/sigma images "
                 f"(0 to 4; calibrated maps are mostly below 2).")
        viz.log_text(rec, "result", notes)
        cx, cy = first.centre_xy
        names = ["truth"] + self.names
        bp = viz.compare_blueprint(
            [f"maps/{n}" for n in names],
            image_grids=[("errors", [f"errors/{n}" for n in self.names]),
                         ("z-scores", [f"zscores/{n}" for n in self.names])],
            time_series_entities=["plots/rmse_m", "plots/coverage_2sigma", "plots/mean_sigma_m"],
            text_entities=["result"], depth_entities=["camera/depth"], timeline="frame",
            hidden_entities=[f"maps/{n}/elevation" for n in self.names],
            eye_position=(cx - 3.0, cy - 3.5, 3.5), eye_look_target=(cx + 0.5, cy, 0.0))
        rec.send_blueprint(bp)

    def abort(self, exc):
        self.recording.__exit__(type(exc), exc, exc.__traceback__)

    def close(self):
        self.recording.__exit__(None, None, None)
