"""Fits of the edge effects: ``flying_pixels``, ``edge_fattening`` (boards before a background).

* flying_pixels: counts of intermediate depths in the rows crossing the board's left and right edges,
  and the spacing of pairs of them (the band's width).
* edge_fattening: how far the board's edges move outwards, from its top and bottom edges (precise) and
  its left and right edges (noisy: the reference shifts them laterally).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtr

from ...sim.effects.base import true_disparity
from ...sim.effects.edges import fattening_levels
from ..capture_data import REGION_BACKGROUND, REGION_EDGE_LEFT, REGION_EDGE_RIGHT, REGION_INTERIOR
from ._common import _disp_sigma, _frame, _interior, _nominal, _roi
from .spec import FitSpec


# ---- geometry of the edges ------------------------------------------------------------------------
def _edge_setup(g, model):
    """Per side (left, right): the side's region mask restricted to rows that cross the board's nominal
    edge, the board/background nominal masks, fg disparity of the board's plane, bg disparity."""
    key = ("fit_edges", float(model.sigma_L), float(model.sigma_R))
    if key in g._cache:
        return g._cache[key]
    z, th, reg, fb = _nominal(g, model)
    zp = g.plane_depth()
    with np.errstate(divide="ignore", invalid="ignore"):
        dfg = fb / zp
    dbg = fb / g.background_m
    board = np.isfinite(z) & (z < g.background_m - 1e-9)
    s, _ = g.board_coordinates()
    out = []
    for code, sigma, sign in ((REGION_EDGE_LEFT, model.sigma_L, -1.0), (REGION_EDGE_RIGHT, model.sigma_R, 1.0)):
        S = reg == code
        rows = (S & board).any(axis=1) & (S & ~board).any(axis=1)
        S = S & rows[:, None]
        if S.sum() == 0:
            out.append(None)
            continue
        # lateral sigma in px: |ds/du| [m/px] at the edge pixels
        with np.errstate(invalid="ignore"):
            dsdu = np.abs(np.gradient(s, axis=1))
        edge_px = S & board
        mpp = float(np.nanmedian(dsdu[edge_px])) if edge_px.any() else float("nan")
        sig_px = sigma / mpp if mpp > 0 else float("nan")
        out.append({"S": S, "rows": int(rows.sum()), "board": board, "dfg": dfg, "dbg": dbg,
                    "dfg_edge": float(np.nanmedian(dfg[S & board])), "sig_px": sig_px})
    g._cache[key] = out
    return out


def _edge_sides(g, model, roi=None):
    """:func:`_edge_setup` restricted to a region of interest (the side's pixels in it, rows that still
    cross the edge inside it)."""
    sides = _edge_setup(g, model)
    if roi is None:
        return sides
    out = []
    for side in sides:
        if side is None:
            out.append(None)
            continue
        S = side["S"] & roi
        rows = (S & side["board"]).any(axis=1) & (S & ~side["board"]).any(axis=1)
        S = S & rows[:, None]
        out.append({**side, "S": S, "rows": int(rows.sum())} if S.any() else None)
    return out


# ---- flying_pixels --------------------------------------------------------------------------------
_PAIR_LAGS = tuple(range(1, 13))


def _flying_stats(c, side, lo_fg, lo_bg):
    """Intermediate pixels of a side: disparity in (d_bg + lo_bg, d_fg - lo_fg); their count and the
    histogram of distances between two of them in the same row and frame."""
    d = c.geometry.fb_px_m / c.depth_m
    lo = side["dbg"] + lo_bg
    hi = side["dfg"] - lo_fg
    with np.errstate(invalid="ignore"):
        M = np.isfinite(d) & (d > lo) & (d < hi) & side["S"][None]
    n = float(M.sum())
    hist = np.array([float(np.sum(M[:, :, h:] & M[:, :, :-h])) for h in _PAIR_LAGS])
    return n, hist


