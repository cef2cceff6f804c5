"""Process-noise prediction and the ellipse-weighted fused map, on hand-checkable 3 x 3 maps, and the
numba kernels against their NumPy references."""

import math

import numba
import numpy as np
import pytest

from conftest import random_pose_cov, random_transform
from elevmap import ElevationMap, FusionParams
from elevmap.map.layers import (
    ELEVATION, HVAR_X, HVAR_XY, HVAR_Y, LAYERS, POINTS, TIME, VARIANCE, ZERO_WHEN_UNKNOWN,
)
from elevmap.map.prediction import MIN_WEIGHT, fused_map, fused_map_reference, predict, predict_reference

IMPLS = ("numba", "numpy")


def small_map(**kw) -> ElevationMap:
    """3 x 3 cells of 1 m: cell centres x, y in {-0.5, 0.5, 1.5} (map index 0, 1, 2)."""
    return ElevationMap(length_m=3.0, resolution_m=1.0, **kw)


def set_cell(m, i, j, h, var, hx=0.3, hy=0.3, hxy=0.0):
    bi, bj = m.geometry.buffer_index([i, j])
    m.data[:, bi, bj] = np.nan
    m.data[[ELEVATION, VARIANCE, HVAR_X, HVAR_Y, HVAR_XY, POINTS, TIME], bi, bj] = (h, var, hx, hy, hxy, 10.0, 0.0)


def layer(m, name):
    return m.layer(name)


def Phi(x):
    return 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))


def cov6(t=None, r=None):
    C = np.zeros((6, 6))
    if t is not None:
        C[:3, :3] = t
    if r is not None:
        C[3:, 3:] = r
    return C


# ---------------------------------------------------------------------------------------------
# prediction by hand
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("impl", IMPLS)
def test_translation_only_adds_exactly_its_terms(impl):
    m = small_map()
    set_cell(m, 0, 0, 0.2, 1e-3, 0.30, 0.31, 0.01)
    set_cell(m, 2, 1, -0.1, 2e-3, 0.26, 0.27, -0.02)
    t = np.array([[0.010, 0.002, 0.003],
                  [0.002, 0.020, 0.001],
                  [0.003, 0.001, 0.005]])
    before = {k: layer(m, k) for k in LAYERS}
    out = m.predict(cov6(t=t), impl=impl)                      # no rotation terms: T_map_base not needed
    assert out == {"cells_expired": 0}
    for i, j in ((0, 0), (2, 1)):
        assert layer(m, "variance")[i, j] == pytest.approx(before["variance"][i, j] + 0.005, abs=1e-15)
        assert layer(m, "horizontal_variance_x")[i, j] == pytest.approx(before["horizontal_variance_x"][i, j] + 0.01)
        assert layer(m, "horizontal_variance_y")[i, j] == pytest.approx(before["horizontal_variance_y"][i, j] + 0.02)
        assert layer(m, "horizontal_variance_xy")[i, j] == pytest.approx(
            before["horizontal_variance_xy"][i, j] + 0.002, abs=1e-15)
        for k in ("elevation", "points", "time"):
            assert layer(m, k)[i, j] == before[k][i, j]
    unknown = ~m.is_known()
    assert unknown.sum() == 7
    assert np.all(np.isnan(layer(m, "variance")[unknown])) and np.all(layer(m, "points")[unknown] == 0)


