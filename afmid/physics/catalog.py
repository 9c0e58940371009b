"""Text and JSON views of the physics registry (``afmid effects``)."""

from __future__ import annotations

import json

from afmid.physics.effect_tags import TERM_ROLES
from afmid.physics.effect_types import RelaxingState
from afmid.physics.effects import EFFECTS, MODELS, coefficient_unit, quantity_range, term_unit
from afmid.physics.tips import TIP_SHAPES
from afmid.quantity_text import range_words
from afmid.registry import unknown_name_message
from afmid.errors import ConfigError


def effect_record(name: str) -> dict:
    effect = EFFECTS.get(name)
    return {
        "name": effect.name,
        "title": effect.title,
        "formula": effect.formula,
        "character": effect.character,
        "region": effect.region,
        "parameters": [
            {"name": p.name, "unit": p.unit, "default": p.default, "range": [p.low, p.high], "doc": p.doc,
             "nonlinear": p.nonlinear, "searched": {m: list(p.search_span(m)) for m in effect.media} if p.nonlinear
             else None}
            for p in effect.parameters
        ],
        "terms": [
            {"label": t.label, "expression": t.expression, "term_unit": str(term_unit(effect, t)),
             "coefficient_unit": str(coefficient_unit(effect, t)), "roles": list(t.roles)}
            for t in effect.terms
        ],
        "states": [{"name": s.name, "source": s.source, "time": s.time} if isinstance(s, RelaxingState)
                   else {"name": s.name, "on": s.on, "off": s.off} for s in effect.states],
        "quantities": [
            {"name": q.name, "unit": q.unit, "doc": q.doc, "plausible_range": list(quantity_range(effect, q))}
            for q in effect.quantities
        ],
        "references": list(effect.references),
        "media": list(effect.media),
        "notes": effect.notes,
    }


def _span_words(low: float, high: float, unit: str) -> str:
    """A search range in words: lengths in nm ("[1, 20] nm"), anything else in SI."""
    if unit == "m":
        return f"[{low * 1e9:g}, {high * 1e9:g}] nm"
    return f"[{low:g}, {high:g}] {unit}"


def model_record(name: str) -> dict:
    model = MODELS.get(name)
    return {"name": model.name, "title": model.title, "effects": list(model.effects),
            "references": list(model.references)}


def tip_record(name: str) -> dict:
    shape = TIP_SHAPES.get(name)
    return {"name": shape.name, "title": shape.title, "contact_law": shape.contact_law,
            "term": f"[z <= a0] * {shape.power_text}", "coefficient": f"E* {shape.factor_text}",
            "coefficient_unit": shape.coefficient_unit, "readout": shape.readout,
            "needs_half_angle": shape.needs_half_angle, "notes": shape.notes, "references": list(shape.references)}


def describe_tips(as_json: bool = False) -> str:
    """The tip shapes (``cantilever.tip_shape``): contact law, the read-out of E*, references."""
    records = [tip_record(n) for n in TIP_SHAPES.names()]
    if as_json:
        return json.dumps(records, indent=2)
    lines = ["Tip shapes (cantilever.tip_shape; cantilever.tip_half_angle in rad for cone and pyramid): the elastic "
             "term of dmt and jkr follows the shape's contact law (repulsive +, delta = a0 - z)", ""]
    for r in records:
        angle = " [needs cantilever.tip_half_angle]" if r["needs_half_angle"] else ""
        lines.append(f"{r['name']}: {r['title']}{angle}")
        lines.append(f"  force (repulsive +): {r['contact_law']}")
        lines.append(f"  term  {r['term']}  (coefficient {r['coefficient']}, in {r['coefficient_unit']}); "
                     f"read-out {r['readout']}")
        if r["notes"]:
            lines.append(f"  note: {r['notes']}")
        for ref in r["references"]:
            lines.append(f"  ref: {ref}")
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def describe_effects(names: list[str], models: bool = False, as_json: bool = False) -> str:
    registry = MODELS if models else EFFECTS
    for name in names:
        if name not in registry:
            raise ConfigError(unknown_name_message("model" if models else "effect", name, registry.names()))
    selected = names or registry.names()
    records = [model_record(n) if models else effect_record(n) for n in selected]
    if as_json:
        return json.dumps(records, indent=2)
    lines: list[str] = []
    for r in records:
        lines.append(f"{r['name']}: {r['title']}")
        if models:
            lines.append(f"  effects: {', '.join(r['effects'])}")
        else:
            lines.append(f"  force (repulsive +): {r['formula']}")
            lines.append(f"  character: {r['character']}; acts: {r['region']}; media: {', '.join(r['media'])} "
                         "(sample.medium)")
            for p in r["parameters"]:
                flag = " [nonlinear, searched by the fit]" if p["nonlinear"] else ""
                narrower = {m: span for m, span in (p["searched"] or {}).items() if span != p["range"]}
                if narrower:
                    where = "; ".join(f"in {m} over {_span_words(*span, p['unit'])}" for m, span in narrower.items())
                    flag = f" [nonlinear, searched by the fit: {where}]"
                lines.append(
                    f"  param {p['name']} [{p['unit']}] default {p['default']:g}, "
                    f"range [{p['range'][0]:g}, {p['range'][1]:g}]: {p['doc']}{flag}"
                )
            for t in r["terms"]:
                role = "".join(f"; {TERM_ROLES[r]}" for r in t["roles"])
                lines.append(f"  term  {t['label']}: {t['expression']}  (coefficient in {t['coefficient_unit']}{role})")
            for s in r["states"]:
                lines.append(f"  state {s['name']}: lags {s['source']} with time constant {s['time']}" if "source" in s
                             else f"  state {s['name']}: on when {s['on']}, off when {s['off']}")
            for q in r["quantities"]:
                low, high = q["plausible_range"]
                plausible = range_words(low, high, q["unit"])
                lines.append(f"  yields {q['name']} [{q['unit']}]: {q['doc']} (plausible: {plausible})")
            if r["notes"]:
                lines.append(f"  note: {r['notes']}")
        for ref in r["references"]:
            lines.append(f"  ref: {ref}")
        lines.append("")
    if not names and not models:  # the whole catalog: the tip shapes the contact effects follow, too
        lines.append(describe_tips())
    return "\n".join(lines).rstrip() + "\n"
