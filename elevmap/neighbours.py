"""Neighbourhood spread: the disagreement of a cell's neighbours, added to its variance.

A cell's fused variance P (``variance`` minus the larger of its two spreads) says how well its points pin down their mean
if they are independent, unbiased and land in the right cell. Near a step edge and in the far field of
a D435 they often do not: the depth noise along a grazing ray is decimetres, so points of one level
land in cells of the other (measured with ``elevmap compare``: cells within 0.4 m of an edge hold
errors of 0.1-0.2 m with P of (3 mm)^2). Such errors are not visible inside a cell, whose points agree
with each other, but they are visible between cells: neighbouring heights scatter far more than their
variances allow.

For every known cell c, over the known cells j within ``radius`` cells (a (2 radius + 1)^2 window,
c included) with weights w_j = 1 / P_j, the DerSimonian-Laird random-effects estimator

    m = sum w_j h_j / sum w_j,   Q = sum w_j (h_j - m)^2,
    tau_n^2 = max(Q - (k - 1), 0) / (S1 - S2 / S1),   S1 = sum w_j, S2 = sum w_j^2,

(k the number of known cells in the window; 0 when k < 2) is the variance of the true heights about
the window's mean beyond the cells' own variances. It is stored as ``neighbour_spread`` and the cell's
variance becomes P + max(spread, neighbour_spread): the height at the centre of a cell in a window
whose cells disagree is uncertain by that disagreement. The fusion's gate and prior work on the
variance without it (:func:`elevmap.fusion._nbr_excess`; the visibility clean-up too); a new point's
weight 1 / (sigma^2 + tau^2) takes tau^2 = max(spread, neighbour_spread), so the heights depend on it
through the weights of later points only.

The window sums are separable (along the rows, then down the columns); heights enter them relative to
the mean height of the map's known cells (sampled every 8th row and column), so that the sums stay well conditioned however high the map
lies. Cells with a non-finite or non-positive P contribute nothing. Only the window of cells touched
by a frame (plus ``radius``) is recomputed: the others' neighbourhoods did not change.

Measured (``elevmap compare``, 60 frames, seed 0; the README's calibration table): see
``FusionParams.neighbour_radius``. What it cannot see: a band of cells that agree with each other and
are all wrong (a sliver of a step's top binned into the floor cell beside it, with nothing of the floor
seen around it).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

from noise_model.kernels import FASTMATH, resolve_threads

from .layers import ELEVATION, NEIGHBOUR_SPREAD, SPREAD, VARIANCE

__all__ = ["update_neighbour_spread", "update_neighbour_spread_reference", "fused_variance"]

_JIT = dict(fastmath=FASTMATH, error_model="numpy", cache=True)


def fused_variance(data) -> np.ndarray:
    """P = variance - max(spread, neighbour_spread) per cell (NaN spreads count as 0), buffer order.

    Parameters
    ----------
    data : ndarray, shape (len(LAYERS), n, n)

    Returns
    -------
    ndarray, shape (n, n) [m^2]
        NaN where the cell is unknown.
    """
    s = np.where(data[SPREAD] > 0, data[SPREAD], 0.0)
    nb = np.where(data[NEIGHBOUR_SPREAD] > 0, data[NEIGHBOUR_SPREAD], 0.0)
    return data[VARIANCE] - np.maximum(s, nb)


@njit(**_JIT)
def _cell(data, bi, bj):
    """(height, fused variance P, spread) of buffer cell (bi, bj); NaN spreads count as 0."""
    s = data[SPREAD, bi, bj]
    s = s if s > 0.0 else 0.0
    nb = data[NEIGHBOUR_SPREAD, bi, bj]
    nb = nb if nb > 0.0 else 0.0
    return data[ELEVATION, bi, bj], data[VARIANCE, bi, bj] - max(s, nb), s


@njit(parallel=True, **_JIT)
def _neighbour_kernel(data, sx, sy, i0, i1, j0, j1, radius, ref):
    """Map rows i0..i1, columns j0..j1 (inclusive, map index); buffer start (sx, sy); heights taken
    relative to ref [m]. The window sums are separable: along each row first (pass A, over the rows the
    windows reach), then down the columns (pass B); rows and columns beyond the map are zero padding.
    Each cell writes only itself (pass B reads only A and its own layers): race-free, and the same
    whatever the thread count."""
    n = data.shape[1]
    r = radius
    C = j1 - j0 + 1
    R = i1 - i0 + 1 + 2 * r                # padded rows of A: map rows i0 - r .. i1 + r
    A = np.zeros((5, R, C))
    for ii in prange(R):
        i = i0 - r + ii
        if i < 0 or i >= n:
            continue                         # beyond the map: zero
        bi = i + sx
        if bi >= n:
            bi -= n
        q = np.zeros((5, C + 2 * r))         # map columns j0 - r .. j1 + r
        for c in range(C + 2 * r):
            j = j0 - r + c
            if j < 0 or j >= n:
                continue
            bj = j + sy
            if bj >= n:
                bj -= n
            h, p, _ = _cell(data, bi, bj)
            if np.isnan(h) or not (p > 0.0 and p < np.inf):
                continue
            w = 1.0 / p
            d = h - ref
            q[0, c] = w
            q[1, c] = w * w
            q[2, c] = w * d
            q[3, c] = w * d * d
            q[4, c] = 1.0
        for f in range(5):
            for t in range(2 * r + 1):
                for c in range(C):
                    A[f, ii, c] += q[f, c + t]
    for i in prange(i0, i1 + 1):
        bi = i + sx
        if bi >= n:
            bi -= n
        B = np.zeros((5, C))
        for t in range(2 * r + 1):
            for f in range(5):
                for c in range(C):
                    B[f, c] += A[f, i - i0 + t, c]
        for c in range(C):
            bj = j0 + c + sy
            if bj >= n:
                bj -= n
            h0, p0, s = _cell(data, bi, bj)
            if np.isnan(h0) or not (p0 > 0.0 and p0 < np.inf):
                continue
            s1 = B[0, c]
            s2 = B[1, c]
            sh = B[2, c]
            shh = B[3, c]
            k = B[4, c]
            tau2 = 0.0
            if k >= 2.0:
                qq = shh - sh * sh / s1
                den = s1 - s2 / s1
                if den > 0.0 and qq > k - 1.0:
                    tau2 = (qq - (k - 1.0)) / den
            data[NEIGHBOUR_SPREAD, bi, bj] = tau2
            data[VARIANCE, bi, bj] = p0 + max(s, tau2)


def _window(geometry, rows, cols, radius):
    n = geometry.n
    i0, i1 = max(int(rows[0]) - radius, 0), min(int(rows[1]) + radius, n - 1)
    j0, j1 = max(int(cols[0]) - radius, 0), min(int(cols[1]) + radius, n - 1)
    return i0, i1, j0, j1


def _check(data, geometry, rows, cols, radius):
    n = geometry.n
    if not isinstance(data, np.ndarray) or data.dtype != np.float64 or data.ndim != 3 or data.shape[1:] != (n, n):
        raise ValueError(f"data must be a float64 layer stack of shape (L, {n}, {n})")
    if isinstance(radius, bool) or not isinstance(radius, (int, np.integer)) or not 1 <= radius <= 10:
        raise ValueError(f"radius must be an integer in [1, 10] cells, got {radius!r}")
    rows = (0, n - 1) if rows is None else rows
    cols = (0, n - 1) if cols is None else cols
    for name, r in (("rows", rows), ("cols", cols)):
        if len(r) != 2 or not (0 <= int(r[0]) <= int(r[1]) <= n - 1):
            raise ValueError(f"{name} must be (first, last) map indices within [0, {n - 1}], got {r!r}")
    return rows, cols


def update_neighbour_spread(data, geometry, radius: int = 2, rows=None, cols=None, nthreads=None) -> None:
    """Recompute ``neighbour_spread`` and ``variance`` of the known cells in a window, in place.

    Parameters
    ----------
    data : ndarray, shape (len(LAYERS), n, n)
        The map's layers (buffer order).
    geometry : GridGeometry
    radius : int
        Half-width of the neighbourhood [cells] (1 to 10).
    rows, cols : (int, int), optional
        First and last map index (inclusive) of the cells whose neighbourhoods changed (default the
        whole map); the cells within ``radius`` of them are recomputed.
    nthreads : int, optional
        numba threads.
    """
    rows, cols = _check(data, geometry, rows, cols, radius)
    i0, i1, j0, j1 = _window(geometry, rows, cols, radius)
    sx, sy = geometry.start_index
    n = resolve_threads(nthreads)
    previous = numba.get_num_threads()
    numba.set_num_threads(n)
    try:
        _neighbour_kernel(data, int(sx), int(sy), i0, i1, j0, j1, int(radius), _reference_height(data))
    finally:
        numba.set_num_threads(previous)


def _reference_height(data) -> float:
    """A height near the map's [m] (the mean of the known cells of every 8th row and column, else of all,
    0 for an empty map): heights enter the sums relative to it, so that w (h - ref)^2 stays small where
    the map lies far above its origin."""
    for h in (data[ELEVATION, ::8, ::8], data[ELEVATION]):
        known = ~np.isnan(h)
        if known.any():
            return float(np.mean(h[known]))
    return 0.0


def update_neighbour_spread_reference(data, geometry, radius: int = 2, rows=None, cols=None) -> None:
    """NumPy reference of :func:`update_neighbour_spread`: the same separable window sums, in map order."""
    rows, cols = _check(data, geometry, rows, cols, radius)
    i0, i1, j0, j1 = _window(geometry, rows, cols, radius)
    n = geometry.n
    r = radius
    ref = _reference_height(data)
    P = geometry.unwrap(fused_variance(data))
    H = geometry.unwrap(data[ELEVATION])
    ok = ~np.isnan(H) & (P > 0) & (P < np.inf)
    w = np.where(ok, 1.0 / np.where(ok, P, 1.0), 0.0)
    d = np.where(ok, H - ref, 0.0)
    q = np.stack([w, w * w, w * d, w * d * d, ok.astype(float)])
    # the rows and columns the windows reach (zero beyond them and beyond the map), summed along the
    # rows, then down the columns, taps in the kernel's order
    a0, a1 = max(i0 - r, 0), min(i1 + r, n - 1)
    b0, b1 = max(j0 - r, 0), min(j1 + r, n - 1)
    q[:, :a0] = 0.0
    q[:, a1 + 1:] = 0.0
    q[:, :, :b0] = 0.0
    q[:, :, b1 + 1:] = 0.0
    qp = np.zeros((5, n, n + 2 * r))
    qp[:, :, r:r + n] = q
    A = np.zeros((5, n, n))
    for t in range(2 * r + 1):
        A += qp[:, :, t:t + n]
    Ap = np.zeros((5, n + 2 * r, n))
    Ap[:, r:r + n] = A
    B = np.zeros((5, n, n))
    for t in range(2 * r + 1):
        B += Ap[:, t:t + n]
    s1, s2, sh, shh, k = B
    with np.errstate(invalid="ignore", divide="ignore"):
        qq = shh - sh * sh / s1
        den = s1 - s2 / s1
        tau2 = np.where((k >= 2) & (den > 0) & (qq > k - 1), (qq - (k - 1)) / den, 0.0)
    region = np.zeros((n, n), dtype=bool)
    region[i0:i1 + 1, j0:j1 + 1] = True
    upd = geometry.wrap(region & ok)
    tau2 = geometry.wrap(tau2)
    s = np.where(data[SPREAD] > 0, data[SPREAD], 0.0)
    Pb = geometry.wrap(P)
    data[NEIGHBOUR_SPREAD] = np.where(upd, tau2, data[NEIGHBOUR_SPREAD])
    data[VARIANCE] = np.where(upd, Pb + np.maximum(s, tau2), data[VARIANCE])
