"""What every stage of the depth -> map-points kernel shares: the model's formulas compiled, the agreement
of two depths, and medians of a few values.

The formulas are those of :mod:`noise_model.formulas` and :mod:`noise_model.geometry`, compiled here with
``njit(**JIT)`` so that the kernels and the NumPy functions the reference composes run the same arithmetic.

Medians: the row and surface medians of the kernel take the median of at most 11 and 5 agreeing depths
for many pixels at once. A sorting network (:func:`sorting_network`, Batcher's odd-even merge sort) is a
fixed list of compare-exchanges, the same for every pixel, so it runs branch-free across a batch of pixels
(one pixel per SIMD lane, :func:`sort_lanes`); values that do not take part are +inf and sort last, so the
median of the k that do is the mean of sorted entries (k - 1) // 2 and k // 2, exactly the value of
:func:`rank_median` (the middle one or two by rank).
"""

from __future__ import annotations

import functools

import numpy as np
from numba import njit

from ..formulas import (
    angle_gain, disparity_angle_gain, disparity_expected_sigma_z_sq, disparity_sigma_z_from_gain, expected_sigma_z_sq,
    reduced_chi2_quantile, sigma_z_from_gain, sigma_z_from_gain_and_root,
)
from ..geometry import centred_moments
from ..numba_config import JIT

__all__ = ["EDGES", "PLANES", "POINTS", "ROW_MEDIANS", "SURFACE_MEDIANS", "sorting_network"]

#: Bits of a fused kernel's ``parts`` argument, one per stage it can run (noise_model.kernels.STAGES):
#: ``surfaces_stage`` runs PLANES, EDGES, ROW_MEDIANS; ``points_stage`` SURFACE_MEDIANS, POINTS.
PLANES = 1
EDGES = 2
ROW_MEDIANS = 4
SURFACE_MEDIANS = 8
POINTS = 16

#: noise_model.geometry.centred_moments, compiled (S a (10,) or longer moment vector, n a number)
centred = njit(**JIT)(centred_moments)
#: The formulas of noise_model.formulas, compiled: sigma_z from the angle gain, the gain, E[sigma_z^2],
#: the Wilson-Hilferty quantile per degree of freedom.
_sigma_z = njit(**JIT)(sigma_z_from_gain)
_sigma_z_root = njit(**JIT)(sigma_z_from_gain_and_root)
_angle_gain = njit(**JIT)(angle_gain)
_expected_sigma_z_sq = njit(**JIT)(expected_sigma_z_sq)
#: ... and the disparity family's: sigma_z = z^2 (c + g), g = (s1 / (f B)) theta^2, E[sigma_z^2]
_disparity_sigma_z = njit(**JIT)(disparity_sigma_z_from_gain)
_disparity_angle_gain = njit(**JIT)(disparity_angle_gain)
_disparity_expected_sigma_z_sq = njit(**JIT)(disparity_expected_sigma_z_sq)
chi2_quantile_per_dof = njit(**JIT)(reduced_chi2_quantile)


@njit(**JIT)
def sigma_model(z, g, c0, c1, c2, disp):
    """sigma_z [m] of the model's family at depth z [m] with angle gain g: the disparity family (disp)
    z^2 (c2 + g) with c2 = s0 / (f B), else the paper's c0 + c1 z + c2 z^2 + g z^(3/2)
    (SensorModel.params_array). Both are computed and one selected, so that loops calling it vectorise."""
    sd = _disparity_sigma_z(z, g, c2)
    sp = _sigma_z(z, g, c0, c1, c2)
    return sd if disp else sp


@njit(**JIT)
def gain_model(t, ct, disp):
    """The angle gain of the model's family at the (capped) angle t [rad]."""
    gd = _disparity_angle_gain(t, ct)
    gp = _angle_gain(t, ct)
    return gd if disp else gp


@njit(**JIT)
def expected_model(z, eg, eg2, c0, c1, c2, disp):
    """E[sigma_z^2] [m^2] of the model's family at depth z [m] from the gain's moments E[g], E[g^2]."""
    ed = _disparity_expected_sigma_z_sq(z, eg, eg2, c2)
    ep = _expected_sigma_z_sq(z, eg, eg2, c0, c1, c2)
    return ed if disp else ep


@njit(**JIT)
def agrees(zn, z, g, jump_rel, thr_sig, c0, c1, c2, disp):
    """Whether neighbour depth zn [m] (NaN / -inf: none) agrees with z [m]: |zn - z| within the depth-edge
    threshold max(jump_rel zq, thr_sig sigma_z(zq, g)) at the nearer depth zq with the pixel's angle gain g
    (noise_model.despeckle). Early exits: for single pixels."""
    if not zn > 0.0:
        return False
    zq = min(zn, z)
    d = abs(zn - z)
    if d <= jump_rel * zq:                   # the relative part settles most pixels without a sqrt
        return True
    return d <= thr_sig * sigma_model(zq, g, c0, c1, c2, disp)


