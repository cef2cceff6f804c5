"""``elevmap gap``: where the paper's D435 model misses real captures, which effect explains it, how far it shrinks.

The command around :func:`noise_model.analysis.diagnosis.diagnose` (the method and the report's keys
are documented there): it reads a capture set (format ``d435-captures/1``, see
docs/capture-set-format.md), shows a progress bar, writes the JSON report of format ``d435-gap/1``
atomically, prints a readable summary (:func:`format_summary`) and writes an optional rerun recording
(:func:`log_gap_recording`).

``run_selftest`` checks the whole chain on pseudo-real data (the reference simulation plus known effects at
random parameters); ``run_realdata`` runs on single real frames whose geometry is a plane fitted to a region.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from noise_model.analysis import diagnosis as G
from noise_model.analysis.capture_data import CaptureData
from noise_model.analysis.diagnosis import (
    FORMAT, SELFTEST_PAIR, SELFTEST_STATIC_PAIR, CaptureSimulator, diagnose, gap_capture_of, parse_effect_names, plane_geometry,
    selftest_case, selftest_cases, selftest_geometries, split_captures,
)
from noise_model.analysis.planes import fit_plane_ransac
from noise_model.d435 import D435, SensorModel

from ..fileio import check_outputs, json_ready, write_json_atomic

# diagnose, split_captures, parse_effect_names, selftest_geometries and SELFTEST_PAIR are the library's
# (noise_model.analysis.diagnosis), importable from here too for the examples and tests that use them.
__all__ = ["FORMAT", "run_gap", "run_selftest", "run_realdata", "format_summary", "format_selftest",
           "REALDATA_PLANES", "realdata_captures", "load_capture_set", "load_capture_sets", "log_gap_recording",
           "diagnose", "split_captures", "parse_effect_names", "selftest_geometries", "SELFTEST_PAIR",
           "SELFTEST_STATIC_PAIR"]


@contextlib.contextmanager
def _model_bar(show: bool):
    """A tqdm bar stepped once per simulated model: yields the ``progress(message)`` callback of
    :func:`noise_model.analysis.diagnosis.diagnose`."""
    from tqdm import tqdm

    bar = tqdm(desc="gap", unit="model", disable=not show, total=None)

    def progress(msg: str) -> None:
        bar.set_postfix_str(msg[:40])
        bar.update(1)

    try:
        yield progress
    finally:
        bar.close()


def load_capture_set(real_dir):
    """Read a capture set into CaptureData (geometry, mask and the geometry's origin from captures.json,
    frames from its depth files)."""
    from ..sources.captures import read_capture_set

    cs = read_capture_set(real_dir)
    out = []
    for cap in cs.captures:
        camera = cs.camera_for(cap.id) if cap.is_recording else cs.camera
        out.append(CaptureData.from_capture_entry(camera, cap.to_dict(), np.asarray(cs.load_depth(cap.id)),
                                                  cs.load_mask(cap.id)))
    return cs, out


def load_capture_sets(real_dirs):
    """Read one capture set or several into one list of CaptureData (ids must be unique across the sets).

    Returns
    -------
    sets : list of CaptureSet
    captures : list of CaptureData
    """
    dirs = [real_dirs] if isinstance(real_dirs, (str, os.PathLike)) else list(real_dirs)
    if not dirs:
        raise ValueError("give at least one capture-set folder")
    sets, caps, where = [], [], {}
    for d in dirs:
        cs, data = load_capture_set(d)
        for c in data:
            if c.id in where:
                raise ValueError(f"capture id {c.id!r} is in both {where[c.id]} and {d}: ids must be unique "
                                 "across the capture sets diagnosed together")
            where[c.id] = str(d)
        sets.append(cs)
        caps += data
    return sets, caps


def run_gap(real_dir, json_path=None, rrd_path=None, heldout="auto", effects=None, seed: int = 0,
            show_progress: bool = True, model: SensorModel = D435, config: G.SelectionConfig | None = None,
            n_splits: int = 64, n_boot: int = 64, overwrite: bool = False, depth_bands=None,
            direct: bool = False, n_jobs: int = 1) -> dict:
    """``elevmap gap REAL_CAPTURES [REAL_CAPTURES ...]``: diagnose capture sets, write the report (and recording).

    Parameters
    ----------
    real_dir : path or sequence of paths
        The real capture set (``captures.json`` folder), or several diagnosed together as one (e.g. the
        boards and the walls of one camera; capture ids unique across them).
    json_path : path, optional
        Write the report there (atomically; an existing file only with ``overwrite``).
    rrd_path : path, optional
        Write a rerun recording there (atomically): gap per stratum as bar charts, before / after,
        real and simulated residual images side by side.
    heldout : "auto", "none", comma-separated ids
    effects : comma-separated names or None (all)
    seed : int
    show_progress : bool
        A progress bar over the simulated models.
    model : SensorModel
    config : noise_model.analysis.diagnosis.SelectionConfig, optional
    n_splits, n_boot : int
    overwrite : bool
        Replace existing output files (otherwise they are refused before any work).
    depth_bands : sequence of float or comma-separated str, optional
        Split every capture into bands of true depth at these edges [m]
        (:func:`noise_model.analysis.diagnosis.split_by_depth`): a slanted plane (a floor) then fills one
        stratum per band, at the band's median depth and incidence angle. Held-out ids may name the
        captures before the split (all their bands are held out).
    direct : bool
        Also measure the effects directly on the captures and on the final model's simulation of them
        (:mod:`noise_model.analysis.diagnosis.direct`), and put each fitted parameter that has a direct
        meaning next to its measurement (report key ``direct``).
    n_jobs : int
        Processes that simulate the captures of each model (the report is the same for any number).

    Returns
    -------
    dict
        The report of :func:`noise_model.analysis.diagnosis.diagnose` plus ``mismatches`` (recordings
        whose intrinsics differ from captures.json), ``rrd`` when a recording was written and, with
        ``depth_bands``, ``depth_bands`` (the edges and each part's capture).
    """
    dirs = [real_dir] if isinstance(real_dir, (str, os.PathLike)) else list(real_dir)
    jp, rp = check_outputs({"json_path": json_path, "rrd_path": rrd_path}, overwrite,
                           inputs=[Path(d) / "captures.json" for d in dirs]      # and a set's depth files:
                           + [Path(d) for d in dirs if (Path(d) / "captures.json").is_file()]).values()
    sets, real = load_capture_sets(dirs)
    distances = angles = parents = None
    if depth_bands is not None:
        edges = _parse_edges(depth_bands)
        real, parents, distances, angles = G.split_by_depth(real, edges)
        heldout = _expand_heldout(heldout, parents)
    with _model_bar(show_progress) as progress:
        report, res = diagnose(real, heldout=heldout, effects=effects, seed=seed, model=model, progress=progress,
                               real_label=", ".join(str(d) for d in dirs), config=config, n_splits=n_splits,
                               n_boot=n_boot, distances=distances, angles=angles, jobs=n_jobs)
    report["mismatches"] = [m for cs in sets for m in cs.mismatches]
    if parents is not None:
        report["depth_bands"] = {"edges_m": list(edges), "parts": parents}
    if direct:
        report["direct"] = direct_check(real, res.selected, model, seed, report.get("sim_frames") or 2,
                                        heldout_ids=report["split"]["heldout"])
    if rp is not None:
        log_gap_recording(rp, report, res, real, model, seed)
        report["rrd"] = str(rp)
    if jp is not None:
        write_json_atomic(jp, report)
    return report


def direct_check(real, selected, model: SensorModel = D435, seed: int = 0, n_frames: int = 2,
                 heldout_ids=None) -> dict:
    """The direct measurements of the real captures and of the final model's simulation of them, and each
    fitted parameter next to its measurement (:func:`noise_model.analysis.diagnosis.direct.check_fitted`;
    ``heldout_ids``: the final model's ratios also over the fit and the held-out captures apart).

    The simulation is the diagnosis's own (:class:`noise_model.analysis.diagnosis.CaptureSimulator`, the
    same seeds), one capture at a time.
    """
    from noise_model.analysis.diagnosis.direct import check_fitted, direct_measurements

    sim = CaptureSimulator({c.id: c.geometry for c in real}, model, seed)

    def simulated():
        for c in real:
            yield CaptureData(c.geometry, sim([c.id], list(selected), int(n_frames))[c.id], c.mask,
                              c.geometry_origin)

    measured = direct_measurements(real)
    model_measured = direct_measurements(simulated())
    effects = [{"name": n, "params": p} for n, p in selected]
    return {"real": measured, "final_model": model_measured,
            "check": check_fitted(effects, measured, model_measured, heldout_ids=heldout_ids)}


def _parse_edges(depth_bands) -> list[float]:
    """Depth band edges [m] from a comma-separated string or a sequence of numbers."""
    items = depth_bands.split(",") if isinstance(depth_bands, str) else list(depth_bands)
    try:
        return [float(x) for x in items]
    except (TypeError, ValueError):
        raise ValueError(f"--depth-bands must be comma-separated metres, e.g. 0.6,0.8,1.0, got {depth_bands!r}") \
            from None


def _expand_heldout(heldout, parents: dict):
    """Held-out ids that name captures before a depth split stand for all their parts."""
    if heldout is None or not isinstance(heldout, (str, list, tuple)):
        return heldout
    if isinstance(heldout, str) and heldout.strip().lower() in ("", "auto", "none"):
        return heldout
    names = [x.strip() for x in heldout.split(",")] if isinstance(heldout, str) else [str(x) for x in heldout]
    out = []
    for n in names:
        kids = [p for p, parent in parents.items() if parent == n]
        out += kids if kids else [n]
    return ",".join(out)


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
    if report.get("fitted_geometry"):
        fg = report["fitted_geometry"]
        out.append(f"  fitted geometry ({len(fg['captures'])} captures): not computed: {fg['not_computed']}")
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
        for bf in rnd.get("backfit", []):
            also = "".join(f" with {w['name']}({_params_text(w['params'])})" for w in bf.get("refit_with", ()))
            if bf.get("kept"):
                out.append(f"    refitted {bf['name']}({_params_text(bf['params'])}){also} on top of the others: "
                           f"held-out gap {bf['gap_heldout_before']:.3g} -> {bf['gap_heldout_after']:.3g}")
            else:
                out.append(f"    refit of {bf['name']}{also} not kept ({bf.get('why') or bf.get('error', '')})")
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
    if report.get("direct"):
        dp = report["direct"]["real"]["pooled"]
        out.append("DIRECT measurements of the real captures: " + ", ".join(
            f"{k} {v:.4g}" for k, v in dp.items() if v is not None and math.isfinite(v)))
        out.extend(format_direct_check(report["direct"]["check"]))
    out.append(f"({report.get('simulated_captures', 0)} captures simulated in {report.get('seconds', 0):.1f} s)")
    return "\n".join(out)


def format_direct_check(rows) -> list[str]:
    """Lines of the direct check (:func:`noise_model.analysis.diagnosis.direct.check_fitted`'s rows): each
    fitted parameter against its direct measurement, and the final model's ratios with their medians by
    incidence angle and over the fit and held-out captures apart (captures in brackets)."""
    out = []
    for row in rows:
        out.append(f"  {row['quantity']:60s} {row['effect']:24s} fitted {row['fitted']:.4g}, direct "
                   f"{row['direct']:.4g}: ratio {row['ratio']:.3f} ({'agrees' if row['agrees'] else 'DISAGREES'})")
        if row.get("ratio_by_angle"):
            out.append("    by incidence angle: " + ", ".join(
                f"{b['angle_deg'][0]:.0f}-{b['angle_deg'][1]:.0f} deg {b['ratio']:.2f} ({b['captures']})"
                for b in row["ratio_by_angle"]))
        if row.get("ratio_by_split"):
            names = {"fit": "fit captures", "heldout": "held-out captures"}
            out.append("    " + ", ".join(f"{names[k]} {v['ratio']:.2f} ({v['captures']})"
                                          for k, v in row["ratio_by_split"].items()))
    return out


def _expected_cost(case: dict) -> float:
    """A rank of a selftest case's run time: every hidden effect adds a round, a static field's fit and its
    second realisation double one, correlated fields cost their draws."""
    names = [n for n, _ in case["effects"]]
    return len(names) + sum(1.0 for n in names if n.startswith("static")) + 0.5 * names.count("correlated_noise")


def run_selftest(effects=None, seed: int = 0, n_frames: int = 12, width: int = 424, height: int = 240,
                 show_progress: bool = True, json_path=None, n_jobs: int = 1, model: SensorModel = D435,
                 overwrite: bool = False) -> dict:
    """``elevmap gap --selftest``: the diagnosis must find effects it was not told about.

    For every effect of the library but those in
    :data:`noise_model.analysis.diagnosis.run.SELFTEST_UNSEEN` (or every one of ``effects``, those
    included): pseudo-real data = the reference simulation of
    :func:`selftest_geometries` (18 walls, or 12 boards before a background for the edge effects,
    ``n_frames`` frames at ``width`` x ``height``) plus that effect at parameters drawn at random from
    :data:`noise_model.sim.effects.PARAM_RANGES` (seeded by ``seed``; the diagnosis is not given them); the
    diagnosis runs blind over all candidate effects with the ``auto`` held-out block and must rank the
    effect first (first selected), recover its parameters within
    :data:`noise_model.analysis.effect_fits.FIT_TOLERANCE` and shrink the held-out gap by at least 60 %. With no
    effect the baseline must not be significant and nothing may be selected; with the two effects of
    :data:`SELFTEST_PAIR` both must be selected; with the static and the per-frame field of
    :data:`SELFTEST_STATIC_PAIR` both must be selected and each fitted within tolerance (the static and the
    temporal part told apart with ``n_frames`` frames).

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
    cases = selftest_cases(effects, seed)
    jp = check_outputs({"json_path": json_path}, overwrite)["json_path"]
    if int(n_jobs) <= 1:
        rows = [selftest_case(c, seed, n_frames, width, height, model, i)
                for i, c in enumerate(tqdm(cases, desc="selftest", unit="case", disable=not show_progress))]
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed

        ctx = mp.get_context("spawn")
        # the longest cases first (the static fields' and the pairs' take twice the others' time), so that no
        # process is left alone with a long case at the end; the rows keep the cases' order
        order = sorted(range(len(cases)), key=lambda i: -_expected_cost(cases[i]))
        with ProcessPoolExecutor(max_workers=int(n_jobs), mp_context=ctx) as ex:
            futs = {i: ex.submit(selftest_case, cases[i], seed, n_frames, width, height, model, i, 1) for i in order}
            for _ in tqdm(as_completed(futs.values()), total=len(futs), desc="selftest", unit="case",
                          disable=not show_progress):
                pass
            rows = [futs[i].result() for i in range(len(cases))]
    out = {"passed": all(r["passed"] for r in rows), "rows": rows,
           "settings": {"seed": int(seed), "n_frames": int(n_frames), "width": int(width), "height": int(height),
                        "pair": list(SELFTEST_PAIR),
                        "static_pair": list(SELFTEST_STATIC_PAIR)},
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
#: Planar regions of the genuine D435 frames of ``elevmap gap --realdata DIR`` (``file`` is relative to DIR;
#: rows and columns are half-open pixel ranges of the frame; the regions that touch column 0 contain the
#: left invalid band).
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

    Each region's plane is fitted (:func:`noise_model.analysis.planes.fit_plane_ransac`); the capture is that
    plane as a wall (:func:`noise_model.analysis.diagnosis.plane_geometry`) with the real frame, and only the
    region's pixels count. Its distance bin is the median true depth over the region.
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
            plane = fit_plane_ransac(depth, K, roi)
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
    """The diagnosis on genuine single D435 frames (no known target): the folder ``root`` of recordings holds
    the files of ``planes``.

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
    jp, rp = check_outputs({"json_path": json_path, "rrd_path": rrd_path}, overwrite, inputs=[root]).values()
    caps, rois, dists, notes, skipped = realdata_captures(root, planes, model)
    if not caps:
        raise ValueError(f"{root}: no usable plane ({skipped})")
    binning = G.Binning(distance_width_m=0.1)       # the planes' median depths are 0.1-0.2 m apart
    with _model_bar(show_progress) as progress:
        report, res = diagnose(caps, heldout=heldout, effects=effects, seed=seed, model=model, progress=progress,
                               rois=rois, distances=dists, kinds={c.id: "plane" for c in caps},
                               real_label=str(root), binning=binning)
    report["planes"] = notes
    report["skipped_planes"] = skipped
    report = json_ready(report)
    if rp is not None:
        log_gap_recording(rp, report, res, caps, model, seed, binning)
        report["rrd"] = str(rp)
    if jp is not None:
        write_json_atomic(jp, report)
    return report
