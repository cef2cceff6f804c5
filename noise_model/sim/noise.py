"""The reference noise of the paper's model on one noise-free frame, and the hook for depth effects.

The reference simulation (docs/capture-set-format.md, docs/noise-model.md), per pixel of one frame:

    z = z_true + sigma_z(z_true, theta) n,    n ~ N(0, 1) independent per pixel,

then ``effects`` in order (below), then ``round(z / depth_scale)`` as uint16 depth units, 0 (no data)
where there is no hit, z <= 0, z is not finite, or the value does not fit in a uint16 (> 65535 units:
a D435 cannot report it, so it is no data rather than a clipped 65535). ``model=None`` adds no noise
(only the quantisation). The standard normals are drawn for the whole image, one
``rng.normal(0, 1, (H, W))`` call per frame, so every caller that feeds the same renders consumes the
same draws: the planar targets (:func:`noise_model.sim.targets.simulate_target`) and the walks
(:func:`noise_model.sim.walks.simulate_walk`) both go through :func:`add_noise`.

Effect hook contract: ``effect(z, theta, rng, context) -> z``.

* ``z``: (H, W) float64, metric z-depth after the noise and the effects before, NaN = no data. The
  effect may modify it in place and return it, or return a new array.
* ``theta``: (H, W) float64 true incidence angles [rad], NaN where nothing is hit; read only.
* ``rng``: the simulation's ``numpy.random.Generator``; draw from it only (reproducibility).
* ``context``: dict with at least ``K`` (3, 3) [px], ``width``, ``height`` [px], ``index`` (frame
  number, 0 outside a walk), ``depth_scale`` [m/unit] and ``z_true`` (H, W) [m] (read only); with a
  ``model``, ``sigma_z`` (H, W) [m] (read only), the reference noise's standard deviation per pixel (0
  where nothing is hit), which an effect that refits the noise replaces for the effects after it;
  :func:`~noise_model.sim.walks.simulate_walk` adds ``stamp`` [s] and ``T_map_cam`` (true pose);
  :func:`~noise_model.sim.targets.simulate_target` adds ``baseline_m`` [m] and ``z_ref``.
* Must return an array of shape (H, W) (any float dtype); values <= 0 or NaN mean no data.
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

import numpy as np

from ..checks import check_positive_scalar
from ..d435 import D435, SensorModel, axial_sigma_unchecked
from ._checks import _rng

__all__ = ["PreparedNoise", "add_noise", "noisy_frame", "prepare_noise"]


def add_noise(z_true, theta, rng: np.random.Generator, model: SensorModel | None = D435,
              effects: Sequence[Callable] | None = None, depth_scale: float = 0.001,
              context: dict | None = None) -> np.ndarray:
    """A depth frame from a noise-free render: the reference simulation of the paper's model.

    Parameters
    ----------
    z_true : array_like, shape (H, W)
        Noise-free z-depth [m]; NaN = no hit.
    theta : array_like, shape (H, W)
        Incidence angle [rad], finite wherever z_true is.
    rng : numpy.random.Generator
        Source of all randomness (required).
    model : SensorModel or None
        Axial noise sigma_z(z_true, theta) of this model; None = no noise (only quantisation). A
        disparity-family model not bound to a focal length is bound to ``context['K'][0, 0]``.
    effects : sequence of callables, optional
        ``effect(z, theta, rng, context) -> z`` applied in order to the noisy metric depth before
        quantisation (contract in the module docstring).
    depth_scale : float
        Metres per depth unit (D435 default 0.001).
    context : dict, optional
        Extra context for the effects (``K``, ``index``, ...); ``width``, ``height``,
        ``depth_scale``, ``z_true`` are filled in; ``K`` defaults to None and ``index`` to 0.

    Returns
    -------
    ndarray, shape (H, W), uint16
        round(z / depth_scale); 0 = no data (no hit, z <= 0, not finite, or beyond 65535 units).
    """
    prepared = prepare_noise(z_true, theta, model, effects, depth_scale, context)
    return noisy_frame(prepared, rng, context)


class PreparedNoise(NamedTuple):
    """What :func:`add_noise` computes from a render before it draws: the checked inputs and sigma_z.

    A render that is the same in every frame (a wall) is prepared once and drawn many times
    (:func:`noisy_frame`), with the draws of :func:`add_noise` itself.
    """

    z_true: np.ndarray          # (H, W) float64 [m], NaN = no hit
    theta: np.ndarray           # (H, W) float64 [rad]
    sigma_z: np.ndarray | None  # (H, W) float64 [m], read only; None = no model
    effects: tuple
    depth_scale: float          # [m / unit]


def prepare_noise(z_true, theta, model: SensorModel | None = D435, effects: Sequence[Callable] | None = None,
                  depth_scale: float = 0.001, context: dict | None = None) -> PreparedNoise:
    """Check :func:`add_noise`'s inputs and compute sigma_z(z_true, theta) once (parameters as there)."""
    z_t = np.asarray(z_true)
    th = np.asarray(theta)
    if z_t.ndim != 2 or z_t.shape[0] < 1 or z_t.shape[1] < 1:
        raise ValueError(f"z_true must be a 2-D image (H, W), got shape {z_t.shape}")
    if not np.issubdtype(z_t.dtype, np.floating):
        raise ValueError(f"z_true must be floating-point metres (NaN = no hit), got dtype {z_t.dtype}")
    if th.shape != z_t.shape:
        raise ValueError(f"theta must have z_true's shape {z_t.shape}, got {th.shape}")
    if not np.issubdtype(th.dtype, np.floating):
        raise ValueError(f"theta must be floating-point radians, got dtype {th.dtype}")
    z_t = z_t.astype(np.float64, copy=False)
    th = th.astype(np.float64, copy=False)
    scale = check_positive_scalar(depth_scale, "depth_scale", upper=0.1, unit=" m per unit")
    if model is not None and not isinstance(model, SensorModel):
        raise ValueError(f"model must be a SensorModel or None, got {type(model).__name__}")
    effects = tuple(effects or ())
    for k, e in enumerate(effects):
        if not callable(e):
            raise ValueError(f"effects[{k}] is not callable: {e!r}")
    if effects and context is not None and not isinstance(context, dict):
        raise ValueError(f"context must be a dict or None, got {type(context).__name__}")
    hit = ~np.isnan(z_t)
    zh = z_t[hit]
    if zh.size:
        if not np.all(np.isfinite(zh)) or float(zh.min()) <= 0:
            raise ValueError("z_true must be finite and > 0 [m] where it is not NaN")
        if float(zh.max()) > 100.0:
            raise ValueError(f"z_true holds values up to {float(zh.max()):.1f}: z_true must be in metres")
        tt = th[hit]
        if not np.all(np.isfinite(tt)):
            raise ValueError("theta must be finite wherever z_true is a hit")
        if float(np.abs(tt).max()) > np.pi:
            raise ValueError(f"theta holds values up to {float(np.abs(tt).max()):.1f}: theta must be in radians")
    sigma = None
    if model is not None:
        K = (context or {}).get("K") if isinstance(context, dict) else None
        if model.family == "disparity" and model.frame_fx_px is None and K is not None:
            model = model.with_focal(float(np.asarray(K, dtype=np.float64)[0, 0]))   # sigma_z needs f
        sigma = np.zeros_like(z_t)
        sigma[hit] = axial_sigma_unchecked(zh, th[hit], model)
        sigma.flags.writeable = False
    return PreparedNoise(z_t, th, sigma, effects, scale)


