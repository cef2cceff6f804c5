"""Argument checks shared by the simulator's modules (scene, ray caster, noise, walks).

Each raises ValueError naming the argument and the bad value, like :mod:`noise_model.checks`; these
are the simulator's own rules (coordinates beyond :data:`_LIMIT_M` are taken for a units mistake,
images of 1 to 16384 px a side, randomness only from a seeded ``numpy.random.Generator``).
"""

from __future__ import annotations

import math

import numpy as np

_LIMIT_M = 1.0e4          # coordinates and sizes beyond this are taken for a units mistake


def _vector(value, n_allowed, name: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numbers, got {value!r}") from None
    if a.ndim != 1 or a.shape[0] not in n_allowed:
        raise ValueError(f"{name} must have {' or '.join(map(str, n_allowed))} components, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} has non-finite entries: {a.tolist()}")
    if float(np.abs(a).max(initial=0.0)) > _LIMIT_M:
        raise ValueError(f"{name} = {a.tolist()} is implausibly far (> {_LIMIT_M:g} m); check its units")
    return a


def _finite(value, name: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise ValueError(f"{name} must be finite, got {x!r}")
    return x


def _start3(start, name: str) -> np.ndarray:
    a = _vector(start, (2, 3), name)
    return np.array([a[0], a[1], 0.0 if a.shape[0] == 2 else a[2]])


def _rng(rng) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator (seed it: np.random.default_rng(seed))")
    return rng


def _image_size(width, height) -> tuple[int, int]:
    out = []
    for value, name in ((width, "width"), (height, "height")):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise ValueError(f"{name} must be an integer number of pixels, got {value!r}")
        if not 1 <= int(value) <= 16384:
            raise ValueError(f"{name} must be in [1, 16384] px, got {value}")
        out.append(int(value))
    return out[0], out[1]
