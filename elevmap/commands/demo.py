"""``elevmap demo``: the built-in demonstrations, written to a rerun ``.rrd`` file.

The mapping demo (:func:`run_mapping_demo`, ``elevmap demo``)
--------------------------------------------------------------
A simulated legged robot walks straight along +x, from x = -0.6 m to 5.6 m at 0.5 m/s, across a field
of twelve 4-15 cm boxes (x in [0.8, 2.8] m) and up six 0.17 m steps (from x = 3.4 m) to a landing. Its
D435 (424x240 at 10 Hz, 0.45 m above the base, pitched 30 deg down) has the paper's noise (the reference
simulation). Every frame goes through :class:`elevmap.Mapper` into an 8 m map at 0.04 m that follows
the robot (:func:`elevmap.pipeline.run_mapping`, default :class:`elevmap.pipeline.MappingConfig`), and the
map is scored against the true terrain. Outputs: the recording (see :mod:`elevmap.pipeline` for its
entities) and, beside it, a PNG of the final map (:func:`elevmap.viz.plots.plot_map_against_truth`:
height, sigma and error against the truth side by side; ``demo.png`` beside ``demo.rrd``).

The noise-model demo (:func:`run_noise_demo`, ``elevmap demo --noise-model``)
------------------------------------------------------------------------------
Four captures of an unbounded planar wall (``noise_model.sim.targets``, the reference simulation of the Ahn et
al. (2019) model) are placed side by side in the ``world`` frame (right-handed, z up, [m]):

====== ============ ========= ==========================================
camera distance [m] yaw [deg] pose
====== ============ ========= ==========================================
0      1.0          0         T_world_cam exact
1      1.0          45        T_world_cam exact
2      2.0          0         T_world_cam exact
3      2.0          45        T_world_cam with an *example* pose covariance
====== ============ ========= ==========================================

Every camera looks along world +x from (0, -SPACING_M i, CAMERA_HEIGHT_M). For each capture the demo
logs the pinhole and one noisy depth frame, runs the per-pixel chain of ``noise_model`` (deproject,
incidence angles, depth edges, camera-frame covariances, map-frame covariances) on it and logs a
random subsample of the points with their 2-sigma covariance ellipsoids, coloured by sigma_z. Two
charts show sigma_z(z, theta) of the model and the paper's equation (1).

A sanity figure is computed over ``n_frames`` simulated frames per capture: the RMS of the depth
residual against the true z, against the RMS of the model's sigma_z at the true z and theta over the
same pixels (they agree when simulator and model agree), and the sigma_z the pipeline *predicts* from
the noisy frame alone (its estimated incidence angles and depth edges).

Entity paths (see :mod:`elevmap.viz`)::

    world                                   ViewCoordinates RIGHT_HAND_Z_UP
    world/camera_<i>                        Transform3D T_world_cam
    world/camera_<i>/depth                  Pinhole (RDF) + DepthImage (1 unit = 1 mm)
    world/points_cov/camera_<i>/points      Points3D, world frame, coloured by sigma_z
    world/points_cov/camera_<i>/ellipsoids  Ellipsoids3D, 2 sigma, world-frame covariances from the
                                            pipeline (estimated theta and depth edges)
    world/points_cov/camera_<i>/ellipsoids_true_theta
                                            the same at the true theta, no edges (hidden at start)
    plots/sigma_z_vs_z, plots/sigma_z_vs_theta   charts (sigma in mm, log scale)
    notes                                   Markdown: what is shown and the summary figures
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

import noise_model as nm
from noise_model.sim import render_planar_target, simulate_target_frames

from .. import viz
from ..fileio import check_outputs

__all__ = ["run_noise_demo", "run_mapping_demo", "demo_png_path", "CAPTURES", "EXAMPLE_POSE_COV", "R_WORLD_CAM"]

#: (distance [m], yaw [deg]) of the four captures.
CAPTURES = ((1.0, 0.0), (1.0, 45.0), (2.0, 0.0), (2.0, 45.0))
#: Index of the capture that gets :data:`EXAMPLE_POSE_COV`.
POSE_COV_CAPTURE = 3
#: Example pose covariance [m^2, rad^2] of xi = (x, y, z, rot_x, rot_y, rot_z) in the world frame
#: (``noise_model.to_map_frame`` convention): 1 cm per translation axis, 0.5 deg per rotation axis,
#: uncorrelated. An illustration only, not a measured odometry error.
EXAMPLE_POSE_COV = np.diag([0.01 ** 2] * 3 + [math.radians(0.5) ** 2] * 3)
#: Camera axes in the world frame (columns): camera x (right) = world -y, camera y (down) = world -z,
#: camera z (forward) = world +x.
R_WORLD_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
#: Lateral spacing of the cameras along world -y [m], and their height [m].
SPACING_M = 6.0
CAMERA_HEIGHT_M = 1.0
#: Working range [m]: depths outside it are dropped (set to 0 = no data in the logged image).
RANGE_M = (0.3, 4.0)
DEPTH_SCALE = 0.001  # [m per depth unit]
#: Colour scale of sigma_z [m] (log): 2 mm (blue) to 200 mm (red).
SIGMA_COLOR_RANGE_M = (0.002, 0.2)
#: Initial 3-D eye: behind the row of cameras, above, looking at the walls [m, world frame].
EYE_POSITION = (-7.0, 3.0, 7.0)
EYE_LOOK_TARGET = (2.0, -9.0, 0.5)
THETAS_DEG = (0, 15, 30, 45, 60, 75)
Z_FIXED_M = (0.5, 1.0, 2.0, 3.0)


def _T_world_cam(i: int) -> np.ndarray:
    """Pose of camera ``i``: p_world = R_WORLD_CAM p_cam + t, shape (4, 4)."""
    T = np.eye(4)
    T[:3, :3] = R_WORLD_CAM
    T[:3, 3] = [0.0, -SPACING_M * i, CAMERA_HEIGHT_M]
    return T


def _capture(i, distance_m, yaw_deg, K, width, height, n_frames, n_points, rng):
    """Simulate one capture; return its statistics and the data to log (no rerun here)."""
    frames = simulate_target_frames(K, width, height, distance_m, n_frames, rng, yaw_deg=yaw_deg,
                                    depth_scale=DEPTH_SCALE)
    z_true, theta_true = render_planar_target(K, width, height, distance_m, yaw_deg)
    lo, hi = RANGE_M
    with np.errstate(invalid="ignore"):
        in_range = np.isfinite(z_true) & (z_true >= lo) & (z_true <= hi)     # (H, W)
    sigma_true = np.zeros_like(z_true)
    sigma_true[in_range] = nm.axial_sigma(z_true[in_range], theta_true[in_range])

    # -- simulator against the model: residual against the true z, selected on the TRUE z only ----
    sel = in_range[None] & (frames > 0)                                       # (F, H, W)
    res = (frames.astype(np.float64) * DEPTH_SCALE - z_true[None])[sel]       # [m]
    sig = np.broadcast_to(sigma_true, frames.shape)[sel]                      # [m]
    measured_std = float(np.sqrt(np.mean(res ** 2)))
    model_sigma = float(np.sqrt(np.mean(sig ** 2)))
    normalized_std = float(np.sqrt(np.mean((res / sig) ** 2)))

    # -- the noise-model pipeline on each noisy frame -------------------------------------------------
    fx, fy = float(K[0, 0]), float(K[1, 1])
    ratios, dtheta, edge_frac, pipe_var = [], [], [], []
    for f, frame in enumerate(frames):
        z_m = nm.depth_to_metres(frame, DEPTH_SCALE, min_depth_m=lo, max_depth_m=hi)   # (H, W) [m]
        points_cam = nm.deproject(z_m, K)                                               # (H, W, 3) [m]
        theta = nm.incidence_angles(points_cam)                                          # (H, W) [rad]
        edge_left, edge_right = nm.depth_edges(z_m, theta=theta)
        valid = np.isfinite(z_m)
        cov_cam = nm.point_covariances(points_cam[valid], theta[valid], edge_left[valid], edge_right[valid],
                                       fx=fx, fy=fy)                                     # (N, 3, 3) [m^2]
        # Sigma_cam[2, 2] = sigma_z^2 exactly (r_z = 1; the lateral terms act on x and y only)
        both = in_range[valid]
        pipe_var.append(cov_cam[both, 2, 2])
        ratios.append(np.sqrt(cov_cam[both, 2, 2]) / sigma_true[valid][both])
        dtheta.append(theta[valid][both] - theta_true[valid][both])
        edge_frac.append((edge_left | edge_right)[valid][both])
        if f == 0:
            logged_depth = np.where(valid, frame, 0).astype(np.uint16)
            points_valid = points_cam[valid]
            n = min(int(n_points), len(points_valid))
            idx = np.sort(rng.choice(len(points_valid), size=n, replace=False))
            T = _T_world_cam(i)
            pose_cov = EXAMPLE_POSE_COV if i == POSE_COV_CAPTURE else None
            points_world = points_valid[idx] @ T[:3, :3].T + T[:3, 3]                   # (n, 3) [m]
            cov_world = nm.to_map_frame(cov_cam[idx], points_valid[idx], T, pose_cov)    # (n, 3, 3) [m^2]
            sigma_z_sub = np.sqrt(cov_cam[idx, 2, 2])                                    # (n,) [m]
            # the same points under the model at the TRUE incidence angle, no edges (what was simulated)
            cov_cam_true = nm.point_covariances(points_valid[idx], theta_true[valid][idx], fx=fx, fy=fy)
            cov_world_true = nm.to_map_frame(cov_cam_true, points_valid[idx], T, pose_cov)
            sigma_z_true_sub = np.sqrt(cov_cam_true[:, 2, 2])
    ratios = np.concatenate(ratios)
    stats = {
        "camera": f"camera_{i}",
        "distance_m": float(distance_m),
        "yaw_deg": float(yaw_deg),
        "n_frames": int(len(frames)),
        "n_samples": int(res.size),
        "measured_std_m": measured_std,
        "model_sigma_m": model_sigma,
        "measured_over_model": measured_std / model_sigma,
        "normalized_residual_std": normalized_std,
        "pipeline_sigma_m": float(np.sqrt(np.mean(np.concatenate(pipe_var)))),
        "pipeline_over_model_median": float(np.median(ratios)),
        "theta_error_median_deg": float(np.degrees(np.median(np.concatenate(dtheta)))),
        "edge_fraction": float(np.mean(np.concatenate(edge_frac))),
        "pose_cov": pose_cov is not None,
        "points_logged": int(n),
    }
    log_data = {
        "T_world_cam": T, "depth_u16": logged_depth, "points_world": points_world, "cov_world": cov_world,
        "sigma_z": sigma_z_sub, "cov_world_true": cov_world_true, "sigma_z_true": sigma_z_true_sub,
    }
    return stats, log_data


def _log_curves(rec) -> None:
    """sigma_z of the model over z and over theta, with the paper's equation (1); values in mm."""
    z = np.linspace(0.3, 3.0, 271)                                  # [m]
    ys = [1e3 * nm.axial_sigma(z, math.radians(t)) for t in THETAS_DEG]
    names = [f"theta {t} deg" for t in THETAS_DEG]
    ys.append(1e3 * nm.expected_rms_error(z))                       # eq. (1), 848 px, HFOV 90, s = 0.08
    names.append("eq. (1), 848 px")
    viz.log_series_plot(rec, "plots/sigma_z_vs_z", z, ys, names=names, dashed=[False] * len(THETAS_DEG) + [True],
                        x_label="z [m]", y_label="sigma_z [mm]", x_range=(0.0, 3.0), y_range=(0.5, 5000.0),
                        log_y=True, title="model sigma_z over depth (dashed: paper eq. 1)")
    theta_deg = np.linspace(0.0, 75.0, 151)
    xs, ys, names, dashed, colors = [], [], [], [], []
    palette = viz.SERIES_COLORS
    for k, zf in enumerate(Z_FIXED_M):
        xs.append(theta_deg)
        ys.append(1e3 * nm.axial_sigma(np.full_like(theta_deg, zf), np.radians(theta_deg)))
        names.append(f"z {zf:g} m")
        dashed.append(False)
        colors.append(palette[k])
    for k, zf in enumerate(Z_FIXED_M):
        xs.append(theta_deg[[0, -1]])
        ys.append(np.full(2, 1e3 * nm.expected_rms_error(zf)))
        names.append(f"eq. (1) {zf:g} m")
        dashed.append(True)
        colors.append(palette[k])
    viz.log_series_plot(rec, "plots/sigma_z_vs_theta", xs, ys, names=names, dashed=dashed, colors=colors,
                        x_label="theta [deg]", y_label="sigma_z [mm]", x_range=(0.0, 75.0), y_range=(0.5, 5000.0),
                        log_y=True, title="model sigma_z over incidence angle (dashed: eq. 1)")


