"""Map files: one ``.npz`` archive per map, tagged ``elevmap-map/1``, written atomically.

:func:`save` stores the layers in buffer order with the geometry, the fusion parameters, the map's
settings, its frame count and last stamp; :func:`load` rebuilds the map bit for bit. No pickled
objects: strings are stored as unicode arrays, so a file can be read without running its code. Maps
saved before the ``spread`` and ``neighbour_spread`` layers existed (``LAYERS_V1``, ``LAYERS_V2``)
still load: the new layers start at 0 in known cells (no spread seen yet).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..fileio import atomic_output
from .fusion import FusionParams
from .grid import GridGeometry
from .layers import ELEVATION, LAYERS, LAYERS_V1, LAYERS_V2, UNKNOWN_VALUES, VARIANCE
from .queries import check_map
from .settings import MAX_COORDINATE_M

if TYPE_CHECKING:
    from .elevation_map import ElevationMap

__all__ = ["save", "load", "read_map", "FORMAT_TAG"]

#: Format tag of the files written by :func:`save`.
FORMAT_TAG = "elevmap-map/1"

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
    emap = check_map(emap)
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
    """Read a map written by :func:`save` (as :meth:`ElevationMap.load`); the round trip is bit-exact.

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
        If the file is truncated or corrupt, not an elevmap map, of another format version, lacks a key,
        or holds a map that breaks the map's invariants (an infinite value, a known cell without a finite
        variance > 0, negative counts or variances, a window beyond the coordinate bound); the message
        names the file and the problem.
    """
    from .elevation_map import ElevationMap      # not at the top: elevation_map imports this module

    return read_map(path, ElevationMap)


def _check_invariants(data: np.ndarray, bad) -> None:
    """What every map holds (the fusion keeps it; a file edited or corrupted past its CRC may not):
    no infinite value in any layer; a cell with a height has a finite variance > 0; counts and sums are
    finite and >= 0; spreads and horizontal variances are >= 0 where set."""
    for k, name in enumerate(LAYERS):
        if np.isinf(data[k]).any():
            raise bad(f"layer '{name}' holds {int(np.isinf(data[k]).sum())} infinite values")
    known = np.isfinite(data[ELEVATION])
    var = data[VARIANCE][known]
    if not (np.isfinite(var) & (var > 0)).all():
        worst = var[~(np.isfinite(var) & (var > 0))][0]
        raise bad(f"{int((~(np.isfinite(var) & (var > 0))).sum())} cells with a height have a variance that "
                  f"is not finite and > 0 (e.g. {worst!r} m^2)")
    for name in ("points", "info_sum", "info_sq_sum"):
        a = data[LAYERS.index(name)]
        if not (np.isfinite(a) & (a >= 0)).all():
            raise bad(f"layer '{name}' holds values that are not finite and >= 0")
    if not np.isfinite(data[LAYERS.index("scatter")]).all():
        raise bad("layer 'scatter' holds non-finite values")
    for name in ("variance", "spread", "neighbour_spread", "horizontal_variance_x", "horizontal_variance_y"):
        a = data[LAYERS.index(name)]
        if (a[np.isfinite(a)] < 0).any():
            raise bad(f"layer '{name}' holds negative variances")


class _FileProblem(ValueError):
    """A ValueError that already names the file."""


def read_map(path, cls):
    """Read a map written by :func:`save` into a new instance of ``cls`` (an :class:`ElevationMap` class).

    :meth:`ElevationMap.load` calls it with its own class, so that subclasses load as themselves.
    Errors as :func:`load`.
    """
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
    _check_invariants(data, bad)
    if frames < 0 or math.isinf(last_stamp):
        raise bad(f"frames = {frames} must be >= 0 and last_stamp = {last_stamp} finite (or NaN: no frame yet)")
    corner = max(abs(gx0), abs(gy0), abs(gx0 + n), abs(gy0 + n)) * res
    if corner > MAX_COORDINATE_M:
        raise bad(f"the window reaches {corner:.3g} m, beyond the {MAX_COORDINATE_M:.0e} m a map position may have")
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
