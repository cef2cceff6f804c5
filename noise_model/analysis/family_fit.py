"""The disparity family of sigma_z fitted to measured axial noise, and held-out errors of both families.

The paper's family (:func:`noise_model.analysis.characterization.fit_axial_model`) has four free
coefficients and an angle term that diverges at 90 deg; fitted to a few captures it can say anything
where it was not measured. The disparity family models the noise where a stereo camera makes it::

    sigma_z = z^2 sigma_d(theta) / (f B),   sigma_d(theta) = s0 + s1 theta^2   [px]

(f the focal length [px], B the baseline [m]; docs/noise-model.md). A measured sigma_z is a measured
sigma_d = sigma_z f B / z^2, and sigma_d is linear in (s0, s1): :func:`fit_disparity_model` solves a
bounded linear least-squares problem (``scipy.optimize.lsq_linear``, s0 > 0, s1 >= 0) in relative
residuals, reweighted from the fit as the paper's fit is. With all measurements at one incidence angle
(a single plane) s1 is not identifiable, and it is fixed at 0 (the report says so).

Which family to use is decided by :func:`heldout_errors`: the measurements are cut into blocks of
distance and angle, each block is predicted by each family fitted to the other blocks, and the family
with the smaller root-mean-square log error (log of measured over predicted sigma) over the blocks both
families could predict wins. Holding out whole blocks, not single measurements, asks what a model is
for: the noise where the camera was not characterised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import optimize

from ..checks import check_positive_scalar
from ..formulas import disparity_angle_gain, disparity_sigma_z_from_gain

__all__ = ["DisparityFit", "fit_disparity_model", "check_axial_points", "distance_angle_blocks", "heldout_errors",
           "FAMILIES_FITTED", "MIN_THETA_SPREAD_RAD", "DISTANCE_BLOCK_M", "ANGLE_BLOCK_DEG", "MIN_PAPER_POINTS"]

#: The families a characterisation fits, in the order reports list them.
FAMILIES_FITTED = ("paper", "disparity")
#: Measurements whose incidence angles span less than this [rad] (5 deg) cannot separate s0 from s1.
MIN_THETA_SPREAD_RAD = math.radians(5.0)
#: Held-out blocks: depth [m] and incidence angle [deg] cut into bins this wide.
DISTANCE_BLOCK_M = 0.5
ANGLE_BLOCK_DEG = 15.0
#: The paper's family has 4 coefficients: fewer measurements than this leave it unfitted.
MIN_PAPER_POINTS = 5
#: A prediction at or below this [m] counts as this (its log error is then large, not undefined).
_SIGMA_FLOOR_M = 1e-6


def check_axial_points(z_m, theta_rad, sigma_m):
    """Depths [m], incidence angles [rad] and axial sigmas [m] of a fit as three flat float arrays.

    Raises ``ValueError`` naming the input that is not a finite depth (0, 100] m, an angle in
    [0, pi/2) or a standard deviation (0, 100) m, or when their lengths differ.
    """
    z = np.asarray(z_m, dtype=np.float64).ravel()
    t = np.asarray(theta_rad, dtype=np.float64).ravel()
    s = np.asarray(sigma_m, dtype=np.float64).ravel()
    if not (z.shape == t.shape == s.shape):
        raise ValueError(f"z_m, theta_rad and sigma_m must have the same length, got {z.shape}, {t.shape}, {s.shape}")
    if not (np.all(np.isfinite(z)) and np.all(z > 0) and np.all(z <= 100.0)):
        raise ValueError("z_m must be finite depths in metres, > 0")
    if not (np.all(np.isfinite(t)) and np.all(t >= 0) and np.all(t < 0.5 * np.pi)):
        raise ValueError("theta_rad must be finite angles in [0, pi/2) radians")
    if not (np.all(np.isfinite(s)) and np.all(s > 0) and np.all(s < 100.0)):
        raise ValueError("sigma_m must be finite standard deviations in metres, > 0")
    return z, t, s


def _focal(fx_px, n: int) -> np.ndarray:
    f = np.broadcast_to(np.asarray(fx_px, dtype=np.float64), (n,)).astype(np.float64)
    if not (np.all(np.isfinite(f)) and np.all(f > 0) and np.all(f < 1e5)):
        raise ValueError("fx_px must be finite focal lengths in pixels, > 0")
    return f


@dataclass(frozen=True)
class DisparityFit:
    """sigma_d(theta) = s0 + s1 theta^2 [px] fitted to measured axial noise.

    Attributes
    ----------
    s0, s1 : float
        [px] and [px / rad^2].
    stderr : tuple of 2 floats
        Their standard errors (from the weighted fit's covariance scaled by its residual; NaN where there
        are no degrees of freedom left; s1's is 0 when s1 was fixed).
    residual_rms_rel : float
        Root mean square of (measured - fitted) / fitted sigma_d over the measurements [-].
    n : int
        Measurements fitted.
    s1_fixed : str or None
        Why s1 was fixed at 0 instead of fitted (all measurements at one angle), else None.
    baseline_m : float
        The baseline B [m] the measurements were converted with.
    """

    s0: float
    s1: float
    stderr: tuple
    residual_rms_rel: float
    n: int
    s1_fixed: str | None
    baseline_m: float

    def sigma_d(self, theta):
        """sigma_d [px] at the incidence angle theta [rad]."""
        t = np.asarray(theta, dtype=np.float64)
        return self.s0 + disparity_angle_gain(t, self.s1)

    def sigma_z(self, z, theta, fx_px):
        """sigma_z [m] = z^2 sigma_d(theta) / (f B) at depth z [m], angle theta [rad], focal length fx_px [px]."""
        fb = np.asarray(fx_px, dtype=np.float64) * self.baseline_m
        t = np.asarray(theta, dtype=np.float64)
        return disparity_sigma_z_from_gain(np.asarray(z, dtype=np.float64), disparity_angle_gain(t, self.s1 / fb),
                                           self.s0 / fb)

    def to_dict(self) -> dict:
        return {"s0_px": self.s0, "s1_px_per_rad2": self.s1, "stderr": [float(e) for e in self.stderr],
                "residual_rms_rel": self.residual_rms_rel, "n": self.n, "s1_fixed": self.s1_fixed,
                "baseline_m": self.baseline_m}


def fit_disparity_model(z_m, theta_rad, sigma_m, fx_px, baseline_m: float, iterations: int = 3,
                        min_theta_spread_rad: float = MIN_THETA_SPREAD_RAD) -> DisparityFit:
    """Fit sigma_d(theta) = s0 + s1 theta^2 [px] to measured sigma_z, with s0 > 0 and s1 >= 0.

    Each measurement becomes sigma_d,i = sigma_z,i f_i B / z_i^2. The sampling error of a measured standard
    deviation is proportional to it, so the residuals are taken relative to the fitted sigma_d (weights from
    the previous round, starting from the measured values; ``iterations`` rounds), and the bounded linear
    problem is solved by ``scipy.optimize.lsq_linear``. s1 >= 0: sigma_d does not shrink with the slant, and
    a fit that finds no growth gives s1 = 0. When the angles span less than ``min_theta_spread_rad``,
    s0 and s1 cannot be told apart and s1 is fixed at 0.

    Parameters
    ----------
    z_m, theta_rad, sigma_m : array_like, shape (K,)
        Per measurement: depth [m] (> 0), incidence angle [rad] in [0, pi/2) (between the surface normal and
        the optical axis, as the mapper estimates it), measured sigma_z [m] (> 0). K >= 1.
    fx_px : float or array_like, shape (K,)
        Focal length [px] of each measurement's frames.
    baseline_m : float
        Stereo baseline B [m].
    iterations : int
        Reweighting rounds.
    min_theta_spread_rad : float
        Below this spread of the angles, s1 is fixed at 0.

    Returns
    -------
    DisparityFit
    """
    z, t, s = check_axial_points(z_m, theta_rad, sigma_m)
    if z.size < 1:
        raise ValueError("fitting sigma_d needs at least one measurement of axial noise")
    f = _focal(fx_px, z.size)
    B = check_positive_scalar(baseline_m, "baseline_m", upper=2.0, unit=" m")
    sd = s * f * B / (z * z)
    fixed = None
    if float(np.ptp(t)) < float(min_theta_spread_rad) or z.size < 2:
        fixed = (f"the measurements' incidence angles span {math.degrees(float(np.ptp(t))):.1f} deg (< "
                 f"{math.degrees(float(min_theta_spread_rad)):.0f} deg): s1 cannot be told from s0 and is fixed at 0")
        A = np.ones((z.size, 1))
    else:
        A = np.stack([np.ones(z.size), t * t], axis=1)
    lo = np.array([1e-9, 0.0][:A.shape[1]])
    hi = np.array([10.0, np.inf][:A.shape[1]])
    w = sd.copy()
    x = None
    for _ in range(max(1, int(iterations))):
        res = optimize.lsq_linear(A / w[:, None], sd / w, bounds=(lo, hi), method="bvls")
        x = res.x
        pred = A @ x
        if np.all(pred > 0):
            w = pred
    pred = A @ x
    rel = (sd - pred) / pred
    dof = z.size - A.shape[1]
    Aw = A / pred[:, None]
    stderr = np.full(A.shape[1], np.nan)
    if dof > 0:
        try:
            cov = float(np.sum(rel * rel) / dof) * np.linalg.inv(Aw.T @ Aw)
            stderr = np.sqrt(np.maximum(np.diag(cov), 0.0))
        except np.linalg.LinAlgError:
            pass
    s0 = float(x[0])
    s1 = float(x[1]) if A.shape[1] == 2 else 0.0
    se = (float(stderr[0]), float(stderr[1]) if A.shape[1] == 2 else 0.0)
    return DisparityFit(s0, s1, se, float(np.sqrt(np.mean(rel * rel))), int(z.size), fixed, B)


def distance_angle_blocks(z_m, theta_rad, distance_block_m: float = DISTANCE_BLOCK_M,
                          angle_block_deg: float = ANGLE_BLOCK_DEG) -> tuple[np.ndarray, list[str]]:
    """Label each measurement with its block of distance and angle.

    Parameters
    ----------
    z_m, theta_rad : array_like, shape (K,)
        Depth [m] and incidence angle [rad].
    distance_block_m, angle_block_deg : float
        Block sizes: [k dz, (k + 1) dz) x [j dtheta, (j + 1) dtheta).

    Returns
    -------
    labels : ndarray of int, shape (K,)
        Block index of each measurement (0 .. number of blocks - 1, in order of distance, then angle).
    names : list of str
        Each block as "z 0.5-1.0 m, theta 15-30 deg".
    """
    z = np.asarray(z_m, dtype=np.float64).ravel()
    t = np.degrees(np.asarray(theta_rad, dtype=np.float64).ravel())
    dz = check_positive_scalar(distance_block_m, "distance_block_m", upper=100.0, unit=" m")
    da = check_positive_scalar(angle_block_deg, "angle_block_deg", upper=90.0, unit=" deg")
    kz = np.floor(z / dz + 1e-9).astype(np.int64)
    ka = np.floor(t / da + 1e-9).astype(np.int64)
    keys = sorted(set(zip(kz.tolist(), ka.tolist())))
    index = {k: i for i, k in enumerate(keys)}
    labels = np.array([index[k] for k in zip(kz.tolist(), ka.tolist())], dtype=np.int64)
    names = [f"z {a * dz:g}-{(a + 1) * dz:g} m, theta {b * da:g}-{(b + 1) * da:g} deg" for a, b in keys]
    return labels, names


def _fit_family(family, z, t, s, f, baseline_m):
    """A predictor sigma_z(z, theta, fx) of ``family`` fitted to the points, or (None, reason)."""
    if family == "disparity":
        fit = fit_disparity_model(z, t, s, f, baseline_m)
        return (lambda zz, tt, ff: fit.sigma_z(zz, tt, ff)), None
    from .characterization import fit_axial_model

    if z.size < MIN_PAPER_POINTS:
        return None, f"{z.size} measurements left to fit its 4 coefficients (needs {MIN_PAPER_POINTS})"
    try:
        fit = fit_axial_model(z, t, s)
    except (ValueError, RuntimeError) as exc:
        return None, f"the fit failed: {exc}"
    return (lambda zz, tt, ff: fit.sigma_z(zz, tt)), None


def heldout_errors(z_m, theta_rad, sigma_m, fx_px, baseline_m: float, labels=None, names=None) -> dict:
    """Each family's error on blocks of measurements it was not fitted to, and which family predicts better.

    For every block, both families are fitted to the measurements of all other blocks (the paper's with
    :func:`noise_model.analysis.characterization.fit_axial_model`, the disparity family with
    :func:`fit_disparity_model`) and predict the block. The error of a prediction is
    log(measured / predicted sigma_z) (a factor either way counts the same); a family's held-out error is
    the root mean square over the measurements it predicted. The better family has the smaller error over
    the measurements both predicted (a family that predicted none loses; with none predicted by either,
    the disparity family, which needs one measurement where the paper's needs five).

    Parameters
    ----------
    z_m, theta_rad, sigma_m : array_like, shape (K,)
        Measurements as for :func:`fit_disparity_model`.
    fx_px : float or array_like, shape (K,)
        Focal length [px] of each measurement.
    baseline_m : float
        Baseline [m].
    labels, names : optional
        Blocks (:func:`distance_angle_blocks` by default).

    Returns
    -------
    dict
        ``blocks`` (one entry per block: ``name``, ``n``, and per family ``rms_log_error`` or the
        ``reason`` it could not predict the block), ``families`` (per family ``rms_log_error``,
        ``median_ratio`` (measured / predicted), ``n_predicted``, ``rms_log_error_common``), ``n_common``,
        ``better``, ``reason``.
    """
    z, t, s = check_axial_points(z_m, theta_rad, sigma_m)
    f = _focal(fx_px, z.size)
    if labels is None:
        labels, names = distance_angle_blocks(z, t)
    labels = np.asarray(labels)
    if labels.shape != z.shape:
        raise ValueError(f"labels must have shape {z.shape}, got {labels.shape}")
    logerr = {fam: np.full(z.size, np.nan) for fam in FAMILIES_FITTED}
    blocks = []
    for b in np.unique(labels):
        test = labels == b
        entry = {"name": names[int(b)] if names is not None else str(int(b)), "n": int(test.sum())}
        train = ~test
        for fam in FAMILIES_FITTED:
            if not train.any():
                entry[fam] = {"reason": "no other block to fit on"}
                continue
            predict, reason = _fit_family(fam, z[train], t[train], s[train], f[train], baseline_m)
            if predict is None:
                entry[fam] = {"reason": reason}
                continue
            pred = np.maximum(np.asarray(predict(z[test], t[test], f[test]), dtype=np.float64), _SIGMA_FLOOR_M)
            pred = np.where(np.isfinite(pred), pred, _SIGMA_FLOOR_M)
            e = np.log(s[test] / pred)
            logerr[fam][test] = e
            entry[fam] = {"rms_log_error": float(np.sqrt(np.mean(e * e))), "median_ratio": float(np.exp(np.median(e)))}
        blocks.append(entry)
    common = np.all([np.isfinite(logerr[fam]) for fam in FAMILIES_FITTED], axis=0)
    fams = {}
    for fam in FAMILIES_FITTED:
        e = logerr[fam]
        ok = np.isfinite(e)
        fams[fam] = {"n_predicted": int(ok.sum()),
                     "rms_log_error": float(np.sqrt(np.mean(e[ok] ** 2))) if ok.any() else None,
                     "median_ratio": float(np.exp(np.median(e[ok]))) if ok.any() else None,
                     "rms_log_error_common": float(np.sqrt(np.mean(e[common] ** 2))) if common.any() else None}
    if common.any():
        better = min(FAMILIES_FITTED, key=lambda fam: fams[fam]["rms_log_error_common"])
        reason = f"smaller held-out error over the {int(common.sum())} measurements both families predicted"
    else:
        have = [fam for fam in FAMILIES_FITTED if fams[fam]["n_predicted"]]
        better = have[0] if len(have) == 1 else "disparity"
        reason = (f"only the {better} family could predict held-out blocks" if len(have) == 1 else
                  "no block could be predicted by a fit to the others (a single block): the disparity family, "
                  f"which one measurement fits, where the paper's needs {MIN_PAPER_POINTS}")
    return {"blocks": blocks, "families": fams, "n_common": int(common.sum()), "better": better, "reason": reason}
