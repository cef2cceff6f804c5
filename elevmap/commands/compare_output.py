"""The output of ``elevmap compare``: the plain-text tables and the rerun recording.

Recording (``rrd_path`` of :func:`elevmap.commands.compare.run_compare`; entity paths)::

    maps                        ViewCoordinates z up
    maps/truth/elevation        the true terrain over the final map's cells (mesh, coloured by height)
    maps/<mapper>/elevation     each final map, coloured by height (hidden at start)
    maps/<mapper>/error         each final map, coloured by its signed error (blue below, red above
                                the truth, +-ERROR_COLOR_RANGE_M)
    maps/<mapper>/trail         the camera's path
    errors/<mapper>             signed error image (map seen from above, +x up, +y left)
    zscores/<mapper>            |error| / sigma image (0 to 4)
    camera/depth                the depth frames (PNG-compressed)
    plots/<metric>/<mapper>     RMSE, 2-sigma coverage and mean sigma over the frames
    result                      the table
"""

from __future__ import annotations

import math

import numpy as np

from ..fileio import json_ready
from ..pipeline import map_error
from .compare_scores import truth_grid

__all__ = ["format_table", "CompareLogger", "ERROR_COLOR_RANGE_M", "ZSCORE_COLOR_RANGE"]

#: Colour range of the signed error meshes and images [m].
ERROR_COLOR_RANGE_M = 0.10
#: Colour range of the z-score images |error| / sigma.
ZSCORE_COLOR_RANGE = (0.0, 4.0)


def _fmt(v, scale=1.0, digits=1):
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v * scale:.{digits}f}"


def _reality_text(report: dict) -> str:
    reality = report.get("reality", "reference")
    if reality == "stereo":
        reality += f" (preset {report.get('preset')})"
    elif reality == "gap":
        reality += f" ({report.get('gap_report')})"
    return reality


def _table(cols, units, rows) -> list[str]:
    widths = [max(len(str(r[k])) for r in rows + [cols, units]) for k in range(len(cols))]
    line = lambda r: "  ".join(str(x).ljust(w) if k == 0 else str(x).rjust(w)  # noqa: E731
                               for k, (x, w) in enumerate(zip(r, widths)))
    return [line(cols), line(units)] + [line(r) for r in rows]


def format_table(report: dict) -> str:
    """The report as a plain-text table (mm, %, ms): the scores, the step-edge band, common and matched."""
    eff = ", ".join(f"{e['name']}({', '.join(f'{k}={v:g}' for k, v in e['params'].items() if v is not None)})"
                    for e in report["sim_effects"]) or "none"
    head = (f"scene {report['scene']}, {report['frames']} frames {report['width']}x{report['height']}, "
            f"seed {report['seed']}, reality {_reality_text(report)}, sim effects: {eff}, cap {report['cap']:g}")
    cols = ("mapper", "RMSE", "p95|e|", "NLL", "cov1s", "cov2s", "mean s", "flat", "known", "ms/fr",
            "| edge:", "RMSE", "bias", "cov2s", "known", "| common:", "RMSE", "NLL", "cov2s", "| matched:", "RMSE",
            "NLL", "cov2s")
    units = ("", "mm", "mm", "", "%", "%", "mm", "mm", "%", "ms", "", "mm", "mm", "%", "%", "", "mm", "", "%", "",
             "mm", "", "%")
    rows = []
    common = report.get("common", {}).get("mappers", {})
    matched = report.get("matched", {}).get("mappers", {})
    for name, m in report["mappers"].items():
        c, q = common.get(name, {}), matched.get(name, {})
        rows.append((name, _fmt(m["rmse_m"], 1e3), _fmt(m["p95_abs_m"], 1e3), _fmt(m["nll"], 1, 2),
                     _fmt(m["coverage_1sigma"], 100), _fmt(m["coverage_2sigma"], 100), _fmt(m["mean_sigma_m"], 1e3),
                     _fmt(m["flat_rmse_m"], 1e3), _fmt(m["known_fraction"], 100), _fmt(m["ms_per_frame"], 1, 2),
                     "|", _fmt(m["edge_rmse_m"], 1e3), _fmt(m.get("edge_mean_error_m"), 1e3),
                     _fmt(m.get("edge_coverage_2sigma"), 100), _fmt(m.get("edge_known_fraction"), 100),
                     "|", _fmt(c.get("rmse_m"), 1e3), _fmt(c.get("nll"), 1, 2),
                     _fmt(c.get("coverage_2sigma"), 100), "|", _fmt(q.get("rmse_m"), 1e3), _fmt(q.get("nll"), 1, 2),
                     _fmt(q.get("coverage_2sigma"), 100)))
    out = [head] + _table(cols, units, rows)
    out.append(f"edge: the known cells within two cells of a step; its 'known' is the fraction of the "
               f"{report.get('edge_band_cells', 0)} band cells some mapper knows. common: the "
               f"{report.get('common', {}).get('cells', 0)} cells known to every mapper; matched: each mapper's "
               f"{report.get('matched', {}).get('cells', 0)} most confident cells (the fewest any mapper knows); "
               "ideal coverage 68.3 % (1 sigma) and 95.4 % (2 sigma); NLL in nats (lower is better)")
    return "\n".join(out)


