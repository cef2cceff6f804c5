"""NumPy reference of the per-cell fusion (:func:`elevmap.map.fusion.fuse_frame`): the same checks and update,
vectorised with ``bincount``, in the order of the module docstring of :mod:`elevmap.map.fusion`. The tests
hold the compiled pass equal to it; ``ElevationMap.update(..., impl="numpy")`` maps with it.
"""

from __future__ import annotations

import numpy as np

from noise_model.formulas import dersimonian_laird_tau2, reduced_chi2_quantile

from .fusion import effective_samples, touched_box
from .fusion_params import FusionParams
from .layers import (
    ELEVATION, HVAR_X, HVAR_XY, HVAR_Y, LAYERS, MAX_HEIGHT, MIN_HEIGHT, NEIGHBOUR_SPREAD, INFO_SQ_SUM,
    INFO_SUM, POINTS, SCATTER, SPREAD, TIME, UPPER_BOUND, VARIANCE, ZERO_WHEN_UNKNOWN,
)
from .settings import check_point_values

__all__ = ["fuse_frame_reference"]


def _cells(geom_n, gx0, gy0, res, x, y):
    """Buffer cell index of each point and the mask of those inside the window (NumPy)."""
    fi = np.floor(x / res) - gx0
    fj = np.floor(y / res) - gy0
    inside = (fi >= 0) & (fi < geom_n) & (fj >= 0) & (fj < geom_n)
    bi = (fi[inside].astype(np.int64) + gx0) % geom_n
    bj = (fj[inside].astype(np.int64) + gy0) % geom_n
    return bi * geom_n + bj, inside