def noisy_frame(prepared: PreparedNoise, rng: np.random.Generator, context: dict | None = None) -> np.ndarray:
    """One frame of :func:`add_noise` from a :func:`prepare_noise` result: the same draws in the same order.

    Returns
    -------
    ndarray, shape (H, W), uint16
        As :func:`add_noise`.
    """
    rng = _rng(rng)
    z_t, th, sigma, effects, scale = prepared
    if sigma is None:
        z = z_t.copy()
    else:
        # z_t + n sigma, formed in the draws' own array: standard_normal draws what normal(0, 1) does
        z = rng.standard_normal(z_t.shape)
        z *= sigma
        z += z_t
    if effects:
        th_ro = th.view()
        th_ro.flags.writeable = False
        z_ro = z_t.view()
        z_ro.flags.writeable = False
        ctx = {"K": None, "index": 0}
        ctx.update(context or {})
        ctx.update(width=z_t.shape[1], height=z_t.shape[0], depth_scale=scale, z_true=z_ro)
        if sigma is not None:
            ctx["sigma_z"] = sigma
        for k, e in enumerate(effects):
            out = np.asarray(e(z, th_ro, rng, ctx))
            if out.shape != z_t.shape or not np.issubdtype(out.dtype, np.floating):
                raise ValueError(f"effects[{k}] must return a float array of shape {z_t.shape}, got "
                                 f"{out.dtype} {out.shape}")
            z = out.astype(np.float64, copy=False)
    with np.errstate(invalid="ignore"):
        units = np.divide(z, scale)
        np.round(units, out=units)
        no_data = ~(units <= 65535)                 # beyond the uint16 range, or NaN
        no_data |= ~(z > 0)
        units[no_data] = 0.0
    return units.astype(np.uint16)

