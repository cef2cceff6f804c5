"""Other point-noise models than the paper's, for comparisons (``elevmap compare``).

Each factory returns a callable with the signature of the mapper's ``Camera.variance_model`` hook::

    model(points_cam (N, 3), T_map_cam (4, 4), pose_cov (6, 6) or None)
        -> (height_var (N,), horizontal_cov (N, 3))

* ``points_cam``: the frame's valid points in the camera frame [m] (x right, y down, z forward;
  ``points_cam[:, 2]`` is the depth z).
* ``T_map_cam``: maps camera-frame points into the map frame (z up), ``p_map = R p_cam + t``.
* ``pose_cov``: covariance of the camera pose error xi = (rho, phi), translation [m^2] then
  rotation [rad^2], both in the map frame, the rotation about the camera centre (the convention of
  :func:`noise_model.to_map_frame`); None = exact pose.
* ``height_var``: variance of each point's map-frame z [m^2], > 0.
* ``horizontal_cov``: the map-frame (xx, xy, yy) covariance of each point [m^2].

Models
------
:func:`constant`
    One isotropic sigma for every point (2 cm by default): the simplest baseline.
:func:`quadratic`
    elevation_mapping_cupy (Miki et al. 2022): ``variance = sensor_noise_factor * z^2`` with z the
    point's z in the *sensor* frame (the depth for a camera), factor 0.05 by default
    (``config/core/core_param.yaml``), used directly as the height variance (``add_points_kernel``:
    the noise is not projected onto the map's z axis and the pose uncertainty is not propagated).
:func:`anybotics_d435`
    ANYbotics' elevation_mapping, ``StructuredLightSensorProcessor::computeVariances`` with the
    ``realsense_d435.yaml`` preset: sigma_N = 0.000611 + 0.003587 (z - 0.3515)^2 on the sensor z
    axis, sigma_L = 0.01576 z on sensor x and y, Sigma_S = diag(sigma_L^2, sigma_L^2, sigma_N^2),
    rotated into the map frame; plus the robot-rotation term J_q Sigma_q J_q^T.

Each callable carries ``name``, ``params`` (its parameters, for reports) and ``source``.
This module uses NumPy only (no numba, rerun or elevmap).
"""

from __future__ import annotations

import numpy as np

from .checks import check_points, check_pose_cov, check_positive_scalar, check_transform
from .covariance import skew
from .registry import build_from_registry

__all__ = ["VarianceModel", "constant", "quadratic", "anybotics_d435", "ANYBOTICS_D435", "VARIANCE_MODELS",
           "make_variance_model"]

#: ANYbotics/elevation_mapping ``elevation_mapping/config/sensor_processors/realsense_d435.yaml``
#: (normal_factor_a, _b, _c, _d, _e, lateral_factor); d = 0 switches the power term off.
ANYBOTICS_D435 = {"normal_factor_a": 0.000611, "normal_factor_b": 0.003587, "normal_factor_c": 0.3515,
                  "normal_factor_d": 0.0, "normal_factor_e": 1.0, "lateral_factor": 0.01576}


class VarianceModel:
    """Base of the models here: input checks and the metadata shown in reports.

    Attributes
    ----------
    name : str
    params : dict
        Parameters (JSON-serialisable).
    source : str
        Where the model comes from.
    """

    name = "variance_model"
    source = ""

    def __init__(self, params: dict):
        self.params = dict(params)

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.params.items())
        return f"{self.name}({args})"

    def __call__(self, points_cam, T_map_cam, pose_cov=None):
        """Height variance and horizontal covariance of each point in the map frame.

        Parameters
        ----------
        points_cam : array_like, shape (N, 3)
            Camera-frame points [m], z > 0.
        T_map_cam : array_like, shape (4, 4)
            Camera pose: maps camera-frame points into the map frame.
        pose_cov : array_like, shape (6, 6), optional
            Camera pose covariance (translation [m^2] then rotation [rad^2], map frame, about the
            camera centre).

        Returns
        -------
        height_var : ndarray, shape (N,)
            [m^2], > 0.
        horizontal_cov : ndarray, shape (N, 3)
            Map-frame (xx, xy, yy) [m^2].
        """
        p = check_points(points_cam, "points_cam")
        if len(p) and float(p[:, 2].min()) <= 0:
            raise ValueError("points_cam must have z > 0 (points in front of the camera)")
        T = check_transform(T_map_cam, "T_map_cam")
        P = None if pose_cov is None else check_pose_cov(pose_cov, "pose_cov")
        return self._compute(p, T, P)

    def _compute(self, p, T, P):  # pragma: no cover - overridden
        raise NotImplementedError


