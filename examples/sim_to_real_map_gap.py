"""From a gap diagnosis to the map: does the fitted sensor model close the map-level gap?

The loop of ``elevmap gap`` end to end, on data whose truth is known:

1. "Real" captures: 18 walls x 12 frames at 424x240 rendered with the paper's reference model plus
   effects the diagnosis is not told about (a user records theirs instead, see the README);
2. ``diagnose`` finds which effects explain the gap and fits them (held-out captures validate);
3. one simulated walk is mapped three times with the same seed: in the "real" world (the hidden
   effects), with the reference model alone, and with the fitted effects. The map-level gap is the
   difference of the map's error statistics (RMSE, 2-sigma coverage, known cells, mean sigma)
   between the real world and each simulation; it should shrink once the fitted effects are in.

Run:  python examples/sim_to_real_map_gap.py [--scene boxes] [--frames 40] [--seed 0]
"""

from __future__ import annotations

import argparse
import zlib

import numpy as np

from elevmap.commands.compare import run_compare
from elevmap.commands.gap import diagnose, selftest_geometries
from noise_model.sim import effects as E
from noise_model.analysis.capture_data import CaptureData, simulate_capture

#: The effects hidden in the "real" data, at parameters the diagnosis is not given.
HIDDEN = [("invalid_band", {"margin_px": 5.0}), ("correlated_noise", {"sigma_z_fraction": 1.5, "length_px": 3.0})]
#: Map statistics compared between the real world and a simulation.
METRICS = ("rmse_m", "coverage_2sigma", "known_fraction", "mean_sigma_m")


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="boxes", help="walk scene (default: boxes)")
    ap.add_argument("--frames", type=int, default=40, help="frames of the walk (default: 40)")
    ap.add_argument("--capture-frames", type=int, default=12, help="frames per capture (default: 12)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    hidden = E.canonical_order([E.make_effect(n, **p) for n, p in HIDDEN])
    real = []
    for g in selftest_geometries("wall"):
        rng = np.random.default_rng([args.seed + 7, zlib.crc32(g.id.encode("utf-8"))])
        real.append(CaptureData.from_units(g, simulate_capture(g, args.capture_frames, rng, effects=hidden)))
    report, _ = diagnose(real, heldout="auto", seed=args.seed)
    fitted = E.effects_from_report(report)
    print("hidden: " + ", ".join(f"{e!r}" for e in hidden))
    print("found:  " + (", ".join(f"{e!r}" for e in fitted) or "nothing"))
    print(f"capture-level held-out gap shrink: {100 * report['final']['shrink_heldout']:.1f} %")

    runs = {}
    for label, fx in (("real", hidden), ("reference", []), ("fitted", E.canonical_order(fitted))):
        r = run_compare(args.scene, args.frames, seed=args.seed, sim_effects=fx, mappers=["paper"],
                        show_progress=False)
        runs[label] = r["mappers"]["paper"]
    out = {"hidden": HIDDEN, "fitted": [{"name": e.name, "params": dict(e.params)} for e in fitted],
           "capture_shrink_heldout": report["final"]["shrink_heldout"], "map": {}}
    print(f"\nmap of the {args.scene} walk ({args.frames} frames), paper mapper: real | reference | fitted")
    for m in METRICS:
        real_v, ref_v, fit_v = runs["real"][m], runs["reference"][m], runs["fitted"][m]
        gap_ref, gap_fit = abs(ref_v - real_v), abs(fit_v - real_v)
        shrink = 1.0 - gap_fit / gap_ref if gap_ref > 0 else float("nan")
        out["map"][m] = {"real": real_v, "reference": ref_v, "fitted": fit_v, "gap_reference": gap_ref,
                         "gap_fitted": gap_fit, "shrink": shrink}
        print(f"  {m:16s} {real_v:9.4f} | {ref_v:9.4f} | {fit_v:9.4f}   gap {gap_ref:.4f} -> {gap_fit:.4f}"
              f" ({100 * shrink:+.0f} % shrink)")
    return out


if __name__ == "__main__":
    main()
