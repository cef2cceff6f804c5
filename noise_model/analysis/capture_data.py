"""Capture data for the sim-to-real gap diagnosis: a capture's geometry, its frames, its simulation.

A capture (docs/capture-set-format.md, format ``d435-captures/1``) is a planar target (a wall, or a
board before an optional fronto-parallel background wall) recorded for N frames by a camera on a
tripod. This module holds, without any I/O (the readers live in ``elevmap.sources.captures``):

* :class:`CaptureGeometry` (from :mod:`noise_model.sim.targets`, where it is rendered and simulated):
  the camera intrinsics K [px], image size, depth scale [m/unit], baseline [m] and the target, built
  from the dicts of ``captures.json``, with its pixel *regions* and their codes ``REGION_*``.
* :class:`CaptureData`: a geometry and its frames as metric depth (F, H, W) [m], NaN = no data.
* :func:`simulate_capture`: the reference simulation of a capture
  (:func:`noise_model.sim.targets.simulate_target`), with the capture's id and regions in the
  context of the effects.

Frames: camera x right, y down, z forward; depth is z (along the optical axis), not ray length.
Pixel (u, v) = (column, row), 0-based, integer coordinates at pixel centres.

Effect context
--------------
:func:`simulate_capture` calls each effect as ``effect(z, theta, rng, context)`` with ``context``:
``K`` (3, 3) [px], ``width``, ``height`` [px], ``index`` (frame index), ``depth_scale`` [m/unit],
``z_true`` (H, W) [m] (this frame's, read only; boards move their edges each frame), ``baseline_m``
[m], ``capture_id`` (str), ``regions`` (H, W) int8 (the nominal regions, read only) and ``z_ref``
(H, W) [m] (the depth after the reference noise, before any effect; read only).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..d435 import D435, SensorModel
from ..sim.targets import (
    EDGE_PX_424, LATERAL_EDGE_SIGMAS, LEFT_BAND_MARGIN_PX_424, REGION_BACKGROUND, REGION_EDGE_LEFT, REGION_EDGE_RIGHT,
    REGION_INTERIOR, REGION_LEFT_BAND, REGION_NAMES, REGION_NONE, CaptureGeometry, simulate_target,
)

__all__ = ["CaptureGeometry", "CaptureData", "simulate_capture", "check_captures", "REGION_NONE", "REGION_INTERIOR",
           "REGION_EDGE_LEFT", "REGION_EDGE_RIGHT", "REGION_LEFT_BAND", "REGION_BACKGROUND", "REGION_NAMES",
           "LEFT_BAND_MARGIN_PX_424", "EDGE_PX_424", "LATERAL_EDGE_SIGMAS"]


@dataclass
class CaptureData:
    """A capture's geometry and frames.

    Attributes
    ----------
    geometry : CaptureGeometry
    depth_m : ndarray, shape (F, H, W), float64
        Metric z-depth [m]; NaN = no data.
    """

    geometry: CaptureGeometry
    depth_m: np.ndarray

    def __post_init__(self):
        if not isinstance(self.geometry, CaptureGeometry):
            raise ValueError(f"geometry must be a CaptureGeometry, got {type(self.geometry).__name__}")
        g = self.geometry
        d = np.asarray(self.depth_m)
        if d.ndim != 3 or d.shape[1:] != (g.height, g.width) or d.shape[0] < 1:
            raise ValueError(f"{g.id}: depth_m must have shape (frames >= 1, {g.height}, {g.width}), got {d.shape}")
        if not np.issubdtype(d.dtype, np.floating):
            raise ValueError(f"{g.id}: depth_m must be floating-point metres (NaN = no data), got dtype {d.dtype}")
        d = d.astype(np.float64, copy=False)
        if np.isinf(d).any():
            raise ValueError(f"{g.id}: depth_m has infinite values (no data must be NaN)")
        with np.errstate(invalid="ignore"):
            if (d <= 0).any():
                raise ValueError(f"{g.id}: depth_m has values <= 0 (no data must be NaN)")
            top = np.nanmax(d) if np.isfinite(d).any() else 0.0
        if top > 100.0:
            raise ValueError(f"{g.id}: depth_m holds values up to {top:.1f}: depth must be in metres")
        self.depth_m = d

    @property
    def id(self) -> str:
        return self.geometry.id

    @property
    def n_frames(self) -> int:
        return int(self.depth_m.shape[0])

    @classmethod
    def from_units(cls, geometry: CaptureGeometry, depth_units: np.ndarray) -> "CaptureData":
        """Frames from depth units: depth_m = units * depth_scale, 0 -> NaN.

        Parameters
        ----------
        geometry : CaptureGeometry
        depth_units : ndarray, shape (F, H, W) or (H, W), unsigned or signed integers
            Depth units of ``geometry.depth_scale`` (uint16 as recorded); 0 = no data.
        """
        if not isinstance(geometry, CaptureGeometry):
            raise ValueError(f"geometry must be a CaptureGeometry, got {type(geometry).__name__}")
        a = np.asarray(depth_units)
        if not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"{geometry.id}: depth units must be integers (uint16), got dtype {a.dtype}")
        if a.ndim == 2:
            a = a[None]
        if a.ndim != 3 or a.shape[1:] != (geometry.height, geometry.width):
            raise ValueError(f"{geometry.id}: depth units must have shape (frames, {geometry.height}, "
                             f"{geometry.width}), got {np.asarray(depth_units).shape}")
        if a.size and int(a.min()) < 0:
            raise ValueError(f"{geometry.id}: depth units must be >= 0, got {int(a.min())}")
        d = a.astype(np.float64) * geometry.depth_scale
        d[a == 0] = np.nan
        return cls(geometry, d)



def check_captures(captures, name: str = "real", *, allow_empty: bool = False) -> list:
    """Validate real captures: a CaptureData or a sequence of them, with distinct ids.

    Returns
    -------
    list of CaptureData

    Raises
    ------
    ValueError
        An item is not a CaptureData, two share an id, or (unless ``allow_empty``) there is none.
    """
    items = [captures] if isinstance(captures, CaptureData) else list(captures)
    if not items and not allow_empty:
        raise ValueError(f"no {name} captures")
    for k, c in enumerate(items):
        if not isinstance(c, CaptureData):
            raise ValueError(f"{name}[{k}] must be a noise_model.analysis.capture_data.CaptureData, "
                             f"got {type(c).__name__}")
    ids = [c.id for c in items]
    if len(set(ids)) != len(ids):
        raise ValueError(f"{name} captures must have distinct ids")
    return items



def simulate_capture(geometry: CaptureGeometry, n_frames: int, rng: np.random.Generator, model: SensorModel = D435,
                     effects=()) -> np.ndarray:
    """The reference simulation of a capture, plus effects; uint16 depth units (F, H, W).

    :func:`noise_model.sim.targets.simulate_target` (same draws, same far-pixel rule) with the
    capture's ``capture_id`` and nominal ``regions`` (``geometry.regions(model=model)``, read only)
    added to the effects' context (see the module docstring).

    Parameters
    ----------
    geometry : CaptureGeometry
    n_frames : int
        Frames, >= 1.
    rng : numpy.random.Generator
        The only source of randomness (effects draw from it too).
    model : SensorModel
        Axial and lateral noise of the reference simulation (the paper's D435 by default).
    effects : sequence of callables
        ``effect(z, theta, rng, context) -> z`` (:mod:`noise_model.sim.effects`), applied in the order given.

    Returns
    -------
    ndarray, shape (n_frames, height, width), uint16
    """
    effects = tuple(effects or ())
    context = None
    if effects and isinstance(geometry, CaptureGeometry) and isinstance(model, SensorModel):
        regions = geometry.regions(model=model)
        regions.flags.writeable = False
        context = {"capture_id": geometry.id, "regions": regions}
    return simulate_target(geometry, n_frames, rng, model, effects, context)