class _Constant(VarianceModel):
    name = "constant"
    source = "a fixed isotropic sigma for every point (the simplest baseline)"

    def _compute(self, p, T, P):
        v = self.params["sigma_m"] ** 2
        n = len(p)
        hcov = np.zeros((n, 3))
        hcov[:, 0] = v
        hcov[:, 2] = v
        return np.full(n, v), hcov


class _Quadratic(VarianceModel):
    name = "quadratic"
    source = ("leggedrobotics/elevation_mapping_cupy: variance = sensor_noise_factor * z^2, z in the sensor frame "
              "(custom_kernels.py, elevation_mapping.py add_noise; core_param.yaml sensor_noise_factor 0.05)")

    def _compute(self, p, T, P):
        v = self.params["factor"] * p[:, 2] ** 2
        hcov = np.zeros((len(p), 3))
        hcov[:, 0] = v
        hcov[:, 2] = v
        return v, hcov


class _AnyboticsD435(VarianceModel):
    name = "anybotics_d435"
    source = ("ANYbotics/elevation_mapping: StructuredLightSensorProcessor::computeVariances with "
              "config/sensor_processors/realsense_d435.yaml")

    def _compute(self, p, T, P):
        a, b, c = self.params["normal_factor_a"], self.params["normal_factor_b"], self.params["normal_factor_c"]
        d, e, lat = self.params["normal_factor_d"], self.params["normal_factor_e"], self.params["lateral_factor"]
        z = p[:, 2]
        sigma_n = a + b * (z - c) ** 2 + d * z ** e
        sigma_l = lat * z
        var_l, var_n = sigma_l ** 2, sigma_n ** 2
        R = T[:3, :3]
        # R diag(vl, vl, vn) R^T = vl (R_0 R_0^T + R_1 R_1^T) + vn R_2 R_2^T, R_k the k-th column of R
        Rl = R[:, :2] @ R[:, :2].T                     # (3, 3)
        Rn = np.outer(R[:, 2], R[:, 2])
        if P is None:                                  # only the entries needed: zz, xx, xy, yy
            hvar = var_l * Rl[2, 2] + var_n * Rn[2, 2]
            hcov = np.stack([var_l * Rl[0, 0] + var_n * Rn[0, 0], var_l * Rl[0, 1] + var_n * Rn[0, 1],
                             var_l * Rl[1, 1] + var_n * Rn[1, 1]], axis=1)
            return hvar, hcov
        cov = var_l[:, None, None] * Rl + var_n[:, None, None] * Rn      # (N, 3, 3), map frame
        if P is not None:
            # ANYbotics: J_q = P C_BM^T ([C_SB^T S_r_SP]_x + [B_r_BS]_x), the lever arm from the base
            # origin, on the base's rotation covariance. Our pose covariance is the camera's, its rotation
            # a map-frame rotation vector about the camera centre (the base rotation's swing of the camera
            # is already in its translation block, see noise_model.sim.walks.camera_pose_cov), so the same
            # term is J = -[R p_cam]_x on pose_cov[3:, 3:]. The translation block is left out, as
            # ANYbotics does (it enters the map as process noise in the motion update).
            S = skew(p @ R.T)                          # (N, 3, 3), [q]_x with q = R p_cam
            cov += np.einsum("nij,jk,nlk->nil", S, P[3:, 3:], S)
        hcov = np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]], axis=1)
        return cov[:, 2, 2].copy(), hcov


def constant(sigma_m: float = 0.02) -> VarianceModel:
    """One isotropic sigma for every point: Sigma = sigma_m^2 I in the map frame.

    Parameters
    ----------
    sigma_m : float
        Point standard deviation [m] (default 0.02: a simple baseline), in (0, 10].

    Returns
    -------
    VarianceModel
        ``f(points_cam, T_map_cam, pose_cov) -> (height_var, horizontal_cov)``; the pose covariance is
        ignored.

    Examples
    --------
    >>> hv, hc = constant(0.02)(np.array([[0.0, 0.0, 1.0]]), np.eye(4), None)
    >>> float(hv[0])
    0.0004
    """
    s = check_positive_scalar(sigma_m, "sigma_m", upper=10.0, unit=" m")
    return _Constant({"sigma_m": s})


