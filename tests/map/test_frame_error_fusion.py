"""The map's per-frame information from the camera model's per-frame error: effective samples of a cell's
pixels under a correlation length, the variance ratio, the kernel against its NumPy reference."""

import math

import numpy as np
import pytest

import noise_model as nm
from elevmap.map.elevation_map import ElevationMap
from elevmap.map.fusion import FusionParams, _effective_samples, effective_samples
from elevmap.mapper import Camera, Mapper


def _brute_force_neff(a: int, ell: float) -> float:
    """n_eff of an a x a patch from the double sum over its pixel pairs (no separability used)."""
    v, u = np.mgrid[0:a, 0:a]
    p = np.stack([u.ravel(), v.ravel()], axis=1).astype(float)
    h2 = ((p[:, None, :] - p[None, :, :]) ** 2).sum(axis=2)
    n = a * a
    return n * n / np.exp(-h2 / (2 * ell * ell)).sum()


def test_effective_samples_by_hand_and_by_the_double_sum():
    # 2 x 2 pixels: n_eff = (2 / (1 + rho(1)))^2
    rho1 = math.exp(-0.5)
    assert effective_samples(np.array([4.0]), 1.0)[0] == pytest.approx((2 / (1 + rho1)) ** 2, rel=1e-12)
    for a, ell in [(3, 1.0), (5, 2.0), (8, 4.1), (12, 0.7)]:
        want = _brute_force_neff(a, ell)
        assert effective_samples(np.array([a * a], dtype=float), ell)[0] == pytest.approx(want, rel=1e-9)
        assert _effective_samples(float(a * a), ell) == pytest.approx(want, rel=1e-9)
    n = np.array([0.0, 1.0, 2.0, 7.0, 50.0, 900.0])
    assert np.array_equal(effective_samples(n, 0.0), n)                       # no correlation: every point
    assert np.allclose(effective_samples(n[1:], 1e3), 1.0, atol=1e-3)         # all one error: one sample
    ne = effective_samples(n, 4.1)
    assert np.all(ne <= np.maximum(n, 1.0)) and np.all(np.diff(ne) >= 0)
    assert np.allclose([_effective_samples(float(x), 4.1) for x in n], ne, rtol=1e-13)


