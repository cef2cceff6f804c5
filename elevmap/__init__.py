"""elevmap: calibrated robot-centric elevation maps from Intel RealSense D435 depth.

Public API:

* :class:`ElevationMap` (the map) with its :class:`FusionParams`;
* :class:`Mapper` and :class:`Camera`: depth frames -> noise model -> map;
* :func:`open_source` (any source of depth frames, see :mod:`elevmap.sources`), :func:`run_mapping`
  and :class:`MappingConfig`: the loop behind ``elevmap run``.

The noise model itself is the separate package :mod:`noise_model`. Names are imported on first use
(PEP 562), so ``import elevmap`` (and ``elevmap --help``) loads neither numba nor the map's kernels.

Subpackages: :mod:`elevmap.map` (the map core), :mod:`elevmap.sources` (depth frames in),
:mod:`elevmap.viz` (rerun and matplotlib out), :mod:`elevmap.commands` (one module per subcommand of
the ``elevmap`` command line, :mod:`elevmap.cli`).
"""

from __future__ import annotations

import importlib

#: Public name -> the module that defines it.
_NAMES = {
    "ElevationMap": ".map.elevation_map",
    "FusionParams": ".map.fusion",
    "Mapper": ".mapper",
    "Camera": ".mapper",
    "open_source": ".sources.open",
    "run_mapping": ".pipeline",
    "MappingConfig": ".pipeline",
}
#: Submodules reachable as attributes (``import elevmap; elevmap.map.queries``) as when they were eager.
_SUBMODULES = ("map", "mapper", "pipeline", "frame", "fileio", "sources", "viz", "commands", "cli")

__all__ = ["ElevationMap", "FusionParams", "Mapper", "Camera", "open_source", "run_mapping", "MappingConfig"]
__version__ = "0.1.0"


def __getattr__(name: str):
    if name in _NAMES:
        value = getattr(importlib.import_module(_NAMES[name], __name__), name)
    elif name in _SUBMODULES:
        value = importlib.import_module(f".{name}", __name__)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_NAMES))