def _levels_from_base(b, model, roi=None):
    """Offsets and robust spreads [px] of the board's and the background's disparities in the base
    simulation relative to the nominal geometry (base effects such as a depth bias move the levels,
    a static pattern widens them): (m_fg, s_fg, m_bg, s_bg)."""
    g = b.geometry
    z, th, reg, fb = _nominal(g, model)
    d = fb / b.depth_m
    out = []
    bgm = reg == REGION_BACKGROUND if roi is None else (reg == REGION_BACKGROUND) & roi
    for mask, level in ((_interior(g, model, roi), fb / z), (bgm, fb / g.background_m)):
        r = (d[:, mask] - (level[mask] if np.ndim(level) else level)).ravel()
        r = r[np.isfinite(r)]
        if r.size < 20:
            out += [0.0, 0.0]
            continue
        med = float(np.median(r))
        out += [med, 1.4826 * float(np.median(np.abs(r - med)))]
    return tuple(out)


def _fit_flying_pixels(real, base, model, rois=None, **_):
    """Counts of intermediate depths at the board's left and right edges, and their spacing.

    In the rows crossing a vertical edge (edge regions), a pixel is intermediate when its disparity
    lies more than 5 noise sigmas inside the board's and the background's levels (the nominal
    disparities shifted by the base simulation's median offsets; sigma the larger of the reference's
    and the base's robust spread). A straight edge has n = 2 (band_px + 1) band pixels per row, each
    flying with probability p, then intermediate with probability q = (d_fg - d_bg - margins) /
    (d_fg - d_bg) (lambda uniform), and valid with the base's valid fraction v of the region. band_px:
    the excess (real - base) histogram of distances between intermediate pixels of the same row and
    side is matched (least squares on the normalised histogram) by the distance distribution of two
    slots among n, P(h) ~ n - h; then p = excess count / (q v n F rows) summed over captures and sides.
    Single frames: the same counts with F = 1 (each frame's band is drawn afresh, so one frame is a
    sample like any other; the precision falls as 1 / sqrt(frames)).
    """
    n_exc, h_exc, denom_unit = 0.0, np.zeros(len(_PAIR_LAGS)), []
    for c, b in zip(real, base):
        g = c.geometry
        sides = _edge_sides(g, model, _roi(rois, g))
        z, th, _, fb = _nominal(g, model)
        m_fg, s_fg, m_bg, s_bg = _levels_from_base(b, model, _roi(rois, g))
        for side in sides:
            if side is None:
                continue
            zf = fb / side["dfg_edge"]
            thf = float(np.nanmedian(th[side["S"] & side["board"]]))
            sig_fg = max(float(_disp_sigma(zf, thf, _frame(model, g), g.depth_scale, fb)), s_fg)
            sig_bg = max(float(_disp_sigma(g.background_m, 0.0, _frame(model, g), g.depth_scale, fb)), s_bg)
            lo_fg, lo_bg = 5.0 * sig_fg - m_fg, 5.0 * sig_bg + m_bg
            nr, hr = _flying_stats(c, side, lo_fg, lo_bg)
            nb, hb = _flying_stats(b, side, lo_fg, lo_bg)
            n_exc += nr - nb
            h_exc += hr - hb
            delta = (side["dfg_edge"] + m_fg) - (side["dbg"] + m_bg)
            q = max(0.0, (delta - 5.0 * sig_fg - 5.0 * sig_bg) / delta)
            v = float(np.mean(np.isfinite(b.pixels_m(side["S"]))))
            denom_unit.append(q * v * c.n_frames * side["rows"])
    if not denom_unit:
        raise ValueError("flying_pixels: needs boards before a background with rows crossing their edges")
    h = np.clip(h_exc, 0.0, None)
    if h.sum() <= 0 or n_exc <= 0:
        return {"fraction": 0.0, "band_px": 0}
    hn = h / h.sum()
    lags = np.array(_PAIR_LAGS, dtype=float)
    best = (np.inf, 0)
    for band in range(0, 6):
        n = 2 * (band + 1)
        pred = np.clip(n - lags, 0.0, None)
        pred /= pred.sum()
        sse = float(np.sum((hn - pred) ** 2))
        if sse < best[0]:
            best = (sse, band)
    band = best[1]
    n = 2 * (band + 1)
    frac = n_exc / (n * float(np.sum(denom_unit)))
    return {"fraction": float(min(max(frac, 0.0), 1.0)), "band_px": int(band)}


