"""Viewer layouts (rerun blueprints) of a mapping run and of a comparison of mappers.

The layouts of the reports of ``elevmap characterize`` and ``elevmap gap`` are beside their logging
functions in :mod:`elevmap.viz.reports`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import rerun.blueprint as rrb

from .charts import PLOT_VISUAL_BOUNDS

__all__ = ["default_blueprint", "compare_blueprint"]


def default_blueprint(depth_entities: Sequence[str] = (), plot_entities: Sequence[str] = (),
                      time_series_entities: Sequence[str] = (), text_entities: Sequence[str] = (),
                      world: str = "world", timeline: str | None = None, hidden_entities: Sequence[str] = (),
                      eye_position=None, eye_look_target=None) -> rrb.Blueprint:
    """The default viewer layout: 3-D ``world`` on the left, depth images and plots on the right.

    Parameters
    ----------
    depth_entities : sequence of str
        Pinhole entities holding depth images (``world/camera_<i>/depth``), one 2-D view each.
    plot_entities : sequence of str
        Charts drawn by :func:`log_series_plot`, one 2-D view each, framed by PLOT_VISUAL_BOUNDS.
    time_series_entities : sequence of str
        Subtrees of ``Scalars`` (from :func:`log_scalar`), one time-series view each.
    text_entities : sequence of str
        Markdown notes (from :func:`log_text`), shown under the 3-D view.
    world : str
        Root of the 3-D view.
    timeline : str, optional
        Timeline selected in the time panel.
    hidden_entities : sequence of str
        Entities of the 3-D view hidden at start (full paths; the user can switch them on).
    eye_position, eye_look_target : array_like, shape (3,), optional
        Initial 3-D eye position and the point it looks at, in the ``world`` frame [m].
    """
    eye = None
    if eye_position is not None and eye_look_target is not None:
        eye = rrb.EyeControls3D(position=np.asarray(eye_position, dtype=np.float64),
                                look_target=np.asarray(eye_look_target, dtype=np.float64), eye_up=[0.0, 0.0, 1.0])
    overrides = {e: rrb.EntityBehavior(visible=False) for e in hidden_entities}
    left = [rrb.Spatial3DView(origin=world, name=world, eye_controls=eye, overrides=overrides or None)]
    left += [rrb.TextDocumentView(origin=e, name=e.rsplit("/", 1)[-1]) for e in text_entities]
    left_c = rrb.Vertical(*left, row_shares=[3] + [1] * (len(left) - 1)) if len(left) > 1 else left[0]
    right = []
    if depth_entities:
        views = [rrb.Spatial2DView(origin=e, name=e.strip("/").split("/")[-2] if "/" in e.strip("/") else e)
                 for e in depth_entities]
        right.append(rrb.Grid(*views, grid_columns=2 if len(views) > 1 else 1))
    (xb, yb) = PLOT_VISUAL_BOUNDS
    for e in plot_entities:
        right.append(rrb.Spatial2DView(origin=e, name=e.rsplit("/", 1)[-1],
                                       visual_bounds=rrb.VisualBounds2D(x_range=xb, y_range=yb)))
    right += [rrb.TimeSeriesView(origin=e, name=e.rsplit("/", 1)[-1]) for e in time_series_entities]
    parts = [rrb.Horizontal(left_c, rrb.Vertical(*right), column_shares=[3, 2]) if right else left_c]
    parts.append(rrb.TimePanel(state="collapsed", timeline=timeline))
    return rrb.Blueprint(*parts, collapse_panels=False)


def compare_blueprint(map_views: Sequence[str], image_grids: Sequence[tuple[str, Sequence[str]]] = (),
                      time_series_entities: Sequence[str] = (), text_entities: Sequence[str] = (),
                      depth_entities: Sequence[str] = (), timeline: str | None = None,
                      hidden_entities: Sequence[str] = (), eye_position=None, eye_look_target=None) -> rrb.Blueprint:
    """Layout of a comparison: one 3-D view per map side by side, image grids in tabs, notes and plots.

    Parameters
    ----------
    map_views : sequence of str
        Roots of the 3-D views (one per mapper, e.g. ``maps/paper``), in a grid; each is z-up.
    image_grids : sequence of (str, sequence of str)
        Tabs of 2-D views: a tab name and the image entities shown in a grid in that tab.
    time_series_entities : sequence of str
        Subtrees of scalars (:func:`log_scalar`), one time-series view each.
    text_entities : sequence of str
        Markdown notes (:func:`log_text`).
    depth_entities : sequence of str
        Pinhole entities with depth images, one 2-D view each.
    timeline : str, optional
        Timeline selected in the time panel.
    hidden_entities : sequence of str
        Entities hidden at start in the 3-D views.
    eye_position, eye_look_target : array_like, shape (3,), optional
        The same initial eye for every 3-D view [m].
    """
    eye = None
    if eye_position is not None and eye_look_target is not None:
        eye = rrb.EyeControls3D(position=np.asarray(eye_position, dtype=np.float64),
                                look_target=np.asarray(eye_look_target, dtype=np.float64), eye_up=[0.0, 0.0, 1.0])
    views3d = []
    for origin in map_views:
        hidden = {e: rrb.EntityBehavior(visible=False) for e in hidden_entities if e.startswith(origin + "/")}
        views3d.append(rrb.Spatial3DView(origin=origin, name=origin.rsplit("/", 1)[-1], eye_controls=eye,
                                         overrides=hidden or None))
    cols = 3 if len(views3d) > 4 else 2
    tabs = [rrb.Grid(*views3d, grid_columns=cols, name="maps")] if views3d else []
    for name, entities in image_grids:
        views = [rrb.Spatial2DView(origin=e, name=e.rsplit("/", 1)[-1]) for e in entities]
        if views:
            tabs.append(rrb.Grid(*views, grid_columns=3 if len(views) > 4 else 2, name=name))
    left = rrb.Tabs(*tabs, active_tab=0) if len(tabs) > 1 else tabs[0]
    right = [rrb.TextDocumentView(origin=e, name=e.rsplit("/", 1)[-1]) for e in text_entities]
    right += [rrb.Spatial2DView(origin=e, name=e.strip("/").split("/")[-2] if "/" in e.strip("/") else e)
              for e in depth_entities]
    right += [rrb.TimeSeriesView(origin=e, name=e.rsplit("/", 1)[-1]) for e in time_series_entities]
    parts = [rrb.Horizontal(left, rrb.Vertical(*right), column_shares=[3, 2]) if right else left]
    parts.append(rrb.TimePanel(state="collapsed", timeline=timeline))
    return rrb.Blueprint(*parts, collapse_panels=False)