def _notes(summary: dict) -> str:
    rows = "\n".join(
        f"| {c['camera']} | {c['distance_m']:.1f} | {c['yaw_deg']:.0f} | {1e3 * c['measured_std_m']:.2f} | "
        f"{1e3 * c['model_sigma_m']:.2f} | {c['measured_over_model']:.3f} | {c['pipeline_over_model_median']:.2f} | "
        f"{c['theta_error_median_deg']:+.1f} | {100 * c['edge_fraction']:.1f} | {'yes' if c['pose_cov'] else 'no'} |"
        for c in summary["captures"])
    columns = ["camera", "z [m]", "yaw [deg]", "measured std", "model sigma_z", "ratio", "pipeline / model (median)",
               "theta error (median) [deg]", "edge pixels [%]", "pose cov"]
    header = "| " + " | ".join(columns) + " |\n" + "|---" * len(columns) + "|"
    lo, hi = SIGMA_COLOR_RANGE_M
    return f"""# D435 noise model demo (Ahn et al. 2019)

Simulated wall, {summary['width']}x{summary['height']} depth, seed {summary['seed']}. Four cameras side by
side along world -y, each looking along world +x. Points and **2-sigma** covariance ellipsoids are a
random subsample of one frame, in the world frame, coloured by the pipeline's sigma_z on a log
scale from {1e3 * lo:.0f} mm (blue) to {1e3 * hi:.0f} mm (red). Depths outside {RANGE_M[0]}-{RANGE_M[1]} m are
dropped. **camera_{POSE_COV_CAPTURE}** carries an *example* pose covariance (1 cm per axis, 0.5 deg per
axis), so its ellipsoids include the pose uncertainty; the others use exact poses.

Statistics over {summary['n_frames']} frames per capture; sigmas are RMS over the pixels in range [mm]:

{header}
{rows}

*measured std*: residual against the true z; *model sigma_z*: at the true z and theta. The pipeline
estimates theta and the depth edges from the noisy frame itself; its ellipsoids are shown, and
`ellipsoids_true_theta` (hidden at start; switch it on in the blueprint panel) shows the model at the
true incidence angle without edges for comparison.
"""


