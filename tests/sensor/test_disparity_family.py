"""The disparity noise family: sigma_z = z^2 (s0 + s1 theta^2) / (f B), its kernel against its NumPy reference,
its model file and the mapper running on it."""

import json
import math

import numpy as np
import pytest
from numba import njit

from conftest import random_pose_cov, random_transform
from noise_model import D435, SensorModel, axial_sigma, axial_variance, depth_to_map_points
from noise_model import depth_to_map_points_reference, expected_rms_error, point_covariances
from noise_model.formulas import disparity_angle_gain, disparity_expected_sigma_z_sq, disparity_sigma_z_from_gain
from noise_model.numba_config import JIT

from test_kernels import assert_same, hostile_depth

DISP = D435.with_disparity(0.05, 0.03)


def test_sigma_z_is_intels_depth_resolution_formula_at_the_frames_focal_length():
    # s0 = 0.08 px, theta = 0: e = z^2 s / (f B), the paper's equation (1) (f = 424 px at 848 wide)
    m = D435.with_disparity(0.08)
    assert axial_sigma(1.0, 0.0, m, fx_px=424.0) == pytest.approx(expected_rms_error(1.0), rel=1e-12)
    # by hand: z = 2 m, theta = 0.5 rad, s0 = 0.05, s1 = 0.03, f = 383.8 px, B = 0.05 m
    want = 4.0 * (0.05 + 0.03 * 0.25) / (383.8 * 0.05)
    assert axial_sigma(2.0, 0.5, DISP, fx_px=383.8) == pytest.approx(want, rel=1e-14)
    # half the focal length (424x240 against 848x480): twice the depth noise per pixel of disparity
    assert axial_sigma(2.0, 0.5, DISP, fx_px=212.0) == pytest.approx(2 * axial_sigma(2.0, 0.5, DISP, fx_px=424.0))
    # the angle is capped at theta_max and its sign ignored, as in the paper's family
    assert axial_sigma(1.0, -1.5, DISP, fx_px=424.0) == axial_sigma(1.0, DISP.theta_max_rad, DISP, fx_px=424.0)
    # bound to a frame, no fx needed
    assert axial_sigma(2.0, 0.5, DISP.with_focal(383.8)) == pytest.approx(want, rel=1e-14)


def test_the_paper_family_stays_the_default_and_ignores_the_focal_length():
    assert D435.family == "paper" and SensorModel().family == "paper"
    assert axial_sigma(1.0, 0.3, D435, fx_px=100.0) == axial_sigma(1.0, 0.3)
    assert D435.params_array()[7] == 0.0 and list(D435.params_array()[:4]) == list(D435.axial_coefficients)


def test_bad_disparity_models_and_missing_focal_lengths_are_clear_errors():
    with pytest.raises(ValueError, match="focal length"):
        axial_sigma(1.0, 0.0, DISP)
    with pytest.raises(ValueError, match="fx"):
        point_covariances(np.array([[0.0, 0.0, 1.0]]), np.zeros(1), model=DISP)
    for bad in ((0.0, 0.0), (-0.1, 0.0), (0.08, -0.01), (0.08, float("nan")), (0.08,), ("a", 0.0)):
        with pytest.raises(ValueError, match="disparity_sigma_px"):
            SensorModel(family="disparity", disparity_sigma_px=bad)
    with pytest.raises(ValueError, match="family"):
        SensorModel(family="quadratic")
    with pytest.raises(ValueError, match="fx_px"):
        axial_sigma(1.0, 0.0, DISP, fx_px=-3.0)


def test_expected_variance_over_an_uncertain_angle_against_a_dense_integral():
    f = 424.0
    assert axial_variance(1.5, 0.9, 0.0, DISP, fx_px=f) == pytest.approx(axial_sigma(1.5, 0.9, DISP, fx_px=f) ** 2,
                                                                          rel=1e-12)
    for th in np.linspace(0.0, 1.5, 16):
        for s in (0.01, 0.05, 0.2):
            t = np.linspace(th - 8 * s, th + 8 * s, 20001)
            w = np.exp(-0.5 * ((t - th) / s) ** 2)
            dense = np.sum(w * axial_sigma(2.0, t, DISP, fx_px=f) ** 2) / np.sum(w)
            smooth = th - 4 * s > 0 and th + 4 * s < DISP.theta_max_rad
            assert axial_variance(2.0, th, s, DISP, fx_px=f) == pytest.approx(dense, rel=0.01 if smooth else 0.06)


