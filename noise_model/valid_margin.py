"""The valid-region margin of a stereo depth image: drop the pixels whose matching window was cut short.

A stereo depth camera decides each pixel's disparity from matching costs summed over a window about it
(the D435's D4 matcher: a 9 x 9 census window, its costs averaged over a 9 x 9 box, then semi-global
aggregation along image paths). Where that window reaches the image border, or pixels the matcher left
without data (the left band no right-imager pixel sees, the occluded side of a step edge, dark or
specular surfaces), the part that remains decides the match alone. At a step edge whose far side has no
data, the remaining part is the near surface: a pixel that looks past the edge takes the near surface's
disparity (edge fattening), and its point lands at the near surface's height in the cells beyond the
edge. When the edge lies at the border of the image or beside the left invalid band, the row shows no
edge at all, so no edge test on the depth image can find these pixels; they are found by their
distance from the end of the valid region instead.

The rule, along each image row (the rectified epipolar line, along which both the disparity search and
the invalid regions run): a pixel with data is dropped when a pixel without data, or the left or right
image border, lies within ``margin_px`` columns of it::

    keep(v, u) = has_data(v, u)  and  has_data(v, u') for all |u' - u| <= margin_px,

with columns outside [0, W) counted as having no data. ``has_data`` is false for the camera's no-data
marker: 0 in uint16 depth units, and zero, negative or non-finite values in float metres (as
:func:`noise_model.checks.check_depth` reads them). Dropped pixels are set to that marker (0 or NaN),
so everything downstream treats them as pixels the camera did not measure. Columns of the same row only
(docs/fusion.md says why image columns are left out).

:func:`drop_valid_margin` is a parallel numba kernel (one image row per iteration, so the result does
not depend on the thread count); :func:`drop_valid_margin_reference` is its NumPy twin, and the tests
hold the two equal.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .numba_config import JIT, threads

__all__ = ["DEFAULT_VALID_MARGIN_PX", "MAX_VALID_MARGIN_PX", "check_valid_margin_px", "drop_valid_margin",
           "drop_valid_margin_reference", "has_data"]

#: Default margin [px], the same at every D435 depth mode (the matcher's windows are fixed in pixels): the
#: half width of the matcher's 9 x 9 cost box plus one column. docs/fusion.md gives the margins measured.
DEFAULT_VALID_MARGIN_PX = 5

#: Largest margin accepted [px]: the census and box windows together reach 8 px; a wider margin only
#: removes data.
MAX_VALID_MARGIN_PX = 16


def has_data(depth) -> np.ndarray:
    """True where a depth image holds a measurement, shape (H, W): uint16 > 0, float finite and > 0."""
    d = np.asarray(depth)
    if d.dtype == np.uint16:
        return d > 0
    with np.errstate(invalid="ignore"):
        return np.isfinite(d) & (d > 0)


def check_valid_margin_px(margin_px, what: str = "margin_px") -> int:
    """``margin_px`` as an int, or ValueError naming ``what``: an integer (not a bool, not a float) in
    [0, :data:`MAX_VALID_MARGIN_PX`] [px]."""
    if (isinstance(margin_px, bool) or not hasattr(margin_px, "__index__")
            or not 0 <= int(margin_px) <= MAX_VALID_MARGIN_PX):
        raise ValueError(f"{what} must be an integer in [0, {MAX_VALID_MARGIN_PX}] [px], got {margin_px!r}")
    return int(margin_px)


def _check(depth, margin_px):
    d = np.asarray(depth)
    if d.ndim != 2 or d.shape[0] < 1 or d.shape[1] < 1:
        raise ValueError(f"depth must be a non-empty 2-D image (H, W), got shape {d.shape}")
    if d.dtype not in (np.uint16, np.float32, np.float64):
        raise ValueError(f"depth must be uint16 depth units or float32/float64 metres, got dtype {d.dtype}")
    return np.ascontiguousarray(d), check_valid_margin_px(margin_px)


@njit(parallel=True, **JIT)
def _margin_kernel(depth, margin, fill, out):
    """Per image row: a pixel keeps its value unless it has data and its window [u - margin, u + margin]
    holds a no-data pixel or reaches past the border. The no-data pixels are counted along the row padded
    by ``margin`` no-data columns on each side (cnt[i]: no-data pixels among padded columns 0 .. i - 1), so
    a window's count is cnt[u + 2 margin + 1] - cnt[u]: one pass for the running count, and one pass without
    branches (which vectorises) for the output."""
    H, W = depth.shape
    m = margin
    L = W + 2 * m
    for v in prange(H):
        cnt = np.empty(L + 1, dtype=np.int32)
        for t in range(m + 1):
            cnt[t] = t
        c = m
        for u in range(W):
            y = float(depth[v, u])
            c += 0 if (y > 0.0) & (y < np.inf) else 1
            cnt[m + u + 1] = c
        for t in range(1, m + 1):
            cnt[m + W + t] = c + t
        w = 2 * m + 1
        for u in range(W):
            x = depth[v, u]
            y = float(x)
            has = (y > 0.0) & (y < np.inf)
            out[v, u] = fill if has & (cnt[u + w] - cnt[u] != 0) else x


def drop_valid_margin(depth, margin_px: int, *, nthreads: int | None = None) -> np.ndarray:
    """Depth with the pixels near the end of the valid region set to no data (numba).

    Parameters
    ----------
    depth : array_like, shape (H, W)
        uint16 depth units (0 = no data) or float metres (zero, negative or non-finite = no data).
    margin_px : int
        Margin along rows [px], 0 .. :data:`MAX_VALID_MARGIN_PX`; 0 returns ``depth`` itself.
    nthreads : int, optional
        numba threads (numba's setting by default).

    Returns
    -------
    ndarray, shape (H, W), the dtype of ``depth``
        A new image: pixels with data within ``margin_px`` columns of a no-data pixel or of the left or
        right image border set to 0 (uint16) or NaN (float); all other pixels unchanged.
    """
    d, m = _check(depth, margin_px)
    if m == 0:
        return d
    out = np.empty_like(d)
    fill = d.dtype.type(0 if d.dtype == np.uint16 else np.nan)
    with threads(nthreads):
        _margin_kernel(d, m, fill, out)
    return out


def drop_valid_margin_reference(depth, margin_px: int) -> np.ndarray:
    """NumPy reference of :func:`drop_valid_margin` (same inputs, same output)."""
    d, m = _check(depth, margin_px)
    if m == 0:
        return d
    ok = has_data(d)
    padded = np.zeros((d.shape[0], d.shape[1] + 2 * m), dtype=bool)
    padded[:, m:m + d.shape[1]] = ok
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * m + 1, axis=1)
    keep = windows.all(axis=2)
    out = d.copy()
    out[ok & ~keep] = 0 if d.dtype == np.uint16 else np.nan
    return out
