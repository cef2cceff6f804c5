"""Depth effects a per-pixel Gaussian model leaves out: forward models, parameter fits, registry.

The effects library of the sim-to-real gap diagnosis (issue 7). Each effect is a *forward model*
applied to the reference simulation of ``shared/specs/capture-set.md`` (the paper's model: z = z_true
+ N(0, sigma_z(z_true, theta)^2), independent per pixel and frame, board edges shifted by the lateral
noise), a *fit* of its parameters from the statistics it changes (:func:`fit_effect`), and a
docstring with its physics and sources. Physics, D435 values and evidence tags: sections E1-E19 of
``shared/notes/depth-effects.md`` (called "the notes" below), which cite the primary sources.

Hook contract
-------------
An effect is a callable with the hook contract of :func:`noise_model.sim.scene.add_noise`::

    effect(z, theta, rng, context) -> z

applied in order to the noisy metric z-depth (H, W) [m] (NaN = no data) before the depth-unit
rounding. ``rng`` is the simulation's generator, the only source of randomness (the static pattern
alone is derived from its own ``seed`` parameter, so that it is the same in every frame). ``context``
holds at least ``K`` (3, 3) [px], ``width``, ``height``, ``index``, ``depth_scale`` and ``z_true``
(H, W) [m]; :func:`noise_model.analysis.capture_data.simulate_capture` adds ``baseline_m`` [m], ``capture_id``,
``regions`` and ``z_ref`` (the depth after the reference noise). :func:`edge_fattening` leaves
``d_edges`` (H, W) [px], the true disparity with the foreground grown, for the effects after it in
the same frame (:func:`flying_pixels` puts its band at that apparent edge). Effects that need more than
``K``/``z_true`` compute it themselves (depth discontinuities from ``z_true``), so every effect also
works on the walk simulator's frames (:func:`noise_model.sim.scene.simulate_walk`). f B (focal length [px]
times baseline [m]) is ``K[0, 0] * context['baseline_m']`` (the D435's 0.050 m when absent); the
disparity of a depth z is d = f B / z [px]. Pixel parameters are in pixels of the simulated stream.

Effects (identifiers; canonical order :data:`ORDER`)
----------------------------------------------------
``axial_refit`` (the notes, section 2: the seed model's variance curve)
    The paper's sigma_z with refitted coefficients: the reference deviation is rescaled.
``depth_bias`` (E4)
    Depth scale error and disparity offset.
``static_pattern`` (E5, E10)
    A smooth disparity-offset field, constant over the frames of a capture.
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
``disparity_quantization`` (E2)
    Disparity on a lattice of 2^-bits px (the D435: 5 bits, 1/32 px).
``invalid_band`` (E6)
    The left band u < f B / z + margin has no depth.
``dropout`` (E11)
    Missing pixels in blobs, more with distance and incidence angle.

What each effect changes (the gap statistics; everything not named stays, to first order)
----------------------------------------------------------------------------------------
``axial_refit``
    temporal std per pixel and a frame's spatial std, both x sigma_new / sigma_ref per distance and
    angle (may decrease; the angle term shows at high angles); no bias, correlation, skew, fill change.
``depth_bias``
    bias vs geometry (scale - 1) z - z^2 offset / (f B), the same in every image cell; W1 shift.
``static_pattern``
    spatial std of a frame's (and of the temporal mean's) residual + sigma_px z^2 / (f B); correlation
    length of the temporal-mean residual; bias per 3 x 3 cell +-, image mean ~0; temporal std unchanged.
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
``disparity_quantization``
    the lattice of depth values (a comb at f B 2^bits / n), temporal std + Delta^2 / 12 at far range.
``invalid_band``
    fill rate 0 in the left_band region (image column 0 of the 3 x 3 grid), width f B / z + margin.
``dropout``
    fill rate down everywhere, more with distance and angle (not regional); holes in blobs.

Pairs a statistic separates: axial_refit / correlated_noise (correlation length), axial_refit /
disparity_noise (angle dependence, skew), static_pattern / correlated_noise (temporal std),
static_pattern / depth_bias (image mean ~0 vs systematic with z), outliers / disparity_noise (tails vs
core width), invalid_band / dropout (left band only vs everywhere), flying_pixels / edge_fattening
(intermediate depths vs foreground depth).

Registry
--------
:data:`EFFECTS` (name -> factory), :func:`make_effect`, :data:`PARAM_RANGES` (the ranges the gap
selftest draws from), :data:`INTEGER_PARAMS`, :func:`draw_params`, :data:`FIT_TOLERANCE` (how close
:func:`fit_effect` recovers each parameter; :func:`within_tolerance`; :data:`FIT_TOLERANCE_SINGLE_FRAME`
on captures of one frame), :data:`NEEDS` (capture kinds a fit uses), :func:`usable_captures`,
:func:`canonical_order`, :func:`effects_from_report`; :func:`disparity_lattice` (the disparity lattice
of real captures and the f B it is found at).

Fits on single frames
---------------------
:func:`fit_effect` works on captures of any number of frames, one included (the genuine single frames
of ``elevmap gap --realdata``): temporal statistics give way to the frame's spatial statistics about
the target's best plane, and parameters the captures cannot determine are fixed as each fit's
docstring says (summary in the comment of :data:`NEEDS`). A fit either returns parameters the factory
accepts or raises ValueError saying why it cannot estimate them. ``rois`` restricts the fits to the
pixels that show the target.
"""

from __future__ import annotations

import json
import math
import os
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from ..checks import check_intrinsics, check_positive_scalar
from ..d435 import D435, SensorModel, _axial_sigma_unchecked

__all__ = ["Effect", "gaussian_random_field", "EFFECTS", "make_effect", "ORDER", "canonical_order",
           "PARAM_RANGES", "INTEGER_PARAMS", "draw_params", "FIT_TOLERANCE", "within_tolerance", "NEEDS",
           "usable_captures", "fit_effect", "effects_from_report", "CORRELATED_NOISE_DEFAULTS",
           "DEPTH_BIAS_DEFAULTS", "EDGE_JUMP_PX", "disparity_lattice", "LATTICE_FB_RANGE",
           "FIT_TOLERANCE_SINGLE_FRAME",
           "axial_refit", "depth_bias", "static_pattern", "disparity_noise", "correlated_noise", "outliers",
           "edge_fattening", "flying_pixels", "disparity_quantization", "invalid_band", "dropout"]

#: Defaults of :func:`correlated_noise`: a correlated part as strong as the paper's white noise
#: (sigma = 1.0 sigma_z, so half the per-pixel variance is correlated) over l = 3 px of the simulated
#: stream (6 px at 848 x 480, inside the 3-10 px of the notes).
CORRELATED_NOISE_DEFAULTS = {"sigma_z_fraction": 1.0, "length_px": 3.0}
#: Defaults of :func:`depth_bias`: -1 % scale (half the -1.9 % of an out-of-box D435, inside the
#: ~2 % datasheet accuracy) and a 0.05 px disparity offset in the simulated stream's pixels (at
#: 424 x 240, f b = 10.6 px m: -4.7 mm at 1 m, -19 mm at 2 m; with the scale -15 mm at 1 m).
DEPTH_BIAS_DEFAULTS = {"scale": 0.99, "offset_px": 0.05, "baseline_m": D435.baseline_m}
#: A depth discontinuity (edge effects): neighbouring pixels (4-neighbours) whose true disparities
#: differ by more than this [px]. Far above the per-pixel disparity change of any plane the D435 sees
#: (the ground at 0.45 m: ~0.1 px per row at 848 x 480), below the jumps of steps and boards (a board at
#: 2 m before a wall at 3 m: 1.8 px at 424 x 240).
EDGE_JUMP_PX = 1.0
#: Largest incidence angle used by the dropout's -ln cos(theta) [rad] (89 deg).
_THETA_DROPOUT_MAX = math.radians(89.0)


# =============================================================================================
# base class and helpers
# =============================================================================================
class Effect:
    """Base of the effects here: the hook's input checks and the metadata shown in reports.

    Attributes
    ----------
    name : str
    params : dict
        Parameters (JSON-serialisable); ``make_effect(name, **params)`` rebuilds the effect.
    """

    name = "effect"

    def __init__(self, params: dict):
        self.params = dict(params)

    def __repr__(self) -> str:
        return f"{self.name}({', '.join(f'{k}={v!r}' for k, v in self.params.items())})"

    def __call__(self, z, theta, rng, context):
        """Apply the effect to one frame.

        Parameters
        ----------
        z : ndarray, shape (H, W), float
            Noisy metric z-depth [m]; NaN = no data. May be modified in place.
        theta : ndarray, shape (H, W), float
            True incidence angles [rad] (NaN where nothing is hit); read only.
        rng : numpy.random.Generator
            The simulation's generator.
        context : dict
            ``K``, ``width``, ``height``, ``index``, ``depth_scale``, ``z_true`` (see the module docstring).

        Returns
        -------
        ndarray, shape (H, W), float64
            The new depth [m]; NaN or <= 0 = no data.
        """
        zz = np.asarray(z)
        if zz.ndim != 2 or not np.issubdtype(zz.dtype, np.floating):
            raise ValueError(f"{self.name}: z must be a 2-D float image [m], got {zz.dtype} {zz.shape}")
        th = np.asarray(theta)
        if th.shape != zz.shape:
            raise ValueError(f"{self.name}: theta must have z's shape {zz.shape}, got {th.shape}")
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"{self.name}: rng must be a numpy.random.Generator, got {type(rng).__name__}")
        if not isinstance(context, dict):
            raise ValueError(f"{self.name}: context must be a dict, got {type(context).__name__}")
        return self._apply(zz.astype(np.float64, copy=False), th, rng, context)

    def _apply(self, z, theta, rng, context):  # pragma: no cover - overridden
        raise NotImplementedError


def _scalar(value, name: str, lo: float, hi: float, *, open_lo: bool = False) -> float:
    if isinstance(value, bool):
        raise ValueError(f"{name} must be a number, got {value!r}")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(x) or x < lo or x > hi or (open_lo and x == lo):
        raise ValueError(f"{name} must be in {'(' if open_lo else '['}{lo}, {hi}], got {value!r}")
    return x


def _integer(value, name: str, lo: int, hi: int) -> int:
    """An integer parameter; a real value is rounded to the nearest integer (random draws are reals)."""
    x = _scalar(value, name, lo - 0.5, hi + 0.5)
    k = int(math.floor(x + 0.5))
    if k < lo or k > hi:
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return k


def _check_model(model) -> SensorModel:
    if not isinstance(model, SensorModel):
        raise ValueError(f"model must be a noise_model.SensorModel, got {type(model).__name__}")
    return model


def _fb(context: dict, who: str) -> float:
    """f B [px m] of the frame: K[0, 0] times context['baseline_m'] (D435's 0.050 m if absent)."""
    K = context.get("K")
    if K is None:
        raise ValueError(f"{who} needs the intrinsics: context['K'] (3, 3) [px]")
    fx = check_intrinsics(K, "context['K']")[0, 0]
    b = context.get("baseline_m")
    b = D435.baseline_m if b is None else check_positive_scalar(b, "context['baseline_m']", upper=2.0, unit=" m")
    return float(fx) * b


def _z_true(context: dict, shape, who: str, fallback=None):
    zt = context.get("z_true")
    if zt is None:
        if fallback is not None:
            return fallback
        raise ValueError(f"{who} needs context['z_true'] (H, W) [m]")
    zt = np.asarray(zt, dtype=np.float64)
    if zt.shape != tuple(shape):
        raise ValueError(f"{who}: context['z_true'] must have shape {tuple(shape)}, got {zt.shape}")
    return zt


def _valid(z):
    with np.errstate(invalid="ignore"):
        return np.isfinite(z) & (z > 0)


def _to_depth(fb: float, d):
    """z = f B / d [m]; NaN where d <= 0 or not finite."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(d) & (d > 0), fb / d, np.nan)


def _to_disparity(fb: float, z):
    """d = f B / z [px]; NaN where z is no data."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(_valid(z), fb / z, np.nan)


def gaussian_random_field(shape, length_px: float, rng: np.random.Generator) -> np.ndarray:
    """A stationary Gaussian random field with unit variance and Gaussian correlation.

    White noise on a grid padded by the kernel's radius is filtered ('valid' part) with the separable
    Gaussian kernel of standard deviation s = length_px / sqrt(2), truncated at 4 s and normalised to
    unit energy, so every output pixel has variance exactly 1 and the correlation between pixels h
    apart is rho(h) = exp(-h^2 / (2 length_px^2)) (up to the truncation and the sampling of the
    kernel: within 0.002 for length_px >= 1.2, 0.02 at 1 px). No wrap-around: the field is stationary up to its borders.

    Parameters
    ----------
    shape : (int, int)
        (H, W) [px].
    length_px : float
        Correlation length l [px], in (0, 200].
    rng : numpy.random.Generator

    Returns
    -------
    ndarray, shape (H, W), float64
    """
    try:
        H, W = (int(v) for v in shape)
    except (TypeError, ValueError):
        raise ValueError(f"shape must be (H, W), got {shape!r}") from None
    if H < 1 or W < 1:
        raise ValueError(f"shape must be positive, got {shape!r}")
    ell = _scalar(length_px, "length_px", 0.0, 200.0, open_lo=True)
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    s = ell / math.sqrt(2.0)
    r = max(1, int(math.ceil(4.0 * s)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / s) ** 2)
    k /= math.sqrt(float(np.sum(k * k)))
    from scipy.ndimage import correlate1d

    w = rng.standard_normal((H + 2 * r, W + 2 * r))
    rows = correlate1d(w, k, axis=1, mode="constant")[:, r:r + W]
    return correlate1d(rows, k, axis=0, mode="constant")[r:r + H, :]


