"""``afmid report RESULT.h5 -o DIR`` for a force-map result (``format: afmid-map-result``).

Writes into a report folder (:mod:`afmid.report.folder`: new, or an earlier afmid report with ``--overwrite``):
one image per parameter map and its 1-sigma map (colour bar with units: nm, MPa, Pa s, nN, zJ), the topography
(from the separation), the error relative to its noise floor, the pixel status and how each pixel was fitted,
a histogram per parameter (ok and suspect pixels apart), ``summary.json`` (per parameter: median, spread and
pixel counts; the failed and suspect pixels with their messages) and a self-contained ``report.html``.
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path

import numpy as np

from afmid.report.figures import figure_html, save_figure
from afmid.report.map_result import MAP_RESULT_FORMAT, read_map_result  # the layout and version checked there
from afmid.report.quantity_text import display_unit

#: Pixels listed by name in the HTML (all of them are in summary.json).
MAX_LISTED = 50
STATUS_COLOURS = ("#2ca02c", "#ff7f0e", "#d62728")


def is_map_result(path: Path) -> bool:
    """True when ``path`` is an HDF5 file written by ``afmid map``. Anything but a regular file (a FIFO would
    block the open) is left to the run-file reader's checks and messages."""
    import h5py

    if not Path(path).is_file():
        return False
    try:
        with h5py.File(path, "r") as h5:
            return h5.attrs.get("format") == MAP_RESULT_FORMAT
    except OSError:
        return False


def parameter_names(maps: dict) -> list[str]:
    """The physical parameters of the map (those with a ``_sigma`` map), in file order."""
    return [name for name in maps if f"{name}_sigma" in maps and name != "separation"]


def make_map_report(path: Path, output: Path, overwrite: bool = False, before: Path | None = None) -> str:
    """Write the report folder of the map result ``path``; returns the terminal summary. ``before``: the result of
    an earlier fit of the same map (e.g. before ``afmid map --add EFFECT``): the error over its floor is drawn
    before and after (afmid.report.map_groups). The page opens with its answer (which effect is missing where, the
    values per group of pixels), links the map explorer (afmid.report.map_explorer, ``explorer.html``) and then
    shows the maps."""
    import afmid.report.map_groups as map_groups
    from afmid.report.folder import report_folder
    from afmid.report.map_explorer import write_explorer
    from afmid.report.map_values import group_values, selected_maps

    result = read_map_result(path)
    groups = map_groups.read_groups(path)
    compared = (map_groups.comparison(before, read_map_result(before)["maps"], result["maps"])
                if before is not None else None)
    maps = result["maps"]
    status = maps["status"][0].astype(int)
    message = np.vectorize(lambda m: m.decode() if isinstance(m, bytes) else str(m))(maps["message"][0])
    names = parameter_names(maps)
    selected = selected_maps(path, names)
    per_group = group_values(maps, names, groups, selected, status < 2)
    inputs = {path: "the map result", **({before: "the earlier map result"} if before is not None else {})}
    with report_folder(Path(output), overwrite, inputs) as tmp:
        extent = _extent(status.shape, result["pixel_size"])
        answer = []  # the figures the page opens with
        if groups is not None:
            answer.append(map_groups.groups_figure(tmp, groups, extent))
        if compared is not None:
            answer.append(map_groups.comparison_figure(tmp, compared, extent))
        figures = []
        for name in names:
            values, unit, _ = maps[name]
            sigma = maps[f"{name}_sigma"][0]
            figures.append(_map_figure(tmp, name, np.where(selected[name], values, np.nan),
                                       np.where(selected[name], sigma, np.nan), unit, status, extent,
                                       unselected=int(np.sum(~selected[name] & (status < 2)))))
            figures.append(_histogram(tmp, name, np.where(selected[name], values, np.nan), unit, status))
        sep, _, _ = maps["separation"]
        height = np.nanmax(sep) - sep  # the sample is higher where the rest separation is smaller
        figures.append(_map_figure(tmp, "topography", height, None, "m", status, extent,
                                   label="height (from the separation)"))
        ratio = maps["cv_error"][0] / maps["cv_error_noise_floor"][0]
        figures.append(_map_figure(tmp, "error_over_floor", ratio, None, "1", status, extent,
                                   label="cv error / noise floor (1: at the floor)"))
        figures.append(map_groups.residual_figure(tmp, maps, extent))
        figures = [f for f in figures if f is not None]
        figures.append(_status_figure(tmp, status, maps.get("fit_route"), extent))
        summary = _summary(path, result, names, status, message, selected)
        summary.update(map_groups.groups_summary(groups, compared))
        if per_group:
            summary["parameters_per_group"] = per_group
        explorer = write_explorer(tmp, path, result, groups, selected, names)
        section = map_groups.groups_html(groups, compared, per_group, [f for f in answer if f is not None], tmp)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2), encoding="utf-8")
        (tmp / "report.html").write_text(_html(path, summary, figures, tmp, section, explorer), encoding="utf-8")
    counts = summary["pixels"]
    lines = [f"map {summary['rows']}x{summary['cols']}: {counts['ok']} ok, {counts['suspect']} suspect, "
             f"{counts['failed']} failed; {summary['model_limited']['pixels']} model-limited"]
    if groups is not None:
        lines.append(f"missing effects: {groups['summary']}")
        lines += [f"  {g['sentence']}" for g in groups["groups"]]
        lines += map_groups.group_value_lines(per_group, names)
    if compared is not None:
        lines += map_groups.comparison_lines(compared)
    lines.append("over all ok pixels (a blend when the map holds several phases):")
    for name, p in summary["parameters"].items():
        if p["selected_pixels"] == 0:
            lines.append(f"  {name}: not selected at any ok pixel")
            continue
        lines.append(f"  {name}: median {p['median']:.4g}{unit_suffix(p['unit'])} (ok pixels; 16-84 % {p['p16']:.4g} "
                     f".. {p['p84']:.4g}; median 1 sigma {p['median_sigma']:.2g})")
    if explorer is not None:
        lines.append(f"wrote {Path(output) / explorer} (hover or click a pixel: its force curve and diagnosis)")
    lines.append(f"wrote {Path(output) / 'report.html'}")
    return "\n".join(lines)


