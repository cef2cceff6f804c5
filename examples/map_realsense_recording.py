"""Map a real RealSense recording with a pose file, and write a rerun recording of it.

    .venv/bin/python examples/map_realsense_recording.py RECORDING [POSES] [--out map.rrd]

RECORDING is a RealSense .bag/.db3 or a folder of 16-bit depth PNGs with its intrinsics JSON;
POSES a TUM text file or an Open3D .log (interpolated to each frame's stamp: linear in position,
slerp in rotation). Without arguments it maps the D435i + T265 floor sequence of
../shared/realdata/polylidar_d435i_floor_filtered, whose poses are the T265's (y up), turned into a
z-up map frame with the camera mounted as in polylidar.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from elevmap.pipeline import MappingConfig, run_mapping
from elevmap.sources.open import open_source
from elevmap.sources.poses import T265_T_POSE_CAM, T_MAP_T265WORLD, read_pose_file, with_poses

POLYLIDAR = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "polylidar_d435i_floor_filtered"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", nargs="?")
    parser.add_argument("poses", nargs="?")
    parser.add_argument("--out", default=None, help="rerun recording to write")
    args = parser.parse_args()
    if args.recording is None:
        if not POLYLIDAR.is_dir():
            raise SystemExit(f"give a recording: the default {POLYLIDAR} is not on this machine")
        src = with_poses(open_source(str(POLYLIDAR)), read_pose_file(POLYLIDAR / "trajectory.log"),
                         T_pose_cam=T265_T_POSE_CAM, T_map_pose=T_MAP_T265WORLD)
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