# ---- edge_fattening -------------------------------------------------------------------------------
def _background_columns(c, side):
    """Sum over the side's columns of the fraction of valid pixels reading background (rows of the side,
    all frames): the expected number of background columns in the side's region."""
    d = c.geometry.fb_px_m / c.depth_m
    S = side["S"]
    mid = 0.5 * (side["dfg"] + side["dbg"])
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & S[None]
        bg = valid & (d < mid)
    nv = valid.sum(axis=(0, 1)).astype(float)
    nb = bg.sum(axis=(0, 1)).astype(float)
    cols = nv > 0
    return float(np.sum(nb[cols] / nv[cols]))


def _expected_background_columns(g, side, model, left: bool):
    """:func:`_background_columns` expected under the reference's edge shifts alone: a pixel of the
    side's region is background with probability P(shift > s + w/2) (left edge) or P(shift < s - w/2)
    (right edge), s its coordinate along the board, shift ~ N(0, sigma_L^2) or N(0, sigma_R^2)."""
    S = side["S"]
    s, _ = g.board_coordinates()
    w2 = g.target["width_m"] / 2.0
    with np.errstate(invalid="ignore"):
        if left:
            p = 1.0 - ndtr((s + w2) / model.sigma_L)
        else:
            p = ndtr((s - w2) / model.sigma_R)
    p = np.where(S & np.isfinite(p), p, 0.0)
    n = S.sum(axis=0).astype(float)
    cols = n > 0
    return float(np.sum(p.sum(axis=0)[cols] / n[cols]))


_HEDGE_ROWS = 10


def _horizontal_edge_zones(g, model):
    """Columns of the board away from its left/right edge regions, and for each its top and bottom edge
    rows (nominal): list of (column, first row, last row) zones of 2 * _HEDGE_ROWS rows straddling a
    horizontal board edge with background on the other side (cached)."""
    key = ("fit_hedges", float(model.sigma_L), float(model.sigma_R))
    if key in g._cache:
        return g._cache[key]
    z, _, reg, _ = _nominal(g, model)
    board = np.isfinite(z) & (z < g.background_m - 1e-9)
    bgm = np.isfinite(z) & ~board
    cols = np.flatnonzero((reg == REGION_INTERIOR).any(axis=0) & ~((reg == REGION_EDGE_LEFT)
                                                                 | (reg == REGION_EDGE_RIGHT)).any(axis=0))
    K = _HEDGE_ROWS
    H = g.height
    zones = []
    for c in cols:
        rows = np.flatnonzero(board[:, c])
        if rows.size == 0:
            continue
        top, bot = int(rows[0]), int(rows[-1])
        if top - K >= 0 and bgm[top - K:top, c].all():
            zones.append((int(c), top - K, top + K))
        if bot + K < H and bgm[bot + 1:bot + K + 1, c].all():
            zones.append((int(c), bot - K + 1, bot + K + 1))
    g._cache[key] = zones
    return zones


def _horizontal_background_rows(c, zones, dmid):
    """Mean over zones of the number of rows reading background (valid pixels, fraction per row)."""
    d = c.geometry.fb_px_m / c.depth_m
    tot = []
    for col, r0, r1 in zones:
        seg = d[:, r0:r1, col]
        with np.errstate(invalid="ignore"):
            v = np.isfinite(seg)
            bg = v & (seg < dmid[r0:r1, col])
        nv = v.sum(axis=0)
        ok = nv > 0
        tot.append(float(np.sum(bg.sum(axis=0)[ok] / nv[ok])))
    return float(np.mean(tot)) if tot else float("nan")


