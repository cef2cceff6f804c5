"""The elevation map: indexing, fusion and moves on tiny hand-checkable maps, and the behaviours a
legged robot depends on (convergence, outliers, terrain change), numba against the NumPy reference."""

import dataclasses
import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from elevmap import ElevationMap, FusionParams
from elevmap.map.grid import GridGeometry
from elevmap.map.layers import LAYERS


def small_map(**kw) -> ElevationMap:
    """3 x 3 cells of 1 m centred on the origin's cell: x and y in [-1, 2)."""
    return ElevationMap(length_m=3.0, resolution_m=1.0, **kw)


def test_tiny_map_indexing_by_hand():
    m = small_map()
    g = m.geometry
    assert (g.n, g.gx0, g.gy0) == (3, -1, -1)
    np.testing.assert_allclose(g.centre_xy, [0.5, 0.5])
    xs, ys = m.cell_centres()
    np.testing.assert_allclose(xs, [-0.5, 0.5, 1.5])
    ij, inside = g.map_index(np.array([[0.2, -0.7], [1.999, 1.0], [2.0, 0.0], [-1.0, -1.0], [-1.0001, 0.0]]))
    assert ij[:2].tolist() == [[1, 0], [2, 2]] and ij[3].tolist() == [0, 0]
    assert inside.tolist() == [True, True, False, True, False]        # borders belong to the cell above
    assert g.buffer_index([[0, 0], [2, 1]]).tolist() == [[2, 2], [1, 0]]   # (gx mod 3, gy mod 3)


def test_fusion_by_hand():
    m = small_map(fusion_params=FusionParams(max_variance=10.0))
    m.update(np.array([[0.5, 0.5, 1.0], [0.6, 0.4, 2.0]]), np.array([1.0, 1.0]), stamp=3.0)
    h, v = m.layer("elevation"), m.layer("variance")
    assert h[1, 1] == pytest.approx(1.5) and v[1, 1] == pytest.approx(0.5)
    assert m.layer("min_height")[1, 1] == 1.0 and m.layer("max_height")[1, 1] == 2.0
    assert m.layer("points")[1, 1] == 2 and m.layer("time")[1, 1] == 3.0
    assert np.isnan(h[0, 0]) and m.layer("points")[0, 0] == 0
    # a second frame combines once with the prior: (1.5 / 0.5 + 1.5 / 0.5) / (1 / 0.5 + 1 / 0.5)
    m.update(np.array([[0.5, 0.5, 1.5]]), np.array([0.5]), stamp=4.0)
    assert m.layer("elevation")[1, 1] == pytest.approx(1.5) and m.layer("variance")[1, 1] == pytest.approx(0.25)


def test_one_frame_is_order_independent_and_equals_sequential_kalman(rng):
    z = rng.normal(0.3, 0.01, 50)
    var = rng.uniform(1e-4, 4e-4, 50)
    pts = np.column_stack([np.full(50, 0.5), np.full(50, 0.5), z])
    pure = FusionParams(min_variance=1e-12, spread_alpha=None)      # the Kalman update alone
    a, b = small_map(fusion_params=pure), small_map(fusion_params=pure)
    a.update(pts, var)
    perm = rng.permutation(50)
    b.update(pts[perm], var[perm])
    np.testing.assert_allclose(a.layer("elevation")[1, 1], b.layer("elevation")[1, 1], rtol=1e-13)
    h, v = z[0], var[0]                                   # sequential 1-D Kalman updates
    for zi, vi in zip(z[1:], var[1:]):
        k = v / (v + vi)
        h, v = h + k * (zi - h), (1 - k) * v
    assert a.layer("elevation")[1, 1] == pytest.approx(h, rel=1e-12)
    assert a.layer("variance")[1, 1] == pytest.approx(v, rel=1e-12)


