"""The map explorer: one self-contained HTML page beside a force map's report (``explorer.html``).

Three maps side by side (which effect is missing where, the error over its noise floor, a parameter chosen from a
menu); hovering a pixel shows its force curve, residual and diagnosis beside them, a click keeps that pixel shown
(hovering elsewhere shows the other pixel until the pointer leaves the maps). Drawn with Plotly, its plotly.js
bundle inlined (``include_plotlyjs=True``): the page needs no server and no network.

What a pixel shows comes from the map result only: the curves kept at fit time (afmid.maps.pixel_curves: the
period-averaged inverted force on approach and retraction with its 1 sigma, the fitted law, the residual), the
per-pixel maps (status and message, error over floor, the residual's region / character / size, the read-outs
with their 1 sigma, "not selected" where the parameter's term was not) and the pixel's group with its verdict.

Size: the plotly.js bundle (about 4.7 MB; a 3x3 map's page is 4.9 MB) plus about 2.2 kB per pixel (measured:
12.2 MB for 3250 pixels, numbers kept to 4 digits); a map of more than :data:`MAX_PIXELS` pixels is shown on every
k-th row and column (said on the page), so the page stays under about 15 MB.
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path

import numpy as np

from afmid.report.quantity_text import display_unit

EXPLORER_NAME = "explorer.html"
#: Pixels the page holds curves for; a larger map is strided (every k-th row and column).
MAX_PIXELS = 4096
BRANCH_COLOURS = ("#1f77b4", "#d62728")  # approach, retraction (the single-trace report's order)
NN, NM = 1e9, 1e9  # N -> nN, m -> nm for display


def _round(values, digits: int = 4) -> list:
    """A JSON list with ``digits`` significant digits, None for NaN (JSON has no NaN)."""
    out = []
    for v in np.asarray(values, dtype=float).ravel():
        out.append(None if not math.isfinite(v) else float(f"{v:.{digits}g}"))
    return out


def _grid(values: np.ndarray, stride: int) -> list:
    """A map (rows x cols) as rows of JSON numbers, on the strided grid."""
    sub = np.asarray(values, dtype=float)[::stride, ::stride]
    return [_round(row) for row in sub]


def _parameter_text(value: float, sigma: float, unit: str, selected: bool) -> str:
    if not selected:
        return "not selected"
    if not math.isfinite(value):
        return "no value"
    factor, shown = display_unit(unit)
    suffix = f" {shown}" if shown and shown != "1" else ""
    spread = f" ± {sigma * factor:.2g}" if math.isfinite(sigma) else ""
    return f"{value * factor:.4g}{spread}{suffix} (1σ)"


def _pixel_html(r: int, c: int, result: dict, groups: dict | None, selected: dict, names: list[str],
                position: str) -> str:
    """The diagnosis panel of pixel (r, c)."""
    from afmid.fit.uncertainty import FLOOR_FACTOR
    from afmid.maps.residual import CHARACTERS, REGIONS
    from afmid.maps.task import STATUS_NAMES
    from afmid.report.map_groups import group_label

    maps = result["maps"]
    code = int(maps["status"][0][r, c])
    message = maps["message"][0][r, c]
    message = message.decode() if isinstance(message, bytes) else str(message)
    lines = [f"<h3>pixel (row {r}, col {c}){html.escape(position)}</h3>",
             f"<p>status: <b>{STATUS_NAMES[min(code, 2)]}</b>"
             + (f": {html.escape(message)}" if message else "") + "</p>"]
    if code >= 2:
        return "".join(lines)
    ratio = float(maps["cv_error"][0][r, c] / maps["cv_error_noise_floor"][0][r, c])
    limited = ratio > FLOOR_FACTOR
    lines.append(f"<p>error {ratio:.2f}x its noise floor"
                 + (" — <b>model-limited</b> (an effect is missing)" if limited else " (at the floor)") + "</p>")
    if "residual_region" in maps:
        region, character = int(maps["residual_region"][0][r, c]), int(maps["residual_character"][0][r, c])
        snr, share = float(maps["residual_snr"][0][r, c]), float(maps["residual_dissipative_share"][0][r, c])
        lines.append(f"<p>residual: mostly {REGIONS[region] if region >= 0 else '?'}, "
                     f"{CHARACTERS[character] if character >= 0 else '?'}; {snr:.1f}x the noise of the period average"
                     + (f"; dissipative share {share:.2f}" if math.isfinite(share) else "") + "</p>")
    if groups is not None and groups["groups"]:
        label = int(groups["labels"][r, c])
        if 0 <= label < len(groups["groups"]):
            group = groups["groups"][label]
            lines.append(f"<p>group {group['group']}: <b>{html.escape(group_label(group))}</b></p>"
                         f"<p class='sentence'>{html.escape(group['sentence'])}</p>")
    rows = "".join(
        f"<tr><td>{html.escape(name)}</td><td>"
        f"{html.escape(_parameter_text(float(maps[name][0][r, c]), float(maps[name + '_sigma'][0][r, c]), maps[name][1], bool(selected[name][r, c])))}"
        "</td></tr>" for name in names)
    sep = float(maps["separation"][0][r, c])
    rows += f"<tr><td>separation d</td><td>{sep * NM:.3g} nm</td></tr>" if math.isfinite(sep) else ""
    lines.append(f"<table>{rows}</table>")
    if limited:
        lines.append("<p><small>model-limited: these values carry the missing effect.</small></p>")
    return "".join(lines)


def _pixel_curves(curves: dict | None, r: int, c: int) -> dict | None:
    """A pixel's curves in nm and nN, or None (not fitted, or a result written without curves)."""
    if curves is None or not np.any(np.isfinite(curves["separation"][r, c])):
        return None
    return {"z": _round(curves["separation"][r, c] * NM),
            "inv": [_round(curves["force_inverted"][r, c, b] * NN) for b in range(2)],
            "sig2": [_round(2 * curves["force_inverted_sigma"][r, c, b] * NN) for b in range(2)],
            "model": [_round(curves["force_model"][r, c, b] * NN) for b in range(2)],
            "res": [_round(curves["residual"][r, c, b] * NN) for b in range(2)]}