@njit(**JIT)
def agrees_select(zn, z, g, jump_rel, thr_sig, c0, c1, c2, disp):
    """:func:`agrees` without branches (both parts computed), for loops over many pixels that vectorise."""
    zq = min(zn, z)
    d = abs(zn - z)
    return (zn > 0.0) & ((d <= jump_rel * zq) | (d <= thr_sig * sigma_model(zq, g, c0, c1, c2, disp)))


@njit(**JIT)
def agrees_select_root(zn, rn, z, rz, g, jump_rel, thr_sig, c0, c1, c2, disp):
    """:func:`agrees_select` with the square roots of the depths given (rn = sqrt(zn), rz = sqrt(z)): the
    root of the nearer depth is the smaller root, exactly (:func:`noise_model.sigma_z_from_gain_and_root`),
    so a pixel compared with many neighbours needs no square root per comparison."""
    zq = min(zn, z)
    rq = min(rn, rz)
    d = abs(zn - z)
    sd = _disparity_sigma_z(zq, g, c2)
    sp = _sigma_z_root(zq, rq, g, c0, c1, c2)
    s = sd if disp else sp
    return (zn > 0.0) & ((d <= jump_rel * zq) | (d <= thr_sig * s))


@njit(**JIT)
def rank_median(buf, k):
    """The median of buf[:k] (k >= 1): the middle one or two by rank, ties broken by position; k^2
    branch-free comparisons cost less than the mispredicted branches of a sort at these sizes."""
    lo = (k - 1) // 2
    hi = k // 2
    a = 0.0
    b = 0.0
    for i in range(k):
        x = buf[i]
        r = 0
        for j in range(k):
            r += (buf[j] < x) | ((buf[j] == x) & (j < i))
        a = x if r == lo else a
        b = x if r == hi else b
    return (a + b) / 2.0


