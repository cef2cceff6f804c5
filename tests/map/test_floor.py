"""The compute floor of ``elevmap bench``: plain information-form fusion, by hand and against its reference."""

import numpy as np
import pytest

from elevmap import ElevationMap
from elevmap.map.floor import FloorWorkspace, fuse_floor, fuse_floor_reference


@pytest.mark.parametrize("impl", ["numba", "numpy"])
def test_floor_fuses_by_the_information_form(impl):
    # 3 x 3 cells of 1 m, x and y in [-1, 2): two points in cell (1, 1), one in (2, 0), one outside
    m = ElevationMap(3.0, 1.0)
    pts = np.array([[0.5, 0.5, 1.0], [0.2, 0.9, 2.0], [1.5, -0.5, 3.0], [5.0, 0.0, 9.0]])
    var = np.array([1.0, 4.0, 0.5, 1.0])

    def fuse():
        if impl == "numba":
            return fuse_floor(m.data, m.geometry, pts, var, ws, nthreads=2)
        return fuse_floor_reference(m.data, m.geometry, pts, var)

    ws = FloorWorkspace(m.n)
    assert fuse() == 2
    h, v = m.layer("elevation"), m.layer("variance")
    # W = 1 + 1/4, WZ = 1 + 2/4: h = 1.5 / 1.25 = 1.2, P = 0.8
    assert h[1, 1] == pytest.approx(1.2) and v[1, 1] == pytest.approx(0.8)
    assert h[2, 0] == pytest.approx(3.0) and v[2, 0] == pytest.approx(0.5)
    assert np.isnan(h).sum() == 7
    assert fuse() == 2
    # with the prior (1.2, 0.8): P = 1 / (1/0.8 + 1.25) = 0.4, h = 0.4 (1.2/0.8 + 1.5) = 1.2
    h, v = m.layer("elevation"), m.layer("variance")
    assert h[1, 1] == pytest.approx(1.2) and v[1, 1] == pytest.approx(0.4)


def test_floor_kernel_equals_reference_and_thread_counts():
    rng = np.random.default_rng(5)
    maps = [ElevationMap(4.0, 0.1) for _ in range(3)]
    wss = [FloorWorkspace(maps[0].n) for _ in range(2)]
    for f in range(3):
        n = 20000
        pts = np.column_stack([rng.uniform(-2.5, 2.5, (n, 2)), rng.normal(0, 0.05, n)])
        pts[: n // 10, :2] = np.round(pts[: n // 10, :2] * 10) / 10            # exactly on cell borders
        var = rng.uniform(1e-4, 1e-3, n)
        counts = [fuse_floor(maps[0].data, maps[0].geometry, pts, var, wss[0], nthreads=1),
                  fuse_floor(maps[1].data, maps[1].geometry, pts, var, wss[1], nthreads=2),
                  fuse_floor_reference(maps[2].data, maps[2].geometry, pts, var)]
        assert counts[0] == counts[1] == counts[2] > 1000
        np.testing.assert_array_equal(maps[0].data, maps[1].data)
        np.testing.assert_allclose(maps[0].data, maps[2].data, rtol=1e-12)
        for m in maps:
            m.move_to((0.3 * f, -0.2 * f))


def test_floor_refuses_shapes_its_unchecked_kernel_would_index_out_of_bounds():
    m = ElevationMap(3.0, 1.0)
    pts = np.zeros((4, 3))
    var = np.ones(4)
    before = m.data.copy()
    for args, msg in (((m.data, m.geometry, pts, var[:3], FloorWorkspace(m.n)), "height_var"),
                      ((m.data, m.geometry, pts[:, :2], var, FloorWorkspace(m.n)), "points_map"),
                      ((m.data, m.geometry, pts.astype(np.float32), var, FloorWorkspace(m.n)), "points_map"),
                      ((m.data, m.geometry, pts, var, FloorWorkspace(m.n + 1)), "workspace"),
                      ((m.data[:, :2], m.geometry, pts, var, FloorWorkspace(m.n)), "data")):
        with pytest.raises(ValueError, match=msg):
            fuse_floor(*args)
        if msg != "workspace":
            with pytest.raises(ValueError, match=msg):
                fuse_floor_reference(*args[:4])
    np.testing.assert_array_equal(m.data, before)
