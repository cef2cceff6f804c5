"""Stage 3 of the depth -> map-points kernel, per pixel from its neighbours: depth edges and speckles,
then in windows of two surfaces the row medians and the surface medians.

The NumPy functions these stages compile: :func:`noise_model.depth_edges`, :func:`noise_model.despeckle`,
:func:`noise_model.row_medians` and :func:`noise_model.surface_depths`. Every stage works per image row
(rows grouped by block row, so that a pixel's block values are one row of the (nby, W) arrays), and
writes only its own rows: the result does not depend on the thread count. :func:`surfaces_stage` runs
the planes, the edges and the row medians of each block row in one parallel region; the surface medians
read the row medians of the neighbouring block rows, so they run in the next region, before the points
(:func:`noise_model.kernels.points.points_stage`).

What the points read:

* ``flags`` (H, W) uint8 per valid pixel: :data:`LEFT_EDGE`, :data:`RIGHT_EDGE`, :data:`SPECKLE`;
* ``speckle_z`` (H, W) [m]: a speckle's replacement depth, written at speckles only;
* ``surface_z`` (H, W) [m]: the surface median, written at the pixels of mixed windows only.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..numba_config import JIT
from .compiled import (
    EDGES, PLANES, ROW_MEDIANS, agrees, agrees_select, agrees_select_root, interleaved, rank_median,
    sigma_model, sort_lanes_any,
)
from .planes import planes_block_row

__all__ = ["LEFT_EDGE", "RIGHT_EDGE", "SPECKLE"]

#: flags: the pixel is the left boundary of a nearer surface (its left neighbour is farther or invalid).
LEFT_EDGE = 1
#: flags: ... the right boundary.
RIGHT_EDGE = 2
#: flags: no neighbour agrees with the pixel; its depth is speckle_z.
SPECKLE = 4

#: 1 - margin on a lower bound of sigma_z computed in floating point (a few roundings of 1e-16 each), so that
#: the bound never certifies an agreement the exact test would refuse.
BOUND_MARGIN = 1.0 - 1e-12

#: Pixels whose medians are sorted together, one per SIMD lane (their values fit in L1).
LANES = 128


@njit(**JIT)
def _speckle_median(depth, scale, zmin, zmax, v, u, z, g, jump_rel, thr_sig, c0, c1, c2, disp, buf):
    """The median depth of the valid 8 neighbours of pixel (v, u) at depth z when none of them agrees with
    it (a speckle), else NaN (noise_model.despeckle)."""
    H, W = depth.shape
    k = 0
    for dv in range(3):
        r = v + dv - 1
        if r < 0 or r >= H:
            continue
        for du in range(3):
            c = u + du - 1
            if c < 0 or c >= W or (dv == 1 and du == 1):
                continue
            zn = depth[r, c] * scale
            if (zn >= zmin) & (zn <= zmax):
                if agrees(zn, z, g, jump_rel, thr_sig, c0, c1, c2, disp):
                    return np.nan
                buf[k] = zn
                k += 1
    return rank_median(buf, k) if k > 0 else np.nan


@njit(parallel=True, **JIT)
def surfaces_stage(parts, depth, scale, zmin, zmax, params, family, jump_rel, thr_sig, b, M, radius, min_points,
                   degenerate_rel, mix_z, hx, hw, gx, gw, half, row_net, gain_px, eg_px, eg2_px, alpha_px, beta_px,
                   gamma_px, mixed_px, rowcount, flags, speckle_z, rowmed):
    """Stages 2, 3a and 3b per block row, in one parallel region: those of ``parts`` (PLANES, EDGES,
    ROW_MEDIANS of :mod:`noise_model.kernels.compiled`), in that order. Each needs only its own block row
    of the one before, so they share a region; run one at a time, they are timed alone.

    Stage 2, the window's plane: :func:`noise_model.kernels.planes.planes_block_row` (M, radius ..
    gw in, gain_px .. mixed_px out). Stage 3b, the row medians: :func:`row_medians_block_row` (half,
    row_net in, rowmed out).

    Stage 3a, inline below: the depth edges and speckles of every valid pixel into ``flags`` and
    ``speckle_z``. Edges (noise_model.depth_edges with the pixel's theta): a valid pixel is on a left edge
    when its left neighbour is invalid or farther by more than max(jump_rel z, thr_sig sigma_z(z, theta)),
    thr_sig = jump_sigmas sqrt(2); right edges mirror it; the image border is no edge (-inf beyond it: not
    NaN, and never farther). Speckles (noise_model.despeckle): no neighbour of 8 agrees. The two row
    neighbours settle almost every pixel in the branch-free loop; only the few pixels neither of them
    settles there (edges, noisy far surfaces) are tested in full and, when still alone, read their other
    six neighbours.

    Parameters
    ----------
    parts : int
        Bits of PLANES, EDGES, ROW_MEDIANS.
    family : None or True
        The model's family as a type (None: the paper's, True: the disparity family), as in
        :func:`noise_model.kernels.points.points_stage`: each compiles without the other's arithmetic.
    jump_rel, thr_sig : float
        The relative part of the depth-edge threshold and its noise part per sigma_z.
    gain_px : ndarray, shape (nby, W)
        The angle gain of each pixel column's window (stage 2).
    rowcount : ndarray, shape (H,)
        Valid pixels per row (rows without any are skipped).
    flags : ndarray, shape (H, W), uint8, out
    speckle_z : ndarray, shape (H, W), out
        See the module's docstring.
    """
    H, W = depth.shape
    nby = gain_px.shape[0]
    c0, c1, c2 = params[0], params[1], params[2]
    disp = family is not None
    grows_z2 = (c0 >= 0.0) & (c1 >= 0.0) & (c2 >= 0.0) & (params[3] >= 0.0)    # and the gain g >= 0
    for ib in prange(nby):
        by = interleaved(ib, nby)
        if parts & PLANES:
            planes_block_row(by, M, b, W, radius, min_points, degenerate_rel, mix_z, params, hx, hw, gx, gw, gain_px,
                             eg_px, eg2_px, alpha_px, beta_px, gamma_px, mixed_px)
        zp = np.empty(W + 2)         # z of the row, padded: zp[u + 1] = z[u]
        zp[0] = -np.inf
        zp[W + 1] = -np.inf
        nbuf = np.empty(8)
        for v in range(by * b, min(H, by * b + b)):
            if not parts & EDGES:
                break
            if rowcount[v] == 0:
                continue
            for u in range(W):
                z = depth[v, u] * scale
                zp[u + 1] = z if (z >= zmin) & (z <= zmax) else np.nan
            # the depth edges. An edge where the neighbour is invalid (NaN: the comparison fails) or
            # farther by more than thr.
            for u in range(W):
                z = zp[u + 1]
                zl = zp[u]
                zr = zp[u + 2]
                s = sigma_model(z, gain_px[by, u], c0, c1, c2, disp)
                thr = max(jump_rel * z, thr_sig * s)
                left = not (zl - z <= thr)
                right = not (zr - z <= thr)
                # speckle candidates: valid, and no row neighbour agrees for certain here: by the relative
                # part at the nearer depth; where the neighbour is the farther one (the nearer depth is z) by
                # thr itself (agrees() at the same depth and gain); where it is the nearer one, zn < z, by a
                # lower bound of its sigma_z: sigma_z(zn) >= sigma_z(z) (zn / z)^2 when no coefficient is
                # negative (each term grows at most as z^2), compared without a division and with a margin
                # for rounding. The candidates left are tested in full below.
                dl = abs(zl - z)
                dr = abs(zr - z)
                bl = thr_sig * s * BOUND_MARGIN
                near_l = (zl > 0.0) & ((dl <= jump_rel * min(zl, z)) | ((zl >= z) & (dl <= thr))
                                       | (grows_z2 & (zl < z) & (dl * z * z <= bl * zl * zl)))
                near_r = (zr > 0.0) & ((dr <= jump_rel * min(zr, z)) | ((zr >= z) & (dr <= thr))
                                       | (grows_z2 & (zr < z) & (dr * z * z <= bl * zr * zr)))
                cand = (z > 0.0) & (not (near_l | near_r))
                flags[v, u] = (LEFT_EDGE if left else 0) | (RIGHT_EDGE if right else 0) | (SPECKLE if cand else 0)
            # the candidates in full: the noise part of the row neighbours' agreement, then the other six
            for u in range(W):
                if flags[v, u] & SPECKLE:
                    z = zp[u + 1]
                    g = gain_px[by, u]
                    md = np.nan
                    if not (agrees(zp[u], z, g, jump_rel, thr_sig, c0, c1, c2, disp)
                            or agrees(zp[u + 2], z, g, jump_rel, thr_sig, c0, c1, c2, disp)):
                        md = _speckle_median(depth, scale, zmin, zmax, v, u, z, g, jump_rel, thr_sig, c0, c1, c2,
                                             disp, nbuf)
                    if md == md:
                        speckle_z[v, u] = md
                    else:
                        flags[v, u] = flags[v, u] & ~SPECKLE
        if parts & ROW_MEDIANS:
            row_medians_block_row(by, depth, scale, zmin, zmax, params, family, jump_rel, thr_sig, b, half, row_net,
                                  gain_px, mixed_px, rowmed)


@njit(**JIT)
def _any_mixed(mixed_px, by):
    """Whether block row ``by`` has a window of two surfaces."""
    found = False
    for u in range(mixed_px.shape[1]):
        found = found | (mixed_px[by, u] > 0.0)
    return found


@njit(**JIT)
def _mixed_segment(mixed_px, by, bx, nbx, b, W):
    """(u0, u1, bx1): the pixel columns u0 .. u1 - 1 of the run of blocks of two surfaces in block row ``by``
    that starts at block column ``bx`` (mixed), and the block column after it."""
    bx1 = bx + 1
    while bx1 < nbx and mixed_px[by, bx1 * b] > 0.0:
        bx1 += 1
    return bx * b, min(W, bx1 * b), bx1


@njit(**JIT)
def _row_depths(depth, scale, zmin, zmax, v, half, u0, u1, zr, sr):
    """Pixels u0 .. u1 - 1 of row v into zr[half + u] (their depths [m], NaN where invalid) and sr (their
    square roots)."""
    for u in range(np.uint64(u0), np.uint64(u1)):
        z = depth[v, u] * scale
        z = z if (z >= zmin) & (z <= zmax) else np.nan
        zr[np.uint64(half) + u] = z
        sr[np.uint64(half) + u] = np.sqrt(z)


@njit(**JIT)
def _row_agree(zr, sr, u0, m0, m, half, by, gain_px, jump_rel, thr_sig, c0, c1, c2, disp, buf, cnt, zc):
    """Pixels u0 .. u0 + m - 1 of a row (zr: its depths, NaN where invalid, padded by ``half`` NaN on each
    side; sr: their square roots) into lanes m0 .. m0 + m - 1 of a batch: their depths into zc, and their
    2 half + 1 row neighbours into the lanes' columns of buf (n, L), those that do not agree with the pixel
    (:func:`noise_model.kernels.compiled.agrees_select_root`) as +inf, with cnt counting the agreeing ones;
    :func:`noise_model.kernels.compiled.sort_lanes_any` then sorts the batch. The neighbours are read
    from the row and tested as they are copied (one store per value), over contiguous pixels with unsigned
    offsets: the loops vectorise."""
    s = np.uint64(u0)
    d = np.uint64(m0)
    h = np.uint64(half)
    for j in range(np.uint64(m)):
        zc[d + j] = zr[h + s + j]
        cnt[d + j] = 0
    for t in range(np.uint64(2 * half + 1)):
        for j in range(np.uint64(m)):
            zn = zr[s + j + t]
            ok = agrees_select_root(zn, sr[s + j + t], zr[h + s + j], sr[h + s + j], gain_px[by, s + j], jump_rel,
                                    thr_sig, c0, c1, c2, disp)
            buf[t, d + j] = zn if ok else np.inf
            cnt[d + j] += 1 if ok else 0


@njit(**JIT)
def _surface_agree(depth, scale, zmin, zmax, u0, m0, m, rows_half, v, b, gain_px, mixed_px, rowmed, jump_rel,
                   thr_sig, c0, c1, c2, disp, buf, cnt, zc):
    """Pixels u0 .. u0 + m - 1 of row v into lanes m0 .. m0 + m - 1 of a batch: their depths (NaN where
    invalid) into zc, and the row medians of rows v - rows_half .. v + rows_half of their columns where that
    row's window is mixed (NaN elsewhere and beyond the image) into the lanes' columns of buf (n, L), those
    that do not agree with the pixel (:func:`noise_model.kernels.compiled.agrees_select`) as +inf, with
    cnt counting the agreeing ones (tested as they are copied, as :func:`_row_agree`)."""
    H = rowmed.shape[0]
    by = v // b
    s = np.uint64(u0)
    d = np.uint64(m0)
    for j in range(np.uint64(m)):
        z = depth[v, s + j] * scale
        zc[d + j] = z if (z >= zmin) & (z <= zmax) else np.nan
        cnt[d + j] = 0
    for t in range(2 * rows_half + 1):
        r = v - rows_half + t
        if r < 0 or r >= H:
            for j in range(np.uint64(m)):
                buf[t, d + j] = np.inf
            continue
        rb = r // b
        for j in range(np.uint64(m)):
            zn = rowmed[r, s + j] if mixed_px[rb, s + j] > 0.0 else np.nan
            ok = agrees_select(zn, zc[d + j], gain_px[by, s + j], jump_rel, thr_sig, c0, c1, c2, disp)
            buf[t, d + j] = zn if ok else np.inf
            cnt[d + j] += 1 if ok else 0


@njit(**JIT)
def _write_medians(buf, zc, cnt, seg_u0, seg_m0, seg_n, ns, v, fallback_own, out):
    """out[v, u] for the lanes of the batch's ns segments (pixel seg_u0 + j is lane seg_m0 + j): the median of
    the agreeing values, and where none agrees the pixel's own depth (``fallback_own``) or NaN."""
    for q in range(ns):
        m0 = np.uint64(seg_m0[q])
        u0 = np.uint64(seg_u0[q])
        for j in range(np.uint64(seg_n[q])):
            lane = m0 + j
            k = cnt[lane]
            # lane_median without branches: unsigned in-bounds indices also for k = 0, whose value is unused
            lo = np.uint64(max(k - 1, 0) >> 1)
            hi = np.uint64(k >> 1)
            med = (buf[lo, lane] + buf[hi, lane]) / 2.0
            none = zc[lane] if fallback_own else np.nan
            out[v, u0 + j] = med if k > 0 else none


