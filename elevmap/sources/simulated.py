"""The simulator as a source: a robot walking through a scene, seen by a simulated D435.

The D435 is the reference simulation of the paper's model (the default) or, with ``sensor="stereo"``,
the physical one of :mod:`noise_model.sim.stereo` (projector, infrared pair, D4 matcher: its noise
emerges). Frames carry the true terrain (``Frame.truth["height"]``: xy (M, 2) -> height (M,) [m]) so
that maps can be scored against it.
"""

from __future__ import annotations

import numpy as np

import noise_model as nm
from noise_model.sim import Scene, simulate_walk

from ..frame import Frame

__all__ = ["SimulatedWalk", "demo_scene", "SCENES", "SENSORS"]

SCENES = ("demo", "stairs", "boxes", "slope", "rough")
#: What can make a simulated walk's depth: the reference simulation or the physical D435.
SENSORS = ("reference", "stereo")


def demo_scene(rng: np.random.Generator) -> tuple[Scene, np.ndarray]:
    """A box field (4-15 cm boxes over x in [0.8, 2.8] m) followed by a staircase (6 x 0.17 m up from
    x = 3.4 m) and its landing; the path runs straight along +x through both. Returns (scene, path)."""
    stairs = Scene.stairs_scene(start_x_m=3.4, landing_m=6.0)
    boxes = Scene.box_field(rng, n_boxes=12, x_range=(0.8, 2.8), y_range=(-1.4, 1.4), height_range=(0.04, 0.15),
                            size_range=(0.2, 0.5))
    scene = stairs.with_primitives(*boxes.primitives)
    return scene, np.array([[-0.6, 0.0], [5.6, 0.0]])


class SimulatedWalk:
    """Frames of a simulated walk.

    Parameters
    ----------
    scene : str or noise_model.sim.scene.Scene
        "demo" (box field then stairs), "stairs", "boxes", "slope", "rough", or a Scene.
    n_frames : int, optional
        Frames to render (the whole path by default).
    seed : int
        Seed of the scene's randomness, the noise and the drift.
    width, height : int
        D435 mode (default 424x240, the decimated stream ANYmal maps from).
    rate_hz : float
        Frame rate [Hz].
    noise : {"reference", "none"}
        With the reference sensor: the paper's model as the reference simulation defines it, or none.
    drift : bool
        Odometry drift: the poses reported are drifted, with their covariance.
    effects : sequence of callables, optional
        Extra depth effects of the reference sensor (see :func:`noise_model.sim.add_noise`).
    path : (K, 2) array_like, optional
        Waypoints [m]; by default a straight walk through the scene along +x.
    camera : str
        Name of the camera in the frames.
    sensor : {"reference", "stereo"}
        The reference simulation (default) or the physical D435 (``noise_model.sim.stereo``; the size
        must be a D435 depth mode; no ``noise="none"`` or effects: it makes its own noise).
    preset : str
        Matcher preset of the physical D435 ("default", "high_accuracy").
    """

    def __init__(self, scene="demo", n_frames: int | None = None, seed: int = 0, width: int = 424,
                 height: int = 240, rate_hz: float = 10.0, noise: str = "reference", drift: bool = False,
                 effects=None, path=None, camera: str = "front", sensor: str = "reference", preset: str = "default"):
        if sensor not in SENSORS:
            raise ValueError(f"unknown sensor {sensor!r}; sensors: {', '.join(SENSORS)}")
        if sensor == "stereo":
            from noise_model.sim.stereo import PRESETS

            if preset not in PRESETS:
                raise ValueError(f"unknown matcher preset {preset!r}; presets: {', '.join(sorted(PRESETS))}")
            if noise != "reference" or effects:
                raise ValueError("the physical D435 (sensor 'stereo') makes its own noise: it takes no noise "
                                 "'none' and no effects")
        self.sensor, self.preset = sensor, preset
        self.rng = np.random.default_rng(seed)
        default_path = np.array([[-0.6, 0.0], [5.0, 0.0]])
        if isinstance(scene, Scene):
            self.scene, self.name = scene, "custom"
        elif scene == "demo":
            self.scene, default_path = demo_scene(self.rng)
            self.name = "demo"
        elif scene in SCENES:
            self.scene, self.name = Scene.named(scene, rng=self.rng), scene
        else:
            raise ValueError(f"unknown scene {scene!r}; scenes: {', '.join(SCENES)}")
        self.path = default_path if path is None else np.asarray(path, dtype=np.float64)
        if n_frames is not None and int(n_frames) < 1:
            raise ValueError(f"n_frames must be >= 1, got {n_frames!r}")
        self.n_frames = n_frames
        self.width, self.height = int(width), int(height)
        self.K = nm.D435.intrinsics(self.width, self.height)
        self._stereo = None
        if sensor == "stereo":
            from noise_model.sim.stereo import StereoD435

            self._stereo = StereoD435(self.width, self.height, K=self.K, matcher=preset)   # checks the size
        self.rate_hz = float(rate_hz)
        self.noise, self.drift, self.effects, self.camera = noise, bool(drift), effects, camera
        self._len = None

    def __len__(self) -> int:
        if self._len is None:
            if self.n_frames is not None:
                self._len = int(self.n_frames)
            else:
                from noise_model.sim import walk

                self._len = len(walk(self.path, rate_hz=self.rate_hz))
        return self._len

    def truth_height(self, xy) -> np.ndarray:
        """True terrain height at xy (M, 2) [m]."""
        return self.scene.height_at(np.asarray(xy, dtype=np.float64))

    def __iter__(self):
        gen = simulate_walk(self.scene, self.K, self.width, self.height, n_frames=self.n_frames, path=self.path,
                            rng=self.rng, noise=self.noise, effects=self.effects, drift=self.drift,
                            rate_hz=self.rate_hz, sensor=self._stereo or "reference")
        for f in gen:
            yield Frame(f["depth"], f["K"], f["depth_scale"], f["stamp"], T_map_cam=f["T_map_cam"],
                        pose_cov=f["pose_cov"], camera=self.camera, index=f["index"],
                        truth={"height": self.truth_height, "T_map_cam": f["T_map_cam_true"]})

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None
