"""Validation figures of the physical D435, each printed next to its target.

* :func:`wall_sweep` -- a fronto-parallel wall lit only by the projector at several distances: the
  temporal sigma of depth and the subpixel sigma it implies, sigma_d = sigma_z f B / z^2 (target
  0.05-0.12 px, Intel's typical 0.08), the single-frame plane scatter in disparity, the left invalid
  band against f B / z (+- 3 px), the nearest depth against f B / 126, the fill rate.
* :func:`real_pair` -- the matcher on a real D435 infrared pair against the D435's own depth picture:
  valid fraction (within 5 points), left band and the occlusion shadow beside an object (+- 3 px at
  the picture's 424 x 240).
* :func:`dot_statistics` -- dots per 100 x 100 px patch and their contrast in an infrared image.
* :func:`aims_floor` -- the concrete floor of the aims_slam recording at its geometry (640 x 480,
  fx 383.8): the per-pixel temporal sigma per depth bin against the real one (+- 35 %) and the
  whole-plane frame-to-frame jitter.

Run ``python -m noise_model.sim.stereo.validation --realdata DIR [--json PATH]`` (DIR holds the
``simsense_d435_ir_pairs`` folder of real recordings; without it only the simulated figures are made).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import label, median_filter

from .pipeline import StereoD435

__all__ = ["wall_scene", "wall_sweep", "real_pair", "dot_statistics", "aims_floor", "speed", "main"]

#: Targets printed next to the figures.
TARGET_SIGMA_D_PX = (0.05, 0.12)
TARGET_BAND_PX = 3.0
TARGET_VALID_POINTS = 0.05


def wall_scene(z_m: float):
    """A wall facing a camera at the origin of map x, 1 m above the ground, at z-depth ``z_m``, wider than the view."""
    from .. import Scene, Target

    return Scene([Target(centre=(z_m, 0.0, 1.0), width=8 * z_m + 2, height=6 * z_m + 2)], ground_z=None)


def _level_camera():
    from ..targets import camera_extrinsics

    return camera_extrinsics((0.0, 0.0, 1.0), pitch_down_deg=0.0)


def wall_sweep(distances=(0.5, 1.0, 1.5, 2.0, 2.5, 3.0), n_frames: int = 10, width: int = 848, height: int = 480,
               seed: int = 0, camera: StereoD435 | None = None) -> list[dict]:
    """Temporal and spatial noise, band and nearest depth of a projector-lit wall (module docstring).

    Per distance: the wall is rendered once and ``n_frames`` frames get fresh sensor noise. The
    temporal sigma is the median over pixels valid in every frame of their standard deviation
    (ddof 1); the spatial sigma is the standard deviation of one frame's disparity fB / z about its
    mean; the band is the median over rows of the first valid column.
    """
    cam = camera if camera is not None else StereoD435(width, height, ambient_w_m2=0.0)
    fB = cam.focal_px * cam.baseline_m
    T = _level_camera()
    rows = []
    for z in distances:
        ir = cam.render(wall_scene(z), T)
        rng = np.random.default_rng([seed, int(round(z * 1000))])
        frames = [cam.frame(ir, rng) for _ in range(n_frames)]
        D = np.stack([f.depth for f in frames]).astype(np.float64) * cam.depth_unit_m
        every = (D > 0).all(axis=0)
        sigma_z = float(np.median(D[:, every].std(axis=0, ddof=1))) if every.any() else float("nan")
        valid0 = D[0] > 0
        disp0 = fB / D[0][valid0]
        rows.append({
            "z_m": z,
            "exposure_ms": frames[0].exposure.time_s * 1e3,
            "gain": frames[0].exposure.gain,
            "valid_fraction": float((D > 0).mean()),
            "temporal_sigma_z_mm": sigma_z * 1e3,
            "temporal_sigma_d_px": sigma_z * fB / z ** 2,
            "spatial_sigma_d_px": float(np.std(disp0)),
            "mean_error_mm": float(np.mean(D[:, every]) - z) * 1e3 if every.any() else float("nan"),
            "band_px": float(np.median(np.argmax(valid0, axis=1))),
            "band_expected_px": fB / z,
            "nearest_m": float(D[D > 0].min()),
            "nearest_allowed_m": fB / 126.0,
        })
    return rows


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
    """The matcher on ``left1.png`` / ``right1.png`` against ``result_from_D435.png`` (module docstring).

    The picture is 424 x 240; our 848 x 480 validity is compared on every second row and column.
    Left band: per row the first valid column (rows 0-200, every 20th). Shadow: per row of
    ``shadow_rows`` the first invalid run after the floor (:func:`_shadow_run`, left of the box in
    that recording), its start column and width, medians over rows.
    """
    from PIL import Image

    from .matcher import match

    folder = Path(folder)
    left = np.asarray(Image.open(folder / "left1.png"))
    right = np.asarray(Image.open(folder / "right1.png"))
    t0 = time.perf_counter()
    res = match(left, right, preset)
    seconds = time.perf_counter() - t0
    ours = ~np.isfinite(res.disparity)[::2, ::2]
    theirs = _black(Image.open(folder / "result_from_D435.png"))
    band_rows = list(range(0, 201, 20))
    band_ours = [int(np.argmax(~ours[r])) for r in band_rows]
    band_theirs = [int(np.argmax(~theirs[r])) for r in band_rows]
    r0, r1 = shadow_rows
    sh_ours = np.array([_shadow_run(ours[r], shadow_x_max) for r in range(r0, r1)])
    sh_theirs = np.array([_shadow_run(theirs[r], shadow_x_max) for r in range(r0, r1)])
    return {
        "preset": preset,
        "valid_fraction_ours": float(1 - ours.mean()),
        "valid_fraction_d435": float(1 - theirs.mean()),
        "band_rows": band_rows,
        "band_ours_px424": band_ours,
        "band_d435_px424": band_theirs,
        "band_max_diff_px424": int(np.max(np.abs(np.subtract(band_ours, band_theirs)))),
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


def aims_floor(folder, ambient_w_m2: float = 0.05, n_frames: int = 16, segment: str = "S1_floor") -> dict:
    """The aims_slam floor segment simulated at its geometry, binned as its ``figures.json``.

    The camera stands ``dist_m`` above a concrete floor, oriented so that the floor's normal in the
    camera frame is the recording's fitted ``plane.normal`` (its pitch and roll); the image is
    640 x 480 with fx = fy = 383.8, (321.7, 238.2). Per depth bin of the segment: the median over
    pixels of the ROI valid in >= 90 % of the frames of their temporal standard deviation.
    """
    from .. import Scene
    from .materials import MaterialMap, concrete

    fig = json.loads((Path(folder) / "figures.json").read_text())
    seg = fig[segment]
    intr = fig["intrinsics_estimate_640x480"]
    K = np.array([[intr["fx"], 0.0, intr["ppx"]], [0.0, intr["fy"], intr["ppy"]], [0.0, 0.0, 1.0]])
    up = np.asarray(seg["plane"]["normal"], dtype=np.float64)
    up /= np.linalg.norm(up)
    axis = np.array([0.0, 0.0, 1.0])
    x_map = axis - (axis @ up) * up
    x_map /= np.linalg.norm(x_map)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x_map, np.cross(up, x_map), up]).T
    T[2, 3] = seg["plane"]["dist_m"]
    cam = StereoD435(640, 480, K=K, materials=MaterialMap(default=concrete(), ground=concrete()),
                     ambient_w_m2=ambient_w_m2)
    ir = cam.render(Scene([], ground_z=0.0), T, with_truth=True)
    rng = np.random.default_rng(0)
    D = np.stack([cam.frame(ir, rng).depth for _ in range(n_frames)]).astype(np.float64) * cam.depth_unit_m
    x0, y0, x1, y1 = seg["roi_xyxy"]
    roi = np.zeros(D.shape[1:], bool)
    roi[y0:y1, x0:x1] = True
    ok = ((D > 0).mean(axis=0) >= 0.9) & roi
    Dv = np.where(D > 0, D, np.nan)
    sd = np.full(D.shape[1:], np.nan)
    sd[ok] = np.nanstd(Dv[:, ok], axis=0, ddof=1)
    fB = cam.focal_px * cam.baseline_m
    bins = []
    for b in seg["plane_temporal_bins"]:
        lo, hi = b["z_m"]
        m = ok & (ir.z_true >= lo) & (ir.z_true < hi)
        sim = float(np.nanmedian(sd[m])) * 1e3 if m.any() else float("nan")
        zm = float(np.median(ir.z_true[m])) if m.any() else float("nan")
        bins.append({"z_m": [lo, hi], "incidence_deg": b["median_local_incidence_deg"],
                     "real_mm": b["median_temporal_std_mm"], "sim_mm": sim,
                     "ratio": sim / b["median_temporal_std_mm"],
                     "real_sigma_d_px": b["implied_subpixel_px"], "sim_sigma_d_px": sim * 1e-3 * fB / zm ** 2})
    offsets = [float(np.nanmean(np.where(roi, Dv[k] - ir.z_true, np.nan))) for k in range(n_frames)]
    return {"segment": segment, "ambient_w_m2": ambient_w_m2, "bins": bins,
            "plane_jitter_sim_mm": float(np.std(offsets, ddof=1)) * 1e3,
            "plane_jitter_real_mm": seg["plane_offset_frame_to_frame_std_mm"]}


def speed(width: int, height: int, repeats: int = 3) -> dict:
    """Milliseconds per frame of a camera pitched 30 deg down over a floor with a box: render and match."""
    from .. import Box, Scene
    from ..targets import camera_extrinsics

    scene = Scene([Box(centre=(1.5, 0.2, 0.15), size=(0.4, 0.4, 0.3))], ground_z=0.0)
    T = camera_extrinsics((0.0, 0.0, 0.45), pitch_down_deg=30.0)
    cam = StereoD435(width, height)
    ir = cam.render(scene, T)
    cam.frame(ir, np.random.default_rng(0))
    render_ms, frame_ms = [], []
    for k in range(repeats):
        t = time.perf_counter()
        ir = cam.render(scene, T)
        render_ms.append((time.perf_counter() - t) * 1e3)
        t = time.perf_counter()
        cam.frame(ir, np.random.default_rng(k))
        frame_ms.append((time.perf_counter() - t) * 1e3)
    return {"size": f"{width}x{height}", "render_ms": float(np.median(render_ms)),
            "noise_and_match_ms": float(np.median(frame_ms)),
            "total_ms": float(np.median(render_ms) + np.median(frame_ms))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--realdata", type=Path,
                    help="folder holding simsense_d435_ir_pairs and aims_slam_d435_robot_floor")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--no-speed", action="store_true")
    args = ap.parse_args(argv)
    out = {"wall_848x480": wall_sweep(n_frames=args.frames)}
    lo, hi = TARGET_SIGMA_D_PX
    print("wall, projector only, 848x480         target")
    for r in out["wall_848x480"]:
        print(f"  z {r['z_m']:.1f} m: temporal sigma_d {r['temporal_sigma_d_px']:.3f} px  [{lo}-{hi}]  "
              f"spatial {r['spatial_sigma_d_px']:.3f} px  band {r['band_px']:.0f} px  [{r['band_expected_px']:.1f} "
              f"+- {TARGET_BAND_PX:.0f}]  nearest {r['nearest_m']:.3f} m  [>= {r['nearest_allowed_m']:.3f}]  "
              f"valid {r['valid_fraction']:.3f}  exposure {r['exposure_ms']:.1f} ms x{r['gain']:.2f}")
    pair = args.realdata / "simsense_d435_ir_pairs" if args.realdata else None
    if pair is not None and pair.is_dir():
        from PIL import Image

        out["real_pair"] = rp = real_pair(pair)
        print(f"real pair: valid {rp['valid_fraction_ours']:.3f} vs D435 {rp['valid_fraction_d435']:.3f} "
              f"[+- {TARGET_VALID_POINTS}]; band max diff {rp['band_max_diff_px424']} px [<= 3]; shadow at "
              f"{rp['shadow_start_ours_px424']:.0f} vs {rp['shadow_start_d435_px424']:.0f} px, width "
              f"{rp['shadow_width_ours_px424']:.0f} vs {rp['shadow_width_d435_px424']:.0f} px [+- 3]")
        left = np.asarray(Image.open(pair / "left1.png"))
        out["real_dots"] = {name: dot_statistics(left, reg) for name, reg in (
            ("carpet_near", np.s_[380:480, 600:700]), ("carpet_left", np.s_[370:470, 100:200]),
            ("box_front", np.s_[270:330, 200:380]), ("book", np.s_[200:300, 480:580]))}
        for k, v in out["real_dots"].items():
            print(f"  real dots {k}: {v['dots_per_100x100']:.0f} per 100x100, contrast {v['contrast_median']:.2f}")
    aims = args.realdata / "aims_slam_d435_robot_floor" if args.realdata else None
    if aims is not None and aims.is_dir():
        out["aims_floor"] = af = aims_floor(aims)
        print(f"aims_slam floor ({af['ambient_w_m2']} W/m^2 ambient), temporal sigma per depth bin, target +-35 %:")
        for b in af["bins"]:
            print(f"  z {b['z_m'][0]:.2f}-{b['z_m'][1]:.2f} m ({b['incidence_deg']:.0f} deg): sim {b['sim_mm']:.2f} mm "
                  f"vs real {b['real_mm']:.2f} mm (x{b['ratio']:.2f}); sigma_d {b['sim_sigma_d_px']:.3f} vs "
                  f"{b['real_sigma_d_px']:.3f} px")
        print(f"  whole-plane jitter {af['plane_jitter_sim_mm']:.2f} mm vs real {af['plane_jitter_real_mm']:.2f} mm")
    if not args.no_speed:
        out["speed"] = [speed(424, 240), speed(848, 480)]
        for s in out["speed"]:
            print(f"speed {s['size']}: render {s['render_ms']:.0f} ms + noise and matching "
                  f"{s['noise_and_match_ms']:.0f} ms = {s['total_ms']:.0f} ms")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
