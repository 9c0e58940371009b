"""The missing-effect map in a force map's report: which effect is missing where.

Reads what ``afmid map`` wrote (afmid.maps.residual, afmid.maps.groups, afmid.maps.group_diagnosis): the per-pixel
residual character (region, conservative / dissipative, size over the noise) as maps, the groups of pixels coloured
by their verdict with one sentence per group, and, given the result of an earlier fit of the same map (``afmid
report BEFORE.h5 AFTER.h5``, e.g. before and after ``afmid map --add EFFECT``), the error over its noise floor
before and after on one colour scale with the change per group of the earlier result.
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from afmid.report.figures import save_figure

#: Colours of the verdicts on the group map: a named missing effect, nothing missing, the rest.
MISSING_COLOURS = ("#d62728", "#9467bd", "#8c564b", "#e377c2")
NOTHING_COLOUR = "#c7e9c0"
#: Further groups with nothing missing (two phases both at the floor): greens of other shades, told apart on the map.
NOTHING_SHADES = (NOTHING_COLOUR, "#74c476", "#a1d99b", "#31a354")
OTHER_COLOUR = "#ff7f0e"


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def read_groups(path: Path) -> dict | None:
    """The groups of a map result: summary, per group (verdict, effects, sentence, fraction, error_over_floor) and
    the group map; None when the result has none (written before maps had groups)."""
    import h5py

    with h5py.File(path, "r") as h5:
        if "groups" not in h5 or "group" not in h5["maps"]:
            return None
        g = h5["groups"]
        out = {"summary": _text(g.attrs.get("summary", "")), "method": _text(g.attrs.get("method", "")),
               "silhouette": float(g.attrs.get("silhouette", np.nan)), "labels": h5["maps/group"][()],
               "groups": []}
        if "verdict" in g:
            for i in range(g["verdict"].shape[0]):
                out["groups"].append({
                    "group": i + 1, "verdict": _text(g["verdict"][i]), "effects": _text(g["effects"][i]),
                    "sentence": _text(g["sentence"][i]), "pixels": int(g["pixels"][i]),
                    "fraction": float(g["fraction"][i]), "error_over_floor": float(g["error_over_floor"][i]),
                    "diagnosed": bool(g["diagnosed"][i])})
    return out


def _plt():
    """pyplot with the single-trace report's publication style (afmid.report.figures.PAPER_STYLE)."""
    from afmid.report.figures import pyplot

    return pyplot()


def _axes_labels(ax, extent) -> None:
    ax.set_xlabel(f"x [{extent[1]}]")
    ax.set_ylabel(f"y [{extent[1]}]")
    ax.grid(False)  # the style's grid would be drawn over the pixels


def residual_figure(folder: Path, maps: dict, extent) -> tuple[str, str] | None:
    """Region, character and size (snr) of each pixel's residual, as maps; None when the result has none."""
    from matplotlib.colors import ListedColormap

    from afmid.maps.residual import CHARACTERS, REGIONS

    if "residual_region" not in maps:
        return None
    plt = _plt()
    panels = [("residual_region", REGIONS, ListedColormap(["#1f77b4", "#17becf", "#bcbd22"]), "where the residual sits"),
              ("residual_character", CHARACTERS, ListedColormap(["#dddddd", "#2ca02c", "#d62728", "#9467bd"]),
               "its character")]
    fig, axes = plt.subplots(1, 3, figsize=(14.0, 3.8), squeeze=False, layout="tight")
    box = extent[0]
    for ax, (name, names, cmap, title) in zip(axes[0], panels):
        data = maps[name][0].astype(float)
        image = ax.imshow(np.where(data >= 0, data, np.nan), extent=box, cmap=cmap, vmin=-0.5,
                          vmax=len(names) - 0.5, interpolation="nearest")
        bar = fig.colorbar(image, ax=ax, ticks=range(len(names)))
        bar.ax.set_yticklabels(names, fontsize=7)
        ax.set_title(title)
        _axes_labels(ax, extent)
    ax = axes[0][2]
    snr = maps["residual_snr"][0]
    image = ax.imshow(np.log10(np.clip(snr, 1e-2, None)), extent=box, cmap="magma", interpolation="nearest")
    fig.colorbar(image, ax=ax).set_label("log10 (residual rms / its noise)")
    ax.set_title("its size over the noise (0: noise only)")
    _axes_labels(ax, extent)
    return (save_figure(fig, folder, "map_residual", dpi=90),
            "each pixel's residual (inverted minus model force, period-averaged): the region holding most of it, "
            "whether it is the same on approach and retraction (conservative) or reverses with the motion "
            "(dissipative), and its rms over the noise of the average (afmid.diagnosis.localize per pixel)")


