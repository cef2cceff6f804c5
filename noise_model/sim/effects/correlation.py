"""Spatially correlated errors: a fresh correlated field each frame, and a static pattern.

* :func:`correlated_noise` (E9): a Gaussian random field drawn afresh every frame, proportional to sigma_z.
* :func:`static_pattern` (E5, E10): a smooth disparity-offset field, the same in every frame of a capture.
* :func:`static_noise` (E10): the static share of the matching error, a field proportional to sigma_z,
  the same in every frame of a capture.

All draw their fields with :func:`~.base.gaussian_random_field`. A temporal statistic separates them
(the static fields survive a temporal mean, the per-frame field does not); the angle and depth
dependence separates the two static ones (``static_pattern`` is uniform in disparity pixels,
``static_noise`` follows the model's sigma_z). Physics and sources: the
sections cited of ``docs/depth-effects.md``.
"""

from __future__ import annotations

import threading
import zlib
from collections import OrderedDict

import numpy as np

from ...checks import check_integer_range, check_scalar_range
from ...d435 import D435, SensorModel
from .base import (
    Effect, _fb, _to_depth, _to_disparity, _z_true, check_sensor_model, gaussian_random_field, model_sigma_image,
)
from .spec import EffectSpec

__all__ = ["correlated_noise", "static_pattern", "static_noise", "CORRELATED_NOISE_DEFAULTS"]


#: Defaults of :func:`correlated_noise`: a correlated part as strong as the paper's white noise
#: (sigma = 1.0 sigma_z, so half the per-pixel variance is correlated) over l = 3 px of the simulated
#: stream (6 px at 848 x 480, inside the 3-10 px of E9).
CORRELATED_NOISE_DEFAULTS = {"sigma_z_fraction": 1.0, "length_px": 3.0}


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
            with np.errstate(invalid="ignore"):
                hit = np.isfinite(zt) & np.isfinite(theta) & (zt > 0)
            sigma = model_sigma_image(self.model, zt, theta, hit, context, self.name, self.params["sigma_z_fraction"])
        return z + sigma * g


#: Bytes of unit fields kept for the static effects (:meth:`_StaticField.field`), shared by every effect object:
#: a field depends only on its length, seed, capture and image size, and a diagnosis builds a new effect
#: object for every model it simulates, with fields of the same lengths and seeds over the same captures.
FIELD_CACHE_BYTES = 128 * 2 ** 20
_FIELDS: OrderedDict = OrderedDict()             # key -> read-only field, least recently used first
_FIELDS_LOCK = threading.Lock()


class _StaticField(Effect):
    """A unit field per capture, drawn from its own generator (never the frame's ``rng``)."""

    def field(self, shape, capture_id: str = "") -> np.ndarray:
        """The unit field G (H, W) of a capture: zero mean, unit standard deviation over the image
        (read only; kept in a cache of :data:`FIELD_CACHE_BYTES` shared by the effect objects)."""
        H, W = (int(v) for v in shape)
        key = (float(self.params["length_px"]), int(self.params["seed"]), H, W, str(capture_id))
        with _FIELDS_LOCK:
            g = _FIELDS.get(key)
            if g is not None:
                _FIELDS.move_to_end(key)
                return g
        crc = zlib.crc32(str(capture_id).encode("utf-8"))
        g = gaussian_random_field((H, W), self.params["length_px"],
                                  np.random.default_rng([self.params["seed"], crc, H, W]))
        g -= g.mean()
        g /= g.std()
        g.flags.writeable = False
        with _FIELDS_LOCK:
            _FIELDS[key] = g
            total = sum(v.nbytes for v in _FIELDS.values())
            while total > FIELD_CACHE_BYTES and len(_FIELDS) > 1:
                total -= _FIELDS.popitem(last=False)[1].nbytes
        return g


class _StaticPattern(_StaticField):
    name = "static_pattern"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        G = self.field(z.shape, context.get("capture_id") or "")
        return _to_depth(fb, _to_disparity(fb, z) + self.params["sigma_px"] * G)


