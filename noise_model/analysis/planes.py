"""Planes in the camera frame and the fits that find them: one :class:`Plane`, one :class:`PlaneFit`.

A plane is n . p = offset_m, with n a unit normal and p a camera-frame point [m]. Four fits, for four
kinds of data:

* :func:`fit_plane` -- total least squares (SVD of the centred points) of points that all lie on it.
* :func:`fit_plane_robust` -- total least squares with inliers within ``inlier_rel`` x (median depth)
  of the plane, refitted until they no longer change (deterministic: no random samples). The right
  fit for isotropic noise, such as one frame's points (the single-frame plane-fit residual).
* :func:`fit_plane_rays` -- least squares *along the pixels' rays* (the plane is linear in inverse
  depth), for depth whose noise is along the rays, such as the per-pixel median of a capture.
* :func:`fit_plane_ransac` -- RANSAC over a region of one depth image, refitted by SVD on its inliers,
  for a region that holds other things too (a real frame without a known target); its inliers are an
  image mask.

:func:`target_plane` and :func:`plane_pose` turn a capture-set target into its plane and back. The
dominant planes of a static stretch of frames, with their pixel masks, are found by
:func:`noise_model.analysis.plane_finder.find_planes` with these fits.

Camera frame: x right, y down, z forward (RealSense / OpenCV); depth is z, not ray length. Normalised
pixel coordinates are u' = (u - cx) / fx, v' = (v - cy) / fy, so a pixel's ray is z (u', v', 1).
NumPy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..checks import check_intrinsics, check_points, check_positive_scalar

__all__ = [
    "Plane",
    "PlaneFit",
    "fit_plane",
    "fit_plane_robust",
    "fit_plane_rays",
    "fit_plane_ransac",
    "normalised_coordinates",
    "points_from_depth",
    "target_plane",
    "plane_pose",
    "INLIER_REL",
]

#: Inlier threshold of the plane fits, relative to the depth (2 %): the threshold of the RANSAC-and-SVD
#: plane fit behind the plane-fit RMS error that the camera's reference figures quote, so residuals
#: measured here compare with them. At 1-3 m it is a few sigma_z.
INLIER_REL = 0.02


@dataclass(frozen=True)
class Plane:
    """The plane n . p = offset_m in the camera frame.

    Attributes
    ----------
    normal : ndarray, shape (3,)
        Unit normal. The fits orient it so that the plane lies in front of the camera: n_z >= 0
        (:func:`fit_plane`, :func:`fit_plane_robust`, :func:`fit_plane_rays`) or offset_m >= 0
        (:func:`fit_plane_ransac`, whose regions may be a floor the optical axis never meets); the two
        agree for every plane that crosses the optical axis in front of the camera.
    offset_m : float
        n . p for any point p of the plane [m]; > 0 for a plane that crosses the optical axis in front
        of the camera.
    """

    normal: np.ndarray
    offset_m: float

    @property
    def theta_rad(self) -> float:
        """Angle between the normal and the optical axis [rad], in [0, pi/2]."""
        return float(math.acos(min(1.0, abs(float(self.normal[2])))))

    def depth_at(self, up, vp) -> np.ndarray:
        """Depth z [m] where the rays of normalised pixels (u', v') hit the plane: z = offset / (n . (u', v', 1));
        NaN where they miss it or hit it behind the camera."""
        up = np.asarray(up, dtype=np.float64)
        vp = np.asarray(vp, dtype=np.float64)
        n = self.normal
        den = n[0] * up + n[1] * vp + n[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = self.offset_m / den
        return np.where(np.isfinite(z) & (z > 0), z, np.nan)

    def distance(self, points) -> np.ndarray:
        """Signed orthogonal distance n . p - offset_m [m] of points (..., 3) to the plane (> 0 beyond it)."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.normal - self.offset_m


