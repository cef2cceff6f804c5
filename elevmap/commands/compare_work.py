"""The work folder of ``elevmap compare``: rendered walks and fitted noise models, cached per reality and seed.

A comparison over several seeds renders the same walks again whenever the mappers change, and its
``fitted`` mapper needs a noise model characterised on a capture set simulated with the walk's own
reality (the workflow a user follows with a camera: ``elevmap simulate --grid paper`` stands for the
captures of the real camera, ``elevmap characterize`` fits the model). Both are slow on the physical
D435 (about 0.15 s per 424 x 240 frame on two cores) and depend only on their parameters, so they are
kept in a work folder::

    WORK/frames/<reality>-<scene>-seed<S>-<W>x<H>-f<N>.npz     the walk's frames (depth, poses)
    WORK/frames/<same>.json                                   the parameters and the frames' SHA-256
    WORK/fitted/<reality>-seed<S>-<W>x<H>-f<N>/captures/      the capture set (d435-captures/1)
    WORK/fitted/<same>/characterize.json, model.json          the characterisation and its model

A cached entry is used when its parameters equal the request's, including the library's version; the
cache does not see edits of the simulator's code, so delete the folder after changing it. Every file is
written atomically (:mod:`elevmap.fileio`): an interrupted run leaves the previous entry or none.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..fileio import atomic_output, write_json_atomic
from ..frame import Frame

__all__ = ["FIT_FRAMES", "FIT_SEED", "WorkDir", "reality_key"]

#: Frames per capture of the capture set the ``fitted`` mapper is characterised on: the paper's grid of
#: 108 boards x 20 frames gives per-pixel temporal sigmas of 5 % relative error (chi distribution with 19
#: degrees of freedom) over thousands of pixels per capture, far below the model's own spread.
FIT_FRAMES = 20
#: Seed of that capture set. A user characterises a camera once and maps many walks with the model, so
#: the capture set does not change with the walk's seed.
FIT_SEED = 0
#: Version of the cache's file layout.
CACHE_FORMAT = "elevmap-compare-cache/1"
#: What a cached characterisation measured: 3 adds the per-frame error and its sigma_z fit the model file
#: carries (:mod:`noise_model.analysis.frame_error`), 4 counts the frame-wide offset in that error, so a
#: model fitted before them is fitted again (from the same capture set).
CHARACTERIZE_VERSION = 4


def reality_key(reality: str, preset: str = "default", effects_digest: str | None = None) -> str:
    """A file-name-safe name of a reality: ``reference``, ``stereo-<preset>``, or ``gap-<digest>``."""
    if reality == "stereo":
        return f"stereo-{preset}"
    if reality == "reference":
        return "reference" if not effects_digest else f"reference-{effects_digest[:12]}"
    return f"gap-{(effects_digest or '')[:12]}"


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("elevmap")
    except PackageNotFoundError:
        return "unknown"


class WorkDir:
    """The caches of a comparison under one folder (created on first use).

    Parameters
    ----------
    path : path
        The folder. Its parent must exist.
    """

    def __init__(self, path):
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise ValueError(f"work folder {self.path} is a file, not a folder")
        if not self.path.parent.is_dir():
            raise ValueError(f"work folder {self.path}: its parent folder does not exist")

    # -----------------------------------------------------------------------------------------
    # frames
    # -----------------------------------------------------------------------------------------
    def frames(self, params: dict, render):
        """The frames of a walk: cached ones whose parameters equal ``params``, else ``render()``'s, saved.

        Parameters
        ----------
        params : dict
            JSON-serialisable: ``reality`` (its key), ``scene``, ``seed``, ``width``, ``height``, ``frames``
            (None: the whole walk) and whatever else decides the depth.
        render : callable
            ``render() -> list of Frame``, called when nothing matching is cached.

        Returns
        -------
        frames : list of Frame
        cached : bool
            True when read from the folder.
        """
        n = "all" if params.get("frames") is None else int(params["frames"])
        stem = (f"{params['reality']}-{params['scene']}-seed{int(params['seed'])}-"
                f"{params['width']}x{params['height']}-f{n}")
        npz, meta = self.path / "frames" / f"{stem}.npz", self.path / "frames" / f"{stem}.json"
        key = {"format": CACHE_FORMAT, "version": _version(), **params}
        if npz.is_file() and meta.is_file():
            try:
                stored = json.loads(meta.read_text())
            except (OSError, ValueError):
                stored = None
            if isinstance(stored, dict) and stored.get("key") == json.loads(json.dumps(key)):
                frames = _read_frames(npz)
                from .compare import frames_digest

                if frames_digest(frames) == stored.get("frames_digest"):
                    return frames, True
        frames = render()
        from .compare import frames_digest

        (self.path / "frames").mkdir(parents=True, exist_ok=True)
        _write_frames(npz, frames)
        write_json_atomic(meta, {"key": key, "frames_digest": frames_digest(frames)})
        return frames, False

    # -----------------------------------------------------------------------------------------
    # the fitted model
    # -----------------------------------------------------------------------------------------
    def fitted_model(self, reality: str, *, sensor: str, preset: str = "default", width: int = 424,
                     height: int = 240, seed: int = FIT_SEED, n_frames: int = FIT_FRAMES,
                     show_progress: bool = False):
        """The model ``elevmap characterize`` fits on the paper's grid simulated with this reality.

        Parameters
        ----------
        reality : str
            The reality's key (:func:`reality_key`).
        sensor : {"reference", "stereo"}
            What simulates the capture set (``elevmap simulate --grid paper --sensor SENSOR``).
        preset : str
            Matcher preset of the physical D435.
        width, height : int
            Depth mode [px]: the walk's.
        seed, n_frames : int
            Seed and frames per capture of the capture set.

        Returns
        -------
        model : noise_model.SensorModel
        info : dict
            ``model_path``, ``family``, ``fit`` (coefficients or sigma_d), ``captures``, ``cached``.

        Raises
        ------
        ValueError
            The characterisation found no model.
        """
        import noise_model as nm

        from .characterize import run_characterize
        from .simulate import simulate_capture_set

        folder = self.path / "fitted" / f"{reality}-seed{int(seed)}-{int(width)}x{int(height)}-f{int(n_frames)}"
        captures, report_path, model_path = folder / "captures", folder / "characterize.json", folder / "model.json"
        key_path = folder / "key.json"
        key = {"format": CACHE_FORMAT, "version": _version(), "reality": reality, "sensor": sensor,
               "preset": preset, "width": int(width), "height": int(height), "seed": int(seed),
               "frames": int(n_frames), "characterize": CHARACTERIZE_VERSION}
        cached = False
        if key_path.is_file() and model_path.is_file() and report_path.is_file():
            try:
                cached = json.loads(key_path.read_text()) == key
            except (OSError, ValueError):
                cached = False
        if not cached:
            folder.mkdir(parents=True, exist_ok=True)
            if not (captures / "captures.json").is_file() or not _same_set(captures, key):
                simulate_capture_set(captures, "paper", n_frames=int(n_frames), width=int(width), height=int(height),
                                     seed=int(seed), sensor=sensor, preset=preset, overwrite=True,
                                     show_progress=show_progress)
            report = run_characterize(captures, json_path=report_path, model_path=model_path, overwrite=True,
                                      show_progress=show_progress)
            if report.get("model") is None or not model_path.is_file():
                raise ValueError(f"characterising the capture set {captures} found no model "
                                 f"({report.get('fit_reason') or 'no fit'}); see {report_path}")
            write_json_atomic(key_path, key)
        report = json.loads(report_path.read_text())
        model = nm.SensorModel.load(model_path)
        fit = (report.get("fit_disparity") or {}) if model.family == "disparity" else (report.get("fit") or {})
        info = {"model_path": str(model_path), "family": model.family, "captures": str(captures),
                "cached": cached, "model": model.to_dict(),
                "fit": {k: fit.get(k) for k in ("coefficients", "s0_px", "s1_px_per_rad2", "residual_rms_rel")
                        if k in fit}}
        return model, info


def _same_set(captures: Path, key: dict) -> bool:
    """Whether an existing capture set was simulated with the key's sensor, seed, size and frames."""
    try:
        doc = json.loads((captures / "captures.json").read_text())
    except (OSError, ValueError):
        return False
    sim = doc.get("simulation") or {}
    cam = doc.get("camera") or {}
    sensor_ok = (sim.get("sensor") == "stereo" and sim.get("preset") == key["preset"]) if key["sensor"] == "stereo" \
        else ("model" in sim and sim.get("sensor") in (None, "reference"))
    return (sensor_ok and sim.get("seed") == key["seed"] and sim.get("frames") == key["frames"]
            and cam.get("width") == key["width"] and cam.get("height") == key["height"])


