"""Depth image -> map-frame points with height variance and horizontal covariance, in one numba pass.

:func:`depth_to_map_points` is the hot path of the mapper: per frame it deprojects every valid pixel,
estimates the incidence angle from block-wise inverse-depth plane fits, finds depth edges and the
windows that hold two surfaces, places speckles at their neighbours' depth
(:func:`noise_model.despeckle`), builds the D435 covariance of :func:`noise_model.point_covariances`,
rotates it into the map frame and adds the first-order pose term of :func:`noise_model.to_map_frame`.
:func:`depth_to_map_points_reference` computes the same thing by composing those public NumPy
functions, and the tests hold the two equal.

The model's formulas (sigma_z and its angle gain, E[sigma_z^2] over an uncertain angle, the
Wilson-Hilferty quantile of the mixed-window test) are those of :mod:`noise_model.formulas`, compiled
here and called by the NumPy functions the reference composes.

numba flags: those of :mod:`noise_model.numba_config` (never ``fastmath=True``, which folds ``isnan`` to
False; no ``arcp``, which changes binning at cell borders). Work is split over image rows or blocks,
each written by one thread only, so the result does not depend on the thread count.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .checks import check_depth, check_intrinsics, check_pose_cov, check_positive_scalar, check_transform
from .covariance import point_covariances, to_map_frame
from .d435 import D435, THETA_GRID, THETA_QUADRATURE, SensorModel, axial_sigma_unchecked
from .formulas import (
    angle_gain, disparity_angle_gain, disparity_expected_sigma_z_sq, disparity_sigma_z_from_gain, expected_sigma_z_sq,
    reduced_chi2_quantile, sigma_z_from_gain,
)
from .geometry import (
    DEGENERATE_REL, EDGE_JUMP_REL, EDGE_JUMP_SIGMAS, MIXED_WINDOW_Z, NORMAL_MIN_POINTS, ROW_MEDIAN_HALF_PX,
    RSS_FLOOR_REL, SURFACE_HALF_ROWS, WINDOW_RADIUS_BLOCKS, centred_moments, default_block_px, deproject,
    depth_edges, depth_to_metres, despeckle, incidence_angle_stats, mixed_windows, plane_depths, surface_depths,
)
from .numba_config import JIT, resolve_threads, threads

__all__ = ["MapPoints", "Workspace", "depth_to_map_points", "depth_to_map_points_reference"]


_GH_X = np.array(THETA_QUADRATURE[0])
_GH_W = np.array(THETA_QUADRATURE[1])
_GRID_X = np.array(THETA_GRID[0])
_GRID_W = np.array(THETA_GRID[1])

#: sigma_z is evaluated at the local plane's depth when the pixel lies within this many sigma of it.
NOISE_DEPTH_SIGMAS = 3.0

#: Default valid depth range [m]: the D435's minimum range at 848x480 is ~0.2 m; 10 m is the
#: datasheet's upper figure (sigma_z there is ~0.4 m).
MIN_DEPTH_M = 0.1
MAX_DEPTH_M = 10.0


class MapPoints(NamedTuple):
    """One frame's valid points in the map frame, in row-major pixel order.

    Attributes
    ----------
    points_map : ndarray, shape (N, 3) [m]
        z: the map-frame height of the measured point. x, y: where the pixel's ray meets the local
        plane fitted around it (the denoised depth at which sigma_z is evaluated), where that plane
        describes the pixel; else (depth edges, too few neighbours) of the measured point. Why: the
        axial noise moves a point along its ray, so at grazing incidence it lands cells away from
        where its ray met the surface, and which cell a noisy point lands in is correlated with its
        height error (far-landing points are low): binning by the measured point biases the cell
        means and breaks their calibration. The plane's depth carries ~1/N of the pixel's own noise
        (N ~ 400 pixels in the window), so the cell is chosen (almost) independently of the height
        error. In a window that holds more than one surface (:func:`noise_model.mixed_windows`) the
        point is binned at the nearer of the plane's depth and a denoised depth of its own surface,
        the median of the agreeing row medians of 5 rows (:func:`noise_model.surface_depths`; a
        speckle: its replaced depth): a plane fitted across an edge lies beyond the near surface (a box
        top seen at a grazing angle is a strip a few pixels tall, its window mostly the floor behind
        it; a riser and its tread), and binning there carries the near surface's height into the cells
        behind the edge, which its own occlusion leaves sparsely seen; points binned a little too near
        land on cells the camera sees densely, where they are outvoted. The surface median's noise is
        about a fifth of a pixel's, so it bins almost as independently of the height error as the
        plane. Only there: on one surface binning nearer would take the pixels whose noise is negative
        nearer, with their too-high heights, and leave the others, which biases a flat floor.
    height_var : ndarray, shape (N,) [m^2]
        Variance of the map-frame z of each point (Sigma_map[2, 2]). Its axial part is at least the
        squared distance of the pixel from its neighbours' median for a speckle, and from its surface
        median (:func:`noise_model.surface_depths`) in a window of two surfaces: there the window's
        angle and plane are fitted across both surfaces, and the pixels whose noise made the window
        test mixed are among its pixels, so the model's sigma alone understates their noise far from
        the camera.
    horizontal_cov : ndarray, shape (N, 3) [m^2]
        (Sigma_xx, Sigma_xy, Sigma_yy) of each point in the map frame.
    pixel : ndarray, shape (N,), int64
        Flat pixel index v * W + u of each point.
    """

    points_map: np.ndarray
    height_var: np.ndarray
    horizontal_cov: np.ndarray
    pixel: np.ndarray


class Workspace:
    """Buffers reused across frames of one image size, so a frame costs no fresh memory.

    Allocating and first touching ~30 MB per 848x480 frame costs more than the arithmetic (page
    faults); a mapper keeps one workspace per camera. Results returned with a workspace are views
    into it, valid until the next call that uses the same workspace.
    """

    def __init__(self, height: int, width: int):
        if int(height) < 1 or int(width) < 1:
            raise ValueError(f"workspace size must be positive, got {height}x{width}")
        self.shape = (int(height), int(width))
        n = self.shape[0] * self.shape[1]
        self.points_map = np.empty((3, n))       # (3, N) storage: contiguous per coordinate
        self.height_var = np.empty(n)
        self.horizontal_cov = np.empty((3, n))
        self.pixel = np.empty(n, dtype=np.int64)
        self.row_median = np.empty(self.shape)  # per pixel of a mixed window: its row median




# ---------------------------------------------------------------------------------------------
# numba kernels
# ---------------------------------------------------------------------------------------------
#: noise_model.geometry.centred_moments, compiled (S a (10,) or longer moment vector, n a number)
_centred = njit(**JIT)(centred_moments)
#: The formulas of noise_model.formulas, compiled: sigma_z from the angle gain, the gain, E[sigma_z^2],
#: the Wilson-Hilferty quantile per degree of freedom.
_sigma_z = njit(**JIT)(sigma_z_from_gain)
_angle_gain = njit(**JIT)(angle_gain)
_expected_sigma_z_sq = njit(**JIT)(expected_sigma_z_sq)
#: ... and the disparity family's: sigma_z = z^2 (c + g), g = (s1 / (f B)) theta^2, E[sigma_z^2]
_disparity_sigma_z = njit(**JIT)(disparity_sigma_z_from_gain)
_disparity_angle_gain = njit(**JIT)(disparity_angle_gain)
_disparity_expected_sigma_z_sq = njit(**JIT)(disparity_expected_sigma_z_sq)


@njit(**JIT)
def _sigma_model(z, g, c0, c1, c2, disp):
    """sigma_z [m] of the model's family at depth z with angle gain g: the disparity family (disp) z^2 (c2 + g)
    with c2 = s0 / (f B), else the paper's c0 + c1 z + c2 z^2 + g z^(3/2) (SensorModel.params_array)."""
    sd = _disparity_sigma_z(z, g, c2)
    sp = _sigma_z(z, g, c0, c1, c2)
    return sd if disp else sp