@pytest.mark.parametrize("impl", IMPLS)
def test_yaw_grows_horizontal_variance_perpendicular_to_r(impl):
    # robot at (0.5, -0.5), i.e. above cell (1, 0); its orientation does not matter (map-frame covariance)
    m = small_map(fusion_params=FusionParams(max_horizontal_variance=10.0))
    for i in range(3):
        for j in range(3):
            set_cell(m, i, j, 0.1 * i, 1e-3, 0.3, 0.3, 0.0)
    T = np.eye(4)
    c, s = math.cos(0.7), math.sin(0.7)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (0.5, -0.5, 0.4)
    s2 = 0.01                                                  # sigma_yaw^2 [rad^2]
    m.predict(cov6(r=np.diag([0.0, 0.0, s2])), T_map_base=T, impl=impl)
    hx, hy, hxy = (layer(m, f"horizontal_variance_{k}") for k in ("x", "y", "xy"))
    # cell (2, 0) at (1.5, -0.5): r = (1, 0) -> y variance + 1 * s2, x unchanged
    assert hx[2, 0] == pytest.approx(0.3) and hy[2, 0] == pytest.approx(0.3 + s2) and hxy[2, 0] == pytest.approx(0.0)
    # cell (1, 2) at (0.5, 1.5): r = (0, 2) -> x variance + 4 s2
    assert hx[1, 2] == pytest.approx(0.3 + 4 * s2) and hy[1, 2] == pytest.approx(0.3)
    # cell (1, 0) under the robot: r = 0, nothing changes
    assert (hx[1, 0], hy[1, 0], hxy[1, 0]) == pytest.approx((0.3, 0.3, 0.0))
    # cell (2, 2) at (1.5, 1.5): r = (1, 2), |r|^2 = 5; increment s2 [[4, -2], [-2, 1]]
    d = np.array([[hx[2, 2] - 0.3, hxy[2, 2]], [hxy[2, 2], hy[2, 2] - 0.3]])
    np.testing.assert_allclose(d, s2 * np.array([[4.0, -2.0], [-2.0, 1.0]]), atol=1e-15)
    r = np.array([1.0, 2.0])
    perp = np.array([-2.0, 1.0]) / math.sqrt(5.0)
    np.testing.assert_allclose(d @ r, 0.0, atol=1e-15)               # no growth along r
    assert perp @ d @ perp == pytest.approx(5.0 * s2)                 # r^2 sigma_yaw^2 across r
    # yaw moves nothing vertically
    np.testing.assert_allclose(layer(m, "variance"), 1e-3)


@pytest.mark.parametrize("impl", IMPLS)
def test_roll_and_pitch_add_height_variance_at_their_lever_arm(impl):
    m = small_map()
    for i in range(3):
        for j in range(3):
            set_cell(m, i, j, 0.0, 1e-3)
    T = np.eye(4)
    T[:3, 3] = (0.5, 0.5, 0.3)                                 # above the centre cell (1, 1)
    sa, sb = 1e-4, 4e-4                                        # roll, pitch variances [rad^2]
    m.predict(cov6(r=np.diag([sa, sb, 0.0])), T_map_base=T, impl=impl)
    v = layer(m, "variance")
    # dz = alpha ry - beta rx
    assert v[1, 1] == pytest.approx(1e-3)
    assert v[2, 1] == pytest.approx(1e-3 + 1.0 * sb)           # r = (1, 0): pitch only
    assert v[1, 0] == pytest.approx(1e-3 + 1.0 * sa)           # r = (0, -1): roll only
    assert v[0, 2] == pytest.approx(1e-3 + sa + sb)            # r = (-1, 1)
    np.testing.assert_allclose(layer(m, "horizontal_variance_x"), 0.3)   # roll/pitch: no horizontal term


def test_time_based_growth():
    m = ElevationMap(length_m=3.0, resolution_m=1.0, fusion_params=FusionParams(min_points=1))
    m.update(np.array([[0.5, 0.5, 0.2], [1.5, -0.5, 0.1]]), np.array([1e-3, 2e-3]), stamp=0.0)
    v0 = m.layer("variance")
    m.predict(dt=2.0, time_variance_rate=1e-3)
    np.testing.assert_allclose(m.layer("variance"), v0 + 2e-3, equal_nan=True)
    m.predict(dt=None, time_variance_rate=1e-3)               # no dt: no growth
    m.predict(dt=0.0, time_variance_rate=5.0)
    np.testing.assert_allclose(m.layer("variance"), v0 + 2e-3, equal_nan=True)
    assert m.is_known().sum() == 2


