"""The robot-centric 2.5-D elevation map: no I/O, no rerun, no progress bars.

* :mod:`.grid` -- the global lattice, the moving window and its circular buffer (:class:`GridGeometry`).
* :mod:`.layers` -- layer names, units and unknown values.
* :mod:`.fusion` -- per-cell information-form (Kalman) fusion of a frame's points (:class:`FusionParams`).
* :mod:`.neighbours` -- the neighbourhood spread (DerSimonian-Laird / Paule-Mandel).
* :mod:`.visibility` -- ray-cast clean-up of cells the sensor saw through.
* :mod:`.prediction` -- process noise from the robot's motion and the fused (ellipse-weighted) map.
* :mod:`.queries` -- height look-ups and height scans for a controller.
* :mod:`.grid_map` -- the map as the content of a ``grid_map_msgs/GridMap`` message.
* :mod:`.storage` -- map files (one ``.npz`` per map, ``elevmap-map/1``).
* :mod:`.elevation_map` -- :class:`ElevationMap`, the class that ties them together.
"""

from .elevation_map import ElevationMap
from .fusion import FusionParams
from .grid import GridGeometry

__all__ = ["ElevationMap", "FusionParams", "GridGeometry"]
