"""The D435 simulator: scenes of primitives, numba ray casting, the reference noise, walks and targets.

It uses the sensor model of :mod:`noise_model` to draw noise; nothing in the model imports it. The
modules, in the order a frame is made:

* :mod:`.scene` -- primitives (:class:`Box`, :class:`Stairs`, :class:`Ramp`, :class:`Target`,
  :class:`HeightField`) and the :class:`Scene` they make, with its ground truth (``height_at``).
* :mod:`.render` -- the numba ray caster :func:`render_depth` and its NumPy reference
  :func:`render_depth_reference`: noise-free z-depth and incidence angle (and, on request, the
  primitive each pixel hit: :data:`HIT_GROUND`, :data:`HIT_NONE`).
* :mod:`.noise` -- :func:`add_noise`, the reference noise of the paper's model on one frame, and the
  hook through which depth effects are applied.
* :mod:`.walks` -- trajectories (:func:`walk`), odometry drift (:func:`odometry_drift`,
  :func:`camera_pose_cov`) and simulated walks (:func:`simulate_walk`) through a scene.
* :mod:`.targets` -- planar targets and floors seen from a posed camera (:func:`render_planar_target`,
  :func:`render_floor`, :func:`camera_extrinsics`), the capture geometry (:class:`CaptureGeometry`) and
  the one reference simulation of a planar target (:func:`simulate_target`, and
  :func:`simulate_target_frames` for a target given by its parameters); the same target seen by the
  physical D435 (:func:`simulate_target_stereo`).
* :mod:`.effects` -- depth effects the reference simulation leaves out, applied by the effects hook.
* :mod:`.stereo` -- the physical D435: projector dot pattern, infrared pair, census + semi-global
  matching; its noise emerges instead of being prescribed (docs/physical-d435.md). Imported on demand;
  chosen explicitly wherever the reference simulation is the default (``sensor="stereo"`` of
  :func:`simulate_walk`, :func:`simulate_target_stereo`). It reads the primitives' ``material``.
"""

from .noise import add_noise
from .render import HIT_GROUND, HIT_NONE, render_depth, render_depth_reference
from .scene import HF_BLOCK, Box, HeightField, Ramp, Scene, Stairs, Target
from .targets import (
    CaptureGeometry, camera_extrinsics, render_floor, render_planar_target, simulate_target, simulate_target_frames,
    simulate_target_stereo, target_rotation,
)
from .walks import DEFAULT_T_BASE_CAM, NOMINAL_BASE_HEIGHT_M, camera_pose_cov, odometry_drift, simulate_walk, walk

__all__ = [
    "Box", "Stairs", "Ramp", "HeightField", "Target", "Scene", "render_depth", "render_depth_reference",
    "add_noise", "walk", "odometry_drift", "camera_pose_cov", "simulate_walk", "NOMINAL_BASE_HEIGHT_M",
    "DEFAULT_T_BASE_CAM", "camera_extrinsics", "render_floor", "render_planar_target",
    "simulate_target_frames", "target_rotation", "CaptureGeometry", "simulate_target", "simulate_target_stereo",
    "HIT_GROUND", "HIT_NONE",
]
