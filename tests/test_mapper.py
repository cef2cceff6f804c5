"""The mapper end to end: simulated D435 depth of a floor -> noise model -> map."""

import numpy as np
import pytest

import noise_model as nm
from elevmap import Camera, ElevationMap, FusionParams, Mapper
from elevmap.map.layers import LAYERS
from noise_model.sim.targets import camera_extrinsics

W, H = 424, 240
K = nm.D435.intrinsics(W, H)


def floor_depth(T_map_cam, rng, height=0.0, noise=True):
    """z-depth of the plane z = height (map frame) with the paper's noise, uint16 mm; 0 = no hit."""
    R, t = T_map_cam[:3, :3], T_map_cam[:3, 3]
    u = (np.arange(W) - K[0, 2]) / K[0, 0]
    v = (np.arange(H) - K[1, 2]) / K[1, 1]
    rays_cam = np.stack(np.broadcast_arrays(u[None, :], v[:, None], 1.0), axis=-1)   # (H, W, 3), z = 1
    dz = rays_cam @ R[2]                                   # map-z change per unit camera z
    with np.errstate(divide="ignore"):
        z = (height - t[2]) / dz
    hit = (dz < 0) & (z > 0) & (z < 6.0)
    theta = np.arccos(abs(R[2, 2]))                        # floor normal vs optical axis
    if noise:
        z = z + rng.normal(size=z.shape) * nm.axial_sigma(np.where(hit, z, 1.0), theta)
    d = np.where(hit & (z > 0), np.round(z / 0.001), 0)
    return np.clip(d, 0, 65535).astype(np.uint16)


def test_a_flat_floor_is_mapped_flat_and_calibrated(rng):
    T = camera_extrinsics((0.0, 0.0, 0.45), pitch_down_deg=30.0)
    mapper = Mapper(ElevationMap(4.0, 0.04), [Camera("front", K, W, H)])
    for f in range(10):
        stats = mapper.integrate("front", floor_depth(T, rng), T_map_cam=T, stamp=0.1 * f)
    assert stats["points"] > 0.9 * W * H * 0.5
    m = mapper.map
    h, v = m.layer("elevation"), m.layer("variance")
    known = np.isfinite(h)
    assert known.mean() > 0.15
    err = np.abs(h[known])
    # the paper's sigma_z on a floor seen at 60 deg is ~9 cm per pixel at 1 m; fused over 10 frames
    # the floor comes out flat to well under a centimetre
    assert np.median(err) < 0.01 and np.percentile(err, 90) < 0.03
    assert np.all(np.isfinite(v[known])) and np.all(v[known] > 0)


def test_two_cameras_feed_one_map(rng):
    front = Camera("front", K, W, H, T_base_cam=camera_extrinsics((0.3, 0.0, 0.0), 30.0, 0.0))
    rear = Camera("rear", K, W, H, T_base_cam=camera_extrinsics((-0.3, 0.0, 0.0), 30.0, 180.0))
    mapper = Mapper(ElevationMap(4.0, 0.05), [front, rear])
    T_map_base = np.eye(4)
    T_map_base[2, 3] = 0.45
    for name, cam in mapper.cameras.items():
        mapper.integrate(name, floor_depth(T_map_base @ cam.T_base_cam, rng), T_map_base=T_map_base)
    known = mapper.map.is_known()
    xs, _ = mapper.map.cell_centres()
    assert known[xs > 0.6].any() and known[xs < -0.6].any()
    assert not known[np.abs(xs) < 0.3].any()                 # under the robot: nobody sees it


