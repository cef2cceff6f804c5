"""Monte Carlo checks of the per-point covariances, and their input validation."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import random_pose_cov, random_transform
from noise_model import D435, axial_sigma, point_covariances, pose_jacobian, to_map_frame

N_SAMPLES = 400_000
FX, FY, CX, CY = 424.0, 424.0, 423.5, 239.5


def _assert_cov_close(sample, model, rel=0.03):
    """Elementwise agreement, scaled by sqrt(C_ii C_jj) so that off-diagonal terms are judged fairly."""
    d = np.sqrt(np.diag(model))
    scaled = np.abs(sample - model) / np.outer(d, d)
    assert scaled.max() < rel, f"max scaled error {scaled.max():.4f}\nsample\n{sample}\nmodel\n{model}"


def _sample_pixel_points(rng, u, v, z, sigma_z, sigma_x_m=None):
    """Noisy deprojection: depth error along z, pixel position uniform over the pixel (or an edge shift)."""
    dz = rng.normal(0.0, sigma_z, N_SAMPLES)
    du = rng.uniform(-0.5, 0.5, N_SAMPLES)
    dv = rng.uniform(-0.5, 0.5, N_SAMPLES)
    zz = z + dz
    x = (u + du - CX) / FX * zz
    if sigma_x_m is not None:                         # lateral error across a vertical edge, in metres
        x = (u - CX) / FX * zz + rng.normal(0.0, sigma_x_m, N_SAMPLES)
    y = (v + dv - CY) / FY * zz
    return np.stack([x, y, zz], axis=1)


@pytest.mark.parametrize("u, v, z, theta_deg", [(423.5, 239.5, 1.0, 0.0), (50.0, 400.0, 2.0, 30.0),
                                                 (800.0, 20.0, 0.6, 60.0), (700.0, 300.0, 3.0, 10.0)])
def test_interior_pixel_covariance_matches_monte_carlo(rng, u, v, z, theta_deg):
    theta = math.radians(theta_deg)
    samples = _sample_pixel_points(rng, u, v, z, axial_sigma(z, theta))
    p = np.array([[(u - CX) / FX * z, (v - CY) / FY * z, z]])
    C = point_covariances(p, [theta], fx=FX, fy=FY)[0]
    _assert_cov_close(np.cov(samples.T), C)


def test_axial_noise_lies_along_the_viewing_ray(rng):
    # an off-centre pixel: the depth error couples x and z (it is not a variance on camera z alone)
    u, v, z = 50.0, 400.0, 2.0
    C = point_covariances(np.array([[(u - CX) / FX * z, (v - CY) / FY * z, z]]), [0.0], fx=FX, fy=FY)[0]
    r = np.array([(u - CX) / FX, (v - CY) / FY, 1.0])
    s2 = axial_sigma(z, 0.0) ** 2
    np.testing.assert_allclose(C[0, 2], s2 * r[0])
    np.testing.assert_allclose(C[1, 2], s2 * r[1])
    assert C[0, 2] < 0 and C[1, 2] > 0


@pytest.mark.parametrize("side", ["left", "right"])
def test_edge_pixel_covariance_matches_monte_carlo(rng, side):
    u, v, z, theta = 600.0, 100.0, 1.2, 0.0
    sigma_lat = D435.sigma_L if side == "left" else D435.sigma_R
    samples = _sample_pixel_points(rng, u, v, z, axial_sigma(z, theta), sigma_x_m=sigma_lat)
    p = np.array([[(u - CX) / FX * z, (v - CY) / FY * z, z]])
    C = point_covariances(p, [theta], [side == "left"], [side == "right"], fx=FX, fy=FY)[0]
    assert C[0, 0] == pytest.approx(sigma_lat ** 2 + axial_sigma(z, 0) ** 2 * ((u - CX) / FX) ** 2)
    _assert_cov_close(np.cov(samples.T), C)


def test_interior_lateral_term_is_the_pixel_footprint():
    z = 2.0
    C = point_covariances(np.array([[0.0, 0.0, z]]), [0.0], fx=FX, fy=FY)[0]
    assert math.sqrt(C[0, 0]) == pytest.approx(z / (FX * math.sqrt(12)))       # 1.36 mm at 2 m
    assert math.sqrt(C[2, 2]) == pytest.approx(axial_sigma(z, 0.0))


def test_map_frame_covariance_with_pose_uncertainty_matches_monte_carlo(rng):
    T = random_transform(rng)
    P = random_pose_cov(rng, sigma_t=0.02, sigma_r=0.01)
    p_cam = np.array([0.4, -0.2, 1.8])
    C_cam = point_covariances(p_cam[None], [math.radians(20)], fx=FX, fy=FY)[0]
    C_map = to_map_frame(C_cam[None], p_cam[None], T, P)[0]

    dp = rng.multivariate_normal(np.zeros(3), C_cam, N_SAMPLES)
    xi = rng.multivariate_normal(np.zeros(6), P, N_SAMPLES)
    R_err = Rotation.from_rotvec(xi[:, 3:]).as_matrix()              # rotation error in the map frame
    q = (p_cam + dp) @ T[:3, :3].T                                     # about the camera centre
    samples = np.einsum("nij,nj->ni", R_err, q) + T[:3, 3] + xi[:, :3]
    _assert_cov_close(np.cov(samples.T), C_map)


def test_map_frame_rotation_only(rng):
    T = random_transform(rng)
    C = point_covariances(np.array([[0.1, 0.2, 1.5]]), [0.3], fx=FX, fy=FY)
    out = to_map_frame(C, np.array([[0.1, 0.2, 1.5]]), T)
    np.testing.assert_allclose(out[0], T[:3, :3] @ C[0] @ T[:3, :3].T)
    np.testing.assert_allclose(np.linalg.eigvalsh(out[0]), np.linalg.eigvalsh(C[0]))


def test_pose_jacobian_matches_finite_differences(rng):
    T = random_transform(rng)
    p = np.array([[0.3, -0.4, 2.0]])
    J = pose_jacobian(p, T)[0]
    eps = 1e-7
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = eps
        R = Rotation.from_rotvec(xi[3:]).as_matrix() @ T[:3, :3]
        moved = R @ p[0] + T[:3, 3] + xi[:3]
        np.testing.assert_allclose((moved - (T[:3, :3] @ p[0] + T[:3, 3])) / eps, J[:, k], atol=1e-6)


def test_bad_inputs_name_what_is_wrong(rng):
    p = np.array([[0.0, 0.0, 1.0]])
    C = point_covariances(p, [0.0])
    T = np.eye(4)
    with pytest.raises(ValueError, match=r"points_cam must have shape \(N, 3\)"):
        point_covariances(np.ones((3, 2)), [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="non-finite"):
        point_covariances(np.array([[0.0, np.nan, 1.0]]), [0.0])
    with pytest.raises(ValueError, match="z > 0"):
        point_covariances(np.array([[0.0, 0.0, -1.0]]), [0.0])
    with pytest.raises(ValueError, match=r"theta must have shape \(1,\)"):
        point_covariances(p, [0.0, 0.1])
    with pytest.raises(ValueError, match="edge_left must be a boolean"):
        point_covariances(p, [0.0], edge_left=np.array([1]))
    bad_T = np.eye(4)
    bad_T[0, 0] = 2.0
    with pytest.raises(ValueError, match="T_map_cam rotation part is not orthonormal"):
        to_map_frame(C, p, bad_T)
    refl = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="reflection"):
        to_map_frame(C, p, refl)
    with pytest.raises(ValueError, match="4x4"):
        to_map_frame(C, p, np.eye(3))
    P = random_pose_cov(rng)
    P_asym = P.copy()
    P_asym[0, 1] += 1e-3
    with pytest.raises(ValueError, match="pose_cov is not symmetric"):
        to_map_frame(C, p, T, P_asym)
    with pytest.raises(ValueError, match="pose_cov is not positive semi-definite"):
        to_map_frame(C, p, T, -np.eye(6))
    with pytest.raises(ValueError, match="6x6"):
        to_map_frame(C, p, T, np.eye(3))
    with pytest.raises(ValueError, match="non-finite"):
        to_map_frame(C, p, T, np.full((6, 6), np.nan))
    with pytest.raises(ValueError, match="2 covariances but there are 1 points"):
        to_map_frame(np.repeat(C, 2, axis=0), p, T)


def test_per_frame_checks_decide_as_the_eigen_decomposition_and_np_allclose(rng):
    from noise_model.checks import check_pose_cov, check_transform
    # pose covariances: accepted exactly when the smallest eigenvalue is >= -1e-9 of the largest entry,
    # diagonal ones (decided from the diagonal) and full ones alike
    for k in range(200):
        d = rng.uniform(-1e-3, 1e-2, 6) if k % 2 else rng.uniform(0.0, 1e-2, 6)
        Q = Rotation.random(random_state=k).as_matrix()
        C = np.diag(d) if k % 4 < 2 else np.kron(np.eye(2), Q) @ np.diag(d) @ np.kron(np.eye(2), Q).T
        C = 0.5 * (C + C.T)
        psd = np.linalg.eigvalsh(C).min() >= -1e-9 * np.abs(C).max()
        if psd:
            np.testing.assert_array_equal(check_pose_cov(C), C)
        else:
            with pytest.raises(ValueError, match="pose_cov is not positive semi-definite"):
                check_pose_cov(C)
    np.testing.assert_array_equal(check_pose_cov(np.zeros((6, 6))), np.zeros((6, 6)))
    C = np.diag([1e-4] * 6)
    C[5, 0] = C[0, 5] = 2e-4                 # one off-diagonal pair: eigenvalues 1e-4 +- 2e-4
    with pytest.raises(ValueError, match=r"smallest eigenvalue -1.000e-04"):
        check_pose_cov(C)
    with pytest.raises(ValueError, match="non-finite"):
        check_pose_cov(np.diag([1.0, 1.0, 1.0, 1.0, 1.0, np.inf]))
    # transforms: max |R R^T - I| against the 1e-6 tolerance, det, the bottom row as np.allclose
    for k in range(50):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=k).as_matrix()
        T[:3, 3] = rng.normal(size=3)
        np.testing.assert_array_equal(check_transform(T), T)
        E = T.copy()
        E[:3, :3] *= 1.0 + 2e-6 * (k + 1)
        with pytest.raises(ValueError, match="not orthonormal"):
            check_transform(E)
    T = np.eye(4)
    T[3, 3] = 1.0 + 1e-5                      # within np.allclose's relative part
    check_transform(T)
    T[3, 3] = 1.0 + 2e-5
    with pytest.raises(ValueError, match=r"bottom row must be \[0, 0, 0, 1\]"):
        check_transform(T)
    T = np.eye(4)
    T[3, 0] = 2e-6
    with pytest.raises(ValueError, match="bottom row"):
        check_transform(T)
    T = np.eye(4)
    T[1, 3] = np.nan
    with pytest.raises(ValueError, match="T_map_cam has non-finite entries"):
        check_transform(T)
    # intrinsics: the last row as np.allclose(row, [0, 0, 1])
    from noise_model.checks import check_intrinsics
    K = np.array([[420.0, 0.0, 212.0], [0.0, 420.0, 120.0], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(check_intrinsics(K), K)
    for row, ok in (([0.0, 0.0, 1.000005], True), ([0.0, 0.0, 1.00002], False), ([1e-7, 0.0, 1.0], False),
                    ([0.0, 5e-9, 1.0], True)):
        K2 = K.copy()
        K2[2] = row
        assert np.allclose(K2[2], [0.0, 0.0, 1.0]) == ok
        if ok:
            check_intrinsics(K2)
        else:
            with pytest.raises(ValueError, match=r"K last row must be \[0, 0, 1\]"):
                check_intrinsics(K2)
    with pytest.raises(ValueError, match="K has non-finite entries"):
        check_intrinsics(np.diag([np.nan, 1.0, 1.0]))


def test_stacks_of_transforms_are_validated_naming_the_bad_one(rng):
    from noise_model import check_transforms

    good = np.stack([random_transform(rng) for _ in range(3)])
    np.testing.assert_array_equal(check_transforms(good), good)
    bad = good.copy()
    bad[2, :3, :3] *= 1.01
    with pytest.raises(ValueError, match=r"poses\[2\] is not a rigid transform"):
        check_transforms(bad)
    with pytest.raises(ValueError, match=r"shape \(N, 4, 4\)"):
        check_transforms(np.eye(4))


def test_point_covariances_with_an_uncertain_angle_use_the_expected_variance(rng):
    from noise_model import axial_variance, point_covariances

    p = np.column_stack([rng.uniform(-0.5, 0.5, 20), rng.uniform(-0.3, 0.3, 20), rng.uniform(0.5, 3.0, 20)])
    th, ts = rng.uniform(0, 1.3, 20), rng.uniform(0, 0.2, 20)
    c = point_covariances(p, th, theta_std=ts)
    c0 = point_covariances(p, th)
    r = p / p[:, 2:]
    ax = axial_variance(p[:, 2], th, ts) - axial_variance(p[:, 2], th, 0.0)
    np.testing.assert_allclose(c - c0, ax[:, None, None] * r[:, :, None] * r[:, None, :], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(point_covariances(p, th, theta_std=np.zeros(20)), c0, rtol=1e-12)
    with pytest.raises(ValueError, match="theta_std"):
        point_covariances(p, th, theta_std=np.full(19, 0.1))
