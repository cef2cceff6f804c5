"""Ray-cast visibility clean-up: hand-checked rays on tiny maps, numba against the NumPy reference on
random maps, thread-count independence, and the box-appears-and-goes-away behaviour a legged robot
needs, through ElevationMap."""

import math

import numpy as np
import pytest

from elevmap import FusionParams
from elevmap.map.elevation_map import ElevationMap
from elevmap.map.grid import GridGeometry
from elevmap.map.layers import (
    ELEVATION, LAYERS, POINTS, TIME, UNKNOWN_VALUES, UPPER_BOUND, VARIANCE, ZERO_WHEN_UNKNOWN,
)
from elevmap.map.visibility import visibility_cleanup, visibility_cleanup_reference

IMPLS = [visibility_cleanup, visibility_cleanup_reference]


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------
def empty(g: GridGeometry) -> np.ndarray:
    d = np.empty((len(LAYERS), g.n, g.n))
    d[:] = np.array(UNKNOWN_VALUES)[:, None, None]
    return d


def set_cell(d, g, ij, h, var=1e-6, time=0.0, ub=np.nan):
    bi, bj = g.buffer_index(ij)
    d[:, bi, bj] = np.nan
    d[ELEVATION, bi, bj], d[VARIANCE, bi, bj], d[TIME, bi, bj] = h, var, time
    d[POINTS, bi, bj] = 10.0
    d[UPPER_BOUND, bi, bj] = ub


def cell(d, g, ij, layer):
    bi, bj = g.buffer_index(ij)
    return d[layer, bi, bj]


def assert_same(a, b):
    """Equal maps: the same unknown cells, every layer bit for bit but upper_bound, which may differ
    in the last bits (a fused multiply-add in the compiled ray height)."""
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    other = [k for k in range(len(LAYERS)) if k != UPPER_BOUND]
    np.testing.assert_array_equal(a[other], b[other])
    np.testing.assert_allclose(a[UPPER_BOUND], b[UPPER_BOUND], rtol=1e-12, atol=1e-12)


# A 5 x 5 map of 1 m cells, global cells 0..4 in x and y. The sensor sits at (0.5, 2.5, 0.5), in
# cell (0, 2); a floor point at (4.5, 2.5, 0) in cell (4, 2). The ray runs along row j = 2: it
# crosses x = 1, 2, 3 at t = 1/8, 3/8, 5/8, z(t) = 0.5 - 0.5 t. Cells 3 and 4 are the point's own
# cell and its neighbour (excluded); the ceilings (entry heights, the ray descends) are
# cell 0: 0.5, cell 1: z(1/8) = 0.4375, cell 2: z(3/8) = 0.3125.
G5 = GridGeometry(5, 1.0, 0, 0)
ORIGIN = np.array([0.5, 2.5, 0.5])
FLOOR_POINT = np.array([[4.5, 2.5, 0.0]])
CEILINGS = {0: 0.5, 1: 0.4375, 2: 0.3125}


# ---------------------------------------------------------------------------------------------
# tiny maps by hand
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fn", IMPLS)
def test_ray_below_a_known_cell_clears_it(fn):
    d = empty(G5)
    set_cell(d, G5, (2, 2), h=1.0, var=1e-6)          # 1 - 3 sigma = 0.997 > ray ceiling 0.3125
    assert fn(d, G5, ORIGIN, FLOOR_POINT, stamp=1.0) == 1
    for k, name in enumerate(LAYERS):
        if name == "upper_bound":
            assert cell(d, G5, (2, 2), k) == 0.3125            # the free-space bound stays
        elif name in ZERO_WHEN_UNKNOWN:
            assert cell(d, G5, (2, 2), k) == 0.0
        else:
            assert np.isnan(cell(d, G5, (2, 2), k)), name


