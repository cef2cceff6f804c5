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

__all__ = ["EffectSpec", "AXIAL_UNITS"]

#: The values of :attr:`EffectSpec.axial_units`.
AXIAL_UNITS = ("", "sets", "static", "temporal")


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
    axial_units : str
        How the effect relates to the axial sigma_z of the model it is added to (:data:`AXIAL_UNITS`): ""
        (sized in its own units), "sets" (it replaces that sigma_z: ``axial_refit``), "static" (a static
        field sized as a fraction of it: ``static_noise``), "temporal" (a per-frame field sized as a
        fraction of it, which takes a share of the temporal variance: ``correlated_noise``). The gap's
        backfitting refits such effects together
        (:func:`noise_model.analysis.diagnosis.selection.refit_pairs`).
    """

    name: str
    factory: Callable
    order: int
    param_ranges: Mapping = field(default_factory=dict)
    valid: Mapping = field(default_factory=dict)
    integer_params: Mapping = field(default_factory=dict)
    axial_units: str = ""

    def __post_init__(self):
        if self.axial_units not in AXIAL_UNITS:
            raise ValueError(f"EffectSpec {self.name!r}: axial_units must be one of {AXIAL_UNITS}, "
                             f"got {self.axial_units!r}")
        for attr in ("param_ranges", "valid", "integer_params"):
            object.__setattr__(self, attr, _frozen(getattr(self, attr)))
