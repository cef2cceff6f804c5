"""Queries on the map: interpolated heights, height scans, grid_map export and files, checked by hand on
3 x 3 maps of 1 m cells (x and y in [-1, 2), cell centres -0.5, 0.5, 1.5), on exact planes, and numba
against the NumPy reference."""

import math
import os
import zipfile

import numpy as np
import pytest

from elevmap import ElevationMap, FusionParams
from elevmap.map import queries as q
from elevmap.map import storage
from elevmap.map.layers import ELEVATION, LAYERS, POINTS, VARIANCE


def small_map() -> ElevationMap:
    """3 x 3 cells of 1 m, window gx, gy in {-1, 0, 1}: map index i = gx + 1."""
    return ElevationMap(length_m=3.0, resolution_m=1.0)


def set_cell(m: ElevationMap, i: int, j: int, h: float, var: float = 0.01, points: float = 10.0) -> None:
    """Write cell (i, j) (map index) through the buffer index, with enough points to be known."""
    bi, bj = m.geometry.buffer_index([i, j])
    m.data[ELEVATION, bi, bj] = h
    m.data[VARIANCE, bi, bj] = var
    m.data[POINTS, bi, bj] = points


def filled_small_map() -> tuple[ElevationMap, np.ndarray, np.ndarray]:
    """Every cell known: h[i, j] = 10 i + j + 1, var[i, j] = (i + 1) / 100 + j / 1000."""
    m = small_map()
    h = np.array([[10.0 * i + j + 1 for j in range(3)] for i in range(3)])
    v = np.array([[(i + 1) / 100 + j / 1000 for j in range(3)] for i in range(3)])
    for i in range(3):
        for j in range(3):
            set_cell(m, i, j, h[i, j], v[i, j])
    return m, h, v


def rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def pose(yaw: float, xyz, roll: float = 0.0, pitch: float = 0.0) -> np.ndarray:
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    T = np.eye(4)
    T[:3, :3] = rot_z(yaw) @ Ry @ Rx
    T[:3, 3] = xyz
    return T


# ---------------------------------------------------------------------------------------------
# height_at
# ---------------------------------------------------------------------------------------------
def test_cell_centres_are_exact():
    m, h, v = filled_small_map()
    xs, ys = m.cell_centres()
    np.testing.assert_array_equal(xs, [-0.5, 0.5, 1.5])
    for i in range(3):
        for j in range(3):
            assert m.height_at([xs[i], ys[j]]) == (h[i, j], v[i, j])
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    hh, vv = m.height_at(np.column_stack([X.ravel(), Y.ravel()]))
    assert hh.shape == vv.shape == (9,)
    np.testing.assert_array_equal(hh, h.ravel())
    np.testing.assert_array_equal(vv, v.ravel())


def test_midpoints_are_means_and_weights_by_hand():
    m, h, v = filled_small_map()
    # between the centres of (0, 1) and (1, 1): x = 0, y = 0.5
    assert m.height_at([0.0, 0.5]) == pytest.approx(((h[0, 1] + h[1, 1]) / 2, (v[0, 1] + v[1, 1]) / 2))
    # the corner shared by (1, 1), (1, 2), (2, 1), (2, 2)
    assert m.height_at([1.0, 1.0])[0] == pytest.approx(h[1:, 1:].mean())
    # (0.25, 0.75): weights along x 0.25 (i=0), 0.75 (i=1); along y 0.75 (j=1), 0.25 (j=2)
    w = {(0, 1): 0.1875, (0, 2): 0.0625, (1, 1): 0.5625, (1, 2): 0.1875}
    got = m.height_at([0.25, 0.75])
    assert got[0] == pytest.approx(sum(wk * h[k] for k, wk in w.items()), rel=1e-14)
    assert got[1] == pytest.approx(sum(wk * v[k] for k, wk in w.items()), rel=1e-14)   # same weights, not squared


