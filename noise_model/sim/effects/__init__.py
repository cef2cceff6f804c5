"""Depth effects a per-pixel Gaussian model leaves out: forward models and their registry.

Each effect is a *forward model* applied to the reference simulation (the paper's model: z = z_true
+ N(0, sigma_z(z_true, theta)^2), independent per pixel and frame, board edges shifted by the lateral
noise; the capture-set format is docs/capture-set-format.md) through the simulator's effects hook
(the hook contract: :mod:`.base`), with a factory whose docstring gives its physics, sources and D435
values. Physics and evidence: sections E1-E19 of ``docs/depth-effects.md``, which cite the primary
sources. The fits of their parameters from captures are in :mod:`noise_model.analysis.effect_fits`
(:func:`fit_effect` and the fit-side tables are re-exported here on first use, so that this package
does not load the analysis).

Modules
-------
:mod:`.base`
    The hook contract, :class:`Effect`, :func:`gaussian_random_field`, disparity helpers.
:mod:`.disparity`
    ``disparity_noise``, ``disparity_quantization``, ``depth_bias``, ``frame_offset``.
:mod:`.coverage`
    ``invalid_band``, ``dropout``.
:mod:`.correlation`
    ``correlated_noise``, ``static_pattern``, ``static_noise``.
:mod:`.edges`
    ``edge_fattening``, ``flying_pixels``.
:mod:`.residuals`
    ``outliers``, ``axial_refit``.
:mod:`.spec`
    :class:`EffectSpec`, the registry record: each module above ends with ``SPECS``, one record per effect.

Effects (identifiers; canonical order :data:`ORDER`)
----------------------------------------------------
``axial_refit`` (docs/depth-effects.md: the paper's model and its caveats)
    The paper's sigma_z with refitted coefficients: the reference deviation is rescaled.
``depth_bias`` (E4)
    Depth scale error and disparity offset.
``static_pattern`` (E5, E10)
    A smooth disparity-offset field, constant over the frames of a capture.
``static_noise`` (E10)
    The static share of the matching error: a field proportional to sigma_z, constant over the frames.
``disparity_noise`` (E1)
    Extra noise Gaussian in disparity (skewed and growing as z^2 in depth).
``correlated_noise`` (E9)
    A fresh spatially correlated Gaussian field each frame, proportional to sigma_z.
``outliers`` (E13, E15)
    A fraction of pixels with a wide disparity error (heavy tails).
``edge_fattening`` (E8)
    The foreground's disparity spreads a few px into the background at depth edges.
``flying_pixels`` (E8)
    Pixels next to depth edges take depths between the two sides.
``frame_offset`` (E4, E9)
    A disparity offset common to the whole frame, drawn afresh every frame.
``disparity_quantization`` (E2)
    Disparity on a lattice of 2^-bits px (the D435: 5 bits, 1/32 px).
``invalid_band`` (E6)
    The left band u < f B / z + margin has no depth.
``dropout`` (E11)
    Missing pixels in blobs, more with distance and incidence angle.

``axial_refit``
    temporal std per pixel and a frame's spatial std, both x sigma_new / sigma_ref per distance and
    angle (may decrease; the angle term shows at high angles); no bias, correlation, skew, fill change.
``depth_bias``
    bias vs geometry (scale - 1) z - z^2 offset / (f B), the same in every image cell; W1 shift.
``static_pattern``
    spatial std of a frame's (and of the temporal mean's) residual + sigma_px z^2 / (f B); correlation
    length of the temporal-mean residual; bias per 3 x 3 cell +-, image mean ~0; temporal std unchanged.
``static_noise``
    spatial std of a frame's (and of the temporal mean's) residual + f sigma_z in quadrature (with the
    model's angle and depth dependence); correlation length of the temporal-mean residual; temporal std
    unchanged.
``disparity_noise``
    temporal and spatial std + z^2 s / (f B) in quadrature, no angle dependence (most at far, frontal);
    right skew of the residual; tiny positive bias z^3 s^2 / (f B)^2; no correlation.
``correlated_noise``
    temporal and spatial std x sqrt(1 + f^2) (the paper's shape); correlation length of a frame's
    residual (minus the temporal mean); W1.
``outliers``
    tails of the residual (|r| >> sigma), kurtosis, non-robust std; everywhere; fill barely.
``edge_fattening``
    edge_left / edge_right regions only: bias toward the foreground (background pixels read the
    board), the board looks wider; no intermediate depths.
``flying_pixels``
    edge_left / edge_right regions only: depths between board and background (residual tails, W1,
    temporal std); interior unchanged.
``frame_offset``
    the standard deviation over frames of a frame's mean disparity deviation from the temporal mean
    (sigma_px sqrt(1 - 1/F)); temporal std + sigma_px z^2 / (f B) in quadrature; nothing static, nothing
    within a frame.
``disparity_quantization``
    the lattice of depth values (a comb at f B 2^bits / n), temporal std + Delta^2 / 12 at far range.
``invalid_band``
    fill rate 0 in the left_band region (image column 0 of the 3 x 3 grid), width f B / z + margin.
``dropout``
    fill rate down everywhere, more with distance and angle (not regional); holes in blobs.

Pairs a statistic separates: axial_refit / correlated_noise (correlation length), axial_refit /
disparity_noise (angle dependence, skew), static_pattern / correlated_noise (temporal std),
static_pattern / static_noise (angle and depth dependence), frame_offset / correlated_noise (the
frame-wide mean deviation vs the lag correlation within a frame), static_pattern / depth_bias (image mean ~0
vs systematic with z), outliers / disparity_noise (tails vs core width), invalid_band / dropout (left
band only vs everywhere), flying_pixels / edge_fattening (intermediate depths vs foreground depth).

Registry
--------
:data:`SPECS` holds one :class:`EffectSpec` per effect (name, factory, composition order, the ranges the
gap self-test draws from, the factory's valid and integer ranges). The tables below are read-only views
of it: :data:`EFFECTS` (name -> factory), :data:`ORDER`, :data:`PARAM_RANGES`, :data:`INTEGER_PARAMS`.
Functions: :func:`make_effect`, :func:`canonical_order`, :func:`effects_from_report`, :func:`draw_params`.
From :mod:`noise_model.analysis.effect_fits` (loaded on first use): :func:`fit_effect`,
:data:`FIT_TOLERANCE` (how close :func:`fit_effect` recovers each parameter; :func:`within_tolerance`;
:data:`FIT_TOLERANCE_SINGLE_FRAME` on captures of one frame), :data:`NEEDS` (capture kinds a fit uses),
:func:`usable_captures`, :func:`disparity_lattice` (the disparity lattice of real captures and the f B
it is found at).
"""

