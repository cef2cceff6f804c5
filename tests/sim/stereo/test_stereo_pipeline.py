"""The physical D435 end to end at 424x240: a wall seen through the projector, imagers and matcher."""

import numpy as np
import pytest

from noise_model.sim import Scene, Target
from noise_model.sim.stereo import materials as MT
from noise_model.sim.stereo.pipeline import StereoD435
from noise_model.sim.stereo.projector import DotPattern, Projector
from noise_model.sim.targets import camera_extrinsics

T_CAM = camera_extrinsics((0.0, 0.0, 1.0), pitch_down_deg=0.0)     # looking along map +x


def wall(z):
    """A wall facing the camera at z-depth ``z`` [m], wider than the view."""
    return Scene([Target(centre=(z, 0.0, 1.0), width=8 * z + 2, height=6 * z + 2)], ground_z=None)


@pytest.fixture(scope="module")
def cam():
    return StereoD435(424, 240)


@pytest.fixture(scope="module")
def wall_1m(cam):
    return cam.render(wall(1.0), T_CAM, with_truth=True)


def test_wall_depth_band_and_determinism(cam, wall_1m):
    ir = wall_1m
    np.testing.assert_allclose(ir.z_true[np.isfinite(ir.z_true)], 1.0, atol=1e-9)
    f1 = cam.frame(ir, np.random.default_rng(7))
    f2 = cam.frame(ir, np.random.default_rng(7))
    np.testing.assert_array_equal(f1.depth, f2.depth)
    np.testing.assert_array_equal(f1.left, f2.left)
    assert f1.depth.dtype == np.uint16 and f1.left.dtype == np.uint8
    f3 = cam.frame(ir, np.random.default_rng(8))
    assert not np.array_equal(f1.left, f3.left)                 # fresh noise, the same dots
    z = f1.depth.astype(float) / 1000.0
    valid = z > 0
    assert valid.mean() > 0.8
    assert abs(np.median(z[valid]) - 1.0) < 0.01
    fB = cam.focal_px * cam.baseline_m
    band = np.median(np.argmax(valid, axis=1))
    assert abs(band - np.ceil(fB / 1.0)) <= 3                     # left band: ceil(f B / z) columns +- 3 px
    assert z[valid].min() >= fB / 126


def test_thread_count_does_not_change_frames(wall_1m):
    a = StereoD435(424, 240, nthreads=1)
    b = StereoD435(424, 240, nthreads=2)
    ia = a.render(wall(1.0), T_CAM)
    ib = b.render(wall(1.0), T_CAM)
    np.testing.assert_array_equal(ia.projector_left, ib.projector_left)
    da = a.frame(ia, np.random.default_rng(3)).depth
    np.testing.assert_array_equal(da, b.frame(ib, np.random.default_rng(3)).depth)


def test_one_material_everywhere():
    cam = StereoD435(424, 240, materials=MT.carpet())
    ir = cam.render(wall(1.0), T_CAM)
    assert np.isfinite(ir.projector_left).all() and ir.projector_left.max() > 0


def test_frames_of_a_static_camera(cam):
    d = cam.frames(wall(1.5), T_CAM, 2, 11)
    assert d.shape == (2, 240, 424) and d.dtype == np.uint16
    np.testing.assert_array_equal(d, cam.frames(wall(1.5), T_CAM, 2, 11))
    assert not np.array_equal(d[0], d[1])


def test_nothing_nearer_than_the_search_range(cam):
    near = cam.frames(wall(0.07), T_CAM, 1, 0)[0]                 # f B / 126 = 0.084 m at 424x240
    z = near[near > 0].astype(float) / 1000.0
    assert z.size == 0 or z.min() >= cam.focal_px * cam.baseline_m / 126


def test_bad_input_names_it():
    with pytest.raises(ValueError, match="no surface"):
        StereoD435(424, 240).render(Scene([], ground_z=None), T_CAM)
    with pytest.raises(ValueError, match="albedo"):
        MT.MaterialMap(default=MT.Uniform(1.3, "mirror"))
    with pytest.raises(ValueError, match="baseline_m"):
        StereoD435(424, 240, baseline_m=0.0)
    with pytest.raises(ValueError, match="baseline_m"):
        StereoD435(424, 240, baseline_m=-0.05)
    with pytest.raises(ValueError, match="n_dots"):
        Projector(DotPattern(n_dots=0))
    with pytest.raises(ValueError, match="not a D435 depth mode"):
        StereoD435(320, 200)
    with pytest.raises(ValueError, match="preset"):
        StereoD435(424, 240, matcher="ultra")
    with pytest.raises(ValueError, match="materials"):
        StereoD435(424, 240, materials="carpet")
    with pytest.raises(ValueError, match="n_frames"):
        StereoD435(424, 240).frames(wall(1.0), T_CAM, 0, 1)
