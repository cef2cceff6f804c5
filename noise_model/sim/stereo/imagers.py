"""The two infrared imagers: surface geometry, radiance, lens blur, pixel integration, exposure, noise, bits.

Frames and units
----------------
Camera frame x right, y down, z forward; pixel (u, v) looks along ((u - cx) / fx, (v - cy) / fy, 1).
The left imager is the depth reference; the right one sits at +B along its x axis with the same
orientation and intrinsics (a rectified pair). Irradiance in W/m^2, signal in photo-electrons (e-),
output in digital numbers (DN).

Radiometry
----------
A Lambertian surface of albedo rho under irradiance E (projector + ambient) has radiance
L = rho E / pi. Through a lens of f-number N the image-plane irradiance is pi L / (4 N^2) times the
relative illumination cos^k(alpha) (alpha the field angle, k = ``vignetting_power``), so a pixel of
area A collects, per second::

    rate = QE  rho E cos^k(alpha) / (4 N^2)  A  lambda / (h c)        [e-/s]

The pixel pitch of a depth mode is the lens focal length over f in pixels (1.93 mm / f_px: 3 um
native pixels at f = 643 px, 4.5 um effective at 848x480), so lower-resolution modes collect more
light per pixel.

Image formation (:func:`render_rates`, :func:`expose`)
-----------------------------------------------------
* Each pixel is sampled at ``supersample`` x ``supersample`` points (the caller renders the scene
  at that resolution with :func:`sample_intrinsics`); the lens blur, a Gaussian of
  ``blur_sigma_native_px`` native pixels, is applied at the sample resolution, and the samples of a
  pixel are averaged (pixel integration; :func:`.optics.integrate_samples`).
* Exposure: manual (``exposure_s``, ``gain``) or auto: the exposure time that brings the left
  image's mean signal to ``ae_target`` of full scale, at most ``max_exposure_s``, then analogue gain
  up to ``max_gain`` (:func:`auto_exposure`).
* Per frame: each imager's pointing jitters about its y axis by a fresh N(0, sigma_p^2) angle
  (``pointing_jitter_rad``), which moves its image sideways by f sigma_p px (:func:`shift_columns`);
  the two imagers jitter independently, so the disparity of the whole frame moves by
  N(0, 2 f^2 sigma_p^2), the frame-wide offset a real D435 shows; then the projector's share of the
  rate times a fresh laser-speckle factor (:func:`expose`), then photo-electrons ~ Poisson(rate t)
  (shot noise), plus read noise N(0, sigma_read^2), times gain, converted at full_well / 1023 e- per
  10-bit DN, plus the black level, rounded and clipped to 0..1023; the 8-bit output is the 10-bit
  value's top eight bits (DN // 4). Fresh noise every frame; the scene, the pattern and therefore the
  noise-free rates do not change.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from ...numba_config import JIT, resolve_threads, threads
from .optics import integrate_samples, integrate_samples_reference

__all__ = [
    "ImagerModel", "Exposure", "surface_geometry", "surface_geometry_reference", "sample_intrinsics",
    "signal_rate", "signal_rate_reference", "integrate_samples", "integrate_samples_reference", "auto_exposure",
    "expose", "expose_reference", "to_map_frame", "to_map_frame_reference", "irradiance_rate", "irradiance_rate_reference",
    "shift_columns", "shift_columns_reference", "PLANCK_J_S", "LIGHT_M_S",
]

PLANCK_J_S = 6.62607015e-34
LIGHT_M_S = 299792458.0


@dataclass(frozen=True)
class ImagerModel:
    """One infrared imager of the D435 (OmniVision OV9282-class global-shutter sensor behind an f/2 lens).

    Attributes
    ----------
    focal_length_m : float
        Lens focal length (1.93 mm).
    native_focal_px : float
        Focal length in native sensor pixels (1.93 mm / 3 um = 643).
    f_number : float
        Lens f-number N.
    quantum_efficiency : float
        Electrons per photon at ``wavelength_m``.
    wavelength_m : float
        Projector wavelength (850 nm).
    full_well_e : float
        Electrons at 10-bit full scale with unit gain.
    read_noise_e : float
        Read noise [e-] per pixel and frame.
    black_level_dn : float
        Offset added to every pixel [10-bit DN].
    output_bits : int
        8 (the D435's Y8 infrared stream) or 10.
    blur_sigma_native_px : float
        Lens blur (Gaussian sigma) in native pixels.
    supersample : int
        Samples per pixel along each axis.
    vignetting_power : float
        Relative illumination cos^k of the field angle.
    exposure_s, gain : float or None
        Manual exposure [s] and analogue gain; exposure None = auto exposure.
    ae_target : float
        Auto exposure's mean signal as a fraction of full scale (the D435 default set point 1536 of
        a 12-bit scale).
    max_exposure_s : float
        Longest exposure (one frame at 30 fps).
    max_gain : float
        Largest analogue gain (the D435's gain 248 over its base 16).
    pointing_jitter_rad : float
        Standard deviation of each imager's per-frame pointing jitter about its y axis [rad] (0 = none):
        the frame-wide disparity offset of a real D435, sqrt(2) f sigma_p px per frame; fitted to the
        per-frame offset that the wall and the floor of the aims_slam recording share
        (docs/physical-d435.md).
    """

    focal_length_m: float = 1.93e-3
    native_focal_px: float = 643.3
    f_number: float = 2.0
    quantum_efficiency: float = 0.30
    wavelength_m: float = 850e-9
    full_well_e: float = 6000.0
    read_noise_e: float = 5.0
    black_level_dn: float = 8.0
    output_bits: int = 8
    blur_sigma_native_px: float = 0.7
    supersample: int = 2
    vignetting_power: float = 2.0
    exposure_s: float | None = None
    gain: float = 1.0
    ae_target: float = 1536.0 / 4096.0
    max_exposure_s: float = 0.033
    max_gain: float = 248.0 / 16.0
    pointing_jitter_rad: float = 1.5e-5

    def __post_init__(self):
        for name in ("focal_length_m", "native_focal_px", "f_number", "wavelength_m", "full_well_e",
                     "max_exposure_s", "max_gain", "gain"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        for name in ("read_noise_e", "black_level_dn", "blur_sigma_native_px", "vignetting_power",
                     "pointing_jitter_rad"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        if not (0.0 < self.quantum_efficiency <= 1.0):
            raise ValueError(f"quantum_efficiency must lie in (0, 1], got {self.quantum_efficiency!r}")
        if not (0.0 < self.ae_target < 1.0):
            raise ValueError(f"ae_target must lie in (0, 1), got {self.ae_target!r}")
        if self.output_bits not in (8, 10):
            raise ValueError(f"output_bits must be 8 or 10, got {self.output_bits!r}")
        if int(self.supersample) != self.supersample or not 1 <= self.supersample <= 8:
            raise ValueError(f"supersample must be an integer in [1, 8], got {self.supersample!r}")
        if self.exposure_s is not None and not (math.isfinite(self.exposure_s) and self.exposure_s > 0):
            raise ValueError(f"exposure_s must be None (auto) or > 0, got {self.exposure_s!r}")

    def pixel_area_m2(self, focal_px: float) -> float:
        """Effective pixel area [m^2] of a mode with focal length ``focal_px``: (focal_length_m / f_px)^2."""
        return (self.focal_length_m / focal_px) ** 2

    def electrons_per_dn(self) -> float:
        """Conversion at unit gain [e- per 10-bit DN]."""
        return self.full_well_e / 1023.0


class Exposure(NamedTuple):
    """Exposure time [s] and analogue gain of a frame."""

    time_s: float
    gain: float


# ---------------------------------------------------------------------------------------------
# surface geometry from a rendered z-depth image
# ---------------------------------------------------------------------------------------------


@njit(**JIT)
def _pick(z0, za, zb):
    """Which neighbour (+1: b, -1: a, 0: none) to difference with: finite, smaller |dz|, b on ties."""
    fa = np.isfinite(za)
    fb = np.isfinite(zb)
    if fb and (not fa or abs(zb - z0) <= abs(za - z0)):
        return 1
    if fa:
        return -1
    return 0


@njit(parallel=True, **JIT)
def _geometry_kernel(z, intr, pts, nrm):
    h, w = z.shape
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    for v in prange(h):
        for u in range(w):
            z0 = z[v, u]
            if not np.isfinite(z0):
                for k in range(3):
                    pts[v, u, k] = np.nan
                    nrm[v, u, k] = np.nan
                continue
            a = (u - cx) / fx
            b = (v - cy) / fy
            px, py, pz = a * z0, b * z0, z0
            pts[v, u, 0] = px
            pts[v, u, 1] = py
            pts[v, u, 2] = pz
            su = _pick(z0, z[v, u - 1] if u > 0 else np.nan, z[v, u + 1] if u < w - 1 else np.nan)
            sv = _pick(z0, z[v - 1, u] if v > 0 else np.nan, z[v + 1, u] if v < h - 1 else np.nan)
            if su == 0 or sv == 0:
                r = math.sqrt(px * px + py * py + pz * pz)
                nrm[v, u, 0] = -px / r
                nrm[v, u, 1] = -py / r
                nrm[v, u, 2] = -pz / r
                continue
            zu = z[v, u + su]
            zv = z[v + sv, u]
            tux = su * (((u + su - cx) / fx) * zu - px)
            tuy = su * (b * zu - py)
            tuz = su * (zu - pz)
            tvx = sv * (a * zv - px)
            tvy = sv * (((v + sv - cy) / fy) * zv - py)
            tvz = sv * (zv - pz)
            nx = tuy * tvz - tuz * tvy
            ny = tuz * tvx - tux * tvz
            nz = tux * tvy - tuy * tvx
            r = math.sqrt(nx * nx + ny * ny + nz * nz)
            if nx * px + ny * py + nz * pz > 0.0:
                r = -r
            nrm[v, u, 0] = nx / r
            nrm[v, u, 1] = ny / r
            nrm[v, u, 2] = nz / r


@njit(parallel=True, **JIT)
def _rigid_kernel(pts, nrm, R, t, out_p, out_n):
    for i in prange(pts.shape[0]):
        for r in range(3):
            out_p[i, r] = R[r, 0] * pts[i, 0] + R[r, 1] * pts[i, 1] + R[r, 2] * pts[i, 2] + t[r]
            out_n[i, r] = R[r, 0] * nrm[i, 0] + R[r, 1] * nrm[i, 1] + R[r, 2] * nrm[i, 2]


def _out(buf, shape) -> np.ndarray:
    """``buf`` if it is a C-contiguous float64 array of ``shape`` (reused from call to call), else a new one."""
    if buf is not None and buf.shape == tuple(shape) and buf.dtype == np.float64 and buf.flags.c_contiguous:
        return buf
    return np.empty(shape)


@njit(parallel=True, **JIT)
def _rigid_shift_kernel(pts, nrm, R, t, shift_x, out_p, out_n):
    for i in prange(pts.shape[0]):
        for r in range(3):
            out_p[i, r] = R[r, 0] * pts[i, 0] + R[r, 1] * pts[i, 1] + R[r, 2] * pts[i, 2] + t[r]
            out_n[i, r] = R[r, 0] * nrm[i, 0] + R[r, 1] * nrm[i, 1] + R[r, 2] * nrm[i, 2]
        pts[i, 0] += shift_x


def to_map_frame(points_cam, normals_cam, T_map_cam, nthreads: int | None = None,
                 out=(None, None), shift_x_m: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) and normals (N, 3) from the camera frame into the map frame: R p + t and R n (numba).

    ``out`` may hold two (N, 3) float64 buffers to write into. With ``shift_x_m``, ``points_cam`` (a
    C-contiguous float64 (N, 3) array) is then moved in place by ``shift_x_m`` [m] along its x axis, in the
    same pass (the renderer's step from the imager's frame into the projector's, which has the same
    orientation); the map-frame points are those of the points before the move.
    """
    if shift_x_m is not None and not (isinstance(points_cam, np.ndarray) and points_cam.dtype == np.float64
                                      and points_cam.flags.c_contiguous and points_cam.size % 3 == 0):
        raise ValueError("points_cam must be a C-contiguous float64 (N, 3) array to be moved in place")
    p = np.ascontiguousarray(points_cam, dtype=np.float64).reshape(-1, 3)
    n = np.ascontiguousarray(normals_cam, dtype=np.float64).reshape(-1, 3)
    T = np.asarray(T_map_cam, dtype=np.float64)
    out_p = _out(out[0], p.shape)
    out_n = _out(out[1], n.shape)
    R, t = np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3])
    with threads(resolve_threads(nthreads)):
        if shift_x_m is None:
            _rigid_kernel(p, n, R, t, out_p, out_n)
        else:
            _rigid_shift_kernel(p, n, R, t, float(shift_x_m), out_p, out_n)
    return out_p, out_n