def group_colours(groups: dict) -> list[str]:
    """The colour of each group on the missing-effect map: a named missing effect red (one colour per effect, the
    same on every page), nothing missing green (a shade per such group), anything else orange."""
    effects = sorted({g["effects"] for g in groups["groups"] if g["effects"]})
    colours, calm = [], 0
    for group in groups["groups"]:
        if group["effects"]:
            colours.append(MISSING_COLOURS[effects.index(group["effects"]) % len(MISSING_COLOURS)])
        elif group["verdict"] == "nothing missing":
            colours.append(NOTHING_SHADES[calm % len(NOTHING_SHADES)])
            calm += 1
        else:
            colours.append(OTHER_COLOUR)
    return colours


def group_label(group: dict) -> str:
    """A group's verdict in a few words: ``viscoelastic missing``, ``nothing missing``."""
    if not group["effects"]:
        return group["verdict"]
    if group["verdict"].startswith("missing"):
        return f"{group['effects']} missing"
    return f"{group['effects']} ({group['verdict'].split(':')[0]})"


def groups_figure(folder: Path, groups: dict, extent) -> tuple[str, str] | None:
    """The group map, each group coloured by its verdict (a named effect red, nothing missing pale green)."""
    from matplotlib.colors import ListedColormap

    if not groups["groups"]:
        return None
    plt = _plt()
    colours = group_colours(groups)
    labels = groups["labels"].astype(float)
    n = len(colours)
    fig, ax = plt.subplots(figsize=(6.4, 4.2), layout="tight")
    image = ax.imshow(np.where(labels >= 0, labels, np.nan), extent=extent[0], cmap=ListedColormap(colours),
                      vmin=-0.5, vmax=n - 0.5, interpolation="nearest")
    bar = fig.colorbar(image, ax=ax, ticks=range(n))
    bar.ax.set_yticklabels([f"group {g['group']}: " + group_label(g) for g in groups["groups"]], fontsize=7)
    ax.set_title("which effect is missing where")
    _axes_labels(ax, extent)
    return (save_figure(fig, folder, "map_missing_effect", dpi=90),
            "groups of pixels (by residual signature and parameters), each coloured by its catalog verdict: "
            + html.escape(groups["summary"]))


def comparison(before_path: Path, before_maps: dict, after_maps: dict) -> dict:
    """The error over its noise floor before and after, per pixel and per group of the earlier result."""
    from afmid.fit.uncertainty import FLOOR_FACTOR

    def ratio(maps):
        r = maps["cv_error"][0] / maps["cv_error_noise_floor"][0]
        return np.where(maps["status"][0] < 2, r, np.nan)

    before, after = ratio(before_maps), ratio(after_maps)
    if before.shape != after.shape:
        from afmid.errors import InputError

        raise InputError(f"the earlier map result is {before.shape[0]}x{before.shape[1]} pixels, this one "
                         f"{after.shape[0]}x{after.shape[1]}: not the same map", file=before_path)
    groups = read_groups(before_path)
    per_group = []
    if groups is not None:
        for g in groups["groups"]:
            members = groups["labels"] == g["group"] - 1
            per_group.append({"group": g["group"], "verdict": g["verdict"], "pixels": int(members.sum()),
                              "median_before": float(np.nanmedian(before[members])),
                              "median_after": float(np.nanmedian(after[members]))})
    return {"before": str(before_path), "ratio_before": before, "ratio_after": after,
            "model_limited_before": int(np.nansum(before > FLOOR_FACTOR)),
            "model_limited_after": int(np.nansum(after > FLOOR_FACTOR)),
            "median_before": float(np.nanmedian(before)), "median_after": float(np.nanmedian(after)),
            "groups": per_group}


def comparison_figure(folder: Path, compared: dict, extent) -> tuple[str, str]:
    """Error over floor before | after on one (log) colour scale."""
    from matplotlib.colors import LogNorm

    plt = _plt()
    both = np.concatenate([compared["ratio_before"].ravel(), compared["ratio_after"].ravel()])
    both = both[np.isfinite(both) & (both > 0)]
    norm = LogNorm(vmin=max(both.min(), 0.3), vmax=max(both.max(), 2.0)) if both.size else None
    fig, axes = plt.subplots(1, 2, figsize=(10.0, 3.8), squeeze=False, layout="tight")
    for ax, key, title in zip(axes[0], ("ratio_before", "ratio_after"), ("before", "after")):
        image = ax.imshow(compared[key], extent=extent[0], cmap="viridis", norm=norm, interpolation="nearest")
        fig.colorbar(image, ax=ax).set_label("cv error / noise floor (1: at the floor)")
        ax.set_title(f"{title}: median {np.nanmedian(compared[key]):.2f}x the floor")
        _axes_labels(ax, extent)
    return (save_figure(fig, folder, "map_error_before_after", dpi=90),
            f"error over its noise floor before ({html.escape(Path(compared['before']).name)}) and after (this "
            "result), one colour scale")


