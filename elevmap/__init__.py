"""elevmap: calibrated robot-centric elevation maps from Intel RealSense D435 depth.

Public API: :class:`ElevationMap` (the map), :class:`Mapper` and :class:`Camera` (depth frames ->
noise model -> map). The noise model itself is the separate package :mod:`noise_model`.
"""

from .map.elevation_map import ElevationMap
from .map.fusion import FusionParams
from .mapper import Camera, Mapper

__all__ = ["ElevationMap", "FusionParams", "Mapper", "Camera"]
__version__ = "0.1.0"