class _StaticNoise(_StaticField):
    name = "static_noise"

    def __init__(self, params: dict, model: SensorModel):
        super().__init__(params)
        self.model = model

    def _apply(self, z, theta, rng, context):
        zt = _z_true(context, z.shape, self.name)
        G = self.field(z.shape, context.get("capture_id") or "")
        with np.errstate(invalid="ignore"):
            hit = np.isfinite(zt) & np.isfinite(theta) & (zt > 0)
        sigma = model_sigma_image(self.model, zt, theta, hit, context, self.name, self.params["sigma_z_fraction"])
        return z + sigma * G


def correlated_noise(sigma_m: float | None = None, length_px: float = CORRELATED_NOISE_DEFAULTS["length_px"], *,
                     sigma_z_fraction: float | None = None, model: SensorModel = D435) -> Effect:
    """Spatially correlated depth noise (E9): a fresh Gaussian random field each frame.

    Physics and source (docs/depth-effects.md, E9): neighbouring D435 pixels share most of their 9 x 9 census
    window and their semi-global matching paths, and the projector's ~5000 dots are ~9 px apart at
    848 x 480, so their depth errors are correlated over several pixels (l ~ 3-10 px at 848 x 480, share
    of the variance unknown). The paper's model draws each pixel independently, so a mapper that fuses
    hundreds of pixels per cell as independent measurements becomes overconfident.

    Forward model: z' = z + sigma * g, g a unit-variance Gaussian random field with correlation
    exp(-h^2 / (2 length_px^2)) between pixels h apart (:func:`gaussian_random_field`, from ``rng``, a
    fresh field each frame), sigma = ``sigma_m`` or ``sigma_z_fraction * sigma_z(z_true, theta)`` (the
    correlated part scales with the matching error, as the white part does), sigma_z that of the axial
    noise in effect (``context['sigma_z']``: the reference's, or :func:`~.residuals.axial_refit`'s once it
    ran; ``model``'s without it, :mod:`.base`). The white noise stays: the total per-pixel variance is
    sigma_z^2 + sigma^2.

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
        The sigma_z of ``sigma_z_fraction`` when the frame's context holds none (the paper's D435 by default).

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
    ell = check_scalar_range(length_px, "length_px", 0.0, 200.0, open_lo=True)
    check_sensor_model(model)
    if sigma_m is not None:
        sigma_m = check_scalar_range(sigma_m, "sigma_m", 0.0, 1.0, open_lo=True)
        return _CorrelatedNoise({"sigma_m": sigma_m, "length_px": ell}, model)
    frac = CORRELATED_NOISE_DEFAULTS["sigma_z_fraction"] if sigma_z_fraction is None else sigma_z_fraction
    frac = check_scalar_range(frac, "sigma_z_fraction", 0.0, 10.0, open_lo=True)
    return _CorrelatedNoise({"sigma_z_fraction": frac, "length_px": ell}, model)


def static_pattern(sigma_px: float = 0.03, length_px: float = 6.0, seed: int = 0) -> Effect:
    """A fixed-pattern disparity error, the same in every frame of a capture (E5, E10).

    Physics and source (docs/depth-effects.md, E5 and E10): residual lens distortion, rectification and imager
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
    ps = {"sigma_px": check_scalar_range(sigma_px, "sigma_px", 0.0, 2.0, open_lo=True),
          "length_px": check_scalar_range(length_px, "length_px", 0.0, 200.0, open_lo=True),
          "seed": check_integer_range(seed, "seed", 0, 2 ** 31 - 1)}
    return _StaticPattern(ps)