@njit(**JIT)
def _gain_model(t, ct, disp):
    """The angle gain of the model's family at the (capped) angle t [rad]."""
    gd = _disparity_angle_gain(t, ct)
    gp = _angle_gain(t, ct)
    return gd if disp else gp


@njit(**JIT)
def _expected_model(z, eg, eg2, c0, c1, c2, disp):
    """E[sigma_z^2] [m^2] of the model's family from the gain's moments E[g], E[g^2]."""
    ed = _disparity_expected_sigma_z_sq(z, eg, eg2, c2)
    ep = _expected_sigma_z_sq(z, eg, eg2, c0, c1, c2)
    return ed if disp else ep
_reduced_chi2_quantile = njit(**JIT)(reduced_chi2_quantile)


@njit(**JIT)
def _rss(S, n, alpha, beta):
    """numba version of :func:`noise_model.geometry.plane_rss` (the same arithmetic on ``_centred``)."""
    _, _, _, _, _, _, cuw, cvw, cww = _centred(S, n)
    return n * (cww - alpha * cuw - beta * cvw)


@njit(**JIT)
def _plane_from_inverse_depth_moments(S, min_points, degenerate_rel):
    """(theta [rad], alpha, beta, gamma, ok) of the inverse-depth plane fit w = alpha u' + beta v' + gamma
    of summed moments S = (n, su, sv, sw, suu, suv, svv, suw, svw); see :func:`noise_model.incidence_angles`."""
    n = S[0]
    if n < max(min_points, 3):
        return 0.0, 0.0, 0.0, 0.0, False
    mu, mv, mw, cuu, cuv, cvv, cuw, cvw, _ = _centred(S, n)
    det = cuu * cvv - cuv * cuv
    if not det > degenerate_rel * (cuu + cvv) * (cuu + cvv):    # pixels on one image line
        return 0.0, 0.0, 0.0, 0.0, False
    alpha = (cvv * cuw - cuv * cvw) / det
    beta = (cuu * cvw - cuv * cuw) / det
    gamma = mw - alpha * mu - beta * mv
    return math.atan2(math.hypot(alpha, beta), abs(gamma)), alpha, beta, gamma, True


