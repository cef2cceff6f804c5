"""The effects library (noise_model.sim.effects): forward models, fits, registry.

Every effect: its forward model changes what its docstring says (worked by hand or Monte Carlo), it runs
through the walk simulator's hook, it is seeded only by the generator passed in, it composes with
another, bad parameters raise ValueError naming them, and its fit recovers parameters drawn from
PARAM_RANGES within FIT_TOLERANCE on a small capture set simulated with it.
"""

import json
import math

import numpy as np
import pytest

from conftest import REALDATA

import noise_model as nm
from noise_model.sim import effects as E
from noise_model.analysis.capture_data import CaptureData, CaptureGeometry, simulate_capture
from noise_model.sim import Box, Scene, add_noise, simulate_walk
from noise_model.analysis.effect_fits import residuals as R

CAMERA = {"width": 424, "height": 240, "fx": 212.0, "fy": 212.0, "ppx": 211.5, "ppy": 119.5,
          "depth_scale": 0.001, "baseline_m": 0.05}
FB = 212.0 * 0.05
K = np.array([[212.0, 0.0, 211.5], [0.0, 212.0, 119.5], [0.0, 0.0, 1.0]])


def _wall(d, yaw=0.0):
    return CaptureGeometry.from_capture_set_entry(
        CAMERA, {"id": f"wall_z{d:.2f}_y{int(yaw):02d}", "target": {"kind": "wall", "distance_m": d, "yaw_deg": yaw}})


def _board(d, yaw=0.0):
    return CaptureGeometry.from_capture_set_entry(
        CAMERA, {"id": f"board_z{d:.2f}_y{int(yaw):02d}", "background_m": 3.0,
                 "target": {"kind": "board", "distance_m": d, "yaw_deg": yaw, "width_m": 0.6, "height_m": 0.9}})


# a small capture set: walls at 4 distances x 2 angles, boards at 4 distances x 2 angles, 8 frames each
WALLS = [_wall(d, y) for d in (0.6, 1.0, 1.5, 2.0) for y in (0.0, 50.0)]
BOARDS = [_board(d, y) for d in (0.9, 1.3, 1.7, 2.1) for y in (0.0, 30.0)]
FRAMES = 8


# frame_offset's fit reads one offset per frame: 8 captures x 8 frames hold only 56 degrees of freedom of its
# variance (a relative error of ~1 / sqrt(2 x 56) = 9 % in sigma), so its captures have 16 frames
FRAMES_OF = {"frame_offset": 16}


def _pseudo_real(name, params, seed):
    geoms = BOARDS if "board+background" in E.NEEDS[name] else WALLS
    eff = E.make_effect(name, **params)
    return [CaptureData.from_units(g, simulate_capture(g, FRAMES_OF.get(name, FRAMES), np.random.default_rng([seed, i]),
                                                       effects=[eff]))
            for i, g in enumerate(geoms)]


# ---------------------------------------------------------------------------------------------
# registry
# ---------------------------------------------------------------------------------------------
NAMES = ("disparity_noise", "disparity_quantization", "depth_bias", "invalid_band", "dropout", "correlated_noise",
         "static_pattern", "static_noise", "flying_pixels", "edge_fattening", "outliers", "axial_refit", "frame_offset")


def test_the_catalogue_identifiers_and_registries_agree():
    assert set(E.EFFECTS) == set(NAMES)
    for table in (E.PARAM_RANGES, E.FIT_TOLERANCE, E.NEEDS):
        assert set(table) == set(NAMES)
    assert sorted(E.ORDER) == sorted(NAMES)
    for name in NAMES:
        eff = E.make_effect(name)                                   # defaults
        assert eff.name == name
        json.dumps(eff.params)                                      # JSON-serialisable
        again = E.make_effect(name, **eff.params)                   # rebuilt from its params
        assert again.params == eff.params
        # every parameter drawn, tolerated and ranged is a parameter of the factory
        assert set(E.FIT_TOLERANCE[name]) <= set(E.PARAM_RANGES[name]) <= set(eff.params)
        p = E.draw_params(name, np.random.default_rng(0))
        for k, (lo, hi) in E.PARAM_RANGES[name].items():
            assert lo <= p[k] <= hi
            if k in E.INTEGER_PARAMS.get(name, ()):
                assert isinstance(p[k], int)
        assert E.make_effect(name, **p).params.items() >= {k: v for k, v in p.items()}.items()


def test_bad_parameters_raise_and_name_the_parameter():
    bad = {"disparity_noise": {"s_px": -0.1}, "disparity_quantization": {"subpixel_bits": 13},
           "depth_bias": {"scale": 0.1}, "invalid_band": {"margin_px": float("nan")},
           "dropout": {"p_1m": 1.0}, "correlated_noise": {"length_px": 0.0}, "static_pattern": {"sigma_px": 3.0},
           "static_noise": {"sigma_z_fraction": 11.0},
           "flying_pixels": {"fraction": 1.5}, "edge_fattening": {"width_px": -1.0},
           "outliers": {"fraction": 0.0}, "axial_refit": {"c0": 0.0}, "frame_offset": {"sigma_px": 0.0}}
    assert set(bad) == set(NAMES)
    for name, params in bad.items():
        (key,) = params
        with pytest.raises(ValueError, match=key):
            E.make_effect(name, **params)
    with pytest.raises(ValueError, match="no parameter"):
        E.make_effect("dropout", rate=0.1)
    with pytest.raises(ValueError, match="unknown effect"):
        E.make_effect("fog")
    with pytest.raises(ValueError, match="band_px"):
        E.flying_pixels(band_px="wide")
    with pytest.raises(ValueError, match="z must be a 2-D"):
        E.dropout()(np.zeros(5), np.zeros(5), np.random.default_rng(0), {})
    with pytest.raises(ValueError, match=r"context\['K'\]"):
        E.disparity_noise()(np.ones((4, 4)), np.zeros((4, 4)), np.random.default_rng(0), {})


def test_integer_parameters_round_and_canonical_order():
    assert E.disparity_quantization(4.6).params["subpixel_bits"] == 5
    assert E.flying_pixels(band_px=2.0).params["band_px"] == 2
    effs = [E.dropout(), E.depth_bias(), E.disparity_quantization(), E.axial_refit()]
    assert [e.name for e in E.canonical_order(effs)] == ["axial_refit", "depth_bias", "disparity_quantization",
                                                          "dropout"]


