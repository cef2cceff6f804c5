"""The diagnosis on real captures: held-out split, simulation and fits with common random numbers, the report.

:func:`diagnose` runs the whole sim-to-real gap diagnosis on captures held in memory
(:class:`noise_model.analysis.capture_data.CaptureData`, e.g. read from a capture set, format
``d435-captures/1``, see docs/capture-set-format.md):

1. **Simulate** every real capture with the reference simulation of Ahn et al.'s model
   (:func:`noise_model.analysis.capture_data.simulate_capture`, as many frames as the real capture;
   capture ``i`` always draws from ``default_rng([seed, crc32(id)])``, in every model: common random
   numbers, :func:`capture_rng`).
2. **Compare** real and simulated per statistic and stratum (:mod:`.sums`, :mod:`.floor`), each
   difference normalised by the real-vs-real noise floor.
3. **Where**: strata and statistics ranked by gap.
4. **Which**: forward selection over the effects library (:mod:`.selection`): each candidate is fitted
   on the *fit* captures (:func:`noise_model.analysis.effect_fits.fit_effect`, :class:`EffectFitter`), the one
   that shrinks the fit gap most is added if it shrinks the *held-out* gap significantly; repeated while
   the remaining gap is significant; then each selected effect is removed again (ablation).
5. **How far**: the shrink on held-out captures only (whole captures, :func:`split_captures`: given
   ids, or ``auto``: the middle third of the distances of each target kind, all angles), what is left
   and where.

The result is the JSON-ready report of format ``d435-gap/1`` (:data:`FORMAT`). Also here: the
self-test's pseudo-real captures (:func:`selftest_geometries`, :func:`selftest_cases`,
:func:`selftest_case`: the reference simulation plus known effects at random parameters, which the
diagnosis must find blind) and :func:`plane_geometry`, which turns a plane fitted to a region of a real
frame into a capture's geometry. Files, progress bars and recordings are the command's
(``elevmap gap``).
"""

from __future__ import annotations

import dataclasses
import math
import time
import zlib
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from ...d435 import D435, SensorModel
from ...reporting import check_names, json_ready
from ...sim.effects import EFFECTS, ORDER, canonical_order, draw_params, make_effect
from ..capture_data import CaptureData, CaptureGeometry, check_captures, simulate_capture, units_to_depth_m
from ..effect_fits import NEEDS, fit_effect, usable_captures, within_tolerance
from ..planes import PlaneFit
from .floor import MIN_FLOOR, Z_FLOOR
from .selection import Diagnosis, SelectionConfig, model_key
from .strata import Binning, GapCapture, make_gap_capture
from .sums import STAT_UNITS, FrameSampling, capture_sums

__all__ = ["FORMAT", "MAX_WHERE", "SELFTEST_PAIR", "SELFTEST_STATIC_PAIR", "SELFTEST_UNSEEN", "MEASURED_ONLY",
           "parse_effect_names", "auto_heldout", "split_captures", "capture_rng", "CaptureSimulator", "EffectFitter",
           "gap_capture_of", "diagnose", "plane_geometry", "selftest_geometries", "selftest_cases", "selftest_case",
           "split_by_depth"]

#: The report's format.
FORMAT = "d435-gap/1"
#: Most ``where`` / ``where_unexplained`` entries written to the report (ranked; the rest are counted).
MAX_WHERE = 300
#: The two effects of the selftest's two-effect case.
SELFTEST_PAIR = ("invalid_band", "correlated_noise")
#: Effects whose fit compares against the true distance: not fitted on captures whose geometry was fitted
#: to their own frames (capture-set ``geometry: "fitted"``), where a plane fit absorbs bias and scale.
MEASURED_ONLY = ("depth_bias",)
#: The selftest's static-and-temporal case: a static field and a per-frame correlated field at once, which
#: the diagnosis must tell apart (both selected, both fitted within tolerance) from the captures' few frames.
SELFTEST_STATIC_PAIR = ("static_noise", "correlated_noise")
#: Effects the self-test does not hide unless named (``--effects``): the gap statistics cannot see them.
#: ``frame_offset`` moves every pixel of a frame alike: it cancels in the spatial statistics (taken about
#: the frame's mean) and adds to the temporal standard deviation and the bias only what the frames' few
#: offset draws give, which differs between two halves of the real frames as much as between real and
#: reference, so the gap stays within the real-vs-real floor. It remains a candidate in every case, and
#: its fit is checked on its own (``tests/sim/test_effects.py``).
SELFTEST_UNSEEN = ("frame_offset",)


# ---------------------------------------------------------------------------------------------
# arguments and the held-out split
# ---------------------------------------------------------------------------------------------
def parse_effect_names(effects) -> list[str]:
    """Candidate effect names: None / ``"all"`` = every effect of the library (canonical order), else a
    comma-separated string or a sequence of names of :data:`noise_model.sim.effects.EFFECTS`."""
    if effects is None or (isinstance(effects, str) and effects.strip().lower() in ("", "all")):
        return list(ORDER) + [n for n in EFFECTS if n not in ORDER]
    return check_names(effects, "--effects", list(EFFECTS), "effect")


