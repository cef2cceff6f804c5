"""Process-noise (prediction) step and on-demand ellipse-weighted map fusion.

Both follow ANYbotics' elevation_mapping ("EM"; Fankhauser et al., "Robot-centric elevation mapping
with uncertainty estimates", CLAWAR 2014, and "Probabilistic terrain mapping for mobile robots with
uncertain localization", RA-L 2018). The equation numbers below are those quoted in EM's code
comments (``src/RobotMotionMapUpdater.cpp``); docs/fusion.md sets them beside the other update rules.

Prediction (:func:`predict`)
----------------------------
The caller passes the covariance Sigma of the robot's pose *change* since the last prediction,
6 x 6, (t_x, t_y, t_z [m^2], then rotations about the map's x, y, z [rad^2]), already expressed in
the map frame. (EM derives it from two absolute pose covariances, its eqs. (A.3)-(A.14); that step
is the caller's.) A pose error (dt, dtheta) moves a map point P by

    dP = dt + dtheta x r = dt - [r]_x dtheta,     r = P - p_robot,

so J_r = I (EM: -R_BM^T, the same covariance for a map-frame Sigma) and J_R = -[r]_x (EM eq. (25),
with r = M_r_BP = cell centre (x, y) with its elevation h as z, minus the robot position taken from
``T_map_base``). Per known cell, with Sigma_t the translation block and sigma_a^2, sigma_b^2,
sigma_ab, sigma_psi^2 the roll, pitch, roll-pitch and yaw entries (EM eq. (24): Sigma_P += J_r
Sigma_t J_r^T + J_R Sigma_R J_R^T, term by term):

    variance               += Sigma_t[z, z] + ry^2 sigma_a^2 - 2 rx ry sigma_ab + rx^2 sigma_b^2
    horizontal_variance_x  += Sigma_t[x, x] + ry^2 sigma_psi^2
    horizontal_variance_y  += Sigma_t[y, y] + rx^2 sigma_psi^2
    horizontal_variance_xy += Sigma_t[x, y] - rx ry sigma_psi^2

* Height: EM adds the z-translation variance only (its rotation covariance is yaw-only, and yaw
  does not move a point vertically). Here the roll/pitch block is added too: the z row of
  -[r]_x is (ry, -rx, 0), i.e. a roll error alpha lifts the cell by alpha ry and a pitch error
  beta by -beta rx. The cell's own height r_z drops out of every included term (it would only
  enter through roll/pitch on the *horizontal* position, which is left out as in EM).
* Horizontal: translation x/y block plus the yaw-only rotation term (as EM), J_R[:, yaw] =
  (-ry, rx, 0): the variance grows by r^2 sigma_psi^2 perpendicular to r. EM drops the
  translation xy term; it is included here (zero for EM's diagonal-in-practice covariances).
* Cross-covariances between translation and rotation, roll/pitch-yaw cross terms, and roll/pitch
  effects on the horizontal position are not included (EM uses the translation and rotation blocks
  separately).

Time-based growth (EMC ``update_variance``: var += time_variance on valid cells): with ``dt`` [s]
and ``time_variance_rate`` [m^2/s], variance += rate * dt on known cells.

Then the clamp (EM ``clean()`` / ``VarianceClampOperator``): variance < min_variance ->
min_variance; variance > max_variance (or NaN) -> the cell becomes unknown (every layer to
``UNKNOWN_VALUES``; EM sets +inf, which makes its cell invalid). Horizontal variances are
*saturated* to [min_horizontal_variance, max_horizontal_variance] (EM maps values above the maximum
to +inf instead; saturation matches :mod:`elevmap.map.fusion`), a NaN horizontal variance of a known
cell is reset to the minimum (the value a fresh cell gets), and horizontal_variance_xy is limited to
|xy| <= sqrt(x y) so that the 2 x 2 covariance stays positive semi-definite after saturation (not in
EM).

Fusion (:func:`fused_map`), EM ``ElevationMap::fuse``
------------------------------------------------------
For each known cell c, with Sigma_c = [[hx, hxy], [hxy, hy]] and eigenvalues lambda_max >=
lambda_min (absolute values, as EM's ``cwiseAbs``), major-axis angle phi = atan2(2 hxy, hx - hy) / 2:

* error ellipse with half-axes a_k = 2.486 sqrt(lambda_k) + sqrt(2) res / 2 (EM: full lengths
  2 * 2.486 sqrt(lambda) + sqrt(2) res, "95.45 % ... 2.486-sigma for 2 dof", plus sqrt(2) res for
  conservative cell inclusion), rotated by phi;
* neighbours: the known cells whose centre lies in the ellipse, (u/a_max)^2 + (v/a_min)^2 <= 1 with
  (u, v) the centre offset projected onto the major and minor axes (``grid_map::EllipseIterator``),
  limited to the map window (no wrap-around);
* weight w_i = max(2 eps_float32, [Phi((|u|+res/2)/sigma_max) - Phi((|u|-res/2)/sigma_max)]
  [Phi((|v|+res/2)/sigma_min) - Phi((|v|-res/2)/sigma_min)]), sigma_k = sqrt(lambda_k);
* elevation = sum w_i h_i / sum w_i; lower_bound / upper_bound = the weighted 1 % / 99 %
  quantiles of {h_i - 2 sigma_i} / {h_i + 2 sigma_i} with EM's estimator
  (``WeightedEmpiricalCumulativeDistributionFunction``): equal values merged (weights summed),
  sorted values v_1 < ... < v_m get P_k = (sum_{j<=k} w_j - w_1) / (W - w_1) (P_1 = 0, P_m = 1),
  linear interpolation in P; a single value is its own quantile;
* uncertainty_range = upper_bound - lower_bound (EM ``publishFusedElevationMap``).

A cell whose ellipse holds only itself returns its own elevation and h -/+ 2 sigma. Deviation from
EM's code, kept on purpose: EM projects the offset for the *weights* with Rotation2D(+phi) (the
inverse of the frame change its EllipseIterator uses); that agrees with the projection above only
for axis-aligned ellipses (phi a multiple of 90 deg). Standard deviations are floored at
1e-9 res to avoid 0/0 for a degenerate ellipse. Note that EM's quantile estimator gives the smallest
distinct value probability 0 (with two distinct values it ignores the weights), so lower_bound <=
elevation is not guaranteed when 2 sigma is below 1 % of the height spread in the ellipse.

Each numba kernel has a NumPy reference beside it (``*_reference``); the tests hold them equal. The
kernels write each cell from one iteration only, so results do not depend on the thread count.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from scipy.special import ndtr

from noise_model.checks import check_pose_cov, check_transform
from noise_model.numba_config import JIT, resolve_threads, threads

from .layers import ELEVATION, HVAR_X, HVAR_XY, HVAR_Y, UNKNOWN_VALUES, VARIANCE, clear_sums

__all__ = ["predict", "predict_reference", "fused_map", "fused_map_reference", "UNCERTAINTY_FACTOR",
           "FUSED_LAYERS"]


#: sqrt(chi^2_2(0.9545)) = sqrt(6.18): the 95.45 % error ellipse of a 2-dof Gaussian (EM ``fuse``).
UNCERTAINTY_FACTOR = 2.486
#: Smallest fusion weight (EM: 2 * std::numeric_limits<float>::epsilon()).
MIN_WEIGHT = 2.0 * float(np.finfo(np.float32).eps)
#: Layers returned by :func:`fused_map`.
FUSED_LAYERS = ("elevation", "lower_bound", "upper_bound", "uncertainty_range")
LOWER_QUANTILE = 0.01
UPPER_QUANTILE = 0.99
_SQRT1_2 = math.sqrt(0.5)
_SIGMA_FLOOR_REL = 1e-9
#: Largest plausible rotation variance [rad^2]: a larger value almost certainly is in deg^2.
_MAX_ROT_VAR = math.pi ** 2


# ---------------------------------------------------------------------------------------------
# input checks (shared by the numba entry and its reference)
# ---------------------------------------------------------------------------------------------
def _prepare_predict(emap, relative_pose_cov, T_map_base, dt, time_variance_rate):
    """Validate the inputs; returns (coef (8,), robot (3,), rate*dt, params (7,))."""
    coef = np.zeros(8)         # zz, xx, yy, xy, roll, pitch, roll-pitch, yaw
    if relative_pose_cov is not None:
        C = check_pose_cov(relative_pose_cov, "relative_pose_cov")
        rot = np.diag(C)[3:]
        if float(rot.max()) > _MAX_ROT_VAR:
            raise ValueError(f"relative_pose_cov rotation variances up to {float(rot.max()):.3g}: they must be in "
                             f"rad^2 (degrees^2?)")
        coef[:] = (C[2, 2], C[0, 0], C[1, 1], C[0, 1], C[3, 3], C[4, 4], C[3, 4], C[5, 5])
    robot = np.zeros(3)
    if T_map_base is not None:
        robot = check_transform(T_map_base, "T_map_base")[:3, 3].copy()
    elif coef[4] > 0.0 or coef[5] > 0.0 or coef[7] > 0.0:
        raise ValueError("T_map_base (the robot pose) is required when relative_pose_cov has rotation variances: "
                         "their effect grows with each cell's distance from the robot")
    try:
        rate = float(time_variance_rate)
    except (TypeError, ValueError):
        raise ValueError(f"time_variance_rate must be a number [m^2/s], got {time_variance_rate!r}") from None
    if not (math.isfinite(rate) and rate >= 0.0):
        raise ValueError(f"time_variance_rate must be finite and >= 0 [m^2/s], got {time_variance_rate!r}")
    growth = 0.0
    if dt is not None:
        try:
            d = float(dt)
        except (TypeError, ValueError):
            raise ValueError(f"dt must be a number [s], got {dt!r}") from None
        if not (math.isfinite(d) and d >= 0.0):
            raise ValueError(f"dt must be finite and >= 0 [s], got {dt!r}")
        growth = rate * d
    params = emap.fusion_params.array(emap.geometry.resolution_m)
    return coef, robot, growth, params


# ---------------------------------------------------------------------------------------------
# prediction: numba
# ---------------------------------------------------------------------------------------------
@njit(parallel=True, **JIT)
def _predict_kernel(data, gx0, gy0, res, coef, robot, growth, params):
    n = data.shape[1]
    nl = data.shape[0]
    sx = gx0 % n
    sy = gy0 % n
    szz, sxx, syy, sxy, saa, sbb, sab, spsi = (coef[0], coef[1], coef[2], coef[3], coef[4], coef[5], coef[6],
                                               coef[7])
    min_var, max_var, min_h, max_h = params[1], params[2], params[3], params[4]
    expired = np.zeros(n, dtype=np.int64)
    for bi in prange(n):
        i = bi - sx
        if i < 0:
            i += n
        rx = (gx0 + i + 0.5) * res - robot[0]
        cnt = 0
        for bj in range(n):
            h = data[ELEVATION, bi, bj]
            if not math.isfinite(h):
                continue
            j = bj - sy
            if j < 0:
                j += n
            ry = (gy0 + j + 0.5) * res - robot[1]
            v = data[VARIANCE, bi, bj] + (szz + (ry * ry * saa - 2.0 * rx * ry * sab + rx * rx * sbb)) + growth
            if v < min_var:
                v = min_var
            if not (v <= max_var):                 # above the maximum (or NaN): the cell is unknown
                for layer in range(nl):
                    data[layer, bi, bj] = np.nan
                clear_sums(data, bi, bj)
                cnt += 1
                continue
            data[VARIANCE, bi, bj] = v
            hx = data[HVAR_X, bi, bj] + (sxx + ry * ry * spsi)
            hy = data[HVAR_Y, bi, bj] + (syy + rx * rx * spsi)
            hxy = data[HVAR_XY, bi, bj] + (sxy - rx * ry * spsi)
            if not (hx >= min_h):
                hx = min_h
            elif hx > max_h:
                hx = max_h
            if not (hy >= min_h):
                hy = min_h
            elif hy > max_h:
                hy = max_h
            lim = math.sqrt(hx * hy)
            if not (hxy >= -lim):               # below -lim, or NaN (-> 0)
                hxy = -lim if hxy < 0.0 else 0.0
            elif hxy > lim:
                hxy = lim
            data[HVAR_X, bi, bj] = hx
            data[HVAR_Y, bi, bj] = hy
            data[HVAR_XY, bi, bj] = hxy
        expired[bi] = cnt
    return expired.sum()


def predict(emap, relative_pose_cov=None, T_map_base=None, dt=None, time_variance_rate=0.0) -> dict:
    """Process-noise step before a frame is fused (see the module docstring for the equations).

    Parameters
    ----------
    emap : elevmap.ElevationMap
        Updated in place.
    relative_pose_cov : array_like, shape (6, 6), optional
        Covariance of the robot's pose change since the last prediction, in the map frame:
        translation x, y, z [m^2], then rotation about x, y, z [rad^2].
    T_map_base : array_like, shape (4, 4), optional
        Robot (base) pose in the map frame; its position is the centre of the rotation errors.
        Required when ``relative_pose_cov`` has rotation variances.
    dt : float, optional
        Time since the last prediction [s], >= 0; None: no time-based growth.
    time_variance_rate : float
        Height-variance growth per second [m^2/s], >= 0 (variance += rate * dt on known cells).

    Returns
    -------
    dict
        ``{"cells_expired": int}``: known cells that became unknown (variance above max_variance).
    """
    coef, robot, growth, params = _prepare_predict(emap, relative_pose_cov, T_map_base, dt, time_variance_rate)
    g = emap.geometry
    n = resolve_threads(emap.nthreads)
    with threads(n):
        expired = _predict_kernel(emap.data, g.gx0, g.gy0, g.resolution_m, coef, robot, growth, params)
    return {"cells_expired": int(expired)}


def predict_reference(emap, relative_pose_cov=None, T_map_base=None, dt=None, time_variance_rate=0.0) -> dict:
    """NumPy reference of :func:`predict` (vectorised over the buffer)."""
    coef, robot, growth, params = _prepare_predict(emap, relative_pose_cov, T_map_base, dt, time_variance_rate)
    szz, sxx, syy, sxy, saa, sbb, sab, spsi = coef
    min_var, max_var, min_h, max_h = params[1:5]
    g = emap.geometry
    n, res = g.n, g.resolution_m
    sx, sy = g.start_index
    k = np.arange(n)
    rx = ((g.gx0 + (k - sx) % n + 0.5) * res - robot[0])[:, None]     # buffer row bi -> map row i
    ry = ((g.gy0 + (k - sy) % n + 0.5) * res - robot[1])[None, :]
    d = emap.data
    known = np.isfinite(d[ELEVATION])
    with np.errstate(invalid="ignore"):
        v = d[VARIANCE] + (szz + (ry * ry * saa - 2.0 * rx * ry * sab + rx * rx * sbb)) + growth
        v = np.where(v < min_var, min_var, v)
        expire = known & ~(v <= max_var)
        keep = known & ~expire
        hx = d[HVAR_X] + (sxx + ry * ry * spsi)
        hy = d[HVAR_Y] + (syy + rx * rx * spsi)
        hxy = d[HVAR_XY] + (sxy - rx * ry * spsi)
        hx = np.where(hx >= min_h, np.minimum(hx, max_h), min_h)
        hy = np.where(hy >= min_h, np.minimum(hy, max_h), min_h)
        lim = np.sqrt(hx * hy)
        hxy = np.where(np.isnan(hxy), 0.0, np.clip(hxy, -lim, lim))
    d[VARIANCE] = np.where(keep, v, d[VARIANCE])
    d[HVAR_X] = np.where(keep, hx, d[HVAR_X])
    d[HVAR_Y] = np.where(keep, hy, d[HVAR_Y])
    d[HVAR_XY] = np.where(keep, hxy, d[HVAR_XY])
    d[:, expire] = np.array(UNKNOWN_VALUES)[:, None]
    return {"cells_expired": int(expire.sum())}


# ---------------------------------------------------------------------------------------------
# fusion: numba
# ---------------------------------------------------------------------------------------------
@njit(**JIT)
def _ndtr(x):
    """Standard normal CDF from math.erf / math.erfc, with the branches of scipy's (cephes) ndtr."""
    z = x * _SQRT1_2
    az = abs(z)
    if az < _SQRT1_2:
        return 0.5 + 0.5 * math.erf(z)
    y = 0.5 * math.erfc(az)
    return 1.0 - y if z > 0.0 else y