def test_static_ground_converges_with_the_information_form_variance(rng):
    m = ElevationMap(2.0, 0.1, fusion_params=FusionParams(min_variance=1e-12))
    info = np.zeros((20, 20))
    for f in range(30):
        pts = np.column_stack([rng.uniform(-1, 1, 4000), rng.uniform(-1, 1, 4000), rng.normal(0.0, 0.02, 4000)])
        var = np.full(4000, 0.02 ** 2)
        m.update(pts, var, stamp=f)
        ij, inside = m.geometry.map_index(pts[:, :2])
        np.add.at(info, (ij[inside, 0], ij[inside, 1]), 1.0 / var[inside])
    v, spread = m.layer("variance"), m.layer("spread")
    # the variance of the fused mean is the information form's; the spreads (DerSimonian-Laird tau^2,
    # within the cell and over its neighbours) are the noise of their moment estimates only, for these
    # points follow their model exactly (points of a cell with spread > 0 are weighted
    # 1/(sigma^2 + tau^2): a little less information)
    ratio = (v - np.maximum(spread, m.layer("neighbour_spread"))) * info
    assert ratio.min() > 0.95 and np.median(ratio) < 1.1 and ratio.max() < 1.5
    assert np.all(spread >= 0) and np.sqrt(np.median(spread)) < 0.2 * 0.02
    h = m.layer("elevation")
    assert np.abs(h).max() < 5 * np.sqrt(v.max())          # the truth is 0
    assert abs(np.mean(h / np.sqrt(v - spread))) < 0.2     # unbiased: normalised errors centred on 0
    assert np.mean(np.abs(h) <= 2 * np.sqrt(v)) >= 0.95    # covered


def confident_cell_map():
    m = small_map()
    rng = np.random.default_rng(0)
    for f in range(5):
        m.update(np.column_stack([np.full(200, 0.5), np.full(200, 0.5), rng.normal(0, 0.005, 200)]),
                 np.full(200, 0.005 ** 2), stamp=f)
    return m


def test_a_single_outlier_does_not_move_a_confident_cell():
    m = confident_cell_map()
    before = m.layer("elevation")[1, 1]
    m.update(np.array([[0.5, 0.5, 0.8]]), np.array([0.005 ** 2]), stamp=10)
    assert abs(m.layer("elevation")[1, 1] - before) < 1e-3
    m.update(np.array([[0.5, 0.5, 0.8], [0.5, 0.5, 0.001]]), np.array([0.005 ** 2, 0.005 ** 2]), stamp=11)
    assert abs(m.layer("elevation")[1, 1] - before) < 1e-3


@pytest.mark.parametrize("step", [0.03, 0.3])
def test_a_box_put_down_appears_within_five_frames(step):
    m = confident_cell_map()
    rng = np.random.default_rng(1)
    for f in range(5):
        m.update(np.column_stack([np.full(100, 0.5), np.full(100, 0.5), step + rng.normal(0, 0.005, 100)]),
                 np.full(100, 0.005 ** 2), stamp=20 + f)
    assert m.layer("elevation")[1, 1] == pytest.approx(step, abs=0.003)
    assert m.layer("min_height")[1, 1] > step - 0.05 or step < 0.05


@pytest.mark.parametrize("impl", ["numba", "numpy"])
def test_a_frame_that_looks_like_a_change_does_not_move_the_cell_at_once(impl):
    """A confident cell at 0 (1000 points); one frame brings 11 points at +6 cm with sigma 1.5 cm,
    rejected by the gate, and 3 at +5 cm with sigma 5 cm, inside it (the lower image border's
    too-near pixels). The change rule inflates the cell's variance by the squared distance to the
    rejected mean, (6 cm)^2, so that the next frame's points pass the gate, but only after this frame's
    accepted points are fused with the prior as it was: the height moves by under a millimetre
    (inflating first let the 3 points pull it to +5 cm). Two more such frames carry it over."""
    m = confident_cell_map()
    h0 = m.layer("elevation")[1, 1]
    xy = np.full((14, 2), 0.5)
    z = np.r_[np.full(11, 0.06), np.full(3, 0.05)]
    var = np.r_[np.full(11, 0.015 ** 2), np.full(3, 0.05 ** 2)]
    m.update(np.column_stack([xy, z]), var, stamp=10, impl=impl)
    assert abs(m.layer("elevation")[1, 1] - h0) < 1e-3
    assert m.layer("variance")[1, 1] >= (0.06 - h0) ** 2
    for f in range(2):
        m.update(np.column_stack([xy, z]), var, stamp=11 + f, impl=impl)
    assert m.layer("elevation")[1, 1] == pytest.approx(0.058, abs=0.005)


