"""Raw depth frames exported by the RealSense Viewer: ``<name>.raw`` with ``<name>_metadata.csv``.

The Viewer's "export" writes each depth frame as headerless little-endian uint16 (Z16, row-major,
``width x height``) and, beside it, a CSV of the frame's info and the stream's intrinsics::

    Frame Info: 
    Type,Depth
    Format,Z16
    Frame Number,531
    Timestamp (ms),1581812447071.36
    Resolution x,848
    Resolution y,480
    Bytes per pixel,2

    Intrinsic:,
    Fx,425.849243
    Fy,425.849243
    PPx,425.867798
    PPy,239.954727
    Distorsion,Brown Conrady

The depth unit is not in the files (the SDK's default is 1 mm): pass ``depth_scale`` when the camera
was set otherwise.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from noise_model.checks import check_positive_scalar

__all__ = ["read_viewer_raw", "viewer_raw_metadata"]

_KEYS = {"frame number": "frame_number", "timestamp (ms)": "timestamp_ms", "resolution x": "width",
         "resolution y": "height", "bytes per pixel": "bytes_per_pixel", "fx": "fx", "fy": "fy", "ppx": "ppx",
         "ppy": "ppy", "format": "format", "type": "type", "distorsion": "distortion", "distortion": "distortion"}


def _metadata_path(raw: Path) -> Path:
    return raw.with_name(raw.stem + "_metadata.csv")


def viewer_raw_metadata(path) -> dict:
    """The metadata CSV of a Viewer export (the CSV itself, or the .raw beside it).

    Returns
    -------
    dict
        ``width``, ``height`` [px] (int), ``fx``, ``fy``, ``ppx``, ``ppy`` [px] (float), ``format``,
        ``type``, ``frame_number``, ``timestamp_ms``, ``bytes_per_pixel``, ``distortion`` where present.

    Raises
    ------
    ValueError
        No such file, or a required key (resolution, intrinsics) is missing or not a number.
    """
    p = Path(path)
    if p.suffix.lower() == ".raw":
        p = _metadata_path(p)
    try:
        text = p.read_text(errors="replace")
    except FileNotFoundError:
        raise ValueError(f"{p}: no such metadata file (a RealSense Viewer export has <name>_metadata.csv "
                         "beside <name>.raw)") from None
    meta = {}
    for line in text.splitlines():
        parts = [x.strip() for x in line.split(",")]
        if len(parts) < 2 or not parts[0]:
            continue
        key = _KEYS.get(parts[0].lower())
        if key is None or not parts[1]:
            continue
        meta[key] = parts[1]
    out = {}
    for key in ("width", "height", "fx", "fy", "ppx", "ppy"):
        if key not in meta:
            raise ValueError(f"{p}: missing '{key}' (Resolution x/y, Fx, Fy, PPx, PPy)")
        try:
            out[key] = float(meta[key])
        except ValueError:
            raise ValueError(f"{p}: '{key}' is not a number: {meta[key]!r}") from None
    out["width"], out["height"] = int(out["width"]), int(out["height"])
    if out["width"] < 1 or out["height"] < 1 or out["fx"] <= 0 or out["fy"] <= 0:
        raise ValueError(f"{p}: implausible resolution or focal length: {out}")
    for key in ("format", "type", "distortion"):
        if key in meta:
            out[key] = meta[key]
    for key, conv in (("frame_number", int), ("timestamp_ms", float), ("bytes_per_pixel", int)):
        if key in meta:
            try:
                out[key] = conv(meta[key])
            except ValueError:
                pass
    return out


def read_viewer_raw(path, depth_scale: float = 0.001) -> tuple[np.ndarray, np.ndarray, dict]:
    """Read one depth frame exported by the RealSense Viewer.

    Parameters
    ----------
    path : str or Path
        The ``.raw`` file; its ``<name>_metadata.csv`` must sit beside it.
    depth_scale : float
        Metres per depth unit (the export does not say; 0.001 is the SDK default).

    Returns
    -------
    depth : ndarray, shape (H, W), uint16
        Depth units (0 = no data).
    K : ndarray, shape (3, 3)
        Pinhole intrinsics [px] from the CSV.
    meta : dict
        :func:`viewer_raw_metadata` plus ``depth_scale`` [m/unit].

    Raises
    ------
    ValueError
        Missing files, a format other than Z16, or a file size that does not match the resolution
        (truncated or another resolution).
    """
    raw = Path(path)
    if raw.suffix.lower() != ".raw":
        raise ValueError(f"{raw}: not a .raw file")
    if not raw.is_file():
        raise ValueError(f"{raw}: no such file")
    meta = viewer_raw_metadata(raw)
    fmt = meta.get("format", "Z16").upper()
    if fmt != "Z16":
        raise ValueError(f"{raw}: format {fmt}, expected Z16 depth")
    if meta.get("bytes_per_pixel", 2) != 2:
        raise ValueError(f"{raw}: {meta['bytes_per_pixel']} bytes per pixel, expected 2 (Z16)")
    W, H = meta["width"], meta["height"]
    size = raw.stat().st_size
    if size != 2 * W * H:
        raise ValueError(f"{raw}: {size} bytes, but {W}x{H} Z16 needs {2 * W * H} (truncated, or another resolution)")
    depth = np.fromfile(raw, dtype="<u2").reshape(H, W).astype(np.uint16)
    meta["depth_scale"] = check_positive_scalar(depth_scale, "depth_scale", upper=0.1, unit=" m per unit")
    K = np.array([[meta["fx"], 0.0, meta["ppx"]], [0.0, meta["fy"], meta["ppy"]], [0.0, 0.0, 1.0]])
    return depth, K, meta
