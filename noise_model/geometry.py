"""Pixel geometry of a depth image: metres, deprojection, incidence angles and depth edges.

Camera frame (RealSense / OpenCV): x right, y down, z forward; depth is z, not ray length. Pixel
(v, u) = (row, column); integer coordinates are pixel centres.

These are the plain NumPy implementations; ``noise_model.kernels`` computes the same quantities in a
single numba pass and is tested against them.
"""

from __future__ import annotations

import math

import numpy as np

from .checks import check_depth, check_intrinsics, check_positive_scalar
from .d435 import D435, SensorModel, axial_sigma_unchecked
from .formulas import reduced_chi2_quantile

__all__ = [
    "depth_to_metres",
    "deproject",
    "incidence_angles",
    "incidence_angle_stats",
    "depth_edges",
    "despeckle",
    "mixed_windows",
    "row_medians",
    "surface_depths",
    "default_block_px",
    "plane_depths",
    "EDGE_JUMP_REL",
    "EDGE_JUMP_SIGMAS",
    "NORMAL_MIN_POINTS",
]

#: Depth-edge threshold, relative part: a jump of more than 5 % of the nearer depth.
EDGE_JUMP_REL = 0.05
#: Depth-edge threshold, noise part: more than 4 standard deviations of the difference of two
#: independent fronto-parallel pixels, 4 sqrt(2) sigma_z(z, 0) (so noise alone rarely makes an edge).
EDGE_JUMP_SIGMAS = 4.0
#: Fewer valid points than this in a normal-estimation window: the surface orientation is unknown
#: and theta falls back to 0 (fronto-parallel).
NORMAL_MIN_POINTS = 6


def default_block_px(width: int) -> int:
    """Block size [px] of the normal estimation: W / 106 rounded, at least 2 (8 px at 848 wide).

    The estimation window is 5 x 5 blocks, so it spans the same ~4.2 deg of the field of view at
    every resolution (40 px at 848x480, 20 px at 424x240, 60 px at 1280x720).
    """
    return max(2, int(round(width / 106.0)))


def depth_to_metres(depth, depth_scale=None, min_depth_m: float | None = None,
                    max_depth_m: float | None = None) -> np.ndarray:
    """Convert a depth image to float64 metres with NaN for every invalid pixel.

    Invalid: 0 depth units, NaN, +-inf, negative, and (when given) outside [min_depth_m, max_depth_m].

    Parameters
    ----------
    depth : array_like, shape (H, W)
        uint16 depth units with ``depth_scale`` [m/unit], or float metres.
    depth_scale : float, optional
        Metres per unit for uint16 depth.
    min_depth_m, max_depth_m : float, optional
        Valid range [m].

    Returns
    -------
    ndarray, shape (H, W), float64 [m]
    """
    d, scale = check_depth(depth, depth_scale)
    z = d.astype(np.float64) * scale
    bad = ~np.isfinite(z) | (z <= 0.0)
    if min_depth_m is not None:
        bad |= z < check_positive_scalar(min_depth_m, "min_depth_m", upper=100.0, unit=" m")
    if max_depth_m is not None:
        bad |= z > check_positive_scalar(max_depth_m, "max_depth_m", upper=100.0, unit=" m")
    z[bad] = np.nan
    return z


def deproject(depth_m, K) -> np.ndarray:
    """Deproject a depth image into camera-frame points.

    Parameters
    ----------
    depth_m : array_like, shape (H, W)
        Depth z [m] (float); non-finite, zero or negative values are invalid.
    K : array_like, shape (3, 3)
        Pinhole intrinsics [px].

    Returns
    -------
    points_cam : ndarray, shape (H, W, 3), float64 [m]
        (x, y, z) in the camera frame (x right, y down, z forward); NaN where the depth is invalid.
        x = (u - cx) z / fx, y = (v - cy) z / fy.
    """
    z = depth_to_metres(depth_m)
    K = check_intrinsics(K)
    H, W = z.shape
    u = (np.arange(W, dtype=np.float64) - K[0, 2]) / K[0, 0]
    v = (np.arange(H, dtype=np.float64) - K[1, 2]) / K[1, 1]
    pts = np.empty((H, W, 3))
    pts[..., 0] = u[None, :] * z
    pts[..., 1] = v[:, None] * z
    pts[..., 2] = z
    return pts


