"""Scenes, the numba ray caster against hand geometry and its NumPy reference, noise, walks and drift."""

import math

import numpy as np
import pytest

from noise_model import D435, axial_sigma
from noise_model.sim import (
    DEFAULT_T_BASE_CAM, HIT_GROUND, HIT_NONE, NOMINAL_BASE_HEIGHT_M, Box, HeightField, Ramp, Scene, Stairs, Target,
    add_noise, camera_pose_cov, odometry_drift, render_depth, render_depth_reference, simulate_walk, walk,
)
from noise_model.sim.targets import (
    camera_extrinsics, render_floor, render_planar_target, simulate_target_frames,
)

# a small odd-sized image: row 30 and column 40 are exactly on the optical axis (v' = u' = 0)
W, H = 81, 61
K = np.array([[40.0, 0.0, 40.0], [0.0, 40.0, 30.0], [0.0, 0.0, 1.0]])


def rays(K, width, height):
    u = (np.arange(width) - K[0, 2]) / K[0, 0]
    v = (np.arange(height) - K[1, 2]) / K[1, 1]
    return np.meshgrid(u, v)


def both(scene, T, K=K, width=W, height=H, **kw):
    """numba and reference renders, asserted equal (NaN pattern exactly, values to 1e-9); the primitive
    index of both equal too, and asking for it changes neither depth nor angle."""
    z, th = render_depth(scene, K, width, height, T, **kw)
    zr, thr = render_depth_reference(scene, K, width, height, T, **kw)
    np.testing.assert_array_equal(np.isnan(z), np.isnan(zr))
    np.testing.assert_array_equal(np.isnan(th), np.isnan(z))
    np.testing.assert_allclose(z, zr, rtol=0, atol=1e-9)
    np.testing.assert_allclose(th, thr, rtol=0, atol=1e-9)
    zi, thi, idx = render_depth(scene, K, width, height, T, return_index=True, **kw)
    zri, thri, idxr = render_depth_reference(scene, K, width, height, T, return_index=True, **kw)
    np.testing.assert_array_equal(zi, z)
    np.testing.assert_array_equal(thi, th)
    np.testing.assert_array_equal(zri, zr)
    np.testing.assert_array_equal(thri, thr)
    np.testing.assert_array_equal(idx, idxr)
    assert idx.dtype == np.int32 and idx.shape == z.shape
    np.testing.assert_array_equal(idx == HIT_NONE, np.isnan(z))
    assert idx.min() >= HIT_NONE and idx.max() < len(scene.primitives)
    return z, th


# ---------------------------------------------------------------------------------------------
# hand-checkable renders
# ---------------------------------------------------------------------------------------------
def test_fronto_parallel_target_and_box_face_give_the_exact_depth():
    T = camera_extrinsics((0.0, 0.0, 1.0), pitch_down_deg=0.0)     # looking along map +x
    U, V = rays(K, W, H)
    # a 1 m x 0.8 m board 2 m ahead, facing the camera
    z, th = both(Scene([Target((2.0, 0.0, 1.0), 1.0, 0.8, 0.0)], ground_z=None), T)       # seen from behind
    inside = (np.abs(U) * 2.0 <= 0.5) & (np.abs(V) * 2.0 <= 0.4)
    np.testing.assert_array_equal(np.isfinite(z), inside)
    assert np.all(z[inside] == 2.0) and np.all(th[inside] == 0.0)
    # a box whose front face is at x = 2.5 and fills the view
    z, th = both(Scene([Box((3.0, 0.0, 1.0), (1.0, 20.0, 20.0), 0.0)], ground_z=None), T)
    assert np.all(np.abs(z - 2.5) < 1e-12) and np.all(th < 1e-12)
    # the same with the planar-target renderer of the capture-set simulation
    z_wall, _ = render_planar_target(K, W, H, 2.5)
    np.testing.assert_allclose(z, z_wall, atol=1e-12)


def test_floor_seen_from_a_pitched_camera_is_analytic_with_theta_60_deg():
    T = camera_extrinsics((0.0, 0.0, 0.45), pitch_down_deg=30.0)
    z, th = both(Scene([], ground_z=0.0), T, max_range_m=10.0)
    # the map z of the ray d = R (u', v', 1) changes by R[2] . (u', v', 1) per unit of z-depth
    U, V = rays(K, W, H)
    dz = T[2, 0] * U + T[2, 1] * V + T[2, 2]
    expected = np.where((dz < 0) & (-0.45 / dz <= 10.0), -0.45 / dz, np.nan)
    np.testing.assert_allclose(z, expected, rtol=1e-12, atol=0)
    z_floor, th_floor = render_floor(K, W, H, T, max_range_m=10.0)
    np.testing.assert_allclose(z, z_floor, rtol=1e-12)
    np.testing.assert_allclose(th[np.isfinite(th)], math.radians(60.0), atol=1e-12)
    # the centre pixel looks 30 deg down from 0.45 m: ray length 0.9 m, z-depth the same (on axis)
    assert z[30, 40] == pytest.approx(0.9, abs=1e-12)