@njit(**JIT)
def _theta_std_from_moments(S, alpha, beta, gamma):
    """Standard deviation [rad] of the plane fit's theta from the summed moments S (10,); numba version of
    :func:`noise_model.geometry._theta_std_from_moments_numpy` (the caller passes only fitted planes)."""
    n = S[0]
    if not n > 3.0:
        return 0.0
    mu, mv, mw, cuu, cuv, cvv, cuw, cvw, cww = _centred(S, n)
    det = cuu * cvv - cuv * cuv
    rss = cww - alpha * cuw - beta * cvw
    rss = rss if rss > RSS_FLOOR_REL * mw * mw else 0.0      # below the rounding of the raw moments: 0
    f = rss / (n - 3.0) / det
    vaa = f * cvv
    vbb = f * cuu
    vab = -f * cuv
    vgg = rss / (n - 3.0) + mu * mu * vaa + 2.0 * mu * mv * vab + mv * mv * vbb
    vag = -(mu * vaa + mv * vab)
    vbg = -(mu * vab + mv * vbb)
    rho = math.hypot(alpha, beta)
    q = rho * rho + gamma * gamma
    if not q > 0.0:
        return 0.0
    ag = abs(gamma)
    ja = ag * alpha / (rho * q) if rho > 0.0 else 0.0
    jb = ag * beta / (rho * q) if rho > 0.0 else 0.0
    sg = 1.0 if gamma > 0.0 else (-1.0 if gamma < 0.0 else 0.0)
    jg = -rho * sg / q
    var = (ja * ja * vaa + jb * jb * vbb + jg * jg * vgg + 2.0 * ja * jb * vab + 2.0 * ja * jg * vag
           + 2.0 * jb * jg * vbg)
    return min(math.sqrt(max(var, 0.0)), 0.5 * math.pi)      # beyond 90 deg: the angle is simply unknown


@njit(**JIT)
def _gain_moments(t, ts, ct, theta_max, disp, hx, hw, gx, gw):
    """(E[g], E[g^2]) of the angle gain of the model's family for theta ~ N(t, ts^2): the Gauss-Hermite nodes
    hx, weights hw where t +- 4 ts lies inside (0, theta_max), else the grid gx, gw (THETA_QUADRATURE,
    THETA_GRID)."""
    if not (t - 4.0 * ts > 0.0 and t + 4.0 * ts < theta_max):
        hx = gx
        hw = gw
    eg = 0.0
    eg2 = 0.0
    for k in range(hx.shape[0]):
        g = _gain_model(min(abs(t + ts * hx[k]), theta_max), ct, disp)
        eg = eg + hw[k] * g
        eg2 = eg2 + hw[k] * (g * g)
    return eg, eg2


@njit(**JIT)
def _agrees(zn, z, g, jump_rel, thr_sig, c0, c1, c2, disp):
    """Whether neighbour depth zn (NaN / -inf: none) agrees with z: |zn - z| within the depth-edge
    threshold at the nearer depth with the pixel's angle gain g (noise_model.despeckle)."""
    if not zn > 0.0:
        return False
    zq = min(zn, z)
    d = abs(zn - z)
    if d <= jump_rel * zq:                   # the relative part settles most pixels without a sqrt
        return True
    return d <= thr_sig * _sigma_model(zq, g, c0, c1, c2, disp)


@njit(**JIT)
def _rank_median(buf, k):
    """The median of buf[:k] (k >= 1): the middle one or two by rank, ties broken by position; k^2
    branch-free comparisons cost less than the mispredicted branches of a sort at these sizes."""
    lo = (k - 1) // 2
    hi = k // 2
    a = 0.0
    b = 0.0
    for i in range(k):
        x = buf[i]
        r = 0
        for j in range(k):
            r += (buf[j] < x) | ((buf[j] == x) & (j < i))
        a = x if r == lo else a
        b = x if r == hi else b
    return (a + b) / 2.0


@njit(**JIT)
def _row_median(zp, u, z, g, half, jump_rel, thr_sig, c0, c1, c2, disp, buf):
    """The median of the depths of row zp (padded: zp[c + 1] is column c) within half columns of u that
    agree with z, z's own included (noise_model.row_medians); buf holds at least 2 half + 1 values."""
    W = zp.shape[0] - 2
    k = 0
    for c in range(max(0, u - half), min(W, u + half + 1)):
        zn = zp[c + 1]
        if _agrees(zn, z, g, jump_rel, thr_sig, c0, c1, c2, disp):
            buf[k] = zn
            k += 1
    return _rank_median(buf, k)


