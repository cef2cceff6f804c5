"""Input validators: one ``check_*`` per input type, called at every public entry.

Each validator coerces its input to the dtype the maths needs and raises ``ValueError`` naming the
argument and what is wrong with it (shape, dtype, finiteness, units). Nothing here imports numba,
rerun, pyrealsense2 or OpenCV.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "check_depth",
    "check_intrinsics",
    "check_transform",
    "check_transforms",
    "check_pose_cov",
    "check_points",
    "check_angles",
    "check_mask",
    "check_covariances",
    "check_positive_scalar",
    "check_scalar_range",
    "check_integer_range",
]

#: Largest plausible depth [m]. A uint16 depth image at the D435's default 1 mm scale reaches 65.5 m;
#: values above this almost certainly mean millimetres were passed where metres were expected.
MAX_PLAUSIBLE_DEPTH_M = 100.0


def check_positive_scalar(value, name: str, *, upper: float | None = None, unit: str = "") -> float:
    """Return ``value`` as a finite, strictly positive float (optionally ``<= upper``)."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(x) or x <= 0.0:
        raise ValueError(f"{name} must be finite and > 0, got {x!r}")
    if upper is not None and x > upper:
        raise ValueError(f"{name} = {x!r} is implausibly large (> {upper}{unit}); check its units")
    return x


def check_scalar_range(value, name: str, lo: float, hi: float, *, open_lo: bool = False) -> float:
    """Return ``value`` as a float in [lo, hi] (in (lo, hi] with ``open_lo``).

    Parameters
    ----------
    value : real number
        Not a bool (``True`` is not a parameter value).
    name : str
        The parameter's name, for the message.
    lo, hi : float
        The closed range; ``open_lo`` excludes ``lo`` (a parameter that must be strictly positive).

    Raises
    ------
    ValueError
        Not a number, not finite, or outside the range; the message names the parameter and the range.
    """
    if isinstance(value, bool):
        raise ValueError(f"{name} must be a number, got {value!r}")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(x) or x < lo or x > hi or (open_lo and x == lo):
        raise ValueError(f"{name} must be in {'(' if open_lo else '['}{lo}, {hi}], got {value!r}")
    return x


def check_integer_range(value, name: str, lo: int, hi: int) -> int:
    """Return ``value`` as an int in [lo, hi]; a real value is rounded to the nearest integer.

    Random draws and fitted estimates are reals, so an integer parameter accepts them: values within
    half a unit of the range round into it (:func:`check_scalar_range` on [lo - 1/2, hi + 1/2], then
    floor(x + 1/2)).

    Raises
    ------
    ValueError
        Not a number, or outside the range after rounding; the message names the parameter.
    """
    x = check_scalar_range(value, name, lo - 0.5, hi + 0.5)
    k = int(math.floor(x + 0.5))
    if k < lo or k > hi:
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return k


def check_depth(depth, depth_scale=None, name: str = "depth") -> tuple[np.ndarray, float]:
    """Validate a depth image and say how to turn it into metres.

    Parameters
    ----------
    depth : array_like, shape (H, W)
        Either ``uint16`` depth units (then ``depth_scale`` [m/unit] is required; 0 = no data) or
        floating-point metres (``depth_scale`` must be None or 1). Non-finite, zero and negative
        values are *invalid pixels*, not errors.
    depth_scale : float, optional
        Metres per depth unit for integer depth (0.001 for a D435 at default settings).

    Returns
    -------
    depth : ndarray, shape (H, W)
        The image, uint16 or float32/float64, C-contiguous, not copied when already so.
    scale : float
        Metres per stored unit (1.0 for float input).
    """
    a = np.asarray(depth)
    if a.ndim != 2:
        raise ValueError(f"{name} must be a 2-D image (H, W), got shape {a.shape}")
    if a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"{name} is empty, shape {a.shape}")
    if a.dtype == np.uint16:
        if depth_scale is None:
            raise ValueError(f"{name} is uint16 depth units: depth_scale [m/unit] is required (D435: 0.001)")
        scale = check_positive_scalar(depth_scale, "depth_scale", upper=0.1, unit=" m per unit")
        return np.ascontiguousarray(a), scale
    if a.dtype in (np.float32, np.float64):
        if depth_scale not in (None, 1, 1.0):
            raise ValueError(
                f"{name} is floating point and is taken as metres; depth_scale must be None, got {depth_scale!r}"
            )
        # largest finite value without copying the finite pixels out (a frame-sized temporary)
        top = float(np.max(a, where=np.isfinite(a), initial=-np.inf))
        if top > MAX_PLAUSIBLE_DEPTH_M:
            raise ValueError(
                f"{name} holds values up to {top:.1f}: float depth must be in metres "
                f"(millimetres? pass uint16 with depth_scale=0.001)"
            )
        return np.ascontiguousarray(a), 1.0
    if a.dtype == np.float16:
        return check_depth(a.astype(np.float32), depth_scale, name)
    raise ValueError(f"{name} must be uint16 (with depth_scale) or float32/float64 metres, got dtype {a.dtype}")