@njit(**JIT)
def _ellipse(hx, hy, hxy, res, min_h):
    """(cos phi, sin phi, sigma_max, sigma_min, a_max, a_min) of one cell's horizontal covariance."""
    if not math.isfinite(hx):
        hx = min_h
    if not math.isfinite(hy):
        hy = min_h
    if not math.isfinite(hxy):
        hxy = 0.0
    m = 0.5 * (hx + hy)
    dd = 0.5 * (hx - hy)
    r = math.sqrt(dd * dd + hxy * hxy)
    l1 = abs(m + r)
    l2 = abs(m - r)
    phi = 0.5 * math.atan2(2.0 * hxy, hx - hy)
    if l2 > l1:
        l1, l2 = l2, l1
        phi += 0.5 * math.pi
    floor = _SIGMA_FLOOR_REL * res
    s1 = max(math.sqrt(l1), floor)
    s2 = max(math.sqrt(l2), floor)
    ext = math.sqrt(2.0) * res / 2.0
    return math.cos(phi), math.sin(phi), s1, s2, UNCERTAINTY_FACTOR * math.sqrt(l1) + ext, \
        UNCERTAINTY_FACTOR * math.sqrt(l2) + ext


@njit(**JIT)
def _wquantile(vals, wts, p):
    """EM's weighted empirical quantile (see the module docstring) of vals (k,) with weights wts."""
    k = vals.shape[0]
    order = np.argsort(vals, kind="mergesort")
    u = np.empty(k)
    s = np.empty(k)
    m = 0
    for t in range(k):
        x = vals[order[t]]
        if m > 0 and x == u[m - 1]:
            s[m - 1] += wts[order[t]]
        else:
            u[m] = x
            s[m] = wts[order[t]]
            m += 1
    if m == 1 or p <= 0.0:
        return u[0]
    if p >= 1.0:
        return u[m - 1]
    total = 0.0
    for t in range(m):
        total += s[t]
    adapted = total - s[0]
    cum = -s[0]
    p_prev = 0.0
    for t in range(m):
        cum += s[t]
        pt = cum / adapted
        if t > 0 and pt >= p:
            return u[t - 1] + (p - p_prev) * (u[t] - u[t - 1]) / (pt - p_prev)
        p_prev = pt
    return u[m - 1]


