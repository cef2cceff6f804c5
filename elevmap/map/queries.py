"""What a controller reads from the map: heights at points and height scans.

Index and frame conventions are those of :mod:`elevmap.map.grid` and are drawn in ``docs/conventions.md``.
All positions are in the map frame [m] (x forward, y left, z up) unless a name says otherwise.

Interpolation (:func:`height_at`). Cell (gx, gy) carries its value at its centre
((gx + 1/2) res, (gy + 1/2) res). A point is interpolated bilinearly between the four cell centres
around it, over the *known* cells only: the weights of the known cells (finite elevation, inside the
window, weight > 0) are renormalised to sum to 1. The result is NaN when no known cell has weight, or
when the point lies outside the window (its cell, floor(xy / res), is not one of the map's cells).
Within half a cell of the window's edge the neighbours beyond the edge count as unknown, so there the
value is the nearest inside cells' (constant extrapolation across the edge) rather than NaN.

Variance of an interpolated height: the cells' variances are interpolated with the *same* weights,
``var = sum w_k var_k``, not with their squares. The squared weights, ``sum w_k^2 var_k``, would be
the variance of the weighted mean of *independent* cells: it would report the point midway between
four equally uncertain cells as four times more certain than any of them, a dip that appears only
because of where the sample falls. Neighbouring cells are not independent (the same camera, the same
pose error and the same pixels' correlated noise fill them), and the terrain between centres is not
measured at all. With fully correlated cells the variance would be (sum w_k sigma_k)^2 <= sum w_k
sigma_k^2, so the linear rule is the conservative of the two, is continuous, and equals a cell's own
variance at its centre. (grid_map interpolates a variance layer the same way: like any other layer.)

Height scans (:func:`height_scan`) follow two consumers: legged_gym's 17 x 11 grid around the base
(Rudin et al. 2022) and the foot rings of Miki et al. (Science Robotics 2022).

The grid_map export is :mod:`elevmap.map.grid_map`, the ``.npz`` files :mod:`elevmap.map.storage`.
These modules take the map as an argument and never import :mod:`elevmap.map.elevation_map` (whose
methods call them); :func:`check_map` checks the argument by what a map holds.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numba import njit

from noise_model.checks import check_transform
from noise_model.numba_config import JIT

from .grid import GridGeometry
from .layers import ELEVATION, POINTS, VARIANCE

if TYPE_CHECKING:                      # for annotations only: elevation_map imports this module
    from .elevation_map import ElevationMap

__all__ = [
    "height_at",
    "height_at_reference",
    "FOOT_RING_RADII",
    "FOOT_RING_COUNTS",
    "foot_ring_pattern",
    "legged_gym_pattern",
    "ScanResult",
    "height_scan",
    "check_map",
]


#: Radii [m] of the rings sampled around each foot (Miki et al., Science Robotics 2022, Table S3).
FOOT_RING_RADII = (0.08, 0.16, 0.26, 0.36, 0.48)
#: Points on each ring: 52 per foot, 208 for four feet.
FOOT_RING_COUNTS = (6, 8, 10, 12, 16)


# ---------------------------------------------------------------------------------------------
# height at points
# ---------------------------------------------------------------------------------------------
@njit(**JIT)
def _height_at_kernel(data, gx0, gy0, res, x, y, out_h, out_v, min_points):
    """Renormalised bilinear interpolation of elevation and variance (see the module docstring).

    ``data`` (len(LAYERS), n, n) in buffer order; x, y (M,) map frame [m]; writes out_h, out_v (M,).
    Cells with fewer than ``min_points`` points fused count as unknown.
    Non-finite x or y give NaN. Index arithmetic stays in floats until a cell is known to be inside,
    so huge coordinates cannot overflow an integer.
    """
    n = data.shape[1]
    sx = gx0 % n
    sy = gy0 % n
    for k in range(x.shape[0]):
        out_h[k] = np.nan
        out_v[k] = np.nan
        xk = x[k]
        yk = y[k]
        if not (np.isfinite(xk) and np.isfinite(yk)):
            continue
        ux = xk / res
        uy = yk / res
        ci = np.floor(ux) - gx0            # the cell that holds the point must be in the window
        cj = np.floor(uy) - gy0
        if not (ci >= 0.0 and ci < n and cj >= 0.0 and cj < n):
            continue
        u = ux - 0.5                       # in units of cells, from the centre of global cell 0
        v = uy - 0.5
        fu = np.floor(u)
        fv = np.floor(v)
        tx = u - fu
        ty = v - fv
        i0 = fu - gx0                      # map index of the lower neighbour: -1 .. n-1
        j0 = fv - gy0
        sw = 0.0
        swh = 0.0
        swv = 0.0
        for di in range(2):
            wx = 1.0 - tx if di == 0 else tx
            i = i0 + di
            if not (i >= 0.0 and i < n):
                continue
            bi = int(i) + sx
            if bi >= n:
                bi -= n
            for dj in range(2):
                wy = 1.0 - ty if dj == 0 else ty
                j = j0 + dj
                if not (j >= 0.0 and j < n):
                    continue
                w = wx * wy
                if not w > 0.0:
                    continue
                bj = int(j) + sy
                if bj >= n:
                    bj -= n
                h = data[ELEVATION, bi, bj]
                if not (np.isfinite(h) and data[POINTS, bi, bj] >= min_points):
                    continue
                sw += w
                swh += w * h
                swv += w * data[VARIANCE, bi, bj]
        if sw > 0.0:
            out_h[k] = swh / sw
            out_v[k] = swv / sw


def _height_at_numba(data, geometry: GridGeometry, x, y, min_points: int = 1):
    """Kernel entry on unvalidated (M,) coordinate arrays: returns (height, variance), each (M,)."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    h = np.empty(x.shape[0])
    v = np.empty(x.shape[0])
    _height_at_kernel(data, geometry.gx0, geometry.gy0, geometry.resolution_m, x, y, h, v, float(min_points))
    return h, v