def _write_frames(path: Path, frames) -> None:
    if not frames:
        raise ValueError("no frames to cache")
    arrays = {"depth": np.stack([f.depth for f in frames]), "K": np.stack([f.K for f in frames]),
              "stamp": np.array([f.stamp for f in frames], dtype=np.float64),
              "T_map_cam": np.stack([f.T_map_cam for f in frames]),
              "depth_scale": np.array([np.nan if f.depth_scale is None else f.depth_scale for f in frames]),
              "camera": np.array([f.camera for f in frames]), "index": np.array([f.index for f in frames])}
    if all(f.pose_cov is not None for f in frames):
        arrays["pose_cov"] = np.stack([f.pose_cov for f in frames])
    elif any(f.pose_cov is not None for f in frames):
        raise ValueError("frames with and without pose covariance cannot be cached together")
    with atomic_output(path, ".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def _read_frames(path: Path) -> list[Frame]:
    with np.load(path, allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    n = d["depth"].shape[0]
    cov = d.get("pose_cov")
    return [Frame(depth=d["depth"][k], K=d["K"][k], stamp=float(d["stamp"][k]), T_map_cam=d["T_map_cam"][k],
                  depth_scale=None if np.isnan(d["depth_scale"][k]) else float(d["depth_scale"][k]),
                  pose_cov=None if cov is None else cov[k], camera=str(d["camera"][k]), index=int(d["index"][k]))
            for k in range(n)]
