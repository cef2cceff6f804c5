"""Depth effects that emerge from the physical D435, measured with the gap tool's own statistics.

Nothing here is put into the simulation: the physical D435 (:class:`.pipeline.StereoD435`) simulates
capture sets of planar targets (``noise_model.sim.targets.simulate_target_stereo``, as
``elevmap simulate --grid paper --sensor stereo`` does) and the statistics of ``elevmap gap``
(``noise_model.analysis.diagnosis``) and its effect fits (``noise_model.analysis.effect_fits``) read
the effects of docs/depth-effects.md off the frames, as they would off a real D435's.

* :func:`capture_statistics` -- per capture (distance, angle), on the target's interior: fill rate,
  temporal and spatial standard deviation, correlation length, concentration on the 1/32-px lattice,
  tail rate (the gap statistics, :data:`noise_model.analysis.diagnosis.STATISTICS`), and the static
  part: the residual of the frames' per-pixel mean about its best plane against the temporal sigma.
* :func:`effect_fits` -- the gap tool's fits on the whole set: the disparity lattice and the f B it is
  found at, correlated noise, static pattern, dropout, extra disparity noise (walls); edge fattening
  and flying pixels (boards before a background wall).
* :func:`fill_vs_albedo` -- the fill rate of a fronto-parallel wall against its albedo and distance.
* :func:`measure` -- all of it on the default design (:data:`WALLS`, :data:`BOARDS`, :data:`ALBEDOS`).

Units: depth z [m], disparity d = f B / z [px], angles [deg]; images 424 x 240 (the gap tool's size)
in 1 mm units.
"""

from __future__ import annotations

import numpy as np

from .pipeline import StereoD435

__all__ = ["WALLS", "BOARDS", "ALBEDOS", "design", "simulate", "capture_statistics", "static_part", "effect_fits",
           "fill_vs_albedo", "measure"]

#: Wall captures: (distance [m], yaw [deg]).
WALLS = tuple((d, y) for d in (0.6, 1.0, 1.5, 2.0) for y in (0, 30, 60))
#: Board captures (0.60 x 0.90 m before a wall at 3 m): (distance [m], yaw [deg]).
BOARDS = ((0.9, 0), (1.5, 0))
#: Albedos of the fill-rate sweep (fronto-parallel walls at :data:`ALBEDO_DISTANCES`).
ALBEDOS = (0.01, 0.02, 0.05, 0.2, 0.8)
ALBEDO_DISTANCES = (1.0, 2.0, 3.0)


def _camera(width: int, height: int) -> dict:
    from ...d435 import D435

    K = D435.intrinsics(width, height)
    return {"width": width, "height": height, "fx": float(K[0, 0]), "fy": float(K[1, 1]), "ppx": float(K[0, 2]),
            "ppy": float(K[1, 2]), "depth_scale": 0.001, "baseline_m": D435.baseline_m}


def design(walls=WALLS, boards=BOARDS, width: int = 424, height: int = 240) -> list:
    """Capture geometries (``CaptureGeometry``) of the walls and the boards (0.60 x 0.90 m, background at 3 m)."""
    from ..targets import CaptureGeometry

    cam = _camera(width, height)
    out = [CaptureGeometry.from_capture_set_entry(cam, {"id": f"wall_z{d:.2f}_y{y:02d}", "target": {
        "kind": "wall", "distance_m": d, "yaw_deg": float(y), "pitch_deg": 0.0}}) for d, y in walls]
    out += [CaptureGeometry.from_capture_set_entry(cam, {"id": f"board_z{d:.2f}_y{y:02d}", "target": {
        "kind": "board", "distance_m": d, "yaw_deg": float(y), "pitch_deg": 0.0, "width_m": 0.6, "height_m": 0.9},
        "background_m": 3.0}) for d, y in boards]
    return out


def simulate(geometries, n_frames: int = 30, seed: int = 0, camera: StereoD435 | None = None) -> list:
    """``CaptureData`` of each geometry: ``n_frames`` frames of the physical D435, seeded per capture."""
    import zlib

    from ...analysis.capture_data import CaptureData
    from ..targets import simulate_target_stereo

    out, cams = [], {}
    for g in geometries:
        key = (g.width, g.height, g.K.tobytes(), g.baseline_m, g.depth_scale)
        if camera is None and key not in cams:
            cams[key] = StereoD435(g.width, g.height, K=g.K, baseline_m=g.baseline_m, depth_unit_m=g.depth_scale)
        cam = camera if camera is not None else cams[key]
        rng = np.random.default_rng([int(seed), zlib.crc32(g.id.encode("utf-8"))])
        out.append(CaptureData.from_units(g, simulate_target_stereo(g, int(n_frames), rng, camera=cam)))
    return out


