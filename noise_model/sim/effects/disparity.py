"""Effects on the disparity itself: extra noise in disparity, the 2^-bits lattice, a depth bias.

* :func:`disparity_noise` (E1): Gaussian noise in disparity, not in depth.
* :func:`disparity_quantization` (E2): disparity on a lattice of 2^-bits px.
* :func:`depth_bias` (E4): a depth scale error and a disparity offset.
* :func:`frame_offset` (E4, E9): a disparity offset common to the whole frame, drawn afresh every frame.

Each works on d = f B / z [px] (:mod:`.base`) and maps back to depth z' = f B / d'. Physics and sources:
the sections cited of ``docs/depth-effects.md``.
"""

from __future__ import annotations

import numpy as np

from ...checks import check_integer_range, check_intrinsics, check_positive_scalar, check_scalar_range
from ...d435 import D435
from .base import Effect, _fb, _to_depth, _to_disparity
from .spec import EffectSpec

__all__ = ["disparity_noise", "disparity_quantization", "depth_bias", "frame_offset", "DEPTH_BIAS_DEFAULTS"]


#: Defaults of :func:`depth_bias`: -1 % scale (half the -1.9 % of an out-of-box D435, inside the
#: ~2 % datasheet accuracy) and a 0.05 px disparity offset in the simulated stream's pixels (at
#: 424 x 240, f b = 10.6 px m: -4.7 mm at 1 m, -19 mm at 2 m; with the scale -15 mm at 1 m).
DEPTH_BIAS_DEFAULTS = {"scale": 0.99, "offset_px": 0.05, "baseline_m": D435.baseline_m}


class _DisparityNoise(Effect):
    name = "disparity_noise"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        e = rng.standard_normal(z.shape) * self.params["s_px"]
        return _to_depth(fb, _to_disparity(fb, z) + e)


class _DisparityQuantization(Effect):
    name = "disparity_quantization"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name) * (1.0 + self.params.get("fb_rel", 0.0))
        q = float(2 ** self.params["subpixel_bits"])
        d = _to_disparity(fb, z)
        return _to_depth(fb, np.round(d * q) / q)


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


class _FrameOffset(Effect):
    name = "frame_offset"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        offset = float(rng.standard_normal()) * self.params["sigma_px"]
        return _to_depth(fb, _to_disparity(fb, z) + offset)


def disparity_noise(s_px: float = 0.08) -> Effect:
    """Extra noise that is Gaussian in disparity, not in depth (E1).

    Physics and source (docs/depth-effects.md, E1): the matcher estimates disparity and its error is roughly
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
    part. (The pure disparity model is this effect with :func:`~.residuals.axial_refit` taking the depth term down.)

    D435 values: s 0.05-0.1 px on good texture at 848 x 480, > 0.2 px suggests recalibration (Intel's
    tuning guide); in (0, 5] px.
    """
    return _DisparityNoise({"s_px": check_scalar_range(s_px, "s_px", 0.0, 5.0, open_lo=True)})


def disparity_quantization(subpixel_bits: int = 5, fb_rel: float = 0.0) -> Effect:
    """Disparity on a lattice of 2^-subpixel_bits px (E2).

    Physics and source (docs/depth-effects.md, E2): the D435 outputs disparity with 5 fractional bits
    (``fractional_bits = 5`` in librealsense ``src/proc/disparity-transform.h``; "1/32 subpixel ...
    4096 depth planes", intelrealsense.com/subpixel-linearity), then depth as uint16 in depth units.
    The depth lattice spacing is z^2 / (2^bits f B): at 424 x 240 (f B = 10.6 px m) 2.9 mm at 1 m,
    12 mm at 2 m for 5 bits, coarser than the 1 mm unit beyond 0.58 m. Signature: comb-shaped
    histograms; the distinct depth values lie on f B / (k 2^-bits) (librealsense #3583: ~5 mm increments).

    Forward model: d = f' B / z, d' = round(d 2^bits) / 2^bits, z' = f' B / d' (no data where d' = 0),
    with the device's f' B = (1 + ``fb_rel``) f B: the lattice lies where the device's own f B puts it,
    which differs from the calibration's K[0, 0] * baseline (or from estimated intrinsics) by a fraction
    of a percent; the depth-unit rounding follows in the simulator. Nothing is drawn from ``rng``.

    ``subpixel_bits`` an integer in [0, 12] (D435: 5; reals are rounded); ``fb_rel`` in [-0.05, 0.05].
    """
    return _DisparityQuantization({"subpixel_bits": check_integer_range(subpixel_bits, "subpixel_bits", 0, 12),
                                   "fb_rel": check_scalar_range(fb_rel, "fb_rel", -0.05, 0.05)})


