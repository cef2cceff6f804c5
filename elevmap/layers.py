"""Names and indices of the elevation map's layers (one float64 array of shape (len(LAYERS), n, n))."""

from __future__ import annotations

__all__ = ["LAYERS", "ELEVATION", "VARIANCE", "MIN_HEIGHT", "MAX_HEIGHT", "HVAR_X", "HVAR_Y", "HVAR_XY", "TIME",
           "POINTS", "UPPER_BOUND", "UNKNOWN_VALUES"]

#: Layer names, in storage order. NaN means unknown in every layer but ``points`` (0 when unknown).
LAYERS = (
    "elevation",               # fused height of the cell [m], map frame
    "variance",                # its variance [m^2]
    "min_height",              # lowest accepted point since the cell was last reset [m]
    "max_height",              # highest accepted point since the cell was last reset [m]
    "horizontal_variance_x",   # horizontal position uncertainty of the cell [m^2]
    "horizontal_variance_y",
    "horizontal_variance_xy",
    "time",                    # stamp of the last update [s]
    "points",                  # points fused since the cell was last reset [-]
    "upper_bound",             # free-space bound from visibility: the terrain is below it [m]
)
(ELEVATION, VARIANCE, MIN_HEIGHT, MAX_HEIGHT, HVAR_X, HVAR_Y, HVAR_XY, TIME, POINTS, UPPER_BOUND) = range(len(LAYERS))

#: The value of each layer in an unknown cell.
UNKNOWN_VALUES = tuple(0.0 if name == "points" else float("nan") for name in LAYERS)