@njit(**JIT)
def _column_median(R, mixed_px, b, v, u, z, g, half, jump_rel, thr_sig, c0, c1, c2, disp, buf):
    """The median of R[v - half .. v + half, u] that agree with z (noise_model.surface_depths), R read only
    where mixed_px (per block row b) marks the pixel's window mixed, NaN there meaning invalid; R[v, u] is
    a median of depths that agree with z, so at least it agrees."""
    H = R.shape[0]
    k = 0
    for r in range(max(0, v - half), min(H, v + half + 1)):
        zn = R[r, u] if mixed_px[r // b, u] > 0.0 else np.nan
        if _agrees(zn, z, g, jump_rel, thr_sig, c0, c1, c2, disp):
            buf[k] = zn
            k += 1
    return _rank_median(buf, k) if k > 0 else z


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
                if _agrees(zn, z, g, jump_rel, thr_sig, c0, c1, c2, disp):
                    return np.nan
                buf[k] = zn
                k += 1
    return _rank_median(buf, k) if k > 0 else np.nan


@njit(**JIT)
def _window_mixed(M, S, by, bx, radius, a, b_, c, mix_z, floor_rel):
    """Whether the window of block (by, bx), with moments S summed over it and plane
    w = a u' + b_ v' + c, holds more than one surface: numba version of
    :func:`noise_model.geometry.mixed_windows` for one block."""
    nby, nbx = M.shape[0], M.shape[1]
    between = 0.0
    dof = 0.0
    nblocks = 0.0
    for i in range(max(0, by - radius), min(nby, by + radius + 1)):
        for j in range(max(0, bx - radius), min(nbx, bx + radius + 1)):
            n = M[i, j, 0]
            if n > 0.0:
                rs = M[i, j, 3] - a * M[i, j, 1] - b_ * M[i, j, 2] - c * n
                between += rs * rs / n
                dof += n - 1.0
                nblocks += 1.0
    rss = _rss(S, S[0], a, b_)
    return _mixed_from_sums(between, max(rss - between, 0.0), dof, nblocks, S[0], S[3], mix_z, floor_rel)


@njit(**JIT)
def _mixed_from_sums(between, within, dof, nblocks, ntot, swtot, mix_z, floor_rel):
    """The test of noise_model.geometry.mixed_windows from a window's sums (scalar version)."""
    if nblocks <= 3.0 or dof <= 0.0:
        return True
    mw = swtot / ntot
    if within <= floor_rel * mw * mw * dof:          # noise-free: any structure beyond rounding is a second surface
        return between > floor_rel * mw * mw * ntot
    k = nblocks - 3.0
    return between * dof > _reduced_chi2_quantile(k, mix_z) * k * within


@njit(parallel=True, **JIT)
def _depth_to_map_kernel(depth, scale, intr, T, P, use_pose, params, edge_params, zrange, block, radius,
                         min_points, degenerate_rel, bin_at_plane, mix_z, row_half, rows_half, hx, hw, gx, gw, rowmed,
                         pts, hvar, hcov, pix):
    """Fill columns 0..N-1 of pts (3, n), hvar (n,), hcov (3, n), pix (n,) with the frame's valid
    pixels in row-major order; return N.

    Speed notes (the inner loops must vectorise): loops index from 0 or with unsigned indices (a
    signed index that may be negative gets numba's wraparound select, which makes the access
    non-contiguous for LLVM); the per-pixel loops are branch-free (selects); arrays are indexed
    directly rather than through views created inside a prange body, so that numba can mark the
    body's arrays noalias and LLVM needs no runtime alias checks.
    """
    H, W = depth.shape
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    c0, c1, c2, ct, theta_max, s_left, s_right = (
        params[0], params[1], params[2], params[3], params[4], params[5], params[6])
    disp = params[7] > 0.5                   # the disparity family (SensorModel.params_array)
    jump_rel, jump_sig, noise_sigmas = edge_params[0], edge_params[1], edge_params[2]
    thr_sig = jump_sig * math.sqrt(2.0)      # noise part of the depth-edge threshold, per sigma_z
    zmin, zmax = zrange[0], zrange[1]
    b = block
    nby = (H + b - 1) // b
    nbx = (W + b - 1) // b
    inv_fx = 1.0 / fx
    inv_fy = 1.0 / fy
    # normalised pixel coordinates u' = x / z = (u - cx) / fx per column, v' = (v - cy) / fy per row
    up = np.empty(W)
    for u in range(W):
        up[u] = (u - cx) * inv_fx
    vp = np.empty(H)
    for v in range(H):
        vp[v] = (v - cy) * inv_fy

    # pass 1: per block, the moments (n, su, sv, sw, suu, suv, svv, suw, svw, sww) of u', v' and w = 1 / z
    # over its valid pixels, and the valid count per row. u' is constant down a column and v' along a
    # row, so per block row only six column sums are needed: n, sum v', sum v'^2, sum w, sum v' w, sum w^2;
    # the u' factors are applied once per column when the columns are summed into blocks. The pixel
    # loop is branch-free (selects) so that it vectorises. zmin > 0 and zmax are finite (_prepare
    # checks them), so zmin <= z <= zmax also rejects 0, NaN, +-inf and negative depth.
    M = np.empty((nby, nbx, 10))
    rowcount = np.empty(H, dtype=np.int64)
    for by in prange(nby):
        cn = np.zeros(W)
        cv = np.zeros(W)
        cvv = np.zeros(W)
        cw = np.zeros(W)
        cvw = np.zeros(W)
        cww = np.zeros(W)
        for v in range(by * b, min(H, by * b + b)):
            vv = vp[v]
            vv2 = vv * vv
            cnt = 0
            for u in range(W):
                z = depth[v, u] * scale
                ok = (z >= zmin) & (z <= zmax)
                f = 1.0 if ok else 0.0
                w = 1.0 / z if ok else 0.0
                cn[u] += f
                cv[u] += f * vv
                cvv[u] += f * vv2
                cw[u] += w
                cvw[u] += vv * w
                cww[u] += w * w
                cnt += 1 if ok else 0
            rowcount[v] = cnt
        for bx in range(nbx):
            n = su = sv = sw = suu = suv = svv = suw = svw = sww = 0.0
            for u in range(bx * b, min(W, bx * b + b)):
                r = up[u]
                n += cn[u]
                su += r * cn[u]
                sv += cv[u]
                sw += cw[u]
                suu += r * r * cn[u]
                suv += r * cv[u]
                svv += cvv[u]
                suw += r * cw[u]
                svw += cvw[u]
                sww += cww[u]
            M[by, bx, 0] = n
            M[by, bx, 1] = su
            M[by, bx, 2] = sv
            M[by, bx, 3] = sw
            M[by, bx, 4] = suu
            M[by, bx, 5] = suv
            M[by, bx, 6] = svv
            M[by, bx, 7] = suw
            M[by, bx, 8] = svw
            M[by, bx, 9] = sww

    # pass 2: theta of each block from the (2 radius + 1)^2 blocks around it, as the gain of the axial
    # theta term c_theta theta / (pi/2 - theta)^2, spread over the block's pixel columns. The window
    # sum is separable: over the block rows first (Vs), then over the block columns.
    gain_px = np.empty((nby, W))
    # E[g] and E[g^2] over the uncertainty of the block's theta, for the axial variance
    eg_px = np.empty((nby, W))
    eg2_px = np.empty((nby, W))
    # the block's plane w = alpha u' + beta v' + gamma per pixel column (gamma NaN: no plane), for the
    # denoised depth at which sigma_z is evaluated
    alpha_px = np.empty((nby, W))
    beta_px = np.empty((nby, W))
    gamma_px = np.empty((nby, W))
    mixed_px = np.empty((nby, W))
    for by in prange(nby):
        Vs = np.zeros((nbx, 10))
        for i in range(max(0, by - radius), min(nby, by + radius + 1)):
            for bx in range(nbx):
                for c in range(10):
                    Vs[bx, c] += M[i, bx, c]
        S = np.empty(10)
        for bx in range(nbx):
            g = 0.0
            eg = 0.0
            eg2 = 0.0
            pa = pb = 0.0
            pg = np.nan
            mixed = True
            if M[by, bx, 0] > 0.0:      # a block without valid pixels needs no gain
                S[:] = 0.0
                for j in range(max(0, bx - radius), min(nbx, bx + radius + 1)):
                    for c in range(10):
                        S[c] += Vs[j, c]
                t, pa, pb, pg, ok = _plane_from_inverse_depth_moments(S, min_points, degenerate_rel)
                ts = _theta_std_from_moments(S, pa, pb, pg) if ok else 0.0
                mixed = _window_mixed(M, S, by, bx, radius, pa, pb, pg, mix_z, RSS_FLOOR_REL) if ok else True
                if not ok:
                    pg = np.nan
                eg, eg2 = _gain_moments(t, ts, ct, theta_max, disp, hx, hw, gx, gw)
                g = _gain_model(min(t, theta_max), ct, disp)
            for u in range(bx * b, min(W, bx * b + b)):
                gain_px[by, u] = g
                eg_px[by, u] = eg
                eg2_px[by, u] = eg2
                alpha_px[by, u] = pa
                beta_px[by, u] = pb
                gamma_px[by, u] = pg
                mixed_px[by, u] = 1.0 if mixed else 0.0

    # pass 2b: in windows of two surfaces, each valid pixel's row median (noise_model.row_medians; for
    # the surface median, which bins the pixel and floors its variance) into rowmed (H, W), NaN for
    # invalid ones; pixels outside mixed windows are neither computed nor written (pass 3 reads rowmed
    # only where mixed_px says so), and rows without any are skipped.
    for v in prange(H):
        by = v // b
        any_mixed = False
        for u in range(W):
            any_mixed = any_mixed | (mixed_px[by, u] > 0.0)
        if not any_mixed:
            continue
        zr_row = np.empty(W + 2)
        zr_row[0] = np.nan
        zr_row[W + 1] = np.nan
        rb = np.empty(2 * row_half + 1)
        for u in range(W):
            z = depth[v, u] * scale
            zr_row[u + 1] = z if (z >= zmin) & (z <= zmax) else np.nan
        for u in range(W):
            if mixed_px[by, u] > 0.0:
                z = zr_row[u + 1]
                rm = np.nan
                if z > 0.0:
                    rm = _row_median(zr_row, u, z, gain_px[by, u], row_half, jump_rel, thr_sig, c0, c1, c2, disp, rb)
                rowmed[v, u] = rm

    # output offsets (exclusive prefix sum of the row counts)
    offsets = np.empty(H + 1, dtype=np.int64)
    offsets[0] = 0
    for v in range(H):
        offsets[v + 1] = offsets[v] + rowcount[v]

    R00, R01, R02, R10, R11, R12, R20, R21, R22 = (
        T[0, 0], T[0, 1], T[0, 2], T[1, 0], T[1, 1], T[1, 2], T[2, 0], T[2, 1], T[2, 2])
    t0, t1, t2 = T[0, 3], T[1, 3], T[2, 3]
    pix_var_x = 1.0 / (12.0 * fx * fx)
    pix_var_y = 1.0 / (12.0 * fy * fy)
    sL2 = s_left * s_left
    sR2 = s_right * s_right
    sLR2 = max(sL2, sR2)
    # pose term J P J^T as quadratic forms in q = R p_cam, J = [I, -[q]_x], whose rows are
    # x = e0 + q2 e4 - q1 e5, y = e1 - q2 e3 + q0 e5, z = e2 + q1 e3 - q0 e4
    P00, P01, P03, P04, P05 = P[0, 0], P[0, 1], P[0, 3], P[0, 4], P[0, 5]
    P11, P13, P14, P15 = P[1, 1], P[1, 3], P[1, 4], P[1, 5]
    P22, P23, P24 = P[2, 2], P[2, 3], P[2, 4]
    P33, P34, P35, P44, P45, P55 = P[3, 3], P[3, 4], P[3, 5], P[4, 4], P[4, 5], P[5, 5]

    # pass 3, per block row (its row buffers allocated once) and per row: (a) z with NaN for invalid
    # pixels, (b) the lateral x variance from the depth edges, (c) compaction of the valid pixels
    # (u, z, var_x) into the row buffers, (d) the arithmetic over the compacted pixels, written to
    # the outputs. (a), (b) and (d) vectorise; (c) is a scalar but branch-free loop (every pixel is
    # stored, the count only advances on valid ones). (d) is bound by its stores, 64 B per point.
    # (a) uses pass 1's validity test, so k == rowcount[v] and rows never write into each other's
    # output ranges.
    nan = np.nan
    half = (nby + 1) // 2
    for ib in prange(nby):
        # even block rows first, then the odd ones: numba gives each thread one contiguous range of
        # iterations, and valid pixels are often uneven over the image (sky, floor out of range).
        # int64: the prange index may be typed unsigned, and unsigned with signed gives float64.
        rank = np.int64(ib)
        by = 2 * rank if rank < half else 2 * (rank - half) + 1
        zp = np.empty(W + 2)         # z of the row, padded: zp[u + 1] = z[u]
        vx = np.empty(W)
        cu = np.empty(W, dtype=np.int64)
        cz = np.empty(W)
        cvx = np.empty(W)
        medrow = np.empty(W)
        cmed = np.empty(W)
        nbuf = np.empty(8)
        colmed = np.empty(W)
        crow = np.empty(W)
        rbuf = np.empty(2 * rows_half + 1)
        # -inf beyond the image: not NaN (invalid) and never farther by more than thr, so the image
        # border is no edge
        zp[0] = -np.inf
        zp[W + 1] = -np.inf
        for v in range(by * b, min(H, by * b + b)):
            if rowcount[v] == 0:
                continue
            for u in range(W):
                z = depth[v, u] * scale
                zp[u + 1] = z if (z >= zmin) & (z <= zmax) else nan
            # an edge where the neighbour is invalid (NaN: the comparison fails) or farther by more
            # than thr; interior pixels get the pixel footprint
            for u in range(W):
                z = zp[u + 1]
                # noise part with this pixel's sigma_z(z, theta), as noise_model.depth_edges(theta=...)
                thr = max(jump_rel * z, thr_sig * _sigma_model(z, gain_px[by, u], c0, c1, c2, disp))
                left = not (zp[u] - z <= thr)
                right = not (zp[u + 2] - z <= thr)
                var_x = sR2 if right else -1.0      # -1: interior, the pixel footprint at the point's depth
                vx[u] = (sLR2 if right else sL2) if left else var_x
            # speckles: no neighbour agrees (noise_model.despeckle); the row neighbours settle
            # almost every pixel, the other six are read only when both disagree. And in windows of
            # two surfaces the median of the agreeing row medians down the column (surface_depths)
            for u in range(W):
                z = zp[u + 1]
                md = nan
                if z > 0.0:
                    g = gain_px[by, u]
                    if not (_agrees(zp[u], z, g, jump_rel, thr_sig, c0, c1, c2, disp)
                            or _agrees(zp[u + 2], z, g, jump_rel, thr_sig, c0, c1, c2, disp)):
                        md = _speckle_median(depth, scale, zmin, zmax, v, u, z, g, jump_rel, thr_sig, c0, c1, c2, disp,
                                             nbuf)
                medrow[u] = md
                rm = nan
                if (z > 0.0) & (mixed_px[by, u] > 0.0):
                    rm = _column_median(rowmed, mixed_px, b, v, u, z, gain_px[by, u], rows_half, jump_rel, thr_sig,
                                        c0, c1, c2, disp, rbuf)
                colmed[u] = rm
            k = 0
            for u in range(W):
                z = zp[u + 1]
                cu[k] = u
                cz[k] = z
                cvx[k] = vx[u]
                cmed[k] = medrow[u]
                crow[k] = colmed[u]
                k += 0 if np.isnan(z) else 1

            # unsigned output index: no wraparound select, so the stores below are contiguous
            k0 = np.uint64(offsets[v])
            vv = vp[v]
            b0 = R01 * vv + R02      # a = R r = R[:, 0] u' + (R[:, 1] v' + R[:, 2])
            b1 = R11 * vv + R12
            b2 = R21 * vv + R22
            base = v * W
            for j in range(np.uint64(k)):
                u = cu[j]
                z = cz[j]
                # a speckle (median not NaN): its depth is its neighbours' median, and it is as uncertain
                # as its distance from them (selects, so that the loop still vectorises)
                md = cmed[j]
                sp = md == md
                dev2 = (z - md) * (z - md) if sp else 0.0
                z = md if sp else z
                zz = z * z
                var_x = cvx[j] if cvx[j] >= 0.0 else zz * pix_var_x
                var_y = zz * pix_var_y
                # sigma_z at the local plane's depth when the pixel lies within 3 sigma of it (a
                # weight must not depend on the pixel's own noise), else at its own depth
                g = gain_px[by, u]
                wf = alpha_px[by, u] * up[u] + beta_px[by, u] * vv + gamma_px[by, u]
                zf = 1.0 / wf if wf > 0.0 else z
                zf = zf if (zf >= zmin) & (zf <= zmax) else z
                sf = max(_sigma_model(zf, g, c0, c1, c2, disp), _sigma_model(z, g, c0, c1, c2, disp))
                zs = zf if abs(z - zf) <= noise_sigmas * sf else z
                # E[sigma_z^2] over the uncertainty of theta (noise_model.axial_variance)
                s2 = max(_expected_model(zs, eg_px[by, u], eg2_px[by, u], c0, c1, c2, disp), dev2)
                # in a window of two surfaces the model's sigma is the fit's across both (its angle,
                # its plane): the pixel's distance from its own surface's median is a floor, as a
                # speckle's from its neighbours (a speckle: its replaced depth, so 0; NaN: not mixed)
                zr = z if sp else crow[j]
                dr = z - zr
                s2 = max(s2, dr * dr) if dr == dr else s2
                ru = up[u]
                a0 = R00 * ru + b0
                a1 = R10 * ru + b1
                a2 = R20 * ru + b2
                cxx = s2 * a0 * a0 + var_x * R00 * R00 + var_y * R01 * R01
                cxy = s2 * a0 * a1 + var_x * R00 * R10 + var_y * R01 * R11
                cyy = s2 * a1 * a1 + var_x * R10 * R10 + var_y * R11 * R11
                czz = s2 * a2 * a2 + var_x * R20 * R20 + var_y * R21 * R21
                q0 = z * a0                          # camera centre -> point, map frame
                q1 = z * a1
                q2 = z * a2
                if use_pose:
                    cxx += (P00 + 2.0 * (q2 * P04 - q1 * P05) + q2 * q2 * P44 - 2.0 * q1 * q2 * P45
                            + q1 * q1 * P55)
                    cyy += (P11 + 2.0 * (q0 * P15 - q2 * P13) + q2 * q2 * P33 - 2.0 * q0 * q2 * P35
                            + q0 * q0 * P55)
                    czz += (P22 + 2.0 * (q1 * P23 - q0 * P24) + q1 * q1 * P33 - 2.0 * q0 * q1 * P34
                            + q0 * q0 * P44)
                    cxy += (P01 - q2 * P03 + q0 * P05
                            + q2 * (P14 - q2 * P34 + q0 * P45)
                            - q1 * (P15 - q2 * P35 + q0 * P55))
                i = k0 + j
                # x, y where the ray meets the local plane (the cell the pixel looks at); in a window of
                # two surfaces at the nearer of the plane and the surface median (a speckle: its
                # replaced depth); z from the measured depth (see MapPoints)
                zb = (min(zf, zr) if mixed_px[by, u] > 0.0 else zs) if bin_at_plane else z
                pts[0, i] = zb * a0 + t0
                pts[1, i] = zb * a1 + t1
                pts[2, i] = q2 + t2
                hvar[i] = czz
                hcov[0, i] = cxx
                hcov[1, i] = cxy
                hcov[2, i] = cyy
                pix[i] = base + u
    return offsets[H]


# ---------------------------------------------------------------------------------------------
# public entries
# ---------------------------------------------------------------------------------------------
def _frame_model(model, K) -> SensorModel:
    """The model as it applies to a frame of intrinsics K: a disparity-family model bound to the frame's
    focal length fx (its sigma_d is in pixels of this frame), the paper's family as it is."""
    if not isinstance(model, SensorModel):
        raise ValueError(f"model must be a noise_model.SensorModel, got {type(model).__name__}")
    return model.with_focal(K[0, 0]) if model.family == "disparity" else model


def _prepare(depth, K, T_map_cam, pose_cov, depth_scale, min_depth_m, max_depth_m, block_px):
    d, scale = check_depth(depth, depth_scale)
    K = check_intrinsics(K)
    T = check_transform(T_map_cam)
    P = None if pose_cov is None else check_pose_cov(pose_cov)
    zmin = check_positive_scalar(min_depth_m, "min_depth_m", upper=100.0, unit=" m")
    zmax = check_positive_scalar(max_depth_m, "max_depth_m", upper=100.0, unit=" m")
    if zmin >= zmax:
        raise ValueError(f"min_depth_m ({zmin}) must be below max_depth_m ({zmax})")
    b = default_block_px(d.shape[1]) if block_px is None else int(block_px)
    if b < 1:
        raise ValueError(f"block_px must be >= 1, got {block_px}")
    return d, scale, K, T, P, zmin, zmax, b


def depth_to_map_points(depth, K, T_map_cam, pose_cov=None, *, depth_scale=None, model: SensorModel = D435,
                        min_depth_m: float = MIN_DEPTH_M, max_depth_m: float = MAX_DEPTH_M,
                        block_px: int | None = None, nthreads: int | None = None,
                        workspace: Workspace | None = None, bin_at_plane: bool = True) -> MapPoints:
    """A depth frame's valid points in the map frame with their height variance and horizontal covariance.

    numba, parallel over block rows; equal to :func:`depth_to_map_points_reference`.

    Parameters
    ----------
    depth : array_like, shape (H, W)
        uint16 depth units (with ``depth_scale``) or float metres; 0, NaN, inf, negative = no point.
    K : array_like, shape (3, 3)
        Depth-stream intrinsics [px].
    T_map_cam : array_like, shape (4, 4)
        Maps camera-frame points into the map frame.
    pose_cov : array_like, shape (6, 6), optional
        Pose-error covariance, translation [m^2] then rotation [rad^2] in the map frame about the
        camera centre (see :func:`noise_model.to_map_frame`).
    depth_scale : float, optional
        Metres per unit for uint16 depth.
    model : SensorModel
        Noise model (the paper's D435 by default); a disparity-family model's sigma_d is converted to depth
        with this frame's focal length K[0, 0] and the model's baseline.
    min_depth_m, max_depth_m : float
        Valid depth range [m].
    block_px : int, optional
        Normal-estimation block size [px] (see :func:`noise_model.incidence_angles`).
    nthreads : int, optional
        Threads to use (numba's current setting by default).
    workspace : Workspace, optional
        Reused buffers of this image size; the result is then a view into it, valid until the
        workspace's next use. Without one, fresh arrays are returned.
    bin_at_plane : bool
        Place each point's x, y where its ray meets the local plane, or, in a window holding more than
        one surface, at the nearer of that and its surface median (:func:`noise_model.surface_depths`;
        see :class:`MapPoints`); False: at its measured depth.

    Returns
    -------
    MapPoints
    """
    d, scale, K, T, P, zmin, zmax, b = _prepare(depth, K, T_map_cam, pose_cov, depth_scale, min_depth_m,
                                                max_depth_m, block_px)
    model = _frame_model(model, K)
    n = resolve_threads(nthreads)
    ws = Workspace(*d.shape) if workspace is None else workspace
    if not isinstance(ws, Workspace) or ws.shape != d.shape:
        raise ValueError(f"workspace must be a Workspace of the depth image's size {d.shape}")
    intr = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    edge = np.array([EDGE_JUMP_REL, EDGE_JUMP_SIGMAS, NOISE_DEPTH_SIGMAS])
    with threads(n):
        N = _depth_to_map_kernel(d, scale, intr, T, np.zeros((6, 6)) if P is None else P, P is not None,
                                 model.params_array(), edge, np.array([zmin, zmax]), b, WINDOW_RADIUS_BLOCKS,
                                 NORMAL_MIN_POINTS,
                                 DEGENERATE_REL, bool(bin_at_plane), MIXED_WINDOW_Z, ROW_MEDIAN_HALF_PX,
                                 SURFACE_HALF_ROWS, _GH_X, _GH_W, _GRID_X, _GRID_W, ws.row_median,
                                 ws.points_map, ws.height_var,
                                 ws.horizontal_cov,
                                 ws.pixel)
    out = MapPoints(ws.points_map[:, :N].T, ws.height_var[:N], ws.horizontal_cov[:, :N].T, ws.pixel[:N])
    if workspace is None:   # fresh arrays of exactly N rows, not views of an oversized buffer
        out = MapPoints(*(np.ascontiguousarray(a) for a in out))
    return out


def depth_to_map_points_reference(depth, K, T_map_cam, pose_cov=None, *, depth_scale=None,
                                  model: SensorModel = D435, min_depth_m: float = MIN_DEPTH_M,
                                  max_depth_m: float = MAX_DEPTH_M, block_px: int | None = None,
                                  bin_at_plane: bool = True) -> MapPoints:
    """NumPy reference of :func:`depth_to_map_points`, composed of the public functions.

    depth_to_metres -> deproject -> incidence_angle_stats, plane_depths -> depth_edges, mixed_windows ->
    despeckle -> point_covariances -> to_map_frame.
    """
    d, scale, K, T, P, zmin, zmax, b = _prepare(depth, K, T_map_cam, pose_cov, depth_scale, min_depth_m,
                                                max_depth_m, block_px)
    model = _frame_model(model, K)
    z = depth_to_metres(d, None if d.dtype != np.uint16 else scale, zmin, zmax)
    pts = deproject(z, K)
    theta, theta_std = incidence_angle_stats(pts, block_px=b)
    z_fit = plane_depths(pts, block_px=b)
    left, right = depth_edges(z, model=model, theta=theta)
    mixed = mixed_windows(pts, block_px=b)
    z_row = surface_depths(z, mixed, model=model, theta=theta)
    # a speckle's depth is its neighbours' median, with its distance from them as a variance floor;
    # the planes, angles, edges and surface medians above are those of the measured depths
    z_measured = z
    z, dev2 = despeckle(z, model=model, theta=theta)
    with np.errstate(invalid="ignore"):
        z_row = np.where(z != z_measured, z, z_row)          # a speckle: its replaced depth
        # in a mixed window, the distance from the pixel's surface median is a variance floor too
        dev2 = np.maximum(dev2, np.where(np.isfinite(z_row), (z - z_row) ** 2, 0.0))
    pts = deproject(z, K)
    # sigma_z at the denoised depth where the local plane describes the pixel (within 3 of the smaller
    # of the two sigmas, and inside the valid range), else at the pixel's own depth (edges, where the
    # window holds two surfaces; planes seen edge-on, whose depth runs away)
    with np.errstate(invalid="ignore"):
        zf = np.where(np.isfinite(z_fit) & (z_fit >= zmin) & (z_fit <= zmax), z_fit, z)
        th = np.nan_to_num(theta)
        zz = np.where(np.isfinite(z), z, 1.0)
        s = np.maximum(axial_sigma_unchecked(np.where(np.isfinite(zf), zf, 1.0), th, model),
                       axial_sigma_unchecked(zz, th, model))
        use_fit = np.isfinite(zf) & (np.abs(z - zf) <= NOISE_DEPTH_SIGMAS * s)
    z_noise = np.where(use_fit, zf, z)
    valid = np.isfinite(z)
    pix = np.flatnonzero(valid.ravel())
    p = pts.reshape(-1, 3)[pix]
    cov = point_covariances(p, theta.ravel()[pix], left.ravel()[pix], right.ravel()[pix], fx=K[0, 0],
                            fy=K[1, 1], model=model, z_noise=z_noise.ravel()[pix], theta_std=theta_std.ravel()[pix],
                            min_axial_var=dev2.ravel()[pix])
    cov_map = to_map_frame(cov, p, T, P)
    points_map = p @ T[:3, :3].T + T[:3, 3]
    if bin_at_plane:          # x, y at the local plane (in a mixed window: or the surface median where nearer)
        zn = z_noise.ravel()[pix]
        zb = np.where(mixed.ravel()[pix], np.minimum(zf.ravel()[pix], z_row.ravel()[pix]), zn)
        pb = p * (zb / p[:, 2])[:, None]
        points_map[:, :2] = (pb @ T[:3, :3].T + T[:3, 3])[:, :2]
    hcov = np.stack([cov_map[:, 0, 0], cov_map[:, 0, 1], cov_map[:, 1, 1]], axis=1)
    return MapPoints(points_map, cov_map[:, 2, 2].copy(), hcov, pix.astype(np.int64))
