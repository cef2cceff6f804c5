"""Shared fixtures. Genuine D435 recordings are read from ../shared/realdata and never copied here."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture
def realdata():
    if not REALDATA.is_dir():
        pytest.skip(f"genuine D435 recordings not available at {REALDATA} (a user's machine has none)")
    return REALDATA


def random_rotation(rng) -> np.ndarray:
    """A uniformly random proper rotation matrix (3, 3)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def random_transform(rng, translation_scale: float = 2.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = random_rotation(rng)
    T[:3, 3] = rng.normal(scale=translation_scale, size=3)
    return T


def random_pose_cov(rng, sigma_t: float = 0.01, sigma_r: float = 0.01) -> np.ndarray:
    """A random full-rank 6x6 pose covariance with roughly the given translation/rotation sigmas."""
    A = rng.normal(size=(6, 6))
    C = A @ A.T / 6.0
    s = np.array([sigma_t] * 3 + [sigma_r] * 3)
    return C * np.outer(s, s)