@pytest.mark.parametrize("fn", IMPLS)
def test_ray_above_a_low_cell_keeps_it(fn):
    d = empty(G5)
    set_cell(d, G5, (2, 2), h=0.1, var=1e-6)          # the ray passes at 0.3125 over it
    before = d.copy()
    assert fn(d, G5, ORIGIN, FLOOR_POINT, stamp=1.0) == 0
    assert cell(d, G5, (2, 2), ELEVATION) == 0.1 and cell(d, G5, (2, 2), VARIANCE) == 1e-6
    assert cell(d, G5, (2, 2), UPPER_BOUND) == 0.3125
    other = [k for k in range(len(LAYERS)) if k != UPPER_BOUND]
    np.testing.assert_array_equal(d[other], before[other])


@pytest.mark.parametrize("fn", IMPLS)
def test_uncertain_cell_is_kept_while_the_ray_is_within_three_sigma(fn):
    d = empty(G5)
    set_cell(d, G5, (2, 2), h=0.5, var=0.07 ** 2)      # 0.5 - 3 * 0.07 = 0.29 < 0.3125
    assert fn(d, G5, ORIGIN, FLOOR_POINT, stamp=1.0) == 0
    assert cell(d, G5, (2, 2), ELEVATION) == 0.5
    set_cell(d, G5, (2, 2), h=0.5, var=0.06 ** 2)      # 0.5 - 3 * 0.06 = 0.32 > 0.3125
    assert fn(d, G5, ORIGIN, FLOOR_POINT, stamp=1.0) == 1


@pytest.mark.parametrize("fn", IMPLS)
def test_cell_updated_in_this_frame_is_never_cleared(fn):
    d = empty(G5)
    set_cell(d, G5, (2, 2), h=1.0, var=1e-6, time=1.0)
    assert fn(d, G5, ORIGIN, FLOOR_POINT, stamp=1.0) == 0
    assert cell(d, G5, (2, 2), ELEVATION) == 1.0 and cell(d, G5, (2, 2), TIME) == 1.0
    assert fn(d, G5, ORIGIN, FLOOR_POINT, stamp=2.0) == 1       # the next frame did not see it


@pytest.mark.parametrize("fn", IMPLS)
def test_upper_bound_of_crossed_unknown_cells_is_the_ray_ceiling(fn):
    d = empty(G5)
    assert fn(d, G5, ORIGIN, FLOOR_POINT, stamp=1.0) == 0
    ub = G5.unwrap(d[UPPER_BOUND])
    expected = np.full((5, 5), np.nan)
    for i, c in CEILINGS.items():
        expected[i, 2] = c
    np.testing.assert_array_equal(ub, expected)          # the point's cell and its neighbour untouched
    assert np.all(np.isnan(G5.unwrap(d[ELEVATION])))


@pytest.mark.parametrize("fn", IMPLS)
def test_upper_bound_is_only_ever_lowered(fn):
    d = empty(G5)
    set_cell(d, G5, (1, 2), h=0.0, ub=0.2)             # below the ray's 0.4375: stays
    set_cell(d, G5, (2, 2), h=0.0, ub=0.9)             # above the ray's 0.3125: lowered
    fn(d, G5, ORIGIN, FLOOR_POINT, stamp=1.0)
    assert cell(d, G5, (1, 2), UPPER_BOUND) == 0.2
    assert cell(d, G5, (2, 2), UPPER_BOUND) == 0.3125


@pytest.mark.parametrize("fn", IMPLS)
def test_two_dimensional_ray_by_hand(fn):
    # (0.5, 0.5, 1) -> (4.5, 2.5, 0): x borders at t = 1/8, 3/8, 5/8, 7/8, y borders at 1/4, 3/4;
    # z = 1 - t. Cells: (0,0) [0, 1/8], (1,0) [1/8, 1/4], (1,1) [1/4, 3/8], (2,1) [3/8, 5/8], then
    # (3,1) which touches the point's cell (4,2) diagonally (excluded).
    d = empty(G5)
    fn(d, G5, [0.5, 0.5, 1.0], [[4.5, 2.5, 0.0]], stamp=1.0)
    expected = np.full((5, 5), np.nan)
    expected[0, 0], expected[1, 0], expected[1, 1], expected[2, 1] = 1.0, 0.875, 0.75, 0.625
    np.testing.assert_array_equal(G5.unwrap(d[UPPER_BOUND]), expected)