def test_information_cap_limits_what_one_frame_adds():
    var = 0.01 ** 2
    pts = np.column_stack([np.full(400, 0.5), np.full(400, 0.5), np.zeros(400)])
    capped = small_map(fusion_params=FusionParams(max_points_per_frame=10, min_variance=1e-12))
    capped.update(pts, np.full(400, var))
    assert capped.layer("variance")[1, 1] == pytest.approx(var / 10)
    free = small_map(fusion_params=FusionParams(min_variance=1e-12))
    free.update(pts, np.full(400, var))
    assert free.layer("variance")[1, 1] == pytest.approx(var / 400)


def test_variance_above_max_leaves_the_cell_unknown_and_min_clamps():
    m = small_map(fusion_params=FusionParams(max_variance=0.01, min_variance=1e-4))
    m.update(np.array([[0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]]), np.array([0.02, 1e-9]))
    assert np.isnan(m.layer("elevation")[1, 1]) and m.layer("points")[1, 1] == 0
    assert m.layer("variance")[0, 1] == 1e-4


def test_move_by_hand_with_wrap_around():
    m = small_map()
    xs, ys = m.cell_centres()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    m.update(np.column_stack([X.ravel(), Y.ravel(), 10 * X.ravel() + Y.ravel()]), np.full(9, 1e-4))
    before = m.layer("elevation")                       # h = 10 x + y at each cell centre
    out = m.move_to((1.4, 0.2))                         # one cell along +x: the x = -0.5 row leaves
    assert out["shift_cells"] == (1, 0) and out["cleared_rows"] == 1
    after = m.layer("elevation")
    np.testing.assert_allclose(after[:2], before[1:])  # kept cells: same values, shifted map index
    assert np.all(np.isnan(after[2]))                   # the new row at x = 2.5 is unknown
    xs2, ys2 = m.cell_centres()
    np.testing.assert_allclose(after[:2], 10 * xs2[:2, None] + ys2[None, :])
    m.move_to((-1.6, -2.8))                             # more than n cells on y: all unknown
    assert not m.is_known().any()


def test_move_there_and_back_keeps_what_stayed_in_view():
    m = ElevationMap(1.0, 0.1)
    pts = np.column_stack([np.random.default_rng(0).uniform(-0.5, 0.5, (500, 2)), np.ones(500)])
    m.update(pts, np.full(500, 1e-4))
    known = m.is_known().sum()
    m.move_to((0.3, -0.2))
    m.move_to((0.0, 0.0))
    assert m.is_known().sum() == pytest.approx(known * 0.7 * 0.8, rel=0.15)
    assert np.allclose(m.layer("elevation")[m.is_known()], 1.0)