def comparison_lines(compared: dict) -> list[str]:
    """The fall of the error in words: over the map and per group of the earlier result."""
    lines = [f"error over its noise floor: median {compared['median_before']:.2f}x -> {compared['median_after']:.2f}x; "
             f"model-limited pixels {compared['model_limited_before']} -> {compared['model_limited_after']}"]
    for g in compared["groups"]:
        lines.append(f"group {g['group']} of the earlier result ({g['verdict']}, {g['pixels']} pixels): median "
                     f"{g['median_before']:.2f}x -> {g['median_after']:.2f}x the floor")
    return lines


def groups_html(groups: dict | None, compared: dict | None, per_group: list[dict] | None = None,
                figures: list[tuple[str, str]] | None = None, folder: Path | None = None) -> str:
    """The opening of the page: the map's verdict, the missing-effect map (and the error before and after), the
    groups with their verdicts and parameter values (afmid.report.map_values), one sentence per group."""
    from afmid.report.figures import figure_html
    from afmid.report.map_values import stats_text

    parts = []
    if groups is not None:
        found = any(g["effects"] and g["verdict"].startswith("missing") for g in groups["groups"])
        other = any(not g["effects"] and g["verdict"] != "nothing missing" for g in groups["groups"])
        kind = "found" if found else ("unexplained" if other else "")
        parts.append(f"<h2>Which effect is missing where</h2><div class='verdict {kind}'><p><b>"
                     f"{html.escape(groups['summary'])}</b></p></div>")
    if figures and folder is not None:
        parts.append("".join(figure_html(folder, f, c) for f, c in figures))
    if groups is not None and groups["groups"]:
        colours = group_colours(groups)
        values = {g["group"]: g["values"] for g in per_group or []}
        names = list(next(iter(values.values())).keys()) if values else []
        head = "".join(f"<th>{html.escape(n)}</th>" for n in names)
        rows = []
        for g, colour in zip(groups["groups"], colours):
            swatch = f"<span class='swatch' style='background:{colour}'></span>"
            cells = "".join(f"<td>{html.escape(stats_text(values[g['group']][n]))}</td>" for n in names
                            if g["group"] in values)
            rows.append(f"<tr><td>{swatch}group {g['group']}</td><td>{html.escape(group_label(g))}</td>"
                        f"<td>{g['pixels']} ({100 * g['fraction']:.0f} %)</td><td>{g['error_over_floor']:.2f}x</td>"
                        f"{cells}</tr>")
        parts.append("<table><tr><th>group</th><th>verdict</th><th>pixels</th><th>error / noise floor (median)</th>"
                     f"{head}</tr>{''.join(rows)}</table><p><small>Values per group: median (16-84 %) over the "
                     "group's fitted pixels (ok and suspect); a model-limited group's values carry the missing effect "
                     "(refit with it before using them).</small></p>")
        items = "".join(f"<li>{html.escape(g['sentence'])}</li>" for g in groups["groups"])
        parts.append(f"<ul>{items}</ul><p><small>{html.escape(groups['method'])}</small></p>")
    if compared is not None:
        items = "".join(f"<li>{html.escape(line)}</li>" for line in comparison_lines(compared))
        parts.append(f"<h2>Before and after</h2><ul>{items}</ul>")
    return "".join(parts)


def group_value_lines(per_group: list[dict], names: list[str]) -> list[str]:
    """The parameter values per group for the terminal."""
    from afmid.report.map_values import stats_text

    return [f"  group {g['group']}: " + "; ".join(f"{n} {stats_text(g['values'][n])}" for n in names)
            for g in per_group]


def groups_summary(groups: dict | None, compared: dict | None) -> dict:
    """The groups and the comparison for summary.json (no arrays)."""
    out = {}
    if groups is not None:
        out["groups"] = {"summary": groups["summary"], "silhouette": groups["silhouette"], "method": groups["method"],
                         "groups": groups["groups"]}
    if compared is not None:
        out["compared_with"] = {k: v for k, v in compared.items() if not k.startswith("ratio_")}
    return out