def test_stair_edge_lands_where_geometry_says():
    # a horizontal camera 0.25 m up, 1.5 m before the first riser (0.17 m rise, 0.29 m run)
    scene = Scene([Stairs((1.5, 0.0), 0.0, 0.17, 0.29, 6, 4.0)], ground_z=0.0)
    T = camera_extrinsics((0.0, 0.0, 0.25), pitch_down_deg=0.0)
    z, th = both(scene, T)
    col = z[:, 40]                                      # u' = 0: the ray stays in the x-z plane
    for v in range(H):
        vp = (v - 30) / 40.0                            # the ray drops vp metres per metre of depth
        h = lambda x: 0.25 - vp * x                     # noqa: E731
        if vp > 0 and 0.25 / vp <= 1.5:
            assert col[v] == pytest.approx(0.25 / vp, abs=1e-12), v    # the floor before the stairs
        elif h(1.5) <= 0.17:
            assert col[v] == pytest.approx(1.5, abs=1e-12), v          # first riser
            assert th[v, 40] == pytest.approx(0.0, abs=1e-12)
        elif vp > 0 and h(1.79) <= 0.17:
            assert col[v] == pytest.approx(0.08 / vp, abs=1e-12), v    # top of the first step
            assert th[v, 40] == pytest.approx(math.pi / 2, abs=1e-12)
        elif h(1.79) <= 0.34:
            assert col[v] == pytest.approx(1.79, abs=1e-12), v         # second riser
    # the rows where the first step's top ends and the second riser starts, by hand:
    # 0.25 - vp 1.79 = 0.17  ->  vp = 0.0447  ->  v = 30 + 1.79 px
    rows = np.flatnonzero(np.abs(col - 1.79) < 1e-9)
    assert rows.max() == 31 and col[32] == pytest.approx(0.08 / 0.05)


def test_ramp_and_box_top_depths_by_hand():
    T = camera_extrinsics((0.0, 0.0, 2.0), pitch_down_deg=90.0)          # looking straight down
    scene = Scene([Ramp((-1.0, 0.0), 0.0, 2.0, 1.0, 1.0), Box((0.0, 1.0, 0.25), (1.0, 0.5, 0.5))], ground_z=0.0)
    z, th = both(scene, T)
    U, V = rays(K, W, H)
    # straight down, image right = map -y, image down = map -x; a point at z-depth t is at
    # x = -V t, y = -U t, z = 2 - t. On the ramp z = 0.5 (x + 1)  ->  t = 1.5 / (1 - 0.5 V)
    t = 1.5 / (1.0 - 0.5 * V)
    on_ramp = (np.abs(V * t) < 1.0 - 1e-9) & (np.abs(U * t) < 0.5 - 1e-9)
    assert on_ramp.sum() > 100
    np.testing.assert_allclose(z[on_ramp], t[on_ramp], atol=1e-12)
    np.testing.assert_allclose(th[on_ramp], math.atan(0.5), atol=1e-12)
    # the box's top at z = 0.5: t = 1.5 over x in [-0.5, 0.5], y in [0.75, 1.25]
    on_box = (np.abs(V * 1.5) < 0.5 - 1e-9) & (np.abs(-U * 1.5 - 1.0) < 0.25 - 1e-9)
    assert on_box.sum() > 50
    np.testing.assert_allclose(z[on_box], 1.5, atol=1e-12)
    np.testing.assert_allclose(th[on_box], 0.0, atol=1e-12)


def test_height_field_hits_lie_on_the_bilinear_surface(rng):
    f = HeightField(rng.uniform(0.0, 0.2, (21, 17)), (0.5, -1.5), 0.15)
    scene = Scene([f], ground_z=None)
    T = camera_extrinsics((0.0, 0.0, 1.2), pitch_down_deg=35.0)
    z, th = both(scene, T)
    U, V = rays(K, W, H)
    d = np.stack([U, V, np.ones_like(U)], -1) @ T[:3, :3].T
    p = T[:3, 3] + z[..., None] * d
    x0, x1, y0, y1 = f.extent
    hit = np.isfinite(z)
    hit &= (p[..., 0] > x0 + 1e-6) & (p[..., 0] < x1 - 1e-6) & (p[..., 1] > y0 + 1e-6) & (p[..., 1] < y1 - 1e-6)
    assert hit.mean() > 0.3                              # hits on the surface, not on the side walls
    np.testing.assert_allclose(p[hit][:, 2], f.height_at(p[hit][:, :2]), atol=1e-9)
    # the normal of the bilinear patch from finite differences of height_at, away from cell borders
    e = 1e-6
    q = p[hit][:, :2]
    g = (q - f.origin) / f.resolution
    good = np.all(np.abs(g - np.round(g)) > 1e-4, axis=1)
    q, th_hit = q[good], th[hit][good]
    hx = (f.height_at(q + [e, 0]) - f.height_at(q - [e, 0])) / (2 * e)
    hy = (f.height_at(q + [0, e]) - f.height_at(q - [0, e])) / (2 * e)
    n = np.stack([-hx, -hy, np.ones_like(hx)], 1) / np.sqrt(1 + hx ** 2 + hy ** 2)[:, None]
    np.testing.assert_allclose(th_hit, np.arccos(np.abs(n @ T[:3, 2])), atol=1e-6)


