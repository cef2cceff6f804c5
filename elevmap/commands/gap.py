"""``elevmap gap``: where the paper's D435 model misses real captures, which effect explains it, how far it shrinks.

The sim-to-real gap diagnosis of issue 7, on a capture set (``shared/specs/capture-set.md``,
format ``d435-captures/1``):

1. **Simulate** every real capture with the spec's reference simulation of Ahn et al.'s model
   (:func:`noise_model.analysis.capture_data.simulate_capture`, as many frames as the real capture; capture ``i``
   always draws from ``default_rng([seed, crc32(id)])``, in every model: common random numbers).
2. **Compare** real and simulated per statistic and stratum (:mod:`noise_model.analysis.diagnosis`: bias, temporal and
   spatial standard deviation, correlation length, quantisation lattice, fill rate, residual
   distribution (W1) and tails, by distance, angle, 3 x 3 image cell and region), each difference
   normalised by the real-vs-real noise floor (random halves of the real frames; bootstrap over frames,
   never over pixels).
3. **Where**: strata and statistics ranked by gap.
4. **Which**: forward selection over the effects library (:mod:`noise_model.sim.effects`): each candidate is
   fitted on the *fit* captures (:func:`noise_model.sim.effects.fit_effect`), the one that shrinks the fit
   gap most is added if it shrinks the *held-out* gap significantly; repeated while the remaining gap
   is significant; then each selected effect is removed again (ablation).
5. **How far**: the shrink on held-out captures only (whole captures: ``--heldout IDS``, or ``auto``:
   the middle third of the distances of each target kind, all angles), what is left and where.
6. A readable summary (:func:`format_summary`), the JSON report of the spec (``d435-gap/1``, written
   atomically; extra keys documented in :func:`run_gap`) and an optional rerun recording.

``run_selftest`` checks the whole chain on pseudo-real data (the reference simulation plus known effects at
random parameters); ``run_realdata`` runs on single real frames whose geometry is a plane fitted to a region.
"""

from __future__ import annotations

import json
import math
import time
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from noise_model.sim import effects as E
from noise_model.analysis import diagnosis as G
from noise_model.analysis.capture_data import CaptureData, CaptureGeometry, check_captures, simulate_capture
from noise_model.checks import check_names
from noise_model.d435 import D435, SensorModel

from ..fileio import check_outputs, json_ready, write_json_atomic

__all__ = ["FORMAT", "run_gap", "run_selftest", "run_realdata", "diagnose", "format_summary", "format_selftest",
           "parse_effect_names", "split_captures", "auto_heldout", "CaptureSimulator", "EffectFitter",
           "gap_capture_of", "json_ready", "SELFTEST_PAIR", "REALDATA_PLANES", "plane_geometry",
           "selftest_geometries", "realdata_captures", "load_capture_set", "log_gap_recording", "capture_rng"]

FORMAT = "d435-gap/1"
#: Most ``where`` / ``where_unexplained`` entries written to the report (ranked; the rest are counted).
MAX_WHERE = 300
#: The two effects of the selftest's two-effect case.
SELFTEST_PAIR = ("invalid_band", "correlated_noise")


# ---------------------------------------------------------------------------------------------
# arguments
# ---------------------------------------------------------------------------------------------
def parse_effect_names(effects) -> list[str]:
    """Candidate effect names: None / ``"all"`` = every effect of the library (canonical order), else a
    comma-separated string or a sequence of names of :data:`noise_model.sim.effects.EFFECTS`."""
    if effects is None or (isinstance(effects, str) and effects.strip().lower() in ("", "all")):
        return list(E.ORDER) + [n for n in E.EFFECTS if n not in E.ORDER]
    return check_names(effects, "--effects", list(E.EFFECTS), "effect")


def _incidence_deg(target: dict) -> float:
    yaw, pitch = math.radians(float(target.get("yaw_deg") or 0.0)), math.radians(float(target.get("pitch_deg") or 0.0))
    return math.degrees(math.acos(min(1.0, abs(math.cos(yaw) * math.cos(pitch)))))


def _kind_of(g: CaptureGeometry) -> str:
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
    heldout : ``"auto"``, ``"none"``, a comma-separated string of ids, or a sequence of ids

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


class CaptureSimulator:
    """``simulate(ids, effects, n_frames) -> {id: depth_m}``: the reference simulation plus effects.

    Effects are (name, params) pairs, made with :func:`noise_model.sim.effects.make_effect` and applied in
    :func:`noise_model.sim.effects.canonical_order`; capture ``id`` draws from :func:`capture_rng`, the
    same generator in every model and in :func:`noise_model.sim.effects.fit_effect`'s base simulations.
    """

    def __init__(self, geometries: dict, model: SensorModel = D435, seed: int = 0):
        self.geometries, self.model, self.seed = geometries, model, int(seed)

    def __call__(self, ids, effects, n_frames: int) -> dict:
        objs = E.canonical_order([E.make_effect(n, **p) for n, p in effects])
        out = {}
        for i in ids:
            g = self.geometries[i]
            units = simulate_capture(g, int(n_frames), capture_rng(self.seed, i), self.model, objs)
            out[i] = CaptureData.from_units(g, units).depth_m
        return out