@njit(parallel=True, **JIT)
def _fuse_map_kernel(E, V, HX, HY, HXY, res, min_h, out):
    n = E.shape[0]
    half = 0.5 * res
    for i in prange(n):
        cap = 16
        hs = np.empty(cap)
        lo = np.empty(cap)
        hi = np.empty(cap)
        ws = np.empty(cap)
        for j in range(n):
            h0 = E[i, j]
            if not math.isfinite(h0):
                for c in range(4):
                    out[c, i, j] = np.nan
                continue
            c_, s_, s1, s2, a1, a2 = _ellipse(HX[i, j], HY[i, j], HXY[i, j], res, min_h)
            ex = math.sqrt((a1 * c_) ** 2 + (a2 * s_) ** 2)
            ey = math.sqrt((a1 * s_) ** 2 + (a2 * c_) ** 2)
            ki = int(ex / res) + 1
            kj = int(ey / res) + 1
            i0 = max(i - ki, 0)
            i1 = min(i + ki, n - 1)
            j0 = max(j - kj, 0)
            j1 = min(j + kj, n - 1)
            need = (i1 - i0 + 1) * (j1 - j0 + 1)
            if need > cap:
                cap = need
                hs = np.empty(cap)
                lo = np.empty(cap)
                hi = np.empty(cap)
                ws = np.empty(cap)
            k = 0
            for ii in range(i0, i1 + 1):
                dx = (ii - i) * res
                for jj in range(j0, j1 + 1):
                    hk = E[ii, jj]
                    if not math.isfinite(hk):
                        continue
                    dy = (jj - j) * res
                    u = dx * c_ + dy * s_
                    v = -dx * s_ + dy * c_
                    if (u / a1) ** 2 + (v / a2) ** 2 > 1.0:
                        continue
                    u = abs(u)
                    v = abs(v)
                    p1 = _ndtr((u + half) / s1) - _ndtr((u - half) / s1)
                    p2 = _ndtr((v + half) / s2) - _ndtr((v - half) / s2)
                    sd = math.sqrt(V[ii, jj])
                    hs[k] = hk
                    lo[k] = hk - 2.0 * sd
                    hi[k] = hk + 2.0 * sd
                    ws[k] = max(MIN_WEIGHT, p1 * p2)
                    k += 1
            if k == 1:                                  # only the cell itself
                out[0, i, j] = h0
                out[1, i, j] = lo[0]
                out[2, i, j] = hi[0]
            else:
                sw = 0.0
                swh = 0.0
                for t in range(k):
                    sw += ws[t]
                    swh += ws[t] * hs[t]
                out[0, i, j] = swh / sw
                out[1, i, j] = _wquantile(lo[:k], ws[:k], LOWER_QUANTILE)
                out[2, i, j] = _wquantile(hi[:k], ws[:k], UPPER_QUANTILE)
            out[3, i, j] = out[2, i, j] - out[1, i, j]


