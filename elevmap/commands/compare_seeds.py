"""``elevmap compare --seeds N``: the comparison over several seeds, scored as median and spread.

One seed is one box layout and one draw of the noise: a mapper can win or lose a walk by a handful of
cells (docs/calibration.md). Over seeds s, s + 1, ..., s + N - 1 each mapper's scores are summarised
by their median, minimum and maximum, and the calibration criteria are checked on the medians:

* 2-sigma coverage in [0.93, 0.97] and 1-sigma coverage in [0.64, 0.73] (a calibrated map has 0.954
  and 0.683; the bands allow the spread of a few thousand correlated cells);
* the lowest median NLL of all mappers;
* a median RMSE within 5 % of the best mapper's.

Mappers know different cells (a mapper stating small variances has more cells cleared by the visibility
clean-up; a pessimistic one keeps far cells the others drop), so the RMSE over each mapper's own known
cells also compares cell sets. The summary therefore gives ``common_rmse_m`` too, the RMSE over the cells
every mapper knows (the run's ``common`` scores), and the criteria say whether its median is within 5 %
of the best mapper's (``common_rmse_within_5pct``, next to the criterion on the own cells, which stays
the verdict).

Report (JSON)::

    {"scene", "reality", "gap_report", "preset", "seeds": [int, ...], "width", "height", "frames",
     "runs": [the report of elevmap.commands.compare.run_compare, one per seed],
     "summary": {mapper: {key: {"median", "min", "max", "values": [...]}}},
     "criteria": {mapper: {"coverage_2sigma", "coverage_1sigma", "lowest_nll", "rmse_within_5pct", "all",
                           "rmse_vs_best", "common_rmse_within_5pct", "common_rmse_vs_best"}}}
"""

from __future__ import annotations

import math

import numpy as np

from .compare import run_compare
from .compare_output import _fmt, _reality_text, _table
from .compare_scores import CONFIDENT_ERROR_M, CONFIDENT_ERROR_SIGMAS

__all__ = ["SUMMARY_KEYS", "COVERAGE_2SIGMA_BAND", "COVERAGE_1SIGMA_BAND", "RMSE_TOLERANCE", "run_compare_seeds",
           "summarise", "criteria", "format_seeds_table"]

#: The per-mapper scores summarised over seeds.
SUMMARY_KEYS = ("rmse_m", "nll", "coverage_1sigma", "coverage_2sigma", "mean_sigma_m", "known_fraction",
                "flat_rmse_m", "flat_nll", "flat_coverage_2sigma", "edge_rmse_m", "edge_mean_error_m",
                "edge_coverage_2sigma", "edge_nll", "edge_known_fraction", "p95_abs_m", "ms_per_frame",
                "common_rmse_m", "confident_errors")
#: The calibration bands on the median coverages.
COVERAGE_2SIGMA_BAND = (0.93, 0.97)
COVERAGE_1SIGMA_BAND = (0.64, 0.73)
#: The median RMSE may exceed the best mapper's by this fraction.
RMSE_TOLERANCE = 0.05


def run_compare_seeds(scene: str = "stairs", n_frames: int | None = None, *, seeds=(0,), show_progress=True,
                      on_run=None, **kwargs) -> dict:
    """:func:`elevmap.commands.compare.run_compare` once per seed, and the summary over the seeds.

    Parameters
    ----------
    scene : str
    n_frames : int, optional
    seeds : sequence of int
        Distinct seeds, at least one.
    on_run : callable, optional
        ``on_run(report)`` after each seed (a progress line).
    **kwargs
        The other arguments of ``run_compare`` (``rrd_path`` is not taken: one recording per seed
        would be needed).

    Returns
    -------
    dict
        The report (module docstring).
    """
    seeds = [_check_seed(s) for s in seeds]
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds must be distinct integers, at least one, got {seeds!r}")
    if kwargs.get("rrd_path") is not None:
        raise ValueError("a recording is written for one seed only")
    runs = []
    for s in seeds:
        r = run_compare(scene, n_frames, seed=s, show_progress=show_progress, **kwargs)
        runs.append(r)
        if on_run is not None:
            on_run(r)
    first = runs[0]
    summary = summarise(runs)
    return {"scene": scene, "reality": first["reality"], "gap_report": first.get("gap_report"),
            "preset": first.get("preset"), "seeds": seeds, "width": first["width"], "height": first["height"],
            "frames": [r["frames"] for r in runs], "sim_effects": first["sim_effects"], "cap": first["cap"],
            "runs": runs, "summary": summary, "criteria": criteria(summary)}


def _check_seed(s) -> int:
    if isinstance(s, bool) or not isinstance(s, (int, np.integer)):
        raise ValueError(f"seeds must be integers, got {s!r}")
    return int(s)


def summarise(runs) -> dict:
    """Per mapper and score of :data:`SUMMARY_KEYS`: median, min, max and the values over the runs
    (NaN values, e.g. a walk without step edges, are left out; all NaN gives NaN)."""
    names = list(runs[0]["mappers"])
    for r in runs:
        if list(r["mappers"]) != names:
            raise ValueError("every run must have the same mappers")
    out = {}
    for name in names:
        out[name] = {}
        for key in SUMMARY_KEYS:
            vals = [_score(r, name, key) for r in runs]
            vals = [math.nan if v is None else float(v) for v in vals]
            finite = [v for v in vals if math.isfinite(v)]
            out[name][key] = {"median": float(np.median(finite)) if finite else math.nan,
                              "min": min(finite) if finite else math.nan,
                              "max": max(finite) if finite else math.nan, "values": vals}
    return out


