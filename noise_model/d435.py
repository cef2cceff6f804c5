"""The Intel RealSense D435 and the empirical noise model of Ahn et al. (2019).

Reference: M. S. Ahn, H. Chae, D. Noh, H. Nam, D. Hong, "Analysis and Noise Modeling of the Intel
RealSense D435 for Mobile Robots", 16th International Conference on Ubiquitous Robots (UR), 2019.

Axial (depth) noise, the paper's fit over 0.4-2.1 m and 0-75 deg of target rotation::

    sigma_z(z, theta) = 0.001063 + 0.0007278 z + 0.003949 z^2 + 0.022 z^(3/2) theta / (pi/2 - theta)^2   [m]

with z the depth [m] and theta [rad] the angle between the surface normal and the optical axis (the
paper rotates its target about the camera's y axis, theta_y; we use the same formula for any tilt).
Lateral noise on depth discontinuities, 90th percentiles: sigma_L = 0.0432 m on left edges (the
shadowed side of the left-imager-referenced depth), sigma_R = 0.0407 m on right edges.

Expected stereo RMS error, the paper's equation (1) (Intel's depth-resolution formula)::

    e = d^2 s / (f b),   f = 0.5 p_x / tan(V_h / 2)

with d the distance [m], s the subpixel accuracy [px] (0.08 is Intel's typical value), b the baseline
[m], p_x the horizontal resolution [px] and V_h the horizontal field of view.

Field of view and default intrinsics
------------------------------------
Intel's white paper "Subpixel Linearity Improvement for Intel RealSense Depth Camera D400 Series" uses
HFOV = 90 deg for the D435 in this formula, and real units agree: the depth stream of a typical D435
at 848x480 has fx ~ 425 px, i.e. HFOV = 2 atan(424 / 425) = 89.9 deg (the datasheet quotes
87 +- 3 deg). The 16:9 modes (1280x720, 848x480, 424x240) therefore use HFOV = 90 deg and
fx = fy = 0.5 W / tan(45 deg) = W / 2. The 4:3 mode 640x480 is a centre crop of the imager at 0.6 of
its 1280-wide scale, so f = 0.6 * 640 = 384 px and HFOV = 2 atan(320 / 384) = 79.6 deg; the librealsense
unit-test D435 recording (640x480, fx = 390.4 px, HFOV 78.7 deg) agrees within unit-to-unit spread.
The principal point is the image centre, ((W - 1) / 2, (H - 1) / 2), in the pixel-centre convention
of RealSense and OpenCV (integer coordinates are pixel centres).

Model families
--------------
``SensorModel.family`` selects the form of sigma_z. ``"paper"`` (the default, and the model of the
constant ``D435``) is Ahn et al.'s polynomial above. ``"disparity"`` models the noise where a stereo
camera makes it, in the disparity d = f B / z::

    sigma_z(z, theta) = z^2 sigma_d(theta) / (f B),   sigma_d(theta) = s0 + s1 theta^2   [px]

with f the focal length [px] of the frame (from its intrinsics: the same camera at 424x240 has half
the focal length of 848x480 and twice the depth noise per pixel of disparity) and B the baseline [m].
Its sigma_z needs f: the kernels take it from the frame's K, the NumPy functions from ``fx_px`` or a
model bound to a frame with :meth:`SensorModel.with_focal`. The lateral terms (sigma_L, sigma_R, the
pixel footprint) are the same in both families.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from .checks import MAX_PLAUSIBLE_DEPTH_M, check_positive_scalar
from .formulas import (
    angle_gain, disparity_angle_gain, disparity_expected_sigma_z_sq, disparity_sigma_z_from_gain, expected_sigma_z_sq,
    sigma_z_from_gain,
)

__all__ = ["SensorModel", "D435", "axial_sigma", "axial_variance", "expected_rms_error", "THETA_MAX_DEFAULT",
           "THETA_QUADRATURE", "THETA_GRID", "axial_sigma_unchecked", "axial_variance_unchecked", "FAMILIES",
           "MODEL_FORMAT", "MODEL_FORMAT_DISPARITY", "MODEL_FORMAT_FRAME_ERROR"]

#: The model families of :class:`SensorModel` (see the module docstring).
FAMILIES = ("paper", "disparity")

#: The model file's format: a paper-family model keeps the first version (files written before the
#: disparity family existed read the same); a disparity-family model is written as the second, which a
#: reader that knows only the paper's family rejects instead of reading it as the paper's.
MODEL_FORMAT = "elevmap-sensor-model/1"
MODEL_FORMAT_DISPARITY = "elevmap-sensor-model/2"
#: A model that also states its per-frame error (``frame_variance_ratio``, ``error_correlation_px``) is
#: written as the third, with ``family`` and ``disparity_sigma_px`` always present; a model without them
#: keeps the first or second, so older readers read it as before.
MODEL_FORMAT_FRAME_ERROR = "elevmap-sensor-model/3"

#: Default cap on the incidence angle [rad]: 80 deg. The paper measured up to 75 deg; its theta term
#: diverges at 90 deg, where a stereo camera sees nothing at all. At 80 deg and 1 m sigma_z is already
#: 1.0 m, so a capped point carries almost no height information, yet its variance stays finite.
THETA_MAX_DEFAULT = math.radians(80.0)

_HFOV_16_9_DEG = 90.0
_HFOV_4_3_DEG = math.degrees(2.0 * math.atan(320.0 / 384.0))


@dataclass(frozen=True)
class SensorModel:
    """A depth camera's geometry and its noise model (Ahn et al.'s form, or the disparity family).

    Attributes
    ----------
    name : str
        Free-form name ("D435 (Ahn et al. 2019)" or a user's own fit).
    axial_coefficients : tuple of 4 floats
        (c0 [m], c1 [-], c2 [1/m], c_theta [m^-1/2]) of the paper's family,
        sigma_z = c0 + c1 z + c2 z^2 + c_theta z^(3/2) theta / (pi/2 - theta)^2.
    sigma_L, sigma_R : float
        Lateral noise [m] across left and right depth edges.
    baseline_m : float
        Stereo baseline [m].
    subpixel : float
        Subpixel disparity accuracy [px] used by ``expected_rms_error``.
    theta_max_rad : float
        Incidence angles at or beyond this are capped to it [rad].
    hfov_deg : dict
        Horizontal field of view [deg] per (width, height) mode.
    family : {"paper", "disparity"}
        Which form sigma_z takes (module docstring); "paper" by default.
    disparity_sigma_px : tuple of 2 floats
        (s0 [px], s1 [px / rad^2]) of the disparity family, sigma_d(theta) = s0 + s1 theta^2; s0 > 0,
        s1 >= 0 (sigma_d grows with the slant; a fit that finds no growth gives 0). Unused by the paper's
        family.
    frame_fx_px : float or None
        The focal length [px] of the frame the model is applied to (:meth:`with_focal`), for the disparity
        family's sigma_z in the NumPy functions; a property of the frame, never saved.
    frame_variance_ratio : float
        Variance of one frame's depth error about the truth over the modelled (per-pixel temporal)
        variance, >= 1: a stereo camera adds a static error pattern that a static capture's temporal
        standard deviation cannot see, yet a moving camera sees it anew in every frame, and an offset
        every pixel of a frame shares, which the axial fit removes with the frame's plane motion. 1 (default): the
        modelled sigma is the whole per-frame error.
    error_correlation_px : float
        Gaussian correlation length l [px] of that per-frame error across the image,
        rho(h) = exp(-h^2 / (2 l^2)), at the focal length ``error_correlation_fx_px``; 0 (default): the
        pixels' errors are independent. A map fuses the pixels a cell holds as fewer independent samples
        (:meth:`frame_error`).
    error_correlation_fx_px : float or None
        Focal length [px] of the stream the correlation length was measured on (it scales with the focal
        length of the frame it is applied to); None when there is no correlation.
    frame_noise : tuple of floats or None
        sigma_z of one frame's error (temporal + static) fitted in the model's own family: (c0, c1, c2,
        c_theta) of the paper's, (s0, s1) of the disparity family. The static part grows with the angle
        and nearness far more than the temporal one, so a single ``frame_variance_ratio`` misstates both
        ends; a map uses :meth:`for_map`. None: only the ratio is known.
    """

    name: str = "D435 (Ahn et al. 2019)"
    axial_coefficients: tuple = (0.001063, 0.0007278, 0.003949, 0.022)
    sigma_L: float = 0.0432
    sigma_R: float = 0.0407
    baseline_m: float = 0.050
    subpixel: float = 0.08
    theta_max_rad: float = THETA_MAX_DEFAULT
    hfov_deg: dict = field(
        default_factory=lambda: {
            (1280, 720): _HFOV_16_9_DEG,
            (848, 480): _HFOV_16_9_DEG,
            (640, 480): _HFOV_4_3_DEG,
            (424, 240): _HFOV_16_9_DEG,
        }
    )
    family: str = "paper"
    disparity_sigma_px: tuple = (0.08, 0.0)
    frame_fx_px: float | None = None
    frame_variance_ratio: float = 1.0
    error_correlation_px: float = 0.0
    error_correlation_fx_px: float | None = None
    frame_noise: tuple | None = None

    def __post_init__(self):
        if self.family not in FAMILIES:
            raise ValueError(f"sensor model {self.name!r}: family must be one of {FAMILIES}, got {self.family!r}")
        try:
            sd = tuple(float(x) for x in self.disparity_sigma_px)
        except (TypeError, ValueError):
            raise ValueError(f"sensor model {self.name!r}: disparity_sigma_px must be 2 numbers (s0 [px], "
                             f"s1 [px/rad^2]), got {self.disparity_sigma_px!r}") from None
        if len(sd) != 2 or not all(math.isfinite(x) for x in sd) or not sd[0] > 0 or sd[1] < 0 or sd[0] > 10.0:
            raise ValueError(f"sensor model {self.name!r}: disparity_sigma_px must be (s0, s1) with 0 < s0 <= 10 px "
                             f"and s1 >= 0 px/rad^2, finite, got {self.disparity_sigma_px!r}")
        object.__setattr__(self, "disparity_sigma_px", sd)
        if self.frame_fx_px is not None:
            object.__setattr__(self, "frame_fx_px",
                               check_positive_scalar(self.frame_fx_px, "frame_fx_px", upper=1e5, unit=" px"))
        ratio, ell, fx = self.frame_variance_ratio, self.error_correlation_px, self.error_correlation_fx_px
        if isinstance(ratio, bool) or not isinstance(ratio, (int, float, np.integer, np.floating)) \
                or not (math.isfinite(ratio) and 1.0 <= ratio <= 100.0):
            raise ValueError(f"sensor model {self.name!r}: frame_variance_ratio must be a number in [1, 100], "
                             f"got {ratio!r}")
        if isinstance(ell, bool) or not isinstance(ell, (int, float, np.integer, np.floating)) \
                or not (math.isfinite(ell) and 0.0 <= ell <= 1000.0):
            raise ValueError(f"sensor model {self.name!r}: error_correlation_px must be a number in [0, 1000] px, "
                             f"got {ell!r}")
        if ell > 0.0 and fx is None:
            raise ValueError(f"sensor model {self.name!r}: error_correlation_px > 0 needs error_correlation_fx_px, "
                             "the focal length [px] it was measured at")
        object.__setattr__(self, "frame_variance_ratio", float(ratio))
        object.__setattr__(self, "error_correlation_px", float(ell))
        if fx is not None:
            object.__setattr__(self, "error_correlation_fx_px",
                               check_positive_scalar(fx, "error_correlation_fx_px", upper=1e5, unit=" px"))
        if self.frame_noise is not None:
            k = 4 if self.family == "paper" else 2
            try:
                fn = tuple(float(x) for x in self.frame_noise)
            except (TypeError, ValueError):
                fn = ()
            if len(fn) != k or not all(math.isfinite(x) for x in fn) or (k == 2 and not (fn[0] > 0 and fn[1] >= 0)):
                raise ValueError(f"sensor model {self.name!r}: frame_noise must be {k} finite numbers of the "
                                 f"{self.family} family, got {self.frame_noise!r}")
            object.__setattr__(self, "frame_noise", fn)

    # -- the paper's coefficients under their own names -------------------------------------------
    @property
    def c0(self) -> float:
        return float(self.axial_coefficients[0])

    @property
    def c1(self) -> float:
        return float(self.axial_coefficients[1])

    @property
    def c2(self) -> float:
        return float(self.axial_coefficients[2])

    @property
    def c_theta(self) -> float:
        return float(self.axial_coefficients[3])

    @property
    def modes(self) -> tuple:
        """The (width, height) modes with default intrinsics."""
        return tuple(self.hfov_deg)

    def focal_px(self, width: int, height: int) -> float:
        """Focal length [px] of a mode: fx = fy = 0.5 width / tan(HFOV / 2)."""
        key = (int(width), int(height))
        if key not in self.hfov_deg:
            raise ValueError(f"no default intrinsics for {width}x{height}; known modes: {sorted(self.hfov_deg)}")
        return 0.5 * key[0] / math.tan(math.radians(self.hfov_deg[key]) / 2.0)

    def intrinsics(self, width: int = 848, height: int = 480) -> np.ndarray:
        """Default 3x3 camera matrix K [px] of a mode (principal point at the image centre)."""
        f = self.focal_px(width, height)
        return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])

    def vfov_deg(self, width: int = 848, height: int = 480) -> float:
        """Vertical field of view [deg] implied by square pixels."""
        return math.degrees(2.0 * math.atan(0.5 * height / self.focal_px(width, height)))

    @property
    def s0(self) -> float:
        """sigma_d at theta = 0 [px] (disparity family)."""
        return float(self.disparity_sigma_px[0])

    @property
    def s1(self) -> float:
        """Growth of sigma_d with theta^2 [px / rad^2] (disparity family)."""
        return float(self.disparity_sigma_px[1])

    def disparity_depth_coefficients(self, fx_px: float | None = None) -> tuple[float, float]:
        """(s0 / (f B), s1 / (f B)) [1/m]: the disparity family's sigma_d in depth units at focal length f.

        Parameters
        ----------
        fx_px : float, optional
            The frame's focal length [px]; ``frame_fx_px`` when None (a ``ValueError`` without either:
            a disparity in pixels means nothing in metres without the focal length).
        """
        f = self.frame_fx_px if fx_px is None else check_positive_scalar(fx_px, "fx_px", upper=1e5, unit=" px")
        if f is None:
            raise ValueError(f"sensor model {self.name!r} is of the disparity family: its sigma_z needs the frame's "
                             "focal length (pass fx_px, or bind the model to the frame with model.with_focal(K[0, 0]))")
        fb = f * float(self.baseline_m)
        return self.s0 / fb, self.s1 / fb

    def params_array(self, fx_px: float | None = None) -> np.ndarray:
        """The noise parameters packed for numba kernels: c0, c1, c2, c_theta, theta_max, sigma_L, sigma_R, family.

        The paper's family: its coefficients and family 0. The disparity family: 0, 0, s0 / (f B),
        s1 / (f B), ..., family 1, with f = ``fx_px`` (the frame's focal length [px]; ``frame_fx_px`` when
        None): sigma_z = z^2 (c2 + c_theta theta^2) (:mod:`noise_model.formulas`).
        """
        if self.family == "disparity":
            c, g = self.disparity_depth_coefficients(fx_px)
            return np.array([0.0, 0.0, c, g, self.theta_max_rad, self.sigma_L, self.sigma_R, 1.0])
        return np.array([*map(float, self.axial_coefficients), self.theta_max_rad, self.sigma_L, self.sigma_R, 0.0])

    def with_disparity(self, s0: float, s1: float = 0.0, **changes) -> "SensorModel":
        """A copy of the disparity family with sigma_d(theta) = s0 + s1 theta^2 [px] (s0 > 0, s1 >= 0).

        ``D435.with_disparity(0.08)`` is Intel's typical subpixel accuracy as a noise model:
        sigma_z = 0.08 z^2 / (f B).
        """
        changes.setdefault("name", f"D435 (disparity noise, sigma_d = {float(s0):g} + {float(s1):g} theta^2 px)")
        return replace(self, family="disparity", disparity_sigma_px=(float(s0), float(s1)), **changes)

    @property
    def has_frame_error(self) -> bool:
        """True when the model states a per-frame error beyond its per-pixel sigma (ratio > 1, a correlation
        or a per-frame sigma_z)."""
        return self.frame_variance_ratio != 1.0 or self.error_correlation_px > 0.0 or self.frame_noise is not None

    def for_map(self) -> "SensorModel":
        """The model a map fuses with: sigma_z of one frame's whole error (``frame_noise``) in place of the
        per-pixel temporal one, with ratio 1 (it is inside that sigma_z) and the same correlation; the model
        itself when it has no ``frame_noise``."""
        if self.frame_noise is None:
            return self
        if self.family == "paper":
            return replace(self, axial_coefficients=self.frame_noise, frame_noise=None, frame_variance_ratio=1.0)
        return replace(self, disparity_sigma_px=self.frame_noise, frame_noise=None, frame_variance_ratio=1.0)

    def frame_error(self, fx_px: float) -> tuple[float, float]:
        """(correlation length [px] at a frame of focal length ``fx_px``, per-frame variance ratio) for the map.

        The length scales with the focal length: a correlation measured over l pixels of one stream spans
        l f / f_measured pixels of a stream of focal length f (the same angle). (0, ratio) when the model
        has no correlation.
        """
        fx = check_positive_scalar(fx_px, "fx_px", upper=1e5, unit=" px")
        if self.error_correlation_px <= 0.0:
            return 0.0, self.frame_variance_ratio
        return self.error_correlation_px * fx / self.error_correlation_fx_px, self.frame_variance_ratio

    def with_focal(self, fx_px: float) -> "SensorModel":
        """A copy bound to a frame of focal length ``fx_px`` [px] (what the disparity family's sigma_z needs)."""
        return replace(self, frame_fx_px=check_positive_scalar(fx_px, "fx_px", upper=1e5, unit=" px"))

    def with_coefficients(self, coefficients, **changes) -> "SensorModel":
        """A copy with other axial coefficients (for example a user's own fit)."""
        c = tuple(float(x) for x in coefficients)
        if len(c) != 4 or not all(np.isfinite(c)):
            raise ValueError(f"axial coefficients must be 4 finite numbers, got {coefficients!r}")
        return replace(self, axial_coefficients=c, **changes)

    # -- persistence: a user's fit replaces the paper's everywhere --------------------------------
    def to_dict(self) -> dict:
        """The model as plain JSON types: :data:`MODEL_FORMAT` for the paper's family (the same keys as
        before the disparity family existed), :data:`MODEL_FORMAT_DISPARITY` with ``family`` and
        ``disparity_sigma_px`` for the disparity family, :data:`MODEL_FORMAT_FRAME_ERROR` (either family)
        with ``frame_variance_ratio``, ``error_correlation_px``, ``error_correlation_fx_px`` and
        ``frame_noise`` (null when not fitted) when the model states a per-frame error. ``frame_fx_px`` (a property of a frame) is not saved."""
        d = asdict(self)
        d["axial_coefficients"] = list(self.axial_coefficients)
        d["hfov_deg"] = [[w, h, v] for (w, h), v in self.hfov_deg.items()]
        del d["frame_fx_px"]
        if self.has_frame_error:
            d["disparity_sigma_px"] = list(self.disparity_sigma_px)
            d["frame_noise"] = None if self.frame_noise is None else list(self.frame_noise)
            d["format"] = MODEL_FORMAT_FRAME_ERROR
            return d
        del d["frame_variance_ratio"], d["error_correlation_px"], d["error_correlation_fx_px"], d["frame_noise"]
        if self.family == "paper":
            del d["family"], d["disparity_sigma_px"]
            d["format"] = MODEL_FORMAT
        else:
            d["disparity_sigma_px"] = list(self.disparity_sigma_px)
            d["format"] = MODEL_FORMAT_DISPARITY
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SensorModel":
        """Read :meth:`to_dict`'s output (any of its formats; the first two have no per-frame error, as the
        files written before it); a missing or bad key raises ``ValueError`` naming it."""
        formats = (MODEL_FORMAT, MODEL_FORMAT_DISPARITY, MODEL_FORMAT_FRAME_ERROR)
        if not isinstance(d, dict) or d.get("format") not in formats:
            fmt = d.get("format") if isinstance(d, dict) else type(d).__name__
            raise ValueError(f"not an elevmap sensor model (format {fmt!r})")
        try:
            hfov = {(int(w), int(h)): float(v) for w, h, v in d["hfov_deg"]}
            extra = {}
            if d["format"] in (MODEL_FORMAT_DISPARITY, MODEL_FORMAT_FRAME_ERROR):
                extra = {"family": str(d["family"]),
                         "disparity_sigma_px": tuple(float(x) for x in d["disparity_sigma_px"])}
            if d["format"] == MODEL_FORMAT_FRAME_ERROR:
                fx = d["error_correlation_fx_px"]
                fn = d.get("frame_noise")
                extra.update(frame_variance_ratio=float(d["frame_variance_ratio"]),
                             error_correlation_px=float(d["error_correlation_px"]),
                             error_correlation_fx_px=None if fx is None else float(fx),
                             frame_noise=None if fn is None else tuple(float(x) for x in fn))
            model = cls(
                name=str(d["name"]),
                axial_coefficients=tuple(float(x) for x in d["axial_coefficients"]),
                sigma_L=float(d["sigma_L"]),
                sigma_R=float(d["sigma_R"]),
                baseline_m=float(d["baseline_m"]),
                subpixel=float(d["subpixel"]),
                theta_max_rad=float(d["theta_max_rad"]),
                hfov_deg=hfov,
                **extra,
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"sensor model is missing or has a bad key: {exc}") from None
        if len(model.axial_coefficients) != 4:
            raise ValueError("sensor model needs exactly 4 axial coefficients")
        if not all(math.isfinite(c) for c in model.axial_coefficients):
            raise ValueError("sensor model's axial_coefficients must be finite")
        if not (model.baseline_m > 0 and math.isfinite(model.baseline_m)):
            raise ValueError(f"sensor model's baseline_m must be a positive length [m], got {model.baseline_m!r}")
        return model

    def save(self, path) -> None:
        """Write the model as JSON, atomically (temporary file, then rename)."""
        path = os.fspath(path)
        directory = os.path.dirname(os.path.abspath(path))
        fd, tmp = tempfile.mkstemp(prefix=".sensor-model-", suffix=".json", dir=directory)
        try:
            with os.fdopen(fd, "w") as fh:
                json.dump(self.to_dict(), fh, indent=2)
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise

    @classmethod
    def load(cls, path) -> "SensorModel":
        """Read a model written by :meth:`save`; a corrupt file raises ``ValueError``."""
        try:
            with open(path) as fh:
                d = json.load(fh)
        except FileNotFoundError:
            raise ValueError(f"{path}: no such sensor model file") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"{path}: cannot read the sensor model file ({exc})") from None
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not valid JSON ({exc})") from None
        try:
            return cls.from_dict(d)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None


