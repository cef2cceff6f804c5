"""How ``elevmap compare`` scores a final map against the true terrain: overall, about the step edges, at the
variance floor, over the cells every mapper knows and at equal coverage.

Every function takes a map's known layers (NaN where unknown) or :class:`elevmap.map.ElevationMap`
objects and the true height at the cell centres; heights in metres, variances in square metres, NLL in
nats (the mean Gaussian negative log-likelihood of the true height under each cell's height and variance).
NumPy only; the report's layout is in :mod:`elevmap.commands.compare`.
"""

from __future__ import annotations

import math

import numpy as np

from ..map.elevation_map import ElevationMap
from ..pipeline import edge_band, map_error

__all__ = ["EDGE_RINGS", "FLOOR_MARGIN", "CONFIDENT_ERROR_M", "CONFIDENT_ERROR_SIGMAS", "truth_grid", "score_map",
           "confident_errors", "edge_profile", "floor_profile", "edge_known_fractions", "common_scores",
           "most_confident", "matched_scores"]

#: A confidently wrong cell (:func:`confident_errors`) is off by more than this [m]: a foothold that much too high
#: or too low is a missed step for a legged robot (a stair riser is 0.15-0.2 m, a foot's clearance about 0.1 m).
CONFIDENT_ERROR_M = 0.1
#: ... and by more than this many of its own sigma: the map's variance did not warn of it (a Gaussian error is
#: beyond 4 sigma 6e-5 of the time).
CONFIDENT_ERROR_SIGMAS = 4.0


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


def truth_grid(emap: ElevationMap, truth) -> np.ndarray:
    """The true height [m] at every cell centre of ``emap``'s window, shape (rows, cols) as its layers;
    ``truth`` maps (N, 2) map-frame x, y [m] to N heights."""
    xs, ys = emap.cell_centres()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    return np.asarray(truth(np.column_stack([X.ravel(), Y.ravel()])), dtype=np.float64).reshape(X.shape)


def confident_errors(height, variance, truth) -> int:
    """The known cells that would mislead a controller: off by more than :data:`CONFIDENT_ERROR_M` and by more
    than :data:`CONFIDENT_ERROR_SIGMAS` of their own sigma.

    The mean NLL weighs such a cell by its log-likelihood, so one of them can outweigh a map (a floor cell held
    at a landing's height with a sigma of millimetres scores 1e5 nats); this counts them instead. ``height``,
    ``variance`` and ``truth`` as in :func:`edge_profile` (shape (H, W), NaN where unknown); returns an int.
    """
    height, variance, truth = (np.asarray(a, dtype=np.float64) for a in (height, variance, truth))
    if not height.shape == variance.shape == truth.shape or height.ndim != 2:
        raise ValueError(f"height, variance and truth must be (H, W) grids of one shape, got {height.shape}, "
                         f"{variance.shape} and {truth.shape}")
    known = np.isfinite(height) & np.isfinite(variance) & np.isfinite(truth)
    e = np.abs(height - truth)[known]
    return int(np.sum((e > CONFIDENT_ERROR_M) & (e > CONFIDENT_ERROR_SIGMAS * np.sqrt(variance[known]))))


def score_map(emap: ElevationMap, truth, times) -> dict:
    """A final map's scores against ``truth`` (:func:`elevmap.pipeline.map_error`'s, the mean sigma, the known
    fraction, :func:`confident_errors`) and the median and 95th percentile of ``times`` [ms per frame] (NaN
    when empty)."""
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
           "edge_cells": err["edge_cells"], "edge_coverage_1sigma": err["edge_coverage_1sigma"],
           "edge_coverage_2sigma": err["edge_coverage_2sigma"], "edge_nll": err["edge_nll"],
           "edge_mean_error_m": err["edge_mean_error_m"], "ms_per_frame_p95": float(np.percentile(t, 95)),
           "confident_errors": confident_errors(emap.known_layer("elevation"), emap.known_layer("variance"),
                                                truth_grid(emap, truth))}
    return out


#: A cell whose variance is at most this times the floor counts as at the floor (:func:`floor_profile`).
FLOOR_MARGIN = 1.1

#: Rings of cells about the step edges for :func:`edge_profile`: (first, last) distance from the edge
#: band in 4-connected cell steps (0: the band itself, within two cells of a step).
EDGE_RINGS = ((0, 0), (1, 3), (4, 8), (9, None))


