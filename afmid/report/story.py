"""The runs of a report told as the loop: each run diagnosed on its own, and how one run followed another.

``afmid report run1.h5 run2.h5`` compares runs; a comparison that diagnosed only the last run lost where
run1 failed and what was suggested. Here every run gets its own diagnosis (:func:`diagnose_runs`: the
public :func:`afmid.diagnosis.diagnose.suggest` per run through :func:`afmid.diagnosis.stored.diagnosed`, which
reuses a diagnosis kept for the run; the last run's result reused) and the runs are
read in order as the loop (:func:`loop_steps`): run1 failed here (region, character, error vs its noise
floor) -> suggestion (effect, ΔBIC) -> run2 = run1 + effect -> error fell from x to y (floor z) -> what is
left. A run that was not the follow-up of a suggestion is told as what it is.

Errors are the normalised cross-validated force error (1 = no better than a constant force), shown with
the standard deviation of the per-fold errors (``cv_error_folds``).
"""

from __future__ import annotations

import html
import math
from pathlib import Path

import numpy as np

from afmid.diagnosis.diagnose import describe_residual, localize
from afmid.diagnosis.stored import diagnosed
from afmid.fit.uncertainty import ERROR_LABEL, TRACK_LEVEL_ERROR, model_limited, statistical_error
from afmid.quantity_text import format_delta_bic, format_measurement, format_value
from afmid.runfile import RunData

#: Keys of a suggestion kept in each run's diagnosis (summary.json ``runs[*].diagnosis.suggestions``).
SUGGESTION_KEYS = ("effect", "delta_bic", "error_after", "noise_floor_after", "evidence")


# --------------------------------------------------------------------------- the error and its spread
def fold_spread(run: RunData) -> tuple[float, int]:
    """(standard deviation of the per-fold cv errors, number of folds); (nan, k) with fewer than two folds."""
    folds = np.asarray(run.cv_error_folds if run.cv_error_folds is not None else [], dtype=float)
    folds = folds[np.isfinite(folds)]
    return (float(np.std(folds, ddof=1)) if folds.size > 1 else math.nan), int(folds.size)


def error_text(error: float, sd: float, k: int) -> str:
    """'0.043 ± 0.004 (sd over 5 folds)': the pooled cv error with the spread of its folds (PDG rounding)."""
    if error is None or not math.isfinite(error):
        return "–"
    if not (math.isfinite(sd) and sd > 0):
        return format_value(error, "1")
    return format_measurement(error, sd, "1", kind=f"sd over {k} folds")


def _ratio_words(error: float, floor: float, floor_dof: float = math.nan) -> str:
    if not (math.isfinite(error) and math.isfinite(floor) and floor > 0):
        return "no noise floor"
    ratio = error / floor
    where = "model-limited" if model_limited(error, floor, floor_dof) else "at the noise level"
    return f"{ratio:.2g}x its noise floor {floor:.3g}: {where}"


# --------------------------------------------------------------------------- per-run diagnosis
def run_diagnosis(run: RunData, result: dict | None, local: dict | None = None) -> dict:
    """The ``diagnosis`` object of one run in summary.json: verdict, region, character, suggestions, ...

    ``result`` is :func:`afmid.diagnosis.diagnose.suggest`'s answer for this run (None: not diagnosed, e.g.
    ``--no-suggest``; where and how the residual sits is still given).
    """
    local = local if local is not None else localize(run)
    diag = (result or {}).get("diagnosis") or {}
    sd, k = fold_spread(run)
    if result is None:
        verdict = "not diagnosed: suggestions were not requested (--no-suggest)"
    else:
        verdict = diag.get("verdict") or result.get("note") or "not diagnosed"
    return {
        "verdict": verdict,
        "region": diag.get("region", local["region"]),
        "character": diag.get("character", local["character"]),
        "description": diag.get("description") or describe_residual(local, run),
        "missing_effect": (result or {}).get("missing_effect"),
        "explained_by_catalog": diag.get("explained_by_catalog"),
        "error": run.cv_error,
        "error_fold_sd": sd,
        "error_folds": k,
        "error_spread_kind": f"sd over {k} folds",
        "noise_floor": run.cv_error_noise_floor,
        "model_limited": run.model_limited,
        "suggestions": [{key: s.get(key) for key in SUGGESTION_KEYS} for s in (result or {}).get("suggestions", [])],
        "undecided": [t["effect"] for t in (result or {}).get("undecided", [])],
        "error_after": diag.get("error_after"),
        "delta_bic_after": diag.get("delta_bic_after"),
        # the undeclared instrument named instead of a sample effect (kind, frequency, ...), None when none is
        "instrument": diag.get("instrument"),
        # every candidate refitted for this run (the effects-tried figure of this run on the loop page); without
        # the refits' wall times, which differ between a diagnosis made now and one reused
        "tried": [{k: v for k, v in t.items() if k != "seconds"} for t in (result or {}).get("tried", [])],
    }