def _score(run: dict, name: str, key: str):
    """Mapper ``name``'s score in one run; ``flat_nll`` (the mean NLL of the known cells outside the step-edge
    band) from its edge profile, ``common_rmse_m`` from the run's scores over the cells every mapper knows
    (None when the run has none)."""
    m = run["mappers"][name]
    if key == "common_rmse_m" and key not in m:
        return ((run.get("common") or {}).get("mappers") or {}).get(name, {}).get("rmse_m")
    if key == "flat_nll" and key not in m:
        rings = (m.get("edge_profile") or [])[1:]
        n = sum(r["cells"] for r in rings)
        return sum(r["nll_sum"] for r in rings) / n if n else None
    return m.get(key)


def criteria(summary: dict) -> dict:
    """The calibration criteria of the module docstring on each mapper's medians."""
    med = {n: {k: v["median"] for k, v in s.items()} for n, s in summary.items()}
    best_rmse = min(m["rmse_m"] for m in med.values())
    common = [m["common_rmse_m"] for m in med.values() if math.isfinite(m.get("common_rmse_m", math.nan))]
    best_common = min(common) if common else math.nan
    out = {}
    for name, m in med.items():
        others = [o["nll"] for n, o in med.items() if n != name]
        c = {"coverage_2sigma": COVERAGE_2SIGMA_BAND[0] <= m["coverage_2sigma"] <= COVERAGE_2SIGMA_BAND[1],
             "coverage_1sigma": COVERAGE_1SIGMA_BAND[0] <= m["coverage_1sigma"] <= COVERAGE_1SIGMA_BAND[1],
             "lowest_nll": all(m["nll"] < o for o in others),
             "rmse_within_5pct": m["rmse_m"] <= (1 + RMSE_TOLERANCE) * best_rmse,
             "rmse_vs_best": m["rmse_m"] / best_rmse - 1 if best_rmse > 0 else math.nan}
        mc = m.get("common_rmse_m", math.nan)
        c["common_rmse_vs_best"] = mc / best_common - 1 if math.isfinite(mc) and best_common > 0 else math.nan
        c["common_rmse_within_5pct"] = bool(math.isfinite(mc) and mc <= (1 + RMSE_TOLERANCE) * best_common)
        c["all"] = bool(c["coverage_2sigma"] and c["coverage_1sigma"] and c["lowest_nll"] and c["rmse_within_5pct"])
        out[name] = c
    return out


def format_seeds_table(report: dict) -> str:
    """The summary as a plain-text table: medians with [min, max], the criteria per mapper."""
    seeds = report["seeds"]
    head = (f"scene {report['scene']}, seeds {seeds[0]}..{seeds[-1]} ({len(seeds)}), frames "
            f"{min(report['frames'])}-{max(report['frames'])} {report['width']}x{report['height']}, reality "
            f"{_reality_text(report)}; medians over the seeds [min, max]")

    def cell(s, key, scale, digits):
        v = s[key]
        return f"{_fmt(v['median'], scale, digits)} [{_fmt(v['min'], scale, digits)}, {_fmt(v['max'], scale, digits)}]"

    cols = ("mapper", "RMSE", "common RMSE", "NLL", "cov1s", "cov2s", "mean s", "flat NLL", "edge RMSE", "edge cov2s",
            "edge known", "wrong", "criteria")
    units = ("", "mm", "mm", "", "%", "%", "mm", "", "mm", "%", "%", "cells", "")
    rows = []
    for name, s in report["summary"].items():
        c = report["criteria"][name]
        verdict = ("all met" if c["all"] else ", ".join(k for k in ("coverage_2sigma", "coverage_1sigma", "lowest_nll",
                                                                     "rmse_within_5pct") if not c[k]) + " missed")
        rows.append((name, cell(s, "rmse_m", 1e3, 1), cell(s, "common_rmse_m", 1e3, 1), cell(s, "nll", 1, 2),
                     cell(s, "coverage_1sigma", 100, 1),
                     cell(s, "coverage_2sigma", 100, 1), cell(s, "mean_sigma_m", 1e3, 1), cell(s, "flat_nll", 1, 2),
                     cell(s, "edge_rmse_m", 1e3, 1),
                     cell(s, "edge_coverage_2sigma", 100, 1), cell(s, "edge_known_fraction", 100, 1),
                     cell(s, "confident_errors", 1, 0), verdict))
    out = [head] + _table(cols, units, rows)
    lo2, hi2 = COVERAGE_2SIGMA_BAND
    out.append(f"criteria on the medians: 2-sigma in [{lo2}, {hi2}], 1-sigma in "
               f"[{COVERAGE_1SIGMA_BAND[0]}, {COVERAGE_1SIGMA_BAND[1]}], the lowest NLL, RMSE within "
               f"{RMSE_TOLERANCE:.0%} of the best mapper's (common RMSE: over the cells every mapper knows; not a "
               f"criterion); wrong: known cells off by more than {CONFIDENT_ERROR_M:g} m and "
               f"{CONFIDENT_ERROR_SIGMAS:g} sigma (not a criterion)")
    return "\n".join(out)