def edge_profile(height, variance, truth) -> list[dict]:
    """Scores of a map's known cells by their distance from the step edges of the true terrain.

    Where the sensor puts an edge's points shows here: edge fattening and bleeding make the band's mean
    error positive on the lower side, flying pixels and points binned at the wrong surface leave errors
    rings away from the band.

    Parameters
    ----------
    height, variance : ndarray, shape (H, W) [m], [m^2]
        The map's known layers (NaN where unknown).
    truth : ndarray, shape (H, W) [m]
        The true height at the cell centres.

    Returns
    -------
    list of dict
        One per ring of :data:`EDGE_RINGS`: ``rings`` (first, last distance), ``cells``, ``rmse_m``,
        ``mean_error_m``, ``coverage_1sigma``, ``coverage_2sigma``, ``nll_sum`` (the ring's share of the NLL
        sum, in nats), ``large_errors`` (cells with |error| > 0.2 m).
    """
    band = edge_band(truth)
    dist = np.full(band.shape, np.iinfo(np.int32).max, dtype=np.int64)
    cur = band.copy()
    dist[cur] = 0
    last = max(r[0] for r in EDGE_RINGS)
    for step in range(1, last + 1):
        grown = cur.copy()
        grown[1:] |= cur[:-1]
        grown[:-1] |= cur[1:]
        grown[:, 1:] |= cur[:, :-1]
        grown[:, :-1] |= cur[:, 1:]
        dist[grown & ~cur] = step
        cur = grown
    known = np.isfinite(height) & np.isfinite(variance)
    err = np.where(known, height - truth, 0.0)
    var = np.where(known, variance, 1.0)
    out = []
    for lo, hi in EDGE_RINGS:
        ring = known & (dist >= lo) & ((dist <= hi) if hi is not None else True)
        e, v = err[ring], var[ring]
        n = int(ring.sum())
        out.append({"rings": [lo, hi], "cells": n,
                    "rmse_m": float(np.sqrt(np.mean(e ** 2))) if n else math.nan,
                    "mean_error_m": float(np.mean(e)) if n else math.nan,
                    "coverage_1sigma": float(np.mean(np.abs(e) <= np.sqrt(v))) if n else math.nan,
                    "coverage_2sigma": float(np.mean(np.abs(e) <= 2.0 * np.sqrt(v))) if n else math.nan,
                    "nll_sum": float(np.sum(0.5 * np.log(2 * np.pi * v) + 0.5 * e ** 2 / v)),
                    "large_errors": int(np.sum(np.abs(e) > 0.2))})
    return out


def floor_profile(height, variance, truth, min_variance: float) -> dict:
    """Scores of the known cells whose variance is at the floor ``min_variance`` [m^2] (within
    :data:`FLOOR_MARGIN`): such a cell reports the floor whatever its points say, so its coverage shows
    whether the floor over- or understates the map's most precise cells. ``height``, ``variance``,
    ``truth``: (H, W) [m], [m^2], [m] as in :func:`edge_profile`. Returns ``cells``, ``fraction`` (of the
    known cells), ``rmse_m``, ``coverage_1sigma``, ``coverage_2sigma`` (NaN without such cells)."""
    known = np.isfinite(height) & np.isfinite(variance) & np.isfinite(truth)
    at = known & (variance <= FLOOR_MARGIN * min_variance)
    n = int(at.sum())
    e, s = (height - truth)[at], np.sqrt(variance[at])
    return {"cells": n, "fraction": float(n / known.sum()) if known.any() else math.nan,
            "rmse_m": float(np.sqrt(np.mean(e ** 2))) if n else math.nan,
            "coverage_1sigma": float(np.mean(np.abs(e) <= s)) if n else math.nan,
            "coverage_2sigma": float(np.mean(np.abs(e) <= 2.0 * s)) if n else math.nan}


def edge_known_fractions(maps: dict, truth) -> tuple[int, dict]:
    """The step-edge band's cells that some mapper knows (the band the walk saw), and per mapper the
    fraction of them it knows."""
    first = next(iter(maps.values()))
    band = edge_band(truth_grid(first, truth))
    seen = np.zeros(band.shape, dtype=bool)
    for m in maps.values():
        seen |= m.is_known()
    seen &= band
    n = int(seen.sum())
    return n, {name: (float((m.is_known() & seen).sum() / n) if n else math.nan) for name, m in maps.items()}


def common_scores(maps: dict, truth) -> dict:
    """Each mapper's scores over the cells every mapper of ``maps`` (name -> ElevationMap) knows, and their
    number (``cells``): the comparison free of which cells each map knows."""
    if not maps:
        return {"cells": 0, "mappers": {}}
    first = next(iter(maps.values()))
    xs, ys = first.cell_centres()
    for name, m in maps.items():
        a, b = m.cell_centres()
        if not (np.array_equal(a, xs) and np.array_equal(b, ys)):
            raise RuntimeError(f"map of {name!r} is not on the same cells as the others")
    tr = truth_grid(first, truth)
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


def matched_scores(maps: dict, truth) -> dict:
    """Scores at equal coverage: each mapper over its N most confident known cells (smallest variance),
    N the fewest known cells of any mapper. What a consumer gets who keeps the N cells its map trusts
    most; a model whose variances rank its cells by their error well scores better."""
    if not maps:
        return {"cells": 0, "mappers": {}}
    n = min(int(m.is_known().sum()) for m in maps.values())
    tr = truth_grid(next(iter(maps.values())), truth)
    out = {}
    for name, m in maps.items():
        v = m.layer("variance")
        out[name] = _cell_scores(m.layer("elevation"), v, tr, most_confident(v, m.is_known(), n))
    return {"cells": n, "mappers": out}