def _fit_edge_fattening(real, base, model, rois=None, **_):
    """The board's edges move outwards by the fattening width.

    Two estimates, combined by their inverse variances:

    * top and bottom edges (columns away from the left/right edge regions, 2 x 10 rows straddling the
      edge): the number of rows reading background (fraction of valid pixels closer to the background
      than to the board, summed over the rows) in the base simulation minus in the real data, R,
      converted to a width through the forward model's own Chebyshev levels on the nominal edge
      (R(w) = mean count of pixels at level <= floor(w) plus (w - floor(w)) times those at the next
      level: a slanted edge loses more rows than w). The reference does not move these edges, so this
      is precise (variance ~0.25 / zones, floored at 0.05^2 px^2 per capture);
    * left and right edges (their regions' rows crossing the edge): the number of background columns,
      sum over columns of the fraction of valid pixels reading background, against its expectation
      under the reference's edge shifts alone (computed from the geometry, N(0, sigma_L^2) and
      N(0, sigma_R^2) along the board: the simulation's own shifts would add their noise). The shifts
      make this noisy: variance (lateral sigma in px)^2 / frames per edge.

    Both are robust to missing pixels (fractions of valid pixels) and to flying pixels (symmetric).
    Single frames: the same with F = 1; the left/right estimates then carry the full lateral noise of
    one frame's edge shift (their weight falls with it), the top/bottom ones stay precise.
    """
    num, den = 0.0, 0.0
    for c, b in zip(real, base):
        g = c.geometry
        zones = _horizontal_edge_zones(g, model)
        roi = _roi(rois, g)
        if roi is not None:
            zones = [(col, r0, r1) for col, r0, r1 in zones if roi[r0:r1, col].all()]
        if len(zones) >= 5:
            z, _, _, fb = _nominal(g, model)
            zp = g.plane_depth()
            with np.errstate(divide="ignore", invalid="ignore"):
                dmid = 0.5 * (fb / zp + fb / g.background_m)
            est = _horizontal_background_rows(b, zones, dmid) - _horizontal_background_rows(c, zones, dmid)
            if math.isfinite(est):
                # rows fattened per zone as a function of the width, from the forward model's own levels
                # (a slanted edge fattens by more rows than the width: Chebyshev distance)
                level, _ = fattening_levels(true_disparity(z, fb), _HEDGE_ROWS - 1)
                cnt = np.zeros(_HEDGE_ROWS + 1)
                for col, r0, r1 in zones:
                    cnt += np.bincount(level[r0:r1, col], minlength=_HEDGE_ROWS + 1)[:_HEDGE_ROWS + 1]
                cnt = cnt[1:] / len(zones)                   # mean count at level 1, 2, ...
                cum = np.concatenate([[0.0], np.cumsum(cnt)])  # R(w) at w = 0, 1, 2, ...
                j = int(np.searchsorted(cum, est, side="right")) - 1
                if est <= 0:
                    w_h, slope = 0.0, max(cnt[0], 1e-3)
                elif j >= len(cnt):
                    w_h, slope = float(len(cnt)), max(cnt[-1], 1e-3)
                else:
                    slope = max(cnt[j], 1e-3)
                    w_h = j + (est - cum[j]) / slope
                var = max(0.25 / (len(zones) * c.n_frames), 0.05 ** 2) / slope ** 2
                num += w_h / var
                den += 1.0 / var
        for left, side in zip((True, False), _edge_sides(g, model, roi)):
            if side is None or not math.isfinite(side["sig_px"]):
                continue
            est = _expected_background_columns(g, side, model, left) - _background_columns(c, side)
            var = max(side["sig_px"], 0.5) ** 2 / c.n_frames
            num += est / var
            den += 1.0 / var
    if den == 0:
        raise ValueError("edge_fattening: needs boards before a background with visible edges")
    return {"width_px": float(max(num / den, 0.0))}


#: Registry records (:class:`~.spec.FitSpec`) of this module's fits.
SPECS = (
    FitSpec("flying_pixels", _fit_flying_pixels, needs=("board+background",),
            tolerance={"fraction": ("rel", 0.1), "band_px": ("abs", 0)},
            tolerance_single_frame={"fraction": ("rel", 0.1), "band_px": ("abs", 0)}),
    # the 0.3 px needs boards whose top or bottom edge is in view (>= 0.85 m for a 0.9 m board at
    # 424 x 240); the left/right edges alone are noisy (lateral sigma / sqrt(frames), ~3 px per edge at 1 m)
    FitSpec("edge_fattening", _fit_edge_fattening, needs=("board+background",),
            tolerance={"width_px": ("abs", 0.3)},
            tolerance_single_frame={"width_px": ("abs", 0.15)}),
)