class CompareLogger:
    """Everything a comparison sends to rerun (through elevmap.viz)."""

    def __init__(self, path, names, frames, show_progress):
        from .. import viz

        self.viz = viz
        self.names = list(names)
        self.recording = viz.open_recording(path, "elevmap_compare")
        self.rec = self.recording.__enter__()
        try:
            self._start(frames)
        except BaseException as exc:
            self.abort(exc)
            raise

    def _start(self, frames):
        viz = self.viz
        viz.log_world_frame(self.rec, "maps")
        for name in ["truth"] + self.names:
            viz.log_world_frame(self.rec, f"maps/{name}")
        f0 = frames[0]
        viz.log_camera(self.rec, "camera/depth", f0.K, f0.width, f0.height, static=True)
        self.trail = np.array([f.T_map_cam[:3, 3] for f in frames])
        for k, f in enumerate(frames):
            viz.set_time(self.rec, "frame", sequence=k)
            if f.depth.dtype == np.uint16:
                viz.log_depth_png(self.rec, "camera/depth", f.depth, meter=1.0 / f.depth_scale)
            else:
                viz.log_depth(self.rec, "camera/depth", f.depth)

    def frame_callback(self, truth):
        viz, rec = self.viz, self.rec

        def on_frame(name, k, emap):
            viz.set_time(rec, "frame", sequence=k)
            err = map_error(emap, truth)
            if err["known_cells"]:
                viz.log_scalar(rec, f"plots/rmse_m/{name}", err["rmse_m"])
                viz.log_scalar(rec, f"plots/coverage_2sigma/{name}", err["coverage_2sigma"])
                var = emap.known_layer("variance")
                viz.log_scalar(rec, f"plots/mean_sigma_m/{name}", float(np.nanmean(np.sqrt(var))))
        return on_frame

    def final(self, maps, truth, walk, report):
        viz, rec = self.viz, self.rec
        viz.set_time(rec, "frame", sequence=report["frames"] - 1)
        first = next(iter(maps.values()))
        xs, ys = first.cell_centres()
        tr = truth_grid(first, truth)
        lo, hi = viz.robust_range(tr)
        viz.log_height_mesh(rec, "maps/truth/elevation", xs, ys, tr, viz.colormap(tr, lo, hi))
        viz.log_trail(rec, "maps/truth/trail", self.trail)
        e = ERROR_COLOR_RANGE_M
        for name, emap in maps.items():
            h, v = emap.known_layer("elevation"), emap.known_layer("variance")
            err = h - tr
            viz.log_height_mesh(rec, f"maps/{name}/elevation", xs, ys, h, viz.colormap(h, lo, hi))
            viz.log_height_mesh(rec, f"maps/{name}/error", xs, ys, h, viz.colormap(err, -e, e))
            viz.log_trail(rec, f"maps/{name}/trail", self.trail)
            viz.log_rgb_image(rec, f"errors/{name}", viz.map_image(viz.colormap(err, -e, e)))
            with np.errstate(invalid="ignore"):
                zs = np.abs(err) / np.sqrt(v)
            viz.log_rgb_image(rec, f"zscores/{name}", viz.map_image(viz.colormap(zs, *ZSCORE_COLOR_RANGE)))
        table = format_table(json_ready(report))
        notes = (f"# elevmap compare\n\n```\n{table}\n```\n\nMaps: `maps/<mapper>/error` is each final map coloured "
                 f"by its signed error (blue: below the truth, green: right, red: above; +-{e * 100:.0f} cm); "
                 f"`elevation` (hidden) by height. Tabs: signed error images and |error|/sigma images "
                 f"(0 to 4; calibrated maps are mostly below 2).")
        viz.log_text(rec, "result", notes)
        cx, cy = first.centre_xy
        names = ["truth"] + self.names
        bp = viz.compare_blueprint(
            [f"maps/{n}" for n in names],
            image_grids=[("errors", [f"errors/{n}" for n in self.names]),
                         ("z-scores", [f"zscores/{n}" for n in self.names])],
            time_series_entities=["plots/rmse_m", "plots/coverage_2sigma", "plots/mean_sigma_m"],
            text_entities=["result"], depth_entities=["camera/depth"], timeline="frame",
            hidden_entities=[f"maps/{n}/elevation" for n in self.names],
            eye_position=(cx - 3.0, cy - 3.5, 3.5), eye_look_target=(cx + 0.5, cy, 0.0))
        rec.send_blueprint(bp)

    def abort(self, exc):
        self.recording.__exit__(type(exc), exc, exc.__traceback__)

    def close(self):
        self.recording.__exit__(None, None, None)