@pytest.mark.parametrize("fn", IMPLS)
def test_ray_through_lattice_corners_steps_diagonally(fn):
    # (0.5, 0.5, 1) -> (4.5, 4.5, 0) crosses x = k and y = k at the same t: cells (0,0), (1,1), (2,2)
    # only, never the side cells (1,0), (0,1), ...
    d = empty(G5)
    fn(d, G5, [0.5, 0.5, 1.0], [[4.5, 4.5, 0.0]], stamp=1.0)
    expected = np.full((5, 5), np.nan)
    expected[0, 0], expected[1, 1], expected[2, 2] = 1.0, 0.875, 0.625
    np.testing.assert_array_equal(G5.unwrap(d[UPPER_BOUND]), expected)


@pytest.mark.parametrize("fn", IMPLS)
def test_rising_ray_uses_the_exit_height(fn):
    d = empty(G5)
    fn(d, G5, [0.5, 2.5, 0.0], [[4.5, 2.5, 0.8]], stamp=1.0)    # z = 0.8 t; exits at t = 1/8, 3/8, 5/8
    ub = G5.unwrap(d[UPPER_BOUND])
    np.testing.assert_allclose([ub[0, 2], ub[1, 2], ub[2, 2]], [0.1, 0.3, 0.5], rtol=1e-15)


@pytest.mark.parametrize("fn", IMPLS)
def test_ray_goes_to_the_lowest_point_of_each_cell(fn):
    d = empty(G5)
    pts = np.array([[4.2, 2.7, 0.9], [4.5, 2.5, 0.0], [4.8, 2.2, 0.6]])
    fn(d, G5, ORIGIN, pts, stamp=1.0)
    # only the ray to (4.5, 2.5, 0) was cast (the higher points would give higher ceilings)
    assert cell(d, G5, (2, 2), UPPER_BOUND) == 0.3125
    assert cell(d, G5, (1, 2), UPPER_BOUND) == 0.4375


@pytest.mark.parametrize("fn", IMPLS)
def test_stride_keeps_every_other_ray_in_map_order(fn):
    pts = np.array([[4.5, 4.5, 0.0], [4.5, 2.5, 0.0], [4.5, 0.5, 0.0]])   # cells (4,4), (4,2), (4,0)
    for stride, middle in ((1, 0.3125), (2, np.nan), (3, np.nan)):
        d = empty(G5)
        fn(d, G5, ORIGIN, pts, stamp=1.0, stride=stride)
        # rays in map order: (4,0), (4,2), (4,4); stride 2 drops the middle one, stride 3 the last two
        np.testing.assert_array_equal(cell(d, G5, (2, 2), UPPER_BOUND), middle)
        assert np.isfinite(cell(d, G5, (2, 1), UPPER_BOUND))              # ray to (4,0) crosses (2,1)
        assert np.isfinite(cell(d, G5, (2, 3), UPPER_BOUND)) == (stride < 3)


@pytest.mark.parametrize("fn", IMPLS)
def test_sensor_outside_the_window_starts_where_the_ray_enters(fn):
    d = empty(G5)
    o = [-2.5, 2.5, 1.0]                                # z = 1 - t, x(t) = -2.5 + 7 t
    fn(d, G5, o, FLOOR_POINT, stamp=1.0)
    ub = G5.unwrap(d[UPPER_BOUND])
    np.testing.assert_allclose([ub[0, 2], ub[1, 2], ub[2, 2]], [1 - 2.5 / 7, 1 - 3.5 / 7, 1 - 4.5 / 7], rtol=1e-15)
    assert np.isfinite(ub).sum() == 3


@pytest.mark.parametrize("fn", IMPLS)
def test_points_outside_the_window_cast_no_ray(fn):
    d = empty(G5)
    set_cell(d, G5, (2, 2), h=1.0)
    before = d.copy()
    assert fn(d, G5, ORIGIN, [[7.5, 2.5, 0.0], [-3.0, 2.5, 0.0], [2.5, 5.0, 0.0]], stamp=1.0) == 0
    np.testing.assert_array_equal(d, before)
    assert fn(d, G5, ORIGIN, np.zeros((0, 3)), stamp=1.0) == 0


