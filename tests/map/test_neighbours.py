"""Neighbourhood spread: a hand-checked window, a flat map, numba against the NumPy reference on random,
NaN/inf, wrapped and map-edge inputs, and the fusion unchanged by it."""

import numpy as np
import pytest

from elevmap import ElevationMap, FusionParams
from elevmap.map.grid import GridGeometry
from elevmap.map.layers import ELEVATION, LAYERS, NEIGHBOUR_SPREAD, SPREAD, UNKNOWN_VALUES, VARIANCE
from elevmap.map.neighbours import fused_variance, update_neighbour_spread, update_neighbour_spread_reference


def blank(n):
    d = np.empty((len(LAYERS), n, n))
    d[:] = np.array(UNKNOWN_VALUES)[:, None, None]
    return d


def test_one_raised_cell_by_hand():
    g = GridGeometry(5, 0.1, 0, 0)
    d = blank(5)
    d[ELEVATION, 1:4, 1:4] = 0.0
    d[ELEVATION, 2, 2] = 0.1
    d[VARIANCE, 1:4, 1:4] = 1e-4
    d[SPREAD, 1:4, 1:4] = 0.0
    update_neighbour_spread(d, g, radius=1)
    # centre window: 9 cells, w = 1e4 each; m = 0.1 / 9; Q = 1e4 (8 (0.1/9)^2 + (0.1 - 0.1/9)^2) = 88.889;
    # S1 = 9e4, S2 = 9e8, den = 9e4 - 1e4 = 8e4; tau^2 = (88.889 - 8) / 8e4 = 1.01111e-3
    assert d[NEIGHBOUR_SPREAD, 2, 2] == pytest.approx((1e4 * (8 * (0.1 / 9) ** 2 + (0.1 - 0.1 / 9) ** 2) - 8) / 8e4)
    assert d[NEIGHBOUR_SPREAD, 2, 2] == pytest.approx(1.01111e-3, rel=1e-5)
    assert d[VARIANCE, 2, 2] == pytest.approx(1e-4 + 1.01111e-3, rel=1e-5)
    # corner (1, 1): its window holds 4 known cells, the raised one among them: m = 0.025,
    # Q = 1e4 (3 * 0.025^2 + 0.075^2) = 75, den = 4e4 - 4e8 / 4e4 = 3e4, tau^2 = (75 - 3) / 3e4 = 2.4e-3
    assert d[NEIGHBOUR_SPREAD, 1, 1] == pytest.approx(2.4e-3)
    assert np.isnan(d[NEIGHBOUR_SPREAD, 0, 0]) and np.isnan(d[VARIANCE, 0, 0])       # unknown stays unknown
    # a second pass gives the same: the fused variance is recovered from variance - max(spread, tau^2)
    before = d.copy()
    update_neighbour_spread(d, g, radius=1)
    np.testing.assert_allclose(d, before, rtol=1e-12, equal_nan=True)
    np.testing.assert_allclose(fused_variance(d)[1:4, 1:4], 1e-4, rtol=1e-12)


def test_unequal_variances_paule_mandel_solves_its_equation():
    """With unequal variances Paule-Mandel and DerSimonian-Laird differ; Paule-Mandel's tau^2 is the root
    of sum w (h - m)^2 = k - 1, w = 1 / (P + tau^2) (found here by scipy's brentq); with equal variances
    (the test above) the two coincide, tau^2 = s^2 - P."""
    from scipy.optimize import brentq

    g = GridGeometry(3, 0.1, 0, 0)
    h = np.array([0.0, 0.01, -0.005, 0.002, 0.15, 0.0, 0.004, -0.002, 0.003])
    P = np.array([1e-6, 4e-6, 1e-6, 2e-6, 1e-2, 1e-6, 3e-6, 1e-6, 5e-6])
    d = blank(3)
    d[ELEVATION] = h.reshape(3, 3)
    d[VARIANCE] = P.reshape(3, 3)
    d[SPREAD] = 0.0
    dl, pm = d.copy(), d.copy()
    update_neighbour_spread(dl, g, radius=1, estimator="dersimonian_laird")
    update_neighbour_spread(pm, g, radius=1)

    def q_minus(t):
        w = 1 / (P + t)
        m = np.sum(w * h) / np.sum(w)
        return np.sum(w * (h - m) ** 2) - (len(h) - 1)

    w = 1 / P
    m = np.sum(w * h) / np.sum(w)
    q = np.sum(w * (h - m) ** 2)
    assert dl[NEIGHBOUR_SPREAD, 1, 1] == pytest.approx((q - 8) / (w.sum() - np.sum(w * w) / w.sum()), rel=1e-9)
    assert pm[NEIGHBOUR_SPREAD, 1, 1] == pytest.approx(brentq(q_minus, 0.0, 1.0, xtol=1e-16, rtol=1e-14), rel=1e-8)
    # the box-top cell's own P is large: DerSimonian-Laird, led by the precise cells, sees less spread
    assert dl[NEIGHBOUR_SPREAD, 1, 1] < 0.7 * pm[NEIGHBOUR_SPREAD, 1, 1]


