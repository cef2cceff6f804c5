"""The Intel RealSense D435 noise model of Ahn et al. (2019) and its propagation into 3-D covariances.

Public API
----------
D435, SensorModel                       the paper's coefficients, geometry and default intrinsics
axial_sigma(z, theta)                   sigma_z [m]
expected_rms_error(z, ...)              the paper's equation (1) [m]
depth_to_metres, deproject              depth image -> metres -> camera-frame points
incidence_angles, depth_edges           theta per pixel; left/right depth-edge masks
despeckle                               pixels no neighbour agrees with: their neighbours' median
mixed_windows                           normal-estimation windows that hold more than one surface
row_medians                             per pixel, the median depth of its agreeing row neighbours
surface_depths                          median of agreeing row medians over 5 rows (binning; variance floor)
point_covariances                       (N, 3, 3) camera-frame covariances
to_map_frame                            (N, 3, 3) map-frame covariances with pose uncertainty
drop_valid_margin                       depth pixels within r columns of no data or the image's side dropped
depth_to_map_points                     the whole chain in six numba stages, three parallel regions (+ NumPy reference)
Scene, render_depth, add_noise          scenes of primitives, numba ray casting, the reference noise
walk, odometry_drift, simulate_walk     trajectories, odometry drift, simulated walks (noise_model.sim.walks)
alternatives                            other point-noise models for comparisons: constant, quadratic
                                        (elevation_mapping_cupy), anybotics_d435 (ANYbotics' D435 preset)
effects, correlated_noise, depth_bias   depth effects for the simulator's effects hook (EFFECTS by name)
stereo                                  the physical D435 (noise_model.sim.stereo: StereoD435, materials)

This package never imports ``elevmap``, rerun, pyrealsense2 or OpenCV.
"""

from .checks import (
    check_angles, check_covariances, check_depth, check_intrinsics, check_points, check_pose_cov,
    check_transform, check_transforms,
)
from .covariance import point_covariances, pose_jacobian, skew, to_map_frame
from .d435 import (
    D435, THETA_MAX_DEFAULT, THETA_QUADRATURE, SensorModel, axial_sigma, axial_variance, expected_rms_error,
)
from .geometry import (
    deproject, depth_edges, depth_to_metres, default_block_px, incidence_angle_stats, incidence_angles,
    despeckle, mixed_windows, row_medians, surface_depths,
)
from .valid_margin import DEFAULT_VALID_MARGIN_PX, drop_valid_margin, drop_valid_margin_reference
from . import kernels
from .kernels import MapPoints, Workspace, depth_to_map_points, depth_to_map_points_reference

# The simulator and the effects library load on first use (PEP 562), so that the map and the sensor
# model import without them: ``noise_model.Scene`` and ``from noise_model import effects`` still work.
_LAZY = {
    "alternatives": ("noise_model.alternatives", None),
    "sim": ("noise_model.sim", None),
    "effects": ("noise_model.sim.effects", None),
    "stereo": ("noise_model.sim.stereo", None),
    "scene": ("noise_model.sim", None),
    "analysis": ("noise_model.analysis", None),
    "EFFECTS": ("noise_model.sim.effects", "EFFECTS"),
    "correlated_noise": ("noise_model.sim.effects", "correlated_noise"),
    "depth_bias": ("noise_model.sim.effects", "depth_bias"),
    **{name: ("noise_model.sim", name) for name in (
        "Box", "HeightField", "Ramp", "Scene", "Stairs", "Target", "add_noise", "odometry_drift", "render_depth",
        "render_depth_reference", "simulate_walk", "walk")},
}


def __getattr__(name):
    try:
        module, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'noise_model' has no attribute {name!r}") from None
    import importlib

    value = importlib.import_module(module)
    if attr is not None:
        value = getattr(value, attr)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "D435",
    "SensorModel",
    "THETA_MAX_DEFAULT",
    "axial_sigma",
    "axial_variance",
    "THETA_QUADRATURE",
    "expected_rms_error",
    "depth_to_metres",
    "deproject",
    "incidence_angles",
    "incidence_angle_stats",
    "depth_edges",
    "despeckle",
    "mixed_windows",
    "row_medians",
    "surface_depths",
    "default_block_px",
    "point_covariances",
    "to_map_frame",
    "pose_jacobian",
    "skew",
    "DEFAULT_VALID_MARGIN_PX",
    "drop_valid_margin",
    "drop_valid_margin_reference",
    "MapPoints",
    "Workspace",
    "depth_to_map_points",
    "depth_to_map_points_reference",
    "check_angles",
    "check_covariances",
    "check_depth",
    "check_intrinsics",
    "check_points",
    "check_pose_cov",
    "check_transform",
    "Scene",
    "Box",
    "Stairs",
    "Ramp",
    "HeightField",
    "Target",
    "render_depth",
    "render_depth_reference",
    "add_noise",
    "walk",
    "odometry_drift",
    "simulate_walk",
    "alternatives",
    "effects",
    "EFFECTS",
    "correlated_noise",
    "depth_bias",
]