class EffectFitter:
    """``fit(name, base_effects) -> params`` on the fit captures (base simulations cached per base model)."""

    def __init__(self, fit_real: Sequence[CaptureData], model: SensorModel = D435, seed: int = 0,
                 rois: dict | None = None):
        self.real, self.model, self.seed = list(fit_real), model, int(seed)
        ids = {c.id for c in self.real}
        # the fits see only each capture's region of interest, as the statistics do
        self.rois = None if not rois else {k: v for k, v in rois.items() if k in ids}
        self._cache: dict = {}
        self._base_key = None

    def __call__(self, name: str, base_effects) -> dict:
        key = G._model_key(base_effects)
        if key != self._base_key:                 # a new base model: drop the old base simulations
            self._cache, self._base_key = {}, key
        base = [E.make_effect(n, **p) for n, p in base_effects]
        try:
            params = E.fit_effect(name, self.real, self.model, base, seed=self.seed, cache=self._cache,
                                  rois=self.rois)
        except (ArithmeticError, np.linalg.LinAlgError, IndexError) as exc:   # a fit that cannot cope
            raise ValueError(f"fit of {name} failed on these captures ({type(exc).__name__}: {exc})") from exc
        return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in params.items()}


def gap_capture_of(data: CaptureData | CaptureGeometry, model: SensorModel = D435, roi=None,
                   distance_m: float | None = None, kind: str | None = None) -> G.GapCapture:
    """The :class:`noise_model.analysis.diagnosis.GapCapture` of a capture's geometry (nominal render, regions)."""
    g = getattr(data, "geometry", data)
    z, th = g.render()
    return G.make_gap_capture(g.id, z, th, g.regions(model=model), g.K, g.baseline_m,
                              g.distance_m if distance_m is None else distance_m, _incidence_deg(g.target),
                              kind or _kind_of(g), model, roi)


# ---------------------------------------------------------------------------------------------
# the diagnosis
# ---------------------------------------------------------------------------------------------
def _where(entries: list, limit: int = MAX_WHERE, pad: int = 20) -> list:
    pos = [e for e in entries if e["gap"] > 0]
    if len(pos) < pad:
        pos = entries[:max(pad, len(pos))]
    return pos[:limit]


def diagnose(real: Sequence[CaptureData], *, heldout="auto", effects=None, seed: int = 0, model: SensorModel = D435,
             show_progress: bool = False, rois: dict | None = None, distances: dict | None = None,
             kinds: dict | None = None, real_label: str = "", config: G.SelectionConfig | None = None,
             n_splits: int = 64, n_boot: int = 64, binning: G.Binning | None = None):
    """Run the diagnosis on real captures held in memory.

    Parameters
    ----------
    real : sequence of CaptureData
        The real captures (frames as metric depth, NaN = no data).
    heldout : "auto", "none", ids
        Held-out captures (see :func:`split_captures`).
    effects : None, str or sequence of str
        Candidate effects (:func:`parse_effect_names`); those whose fits need capture kinds the fit
        captures lack (:data:`noise_model.sim.effects.NEEDS`) are skipped and listed.
    seed : int
        Seed of the simulations (common random numbers), the fits' base simulations, the half-splits
        and the bootstrap.
    model : SensorModel
        The reference model.
    rois, distances, kinds : dict, optional
        Per capture id: a boolean region of interest (H, W) (only those pixels count), the distance
        [m] for its distance bin (default: the target's), its kind label.
    real_label : str
        What the report's ``real`` says.
    config : noise_model.analysis.diagnosis.SelectionConfig, optional
    n_splits, n_boot : int
        Half-splits of the noise floor and bootstrap replicates over frames.

    Returns
    -------
    report : dict
        The JSON report (see :func:`run_gap`).
    result : noise_model.analysis.diagnosis.DiagnosisResult
    """
    from tqdm import tqdm

    t0 = time.perf_counter()
    real = check_captures(real)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    names = parse_effect_names(effects)
    geoms = {c.id: c.geometry for c in real}
    fit_ids, held_ids, rule = split_captures([c.geometry for c in real], heldout, distances)
    by_id = {c.id: c for c in real}
    fit_real = [by_id[i] for i in fit_ids]
    candidates, skipped = [], {}
    for n in names:
        if E.usable_captures(n, fit_real):
            candidates.append(n)
        else:
            skipped[n] = f"its fit needs {' or '.join(E.NEEDS[n])} captures among the fit captures"
    caps = [gap_capture_of(c, model, (rois or {}).get(c.id), (distances or {}).get(c.id), (kinds or {}).get(c.id))
            for c in real]
    bar = tqdm(desc="gap", unit="model", disable=not show_progress, total=None)

    def progress(msg):
        bar.set_postfix_str(msg[:40])
        bar.update(1)

    try:
        dg = G.Diagnosis(caps, {c.id: c.depth_m for c in real}, fit_ids, held_ids,
                         CaptureSimulator(geoms, model, seed), EffectFitter(fit_real, model, seed, rois),
                         binning=binning or G.Binning(), n_splits=n_splits, n_boot=n_boot, seed=int(seed),
                         config=config or G.SelectionConfig(), progress=progress)
        res = dg.run(candidates)
    finally:
        bar.close()
    r = res.report
    report = {"format": FORMAT, "real": real_label, "split": {"fit": fit_ids, "heldout": held_ids},
              "baseline": r["baseline"], "where": _where(r["where"]), "effects": r["effects"],
              "final": {**r["final"], "where_unexplained": _where(r["final"]["where_unexplained"], pad=0)}}
    report.update({
        "where_count": sum(1 for e in r["where"] if e["gap"] > 0),
        "heldout_rule": rule, "validation": r["validation"], "candidates": candidates, "skipped": skipped,
        "rounds": r["rounds"], "stop_reason": r["stop_reason"],
        "floor": {"source": r["floor_source"], "n_splits": int(n_splits), "n_boot": int(n_boot),
                  "z_floor": G.Z_FLOOR, "min_floor": dict(G.MIN_FLOOR),
                  "alpha": (config or G.SelectionConfig()).alpha},
        "unavailable": r["unavailable"], "statistics": dict(G.STAT_UNITS), "by": r["by"], "by_final": r["by_final"],
        "frames": r["frames"], "sim_frames": r["sim_frames"], "seed": int(seed), "model": model.to_dict(),
        "binning": {"distance_width_m": dg.binning.distance_width_m, "angle_width_deg": dg.binning.angle_width_deg},
        "captures": [{"id": c.id, "kind": c.kind, "distance_m": c.distance_m, "angle_deg": c.angle_deg,
                      "frames": int(by_id[c.id].n_frames), "heldout": c.id in held_ids} for c in caps],
        "simulated_captures": dg.n_simulated, "seconds": time.perf_counter() - t0,
    })
    if "frames_cut" in r:
        report["frames_cut"] = r["frames_cut"]
    return json_ready(report), res