from __future__ import annotations

import importlib
import json
import os
from collections.abc import Mapping
from types import MappingProxyType

import numpy as np

from ...registry import build_from_registry
from . import correlation, coverage, disparity, edges, residuals
from .base import Effect, gaussian_random_field
from .correlation import CORRELATED_NOISE_DEFAULTS, correlated_noise, static_noise, static_pattern
from .coverage import dropout, invalid_band
from .disparity import DEPTH_BIAS_DEFAULTS, depth_bias, disparity_noise, disparity_quantization, frame_offset
from .edges import EDGE_JUMP_PX, edge_fattening, flying_pixels
from .residuals import axial_refit, outliers
from .spec import EffectSpec

__all__ = ["Effect", "gaussian_random_field", "EFFECTS", "make_effect", "ORDER", "canonical_order",
           "PARAM_RANGES", "INTEGER_PARAMS", "draw_params", "FIT_TOLERANCE", "within_tolerance", "NEEDS",
           "usable_captures", "fit_effect", "effects_from_report", "CORRELATED_NOISE_DEFAULTS",
           "DEPTH_BIAS_DEFAULTS", "EDGE_JUMP_PX", "disparity_lattice", "LATTICE_FB_RANGE",
           "FIT_TOLERANCE_SINGLE_FRAME", "EffectSpec", "SPECS",
           "axial_refit", "depth_bias", "static_pattern", "static_noise", "disparity_noise", "correlated_noise",
           "outliers", "edge_fattening", "flying_pixels", "frame_offset", "disparity_quantization", "invalid_band",
           "dropout"]

#: The registry: effect name -> :class:`EffectSpec`, one record per effect, in the catalogue's order
#: (the order of help texts and of "known: ..." messages). Each family module lists its own records.
SPECS = MappingProxyType({s.name: s for module in (disparity, coverage, correlation, edges, residuals)
                          for s in module.SPECS})

#: Effect factories by name (the identifiers of the gap report and of ``--sim-effects``); a read-only
#: view of :data:`SPECS`.
EFFECTS = MappingProxyType({name: s.factory for name, s in SPECS.items()})

#: The order in which the device applies them (docs/depth-effects.md, "Composition order"): the noise's
#: magnitude, calibration biases, disparity noise (white, correlated, gross), edge effects, the frame-wide
#: offset, the 2^-bits lattice, then the masks (:attr:`EffectSpec.order`). :func:`canonical_order` sorts a list of effects by it.
ORDER = tuple(s.name for s in sorted(SPECS.values(), key=lambda s: s.order))

