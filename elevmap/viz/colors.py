"""Colour scales for images and meshes: plain NumPy, no rerun and no matplotlib.

:func:`colormap` maps values to RGB (turbo or viridis, linear or log); :func:`robust_range` picks a
colour range that a few outliers do not stretch.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["colormap", "robust_range"]


# 17 samples of each map at 0, 16, ..., 255 (taken from OpenCV's COLORMAP_TURBO / COLORMAP_VIRIDIS).
_CMAP_X = np.array([0, 16, 32, 48, 64, 80, 96, 112, 128, 143, 159, 175, 191, 207, 223, 239, 255]) / 255.0
_CMAPS = {
    "turbo": np.array([[48, 18, 59], [64, 64, 162], [70, 107, 227], [66, 148, 255], [40, 188, 235],
                       [24, 221, 194], [50, 242, 152], [109, 254, 98], [164, 252, 60], [203, 237, 52],
                       [236, 209, 58], [253, 174, 53], [251, 129, 34], [236, 83, 15], [210, 49, 5],
                       [172, 23, 1], [122, 4, 3]], dtype=np.float64),
    "viridis": np.array([[68, 1, 84], [72, 24, 106], [71, 45, 123], [66, 64, 134], [59, 82, 139],
                         [51, 99, 141], [44, 114, 142], [38, 130, 142], [33, 145, 140], [31, 159, 136],
                         [39, 173, 129], [61, 188, 116], [92, 200, 99], [129, 211, 77], [170, 220, 50],
                         [213, 226, 26], [253, 231, 37]], dtype=np.float64),
}


def colormap(values, vmin: float, vmax: float, name: str = "turbo", log: bool = False,
             nan_color=(128, 128, 128)) -> np.ndarray:
    """Map values to RGB colours (piecewise-linear turbo or viridis; no matplotlib).

    Parameters
    ----------
    values : array_like, any shape
    vmin, vmax : float
        Values at the two ends of the map; values outside are clipped. With ``log=True`` both
        must be > 0 and the map is linear in log10(value).
    name : {"turbo", "viridis"}
    nan_color : (3,) uint8
        Colour of non-finite values (and of values <= 0 with ``log=True``).

    Returns
    -------
    ndarray, shape values.shape + (3,), uint8
    """
    if name not in _CMAPS:
        raise ValueError(f"unknown colormap {name!r}; use one of {sorted(_CMAPS)}")
    v = np.asarray(values, dtype=np.float64)
    lo, hi = float(vmin), float(vmax)
    if log:
        if lo <= 0 or hi <= 0:
            raise ValueError("log colormap needs vmin, vmax > 0")
        with np.errstate(divide="ignore", invalid="ignore"):
            v = np.where(v > 0, np.log10(v), np.nan)
        lo, hi = math.log10(lo), math.log10(hi)
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise ValueError(f"need finite vmin < vmax, got {vmin}, {vmax}")
    ok = np.isfinite(v)
    t = np.clip((np.where(ok, v, lo) - lo) / (hi - lo), 0.0, 1.0)
    table = _CMAPS[name]
    rgb = np.stack([np.interp(t, _CMAP_X, table[:, k]) for k in range(3)], axis=-1)
    rgb[~ok] = np.asarray(nan_color, dtype=np.float64)
    return np.round(rgb).astype(np.uint8)


def robust_range(values) -> tuple[float, float]:
    """(2nd, 98th) percentile of the finite values, for colour scales; (0, 1) when there are none."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if not v.size:
        return 0.0, 1.0
    lo, hi = np.percentile(v, [2, 98])
    return float(lo), float(max(hi, lo + 1e-3))
