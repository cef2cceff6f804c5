"""The base of the depth effects: the hook contract, the :class:`Effect` base class, shared helpers.

Hook contract
-------------
An effect is a callable with the hook contract of :func:`noise_model.sim.add_noise`::

    effect(z, theta, rng, context) -> z

applied in order to the noisy metric z-depth (H, W) [m] (NaN = no data) before the depth-unit
rounding. ``rng`` is the simulation's generator, the only source of randomness (the static pattern
alone is derived from its own ``seed`` parameter, so that it is the same in every frame). ``context``
holds at least ``K`` (3, 3) [px], ``width``, ``height``, ``index``, ``depth_scale`` and ``z_true``
(H, W) [m]; :func:`noise_model.analysis.capture_data.simulate_capture` adds ``baseline_m`` [m], ``capture_id``,
``regions`` and ``z_ref`` (the depth after the reference noise). :func:`~.edges.edge_fattening` leaves
``d_edges`` (H, W) [px], the true disparity with the foreground grown, for the effects after it in
the same frame (:func:`~.edges.flying_pixels` puts its band at that apparent edge). Effects that need
more than ``K``/``z_true`` compute it themselves (depth discontinuities from ``z_true``), so every effect
also works on the walk simulator's frames (:func:`noise_model.sim.simulate_walk`).

Disparity
---------
f B (focal length [px] times baseline [m]) is ``K[0, 0] * context['baseline_m']`` (the D435's 0.050 m
when absent); the disparity of a depth z is d = f B / z [px]. Pixel parameters are in pixels of the
simulated stream.

The axial noise in effect
-------------------------
``context['sigma_z']`` (H, W) [m], when present, is the standard deviation of the white axial noise the
frame holds so far: :func:`noise_model.sim.add_noise` sets it to the reference model's sigma_z(z_true,
theta) (0 where nothing is hit) and :func:`~.residuals.axial_refit` replaces it with its refitted sigma.
The effects whose size is a fraction of sigma_z (``correlated_noise``, ``static_noise``) scale with it,
so that after a refit they are fractions of the refitted noise, not of the paper's (whose angle term can
be 100 times a real camera's at grazing angles). Without it they use their own ``model``'s sigma_z
(:func:`model_sigma`), bound to the frame's focal length when the model is of the disparity family.
"""

from __future__ import annotations

import math

import numpy as np

from ...checks import check_intrinsics, check_positive_scalar, check_scalar_range
from ...d435 import D435, SensorModel, axial_sigma_unchecked

__all__ = ["Effect", "gaussian_random_field", "check_sensor_model", "true_disparity", "frame_model", "model_sigma",
           "model_sigma_image"]


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


def check_sensor_model(model) -> SensorModel:
    """``model`` itself when it is a :class:`noise_model.SensorModel`; ValueError otherwise."""
    if not isinstance(model, SensorModel):
        raise ValueError(f"model must be a noise_model.SensorModel, got {type(model).__name__}")
    return model


def frame_model(model: SensorModel, fx_px) -> SensorModel:
    """``model`` bound to a frame of focal length ``fx_px`` [px] when it is of the disparity family and not
    bound yet (its sigma_z in metres needs the focal length, :meth:`noise_model.SensorModel.with_focal`);
    ``model`` itself otherwise. ``fx_px`` None leaves an unbound disparity model unbound (its sigma_z then
    raises a ValueError that says what is missing)."""
    if model.family == "disparity" and model.frame_fx_px is None and fx_px is not None:
        return model.with_focal(float(fx_px))
    return model


