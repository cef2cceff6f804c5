"""Fits of the depth effects' parameters from captures: :func:`fit_effect` and its registry.

Every fit compares a statistic the effect changes between the real captures and the *base* simulation
of the same captures (the reference simulation plus the effects already selected) and inverts the
effect's forward model (:mod:`noise_model.sim.effects`) on the difference: method of moments, maximum
likelihood or a 1-D search (see each ``_fit_*``).

Modules
-------
:mod:`._common`
    Base simulations, nominal geometry, pixel samples, robust per-pixel and per-frame statistics.
:mod:`.disparity`
    disparity_noise, disparity_quantization (+ :func:`disparity_lattice`), depth_bias.
:mod:`.coverage`
    invalid_band, dropout.
:mod:`.correlation`
    correlated_noise, static_pattern.
:mod:`.edges`
    flying_pixels, edge_fattening.
:mod:`.residuals`
    outliers, axial_refit.
:mod:`.spec`
    :class:`FitSpec`, the registry record (each module above ends with ``SPECS``), capture kinds.

Registry
--------
:data:`FITS` (name -> :class:`FitSpec`: the fit, the capture kinds it needs, its tolerances) and its
read-only views :data:`FIT_TOLERANCE` (how close :func:`fit_effect` recovers each parameter;
:func:`within_tolerance`), :data:`FIT_TOLERANCE_SINGLE_FRAME` (the same on captures of one frame),
:data:`NEEDS` (capture kinds each fit uses; :func:`usable_captures`).

Fits on single frames
---------------------
:func:`fit_effect` works on captures of any number of frames, one included (genuine single frames, as
``elevmap gap --realdata`` reads them): temporal statistics give way to the frame's spatial statistics
about the target's best plane, and parameters the captures cannot determine are fixed as each fit's
docstring says (summary at :data:`NEEDS`). A fit either returns parameters the factory accepts or raises
ValueError saying why it cannot estimate them. ``rois`` restricts the fits to the pixels that show the
target.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from types import MappingProxyType

import numpy as np

from ...d435 import D435, SensorModel
from ...sim.effects import SPECS as EFFECT_SPECS
from ...sim.effects import make_effect
from ...sim.effects.base import check_sensor_model
from ..capture_data import check_captures
from . import correlation, coverage, disparity, edges, residuals
from ._common import FIT_MAX_Z_M, _base_sims, _check_rois
from .disparity import LATTICE_FB_RANGE, disparity_lattice
from .spec import CAPTURE_KINDS, FitSpec, select_captures

__all__ = ["fit_effect", "within_tolerance", "usable_captures", "disparity_lattice", "FitSpec", "FITS",
           "FIT_TOLERANCE", "FIT_TOLERANCE_SINGLE_FRAME", "NEEDS", "CAPTURE_KINDS", "LATTICE_FB_RANGE",
           "FIT_MAX_Z_M"]

#: The registry of the fits: effect name -> :class:`FitSpec`, in the order of
#: :data:`noise_model.sim.effects.EFFECTS`. Each family module lists its own records.
FITS = MappingProxyType({s.name: s for module in (disparity, coverage, correlation, edges, residuals)
                         for s in module.SPECS})

#: How close :func:`fit_effect` recovers each parameter (read-only view of :data:`FITS`) when the data
#: are the reference simulation plus that effect at parameters of
#: :data:`noise_model.sim.effects.PARAM_RANGES`, on captures like the gap self-test's (walls at >= 3
#: distances in 0.5-2 m and 0 to >= 45 deg; boards 0.6 x 0.9 m before a wall at 3 m at 0.9-2.1 m for the
#: edge effects; 8-12 frames at 424 x 240): ("abs", x) = |fit - true| <= x, ("rel", x) = |fit - true| <=
#: x |true|. Each is a few times the largest error over random draws from PARAM_RANGES on such captures
#: (docs/calibration.md). Parameters not listed (``seed``, ``baseline_m``) are not estimated. Caveats
#: beside each record.
FIT_TOLERANCE = MappingProxyType({name: s.tolerance for name, s in FITS.items()})

#: :data:`FIT_TOLERANCE` when every capture has a single frame (same captures otherwise: walls or boards
#: x 1 frame at 424 x 240), a few times the largest error over random draws. What one frame cannot give
#: is not in it: the fits of disparity_noise, correlated_noise, static_pattern and axial_refit read the
#: frame's excess *spatial* statistics, so they recover their parameter when the data hold that effect
#: alone, but cannot tell it from the others of the four (temporal vs static: see each fit). Captures of
#: 2 frames meet :data:`FIT_TOLERANCE`.
FIT_TOLERANCE_SINGLE_FRAME = MappingProxyType({name: s.tolerance_single_frame for name, s in FITS.items()})

#: Captures each fit uses (read-only view of :data:`FITS`): "wall" (a wall, all of it but the left
#: band), "board" (a board's interior), "board+background" (a board before a background wall: its left
#: and right edges). A fit uses every capture of the kinds listed (:func:`usable_captures`) and raises
#: ValueError when there is none. What else each needs (distances, angles, interiors) is stated beside
#: its record. Single frames (or few): every fit runs on captures of one frame (see :func:`fit_effect`).
#: Assumptions then: disparity_noise, axial_refit take the frame's spatial spread about the target's
#: plane as per-frame noise, correlated_noise and static_pattern take its whole excess spatial
#: correlation as theirs (static vs per-frame is not identifiable from one frame). Too narrow a design
#: fixes what it cannot determine: depth_bias with distances spanning < 1.5x fits a scale alone
#: (offset_px 0); dropout fixes k_z = 0 with distances spanning < 1.5x and k_theta = 0 with angles
#: spanning < 25 deg; axial_refit fits one factor on the paper's coefficients (plus c_theta with
#: angles, or c0..c2 with distances spanning >= 2x). Captures whose target does not fill the image
#: (a plane fitted to a region of a frame) need ``rois`` in :func:`fit_effect`, or the fits read the
#: other surfaces as the target's errors.
NEEDS = MappingProxyType({name: s.needs for name, s in FITS.items()})


def fit_effect(name: str, real: Sequence, model: SensorModel = D435, base_effects=(), *, seed: int = 0,
               cache: dict | None = None, rois: Mapping | None = None) -> dict:
    """Estimate the parameters of effect ``name`` from real captures.

    Every fit compares a statistic the effect changes between the real captures and the *base*
    simulation of the same captures (:func:`noise_model.analysis.capture_data.simulate_capture` with
    ``model`` and ``base_effects`` in :func:`~noise_model.sim.effects.canonical_order`, as many frames as
    the real capture, seeded by ``seed`` and the capture id: common random numbers across fits), and
    inverts the effect's forward model on the difference (method of moments, maximum likelihood or a 1-D
    search; see each ``_fit_*``). Only the captures of :data:`NEEDS` are used (and simulated).

    Parameters
    ----------
    name : str
        An effect of :data:`~noise_model.sim.effects.EFFECTS`.
    real : sequence of CaptureData
        The real captures.
    model : SensorModel
        The reference model (the paper's D435).
    base_effects : sequence of Effect
        Effects already selected: part of the base simulation.
    seed : int
        Seed of the base simulation.
    cache : dict, optional
        Shared between calls (e.g. one forward-selection round) to reuse base simulations.
    rois : mapping, optional
        Capture id -> boolean image (H, W) of the pixels that show the target (a region of interest):
        the fits use only those pixels (captures without an entry: all of the target's pixels). For
        captures whose target does not fill the image, e.g. a plane fitted to a region of a genuine
        frame: the other pixels show other surfaces, which every statistic would read as the target's
        errors. Ids of captures not in ``real`` are ignored.

    Returns
    -------
    dict
        Parameters for ``make_effect(name, **params)``: finite and inside the factory's ranges (an
        estimate outside them is clipped to them; integers are rounded).

    Single frames and few frames
    ----------------------------
    Every fit is defined on captures of one frame or a few: where its statistic is temporal (the
    variance over frames of disparity_noise and axial_refit, the frame-to-frame residual of
    correlated_noise, the temporal mean of static_pattern), a capture of one frame uses the spatial
    statistic of its frame about the target's best plane instead, and what one frame cannot separate is
    stated in the fit's docstring (static vs per-frame noise, above all); where the captures do not
    span what a parameter needs (one distance for a depth scale vs a disparity offset, a narrow range
    of distances or angles for the dropout's and the axial noise's slopes) the fit estimates what they
    determine and fixes the rest as its docstring says.

    Raises
    ------
    ValueError
        Unknown name, no usable capture, bad input, or a fit that cannot be estimated from these
        captures (the message says why; arithmetic failures of a fit are reported the same way).
    """
    if name not in FITS:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(FITS)}")
    check_sensor_model(model)
    real = check_captures(real, allow_empty=True)
    base_effects = list(base_effects or ())
    for k, e in enumerate(base_effects):
        if not callable(e):
            raise ValueError(f"base_effects[{k}] is not callable: {e!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    if cache is not None and not isinstance(cache, dict):
        raise ValueError(f"cache must be a dict or None, got {type(cache).__name__}")
    rois = _check_rois(rois, real)
    use = usable_captures(name, real)
    if not use:
        raise ValueError(f"fit of {name} needs captures of kind {' or '.join(NEEDS[name])}; none given")
    if rois:
        use = [c for c in use if c.id not in rois or rois[c.id].any()]
        if not use:
            raise ValueError(f"fit of {name}: the regions of interest of its captures are empty")
    base = _base_sims(use, model, base_effects, int(seed), {} if cache is None else cache)
    try:
        with np.errstate(all="ignore"):
            params = FITS[name].fit(use, base, model, base_effects=base_effects, seed=int(seed),
                                    cache={} if cache is None else cache, rois=rois)
    except (ArithmeticError, np.linalg.LinAlgError, IndexError) as exc:
        raise ValueError(f"fit of {name} failed on these captures ({type(exc).__name__}: {exc})") from exc
    return _valid_params(name, params)


def _valid_params(name: str, params: dict) -> dict:
    """The fit's parameters made valid for the factory: finite (else ValueError naming the parameter),
    clipped to the factory's valid ranges (:attr:`~noise_model.sim.effects.EffectSpec.valid`), integers
    rounded and clipped (:attr:`~noise_model.sim.effects.EffectSpec.integer_params`); then the effect is
    built once, so that a parameter the factory refuses is a ValueError of the fit, never of a later step."""
    out = {}
    for k, v in params.items():
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise ValueError(f"fit of {name}: parameter {k} is not a number ({v!r})")
        if not math.isfinite(float(v)):
            raise ValueError(f"fit of {name}: parameter {k} could not be estimated from these captures "
                             f"(the estimate is {float(v)})")
        out[k] = v
    spec = EFFECT_SPECS[name]
    for k, (lo, hi) in spec.valid.items():                    # within the factory's own ranges
        if k in out:
            out[k] = float(min(max(float(out[k]), lo), hi))
    for k, (lo, hi) in spec.integer_params.items():
        if k in out:
            out[k] = int(min(max(int(math.floor(float(out[k]) + 0.5)), lo), hi))
    try:
        make_effect(name, **out)
    except ValueError as exc:
        raise ValueError(f"fit of {name} returned parameters the effect refuses: {exc}") from None
    return out


def within_tolerance(name: str, true_params: Mapping, fitted_params: Mapping,
                     tolerance: Mapping | None = None) -> tuple[bool, dict]:
    """Whether a fit recovered the parameters within :data:`FIT_TOLERANCE` (or ``tolerance``, a table
    of the same form, e.g. :data:`FIT_TOLERANCE_SINGLE_FRAME`).

    Returns
    -------
    ok : bool
    errors : dict
        param -> (|fit - true|, allowed) for every parameter of the tolerance.
    """
    table = FIT_TOLERANCE if tolerance is None else tolerance
    if not isinstance(table, Mapping):
        raise ValueError(f"tolerance must be a mapping like FIT_TOLERANCE, got {type(table).__name__}")
    if name not in table:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(table)}")
    errors, ok = {}, True
    for k, (kind, tol) in table[name].items():
        if k not in true_params or k not in fitted_params:
            raise ValueError(f"{name}: parameter {k!r} missing from the true or the fitted parameters")
        err = abs(float(fitted_params[k]) - float(true_params[k]))
        allowed = tol if kind == "abs" else tol * abs(float(true_params[k]))
        errors[k] = (err, allowed)
        ok &= err <= allowed + 1e-12
    return bool(ok), errors


def usable_captures(name: str, captures: Sequence) -> list:
    """The captures (CaptureData or CaptureGeometry) whose kind the fit of ``name`` uses (:data:`NEEDS`)."""
    if name not in NEEDS:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(NEEDS)}")
    return select_captures(NEEDS[name], captures)
