"""The registry record of one depth effect: :class:`EffectSpec`.

Each effect family module (:mod:`.disparity`, :mod:`.coverage`, :mod:`.correlation`, :mod:`.edges`,
:mod:`.residuals`) ends with ``SPECS``, one record per effect it defines; :mod:`noise_model.sim.effects`
collects them into the registry. Adding an effect means writing its forward model and factory and one
record here; the fit of its parameters has its own record,
:class:`noise_model.analysis.effect_fits.FitSpec`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

__all__ = ["EffectSpec"]


def _frozen(table: Mapping) -> Mapping:
    return MappingProxyType({k: tuple(v) for k, v in dict(table).items()})


@dataclass(frozen=True)
class EffectSpec:
    """One depth effect in the registry (immutable).

    Attributes
    ----------
    name : str
        The identifier (gap reports, ``--sim-effects``, ``make_effect``).
    factory : callable
        ``factory(**params) -> Effect``; its keyword parameters are the effect's parameters.
    order : int
        Rank in the device's composition order (:data:`noise_model.sim.effects.ORDER`, lowest first):
        effects are applied in this order in one frame.
    param_ranges : mapping of str to (float, float)
        Parameter -> (lo, hi), the range the gap self-test draws it from (uniformly; integers as
        integers): realistic D435 values in pixels of the 424 x 240 stream, strong enough to be seen.
    valid : mapping of str to (float, float)
        Real parameter -> (lo, hi) inside the factory's accepted range: a fitted estimate is clipped to
        it (an ill-determined parameter of an effect the data do not hold can leave the range).
    integer_params : mapping of str to (int, int)
        Integer parameter -> the factory's range (inclusive); draws are integers, estimates are rounded
        and clipped to it.
    """

    name: str
    factory: Callable
    order: int
    param_ranges: Mapping = field(default_factory=dict)
    valid: Mapping = field(default_factory=dict)
    integer_params: Mapping = field(default_factory=dict)

    def __post_init__(self):
        for attr in ("param_ranges", "valid", "integer_params"):
            object.__setattr__(self, attr, _frozen(getattr(self, attr)))
