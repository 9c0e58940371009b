"""The blind loop over random experiments: ``afmid coverage`` with ``coverage.diagnose`` (or ``coverage.hidden``).

Each draw is simulated with at most one *hidden* effect the fit's model lacks (``coverage.hidden``: the effect
and a distribution per parameter of it; ``none`` for a draw with nothing hidden), fitted with the config's model,
diagnosed as ``afmid report`` diagnoses a run (:func:`afmid.diagnosis.diagnose.suggest`, every missing catalog
effect refitted), and, when an effect is suggested, fitted again with it added, as a user following the report
would (``afmid fit --add EFFECT``). Counted over the draws:

- **named first**: a draw with a hidden effect whose top suggestion is that effect;
- **raised**: a draw whose suggested effect, once added, raises the cross-validated force error (the folds are the
  same for both fits, so the comparison is of one computation on one record, without noise of its own);
- **false alarm**: a draw with nothing hidden in which an effect is suggested; a *residual alarm* when the
  diagnosis calls the residual significant with no effect named;
- **cannot decide**: the diagnosis said that the data cannot decide between effects (no effect named);
- **refused**: afmid's fit or diagnosis raised on the draw's record (counted, never dropped).

A steady oscillation that never settles (a capillary neck formed on some taps only: a period-n orbit) is
recorded as it is (simulate.unsettled: record, :mod:`afmid.coverage.draws`); the draw's ``recorded`` says so and
the summary lists such draws with their outcome.

The hidden effect and its parameters come from their own random stream of (``coverage.seed``, k), so that the
drawn experiment (``coverage.vary``) is the same with and without the loop.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from afmid.sections.coverage import CoverageConfig
from afmid.coverage.draws import draw_number
from afmid.coverage.summary import binomial_interval

#: The hidden-effect entry of a draw with nothing hidden.
NOTHING_HIDDEN = "none"


def hidden_stream(coverage_seed: int, index: int) -> np.random.Generator:
    """The generator of draw ``index``'s hidden effect and its parameters: a third stream of (seed, index),
    independent of the drawn values' and the simulation seed's (afmid.coverage.draws.draw_streams)."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(coverage_seed, spawn_key=(index, 2))))


def draw_hidden(section: CoverageConfig, index: int) -> tuple[str, dict[str, float]]:
    """(hidden effect or ``none``, its parameters by name: SI) of draw ``index``; each entry of
    ``coverage.hidden`` equally likely, each parameter from its distribution (mode absolute: the value)."""
    if not section.hidden:
        return NOTHING_HIDDEN, {}
    rng = hidden_stream(section.seed, index)
    names = list(section.hidden)
    effect = names[min(int(rng.random() * len(names)), len(names) - 1)]
    return effect, {name: float(draw_number(dist, rng)) for name, dist in section.hidden[effect].items()}


def hide(simulated: dict, effect: str, parameters: dict[str, float]) -> dict:
    """The simulation's config mapping with ``effect`` (and its parameters) added to simulate.effects; the
    mapping itself when nothing is hidden."""
    if effect == NOTHING_HIDDEN:
        return simulated
    out = {**simulated, "simulate": dict(simulated["simulate"])}
    out["simulate"]["effects"] = [*(out["simulate"].get("effects") or []), effect]
    out["simulate"]["parameters"] = {**(out["simulate"].get("parameters") or {}), **parameters}
    return out


def with_effect(fitted: dict, effect: str) -> dict:
    """The fit's config mapping with ``effect`` added to model.effects (``afmid fit --add EFFECT``)."""
    out = {**fitted, "model": dict(fitted["model"])}
    out["model"]["effects"] = [*(out["model"].get("effects") or []), effect]
    return out


