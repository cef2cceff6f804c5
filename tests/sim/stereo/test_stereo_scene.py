"""Materials, the dot projector and the imagers of the physical D435; numba kernels against NumPy references."""

import math

import numpy as np
import pytest

from noise_model.sim.stereo import imagers as I
from noise_model.sim.stereo import materials as MT
from noise_model.sim.stereo import projector as P

# ---------------------------------------------------------------------------------------------
# materials
# ---------------------------------------------------------------------------------------------


def test_fbm_matches_reference_and_is_bounded(rng):
    s = rng.uniform(-3.0, 3.0, size=(2000, 2))
    s[5] = np.nan
    s[7, 1] = np.inf
    a = MT.fbm(s, 0.016, 4, 0.5, seed=3, nthreads=1)
    b = MT.fbm_reference(s, 0.016, 4, 0.5, seed=3)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(a, MT.fbm(s, 0.016, 4, 0.5, seed=3, nthreads=2))
    assert np.isnan(a[5]) and np.isnan(a[7])
    ok = np.isfinite(a)
    assert np.abs(a[ok]).max() <= 1.0
    assert a[ok].std() > 0.1                                   # it is a texture, not a constant
    assert not np.allclose(a, MT.fbm(s, 0.016, 4, 0.5, seed=4), equal_nan=True)


def test_fbm_spectrum_follows_the_octaves():
    """Neighbouring samples 1/8 of the finest spacing apart agree; samples a coarse spacing apart do not."""
    x = np.arange(0.0, 4.0, 0.00025)
    s = np.stack([x, np.full_like(x, 0.3)], axis=1)
    f = MT.fbm(s, 0.016, 4, 0.5)
    lag = {k: np.corrcoef(f[:-k], f[k:])[0, 1] for k in (1, 64)}   # 0.25 mm and 16 mm
    assert lag[1] > 0.95 and abs(lag[64]) < 0.3


def test_triplanar_coordinates():
    p = np.array([[1.0, 2.0, 3.0]] * 3)
    n = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, -1.0, 0]])
    np.testing.assert_array_equal(MT.triplanar_coordinates(p, n), [[1, 2], [2, 3], [1, 3]])


def test_materials_validate_albedo():
    with pytest.raises(ValueError, match="albedo of paint"):
        MT.Uniform(1.2, "paint")
    with pytest.raises(ValueError, match="albedo of tar"):
        MT.Uniform(-0.1, "tar")
    with pytest.raises(ValueError, match="brightest point"):
        MT.Texture("shiny", mean=0.8, contrast=0.5, wavelength_m=0.01)
    with pytest.raises(ValueError, match="darkest point"):
        MT.Texture("dark", mean=0.2, contrast=0.9, wavelength_m=0.01, weave_period_m=0.004, weave_contrast=0.5)
    with pytest.raises(ValueError, match="wavelength_m"):
        MT.Texture("x", mean=0.5, contrast=0.1, wavelength_m=0.0)
    with pytest.raises(ValueError, match="region 0"):
        MT.MaterialMap(regions=(((0, 0, 0), (1, 1, 1), "wood"),))


def test_presets_stay_in_range(rng):
    p = rng.uniform(-2, 2, size=(5000, 3))
    n = np.tile([0.0, 0.0, 1.0], (5000, 1))
    for mat in (MT.concrete(), MT.carpet(), MT.white_wall()):
        a = mat.evaluate(p, n)
        assert np.all((a >= 0) & (a <= 1))
    a = MT.carpet().evaluate(p, n)
    assert abs(a.mean() - 0.22) < 0.02 and a.std() > 0.03