#: The D435 with the paper's coefficients.
D435 = SensorModel()


def axial_sigma(z, theta=0.0, model: SensorModel = D435, fx_px: float | None = None):
    """Axial (depth) noise sigma_z [m] of the model (Ahn et al. 2019 by default), broadcasting over any shapes.

    Parameters
    ----------
    z : array_like
        Depth along the optical axis [m]; finite and > 0.
    theta : array_like, optional
        Angle between the surface normal and the optical axis [rad]. The sign is ignored; values at
        or beyond ``model.theta_max_rad`` (80 deg by default) are capped to it.
    model : SensorModel
        Coefficients; the paper's D435 by default.
    fx_px : float, optional
        The frame's focal length [px], for a disparity-family model (sigma_z = z^2 sigma_d(theta) / (f B));
        the model's ``frame_fx_px`` when None. The paper's family ignores it.

    Returns
    -------
    ndarray or float
        sigma_z [m], with the broadcast shape of ``z`` and ``theta``.

    Raises
    ------
    ValueError
        If z is not finite and positive, looks like millimetres, or theta is not finite radians; if a
        disparity-family model has no focal length.
    """
    z_a = np.asarray(z, dtype=np.float64)
    t_a = np.asarray(theta, dtype=np.float64)
    if not np.all(np.isfinite(z_a)) or np.any(z_a <= 0):
        raise ValueError("z must be finite and > 0 [m]")
    if z_a.size and float(z_a.max()) > MAX_PLAUSIBLE_DEPTH_M:
        raise ValueError(f"z holds values up to {float(z_a.max()):.1f}: z must be in metres")
    if not np.all(np.isfinite(t_a)):
        raise ValueError("theta must be finite [rad]")
    if t_a.size and float(np.abs(t_a).max()) > 2 * np.pi:
        raise ValueError(f"theta holds values up to {float(np.abs(t_a).max()):.1f}: theta must be in radians")
    out = axial_sigma_unchecked(z_a, t_a, _bound(model, fx_px))
    return float(out) if out.ndim == 0 else out


