"""What the gap statistics are taken over: a capture's geometry (:class:`GapCapture`) and its strata.

A capture is a static planar target seen by a static camera for F frames: its noise-free depth
``z_true`` (H, W) [m], incidence angle ``theta`` [rad], region labels (those of
:mod:`noise_model.analysis.capture_data`: interior, left/right board edges, left invalid band,
background), the paper's sigma_z(z_true, theta) [m] and f b [px m] (focal length times baseline).

Each capture falls into one *distance bin* and one *angle bin* (its target's distance_m and incidence
angle, :class:`Binning`); inside it, pixels fall into one cell of a 3 x 3 grid over the image
(``image_cell`` [row, col], row 0 at the top) and into at most one *region* (``left_band``,
``interior``, ``edge_left``, ``edge_right``). A stratum is (distance bin, angle bin, image cell) or
(distance bin, angle bin, region); captures sharing the bins are pooled. The 9 cells and 4 regions of
one capture are its *local strata* (:data:`LOCAL_STRATA`); a *global key* is (distance bin, angle bin,
local stratum index).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...checks import check_intrinsics, check_positive_scalar
from ...d435 import D435, SensorModel, axial_sigma_unchecked
from ..capture_data import (
    REGION_EDGE_LEFT, REGION_EDGE_RIGHT, REGION_INTERIOR, REGION_LEFT_BAND, REGION_NONE,
)

__all__ = ["REGIONS", "REGION_ORDER", "LOCAL_STRATA", "N_LOCAL", "REGION_LOCAL", "MAX_RANGE_M", "GapCapture",
           "make_gap_capture", "Binning"]

#: Report names of the regions of ``noise_model.analysis.capture_data.CaptureGeometry.regions`` that
#: form strata (no data, background: none).
REGIONS = {REGION_LEFT_BAND: "left_band", REGION_INTERIOR: "interior", REGION_EDGE_LEFT: "edge_left",
           REGION_EDGE_RIGHT: "edge_right"}
#: The regions in the order of the local strata.
REGION_ORDER = (REGION_INTERIOR, REGION_EDGE_LEFT, REGION_EDGE_RIGHT, REGION_LEFT_BAND)
#: Local strata of a capture: the 9 image cells (row-major), then the 4 regions.
LOCAL_STRATA = tuple(("image_cell", (r, c)) for r in range(3) for c in range(3)) + tuple(
    ("region", REGIONS[g]) for g in REGION_ORDER)
#: Number of local strata (13).
N_LOCAL = len(LOCAL_STRATA)
#: Region code -> index of its local stratum.
REGION_LOCAL = {g: 9 + i for i, g in enumerate(REGION_ORDER)}
#: Surfaces farther than this [m] are left out of the statistics (beyond the D435's range).
MAX_RANGE_M = 10.0


@dataclass(frozen=True, eq=False)
class GapCapture:
    """What the gap statistics need to know about one capture (static camera and target).

    Attributes
    ----------
    id : str
    z_true_m : ndarray, shape (H, W), float64
        Noise-free z-depth [m] of the surface each pixel sees; NaN where there is none (or outside
        the region of interest).
    sigma_m : ndarray, shape (H, W), float64
        The paper's sigma_z(z_true, theta) [m]; NaN where ``z_true_m`` is.
    regions : ndarray, shape (H, W), int8
        Region codes (``REGION_*``; those of ``noise_model.analysis.capture_data``).
    fb_px_m : float
        f b: focal length [px] times baseline [m] (disparity = f b / z [px]).
    distance_m : float
        The target's distance [m] (for the distance bin).
    angle_deg : float
        The target's incidence angle [deg] (for the angle bin).
    kind : str
        ``wall``, ``board`` or ``plane`` (a plane fitted to a region of a real frame).
    """

    id: str
    z_true_m: np.ndarray
    sigma_m: np.ndarray
    regions: np.ndarray
    fb_px_m: float
    distance_m: float
    angle_deg: float
    kind: str = "wall"

    @property
    def shape(self) -> tuple[int, int]:
        return self.z_true_m.shape


def make_gap_capture(capture_id: str, z_true_m, theta_rad, regions, K, baseline_m: float, distance_m: float,
                     angle_deg: float, kind: str = "wall", model: SensorModel = D435, roi=None) -> GapCapture:
    """Build a :class:`GapCapture` from a rendered geometry.

    Parameters
    ----------
    capture_id : str
    z_true_m, theta_rad : array_like, shape (H, W)
        Noise-free z-depth [m] and incidence angle [rad]; NaN where nothing is hit.
    regions : array_like, shape (H, W), integer
        Region codes (0 none, 1 interior, 2 left edge, 3 right edge, 4 left band, 5 background).
    K : array_like, shape (3, 3)
        Intrinsics [px].
    baseline_m : float
        Stereo baseline [m].
    distance_m, angle_deg : float
        Distance [m] and incidence angle [deg] of the target (strata bins).
    kind : str
    model : SensorModel
        The model whose sigma_z normalises residuals.
    roi : array_like of bool, shape (H, W), optional
        Only these pixels count (e.g. the region a plane was fitted to); None = all.

    Raises
    ------
    ValueError
        Shapes that differ, non-float depth, depth that is not metres, bad intrinsics.
    """
    z = np.asarray(z_true_m)
    th = np.asarray(theta_rad)
    if z.ndim != 2 or not np.issubdtype(z.dtype, np.floating):
        raise ValueError(f"z_true_m must be a 2-D float image [m], got {z.dtype} {z.shape}")
    if th.shape != z.shape:
        raise ValueError(f"theta_rad must have z_true_m's shape {z.shape}, got {th.shape}")
    reg = np.asarray(regions)
    if reg.shape != z.shape or not np.issubdtype(reg.dtype, np.integer):
        raise ValueError(f"regions must be an integer image of shape {z.shape}, got {reg.dtype} {reg.shape}")
    if z.shape[0] < 3 or z.shape[1] < 3:
        raise ValueError(f"image too small for a 3 x 3 grid of cells: {z.shape}")
    zf = z.astype(np.float64)
    finite = np.isfinite(zf)
    if finite.any() and (zf[finite].min() <= 0 or float(np.median(zf[finite])) > 100.0):
        raise ValueError("z_true_m must be in metres and > 0 where finite")
    with np.errstate(invalid="ignore"):
        finite &= zf <= MAX_RANGE_M                    # grazing rays far beyond the camera's range
    Kc = check_intrinsics(K)
    b = check_positive_scalar(baseline_m, "baseline_m", upper=2.0, unit=" m")
    geom = finite & np.isfinite(th)
    if roi is not None:
        r = np.asarray(roi)
        if r.shape != z.shape or r.dtype != bool:
            raise ValueError(f"roi must be a boolean image of shape {z.shape}, got {r.dtype} {r.shape}")
        geom &= r
    zt = np.where(geom, zf, np.nan)
    sig = np.full(z.shape, np.nan)
    if model.family == "disparity" and model.frame_fx_px is None:
        model = model.with_focal(float(Kc[0, 0]))            # its sigma_z in metres needs the frame's f
    sig[geom] = axial_sigma_unchecked(zt[geom], th.astype(np.float64)[geom], model)
    reg8 = np.where(geom, reg, REGION_NONE).astype(np.int8)
    return GapCapture(str(capture_id), zt, sig, reg8, float(Kc[0, 0]) * b, float(distance_m), float(angle_deg),
                      str(kind))


@dataclass(frozen=True)
class Binning:
    """Distance and angle bins of the strata: [i w, (i + 1) w) for bin i.

    Attributes
    ----------
    distance_width_m : float
        Width of a distance bin [m] (default 0.2).
    angle_width_deg : float
        Width of an incidence-angle bin [deg] (default 15).
    """

    distance_width_m: float = 0.2
    angle_width_deg: float = 15.0

    def bins(self, cap: GapCapture) -> tuple[int, int]:
        """(distance bin, angle bin) of a capture: floor(distance / width), floor(angle / width), the
        quotient rounded to 9 decimals first so that 0.6 m / 0.2 m lands in bin 3, not 2."""
        d = int(math.floor(round(cap.distance_m / self.distance_width_m, 9)))
        a = int(math.floor(round(cap.angle_deg / self.angle_width_deg, 9)))
        return d, a

    def stratum(self, key: tuple[int, int, int]) -> dict:
        """The report's stratum of a global key (distance bin, angle bin, local stratum)."""
        d, a, k = key
        w, aw = self.distance_width_m, self.angle_width_deg
        kind, val = LOCAL_STRATA[k]
        out = {"distance_m": [round(d * w, 6), round((d + 1) * w, 6)],
               "angle_deg": [round(a * aw, 6), round((a + 1) * aw, 6)]}
        out[kind] = list(val) if kind == "image_cell" else val
        return out