def test_texture_and_map_match_their_references(rng):
    p = rng.uniform(-2, 2, size=(3000, 3))
    p[:1000, 2] = 0.0                                           # on the ground
    p[10] = np.nan
    n = rng.normal(size=(3000, 3))
    n[20] = np.nan
    n[30] = [0.5, 0.5, 0.5]                                     # a tie: z wins
    for mat in (MT.concrete(), MT.carpet()):
        np.testing.assert_allclose(mat.evaluate(p, n, nthreads=1), mat.evaluate_reference(p, n), rtol=0,
                                   atol=1e-12, equal_nan=True)
        np.testing.assert_array_equal(mat.evaluate(p, n, nthreads=1), mat.evaluate(p, n, nthreads=2))
    mm = MT.MaterialMap(default=MT.carpet(), ground=MT.concrete(),
                        regions=(((-1.0, -1.0, -1.0), (0.0, 0.0, 1.0), MT.Uniform(0.7, "box")),))
    np.testing.assert_allclose(mm.evaluate(p, n), mm.evaluate_reference(p, n), rtol=0, atol=1e-12, equal_nan=True)
    only = MT.MaterialMap(default=MT.concrete(), ground=None)
    np.testing.assert_allclose(only.evaluate(p, n), only.evaluate_reference(p, n), rtol=0, atol=1e-12,
                               equal_nan=True)


def test_material_map_evaluates_each_material_at_its_own_points_only(rng):
    n = 3000
    p = rng.uniform([-1, -2, -0.1], [5, 2, 1.5], (n, 3))
    p[rng.random(n) < 0.4, 2] = 0.0                                   # on the ground plane
    p[::97] = np.nan
    nrm = rng.normal(size=(n, 3))
    box = ((2.5, 0.5, 0.0), (3.5, 1.5, 1.0), MT.Uniform(0.6, "crate"))
    mm = MT.MaterialMap(default=MT.carpet(), ground=MT.concrete(), regions=(box,))
    ground = np.isfinite(p).all(axis=1) & (np.abs(p[:, 2]) <= mm.ground_tol_m)
    crate = np.isfinite(p).all(axis=1) & np.all((p >= box[0]) & (p <= box[1]), axis=1)
    ground &= ~crate
    rest = np.isfinite(p).all(axis=1) & ~ground & ~crate
    for nthreads in (1, 2):
        got = mm.evaluate(p, nrm, nthreads)
        np.testing.assert_array_equal(got[ground], MT.concrete().evaluate(p[ground], nrm[ground]))   # to the bit
        np.testing.assert_array_equal(got[rest], MT.carpet().evaluate(p[rest], nrm[rest]))
        assert np.all(got[crate] == 0.6) and np.all(np.isnan(got[~np.isfinite(p).all(axis=1)]))


def test_material_codes_are_counted_as_bincount(rng):
    for n in (0, 5, 63, 64, 1000):
        code = rng.integers(-1, 4, n).astype(np.int32)
        want = np.bincount(code[code >= 0], minlength=4)
        for nthreads in (1, 2):
            with MT.threads(nthreads):
                np.testing.assert_array_equal(MT._count_codes(code, 4), want)


def test_material_map_assigns_by_position():
    mm = MT.MaterialMap(default=MT.Uniform(0.8, "wall"), ground=MT.Uniform(0.3, "floor"),
                        regions=(((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), MT.Uniform(0.1, "box")),))
    p = np.array([[0.5, 0.5, 0.5], [3.0, 0.0, 0.0005], [3.0, 0.0, 1.0], [0.5, 0.5, 0.0], [np.nan, 0, 0]])
    n = np.tile([0.0, 0.0, 1.0], (5, 1))
    np.testing.assert_array_equal(mm.evaluate(p, n)[:4], [0.1, 0.3, 0.8, 0.1])
    assert np.isnan(mm.evaluate(p, n)[4])


# ---------------------------------------------------------------------------------------------
# projector
# ---------------------------------------------------------------------------------------------


def test_dot_pattern_is_fixed_and_fills_the_field():
    pat = P.DotPattern()
    d1, p1 = pat.dots()
    d2, p2 = P.DotPattern().dots()
    np.testing.assert_array_equal(d1, d2)
    np.testing.assert_array_equal(p1, p2)
    assert d1.shape == (5000, 3) and np.allclose(np.linalg.norm(d1, axis=1), 1.0)
    assert abs(p1.sum() - pat.power_w) < 0.05 * pat.power_w
    a, b = d1[:, 0] / d1[:, 2], d1[:, 1] / d1[:, 2]
    a_max, b_max = pat.tangent_extent()
    assert np.abs(a).max() <= a_max and np.abs(b).max() <= b_max
    assert np.abs(a).max() > 0.95 * a_max and np.abs(b).max() > 0.95 * b_max
    assert not np.array_equal(d1, P.DotPattern(seed=1).dots()[0])