@dataclass(frozen=True)
class PlaneFit:
    """A robust plane fit: the plane, which data it kept, and how far the kept data lie from it.

    Attributes
    ----------
    plane : Plane
    inliers : ndarray of bool
        The data within the inlier threshold of the plane, shaped like the data: (M,) for M points or
        depths; (H, W) for :func:`fit_plane_ransac` (pixels of the region, in the frame it used).
    threshold_m : float
        Inlier threshold [m]: ``inlier_rel`` times the median depth (:func:`fit_plane_robust`); the final
        |z - z_plane| bound (:func:`fit_plane_rays`); at the region's median depth, each pixel's being
        ``inlier_rel`` times its own depth (:func:`fit_plane_ransac`).
    residual_std_m : float
        Root mean square residual of the inliers [m]: orthogonal distance to the plane, or depth along
        the ray (z - z_plane) for :func:`fit_plane_rays`.
    residual_mad_sigma_m : float
        1.4826 times the median absolute deviation of the inliers' residuals [m] (a robust standard
        deviation).
    """

    plane: Plane
    inliers: np.ndarray
    threshold_m: float
    residual_std_m: float
    residual_mad_sigma_m: float

    @property
    def normal(self) -> np.ndarray:
        """The plane's unit normal (3,)."""
        return self.plane.normal

    @property
    def offset_m(self) -> float:
        """The plane's offset n . p [m]."""
        return self.plane.offset_m

    @property
    def incidence_deg(self) -> float:
        """Angle between the normal and the optical axis [deg]."""
        return float(np.degrees(np.arccos(min(1.0, abs(self.plane.normal[2])))))

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def _mad_sigma(r: np.ndarray) -> float:
    """1.4826 median |r - median r|: the standard deviation of a normal sample, robust to outliers."""
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


def _check_points3(points, name="points_cam", min_points=3) -> np.ndarray:
    """:func:`noise_model.checks.check_points`, and at least ``min_points`` of them (a plane needs 3)."""
    p = check_points(points, name)
    if p.shape[0] < min_points:
        raise ValueError(f"{name} needs at least {min_points} points for a plane, got {p.shape[0]}")
    return p


def _tls_plane(p: np.ndarray) -> Plane:
    """The plane through the centroid c whose normal is the direction of least spread (last right
    singular vector of p - c), oriented n_z >= 0."""
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[-1]
    if n[2] < 0:
        n = -n
    return Plane(n / np.linalg.norm(n), float(n @ c))


def fit_plane(points) -> Plane:
    """Total-least-squares plane of camera-frame points (SVD of the centred points).

    Parameters
    ----------
    points : array_like, shape (M, 3)
        Camera-frame points [m], finite, M >= 3.

    Returns
    -------
    Plane
        Oriented n_z >= 0.
    """
    return _tls_plane(_check_points3(points))


def fit_plane_robust(points, inlier_rel: float = INLIER_REL, max_iter: int = 30) -> PlaneFit:
    """Plane fit that ignores points off the plane (objects in front of or behind it, flying pixels).

    The inliers are the points within ``inlier_rel`` x (median depth) of the plane, refitted by total
    least squares until they no longer change. The start is deterministic instead of random: a fit to
    all points, then inliers within 4 robust standard deviations of the distances (at least the final
    threshold), the threshold halved at each refit down to the final one, so that a large fraction of
    off-plane points does not capture the fit.

    Parameters
    ----------
    points : array_like, shape (M, 3)
        Camera-frame points [m], finite, z > 0.
    inlier_rel : float
        Inlier threshold relative to the median depth (default :data:`INLIER_REL`).
    max_iter : int
        Largest number of refits.

    Returns
    -------
    PlaneFit
        Oriented n_z >= 0; ``inliers`` shape (M,); residuals are orthogonal distances.
    """
    p = _check_points3(points)
    if np.any(p[:, 2] <= 0):
        raise ValueError("points_cam must lie in front of the camera (z > 0)")
    rel = check_positive_scalar(inlier_rel, "inlier_rel", upper=1.0)
    thr = rel * float(np.median(p[:, 2]))
    plane = _tls_plane(p)
    d = np.abs(plane.distance(p))
    # shrink from a generous threshold (robust against a large fraction of off-plane points)
    scale = max(4.0 * 1.4826 * float(np.median(d)), thr)
    inl = d <= scale
    for _ in range(int(max_iter)):
        if inl.sum() < 3:
            break
        plane = _tls_plane(p[inl])
        d = np.abs(plane.distance(p))
        scale = max(thr, 0.5 * scale)
        new = d <= scale
        if scale == thr and np.array_equal(new, inl):
            break
        inl = new
    if inl.sum() < 3:
        raise ValueError("no plane found: fewer than 3 points lie within the inlier threshold")
    di = plane.distance(p[inl])
    return PlaneFit(plane, inl, thr, float(np.sqrt(np.mean(di * di))), _mad_sigma(di))


