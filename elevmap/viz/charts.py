"""Static 2-D charts drawn in rerun: axes, ticks, labels, legend and curves as ``LineStrips2D``.

rerun 0.41 has time-series views but no x-y chart, so a chart is drawn on a canvas of
:data:`PLOT_CANVAS` units (y down, as in 2-D views) and shown in a ``Spatial2DView`` framed by
:data:`PLOT_VISUAL_BOUNDS`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import rerun as rr

__all__ = ["log_series_plot", "tick_label", "PLOT_CANVAS", "PLOT_VISUAL_BOUNDS", "SERIES_COLORS"]


#: Size (width, height) of the chart canvas of :func:`log_series_plot`, in canvas units (y down).
PLOT_CANVAS = (1000.0, 600.0)
#: Visual bounds (x_range, y_range) of a 2-D view showing a whole chart with its labels.
PLOT_VISUAL_BOUNDS = ((-125.0, 1190.0), (-95.0, 720.0))

#: Default curve colours (RGB uint8), cycled.
SERIES_COLORS = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                           [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]],
                          dtype=np.uint8)


def _nice_ticks(lo: float, hi: float, n: int = 6) -> np.ndarray:
    span = hi - lo
    raw = span / max(n, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=10 * mag)
    first = math.ceil(lo / step - 1e-9) * step
    return np.arange(first, hi + 1e-9 * span, step)


def tick_label(v: float) -> str:
    """A short tick label: 0, plain ``%g``, or ``%.0e`` for very large and very small values."""
    if v == 0:
        return "0"
    if abs(v) >= 1e6 or abs(v) < 1e-3:
        return f"{v:.0e}"
    return f"{v:g}"


def log_series_plot(rec: rr.RecordingStream, entity: str, xs, ys, *, names: Sequence[str] | None = None,
                    colors=None, x_label: str = "", y_label: str = "", title: str = "",
                    x_range: tuple[float, float] | None = None, y_range: tuple[float, float] | None = None,
                    log_y: bool = False, dashed: Sequence[bool] | None = None, static: bool = True) -> None:
    """Draw static curves as a 2-D chart (axes, ticks, labels, legend) with ``LineStrips2D``.

    Points outside the axis ranges are not drawn (the curve is cut there).

    The chart is drawn on a canvas of :data:`PLOT_CANVAS` units (y down, as in 2-D views) and is
    visible whatever the selected timeline; show it in a ``Spatial2DView`` with
    :data:`PLOT_VISUAL_BOUNDS` (:func:`default_blueprint` does so for ``plot_entities``).
    Sub-entities: ``<entity>/frame`` (axes and ticks), ``<entity>/tick_labels``, ``<entity>/curves``,
    ``<entity>/legend``.

    Parameters
    ----------
    xs : array_like, shape (M,), or a sequence of C arrays
        Abscissae, shared by all curves or one array per curve.
    ys : array_like, shape (C, M) or (M,), or a sequence of C arrays
        Ordinates; non-finite values (and values <= 0 with ``log_y``) break a curve.
    names : sequence of C str, optional
        Legend entries.
    colors : array_like, shape (C, 3) uint8, optional
    x_range, y_range : (float, float), optional
        Axis limits; the data's extent by default. With ``log_y`` the y limits must be > 0.
    log_y : bool
        Logarithmic y axis (decade ticks).
    dashed : sequence of C bool, optional
        Draw these curves dashed.
    """
    y_list = [np.asarray(y, dtype=np.float64).ravel() for y in (ys if _is_ragged(ys) else np.atleast_2d(ys))]
    C = len(y_list)
    if _is_ragged(xs) or (np.ndim(xs) == 2):
        x_list = [np.asarray(x, dtype=np.float64).ravel() for x in xs]
    else:
        x_list = [np.asarray(xs, dtype=np.float64).ravel()] * C
    if len(x_list) != C or any(len(x) != len(y) for x, y in zip(x_list, y_list)):
        raise ValueError("xs and ys must give one abscissa per ordinate for every curve")
    names = [f"series {k}" for k in range(C)] if names is None else [str(n) for n in names]
    if len(names) != C:
        raise ValueError(f"{len(names)} names for {C} curves")
    cols = SERIES_COLORS[np.arange(C) % len(SERIES_COLORS)] if colors is None else np.asarray(colors, np.uint8)
    dashed = [False] * C if dashed is None else [bool(d) for d in dashed]

    def fy(y):
        if not log_y:
            return y
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(y > 0, np.log10(y), np.nan)

    all_x = np.concatenate(x_list)
    all_y = np.concatenate([fy(y) for y in y_list])
    xlo, xhi = x_range if x_range is not None else (np.nanmin(all_x), np.nanmax(all_x))
    if y_range is not None:
        ylo, yhi = fy(np.asarray(y_range, dtype=np.float64))
    else:
        ylo, yhi = np.nanmin(all_y), np.nanmax(all_y)
        if log_y:
            ylo, yhi = math.floor(ylo), math.ceil(yhi)
    if not (np.isfinite([xlo, xhi, ylo, yhi]).all() and xhi > xlo and yhi > ylo):
        raise ValueError("cannot derive finite axis ranges from the data; give x_range / y_range")
    Wc, Hc = PLOT_CANVAS

    def to_canvas(x, y):
        return np.stack([(x - xlo) / (xhi - xlo) * Wc, Hc - (y - ylo) / (yhi - ylo) * Hc], axis=-1)

    # axes, grid and ticks
    frame = [np.array([[0, 0], [Wc, 0], [Wc, Hc], [0, Hc], [0, 0]], dtype=np.float64)]
    grid = []
    labels_pos, labels_txt = [], []
    for xt in _nice_ticks(xlo, xhi):
        cx = (xt - xlo) / (xhi - xlo) * Wc
        frame.append(np.array([[cx, Hc], [cx, Hc + 10]]))
        grid.append(np.array([[cx, 0], [cx, Hc]]))
        labels_pos.append([cx, Hc + 14])
        labels_txt.append(tick_label(xt))
    if log_y:
        yt_list = np.arange(math.ceil(ylo - 1e-9), math.floor(yhi + 1e-9) + 1)
        ytxt = [tick_label(10.0 ** k) for k in yt_list]
    else:
        yt_list = _nice_ticks(ylo, yhi)
        ytxt = [tick_label(v) for v in yt_list]
    for yt, txt in zip(yt_list, ytxt):
        cy = Hc - (yt - ylo) / (yhi - ylo) * Hc
        frame.append(np.array([[-10, cy], [0, cy]]))
        grid.append(np.array([[0, cy], [Wc, cy]]))
        labels_pos.append([-60, cy])
        labels_txt.append(txt)
    rec.log(f"{entity}/frame", rr.LineStrips2D(frame, colors=[200, 200, 200], radii=1.0, draw_order=1.0),
            static=static)
    rec.log(f"{entity}/grid", rr.LineStrips2D(grid, colors=[90, 90, 90], radii=0.5, draw_order=0.5),
            static=static)
    labels_pos += [[Wc / 2, Hc + 50], [60, -25], [Wc / 2, -68]]
    labels_txt += [x_label, y_label, title]
    rec.log(f"{entity}/tick_labels", rr.Points2D(np.asarray(labels_pos, dtype=np.float32), labels=labels_txt,
                                                 radii=0.1, colors=[220, 220, 220], show_labels=True),
            static=static)

    # curves, clipped to the axes; breaks at non-finite values
    strips, strip_cols, legend_pos = [], [], []
    for k, (x, y) in enumerate(zip(x_list, y_list)):
        yy = fy(y)
        ok = np.isfinite(x) & np.isfinite(yy) & (x >= xlo) & (x <= xhi) & (yy >= ylo) & (yy <= yhi)
        pts = to_canvas(x, yy)
        runs = np.split(np.arange(len(x)), np.flatnonzero(np.diff(ok.astype(np.int8)) != 0) + 1)
        last = None
        for run in runs:
            if len(run) < 2 or not ok[run[0]]:
                continue
            seg = pts[run]
            if dashed[k]:
                seg_list = _dash(seg, 14.0)
            else:
                seg_list = [seg]
            strips += seg_list
            strip_cols += [cols[k]] * len(seg_list)
            last = seg[-1]
        legend_pos.append(last if last is not None else [Wc, 0])
    if strips:
        rec.log(f"{entity}/curves", rr.LineStrips2D(strips, colors=np.asarray(strip_cols), radii=2.0,
                                                    draw_order=2.0), static=static)
    legend_pos = np.asarray(legend_pos, dtype=np.float64) + [8.0, 0.0]
    legend_pos[:, 1] = _spread(legend_pos[:, 1], min_gap=min(70.0, Hc / max(C, 1)), lo=0.0, hi=Hc)
    rec.log(f"{entity}/legend", rr.Points2D(legend_pos.astype(np.float32), labels=names, colors=cols,
                                            radii=4.0, show_labels=True, draw_order=3.0), static=static)


def _spread(y: np.ndarray, min_gap: float, lo: float, hi: float) -> np.ndarray:
    """Move label heights ``y`` apart by at least ``min_gap`` (order kept), staying within [lo, hi]."""
    order = np.argsort(y, kind="stable")
    ys = y[order].astype(np.float64).copy()
    for k in range(1, len(ys)):
        ys[k] = max(ys[k], ys[k - 1] + min_gap)
    overflow = ys[-1] - hi if len(ys) else 0.0
    if overflow > 0:
        ys[-1] -= overflow
        for k in range(len(ys) - 2, -1, -1):
            ys[k] = min(ys[k], ys[k + 1] - min_gap)
    ys = np.maximum(ys, lo)
    out = np.empty_like(ys)
    out[order] = ys
    return out


def _is_ragged(a) -> bool:
    return isinstance(a, (list, tuple)) and len(a) > 0 and np.ndim(a[0]) == 1


def _dash(seg: np.ndarray, dash: float) -> list:
    """Cut a polyline into dashes of length ``dash`` separated by gaps of the same length."""
    d = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(seg, axis=0), axis=1))])
    out = []
    s = 0.0
    while s < d[-1]:
        e = min(s + dash, d[-1])
        t = np.concatenate([[s], d[(d > s) & (d < e)], [e]])
        out.append(np.stack([np.interp(t, d, seg[:, 0]), np.interp(t, d, seg[:, 1])], axis=1))
        s += 2 * dash
    return out
