"""Find the planar target in a depth image the way Ahn et al. (2019) did: bilateral filtering, Canny
edges, and shape detection of the board's quadrilateral.

This is the **one module of** ``noise_model`` **that imports OpenCV**. The rest of the package is the
noise model's maths and must stay importable and testable with NumPy, SciPy and numba alone; the
paper's target detection, however, *is* image processing (an edge-preserving bilateral filter, the
Canny detector, contour following and polygon approximation), for which OpenCV is the reference
implementation and re-implementing it would only add bugs. Keeping every ``cv2`` call here confines
the dependency (and OpenCV's API changes) to one file; :mod:`noise_model.analysis.characterization` takes the
pixels this module selects and does the statistics without OpenCV.

Method (:func:`detect_target`), on one depth image (in practice the per-pixel median of a capture's
frames, which keeps the edges sharp where a mean would smear them over the edges' lateral motion):

1. Bilateral filter (``cv2.bilateralFilter``) of the depth in metres, its range kernel set from the
   image's own noise, so the board's surface is smoothed and its edges are not.
2. Canny edges (``cv2.Canny`` on 16-bit Sobel derivatives of log-depth, so a threshold is a relative
   depth jump: 5 %, or more where the filtered image is noisier) plus every invalid pixel.
3. The target is the region grown from the principal point (the spec puts the target's centre on the
   optical axis) that no Canny edge and no larger jump between neighbours than the threshold
   interrupts (``cv2.floodFill``).
4. For a board: its outer contour (``cv2.findContours``), its convex hull, approximated by a
   quadrilateral (``cv2.approxPolyDP``); its left and right sides, refined to the region's boundary row by row
   and with the corners removed, are the vertical edges of the lateral-noise analysis; the
   quadrilateral shrunk about its centroid is the central region, "well inside the board". For a
   wall: the grown region within a central box of the image.

Failures are not exceptions: :class:`Detection` carries ``ok = False`` and a ``reason``, so a capture
set characterisation can report the capture and carry on with the others.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = ["Detection", "EdgeBand", "detect_target", "region_from_box", "REGION_SCALE", "CORNER_TRIM",
           "JUMP_REL"]

#: The central region is the board's quadrilateral (or, for a wall, the image) shrunk about its centre
#: to this fraction of its size: far enough from the edges for a lateral motion of a few sigma_L.
REGION_SCALE = 0.4
#: Fraction of each vertical edge's length removed at both ends (the corners).
CORNER_TRIM = 0.15
#: Smallest relative depth jump taken for an edge (5 % of the depth).
JUMP_REL = 0.05
#: Rows this close to the image's top or bottom are not used on an edge [px].
BORDER_PX = 2


@dataclass
class EdgeBand:
    """A vertical edge of the board in the image: u = slope v + intercept over ``rows``.

    Attributes
    ----------
    side : {"left", "right"}
        The board lies to the right of a left edge and to the left of a right edge.
    slope : float
        du/dv [px/px].
    intercept : float
        u at v = 0 [px].
    rows : ndarray of int, shape (R,)
        Image rows of the edge with the corners (and the image border) removed.
    half_width_px : float
        Distance along the image row from this edge to the middle of the board at the edge's middle
        row [px] (bounds the search window on the board's side).
    """

    side: str
    slope: float
    intercept: float
    rows: np.ndarray
    half_width_px: float

    def column_at(self, rows) -> np.ndarray:
        """The edge's column u [px] at image rows ``rows``."""
        return self.slope * np.asarray(rows, dtype=np.float64) + self.intercept


@dataclass
class Detection:
    """The target found in a depth image.

    Attributes
    ----------
    ok : bool
        False when the target was not found; ``reason`` says why.
    reason : str or None
    target_mask : ndarray of bool, shape (H, W)
        Pixels of the board (or of the wall's part connected to the image centre).
    region_mask : ndarray of bool, shape (H, W)
        The central region used for axial noise and the plane fit.
    corners : ndarray, shape (4, 2) or None
        The board's quadrilateral (u, v) [px]: top-left, top-right, bottom-right, bottom-left; None for
        a wall or a given region.
    edges : dict
        ``"left"`` and ``"right"``: an :class:`EdgeBand`, or None when that edge cannot be measured
        (``edge_reasons`` says why).
    edge_reasons : dict
        ``"left"`` / ``"right"``: a reason string where the edge is None.
    jump_rel : float
        The relative depth jump taken for an edge.
    """

    ok: bool
    reason: str | None
    target_mask: np.ndarray
    region_mask: np.ndarray
    corners: np.ndarray | None = None
    edges: dict = field(default_factory=lambda: {"left": None, "right": None})
    edge_reasons: dict = field(default_factory=dict)
    jump_rel: float = JUMP_REL


def _fail(shape, reason: str) -> Detection:
    empty = np.zeros(shape, dtype=bool)
    return Detection(False, reason, empty, empty.copy(), None, {"left": None, "right": None},
                     {"left": reason, "right": reason})


def region_from_box(shape, rows, cols) -> np.ndarray:
    """A rectangular region mask (H, W): rows ``rows[0] <= v < rows[1]``, columns ``cols[0] <= u < cols[1]``
    (half-open, as Python slices)."""
    H, W = (int(s) for s in shape)
    try:
        r0, r1 = (int(x) for x in rows)
        c0, c1 = (int(x) for x in cols)
    except (TypeError, ValueError):
        raise ValueError(f"a region needs rows [r0, r1] and cols [c0, c1] as integers, got {rows!r}, {cols!r}") from None
    if not (0 <= r0 < r1 <= H and 0 <= c0 < c1 <= W):
        raise ValueError(f"region rows [{r0}, {r1}) and cols [{c0}, {c1}) do not lie inside the {W}x{H} image")
    m = np.zeros((H, W), dtype=bool)
    m[r0:r1, c0:c1] = True
    return m


def _noise_rel(logz: np.ndarray, valid: np.ndarray) -> float:
    """Robust per-pixel noise of log-depth from horizontal second differences (a plane's gradient
    cancels): 1.4826 MAD / sqrt(6)."""
    ok = valid[:, 2:] & valid[:, 1:-1] & valid[:, :-2]
    if ok.sum() < 20:
        return 0.0
    d2 = (logz[:, 2:] - 2.0 * logz[:, 1:-1] + logz[:, :-2])[ok]
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


def _centre_window(shape, cx: float, cy: float) -> tuple[slice, slice]:
    """A small window around the principal point (half-size 3 % of the width, at least 7 px)."""
    H, W = shape
    r = max(7, int(round(0.03 * W)))
    u0, v0 = int(round(min(max(cx, 0), W - 1))), int(round(min(max(cy, 0), H - 1)))
    return slice(max(0, v0 - r), min(H, v0 + r + 1)), slice(max(0, u0 - r), min(W, u0 + r + 1))


def _seed(valid_free: np.ndarray, cx: float, cy: float, radius: int = 40):
    """The free pixel nearest to the principal point, within ``radius`` px, or None."""
    H, W = valid_free.shape
    u0, v0 = int(round(min(max(cx, 0), W - 1))), int(round(min(max(cy, 0), H - 1)))
    if valid_free[v0, u0]:
        return u0, v0
    v_lo, v_hi = max(0, v0 - radius), min(H, v0 + radius + 1)
    u_lo, u_hi = max(0, u0 - radius), min(W, u0 + radius + 1)
    vv, uu = np.nonzero(valid_free[v_lo:v_hi, u_lo:u_hi])
    if vv.size == 0:
        return None
    k = int(np.argmin((vv + v_lo - v0) ** 2 + (uu + u_lo - u0) ** 2))
    return int(uu[k] + u_lo), int(vv[k] + v_lo)


def _order_corners(q: np.ndarray) -> np.ndarray:
    """Corners (4, 2) as top-left, top-right, bottom-right, bottom-left: the two leftmost corners form
    the left side (a board's sides are near-vertical in the image, however narrow it looks)."""
    q = q[np.argsort(q[:, 0], kind="stable")]
    left, right = q[:2], q[2:]
    left = left[np.argsort(left[:, 1])]
    right = right[np.argsort(right[:, 1])]
    return np.array([left[0], right[0], right[1], left[1]])


def _drop_straight_vertices(poly: np.ndarray, min_turn_deg: float = 12.0) -> np.ndarray:
    """Remove polygon vertices where the outline turns by less than ``min_turn_deg`` (Douglas-Peucker
    always keeps the contour's first point, which may lie in the middle of a side)."""
    p = np.asarray(poly, dtype=np.float64)
    changed = True
    while changed and len(p) > 3:
        changed = False
        for i in range(len(p)):
            a, b = p[i] - p[i - 1], p[(i + 1) % len(p)] - p[i]
            na, nb = np.linalg.norm(a), np.linalg.norm(b)
            if na == 0 or nb == 0:
                p = np.delete(p, i, axis=0)
                changed = True
                break
            turn = math.degrees(math.acos(max(-1.0, min(1.0, float(a @ b) / (na * nb)))))
            if turn < min_turn_deg:
                p = np.delete(p, i, axis=0)
                changed = True
                break
    return p


def _quadrilateral(mask: np.ndarray):
    cs, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not cs:
        return None, "no outline around the target region"
    c = cv2.convexHull(max(cs, key=cv2.contourArea))    # the board is convex: ragged noise is not its shape
    n_seen = []
    for eps in (0.01, 0.02, 0.03, 0.05, 0.08):
        poly = _drop_straight_vertices(cv2.approxPolyDP(c, eps * cv2.arcLength(c, True), True).reshape(-1, 2))
        n_seen.append(len(poly))
        if len(poly) == 4 and cv2.isContourConvex(poly.reshape(-1, 1, 2).astype(np.int32)):
            return _order_corners(poly.astype(np.float64)), None
    return None, (f"the target's outline is not a convex quadrilateral (polygons of {sorted(set(n_seen))} "
                  "vertices): is the board fully separated from its surroundings in depth?")


def _edge_band(mask: np.ndarray, corners: np.ndarray, side: str, trim: float) -> tuple[EdgeBand | None, str | None]:
    H, W = mask.shape
    tl, tr, br, bl = corners
    top, bottom = (tl, bl) if side == "left" else (tr, br)
    du, dv = bottom[0] - top[0], bottom[1] - top[1]
    if abs(du) >= abs(dv):
        return None, f"the board's {side} side is not vertical in the image (du {du:.0f} px, dv {dv:.0f} px)"
    v_a, v_b = top[1], bottom[1]
    length = v_b - v_a
    r0 = int(math.ceil(max(v_a + trim * length, BORDER_PX)))
    r1 = int(math.floor(min(v_b - trim * length, H - 1 - BORDER_PX)))
    if r1 - r0 + 1 < 5:
        return None, f"the board's {side} edge spans only {max(r1 - r0 + 1, 0)} rows once its corners are removed"
    rows = np.arange(r0, r1 + 1)
    # the region's boundary on each row: the first (left) or last (right) target pixel
    sub = mask[rows]
    has = sub.any(axis=1)
    if has.sum() < 5:
        return None, f"the board's {side} edge has no target pixels on its rows"
    if side == "left":
        b = np.argmax(sub, axis=1).astype(np.float64) - 0.5
    else:
        b = W - 1 - np.argmax(sub[:, ::-1], axis=1).astype(np.float64) + 0.5
    rows, b = rows[has], b[has]
    at_border = (b < 1.0) if side == "left" else (b > W - 2.0)
    if at_border.mean() > 0.5:
        return None, f"the board's {side} edge is at the image border (the board is too wide for the view)"
    A = np.stack([rows.astype(np.float64), np.ones(rows.size)], axis=1)
    coef, *_ = np.linalg.lstsq(A, b, rcond=None)
    r = b - A @ coef
    keep = np.abs(r) <= max(3.0 * 1.4826 * np.median(np.abs(r)), 1.5)
    if keep.sum() >= 5:
        coef, *_ = np.linalg.lstsq(A[keep], b[keep], rcond=None)
    slope, intercept = float(coef[0]), float(coef[1])
    # half width: from this edge to the middle between the two sides, at the edge's middle row
    v_mid = 0.5 * (rows[0] + rows[-1])

    def side_u(p, q, v):
        return p[0] + (q[0] - p[0]) * (v - p[1]) / (q[1] - p[1]) if q[1] != p[1] else 0.5 * (p[0] + q[0])

    u_l, u_r = side_u(tl, bl, v_mid), side_u(tr, br, v_mid)
    half = 0.5 * abs(u_r - u_l)
    if half < 2.0:
        return None, f"the board is only {2 * half:.0f} px wide in the image"
    return EdgeBand(side, slope, intercept, rows.astype(np.int64), float(half)), None


def detect_target(depth_m, kind: str, principal_point, *, region_box=None, region_scale: float = REGION_SCALE,
                  corner_trim: float = CORNER_TRIM, jump_rel: float = JUMP_REL) -> Detection:
    """Find a planar target (a board or a wall) in a depth image.

    Parameters
    ----------
    depth_m : array_like, shape (H, W)
        Depth [m], float; NaN, 0 or negative = no data. Typically the per-pixel median of a capture.
    kind : {"board", "wall"}
        ``board``: a rectangle whose outline must be found; ``wall``: an unbounded plane.
    principal_point : (float, float)
        (cx, cy) [px]; the target's centre is on the optical axis (capture-set convention).
    region_box : ((r0, r1), (c0, c1)), optional
        A given central region (half-open rows and columns) instead of the detected one; a board's
        outline and edges are still looked for (their failure then only removes the edges).
    region_scale : float
        Size of the central region relative to the board (or, for a wall, the image).
    corner_trim : float
        Fraction of each vertical edge removed at both ends.
    jump_rel : float
        Smallest relative depth jump taken for an edge.

    Returns
    -------
    Detection
        ``ok = False`` with a ``reason`` when the target cannot be found (never raises for that); bad
        arguments (shape, kind, units) raise ``ValueError``.
    """
    d = np.asarray(depth_m)
    if d.ndim != 2 or min(d.shape) < 8:
        raise ValueError(f"depth_m must be a 2-D image of at least 8 x 8 pixels, got shape {d.shape}")
    if not np.issubdtype(d.dtype, np.floating):
        raise ValueError(f"depth_m must be floating-point metres, got dtype {d.dtype}")
    if kind not in ("board", "wall"):
        raise ValueError(f"kind must be 'board' or 'wall', got {kind!r}")
    if not (0.0 < float(region_scale) <= 1.0 and 0.0 <= float(corner_trim) < 0.5 and 0.0 < float(jump_rel) < 1.0):
        raise ValueError("region_scale must be in (0, 1], corner_trim in [0, 0.5), jump_rel in (0, 1)")
    H, W = d.shape
    z = d.astype(np.float32)
    valid = np.isfinite(z) & (z > 0)
    top = float(z[valid].max()) if valid.any() else 0.0
    if top > 100.0:
        raise ValueError(f"depth_m holds values up to {top:.1f}: depth must be in metres")
    given = None
    if region_box is not None:
        given = region_from_box((H, W), *region_box) & valid
        if given.sum() < 10:
            return _fail((H, W), "the given region holds fewer than 10 valid pixels")
    if valid.mean() < 0.02:
        return _fail((H, W), f"only {100 * valid.mean():.1f}% of the pixels have depth")
    cx, cy = float(principal_point[0]), float(principal_point[1])

    # 1. bilateral filter, range kernel from the noise of the target's surface (around the centre)
    logz = np.where(valid, np.log(np.where(valid, z, 1.0)), 0.0).astype(np.float32)
    win = _centre_window((H, W), cx, cy)
    noise = _noise_rel(logz[win], valid[win])
    filled = np.where(valid, z, 0.0).astype(np.float32)
    zc = z[win][valid[win]]
    z_centre = float(np.median(zc)) if zc.size else float(np.median(z[valid]))
    sigma_color = max(3.0 * noise * z_centre, 0.005)
    filt = cv2.bilateralFilter(filled, 5, sigma_color, 3.0)
    filt = np.where(valid, filt, 0.0).astype(np.float32)

    # 2. Canny on 16-bit Sobel derivatives of log-depth: thresholds are relative jumps, at least 6 times
    #    the filtered surface's noise
    big = math.log(1e3)             # invalid pixels: a jump far beyond any threshold
    g = np.where(valid, np.log(np.where(valid, filt, 1.0)), big).astype(np.float32)
    jump = max(float(jump_rel), 6.0 * _noise_rel(g[win], valid[win]))
    scale = 1000.0 / (4.0 * math.log1p(jump))      # a jump of `jump` -> Sobel response 1000
    dx = np.clip(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) * scale, -32000, 32000).astype(np.int16)
    dy = np.clip(cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) * scale, -32000, 32000).astype(np.int16)
    edges = cv2.Canny(dx, dy, 500.0, 1000.0, L2gradient=True) > 0

    # 3. grow the target from the principal point, stopped by edges, invalid pixels and jumps
    barrier = edges | ~valid
    free = ~barrier
    seed = _seed(free, cx, cy)
    if seed is None:
        return _fail((H, W), "no valid depth near the image centre (where the target's centre should be)")
    ff_mask = np.zeros((H + 2, W + 2), dtype=np.uint8)
    ff_mask[1:-1, 1:-1] = barrier.astype(np.uint8)
    step = float(math.log1p(jump))
    cv2.floodFill(g.copy(), ff_mask, seed, 0.0, step, step, 4 | cv2.FLOODFILL_MASK_ONLY | (2 << 8))
    comp = ff_mask[1:-1, 1:-1] == 2
    # the edge pixels themselves belong to whichever side they are nearer in depth: close the region
    comp = cv2.morphologyEx(comp.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)).astype(bool) & valid
    if comp.sum() < 50:
        return _fail((H, W), f"the surface at the image centre is only {int(comp.sum())} px large: no target there")

    if kind == "wall":
        if given is not None:
            region = given
        else:
            hw, hh = 0.5 * region_scale * W, 0.5 * region_scale * H
            box = region_from_box((H, W), (max(0, int(cy - hh)), min(H, int(cy + hh) + 1)),
                                  (max(0, int(cx - hw)), min(W, int(cx + hw) + 1)))
            region = box & comp
        if region.sum() < 10:
            return _fail((H, W), "the wall's central region holds fewer than 10 valid pixels")
        return Detection(True, None, comp, region, None, {"left": None, "right": None},
                         {"left": "a wall has no edges", "right": "a wall has no edges"}, jump)

    # 4. the board's quadrilateral, its vertical edges and its central region
    touches = [comp[:, 0].mean(), comp[:, -1].mean()]
    if min(touches) > 0.5:
        reason = ("the surface at the image centre reaches both the left and the right image border: no board "
                  "outline (a wall? the board too near?)")
        return _fail_or_given((H, W), reason, given, comp)
    corners, why = _quadrilateral(comp)
    if corners is None:
        return _fail_or_given((H, W), why, given, comp)
    edges_out, reasons = {}, {}
    for side in ("left", "right"):
        band, why_e = _edge_band(comp, corners, side, corner_trim)
        edges_out[side] = band
        if band is None:
            reasons[side] = why_e
    if given is not None:
        region = given
    else:
        c = corners.mean(axis=0)
        inner = c + region_scale * (corners - c)
        poly = np.zeros((H, W), dtype=np.uint8)
        cv2.fillConvexPoly(poly, np.round(inner).astype(np.int32), 1)
        region = poly.astype(bool) & comp
    if region.sum() < 10:
        return _fail((H, W), f"the board's central region holds only {int(region.sum())} valid pixels")
    return Detection(True, None, comp, region, corners, edges_out, reasons, jump)


def _fail_or_given(shape, reason: str, given, comp) -> Detection:
    """No board outline: a failure, unless a region was given (then the edges alone are missing)."""
    if given is None:
        return _fail(shape, reason)
    return Detection(True, None, comp, given, None, {"left": None, "right": None},
                     {"left": reason, "right": reason})
