"""The model families' fits on arrays: the disparity family's sigma_d, held-out blocks of distance and angle,
and the axial noise of a plane per depth bin."""

from __future__ import annotations

import math

import numpy as np
import pytest

import noise_model as nm
from noise_model.analysis import characterization as ch, family_fit as ff, planes

#: A camera with sigma_d = 0.06 + 0.05 theta^2 px.
TRUE = nm.D435.with_disparity(0.06, 0.05, baseline_m=0.05)


def test_disparity_fit_recovers_sigma_d_and_fixes_s1_at_one_angle():
    rng = np.random.default_rng(0)
    z = rng.uniform(0.5, 2.5, 40)
    t = rng.choice(np.radians([10.0, 35.0, 60.0]), 40)
    s = TRUE.with_focal(383.8)
    sig = nm.axial_sigma(z, t, s) * np.exp(0.03 * rng.standard_normal(40))
    fit = ff.fit_disparity_model(z, t, sig, 383.8, 0.05)
    assert fit.s0 == pytest.approx(0.06, rel=0.05) and fit.s1 == pytest.approx(0.05, rel=0.15)
    assert fit.s1_fixed is None and np.all(np.isfinite(fit.stderr))
    np.testing.assert_allclose(fit.sigma_z(z, t, 383.8), nm.axial_sigma(z, t, nm.D435.with_disparity(
        fit.s0, fit.s1), fx_px=383.8), rtol=1e-12)
    one = ff.fit_disparity_model(z, np.full(40, 0.4), sig, 383.8, 0.05)
    assert one.s1 == 0.0 and "fixed at 0" in one.s1_fixed
    # sigma_d shrinking with the angle: s1 stays at its bound 0
    shrink = ff.fit_disparity_model(z, t, 0.1 * z * z / (383.8 * 0.05) * (1.0 - 0.3 * t), 383.8, 0.05)
    assert shrink.s1 == 0.0
    with pytest.raises(ValueError, match="theta_rad"):
        ff.fit_disparity_model(z, np.degrees(t), sig, 383.8, 0.05)
    with pytest.raises(ValueError, match="fx_px"):
        ff.fit_disparity_model(z, t, sig, -1.0, 0.05)


def test_heldout_blocks_prefer_the_family_the_data_came_from():
    rng = np.random.default_rng(1)
    zz, tt = np.meshgrid(np.arange(0.5, 2.6, 0.25), np.radians(np.arange(0.0, 76.0, 15.0)), indexing="ij")
    z, t = zz.ravel(), tt.ravel()
    noise = np.exp(0.05 * rng.standard_normal(z.size))
    disp = ff.heldout_errors(z, t, nm.axial_sigma(z, t, TRUE, fx_px=424.0) * noise, 424.0, 0.05)
    assert disp["better"] == "disparity" and disp["families"]["disparity"]["rms_log_error_common"] < 0.1
    paper = ff.heldout_errors(z, t, nm.axial_sigma(z, t) * noise, 424.0, 0.05)
    assert paper["better"] == "paper"
    labels, names = ff.distance_angle_blocks(z, t)
    assert len(names) == labels.max() + 1 == len(disp["blocks"])


def test_axial_noise_per_depth_bin_follows_the_depth(rng):
    """A floor seen at 60 deg from 0.5 to 3 m, 16 frames of noise z^2 sigma_d / (f B) with sigma_d = 0.06 px:
    each 0.1 m bin's sigma is the model's at its median depth (within its sampling error), and the bins
    tile the depths."""
    K = nm.D435.intrinsics(424, 240)
    n = np.array([0.0, -math.sin(math.radians(60)), -math.cos(math.radians(60))])
    plane = planes.Plane(-n, 0.6)
    vv, uu = np.mgrid[0:240, 0:424]
    up, vp = planes.normalised_coordinates(K, uu.ravel(), vv.ravel())
    z = plane.depth_at(up, vp)
    keep = np.isfinite(z) & (z > 0.5) & (z < 3.0)
    up, vp, z = up[keep], vp[keep], z[keep]
    model = nm.D435.with_disparity(0.06)
    sig = nm.axial_sigma(z, plane.theta_rad, model, fx_px=K[0, 0])
    frames = z[None] + sig[None] * rng.standard_normal((16, z.size))
    out = ch.axial_noise_bins(frames, up, vp, plane)
    assert out["reason"] is None and out["theta_rad"] == pytest.approx(math.radians(60))
    lo = [b["z_range_m"][0] for b in out["bins"]]
    assert lo == sorted(lo) and all(b["n_pixels"] >= ch.MIN_BIN_PIXELS for b in out["bins"])
    for b in out["bins"]:
        want = float(nm.axial_sigma(b["z_m"], plane.theta_rad, model, fx_px=K[0, 0]))
        assert b["sigma_z_m"] == pytest.approx(want, abs=4 * b["stderr_m"] + 0.02 * want)
        assert b["z_range_m"][0] <= b["z_m"] < b["z_range_m"][1]
        assert b["_z_pixels_m"].size == b["n_pixels"]
    # the whole region's single figure is one median over all those depths
    whole = ch.axial_noise(frames, up, vp, plane)
    assert out["bins"][0]["sigma_z_m"] < whole["sigma_z_m"] < out["bins"][-1]["sigma_z_m"]
    one = ch.axial_noise_bins(frames[:1], up, vp, plane)
    assert one["bins"] == [] and "2 frames" in one["reason"]
