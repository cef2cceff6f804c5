"""Lens blur and pixel integration of the infrared imagers: a sample image of electron rates -> pixels.

The imagers sample each pixel at s x s points (:mod:`.imagers`); the lens blur, a Gaussian, is applied at
the sample resolution (``scipy.ndimage.gaussian_filter``: truncated at 4 sigma, edges extended by the
nearest sample, along the columns, then the rows) and the samples of a pixel are averaged. The numba
kernel gives the same values as the scipy/NumPy reference to the last bit: it keeps the order of every
sum (scipy's symmetric correlation, NumPy's pixel mean), and each addition of a product to a running sum
is a loop of its own over stored values, because the project's fastmath flags (``contract``,
``reassoc``) would otherwise fuse a multiply-add or reorder a sum within one expression.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from scipy.ndimage import gaussian_filter

from ...numba_config import JIT, resolve_threads, threads

__all__ = ["integrate_samples", "integrate_samples_reference"]

#: Largest supersampling whose pixel mean the numba kernel sums in NumPy's order (NumPy sums 8 or more
#: samples of a row pairwise); larger factors take the NumPy path.
_KERNEL_MAX_SUPERSAMPLE = 7


def _blur_weights(sigma_samples: float) -> np.ndarray:
    """The normalised Gaussian taps of ``scipy.ndimage.gaussian_filter`` (truncate 4), computed as it does."""
    radius = int(4.0 * sigma_samples + 0.5)
    x = np.arange(-radius, radius + 1)
    phi = np.exp(-0.5 / (sigma_samples * sigma_samples) * x ** 2)
    return np.ascontiguousarray((phi / phi.sum())[::-1])


@njit(**JIT)
def _blur_row(r, v, wts, acc, prod, pad):
    """Sample row v of the separable blur (columns of rows v - R .. v + R, then along the row; edges
    clamped) into ``acc`` (Ws,), in the order of scipy's symmetric correlation:
    c w_0 + sum over j = -R .. -1 of (x_j + x_-j) w_j. Every addition of a product to the running sum is
    a loop of its own over stored products, so that no multiply-add is fused and no sum is reordered
    (the project's fastmath flags allow both within one expression)."""
    hs, ws = r.shape
    rad = (wts.shape[0] - 1) // 2
    for u in range(ws):
        pad[rad + u] = r[v, u] * wts[rad]
    for j in range(-rad, 0):
        above = r[min(max(v + j, 0), hs - 1)]
        below = r[min(max(v - j, 0), hs - 1)]
        wj = wts[rad + j]
        for u in range(ws):
            prod[u] = (above[u] + below[u]) * wj
        for u in range(ws):
            pad[rad + u] += prod[u]
    for k in range(rad):
        pad[k] = pad[rad]
        pad[rad + ws + k] = pad[rad + ws - 1]
    for u in range(ws):
        acc[u] = pad[rad + u] * wts[rad]
    for j in range(-rad, 0):
        wj = wts[rad + j]
        for u in range(ws):
            prod[u] = (pad[rad + u + j] + pad[rad + u - j]) * wj
        for u in range(ws):
            acc[u] += prod[u]


@njit(parallel=True, **JIT)
def _integrate_kernel(r, wts, s, out):
    """Blur and s x s pixel mean; each output row from its own s blurred sample rows (one thread each)."""
    hs, ws = r.shape
    h, w = out.shape
    rad = (wts.shape[0] - 1) // 2
    for y in prange(h):
        pad = np.empty(ws + 2 * rad)
        prod = np.empty(ws)
        row = np.empty(ws)
        part = np.empty(w)
        total = np.empty(w)
        for i in range(s):
            _blur_row(r, y * s + i, wts, row, prod, pad)
            for x in range(w):                     # a row's s samples, left to right (NumPy's order)
                part[x] = row[x * s]
            for k in range(1, s):
                for x in range(w):
                    part[x] += row[x * s + k]
            if i == 0:
                for x in range(w):
                    total[x] = part[x]
            else:
                for x in range(w):
                    total[x] += part[x]
        n = float(s * s)
        for x in range(w):
            out[y, x] = total[x] / n


def integrate_samples(rate_samples, supersample: int, blur_sigma_px: float, nthreads: int | None = None) -> np.ndarray:
    """Lens blur at the sample resolution, then the mean over each pixel's s x s samples (numba).

    ``blur_sigma_px`` is in output pixels (the sample grid uses s times that): a Gaussian of
    ``scipy.ndimage.gaussian_filter`` (truncated at 4 sigma, edges extended by the nearest sample),
    applied along the columns, then the rows. Returns (H, W); the same values as
    :func:`integrate_samples_reference` to the last bit (the kernel keeps scipy's and NumPy's order of
    every sum), for any thread count.
    """
    s = int(supersample)
    r = np.ascontiguousarray(rate_samples, dtype=np.float64)
    if r.ndim != 2:
        raise ValueError(f"rate_samples must be a 2-D sample image, got shape {r.shape}")
    hs, ws = r.shape
    if hs % s or ws % s:
        raise ValueError(f"sample image {ws}x{hs} is not a multiple of the supersampling {s}")
    if not (math.isfinite(blur_sigma_px) and blur_sigma_px >= 0):
        raise ValueError(f"blur_sigma_px must be finite and >= 0, got {blur_sigma_px!r}")
    if s > _KERNEL_MAX_SUPERSAMPLE:
        return integrate_samples_reference(r, s, blur_sigma_px)
    wts = _blur_weights(blur_sigma_px * s) if blur_sigma_px > 0 else np.ones(1)
    out = np.empty((hs // s, ws // s))
    with threads(resolve_threads(nthreads)):
        _integrate_kernel(r, wts, s, out)
    return out


def integrate_samples_reference(rate_samples, supersample: int, blur_sigma_px: float) -> np.ndarray:
    """NumPy/scipy reference of :func:`integrate_samples` (``gaussian_filter``, then the mean of each block)."""
    s = int(supersample)
    r = np.asarray(rate_samples, dtype=np.float64)
    if blur_sigma_px > 0:
        r = gaussian_filter(r, sigma=blur_sigma_px * s, mode="nearest", truncate=4.0)
    hs, ws = r.shape
    if hs % s or ws % s:
        raise ValueError(f"sample image {ws}x{hs} is not a multiple of the supersampling {s}")
    return r.reshape(hs // s, s, ws // s, s).mean(axis=(1, 3))