def _true_disparity(zt, fb):
    """True disparity [px] with 0 where nothing is hit (infinitely far)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(_valid(zt), fb / zt, 0.0)


def _jump_pixels(D, tau: float):
    """Pixels with a 4-neighbour whose disparity differs by more than tau, and the nearer side of each jump.

    Returns (edge, fg): ``edge`` marks both pixels of every jump, ``fg`` only the nearer (larger
    disparity) one.
    """
    edge = np.zeros(D.shape, dtype=bool)
    fg = np.zeros(D.shape, dtype=bool)
    dh = D[:, 1:] - D[:, :-1]
    jh = np.abs(dh) > tau
    edge[:, 1:] |= jh
    edge[:, :-1] |= jh
    fg[:, 1:] |= jh & (dh > 0)
    fg[:, :-1] |= jh & (dh < 0)
    dv = D[1:, :] - D[:-1, :]
    jv = np.abs(dv) > tau
    edge[1:, :] |= jv
    edge[:-1, :] |= jv
    fg[1:, :] |= jv & (dv > 0)
    fg[:-1, :] |= jv & (dv < 0)
    return edge, fg


def _max3(a):
    """3 x 3 maximum filter (borders: the image's own pixels only)."""
    out = a.copy()
    out[1:, :] = np.maximum(out[1:, :], a[:-1, :])
    out[:-1, :] = np.maximum(out[:-1, :], a[1:, :])
    o2 = out.copy()
    o2[:, 1:] = np.maximum(o2[:, 1:], out[:, :-1])
    o2[:, :-1] = np.maximum(o2[:, :-1], out[:, 1:])
    return o2


def _min3(a):
    return -_max3(-a)


def _fattening_levels(D, levels: int):
    """Chebyshev distance (1..levels, 0 = none) of each pixel from the nearer pixel of a depth
    discontinuity it is behind by more than EDGE_JUMP_PX, and that pixel's disparity [px]."""
    _, fg = _jump_pixels(D, EDGE_JUMP_PX)
    target = np.zeros(D.shape)
    level = np.zeros(D.shape, dtype=np.int32)
    E = np.where(fg, D, 0.0)
    for j in range(1, levels + 1):
        E = _max3(E)
        new = (level == 0) & (E - D > EDGE_JUMP_PX)
        level[new] = j
        target[new] = E[new]
    return level, target


# =============================================================================================
# forward models
# =============================================================================================
class _AxialRefit(Effect):
    name = "axial_refit"

    def __init__(self, params: dict, model: SensorModel):
        super().__init__(params)
        self.model = model
        self.new_model = replace(model, axial_coefficients=(params["c0"], params["c1"], params["c2"],
                                                            params["c_theta"]))

    def _apply(self, z, theta, rng, context):
        zt = _z_true(context, z.shape, self.name)
        z_ref = context.get("z_ref")
        z_ref = z if z_ref is None else np.asarray(z_ref, dtype=np.float64)
        if z_ref.shape != z.shape:
            raise ValueError(f"{self.name}: context['z_ref'] must have shape {z.shape}, got {z_ref.shape}")
        hit = _valid(zt) & np.isfinite(theta) & np.isfinite(z_ref)
        ratio = np.ones(z.shape)
        s_ref = _axial_sigma_unchecked(zt[hit], theta[hit], self.model)
        s_new = _axial_sigma_unchecked(zt[hit], theta[hit], self.new_model)
        ratio[hit] = s_new / s_ref
        out = z.copy()
        out[hit] = z[hit] + (ratio[hit] - 1.0) * (z_ref[hit] - zt[hit])
        return out


class _DepthBias(Effect):
    name = "depth_bias"

    def _apply(self, z, theta, rng, context):
        K = context.get("K")
        if K is None:
            raise ValueError("depth_bias needs the intrinsics: context['K'] (3, 3) [px]")
        fx = check_intrinsics(K, "context['K']")[0, 0]
        fb = fx * self.params["baseline_m"]
        with np.errstate(divide="ignore", invalid="ignore"):
            d = fb / z + self.params["offset_px"]
            out = np.where(d > 0, self.params["scale"] * fb / d, np.nan)
        out[~np.isfinite(z) | (z <= 0)] = np.nan
        return out


class _StaticPattern(Effect):
    name = "static_pattern"

    def __init__(self, params: dict):
        super().__init__(params)
        self._fields: dict = {}

    def field(self, shape, capture_id: str = "") -> np.ndarray:
        """The unit field G (H, W) of a capture: zero mean, unit standard deviation over the image."""
        H, W = (int(v) for v in shape)
        key = (H, W, str(capture_id))
        if key not in self._fields:
            crc = zlib.crc32(str(capture_id).encode("utf-8"))
            g = gaussian_random_field((H, W), self.params["length_px"],
                                      np.random.default_rng([self.params["seed"], crc, H, W]))
            g -= g.mean()
            g /= g.std()
            g.flags.writeable = False
            if len(self._fields) >= 64:
                self._fields.pop(next(iter(self._fields)))
            self._fields[key] = g
        return self._fields[key]

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        G = self.field(z.shape, context.get("capture_id") or "")
        return _to_depth(fb, _to_disparity(fb, z) + self.params["sigma_px"] * G)


class _DisparityNoise(Effect):
    name = "disparity_noise"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        e = rng.standard_normal(z.shape) * self.params["s_px"]
        return _to_depth(fb, _to_disparity(fb, z) + e)


class _CorrelatedNoise(Effect):
    name = "correlated_noise"

    def __init__(self, params: dict, model: SensorModel):
        super().__init__(params)
        self.model = model

    def _apply(self, z, theta, rng, context):
        g = gaussian_random_field(z.shape, self.params["length_px"], rng)
        if self.params.get("sigma_m") is not None:
            sigma = self.params["sigma_m"]
        else:
            zt = context.get("z_true")
            if zt is None:
                raise ValueError("correlated_noise with sigma_z_fraction needs context['z_true']")
            zt = np.asarray(zt, dtype=np.float64)
            if zt.shape != z.shape:
                raise ValueError(f"correlated_noise: context['z_true'] must have shape {z.shape}, got {zt.shape}")
            hit = np.isfinite(zt) & np.isfinite(theta) & (zt > 0)
            sigma = np.zeros(z.shape)
            sigma[hit] = self.params["sigma_z_fraction"] * _axial_sigma_unchecked(zt[hit], theta[hit], self.model)
        return z + sigma * g


class _Outliers(Effect):
    name = "outliers"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        pick = rng.random(z.shape) < self.params["fraction"]
        e = rng.standard_normal(z.shape) * self.params["sigma_px"]
        d = _to_disparity(fb, z)
        d = np.where(pick, d + e, d)
        return _to_depth(fb, d)


class _EdgeFattening(Effect):
    name = "edge_fattening"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        zt = _z_true(context, z.shape, self.name)
        D = _true_disparity(zt, fb)
        w = self.params["width_px"]
        full = int(math.floor(w))
        frac = w - full
        levels = full + (1 if frac > 0 else 0)
        u = rng.random(z.shape)                       # drawn every frame (the same draws with any width)
        level, target = _fattening_levels(D, levels)
        fat = (level > 0) & ((level <= full) | ((level == full + 1) & (u < frac)))
        # the true disparity with the foreground grown: flying pixels come after, at the apparent edge
        d_edges = np.where(fat, target, D)
        d_edges.flags.writeable = False
        context["d_edges"] = d_edges
        if not fat.any():
            return z
        d = _to_disparity(fb, z)
        noise = np.where(np.isfinite(d) & (D > 0), d - D, 0.0)
        d = np.where(fat, target + noise, d)
        return _to_depth(fb, d)


class _FlyingPixels(Effect):
    name = "flying_pixels"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        D = context.get("d_edges")
        if D is None:
            D = _true_disparity(_z_true(context, z.shape, self.name), fb)
        elif np.shape(D) != z.shape:
            raise ValueError(f"{self.name}: context['d_edges'] must have shape {z.shape}, got {np.shape(D)}")
        b = self.params["band_px"]
        pick = rng.random(z.shape) < self.params["fraction"]
        lam = rng.random(z.shape)
        edge, _ = _jump_pixels(D, EDGE_JUMP_PX)
        band = edge
        for _ in range(b):
            band = _max3(band.astype(np.float64)) > 0
        dmax, dmin = D, np.where(D > 0, D, np.inf)
        for _ in range(b + 1):
            dmax, dmin = _max3(dmax), _min3(dmin)
        d = _to_disparity(fb, z)
        fly = band & pick & np.isfinite(d) & (dmin > 0) & np.isfinite(dmin) & (dmax - dmin > EDGE_JUMP_PX)
        if not fly.any():
            return z
        near = np.where(np.abs(d - dmax) <= np.abs(d - dmin), dmax, dmin)
        noise = d - near
        d = np.where(fly, lam * dmax + (1.0 - lam) * dmin + noise, d)
        return _to_depth(fb, d)


class _DisparityQuantization(Effect):
    name = "disparity_quantization"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        q = float(2 ** self.params["subpixel_bits"])
        d = _to_disparity(fb, z)
        return _to_depth(fb, np.round(d * q) / q)


class _InvalidBand(Effect):
    name = "invalid_band"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        zt = _z_true(context, z.shape, self.name, fallback=z)
        u = np.arange(z.shape[1], dtype=np.float64)[None, :]
        with np.errstate(invalid="ignore", divide="ignore"):
            ref = np.where(_valid(zt), zt, z)
            band = _valid(ref) & (u < fb / ref + self.params["margin_px"])
        out = z.copy()
        out[band] = np.nan
        return out


class _Dropout(Effect):
    name = "dropout"

    def probability(self, z_true, theta) -> np.ndarray:
        """P(no data) per pixel: logistic in z [m] and -ln cos(theta) (NaN where nothing is hit)."""
        from scipy.special import expit, logit

        p = self.params
        th = np.minimum(np.abs(theta), _THETA_DROPOUT_MAX)
        with np.errstate(invalid="ignore"):
            eta = logit(p["p_1m"]) + p["k_z"] * (z_true - 1.0) - p["k_theta"] * np.log(np.cos(th))
        return expit(eta)

    def _thresholds(self, zt, z, theta):
        """Phi^-1(P) per pixel (-inf where nothing is hit); the last map is kept (static scenes)."""
        from scipy.special import ndtri

        ref = np.where(_valid(zt), zt, z)
        key = (ref.shape, zlib.crc32(np.ascontiguousarray(ref).tobytes()),
               zlib.crc32(np.ascontiguousarray(theta, dtype=np.float64).tobytes()))
        cached = getattr(self, "_tcache", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        ok = _valid(ref) & np.isfinite(theta)
        p = np.zeros(z.shape)
        p[ok] = self.probability(ref[ok], theta[ok])
        with np.errstate(divide="ignore"):
            t = ndtri(p)
        t.flags.writeable = False
        self._tcache = (key, t)
        return t

    def _apply(self, z, theta, rng, context):
        zt = _z_true(context, z.shape, self.name, fallback=z)
        g = gaussian_random_field(z.shape, self.params["length_px"], rng)
        t = self._thresholds(zt, z, theta)
        out = z.copy()
        out[g < t] = np.nan
        return out


# =============================================================================================
# factories
# =============================================================================================
def axial_refit(c0: float = D435.axial_coefficients[0], c1: float = D435.axial_coefficients[1],
                c2: float = D435.axial_coefficients[2], c_theta: float = D435.axial_coefficients[3], *,
                model: SensorModel = D435) -> Effect:
    """The paper's sigma_z with refitted coefficients (the axial noise's magnitude, not its shape).

    Physics and source: Ahn et al. 2019 fitted sigma_z(z, theta) = c0 + c1 z + c2 z^2
    + c_theta z^1.5 theta / (pi/2 - theta)^2 to one D435 with plane fits, which mix temporal noise,
    static patterns, quantisation and edge pixels (the notes, section 2, caveat 2); other D435 units and
    settings differ: ANYbotics/elevation_mapping's D435 model gives 2.1 mm at 1 m where the paper gives
    5.7 mm, Intel's RMS formula 3.8 mm (the notes' table in section 2). Refitting the four coefficients
    to the temporal standard deviation per distance and angle is the first thing a user does.

    Forward model: the reference deviation is rescaled to the new sigma, per pixel,
    z' = z + (sigma_new / sigma_ref - 1) (z_ref - z_true), with z_ref the depth right after the
    reference noise (``context['z_ref']``, set by :func:`noise_model.analysis.capture_data.simulate_capture`;
    without it, z itself: then put axial_refit first, as :data:`ORDER` does) and sigma_* the sigma_z of
    ``model`` and of the new coefficients at (z_true, theta). The noise stays Gaussian, independent per
    pixel and frame, with standard deviation sigma_new exactly; nothing is drawn from ``rng``.

    D435 values: the paper's (0.001063, 0.0007278, 0.003949, 0.022); quieter units and modes reach
    ~0.4-0.6 of them (elevation_mapping's fit). Parameters in [0, 0.05] m, [0, 0.05], [0, 0.05] 1/m,
    [0, 1] m^-1/2, sigma_new > 0 everywhere (c0 > 0).

    Parameters
    ----------
    c0 : float
        Constant term [m], in (0, 0.05].
    c1 : float
        Linear term [-], in [0, 0.05].
    c2 : float
        Quadratic term [1/m], in [0, 0.05].
    c_theta : float
        Angle term [m^-1/2], in [0, 1].
    model : SensorModel
        The reference (the paper's D435).
    """
    ps = {"c0": _scalar(c0, "c0", 0.0, 0.05, open_lo=True), "c1": _scalar(c1, "c1", 0.0, 0.05),
          "c2": _scalar(c2, "c2", 0.0, 0.05), "c_theta": _scalar(c_theta, "c_theta", 0.0, 1.0)}
    return _AxialRefit(ps, _check_model(model))


def depth_bias(scale: float = DEPTH_BIAS_DEFAULTS["scale"], offset_px: float = DEPTH_BIAS_DEFAULTS["offset_px"], *,
               baseline_m: float = DEPTH_BIAS_DEFAULTS["baseline_m"]) -> Effect:
    """A depth scale error and a disparity offset (E4).

    Physics and source (the notes, E4): an error of f b (focal length, baseline, rectification scale)
    is multiplicative; an offset in disparity (principal-point / rectification error) gives a bias
    growing as z^2; temperature moves both (librealsense #8434, #9561; Intel's "Tare" self-calibration
    white paper exists to remove it). An out-of-box D435 averaged 980.7 mm at 1000 mm (-1.9 %,
    M. Calvert); the datasheet's absolute accuracy is ~2 % at 2 m; offset_px = 0.05 px at 848 x 480 is
    2.4 / 9.5 / 21 mm at 1 / 2 / 3 m.

    Forward model: with f = ``context['K'][0, 0]`` [px] and b = ``baseline_m``: the depth's disparity
    d = f b / z is offset, d' = d + offset_px, and the depth scaled: z' = scale * f b / d'. To first
    order z' - z ~ (scale - 1) z - scale z^2 offset_px / (f b): a positive offset makes the far range
    read short. Pixels whose d' <= 0 become no data. Nothing is drawn from ``rng``.

    Parameters
    ----------
    scale : float
        Depth scale factor, in [0.5, 2] (default 0.99: -1 %).
    offset_px : float
        Disparity offset [px of the simulated stream], in [-5, 5] (default 0.05).
    baseline_m : float
        Stereo baseline b [m] (D435: 0.050).

    Returns
    -------
    Effect
        ``effect(z, theta, rng, context) -> z``; needs ``context['K']``; draws nothing from ``rng``.
    """
    s = _scalar(scale, "scale", 0.5, 2.0)
    off = _scalar(offset_px, "offset_px", -5.0, 5.0)
    b = check_positive_scalar(baseline_m, "baseline_m", upper=2.0, unit=" m")
    return _DepthBias({"scale": s, "offset_px": off, "baseline_m": b})


def static_pattern(sigma_px: float = 0.03, length_px: float = 6.0, seed: int = 0) -> Effect:
    """A fixed-pattern disparity error, the same in every frame of a capture (E5, E10).

    Physics and source (the notes, E5 and E10): residual lens distortion, rectification and imager
    alignment errors make a smooth disparity-offset field over the image ("calibration and lens
    distortions ... limit whole FOV uniformity", librealsense #3904; ring-like patterns of ~1 % of the
    distance, #3210; concave planes, #4939, #11511); and with a static scene the projector's dots and
    the camera are fixed, so most matching errors repeat every frame: a temporal average does not
    remove them (Intel's Depth Quality Tool separates spatial from temporal noise,
    ``tools/depth-quality/readme.md``). The paper's model is independent per frame.

    Forward model: d' = f B / z + sigma_px G(u, v), z' = f B / d', with G a Gaussian random field of
    correlation exp(-h^2 / (2 length_px^2)) (:func:`gaussian_random_field`) shifted and scaled to zero
    mean and unit standard deviation over the image (so ``sigma_px`` is exactly the pattern's spatial
    standard deviation [px]). G is constant over the frames of a capture: it is drawn from its own
    generator, ``numpy.random.default_rng([seed, crc32(capture_id), H, W])`` (``context['capture_id']``;
    "" on a walk, where the pattern is then locked to the pixel grid for the whole walk, as a
    calibration error is), never from the frame's ``rng``. Different captures get different
    realisations of the same statistics (the static part depends on the scene under the dots).

    D435 values: a 1 % ring pattern at 1 m is ~0.2 px at 848 x 480; plane-fit sigma 4.7 mm vs maximum
    deviation 26.5 mm on a D415 at 1 m (Carfagni et al. 2019); length from ~5 px (dot spacing, matching
    window) to the image size (calibration). ``sigma_px`` in (0, 2] px, ``length_px`` in (0, 200] px,
    ``seed`` an integer in [0, 2^31 - 1] (reals are rounded).
    """
    ps = {"sigma_px": _scalar(sigma_px, "sigma_px", 0.0, 2.0, open_lo=True),
          "length_px": _scalar(length_px, "length_px", 0.0, 200.0, open_lo=True),
          "seed": _integer(seed, "seed", 0, 2 ** 31 - 1)}
    return _StaticPattern(ps)


def disparity_noise(s_px: float = 0.08) -> Effect:
    """Extra noise that is Gaussian in disparity, not in depth (E1).

    Physics and source (the notes, E1): the matcher estimates disparity and its error is roughly
    constant in pixels ("errors in disparity space are usually constant for a stereo system",
    Keselman et al. 2017, arXiv 1705.05548); depth is f B / d, so depth errors grow as z^2, are
    right-skewed at long range and have a small positive bias. Intel's RMS formula e = z^2 s / (f B) is
    this model (librealsense #3904: s "as low as 0.032 ... best to use about 0.08").

    Forward model (relative to the reference): the reference's depth-Gaussian noise stays (it carries
    the paper's fit of the magnitude, angle term included) and the matcher's disparity error is added
    on top of it: d = f B / z, d' = d + s_px * N(0, 1) (one standard normal per pixel and frame from
    ``rng``, drawn over the whole image), z' = f B / d' (no data where d' <= 0). Relative to the
    reference this adds the variance z^4 s^2 / (f B)^2 (flat in disparity units, no angle
    dependence), a positive mean error ~ z^3 s^2 / (f B)^2 and a right skew ~ 6 s z / (f B) of the added
    part. (The pure disparity model is this effect with :func:`axial_refit` taking the depth term down.)

    D435 values: s 0.05-0.1 px on good texture at 848 x 480, > 0.2 px suggests recalibration (Intel's
    tuning guide); in (0, 5] px.
    """
    return _DisparityNoise({"s_px": _scalar(s_px, "s_px", 0.0, 5.0, open_lo=True)})


def correlated_noise(sigma_m: float | None = None, length_px: float = CORRELATED_NOISE_DEFAULTS["length_px"], *,
                     sigma_z_fraction: float | None = None, model: SensorModel = D435) -> Effect:
    """Spatially correlated depth noise (E9): a fresh Gaussian random field each frame.

    Physics and source (the notes, E9): neighbouring D435 pixels share most of their 9 x 9 census
    window and their semi-global matching paths, and the projector's ~5000 dots are ~9 px apart at
    848 x 480, so their depth errors are correlated over several pixels (l ~ 3-10 px at 848 x 480, share
    of the variance unknown). The paper's model draws each pixel independently, so a mapper that fuses
    hundreds of pixels per cell as independent measurements becomes overconfident.

    Forward model: z' = z + sigma * g, g a unit-variance Gaussian random field with correlation
    exp(-h^2 / (2 length_px^2)) between pixels h apart (:func:`gaussian_random_field`, from ``rng``, a
    fresh field each frame), sigma = ``sigma_m`` or ``sigma_z_fraction * sigma_z(z_true, theta)`` (the
    correlated part scales with the matching error, as the white part does). The white reference noise
    stays: the total per-pixel variance is sigma_z^2 + sigma^2.

    Parameters
    ----------
    sigma_m : float, optional
        Standard deviation of the correlated part [m], the same for every pixel, in (0, 1].
    length_px : float
        Correlation length l [px of the simulated stream], in (0, 200] (default 3 px: 6 px at
        848 x 480 when simulating the 424 x 240 stream; the D435's is 3-10 px at 848 x 480).
    sigma_z_fraction : float, optional
        Instead of ``sigma_m``: the standard deviation is this fraction of the model's sigma_z at the
        true depth and incidence angle (``context['z_true']``, ``theta``), in (0, 10]. When neither is
        given: 1.0 (the correlated part as strong as the paper's white noise).
    model : SensorModel
        The sigma_z of ``sigma_z_fraction`` (the paper's D435 by default).

    Returns
    -------
    Effect
        ``effect(z, theta, rng, context) -> z``.

    Raises
    ------
    ValueError
        Both ``sigma_m`` and ``sigma_z_fraction`` given, or a value out of range.
    """
    if sigma_m is not None and sigma_z_fraction is not None:
        raise ValueError("give sigma_m or sigma_z_fraction, not both")
    ell = _scalar(length_px, "length_px", 0.0, 200.0, open_lo=True)
    _check_model(model)
    if sigma_m is not None:
        return _CorrelatedNoise({"sigma_m": _scalar(sigma_m, "sigma_m", 0.0, 1.0, open_lo=True), "length_px": ell},
                                model)
    frac = CORRELATED_NOISE_DEFAULTS["sigma_z_fraction"] if sigma_z_fraction is None else sigma_z_fraction
    return _CorrelatedNoise({"sigma_z_fraction": _scalar(frac, "sigma_z_fraction", 0.0, 10.0, open_lo=True),
                             "length_px": ell}, model)


def outliers(fraction: float = 0.01, sigma_px: float = 1.0) -> Effect:
    """Heavy tails: a fraction of pixels with a wide disparity error (E13, E15).

    Physics and source (the notes, E13 and E15): the matcher sometimes locks onto a wrong match:
    repetitive texture aliases to other disparities (librealsense #8258, realsense-ros #2667),
    reflections make ghost points (realsense-ros #1343), near range beyond the 126 px search gives
    "flickering points where the distance can be anything" (#8400, #14447). The D4 ASIC outputs a match
    or nothing, so such pixels are valid depths far from the truth, not holes: the residual
    distribution has heavy tails that a Gaussian model lacks.

    Forward model: each valid pixel, independently per frame, with probability ``fraction`` (a uniform
    draw per pixel from ``rng``) gets a disparity error e ~ N(0, sigma_px^2) (a standard normal per
    pixel from ``rng``; both drawn over the whole image): d' = f B / z + e, z' = f B / d', no data where
    d' <= 0 (a match beyond infinity). A mixture (1 - p) reference + p wide Gaussian in disparity.

    D435 values: gross-error rates are scene-dependent, ~0.1-3 % of pixels on matte planar targets
    [engineering estimate], up to tens of % on specular or repetitive surfaces; errors of ~1 px up to
    the search range. ``fraction`` in (0, 0.5], ``sigma_px`` in (0, 100] px.
    """
    return _Outliers({"fraction": _scalar(fraction, "fraction", 0.0, 0.5, open_lo=True),
                      "sigma_px": _scalar(sigma_px, "sigma_px", 0.0, 100.0, open_lo=True)})


def edge_fattening(width_px: float = 2.0) -> Effect:
    """The foreground spreads into the background at depth edges (E8, fattening).

    Physics and source (the notes, E8): a 9 x 9 census window (``census.uDiameter = 9`` in librealsense
    ``presets.cpp``) straddling two depths is dominated by the better-textured, usually nearer surface,
    and semi-global matching propagates its disparity across the edge: objects grow by a roughly
    constant number of pixels at all ranges (shallow depth at object edges, librealsense #12887;
    rounded corners, #7608). k ~ half the census window, 2-5 px at 848 x 480.

    Forward model: depth discontinuities are 4-neighbours whose true disparities (from
    ``context['z_true']``; no hit = disparity 0) differ by more than :data:`EDGE_JUMP_PX`; a
    background pixel at Chebyshev distance j >= 1 from the nearer pixel of a discontinuity takes that
    pixel's true disparity (the largest within distance j) plus its own current disparity error,
    d' = d_fg + (f B / z - d_true), if j <= floor(width_px), and with probability
    width_px - floor(width_px) (a uniform draw per pixel from ``rng``, drawn every frame) if
    j = floor(width_px) + 1: the foreground grows by ``width_px`` px on average into the background
    (and into pixels with no hit). Only jumps in the true depth count: a slanted plane or the ground
    never fattens. It leaves ``context['d_edges']``, the true disparity with the foreground grown, for
    :func:`flying_pixels`.

    ``width_px`` in [0, 20] px.
    """
    return _EdgeFattening({"width_px": _scalar(width_px, "width_px", 0.0, 20.0)})


def flying_pixels(fraction: float = 0.3, band_px: int = 1) -> Effect:
    """Pixels next to depth edges take depths between the two sides (E8, flying pixels).

    Physics and source (the notes, E8): a matching window straddling two depths has two cost minima;
    the subpixel fit between them and the semi-global smoothing give intermediate depths: points that
    connect an object's edge to the background (librealsense #4346, D435 at ~2 m), "ramps" at stair
    nosings in an elevation map.

    Forward model: depth discontinuities as in :func:`edge_fattening` (from ``context['z_true']``, or
    from ``context['d_edges']`` when an edge_fattening before it in the frame left it: flying pixels
    sit at the apparent, fattened edge); the band is the pixels within Chebyshev distance
    ``band_px`` of a pixel of a discontinuity (on both sides; 2 (band_px + 1) pixels across a
    straight edge); each band pixel, independently per frame
    with probability ``fraction`` (a uniform draw per pixel from ``rng``), takes the disparity
    lambda d_fg + (1 - lambda) d_bg, lambda ~ U(0, 1) (a second uniform draw per pixel), with d_fg, d_bg
    the largest and smallest true disparities within distance band_px + 1, plus the pixel's own
    current disparity error relative to the nearer of the two levels. Edges with nothing hit on one side
    have no flying pixels (nothing to interpolate to).

    D435 values: seen at most object edges; 1-3 px wide at 848 x 480 [engineering estimate].
    ``fraction`` in [0, 1], ``band_px`` an integer in [0, 10] (reals are rounded).
    """
    return _FlyingPixels({"fraction": _scalar(fraction, "fraction", 0.0, 1.0),
                          "band_px": _integer(band_px, "band_px", 0, 10)})


def disparity_quantization(subpixel_bits: int = 5) -> Effect:
    """Disparity on a lattice of 2^-subpixel_bits px (E2).

    Physics and source (the notes, E2): the D435 outputs disparity with 5 fractional bits
    (``fractional_bits = 5`` in librealsense ``src/proc/disparity-transform.h``; "1/32 subpixel ...
    4096 depth planes", intelrealsense.com/subpixel-linearity), then depth as uint16 in depth units.
    The depth lattice spacing is z^2 / (2^bits f B): at 424 x 240 (f B = 10.6 px m) 2.9 mm at 1 m,
    12 mm at 2 m for 5 bits, coarser than the 1 mm unit beyond 0.58 m. Signature: comb-shaped
    histograms; the distinct depth values lie on f B / (k 2^-bits) (issue #3583: ~5 mm increments).

    Forward model: d = f B / z, d' = round(d 2^bits) / 2^bits, z' = f B / d' (no data where d' = 0);
    the depth-unit rounding follows in the simulator. Nothing is drawn from ``rng``.

    ``subpixel_bits`` an integer in [0, 12] (D435: 5; reals are rounded).
    """
    return _DisparityQuantization({"subpixel_bits": _integer(subpixel_bits, "subpixel_bits", 0, 12)})


def invalid_band(margin_px: float = 4.0) -> Effect:
    """The D435's left invalid band (E6).

    Physics and source (the notes, E6): the left imager is the reference; its leftmost columns have
    no counterpart in the right image. The datasheet's "Invalid Depth Band" (librealsense #3684,
    #12072): band = f B / Z px; a user measured it wider (#1462): the matcher needs half its window
    and firmware margins beyond it, w0 ~ 4-10 px at 848 x 480.

    Forward model: pixel (u, v) (u the 0-based column) has no data when u < f B / z_true(u, v)
    + margin_px, with z_true from ``context['z_true']`` (the pixel's own true disparity; the current
    depth where that is missing). Nothing is drawn from ``rng``.

    D435 values: 70 / 42 / 21 / 11 px at 0.3 / 0.5 / 1 / 2 m at 848 x 480 plus w0; half at 424 x 240.
    ``margin_px`` in [-50, 200] px.
    """
    return _InvalidBand({"margin_px": _scalar(margin_px, "margin_px", -50.0, 200.0)})


def dropout(p_1m: float = 0.05, k_z: float = 1.0, k_theta: float = 1.0, length_px: float = 2.5) -> Effect:
    """Missing pixels in blobs, more with distance and incidence angle (E11).

    Physics and source (the notes, E11): the D4 ASIC outputs a match or nothing ("pixels are either
    100% matched or they are not", librealsense #7608); pixels fail the second-peak, texture,
    left-right and small-segment tests (``presets.cpp``); projected irradiance falls ~1/z^2 and the
    return with cos(theta) (Keselman et al.: range ~ sqrt(albedo cos theta)); holes come in blobs
    (Isaac Lab's "blob-like missing data"; remove-small-segments).

    Forward model: P(no data) = sigmoid(logit(p_1m) + k_z (z_true - 1 m) - k_theta ln cos(theta))
    (the notes' logistic with beta1 = k_z, beta3 = -k_theta; theta capped at 89 deg), made spatially
    structured by thresholding a Gaussian random field g (:func:`gaussian_random_field`, correlation
    length ``length_px``, a fresh field from ``rng`` every frame): a pixel is dropped when
    g < Phi^-1(P), so its marginal probability is exactly P and holes are blobs of ~length_px.

    D435 values: fill ~99 % on a matte wall at 1 m, falling at range, at grazing angles and on dark or
    glossy materials (#9737, #10229) [engineering estimate for the coefficients].
    ``p_1m`` in (0, 1), ``k_z`` in [-20, 20] 1/m, ``k_theta`` in [-20, 20], ``length_px`` in (0, 200] px.
    """
    ps = {"p_1m": _scalar(p_1m, "p_1m", 0.0, 1.0, open_lo=True), "k_z": _scalar(k_z, "k_z", -20.0, 20.0),
          "k_theta": _scalar(k_theta, "k_theta", -20.0, 20.0),
          "length_px": _scalar(length_px, "length_px", 0.0, 200.0, open_lo=True)}
    if ps["p_1m"] >= 1.0:
        raise ValueError(f"p_1m must be in (0, 1), got {p_1m!r}")
    return _Dropout(ps)


#: Effect factories by name (the identifiers of the gap report and of ``--sim-effects``).
EFFECTS = {"disparity_noise": disparity_noise, "disparity_quantization": disparity_quantization,
           "depth_bias": depth_bias, "invalid_band": invalid_band, "dropout": dropout,
           "correlated_noise": correlated_noise, "static_pattern": static_pattern, "flying_pixels": flying_pixels,
           "edge_fattening": edge_fattening, "outliers": outliers, "axial_refit": axial_refit}

#: The order in which the device applies them (the notes' "Composition order"): the noise's magnitude,
#: calibration biases, disparity noise (white, correlated, gross), edge effects, the 2^-bits lattice,
#: then the masks. :func:`canonical_order` sorts a list of effects by it.
ORDER = ("axial_refit", "depth_bias", "static_pattern", "disparity_noise", "correlated_noise", "outliers",
         "edge_fattening", "flying_pixels", "disparity_quantization", "invalid_band", "dropout")


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
    from ..checks import build_from_registry

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


# =============================================================================================
# registry of the gap diagnosis: ranges, tolerances, needs
# =============================================================================================
#: Ranges the gap selftest draws each parameter from (uniformly; :data:`INTEGER_PARAMS` rounded),
#: for the 424 x 240 stream (f B = 10.6 px m; pixel parameters are px of that stream). Realistic D435
#: values (sources in each factory's docstring), but strong enough to stand out of 18 captures x 12
#: frames at 424 x 240, and of one sign where the effect vanishes at 0 (scale < 1, offset > 0: an
#: out-of-box D435 reads short; axial_refit: a quieter unit than the paper's, as elevation_mapping's
#: fit is), so that no draw is an invisible effect. The fits are not restricted to these ranges.
PARAM_RANGES = {
    # 0.04 px adds 3.8 mm at 1 m / 15 mm at 2 m at 424 x 240 (the paper: 5.7 / 18 mm)
    "disparity_noise": {"s_px": (0.04, 0.12)},
    # 3-6 fractional bits: lattice 1.5-12 mm at 1 m, 5.9-47 mm at 2 m (the D435: 5)
    "disparity_quantization": {"subpixel_bits": (3, 6)},
    # -1 to -2.5 % scale; 0.02-0.08 px offset: -7.5 to -30 mm at 2 m at 424 x 240
    "depth_bias": {"scale": (0.975, 0.99), "offset_px": (0.02, 0.08)},
    # w0 of E6: 4-10 px at 848 x 480, 2-8 px here
    "invalid_band": {"margin_px": (2.0, 8.0)},
    # 3-12 % missing at 1 m fronto-parallel, rising with z and theta; blobs of 1.5-4 px
    "dropout": {"p_1m": (0.03, 0.12), "k_z": (0.5, 1.5), "k_theta": (0.5, 1.5), "length_px": (1.5, 4.0)},
    # 0.5-1.2 sigma_z correlated over 1.5-4 px (3-8 px at 848 x 480, the notes: 3-10)
    "correlated_noise": {"sigma_z_fraction": (0.5, 1.2), "length_px": (1.5, 4.0)},
    # 0.02-0.05 px: 1.9-4.7 mm at 1 m, 7.5-19 mm at 2 m; correlated over 3-10 px
    "static_pattern": {"sigma_px": (0.02, 0.05), "length_px": (3.0, 10.0), "seed": (0, 1_000_000)},
    # 15-50 % of the band's pixels, band 0-3 px (2-8 px across an edge)
    "flying_pixels": {"fraction": (0.15, 0.5), "band_px": (0, 3)},
    # 1.5-4.5 px (E8: 2-5 px at 848 x 480 is 1-2.5 px here; upper end for the D435's default preset)
    "edge_fattening": {"width_px": (1.5, 4.5)},
    # 0.5-2 % gross errors of 0.5-2 px (5-20 % of the disparity at 2 m)
    "outliers": {"fraction": (0.005, 0.02), "sigma_px": (0.5, 2.0)},
    # a quieter unit than the paper's (0.001063, 0.0007278, 0.003949, 0.022)
    "axial_refit": {"c0": (0.0004, 0.0009), "c1": (0.0002, 0.0006), "c2": (0.0018, 0.003), "c_theta": (0.010, 0.016)},
}
#: Parameters that are integers (drawn as integers by :func:`draw_params`; factories round reals).
INTEGER_PARAMS = {"disparity_quantization": ("subpixel_bits",), "flying_pixels": ("band_px",),
                  "static_pattern": ("seed",)}
#: How close :func:`fit_effect` recovers each parameter when the data are the reference simulation
#: plus that effect at parameters of :data:`PARAM_RANGES`, on captures like the gap selftest's (walls
#: at >= 3 distances in 0.5-2 m and 0 to >= 45 deg; boards 0.6 x 0.9 m before a wall at 3 m at
#: 0.9-2.1 m for the edge effects; 8-12 frames at 424 x 240): ("abs", x) = |fit - true| <= x, ("rel", x)
#: = |fit - true| <= x |true|. Each is 3-5 times the largest error measured over 10 random draws on
#: 8 walls / 8 boards x 8 frames (the module's tests) and 6 draws on 18 captures x 12 frames.
#: Parameters not listed (``seed``, ``baseline_m``) are not estimated. Caveats: invalid_band's 0.5 px
#: needs several distances (the step between consecutive c = u - f B / z values); edge_fattening's
#: 0.3 px needs boards whose top or bottom edge is in view (>= 0.85 m for 0.9 m at 424 x 240), the
#: left/right edges alone are noisy (lateral sigma / sqrt(frames), ~3 px per edge at 1 m).
FIT_TOLERANCE = {
    "disparity_noise": {"s_px": ("rel", 0.05)},
    "disparity_quantization": {"subpixel_bits": ("abs", 0)},
    "depth_bias": {"scale": ("abs", 0.001), "offset_px": ("abs", 0.006)},
    "invalid_band": {"margin_px": ("abs", 0.5)},
    "dropout": {"p_1m": ("rel", 0.1), "k_z": ("abs", 0.1), "k_theta": ("abs", 0.2), "length_px": ("rel", 0.1)},
    "correlated_noise": {"sigma_z_fraction": ("rel", 0.05), "length_px": ("rel", 0.05)},
    "static_pattern": {"sigma_px": ("rel", 0.1), "length_px": ("rel", 0.15)},
    "flying_pixels": {"fraction": ("rel", 0.1), "band_px": ("abs", 0)},
    "edge_fattening": {"width_px": ("abs", 0.3)},
    "outliers": {"fraction": ("rel", 0.1), "sigma_px": ("rel", 0.1)},
    "axial_refit": {"c0": ("abs", 0.0002), "c1": ("abs", 0.0003), "c2": ("abs", 0.0002), "c_theta": ("abs", 0.001)},
}
#: :data:`FIT_TOLERANCE` when every capture has a single frame (same captures otherwise: 8 walls or
#: 8 boards x 1 frame at 424 x 240), ~3 times the largest error over 10 random draws. What one frame
#: cannot give is not in it: the fits of disparity_noise, correlated_noise, static_pattern and
#: axial_refit read the frame's excess *spatial* statistics, so they recover their parameter when the
#: data hold that effect alone, but cannot tell it from the others of the four (temporal vs static:
#: see each fit). Captures of 2 frames meet :data:`FIT_TOLERANCE`.
FIT_TOLERANCE_SINGLE_FRAME = {
    "disparity_noise": {"s_px": ("rel", 0.03)},
    "disparity_quantization": {"subpixel_bits": ("abs", 0)},
    "depth_bias": {"scale": ("abs", 0.002), "offset_px": ("abs", 0.02)},
    "invalid_band": {"margin_px": ("abs", 0.5)},
    "dropout": {"p_1m": ("rel", 0.06), "k_z": ("abs", 0.07), "k_theta": ("abs", 0.3), "length_px": ("rel", 0.4)},
    "correlated_noise": {"sigma_z_fraction": ("rel", 0.03), "length_px": ("rel", 0.06)},
    "static_pattern": {"sigma_px": ("rel", 0.05), "length_px": ("rel", 0.16)},
    "flying_pixels": {"fraction": ("rel", 0.1), "band_px": ("abs", 0)},
    "edge_fattening": {"width_px": ("abs", 0.15)},
    "outliers": {"fraction": ("rel", 0.2), "sigma_px": ("rel", 0.1)},
    "axial_refit": {"c0": ("abs", 0.0003), "c1": ("abs", 0.0005), "c2": ("abs", 0.0003), "c_theta": ("abs", 0.0004)},
}
#: Captures each fit uses: "wall" (a wall, all of it but the left band), "board" (a board's interior),
#: "board+background" (a board before a background wall: its left and right edges). A fit uses every
#: capture of the kinds listed (:func:`usable_captures`) and raises ValueError when there is none.
#: Also needed: disparity_quantization depth where the 2^-bits lattice is >= 2 depth units apart (at
#: 424 x 240 and 1 mm units: z >= 0.82 m for 5 bits, 1.16 m for 6); depth_bias distances spanning
#: >= 1.5x to tell the scale from the offset;
#: axial_refit distances from ~0.5 to ~2 m and angles from 0 to >= 45 deg (the angle term); dropout
#: angles >= 45 deg too (k_theta: with boards at 0 and 30 deg alone it is off by up to 0.3);
#: static_pattern large interiors (walls; a board's interior holds few pattern cells: ~15 % errors);
#: invalid_band any planar targets at several distances.
#: Single frames (or few): every fit runs on captures of one frame (see :func:`fit_effect`).
#: Assumptions then: disparity_noise, axial_refit take the frame's spatial spread about the target's
#: plane as per-frame noise, correlated_noise and static_pattern take its whole excess spatial
#: correlation as theirs (static vs per-frame is not identifiable from one frame). Too narrow a design
#: fixes what it cannot determine: depth_bias with distances spanning < 1.5x fits a scale alone
#: (offset_px 0); dropout fixes k_z = 0 with distances spanning < 1.5x and k_theta = 0 with angles
#: spanning < 25 deg; axial_refit fits one factor on the paper's coefficients (plus c_theta with
#: angles, or c0..c2 with distances spanning >= 2x). Captures whose target does not fill the image
#: (a plane fitted to a region of a frame) need ``rois`` in :func:`fit_effect`, or the fits read the
#: other surfaces as the target's errors.
NEEDS = {
    "disparity_noise": ("wall", "board"),
    "disparity_quantization": ("wall", "board"),
    "depth_bias": ("wall", "board"),
    "invalid_band": ("wall", "board"),
    "dropout": ("wall", "board"),
    "correlated_noise": ("wall", "board"),
    "static_pattern": ("wall", "board"),
    "flying_pixels": ("board+background",),
    "edge_fattening": ("board+background",),
    "outliers": ("wall", "board"),
    "axial_refit": ("wall", "board"),
}


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


def _capture_kinds(geometry) -> set:
    if geometry.kind == "wall":
        return {"wall"}
    return {"board", "board+background"} if geometry.background_m is not None else {"board"}


def usable_captures(name: str, captures: Sequence) -> list:
    """The captures (CaptureData or CaptureGeometry) whose kind the fit of ``name`` uses (:data:`NEEDS`)."""
    if name not in NEEDS:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(NEEDS)}")
    out = []
    for c in captures:
        g = getattr(c, "geometry", c)
        if _capture_kinds(g) & set(NEEDS[name]):
            out.append(c)
    return out


# =============================================================================================
# fits
# =============================================================================================
def fit_effect(name: str, real: Sequence, model: SensorModel = D435, base_effects=(), *, seed: int = 0,
               cache: dict | None = None, rois: Mapping | None = None) -> dict:
    """Estimate the parameters of effect ``name`` from real captures.

    Every fit compares a statistic the effect changes between the real captures and the *base*
    simulation of the same captures (:func:`noise_model.analysis.capture_data.simulate_capture` with ``model``
    and ``base_effects`` in :func:`canonical_order`, as many frames as the real capture, seeded by
    ``seed`` and the capture id: common random numbers across fits), and inverts the effect's
    forward model on the difference (method of moments, maximum likelihood or a 1-D search; see each
    ``_fit_*``). Only the captures of :data:`NEEDS` are used (and simulated).

    Parameters
    ----------
    name : str
        An effect of :data:`EFFECTS`.
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
    from ..analysis.capture_data import check_captures

    if name not in _FITS:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(_FITS)}")
    _check_model(model)
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
            params = _FITS[name](use, base, model, base_effects=base_effects, seed=int(seed),
                                 cache={} if cache is None else cache, rois=rois)
    except (ArithmeticError, np.linalg.LinAlgError, IndexError) as exc:
        raise ValueError(f"fit of {name} failed on these captures ({type(exc).__name__}: {exc})") from exc
    return _valid_params(name, params)


def _check_rois(rois, real) -> dict:
    """{id: bool (H, W)} for the captures of ``real`` that have a region of interest (checked)."""
    if rois is None:
        return {}
    if not isinstance(rois, Mapping):
        raise ValueError(f"rois must be a mapping capture id -> boolean image, got {type(rois).__name__}")
    out = {}
    for c in real:
        if c.id not in rois or rois[c.id] is None:
            continue
        r = np.asarray(rois[c.id])
        g = c.geometry
        if r.dtype != bool or r.shape != (g.height, g.width):
            raise ValueError(f"rois[{c.id!r}] must be a boolean image of shape ({g.height}, {g.width}), "
                             f"got {r.dtype} {r.shape}")
        out[c.id] = r
    return out


def _valid_params(name: str, params: dict) -> dict:
    """The fit's parameters made valid for the factory: finite (else ValueError naming the parameter),
    clipped to :data:`_VALID` and the factories' ranges, integers rounded; then the effect is built
    once, so that a parameter the factory refuses is a ValueError of the fit, never of a later step."""
    out = {}
    for k, v in params.items():
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise ValueError(f"fit of {name}: parameter {k} is not a number ({v!r})")
        if not math.isfinite(float(v)):
            raise ValueError(f"fit of {name}: parameter {k} could not be estimated from these captures "
                             f"(the estimate is {float(v)})")
        out[k] = v
    for k, (lo, hi) in _VALID.get(name, {}).items():          # within the factory's own ranges
        if k in out:
            out[k] = float(min(max(float(out[k]), lo), hi))
    for k in INTEGER_PARAMS.get(name, ()):
        if k in out:
            lo, hi = _INT_VALID.get((name, k), (0, 2 ** 31 - 1))
            out[k] = int(min(max(int(math.floor(float(out[k]) + 0.5)), lo), hi))
    try:
        make_effect(name, **out)
    except ValueError as exc:
        raise ValueError(f"fit of {name} returned parameters the effect refuses: {exc}") from None
    return out


#: The factories' valid ranges that a fit could leave (ill-determined parameters of a null effect).
_VALID = {"disparity_noise": {"s_px": (1e-6, 5.0)}, "depth_bias": {"scale": (0.5, 2.0), "offset_px": (-5.0, 5.0)},
          "invalid_band": {"margin_px": (-50.0, 200.0)},
          "dropout": {"p_1m": (1e-9, 1.0 - 1e-9), "k_z": (-20.0, 20.0), "k_theta": (-20.0, 20.0),
                      "length_px": (0.05, 200.0)},
          "correlated_noise": {"sigma_z_fraction": (1e-6, 10.0), "length_px": (0.05, 200.0)},
          "static_pattern": {"sigma_px": (1e-9, 2.0), "length_px": (0.05, 200.0)},
          "flying_pixels": {"fraction": (0.0, 1.0)}, "edge_fattening": {"width_px": (0.0, 20.0)},
          "outliers": {"fraction": (1e-9, 0.5), "sigma_px": (1e-6, 100.0)},
          "axial_refit": {"c0": (1e-9, 0.05), "c1": (0.0, 0.05), "c2": (0.0, 0.05), "c_theta": (0.0, 1.0)}}
#: The factories' ranges of the integer parameters.
_INT_VALID = {("disparity_quantization", "subpixel_bits"): (0, 12), ("flying_pixels", "band_px"): (0, 10),
              ("static_pattern", "seed"): (0, 2 ** 31 - 1)}


def _base_sims(real, model, base_effects, seed, cache) -> list:
    from ..analysis.capture_data import CaptureData, simulate_capture

    effects = canonical_order(base_effects)
    ekey = tuple(repr(e) for e in effects)
    mkey = (model.name, tuple(float(c) for c in model.axial_coefficients), float(model.sigma_L),
            float(model.sigma_R))
    out = []
    for c in real:
        g = c.geometry
        key = ("base", g.id, id(g), c.n_frames, ekey, seed, mkey)
        if key not in cache:
            rng = np.random.default_rng([seed, zlib.crc32(g.id.encode("utf-8"))])
            cache[key] = CaptureData.from_units(g, simulate_capture(g, c.n_frames, rng, model, effects))
        out.append(cache[key])
    return out


def _nominal(g, model):
    """Nominal z_true, theta, regions, f B of a geometry (cached on it)."""
    key = ("fit_nominal", float(model.sigma_L), float(model.sigma_R))
    if key not in g._cache:
        z, th = g.render()
        g._cache[key] = (z, th, g.regions(model=model), g.fb_px_m)
    return g._cache[key]


#: The fits use target pixels up to this true depth [m] (a steep wall reaches hundreds of metres in the
#: image corners, where the depth is noise and the uint16 range truncates it).
FIT_MAX_Z_M = 10.0


def _roi(rois, g):
    """The capture's region of interest (bool (H, W)) or None."""
    return rois.get(g.id) if rois else None


def _interior(g, model, roi=None):
    """Interior pixels of the target (region INTERIOR) with z_true <= FIT_MAX_Z_M, on a board also
    4 lateral sigmas from its left and right edges (cached); only those in ``roi`` when given."""
    if roi is not None:
        return _interior(g, model) & roi
    from ..analysis.capture_data import REGION_INTERIOR

    key = ("fit_interior", float(model.sigma_L), float(model.sigma_R))
    if key not in g._cache:
        z, th, reg, fb = _nominal(g, model)
        with np.errstate(invalid="ignore"):
            m = (reg == REGION_INTERIOR) & (z <= FIT_MAX_Z_M)
            if g.kind == "board":
                # a board's left/right edges move by N(0, sigma^2) each frame: keep 4 sigma away from them
                s, _ = g.board_coordinates()
                w2 = g.target["width_m"] / 2.0
                m &= (s + w2 > 4.0 * model.sigma_L) & (w2 - s > 4.0 * model.sigma_R)
        g._cache[key] = m
    return g._cache[key]


def _robust_temporal_var(x, scale=None, min_count: int = 3):
    """Per-pixel temporal variance (ddof 1) of x (F, N), NaN = missing, after dropping values more than
    6 robust sigmas from the pixel's mean (outliers), in two passes. The robust sigma of a pixel is
    ``scale`` (N,) (its expected noise, e.g. the model's; 1 if None) times the median absolute
    deviation of the residuals divided by their scales, pooled over the pixels. Returns
    (var (N,), count (N,)); var is NaN where fewer than ``min_count`` (>= 2) values remain."""
    v = np.isfinite(x)
    x0 = np.where(v, x, 0.0)
    n = v.sum(axis=0)
    sc = np.ones(x.shape[1]) if scale is None else np.where(np.asarray(scale) > 0, np.asarray(scale), 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        m = x0.sum(axis=0) / n
        r = np.abs(x0 - m) / sc
    rs = r[v]
    if rs.size == 0:
        return np.full(x.shape[1], np.nan), np.zeros(x.shape[1], dtype=int)
    sub = rs if rs.size <= 200_000 else rs[:: rs.size // 200_000 + 1]
    s = 1.4826 * float(np.median(sub))
    if not s > 0:
        s = float(np.std(sub)) or 1.0
    with np.errstate(invalid="ignore"):
        keep = v & (r <= 6.0 * s)
    xk = np.where(keep, x0, 0.0)
    n2 = keep.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        m2 = xk.sum(axis=0) / n2
        var = np.where(keep, (x0 - m2) ** 2, 0.0).sum(axis=0) / np.maximum(n2 - 1, 1)
    var[n2 < max(int(min_count), 2)] = np.nan
    return var, n2


def _temporal_min_count(n_frames: int) -> int:
    """Values a pixel needs for its temporal variance: 3, or every frame of a 2-frame capture."""
    return 3 if n_frames >= 3 else 2


def _plane_residual(d, m, scale=None):
    """One frame's disparity d (H, W) [px] minus its best plane a + b u + c v over the mask's pixels with
    data, fitted by least squares, then refitted (twice at most) without the pixels more than 6 robust
    sigmas from the plane (outliers; robust sigma: ``scale`` (H, W) times 1.4826 MAD of r / scale).

    A plane target's true disparity is affine in (u, v), and so is any depth bias's image of it (a
    scale and a disparity offset), so the residual holds the frame's noise and patterns only. Returns
    (r (H, W) [px] with NaN outside the mask or without data, plane (H, W) [px] over the whole image),
    or None when fewer than 50 pixels have data.
    """
    ok = m & np.isfinite(d)
    vv, uu = np.nonzero(ok)
    if vv.size < 50:
        return None
    A = np.column_stack([np.ones(vv.size), uu, vv]).astype(np.float64)
    y = d[ok]
    sc = np.ones(vv.size) if scale is None else np.where(scale[ok] > 0, scale[ok], 1.0)
    coef = np.linalg.lstsq(A, y, rcond=None)[0]
    for _ in range(2):
        r = (y - A @ coef) / sc
        mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
        if not mad > 0:
            break
        keep = np.abs(r - np.median(r)) <= 6.0 * mad
        if keep.sum() < 50 or keep.all():
            break
        coef = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
    H, W = d.shape
    plane = coef[0] + coef[1] * np.arange(W)[None, :] + coef[2] * np.arange(H)[:, None]
    out = np.full(d.shape, np.nan)
    out[ok] = y - A @ coef
    return out, plane


def _robust_mean_square(r, scale=None):
    """Mean of r^2 (N,) over the values within 6 robust sigmas of 0 (robust sigma: ``scale`` (N,) times
    1.4826 MAD of r / scale), the spatial counterpart of :func:`_robust_temporal_var`; returns
    (mean square, kept (N,) bool). NaN values are left out."""
    r = np.asarray(r, dtype=np.float64)
    v = np.isfinite(r)
    sc = np.ones(r.shape) if scale is None else np.where(np.asarray(scale) > 0, np.asarray(scale), 1.0)
    if not v.any():
        return float("nan"), v
    a = np.abs(r[v] / sc[v])
    s = 1.4826 * float(np.median(a))
    if not s > 0:
        s = float(np.std(a)) or 1.0
    keep = np.zeros(r.shape, dtype=bool)
    keep[v] = a <= 6.0 * s
    return float(np.mean(r[keep] ** 2)) if keep.any() else float("nan"), keep


def _sigma_ref_px(g, model, mask):
    """The model's sigma_z [m] at the mask's pixels (z_true, theta of the nominal render)."""
    z, th, _, _ = _nominal(g, model)
    return _axial_sigma_unchecked(z[mask], th[mask], model)


#: Pixels per capture used by the per-pixel statistics (a fixed stride through the interior).
_MAX_SAMPLE_PX = 30_000


def _sample_mask(g, model, max_px: int = _MAX_SAMPLE_PX, roi=None):
    """The interior pixels of a capture (those in ``roi`` when given), thinned by a fixed stride to at
    most ``max_px`` (cached)."""
    key = ("fit_sample", float(model.sigma_L), float(model.sigma_R), int(max_px))
    if roi is not None:
        key = key + (zlib.crc32(np.packbits(roi).tobytes()),)
    if key not in g._cache:
        m = _interior(g, model, roi)
        idx = np.flatnonzero(m)
        if idx.size > max_px:
            idx = idx[:: int(math.ceil(idx.size / max_px))]
        out = np.zeros(m.shape, dtype=bool)
        out.flat[idx] = True
        g._cache[key] = out
    return g._cache[key]


def _pixels(c, mask):
    """Frames of c at the mask's pixels: (F, N) depth [m]."""
    return c.depth_m[:, mask]


# ---- disparity_noise ---------------------------------------------------------------------------
def _fit_disparity_noise(real, base, model, rois=None, **_):
    """Method of moments on the temporal variance in disparity units.

    The effect adds an independent N(0, s^2) to each pixel's disparity every frame, so the per-pixel
    temporal variance of d = f B / z grows by s^2 at every distance and angle. Per capture (interior
    pixels), v_real - v_base estimates s^2 (robust two-pass variance, :func:`_robust_temporal_var`);
    captures are combined with the inverse variance of that estimate, w ~ N (F - 1) / (v_base + s^2)^2
    (iterated), so far and grazing captures, whose reference noise is large, count little.

    A capture of one frame has no temporal variance: its frame's spatial variance about the target's
    best plane in disparity (:func:`_plane_residual`, :func:`_robust_mean_square`; weight N) stands in.
    One frame cannot tell noise that changes every frame from a static pattern or a correlated field
    (static_pattern, correlated_noise): their excess spatial variance is attributed to s too, so on
    single frames s is the excess disparity spread of a frame, an upper bound of the temporal part.
    Captures of two frames use both (a pixel needs its two values).
    """
    vr, vb, n = [], [], []
    for c, b in zip(real, base):
        g = c.geometry
        m = _sample_mask(g, model, roi=_roi(rois, g))
        fb = g.fb_px_m
        zt = _nominal(g, model)[0][m]
        sd = np.sqrt((_sigma_ref_px(g, model, m) * fb / zt ** 2) ** 2 + 0.05 ** 2)
        if c.n_frames >= 2:
            mc = _temporal_min_count(c.n_frames)
            a, na = _robust_temporal_var(fb / _pixels(c, m), sd, mc)
            s, ns = _robust_temporal_var(fb / _pixels(b, m), sd, mc)
            ok = np.isfinite(a) & np.isfinite(s)
            if ok.sum() < 50:
                continue
            vr.append(float(np.mean(a[ok])))
            vb.append(float(np.mean(s[ok])))
            n.append(float(ok.sum()) * (c.n_frames - 1))
        else:
            sdi = np.ones(m.shape)
            sdi[m] = sd
            with np.errstate(divide="ignore", invalid="ignore"):
                pr = _plane_residual(fb / c.depth_m[0], m, sdi)
                pb = _plane_residual(fb / b.depth_m[0], m, sdi)
            if pr is None or pb is None:
                continue
            a, ka = _robust_mean_square(pr[0][m], sd)
            s, kb = _robust_mean_square(pb[0][m], sd)
            if min(ka.sum(), kb.sum()) < 50:
                continue
            vr.append(a)
            vb.append(s)
            n.append(float(min(ka.sum(), kb.sum())))
    if not vr:
        raise ValueError("disparity_noise: no capture with >= 50 interior pixels with data (>= 3 values per "
                         "pixel over the frames, both of a 2-frame capture, or the one frame)")
    vr, vb, n = np.array(vr), np.array(vb), np.array(n, dtype=float)
    s2 = 0.0
    for _ in range(4):
        w = n / (vb + max(s2, 0.0)) ** 2
        s2 = float(np.sum(w * (vr - vb)) / np.sum(w))
    return {"s_px": float(math.sqrt(max(s2, 1e-8)))}


# ---- disparity_quantization ----------------------------------------------------------------------
def _lattice_member(k, A):
    """Whether depth unit k is round(A / n) for an integer n > 0 (A = f B 2^bits / depth_scale)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        hi = np.floor(A / (k - 0.5))
        return hi * (k + 0.5) >= A


#: Relative range of the search over f B of the lattice fit (+-1 %): the depth is f B / d with the
#: device's own f B, which can differ from the calibration's K[0, 0] * baseline_m the capture set
#: states (a baseline of 49.8 mm instead of the nominal 50 mm is -0.4 %); the lattice f B / (n 2^-b)
#: moves by k * rel depth units at value k, so it is found only at the right f B.
LATTICE_FB_RANGE = 0.01
_LATTICE_BITS = tuple(range(2, 11))


def _camera_key(g):
    return (int(g.width), int(g.height), tuple(float(x) for x in np.round(np.asarray(g.K).ravel(), 6)),
            float(g.depth_scale), float(g.baseline_m))


def _lattice_hists(real, base, model, rois):
    """Per capture: (id, camera key, distinct depth units k, real counts, base counts, f B / depth_scale)."""
    hists = []
    for c, b in zip(real, base):
        g = c.geometry
        m = _sample_mask(g, model, 2 * _MAX_SAMPLE_PX, _roi(rois, g))
        kr = np.round(_pixels(c, m) / g.depth_scale)
        kb = np.round(_pixels(b, m) / g.depth_scale)
        kr = kr[np.isfinite(kr)].astype(np.int64)
        kb = kb[np.isfinite(kb)].astype(np.int64)
        kr, kb = kr[kr > 0], kb[kb > 0]
        if kr.size == 0 or kb.size == 0:
            continue
        top = int(max(kr.max(), kb.max())) + 1
        hr, hb = np.bincount(kr, minlength=top), np.bincount(kb, minlength=top)
        k = np.flatnonzero((hr > 0) | (hb > 0))
        hists.append((c.id, _camera_key(g), k.astype(np.float64), hr[k].astype(np.float64),
                      hb[k].astype(np.float64), g.fb_px_m / g.depth_scale))
    return hists


def _lattice_counts(k, h, Aq, rels):
    """Sum of the counts h (K,) of the depth units k (K,) that lie on the lattice round(Aq (1 + rel) / n),
    n = 1, 2, ..., for every rel of the uniform grid ``rels`` (R,) (:func:`_lattice_member` at each rel).

    Unit k is on it when k - 1/2 <= Aq (1 + rel) / n <= k + 1/2 for some n (one n at most where the
    lattice is >= 2 units apart): an interval of rel per (k, n), summed on the grid by differences.
    """
    if rels.size == 1:
        return np.array([float(np.sum(h[_lattice_member(k, Aq * (1.0 + rels[0]))]))])
    r0, step, R = float(rels[0]), float(rels[1] - rels[0]), rels.size
    nlo = np.ceil(Aq * (1.0 + r0) / (k + 0.5))
    nhi = np.floor(Aq * (1.0 + float(rels[-1])) / (k - 0.5))
    cnt = np.maximum(nhi - nlo + 1.0, 0.0).astype(np.int64)
    if cnt.sum() == 0:
        return np.zeros(R)
    idx = np.repeat(np.arange(k.size), cnt)
    n = nlo[idx] + (np.arange(idx.size) - np.repeat(np.cumsum(cnt) - cnt, cnt))
    kk, w = k[idx], h[idx]
    lo = n * (kk - 0.5) / Aq - 1.0
    hi = n * (kk + 0.5) / Aq - 1.0
    i0 = np.maximum(np.ceil((lo - r0) / step - 1e-9), 0).astype(np.int64)
    i1 = np.minimum(np.floor((hi - r0) / step + 1e-9), R - 1).astype(np.int64)
    ok = i0 <= i1
    diff = np.bincount(i0[ok], weights=w[ok], minlength=R + 1) - np.bincount(i1[ok] + 1, weights=w[ok],
                                                                               minlength=R + 1)
    return np.cumsum(diff)[:R]


def _lattice_group_scan(group, bits: int, rel_range: float):
    """One camera's captures at one lattice: the relative f B error rel (grid over +-rel_range, fine
    enough to move the lattice by <= 1/4 unit at the largest value) that puts most real values on the
    lattice; returns dict(rel, mr, nr, mb, nb, score, alias) or None when no value is testable.

    Only values where the lattice is >= 2 units apart are tested (k^2 / (2^b A) >= 2). The score is
    L = (f - f0) / (1 - f0) (f, f0: fractions of the real and the base values on the lattice); among
    rel within 0.02 of the best score, the one nearest 0 (the stated f B) is kept: over a narrow range
    of depths the lattice repeats every ``alias`` ~ 1 / (mean disparity in lattice steps) in rel.
    """
    q = 2.0 ** bits
    parts = []
    for _, _, k, hr, hb, A in group:
        sel = k * k / (q * A) >= 2.0
        if sel.any():
            parts.append((k[sel], hr[sel], hb[sel], A * q))
    if not parts:
        return None
    kmax = max(float(p[0].max()) for p in parts)
    nsteps = int(min(20000, max(2, math.ceil(rel_range * 4.0 * kmax))))
    rels = np.linspace(-rel_range, rel_range, 2 * nsteps + 1) if rel_range > 0 else np.zeros(1)
    mr = np.zeros(rels.size)
    mb = np.zeros(rels.size)
    nr = nb = 0.0
    tsum = tn = 0.0
    for k, hr, hb, Aq in parts:
        mr += _lattice_counts(k, hr, Aq, rels)
        mb += _lattice_counts(k, hb, Aq, rels)
        nr += float(hr.sum())
        nb += float(hb.sum())
        tsum += float(np.sum(hr * Aq / k))
        tn += float(hr.sum())
    if nr <= 0 or nb <= 0:
        return None
    fr, f0 = mr / nr, mb / nb
    with np.errstate(divide="ignore", invalid="ignore"):
        score = np.where(f0 < 0.95, (fr - f0) / (1.0 - f0), -np.inf)
    best = float(np.max(score))
    near = np.flatnonzero(score >= best - 0.02)
    i = int(near[np.argmin(np.abs(rels[near]))])
    return {"rel": float(rels[i]), "mr": float(mr[i]), "nr": nr, "mb": float(mb[i]), "nb": nb,
            "score": float(score[i]), "alias": float(tn / tsum) if tsum > 0 else float("nan")}


def _lattice_scan(hists, rel_range: float = LATTICE_FB_RANGE):
    """The lattice fit: (bits or None, {bits: [(ids, key, group scan), ...]}, tested), tested = whether any
    b had >= 500 testable real and base values; see _fit_disparity_quantization."""
    groups: dict = {}
    for h in hists:
        groups.setdefault(h[1], []).append(h)
    scans = {}
    tested = False
    for bits in _LATTICE_BITS:
        rows = []
        for key, grp in groups.items():
            r = _lattice_group_scan(grp, bits, rel_range)
            if r is not None:
                rows.append(([h[0] for h in grp], key, r))
        scans[bits] = rows
        nr = sum(r["nr"] for _, _, r in rows)
        nb = sum(r["nb"] for _, _, r in rows)
        if nr < 500 or nb < 500:
            continue
        fr = sum(r["mr"] for _, _, r in rows) / nr
        f0 = sum(r["mb"] for _, _, r in rows) / nb
        if f0 >= 0.95:
            continue
        tested = True
        if (fr - f0) / (1.0 - f0) >= 0.7:
            return bits, scans, True
    return None, scans, tested


def _fit_disparity_quantization(real, base, model, rois=None, **_):
    """The coarsest disparity lattice the depth values lie on, at the f B the device uses.

    For bits b = 2..10, the depth units k the lattice f B / (n 2^-b) can produce (:func:`_lattice_member`)
    are tested where that lattice is >= 2 units apart at the value itself (k^2 u / (2^b f B) >= 2, where
    its density among the integers is <= 1/2), on the histograms of the interior's depth units: the
    fraction f_b of real values on it is compared with the base simulation's f0_b (continuous
    disparities, only the unit rounding): score L_b = (f_b - f0_b) / (1 - f0_b), 1 when every value is
    on the lattice, <= ~1/2 when the data's lattice is finer. The estimate is the smallest b with
    L_b >= 0.7 (finer lattices contain coarser ones, so every b above it also scores ~1); 10 when none
    does (no lattice visible: at 424 x 240 a 10-bit lattice is < 0.4 mm at 2 m); ValueError when no b
    has 500 values to test (every target nearer than the depth unit resolves the lattice).

    f B: the lattice is f B / (n 2^-b) with the device's f B, which may differ from the capture's
    K[0, 0] * baseline_m by a fraction of a percent (a 0.2 % error moves the 1/32 px lattice by a whole
    step at 1.6 m at 848 x 480 and hides it). So the captures are grouped by camera (same intrinsics,
    size, depth scale and baseline) and each group's f B is searched over +-:data:`LATTICE_FB_RANGE`
    (:func:`_lattice_group_scan`; f0 at the same f B); f_b and f0_b pool the groups at their own f B,
    so captures of different cameras (e.g. a 424 x 240 stream, whose depth is not on the 848 x 480
    lattice) neither hide nor fake another's lattice. :func:`disparity_lattice` reports the f B found.
    Works on single frames unchanged (it counts values, not frames).
    """
    hists = _lattice_hists(real, base, model, rois)
    if not hists:
        raise ValueError("disparity_quantization: no valid depth in the captures' interiors")
    bits, _, tested = _lattice_scan(hists)
    if not tested:
        raise ValueError("disparity_quantization: fewer than 500 depth values where a 2^-b px lattice is >= 2 "
                         "depth units apart (targets too near for the depth unit, or too few pixels): no lattice "
                         "can be tested")
    return {"subpixel_bits": 10 if bits is None else bits}


def disparity_lattice(real: Sequence, model: SensorModel = D435, base_effects=(), *, seed: int = 0,
                      cache: dict | None = None, rois: Mapping | None = None,
                      rel_range: float = LATTICE_FB_RANGE) -> dict:
    """The disparity lattice of real captures and the f B [px m] it is found at (the fit of
    ``disparity_quantization``, with its details).

    Parameters
    ----------
    real, model, base_effects, seed, cache, rois
        As for :func:`fit_effect` (wall and board captures are used).
    rel_range : float
        Relative half-range of the f B search, in [0, 0.05] (0: the stated f B only).

    Returns
    -------
    dict
        ``subpixel_bits`` (int, or None when no lattice is visible) and ``cameras``: one entry per
        camera (captures with the same intrinsics, size, depth scale, baseline) with ``captures`` (ids),
        ``fb_px_m_stated`` (K[0, 0] * baseline_m), ``fb_px_m`` (where the lattice of ``subpixel_bits``
        is found; the stated one when no lattice), ``fb_rel`` (fb / stated - 1), ``score`` (fraction of
        the values on the lattice above chance: 1 = all, ~0 = none), ``values`` (depth values tested) and
        ``alias_rel``: over a narrow range of depths the lattice repeats every ~alias_rel in f B, so the
        f B is determined only modulo it (the value nearest the stated one is reported); captures at
        several distances remove the ambiguity.

    Raises
    ------
    ValueError
        No usable capture or no valid depth, bad input.
    """
    from ..analysis.capture_data import check_captures

    _check_model(model)
    real = check_captures(real, allow_empty=True)
    rel_range = _scalar(rel_range, "rel_range", 0.0, 0.05)
    rois = _check_rois(rois, real)
    use = usable_captures("disparity_quantization", real)
    if not use:
        raise ValueError("disparity_lattice needs wall or board captures; none given")
    base = _base_sims(use, model, list(base_effects or ()), int(seed), {} if cache is None else cache)
    hists = _lattice_hists(use, base, model, rois)
    if not hists:
        raise ValueError("disparity_lattice: no valid depth in the captures' interiors")
    bits, scans, _ = _lattice_scan(hists, rel_range)
    show = scans[bits] if bits is not None else scans[_LATTICE_BITS[-1]]
    by_key = {key: (ids, r) for ids, key, r in show}
    cams = []
    seen = set()
    for h in hists:
        if h[1] in seen:
            continue
        seen.add(h[1])
        ids = [x[0] for x in hists if x[1] == h[1]]
        g = next(c.geometry for c in use if c.id == ids[0])
        fb0 = float(g.fb_px_m)
        r = by_key.get(h[1], (None, None))[1]
        rel = r["rel"] if (r is not None and bits is not None) else 0.0
        cams.append({"captures": ids, "fb_px_m_stated": fb0, "fb_px_m": fb0 * (1.0 + rel), "fb_rel": rel,
                     "score": None if r is None else r["score"], "values": 0 if r is None else int(r["nr"]),
                     "alias_rel": None if r is None else r["alias"]})
    return {"subpixel_bits": bits, "cameras": cams}


# ---- depth_bias ----------------------------------------------------------------------------------
def _trim_mean(x, cut=0.1):
    from scipy.stats import trim_mean

    x = x[np.isfinite(x)]
    return float(trim_mean(x, cut)) if x.size else float("nan")


#: depth_bias: the captures' true depths must span this ratio (largest / smallest bin) for the scale and
#: the disparity offset to be told apart; below it the bias is one number per distance (a scale).
_BIAS_Z_RATIO = 1.5


def _fit_depth_bias(real, base, model, rois=None, **_):
    """Linear regression in disparity.

    The effect maps each disparity d (reference noise and base effects included) to
    d' = (d + offset_px) / scale, an affine map; trimmed means commute with it. Per capture and per
    quartile of the true disparity (interior pixels), the 10 %-trimmed mean of the real disparities is
    regressed on that of the base simulation: slope 1 / scale, intercept offset_px / scale.

    Scale and offset differ only in how the bias grows with distance ((scale - 1) z vs z^2 offset / (f B)),
    so they are told apart only by captures at different distances: when the bins' true depths span
    less than a factor :data:`_BIAS_Z_RATIO` (a single distance, or a few close ones), the bias is
    fitted as a scale alone (offset_px = 0: the regression through the origin), which reproduces the
    bias at the captures' distances but not its growth beyond them. Single frames: the trimmed means of
    one frame (nothing temporal is used). A capture whose target geometry was itself fitted to its
    depths (a plane fitted to a region of a frame) has no bias by construction: scale ~1.
    """
    xs, ys, ws, zs = [], [], [], []
    for c, b in zip(real, base):
        g = c.geometry
        m = _sample_mask(g, model, roi=_roi(rois, g))
        if m.sum() < 20:
            continue
        z, _, _, fb = _nominal(g, model)
        dt = fb / z[m]
        edges = np.quantile(dt, [0.0, 0.25, 0.5, 0.75, 1.0])
        dr, db = fb / _pixels(c, m), fb / _pixels(b, m)
        for i in range(4):
            sel = (dt >= edges[i]) & (dt <= edges[i + 1]) if i == 3 else (dt >= edges[i]) & (dt < edges[i + 1])
            if sel.sum() < 20:
                continue
            y, x = _trim_mean(dr[:, sel].ravel()), _trim_mean(db[:, sel].ravel())
            if math.isfinite(x) and math.isfinite(y) and x > 0 and y > 0:
                xs.append(x)
                ys.append(y)
                ws.append(float(sel.sum()))
                zs.append(float(np.median(fb / dt[sel])))
    if not xs:
        raise ValueError("depth_bias: no capture with >= 20 interior pixels with data")
    xs, ys, ws = np.array(xs), np.array(ys), np.array(ws)
    if len(xs) < 2 or np.ptp(xs) < 1e-6 or max(zs) / min(zs) < _BIAS_Z_RATIO:
        slope = float(np.sum(ws * xs * ys) / np.sum(ws * xs * xs))      # through the origin: a scale
        return {"scale": float(1.0 / slope), "offset_px": 0.0, "baseline_m": float(real[0].geometry.baseline_m)}
    X = np.column_stack([xs, np.ones_like(xs)]) * np.sqrt(ws)[:, None]
    slope, icpt = np.linalg.lstsq(X, ys * np.sqrt(ws), rcond=None)[0]
    scale = 1.0 / slope
    return {"scale": float(scale), "offset_px": float(icpt * scale), "baseline_m": float(real[0].geometry.baseline_m)}


# ---- invalid_band --------------------------------------------------------------------------------
def _fit_invalid_band(real, base, model, rois=None, **_):
    """Least-squares threshold on the missing fraction.

    Every hit pixel has c = u - f B / z_true (columns beyond its own disparity); the effect removes the
    pixels with c < margin. Over the pixels with c < 60 px of all captures, the margin minimising
    sum (a - 1)^2 over c < margin plus sum (a - a0)^2 over c >= margin (a, a0: the pixel's missing
    fraction over the frames in the real data and in the base simulation) is found by sorting c;
    the estimate is the middle of the gap between the two c values around the step. Single frames:
    the fractions are 0 or 1 (nothing temporal is used).
    """
    cs, a, a0 = [], [], []
    for c, b in zip(real, base):
        z, _, _, fb = _nominal(c.geometry, model)
        u = np.arange(c.geometry.width)[None, :]
        with np.errstate(invalid="ignore", divide="ignore"):
            cc = u - fb / z
        m = np.isfinite(cc) & (cc < 60.0)
        if _roi(rois, c.geometry) is not None:
            m &= _roi(rois, c.geometry)
        if not m.any():
            continue
        cs.append(cc[m])
        a.append(np.mean(~np.isfinite(_pixels(c, m)), axis=0))
        a0.append(np.mean(~np.isfinite(_pixels(b, m)), axis=0))
    if not cs:
        raise ValueError("invalid_band: no pixel near the left band")
    cs, a, a0 = (np.concatenate(x) for x in (cs, a, a0))
    order = np.argsort(cs, kind="stable")
    cs, a, a0 = cs[order], a[order], a0[order]
    left = np.concatenate([[0.0], np.cumsum((a - 1.0) ** 2)])        # pixels 0..k-1 in the band
    right = np.concatenate([np.cumsum(((a - a0) ** 2)[::-1])[::-1], [0.0]])
    k = int(np.argmin(left + right))
    if k == 0:
        margin = cs[0] - 0.5
    elif k == cs.size:
        margin = cs[-1] + 0.5
    else:
        margin = 0.5 * (cs[k - 1] + cs[k])
    return {"margin_px": float(margin)}


# ---- dropout -------------------------------------------------------------------------------------
def _bvn_same(t, rho):
    """P(X < t, Y < t) for a standard bivariate normal with correlation rho (Owen's T)."""
    from scipy.special import ndtr, owens_t

    rho = np.clip(rho, -0.999999, 0.999999)
    a = np.sqrt((1.0 - rho) / (1.0 + rho))
    return ndtr(t) - 2.0 * owens_t(t, a)


#: dropout: the bins' true depths must span this ratio for k_z, and -ln cos(theta) this range (0.1:
#: 0 to 25 deg) for k_theta, to be fitted; otherwise the slope is 0 (the level is fitted alone).
_DROPOUT_Z_RATIO = 1.5
_DROPOUT_X_RANGE = 0.1


def _fit_dropout(real, base, model, rois=None, **_):
    """Binomial maximum likelihood for P(z, theta), then the blob length from pairs of holes.

    1. Per capture and bin of z_true 3 % wide (interior pixels): n pixel-frames, y missing in the real
       data, a0 the missing fraction in the base simulation. P(missing) = 1 - (1 - p)(1 - a0) with
       p = sigmoid(b0 + k_z (z - 1) - k_theta ln cos theta); (b0, k_z, k_theta) by maximum likelihood
       (L-BFGS from a least-squares start on the logits). p_1m = sigmoid(b0).
    2. A pixel is dropped when a Gaussian field g < t = Phi^-1(p), so two pixels h apart are both
       dropped with probability Phi2(t, t; rho(h)), rho(h) = exp(-h^2 / (2 l^2)) (Owen's T). The
       observed fraction of pixel pairs (lags 1, 2, 3 along rows and columns) both missing, per bin,
       is matched by l (bounded 1-D search, least squares weighted by the binomial variance).

    What the captures determine: k_z only when the bins' true depths span a factor
    :data:`_DROPOUT_Z_RATIO`, k_theta only when -ln cos(theta) spans :data:`_DROPOUT_X_RANGE` (0 to
    25 deg); otherwise that slope is fixed at 0 and p_1m is the level seen at the captures' distances
    (or angles), not an extrapolation to 1 m. The coefficients are bounded by the factory's ranges
    (|k| <= 20, p_1m in [1e-9, 1 - 1e-9]): a capture with no hole at all (perfect separation) drives a
    slope to its bound, not to infinity. Single frames: counts over pixels; nothing is temporal (the
    holes of one frame cannot tell static holes from flickering ones: both are the effect's).
    """
    from scipy.optimize import minimize, minimize_scalar
    from scipy.special import expit, logit, ndtri

    rows = []      # z, x, n, y, a0, per bin
    pair_bins = []  # t-index, per lag: (n_pairs, both)
    per_cap = []
    for c, b in zip(real, base):
        g = c.geometry
        z, th, _, _ = _nominal(g, model)
        m = _interior(g, model, _roi(rois, g))
        if m.sum() < 50:
            continue
        zs = z[m]
        x = -np.log(np.cos(np.minimum(np.abs(th[m]), _THETA_DROPOUT_MAX)))
        miss_r = ~np.isfinite(c.depth_m)
        miss_b = ~np.isfinite(b.depth_m)
        # bins 3 % wide in z (P varies little inside one)
        _, binid = np.unique(np.floor(np.log(zs) / 0.03).astype(np.int64), return_inverse=True)
        binid = binid.ravel()
        nbin = int(binid.max()) + 1
        F = c.n_frames
        cnt = np.bincount(binid, minlength=nbin).astype(float)
        yr = np.bincount(binid, weights=miss_r[:, m].sum(axis=0), minlength=nbin)
        yb = np.bincount(binid, weights=miss_b[:, m].sum(axis=0), minlength=nbin)
        zsum = np.bincount(binid, weights=zs, minlength=nbin)
        xsum = np.bincount(binid, weights=x, minlength=nbin)
        keep = cnt >= 10
        newid = np.full(nbin, -1, dtype=np.int64)
        newid[keep] = np.arange(int(keep.sum())) + len(rows)
        for i in np.flatnonzero(keep):
            rows.append((zsum[i] / cnt[i], xsum[i] / cnt[i], cnt[i] * F, yr[i], yb[i] / (cnt[i] * F)))
        binmap = np.full(m.shape, -1, dtype=np.int64)
        binmap[m] = newid[binid]
        per_cap.append((miss_r, binmap))
    if not rows:
        raise ValueError("dropout: no capture with >= 50 interior pixels (bins of >= 10 pixels)")
    R = np.array(rows)
    zb, xb, nb, yb, a0 = R.T
    a0 = np.clip(a0, 0.0, 0.999)
    pobs = np.clip(yb / nb, 0.5 / nb, 1 - 0.5 / nb)
    p0 = np.clip(1.0 - (1.0 - pobs) / (1.0 - a0), 1e-4, 1 - 1e-4)
    X = np.column_stack([np.ones_like(zb), zb - 1.0, xb])
    free = np.array([True, zb.max() / zb.min() >= _DROPOUT_Z_RATIO and len(rows) >= 3,
                     np.ptp(xb) >= _DROPOUT_X_RANGE and len(rows) >= 3])
    if free.all():
        Xf = X
    else:
        Xf = X[:, free]
    w = np.sqrt(nb * p0 * (1 - p0))
    bf0 = np.linalg.lstsq(Xf * w[:, None], logit(p0) * w, rcond=None)[0]
    lim = np.array([logit(1 - 1e-9), 20.0, 20.0])[free]
    bf0 = np.clip(bf0, -lim, lim)

    def nll(bf):
        p = expit(Xf @ bf)
        P = np.clip(1.0 - (1.0 - p) * (1.0 - a0), 1e-12, 1 - 1e-12)
        return -float(np.sum(yb * np.log(P) + (nb - yb) * np.log1p(-P)))

    if free.all():
        res = minimize(nll, bf0, method="L-BFGS-B")
        bf = res.x if res.success or res.fun <= nll(bf0) else bf0
        if not np.all(np.abs(bf) <= lim):          # a separated design: keep the slopes in range
            res = minimize(nll, bf0, method="L-BFGS-B", bounds=list(zip(-lim, lim)))
            bf = res.x if res.success or res.fun <= nll(bf0) else bf0
    else:
        res = minimize(nll, bf0, method="L-BFGS-B", bounds=list(zip(-lim, lim)))
        bf = res.x if res.success or res.fun <= nll(bf0) else bf0
    beta = np.zeros(3)
    beta[free] = bf
    # 2. length from pairs of holes
    tfull = ndtri(np.clip(expit(X @ beta), 1e-9, 1 - 1e-9))       # threshold per bin (row of R)
    nbins = tfull.size
    obs, npairs, tt, lags = [], [], [], []
    for miss_r, binmap in per_cap:
        for h in (1, 2, 3):
            for axis in (1, 2):
                if axis == 2:
                    b1, b2 = binmap[:, :-h], binmap[:, h:]
                    m1, m2 = miss_r[:, :, :-h], miss_r[:, :, h:]
                else:
                    b1, b2 = binmap[:-h, :], binmap[h:, :]
                    m1, m2 = miss_r[:, :-h, :], miss_r[:, h:, :]
                ok = (b1 >= 0) & (b1 == b2)
                if not ok.any():
                    continue
                both = (m1 & m2)[:, ok].sum(axis=0)              # per pair over frames
                ids = b1[ok]
                cnt = np.bincount(ids, minlength=nbins) * miss_r.shape[0]
                bsum = np.bincount(ids, weights=both, minlength=nbins)
                sel = (cnt > 0) & np.isfinite(tfull)
                obs.append(bsum[sel] / cnt[sel])
                npairs.append(cnt[sel])
                tt.append(tfull[sel])
                lags.append(np.full(int(sel.sum()), float(h)))
    if not obs or sum(a.size for a in obs) == 0:
        raise ValueError("dropout: no pair of neighbouring interior pixels for the blob length")
    obs, npairs, tt, lags = (np.concatenate(a) for a in (obs, npairs, tt, lags))

    def loss(logl):
        ell = math.exp(logl)
        pred = _bvn_same(tt, np.exp(-lags ** 2 / (2 * ell * ell)))
        var = np.maximum(pred * (1 - pred), 1e-6) / npairs
        return float(np.sum((obs - pred) ** 2 / var))

    r = minimize_scalar(loss, bounds=(math.log(0.3), math.log(40.0)), method="bounded",
                        options={"xatol": 1e-4})
    return {"p_1m": float(expit(beta[0])), "k_z": float(beta[1]), "k_theta": float(beta[2]),
            "length_px": float(math.exp(r.x))}


# ---- lag covariances ------------------------------------------------------------------------------
def _lag_cov(x, mask, lags):
    """Mean of x_p x_{p+h} over frames and over pixel pairs h apart (rows and columns) both in mask and
    finite in x (F, H, W); returns (cov (len(lags),), n_pairs)."""
    xf = np.where(np.isfinite(x) & mask[None], x, 0.0)
    vf = (np.isfinite(x) & mask[None]).astype(np.float64)
    cov, npairs = [], []
    for h in lags:
        if h == 0:
            s, n = float(np.sum(xf * xf)), float(np.sum(vf))
        else:
            s = float(np.sum(xf[:, :, h:] * xf[:, :, :-h])) + float(np.sum(xf[:, h:, :] * xf[:, :-h, :]))
            n = float(np.sum(vf[:, :, h:] * vf[:, :, :-h])) + float(np.sum(vf[:, h:, :] * vf[:, :-h, :]))
        cov.append(s / n if n > 0 else np.nan)
        npairs.append(n)
    return np.array(cov), np.array(npairs)


def _fit_gaussian_cov(lags, excess, weights=None, lmin=0.3, lmax=60.0):
    """A exp(-h^2 / (2 l^2)) fitted to excess covariances (grid in l, A in closed form, A >= 0)."""
    lags = np.asarray(lags, dtype=float)
    w = np.ones_like(lags) if weights is None else np.asarray(weights, dtype=float)
    best = (np.inf, 0.0, 1.0)
    for ell in np.exp(np.linspace(math.log(lmin), math.log(lmax), 400)):
        rho = np.exp(-lags ** 2 / (2 * ell * ell))
        A = max(float(np.sum(w * excess * rho) / np.sum(w * rho * rho)), 0.0)
        sse = float(np.sum(w * (excess - A * rho) ** 2))
        if sse < best[0]:
            best = (sse, A, ell)
    return best[1], best[2]


# ---- correlated_noise -------------------------------------------------------------------------------
_CORR_LAGS = (0, 1, 2, 3, 4, 6, 8, 11)
#: Frames whose lag products the correlated-noise fit averages (the temporal mean uses all of them).
_CORR_FRAMES = 6


def _lag_cov_masked(x, w, lags):
    """:func:`_lag_cov` for x (F, H, W) that is 0 where the weights w (F, H, W) (0/1, float32) are 0."""
    cov, npairs = [], []
    for h in lags:
        if h == 0:
            s = float(np.einsum("ijk,ijk->", x, x, dtype=np.float64))
            n = float(np.einsum("ijk->", w, dtype=np.float64))
        else:
            s = float(np.einsum("ijk,ijk->", x[:, :, h:], x[:, :, :-h], dtype=np.float64))
            s += float(np.einsum("ijk,ijk->", x[:, h:, :], x[:, :-h, :], dtype=np.float64))
            n = float(np.einsum("ijk,ijk->", w[:, :, h:], w[:, :, :-h], dtype=np.float64))
            n += float(np.einsum("ijk,ijk->", w[:, h:, :], w[:, :-h, :], dtype=np.float64))
        cov.append(s / n if n > 0 else np.nan)
        npairs.append(n)
    return np.array(cov), np.array(npairs)


def _standardised_residuals(c, m, sig, nf):
    """(z - temporal mean) / sigma over the first nf frames at the mask's pixels, values more than 8
    sigma from the pixel's temporal median left out (0, weight 0) and the mean taken without them;
    returns (x, w) float32 (nf, H, W)."""
    z = c.depth_m
    med = np.median(z, axis=0)
    with np.errstate(invalid="ignore"):
        keep = (np.abs(z - med) <= 8.0 * sig) & m[None]
    n = keep.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(keep, z, 0.0).sum(axis=0) / np.maximum(n, 1)
    k = keep[:nf]
    x = np.where(k, (z[:nf] - mean) / sig, 0.0).astype(np.float32)
    return x, k.astype(np.float32)


def _spatial_standardised_residual(c, m, sig, fb):
    """One-frame counterpart of :func:`_standardised_residuals`: (z - z_plane) / sigma at the mask's
    pixels, z_plane = f B / (the frame's best disparity plane, :func:`_plane_residual`), values more
    than 8 sigma from the median left out (0, weight 0); returns (x, w) float32 (1, H, W) or None."""
    with np.errstate(divide="ignore", invalid="ignore"):
        pr = _plane_residual(fb / c.depth_m[0], m)
    if pr is None:
        return None
    z = c.depth_m[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (z - fb / pr[1]) / sig
        keep = m & np.isfinite(x)
        med = float(np.median(x[keep])) if keep.any() else 0.0
        keep &= np.abs(x - med) <= 8.0
    return (np.where(keep, x, 0.0).astype(np.float32)[None], keep.astype(np.float32)[None])


def _fit_correlated_noise(real, base, model, rois=None, **_):
    """Excess lag covariance of the per-frame residuals, in units of sigma_z.

    Per capture (interior pixels valid in every frame; captures up to 60 deg, below the truncation of
    the reference noise at grazing angles), x = (z - temporal mean) / sigma_z(z_true, theta), values
    more than 8 sigma from the pixel's temporal median (outliers) left out of the mean and the sums: the
    temporal mean removes everything static. The effect adds f g with g a unit field of correlation
    rho(h), so x's lag covariance (over the first 6 frames) grows by f^2 (1 - 1/F) rho(h). The
    real-minus-base covariances at lags 0-11 px (rows and columns), divided by (1 - 1/F) and pooled
    over captures by pair counts, give f^2 and l (:func:`_fit_gaussian_cov`).

    A capture of one frame has no temporal mean: x is its frame's residual about the target's best
    plane (:func:`_spatial_standardised_residual`), whose lag covariance grows by f^2 rho(h), and lag 0
    is left out of the fit when any capture has one frame (extra white noise, disparity_noise or a
    refitted axial sigma, adds there only). Assumption: one frame cannot tell a field drawn afresh
    every frame from a static one (static_pattern) or from a static share of it, so on single frames
    the whole excess spatial correlation is attributed to this effect (the temporal share is not
    identifiable; it is 1 here).
    """
    num, den, nF = np.zeros(len(_CORR_LAGS)), np.zeros(len(_CORR_LAGS)), 0
    single = False
    for c, b in zip(real, base):
        g = c.geometry
        z, th, _, fb = _nominal(g, model)
        if np.nanmax(th) > math.radians(60.5):
            continue
        m = (_interior(g, model, _roi(rois, g)) & np.all(np.isfinite(c.depth_m), axis=0)
             & np.all(np.isfinite(b.depth_m), axis=0))
        if m.sum() < 100:
            continue
        sig = np.where(m, _axial_sigma_unchecked(np.where(m, z, 1.0), np.where(m, th, 0.0), model), 1.0)
        if c.n_frames >= 2:
            nf = min(c.n_frames, _CORR_FRAMES)
            xr, wr = _standardised_residuals(c, m, sig, nf)
            xb, wb = _standardised_residuals(b, m, sig, nf)
            gain = 1.0 - 1.0 / c.n_frames
        else:
            rr = _spatial_standardised_residual(c, m, sig, fb)
            rb = _spatial_standardised_residual(b, m, sig, fb)
            if rr is None or rb is None:
                continue
            (xr, wr), (xb, wb) = rr, rb
            gain, single = 1.0, True
        cr, n = _lag_cov_masked(xr, wr, _CORR_LAGS)
        cb, _ = _lag_cov_masked(xb, wb, _CORR_LAGS)
        ok = np.isfinite(cr) & np.isfinite(cb)
        num[ok] += n[ok] * (cr[ok] - cb[ok]) / gain
        den[ok] += n[ok]
        nF += 1
    if not nF or not (den > 0).all():
        raise ValueError("correlated_noise: needs captures at <= 60 deg with >= 100 interior pixels valid in "
                         "every frame")
    lags, exc = np.array(_CORR_LAGS), num / den
    if single:
        lags, exc = lags[1:], exc[1:]
    A, ell = _fit_gaussian_cov(lags, exc)
    return {"sigma_z_fraction": float(math.sqrt(max(A, 1e-8))), "length_px": float(ell)}


# ---- static_pattern ---------------------------------------------------------------------------------
_STATIC_LAGS = (0, 1, 2, 3, 4, 6, 8, 11, 15, 20, 26)


def _detrended_mean_residual(c, m, fb, dtrue):
    """Temporal mean of the disparity residual, minus its best plane a + b u + c v over the mask."""
    d = fb / c.depth_m
    v = np.isfinite(d)
    n = np.sum(v, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n >= max(2, c.n_frames // 2), np.where(v, d, 0.0).sum(axis=0) / n, np.nan)
    r = mean - dtrue
    ok = m & np.isfinite(r)
    vv, uu = np.nonzero(ok)
    if vv.size < 50:
        return None
    A = np.column_stack([np.ones(vv.size), uu, vv]).astype(np.float64)
    coef = np.linalg.lstsq(A, r[ok], rcond=None)[0]
    out = np.full(r.shape, np.nan)
    out[ok] = r[ok] - A @ coef
    return out


def _single_frame_residual(c, m, fb):
    """One frame's disparity minus its best plane (:func:`_plane_residual`), values more than 8 robust
    sigmas from 0 (outliers) set to NaN; None when fewer than 50 pixels have data."""
    with np.errstate(divide="ignore", invalid="ignore"):
        pr = _plane_residual(fb / c.depth_m[0], m)
    if pr is None:
        return None
    r = pr[0]
    ok = np.isfinite(r)
    s = 1.4826 * float(np.median(np.abs(r[ok])))
    if s > 0:
        r = np.where(np.abs(r) <= 8.0 * s, r, np.nan)
    return r


def _fit_static_pattern(real, base, model, rois=None, **_):
    """Excess lag covariance of the temporal-mean disparity residual.

    Per capture (interior pixels): the temporal mean of d = f B / z minus the true disparity, minus its
    best plane in (u, v) (a depth bias maps a plane's affine disparity to another affine disparity, so
    it leaves nothing). The pattern adds sigma_px^2 rho(h) to its lag covariance; the base simulation's
    (noise / F) is subtracted. Captures are pooled with weights n / (base variance + current estimate)^2,
    then sigma_px^2 and the length are fitted (:func:`_fit_gaussian_cov`). The pattern's realisation is
    not recovered (its ``seed`` is returned as 0).

    A capture of one frame: the "temporal mean" is its frame (the residual about its best plane fitted
    robustly, values beyond 8 robust sigmas left out, :func:`_single_frame_residual`), and lag 0 is left
    out of the fit when any capture has one frame (white noise adds there: the base's is subtracted,
    but any extra white noise of the real data would read as a pattern). Assumption: one frame cannot
    tell a static pattern from a field drawn afresh every frame (correlated_noise): on single frames
    the whole excess spatial correlation of the frame is attributed to the static pattern.
    """
    rows = []
    single = False
    for c, b in zip(real, base):
        g = c.geometry
        z, _, _, fb = _nominal(g, model)
        m = _interior(g, model, _roi(rois, g))
        with np.errstate(divide="ignore", invalid="ignore"):
            dtrue = fb / z
        if c.n_frames >= 2:
            rr = _detrended_mean_residual(c, m, fb, dtrue)
            rb = _detrended_mean_residual(b, m, fb, dtrue)
        else:
            rr = _single_frame_residual(c, m, fb)
            rb = _single_frame_residual(b, m, fb)
        if rr is None or rb is None:
            continue
        single |= c.n_frames == 1
        cr, n = _lag_cov(rr[None], m, _STATIC_LAGS)
        cb, _ = _lag_cov(rb[None], m, _STATIC_LAGS)
        if not (np.all(np.isfinite(cr)) and np.all(np.isfinite(cb))):
            continue
        rows.append((cr - cb, n, cb[0]))
    if not rows:
        raise ValueError("static_pattern: no capture with >= 50 interior pixels with data (in half its frames)")
    lags = np.array(_STATIC_LAGS)
    use = slice(1, None) if single else slice(None)
    A = 0.0
    ell = 5.0
    for _ in range(3):
        num = sum(n * e / (v0 + A) ** 2 for e, n, v0 in rows)
        den = sum(n / (v0 + A) ** 2 for e, n, v0 in rows)
        A, ell = _fit_gaussian_cov(lags[use], (num / den)[use], lmin=0.5, lmax=80.0)
    return {"sigma_px": float(math.sqrt(max(A, 1e-10))), "length_px": float(ell), "seed": 0}


# ---- edges: flying_pixels and edge_fattening --------------------------------------------------------
def _edge_setup(g, model):
    """Per side (left, right): the side's region mask restricted to rows that cross the board's nominal
    edge, the board/background nominal masks, fg disparity of the board's plane, bg disparity."""
    from ..analysis.capture_data import REGION_EDGE_LEFT, REGION_EDGE_RIGHT

    key = ("fit_edges", float(model.sigma_L), float(model.sigma_R))
    if key in g._cache:
        return g._cache[key]
    z, th, reg, fb = _nominal(g, model)
    zp = g.plane_depth()
    with np.errstate(divide="ignore", invalid="ignore"):
        dfg = fb / zp
    dbg = fb / g.background_m
    board = np.isfinite(z) & (z < g.background_m - 1e-9)
    s, _ = g.board_coordinates()
    out = []
    for code, sigma, sign in ((REGION_EDGE_LEFT, model.sigma_L, -1.0), (REGION_EDGE_RIGHT, model.sigma_R, 1.0)):
        S = reg == code
        rows = (S & board).any(axis=1) & (S & ~board).any(axis=1)
        S = S & rows[:, None]
        if S.sum() == 0:
            out.append(None)
            continue
        # lateral sigma in px: |ds/du| [m/px] at the edge pixels
        with np.errstate(invalid="ignore"):
            dsdu = np.abs(np.gradient(s, axis=1))
        edge_px = S & board
        mpp = float(np.nanmedian(dsdu[edge_px])) if edge_px.any() else float("nan")
        sig_px = sigma / mpp if mpp > 0 else float("nan")
        out.append({"S": S, "rows": int(rows.sum()), "board": board, "dfg": dfg, "dbg": dbg,
                    "dfg_edge": float(np.nanmedian(dfg[S & board])), "sig_px": sig_px})
    g._cache[key] = out
    return out


def _edge_sides(g, model, roi=None):
    """:func:`_edge_setup` restricted to a region of interest (the side's pixels in it, rows that still
    cross the edge inside it)."""
    sides = _edge_setup(g, model)
    if roi is None:
        return sides
    out = []
    for side in sides:
        if side is None:
            out.append(None)
            continue
        S = side["S"] & roi
        rows = (S & side["board"]).any(axis=1) & (S & ~side["board"]).any(axis=1)
        S = S & rows[:, None]
        out.append({**side, "S": S, "rows": int(rows.sum())} if S.any() else None)
    return out


def _disp_sigma(z, th, model, depth_scale, fb):
    """Disparity noise [px] of the reference at depth z with the unit rounding: sqrt(s_d^2 + q^2 / 12)."""
    s = _axial_sigma_unchecked(np.asarray(z, dtype=float), np.asarray(th, dtype=float), model)
    q = fb * depth_scale / np.asarray(z, dtype=float) ** 2
    return np.sqrt((s * fb / np.asarray(z, dtype=float) ** 2) ** 2 + q * q / 12.0)


_PAIR_LAGS = tuple(range(1, 13))


def _flying_stats(c, side, lo_fg, lo_bg):
    """Intermediate pixels of a side: disparity in (d_bg + lo_bg, d_fg - lo_fg); their count and the
    histogram of distances between two of them in the same row and frame."""
    d = c.geometry.fb_px_m / c.depth_m
    lo = side["dbg"] + lo_bg
    hi = side["dfg"] - lo_fg
    with np.errstate(invalid="ignore"):
        M = np.isfinite(d) & (d > lo) & (d < hi) & side["S"][None]
    n = float(M.sum())
    hist = np.array([float(np.sum(M[:, :, h:] & M[:, :, :-h])) for h in _PAIR_LAGS])
    return n, hist


def _levels_from_base(b, model, roi=None):
    """Offsets and robust spreads [px] of the board's and the background's disparities in the base
    simulation relative to the nominal geometry (base effects such as a depth bias move the levels,
    a static pattern widens them): (m_fg, s_fg, m_bg, s_bg)."""
    from ..analysis.capture_data import REGION_BACKGROUND

    g = b.geometry
    z, th, reg, fb = _nominal(g, model)
    d = fb / b.depth_m
    out = []
    bgm = reg == REGION_BACKGROUND if roi is None else (reg == REGION_BACKGROUND) & roi
    for mask, level in ((_interior(g, model, roi), fb / z), (bgm, fb / g.background_m)):
        r = (d[:, mask] - (level[mask] if np.ndim(level) else level)).ravel()
        r = r[np.isfinite(r)]
        if r.size < 20:
            out += [0.0, 0.0]
            continue
        med = float(np.median(r))
        out += [med, 1.4826 * float(np.median(np.abs(r - med)))]
    return tuple(out)


def _fit_flying_pixels(real, base, model, rois=None, **_):
    """Counts of intermediate depths at the board's left and right edges, and their spacing.

    In the rows crossing a vertical edge (edge regions), a pixel is intermediate when its disparity
    lies more than 5 noise sigmas inside the board's and the background's levels (the nominal
    disparities shifted by the base simulation's median offsets; sigma the larger of the reference's
    and the base's robust spread). A straight edge has n = 2 (band_px + 1) band pixels per row, each
    flying with probability p, then intermediate with probability q = (d_fg - d_bg - margins) /
    (d_fg - d_bg) (lambda uniform), and valid with the base's valid fraction v of the region. band_px:
    the excess (real - base) histogram of distances between intermediate pixels of the same row and
    side is matched (least squares on the normalised histogram) by the distance distribution of two
    slots among n, P(h) ~ n - h; then p = excess count / (q v n F rows) summed over captures and sides.
    Single frames: the same counts with F = 1 (each frame's band is drawn afresh, so one frame is a
    sample like any other; the precision falls as 1 / sqrt(frames)).
    """
    n_exc, h_exc, denom_unit = 0.0, np.zeros(len(_PAIR_LAGS)), []
    for c, b in zip(real, base):
        g = c.geometry
        sides = _edge_sides(g, model, _roi(rois, g))
        z, th, _, fb = _nominal(g, model)
        m_fg, s_fg, m_bg, s_bg = _levels_from_base(b, model, _roi(rois, g))
        for side in sides:
            if side is None:
                continue
            zf = fb / side["dfg_edge"]
            thf = float(np.nanmedian(th[side["S"] & side["board"]]))
            sig_fg = max(float(_disp_sigma(zf, thf, model, g.depth_scale, fb)), s_fg)
            sig_bg = max(float(_disp_sigma(g.background_m, 0.0, model, g.depth_scale, fb)), s_bg)
            lo_fg, lo_bg = 5.0 * sig_fg - m_fg, 5.0 * sig_bg + m_bg
            nr, hr = _flying_stats(c, side, lo_fg, lo_bg)
            nb, hb = _flying_stats(b, side, lo_fg, lo_bg)
            n_exc += nr - nb
            h_exc += hr - hb
            delta = (side["dfg_edge"] + m_fg) - (side["dbg"] + m_bg)
            q = max(0.0, (delta - 5.0 * sig_fg - 5.0 * sig_bg) / delta)
            v = float(np.mean(np.isfinite(b.depth_m[:, side["S"]])))
            denom_unit.append(q * v * c.n_frames * side["rows"])
    if not denom_unit:
        raise ValueError("flying_pixels: needs boards before a background with rows crossing their edges")
    h = np.clip(h_exc, 0.0, None)
    if h.sum() <= 0 or n_exc <= 0:
        return {"fraction": 0.0, "band_px": 0}
    hn = h / h.sum()
    lags = np.array(_PAIR_LAGS, dtype=float)
    best = (np.inf, 0)
    for band in range(0, 6):
        n = 2 * (band + 1)
        pred = np.clip(n - lags, 0.0, None)
        pred /= pred.sum()
        sse = float(np.sum((hn - pred) ** 2))
        if sse < best[0]:
            best = (sse, band)
    band = best[1]
    n = 2 * (band + 1)
    frac = n_exc / (n * float(np.sum(denom_unit)))
    return {"fraction": float(min(max(frac, 0.0), 1.0)), "band_px": int(band)}


def _background_columns(c, side):
    """Sum over the side's columns of the fraction of valid pixels reading background (rows of the side,
    all frames): the expected number of background columns in the side's region."""
    d = c.geometry.fb_px_m / c.depth_m
    S = side["S"]
    mid = 0.5 * (side["dfg"] + side["dbg"])
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & S[None]
        bg = valid & (d < mid)
    nv = valid.sum(axis=(0, 1)).astype(float)
    nb = bg.sum(axis=(0, 1)).astype(float)
    cols = nv > 0
    return float(np.sum(nb[cols] / nv[cols]))


def _expected_background_columns(g, side, model, left: bool):
    """:func:`_background_columns` expected under the reference's edge shifts alone: a pixel of the
    side's region is background with probability P(shift > s + w/2) (left edge) or P(shift < s - w/2)
    (right edge), s its coordinate along the board, shift ~ N(0, sigma_L^2) or N(0, sigma_R^2)."""
    from scipy.special import ndtr

    S = side["S"]
    s, _ = g.board_coordinates()
    w2 = g.target["width_m"] / 2.0
    with np.errstate(invalid="ignore"):
        if left:
            p = 1.0 - ndtr((s + w2) / model.sigma_L)
        else:
            p = ndtr((s - w2) / model.sigma_R)
    p = np.where(S & np.isfinite(p), p, 0.0)
    n = S.sum(axis=0).astype(float)
    cols = n > 0
    return float(np.sum(p.sum(axis=0)[cols] / n[cols]))


_HEDGE_ROWS = 10


def _horizontal_edge_zones(g, model):
    """Columns of the board away from its left/right edge regions, and for each its top and bottom edge
    rows (nominal): list of (column, first row, last row) zones of 2 * _HEDGE_ROWS rows straddling a
    horizontal board edge with background on the other side (cached)."""
    from ..analysis.capture_data import REGION_EDGE_LEFT, REGION_EDGE_RIGHT, REGION_INTERIOR

    key = ("fit_hedges", float(model.sigma_L), float(model.sigma_R))
    if key in g._cache:
        return g._cache[key]
    z, _, reg, _ = _nominal(g, model)
    board = np.isfinite(z) & (z < g.background_m - 1e-9)
    bgm = np.isfinite(z) & ~board
    cols = np.flatnonzero((reg == REGION_INTERIOR).any(axis=0) & ~((reg == REGION_EDGE_LEFT)
                                                                 | (reg == REGION_EDGE_RIGHT)).any(axis=0))
    K = _HEDGE_ROWS
    H = g.height
    zones = []
    for c in cols:
        rows = np.flatnonzero(board[:, c])
        if rows.size == 0:
            continue
        top, bot = int(rows[0]), int(rows[-1])
        if top - K >= 0 and bgm[top - K:top, c].all():
            zones.append((int(c), top - K, top + K))
        if bot + K < H and bgm[bot + 1:bot + K + 1, c].all():
            zones.append((int(c), bot - K + 1, bot + K + 1))
    g._cache[key] = zones
    return zones


def _horizontal_background_rows(c, zones, dmid):
    """Mean over zones of the number of rows reading background (valid pixels, fraction per row)."""
    d = c.geometry.fb_px_m / c.depth_m
    tot = []
    for col, r0, r1 in zones:
        seg = d[:, r0:r1, col]
        with np.errstate(invalid="ignore"):
            v = np.isfinite(seg)
            bg = v & (seg < dmid[r0:r1, col])
        nv = v.sum(axis=0)
        ok = nv > 0
        tot.append(float(np.sum(bg.sum(axis=0)[ok] / nv[ok])))
    return float(np.mean(tot)) if tot else float("nan")


def _fit_edge_fattening(real, base, model, rois=None, **_):
    """The board's edges move outwards by the fattening width.

    Two estimates, combined by their inverse variances:

    * top and bottom edges (columns away from the left/right edge regions, 2 x 10 rows straddling the
      edge): the number of rows reading background (fraction of valid pixels closer to the background
      than to the board, summed over the rows) in the base simulation minus in the real data, R,
      converted to a width through the forward model's own Chebyshev levels on the nominal edge
      (R(w) = mean count of pixels at level <= floor(w) plus (w - floor(w)) times those at the next
      level: a slanted edge loses more rows than w). The reference does not move these edges, so this
      is precise (variance ~0.25 / zones, floored at 0.05^2 px^2 per capture);
    * left and right edges (their regions' rows crossing the edge): the number of background columns,
      sum over columns of the fraction of valid pixels reading background, against its expectation
      under the reference's edge shifts alone (computed from the geometry, N(0, sigma_L^2) and
      N(0, sigma_R^2) along the board: the simulation's own shifts would add their noise). The shifts
      make this noisy: variance (lateral sigma in px)^2 / frames per edge.

    Both are robust to missing pixels (fractions of valid pixels) and to flying pixels (symmetric).
    Single frames: the same with F = 1; the left/right estimates then carry the full lateral noise of
    one frame's edge shift (their weight falls with it), the top/bottom ones stay precise.
    """
    num, den = 0.0, 0.0
    for c, b in zip(real, base):
        g = c.geometry
        zones = _horizontal_edge_zones(g, model)
        roi = _roi(rois, g)
        if roi is not None:
            zones = [(col, r0, r1) for col, r0, r1 in zones if roi[r0:r1, col].all()]
        if len(zones) >= 5:
            z, _, _, fb = _nominal(g, model)
            zp = g.plane_depth()
            with np.errstate(divide="ignore", invalid="ignore"):
                dmid = 0.5 * (fb / zp + fb / g.background_m)
            est = _horizontal_background_rows(b, zones, dmid) - _horizontal_background_rows(c, zones, dmid)
            if math.isfinite(est):
                # rows fattened per zone as a function of the width, from the forward model's own levels
                # (a slanted edge fattens by more rows than the width: Chebyshev distance)
                level, _ = _fattening_levels(_true_disparity(z, fb), _HEDGE_ROWS - 1)
                cnt = np.zeros(_HEDGE_ROWS + 1)
                for col, r0, r1 in zones:
                    cnt += np.bincount(level[r0:r1, col], minlength=_HEDGE_ROWS + 1)[:_HEDGE_ROWS + 1]
                cnt = cnt[1:] / len(zones)                   # mean count at level 1, 2, ...
                cum = np.concatenate([[0.0], np.cumsum(cnt)])  # R(w) at w = 0, 1, 2, ...
                j = int(np.searchsorted(cum, est, side="right")) - 1
                if est <= 0:
                    w_h, slope = 0.0, max(cnt[0], 1e-3)
                elif j >= len(cnt):
                    w_h, slope = float(len(cnt)), max(cnt[-1], 1e-3)
                else:
                    slope = max(cnt[j], 1e-3)
                    w_h = j + (est - cum[j]) / slope
                var = max(0.25 / (len(zones) * c.n_frames), 0.05 ** 2) / slope ** 2
                num += w_h / var
                den += 1.0 / var
        for left, side in zip((True, False), _edge_sides(g, model, roi)):
            if side is None or not math.isfinite(side["sig_px"]):
                continue
            est = _expected_background_columns(g, side, model, left) - _background_columns(c, side)
            var = max(side["sig_px"], 0.5) ** 2 / c.n_frames
            num += est / var
            den += 1.0 / var
    if den == 0:
        raise ValueError("edge_fattening: needs boards before a background with visible edges")
    return {"width_px": float(max(num / den, 0.0))}


# ---- outliers ----------------------------------------------------------------------------------------
def _fit_outliers(real, base, model, rois=None, **_):
    """Maximum likelihood on the tails of the disparity residual.

    Per capture (interior, <= 60 deg) and pixel i: r = d - d_true minus the base simulation's mean
    residual as a linear function of d_true (a depth bias among the base effects shifts the core);
    the core scale is sigma_i = k s_i, s_i the reference's disparity noise at the pixel
    (sigma_z f B / z^2 with the unit rounding) and k the larger of 1.4826 MAD(r / s_i) over the
    capture (robust: the core, not the outliers) and the base's RMS of r / s_i (a disparity lattice can
    make the MAD 0); tails are |r| > T_i = max(10 k, 1.5 q) s_i, q the base's 99.99 % quantile of
    |r / s_i|: the core has nothing there. An outlier's error X ~ N(0, S_i^2), S_i^2 = s^2 + sigma_i^2,
    is seen as a tail with probability Q_i = P(|X| > T_i, X > -(d_i - d_min)) (below, d + X is beyond
    the uint16 range: no data, not seen). s maximises the likelihood of the tail residuals
    conditional on being seen (1-D bounded search); then fraction = (real tails - base tails) /
    sum_i Q_i n_i, n_i the pixel's valid frames in the base simulation. Single frames: the same counts
    over pixels (nothing temporal is used); fewer than 5 tail values in all: fraction 1e-6 (none).
    """
    from scipy.optimize import minimize_scalar
    from scipy.special import ndtr

    caps = []
    for c, b in zip(real, base):
        g = c.geometry
        z, th, _, fb = _nominal(g, model)
        if np.nanmax(th) > math.radians(60.5):
            continue
        m = _sample_mask(g, model, 2 * _MAX_SAMPLE_PX, _roi(rois, g))
        if m.sum() < 100:
            continue
        zt = z[m]
        dt = fb / zt
        sd = _disp_sigma(zt, th[m], model, g.depth_scale, fb)
        rr = fb / _pixels(c, m) - dt
        rb = fb / _pixels(b, m) - dt
        okb = np.isfinite(rb)
        if okb.sum() < 100 or np.isfinite(rr).sum() < 100:
            continue
        # the base's mean residual, linear in d_true
        X = np.column_stack([np.ones(int(okb.sum())), np.broadcast_to(dt, rb.shape)[okb]])
        coef = np.linalg.lstsq(X, rb[okb], rcond=None)[0]
        centre = coef[0] + coef[1] * dt
        rr, rb = rr - centre, rb - centre
        fin = (rr / sd)[np.isfinite(rr)]
        sub = fin if fin.size <= 300_000 else fin[:: fin.size // 300_000 + 1]
        k = 1.4826 * float(np.median(np.abs(sub - np.median(sub))))
        fbs = np.abs(rb / sd)[okb]
        kb = float(np.sqrt(np.mean(fbs ** 2)))                          # base core (lattices too)
        kq = float(np.quantile(fbs, 0.9999))                            # base core's extent
        sc = max(k, kb) * sd                                            # (N,)
        T = max(10.0 * max(k, kb), 1.5 * kq) * sd
        with np.errstate(invalid="ignore"):
            tmask = np.isfinite(rr) & (np.abs(rr) > T)
            nb_tail = float(np.sum(okb & (np.abs(rb) > T)))
        pix = np.broadcast_to(np.arange(rr.shape[1]), rr.shape)
        d_lim = dt - fb / (65535 * g.depth_scale)                        # X below -d_lim: no data
        caps.append(dict(tail=rr[tmask], tpix=pix[tmask], sc=sc, T=T, dlim=d_lim, nb=nb_tail,
                         nvalid=okb.sum(axis=0).astype(float)))
    if not caps:
        raise ValueError("outliers: needs captures at <= 60 deg with >= 100 interior pixels with data")
    if sum(cp["tail"].size for cp in caps) < 5:
        return {"fraction": 1e-6, "sigma_px": 1.0}

    def seen(s, sc, T, dlim):
        S = np.sqrt(s * s + sc * sc)
        up = ndtr(-T / S)
        return up + np.maximum(up - ndtr(-dlim / S), 0.0), S

    def nll(logs):
        s = math.exp(logs)
        ll = 0.0
        for cp in caps:
            t = cp["tpix"]
            Q, S = seen(s, cp["sc"][t], cp["T"][t], cp["dlim"][t])
            ll += float(np.sum(-0.5 * (cp["tail"] / S) ** 2 - np.log(S) - np.log(np.maximum(Q, 1e-300))))
        return -ll

    r = minimize_scalar(nll, bounds=(math.log(0.01), math.log(50.0)), method="bounded", options={"xatol": 1e-5})
    s = math.exp(r.x)
    num = sum(cp["tail"].size - cp["nb"] for cp in caps)
    den = sum(float(np.sum(seen(s, cp["sc"], cp["T"], cp["dlim"])[0] * cp["nvalid"])) for cp in caps)
    return {"fraction": float(min(max(num / den, 1e-6), 0.5)), "sigma_px": float(s)}


# ---- axial_refit -----------------------------------------------------------------------------------
#: Scale of the coefficients of axial_refit's second base simulation (inside the quieter units' range,
#: where the base effects' variance is interpolated rather than extrapolated).
_AXIAL_SCALE2 = 0.6


#: axial_refit: the bins' mean true depths must span this ratio for c0, c1, c2 to be fitted separately,
#: and the share of the angle term in the reference sigma must vary by this much between bins for
#: c_theta to be told from them.
_AXIAL_Z_RATIO = 2.0
_AXIAL_ANGLE_SHARE = 0.3


def _pixel_variances(c, m, sref, fb, zs):
    """Per-pixel variance estimates of z [m^2] at the mask's pixels and the number of values behind each
    (N,): the robust temporal variance (:func:`_robust_temporal_var`) with >= 2 frames; with one frame,
    the squared residual about the frame's best disparity plane (z - f B / plane, :func:`_plane_residual`),
    NaN beyond 6 robust sigmas (:func:`_robust_mean_square`); zs (N,) the pixels' true depths [m].
    Returns (v (N,), degrees of freedom per value)."""
    if c.n_frames >= 2:
        v, _ = _robust_temporal_var(_pixels(c, m), sref, _temporal_min_count(c.n_frames))
        return v, c.n_frames - 1
    sc = np.ones(m.shape)
    sc[m] = sref * fb / np.maximum(zs, 1e-6) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        pr = _plane_residual(fb / c.depth_m[0], m, sc)
    if pr is None:
        return np.full(int(m.sum()), np.nan), 1
    with np.errstate(divide="ignore", invalid="ignore"):
        r = c.depth_m[0][m] - fb / pr[1][m]
    _, keep = _robust_mean_square(r, sref)
    return np.where(keep, r * r, np.nan), 1


def _fit_axial_refit(real, base, model, base_effects=(), seed=0, cache=None, rois=None, **_):
    """Least squares of the temporal variance on the paper's four terms.

    Per capture and quartile of z_true (interior pixels): v the mean robust per-pixel temporal variance
    of z (:func:`_robust_temporal_var`) in the real data and in the base simulation, and the mean
    reference sigma_ref^2. The base effects act on the variance as v = f sigma^2 + e (e: depth-unit
    rounding, added noise; f: a scale, e.g. a depth bias's); with base effects, a second base
    simulation with every coefficient x 0.6 (common random numbers) gives f and e per bin; without,
    f = 1 and e = depth_scale^2 / 12 (the rounding's variance, Sheppard: exact for sigma >~ 0.6 units;
    the base simulation's own sampling noise stays out). Then y = (v_real - e) / f estimates sigma_new^2. The model of y
    is the bin's mean of sigma(c)^2 = (c0 + c1 z + c2 z^2 + c_theta z^1.5 theta / (pi/2 - theta)^2)^2
    over its pixels; residuals (model - y) / sd(y), sd(y)^2 ~ 2 (v_real^2 + v_base^2) / (n (F - 1)),
    non-negative coefficients (bounded least squares started from the non-negative linear fit of
    sqrt(y)). Bins whose sigma exceeds 15 % of z are left out (the reference noise is truncated at
    z <= 0 there).

    Single frames: a capture of one frame has no temporal variance; the squared residual of its frame
    about the target's best plane (:func:`_pixel_variances`) stands in, pixel by pixel (the paper's own
    plane-fit sigma). Assumption: the spatial spread of one frame is all per-frame noise; a static
    pattern or a correlated field in it (not separable from one frame) is fitted into sigma too.

    What the captures determine: the four coefficients only when the bins span distances (mean true
    depths a factor >= :data:`_AXIAL_Z_RATIO` apart) and angles (the angle term's share of the
    reference sigma differs by >= :data:`_AXIAL_ANGLE_SHARE` between bins, e.g. 0 and >= 30 deg). If
    not, fewer parameters are fitted and the others follow the paper's shape: distances but no angles:
    c0, c1, c2 free and c_theta = the paper's times the ratio of the fitted to the paper's distance
    term at the bins' median depth; angles but one distance range: the distance term is the paper's
    times one factor a, c_theta free; neither: every coefficient is the paper's times one factor a
    (the noise's magnitude at the captures' distances and angles).
    """
    from scipy.optimize import least_squares, nnls

    base2 = None
    if base_effects:
        model2 = replace(model, axial_coefficients=tuple(_AXIAL_SCALE2 * float(c) for c in model.axial_coefficients))
        base2 = _base_sims(real, model2, base_effects, seed, {} if cache is None else cache)
    bins, ys, sds, zmean, share = [], [], [], [], []
    ct = model.theta_max_rad
    cref = np.array([float(v) for v in model.axial_coefficients])
    for k, (c, b) in enumerate(zip(real, base)):
        g = c.geometry
        z, th, _, fb = _nominal(g, model)
        m = _sample_mask(g, model, roi=_roi(rois, g))
        if m.sum() < 50:
            continue
        zs, ts = z[m], np.minimum(np.abs(th[m]), ct)
        sref = _axial_sigma_unchecked(zs, ts, model)
        vr, dof = _pixel_variances(c, m, sref, fb, zs)
        vb, _ = _pixel_variances(b, m, sref, fb, zs)
        vb2 = _pixel_variances(base2[k], m, _AXIAL_SCALE2 * sref, fb, zs)[0] if base2 is not None else None
        edges = np.quantile(zs, [0.0, 0.25, 0.5, 0.75, 1.0])
        for i in range(4):
            sel = (zs >= edges[i]) & ((zs <= edges[i + 1]) if i == 3 else (zs < edges[i + 1]))
            sel &= np.isfinite(vr) & np.isfinite(vb)
            if vb2 is not None:
                sel &= np.isfinite(vb2)
            if sel.sum() < 20:
                continue
            s2 = float(np.mean(sref[sel] ** 2))
            v_r, v_b = float(np.mean(vr[sel])), float(np.mean(vb[sel]))
            if vb2 is not None:
                f = (float(np.mean(vb2[sel])) - v_b) / ((_AXIAL_SCALE2 ** 2 - 1.0) * s2)
                if not f > 0.05:
                    continue
                e = v_b - f * s2
            else:
                f, e = 1.0, g.depth_scale ** 2 / 12.0            # only the rounding (Sheppard)
            y2 = (v_r - e) / f
            zz, tt = zs[sel], ts[sel]
            if (y2 <= 0 or math.sqrt(y2) > 0.15 * float(np.mean(zz))
                    or float(np.max(sref[sel])) > 0.15 * float(np.min(zz))):
                continue
            gth = zz * np.sqrt(zz) * tt / (0.5 * np.pi - tt) ** 2
            bins.append(np.column_stack([np.ones_like(zz), zz, zz * zz, gth]))
            ys.append(y2)
            sds.append(math.sqrt(2.0 * (v_r ** 2 + v_b ** 2) / (sel.sum() * max(dof, 1))) / f)
            zmean.append(float(np.mean(zz)))
            share.append(float(np.mean(cref[3] * gth / sref[sel])))
    if not ys:
        raise ValueError("axial_refit: no bin of >= 20 interior pixels with a usable variance (>= 2 values per "
                         "pixel over the frames or one frame's plane residual; sigma < 15 % of z)")
    y, sd = np.array(ys), np.array(sds)
    Bm = np.array([Bk.mean(axis=0) for Bk in bins])
    Ball = np.concatenate(bins)
    ids = np.repeat(np.arange(len(bins)), [len(Bk) for Bk in bins])
    cnt = np.bincount(ids).astype(float)
    dist_free = max(zmean) / min(zmean) >= _AXIAL_Z_RATIO
    angle_free = max(share) - min(share) >= _AXIAL_ANGLE_SHARE
    scale = np.array([1e-3, 1e-3, 1e-3, 1e-2])
    if dist_free and angle_free and len(ys) >= 4:
        c_lin, _ = nnls(Bm / np.sqrt(y)[:, None], np.ones_like(y))

        def resid(cc):
            s2 = (Ball @ cc) ** 2
            return (np.bincount(ids, weights=s2) / cnt - y) / sd

        x0 = np.maximum(c_lin, 1e-7)
        r = least_squares(lambda q: resid(q * scale), x0 / scale, bounds=(0.0, np.inf), method="trf")
        c0, c1, c2, cth = (float(v) for v in r.x * scale)
        return {"c0": max(c0, 1e-6), "c1": c1, "c2": c2, "c_theta": cth}
    # fewer parameters: c = coefficients(q)
    zmed = float(np.median(zmean))
    dref = cref[0] + cref[1] * zmed + cref[2] * zmed ** 2
    if dist_free and len(ys) >= 3:
        def coef(q):
            cd = q[:3] * scale[:3]
            return np.append(cd, cref[3] * (cd[0] + cd[1] * zmed + cd[2] * zmed ** 2) / dref)
        c_lin, _ = nnls(Bm[:, :3] / np.sqrt(y)[:, None], np.ones_like(y))
        x0 = np.maximum(c_lin, 1e-7) / scale[:3]
    elif angle_free and len(ys) >= 2:
        def coef(q):
            return np.array([q[0] * cref[0], q[0] * cref[1], q[0] * cref[2], q[1] * scale[3]])
        a0 = float(np.median(np.sqrt(y) / np.maximum(Bm @ cref, 1e-12)))
        x0 = np.array([a0, a0 * cref[3] / scale[3]])
    else:
        def coef(q):
            return q[0] * cref
        x0 = np.array([float(np.median(np.sqrt(y) / np.maximum(Bm @ cref, 1e-12)))])

    def resid_q(q):
        s2 = (Ball @ coef(q)) ** 2
        return (np.bincount(ids, weights=s2) / cnt - y) / sd

    r = least_squares(resid_q, np.maximum(x0, 1e-7), bounds=(0.0, np.inf), method="trf")
    c0, c1, c2, cth = (float(v) for v in coef(r.x))
    return {"c0": max(c0, 1e-6), "c1": c1, "c2": c2, "c_theta": cth}


_FITS = {"disparity_noise": _fit_disparity_noise, "disparity_quantization": _fit_disparity_quantization,
         "depth_bias": _fit_depth_bias, "invalid_band": _fit_invalid_band, "dropout": _fit_dropout,
         "correlated_noise": _fit_correlated_noise, "static_pattern": _fit_static_pattern,
         "flying_pixels": _fit_flying_pixels, "edge_fattening": _fit_edge_fattening, "outliers": _fit_outliers,
         "axial_refit": _fit_axial_refit}
