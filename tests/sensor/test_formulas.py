"""The shared formulas: worked by hand, against scipy, and the same compiled as in NumPy."""

import math

import numpy as np
import pytest
from numba import njit
from scipy.stats import chi2, norm

from noise_model import D435, axial_sigma, axial_variance
from noise_model.formulas import (
    angle_gain, dersimonian_laird_tau2, expected_sigma_z_sq, reduced_chi2_quantile, sigma_z_from_gain,
)
from noise_model.numba_config import JIT


def test_sigma_z_from_the_angle_gain_is_the_papers_sigma():
    c0, c1, c2, ct = D435.axial_coefficients
    # theta term at 2 m, 45 deg: 0.022 * 2^1.5 * (pi/4) / (pi/4)^2 = 0.0792278 (test_d435)
    assert angle_gain(math.pi / 4, ct) * 2.0 ** 1.5 == pytest.approx(0.0792278, rel=1e-6)
    z = np.linspace(0.3, 4.0, 7)[:, None]
    th = np.radians([0.0, 20.0, 60.0, 75.0])[None, :]
    np.testing.assert_allclose(sigma_z_from_gain(z, angle_gain(th, ct), c0, c1, c2), axial_sigma(z, th), rtol=1e-15)
    # with a certain angle the expected variance is sigma_z^2
    g = angle_gain(th, ct)
    np.testing.assert_allclose(expected_sigma_z_sq(z, g, g * g, c0, c1, c2), axial_sigma(z, th) ** 2, rtol=1e-14)
    np.testing.assert_allclose(axial_variance(z, th, 0.0), axial_sigma(z, th) ** 2, rtol=1e-14)


@pytest.mark.parametrize("q", [0.5, 0.999, 0.9999])
@pytest.mark.parametrize("k", [20, 100, 1000])
def test_wilson_hilferty_is_close_to_the_exact_quantile(k, q):
    assert reduced_chi2_quantile(float(k), norm.ppf(q)) * k == pytest.approx(chi2.ppf(q, k), rel=1e-2)


def test_dersimonian_laird_by_hand():
    # y = (0, 3), v = (1, 1): m = 1.5, Q = 2 * 1.5^2 = 4.5, excess Q - 1 = 3.5, S1 - S2 / S1 = 2 - 1 = 1
    assert dersimonian_laird_tau2(3.5, 2.0, 2.0) == 3.5
    # y = (0, 1): Q = 0.5 < k - 1 = 1: no spread
    assert dersimonian_laird_tau2(-0.5, 2.0, 2.0) == 0.0
    np.testing.assert_array_equal(dersimonian_laird_tau2(np.array([3.5, -0.5]), 2.0, 2.0), [3.5, 0.0])


def test_compiled_formulas_equal_the_numpy_ones():
    rng = np.random.default_rng(0)
    c0, c1, c2, ct = D435.axial_coefficients
    compiled = {f: njit(**JIT)(f) for f in (angle_gain, sigma_z_from_gain, expected_sigma_z_sq, reduced_chi2_quantile,
                                            dersimonian_laird_tau2)}
    for z, t, s in zip(rng.uniform(0.2, 8.0, 50), rng.uniform(0.0, 1.39, 50), rng.uniform(0.0, 0.3, 50)):
        g = angle_gain(t, ct)
        for f, args in ((angle_gain, (t, ct)), (sigma_z_from_gain, (z, g, c0, c1, c2)),
                        (expected_sigma_z_sq, (z, g, g * g + s, c0, c1, c2)),
                        (reduced_chi2_quantile, (1.0 + 100 * s, 3.09)),
                        (dersimonian_laird_tau2, (z - 1.0, 3.0 + t, 2.0 + s))):
            assert compiled[f](*args) == pytest.approx(f(*args), rel=1e-14, abs=0.0)


def test_openmp_spins_briefly_unless_the_user_chose_a_policy():
    """Long-spinning OpenMP threads lose whole time slices at every barrier on a busy robot computer; the spin
    count must be in the environment before numba loads OpenMP, and a user's own choice wins."""
    import os
    import subprocess
    import sys

    code = ("import os; from noise_model import numba_config; "
            "print(os.environ.get('GOMP_SPINCOUNT'), os.environ.get('OMP_WAIT_POLICY'))")
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}

    def run(**extra):
        out = subprocess.run([sys.executable, "-c", code], env={**env, **extra}, capture_output=True, text=True,
                             check=True)
        return out.stdout.split()

    assert run() == ["10000", "None"]
    assert run(OMP_WAIT_POLICY="ACTIVE") == ["None", "ACTIVE"]
    assert run(GOMP_SPINCOUNT="5") == ["5", "None"]