def diagnose_runs(runs: list[RunData], last_result: dict | None, last_local: dict, suggest_effects: bool,
                  progress: bool = False, traces: list | None = None, localized: list | None = None) -> list[dict]:
    """Each run's own diagnosis, in order. The last run's ``suggest`` result and localisation are reused; a
    run file given twice is diagnosed once; the refits of each :func:`suggest` try only the effects that run
    lacks (:func:`afmid.diagnosis.stored.diagnosed`: a diagnosis kept for the run is reused, not refitted).
    ``traces``: each run's trace held in memory (None: read from its input file), as :func:`suggest` takes;
    ``localized``: each run's :func:`localize` already made (None: made here)."""
    done: dict[Path, dict] = {runs[-1].path.resolve(): run_diagnosis(runs[-1], last_result, last_local)}
    out = []
    for i, (run, trace) in enumerate(zip(runs, traces or [None] * len(runs))):
        key = run.path.resolve()
        if key not in done:
            local = localized[i] if localized is not None else None
            done[key] = run_diagnosis(run, diagnosed(run, progress=progress, trace=trace) if suggest_effects else None,
                                      local)
        out.append(done[key])
    return out


def force_band(run: RunData) -> dict:
    """The force's uncertainty band of a run (summary.json ``runs[*].force_band``): each share and their total in
    quadrature, relative to the peak |force|, 1 sigma (afmid.fit.force_band); None where a share was not computed
    (the separation given: no separation share; no bootstrap: no statistical share). ``separation_fraction`` is the
    separation's part of the total's variance (its share squared over the total squared)."""
    total, separation = run.force_total_uncertainty, run.force_separation_uncertainty
    fraction = (separation / total) ** 2 if total > 0 and math.isfinite(separation) else math.nan
    return {"total": total, "separation": separation, "statistical": run.force_statistical_uncertainty,
            "selection": run.force_selection_uncertainty, "calibration": run.force_calibration_uncertainty,
            "separation_fraction": fraction, "unit": "1 (relative to the peak |force|)", "error_kind": "1 sigma"}


def separation_entry(run: RunData) -> dict:
    """The rest separation of a run with its 1 sigma (m) and whether it was estimated."""
    return {"value": run.separation, "error": run.separation_error if run.separation_estimated else 0.0,
            "estimated": run.separation_estimated, "unit": "m", "error_kind": "1 sigma"}


def band_words(entry: dict) -> str:
    """"force known to 4.1 % of the peak (1σ), 62 % of its variance from the estimated separation 8.1 ± 0.4 nm (1σ)" from a
    summary.json run entry; "" for a run file without a force band (written before the band existed)."""
    band, sep = entry.get("force_band") or {}, entry.get("separation") or {}
    total = band.get("total")
    if total is None or not math.isfinite(total):
        return ""
    words = f"force known to {100 * total:.2g} % of the peak (1σ)"
    value = sep.get("value")
    if value is not None and math.isfinite(value):
        if sep.get("estimated"):
            fraction = band.get("separation_fraction")
            share = (f"{100 * fraction:.0f} % of its variance from" if fraction is not None
                     and math.isfinite(fraction) else "with")
            words += f", {share} the estimated separation {format_measurement(value, sep.get('error', math.nan), 'm')}"
        else:
            words += f", the separation {format_value(value, 'm')} given"
    return words