def random_frame(rng, n, spread=2.5):
    pts = np.column_stack([rng.uniform(-spread, spread, n), rng.uniform(-spread, spread, n), rng.normal(0, 0.02, n)])
    pts[: n // 10, :2] = np.round(pts[: n // 10, :2] * 10) / 10            # exactly on cell borders
    pts[n // 10: n // 5, 2] += rng.choice([0.3, 5.0], n // 10)               # steps and outliers
    return pts, rng.uniform(1e-4, 1e-3, n), rng.uniform(1e-5, 1e-3, (n, 3)) * np.array([1, 0.01, 1])


@pytest.mark.parametrize("cap, stride", [(None, 1), (4.0, 3)])
def test_numba_equals_reference_over_frames_and_moves(cap, stride):
    rng = np.random.default_rng(3)
    a = ElevationMap(4.0, 0.1, fusion_params=FusionParams(max_points_per_frame=cap, change_min_points=2),
                     cleanup_stride=stride)
    b = ElevationMap(4.0, 0.1, fusion_params=FusionParams(max_points_per_frame=cap, change_min_points=2),
                     cleanup_stride=stride)
    cleared = 0
    for f in range(8):
        pts, var, hc = random_frame(rng, 3000)
        # the clean-up (sensor origin given) in most frames, from inside the window and from outside it
        origin = None if f % 3 == 0 else (0.3 * f - 1.0, -0.7, 1.2) if f % 3 == 1 else (-3.5, 2.8, 2.0)
        sa = a.update(pts, var, stamp=f, horizontal_cov=hc if f % 2 else None, sensor_origin_map=origin)
        sb = b.update(pts, var, stamp=f, horizontal_cov=hc if f % 2 else None, sensor_origin_map=origin,
                      impl="numpy")
        assert sa == sb
        cleared += sa["cells_cleared"]
        if f in (2, 5):
            a.move_to((0.37 * f, -0.21 * f))
            b.move_to((0.37 * f, -0.21 * f))
        np.testing.assert_array_equal(np.isnan(a.data), np.isnan(b.data))
        sums = [LAYERS.index("scatter")]            # sums of O(n) terms that cancel: compare on their scale
        rest = [k for k in range(len(LAYERS)) if k not in sums]
        # atol 1e-13: the fused variance is recovered as variance - max(spread, neighbour_spread), which
        # rounds differently in the two summation orders
        np.testing.assert_allclose(a.data[rest], b.data[rest], rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(a.data[sums], b.data[sums], rtol=1e-9, atol=1e-9)
    assert cleared > 20                             # the clean-up's rays cleared cells


@pytest.mark.parametrize("offset", [0.0, 5.0e5 + 0.02, -3.7e6])
def test_cells_of_runs_of_points_and_of_border_points_are_those_of_the_reference(offset):
    # runs of points inside a cell (as a depth image's neighbouring pixels), then points on a border and one ulp
    # either side of it, near the origin and at UTM-sized coordinates: every point lands in floor(x / res)
    res = 0.1
    borders = (np.floor(offset / res) + np.arange(-8, 8)) * res
    xs = []
    for border in borders:
        xs += list(border + np.linspace(0.005, 0.095, 10)) + [border, np.nextafter(border, -np.inf),
                                                            np.nextafter(border, np.inf)]
    x = np.array(xs)
    y = offset + np.roll(x - offset, 7)
    pts = np.column_stack([x, y, np.linspace(0.0, 0.01, len(x))])
    maps = [ElevationMap(2.0, res, centre_xy=(offset, offset), fusion_params=FusionParams(min_points=1))
            for _ in range(2)]
    maps[0].update(pts, np.full(len(x), 1e-4))
    maps[1].update(pts, np.full(len(x), 1e-4), impl="numpy")
    np.testing.assert_array_equal(maps[0].layer("points"), maps[1].layer("points"))     # cell by cell counts
    assert maps[0].layer("points").sum() > 0.8 * len(x)


def test_same_result_with_one_and_two_threads():
    rng = np.random.default_rng(4)
    one, two = ElevationMap(4.0, 0.1, nthreads=1), ElevationMap(4.0, 0.1, nthreads=2)
    for f in range(4):
        pts, var, hc = random_frame(rng, 20000)
        origin = (0.2 * f, 0.1, 1.0) if f % 2 else None
        assert (one.update(pts, var, stamp=f, horizontal_cov=hc, sensor_origin_map=origin)
                == two.update(pts, var, stamp=f, horizontal_cov=hc, sensor_origin_map=origin))
        np.testing.assert_array_equal(one.data, two.data)


def test_bad_inputs_name_the_problem():
    m = small_map()
    with pytest.raises(ValueError, match=r"points_map must have shape \(N, 3\)"):
        m.update(np.zeros((3, 2)), np.ones(3))
    with pytest.raises(ValueError, match="non-finite"):
        m.update(np.array([[0.0, np.nan, 0.0]]), np.ones(1))
    with pytest.raises(ValueError, match=r"height_var must have shape \(1,\)"):
        m.update(np.zeros((1, 3)), np.ones(2))
    with pytest.raises(ValueError, match="finite and > 0"):
        m.update(np.zeros((1, 3)), np.zeros(1))
    with pytest.raises(ValueError, match="m\\^2"):
        m.update(np.zeros((1, 3)), np.full(1, 1e6))
    with pytest.raises(ValueError, match="sensor_origin_map"):
        m.update(np.zeros((1, 3)), np.ones(1), sensor_origin_map=[0, 0])
    with pytest.raises(ValueError, match="stamp must be finite"):
        m.update(np.zeros((1, 3)), np.ones(1), stamp=np.inf)
    with pytest.raises(ValueError, match="centre_xy"):
        m.move_to((np.nan, 0))
    with pytest.raises(ValueError, match="unknown layer"):
        m.layer("height")
    with pytest.raises(ValueError, match="resolution_m"):
        ElevationMap(1.0, 0.0)
    with pytest.raises(ValueError, match="min_variance must be below"):
        FusionParams(min_variance=1.0, max_variance=0.1)



@pytest.mark.parametrize("impl", ["numba", "numpy"])
@pytest.mark.parametrize("bad", [(0, -1e-9), (0, np.inf), (1, -np.inf), (1, np.nan), (2, np.nan), (2, -np.inf)])
@pytest.mark.parametrize("xy", [(0.5, 0.5), (50.0, -70.0)])
def test_a_bad_horizontal_covariance_is_refused_inside_or_outside_the_window(impl, bad, xy):
    m = small_map()
    pts = np.array([[0.2, 0.3, 1.0], [xy[0], xy[1], 2.0], [1.5, -0.5, 0.0]])
    hcov = np.full((3, 3), 1e-3)
    m.update(pts, np.ones(3), horizontal_cov=hcov, impl=impl)
    before = m.data.copy()
    hcov[1, bad[0]] = bad[1]
    with pytest.raises(ValueError, match="horizontal_cov must be finite with non-negative variances"):
        m.update(pts, np.ones(3), stamp=1.0, horizontal_cov=hcov, impl=impl)
    np.testing.assert_array_equal(m.data, before)
    hcov[1, bad[0]] = -1e-9 if bad[0] == 1 else 0.0        # a negative covariance or zero variances are valid
    m.update(pts, np.ones(3), stamp=1.0, horizontal_cov=hcov, impl=impl)


@pytest.mark.parametrize("impl", ["numba", "numpy"])
@pytest.mark.parametrize("bad", [(0, np.nan), (1, np.inf), (2, -np.inf), (2, 2e9), (3, 1e-30), (3, 1e6), (3, np.nan)])
@pytest.mark.parametrize("xy", [(0.5, 0.5), (50.0, -70.0)])
def test_a_bad_point_value_is_refused_inside_or_outside_the_window(impl, bad, xy):
    """x, y, z or the variance out of range (column 3: the variance) in a point that lies in the window or
    outside it: the update is refused and the map is left as it was."""
    m = small_map()
    pts = np.array([[0.2, 0.3, 1.0], [xy[0], xy[1], 2.0], [1.5, -0.5, 0.0]])
    var = np.ones(3)
    m.update(pts, var, impl=impl)
    before = m.data.copy()
    if bad[0] == 3:
        var[1] = bad[1]
    else:
        pts[1, bad[0]] = bad[1]
    with pytest.raises(ValueError, match="points_map|height_var"):
        m.update(pts, var, stamp=1.0, impl=impl)
    np.testing.assert_array_equal(m.data, before)


@pytest.mark.parametrize("impl", ["numba", "numpy"])
def test_a_point_beyond_the_coordinate_limit_is_refused_in_a_window_that_reaches_past_it(impl):
    """A map centred 1 m inside MAX_COORDINATE_M reaches past it: a point in its window beyond the limit
    is refused, one within it is fused."""
    from elevmap.map.settings import MAX_COORDINATE_M

    c = MAX_COORDINATE_M - 1.0
    m = ElevationMap(length_m=8.0, resolution_m=1.0, centre_xy=(c, 0.0))
    with pytest.raises(ValueError, match="points_map"):
        m.update(np.array([[c + 2.5, 0.5, 0.1]]), np.ones(1), impl=impl)
    assert m.frames == 0 and not m.is_known().any()
    assert m.update(np.array([[c + 0.5, 0.5, 0.1]]), np.ones(1), impl=impl)["cells_updated"] == 1


finite = st.floats(-3.0, 3.0, allow_nan=False)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31), moves=st.lists(st.tuples(finite, finite), max_size=3),
       scale=st.sampled_from([1e-8, 1e-4, 1e-1, 10.0]))
def test_fuzz_never_nan_or_negative_variance(seed, moves, scale):
    rng = np.random.default_rng(seed)
    m = ElevationMap(2.0, 0.25, fusion_params=FusionParams(change_min_points=1))
    for k, mv in enumerate([None, *moves]):
        if mv is not None:
            m.move_to(mv)
        n = int(rng.integers(0, 300))
        pts = np.column_stack([rng.uniform(-3, 3, (n, 2)), rng.normal(0, 1, n) * rng.choice([0.01, 1.0, 50.0])])
        var = rng.uniform(0.1, 1.0, n) * scale
        m.update(pts, var, stamp=k, horizontal_cov=np.abs(rng.normal(size=(n, 3))) * 1e-3)
        L = m.layers()
        known = np.isfinite(L["elevation"])
        assert np.all(np.isfinite(L["variance"][known])) and np.all(L["variance"][known] > 0)
        assert np.all(np.isnan(L["variance"][~known])) and np.all(L["points"][~known] == 0)
        assert np.all(L["min_height"][known] <= L["max_height"][known])
        assert np.all(L["horizontal_variance_x"][known] > 0)
        assert set(L) == set(LAYERS)


def test_geometry_rejects_bad_windows():
    with pytest.raises(ValueError, match="length_m"):
        GridGeometry.centred(0.01, 0.04)
    with pytest.raises(ValueError, match="too large"):
        GridGeometry.centred(1e4, 0.01)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31), ops=st.lists(st.sampled_from(["update", "predict", "move", "query"]),
                                                 min_size=1, max_size=8))