def _points(rng, m_per_cell, cells=6, res=0.1):
    """m points in each of cells x cells cells of a flat floor at 0.5 m."""
    ij = np.stack(np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij"), -1).reshape(-1, 2)
    xy = (np.repeat(ij, m_per_cell, axis=0) + rng.uniform(0.05, 0.95, (len(ij) * m_per_cell, 2))) * res
    return np.c_[xy, 0.5 + rng.normal(0, 0.003, len(xy))]


def test_a_frame_adds_n_eff_over_r_points_of_information(rng):
    """An unknown cell fed m points of variance v in one frame: P = v r / n_eff(m, l)."""
    m, v, ell, r = 16, 1e-5, 2.0, 1.7
    pts = _points(rng, m)
    for impl in ("numba", "numpy"):
        emap = ElevationMap(2.0, 0.1, fusion_params=FusionParams(min_variance=1e-12, spread_alpha=None,
                                                                 neighbour_radius=0))
        emap.update(pts, np.full(len(pts), v), frame_error=(ell, r), impl=impl)
        P = emap.layer("variance")[np.isfinite(emap.layer("variance"))]
        assert P.size == 36
        assert np.allclose(P, v * r / _brute_force_neff(4, ell), rtol=1e-12)


def test_no_frame_error_is_the_map_as_before_and_the_cap_still_caps(rng):
    pts = _points(rng, 9)
    var = rng.uniform(1e-6, 1e-5, len(pts))
    maps = {}
    for key, fe, cap in [("none", None, None), ("zero", (0.0, 1.0), None), ("cap", None, 2.0),
                         ("cap_zero", (0.0, 1.0), 2.0), ("both", (50.0, 1.0), 2.0)]:
        emap = ElevationMap(2.0, 0.1, fusion_params=FusionParams(min_variance=1e-12, max_points_per_frame=cap))
        emap.update(pts, var, frame_error=fe)
        maps[key] = emap.data
    assert np.array_equal(maps["none"], maps["zero"], equal_nan=True)
    assert np.array_equal(maps["cap"], maps["cap_zero"], equal_nan=True)
    # a correlation length far beyond the cell: one sample per frame, below the cap of 2
    v_cap, v_both = maps["cap"][1], maps["both"][1]
    ok = np.isfinite(v_cap)
    assert np.all(v_both[ok] > 1.9 * v_cap[ok])


@pytest.mark.parametrize("frame_error", [(4.1, 2.0), (1.5, 1.0)])
def test_kernel_equals_reference_and_threads_do_not_matter(rng, frame_error):
    kw = dict(fusion_params=FusionParams(max_points_per_frame=20.0, change_min_points=2))
    a, b, c = (ElevationMap(4.0, 0.1, **kw) for _ in range(3))
    a.nthreads, c.nthreads = 1, 2
    for f in range(4):
        pts = np.c_[rng.uniform(-1, 1, (4000, 2)), rng.normal(0.01 * f, 0.01, 4000)]
        var = rng.uniform(1e-5, 1e-4, 4000)
        a.update(pts, var, frame_error=frame_error)
        c.update(pts, var, frame_error=frame_error)
        b.update(pts, var, frame_error=frame_error, impl="numpy")
    assert np.array_equal(a.data, c.data, equal_nan=True)
    for name in ("elevation", "variance", "points"):
        np.testing.assert_allclose(a.layer(name), b.layer(name), rtol=1e-12, atol=1e-15)


def test_bad_frame_error_is_refused_before_the_map_changes(rng):
    emap = ElevationMap(2.0, 0.1)
    pts = _points(rng, 4)
    for bad, msg in [((4.0, 0.5), "variance ratio"), ((-1.0, 1.0), "correlation length"), ((np.nan, 1.0), "finite"),
                     (3.0, "frame_error must be")]:
        with pytest.raises(ValueError, match=msg):
            emap.update(pts, np.full(len(pts), 1e-5), frame_error=bad)
    assert not np.isfinite(emap.layer("elevation")).any()


def test_the_mapper_takes_the_frame_error_from_the_cameras_model():
    """A camera whose model states a per-frame error maps with it (the length scaled to its focal length);
    the same frame through ElevationMap.update with that frame_error gives the same map."""
    K = np.array([[212.0, 0, 211.5], [0, 212.0, 119.5], [0, 0, 1]])
    model = nm.D435.with_coefficients(nm.D435.axial_coefficients, frame_variance_ratio=2.0,
                                      error_correlation_px=8.2, error_correlation_fx_px=424.0)
    depth = np.full((240, 424), 1000, dtype=np.uint16)
    T = np.eye(4)
    T[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]      # looking along +x, image down = -z
    T[:3, :3] = T[:3, :3] @ np.array([[1, 0, 0], [0, math.cos(1.0), -math.sin(1.0)],
                                      [0, math.sin(1.0), math.cos(1.0)]])
    T[2, 3] = 0.6
    out = {}
    for key, mdl in [("plain", nm.D435), ("frame", model)]:
        mp = Mapper(ElevationMap(4.0, 0.04), [Camera("c", K, 424, 240, model=mdl, valid_margin_px=0)], nthreads=1)
        mp.integrate("c", depth, T_map_cam=T)
        out[key] = (mp.map.data.copy(), mp.last_points)
    assert model.frame_error(212.0) == (4.1, 2.0)
    pts = out["plain"][1]
    ref = ElevationMap(4.0, 0.04)
    ref.nthreads = 1
    ref.update(pts.points_map, pts.height_var, sensor_origin_map=T[:3, 3], horizontal_cov=pts.horizontal_cov,
               frame_error=(4.1, 2.0))
    assert np.array_equal(out["frame"][0], ref.data, equal_nan=True)
    assert np.isfinite(out["plain"][0][0]).sum() > 50
    assert not np.array_equal(out["frame"][0], out["plain"][0], equal_nan=True)


def test_a_model_with_a_per_frame_sigma_maps_with_it():
    """A camera model with ``frame_noise`` maps as the camera whose model is its ``for_map()``."""
    from dataclasses import replace

    K = np.array([[212.0, 0, 211.5], [0, 212.0, 119.5], [0, 0, 1]])
    model = replace(nm.D435.with_coefficients((3.4e-4, -6.6e-4, 3.3e-3, 5.8e-5)), frame_variance_ratio=2.2,
                    error_correlation_px=4.0, error_correlation_fx_px=212.0, frame_noise=(3e-4, 4e-4, 3.5e-3, 3e-4))
    depth = np.full((240, 424), 1500, dtype=np.uint16)
    T = np.eye(4)
    T[:3, :3] = [[0, -0.5, 0.8660254037844386], [-1, 0, 0], [0, -0.8660254037844386, -0.5]]
    T[2, 3] = 0.6
    maps = []
    for mdl in (model, model.for_map(), nm.D435.with_coefficients(model.axial_coefficients)):
        mp = Mapper(ElevationMap(4.0, 0.04), [Camera("c", K, 424, 240, model=mdl, valid_margin_px=0)], nthreads=1)
        mp.integrate("c", depth, T_map_cam=T)
        maps.append(mp.map.data)
    assert np.array_equal(maps[0], maps[1], equal_nan=True)
    assert not np.array_equal(maps[0], maps[2], equal_nan=True)