def _incidence_deg(target: dict) -> float:
    """Incidence angle [deg] of a capture-set target on the optical axis: acos |cos(yaw) cos(pitch)|."""
    yaw, pitch = math.radians(float(target.get("yaw_deg") or 0.0)), math.radians(float(target.get("pitch_deg") or 0.0))
    return math.degrees(math.acos(min(1.0, abs(math.cos(yaw) * math.cos(pitch)))))


def _kind_of(g: CaptureGeometry) -> str:
    """The target kind of the held-out blocks: ``wall``, ``board`` or ``board+background``."""
    if g.kind == "wall":
        return "wall"
    return "board+background" if g.background_m is not None else "board"


def auto_heldout(geometries: Sequence[CaptureGeometry], distances: dict | None = None) -> tuple[list[str], str]:
    """The ``auto`` held-out block: per target kind, the captures at the middle third of that kind's
    distinct distances (all angles); with a single distance, the middle third of its angles.

    Returns
    -------
    ids : list of str
    rule : str
        The block in words (for the report).
    """
    out, parts = [], []
    kinds: dict = {}
    for g in geometries:
        kinds.setdefault(_kind_of(g), []).append(g)
    for kind, gs in kinds.items():
        if len(gs) < 2:
            continue
        dist = {g.id: (distances or {}).get(g.id, g.distance_m) for g in gs}
        ds = sorted({round(dist[g.id], 6) for g in gs})
        if len(ds) >= 2:
            k = max(1, int(round(len(ds) / 3)))
            block = ds[(len(ds) - k) // 2:(len(ds) - k) // 2 + k]
            ids = [g.id for g in gs if round(dist[g.id], 6) in block]
            parts.append(f"{kind}: distances {block[0]:g}-{block[-1]:g} m (all angles)")
        else:
            angs = sorted({round(_incidence_deg(g.target), 6) for g in gs})
            if len(angs) < 2:
                continue
            k = max(1, int(round(len(angs) / 3)))
            block = angs[(len(angs) - k) // 2:(len(angs) - k) // 2 + k]
            ids = [g.id for g in gs if round(_incidence_deg(g.target), 6) in block]
            parts.append(f"{kind}: angles {block[0]:g}-{block[-1]:g} deg at {ds[0]:g} m")
        if len(ids) < len(gs):
            out += ids
    return out, "; ".join(parts) if parts else "none (too few captures to hold any out)"


def split_captures(geometries: Sequence[CaptureGeometry], heldout="auto", distances: dict | None = None):
    """Fit and held-out captures (whole captures).

    Parameters
    ----------
    geometries : sequence of CaptureGeometry
    heldout : ``"auto"`` (or None: :func:`auto_heldout`), ``"none"``, a comma-separated string of ids,
        or a sequence of ids
    distances : dict, optional
        Capture id -> the distance [m] the ``auto`` block goes by (default: the target's).

    Returns
    -------
    fit_ids, heldout_ids : list of str
    rule : str

    Raises
    ------
    ValueError
        Unknown id, or every capture held out.
    """
    ids = [g.id for g in geometries]
    if heldout is None or (isinstance(heldout, str) and heldout.strip().lower() == "auto"):
        held, rule = auto_heldout(geometries, distances)
    elif isinstance(heldout, str) and heldout.strip().lower() in ("", "none"):
        held, rule = [], "none"
    else:
        held = check_names(heldout, "--heldout", ids, "capture")
        rule = "given: " + ", ".join(held)
    hs = set(held)
    fit = [i for i in ids if i not in hs]
    if not fit:
        raise ValueError("every capture is held out: nothing is left to fit the effects on")
    return fit, [i for i in ids if i in hs], rule


# ---------------------------------------------------------------------------------------------
# simulation and fits with common random numbers
# ---------------------------------------------------------------------------------------------
def capture_rng(seed: int, capture_id: str) -> np.random.Generator:
    """The generator of a capture's simulation in every model (and in the fits' base simulations)."""
    return np.random.default_rng([int(seed), zlib.crc32(capture_id.encode("utf-8"))])


def _simulate_depth(geometry: CaptureGeometry, n_frames: int, seed: int, model: SensorModel, objs) -> np.ndarray:
    """One capture's simulation as metric depth (F, H, W) [m], NaN = no data, drawn from :func:`capture_rng`."""
    units = simulate_capture(geometry, int(n_frames), capture_rng(seed, geometry.id), model, objs)
    return units_to_depth_m(units, geometry.depth_scale)


def _simulate_sums(geometry: CaptureGeometry, cap: GapCapture, n_frames: int, seed: int, model: SensorModel,
                   effects, sampling: FrameSampling) -> np.ndarray:
    """A worker's task: one capture simulated with ``effects`` and reduced to its
    :func:`noise_model.analysis.diagnosis.capture_sums` (only these sums travel back, not the frames)."""
    objs = canonical_order([make_effect(n, **p) for n, p in effects])
    return capture_sums(cap, _simulate_depth(geometry, n_frames, seed, model, objs), sampling)


def _simulate_units(geometry: CaptureGeometry, n_frames: int, seed: int, model: SensorModel, effects) -> np.ndarray:
    """A worker's task: one capture's simulation with ``effects`` in depth units (uint16 (F, H, W))."""
    objs = canonical_order([make_effect(n, **p) for n, p in effects])
    return simulate_capture(geometry, int(n_frames), capture_rng(seed, geometry.id), model, objs)


def _worker_init() -> None:
    """A simulation worker uses one numba thread: the processes, not the threads, share the cores."""
    import numba

    numba.set_num_threads(1)


class CaptureSimulator:
    """``simulate(ids, effects, n_frames) -> {id: depth_m}``: the reference simulation plus effects.

    Effects are (name, params) pairs, made with :func:`noise_model.sim.effects.make_effect` and applied in
    :func:`noise_model.sim.effects.canonical_order`; capture ``id`` draws from :func:`capture_rng`, the
    same generator in every model and in :func:`noise_model.analysis.effect_fits.fit_effect`'s base simulations.

    :meth:`sums` simulates captures and reduces each to its statistics' sums, in ``jobs`` worker processes when
    ``jobs`` > 1 (one capture per task; :meth:`submit` starts them without waiting). A capture's draws depend
    only on the seed and its id, never on the process or the order, so the sums are the same for any ``jobs``.
    Workers are started on first use (``spawn``: numba's thread pools are not safe to fork) and stopped by
    :meth:`close` (or ``with``).

    Parameters
    ----------
    geometries : dict
        Capture id -> CaptureGeometry.
    model : SensorModel
    seed : int
    jobs : int
        Worker processes of :meth:`sums` (1: in this process).
    """

    def __init__(self, geometries: dict, model: SensorModel = D435, seed: int = 0, jobs: int = 1):
        if isinstance(jobs, bool) or not isinstance(jobs, (int, np.integer)) or int(jobs) < 1:
            raise ValueError(f"jobs must be an integer >= 1, got {jobs!r}")
        self.geometries, self.model, self.seed, self.jobs = geometries, model, int(seed), int(jobs)
        self._pool = None

    def __call__(self, ids, effects, n_frames: int) -> dict:
        objs = canonical_order([make_effect(n, **p) for n, p in effects])
        return {i: _simulate_depth(self.geometries[i], n_frames, self.seed, self.model, objs) for i in ids}

    def sums(self, ids, effects, n_frames: int, captures: dict, sampling: FrameSampling) -> dict:
        """``{id: capture_sums(captures[id], simulation of id, sampling)}`` for the captures ``ids``.

        Parameters
        ----------
        ids : sequence of str
        effects : list of (str, dict)
        n_frames : int
        captures : dict
            Capture id -> GapCapture.
        sampling : FrameSampling
            Rows of frame weights for ``n_frames`` frames.
        """
        ids = list(ids)
        if self.jobs <= 1 or len(ids) < 2:
            objs = canonical_order([make_effect(n, **p) for n, p in effects])
            return {i: capture_sums(captures[i], _simulate_depth(self.geometries[i], n_frames, self.seed,
                                                                 self.model, objs), sampling) for i in ids}
        return {i: f.result() for i, f in self.submit(ids, effects, n_frames, captures, sampling).items()}

    def submit(self, ids, effects, n_frames: int, captures: dict, sampling: FrameSampling) -> dict:
        """:meth:`sums` without waiting: ``{id: future}`` whose ``result()`` is the capture's sums (worker
        processes are started here; with ``jobs`` = 1 there are none, and this returns ``{}``)."""
        if self.jobs <= 1:
            return {}
        pool = self._executor()
        effects = [(n, dict(p)) for n, p in effects]
        # the geometry travels without its render cache (the worker renders it again, to the same values)
        return {i: pool.submit(_simulate_sums, dataclasses.replace(self.geometries[i]), captures[i],
                               int(n_frames), self.seed, self.model, effects, sampling) for i in ids}

    def _executor(self):
        """The worker processes, started on first use."""
        if self._pool is None:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            self._pool = ProcessPoolExecutor(max_workers=self.jobs, mp_context=mp.get_context("spawn"),
                                             initializer=_worker_init)
        return self._pool

    def submit_units(self, captures: Sequence[CaptureData], effects) -> dict:
        """``{id: future}`` of each capture's simulation in depth units (uint16 (F, H, W), as many frames as
        the capture has), in the workers; ``{}`` with ``jobs`` = 1."""
        if self.jobs <= 1:
            return {}
        pool = self._executor()
        effects = [(n, dict(p)) for n, p in effects]
        return {c.id: pool.submit(_simulate_units, dataclasses.replace(c.geometry), c.n_frames, self.seed,
                                  self.model, effects) for c in captures}

    def close(self) -> None:
        """Stop the worker processes (if any were started)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _DepthOnAccess(Mapping):
    """Capture id -> its metric frames (:attr:`CaptureData.depth_m`), made on each access: the
    :class:`Diagnosis` reads one capture at a time, so the frames of every capture in metres are never in
    memory together (the captures keep their depth units)."""

    def __init__(self, captures: Sequence[CaptureData]):
        self._by_id = {c.id: c for c in captures}

    def __getitem__(self, capture_id):
        return self._by_id[capture_id].depth_m

    def __iter__(self):
        return iter(self._by_id)

    def __len__(self) -> int:
        return len(self._by_id)


class _KeysAsked(dict):
    """A cache that claims to hold every key and records the keys it is asked for, in order: run through
    :func:`noise_model.analysis.effect_fits._common._base_sims`, it names the cache entries of the base
    simulations without simulating anything."""

    def __init__(self):
        super().__init__()
        self.asked: list = []

    def __contains__(self, key) -> bool:
        self.asked.append(key)
        return True

    def __getitem__(self, key):
        return None


class EffectFitter:
    """``fit(name, base_effects) -> params`` on the fit captures (base simulations cached per base model).

    With a ``simulator`` that has worker processes (:class:`CaptureSimulator`, ``jobs`` > 1), the base
    simulations of a new base model are run in its workers and put in the fits' cache under the keys
    :func:`noise_model.analysis.effect_fits.fit_effect` looks them up by (the same frames: each capture's
    draws depend on the seed and its id only; tested against the fits' own simulations).
    """

    def __init__(self, fit_real: Sequence[CaptureData], model: SensorModel = D435, seed: int = 0,
                 rois: dict | None = None, simulator: CaptureSimulator | None = None):
        self.real, self.model, self.seed = list(fit_real), model, int(seed)
        ids = {c.id for c in self.real}
        # the fits see only each capture's region of interest, as the statistics do
        self.rois = None if not rois else {k: v for k, v in rois.items() if k in ids}
        self.simulator = simulator
        self.n_prefilled = 0                         # base simulations made in the simulator's workers
        self._cache: dict = {}
        self._base_key = None

    def _prefill(self, base_effects) -> None:
        """The base simulations of every fit capture, simulated in the simulator's workers, in the cache."""
        sim = self.simulator
        if sim is None or sim.jobs <= 1 or len(self.real) < 2:
            return
        from ..effect_fits._common import _base_sims

        probe = _KeysAsked()
        _base_sims(self.real, self.model, [make_effect(n, **p) for n, p in base_effects], self.seed, probe)
        if len(probe.asked) != len(self.real) or len(set(probe.asked)) != len(self.real):
            return                                   # not one entry per capture: leave the fits to simulate
        futs = sim.submit_units(self.real, base_effects)
        for c, key in zip(self.real, probe.asked):
            self._cache[key] = CaptureData.from_units(c.geometry, futs[c.id].result())
        self.n_prefilled += len(self.real)

    def __call__(self, name: str, base_effects) -> dict:
        key = model_key(base_effects)
        if key != self._base_key:                 # a new base model: drop the old base simulations
            self._cache, self._base_key = {}, key
            self._prefill(base_effects)
        base = [make_effect(n, **p) for n, p in base_effects]
        try:
            params = fit_effect(name, self.real, self.model, base, seed=self.seed, cache=self._cache,
                                  rois=self.rois)
        except (ArithmeticError, np.linalg.LinAlgError, IndexError) as exc:   # a fit that cannot cope
            raise ValueError(f"fit of {name} failed on these captures ({type(exc).__name__}: {exc})") from exc
        return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in params.items()}


def gap_capture_of(data: CaptureData | CaptureGeometry, model: SensorModel = D435, roi=None,
                   distance_m: float | None = None, kind: str | None = None,
                   angle_deg: float | None = None) -> GapCapture:
    """The :class:`noise_model.analysis.diagnosis.GapCapture` of a capture's geometry (nominal render, regions)."""
    g = getattr(data, "geometry", data)
    z, th = g.render()
    return make_gap_capture(g.id, z, th, g.regions(model=model), g.K, g.baseline_m,
                            g.distance_m if distance_m is None else distance_m,
                            _incidence_deg(g.target) if angle_deg is None else angle_deg,
                            kind or _kind_of(g), model, roi)


def split_by_depth(captures: Sequence[CaptureData], edges_m: Sequence[float], min_pixels: int = 2000):
    """Split each capture into depth bands: one capture per band of true depth, its mask the band's pixels.

    A plane seen at a slant (a floor) spans a range of depths and incidence angles that one capture
    puts in one stratum; split into bands, the diagnosis says at which depth and angle the gap lies.
    Each part keeps the frames and the geometry (its simulation is the whole capture's), with the mask
    = the capture's target pixels (its mask, else every pixel the target covers) whose true depth lies in
    [edges_m[i], edges_m[i + 1]).

    Parameters
    ----------
    captures : sequence of CaptureData
    edges_m : sequence of float
        Increasing band edges [m] (>= 2 values).
    min_pixels : int
        Bands with fewer target pixels are left out.

    Returns
    -------
    parts : list of CaptureData
        Ids ``<id>_z<lo>-<hi>`` (depths with 2 decimals).
    parents : dict
        Part id -> the capture id it came from.
    distances, angles : dict
        Part id -> the median true depth [m] and incidence angle [deg] over its mask (its strata bins).
    """
    e = np.asarray(edges_m, dtype=np.float64)
    if e.ndim != 1 or e.size < 2 or not np.all(np.isfinite(e)) or not np.all(np.diff(e) > 0) or e[0] < 0:
        raise ValueError(f"depth band edges must be >= 2 increasing non-negative metres, got {list(edges_m)!r}")
    parts, parents, distances, angles = [], {}, {}, {}
    for c in check_captures(captures):
        z, th = c.geometry.render()
        target = c.target_pixels()
        for lo, hi in zip(e[:-1], e[1:]):
            with np.errstate(invalid="ignore"):
                m = target & (z >= lo) & (z < hi)
            if int(m.sum()) < int(min_pixels):
                continue
            g = c.geometry
            pid = f"{c.id}_z{lo:.2f}-{hi:.2f}"
            part = c.with_geometry(dataclasses.replace(g, id=pid), m)
            parts.append(part)
            parents[pid] = c.id
            distances[pid] = float(np.median(z[m]))
            angles[pid] = float(np.degrees(np.median(th[m])))
    if not parts:
        raise ValueError(f"no depth band of {list(edges_m)!r} holds {min_pixels} target pixels of any capture")
    return parts, parents, distances, angles


# ---------------------------------------------------------------------------------------------
# the diagnosis
# ---------------------------------------------------------------------------------------------
def _where(entries: list, limit: int = MAX_WHERE, pad: int = 20) -> list:
    """The ``where`` entries worth reporting: those with a gap (at least ``pad``, ranked), at most ``limit``."""
    pos = [e for e in entries if e["gap"] > 0]
    if len(pos) < pad:
        pos = entries[:max(pad, len(pos))]
    return pos[:limit]


def diagnose(real: Sequence[CaptureData], *, heldout="auto", effects=None, seed: int = 0, model: SensorModel = D435,
             progress: Callable[[str], None] | None = None, rois: dict | None = None, distances: dict | None = None,
             kinds: dict | None = None, real_label: str = "", config: SelectionConfig | None = None,
             n_splits: int = 64, n_boot: int = 64, binning: Binning | None = None, angles: dict | None = None,
             jobs: int = 1):
    """Run the diagnosis on real captures held in memory.

    Parameters
    ----------
    real : sequence of CaptureData
        The real captures (frames as metric depth, NaN = no data).
    heldout : "auto", "none", ids
        Held-out captures (see :func:`split_captures`).
    effects : None, str or sequence of str
        Candidate effects (:func:`parse_effect_names`); those whose fits need capture kinds the fit
        captures lack (:data:`noise_model.analysis.effect_fits.NEEDS`) are skipped and listed.
    seed : int
        Seed of the simulations (common random numbers), the fits' base simulations, the half-splits
        and the bootstrap.
    model : SensorModel
        The reference model.
    progress : callable, optional
        ``progress(message)`` after every simulated model (a progress bar's step).
    rois, distances, kinds : dict, optional
        Per capture id: a boolean region of interest (H, W) (only those pixels count; a capture's own
        ``mask`` is one too, and both apply when both are given), the distance [m] for its distance bin
        (default: the target's), its kind label.
    real_label : str
        What the report's ``real`` says.
    config : SelectionConfig, optional
    n_splits, n_boot : int
        Half-splits of the noise floor and bootstrap replicates over frames.
    binning : Binning, optional
        Distance and angle bins of the strata.
    angles : dict, optional
        Per capture id: the incidence angle [deg] for its angle bin (default: the target's on the optical
        axis; e.g. the median over a mask of a floor, whose incidence changes across the image).
    jobs : int
        Worker processes that simulate the models' captures (:meth:`CaptureSimulator.sums`); the report
        is the same for any number (each capture's draws depend on the seed and its id only). The workers
        are started with ``spawn``, which imports the calling script again: a script that asks for more
        than one must call this under ``if __name__ == "__main__":``.

    Returns
    -------
    report : dict
        The JSON-ready report, format ``d435-gap/1``. The keys of the format (``format``, ``real``,
        ``split``, ``baseline``, ``where``, ``effects``, ``final``) plus: ``baseline.gap_all``,
        ``p_value``, ``significant_fit``, ``significant_heldout``, ``null_gap_p95`` (the 95th percentile
        of real-vs-real aggregate gaps); each ``where`` entry's ``z`` (difference / floor), ``floor``
        (sigma_0, units of the statistic) and ``weight`` (its share of the aggregate); each effect's
        ``shrink_test`` (paired bootstrap) and ``ablation`` (``gap_heldout_without``, ``confirmed``);
        ``final.gap_fit``, ``gap_all``, ``significant``; ``rounds`` (every candidate's fitted parameters
        and fit gap per round), ``stop_reason``, ``candidates``, ``skipped`` (effects whose fits need
        captures the set lacks), ``heldout_rule``, ``validation``, ``floor`` (source, splits,
        replicates, thresholds), ``unavailable`` (statistics that could not be computed, and why),
        ``statistics`` (units), ``by`` / ``by_final`` (mean gap and share per statistic, region, image
        cell, distance and angle bin, before / after), ``captures``, ``frames``, ``sim_frames``,
        ``seed``, ``model``, ``binning``, ``seconds``; ``frames_cut`` when captures had more frames
        than the fewest; ``fitted_geometry`` when captures' geometry was fitted to their own frames
        (which ones, and what is not computed for them: the bias of their strata and the effects of
        :data:`MEASURED_ONLY`, which are then listed in ``skipped`` too when every fit capture is fitted).
    result : DiagnosisResult
    """
    t0 = time.perf_counter()
    real = check_captures(real)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    names = parse_effect_names(effects)
    geoms = {c.id: c.geometry for c in real}
    fit_ids, held_ids, rule = split_captures([c.geometry for c in real], heldout, distances)
    by_id = {c.id: c for c in real}
    fit_real = [by_id[i] for i in fit_ids]
    rois = dict(rois or {})
    for c in real:                              # a capture's own mask is its region of interest
        if c.mask is not None:
            rois[c.id] = c.mask & rois[c.id] if c.id in rois else c.mask
    fitted = [c.id for c in real if c.is_fitted]
    candidates, skipped = [], {}
    for n in names:
        if n in MEASURED_ONLY and all(c.is_fitted for c in fit_real):
            skipped[n] = ("bias and scale need a measured distance; the fit captures' geometry is fitted to their "
                          "own frames, which absorbs them")
        elif usable_captures(n, fit_real):
            candidates.append(n)
        else:
            skipped[n] = f"its fit needs {' or '.join(NEEDS[n])} captures among the fit captures"
    caps = [gap_capture_of(c, model, rois.get(c.id), (distances or {}).get(c.id), (kinds or {}).get(c.id),
                           (angles or {}).get(c.id)) for c in real]
    with CaptureSimulator(geoms, model, seed, jobs) as simulator:
        dg = Diagnosis(caps, _DepthOnAccess(real), fit_ids, held_ids,
                       simulator, EffectFitter(fit_real, model, seed, rois or None, simulator),
                       binning=binning or Binning(), n_splits=n_splits, n_boot=n_boot, seed=int(seed),
                       config=config or SelectionConfig(), progress=progress, fitted_ids=fitted)
        res = dg.run(candidates)
    r = res.report
    report = {"format": FORMAT, "real": real_label, "split": {"fit": fit_ids, "heldout": held_ids},
              "baseline": r["baseline"], "where": _where(r["where"]), "effects": r["effects"],
              "final": {**r["final"], "where_unexplained": _where(r["final"]["where_unexplained"], pad=0)}}
    report.update({
        "where_count": sum(1 for e in r["where"] if e["gap"] > 0),
        "heldout_rule": rule, "validation": r["validation"], "candidates": candidates, "skipped": skipped,
        "rounds": r["rounds"], "stop_reason": r["stop_reason"],
        "floor": {"source": r["floor_source"], "n_splits": int(n_splits), "n_boot": int(n_boot),
                  "z_floor": Z_FLOOR, "min_floor": dict(MIN_FLOOR),
                  "alpha": (config or SelectionConfig()).alpha},
        "unavailable": r["unavailable"], "statistics": dict(STAT_UNITS), "by": r["by"], "by_final": r["by_final"],
        "frames": r["frames"], "sim_frames": r["sim_frames"], "seed": int(seed), "model": model.to_dict(),
        "binning": {"distance_width_m": dg.binning.distance_width_m, "angle_width_deg": dg.binning.angle_width_deg},
        "captures": [{"id": c.id, "kind": c.kind, "distance_m": c.distance_m, "angle_deg": c.angle_deg,
                      "frames": int(by_id[c.id].n_frames), "heldout": c.id in held_ids} for c in caps],
        "simulated_captures": dg.n_simulated, "seconds": time.perf_counter() - t0,
    })
    if fitted:
        report["fitted_geometry"] = {
            "captures": fitted,
            "not_computed": "bias_m of the strata these captures fall in, and the effects "
                            f"{', '.join(n for n in MEASURED_ONLY if n in names)}: their geometry is a plane fitted "
                            "to their own frames, which absorbs any bias and scale error"}
    if "frames_cut" in r:
        report["frames_cut"] = r["frames_cut"]
    return json_ready(report), res


# ---------------------------------------------------------------------------------------------
# selftest
# ---------------------------------------------------------------------------------------------
def _selftest_camera(width: int, height: int, model: SensorModel) -> dict:
    """The capture-set ``camera`` of the selftest: ``model``'s intrinsics at width x height, 1 mm units."""
    K = model.intrinsics(width, height)
    return {"width": int(width), "height": int(height), "fx": float(K[0, 0]), "fy": float(K[1, 1]),
            "ppx": float(K[0, 2]), "ppy": float(K[1, 2]), "depth_scale": 0.001, "baseline_m": model.baseline_m}


def selftest_geometries(kind: str = "wall", width: int = 424, height: int = 240,
                        model: SensorModel = D435) -> list[CaptureGeometry]:
    """The selftest's captures: 18 walls (0.5 to 2.0 m every 0.3 m x yaw 0, 30, 55 deg), or 12 boards
    0.60 x 0.90 m before a wall at 3 m (0.6 to 2.1 m every 0.3 m x yaw 0, 30 deg), the sets
    :data:`noise_model.analysis.effect_fits.FIT_TOLERANCE` is stated for."""
    cam = _selftest_camera(width, height, model)
    if kind == "wall":
        return [CaptureGeometry.from_capture_set_entry(cam, {"id": f"wall_z{d:.2f}_y{y:02d}", "target": {
            "kind": "wall", "distance_m": d, "yaw_deg": float(y), "pitch_deg": 0.0}})
            for d in (0.5, 0.8, 1.1, 1.4, 1.7, 2.0) for y in (0, 30, 55)]
    if kind == "board":
        return [CaptureGeometry.from_capture_set_entry(cam, {"id": f"board_z{d:.2f}_y{y:02d}", "target": {
            "kind": "board", "distance_m": d, "yaw_deg": float(y), "pitch_deg": 0.0, "width_m": 0.6,
            "height_m": 0.9}, "background_m": 3.0}) for d in (0.6, 0.9, 1.2, 1.5, 1.8, 2.1) for y in (0, 30)]
    raise ValueError(f"kind must be 'wall' or 'board', got {kind!r}")


def selftest_cases(effects, seed: int) -> list[dict]:
    """The selftest's cases: each effect alone at parameters drawn from its range (seeded), no effect,
    the two effects of :data:`SELFTEST_PAIR` together, and the static and the per-frame field of
    :data:`SELFTEST_STATIC_PAIR` together. ``effects`` None or "all": every effect but those of
    :data:`SELFTEST_UNSEEN`; effects named are hidden whatever they are.

    Returns
    -------
    list of dict
        ``case`` (its name) and ``effects`` (list of (name, params)).
    """
    names = parse_effect_names(effects)
    if effects is None or (isinstance(effects, str) and effects.strip().lower() in ("", "all")):
        names = [n for n in names if n not in SELFTEST_UNSEEN]
    cases = []
    for k, n in enumerate(names):
        p = draw_params(n, np.random.default_rng([int(seed), 1, k]))
        cases.append({"case": n, "effects": [(n, p)]})
    cases.append({"case": "none", "effects": []})
    pair = [(n, draw_params(n, np.random.default_rng([int(seed), 2, j]))) for j, n in enumerate(SELFTEST_PAIR)]
    cases.append({"case": "+".join(SELFTEST_PAIR), "effects": pair})
    pair = [(n, draw_params(n, np.random.default_rng([int(seed), 3, j]))) for j, n in enumerate(SELFTEST_STATIC_PAIR)]
    cases.append({"case": "+".join(SELFTEST_STATIC_PAIR), "effects": pair, "fit_each": True})
    return cases


def selftest_case(case: dict, seed: int, n_frames: int, width: int, height: int, model: SensorModel,
                  index: int, numba_threads: int | None = None) -> dict:
    """One selftest case: build the pseudo-real captures, diagnose them blind, check the outcome.

    The pseudo-real data are the reference simulation of :func:`selftest_geometries` (walls, or boards
    before a background when an effect's fit needs them) plus the case's effects, drawn from generators
    the diagnosis never uses. Checks: one effect must be selected first, its parameters recovered within
    :func:`noise_model.analysis.effect_fits.within_tolerance` and the held-out gap shrink by >= 60 %; no effect:
    no significant baseline gap and nothing selected; two effects: both selected, shrink >= 60 % (and with
    ``case["fit_each"]``, each one's parameters within tolerance).

    Parameters
    ----------
    case : dict
        One of :func:`selftest_cases`.
    seed : int
    n_frames, width, height : int
        Frames per capture and image size [px].
    model : SensorModel
    index : int
        The case's index (seeds its pseudo-real data).
    numba_threads : int, optional
        Set numba's thread count first (a worker process of a parallel selftest).

    Returns
    -------
    dict
        JSON-ready: ``case``, ``captures``, ``true``, ``selected``, ``fitted``, ``param_errors``,
        ``baseline_gap_heldout``, ``significant``, ``shrink_heldout``, ``stop_reason``, ``round1``,
        ``seconds``, ``checks``, ``passed``.
    """
    if numba_threads is not None:
        import numba

        numba.set_num_threads(int(numba_threads))
    t0 = time.perf_counter()
    needs_board = any("board+background" in NEEDS[n] for n, _ in case["effects"])
    geoms = selftest_geometries("board" if needs_board else "wall", width, height, model)
    objs = canonical_order([make_effect(n, **p) for n, p in case["effects"]])
    real = []
    for g in geoms:
        rng = np.random.default_rng([int(seed) + 1_000_003, index, zlib.crc32(g.id.encode("utf-8"))])
        real.append(CaptureData.from_units(g, simulate_capture(g, int(n_frames), rng, model, objs)))
    report, _ = diagnose(real, heldout="auto", effects=None, seed=int(seed), model=model,
                         real_label=f"selftest:{case['case']}")
    selected = [e["name"] for e in report["effects"]]
    row = {"case": case["case"], "captures": f"{len(geoms)} {'boards' if needs_board else 'walls'} x {n_frames} "
                                              f"frames {width}x{height}",
           "true": {n: p for n, p in case["effects"]}, "selected": selected,
           "fitted": {e["name"]: e["params"] for e in report["effects"]},
           "baseline_gap_heldout": report["baseline"]["gap_heldout"], "significant": report["baseline"]["significant"],
           "shrink_heldout": report["final"]["shrink_heldout"], "stop_reason": report["stop_reason"],
           "round1": [c["name"] for c in report["rounds"][0]["candidates"][:3]] if report["rounds"] else [],
           "seconds": time.perf_counter() - t0}
    checks = {}
    if not case["effects"]:
        checks["not_significant"] = not report["baseline"]["significant"]
        checks["nothing_selected"] = not selected
    elif len(case["effects"]) == 1:
        name, true = case["effects"][0]
        checks["ranked_first"] = bool(selected) and selected[0] == name
        if checks["ranked_first"]:
            ok, errs = within_tolerance(name, true, row["fitted"][name])
            row["param_errors"] = {k: {"error": e, "allowed": a} for k, (e, a) in errs.items()}
        else:
            ok = False
        checks["params_within_tolerance"] = bool(ok)
        checks["shrink_heldout_ge_0.6"] = row["shrink_heldout"] >= 0.6
    else:
        checks["all_found"] = all(n in selected for n, _ in case["effects"])
        if case.get("fit_each"):
            ok, errs = True, {}
            for name, true in case["effects"]:
                if name in row["fitted"]:
                    o, e = within_tolerance(name, true, row["fitted"][name])
                    ok &= o
                    errs.update({f"{name}.{k}": {"error": v[0], "allowed": v[1]} for k, v in e.items()})
                else:
                    ok = False
            row["param_errors"] = errs
            checks["params_within_tolerance"] = bool(ok)
        checks["shrink_heldout_ge_0.6"] = row["shrink_heldout"] >= 0.6
    row["checks"] = checks
    row["passed"] = all(checks.values())
    return json_ready(row)


# ---------------------------------------------------------------------------------------------
# a plane fitted to a region of a real frame as a capture
# ---------------------------------------------------------------------------------------------
def plane_geometry(capture_id: str, plane: PlaneFit, K, width: int, height: int, depth_scale: float,
                   baseline_m: float = D435.baseline_m) -> CaptureGeometry:
    """A capture-set wall whose plane is a fitted plane n . X = c (c >= 0).

    The wall's centre is where the plane crosses the optical axis, distance_m = c / n_z; yaw =
    atan2(n_x, n_z), pitch = -asin(n_y), so that its normal R_y(yaw) R_x(pitch) e_z is n.

    Raises
    ------
    ValueError
        A plane that does not cross the optical axis in front of the camera (n_z <= 0, e.g. a floor
        seen by a camera looking slightly up): it is not a capture-set target.
    """
    n = np.asarray(plane.normal, dtype=np.float64)
    if n[2] <= 1e-3 or plane.offset_m / n[2] > 100.0:
        raise ValueError(f"{capture_id}: the fitted plane (normal {np.round(n, 4).tolist()}, incidence "
                         f"{plane.incidence_deg:.1f} deg) does not cross the optical axis within 100 m in front of "
                         "the camera, so it is not a capture-set target")
    target = {"kind": "wall", "distance_m": float(plane.offset_m / n[2]),
              "yaw_deg": math.degrees(math.atan2(n[0], n[2])), "pitch_deg": -math.degrees(math.asin(float(n[1])))}
    camera = {"width": int(width), "height": int(height), "fx": float(K[0, 0]), "fy": float(K[1, 1]),
              "ppx": float(K[0, 2]), "ppy": float(K[1, 2]), "depth_scale": float(depth_scale),
              "baseline_m": float(baseline_m)}
    return CaptureGeometry.from_capture_set_entry(camera, {"id": capture_id, "target": target})
