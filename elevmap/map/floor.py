"""The compute floor of a frame's fusion: plain information-form fusion, nothing else.

``elevmap bench`` times :func:`fuse_floor` next to :meth:`ElevationMap.update` on the same points, so that
the map's distance from what the hardware can do is a ratio measured side by side. It is the fusion of
docs/fusion.md stripped to its core: every point inside the window is summed into its cell, W = sum w_i
and WZ = sum w_i z_i with w_i = 1 / sigma_i^2, and combined with the cell's prior (h, P):

    P_post = 1 / (1/P + W),      h_post = P_post (h/P + WZ),

an unknown cell taking WZ / W and 1 / W. There is no input check, no gate, no spread, no change rule, no
variance bound, no horizontal covariance and no neighbourhood: a map built with it is not calibrated
(``tests/map/test_floor.py`` holds it to its equation, not to the map's rules).

Like the map's fusion, the points are cut into ``PARTIALS`` fixed contiguous ranges, each summed into its
own partial grid (reset lazily by a frame stamp), and merged per cell in a fixed order over the frame's
touched rows and columns, so the result does not depend on the thread count.
:func:`fuse_floor_reference` is the same update with NumPy (bincount).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from noise_model.numba_config import JIT, resolve_threads, threads

from .fusion import PARTIALS
from .layers import ELEVATION, VARIANCE

__all__ = ["FloorWorkspace", "fuse_floor", "fuse_floor_reference"]


class FloorWorkspace:
    """Partial grids of :func:`fuse_floor` (W, WZ per cell), kept across frames and reset lazily."""

    def __init__(self, n: int):
        self.n = int(n)
        self.acc = np.zeros((PARTIALS, self.n * self.n, 2))
        self.stamp = np.full((PARTIALS, self.n * self.n), -1, dtype=np.int64)
        self.frame = 0


@njit(parallel=True, **JIT)
def _floor_kernel(data, gx0, gy0, res, x, y, z, var, acc, acc_stamp, fid):
    n = data.shape[1]
    P = acc.shape[0]
    N = x.shape[0]
    sx = gx0 % n
    sy = gy0 % n
    box = np.empty((P, 4), dtype=np.int64)        # per partial: first and last map row and column touched
    for p in prange(P):
        a0 = b0 = n
        a1 = b1 = -1
        for k in range((N * p) // P, (N * (p + 1)) // P):
            fi = math.floor(x[k] / res) - gx0
            fj = math.floor(y[k] / res) - gy0
            if not (fi >= 0.0 and fi < n and fj >= 0.0 and fj < n):
                continue
            i = int(fi)
            j = int(fj)
            a0 = min(a0, i)
            a1 = max(a1, i)
            b0 = min(b0, j)
            b1 = max(b1, j)
            bi = i + sx
            if bi >= n:
                bi -= n
            bj = j + sy
            if bj >= n:
                bj -= n
            c = bi * n + bj
            if acc_stamp[p, c] != fid:
                acc_stamp[p, c] = fid
                acc[p, c, 0] = 0.0
                acc[p, c, 1] = 0.0
            w = 1.0 / var[k]
            acc[p, c, 0] += w
            acc[p, c, 1] += w * z[k]
        box[p, 0] = a0
        box[p, 1] = a1
        box[p, 2] = b0
        box[p, 3] = b1
    i0 = box[:, 0].min()
    i1 = box[:, 1].max()
    j0 = box[:, 2].min()
    j1 = box[:, 3].max()
    touched = 0
    for i in prange(i0, i1 + 1):
        bi = i + sx
        if bi >= n:
            bi -= n
        for j in range(j0, j1 + 1):
            bj = j + sy
            if bj >= n:
                bj -= n
            c = bi * n + bj
            W = 0.0
            WZ = 0.0
            seen = False
            for p in range(P):
                if acc_stamp[p, c] == fid:
                    seen = True
                    W += acc[p, c, 0]
                    WZ += acc[p, c, 1]
            if not seen:
                continue
            touched += 1
            h = data[ELEVATION, bi, bj]
            if np.isnan(h):
                v = 1.0 / W
                data[ELEVATION, bi, bj] = WZ * v
            else:
                ip = 1.0 / data[VARIANCE, bi, bj]
                v = 1.0 / (ip + W)
                data[ELEVATION, bi, bj] = (ip * h + WZ) * v
            data[VARIANCE, bi, bj] = v
    return touched


def _check_floor_shapes(data, geometry, points_map, height_var, workspace=None) -> None:
    """The shapes and dtypes the floor's kernel indexes by, checked in O(1) (the values stay unchecked: that
    is the floor's definition). Without it a short ``height_var`` or a workspace of another map size would
    be read or written out of bounds by the unchecked numba kernel."""
    n = geometry.n
    if not (isinstance(data, np.ndarray) and data.ndim == 3 and data.shape[1:] == (n, n)
            and data.dtype == np.float64):
        raise ValueError(f"data must be a float64 (layers, {n}, {n}) array of the geometry's map, got "
                         f"{getattr(data, 'dtype', type(data).__name__)} {getattr(data, 'shape', '')}")
    if not (isinstance(points_map, np.ndarray) and points_map.ndim == 2 and points_map.shape[1] == 3
            and points_map.dtype == np.float64):
        raise ValueError(f"points_map must be a float64 (N, 3) array [m], got "
                         f"{getattr(points_map, 'dtype', type(points_map).__name__)} {getattr(points_map, 'shape', '')}")
    if not (isinstance(height_var, np.ndarray) and height_var.shape == (points_map.shape[0],)
            and height_var.dtype == np.float64):
        raise ValueError(f"height_var must be a float64 array of shape ({points_map.shape[0]},) [m^2], got "
                         f"{getattr(height_var, 'dtype', type(height_var).__name__)} {getattr(height_var, 'shape', '')}")
    if workspace is not None and (not isinstance(workspace, FloorWorkspace) or workspace.n != n):
        raise ValueError(f"workspace must be a FloorWorkspace of the map's size n = {n}")


def fuse_floor(data, geometry, points_map, height_var, workspace: FloorWorkspace, nthreads=None) -> int:
    """Fuse one frame into the ``elevation`` and ``variance`` layers of ``data`` in place (numba).

    Parameters
    ----------
    data : ndarray, shape (len(LAYERS), n, n)
        The map's layers, buffer order (an :class:`ElevationMap`'s ``data``).
    geometry : elevmap.map.grid.GridGeometry
    points_map : ndarray, shape (N, 3), float64
        Map-frame points [m] (any memory layout). Shapes, dtypes and the workspace's size are checked
        (``ValueError``); the values are not: the floor does no per-point check.
    height_var : ndarray, shape (N,), float64
        Height variance of each point [m^2], > 0.
    workspace : FloorWorkspace
    nthreads : int, optional

    Returns
    -------
    int
        Cells touched.
    """
    _check_floor_shapes(data, geometry, points_map, height_var, workspace)
    n = resolve_threads(nthreads)
    workspace.frame += 1
    with threads(n):
        return int(_floor_kernel(data, geometry.gx0, geometry.gy0, geometry.resolution_m, points_map[:, 0],
                                 points_map[:, 1], points_map[:, 2], height_var, workspace.acc, workspace.stamp,
                                 workspace.frame))


def fuse_floor_reference(data, geometry, points_map, height_var) -> int:
    """NumPy reference of :func:`fuse_floor` (bincount), with the same checks."""
    _check_floor_shapes(data, geometry, points_map, height_var)
    g = geometry
    n = g.n
    fi = np.floor(points_map[:, 0] / g.resolution_m) - g.gx0
    fj = np.floor(points_map[:, 1] / g.resolution_m) - g.gy0
    inside = (fi >= 0) & (fi < n) & (fj >= 0) & (fj < n)
    bi = (fi[inside].astype(np.int64) + g.gx0) % n
    bj = (fj[inside].astype(np.int64) + g.gy0) % n
    c = bi * n + bj
    w = 1.0 / height_var[inside]
    W = np.bincount(c, weights=w, minlength=n * n)
    WZ = np.bincount(c, weights=w * points_map[inside, 2], minlength=n * n)
    seen = np.bincount(c, minlength=n * n) > 0
    h = data[ELEVATION].reshape(-1)          # views: writes go to data
    v = data[VARIANCE].reshape(-1)
    known = seen & ~np.isnan(h)
    new = seen & np.isnan(h)
    ip = 1.0 / v[known]
    v_post = 1.0 / (ip + W[known])
    h[known] = (ip * h[known] + WZ[known]) * v_post
    v[known] = v_post
    v[new] = 1.0 / W[new]
    h[new] = WZ[new] * v[new]
    return int(seen.sum())
