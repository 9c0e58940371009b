"""What ``afmid fit`` prints when it is done: the identified law, the physical parameters, the verdicts.

A plain function of the fit's result (:func:`fit_text`), so tests read the same text the user reads; the CLI
only prints it. Numbers are in human units with labelled intervals (:mod:`afmid.quantity_text`): every ±
says ``(1σ)``, every interval ``(95 %)``. A read-out whose term was not selected says "not determined", never
``0 ± 0``; a fit whose error stands above its noise floor says MODEL-LIMITED on every parameter it biases.
``verbose`` adds how the terms were selected: the criterion, the candidate supports with their criterion values
relative to the chosen one, and the library terms that were dropped.
"""

from __future__ import annotations

import math

import numpy as np

from afmid.fit.plausibility import judge, judge_separation
from afmid.fit.uncertainty import (STATISTICAL_ONLY_TEXT, calibration_declared, floor_threshold, model_limited,
                                   one_sigma_parts)
from afmid.quantity_text import format_delta_bic, format_interval, format_measurement, format_value

#: Candidate supports listed by ``-v`` (best by the criterion first).
VERBOSE_CANDIDATES = 8


def fit_text(result, verbose: bool = False) -> str:
    """The read-out of a finished fit (:class:`afmid.fit.pipeline.FitResult`) as lines of text."""
    lines = (law_lines(result) + parameter_lines(result) + intervals_lines(result) + force_lines(result)
             + error_lines(result))
    if verbose:
        lines += selection_lines(result)
    return "\n".join(lines)


def intervals_lines(result) -> list[str]:
    """One line when no calibration uncertainty is declared: the intervals above cover the noise only."""
    config = getattr(result, "config", None)
    if config is None or calibration_declared(config):
        return []
    return ["note: " + STATISTICAL_ONLY_TEXT]


def force_lines(result) -> list[str]:
    """The force's own uncertainty shares (calibration of k / Q, the estimated separation), when there are any."""
    lines = []
    calibration = getattr(result, "force_calibration_uncertainty", 0.0)
    if calibration > 0:
        lines.append(f"force: calibration share {100 * calibration:.2g} % (1σ, relative)")
    separation = getattr(result, "force_separation_uncertainty", math.nan)
    if math.isfinite(separation):  # not NaN: the separation was estimated
        lines.append(f"force: separation share {100 * separation:.2g} % of the peak (1σ, RMS over the samples)")
    statistical = getattr(result, "force_statistical_uncertainty", math.nan)
    if math.isfinite(statistical):  # not NaN: error bars by the bootstrap
        lines.append(f"force: statistical share {100 * statistical:.2g} % of the peak (1σ, RMS over the samples; "
                     "bootstrap over periods)")
    selection = getattr(result, "force_selection_uncertainty", math.nan)
    if math.isfinite(selection) and selection > 0:  # a term of a selected effect was dropped
        lines.append(f"force: selection share {100 * selection:.2g} % of the peak (1σ: half its change with the "
                     "dropped terms of the selected effects forced in)")
    total = getattr(result, "force_total_uncertainty", math.nan)
    if math.isfinite(total) and len(lines) > 1:
        lines.append(f"force: known to {100 * total:.2g} % of the peak (1σ, the shares above in quadrature)"
                     + _record_clause(result, statistical, separation, selection, calibration, total))
    return lines


def _record_clause(result, statistical: float, separation: float, selection: float, calibration: float,
                   total: float) -> str:
    """"; a record of about N periods ..." when the band is above the target and a longer record would help."""
    from afmid.fit.force_band import RECORD_TARGET, periods_for_total

    periods = getattr(result, "n_periods", None)
    if total <= RECORD_TARGET or periods is None:
        return ""
    needed = periods_for_total(periods, statistical, separation, selection, calibration if calibration > 0 else math.nan)
    if needed is None:
        return f"; no longer record brings it to {100 * RECORD_TARGET:.2g} % (the calibration share is larger)"
    return f"; a record of about {needed:,} periods (now {periods:,}) would bring it to {100 * RECORD_TARGET:.2g} %"


def _selected_columns(result) -> list[int]:
    mask = np.asarray(result.selected[: result.n_library], dtype=bool)
    return [int(j) for j in np.flatnonzero(mask)]


def law_lines(result) -> list[str]:
    """The identified law: F_ts as the sum of the selected terms, each coefficient with its 1σ (SI units of the
    coefficient: N per unit of the term)."""
    columns = _selected_columns(result)
    if not columns:
        return ["identified law: no term selected (F_ts = 0 within the noise)"]
    lines = ["identified law, F_ts [N] = sum of (coefficient x term), z = separation, delta = indentation:"]
    for j in columns:
        term = result.library.terms[j]
        coefficient = format_measurement(float(result.coef[j]), float(result.coef_std[j]), term.coefficient_unit)
        lines.append(f"  {term.name}: {coefficient} x {term.expression}")
    return lines


def _nonlinear_lines(result) -> list[str]:
    lines = []
    for name, est in getattr(result, "nonlinear", {}).items():
        label = "rest separation d" if name == "d" else name
        if math.isfinite(est.sigma) and est.sigma > 0:
            lines.append(f"  {label} = {format_measurement(est.value, est.sigma, est.unit)} (estimated, profile)")
        else:
            lines.append(f"  {label} = {format_value(est.value, est.unit, significant=4)} (estimated, no error bar)")
        if name == "d" and est.estimated:
            verdict = judge_separation(float(est.value), float(est.sigma))
            if not verdict.plausible:
                lines[-1] += f"; IMPLAUSIBLE: {verdict.finding}"
    return lines


