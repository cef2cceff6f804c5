"""Record a small simulated walk up a staircase as a rerun recording (recordings/stairs_walk.rrd).

    python examples/record_walk.py [--out recordings/stairs_walk.rrd] [--frames 24]

The recording holds what `elevmap replay` needs (depth under a pinhole, exact poses) plus the map as
it was built, and stays under 5 MB. Open it with `rerun recordings/stairs_walk.rrd`.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from elevmap import MappingConfig, run_mapping
from elevmap.fileio import check_outputs
from elevmap.sources import SimulatedWalk


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "recordings" / "stairs_walk.rrd"))
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--overwrite", action="store_true", help="replace an existing recording")
    args = parser.parse_args()
    try:
        check_outputs({"--out": args.out}, args.overwrite)
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    src = SimulatedWalk("stairs", n_frames=args.frames, seed=args.seed)
    config = MappingConfig(length_m=6.0, resolution_m=0.04, mesh_every=1000, max_points=800, max_ellipsoids=60,
                           png_depth=True)
    summary = run_mapping(src, config, rrd_path=args.out, total=len(src), application_id="elevmap_stairs_walk",
                          notes="A simulated D435 (424x240, 10 Hz) walking up six 0.17 m steps, paper noise.")
    err = summary["error"]
    print(f"{summary['frames']} frames, median |error| {1000 * err['median_abs_m']:.1f} mm, "
          f"{os.path.getsize(args.out) / 1e6:.2f} MB -> {args.out}")


if __name__ == "__main__":
    main()
