"""``elevmap captures``: a capture set from static stretches of any recording, one capture per plane.

Real recordings rarely come with a target at a measured distance. :func:`run_captures` takes one or
more static stretches of a recording (a camera that does not move for a few frames: ``--frames
141-156``), finds the dominant planes of each stretch's per-pixel mean (RANSAC, then a refit along the
rays; :func:`noise_model.analysis.plane_finder.find_planes`) and writes a capture set (format
``d435-captures/1``, docs/capture-set-format.md) with one capture per plane:

* ``depth``: the stretch's frames, uint16 depth units, every pixel (the frames as recorded);
* ``target``: ``{"kind": "plane", "normal": m, "offset_m": d}``, the plane m . p + d = 0 in the camera
  frame, m pointing towards the camera (m_z < 0), d > 0 its distance;
* ``mask``: a PNG, non-zero where the pixel's mean lies on the plane within 4 temporal sigmas at its depth
  (cleaned, see :func:`~noise_model.analysis.plane_finder.find_planes`);
* ``geometry``: ``"fitted"``: statistics that need a measured distance (bias, scale) are not computed for it;
* ``fit``: what the fit found (frames, pixels, residuals, the stretch's temporal noise), kept by the reader.

Frames are numbered from 0 in the order the source yields them (a PNG folder: natural name order, so
``0.png`` is frame 0). The recording is opened with :func:`elevmap.sources.open.open_source`; a PNG
folder needs its intrinsics (``--intrinsics FILE.json`` or ``fx,fy,ppx,ppy``) when no intrinsics file lies
beside it. Float-metre frames are stored in 1 mm units.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from noise_model.analysis.plane_finder import MASK_N_SIGMA, MIN_PLANE_FRACTION, find_planes
from noise_model.analysis.planes import normalised_coordinates

from ..fileio import atomic_folder, check_folder_output

__all__ = ["run_captures", "parse_frame_ranges", "parse_intrinsics", "format_summary", "REPORT_FORMAT"]

REPORT_FORMAT = "elevmap-captures/1"
#: Depth unit [m] of frames that a source gives in float metres.
_FLOAT_UNIT_M = 0.001
#: The D435's stereo baseline [m], written into the camera entry unless told otherwise.
D435_BASELINE_M = 0.050


def parse_frame_ranges(text) -> list[tuple[int, int]]:
    """``"141-156"`` or ``"141-156,1-8"`` -> [(141, 156), (1, 8)]: inclusive ranges of frame numbers.

    Each range needs at least 2 frames (a stretch's temporal noise needs two); ranges may not overlap.
    """
    if isinstance(text, (list, tuple)):
        items = [str(t) for t in text]
    elif isinstance(text, str):
        items = [t.strip() for t in text.split(",")]
    else:
        raise ValueError(f"--frames must be ranges A-B, got {text!r}")
    out = []
    for item in items:
        m = re.fullmatch(r"\s*(\d+)\s*-\s*(\d+)\s*", item)
        if not m:
            raise ValueError(f"--frames: {item!r} is not a range A-B of frame numbers (e.g. 141-156)")
        a, b = int(m.group(1)), int(m.group(2))
        if b <= a:
            raise ValueError(f"--frames: {item!r}: a static stretch needs at least 2 frames (A < B)")
        out.append((a, b))
    if not out:
        raise ValueError("--frames: no range given")
    spans = sorted(out)
    for (a0, b0), (a1, b1) in zip(spans, spans[1:]):
        if a1 <= b0:
            raise ValueError(f"--frames: ranges {a0}-{b0} and {a1}-{b1} overlap")
    return out


def parse_intrinsics(text):
    """``--intrinsics``: None, a JSON file (Open3D or fx/fy/ppx/ppy keys), or ``"fx,fy,ppx,ppy"`` [px]."""
    if text is None:
        return None
    if isinstance(text, (dict, np.ndarray)):
        return text
    s = str(text)
    parts = s.split(",")
    if len(parts) == 4 and not Path(s).exists():
        try:
            fx, fy, cx, cy = (float(p) for p in parts)
        except ValueError:
            raise ValueError(f"--intrinsics {s!r}: four numbers fx,fy,ppx,ppy [px] or a JSON file") from None
        return {"fx": fx, "fy": fy, "ppx": cx, "ppy": cy}
    if not Path(s).is_file():
        raise ValueError(f"--intrinsics {s}: no such file (give a JSON file or fx,fy,ppx,ppy)")
    return s


def _read_stretches(recording, ranges, intrinsics):
    """The frames of each range as uint16 (F, H, W), with K and the depth scale of the recording."""
    from ..sources.open import open_source

    spec = str(recording)
    path = Path(spec)
    if intrinsics is not None and path.is_file():
        raise ValueError(f"{spec}: a recording file carries its own intrinsics; --intrinsics is for a PNG folder")
    last = max(b for _, b in ranges)
    want = {k: i for i, (a, b) in enumerate(ranges) for k in range(a, b + 1)}
    frames: list[list[np.ndarray]] = [[] for _ in ranges]
    K = scale = shape = None
    n_seen = 0
    try:
        src = open_source(spec, intrinsics=intrinsics)
    except ValueError as exc:
        if intrinsics is None and "intrinsics" in str(exc):
            raise ValueError(f"{exc} (--intrinsics FILE.json or fx,fy,ppx,ppy)") from None
        raise
    with src:
        for pos, fr in enumerate(src):
            n_seen = pos + 1
            if pos in want:
                where = f"{spec}: frame {pos}"
                depth = np.asarray(fr.depth)
                if depth.dtype == np.uint16:
                    units, s = depth, float(fr.depth_scale)
                else:
                    z = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
                    units = np.round(z / _FLOAT_UNIT_M)
                    units = np.where(units <= 65535, units, 0).astype(np.uint16)
                    s = _FLOAT_UNIT_M
                if K is None:
                    K, scale, shape = np.array(fr.K, dtype=np.float64), s, units.shape
                elif units.shape != shape or not np.allclose(fr.K, K, rtol=0, atol=1e-9) or s != scale:
                    raise ValueError(f"{where}: its size, intrinsics or depth scale differ from the first frame's; "
                                     "a static stretch is one camera mode")
                frames[want[pos]].append(units)
            if pos >= last:
                break
    for (a, b), fs in zip(ranges, frames):
        if len(fs) != b - a + 1:
            raise ValueError(f"{spec}: frames {a}-{b} asked for, but the recording has {n_seen} frames "
                             f"(0-{n_seen - 1})")
    return [np.stack(fs) for fs in frames], K, scale


def run_captures(recording, frames, out, *, intrinsics=None, baseline_m: float = D435_BASELINE_M,
                 max_planes: int = 4, min_plane_fraction: float = MIN_PLANE_FRACTION, n_sigma: float = MASK_N_SIGMA,
                 seed: int = 0, overwrite: bool = False) -> dict:
    """``elevmap captures RECORDING --frames A-B --out DIR``: one capture per dominant plane of each stretch.

    Parameters
    ----------
    recording : str or path
        Any source :func:`elevmap.sources.open.open_source` opens (PNG folder, .bag/.db3, .rrd, capture
        set, ``sim:SCENE``).
    frames : str or list of str
        Static stretches, ``"A-B"`` inclusive, several separated by commas (:func:`parse_frame_ranges`).
    out : path
        The capture set's folder: new, empty, or with ``overwrite`` an earlier capture set holding nothing
        else. It is built aside and swapped in whole once complete.
    intrinsics : path or str or dict, optional
        Intrinsics of a PNG folder (:func:`parse_intrinsics`).
    baseline_m : float
        Stereo baseline [m] written into the camera entry (the D435's 0.050 by default).
    max_planes, min_plane_fraction, n_sigma, seed
        Of :func:`noise_model.analysis.plane_finder.find_planes`.
    overwrite : bool
        Replace an earlier capture set in ``out``.

    Returns
    -------
    dict
        ``format``, ``recording``, ``out``, ``camera``, ``stretches`` (per range: ``frames`` [A, B],
        ``planes``: per plane ``id``, ``pixels``, ``normal``, ``offset_m``, ``incidence_deg``,
        ``depth_range_m`` (1st-99th percentile over the mask), ``residual_std_m``, ``sigma_d_px``
        (the stretch's temporal noise as a disparity sigma, k f B), ``spread``), ``frame_deviation_m``
        (per frame, the median over the planes' pixels of |depth - the pixel's median over the stretch|:
        a frame in which the camera moved stands out).

    Raises
    ------
    ValueError
        Bad ranges, a recording shorter than asked, frames of different modes, no plane in a stretch, an
        output folder that is an input or holds other files.
    """
    from noise_model.checks import check_positive_scalar

    from ..sources.captures import capture_set_files, read_capture_set, write_capture_set

    ranges = parse_frame_ranges(frames)
    intr = parse_intrinsics(intrinsics)
    B = check_positive_scalar(baseline_m, "baseline_m", upper=2.0, unit=" m")
    rec = str(recording)
    inputs = [] if rec.startswith(("sim:", "live")) else [rec]
    out = check_folder_output("--out", out, overwrite, capture_set_files, inputs=inputs, kind="a capture set")
    stacks, K, scale = _read_stretches(rec, ranges, intr)
    H, W = stacks[0].shape[1:]
    camera = {"width": int(W), "height": int(H), "fx": float(K[0, 0]), "fy": float(K[1, 1]),
              "ppx": float(K[0, 2]), "ppy": float(K[1, 2]), "depth_scale": float(scale), "baseline_m": B}
    up, vp = normalised_coordinates(K, np.arange(W)[None, :], np.arange(H)[:, None])
    items, stretches = [], []
    for (a, b), units in zip(ranges, stacks):
        depth_m = units.astype(np.float64) * scale
        depth_m[units == 0] = np.nan
        found = find_planes(depth_m, K, max_planes=max_planes, min_plane_fraction=min_plane_fraction,
                            n_sigma=n_sigma, depth_unit_m=scale, seed=seed)
        if not found:
            raise ValueError(f"{rec}: frames {a}-{b}: no plane covers {100 * min_plane_fraction:.0f} % of the image "
                             "(is the camera static there, and the intrinsics right?)")
        planes_out = []
        for i, mp in enumerate(found, start=1):
            cid = f"f{a}-{b}_plane{i}"
            normal = [float(-x) for x in mp.plane.normal]
            zp = mp.plane.depth_at(up, vp)[mp.mask]
            fit = {"frames": [a, b], "pixels": mp.n_pixels, "support": mp.support,
                   "temporal_sigma_per_z2": mp.temporal_k_per_m, "mask_n_sigma": mp.n_sigma,
                   "mask_inlier_rel": mp.inlier_rel, "residual_std_m": mp.residual_std_m,
                   "residual_mad_sigma_m": mp.residual_mad_sigma_m, "spread": mp.spread}
            entry = {"id": cid, "target": {"kind": "plane", "normal": normal, "offset_m": float(mp.plane.offset_m)},
                     "geometry": "fitted", "fit": fit}
            items.append((entry, units, mp.mask))
            planes_out.append({"id": cid, "pixels": mp.n_pixels, "fraction": mp.n_pixels / (H * W), "normal": normal,
                               "offset_m": float(mp.plane.offset_m), "incidence_deg": mp.incidence_deg,
                               "depth_range_m": [float(np.percentile(zp, 1)), float(np.percentile(zp, 99))],
                               "residual_std_m": mp.residual_std_m, "spread": mp.spread,
                               "sigma_d_px": mp.temporal_k_per_m * float(K[0, 0]) * B})
        union = np.zeros((H, W), dtype=bool)
        for mp in found:
            union |= mp.mask
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)          # a pixel with no data in the stretch
            ref = np.nanmedian(depth_m[:, union], axis=0)
            dev = [float(np.nanmedian(np.abs(f[union] - ref))) for f in depth_m]
        stretches.append({"frames": [a, b], "n_frames": int(units.shape[0]), "planes": planes_out,
                          "frame_deviation_m": dev})
    made_by = {"command": "elevmap captures", "recording": rec, "frames": [list(r) for r in ranges],
               "max_planes": int(max_planes), "min_plane_fraction": float(min_plane_fraction),
               "mask_n_sigma": float(n_sigma), "seed": int(seed)}
    with atomic_folder(out) as tmp:          # a previous set stays whole until the new one is complete
        write_capture_set(tmp, camera, items, overwrite=True, extra={"made_by": made_by})
    cs = read_capture_set(out)
    return {"format": REPORT_FORMAT, "recording": rec, "out": str(cs.folder), "camera": camera,
            "captures": cs.ids, "stretches": stretches}


def format_summary(report: dict) -> str:
    """A table of the planes found, one line per capture."""
    lines = [f"capture set {report['out']} from {report['recording']}",
             f"{'capture':<22} {'pixels':>7} {'normal (towards camera)':>26} {'offset m':>8} {'incid.':>6} "
             f"{'depth m':>11} {'resid mm':>8} {'sigma_d px':>10}"]
    for st in report["stretches"]:
        for p in st["planes"]:
            n = ", ".join(f"{x:+.3f}" for x in p["normal"])
            lo, hi = p["depth_range_m"]
            lines.append(f"{p['id']:<22} {p['pixels']:>7d} {n:>26} {p['offset_m']:>8.3f} {p['incidence_deg']:>5.1f}d "
                         f"{lo:>5.2f}-{hi:<5.2f} {1000 * p['residual_std_m']:>8.2f} {p['sigma_d_px']:>10.3f}")
        worst = max(st["frame_deviation_m"])
        lines.append(f"  frames {st['frames'][0]}-{st['frames'][1]}: {st['n_frames']} frames, largest per-frame median "
                     f"|depth - median| on the planes {1000 * worst:.2f} mm")
    return "\n".join(lines)
