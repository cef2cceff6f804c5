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

:func:`find_planes` finds the dominant planes of a static stretch of frames (RANSAC one after the
other on the per-pixel mean, each refitted along the rays) and gives each a pixel mask bounded by the
stretch's own temporal noise (:class:`MaskedPlane`). :func:`target_plane` and :func:`plane_pose` turn a
capture-set target into its plane and back.

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
    "stretch_mean",
    "find_planes",
    "MaskedPlane",
    "INLIER_REL",
    "MASK_N_SIGMA",
    "MIN_PLANE_FRACTION",
    "MAX_SPREAD",
]

#: Inlier threshold of the plane fits, relative to the depth (2 %): the threshold of the RANSAC-and-SVD
#: plane fit behind the plane-fit RMS error that the camera's reference figures quote, so residuals
#: measured here compare with them. At 1-3 m it is a few sigma_z.
INLIER_REL = 0.02

#: Half-width of a plane's pixel mask, in single-frame temporal standard deviations at the pixel's depth.
#: The per-pixel mean of a flat surface lies off its plane by the surface's static error (the camera's
#: fixed pattern and the surface's own unevenness, on real D435 data about as large as one frame's
#: temporal sigma) plus sigma / sqrt(N); 4 sigma keeps all of it, so the static pattern a diagnosis
#: looks for is not cut away, and rejects what stands off the plane by more (objects, mixed pixels).
MASK_N_SIGMA = 4.0

#: Smallest plane :func:`find_planes` reports, as a fraction of the image: a dominant plane. Below 5 %
#: a "plane" is a patch of an object (a box side, a chair seat), and its pixels are too few to split
#: into depth and angle bins of a thousand pixels each.
MIN_PLANE_FRACTION = 0.05

#: Largest median of |residual| / half-width over a plane's mask for it to count as a plane. Points
#: that merely happen to lie within the band (no surface there) spread evenly over it and give 0.5; the
#: mean of a flat surface, whose residuals have a standard deviation of a quarter of the band
#: (n_sigma = 4) or less, gives 0.17 or less; 0.3 lies between.
MAX_SPREAD = 0.3

#: Distance [px] within which a pixel in the bands of two planes is taken as seeing where they meet
#: (:func:`find_planes`, step 6): about the half-width of a stereo matching window at VGA-like sizes.
MEET_PX = 4

#: Pixels :func:`find_planes` gives RANSAC at most (a regular subsample of the image).
RANSAC_SAMPLE_PX = 20000


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