def depth_bias(scale: float = DEPTH_BIAS_DEFAULTS["scale"], offset_px: float = DEPTH_BIAS_DEFAULTS["offset_px"], *,
               baseline_m: float = DEPTH_BIAS_DEFAULTS["baseline_m"]) -> Effect:
    """A depth scale error and a disparity offset (E4).

    Physics and source (docs/depth-effects.md, E4): an error of f b (focal length, baseline, rectification scale)
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
    s = check_scalar_range(scale, "scale", 0.5, 2.0)
    off = check_scalar_range(offset_px, "offset_px", -5.0, 5.0)
    b = check_positive_scalar(baseline_m, "baseline_m", upper=2.0, unit=" m")
    return _DepthBias({"scale": s, "offset_px": off, "baseline_m": b})


def frame_offset(sigma_px: float = 0.015) -> Effect:
    """A disparity offset common to the whole frame, drawn afresh every frame (E4, E9).

    Physics and source (docs/depth-effects.md, E4 and E9): whatever moves the two imagers' rays against
    each other between frames shifts every pixel's disparity by about the same amount: each imager's
    pointing jitter (a sideways image shift of one imager against the other is a disparity offset of f
    times the angle), the small thermal and mechanical motion of the imagers on their stiffener. A
    calibration offset that stays (:func:`depth_bias`) is the mean of it; what changes from frame to
    frame is this effect. The paper's model draws every pixel independently, and no per-pixel field
    expresses it: a frame-wide part of the temporal noise is a correlation of infinite length, which a
    Gaussian random field (:func:`~.correlation.correlated_noise`) can only imitate by stretching its
    correlation length. A temporal mean over many frames removes it; a single frame cannot tell it from
    a depth bias.

    Forward model: one standard normal n per frame from ``rng`` (one value per call), d = f B / z,
    d' = d + ``sigma_px`` n at every pixel with data, z' = f B / d' (no data where d' <= 0). The
    per-pixel temporal variance grows by sigma_px^2 z^4 / (f B)^2; the frame's mean deviation from the
    temporal mean, in disparity, has the standard deviation ``sigma_px`` sqrt(1 - 1/F) over F frames;
    nothing static, and within one frame every pixel moves alike.

    D435 values: the physical D435 simulation has one (each imager's pointing jitter,
    docs/physical-d435.md, where its size was fitted to a real unit's frame-wide offset); its size on a
    real unit depends on the mounting and the temperature, a fraction of the per-pixel temporal sigma_d
    [estimate]. ``sigma_px`` in (0, 2] px of the simulated stream.

    Parameters
    ----------
    sigma_px : float
        Standard deviation of the per-frame offset [px of the simulated stream], in (0, 2].

    Returns
    -------
    Effect
        ``effect(z, theta, rng, context) -> z``; one standard normal drawn from ``rng`` per call.
    """
    return _FrameOffset({"sigma_px": check_scalar_range(sigma_px, "sigma_px", 0.0, 2.0, open_lo=True)})


#: Registry records (:class:`~.spec.EffectSpec`) of this module's effects.
SPECS = (
    EffectSpec("disparity_noise", disparity_noise, order=3,
               # 0.04 px adds 3.8 mm at 1 m / 15 mm at 2 m at 424 x 240 (the paper: 5.7 / 18 mm)
               param_ranges={"s_px": (0.04, 0.12)},
               valid={"s_px": (1e-6, 5.0)}),
    EffectSpec("disparity_quantization", disparity_quantization, order=9,
               # 3-6 fractional bits: lattice 1.5-12 mm at 1 m, 5.9-47 mm at 2 m (the D435: 5)
               param_ranges={"subpixel_bits": (3, 6)},
               valid={"fb_rel": (-0.05, 0.05)},
               integer_params={"subpixel_bits": (0, 12)}),
    EffectSpec("depth_bias", depth_bias, order=1,
               # -1 to -2.5 % scale; 0.02-0.08 px offset: -7.5 to -30 mm at 2 m at 424 x 240 (of one sign:
               # an out-of-box D435 reads short)
               param_ranges={"scale": (0.975, 0.99), "offset_px": (0.02, 0.08)},
               valid={"scale": (0.5, 2.0), "offset_px": (-5.0, 5.0)}),
    # after the edge effects (it moves the whole frame, edges too), before the lattice the device outputs on
    EffectSpec("frame_offset", frame_offset, order=8,
               # 0.03-0.06 px: a third to the whole of the paper's per-pixel temporal sigma_d at 2 m (0.049 px
               # at 424 x 240), so that the self-test's 12 frames show it
               param_ranges={"sigma_px": (0.03, 0.06)},
               valid={"sigma_px": (1e-9, 2.0)}),
)
