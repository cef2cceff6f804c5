"""Effects at depth discontinuities: edge fattening and flying pixels (E8).

* :func:`edge_fattening`: the foreground's disparity spreads a few px into the background.
* :func:`flying_pixels`: pixels next to depth edges take depths between the two sides.

A depth discontinuity is a pair of 4-neighbours whose true disparities (from ``context['z_true']``)
differ by more than :data:`EDGE_JUMP_PX`; a slanted plane or the ground never has one. Edge fattening
runs first (:data:`noise_model.sim.effects.ORDER`) and leaves the grown foreground in
``context['d_edges']``, where flying pixels then put their band. Physics and sources:
``docs/depth-effects.md``, E8.
"""

from __future__ import annotations

import math

import numpy as np

from ...checks import check_integer_range, check_scalar_range
from .base import Effect, _fb, _to_depth, _to_disparity, _z_true, true_disparity
from .spec import EffectSpec

__all__ = ["edge_fattening", "flying_pixels", "EDGE_JUMP_PX", "fattening_levels"]


#: A depth discontinuity (edge effects): neighbouring pixels (4-neighbours) whose true disparities
#: differ by more than this [px]. Far above the per-pixel disparity change of any plane the D435 sees
#: (the ground at 0.45 m: ~0.1 px per row at 848 x 480), below the jumps of steps and boards (a board at
#: 2 m before a wall at 3 m: 1.8 px at 424 x 240).
EDGE_JUMP_PX = 1.0


def _jump_pixels(D, tau: float):
    """Pixels with a 4-neighbour whose disparity differs by more than tau, and the nearer side of each jump.

    Returns (edge, fg): ``edge`` marks both pixels of every jump, ``fg`` only the nearer (larger
    disparity) one.
    """
    edge = np.zeros(D.shape, dtype=bool)
    fg = np.zeros(D.shape, dtype=bool)
    dh = D[:, 1:] - D[:, :-1]
    jh = np.abs(dh) > tau
    edge[:, 1:] |= jh
    edge[:, :-1] |= jh
    fg[:, 1:] |= jh & (dh > 0)
    fg[:, :-1] |= jh & (dh < 0)
    dv = D[1:, :] - D[:-1, :]
    jv = np.abs(dv) > tau
    edge[1:, :] |= jv
    edge[:-1, :] |= jv
    fg[1:, :] |= jv & (dv > 0)
    fg[:-1, :] |= jv & (dv < 0)
    return edge, fg


def _max3(a):
    """3 x 3 maximum filter (borders: the image's own pixels only)."""
    out = a.copy()
    out[1:, :] = np.maximum(out[1:, :], a[:-1, :])
    out[:-1, :] = np.maximum(out[:-1, :], a[1:, :])
    o2 = out.copy()
    o2[:, 1:] = np.maximum(o2[:, 1:], out[:, :-1])
    o2[:, :-1] = np.maximum(o2[:, :-1], out[:, 1:])
    return o2


def _min3(a):
    return -_max3(-a)


def fattening_levels(D, levels: int):
    """Chebyshev distance (1..levels, 0 = none) of each pixel from the nearer pixel of a depth
    discontinuity it is behind by more than EDGE_JUMP_PX, and that pixel's disparity [px]."""
    _, fg = _jump_pixels(D, EDGE_JUMP_PX)
    target = np.zeros(D.shape)
    level = np.zeros(D.shape, dtype=np.int32)
    E = np.where(fg, D, 0.0)
    for j in range(1, levels + 1):
        E = _max3(E)
        new = (level == 0) & (E - D > EDGE_JUMP_PX)
        level[new] = j
        target[new] = E[new]
    return level, target


class _EdgeFattening(Effect):
    name = "edge_fattening"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        zt = _z_true(context, z.shape, self.name)
        D = true_disparity(zt, fb)
        w = self.params["width_px"]
        full = int(math.floor(w))
        frac = w - full
        levels = full + (1 if frac > 0 else 0)
        u = rng.random(z.shape)                       # drawn every frame (the same draws with any width)
        level, target = fattening_levels(D, levels)
        fat = (level > 0) & ((level <= full) | ((level == full + 1) & (u < frac)))
        # the true disparity with the foreground grown: flying pixels come after, at the apparent edge
        d_edges = np.where(fat, target, D)
        d_edges.flags.writeable = False
        context["d_edges"] = d_edges
        if not fat.any():
            return z
        d = _to_disparity(fb, z)
        noise = np.where(np.isfinite(d) & (D > 0), d - D, 0.0)
        d = np.where(fat, target + noise, d)
        return _to_depth(fb, d)