def _height_at_numpy(data, geometry: GridGeometry, x, y, min_points: int = 1):
    """NumPy reference of :func:`_height_at_kernel`, term for term in the same order."""
    g = geometry
    n, res = g.n, g.resolution_m
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    M = x.shape[0]
    h_out = np.full(M, np.nan)
    v_out = np.full(M, np.nan)
    with np.errstate(invalid="ignore"):
        ux, uy = x / res, y / res
        ci, cj = np.floor(ux) - g.gx0, np.floor(uy) - g.gy0
        inside = np.isfinite(x) & np.isfinite(y) & (ci >= 0) & (ci < n) & (cj >= 0) & (cj < n)
        u, v = ux - 0.5, uy - 0.5
        fu, fv = np.floor(u), np.floor(v)
        tx, ty = u - fu, v - fv
        i0, j0 = fu - g.gx0, fv - g.gy0
    sw, swh, swv = np.zeros(M), np.zeros(M), np.zeros(M)
    for di, wx in ((0, 1.0 - tx), (1, tx)):
        for dj, wy in ((0, 1.0 - ty), (1, ty)):
            i, j = i0 + di, j0 + dj
            w = wx * wy
            with np.errstate(invalid="ignore"):
                ok = inside & (i >= 0) & (i < n) & (j >= 0) & (j < n) & (w > 0)
            bi = (i[ok].astype(np.int64) + g.gx0) % n
            bj = (j[ok].astype(np.int64) + g.gy0) % n
            h = np.zeros(M)
            var = np.zeros(M)
            pts = np.zeros(M)
            h[ok] = data[ELEVATION, bi, bj]
            var[ok] = data[VARIANCE, bi, bj]
            pts[ok] = data[POINTS, bi, bj]
            use = ok & np.isfinite(h) & (pts >= min_points)
            sw = np.where(use, sw + w, sw)
            swh = np.where(use, swh + w * h, swh)
            swv = np.where(use, swv + w * var, swv)
    has = sw > 0
    h_out[has] = swh[has] / sw[has]
    v_out[has] = swv[has] / sw[has]
    return h_out, v_out


def check_map(emap):
    """``emap`` if it is an elevation map, else ValueError.

    A map is recognised by what it holds (a :class:`GridGeometry` ``geometry``, a 3-D ``data`` array of
    layers, ``fusion_params``), so that this module need not import :class:`elevmap.ElevationMap`, whose
    methods call it.
    """
    data = getattr(emap, "data", None)
    if not (isinstance(getattr(emap, "geometry", None), GridGeometry) and isinstance(data, np.ndarray)
            and data.ndim == 3 and hasattr(emap, "fusion_params")):
        raise ValueError(f"emap must be an elevmap.ElevationMap, got {type(emap).__name__}")
    return emap