def _maps_figure(result: dict, groups: dict | None, names: list[str], selected: dict, stride: int, scale: float,
                 axis_unit: str):
    """The Plotly figure of the three maps (every ``stride``-th pixel, ``scale`` display units apart) and the
    parameter menu."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    from afmid.report.map_groups import group_colours, group_label

    maps = result["maps"]
    status = maps["status"][0][::stride, ::stride]
    rows, cols = status.shape
    xs = [c * stride * scale for c in range(cols)]
    ys = [r * stride * scale for r in range(rows)]
    titles = ["which effect is missing where", "error / noise floor", "parameter"]
    fig = make_subplots(rows=1, cols=3, subplot_titles=titles, horizontal_spacing=0.11)
    ends = [fig.layout[f"xaxis{'' if i == 0 else i + 1}"].domain[1] for i in range(3)]
    bar = {"len": 0.9, "thickness": 12}
    if groups is not None and groups["groups"]:
        colours = group_colours(groups)
        n = len(colours)
        scale_steps = []
        for i, colour in enumerate(colours):
            scale_steps += [[i / n, colour], [(i + 1) / n, colour]]
        labels = groups["labels"][::stride, ::stride].astype(float)
        text = [[("group %d: %s" % (groups["groups"][int(v)]["group"], group_label(groups["groups"][int(v)]))
                  if v >= 0 else "not fitted") for v in row] for row in labels]
        fig.add_trace(go.Heatmap(z=[_round(np.where(row >= 0, row, np.nan)) for row in labels], x=xs, y=ys,
                                 colorscale=scale_steps, zmin=-0.5, zmax=n - 0.5, text=text,
                                 hovertemplate="%{text}<extra></extra>",
                                 colorbar=dict(bar, x=ends[0] + 0.005, tickvals=list(range(n)),
                                               ticktext=[f"group {g['group']}" for g in groups["groups"]])),
                      row=1, col=1)
    else:
        # No groups (a result written before maps had groups): the pixels' status instead.
        fig.add_trace(go.Heatmap(z=_grid(status, 1), x=xs, y=ys, colorscale="Viridis",
                                 hovertemplate="status %{z}<extra></extra>", colorbar=dict(bar, x=ends[0] + 0.005)),
                      row=1, col=1)
    ratio = maps["cv_error"][0] / maps["cv_error_noise_floor"][0]
    ratio = np.where(maps["status"][0] < 2, ratio, np.nan)
    fig.add_trace(go.Heatmap(z=_grid(np.log10(np.clip(ratio, 1e-3, None)), stride), x=xs, y=ys,
                             colorscale="Viridis", customdata=_grid(ratio, stride),
                             hovertemplate="error %{customdata:.2f}x its noise floor<extra></extra>",
                             colorbar=dict(bar, x=ends[1] + 0.005, title=dict(text="log10"))),
                  row=1, col=2)
    menus, first = [], None
    for name in names:
        factor, shown = display_unit(maps[name][1])
        values = np.where(selected[name] & (maps["status"][0] < 2), maps[name][0] * factor, np.nan)
        z = _grid(values, stride)
        unit = f" [{shown}]" if shown and shown != "1" else ""
        if first is None:
            first = (z, f"{name}{unit}")
        menus.append(dict(label=f"{name}{unit}", method="restyle",
                          args=[{"z": [z], "colorbar.title.text": f"{name}{unit}"}, [2]]))
    if first is not None:
        fig.add_trace(go.Heatmap(z=first[0], x=xs, y=ys, colorscale="Viridis",
                                 hovertemplate="%{z:.4g}<extra></extra>",
                                 colorbar=dict(bar, x=ends[2] + 0.005, title=dict(text=first[1]))), row=1, col=3)
    for i in range(3):  # the shown pixel, marked on every map
        fig.add_trace(go.Scatter(x=[None], y=[None], mode="markers", hoverinfo="skip", showlegend=False,
                                 marker=dict(symbol="square-open", size=14, color="black", line=dict(width=2))),
                      row=1, col=i + 1)
    for i in range(3):
        suffix = "" if i == 0 else str(i + 1)
        fig.update_layout({f"yaxis{suffix}": dict(autorange="reversed", scaleanchor=f"x{suffix}",
                                                  title=f"y [{axis_unit}]" if i == 0 else None),
                           f"xaxis{suffix}": dict(title=f"x [{axis_unit}]", constrain="domain")})
    fig.update_layout(height=360, margin=dict(l=50, r=10, t=80, b=40), template="simple_white",
                      updatemenus=[dict(buttons=menus, x=ends[2], xanchor="right", y=1.32, yanchor="top")]
                      if len(menus) > 1 else [])
    return fig


SCRIPT = r"""
(function () {
  var D = JSON.parse(document.getElementById("afmid-explorer-data").textContent);
  var maps = document.getElementById("afmid-maps"), curve = document.getElementById("afmid-curve");
  var panel = document.getElementById("afmid-diagnosis");
  var BR = ["approach", "retraction"], COL = D.colours, pinned = D.start;
  function show(p) {
    var d = D.pixels[p], traces = [];
    if (d.curves) {
      for (var b = 0; b < 2; b++) {
        traces.push({x: d.curves.z, y: d.curves.inv[b], mode: "lines+markers", marker: {size: 4},
                     error_y: {type: "data", array: d.curves.sig2[b], visible: true, thickness: 1, width: 0},
                     name: "inverted, " + BR[b] + " (± 2σ)", line: {color: COL[b]}});
        traces.push({x: d.curves.z, y: d.curves.model[b], mode: "lines", name: "model, " + BR[b],
                     line: {color: COL[b], dash: "dash"}});
        traces.push({x: d.curves.z, y: d.curves.res[b], mode: "lines", name: "residual, " + BR[b],
                     line: {color: COL[b]}, xaxis: "x2", yaxis: "y2", showlegend: false});
      }
    }
    var layout = {height: 440, template: "simple_white", margin: {l: 60, r: 10, t: 30, b: 45},
                  title: {text: d.title, font: {size: 13}}, legend: {font: {size: 10}},
                  xaxis: {anchor: "y", showticklabels: false, matches: "x2"},
                  yaxis: {domain: [0.38, 1], title: {text: "force [nN]"}, zeroline: true},
                  xaxis2: {anchor: "y2", title: {text: "separation z [nm]"}},
                  yaxis2: {domain: [0, 0.28], title: {text: "residual [nN]"}, zeroline: true},
                  annotations: d.curves ? [] : [{text: "no force curve: " + d.status, showarrow: false,
                                                 xref: "paper", yref: "paper", x: 0.5, y: 0.6}]};
    Plotly.react(curve, traces, layout, {displaylogo: false, responsive: true});
    curve.setAttribute("data-pixel", String(p));
    panel.innerHTML = d.html;
    var idx = [D.n_traces, D.n_traces + 1, D.n_traces + 2];
    Plotly.restyle(maps, {x: [[d.x], [d.x], [d.x]], y: [[d.y], [d.y], [d.y]]}, idx);
  }
  function pixelOf(event) {
    var pt = event.points && event.points[0];
    if (!pt || pt.pointIndex === undefined || !Array.isArray(pt.pointIndex)) return null;
    var p = pt.pointIndex[0] * D.cols + pt.pointIndex[1];
    return D.pixels[p] ? p : null;
  }
  maps.on("plotly_click", function (event) { var p = pixelOf(event); if (p !== null) { pinned = p; show(p); } });
  maps.on("plotly_hover", function (event) { var p = pixelOf(event); if (p !== null) show(p); });
  maps.on("plotly_unhover", function () { show(pinned); });
  show(pinned);
})();
"""

CSS_EXTRA = (".explorer-row{display:flex;gap:1em;align-items:flex-start}#afmid-curve{flex:3;min-width:0}"
             "#afmid-diagnosis{flex:2;font-size:.9em}#afmid-diagnosis h3{margin:.2em 0}.sentence{color:#555}")


def write_explorer(folder: Path, path: Path, result: dict, groups: dict | None, selected: dict,
                   names: list[str]) -> str | None:
    """Write ``folder/explorer.html`` for the map result ``path`` (read as ``result``; ``groups`` from
    afmid.report.map_groups.read_groups, ``selected`` from afmid.report.map_values.selected_maps); returns its
    file name."""
    from afmid.maps.pixel_curves import read_pixel_curves
    from afmid.report.page import CSS

    maps = result["maps"]
    status = maps["status"][0].astype(int)
    rows, cols = status.shape
    stride = max(1, math.ceil(math.sqrt(rows * cols / MAX_PIXELS)))
    curves = read_pixel_curves(path)
    pixel_size = result["pixel_size"]
    scale, axis_unit = (pixel_size * NM, "nm") if pixel_size else (1.0, "pixel")
    fig = _maps_figure(result, groups, names, selected, stride, scale, axis_unit)
    sub_rows, sub_cols = len(range(0, rows, stride)), len(range(0, cols, stride))
    pixels = []
    ratio = maps["cv_error"][0] / maps["cv_error_noise_floor"][0]
    for i in range(sub_rows):
        for j in range(sub_cols):
            r, c = i * stride, j * stride
            position = f" at x {c * scale:.4g} {axis_unit}, y {r * scale:.4g} {axis_unit}" if pixel_size else ""
            pixels.append({"x": j * stride * scale, "y": i * stride * scale,
                           "title": f"pixel (row {r}, col {c}): force on the tip vs separation",
                           "status": "failed" if status[r, c] >= 2 else "no curve stored",
                           "curves": _pixel_curves(curves, r, c) if status[r, c] < 2 else None,
                           "html": _pixel_html(r, c, result, groups, selected, names, position)})
    fitted_ratio = np.where(status[::stride, ::stride] < 2, ratio[::stride, ::stride], -np.inf)
    start = int(np.argmax(fitted_ratio)) if np.isfinite(fitted_ratio).any() else 0
    data = {"cols": sub_cols, "pixels": pixels, "start": start, "colours": list(BRANCH_COLOURS),
            "n_traces": len(fig.data) - 3}
    maps_div = fig.to_html(include_plotlyjs=True, full_html=False, div_id="afmid-maps",
                           config={"displaylogo": False, "responsive": True})
    note = (f"<p>A map of {rows} x {cols} pixels: shown on every {stride}th row and column.</p>" if stride > 1 else "")
    missing = "" if curves is not None else ("<p>This result was written without the pixels' force curves (before "
                                             "afmid 33): refit the map to see them.</p>")
    text = ("<!doctype html>\n<html><head><meta charset=\"utf-8\"><title>afmid map explorer</title>"
            f"<style>{CSS}\n{CSS_EXTRA}</style></head><body>"
            f"<h1>Map explorer: {html.escape(Path(path).name)}</h1>"
            "<p>Hover a pixel to see its force curve (the inverted force on approach and retraction ± 2σ of the "
            "period average, the fitted law dashed), its residual (inverted minus the law on the same harmonics) "
            "and its diagnosis; click to keep it. Shown first: the pixel with the largest error over its noise "
            "floor. Forces on the tip, positive = repulsive. <a href=\"report.html\">Back to the report</a>.</p>"
            f"{note}{missing}{maps_div}"
            "<div class=\"explorer-row\"><div id=\"afmid-curve\"></div><div id=\"afmid-diagnosis\"></div></div>"
            f"<script type=\"application/json\" id=\"afmid-explorer-data\">{_json_in_html(data)}</script>"
            f"<script>{SCRIPT}</script></body></html>\n")
    (Path(folder) / EXPLORER_NAME).write_text(text, encoding="utf-8")
    return EXPLORER_NAME


def _json_in_html(data: dict) -> str:
    """JSON safe inside a <script> element (no ``</`` that would end it)."""
    return json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