def _bound(model: SensorModel, fx_px) -> SensorModel:
    """``model`` bound to the focal length ``fx_px`` where it is of the disparity family and one is given; checked
    here so that a disparity model without a focal length fails at the public entry."""
    if not isinstance(model, SensorModel):
        raise ValueError(f"model must be a noise_model.SensorModel, got {type(model).__name__}")
    if model.family == "disparity":
        if fx_px is not None:
            model = model.with_focal(fx_px)
        model.disparity_depth_coefficients()
    return model


def axial_sigma_unchecked(z, theta, model: SensorModel = D435):
    """:func:`axial_sigma` without the input checks, for callers inside the package whose inputs are valid.

    Parameters
    ----------
    z : ndarray
        Depth [m], finite and > 0.
    theta : ndarray
        Incidence angle [rad], finite; its sign is ignored and it is capped at ``model.theta_max_rad``.
    model : SensorModel
        A disparity-family model must be bound to the frame's focal length (:meth:`SensorModel.with_focal`).

    Returns
    -------
    ndarray
        sigma_z [m] (:func:`noise_model.formulas.sigma_z_from_gain`, or
        :func:`noise_model.formulas.disparity_sigma_z_from_gain` for the disparity family), the broadcast shape
        of ``z`` and ``theta``.
    """
    t = np.minimum(np.abs(theta), model.theta_max_rad)
    if model.family == "disparity":
        c, g1 = model.disparity_depth_coefficients()
        return disparity_sigma_z_from_gain(z, disparity_angle_gain(t, g1), c)
    c0, c1, c2, ct = (float(c) for c in model.axial_coefficients)
    return sigma_z_from_gain(z, angle_gain(t, ct), c0, c1, c2)