def test_paule_mandel_follows_a_step_that_dersimonian_laird_loses(rng):
    """Windows of two levels (a 15 cm step; 10 % of the cells on the top) whose cells' variances span
    four decades, as a D435 map's near and far cells: both estimators are unbiased on average, but
    DerSimonian-Laird, whose weights are the precise cells', falls below half the true spread in a
    window in four (48 of 200; a cell beside a box made confident), Paule-Mandel in none."""
    g = GridGeometry(9, 0.05, 0, 0)
    low = {"paule_mandel": 0, "dersimonian_laird": 0}
    trials = 200
    for _ in range(trials):
        P = 10 ** rng.uniform(-6, -2, (9, 9))
        true = np.where(rng.random((9, 9)) < 0.1, 0.15, 0.0)
        d = blank(9)
        d[ELEVATION] = true + rng.normal(0, np.sqrt(P))
        d[VARIANCE] = P
        d[SPREAD] = 0.0
        for est in low:
            e = d.copy()
            update_neighbour_spread(e, g, radius=4, estimator=est)
            low[est] += e[NEIGHBOUR_SPREAD, 4, 4] < 0.5 * true.var()
    assert low["dersimonian_laird"] / trials > 0.15
    assert low["paule_mandel"] / trials < 0.08


def test_a_flat_map_gets_no_spread_and_the_cell_spread_wins_when_larger():
    g = GridGeometry(6, 0.1, 0, 0)
    d = blank(6)
    d[ELEVATION] = 0.3
    d[VARIANCE] = 2e-4
    d[SPREAD] = 0.0
    d[SPREAD, 3, 3] = 1e-4
    d[VARIANCE, 3, 3] = 3e-4                 # fused 2e-4 plus its own spread
    update_neighbour_spread(d, g, radius=2)
    assert (d[NEIGHBOUR_SPREAD] == 0).all()
    np.testing.assert_allclose(d[VARIANCE], np.where(np.arange(36).reshape(6, 6) == 21, 3e-4, 2e-4))


def random_map(rng, n, frac_known=0.7):
    d = blank(n)
    known = rng.random((n, n)) < frac_known
    d[ELEVATION][known] = rng.normal(0.0, 0.05, known.sum()) + (rng.random(known.sum()) < 0.1) * 0.3
    d[VARIANCE][known] = rng.uniform(1e-5, 4e-3, known.sum())
    d[SPREAD][known] = np.where(rng.random(known.sum()) < 0.3, rng.uniform(0, 2e-3, known.sum()), 0.0)
    d[VARIANCE][known] += d[SPREAD][known]
    d[NEIGHBOUR_SPREAD][known] = np.where(rng.random(known.sum()) < 0.3, rng.uniform(0, 1e-3, known.sum()), 0.0)
    d[VARIANCE][known] += np.maximum(d[NEIGHBOUR_SPREAD][known] - d[SPREAD][known], 0.0)
    return d, known


@pytest.mark.parametrize("estimator", ["paule_mandel", "dersimonian_laird"])
@pytest.mark.parametrize("seed", range(4))
def test_numba_equals_reference_on_random_wrapped_maps(seed, estimator):
    rng = np.random.default_rng(seed)
    n = 23
    g = GridGeometry(n, 0.05, int(rng.integers(-40, 40)), int(rng.integers(-40, 40)))   # wrapped buffer
    d, known = random_map(rng, n)
    ks = np.flatnonzero(known.ravel())
    d[VARIANCE].flat[ks[0]] = np.inf                 # a known cell with infinite variance: ignored
    d[SPREAD].flat[ks[1]] = np.nan                   # NaN spread counts as 0
    for radius in (1, 2, 3):
        for rows, cols in (((0, n - 1), (0, n - 1)), ((0, 4), (18, n - 1)), ((7, 9), (2, 2)), ((n - 1, n - 1), (0, 0))):
            a, b = d.copy(), d.copy()
            update_neighbour_spread(a, g, radius, rows, cols, nthreads=2, estimator=estimator)
            update_neighbour_spread_reference(b, g, radius, rows, cols, estimator=estimator)
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-15, equal_nan=True)
            # cells farther than radius from the window are untouched
            ij = np.indices((n, n))
            far = ((ij[0] < rows[0] - radius) | (ij[0] > rows[1] + radius) | (ij[1] < cols[0] - radius)
                   | (ij[1] > cols[1] + radius))
            far_b = g.wrap(far)
            np.testing.assert_array_equal(a[:, far_b], d[:, far_b])