@njit(**JIT)
def row_medians_block_row(by, depth, scale, zmin, zmax, params, family, jump_rel, thr_sig, b, half, net, gain_px,
                          mixed_px, rowmed):
    """Stage 3b for block row ``by``: in windows of two surfaces, each valid pixel's row median
    (noise_model.row_medians) into ``rowmed`` (H, W) [m], NaN for invalid ones (no neighbour agrees with
    NaN); pixels outside mixed windows are neither computed nor written (the next stage reads rowmed only
    where mixed_px says so), and block rows without any are skipped. Mixed windows come in whole blocks:
    the runs of contiguous mixed blocks of a row are copied into batches of at most :data:`LANES` pixels.
    ``net``: :func:`noise_model.kernels.compiled.sorting_network` (2 half + 1); ``family`` as in
    :func:`surfaces_stage`."""
    H, W = depth.shape
    nbx = (W + b - 1) // b
    c0, c1, c2 = params[0], params[1], params[2]
    disp = family is not None
    n = 2 * half + 1
    if not _any_mixed(mixed_px, by):
        return
    zr = np.empty(W + 2 * half)                    # depths of the row where read: the mixed segments and
    zr[:half] = np.nan                             # their neighbours
    zr[W + half:] = np.nan
    sr = np.empty(W + 2 * half)                    # their square roots, each taken once
    sr[:half] = np.nan
    sr[W + half:] = np.nan
    cnt = np.empty(LANES, dtype=np.int64)
    zc = np.empty(LANES)
    buf = np.empty((n, LANES))
    seg = np.empty((3, LANES), dtype=np.int64)     # per segment of a batch: first pixel, first lane, pixels
    for v in range(by * b, min(H, by * b + b)):
        m = 0
        ns = 0
        bx = 0
        while bx < nbx:
            if not mixed_px[by, bx * b] > 0.0:       # mixed is per block: whole blocks in or out
                bx += 1
                continue
            u, u1, bx = _mixed_segment(mixed_px, by, bx, nbx, b, W)
            _row_depths(depth, scale, zmin, zmax, v, half, max(0, u - half), min(W, u1 + half), zr, sr)
            while u < u1:
                take = min(u1 - u, LANES - m)
                _row_agree(zr, sr, u, m, take, half, by, gain_px, jump_rel, thr_sig, c0, c1, c2, disp, buf, cnt, zc)
                seg[0, ns] = u
                seg[1, ns] = m
                seg[2, ns] = take
                ns += 1
                m += take
                u += take
                if m == LANES:
                    sort_lanes_any(buf, m, net)
                    _write_medians(buf, zc, cnt, seg[0], seg[1], seg[2], ns, v, False, rowmed)
                    m = 0
                    ns = 0
        if m > 0:
            sort_lanes_any(buf, m, net)
            _write_medians(buf, zc, cnt, seg[0], seg[1], seg[2], ns, v, False, rowmed)


