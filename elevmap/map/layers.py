"""Names and indices of the elevation map's layers (one float64 array of shape (len(LAYERS), n, n))."""

from __future__ import annotations

from numba import njit

from noise_model.numba_config import JIT

__all__ = ["LAYERS", "ELEVATION", "VARIANCE", "MIN_HEIGHT", "MAX_HEIGHT", "HVAR_X", "HVAR_Y", "HVAR_XY", "TIME",
           "POINTS", "UPPER_BOUND", "SPREAD", "INFO_SUM", "INFO_SQ_SUM", "SCATTER", "NEIGHBOUR_SPREAD",
           "UNKNOWN_VALUES", "ZERO_WHEN_UNKNOWN", "LAYERS_V1", "LAYERS_V2"]

#: Layer names, in storage order. NaN means unknown in every layer but ``points`` and the three
#: sums behind ``spread`` (0 when unknown).
LAYERS = (
    "elevation",               # fused height of the cell [m], map frame
    "variance",                # variance of the true height at the cell's centre [m^2]: that of the
                               # fused mean plus the larger of ``spread`` and ``neighbour_spread``
    "min_height",              # lowest accepted point since the cell was last reset [m]
    "max_height",              # highest accepted point since the cell was last reset [m]
    "horizontal_variance_x",   # horizontal position uncertainty of the cell [m^2]
    "horizontal_variance_y",
    "horizontal_variance_xy",
    "time",                    # stamp of the last update [s]
    "points",                  # points fused since the cell was last reset [-]
    "upper_bound",             # free-space bound from visibility: the terrain is below it [m]
    "spread",                  # tau^2: variance of the cell's points about its height beyond their
                               # modelled noise (steps inside the cell, points displaced over an edge,
                               # unmodelled sensor effects) [m^2]; random-effects estimate, see fusion
    "info_sum",                # sum of 1/sigma_i^2 of the accepted points since the last reset [1/m^2]
    "info_sq_sum",             # sum of 1/sigma_i^4 [1/m^4]
    "scatter",                 # excess scatter Q - (n - 1), Q = sum (z_i - h)^2/sigma_i^2 over the points [-]
    "neighbour_spread",        # tau^2 of the cell's neighbourhood: the heights of the known cells within
                               # ``FusionParams.neighbour_radius`` scatter about their weighted mean more than
                               # their fused variances allow (points bled over an edge, a band of cells fed by
                               # far grazing pixels) [m^2]; random-effects estimate, see elevmap.map.neighbours
)
(ELEVATION, VARIANCE, MIN_HEIGHT, MAX_HEIGHT, HVAR_X, HVAR_Y, HVAR_XY, TIME, POINTS, UPPER_BOUND, SPREAD, INFO_SUM,
 INFO_SQ_SUM, SCATTER, NEIGHBOUR_SPREAD) = range(len(LAYERS))

#: Layers that are 0, not NaN, in an unknown cell (counts and sums).
ZERO_WHEN_UNKNOWN = ("points", "info_sum", "info_sq_sum", "scatter")

#: The value of each layer in an unknown cell.
UNKNOWN_VALUES = tuple(0.0 if name in ZERO_WHEN_UNKNOWN else float("nan") for name in LAYERS)

#: The layers of maps saved before ``spread`` existed (loaded with spread 0: no excess scatter).
LAYERS_V1 = LAYERS[:10]
#: The layers of maps saved before ``neighbour_spread`` existed (loaded with neighbour_spread 0).
LAYERS_V2 = LAYERS[:14]


def _clear_sums_py(data, bi, bj):
    """Set the counts and sums of cell (bi, bj) of ``data`` (len(LAYERS), n, n) to their unknown value, 0."""
    data[POINTS, bi, bj] = 0.0
    data[INFO_SUM, bi, bj] = 0.0
    data[INFO_SQ_SUM, bi, bj] = 0.0
    data[SCATTER, bi, bj] = 0.0


#: numba version of :func:`_clear_sums_py`, for the kernels that clear a cell (its other layers NaN).
clear_sums = njit(**JIT)(_clear_sums_py)
