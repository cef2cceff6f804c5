"""The D435 simulator: scenes of primitives, numba ray casting, the reference noise, walks and targets.

It uses the sensor model of :mod:`noise_model` to draw noise; nothing in the model imports it.

* :mod:`.scene` -- primitives (:class:`Box`, :class:`Stairs`, :class:`Ramp`, :class:`Target`,
  :class:`HeightField`), :class:`Scene`, the ray caster (:func:`render_depth` and its NumPy reference),
  the reference noise (:func:`add_noise`), walks (:func:`walk`, :func:`odometry_drift`,
  :func:`simulate_walk`).
* :mod:`.targets` -- planar targets and floors seen from a posed camera (:func:`render_planar_target`,
  :func:`render_floor`, :func:`camera_extrinsics`, :func:`simulate_target_frames`).
* :mod:`.effects` -- depth effects the reference simulation leaves out, applied by the effects hook.
"""

from .scene import (
    DEFAULT_T_BASE_CAM, NOMINAL_BASE_HEIGHT_M, Box, HeightField, Ramp, Scene, Stairs, Target, add_noise,
    camera_pose_cov, odometry_drift, render_depth, render_depth_reference, simulate_walk, walk,
)
from .targets import camera_extrinsics, render_floor, render_planar_target, simulate_target_frames, target_rotation

__all__ = [
    "Box", "Stairs", "Ramp", "HeightField", "Target", "Scene", "render_depth", "render_depth_reference",
    "add_noise", "walk", "odometry_drift", "camera_pose_cov", "simulate_walk", "NOMINAL_BASE_HEIGHT_M",
    "DEFAULT_T_BASE_CAM", "camera_extrinsics", "render_floor", "render_planar_target",
    "simulate_target_frames", "target_rotation",
]
