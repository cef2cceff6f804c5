"""The validation tools of the physical D435: planar scenes, the pointing jitter, the emergent statistics,
and (with the genuine recordings) the figures against real D435 data."""

import json

import numpy as np
import pytest

from noise_model.analysis.capture_data import CaptureData
from noise_model.analysis.diagnosis import selftest_geometries
from noise_model.sim.stereo import emergent as E
from noise_model.sim.stereo import imagers as I
from noise_model.sim.stereo import planar as PL
from noise_model.sim.stereo import realdata as RD
from noise_model.sim.stereo import validation as V
from noise_model.sim.stereo.pipeline import StereoD435
from noise_model.sim.targets import target_rotation


def scene_of(g):
    """The capture geometry's target as planar surfaces in its camera frame (the capture-set convention)."""
    t = g.target
    R = target_rotation(t["yaw_deg"], t["pitch_deg"])
    c = (0.0, 0.0, t["distance_m"])
    if t["kind"] == "wall":
        surfaces = [PL.PlaneSurface(tuple(R[:, 2]), c)]
    else:
        surfaces = [PL.PlaneSurface(tuple(R[:, 2]), c, t["width_m"], t["height_m"], tuple(R[:, 0]))]
    if g.background_m is not None:
        surfaces.append(PL.PlaneSurface((0.0, 0.0, 1.0), (0.0, 0.0, g.background_m)))
    return PL.PlanarScene(tuple(surfaces))


# ---------------------------------------------------------------------------------------------
# planar scenes
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["wall", "board"])
def test_planar_render_equals_the_capture_geometry(kind):
    for g in selftest_geometries(kind)[::3]:
        z0, t0 = g.render()
        z1, t1 = PL.render_planar(scene_of(g), g.K, g.width, g.height, np.eye(4), max_range_m=1e9)
        np.testing.assert_array_equal(np.isfinite(z0), np.isfinite(z1))
        np.testing.assert_allclose(z1, z0, rtol=1e-12, equal_nan=True)
        np.testing.assert_allclose(t1, t0, atol=1e-12, equal_nan=True)


def test_planar_corner_nearest_hit_pose_and_index():
    """A floor and a wall meeting at a concave corner, seen from a posed camera: each pixel sees the nearer."""
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    floor = PL.PlaneSurface((0, 0, 1), (0, 0, 0), name="floor")
    wall = PL.PlaneSurface((-1, 0, 0), (2.0, 0, 0), name="wall")
    T = np.eye(4)
    T[:3, :3] = np.column_stack([(0, -1, 0), (0, 0, -1), (1, 0, 0)])     # level, looking along map +x
    T[:3, 3] = (0, 0, 0.5)
    z, th, idx = PL.render_planar(PL.PlanarScene((floor, wall)), K, 64, 48, T, return_index=True)
    assert set(np.unique(idx)) == {0, 1}
    assert np.allclose(z[idx == 1], 2.0)                         # the wall, 2 m ahead, head-on
    assert np.allclose(th[idx == 1], 0.0) and np.allclose(th[idx == 0], np.pi / 2)
    v = np.arange(48)[:, None] * np.ones((1, 64))
    below = idx == 0
    np.testing.assert_allclose(z[below], 0.5 * 50.0 / (v[below] - 23.5))    # floor: z = h f / (v - cy)
    assert np.all(z[below] <= 2.0 + 1e-9)                         # the floor ends at the corner
    # a plane in the camera frame, moved into the map by the pose
    p = PL.plane_from_camera((0, 0, -1), -2.0, T, name="p")
    np.testing.assert_allclose(p.normal, (-1, 0, 0), atol=1e-12)
    assert np.isclose(np.dot(p.normal, p.point_m), -2.0)


def test_planar_bad_input():
    with pytest.raises(ValueError, match="normal"):
        PL.PlaneSurface((0, 0, 0), (0, 0, 1))
    with pytest.raises(ValueError, match="width_m and height_m"):
        PL.PlaneSurface((0, 0, 1), (0, 0, 1), width_m=1.0)
    with pytest.raises(ValueError, match="height_m"):
        PL.PlaneSurface((0, 0, 1), (0, 0, 1), width_m=1.0, height_m=-1.0)
    with pytest.raises(ValueError, match="parallel"):
        PL.PlaneSurface((0, 0, 1), (0, 0, 1), 1.0, 1.0, u_axis=(0, 0, 2))
    with pytest.raises(ValueError, match="at least one"):
        PL.PlanarScene(())
    with pytest.raises(ValueError, match="PlanarScene"):
        PL.render_planar([], np.eye(3), 4, 4, np.eye(4))