def unit_suffix(shown: str) -> str:
    """`` MPa`` after a number; nothing for a dimensionless value (no empty unit)."""
    return f" {shown}" if shown and shown != "1" else ""


def unit_label(title: str, shown: str) -> str:
    """``E_star [MPa]``; the title alone for a dimensionless value (never ``[]``)."""
    return f"{title} [{shown}]" if shown and shown != "1" else title


def _extent(shape: tuple[int, int], pixel_size: float | None):
    if pixel_size is None:
        return None, "pixel"
    rows, cols = shape
    scale = pixel_size * 1e9
    return (-0.5 * scale, (cols - 0.5) * scale, (rows - 0.5) * scale, -0.5 * scale), "nm"


def _plt():
    """pyplot with the single-trace report's publication style (afmid.report.figures.PAPER_STYLE)."""
    from afmid.report.figures import pyplot

    return pyplot()


def _map_figure(folder: Path, name: str, values: np.ndarray, sigma: np.ndarray | None, unit: str,
                status: np.ndarray, extent, label: str | None = None, unselected: int = 0) -> tuple[str, str]:
    plt = _plt()
    factor, shown = display_unit(unit)
    panels = [(values, label or name)] + ([(sigma, f"{name} 1 sigma")] if sigma is not None else [])
    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 3.8), squeeze=False, layout="tight")
    box, axis_unit = extent
    for ax, (data, title) in zip(axes[0], panels):
        shown_data = np.where(status < 2, data * factor, np.nan)
        image = ax.imshow(shown_data, extent=box, cmap="viridis", interpolation="nearest")
        bar = fig.colorbar(image, ax=ax)
        bar.set_label(unit_label(title, shown))
        ax.set_title(title)
        ax.set_xlabel(f"x [{axis_unit}]")
        ax.set_ylabel(f"y [{axis_unit}]")
        ax.grid(False)  # the style's grid would be drawn over the pixels
        failed = np.argwhere(status >= 2)
        if failed.size:
            _mark(ax, failed, box, status.shape, "x", "red")
        suspect = np.argwhere(status == 1)
        if suspect.size:
            _mark(ax, suspect, box, status.shape, "o", "orange")
    file = save_figure(fig, folder, f"map_{name}", dpi=90)
    caption = unit_label(label or name, shown) + (" and its 1-sigma map" if sigma is not None else "")
    if unselected:
        caption += f"; blank at the {unselected} fitted pixels where its term was not selected"
    return file, caption + "; failed pixels blank with a red x, suspect pixels ringed orange"


