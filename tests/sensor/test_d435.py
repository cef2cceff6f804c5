"""The paper's sensor model: reference values from Ahn et al. (2019), worked by hand."""

import math

import numpy as np
import pytest

import noise_model as nm
from noise_model import D435, SensorModel, axial_sigma, expected_rms_error


def test_sigma_z_at_one_metre_fronto_parallel_is_the_papers_value():
    # 0.001063 + 0.0007278 * 1 + 0.003949 * 1 + 0 = 0.0057398 m
    assert axial_sigma(1.0, 0.0) == pytest.approx(0.0057398, abs=1e-12)


def test_sigma_z_at_two_metres_45_degrees_worked_by_hand():
    # polynomial: 0.001063 + 0.0007278*2 + 0.003949*4 = 0.0183146
    # theta term: 0.022 * 2^1.5 * (pi/4) / (pi/4)^2 = 0.022 * 2.8284271 / 0.7853982 = 0.0792278
    assert axial_sigma(2.0, math.radians(45)) == pytest.approx(0.0183146 + 0.0792278, rel=1e-6)


def test_sigma_z_at_half_a_metre_60_degrees_worked_by_hand():
    # polynomial: 0.001063 + 0.0007278*0.5 + 0.003949*0.25 = 0.00241415
    # theta term: 0.022 * 0.5^1.5 * (pi/3) / (pi/6)^2 = 0.022 * 0.3535534 * 3.8197186 = 0.0297104
    assert axial_sigma(0.5, math.radians(60)) == pytest.approx(0.00241415 + 0.0297104, rel=1e-5)


def test_equation_1_at_one_metre_for_the_848_stream():
    # f = 0.5 * 848 / tan(45 deg) = 424 px; e = 1^2 * 0.08 / (424 * 0.050) = 0.0037736 m
    assert expected_rms_error(1.0) == pytest.approx(0.0037735849, rel=1e-7)
    # quadratic in distance, inverse in resolution
    assert expected_rms_error(2.0) == pytest.approx(4 * expected_rms_error(1.0))
    assert expected_rms_error(1.0, width_px=424) == pytest.approx(2 * expected_rms_error(1.0))


def test_axial_sigma_broadcasts_and_keeps_shapes():
    z = np.linspace(0.3, 3.0, 5)[:, None]
    th = np.radians([0, 30, 60])[None, :]
    s = axial_sigma(z, th)
    assert s.shape == (5, 3)
    assert np.all(np.diff(s, axis=0) > 0) and np.all(np.diff(s, axis=1) > 0)
    assert isinstance(axial_sigma(1.0), float)


def test_theta_at_or_beyond_90_degrees_is_capped_at_80():
    capped = axial_sigma(1.0, math.radians(80))
    # 0.0057398 + 0.022 * 1.3962634 / 0.1745329^2 = 1.0141455 m
    assert capped == pytest.approx(1.0141455, rel=1e-6)
    for theta in (math.pi / 2, 2.0, math.pi):
        assert axial_sigma(1.0, theta) == capped
    assert axial_sigma(1.0, -0.5) == axial_sigma(1.0, 0.5)


@pytest.mark.parametrize("z", [0.0, -1.0, np.nan, np.inf])
def test_axial_sigma_rejects_invalid_depth(z):
    with pytest.raises(ValueError, match="z must be finite and > 0"):
        axial_sigma(z, 0.0)


def test_axial_sigma_rejects_millimetres_and_degrees():
    with pytest.raises(ValueError, match="metres"):
        axial_sigma(1500.0, 0.0)
    with pytest.raises(ValueError, match="radians"):
        axial_sigma(1.0, 45.0)


