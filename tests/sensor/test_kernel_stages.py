"""The stages of the depth -> map-points kernel: the sorting networks of its medians, and the stages run one
by one (as ``elevmap bench`` times them) against the whole kernel."""

import itertools

import numpy as np
import pytest

from conftest import random_pose_cov, random_transform
from noise_model import D435, Workspace, depth_to_map_points, depth_to_map_points_reference
from noise_model.kernels import STAGES, depth_to_map_points_by_stage
from noise_model.formulas import sigma_z_from_gain, sigma_z_from_gain_and_root
from noise_model.geometry import default_block_px
from noise_model.kernels.compiled import (
    agrees_select, agrees_select_root, lane_median, rank_median, sort_lanes, sort_lanes_any, sorting_network,
)
from test_kernels import hostile_depth


def test_the_root_of_the_nearer_depth_is_the_smaller_root_and_the_agreement_is_unchanged():
    # the medians take each pixel's square root once: sqrt(min(a, b)) == min(sqrt(a), sqrt(b)) bit for bit,
    # sigma_z from the root is sigma_z_from_gain's, and the agreement decides the same, on both families
    rng = np.random.default_rng(3)
    z = rng.uniform(0.1, 10.0, 5000)
    zn = np.where(rng.random(z.size) < 0.5, z * rng.uniform(0.9, 1.1, z.size), rng.uniform(0.1, 10.0, z.size))
    zn[::97] = np.nan
    np.testing.assert_array_equal(np.sqrt(np.minimum(z, zn)), np.minimum(np.sqrt(z), np.sqrt(zn)))
    g = rng.uniform(0.0, 0.02, z.size)
    c0, c1, c2 = 0.0012, 0.0009, 0.0025
    np.testing.assert_array_equal(sigma_z_from_gain_and_root(z, np.sqrt(z), g, c0, c1, c2),
                                  sigma_z_from_gain(z, g, c0, c1, c2))
    for disp in (False, True):
        a = [agrees_select(x, y, w, 0.05, 4.0 * np.sqrt(2.0), c0, c1, c2, disp) for x, y, w in zip(zn, z, g)]
        b = [agrees_select_root(x, np.sqrt(x), y, np.sqrt(y), w, 0.05, 4.0 * np.sqrt(2.0), c0, c1, c2, disp)
             for x, y, w in zip(zn, z, g)]
        assert a == b and 0.05 < np.mean(a) < 0.95


@pytest.mark.parametrize("n", range(1, 14))
def test_sorting_network_sorts_every_zero_one_input(n):
    # the 0-1 principle: a network of compare-exchanges that sorts every 0/1 input sorts every input
    net = sorting_network(n)
    assert np.all(net[:, 0] < net[:, 1]) and np.all(net < n)
    cases = np.array(list(itertools.product((0.0, 1.0), repeat=n))).T.copy()       # (n, 2^n): one per column
    sort_lanes(cases, cases.shape[1], net)
    assert np.all(np.diff(cases, axis=0) >= 0)


@pytest.mark.parametrize("n", [5, 11, 7])
def test_the_written_out_networks_sort_as_the_generic_one_and_give_the_rank_median(n):
    rng = np.random.default_rng(n)
    m = 300
    vals = np.round(rng.uniform(0.5, 3.0, (n, m)), 2)                # ties on purpose
    k = rng.integers(1, n + 1, m)                                    # how many take part per column
    vals[np.arange(n)[:, None] >= k] = np.inf                        # the others: +inf
    a, b = vals.copy(), vals.copy()
    sort_lanes_any(a, m - 3, sorting_network(n))                     # the last columns stay as they were
    sort_lanes(b, m - 3, sorting_network(n))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a[:, m - 3:], vals[:, m - 3:])
    for j in range(m - 3):
        assert lane_median(a, j, k[j]) == rank_median(vals[:k[j], j].copy(), k[j]) == np.median(vals[:k[j], j])