def model_sigma(model: SensorModel, zt, theta, hit, context: dict, who: str):
    """sigma_z [m] of the axial noise in effect at the pixels ``hit``: ``context['sigma_z'][hit]`` when
    the context holds it (the reference's or a refit's, module docstring), else ``model``'s sigma_z at
    (zt, theta) bound to the frame's focal length ``context['K'][0, 0]`` (:func:`frame_model`).

    Parameters
    ----------
    model : SensorModel
    zt, theta : ndarray, shape (H, W)
        True depth [m] and incidence angle [rad]; finite, zt > 0 at ``hit``.
    hit : ndarray of bool, shape (H, W)
    context : dict
    who : str
        The effect's name, for error messages.

    Returns
    -------
    ndarray, shape (hit.sum(),)
    """
    sig = context.get("sigma_z")
    if sig is not None:
        s = np.asarray(sig, dtype=np.float64)
        if s.shape != hit.shape:
            raise ValueError(f"{who}: context['sigma_z'] must have shape {hit.shape}, got {s.shape}")
        return s[hit]
    K = context.get("K")
    fx = None if K is None else float(np.asarray(K, dtype=np.float64)[0, 0])
    return axial_sigma_unchecked(zt[hit], theta[hit], frame_model(model, fx))


def model_sigma_image(model: SensorModel, zt, theta, hit, context: dict, who: str, factor: float) -> np.ndarray:
    """``factor`` times :func:`model_sigma` as an image (H, W) [m], 0 outside ``hit``.

    The same values as filling zeros at ``hit`` with ``factor * model_sigma(...)``; with the context's
    sigma_z it is one pass over the image instead of a gather and a scatter of the pixels hit.
    """
    sig = context.get("sigma_z")
    if sig is not None:
        s = np.asarray(sig, dtype=np.float64)
        if s.shape != hit.shape:
            raise ValueError(f"{who}: context['sigma_z'] must have shape {hit.shape}, got {s.shape}")
        return np.where(hit, factor * s, 0.0)
    out = np.zeros(hit.shape)
    out[hit] = factor * model_sigma(model, zt, theta, hit, context, who)
    return out


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
    """``context['z_true']`` (H, W) [m] as float64, checked against ``shape``; ``fallback`` when absent
    (ValueError naming ``who`` when there is no fallback either)."""
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
    """Pixels with data: finite and > 0."""
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


#: Kernel radius [px] above which :func:`gaussian_random_field` filters by FFT (where the FFT is the
#: faster of the two at 424 x 240).
_FFT_RADIUS_PX = 24


def gaussian_random_field(shape, length_px: float, rng: np.random.Generator) -> np.ndarray:
    """A stationary Gaussian random field with unit variance and Gaussian correlation.

    White noise on a grid padded by the kernel's radius is filtered ('valid' part) with the separable
    Gaussian kernel of standard deviation s = length_px / sqrt(2), truncated at 4 s and normalised to
    unit energy, so every output pixel has variance exactly 1 and the correlation between pixels h
    apart is rho(h) = exp(-h^2 / (2 length_px^2)) (up to the truncation and the sampling of the
    kernel: within 0.002 for length_px >= 1.2, 0.02 at 1 px). No wrap-around: the field is stationary
    up to its borders.

    Kernels longer than :data:`_FFT_RADIUS_PX` taps either side are applied by FFT
    (``scipy.signal.fftconvolve``, 'valid' part), shorter ones directly (``scipy.ndimage.correlate1d``):
    the same filter on the same draws, equal up to rounding, and the FFT's cost does not grow with the
    kernel's length (the direct filter's does, linearly).

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
    ell = check_scalar_range(length_px, "length_px", 0.0, 200.0, open_lo=True)
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    s = ell / math.sqrt(2.0)
    r = max(1, int(math.ceil(4.0 * s)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / s) ** 2)
    k /= math.sqrt(float(np.sum(k * k)))
    w = rng.standard_normal((H + 2 * r, W + 2 * r))
    if r > _FFT_RADIUS_PX:
        from scipy.signal import fftconvolve

        rows = fftconvolve(w, k[None, :], mode="valid", axes=1)        # k is symmetric: convolution = correlation
        return fftconvolve(rows, k[:, None], mode="valid", axes=0)
    from scipy.ndimage import correlate1d

    rows = correlate1d(w, k, axis=1, mode="constant")[:, r:r + W]
    return correlate1d(rows, k, axis=0, mode="constant")[r:r + H, :]


def true_disparity(zt, fb):
    """True disparity d = f B / z_true [px], (H, W), with 0 where nothing is hit (infinitely far).

    ``zt`` (H, W) [m] is the true depth (NaN or <= 0 = no hit), ``fb`` f B [px m].
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(_valid(zt), fb / zt, 0.0)

