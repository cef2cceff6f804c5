"""Census transform and the matching cost of the D4 matcher: census Hamming distance plus absolute difference.

Images and units
----------------
Infrared images are (H, W) arrays of 10-bit levels (``uint16`` 0..1023); 8-bit images are scaled to
10 bits (x 4) by :func:`to_10bit` first, as the D4 works on the imagers' 10-bit output. Column ``x``
of the left image matches column ``x - d`` of the right image at disparity ``d`` [px] (the right imager
sits at +B along the camera x axis, so points move left in it).

Census
------
For a window of radius r (the D4 default is 9 x 9, r = 4), bit k of pixel p is
``I(p + o_k) < I(p)`` over the (2r+1)^2 - 1 offsets o_k in row-major order (the centre left out):
bits 0..63 go into the word ``lo``, bits 64.. into ``hi``. Outside the image the nearest border pixel
is read (coordinates clamped), so border pixels still get a descriptor.

Cost
----
The D4's hybrid cost combines the two terms through the robust function
rho(c, lambda) = 1 - exp(-c / lambda) (as in AD-Census, Mei et al. 2011)::

    C(x, y, d) = LUT_census[H(x, y, d)] + LUT_ad[A(x, y, d)]
    LUT_census[h] = round(1023 (1 - exp(-h / lambda_census)))
    LUT_ad[a]     = round(1023 (1 - exp(-a / lambda_ad)))

with H the Hamming distance of the two census words and A = |I_L(x, y) - I_R(x - d, y)| in 10-bit
levels. Both terms lie in 0..1023, so C is an integer in 0..2046 (:data:`COST_MAX`). The lambdas are
the presets' ``lambdaCensus`` and ``lambdaAD``; reading them as the scales of this robust function,
with costs on a 10-bit scale per term, is this module's interpretation (Intel documents the names and
values, not the formula). A disparity whose right pixel falls outside the image (x - d < 0) has no
cost (see below).

Box averaging
-------------
Before the semi-global aggregation the per-pixel costs are averaged over a (2 b + 1)^2 window, the
census-plus-box-aggregation of the R200 that the D400 keeps under its semi-global stage (Keselman
et al. 2017, arXiv 1705.05548, describe 7 x 7 boxes on the R200; the matcher's default is the census
window's 9 x 9, which brings the static, dot-layout-dependent part of the subpixel error down to the
D435's measured plane-fit scatter, see docs/physical-d435.md). The mean is taken over the window's
pixels inside the image, rounded to the nearest integer; a window pixel whose right pixel does not
exist (x' - d < 0) counts as :data:`COST_MAX`, and where the centre's own right pixel does not exist
the cost is :data:`COST_MAX` (the matcher never selects such a disparity). The rule is a fixed
window whose right pixels must all exist, as a hardware window that cannot reach beyond the right
image; it widens the left invalid band from ceil(f B / z) by about the box radius, which is where the
D435's own depth picture of a real infrared pair puts its band (docs/physical-d435.md; averaging only
the existing costs instead leaves the band 2-4 px narrower than the D435's at 424 x 240).
The mean keeps the 0..2046 scale, so the SGM penalties stay on the scale of one pixel's cost. Without
it the cost curve of a single pixel is too coarse (integer Hamming steps) for a 1/32-px subpixel fit.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ...numba_config import JIT, resolve_threads, threads

__all__ = [
    "COST_MAX", "TERM_MAX", "MAX_RADIUS", "to_10bit", "census_transform", "census_transform_reference",
    "cost_luts", "pixel_cost", "popcount64", "cost_volume", "cost_volume_reference", "texture_measure",
    "texture_measure_reference",
]

#: Largest value of one cost term (10-bit scale).
TERM_MAX = 1023
#: Largest matching cost (both terms saturated); also the cost of a disparity outside the image.
COST_MAX = 2 * TERM_MAX
#: Largest census radius: (2 r + 1)^2 - 1 bits must fit the two 64-bit words.
MAX_RADIUS = 5



def to_10bit(image, name: str = "image") -> np.ndarray:
    """An infrared image as int32 10-bit levels (H, W): uint8 is scaled by 4, uint16 must be <= 1023."""
    a = np.asarray(image)
    if a.ndim != 2:
        raise ValueError(f"{name} must be a 2-D infrared image, got shape {a.shape}")
    if a.dtype == np.uint8:
        return a.astype(np.int32) * 4
    if a.dtype == np.uint16:
        if a.size and int(a.max()) > TERM_MAX:
            raise ValueError(f"{name} is uint16 but holds values above 1023; 10-bit levels are expected")
        return a.astype(np.int32)
    raise ValueError(f"{name} must be uint8 (8-bit) or uint16 (10-bit levels), got dtype {a.dtype}")


def _check_radius(radius) -> int:
    r = int(radius)
    if r != radius or r < 1 or r > MAX_RADIUS:
        raise ValueError(f"census radius must be an integer in [1, {MAX_RADIUS}], got {radius!r}")
    return r


def cost_luts(lambda_census: float, lambda_ad: float) -> tuple[np.ndarray, np.ndarray]:
    """The two lookup tables of the cost (int32): census term by Hamming distance, AD term by |dI|."""
    if not (lambda_census > 0 and lambda_ad > 0 and math.isfinite(lambda_census) and math.isfinite(lambda_ad)):
        raise ValueError(f"lambda_census and lambda_ad must be finite and > 0, got {lambda_census}, {lambda_ad}")
    h = np.arange(128, dtype=np.float64)
    a = np.arange(TERM_MAX + 1, dtype=np.float64)
    lut_c = np.floor(TERM_MAX * (1.0 - np.exp(-h / lambda_census)) + 0.5).astype(np.int32)
    lut_a = np.floor(TERM_MAX * (1.0 - np.exp(-a / lambda_ad)) + 0.5).astype(np.int32)
    return lut_c, lut_a


# ---------------------------------------------------------------------------------------------
# census transform
# ---------------------------------------------------------------------------------------------


@njit(parallel=True, **JIT)
def _census_kernel(pad, r, lo, hi):
    """Bits in four 32-bit words per pixel (8 or 16 pixels per vector), then joined into the two 64-bit words."""
    h, w = lo.shape
    for y in prange(h):
        words = np.zeros((4, w), np.uint32)
        centre = pad[y + r, r:r + w]
        k = 0
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                if dy == 0 and dx == 0:
                    continue
                other = pad[y + r + dy, r + dx:r + dx + w]
                word = words[k >> 5]
                bit = np.uint32(k & 31)
                for x in range(w):
                    word[x] |= np.uint32(other[x] < centre[x]) << bit
                k += 1
        for x in range(w):
            lo[y, x] = np.uint64(words[0, x]) | (np.uint64(words[1, x]) << np.uint64(32))
            hi[y, x] = np.uint64(words[2, x]) | (np.uint64(words[3, x]) << np.uint64(32))


def census_transform(image10, radius: int = 4, nthreads: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Census descriptors of a 10-bit image (numba).

    Parameters
    ----------
    image10 : ndarray, shape (H, W), int
        Infrared image in 10-bit levels (see :func:`to_10bit`).
    radius : int
        Window radius r [px]; the window is (2r + 1) x (2r + 1).
    nthreads : int, optional
        numba threads; the result does not depend on it.

    Returns
    -------
    lo, hi : ndarray, shape (H, W), uint64
        Bits 0..63 and 64.. of the descriptor (bit k set where neighbour k is darker than the centre).
    """
    r = _check_radius(radius)
    img = np.asarray(image10, dtype=np.int32)
    pad = np.pad(img, r, mode="edge")
    lo = np.zeros(img.shape, np.uint64)
    hi = np.zeros(img.shape, np.uint64)
    with threads(resolve_threads(nthreads)):
        _census_kernel(pad, r, lo, hi)
    return lo, hi