def _gh_rule(k: int):
    x, w = np.polynomial.hermite_e.hermegauss(k)
    return tuple(float(v) for v in x), tuple(float(v) for v in w / w.sum())


def _grid_rule(k: int, half_width: float):
    x = np.linspace(-half_width, half_width, k)
    w = np.exp(-0.5 * x * x)
    return tuple(float(v) for v in x), tuple(float(v) for v in w / w.sum())


#: Rules for E[f(theta)], theta ~ N(mu, s^2), as sum_k w_k f(mu + s x_k) (sum w_k = 1). Where
#: [mu - 4 s, mu + 4 s] lies inside (0, theta_max) the angle gain is smooth there and the probabilists'
#: 9-node Gauss-Hermite rule is used (within 1 % of a 20001-point integral); elsewhere the gain has a
#: kink (|theta| at 0, the cap at theta_max) and a 33-node grid over +-4 s is used. Both bounds are for
#: E[sigma_z^2] at angle standard deviations up to 0.26 rad (within 6 % on the grid); the moment E[g^2]
#: taken alone is less accurate next to the cap's kink. Checked in ``tests/sensor/test_d435.py``.
THETA_QUADRATURE = _gh_rule(9)
THETA_GRID = _grid_rule(33, 4.0)


def axial_variance(z, theta=0.0, theta_std=0.0, model: SensorModel = D435, fx_px: float | None = None):
    """E[sigma_z^2] [m^2] of Ahn et al.'s model when theta is an estimate: theta_true ~ N(theta, theta_std^2).

    The angle term of sigma_z grows as theta / (pi/2 - theta)^2, so an angle estimated from noisy depth
    (a plane fit over a window of pixels, see :func:`noise_model.incidence_angle_stats`) makes
    sigma_z(theta_hat)^2 an underestimate on average: E[sigma_z^2] over the angle's uncertainty is
    a^2 + 2 a k E[g] + k^2 E[g^2] with a = c0 + c1 z + c2 z^2, k = z^(3/2), g = c_theta theta /
    (pi/2 - theta)^2 (theta capped at theta_max, its sign ignored), the expectations by
    :data:`THETA_QUADRATURE` or :data:`THETA_GRID`. With theta_std = 0 it is sigma_z(z, theta)^2.

    Parameters
    ----------
    z : array_like
        Depth [m]; finite and > 0.
    theta : array_like
        Estimated incidence angle [rad].
    theta_std : array_like
        Standard deviation of the estimate [rad], finite and >= 0.
    model : SensorModel
    fx_px : float, optional
        The frame's focal length [px] for a disparity-family model (as :func:`axial_sigma`).

    Returns
    -------
    ndarray or float
        [m^2], the broadcast shape of the inputs.
    """
    model = _bound(model, fx_px)
    axial_sigma(z, theta, model)             # validates z and theta
    s_a = np.asarray(theta_std, dtype=np.float64)
    if not np.all(np.isfinite(s_a)) or np.any(s_a < 0):
        raise ValueError("theta_std must be finite and >= 0 [rad]")
    if s_a.size and float(s_a.max()) > np.pi:
        raise ValueError(f"theta_std holds values up to {float(s_a.max()):.1f}: theta_std must be in radians")
    z_a, t_a, s_a = np.broadcast_arrays(np.asarray(z, dtype=np.float64), np.asarray(theta, dtype=np.float64), s_a)
    out = axial_variance_unchecked(z_a, t_a, s_a, model)
    return float(out) if out.ndim == 0 else out


