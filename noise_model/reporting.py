"""What the analysis and the commands' reports share: strict-JSON copies and lists of names.

``noise_model`` cannot import ``elevmap``, so the helpers that both the library half of a diagnosis
(:mod:`noise_model.analysis.diagnosis`) and the commands (``elevmap.commands``) need live here.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["json_ready", "check_names"]


def json_ready(obj):
    """Strict-JSON copy of a report: NaN/inf -> None, NumPy scalars and arrays -> Python numbers and
    lists, tuples -> lists, paths -> str, dict keys -> str."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def check_names(spec, option: str, allowed=None, what: str = "name") -> list[str]:
    """A list of distinct names from a comma-separated string or a sequence (a command-line option).

    Parameters
    ----------
    spec : str or sequence of str
    option : str
        The option's name for messages, e.g. ``"--mappers"``.
    allowed : sequence of str, optional
        The names known; others are an error naming them.
    what : str
        What one name is, for messages ("mapper", "effect", "capture").

    Raises
    ------
    ValueError
        An empty entry, an unknown name, a name given twice.
    """
    if isinstance(spec, str):
        names = [s.strip() for s in spec.split(",")]
    else:
        try:
            names = [str(s).strip() for s in spec]
        except TypeError:
            raise ValueError(f"{option} must be comma-separated {what}s or a list of them, got {spec!r}") from None
    if not names or any(not n for n in names):
        hint = f" of {', '.join(allowed)}" if allowed is not None else ""
        raise ValueError(f"{option} {spec!r}: give comma-separated {what}s{hint}")
    if allowed is not None:
        for n in names:
            if n not in allowed:
                raise ValueError(f"unknown {what} {n!r}; {what}s: {', '.join(allowed)}")
    if len(set(names)) != len(names):
        raise ValueError(f"{option} {spec!r} names a {what} twice")
    return names