def test_bad_input_names_what_is_wrong():
    g = GridGeometry(5, 0.1, 0, 0)
    d = blank(5)
    with pytest.raises(ValueError, match="radius"):
        update_neighbour_spread(d, g, radius=0)
    with pytest.raises(ValueError, match="rows"):
        update_neighbour_spread(d, g, rows=(3, 9))
    with pytest.raises(ValueError, match="layer stack"):
        update_neighbour_spread(d[:, :4], g)
    with pytest.raises(ValueError, match="neighbour_radius"):
        FusionParams(neighbour_radius=-1)
    with pytest.raises(ValueError, match="neighbour_radius"):
        FusionParams(neighbour_radius=1.5)
    with pytest.raises(ValueError, match="estimator"):
        update_neighbour_spread(d, g, estimator="reml")
    with pytest.raises(ValueError, match="neighbour_estimator"):
        FusionParams(neighbour_estimator="DL")


def test_the_heights_change_only_where_neighbours_disagree(rng):
    """The gate and the prior work on the variance without the neighbourhood's part, and a point's
    weight 1 / (sigma^2 + tau^2) takes the neighbourhood spread: on flat ground, where it is ~0, a map
    with neighbour_radius 2 has the heights of one with 0; beside a step it weighs the points more
    equally."""
    a = ElevationMap(2.0, 0.1, fusion_params=FusionParams(neighbour_radius=2), visibility_cleanup=False)
    b = ElevationMap(2.0, 0.1, fusion_params=FusionParams(neighbour_radius=0), visibility_cleanup=False)
    xs, _ = a.cell_centres()
    far = np.abs(xs - 0.13) > 0.5                            # rows of cells away from the step
    for f in range(12):
        xy = rng.uniform(-1, 1, (3000, 2))
        z = np.where(xy[:, 0] > 0.13, 0.2, 0.0) + rng.normal(0, 0.01, 3000)    # a step
        z[rng.random(3000) < 0.05] += 0.3                                        # and outliers
        var = rng.uniform(0.5, 2.0, 3000) * 1e-4
        a.update(np.column_stack([xy, z]), var, stamp=f)
        b.update(np.column_stack([xy, z]), var, stamp=f)
        # within twice the cells' own sigma (~90 points of 1 cm after 12 frames: 1 mm; an accepted outlier
        # weighed differently moves a cell by a few mm, most in the first frames, while the cells are uncertain
        # enough to accept it)
        diff = np.abs(a.layer("elevation") - b.layer("elevation"))[far]
        ratio = diff / np.sqrt(b.layer("variance")[far])
        assert np.nanmax(ratio) < (2.0 if f >= 6 else 4.0) and np.nanmedian(ratio) < 0.05
    assert (a.layer("neighbour_spread")[np.isfinite(a.layer("elevation"))] >= 0).all()
    assert np.nanmedian(a.layer("neighbour_spread")) < 1e-5             # flat ground: ~ nothing added
    near_step = np.abs(xs - 0.13) < 0.15                     # rows of cells next to the step
    assert np.nanmedian(a.layer("neighbour_spread")[near_step]) > 10 * np.nanmedian(a.layer("neighbour_spread"))
    assert np.abs(a.layer("elevation") - b.layer("elevation"))[near_step].max() > 1e-3
    known = np.isfinite(a.layer("elevation"))
    assert np.all(np.isfinite(a.layer("variance")[known])) and np.all(a.layer("variance")[known] > 0)


def test_numba_equals_reference_through_the_map(rng):
    a = ElevationMap(2.0, 0.1, centre_xy=(0.33, -0.71))
    b = ElevationMap(2.0, 0.1, centre_xy=(0.33, -0.71))
    for f in range(6):
        xy = rng.uniform(-1.5, 1.5, (2000, 2)) + [0.33, -0.71]
        z = np.where(xy[:, 1] > -0.5, 0.15, 0.0) + rng.normal(0, 0.01, 2000)
        var = np.full(2000, 1e-4)
        origin = np.array([0.3 + 0.05 * f, -0.7, 0.5])
        a.update(np.column_stack([xy, z]), var, stamp=f, sensor_origin_map=origin)
        b.update(np.column_stack([xy, z]), var, stamp=f, sensor_origin_map=origin, impl="numpy")
        np.testing.assert_allclose(a.data, b.data, rtol=1e-9, atol=1e-11, equal_nan=True)
        a.move_to([0.33 + 0.1 * f, -0.71])
        b.move_to([0.33 + 0.1 * f, -0.71])