def _gain_moments_unchecked(theta, theta_std, model: SensorModel = D435):
    """(E[g], E[g^2]) of the angle gain g(theta) = c_theta t / (pi/2 - t)^2 (the disparity family:
    (s1 / (f B)) t^2), t = min(|theta|, theta_max), for theta ~ N(theta, theta_std^2) by
    :data:`THETA_QUADRATURE` or :data:`THETA_GRID` (the nodes summed in order, as the kernel)."""
    if model.family == "disparity":
        ct = model.disparity_depth_coefficients()[1]
        gain = disparity_angle_gain
    else:
        ct = float(model.axial_coefficients[3])
        gain = angle_gain
    tmax = float(model.theta_max_rad)
    out = []
    for xs, ws in (THETA_QUADRATURE, THETA_GRID):
        eg = np.zeros(np.shape(theta))
        eg2 = np.zeros(np.shape(theta))
        for x, w in zip(xs, ws):
            g = gain(np.minimum(np.abs(theta + theta_std * x), tmax), ct)
            eg = eg + w * g
            eg2 = eg2 + w * (g * g)
        out.append((eg, eg2))
    smooth = (theta - 4.0 * theta_std > 0.0) & (theta + 4.0 * theta_std < tmax)
    return np.where(smooth, out[0][0], out[1][0]), np.where(smooth, out[0][1], out[1][1])


