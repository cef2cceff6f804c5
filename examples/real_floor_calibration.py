"""Can I trust the map's sigmas on my camera? The map of a real floor, scored against its own plane.

A static stretch of a real recording that sees a floor (``elevmap captures`` makes its capture set: one
``plane`` capture per dominant plane, with its pixel mask) gives a map whose truth is known without any
measurement: the floor's fitted plane. This example maps the floor's pixels of each chosen capture with
the camera placed by that plane (map z = height above it), once from the first frame and once from all
frames of the stretch, with each sensor model given, and reports per range band the cells' RMSE, their
median stated sigma, and how often the error lies within 1 and 2 sigma (0.68 / 0.95 when the sigmas are
right). Fit the model on another capture than the floor (``elevmap characterize SET --only WALL``) so that
the floor is held out.

What it cannot tell apart: the floor's own unevenness and the camera's systematic depth error both count as
error (the plane is that of the frames' mean); with the camera still, a cell is seen through the same
pixels in every frame, so a static error pattern does not average out over frames.

Run:  python examples/real_floor_calibration.py SET --capture f1-8_plane1 --model wall.model.json
"""

from __future__ import annotations

import argparse

import numpy as np

import noise_model as nm
from elevmap.map.elevation_map import ElevationMap
from elevmap.mapper import Camera, Mapper
from elevmap.sources.captures import read_capture_set
from noise_model.analysis.planes import target_plane

#: Range bands [m] (horizontal distance of a cell's centre from the camera) the scores are split by.
DEFAULT_BANDS_M = ((0.0, 2.5), (2.5, np.inf))


def T_floor_cam(target) -> np.ndarray:
    """The camera's pose in a frame whose z is the height above a capture's plane (4, 4).

    With the plane n . p = offset_m (:func:`target_plane`, n towards the scene), a camera-frame point p lies
    offset_m - n . p above it: the map's z axis is -n, the camera offset_m above the origin; x, y complete a
    right-handed frame (x from the camera's y axis crossed with z).
    """
    plane = target_plane(target)
    z_axis = -np.asarray(plane.normal, dtype=np.float64)
    x_axis = np.cross([0.0, 1.0, 0.0], z_axis)
    x_axis /= np.linalg.norm(x_axis)
    T = np.eye(4)
    T[:3, :3] = np.vstack([x_axis, np.cross(z_axis, x_axis), z_axis])
    T[2, 3] = plane.offset_m
    return T


def floor_scores(cs, capture_id: str, model, frames: int | None = None, bands=DEFAULT_BANDS_M) -> list[dict]:
    """Map the masked pixels of ``capture_id``'s first ``frames`` frames (all when None) with ``model`` and
    score the cells against height 0, per range band.

    Returns
    -------
    list of dict
        Per band: ``band_m``, ``cells``, ``rmse_m``, ``mean_error_m``, ``median_sigma_m``, ``coverage_1sigma``,
        ``coverage_2sigma``.
    """
    if frames is not None and (isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1):
        raise ValueError(f"frames must be a positive integer or None, got {frames!r}")
    cap = next((c for c in cs.captures if c.id == capture_id), None)
    if cap is None:
        raise ValueError(f"{cs.folder}: no capture {capture_id!r}; captures: {', '.join(c.id for c in cs.captures)}")
    if cap.kind != "plane":
        raise ValueError(f"{cs.folder}: capture {capture_id!r} is a {cap.kind!r} target; a fitted 'plane' is needed")
    cam = cs.camera_for(cap.id) if cap.is_recording else cs.camera
    K = np.array([[cam["fx"], 0.0, cam["ppx"]], [0.0, cam["fy"], cam["ppy"]], [0.0, 0.0, 1.0]])
    mask = cs.load_mask(cap.id)
    depth = np.asarray(cs.load_depth(cap.id))
    depth = np.where(mask[None], depth, 0).astype(np.uint16) if mask is not None else depth
    T_map_cam = T_floor_cam(cap.to_dict()["target"])
    emap = ElevationMap()
    mapper = Mapper(emap, [Camera("cam", K, int(cam["width"]), int(cam["height"]), model=model,
                                  depth_scale=float(cam["depth_scale"]))])
    for f in range(depth.shape[0] if frames is None else min(frames, depth.shape[0])):
        mapper.integrate("cam", depth[f], T_map_cam=T_map_cam)
    known = emap.is_known()
    h, sigma = emap.layer("elevation"), np.sqrt(emap.layer("variance"))
    xs, ys = emap.cell_centres()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    r = np.hypot(X - T_map_cam[0, 3], Y - T_map_cam[1, 3])
    rows = []
    for lo, hi in bands:
        s = known & (r >= lo) & (r < hi)
        e, sg = h[s], sigma[s]
        n = int(s.sum())
        rows.append({"band_m": (lo, hi), "cells": n,
                     "rmse_m": float(np.sqrt(np.mean(e ** 2))) if n else np.nan,
                     "mean_error_m": float(e.mean()) if n else np.nan,
                     "median_sigma_m": float(np.median(sg)) if n else np.nan,
                     "coverage_1sigma": float(np.mean(np.abs(e) <= sg)) if n else np.nan,
                     "coverage_2sigma": float(np.mean(np.abs(e) <= 2 * sg)) if n else np.nan})
    return rows


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("captures", help="capture set folder (elevmap captures)")
    ap.add_argument("--capture", action="append", required=True, help="a floor's capture id (repeatable)")
    ap.add_argument("--model", action="append", default=[], help="a sensor model file (repeatable); the paper's is "
                                                                 "always scored")
    args = ap.parse_args(argv)
    cs = read_capture_set(args.captures)
    models = {"paper": nm.D435, **{p: nm.SensorModel.load(p) for p in args.model}}
    out = []
    print("capture | model | frames | range [m] | cells | RMSE [mm] | mean [mm] | median sigma [mm] | 1 / 2-sigma")
    for cid in args.capture:
        n_frames = np.asarray(cs.load_depth(cid)).shape[0]
        for name, model in models.items():
            for frames in sorted({1, n_frames}):
                for row in floor_scores(cs, cid, model, frames):
                    row.update(capture=cid, model=name, frames=frames)
                    out.append(row)
                    lo, hi = row["band_m"]
                    print(f"{cid} | {name} | {frames} | {lo:g}-{hi:g} | {row['cells']} | {1e3 * row['rmse_m']:.1f} | "
                          f"{1e3 * row['mean_error_m']:+.1f} | {1e3 * row['median_sigma_m']:.1f} | "
                          f"{row['coverage_1sigma']:.2f} / {row['coverage_2sigma']:.2f}")
    return out


if __name__ == "__main__":
    main()