def test_fuzz_all_public_entries_keep_the_map_valid(tmp_path, seed, ops):
    rng = np.random.default_rng(seed)
    m = ElevationMap(2.0, 0.2)
    T = np.eye(4)
    for k, op in enumerate(ops):
        if op == "update":
            n = int(rng.integers(0, 200))
            pts = np.column_stack([rng.uniform(-1.5, 1.5, (n, 2)), rng.normal(0, 0.3, n)])
            m.update(pts, rng.uniform(1e-6, 1e-2, n), stamp=float(k),
                     sensor_origin_map=np.append(rng.uniform(-1, 1, 2), rng.uniform(0.2, 1.0)))
        elif op == "predict":
            A = rng.normal(size=(6, 6)) * rng.choice([1e-4, 1e-2])
            m.predict(A @ A.T, T_map_base=T, dt=float(rng.uniform(0, 1)), time_variance_rate=1e-4)
        elif op == "move":
            m.move_to(rng.uniform(-1, 1, 2))
        else:
            h, v = m.height_at(rng.uniform(-2, 2, (20, 2)))
            assert np.all(np.isnan(h) == np.isnan(v)) and np.all(v[np.isfinite(v)] > 0)
            scan = m.height_scan(T, "legged_gym")
            assert scan.height.shape == (187,) and np.all(scan.known == np.isfinite(scan.height))
            fused = m.fused_map()
            known = np.isfinite(fused["elevation"])
            assert np.all(fused["lower_bound"][known] <= fused["upper_bound"][known])
        L = m.layers()
        known = np.isfinite(L["elevation"])
        assert np.all(np.isfinite(L["variance"][known])) and np.all(L["variance"][known] > 0)
        assert np.all(np.isnan(L["variance"][~known]))
        for name in ("horizontal_variance_x", "horizontal_variance_y"):
            assert np.all(L[name][known] > 0)
    path = tmp_path / f"map-{seed}.npz"
    m.save(path)
    back = ElevationMap.load(path)
    np.testing.assert_array_equal(back.data, m.data)


