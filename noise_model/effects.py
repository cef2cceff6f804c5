"""Depth effects a per-pixel Gaussian model leaves out: make the simulated D435 harder than the model.

Each factory returns an *effect*: a callable with the hook contract of :func:`noise_model.scene.add_noise`
(see ``noise_model/scene.py``)::

    effect(z, theta, rng, context) -> z

applied in order to the noisy metric z-depth (H, W) [m] (NaN = no data) before quantisation; ``rng``
is the simulation's generator (the only source of randomness, so a seed reproduces every frame);
``context`` holds at least ``K`` (3, 3) [px], ``width``, ``height``, ``index``, ``depth_scale`` and
``z_true`` (H, W) [m]. An effect never writes ``theta`` or ``z_true``; it may modify ``z`` in place.

Each effect carries ``name`` and ``params`` (its parameters, for reports). The effect names are
the identifiers of the effects library (``EFFECTS``); more follow with the sim-to-real gap issue.
Physics and D435 parameter ranges: ``shared/notes/depth-effects.md`` (E4, E9). NumPy only.

Effects
-------
:func:`correlated_noise` (E9, spatially correlated noise)
    Neighbouring D435 pixels share most of their 9 x 9 census window and their semi-global matching
    paths, and the projector's ~5000 dots are ~9 px apart at 848 x 480, so their depth errors are
    correlated over several pixels (l ~ 3-10 px at 848 x 480, share of the variance unknown). The
    paper's model (and the reference simulation) draws each pixel independently, so a mapper that
    fuses hundreds of pixels per cell as independent measurements becomes overconfident. Forward
    model: per frame a stationary Gaussian random field g(u, v) with unit variance and correlation
    rho(h) = exp(-h^2 / (2 l^2)) (h the pixel distance), made by low-pass filtering white noise with
    a Gaussian kernel of standard deviation l / sqrt(2) (two such kernels convolve to one of std l);
    z += sigma(u, v) g(u, v), with sigma = ``sigma_m`` or ``sigma_z_fraction * sigma_z(z_true, theta)``
    (the paper's sigma_z at the true depth and incidence angle: the correlated part scales with the
    matching error, as the white part does). The white reference noise stays: the total per-pixel
    variance is sigma_z^2 + sigma^2.
:func:`depth_bias` (E4, depth-dependent bias)
    An error of f b (focal length, baseline, rectification scale) is multiplicative; an offset in
    disparity (principal-point / rectification error) gives a bias growing as z^2. Forward model,
    with d = f b / z the disparity [px] of the (noisy) depth:
    z' = scale * f b / (f b / z + offset_px)  ~  scale z - z^2 offset_px / (f b).
    An out-of-box D435 averaged 980.7 mm at 1000 mm (-1.9 %); the datasheet's absolute accuracy is
    ~2 % at 2 m; offset_px = 0.05 px at 848 x 480 is 2.4 / 9.5 / 21 mm at 1 / 2 / 3 m.
"""

from __future__ import annotations

import math

import numpy as np

from .checks import check_intrinsics, check_positive_scalar
from .d435 import D435, SensorModel, _axial_sigma_unchecked

__all__ = ["Effect", "correlated_noise", "depth_bias", "gaussian_random_field", "EFFECTS", "make_effect",
           "CORRELATED_NOISE_DEFAULTS", "DEPTH_BIAS_DEFAULTS"]

#: Defaults of :func:`correlated_noise`: a correlated part as strong as the paper's white noise
#: (sigma = 1.0 sigma_z, so half the per-pixel variance is correlated) over l = 3 px of the simulated
#: stream (6 px at 848 x 480, inside the 3-10 px of the notes).
CORRELATED_NOISE_DEFAULTS = {"sigma_z_fraction": 1.0, "length_px": 3.0}
#: Defaults of :func:`depth_bias`: -1 % scale (half the -1.9 % of an out-of-box D435, inside the
#: ~2 % datasheet accuracy) and a 0.05 px disparity offset in the simulated stream's pixels (at
#: 424 x 240, f b = 10.6 px m: -4.7 mm at 1 m, -19 mm at 2 m; with the scale -15 mm at 1 m).
DEPTH_BIAS_DEFAULTS = {"scale": 0.99, "offset_px": 0.05, "baseline_m": D435.baseline_m}


class Effect:
    """Base of the effects here: the hook's input checks and the metadata shown in reports.

    Attributes
    ----------
    name : str
    params : dict
        Parameters (JSON-serialisable).
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
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(x) or x < lo or x > hi or (open_lo and x == lo):
        raise ValueError(f"{name} must be in {'(' if open_lo else '['}{lo}, {hi}], got {value!r}")
    return x


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
    w = rng.standard_normal((H + 2 * r, W + 2 * r))
    rows = np.zeros((H + 2 * r, W))
    for j in range(2 * r + 1):
        rows += k[j] * w[:, j:j + W]
    out = np.zeros((H, W))
    for i in range(2 * r + 1):
        out += k[i] * rows[i:i + H, :]
    return out


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


def correlated_noise(sigma_m: float | None = None, length_px: float = CORRELATED_NOISE_DEFAULTS["length_px"], *,
                     sigma_z_fraction: float | None = None, model: SensorModel = D435) -> Effect:
    """Spatially correlated depth noise (E9): a fresh Gaussian random field each frame.

    z += sigma * g, g a unit-variance Gaussian random field with correlation
    exp(-h^2 / (2 length_px^2)) between pixels h apart (:func:`gaussian_random_field`).

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
    if not isinstance(model, SensorModel):
        raise ValueError(f"model must be a noise_model.SensorModel, got {type(model).__name__}")
    if sigma_m is not None:
        return _CorrelatedNoise({"sigma_m": _scalar(sigma_m, "sigma_m", 0.0, 1.0, open_lo=True), "length_px": ell},
                                model)
    frac = CORRELATED_NOISE_DEFAULTS["sigma_z_fraction"] if sigma_z_fraction is None else sigma_z_fraction
    return _CorrelatedNoise({"sigma_z_fraction": _scalar(frac, "sigma_z_fraction", 0.0, 10.0, open_lo=True),
                             "length_px": ell}, model)


def depth_bias(scale: float = DEPTH_BIAS_DEFAULTS["scale"], offset_px: float = DEPTH_BIAS_DEFAULTS["offset_px"], *,
               baseline_m: float = DEPTH_BIAS_DEFAULTS["baseline_m"]) -> Effect:
    """A depth scale error and a disparity offset (E4).

    With f = ``context['K'][0, 0]`` [px] and b = ``baseline_m``: the depth's disparity d = f b / z is
    offset, d' = d + offset_px, and the depth scaled: z' = scale * f b / d'. To first order
    z' - z ~ (scale - 1) z - scale z^2 offset_px / (f b): a positive offset makes the far range read
    short. Pixels whose d' <= 0 become no data.

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


#: Effect factories by name (the identifiers of ``--sim-effects``).
EFFECTS = {"correlated_noise": correlated_noise, "depth_bias": depth_bias}


def make_effect(name: str, **params) -> Effect:
    """An effect of :data:`EFFECTS` by name, with keyword overrides of its defaults.

    Raises
    ------
    ValueError
        Unknown name or parameter, or a bad value.
    """
    from .checks import build_from_registry

    return build_from_registry(EFFECTS, "effect", name, params, hidden=("model",))