def static_noise(sigma_z_fraction: float = 0.8, length_px: float = 6.0, seed: int = 0, *,
                 model: SensorModel = D435) -> Effect:
    """The static share of the matching error: a field proportional to sigma_z, the same in every frame (E10).

    Physics and source (docs/depth-effects.md, E10): with a static scene the projector's dots, the
    surface's texture under them and the camera are fixed, so the part of the matching error that the
    dots and the texture decide repeats every frame; only the imagers' shot, read and speckle noise is
    drawn afresh. Its size follows the matching error itself (a weaker, more slanted or farther
    surface gives a worse match in every frame), so it scales with sigma_z, unlike a calibration
    pattern (:func:`static_pattern`), which is a fixed disparity offset. Intel's Depth Quality Tool
    reports the two parts separately (spatial against temporal noise, ``tools/depth-quality/readme.md``).

    Forward model: z' = z + sigma_z_fraction * sigma_z(z_true, theta) * G(u, v), sigma_z that of the axial
    noise in effect at the true depth and incidence angle (``context['sigma_z']``: the reference's, or
    :func:`~.residuals.axial_refit`'s once it ran; ``model``'s without it), G the unit field of
    :func:`static_pattern` (zero mean and unit standard deviation over the image, correlation
    exp(-h^2 / (2 length_px^2)), drawn from ``numpy.random.default_rng([seed, crc32(capture_id), H, W])``,
    never from the frame's ``rng``). The temporal noise is unchanged: the temporal mean of N frames
    keeps the field and 1/N of the per-frame variance.

    D435 values: the physical D435 simulation's static part is a fraction of the order of one of its
    temporal standard deviation, correlated over about the matching window (docs/physical-d435.md,
    the emergent effects); a real unit's share is not documented [estimate].
    ``sigma_z_fraction`` in (0, 10], ``length_px`` in (0, 200] px, ``seed`` an integer in [0, 2^31 - 1].

    Parameters
    ----------
    sigma_z_fraction : float
        The field's standard deviation in units of the model's sigma_z at each pixel.
    length_px : float
        Correlation length l [px of the simulated stream].
    seed : int
        Seed of the field's realisation.
    model : SensorModel
        The sigma_z the field scales with when the frame's context holds none (the paper's D435 by default).
    """
    ps = {"sigma_z_fraction": check_scalar_range(sigma_z_fraction, "sigma_z_fraction", 0.0, 10.0, open_lo=True),
          "length_px": check_scalar_range(length_px, "length_px", 0.0, 200.0, open_lo=True),
          "seed": check_integer_range(seed, "seed", 0, 2 ** 31 - 1)}
    return _StaticNoise(ps, check_sensor_model(model))


#: Registry records (:class:`~.spec.EffectSpec`) of this module's effects.
SPECS = (
    EffectSpec("correlated_noise", correlated_noise, order=4,
               # 0.5-1.2 sigma_z correlated over 1.5-4 px (3-8 px at 848 x 480; E9: 3-10)
               param_ranges={"sigma_z_fraction": (0.5, 1.2), "length_px": (1.5, 4.0)},
               valid={"sigma_z_fraction": (1e-6, 10.0), "length_px": (0.05, 200.0)}, axial_units="temporal"),
    EffectSpec("static_pattern", static_pattern, order=2,
               # 0.02-0.05 px: 1.9-4.7 mm at 1 m, 7.5-19 mm at 2 m; correlated over 3-10 px
               param_ranges={"sigma_px": (0.02, 0.05), "length_px": (3.0, 10.0), "seed": (0, 1_000_000)},
               valid={"sigma_px": (1e-9, 2.0), "length_px": (0.05, 200.0)},
               integer_params={"seed": (0, 2 ** 31 - 1)}),
    EffectSpec("static_noise", static_noise, order=2,
               # a static part of 0.5-1.5 times the temporal sigma, correlated over 2-16 px
               param_ranges={"sigma_z_fraction": (0.5, 1.5), "length_px": (2.0, 16.0), "seed": (0, 1_000_000)},
               valid={"sigma_z_fraction": (1e-6, 10.0), "length_px": (0.05, 200.0)},
               integer_params={"seed": (0, 2 ** 31 - 1)}, axial_units="static"),
)