def static_part(capture, mask) -> dict:
    """The static part of the error: the per-pixel mean's residual against the temporal sigma (disparity).

    On the mask's pixels valid in at least half the frames: d = f B / z; the temporal sigma s_t is the
    root mean square over pixels of each pixel's standard deviation over frames (ddof 1); the static
    sigma s_s is the standard deviation of the per-pixel mean about its best plane a + b u + c v (a
    plane target's true disparity is affine in (u, v)), with the temporal share s_t^2 / F removed.

    Returns
    -------
    dict
        ``temporal_sigma_d_px`` (s_t), ``static_sigma_d_px`` (s_s) and ``static_ratio`` = s_s / s_t (NaN
        without 2 frames and 50 pixels).
    """
    g = capture.geometry
    d = g.fb_px_m / capture.depth_m                       # NaN stays NaN
    F = d.shape[0]
    n = np.isfinite(d).sum(axis=0)
    ok = mask & (n >= max(2, F // 2))
    if F < 2 or ok.sum() < 50:
        return {"temporal_sigma_d_px": float("nan"), "static_sigma_d_px": float("nan"), "static_ratio": float("nan")}
    dv = d[:, ok]
    st = np.sqrt(np.nanmean(np.nanvar(dv, axis=0, ddof=1)))
    mean = np.nanmean(dv, axis=0)
    vv, uu = np.nonzero(ok)
    A = np.column_stack([np.ones(vv.size), uu, vv]).astype(np.float64)
    r = mean - A @ np.linalg.lstsq(A, mean, rcond=None)[0]
    ss = float(np.sqrt(max(float(np.var(r)) - st ** 2 / F, 0.0)))
    return {"temporal_sigma_d_px": float(st), "static_sigma_d_px": ss, "static_ratio": ss / float(st)}


def capture_statistics(data) -> list[dict]:
    """The gap statistics and the static part of each capture, on its target's interior.

    The statistics are :func:`noise_model.analysis.diagnosis.capture_sums` and ``statistic_values``
    over the full sample of frames, in the stratum of the capture's interior region (the target
    without the left band and a board's edges), in metres as the gap report has them; the static part
    (:func:`static_part`) is in disparity.
    """
    from ...analysis import diagnosis as G
    from ...analysis.capture_data import REGION_INTERIOR
    from ...analysis.diagnosis.strata import REGION_LOCAL

    rows = []
    binning = G.Binning()
    for c in data:
        g = c.geometry
        cap = G.gap_capture_of(c)
        sums = G.capture_sums(cap, c.depth_m, G.frame_sampling(c.n_frames, n_splits=0, n_boot=0))
        keys, pooled = G.pool_sums([cap], [sums], binning)
        vals, _ = G.statistic_values(pooled)
        k = REGION_LOCAL[REGION_INTERIOR]
        col = [i for i, key in enumerate(keys) if key[2] == k][0]
        stat = {name: float(vals[0, j, col]) for j, name in enumerate(G.STATISTICS)}
        interior = cap.regions == REGION_INTERIOR
        row = {"id": g.id, "kind": g.kind, "distance_m": g.distance_m, "angle_deg": abs(g.yaw_deg),
               "frames": c.n_frames, "median_z_m": float(np.nanmedian(cap.z_true_m[interior])), **stat}
        row.update(static_part(c, interior))
        rows.append(row)
    return rows


def effect_fits(walls, boards, seed: int = 0) -> dict:
    """The gap tool's effect fits (``fit_effect``, ``disparity_lattice``) on the simulated captures.

    Each fit reads the effect as an excess over the reference simulation (the paper's model) of the
    same captures: ``disparity_quantization`` and ``disparity_lattice`` (which lattice, at which f B),
    ``correlated_noise`` (share of sigma_z correlated per frame and its length), ``static_pattern``
    (the static disparity pattern's sigma and length), ``dropout`` (missing pixels against depth and
    angle), ``disparity_noise`` (extra white disparity noise) on the walls; ``edge_fattening`` and
    ``flying_pixels`` on the boards. A fit that cannot run on these captures gives its error message.
    """
    from ...analysis.effect_fits import disparity_lattice, fit_effect

    out = {}
    cache: dict = {}
    try:
        lat = disparity_lattice(walls, seed=seed, cache=cache)
        out["disparity_lattice"] = {"subpixel_bits": lat["subpixel_bits"],
                                    "fb_rel": [c["fb_rel"] for c in lat["cameras"]],
                                    "score": [c["score"] for c in lat["cameras"]]}
    except ValueError as exc:
        out["disparity_lattice"] = {"error": str(exc)}
    for name, caps in (("correlated_noise", walls), ("static_pattern", walls), ("dropout", walls),
                       ("disparity_noise", walls), ("edge_fattening", boards), ("flying_pixels", boards)):
        try:
            out[name] = fit_effect(name, caps, seed=seed, cache=cache)
        except ValueError as exc:
            out[name] = {"error": str(exc)}
    return out


def fill_vs_albedo(albedos=ALBEDOS, distances=ALBEDO_DISTANCES, n_frames: int = 5, width: int = 424,
                   height: int = 240, seed: int = 0) -> list[dict]:
    """Fill rate of a fronto-parallel wall of each albedo at each distance (projector only).

    The fill rate is the fraction of the wall's pixels right of the left band (columns >= f B / z + 10 px,
    scaled from 424 wide) with depth, over ``n_frames`` frames.
    """
    from .materials import Uniform

    geoms = design(walls=[(d, 0) for d in distances], boards=(), width=width, height=height)
    rows = []
    for g in geoms:
        cam = StereoD435(g.width, g.height, K=g.K, baseline_m=g.baseline_m, depth_unit_m=g.depth_scale)
        band = int(np.ceil(g.fb_px_m / g.distance_m + g.default_left_margin_px()))
        for a in albedos:
            scene, T = g.scene(max_range_m=cam.max_range_m, material=Uniform(float(a), "wall"))
            D = cam.frames(scene, T, int(n_frames), np.random.default_rng([int(seed), int(a * 1000)]))
            rows.append({"distance_m": g.distance_m, "albedo": float(a),
                         "fill_rate": float((D[:, :, band:] > 0).mean())})
    return rows


def measure(n_frames: int = 30, seed: int = 0, walls=WALLS, boards=BOARDS, albedos=ALBEDOS) -> dict:
    """Every emergent figure of the module docstring on the default design."""
    wall_data = simulate(design(walls, ()), n_frames, seed)
    board_data = simulate(design((), boards), n_frames, seed)
    return {"captures": capture_statistics(wall_data + board_data),
            "fits": effect_fits(wall_data, board_data, seed),
            "fill_vs_albedo": fill_vs_albedo(albedos, seed=seed) if albedos else []}