def to_map_frame_reference(points_cam, normals_cam, T_map_cam, shift_x_m: float | None = None):
    """NumPy reference of :func:`to_map_frame` (moves ``points_cam`` in place likewise)."""
    T = np.asarray(T_map_cam, dtype=np.float64)
    p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals_cam, dtype=np.float64).reshape(-1, 3)
    out_p = p @ T[:3, :3].T + T[:3, 3]
    out_n = n @ T[:3, :3].T
    if shift_x_m is not None:
        p[:, 0] += shift_x_m
    return out_p, out_n


@njit(parallel=True, **JIT)
def _irradiance_rate_kernel(per_irr, irr, out):
    big = np.finfo(np.float64).max
    for i in prange(irr.shape[0]):
        e = irr[i]
        if np.isnan(e):
            e = 0.0
        elif e == np.inf:
            e = big
        elif e == -np.inf:
            e = -big
        irr[i] = e
        out[i] = per_irr[i] * e


def irradiance_rate(rate_per_irradiance, irradiance_w_m2, nthreads: int | None = None, out=None) -> np.ndarray:
    """The electron rate of the projector's light per sample, rate = rate_per_irradiance * E (numba).

    ``irradiance_w_m2`` (a C-contiguous float64 array) has its NaN (no surface) set to 0 in place first,
    as ``np.nan_to_num`` does (infinities to the largest finite value), so that it can be integrated
    too. ``rate_per_irradiance`` [e-/s per W/m^2] has the same shape. Returns the rate [e-/s] (``out``
    if given: a float64 buffer of that shape).
    """
    irr = irradiance_w_m2
    if not (isinstance(irr, np.ndarray) and irr.dtype == np.float64 and irr.flags.c_contiguous):
        raise ValueError("irradiance_w_m2 must be a C-contiguous float64 array (it is cleaned in place)")
    per = np.ascontiguousarray(rate_per_irradiance, dtype=np.float64)
    if per.shape != irr.shape:
        raise ValueError(f"rate_per_irradiance {per.shape} and irradiance_w_m2 {irr.shape} differ in shape")
    out = _out(out, irr.shape)
    with threads(resolve_threads(nthreads)):
        _irradiance_rate_kernel(per.reshape(-1), irr.reshape(-1), out.reshape(-1))
    return out