class _FlyingPixels(Effect):
    name = "flying_pixels"

    def _apply(self, z, theta, rng, context):
        fb = _fb(context, self.name)
        D = context.get("d_edges")
        if D is None:
            D = true_disparity(_z_true(context, z.shape, self.name), fb)
        elif np.shape(D) != z.shape:
            raise ValueError(f"{self.name}: context['d_edges'] must have shape {z.shape}, got {np.shape(D)}")
        b = self.params["band_px"]
        pick = rng.random(z.shape) < self.params["fraction"]
        lam = rng.random(z.shape)
        edge, _ = _jump_pixels(D, EDGE_JUMP_PX)
        band = edge
        for _ in range(b):
            band = _max3(band.astype(np.float64)) > 0
        dmax, dmin = D, np.where(D > 0, D, np.inf)
        for _ in range(b + 1):
            dmax, dmin = _max3(dmax), _min3(dmin)
        d = _to_disparity(fb, z)
        fly = band & pick & np.isfinite(d) & (dmin > 0) & np.isfinite(dmin) & (dmax - dmin > EDGE_JUMP_PX)
        if not fly.any():
            return z
        near = np.where(np.abs(d - dmax) <= np.abs(d - dmin), dmax, dmin)
        noise = d - near
        d = np.where(fly, lam * dmax + (1.0 - lam) * dmin + noise, d)
        return _to_depth(fb, d)


def edge_fattening(width_px: float = 2.0) -> Effect:
    """The foreground spreads into the background at depth edges (E8, fattening).

    Physics and source (docs/depth-effects.md, E8): a 9 x 9 census window (``census.uDiameter = 9`` in librealsense
    ``presets.cpp``) straddling two depths is dominated by the better-textured, usually nearer surface,
    and semi-global matching propagates its disparity across the edge: objects grow by a roughly
    constant number of pixels at all ranges (shallow depth at object edges, librealsense #12887;
    rounded corners, #7608). k ~ half the census window, 2-5 px at 848 x 480.

    Forward model: depth discontinuities are 4-neighbours whose true disparities (from
    ``context['z_true']``; no hit = disparity 0) differ by more than :data:`EDGE_JUMP_PX`; a
    background pixel at Chebyshev distance j >= 1 from the nearer pixel of a discontinuity takes that
    pixel's true disparity (the largest within distance j) plus its own current disparity error,
    d' = d_fg + (f B / z - d_true), if j <= floor(width_px), and with probability
    width_px - floor(width_px) (a uniform draw per pixel from ``rng``, drawn every frame) if
    j = floor(width_px) + 1: the foreground grows by ``width_px`` px on average into the background
    (and into pixels with no hit). Only jumps in the true depth count: a slanted plane or the ground
    never fattens. It leaves ``context['d_edges']``, the true disparity with the foreground grown, for
    :func:`flying_pixels`.

    ``width_px`` in [0, 20] px.
    """
    return _EdgeFattening({"width_px": check_scalar_range(width_px, "width_px", 0.0, 20.0)})


def flying_pixels(fraction: float = 0.3, band_px: int = 1) -> Effect:
    """Pixels next to depth edges take depths between the two sides (E8, flying pixels).

    Physics and source (docs/depth-effects.md, E8): a matching window straddling two depths has two cost minima;
    the subpixel fit between them and the semi-global smoothing give intermediate depths: points that
    connect an object's edge to the background (librealsense #4346, D435 at ~2 m), "ramps" at stair
    nosings in an elevation map.

    Forward model: depth discontinuities as in :func:`edge_fattening` (from ``context['z_true']``, or
    from ``context['d_edges']`` when an edge_fattening before it in the frame left it: flying pixels
    sit at the apparent, fattened edge); the band is the pixels within Chebyshev distance
    ``band_px`` of a pixel of a discontinuity (on both sides; 2 (band_px + 1) pixels across a
    straight edge); each band pixel, independently per frame
    with probability ``fraction`` (a uniform draw per pixel from ``rng``), takes the disparity
    lambda d_fg + (1 - lambda) d_bg, lambda ~ U(0, 1) (a second uniform draw per pixel), with d_fg, d_bg
    the largest and smallest true disparities within distance band_px + 1, plus the pixel's own
    current disparity error relative to the nearer of the two levels. Edges with nothing hit on one side
    have no flying pixels (nothing to interpolate to).

    D435 values: seen at most object edges; 1-3 px wide at 848 x 480 [engineering estimate].
    ``fraction`` in [0, 1], ``band_px`` an integer in [0, 10] (reals are rounded).
    """
    return _FlyingPixels({"fraction": check_scalar_range(fraction, "fraction", 0.0, 1.0),
                          "band_px": check_integer_range(band_px, "band_px", 0, 10)})


#: Registry records (:class:`~.spec.EffectSpec`) of this module's effects.
SPECS = (
    EffectSpec("flying_pixels", flying_pixels, order=7,
               # 15-50 % of the band's pixels, band 0-3 px (2-8 px across an edge)
               param_ranges={"fraction": (0.15, 0.5), "band_px": (0, 3)},
               valid={"fraction": (0.0, 1.0)},
               integer_params={"band_px": (0, 10)}),
    EffectSpec("edge_fattening", edge_fattening, order=6,
               # 1.5-4.5 px (E8: 2-5 px at 848 x 480 is 1-2.5 px here; upper end for the D435's default preset)
               param_ranges={"width_px": (1.5, 4.5)},
               valid={"width_px": (0.0, 20.0)}),
)