def _mark(ax, pixels: np.ndarray, box, shape: tuple[int, int], marker: str, colour: str) -> None:
    """Markers at the centres of ``pixels`` ((row, col) pairs) on an image drawn with ``extent=box``."""
    rows, cols = pixels[:, 0], pixels[:, 1]
    if box is None:
        xs, ys = cols, rows
    else:
        sx, sy = (box[1] - box[0]) / shape[1], (box[2] - box[3]) / shape[0]
        xs, ys = box[0] + (cols + 0.5) * sx, box[3] + (rows + 0.5) * sy
    if marker == "o":  # a ring: the pixel's value stays visible
        ax.scatter(xs, ys, marker=marker, facecolors="none", edgecolors=colour, s=40)
    else:  # a line marker (x, +) has no face: its colour is the line's
        ax.scatter(xs, ys, marker=marker, color=colour, s=40)


def _histogram(folder: Path, name: str, values: np.ndarray, unit: str, status: np.ndarray) -> tuple[str, str]:
    plt = _plt()
    factor, shown = display_unit(unit)
    fig, ax = plt.subplots(figsize=(4.6, 3.4), layout="tight")
    groups = [(values[status == 0] * factor, "ok", STATUS_COLOURS[0]),
              (values[status == 1] * factor, "suspect", STATUS_COLOURS[1])]
    finite = np.concatenate([g[np.isfinite(g)] for g, _, _ in groups])
    bins = np.histogram_bin_edges(finite, bins=30) if finite.size else 10
    for data, label, colour in groups:
        data = data[np.isfinite(data)]
        if data.size:
            ax.hist(data, bins=bins, alpha=0.7, label=f"{label} ({data.size})", color=colour)
    ax.set_xlabel(unit_label(name, shown))
    ax.set_ylabel("pixels")
    ax.legend()
    file = save_figure(fig, folder, f"hist_{name}", dpi=90)
    return file, f"histogram of {name} over the pixels (ok and suspect apart; failed pixels have no value)"


def _status_figure(folder: Path, status: np.ndarray, route, extent) -> tuple[str, str]:
    plt = _plt()
    from matplotlib.colors import ListedColormap

    from afmid.maps.pixel_fit import ROUTES
    from afmid.maps.task import STATUS_NAMES

    panels = [(status, ListedColormap(STATUS_COLOURS), STATUS_NAMES, "status")]
    if route is not None:
        panels.append((route[0], plt.get_cmap("tab10", len(ROUTES)), ROUTES, "how the pixel was fitted"))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 3.8), squeeze=False, layout="tight")
    box, axis_unit = extent
    for ax, (data, cmap, names, title) in zip(axes[0], panels):
        image = ax.imshow(np.where(data >= 0, data, np.nan), extent=box, cmap=cmap, vmin=-0.5,
                          vmax=len(names) - 0.5, interpolation="nearest")
        bar = fig.colorbar(image, ax=ax, ticks=range(len(names)))
        bar.ax.set_yticklabels(names, fontsize=7)
        ax.set_title(title)
        ax.set_xlabel(f"x [{axis_unit}]")
        ax.set_ylabel(f"y [{axis_unit}]")
        ax.grid(False)
    return save_figure(fig, folder, "map_status", dpi=90), "status per pixel (ok / suspect / failed) and how each pixel was fitted"