def load_capture_set(real_dir):
    """Read a capture set into CaptureData (geometry from captures.json, frames from its depth files)."""
    from ..sources.captures import read_capture_set

    cs = read_capture_set(real_dir)
    out = []
    for cap in cs.captures:
        camera = cs.camera_for(cap.id) if cap.is_recording else cs.camera
        g = CaptureGeometry.from_capture_set_entry(camera, cap.to_dict())
        out.append(CaptureData.from_units(g, np.asarray(cs.load_depth(cap.id))))
    return cs, out


def run_gap(real_dir, json_path=None, rrd_path=None, heldout="auto", effects=None, seed: int = 0,
            show_progress: bool = True, model: SensorModel = D435, config: G.SelectionConfig | None = None,
            n_splits: int = 64, n_boot: int = 64, overwrite: bool = False) -> dict:
    """``elevmap gap REAL_CAPTURES``: diagnose a capture set, write the report (and recording).

    Parameters
    ----------
    real_dir : path
        The real capture set (``captures.json`` folder).
    json_path : path, optional
        Write the report there (atomically; an existing file only with ``overwrite``).
    rrd_path : path, optional
        Write a rerun recording there (atomically): gap per stratum as bar charts, before / after,
        real and simulated residual images side by side.
    heldout : "auto", "none", comma-separated ids
    effects : comma-separated names or None (all)
    seed : int
    show_progress : bool
    model : SensorModel
    config : noise_model.analysis.diagnosis.SelectionConfig, optional
    n_splits, n_boot : int
    overwrite : bool
        Replace existing output files (otherwise they are refused before any work).

    Returns
    -------
    dict
        The report. The keys of the spec (``format``, ``real``, ``split``, ``baseline``, ``where``,
        ``effects``, ``final``) plus: ``baseline.gap_all``, ``p_value``, ``significant_fit``,
        ``significant_heldout``, ``null_gap_p95`` (the 95th percentile of real-vs-real aggregate gaps);
        each ``where`` entry's ``z`` (difference / floor), ``floor`` (sigma_0, units of the statistic)
        and ``weight`` (its share of the aggregate); each effect's ``shrink_test`` (paired bootstrap)
        and ``ablation`` (``gap_heldout_without``, ``confirmed``); ``final.gap_fit``, ``gap_all``,
        ``significant``; ``rounds`` (every candidate's fitted parameters and fit gap per round),
        ``stop_reason``, ``candidates``, ``skipped`` (effects whose fits need captures the set lacks),
        ``heldout_rule``, ``validation``, ``floor`` (source, splits, replicates, thresholds),
        ``unavailable`` (statistics that could not be computed, and why), ``statistics`` (units),
        ``by`` / ``by_final`` (mean gap and share per statistic, region, image cell, distance and
        angle bin, before / after), ``captures``, ``frames``, ``sim_frames``, ``seed``, ``model``,
        ``binning``, ``mismatches`` (recordings whose intrinsics differ from captures.json),
        ``seconds``, and ``rrd`` when a recording was written.
    """
    jp, rp = check_outputs({"json_path": json_path, "rrd_path": rrd_path}, overwrite,
                           inputs=[Path(real_dir) / "captures.json"]).values()
    cs, real = load_capture_set(real_dir)
    report, res = diagnose(real, heldout=heldout, effects=effects, seed=seed, model=model,
                           show_progress=show_progress, real_label=str(real_dir), config=config, n_splits=n_splits,
                           n_boot=n_boot)
    report["mismatches"] = list(cs.mismatches)
    if rp is not None:
        log_gap_recording(rp, report, res, real, model, seed)
        report["rrd"] = str(rp)
    if jp is not None:
        write_json_atomic(jp, report)
    return report