@pytest.mark.parametrize("impl", IMPLS)
def test_variance_above_max_makes_the_cell_unknown(impl):
    m = small_map()                                            # max_variance 0.04
    set_cell(m, 0, 0, 0.5, 0.039)
    set_cell(m, 1, 1, 0.2, 0.010)
    out = m.predict(cov6(t=np.diag([0.0, 0.0, 0.002])), impl=impl)
    assert out == {"cells_expired": 1}
    L = m.layers()
    for name in LAYERS:
        if name in ZERO_WHEN_UNKNOWN:
            assert L[name][0, 0] == 0.0
        else:
            assert np.isnan(L[name][0, 0]), name
    assert L["elevation"][1, 1] == 0.2 and L["variance"][1, 1] == pytest.approx(0.012)
    # a cell whose variance is NaN (corrupt) is dropped too
    set_cell(m, 2, 2, 0.0, np.nan)
    assert m.predict(impl=impl) == {"cells_expired": 1}
    assert not m.is_known()[2, 2]


@pytest.mark.parametrize("impl", IMPLS)
def test_clamping_below_min_and_horizontal_bounds(impl):
    m = small_map(fusion_params=FusionParams(min_variance=1e-4))   # min_h = (1/2)^2, max_h = 0.5
    set_cell(m, 0, 0, 0.0, 1e-6, 0.01, 2.0, 0.9)
    set_cell(m, 2, 2, 0.0, 1e-3, np.nan, 0.3, np.nan)
    set_cell(m, 1, 2, 0.0, 1e-3, 0.3, 0.4, -0.2)
    m.predict(impl=impl)
    v, hx, hy, hxy = (layer(m, k) for k in ("variance", "horizontal_variance_x", "horizontal_variance_y",
                                            "horizontal_variance_xy"))
    assert v[0, 0] == 1e-4 and v[2, 2] == 1e-3
    assert hx[0, 0] == 0.25 and hy[0, 0] == 0.5
    assert hxy[0, 0] == pytest.approx(math.sqrt(0.25 * 0.5))    # |xy| <= sqrt(x y): stays PSD
    assert (hx[2, 2], hy[2, 2], hxy[2, 2]) == (0.25, 0.3, 0.0)  # NaN -> fresh-cell values
    assert (hx[1, 2], hy[1, 2], hxy[1, 2]) == (0.3, 0.4, -0.2)  # inside the bounds: untouched


# ---------------------------------------------------------------------------------------------
# prediction: numba == reference, thread count
# ---------------------------------------------------------------------------------------------
def random_map(rng, n=17, res=0.1, nthreads=None, known=0.7, **fp):
    centre = rng.uniform(-3.0, 3.0, 2)                         # off-origin: the buffer wraps
    m = ElevationMap(length_m=n * res, resolution_m=res, centre_xy=centre, nthreads=nthreads,
                     fusion_params=FusionParams(**fp) if fp else None)
    shape = (n, n)
    k = rng.random(shape) < known
    d = m.data
    d[ELEVATION] = np.where(k, rng.normal(0.0, 0.3, shape), np.nan)
    d[VARIANCE] = np.where(k, rng.uniform(1e-6, 0.045, shape), np.nan)       # some above max already
    for layer_ in (HVAR_X, HVAR_Y):
        d[layer_] = np.where(k, rng.uniform(0.0, 0.6, shape), np.nan)         # some out of bounds
    d[HVAR_XY] = np.where(k, rng.normal(0.0, 0.05, shape), np.nan)
    d[HVAR_X][k & (rng.random(shape) < 0.05)] = np.nan
    d[TIME] = np.where(k, 1.0, np.nan)
    d[POINTS] = np.where(k, 3.0, 0.0)
    return m


def same(a, b, rtol=1e-12):
    np.testing.assert_allclose(a, b, rtol=rtol, atol=1e-15, equal_nan=True)


@pytest.mark.parametrize("seed", range(4))
def test_predict_numba_equals_reference(seed):
    rng = np.random.default_rng(seed)
    a = random_map(rng)
    b = ElevationMap(length_m=a.length_m, resolution_m=a.resolution_m, centre_xy=a.centre_xy)
    b.data[:] = a.data
    C = random_pose_cov(rng, sigma_t=0.02, sigma_r=0.02)
    T = random_transform(rng, translation_scale=1.0)
    T[:2, 3] += a.centre_xy
    kw = dict(relative_pose_cov=C, T_map_base=T, dt=0.1, time_variance_rate=1e-3)
    ra, rb = predict(a, **kw), predict_reference(b, **kw)
    assert ra == rb and ra["cells_expired"] > 0
    same(a.data, b.data)
    # no arguments: clamping only
    ra, rb = predict(a), predict_reference(b)
    assert ra == rb
    same(a.data, b.data)