def run_loop(config, trace, run, task: dict, source) -> dict:
    """The loop of one fitted draw: diagnose ``run`` (the run record of the fit of ``trace`` as ``config`` says,
    afmid.runfile.run_data), refit with the top suggestion; the draw's ``loop`` record (see the module
    docstring)."""
    from afmid.config import build_config
    from afmid.diagnosis.diagnose import suggest
    from afmid.fit.pipeline import run_fit

    hidden = task["hidden"]
    answer = suggest(run, trace=trace)
    suggestions = answer.get("suggestions") or []
    named = suggestions[0]["effect"] if suggestions else None
    diagnosis = answer.get("diagnosis") or {}
    out: dict[str, Any] = {
        "hidden": hidden, "hidden_parameters": task["hidden_parameters"], "suggested": named,
        "explained_by_catalog": bool(diagnosis.get("explained_by_catalog", False)),
        "missing_effect": bool(answer.get("missing_effect", False)), "undecided": bool(answer.get("undecided")),
        "delta_bic": float(suggestions[0].get("delta_bic", math.nan)) if suggestions else math.nan,
        "error_before": float(run.cv_error), "error_after": math.nan,
        "noise_floor_before": float(run.cv_error_noise_floor), "noise_floor_after": math.nan,
    }
    if named is not None:
        refitted = run_fit(build_config(with_effect(task["fit"], named), source=source), trace=trace)
        out["error_after"] = float(refitted.cv_error)
        out["noise_floor_after"] = float(refitted.cv_error_noise_floor)
    out.update(judge(out))
    return out


def judge(loop: dict) -> dict:
    """The loop record's verdicts: named_first, raised, false_alarm, residual_alarm (booleans; named_first only
    for a draw with an effect hidden, false_alarm and residual_alarm only for one with nothing hidden)."""
    hidden, named = loop["hidden"], loop["suggested"]
    after, before = loop["error_after"], loop["error_before"]
    return {"named_first": hidden != NOTHING_HIDDEN and named == hidden,
            "raised": named is not None and math.isfinite(after) and after > before,
            "false_alarm": hidden == NOTHING_HIDDEN and named is not None,
            "residual_alarm": hidden == NOTHING_HIDDEN and named is None and loop["missing_effect"]}


# --------------------------------------------------------------------------- over the draws
#: Stages of a failed draw at which afmid itself refused the recorded trace (its fit or its diagnosis raised): such
#: a draw is counted as a refusal, not dropped (the simulator's own failures, stage simulate, are listed apart).
REFUSING_STAGES = ("fit", "diagnose")


def refused_row(one: dict) -> dict | None:
    """The loop row of a failed draw whose record afmid's fit or diagnosis refused (None for any other draw):
    nothing named, no refit, ``refused`` true."""
    if one.get("status") == "ok" or one.get("stage") not in REFUSING_STAGES or "hidden" not in one:
        return None
    row = {"hidden": one["hidden"], "hidden_parameters": one.get("hidden_parameters", {}), "suggested": None,
           "explained_by_catalog": False, "missing_effect": False, "undecided": False, "delta_bic": math.nan,
           "error_before": math.nan, "error_after": math.nan, "noise_floor_before": math.nan,
           "noise_floor_after": math.nan, "refused": True}
    row.update(judge(row))
    return row


def loop_rows(draws: list[dict]) -> list[tuple[dict, dict]]:
    """(draw, its loop row) of every draw the loop counts: the fitted draws with a loop record, and the draws afmid
    refused (:func:`refused_row`)."""
    out = []
    for one in draws:
        row = one.get("loop") if one.get("status") == "ok" else refused_row(one)
        if row:
            out.append((one, row))
    return out


def outcome(one: dict) -> str:
    """A draw's outcome in the loop's words: 'named first', 'other: EFFECT', 'cannot decide', 'none', 'refused
    (STAGE): ERROR' or 'failed (STAGE): ERROR'; ', raised' appended when the suggestion raised the error."""
    row = one.get("loop") if one.get("status") == "ok" else refused_row(one)
    if not row:
        return f"failed ({one.get('stage', '')}): {one.get('error', '')}"
    if row.get("refused"):
        return f"refused ({one['stage']}): {one.get('error', '')}"
    if row["named_first"]:
        words = "named first"
    elif row["suggested"] is not None:
        words = f"other: {row['suggested']}"
    else:
        words = "cannot decide" if row["undecided"] else "none"
    return words + (", raised" if row["raised"] else "")