def run_entry(path: Path, run: RunData, diagnosis: dict) -> dict:
    """One entry of summary.json's ``runs``."""
    return {"run": str(path), "effects": run.effects, "error": run.cv_error,
            "force_band": force_band(run), "separation": separation_entry(run),
            "error_fold_sd": diagnosis["error_fold_sd"], "error_spread_kind": diagnosis["error_spread_kind"],
            "noise_floor": run.cv_error_noise_floor, "n_terms": run.n_terms, "terms": run.selected_terms,
            "chi2_reduced": run.chi2_reduced, "model_limited": run.model_limited,
            "tip_radius": run.cantilever.get("tip_radius"),  # m: the bound of forces that grow with the tip
            "parameters": {k: {"value": v["value"], "error": v["error"], "error_kind": ERROR_LABEL,
                               "error_statistical": statistical_error(v),
                               "error_calibration": v.get("error_calibration", 0.0),
                               TRACK_LEVEL_ERROR: v.get(TRACK_LEVEL_ERROR, 0.0),
                               "ci_low": v.get("ci_low"), "ci_high": v.get("ci_high"), "interval": "95 %",
                               "model_limited": v.get("model_limited", False), "unit": v["unit"],
                               "determined": v.get("determined", True), "effect": v.get("effect", ""),
                               "plausible": v.get("plausible", True), "plausibility": v.get("plausibility", "")}
                           for k, v in run.quantities.items()},
            "diagnosis": diagnosis}


# --------------------------------------------------------------------------- the loop
_REGIONS = {"contact": "in contact", "near": "near the surface", "far": "far from the surface"}
_CHARACTERS = {"conservative": "conservative (the same on approach and retraction)",
               "dissipative": "dissipative (it reverses with the direction of motion)",
               "mixed": "partly conservative, partly direction-dependent", "none": "not distinguishable from noise"}


def _state(run: RunData, diagnosis: dict) -> str:
    error = error_text(run.cv_error, diagnosis["error_fold_sd"], diagnosis["error_folds"])
    floor_dof = getattr(run, "cv_error_floor_dof", math.nan)  # NaN: the single factor (older stand-ins)
    return f"{error}, {_ratio_words(run.cv_error, run.cv_error_noise_floor, floor_dof)}"


def _failure(diagnosis: dict) -> str:
    region = _REGIONS.get(diagnosis["region"], diagnosis["region"])
    character = _CHARACTERS.get(diagnosis["character"], diagnosis["character"])
    return f"it fails mostly {region}: the residual is {character}"


def _suggestion_words(diagnosis: dict) -> str:
    sugg = diagnosis["suggestions"]
    if sugg:
        names = " + ".join(f"`{s['effect']}`" for s in sugg)
        top = sugg[0]
        return (f"suggested: add {names} (ΔBIC {format_delta_bic(top['delta_bic'])}, error after "
                f"{format_value(top['error_after'], '1')})")
    if diagnosis["undecided"]:
        return "a missing effect, but the data cannot decide between " + ", ".join(
            f"`{e}`" for e in diagnosis["undecided"])
    return diagnosis["verdict"]