def test_points_that_scatter_beyond_their_noise_do_not_make_a_cell_confident(rng):
    # one cell holding two surfaces 10 cm apart (a step inside the cell), points claiming 5 mm noise
    z = np.concatenate([rng.normal(0.0, 0.005, 50), rng.normal(0.1, 0.005, 50)])
    pts = np.column_stack([np.full(100, 0.5), np.full(100, 0.5), z])
    var = np.full(100, 0.005 ** 2)
    fine = dict(min_variance=1e-12)            # variances below the default floor are the point here
    plain = small_map(fusion_params=FusionParams(spread_alpha=None, **fine))
    default = small_map(fusion_params=FusionParams(**fine))
    for m in (plain, default):
        m.update(pts, var)
    # without the spread the cell claims the fixed-effect variance of 100 points: confident and wrong
    assert plain.layer("variance")[1, 1] == pytest.approx(0.005 ** 2 / 100)
    # by default the cell's spread (DerSimonian-Laird tau^2 = sigma^2 (chi2 - 1) for equal weights, ~(5 cm)^2)
    # is added: the height at the cell's centre is either level, not their mean to +-0.5 mm
    chi2 = np.sum((z - z.mean()) ** 2) / 0.005 ** 2 / 99                   # ~100: the points disagree
    tau2 = 0.005 ** 2 * (chi2 - 1.0)
    assert default.layer("spread")[1, 1] == pytest.approx(tau2, rel=1e-9)
    assert default.layer("variance")[1, 1] == pytest.approx(0.005 ** 2 / 100 + tau2, rel=1e-9)
    assert abs(default.layer("elevation")[1, 1] - 0.1) < 2 * np.sqrt(default.layer("variance")[1, 1])
    assert abs(default.layer("elevation")[1, 1] - 0.0) < 2 * np.sqrt(default.layer("variance")[1, 1])
    # points that agree with their noise add no spread
    ok = small_map(fusion_params=FusionParams(min_variance=1e-12))
    ok.update(np.column_stack([np.full(100, 0.5), np.full(100, 0.5), rng.normal(0, 0.005, 100)]), var)
    assert ok.layer("variance")[1, 1] == pytest.approx(0.005 ** 2 / 100)