def test_predict_same_with_one_and_two_threads(rng):
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread")
    a = random_map(rng, n=33, nthreads=1)
    b = ElevationMap(length_m=a.length_m, resolution_m=a.resolution_m, centre_xy=a.centre_xy, nthreads=2)
    b.data[:] = a.data
    C = random_pose_cov(rng)
    T = random_transform(rng)
    assert a.predict(C, T, 0.5, 1e-3) == b.predict(C, T, 0.5, 1e-3)
    np.testing.assert_array_equal(a.data, b.data)


# ---------------------------------------------------------------------------------------------
# fused map
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("impl", IMPLS)
def test_fused_weights_by_hand_on_3x3(impl):
    m = small_map()                                   # min_h = (res/2)^2 = 0.25: sigma 0.5 m, isotropic
    heights = np.array([[1.0, 1.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0]])
    for i in range(3):
        for j in range(3):
            set_cell(m, i, j, heights[i, j], 1e-4, 0.25, 0.25, 0.0)
    f = m.fused_map(impl=impl)
    # half-axes 2.486 * 0.5 + sqrt(2) / 2 = 1.950 m: from the centre, all 9 cells (corners at 1.414 m)
    centre = (Phi(1.0) - Phi(-1.0)) ** 2                      # |du| = |dv| = 0: Phi(+-0.5 / 0.5)
    edge = (Phi(3.0) - Phi(1.0)) * (Phi(1.0) - Phi(-1.0))    # |du| = 1: Phi((1 +- 0.5) / 0.5)
    corner = (Phi(3.0) - Phi(1.0)) ** 2
    assert (centre, edge, corner) == pytest.approx((0.466065, 0.107391, 0.024745), abs=1e-6)
    mean = (4 * edge + 4 * corner) * 1.0 / (centre + 4 * edge + 4 * corner)
    assert f["elevation"][1, 1] == pytest.approx(mean, rel=1e-12)
    assert mean == pytest.approx(0.531409, abs=1e-6)
    # two distinct values h -/+ 2 sigma = {-0.02, 0.98} / {0.02, 1.02}: EM's ECDF puts them at P = 0 and 1
    assert f["lower_bound"][1, 1] == pytest.approx(-0.02 + 0.01 * 1.0)
    assert f["upper_bound"][1, 1] == pytest.approx(0.02 + 0.99 * 1.0)
    assert f["uncertainty_range"][1, 1] == pytest.approx(1.02)
    # corner cell (0, 0): neighbours (1, 0), (0, 1) at 1 m and (1, 1) at 1.414 m; (2, 0) at 2 m > 1.95 m
    w = np.array([centre, edge, edge, corner])
    h = np.array([1.0, 1.0, 1.0, 0.0])
    assert f["elevation"][0, 0] == pytest.approx(w @ h / w.sum(), rel=1e-12)


@pytest.mark.parametrize("impl", IMPLS)
def test_fused_weights_anisotropic_by_hand(impl):
    # sigma_y = 1 m > sigma_x = 0.5 m: the major axis is y (phi = 90 deg); half-axes 3.19 m (y), 1.95 m (x)
    m = small_map()
    for i in range(3):
        for j in range(3):
            set_cell(m, i, j, float(j == 2), 1e-4, 0.25 if (i, j) == (1, 1) else 0.3, 1.0 if (i, j) == (1, 1) else 0.3)
    f = m.fused_map(impl=impl)
    ax = {0: Phi(1.0) - Phi(-1.0), 1: Phi(3.0) - Phi(1.0)}          # sigma 0.5 across, |dx| in {0, 1}
    ay = {0: Phi(0.5) - Phi(-0.5), 1: Phi(1.5) - Phi(0.5)}          # sigma 1 along y, |dy| in {0, 1}
    num = den = 0.0
    for i in range(3):
        for j in range(3):
            w = ax[abs(i - 1)] * ay[abs(j - 1)]
            num += w * float(j == 2)
            den += w
    assert f["elevation"][1, 1] == pytest.approx(num / den, rel=1e-12)