@pytest.mark.parametrize("nthreads", [1, 2])
def test_stages_one_by_one_equal_the_kernel_bit_for_bit(nthreads):
    rng = np.random.default_rng(4)
    d, s = hostile_depth(rng, 240, 424, np.uint16)
    K, T, P = D435.intrinsics(424, 240), random_transform(rng), random_pose_cov(rng)
    whole = depth_to_map_points(d, K, T, P, depth_scale=s, nthreads=nthreads)
    ws = Workspace(240, 424)
    staged, seconds = depth_to_map_points_by_stage(d, K, T, P, depth_scale=s, nthreads=nthreads, workspace=ws)
    for x, y in zip(whole, staged):
        np.testing.assert_array_equal(x, y)
    assert tuple(seconds) == STAGES and all(t >= 0.0 for t in seconds.values())
    assert np.shares_memory(staged.points_map, ws.points_map)
    with pytest.raises(ValueError, match="workspace must be a Workspace"):
        depth_to_map_points_by_stage(d, K, T, P, depth_scale=s, workspace=Workspace(10, 10))


def test_a_workspace_serves_frames_of_different_block_sizes():
    rng = np.random.default_rng(8)
    d, s = hostile_depth(rng, 60, 80, np.uint16)
    K = np.array([[60.0, 0, 40], [0, 60.0, 30], [0, 0, 1]])
    ws = Workspace(60, 80)
    for b in (3, 5, 3):
        a = depth_to_map_points(d, K, np.eye(4), depth_scale=s, block_px=b, workspace=ws)
        fresh = depth_to_map_points(d, K, np.eye(4), depth_scale=s, block_px=b)
        for x, y in zip(a, fresh):
            np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("c1", [0.0007278, -0.0004])
def test_speckles_equal_the_reference_whether_or_not_sigma_grows_at_most_as_z_squared(c1):
    # the edges stage settles most pixels with a lower bound of a nearer neighbour's sigma_z that holds when
    # no coefficient is negative; with a negative one it tests them in full
    from noise_model import depth_to_map_points_reference
    rng = np.random.default_rng(12)
    d, s = hostile_depth(rng, 97, 131, np.uint16)
    K = D435.intrinsics(848, 480) * np.array([[131 / 848], [97 / 480], [1.0]])
    c = D435.axial_coefficients
    model = D435.with_coefficients((c[0], c1, c[2], c[3]))
    T = random_transform(rng)
    a = depth_to_map_points(d, K, T, depth_scale=s, model=model)
    b = depth_to_map_points_reference(d, K, T, depth_scale=s, model=model)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-6 * float(np.abs(y).max(initial=1.0)))


def test_kernel_equals_reference_on_real_d435_depth(realdata):
    """Raw D435 depth (aims_slam, a floor, a stand and glass; 640x480, 1 mm units) has windows of two
    surfaces nearly everywhere, so every pixel of this crop runs the row and surface medians: the kernel,
    with 1 and 2 threads, equals the NumPy reference there, and counts no value outside the map's bounds."""
    from noise_model.sim.stereo.realdata import read_png

    d = read_png(realdata / "aims_slam_d435_robot_floor" / "depth" / "5.png")[200:296, 240:400].copy()
    K = np.array([[383.8, 0.0, 321.7 - 240], [0.0, 383.8, 238.2 - 200], [0.0, 0.0, 1.0]])
    T = random_transform(np.random.default_rng(4))
    one = depth_to_map_points(d, K, T, depth_scale=0.001, nthreads=1)
    two = depth_to_map_points(d, K, T, depth_scale=0.001, nthreads=2)
    for x, y in zip(one, two):
        np.testing.assert_array_equal(x, y)
    ref = depth_to_map_points_reference(d, K, T, depth_scale=0.001)
    np.testing.assert_array_equal(one.pixel, ref.pixel)
    for x, y in zip(one[:3], ref[:3]):
        np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12)
    assert one.n_outside == ref.n_outside == 0
    ws = Workspace(*d.shape)
    depth_to_map_points(d, K, T, depth_scale=0.001, workspace=ws)
    assert (ws.blocks(default_block_px(d.shape[1]))[1][6] > 0).mean() > 0.5       # mostly mixed windows
