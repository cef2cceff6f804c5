"""The valid-region margin: hand-worked rows, the numba kernel against its NumPy reference, bad input, the mapper."""

from __future__ import annotations

import numpy as np
import pytest

import noise_model as nm
from elevmap import ElevationMap
from elevmap.mapper import Camera, Mapper
from noise_model.valid_margin import (MAX_VALID_MARGIN_PX, drop_valid_margin, drop_valid_margin_reference,
                                      has_data)

IMPLS = (lambda d, m: drop_valid_margin(d, m, nthreads=1), lambda d, m: drop_valid_margin(d, m, nthreads=2),
         drop_valid_margin_reference)


@pytest.mark.parametrize("impl", IMPLS)
def test_hand_worked_rows(impl):
    # row 0: a no-data pixel at u = 5; row 1: all valid (only the borders cut); row 2: no-data run at the left
    d = np.full((3, 12), 1500, dtype=np.uint16)
    d[0, 5] = 0
    d[2, :3] = 0
    out = impl(d, 2)
    kept = out > 0
    assert kept[0].tolist() == [0, 0, 1, 0, 0, 0, 0, 0, 1, 1, 0, 0]
    assert kept[1].tolist() == [0, 0] + [1] * 8 + [0, 0]
    assert kept[2].tolist() == [0] * 5 + [1] * 5 + [0, 0]
    assert np.all(out[kept] == 1500)                       # kept pixels unchanged
    assert out.dtype == np.uint16


@pytest.mark.parametrize("impl", IMPLS)
def test_float_marks_dropped_pixels_nan_and_keeps_no_data_as_given(impl):
    d = np.array([[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0],
                  [1.0, 2.0, -1.0, 4.0, 5.0, 6.0, 7.0]], dtype=np.float32)
    d[0, 3] = np.inf
    out = impl(d, 1)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out[0], [np.nan, 2.0, np.nan, np.inf, np.nan, 6.0, np.nan])
    np.testing.assert_array_equal(out[1], [np.nan, np.nan, -1.0, np.nan, 5.0, 6.0, np.nan])


def test_zero_margin_and_margin_wider_than_the_image():
    d = np.arange(1, 13, dtype=np.uint16).reshape(2, 6)
    for impl in IMPLS:
        np.testing.assert_array_equal(impl(d, 0), d)
    for impl in IMPLS:
        assert not np.any(impl(d, 3) > 0)                  # 2 * 3 + 1 > 6 columns: nothing left


@pytest.mark.parametrize("dtype", [np.uint16, np.float32, np.float64])
@pytest.mark.parametrize("margin", [1, 2, 4, 7])
def test_kernel_equals_reference_on_random_images(dtype, margin):
    rng = np.random.default_rng(margin)
    for shape in ((1, 1), (1, 9), (9, 1), (37, 53)):
        d = (rng.random(shape) * 4000 if dtype == np.uint16 else rng.random(shape) * 4).astype(dtype)
        holes = rng.random(shape)
        d[holes < 0.12] = 0
        if dtype != np.uint16:
            d[(holes >= 0.12) & (holes < 0.17)] = np.nan
            d[(holes >= 0.17) & (holes < 0.19)] = -0.5
            d[(holes >= 0.19) & (holes < 0.2)] = np.inf
        ref = drop_valid_margin_reference(d, margin)
        for n in (1, 2):
            got = drop_valid_margin(d, margin, nthreads=n)
            assert got.dtype == d.dtype and got.shape == d.shape
            assert got.tobytes() == ref.tobytes()          # bit-identical, NaN payload included
        # what is dropped had data, lay within the margin of no data or a border, and nothing else changed
        ok = has_data(d)
        dropped = ok & ~has_data(ref)
        for v, u in zip(*np.nonzero(ok)):
            near = [c for c in range(u - margin, u + margin + 1) if c < 0 or c >= shape[1] or not ok[v, c]]
            assert dropped[v, u] == bool(near)
        np.testing.assert_array_equal(ref[~dropped], d[~dropped])


def test_non_contiguous_input_equals_contiguous():
    rng = np.random.default_rng(3)
    d = (rng.random((20, 40)) * 3000).astype(np.uint16)
    d[rng.random(d.shape) < 0.1] = 0
    view = d[:, ::2]
    np.testing.assert_array_equal(drop_valid_margin(view, 2), drop_valid_margin_reference(np.ascontiguousarray(view), 2))


@pytest.mark.parametrize("depth, margin, match", [
    (np.ones((2, 3, 4), np.uint16), 2, "2-D image"),
    (np.ones((0, 4), np.uint16), 2, "2-D image"),
    (np.ones((3, 4), np.int32), 2, "dtype int32"),
    (np.ones((3, 4), np.uint16), -1, "margin_px"),
    (np.ones((3, 4), np.uint16), MAX_VALID_MARGIN_PX + 1, "margin_px"),
    (np.ones((3, 4), np.uint16), 2.0, "margin_px"),
    (np.ones((3, 4), np.uint16), True, "margin_px"),
])
def test_bad_input_is_refused(depth, margin, match):
    for fn in (drop_valid_margin, drop_valid_margin_reference):
        with pytest.raises(ValueError, match=match):
            fn(depth, margin)


def test_camera_checks_its_margin():
    K = nm.D435.intrinsics(424, 240)
    for bad in (-1, MAX_VALID_MARGIN_PX + 1, 1.5, True, "3"):
        with pytest.raises(ValueError, match="valid_margin_px"):
            Camera("d435", K, 424, 240, valid_margin_px=bad)


@pytest.mark.parametrize("impl", ["numba", "numpy"])
def test_mapper_drops_the_margin_before_the_noise_model(impl):
    """A camera looking down at a floor, with a no-data band at the left as the D435 has: the points the
    mapper fuses come only from pixels at least the margin away from the band and the borders."""
    W, H, margin = 64, 48, 3
    K = nm.D435.intrinsics(424, 240).copy()
    K[0, 2], K[1, 2] = (W - 1) / 2, (H - 1) / 2
    depth = np.full((H, W), 1200, dtype=np.uint16)
    depth[:, :10] = 0                                       # the left invalid band
    depth[20, 30] = 0                                       # one pixel without data
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])                  # looking straight down
    T[2, 3] = 1.2
    counts = {}
    for m in (0, margin):
        mapper = Mapper(ElevationMap(4.0, 0.04), [Camera("d435", K, W, H, valid_margin_px=m)], nthreads=1)
        stats = mapper.integrate("d435", depth, T_map_cam=T, impl=impl)
        px = mapper.last_points.pixel
        u, v = px % W, px // W
        counts[m] = stats["points"]
        if m:
            assert u.min() >= 10 + margin and u.max() <= W - 1 - margin
            assert not np.any((v == 20) & (np.abs(u - 30) <= margin))
    expected = drop_valid_margin_reference(depth, margin)
    assert counts[margin] == int(np.count_nonzero(expected)) < counts[0] == int(np.count_nonzero(depth))
