"""A physical Intel RealSense D435: active-stereo simulation in which the depth noise emerges.

Instead of drawing noise from a formula, the D435 is rebuilt stage by stage: the scene's surfaces
(:mod:`.materials`) lit by the fixed pseudo-random dot pattern of the projector (:mod:`.projector`),
seen by two rectified infrared imagers 50 mm apart with lens blur, pixel integration, auto exposure,
laser speckle, shot and read noise and 8-bit output (:mod:`.imagers`), and matched as the D4 ASIC
does by default: census cost averaged over a box (:mod:`.census`), semi-global aggregation
(:mod:`.sgm`), winner-take-all over 126 disparities with 1/32-px subpixel, second-peak, texture and
left-right tests and small-segment removal, then z = f B / d in 1 mm units (:mod:`.matcher`).
:class:`StereoD435` (:mod:`.pipeline`) chains them: scene and pose in, uint16 depth out. A scene's
primitives may carry their own infrared ``material`` (:mod:`noise_model.sim.scene`); the camera's
:class:`MaterialMap` covers the rest.

Every numba kernel has a NumPy reference beside it (``*_reference``), and results do not depend on
the thread count. The model's parameters, their sources and its validation against real D435 data
are in docs/physical-d435.md.
"""

from .materials import MaterialMap, Texture, Uniform, as_material, carpet, concrete, white_wall
from .matcher import D435_DEPTH_SIZES, PRESETS, MatcherParams, MatchResult, disparity_to_depth, match
from .imagers import Exposure, ImagerModel
from .pipeline import IRFrame, IRScene, StereoD435
from .projector import DotPattern, Projector, ProjectorView

__all__ = [
    "StereoD435", "IRScene", "IRFrame", "DotPattern", "Projector", "ProjectorView", "ImagerModel", "Exposure",
    "MaterialMap", "Uniform", "Texture", "as_material", "concrete", "carpet", "white_wall", "MatcherParams",
    "MatchResult", "PRESETS", "D435_DEPTH_SIZES", "match", "disparity_to_depth",
]
