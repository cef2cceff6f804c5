"""Registries of named factories: build an object by name from keyword parameters, checking both.

The depth effects (:data:`noise_model.sim.effects.EFFECTS`) and the alternative variance models
(:data:`noise_model.alternatives.VARIANCE_MODELS`) are registries: a mapping from a name to a factory
function whose keyword parameters are the object's parameters. :func:`build_from_registry` is the one
place that turns a name and a dict of parameters (from a command line or a JSON report) into an object,
with error messages that name what is unknown and list what is known.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping

__all__ = ["build_from_registry"]


def build_from_registry(registry: Mapping[str, Callable], kind: str, name: str, params: dict, hidden=()):
    """Call the factory ``registry[name](**params)``, checking the name and the parameter names.

    Parameters
    ----------
    registry : mapping of str to callable
        Name -> factory.
    kind : str
        What one entry is, for messages (e.g. "effect", "variance model").
    name : str
        The entry to build.
    params : dict
        Keyword parameters of the factory.
    hidden : sequence of str
        Factory parameters that are not the entry's own parameters (e.g. the reference ``model``): refused.

    Raises
    ------
    ValueError
        Naming the unknown ``kind`` or parameter and the known ones (or the factory's own ValueError).
    """
    if name not in registry:
        raise ValueError(f"unknown {kind} {name!r}; known: {', '.join(registry)}")
    allowed = set(inspect.signature(registry[name]).parameters) - set(hidden)
    bad = set(params) - allowed
    if bad:
        raise ValueError(f"{kind} {name!r} has no parameter(s) {sorted(bad)}; known: {sorted(allowed)}")
    return registry[name](**params)