def axial_variance_unchecked(z, theta, theta_std, model: SensorModel = D435):
    """:func:`axial_variance` without the input checks (z > 0 [m], theta finite, theta_std >= 0 [rad]):
    E[sigma_z^2] [m^2] = a^2 + 2 a k E[g] + k^2 E[g^2] (:func:`noise_model.formulas.expected_sigma_z_sq`; the
    disparity family, bound to its frame's focal length: :func:`noise_model.formulas.disparity_expected_sigma_z_sq`)."""
    eg, eg2 = _gain_moments_unchecked(theta, theta_std, model)
    if model.family == "disparity":
        return disparity_expected_sigma_z_sq(z, eg, eg2, model.disparity_depth_coefficients()[0])
    c0, c1, c2, _ = (float(c) for c in model.axial_coefficients)
    return expected_sigma_z_sq(z, eg, eg2, c0, c1, c2)


def expected_rms_error(z, subpixel: float = 0.08, baseline: float = 0.050, width_px: int = 848,
                       hfov_deg: float = _HFOV_16_9_DEG):
    """Expected stereo depth RMS error, equation (1) of Ahn et al. (2019) [m].

    e = z^2 s / (f b), with f = 0.5 width_px / tan(hfov / 2) [px].

    Parameters
    ----------
    z : array_like
        Distance [m], finite and > 0.
    subpixel : float
        Subpixel disparity accuracy s [px] (Intel's typical 0.08).
    baseline : float
        Stereo baseline b [m] (D435: 0.050).
    width_px : int
        Horizontal resolution p_x of the depth stream [px].
    hfov_deg : float
        Horizontal field of view V_h [deg] (D435: 90, Intel's value for this formula).
    """
    z_a = np.asarray(z, dtype=np.float64)
    if not np.all(np.isfinite(z_a)) or np.any(z_a <= 0):
        raise ValueError("z must be finite and > 0 [m]")
    if z_a.size and float(z_a.max()) > MAX_PLAUSIBLE_DEPTH_M:
        raise ValueError(f"z holds values up to {float(z_a.max()):.1f}: z must be in metres")
    s = check_positive_scalar(subpixel, "subpixel", upper=10.0, unit=" px")
    b = check_positive_scalar(baseline, "baseline", upper=2.0, unit=" m")
    w = check_positive_scalar(width_px, "width_px")
    h = check_positive_scalar(hfov_deg, "hfov_deg", upper=179.0, unit=" deg")
    f = 0.5 * w / math.tan(math.radians(h) / 2.0)
    out = z_a * z_a * s / (f * b)
    return float(out) if out.ndim == 0 else out