def _map_layers(emap):
    """Elevation (NaN where the cell is not known, see ``ElevationMap.is_known``), variance and the
    horizontal variances, map-index order."""
    g = emap.geometry
    d = g.unwrap(emap.data[[ELEVATION, VARIANCE, HVAR_X, HVAR_Y, HVAR_XY]])
    d[0] = np.where(emap.is_known(), d[0], np.nan)
    return [np.ascontiguousarray(a) for a in d]


def fused_map(emap) -> dict:
    """EM's ellipse-weighted fusion of the map, on demand (see the module docstring).

    Returns
    -------
    dict
        ``"elevation"``, ``"lower_bound"``, ``"upper_bound"``, ``"uncertainty_range"``: (n, n) arrays
        in map-index order [m], NaN where the cell is unknown. The map is not modified.
    """
    E, V, HX, HY, HXY = _map_layers(emap)
    res = emap.geometry.resolution_m
    min_h = float(emap.fusion_params.array(res)[3])
    out = np.empty((4,) + E.shape)
    n = resolve_threads(emap.nthreads)
    with threads(n):
        _fuse_map_kernel(E, V, HX, HY, HXY, res, min_h, out)
    return dict(zip(FUSED_LAYERS, out))


# ---------------------------------------------------------------------------------------------
# fusion: NumPy reference
# ---------------------------------------------------------------------------------------------
def _wquantile_reference(vals, wts, p):
    u, inv = np.unique(vals, return_inverse=True)
    s = np.bincount(inv.ravel(), weights=wts, minlength=len(u))
    if len(u) == 1 or p <= 0.0:
        return float(u[0])
    if p >= 1.0:
        return float(u[-1])
    P = (np.cumsum(s) - s[0]) / (s.sum() - s[0])
    hit = np.flatnonzero(P[1:] >= p)
    if not len(hit):
        return float(u[-1])
    t = hit[0] + 1
    return float(u[t - 1] + (p - P[t - 1]) * (u[t] - u[t - 1]) / (P[t] - P[t - 1]))


