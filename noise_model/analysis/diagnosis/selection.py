"""Effect selection: the baseline gap, forward selection of effects, ablation (:class:`Diagnosis`).

:class:`Diagnosis` holds the real captures (fit and held-out split, whole captures) and two callables,
``simulate(ids, effects, n_frames)`` and ``fit(name, base_effects)``. Forward selection: every candidate
effect is fitted on the fit captures and simulated (common random numbers: each capture's noise seed
is the same in every model), the one that lowers the fit gap most is added if it shrinks the held-out
gap significantly (paired bootstrap over frames, :func:`.floor.shrink_test`: at least 1 - alpha of the
replicates shrink) and materially (by at least ``min_shrink`` of the held-out gap left before its round,
and by more than the 95th percentile of real-vs-real aggregate gaps); after each accepted effect from
the second on, the effects selected before it are fitted again on top of all the others (backfitting);
repeat while the remaining gap is significant. Ablation then removes each selected effect again and reports whether the
held-out gap grows significantly (confirmed) or not.

An effect is a (name, params) pair; a model is the reference simulation plus a list of effects.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from .floor import Floor, GapResult, aggregate_by, compare, make_floor, realisation_variance, shrink_test
from .strata import Binning, GapCapture
from .sums import STATISTICS, capture_sums, check_depth_stack, frame_sampling, pool_sums

__all__ = ["SelectionConfig", "DiagnosisResult", "Diagnosis", "model_key", "other_realisation", "refit_pairs"]

@dataclass(frozen=True)
class SelectionConfig:
    """Settings of the forward selection.

    Attributes
    ----------
    alpha : float
        Significance level: the baseline test, and the paired bootstrap of a shrink (at least
        1 - alpha of the replicates must shrink).
    min_shrink : float
        Materiality: an effect must also shrink the held-out gap by at least this fraction of the
        held-out gap left before its round (what the effects selected so far leave unexplained), and
        by more than the 95th percentile of the real-vs-real aggregate gaps of the held-out captures
        (a shrink two halves of the real data could show against each other is no shrink). Relative
        to what is left, not to the baseline: once a first effect has removed most of a gap that the
        reference model gets wrong by orders of magnitude, the next effect's share of the baseline is
        small however real it is, while its share of what is left is what a user gains by adding it.
    max_effects : int
        At most this many effects are selected (the library holds 13; the selection normally stops
        earlier, when no candidate passes the held-out test or the gap left is within the floor).
    prune : bool
        From the second round on, only candidates that shrank the fit gap in the previous round are
        tried again (saves time; an effect that did not help before rarely helps after another).
    readmit_after : tuple of str
        With ``prune``: once one of these effects is accepted, every candidate pruned before is tried again.
        ``axial_refit`` replaces the axial noise that the effects sized in units of it
        (``correlated_noise``, ``static_noise``) are fitted on top of: fitted on the reference's noise
        (on a stereo camera many times the real one at slant angles) such a field comes out at zero size,
        cannot shrink anything, and would otherwise be pruned for good before the noise it belongs to is
        in the model.
    backfit : bool
        After each accepted effect from the second on, every effect selected before it is fitted again
        on top of all the others (backfitting): an effect fitted while the model lacked a later one has
        taken that one's share (``axial_refit`` fitted to a white model takes the whole temporal
        variance, and a correlated field then adds to it instead of taking its share). The refit is
        kept when it lowers the fit gap and the held-out gap passes the shrink test's significance.
    refit_with : tuple of (str, tuple of str)
        When the first effect of a pair is tried as a candidate or refitted in backfitting, the selected
        effects named in the second are fitted again on top of it in the same trial, which is kept or
        dropped as a whole. A candidate whose field takes a share of the temporal variance is so judged
        with the axial noise that gives the rest: added alone, the variance would be counted twice, and a
        later backfit of the axial noise would have to pass the held-out test on a difference the gap's
        statistics barely see (docs/calibration.md). The
        default, :func:`refit_pairs`, derives the pairs from the registry's
        :attr:`~noise_model.sim.effects.EffectSpec.axial_units`. For effects whose size is a parameter in
        units of the first's output: ``static_noise`` is a fraction of
        the sigma_z ``axial_refit`` sets, and what its fit measures is the static field's size in the data.
        A refit of ``axial_refit`` alone (lower once a correlated field takes its temporal share) would
        shrink that static field by the same factor; the fit gap would then weigh a smaller temporal error
        against a new static one, and could refuse the refit, leaving the temporal variance counted twice.
        ``correlated_noise``'s field, k sigma_z drawn each frame, is the share of the temporal variance the
        refit of ``axial_refit`` leaves to it (that refit divides the real variance by 1 + k^2), so it does
        not follow ``axial_refit``; the other way round, a refit of ``correlated_noise`` (a larger k once
        the white noise under it is smaller) is tried with ``axial_refit`` refitted on top of it, so the
        temporal variance stays the real one while its correlated share grows. The effects are refitted in
        the order listed.
    """

    alpha: float = 0.05
    min_shrink: float = 0.05
    max_effects: int = 8
    prune: bool = True
    readmit_after: tuple = ("axial_refit",)
    backfit: bool = True
    refit_with: tuple = field(default_factory=lambda: refit_pairs())

    def __post_init__(self):
        def names(value, what):
            if isinstance(value, str) or not isinstance(value, (tuple, list)) \
                    or not all(isinstance(n, str) and n for n in value):
                raise ValueError(f"SelectionConfig.{what} must be a tuple of effect names, got {value!r}")
            return tuple(value)

        object.__setattr__(self, "readmit_after", names(self.readmit_after, "readmit_after"))
        pairs = self.refit_with
        if isinstance(pairs, str) or not isinstance(pairs, (tuple, list)) \
                or not all(isinstance(p, (tuple, list)) and len(p) == 2 and isinstance(p[0], str) for p in pairs):
            raise ValueError("SelectionConfig.refit_with must be a tuple of (effect name, tuple of effect names), "
                             f"got {pairs!r}")
        object.__setattr__(self, "refit_with",
                           tuple((a, names(b, f"refit_with[{a!r}]")) for a, b in pairs))


def refit_pairs(specs=None) -> tuple:
    """The default of :attr:`SelectionConfig.refit_with`, from the effects' :attr:`EffectSpec.axial_units`.

    An effect that sets the axial sigma_z ("sets") is refitted with the static fields sized in its units
    ("static"), which would otherwise shrink with it; an effect whose per-frame field takes a share of the
    temporal variance ("temporal") is refitted with the "sets" effects (which then give the rest of that
    variance) and the "static" ones after them. Each list in the registry's composition order.

    Parameters
    ----------
    specs : mapping of str to EffectSpec, optional
        The registry (:data:`noise_model.sim.effects.SPECS` when omitted).

    Returns
    -------
    tuple of (str, tuple of str)
    """
    if specs is None:
        from ...sim.effects import SPECS as specs
    ordered = sorted(specs.values(), key=lambda s: s.order)
    kind = {u: tuple(s.name for s in ordered if s.axial_units == u) for u in ("sets", "static", "temporal")}
    return (tuple((name, kind["static"]) for name in kind["sets"])
            + tuple((name, kind["sets"] + kind["static"]) for name in kind["temporal"]))


def model_key(effects) -> tuple:
    """A hashable key of a model (a list of (name, params) effects): equal for equal effects and
    parameters, whatever the order of the parameters (the cache key of simulations and base fits)."""
    return tuple((name, tuple(sorted((k, _hashable(v)) for k, v in params.items()))) for name, params in effects)


def _hashable(v):
    """A parameter value as a hashable, comparable key (lists -> tuples, NumPy scalars -> Python)."""
    if isinstance(v, (list, tuple)):
        return tuple(_hashable(x) for x in v)
    if isinstance(v, np.generic):
        return v.item()
    return v


@dataclass
class DiagnosisResult:
    """What :meth:`Diagnosis.run` found.

    Attributes
    ----------
    report : dict
        ``baseline``, ``where``, ``rounds``, ``effects``, ``final``, ``unavailable``, ``floor_source``
        (JSON-ready; the orchestrator adds ``format``, ``real``, ``split``).
    baseline_all, final_all : GapResult
        Reference model and final model against all captures.
    baseline_heldout, final_heldout : GapResult
    selected : list of (str, dict)
        The effects selected, in order, with their fitted parameters.
    captures : dict
        id -> GapCapture (fit captures first, then held-out).
    """

    report: dict
    baseline_all: GapResult
    final_all: GapResult
    baseline_heldout: GapResult
    final_heldout: GapResult
    selected: list
    captures: dict = field(default_factory=dict)


def other_realisation(effects):
    """The same model with its static fields drawn anew: every effect with a ``seed`` parameter (the
    realisation of a field fixed over the frames) gets another seed; None when there is none."""
    out, changed = [], False
    for name, params in effects:
        if "seed" in params:
            params = {**params, "seed": (int(params["seed"]) + 7919) % (2 ** 31 - 1)}
            changed = True
        out.append((name, params))
    return out if changed else None


class Diagnosis:
    """Real captures against simulated models: baseline gap, forward selection of effects, ablation.

    Parameters
    ----------
    captures : sequence of GapCapture
    real_depth : mapping id -> ndarray (F, H, W) float [m]
        The real frames (NaN = no data). Captures with more frames than the fewest are cut to it. Each is
        read twice (its checks, then its sums) and not kept, so a mapping that makes the frames on access
        holds one capture's at a time.
    fit_ids, heldout_ids : sequence of str
        Whole captures used to fit effects and to validate them (disjoint). With no held-out capture
        the fit captures validate (the report says so).
    simulate : callable
        ``simulate(ids, effects, n_frames) -> {id: ndarray (n_frames, H, W) float [m]}``: the reference
        simulation plus ``effects`` (list of (name, params)), each capture seeded the same way in every
        model (common random numbers). When it also has a method ``simulate.sums(ids, effects, n_frames,
        captures, sampling) -> {id: capture_sums}`` (:meth:`noise_model.analysis.diagnosis.CaptureSimulator.sums`,
        e.g. in worker processes), that is used instead, and only the sums are kept.
    fit : callable or None
        ``fit(name, base_effects) -> params``: an effect's parameters fitted on the fit captures on top
        of ``base_effects``. None: baseline only.
    binning : Binning
    n_splits, n_boot : int
        Real-vs-real half-splits (noise floor) and bootstrap replicates over frames.
    seed : int
        Seed of the splits and replicates.
    config : SelectionConfig
    progress : callable, optional
        ``progress(message)`` after every simulated model.
    fitted_ids : sequence of str, optional
        Captures whose geometry was fitted to their own frames: the bias (``bias_m``) of every stratum
        they contribute to is not computed (the plane fit absorbs any bias and scale error).
    """

    def __init__(self, captures: Sequence[GapCapture], real_depth, fit_ids, heldout_ids, simulate: Callable,
                 fit: Callable | None = None, *, binning: Binning = Binning(), n_splits: int = 64, n_boot: int = 64,
                 seed: int = 0, config: SelectionConfig = SelectionConfig(), progress: Callable | None = None,
                 n_floor_frames: int = 8, fitted_ids: Sequence[str] = ()):
        self.captures = {c.id: c for c in captures}
        if len(self.captures) != len(captures) or not captures:
            raise ValueError("captures must be non-empty with unique ids")
        fit_ids, heldout_ids = [str(i) for i in fit_ids], [str(i) for i in heldout_ids]
        for i in fit_ids + heldout_ids:
            if i not in self.captures:
                raise ValueError(f"unknown capture id {i!r}")
        if set(fit_ids) & set(heldout_ids):
            raise ValueError(f"fit and held-out captures overlap: {sorted(set(fit_ids) & set(heldout_ids))}")
        if not fit_ids:
            raise ValueError("no fit captures")
        self.fit_ids, self.heldout_ids = fit_ids, heldout_ids
        self.validation_ids = heldout_ids if heldout_ids else fit_ids
        self.all_ids = fit_ids + heldout_ids
        n_frames = {}
        for i in self.all_ids:                     # one capture's frames at a time (real_depth may make them)
            if i not in real_depth:
                raise ValueError(f"no real depth for capture {i!r}")
            n_frames[i] = check_depth_stack(self.captures[i], real_depth[i]).shape[0]
        self.n_frames = min(n_frames.values())
        self.cut_frames = sorted(i for i, n in n_frames.items() if n > self.n_frames)
        self.simulate, self.fit = simulate, fit
        self.binning, self.config, self.progress = binning, config, progress
        self.seed = int(seed)
        F = self.n_frames
        self.single_frame = F < 2
        self.n_sim_frames = F if F >= 2 else int(n_floor_frames)
        self.real_sampling = frame_sampling(F, seed, n_splits, n_boot)
        self.sim_sampling = frame_sampling(self.n_sim_frames, seed + 1, n_splits if self.single_frame else 0, n_boot)
        self.real_sums = {i: capture_sums(self.captures[i], np.asarray(real_depth[i])[:F], self.real_sampling)
                          for i in self.all_ids}
        self.fitted_bins = {binning.bins(self.captures[i]) for i in fitted_ids if i in self.captures}
        self._sums: dict = {}
        self._pending: dict = {}
        self._floors: dict = {}
        self.n_simulated = 0

    # -- evaluation ---------------------------------------------------------------------------
    def prefetch(self, effects, ids) -> None:
        """Start simulating the model reference + ``effects`` on the captures ``ids`` (and its other
        realisation, :func:`other_realisation`) without waiting, when ``simulate`` can
        (``simulate.submit(ids, effects, n_frames, captures, sampling) -> {id: future of capture_sums}``,
        :meth:`noise_model.analysis.diagnosis.CaptureSimulator.submit`, worker processes): the next
        :meth:`evaluate` of the model collects the sums. The selection fits the next candidate meanwhile.
        Does nothing otherwise."""
        submit = getattr(self.simulate, "submit", None)
        if not callable(submit):
            return
        for model in (effects, other_realisation(effects)):
            if model is None:
                continue
            key = model_key(model)
            store, pend = self._sums.get(key, {}), self._pending.setdefault(key, {})
            missing = [i for i in ids if i not in store and i not in pend]
            if missing:
                pend.update(submit(missing, list(model), self.n_sim_frames, self.captures, self.sim_sampling))

    def _ensure(self, effects, ids):
        key = model_key(effects)
        store = self._sums.setdefault(key, {})
        pend = self._pending.get(key, {})
        done = [i for i in ids if i not in store and i in pend]
        for i in done:
            store[i] = pend.pop(i).result()
        missing = [i for i in ids if i not in store]
        if missing:
            sums = getattr(self.simulate, "sums", None)
            if callable(sums):
                got = sums(missing, list(effects), self.n_sim_frames, self.captures, self.sim_sampling)
            else:
                depth = self.simulate(missing, list(effects), self.n_sim_frames)
                got = {i: capture_sums(self.captures[i], depth[i], self.sim_sampling) for i in missing if i in depth}
            for i in missing:
                if i not in got:
                    raise ValueError(f"simulate returned no depth for capture {i!r}")
                store[i] = got[i]
        missing = done + missing
        if missing:
            self.n_simulated += len(missing)
            if self.progress is not None:
                names = "+".join(n for n, _ in effects) or "reference"
                self.progress(f"{names} ({len(missing)} captures)")
        return store

    def floor(self, ids) -> Floor:
        key = tuple(ids)
        if key not in self._floors:
            caps = [self.captures[i] for i in ids]
            keys, real = pool_sums(caps, [self.real_sums[i] for i in ids], self.binning)
            exclude = np.zeros((len(STATISTICS), len(keys)), dtype=bool)
            exclude[STATISTICS.index("bias_m")] = [k[:2] in self.fitted_bins for k in keys]
            why = ("needs a measured distance: the captures' geometry is fitted to their own frames, which "
                   "absorbs bias and scale")
            if self.single_frame:
                store = self._ensure([], ids)
                _, fl = pool_sums(caps, [store[i] for i in ids], self.binning)
                self._floors[key] = make_floor(keys, real, self.real_sampling, self.n_sim_frames, fl,
                                               self.sim_sampling, exclude=exclude, exclude_reason=why)
            else:
                self._floors[key] = make_floor(keys, real, self.real_sampling, self.n_sim_frames, exclude=exclude,
                                               exclude_reason=why)
        return self._floors[key]

    def evaluate(self, effects, ids) -> GapResult:
        """The gap of the model reference + ``effects`` over the captures ``ids``.

        A model with static fields (effects with a ``seed`` of their realisation) is simulated a second
        time with other realisations, and the spread of the cells' bias between them is added to its
        floor (:func:`~.floor.realisation_variance`): the real data hold one realisation, which no seed
        fitted to them can reproduce.
        """
        fl = self.floor(ids)
        store = self._ensure(effects, ids)
        caps = [self.captures[i] for i in ids]
        keys, sim = pool_sums(caps, [store[i] for i in ids], self.binning)
        extra = None
        other = other_realisation(effects)
        if other is not None:
            alt = self._ensure(other, ids)
            _, sim2 = pool_sums(caps, [alt[i] for i in ids], self.binning)
            extra = realisation_variance(keys, sim, sim2)
        return compare(fl, self.real_sampling, sim, self.sim_sampling, self.config.alpha, extra)

    def forget(self, keep) -> None:
        """Drop cached simulations of models not in ``keep`` (lists of effects)."""
        keep = list(keep)
        keep += [o for o in (other_realisation(e) for e in keep) if o is not None]
        keys = {model_key(e) for e in keep} | {model_key([])}
        for k in list(self._sums):
            if k not in keys:
                del self._sums[k]
        for k in list(self._pending):
            if k not in keys:
                for f in self._pending.pop(k).values():
                    f.cancel()

    def min_delta(self, current: GapResult) -> float:
        """The smallest material shrink of the held-out gap from ``current`` (the model before the round):
        ``min_shrink`` of its gap, and no less than the 95th percentile of the real-vs-real aggregate
        gaps of its captures (:attr:`SelectionConfig.min_shrink`)."""
        null = current.floor.null_g
        noise = float(np.percentile(null, 95)) if null.size else 0.0
        return max(self.config.min_shrink * current.G, noise)

    def _refit_followers(self, trial, j):
        """Fit again, on top of ``trial[j]``, the effects of ``trial`` that follow it
        (:attr:`SelectionConfig.refit_with`), in the order listed.

        Returns
        -------
        trial : list of (name, params)
            A new list with the followers' parameters replaced.
        refitted : dict
            Index in ``trial`` -> (name, params) of each follower fitted again.
        """
        trial = list(trial)
        refitted = {}
        for other in dict(self.config.refit_with).get(trial[j][0], ()):
            for i in [i for i, (n, _) in enumerate(trial) if n == other and i != j]:
                trial[i] = (other, dict(self.fit(other, trial[:i] + trial[i + 1:])))
                refitted[i] = trial[i]
        return trial, refitted

    def _backfit(self, selected, cur_fit, cur_val, effects_out, rnd):
        """Fit every effect selected before the last one again on top of all the others
        (:attr:`SelectionConfig.backfit`), with the effects sized in its units fitted again on top of it
        (:attr:`SelectionConfig.refit_with`); keep a refit that lowers the fit gap and shrinks the held-out gap
        significantly. Records each attempt in ``rnd["backfit"]`` (``refit_with``: the effects refitted with
        it) and updates ``effects_out``'s parameters.

        Returns
        -------
        selected, cur_fit, cur_val
        """
        log = rnd.setdefault("backfit", [])
        for j in range(len(selected) - 1):
            name = selected[j][0]
            others = selected[:j] + selected[j + 1:]
            try:
                params = dict(self.fit(name, others))
            except ValueError as exc:
                log.append({"name": name, "error": str(exc), "kept": False})
                continue
            if model_key([(name, params)]) == model_key([selected[j]]):
                log.append({"name": name, "params": params, "kept": False, "why": "same parameters"})
                continue
            trial = selected[:j] + [(name, params)] + selected[j + 1:]
            try:
                trial, with_ = self._refit_followers(trial, j)
                r_fit = self.evaluate(trial, self.fit_ids)
            except ValueError as exc:
                log.append({"name": name, "params": params, "error": str(exc), "kept": False})
                continue
            entry = {"name": name, "params": params, "gap_fit_before": cur_fit.G, "gap_fit_after": r_fit.G}
            if with_:
                entry["refit_with"] = [{"name": n, "params": p} for n, p in with_.values()]
            if not r_fit.G < cur_fit.G:
                log.append({**entry, "kept": False, "why": "the fit gap does not fall"})
                continue
            r_val = self.evaluate(trial, self.validation_ids)
            test = shrink_test(cur_val, r_val, self.config.alpha)
            entry.update(gap_heldout_before=cur_val.G, gap_heldout_after=r_val.G, heldout_test=test)
            if not test["significant"]:
                log.append({**entry, "kept": False, "why": "the held-out gap does not fall significantly"})
                continue
            log.append({**entry, "kept": True})
            effects_out[j]["params_first_fit"] = effects_out[j].get("params_first_fit", effects_out[j]["params"])
            effects_out[j]["params"] = params
            for i, (_, p) in with_.items():
                effects_out[i]["params_first_fit"] = effects_out[i].get("params_first_fit", effects_out[i]["params"])
                effects_out[i]["params"] = p
            selected, cur_fit, cur_val = trial, r_fit, r_val
        return selected, cur_fit, cur_val

    # -- the whole diagnosis ------------------------------------------------------------------
    def run(self, candidates: Sequence[str] = ()) -> DiagnosisResult:
        """Baseline, forward selection over ``candidates`` (effect names) and ablation."""
        cfg = self.config
        b_all = self.evaluate([], self.all_ids)
        b_fit = self.evaluate([], self.fit_ids)
        b_val = self.evaluate([], self.validation_ids)
        baseline = {"gap_fit": b_fit.G, "gap_heldout": b_val.G, "gap_all": b_all.G,
                    "significant": b_all.significant, "p_value": b_all.p_value,
                    "significant_fit": b_fit.significant, "significant_heldout": b_val.significant,
                    "null_gap_p95": float(np.percentile(b_all.floor.null_g, 95)) if b_all.floor.null_g.size else None}
        selected: list = []
        rounds: list = []
        effects_out: list = []
        cur_fit, cur_val = b_fit, b_val
        remaining = list(dict.fromkeys(candidates))
        all_candidates = list(remaining)
        stop_reason = "no candidate effects" if not remaining else None
        if self.fit is None and remaining:
            stop_reason = "no fit function: baseline only"
            remaining = []
        if remaining and not (b_all.significant or b_fit.significant or b_val.significant):
            stop_reason = "no significant gap: the reference model is within the real-vs-real noise floor"
            remaining = []
        while remaining and len(selected) < cfg.max_effects:
            fitted = []                            # every candidate fitted first, its simulation started at once
            for name in remaining:
                try:
                    params = dict(self.fit(name, list(selected)))
                    # a candidate tried with the selected effects that follow it fitted again on top (a
                    # field taking a share of the temporal variance with the axial noise that gives the rest)
                    model, with_ = self._refit_followers(selected + [(name, params)], len(selected))
                except ValueError as exc:          # no usable fit
                    fitted.append((name, None, exc, None, {}))
                    continue
                self.prefetch(model, self.fit_ids)
                fitted.append((name, params, None, model, with_))
            tried = []
            for name, params, fit_error, model, with_ in fitted:
                entry = {"name": name}
                try:
                    if fit_error is not None:
                        raise fit_error
                    if with_:
                        entry["refit_with"] = [{"name": n, "params": p} for n, p in with_.values()]
                    r = self.evaluate(model, self.fit_ids)
                except ValueError as exc:          # no usable fit, or parameters the effect refuses
                    entry.update(error=str(exc), gap_fit_after=None, shrink_fit=None)
                    tried.append((entry, None, None, {}))
                    continue
                entry.update(params=params, gap_fit_after=r.G,
                             shrink_fit=1.0 - r.G / cur_fit.G if cur_fit.G > 0 else 0.0)
                tried.append((entry, model, r, with_))
            ok = [t for t in tried if t[2] is not None]
            ok.sort(key=lambda t: t[2].G)
            rnd = {"round": len(rounds) + 1, "gap_fit_before": cur_fit.G, "gap_heldout_before": cur_val.G,
                   "candidates": [t[0] for t in ok] + [t[0] for t in tried if t[2] is None]}
            rounds.append(rnd)
            if not ok or ok[0][2].G >= cur_fit.G:
                stop_reason = "no candidate shrinks the fit gap"
                break
            entry, model, r_fit, with_ = ok[0]
            r_val = self.evaluate(model, self.validation_ids)
            test = shrink_test(cur_val, r_val, cfg.alpha)
            min_delta = self.min_delta(cur_val)
            big_enough = test["delta"] >= min_delta
            rnd["chosen"] = entry["name"]
            rnd["heldout_test"] = {**test, "gap_heldout_after": r_val.G, "min_delta": min_delta}
            if not (test["significant"] and big_enough):
                rnd["accepted"] = False
                why = "significantly" if not test["significant"] else "materially"
                stop_reason = (f"best candidate {entry['name']} does not shrink the held-out gap {why} "
                               f"(shrinks in {100 * test['fraction']:.0f} % of replicates, by {test['delta']:.3g}; "
                               f"material from {min_delta:.3g})")
                break
            rnd["accepted"] = True
            selected = model
            for i, (_, p) in with_.items():      # the followers fitted again in the accepted trial
                effects_out[i]["params_first_fit"] = effects_out[i].get("params_first_fit", effects_out[i]["params"])
                effects_out[i]["params"] = p
            effects_out.append({"name": entry["name"], "params": entry["params"], "gap_fit_after": r_fit.G,
                                "gap_heldout_after": r_val.G,
                                "shrink_heldout": 1.0 - r_val.G / b_val.G if b_val.G > 0 else 0.0,
                                "shrink_test": test})
            prev_fit = cur_fit.G
            cur_fit, cur_val = r_fit, r_val
            if cfg.prune:
                remaining = [t[0]["name"] for t in ok[1:] if t[2].G < prev_fit]
                if entry["name"] in cfg.readmit_after:
                    chosen = {n for n, _ in model}
                    back = [n for n in all_candidates if n not in chosen and n not in remaining]
                    if back:
                        rnd["readmitted"] = back
                        remaining += back
            else:
                remaining = [t[0]["name"] for t in tried if t[0]["name"] != entry["name"]]
            if cfg.backfit and len(selected) > 1:
                selected, cur_fit, cur_val = self._backfit(selected, cur_fit, cur_val, effects_out, rnd)
            self.forget([selected])
            if not (cur_fit.significant or cur_val.significant):
                stop_reason = "remaining gap within the real-vs-real noise floor"
                break
            if not remaining:
                stop_reason = "no candidate left that shrank the fit gap"
        if stop_reason is None:
            stop_reason = f"reached the maximum of {cfg.max_effects} effects"
        # ablation: remove each selected effect again
        for i in range(len(effects_out)):
            self.prefetch(selected[:i] + selected[i + 1:], self.validation_ids)
        self.prefetch(selected, self.all_ids)
        for i, e in enumerate(effects_out):
            without = selected[:i] + selected[i + 1:]
            r = self.evaluate(without, self.validation_ids)
            test = shrink_test(r, cur_val, cfg.alpha)
            e["ablation"] = {"gap_heldout_without": r.G, "delta": test["delta"], "fraction": test["fraction"],
                             "confirmed": test["significant"]}
        f_all = self.evaluate(selected, self.all_ids)
        final = {"gap_heldout": cur_val.G, "shrink_heldout": 1.0 - cur_val.G / b_val.G if b_val.G > 0 else 0.0,
                 "unexplained_fraction": cur_val.G / b_val.G if b_val.G > 0 else 0.0,
                 "gap_fit": cur_fit.G, "gap_all": f_all.G, "significant": f_all.significant,
                 "p_value": f_all.p_value,
                 "where_unexplained": f_all.entries(self.binning, only_positive=True)}
        report = {"baseline": baseline, "where": b_all.entries(self.binning, only_positive=False),
                  "effects": effects_out, "final": final, "rounds": rounds, "stop_reason": stop_reason,
                  "floor_source": b_all.floor.source, "unavailable": dict(b_all.floor.unavailable),
                  "frames": self.n_frames, "sim_frames": self.n_sim_frames,
                  "validation": "held-out captures" if self.heldout_ids else
                                "fit captures (no held-out capture: shrink is not independent)",
                  "by": {by: aggregate_by(b_all, self.binning, by)
                         for by in ("statistic", "region", "image_cell", "distance_m", "angle_deg")},
                  "by_final": {by: aggregate_by(f_all, self.binning, by)
                               for by in ("statistic", "region", "image_cell", "distance_m", "angle_deg")}}
        if self.cut_frames:
            report["frames_cut"] = {"to": self.n_frames, "captures": self.cut_frames}
        return DiagnosisResult(report, b_all, f_all, b_val, cur_val, list(selected),
                               {i: self.captures[i] for i in self.all_ids})

