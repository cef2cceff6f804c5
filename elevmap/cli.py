"""The ``elevmap`` command line: one console script with subcommands.

This module parses and dispatches only: each ``_cmd_*`` checks the arguments, then calls its command
module of :mod:`elevmap.commands` (imported when the command runs, so ``elevmap --help`` loads neither
numba nor rerun). Every output goes through :func:`elevmap.fileio.check_outputs` before any work.
A ``ValueError`` is a user error: printed as ``elevmap COMMAND: error: ...``, exit status 2.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
import textwrap
from pathlib import Path


__all__ = ["main", "build_parser"]


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose description may end in text computed only when help is shown
    (``description_tail``: a function returning str), so that building the parser stays light."""

    description_tail = None

    def format_help(self) -> str:
        if self.description_tail is not None:
            self.description, self.description_tail = self.description + self.description_tail(), None
        return super().format_help()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="elevmap",
        description="Calibrated robot-centric elevation maps from Intel RealSense D435 depth, with the "
                    "noise model of Ahn et al. (2019).",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)

    p = sub.add_parser("demo", help="the built-in demonstration: a simulated walk mapped; writes demo.rrd and demo.png",
                       description="Simulate a legged robot walking about 6 m straight ahead, across a field of "
                                   "4-15 cm boxes and up six 0.17 m steps, seen by a D435 (424x240 at 10 Hz, "
                                   "0.45 m up, pitched 30 deg down) with the noise of Ahn et al. (2019); map "
                                   "every frame (8 m map at 0.04 m, following the robot) and score the map "
                                   "against the true terrain. Writes a rerun recording (depth, camera poses, "
                                   "points with their 2-sigma covariance ellipsoids, the map coloured by height "
                                   "and by sigma, time, sigma and error over the frames) and, beside it, a PNG of "
                                   "the final map (height, sigma and error against the truth side by side: "
                                   "demo.png beside demo.rrd). Existing files are replaced only with --overwrite. "
                                   "Open the recording with `rerun demo.rrd`. --sensor stereo: the same walk seen "
                                   "by the physical D435 (projector, infrared pair, matching), whose noise is not "
                                   "the model's.")
    p.add_argument("--rrd", default="demo.rrd", help="recording to write (default: demo.rrd)")
    p.add_argument("--sensor", default="reference", choices=("reference", "stereo"),
                   help="the D435 that sees the walk: reference (the paper's model draws the noise; default) or "
                        "stereo (the physical D435; about 0.1 s per frame more)")
    p.add_argument("--model", metavar="MODEL.json",
                   help="map with this sensor model file from `elevmap characterize` (default: the paper's D435)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    p.add_argument("--frames", type=int, default=None, help="frames of the walk (default: the whole path)")
    p.add_argument("--noise-model", action="store_true",
                   help="instead: the noise model alone (walls at 1 and 2 m, head-on and at 45 deg; no PNG)")
    p.add_argument("--spawn", action="store_true", help="also stream to a rerun viewer")
    p.add_argument("--overwrite", action="store_true", help="replace an existing recording and picture")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    for name, help_, desc in (
            ("run", "map any source (camera, ROS/RealSense bags, .rrd, capture set, PNG folder, simulator)",
             "Map a source of D435 depth frames into a robot-centric elevation map.\n\n"),
            ("replay", "map a rerun recording (.rrd)",
             "Replay a rerun recording's depth frames through the mapper.\n\n")):
        p = sub.add_parser(name, help=help_, formatter_class=argparse.RawDescriptionHelpFormatter,
                           description=desc + _source_help())
        p.add_argument("source", metavar="SOURCE" if name == "run" else "FILE.rrd")
        p.add_argument("--rrd", metavar="PATH", help="write a rerun recording of the run")
        p.add_argument("--spawn", action="store_true", help="stream to a rerun viewer")
        p.add_argument("--config", metavar="FILE.toml", help="settings: [map] and [map.fusion] tables")
        p.add_argument("--model", metavar="MODEL.json",
                       help="sensor model file from `elevmap characterize` (default: the paper's D435)")
        p.add_argument("--poses", metavar="FILE", help="pose file (TUM text or Open3D .log) for any source")
        p.add_argument("--intrinsics", metavar="FILE.json", help="intrinsics of a PNG folder")
        p.add_argument("--frames", type=int, default=None, help="frames of a simulated walk")
        p.add_argument("--seed", type=int, default=0, help="seed of a simulated walk (default: 0)")
        p.add_argument("--json", metavar="PATH", help="write the run's summary as JSON")
        p.add_argument("--overwrite", action="store_true", help="replace an existing --rrd/--json file")
        p.add_argument("--no-progress", action="store_true", help="no progress bar")
        p.add_argument("--view-rate", type=float, default=None, metavar="HZ",
                       help="with --rrd/--spawn: log the points, trail, map plots and meshes at most HZ times per "
                            "second of the source's time (default 10; every frame's depth and pose are logged)")
        p.add_argument("--threads", type=int, default=None,
                       help="numba threads of the mapper (default: all; fewer on a machine busy with other work)")
        p.add_argument("--valid-margin", type=int, default=None, metavar="PX",
                       help="drop depth pixels within PX columns of a no-data pixel or the image's side, where the "
                            "stereo matcher's window was cut short (default 5; a replay of this project's recording "
                            "uses the margin it names, 0 for one older than the margin); 0 for depth that is not "
                            "straight from a stereo matcher or is already filtered. Config key: valid_margin_px")
        p.add_argument("--png-depth", action="store_true",
                       help="with --rrd: log uint16 depth PNG-compressed (smaller files, but too slow to encode for "
                            "848x480 at 30 frames/s)")
        if name == "run":
            _ros_options(p)
            p.add_argument("--bag-out", metavar="PATH",
                           help="write the map as grid_map_msgs/GridMap + foxglove_msgs/Grid + /tf: PATH.bag (ROS 1), "
                                "PATH.mcap or a folder name (ROS 2 .db3)")
            p.add_argument("--map-rate", type=float, default=None, metavar="HZ",
                           help="maps per second of the source's time in --bag-out and --foxglove (default: 2)")
            p.add_argument("--foxglove", nargs="?", type=int, const=8765, default=None, metavar="PORT",
                           help="serve the map, depth and transforms live to Foxglove on 127.0.0.1:PORT "
                                "(default 8765; needs foxglove-sdk)")

    p = sub.add_parser("bag-info", help="what a ROS bag holds for mapping: depth topics, camera info, transforms",
                       description="List the depth topics of a ROS bag (ROS 1 .bag, ROS 2 folder, .mcap, .db3) as "
                                   "`elevmap run` reads them: encoding, size, frames, the matching camera info, the "
                                   "chain of transforms to the map frame, and in plain words what is missing.")
    p.add_argument("bag", metavar="BAG")
    _ros_options(p)
    p.add_argument("--json", metavar="PATH", help="also write the inspection as JSON")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")

    p = sub.add_parser("simulate", help="simulate a D435: capture sets on the paper's grid, or a walk",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Simulate a D435 with the reference simulation of the paper's model (default) or\n"
                                   "the physical D435 (--sensor stereo: projector, infrared pair, D4 matcher).\n\n"
                                   "  elevmap simulate --grid paper [--frames 100] [--sensor stereo] --out DIR\n"
                                   "      a capture set (d435-captures/1): boards 0.60 x 0.90 m before a wall at 3 m,\n"
                                   "      0.4 to 2.1 m every 0.1 m by 0 to 75 deg every 15 deg (108 captures)\n"
                                   "  elevmap simulate --walk SCENE [--frames N] [--drift] [--sensor stereo]\n"
                                   "                   --rrd PATH\n"
                                   "      a robot walking through SCENE (demo, stairs, boxes, slope, rough), mapped\n"
                                   "      and recorded for `elevmap replay`\n"
                                   "  elevmap simulate --sensor stereo --validate [DIR] [--json PATH]\n"
                                   "      the physical D435's validation figures next to their targets; with DIR, the\n"
                                   "      folder of real D435 recordings, also the comparisons with them")
    p.add_argument("--grid", choices=["paper"], help="capture set on the paper's grid")
    p.add_argument("--walk", metavar="SCENE", help="a walk through SCENE")
    p.add_argument("--sensor", choices=["reference", "stereo"], default="reference",
                   help="reference (the paper's model; default) or stereo (the physical D435)")
    p.add_argument("--preset", default=None, metavar="NAME",
                   help="matcher preset of --sensor stereo: default or high_accuracy (default: default)")
    p.add_argument("--validate", nargs="?", const="", default=None, metavar="DIR",
                   help="with --sensor stereo: print the validation figures (DIR: real recordings to compare with)")
    p.add_argument("--json", metavar="PATH", help="the validation figures as JSON (with --validate)")
    p.add_argument("--frames", type=int, default=None,
                   help="frames per capture (100), of the walk (all) or per setting of --validate")
    p.add_argument("--out", metavar="DIR", help="capture-set folder (with --grid)")
    p.add_argument("--rrd", metavar="PATH", help="recording of the walk (with --walk)")
    p.add_argument("--kind", choices=["board", "wall"], default="board", help="target of the captures")
    p.add_argument("--size", default="424x240", help="depth mode WIDTHxHEIGHT (default 424x240)")
    p.add_argument("--drift", action="store_true", help="odometry drift on the walk's poses")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    p = sub.add_parser("compare", help="one simulated walk through several mappers: error and calibration",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Render one simulated walk and feed the same frames to several mappers; score\n"
                                   "each final map against the true terrain (RMSE, 95th percentile, NLL, 1/2-sigma\n"
                                   "coverage, mean sigma, the step-edge band and flat ground, known cells, time per\n"
                                   "frame), also over the cells every mapper knows (common) and at equal coverage\n"
                                   "(matched). --seeds N: seeds SEED..SEED+N-1, scores as medians [min, max].\n"
                                   "--reality: reference (the paper's model plus --sim-effects), stereo (the\n"
                                   "physical D435) or GAP.json (the reference plus a gap report's fitted effects).\n\n"
                                   "mappers: paper (the paper's model, full covariance propagation), fitted (the\n"
                                   "  model elevmap characterize fits on the paper's grid simulated with the same\n"
                                   "  reality, cached in --work; or --fitted-model), disparity (sigma_d 0.08 px),\n"
                                   "  quadratic (elevation_mapping_cupy: 0.05 z^2), anybotics_d435 (ANYbotics' D435\n"
                                   "  preset), constant (2 cm), NAME_capped (NAME with the per-frame information cap\n"
                                   "  --cap); default: all but the capped ones, and fitted_capped\n"
                                   "sim effects (noise_model.sim.effects), NAME[:KEY=VALUE[:KEY=VALUE]]\n"
                                   "comma-separated, or a gap report (elevmap gap --json PATH): its selected effects\n"
                                   "as fitted:\n")
    p.description_tail = _effects_help
    p.add_argument("--scene", default="stairs", help="stairs, boxes, slope, rough or demo (default: stairs)")
    p.add_argument("--reality", default="reference", metavar="reference|stereo|GAP.json",
                   help="what makes the walk's depth: reference (the paper's model plus --sim-effects; default), "
                        "stereo (the physical D435) or a gap report (the reference plus its fitted effects)")
    p.add_argument("--preset", default=None, metavar="NAME",
                   help="matcher preset of --reality stereo: default or high_accuracy (default: default)")
    p.add_argument("--frames", type=int, default=None, help="frames of the walk (default: the whole path)")
    p.add_argument("--sim-effects", default=None, metavar="NAMES|GAP.json",
                   help="effects added to the simulated depth, or a gap report's fitted effects")
    p.add_argument("--mappers", default=None, metavar="NAMES",
                   help="comma-separated subset of paper, fitted, disparity, quadratic, anybotics_d435, constant "
                        "and NAME_capped")
    p.add_argument("--cap", type=float, default=None, metavar="N_EFF",
                   help="information cap of the capped mappers, points per cell and frame (default: 1)")
    p.add_argument("--seed", type=int, default=0, help="seed of the scene, noise and effects (default: 0)")
    p.add_argument("--seeds", type=int, default=None, metavar="N",
                   help="run seeds SEED..SEED+N-1 and report medians and spreads")
    p.add_argument("--size", default="424x240", help="depth mode WIDTHxHEIGHT (default 424x240)")
    p.add_argument("--max-variance", type=float, default=None, metavar="M2",
                   help="every mapper's variance ceiling [m^2] (default 1, elevation_mapping_cupy's; "
                        "the map's own default is 0.04)")
    p.add_argument("--work", metavar="DIR", default=None,
                   help="work folder caching the rendered walks and the fitted model (default: none for the "
                        "walks, elevmap-compare-work beside the --json report for the fitted model)")
    p.add_argument("--set", default=None, metavar="KEY=VALUE,...", dest="settings",
                   help="map settings for every mapper: FusionParams fields, visibility_cleanup and the camera's "
                        "bin_at_plane and valid_margin_px, e.g. spread_alpha=none,neighbour_radius=0 or "
                        "valid_margin_px=0 (what a rule buys)")
    p.add_argument("--fitted-model", metavar="PATH", default=None,
                   help="the fitted mapper's model file (elevmap characterize --model) instead of fitting one")
    p.add_argument("--json", metavar="PATH", help="the report (required)")
    p.add_argument("--rrd", metavar="PATH", help="rerun recording: the maps side by side, error maps (one seed)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --json/--rrd file")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    p = sub.add_parser("gap", help="sim-to-real gap: where the paper's model misses real captures, which effect "
                                   "explains it",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Compare a real capture set (d435-captures/1) with the reference simulation of the\n"
                                   "paper's model: WHERE (statistic x distance/angle/image cell/region, normalised by\n"
                                   "the real-vs-real noise floor), WHICH effect explains it (forward selection on fit\n"
                                   "captures, validated on held-out captures, ablation), HOW FAR the held-out gap\n"
                                   "shrinks.\n\n"
                                   "  elevmap gap REAL_CAPTURES [REAL_CAPTURES ...] --json gap.json [--rrd gap.rrd]\n"
                                   "              [--heldout IDS|auto|none]\n"
                                   "  elevmap gap --selftest [--jobs 2]\n"
                                   "  elevmap gap --realdata DIR --json real.json")
    p.add_argument("real", metavar="REAL_CAPTURES", nargs="*",
                   help="capture-set folder (captures.json); several are diagnosed together as one set")
    p.add_argument("--json", metavar="PATH", help="write the report (d435-gap/1); with --selftest, the table")
    p.add_argument("--rrd", metavar="PATH", help="write a rerun recording (bar charts, residual images)")
    p.add_argument("--heldout", metavar="IDS|auto|none", default=None,
                   help="held-out captures: comma-separated ids, auto (middle third of the distances per target "
                        "kind; default) or none (validate on the fit captures; default with --realdata)")
    p.add_argument("--effects", metavar="NAMES", default=None,
                   help="comma-separated candidate effects (default: all); with --selftest, the effects to hide")
    p.add_argument("--seed", type=int, default=0, help="seed of simulations, splits and bootstrap (default: 0)")
    p.add_argument("--selftest", action="store_true", help="hide each effect in simulated data and find it")
    p.add_argument("--depth-bands", metavar="EDGES", default=None,
                   help="split every capture into bands of true depth at these comma-separated edges [m] (a floor "
                        "then shows where in depth and angle the gap lies)")
    p.add_argument("--direct", action="store_true",
                   help="also measure the effects directly on the captures and the final model's simulation, "
                        "and put each fitted parameter next to its measurement")
    p.add_argument("--jobs", type=int, default=1,
                   help="processes: --selftest's cases, or the captures each model simulates (the report is the "
                        "same for any number; default: 1)")
    p.add_argument("--min-shrink", type=float, default=None, metavar="FRACTION",
                   help="materiality: an effect must shrink the held-out gap left before its round by at least this "
                        "fraction, in [0, 1) (default: 0.05)")
    p.add_argument("--max-effects", type=int, default=None, metavar="N",
                   help="select at most N effects (default: 8)")
    p.add_argument("--no-backfit", action="store_true",
                   help="do not refit the effects selected before each newly accepted one")
    p.add_argument("--realdata", metavar="DIR", help="instead: the genuine single D435 frames of DIR (its regions "
                                                      "of known planes)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --json/--rrd file")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    from .commands.protocol import PROTOCOL

    p = sub.add_parser("characterize", help="your own D435 noise model from a capture set (the paper's method)",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description=textwrap.fill(
                           "Characterise a depth camera as Ahn et al. (2019) did: find the planar target in "
                           "each capture (bilateral filter, Canny edges, the board's quadrilateral), measure "
                           "axial noise (pixel-wise temporal std about a fitted plane), lateral noise (left "
                           "and right edges), the plane-fit residual and the systematic error against the "
                           "measured distance with eq. (1); fit sigma_z(z, theta) in the paper's form and "
                           "sigma_L, sigma_R (90th percentiles). Writes the report, the fitted model "
                           "(<json stem>.model.json, read by noise_model.SensorModel.load) and the paper's "
                           "figures (PNG, rerun).", 100) + "\n\n" + PROTOCOL)
    p.add_argument("captures", metavar="CAPTURES", help="capture-set folder (captures.json, format d435-captures/1)")
    p.add_argument("--json", metavar="PATH", required=True, help="the report")
    p.add_argument("--model", metavar="PATH",
                   help="the fitted model (default: <json stem>.model.json beside the report)")
    p.add_argument("--predict", metavar="CAPTURES",
                   help="another capture set whose axial noise the fitted models predict (per depth bin)")
    p.add_argument("--only", metavar="IDS", help="characterise only these captures (comma-separated ids)")
    p.add_argument("--rrd", metavar="PATH", help="rerun recording of the figures")
    p.add_argument("--figures", metavar="DIR", help="folder for the PNG figures (Fig. 2, 3, 4, lateral noise)")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    p = sub.add_parser("captures", help="a capture set from static stretches of a recording: one capture per plane",
                       description=textwrap.fill(
                           "Make a capture set (d435-captures/1) from static stretches of any recording (no "
                           "measured target needed): for each stretch, the dominant planes of the per-pixel mean "
                           "(RANSAC, refitted along the rays), each written as a capture with a fitted plane "
                           "target, the stretch's frames and a pixel mask (the mean within 4 temporal sigmas of "
                           "the plane), geometry 'fitted'. Frames are numbered from 0 in the order the source "
                           "yields them.", 100) + "\n\n"
                                   "  elevmap captures RECORDING --frames 141-156[,1-8] --out DIR "
                                   "[--intrinsics FILE.json|fx,fy,ppx,ppy]",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recording", metavar="RECORDING", help="a PNG folder, .bag/.db3, .rrd, capture set or sim:SCENE")
    p.add_argument("--frames", required=True, metavar="A-B[,C-D]",
                   help="static stretches, inclusive frame ranges (at least 2 frames each)")
    p.add_argument("--out", required=True, metavar="DIR", help="the capture set's folder (new or empty)")
    p.add_argument("--intrinsics", metavar="FILE.json|fx,fy,ppx,ppy", help="intrinsics of a PNG folder [px]")
    p.add_argument("--baseline-m", type=float, default=0.050, help="stereo baseline written to the set (default: "
                                                                    "the D435's 0.050 m)")
    p.add_argument("--max-planes", type=int, default=4, help="planes per stretch at most (default: 4)")
    p.add_argument("--min-plane-fraction", type=float, default=0.05,
                   help="smallest plane kept, as a fraction of the image (default: 0.05)")
    p.add_argument("--seed", type=int, default=0, help="seed of RANSAC (default: 0)")
    p.add_argument("--json", metavar="PATH", help="also write what was found as JSON")
    p.add_argument("--overwrite", action="store_true", help="replace an earlier capture set in --out and --json")

    p = sub.add_parser("warmup", help="compile every numba kernel once, into the cache later commands load",
                       description="Compile the numba kernels the commands use (the noise model of both families "
                                   "and the map; the simulator; the physical D435) into numba's cache: "
                                   "NUMBA_CACHE_DIR when set, else __pycache__ folders beside the sources. Later "
                                   "commands load them instead of compiling (a cold cache costs tens of seconds "
                                   "in the first command that maps). `make demo` and `make test` run it once after "
                                   "installing. A warm cache compiles nothing and says so.")
    p.add_argument("--only", default=None, metavar="GROUPS",
                   help="comma-separated subset of: mapping, simulator, stereo (default: all)")
    p.add_argument("--threads", type=int, default=None, help="numba threads (default: all)")

    p = sub.add_parser("bench", help="time the numba kernels against their NumPy references",
                       description="Median per-frame time of each compiled kernel after warm-up, next to its "
                                   "NumPy reference measured in the same run; the physical D435 (stereo) next "
                                   "to its time budget.")
    p.add_argument("--frames", type=int, default=200, help="timed frames per kernel and size (default: 200)")
    p.add_argument("--reference-frames", type=int, default=10,
                   help="timed frames of the NumPy references (default: 10)")
    p.add_argument("--threads", type=int, default=None, help="numba threads (default: all)")
    p.add_argument("--only", default=None, metavar="GROUPS",
                   help="comma-separated subset of: noise, mapper, physical (the mapper on the physical D435's "
                        "frame), update, move_to, height_scan, first_frame, render, stereo, ros, run")
    p.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def _ros_options(p) -> None:
    """The options of a ROS bag source."""
    p.add_argument("--depth-topic", action="append", default=None, metavar="TOPIC",
                   help="a ROS bag's depth topic to map (repeat for several cameras; default: every depth topic)")
    p.add_argument("--map-frame", metavar="FRAME",
                   help="a ROS bag's map frame (default: the odometry's frame, else the root of /tf)")
    p.add_argument("--base-frame", metavar="FRAME",
                   help="the robot frame a ROS bag's odometry poses (default: its child_frame_id)")


def _source_help() -> str:
    from .sources.open import SOURCE_HELP

    return SOURCE_HELP


def _effects_help() -> str:
    """The effects and their default parameters, then an example (imports the effects library)."""
    from .commands.compare_args import effects_help

    return (effects_help() + "\ne.g. --sim-effects correlated_noise:length_px=5,depth_bias  or  "
            "--sim-effects gap.json")


def _open_hint(path) -> str:
    return f"open it with: rerun {path}"


def _check_outputs(*args, **kwargs):
    """:func:`elevmap.fileio.check_outputs`, imported when a command runs (it loads the model and numba,
    which ``elevmap --help`` does not need)."""
    from .fileio import check_outputs

    return check_outputs(*args, **kwargs)


def _cmd_demo(args) -> int:
    if args.noise_model:
        from .commands.demo import run_noise_demo

        _check_outputs({"--rrd": args.rrd}, args.overwrite)
        summary = run_noise_demo(args.rrd, seed=args.seed, show_progress=not args.no_progress)
        print(json.dumps(summary, indent=2))
        print(f"wrote {args.rrd}; {_open_hint(args.rrd)}")
    else:
        from .commands.demo import run_mapping_demo

        summary = run_mapping_demo(args.rrd, seed=args.seed, n_frames=args.frames, sensor=args.sensor,
                                   model=args.model, show_progress=not args.no_progress, spawn=args.spawn,
                                   overwrite=args.overwrite)
        _print_summary(summary)
        print(f"wrote {args.rrd} and {summary['png']}; {_open_hint(args.rrd)}")
    return 0


def _load_config(path):
    import tomllib

    from .pipeline import MappingConfig

    if path is None:
        return MappingConfig()
    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except FileNotFoundError:
        raise ValueError(f"{path}: no such config file") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid TOML ({exc})") from None
    bad = set(doc) - {"map"}
    if bad:
        raise ValueError(f"{path}: unknown table(s) {sorted(bad)}; expected [map] and [map.fusion]")
    table = doc.get("map", {})
    if isinstance(table, dict) and isinstance(table.get("sensor_model"), str) and table["sensor_model"]:
        table = dict(table)                                 # a relative model path is the config file's
        table["sensor_model"] = str(Path(path).parent / Path(table["sensor_model"]).expanduser())
    try:
        return MappingConfig.from_dict(table)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {exc}") from None


def _recorded_margins(src):
    """The valid-region margins a replayed recording names per camera (a pose file's wrapper looks inside)."""
    while src is not None:
        if getattr(src, "valid_margins_px", None) is not None:
            return src.valid_margins_px
        src = getattr(src, "source", None)
    return None


def _print_summary(summary: dict) -> None:
    shown = {k: v for k, v in summary.items() if k != "map"}
    print(json.dumps(shown, indent=2, default=float))
    err = summary.get("error")
    line = (f"{summary['frames']} frames, {summary['ms_per_frame_median']:.2f} ms per frame (median), "
            f"{100 * summary['known_fraction']:.1f}% of the map known")
    if "frames_per_s" in summary:
        line += f", {summary['frames_per_s']:.1f} frames/s end to end"
    if err:
        line += (f"; against the true terrain: median |error| {1000 * err['median_abs_m']:.1f} mm, RMSE on flat "
                 f"cells {1000 * err['flat_rmse_m']:.1f} mm and within {2} cells of step edges "
                 f"{1000 * err['edge_rmse_m']:.0f} mm, 2-sigma coverage {100 * err['coverage_2sigma']:.1f}%")
    print(line)


def _cmd_run(args) -> int:
    from .fileio import write_json_atomic
    from .pipeline import run_mapping
    from .sources.open import open_source

    if args.command == "replay" and not str(args.source).lower().endswith(".rrd"):
        raise ValueError(f"{args.source}: replay takes a rerun recording (.rrd); use `elevmap run` for others")
    config = _load_config(args.config)
    if args.model is not None:
        config = dataclasses.replace(config, sensor_model=args.model)
    if args.view_rate is not None:
        config = dataclasses.replace(config, view_rate_hz=args.view_rate)
    if args.png_depth:
        config = dataclasses.replace(config, png_depth=True)
    if args.valid_margin is not None:
        config = dataclasses.replace(config, valid_margin_px=args.valid_margin)
    if config.sensor_model:
        from noise_model.d435 import SensorModel

        SensorModel.load(config.sensor_model)               # a bad model file fails before any work
    _check_outputs({"--rrd": args.rrd, "--json": args.json}, args.overwrite,
                   inputs=[args.source, args.poses, args.config, args.intrinsics, config.sensor_model or None])
    if args.frames is not None and args.frames < 1:
        raise ValueError("--frames must be >= 1")
    if args.threads is not None:
        from noise_model.numba_config import resolve_threads

        resolve_threads(args.threads)                       # a bad count fails before any work
    ros = {k: getattr(args, k, None) for k in ("depth_topic", "map_frame", "base_frame", "bag_out", "map_rate",
                                               "foxglove")}
    if ros["bag_out"]:
        from .ros.bagout import bag_layout

        bag_layout(ros["bag_out"])
        _check_outputs({"--bag-out": ros["bag_out"], "--rrd": args.rrd, "--json": args.json}, args.overwrite,
                       inputs=[args.source, args.poses, args.config, args.intrinsics])
    if ros["map_rate"] is not None and not (ros["bag_out"] or ros["foxglove"] is not None):
        raise ValueError("--map-rate goes with --bag-out or --foxglove")
    src = open_source(args.source, poses=args.poses, intrinsics=args.intrinsics, frames=args.frames,
                      seed=args.seed, depth_topics=ros["depth_topic"], map_frame=ros["map_frame"],
                      base_frame=ros["base_frame"])
    total = len(src) if hasattr(src, "__len__") else None
    outputs = _ros_outputs(ros, getattr(src, "map_frame", None) or "map")
    try:
        with src if hasattr(src, "__enter__") else contextlib.nullcontext(src) as frames:
            summary = run_mapping(frames, config, rrd_path=args.rrd, spawn=args.spawn, total=total,
                                  show_progress=not args.no_progress, notes=f"elevmap {args.command} {args.source}",
                                  callbacks=list(outputs.values()), nthreads=args.threads,
                                  recorded_margins_px=_recorded_margins(src))
        for name, out in outputs.items():
            summary[name] = out.finish(summary["map"])
    except BaseException:
        for out in outputs.values():
            out.abort()
        raise
    if hasattr(src, "summary"):
        summary["source"] = src.summary()
    _print_summary(summary)
    if "source" in summary:
        s = summary["source"]
        print(f"{s['frames_mapped']} frames mapped, {s['frames_skipped']} skipped" + "".join(
            f"; {topic}: " + ", ".join(f"{n} {why}" for why, n in reasons.items())
            for topic, reasons in s["skipped"].items()))
    if "bag_out" in summary:
        print(f"wrote {summary['bag_out']['path']} ({summary['bag_out']['maps']} maps)")
    if args.json:
        write_json_atomic(args.json, {k: v for k, v in summary.items() if k != "map"})
    if args.rrd:
        print(f"wrote {args.rrd}; {_open_hint(args.rrd)}")
    return 0


def _ros_outputs(ros: dict, map_frame: str) -> dict:
    """The ``--bag-out`` and ``--foxglove`` consumers of a run (none asked: an empty dict)."""
    from .commands.bag import DEFAULT_MAP_RATE_HZ, BagOutput, LiveOutput

    rate = DEFAULT_MAP_RATE_HZ if ros["map_rate"] is None else ros["map_rate"]
    outputs = {}
    try:
        if ros["bag_out"]:
            outputs["bag_out"] = BagOutput(ros["bag_out"], map_frame=map_frame, rate_hz=rate)
        if ros["foxglove"] is not None:
            outputs["foxglove"] = LiveOutput(ros["foxglove"], map_frame=map_frame, rate_hz=rate)
            print(f"Foxglove: open a connection to {outputs['foxglove'].server.url}", file=sys.stderr)
    except BaseException:
        for out in outputs.values():
            out.abort()
        raise
    return outputs


def _cmd_bag_info(args) -> int:
    from .commands.bag import format_bag_info, run_bag_info
    from .fileio import write_json_atomic

    _check_outputs({"--json": args.json}, args.overwrite, inputs=[args.bag])
    info = run_bag_info(args.bag, depth_topics=args.depth_topic, map_frame=args.map_frame,
                        base_frame=args.base_frame)
    print(format_bag_info(info))
    if args.json:
        write_json_atomic(args.json, info)
        print(f"wrote {args.json}")
    return 0 if all(d["problem"] is None for d in info["depth"].values()) else 1


def _cmd_bench(args) -> int:
    from .commands.bench import GROUPS, format_table, run_bench
    from .fileio import write_json_atomic

    if args.frames < 1 or args.reference_frames < 1:
        raise ValueError("--frames and --reference-frames must be >= 1")
    _check_outputs({"--json": args.json}, args.overwrite)
    groups = GROUPS if args.only is None else tuple(g.strip() for g in args.only.split(",") if g.strip())
    report = run_bench(args.frames, args.reference_frames, args.threads, show_progress=not args.no_progress,
                       groups=groups)
    print(format_table(report))
    if args.json:
        write_json_atomic(args.json, report)
        print(f"wrote {args.json}")
    return 0


def _cmd_warmup(args) -> int:
    from .commands.warmup import WARMUP_GROUPS, run_warmup

    groups = WARMUP_GROUPS if args.only is None else tuple(g.strip() for g in args.only.split(",") if g.strip())
    run_warmup(groups, nthreads=args.threads)
    return 0


def _cmd_simulate(args) -> int:
    if args.validate is not None:
        return _cmd_validate(args)
    if args.json:
        raise ValueError("--json goes with --validate")
    if (args.grid is None) == (args.walk is None):
        raise ValueError("give exactly one of --grid paper and --walk SCENE")
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise ValueError(f"--size must be WIDTHxHEIGHT, got {args.size!r}") from None
    if args.frames is not None and args.frames < 1:
        raise ValueError("--frames must be >= 1")
    if args.preset is not None and args.sensor != "stereo":
        raise ValueError("--preset goes with --sensor stereo")
    preset = args.preset or "default"
    if args.grid:
        from .commands.simulate import simulate_capture_set

        if not args.out:
            raise ValueError("--grid needs --out DIR")
        cs = simulate_capture_set(args.out, "paper", n_frames=args.frames or 100, width=width, height=height,
                                  kind=args.kind, seed=args.seed, overwrite=args.overwrite,
                                  show_progress=not args.no_progress, sensor=args.sensor, preset=preset)
        print(f"wrote {len(cs.captures)} captures of {args.frames or 100} frames ({width}x{height}, {args.sensor} "
              f"sensor) to {args.out}")
        return 0
    from .pipeline import MappingConfig, run_mapping
    from .sources.simulated import SimulatedWalk

    if not args.rrd:
        raise ValueError("--walk needs --rrd PATH")
    _check_outputs({"--rrd": args.rrd}, args.overwrite)
    src = SimulatedWalk(args.walk, n_frames=args.frames, seed=args.seed, width=width, height=height,
                        drift=args.drift, sensor=args.sensor, preset=preset)
    summary = run_mapping(src, MappingConfig(), rrd_path=args.rrd, total=len(src),
                          show_progress=not args.no_progress, notes=f"elevmap simulate --walk {args.walk}")
    _print_summary(summary)
    print(f"wrote {args.rrd}; replay it with: elevmap replay {args.rrd}")
    return 0


def _cmd_validate(args) -> int:
    """``elevmap simulate --sensor stereo --validate [DIR] [--json PATH]``."""
    from .commands.simulate import validate_stereo

    if args.sensor != "stereo":
        raise ValueError("--validate checks the physical D435: give --sensor stereo")
    if args.grid or args.walk or args.out or args.rrd:
        raise ValueError("--validate takes no --grid, --walk, --out or --rrd")
    if args.frames is not None and args.frames < 1:
        raise ValueError("--frames must be >= 1")
    realdata = args.validate or None
    _check_outputs({"--json": args.json}, args.overwrite, inputs=[realdata] if realdata else [])
    status = validate_stereo(realdata, args.json, args.frames)
    if args.json:
        print(f"wrote {args.json}")
    return status


def _cmd_compare(args) -> int:
    from pathlib import Path

    from .commands.compare import COMPARE_MAX_VARIANCE, DEFAULT_CAP, json_ready, run_compare
    from .commands.compare_output import format_table
    from .fileio import write_json_atomic

    if not args.json:
        raise ValueError("--json PATH is required (the report)")
    gap = [args.reality] if args.reality.lower().endswith(".json") else []
    _check_outputs({"--json": args.json, "--rrd": args.rrd}, args.overwrite,
                   inputs=[args.sim_effects, args.fitted_model] + gap)
    if args.frames is not None and args.frames < 1:
        raise ValueError("--frames must be >= 1")
    if args.seeds is not None and args.seeds < 1:
        raise ValueError("--seeds must be >= 1")
    if args.seeds is not None and args.rrd:
        raise ValueError("--rrd records one seed: leave out --seeds")
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise ValueError(f"--size must be WIDTHxHEIGHT, got {args.size!r}") from None
    if args.preset is not None and args.reality != "stereo":
        raise ValueError("--preset goes with --reality stereo")
    fit_dir = Path(args.json).resolve().parent / "elevmap-compare-work"
    kw = dict(sim_effects=args.sim_effects, mappers=args.mappers, cap=DEFAULT_CAP if args.cap is None else args.cap,
              width=width, height=height, show_progress=not args.no_progress,
              max_variance=COMPARE_MAX_VARIANCE if args.max_variance is None else args.max_variance,
              reality=args.reality, preset=args.preset or "default", work_dir=args.work, fitted_model=args.fitted_model,
              fit_dir=fit_dir, settings=args.settings)
    if args.seeds is None:
        report = json_ready(run_compare(args.scene, args.frames, seed=args.seed, rrd_path=args.rrd, **kw))
        text = format_table(report)
    else:
        from .commands.compare_seeds import format_seeds_table, run_compare_seeds

        report = json_ready(run_compare_seeds(args.scene, args.frames, seeds=range(args.seed, args.seed + args.seeds),
                                              on_run=lambda r: print(format_table(json_ready(r)), flush=True), **kw))
        text = format_seeds_table(report)
    write_json_atomic(args.json, report)
    print(text)
    print(f"wrote {args.json}" + (f" and {args.rrd}; {_open_hint(args.rrd)}" if args.rrd else "")
          + (f" (work folder {args.work})" if args.work else ""))
    return 0


def _cmd_gap(args) -> int:
    from .commands.gap import format_selftest, format_summary, run_gap, run_realdata, run_selftest

    if args.jobs < 1:
        raise ValueError(f"--jobs must be >= 1, got {args.jobs}")
    config = None
    if args.min_shrink is not None or args.max_effects is not None or args.no_backfit:
        import dataclasses

        from noise_model.analysis.diagnosis import SelectionConfig

        if args.selftest or args.realdata:
            raise ValueError("--min-shrink, --max-effects and --no-backfit apply to REAL_CAPTURES (the self-test and "
                             "--realdata keep their settings)")
        config = SelectionConfig()
        if args.min_shrink is not None:
            if not (0.0 <= args.min_shrink < 1.0):
                raise ValueError(f"--min-shrink must be in [0, 1), got {args.min_shrink}")
            config = dataclasses.replace(config, min_shrink=float(args.min_shrink))
        if args.max_effects is not None:
            if args.max_effects < 1:
                raise ValueError(f"--max-effects must be >= 1, got {args.max_effects}")
            config = dataclasses.replace(config, max_effects=int(args.max_effects))
        if args.no_backfit:
            config = dataclasses.replace(config, backfit=False)
    if args.selftest:
        if args.real or args.realdata or args.rrd:
            raise ValueError("--selftest takes no REAL_CAPTURES, --realdata or --rrd")
        res = run_selftest(effects=args.effects, seed=args.seed, show_progress=not args.no_progress,
                           json_path=args.json, n_jobs=args.jobs, overwrite=args.overwrite)
        print(format_selftest(res))
        return 0 if res["passed"] else 1
    if args.realdata:
        if args.real:
            raise ValueError("give REAL_CAPTURES or --realdata, not both")
        report = run_realdata(args.realdata, json_path=args.json, rrd_path=args.rrd, effects=args.effects,
                              seed=args.seed, heldout=args.heldout or "none", show_progress=not args.no_progress,
                              overwrite=args.overwrite)
    else:
        if not args.real:
            raise ValueError("give REAL_CAPTURES (a capture-set folder), --realdata DIR or --selftest")
        report = run_gap(args.real if len(args.real) > 1 else args.real[0], json_path=args.json, rrd_path=args.rrd,
                         heldout=args.heldout or "auto", effects=args.effects, seed=args.seed,
                         show_progress=not args.no_progress, overwrite=args.overwrite, depth_bands=args.depth_bands,
                         direct=args.direct, n_jobs=args.jobs, config=config)
    print(format_summary(report))
    if args.json or args.rrd:
        print("wrote " + " and ".join(p for p in (args.json, args.rrd) if p)
              + (f"; {_open_hint(args.rrd)}" if args.rrd else ""))
    return 0


def _cmd_captures(args) -> int:
    from .commands.captures import format_summary, run_captures

    _check_outputs({"--json": args.json}, args.overwrite, inputs=[args.recording])
    report = run_captures(args.recording, args.frames, args.out, intrinsics=args.intrinsics,
                          baseline_m=args.baseline_m, max_planes=args.max_planes,
                          min_plane_fraction=args.min_plane_fraction, seed=args.seed, overwrite=args.overwrite)
    if args.json:
        from .fileio import write_json_atomic

        write_json_atomic(args.json, report)
    print(format_summary(report))
    print(f"wrote {report['out']}" + (f" and {args.json}" if args.json else ""))
    return 0


def _cmd_characterize(args) -> int:
    from .commands.characterize import format_summary, run_characterize

    report = run_characterize(args.captures, json_path=args.json, rrd_path=args.rrd, figures_dir=args.figures,
                              model_path=args.model, overwrite=args.overwrite, show_progress=not args.no_progress,
                              predict_dir=args.predict, only=args.only)
    print(format_summary(report))
    print(f"wrote {args.json}" + (f" and {args.rrd}" if args.rrd else ""))
    return 0 if report["model"] is not None else 1


COMMANDS = {"gap": _cmd_gap, "characterize": _cmd_characterize, "captures": _cmd_captures, "compare": _cmd_compare,
            "simulate": _cmd_simulate, "demo": _cmd_demo, "bench": _cmd_bench, "warmup": _cmd_warmup,
            "run": _cmd_run, "replay": _cmd_run,
            "bag-info": _cmd_bag_info}


def main(argv=None) -> int:
    """Run one command. Exit status: the command's (0 done), 2 a user error (``ValueError``), 1 the system
    refused a write (``OSError``: disk full, permissions), 128 + the signal number when interrupted
    (SIGINT, SIGTERM, SIGHUP; the outputs not finished are not written and no temporary file is left)."""
    args = build_parser().parse_args(argv)
    from .fileio import handle_signals

    try:
        with handle_signals():
            return COMMANDS[args.command](args)
    except ValueError as exc:
        print(f"elevmap {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"elevmap {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as exc:
        import signal

        signum = getattr(exc, "signum", signal.SIGINT)
        print(f"elevmap {args.command}: interrupted ({signal.Signals(signum).name}); unfinished outputs were not "
              "written", file=sys.stderr)
        return 128 + int(signum)


if __name__ == "__main__":
    sys.exit(main())