def fused_map_reference(emap) -> dict:
    """NumPy reference of :func:`fused_map`: a loop over known cells, vectorised over each ellipse."""
    E, V, HX, HY, HXY = _map_layers(emap)
    res = emap.geometry.resolution_m
    min_h = float(emap.fusion_params.array(res)[3])
    n = E.shape[0]
    out = np.full((4, n, n), np.nan)
    half = 0.5 * res
    known = np.isfinite(E)
    for i, j in zip(*np.nonzero(known)):
        hx, hy, hxy = HX[i, j], HY[i, j], HXY[i, j]
        hx = hx if np.isfinite(hx) else min_h
        hy = hy if np.isfinite(hy) else min_h
        hxy = hxy if np.isfinite(hxy) else 0.0
        m, dd = 0.5 * (hx + hy), 0.5 * (hx - hy)
        r = math.sqrt(dd * dd + hxy * hxy)
        l1, l2 = abs(m + r), abs(m - r)
        phi = 0.5 * math.atan2(2.0 * hxy, hx - hy)
        if l2 > l1:                          # |negative| eigenvalue dominates (not PSD)
            l1, l2 = l2, l1
            phi += 0.5 * math.pi
        c, s = math.cos(phi), math.sin(phi)
        s1 = max(math.sqrt(l1), _SIGMA_FLOOR_REL * res)
        s2 = max(math.sqrt(l2), _SIGMA_FLOOR_REL * res)
        a1 = UNCERTAINTY_FACTOR * math.sqrt(l1) + math.sqrt(2.0) * res / 2.0
        a2 = UNCERTAINTY_FACTOR * math.sqrt(l2) + math.sqrt(2.0) * res / 2.0
        ki = int(math.hypot(a1 * c, a2 * s) / res) + 1
        kj = int(math.hypot(a1 * s, a2 * c) / res) + 1
        ii, jj = np.meshgrid(np.arange(max(i - ki, 0), min(i + ki, n - 1) + 1),
                             np.arange(max(j - kj, 0), min(j + kj, n - 1) + 1), indexing="ij")
        ii, jj = ii.ravel(), jj.ravel()
        dx, dy = (ii - i) * res, (jj - j) * res
        u = dx * c + dy * s
        v = -dx * s + dy * c
        sel = known[ii, jj] & ((u / a1) ** 2 + (v / a2) ** 2 <= 1.0)
        ii, jj, u, v = ii[sel], jj[sel], np.abs(u[sel]), np.abs(v[sel])
        w = np.maximum(MIN_WEIGHT, (ndtr((u + half) / s1) - ndtr((u - half) / s1))
                       * (ndtr((v + half) / s2) - ndtr((v - half) / s2)))
        h = E[ii, jj]
        sd = np.sqrt(V[ii, jj])
        lo, hi = h - 2.0 * sd, h + 2.0 * sd
        if len(h) == 1:
            out[:3, i, j] = (E[i, j], lo[0], hi[0])
        else:
            out[0, i, j] = np.sum(w * h) / np.sum(w)
            out[1, i, j] = _wquantile_reference(lo, w, LOWER_QUANTILE)
            out[2, i, j] = _wquantile_reference(hi, w, UPPER_QUANTILE)
        out[3, i, j] = out[2, i, j] - out[1, i, j]
    return dict(zip(FUSED_LAYERS, out))
