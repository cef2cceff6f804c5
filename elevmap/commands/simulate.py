"""``elevmap simulate``: capture sets on the paper's grid, recordings of simulated walks, and the
validation of the physical D435.

Capture sets follow docs/capture-set-format.md (``d435-captures/1``). By default each capture's frames
are the reference simulation of the paper's model of its own ``captures.json`` entry
(:func:`noise_model.sim.simulate_target` of :meth:`noise_model.sim.CaptureGeometry.from_capture_set_entry`),
so that a characterisation of them should give back the paper's coefficients, and the gap diagnosis
simulates exactly what was written. With ``sensor="stereo"`` the physical D435 of
:mod:`noise_model.sim.stereo` sees the same targets (:func:`noise_model.sim.targets.simulate_target_stereo`):
a reality nobody wrote as a formula, for the characterisation and the gap tool to measure.
:func:`validate_stereo` prints the physical model's validation figures next to their targets
(docs/physical-d435.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import noise_model as nm
from noise_model.sim import CaptureGeometry, simulate_target
from noise_model.sim.targets import simulate_target_stereo

from ..fileio import atomic_folder, check_folder_output

__all__ = ["paper_grid", "simulate_capture_set", "validate_stereo", "SENSORS", "BOARD_WIDTH_M", "BOARD_HEIGHT_M",
           "BACKGROUND_M"]

#: What makes a capture set's frames: the reference simulation of the paper's model, or the physical D435.
SENSORS = ("reference", "stereo")

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
                         overwrite: bool = False, show_progress: bool = True, sensor: str = "reference",
                         preset: str = "default"):
    """Write a capture set rendered with the reference simulation of the paper's model, or the physical D435.

    Parameters
    ----------
    out : path
        Output folder: a new or empty one, or with ``overwrite`` an earlier capture set holding nothing else.
        The set is built in a temporary folder beside it and swapped in once complete, so an interrupted
        run leaves the previous set as it was (:func:`elevmap.fileio.atomic_folder`).
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
        The noise model simulated by the reference sensor (the paper's by default); its intrinsics and
        baseline are the camera's for either sensor.
    sensor : {"reference", "stereo"}
        The reference simulation (default), or the physical D435 (each capture rendered once, its
        frames matched with fresh sensor noise; the size must be a D435 depth mode).
    preset : str
        Matcher preset of the physical D435 ("default", "high_accuracy").

    Returns
    -------
    elevmap.sources.captures.CaptureSet
        The set as read back.
    """
    from tqdm import tqdm

    from ..sources.captures import capture_set_files, read_capture_set, write_capture_set

    settings = paper_grid() if isinstance(grid, str) and grid == "paper" else [(float(d), float(y)) for d, y in grid]
    if isinstance(grid, str) and grid != "paper":
        raise ValueError(f"unknown grid {grid!r}; 'paper' or a list of (distance_m, yaw_deg)")
    if int(n_frames) < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames!r}")
    if kind not in ("board", "wall"):
        raise ValueError(f"kind must be 'board' or 'wall', got {kind!r}")
    if sensor not in SENSORS:
        raise ValueError(f"unknown sensor {sensor!r}; sensors: {', '.join(SENSORS)}")
    stereo = None
    if sensor == "stereo":
        from noise_model.sim.stereo import StereoD435
        from noise_model.sim.stereo.matcher import preset as matcher_preset

        matcher_preset(preset).check_size(width, height)        # the preset and the size, before anything else
        stereo = StereoD435(int(width), int(height), K=model.intrinsics(width, height), baseline_m=model.baseline_m,
                            matcher=preset)
    out = check_folder_output("--out", out, overwrite, capture_set_files, kind="a capture set")
    K = model.intrinsics(width, height)
    what = ("reference simulation of Ahn et al. 2019" if stereo is None
            else f"physical active-stereo model, matcher preset {preset}")
    camera = {"model": f"D435 (simulated: {what})", "width": int(width),
              "height": int(height), "fx": float(K[0, 0]), "fy": float(K[1, 1]), "ppx": float(K[0, 2]),
              "ppy": float(K[1, 2]), "depth_scale": 0.001, "baseline_m": model.baseline_m}
    rng = np.random.default_rng(seed)
    entries = []
    with atomic_folder(out) as tmp:         # the previous set stays whole until the new one is complete
        for distance, yaw in tqdm(settings, desc="simulate", unit="capture", disable=not show_progress):
            cid = _capture_id(kind, distance, yaw)
            target = {"kind": kind, "distance_m": distance, "yaw_deg": yaw, "pitch_deg": 0.0}
            if kind == "board":
                target.update(width_m=BOARD_WIDTH_M, height_m=BOARD_HEIGHT_M)
            entry = {"id": cid, "depth": f"{cid}.npy", "target": target,
                     "background_m": BACKGROUND_M if kind == "board" else None}
            geometry = CaptureGeometry.from_capture_set_entry(camera, entry)
            if stereo is None:
                frames = simulate_target(geometry, int(n_frames), rng, model)
            else:
                frames = simulate_target_stereo(geometry, int(n_frames), rng, camera=stereo)
            with open(tmp / f"{cid}.npy", "wb") as fh:
                np.save(fh, frames)
            entries.append((entry, None))
        simulation = ({"model": model.to_dict(), "seed": seed, "frames": int(n_frames)} if stereo is None else
                      {"sensor": "stereo", "preset": preset, "seed": seed, "frames": int(n_frames)})
        write_capture_set(tmp, camera, entries, overwrite=True, extra={"simulation": simulation})
    return read_capture_set(out)


def validate_stereo(realdata=None, json_path=None, n_frames: int | None = None) -> int:
    """The physical D435's validation figures, each printed next to its target.

    Runs ``noise_model.sim.stereo.validation.main`` (docs/physical-d435.md): the simulated figures,
    and with ``realdata`` (a folder of the real D435 recordings it knows) the comparisons with them.

    Parameters
    ----------
    realdata : path, optional
        Folder of real recordings.
    json_path : path, optional
        Write the figures there (the caller has checked the path).
    n_frames : int, optional
        Frames per setting (the validation's own default when None).

    Returns
    -------
    int
        The validation's exit status.
    """
    from noise_model.sim.stereo import validation

    if realdata is not None and not Path(realdata).is_dir():
        raise ValueError(f"{realdata}: no such folder (the real recordings to validate against)")
    argv = []
    if realdata is not None:
        argv += ["--realdata", str(realdata)]
    if json_path is not None:
        argv += ["--json", str(json_path)]
    if n_frames is not None:
        argv += ["--frames", str(int(n_frames))]
    return int(validation.main(argv) or 0)