def test_compiled_disparity_formulas_equal_the_numpy_ones():
    rng = np.random.default_rng(3)
    comp = {f: njit(**JIT)(f) for f in (disparity_angle_gain, disparity_sigma_z_from_gain,
                                        disparity_expected_sigma_z_sq)}
    for z, t, c, g1 in zip(rng.uniform(0.2, 8, 40), rng.uniform(0, 1.4, 40), rng.uniform(1e-4, 1e-2, 40),
                           rng.uniform(0, 1e-2, 40)):
        g = disparity_angle_gain(t, g1)
        for f, args in ((disparity_angle_gain, (t, g1)), (disparity_sigma_z_from_gain, (z, g, c)),
                        (disparity_expected_sigma_z_sq, (z, g, g * g + 1e-6, c))):
            assert comp[f](*args) == pytest.approx(f(*args), rel=1e-14, abs=0.0)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_kernel_equals_reference_for_the_disparity_family(seed, dtype):
    """Random depths with holes, NaN, inf, negative values and a near box, image sizes that are no multiple
    of the block size, with and without pose covariance, 1 and 2 threads."""
    rng = np.random.default_rng(seed)
    H, W = 97, 131
    d, scale = hostile_depth(rng, H, W, dtype)
    K = D435.intrinsics(848, 480) * np.array([[W / 848], [H / 480], [1.0]])
    T = random_transform(rng)
    P = random_pose_cov(rng) if seed else None
    one = depth_to_map_points(d, K, T, P, depth_scale=scale, model=DISP, nthreads=1)
    two = depth_to_map_points(d, K, T, P, depth_scale=scale, model=DISP, nthreads=2)
    for x, y in zip(one, two):
        np.testing.assert_array_equal(x, y)
    ref = depth_to_map_points_reference(d, K, T, P, depth_scale=scale, model=DISP)
    assert_same(one, ref)
    assert np.all(np.isfinite(one.height_var)) and np.all(one.height_var > 0)
    # the family matters: the paper's model gives other variances on the same frame
    paper = depth_to_map_points(d, K, T, P, depth_scale=scale)
    np.testing.assert_array_equal(paper.pixel, one.pixel)
    assert not np.allclose(paper.height_var, one.height_var)


@pytest.mark.parametrize("shape", [(1, 1), (3, 2), (9, 17)])
def test_kernel_equals_reference_on_tiny_images(shape):
    rng = np.random.default_rng(7)
    z = rng.uniform(0.5, 3.0, shape)
    K = np.array([[50.0, 0, shape[1] / 2], [0, 50.0, shape[0] / 2], [0, 0, 1]])
    assert_same(depth_to_map_points(z, K, np.eye(4), model=DISP),
                depth_to_map_points_reference(z, K, np.eye(4), model=DISP))


def test_a_wall_gets_the_disparity_variance_of_its_depth():
    """A fronto-parallel wall at 2 m with T = I: the map height is the camera z, the height variance the
    axial variance, (z^2 s0 / (f B))^2 with the frame's own focal length (theta ~ 0, so s1 barely acts)."""
    H, W = 120, 212
    K = D435.intrinsics(424, 240) * np.array([[W / 424], [H / 240], [1.0]])
    z = np.full((H, W), 2.0)
    m = D435.with_disparity(0.08)
    for impl in (depth_to_map_points, depth_to_map_points_reference):
        out = impl(z, K, np.eye(4), model=m)
        want = (4.0 * 0.08 / (K[0, 0] * 0.05)) ** 2
        assert np.median(out.height_var) == pytest.approx(want, rel=1e-9)


