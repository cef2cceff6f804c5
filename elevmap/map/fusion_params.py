"""The measurement update's settings (:class:`FusionParams`) and the check of a frame's error description.

Apart from :mod:`elevmap.map.fusion` so that a user reading or writing a map's settings (a config file, a
saved map, ``elevmap compare --set``) finds them without the kernels; the fusion packs them for its kernels
with :meth:`FusionParams.array`. What each rule does and why its default: docs/fusion.md; the figures
behind the defaults: docs/calibration.md.
"""

from __future__ import annotations

import warnings
from dataclasses import InitVar, dataclass
from statistics import NormalDist

import numpy as np

from .neighbours import ESTIMATORS
from .settings import check_bool, check_int, check_real

__all__ = ["FusionParams", "REMOVED_PARAMS", "check_frame_error"]

#: Settings that earlier versions had and that no longer exist, with why: a config file or a saved map
#: naming one is read with a ``FutureWarning`` (which Python shows to the command line's users, unlike a
#: ``DeprecationWarning``) and the setting is ignored; a value of the wrong type is still an error.
REMOVED_PARAMS = {
    "scatter_inflation": "dividing a frame's information in a cell by the reduced chi-square of its points changed "
                         "no score on the paper's reference nor on the physical D435: the spreads cover what it "
                         "guarded against (docs/fusion.md)",
}