def fit_plane_rays(z_m, up, vp, inlier_rel: float = INLIER_REL, n_sigma: float = 4.0,
                   max_iter: int = 30) -> PlaneFit:
    """Plane fit by least squares *along the pixels' rays*, for depth whose noise is along the rays.

    A plane n . p = d seen through a pinhole is linear in inverse depth: 1/z = alpha u' + beta v' + gamma,
    with noise-free regressors (u', v'). Each step solves that linear system with rows weighted by
    z_plane^2 (so the residual is, to first order, the depth error z - z_plane, the quantity the noise
    model describes); the weights come from the previous step's plane, not from the noisy depths. Total
    least squares (:func:`fit_plane_robust`) is the right fit for isotropic noise but tilts towards the
    rays when the depth noise is large against the region's extent (a narrow strip of an oblique board).

    Inliers: |z - z_plane| <= max(inlier_rel x median depth, n_sigma x robust sigma of the residuals),
    narrowed from a generous start as in :func:`fit_plane_robust`.

    Parameters
    ----------
    z_m : array_like, shape (M,)
        Depths [m] (finite, > 0).
    up, vp : array_like, shape (M,)
        Normalised pixel coordinates.
    inlier_rel : float
        Smallest inlier threshold relative to the median depth.
    n_sigma : float
        Inlier threshold in robust standard deviations of the depth residuals.
    max_iter : int
        Largest number of refits.

    Returns
    -------
    PlaneFit
        Oriented n_z > 0 (offset > 0); ``inliers`` shape (M,); ``residual_std_m`` and
        ``residual_mad_sigma_m`` are of the depth residuals z - z_plane [m].
    """
    z = np.asarray(z_m, dtype=np.float64).ravel()
    up = np.asarray(up, dtype=np.float64).ravel()
    vp = np.asarray(vp, dtype=np.float64).ravel()
    if not (z.shape == up.shape == vp.shape):
        raise ValueError(f"z_m, up and vp must have the same shape, got {z.shape}, {up.shape}, {vp.shape}")
    if z.size < 3 or not np.all(np.isfinite(z)) or np.any(z <= 0):
        raise ValueError("z_m must hold at least 3 finite depths > 0 [m]")
    if float(z.max()) > 100.0:
        raise ValueError(f"z_m holds values up to {float(z.max()):.1f}: depth must be in metres")
    rel = check_positive_scalar(inlier_rel, "inlier_rel", upper=1.0)
    A = np.stack([up, vp, np.ones_like(up)], axis=1)
    w_obs = 1.0 / z
    zw = z.copy()
    inl = np.ones(z.size, dtype=bool)
    thr0 = rel * float(np.median(z))
    scale = np.inf
    coef = None
    for it in range(int(max_iter)):
        if inl.sum() < 3:
            break
        # 1/z = A coef, rows weighted by z_plane^2 so that the residual is z - z_plane to first order
        W2 = zw[inl] ** 2
        coef, *_ = np.linalg.lstsq(A[inl] * W2[:, None], w_obs[inl] * W2, rcond=None)
        den = A @ coef
        with np.errstate(divide="ignore", invalid="ignore"):
            zp = np.where(den > 0, 1.0 / den, np.nan)
        r = z - zp
        ok = np.isfinite(r)
        zw = np.where(np.isfinite(zp), zp, z)
        ri = r[inl & ok]
        sig = _mad_sigma(ri) if ri.size else 0.0
        target = max(thr0, n_sigma * sig)
        scale = 4.0 * target if not np.isfinite(scale) else max(target, 0.5 * scale)
        new = ok & (np.abs(r) <= scale)
        if scale == target and np.array_equal(new, inl) and it > 0:
            break
        inl = new
    if coef is None or inl.sum() < 3:
        raise ValueError("no plane found: fewer than 3 points lie within the inlier threshold")
    g = float(np.linalg.norm(coef))
    if not np.isfinite(g) or g == 0 or coef[2] <= 0:
        raise ValueError("no plane in front of the camera fits these depths")
    # (alpha, beta, gamma) . (u', v', 1) = 1/z  <=>  n . p = d with n = coef / |coef|, d = 1 / |coef|
    plane = Plane(coef / g, 1.0 / g)
    r = (z - plane.depth_at(up, vp))[inl]
    return PlaneFit(plane, inl, float(scale), float(np.sqrt(np.mean(r * r))), _mad_sigma(r))