def test_within_tolerance():
    tol = E.FIT_TOLERANCE["depth_bias"]["scale"][1]
    ok, err = E.within_tolerance("depth_bias", {"scale": 0.98, "offset_px": 0.05},
                                 {"scale": 0.98 + 0.9 * tol, "offset_px": 0.05})
    assert ok and err["scale"] == (pytest.approx(0.9 * tol), tol)
    assert not E.within_tolerance("depth_bias", {"scale": 0.98, "offset_px": 0.05},
                                  {"scale": 0.98 + 1.1 * tol, "offset_px": 0.05})[0]
    assert not E.within_tolerance("disparity_noise", {"s_px": 0.1}, {"s_px": 0.12})[0]
    with pytest.raises(ValueError, match="s_px"):
        E.within_tolerance("disparity_noise", {}, {"s_px": 0.1})


def test_effects_from_report(tmp_path):
    report = {"format": "d435-gap/1", "effects": [
        {"name": "invalid_band", "params": {"margin_px": 6.0}, "gap_fit_after": 0.1},
        {"name": "static_pattern", "params": {"sigma_px": 0.03, "length_px": 5.0, "seed": 0}}]}
    effs = E.effects_from_report(report)
    assert [e.name for e in effs] == ["invalid_band", "static_pattern"]
    assert effs[0].params == {"margin_px": 6.0, "dark_margin_px": 0.0}          # a report without it: none
    path = tmp_path / "gap.json"
    path.write_text(json.dumps(report))
    assert [e.params for e in E.effects_from_report(path)] == [e.params for e in effs]
    assert E.effects_from_report({"effects": []}) == []
    path.write_text("{not json")
    for bad, msg in ((path, "not valid JSON"), (tmp_path / "none.json", "cannot read"), ({}, "no 'effects'"),
                     ({"effects": [{"params": {}}]}, "name"),
                     ({"effects": [{"name": "invalid_band", "params": {"margin": 1}}]}, r"effects\[0\]")):
        with pytest.raises(ValueError, match=msg):
            E.effects_from_report(bad)


# ---------------------------------------------------------------------------------------------
# forward models: exact or Monte Carlo checks
# ---------------------------------------------------------------------------------------------
def _ctx(z_true, **extra):
    c = {"K": K, "width": z_true.shape[1], "height": z_true.shape[0], "index": 0, "depth_scale": 0.001,
         "z_true": z_true}
    c.update(extra)
    return c


def _step(z_left=1.0, z_right=2.0, col=200, h=60, w=424):
    """A vertical step: columns < col at z_left, the others at z_right."""
    z = np.full((h, w), z_right)
    z[:, :col] = z_left
    return z, np.zeros_like(z)


def test_quantization_puts_disparities_on_the_lattice_and_invalid_band_cuts_the_columns():
    rng = np.random.default_rng(0)
    z_true = np.full((20, 424), 1.0)
    z = z_true + rng.normal(0, 0.01, z_true.shape)
    q = E.disparity_quantization(5)(z.copy(), np.zeros_like(z), rng, _ctx(z_true))
    d = FB / q
    assert np.allclose(d * 32, np.round(d * 32), atol=1e-9)
    assert np.abs(q - z).max() <= (1.0 + 0.04) ** 2 / (2 * 32 * FB)          # half a step at ~1 m
    # the band: u < f B / z + margin = 10.6 + 4 -> columns 0..14 have no data
    out = E.invalid_band(4.0)(z.copy(), np.zeros_like(z), rng, _ctx(z_true))
    cols = np.flatnonzero(np.isnan(out).all(axis=0))
    assert cols.tolist() == list(range(15)) and np.isfinite(out[:, 15:]).all()
    # on a walk frame without z_true, the depth itself decides
    ctx = _ctx(z_true)
    del ctx["z_true"]
    assert np.isnan(E.invalid_band(4.0)(z_true.copy(), z_true * 0, rng, ctx)[:, :15]).all()


def test_invalid_band_is_wider_on_a_surface_darker_than_the_frame_by_the_dark_margin():
    rng = np.random.default_rng(0)
    from noise_model.sim.effects.coverage import band_darkness

    z_true, theta = _step(z_left=3.0, z_right=1.0, col=212)           # a far background left of a near board
    # b = 1 / z^2: 1/9 on the left, 1 on the right, mean 5/9 -> darkness 1 - (1/9) / (5/9) = 0.8 on the left
    s = band_darkness(z_true, theta)
    assert np.allclose(s[:, :212], 0.8) and np.all(s[:, 212:] == 0.0)
    # u < f B / 3 + 2 + 2.5 x 0.8 = 3.533 + 4 -> columns 0..7 have no data; without the dark margin 0..5
    out = E.invalid_band(2.0, dark_margin_px=2.5)(z_true.copy(), theta, rng, _ctx(z_true))
    assert np.flatnonzero(np.isnan(out).all(axis=0)).tolist() == list(range(8))
    plain = E.invalid_band(2.0)(z_true.copy(), theta, rng, _ctx(z_true))
    assert np.flatnonzero(np.isnan(plain).all(axis=0)).tolist() == list(range(6))
    # a uniformly lit wall is nowhere darker than its own level: the dark margin changes nothing
    wall = np.full((20, 424), 1.0)
    assert np.array_equal(E.invalid_band(2.0, 2.5)(wall.copy(), wall * 0, rng, _ctx(wall)),
                          E.invalid_band(2.0)(wall.copy(), wall * 0, rng, _ctx(wall)), equal_nan=True)
    with pytest.raises(ValueError, match="dark_margin_px"):
        E.invalid_band(2.0, dark_margin_px=-1.0)
    with pytest.raises(ValueError, match="one shape"):
        band_darkness(z_true, theta[:, :100])