@dataclass(frozen=True)
class FusionParams:
    """Parameters of the measurement update (module docstring; docs/fusion.md; the defaults' figures are
    in docs/calibration.md).

    Attributes
    ----------
    mahalanobis_threshold : float
        Gate on |z - h| / sqrt(sigma^2 + P) [-].
    min_variance, max_variance : float
        Clamp of the cell variance [m^2]. Above ``max_variance`` a cell becomes unknown: 0.04 (sigma
        20 cm) by default, a consumer's "no height rather than one that uncertain" (``elevmap compare``
        runs every mapper with 1, elevation_mapping_cupy's, so that the ceiling does not decide which
        cells each noise model is scored on; ANYbotics' code uses 9e-4). The floor, (1 mm)^2 (the
        D435's depth unit), is what a D435 can say about the height at a 4 cm cell's centre however
        many points it fuses: without one a cell of many precise near-range points claims a fraction of
        a millimetre. The neighbourhood spread covers binning errors, so the floor need not (ANYbotics'
        default is (3 mm)^2). A user whose real D435 adds calibration error the simulation lacks should
        raise it (``elevmap gap`` fits a depth bias and a static pattern among its effects).
    min_horizontal_variance : float or None
        Floor of the horizontal variances [m^2]; (resolution / 2)^2 when None (as ANYbotics).
    max_horizontal_variance : float
        Ceiling of the horizontal variances [m^2].
    change_min_points : int
        Rejected points needed (and more than accepted) before a cell is taken to have changed.
    max_points_per_frame : float or None
        The information cap n_eff (None: off).
    spread_alpha : float or None
        Significance level of the spread test: a cell's points scatter about its height more than
        their modelled noise allows (chi-square above its 1 - spread_alpha quantile) -> tau^2 > 0
        (DerSimonian-Laird), added to the cell's variance. 0.5 (default): the plain DerSimonian-Laird
        estimator, any excess counts; smaller: only a significant excess. None: no spread (tau^2 = 0).
    spread_ratio : float
        The spread counts only where a cell's points scatter about its height more than
        ``spread_ratio`` times their modelled variance (reduced chi-square Q / (n - 1)): a second
        surface in the cell, points bled over an edge. Below, the excess is the noise model
        misjudging its own sigma (the estimated incidence angle's error, unmodelled effects): it
        averages out in the cell's mean, and adding it as tau^2 makes such cells' sigma several times
        too large. 20 by default, where the simulated walks' mean NLL has levelled off; 1: any
        significant excess counts.
    neighbour_radius : int
        Half-width [cells] of the neighbourhood whose disagreement is added to a cell's variance
        (``neighbour_spread``, see :mod:`elevmap.map.neighbours`); 0: off. 4 (a 9 x 9 window, 0.36 m at
        4 cm) by default. The heights depend on it only through the weights of later points (the
        module docstring).
    neighbour_estimator : {"paule_mandel", "dersimonian_laird"}
        The estimator of the neighbourhood spread (:mod:`elevmap.map.neighbours`): Paule-Mandel (default),
        or DerSimonian-Laird, which its weights 1 / P make the precise cells' alone.
    min_points : int
        Points a cell must have fused (``points`` layer) before it is reported: below, the map keeps and
        fuses it but :meth:`ElevationMap.is_known`, the queries, the exports, the fused map and the scores
        treat it as unknown. A cell one or two pixels have seen holds a tail draw or a sliver of a
        neighbouring level as often as not. 3 by default; 1 reports every fused cell.
    scatter_inflation : bool, optional
        Removed (:data:`REMOVED_PARAMS`): accepted for old config files and saved maps, with a
        ``FutureWarning``, and ignored.
    """

    mahalanobis_threshold: float = 2.5
    min_variance: float = 1e-6
    max_variance: float = 0.04
    min_horizontal_variance: float | None = None
    max_horizontal_variance: float = 0.5
    change_min_points: int = 3
    max_points_per_frame: float | None = None
    spread_alpha: float | None = 0.5
    spread_ratio: float = 20.0
    neighbour_radius: int = 4
    neighbour_estimator: str = "paule_mandel"
    min_points: int = 3
    scatter_inflation: InitVar[bool | None] = None

    def __post_init__(self, scatter_inflation=None):
        if scatter_inflation is not None:
            check_bool(scatter_inflation, "scatter_inflation")
            warnings.warn("FusionParams: scatter_inflation was removed and is ignored "
                          f"({REMOVED_PARAMS['scatter_inflation']})", FutureWarning, stacklevel=3)
        for name in ("mahalanobis_threshold", "min_variance", "max_variance", "max_horizontal_variance"):
            check_real(getattr(self, name), name, 0.0, lo_open=True)
        if self.min_variance >= self.max_variance:
            raise ValueError("min_variance must be below max_variance")
        if self.min_horizontal_variance is not None:
            check_real(self.min_horizontal_variance, "min_horizontal_variance", 0.0, lo_open=True)
        check_int(self.change_min_points, "change_min_points", 1)
        if self.max_points_per_frame is not None:
            check_real(self.max_points_per_frame, "max_points_per_frame (None or a number)", 1.0)
        if self.spread_alpha is not None:
            check_real(self.spread_alpha, "spread_alpha (None or a number)", 1e-12, 0.5)
        check_real(self.spread_ratio, "spread_ratio", 1.0, 1e6)
        check_int(self.neighbour_radius, "neighbour_radius [cells]", 0, 10)
        if self.neighbour_estimator not in ESTIMATORS:
            raise ValueError(f"neighbour_estimator must be one of {ESTIMATORS}, got {self.neighbour_estimator!r}")
        check_int(self.min_points, "min_points", 1, 10000)

    def array(self, resolution_m: float, frame_error=None) -> np.ndarray:
        """Packed for the kernels: thr, min_var, max_var, min_hvar, max_hvar, change_min, cap (0 = off),
        spread z (normal quantile of 1 - spread_alpha; -1 = off), spread ratio, and the frame's error
        correlation length l [px] (0 = none) and variance ratio r (1 = none) from ``frame_error`` = (l, r)
        (module docstring; None: (0, 1))."""
        min_h = (resolution_m / 2) ** 2 if self.min_horizontal_variance is None else self.min_horizontal_variance
        ell, ratio = check_frame_error(frame_error)
        return np.array([self.mahalanobis_threshold, self.min_variance, self.max_variance, min_h,
                         self.max_horizontal_variance, float(self.change_min_points),
                         0.0 if self.max_points_per_frame is None else float(self.max_points_per_frame),
                         -1.0 if self.spread_alpha is None else NormalDist().inv_cdf(1.0 - self.spread_alpha),
                         float(self.spread_ratio), ell, ratio])


def check_frame_error(frame_error) -> tuple[float, float]:
    """(l [px], r) of a frame's error from ``frame_error`` = (l, r) or None ((0, 1)): l in [0, 1000], r in
    [1, 100], finite numbers; a ValueError naming what is wrong."""
    if frame_error is None:
        return 0.0, 1.0
    try:
        ell, ratio = frame_error
    except (TypeError, ValueError):
        raise ValueError(f"frame_error must be (correlation length [px], variance ratio), got {frame_error!r}") \
            from None
    return (check_real(ell, "frame_error correlation length", 0.0, 1000.0, unit=" px"),
            check_real(ratio, "frame_error variance ratio", 1.0, 100.0))