def test_removed_scatter_inflation_is_read_with_a_warning(tmp_path):
    # an old config or saved map may name it: ignored with a warning; a value of the wrong type is an error
    with pytest.warns(FutureWarning, match="scatter_inflation was removed"):
        p = FusionParams(scatter_inflation=True)
    assert p == FusionParams() and "scatter_inflation" not in dataclasses.asdict(p)
    with pytest.raises(ValueError, match="scatter_inflation must be true or false"):
        FusionParams(scatter_inflation="no")
    m = small_map()
    m.update([[0.5, 0.5, 1.0]] * 3, np.full(3, 1e-4))
    m.save(tmp_path / "new.npz")
    with np.load(tmp_path / "new.npz") as f:
        arrays = dict(f)
    params = json.loads(str(arrays["fusion_params"]))
    assert "scatter_inflation" not in params
    arrays["fusion_params"] = np.array(json.dumps({**params, "scatter_inflation": True}))
    np.savez(tmp_path / "old.npz", **arrays)
    with pytest.warns(FutureWarning, match="scatter_inflation"):
        old = ElevationMap.load(tmp_path / "old.npz")
    np.testing.assert_array_equal(old.data, m.data)


@pytest.mark.parametrize("impl", ["numba", "numpy"])
def test_a_cell_started_by_one_wrong_point_follows_the_points_that_agree(impl):
    """The simulated boxes walk's failure: a far depth outlier (-0.46 m, stated sigma 35 mm) starts a box-top
    cell; later points, most at the true 0.25 m, must pull it over. The spread they raise weights each
    new point 1/(sigma^2 + tau^2); the prior, a mean of n points gathered m at a time, then counts as known
    to tau^2 m / n, not to its one point's sigma (which held the cell at -0.39 m through 29 points)."""
    m = small_map()
    m.update(np.array([[0.5, 0.5, -0.46]]), np.array([0.035 ** 2]), stamp=0, impl=impl)
    rng = np.random.default_rng(0)
    for f in range(1, 16):
        z = 0.25 + rng.normal(0, 0.01, 2)
        v = np.full(2, 0.03 ** 2)
        if f % 3 == 0:                                   # now and then a far, noisy point near the floor
            z, v = np.append(z, -0.06), np.append(v, 0.4 ** 2)
        m.update(np.column_stack([np.full(len(z), 0.5), np.full(len(z), 0.5), z]), v, stamp=f, impl=impl)
    h, sd = m.layer("elevation")[1, 1], np.sqrt(m.layer("variance")[1, 1])
    assert abs(h - 0.25) < 0.01 and abs(h - 0.25) < 2 * sd
    assert m.layer("points")[1, 1] >= 20


