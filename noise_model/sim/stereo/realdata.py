"""The physical D435 against real D435 recordings: the same geometry simulated, the same figures compared.

Each function reads one folder of real recordings (the folders of ``PATH/TO/realdata``: a
``figures.json`` of figures measured on the recording, a ``PROVENANCE.md`` stating its camera,
intrinsics and scene; docs/physical-d435.md lists them), rebuilds the recorded geometry as a
:class:`.planar.PlanarScene`, simulates it with :class:`.pipeline.StereoD435` and measures the
simulation the way the real figure was measured.

* :func:`real_pair` -- the matcher on a real infrared pair against the D435's own depth picture:
  valid fraction, left invalid band, occlusion shadow beside the box.
* :func:`dot_statistics` -- dots per 100 x 100 px patch and their contrast in an infrared image;
  :func:`simulated_dots` -- the same on a simulated carpet floor at the real pair's geometry.
* :func:`aims_stretch` -- the static stretch of the aims_slam recording (a wall and a concrete floor,
  640 x 480): per-pixel temporal sigma per depth bin of wall and floor, whole-plane frame-to-frame
  jitter, plane-fit residuals of one frame and of the stretch's mean.
* :func:`aims_real_offsets` -- the real stretch's per-frame plane offsets in disparity: how much of its
  whole-plane jitter a frame-wide disparity offset could explain.
* :func:`single_plane` -- one frame of a real plane (the opf board, the lrs wall) at its recorded
  geometry: the RANSAC plane-fit residual against the real one.

Frames: camera x right, y down, z forward; a real plane is n . p = offset in the camera frame
(``figures.json`` convention); depth is z in metres.
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.ndimage import label, median_filter

from .materials import MaterialMap, Uniform, concrete, white_wall
from .pipeline import IRScene, StereoD435
from .planar import PlanarScene, PlaneSurface, plane_from_camera, render_planar

__all__ = ["real_pair", "dot_statistics", "simulated_dots", "DOT_PATCHES", "FLOOR_PATCHES", "aims_scene",
           "aims_stretch", "aims_real_offsets", "SINGLE_PLANES", "single_plane",
           "ambient_for_exposure", "read_png"]


def read_png(path) -> np.ndarray:
    """A PNG as an array (8- or 16-bit grey, or RGB), read with Pillow."""
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im)


def _black(picture) -> np.ndarray:
    """Invalid pixels of a colour-mapped depth picture (black)."""
    return np.asarray(picture).astype(int)[..., :3].sum(axis=2) < 40


def _shadow_run(invalid_row, x_max, min_len=2):
    """(start, length) of the first invalid run of >= ``min_len`` px after the row's first valid pixel.

    Scanning a row from the left: the left band (invalid), the floor (valid), then the occlusion
    shadow left of an object (invalid). Returns (nan, 0) when there is no such run before ``x_max``.
    """
    row = np.asarray(invalid_row[:x_max], dtype=bool)
    first_valid = int(np.argmax(~row)) if (~row).any() else len(row)
    x = first_valid
    while x < len(row):
        if row[x]:
            end = x
            while end < len(row) and row[end]:
                end += 1
            if end - x >= min_len:
                return float(x), end - x
            x = end
        else:
            x += 1
    return float("nan"), 0


def real_pair(folder, preset: str = "default", shadow_rows=(75, 150), shadow_x_max=140) -> dict:
    """The matcher on ``left1.png`` / ``right1.png`` against ``result_from_D435.png`` (simsense_d435_ir_pairs).

    The picture is 424 x 240; our 848 x 480 validity is compared on every second row and column.
    Left band: per row the first valid column (rows 0-200, every 20th). Shadow: per row of
    ``shadow_rows`` the first invalid run after the floor (:func:`_shadow_run`, left of the box in
    that recording), its start column and width, medians over rows.
    """
    from .matcher import match

    folder = Path(folder)
    left = read_png(folder / "left1.png")
    right = read_png(folder / "right1.png")
    t0 = time.perf_counter()
    res = match(left, right, preset)
    seconds = time.perf_counter() - t0
    ours = ~np.isfinite(res.disparity)[::2, ::2]
    theirs = _black(read_png(folder / "result_from_D435.png"))
    band_rows = list(range(0, 201, 20))
    band_ours = [int(np.argmax(~ours[r])) for r in band_rows]
    band_theirs = [int(np.argmax(~theirs[r])) for r in band_rows]
    r0, r1 = shadow_rows
    sh_ours = np.array([_shadow_run(ours[r], shadow_x_max) for r in range(r0, r1)])
    sh_theirs = np.array([_shadow_run(theirs[r], shadow_x_max) for r in range(r0, r1)])
    diff = np.abs(np.subtract(band_ours, band_theirs))
    return {
        "preset": preset,
        "valid_fraction_ours": float(1 - ours.mean()),
        "valid_fraction_d435": float(1 - theirs.mean()),
        "band_rows": band_rows,
        "band_ours_px424": band_ours,
        "band_d435_px424": band_theirs,
        "band_max_diff_px424": int(diff.max()),
        "band_median_diff_px424": float(np.median(diff)),
        "shadow_start_ours_px424": float(np.nanmedian(sh_ours[:, 0])),
        "shadow_start_d435_px424": float(np.nanmedian(sh_theirs[:, 0])),
        "shadow_width_ours_px424": float(np.median(sh_ours[:, 1])),
        "shadow_width_d435_px424": float(np.median(sh_theirs[:, 1])),
        "reasons": {name: float((res.reason == k).mean()) for k, name in enumerate(
            ("valid", "no_minimum", "second_peak", "low_texture", "left_right", "small_segment"))},
        "match_seconds": seconds,
    }


def dot_statistics(image, region, threshold_rel: float = 0.25, threshold_dn: float = 6.0) -> dict:
    """Dots in a patch of an infrared image: count per 100 x 100 px and median contrast.

    A dot is a connected set of pixels brighter than the local median (9 x 9) by more than
    ``threshold_rel`` of it plus ``threshold_dn``, of 2 to 25 pixels; its contrast is
    (peak - background) / background at its brightest pixel.
    """
    a = np.asarray(image, dtype=np.float64)
    bg = median_filter(a, size=9)
    A, B = a[region], bg[region]
    lab, n = label((A - B) > threshold_rel * B + threshold_dn)
    sizes = np.bincount(lab.ravel())
    contrasts = []
    for k in range(1, n + 1):
        if not 2 <= sizes[k] <= 25:
            continue
        ys, xs = np.nonzero(lab == k)
        i = np.argmax(A[ys, xs])
        contrasts.append((A[ys[i], xs[i]] - B[ys[i], xs[i]]) / max(B[ys[i], xs[i]], 1.0))
    area = A.shape[0] * A.shape[1]
    return {"dots_per_100x100": len(contrasts) * 1e4 / area,
            "contrast_median": float(np.median(contrasts)) if contrasts else float("nan"),
            "background_dn": float(np.median(B))}


#: Patches of the real pair's left image (rows, columns at 848 x 480) whose dots are counted: the carpet
#: near the camera, the carpet on the left, the box's front, the book.
DOT_PATCHES = {"carpet_near": np.s_[380:480, 600:700], "carpet_left": np.s_[370:470, 100:200],
               "box_front": np.s_[270:330, 200:380], "book": np.s_[200:300, 480:580]}
#: The carpet patches, which the simulated floor reproduces.
FLOOR_PATCHES = ("carpet_near", "carpet_left")
#: The real pair's camera (its PROVENANCE: 848 x 480, f 427.12, c (426.93, 234.78)) and the carpet's plane
#: fitted to our matcher's disparity of the pair, n . p = offset in the camera frame (0.447 m below the
#: camera, pitched 53 deg down).
PAIR_INTRINSICS = (427.12, 426.93, 234.78)
PAIR_FLOOR_PLANE = ((0.038, -0.597, -0.801), -0.447)


def simulated_dots(ambient_w_m2: float = 5.0, seed: int = 0) -> dict:
    """Dots of a simulated carpet floor at the real pair's geometry, counted as in the real left image.

    The floor is :data:`PAIR_FLOOR_PLANE` with ``materials.carpet()``; one left infrared frame at the
    pair's intrinsics (848 x 480), the dots of :data:`FLOOR_PATCHES` by :func:`dot_statistics`. The
    ambient irradiance sets the dots' contrast (a scene parameter: the real pair's scene light is not
    known).
    """
    from .materials import carpet

    f, cx, cy = PAIR_INTRINSICS
    K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    n, off = PAIR_FLOOR_PLANE
    cam = StereoD435(848, 480, K=K, materials=MaterialMap(default=carpet(), ground=None), ambient_w_m2=ambient_w_m2,
                     renderer=render_planar)
    ir = cam.render(PlanarScene((plane_from_camera(n, off, name="carpet"),)), np.eye(4))
    left, _, exposure = cam.ir_pair(ir, np.random.default_rng([seed, 0xD07]))
    out = {name: dot_statistics(left, DOT_PATCHES[name]) for name in FLOOR_PATCHES}
    out["ambient_w_m2"] = ambient_w_m2
    out["exposure_ms"] = exposure.time_s * 1e3
    return out


# ---------------------------------------------------------------------------------------------
# aims_slam: a wall and a concrete floor seen by a static robot
# ---------------------------------------------------------------------------------------------


def _intrinsics(intr: dict) -> np.ndarray:
    return np.array([[intr["fx"], 0.0, intr["ppx"]], [0.0, intr["fy"], intr["ppy"]], [0.0, 0.0, 1.0]])


def _unit(v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    return a / np.linalg.norm(a)


def aims_scene(fig: dict, segment: str = "S1", wall_edge_px=(385.0, 165.0)):
    """The aims_slam stretch as a scene: (scene, T_map_cam, K), the floor at map z = 0.

    The floor is the plane of ``figures.json``'s ``{segment}_floor`` (normal and distance in the camera
    frame); the map frame has z along the floor's normal, x along the optical axis projected on the
    floor, the camera ``dist_m`` above it (its pitch and roll are the recording's). The wall is the
    plane of ``{segment}_wall``, a panel whose right edge is vertical (along the floor's normal) through
    the wall point seen at pixel ``wall_edge_px`` (u, v) [px] (where the recording's depth leaves the
    panel for the room behind it); it reaches far to the left and up, and down to the floor. 640 x 480
    with the recording's estimated intrinsics.
    """
    K = _intrinsics(fig["intrinsics_estimate_640x480"])
    fl, wl = fig[f"{segment}_floor"]["plane"], fig[f"{segment}_wall"]["plane"]
    nf, nw = _unit(fl["normal"]), _unit(wl["normal"])
    x_map = np.array([0.0, 0.0, 1.0]) - nf[2] * nf
    x_map /= np.linalg.norm(x_map)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x_map, np.cross(nf, x_map), nf]).T      # rows: map axes in the camera frame
    T[2, 3] = fl["dist_m"]
    R = T[:3, :3]
    u, v = wall_edge_px
    ray = np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0])
    edge = ray * (-wl["dist_m"]) / (nw @ ray)            # figures.json planes: n . p = -dist_m, n towards the camera
    along = np.cross(nf, nw)
    along -= (along @ nw) * nw
    along = along / np.linalg.norm(along) * (1.0 if along[0] >= 0 else -1.0)      # towards the image right
    size = 20.0
    centre = edge - along * size / 2
    wall = PlaneSurface(tuple(R @ nw), tuple(R @ centre + T[:3, 3]), size, size, tuple(R @ along), name="aims wall")
    floor = PlaneSurface((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), name="aims floor")
    return PlanarScene((floor, wall)), T, K


def _temporal_std(D: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Per-pixel standard deviation over frames (ddof 1) of the frames' valid values where ``ok``; NaN elsewhere."""
    Dv = np.where(D > 0, D, np.nan)
    sd = np.full(D.shape[1:], np.nan)
    with np.errstate(invalid="ignore"):
        sd[ok] = np.nanstd(Dv[:, ok], axis=0, ddof=1)
    return sd


def aims_stretch(folder, n_frames: int = 16, ambient_w_m2: float = 0.05, floor_material=None, seed: int = 0,
                 segment: str = "S1") -> dict:
    """The aims_slam static stretch simulated at its geometry and measured as its ``figures.json``.

    Scene: :func:`aims_scene` (a white wall, albedo 0.8, and a concrete floor, ``materials.concrete()``
    unless ``floor_material`` says otherwise), ambient ``ambient_w_m2``, ``n_frames`` frames of a static
    camera. Per plane (wall, floor): the pixels of the segment's ``roi_xyxy`` that see that plane, valid
    in >= 90 % of the frames (the real figures' rule); per depth bin of ``plane_temporal_bins`` (binned
    by the true depth) the median of the per-pixel temporal standard deviation, and the subpixel sigma
    it implies, sigma_d = sigma_z f B / z^2 at the bin's median depth. Whole-plane jitter: the standard
    deviation over frames of the mean of (z - z_true) over the plane's pixels valid in every frame.
    Plane-fit residuals: :func:`noise_model.analysis.planes.fit_plane_ransac` (the real figures' fit:
    RANSAC, inliers within 2 % of the depth, SVD refit) of the first frame and of the per-pixel mean
    over the frames, on the plane's pixels.

    Returns
    -------
    dict
        ``exposure_ms``, ``gain``, and per plane (``wall``, ``floor``): ``bins`` (z_m, incidence_deg,
        real_mm, sim_mm, ratio, real_sigma_d_px, sim_sigma_d_px), ``valid_fraction``, ``jitter_sim_mm``,
        ``jitter_real_mm``, ``residual_single_sim_mm`` / ``_real_mm``, ``residual_mean_sim_mm`` / ``_real_mm``.
    """
    from ...analysis.planes import fit_plane_ransac

    folder = Path(folder)
    fig = json.loads((folder / "figures.json").read_text())
    scene, T, K = aims_scene(fig, segment)
    ground = concrete() if floor_material is None else floor_material
    cam = StereoD435(640, 480, K=K, materials=MaterialMap(default=white_wall(), ground=ground),
                     ambient_w_m2=ambient_w_m2, renderer=render_planar)
    ir = cam.render(scene, T, with_truth=True)
    _, _, index = render_planar(scene, K, 640, 480, T, return_index=True)
    rng = np.random.default_rng([seed, 0xA135])
    frames = [cam.frame(ir, rng) for _ in range(int(n_frames))]
    D = np.stack([f.depth for f in frames]).astype(np.float64) * cam.depth_unit_m
    Dv = np.where(D > 0, D, np.nan)
    zt = ir.z_true
    fB = cam.focal_px * cam.baseline_m
    out = {"segment": segment, "ambient_w_m2": ambient_w_m2, "n_frames": int(n_frames),
           "floor_material": repr(ground), "exposure_ms": frames[0].exposure.time_s * 1e3,
           "gain": frames[0].exposure.gain}
    for name, code in (("wall", 1), ("floor", 0)):
        seg = fig[f"{segment}_{name}"]
        x0, y0, x1, y1 = seg["roi_xyxy"]
        roi = np.zeros(zt.shape, bool)
        roi[y0:y1, x0:x1] = True
        roi &= index == code
        ok = roi & ((D > 0).mean(axis=0) >= 0.9)
        sd = _temporal_std(D, ok)
        bins = []
        for b in seg["plane_temporal_bins"]:
            lo, hi = b["z_m"]
            m = ok & (zt >= lo) & (zt < hi)
            sim = float(np.nanmedian(sd[m])) * 1e3 if m.any() else float("nan")
            zm = float(np.median(zt[m])) if m.any() else float("nan")
            bins.append({"z_m": [lo, hi], "incidence_deg": b["median_local_incidence_deg"], "pixels": int(m.sum()),
                         "real_mm": b["median_temporal_std_mm"], "sim_mm": sim,
                         "ratio": sim / b["median_temporal_std_mm"], "real_sigma_d_px": b["implied_subpixel_px"],
                         "sim_sigma_d_px": sim * 1e-3 * fB / zm ** 2})
        every = roi & (D > 0).all(axis=0)
        offsets = [float(np.mean(D[k][every] - zt[every])) for k in range(len(frames))]
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)            # pixels never valid: NaN
            mean = np.nanmean(Dv, axis=0) if len(frames) > 1 else Dv[0]
        single = fit_plane_ransac(Dv[0], K, roi)
        mean_fit = fit_plane_ransac(np.where(ok, mean, np.nan), K, roi)
        out[name] = {
            "bins": bins, "valid_fraction": float((D[:, roi] > 0).mean()),
            "jitter_sim_mm": float(np.std(offsets, ddof=1)) * 1e3 if len(frames) > 1 else float("nan"),
            "offsets_sim_mm": [o * 1e3 for o in offsets],
            "jitter_real_mm": seg["plane_offset_frame_to_frame_std_mm"],
            "residual_single_sim_mm": single.residual_std_m * 1e3,
            "residual_single_real_mm": seg["plane_residual_std_mm"]["single_frame"],
            "residual_mean_sim_mm": mean_fit.residual_std_m * 1e3,
            "residual_mean_real_mm": seg["plane_residual_std_mm"]["mean_image"],
        }
    return out


def aims_real_offsets(folder, segment: str = "S1", inlier_rel: float = 0.03) -> dict:
    """Per-frame offsets of the real stretch's wall and floor in disparity (what its whole-plane jitter is).

    Reads the stretch's depth frames (``depth/{k}.png``, 1 mm units, ``frames_used`` of the segment).
    Per plane: the pixels of its ROI valid in every frame, within the depth bins of its figures and
    within ``inlier_rel`` of the per-pixel median over the frames (off-plane pixels and objects left
    out); per frame the mean of d - d_median with d = f B / z (f B = fx 0.050 m). A frame-wide
    disparity offset (rectification, exposure or projector power acting on the whole image) would move
    wall and floor together: their correlation over frames says how much of the jitter is frame-wide.

    The first and the last frame of a stretch sit next to the robot's moves (auto exposure still
    settling): the "inner" figures leave them out. The frame-wide part is estimated as
    sqrt(max(0, cov(wall, floor))) over the inner frames.

    Returns
    -------
    dict
        ``frames``; per plane ``offsets_px`` (per frame), ``std_px``, ``std_inner_px``, and the same
        in depth, ``jitter_mm`` and ``jitter_inner_mm`` (standard deviation over frames of the mean of
        z - z_median); ``correlation`` and ``correlation_inner`` of the wall's and the floor's
        offsets; ``shared_inner_px``: the frame-wide disparity offset's standard deviation.
    """
    folder = Path(folder)
    fig = json.loads((folder / "figures.json").read_text())
    f0, f1 = fig[f"{segment}_wall"]["frames_used"]
    fB = fig["intrinsics_estimate_640x480"]["fx"] * 0.050
    D = np.stack([read_png(folder / "depth" / f"{k}.png").astype(np.float64) * 1e-3 for k in range(f0, f1 + 1)])
    D[(D <= 0) | (D > 60.0)] = np.nan
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)                # pixels never valid: NaN
        med = np.nanmedian(D, axis=0)
    out = {"frames": [f0, f1]}
    for name in ("wall", "floor"):
        seg = fig[f"{segment}_{name}"]
        x0, y0, x1, y1 = seg["roi_xyxy"]
        lo, hi = seg["plane_temporal_bins"][0]["z_m"][0], seg["plane_temporal_bins"][-1]["z_m"][1]
        m = np.zeros(med.shape, bool)
        m[y0:y1, x0:x1] = True
        with np.errstate(invalid="ignore"):
            m &= np.isfinite(D).all(axis=0) & (med >= lo) & (med < hi)
            m &= (np.abs(D - med).max(axis=0) <= inlier_rel * med)
        off = np.array([float(np.mean(fB / D[k][m] - fB / med[m])) for k in range(D.shape[0])])
        mm = np.array([float(np.mean(D[k][m] - med[m])) * 1e3 for k in range(D.shape[0])])
        out[name] = {"pixels": int(m.sum()), "offsets_px": off.tolist(), "std_px": float(np.std(off, ddof=1)),
                     "std_inner_px": float(np.std(off[1:-1], ddof=1)), "jitter_mm": float(np.std(mm, ddof=1)),
                     "jitter_inner_mm": float(np.std(mm[1:-1], ddof=1))}
    w, f = np.array(out["wall"]["offsets_px"]), np.array(out["floor"]["offsets_px"])
    out["correlation"] = float(np.corrcoef(w, f)[0, 1])
    out["correlation_inner"] = float(np.corrcoef(w[1:-1], f[1:-1])[0, 1])
    out["shared_inner_px"] = float(np.sqrt(max(0.0, float(np.cov(w[1:-1], f[1:-1])[0, 1]))))
    return out