# ---------------------------------------------------------------------------------------------
# readable summary
# ---------------------------------------------------------------------------------------------
def _stratum_text(st: dict) -> str:
    parts = [f"{st['distance_m'][0]:g}-{st['distance_m'][1]:g} m", f"{st['angle_deg'][0]:g}-{st['angle_deg'][1]:g} deg"]
    if "image_cell" in st:
        parts.append(f"cell {st['image_cell'][0]},{st['image_cell'][1]}")
    if "region" in st:
        parts.append(st["region"])
    return ", ".join(parts)


def _value_text(stat: str, v) -> str:
    if v is None:
        return "-"
    if stat.endswith("_m"):
        return f"{v * 1e3:.2f} mm"
    if stat.endswith("_px"):
        return f"{v:.2f} px"
    if stat in ("fill_rate", "tail_rate"):
        return f"{100 * v:.2f} %"
    return f"{v:.3f}"


def _params_text(p: dict) -> str:
    return ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in p.items()
                     if k not in ("baseline_m", "seed"))


def format_summary(report: dict, top: int = 8) -> str:
    """The report as readable text: where, which, how far."""
    b, f = report["baseline"], report["final"]
    nf, nh = len(report["split"]["fit"]), len(report["split"]["heldout"])
    out = [f"elevmap gap: {report.get('real') or 'captures'}: {nf + nh} captures ({nf} fit, {nh} held out: "
           f"{report.get('heldout_rule', '')}), {report.get('frames')} frames each, seed {report.get('seed')}",
           f"noise floor: {report['floor']['source']}; "
           f"gap = max(0, |real - sim| / floor - {report['floor']['z_floor']:g})"]
    sig = "SIGNIFICANT" if b["significant"] else "not significant"
    out.append(f"baseline (reference model): gap {b['gap_all']:.3g} over all captures ({sig}, p = {b['p_value']:.3g}; "
               f"real-vs-real 95 %: {b['null_gap_p95']:.3g}); fit {b['gap_fit']:.3g}, held-out {b['gap_heldout']:.3g}")
    if report.get("unavailable"):
        for k, why in report["unavailable"].items():
            out.append(f"  not computed: {k}: {why}")
    out.append("WHERE (largest gaps first):")
    for e in report["where"][:top]:
        out.append(f"  {e['gap']:9.3g}  {e['statistic']:15s} {_stratum_text(e['stratum']):42s} real "
                   f"{_value_text(e['statistic'], e['real'])}, sim {_value_text(e['statistic'], e['sim'])}")
    shares = report["by"]["statistic"]
    out.append("  share of the gap by statistic: " + ", ".join(
        f"{k} {100 * v['share']:.0f} %" for k, v in shares.items() if v["share"] >= 0.005) or "  (no gap)")
    reg = report["by"].get("region", {})
    if reg:
        out.append("  mean gap by region: " + ", ".join(f"{k} {v['gap']:.3g}" for k, v in reg.items()))
    out.append("WHICH (forward selection on the fit captures, validated on the held-out captures):")
    for rnd in report["rounds"]:
        cands = rnd["candidates"]
        head = ", ".join(f"{c['name']} {-100 * c['shrink_fit']:+.0f} %" if c.get("shrink_fit") is not None
                         else f"{c['name']} (fit failed)" for c in cands[:6])
        out.append(f"  round {rnd['round']}: fit gap {rnd['gap_fit_before']:.3g}; candidates: {head}")
        if "chosen" in rnd:
            t = rnd["heldout_test"]
            verdict = "ACCEPTED" if rnd.get("accepted") else "rejected"
            out.append(f"    best {rnd['chosen']}: held-out gap {rnd['gap_heldout_before']:.3g} -> "
                       f"{t['gap_heldout_after']:.3g}, smaller in {100 * t['fraction']:.0f} % of the bootstrap "
                       f"replicates: {verdict}")
    for e in report["effects"]:
        a = e.get("ablation", {})
        conf = "confirmed" if a.get("confirmed") else "NOT confirmed"
        out.append(f"  selected {e['name']}({_params_text(e['params'])}): held-out shrink "
                   f"{100 * e['shrink_heldout']:.1f} %; ablation: without it the held-out gap is "
                   f"{a.get('gap_heldout_without', float('nan')):.3g} ({conf})")
    if not report["effects"]:
        out.append("  nothing selected")
    out.append(f"  stopped: {report['stop_reason']}")
    for name, why in report.get("skipped", {}).items():
        out.append(f"  skipped {name}: {why}")
    out.append(f"HOW FAR: held-out gap {b['gap_heldout']:.3g} -> {f['gap_heldout']:.3g} "
               f"(shrink {100 * f['shrink_heldout']:.1f} %, unexplained {100 * f['unexplained_fraction']:.1f} %; "
               f"{report.get('validation', '')})")
    left = f["where_unexplained"][:top]
    if left:
        out.append("  left unexplained (largest):")
        for e in left:
            out.append(f"  {e['gap']:9.3g}  {e['statistic']:15s} {_stratum_text(e['stratum']):42s} real "
                       f"{_value_text(e['statistic'], e['real'])}, sim {_value_text(e['statistic'], e['sim'])}")
    else:
        out.append("  nothing left above the noise floor")
    out.append(f"({report.get('simulated_captures', 0)} captures simulated in {report.get('seconds', 0):.1f} s)")
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------
# selftest
# ---------------------------------------------------------------------------------------------
def _selftest_camera(width: int, height: int, model: SensorModel) -> dict:
    K = model.intrinsics(width, height)
    return {"width": int(width), "height": int(height), "fx": float(K[0, 0]), "fy": float(K[1, 1]),
            "ppx": float(K[0, 2]), "ppy": float(K[1, 2]), "depth_scale": 0.001, "baseline_m": model.baseline_m}


