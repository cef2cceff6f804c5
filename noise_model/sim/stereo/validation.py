"""Validation of the physical D435: every figure printed next to its target (docs/physical-d435.md).

Sections of the report (:func:`main`; ``elevmap simulate --sensor stereo --validate [DIR] --json PATH``
runs it):

1. :func:`wall_sweep` -- a fronto-parallel wall lit only by the projector, 0.5-3 m at 848 x 480: the
   temporal sigma of depth and the subpixel sigma it implies, sigma_d = sigma_z f B / z^2 (target
   0.05-0.12 px, Intel's typical 0.08), the left invalid band against its width in whole columns,
   ceil(f B / z) (+- 3 px; the columns x < f B / z have no right pixel at the true disparity), the nearest
   depth against f B / 126, the fill rate.
2. The aims_slam stretch (:func:`.realdata.aims_stretch`): per-pixel temporal sigma per depth bin of
   its wall and its floor (+- 35 %), the whole-plane frame-to-frame jitter next to the real one (and
   what the real one is made of, :func:`.realdata.aims_real_offsets`), plane-fit residuals.
3. The real infrared pair (:func:`.realdata.real_pair`): valid fraction (5 points), left band and
   occlusion shadow (+- 3 px at 424 x 240); dots per 100 x 100 px patch and their contrast, real and
   simulated (+- 30 %, :func:`.realdata.simulated_dots`).
4. Single frames of real planes (:func:`.realdata.single_plane`): the plane-fit residual within a
   factor 1.5 of the real one.
5. Emergent effects (:mod:`.emergent`), per distance and angle, with the gap tool's statistics.
6. Speed (:func:`speed`): ms per frame at 424 x 240 (<= 150) and 848 x 480 (<= 600).

The folder ``DIR`` holds the real recordings (``simsense_d435_ir_pairs``,
``aims_slam_d435_robot_floor``, ``opf_d435i_viewer_raw``, ``lrs_unittest_bag_d435``); without it only
the simulated figures are made.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from .pipeline import StereoD435

__all__ = ["wall_scene", "wall_sweep", "speed", "run", "main", "TARGET_SIGMA_D_PX", "TARGET_BAND_PX",
           "TARGET_VALID_POINTS", "TARGET_AIMS_REL", "TARGET_PLANE_FACTOR", "TARGET_DOTS_REL", "TARGET_MS"]

#: Targets printed next to the figures (issue text of the validation, docs/physical-d435.md).
TARGET_SIGMA_D_PX = (0.05, 0.12)
TARGET_BAND_PX = 3.0
TARGET_VALID_POINTS = 0.05
TARGET_AIMS_REL = 0.35
TARGET_PLANE_FACTOR = 1.5
TARGET_DOTS_REL = 0.30
TARGET_MS = {(424, 240): 150.0, (848, 480): 600.0}


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
            "band_expected_px": float(math.ceil(fB / z)),     # whole columns x < f B / z have no match
            "nearest_m": float(D[D > 0].min()),
            "nearest_allowed_m": fB / 126.0,
        })
    return rows


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
    total = float(np.median(render_ms) + np.median(frame_ms))
    return {"size": f"{width}x{height}", "render_ms": float(np.median(render_ms)),
            "noise_and_match_ms": float(np.median(frame_ms)), "total_ms": total,
            "target_ms": TARGET_MS.get((width, height))}


# ---------------------------------------------------------------------------------------------
# the report
# ---------------------------------------------------------------------------------------------


def _ok(flag) -> str:
    return "ok  " if flag else "MISS"


def _within(x, lo, hi) -> bool:
    return bool(np.isfinite(x) and lo <= x <= hi)


def _section_wall(out, n_frames, say):
    out["wall_848x480"] = rows = wall_sweep(n_frames=n_frames)
    lo, hi = TARGET_SIGMA_D_PX
    say(f"1. Fronto-parallel wall lit only by the projector, 848x480, {n_frames} frames per distance")
    say(f"   z [m]  temporal sigma_z   sigma_d [{lo}-{hi} px]   single-frame sigma_d   left band [ceil(f B / z) +- "
        f"{TARGET_BAND_PX:.0f} px]   nearest [>= f B / 126]   valid   exposure")
    for r in rows:
        band_ok = abs(r["band_px"] - r["band_expected_px"]) <= TARGET_BAND_PX
        near_ok = r["nearest_m"] >= r["nearest_allowed_m"]
        say(f"   {r['z_m']:4.1f}   {r['temporal_sigma_z_mm']:6.2f} mm        {r['temporal_sigma_d_px']:.3f} "
            f"{_ok(_within(r['temporal_sigma_d_px'], lo, hi))}        {r['spatial_sigma_d_px']:.3f} px"
            f"               {r['band_px']:4.0f} vs {r['band_expected_px']:5.1f} {_ok(band_ok)}"
            f"           {r['nearest_m']:.3f} m {_ok(near_ok)}     {r['valid_fraction']:.3f}   "
            f"{r['exposure_ms']:.1f} ms x{r['gain']:.2f}")


def _section_aims(out, folder, say):
    from .realdata import aims_real_offsets, aims_stretch

    out["aims_slam"] = a = aims_stretch(folder)
    say(f"2. aims_slam stretch S1 (640x480, fx 383.8; white wall and concrete floor, {a['n_frames']} frames, "
        f"ambient {a['ambient_w_m2']} W/m^2, exposure {a['exposure_ms']:.1f} ms x{a['gain']:.2f})")
    say(f"   per-pixel temporal sigma per depth bin of figures.json, target +- {TARGET_AIMS_REL:.0%}")
    for name in ("wall", "floor"):
        for b in a[name]["bins"]:
            ok = _within(b["ratio"], 1 - TARGET_AIMS_REL, 1 + TARGET_AIMS_REL)
            say(f"   {name:5s} z {b['z_m'][0]:.2f}-{b['z_m'][1]:.2f} m ({b['incidence_deg']:2.0f} deg): "
                f"sim {b['sim_mm']:5.2f} mm vs real {b['real_mm']:5.2f} mm  x{b['ratio']:.2f} {_ok(ok)}  "
                f"sigma_d {b['sim_sigma_d_px']:.3f} vs {b['real_sigma_d_px']:.3f} px")
    out["aims_slam_real_offsets"] = ro = aims_real_offsets(folder)
    for name in ("wall", "floor"):
        p = a[name]
        say(f"   {name:5s} whole-plane frame-to-frame jitter: sim {p['jitter_sim_mm']:.2f} mm vs real "
            f"{p['jitter_real_mm']:.2f} mm (figures.json); real without the stretch's first and last frame "
            f"{ro[name]['jitter_inner_mm']:.2f} mm")
        say(f"   {name:5s} plane-fit residual, one frame: sim {p['residual_single_sim_mm']:.2f} vs real "
            f"{p['residual_single_real_mm']:.2f} mm; {a['n_frames']}-frame mean: sim {p['residual_mean_sim_mm']:.2f} "
            f"vs real {p['residual_mean_real_mm']:.2f} mm")
    say(f"   real per-frame offsets, wall vs floor: correlation {ro['correlation']:.2f} (without first and last "
        f"frame {ro['correlation_inner']:.2f}); frame-wide part {ro['shared_inner_px']:.4f} px")


def _section_pair(out, folder, say):
    from .realdata import DOT_PATCHES, FLOOR_PATCHES, dot_statistics, read_png, real_pair, simulated_dots

    out["real_pair"] = rp = real_pair(folder)
    vp = abs(rp["valid_fraction_ours"] - rp["valid_fraction_d435"]) <= TARGET_VALID_POINTS
    say("3. Real infrared pair (simsense_d435_ir_pairs/left1, right1; 848x480, f 427.12), default preset")
    say(f"   valid fraction {rp['valid_fraction_ours']:.3f} vs D435 {rp['valid_fraction_d435']:.3f} "
        f"[+- {TARGET_VALID_POINTS}] {_ok(vp)}")
    say(f"   left band per row (424 px) ours {rp['band_ours_px424']}")
    say(f"                          D435 {rp['band_d435_px424']}")
    say(f"   band difference: median {rp['band_median_diff_px424']:.0f}, max {rp['band_max_diff_px424']} px "
        f"[+- {TARGET_BAND_PX:.0f}] {_ok(rp['band_max_diff_px424'] <= TARGET_BAND_PX)}")
    ss = abs(rp["shadow_start_ours_px424"] - rp["shadow_start_d435_px424"]) <= TARGET_BAND_PX
    sw = abs(rp["shadow_width_ours_px424"] - rp["shadow_width_d435_px424"]) <= TARGET_BAND_PX
    say(f"   occlusion shadow left of the box: starts {rp['shadow_start_ours_px424']:.0f} vs "
        f"{rp['shadow_start_d435_px424']:.0f} px {_ok(ss)}, width {rp['shadow_width_ours_px424']:.0f} vs "
        f"{rp['shadow_width_d435_px424']:.0f} px {_ok(sw)} [+- {TARGET_BAND_PX:.0f}]")
    left = read_png(Path(folder) / "left1.png")
    out["real_dots"] = real = {k: dot_statistics(left, v) for k, v in DOT_PATCHES.items()}
    out["simulated_dots"] = sim = simulated_dots()
    say(f"   dots per 100x100 px and contrast, simulated carpet floor at the pair's geometry (ambient "
        f"{sim['ambient_w_m2']} W/m^2) vs real, target +- {TARGET_DOTS_REL:.0%}:")
    for k in FLOOR_PATCHES:
        r, s = real[k], sim[k]
        cn = abs(s["dots_per_100x100"] / r["dots_per_100x100"] - 1) <= TARGET_DOTS_REL
        cc = abs(s["contrast_median"] / r["contrast_median"] - 1) <= TARGET_DOTS_REL
        say(f"   {k:12s} dots {s['dots_per_100x100']:4.0f} vs {r['dots_per_100x100']:4.0f} {_ok(cn)}   contrast "
            f"{s['contrast_median']:.2f} vs {r['contrast_median']:.2f} {_ok(cc)}")
    for k in DOT_PATCHES:
        if k not in FLOOR_PATCHES:
            say(f"   {k:12s} real only: dots {real[k]['dots_per_100x100']:4.0f}, contrast "
                f"{real[k]['contrast_median']:.2f}")


def _section_planes(out, folder, say):
    from .realdata import SINGLE_PLANES, single_plane

    say(f"4. Single frames of real planes: plane-fit residual (RANSAC, 2 % of depth), target within a factor "
        f"{TARGET_PLANE_FACTOR}")
    out["single_planes"] = rows = []
    for name, spec in SINGLE_PLANES.items():
        if not (Path(folder) / spec["folder"]).is_dir():
            continue
        for amb in ((0.05, None) if spec["exposure_ms"] is not None else (0.05,)):
            r = single_plane(folder, name, ambient_w_m2=amb)
            rows.append(r)
            ok = _within(r["ratio"], 1 / TARGET_PLANE_FACTOR, TARGET_PLANE_FACTOR)
            how = "fitted to the recording's exposure" if amb is None else "default"
            w, h = spec["size"]
            say(f"   {name:9s} {w}x{h} at {r['median_depth_m']:.2f} m: sim {r['residual_sim_mm']:5.2f} mm vs real "
                f"{r['residual_real_mm']:5.2f} mm  x{r['ratio']:.2f} {_ok(ok)}  (ambient {r['ambient_w_m2']:.2f} "
                f"W/m^2, {how}; exposure {r['exposure_ms']:.1f} ms"
                + (f" vs real {r['exposure_real_ms']:.1f} ms)" if r["exposure_real_ms"] else ")"))


def _section_emergent(out, n_frames, say):
    from . import emergent as E

    t0 = time.perf_counter()
    out["emergent"] = em = E.measure(n_frames=n_frames)
    say(f"5. Emergent effects (424x240, {n_frames} frames per capture, gap statistics on each target's interior; "
        f"{time.perf_counter() - t0:.0f} s)")
    say("   capture          z [m] angle  fill   temporal   spatial  corr.len  lattice  tail    sigma_d: temporal"
        "  static  static/temporal")
    for c in em["captures"]:
        say(f"   {c['id']:16s} {c['distance_m']:4.1f} {c['angle_deg']:5.0f}  {c['fill_rate']:.3f}  "
            f"{c['temporal_std_m'] * 1e3:6.2f} mm {c['spatial_std_m'] * 1e3:6.2f} mm  {c['corr_length_px']:5.2f} px"
            f"  {c['lattice']:6.3f}  {c['tail_rate']:.4f}  {c['temporal_sigma_d_px']:.3f} px"
            f"   {c['static_sigma_d_px']:.3f}   {c['static_ratio']:.2f}")
    f = em["fits"]

    def show(name):
        v = f.get(name, {})
        return v["error"] if "error" in v else ", ".join(
            f"{k} {x:.3g}" if isinstance(x, float) else f"{k} {x}" for k, x in v.items() if k != "seed")

    say(f"   disparity lattice (gap fit): {show('disparity_lattice')}  [5 bits = 1/32 px]")
    for name in ("correlated_noise", "static_pattern", "edge_fattening", "flying_pixels", "dropout",
                 "disparity_noise"):
        say(f"   {name} (gap fit, excess over the paper's model): {show(name)}")
    say("   fill rate against albedo (fronto-parallel wall, projector only):")
    for d in sorted({r["distance_m"] for r in em["fill_vs_albedo"]}):
        cells = "  ".join(f"{r['albedo']:.2f}: {r['fill_rate']:.3f}" for r in em["fill_vs_albedo"]
                          if r["distance_m"] == d)
        say(f"   z {d:.1f} m  {cells}")


def _section_speed(out, say):
    out["speed"] = [speed(424, 240), speed(848, 480)]
    say("6. Speed (render + noise and matching, ms per frame; a static camera renders once)")
    for s in out["speed"]:
        say(f"   {s['size']}: render {s['render_ms']:.0f} + noise and matching {s['noise_and_match_ms']:.0f} = "
            f"{s['total_ms']:.0f} ms [<= {s['target_ms']:.0f}] {_ok(s['total_ms'] <= s['target_ms'])}")


def run(realdata=None, n_frames: int = 10, emergent_frames: int = 30, with_speed: bool = True,
        with_emergent: bool = True, say=print) -> dict:
    """Every section of the module docstring; ``realdata`` (a folder) adds those against real recordings.

    Returns the figures (JSON-ready) and prints each next to its target through ``say``.
    """
    out: dict = {}
    _section_wall(out, n_frames, say)
    folder = Path(realdata) if realdata is not None else None
    if folder is not None and (folder / "aims_slam_d435_robot_floor").is_dir():
        _section_aims(out, folder / "aims_slam_d435_robot_floor", say)
    if folder is not None and (folder / "simsense_d435_ir_pairs").is_dir():
        _section_pair(out, folder / "simsense_d435_ir_pairs", say)
    if folder is not None:
        _section_planes(out, folder, say)
    if with_emergent:
        _section_emergent(out, emergent_frames, say)
    if with_speed:
        _section_speed(out, say)
    return out


def _json_ready(x):
    if isinstance(x, dict):
        return {str(k): _json_ready(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_ready(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--realdata", type=Path,
                    help="folder of the real D435 recordings (simsense_d435_ir_pairs, aims_slam_d435_robot_floor, "
                         "opf_d435i_viewer_raw, lrs_unittest_bag_d435)")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--frames", type=int, default=10, help="frames per distance of the wall sweep (default 10)")
    ap.add_argument("--emergent-frames", type=int, default=30,
                    help="frames per capture of the emergent effects (default 30)")
    ap.add_argument("--no-speed", action="store_true", help="skip the speed section")
    ap.add_argument("--no-emergent", action="store_true", help="skip the emergent effects")
    args = ap.parse_args(argv)
    if args.realdata is not None and not args.realdata.is_dir():
        raise ValueError(f"{args.realdata}: no such folder (the real recordings)")
    out = run(args.realdata, args.frames, args.emergent_frames, not args.no_speed, not args.no_emergent)
    if args.json:
        args.json.write_text(json.dumps(_json_ready(out), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