# ---------------------------------------------------------------------------------------------
# single frames of real planes
# ---------------------------------------------------------------------------------------------

#: The real single-frame planes: folder, figures.json keys, image size, intrinsics (fx, ppx, ppy), the
#: recording's ROI (rows, columns) and the planes of its scene, as their PROVENANCE.md states them.
SINGLE_PLANES = {
    "opf_board": {"folder": "opf_d435i_viewer_raw", "figure": ("big_board_plane", "residual_std_mm"),
                  "size": (848, 480), "intrinsics": (425.849243, 425.867798, 239.954727),
                  "rows": (20, 190), "cols": (300, 430), "planes": ("big_board_plane",), "exposure_ms": None},
    "lrs_wall": {"folder": "lrs_unittest_bag_d435", "figure": ("yellow_wall_plane", "residual_std_mm"),
                 "size": (640, 480), "intrinsics": (390.43145751953125, 331.38787841796875, 242.18734741210938),
                 "rows": (10, 260), "cols": (20, 300), "planes": ("yellow_wall_plane", "whiteboard_wall_plane"),
                 "exposure_ms": 6.452},
}


def ambient_for_exposure(cam: StereoD435, ir_unit: IRScene, exposure_s: float) -> float:
    """The ambient irradiance [W/m^2] at which the auto exposure picks ``exposure_s`` (at gain 1).

    ``ir_unit`` is a render of the scene with ``ambient_w_m2 = 1`` (rates are linear in the ambient):
    the auto exposure brings the mean left rate to ae_target full_well / t, so
    A = (ae_target full_well / t - mean(projector)) / mean(ambient at 1 W/m^2), at least 0.
    """
    m = cam.imager
    need = m.ae_target * m.full_well_e / float(exposure_s)
    return max(0.0, (need - float(np.mean(ir_unit.projector_left))) / float(np.mean(ir_unit.ambient_left)))