def _valid_points(points_cam):
    p = np.asarray(points_cam)
    if p.ndim != 3 or p.shape[2] != 3:
        raise ValueError(f"points_cam must have shape (H, W, 3), got {p.shape}")
    if not np.issubdtype(p.dtype, np.floating):
        raise ValueError(f"points_cam must be floating point metres, got dtype {p.dtype}")
    p = p.astype(np.float64, copy=False)
    valid = np.isfinite(p).all(axis=2) & (p[..., 2] > 0.0)
    return p, valid


def incidence_angles(points_cam, block_px: int | None = None, min_points: int = NORMAL_MIN_POINTS) -> np.ndarray:
    """Incidence angle theta [rad] per pixel: angle between the local surface normal and the optical axis.

    A plane n . p = d seen through a pinhole is exactly linear in inverse depth:
    1 / z = (n_x u' + n_y v' + n_z) / d, with u' = x / z and v' = y / z the normalised pixel
    coordinates. So each window fits w = 1 / z = alpha u' + beta v' + gamma by ordinary least squares
    and takes n proportional to (alpha, beta, gamma). Stereo noise moves a point along its viewing
    ray, which changes z but leaves (u', v') exact: the regressors are noise-free and the fit is free
    of the bias that a 3-D principal-component fit suffers (there the noise along the rays tilts the
    normal away from them, and theta grows with the noise).

    The image is cut into ``block_px`` x ``block_px`` blocks; each block's fit uses the valid pixels
    of the 5 x 5 blocks around it, and every pixel of the block gets that block's theta =
    atan2(|(alpha, beta)|, |gamma|), in [0, pi/2]. It is 0 for a fronto-parallel plane wherever it lies
    in the image (the paper's theta_y, generalised to any tilt).

    Parameters
    ----------
    points_cam : array_like, shape (H, W, 3)
        Camera-frame points [m] from :func:`deproject` (NaN = invalid).
    block_px : int, optional
        Block size [px]; :func:`default_block_px` of the width by default.
    min_points : int
        A window with fewer valid points gives theta = 0 (orientation unknown, taken fronto-parallel);
        so does a degenerate window (all pixels on one image line).

    Returns
    -------
    theta : ndarray, shape (H, W), float64 [rad]
        NaN where the pixel itself is invalid.
    """
    p, valid = _valid_points(points_cam)
    H, W = valid.shape
    b = default_block_px(W) if block_px is None else int(block_px)
    if b < 1:
        raise ValueError(f"block_px must be >= 1, got {block_px}")
    theta_block = _block_theta_numpy(p, valid, b, int(min_points))
    theta = np.repeat(np.repeat(theta_block, b, axis=0), b, axis=1)[:H, :W].copy()
    theta[~valid] = np.nan
    return theta


#: A window's residual mean square of inverse depth below this fraction of its squared mean is the
#: rounding of the raw moments (sum w^2 / n - mean(w)^2), not noise: the angle's standard deviation is
#: then 0. Real D435 noise is >= ~1e-5 of it (1 mm at 0.3 m).
RSS_FLOOR_REL = 1e-12

#: Half-width of the normal-estimation window, in blocks (the window is 5 x 5 blocks).
WINDOW_RADIUS_BLOCKS = 2

#: Normal quantile of the significance level (1e-3) at which a window's blocks depart from its plane
#: (:func:`mixed_windows`).
MIXED_WINDOW_Z = 3.090
#: Half-width [px] of the row neighbourhood of :func:`row_medians`: 11 pixels, whose median has
#: about a third of one pixel's noise standard deviation (sqrt(pi / (2 * 11)) for Gaussian noise).
ROW_MEDIAN_HALF_PX = 5
#: Half-height [rows] of :func:`surface_depths`: the median of 5 rows' medians.
SURFACE_HALF_ROWS = 2


def _block_theta_numpy(p, valid, b, min_points):
    """Per-block theta [rad] from inverse-depth plane fits over 5 x 5-block windows (NumPy reference)."""
    return _block_planes_numpy(p, valid, b, min_points)[0]