def irradiance_rate_reference(rate_per_irradiance, irradiance_w_m2) -> np.ndarray:
    """NumPy reference of :func:`irradiance_rate` (cleans ``irradiance_w_m2`` in place likewise)."""
    np.nan_to_num(irradiance_w_m2, copy=False, nan=0.0)
    with np.errstate(over="ignore"):                      # an infinite irradiance stays infinite
        return np.multiply(rate_per_irradiance, irradiance_w_m2)


def _intr(K) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError("K must be a 3x3 camera matrix with positive focal lengths")
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])


def surface_geometry(z, K, nthreads: int | None = None, out=(None, None)) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points and unit normals of a z-depth image (numba).

    Parameters
    ----------
    z : ndarray, shape (H, W)
        z-depth [m]; NaN = no surface.
    K : ndarray, shape (3, 3)
        Intrinsics [px] of that image.
    nthreads : int, optional
        numba threads; the result does not depend on it.
    out : tuple of two arrays, optional
        (H, W, 3) float64 buffers to write into (reused from frame to frame).

    Returns
    -------
    points_cam, normals_cam : ndarray, shape (H, W, 3)
        Points [m] and unit normals, NaN where z is. The normal is the cross product of one-sided
        differences to the right/left and lower/upper neighbour, each time the neighbour whose depth
        differs least (so depth edges do not tilt it), turned towards the camera; a pixel with no
        valid neighbour along an axis gets the normal facing the camera (-ray direction).
    """
    zz = np.ascontiguousarray(z, dtype=np.float64)
    if zz.ndim != 2:
        raise ValueError(f"z must be a 2-D depth image, got shape {zz.shape}")
    pts = _out(out[0], zz.shape + (3,))
    nrm = _out(out[1], zz.shape + (3,))
    with threads(resolve_threads(nthreads)):
        _geometry_kernel(zz, _intr(K), pts, nrm)
    return pts, nrm


def surface_geometry_reference(z, K) -> tuple[np.ndarray, np.ndarray]:
    """NumPy reference of :func:`surface_geometry`."""
    z = np.asarray(z, dtype=np.float64)
    fx, fy, cx, cy = _intr(K)
    h, w = z.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    a, b = (u - cx) / fx, (v - cy) / fy
    P = np.stack([a * z, b * z, z], axis=-1)
    nan_col = np.full((h, 1), np.nan)
    nan_row = np.full((1, w), np.nan)

    def pick(za, zb):
        fa, fb = np.isfinite(za), np.isfinite(zb)
        use_b = fb & (~fa | (np.abs(zb - z) <= np.abs(za - z)))
        return np.where(use_b, 1, np.where(fa, -1, 0))

    su = pick(np.hstack([nan_col, z[:, :-1]]), np.hstack([z[:, 1:], nan_col]))
    sv = pick(np.vstack([nan_row, z[:-1]]), np.vstack([z[1:], nan_row]))
    uu = np.clip(u.astype(int) + su, 0, w - 1)
    vv = np.clip(v.astype(int) + sv, 0, h - 1)
    rows, cols = v.astype(int), u.astype(int)
    zu, zv = z[rows, uu], z[vv, cols]
    tu = su[..., None] * (np.stack([((uu - cx) / fx) * zu, b * zu, zu], axis=-1) - P)
    tv = sv[..., None] * (np.stack([a * zv, ((vv - cy) / fy) * zv, zv], axis=-1) - P)
    n = np.cross(tu, tv)
    n *= np.where((n * P).sum(axis=-1) > 0, -1.0, 1.0)[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        facing = -P / np.linalg.norm(P, axis=-1, keepdims=True)
    n = np.where(((su == 0) | (sv == 0))[..., None], facing, n)
    bad = ~np.isfinite(z)
    P[bad] = np.nan
    n[bad] = np.nan
    return P, n


# ---------------------------------------------------------------------------------------------
# radiometry and image formation
# ---------------------------------------------------------------------------------------------


def sample_intrinsics(K, supersample: int) -> np.ndarray:
    """Intrinsics of the sample grid: s x s samples per pixel at the centres of its sub-squares.

    Sample (i, j) of pixel (u, v) sits at (u + (i + 0.5) / s - 0.5, v + (j + 0.5) / s - 0.5), so the
    sample image has f_s = s f and c_s = s c + (s - 1) / 2 (pixel centres at integer coordinates).
    """
    s = int(supersample)
    K = np.asarray(K, dtype=np.float64).copy()
    K[0, 0] *= s
    K[1, 1] *= s
    K[0, 2] = s * K[0, 2] + (s - 1) / 2.0
    K[1, 2] = s * K[1, 2] + (s - 1) / 2.0
    return K


@njit(parallel=True, **JIT)
def _relative_illumination_kernel(intr, power, out):
    hs, ws = out.shape
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    for v in prange(hs):
        b = (v - cy) / fy
        for u in range(ws):
            a = (u - cx) / fx
            out[v, u] = (1.0 + a * a + b * b) ** (-0.5 * power)


@njit(parallel=True, **JIT)
def _rate_kernel(rho, E, rel, k, out):
    hs, ws = rho.shape
    for v in prange(hs):
        for u in range(ws):
            r = k * rho[v, u] * E[v, u] * rel[v, u]
            out[v, u] = r if r > 0.0 else 0.0                  # also 0 for NaN (no surface)


@njit(parallel=True, **JIT)
def _rate_scalar_kernel(rho, E, rel, k, out):
    hs, ws = rho.shape
    for v in prange(hs):
        for u in range(ws):
            r = k * rho[v, u] * E * rel[v, u]
            out[v, u] = r if r > 0.0 else 0.0


def _rate_constant(focal_px: float, model: ImagerModel) -> float:
    photon_j = PLANCK_J_S * LIGHT_M_S / model.wavelength_m
    return model.quantum_efficiency * model.pixel_area_m2(focal_px) / (4.0 * model.f_number ** 2 * photon_j)


#: Relative illumination images by (intrinsics, shape, power): the same for every pose of a camera.
_RELATIVE_ILLUMINATION: dict = {}


def _relative_illumination(intr: np.ndarray, shape, power: float, nthreads: int) -> np.ndarray:
    """cos^k of the field angle, (1 + a^2 + b^2)^(-k / 2), at every sample of a grid (kept for reuse)."""
    key = (tuple(intr.tolist()), tuple(shape), float(power))
    rel = _RELATIVE_ILLUMINATION.get(key)
    if rel is None:
        if len(_RELATIVE_ILLUMINATION) >= 8:
            _RELATIVE_ILLUMINATION.clear()
        rel = np.empty(shape)
        with threads(nthreads):
            _relative_illumination_kernel(intr, float(power), rel)
        rel.flags.writeable = False
        _RELATIVE_ILLUMINATION[key] = rel
    return rel


def signal_rate(albedo, irradiance_w_m2, K_samples, focal_px: float, model: ImagerModel,
                nthreads: int | None = None, out=None) -> np.ndarray:
    """Photo-electron rate [e-/s] per pixel area at each sample (the module docstring's equation; numba).

    Parameters
    ----------
    albedo, irradiance_w_m2 : ndarray, shape (Hs, Ws)
        Surface albedo and total irradiance at each sample (the irradiance may be a scalar); NaN (no
        surface) gives 0.
    K_samples : ndarray, shape (3, 3)
        Intrinsics of the sample grid (field angles).
    focal_px : float
        Focal length of the output pixels (pixel area).
    model : ImagerModel
        The imager.
    nthreads : int, optional
        numba threads; the result does not depend on it.
    out : ndarray, shape (Hs, Ws), float64, optional
        Buffer to write into.

    Notes
    -----
    The relative illumination depends only on the sample grid, so it is computed once per grid and
    kept (up to 8 grids).
    """
    rho = np.ascontiguousarray(albedo, dtype=np.float64)
    if rho.ndim != 2:
        raise ValueError(f"albedo must be a 2-D sample image, got shape {rho.shape}")
    E = np.asarray(irradiance_w_m2, dtype=np.float64)
    out = _out(out, rho.shape)
    n = resolve_threads(nthreads)
    rel = _relative_illumination(_intr(K_samples), rho.shape, model.vignetting_power, n)
    k = _rate_constant(focal_px, model)
    with threads(n):
        if E.ndim == 0:
            _rate_scalar_kernel(rho, float(E), rel, k, out)
        else:
            _rate_kernel(rho, np.ascontiguousarray(np.broadcast_to(E, rho.shape)), rel, k, out)
    return out


def signal_rate_reference(albedo, irradiance_w_m2, K_samples, focal_px: float, model: ImagerModel) -> np.ndarray:
    """NumPy reference of :func:`signal_rate`."""
    rho = np.asarray(albedo, dtype=np.float64)
    E = np.asarray(irradiance_w_m2, dtype=np.float64)
    hs, ws = rho.shape
    fx, fy, cx, cy = _intr(K_samples)
    a2 = ((np.arange(ws) - cx) / fx) ** 2
    b2 = ((np.arange(hs) - cy) / fy) ** 2
    rel = (1.0 + b2[:, None] + a2[None, :]) ** (-0.5 * model.vignetting_power)
    rate = _rate_constant(focal_px, model) * rho * E * rel
    return np.where(np.isfinite(rate), np.maximum(rate, 0.0), 0.0)


@njit(**JIT)
def _shift_kernel(rate, dx, out):
    h, w = rate.shape
    for v in range(h):                 # serial: a few hundred microseconds, less than waking threads
        for u in range(w):
            x = u - dx
            x = min(max(x, 0.0), w - 1.0)
            x0 = min(int(np.floor(x)), w - 2) if w > 1 else 0
            t = x - x0
            out[v, u] = rate[v, x0] * (1.0 - t) + rate[v, x0 + 1] * t if w > 1 else rate[v, 0]


def shift_columns(rate, dx_px: float, nthreads: int | None = None) -> np.ndarray:
    """An image moved sideways by ``dx_px`` [px]: out(u) = rate(u - dx) by linear interpolation (numba).

    Columns beyond the border read the border column. ``rate`` (H, W); returns a new float64 array.
    ``nthreads`` is accepted for the common signature; the kernel is serial.
    """
    r = np.ascontiguousarray(rate, dtype=np.float64)
    if r.ndim != 2:
        raise ValueError(f"rate must be a 2-D image, got shape {r.shape}")
    resolve_threads(nthreads)
    out = np.empty_like(r)
    _shift_kernel(r, float(dx_px), out)
    return out


def shift_columns_reference(rate, dx_px: float) -> np.ndarray:
    """NumPy reference of :func:`shift_columns`."""
    r = np.asarray(rate, dtype=np.float64)
    w = r.shape[1]
    x = np.clip(np.arange(w) - float(dx_px), 0.0, w - 1.0)
    return np.stack([np.interp(x, np.arange(w), row) for row in r]) if w > 1 else r.copy()


def auto_exposure(rate_left, model: ImagerModel) -> Exposure:
    """Exposure time and gain that bring the mean signal of ``rate_left`` [e-/s] to ``ae_target``.

    t = ae_target full_well / mean(rate), at most ``max_exposure_s``; if that is not enough the gain
    makes up the rest, at most ``max_gain``. A manual ``exposure_s`` is returned unchanged.
    """
    if model.exposure_s is not None:
        return Exposure(float(model.exposure_s), float(model.gain))
    target_e = model.ae_target * model.full_well_e
    mean_rate = float(np.mean(rate_left))
    if not mean_rate > 0:
        return Exposure(model.max_exposure_s, model.max_gain)
    t = target_e / mean_rate
    if t <= model.max_exposure_s:
        return Exposure(t, 1.0)
    gain = min(model.max_gain, target_e / (mean_rate * model.max_exposure_s))
    return Exposure(model.max_exposure_s, gain)


def expose(rate_ambient, rate_projector, exposure: Exposure, rng: np.random.Generator, model: ImagerModel,
           speckle_contrast: float = 0.0, focal_px: float | None = None, nthreads: int | None = None) -> np.ndarray:
    """One frame of an imager: pointing jitter, laser speckle, shot and read noise, gain, conversion, bits.

    Parameters
    ----------
    rate_ambient, rate_projector : ndarray, shape (H, W)
        Noise-free photo-electron rates [e-/s] per pixel from the ambient light and from the projector.
    exposure : Exposure
        Exposure time [s] and gain.
    rng : numpy.random.Generator
        Draws the noise in this order: pointing jitter (if any), speckle (if any), Poisson shot noise,
        Gaussian read noise.
    model : ImagerModel
        The imager.
    speckle_contrast : float
        Contrast C (std / mean) of the laser speckle on the projector's light: each pixel's projector
        rate is multiplied by a fresh Gamma(1 / C^2, C^2) factor (mean 1, sd C; the intensity
        statistics of speckle averaged over a few grains), independently in the two imagers, which see
        different speckle through their own apertures. 0 = none.
    focal_px : float, optional
        Focal length of the image [px]: with ``model.pointing_jitter_rad`` > 0 the frame is moved
        sideways by f N(0, sigma_p^2) px (:func:`shift_columns`) before the noise. None = no jitter.
    nthreads : int, optional
        numba threads of the arithmetic between the draws (numba); the image does not depend on it,
        and equals :func:`expose_reference`'s to the bit.

    Returns
    -------
    ndarray, shape (H, W)
        uint8 (8-bit output: the 10-bit value // 4) or uint16 (10-bit levels).
    """
    proj = np.ascontiguousarray(rate_projector, dtype=np.float64)
    amb = np.ascontiguousarray(rate_ambient, dtype=np.float64)
    if proj.ndim != 2 or amb.shape != proj.shape:
        return expose_reference(amb, proj, exposure, rng, model, speckle_contrast, focal_px)
    shift = focal_px is not None and model.pointing_jitter_rad > 0
    dx = float(rng.normal(0.0, model.pointing_jitter_rad)) * float(focal_px) if shift else 0.0
    if speckle_contrast > 0:
        k = 1.0 / speckle_contrast ** 2
        speckle = rng.gamma(k, 1.0 / k, proj.shape)
    else:
        speckle = np.ones((1, 1))
    n = resolve_threads(nthreads)
    lam = np.empty(proj.shape)
    with threads(n):
        _expected_electrons_kernel(proj, amb, dx, shift, speckle, speckle_contrast > 0, float(exposure.time_s), lam)
    counts = rng.poisson(lam)
    read = rng.normal(0.0, model.read_noise_e, lam.shape) if model.read_noise_e > 0 else np.zeros((1, 1))
    dn10 = np.empty(proj.shape, np.uint16)
    with threads(n):
        _quantise_kernel(counts, read, model.read_noise_e > 0, float(exposure.gain), model.electrons_per_dn(),
                         float(model.black_level_dn), dn10)
    if model.output_bits == 10:
        return dn10
    return (dn10 // 4).astype(np.uint8)


@njit(inline="always", **JIT)
def _shift_row_into(out, img, v, dx):
    """out[u] = row v of ``img`` (H, W) read at column u - dx by linear interpolation, clamped to the row, as
    :func:`shift_columns` reads it."""
    w = img.shape[1]
    for u in range(w):
        x = u - dx
        x = min(max(x, 0.0), w - 1.0)
        x0 = min(int(np.floor(x)), w - 2) if w > 1 else 0
        t = x - x0
        out[u] = img[v, x0] * (1.0 - t) + img[v, x0 + 1] * t if w > 1 else img[v, 0]


@njit(parallel=True, **JIT)
def _expected_electrons_kernel(proj, amb, dx, shift, speckle, use_speckle, time_s, lam):
    """lam = max((amb' + proj' g) t, 0) of :func:`expose_reference`, amb' and proj' moved by dx (if ``shift``)
    as :func:`shift_columns` moves them. One operation per loop over a row (stored between), so that the
    fastmath flags fuse or reorder nothing: the same values as the NumPy passes."""
    h, w = proj.shape
    for v in prange(h):
        p = np.empty(w)
        a = np.empty(w)
        if shift:
            _shift_row_into(p, proj, v, dx)
            _shift_row_into(a, amb, v, dx)
        else:
            for u in range(w):
                p[u] = proj[v, u]
                a[u] = amb[v, u]
        if use_speckle:
            for u in range(w):
                p[u] = p[u] * speckle[v, u]
        for u in range(w):
            p[u] = a[u] + p[u]
        for u in range(w):
            e = p[u] * time_s
            lam[v, u] = 0.0 if e < 0.0 else e


@njit(parallel=True, **JIT)
def _quantise_kernel(counts, read, use_read, gain, e_per_dn, black_dn, dn10):
    """floor(e gain / e_per_dn + black + 1/2) clipped to 0..1023, e = counts (+ read): the NumPy order, one
    operation per loop."""
    h, w = counts.shape
    for v in prange(h):
        e = np.empty(w)
        for u in range(w):
            e[u] = float(counts[v, u])
        if use_read:
            for u in range(w):
                e[u] = e[u] + read[v, u]
        for u in range(w):
            e[u] = e[u] * gain
        for u in range(w):
            e[u] = e[u] / e_per_dn
        for u in range(w):
            e[u] = e[u] + black_dn
        for u in range(w):
            e[u] = e[u] + 0.5
        for u in range(w):
            d = np.floor(e[u])
            dn10[v, u] = np.uint16(0.0 if d < 0.0 else (1023.0 if d > 1023.0 else d))


def expose_reference(rate_ambient, rate_projector, exposure: Exposure, rng: np.random.Generator, model: ImagerModel,
                     speckle_contrast: float = 0.0, focal_px: float | None = None) -> np.ndarray:
    """NumPy reference of :func:`expose`: the same draws from ``rng`` and the same image."""
    proj = np.asarray(rate_projector, dtype=np.float64)
    amb = np.asarray(rate_ambient, dtype=np.float64)
    if focal_px is not None and model.pointing_jitter_rad > 0:
        dx = float(rng.normal(0.0, model.pointing_jitter_rad)) * float(focal_px)
        proj = shift_columns(proj, dx)
        amb = shift_columns(amb, dx) if np.any(amb) else amb
    if speckle_contrast > 0:
        k = 1.0 / speckle_contrast ** 2
        proj = proj * rng.gamma(k, 1.0 / k, proj.shape)
    lam = np.maximum((amb + proj) * exposure.time_s, 0.0)
    electrons = rng.poisson(lam).astype(np.float64)
    if model.read_noise_e > 0:
        electrons += rng.normal(0.0, model.read_noise_e, lam.shape)
    dn = np.floor(electrons * exposure.gain / model.electrons_per_dn() + model.black_level_dn + 0.5)
    dn10 = np.clip(dn, 0, 1023).astype(np.uint16)
    if model.output_bits == 10:
        return dn10
    return (dn10 // 4).astype(np.uint8)