def fit_plane_ransac(depth_m, K, roi, *, inlier_rel: float = INLIER_REL, iterations: int = 300,
                     seed: int = 0) -> PlaneFit:
    """RANSAC plane through a region's valid pixels of one depth frame, refitted by SVD on its inliers.

    A pixel with depth z is an inlier when its orthogonal distance to the plane is below inlier_rel x z
    (the depth noise grows with depth). RANSAC keeps the plane through 3 random points with the most
    inliers; two rounds of total least squares on the inliers (each with the inliers recomputed), then
    a last one, give the plane.

    Parameters
    ----------
    depth_m : array_like, shape (F, H, W) or (H, W), float
        Depth [m], NaN = no data (only the first frame is used).
    K : array_like, shape (3, 3)
        Intrinsics [px].
    roi : array_like of bool, shape (H, W)
        The region (e.g. a fronto-parallel board or a wall).
    inlier_rel : float
        Inlier threshold as a fraction of each pixel's depth (default :data:`INLIER_REL`).
    iterations : int
        RANSAC samples.
    seed : int
        Seed of the samples.

    Returns
    -------
    PlaneFit
        Oriented offset_m >= 0; ``inliers`` shape (H, W); residuals are orthogonal distances.

    Raises
    ------
    ValueError
        Fewer than 100 valid pixels in the region, bad shapes, degenerate points.
    """
    d = np.asarray(depth_m, dtype=np.float64)
    d = d[0] if d.ndim == 3 else d
    if d.ndim != 2:
        raise ValueError(f"depth_m must be (F, H, W) or (H, W), got {np.asarray(depth_m).shape}")
    r = np.asarray(roi)
    if r.shape != d.shape or r.dtype != bool:
        raise ValueError(f"roi must be a boolean image of shape {d.shape}")
    Kc = check_intrinsics(K)
    th = check_positive_scalar(inlier_rel, "inlier_rel", upper=0.5)
    H, W = d.shape
    vv, uu = np.nonzero(r & np.isfinite(d) & (d > 0))
    if vv.size < 100:
        raise ValueError(f"the region has {vv.size} pixels with data; a plane fit needs >= 100")
    z = d[vv, uu]
    P = np.column_stack([(uu - Kc[0, 2]) * z / Kc[0, 0], (vv - Kc[1, 2]) * z / Kc[1, 1], z])
    rng = np.random.default_rng(seed)
    best, best_n = None, -1
    for _ in range(int(iterations)):
        idx = rng.choice(P.shape[0], 3, replace=False)
        a, b, c = P[idx]
        n = np.cross(b - a, c - a)
        nn = np.linalg.norm(n)
        if nn < 1e-12:
            continue
        n /= nn
        inl = np.abs(P @ n - n @ a) < th * z
        cnt = int(inl.sum())
        if cnt > best_n:
            best, best_n = inl, cnt
    if best is None:
        raise ValueError("plane fit failed: the region's points are degenerate")
    for _ in range(2):
        Q = P[best]
        cen = Q.mean(axis=0)
        n = np.linalg.svd(Q - cen, full_matrices=False)[2][-1]
        c = float(n @ cen)
        best = np.abs(P @ n - c) < th * z
    Q = P[best]
    cen = Q.mean(axis=0)
    n = np.linalg.svd(Q - cen, full_matrices=False)[2][-1]
    c = float(n @ cen)
    if c < 0:
        n, c = -n, -c
    # the plane passes through the inliers' centroid, so their distances have mean 0: std = RMS
    dist = P[best] @ n - c
    mask = np.zeros((H, W), dtype=bool)
    mask[vv[best], uu[best]] = True
    return PlaneFit(Plane(n, c), mask, th * float(np.median(z)), float(np.std(dist)), _mad_sigma(dist))


def normalised_coordinates(K, us, vs) -> tuple[np.ndarray, np.ndarray]:
    """(u', v') = ((u - cx) / fx, (v - cy) / fy) of pixel columns ``us`` and rows ``vs`` [px]."""
    K = check_intrinsics(K)
    return ((np.asarray(us, dtype=np.float64) - K[0, 2]) / K[0, 0],
            (np.asarray(vs, dtype=np.float64) - K[1, 2]) / K[1, 1])


