"""``elevmap simulate``: capture sets on the paper's grid, and recordings of simulated walks.

Capture sets follow docs/capture-set-format.md (``d435-captures/1``). Each capture's frames are the
reference simulation of the paper's model of its own ``captures.json`` entry
(:func:`noise_model.sim.simulate_target` of :meth:`noise_model.sim.CaptureGeometry.from_capture_set_entry`),
so that a characterisation of them should give back the paper's coefficients, and the gap diagnosis
simulates exactly what was written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import noise_model as nm
from noise_model.sim import CaptureGeometry, simulate_target

from ..fileio import atomic_output, check_outputs

__all__ = ["paper_grid", "simulate_capture_set", "BOARD_WIDTH_M", "BOARD_HEIGHT_M", "BACKGROUND_M"]

#: The planar target of a simulated board capture (the capture-set spec's example) [m].
BOARD_WIDTH_M = 0.60
BOARD_HEIGHT_M = 0.90
#: A fronto-parallel wall behind boards [m].
BACKGROUND_M = 3.0


def paper_grid() -> list[tuple[float, float]]:
    """The paper's grid: 0.4 to 2.1 m every 0.1 m by 0 to 75 deg every 15 deg (108 settings)."""
    return [(round(0.4 + 0.1 * i, 2), 15.0 * j) for i in range(18) for j in range(6)]


def _capture_id(kind: str, distance: float, yaw: float) -> str:
    return f"{kind}_z{distance:.2f}_y{int(round(yaw)):02d}"


def simulate_capture_set(out, grid="paper", n_frames: int = 100, width: int = 424, height: int = 240,
                         kind: str = "board", seed: int = 0, model: nm.SensorModel = nm.D435,
                         overwrite: bool = False, show_progress: bool = True):
    """Write a capture set rendered with the reference simulation of the paper's model.

    Parameters
    ----------
    out : path
        Output folder (a new one, or ``overwrite``).
    grid : "paper" or sequence of (distance_m, yaw_deg)
        The settings.
    n_frames : int
        Frames per capture.
    width, height : int
        A D435 depth mode with default intrinsics (1280x720, 848x480, 640x480, 424x240).
    kind : {"board", "wall"}
        A 0.60 x 0.90 m board before a wall at 3 m, or an unbounded wall.
    seed : int
        Seed of the noise.
    model : noise_model.SensorModel
        The noise model simulated (the paper's by default).

    Returns
    -------
    elevmap.sources.captures.CaptureSet
        The set as read back.
    """
    from tqdm import tqdm

    from ..sources.captures import write_capture_set

    settings = paper_grid() if isinstance(grid, str) and grid == "paper" else [(float(d), float(y)) for d, y in grid]
    if isinstance(grid, str) and grid != "paper":
        raise ValueError(f"unknown grid {grid!r}; 'paper' or a list of (distance_m, yaw_deg)")
    if int(n_frames) < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames!r}")
    if kind not in ("board", "wall"):
        raise ValueError(f"kind must be 'board' or 'wall', got {kind!r}")
    out = Path(out)
    if (out / "captures.json").exists() and not overwrite:
        raise ValueError(f"{out} already holds a capture set; pass overwrite=True (--overwrite) to replace it")
    check_outputs({f"capture {_capture_id(kind, d, y)}": out / f"{_capture_id(kind, d, y)}.npy" for d, y in settings},
                  overwrite, create_folders=True)
    K = model.intrinsics(width, height)
    camera = {"model": "D435 (simulated: reference simulation of Ahn et al. 2019)", "width": int(width),
              "height": int(height), "fx": float(K[0, 0]), "fy": float(K[1, 1]), "ppx": float(K[0, 2]),
              "ppy": float(K[1, 2]), "depth_scale": 0.001, "baseline_m": model.baseline_m}
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)
    entries, written = [], []
    try:
        for distance, yaw in tqdm(settings, desc="simulate", unit="capture", disable=not show_progress):
            cid = _capture_id(kind, distance, yaw)
            target = {"kind": kind, "distance_m": distance, "yaw_deg": yaw, "pitch_deg": 0.0}
            if kind == "board":
                target.update(width_m=BOARD_WIDTH_M, height_m=BOARD_HEIGHT_M)
            entry = {"id": cid, "depth": f"{cid}.npy", "target": target,
                     "background_m": BACKGROUND_M if kind == "board" else None}
            geometry = CaptureGeometry.from_capture_set_entry(camera, entry)
            frames = simulate_target(geometry, int(n_frames), rng, model)
            path = out / f"{cid}.npy"
            with atomic_output(path, suffix=".npy") as tmp:
                with open(tmp, "wb") as fh:
                    np.save(fh, frames)
            written.append(path)
            entries.append((entry, None))
        return write_capture_set(out, camera, entries, overwrite=True,
                                 extra={"simulation": {"model": model.to_dict(), "seed": seed,
                                                       "frames": int(n_frames)}})
    except BaseException:
        for p in written:                       # no partial capture set is left behind
            p.unlink(missing_ok=True)
        raise