def run_noise_demo(path="demo.rrd", seed: int = 0, show_progress: bool = True, *, width: int = 424,
                   height: int = 240, n_frames: int = 10, n_points: int = 1500, spawn: bool = False) -> dict:
    """Simulate the four wall captures and write the noise-model demo recording.

    Parameters
    ----------
    path : str or os.PathLike
        Destination ``.rrd``. Written atomically: a failed run leaves no partial file and leaves an
        existing file untouched; a successful run replaces it.
    seed : int
        Seed of the one ``np.random.default_rng`` used for the noise and the subsampling.
    show_progress : bool
        Show a tqdm progress bar (on stderr).
    width, height : int
        Depth stream mode with D435 default intrinsics (424x240 keeps the file small; 848x480
        works too).
    n_frames : int
        Frames simulated per capture for the statistics (one of them is logged).
    n_points : int
        Points (and ellipsoids) logged per capture.
    spawn : bool
        Also stream to a newly spawned rerun viewer.

    Returns
    -------
    dict
        ``path`` (absolute), ``file_size_bytes``, ``seed``, ``width``, ``height``, ``n_frames``,
        ``points_logged`` (total), ``captures``: one dict per capture with ``camera``, ``distance_m``,
        ``yaw_deg``, ``measured_std_m`` (RMS of depth - true z over the in-range pixels of all frames),
        ``model_sigma_m`` (RMS of sigma_z(true z, true theta) over the same samples),
        ``measured_over_model``, ``normalized_residual_std`` (RMS of residual / sigma_z, ~1),
        ``pipeline_sigma_m`` (RMS of the sigma_z predicted by the noise-model pipeline from the noisy
        frames), ``pipeline_over_model_median``, ``theta_error_median_deg`` (estimated - true
        incidence angle), ``edge_fraction`` (pixels flagged as depth edges), ``pose_cov`` (bool),
        ``points_logged``.
    """
    from tqdm.auto import tqdm

    rng = np.random.default_rng(seed)
    K = nm.D435.intrinsics(width, height)
    cams = [f"world/camera_{i}" for i in range(len(CAPTURES))]
    blueprint = viz.default_blueprint(depth_entities=[f"{c}/depth" for c in cams],
                                      plot_entities=["plots/sigma_z_vs_z", "plots/sigma_z_vs_theta"],
                                      text_entities=["notes"],
                                      hidden_entities=[f"/world/points_cov/camera_{i}/ellipsoids_true_theta"
                                                       for i in range(len(CAPTURES))],
                                      eye_position=EYE_POSITION, eye_look_target=EYE_LOOK_TARGET)
    summary = {"path": os.path.abspath(os.fspath(path)), "seed": int(seed), "width": int(width),
               "height": int(height), "n_frames": int(n_frames), "captures": []}
    bar = tqdm(total=len(CAPTURES) + 2, desc="noise demo", unit="step", disable=not show_progress)
    try:
        with viz.open_recording(path, "elevmap_noise_demo", spawn=spawn, blueprint=blueprint) as rec:
            viz.log_world_frame(rec, "world")
            for i, (distance_m, yaw_deg) in enumerate(CAPTURES):
                bar.set_postfix_str(f"camera_{i}: {distance_m:g} m, {yaw_deg:g} deg")
                stats, d = _capture(i, distance_m, yaw_deg, K, width, height, n_frames, n_points, rng)
                cam = cams[i]
                viz.log_transform(rec, cam, d["T_world_cam"], static=True)
                viz.log_camera(rec, f"{cam}/depth", K, width, height, static=True, image_plane_distance=0.3)
                viz.log_depth(rec, f"{cam}/depth", d["depth_u16"], meter=1.0 / DEPTH_SCALE,
                              depth_range=(0.0, RANGE_M[1] / DEPTH_SCALE), static=True)
                colors = viz.colormap(d["sigma_z"], *SIGMA_COLOR_RANGE_M, name="turbo", log=True)
                viz.log_points(rec, f"world/points_cov/camera_{i}/points", d["points_world"], colors=colors,
                               radii=0.004, static=True)
                viz.log_covariance_ellipsoids(rec, f"world/points_cov/camera_{i}/ellipsoids", d["points_world"],
                                              d["cov_world"], n_sigma=2.0, colors=colors, static=True)
                colors_true = viz.colormap(d["sigma_z_true"], *SIGMA_COLOR_RANGE_M, name="turbo", log=True)
                viz.log_covariance_ellipsoids(rec, f"world/points_cov/camera_{i}/ellipsoids_true_theta",
                                              d["points_world"], d["cov_world_true"], n_sigma=2.0,
                                              colors=colors_true, static=True)
                summary["captures"].append(stats)
                bar.update(1)
            bar.set_postfix_str("curves")
            _log_curves(rec)
            summary["points_logged"] = int(sum(c["points_logged"] for c in summary["captures"]))
            viz.log_text(rec, "notes", _notes(summary))
            bar.update(1)
            bar.set_postfix_str("writing")
        bar.update(1)
    finally:
        bar.close()
    summary["file_size_bytes"] = os.path.getsize(summary["path"])
    return summary


