"""The D4 matcher: winner-take-all on the aggregated cost, subpixel, consistency tests, depth in 1 mm units.

Stages (one rectified 10-bit pair in, one disparity map out)
-----------------------------------------------------------
1. Census transform and cost averaged over a 9 x 9 box (:mod:`.census`), semi-global aggregation S
   over four paths (:mod:`.sgm`).
2. Winner-take-all per left pixel x over the disparities whose right pixel exists,
   d = 0 .. min(D - 1, x) with D = 126 (the D4's fixed search range, so nothing nearer than
   z_min = f B / 126 can be measured). A minimum at either end of that range is not a minimum of the
   cost curve (it continues outside the range) and has no neighbours for the subpixel fit: the pixel
   is invalid. This rule makes the left invalid band emerge: for x < f B / z the true disparity lies
   outside the range.
3. Second peak (uniqueness): with S1 the winner's cost and S2 the lowest cost at |d - d1| > 1, the
   match is kept only if ``(S2 - S1) 1024 > second_peak S1``; the preset's ``deepSeaSecondPeakThreshold``
   read as a margin in units of 1/1024 of S1 (this module's interpretation).
4. Texture: the census window's texture measure (:func:`.census.texture_measure`) must reach
   ``texture_difference`` (``textureDifferenceThreshold``; 0 in the default preset = off).
5. Subpixel: with c0, c1, c2 the costs at d1 - 1, d1, d1 + 1, the offset t is where a cost curve of
   the shape a |d - t|^p + b through the three costs has its minimum. With the lower neighbour's and
   the higher neighbour's excess costs e_near <= e_far over c1, rho = e_near / e_far solves
   rho = ((1 - |t|)^p - |t|^p) / ((1 + |t|)^p - |t|^p), |t| <= 1/2, towards the lower neighbour.
   p = 1 is the equiangular (V-shaped) fit ``(c0 - c2) / (2 (max(c0, c2) - c1))``, p = 2 the parabola
   vertex ``(c0 - c2) / (2 (c0 - 2 c1 + c2))``; other exponents go through a 1025-entry table of t
   over rho (:func:`subpixel_table`). A fit whose shape does not match the cost curve's pulls the
   disparity towards whole pixels (pixel locking): the aggregated census cost is sharper than a V
   near its minimum, so the default exponent is below 1 (docs/physical-d435.md). The disparity is
   rounded to 1/2^5 = 1/32 px (the D4's 5 fractional bits).
6. Left-right check: the right image's disparity d_R(x_r) = argmin_d S(x_r + d, d) (same subpixel
   rule) must agree with the left one at x_r = x - round(d_L): ``|d_L - d_R| <= lr_threshold / 32``
   (``lrAgreeThreshold`` read in 1/32 px).
7. Small-segment removal: 4-connected regions of valid pixels whose neighbours' disparities differ by
   at most ``rsm_diff`` px are dropped when smaller than ``rsm_remove`` pixels (``rsm.diffThresh``,
   ``rsm.removeThresh``).
8. Depth z = f B / d, written as uint16 in depth units (1 mm), 0 = invalid (:func:`disparity_to_depth`).

Not modelled: the D4's median, neighbour and score thresholds (``deepSeaMedianThreshold``,
``deepSeaNeighborThreshold``, ``scoreThreshA/B``), the texture count threshold (0 in both presets),
the edge-dependent penalty modifiers and the "rsvc" valid-neighbour filter.

Every numba kernel here is split over image rows (or runs serially) and has a NumPy reference
(``*_reference``); the result does not depend on the thread count.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from ...numba_config import JIT, resolve_threads, threads
from .census import census_transform, cost_volume, cost_volume_reference, texture_measure, texture_measure_reference
from .census import to_10bit
from .sgm import aggregate, aggregate_reference, check_penalties

__all__ = [
    "MatcherParams", "PRESETS", "D435_DEPTH_SIZES", "MatchResult", "VALID", "NO_MINIMUM", "SECOND_PEAK",
    "LOW_TEXTURE", "LEFT_RIGHT", "SMALL_SEGMENT", "match", "match_reference", "winner_take_all",
    "winner_take_all_reference", "remove_small_segments", "remove_small_segments_reference",
    "disparity_to_depth", "preset", "subpixel_table", "SUBPIXEL_EXPONENT",
]

#: Exponent of the power-law subpixel fit (stage 5 of the module docstring).
SUBPIXEL_EXPONENT = 0.5

#: Depth-stream sizes (width, height) of the D435 that the presets cover.
D435_DEPTH_SIZES = ((1280, 720), (848, 480), (640, 480), (640, 360), (480, 270), (424, 240))

# reasons a pixel is invalid (the ``reason`` image of a MatchResult)
VALID, NO_MINIMUM, SECOND_PEAK, LOW_TEXTURE, LEFT_RIGHT, SMALL_SEGMENT = 0, 1, 2, 3, 4, 5

_PARABOLA, _EQUIANGULAR, _POWER = 0, 1, 2
_SUBPIXEL_MODES = {"parabola": _PARABOLA, "equiangular": _EQUIANGULAR, "power": _POWER}
_TABLE_SIZE = 1025


@dataclass(frozen=True)
class MatcherParams:
    """Parameters of the D4 matcher; the presets' names in the librealsense advanced mode in brackets.

    Attributes
    ----------
    census_radius : int
        Census window radius [px] (``census.uDiameter = vDiameter = 9`` -> 4).
    n_disp : int
        Disparities searched, 0 .. n_disp - 1 [px] (126, fixed on the D4).
    lambda_census, lambda_ad : float
        Robust-function scales of the census and absolute-difference terms (``hdad.lambdaCensus``,
        ``hdad.lambdaAD``).
    box_radius : int
        Per-pixel costs are averaged over a (2 b + 1)^2 window before aggregation (9 x 9 -> 4).
    p1, p2 : int
        SGM penalties (``spc.sloK1Penalty``, ``spc.sloK2Penalty``).
    second_peak : int
        Uniqueness margin in 1/1024 of the winner's cost (``deepSeaSecondPeakThreshold``); 0 = off.
    lr_threshold : int
        Left-right agreement [1/32 px] (``lrAgreeThreshold``); negative = off.
    texture_difference : int
        Minimum texture measure [10-bit levels] (``textureDifferenceThreshold``); 0 = off.
    rsm_diff : float
        Neighbours whose disparities differ by at most this [px] belong to one segment (``rsm.diffThresh``).
    rsm_remove : int
        Segments with fewer pixels are removed (``rsm.removeThresh``); 0 = off.
    subpixel : str
        "power" (the fit of exponent ``subpixel_exponent``), "equiangular" (exponent 1) or "parabola"
        (exponent 2); module docstring, stage 5.
    subpixel_exponent : float
        Exponent p of the cost-curve shape of the "power" fit, > 0.
    fractional_bits : int
        Disparity is rounded to 1 / 2^fractional_bits px (5 on the D4).
    sizes : tuple of (width, height), or None
        Image sizes accepted (the D435 depth modes); None accepts any size (tests, other cameras).
    """

    census_radius: int = 4
    n_disp: int = 126
    lambda_census: float = 26.0
    lambda_ad: float = 800.0
    box_radius: int = 4
    p1: int = 60
    p2: int = 342
    second_peak: int = 325
    lr_threshold: int = 24
    texture_difference: int = 0
    rsm_diff: float = 4.0
    rsm_remove: int = 63
    subpixel: str = "power"
    subpixel_exponent: float = SUBPIXEL_EXPONENT
    fractional_bits: int = 5
    sizes: tuple | None = D435_DEPTH_SIZES

    def __post_init__(self):
        check_penalties(self.p1, self.p2)
        if self.subpixel not in _SUBPIXEL_MODES:
            raise ValueError(f"subpixel must be one of {sorted(_SUBPIXEL_MODES)}, got {self.subpixel!r}")
        if not (np.isfinite(self.subpixel_exponent) and 0.0 < self.subpixel_exponent <= 4.0):
            raise ValueError(f"subpixel_exponent must be in (0, 4], got {self.subpixel_exponent!r}")
        if int(self.box_radius) < 0:
            raise ValueError(f"box_radius must be >= 0, got {self.box_radius!r}")
        for name in ("n_disp", "census_radius"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        for name in ("second_peak", "texture_difference", "rsm_remove", "fractional_bits"):
            if int(getattr(self, name)) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if not self.rsm_diff >= 0:
            raise ValueError(f"rsm_diff must be >= 0 px, got {self.rsm_diff!r}")

    def check_size(self, width: int, height: int) -> None:
        """ValueError unless (width, height) is one of :attr:`sizes` (None: any)."""
        if self.sizes is not None and (int(width), int(height)) not in self.sizes:
            raise ValueError(f"image size {width}x{height} is not a D435 depth mode the matcher presets cover: "
                             f"{', '.join(f'{w}x{h}' for w, h in self.sizes)}")


#: The librealsense presets (``src/ds/advanced_mode/presets.cpp``: ``default_430``, ``high_accuracy``).
PRESETS = {
    "default": MatcherParams(),
    "high_accuracy": MatcherParams(lambda_census=6.0, lambda_ad=751.0, p1=155, p2=190, second_peak=647,
                                   lr_threshold=10, texture_difference=1722, rsm_diff=1.65625, rsm_remove=136),
}


def preset(name_or_params) -> MatcherParams:
    """A preset by name ("default", "high_accuracy") or a :class:`MatcherParams` unchanged."""
    if isinstance(name_or_params, MatcherParams):
        return name_or_params
    try:
        return PRESETS[name_or_params]
    except (KeyError, TypeError):
        raise ValueError(f"unknown matcher preset {name_or_params!r}; choose one of {sorted(PRESETS)}") from None


class MatchResult(NamedTuple):
    """Output of :func:`match`.

    Attributes
    ----------
    disparity : ndarray, shape (H, W), float32
        Left-referenced disparity [px] on the 1/32-px lattice; NaN where invalid.
    reason : ndarray, shape (H, W), uint8
        0 valid, or the first test the pixel failed: 1 no interior minimum (search range end, left
        band), 2 second peak, 3 low texture, 4 left-right check, 5 small segment.
    """

    disparity: np.ndarray
    reason: np.ndarray


# ---------------------------------------------------------------------------------------------
# winner-take-all, subpixel, second peak, texture, left-right check
# ---------------------------------------------------------------------------------------------


def subpixel_table(exponent: float, size: int = _TABLE_SIZE) -> np.ndarray:
    """Offsets |t| [px] of the power-law fit at rho = k / (size - 1), k = 0 .. size - 1 (stage 5).

    rho(t) = ((1 - t)^p - t^p) / ((1 + t)^p - t^p) falls from 1 at t = 0 to 0 at t = 1/2; the table
    inverts it on a fine grid of t by linear interpolation.
    """
    p = float(exponent)
    if not (np.isfinite(p) and p > 0.0):
        raise ValueError(f"subpixel exponent must be > 0, got {exponent!r}")
    t = np.linspace(0.0, 0.5, 20001)
    rho = ((1.0 - t) ** p - t ** p) / ((1.0 + t) ** p - t ** p)
    return np.interp(np.linspace(0.0, 1.0, int(size)), rho[::-1], t[::-1])


@njit(**JIT)
def _subpixel(c0, c1, c2, mode, table):
    if mode == _PARABOLA:
        den = c0 - 2.0 * c1 + c2
        off = (c0 - c2) / (2.0 * den) if den > 0.0 else 0.0
    elif mode == _EQUIANGULAR:
        den = max(c0, c2) - c1
        off = (c0 - c2) / (2.0 * den) if den > 0.0 else 0.0
    else:
        far = max(c0, c2) - c1
        if far > 0.0:
            u = (min(c0, c2) - c1) / far * (table.size - 1)
            k = min(int(u), table.size - 2)
            t = table[k] + (u - k) * (table[k + 1] - table[k])
            off = t if c0 > c2 else -t
        else:
            off = 0.0
    return min(0.5, max(-0.5, off))


@njit(parallel=True, **JIT)
def _wta_kernel(S, texture, second_peak, texture_min, lr_max, mode, table, scale, disp, reason):
    h, w, n_disp = S.shape
    for y in prange(h):
        dl = np.full(w, -1.0)
        dr = np.full(w, -1.0)
        for x in range(w):
            row = S[y, x]
            dmax = min(n_disp - 1, x)
            m = row[0]
            for d in range(1, dmax + 1):                   # the lowest cost (a branch-free, vectorised loop),
                m = min(m, row[d])
            best = 0
            while row[best] != m:                          # then its first disparity
                best += 1
            s1 = np.int64(m)
            if best < 1 or best > dmax - 1:
                reason[y, x] = 1
                continue
            s2 = np.int64(1) << 40                         # lowest cost at |d - best| > 1
            if best >= 2:
                m = row[0]
                for d in range(1, best - 1):
                    m = min(m, row[d])
                s2 = np.int64(m)
            if best + 2 <= dmax:
                m = row[best + 2]
                for d in range(best + 3, dmax + 1):
                    m = min(m, row[d])
                s2 = min(s2, np.int64(m))
            if second_peak > 0 and not ((s2 - s1) * 1024 > second_peak * s1):
                reason[y, x] = 2
                continue
            if texture[y, x] < texture_min:
                reason[y, x] = 3
                continue
            off = _subpixel(float(row[best - 1]), float(s1), float(row[best + 1]), mode, table)
            dl[x] = np.floor((best + off) * scale + 0.5) / scale
        rmin = np.empty(w, S.dtype)                    # rmin[w - 1 - xr]: the lowest S(xr + d, d) over d,
        for q in range(w):                             # gathered along each left pixel's row of S
            rmin[q] = S[y, w - 1 - q, 0]
        for x in range(1, w):
            row = S[y, x]
            seg = rmin[w - 1 - x:]                     # a view, so that the index is a plain loop counter
            for d in range(1, min(n_disp - 1, x) + 1):
                seg[d] = min(seg[d], row[d])
        for xr in range(w):
            dmax = min(n_disp - 1, w - 1 - xr)
            m = rmin[w - 1 - xr]
            best = 0
            while S[y, xr + best, best] != m:          # its first disparity
                best += 1
            if best < 1 or best > dmax - 1:
                continue
            off = _subpixel(float(S[y, xr + best - 1, best - 1]), float(m), float(S[y, xr + best + 1, best + 1]),
                            mode, table)
            dr[xr] = np.floor((best + off) * scale + 0.5) / scale
        for x in range(w):
            if dl[x] < 0.0:
                disp[y, x] = np.nan
                continue
            if lr_max >= 0.0:
                xr = x - int(np.floor(dl[x] + 0.5))
                if xr < 0 or dr[xr] < 0.0 or abs(dl[x] - dr[xr]) > lr_max:
                    reason[y, x] = 4
                    disp[y, x] = np.nan
                    continue
            disp[y, x] = dl[x]
            reason[y, x] = 0


def winner_take_all(S, texture, params: MatcherParams, nthreads: int | None = None) -> MatchResult:
    """Stages 2-6 of the module docstring on an aggregated cost S (H, W, D) (numba).

    ``texture`` is the (H, W) texture measure of the left image. Returns disparity (NaN invalid) and
    the reason codes, before small-segment removal.
    """
    S = np.ascontiguousarray(S, dtype=np.uint16)
    h, w, _ = S.shape
    disp = np.empty((h, w), np.float32)
    reason = np.zeros((h, w), np.uint8)
    lr_max = params.lr_threshold / 32.0 if params.lr_threshold >= 0 else -1.0
    with threads(resolve_threads(nthreads)):
        _wta_kernel(S, np.ascontiguousarray(texture, dtype=np.int32), int(params.second_peak),
                    int(params.texture_difference), float(lr_max), _SUBPIXEL_MODES[params.subpixel],
                    subpixel_table(params.subpixel_exponent), float(2 ** params.fractional_bits), disp, reason)
    return MatchResult(disp, reason)


def _subpixel_np(c0, c1, c2, mode, exponent=1.0):
    c0, c1, c2 = (np.asarray(c, dtype=np.float64) for c in (c0, c1, c2))
    if mode == _POWER:
        table = subpixel_table(exponent)
        far = np.maximum(c0, c2) - c1
        rho = np.where(far > 0.0, (np.minimum(c0, c2) - c1) / np.where(far > 0.0, far, 1.0), 0.0)
        u = np.clip(rho, 0.0, 1.0) * (table.size - 1)             # outside [0, 1] only where c1 is no minimum
        k = np.minimum(u.astype(np.int64), table.size - 2)
        t = table[k] + (u - k) * (table[k + 1] - table[k])
        off = np.where(far > 0.0, np.where(c0 > c2, t, -t), 0.0)
        return np.clip(off, -0.5, 0.5)
    den = c0 - 2.0 * c1 + c2 if mode == _PARABOLA else np.maximum(c0, c2) - c1
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(den > 0.0, (c0 - c2) / (2.0 * np.where(den > 0.0, den, 1.0)), 0.0)
    return np.clip(off, -0.5, 0.5)


def winner_take_all_reference(S, texture, params: MatcherParams) -> MatchResult:
    """NumPy reference of :func:`winner_take_all`."""
    S = np.asarray(S).astype(np.int64)
    h, w, n_disp = S.shape
    mode = _SUBPIXEL_MODES[params.subpixel]
    scale = float(2 ** params.fractional_bits)
    d_idx = np.arange(n_disp)
    x_idx = np.arange(w)
    dmax = np.minimum(n_disp - 1, x_idx)                                   # (W,)
    big = np.int64(1) << 50
    SL = np.where(d_idx[None, None, :] <= dmax[None, :, None], S, big)
    best = SL.argmin(axis=2)
    s1 = np.take_along_axis(SL, best[..., None], axis=2)[..., 0]
    reason = np.zeros((h, w), np.uint8)
    no_min = (best < 1) | (best > dmax[None, :] - 1)
    far = np.abs(d_idx[None, None, :] - best[..., None]) > 1
    s2 = np.where(far, SL, big).min(axis=2)
    uniq_fail = (params.second_peak > 0) & ~((s2 - s1) * 1024 > params.second_peak * s1)
    tex_fail = np.asarray(texture) < params.texture_difference
    bm = np.clip(best - 1, 0, n_disp - 1)
    bp = np.clip(best + 1, 0, n_disp - 1)
    c0 = np.take_along_axis(S, bm[..., None], axis=2)[..., 0]
    c2 = np.take_along_axis(S, bp[..., None], axis=2)[..., 0]
    dl = np.floor((best + _subpixel_np(c0, s1, c2, mode, params.subpixel_exponent)) * scale + 0.5) / scale
    reason[tex_fail] = LOW_TEXTURE
    reason[uniq_fail] = SECOND_PEAK
    reason[no_min] = NO_MINIMUM
    dl = np.where(reason == 0, dl, -1.0)
    # right image: D_R(x_r, d) = S(x_r + d, d)
    DR = np.full((h, w, n_disp), big)
    for d in range(n_disp):
        if d < w:
            DR[:, :w - d, d] = S[:, d:, d]
    dmax_r = np.minimum(n_disp - 1, w - 1 - x_idx)
    br = DR.argmin(axis=2)
    sr1 = np.take_along_axis(DR, br[..., None], axis=2)[..., 0]
    ok_r = (br >= 1) & (br <= dmax_r[None, :] - 1)
    xr_idx = np.broadcast_to(x_idx[None, :], (h, w))
    rows = np.arange(h)[:, None]
    cm = S[rows, np.clip(xr_idx + br - 1, 0, w - 1), np.clip(br - 1, 0, n_disp - 1)]
    cp = S[rows, np.clip(xr_idx + br + 1, 0, w - 1), np.clip(br + 1, 0, n_disp - 1)]
    dr = np.where(ok_r, np.floor((br + _subpixel_np(cm, sr1, cp, mode, params.subpixel_exponent)) * scale + 0.5)
                  / scale, -1.0)
    valid = dl >= 0.0
    if params.lr_threshold >= 0:
        xr = x_idx[None, :] - np.floor(dl + 0.5).astype(np.int64)
        inside = valid & (xr >= 0)
        drx = np.where(inside, dr[rows, np.clip(xr, 0, w - 1)], -1.0)
        lr_fail = valid & ((drx < 0.0) | (np.abs(dl - drx) > params.lr_threshold / 32.0))
        reason[lr_fail] = LEFT_RIGHT
        valid &= ~lr_fail
    disp = np.where(valid, dl, np.nan).astype(np.float32)
    return MatchResult(disp, reason)


# ---------------------------------------------------------------------------------------------
# small-segment removal
# ---------------------------------------------------------------------------------------------


@njit(**JIT)
def _rsm_kernel(disp, max_diff, min_size, reason):
    h, w = disp.shape
    seen = np.zeros((h, w), np.bool_)
    stack = np.empty(h * w, np.int64)
    members = np.empty(h * w, np.int64)
    for y0 in range(h):
        for x0 in range(w):
            if seen[y0, x0] or np.isnan(disp[y0, x0]):
                continue
            seen[y0, x0] = True
            top = 0
            stack[top] = y0 * w + x0
            top += 1
            n = 0
            while top > 0:
                top -= 1
                p = stack[top]
                members[n] = p
                n += 1
                y = p // w
                x = p - y * w
                dp = disp[y, x]
                for k in range(4):
                    yy = y + (1 if k == 0 else (-1 if k == 1 else 0))
                    xx = x + (1 if k == 2 else (-1 if k == 3 else 0))
                    if yy < 0 or yy >= h or xx < 0 or xx >= w or seen[yy, xx]:
                        continue
                    dq = disp[yy, xx]
                    if np.isnan(dq) or abs(dq - dp) > max_diff:
                        continue
                    seen[yy, xx] = True
                    stack[top] = yy * w + xx
                    top += 1
            if n < min_size:
                for i in range(n):
                    p = members[i]
                    y = p // w
                    x = p - y * w
                    disp[y, x] = np.nan
                    reason[y, x] = 5


def remove_small_segments(disparity, reason, max_diff: float, min_size: int) -> MatchResult:
    """Stage 7: drop 4-connected segments smaller than ``min_size`` pixels (numba, serial); returns copies."""
    disp = np.array(disparity, dtype=np.float32, copy=True)
    rsn = np.array(reason, dtype=np.uint8, copy=True)
    if int(min_size) > 1:
        _rsm_kernel(disp, np.float32(max_diff), int(min_size), rsn)
    return MatchResult(disp, rsn)


def remove_small_segments_reference(disparity, reason, max_diff: float, min_size: int) -> MatchResult:
    """Pure-Python reference of :func:`remove_small_segments` (breadth-first; small images only)."""
    disp = np.array(disparity, dtype=np.float32, copy=True)
    rsn = np.array(reason, dtype=np.uint8, copy=True)
    if int(min_size) <= 1:
        return MatchResult(disp, rsn)
    h, w = disp.shape
    label = np.full((h, w), -1, np.int64)
    max_diff = np.float32(max_diff)
    segments = []
    for y0 in range(h):
        for x0 in range(w):
            if label[y0, x0] >= 0 or np.isnan(disp[y0, x0]):
                continue
            label[y0, x0] = len(segments)
            queue, members = deque([(y0, x0)]), []
            while queue:
                y, x = queue.popleft()
                members.append((y, x))
                for yy, xx in ((y + 1, x), (y - 1, x), (y, x + 1), (y, x - 1)):
                    if (0 <= yy < h and 0 <= xx < w and label[yy, xx] < 0 and not np.isnan(disp[yy, xx])
                            and abs(disp[yy, xx] - disp[y, x]) <= max_diff):
                        label[yy, xx] = len(segments)
                        queue.append((yy, xx))
            segments.append(members)
    for members in segments:
        if len(members) < min_size:
            for y, x in members:
                disp[y, x] = np.nan
                rsn[y, x] = SMALL_SEGMENT
    return MatchResult(disp, rsn)


# ---------------------------------------------------------------------------------------------
# the whole matcher
# ---------------------------------------------------------------------------------------------


def _pair(left, right, params: MatcherParams):
    L = to_10bit(left, "left image")
    R = to_10bit(right, "right image")
    if L.shape != R.shape:
        raise ValueError(f"left and right images differ in size: {L.shape} vs {R.shape}")
    params.check_size(L.shape[1], L.shape[0])
    return L, R


def match(left, right, params="default", nthreads: int | None = None, workspace: dict | None = None) -> MatchResult:
    """Disparity of a rectified infrared pair as the D4 computes it (stages 1-7; numba).

    Parameters
    ----------
    left, right : ndarray, shape (H, W), uint8 or uint16
        Rectified left (reference) and right infrared images: 8-bit, or 10-bit levels in uint16.
    params : str or MatcherParams
        A preset name ("default", "high_accuracy") or parameters.
    nthreads : int, optional
        numba threads; the result does not depend on it.
    workspace : dict, optional
        Holds the cost and aggregation volumes between calls (pass the same dict every frame: two
        (H, W, 126) uint16 volumes are not allocated again).

    Returns
    -------
    MatchResult
        Disparity [px] (NaN invalid) and the reason code of every invalid pixel.

    Raises
    ------
    ValueError
        Unknown preset, images not 2-D uint8/uint16 of the same size, or a size the preset does not cover.
    """
    p = preset(params)
    L, R = _pair(left, right, p)
    n = resolve_threads(nthreads)
    lo_l, hi_l = census_transform(L, p.census_radius, n)
    lo_r, hi_r = census_transform(R, p.census_radius, n)
    ws = workspace if workspace is not None else {}
    C = cost_volume(L, R, p.n_disp, p.census_radius, p.lambda_census, p.lambda_ad, p.box_radius,
                    census=(lo_l, hi_l, lo_r, hi_r), out=ws.get("cost"), nthreads=n)
    S = aggregate(C, p.p1, p.p2, out=ws.get("aggregated"), nthreads=n)
    if workspace is not None:
        workspace["cost"], workspace["aggregated"] = C, S
    tex = texture_measure(L, p.census_radius, n) if p.texture_difference > 0 else np.zeros(L.shape, np.int32)
    res = winner_take_all(S, tex, p, n)
    return remove_small_segments(res.disparity, res.reason, p.rsm_diff, p.rsm_remove)


def match_reference(left, right, params="default") -> MatchResult:
    """NumPy reference of :func:`match` (cost volume, aggregation and tests in NumPy; small images)."""
    p = preset(params)
    L, R = _pair(left, right, p)
    C = cost_volume_reference(L, R, p.n_disp, p.census_radius, p.lambda_census, p.lambda_ad, p.box_radius)
    S = aggregate_reference(C, p.p1, p.p2)
    tex = texture_measure_reference(L, p.census_radius)
    res = winner_take_all_reference(S, tex, p)
    return remove_small_segments_reference(res.disparity, res.reason, p.rsm_diff, p.rsm_remove)


def disparity_to_depth(disparity, focal_px: float, baseline_m: float, depth_unit_m: float = 0.001) -> np.ndarray:
    """Depth z = f B / d as uint16 in depth units (1 mm by default); 0 where invalid or out of range.

    Parameters
    ----------
    disparity : ndarray, shape (H, W)
        Disparity [px]; NaN or <= 0 = invalid.
    focal_px : float
        Focal length f [px] of the rectified pair.
    baseline_m : float
        Baseline B [m].
    depth_unit_m : float
        Size of one depth unit [m] (the D435's default 0.001).

    Returns
    -------
    ndarray, shape (H, W), uint16
        round(f B / (d u)); 0 where d is invalid or the value exceeds 65535.
    """
    for name, v in (("focal_px", focal_px), ("baseline_m", baseline_m), ("depth_unit_m", depth_unit_m)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be finite and > 0, got {v!r}")
    d = np.asarray(disparity, dtype=np.float64)
    ok = np.isfinite(d) & (d > 0)
    z = np.zeros(d.shape)
    z[ok] = np.floor(focal_px * baseline_m / (d[ok] * depth_unit_m) + 0.5)
    z[z > np.iinfo(np.uint16).max] = 0
    return z.astype(np.uint16)
