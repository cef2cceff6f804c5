"""Per-point 3-D covariances: the D435 noise in the camera frame, then in the map frame.

Camera frame
------------
A pixel (u, v) with depth z deprojects to p = z r, r = ((u - cx)/fx, (v - cy)/fy, 1) = p / z.

* Axial noise: an error dz moves the point along its viewing ray, dp = r dz, so it contributes
  sigma_z(z, theta)^2 r r^T (not a variance on the camera z axis alone).
* Lateral noise acts in the image-plane directions (camera x and y). Across a depth edge the paper's
  sigma_L (left edges) or sigma_R (right edges) [m] applies along x; the paper's edges are vertical
  (left/right boundaries of a target), so their lateral error is horizontal in the image.
  Everywhere else the lateral term is the pixel footprint: the true ray lies anywhere inside the
  pixel, a uniform error of one pixel width, variance 1/12 px^2, i.e. sigma_x = z / (fx sqrt(12)) and
  sigma_y = z / (fy sqrt(12)) [m] (1.4 mm at 2 m for the 848-wide stream).

So Sigma_cam = sigma_z^2 r r^T + diag(sigma_x^2, sigma_y^2, 0).

Map frame
---------
p_map = R p_cam + t with T_map_cam = [[R, t], [0, 1]]. The pose error is a 6-vector xi = (rho, phi):
translation first [m] then rotation [rad], both expressed in the map frame, and the rotation is
about the camera centre:

    T_map_cam = (Exp(phi) R_hat,  t_hat + rho),   so   p_map = p_hat + rho + phi x (R_hat p_cam).

This is the ordering and fixed-axis convention of ROS ``PoseWithCovariance`` (x, y, z, rot_x, rot_y,
rot_z). First order: Sigma_map = R Sigma_cam R^T + J Sigma_pose J^T, J = [I_3, -[R p_cam]_x].
"""

from __future__ import annotations

import numpy as np

from .checks import (
    check_angles, check_covariances, check_mask, check_points, check_pose_cov, check_positive_scalar,
    check_transform,
)
from .d435 import D435, SensorModel, axial_sigma_unchecked, axial_variance_unchecked

__all__ = ["point_covariances", "to_map_frame", "skew", "pose_jacobian", "PIXEL_VARIANCE_PX2"]

#: Variance of a uniform position error over one pixel [px^2].
PIXEL_VARIANCE_PX2 = 1.0 / 12.0


