"""Map a real RealSense recording with a pose file, and write a rerun recording of it.

    python examples/map_realsense_recording.py RECORDING [POSES] [--t265] [--out map.rrd]

RECORDING is anything :func:`elevmap.open_source` opens: a RealSense .bag/.db3, a folder of 16-bit depth
PNGs with its intrinsics JSON, a capture set, a rerun recording. POSES is a TUM text file or an Open3D
.log, interpolated to each frame's stamp (linear in position, slerp in rotation). ``--t265``: the poses
are those of a RealSense T265 tracking camera (y up, -z the initial heading), mounted with the D435 as
in polylidar-realsense; they are turned into a z-up map frame (:data:`elevmap.sources.poses.T265_T_POSE_CAM`,
:data:`elevmap.sources.poses.T_MAP_T265WORLD`). The map is fixed (6 m at 0.04 m, not following the
camera), as for a hand-held sequence over one floor.
"""

from __future__ import annotations

import argparse

from elevmap import MappingConfig, open_source, run_mapping
from elevmap.sources import read_pose_file, with_poses
from elevmap.sources.poses import T265_T_POSE_CAM, T_MAP_T265WORLD


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording")
    parser.add_argument("poses", nargs="?")
    parser.add_argument("--t265", action="store_true", help="POSES are a T265 trajectory (see above)")
    parser.add_argument("--out", default=None, help="rerun recording to write")
    args = parser.parse_args()
    if args.t265:
        if args.poses is None:
            parser.error("--t265 needs POSES")
        src = with_poses(open_source(args.recording), read_pose_file(args.poses), T_pose_cam=T265_T_POSE_CAM,
                         T_map_pose=T_MAP_T265WORLD)
    else:
        src = open_source(args.recording, poses=args.poses)
    with src:
        summary = run_mapping(src, MappingConfig(length_m=6.0, resolution_m=0.04, follow=False),
                              rrd_path=args.out, show_progress=True)
    m = summary["map"]
    h = m.known_layer("elevation")
    print(f"{summary['frames']} frames, {summary['ms_per_frame_median']:.1f} ms per frame, "
          f"{m.is_known().sum()} cells known, heights {h[m.is_known()].min():.3f}..{h[m.is_known()].max():.3f} m")
    if args.out:
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
