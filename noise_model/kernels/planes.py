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
    without valid pixels needs no plane. The angle's quadrature runs node by node across the block row's
    windows (one window per SIMD lane): each window sums its own rule's nodes in order, the 9-node rule
    padded to the grid's length with weight-0 nodes, which add exactly 0 (the gain is finite at every
    capped angle), so each window's sums are those of :func:`noise_model.axial_variance`: the
    9-node rule where theta +- 4 s_theta lies inside (0, theta_max), else the grid (THETA_QUADRATURE,
    THETA_GRID).
    """
    nby, nbx = M.shape[0], M.shape[1]
    ct, theta_max = params[3], params[4]
    disp = params[7] > 0.5
    Vs = np.zeros(nbx * 10)         # (nbx, 10) flat: the moments summed over the window's block rows
    for i in range(max(0, by - radius), min(nby, by + radius + 1)):
        Mi = M[i].ravel()
        for k in range(nbx * 10):
            Vs[k] += Mi[k]
    Sw = np.zeros(nbx * 10)         # ... and over its block columns, each window's blocks in ascending order
    for dj in range(-radius, radius + 1):
        lo, hi = max(0, -dj), min(nbx, nbx - dj)
        src = Vs[(lo + dj) * 10:(hi + dj) * 10]
        dst = Sw[lo * 10:hi * 10]
        for k in range((hi - lo) * 10):
            dst[k] += src[k]
    t_b = np.zeros(nbx)             # per window: theta [rad], its standard deviation [rad], which rule
    ts_b = np.zeros(nbx)
    grid_b = np.zeros(nbx, dtype=np.bool_)
    pa_b = np.zeros(nbx)
    pb_b = np.zeros(nbx)
    pg_b = np.full(nbx, np.nan)
    mixed_b = np.zeros(nbx)         # a block without valid pixels has nothing to denoise (the medians skip it)
    fit_b = np.zeros(nbx, dtype=np.bool_)
    c_b = np.zeros(nbx)             # gamma of the fit (0 where none), total RSS, n and sum w of the window
    total_b = np.zeros(nbx)
    n_b = np.zeros(nbx)
    sw_b = np.zeros(nbx)
    for bx in range(nbx):
        if M[by, bx, 0] > 0.0:
            S = Sw[bx * 10:bx * 10 + 10]
            t, pa, pb, pg, ok = plane_from_inverse_depth_moments(S, min_points, degenerate_rel)
            ts = theta_std_from_moments(S, pa, pb, pg) if ok else 0.0
            t_b[bx] = t
            ts_b[bx] = ts
            grid_b[bx] = not (t - 4.0 * ts > 0.0 and t + 4.0 * ts < theta_max)     # the gain has a kink there
            pa_b[bx] = pa
            pb_b[bx] = pb
            pg_b[bx] = pg if ok else np.nan
            fit_b[bx] = ok
            c_b[bx] = pg
            total_b[bx] = rss(S, S[0], pa, pb) if ok else 0.0
            n_b[bx] = S[0]
            sw_b[bx] = S[3]
    # the mixed test's between-block sums, block by block of the window across the row (the terms of
    # noise_model.geometry.mixed_windows in its order; a block without valid pixels adds exactly 0)
    between_b = np.zeros(nbx)
    dof_b = np.zeros(nbx)
    nblocks_b = np.zeros(nbx)
    Mn = np.empty(nbx)              # the block row's n, su, sv, sw contiguous, so that the loop vectorises
    Mu = np.empty(nbx)
    Mv = np.empty(nbx)
    Mw = np.empty(nbx)
    for i in range(max(0, by - radius), min(nby, by + radius + 1)):
        for bx in range(nbx):
            Mn[bx] = M[i, bx, 0]
            Mu[bx] = M[i, bx, 1]
            Mv[bx] = M[i, bx, 2]
            Mw[bx] = M[i, bx, 3]
        for dj in range(-radius, radius + 1):
            lo, hi = max(0, -dj), min(nbx, nbx - dj)      # windows bx whose block bx + dj is in the image
            n_j, u_j, v_j, w_j = Mn[lo + dj:hi + dj], Mu[lo + dj:hi + dj], Mv[lo + dj:hi + dj], Mw[lo + dj:hi + dj]
            a_w, b_w, c_w = pa_b[lo:hi], pb_b[lo:hi], c_b[lo:hi]
            bet_w, dof_w, nbl_w = between_b[lo:hi], dof_b[lo:hi], nblocks_b[lo:hi]
            for k in range(hi - lo):
                n = n_j[k]
                has = n > 0.0
                rs = w_j[k] - a_w[k] * u_j[k] - b_w[k] * v_j[k] - c_w[k] * n
                q = rs * rs / (n if has else 1.0)
                bet_w[k] += q if has else 0.0
                dof_w[k] += n - 1.0 if has else 0.0
                nbl_w[k] += 1.0 if has else 0.0
    for bx in range(nbx):
        if M[by, bx, 0] > 0.0:
            mixed = True
            if fit_b[bx]:
                mixed = mixed_from_sums(between_b[bx], max(total_b[bx] - between_b[bx], 0.0), dof_b[bx],
                                        nblocks_b[bx], n_b[bx], sw_b[bx], mix_z, RSS_FLOOR_REL)
            mixed_b[bx] = 1.0 if mixed else 0.0
    nk = max(gx.shape[0], hx.shape[0])
    hxp = np.zeros(nk)
    hwp = np.zeros(nk)
    gxp = np.zeros(nk)
    gwp = np.zeros(nk)
    hxp[:hx.shape[0]] = hx
    hwp[:hx.shape[0]] = hw
    gxp[:gx.shape[0]] = gx
    gwp[:gx.shape[0]] = gw
    eg_b = np.zeros(nbx)
    eg2_b = np.zeros(nbx)
    for k in range(nk):
        for bx in range(nbx):
            x = gxp[k] if grid_b[bx] else hxp[k]
            w = gwp[k] if grid_b[bx] else hwp[k]
            g = gain_model(min(abs(t_b[bx] + ts_b[bx] * x), theta_max), ct, disp)
            eg_b[bx] = eg_b[bx] + w * g
            eg2_b[bx] = eg2_b[bx] + w * (g * g)
    for bx in range(nbx):
        valid = M[by, bx, 0] > 0.0
        g = gain_model(min(t_b[bx], theta_max), ct, disp) if valid else 0.0
        eg = eg_b[bx] if valid else 0.0
        eg2 = eg2_b[bx] if valid else 0.0
        for u in range(bx * b, min(W, bx * b + b)):
            gain_px[by, u] = g
            eg_px[by, u] = eg
            eg2_px[by, u] = eg2
            alpha_px[by, u] = pa_b[bx]
            beta_px[by, u] = pb_b[bx]
            gamma_px[by, u] = pg_b[bx]
            mixed_px[by, u] = mixed_b[bx]