@njit(**JIT)
def surface_medians_block_row(by, depth, scale, zmin, zmax, params, family, jump_rel, thr_sig, b, rows_half, net,
                              gain_px, mixed_px, rowmed, surface_z):
    """Stage 3c for block row ``by`` (run by :func:`noise_model.kernels.points.points_stage`): at each valid
    pixel of a window of two surfaces, the median of the agreeing row medians of
    2 rows_half + 1 rows (noise_model.surface_depths) into ``surface_z`` (H, W) [m], the pixel's own depth
    where none agrees; invalid pixels get NaN and are never read. In batches of runs of contiguous mixed
    blocks, as :func:`row_medians_block_row`. ``net``: :func:`noise_model.kernels.compiled.sorting_network`
    (2 rows_half + 1); ``family`` as in :func:`surfaces_stage`."""
    H, W = depth.shape
    nbx = (W + b - 1) // b
    c0, c1, c2 = params[0], params[1], params[2]
    disp = family is not None
    n = 2 * rows_half + 1
    if not _any_mixed(mixed_px, by):
        return
    zc = np.empty(LANES)
    cnt = np.empty(LANES, dtype=np.int64)
    buf = np.empty((n, LANES))
    seg = np.empty((3, LANES), dtype=np.int64)
    for v in range(by * b, min(H, by * b + b)):
        m = 0
        ns = 0
        bx = 0
        while bx < nbx:
            if not mixed_px[by, bx * b] > 0.0:
                bx += 1
                continue
            u, u1, bx = _mixed_segment(mixed_px, by, bx, nbx, b, W)
            while u < u1:
                take = min(u1 - u, LANES - m)
                _surface_agree(depth, scale, zmin, zmax, u, m, take, rows_half, v, b, gain_px, mixed_px, rowmed,
                               jump_rel, thr_sig, c0, c1, c2, disp, buf, cnt, zc)
                seg[0, ns] = u
                seg[1, ns] = m
                seg[2, ns] = take
                ns += 1
                m += take
                u += take
                if m == LANES:
                    sort_lanes_any(buf, m, net)
                    _write_medians(buf, zc, cnt, seg[0], seg[1], seg[2], ns, v, True, surface_z)
                    m = 0
                    ns = 0
        if m > 0:
            sort_lanes_any(buf, m, net)
            _write_medians(buf, zc, cnt, seg[0], seg[1], seg[2], ns, v, True, surface_z)