def check_intrinsics(K, name: str = "K") -> np.ndarray:
    """Validate a pinhole camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` [px]; returns float64."""
    a = np.asarray(K)
    if a.shape != (3, 3):
        raise ValueError(f"{name} must be a 3x3 camera matrix, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise ValueError(f"{name} must be real numbers, got dtype {a.dtype}")
    a = a.astype(np.float64)
    (fx, s01, _), (s10, fy, _), last = rows = a.tolist()      # Python floats: checked on every frame
    if not all(math.isfinite(x) for row in rows for x in row):
        raise ValueError(f"{name} has non-finite entries")
    if fx <= 0 or fy <= 0:
        raise ValueError(f"{name} focal lengths must be > 0 px, got fx={fx}, fy={fy}")
    if fx < 1.0 or fy < 1.0:       # a field of view near 180 deg; the noise model's 1/f^2 overflows
        raise ValueError(f"{name} focal lengths must be >= 1 px, got fx={fx:g}, fy={fy:g}")
    if s01 != 0 or s10 != 0:
        raise ValueError(f"{name} has skew/shear terms ({s01}, {s10}); only zero skew is supported")
    # np.allclose(last, [0, 0, 1]): |x - y| <= 1e-8 + 1e-5 |y|
    if not (abs(last[0]) <= 1e-8 and abs(last[1]) <= 1e-8 and abs(last[2] - 1.0) <= 1e-8 + 1e-5):
        raise ValueError(f"{name} last row must be [0, 0, 1], got {last}")
    return a


def check_transform(T, name: str = "T_map_cam", *, tol: float = 1e-6) -> np.ndarray:
    """Validate a 4x4 rigid transform (rotation, translation [m], bottom row [0 0 0 1]); returns float64."""
    a = np.asarray(T)
    if a.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 homogeneous transform, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise ValueError(f"{name} must be real numbers, got dtype {a.dtype}")
    a = a.astype(np.float64)
    # on the 16 entries as Python floats: NumPy's per-call overhead on a 4x4 is larger than the arithmetic,
    # and this check runs on every frame
    (r00, r01, r02, _), (r10, r11, r12, _), (r20, r21, r22, _), bottom = rows = a.tolist()
    if not all(math.isfinite(x) for row in rows for x in row):
        raise ValueError(f"{name} has non-finite entries")
    # np.allclose(bottom, [0, 0, 0, 1], atol=tol): |x - y| <= tol + 1e-5 |y|
    if not (abs(bottom[0]) <= tol and abs(bottom[1]) <= tol and abs(bottom[2]) <= tol
            and abs(bottom[3] - 1.0) <= tol + 1e-5):
        raise ValueError(f"{name} bottom row must be [0, 0, 0, 1], got {bottom}")
    err = max(abs(r00 * r00 + r01 * r01 + r02 * r02 - 1.0), abs(r10 * r10 + r11 * r11 + r12 * r12 - 1.0),
              abs(r20 * r20 + r21 * r21 + r22 * r22 - 1.0), abs(r00 * r10 + r01 * r11 + r02 * r12),
              abs(r00 * r20 + r01 * r21 + r02 * r22), abs(r10 * r20 + r11 * r21 + r12 * r22))    # max |R R^T - I|
    if err > tol:
        raise ValueError(f"{name} rotation part is not orthonormal (max |R R^T - I| = {err:.2e})")
    det = r00 * (r11 * r22 - r12 * r21) - r01 * (r10 * r22 - r12 * r20) + r02 * (r10 * r21 - r11 * r20)
    if det < 0:
        raise ValueError(f"{name} rotation part is a reflection (det = {det:.3f}), not a rotation")
    return a


def check_transforms(T, name: str = "poses", *, tol: float = 1e-6) -> np.ndarray:
    """Validate a stack of rigid transforms, shape (N, 4, 4), N >= 1, as :func:`check_transform`
    does one; returns float64. The error names the first bad index."""
    a = np.asarray(T)
    if a.ndim != 3 or a.shape[1:] != (4, 4) or a.shape[0] < 1:
        raise ValueError(f"{name} must have shape (N, 4, 4), got {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"{name} must be floating point, got dtype {a.dtype}")
    a = a.astype(np.float64, copy=False)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} has non-finite entries")
    R = a[:, :3, :3]
    err = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    bad = (err > tol) | (np.linalg.det(R) < 0) | np.any(np.abs(a[:, 3] - [0, 0, 0, 1]) > tol, axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name}[{i}] is not a rigid transform (rotation orthonormal, det +1, bottom row 0 0 0 1)")
    return a


def check_pose_cov(C, name: str = "pose_cov", *, tol: float = 1e-9) -> np.ndarray:
    """Validate a 6x6 pose covariance (translation [m^2] first, then rotation [rad^2]); returns float64.

    Must be finite, symmetric and positive semi-definite (within a relative tolerance).
    """
    a = np.asarray(C)
    if a.shape != (6, 6):
        raise ValueError(f"{name} must be a 6x6 covariance (x, y, z, rx, ry, rz), got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise ValueError(f"{name} must be real numbers, got dtype {a.dtype}")
    a = a.astype(np.float64)
    top = float(np.abs(a).max())            # NaN or inf when any entry is
    if not math.isfinite(top):
        raise ValueError(f"{name} has non-finite entries")
    scale = max(top, 1e-300)
    asym = float(np.abs(a - a.T).max())
    if asym > tol * scale:
        raise ValueError(f"{name} is not symmetric (max |C - C^T| = {asym:.3e})")
    a = 0.5 * (a + a.T)
    # a diagonal covariance (the common case; checked on every frame) has its diagonal as eigenvalues:
    # the 30 off-diagonal entries are the first six of each row of the entries after C[0, 0] taken 7 at a time
    if a.ravel()[1:].reshape(5, 7)[:, :6].any():
        wmin = float(np.linalg.eigvalsh(a).min())
    else:
        wmin = float(a.diagonal().min())
    if wmin < -tol * scale:
        raise ValueError(f"{name} is not positive semi-definite (smallest eigenvalue {wmin:.3e})")
    return a


def check_points(points, name: str = "points_cam", *, allow_nan: bool = False) -> np.ndarray:
    """Validate an (N, 3) array of points [m]; returns float64. With ``allow_nan`` NaN rows are kept."""
    a = np.asarray(points)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        if np.issubdtype(a.dtype, np.integer):
            a = a.astype(np.float64)
        else:
            raise ValueError(f"{name} must be floating point metres, got dtype {a.dtype}")
    a = a.astype(np.float64, copy=False)
    bad = ~np.isfinite(a)
    if bad.any() and not allow_nan:
        raise ValueError(f"{name} has {int(bad.any(axis=1).sum())} non-finite row(s); drop invalid points first")
    return a


def check_angles(theta, n: int | None = None, name: str = "theta") -> np.ndarray:
    """Validate incidence angles [rad] (finite, |theta| <= pi); returns float64 of the same shape."""
    a = np.asarray(theta)
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name} must be real angles in radians, got dtype {a.dtype}")
    a = a.astype(np.float64)
    if n is not None and a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} has non-finite values")
    if a.size and float(np.abs(a).max()) > np.pi + 1e-9:
        raise ValueError(f"{name} has values up to {float(np.abs(a).max()):.2f}: angles must be in radians")
    return a