def test_depth_bias_and_static_pattern_in_disparity():
    rng = np.random.default_rng(1)
    z_true = np.full((240, 424), 1.5)
    ctx = _ctx(z_true, capture_id="c1", baseline_m=0.05)
    out = E.depth_bias(0.98, 0.1)(z_true.copy(), z_true * 0, rng, ctx)
    assert np.allclose(out, 0.98 * FB / (FB / 1.5 + 0.1))
    sp = E.static_pattern(sigma_px=0.04, length_px=5.0, seed=3)
    a = FB / sp(z_true.copy(), z_true * 0, rng, ctx) - FB / 1.5
    b = FB / sp(z_true.copy(), z_true * 0, np.random.default_rng(99), ctx) - FB / 1.5
    assert np.array_equal(a, b)                                        # constant over frames and generators
    assert a.std() == pytest.approx(0.04, rel=1e-9) and abs(a.mean()) < 1e-12
    other = FB / sp(z_true.copy(), z_true * 0, rng, _ctx(z_true, capture_id="c2")) - FB / 1.5
    assert abs(np.corrcoef(a.ravel(), other.ravel())[0, 1]) < 0.1     # another capture, another pattern
    # its correlation at 5 px along rows is exp(-1/2)
    rho = np.mean(a[:, 5:] * a[:, :-5]) / np.mean(a * a)
    assert rho == pytest.approx(math.exp(-0.5), abs=0.1)


def test_static_noise_follows_sigma_z_and_stays_over_frames():
    # a yawed wall: the field's standard deviation is the fraction times sigma_z(z_true, theta) pixel by pixel
    g = _wall(1.2, 40.0)
    z, th = g.render()
    sn = E.static_noise(sigma_z_fraction=0.7, length_px=4.0, seed=5)
    ctx = _ctx(z, capture_id=g.id, baseline_m=0.05)
    a = sn(z.copy(), th, np.random.default_rng(1), ctx) - z
    b = sn(z.copy(), th, np.random.default_rng(2), ctx) - z
    assert np.array_equal(a, b)                                        # constant over frames and generators
    ok = np.isfinite(z) & (z < 5.0)
    unit = a[ok] / (0.7 * nm.axial_sigma(z[ok], th[ok]))
    G = E.static_pattern(length_px=4.0, seed=5).field(z.shape, g.id)   # the same unit field as static_pattern
    assert np.allclose(unit, G[ok], atol=1e-9)
    # temporal mean of 40 frames of the reference plus the field: the field stays, the white noise averages out
    frames = simulate_capture(g, 40, np.random.default_rng(3), effects=[sn]).astype(float) * 0.001
    centre = (slice(100, 140), slice(190, 230))
    resid = frames[:, centre[0], centre[1]].mean(axis=0) - z[centre]
    expect = a[centre]
    assert np.corrcoef(resid.ravel(), expect.ravel())[0, 1] > 0.9
    assert frames[:, centre[0], centre[1]].std(axis=0, ddof=1).mean() == pytest.approx(
        float(np.mean(nm.axial_sigma(z[centre], th[centre]))), rel=0.06)   # temporal std unchanged


def test_static_noise_fit_tells_the_static_part_from_a_temporal_one():
    # a static field and a correlated field drawn afresh every frame, 12 frames: the static fit reads the
    # static part only, however strong the temporal part left in the temporal mean is
    true = {"sigma_z_fraction": 0.6, "length_px": 6.0, "seed": 4}
    effs = [E.static_noise(**true), E.correlated_noise(sigma_z_fraction=1.2, length_px=3.0)]
    real = [CaptureData.from_units(g, simulate_capture(g, 12, np.random.default_rng([21, i]), effects=effs))
            for i, g in enumerate(WALLS)]
    fit = E.fit_effect("static_noise", real, seed=5)
    ok, errors = E.within_tolerance("static_noise", true, fit)
    assert ok, f"fit {fit}, errors {errors}"


@pytest.mark.parametrize("name, size_key, small, large", [("static_noise", "sigma_z_fraction", 0.6, 2.4),
                                                            ("static_pattern", "sigma_px", 0.03, 0.12)])
def test_static_fits_give_the_typical_captures_size(name, size_key, small, large):
    # six walls with a static field of one size and two (the near fronto-parallel ones, standing for the
    # grazing captures of a physical D435, whose static error the effect's form cannot follow) with one four
    # times larger: the fit gives the six's size and length. Pooled over the captures' pixel pairs, the two
    # set it: sqrt((6 small^2 + 2 (4 small)^2) / 8) = 2.1 small.
    geoms = [_wall(d, y) for d in (0.8, 1.2, 1.6, 2.0) for y in (0.0, 40.0)]
    real = []
    for i, g in enumerate(geoms):
        size = large if g.distance_m < 1.5 and g.yaw_deg == 0 else small
        eff = E.make_effect(name, **{size_key: size, "length_px": 4.0, "seed": 3})
        real.append(CaptureData.from_units(g, simulate_capture(g, 6, np.random.default_rng([31, i]), effects=[eff])))
    fit = E.fit_effect(name, real, seed=5)
    ok, errors = E.within_tolerance(name, {size_key: small, "length_px": 4.0, "seed": 0}, fit)
    assert ok, f"fit {fit}, errors {errors}"


def test_disparity_noise_and_outliers_in_disparity_units():
    rng = np.random.default_rng(2)
    z_true = np.full((240, 424), 2.0)
    ctx = _ctx(z_true)
    d = np.stack([FB / E.disparity_noise(0.1)(z_true.copy(), z_true * 0, rng, ctx) for _ in range(4)])
    assert (d - FB / 2.0).std() == pytest.approx(0.1, rel=0.02)
    z = np.stack([E.disparity_noise(0.1)(z_true.copy(), z_true * 0, rng, ctx) for _ in range(4)]) - 2.0
    zc = z - z.mean()
    skew = np.mean(zc ** 3) / np.mean(zc ** 2) ** 1.5
    assert skew == pytest.approx(6 * 0.1 * 2.0 / FB, rel=0.25)          # right skew ~ 6 s z / (f B)
    d = FB / E.outliers(0.05, 1.0)(z_true.copy(), z_true * 0, rng, ctx) - FB / 2.0
    hit = np.abs(d) > 1e-9
    assert hit.mean() == pytest.approx(0.05, abs=0.003)
    assert d[hit].std() == pytest.approx(1.0, rel=0.05)