def test_default_intrinsics_follow_the_stated_fields_of_view():
    assert D435.focal_px(848, 480) == pytest.approx(424.0)
    assert D435.focal_px(1280, 720) == pytest.approx(640.0)
    assert D435.focal_px(424, 240) == pytest.approx(212.0)
    assert D435.focal_px(640, 480) == pytest.approx(384.0)
    K = D435.intrinsics(848, 480)
    np.testing.assert_allclose(K, [[424, 0, 423.5], [0, 424, 239.5], [0, 0, 1]])
    assert D435.vfov_deg(848, 480) == pytest.approx(2 * math.degrees(math.atan(240 / 424)))
    with pytest.raises(ValueError, match="no default intrinsics"):
        D435.intrinsics(320, 200)


def test_paper_constants():
    assert (D435.c0, D435.c1, D435.c2, D435.c_theta) == (0.001063, 0.0007278, 0.003949, 0.022)
    assert (D435.sigma_L, D435.sigma_R, D435.baseline_m) == (0.0432, 0.0407, 0.050)


def test_a_users_fit_round_trips_through_a_file_and_replaces_the_papers(tmp_path):
    mine = D435.with_coefficients([0.002, 0.001, 0.004, 0.03], name="my D435", sigma_L=0.05)
    path = tmp_path / "mine.json"
    mine.save(path)
    back = SensorModel.load(path)
    assert back == mine
    assert axial_sigma(1.0, 0.0, back) == pytest.approx(0.002 + 0.001 + 0.004)
    assert [p.name for p in tmp_path.iterdir()] == ["mine.json"]     # no temporary file left


def test_a_corrupt_model_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "elevmap-sensor-model/1", "name": "x"')
    with pytest.raises(ValueError, match="not valid JSON"):
        SensorModel.load(bad)
    bad.write_text('{"format": "elevmap-sensor-model/1", "name": "x"}')
    with pytest.raises(ValueError, match="missing or has a bad key"):
        SensorModel.load(bad)
    bad.write_text('{"format": "something-else"}')
    with pytest.raises(ValueError, match="not an elevmap sensor model"):
        SensorModel.load(bad)


def test_public_api_names():
    for name in ("D435", "axial_sigma", "expected_rms_error", "deproject", "incidence_angles", "depth_edges",
                 "point_covariances", "to_map_frame", "depth_to_map_points", "depth_to_map_points_reference"):
        assert hasattr(nm, name)


def test_axial_variance_is_the_expected_square_over_the_angle():
    from noise_model import axial_variance

    # no angle uncertainty: sigma_z^2
    assert axial_variance(1.5, 0.9, 0.0) == pytest.approx(axial_sigma(1.5, 0.9) ** 2, rel=1e-12)
    # against a dense integral of sigma_z(theta)^2 over N(theta_hat, s^2) (sign ignored, capped at 80 deg):
    # within 1 % where the gain is smooth over +-4 s (Gauss-Hermite), 6 % across its kinks (the grid)
    for th in np.linspace(0.0, 1.55, 32):
        for s in (0.005, 0.02, 0.05, 0.1, 0.26):
            t = np.linspace(th - 8 * s, th + 8 * s, 20001)
            w = np.exp(-0.5 * ((t - th) / s) ** 2)
            dense = np.sum(w * axial_sigma(2.0, t) ** 2) / np.sum(w)
            smooth = th - 4 * s > 0 and th + 4 * s < D435.theta_max_rad
            assert axial_variance(2.0, th, s) == pytest.approx(dense, rel=0.01 if smooth else 0.06)
    # the gain is convex in theta: an uncertain angle means more noise on average, never less
    assert axial_variance(1.0, 1.05, 0.1) > axial_sigma(1.0, 1.05) ** 2 * 1.05
    np.testing.assert_allclose(axial_variance(np.array([1.0, 2.0]), 0.5, np.array([0.0, 0.1])).shape, (2,))
    with pytest.raises(ValueError, match="theta_std"):
        axial_variance(1.0, 0.5, -0.1)
    with pytest.raises(ValueError, match="radians"):
        axial_variance(1.0, 0.5, 10.0)