def _offsets(r: int) -> list[tuple[int, int]]:
    return [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if (dy, dx) != (0, 0)]


def census_transform_reference(image10, radius: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """NumPy reference of :func:`census_transform` (same bits, clamped borders)."""
    r = _check_radius(radius)
    img = np.asarray(image10, dtype=np.int32)
    pad = np.pad(img, r, mode="edge")
    h, w = img.shape
    lo = np.zeros((h, w), np.uint64)
    hi = np.zeros((h, w), np.uint64)
    for k, (dy, dx) in enumerate(_offsets(r)):
        bit = (pad[r + dy:r + dy + h, r + dx:r + dx + w] < img).astype(np.uint64)
        if k < 64:
            lo |= bit << np.uint64(k)
        else:
            hi |= bit << np.uint64(k - 64)
    return lo, hi


# ---------------------------------------------------------------------------------------------
# texture measure (the texture threshold of the matcher)
# ---------------------------------------------------------------------------------------------


@njit(parallel=True, **JIT)
def _texture_kernel(img, r, out):
    h, w = img.shape
    for y in prange(h):
        for x in range(w):
            c = img[y, x]
            s = 0
            for dy in range(-r, r + 1):
                yy = min(max(y + dy, 0), h - 1)
                for dx in range(-r, r + 1):
                    xx = min(max(x + dx, 0), w - 1)
                    s += abs(img[yy, xx] - c)
            out[y, x] = s


def texture_measure(image10, radius: int = 4, nthreads: int | None = None) -> np.ndarray:
    """Sum over the census window of |I(p + o) - I(p)| [10-bit levels], int32 (H, W) (numba).

    A window of constant brightness scores 0; the matcher's texture threshold invalidates pixels whose
    score is below it (a match there would rest on noise alone).
    """
    r = _check_radius(radius)
    img = np.ascontiguousarray(image10, dtype=np.int32)
    out = np.zeros(img.shape, np.int32)
    with threads(resolve_threads(nthreads)):
        _texture_kernel(img, r, out)
    return out


def texture_measure_reference(image10, radius: int = 4) -> np.ndarray:
    """NumPy reference of :func:`texture_measure`."""
    r = _check_radius(radius)
    img = np.asarray(image10, dtype=np.int32)
    pad = np.pad(img, r, mode="edge")
    h, w = img.shape
    out = np.zeros((h, w), np.int32)
    for dy, dx in _offsets(r):
        out += np.abs(pad[r + dy:r + dy + h, r + dx:r + dx + w] - img)
    return out


# ---------------------------------------------------------------------------------------------
# matching cost
# ---------------------------------------------------------------------------------------------


@njit(**JIT)
def popcount64(x):
    """Number of set bits of a uint64 (SWAR; LLVM turns it into one popcnt where the CPU has it)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return np.int64((x * np.uint64(0x0101010101010101)) >> np.uint64(56))


@njit(**JIT)
def pixel_cost(lo_l, hi_l, lo_r, hi_r, img_l, img_r, lut_c, lut_a, y, x, d):
    """Cost C(x, y, d) of one pixel and disparity (d <= x), the formula of the module docstring."""
    xr = x - d
    h = popcount64(lo_l[y, x] ^ lo_r[y, xr]) + popcount64(hi_l[y, x] ^ hi_r[y, xr])
    a = abs(img_l[y, x] - img_r[y, xr])
    return lut_c[h] + lut_a[a]


@njit(**JIT)
def _hsum_row(lo_l, hi_l, lo_r, hi_r, img_l, img_r, lut_c, lut_a, box, y, raw, out):
    """Per-pixel costs of row y summed over the columns x - box .. x + box (clamped) into ``out`` (W, D)."""
    w, n_disp = raw.shape
    ll, hl, lr, hr, il, ir = lo_l[y], hi_l[y], lo_r[y], hi_r[y], img_l[y], img_r[y]
    for x in range(w):
        dmax = min(n_disp - 1, x)
        a, b, c = ll[x], hl[x], il[x]
        lrx, hrx, irx = lr[x::-1], hr[x::-1], ir[x::-1]    # right pixel x - d at index d (a plain loop counter)
        rx = raw[x]
        for d in range(dmax + 1):
            rx[d] = lut_c[popcount64(a ^ lrx[d]) + popcount64(b ^ hrx[d])] + lut_a[abs(c - irx[d])]
        for d in range(dmax + 1, n_disp):
            rx[d] = COST_MAX                               # no right pixel: the worst cost
    first = out[0]
    for d in range(n_disp):
        first[d] = 0
    for x in range(min(box + 1, w)):
        for d in range(n_disp):
            first[d] += raw[x, d]
    for x in range(1, w):                                  # slide the window: one pass per column
        prev = out[x - 1]
        cur = out[x]
        if x + box < w and x - box - 1 >= 0:
            add = raw[x + box]
            sub = raw[x - box - 1]
            for d in range(n_disp):
                cur[d] = prev[d] + add[d] - sub[d]
        elif x + box < w:
            add = raw[x + box]
            for d in range(n_disp):
                cur[d] = prev[d] + add[d]
        elif x - box - 1 >= 0:
            sub = raw[x - box - 1]
            for d in range(n_disp):
                cur[d] = prev[d] - sub[d]
        else:
            for d in range(n_disp):
                cur[d] = prev[d]


@njit(parallel=True, **JIT)
def _cost_kernel(lo_l, hi_l, lo_r, hi_r, img_l, img_r, lut_c, lut_a, box, magic, band_rows, out):
    """Box-averaged cost, in bands of ``band_rows`` rows; each band keeps a ring of the 2 box + 1 row sums it
    needs (and computes the 2 box rows above it again). Integer sums: the result does not depend on the bands."""
    h, w, n_disp = out.shape
    n_ring = 2 * box + 1
    n_bands = (h + band_rows - 1) // band_rows
    for band in prange(n_bands):
        y0 = band * band_rows
        y1 = min(h, y0 + band_rows)
        ring = np.empty((n_ring, w, n_disp), np.int32)
        raw = np.empty((w, n_disp), np.int32)
        acc = np.zeros((w, n_disp), np.int32)
        first = max(0, y0 - box)
        for yy in range(first, min(h, y0 + box)):
            row = ring[yy % n_ring]
            _hsum_row(lo_l, hi_l, lo_r, hi_r, img_l, img_r, lut_c, lut_a, box, yy, raw, row)
            for x in range(w):
                for d in range(n_disp):
                    acc[x, d] += row[x, d]
        for y in range(y0, y1):
            row = ring[(y + box) % n_ring]
            if y - box - 1 >= first:                       # the row leaving the window
                for x in range(w):
                    for d in range(n_disp):
                        acc[x, d] -= row[x, d]
            if y + box < h:                                # the row entering it, in the same slot
                _hsum_row(lo_l, hi_l, lo_r, hi_r, img_l, img_r, lut_c, lut_a, box, y + box, raw, row)
                for x in range(w):
                    for d in range(n_disp):
                        acc[x, d] += row[x, d]
            ny = min(h - 1, y + box) - max(0, y - box) + 1
            for x in range(w):
                x_lo = max(0, x - box)
                x_hi = min(w - 1, x + box)
                n = ny * (x_hi - x_lo + 1)
                mg = magic[n]
                half = np.int64(n >> 1)
                dm = min(x, n_disp - 1)
                a = acc[x]
                o = out[y, x]
                for d in range(dm + 1):
                    o[d] = np.uint16(((np.int64(a[d]) + half) * mg) >> 32)
                for d in range(dm + 1, n_disp):            # the centre's right pixel does not exist
                    o[d] = COST_MAX


def _check_pair(left10, right10):
    L = np.ascontiguousarray(left10, dtype=np.int32)
    R = np.ascontiguousarray(right10, dtype=np.int32)
    if L.shape != R.shape or L.ndim != 2:
        raise ValueError(f"left and right images must be 2-D and the same shape, got {L.shape} and {R.shape}")
    return L, R


def _magic(box: int) -> np.ndarray:
    """ceil(2^32 / n) for n = 1 .. (2 box + 1)^2: (v * magic[n]) >> 32 == v // n for every v below 2^25."""
    n = np.arange((2 * box + 1) ** 2 + 1, dtype=np.int64)
    n[0] = 1
    return ((np.int64(1) << 32) + n - 1) // n


def _buffer(out, shape) -> np.ndarray:
    """``out`` if it is a C-contiguous uint16 array of ``shape``, else a new one."""
    if out is not None and out.shape == shape and out.dtype == np.uint16 and out.flags.c_contiguous:
        return out
    return np.empty(shape, np.uint16)


def _check_box(box_radius) -> int:
    b = int(box_radius)
    if b != box_radius or b < 0 or (2 * b + 1) ** 2 * COST_MAX > np.iinfo(np.int32).max:
        raise ValueError(f"box_radius must be a small integer >= 0, got {box_radius!r}")
    return b


def cost_volume(left10, right10, n_disp: int, radius: int = 4, lambda_census: float = 26.0,
                lambda_ad: float = 800.0, box_radius: int = 4, census=None, out=None,
                nthreads: int | None = None) -> np.ndarray:
    """Matching cost of every pixel and disparity, averaged over a box window (numba).

    Parameters
    ----------
    left10, right10 : ndarray, shape (H, W)
        Rectified left (reference) and right infrared images in 10-bit levels.
    n_disp : int
        Number of disparities searched, d = 0 .. n_disp - 1 [px].
    radius : int
        Census window radius [px].
    lambda_census, lambda_ad : float
        Scales of the robust function of the two terms.
    box_radius : int
        The per-pixel costs are averaged over the (2 b + 1) x (2 b + 1) window around each pixel
        (clamped at the image border; rounded to the nearest integer); 0 = no averaging.
    census : tuple of 4 arrays, optional
        ``(lo_l, hi_l, lo_r, hi_r)`` already computed by :func:`census_transform`.
    out : ndarray, shape (H, W, n_disp), uint16, optional
        Written in place and returned (a buffer reused from frame to frame).
    nthreads : int, optional
        numba threads; the result does not depend on it.

    Returns
    -------
    ndarray, shape (H, W, n_disp), uint16
        Cost in 0..:data:`COST_MAX`: the mean over the window's per-pixel costs, missing right
        pixels (x' - d < 0) counted as :data:`COST_MAX`; :data:`COST_MAX` where the centre's right
        pixel is missing.
    """
    L, R = _check_pair(left10, right10)
    b = _check_box(box_radius)
    n_disp = int(n_disp)
    if n_disp < 1:
        raise ValueError(f"n_disp must be >= 1, got {n_disp}")
    n = resolve_threads(nthreads)
    lut_c, lut_a = cost_luts(lambda_census, lambda_ad)
    if census is None:
        lo_l, hi_l = census_transform(L, radius, n)
        lo_r, hi_r = census_transform(R, radius, n)
    else:
        lo_l, hi_l, lo_r, hi_r = census
    out = _buffer(out, L.shape + (n_disp,))
    band_rows = max(1, -(-L.shape[0] // n))                 # one band per thread: fewest rows computed twice
    with threads(n):
        _cost_kernel(lo_l, hi_l, lo_r, hi_r, L, R, lut_c, lut_a, b, _magic(b), band_rows, out)
    return out


def cost_volume_reference(left10, right10, n_disp: int, radius: int = 4, lambda_census: float = 26.0,
                          lambda_ad: float = 800.0, box_radius: int = 4) -> np.ndarray:
    """NumPy reference of :func:`cost_volume`."""
    L, R = _check_pair(left10, right10)
    b = _check_box(box_radius)
    lut_c, lut_a = cost_luts(lambda_census, lambda_ad)
    lo_l, hi_l = census_transform_reference(L, radius)
    lo_r, hi_r = census_transform_reference(R, radius)
    h, w = L.shape
    raw = np.full((h, w, int(n_disp)), COST_MAX, np.int64)           # no right pixel: the worst cost
    for d in range(min(int(n_disp), w)):
        ham = (np.bitwise_count(lo_l[:, d:] ^ lo_r[:, :w - d]).astype(np.int64)
               + np.bitwise_count(hi_l[:, d:] ^ hi_r[:, :w - d]))
        ad = np.abs(L[:, d:] - R[:, :w - d])
        raw[:, d:, d] = lut_c[ham] + lut_a[ad]
    # box sums by cumulative sums over the clamped window
    cs = np.concatenate([np.zeros((h, 1, raw.shape[2]), np.int64), np.cumsum(raw, axis=1)], axis=1)
    x = np.arange(w)
    x_lo, x_hi = np.maximum(0, x - b), np.minimum(w - 1, x + b)
    hs = cs[:, x_hi + 1] - cs[:, x_lo]
    cs = np.concatenate([np.zeros((1, w, raw.shape[2]), np.int64), np.cumsum(hs, axis=0)], axis=0)
    y = np.arange(h)
    y_lo, y_hi = np.maximum(0, y - b), np.minimum(h - 1, y + b)
    total = cs[y_hi + 1] - cs[y_lo]
    d = np.arange(int(n_disp))
    count = ((y_hi - y_lo + 1)[:, None] * (x_hi - x_lo + 1)[None, :])[:, :, None]
    centre_missing = (d[None, :] > x[:, None])[None, :, :]                 # (1, W, D)
    return np.where(centre_missing, COST_MAX, (total + count // 2) // count).astype(np.uint16)