def test_unknown_neighbours_are_renormalised_away():
    m, h, v = filled_small_map()
    set_cell(m, 1, 2, np.nan, np.nan)
    w = {(0, 1): 0.1875, (0, 2): 0.0625, (1, 1): 0.5625}
    got = m.height_at([0.25, 0.75])
    assert got[0] == pytest.approx(sum(wk * h[k] for k, wk in w.items()) / 0.8125, rel=1e-14)
    assert got[1] == pytest.approx(sum(wk * v[k] for k, wk in w.items()) / 0.8125, rel=1e-14)
    set_cell(m, 0, 1, np.nan, np.nan)
    assert m.height_at([0.0, 0.5]) == (h[1, 1], v[1, 1])          # one of two known: its value
    for k in [(0, 2), (1, 1)]:
        set_cell(m, *k, np.nan, np.nan)
    assert all(math.isnan(x) for x in m.height_at([0.25, 0.75]))  # none of the four known
    # a point on an unknown cell's centre: its known neighbours have zero weight, so no data
    assert math.isnan(m.height_at([0.5, 0.5])[0])


def test_outside_is_nan_and_the_edge_extrapolates_the_inside_cells():
    m, h, v = filled_small_map()
    outside = [[-1.0001, 0.0], [2.0, 0.0], [0.0, 2.0], [0.0, -1.5], [1e6, -1e6]]   # 2.0 belongs to the next cell
    hh, vv = m.height_at(outside)
    assert np.all(np.isnan(hh)) and np.all(np.isnan(vv))
    assert m.height_at([-1.0, 0.5]) == (h[0, 1], v[0, 1])        # on the lower border: inside
    assert m.height_at([-0.9, 0.5]) == (h[0, 1], v[0, 1])        # beyond the last centre: constant
    assert m.height_at([1.99, 1.99]) == (h[2, 2], v[2, 2])
    assert m.height_at([1.9, 0.0])[0] == pytest.approx((h[2, 0] + h[2, 1]) / 2)


def test_height_at_after_a_move_with_wrap_around():
    m = small_map()
    xs, ys = m.cell_centres()
    for i in range(3):
        for j in range(3):
            set_cell(m, i, j, 10 * xs[i] + ys[j])                 # the plane h = 10 x + y
    m.move_to((1.4, 0.2))                                         # gx0: -1 -> 0; the x = -0.5 row leaves
    assert (m.geometry.gx0, m.geometry.gy0) == (0, -1)
    assert m.height_at([1.0, 0.0])[0] == pytest.approx(10.0)      # bilinear is exact on a plane
    assert m.height_at([1.5, -0.5])[0] == pytest.approx(14.5)
    assert m.height_at([2.2, 0.5])[0] == pytest.approx(15.5)      # new row x = 2.5 unknown: renormalised
    assert math.isnan(m.height_at([-0.5, 0.5])[0])                # left the window
    assert math.isnan(m.height_at([2.5, 0.5])[0])
    set_cell(m, 2, 1, 25.5)                     # map (2, 1) = global (2, 0): buffer slot (2, 0), where gx=-1 was
    assert tuple(m.geometry.buffer_index([2, 1])) == (2, 0)
    assert m.height_at([2.5, 0.5])[0] == 25.5
    assert m.height_at([2.0, 0.5])[0] == pytest.approx(20.5)


def test_height_at_after_a_real_update():
    one = FusionParams(neighbour_radius=0, min_points=1)           # one point per cell counts
    m = ElevationMap(length_m=3.0, resolution_m=1.0, fusion_params=one)
    m.update(np.array([[0.5, 0.5, 1.0], [-0.5, 0.5, 3.0]]), np.array([1e-4, 1e-4]))
    h, v = m.height_at([0.0, 0.5])
    assert h == pytest.approx(2.0) and v == pytest.approx(1e-4)
    # with the neighbourhood spread, two neighbours 2 m apart with variances 1e-4 are not both right:
    # each gets tau^2 = (Q - 1) / (S1 - S2 / S1) = (2e4 - 1) / 1e4: Q = 1e4 (1^2 + 1^2), S1 = 2e4, S2 = 2e8
    m = ElevationMap(length_m=3.0, resolution_m=1.0, fusion_params=FusionParams(min_points=1))
    m.update(np.array([[0.5, 0.5, 1.0], [-0.5, 0.5, 3.0]]), np.array([1e-4, 1e-4]))
    h, v = m.height_at([0.0, 0.5])
    assert h == pytest.approx(2.0) and v == pytest.approx(1e-4 + (2e4 - 1) / 1e4)
    # with the default min_points (3) one point does not make a cell known
    m = small_map()
    m.update(np.array([[0.5, 0.5, 1.0], [-0.5, 0.5, 3.0]]), np.array([1e-4, 1e-4]))
    assert np.isnan(m.height_at([0.0, 0.5])[0]) and not m.is_known().any()
    m.update(np.array([[0.5, 0.5, 1.0]] * 2 + [[-0.5, 0.5, 3.0]] * 2), np.full(4, 1e-4))
    assert m.is_known().sum() == 2 and m.height_at([0.0, 0.5])[0] == pytest.approx(2.0)