def _relation(prev: RunData, prev_diag: dict, run: RunData) -> tuple[str, str]:
    """(kind, words): how ``run``'s model relates to the previous run's."""
    added = [e for e in run.effects if e not in prev.effects]
    removed = [e for e in prev.effects if e not in run.effects]
    suggested = {s["effect"] for s in prev_diag["suggestions"]}
    a, p = run.path.name, prev.path.name
    if not added and not removed:
        return "same_model", f"{a} has the same effects as {p} ({', '.join(run.effects) or 'a preset library'})"
    if added and not removed and set(added) <= suggested:
        return "follow_up", f"{a} = {p} + {' + '.join(f'`{e}`' for e in added)}: the suggestion followed"
    if added and not removed:
        undecided = set(prev_diag["undecided"])
        why = (" (one of the effects the data could not tell apart)" if set(added) <= undecided else
               f" — not what the diagnosis of {p} suggested")
        return "added_unsuggested", f"{a} = {p} + {' + '.join(f'`{e}`' for e in added)}{why}"
    words = f"{a} is a different model: [{', '.join(run.effects)}]"
    if removed:
        words += f" (without {', '.join(f'`{e}`' for e in removed)}"
        words += f", with {', '.join(f'`{e}`' for e in added)})" if added else ")"
    return "different_model", words


def _change(prev: RunData, run: RunData) -> str:
    before, after = prev.cv_error, run.cv_error
    if not (math.isfinite(before) and math.isfinite(after)):
        return "the errors cannot be compared:"
    verb = "fell" if after < before else "rose" if after > before else "stayed"
    return f"the error {verb} from {format_value(before, '1')} to"


#: Read-outs of two runs of one model agree when they differ by at most this many combined sigmas (1 sigma each,
#: in quadrature): two independent right answers differ by more 1 time in 22.
AGREEMENT_SIGMAS = 2.0


def readout_agreement(prev: RunData, run: RunData) -> list[dict]:
    """The read-outs two runs of the same model share, compared: one entry per read-out determined in both with a
    finite 1-sigma error (value and error of each, SI unit; ``z``: their difference over the errors in quadrature;
    ``agree``: z <= :data:`AGREEMENT_SIGMAS`). The errors are those the runs hold (statistical, and calibration when
    declared: the same calibration moves both runs alike, so a declared one makes the test lenient)."""
    out = []
    for name, a in prev.quantities.items():
        b = run.quantities.get(name)
        if b is None or not (a.get("determined", True) and b.get("determined", True)):
            continue
        values, errors = (float(a["value"]), float(b["value"])), (float(a["error"]), float(b["error"]))
        combined = math.hypot(*errors)
        if not (all(map(math.isfinite, values + errors)) and combined > 0):
            continue
        z = abs(values[1] - values[0]) / combined
        out.append({"quantity": name, "unit": a["unit"], "values": list(values), "errors": list(errors), "z": z,
                    "agree": z <= AGREEMENT_SIGMAS})
    return out


def agreement_words(prev: RunData, run: RunData, compared: list[dict]) -> str:
    """What :func:`readout_agreement` found, and why two runs of one model may disagree."""
    if not compared:
        return "no read-out is determined in both with an error bar, so they cannot be compared"
    sigma = f"{AGREEMENT_SIGMAS:g}σ"
    agree = [f"{c['quantity']} ({c['z']:.1f}σ)" for c in compared if c["agree"]]
    differ = [f"{c['quantity']} ({c['z']:.1f}σ: {format_value(c['values'][0], c['unit'])} against "
              f"{format_value(c['values'][1], c['unit'])})" for c in compared if not c["agree"]]
    same_record = prev.input_sha256 is not None and prev.input_sha256 == run.input_sha256
    words = f"read-outs {'of the same record ' if same_record else ''}within their combined {sigma}: "
    words += ", ".join(agree) if agree else "none"
    if not differ:
        return words
    words += f"; beyond it: {', '.join(differ)}"
    if prev.model_limited or run.model_limited:
        limited = " and ".join(r.path.name for r in (prev, run) if r.model_limited)
        return (words + f": {limited} {'is' if ' and ' not in limited else 'are'} model-limited, and a model that "
                "misses part of the force biases its parameters by more than their error bars, differently on "
                "different data")
    return (words + ": neither run is model-limited, so the sample, the instrument or the calibration changed "
            "between them (non-stationarity), or the error bars are too narrow")