@pytest.mark.parametrize("impl", IMPLS)
def test_fused_weights_of_a_diagonal_ellipse(impl):
    # [[0.5, 0.4], [0.4, 0.5]]: lambda 0.9 along (1, 1), 0.1 along (1, -1); half-axes 3.07 m, 1.49 m
    m = small_map()
    for i in range(3):
        for j in range(3):
            h = 1.0 if (i, j) in ((0, 0), (2, 2)) else (-1.0 if (i, j) in ((0, 2), (2, 0)) else 0.0)
            set_cell(m, i, j, h, 1e-4)
    set_cell(m, 1, 1, 0.0, 1e-4, 0.5, 0.5, 0.4)
    f = m.fused_map(impl=impl)
    s1, s2 = math.sqrt(0.9), math.sqrt(0.1)
    num = den = 0.0
    for i in range(3):
        for j in range(3):
            u = abs((i - 1) + (j - 1)) / math.sqrt(2.0)          # offset along the major axis
            v = abs((j - 1) - (i - 1)) / math.sqrt(2.0)          # along the minor axis
            w = (Phi((u + 0.5) / s1) - Phi((u - 0.5) / s1)) * (Phi((v + 0.5) / s2) - Phi((v - 0.5) / s2))
            num += w * m.layer("elevation")[i, j]
            den += w
    assert f["elevation"][1, 1] == pytest.approx(num / den, rel=1e-12)
    assert f["elevation"][1, 1] > 0.05          # cells along the major axis (h = +1) weigh more


@pytest.mark.parametrize("impl", IMPLS)
def test_fused_equals_raw_with_minimal_horizontal_variance(impl, rng):
    m = ElevationMap(length_m=1.5, resolution_m=0.1, fusion_params=FusionParams(min_horizontal_variance=1e-6))
    pts = np.column_stack([rng.uniform(-0.75, 0.75, (400, 2)), rng.normal(0.0, 0.2, 400)])
    m.update(pts, np.full(400, 1e-4))
    f = m.fused_map(impl=impl)
    h, v = m.known_layer("elevation"), m.known_layer("variance")     # cells below min_points: unknown
    np.testing.assert_array_equal(f["elevation"], h)            # the ellipse holds the cell only
    np.testing.assert_allclose(f["lower_bound"], h - 2 * np.sqrt(v), equal_nan=True, rtol=1e-15)
    np.testing.assert_allclose(f["upper_bound"], h + 2 * np.sqrt(v), equal_nan=True, rtol=1e-15)
    assert np.isnan(h).sum() > 0 and np.array_equal(np.isnan(f["elevation"]), np.isnan(h))


@pytest.mark.parametrize("impl", IMPLS)
def test_fused_smooths_a_step_under_horizontal_uncertainty(impl):
    m = ElevationMap(length_m=2.0, resolution_m=0.1)              # 20 x 20, x in [-1, 1)
    xs, ys = m.cell_centres()
    n = m.n
    for i in range(n):
        for j in range(n):
            if (i, j) in ((10, 3), (9, 16)):
                continue                                            # holes
            set_cell(m, i, j, 0.3 if xs[i] > 0 else 0.0, 1e-4, 0.01, 0.01, 0.0)   # sigma_xy = 0.1 m
    raw = m.layer("elevation")
    f = m.fused_map(impl=impl)
    e = f["elevation"]
    known = np.isfinite(raw)
    assert np.array_equal(np.isfinite(e), known)
    low, high = xs <= 0, xs > 0
    edge_lo, edge_hi = np.flatnonzero(low)[-1], np.flatnonzero(high)[0]
    assert np.all(e[edge_lo, 6:14] > 0.02) and np.all(e[edge_hi, 6:14] < 0.28)   # smoothed at the step
    assert np.all(np.diff(e[:, 8]) >= -1e-12)                                    # still monotone across it
    # ellipse half-axis 2.486 * 0.1 + 0.0707 = 0.32 m: cells 4 rows away are untouched
    np.testing.assert_allclose(e[: edge_lo - 3], 0.0, atol=1e-12)
    np.testing.assert_allclose(e[edge_hi + 4:], 0.3, atol=1e-12)
    lo, hi = f["lower_bound"], f["upper_bound"]
    assert np.all(lo[known] <= e[known]) and np.all(e[known] <= hi[known])
    np.testing.assert_allclose(f["uncertainty_range"][known], (hi - lo)[known])
    assert m.layer("elevation") is not raw and np.array_equal(m.layer("elevation"), raw, equal_nan=True)


