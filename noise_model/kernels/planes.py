"""Stages 1 and 2 of the depth -> map-points kernel: block moments, then per block the window's
inverse-depth plane, its incidence angle and the angle's uncertainty, and whether the window holds two
surfaces.

The NumPy functions these stages compile: :func:`noise_model.incidence_angle_stats`,
:func:`noise_model.plane_depths` and :func:`noise_model.mixed_windows` (the tests hold the whole kernel
equal to :func:`noise_model.depth_to_map_points_reference`, which composes them).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..geometry import RSS_FLOOR_REL
from ..numba_config import JIT
from .compiled import centred, chi2_quantile_per_dof, gain_model, rss

__all__: list[str] = []


@njit(parallel=True, **JIT)
def moments_stage(depth, scale, zmin, zmax, up, vp, b, M, rowcount, offsets):
    """Stage 1: per block of b x b pixels the moments of u', v' and w = 1 / z over its valid pixels, the
    valid count per image row and where each row's points go; returns the number of valid pixels N.

    Parameters
    ----------
    depth : ndarray, shape (H, W)
        Depth in units of ``scale`` [m / unit] (uint16, float32 or float64).
    zmin, zmax : float
        Valid depth range [m]; zmin > 0 and zmax finite (checked by the caller), so zmin <= z <= zmax
        also rejects 0, NaN, +-inf and negative depth.
    up, vp : ndarray, shapes (W,), (H,)
        Normalised pixel coordinates u' = (u - cx) / fx, v' = (v - cy) / fy.
    M : ndarray, shape (nby, nbx, 10), out
        (n, su, sv, sw, suu, suv, svv, suw, svw, sww) per block.
    rowcount : ndarray, shape (H,), int64, out
        Valid pixels per row.
    offsets : ndarray, shape (H + 1,), int64, out
        The exclusive prefix sum of ``rowcount``: row v's points are offsets[v] .. offsets[v + 1] - 1.

    u' is constant down a column and v' along a row, so per block row only six column sums are needed:
    n, sum v', sum v'^2, sum w, sum v' w, sum w^2; the u' factors are applied once per column when the
    columns are summed into blocks. The pixel loop is branch-free (selects) so that it vectorises.
    """
    H, W = depth.shape
    nby, nbx = M.shape[0], M.shape[1]
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
    offsets[0] = 0
    for v in range(H):
        offsets[v + 1] = offsets[v] + rowcount[v]
    return offsets[H]


@njit(**JIT)
def plane_from_inverse_depth_moments(S, min_points, degenerate_rel):
    """(theta [rad], alpha, beta, gamma, ok) of the inverse-depth plane fit w = alpha u' + beta v' + gamma
    of summed moments S = (n, su, sv, sw, suu, suv, svv, suw, svw); see :func:`noise_model.incidence_angles`."""
    n = S[0]
    if n < max(min_points, 3):
        return 0.0, 0.0, 0.0, 0.0, False
    mu, mv, mw, cuu, cuv, cvv, cuw, cvw, _ = centred(S, n)
    det = cuu * cvv - cuv * cuv
    if not det > degenerate_rel * (cuu + cvv) * (cuu + cvv):    # pixels on one image line
        return 0.0, 0.0, 0.0, 0.0, False
    alpha = (cvv * cuw - cuv * cvw) / det
    beta = (cuu * cvw - cuv * cuw) / det
    gamma = mw - alpha * mu - beta * mv
    # |(alpha, beta)| as a square root, not hypot: an inverse-depth plane's slopes [1/m] are far from
    # overflow, and libm's careful hypot cost a sixth of this stage (NumPy's reference: within an ulp)
    return math.atan2(math.sqrt(alpha * alpha + beta * beta), abs(gamma)), alpha, beta, gamma, True


@njit(**JIT)
def theta_std_from_moments(S, alpha, beta, gamma):
    """Standard deviation [rad] of the plane fit's theta from the summed moments S (10,); numba version of
    :func:`noise_model.geometry._theta_std_from_moments_numpy` (the caller passes only fitted planes)."""
    n = S[0]
    if not n > 3.0:
        return 0.0
    mu, mv, mw, cuu, cuv, cvv, cuw, cvw, cww = centred(S, n)
    det = cuu * cvv - cuv * cuv
    res = cww - alpha * cuw - beta * cvw
    res = res if res > RSS_FLOOR_REL * mw * mw else 0.0      # below the rounding of the raw moments: 0
    f = res / (n - 3.0) / det
    vaa = f * cvv
    vbb = f * cuu
    vab = -f * cuv
    vgg = res / (n - 3.0) + mu * mu * vaa + 2.0 * mu * mv * vab + mv * mv * vbb
    vag = -(mu * vaa + mv * vab)
    vbg = -(mu * vab + mv * vbb)
    rho = math.sqrt(alpha * alpha + beta * beta)       # as in plane_from_inverse_depth_moments
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
def gain_moments(t, ts, ct, theta_max, disp, hx, hw, gx, gw):
    """(E[g], E[g^2]) of the angle gain of the model's family for theta ~ N(t, ts^2): the Gauss-Hermite nodes
    hx, weights hw where t +- 4 ts lies inside (0, theta_max), else the grid gx, gw (THETA_QUADRATURE,
    THETA_GRID)."""
    if not (t - 4.0 * ts > 0.0 and t + 4.0 * ts < theta_max):
        hx = gx
        hw = gw
    eg = 0.0
    eg2 = 0.0
    for k in range(hx.shape[0]):
        g = gain_model(min(abs(t + ts * hx[k]), theta_max), ct, disp)
        eg = eg + hw[k] * g
        eg2 = eg2 + hw[k] * (g * g)
    return eg, eg2


@njit(**JIT)
def window_mixed(M, S, by, bx, radius, a, b_, c, mix_z, floor_rel):
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
    total = rss(S, S[0], a, b_)
    return mixed_from_sums(between, max(total - between, 0.0), dof, nblocks, S[0], S[3], mix_z, floor_rel)


@njit(**JIT)
def mixed_from_sums(between, within, dof, nblocks, ntot, swtot, mix_z, floor_rel):
    """The test of noise_model.geometry.mixed_windows from a window's sums (scalar version)."""
    if nblocks <= 3.0 or dof <= 0.0:
        return True
    mw = swtot / ntot
    if within <= floor_rel * mw * mw * dof:          # noise-free: any structure beyond rounding is a second surface
        return between > floor_rel * mw * mw * ntot
    k = nblocks - 3.0
    return between * dof > chi2_quantile_per_dof(k, mix_z) * k * within