def single_plane(realdata, name: str, n_frames: int = 5, ambient_w_m2: float | None = 0.05,
                 albedo: float = 0.8, seed: int = 0) -> dict:
    """One frame of a real plane at its geometry: the plane-fit residual against the real one.

    The recording's planes (``figures.json``: n . p = offset in the camera frame) are rendered as
    unbounded planes (the lrs corner: its yellow wall and the whiteboard wall at grazing incidence)
    with a uniform albedo, at the recording's size and intrinsics. Each of ``n_frames`` independent
    frames is fitted as the real one was (:func:`noise_model.analysis.planes.fit_plane_ransac` on the
    ROI of its PROVENANCE.md); the figure is the mean residual over those frames. ``ambient_w_m2`` None:
    the ambient that gives the recording's own exposure (:func:`ambient_for_exposure`; only where the
    recording states it, else 0.05 W/m^2).
    """
    from ...analysis.planes import fit_plane_ransac

    spec = SINGLE_PLANES[name]
    fig = json.loads((Path(realdata) / spec["folder"] / "figures.json").read_text())
    w, h = spec["size"]
    f, cx, cy = spec["intrinsics"]
    K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    scene = PlanarScene(tuple(plane_from_camera(fig[k]["plane_normal"], fig[k]["plane_offset_m"], name=k)
                              for k in spec["planes"]))
    mats = MaterialMap(default=Uniform(albedo, name), ground=None)
    ambient = ambient_w_m2
    if ambient is None:
        ambient = 0.05
        if spec["exposure_ms"] is not None:
            unit = StereoD435(w, h, K=K, materials=mats, ambient_w_m2=1.0, renderer=render_planar)
            ambient = ambient_for_exposure(unit, unit.render(scene, np.eye(4)), spec["exposure_ms"] * 1e-3)
    cam = StereoD435(w, h, K=K, materials=mats, ambient_w_m2=ambient, renderer=render_planar)
    ir = cam.render(scene, np.eye(4))
    roi = np.zeros((h, w), bool)
    roi[spec["rows"][0]:spec["rows"][1], spec["cols"][0]:spec["cols"][1]] = True
    rng = np.random.default_rng([seed, 0x5F])
    res, valid = [], []
    for _ in range(int(n_frames)):
        fr = cam.frame(ir, rng)
        D = np.where(fr.depth > 0, fr.depth * cam.depth_unit_m, np.nan)
        res.append(fit_plane_ransac(D, K, roi).residual_std_m * 1e3)
        valid.append(float(np.isfinite(D[roi]).mean()))
    key, stat = spec["figure"]
    real = float(fig[key][stat])
    sim = float(np.mean(res))
    return {"name": name, "ambient_w_m2": ambient, "exposure_ms": fr.exposure.time_s * 1e3,
            "exposure_real_ms": spec["exposure_ms"], "gain": fr.exposure.gain, "residual_sim_mm": sim,
            "residual_sim_frames_mm": res, "residual_real_mm": real, "ratio": sim / real,
            "valid_fraction_roi": float(np.mean(valid)), "median_depth_m": fig[key]["inlier_depth_median_m"]}