#: Two runs of one record name the same instrument when the kinds agree and the frequencies lie within this factor
#: (the detector search's resolution with the separation estimated: tests/preprocess/test_instrument.py).
SAME_INSTRUMENT_FACTOR = 2.0


def instrument_words(prev: RunData, prev_diagnosis: dict, run: RunData, diagnosis: dict) -> str:
    """For two runs of the same record (one input file, e.g. its halves): whether their diagnoses name the same
    undeclared instrument. One record was taken through one instrument, so an instrument named for one part and not
    for the other (or a different one) is not established by either; '' when neither names one, or the runs are
    of different records."""
    if prev.input_sha256 is None or prev.input_sha256 != run.input_sha256:
        return ""
    found = [d.get("instrument") for d in (prev_diagnosis, diagnosis)]
    if not any(found):
        return ""

    def named(instrument) -> str:
        if not instrument:
            return "none"
        return f"a {instrument['kind'].replace('_', ' ')} near {format_value(instrument['frequency'], 'Hz')}"

    a, b = found
    if a and b and a["kind"] == b["kind"] and (
            max(a["frequency"], b["frequency"]) <= SAME_INSTRUMENT_FACTOR * min(a["frequency"], b["frequency"])):
        return f"both parts of the record name {named(a)} and {named(b)}: the instrument is consistent"
    return (f"the instrument differs between the parts of one record ({prev.path.name}: {named(a)}; {run.path.name}: "
            f"{named(b)}), which were taken through one instrument: neither part establishes it (check the "
            "instrument's specification, e.g. data.detector, before declaring it)")


def loop_steps(runs: list[RunData], diagnoses: list[dict]) -> list[dict]:
    """The runs read in order: one step per run (what it is, how it fared, what its diagnosis said)."""
    steps = []
    for i, (run, diagnosis) in enumerate(zip(runs, diagnoses)):
        name = f"{run.path.name} [{', '.join(run.effects) or 'preset library'}]"
        limited = run.model_limited or bool(diagnosis.get("missing_effect"))
        if i == 0:
            kind, how = "first", f"{name}: error {_state(run, diagnosis)}"
        else:
            kind, how = _relation(runs[i - 1], diagnoses[i - 1], run)
            how = f"{how}; {_change(runs[i - 1], run)} {_state(run, diagnosis)}"
        parts = [how]
        compared = readout_agreement(runs[i - 1], run) if kind == "same_model" else None
        if compared is not None:
            parts.append(agreement_words(runs[i - 1], run, compared))
            instrument = instrument_words(runs[i - 1], diagnoses[i - 1], run, diagnosis)
            if instrument:
                parts.append(instrument)
        if limited:
            parts.append(_failure(diagnosis))
        said = _suggestion_words(diagnosis)
        parts.append(("what is left: " + said) if i == len(runs) - 1 else said)
        step = {"run": str(run.path), "relation": kind, "text": "; ".join(parts) + "."}
        if compared is not None:
            step["agreement"] = compared
        steps.append(step)
    return steps


def loop_html(steps: list[dict], rich, evidence: list[str] | None = None) -> str:
    """The loop section of the page (``rich``: the page's escaper that turns `name` into code; ``evidence``: each
    step's where-it-fails and effects-tried block, :func:`afmid.report.loop_evidence.run_evidence_html`)."""
    evidence = evidence or [""] * len(steps)
    items = "".join(f"<li>{rich(s['text'])}{block}</li>" for s, block in zip(steps, evidence))
    return ("<h2>The loop, run by run</h2><p>Each run is diagnosed on its own (the refits try the effects it "
            "lacks); the error is the cross-validated force error ± the standard deviation of its folds.</p>"
            f"<ol class='loop'>{items}</ol>")


def loop_lines(steps: list[dict]) -> list[str]:
    """The loop for the terminal: one line per run."""
    return [f"{i + 1}. " + html.unescape(s["text"]).replace("`", "") for i, s in enumerate(steps)]