def test_edge_fattening_grows_the_foreground_by_its_width():
    rng = np.random.default_rng(3)
    z_true, th = _step()
    for w in (1.0, 3.0):
        out = E.edge_fattening(w)(z_true.copy(), th, rng, _ctx(z_true))
        fg = out < 1.5
        assert fg.sum(axis=1).tolist() == [200 + int(w)] * 60
    # a fractional width: the next column with that probability
    fg = np.stack([E.edge_fattening(2.3)(z_true.copy(), th, rng, _ctx(z_true)) < 1.5 for _ in range(20)])
    assert fg.sum(axis=2).mean() == pytest.approx(202.3, abs=0.05)
    # a slanted plane (the ground) has no discontinuity: nothing moves
    ground = np.linspace(3.0, 0.5, 240)[:, None] * np.ones((1, 424))
    assert np.array_equal(E.edge_fattening(4.0)(ground.copy(), ground * 0, rng, _ctx(ground)), ground)


def test_flying_pixels_lie_between_the_two_sides_in_the_band():
    rng = np.random.default_rng(4)
    z_true, th = _step()
    out = np.stack([E.flying_pixels(0.5, 1)(z_true.copy(), th, rng, _ctx(z_true)) for _ in range(10)])
    moved = out != z_true
    cols = np.flatnonzero(moved.any(axis=(0, 1)))
    assert cols.tolist() == [198, 199, 200, 201]                       # 2 (band + 1) columns
    assert moved[:, :, 198:202].mean() == pytest.approx(0.5, abs=0.03)
    d = FB / out[moved]
    assert (d > FB / 2.0).all() and (d < FB / 1.0).all()
    assert np.mean(d) == pytest.approx(0.5 * (FB / 1.0 + FB / 2.0), abs=0.1)   # lambda ~ U(0, 1)


def test_dropout_marginal_probability_and_blobs():
    z_true = np.full((240, 424), 1.0)
    th = np.full_like(z_true, math.radians(45.0))
    eff = E.dropout(p_1m=0.1, k_z=1.0, k_theta=1.0, length_px=3.0)
    p = float(eff.probability(np.array(1.0), np.array(math.radians(45.0))))
    assert p == pytest.approx(1 / (1 + math.exp(-(math.log(0.1 / 0.9) - math.log(math.cos(math.pi / 4))))))
    rng = np.random.default_rng(5)
    miss = np.stack([np.isnan(eff(z_true.copy(), th, rng, _ctx(z_true))) for _ in range(6)])
    assert miss.mean() == pytest.approx(p, abs=0.01)
    # holes come in blobs: neighbours are missing together far more often than p^2
    both = np.mean(miss[:, :, 1:] & miss[:, :, :-1])
    assert both > 3 * p * p
    white = np.stack([np.isnan(E.dropout(0.1, 1.0, 1.0, 0.3)(z_true.copy(), th, rng, _ctx(z_true)))
                      for _ in range(6)])
    assert np.mean(white[:, :, 1:] & white[:, :, :-1]) == pytest.approx(p * p, rel=0.15)


def test_axial_refit_rescales_the_reference_noise():
    g = _wall(1.5, 30.0)
    new = E.axial_refit(0.0005, 0.0003, 0.002, 0.011)
    frames = simulate_capture(g, 30, np.random.default_rng(6), effects=[new]).astype(float) * 0.001
    z, th = g.render()
    centre = (slice(100, 140), slice(190, 230))
    sd = frames[:, centre[0], centre[1]].std(axis=0, ddof=1).mean()
    model = nm.SensorModel(axial_coefficients=(0.0005, 0.0003, 0.002, 0.011))
    expect = float(np.mean(nm.axial_sigma(z[centre], th[centre], model)))
    assert sd == pytest.approx(math.sqrt(expect ** 2 + 1e-6 / 12), rel=0.05)
    # the paper's coefficients change nothing
    a = simulate_capture(g, 3, np.random.default_rng(6), effects=[E.axial_refit()])
    assert np.array_equal(a, simulate_capture(g, 3, np.random.default_rng(6)))


def test_fractions_of_sigma_z_follow_the_refitted_noise_after_axial_refit():
    # at 55 deg the paper's angle term makes its sigma ~4x the refit's (no angle term): a correlated field of
    # 1.0 sigma_z after the refit must add the refit's variance, not the paper's
    g = _wall(1.5, 55.0)
    refit = E.axial_refit(0.0005, 0.0003, 0.002, 0.0)
    corr = E.correlated_noise(sigma_z_fraction=1.0, length_px=2.0)
    frames = simulate_capture(g, 40, np.random.default_rng(7), effects=[refit, corr]).astype(float) * 0.001
    z, th = g.render()
    centre = (slice(100, 140), slice(190, 230))
    var = frames[:, centre[0], centre[1]].var(axis=0, ddof=1).mean()
    s_new = np.mean(nm.axial_sigma(z[centre], th[centre], nm.SensorModel(axial_coefficients=refit.params.values())))
    s_ref = np.mean(nm.axial_sigma(z[centre], th[centre]))
    assert s_ref > 3 * s_new
    assert var == pytest.approx(2 * s_new ** 2 + 1e-6 / 12, rel=0.1)
    # and the fit reads the fraction in units of the base's refitted sigma
    real = [CaptureData.from_units(w, simulate_capture(w, FRAMES, np.random.default_rng([11, i]),
                                                       effects=[refit, E.correlated_noise(sigma_z_fraction=0.8,
                                                                                          length_px=3.0)]))
            for i, w in enumerate(WALLS)]
    fit = E.fit_effect("correlated_noise", real, base_effects=[refit])
    assert E.within_tolerance("correlated_noise", {"sigma_z_fraction": 0.8, "length_px": 3.0}, fit)[0], fit


def test_axial_refit_counts_the_base_effects_variance_where_the_reference_is_truncated():
    # Monte Carlo: a quieter unit (refit) with a correlated field of 1.0 sigma_z on walls at 0 and 65 deg; at
    # 65 deg the paper's angle term truncates the reference noise, so the refit's fit takes the correlated
    # field's share of the temporal variance in closed form there (1 + k^2): it must not read it as white
    true = {"c0": 0.0006, "c1": 0.0004, "c2": 0.0024, "c_theta": 0.012}
    corr = E.correlated_noise(sigma_z_fraction=1.0, length_px=3.0)
    walls = [_wall(d, y) for d in (0.6, 1.0, 1.5, 2.0) for y in (0.0, 65.0)]
    real = [CaptureData.from_units(g, simulate_capture(g, FRAMES, np.random.default_rng([21, i]),
                                                       effects=[E.axial_refit(**true), corr]))
            for i, g in enumerate(walls)]
    fit = E.fit_effect("axial_refit", real, base_effects=[corr], seed=5)
    ok, errors = E.within_tolerance("axial_refit", true, fit)
    assert ok, (fit, errors)
    # counted as white, the angle term would come out ~sqrt(2) times too large
    assert fit["c_theta"] == pytest.approx(true["c_theta"], rel=0.1)
    # the closed form itself: k^2 of each correlated field, z^4 s^2 / (f B)^2 of each disparity noise, the rounding
    zz = np.array([1.0, 2.0])
    f, e = R._closed_form_base([corr, E.static_noise(0.7), E.frame_offset(0.02), E.disparity_quantization(5)],
                               zz, FB / zz, FB, 0.001)
    assert f == pytest.approx(2.0)
    assert e == pytest.approx((0.02 ** 2 + 2.0 ** -10 / 12) * 8.5 / FB ** 2 + 1e-6 / 12)