def test_the_mapper_runs_with_a_disparity_model():
    """elevmap.Mapper with a camera whose model is the disparity family (sigma_d = 0.08 px): a flat floor
    1 m below the camera, looking down; the map's heights are the floor's and its variances those of the
    disparity model (not the paper's), with numba and NumPy alike."""
    from elevmap import Camera, ElevationMap, Mapper

    H, W = 120, 212
    K = D435.intrinsics(424, 240) * np.array([[W / 424], [H / 240], [1.0]])
    pitch = math.radians(50.0)           # optical axis 50 deg below the horizon
    c, s = math.cos(pitch), math.sin(pitch)
    # camera x right, y down, z forward -> map x forward, y left, z up; camera 1 m above the floor
    R = np.array([[0.0, -s, c], [-1.0, 0.0, 0.0], [0.0, -c, -s]])
    T = np.eye(4)
    T[:3, :3] = R
    T[2, 3] = 1.0
    v, u = np.mgrid[0:H, 0:W]
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], axis=-1)
    down = -(ray @ R.T)[..., 2]
    z = np.where(down > 0.05, 1.0 / np.where(down > 0.05, down, 1.0), 0.0)
    z = np.where(z < 6.0, z, 0.0)
    depth = np.round(z / 0.001).astype(np.uint16)
    results = {}
    for name, model in (("disparity", D435.with_disparity(0.08)), ("paper", D435)):
        for impl in ("numba", "numpy"):
            mapper = Mapper(ElevationMap())
            mapper.add_camera(Camera("front", K, W, H, model=model))
            stats = mapper.integrate("front", depth, T_map_cam=T, impl=impl)
            assert stats["points"] > 0.5 * H * W
            results[name, impl] = mapper
    for impl in ("numba", "numpy"):
        pts = results["disparity", impl].last_points
        assert np.all(np.isfinite(pts.height_var)) and np.all(pts.height_var > 0)
        near = pts.points_map[:, 0] < 2.0
        assert np.median(np.abs(pts.points_map[near, 2])) < 1e-3
        h, var = results["disparity", impl].map.height_at(np.array([[1.5, 0.0]]))
        assert abs(float(np.ravel(h)[0])) < 0.01 and np.isfinite(np.ravel(var)[0])
    a, b = results["disparity", "numba"].last_points, results["disparity", "numpy"].last_points
    np.testing.assert_allclose(a.height_var, b.height_var, rtol=1e-6)
    assert not np.allclose(a.height_var, results["paper", "numba"].last_points.height_var, rtol=0.1)


def test_model_file_round_trip_of_both_families(tmp_path):
    disp = D435.with_disparity(0.061, 0.004, name="aims wall fit", baseline_m=0.0501)
    disp.save(tmp_path / "d.json")
    back = SensorModel.load(tmp_path / "d.json")
    assert back == disp and back.family == "disparity" and back.disparity_sigma_px == (0.061, 0.004)
    assert axial_sigma(1.3, 0.7, back, fx_px=383.8) == axial_sigma(1.3, 0.7, disp, fx_px=383.8)
    doc = json.loads((tmp_path / "d.json").read_text())
    assert doc["format"] == "elevmap-sensor-model/2" and doc["family"] == "disparity"
    assert "frame_fx_px" not in doc                       # a property of a frame, not of the camera
    # bound to a frame, it saves the camera's model only
    disp.with_focal(383.8).save(tmp_path / "bound.json")
    assert SensorModel.load(tmp_path / "bound.json") == disp
    # the paper's family writes the first format with exactly its old keys (older files read the same)
    D435.save(tmp_path / "p.json")
    doc = json.loads((tmp_path / "p.json").read_text())
    assert doc["format"] == "elevmap-sensor-model/1"
    assert set(doc) == {"format", "name", "axial_coefficients", "sigma_L", "sigma_R", "baseline_m", "subpixel",
                        "theta_max_rad", "hfov_deg"}
    assert SensorModel.load(tmp_path / "p.json") == D435


def test_corrupt_disparity_model_files_are_clear_errors(tmp_path):
    doc = D435.with_disparity(0.08).to_dict()
    for key, value, match in (("disparity_sigma_px", [0.08], "disparity_sigma_px"),
                              ("disparity_sigma_px", [-0.08, 0.0], "disparity_sigma_px"),
                              ("family", "cubic", "family"),
                              ("baseline_m", 0.0, "baseline_m")):
        bad = dict(doc, **{key: value})
        (tmp_path / "bad.json").write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=match) as err:
            SensorModel.load(tmp_path / "bad.json")
        assert "bad.json" in str(err.value)
    bad = dict(doc)
    del bad["family"]
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="missing or has a bad key"):
        SensorModel.load(tmp_path / "bad.json")
