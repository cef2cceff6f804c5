"""Visualisation: rerun recordings and matplotlib figures. Every ``rerun`` call that writes a recording
lives in this package; the maths never imports it.

* :mod:`.recording` -- recordings written atomically (:func:`open_recording`).
* :mod:`.log` -- the world: frames, cameras, depth, points, covariance ellipsoids, scalars, text,
  images, the height mesh.
* :mod:`.colors` -- colour scales (NumPy only).
* :mod:`.charts` -- static 2-D charts drawn with line strips.
* :mod:`.blueprints` -- viewer layouts of a mapping run and of a comparison.
* :mod:`.reports` -- the views of ``elevmap characterize`` and ``elevmap gap``.
* :mod:`.plots` -- PNG figures with matplotlib (not imported here: it loads matplotlib).

Importing this package imports rerun; the commands import it only when they write a recording.
"""

from __future__ import annotations

from .blueprints import compare_blueprint, default_blueprint
from .charts import PLOT_CANVAS, PLOT_VISUAL_BOUNDS, SERIES_COLORS, log_series_plot
from .colors import colormap, robust_range
from .log import (
    ellipsoid_parameters, log_camera, log_covariance_ellipsoids, log_depth, log_depth_png, log_exact, log_height_mesh,
    log_points, log_rgb_image, log_scalar, log_text, log_trail, log_transform, log_world_frame, map_image, set_time,
)
from .recording import AtomicRecording, open_recording
from .reports import (
    characterisation_blueprint, gap_bar_bounds, gap_blueprint, log_characterisation, log_gap_bars, log_gap_images,
)

__all__ = [
    "AtomicRecording",
    "open_recording",
    "log_world_frame",
    "log_transform",
    "log_camera",
    "log_depth",
    "log_points",
    "ellipsoid_parameters",
    "log_covariance_ellipsoids",
    "log_scalar",
    "set_time",
    "log_text",
    "log_series_plot",
    "colormap",
    "default_blueprint",
    "log_height_mesh",
    "log_trail",
    "log_exact",
    "log_depth_png",
    "robust_range",
    "PLOT_CANVAS",
    "PLOT_VISUAL_BOUNDS",
    "SERIES_COLORS",
    "log_rgb_image",
    "map_image",
    "compare_blueprint",
    "log_characterisation",
    "characterisation_blueprint",
    "log_gap_bars",
    "log_gap_images",
    "gap_blueprint",
    "gap_bar_bounds",
]