@pytest.mark.parametrize("fn", IMPLS)
def test_buffer_order_is_respected_after_a_move(fn):
    g = GridGeometry(5, 1.0, 3, -2)                     # window gx 3..7, gy -2..2; buffer != map order
    d = empty(g)
    set_cell(d, g, (2, 2), h=1.0)                       # global cell (5, 0)
    assert fn(d, g, [3.5, 0.5, 0.5], [[7.5, 0.5, 0.0]], stamp=1.0) == 1
    ub = g.unwrap(d[UPPER_BOUND])
    assert (ub[0, 2], ub[1, 2], ub[2, 2]) == (0.5, 0.4375, 0.3125)


@pytest.mark.parametrize("fn", IMPLS)
def test_invalid_inputs_are_rejected_by_name(fn):
    d = empty(G5)
    set_cell(d, G5, (2, 2), h=1.0)
    before = d.copy()
    bad = [
        (dict(sensor_origin_map=[0.0, 0.0]), "sensor_origin_map"),
        (dict(sensor_origin_map=[0.0, np.nan, 1.0]), "sensor_origin_map"),
        (dict(sensor_origin_map=[1e20, 0.0, 1.0]), "sensor_origin_map"),
        (dict(points_map=np.zeros((3, 2))), "points_map"),
        (dict(points_map=np.array([[4.5, 2.5, 0.0], [1.0, np.inf, 0.0]])), "non-finite"),
        (dict(points_map=np.array([["a", "b", "c"]])), "points_map"),
        (dict(stride=0), "stride"),
        (dict(stride=1.5), "stride"),
        (dict(stamp=np.nan), "stamp"),
        (dict(nthreads=0), "nthreads"),
    ]
    for kw, match in bad:
        args = dict(sensor_origin_map=ORIGIN, points_map=FLOOR_POINT, stamp=1.0)
        args.update(kw)
        with pytest.raises(ValueError, match=match):
            fn(d, G5, **args)
        np.testing.assert_array_equal(d, before)          # nothing changed
    with pytest.raises(ValueError, match="data"):
        fn(np.zeros((3, 5, 5)), G5, ORIGIN, FLOOR_POINT, 1.0)