def selftest_geometries(kind: str = "wall", width: int = 424, height: int = 240,
                        model: SensorModel = D435) -> list[CaptureGeometry]:
    """The selftest's captures: 18 walls (0.5 to 2.0 m every 0.3 m x yaw 0, 30, 55 deg), or 12 boards
    0.60 x 0.90 m before a wall at 3 m (0.6 to 2.1 m every 0.3 m x yaw 0, 30 deg), the sets
    :data:`noise_model.sim.effects.FIT_TOLERANCE` is stated for."""
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


def _selftest_cases(effects, seed: int) -> list[dict]:
    names = parse_effect_names(effects)
    cases = []
    for k, n in enumerate(names):
        p = E.draw_params(n, np.random.default_rng([int(seed), 1, k]))
        cases.append({"case": n, "effects": [(n, p)]})
    cases.append({"case": "none", "effects": []})
    pair = [(n, E.draw_params(n, np.random.default_rng([int(seed), 2, j]))) for j, n in enumerate(SELFTEST_PAIR)]
    cases.append({"case": "+".join(SELFTEST_PAIR), "effects": pair})
    return cases


def _selftest_case(case: dict, seed: int, n_frames: int, width: int, height: int, model: SensorModel,
                   index: int, numba_threads: int | None = None) -> dict:
    """One selftest case: build the pseudo-real captures, diagnose them blind, check the outcome."""
    if numba_threads is not None:
        import numba

        numba.set_num_threads(int(numba_threads))
    t0 = time.perf_counter()
    needs_board = any("board+background" in E.NEEDS[n] for n, _ in case["effects"])
    geoms = selftest_geometries("board" if needs_board else "wall", width, height, model)
    objs = E.canonical_order([E.make_effect(n, **p) for n, p in case["effects"]])
    real = []
    for g in geoms:
        rng = np.random.default_rng([int(seed) + 1_000_003, index, zlib.crc32(g.id.encode("utf-8"))])
        real.append(CaptureData.from_units(g, simulate_capture(g, int(n_frames), rng, model, objs)))
    report, _ = diagnose(real, heldout="auto", effects=None, seed=int(seed), model=model, show_progress=False,
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
            ok, errs = E.within_tolerance(name, true, row["fitted"][name])
            row["param_errors"] = {k: {"error": e, "allowed": a} for k, (e, a) in errs.items()}
        else:
            ok = False
        checks["params_within_tolerance"] = bool(ok)
        checks["shrink_heldout_ge_0.6"] = row["shrink_heldout"] >= 0.6
    else:
        checks["all_found"] = all(n in selected for n, _ in case["effects"])
        checks["shrink_heldout_ge_0.6"] = row["shrink_heldout"] >= 0.6
    row["checks"] = checks
    row["passed"] = all(checks.values())
    return json_ready(row)


def run_selftest(effects=None, seed: int = 0, n_frames: int = 12, width: int = 424, height: int = 240,
                 show_progress: bool = True, json_path=None, n_jobs: int = 1, model: SensorModel = D435,
                 overwrite: bool = False) -> dict:
    """``elevmap gap --selftest``: the diagnosis must find effects it was not told about.

    For every effect of the library (or ``effects``): pseudo-real data = the reference simulation of
    :func:`selftest_geometries` (18 walls, or 12 boards before a background for the edge effects,
    ``n_frames`` frames at ``width`` x ``height``) plus that effect at parameters drawn at random from
    :data:`noise_model.sim.effects.PARAM_RANGES` (seeded by ``seed``; the diagnosis is not given them); the
    diagnosis runs blind over all candidate effects with the ``auto`` held-out block and must rank the
    effect first (first selected), recover its parameters within
    :data:`noise_model.sim.effects.FIT_TOLERANCE` and shrink the held-out gap by at least 60 %. With no
    effect the baseline must not be significant and nothing may be selected; with the two effects of
    :data:`SELFTEST_PAIR` both must be selected.

    Parameters
    ----------
    n_jobs : int
        Cases run in this many processes (1: in this process).
    overwrite : bool
        Replace an existing ``json_path``.

    Returns
    -------
    dict
        ``passed`` (all cases), ``rows`` (one per case: ``case``, ``true`` parameters, ``selected``,
        ``fitted``, ``param_errors``, ``shrink_heldout``, ``checks``, ``passed``, ``seconds``),
        ``settings``, ``seconds``.
    """
    from tqdm import tqdm

    t0 = time.perf_counter()
    cases = _selftest_cases(effects, seed)
    jp = check_outputs({"json_path": json_path}, overwrite)["json_path"]
    if int(n_jobs) <= 1:
        rows = [_selftest_case(c, seed, n_frames, width, height, model, i)
                for i, c in enumerate(tqdm(cases, desc="selftest", unit="case", disable=not show_progress))]
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        ctx = mp.get_context("spawn")
        with ProcessPoolExecutor(max_workers=int(n_jobs), mp_context=ctx) as ex:
            futs = [ex.submit(_selftest_case, c, seed, n_frames, width, height, model, i, 1)
                    for i, c in enumerate(cases)]
            rows = [f.result() for f in tqdm(futs, desc="selftest", unit="case", disable=not show_progress)]
    out = {"passed": all(r["passed"] for r in rows), "rows": rows,
           "settings": {"seed": int(seed), "n_frames": int(n_frames), "width": int(width), "height": int(height),
                        "pair": list(SELFTEST_PAIR)},
           "seconds": time.perf_counter() - t0}
    out = json_ready(out)
    if jp is not None:
        write_json_atomic(jp, out)
    return out


def format_selftest(result: dict) -> str:
    """The selftest as a pass/fail table."""
    lines = [f"{'case':34s} {'selected':38s} {'params':7s} {'shrink':>7s} {'time':>6s}  result"]
    for r in result["rows"]:
        c = r["checks"]
        par = "-" if "params_within_tolerance" not in c else ("ok" if c["params_within_tolerance"] else "FAIL")
        sel = ",".join(r["selected"]) or "(none)"
        if r["case"] == "none":
            sel += " (significant)" if r["significant"] else " (not significant)"
        verdict = "PASS" if r["passed"] else "FAIL " + ",".join(k for k, v in c.items() if not v)
        lines.append(f"{r['case']:34s} {sel[:38]:38s} {par:7s} {100 * r['shrink_heldout']:6.1f}% "
                     f"{r['seconds']:5.0f}s  {verdict}")
        for name, true in r["true"].items():
            fit = r["fitted"].get(name)
            lines.append(f"    {name}: true {_params_text(true)}" + (f"; fitted {_params_text(fit)}" if fit else
                                                                       "; not selected"))
    s = result["settings"]
    lines.append(f"{'PASSED' if result['passed'] else 'FAILED'}: {sum(r['passed'] for r in result['rows'])}/"
                 f"{len(result['rows'])} cases ({s['n_frames']} frames at {s['width']}x{s['height']}, "
                 f"seed {s['seed']}) "
                 f"in {result['seconds']:.0f} s")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# rerun recording
# ---------------------------------------------------------------------------------------------
#: Captures whose images the recording shows (those carrying the largest share of the baseline gap).
RRD_CAPTURES = 6
#: Rows of the chart of the largest gaps.
RRD_TOP = 25


def _bin_gap_share(res: G.DiagnosisResult) -> dict:
    """Baseline gap carried by each (distance bin, angle bin) (weights x gaps), for choosing images."""
    fl = res.baseline_all.floor
    wg = (fl.weights * res.baseline_all.gap).sum(axis=0)
    per_bin: dict = {}
    for k, key in enumerate(fl.keys):
        per_bin[key[:2]] = per_bin.get(key[:2], 0.0) + float(wg[k])
    return per_bin


def log_gap_recording(path, report: dict, res: G.DiagnosisResult, real: Sequence[CaptureData],
                      model: SensorModel = D435, seed: int = 0, binning: G.Binning | None = None) -> None:
    """Write the rerun recording of a diagnosis (atomically): bar charts and images, see :mod:`elevmap.viz.reports`.

    Entities: ``gap/top`` (the largest baseline gaps, before / after the selected effects), ``gap/by_statistic``,
    ``gap/by_region``, ``gap/by_image_cell``, ``gap/by_distance_m``, ``gap/by_angle_deg`` (mean gap per group,
    before / after), ``gap/residual/{real,reference,final}`` and ``gap/fill/{real,reference,final}`` (the mean
    residual over the frames and the fraction of frames with data of one capture per step of the ``capture``
    timeline), ``gap/capture`` and ``gap/summary`` (text).
    """
    from .. import viz

    binning = binning or G.Binning()
    before, after = res.baseline_all, res.final_all
    fl = before.floor
    order = np.dstack(np.unravel_index(np.argsort(-before.gap, axis=None), before.gap.shape))[0]
    top = [(int(s), int(k)) for s, k in order if fl.defined[s, k] and before.gap[s, k] > 0][:RRD_TOP]
    if not top:
        top = [(int(s), int(k)) for s, k in np.dstack(np.unravel_index(np.argsort(-np.nan_to_num(before.z), axis=None),
                                                                        before.z.shape))[0]
               if fl.defined[s, k]][:RRD_TOP]
    charts = []
    by_id = {c.id: c for c in real}
    caps = list(res.captures.values()) or [gap_capture_of(c, model) for c in real]
    share = _bin_gap_share(res)
    ranked = sorted(caps, key=lambda c: -share.get(binning.bins(c), 0.0))[:RRD_CAPTURES]
    sim = CaptureSimulator({c.id: c.geometry for c in real}, model, seed)
    n = report.get("sim_frames") or real[0].n_frames
    ids = [c.id for c in ranked]
    ref = sim(ids, [], n)
    fin = sim(ids, res.selected, n) if res.selected else ref
    with viz.open_recording(path, "elevmap_gap") as rec:
        labels = [f"{G.STATISTICS[s]} | {_stratum_text(binning.stratum(fl.keys[k]))}" for s, k in top]
        viz.log_gap_bars(rec, "gap/top", labels, [[before.gap[s, k] for s, k in top],
                                                  [after.gap[s, k] for s, k in top]],
                         series_names=("reference model", "with the selected effects"),
                         title="largest gaps (log scale: 0, 1, 10, ...)")
        charts.append(("gap/top", len(top)))
        for by in ("statistic", "region", "image_cell", "distance_m", "angle_deg"):
            b, a = report["by"].get(by, {}), report["by_final"].get(by, {})
            keys = list(b)
            if not keys:
                continue
            e = f"gap/by_{by}"
            viz.log_gap_bars(rec, e, keys, [[b[k]["gap"] for k in keys],
                                            [a.get(k, {}).get("gap", np.nan) for k in keys]],
                             series_names=("reference model", "with the selected effects"),
                             title=f"mean gap by {by}")
            charts.append((e, len(keys)))
        keys = ["residual/real", "residual/reference", "residual/final", "fill/real", "fill/reference", "fill/final"]
        for step, c in enumerate(ranked):
            rd = by_id[c.id].depth_m
            zt = np.where(np.isfinite(c.z_true_m), c.z_true_m, np.nan)

            def mean_res(d):
                with np.errstate(invalid="ignore"):
                    r = d - zt[None]
                    cnt = np.isfinite(r).sum(axis=0)
                    return np.where(cnt > 0, np.nansum(r, axis=0) / np.maximum(cnt, 1), np.nan), cnt / d.shape[0]

            imgs = {}
            for name, d in (("real", rd), ("reference", ref[c.id]), ("final", fin[c.id])):
                r, fill = mean_res(d)
                imgs[f"residual/{name}"] = r
                imgs[f"fill/{name}"] = np.where(np.isfinite(zt), fill, np.nan)
            sig = float(np.nanmedian(c.sigma_m)) if np.isfinite(c.sigma_m).any() else 0.01
            note = (f"`{c.id}` ({c.kind}, {c.distance_m:g} m, {c.angle_deg:.0f} deg): mean residual over the frames "
                    f"(+-{3e3 * sig:.1f} mm = 3 median sigma_z; blue nearer, red farther) and fill rate, real | "
                    f"reference model | with {', '.join(n for n, _ in res.selected) or 'no effect'}")
            viz.log_gap_images(rec, step, imgs, note, residual_range_m=3.0 * sig)
        viz.log_text(rec, "gap/summary", "# elevmap gap\n\n```\n" + format_summary(report) + "\n```")
        rec.send_blueprint(viz.gap_blueprint(charts, keys if ranked else []))


# ---------------------------------------------------------------------------------------------
# real single frames: geometry from a plane fitted to a region
# ---------------------------------------------------------------------------------------------
#: Planar regions of the genuine D435 frames in ``shared/realdata`` (rows and columns are half-open pixel
#: ranges of the frame; the regions that touch column 0 contain the left invalid band).
REALDATA_PLANES = (
    {"id": "opf848_board", "file": "opf_d435i_viewer_raw/001_big_depth.raw", "rows": (20, 175), "cols": (300, 430),
     "what": "drawing board on an easel at ~1.63 m, 848x480 (the region of its PROVENANCE.md without the easel's "
             "tray, rows 175-190)"},
    {"id": "opf848_left_wall", "file": "opf_d435i_viewer_raw/001_big_depth.raw", "rows": (20, 190), "cols": (0, 60),
     "what": "wall at ~2 m on the left edge, 848x480, with the left invalid band"},
    {"id": "opf848_floor", "file": "opf_d435i_viewer_raw/001_big_depth.raw", "rows": (400, 470), "cols": (0, 848),
     "what": "floor at grazing incidence, 848x480 (the region of its PROVENANCE.md)"},
    {"id": "opf424_board", "file": "opf_d435i_viewer_raw/001_small_depth.raw", "rows": (52, 90),
     "cols": (150, 228), "what": "the lower half of the same board at ~1.57 m in another capture, 424x240 (above "
                                 "the tray; its upper half leans away)"},
    {"id": "lrs640_wall", "file": "lrs_unittest_bag_d435/single_depth_color_640x480.bag", "rows": (10, 260),
     "cols": (0, 300), "what": "painted wall at ~1.8 m, 640x480 (librealsense's unit-test .bag), with the "
                               "left invalid band"},
)


def plane_geometry(capture_id: str, plane: G.PlaneFit, K, width: int, height: int, depth_scale: float,
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


def _read_realdata_frame(root: Path, rel: str):
    """(uint16 depth (H, W), K, depth_scale) of a realdata file (.raw + CSV, or a RealSense .bag)."""
    p = root / rel
    if p.suffix.lower() == ".raw":
        from ..sources.viewer_raw import read_viewer_raw

        depth, K, meta = read_viewer_raw(p)
        return depth, K, float(meta["depth_scale"])
    from ..sources.realsense import RealSenseFileSource

    with RealSenseFileSource(p) as src:
        frames = [f for f in src]
    if not frames:
        raise ValueError(f"{p}: no depth frame")
    f = frames[0]
    return np.asarray(f.depth), np.asarray(f.K), float(f.depth_scale)


def realdata_captures(root, planes=REALDATA_PLANES, model: SensorModel = D435):
    """Plane captures of the genuine frames: (captures, rois, distances, notes, skipped).

    Each region's plane is fitted (:func:`noise_model.analysis.diagnosis.fit_plane`); the capture is that plane as a
    wall (:func:`plane_geometry`) with the real frame, and only the region's pixels count. Its
    distance bin is the median true depth over the region.
    """
    root = Path(root)
    caps, rois, dists, notes, skipped = [], {}, {}, {}, {}
    cache: dict = {}
    for spec in planes:
        if spec["file"] not in cache:
            cache[spec["file"]] = _read_realdata_frame(root, spec["file"])
        units, K, scale = cache[spec["file"]]
        H, W = units.shape
        roi = np.zeros((H, W), dtype=bool)
        (r0, r1), (c0, c1) = spec["rows"], spec["cols"]
        roi[r0:r1, c0:c1] = True
        depth = np.where(units > 0, units * scale, np.nan)
        try:
            plane = G.fit_plane(depth, K, roi)
            g = plane_geometry(spec["id"], plane, K, W, H, scale, model.baseline_m)
        except ValueError as exc:
            skipped[spec["id"]] = str(exc)
            continue
        data = CaptureData.from_units(g, units[None])
        z, _ = g.render()
        caps.append(data)
        rois[g.id] = roi
        dists[g.id] = float(np.nanmedian(np.where(roi, z, np.nan)))
        notes[g.id] = {"what": spec["what"], "file": spec["file"], "rows": list(spec["rows"]),
                       "cols": list(spec["cols"]), "plane_normal": plane.normal.tolist(),
                       "plane_offset_m": plane.offset_m,
                       "incidence_deg": plane.incidence_deg, "plane_residual_std_m": plane.residual_std_m,
                       "median_depth_m": dists[g.id], "valid_fraction": float(np.isfinite(depth[roi]).mean())}
    return caps, rois, dists, notes, skipped


def run_realdata(root, json_path=None, rrd_path=None, effects=None, seed: int = 0, heldout="none",
                 show_progress: bool = True, model: SensorModel = D435, planes=REALDATA_PLANES,
                 overwrite: bool = False) -> dict:
    """The diagnosis on the genuine single D435 frames of ``shared/realdata`` (no known target).

    Every region of ``planes`` becomes a capture whose geometry is the plane fitted to it; one frame
    each, so the temporal statistics are unavailable and the noise floor comes from the reference
    simulation (sim-vs-sim halves of 8 simulated frames). What remains: fill rate, the spatial
    residuals about the plane (bias, spatial std, correlation length, W1, tails, lattice) and the left
    band, by distance, angle, image cell and region. With a handful of planes from three cameras the
    default is no held-out capture: effects are validated on the fit captures (the report says so).

    Returns
    -------
    dict
        The report of :func:`run_gap` plus ``planes`` (per capture: region, plane, incidence, median
        depth, valid fraction) and ``skipped_planes`` (regions that could not become a capture, why).
    """
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"{root}: no such folder (the genuine D435 recordings)")
    jp, rp = check_outputs({"json_path": json_path, "rrd_path": rrd_path}, overwrite).values()
    caps, rois, dists, notes, skipped = realdata_captures(root, planes, model)
    if not caps:
        raise ValueError(f"{root}: no usable plane ({skipped})")
    binning = G.Binning(distance_width_m=0.1)       # the planes' median depths are 0.1-0.2 m apart
    report, res = diagnose(caps, heldout=heldout, effects=effects, seed=seed, model=model,
                           show_progress=show_progress, rois=rois, distances=dists,
                           kinds={c.id: "plane" for c in caps}, real_label=str(root), binning=binning)
    report["planes"] = notes
    report["skipped_planes"] = skipped
    report = json_ready(report)
    if rp is not None:
        log_gap_recording(rp, report, res, caps, model, seed, binning)
        report["rrd"] = str(rp)
    if jp is not None:
        write_json_atomic(jp, report)
    return report
