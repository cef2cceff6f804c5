"""What the paper's Gaussian leaves in the residual: its magnitude, and heavy tails.

* :func:`axial_refit`: the paper's sigma_z with refitted coefficients (the reference deviation rescaled).
* :func:`outliers` (E13, E15): a fraction of pixels with a wide disparity error.

The first changes the width of the residual's Gaussian core, the second adds tails outside it.
Physics and sources: the sections cited of ``docs/depth-effects.md``.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...checks import check_scalar_range
from ...d435 import D435, SensorModel, axial_sigma_unchecked
from .base import Effect, _fb, _to_depth, _to_disparity, _valid, _z_true, check_sensor_model, model_sigma
from .spec import EffectSpec

__all__ = ["axial_refit", "outliers"]


class _Outliers(Effect):
    name = "outliers"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        pick = rng.random(z.shape) < self.params["fraction"]
        e = rng.standard_normal(z.shape) * self.params["sigma_px"]
        d = _to_disparity(fb, z)
        d = np.where(pick, d + e, d)
        return _to_depth(fb, d)


class _AxialRefit(Effect):
    name = "axial_refit"

    def __init__(self, params: dict, model: SensorModel):
        super().__init__(params)
        self.model = model
        self.new_model = replace(model, family="paper", axial_coefficients=(params["c0"], params["c1"],
                                                                             params["c2"], params["c_theta"]))
        self._sigma_memo = None               # (z_true, theta, sigma_z) at the pixels hit, of the last frame

    def _apply(self, z, theta, rng, context):
        zt = _z_true(context, z.shape, self.name)
        z_ref = context.get("z_ref")
        z_ref = z if z_ref is None else np.asarray(z_ref, dtype=np.float64)
        if z_ref.shape != z.shape:
            raise ValueError(f"{self.name}: context['z_ref'] must have shape {z.shape}, got {z_ref.shape}")
        with np.errstate(invalid="ignore"):
            hit = _valid(zt) & np.isfinite(theta) & np.isfinite(z_ref)
        s_ref = model_sigma(self.model, zt, theta, hit, context, self.name)
        zh, th_h = zt[hit], theta[hit]
        memo = self._sigma_memo               # the last frame's: a static render gives the same sigma every frame
        if memo is not None and np.array_equal(memo[0], zh) and np.array_equal(memo[1], th_h):
            s_new = memo[2]
        else:
            s_new = axial_sigma_unchecked(zh, th_h, self.new_model)
            self._sigma_memo = (zh, th_h, s_new)
        ratio = np.where(s_ref > 0, s_new / np.where(s_ref > 0, s_ref, 1.0), 1.0)
        out = z.copy()
        out[hit] = z[hit] + (ratio - 1.0) * (z_ref[hit] - zt[hit])
        prev = context.get("sigma_z")
        sig = np.zeros(z.shape) if prev is None else np.array(prev, dtype=np.float64)
        sig[hit] = s_new
        sig.flags.writeable = False
        context["sigma_z"] = sig              # the effects after it scale with the refitted noise
        return out


def outliers(fraction: float = 0.01, sigma_px: float = 1.0) -> Effect:
    """Heavy tails: a fraction of pixels with a wide disparity error (E13, E15).

    Physics and source (docs/depth-effects.md, E13 and E15): the matcher sometimes locks onto a wrong match:
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
    return _Outliers({"fraction": check_scalar_range(fraction, "fraction", 0.0, 0.5, open_lo=True),
                      "sigma_px": check_scalar_range(sigma_px, "sigma_px", 0.0, 100.0, open_lo=True)})


def axial_refit(c0: float = D435.axial_coefficients[0], c1: float = D435.axial_coefficients[1],
                c2: float = D435.axial_coefficients[2], c_theta: float = D435.axial_coefficients[3], *,
                model: SensorModel = D435) -> Effect:
    """The paper's sigma_z with refitted coefficients (the axial noise's magnitude, not its shape).

    Physics and source: Ahn et al. 2019 fitted sigma_z(z, theta) = c0 + c1 z + c2 z^2
    + c_theta z^1.5 theta / (pi/2 - theta)^2 to one D435 with plane fits, which mix temporal noise,
    static patterns, quantisation and edge pixels (docs/depth-effects.md: the paper's model and its
    caveats); other D435 units and settings differ: ANYbotics/elevation_mapping's D435 model gives
    2.1 mm at 1 m where the paper gives 5.7 mm, Intel's RMS formula 3.8 mm. Refitting the four
    coefficients to the temporal standard deviation per distance and angle is the first thing a user does.

    Forward model: the reference deviation is rescaled to the new sigma, per pixel,
    z' = z + (sigma_new / sigma_ref - 1) (z_ref - z_true), with z_ref the depth right after the
    reference noise (``context['z_ref']``, set by
    :func:`noise_model.analysis.capture_data.simulate_capture`; without it, z itself: then put axial_refit
    first, as :data:`~noise_model.sim.effects.ORDER` does), sigma_ref the reference noise's sigma
    (``context['sigma_z']``, set by :func:`noise_model.sim.add_noise`; ``model``'s without it) and
    sigma_new the paper's form with the new coefficients at (z_true, theta). The noise stays Gaussian,
    independent per pixel and frame, with standard deviation sigma_new exactly; nothing is drawn from
    ``rng``. ``context['sigma_z']`` becomes sigma_new, so that the effects after it whose size is a
    fraction of sigma_z (``correlated_noise``, ``static_noise``) are fractions of the refitted noise.

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
        The reference (the paper's D435), when the frame's context holds no ``sigma_z``.
    """
    ps = {"c0": check_scalar_range(c0, "c0", 0.0, 0.05, open_lo=True), "c1": check_scalar_range(c1, "c1", 0.0, 0.05),
          "c2": check_scalar_range(c2, "c2", 0.0, 0.05),
          "c_theta": check_scalar_range(c_theta, "c_theta", 0.0, 1.0)}
    return _AxialRefit(ps, check_sensor_model(model))


#: Registry records (:class:`~.spec.EffectSpec`) of this module's effects.
SPECS = (
    EffectSpec("outliers", outliers, order=5,
               # 0.5-2 % gross errors of 0.5-2 px (5-20 % of the disparity at 2 m)
               param_ranges={"fraction": (0.005, 0.02), "sigma_px": (0.5, 2.0)},
               valid={"fraction": (1e-9, 0.5), "sigma_px": (1e-6, 100.0)}),
    EffectSpec("axial_refit", axial_refit, order=0,
               # a quieter unit than the paper's (0.001063, 0.0007278, 0.003949, 0.022), as
               # elevation_mapping's fit is: no draw is an invisible effect
               param_ranges={"c0": (0.0004, 0.0009), "c1": (0.0002, 0.0006), "c2": (0.0018, 0.003),
                             "c_theta": (0.010, 0.016)},
               valid={"c0": (1e-9, 0.05), "c1": (0.0, 0.05), "c2": (0.0, 0.05), "c_theta": (0.0, 1.0)},
               axial_units="sets"),
)
