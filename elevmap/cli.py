"""The ``elevmap`` command line: one console script with subcommands."""

from __future__ import annotations

import argparse
import json
import sys

__all__ = ["main", "build_parser"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="elevmap",
        description="Calibrated robot-centric elevation maps from Intel RealSense D435 depth, with the "
                    "noise model of Ahn et al. (2019).",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("demo", help="the built-in demonstration; writes demo.rrd",
                       description="Simulate a wall seen by a D435 at 1 m and 2 m, head-on and at 45 deg, "
                                   "and write a rerun recording of the depth, the per-point covariance "
                                   "ellipsoids and sigma_z over depth and incidence angle. Open it with "
                                   "`rerun demo.rrd`.")
    p.add_argument("--rrd", default="demo.rrd", help="recording to write (default: demo.rrd)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    p = sub.add_parser("bench", help="time the numba kernels against their NumPy references",
                       description="Median per-frame time of each compiled kernel after warm-up, next to its "
                                   "NumPy reference measured in the same run.")
    p.add_argument("--frames", type=int, default=200, help="timed frames per kernel and size (default: 200)")
    p.add_argument("--reference-frames", type=int, default=10,
                   help="timed frames of the NumPy references (default: 10)")
    p.add_argument("--threads", type=int, default=None, help="numba threads (default: all)")
    p.add_argument("--only", default=None, metavar="GROUPS",
                   help="comma-separated subset of: noise, mapper, move_to, height_scan, first_frame")
    p.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def _cmd_demo(args) -> int:
    from .demo import run_noise_demo

    summary = run_noise_demo(args.rrd, seed=args.seed, show_progress=not args.no_progress)
    print(json.dumps(summary, indent=2))
    print(f"wrote {args.rrd}; open it with: rerun {args.rrd}")
    return 0


def _cmd_bench(args) -> int:
    from .bench import format_table, run_bench
    from .fileio import write_json_atomic

    if args.frames < 1 or args.reference_frames < 1:
        raise ValueError("--frames and --reference-frames must be >= 1")
    from .bench import GROUPS

    groups = GROUPS if args.only is None else tuple(g.strip() for g in args.only.split(",") if g.strip())
    report = run_bench(args.frames, args.reference_frames, args.threads, show_progress=not args.no_progress,
                       groups=groups)
    print(format_table(report))
    if args.json:
        write_json_atomic(args.json, report)
        print(f"wrote {args.json}")
    return 0


COMMANDS = {"demo": _cmd_demo, "bench": _cmd_bench}


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except ValueError as exc:
        print(f"elevmap {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
