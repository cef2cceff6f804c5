"""The views of two reports in rerun: ``elevmap characterize`` and ``elevmap gap``.

* Characterisation: the figures of Ahn et al. (2019) (Fig. 2 and 3 and the lateral noise) as 2-D
  charts, the per-capture distance-to-plane images on a ``capture`` timeline, and a summary note
  (:func:`log_characterisation`, :func:`characterisation_blueprint`).
* Gap diagnosis: the gap per stratum as labelled bar charts (before / after the selected effects), the
  real and simulated residual and fill images of a capture side by side on a ``capture`` timeline, and
  the summary (:func:`log_gap_bars`, :func:`log_gap_images`, :func:`gap_blueprint`). Bars are thick
  2-D lines on a canvas (rerun's BarChart has no category labels).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from .charts import PLOT_VISUAL_BOUNDS, SERIES_COLORS, log_series_plot, tick_label
from .colors import colormap
from .log import log_rgb_image, log_text, set_time

__all__ = ["log_characterisation", "characterisation_blueprint", "log_gap_bars", "log_gap_images", "gap_blueprint",
           "gap_bar_bounds", "GAP_BAR_ROW", "GAP_BAR_WIDTH", "GAP_SERIES_COLORS"]


# ---------------------------------------------------------------------------------------------
# Characterisation (elevmap characterize)
# ---------------------------------------------------------------------------------------------
def log_characterisation(rec: rr.RecordingStream, series: dict, plane_images: Sequence[tuple[str, np.ndarray]],
                         summary_markdown: str, send_blueprint: bool = True) -> None:
    """Log the characterisation figures.

    Parameters
    ----------
    series : dict
        ``elevmap.commands.characterize.figure_series(report)``: ``fig2`` (distances [m], RMS error of the mean of the
        frames, single-frame residual and eq. (1) [m]), ``fig3`` (per angle [deg]: points (z [m], variance
        [m^2]), fitted and paper curves over ``curve_z_m``), ``lateral`` (per side: distances [m] and lateral
        noise [m]; sigma_L, sigma_R and the paper's [m]).
    plane_images : sequence of (str, ndarray (H, W)) or (str, ndarray (H, W), float)
        Per capture, the distance of each pixel to the fitted plane [m] (NaN off the target), and optionally
        the colour range [m]; one image per step of the ``capture`` timeline at
        ``characterize/plane_distance``, coloured blue (in front of the plane) to red (behind it) over
        +-the range (default: the 98th percentile of |distance|).
    summary_markdown : str
        The note shown beside the charts (``characterize/summary``).

    Entities: ``characterize/fig2_systematic_error``, ``characterize/fig3_axial_variance``,
    ``characterize/lateral_noise`` (charts, in mm and mm^2), ``characterize/plane_distance`` (image),
    ``characterize/summary`` (text).
    """
    f2, f3, lat = series["fig2"], series["fig3"], series["lateral"]
    plots = []
    if f2["distance_m"]:
        d = np.asarray(f2["distance_m"], dtype=np.float64)

        def mm(v):
            return 1000.0 * np.array([np.nan if x is None else x for x in v], dtype=np.float64)

        e = "characterize/fig2_systematic_error"
        log_series_plot(rec, e, d, [mm(f2["rms_error_m"]), mm(f2["residual_m"]), mm(f2["eq1_m"])],
                        names=["RMS error of the frames' mean", "single-frame plane residual", "eq. (1)"],
                        x_label="distance [m]", y_label="error [mm]", dashed=[False, False, True],
                        title=f"Fig. 2: systematic error ({f2['kind']})")
        plots.append(e)
    if f3["angles_deg"]:
        xs, ys, names, colors, dashed = [], [], [], [], []
        zc = np.asarray(f3["curve_z_m"], dtype=np.float64)
        for k, a in enumerate(f3["angles_deg"]):
            col = SERIES_COLORS[k % len(SERIES_COLORS)]
            z, v = f3["points"][a]
            order = np.argsort(z)
            xs.append(np.asarray(z, dtype=np.float64)[order])
            ys.append(1e6 * np.asarray(v, dtype=np.float64)[order])
            names.append(f"{a} deg measured")
            colors.append(col)
            dashed.append(False)
            if a in f3["fitted"]:
                xs.append(zc)
                ys.append(1e6 * np.asarray(f3["fitted"][a], dtype=np.float64))
                names.append(f"{a} deg fit")
                colors.append(col)
                dashed.append(False)
            xs.append(zc)
            ys.append(1e6 * np.asarray(f3["paper"][a], dtype=np.float64))
            names.append(f"{a} deg paper")
            colors.append(col)
            dashed.append(True)
        e = "characterize/fig3_axial_variance"
        allv = np.concatenate([y[np.isfinite(y) & (y > 0)] for y in ys])
        lo, hi = (10.0 ** np.floor(np.log10(allv.min())), 10.0 ** np.ceil(np.log10(allv.max()))) if allv.size \
            else (1e-1, 1e1)
        log_series_plot(rec, e, xs, ys, names=names, colors=np.asarray(colors, dtype=np.uint8), dashed=dashed,
                        x_label="depth z [m]", y_label="sigma_z^2 [mm^2]", log_y=True, y_range=(lo, hi),
                        x_range=(float(zc.min()), float(zc.max())),
                        title="Fig. 3: axial variance (measured, fit, paper dashed)")
        plots.append(e)
    xs, ys, names, dashed = [], [], [], []
    for side, key, pkey in (("left", "sigma_L_m", "paper_sigma_L_m"), ("right", "sigma_R_m", "paper_sigma_R_m")):
        d, v = lat[side]
        if d:
            # median over the captures at each distance (angles differ), so the curve does not zigzag
            d_arr, v_arr = np.round(np.asarray(d, dtype=np.float64), 3), np.asarray(v, dtype=np.float64)
            du = np.unique(d_arr)
            xs.append(du)
            ys.append(1000.0 * np.array([np.median(v_arr[d_arr == x]) for x in du]))
            names.append(f"{side} edge (median per distance)")
            dashed.append(False)
        ends = np.array([0.3, 2.2])
        if lat[key] is not None:
            xs.append(ends)
            ys.append(np.full(2, 1000.0 * lat[key]))
            names.append(f"{key[:7]} {1000 * lat[key]:.1f} mm")
            dashed.append(False)
        xs.append(ends)
        ys.append(np.full(2, 1000.0 * lat[pkey]))
        names.append(f"paper {key[:7]}")
        dashed.append(True)
    if any("edge" in n for n in names):
        e = "characterize/lateral_noise"
        log_series_plot(rec, e, xs, ys, names=names, dashed=dashed, x_label="distance [m]",
                        y_label="lateral noise [mm]", title="Lateral noise of the board's edges")
        plots.append(e)
    img_entity = "characterize/plane_distance"
    for k, item in enumerate(plane_images):
        cid, img = item[0], item[1]
        a = np.asarray(img, dtype=np.float64)
        if a.ndim != 2:
            raise ValueError(f"plane image of {cid} must be 2-D, got shape {a.shape}")
        if len(item) > 2:
            e = float(item[2])
        else:
            v = np.abs(a[np.isfinite(a)])
            e = float(np.percentile(v, 98)) if v.size else 1e-3
        set_time(rec, "capture", sequence=k)
        log_rgb_image(rec, img_entity, colormap(a, -max(e, 1e-6), max(e, 1e-6), "turbo"))
        log_text(rec, "characterize/capture", f"`{cid}`: distance to the plane, +-{1000 * e:.1f} mm "
                                              "(blue in front, red behind)", static=False)
    log_text(rec, "characterize/summary", summary_markdown)
    if send_blueprint:
        rec.send_blueprint(characterisation_blueprint(plots, img_entity if plane_images else None))


def characterisation_blueprint(plot_entities: Sequence[str], image_entity: str | None = None) -> rrb.Blueprint:
    """Layout of a characterisation: the charts in tabs on the left; the distance-to-plane image (stepped
    along the ``capture`` timeline), the capture's note and the summary on the right."""
    (xb, yb) = PLOT_VISUAL_BOUNDS
    charts = [rrb.Spatial2DView(origin=e, name=e.rsplit("/", 1)[-1],
                                visual_bounds=rrb.VisualBounds2D(x_range=xb, y_range=yb)) for e in plot_entities]
    right = []
    if image_entity is not None:
        right.append(rrb.Spatial2DView(origin=image_entity, name="distance to the plane"))
        right.append(rrb.TextDocumentView(origin="characterize/capture", name="capture"))
    right.append(rrb.TextDocumentView(origin="characterize/summary", name="summary"))
    left = rrb.Tabs(*charts, active_tab=0) if len(charts) > 1 else (charts[0] if charts else None)
    parts = [rrb.Horizontal(left, rrb.Vertical(*right), column_shares=[3, 2]) if left is not None
             else rrb.Vertical(*right)]
    parts.append(rrb.TimePanel(state="collapsed", timeline="capture"))
    return rrb.Blueprint(*parts, collapse_panels=False)


# ---------------------------------------------------------------------------------------------
# Gap diagnosis (elevmap gap)
# ---------------------------------------------------------------------------------------------
GAP_BAR_ROW = 28.0
GAP_BAR_WIDTH = 1000.0
GAP_SERIES_COLORS = np.array([[214, 39, 40], [44, 160, 44], [31, 119, 180]], dtype=np.uint8)


def gap_bar_bounds(n_rows: int) -> tuple[tuple[float, float], tuple[float, float]]:
    """Visual bounds (x_range, y_range) of a chart of :func:`log_gap_bars` with ``n_rows`` rows."""
    return (-520.0, GAP_BAR_WIDTH + 160.0), (-70.0, n_rows * GAP_BAR_ROW + 40.0)


def log_gap_bars(rec: rr.RecordingStream, entity: str, labels: Sequence[str], values, *,
                 series_names: Sequence[str] = ("before", "after"), title: str = "", static: bool = True) -> None:
    """Horizontal grouped bars with category labels, on a log(1 + gap) axis.

    Parameters
    ----------
    labels : sequence of N str
        One row per category (e.g. a statistic in a stratum), drawn top to bottom.
    values : array_like, shape (S, N)
        S series (e.g. the gap before and after the selected effects), >= 0; NaN draws nothing.
    series_names : sequence of S str
    title : str

    Sub-entities: ``<entity>/bars`` (thick LineStrips2D), ``<entity>/values``, ``<entity>/labels``, ``<entity>/axis``, ``<entity>/legend``.
    Show it in a Spatial2DView with :func:`gap_bar_bounds`.
    """
    v = np.atleast_2d(np.asarray(values, dtype=np.float64))
    labels = [str(s) for s in labels]
    S, N = v.shape
    if N != len(labels):
        raise ValueError(f"{len(labels)} labels for {N} values per series")
    if len(series_names) != S:
        raise ValueError(f"{len(series_names)} series names for {S} series")
    top = float(np.nanmax(v)) if np.isfinite(v).any() else 1.0
    decades = max(1, int(math.ceil(math.log10(1.0 + max(top, 1e-9)))))

    def x_of(g):
        return GAP_BAR_WIDTH * np.log10(1.0 + np.maximum(g, 0.0)) / decades

    h = GAP_BAR_ROW / (S + 1)
    centers, halves, colors, vals = [], [], [], []
    for s in range(S):
        for i in range(N):
            if not np.isfinite(v[s, i]):
                continue
            x = float(x_of(v[s, i]))
            y = i * GAP_BAR_ROW + (s + 0.5) * h + 0.5 * h
            centers.append([x / 2.0, y])
            halves.append([max(x / 2.0, 0.5), 0.45 * h])
            colors.append(GAP_SERIES_COLORS[s % len(GAP_SERIES_COLORS)])
            vals.append(f"{v[s, i]:.3g}")
    if centers:
        # a bar is a thick line from 0 to its value (Boxes2D are outlines only)
        strips = [np.array([[0.0, c[1]], [2.0 * c[0], c[1]]]) for c in centers]
        rec.log(f"{entity}/bars", rr.LineStrips2D(strips, colors=np.asarray(colors),
                                                  radii=np.asarray([hh[1] for hh in halves], dtype=np.float32),
                                                  draw_order=2.0), static=static)
        tips = np.asarray(centers, dtype=np.float32) * [2.0, 1.0] + [40.0, 0.0]
        rec.log(f"{entity}/values", rr.Points2D(tips, labels=vals, radii=0.1, colors=np.asarray(colors),
                                                show_labels=True, draw_order=3.0), static=static)
    rec.log(f"{entity}/labels", rr.Points2D(np.array([[-260.0, (i + 0.5) * GAP_BAR_ROW] for i in range(N)],
                                                     dtype=np.float32),
                                            labels=labels, radii=0.1, colors=[220, 220, 220], show_labels=True),
            static=static)
    ticks = [0.0] + [10.0 ** k for k in range(decades + 1)]
    axis = [np.array([[0.0, -8.0], [GAP_BAR_WIDTH, -8.0]])] + [np.array([[float(x_of(t)), -14.0], [float(x_of(t)), -8.0]])
                                                              for t in ticks]
    rec.log(f"{entity}/axis", rr.LineStrips2D(axis, colors=[200, 200, 200], radii=1.0), static=static)
    rec.log(f"{entity}/tick_labels", rr.Points2D(np.array([[float(x_of(t)), -30.0] for t in ticks] +
                                                          [[GAP_BAR_WIDTH / 2.0, -58.0]], dtype=np.float32),
                                                 labels=[tick_label(t) for t in ticks] + [title], radii=0.1,
                                                 colors=[220, 220, 220], show_labels=True), static=static)
    leg = np.array([[GAP_BAR_WIDTH + 60.0, 20.0 + 30.0 * s] for s in range(S)], dtype=np.float32)
    rec.log(f"{entity}/legend", rr.Points2D(leg, labels=list(series_names), radii=6.0,
                                            colors=GAP_SERIES_COLORS[np.arange(S) % len(GAP_SERIES_COLORS)],
                                            show_labels=True), static=static)


def log_gap_images(rec: rr.RecordingStream, step: int, images: dict, note: str, *, residual_range_m: float,
                   timeline: str = "capture") -> None:
    """One capture's images at step ``step`` of ``timeline``.

    Parameters
    ----------
    images : dict
        ``residual/<model>`` -> (H, W) mean residual over the frames [m] (NaN: no data), coloured blue
        (nearer than the truth) to red (farther) over +-``residual_range_m``; ``fill/<model>`` -> (H, W)
        fraction of frames with data, coloured 0 (dark) to 1 (yellow). Logged at ``gap/<key>``.
    note : str
        Markdown logged at ``gap/capture``.
    """
    set_time(rec, timeline, sequence=int(step))
    e = max(float(residual_range_m), 1e-6)
    for key, img in images.items():
        a = np.asarray(img, dtype=np.float64)
        if a.ndim != 2:
            raise ValueError(f"image {key} must be 2-D, got shape {a.shape}")
        if key.startswith("residual/"):
            rgb = colormap(a, -e, e, "turbo")
        elif key.startswith("fill/"):
            rgb = colormap(a, 0.0, 1.0, "viridis")
        else:
            raise ValueError(f"image keys start with residual/ or fill/, got {key!r}")
        log_rgb_image(rec, f"gap/{key}", rgb)
    log_text(rec, "gap/capture", note, static=False)


def gap_blueprint(bar_charts: Sequence[tuple[str, int]], image_keys: Sequence[str],
                  text_entity: str = "gap/summary") -> rrb.Blueprint:
    """Layout of a gap diagnosis: the bar charts in tabs on the left; the residual and fill images (a grid,
    stepped along the ``capture`` timeline), the capture's note and the summary on the right.

    Parameters
    ----------
    bar_charts : sequence of (entity, n_rows)
    image_keys : sequence of str
        Keys of :func:`log_gap_images` (``residual/real`` ...), in grid order.
    """
    charts = []
    for e, n in bar_charts:
        xb, yb = gap_bar_bounds(n)
        charts.append(rrb.Spatial2DView(origin=e, name=e.rsplit("/", 1)[-1],
                                        visual_bounds=rrb.VisualBounds2D(x_range=xb, y_range=yb)))
    right = []
    if image_keys:
        right.append(rrb.Grid(*[rrb.Spatial2DView(origin=f"gap/{k}", name=k) for k in image_keys],
                              grid_columns=3 if len(image_keys) > 4 else 2))
        right.append(rrb.TextDocumentView(origin="gap/capture", name="capture"))
    right.append(rrb.TextDocumentView(origin=text_entity, name="summary"))
    left = rrb.Tabs(*charts, active_tab=0) if len(charts) > 1 else (charts[0] if charts else None)
    parts = [rrb.Horizontal(left, rrb.Vertical(*right, row_shares=[3, 1, 2][:len(right)]), column_shares=[1, 1])
             if left is not None else rrb.Vertical(*right)]
    parts.append(rrb.TimePanel(state="collapsed", timeline="capture"))
    return rrb.Blueprint(*parts, collapse_panels=False)
