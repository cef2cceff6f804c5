"""Effects on which pixels have data: the left invalid band and dropouts.

* :func:`invalid_band` (E6): the left band u < f B / z + margin has no depth (wider on a surface darker
  than the frame's exposure level, :func:`band_darkness`).
* :func:`dropout` (E11): missing pixels in blobs, more with distance and incidence angle.

Both only set pixels to no data (NaN); the depths that remain are unchanged. Physics and sources: the
sections cited of ``docs/depth-effects.md``.
"""

from __future__ import annotations

import math
import zlib

import numpy as np

from ...checks import check_scalar_range
from .base import Effect, _fb, _valid, _z_true, gaussian_random_field
from .spec import EffectSpec

__all__ = ["invalid_band", "band_darkness", "dropout", "DROPOUT_THETA_MAX_RAD"]


#: Largest incidence angle used by the dropout's -ln cos(theta) [rad] (89 deg): the term is finite.
DROPOUT_THETA_MAX_RAD = math.radians(89.0)


class _InvalidBand(Effect):
    name = "invalid_band"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        zt = _z_true(context, z.shape, self.name, fallback=z)
        u = np.arange(z.shape[1], dtype=np.float64)[None, :]
        with np.errstate(invalid="ignore", divide="ignore"):
            ref = np.where(_valid(zt), zt, z)
            margin = self.params["margin_px"]
            dark = self.params.get("dark_margin_px", 0.0)
            if dark != 0.0:
                margin = margin + dark * band_darkness(ref, theta)
            band = _valid(ref) & (u < fb / ref + margin)
        out = z.copy()
        out[band] = np.nan
        return out


