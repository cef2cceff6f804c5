"""Stage 4 of the depth -> map-points kernel: each valid pixel's point, its covariance in the camera frame,
rotated into the map frame with the pose term, written to the outputs in row-major pixel order (in the
same parallel region as the surface medians of stage 3c).

The NumPy functions this stage compiles: :func:`noise_model.point_covariances` and
:func:`noise_model.to_map_frame`, with the depth at which sigma_z is evaluated and the binning depth of
:class:`noise_model.MapPoints` (the tests hold the whole kernel equal to
:func:`noise_model.depth_to_map_points_reference`).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..numba_config import JIT
from .compiled import POINTS, SURFACE_MEDIANS, expected_model, interleaved, sigma_model
from .surfaces import LEFT_EDGE, RIGHT_EDGE, SPECKLE, surface_medians_block_row

__all__: list[str] = []


@njit(parallel=True, **JIT)
def points_stage(parts, depth, scale, zmin, zmax, up, vp, fx, fy, T, P, use_pose, pose_form, params, family,
                 noise_sigmas, b, bin_at_plane, jump_rel, thr_sig, rows_half, surface_net, rowmed, gain_px, eg_px,
                 eg2_px, alpha_px, beta_px, gamma_px, mixed_px, offsets, flags, speckle_z, surface_z, coord_max,
                 var_min, var_max, pts, hvar, hcov, pix, outside):
    """Stages 3c and 4 per block row, in one parallel region: those of ``parts`` (SURFACE_MEDIANS, POINTS
    of :mod:`noise_model.kernels.compiled`). Stage 3c, the surface medians of the block row's pixels:
    :func:`noise_model.kernels.surfaces.surface_medians_block_row` (jump_rel .. rowmed in, surface_z out).
    Stage 4, inline below: fill columns offsets[v] .. offsets[v + 1] - 1 of pts (3, n) [m], hvar (n,)
    [m^2], hcov (3, n) [m^2] and pix (n,) with the valid pixels of row v, and count in outside[v] the points
    of row v whose values lie outside the bounds a map takes (see :func:`count_outside`, whose predicate the
    loop repeats inline so that it stays vectorised).

    Parameters
    ----------
    parts : int
        Bits of SURFACE_MEDIANS, POINTS.
    depth, scale, zmin, zmax
        As in :func:`noise_model.kernels.planes.moments_stage`.
    up, vp : ndarray, shapes (W,), (H,)
        Normalised pixel coordinates.
    fx, fy : float
        Focal lengths [px].
    T : ndarray, shape (4, 4)
        T_map_cam.
    P : ndarray, shape (6, 6)
        Pose covariance (translation [m^2], rotation [rad^2]), used where ``use_pose``.
    pose_form : None or True
        True: the pose term J P J^T with every entry of P. None: P is diagonal (a common odometry covariance)
        or not used, and its products with the zero entries are left out; the entries left are summed in the
        same order, and a product with an exact zero adds an exact zero, so both forms agree on a diagonal P.
        As ``family``, its type tells numba which: each compiles to a loop with only its own pose term (a
        flag would make the vectorised loop compute both and select). The mapper's usual inputs (a diagonal
        pose covariance or none) share one compiled kernel, in which ``use_pose`` selects between the loop
        with the diagonal term and the loop without.
    params : ndarray
        SensorModel.params_array.
    family : None or True
        None for the paper's family, True for the disparity family: its type, not its value, tells numba
        which, so each family compiles to a loop without the other's arithmetic (params[7] says the same).
    noise_sigmas : float
        sigma_z is evaluated at the local plane's depth when the pixel lies within this many sigma of it.
    gain_px .. mixed_px : ndarray, shape (nby, W)
        The window's plane per pixel column (:func:`noise_model.kernels.planes.planes_block_row`).
    offsets : ndarray, shape (H + 1,)
        Where each row's points go (:func:`noise_model.kernels.planes.moments_stage`).
    flags, speckle_z, surface_z : ndarray, shape (H, W)
        The edges, speckles and surface medians of :mod:`noise_model.kernels.surfaces`.
    coord_max, var_min, var_max : float
        The bounds of :func:`count_outside`: coordinates [m], height variance [m^2].
    outside : ndarray, shape (H,), int64
        Out: per row, the number of its points that :func:`count_outside` would count (0 for a row
        without points).

    Returns
    -------
    int
        The number of points outside the bounds (the sum of ``outside``); 0 unless ``parts`` has POINTS.

    Per row: (a) compaction of the valid pixels into row buffers, a scalar loop, (b) the arithmetic over
    the compacted pixels, written to the outputs. (b) vectorises: it indexes from 0 or with unsigned
    indices (a signed index that may be negative gets numba's wraparound select, which makes the access
    non-contiguous for LLVM), is branch-free (selects), and indexes arrays directly rather than through
    views created in the prange body, so that numba can mark them noalias. It is bound by its square
    roots, its division and its stores, 64 B per point. Runs of valid pixels, each its own loop without
    compaction, cost more: the scalar remainder of every run (a hole every 50 pixels) takes longer than the
    compaction.
    """
    H, W = depth.shape
    nby = gain_px.shape[0]
    c0, c1, c2 = params[0], params[1], params[2]
    s_left, s_right = params[5], params[6]
    disp = family is not None
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
    full_pose = pose_form is not None
    nan = np.nan
    inf = np.inf
    for ib in prange(nby):
        by = interleaved(ib, nby)
        if parts & SURFACE_MEDIANS:
            surface_medians_block_row(by, depth, scale, zmin, zmax, params, family, jump_rel, thr_sig, b, rows_half,
                                      surface_net, gain_px, mixed_px, rowmed, surface_z)
        cu = np.empty(W, dtype=np.uint64)     # unsigned: the gathers by column need no wraparound select
        cz = np.empty(W)
        cf = np.empty(W, dtype=np.uint8)
        for v in range(by * b, min(H, by * b + b)):
            if not parts & POINTS:
                break
            outside[v] = 0
            if offsets[v + 1] == offsets[v]:
                continue
            # (a) compaction of the valid pixels (column, depth, flags): every pixel is stored, the count
            # advances only on valid ones (stage 1's validity test, so k ends at the row's valid count and
            # each row fills exactly its own output range)
            k = 0
            for u in range(W):
                z = depth[v, u] * scale
                f = flags[v, u]
                cu[k] = np.uint64(u)
                cz[k] = z
                cf[k] = f
                k += 1 if (z >= zmin) & (z <= zmax) else 0

            # (b) the arithmetic over the compacted pixels. Unsigned output index: no wraparound select, so
            # the stores are contiguous
            k0 = np.uint64(offsets[v])
            vv = vp[v]
            b0 = R01 * vv + R02      # a = R r = R[:, 0] u' + (R[:, 1] v' + R[:, 2])
            b1 = R11 * vv + R12
            b2 = R21 * vv + R22
            base = v * W
            nout = 0
            for j in range(np.uint64(k)):
                u = cu[j]
                z = cz[j]
                f = cf[j]
                # a speckle: its depth is its neighbours' median, and it is as uncertain as its distance from
                # them (selects, so that the loop still vectorises)
                sp = (f & SPECKLE) != 0
                md = speckle_z[v, u] if sp else z
                dev2 = (z - md) * (z - md)
                z = md
                zz = z * z
                # lateral x variance: sigma_L^2 / sigma_R^2 on edges, else the pixel footprint
                left = (f & LEFT_EDGE) != 0
                right = (f & RIGHT_EDGE) != 0
                var_x = (sLR2 if right else sL2) if left else (sR2 if right else zz * pix_var_x)
                var_y = zz * pix_var_y
                # sigma_z at the local plane's depth when the pixel lies within noise_sigmas of it (a
                # weight must not depend on the pixel's own noise), else at its own depth. Both
                # candidates are evaluated and one selected, so that each square root is taken once.
                g = gain_px[by, u]
                wf = alpha_px[by, u] * up[u] + beta_px[by, u] * vv + gamma_px[by, u]
                zf = 1.0 / wf if wf > 0.0 else z
                zf = zf if (zf >= zmin) & (zf <= zmax) else z
                sf = max(sigma_model(zf, g, c0, c1, c2, disp), sigma_model(z, g, c0, c1, c2, disp))
                at_plane = abs(z - zf) <= noise_sigmas * sf
                zs = zf if at_plane else z
                # E[sigma_z^2] over the uncertainty of theta (noise_model.axial_variance)
                e_f = expected_model(zf, eg_px[by, u], eg2_px[by, u], c0, c1, c2, disp)
                e_z = expected_model(z, eg_px[by, u], eg2_px[by, u], c0, c1, c2, disp)
                s2 = max(e_f if at_plane else e_z, dev2)
                # in a window of two surfaces the model's sigma is the fit's across both (its angle,
                # its plane): the pixel's distance from its own surface's median is a floor, as a
                # speckle's from its neighbours (a speckle: its replaced depth, so 0; NaN: not mixed)
                zr = z if sp else (surface_z[v, u] if mixed_px[by, u] > 0.0 else nan)
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
                if full_pose:                        # J P J^T in full (its own compiled loop)
                    cxx += (P00 + 2.0 * (q2 * P04 - q1 * P05) + q2 * q2 * P44 - 2.0 * q1 * q2 * P45
                            + q1 * q1 * P55)
                    cyy += (P11 + 2.0 * (q0 * P15 - q2 * P13) + q2 * q2 * P33 - 2.0 * q0 * q2 * P35
                            + q0 * q0 * P55)
                    czz += (P22 + 2.0 * (q1 * P23 - q0 * P24) + q1 * q1 * P33 - 2.0 * q0 * q1 * P34
                            + q0 * q0 * P44)
                    cxy += (P01 - q2 * P03 + q0 * P05
                            + q2 * (P14 - q2 * P34 + q0 * P45)
                            - q1 * (P15 - q2 * P35 + q0 * P55))
                elif use_pose:                       # P diagonal: the terms left of the full form
                    cxx += P00 + q2 * q2 * P44 + q1 * q1 * P55
                    cyy += P11 + q2 * q2 * P33 + q0 * q0 * P55
                    czz += P22 + q1 * q1 * P33 + q0 * q0 * P44
                    cxy += P01 - q1 * (q0 * P55)
                i = k0 + j
                # x, y where the ray meets the local plane (the cell the pixel looks at); in a window of
                # two surfaces at the nearer of the plane and the surface median (a speckle: its
                # replaced depth); z from the measured depth (see MapPoints)
                zb = (min(zf, zr) if mixed_px[by, u] > 0.0 else zs) if bin_at_plane else z
                x = zb * a0 + t0
                y = zb * a1 + t1
                zm = q2 + t2
                pts[0, i] = x
                pts[1, i] = y
                pts[2, i] = zm
                hvar[i] = czz
                hcov[0, i] = cxx
                hcov[1, i] = cxy
                hcov[2, i] = cyy
                pix[i] = base + np.int64(u)
                # the predicate of count_outside (NaN fails every comparison, so it counts)
                ok = ((abs(x) <= coord_max) & (abs(y) <= coord_max) & (abs(zm) <= coord_max) & (czz >= var_min)
                      & (czz <= var_max) & (cxx >= 0.0) & (cxx < inf) & (cyy >= 0.0) & (cyy < inf)
                      & (abs(cxy) < inf))
                nout += 0 if ok else 1
            outside[v] = nout
    total = 0
    if parts & POINTS:
        for v in range(H):
            total += outside[v]
    return total


def count_outside(points_map, height_var, horizontal_cov, coord_max, var_min, var_max):
    """Number of points whose values lie outside the bounds a map takes (NumPy; the points stage counts
    the same inline as it writes its outputs).

    A point counts when a coordinate is not finite or beyond ``coord_max`` in magnitude, its height
    variance is not within [var_min, var_max], or its horizontal covariance has an xx or yy entry that is
    negative or not finite, or an xy entry that is not finite.

    Parameters
    ----------
    points_map : ndarray, shape (N, 3) [m]
    height_var : ndarray, shape (N,) [m^2]
    horizontal_cov : ndarray, shape (N, 3) [m^2]
        (Sigma_xx, Sigma_xy, Sigma_yy).
    coord_max, var_min, var_max : float
        The bounds: coordinates [m], height variance [m^2].

    Returns
    -------
    int
    """
    with np.errstate(invalid="ignore"):
        ok = np.all(np.abs(points_map) <= coord_max, axis=1)
        ok &= (height_var >= var_min) & (height_var <= var_max)
        h = horizontal_cov
        ok &= (h[:, 0] >= 0.0) & (h[:, 0] < np.inf) & (h[:, 2] >= 0.0) & (h[:, 2] < np.inf) & (np.abs(h[:, 1]) < np.inf)
    return int(len(ok) - np.count_nonzero(ok))