def fuse_frame_reference(data, geometry, points_map, height_var, horizontal_cov, stamp,
                         params: FusionParams, frame_error=None) -> tuple[int, tuple | None]:
    """NumPy reference of :func:`fuse_frame`: the same checks (:func:`elevmap.map.settings.check_point_values`)
    and update, vectorised with bincount."""
    check_point_values(points_map, height_var, horizontal_cov)
    g = geometry
    n = g.n
    p = params.array(g.resolution_m, frame_error)
    thr, min_var, max_var, min_h, max_h, change_min, cap, spread_z, ratio, ell, fratio = p
    x, y, z = points_map[:, 0], points_map[:, 1], points_map[:, 2]
    c, inside = _cells(n, g.gx0, g.gy0, g.resolution_m, x, y)
    z, var = z[inside], height_var[inside]
    hc = None if horizontal_cov is None else horizontal_cov[inside]
    flat = data.reshape(len(LAYERS), n * n)            # a view: writes go to data
    tau2_old = np.where(flat[SPREAD] > 0, flat[SPREAD], 0.0)      # NaN (unknown) -> 0
    nb_old = np.where(flat[NEIGHBOUR_SPREAD] > 0, flat[NEIGHBOUR_SPREAD], 0.0)
    excess = np.maximum(nb_old - tau2_old, 0.0)      # the neighbourhood's part (see neighbour_excess)
    h0, v0 = flat[ELEVATION, c], (flat[VARIANCE] - excess)[c]
    rej = ~np.isnan(h0) & ((z - h0) ** 2 > thr * thr * (var + v0))
    acc = ~rej
    t2 = np.maximum(tau2_old, nb_old)[c]            # see _weight_tau2
    w0 = 1.0 / var
    w = np.where(t2 > 0, 1.0 / (var + t2), w0)
    m = n * n

    def bc(mask, weights=None):
        return np.bincount(c[mask], weights=None if weights is None else weights[mask], minlength=m).astype(float)

    def extreme(mask, fn, init):
        out = np.full(m, init)
        fn.at(out, c[mask], z[mask])
        return out

    W, WZ, N = bc(acc, w), bc(acc, w * z), bc(acc)
    every = np.ones_like(acc)
    W0, WZ0, WZZ0, WW0 = bc(every, w0), bc(every, w0 * z), bc(every, w0 * z * z), bc(every, w0 * w0)
    Wr, WZr, Nr = bc(rej, w), bc(rej, w * z), bc(rej)
    zmin, zmax = extreme(acc, np.minimum, np.inf), extreme(acc, np.maximum, -np.inf)
    zminr, zmaxr = extreme(rej, np.minimum, np.inf), extreme(rej, np.maximum, -np.inf)
    seen = (N + Nr) > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        if hc is not None:
            Hx, Hxy, Hy = (bc(acc, w * hc[:, k]) / W for k in range(3))
        if cap > 0 or ell > 0 or fratio != 1.0:
            def scale(cnt):             # n_eff / (N r), n_eff = min(effective samples, cap): _information_scale
                ne = effective_samples(cnt, ell)
                if cap > 0:
                    ne = np.minimum(ne, cap)
                return np.where(cnt > 0, ne / (np.maximum(cnt, 1) * fratio), 1.0)

            s, sr = scale(N), scale(Nr)
            W, WZ, Wr, WZr = W * s, WZ * s, Wr * sr, WZr * sr
        h, v = flat[ELEVATION].copy(), flat[VARIANCE] - tau2_old - excess
        known = ~np.isnan(h)
        npo = flat[POINTS]
        v = np.where(known & (tau2_old > 0) & (npo > 0),
                     np.maximum(v, tau2_old * np.maximum(N + Nr, 1.0) / np.where(npo > 0, npo, 1.0)), v)
        change = seen & known & (Nr >= change_min) & (Nr > N)
        mr = WZr / Wr
        inflation = np.where(change, (mr - h) ** 2, 0.0)     # added after the fusion (see _merge_cell)
        reset = change & (v + inflation > max_var)
        fuse = seen & ~reset & (N > 0)
        fuse_known = fuse & known
        fuse_new = fuse & ~known
        # P_post = 1 / (1/P + W);  h_post = P_post (h/P + WZ)  (an unknown cell: 1 / W, WZ / W)
        v_post = np.where(fuse_known, 1.0 / (1.0 / v + W), np.where(fuse_new, 1.0 / W, v))
        h_post = np.where(fuse_known, (h / v + WZ) * v_post, np.where(fuse_new, WZ / W, h))
        h_post = np.where(reset, mr, h_post)
        v_post = np.where(reset, 1.0 / Wr, v_post)
        v_post = np.where(change & ~reset, v_post + inflation, v_post)
        # spread statistics (see _spread_update)
        mb = WZ0 / W0
        qb = np.maximum(WZZ0 - WZ0 * mb, 0.0)
        # continued where the cell was known and fused; fresh (this frame's points only) where it is new
        # or was reset
        s1o = np.where(fuse_known, flat[INFO_SUM], 0.0)
        s2o = np.where(fuse_known, flat[INFO_SQ_SUM], 0.0)
        qo = np.where(fuse_known, flat[SCATTER], 0.0)
        Nall = N + Nr
        q = np.where(s1o > 0, qo + qb + s1o * W0 / (s1o + W0) * (mb - h) ** 2 - Nall, qb - (Nall - 1.0))
        s1, s2 = s1o + W0, s2o + WW0
        den = s1 - s2 / s1
        npts = np.where(fuse_known, flat[POINTS], 0.0) + Nall
        kk = np.maximum(npts - 1.0, 1.0)
        crit = reduced_chi2_quantile(kk, spread_z) * kk
        tau2_new = np.where((spread_z >= 0) & (npts >= 2) & (den > 0) & (q + kk > crit) & (q + kk > ratio * kk),
                            dersimonian_laird_tau2(q, s1, s2),
                            0.0)
    on = spread_z >= 0
    stats = (reset | fuse) & on
    tau2 = np.where(stats, tau2_new, np.where(reset, 0.0, tau2_old))
    L = flat
    L[INFO_SUM] = np.where(stats, s1, np.where(reset, 0.0, L[INFO_SUM]))
    L[INFO_SQ_SUM] = np.where(stats, s2, np.where(reset, 0.0, L[INFO_SQ_SUM]))
    L[SCATTER] = np.where(stats, q, np.where(reset, 0.0, L[SCATTER]))
    L[MIN_HEIGHT] = np.where(reset, zminr, np.where(fuse_known, np.minimum(L[MIN_HEIGHT], zmin),
                                                     np.where(fuse_new, zmin, L[MIN_HEIGHT])))
    L[MAX_HEIGHT] = np.where(reset, zmaxr, np.where(fuse_known, np.maximum(L[MAX_HEIGHT], zmax),
                                                     np.where(fuse_new, zmax, L[MAX_HEIGHT])))
    L[POINTS] = np.where(reset, Nr, np.where(fuse_known, L[POINTS] + N, np.where(fuse_new, N, L[POINTS])))
    if hc is not None:
        hx, hy, hxy = np.clip(Hx, min_h, max_h), np.clip(Hy, min_h, max_h), Hxy
    else:
        hx, hy, hxy = min_h, min_h, 0.0
    upd = reset | fuse
    L[HVAR_X] = np.where(reset, min_h, np.where(fuse, hx, L[HVAR_X]))
    L[HVAR_Y] = np.where(reset, min_h, np.where(fuse, hy, L[HVAR_Y]))
    L[HVAR_XY] = np.where(reset, 0.0, np.where(fuse, hxy, L[HVAR_XY]))
    L[TIME] = np.where(upd, float(stamp), L[TIME])
    L[UPPER_BOUND] = np.where(reset | fuse_new, np.nan, L[UPPER_BOUND])
    write = upd | change
    v_post = np.where(write, np.maximum(v_post, min_var), v_post)
    expire = write & (v_post > max_var)
    L[ELEVATION] = np.where(write, h_post, L[ELEVATION])
    nb = np.where(known & ~reset, nb_old, 0.0)
    L[VARIANCE] = np.where(write, v_post + np.maximum(tau2, nb), L[VARIANCE])
    L[SPREAD] = np.where(write, tau2, L[SPREAD])
    L[NEIGHBOUR_SPREAD] = np.where(write, nb, L[NEIGHBOUR_SPREAD])
    with np.errstate(invalid="ignore"):
        stale = write & (L[UPPER_BOUND] < L[ELEVATION])
    L[UPPER_BOUND] = np.where(stale, np.nan, L[UPPER_BOUND])
    L[:, expire] = np.nan
    for name in ZERO_WHEN_UNKNOWN:
        L[LAYERS.index(name), expire] = 0.0
    return int(seen.sum()), touched_box(geometry, points_map)