def check_mask(mask, n: int, name: str) -> np.ndarray:
    """Validate an optional boolean mask of shape (n,); None gives all False."""
    if mask is None:
        return np.zeros(n, dtype=bool)
    a = np.asarray(mask)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
    if a.dtype != bool:
        raise ValueError(f"{name} must be a boolean mask, got dtype {a.dtype}")
    return a


def check_covariances(cov, n: int | None = None, name: str = "cov_cam") -> np.ndarray:
    """Validate (N, 3, 3) covariances [m^2]: finite, symmetric, non-negative diagonal; returns float64."""
    a = np.asarray(cov)
    if a.ndim != 3 or a.shape[1:] != (3, 3):
        raise ValueError(f"{name} must have shape (N, 3, 3), got {a.shape}")
    if n is not None and a.shape[0] != n:
        raise ValueError(f"{name} has {a.shape[0]} covariances but there are {n} points")
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"{name} must be floating point, got dtype {a.dtype}")
    a = a.astype(np.float64, copy=False)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} has non-finite entries")
    if a.size:
        scale = max(float(np.abs(a).max()), 1e-300)
        if float(np.abs(a - a.transpose(0, 2, 1)).max()) > 1e-9 * scale:
            raise ValueError(f"{name} has non-symmetric matrices")
        if float(np.diagonal(a, axis1=1, axis2=2).min()) < 0:
            raise ValueError(f"{name} has negative variances on the diagonal")
    return a
