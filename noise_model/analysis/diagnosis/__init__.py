"""Sim-to-real gap: where the paper's model misses real captures, which depth effect explains it, how far.

Real captures of a planar target are compared with their reference simulation (the paper's model)
statistic by statistic and stratum by stratum; each difference is normalised by the real-vs-real noise
floor (random halves of the real frames); forward selection then adds the effects of the effects
library that shrink the gap on held-out captures. The effects, and the E-numbers the statistics cite,
are described in docs/depth-effects.md; the capture sets and the report in docs/capture-set-format.md.
NumPy, SciPy and numba; no files, no progress bars, no rerun: ``elevmap gap`` reads capture sets and
writes the report and recording.

The modules, in the order the data flows:

* :mod:`.strata` -- :class:`GapCapture` (a capture's noise-free geometry, sigma_z and regions), the
  local strata (3 x 3 image cells, regions) and :class:`Binning` (distance and angle bins).
* :mod:`.sums` -- the statistics (:data:`STATISTICS`): per-frame sums of a capture in one numba pass
  (and its NumPy reference), rows of frame weights (full sample, half-splits, bootstrap), pooling over
  captures, the statistics from the sums.
* :mod:`.floor` -- the noise floor, the normalised gap against one simulated model, the paired
  bootstrap shrink test, gaps grouped by statistic, region, cell, distance or angle.
* :mod:`.selection` -- :class:`Diagnosis`: baseline, forward selection of effects, ablation.
* :mod:`.run` -- :func:`diagnose` on captures in memory: the held-out split, simulations and effect
  fits with common random numbers, the ``d435-gap/1`` report; the selftest's pseudo-real cases; a
  fitted plane as a capture (:func:`plane_geometry`).

Callers use the package: ``from noise_model.analysis import diagnosis as G; G.diagnose(...)``.
"""

from __future__ import annotations

from .floor import _MIN_FLOOR  # MIN_FLOOR as an array over STATISTICS (the tests use it)
from .floor import (
    MIN_FLOOR, MIN_SIGNIFICANT_GAP, Z_CAP, Z_FLOOR, Floor, GapResult, aggregate_by, compare, make_floor, shrink_test,
)
from .run import (
    FORMAT, MAX_WHERE, SELFTEST_PAIR, SELFTEST_STATIC_PAIR, CaptureSimulator, EffectFitter, auto_heldout,
    capture_rng, diagnose, gap_capture_of, parse_effect_names, plane_geometry, selftest_case, selftest_cases,
    selftest_geometries, split_by_depth, split_captures,
)
from .selection import Diagnosis, DiagnosisResult, SelectionConfig, model_key
from .strata import LOCAL_STRATA, MAX_RANGE_M, REGIONS, Binning, GapCapture, make_gap_capture
from .sums import (
    CORE_SIGMAS, HIST_CENTRES, HIST_EDGES, LAGS_PX, LATTICE_STEPS_PER_PX, MIN_COUNT, STAT_UNITS, STATISTICS,
    TAIL_SIGMAS, FrameSampling, capture_sums, capture_sums_reference, frame_sampling, pool_sums, statistic_values,
    wasserstein1_hist,
)

__all__ = [
    "STATISTICS", "STAT_UNITS", "REGIONS", "LOCAL_STRATA", "MIN_FLOOR", "Z_FLOOR", "MIN_SIGNIFICANT_GAP",
    "GapCapture", "make_gap_capture", "FrameSampling", "frame_sampling", "capture_sums", "capture_sums_reference",
    "Binning", "pool_sums", "statistic_values", "Floor", "make_floor", "GapResult", "compare", "shrink_test",
    "Diagnosis", "DiagnosisResult", "SelectionConfig", "model_key", "wasserstein1_hist", "aggregate_by",
    "HIST_EDGES", "HIST_CENTRES", "LAGS_PX", "LATTICE_STEPS_PER_PX", "TAIL_SIGMAS", "CORE_SIGMAS", "MAX_RANGE_M",
    "Z_CAP", "MIN_COUNT",
    "FORMAT", "MAX_WHERE", "SELFTEST_PAIR", "SELFTEST_STATIC_PAIR", "diagnose", "parse_effect_names",
    "split_captures", "auto_heldout",
    "capture_rng", "CaptureSimulator", "EffectFitter", "gap_capture_of", "plane_geometry", "selftest_geometries",
    "selftest_cases", "selftest_case", "split_by_depth",
]