@pytest.mark.parametrize("bad", [dict(n_dots=0), dict(n_dots=-5), dict(dot_sigma_rad=0.0), dict(power_w=-1.0),
                                 dict(hfov_deg=180.0), dict(jitter=1.5)])
def test_dot_pattern_rejects_bad_values(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        P.DotPattern(**bad)


def random_surface(rng, n=400):
    pts = np.stack([rng.uniform(-0.9, 0.9, n), rng.uniform(-0.6, 0.6, n), np.ones(n)], axis=1)
    pts *= rng.uniform(0.3, 4.0, (n, 1))
    nrm = rng.normal(size=(n, 3))
    nrm[:, 2] = -np.abs(nrm[:, 2]) - 0.2                       # mostly facing the projector
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    pts[3] = np.nan
    pts[4, 2] = -1.0                                            # behind the projector
    nrm[5] = -nrm[5]                                            # a back face
    return pts, nrm


def test_irradiance_matches_reference(rng):
    proj = P.Projector(P.DotPattern(n_dots=300, dot_sigma_rad=0.02))
    pts, nrm = random_surface(rng)
    e = proj.irradiance(pts, nrm, nthreads=1)
    np.testing.assert_allclose(e, P.irradiance_reference(proj, pts, nrm), rtol=1e-9, atol=1e-12, equal_nan=True)
    np.testing.assert_array_equal(e, proj.irradiance(pts, nrm, nthreads=2))
    assert np.isnan(e[3]) and e[4] == 0.0 and (e[np.isfinite(e)] >= 0).all()
    assert (e > 0).sum() > 50


def test_irradiance_inverse_square_and_cosine():
    proj = P.Projector(P.DotPattern(n_dots=2000, dot_sigma_rad=0.05, power_spread=0.0))
    ray = proj._tables["dirs"][0]
    pts = np.stack([ray * 1.0, ray * 2.0, ray * 2.0])
    facing = -ray
    tilted = np.cross(ray, [0.0, 1.0, 0.0])
    tilted = -0.5 * ray + math.sqrt(0.75) * tilted / np.linalg.norm(tilted)   # 60 deg incidence
    nrm = np.stack([facing, facing, tilted])
    e = proj.irradiance(pts, nrm)
    assert e[0] == pytest.approx(4.0 * e[1], rel=1e-12)
    assert e[2] == pytest.approx(0.5 * e[1], rel=1e-12)


def test_shadows_from_a_depth_view_and_a_callable(rng):
    proj = P.Projector(P.DotPattern(n_dots=300, dot_sigma_rad=0.02))
    K = proj.view_intrinsics(40, 30)
    depth = np.full((30, 40), 2.0)
    depth[:, :20] = 1.0                                         # an occluder in the left half of the view
    depth[0, 39] = np.nan
    view = P.ProjectorView(depth, K)
    pts, nrm = random_surface(rng)
    lit = P.shadow_mask(pts, view)
    np.testing.assert_array_equal(lit, P.shadow_mask_reference(pts, view))
    e = proj.irradiance(pts, nrm, occlusion=view)
    np.testing.assert_allclose(e, P.irradiance_reference(proj, pts, nrm, view), rtol=1e-9, atol=1e-12, equal_nan=True)
    u = K[0, 0] * pts[:, 0] / pts[:, 2] + K[0, 2]
    far_left = np.isfinite(u) & (u < 18) & (u >= 0) & (pts[:, 2] > 1.2)
    assert far_left.any() and not lit[far_left].any()           # behind the occluder
    e2 = proj.irradiance(pts, nrm, occlusion=lambda q: np.zeros(len(q), bool))
    assert np.all((e2 == 0) | np.isnan(e2))
    with pytest.raises(ValueError, match="occlusion"):
        proj.irradiance(pts, nrm, occlusion=3)


def test_projector_geometry():
    proj = P.Projector(offset_m=0.025)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    np.testing.assert_allclose(proj.pose_in_map(T)[:3, 3], [1.025, 2.0, 3.0])
    K = proj.view_intrinsics(101, 61)
    a_max, b_max = proj.pattern.tangent_extent()
    assert K[0, 0] * a_max <= 50.0 + 1e-9 and K[1, 1] * b_max <= 30.0 + 1e-9


# ---------------------------------------------------------------------------------------------
# imagers
# ---------------------------------------------------------------------------------------------


def plane_depth(K, w, h, n, c):
    """z-depth of the plane n . X = c seen by a pinhole at the origin."""
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], axis=-1)
    return c / (ray @ n)


