"""The dominant planes of a static stretch of frames, each with its pixel mask (:func:`find_planes`).

RANSAC one plane after the other on the stretch's per-pixel mean (:func:`stretch_mean`), each refitted
along the rays (:mod:`.planes`), and a pixel mask per plane bounded by the stretch's own temporal noise
(:class:`MaskedPlane`). ``elevmap captures`` writes one capture per plane found. Camera frame and
normalised pixel coordinates as in :mod:`.planes`. NumPy and SciPy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..checks import check_intrinsics, check_positive_scalar
from .planes import (INLIER_REL, Plane, _mad_sigma, fit_plane_rays, fit_plane_ransac, normalised_coordinates,
                     points_from_depth)

__all__ = ["stretch_mean", "find_planes", "MaskedPlane", "MASK_N_SIGMA", "MIN_PLANE_FRACTION", "MAX_SPREAD"]

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