def test_interleaved_rows_are_a_permutation_that_deals_every_thread_every_tth_row():
    from elevmap.map.neighbours import interleaved

    for n in (1, 2, 5, 95, 96):
        for T in (1, 2, 3, 4):
            order = [interleaved(q, n, T) for q in range(n)]
            assert sorted(order) == list(range(n))
            first = order[:(n + T - 1) // T]          # the first thread's contiguous range of q
            assert first == list(range(0, n, T))


@pytest.mark.parametrize("radius", [4, 10])
def test_numba_equals_reference_on_rows_wider_than_a_block_of_solves(radius):
    """Rows of more than PM_BLOCK cells solved side by side (several blocks per row, the last one short),
    with and without a warm start, the window's edge in the middle of the wrapped buffer."""
    from elevmap.map.neighbours import PM_BLOCK

    rng = np.random.default_rng(5)
    n = 2 * PM_BLOCK + 37
    g = GridGeometry(n, 0.05, 61, -29)
    d, _ = random_map(rng, n, frac_known=0.8)
    for warm in (False, True):
        if not warm:
            d[NEIGHBOUR_SPREAD] = np.where(np.isnan(d[ELEVATION]), np.nan, 0.0)
        results = []
        for nthreads in (1, 2):
            a = d.copy()
            update_neighbour_spread(a, g, radius, (n - 9, n - 2), (0, n - 1), nthreads=nthreads)
            results.append(a)
        b = d.copy()
        update_neighbour_spread_reference(b, g, radius, (n - 9, n - 2), (0, n - 1))
        np.testing.assert_array_equal(results[0], results[1])
        np.testing.assert_allclose(results[0], b, rtol=1e-9, atol=1e-15, equal_nan=True)
        assert (results[0][NEIGHBOUR_SPREAD] > 0).sum() > 2 * n


def test_a_camera_view_of_known_cells_equals_the_reference_with_one_and_two_threads():
    """Known cells in a trapezoid (a camera's view), with holes and rows without a known cell, inside a
    wrapped window that reaches the map's edge: the kernel sums each row's span of counting cells only,
    the reference the whole window; the results agree, and 1 and 2 threads bit for bit."""
    rng = np.random.default_rng(11)
    n = 90
    g = GridGeometry(n, 0.05, 23, -41)
    d, _ = random_map(rng, n, frac_known=0.9)
    i, j = np.indices((n, n))
    view = (i >= 5) & (i <= 80) & (np.abs(j - 45) <= 3 + 0.5 * (i - 5)) & (i % 17 != 0)   # map order
    keep = g.wrap(view)
    d[:, ~keep] = np.array(UNKNOWN_VALUES)[:, None]
    rows, cols = (5, 80), (0, n - 1)
    out = []
    for nthreads in (1, 2):
        a = d.copy()
        update_neighbour_spread(a, g, 4, rows, cols, nthreads=nthreads)
        out.append(a)
    b = d.copy()
    update_neighbour_spread_reference(b, g, 4, rows, cols)
    np.testing.assert_array_equal(out[0], out[1])
    np.testing.assert_allclose(out[0], b, rtol=1e-9, atol=1e-15, equal_nan=True)
    assert (out[0][NEIGHBOUR_SPREAD] > 0).sum() > 100


@pytest.mark.parametrize("estimator", ["paule_mandel", "dersimonian_laird"])
@pytest.mark.parametrize("impl", [update_neighbour_spread, update_neighbour_spread_reference])
def test_a_few_cells_far_above_the_origin_get_the_spread_they_get_at_its_height(impl, estimator):
    """The sums are taken relative to a height near the window's cells (sampled on every 8th row and
    column, else over the whole window): a patch of cells that no sample meets, 100 km up, gets the spread
    it gets at 0 m (without the reference height, DerSimonian-Laird's sums lose digits of it there)."""
    rng = np.random.default_rng(3)
    n = 64
    g = GridGeometry(n, 0.05, 0, 0)
    d = blank(n)
    patch = (slice(33, 38), slice(41, 46))                  # no row or column a multiple of 8
    d[ELEVATION][patch] = rng.normal(0.0, 0.05, (5, 5))
    d[VARIANCE][patch] = 1e-4
    d[SPREAD][patch] = 0.0
    spread = []
    for lift in (0.0, 1e5):
        a = d.copy()
        a[ELEVATION][patch] += lift
        impl(a, g, 2, (33, 37), (41, 45), estimator=estimator)
        spread.append(a[NEIGHBOUR_SPREAD][patch])
    assert np.all(spread[0] > 0)
    np.testing.assert_allclose(spread[1], spread[0], rtol=1e-6)