@njit(**JIT)
def planes_block_row(by, M, b, W, radius, min_points, degenerate_rel, mix_z, params, hx, hw, gx, gw,
                     gain_px, eg_px, eg2_px, alpha_px, beta_px, gamma_px, mixed_px):
    """Stage 2 for block row ``by``: per block, the plane fitted over the (2 radius + 1)^2 blocks around it,
    spread over the block's pixel columns (run by :func:`noise_model.kernels.surfaces.surfaces_stage`).

    Parameters
    ----------
    M : ndarray, shape (nby, nbx, 10)
        Block moments of :func:`moments_stage`.
    b, W : int
        Block size [px] and image width [px].
    params : ndarray
        SensorModel.params_array: c0, c1, c2, c_theta, theta_max, sigma_L, sigma_R, family.
    hx, hw, gx, gw : ndarray
        Gauss-Hermite nodes and weights, and the grid's, of the angle's quadrature.
    gain_px, eg_px, eg2_px : ndarray, shape (nby, W), out
        The angle gain at the window's theta (capped) and E[g], E[g^2] over theta's uncertainty.
    alpha_px, beta_px, gamma_px : ndarray, shape (nby, W), out
        The window's plane w = alpha u' + beta v' + gamma [1/m]; gamma NaN: no plane.
    mixed_px : ndarray, shape (nby, W), out
        1.0 where the window holds more than one surface (or has no plane), else 0.0; 0.0 for blocks
        without valid pixels.

    The window sum is separable: over the block rows first (Vs), then over the block columns. A block
    without valid pixels needs no plane.
    """
    nby, nbx = M.shape[0], M.shape[1]
    ct, theta_max = params[3], params[4]
    disp = params[7] > 0.5
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
        mixed = False           # a block without valid pixels has nothing to denoise (the medians skip it)
        if M[by, bx, 0] > 0.0:
            S[:] = 0.0
            for j in range(max(0, bx - radius), min(nbx, bx + radius + 1)):
                for c in range(10):
                    S[c] += Vs[j, c]
            t, pa, pb, pg, ok = plane_from_inverse_depth_moments(S, min_points, degenerate_rel)
            ts = theta_std_from_moments(S, pa, pb, pg) if ok else 0.0
            mixed = window_mixed(M, S, by, bx, radius, pa, pb, pg, mix_z, RSS_FLOOR_REL) if ok else True
            if not ok:
                pg = np.nan
            eg, eg2 = gain_moments(t, ts, ct, theta_max, disp, hx, hw, gx, gw)
            g = gain_model(min(t, theta_max), ct, disp)
        for u in range(bx * b, min(W, bx * b + b)):
            gain_px[by, u] = g
            eg_px[by, u] = eg
            eg2_px[by, u] = eg2
            alpha_px[by, u] = pa
            beta_px[by, u] = pb
            gamma_px[by, u] = pg
            mixed_px[by, u] = 1.0 if mixed else 0.0