#: Ranges the gap self-test draws each parameter from (uniformly; :data:`INTEGER_PARAMS` rounded), for
#: the 424 x 240 stream (f B = 10.6 px m; pixel parameters are px of that stream): realistic D435 values
#: (sources in each factory's docstring), but strong enough to stand out of the self-test's captures, and
#: of one sign where the effect vanishes at 0 (scale < 1, offset > 0: an out-of-box D435 reads short;
#: axial_refit: a quieter unit than the paper's, as elevation_mapping's fit is), so that no draw is an
#: invisible effect. The fits are not restricted to these ranges. Read-only view of :data:`SPECS`.
PARAM_RANGES = MappingProxyType({name: s.param_ranges for name, s in SPECS.items()})

#: Parameters that are integers (drawn as integers by :func:`draw_params`; factories round reals).
#: Read-only view of :data:`SPECS`.
INTEGER_PARAMS = MappingProxyType({name: tuple(s.integer_params) for name, s in SPECS.items()
                                   if s.integer_params})


def canonical_order(effects) -> list:
    """The effects sorted by :data:`ORDER` (stable; unknown names keep their place at the end)."""
    effects = list(effects or ())
    rank = {n: i for i, n in enumerate(ORDER)}
    return sorted(effects, key=lambda e: rank.get(getattr(e, "name", None), len(ORDER)))


def make_effect(name: str, **params) -> Effect:
    """An effect of :data:`EFFECTS` by name, with keyword overrides of its defaults.

    Raises
    ------
    ValueError
        Unknown name or parameter, or a bad value.
    """
    return build_from_registry(EFFECTS, "effect", name, params, hidden=("model",))


def effects_from_report(report) -> list[Effect]:
    """The effects selected by a gap report (``format`` ``d435-gap/1``), in the report's order.

    Parameters
    ----------
    report : dict or path
        The report, or the path of its JSON file. Its ``effects`` list holds ``{"name", "params"}``.

    Returns
    -------
    list of Effect
        ``make_effect(name, **params)`` for each entry (an empty list when nothing was selected).

    Raises
    ------
    ValueError
        Unreadable file, no ``effects`` list, an entry without a name or with bad parameters.
    """
    if isinstance(report, (str, os.PathLike)):
        try:
            with open(report, encoding="utf-8") as fh:
                report = json.load(fh)
        except OSError as exc:
            raise ValueError(f"cannot read the gap report {os.fspath(report)!r}: {exc}") from None
        except json.JSONDecodeError as exc:
            raise ValueError(f"the gap report is not valid JSON: {exc}") from None
    if not isinstance(report, Mapping):
        raise ValueError(f"a gap report must be a JSON object, got {type(report).__name__}")
    entries = report.get("effects")
    if not isinstance(entries, list):
        raise ValueError("the gap report has no 'effects' list")
    out = []
    for k, e in enumerate(entries):
        if not isinstance(e, Mapping) or not isinstance(e.get("name"), str):
            raise ValueError(f"gap report effects[{k}] must be an object with a 'name', got {e!r}")
        params = e.get("params", {})
        if not isinstance(params, Mapping):
            raise ValueError(f"gap report effects[{k}] ({e['name']}): 'params' must be an object")
        try:
            out.append(make_effect(e["name"], **dict(params)))
        except ValueError as exc:
            raise ValueError(f"gap report effects[{k}]: {exc}") from None
    return out


def draw_params(name: str, rng: np.random.Generator) -> dict:
    """Parameters of effect ``name`` drawn uniformly from :data:`PARAM_RANGES` (integers as integers)."""
    if name not in PARAM_RANGES:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(PARAM_RANGES)}")
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    ints = INTEGER_PARAMS.get(name, ())
    out = {}
    for k, (lo, hi) in PARAM_RANGES[name].items():
        out[k] = int(rng.integers(int(lo), int(hi) + 1)) if k in ints else float(rng.uniform(lo, hi))
    return out


# The fit side lives in noise_model.analysis.effect_fits, which imports this package; its names are
# reachable here too (``from noise_model import effects as E; E.fit_effect``), loaded on first use.
_FIT_NAMES = ("fit_effect", "within_tolerance", "usable_captures", "disparity_lattice", "FIT_TOLERANCE",
              "FIT_TOLERANCE_SINGLE_FRAME", "NEEDS", "LATTICE_FB_RANGE", "FIT_MAX_Z_M")


def __getattr__(name):
    if name not in _FIT_NAMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module("noise_model.analysis.effect_fits"), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_FIT_NAMES))
