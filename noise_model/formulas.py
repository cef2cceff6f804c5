"""The formulas that the sensor model and the map share, each written once.

Every function here is plain arithmetic that runs unchanged on Python floats, NumPy arrays (the
references, the public NumPy API) and, compiled with ``njit(**JIT)(f)``, inside the numba kernels
(``noise_model.kernels``, ``elevmap.map.fusion``, ``elevmap.map.neighbours``). A kernel and its NumPy
reference therefore cannot drift apart on a formula. Only ``+ - * /``, ``np.sqrt`` and ``np.maximum``
are used, so the same source works on a scalar and on an array; the conditions under which a formula
applies (caps, degenerate inputs) stay with the callers, where they read as the rule they are. The
functions do not call one another: a compiled function can only call compiled ones, so a caller
composes them (``sigma_z_from_gain(z, angle_gain(theta, c_theta), c0, c1, c2)``).

numba's on-disk cache (``cache=True``) keys a compiled kernel on its own source file only: a kernel
compiled before an edit here keeps the old formula until ``NUMBA_CACHE_DIR`` is cleared.

Axial noise (Ahn et al. 2019; docs/noise-model.md)
---------------------------------------------------
::

    sigma_z(z, theta) = c0 + c1 z + c2 z^2 + g(theta) z^(3/2),   g(theta) = c_theta theta / (pi/2 - theta)^2

z the depth [m], theta the incidence angle [rad] (capped below pi/2 by the caller, where the angle term
diverges), sigma_z [m]. When theta is an estimate, theta_true ~ N(theta, s^2), the expected variance is

    E[sigma_z^2] = a^2 + 2 a k E[g] + k^2 E[g^2],   a = c0 + c1 z + c2 z^2,   k = z^(3/2).

Axial noise of the disparity family (docs/noise-model.md)
---------------------------------------------------------
A stereo camera measures disparity d = f B / z; an error of sigma_d pixels in d is an error of
z^2 sigma_d / (f B) in depth. With sigma_d(theta) = s0 + s1 theta^2 [px]::

    sigma_z(z, theta) = z^2 (c + g),   c = s0 / (f B),   g(theta) = (s1 / (f B)) theta^2

f the focal length [px] of the frame, B the baseline [m], so c [1/m] and g [1/m]. With an uncertain
angle, E[sigma_z^2] = z^4 (c^2 + 2 c E[g] + E[g^2]).

Wilson-Hilferty quantile of the chi-square distribution
-------------------------------------------------------
With k degrees of freedom and z_q the standard normal quantile of probability q (Wilson & Hilferty 1931)::

    chi2_{k,q} ~ k (1 - 2 / (9 k) + z_q sqrt(2 / (9 k)))^3,

written here per degree of freedom (chi2_{k,q} / k, the quantile of a reduced chi-square Q / k); callers
that compare Q itself multiply by k. Its relative error falls quickly with k (it is largest, several per
cent, at k = 1 and the tail quantiles), and it needs no special function inside a kernel. Used by the
mixed-window test (``noise_model.mixed_windows``), the fusion's scatter inflation and its spread test
(``elevmap.map.fusion``).

DerSimonian-Laird between-study variance
----------------------------------------
For k estimates y_j with weights w_j = 1 / v_j (DerSimonian & Laird 1986)::

    Q = sum w_j (y_j - m)^2,   m = sum w_j y_j / S1,
    tau^2 = max(Q - (k - 1), 0) / (S1 - S2 / S1),   S1 = sum w_j,   S2 = sum w_j^2.

Q - (k - 1) is Q's excess over its expectation when the y_j scatter only by their v_j. Used by the
fusion's per-cell spread, the map's neighbourhood spread (``elevmap.map.neighbours``) and the lateral
noise percentile of the characterisation.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["angle_gain", "sigma_z_from_gain", "sigma_z_from_gain_and_root", "expected_sigma_z_sq", "disparity_angle_gain", "disparity_sigma_z_from_gain",
           "disparity_expected_sigma_z_sq", "reduced_chi2_quantile", "dersimonian_laird_tau2"]

_HALF_PI = 0.5 * math.pi


def angle_gain(theta, c_theta):
    """The angle gain g = c_theta theta / (pi/2 - theta)^2 of sigma_z [m^-1/2].

    Parameters
    ----------
    theta : float or ndarray
        Incidence angle [rad] in [0, pi/2): the caller takes |theta| and caps it (``theta_max_rad``),
        because the term diverges at pi/2, where a stereo camera sees nothing.
    c_theta : float
        The model's angle coefficient [m^-1/2].

    Returns
    -------
    float or ndarray
        g, the shape of ``theta``; the angle term of sigma_z is g z^(3/2).
    """
    d = _HALF_PI - theta
    return c_theta * theta / (d * d)


def sigma_z_from_gain(z, gain, c0, c1, c2):
    """sigma_z = c0 + c1 z + c2 z^2 + g z^(3/2) [m], the axial noise of Ahn et al. with the angle gain g.

    sigma_z(z, theta) is ``sigma_z_from_gain(z, angle_gain(theta, c_theta), c0, c1, c2)``; the kernels
    compute g once per block of pixels and evaluate this per pixel.

    Parameters
    ----------
    z : float or ndarray
        Depth [m], > 0.
    gain : float or ndarray
        Angle gain g [m^-1/2] (:func:`angle_gain`); broadcasts with ``z``.
    c0, c1, c2 : float
        The model's polynomial coefficients [m], [-], [1/m].

    Returns
    -------
    float or ndarray
        sigma_z [m], the broadcast shape of ``z`` and ``gain``.
    """
    return c0 + c1 * z + c2 * z * z + gain * z * np.sqrt(z)


def sigma_z_from_gain_and_root(z, root_z, gain, c0, c1, c2):
    """:func:`sigma_z_from_gain` with the square root of the depth given: c0 + c1 z + c2 z^2 + g z root_z [m].

    Where many pairs of depths are compared at the nearer one, min(z1, z2), each pixel's square root can be
    taken once: sqrt(min(z1, z2)) = min(sqrt(z1), sqrt(z2)) exactly, because the correctly rounded square
    root is monotone.

    Parameters
    ----------
    z : float or ndarray
        Depth [m], > 0.
    root_z : float or ndarray
        sqrt(z) [m^1/2].
    gain, c0, c1, c2
        As in :func:`sigma_z_from_gain`.

    Returns
    -------
    float or ndarray
        sigma_z [m].
    """
    return c0 + c1 * z + c2 * z * z + gain * z * root_z


def expected_sigma_z_sq(z, mean_gain, mean_gain_sq, c0, c1, c2):
    """E[sigma_z^2] [m^2] over an uncertain angle, from the moments of its gain.

    sigma_z = a + k g with a = c0 + c1 z + c2 z^2 and k = z^(3/2), so E[sigma_z^2] = a^2 + 2 a k E[g] +
    k^2 E[g^2]: an angle estimated from noisy depth makes sigma_z(theta_hat)^2 an underestimate on
    average, because g is convex in theta.

    Parameters
    ----------
    z : float or ndarray
        Depth [m], > 0.
    mean_gain, mean_gain_sq : float or ndarray
        E[g] [m^-1/2] and E[g^2] [1/m] over the angle's distribution.
    c0, c1, c2 : float
        The model's polynomial coefficients.

    Returns
    -------
    float or ndarray
        E[sigma_z^2] [m^2], the broadcast shape of the inputs.
    """
    a = c0 + c1 * z + c2 * z * z
    k = z * np.sqrt(z)
    return a * a + 2.0 * a * k * mean_gain + k * k * mean_gain_sq


def disparity_angle_gain(theta, s1_depth):
    """The disparity family's angle gain g = (s1 / (f B)) theta^2 [1/m].

    Parameters
    ----------
    theta : float or ndarray
        Incidence angle [rad], |theta| capped by the caller (``theta_max_rad``) as for the paper's family.
    s1_depth : float
        s1 / (f B): the angle coefficient s1 [px / rad^2] of sigma_d over f B [px m].

    Returns
    -------
    float or ndarray
        g, the shape of ``theta``; sigma_z = z^2 (c + g).
    """
    return s1_depth * theta * theta


def disparity_sigma_z_from_gain(z, gain, c):
    """sigma_z = z^2 (c + g) [m], the disparity family's axial noise: z^2 sigma_d(theta) / (f B).

    Parameters
    ----------
    z : float or ndarray
        Depth [m], > 0.
    gain : float or ndarray
        g = (s1 / (f B)) theta^2 [1/m] (:func:`disparity_angle_gain`); broadcasts with ``z``.
    c : float
        s0 / (f B) [1/m].

    Returns
    -------
    float or ndarray
        sigma_z [m], the broadcast shape of ``z`` and ``gain``.
    """
    return z * z * (c + gain)


def disparity_expected_sigma_z_sq(z, mean_gain, mean_gain_sq, c):
    """E[sigma_z^2] = z^4 (c^2 + 2 c E[g] + E[g^2]) [m^2]: the disparity family over an uncertain angle.

    Parameters
    ----------
    z : float or ndarray
        Depth [m], > 0.
    mean_gain, mean_gain_sq : float or ndarray
        E[g] and E[g^2] of :func:`disparity_angle_gain` over the angle's distribution [1/m], [1/m^2].
    c : float
        s0 / (f B) [1/m].

    Returns
    -------
    float or ndarray
        [m^2], the broadcast shape of the inputs.
    """
    z2 = z * z
    return z2 * z2 * (c * c + 2.0 * c * mean_gain + mean_gain_sq)


def reduced_chi2_quantile(dof, z):
    """chi2_{k,q} / k ~ (1 - 2 / (9 k) + z_q sqrt(2 / (9 k)))^3, the Wilson-Hilferty quantile per degree of
    freedom: the level a reduced chi-square Q / k exceeds with probability 1 - q (times k: the level Q
    exceeds).

    Parameters
    ----------
    dof : float or ndarray
        Degrees of freedom k, > 0.
    z : float or ndarray
        Standard normal quantile z_q of the probability q.

    Returns
    -------
    float or ndarray
        chi2_{k,q} / k [-].
    """
    c = 1.0 - 2.0 / (9.0 * dof) + z * np.sqrt(2.0 / (9.0 * dof))
    return c * c * c


def dersimonian_laird_tau2(excess, s1, s2):
    """tau^2 = max(Q - (k - 1), 0) / (S1 - S2 / S1), the DerSimonian-Laird between-study variance.

    Parameters
    ----------
    excess : float or ndarray
        Q - (k - 1): Cochran's Q = sum w_j (y_j - m)^2 less its expectation k - 1 under the stated
        variances (the kernels keep this excess, not Q, as their running statistic).
    s1, s2 : float or ndarray
        S1 = sum w_j and S2 = sum w_j^2 of the weights w_j = 1 / v_j.

    Returns
    -------
    float or ndarray
        tau^2 in the units of v_j. Meaningful where S1 - S2 / S1 > 0 (at least two estimates with
        positive weight): the caller checks that.
    """
    return np.maximum(excess, 0.0) / (s1 - s2 / s1)
