"""Semi-global aggregation of the matching cost along four image paths (Hirschmueller 2008).

Along each path direction r (left-to-right, right-to-left, top-to-bottom, bottom-to-top), with
``p - r`` the previous pixel on the path::

    L_r(p, d) = C(p, d) + min( L_r(p - r, d),
                               L_r(p - r, d - 1) + P1,
                               L_r(p - r, d + 1) + P1,
                               min_k L_r(p - r, k) + P2 )  -  min_k L_r(p - r, k)

    S(p, d) = sum_r L_r(p, d)

and L_r(p, d) = C(p, d) at the first pixel of a path. P1 penalises a one-pixel disparity change
between neighbours (slanted surfaces), P2 any larger jump (depth edges); subtracting the previous
minimum keeps L_r <= C + P2, so S <= 4 (COST_MAX + P2) fits uint16 for the D4 presets. The D4 calls
this "SLO" aggregation and sets P1 = ``sloK1Penalty``, P2 = ``sloK2Penalty`` on the cost scale of
:mod:`.census` (its edge-dependent modifiers ``...Mod1/Mod2`` are not modelled).

The horizontal paths are split over rows and the vertical paths over blocks of columns, so every
element of S is written by one thread in a fixed order, and all sums are integers: the result is the
same for any thread count. :func:`aggregate_reference` does the same in NumPy.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ...numba_config import JIT, resolve_threads, threads
from .census import COST_MAX

__all__ = ["aggregate", "aggregate_reference", "check_penalties", "N_PATHS"]

#: Number of paths summed into S.
N_PATHS = 4

_BIG = 1 << 24            # padding at d = -1 and d = D of the reference: never the minimum
_PAD = 1 << 14            # the same padding in the kernels' int16 paths (above every L_r, see _step)
_BLOCK_COLUMNS = 16       # columns per work item of the vertical paths


def check_penalties(p1, p2) -> tuple[int, int]:
    """P1 and P2 as integers with 0 <= P1 <= P2 and S fitting uint16; else ValueError."""
    try:
        a, b = int(p1), int(p2)
    except (TypeError, ValueError):
        raise ValueError(f"SGM penalties must be integers, got P1={p1!r}, P2={p2!r}") from None
    if a != p1 or b != p2 or a < 0 or b < a:
        raise ValueError(f"SGM penalties must be integers with 0 <= P1 <= P2, got P1={p1!r}, P2={p2!r}")
    if N_PATHS * (COST_MAX + b) > np.iinfo(np.uint16).max:
        raise ValueError(f"P2 = {b} is too large: the aggregated cost would overflow uint16")
    return a, b


@njit(**JIT)
def _step(cost, prev, cur, n_disp, p1, p2, minprev):
    """One path step: cur[1..D] from prev[1..D] (padded at 0 and D + 1 with :data:`_PAD`); returns min of cur.

    int16 throughout, every intermediate cast back to int16 so that the loop runs on 16 lanes per vector:
    L_r <= COST_MAX + P2 <= 16383 (the bound :func:`check_penalties` keeps), the padding 16384 plus P1
    and the previous minimum plus P2 stay below 32767, and the padding never wins over a real L_r."""
    c = np.int16(minprev + p2)
    mp = np.int16(minprev)
    m = np.int16(_PAD)
    for d in range(n_disp):
        a = prev[d]
        b = prev[d + 2]
        t = a if a < b else b
        t = np.int16(t + p1)
        z = prev[d + 1]
        t = t if t < z else z
        t = t if t < c else c
        v = np.int16(np.int16(cost[d]) + np.int16(t - mp))
        cur[d + 1] = v
        m = v if v < m else m
    return m


@njit(parallel=True, **JIT)
def _horizontal_kernel(C, p1, p2, S):
    h, w, n_disp = C.shape
    for y in prange(h):
        prev = np.full(n_disp + 2, _PAD, np.int16)
        cur = np.full(n_disp + 2, _PAD, np.int16)
        # left to right: S = L
        m = np.int16(_PAD)
        for d in range(n_disp):
            v = np.int16(C[y, 0, d])
            prev[d + 1] = v
            S[y, 0, d] = C[y, 0, d]
            m = v if v < m else m
        for x in range(1, w):
            m = _step(C[y, x], prev, cur, n_disp, p1, p2, m)
            for d in range(n_disp):
                S[y, x, d] = np.uint16(cur[d + 1])
            prev, cur = cur, prev
        # right to left: S += L
        m = np.int16(_PAD)
        for d in range(n_disp):
            v = np.int16(C[y, w - 1, d])
            prev[d + 1] = v
            S[y, w - 1, d] = np.uint16(S[y, w - 1, d] + C[y, w - 1, d])
            m = v if v < m else m
        for x in range(w - 2, -1, -1):
            m = _step(C[y, x], prev, cur, n_disp, p1, p2, m)
            for d in range(n_disp):
                S[y, x, d] = np.uint16(S[y, x, d] + np.uint16(cur[d + 1]))
            prev, cur = cur, prev


@njit(parallel=True, **JIT)
def _vertical_kernel(C, p1, p2, S):
    h, w, n_disp = C.shape
    n_blocks = (w + _BLOCK_COLUMNS - 1) // _BLOCK_COLUMNS
    for b in prange(n_blocks):
        x0 = b * _BLOCK_COLUMNS
        x1 = min(w, x0 + _BLOCK_COLUMNS)
        nb = x1 - x0
        prev = np.full((nb, n_disp + 2), _PAD, np.int16)
        cur = np.full((nb, n_disp + 2), _PAD, np.int16)
        mins = np.empty(nb, np.int16)
        for direction in range(2):
            for k in range(h):
                y = k if direction == 0 else h - 1 - k
                for j in range(nb):
                    x = x0 + j
                    if k == 0:
                        m = np.int16(_PAD)
                        for d in range(n_disp):
                            v = np.int16(C[y, x, d])
                            cur[j, d + 1] = v
                            m = v if v < m else m
                    else:
                        m = _step(C[y, x], prev[j], cur[j], n_disp, p1, p2, mins[j])
                    mins[j] = m
                    for d in range(n_disp):
                        S[y, x, d] = np.uint16(S[y, x, d] + np.uint16(cur[j, d + 1]))
                prev, cur = cur, prev


def _check_cost(cost) -> np.ndarray:
    C = np.asarray(cost)
    if C.ndim != 3 or C.shape[2] < 1:
        raise ValueError(f"cost must be an (H, W, D) volume, got shape {C.shape}")
    if C.size and int(C.max()) > COST_MAX:
        raise ValueError(f"cost values must lie in 0..{COST_MAX}")
    return np.ascontiguousarray(C, dtype=np.uint16)


def aggregate(cost, p1: int, p2: int, out=None, nthreads: int | None = None) -> np.ndarray:
    """Aggregated cost S over the four paths (numba).

    Parameters
    ----------
    cost : ndarray, shape (H, W, D), uint16
        Matching cost C(x, y, d) in 0..COST_MAX (:func:`.census.cost_volume`).
    p1, p2 : int
        SGM penalties on the same scale.
    out : ndarray, shape (H, W, D), uint16, optional
        Written in place and returned (a buffer reused from frame to frame).
    nthreads : int, optional
        numba threads; the result does not depend on it.

    Returns
    -------
    ndarray, shape (H, W, D), uint16
        S(x, y, d), the equation of the module docstring.
    """
    p1, p2 = check_penalties(p1, p2)
    C = _check_cost(cost)
    S = out if (out is not None and out.shape == C.shape and out.dtype == np.uint16 and out.flags.c_contiguous
                and out is not C) else np.empty(C.shape, np.uint16)
    with threads(resolve_threads(nthreads)):
        _horizontal_kernel(C, np.int16(p1), np.int16(p2), S)
        _vertical_kernel(C, np.int16(p1), np.int16(p2), S)
    return S


def _path_reference(C, p1, p2):
    """L_r along axis 0 of C (n_steps, n_lines, D), int64; the path runs in increasing index."""
    out = np.empty_like(C)
    out[0] = C[0]
    big = np.full(C.shape[1:2] + (1,), _BIG, np.int64)
    for i in range(1, C.shape[0]):
        prev = out[i - 1]
        m = prev.min(axis=1, keepdims=True)
        padded = np.concatenate([big, prev, big], axis=1)
        a = np.minimum(np.minimum(prev, np.minimum(padded[:, :-2], padded[:, 2:]) + p1), m + p2)
        out[i] = C[i] + a - m
    return out


def aggregate_reference(cost, p1: int, p2: int) -> np.ndarray:
    """NumPy reference of :func:`aggregate`."""
    p1, p2 = check_penalties(p1, p2)
    C = _check_cost(cost).astype(np.int64)
    Cx = C.transpose(1, 0, 2)                               # (W, H, D): paths along x
    S = _path_reference(Cx, p1, p2) + _path_reference(Cx[::-1], p1, p2)[::-1]
    S = S.transpose(1, 0, 2)
    S = S + _path_reference(C, p1, p2) + _path_reference(C[::-1], p1, p2)[::-1]
    return S.astype(np.uint16)
