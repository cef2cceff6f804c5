"""Feed a legged controller from the map: height scans at 50 Hz while a recording replays.

    python examples/controller_feed.py [recordings/stairs_walk.rrd]

The map is updated at the camera's rate; the controller asks for a height scan every 20 ms of
recording time (50 Hz, as the policy of Miki et al. 2022): 52 samples on rings around each of four
feet, and legged_gym's 17 x 11 grid around the base. Unknown samples are filled (here with the
base's foot height) and counted, as a policy trained with gaps expects.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from elevmap import Camera, ElevationMap, Mapper
from elevmap.sources import RrdSource
from noise_model import DEFAULT_VALID_MARGIN_PX
from noise_model.sim import DEFAULT_T_BASE_CAM

FEET_BASE = np.array([[0.35, 0.2, -0.4], [0.35, -0.2, -0.4], [-0.35, 0.2, -0.4], [-0.35, -0.2, -0.4]])
CONTROL_DT = 0.02


def main(path: str) -> None:
    emap = ElevationMap(8.0, 0.04)
    mapper = Mapper(emap)
    T_cam_base = np.linalg.inv(DEFAULT_T_BASE_CAM)
    next_control, scans, unknown, latency = None, 0, 0, []
    with RrdSource(path) as src:
        for frame in src:
            if frame.camera not in mapper.cameras:
                # the valid-region margin the recording was mapped with (0 if it predates the margin)
                margin_px = src.valid_margins_px.get(frame.camera, DEFAULT_VALID_MARGIN_PX)
                mapper.add_camera(Camera(frame.camera, frame.K, frame.width, frame.height,
                                         depth_scale=frame.depth_scale, valid_margin_px=margin_px))
            emap.move_to(frame.T_map_cam[:2, 3])
            mapper.integrate(frame.camera, frame.depth, T_map_cam=frame.T_map_cam, pose_cov=frame.pose_cov,
                             stamp=frame.stamp)
            T_map_base = frame.T_map_cam @ T_cam_base
            if next_control is None:
                next_control = frame.stamp
            while next_control <= frame.stamp:          # the 50 Hz controller ticks until the next frame
                t0 = time.perf_counter()
                rings = emap.height_scan(T_map_base, "foot_rings", feet_base=FEET_BASE)
                grid = emap.height_scan(T_map_base, "legged_gym")
                latency.append(time.perf_counter() - t0)
                heights = np.concatenate([rings.height, grid.height])
                unknown += int(np.isnan(heights).sum())
                heights = np.where(np.isnan(heights), T_map_base[2, 3] + FEET_BASE[0, 2], heights)
                scans += 1
                next_control += CONTROL_DT
    n = len(rings.height) + len(grid.height)
    print(f"{scans} height scans of {n} samples at 50 Hz; {100 * unknown / (scans * n):.1f}% of samples unknown "
          f"(filled); query time median {1e6 * np.median(latency):.0f} us, max {1e6 * np.max(latency):.0f} us")
    print(f"last scan: foot-ring heights {np.nanmin(rings.height):.3f}..{np.nanmax(rings.height):.3f} m, "
          f"base at z = {T_map_base[2, 3]:.3f} m")


if __name__ == "__main__":
    default = Path(__file__).resolve().parents[1] / "recordings" / "stairs_walk.rrd"
    main(sys.argv[1] if len(sys.argv) > 1 else str(default))