def stretch_mean(depth_m, min_valid_fraction: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel mean and temporal standard deviation of a static stretch of frames, ignoring no-data.

    Parameters
    ----------
    depth_m : array_like, shape (F, H, W), float
        Depth [m] of F >= 2 frames of a static camera; NaN (or 0) = no data.
    min_valid_fraction : float
        A pixel counts only where at least this fraction of the frames (and at least 2) have data: the
        mean of a pixel that mostly drops out is a few samples, often of its edge.

    Returns
    -------
    mean_m : ndarray, shape (H, W)
        Mean depth over the frames with data [m]; NaN where the pixel does not count.
    temporal_std_m : ndarray, shape (H, W)
        Sample standard deviation over those frames (ddof = 1) [m]; NaN where the pixel does not count.
    """
    d = np.asarray(depth_m, dtype=np.float64)
    if d.ndim != 3 or d.shape[0] < 2:
        raise ValueError(f"depth_m must be (frames >= 2, H, W): a stretch's temporal noise needs 2 frames, "
                         f"got shape {d.shape}")
    if np.isinf(d).any():
        raise ValueError("depth_m has infinite values (no data must be NaN)")
    frac = check_positive_scalar(min_valid_fraction, "min_valid_fraction", upper=1.0)
    d = np.where(d > 0, d, np.nan)
    n = np.isfinite(d).sum(axis=0)
    ok = (n >= max(2, math.ceil(frac * d.shape[0] - 1e-9)))
    s = np.where(ok, np.nansum(np.where(np.isfinite(d), d, 0.0), axis=0), np.nan)
    mean = np.where(ok, s / np.maximum(n, 1), np.nan)
    dev = np.where(np.isfinite(d), d - mean, 0.0)
    std = np.where(ok, np.sqrt((dev * dev).sum(axis=0) / np.maximum(n - 1, 1)), np.nan)
    return mean, std


@dataclass(frozen=True)
class MaskedPlane:
    """A plane found in a static stretch, with the pixels that see it.

    Attributes
    ----------
    plane : Plane
        n . p = offset_m, n_z > 0, offset_m > 0 (it crosses the optical axis in front of the camera).
    mask : ndarray of bool, shape (H, W)
        Pixels whose mean depth lies within ``n_sigma`` temporal sigmas (at their depth, at most
        ``inlier_rel`` of it) of the plane, morphologically cleaned (:func:`find_planes`).
    temporal_k_per_m : float
        The stretch's temporal noise on this plane as sigma_t(z) = k z^2 [m] (k [1/m]): the median over
        the mask of std / z^2. Stereo depth noise grows as z^2 sigma_d / (f B), so k = sigma_d / (f B).
    n_sigma : float
        Half-width of the mask in sigma_t.
    inlier_rel : float
        Largest half-width of the mask relative to the depth.
    residual_std_m, residual_mad_sigma_m : float
        RMS and robust sigma (1.4826 MAD) of the mean depth's residual z - z_plane over the mask [m].
    spread : float
        Median over the mask of |z - z_plane| / the mask's half-width at the pixel: 0.5 for points
        spread evenly over the band, small for a surface (:data:`MAX_SPREAD`).
    support : int
        Pixels of the RANSAC consensus that found it (within ``inlier_rel`` of the depth).
    """

    plane: Plane
    mask: np.ndarray
    temporal_k_per_m: float
    n_sigma: float
    inlier_rel: float
    residual_std_m: float
    residual_mad_sigma_m: float
    spread: float
    support: int

    @property
    def n_pixels(self) -> int:
        return int(self.mask.sum())

    @property
    def incidence_deg(self) -> float:
        """Angle between the plane's normal and the optical axis [deg]."""
        return float(np.degrees(self.plane.theta_rad))

    def threshold_m(self, z_m) -> np.ndarray:
        """The mask's half-width at depth z [m]: min(n_sigma k z, inlier_rel) z (before the 2-unit floor)."""
        z = np.asarray(z_m, dtype=np.float64)
        return np.minimum(self.n_sigma * self.temporal_k_per_m * z, self.inlier_rel) * z


def _clean_mask(mask: np.ndarray, min_component_px: int) -> np.ndarray:
    """Opening by a 3 x 3 square (drops single pixels and strands 1-2 px wide: where another surface
    crosses the plane's depth along a line), then only 8-connected components of at least
    ``min_component_px`` pixels."""
    from scipy import ndimage

    m = ndimage.binary_opening(mask, structure=np.ones((3, 3), dtype=bool))
    lab, n = ndimage.label(m, structure=np.ones((3, 3), dtype=bool))
    if n == 0:
        return m
    size = np.bincount(lab.ravel(), minlength=n + 1)
    keep = size >= min_component_px
    keep[0] = False
    return keep[lab]


def _settle_meeting_pixels(found: list[MaskedPlane], mean, up, vp, unit: float, min_component: int) -> list:
    """The masks with the pixels where planes meet settled (:func:`find_planes`, step 6).

    A pixel of some mask whose mean lies within the bands of several planes is ambiguous. It goes to the
    plane whose unambiguous pixels are nearest in the image (the side of the line where the surfaces
    meet that it lies on), and leaves every mask when another of those planes has pixels (after this
    assignment) within :data:`MEET_PX`. The masks are then cleaned again.
    """
    from scipy import ndimage

    if len(found) < 2:
        return [mp.mask for mp in found]
    bands = []
    for mp in found:
        zp = mp.plane.depth_at(up, vp)
        with np.errstate(invalid="ignore"):
            bands.append(np.abs(mean - zp) <= np.maximum(mp.threshold_m(zp), 2.0 * unit))
    bands = np.stack(bands)
    taken = np.zeros(mean.shape, dtype=bool)
    for mp in found:
        taken |= mp.mask
    in_bands = bands & taken[None]
    ambiguous = in_bands.sum(axis=0) >= 2
    # the side: the plane (whose band holds the pixel) with the nearest unambiguous pixels [px]
    dist = np.stack([ndimage.distance_transform_edt(~(mp.mask & ~ambiguous)) for mp in found])
    owner = np.argmin(np.where(in_bands, dist, np.inf), axis=0)
    sides = [np.where(ambiguous, owner == k, mp.mask) for k, mp in enumerate(found)]
    # the meeting: another plane whose band holds the pixel has pixels within MEET_PX of it
    near = np.stack([ndimage.distance_transform_edt(~side) <= MEET_PX for side in sides])
    meets = (in_bands & near & (np.arange(len(found))[:, None, None] != owner[None])).any(axis=0)
    return [_clean_mask(side & ~(ambiguous & meets), min_component) for side in sides]


def find_planes(depth_m, K, *, max_planes: int = 4, min_plane_fraction: float = MIN_PLANE_FRACTION,
                n_sigma: float = MASK_N_SIGMA, max_spread: float = MAX_SPREAD, min_valid_fraction: float = 0.5,
                depth_unit_m: float = 0.001,
                inlier_rel: float = INLIER_REL, iterations: int = 300, seed: int = 0) -> list[MaskedPlane]:
    """The dominant planes of a static stretch of frames, each with its pixel mask, largest first.

    1. The stretch's per-pixel mean and temporal sigma (:func:`stretch_mean`).
    2. RANSAC on the mean over the pixels no plane has taken yet (:func:`fit_plane_ransac` on a regular
       subsample of them, inliers within ``inlier_rel`` x depth): the plane with the largest consensus;
       its support is every free pixel within ``inlier_rel`` x depth of it.
    3. The stretch's temporal noise on it, sigma_t(z) = k z^2 with k the median of std / z^2 (stereo
       noise grows as z^2 sigma_d / (f B); the fit measures sigma_d / (f B) on the data, so neither the
       baseline nor a noise model is assumed).
    4. Mask: free pixels whose mean lies within max(min(n_sigma sigma_t(z), inlier_rel z), 2 depth
       units) of the plane along the ray, z = z_plane. The band is never wider than RANSAC's rule:
       where n_sigma sigma_t exceeds it (far along a grazing floor, whose depth grows without bound
       towards its horizon) the mean's own noise sigma_t / sqrt(F) is still well inside it, and a wider
       band would take in whatever stands near the plane far away. It is never narrower than 2 depth
       units, the frames' resolution. The mask is cleaned (an opening by a 3 x 3 square, then
       8-connected components of at least 1 % of the minimum plane size); the plane is refitted along
       the rays (:func:`fit_plane_rays`) to the mask's mean depths and k re-measured, three times.
    5. A plane whose mask holds at least ``min_plane_fraction`` of the image, and whose residuals are
       concentrated near it (``spread`` at most ``max_spread``), is kept. Its RANSAC consensus and mask
       leave the pool either way; repeat from 2 until ``max_planes`` planes are kept or no consensus is
       large enough.
    6. Where planes meet: a mask pixel whose mean lies within the bands of several kept planes goes to
       the one whose unambiguous pixels are nearest (the side of the meeting line it lies on), and leaves
       every mask when another such plane's unambiguous pixels lie within :data:`MEET_PX`: there the
       mean cannot tell the surfaces apart and the camera's matching window sees both. Where one plane's
       band crosses the other far from its pixels (a wall's plane continued across the floor beside the
       wall) only one surface is there, and the pixels stay. The masks are cleaned again.

    Parameters
    ----------
    depth_m : array_like, shape (F, H, W), float
        Depth [m] of F >= 2 frames of a static camera, NaN = no data.
    K : array_like, shape (3, 3)
        Intrinsics [px].
    max_planes : int
        Most planes to find.
    min_plane_fraction : float
        Smallest mask kept, as a fraction of H W (default :data:`MIN_PLANE_FRACTION`).
    n_sigma : float
        Mask half-width in temporal sigmas (default :data:`MASK_N_SIGMA`).
    max_spread : float
        Largest :attr:`MaskedPlane.spread` of a plane (default :data:`MAX_SPREAD`).
    min_valid_fraction : float
        See :func:`stretch_mean`.
    depth_unit_m : float
        The frames' depth unit [m]: the mask is never narrower than 2 units.
    inlier_rel, iterations, seed
        RANSAC's threshold relative to the depth, samples, and seed (plane k uses ``seed + k``).

    Returns
    -------
    list of MaskedPlane
        Largest mask first; masks do not overlap.
    """
    Kc = check_intrinsics(K)
    mean, std = stretch_mean(depth_m, min_valid_fraction)
    H, W = mean.shape
    frac = check_positive_scalar(min_plane_fraction, "min_plane_fraction", upper=1.0)
    ns = check_positive_scalar(n_sigma, "n_sigma", upper=100.0)
    spread_max = check_positive_scalar(max_spread, "max_spread", upper=1.0)
    unit = check_positive_scalar(depth_unit_m, "depth_unit_m", upper=0.1, unit=" m")
    if isinstance(max_planes, bool) or not isinstance(max_planes, (int, np.integer)) or max_planes < 1:
        raise ValueError(f"max_planes must be an integer >= 1, got {max_planes!r}")
    rel = check_positive_scalar(inlier_rel, "inlier_rel", upper=0.5)
    min_px = max(100, int(math.ceil(frac * H * W)))
    min_component = max(9, min_px // 100)
    up, vp = normalised_coordinates(Kc, np.arange(W)[None, :], np.arange(H)[:, None])
    up, vp = np.broadcast_to(up, (H, W)), np.broadcast_to(vp, (H, W))
    noisy = np.isfinite(std) & (std > 0)
    pool = np.isfinite(mean)
    found: list[MaskedPlane] = []
    k = -1
    while len(found) < int(max_planes):
        k += 1
        if pool.sum() < min_px:
            break
        # RANSAC on a regular subsample of the pool (at most ~RANSAC_SAMPLE_PX pixels): the consensus of a
        # plane covering >= 5 % of the image is decided as surely by a few ten thousand pixels, and the
        # plane is refitted on every pixel below
        stride = max(1, int(math.sqrt(pool.sum() / RANSAC_SAMPLE_PX)))
        sub = np.zeros_like(pool)
        sub[::stride, ::stride] = pool[::stride, ::stride]
        try:
            pf = fit_plane_ransac(mean, Kc, sub, inlier_rel=rel, iterations=iterations, seed=seed + k)
        except ValueError:
            break
        plane = pf.plane
        with np.errstate(invalid="ignore"):
            support = pool & (np.abs(plane.distance(points_from_depth(mean, up, vp))) < rel * mean)
        if support.sum() < min_px:
            break
        if plane.normal[2] <= 1e-9:          # seen only edge-on or from behind the optical axis: skip it
            pool &= ~support
            continue
        region = support
        mask = None
        kz = float("nan")
        for it in range(4):                  # mask, refit, mask, ...: three refits, the last mask on the last fit
            sel = region & noisy
            if sel.sum() < 3:
                mask = None
                break
            kz = float(np.median(std[sel] / mean[sel] ** 2))
            zp = plane.depth_at(up, vp)
            with np.errstate(invalid="ignore"):
                near = np.abs(mean - zp) <= np.maximum(np.minimum(ns * kz * zp, rel) * zp, 2.0 * unit)
            mask = _clean_mask(pool & near, min_component)
            if it == 3 or mask.sum() < 3:
                break
            try:
                plane = fit_plane_rays(mean[mask], up[mask], vp[mask]).plane
            except ValueError:
                mask = None
                break
            region = mask
        if mask is None or mask.sum() < min_px or not np.isfinite(kz):
            pool &= ~support
            continue
        zp = plane.depth_at(up, vp)[mask]
        r = mean[mask] - zp
        half = np.maximum(np.minimum(ns * kz * zp, rel) * zp, 2.0 * unit)
        spread = float(np.median(np.abs(r) / half))
        pool &= ~(support | mask)
        if spread <= spread_max:
            found.append(MaskedPlane(plane, mask, kz, ns, rel, float(np.sqrt(np.mean(r * r))), _mad_sigma(r),
                                     spread, int(support.sum())))
    masks = _settle_meeting_pixels(found, mean, up, vp, unit, min_component)
    out = []
    for mp, mask in zip(found, masks):
        if mask.sum() < min_px:
            continue
        zp = mp.plane.depth_at(up, vp)[mask]
        r = mean[mask] - zp
        half = np.maximum(np.minimum(ns * mp.temporal_k_per_m * zp, rel) * zp, 2.0 * unit)
        out.append(MaskedPlane(mp.plane, mask, mp.temporal_k_per_m, ns, rel, float(np.sqrt(np.mean(r * r))),
                               _mad_sigma(r), float(np.median(np.abs(r) / half)), mp.support))
    out.sort(key=lambda m: -m.n_pixels)
    return out
