"""The valid-region margin on a genuine D435 recording: the pixels it drops are the real camera's noisy ones.

The margin was chosen on simulated cameras (the physical D435's edge fattening beside hidden step edges).
Here it is held to a camera nobody wrote: in the aims_slam recording's two static stretches, a pixel that
has data in every frame but that the 5 px margin drops in at least half of them must be far noisier over
time than a pixel the margin never drops. Noise is compared as std(z) / mean(z)^2, the disparity-like
quantity a stereo camera's noise is flat in, so that the two groups' different depths do not decide it.
Temporal noise is the part of the rule's reason a static recording can show: edge fattening itself is
static and needs a known geometry (the physical simulation's walks, docs/fusion.md).
"""

from __future__ import annotations

import numpy as np
import pytest

from noise_model.valid_margin import DEFAULT_VALID_MARGIN_PX, drop_valid_margin, has_data


def _stretch(realdata, first, last):
    from noise_model.sim.stereo.realdata import read_png

    folder = realdata / "aims_slam_d435_robot_floor" / "depth"
    if not folder.is_dir():
        pytest.skip(f"aims_slam depth frames not found in {folder}")
    return np.stack([read_png(folder / f"{i}.png") for i in range(first, last + 1)])


@pytest.mark.parametrize("first, last", [(141, 156), (1, 8)])
def test_dropped_pixels_are_the_real_cameras_noisy_ones(realdata, first, last):
    depth_mm = _stretch(realdata, first, last)
    assert depth_mm.dtype == np.uint16
    valid = np.stack([has_data(d) for d in depth_mm])
    kept = np.stack([has_data(drop_valid_margin(d, DEFAULT_VALID_MARGIN_PX, nthreads=1)) for d in depth_mm])
    # the rule only removes data, never adds it
    assert not (kept & ~valid).any()
    always = valid.all(axis=0)
    n_dropped = (valid & ~kept).sum(axis=0)
    never_dropped = always & (n_dropped == 0)
    often_dropped = always & (2 * n_dropped >= len(depth_mm))
    assert never_dropped.sum() > 50_000 and often_dropped.sum() > 300

    z = depth_mm.astype(np.float64) * 1e-3
    z_med = np.median(z, axis=0)

    def noise(mask):
        """std(z) / z^2 [1/m] per pixel, and whether any frame leaves the median by > 0.05 z^2 [m]."""
        zm = z[:, mask]
        jumps = (np.abs(zm - z_med[mask]) / z_med[mask] ** 2).max(axis=0) > 0.05
        return zm.std(axis=0, ddof=1) / zm.mean(axis=0) ** 2, jumps

    quiet, quiet_jumps = noise(never_dropped)
    dropped, dropped_jumps = noise(often_dropped)
    # noisier in the bulk (about 1.3x in the median and 1.5-1.8x at the 90th percentile) ...
    assert np.median(dropped) > 1.15 * np.median(quiet)
    assert np.percentile(dropped, 90) > 1.3 * np.percentile(quiet, 90)
    # ... and where it matters for a map, far more often a frame's depth jumps away (40-90x)
    assert dropped_jumps.mean() > 10.0 * max(quiet_jumps.mean(), 1e-4)
    # the dropped share of the frame's data is modest: a margin, not a crop (6 % and 10 %)
    share = 1.0 - kept.sum() / valid.sum()
    assert 0.02 < share < 0.15, share
