"""PNG figures with matplotlib (imported lazily, ``Agg`` backend; no display needed).

The characterisation figures of Ahn et al. (2019), drawn from the plain arrays of an ``elevmap
characterize`` report (``series``: ``elevmap.commands.characterize.figure_series(report)``; ``panels``:
``elevmap.commands.characterize.plane_distance_panels(records)``):

* :func:`plot_systematic_error`: Fig. 2, the RMS error of the mean of the frames against the known
  distance, with the single-frame plane-fit residual and the paper's equation (1);
* :func:`plot_axial_variance`: Fig. 3, the axial variance against distance per angle, with the
  fitted and the paper's curves;
* :func:`plot_plane_distance`: Fig. 4, each pixel's distance to the fitted plane;
* :func:`plot_lateral_noise`: the lateral noise of left and right edges per capture, with sigma_L,
  sigma_R and the paper's values.

And the picture of a map against the true terrain (``elevmap demo`` writes it as ``demo.png``):

* :func:`plot_map_against_truth`: height, sigma and error against the truth side by side, seen from
  above.

Every file is written atomically (:func:`elevmap.fileio.atomic_output`).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ..fileio import atomic_output

__all__ = ["plot_systematic_error", "plot_axial_variance", "plot_plane_distance", "plot_lateral_noise",
           "plot_map_against_truth", "MAP_ERROR_RANGE_M", "MAP_SIGMA_RANGE_M"]

_DPI = 110
#: Resolution of :func:`plot_map_against_truth` [dots per inch]: 1500 x 440 pixels.
MAP_DPI = 100
#: Colour range of the error panel of :func:`plot_map_against_truth`: +-10 cm [m].
MAP_ERROR_RANGE_M = 0.10
#: Colour range of its sigma panel (log scale): 1 mm to 10 cm [m], as the recordings' sigma mesh.
MAP_SIGMA_RANGE_M = (0.001, 0.1)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path, dpi: int = _DPI, palette: bool = False) -> Path:
    """Write ``fig`` as a PNG, atomically. ``palette``: 256 colours (Pillow's median cut, no dithering),
    about a third of the size for figures of noisy per-cell maps, which compress badly in full colour."""
    path = Path(path)
    with atomic_output(path, suffix=".png") as tmp:
        if not palette:
            fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight")
        else:
            from PIL import Image                  # matplotlib's own dependency

            buf = io.BytesIO()
            fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
            buf.seek(0)
            with Image.open(buf) as im:
                q = im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
                q.save(tmp, format="PNG", optimize=True)
    return path


def plot_systematic_error(series: dict, path) -> Path:
    """Fig. 2: systematic (RMS) error of the mean of the frames vs distance, with eq. (1) [mm].

    ``series["fig2"]``: ``distance_m``, ``rms_error_m``, ``residual_m``, ``eq1_m`` (lists [m], None where
    not measured), ``kind`` and ``theta_deg``.
    """
    plt = _pyplot()
    s = series["fig2"]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    try:
        d = np.asarray(s["distance_m"], dtype=float)
        if d.size:
            def mm(v):
                return 1000.0 * np.array([np.nan if x is None else x for x in v], dtype=float)

            ax.plot(d, mm(s["rms_error_m"]), "o-", label="RMS error of the mean of the frames vs known distance")
            ax.plot(d, mm(s["residual_m"]), "s--", label="single-frame plane-fit residual (std)")
            ax.plot(d, mm(s["eq1_m"]), "k-", label="eq. (1): e = d^2 s / (f b), s = 0.08 px")
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "no capture measured", ha="center", va="center", transform=ax.transAxes)
        ax.set_xlabel("distance [m]")
        ax.set_ylabel("error [mm]")
        t = s["theta_deg"]
        ax.set_title(f"Fig. 2: systematic error ({s['kind']} captures"
                     + ("" if t is None else f", {t:.0f} deg") + ")")
        ax.grid(True, alpha=0.3)
        return _save(fig, path)
    finally:
        plt.close(fig)


def plot_axial_variance(series: dict, path) -> Path:
    """Fig. 3: axial variance sigma_z^2 vs depth per angle; fitted (solid) and paper (dashed) curves.

    ``series["fig3"]``: ``angles_deg``, ``points`` (per angle: z [m], variance [m^2]), ``curve_z_m`` and
    the ``fitted`` and ``paper`` variances over it [m^2].
    """
    plt = _pyplot()
    s = series["fig3"]
    fig, ax = plt.subplots(figsize=(6.4, 4.6))
    try:
        colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
        zc = np.asarray(s["curve_z_m"])
        for k, a in enumerate(s["angles_deg"]):
            c = colors[k % len(colors)]
            z, v = s["points"][a]
            ax.plot(z, 1e6 * np.asarray(v), "o", color=c, ms=4, label=f"{a} deg")
            if a in s["fitted"]:
                ax.plot(zc, 1e6 * np.asarray(s["fitted"][a]), "-", color=c, lw=1.2)
            ax.plot(zc, 1e6 * np.asarray(s["paper"][a]), "--", color=c, lw=0.8)
        ax.set_yscale("log")
        ax.set_xlabel("depth z [m]")
        ax.set_ylabel("axial variance sigma_z^2 [mm^2]")
        ax.set_title("Fig. 3: axial variance (points), fit (solid), paper (dashed)")
        ax.grid(True, which="both", alpha=0.3)
        if s["angles_deg"]:
            ax.legend(fontsize=8, ncol=2)
        return _save(fig, path)
    finally:
        plt.close(fig)


def plot_plane_distance(panels, path) -> Path:
    """Fig. 4: per-pixel distance of the mean of the frames to the fitted plane [mm], a few captures.

    ``panels``: (capture id, distance image (H, W) [m], colour range [m]) per capture shown.
    """
    plt = _pyplot()
    n = max(1, len(panels))
    cols = min(3, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False)
    try:
        if not panels:
            axes[0, 0].text(0.5, 0.5, "no capture measured", ha="center", va="center")
        for k, ax in enumerate(axes.ravel()):
            ax.set_axis_off()
            if k >= len(panels):
                continue
            cid, img, rng = panels[k]
            e = 1000.0 * rng
            im = ax.imshow(1000.0 * img, cmap="RdBu_r", vmin=-e, vmax=e, interpolation="nearest")
            ax.set_title(cid, fontsize=9)
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02, label="mm")
        fig.suptitle("Fig. 4: distance of each pixel (mean of the frames) to the fitted plane\n"
                     "(colour range: 98th percentile over the central region; the moving edges saturate)")
        return _save(fig, path)
    finally:
        plt.close(fig)


def plot_lateral_noise(series: dict, path) -> Path:
    """Lateral noise per capture (left and right edges) vs distance, with sigma_L, sigma_R [mm].

    ``series["lateral"]``: per side (distances [m], noise [m]) of the captures used and of those left
    out (``<side>_unused``), ``sigma_L_m``, ``sigma_R_m`` and the paper's.
    """
    plt = _pyplot()
    s = series["lateral"]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    try:
        for side, c, key, pkey in (("left", "C0", "sigma_L_m", "paper_sigma_L_m"),
                                   ("right", "C3", "sigma_R_m", "paper_sigma_R_m")):
            d, v = s[side]
            ax.plot(d, 1000.0 * np.asarray(v, dtype=float), "o", color=c, ms=4, label=f"{side} edge, per capture")
            d, v = s[f"{side}_unused"]
            if d:
                ax.plot(d, 1000.0 * np.asarray(v, dtype=float), "o", mfc="none", color=c, ms=4,
                        label=f"{side} edge, not used (sigma_z > 20% of z)")
            if s[key] is not None:
                ax.axhline(1000.0 * s[key], color=c, lw=1.5, label=f"{key[:7]} (90th pct): {1000 * s[key]:.1f} mm")
            ax.axhline(1000.0 * s[pkey], color=c, lw=0.8, ls="--", label=f"paper {key[:7]}: {1000 * s[pkey]:.1f} mm")
        ax.set_xlabel("distance [m]")
        ax.set_ylabel("lateral noise [mm]")
        ax.set_title("Lateral noise: spread of edge pixels about the edge's line")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        return _save(fig, path)
    finally:
        plt.close(fig)


def plot_map_against_truth(x_centres, y_centres, height, sigma, error, path, *, title: str = "",
                           trail_xy=None) -> Path:
    """The map seen from above, three panels side by side: height, sigma, and error against the truth.

    Parameters
    ----------
    x_centres, y_centres : array_like, shape (n,), (m,)
        Cell-centre coordinates of the rows and columns [m], map frame (``ElevationMap.cell_centres()``).
    height, sigma, error : array_like, shape (n, m)
        Per cell, map-index order (row i along +x, column j along +y): the fused height [m], its standard
        deviation sqrt(variance) [m], and height minus the true height at the cell's centre [m]; NaN
        where the cell is not known (drawn blank).
    path : path
        The PNG, written atomically.
    title : str
        A line above the panels.
    trail_xy : array_like, shape (K, 2), optional
        The camera's path [m], drawn on every panel.

    Returns
    -------
    pathlib.Path

    Notes
    -----
    x (the robot's forward direction in the demo) runs to the right and y upwards, so the image is the
    map frame seen from above (z towards the viewer). Colours: height on ``viridis`` over the known
    cells' range; sigma on a log scale over :data:`MAP_SIGMA_RANGE_M` (``turbo``); error on ``RdBu_r``
    over +-:data:`MAP_ERROR_RANGE_M` (blue: below the truth, red: above). The error panel's title gives
    the RMSE and the 2-sigma coverage over the known cells (the fraction with |error| <= 2 sigma).
    """
    plt = _pyplot()
    from matplotlib.colors import LogNorm

    xs, ys = np.asarray(x_centres, dtype=float), np.asarray(y_centres, dtype=float)
    h, sg, err = (np.asarray(a, dtype=float) for a in (height, sigma, error))
    if not (h.shape == sg.shape == err.shape == (len(xs), len(ys))):
        raise ValueError(f"height, sigma and error must have shape ({len(xs)}, {len(ys)}), got "
                         f"{h.shape}, {sg.shape}, {err.shape}")
    res = float(xs[1] - xs[0]) if len(xs) > 1 else 1.0
    extent = (xs[0] - res / 2, xs[-1] + res / 2, ys[0] - res / 2, ys[-1] + res / 2)
    known = np.isfinite(h) & np.isfinite(sg) & np.isfinite(err)
    lo, hi = (float(np.nanpercentile(h[known], 1)), float(np.nanpercentile(h[known], 99))) if known.any() \
        else (0.0, 1.0)
    e = MAP_ERROR_RANGE_M
    panels = [
        (h, dict(cmap="viridis", vmin=lo, vmax=max(hi, lo + 1e-3)), "height [m]", 1.0, "height"),
        (sg, dict(cmap="turbo", norm=LogNorm(*MAP_SIGMA_RANGE_M)), "sigma [mm]", 1000.0, "sigma (log scale)"),
        (err, dict(cmap="RdBu_r", vmin=-e, vmax=e), "error [mm]", 1000.0, "error against the truth"),
    ]
    if known.any():
        rmse = float(np.sqrt(np.mean(err[known] ** 2)))
        cov2 = float(np.mean(np.abs(err[known]) <= 2.0 * sg[known]))
        panels[2] = panels[2][:4] + (f"error: RMSE {1000 * rmse:.0f} mm, {100 * cov2:.0f}% within 2 sigma",)
    fig, axes = plt.subplots(1, 3, figsize=(15.0, 4.4), constrained_layout=True)
    try:
        for ax, (a, style, label, scale, name) in zip(axes, panels):
            im = ax.imshow(np.where(known, a, np.nan).T, origin="lower", extent=extent, interpolation="nearest",
                           **style)
            cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
            cb.set_label(label)
            if scale != 1.0:
                cb.formatter = plt.FuncFormatter(lambda v, _pos, s=scale: f"{s * v:g}")
                cb.update_ticks()
            if trail_xy is not None:
                t = np.asarray(trail_xy, dtype=float)
                ax.plot(t[:, 0], t[:, 1], "-", color="0.3", lw=0.8)
            ax.set_xlim(extent[0], extent[1])
            ax.set_ylim(extent[2], extent[3])
            ax.set_title(name, fontsize=10)
            ax.set_xlabel("x [m]")
            ax.set_ylabel("y [m]")
            ax.set_aspect("equal")
        if title:
            fig.suptitle(title, fontsize=11)
        return _save(fig, path, dpi=MAP_DPI, palette=True)
    finally:
        plt.close(fig)