def _summary(path: Path, result: dict, names: list[str], status: np.ndarray, message: np.ndarray,
             selected: dict) -> dict:
    from afmid.report.map_values import value_stats

    maps = result["maps"]
    rows, cols = status.shape
    out = {"map_result": str(path), "rows": rows, "cols": cols,
           "pixel_fit": str(result["attrs"].get("pixel_fit", "")),
           "pixels": {"ok": int(np.sum(status == 0)), "suspect": int(np.sum(status == 1)),
                      "failed": int(np.sum(status >= 2))},
           "parameters": {}, "failed": [], "suspect": []}
    from afmid.fit.uncertainty import FLOOR_FACTOR

    ratio = maps["cv_error"][0] / maps["cv_error_noise_floor"][0]
    fitted = status < 2
    limited = fitted & (ratio > FLOOR_FACTOR)
    out["model_limited"] = {"pixels": int(limited.sum()), "fraction_of_fitted": float(limited.sum() / max(fitted.sum(), 1)),
                            "rule": f"cv_error above {FLOOR_FACTOR} x its noise floor (an effect the model lacks, "
                                    "or a poor fit): see map_error_over_floor.png; refit with afmid map --add EFFECT"}
    ok = status == 0
    for name in names:
        values, unit, _ = maps[name]
        stats = value_stats(values, maps[f"{name}_sigma"][0], ok, selected[name], unit)
        stats["n_ok"] = stats.pop("pixels")
        stats["sigma_kind"] = maps[f"{name}_sigma"][2]
        out["parameters"][name] = stats
    for code, key in ((2, "failed"), (1, "suspect")):
        for r, c in np.argwhere(status == code if code == 1 else status >= code):
            out[key].append({"row": int(r), "col": int(c), "message": str(message[r, c])})
    return out


def _html(path: Path, summary: dict, figures: list[tuple[str, str]], folder: Path, section: str = "",
          explorer: str | None = None) -> str:
    from afmid.report.map_values import stats_text
    from afmid.report.page import CSS

    counts = summary["pixels"]
    rows = "".join(f"<tr><td>{html.escape(name)}</td><td>{html.escape(stats_text({**p, 'pixels': p['n_ok']}))}</td>"
                   f"<td>{p['n_ok']}</td></tr>" for name, p in summary["parameters"].items())
    listed = []
    for key in ("failed", "suspect"):
        items = summary[key]
        if items:
            lis = "".join(f"<li>pixel (row {i['row']}, col {i['col']}): {html.escape(i['message'])}</li>"
                          for i in items[:MAX_LISTED])
            more = f"<p>... and {len(items) - MAX_LISTED} more (summary.json)</p>" if len(items) > MAX_LISTED else ""
            listed.append(f"<h2>{key.capitalize()} pixels ({len(items)})</h2><ul>{lis}</ul>{more}")
    body = "".join(figure_html(folder, f, c) for f, c in figures)
    link = (f"<p class='explorer'><a href=\"{html.escape(explorer)}\">Open the map explorer</a>: hover or click a "
            "pixel to see its force curve (approach and retraction, the model), its residual and its diagnosis beside "
            "the maps (one file, works offline).</p>" if explorer else "")
    return (
        "<!doctype html>\n<html><head><meta charset=\"utf-8\"><title>afmid map report</title>"
        f"<style>{CSS}\nfigure{{display:inline-block;margin:8px;vertical-align:top;max-width:100%}}"
        ".swatch{display:inline-block;width:.9em;height:.9em;margin-right:.3em;vertical-align:middle}</style>"
        "</head><body>"
        f"<h1>Force map: {html.escape(Path(path).name)}</h1>"
        f"<p>{summary['rows']} x {summary['cols']} pixels: {counts['ok']} ok, {counts['suspect']} suspect, "
        f"{counts['failed']} failed. Pixel fit: {html.escape(summary['pixel_fit'])}. "
        f"Model-limited (error above the noise floor): {summary['model_limited']['pixels']} pixels "
        f"({100 * summary['model_limited']['fraction_of_fitted']:.0f} % of the fitted). Forces on the tip, positive = "
        "repulsive.</p>"
        f"{section}{link}"
        "<h2>Over the whole map</h2><p>Medians over all ok pixels: over a map of several phases these blend them "
        "(the values per group above are the phases' own). \"not selected\": no term of the parameter's effect was "
        "selected (its value would read 0).</p>"
        "<table><tr><th>parameter</th><th>median (ok pixels), 16-84 %, median 1 sigma</th><th>ok pixels</th></tr>"
        f"{rows}</table><h2>Maps</h2>"
        f"{body}{''.join(listed)}</body></html>\n")
