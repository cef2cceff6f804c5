"""The registry record of one effect's fit: :class:`FitSpec`, and the capture kinds a fit uses.

Each fit family module (:mod:`.disparity`, :mod:`.coverage`, :mod:`.correlation`, :mod:`.edges`,
:mod:`.residuals`) ends with ``SPECS``, one record per effect; :mod:`noise_model.analysis.effect_fits`
collects them. The forward model of the same effect has its own record,
:class:`noise_model.sim.effects.EffectSpec`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

__all__ = ["FitSpec", "CAPTURE_KINDS", "capture_kinds", "select_captures"]

#: Kinds of capture a fit can use: "wall" (a wall, all of it but the left band), "board" (a board's
#: interior), "board+background" (a board before a background wall: its left and right edges).
CAPTURE_KINDS = ("wall", "board", "board+background")


def _frozen(table: Mapping) -> Mapping:
    return MappingProxyType({k: tuple(v) for k, v in dict(table).items()})


@dataclass(frozen=True)
class FitSpec:
    """How one effect's parameters are fitted and how well (immutable).

    Attributes
    ----------
    name : str
        The effect's identifier (:data:`noise_model.sim.effects.EFFECTS`).
    fit : callable
        ``fit(real, base, model, *, base_effects, seed, cache, rois) -> dict`` of parameters: ``real``
        the usable captures, ``base`` their base simulations (same order), see
        :func:`noise_model.analysis.effect_fits.fit_effect`.
    needs : tuple of str
        Capture kinds (:data:`CAPTURE_KINDS`) the fit uses; it uses every capture of these kinds.
    tolerance : mapping of str to (str, float)
        Parameter -> ("abs", x): |fit - true| <= x, or ("rel", x): |fit - true| <= x |true|; how close
        the fit recovers the parameter on multi-frame captures like the gap self-test's.
    tolerance_single_frame : mapping of str to (str, float)
        The same on captures of a single frame each.
    """

    name: str
    fit: Callable
    needs: tuple
    tolerance: Mapping
    tolerance_single_frame: Mapping

    def __post_init__(self):
        needs = tuple(self.needs)
        bad = set(needs) - set(CAPTURE_KINDS)
        if bad:
            raise ValueError(f"fit of {self.name}: unknown capture kinds {sorted(bad)}; known: {CAPTURE_KINDS}")
        object.__setattr__(self, "needs", needs)
        object.__setattr__(self, "tolerance", _frozen(self.tolerance))
        object.__setattr__(self, "tolerance_single_frame", _frozen(self.tolerance_single_frame))


def capture_kinds(geometry) -> set:
    """The kinds (:data:`CAPTURE_KINDS`) a capture geometry provides: a board before a background
    provides both its interior ("board") and its edges ("board+background")."""
    if geometry.kind == "wall":
        return {"wall"}
    return {"board", "board+background"} if geometry.background_m is not None else {"board"}


def select_captures(needs: Sequence[str], captures: Sequence) -> list:
    """The captures (CaptureData or CaptureGeometry) that provide one of the kinds ``needs``, in order."""
    return [c for c in captures if capture_kinds(getattr(c, "geometry", c)) & set(needs)]
