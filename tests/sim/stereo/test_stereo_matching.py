"""The D4 matcher's stages: census, box-averaged cost, SGM, winner-take-all, segments; numba against NumPy."""

from dataclasses import replace

import numpy as np
import pytest

from noise_model.sim.stereo import census as C
from noise_model.sim.stereo import matcher as M
from noise_model.sim.stereo import sgm as G

SMALL = replace(M.PRESETS["default"], n_disp=12, sizes=None, rsm_remove=6)


def textured_pair(rng, h=24, w=40, shift=5, noise=0.0):
    """A random-texture left image and its right image: every point moved ``shift`` px to the left."""
    base = rng.integers(0, 1024, size=(h, w + shift))
    left = base[:, :w]
    right = base[:, shift:]
    if noise:
        left = left + rng.normal(0, noise, left.shape)
        right = right + rng.normal(0, noise, right.shape)
    return (np.clip(np.rint(left), 0, 1023).astype(np.uint16), np.clip(np.rint(right), 0, 1023).astype(np.uint16))


# ---------------------------------------------------------------------------------------------
# census and cost
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("radius", [1, 2, 4, 5])
def test_census_matches_reference(rng, radius):
    img = rng.integers(0, 1024, size=(13, 17))
    img[:, 3] = img[:, 4]                                    # ties: equal is not darker
    lo, hi = C.census_transform(img, radius, nthreads=1)
    lo_r, hi_r = C.census_transform_reference(img, radius)
    np.testing.assert_array_equal(lo, lo_r)
    np.testing.assert_array_equal(hi, hi_r)
    lo2, hi2 = C.census_transform(img, radius, nthreads=2)
    np.testing.assert_array_equal(lo, lo2)
    np.testing.assert_array_equal(hi, hi2)
    n_bits = (2 * radius + 1) ** 2 - 1
    assert int((np.bitwise_count(lo) + np.bitwise_count(hi)).max()) <= n_bits


def test_census_of_constant_image_is_zero():
    lo, hi = C.census_transform(np.full((9, 11), 500), 4)
    assert not lo.any() and not hi.any()


def test_census_bit_order():
    img = np.zeros((5, 5), np.int32)
    img[2, 2] = 10                                           # every neighbour is darker than the centre
    lo, hi = C.census_transform(img, 1)
    assert lo[2, 2] == 0xFF and hi[2, 2] == 0
    img = np.full((5, 5), 10, np.int32)
    img[1, 1] = 0                                            # offset (-1, -1) from (2, 2): bit 0 (row-major)
    lo, _ = C.census_transform(img, 1)
    assert lo[2, 2] == 1


@pytest.mark.parametrize("box", [0, 1, 3])
@pytest.mark.parametrize("n_disp", [1, 7, 45])
def test_cost_volume_matches_reference(rng, box, n_disp):
    left, right = textured_pair(rng, h=37, w=40, shift=4, noise=20.0)
    cv = C.cost_volume(left, right, n_disp, radius=2, box_radius=box, nthreads=1)
    ref = C.cost_volume_reference(left, right, n_disp, radius=2, box_radius=box)
    np.testing.assert_array_equal(cv, ref)
    np.testing.assert_array_equal(cv, C.cost_volume(left, right, n_disp, radius=2, box_radius=box, nthreads=2))
    assert cv.dtype == np.uint16 and int(cv.max()) <= C.COST_MAX
    if box == 0 and n_disp > 5:
        assert (cv[:, 3, 4:] == C.COST_MAX).all()             # right pixel outside the image


def test_cost_is_lowest_at_the_true_disparity(rng):
    left, right = textured_pair(rng, shift=5)
    cv = C.cost_volume(left, right, 12, radius=4, box_radius=0)
    assert (cv[:, 12:-4, 5] == 0).all()                      # (the right border clamps the left windows)
    assert (cv[:, 12:-4].argmin(axis=2) == 5).all()


def test_cost_luts():
    lut_c, lut_a = C.cost_luts(26.0, 800.0)
    assert lut_c[0] == 0 and lut_a[0] == 0
    assert np.all(np.diff(lut_c) >= 0) and np.all(np.diff(lut_a) >= 0)
    assert lut_c.max() <= C.TERM_MAX and lut_a.max() <= C.TERM_MAX
    with pytest.raises(ValueError, match="lambda"):
        C.cost_luts(0.0, 800.0)


def test_texture_measure_matches_reference(rng):
    img = rng.integers(0, 1024, size=(15, 19))
    np.testing.assert_array_equal(C.texture_measure(img, 4), C.texture_measure_reference(img, 4))
    assert (C.texture_measure(np.full((9, 9), 7), 4) == 0).all()


def test_to_10bit():
    assert C.to_10bit(np.array([[0, 255]], np.uint8)).tolist() == [[0, 1020]]
    assert C.to_10bit(np.array([[0, 1023]], np.uint16)).tolist() == [[0, 1023]]
    with pytest.raises(ValueError, match="1023"):
        C.to_10bit(np.array([[1024]], np.uint16))
    with pytest.raises(ValueError, match="dtype"):
        C.to_10bit(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="2-D"):
        C.to_10bit(np.zeros(3, np.uint8))


