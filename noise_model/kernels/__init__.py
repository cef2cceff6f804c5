"""The compiled depth -> map-points kernel of the mapper, in stages (see :mod:`noise_model.kernels.frame`).

Modules: ``frame`` (the public entries, the workspace, the NumPy reference), ``planes`` (block moments,
window planes, angles, mixed windows), ``surfaces`` (depth edges, speckles, row and surface medians),
``points`` (covariances and outputs), ``compiled`` (the formulas compiled, agreement of two depths, medians).
"""

from __future__ import annotations

from .frame import (
    MAX_COORDINATE_M, MAX_DEPTH_M, MAX_POINT_VARIANCE, MIN_DEPTH_M, MIN_HEIGHT_VARIANCE, NOISE_DEPTH_SIGMAS, STAGES,
    MapPoints, Workspace, depth_to_map_points, depth_to_map_points_by_stage, depth_to_map_points_reference,
)

__all__ = ["MAX_COORDINATE_M", "MAX_DEPTH_M", "MAX_POINT_VARIANCE", "MIN_DEPTH_M", "MIN_HEIGHT_VARIANCE",
           "NOISE_DEPTH_SIGMAS", "STAGES", "MapPoints", "Workspace", "depth_to_map_points",
           "depth_to_map_points_by_stage", "depth_to_map_points_reference"]