def incidence_angle_stats(points_cam, block_px: int | None = None, min_points: int = NORMAL_MIN_POINTS):
    """Incidence angle theta [rad] per pixel, as :func:`incidence_angles`, and the standard deviation of
    that estimate [rad].

    The plane fit w = alpha u' + beta v' + gamma over a window is ordinary least squares with noise-free
    regressors, so its parameters have covariance s^2 (X^T X)^-1 with s^2 = RSS / (n - 3) the residual
    variance of the window's inverse depths; theta = atan2(|(alpha, beta)|, |gamma|) carries it to first
    order (delta method). On a noisy or grazing surface (a floor seen 2 m ahead) the window's theta is
    uncertain by several degrees, and where the window straddles two surfaces the residuals, and so
    the standard deviation, grow: both are what :func:`noise_model.axial_variance` integrates over.

    Returns
    -------
    theta, theta_std : ndarray, shape (H, W), float64 [rad]
        NaN where the pixel is invalid; theta_std is 0 where theta falls back to 0 (too few points,
        degenerate window) or the window holds no more than 3 points, and at most pi/2 (a window of
        noise alone: the angle is unknown).
    """
    p, valid = _valid_points(points_cam)
    H, W = valid.shape
    b = default_block_px(W) if block_px is None else int(block_px)
    if b < 1:
        raise ValueError(f"block_px must be >= 1, got {block_px}")
    S = _block_moments_numpy(p, valid, b)
    theta, alpha, beta, gamma, ok = _planes_from_inverse_depth_moments(S, int(min_points))
    std = _theta_std_from_moments_numpy(S, alpha, beta, gamma, ok)
    out = []
    for a in (theta, std):
        a = np.repeat(np.repeat(a, b, axis=0), b, axis=1)[:H, :W].copy()
        a[~valid] = np.nan
        out.append(a)
    return out[0], out[1]


def centred_moments(S, n):
    """(mu, mv, mw, cuu, cuv, cvv, cuw, cvw, cww): means and (co)variances of u', v', w from the summed
    moments S = (n, su, sv, sw, suu, suv, svv, suw, svw, sww) along S's first axis, divided by n (a
    number or an array of S's other shape). Plain arithmetic: the numba kernels compile this same
    function (``noise_model.kernels``)."""
    mu, mv, mw = S[1] / n, S[2] / n, S[3] / n
    return (mu, mv, mw, S[4] / n - mu * mu, S[5] / n - mu * mv, S[6] / n - mv * mv, S[7] / n - mu * mw,
            S[8] / n - mv * mw, S[9] / n - mw * mw)


def plane_rss(S, n, alpha, beta):
    """Residual sum of squares of the least-squares plane w = alpha u' + beta v' + gamma over the
    summed moments S (along its first axis) of n points. ``noise_model.kernels`` repeats these two lines
    on the compiled :func:`centred_moments`."""
    _, _, _, _, _, _, cuw, cvw, cww = centred_moments(S, n)
    return n * (cww - alpha * cuw - beta * cvw)


def _theta_std_from_moments_numpy(S, alpha, beta, gamma, ok):
    """Standard deviation [rad] of theta = atan2(|(alpha, beta)|, |gamma|) of the plane fit of the summed
    moments S (..., 10) = (n, su, sv, sw, suu, suv, svv, suw, svw, sww); 0 where not ok or n <= 3."""
    n = S[..., 0]
    ok = ok & (n > 3)
    nn = np.where(ok, n, 4.0)
    mu, mv, mw, cuu, cuv, cvv, cuw, cvw, cww = centred_moments(np.moveaxis(S, -1, 0), nn)
    det = np.where(ok, cuu * cvv - cuv * cuv, 1.0)
    rss = cww - alpha * cuw - beta * cvw                           # RSS / n
    rss = np.where(rss > RSS_FLOOR_REL * mw * mw, rss, 0.0)        # below the moments' rounding: 0
    f = rss / (nn - 3.0) / det                                     # s^2 / (n det)
    vaa, vbb, vab = f * cvv, f * cuu, -f * cuv
    vgg = rss / (nn - 3.0) + mu * mu * vaa + 2.0 * mu * mv * vab + mv * mv * vbb
    vag = -(mu * vaa + mv * vab)
    vbg = -(mu * vab + mv * vbb)
    rho = np.hypot(alpha, beta)
    q = rho * rho + gamma * gamma
    qq = np.where(q > 0, q, 1.0)
    ag = np.abs(gamma)
    rr = np.where(rho > 0, rho, 1.0)
    ja = np.where(rho > 0, ag * alpha / (rr * qq), 0.0)
    jb = np.where(rho > 0, ag * beta / (rr * qq), 0.0)
    jg = -rho * np.sign(gamma) / qq
    var = (ja * ja * vaa + jb * jb * vbb + jg * jg * vgg + 2.0 * ja * jb * vab + 2.0 * ja * jg * vag
           + 2.0 * jb * jg * vbg)
    return np.where(ok & (q > 0), np.minimum(np.sqrt(np.maximum(var, 0.0)), 0.5 * np.pi), 0.0)   # <= 90 deg


