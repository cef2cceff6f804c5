"""Checks of the map's settings and inputs: types, ranges, coordinates and memory.

A setting read from a file arrives as whatever the file held: ``"false"`` is a true value to Python,
``true`` is the number 1 and ``0`` an interval that ends in a division by zero. Every setting of
:class:`~elevmap.map.fusion.FusionParams` and of the mapping run is therefore checked for its type and
range here, before any work, and the message names the setting and the value.

Coordinates are bounded (:data:`MAX_COORDINATE_M`): a cell's global index is ``floor(x / resolution)``
as a 64-bit integer, and squares of heights enter the fusion's sums, so a coordinate of 1e18 m or a
height of 1e152 m would overflow into an error deep inside a kernel or an infinite variance. A map's
memory is stated before it is allocated and capped (:data:`MAX_MAP_BYTES`).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["MAX_COORDINATE_M", "MAX_MAP_BYTES", "MIN_HEIGHT_VARIANCE", "MAX_POINT_VARIANCE", "check_bool",
           "check_int", "check_real", "check_coordinates", "check_point_values", "check_map_memory"]

#: Largest |x|, |y|, |z| [m] of a map position, a point or a sensor origin: far beyond any robot's
#: workspace (UTM and Earth-centred coordinates are below 1e7 m), far below where 64-bit cell indices and
#: squared heights overflow.
MAX_COORDINATE_M = 1e9

#: Largest memory a map may take [bytes] (its layers and the fusion's partial grids): 8 GiB.
MAX_MAP_BYTES = 8 * 2 ** 30

#: Smallest accepted height variance of a point [m^2] ((1 nm)^2): below, the information 1/var and its
#: square leave the range where the compiled kernel and its NumPy reference round alike.
MIN_HEIGHT_VARIANCE = 1e-18

#: Largest accepted height variance of a point [m^2] (sigma 100 m): above, the variances are not in m^2
#: (mm^2, or a covariance of the wrong quantity).
MAX_POINT_VARIANCE = 1e4


def check_bool(value, name: str) -> bool:
    """A boolean setting: ``True`` or ``False`` only (not ``"false"``, ``0`` or ``"no"``)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be true or false, got {value!r}")
    return bool(value)


def check_int(value, name: str, lo: int | None = None, hi: int | None = None) -> int:
    """An integer setting in [lo, hi] (not a bool, a float or a string)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    v = int(value)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        rng = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ValueError(f"{name} must be {rng}, got {value!r}")
    return v


def check_real(value, name: str, lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
               unit: str = "") -> float:
    """A finite real setting (an int or a float, not a bool or a string) in [lo, hi] (``lo_open``: > lo)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number{unit}, got {value!r}")
    try:
        v = float(value)
    except OverflowError:
        raise ValueError(f"{name} = {value!r} is too large") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite{unit}, got {value!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise ValueError(f"{name} must be {'>' if lo_open else '>='} {lo}{unit}, got {value!r}")
    if hi is not None and v > hi:
        raise ValueError(f"{name} must be <= {hi}{unit}, got {value!r}")
    return v


def check_coordinates(a, name: str) -> None:
    """Refuse positions [m] beyond :data:`MAX_COORDINATE_M` (``a`` finite, any shape)."""
    a = np.asarray(a, dtype=np.float64)
    if a.size and float(np.abs(a).max()) > MAX_COORDINATE_M:
        raise ValueError(f"{name} holds a coordinate of {float(np.abs(a).max()):.3g} m, beyond the "
                         f"{MAX_COORDINATE_M:.0e} m a map position may have")


def check_point_values(points_map, height_var, horizontal_cov=None) -> None:
    """Refuse a frame whose values a fusion cannot take (NumPy; shapes and dtypes checked before).

    The fusion kernel makes the same checks per point while it sums the points
    (:func:`elevmap.map.fusion.fuse_frame`), and calls this for the message when one fails.

    Parameters
    ----------
    points_map : ndarray, shape (N, 3), float64
        Map-frame points [m]: finite, within :data:`MAX_COORDINATE_M`.
    height_var : ndarray, shape (N,), float64
        Height variances [m^2]: finite, in [:data:`MIN_HEIGHT_VARIANCE`, :data:`MAX_POINT_VARIANCE`].
    horizontal_cov : ndarray, shape (N, 3), float64, optional
        (Sigma_xx, Sigma_xy, Sigma_yy) [m^2]: finite, with Sigma_xx, Sigma_yy >= 0.

    Raises
    ------
    ValueError
        Naming the array and what is wrong with it.
    """
    p = points_map
    if not len(p):
        return
    bad = ~np.isfinite(p)
    if bad.any():
        raise ValueError(f"points_map has {int(bad.any(axis=1).sum())} non-finite row(s); drop invalid points first")
    var = height_var
    if not (np.all(np.isfinite(var)) and float(var.min()) > 0.0):
        raise ValueError("height_var must be finite and > 0 [m^2]")
    if float(var.min()) < MIN_HEIGHT_VARIANCE:
        raise ValueError(f"height_var holds {float(var.min()):.3g} m^2, below the smallest variance a point "
                         f"may claim ({MIN_HEIGHT_VARIANCE:g} m^2)")
    check_coordinates(p, "points_map")
    if float(var.max()) > MAX_POINT_VARIANCE:
        raise ValueError(f"height_var holds values up to {float(var.max()):.3g}: variances must be in m^2")
    h = horizontal_cov
    if h is not None and (not np.all(np.isfinite(h)) or float(min(h[:, 0].min(), h[:, 2].min())) < 0):
        raise ValueError("horizontal_cov must be finite with non-negative variances (xx, yy)")


def check_map_memory(n: int, bytes_per_cell: int, resolution_m: float) -> int:
    """The memory of an n x n map [bytes]; a ValueError stating it when above :data:`MAX_MAP_BYTES`."""
    need = int(n) * int(n) * int(bytes_per_cell)
    if need > MAX_MAP_BYTES:
        side = n * resolution_m
        fits = int(math.isqrt(MAX_MAP_BYTES // int(bytes_per_cell)))
        raise ValueError(f"a {n} x {n} map ({side:g} m at {resolution_m:g} m) needs {need / 2 ** 30:.1f} GiB "
                         f"({bytes_per_cell} bytes per cell), above the limit of {MAX_MAP_BYTES / 2 ** 30:.0f} GiB; "
                         f"at most {fits} x {fits} cells ({fits * resolution_m:g} m at this resolution)")
    return need