def test_a_planar_scene_with_no_hit_is_a_value_error():
    cam = StereoD435(424, 240, renderer=PL.render_planar)
    behind = PL.PlanarScene((PL.PlaneSurface((0, 0, 1), (0, 0, -1.0)),))
    with pytest.raises(ValueError, match="no surface"):
        cam.render(behind, np.eye(4))


# ---------------------------------------------------------------------------------------------
# pointing jitter
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dx", [0.0, 0.013, -0.4, 1.75, -30.0])
def test_shift_columns_matches_reference(rng, dx):
    a = rng.uniform(0, 1e4, size=(7, 23))
    np.testing.assert_allclose(I.shift_columns(a, dx), I.shift_columns_reference(a, dx), rtol=1e-13, atol=1e-9)
    if dx == 0.0:
        np.testing.assert_allclose(I.shift_columns(a, dx), a, rtol=1e-14)
    if dx == 1.75:
        np.testing.assert_allclose(I.shift_columns(a, dx)[:, 5], 0.75 * a[:, 3] + 0.25 * a[:, 4])   # a(5 - 1.75)
    with pytest.raises(ValueError, match="2-D"):
        I.shift_columns(a[0], dx)


def test_expose_moves_the_image_by_the_drawn_pointing_angle(rng):
    """The jitter is the generator's first draw; the image is the noise of the shifted rates."""
    m = I.ImagerModel(read_noise_e=0.0, pointing_jitter_rad=2e-3)
    rate = np.tile(np.linspace(1e4, 5e4, 40), (6, 1))
    ex = I.Exposure(0.01, 1.0)
    got = I.expose(np.zeros_like(rate), rate, ex, np.random.default_rng(5), m, focal_px=400.0)
    g = np.random.default_rng(5)
    dx = g.normal(0.0, 2e-3) * 400.0
    electrons = g.poisson(I.shift_columns(rate, dx) * ex.time_s).astype(float)
    want = (np.clip(np.floor(electrons / m.electrons_per_dn() + m.black_level_dn + 0.5), 0, 1023)
            .astype(np.uint16) // 4).astype(np.uint8)
    np.testing.assert_array_equal(got, want)
    none = I.expose(np.zeros_like(rate), rate, ex, np.random.default_rng(5), m)         # no focal: no jitter
    g = np.random.default_rng(5)
    assert np.array_equal(none, (np.clip(np.floor(g.poisson(rate * ex.time_s) / m.electrons_per_dn()
                                                  + m.black_level_dn + 0.5), 0, 1023).astype(np.uint16) // 4))
    with pytest.raises(ValueError, match="pointing_jitter_rad"):
        I.ImagerModel(pointing_jitter_rad=-1e-5)


def test_pointing_jitter_moves_the_whole_frame():
    """The per-frame mean disparity of a wall scatters more with the jitter than without it."""
    from noise_model.sim.stereo.validation import _level_camera, wall_scene

    def offsets(jitter):
        cam = StereoD435(424, 240, imager=I.ImagerModel(pointing_jitter_rad=jitter))
        ir = cam.render(wall_scene(1.0), _level_camera())
        rng = np.random.default_rng(11)
        fb = cam.focal_px * cam.baseline_m
        out = []
        for _ in range(6):
            d = cam.frame(ir, rng).depth.astype(float)
            out.append(np.mean(fb / (d[d > 0] * 1e-3)))
        return np.std(out, ddof=1)

    assert offsets(4e-4) > 3 * offsets(0.0)


# ---------------------------------------------------------------------------------------------
# emergent statistics
# ---------------------------------------------------------------------------------------------


def test_static_part_recovers_a_known_static_share(rng):
    g = selftest_geometries("wall")[0]
    z0, _ = g.render()
    fb = g.fb_px_m
    F = 40
    static = rng.normal(0, 0.03, z0.shape)
    d = fb / z0 + static + rng.normal(0, 0.06, (F,) + z0.shape) + 0.2       # a disparity offset is a plane
    c = CaptureData(g, fb / d)
    s = E.static_part(c, np.isfinite(z0))
    assert s["temporal_sigma_d_px"] == pytest.approx(0.06, rel=0.03)
    assert s["static_sigma_d_px"] == pytest.approx(0.03, rel=0.1)
    assert s["static_ratio"] == pytest.approx(0.5, rel=0.1)
    one = E.static_part(CaptureData(g, c.depth_m[:1]), np.isfinite(z0))
    assert np.isnan(one["static_ratio"])


def test_capture_statistics_of_a_simulated_wall():
    geoms = E.design(walls=[(1.5, 0)], boards=())
    data = E.simulate(geoms, n_frames=4, seed=3)
    again = E.simulate(geoms, n_frames=4, seed=3)
    np.testing.assert_array_equal(data[0].depth_m, again[0].depth_m)          # seeded
    (row,) = E.capture_statistics(data)
    assert row["id"] == "wall_z1.50_y00" and row["frames"] == 4
    assert row["fill_rate"] > 0.95
    assert 0.8 < row["lattice"] <= 1.0            # the 1/32-px lattice: one step is 3.3 mm at 1.5 m, 3 depth units
    assert 0.02 < row["temporal_sigma_d_px"] < 0.1
    assert 1.0 < row["corr_length_px"] < 5.0                         # correlated over the matching window


def test_validation_wall_sweep_and_command_line(tmp_path):
    (r,) = V.wall_sweep(distances=(1.0,), n_frames=3, width=424, height=240)
    assert abs(r["band_px"] - r["band_expected_px"]) <= V.TARGET_BAND_PX
    assert V.TARGET_SIGMA_D_PX[0] / 2 < r["temporal_sigma_d_px"] < V.TARGET_SIGMA_D_PX[1]
    assert r["nearest_m"] >= r["nearest_allowed_m"]
    with pytest.raises(ValueError, match="no such folder"):
        V.main(["--realdata", str(tmp_path / "absent"), "--no-speed", "--no-emergent"])


# ---------------------------------------------------------------------------------------------
# against the genuine recordings
# ---------------------------------------------------------------------------------------------


def test_ambient_for_exposure():
    scene = PL.PlanarScene((PL.PlaneSurface((0, 0, -1), (0, 0, 1.5)),))
    unit = StereoD435(424, 240, renderer=PL.render_planar, ambient_w_m2=1.0)
    a = RD.ambient_for_exposure(unit, unit.render(scene, np.eye(4)), 0.004)
    cam = StereoD435(424, 240, renderer=PL.render_planar, ambient_w_m2=a)
    ex = I.auto_exposure(cam.render(scene, np.eye(4)).rate_left, cam.imager)
    assert ex.time_s == pytest.approx(0.004, rel=1e-9) and ex.gain == 1.0
    assert RD.ambient_for_exposure(unit, unit.render(scene, np.eye(4)), 10.0) == 0.0    # the dots alone suffice


@pytest.mark.realdata
def test_aims_scene_has_the_recorded_geometry(realdata):
    fig = json.loads((realdata / "aims_slam_d435_robot_floor" / "figures.json").read_text())
    scene, T, K = RD.aims_scene(fig)
    z, _, idx = PL.render_planar(scene, K, 640, 480, T, return_index=True)
    floor, wall = fig["S1_floor"], fig["S1_wall"]
    for key, code in (("S1_floor", 0), ("S1_wall", 1)):
        x0, y0, x1, y1 = fig[key]["roi_xyxy"]
        assert (idx[y0:y1, x0:x1] == code).mean() > 0.97           # each ROI sees its own plane
    assert T[2, 3] == pytest.approx(floor["plane"]["dist_m"])
    n_floor_cam = T[:3, :3].T @ np.array([0, 0, 1.0])
    np.testing.assert_allclose(n_floor_cam, np.array(floor["plane"]["normal"]) / np.linalg.norm(
        floor["plane"]["normal"]), atol=1e-9)
    lo, hi = wall["plane"]["depth_range_inliers_m"]
    x0, y0, x1, y1 = wall["roi_xyxy"]
    zw = z[y0:y1, x0:x1]
    assert lo - 0.05 < np.nanmin(zw) and np.nanmax(zw) < hi + 0.1


@pytest.mark.realdata
def test_aims_real_offsets_have_a_frame_wide_part(realdata):
    o = RD.aims_real_offsets(realdata / "aims_slam_d435_robot_floor")
    assert len(o["wall"]["offsets_px"]) == 16
    assert o["wall"]["std_inner_px"] < o["wall"]["std_px"]          # the end frames dominate
    assert o["correlation_inner"] > 0.3 and 0.004 < o["shared_inner_px"] < 0.02


@pytest.mark.realdata
def test_single_plane_against_the_opf_board(realdata):
    r = RD.single_plane(realdata, "opf_board", n_frames=1)
    assert 1 / V.TARGET_PLANE_FACTOR <= r["ratio"] <= V.TARGET_PLANE_FACTOR
    assert r["valid_fraction_roi"] > 0.8


@pytest.mark.realdata
def test_simulated_dots_match_the_real_carpet(realdata):
    left = RD.read_png(realdata / "simsense_d435_ir_pairs" / "left1.png")
    sim = RD.simulated_dots()
    for k in RD.FLOOR_PATCHES:
        real = RD.dot_statistics(left, RD.DOT_PATCHES[k])
        assert abs(sim[k]["dots_per_100x100"] / real["dots_per_100x100"] - 1) <= V.TARGET_DOTS_REL