def _block_planes_numpy(p, valid, b, min_points):
    """Per-block (theta, alpha, beta, gamma, ok) of the inverse-depth plane fit 1/z = alpha u' + beta v' + gamma
    over the 5 x 5 blocks around each block (NumPy reference of the numba kernel)."""
    return _planes_from_inverse_depth_moments(_block_moments_numpy(p, valid, b), min_points)


def _block_moments_numpy(p, valid, b):
    """Per block, the moments (n, su, sv, sw, suu, suv, svv, suw, svw, sww) of u', v' and w = 1 / z summed
    over the 5 x 5 blocks around it, shape (nby, nbx, 10)."""
    return _window_sums(_block_sums_numpy(p, valid, b))


def _block_sums_numpy(p, valid, b):
    """Per block, the moments (n, su, sv, sw, suu, suv, svv, suw, svw, sww) over its own pixels, shape
    (nby, nbx, 10)."""
    H, W = valid.shape
    nby, nbx = -(-H // b), -(-W // b)
    vv, uu = np.nonzero(valid)
    cell = (vv // b) * nbx + (uu // b)
    z = p[vv, uu, 2]
    up, vp, w = p[vv, uu, 0] / z, p[vv, uu, 1] / z, 1.0 / z
    weights = (None, up, vp, w, up * up, up * vp, vp * vp, up * w, vp * w, w * w)
    M = np.stack([np.bincount(cell, weights=x, minlength=nby * nbx) for x in weights], axis=1)
    return M.reshape(nby, nbx, 10)


def _window_sums(M):
    """The per-block moments M (nby, nbx, 10) summed over the 5 x 5 blocks around each block."""
    nby, nbx = M.shape[:2]
    r = WINDOW_RADIUS_BLOCKS
    padded = np.zeros((nby + 2 * r, nbx + 2 * r, 10))
    padded[r:-r, r:-r] = M
    return sum(padded[i:i + nby, j:j + nbx] for i in range(2 * r + 1) for j in range(2 * r + 1))


def _theta_from_inverse_depth_moments(S, min_points):
    """theta [rad] from summed moments (n, su, sv, sw, suu, suv, svv, suw, svw), any leading shape."""
    return _planes_from_inverse_depth_moments(S, min_points)[0]


def _planes_from_inverse_depth_moments(S, min_points):
    """(theta, alpha, beta, gamma, ok) of the least-squares plane w = alpha u' + beta v' + gamma."""
    n = S[..., 0]
    ok = n >= max(min_points, 3)
    nn = np.where(ok, n, 1.0)
    mu, mv, mw, cuu, cuv, cvv, cuw, cvw, _ = centred_moments(np.moveaxis(S, -1, 0), nn)
    det = cuu * cvv - cuv * cuv
    ok &= det > DEGENERATE_REL * (cuu + cvv) ** 2
    det = np.where(ok, det, 1.0)
    alpha = (cvv * cuw - cuv * cvw) / det
    beta = (cuu * cvw - cuv * cuw) / det
    gamma = mw - alpha * mu - beta * mv
    theta = np.where(ok, np.arctan2(np.hypot(alpha, beta), np.abs(gamma)), 0.0)
    return theta, alpha, beta, gamma, ok


def plane_depths(points_cam, block_px: int | None = None, min_points: int = NORMAL_MIN_POINTS) -> np.ndarray:
    """Denoised depth [m] per pixel: the local plane of :func:`incidence_angles` evaluated at the pixel.

    z_fit = 1 / (alpha u' + beta v' + gamma) with the block's inverse-depth plane fit. Noise model
    variances are evaluated at this depth rather than at the pixel's own noisy depth: a weight
    computed from the noisy depth is correlated with the noise (a pixel measured too near gets a
    smaller sigma, a larger weight, and, on a surface seen from above, a height too high), which biases
    an inverse-variance weighted mean.

    Returns
    -------
    ndarray, shape (H, W) [m]
        NaN where the pixel is invalid or its block has no plane (too few points, degenerate) or the
        plane does not put the pixel in front of the camera.
    """
    p, valid = _valid_points(points_cam)
    H, W = valid.shape
    b = default_block_px(W) if block_px is None else int(block_px)
    if b < 1:
        raise ValueError(f"block_px must be >= 1, got {block_px}")
    _, alpha, beta, gamma, ok = _block_planes_numpy(p, valid, b, int(min_points))
    def spread(a):
        return np.repeat(np.repeat(a, b, axis=0), b, axis=1)[:H, :W]
    with np.errstate(invalid="ignore", divide="ignore"):
        up = p[..., 0] / p[..., 2]
        vp = p[..., 1] / p[..., 2]
        w = spread(alpha) * up + spread(beta) * vp + spread(gamma)
        z_fit = np.where(valid & spread(ok) & (w > 0), 1.0 / w, np.nan)
    return z_fit


#: A window whose pixel-coordinate covariance has a determinant below this fraction of its squared
#: trace holds pixels on one line (or one pixel): the plane, and so its normal, is undefined.
DEGENERATE_REL = 1e-9


def _jump_inputs(depth_m, jump_rel, jump_sigmas, theta):
    """(z [m] with NaN where invalid, valid, theta with 0 where unknown, jump_rel, jump_sigmas), checked."""
    z = depth_to_metres(depth_m)
    jr = float(jump_rel)
    js = float(jump_sigmas)
    if not (np.isfinite(jr) and jr >= 0 and np.isfinite(js) and js >= 0):
        raise ValueError(f"jump_rel and jump_sigmas must be finite and >= 0, got {jump_rel}, {jump_sigmas}")
    valid = np.isfinite(z)
    th = np.zeros(z.shape) if theta is None else np.asarray(theta, dtype=np.float64)
    if th.shape != z.shape:
        raise ValueError(f"theta must have the depth image's shape {z.shape}, got {th.shape}")
    return z, valid, np.where(valid & np.isfinite(th), th, 0.0), jr, js


def _jump_threshold(z, theta, jump_rel, jump_sigmas, model):
    """The depth-edge threshold max(jump_rel z, jump_sigmas sqrt(2) sigma_z(z, theta)) [m]."""
    return np.maximum(jump_rel * z, jump_sigmas * np.sqrt(2.0) * axial_sigma_unchecked(z, theta, model))


def depth_edges(depth_m, jump_rel: float = EDGE_JUMP_REL, jump_sigmas: float = EDGE_JUMP_SIGMAS,
                model: SensorModel = D435, theta=None):
    """Pixels on the left and right edges of depth discontinuities (the paper's lateral-noise edges).

    A valid pixel is on a *left edge* when the pixel to its left is invalid, or farther by more than
    the threshold: it is the left boundary of a nearer surface. Right edges mirror this with the
    pixel to its right. The threshold on the jump is max(jump_rel z, jump_sigmas sqrt(2)
    sigma_z(z, theta)) with z and theta those of the nearer pixel: by default 5 % of the depth, or 4
    standard deviations of the difference of two pixels where the paper's noise is larger (beyond
    ~2.4 m head-on, and sooner on oblique surfaces, whose noise would otherwise be taken for edges).
    The image border itself is not an edge.

    Parameters
    ----------
    depth_m : array_like, shape (H, W)
        Depth [m]; non-finite, zero or negative = invalid.
    jump_rel : float
        Relative part of the threshold [-].
    jump_sigmas : float
        Noise part of the threshold [standard deviations].
    model : SensorModel
        For sigma_z.
    theta : array_like, shape (H, W), optional
        Incidence angles [rad] (:func:`incidence_angles`); 0 (fronto-parallel) where not given.

    Returns
    -------
    edge_left, edge_right : ndarray of bool, shape (H, W)
    """
    z, valid, th, jr, js = _jump_inputs(depth_m, jump_rel, jump_sigmas, theta)
    thr = _jump_threshold(np.where(valid, z, 1.0), th, jr, js, model)
    left = np.zeros(z.shape, dtype=bool)
    right = np.zeros(z.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        left[:, 1:] = valid[:, 1:] & (~valid[:, :-1] | (z[:, :-1] - z[:, 1:] > thr[:, 1:]))
        right[:, :-1] = valid[:, :-1] & (~valid[:, 1:] | (z[:, 1:] - z[:, :-1] > thr[:, :-1]))
    return left, right


def row_medians(depth_m, half_px: int = ROW_MEDIAN_HALF_PX, jump_rel: float = EDGE_JUMP_REL,
                jump_sigmas: float = EDGE_JUMP_SIGMAS, model: SensorModel = D435, theta=None) -> np.ndarray:
    """Per pixel, the median depth of the pixels of its row within ``half_px`` that agree with it.

    A neighbour agrees when the depth difference is within the depth-edge threshold of
    :func:`depth_edges`, max(jump_rel z, jump_sigmas sqrt(2) sigma_z(z, theta)), z the nearer of the
    two depths and theta the pixel's own (as :func:`despeckle`); the pixel itself always agrees.

    Why: in a window that holds two surfaces (:func:`mixed_windows`) the window's plane describes
    neither, so it cannot denoise a pixel's depth; a near surface seen at a grazing angle (a box top,
    a stair's tread) is a strip a few rows tall and many columns wide, and the pixels of the pixel's
    own row on its own surface average its noise down (the median of 11 independent Gaussian pixels:
    0.38 of one pixel's standard deviation). :func:`surface_depths` takes the median of these down
    the column, and :func:`noise_model.depth_to_map_points` bins the pixels of mixed windows at the
    nearer of that depth and the plane's, and takes a pixel's squared distance from it as a floor of
    its axial variance (see :class:`noise_model.MapPoints`).

    Parameters
    ----------
    depth_m : array_like, shape (H, W)
        Depth [m]; non-finite, zero or negative = invalid.
    half_px : int
        Row neighbours on each side [px], >= 0.
    jump_rel, jump_sigmas, model, theta
        The agreement of two pixels, as in :func:`despeckle`.

    Returns
    -------
    ndarray, shape (H, W), float64 [m]
        NaN where the pixel is invalid.
    """
    z, valid, th, jr, js = _jump_inputs(depth_m, jump_rel, jump_sigmas, theta)
    return _row_medians(z, valid, th, jr, js, model, half_px)


def _row_medians(z, sel, th, jr, js, model, half_px):
    """:func:`row_medians` of checked inputs, computed at the pixels ``sel`` only (NaN elsewhere)."""
    h = int(half_px)
    if h != half_px or h < 0:
        raise ValueError(f"half_px must be an integer >= 0, got {half_px!r}")
    H, W = z.shape
    zp = np.pad(z, ((0, 0), (h, h)), constant_values=np.nan)
    nbrs = np.stack([zp[:, k:k + W] for k in range(2 * h + 1)])                 # (2h + 1, H, W)
    with np.errstate(invalid="ignore"):
        zq = np.where(nbrs < z, nbrs, z)                                        # the nearer depth
        zq = np.where(np.isfinite(zq), zq, 1.0)
        thr = _jump_threshold(zq, np.broadcast_to(th, zq.shape), jr, js, model)
        agree = np.abs(nbrs - z) <= thr                                         # False where either is NaN
    out = np.full(z.shape, np.nan)
    if sel.any():
        out[sel] = np.nanmedian(np.where(agree[:, sel], nbrs[:, sel], np.nan), axis=0)
    return out


def surface_depths(depth_m, mask, half_px: int = ROW_MEDIAN_HALF_PX, half_rows: int = SURFACE_HALF_ROWS,
                   jump_rel: float = EDGE_JUMP_REL, jump_sigmas: float = EDGE_JUMP_SIGMAS, model: SensorModel = D435,
                   theta=None) -> np.ndarray:
    """Per pixel of ``mask``, a denoised depth of its own surface: the median of the row medians
    (:func:`row_medians`) of the ``mask`` pixels in its column within ``half_rows`` rows that agree
    with its depth (the depth-edge threshold at the nearer depth with the pixel's theta).

    A box top or a stair's tread seen at a grazing angle is a strip a few rows tall: the row medians
    of its rows average along the strip, and their median over 5 rows averages across it (about
    1/5 of one pixel's noise standard deviation where 55 pixels agree), while the agreement keeps the
    other surface of the window out. Used for binning in windows of two surfaces
    (:func:`mixed_windows`, :class:`noise_model.MapPoints`), and the pixel's squared distance from it
    is a floor of its axial variance there (the window's angle and plane are fitted across both
    surfaces, so the model's sigma alone understates the noise).

    Parameters
    ----------
    depth_m : array_like, shape (H, W)
        Depth [m]; non-finite, zero or negative = invalid.
    mask : array_like of bool, shape (H, W)
        The pixels to compute (and whose row medians take part), e.g. :func:`mixed_windows`.
    half_rows : int
        Rows above and below [rows], >= 0.
    half_px, jump_rel, jump_sigmas, model, theta
        As in :func:`row_medians`.

    Returns
    -------
    ndarray, shape (H, W), float64 [m]
        NaN where the pixel is invalid or outside ``mask``.
    """
    z, valid, th, jr, js = _jump_inputs(depth_m, jump_rel, jump_sigmas, theta)
    m = np.asarray(mask)
    if m.shape != z.shape or m.dtype != bool:
        raise ValueError(f"mask must be a boolean array of the depth image's shape {z.shape}, got "
                         f"{m.dtype} {m.shape}")
    h = int(half_rows)
    if h != half_rows or h < 0:
        raise ValueError(f"half_rows must be an integer >= 0, got {half_rows!r}")
    r = _row_medians(z, m & valid, th, jr, js, model, half_px)       # only where the column median reads
    H, W = z.shape
    rp = np.pad(r, ((h, h), (0, 0)), constant_values=np.nan)
    nbrs = np.stack([rp[k:k + H] for k in range(2 * h + 1)])                    # (2h + 1, H, W)
    with np.errstate(invalid="ignore"):
        zq = np.where(nbrs < z, nbrs, z)
        zq = np.where(np.isfinite(zq), zq, 1.0)
        thr = _jump_threshold(zq, np.broadcast_to(th, zq.shape), jr, js, model)
        agree = np.abs(nbrs - z) <= thr
    out = np.full(z.shape, np.nan)
    sel = m & valid
    if sel.any():
        out[sel] = np.nanmedian(np.where(agree, nbrs, np.nan)[:, sel], axis=0)
    return out


def despeckle(depth_m, jump_rel: float = EDGE_JUMP_REL, jump_sigmas: float = EDGE_JUMP_SIGMAS,
               model: SensorModel = D435, theta=None):
    """Speckles replaced by their neighbours' median depth, and how far each was from it.

    A valid pixel is a *speckle* when none of its 8 neighbours agrees with it: for each valid
    neighbour the depth difference exceeds the depth-edge threshold of :func:`depth_edges`,
    max(jump_rel z, jump_sigmas sqrt(2) sigma_z(z, theta)), with z the nearer of the two depths and
    theta the pixel's own. A pixel without valid neighbours is no speckle (nothing to compare with).

    Why: on a surface seen near grazing incidence the paper's sigma_z is metres (theta / (pi/2 -
    theta)^2), so the reference simulation, and a real D435 on a bad surface, returns the odd pixel
    anywhere between the camera and the far range. Such a pixel 2 m in front of its neighbours also
    pulls the window's inverse-depth plane (and so sigma_z at that plane) towards the camera, and gets
    a sigma of millimetres: each such point outweighs the hundreds of points of the cell it lands in,
    and a cell that only such pixels reach reads the camera's height. Nothing but its neighbours says
    where a speckle's surface is: :func:`noise_model.depth_to_map_points` places it at their median
    depth along its ray, with the squared distance as the floor of its axial variance (the usual
    speckle filter of stereo pipelines would drop it; it is kept, so the counts of points stay those of
    the image).

    Parameters
    ----------
    depth_m : array_like, shape (H, W)
        Depth [m]; non-finite, zero or negative = invalid.
    jump_rel, jump_sigmas : float
        Threshold of agreement, as in :func:`depth_edges`.
    model : SensorModel
        For sigma_z.
    theta : array_like, shape (H, W), optional
        Incidence angles [rad]; 0 where not given.

    Returns
    -------
    depth : ndarray, shape (H, W), float64 [m]
        The input (NaN where invalid) with each speckle's depth replaced by the median of its valid
        neighbours' depths.
    deviation2 : ndarray, shape (H, W), float64 [m^2]
        (measured - median)^2 at the speckles, 0 elsewhere.
    """
    z, valid, th, jr, js = _jump_inputs(depth_m, jump_rel, jump_sigmas, theta)
    H, W = z.shape
    zp = np.pad(z, 1, constant_values=np.nan)
    offsets = [(dv, du) for dv in (-1, 0, 1) for du in (-1, 0, 1) if (dv, du) != (0, 0)]
    nbrs = np.stack([zp[1 + dv:1 + dv + H, 1 + du:1 + du + W] for dv, du in offsets])   # (8, H, W)
    with np.errstate(invalid="ignore"):
        zq = np.where(nbrs < z, nbrs, z)                                  # the nearer depth
        zq = np.where(np.isfinite(zq), zq, 1.0)
        thr = _jump_threshold(zq, np.broadcast_to(th, zq.shape), jr, js, model)
        agree = np.abs(nbrs - z) <= thr                                   # False where either is NaN
    speckle = valid & np.isfinite(nbrs).any(axis=0) & ~agree.any(axis=0)
    out = z.copy()
    dev2 = np.zeros(z.shape)
    if speckle.any():
        med = np.nanmedian(nbrs[:, speckle], axis=0)
        dev2[speckle] = (z[speckle] - med) ** 2
        out[speckle] = med
    return out, dev2


def mixed_windows(points_cam, block_px: int | None = None, min_points: int = NORMAL_MIN_POINTS,
                  z: float = MIXED_WINDOW_Z) -> np.ndarray:
    """Whether each pixel's normal-estimation window holds more than one surface.

    The window's plane (the inverse-depth fit of :func:`incidence_angles`) leaves each of its 5 x 5
    blocks a mean residual r_j over the block's n_j pixels and a scatter about that mean. On one surface
    with independent noise the block means scatter as their pixels do: F = [sum n_j r_j^2 / (B - 3)] /
    [(RSS - sum n_j r_j^2) / sum (n_j - 1)] follows an F distribution with B - 3 and sum (n_j - 1)
    degrees of freedom (B blocks with a valid pixel, RSS the window's residual sum of squares). Where
    blocks lie on another surface (a box top's strip in a window of floor, a riser and its tread, a
    step) their means depart together and F is large. Mixed: F above its 1 - 1e-3 quantile (``z``,
    Wilson-Hilferty for the numerator's chi-square; the denominator's degrees of freedom are in the
    hundreds). Also mixed: windows without
    a plane or with at most 3 blocks (nothing to test). Noise-free windows are mixed when their blocks
    depart from the plane beyond the rounding of the moments.

    Used for binning (:class:`noise_model.MapPoints`): a pixel nearer than its plane is binned at its
    own depth only in a mixed window, where the plane may describe the other surface; on one surface
    that choice would take the pixels with negative noise nearer and leave the others, and so bias a
    flat floor's heights (docs/calibration.md).

    Parameters
    ----------
    points_cam : array_like, shape (H, W, 3)
        Camera-frame points [m] (:func:`deproject`), NaN where invalid.
    block_px : int, optional
        Block size [px]; :func:`default_block_px` of the width by default.
    min_points : int
        Fewer valid points in a window: no plane (mixed).
    z : float
        Normal quantile of the test's significance level.

    Returns
    -------
    ndarray of bool, shape (H, W)
        False where the pixel is invalid.
    """
    p, valid = _valid_points(points_cam)
    H, W = valid.shape
    b = default_block_px(W) if block_px is None else int(block_px)
    if b < 1:
        raise ValueError(f"block_px must be >= 1, got {block_px}")
    zq = float(z)
    if not (math.isfinite(zq) and zq > 0):
        raise ValueError(f"z must be a positive normal quantile, got {z!r}")
    Mb = _block_sums_numpy(p, valid, b)                       # (nby, nbx, 10) per block
    S = _window_sums(Mb)
    _, alpha, beta, gamma, ok = _planes_from_inverse_depth_moments(S, int(min_points))
    nby, nbx = Mb.shape[:2]
    r = WINDOW_RADIUS_BLOCKS
    pad = np.zeros((nby + 2 * r, nbx + 2 * r, 10))
    pad[r:-r, r:-r] = Mb
    between = np.zeros((nby, nbx))
    dof = np.zeros((nby, nbx))
    nblocks = np.zeros((nby, nbx))
    a, bb, c = (np.where(ok, x, 0.0) for x in (alpha, beta, gamma))
    for i in range(2 * r + 1):
        for j in range(2 * r + 1):
            Mj = pad[i:i + nby, j:j + nbx]
            n = Mj[..., 0]
            use = n > 0.0
            rs = Mj[..., 3] - a * Mj[..., 1] - bb * Mj[..., 2] - c * n
            between += np.where(use, rs * rs / np.where(use, n, 1.0), 0.0)
            dof += np.where(use, n - 1.0, 0.0)
            nblocks += use
    ntot, swtot = S[..., 0], S[..., 3]
    within = np.maximum(plane_rss(np.moveaxis(S, -1, 0), np.where(ntot > 0, ntot, 1.0), a, bb) - between, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mw = swtot / np.where(ntot > 0, ntot, 1.0)
        exact = within <= RSS_FLOOR_REL * mw * mw * dof
        k = np.maximum(nblocks - 3.0, 1.0)
        # F = (between / k) / (within / dof) > chi2_{k,q} / k, k = B - 3 (dof in the hundreds: F ~ chi2_k / k)
        mixed = np.where(exact, between > RSS_FLOOR_REL * mw * mw * ntot,
                         between * dof > reduced_chi2_quantile(k, zq) * k * within)
    mixed = mixed | (nblocks <= 3.0) | (dof <= 0.0) | ~ok
    out = np.repeat(np.repeat(mixed, b, axis=0), b, axis=1)[:H, :W].copy()
    out[~valid] = False
    return out