def band_darkness(z_true, theta) -> np.ndarray:
    """How much darker than the frame's exposure level each pixel is: max(0, 1 - b / mean(b)), (H, W).

    b = cos(theta) / z_true^2 is the projector's irradiance on a Lambertian surface up to the albedo
    (inverse-square fall-off, incidence cosine); the mean is over the whole frame with 0 where nothing is
    hit, as the auto exposure averages the image. Auto exposure brings that mean to a fixed signal, so a
    surface of b below the mean (a far background beside a nearer, brighter board) is imaged darker than
    the frame's level by the ratio b / mean(b); 0 where the pixel is at or above the level or not hit.

    Parameters
    ----------
    z_true : ndarray, shape (H, W)
        True z-depth [m]; NaN or <= 0 = nothing hit.
    theta : ndarray, shape (H, W)
        Incidence angle [rad]; NaN where nothing is hit (taken as 0 where the depth is valid).
    """
    zt = np.asarray(z_true, dtype=np.float64)
    th = np.asarray(theta, dtype=np.float64)
    if zt.ndim != 2 or th.shape != zt.shape:
        raise ValueError(f"band_darkness: z_true and theta must be images of one shape (H, W), got {zt.shape} "
                         f"and {th.shape}")
    hit = _valid(zt)
    b = np.zeros(zt.shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        b[hit] = np.cos(np.where(np.isfinite(th[hit]), th[hit], 0.0)) / zt[hit] ** 2
    level = float(b.mean()) if b.size else 0.0
    if not level > 0.0:
        return np.zeros(zt.shape)
    return np.where(hit, np.maximum(0.0, 1.0 - b / level), 0.0)


class _Dropout(Effect):
    name = "dropout"

    def probability(self, z_true, theta) -> np.ndarray:
        """P(no data) per pixel: logistic in z [m] and -ln cos(theta) (NaN where nothing is hit)."""
        from scipy.special import expit, logit

        p = self.params
        th = np.minimum(np.abs(theta), DROPOUT_THETA_MAX_RAD)
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


def invalid_band(margin_px: float = 4.0, dark_margin_px: float = 0.0) -> Effect:
    """The D435's left invalid band (E6), wider on a surface darker than the frame's exposure level.

    Physics and source (docs/depth-effects.md, E6): the left imager is the reference; its leftmost columns have
    no counterpart in the right image. The datasheet's "Invalid Depth Band" (librealsense #3684,
    #12072): band = f B / Z px; a user measured it wider (#1462): the matcher needs half its window
    and firmware margins beyond it, w0 ~ 4-10 px at 848 x 480. Near the border the matcher's window
    is cut short, so its cost minimum is shallow there; on a surface imaged darker than the level the
    auto exposure sets for the frame (a far background beside a nearer, brighter board) shot noise
    and the 8-bit output make it shallower still, and the uniqueness and left-right tests reject more
    of the columns next to the band (docs/calibration.md, the band margin).

    Forward model: pixel (u, v) (u the 0-based column) has no data when
    u < f B / z_true(u, v) + margin_px + dark_margin_px * s(u, v), with s = max(0, 1 - b / mean(b)),
    b = cos(theta) / z_true^2 (:func:`band_darkness`): 0 on a surface at or above the frame's mean
    brightness, towards 1 on one much darker. z_true from ``context['z_true']`` (the pixel's own true
    disparity; the current depth where that is missing). Nothing is drawn from ``rng``.

    D435 values: 70 / 42 / 21 / 11 px at 0.3 / 0.5 / 1 / 2 m at 848 x 480 plus w0; half at 424 x 240.
    ``margin_px`` in [-50, 200] px, ``dark_margin_px`` in [0, 50] px (0: the same margin everywhere).
    """
    return _InvalidBand({"margin_px": check_scalar_range(margin_px, "margin_px", -50.0, 200.0),
                         "dark_margin_px": check_scalar_range(dark_margin_px, "dark_margin_px", 0.0, 50.0)})


def dropout(p_1m: float = 0.05, k_z: float = 1.0, k_theta: float = 1.0, length_px: float = 2.5) -> Effect:
    """Missing pixels in blobs, more with distance and incidence angle (E11).

    Physics and source (docs/depth-effects.md, E11): the D4 ASIC outputs a match or nothing ("pixels are either
    100% matched or they are not", librealsense #7608); pixels fail the second-peak, texture,
    left-right and small-segment tests (``presets.cpp``); projected irradiance falls ~1/z^2 and the
    return with cos(theta) (Keselman et al.: range ~ sqrt(albedo cos theta)); holes come in blobs
    (Isaac Lab's "blob-like missing data"; remove-small-segments).

    Forward model: P(no data) = sigmoid(logit(p_1m) + k_z (z_true - 1 m) - k_theta ln cos(theta))
    (the logistic of E11 with beta1 = k_z, beta3 = -k_theta; theta capped at 89 deg), made spatially
    structured by thresholding a Gaussian random field g (:func:`gaussian_random_field`, correlation
    length ``length_px``, a fresh field from ``rng`` every frame): a pixel is dropped when
    g < Phi^-1(P), so its marginal probability is exactly P and holes are blobs of ~length_px.

    D435 values: fill ~99 % on a matte wall at 1 m, falling at range, at grazing angles and on dark or
    glossy materials (#9737, #10229) [engineering estimate for the coefficients].
    ``p_1m`` in (0, 1), ``k_z`` in [-20, 20] 1/m, ``k_theta`` in [-20, 20], ``length_px`` in (0, 200] px.
    """
    ps = {"p_1m": check_scalar_range(p_1m, "p_1m", 0.0, 1.0, open_lo=True),
          "k_z": check_scalar_range(k_z, "k_z", -20.0, 20.0),
          "k_theta": check_scalar_range(k_theta, "k_theta", -20.0, 20.0),
          "length_px": check_scalar_range(length_px, "length_px", 0.0, 200.0, open_lo=True)}
    if ps["p_1m"] >= 1.0:
        raise ValueError(f"p_1m must be in (0, 1), got {p_1m!r}")
    return _Dropout(ps)


#: Registry records (:class:`~.spec.EffectSpec`) of this module's effects.
SPECS = (
    EffectSpec("invalid_band", invalid_band, order=10,
               # w0 of E6: 4-10 px at 848 x 480, 2-8 px here; up to ~1.5 px more on a dark background
               param_ranges={"margin_px": (2.0, 8.0), "dark_margin_px": (0.5, 3.0)},
               valid={"margin_px": (-50.0, 200.0), "dark_margin_px": (0.0, 50.0)}),
    EffectSpec("dropout", dropout, order=11,
               # 3-12 % missing at 1 m fronto-parallel, rising with z and theta; blobs of 1.5-4 px
               param_ranges={"p_1m": (0.03, 0.12), "k_z": (0.5, 1.5), "k_theta": (0.5, 1.5), "length_px": (1.5, 4.0)},
               valid={"p_1m": (1e-9, 1.0 - 1e-9), "k_z": (-20.0, 20.0), "k_theta": (-20.0, 20.0),
                      "length_px": (0.05, 200.0)}),
)
