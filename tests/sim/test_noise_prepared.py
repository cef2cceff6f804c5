"""A render prepared once and drawn many times gives add_noise's frames, draw for draw."""

from __future__ import annotations

import numpy as np
import pytest

from noise_model.sim.noise import add_noise, noisy_frame, prepare_noise


def _render(seed=0):
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.4, 3.0, (12, 17))
    z[rng.random(z.shape) < 0.1] = np.nan
    theta = rng.uniform(0.0, 1.4, z.shape)
    return z, theta


@pytest.mark.parametrize("with_effect", [False, True])
def test_prepared_frames_equal_add_noise_frames(with_effect):
    z, theta = _render()
    seen = []

    def effect(zn, th, rng, ctx):                   # reads the context and draws from the generator
        seen.append(ctx["index"])
        return zn + 0.001 * rng.standard_normal(zn.shape) + 0.0 * ctx["sigma_z"]

    effects = (effect,) if with_effect else None
    a, b = np.random.default_rng(5), np.random.default_rng(5)
    prepared = prepare_noise(z, theta, effects=effects, context={"index": 0})
    for f in range(4):
        ctx = {"index": f}
        assert np.array_equal(add_noise(z, theta, a, effects=effects, context=ctx), noisy_frame(prepared, b, ctx))
    assert seen == ([0, 0, 1, 1, 2, 2, 3, 3] if with_effect else [])


def test_the_prepared_sigma_cannot_be_written():
    z, theta = _render(1)
    prepared = prepare_noise(z, theta)
    with pytest.raises(ValueError):
        prepared.sigma_z[0, 0] = 1.0


@pytest.mark.parametrize("bad", ["units", "theta_deg", "shape"])
def test_prepare_checks_what_add_noise_checks(bad):
    z, theta = _render(2)
    if bad == "units":
        z = z * 1000.0
    elif bad == "theta_deg":
        theta = np.degrees(theta)
    else:
        theta = theta[:, :-1]
    with pytest.raises(ValueError):
        prepare_noise(z, theta)


def test_the_draws_are_one_standard_normal_image_per_frame():
    z, theta = _render(3)
    z[0, :4] = 70.0                                 # beyond the uint16 range of 1 mm units: no data
    prepared = prepare_noise(z, theta)
    a, b = np.random.default_rng(9), np.random.default_rng(9)
    for _ in range(3):
        got = noisy_frame(prepared, a)
        with np.errstate(invalid="ignore"):
            zn = z + b.normal(0.0, 1.0, z.shape) * prepared.sigma_z
            units = np.round(zn / 0.001)
            want = np.where(np.isfinite(units) & (zn > 0) & (units <= 65535), units, 0.0).astype(np.uint16)
        np.testing.assert_array_equal(got, want)
        assert np.all(got[np.isnan(z)] == 0) and np.any(got[0, :4] == 0)
    assert a.random() == b.random()                 # the generator is left where the reference leaves it