def quadratic(factor: float = 0.05) -> VarianceModel:
    """elevation_mapping_cupy's point noise: variance = factor * z^2, z the depth in the sensor frame.

    As elevation_mapping_cupy does, the value is used directly as the point's height variance (it is not
    projected onto the map's z axis: issue #93 of that repository) and the pose covariance is not
    propagated. Its horizontal covariance, which elevation_mapping_cupy does not have, is taken isotropic
    with the same variance.

    Parameters
    ----------
    factor : float
        ``sensor_noise_factor``, dimensionless (variance [m^2] per squared depth [m^2]; default 0.05, the value of
        elevation_mapping_cupy's ``config/core/core_param.yaml``), in (0, 10].

    Returns
    -------
    VarianceModel

    Examples
    --------
    >>> hv, hc = quadratic()(np.array([[0.0, 0.0, 2.0]]), np.eye(4), None)
    >>> float(hv[0])
    0.2
    """
    f = check_positive_scalar(factor, "factor", upper=10.0)
    return _Quadratic({"factor": f})


def anybotics_d435(normal_factor_a: float = ANYBOTICS_D435["normal_factor_a"],
                   normal_factor_b: float = ANYBOTICS_D435["normal_factor_b"],
                   normal_factor_c: float = ANYBOTICS_D435["normal_factor_c"],
                   lateral_factor: float = ANYBOTICS_D435["lateral_factor"],
                   normal_factor_d: float = ANYBOTICS_D435["normal_factor_d"],
                   normal_factor_e: float = ANYBOTICS_D435["normal_factor_e"]) -> VarianceModel:
    """ANYbotics' structured-light sensor model with its D435 preset.

    With z the point's depth (its z in the sensor frame):

    * sigma_N = a + b (z - c)^2 + d z^e along the sensor z axis (ANYbotics' "normal direction"),
    * sigma_L = lateral_factor z along the sensor x and y axes,
    * Sigma_S = diag(sigma_L^2, sigma_L^2, sigma_N^2) in the sensor frame; map frame R Sigma_S R^T, so
      the height variance is J_s Sigma_S J_s^T with J_s = e_z^T R (ANYbotics' P C_BM^T C_SB^T);
    * with a pose covariance, plus J_q Sigma_q J_q^T: J_q = -e_z^T [R p_cam]_x on the rotation block
      ``pose_cov[3:, 3:]`` (ANYbotics' J_q = P C_BM^T ([C_SB^T S_r_SP]_x + [B_r_BS]_x) expressed in this
      package's convention: rotation error of the camera pose in the map frame about the camera
      centre; the sign does not matter in the quadratic form). The horizontal covariance gets the
      same two terms' x/y block.

    ANYbotics' cut-offs (0.2-3.25 m) are not applied: a variance model cannot drop points, and all
    mappers of a comparison see the same points.

    Parameters
    ----------
    normal_factor_a, normal_factor_b, normal_factor_c : float
        a [m], b [1/m], c [m] (preset 0.000611, 0.003587, 0.3515).
    lateral_factor : float
        [m/m] (preset 0.01576).
    normal_factor_d, normal_factor_e : float
        The power term d z^e (preset d = 0: off).

    Returns
    -------
    VarianceModel

    Examples
    --------
    A camera looking straight down (camera z = map -z), a point at depth 1 m:
    sigma_N = 0.000611 + 0.003587 * 0.6485^2 = 0.0021195 m, height variance sigma_N^2.

    >>> T = np.diag([1.0, -1.0, -1.0, 1.0])
    >>> hv, hc = anybotics_d435()(np.array([[0.0, 0.0, 1.0]]), T, None)
    >>> round(float(hv[0]), 10)
    4.4924e-06
    """
    vals = {}
    for key, v in (("normal_factor_a", normal_factor_a), ("normal_factor_b", normal_factor_b),
                   ("normal_factor_c", normal_factor_c), ("lateral_factor", lateral_factor),
                   ("normal_factor_d", normal_factor_d), ("normal_factor_e", normal_factor_e)):
        try:
            x = float(v)
        except (TypeError, ValueError):
            raise ValueError(f"{key} must be a number, got {v!r}") from None
        if not np.isfinite(x) or x < 0 or x > 100:
            raise ValueError(f"{key} must be finite and in [0, 100], got {v!r}")
        vals[key] = x
    if vals["normal_factor_a"] <= 0:
        raise ValueError("normal_factor_a must be > 0 (sigma_N must stay positive)")
    if vals["lateral_factor"] <= 0:
        raise ValueError("lateral_factor must be > 0")
    return _AnyboticsD435(vals)


#: Factories by name (the names ``elevmap compare`` uses).
VARIANCE_MODELS = {"constant": constant, "quadratic": quadratic, "anybotics_d435": anybotics_d435}


def make_variance_model(name: str, **params) -> VarianceModel:
    """A model of :data:`VARIANCE_MODELS` by name, with keyword overrides of its defaults.

    Raises
    ------
    ValueError
        Unknown name or parameter, or a bad value.
    """
    return build_from_registry(VARIANCE_MODELS, "variance model", name, params)