def _check_xy(xy, name: str = "xy"):
    """(x (M,), y (M,), single) from xy of shape (2,) or (M, 2), finite real metres."""
    a = np.asarray(xy)
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)) or a.dtype == bool:
        raise ValueError(f"{name} must be real numbers [m], got dtype {a.dtype}")
    single = a.shape == (2,)
    if single:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"{name} must have shape (2,) or (M, 2), got {np.shape(xy)}")
    a = a.astype(np.float64, copy=False)
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise ValueError(f"{name} has {int(bad.sum())} non-finite row(s)")
    return np.ascontiguousarray(a[:, 0]), np.ascontiguousarray(a[:, 1]), single


def _result(h, v, single):
    if single:
        return float(h[0]), float(v[0])
    return h, v


def height_at(emap: ElevationMap, xy):
    """Height and its variance at map-frame points, by bilinear interpolation over known cells.

    Parameters
    ----------
    emap : ElevationMap
        The map.
    xy : array_like, shape (2,) or (M, 2)
        Positions (x, y) in the map frame [m], finite.

    Returns
    -------
    height : ndarray, shape (M,), or float
        Interpolated elevation [m] (map frame z); NaN where no known cell contributes or the point
        is outside the map.
    variance : ndarray, shape (M,), or float
        The cells' variances interpolated with the same renormalised weights [m^2] (not the squared
        weights: see the module docstring); NaN where ``height`` is.

    A single point of shape (2,) gives two floats.

    Raises
    ------
    ValueError
        If ``xy`` has the wrong shape or dtype or holds NaN/inf.
    """
    emap = check_map(emap)
    x, y, single = _check_xy(xy)
    return _result(*_height_at_numba(emap.data, emap.geometry, x, y, emap.fusion_params.min_points), single)


def height_at_reference(emap: ElevationMap, xy):
    """NumPy reference of :func:`height_at` (same inputs, outputs and errors)."""
    emap = check_map(emap)
    x, y, single = _check_xy(xy)
    return _result(*_height_at_numpy(emap.data, emap.geometry, x, y, emap.fusion_params.min_points), single)


# ---------------------------------------------------------------------------------------------
# scan patterns
# ---------------------------------------------------------------------------------------------
def foot_ring_pattern() -> np.ndarray:
    """Offsets of the 52 samples around one foot (Miki et al. 2022), shape (52, 2) [m].

    Ring r (radius ``FOOT_RING_RADII[r]``) holds ``FOOT_RING_COUNTS[r]`` points at angles
    2 pi k / count, k = 0 .. count - 1, starting on +x; rings from the innermost out. The offsets are
    in a frame aligned with the base's heading (x forward, y left).
    """
    out = []
    for r, c in zip(FOOT_RING_RADII, FOOT_RING_COUNTS):
        a = 2.0 * np.pi * np.arange(c) / c
        out.append(np.column_stack([r * np.cos(a), r * np.sin(a)]))
    return np.concatenate(out)


def legged_gym_pattern() -> np.ndarray:
    """legged_gym's height-scan grid in the base's heading frame, shape (187, 2) [m].

    17 x 11 points 0.1 m apart: x in [-0.8, 0.8] (``measured_points_x``), y in [-0.5, 0.5]
    (``measured_points_y``), ordered as legged_gym's ``torch.meshgrid(x, y)`` flattened: point
    ``11 ix + iy`` is (x[ix], y[iy]).
    """
    x = np.arange(-8, 9) / 10.0
    y = np.arange(-5, 6) / 10.0
    X, Y = np.meshgrid(x, y, indexing="ij")
    return np.column_stack([X.ravel(), Y.ravel()])


class ScanResult(NamedTuple):
    """Heights sampled by :func:`height_scan`.

    Attributes
    ----------
    points_map : ndarray, shape (K, 2)
        Sample positions (x, y) in the map frame [m].
    height : ndarray, shape (K,)
        Map-frame elevation at each sample [m] (subtract ``T_map_base[2, 3]`` for heights relative
        to the base); ``fill`` where the map has no data.
    variance : ndarray, shape (K,)
        Its variance [m^2]; NaN where the map has no data.
    known : ndarray, shape (K,), bool
        True where the map had data (``height`` is not the fill value).
    """

    points_map: np.ndarray
    height: np.ndarray
    variance: np.ndarray
    known: np.ndarray