@pytest.mark.parametrize("seed", range(3))
def test_fused_numba_equals_reference(seed):
    rng = np.random.default_rng(100 + seed)
    m = random_map(rng, n=15, res=0.1, min_horizontal_variance=1e-4, max_horizontal_variance=0.05)
    predict(m)                                                      # bring layers into their bounds
    # an anisotropic, rotated covariance in some cells
    d = m.data
    k = np.isfinite(d[ELEVATION]) & (rng.random(d[ELEVATION].shape) < 0.5)
    d[HVAR_X][k] = rng.uniform(1e-4, 0.05, k.sum())
    d[HVAR_Y][k] = rng.uniform(1e-4, 0.05, k.sum())
    d[HVAR_XY][k] = rng.uniform(-0.9, 0.9, k.sum()) * np.sqrt(d[HVAR_X][k] * d[HVAR_Y][k])
    a, b = fused_map(m), fused_map_reference(m)
    for name in a:
        same(a[name], b[name], rtol=1e-10)
    assert np.isfinite(a["elevation"]).sum() == np.isfinite(m.layer("elevation")).sum()


def test_fused_same_with_one_and_two_threads(rng):
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread")
    m = random_map(rng, n=25, res=0.05, max_horizontal_variance=0.02)
    predict(m)
    m.nthreads = 1
    a = m.fused_map()
    m.nthreads = 2
    b = m.fused_map()
    for name in a:
        np.testing.assert_array_equal(a[name], b[name])


def test_min_weight_is_em_value():
    assert MIN_WEIGHT == pytest.approx(2 * 1.1920929e-07)


# ---------------------------------------------------------------------------------------------
# bad inputs
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("impl", IMPLS)
def test_bad_inputs_raise_naming_the_problem(impl):
    m = small_map()
    set_cell(m, 1, 1, 0.0, 1e-3)
    before = m.data.copy()
    bad = cov6(t=np.diag([1e-3, 1e-3, 1e-3]))
    bad[0, 1] = bad[1, 0] = 5e-3                                       # |xy| > sqrt(xx yy)
    with pytest.raises(ValueError, match="relative_pose_cov is not positive semi-definite"):
        m.predict(bad, impl=impl)
    with pytest.raises(ValueError, match="relative_pose_cov must be a 6x6"):
        m.predict(np.eye(3), impl=impl)
    T = np.eye(4)
    T[0, 0] = 2.0
    with pytest.raises(ValueError, match="T_map_base rotation part is not orthonormal"):
        m.predict(cov6(r=np.diag([0, 0, 1e-3])), T_map_base=T, impl=impl)
    with pytest.raises(ValueError, match="T_map_base rotation part is a reflection"):
        m.predict(T_map_base=np.diag([1.0, 1.0, -1.0, 1.0]), impl=impl)
    with pytest.raises(ValueError, match="T_map_base .* is required"):
        m.predict(cov6(r=np.diag([0, 0, 1e-3])), impl=impl)
    with pytest.raises(ValueError, match="dt must be finite and >= 0"):
        m.predict(dt=-0.1, time_variance_rate=1e-3, impl=impl)
    with pytest.raises(ValueError, match="time_variance_rate must be finite and >= 0"):
        m.predict(dt=0.1, time_variance_rate=-1.0, impl=impl)
    with pytest.raises(ValueError, match="rad\\^2"):
        m.predict(cov6(r=np.diag([0, 0, 25.0])), T_map_base=np.eye(4), impl=impl)
    np.testing.assert_array_equal(m.data, before)                     # nothing was changed
    with pytest.raises(ValueError, match="impl must be"):
        m.predict(impl="cuda")
    with pytest.raises(ValueError, match="impl must be"):
        m.fused_map(impl="cuda")