# ---------------------------------------------------------------------------------------------
# semi-global aggregation
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(1, 1, 1), (1, 9, 4), (11, 1, 5), (23, 37, 9)])
def test_aggregate_matches_reference(rng, shape):
    cost = rng.integers(0, C.COST_MAX + 1, size=shape).astype(np.uint16)
    S = G.aggregate(cost, 60, 342, nthreads=1)
    np.testing.assert_array_equal(S, G.aggregate_reference(cost, 60, 342))
    np.testing.assert_array_equal(S, G.aggregate(cost, 60, 342, nthreads=2))


@pytest.mark.parametrize("p1, p2", [(0, 14337), (14337, 14337), (3, 14337), (155, 190)])
def test_aggregate_at_the_largest_penalties_matches_reference(rng, p1, p2):
    """The kernels' int16 paths at the largest P2 that keeps S in uint16: costs at COST_MAX, random and 1-D."""
    for cost in (np.full((5, 6, 4), C.COST_MAX, np.uint16), rng.integers(0, C.COST_MAX + 1, (6, 7, 3)).astype(np.uint16),
                 rng.integers(C.COST_MAX - 40, C.COST_MAX + 1, (4, 5, 1)).astype(np.uint16)):
        S = G.aggregate(cost, p1, p2, nthreads=2)
        np.testing.assert_array_equal(S, G.aggregate_reference(cost, p1, p2))
    np.testing.assert_array_equal(G.aggregate(np.full((3, 3, 2), C.COST_MAX, np.uint16), p1, p2), 4 * C.COST_MAX)


def test_aggregate_of_a_constant_volume():
    cost = np.full((5, 6, 4), 100, np.uint16)
    np.testing.assert_array_equal(G.aggregate(cost, 10, 20), np.full((5, 6, 4), 400))


def test_aggregate_bad_input():
    with pytest.raises(ValueError, match="P1"):
        G.aggregate(np.zeros((2, 2, 2), np.uint16), 30, 20)
    with pytest.raises(ValueError, match="overflow"):
        G.aggregate(np.zeros((2, 2, 2), np.uint16), 30, 20000)
    with pytest.raises(ValueError, match="shape"):
        G.aggregate(np.zeros((2, 2), np.uint16), 1, 2)


# ---------------------------------------------------------------------------------------------
# winner-take-all, segments, the whole matcher
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kw", [
    {}, {"subpixel": "parabola"}, {"subpixel": "equiangular"}, {"subpixel_exponent": 1.7}, {"lr_threshold": -1},
    {"second_peak": 0}, {"texture_difference": 500}, {"lr_threshold": 0, "fractional_bits": 0},
])
def test_winner_take_all_matches_reference(rng, kw):
    p = replace(SMALL, **kw)
    S = rng.integers(0, 400, size=(9, 30, p.n_disp)).astype(np.uint16)
    S[:, :, 3] //= 4                                            # a favoured disparity, so that some pass
    S[2] = 50                                                   # a row of ties
    tex = rng.integers(0, 1000, size=(9, 30))
    a = M.winner_take_all(S, tex, p, nthreads=1)
    b = M.winner_take_all_reference(S, tex, p)
    np.testing.assert_array_equal(a.reason, b.reason)
    np.testing.assert_array_equal(a.disparity, b.disparity)
    c = M.winner_take_all(S, tex, p, nthreads=2)
    np.testing.assert_array_equal(a.disparity, c.disparity)
    assert (a.reason[2] != M.VALID).all()                       # ties have no unique minimum
    ok = np.isfinite(a.disparity)
    assert np.all(a.reason[ok] == M.VALID) and np.all(a.reason[~ok] != M.VALID)
    scale = 2 ** p.fractional_bits
    np.testing.assert_array_equal(a.disparity[ok] * scale, np.round(a.disparity[ok] * scale))


@pytest.mark.parametrize("t", [0.0, 0.05, 0.125, 0.3, 0.45, -0.2])
@pytest.mark.parametrize("p", [0.5, 1.0, 1.5, 2.0])
def test_power_subpixel_recovers_the_minimum_of_its_own_curve(t, p):
    """Costs sampled from a |d - t|^p + b at d = -1, 0, 1 give back t; p = 1 and 2 are the closed forms."""
    c0, c1, c2 = (3.0 * abs(d - t) ** p + 7.0 for d in (-1, 0, 1))
    off = M._subpixel_np(c0, c1, c2, M._POWER, p)
    assert abs(float(off) - t) < 2e-4
    if p == 1.0:
        assert abs(float(M._subpixel_np(c0, c1, c2, M._EQUIANGULAR)) - t) < 1e-12
    if p == 2.0:
        assert abs(float(M._subpixel_np(c0, c1, c2, M._PARABOLA)) - t) < 1e-12
    table = M.subpixel_table(p)
    assert table[0] == 0.5 and table[-1] == 0.0 and np.all(np.diff(table) <= 0)