def test_frame_offset_moves_every_pixel_of_a_frame_alike():
    g = _wall(1.5, 30.0)
    eff = E.frame_offset(0.05)
    frames = simulate_capture(g, 40, np.random.default_rng(3), effects=[eff]).astype(float) * 0.001
    plain = simulate_capture(g, 40, np.random.default_rng(3)).astype(float) * 0.001
    z, _ = g.render()
    centre = (slice(100, 140), slice(190, 230))
    d = FB / frames[:, centre[0], centre[1]]
    dev = d - d.mean(axis=0)
    offsets = dev.reshape(40, -1).mean(axis=1)
    assert offsets.std(ddof=1) == pytest.approx(0.05, rel=0.3)          # 40 draws of N(0, 0.05^2)
    # the rest of a frame's deviation is the reference's: within a frame every pixel moved alike
    d0 = FB / plain[:, centre[0], centre[1]]
    dev0 = d0 - d0.mean(axis=0)
    rest = (dev - offsets[:, None, None]).std()
    assert rest == pytest.approx(dev0.std(), rel=0.05)
    # the per-pixel temporal variance grows by the offsets' variance times z^4 / (f B)^2
    grow = frames[:, centre[0], centre[1]].var(axis=0, ddof=1).mean() - plain[:, centre[0], centre[1]].var(
        axis=0, ddof=1).mean()
    assert grow == pytest.approx(np.mean(offsets.var(ddof=1) * z[centre] ** 4 / FB ** 2), rel=0.1)


def test_frame_offset_and_correlated_noise_are_told_apart():
    # data with both: each fit reads its own effect, the correlated field's length does not stretch to take the
    # frame-wide offset
    both = [E.correlated_noise(sigma_z_fraction=0.8, length_px=3.0), E.frame_offset(0.04)]
    real = [CaptureData.from_units(g, simulate_capture(g, FRAMES, np.random.default_rng([31, i]), effects=both))
            for i, g in enumerate(WALLS)]
    fit = E.fit_effect("correlated_noise", real, seed=5)
    assert E.within_tolerance("correlated_noise", both[0].params, fit)[0], fit
    fit = E.fit_effect("frame_offset", real, seed=5)
    assert E.within_tolerance("frame_offset", both[1].params, fit)[0], fit
    # one frame cannot give it: the fit says so
    single = [CaptureData.from_units(g, simulate_capture(g, 1, np.random.default_rng(i))) for i, g in enumerate(WALLS)]
    with pytest.raises(ValueError, match="frame_offset: needs captures of >= 2 frames"):
        E.fit_effect("frame_offset", single)


def test_a_disparity_model_simulates_at_the_captures_focal_length():
    g = _wall(1.5, 30.0)
    model = nm.D435.with_disparity(0.08)
    frames = simulate_capture(g, 30, np.random.default_rng(8), model,
                              effects=[E.correlated_noise(sigma_z_fraction=1.0, length_px=2.0)]).astype(float) * 1e-3
    z, _ = g.render()
    centre = (slice(100, 140), slice(190, 230))
    sd = frames[:, centre[0], centre[1]].std(axis=0, ddof=1).mean()
    s = float(np.mean(0.08 * z[centre] ** 2 / FB))                  # sigma_z = sigma_d z^2 / (f B)
    assert sd == pytest.approx(math.sqrt(2 * s ** 2 + 1e-6 / 12), rel=0.08)


# ---------------------------------------------------------------------------------------------
# hook contract: walks, composition, seeding
# ---------------------------------------------------------------------------------------------
def test_every_effect_runs_on_a_walk_frame():
    scene = Scene([Box((1.2, 0.0, 0.15), (0.4, 0.6, 0.3))])
    Kw = nm.D435.intrinsics(424, 240)
    plain = next(simulate_walk(scene, Kw, 424, 240, n_frames=1, rng=np.random.default_rng(7)))["depth"]
    for name in NAMES:
        params = E.draw_params(name, np.random.default_rng(1))
        eff = E.make_effect(name, **params)
        frame = next(simulate_walk(scene, Kw, 424, 240, n_frames=1, rng=np.random.default_rng(7),
                                   effects=[eff]))["depth"]
        assert frame.shape == plain.shape and frame.dtype == np.uint16
        assert not np.array_equal(frame, plain), name
        if name in ("edge_fattening", "flying_pixels"):
            # only next to the box's edges: the rest of the frame is untouched (same draws before them)
            assert np.mean(frame != plain) < 0.05, name


def test_two_effects_compose_in_sequence():
    g = _wall(1.2)
    bias, band = E.depth_bias(0.98, 0.05), E.invalid_band(5.0)
    both = simulate_capture(g, 4, np.random.default_rng(8), effects=[bias, band]).astype(float)
    only = simulate_capture(g, 4, np.random.default_rng(8), effects=[bias]).astype(float)
    cut = int(math.ceil(FB / 1.2 + 5.0))
    assert (both[:, :, :cut] == 0).all()
    assert np.array_equal(both[:, :, cut:], only[:, :, cut:])
    assert np.mean(only[only > 0]) * 0.001 == pytest.approx(0.98 * FB / (FB / 1.2 + 0.05), abs=5e-4)
    # quantisation after a bias: the biased depths land on the 1/32 px lattice
    q = simulate_capture(g, 2, np.random.default_rng(8),
                         effects=[bias, E.disparity_quantization(5)]).astype(float) * 0.001
    v = q[q > 0]
    k = FB * 32 / v
    assert np.mean(np.abs(k - np.round(k)) < 0.1) > 0.9