def test_surface_geometry_matches_reference_and_plane_normals(rng):
    K = np.array([[40.0, 0, 20.0], [0, 40.0, 15.0], [0, 0, 1]])
    n_true = np.array([0.3, -0.5, -0.8])
    n_true /= np.linalg.norm(n_true)
    z = plane_depth(K, 41, 31, -n_true, 1.5)
    z[10, 10:14] = np.nan
    z[20:, 30:] += 0.5                                          # a step: normals there from the near side
    z[0, 0] = np.nan
    pts, nrm = I.surface_geometry(z, K, nthreads=1)
    pr, nr = I.surface_geometry_reference(z, K)
    np.testing.assert_allclose(pts, pr, rtol=0, atol=1e-12, equal_nan=True)
    np.testing.assert_allclose(nrm, nr, rtol=0, atol=1e-9, equal_nan=True)
    np.testing.assert_array_equal(nrm, I.surface_geometry(z, K, nthreads=2)[1])
    inner = np.isfinite(z)
    inner[19:21, :] = False
    inner[:, 29:31] = False
    np.testing.assert_allclose(nrm[:18][inner[:18]], np.broadcast_to(n_true, nrm[:18][inner[:18]].shape), atol=1e-9)
    np.testing.assert_allclose(pts[..., 2], z, equal_nan=True)
    lone = np.full((3, 3), np.nan)
    lone[1, 1] = 2.0
    _, n1 = I.surface_geometry(lone, K)
    assert n1[1, 1] @ np.array([(1 - 20.0) / 40, (1 - 15.0) / 40, 1.0]) < 0   # faces the camera


def test_sample_intrinsics_keeps_pixel_centres():
    K = np.array([[400.0, 0, 100.0], [0, 400.0, 50.0], [0, 0, 1]])
    Ks = I.sample_intrinsics(K, 3)
    # the centre sample of pixel (u, v) is sample (3u + 1, 3v + 1) and looks along the pixel's own ray
    u, v = 37, 12
    assert ((3 * u + 1) - Ks[0, 2]) / Ks[0, 0] == pytest.approx((u - K[0, 2]) / K[0, 0])
    assert ((3 * v + 1) - Ks[1, 2]) / Ks[1, 1] == pytest.approx((v - K[1, 2]) / K[1, 1])


def test_signal_and_integration():
    m = I.ImagerModel()
    K = I.sample_intrinsics(np.array([[400.0, 0, 9.5], [0, 400.0, 4.5], [0, 0, 1]]), 2)
    albedo = np.full((10, 20), 0.5)
    E = np.full((10, 20), 0.1)
    E[0, 0] = np.nan
    r = I.signal_rate(albedo, E, K, 400.0, m)
    np.testing.assert_allclose(r, I.signal_rate_reference(albedo, E, K, 400.0, m), rtol=1e-12, atol=0)
    assert r[0, 0] == 0.0 and np.all(r[1:] > 0)
    photon = I.PLANCK_J_S * I.LIGHT_M_S / m.wavelength_m
    centre = m.quantum_efficiency * 0.5 * 0.1 / (4 * m.f_number ** 2) * m.pixel_area_m2(400.0) / photon
    assert r.max() == pytest.approx(centre, rel=1e-3)           # the sample nearest the axis
    img = I.integrate_samples(r, 2, 0.0)
    assert img.shape == (5, 10)
    assert img[2, 4] == pytest.approx(r[4:6, 8:10].mean())
    with pytest.raises(ValueError, match="multiple"):
        I.integrate_samples(np.zeros((5, 5)), 2, 0.0)


