"""noise_model.analysis.frame_error: the per-frame error a map sees (temporal + static) and its correlation
length, measured on synthetic captures whose disparity error is known."""

import math

import numpy as np
import pytest
from scipy import ndimage

from noise_model.analysis.capture_data import CaptureData, CaptureGeometry
from noise_model.analysis.frame_error import capture_frame_error, frame_offset_covariance, pooled_frame_error

CAMERA = {"model": "D435", "width": 424, "height": 240, "fx": 212.0, "fy": 212.0, "ppx": 211.5, "ppy": 119.5,
          "depth_scale": 0.001, "baseline_m": 0.05}
WALL = {"id": "wall", "target": {"kind": "wall", "distance_m": 1.0, "yaw_deg": 0.0, "pitch_deg": 0.0}}


def _field(rng, shape, ell_px):
    """A unit-variance Gaussian field with correlation exp(-h^2 / (2 l^2)) (white noise filtered by a
    Gaussian of standard deviation l / sqrt(2))."""
    f = ndimage.gaussian_filter(rng.standard_normal(shape), ell_px / math.sqrt(2.0), mode="wrap")
    return f / f.std()


def _capture(rng, sigma_t_px, static_px, ell_px, temporal_ell_px=0.0, frames=12, offset_px=0.0):
    g = CaptureGeometry.from_capture_set_entry(CAMERA, WALL)
    z, _ = g.render()
    d_true = g.fb_px_m / z
    static = static_px * _field(rng, z.shape, ell_px) if static_px else 0.0
    d = np.empty((frames,) + z.shape)
    for f in range(frames):
        noise = _field(rng, z.shape, temporal_ell_px) if temporal_ell_px else rng.standard_normal(z.shape)
        d[f] = d_true + static + sigma_t_px * noise + offset_px * rng.standard_normal()
    return CaptureData(g, g.fb_px_m / d)          # float depth [m], no quantisation


def test_independent_pixels_have_no_correlation_and_the_temporal_error_only(rng):
    row = capture_frame_error(_capture(rng, 0.05, 0.0, 0.0))
    assert row["reason"] is None
    assert row["ratio"] == pytest.approx(1.0, abs=0.01)
    assert row["length_px"] == 0.0 and abs(row["rho"][1]) < 0.02


def test_a_static_pattern_adds_its_variance_and_its_correlation_length(rng):
    """Static sigma = temporal sigma over l = 4 px: the per-frame error variance is twice the temporal
    one, rho(1) = exp(-1/32) / 2 and the fitted length is the pattern's."""
    row = capture_frame_error(_capture(rng, 0.05, 0.05, 4.0))
    assert row["ratio"] == pytest.approx(2.0, rel=0.08)
    assert row["rho"][1] == pytest.approx(0.5 * math.exp(-1 / 32), abs=0.05)
    assert row["length_px"] == pytest.approx(4.0, rel=0.15)


def test_a_correlated_temporal_error_is_measured_without_a_static_part(rng):
    row = capture_frame_error(_capture(rng, 0.05, 0.0, 0.0, temporal_ell_px=3.0))
    assert row["ratio"] == pytest.approx(1.0, abs=0.05)
    assert row["length_px"] == pytest.approx(3.0, rel=0.15)


def test_a_frame_wide_offset_adds_its_variance_to_the_ratio_not_to_the_length(rng):
    """Every pixel of a frame off by the same N(0, 0.04^2) px on top of a 0.05 px temporal and a 0.05 px
    static error over 4 px: ratio (T + S + O) / T = 1 + 1 + 0.64; the offset, common to all lags, leaves
    rho and the length as without it. 40 frames: the offset's variance from 40 draws is within about
    +-0.22 of its value (relative, one standard error), the tolerance 3 of them; the seed is fixed."""
    row = capture_frame_error(_capture(rng, 0.05, 0.05, 4.0, frames=40, offset_px=0.04))
    assert row["offset_var_d_px2"] == pytest.approx(0.04 ** 2, rel=0.6)
    assert row["ratio"] == pytest.approx(1.0 + 1.0 + row["offset_var_d_px2"] / 0.05 ** 2, rel=0.08)
    assert row["length_px"] == pytest.approx(4.0, rel=0.15)
    assert capture_frame_error(_capture(rng, 0.05, 0.0, 0.0))["offset_var_d_px2"] < 1e-5


def test_frame_offset_covariance_by_hand():
    """Two frames, six pixels in columns 0-5: the left third (columns 0, 1) has frame means -1, 1, the
    right third (4, 5) 1, -1 on one and 1, 3 on the other: covariances -2 (clipped to 0) and 2; the
    middle columns (2, 3) do not count."""
    cols = np.arange(6)
    dev = np.array([[-1, -1, 50, -50, 1, 1], [1, 1, -50, 50, -1, -1]], dtype=float)
    assert frame_offset_covariance(dev, cols) == 0.0
    dev2 = np.array([[-1, -1, 50, -50, 1, 1], [1, 1, -50, 50, 3, 3]], dtype=float)
    assert frame_offset_covariance(dev2, cols) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="frames >= 2"):
        frame_offset_covariance(dev[:1], cols)
    with pytest.raises(ValueError, match="finite"):
        frame_offset_covariance(np.where(dev > 10, np.nan, dev), cols)


def test_pooled_takes_the_medians_and_says_when_nothing_was_measured():
    rows = [{"ratio": 1.5, "length_px": 4.0}, {"ratio": 2.5, "length_px": 0.0}, {"ratio": 2.0, "length_px": 3.0},
            {"ratio": float("nan"), "length_px": float("nan")}]
    assert pooled_frame_error(rows) == {"frame_variance_ratio": 2.0, "error_correlation_px": 3.0, "n_captures": 3}
    assert pooled_frame_error(rows[3:])["n_captures"] == 0


def test_too_few_frames_or_a_target_that_is_not_its_plane_give_a_reason(rng):
    row = capture_frame_error(_capture(rng, 0.05, 0.0, 0.0, frames=3))
    assert "frames" in row["reason"] and math.isnan(row["ratio"])
    row = capture_frame_error(_capture(rng, 0.001, 0.5, 4.0))            # a 500x "static" part: not noise
    assert "not the plane" in row["reason"] and math.isnan(row["ratio"])