def test_spread_counts_only_beyond_the_spread_ratio(rng):
    """Points that scatter 2x their stated sigma (a misjudged noise model) add no spread with ratio 9;
    points 4x beyond it (a second surface) do; ratio 1 counts any significant excess. Ratio 1.5: a 10 %
    sigma error (variance ratio 1.21) adds none, a 50 % one (2.25) does. The default, 20, counts a second
    surface (10 cm levels under 5 mm noise scatter ~100x their variance) and not a misjudged sigma."""
    var = np.full(400, 0.005 ** 2)
    xy = np.full((400, 2), 0.5)
    fine = dict(min_variance=1e-12)
    assert FusionParams().spread_ratio == 20.0
    for scale, ratio, expect in ((2.0, 9.0, False), (4.0, 9.0, True), (2.0, 1.0, True), (1.1, 1.5, False),
                                 (1.5, 1.5, True), (4.0, 20.0, False), (10.0, 20.0, True)):
        m = small_map(fusion_params=FusionParams(spread_ratio=ratio, **fine))
        m.update(np.column_stack([xy, rng.normal(0.0, scale * 0.005, 400)]), var)
        assert (m.layer("spread")[1, 1] > 0) == expect, (scale, ratio)


def test_fusion_params_reject_bad_calibration_settings():
    for kw, name in (({"spread_ratio": 0.5}, "spread_ratio"), ({"spread_ratio": float("nan")}, "spread_ratio"),
                     ({"min_points": 0}, "min_points"), ({"min_points": 2.5}, "min_points"),
                     ({"neighbour_radius": 11}, "neighbour_radius")):
        with pytest.raises(ValueError, match=name):
            FusionParams(**kw)
