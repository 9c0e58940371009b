"""A force map's parameter values per group of pixels, and where a parameter's term was not selected.

A map over a blend of phases has one value per phase, not one per map: a median over all pixels of a bimodal E*
(matrix 2 GPa, soft domains 0.35 GPa) is neither. The groups of pixels (afmid.maps.groups: by residual signature
and parameters) are the phases the fit found, so the page gives each parameter's median and 16-84 % spread per
group. A parameter whose effect had no term selected at a pixel reads 0 there (afmid.fit.forces.read_out: an
unselected coefficient is 0): that is "not selected", not a measured 0, and it is left out of the values.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from afmid.report.quantity_text import display_unit


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def term_belongs_to(term: str, effect: str) -> bool:
    """Whether the library term ``term`` (``EFFECT.LABEL`` in /model/terms) is one of ``effect``'s."""
    return term == effect or term.startswith(effect + ".")


def selected_maps(path: Path, names: list[str]) -> dict[str, np.ndarray]:
    """Per parameter, the pixels where a term of its effect was selected (bool, rows x cols): from /maps/selected
    (bit k: /model/terms[k]) and the parameter's ``effect`` attribute. A parameter without an ``effect`` attribute
    (written by an older afmid) counts as selected everywhere."""
    import h5py

    with h5py.File(path, "r") as h5:
        bits = np.asarray(h5["maps/selected"][()], dtype=np.int64)
        terms = [_text(t) for t in h5["model/terms"][()]] if "model/terms" in h5 else []
        effects = {name: _text(h5["maps"][name].attrs.get("effect", "")) for name in names}
    out = {}
    for name in names:
        if not effects[name]:
            out[name] = np.ones(bits.shape, bool)
            continue
        mask = sum(1 << k for k, term in enumerate(terms) if term_belongs_to(term, effects[name]))
        out[name] = (bits & mask) != 0
    return out


def value_stats(values: np.ndarray, sigma: np.ndarray, pixels: np.ndarray, selected: np.ndarray, unit: str) -> dict:
    """Median, 16-84 % and median 1 sigma (display unit) of ``values`` over ``pixels`` where the term was
    ``selected``; ``selected_pixels`` of ``pixels``; the numbers are NaN when it was selected at none."""
    factor, shown = display_unit(unit)
    chosen = pixels & selected & np.isfinite(values)
    v = values[chosen] * factor
    s = sigma[chosen & np.isfinite(sigma)] * factor
    nan = math.nan
    return {"unit": shown or unit, "factor_from_SI": factor, "pixels": int(pixels.sum()),
            "selected_pixels": int(chosen.sum()),
            "median": float(np.median(v)) if v.size else nan,
            "p16": float(np.percentile(v, 16)) if v.size else nan,
            "p84": float(np.percentile(v, 84)) if v.size else nan,
            "median_sigma": float(np.median(s)) if s.size else nan}


def stats_text(stats: dict) -> str:
    """One cell: ``1885 MPa (16-84 %: 350 .. 2104; 1 sigma 12)``, or ``not selected``; with the selected share
    when the term was selected at some of the pixels only."""
    if stats["selected_pixels"] == 0:
        return "not selected"
    unit = f" {stats['unit']}" if stats["unit"] and stats["unit"] != "1" else ""
    if stats["selected_pixels"] == 1:  # one pixel's value is not the group's: no median, no spread to show
        sigma = f" ± {stats['median_sigma']:.2g} (1 sigma)" if math.isfinite(stats["median_sigma"]) else ""
        text = f"{stats['median']:.4g}{unit}{sigma} at that one pixel only, not a group value"
    else:
        text = (f"{stats['median']:.4g}{unit} (16-84 %: {stats['p16']:.4g} .. {stats['p84']:.4g}; "
                f"median 1 sigma {stats['median_sigma']:.2g})")
    if stats["selected_pixels"] < stats["pixels"]:
        text += f"; selected at {stats['selected_pixels']} of {stats['pixels']} pixels"
    return text


def group_values(maps: dict, names: list[str], groups: dict | None, selected: dict, usable: np.ndarray) -> list[dict]:
    """Per group of pixels (afmid.report.map_groups.read_groups), each parameter's :func:`value_stats` over the
    group's ``usable`` pixels (ok, or ok and suspect); [] without groups."""
    if groups is None:
        return []
    out = []
    for group in groups["groups"]:
        members = (groups["labels"] == group["group"] - 1) & usable
        out.append({"group": group["group"], "values": {
            name: value_stats(maps[name][0], maps[f"{name}_sigma"][0], members, selected[name], maps[name][1])
            for name in names}})
    return out