@pytest.mark.parametrize("s, blur", [(2, 0.23), (2, 0.0), (1, 0.9), (3, 0.5), (2, 2.5), (8, 0.3)])
def test_integration_equals_scipy_and_numpy_to_the_bit(rng, s, blur):
    r = rng.random((6 * s, 9 * s)) * 10.0 ** rng.integers(0, 8, (6 * s, 9 * s))    # values of very different size
    r[: s, : s] = 0.0
    ref = I.integrate_samples_reference(r, s, blur)
    np.testing.assert_array_equal(I.integrate_samples(r, s, blur, nthreads=1), ref)
    np.testing.assert_array_equal(I.integrate_samples(r, s, blur, nthreads=2), ref)
    wide = rng.random((2 * s, 37 * s))                           # one row of pixels, blur wider than the image
    np.testing.assert_array_equal(I.integrate_samples(wide, s, 3.0), I.integrate_samples_reference(wide, s, 3.0))
    with pytest.raises(ValueError, match="blur_sigma_px"):
        I.integrate_samples(r, s, float("nan"))


def test_signal_rate_with_a_scalar_irradiance_and_a_new_grid():
    m = I.ImagerModel(vignetting_power=4.0)
    K = I.sample_intrinsics(np.array([[300.0, 0, 7.5], [0, 300.0, 3.5], [0, 0, 1]]), 2)
    albedo = np.linspace(0.0, 1.0, 16 * 32).reshape(16, 32)
    albedo[3, 4] = np.nan
    ref = I.signal_rate_reference(albedo, 0.2, K, 300.0, m)
    for n in (1, 2):
        np.testing.assert_allclose(I.signal_rate(albedo, 0.2, K, 300.0, m, nthreads=n), ref, rtol=1e-12, atol=0)
    np.testing.assert_allclose(I.signal_rate(albedo, np.full(albedo.shape, 0.2), K, 300.0, m), ref, rtol=1e-12, atol=0)
    small = I.signal_rate(albedo[:8, :8], 0.2, K, 300.0, m)         # another grid size: its own field angles
    np.testing.assert_allclose(small, I.signal_rate_reference(albedo[:8, :8], 0.2, K, 300.0, m), rtol=1e-12)