def demo_png_path(rrd_path) -> Path:
    """Where :func:`run_mapping_demo` writes its picture: beside the recording, suffix ``.png``."""
    return Path(rrd_path).with_suffix(".png")


def run_mapping_demo(path="demo.rrd", seed: int = 0, n_frames: int | None = None, show_progress: bool = True,
                     spawn: bool = False, png: bool = True, overwrite: bool = True,
                     sensor: str = "reference", model=None) -> dict:
    """The built-in mapping demo: a simulated robot walks across a box field and up a staircase.

    A D435 (424x240, 10 Hz) 0.45 m above the ground and pitched 30 deg down, with the paper's noise
    (the reference simulation) or the physical D435's, feeds the mapper; the map follows the robot (module
    docstring).

    Parameters
    ----------
    path : str or os.PathLike
        The rerun recording (depth, camera poses, points, covariance ellipsoids, the map as meshes
        coloured by height and by sigma, plots of time, known cells, sigma and error against the true
        terrain). Written atomically; an existing file is replaced.
    seed : int
        Seed of the box field, the noise and the subsampling.
    n_frames : int, optional
        Frames of the walk (the whole path by default).
    show_progress : bool
        A progress bar.
    spawn : bool
        Also stream to a new rerun viewer.
    png : bool
        Also write the final map against the truth as a PNG beside the recording
        (:func:`demo_png_path`; replaced if it exists).
    overwrite : bool
        Replace existing files (the command line passes ``--overwrite``; otherwise they are refused before
        any work).
    sensor : {"reference", "stereo"}
        The D435 that sees the walk (:class:`elevmap.sources.simulated.SimulatedWalk`): the reference
        simulation, whose noise the paper's model draws (default), or the physical D435 (projector, infrared
        pair, matching), whose noise emerges. With the paper's model (the default ``model``) the physical
        D435's map states a sigma larger than its error (docs/calibration.md, "The demo").
    model : str or os.PathLike, optional
        A sensor model file of ``elevmap characterize`` to map with (``MappingConfig.sensor_model`` of
        :mod:`elevmap.pipeline`); default: the paper's D435.

    Returns
    -------
    dict
        The summary of :func:`elevmap.pipeline.run_mapping` (with the map under ``map`` and its error
        against the true terrain under ``error``), plus ``scene`` and ``png`` (the picture's path, or None).
    """
    from ..pipeline import MappingConfig, run_mapping
    from ..sources.simulated import SimulatedWalk

    png_path = demo_png_path(path) if png else None
    check_outputs({"--rrd": path, "the picture": png_path}, overwrite=overwrite)
    src = SimulatedWalk("demo", n_frames=n_frames, seed=seed, sensor=sensor)
    seen_by = ("is the physical D435: projector, infrared pair and matching make its noise" if sensor == "stereo"
               else "has the noise of Ahn et al. (2019)")
    notes = ("# elevmap demo\n\nA simulated legged robot walks across a field of 4-15 cm boxes and up six "
             f"0.17 m steps. Its D435 (424x240 at 10 Hz, 0.45 m up, pitched 30 deg down) {seen_by}. The map "
             "(8 m at 0.04 m) follows the robot. `world/map/elevation` is "
             "coloured by height; switch on `world/map/sigma` (coloured by sigma, log scale) and "
             "`world/points_cov` (2-sigma ellipsoids of a point subsample).")
    trail = []

    def frames():
        for f in src:
            trail.append(f.T_map_cam[:2, 3])
            yield f

    # the demo's recording is kept and its frames are few: PNG depth keeps the file small at no cost to real time
    config = MappingConfig(png_depth=True, sensor_model="" if model is None else str(model))
    summary = run_mapping(frames(), config, rrd_path=path, spawn=spawn, total=len(src),
                          show_progress=show_progress, application_id="elevmap_demo", notes=notes)
    summary["scene"] = "demo: box field then stairs"
    summary["sensor"] = sensor
    summary["png"] = None
    if png_path is not None:
        from ..viz.plots import plot_map_against_truth

        emap = summary["map"]
        xs, ys = emap.cell_centres()
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        truth = src.truth_height(np.column_stack([X.ravel(), Y.ravel()])).reshape(X.shape)
        height = emap.known_layer("elevation")
        err = summary.get("error", {})
        walk = "a walk seen by the physical D435" if sensor == "stereo" else "a simulated D435 walk"
        title = (f"elevmap demo: {summary['frames']} frames of {walk} (box field, then six 0.17 m steps), "
                 f"map {emap.length_m:g} m at {emap.resolution_m:g} m, seed {seed}")
        if err:
            title += f"; median |error| {1000 * err['median_abs_m']:.1f} mm"
        plot_map_against_truth(xs, ys, height, np.sqrt(emap.known_layer("variance")), height - truth, png_path,
                               title=title, trail_xy=np.array(trail) if trail else None)
        summary["png"] = str(png_path)
    return summary