@pytest.mark.parametrize("name", NAMES)
def test_seeded_by_the_generator_only(name):
    g = _board(1.2, 20.0)
    eff = E.make_effect(name, **E.draw_params(name, np.random.default_rng(2)))
    a = simulate_capture(g, 2, np.random.default_rng(11), effects=[eff])
    b = simulate_capture(g, 2, np.random.default_rng(11), effects=[eff])
    c = simulate_capture(g, 2, np.random.default_rng(12), effects=[eff])
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


# ---------------------------------------------------------------------------------------------
# fits: parameters drawn from PARAM_RANGES are recovered within FIT_TOLERANCE
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", NAMES)
def test_fit_recovers_parameters_within_tolerance(name):
    seed = 1000 + NAMES.index(name)
    true = E.draw_params(name, np.random.default_rng(seed))
    real = _pseudo_real(name, true, seed)
    fit = E.fit_effect(name, real, seed=5)
    ok, errors = E.within_tolerance(name, true, fit)
    assert ok, f"{name}: true {true}, fit {fit}, errors {errors}"
    E.make_effect(name, **fit)                                   # a fit is a valid effect


def test_fit_accounts_for_effects_already_selected():
    # pseudo-real = invalid band + depth bias; the bias is fitted with the band as a base effect
    band = E.invalid_band(6.0)
    bias = E.depth_bias(0.985, 0.04)
    real = [CaptureData.from_units(g, simulate_capture(g, FRAMES, np.random.default_rng([9, i]), effects=[bias, band]))
            for i, g in enumerate(WALLS)]
    cache = {}
    fit = E.fit_effect("depth_bias", real, base_effects=[band], cache=cache)
    assert E.within_tolerance("depth_bias", bias.params, fit)[0], fit
    assert len(cache) == len(WALLS)                                # one base simulation per capture, reused
    again = E.fit_effect("invalid_band", real, base_effects=[E.make_effect("depth_bias", **fit)], cache=cache)
    assert abs(again["margin_px"] - 6.0) <= E.FIT_TOLERANCE["invalid_band"]["margin_px"][1]


def test_fit_effect_checks_its_input():
    real = [CaptureData.from_units(WALLS[0], simulate_capture(WALLS[0], 2, np.random.default_rng(0)))]
    with pytest.raises(ValueError, match="unknown effect"):
        E.fit_effect("fog", real)
    with pytest.raises(ValueError, match="board"):
        E.fit_effect("edge_fattening", real)
    with pytest.raises(ValueError, match="CaptureData"):
        E.fit_effect("depth_bias", [np.zeros((2, 240, 424))])
    with pytest.raises(ValueError, match="distinct ids"):
        E.fit_effect("depth_bias", real + real)
    assert E.usable_captures("flying_pixels", [WALLS[0], BOARDS[0]]) == [BOARDS[0]]


# ---------------------------------------------------------------------------------------------
# fits on single frames and few frames (the genuine D435 frames of ``elevmap gap --realdata``)
# ---------------------------------------------------------------------------------------------
def _pseudo_real_frames(name, params, seed, frames, geoms=None):
    geoms = geoms or (BOARDS if "board+background" in E.NEEDS[name] else WALLS)
    eff = E.make_effect(name, **params)
    return [CaptureData.from_units(g, simulate_capture(g, frames, np.random.default_rng([seed, i]), effects=[eff]))
            for i, g in enumerate(geoms)]


def _assert_valid(name, params):
    assert all(math.isfinite(float(v)) for v in params.values()), (name, params)
    E.make_effect(name, **params)                                   # the factory accepts them


@pytest.mark.parametrize("name", [n for n in NAMES if n != "frame_offset"])          # one frame cannot give it
def test_single_frame_fit_recovers_parameters_within_its_tolerance(name):
    # one frame per capture: temporal statistics give way to the frame's spatial ones
    seed = 2000 + NAMES.index(name)
    true = E.draw_params(name, np.random.default_rng(seed))
    real = _pseudo_real_frames(name, true, seed, 1)
    fit = E.fit_effect(name, real, seed=5)
    ok, errors = E.within_tolerance(name, true, fit, E.FIT_TOLERANCE_SINGLE_FRAME)
    assert ok, f"{name}: true {true}, fit {fit}, errors {errors}"
    _assert_valid(name, fit)


@pytest.mark.parametrize("name", ("disparity_noise", "correlated_noise", "static_pattern", "static_noise", "axial_refit"))
def test_two_frame_fits_of_temporal_statistics_meet_the_multi_frame_tolerance(name):
    seed = 3000 + NAMES.index(name)
    true = E.draw_params(name, np.random.default_rng(seed))
    fit = E.fit_effect(name, _pseudo_real_frames(name, true, seed, 2), seed=5)
    ok, errors = E.within_tolerance(name, true, fit)
    assert ok, f"{name}: true {true}, fit {fit}, errors {errors}"


# two fronto-parallel walls 0.2 m apart: one distance range, one angle
NEAR_WALLS = [_wall(1.4), _wall(1.6)]


def test_single_distance_depth_bias_is_a_scale_that_reproduces_the_bias_there():
    true = {"scale": 0.98, "offset_px": 0.05}
    fit = E.fit_effect("depth_bias", _pseudo_real_frames("depth_bias", true, 11, 1, NEAR_WALLS))
    assert fit["offset_px"] == 0.0                                  # scale and offset: not separable here
    # worked by hand: z' = 0.98 f B / (f B / z + 0.05) = s' z at z = 1.5 m
    expect = 0.98 * (FB / 1.5) / (FB / 1.5 + 0.05)
    assert fit["scale"] == pytest.approx(expect, abs=0.002)
    # at several distances the two are told apart again (the multi-frame tolerance holds on one frame)
    fit = E.fit_effect("depth_bias", _pseudo_real_frames("depth_bias", true, 11, 1))
    assert E.within_tolerance("depth_bias", true, fit)[0], fit


def test_single_distance_dropout_fits_the_level_and_no_slopes():
    true = {"p_1m": 0.06, "k_z": 1.2, "k_theta": 1.0, "length_px": 2.5}
    fit = E.fit_effect("dropout", _pseudo_real_frames("dropout", true, 12, 1, NEAR_WALLS))
    assert fit["k_z"] == 0.0 and fit["k_theta"] == 0.0             # one distance, one angle
    level = float(E.dropout(**true).probability(np.array(1.5), np.array(0.0)))   # ~0.11 at 1.5 m, 0 deg
    assert fit["p_1m"] == pytest.approx(level, rel=0.1)
    assert fit["length_px"] == pytest.approx(2.5, rel=0.4)