def skew(v) -> np.ndarray:
    """Cross-product matrices [v]_x of shape (..., 3, 3) with [v]_x w = v x w."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def pose_jacobian(points_cam, T_map_cam) -> np.ndarray:
    """d p_map / d xi, shape (N, 3, 6), for the pose error xi = (rho, phi) of :func:`to_map_frame`."""
    T = check_transform(T_map_cam)
    p = check_points(points_cam)
    q = p @ T[:3, :3].T
    J = np.zeros((len(p), 3, 6))
    J[:, :, :3] = np.eye(3)
    J[:, :, 3:] = -skew(q)
    return J


def point_covariances(points_cam, theta, edge_left=None, edge_right=None, *, fx: float | None = None,
                      fy: float | None = None, model: SensorModel = D435, z_noise=None,
                      theta_std=None, min_axial_var=None) -> np.ndarray:
    """Camera-frame covariance of each point under the D435 noise model.

    Parameters
    ----------
    points_cam : array_like, shape (N, 3)
        Valid camera-frame points [m], z > 0.
    theta : array_like, shape (N,)
        Incidence angles [rad] (see :func:`noise_model.incidence_angles`).
    edge_left, edge_right : array_like of bool, shape (N,), optional
        Points on a left / right depth edge (see :func:`noise_model.depth_edges`); a point on both
        (a one-pixel-wide object) gets the larger of sigma_L and sigma_R.
    fx, fy : float, optional
        Focal lengths [px] for the interior lateral term; the D435's 848x480 default (424 px). A
        disparity-family model not bound to a frame (``model.frame_fx_px`` None) needs ``fx``: its sigma_z
        is z^2 sigma_d(theta) / (fx B).
    model : SensorModel
        Noise model (the paper's by default).
    z_noise : array_like, shape (N,), optional
        Depth [m] at which sigma_z is evaluated (default: the points' own z). Pass a denoised depth
        (:func:`noise_model.plane_depths`) so that a point's weight does not depend on its own noise.
    theta_std : array_like, shape (N,), optional
        Standard deviation of the estimated theta [rad] (:func:`noise_model.incidence_angle_stats`); the
        axial variance is then E[sigma_z^2] over the angle's uncertainty
        (:func:`noise_model.axial_variance`) instead of sigma_z(theta)^2.
    min_axial_var : array_like, shape (N,), optional
        A floor [m^2] under the axial variance: a speckle's squared deviation from its neighbours
        (:func:`noise_model.despeckle`).

    Returns
    -------
    cov_cam : ndarray, shape (N, 3, 3) [m^2]
        sigma_z^2 r r^T + diag(sigma_x^2, sigma_y^2, 0), r = p / z; see the module docstring.
    """
    p = check_points(points_cam, "points_cam")
    n = len(p)
    if n and float(p[:, 2].min()) <= 0:
        raise ValueError("points_cam must have z > 0 (points in front of the camera)")
    th = check_angles(theta, n)
    left = check_mask(edge_left, n, "edge_left")
    right = check_mask(edge_right, n, "edge_right")
    if not isinstance(model, SensorModel):
        raise ValueError(f"model must be a noise_model.SensorModel, got {type(model).__name__}")
    if model.family == "disparity" and model.frame_fx_px is None:
        if fx is None:
            raise ValueError(f"sensor model {model.name!r} is of the disparity family: pass the frame's fx [px] "
                             "(its sigma_d is in pixels of the frame)")
        model = model.with_focal(fx)
    f_default = model.focal_px(848, 480)
    fx = check_positive_scalar(f_default if fx is None else fx, "fx", upper=1e5, unit=" px")
    fy = check_positive_scalar(f_default if fy is None else fy, "fy", upper=1e5, unit=" px")
    z = p[:, 2]
    r = p / z[:, None]
    zs = z
    if z_noise is not None:
        zs = np.asarray(z_noise, dtype=np.float64)
        if zs.shape != (n,) or not np.all(np.isfinite(zs)) or (n and float(zs.min()) <= 0):
            raise ValueError(f"z_noise must be ({n},) finite depths > 0 [m]")
    if theta_std is None:
        sz = axial_sigma_unchecked(zs, th, model)
        s2 = sz * sz
    else:
        ts = np.asarray(theta_std, dtype=np.float64)
        if ts.shape != (n,) or not np.all(np.isfinite(ts)) or (n and float(ts.min()) < 0):
            raise ValueError(f"theta_std must be ({n},) finite standard deviations >= 0 [rad]")
        s2 = axial_variance_unchecked(zs, th, ts, model)
    if min_axial_var is not None:
        floor = np.asarray(min_axial_var, dtype=np.float64)
        if floor.shape != (n,) or not np.all(np.isfinite(floor)) or (n and float(floor.min()) < 0):
            raise ValueError(f"min_axial_var must be ({n},) finite variances >= 0 [m^2]")
        s2 = np.maximum(s2, floor)
    cov = s2[:, None, None] * (r[:, :, None] * r[:, None, :])
    var_x = z * z * (PIXEL_VARIANCE_PX2 / (fx * fx))
    var_y = z * z * (PIXEL_VARIANCE_PX2 / (fy * fy))
    var_x = np.where(left, model.sigma_L ** 2, var_x)
    var_x = np.where(right, np.maximum(model.sigma_R ** 2, left * model.sigma_L ** 2), var_x)
    cov[:, 0, 0] += var_x
    cov[:, 1, 1] += var_y
    return cov


def to_map_frame(cov_cam, points_cam, T_map_cam, pose_cov=None) -> np.ndarray:
    """Map-frame covariance of camera-frame points, with first-order pose-uncertainty propagation.

    Parameters
    ----------
    cov_cam : array_like, shape (N, 3, 3)
        Camera-frame point covariances [m^2] (from :func:`point_covariances`).
    points_cam : array_like, shape (N, 3)
        The points in the camera frame [m].
    T_map_cam : array_like, shape (4, 4)
        Maps camera-frame points into the map frame: p_map = R p_cam + t.
    pose_cov : array_like, shape (6, 6), optional
        Covariance of the pose error xi = (rho, phi): translation (x, y, z) [m^2] first, then
        rotation (about map x, y, z) [rad^2]; the rotation error is a small rotation vector in the
        map frame applied about the camera centre (T = (Exp(phi) R, t + rho)), as in ROS
        ``PoseWithCovariance``.

    Returns
    -------
    cov_map : ndarray, shape (N, 3, 3) [m^2]
        R Sigma_cam R^T + J Sigma_pose J^T with J = [I_3, -[R p_cam]_x].
    """
    p = check_points(points_cam, "points_cam")
    C = check_covariances(cov_cam, len(p))
    T = check_transform(T_map_cam)
    R = T[:3, :3]
    out = np.einsum("ij,njk,lk->nil", R, C, R)
    if pose_cov is not None:
        P = check_pose_cov(pose_cov)
        J = pose_jacobian(p, T)
        out += np.einsum("nia,ab,njb->nij", J, P, J)
    return out