def test_height_field_from_a_function_and_its_side_wall():
    f = HeightField.from_function(lambda x, y: 0.3 + 0.0 * x * y, (1.0, 3.0), (-1.0, 1.0), 0.1, base_z=0.0)
    assert f.heights.shape == (21, 21) and f.extent == pytest.approx((1.0, 3.0, -1.0, 1.0))
    T = camera_extrinsics((0.0, 0.0, 0.1), pitch_down_deg=0.0)
    z, th = both(Scene([f], ground_z=None), T)
    assert z[30, 40] == pytest.approx(1.0, abs=1e-12) and th[30, 40] == pytest.approx(0.0, abs=1e-12)


# ---------------------------------------------------------------------------------------------
# numba == NumPy reference
# ---------------------------------------------------------------------------------------------
def random_scene(rng):
    prims = []
    for _ in range(rng.integers(0, 4)):
        prims.append(Box(rng.uniform(-3, 3, 3), rng.uniform(0.1, 1.5, 3), rng.uniform(-180, 180)))
    for _ in range(rng.integers(0, 2)):
        prims.append(Stairs(rng.uniform(-3, 3, 3), rng.uniform(-180, 180), rng.uniform(0.05, 0.3),
                            rng.uniform(0.1, 0.5), int(rng.integers(1, 6)), rng.uniform(0.3, 2)))
    for _ in range(rng.integers(0, 2)):
        prims.append(Ramp(rng.uniform(-3, 3, 3), rng.uniform(-180, 180), rng.uniform(0.5, 3), rng.uniform(0.3, 2),
                          rng.uniform(0.1, 1.5)))
    for _ in range(rng.integers(0, 2)):
        prims.append(Target(rng.uniform(-3, 3, 3), rng.uniform(0.2, 2), rng.uniform(0.2, 2), rng.uniform(-180, 180)))
    for _ in range(rng.integers(0, 2)):
        nx, ny = rng.integers(2, 25, 2)
        prims.append(HeightField(rng.uniform(-0.5, 0.5, (nx, ny)), rng.uniform(-3, 1, 2), rng.uniform(0.05, 0.4),
                                 base_z=-0.5 - rng.uniform(0, 1)))
    return Scene(prims, ground_z=rng.uniform(-1.5, 0) if rng.random() < 0.5 else None)