# ---------------------------------------------------------------------------------------------
# numba against the reference
# ---------------------------------------------------------------------------------------------
def random_case(seed):
    """A random map (some cells updated this frame, some with bounds) and points, with hostile
    geometry: points outside the window and on cell borders, axis-parallel rays, a sensor outside
    the window or on a border."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 24))
    res = float(rng.choice([0.04, 0.1, 0.25, 1.0]))
    g = GridGeometry(n, res, int(rng.integers(-40, 40)), int(rng.integers(-40, 40)))
    d = empty(g)
    known = rng.random((n, n)) < 0.7
    d[ELEVATION][known] = rng.uniform(-0.5, 1.5, known.sum())
    d[VARIANCE][known] = rng.uniform(1e-5, 1e-2, known.sum())
    d[TIME][known] = rng.choice([3.0, 4.0], known.sum())
    d[POINTS][known] = 5.0
    with_ub = known & (rng.random((n, n)) < 0.5)
    d[UPPER_BOUND][with_ub] = rng.uniform(0.0, 2.0, with_ub.sum())
    lo, L = g.lower_corner_xy, g.length_m
    N = int(rng.integers(1, 400))
    p = np.column_stack([rng.uniform(lo[0] - 0.3 * L, lo[0] + 1.3 * L, N),
                         rng.uniform(lo[1] - 0.3 * L, lo[1] + 1.3 * L, N), rng.uniform(-0.5, 1.0, N)])
    on_border = rng.random(N) < 0.3
    p[on_border, :2] = np.round(p[on_border, :2] / res) * res
    p[rng.random(N) < 0.05, 2] = p[0, 2]                 # equal heights: ties in the lowest point
    kind = seed % 4
    if kind == 0:                                       # far outside the window
        o = np.array([lo[0] - 3 * L, lo[1] + rng.uniform(-L, 2 * L), 2.0])
    else:
        o = np.array([lo[0] + rng.uniform(0, L), lo[1] + rng.uniform(0, L), rng.uniform(0.0, 2.0)])
    if kind == 2:
        o[:2] = np.round(o[:2] / res) * res             # sensor on a cell corner
    if kind == 3:
        p[: N // 3, 1] = o[1]                           # rays parallel to x
        p[N // 3: N // 2, 0] = o[0]                     # rays parallel to y
    return g, d, o, p, int(rng.integers(1, 4))


@pytest.mark.parametrize("seed", range(24))
def test_numba_equals_reference_on_random_maps(seed):
    g, d, o, p, stride = random_case(seed)
    a, b = d.copy(), d.copy()
    ca = visibility_cleanup(a, g, o, p, 4.0, stride=stride, nthreads=2)
    cb = visibility_cleanup_reference(b, g, o, p, 4.0, stride=stride)
    assert ca == cb
    assert_same(a, b)
    assert np.isfinite(a[UPPER_BOUND]).sum() >= np.isfinite(d[UPPER_BOUND]).sum()


def test_random_cases_exercise_clearing_and_bounds():
    cleared = lowered = 0
    for seed in range(24):
        g, d, o, p, stride = random_case(seed)
        a = d.copy()
        cleared += visibility_cleanup(a, g, o, p, 4.0, stride=stride)
        with np.errstate(invalid="ignore"):
            lowered += int(np.sum(a[UPPER_BOUND] < d[UPPER_BOUND]))
    assert cleared > 50 and lowered > 50


def d435_floor_frame(seed=0, width=848, height=480):
    """A D435-sized frame of a floor with a step, from a camera at 0.5 m pitched 30 deg down."""
    rng = np.random.default_rng(seed)
    fx = width / 2 / math.tan(math.radians(87.0) / 2)
    fy = height / 2 / math.tan(math.radians(58.0) / 2)
    u, v = np.meshgrid(np.arange(width) + 0.5 - width / 2, np.arange(height) + 0.5 - height / 2)
    d = np.stack([np.ones_like(u), -u / fx, -v / fy], -1).reshape(-1, 3)
    p = math.radians(30.0)
    d = d @ np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]]).T
    o = np.array([0.0, 0.0, 0.5])
    d = d[d[:, 2] < -0.05]
    pts = o + (-o[2] / d[:, 2])[:, None] * d
    step = (pts[:, 0] > 1.2) & (pts[:, 0] < 1.6)
    pts[step, 2] = 0.15
    pts[:, 2] += rng.normal(0, 0.005, len(pts))
    return o, pts


def test_same_result_with_one_and_two_threads():
    o, pts = d435_floor_frame(width=424, height=240)
    g = GridGeometry.centred(8.0, 0.04, (0.3, -0.2))
    d = empty(g)
    d[ELEVATION], d[VARIANCE], d[TIME] = 0.05, 1e-4, 0.0
    d[ELEVATION, ::7] = 0.6
    one, two = d.copy(), d.copy()
    c1 = visibility_cleanup(one, g, o, pts, 1.0, nthreads=1)
    c2 = visibility_cleanup(two, g, o, pts, 1.0, nthreads=2)
    assert c1 == c2 > 100
    np.testing.assert_array_equal(one.view(np.int64), two.view(np.int64))      # bit for bit
    a, b = d.copy(), d.copy()                          # and the reference, on a quarter of the points
    assert visibility_cleanup(a, g, o, pts[::4], 1.0) == visibility_cleanup_reference(b, g, o, pts[::4], 1.0)
    assert_same(a, b)


# ---------------------------------------------------------------------------------------------
# end to end through ElevationMap: a box appears and goes away
# ---------------------------------------------------------------------------------------------
SENSOR = np.array([0.0, 0.0, 0.5])
BOX_LO, BOX_HI = np.array([1.3, -0.2, 0.0]), np.array([1.7, 0.2, 0.3])


def pixel_rays(width=320, height=320, hfov_deg=87.0, vfov_deg=58.0, pitch_deg=25.0):
    """Unit-free pinhole ray directions in the map frame (x forward, y left, z up), pitched down."""
    fx = width / 2 / math.tan(math.radians(hfov_deg) / 2)
    fy = height / 2 / math.tan(math.radians(vfov_deg) / 2)
    u, v = np.meshgrid(np.arange(width) + 0.5 - width / 2, np.arange(height) + 0.5 - height / 2)
    d = np.stack([np.ones_like(u), -u / fx, -v / fy], -1).reshape(-1, 3)
    p = math.radians(pitch_deg)
    return d @ np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]]).T


def render(dirs, box: bool, rng, noise=0.005, max_range=8.0):
    """Ray-cast the floor z = 0 (and the box) from SENSOR; z noise of ``noise`` [m]."""
    t = np.full(len(dirs), np.inf)
    down = dirs[:, 2] < 0
    t[down] = -SENSOR[2] / dirs[down, 2]
    if box:
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (BOX_LO - SENSOR) / dirs, (BOX_HI - SENSOR) / dirs
        t_near = np.nanmax(np.minimum(t1, t2), axis=1)
        t_far = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (t_near <= t_far) & (t_near > 0) & (t_near < t)
        t[hit] = t_near[hit]
    ok = t < max_range
    pts = SENSOR + t[ok, None] * dirs[ok]
    pts[:, 2] += rng.normal(0.0, noise, len(pts))
    return pts


class Scene:
    def __init__(self, seed=0, **map_kw):
        self.rng = np.random.default_rng(seed)
        self.dirs = pixel_rays()
        self.m = ElevationMap(8.0, 0.04, **map_kw)
        self.stamp = 0.0

    def frame(self, box: bool, drop=None) -> dict:
        p = render(self.dirs, box, self.rng)
        if drop is not None:                               # cells that return no depth (a black mat)
            ij, inside = self.m.geometry.map_index(p[:, :2])
            ij = np.clip(ij, 0, self.m.n - 1)
            p = p[~(inside & drop[ij[:, 0], ij[:, 1]])]
        r = self.m.update(p, np.full(len(p), 0.01 ** 2), self.stamp, sensor_origin_map=SENSOR)
        self.stamp += 0.1
        return r


def box_footprint(m):
    xs, ys = m.cell_centres()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    h = m.resolution_m / 2
    inside = (X - h > BOX_LO[0] - 1e-9) & (X + h < BOX_HI[0] + 1e-9) & (Y - h > BOX_LO[1] - 1e-9) & (
        Y + h < BOX_HI[1] + 1e-9)
    return X, Y, inside


def test_box_appears_then_goes_away():
    s = Scene(visibility_cleanup=True)
    m = s.m
    X, Y, box = box_footprint(m)
    for _ in range(3):
        s.frame(box=False)
    floor = m.is_known()
    assert floor.sum() > 5000 and floor[box].all()
    _floor_is_right(m, floor)
    t_box = s.stamp
    cleared_with_box = sum(s.frame(box=True)["cells_cleared"] for _ in range(5))
    h = m.layer("elevation")
    assert (np.abs(h[box] - 0.3) < 0.03).mean() > 0.9, "the box's cells rise"
    # the floor behind the box, hidden while it stood: not updated, and not touched by any ray
    shadow = (X > BOX_HI[0] + 0.05) & floor & (m.layer("time") < t_box)
    assert shadow.sum() > 200
    assert np.isfinite(h[shadow]).all() and np.abs(h[shadow]).max() < 0.03
    assert cleared_with_box == 0 and np.isfinite(h[floor]).all(), "no floor cell cleared"
    t_gone = s.stamp
    back = None
    for k in range(10):
        s.frame(box=False)
        h = m.layer("elevation")
        if back is None and np.isfinite(h[box]).all() and np.abs(h[box]).max() < 0.03:
            back = k
    assert back is not None and back <= 2, "the box's cells are back near the floor"
    h = m.layer("elevation")
    assert np.isfinite(h[box]).all() and np.abs(h[box]).max() < 0.03
    # the formerly occluded floor is seen again and right
    assert (m.layer("time")[shadow] >= t_gone).all()
    assert np.abs(h[shadow]).max() < 0.03
    _floor_is_right(m, floor)
    ub = m.layer("upper_bound")
    with np.errstate(invalid="ignore"):
        assert not np.any(ub < h - 0.05), "no free-space bound below the surface"


@pytest.mark.parametrize("visibility", [True, False])
def test_phantom_box_over_a_no_return_patch_is_cleared_only_by_visibility(visibility):
    # After the box goes, its footprint returns no depth (a black mat): the fusion never sees those
    # cells again and only the rays to the floor behind them can remove the phantom.
    s = Scene(seed=1, visibility_cleanup=visibility)
    m = s.m
    _, _, box = box_footprint(m)
    for k in range(8):
        s.frame(box=k >= 3)
    rose = m.layer("elevation") > 0.2
    assert rose[box].mean() > 0.9
    r = s.frame(box=False, drop=rose)
    h = m.layer("elevation")
    if visibility:
        assert r["cells_cleared"] == rose.sum()
        assert np.isnan(h[rose]).all()
        assert (m.layer("upper_bound")[rose] < 0.2).all()      # the free-space bound stays
    else:
        assert r["cells_cleared"] == 0
        assert (h[rose] > 0.2).all()
    known_floor = m.is_known() & ~rose
    _floor_is_right(m, known_floor)


def _floor_is_right(m, floor):
    """Floor cells are at 0 within 3 cm, or, the few that held points of the box's edge too (spread > 0),
    within 3 of their sigma."""
    h, v, spread = m.layer("elevation")[floor], m.layer("variance")[floor], m.layer("spread")[floor]
    assert np.isfinite(h).all()
    sharp = spread < 0.01 ** 2
    assert sharp.mean() > 0.95
    assert np.abs(h[sharp]).max() < 0.03
    assert np.all(np.abs(h) < 3 * np.sqrt(v))


def test_elevation_map_numpy_impl_calls_the_reference():
    o, pts = d435_floor_frame(width=106, height=60)
    a, b = ElevationMap(4.0, 0.1), ElevationMap(4.0, 0.1)
    for m in (a, b):
        m.data[ELEVATION], m.data[VARIANCE], m.data[TIME] = 0.4, 1e-4, -1.0
    ra = a.update(pts, np.full(len(pts), 1e-4), 0.0, sensor_origin_map=o, impl="numba")
    rb = b.update(pts, np.full(len(pts), 1e-4), 0.0, sensor_origin_map=o, impl="numpy")
    assert ra["cells_cleared"] == rb["cells_cleared"] > 0
    np.testing.assert_array_equal(np.isnan(a.data), np.isnan(b.data))
    np.testing.assert_allclose(a.data[UPPER_BOUND], b.data[UPPER_BOUND], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("impl", ["numba", "numpy"])
def test_a_point_measured_too_low_does_not_clear_the_floor_it_was_measured_on(impl):
    # 7 x 7 cells of 1 m, x in [-3, 4); a confident floor cell at x in [1, 2) (h = 0, sigma 1 mm)
    from elevmap.map.elevation_map import ElevationMap
    from elevmap.map.visibility import visibility_cleanup, visibility_cleanup_reference

    fn = visibility_cleanup if impl == "numba" else visibility_cleanup_reference
    origin = np.array([-2.5, 0.5, 1.0])
    point = np.array([[3.5, 0.5, -1.5]])        # 1.5 m too low: its ray passes at -0.46 m over x in [1, 2)
    for var, cleared in ((None, 1), (np.array([0.6 ** 2]), 0)):   # with 3 sigma = 1.8 m the ray ends at +0.3
        m = ElevationMap(7.0, 1.0, fusion_params=FusionParams(min_points=1))
        m.update(np.array([[1.5, 0.5, 0.0]]), np.array([1e-6]), stamp=0.0)
        assert fn(m.data, m.geometry, origin, point, 1.0, height_var=var) == cleared
        assert m.is_known()[4, 3] == (cleared == 0)
    with pytest.raises(ValueError, match="height_var must have shape"):
        fn(m.data, m.geometry, origin, point, 1.0, height_var=np.ones(3))