def random_map(rng, n_cells=12, res=0.25, move=(0.9, -1.3)) -> ElevationMap:
    m = ElevationMap(n_cells * res, res, centre_xy=(0.3, -0.2))
    m.move_to(move)
    shape = m.data.shape[1:]
    m.data[ELEVATION] = rng.normal(0, 1, shape)
    m.data[POINTS] = rng.choice([1.0, 2.0, 5.0, 10.0], shape, p=[0.1, 0.1, 0.4, 0.4])   # < 3: unknown
    m.data[VARIANCE] = rng.uniform(1e-4, 1e-2, shape)
    pick = rng.uniform(size=shape)
    m.data[ELEVATION][pick < 0.25] = np.nan
    m.data[ELEVATION][(pick >= 0.25) & (pick < 0.3)] = np.inf      # not finite: unknown
    m.data[ELEVATION][(pick >= 0.3) & (pick < 0.33)] = -np.inf
    m.data[VARIANCE][(pick >= 0.33) & (pick < 0.36)] = np.inf      # a known cell with infinite variance
    return m


def edge_points(m: ElevationMap) -> np.ndarray:
    """Points on and just beside every cell border and centre along both window edges."""
    g = m.geometry
    lo = np.array([g.gx0, g.gy0]) * g.resolution_m
    hi = lo + g.length_m
    xs = []
    for a, b in [(lo[0], lo[1]), (hi[0], hi[1])]:
        for d in (0.0, 0.5 * g.resolution_m):
            for e in (a + d, b - d):
                xs += [e, np.nextafter(e, -np.inf), np.nextafter(e, np.inf)]
    borders = lo[0] + g.resolution_m * np.arange(g.n + 1)
    xs = np.concatenate([xs, borders, borders + 0.5 * g.resolution_m])
    X, Y = np.meshgrid(xs, np.concatenate([xs, lo[1] + g.resolution_m * np.arange(g.n + 1)]), indexing="ij")
    return np.column_stack([X.ravel(), Y.ravel()])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_numba_equals_numpy_reference(seed):
    rng = np.random.default_rng(seed)
    m = random_map(rng)
    g = m.geometry
    centre = g.centre_xy
    pts = np.concatenate([centre + rng.uniform(-0.7, 0.7, (2000, 2)) * g.length_m, edge_points(m)])
    a = q.height_at(m, pts)
    b = q.height_at_reference(m, pts)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(np.isnan(x), np.isnan(y))
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-14)   # FMA contraction in the kernel
    assert 0.2 < np.isnan(a[0]).mean() < 0.8                    # both outcomes well exercised
    assert np.isinf(a[1]).any()                                  # the infinite variance came through
    # kernel level, NaN/inf coordinates too (the public functions refuse them)
    bad = np.array([[np.nan, 0.0], [0.0, np.inf], [-np.inf, np.nan], [centre[0], centre[1]]])
    ka = q._height_at_numba(m.data, g, bad[:, 0], bad[:, 1])
    kb = q._height_at_numpy(m.data, g, bad[:, 0], bad[:, 1])
    for x, y in zip(ka, kb):
        assert np.all(np.isnan(x[:3]))
        np.testing.assert_array_equal(x, y)