def loop_summary(draws: list[dict]) -> dict:
    """Counts over the draws the loop counts (:func:`loop_rows`): per hidden effect and in all (named first,
    suggested something else, cannot decide, refused, nothing named, raised), and over the draws with nothing
    hidden (false alarms, residual alarms, refused), each fraction with its 95 % Wilson interval; and the draws
    whose record is not a settled steady state (``recorded`` says so), each with its outcome."""
    loops = [row for _, row in loop_rows(draws)]
    hidden = [one for one in loops if one["hidden"] != NOTHING_HIDDEN]
    null = [one for one in loops if one["hidden"] == NOTHING_HIDDEN]

    def rates(rows: list[dict]) -> dict:
        n = len(rows)
        named = sum(r["named_first"] for r in rows)
        other = sum(r["suggested"] is not None and not r["named_first"] for r in rows)
        undecided = sum(r["suggested"] is None and r["undecided"] for r in rows)
        refused = sum(bool(r.get("refused")) for r in rows)
        return {"n": n, "named_first": named, "named_first_fraction": named / n if n else math.nan,
                "named_first_interval95": list(binomial_interval(named, n)), "named_other": other,
                "cannot_decide": undecided, "refused": refused,
                "nothing_named": n - named - other - undecided - refused, "raised": sum(r["raised"] for r in rows)}

    by_effect = {}
    for effect in sorted({r["hidden"] for r in hidden}):
        by_effect[effect] = rates([r for r in hidden if r["hidden"] == effect])
    n_null = len(null)
    false = sum(r["false_alarm"] for r in null)
    residual = sum(r["residual_alarm"] for r in null)
    unsettled = [{"index": d["index"], "hidden": d.get("hidden", NOTHING_HIDDEN), "recorded": d["recorded"],
                  "outcome": outcome(d)}
                 for d in draws if str(d.get("recorded", "")).startswith("unsettled")]
    return {"hidden": rates(hidden), "by_effect": by_effect,
            "null": {"n": n_null, "false_alarms": false, "false_alarm_fraction": false / n_null if n_null else math.nan,
                     "false_alarm_interval95": list(binomial_interval(false, n_null)),
                     "residual_alarms": residual, "refused": sum(bool(r.get("refused")) for r in null),
                     "raised": sum(r["raised"] for r in null),
                     "suggested": sorted({r["suggested"] for r in null if r["suggested"]})},
            "raised_draws": [d["index"] for d, row in loop_rows(draws) if row["raised"]],
            "unsettled": unsettled}


def loop_text(summary: dict) -> str:
    """The loop's table as ``afmid coverage`` prints it."""
    lines = ["\nthe blind loop (fit -> diagnose -> add the top suggestion -> refit); fraction [95 % Wilson interval]:",
             f"{'hidden':<24} {'n':>4} {'named first':<22} {'other':>5} {'undecided':>9} {'refused':>7} {'none':>5} "
             f"{'raised':>6}"]

    def row(name: str, r: dict) -> str:
        low, high = r["named_first_interval95"]
        cell = f"{r['named_first_fraction']:.2f} [{low:.2f}, {high:.2f}]" if r["n"] else "-"
        return (f"{name:<24} {r['n']:>4} {cell:<22} {r['named_other']:>5} {r['cannot_decide']:>9} "
                f"{r.get('refused', 0):>7} {r['nothing_named']:>5} {r['raised']:>6}")

    for effect, r in summary["by_effect"].items():
        lines.append(row(effect, r))
    if len(summary["by_effect"]) > 1:
        lines.append(row("all hidden", summary["hidden"]))
    null = summary["null"]
    if null["n"]:
        low, high = null["false_alarm_interval95"]
        lines.append(f"nothing hidden: {null['false_alarms']} of {null['n']} draws named an effect "
                     f"({null['false_alarm_fraction']:.3f} [{low:.3f}, {high:.3f}])"
                     + (f": {', '.join(null['suggested'])}" if null["suggested"] else "")
                     + f"; {null['residual_alarms']} called the residual significant with no effect named")
    if summary["raised_draws"]:
        lines.append(f"the suggested effect raised the cross-validated error in draws {summary['raised_draws']}")
    for one in summary.get("unsettled", []):
        lines.append(f"draw {one['index']} (hidden {one['hidden']}): {one['recorded']}; {one['outcome']}")
    return "\n".join(lines)


def check_hidden(section: CoverageConfig, known_effects, source) -> None:
    """Refuse a hidden effect the catalog does not have, naming ``coverage.hidden.NAME``."""
    from afmid.errors import ConfigError

    for effect in section.hidden:
        if effect != NOTHING_HIDDEN and effect not in known_effects:
            raise ConfigError(f"{effect!r} is no catalog effect (see afmid effects) and not {NOTHING_HIDDEN!r}",
                              file=source, key=f"coverage.hidden.{effect}")


def hidden_distributions(section: CoverageConfig) -> dict[str, str]:
    """The hidden entries in words (for the printed header and the output's provenance)."""
    return {effect: "; ".join(f"{name} {dist.describe()}" for name, dist in params.items()) or "-"
            for effect, params in section.hidden.items()}