def points_from_depth(z, up, vp) -> np.ndarray:
    """Camera-frame points (..., 3) [m] of depths z [m] on the rays (u', v', 1): p = z (u', v', 1)."""
    z = np.asarray(z, dtype=np.float64)
    return np.stack([np.asarray(up) * z, np.asarray(vp) * z, z], axis=-1)


def target_plane(target) -> Plane:
    """The plane of a capture-set target (a ``target`` object of captures.json), as a :class:`Plane`.

    * ``kind`` "wall" or "board": the normal is R e_z with R = R_y(yaw) R_x(pitch) (the target's axes,
      :func:`noise_model.sim.targets.target_rotation`) and the plane passes through the target's centre
      c = (0, 0, distance_m): offset_m = c . R e_z = distance_m cos(yaw) cos(pitch).
    * ``kind`` "plane": the file's ``normal`` m points towards the camera (m_z < 0) and the plane is
      m . p + offset_m = 0, so here normal = -m / |m| and offset_m is the file's (both > 0 on the axis).

    Parameters
    ----------
    target : mapping
        ``kind`` and its keys (``distance_m`` [m], ``yaw_deg``, ``pitch_deg`` [deg]; or ``normal`` (3,),
        ``offset_m`` [m]).

    Returns
    -------
    Plane
        n . p = offset_m with n_z > 0 and offset_m > 0 (the plane crosses the optical axis in front of
        the camera).

    Raises
    ------
    ValueError
        An unknown kind, a missing or non-finite key, a zero or backward-facing normal, offset_m <= 0.
    """
    kind = target.get("kind") if hasattr(target, "get") else None
    if kind in ("wall", "board"):
        from ..sim.targets import target_rotation

        d = _finite(target.get("distance_m"), "target distance_m")
        R = target_rotation(_finite(target.get("yaw_deg") or 0.0, "target yaw_deg"),
                            _finite(target.get("pitch_deg") or 0.0, "target pitch_deg"))
        n = R[:, 2]
        off = d * float(n[2])
        if d <= 0 or n[2] <= 1e-12:
            raise ValueError(f"target distance_m {d} m, yaw_deg/pitch_deg: the plane does not face the camera")
        return Plane(n, off)
    if kind == "plane":
        m = np.asarray(target.get("normal"), dtype=np.float64) if target.get("normal") is not None else None
        if m is None or m.shape != (3,) or not np.all(np.isfinite(m)):
            raise ValueError(f"target normal must be 3 finite numbers, got {target.get('normal')!r}")
        norm = float(np.linalg.norm(m))
        if norm == 0.0 or m[2] >= 0:
            raise ValueError(f"target normal {m.tolist()} must point towards the camera (normal[2] < 0)")
        off = _finite(target.get("offset_m"), "target offset_m")
        if off <= 0:
            raise ValueError(f"target offset_m = {off} m must be > 0 (the camera's distance to the plane)")
        return Plane(-m / norm, off)
    raise ValueError(f"target kind must be 'wall', 'board' or 'plane', got {kind!r}")


def plane_pose(plane: Plane) -> tuple[float, float, float]:
    """The wall pose (distance_m [m], yaw_deg, pitch_deg [deg]) whose plane is ``plane``.

    The inverse of :func:`target_plane` for a wall: with n = R e_z = (sin a cos b, -sin b, cos a cos b),
    pitch b = -asin(n_y), yaw a = atan2(n_x, n_z), and the plane meets the optical axis at
    distance_m = offset_m / n_z.

    Parameters
    ----------
    plane : Plane
        With n_z > 0 and offset_m > 0 (it crosses the optical axis in front of the camera).

    Returns
    -------
    (float, float, float)

    Raises
    ------
    ValueError
        The plane does not cross the optical axis in front of the camera.
    """
    n = np.asarray(plane.normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    if not (n[2] > 1e-12 and plane.offset_m > 0):
        raise ValueError(f"plane normal {n.tolist()}, offset {plane.offset_m} m does not cross the optical axis "
                         "in front of the camera")
    pitch = -math.degrees(math.asin(min(1.0, max(-1.0, float(n[1])))))
    yaw = math.degrees(math.atan2(float(n[0]), float(n[2])))
    return float(plane.offset_m / n[2]), yaw, pitch


def _finite(v, name: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(float(v)):
        raise ValueError(f"{name} must be a finite number, got {v!r}")
    return float(v)