def test_single_distance_axial_refit_scales_the_papers_sigma():
    true = {"c0": 0.0006, "c1": 0.0004, "c2": 0.0024, "c_theta": 0.012}
    fit = E.fit_effect("axial_refit", _pseudo_real_frames("axial_refit", true, 13, 1, NEAR_WALLS))
    ref = np.array(nm.D435.axial_coefficients)
    got = np.array([fit[k] for k in ("c0", "c1", "c2", "c_theta")])
    assert got / ref == pytest.approx(np.full(4, got[0] / ref[0]), rel=1e-9)   # one factor on the paper's
    # the fitted sigma is the true one at the captures' distance (1.4-1.6 m, fronto-parallel)
    for z in (1.4, 1.6):
        s_true = true["c0"] + true["c1"] * z + true["c2"] * z * z
        s_fit = fit["c0"] + fit["c1"] * z + fit["c2"] * z * z
        assert s_fit == pytest.approx(s_true, rel=0.03)


def test_fits_use_only_the_region_of_interest():
    # the bottom rows show another surface (a wall at 2.5 m): outside the region of interest
    true = {"s_px": 0.08}
    real = _pseudo_real_frames("disparity_noise", true, 14, 1)
    other = simulate_capture(_wall(2.5), 1, np.random.default_rng(15))
    mixed = []
    for c in real:
        units = np.round(c.depth_m / 0.001)
        units[np.isnan(units)] = 0
        units = units.astype(np.uint16)
        units[:, 160:, :] = other[:, 160:, :]
        mixed.append(CaptureData.from_units(c.geometry, units))
    roi = np.zeros((240, 424), dtype=bool)
    roi[:160] = True
    rois = {c.id: roi for c in mixed}
    fit = E.fit_effect("disparity_noise", mixed, rois=rois)
    assert E.within_tolerance("disparity_noise", true, fit, E.FIT_TOLERANCE_SINGLE_FRAME)[0], fit
    assert E.fit_effect("disparity_noise", mixed)["s_px"] > 5 * true["s_px"]     # the other surface read as noise
    fit = E.fit_effect("depth_bias", mixed, rois=rois)
    assert fit["scale"] == pytest.approx(1.0, abs=0.002) and fit["offset_px"] == pytest.approx(0.0, abs=0.02)
    with pytest.raises(ValueError, match="boolean image"):
        E.fit_effect("disparity_noise", mixed, rois={mixed[0].id: roi[:10]})
    with pytest.raises(ValueError, match="regions of interest"):
        E.fit_effect("disparity_noise", mixed, rois={c.id: np.zeros_like(roi) for c in mixed})


def test_the_lattice_is_found_at_the_devices_fb():
    # the device computes depth with f B 0.3 % above the stated one: the stated f B hides the lattice
    rel = 0.003
    cam = dict(CAMERA, baseline_m=0.05 * (1 + rel))
    geoms = [CaptureGeometry.from_capture_set_entry(cam, {"id": g.id, "target": g.target}) for g in WALLS]
    eff = E.disparity_quantization(5)
    real = [CaptureData.from_units(w, simulate_capture(g, 1, np.random.default_rng(i), effects=[eff]))
            for i, (g, w) in enumerate(zip(geoms, WALLS))]
    fit = E.fit_effect("disparity_quantization", real)
    assert fit["subpixel_bits"] == 5 and fit["fb_rel"] == pytest.approx(rel, abs=2e-4)
    # the fitted effect puts a simulation at the stated f B on the device's lattice
    again = [CaptureData.from_units(w, simulate_capture(w, 1, np.random.default_rng(50 + i),
                                                        effects=[E.disparity_quantization(**fit)]))
             for i, w in enumerate(WALLS)]
    assert E.disparity_lattice(again)["cameras"][0]["fb_rel"] == pytest.approx(rel, abs=2e-4)
    found = E.disparity_lattice(real)
    assert found["subpixel_bits"] == 5
    (camera,) = found["cameras"]
    assert camera["fb_rel"] == pytest.approx(rel, abs=2e-4)         # 4 distances: no alias
    assert camera["fb_px_m"] == pytest.approx(FB * (1 + rel), rel=2e-4)
    assert camera["score"] > 0.9
    assert E.disparity_lattice(real, rel_range=0.0)["subpixel_bits"] != 5    # at the stated f B: not seen
    # data without a lattice: none found, at any f B
    plain = [CaptureData.from_units(g, simulate_capture(g, 1, np.random.default_rng(i))) for i, g in enumerate(WALLS)]
    assert E.disparity_lattice(plain)["subpixel_bits"] is None
    assert E.fit_effect("disparity_quantization", plain) == {"subpixel_bits": 10, "fb_rel": 0.0}


def _degenerate_single_frames():
    rng = np.random.default_rng(16)
    wall, board, steep = _wall(1.0), _board(1.2, 20.0), _wall(1.0, 80.0)
    blank = np.zeros((1, 240, 424), dtype=np.uint16)
    sparse = simulate_capture(_wall(1.5, 30.0), 1, rng)
    sparse[rng.random(sparse.shape) < 0.97] = 0
    every = [E.make_effect(n) for n in E.ORDER]
    tiny = np.zeros((240, 424), dtype=bool)
    tiny[100:104, 200:203] = True
    left = np.zeros((240, 424), dtype=bool)
    left[:, :150] = True
    yield "blank frame", [CaptureData.from_units(wall, blank)], None
    yield "97 % missing", [CaptureData.from_units(_wall(1.5, 30.0), sparse)], None
    yield "grazing 80 deg", [CaptureData.from_units(steep, simulate_capture(steep, 1, rng))], None
    yield "one wall, tiny roi", [CaptureData.from_units(wall, simulate_capture(wall, 1, rng))], {wall.id: tiny}
    frame = simulate_capture(board, 1, rng, effects=every)
    yield "board, every effect, left roi", [CaptureData.from_units(board, frame)], {board.id: left}


