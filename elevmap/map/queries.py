"""What a controller reads from the map: heights at points, height scans, grid_map export, files.

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

Height scans (:func:`height_scan`) follow the two consumers of the notes: legged_gym's 17 x 11 grid
around the base (Rudin et al. 2022) and the foot rings of Miki et al. (Science Robotics 2022).

grid_map export (:func:`to_grid_map`): see its docstring for the layout and the start-index choice.

Files (:func:`save`, :func:`load`): one ``.npz`` (no pickle) tagged ``elevmap-map/1``, written
atomically.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numba import njit

from noise_model.checks import check_transform
from noise_model.numba_config import JIT

from .elevation_map import ElevationMap
from ..fileio import atomic_output
from .fusion import FusionParams
from .grid import GridGeometry
from .layers import ELEVATION, LAYERS, LAYERS_V1, LAYERS_V2, POINTS, UNKNOWN_VALUES, VARIANCE

__all__ = [
    "height_at",
    "height_at_reference",
    "FOOT_RING_RADII",
    "FOOT_RING_COUNTS",
    "foot_ring_pattern",
    "legged_gym_pattern",
    "ScanResult",
    "height_scan",
    "to_grid_map",
    "save",
    "load",
    "FORMAT_TAG",
]


#: Radii [m] of the rings sampled around each foot (Miki et al., Science Robotics 2022, Table S3).
FOOT_RING_RADII = (0.08, 0.16, 0.26, 0.36, 0.48)
#: Points on each ring: 52 per foot, 208 for four feet.
FOOT_RING_COUNTS = (6, 8, 10, 12, 16)
#: Format tag of the files written by :func:`save`.
FORMAT_TAG = "elevmap-map/1"


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


def _check_map(emap) -> ElevationMap:
    if not isinstance(emap, ElevationMap):
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
    emap = _check_map(emap)
    x, y, single = _check_xy(xy)
    return _result(*_height_at_numba(emap.data, emap.geometry, x, y, emap.fusion_params.min_points), single)


def height_at_reference(emap: ElevationMap, xy):
    """NumPy reference of :func:`height_at` (same inputs, outputs and errors)."""
    emap = _check_map(emap)
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
    emap = _check_map(emap)
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


# ---------------------------------------------------------------------------------------------
# grid_map export
# ---------------------------------------------------------------------------------------------
def to_grid_map(emap: ElevationMap, layers=None, *, frame_id: str = "map") -> dict:
    """The content of a ``grid_map_msgs/GridMap`` message.

    grid_map's index (row, col) = (0, 0) is the +x, +y corner of the map, rows run towards -x and
    columns towards -y, and its (unwrapped) cell (r, c) is centred at

        x = position_x + (length_x/2 - res/2) - res r,   y = position_y + (length_y/2 - res/2) - res c.

    So matrix ``M[r, c] = layer[n - 1 - r, n - 1 - c]`` with ``layer`` in map-index order.

    Start indices: the map is exported *unwrapped*, with ``outer_start_index = inner_start_index = 0``.
    The alternative (the raw circular buffer, flipped, with start indices (-gx0 mod n, -gy0 mod n))
    saves one roll of each layer, which costs nothing next to the float32, column-major copy the
    message needs anyway; in exchange every consumer is right, including those that ignore the
    start indices (as many Python consumers do). elevation_mapping_cupy publishes the same way.

    Parameters
    ----------
    emap : ElevationMap
        The map.
    layers : sequence of str, optional
        Layers to export, in this order (all of ``elevmap.map.layers.LAYERS`` by default).
    frame_id : str
        The map frame's name.

    Returns
    -------
    dict
        ``frame_id``; ``stamp`` (``emap.last_stamp`` [s], NaN before the first update);
        ``resolution`` [m]; ``length_x``, ``length_y`` [m]; ``position`` (x, y) [m], the map's centre;
        ``layers`` (names); ``basic_layers`` (``["elevation", "variance"]``, those of them exported);
        ``data`` {name: float32 array (rows * cols,), the matrix in column-major order, i.e.
        ``data[k] = M[k % rows, k // rows]``}; ``layout``, the Float32MultiArray dimensions
        (``column_index`` then ``row_index``); ``outer_start_index``, ``inner_start_index`` (0, 0);
        ``size`` (rows, cols). ``elevation`` and ``variance`` are NaN in cells that are not known
        (fewer than ``FusionParams.min_points`` points, see ``ElevationMap.is_known``): grid_map's
        basic layers mark validity; the other layers are exported as stored.

    Raises
    ------
    ValueError
        For an unknown or repeated layer name.
    """
    emap = _check_map(emap)
    names = list(LAYERS) if layers is None else [layers] if isinstance(layers, str) else list(layers)
    if not names:
        raise ValueError("layers is empty")
    for name in names:
        if name not in LAYERS:
            raise ValueError(f"unknown layer {name!r}; layers are {', '.join(LAYERS)}")
    if len(set(names)) != len(names):
        raise ValueError(f"layers has repeated names: {names}")
    g = emap.geometry
    n, res = g.n, g.resolution_m
    rows = cols = n
    data = {}
    pending = ~emap.is_known() & np.isfinite(g.unwrap(emap.data[LAYERS.index("elevation")]))
    for name in names:
        m = g.unwrap(emap.data[LAYERS.index(name)])      # map-index order, [i, j]
        if name in ("elevation", "variance"):            # cells below min_points read as unknown
            m = np.where(pending, np.nan, m)
        gm = m[::-1, ::-1]                               # grid_map order, [r, c]
        data[name] = np.ascontiguousarray(gm.T, dtype=np.float32).ravel()   # column-major
    centre = g.centre_xy
    return {
        "frame_id": str(frame_id),
        "stamp": float(emap.last_stamp),
        "resolution": float(res),
        "length_x": float(n * res),
        "length_y": float(n * res),
        "position": (float(centre[0]), float(centre[1])),
        "layers": names,
        "basic_layers": [b for b in ("elevation", "variance") if b in names],
        "data": data,
        "layout": [{"label": "column_index", "size": cols, "stride": rows * cols},
                   {"label": "row_index", "size": rows, "stride": rows}],
        "outer_start_index": 0,
        "inner_start_index": 0,
        "size": (rows, cols),
    }


# ---------------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------------
_KEYS = ("format", "layers", "data", "n", "resolution_m", "gx0", "gy0", "fusion_params", "settings", "frames",
         "last_stamp")


def save(emap: ElevationMap, path) -> None:
    """Write the map to one ``.npz`` file, atomically (a crash leaves any previous file intact).

    The archive holds ``format`` ("elevmap-map/1"), ``layers`` (the layer names, JSON), ``data``
    (len(LAYERS), n, n) float64 in buffer order, the geometry ``n``, ``resolution_m`` [m], ``gx0``,
    ``gy0``, ``fusion_params`` (JSON), ``settings`` (JSON: visibility_cleanup, cleanup_stride),
    ``frames`` and ``last_stamp`` [s]. No pickled objects: strings are stored as unicode arrays.

    Parameters
    ----------
    emap : ElevationMap
        The map.
    path : str or os.PathLike
        Target file (any name; no suffix is added).
    """
    emap = _check_map(emap)
    g = emap.geometry
    arrays = {
        "format": np.array(FORMAT_TAG),
        "layers": np.array(json.dumps(list(LAYERS))),
        "data": np.ascontiguousarray(emap.data, dtype=np.float64),
        "n": np.array(g.n, dtype=np.int64),
        "resolution_m": np.array(g.resolution_m, dtype=np.float64),
        "gx0": np.array(g.gx0, dtype=np.int64),
        "gy0": np.array(g.gy0, dtype=np.int64),
        "fusion_params": np.array(json.dumps(dataclasses.asdict(emap.fusion_params))),
        "settings": np.array(json.dumps({"visibility_cleanup": bool(emap.visibility_cleanup),
                                         "cleanup_stride": int(emap.cleanup_stride)})),
        "frames": np.array(int(emap.frames), dtype=np.int64),
        "last_stamp": np.array(float(emap.last_stamp), dtype=np.float64),
    }
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as f:           # a file object: np.savez then adds no ".npz" suffix
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())


def load(path) -> ElevationMap:
    """Read a map written by :func:`save`; the round trip is bit-exact.

    Parameters
    ----------
    path : str or os.PathLike
        The file.

    Returns
    -------
    ElevationMap
        The map, with its data, geometry, fusion parameters, settings, frame count and last stamp.

    Raises
    ------
    FileNotFoundError
        If there is no such file.
    ValueError
        If the file is truncated or corrupt, not an elevmap map, of another format version, or lacks
        a key; the message names the file and the problem.
    """
    return _load(path, ElevationMap)


class _FileProblem(ValueError):
    """A ValueError that already names the file."""


def _load(path, cls):
    path = Path(path)

    def bad(problem: str) -> ValueError:
        return _FileProblem(f"{path}: {problem}")

    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        with open(path, "rb") as f:
            magic = f.read(6)
        if not magic:
            raise bad("empty file (truncated?)")
        if magic.startswith(b"\x93NUMPY"):
            raise bad("not an .npz archive but a single .npy array")
        if not magic.startswith(b"PK"):
            raise bad("not an .npz archive (no zip signature): corrupt, or not an elevmap map file")
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise bad("not an .npz archive")
        with z:
            present = set(z.files)
            if "format" not in present:
                raise bad(f"no 'format' tag: not an elevmap map file (expected {FORMAT_TAG!r})")
            arrays = {k: z[k] for k in _KEYS if k in present}      # reads (and CRC-checks) every member
    except (_FileProblem, FileNotFoundError, IsADirectoryError, PermissionError):
        raise
    except Exception as e:                      # zipfile.BadZipFile, EOFError, OSError, zlib errors, ...
        raise bad(f"truncated or corrupt ({type(e).__name__}: {e})") from e

    tag = arrays["format"]
    if tag.dtype.kind != "U" or tag.shape != () or str(tag) != FORMAT_TAG:
        raise bad(f"format tag is {tag!r}, expected {FORMAT_TAG!r}")
    missing = [k for k in _KEYS if k not in arrays]
    if missing:
        raise bad(f"missing key(s) {', '.join(missing)}")

    def text(key):
        a = arrays[key]
        if a.dtype.kind != "U" or a.shape != ():
            raise bad(f"{key} must be a string, got dtype {a.dtype} shape {a.shape}")
        try:
            return json.loads(str(a))
        except json.JSONDecodeError as e:
            raise bad(f"{key} is not valid JSON ({e})") from None

    def scalar(key, kind):
        a = arrays[key]
        if a.shape != () or a.dtype.kind not in kind:
            raise bad(f"{key} must be a scalar of kind {kind!r}, got dtype {a.dtype} shape {a.shape}")
        return a[()]

    names = text("layers")
    if names not in (list(LAYERS), list(LAYERS_V1), list(LAYERS_V2)):
        raise bad(f"layers {names} do not match this version's {list(LAYERS)}")
    n = int(scalar("n", "iu"))
    res = float(scalar("resolution_m", "f"))
    gx0, gy0 = int(scalar("gx0", "iu")), int(scalar("gy0", "iu"))
    frames = int(scalar("frames", "iu"))
    last_stamp = float(scalar("last_stamp", "f"))
    if n < 1 or not (math.isfinite(res) and res > 0):
        raise bad(f"bad geometry n={n}, resolution_m={res}")
    data = arrays["data"]
    if data.shape != (len(names), n, n) or data.dtype != np.float64:
        raise bad(f"data must be float64 of shape {(len(names), n, n)}, got {data.dtype} {data.shape}")
    if len(names) < len(LAYERS):         # a map saved before the spread layers: no spread seen yet
        extra = np.empty((len(LAYERS) - len(names), n, n))
        extra[:] = np.array(UNKNOWN_VALUES[len(names):])[:, None, None]
        known = np.isfinite(data[LAYERS.index("elevation")])
        for name in ("spread", "neighbour_spread"):
            if LAYERS.index(name) >= len(names):
                extra[LAYERS.index(name) - len(names)][known] = 0.0
        data = np.concatenate([data, extra])
    params = text("fusion_params")
    settings = text("settings")
    try:
        fp = FusionParams(**params)
        emap = cls(n * res, res, fusion_params=fp, visibility_cleanup=bool(settings["visibility_cleanup"]),
                   cleanup_stride=int(settings["cleanup_stride"]))
    except (TypeError, KeyError, ValueError) as e:
        raise bad(f"bad parameters ({type(e).__name__}: {e})") from None
    if emap.geometry.n != n:
        raise bad(f"cannot rebuild a {n} x {n} window at {res} m")
    emap.geometry = GridGeometry(n, res, gx0, gy0)
    emap.data[...] = data
    emap.frames = frames
    emap.last_stamp = last_stamp
    return emap