def random_pose(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    T = np.eye(4)
    T[:3, :3] = q
    T[:3, 3] = rng.uniform(-4, 4, 3)
    return T


def test_numba_equals_reference_on_random_scenes_and_poses():
    hits = misses = 0
    for seed in range(60):
        rng = np.random.default_rng(seed)
        scene = random_scene(rng)
        z, _ = both(scene, random_pose(rng), max_range_m=float(rng.uniform(2.0, 12.0)))
        hits += np.isfinite(z).sum()
        misses += np.isnan(z).sum()
    assert hits > 20000 and misses > 20000          # both cases are exercised


def test_numba_equals_reference_looking_at_height_fields():
    for seed in range(30):
        rng = np.random.default_rng(100 + seed)
        nx, ny = rng.integers(2, 40, 2)
        res = rng.uniform(0.05, 0.3)
        tilt = (rng.random() < 0.5) * np.linspace(0, 1, nx)[:, None]
        prims = [HeightField(rng.uniform(-0.3, 0.3, (nx, ny)) + tilt, (0, 0), res,
                             base_z=-0.5 if rng.random() < 0.5 else None)]
        if rng.random() < 0.5:
            prims.append(Box(rng.uniform(0, 3, 3), rng.uniform(0.1, 1, 3), rng.uniform(-180, 180)))
        scene = Scene(prims, ground_z=None if rng.random() < 0.5 else -0.6)
        pos = [rng.uniform(-2, nx * res + 2), rng.uniform(-2, ny * res + 2), rng.uniform(-0.3, 2.0)]
        both(scene, camera_extrinsics(pos, rng.uniform(-20, 80), rng.uniform(-180, 180)))


def test_primitive_index_names_what_each_pixel_hit():
    # looking along map +x, level, 1 m up: a box (index 1) ahead on the ground, a target (index 0) off to
    # the side, a height field (index 2) behind the camera (out of view); the ground below, the sky above
    scene = Scene([Target((2.0, 3.0, 1.0), 0.5, 0.5), Box((3.0, 0.0, 0.5), (1.0, 1.0, 1.0)),
                   HeightField(np.zeros((3, 3)), (-5.0, -1.0), 0.5)], ground_z=0.0)
    T = camera_extrinsics((0.0, 0.0, 1.0), pitch_down_deg=0.0)
    z, _ = both(scene, T)
    _, _, idx = render_depth(scene, K, W, H, T, return_index=True)
    assert idx[30, 40] == 1                                         # the centre ray: the box's front face
    assert idx[H - 1, 0] == HIT_GROUND and idx[0, 0] == HIT_NONE    # bottom-left: floor; top-left: sky
    assert set(np.unique(idx)) == {HIT_NONE, HIT_GROUND, 1}         # the target and the field are out of view
    assert np.all(z[idx == 1] <= 2.5 + 1e-12)
    # a camera inside a solid is blinded: every pixel is no hit
    _, _, idx = render_depth(scene, K, W, H, camera_extrinsics((3.0, 0.0, 0.5), 0.0), return_index=True)
    assert np.all(idx == HIT_NONE)


def test_primitives_and_the_ground_carry_a_material():
    from noise_model.sim.stereo.materials import Uniform, concrete

    b = Box((0.0, 0.0, 0.5), (1.0, 1.0, 1.0), material=0.3)
    assert b.material == Uniform(0.3, "Box.material")
    st = Stairs((0.0, 0.0), material=concrete())
    assert all(step.material == concrete() for step in st.steps())
    assert HeightField.from_function(lambda x, y: 0 * x, (0, 1), (0, 1), material=0.5).material.albedo == 0.5
    scene = Scene([Box((0.0, 0.0, 0.5), (1.0, 1.0, 1.0))], ground_material=0.2)
    assert scene.has_materials and scene.ground_material.albedo == 0.2
    assert scene.with_primitives(b).ground_material == scene.ground_material
    assert not Scene.stairs_scene().has_materials                   # materials are optional everywhere


def test_rays_that_miss_everything():
    scene = Scene([Box((3.0, 0.0, 0.5), (1.0, 1.0, 1.0))], ground_z=0.0)
    z, th = both(scene, camera_extrinsics((0.0, 0.0, 1.0), pitch_down_deg=-60.0))    # looking up
    assert np.all(np.isnan(z)) and np.all(np.isnan(th))
    z, _ = both(scene, camera_extrinsics((0.0, 0.0, 1.0), pitch_down_deg=0.0, yaw_deg=180.0), max_range_m=3.0)
    assert np.isnan(z[:44]).all() and np.isfinite(z[44:]).all()      # z-depth 1 / v' of the floor <= 3 m


def test_camera_inside_a_solid_sees_nothing():
    scene = Scene([Box((1.0, 0.0, 0.5), (1.0, 1.0, 1.0)), Stairs((3.0, 0.0), 0.0, 0.2, 0.3, 3, 1.0),
                   HeightField(np.full((5, 5), 0.5), (-5.0, -5.0), 0.5, base_z=0.0)], ground_z=0.0)
    for pos in [(1.0, 0.0, 0.5), (1.5, 0.5, 1.0), (3.1, 0.0, 0.15), (-4.0, -4.0, 0.3), (0.0, 0.0, -0.1)]:
        z, th = both(scene, camera_extrinsics(pos, 30.0))
        assert np.all(np.isnan(z)) and np.all(np.isnan(th)), pos
    # above the first step of the stairs (inside their bounding box, outside the steps): sees
    z, _ = both(scene, camera_extrinsics((3.1, 0.0, 0.25), 30.0))
    assert np.isfinite(z).mean() > 0.5


def test_grazing_rays():
    # the centre row is horizontal (v' = 0): from exactly the box's top height it lies in the top
    # face's plane; slabs are closed, so it hits the front face's top edge
    scene = Scene([Box((3.0, 0.0, 0.5), (1.0, 1.0, 1.0))], ground_z=None)
    z, _ = both(scene, camera_extrinsics((0.0, 0.0, 1.0), pitch_down_deg=0.0))
    U, _ = rays(K, W, H)
    on_face = np.abs(U[30]) * 2.5 <= 0.5
    np.testing.assert_allclose(z[30, on_face], 2.5, atol=1e-12)
    assert np.isnan(z[29]).all()                                       # the rows above miss
    # a hair above the top: the centre row passes over it
    z, _ = both(scene, camera_extrinsics((0.0, 0.0, 1.0 + 1e-9), pitch_down_deg=0.0))
    assert np.isnan(z[30]).all()
    # along a face (the camera in the plane of the box's side face y = 0.5, looking along +x)
    z, _ = both(scene, camera_extrinsics((0.0, 0.5, 0.5), pitch_down_deg=0.0))
    assert z[30, 40] == pytest.approx(2.5, abs=1e-12)
    # a height field seen edge-on at its maximum height: the centre row hits its wall's top edge
    f = HeightField(np.array([[0.2, 0.2], [0.2, 0.2], [0.1, 0.0]]), (2.0, -0.5), 0.5)
    z, th = both(Scene([f], ground_z=None), camera_extrinsics((0.0, 0.0, 0.2), pitch_down_deg=0.0))
    assert z[30, 40] == 2.0 and th[30, 40] == 0.0 and np.isnan(z[29]).all()
    # a ray in the plane of a ramp's slope (45 deg, built exactly): it meets the ramp's bottom edge
    s = math.sqrt(0.5)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([[0.0, -1.0, 0.0], [s, 0.0, -s], [s, 0.0, s]])
    T[:3, 3] = [0.0, 0.0, -1.0]
    z, _ = both(Scene([Ramp((1.0, 0.0), 0.0, 2.0, 1.0, 2.0)], ground_z=None), T)
    assert z[30, 40] == pytest.approx(1.0 / s, abs=1e-12)                # at x = 1: z-depth 1 / s


def test_result_does_not_depend_on_the_thread_count(rng):
    scene = Scene.box_field(rng).with_primitives(HeightField(rng.uniform(0, 0.1, (30, 30)), (1.0, -1.0), 0.1))
    T = walk([[0.0, 0.0], [1.0, 0.0]])[0] @ DEFAULT_T_BASE_CAM
    K2 = D435.intrinsics(424, 240)
    one = render_depth(scene, K2, 424, 240, T, nthreads=1)
    two = render_depth(scene, K2, 424, 240, T, nthreads=2)
    np.testing.assert_array_equal(one[0], two[0])
    np.testing.assert_array_equal(one[1], two[1])


def test_scenes_by_name():
    assert Scene.named("stairs").primitives == Scene.stairs_scene().primitives
    a = Scene.named("boxes", np.random.default_rng(5)).primitives
    assert a == Scene.box_field(np.random.default_rng(5)).primitives and len(a) == 15
    assert all(0.05 <= b.size[2] <= 0.3 for b in a)
    assert isinstance(Scene.named("slope").primitives[0], Ramp)
    with pytest.raises(ValueError, match="unknown scene 'stair'; choose from stairs, boxes, slope, rough"):
        Scene.named("stair")
    with pytest.raises(ValueError, match="rng"):
        Scene.named("rough")


def test_convenience_scenes_render():
    K2 = D435.intrinsics(424, 240)
    for scene in (Scene.stairs_scene(), Scene.box_field(np.random.default_rng(0)), Scene.slope(),
                  Scene.rough(np.random.default_rng(0), x_range=(-1.0, 4.0), y_range=(-3.0, 3.0))):
        T = walk([[0.0, 0.0], [1.0, 0.0]], scene=scene)[0] @ DEFAULT_T_BASE_CAM
        z, th = render_depth(scene, K2, 424, 240, T)
        assert np.isfinite(z).mean() > 0.9
        assert np.nanmax(th) <= math.pi / 2


# ---------------------------------------------------------------------------------------------
# ground truth heights
# ---------------------------------------------------------------------------------------------
def test_height_at_by_hand():
    stairs = Stairs((1.0, 2.0), 90.0, 0.2, 0.25, 4, 1.0)              # ascending along map +y
    box = Box((-2.0, 0.0, 0.15), (1.0, 0.5, 0.3), 90.0)               # yawed: 0.5 along x, 1.0 along y
    ramp = Ramp((0.0, -3.0, 0.1), 180.0, 2.0, 1.0, 0.5)               # ascending along -x, base at 0.1
    scene = Scene([stairs, box, ramp, Target((5.0, 5.0, 1.0), 2.0, 2.0)], ground_z=0.0)
    pts = [(1.0, 1.9), (1.0, 2.1), (1.0, 2.25), (1.0, 2.3), (1.4, 2.9), (1.6, 2.9), (1.0, 3.25),
           (-2.0, 0.45), (-2.2, 0.0), (-2.3, 0.0), (-1.0, -3.0), (-2.0, -3.0), (5.0, 5.0)]
    # (1.0, 2.25) is on the border of steps 0 and 1: the higher one counts
    expected = [0.0, 0.2, 0.4, 0.4, 0.8, 0.0, 0.0, 0.3, 0.3, 0.0, 0.1 + 0.25, 0.1 + 0.5, 0.0]
    np.testing.assert_allclose(scene.height_at(pts), expected, atol=1e-12)
    assert np.isnan(Scene([box], ground_z=None).height_at([[0.0, 0.0]]))[0]
    f = HeightField(np.array([[0.0, 1.0], [2.0, 3.0]]), (0.0, 0.0), 2.0)
    hf = Scene([f], ground_z=None)
    np.testing.assert_allclose(hf.height_at([[1.0, 1.0], [2.0, 0.0], [0.5, 1.5]]),
                               [1.5, 2.0, 1.25])                     # h = x + y / 2
    grid = scene.height_grid([1.0, 1.6], [2.1, 3.1])
    assert grid.shape == (2, 2) and grid[0, 0] == pytest.approx(0.2) and grid[1, 1] == 0.0


def test_rendered_stairs_agree_with_height_at():
    scene = Scene.stairs_scene()
    T = camera_extrinsics((0.5, 0.2, 1.6), pitch_down_deg=50.0)
    z, th = render_depth(scene, K, W, H, T)
    U, V = rays(K, W, H)
    p = T[:3, 3] + z[..., None] * (np.stack([U, V, np.ones_like(U)], -1) @ T[:3, :3].T)
    top = np.isfinite(z) & (np.abs(th - math.radians(40.0)) < 1e-9)   # horizontal faces (risers: 50 deg)
    assert top.sum() > 1000
    np.testing.assert_allclose(p[top][:, 2], scene.height_at(p[top][:, :2]), atol=1e-9)


# ---------------------------------------------------------------------------------------------
# noise
# ---------------------------------------------------------------------------------------------
def test_reference_noise_has_the_papers_sigma():
    scene = Scene([Target((1.5, 0.3, 0.6), 0.8, 0.8, 150.0), Box((2.8, -0.5, 0.6), (0.5, 1.0, 1.2), 10.0)],
                  ground_z=None)
    T = camera_extrinsics((0.0, 0.0, 0.6), pitch_down_deg=0.0)
    z, th = render_depth(scene, K, W, H, T)
    rng = np.random.default_rng(7)
    frames = np.stack([add_noise(z, th, rng) for _ in range(800)]) * 0.001
    hit = np.isfinite(z)
    assert hit.sum() > 300 and np.ptp(th[hit]) > 0.3
    std = frames[:, hit].std(axis=0)
    sigma = axial_sigma(z[hit], th[hit])
    ratio = std / np.sqrt(sigma ** 2 + 0.001 ** 2 / 12)           # plus the 1 mm quantisation
    assert abs(np.median(ratio) - 1.0) < 0.01
    assert np.mean(np.abs(ratio - 1.0) < 0.1) > 0.95              # per pixel, 800 frames: ~2.5 % spread
    np.testing.assert_allclose(frames[:, hit].mean(axis=0), z[hit], atol=float(5 * sigma.max() / np.sqrt(800)))
    assert np.all(frames[:, ~np.isfinite(z)] == 0)


def test_reference_noise_equals_the_capture_set_simulation():
    Kd = D435.intrinsics(424, 240)
    z, th = render_planar_target(Kd, 424, 240, 1.5, 30.0)
    mine = add_noise(z, th, np.random.default_rng(3))
    theirs = simulate_target_frames(Kd, 424, 240, 1.5, 1, np.random.default_rng(3), yaw_deg=30.0)[0]
    np.testing.assert_array_equal(mine, theirs)


def test_no_noise_is_exact_up_to_quantisation(rng):
    T = camera_extrinsics((0.0, 0.0, 0.45), pitch_down_deg=30.0)
    z, th = render_depth(Scene.stairs_scene(), K, W, H, T)
    for scale in (0.001, 0.0001):
        d = add_noise(z, th, rng, model=None, depth_scale=scale)
        hit = np.isfinite(z) & (z / scale <= 65535)
        assert d.dtype == np.uint16 and np.all(d[~hit] == 0)
        assert np.max(np.abs(d[hit] * scale - z[hit])) <= 0.5 * scale * (1 + 1e-9)


def test_effects_are_applied_in_order_with_their_context(rng):
    z, th = render_planar_target(K, W, H, 1.0)
    seen = []

    def blank_left(zz, theta, g, ctx):
        seen.append(("blank", sorted(ctx)))
        zz[:, :40] = np.nan
        return zz

    def push(zz, theta, g, ctx):
        seen.append(("push", ctx["index"], ctx["width"], ctx["height"], ctx["depth_scale"]))
        assert np.isnan(zz[:, :40]).all()                        # runs after blank_left
        return zz + 0.5

    d = add_noise(z, th, rng, model=None, effects=[blank_left, push], context={"K": K, "index": 7})
    assert np.all(d[:, :40] == 0) and np.all(d[:, 40:] == 1500)
    assert seen[0] == ("blank", ["K", "depth_scale", "height", "index", "width", "z_true"])
    assert seen[1] == ("push", 7, W, H, 0.001)
    with pytest.raises(ValueError, match=r"effects\[0\] must return"):
        add_noise(z, th, rng, effects=[lambda zz, t, g, c: zz[:2]])

    def scribble(zz, theta, g, ctx):
        theta[0, 0] = 1.0
        return zz

    with pytest.raises(ValueError, match="read-only"):                 # theta and z_true are read only
        add_noise(z, th, rng, effects=[scribble])
    assert th[0, 0] == 0.0


# ---------------------------------------------------------------------------------------------
# trajectories and drift
# ---------------------------------------------------------------------------------------------
def test_walk_follows_the_path_at_constant_speed():
    path = [[0.0, 0.0], [2.0, 0.0], [2.0, 1.0]]
    poses = walk(path, speed_mps=0.5, rate_hz=10.0)
    assert poses.shape == (61, 4, 4)                                  # 3 m at 0.05 m per frame
    s = np.arange(61) * 0.05
    expected = np.where(s[:, None] <= 2.0, np.column_stack([s, 0 * s]), np.column_stack([0 * s + 2.0, s - 2.0]))
    np.testing.assert_allclose(poses[:, :2, 3], expected, atol=1e-12)
    yaw = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    np.testing.assert_allclose(yaw[:40], 0.0, atol=1e-12)
    np.testing.assert_allclose(yaw[40:], math.pi / 2, atol=1e-12)     # from the waypoint on: the next segment
    np.testing.assert_allclose(poses[:, 2, 3], NOMINAL_BASE_HEIGHT_M)
    # the default camera is 0.45 m above the ground, pitched 30 deg down
    T = poses[0] @ DEFAULT_T_BASE_CAM
    assert T[2, 3] == pytest.approx(0.45) and -T[2, 2] == pytest.approx(0.5)


def test_walk_follows_the_terrain():
    scene = Scene.stairs_scene()
    poses = walk([[0.0, 0.0], [4.0, 0.0]], 0.5, 10.0, base_height_m=0.4, scene=scene, terrain_window_m=0.0)
    np.testing.assert_allclose(poses[:, 2, 3], scene.height_at(poses[:, :2, 3]) + 0.4)
    assert poses[-1, 2, 3] == pytest.approx(1.02 + 0.4)
    smooth = walk([[0.0, 0.0], [4.0, 0.0]], 0.5, 10.0, scene=scene)
    assert np.abs(np.diff(smooth[:, 2, 3])).max() < np.abs(np.diff(poses[:, 2, 3])).max()


def test_drift_grows_with_distance_and_its_covariance_matches():
    poses = walk([[0.0, 0.0], [3.0, 0.0], [3.0, 3.0]], 1.0, 10.0)
    errors = []
    for seed in range(300):
        drifted, covs = odometry_drift(poses, np.random.default_rng(seed), sigma_xy_per_m=0.02,
                                       sigma_yaw_per_m=0.02)
        rho = drifted[:, :3, 3] - poses[:, :3, 3]
        phi = np.arctan2(drifted[:, 1, 0], drifted[:, 0, 0]) - np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
        errors.append(np.column_stack([rho[:, :2], phi]))
    e = np.array(errors)                                     # (runs, frames, 3): x, y, yaw
    assert np.all(e[:, 0] == 0) and np.all(covs[0] == 0)
    spread = np.linalg.norm(e[:, :, :2], axis=2).mean(axis=0)
    assert spread[60] > 2 * spread[10] > 0
    trace = np.trace(covs[:, :3, :3], axis1=1, axis2=2)
    assert np.all(np.diff(trace) >= -1e-15) and trace[-1] > trace[10] > 0
    assert np.all(np.diff(covs[:, 5, 5]) > 0)
    empirical = np.cov(e[:, -1].T)
    predicted = covs[-1][np.ix_([0, 1, 5], [0, 1, 5])]
    np.testing.assert_allclose(np.diag(empirical), np.diag(predicted), rtol=0.2)
    corr = lambda C: C[0, 2] / math.sqrt(C[0, 0] * C[2, 2])            # noqa: E731
    assert corr(empirical) == pytest.approx(corr(predicted), abs=0.12)


def test_camera_pose_cov_moves_the_rotation_lever_arm():
    C = np.diag([0.0, 0.0, 0.0, 0.0, 0.0, 0.01])                    # yaw only
    Pc = camera_pose_cov(C, np.eye(4), DEFAULT_T_BASE_CAM)
    assert Pc[1, 1] == pytest.approx(0.3 ** 2 * 0.01) and Pc[0, 0] == pytest.approx(0.0)


def test_simulate_walk_yields_frames():
    scene = Scene.stairs_scene()
    K2 = D435.intrinsics(424, 240)
    frames = list(simulate_walk(scene, K2, 424, 240, 4, rng=np.random.default_rng(0)))
    assert [f["index"] for f in frames] == [0, 1, 2, 3]
    f = frames[2]
    assert f["depth"].shape == (240, 424) and f["depth"].dtype == np.uint16 and f["pose_cov"] is None
    assert f["stamp"] == pytest.approx(2 / 30.0) and f["depth_scale"] == 0.001
    np.testing.assert_array_equal(f["T_map_cam"], f["T_map_cam_true"])
    assert f["T_map_cam_true"][0, 3] == pytest.approx(0.3 + 2 * 0.5 / 30.0)
    assert f["T_map_cam_true"][2, 3] == pytest.approx(0.45)
    # noise "none": depth is the quantised render of the true pose
    clean = list(simulate_walk(scene, K2, 424, 240, path=[[0.0, 0.0], [0.1, 0.0]], rng=np.random.default_rng(0),
                               noise="none", rate_hz=10.0))
    assert len(clean) == 3
    z, th = render_depth(scene, K2, 424, 240, clean[1]["T_map_cam_true"])
    np.testing.assert_array_equal(clean[1]["depth"], add_noise(z, th, np.random.default_rng(0), model=None))
    # drift: reported poses differ from the truth, with a covariance
    drifted = list(simulate_walk(scene, K2, 424, 240, 20, rng=np.random.default_rng(1), drift=True, noise="none"))
    assert drifted[0]["pose_cov"].shape == (6, 6) and not np.allclose(drifted[-1]["T_map_cam"],
                                                                      drifted[-1]["T_map_cam_true"])
    assert np.trace(drifted[-1]["pose_cov"]) > np.trace(drifted[1]["pose_cov"]) > 0
    # an effect sees the frame index
    idx = []
    list(simulate_walk(scene, K2, 424, 240, 2, rng=np.random.default_rng(0),
                       effects=[lambda zz, t, g, c: idx.append(c["index"]) or zz]))
    assert idx == [0, 1]


# ---------------------------------------------------------------------------------------------
# bad inputs
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("make, match", [
    (lambda: Box((0, 0, 0), (1, -1, 1)), "Box.size"),
    (lambda: Box((0, 0), (1, 1, 1)), "Box.centre"),
    (lambda: Box((0, 0, np.nan), (1, 1, 1)), "Box.centre"),
    (lambda: Box((0, 0, 0), (1, 1, 1), yaw_deg=np.inf), "Box.yaw_deg"),
    (lambda: Stairs((0, 0), 0.0, 0.17, 0.29, 0), "Stairs.count"),
    (lambda: Stairs((0, 0), 0.0, 170.0, 0.29, 6), "Stairs.rise"),
    (lambda: Ramp((0, 0), 0.0, -1.0), "Ramp.length"),
    (lambda: Target((0, 0, 0), 0.0), "Target.width"),
    (lambda: HeightField(np.array([[0.0, np.nan], [0, 0]])), "non-finite"),
    (lambda: HeightField(np.zeros(5)), "2-D"),
    (lambda: HeightField(np.zeros((3, 3)), resolution=0.0), "resolution"),
    (lambda: HeightField(np.zeros((3, 3)), base_z=1.0), "base_z"),
    (lambda: HeightField(np.full((3, 3), 1500.0)), "metres"),
    (lambda: HeightField.from_function(lambda x, y: x[:1], (0, 1), (0, 1)), "fn returned shape"),
    (lambda: Scene(["box"]), r"primitives\[0\]"),
    (lambda: Scene(ground_z=np.nan), "ground_z"),
    (lambda: Scene.box_field(None), "rng"),
    (lambda: Scene.box_field(np.random.default_rng(0), n_boxes=-1), "n_boxes"),
    (lambda: Scene.rough(np.random.default_rng(0), relief_m=-0.1), "relief_m"),
    (lambda: Scene().height_at([[0.0, 0.0, 0.0]]), r"xy must have shape \(M, 2\)"),
    (lambda: Scene().height_at([[np.nan, 0.0]]), "non-finite"),
    (lambda: Box((0, 0, 0), (1, 1, 1), material=1.3), r"albedo of Box.material must lie in \[0, 1\]"),
    (lambda: Stairs((0, 0), material=-0.1), "Stairs.material"),
    (lambda: Ramp((0, 0), material="carpet"), "Ramp.material must be a Uniform, a Texture or an albedo"),
    (lambda: Target((0, 0, 0), material=np.nan), "Target.material"),
    (lambda: HeightField(np.zeros((3, 3)), material=2), "HeightField.material"),
    (lambda: Scene(ground_material=1.5), "Scene.ground_material"),
])
def test_bad_scene_inputs_raise(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_bad_render_inputs_raise():
    scene = Scene.stairs_scene()
    T = camera_extrinsics((0.0, 0.0, 0.45), 30.0)
    for fn in (render_depth, render_depth_reference):
        with pytest.raises(ValueError, match="scene must be a Scene"):
            fn("stairs", K, W, H, T)
        with pytest.raises(ValueError, match="K must be a 3x3"):
            fn(scene, np.eye(2), W, H, T)
        with pytest.raises(ValueError, match="width must be an integer"):
            fn(scene, K, 81.5, H, T)
        with pytest.raises(ValueError, match="height must be in"):
            fn(scene, K, W, 0, T)
        with pytest.raises(ValueError, match="not orthonormal"):
            fn(scene, K, W, H, np.diag([2.0, 1.0, 1.0, 1.0]))
        with pytest.raises(ValueError, match="T_map_cam has non-finite"):
            fn(scene, K, W, H, np.full((4, 4), np.nan))
        with pytest.raises(ValueError, match="max_range_m"):
            fn(scene, K, W, H, T, max_range_m=-1.0)
    with pytest.raises(ValueError, match="nthreads"):
        render_depth(scene, K, W, H, T, nthreads=0)


def test_bad_noise_and_walk_inputs_raise(rng):
    z, th = render_planar_target(K, W, H, 1.0)
    with pytest.raises(ValueError, match="rng must be a numpy.random.Generator"):
        add_noise(z, th, None)
    with pytest.raises(ValueError, match="theta must have z_true's shape"):
        add_noise(z, th[:3], rng)
    with pytest.raises(ValueError, match="metres"):
        add_noise(z * 1000, th, rng)
    with pytest.raises(ValueError, match="radians"):
        add_noise(z, th + 30.0, rng)
    with pytest.raises(ValueError, match="theta must be finite"):
        add_noise(z, th * np.nan, rng)
    with pytest.raises(ValueError, match="floating-point metres"):
        add_noise((z * 1000).astype(np.uint16), th, rng)
    with pytest.raises(ValueError, match="depth_scale"):
        add_noise(z, th, rng, depth_scale=0.0)
    with pytest.raises(ValueError, match=r"effects\[0\] is not callable"):
        add_noise(z, th, rng, effects=["dropouts"])
    with pytest.raises(ValueError, match="model must be a SensorModel"):
        add_noise(z, th, rng, model="D435")
    with pytest.raises(ValueError, match="zero-length segment"):
        walk([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0]])
    with pytest.raises(ValueError, match="M >= 2"):
        walk([[0.0, 0.0]])
    with pytest.raises(ValueError, match="speed_mps"):
        walk([[0.0, 0.0], [1.0, 0.0]], speed_mps=0.0)
    with pytest.raises(ValueError, match="no terrain under pose 0"):
        walk([[0.0, 0.0], [1.0, 0.0]], scene=Scene([], ground_z=None))
    poses = walk([[0.0, 0.0], [1.0, 0.0]])
    with pytest.raises(ValueError, match="sigma_xy_per_m"):
        odometry_drift(poses, rng, sigma_xy_per_m=-0.1)
    with pytest.raises(ValueError, match="poses must have shape"):
        odometry_drift(poses[0], rng)
    bad = poses.copy()
    bad[3, 0, 0] = 2.0
    with pytest.raises(ValueError, match=r"poses\[3\] is not a rigid transform"):
        odometry_drift(bad, rng)
    scene = Scene.stairs_scene()
    with pytest.raises(ValueError, match="noise must be"):
        simulate_walk(scene, K, W, H, 3, rng=rng, noise="paper")
    with pytest.raises(ValueError, match="rng must be"):
        simulate_walk(scene, K, W, H, 3)
    with pytest.raises(ValueError, match="give n_frames, path, or both"):
        simulate_walk(scene, K, W, H, rng=rng)
    with pytest.raises(ValueError, match="n_frames"):
        simulate_walk(scene, K, W, H, 0, rng=rng)