def test_fits_on_degenerate_single_frames_return_valid_parameters_or_say_why_not():
    for label, real, rois in _degenerate_single_frames():
        for name in NAMES:
            try:
                fit = E.fit_effect(name, real, rois=rois)
            except ValueError as exc:                               # the reason, named
                assert str(exc).strip(), (label, name)
                continue
            _assert_valid(name, fit)


def test_fits_on_the_genuine_d435_frames():
    from pathlib import Path

    root = REALDATA
    if not root.is_dir():
        pytest.skip(f"the genuine D435 recordings are not at {root}")
    from elevmap.commands.gap import realdata_captures

    caps, rois, *_ = realdata_captures(root)
    for name in NAMES:
        try:
            fit = E.fit_effect(name, caps, rois=rois)
        except ValueError as exc:       # edge effects: no board before a wall; frame_offset: single frames
            assert name in ("edge_fattening", "flying_pixels", "frame_offset"), (name, exc)
            continue
        _assert_valid(name, fit)
    # the D435's 5 fractional bits (librealsense disparity-transform.h), on the 848 x 480 frame at the
    # stated f B; the 424 x 240 frame's depth is not on a lattice
    found = E.disparity_lattice(caps, rois=rois)
    assert found["subpixel_bits"] == 5
    cams = {tuple(c["captures"]): c for c in found["cameras"]}
    big = cams[("opf848_board", "opf848_left_wall")]
    assert big["score"] > 0.9 and abs(big["fb_rel"]) < 0.5 * big["alias_rel"]
    assert cams[("opf424_board",)]["score"] < 0.2


@pytest.mark.parametrize("n_frames", [1, 4, 5])
def test_the_fits_temporal_median_is_numpys(n_frames):
    from noise_model.analysis.effect_fits._common import _temporal_median

    rng = np.random.default_rng(n_frames)
    x = np.round(rng.normal(1.0, 0.01, (n_frames, 7, 9)), 3)          # depth units: ties between frames
    x[rng.random(x.shape) < 0.1] = np.nan
    np.testing.assert_array_equal(_temporal_median(x), np.median(x, axis=0))


@pytest.mark.parametrize("n", [1, 2, 7, 1000, 1001])
def test_the_fits_median_is_numpys(n):
    from noise_model.analysis.effect_fits._common import _median

    rng = np.random.default_rng(n)
    x = np.round(rng.normal(0.0, 1.0, n), 2)                           # ties
    assert _median(x) == np.median(x)
    assert _median(x.reshape(-1, 1)) == np.median(x)
    xx = np.asfortranarray(np.stack([x, 2.0 * x]))                    # another memory order
    assert _median(xx) == np.median(xx)
    x[n // 2] = np.nan
    assert math.isnan(_median(x))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_lag_sums_kernel_equals_its_numpy_reference(dtype):
    from noise_model.analysis.effect_fits.correlation import _lag_sums, _lag_sums_reference

    rng = np.random.default_rng(4)
    for shape in ((3, 11, 13), (1, 6, 5)):
        x = rng.normal(0.0, 1.0, shape).astype(dtype)
        x[rng.random(shape) < 0.2] = 0.0                                 # pixels without a value
        lags = (0, 1, 2, 4, 7, 12)                                        # 7, 12: beyond a side of the image
        np.testing.assert_allclose(_lag_sums(x, lags), _lag_sums_reference(x, lags), rtol=1e-12, atol=1e-12)


def test_static_fields_are_shared_between_effect_objects_within_the_cache_size(monkeypatch):
    from noise_model.sim.effects import correlation as EC

    a, b = E.static_noise(0.8, 5.0, seed=3), E.static_pattern(0.03, 5.0, seed=3)
    ga = a.field((20, 30), "cap1")
    assert b.field((20, 30), "cap1") is ga                               # the same length, seed, capture
    assert not ga.flags.writeable
    assert abs(ga.mean()) < 1e-12 and ga.std() == pytest.approx(1.0)
    assert not np.array_equal(a.field((20, 30), "cap2"), ga)            # another capture, another field
    monkeypatch.setattr(EC, "FIELD_CACHE_BYTES", 3 * ga.nbytes)
    monkeypatch.setattr(EC, "_FIELDS", type(EC._FIELDS)())
    fields = [E.static_noise(0.8, 5.0, seed=s).field((20, 30), "cap1") for s in range(5)]
    assert sum(v.nbytes for v in EC._FIELDS.values()) <= 3 * ga.nbytes
    np.testing.assert_array_equal(fields[3], ga)                        # recomputed after eviction: the same


def test_axial_refit_gives_every_frame_what_a_fresh_effect_gives():
    rng = np.random.default_rng(6)
    zt = rng.uniform(0.5, 3.0, (9, 12))
    th = rng.uniform(0.0, 1.2, zt.shape)
    zt[0, :3] = np.nan
    th[0, :3] = np.nan
    params = dict(c0=0.0012, c1=0.0006, c2=0.003, c_theta=0.02)
    kept = E.make_effect("axial_refit", **params)
    for f, (zt_f, th_f) in enumerate([(zt, th), (zt, th), (zt * 1.01, th), (zt, th)]):
        z = zt_f + 0.003 * rng.standard_normal(zt.shape)
        ctx = {"K": np.eye(3), "index": f, "z_true": zt_f}
        got = kept(z.copy(), th_f, rng, dict(ctx))
        want = E.make_effect("axial_refit", **params)(z.copy(), th_f, rng, dict(ctx))
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("with_context_sigma", [False, True])
def test_the_sigma_image_is_the_pixels_sigma_filled_into_zeros(with_context_sigma):
    from noise_model.sim.effects.base import model_sigma, model_sigma_image

    rng = np.random.default_rng(8)
    zt = rng.uniform(0.5, 3.0, (7, 10))
    th = rng.uniform(0.0, 1.2, zt.shape)
    zt[1, :4] = np.nan
    hit = np.isfinite(zt)
    ctx = {"K": np.diag([400.0, 400.0, 1.0])}
    if with_context_sigma:
        ctx["sigma_z"] = np.where(hit, rng.uniform(0.001, 0.01, zt.shape), 0.0)
    want = np.zeros(zt.shape)
    want[hit] = 0.7 * model_sigma(nm.D435, zt, th, hit, ctx, "test")
    np.testing.assert_array_equal(model_sigma_image(nm.D435, zt, th, hit, ctx, "test", 0.7), want)
