"""The map as a ``grid_map_msgs/GridMap`` message (ANYbotics' grid_map), without ROS.

:func:`to_grid_map` returns the message's content as plain Python and NumPy values: the layers as
float32 matrices in grid_map's index order and column-major layout, the geometry, the frame and the
stamp. A ROS node fills a ``GridMap`` message from it field by field.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .layers import LAYERS
from .queries import check_map

if TYPE_CHECKING:                      # for annotations only: elevation_map imports this module
    from .elevation_map import ElevationMap

__all__ = ["to_grid_map"]


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
        basic layers mark validity; ``time`` is exported relative to ``stamp`` (t - stamp [s], <= 0:
        float32 resolves a wall-clock stamp of ~1.7e9 s only to ~128 s, an age to milliseconds); the
        other layers are exported as stored.

    Raises
    ------
    ValueError
        For an unknown or repeated layer name.
    """
    emap = check_map(emap)
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
        elif name == "time":                             # relative to the stamp: float32 keeps ms precision
            m = m - emap.last_stamp
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