def test_height_at_rejects_bad_inputs():
    m = small_map()
    with pytest.raises(ValueError, match=r"shape \(2,\) or \(M, 2\)"):
        m.height_at([1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match=r"shape \(2,\) or \(M, 2\)"):
        m.height_at(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        m.height_at([[0.0, np.nan], [0.0, 0.0]])
    with pytest.raises(ValueError, match="non-finite"):
        q.height_at_reference(m, [np.inf, 0.0])
    with pytest.raises(ValueError, match="real numbers"):
        m.height_at(np.array(["a", "b"]))
    with pytest.raises(ValueError, match="ElevationMap"):
        q.height_at(np.zeros((3, 3)), [0.0, 0.0])
    h, v = m.height_at(np.zeros((0, 2)))
    assert h.shape == v.shape == (0,)


# ---------------------------------------------------------------------------------------------
# height scans
# ---------------------------------------------------------------------------------------------
PLANE = (0.3, -0.2, 0.1)    # h = a x + b y + c


def plane_map(centre=(0.0, 0.0)) -> ElevationMap:
    m = ElevationMap(4.0, 0.05, centre_xy=centre)
    xs, ys = m.cell_centres()
    a, b, c = PLANE
    m.data[ELEVATION] = m.geometry.wrap(a * xs[:, None] + b * ys[None, :] + c)
    m.data[POINTS] = 10.0
    m.data[VARIANCE] = 1e-4
    return m


def plane(xy):
    a, b, c = PLANE
    return a * xy[:, 0] + b * xy[:, 1] + c


def test_patterns():
    lg = q.legged_gym_pattern()
    assert lg.shape == (187, 2)
    np.testing.assert_allclose(np.unique(lg[:, 0]), np.linspace(-0.8, 0.8, 17), atol=1e-15)
    np.testing.assert_allclose(np.unique(lg[:, 1]), np.linspace(-0.5, 0.5, 11), atol=1e-15)
    np.testing.assert_array_equal(lg[11 * 3 + 7], [-0.5, 0.2])           # meshgrid(x, y, "ij") order
    ring = q.foot_ring_pattern()
    assert ring.shape == (52, 2) and sum(q.FOOT_RING_COUNTS) == 52
    r = np.hypot(ring[:, 0], ring[:, 1])
    radii, counts = np.unique(np.round(r, 12), return_counts=True)
    np.testing.assert_allclose(radii, q.FOOT_RING_RADII)
    assert tuple(counts) == q.FOOT_RING_COUNTS
    np.testing.assert_allclose(ring[0], [0.08, 0.0])                   # each ring starts on +x


def test_legged_gym_scan_on_a_plane_with_yaw_by_hand():
    T = pose(math.pi / 2, (1.0, 2.0, 0.6))
    m = plane_map(centre=(1.0, 2.0))
    s = m.height_scan(T)
    assert isinstance(s, q.ScanResult) and s.points_map.shape == (187, 2)
    # yaw 90 deg: base offset (x, y) -> map (-y, x); (0.8, -0.5) is point 16 * 11 + 0
    np.testing.assert_allclose(s.points_map[16 * 11], [1.0 + 0.5, 2.0 + 0.8], atol=1e-15)
    np.testing.assert_allclose(s.points_map[0], [1.0 + 0.5, 2.0 - 0.8], atol=1e-15)      # (-0.8, -0.5)
    np.testing.assert_allclose(s.points_map[5 * 11 + 10], [1.0 - 0.5, 2.0 - 0.3], atol=1e-15)  # (-0.3, 0.5)
    assert s.known.all()
    np.testing.assert_allclose(s.height, plane(s.points_map), atol=1e-12)
    np.testing.assert_allclose(s.variance, 1e-4, rtol=1e-12)


def test_scan_ignores_roll_and_pitch():
    m = plane_map()
    yaw = 0.4
    level = m.height_scan(pose(yaw, (0.1, -0.2, 0.5)))
    tilted = m.height_scan(pose(yaw, (0.1, -0.2, 0.5), roll=0.3, pitch=-0.25))
    np.testing.assert_allclose(tilted.points_map, level.points_map, atol=1e-14)
    Rz = rot_z(yaw)[:2, :2]
    np.testing.assert_allclose(level.points_map, q.legged_gym_pattern() @ Rz.T + [0.1, -0.2], atol=1e-15)
    np.testing.assert_allclose(level.height, plane(level.points_map), atol=1e-12)


def test_foot_rings_52_per_foot_around_each_foot():
    m = plane_map()
    yaw = -0.7
    T = pose(yaw, (0.2, 0.1, 0.55), roll=0.1)
    feet = np.array([[0.3, 0.2, -0.5], [0.3, -0.2, -0.5], [-0.3, 0.2, -0.5], [-0.3, -0.2, -0.5]])
    s = m.height_scan(T, pattern="foot_rings", feet_base=feet)
    assert s.points_map.shape == (208, 2) and s.height.shape == (208,) and s.known.all()
    feet_map = (feet @ T[:3, :3].T + T[:3, 3])[:, :2]
    for f in range(4):
        d = s.points_map[52 * f: 52 * (f + 1)] - feet_map[f]
        radii, counts = np.unique(np.round(np.hypot(d[:, 0], d[:, 1]), 9), return_counts=True)
        np.testing.assert_allclose(radii, q.FOOT_RING_RADII)
        assert tuple(counts) == q.FOOT_RING_COUNTS
        assert math.atan2(d[0, 1], d[0, 0]) == pytest.approx(yaw)       # rings turned by the heading
    np.testing.assert_allclose(s.height, plane(s.points_map), atol=1e-12)
    one = m.height_scan(T, pattern="foot_rings", feet_base=[[0.0, 0.0]])  # (F, 2): z = 0 in the base frame
    assert one.points_map.shape == (52, 2)
    np.testing.assert_allclose(one.points_map, q.foot_ring_pattern() @ rot_z(yaw)[:2, :2].T + T[:2, 3], atol=1e-14)


def test_scan_fill_and_custom_pattern():
    m = small_map()
    set_cell(m, 1, 1, 0.4)
    s = m.height_scan(np.eye(4), pattern=[[0.5, 0.5], [0.0, 0.5], [5.0, 0.0]], fill=-1.0)
    np.testing.assert_array_equal(s.height, [0.4, 0.4, -1.0])
    np.testing.assert_array_equal(s.known, [True, True, False])
    assert math.isnan(s.variance[2]) and s.variance[0] == 0.01


def test_height_scan_rejects_bad_inputs():
    m = small_map()
    T = np.eye(4)
    with pytest.raises(ValueError, match="T_map_base rotation part is not orthonormal"):
        m.height_scan(np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="reflection"):
        m.height_scan(np.diag([-1.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="4x4"):
        m.height_scan(np.eye(3))
    with pytest.raises(ValueError, match="non-finite"):
        m.height_scan(np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="pattern must be"):
        m.height_scan(T, pattern="rings")
    with pytest.raises(ValueError, match=r"pattern must have shape \(K, 2\)"):
        m.height_scan(T, pattern=np.zeros((5, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        m.height_scan(T, pattern=[[0.0, np.nan]])
    with pytest.raises(ValueError, match="needs feet_base"):
        m.height_scan(T, pattern="foot_rings")
    with pytest.raises(ValueError, match="only used with"):
        m.height_scan(T, feet_base=np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"feet_base must have shape \(F, 2\) or \(F, 3\)"):
        m.height_scan(T, pattern="foot_rings", feet_base=np.zeros((4, 4)))
    with pytest.raises(ValueError, match="fill"):
        m.height_scan(T, fill="zero")


# ---------------------------------------------------------------------------------------------
# grid_map export
# ---------------------------------------------------------------------------------------------
def grid_map_positions(msg: dict) -> np.ndarray:
    """(x, y) of every element of a data array, rebuilt from the message alone (grid_map's formula).

    data[k] is matrix element (row k % rows, col k // rows) (column-major); its buffer index is
    (row, col), its unwrapped index (row - outer_start, col - inner_start) mod size, and
    position = map_position + (L/2 - res/2) - res * unwrapped, per axis.
    """
    rows, cols = msg["size"]
    assert msg["layout"][0]["label"] == "column_index" and msg["layout"][1]["label"] == "row_index"
    k = np.arange(rows * cols)
    r, c = k % rows, k // rows
    ur = (r - msg["outer_start_index"]) % rows
    uc = (c - msg["inner_start_index"]) % cols
    res = msg["resolution"]
    px, py = msg["position"]
    x = px + (msg["length_x"] / 2 - res / 2) - res * ur
    y = py + (msg["length_y"] / 2 - res / 2) - res * uc
    return np.column_stack([x, y])


def check_export(m: ElevationMap) -> dict:
    msg = m.to_grid_map()
    assert msg["frame_id"] == "map" and msg["layers"] == list(LAYERS)
    assert msg["basic_layers"] == ["elevation", "variance"]
    xy = grid_map_positions(msg)
    ij, inside = m.geometry.map_index(xy)
    assert inside.all()
    assert len({(a, b) for a, b in ij}) == m.n * m.n             # every cell exactly once
    for name in LAYERS:
        d = msg["data"][name]
        assert d.dtype == np.float32 and d.shape == (m.n * m.n,)
        expect = m.layer(name)[ij[:, 0], ij[:, 1]].astype(np.float32)
        np.testing.assert_array_equal(d, expect)               # NaN in the same places, values equal
    h = msg["data"]["elevation"]
    known = np.isfinite(h)
    np.testing.assert_array_equal(h[known], np.float32(m.height_at(xy[known])[0]))   # at the cell centre
    return msg


def test_grid_map_export_by_hand():
    m, h, v = filled_small_map()
    set_cell(m, 0, 2, np.nan, np.nan)
    msg = check_export(m)
    assert msg["size"] == (3, 3) and msg["position"] == (0.5, 0.5) and msg["resolution"] == 1.0
    assert (msg["outer_start_index"], msg["inner_start_index"]) == (0, 0)
    e = msg["data"]["elevation"]
    assert e[0] == h[2, 2]          # grid_map (0, 0): the +x, +y corner
    assert e[1] == h[1, 2]          # (1, 0): one row down is one cell towards -x (column-major)
    assert e[3] == h[2, 1]          # (0, 1): one column on is one cell towards -y
    assert math.isnan(e[2])         # (2, 0) = map (0, 2), unknown
    sub = m.to_grid_map(layers=["variance", "time"], frame_id="odom")
    assert sub["layers"] == ["variance", "time"] and sub["basic_layers"] == ["variance"]
    assert sub["frame_id"] == "odom" and set(sub["data"]) == {"variance", "time"}


def test_grid_map_export_after_moves_with_wrap_around():
    m, h, v = filled_small_map()
    m.move_to((1.4, 0.2))           # x wraps
    set_cell(m, 2, 0, 99.0)
    assert m.geometry.start_index == (0, 2)
    check_export(m)
    m.move_to((-2.3, 3.6))          # both axes, one fully renewed
    set_cell(m, 1, 2, 7.0)
    set_cell(m, 0, 0, 8.0)
    msg = check_export(m)
    np.testing.assert_allclose(msg["position"], m.centre_xy)
    big = ElevationMap(2.0, 0.1)
    big.data[ELEVATION] = np.random.default_rng(5).normal(size=(20, 20))
    big.data[POINTS] = 10.0
    big.data[VARIANCE] = 1e-3
    big.move_to((0.73, -0.46))
    check_export(big)


def test_to_grid_map_rejects_bad_layers():
    m = small_map()
    with pytest.raises(ValueError, match="unknown layer 'height'"):
        m.to_grid_map(["elevation", "height"])
    with pytest.raises(ValueError, match="repeated"):
        m.to_grid_map(["elevation", "elevation"])


# ---------------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------------
def busy_map() -> ElevationMap:
    rng = np.random.default_rng(7)
    m = ElevationMap(2.0, 0.1, fusion_params=FusionParams(max_points_per_frame=5.0, mahalanobis_threshold=3.1),
                     visibility_cleanup=False, cleanup_stride=3)
    for f in range(3):
        pts = np.column_stack([rng.uniform(-1, 1, (500, 2)), rng.normal(0, 0.05, 500)])
        m.update(pts, rng.uniform(1e-4, 1e-3, 500), stamp=0.1 * f + 1e-9)
        m.move_to((0.37 * f, -0.21 * f))
    return m


def test_save_load_round_trip_is_bit_exact(tmp_path):
    m = busy_map()
    path = tmp_path / "map.npz"
    m.save(path)
    assert os.listdir(tmp_path) == ["map.npz"]                 # no temporary file left
    r = ElevationMap.load(path)
    assert r.data.tobytes() == m.data.tobytes()
    assert r.geometry == m.geometry and r.fusion_params == m.fusion_params
    assert (r.frames, r.last_stamp, r.visibility_cleanup, r.cleanup_stride) == (3, m.last_stamp, False, 3)
    assert r.last_stamp.hex() == m.last_stamp.hex()
    pts = np.column_stack([np.random.default_rng(8).uniform(-1, 1, (300, 2)), np.zeros(300)])
    m.update(pts, np.full(300, 1e-4), stamp=5.0)
    r.update(pts, np.full(300, 1e-4), stamp=5.0)
    assert r.data.tobytes() == m.data.tobytes()                 # and it goes on the same
    assert type(storage.load(path)) is ElevationMap


@pytest.mark.parametrize("version", ["v1", "v2"])
def test_maps_saved_before_the_spread_layers_still_load(tmp_path, version):
    import json

    from elevmap.map.layers import LAYERS, LAYERS_V1, LAYERS_V2

    old_layers, dropped = {"v1": (LAYERS_V1, ("spread_alpha", "neighbour_radius")),
                           "v2": (LAYERS_V2, ("neighbour_radius",))}[version]
    m = busy_map()
    path = tmp_path / "map.npz"
    m.save(path)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["data"] = arrays["data"][: len(old_layers)]
    arrays["layers"] = np.array(json.dumps(list(old_layers)))
    fp = json.loads(str(arrays["fusion_params"]))
    for key in dropped:
        fp.pop(key)
    arrays["fusion_params"] = np.array(json.dumps(fp))
    old = tmp_path / "old.npz"
    np.savez(old, **arrays)
    r = ElevationMap.load(old)
    assert r.data.shape[0] == len(LAYERS)
    np.testing.assert_array_equal(r.data[: len(old_layers)], m.data[: len(old_layers)])
    known = np.isfinite(r.layer("elevation"))
    new = ["neighbour_spread"] + (["spread"] if version == "v1" else [])
    for name in new:
        assert (r.layer(name)[known] == 0).all() and np.isnan(r.layer(name)[~known]).all()
    if version == "v1":
        assert (r.layer("info_sum") == 0).all() and (r.layer("scatter") == 0).all()
    r.update(np.column_stack([np.zeros((10, 2)), np.zeros(10)]), np.full(10, 1e-4), stamp=9.0)   # and it goes on


def test_save_any_name_and_never_updated_map(tmp_path):
    m = small_map()
    path = tmp_path / "sub" / "map.bin"
    storage.save(m, path)
    assert os.listdir(tmp_path / "sub") == ["map.bin"]        # np.savez added no ".npz"
    r = storage.load(path)
    assert math.isnan(r.last_stamp) and r.frames == 0 and r.data.tobytes() == m.data.tobytes()


def test_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    path = tmp_path / "map.npz"
    small_map().save(path)
    before = path.read_bytes()

    def broken_savez(f, **arrays):
        f.write(b"PK\x03\x04 half an archive")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", broken_savez)
    with pytest.raises(OSError, match="disk full"):
        busy_map().save(path)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["map.npz"]


def test_load_names_the_file_and_the_problem(tmp_path):
    good = tmp_path / "good.npz"
    busy_map().save(good)
    raw = good.read_bytes()

    cases = {
        "truncated.npz": raw[: len(raw) // 2],
        "empty.npz": b"",
        "garbage.npz": bytes(np.random.default_rng(1).integers(0, 256, 2000, dtype=np.uint8)),
    }
    flipped = bytearray(raw)
    flipped[len(raw) // 2] ^= 0xFF                              # inside the data array: CRC mismatch
    cases["flipped.npz"] = bytes(flipped)
    for name, content in cases.items():
        p = tmp_path / name
        p.write_bytes(content)
        with pytest.raises(ValueError, match=rf"{name}: (truncated or corrupt|empty file|not an \.npz archive)"):
            storage.load(p)

    np.save(tmp_path / "single.npy", np.zeros(3))
    with pytest.raises(ValueError, match=r"single.npy: not an \.npz archive but a single \.npy array"):
        storage.load(tmp_path / "single.npy")

    with np.load(good) as z:
        arrays = {k: z[k] for k in z.files}
    for name, change, match in [
        ("tag.npz", {"format": np.array("elevmap-map/2")}, "format tag is .*expected 'elevmap-map/1'"),
        ("notag.npz", {"format": None}, "no 'format' tag"),
        ("nodata.npz", {"data": None, "frames": None}, "missing key.*data, frames"),
        ("shape.npz", {"data": np.zeros((3, 4, 4))}, "data must be float64 of shape"),
        ("params.npz", {"fusion_params": np.array('{"gate": 2}')}, "bad parameters"),
        ("json.npz", {"settings": np.array("{not json")}, "settings is not valid JSON"),
        ("layers.npz", {"layers": np.array('["elevation"]')}, "layers .* do not match"),
    ]:
        a = {k: v for k, v in {**arrays, **change}.items() if v is not None}
        p = tmp_path / name
        np.savez(p, **a)
        with pytest.raises(ValueError, match=rf"{name}: {match}"):
            storage.load(p)
    with pytest.raises(FileNotFoundError):
        storage.load(tmp_path / "absent.npz")
    assert zipfile.is_zipfile(good)                             # the good file itself is fine
    storage.load(good)