def test_numba_and_numpy_mappers_agree(rng):
    T = camera_extrinsics((0.0, 0.0, 0.45), 30.0)
    P = np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5])
    a = Mapper(ElevationMap(4.0, 0.04, visibility_cleanup=False), [Camera("c", K, W, H)])
    b = Mapper(ElevationMap(4.0, 0.04, visibility_cleanup=False), [Camera("c", K, W, H)])
    for f in range(3):
        d = floor_depth(T, rng)
        a.integrate("c", d, T_map_cam=T, pose_cov=P, stamp=f)
        b.integrate("c", d, T_map_cam=T, pose_cov=P, stamp=f, impl="numpy")
    np.testing.assert_array_equal(np.isnan(a.map.data), np.isnan(b.map.data))
    sums = [LAYERS.index("scatter")]            # sums of O(n) terms that cancel: compare on their scale
    rest = [k for k in range(len(LAYERS)) if k not in sums]
    np.testing.assert_allclose(a.map.data[rest], b.map.data[rest], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(a.map.data[sums], b.map.data[sums], rtol=1e-7, atol=1e-7)


def test_pose_uncertainty_makes_the_map_less_confident(rng):
    T = camera_extrinsics((0.0, 0.0, 0.45), 30.0)
    d = floor_depth(T, rng)
    plain = FusionParams(spread_alpha=None, min_variance=1e-12,
                         neighbour_radius=0)                                          # the pose term alone
    sure = Mapper(ElevationMap(4.0, 0.04, fusion_params=plain), [Camera("c", K, W, H)])
    unsure = Mapper(ElevationMap(4.0, 0.04, fusion_params=plain), [Camera("c", K, W, H)])
    sure.integrate("c", d, T_map_cam=T)
    unsure.integrate("c", d, T_map_cam=T, pose_cov=np.diag([0.0, 0.0, 1e-4, 1e-4, 1e-4, 0.0]))
    k = sure.map.is_known() & unsure.map.is_known()
    assert np.all(unsure.map.layer("variance")[k] > sure.map.layer("variance")[k])


def test_bad_calls_name_the_problem(rng):
    mapper = Mapper(cameras=[Camera("c", K, W, H)])
    d = np.zeros((H, W), np.uint16)
    with pytest.raises(ValueError, match="unknown camera 'x'"):
        mapper.integrate("x", d, T_map_cam=np.eye(4))
    with pytest.raises(ValueError, match="exactly one of T_map_cam and T_map_base"):
        mapper.integrate("c", d, T_map_cam=np.eye(4), T_map_base=np.eye(4))
    with pytest.raises(ValueError, match="gives 240x424 depth"):
        mapper.integrate("c", np.zeros((10, 10), np.uint16), T_map_cam=np.eye(4))
    with pytest.raises(ValueError, match="already registered"):
        mapper.add_camera(Camera("c", K, W, H))
    with pytest.raises(ValueError, match="T_base_cam"):
        Camera("bad", K, W, H, T_base_cam=np.ones((4, 4)))


def test_out_of_range_points_are_refused_whether_the_kernel_or_a_variance_model_made_them(rng):
    """The map skips its own check of a frame's values only where the noise kernel counted none out of
    range as it wrote them. A frame with such points (a camera 2 m short of the 1e9 m coordinate bound, a
    pose covariance that makes every height variance exceed 1e4 m^2) or from a camera's variance_model (not
    counted) is refused with the check's message and the map unchanged, as ElevationMap.update refuses
    the same points; an ordinary frame gives the map bit for bit that update gives."""
    far = camera_extrinsics((1e9 - 2.0, 0.0, 0.45), 30.0)        # the floor seen up to 6 m ahead: beyond 1e9 m
    near = camera_extrinsics((0.0, 0.0, 0.45), 30.0)
    big = np.diag([1e-4, 1e-4, 1e5, 1e-6, 1e-6, 1e-6])

    def huge_variance(points_cam, T_map_cam, pose_cov):
        return np.full(len(points_cam), 1e5), np.full((len(points_cam), 3), 1e-4)

    for name, T, P, message in (("c", far, None, r"beyond the 1e\+09 m"), ("c", near, big, r"must be in m\^2"),
                                ("v", near, None, r"must be in m\^2")):
        mapper = Mapper(ElevationMap(4.0, 0.04, centre_xy=T[:2, 3]),
                        [Camera("c", K, W, H), Camera("v", K, W, H, variance_model=huge_variance)])
        d = floor_depth(T, rng)
        before = mapper.map.data.copy()
        with pytest.raises(ValueError, match=message):
            mapper.integrate(name, d, T_map_cam=T, pose_cov=P)
        np.testing.assert_array_equal(mapper.map.data, before)
        if name == "c":
            pts = nm.depth_to_map_points(d, K, T, P, depth_scale=0.001)
            assert pts.n_outside > 0
            with pytest.raises(ValueError, match=message):
                mapper.map.update(pts.points_map, pts.height_var, horizontal_cov=pts.horizontal_cov)
    T = camera_extrinsics((0.0, 0.0, 0.45), 30.0)
    mapper = Mapper(ElevationMap(4.0, 0.04, visibility_cleanup=False), [Camera("c", K, W, H)])
    emap = ElevationMap(4.0, 0.04, visibility_cleanup=False)
    for f in range(2):
        d = floor_depth(T, rng)
        mapper.integrate("c", d, T_map_cam=T, stamp=f)
        pts = mapper.last_points
        assert pts.n_outside == 0
        emap.update(pts.points_map, pts.height_var, stamp=f, horizontal_cov=pts.horizontal_cov)
    np.testing.assert_array_equal(mapper.map.data, emap.data)