@functools.lru_cache(maxsize=None)
def sorting_network(n: int) -> np.ndarray:
    """The compare-exchanges (i, j), i < j, of a sorting network of n inputs, shape (m, 2), int64.

    Batcher's odd-even merge sort for the next power of two, without the compare-exchanges that touch an
    input >= n: those inputs stand for +inf, which a compare-exchange never moves below n, so they are
    no-ops. Applied in order (the smaller value to i) it sorts any n values; tests check it on every 0/1
    input (the 0-1 principle)."""
    n = int(n)
    if n < 1:
        raise ValueError(f"a sorting network needs n >= 1 inputs, got {n}")
    size = 1 << (n - 1).bit_length()
    pairs = []
    p = 1
    while p < size:
        k = p
        while k >= 1:
            for j in range(k % p, size - k, 2 * k):
                for i in range(min(k, size - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p) and i + j + k < n:
                        pairs.append((i + j, i + j + k))
            k //= 2
        p *= 2
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


@njit(**JIT)
def sort_lanes(buf, m, net):
    """Sort the columns 0..m-1 of buf (n, L) in place by the compare-exchanges net (c, 2) of
    :func:`sorting_network` (n): each column is one pixel's values, and each compare-exchange is one
    branch-free pass over the columns (NaN must not occur: values that take no part are +inf)."""
    for c in range(net.shape[0]):
        i = net[c, 0]
        j = net[c, 1]
        for k in range(m):
            x = buf[i, k]
            y = buf[j, k]
            lt = x < y
            buf[i, k] = x if lt else y
            buf[j, k] = y if lt else x


@njit(**JIT)
def _cx(x, y):
    """A compare-exchange: (min, max) of two values that are not NaN."""
    lt = x < y
    return (x if lt else y), (y if lt else x)


@njit(**JIT)
def _sort11_lanes(buf, m):
    """:func:`sort_lanes` for n = 11: the compare-exchanges of ``sorting_network(11)`` written out, on
    values held in registers (each loaded and stored once per column)."""
    for k in range(m):
        x0 = buf[0, k]
        x1 = buf[1, k]
        x2 = buf[2, k]
        x3 = buf[3, k]
        x4 = buf[4, k]
        x5 = buf[5, k]
        x6 = buf[6, k]
        x7 = buf[7, k]
        x8 = buf[8, k]
        x9 = buf[9, k]
        x10 = buf[10, k]
        x0, x1 = _cx(x0, x1)
        x2, x3 = _cx(x2, x3)
        x4, x5 = _cx(x4, x5)
        x6, x7 = _cx(x6, x7)
        x8, x9 = _cx(x8, x9)
        x0, x2 = _cx(x0, x2)
        x1, x3 = _cx(x1, x3)
        x4, x6 = _cx(x4, x6)
        x5, x7 = _cx(x5, x7)
        x8, x10 = _cx(x8, x10)
        x1, x2 = _cx(x1, x2)
        x5, x6 = _cx(x5, x6)
        x9, x10 = _cx(x9, x10)
        x0, x4 = _cx(x0, x4)
        x1, x5 = _cx(x1, x5)
        x2, x6 = _cx(x2, x6)
        x3, x7 = _cx(x3, x7)
        x2, x4 = _cx(x2, x4)
        x3, x5 = _cx(x3, x5)
        x1, x2 = _cx(x1, x2)
        x3, x4 = _cx(x3, x4)
        x5, x6 = _cx(x5, x6)
        x9, x10 = _cx(x9, x10)
        x0, x8 = _cx(x0, x8)
        x1, x9 = _cx(x1, x9)
        x2, x10 = _cx(x2, x10)
        x4, x8 = _cx(x4, x8)
        x5, x9 = _cx(x5, x9)
        x6, x10 = _cx(x6, x10)
        x2, x4 = _cx(x2, x4)
        x3, x5 = _cx(x3, x5)
        x6, x8 = _cx(x6, x8)
        x7, x9 = _cx(x7, x9)
        x1, x2 = _cx(x1, x2)
        x3, x4 = _cx(x3, x4)
        x5, x6 = _cx(x5, x6)
        x7, x8 = _cx(x7, x8)
        x9, x10 = _cx(x9, x10)
        buf[0, k] = x0
        buf[1, k] = x1
        buf[2, k] = x2
        buf[3, k] = x3
        buf[4, k] = x4
        buf[5, k] = x5
        buf[6, k] = x6
        buf[7, k] = x7
        buf[8, k] = x8
        buf[9, k] = x9
        buf[10, k] = x10


@njit(**JIT)
def _sort5_lanes(buf, m):
    """:func:`sort_lanes` for n = 5: the compare-exchanges of ``sorting_network(5)`` written out, on
    values held in registers (each loaded and stored once per column)."""
    for k in range(m):
        x0 = buf[0, k]
        x1 = buf[1, k]
        x2 = buf[2, k]
        x3 = buf[3, k]
        x4 = buf[4, k]
        x0, x1 = _cx(x0, x1)
        x2, x3 = _cx(x2, x3)
        x0, x2 = _cx(x0, x2)
        x1, x3 = _cx(x1, x3)
        x1, x2 = _cx(x1, x2)
        x0, x4 = _cx(x0, x4)
        x2, x4 = _cx(x2, x4)
        x1, x2 = _cx(x1, x2)
        x3, x4 = _cx(x3, x4)
        buf[0, k] = x0
        buf[1, k] = x1
        buf[2, k] = x2
        buf[3, k] = x3
        buf[4, k] = x4


@njit(**JIT)
def sort_lanes_any(buf, m, net):
    """:func:`sort_lanes` with the networks of 11 and 5 inputs (the row and surface medians) written out.

    A network applied one compare-exchange at a time over the columns stores each value back after
    every compare-exchange; compilers turn "store the smaller back where it came from" into a masked
    store, and a load from a masked store cannot be forwarded, so each compare-exchange waits for the
    last. Written out, each column's values stay in registers."""
    n = buf.shape[0]
    if n == 11:
        _sort11_lanes(buf, m)
    elif n == 5:
        _sort5_lanes(buf, m)
    else:
        sort_lanes(buf, m, net)


@njit(**JIT)
def lane_median(buf, lane, k):
    """The median of the k smallest values of column ``lane`` of buf, sorted by :func:`sort_lanes` (its
    k agreeing values; the others are +inf and last): equal to :func:`rank_median` of those k."""
    return (buf[(k - 1) // 2, lane] + buf[k // 2, lane]) / 2.0


@njit(**JIT)
def rss(S, n, alpha, beta):
    """numba version of :func:`noise_model.geometry.plane_rss` (the same arithmetic on ``centred``)."""
    _, _, _, _, _, _, cuw, cvw, cww = centred(S, n)
    return n * (cww - alpha * cuw - beta * cvw)


@njit(**JIT)
def interleaved(rank, count):
    """The block row a prange iteration ``rank`` of ``count`` works on: the even block rows first, then
    the odd ones. numba gives each thread one contiguous range of iterations, and valid pixels are often
    uneven over the image (sky, floor out of range); interleaving evens the threads' loads. int64: the
    prange index may be typed unsigned, and unsigned with signed gives float64."""
    r = np.int64(rank)
    half = (np.int64(count) + 1) // 2
    return 2 * r if r < half else 2 * (r - half) + 1