def test_power_subpixel_bad_exponent():
    for bad in (0.0, -1.0, float("nan"), 5.0):
        with pytest.raises(ValueError, match="subpixel_exponent"):
            replace(SMALL, subpixel_exponent=bad)


def test_remove_small_segments_matches_reference(rng):
    disp = rng.choice([1.0, 1.5, 4.0, np.nan], size=(20, 25)).astype(np.float32)
    reason = np.where(np.isnan(disp), M.SECOND_PEAK, M.VALID).astype(np.uint8)
    for min_size in (0, 2, 5, 30):
        a = M.remove_small_segments(disp, reason, 0.6, min_size)
        b = M.remove_small_segments_reference(disp, reason, 0.6, min_size)
        np.testing.assert_array_equal(a.disparity, b.disparity)
        np.testing.assert_array_equal(a.reason, b.reason)
    blob = np.full((6, 6), np.nan, np.float32)
    blob[1:3, 1:3] = 2.0
    blob[4, 4] = 9.0
    out = M.remove_small_segments(blob, np.zeros((6, 6), np.uint8), 0.5, 2)
    assert np.isfinite(out.disparity).sum() == 4 and out.reason[4, 4] == M.SMALL_SEGMENT


def test_match_matches_reference(rng):
    left, right = textured_pair(rng, h=26, w=44, shift=6, noise=8.0)
    a = M.match(left, right, SMALL, nthreads=1)
    b = M.match_reference(left, right, SMALL)
    np.testing.assert_array_equal(a.reason, b.reason)
    np.testing.assert_array_equal(a.disparity, b.disparity)
    np.testing.assert_array_equal(a.disparity, M.match(left, right, SMALL, nthreads=2).disparity)


def test_match_finds_a_known_shift_and_the_left_band(rng):
    left, right = textured_pair(rng, h=30, w=60, shift=7)
    res = M.match(left, right, SMALL)
    inner = res.disparity[5:-5, 14:-5]
    assert np.isfinite(inner).all()
    np.testing.assert_allclose(inner, 7.0, rtol=0, atol=1 / 32)  # cost asymmetry about d = 7: one lattice step
    assert np.median(inner) == 7.0
    band = ~np.isfinite(res.disparity[5:-5, :7])               # columns x < d have no right pixel
    assert band.all()
    assert (res.reason[5:-5, :7] != M.VALID).all()


def test_match_input_checks():
    ok = np.zeros((240, 424), np.uint8)
    with pytest.raises(ValueError, match="not a D435 depth mode"):
        M.match(np.zeros((20, 30), np.uint8), np.zeros((20, 30), np.uint8))
    with pytest.raises(ValueError, match="unknown matcher preset"):
        M.match(ok, ok, "fast")
    with pytest.raises(ValueError, match="differ in size"):
        M.match(ok, np.zeros((240, 423), np.uint8), replace(SMALL, sizes=None))
    with pytest.raises(ValueError, match="subpixel"):
        replace(SMALL, subpixel="cubic")
    with pytest.raises(ValueError, match="P1"):
        replace(SMALL, p1=400)


def test_presets_hold_the_librealsense_values():
    d, h = M.PRESETS["default"], M.PRESETS["high_accuracy"]
    assert (d.census_radius, d.n_disp, d.p1, d.p2, d.second_peak, d.lr_threshold, d.texture_difference) == \
        (4, 126, 60, 342, 325, 24, 0)
    assert (h.p1, h.p2, h.second_peak, h.lr_threshold, h.texture_difference, h.rsm_remove) == \
        (155, 190, 647, 10, 1722, 136)
    assert (848, 480) in d.sizes and (424, 240) in d.sizes and (640, 480) in d.sizes


def test_disparity_to_depth():
    disp = np.array([[21.25, np.nan, 0.0, -1.0, 0.0003]], np.float32)
    z = M.disparity_to_depth(disp, 425.0, 0.05)
    assert z.dtype == np.uint16
    assert z.tolist() == [[1000, 0, 0, 0, 0]]                 # 0.0003 px -> 70.8 km: out of range
    assert M.disparity_to_depth(np.array([[10.0]]), 425.0, 0.05, 0.0001)[0, 0] == 21250
    with pytest.raises(ValueError, match="baseline"):
        M.disparity_to_depth(disp, 425.0, 0.0)


@pytest.mark.realdata
def test_real_d435_pair_band_shadow_and_fill(realdata):
    """The real pair: fill near the D435's 0.92, its left band and the box's occlusion shadow in place."""
    from noise_model.sim.stereo.realdata import real_pair

    r = real_pair(realdata / "simsense_d435_ir_pairs")
    assert abs(r["valid_fraction_ours"] - r["valid_fraction_d435"]) < 0.05
    diff = np.abs(np.subtract(r["band_ours_px424"], r["band_d435_px424"]))
    assert np.median(diff) <= 2 and diff.max() <= 3             # every sampled row within 3 px of the D435's
    assert abs(r["shadow_start_ours_px424"] - r["shadow_start_d435_px424"]) <= 3
    assert abs(r["shadow_width_ours_px424"] - r["shadow_width_d435_px424"]) <= 3