def _offsets(a, name: str, cols=(2,), rows: str = "K") -> np.ndarray:
    a = np.asarray(a)
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)) or a.dtype == bool:
        raise ValueError(f"{name} must be real numbers [m], got dtype {a.dtype}")
    if a.ndim != 2 or a.shape[1] not in cols:
        shapes = " or ".join(f"({rows}, {c})" for c in cols)
        raise ValueError(f"{name} must have shape {shapes}, got {a.shape}")
    a = a.astype(np.float64, copy=False)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} has non-finite entries")
    return a


def height_scan(emap: ElevationMap, T_map_base, pattern="legged_gym", feet_base=None, fill=np.nan) -> ScanResult:
    """Sample the map on a height-scan pattern around the robot, as a policy consumes it.

    The pattern is turned by the base's heading only, yaw = atan2(R[1, 0], R[0, 0]) of
    ``R = T_map_base[:3, :3]`` (the base x axis projected onto the ground), never by its roll or
    pitch, so the samples stay on a level grid as in legged_gym. (legged_gym's ``quat_apply_yaw``
    takes the quaternion's twist about z instead; the two agree when roll or pitch is zero and
    differ at second order in roll x pitch.)

    Parameters
    ----------
    emap : ElevationMap
        The map.
    T_map_base : array_like, shape (4, 4)
        Pose of the robot's base: maps base-frame points into the map frame (rotation, translation [m]).
    pattern : {"legged_gym", "foot_rings"} or array_like, shape (K, 2)
        * ``"legged_gym"``: :func:`legged_gym_pattern` (187 points) around the base position.
        * ``"foot_rings"``: :func:`foot_ring_pattern` around each foot, K = 52 F, foot after foot.
          Each foot's map position is ``T_map_base @ [foot, 1]`` (full rotation), the ring offsets
          are turned by the heading only.
        * an array of offsets (x, y) [m] in the base's heading frame, around the base position.
    feet_base : array_like, shape (F, 2) or (F, 3), optional
        Foot positions in the base frame [m] (z = 0 when only x, y are given); required with
        ``"foot_rings"`` and not accepted otherwise.
    fill : float
        Height reported where the map has no data (NaN by default; Miki et al. fill a random value).

    Returns
    -------
    ScanResult
        ``points_map`` (K, 2) [m], ``height`` (K,) [m], ``variance`` (K,) [m^2], ``known`` (K,) bool.

    Raises
    ------
    ValueError
        If ``T_map_base`` is not a rigid transform, the pattern is unknown or malformed, or
        ``feet_base`` is missing, misshapen or not finite.
    """
    emap = check_map(emap)
    T = check_transform(T_map_base, "T_map_base")
    try:
        fill = float(fill)
    except (TypeError, ValueError):
        raise ValueError(f"fill must be a number, got {fill!r}") from None
    yaw = math.atan2(T[1, 0], T[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    R_yaw = np.array([[c, -s], [s, c]])
    base_xy = T[:2, 3]
    if isinstance(pattern, str) and pattern == "foot_rings":
        if feet_base is None:
            raise ValueError("pattern 'foot_rings' needs feet_base, the feet's positions (F, 2) or (F, 3) [m]")
        feet = _offsets(feet_base, "feet_base", cols=(2, 3), rows="F")
        if feet.shape[1] == 2:
            feet = np.column_stack([feet, np.zeros(len(feet))])
        feet_map = feet @ T[:3, :3].T + T[:3, 3]
        ring = foot_ring_pattern() @ R_yaw.T
        points = (feet_map[:, None, :2] + ring[None, :, :]).reshape(-1, 2)
    else:
        if feet_base is not None:
            raise ValueError("feet_base is only used with pattern='foot_rings'")
        if isinstance(pattern, str):
            if pattern != "legged_gym":
                raise ValueError(f"pattern must be 'legged_gym', 'foot_rings' or a (K, 2) array, got {pattern!r}")
            offsets = legged_gym_pattern()
        else:
            offsets = _offsets(pattern, "pattern")
        points = offsets @ R_yaw.T + base_xy
    points = np.ascontiguousarray(points)
    h, v = _height_at_numba(emap.data, emap.geometry, points[:, 0], points[:, 1], emap.fusion_params.min_points)
    known = np.isfinite(h)
    h[~known] = fill
    return ScanResult(points, h, v, known)
