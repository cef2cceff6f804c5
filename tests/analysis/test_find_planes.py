"""The planes of a static stretch: per-pixel mean and temporal sigma, multi-plane RANSAC + refit, masks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from noise_model.analysis.plane_finder import MaskedPlane, find_planes, stretch_mean

K = np.array([[100.0, 0.0, 63.5], [0.0, 100.0, 47.5], [0.0, 0.0, 1.0]])
H, W = 96, 128


def test_stretch_mean_ignores_no_data_and_counts_only_pixels_seen_often_enough():
    d = np.full((4, 1, 3), np.nan)
    d[:, 0, 0] = [1.0, 1.2, 0.0, np.nan]          # 2 of 4 valid: mean 1.1, std 0.1414
    d[:, 0, 1] = [2.0, np.nan, np.nan, np.nan]      # 1 of 4: does not count
    d[:, 0, 2] = [3.0, 3.0, 3.3, 3.3]
    mean, std = stretch_mean(d)
    assert mean[0, 0] == pytest.approx(1.1) and std[0, 0] == pytest.approx(math.sqrt(0.02))
    assert np.isnan(mean[0, 1]) and np.isnan(std[0, 1])
    assert mean[0, 2] == pytest.approx(3.15) and std[0, 2] == pytest.approx(math.sqrt(4 * 0.15 ** 2 / 3))
    mean, _ = stretch_mean(d, min_valid_fraction=0.75)
    assert np.isnan(mean[0, 0]) and np.isfinite(mean[0, 2])
    with pytest.raises(ValueError, match="frames >= 2"):
        stretch_mean(d[:1])
    with pytest.raises(ValueError, match="infinite"):
        stretch_mean(np.full((2, 1, 1), np.inf))


def _plane_z(n, d):
    u, v = np.meshgrid((np.arange(W) - K[0, 2]) / K[0, 0], (np.arange(H) - K[1, 2]) / K[1, 1])
    den = n[0] * u + n[1] * v + n[2]
    with np.errstate(divide="ignore"):
        return np.where(den > 0, d / den, np.inf)


def _noisy(z, rng, frames=6, k=0.003):
    zt = np.where(np.isfinite(z), z, np.nan)
    return zt[None] + rng.normal(size=(frames, H, W)) * k * zt[None] ** 2


def test_two_planes_refound_with_masks_that_leave_out_where_they_meet(rng):
    """A concave corner: each plane within 0.2 deg, its noise measured, its mask on its side of the line
    where they meet and not on that line."""
    n1 = np.array([0.3, 0.0, 1.0]) / math.hypot(0.3, 1.0)
    n2 = np.array([-0.5, 0.2, 1.0]) / np.linalg.norm([-0.5, 0.2, 1.0])
    z1, z2 = _plane_z(n1, 1.2 * n1[2]), _plane_z(n2, 1.1 * n2[2])   # a concave corner seen from inside
    z = np.minimum(z1, z2)
    found = find_planes(_noisy(z, rng), K)
    assert len(found) == 2 and all(isinstance(p, MaskedPlane) for p in found)
    for n in (n1, n2):
        p = min(found, key=lambda p: 1 - abs(p.plane.normal @ n))
        assert math.degrees(math.acos(min(1.0, p.plane.normal @ n))) < 0.2
        assert p.plane.normal[2] > 0 and p.plane.offset_m > 0
        assert p.temporal_k_per_m == pytest.approx(0.003, rel=0.1)
        assert p.spread < 0.3
    # each mask on its own side of the line where the planes meet, nothing on that line (the pixels either
    # side of it, where the planes' depths differ by less than their noise bands), nearly everything else
    side = {id(p): (z1 <= z2) if abs(p.plane.normal @ n1) > abs(p.plane.normal @ n2) else (z2 < z1)
            for p in found}
    a, b = found[0].mask, found[1].mask
    assert not (a & b).any()
    for p in found:
        assert (p.mask & ~side[id(p)]).sum() == 0
    edge = np.zeros((H, W), dtype=bool)
    flip = (z1 <= z2)
    edge[:, 1:] |= flip[:, 1:] != flip[:, :-1]
    edge[:, :-1] |= flip[:, 1:] != flip[:, :-1]
    from scipy import ndimage

    assert edge.sum() > 50 and not ((a | b) & edge).any()
    away = ~ndimage.binary_dilation(edge, iterations=8)
    assert ((a | b) & away).sum() >= 0.97 * away.sum()


def test_a_band_of_scattered_points_is_not_a_plane(rng):
    """A plane and, beside it, scattered depths (removed by the cleaning) or blocks at two depths 3 cm
    apart (a 'plane' between them holds every block within its band, but no surface lies on it: its
    residuals fill the band, spread 0.375): only the plane is reported."""
    n = np.array([0.0, 0.0, 1.0])
    z = _plane_z(n, 1.2)
    z[:, 80:] = rng.uniform(0.8, 3.0, (H, W - 80))
    found = find_planes(_noisy(z, rng), K, max_planes=4)
    assert len(found) == 1
    assert found[0].mask[:, :78].mean() > 0.95 and found[0].mask[:, 82:].mean() < 0.01
    assert found[0].plane.offset_m == pytest.approx(1.2, abs=0.002)
    r, c = np.mgrid[0:H, 0:W - 64]
    z = _plane_z(n, 1.2)
    z[:, 64:] = 2.0 + 0.03 * ((r // 16 + c // 16) % 2)
    frames = _noisy(z, rng)
    found = find_planes(frames, K, max_planes=4)
    assert len(found) == 1 and found[0].plane.offset_m == pytest.approx(1.2, abs=0.002)
    loose = find_planes(frames, K, max_planes=4, max_spread=1.0)
    assert len(loose) == 2 and loose[1].spread == pytest.approx(0.375, abs=0.05)


def test_smaller_than_the_minimum_is_left_out_and_bad_input_is_named(rng):
    n = np.array([0.0, 0.0, 1.0])
    z = _plane_z(n, 1.5)
    z[:, 16:] = np.nan                                   # the plane covers 1/8 of the image
    assert len(find_planes(_noisy(z, rng), K, min_plane_fraction=0.1)) == 1
    assert find_planes(_noisy(z, rng), K, min_plane_fraction=0.2) == []
    with pytest.raises(ValueError, match="max_planes"):
        find_planes(_noisy(z, rng), K, max_planes=0)
    with pytest.raises(ValueError, match="n_sigma"):
        find_planes(_noisy(z, rng), K, n_sigma=-1.0)
    with pytest.raises(ValueError, match="frames >= 2"):
        find_planes(_noisy(z, rng)[:1], K)