def test_to_map_frame_and_the_move_into_the_projector_frame(rng):
    p = rng.normal(size=(500, 3))
    p[7] = np.nan
    n = rng.normal(size=(500, 3))
    a, b, c = 0.3, -1.1, 2.0
    R = (np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
         @ np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
         @ np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]]))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, (1.0, -2.0, 0.5)
    ref_p, ref_n = I.to_map_frame_reference(p.copy(), n, T)
    for nthreads in (1, 2):
        q = p.copy()
        got_p, got_n = I.to_map_frame(q, n, T, nthreads, shift_x_m=-0.025)
        np.testing.assert_allclose(got_p, ref_p, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got_n, ref_n, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(q[:, 0], p[:, 0] - 0.025)              # moved in place, after the transform
        np.testing.assert_array_equal(q[:, 1:], p[:, 1:])
    np.testing.assert_array_equal(I.to_map_frame(p, n, T)[0], got_p)          # without the move: p unchanged
    with pytest.raises(ValueError, match="in place"):
        I.to_map_frame(p.astype(np.float32), n, T, shift_x_m=0.1)


def test_irradiance_rate_cleans_like_nan_to_num(rng):
    e = rng.random((30, 40))
    e[3, 4], e[5, 6], e[7, 8] = np.nan, np.inf, -np.inf
    per = rng.random((30, 40)) * 1e3
    e_ref = e.copy()
    ref = I.irradiance_rate_reference(per, e_ref)
    for nthreads in (1, 2):
        got_e = e.copy()
        np.testing.assert_array_equal(I.irradiance_rate(per, got_e, nthreads), ref)
        np.testing.assert_array_equal(got_e, e_ref)
    assert ref[3, 4] == 0.0 and e_ref[3, 4] == 0.0
    with pytest.raises(ValueError, match="in place"):
        I.irradiance_rate(per, e.astype(np.float32))
    with pytest.raises(ValueError, match="shape"):
        I.irradiance_rate(per[:, :3], e)


def test_auto_exposure_and_expose(rng):
    m = I.ImagerModel()
    rate = np.full((20, 30), 1e5)
    ex = I.auto_exposure(rate, m)
    assert ex.gain == 1.0 and ex.time_s * 1e5 == pytest.approx(m.ae_target * m.full_well_e)
    dim = I.auto_exposure(rate * 1e-3, m)
    assert dim.time_s == m.max_exposure_s and dim.gain == m.max_gain
    assert I.auto_exposure(np.zeros((2, 2)), m) == (m.max_exposure_s, m.max_gain)
    manual = I.ImagerModel(exposure_s=0.01, gain=2.0)
    assert I.auto_exposure(rate, manual) == (0.01, 2.0)
    img = I.expose(rate, np.zeros_like(rate), ex, np.random.default_rng(1), m)
    assert img.dtype == np.uint8
    assert abs(img.mean() - (m.ae_target * 1023 + m.black_level_dn) / 4) < 1.0
    again = I.expose(rate, np.zeros_like(rate), ex, np.random.default_rng(1), m)
    np.testing.assert_array_equal(img, again)
    other = I.expose(rate, np.zeros_like(rate), ex, np.random.default_rng(2), m)
    assert not np.array_equal(img, other)                       # fresh noise per frame
    ten = I.expose(rate * 100, np.zeros_like(rate), ex, rng, I.ImagerModel(output_bits=10))
    assert ten.dtype == np.uint16 and ten.max() == 1023         # saturated
    spk = I.expose(np.zeros_like(rate), rate, ex, np.random.default_rng(1), m, speckle_contrast=0.4)
    assert spk.astype(float).std() > 2 * img.astype(float).std()


@pytest.mark.parametrize("kw", [dict(), dict(output_bits=10), dict(read_noise_e=0.0), dict(pointing_jitter_rad=0.0),
                                dict(exposure_s=0.02, gain=3.7, black_level_dn=0.0)])
def test_expose_equals_its_reference_to_the_bit(rng, kw):
    """The same draws and the same image as the NumPy passes: jitter, speckle, ambient, saturation, any thread count."""
    m = I.ImagerModel(**kw)
    proj = rng.random((23, 31)) * 10.0 ** rng.uniform(2, 6, (23, 31))
    amb = rng.random((23, 31)) * 1e4
    amb[:, :3] = 0.0
    proj[5, 5] = 1e12                                                       # saturates
    ex = I.auto_exposure(amb + proj, m) if m.exposure_s is None else I.Exposure(m.exposure_s, m.gain)
    for speckle, focal in ((0.4, 400.0), (0.0, None), (0.4, None)):
        ref = I.expose_reference(amb, proj, ex, np.random.default_rng(3), m, speckle, focal)
        for nthreads in (1, 2):
            got = I.expose(amb, proj, ex, np.random.default_rng(3), m, speckle, focal, nthreads)
            assert got.dtype == ref.dtype
            np.testing.assert_array_equal(got, ref)
    zero = I.expose(np.zeros_like(amb), proj, ex, np.random.default_rng(4), m, 0.4, 400.0)     # no ambient light
    np.testing.assert_array_equal(zero, I.expose_reference(np.zeros_like(amb), proj, ex, np.random.default_rng(4), m,
                                                           0.4, 400.0))


@pytest.mark.parametrize("bad", [dict(f_number=0.0), dict(quantum_efficiency=1.5), dict(output_bits=12),
                                 dict(supersample=0), dict(exposure_s=-1.0), dict(ae_target=1.0)])
def test_imager_rejects_bad_values(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        I.ImagerModel(**bad)