def parameter_lines(result) -> list[str]:
    """One line per physical read-out: value ± 1σ, the 95 % interval, its plausibility and model-limited mark."""
    quantities = result.quantities
    if not quantities and not getattr(result, "nonlinear", {}):
        return ["physical parameters: none (the library's terms map to no catalog effect)"]
    lines = ["physical parameters:"]
    for name, q in quantities.items():
        lines.append("  " + quantity_line(name, q))
    lines += _nonlinear_lines(result)
    return lines


def quantity_line(name: str, q: dict) -> str:
    """``E_star = 1966 ± 56 MPa (1σ), [1870, 2035] MPa (95 %)`` plus its verdicts; a term that was not selected
    is "not determined" with the interval the data allow when it is forced in."""
    unit = q.get("unit", "")
    verdict = judge(name, q)
    if q.get("determined", True) is False:
        terms = ", ".join(q.get("undetermined_terms", [])) or "its term"
        text = (f"{name}: NOT DETERMINED ({terms} not selected, inclusion probability "
                f"{q.get('inclusion', math.nan):.2f})")
        if q.get("silent_terms"):
            text += "; its column is zero on this trace, so no bound"
        lo, hi = q.get("ci_low", math.nan), q.get("ci_high", math.nan)
        if math.isfinite(lo) and math.isfinite(hi):
            text += f"; with its term forced in: {format_interval(lo, hi, unit)}"
        if not verdict.plausible:
            text += "; IMPLAUSIBLE: the model needs it"
        return text
    text = f"{name} = {format_measurement(q['value'], q.get('error', math.nan), unit)}"
    lo, hi = q.get("ci_low", math.nan), q.get("ci_high", math.nan)
    if math.isfinite(lo) and math.isfinite(hi):
        text += f", {format_interval(lo, hi, unit)}"
    parts = one_sigma_parts(q)
    if parts:
        text += "; of the 1σ, in quadrature: " + ", ".join(
            f"{'the rest' if label == 'rest' else label} {format_value(value, unit, 2)}" for label, value in parts.items())
        if "rest" in parts:
            text += " (widened after them: a model-limited fit's separation, a declared drive)"
    if q.get("undecided"):
        text += f"; the data cannot decide on {', '.join(q.get('undecided_terms', []))} (included in the error bar)"
    text += "; plausible" if verdict.plausible else f"; IMPLAUSIBLE: {verdict.finding}"
    if q.get("model_limited"):
        text += "; MODEL-LIMITED (biased beyond its error bar)"
    return text


def error_lines(result) -> list[str]:
    """The cross-validated force error against the error a perfect model would show at this noise."""
    error, floor = float(result.cv_error), float(result.cv_error_noise_floor)
    folds = np.asarray(getattr(result, "cv_error_folds", np.zeros(0)), dtype=float)
    folds = folds[np.isfinite(folds)]
    spread = f" (folds {folds.min():.3f} to {folds.max():.3f}, {folds.size} folds)" if folds.size > 1 else ""
    line = f"force error (cross-validated, relative RMS) {error:.3f}{spread}, noise floor {floor:.3f}"
    if not (math.isfinite(error) and math.isfinite(floor) and floor > 0):
        return [line + ": not compared (no finite floor)"]
    ratio = error / floor
    floor_dof = float(getattr(result, "cv_error_floor_dof", math.nan))
    limit = floor_threshold(floor_dof)
    if model_limited(error, floor, floor_dof):
        verdict = (f"MODEL-LIMITED: x{ratio:.2g} the floor (more than x{limit:.3g}); the model misses part "
                   "of the force (afmid report RUN names what is missing)")
    elif getattr(result, "model_limited", False):
        verdict = (f"MODEL-LIMITED at x{ratio:.2g} the floor: the model fails a test of its law's shape (see the "
                   "warnings), so its parameters are biased beyond their error bars")
    else:
        verdict = f"at the noise floor (x{ratio:.2g}, limit x{limit:.3g}): the model explains the force"
    return [line, f"verdict: {verdict}"]


def selection_lines(result) -> list[str]:
    """How the support was chosen (``-v``): criterion, candidate supports, dropped terms, inclusion."""
    selection = result.selection
    names = result.library.names
    n = result.n_library
    key = {"bic": "bic", "aicc": "aicc"}.get(selection.criterion, "bic")
    chosen = selection.best
    lines = [f"selection: criterion {selection.criterion}, {len(selection.candidates)} candidate supports "
             f"cross-validated; chosen: {', '.join(result.selected_terms()) or 'none'}"]
    ranked = sorted(selection.candidates, key=lambda c: getattr(c, key))
    for cand in ranked[:VERBOSE_CANDIDATES]:
        terms = ", ".join(t for t, m in zip(names, cand.mask[:n]) if m) or "none"
        delta = format_delta_bic(getattr(cand, key) - getattr(chosen, key))
        mark = "*" if cand is chosen else " "
        lines.append(f"  {mark} Δ{key.upper()} {delta:>7}  cv_rss {cand.cv_rss:.4g}  [{terms}]")
    if len(ranked) > VERBOSE_CANDIDATES:
        lines.append(f"    ... {len(ranked) - VERBOSE_CANDIDATES} more")
    inclusion = np.asarray(getattr(result, "inclusion", np.ones(n)), dtype=float)
    dropped = [f"{names[j]} (inclusion {inclusion[j]:.2f})" for j in range(n) if not result.selected[j]]
    lines.append("dropped: " + (", ".join(dropped) if dropped else "none (every library term is in the law)"))
    return lines
