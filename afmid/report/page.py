"""``afmid report``: figures, a self-contained HTML page and summary.json for one or more runs.

The last run is diagnosed (:mod:`afmid.diagnosis.diagnose`); all runs are compared by
their cross-validated error and physical parameters. Outputs (pinned):
``DIR/report.html`` (figures embedded, opens offline), ``DIR/*.png`` with an SVG of each
beside it (``DIR/*.svg``, linked under each figure: :mod:`afmid.report.figures`),
``DIR/summary.json``, and the marker ``DIR/.afmid-report``. The folder is written
under a temporary name and swapped in when complete; ``--overwrite`` replaces
only a report folder afmid wrote (:mod:`afmid.report.folder`).
"""

from __future__ import annotations

import html
import json
import logging
import math
import re
from pathlib import Path

import numpy as np

from afmid.version import __version__
import afmid.fit.plausibility as plausibility
from afmid.diagnosis.diagnose import BIC_EVIDENCE, describe_residual, localize
from afmid.diagnosis.localize import energy_check
from afmid.diagnosis.stored import diagnosed
from afmid.report.energy_rows import energy_caveat, energy_rows, inverted_force_name
from afmid.io.trace import now_iso
from afmid.physics.effects import EFFECTS
from afmid.physics.tips import effect_for, tip_geometry
from afmid.diagnosis.checklist import check_lines
from afmid.diagnosis.candidate_shapes import shape_words
from afmid.fit.uncertainty import (INTERVALS_STATISTICAL, STATISTICAL_ONLY_TEXT, TRACK_LEVEL_ERROR, calibration_declared,
                                   intervals_kind, one_sigma_parts)
from afmid.report.figures import figure_html
from afmid.report.folder import report_folder
from afmid.report.forked_figures import figures_aside
from afmid.report.observables import summarize as summarize_observables
from afmid.report.plots import (bandwidth_text, fig_coefficients, fig_error_runs, fig_force_separation, no_contact_note,
                                fig_force_time, fig_observables, fig_periods, fig_phase_portraits, fig_residual,
                                fig_suggestions)
from afmid.report.loop_evidence import (REGION_HEADER, SUGGESTIONS_CAPTION, earlier_run_figures, region_rows,
                                        residual_caption, run_evidence_html)
from afmid.report.quantity_text import format_delta_bic, format_measurement, format_number, format_value
from afmid.report.story import (band_words, diagnose_runs, error_text, fold_spread, loop_html, loop_lines, loop_steps,
                                run_entry)
from afmid.runcheck import check_same_traces
from afmid.runfile import RunData, load_run

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- truth
def truth_coefficients(run: RunData) -> dict[str, float]:
    """True coefficient of each run term (by effect.label) for simulated traces; missing terms are 0."""
    if run.truth is None:
        return {}
    params = dict(run.truth.parameters)
    out: dict[str, float] = {}
    for name in run.terms:
        effect, _, label = name.partition(".")
        if effect in run.truth.effects and effect in EFFECTS:
            term = next((t for t in effect_for(effect, tip_geometry(run.config.cantilever)).terms
                         if t.label == label), None)
            out[name] = float(term.coefficient(params)) if term else math.nan
        else:
            out[name] = 0.0
    return out


def truth_quantities(run: RunData) -> dict[str, float]:
    """True physical quantities for simulated traces (the effects' read-out of the true coefficients)."""
    if run.truth is None:
        return {}
    params = dict(run.truth.parameters)
    out = {}
    for effect_name in run.truth.effects:
        if effect_name not in EFFECTS:  # simulated with an effect this afmid does not know
            continue
        effect = effect_for(effect_name, tip_geometry(run.config.cantilever))  # the tip the trace was simulated with
        try:
            coefs = {t.label: t.coefficient(params) for t in effect.terms}
            with np.errstate(all="ignore"):
                out.update({k: float(v) for k, v in effect.readout(coefs, params).items()})
        except (KeyError, ValueError, ZeroDivisionError):
            continue
        out.update({p.name: float(params[p.name]) for p in effect.parameters if p.nonlinear and p.name in params})
    return out


# --------------------------------------------------------------------------- html
def _img(folder: Path, name: str, caption: str) -> str:
    return figure_html(folder, name, caption)


def _rich(text: str) -> str:
    """Escape for HTML, turning `name` into <code>name</code>."""
    return re.sub(r"`([^`<>]+)`", r"<code>\1</code>", html.escape(str(text)))


def _table(header: list[str], rows: list[list]) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_rich(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


CSS = """body{font-family:system-ui,sans-serif;max-width:1150px;margin:2em auto;color:#222;line-height:1.45}
h1{font-size:1.5em}h2{font-size:1.2em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:left;vertical-align:top}
th{background:#f3f3f3}figure{margin:1em 0}img{max-width:100%}figcaption{font-size:.85em;color:#555}
.verdict{padding:.8em 1em;border-left:6px solid #2a7;background:#f3fbf6;margin:1em 0}
.verdict.found{border-color:#d80;background:#fff8ec}.verdict.unexplained{border-color:#c33;background:#fdf0f0}
.verdict h2{border:none;margin:0 0 .3em 0;font-size:1.15em}.verdict p{margin:.3em 0}
code{background:#f3f3f3;padding:0 .2em}
details.run-evidence{margin:.4em 0 1em;padding:.2em .6em;border-left:3px solid #ddd}
details.run-evidence summary{cursor:pointer;color:#444}details.run-evidence h3{font-size:1em;margin:.6em 0 .2em}"""


def _verdict_box(summary: dict, last_name: str | None = None) -> str:
    """The verdict on the (last) run; ``last_name`` given when the page compares several runs."""
    diag = summary.get("diagnosis") or {}
    sugg = summary.get("suggestions") or []
    if "missing_effect" not in summary or not diag:
        return ("<div class='verdict'><h2>Verdict: not diagnosed</h2><p>"
                + html.escape(summary.get("note", "suggestions were not requested (--no-suggest)")) + "</p></div>")
    facts = (f"Current model: error {format_number(diag.get('error'))} "
             f"(noise floor {format_number(diag.get('noise_floor'))}), "
             f"reduced χ² {format_number(diag.get('chi2_reduced'))} (significant above {format_number(diag.get('chi2_limit'))}).")
    band = band_words(summary["runs"][-1]) if summary.get("runs") else ""
    if band:  # how well the force itself is known, next to the verdict on its law
        facts += f" {band[0].upper()}{band[1:]}."
    if sugg and diag.get("explained_by_catalog", False):
        top = sugg[0]
        head = f"Missing effect: <code>{html.escape(top['effect'])}</code>"
        body = f"<p>{_rich(top['evidence'])}</p>"
        if len(sugg) > 1:
            body += "<p>Also missing: " + ", ".join(f"<code>{html.escape(s['effect'])}</code>" for s in sugg[1:]) + "</p>"
        cls = "found"
    elif sugg:
        top = sugg[0]
        head = (f"Not explained by the catalog: <code>{html.escape(top['effect'])}</code> accounts for only part "
                "of the residual")
        body = f"<p>{_rich(top['evidence'])}</p><p>Residual: {_rich(diag.get('description', ''))}.</p>"
        cls = "unexplained"
    elif summary.get("undecided"):  # afmid.diagnosis.decide: several effects, not told apart by the data
        head = "A missing effect, but the data cannot decide which"
        body = f"<p>{_rich(diag.get('verdict', ''))}.</p>"
        cls = "unexplained"
    elif summary.get("missing_effect"):
        head = "A significant residual that no catalog effect explains"
        body = (f"<p>{_rich(diag.get('description', ''))}.</p><p>No effect in the catalog lowers the BIC by "
                "the evidence threshold with physical parameter values; see 'Effects tried'.</p>")
        cls = "unexplained"
    else:
        head = "No effect is missing: the model explains the data to the noise level"
        body = "<p>No catalog effect improves the fit with strong evidence; see 'Effects tried'.</p>"
        cls = ""
    if summary.get("what_to_check"):  # afmid.diagnosis.checklist: the inputs to check, not a fix
        body += ("<p><b>What to check</b> before trusting any force law on this record (no effect or instrument "
                 "declaration is suggested without evidence):</p><ul>"
                 + "".join(f"<li>{html.escape(line)}</li>" for line in check_lines(summary["what_to_check"]))
                 + "</ul>")
    if last_name:
        head = f"The last run, {html.escape(last_name)}: {head[0].lower()}{head[1:]}"
    return f"<div class='verdict {cls}'><h2>{head}</h2>{body}<p>{html.escape(facts)}</p></div>"


def render_html(runs, summary, figures, local, energy, folder: Path, truth_q: dict,
                evidence: list[str] | None = None) -> str:
    """The page; ``evidence``: each run's where-it-fails and effects-tried block for the loop (several runs)."""
    last = runs[-1]
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>afmid report</title><style>{CSS}</style></head><body>",
             f"<h1>afmid report</h1><p>{len(runs)} run(s); afmid {__version__}; made {now_iso()}. "
             "Forces are on the tip, positive = repulsive; z is the tip-sample separation (contact at z = a0). "
             f"The {inverted_force_name(last.drive_calibrated)} is F = drive − (m x'' + c x' + k x), limited to the "
             "drive harmonics that stand above the noise; the model is compared with it on the same harmonics. "
             + ("The drive is the calibrated one (drive.force_amplitude, drive.phase): this force does not depend "
                "on the model." if last.drive_calibrated else "The drive is fitted together with the force law, so "
                "this force's first harmonic (and the energy from it) depends on the model.") + "</p>"]
    diag = summary.get("diagnosis", {})
    if summary.get("loop"):  # several runs: the loop first, then the verdict on the last run
        parts.append(loop_html(summary["loop"], _rich, evidence))
    parts.append(_verdict_box(summary, last.path.name if len(runs) > 1 else None))
    parts.extend(f"<p><b>Note:</b> {html.escape(note)}</p>" for note in summary.get("notes", []))
    parts.append("<h2>Runs</h2>")
    rows = [[r.path.name, ", ".join(r.effects) or "(library)", error_text(r.cv_error, *fold_spread(r)),
             format_number(r.cv_error_noise_floor, digits=3), "yes" if r.model_limited else "no", r.n_terms,
             format_number(r.chi2_reduced, digits=3), ", ".join(r.selected_terms), e["diagnosis"]["verdict"]]
            for r, e in zip(runs, summary["runs"])]
    parts.append(_table(["run", "effects", "cv error ± sd over folds", "noise floor", "model-limited", "terms",
                         "χ²_red", "selected terms", "diagnosis of this run"], rows))
    if "error_by_run" in figures:
        parts.append(_img(folder, figures["error_by_run"], "Cross-validated error of each run, in the order given, "
                                                           "with the error a perfect model would show (noise floor)"))
    parts.extend(joint_html(r) for r in runs if r.joint)
    parts.append("<h2>Physical parameters</h2>")
    names = sorted({k for r in runs for k in r.quantities}) + sorted(
        {k for r in runs for k in r.nonlinear if k != "d"} - {k for r in runs for k in r.quantities})
    units = {p.name: p.unit for e in EFFECTS for p in e.parameters}
    units.update({k: q.get("unit", "") for r in runs for k, q in {**r.nonlinear, **r.quantities}.items()})
    rows = []
    for n in names:
        row = [n]
        for r in runs:
            q = r.quantities.get(n) or r.nonlinear.get(n)
            fixed = r.config.model.parameters.get(n)
            if q and not q.get("plausible", True):
                row.append(plausibility.flagged_value(n, q, r.cantilever.get("tip_radius")))
            elif q:
                row.append(quantity_cell(q))
            elif fixed is not None:
                row.append(f"{format_value(fixed, units.get(n, ''), 4)} (fixed)")
            else:
                row.append("–")
        if truth_q:
            truth = truth_q.get(n, math.nan)
            row.append(format_value(truth, units.get(n, ""), 4) if math.isfinite(truth) else "–")
        rows.append(row)
    parts.append(_table(["quantity"] + [r.path.name for r in runs] + (["truth"] if truth_q else []), rows))
    parts.append("<p>Errors are 1 σ: the bootstrap over periods (and the nonlinear parameters' profiles), plus, "
                 "where <code>cantilever.spring_constant_uncertainty</code> / <code>quality_factor_uncertainty</code> / "
                 "<code>data.invols_uncertainty</code> are declared, the calibration's share in quadrature (shown as stat / cal). 95 % intervals are in "
                 "the run file (<code>ci_low</code>, <code>ci_high</code>).</p>")
    if any(q.get(TRACK_LEVEL_ERROR, 0.0) > 0 for r in runs for q in r.quantities.values()):
        parts.append("<p>A separation track's read-outs also hold, in quadrature, the track's share (shown as track): "
                     "the sigma its blocks' separations gained beyond the joint fit's, carried into the law by refitting "
                     "it at the levels moved by that sigma.</p>")
    statistical = [r.path.name for r in runs if not calibration_declared(r.config)]
    if statistical:
        parts.append(f"<p><b>Statistical only</b> ({html.escape(', '.join(statistical))}): "
                     f"{html.escape(STATISTICAL_ONLY_TEXT)}.</p>")
    limited = [r.path.name for r in runs if r.model_limited]
    if limited:
        parts.append(f"<p><b>Model-limited</b>: {html.escape(', '.join(limited))}: the cross-validated error stands "
                     "above the noise floor, so the model misses part of the force and its parameters are biased by "
                     "more than their error bars (which cover the noise and a declared calibration uncertainty only). "
                     "Do not publish them as measurements.</p>")
    flagged = [(r.path.name, q.get("plausibility", "")) for r in runs for q in r.quantities.values()
               if not q.get("plausible", True)]
    if flagged:
        parts.append("<p><b>Implausible read-outs</b> (outside the range a physical sample can have, or not "
                     "determined by the data; <code>afmid effects</code> lists the ranges): these are not "
                     "results.</p><ul>"
                     + "".join(f"<li>{html.escape(run)}: {html.escape(reason)}</li>" for run, reason in flagged)
                     + "</ul>")
    parts.append(f"<h2>The last run: {html.escape(last.path.name)}</h2>")
    parts.append(_img(folder, figures["force_separation"],
                      "Force vs separation, approach (left) and retraction (right) drawn separately: the inverted "
                      "force averaged over periods (band: ±2σ of that average), the model on the same harmonics and "
                      "at full bandwidth" + (", and the true force of the simulation" if last.truth is not None else "")
                      + (f". The fit has {no_contact_note(last)}" if no_contact_note(last) else "")))
    parts.append(_img(folder, figures["force_time"],
                      "Force vs time over three consecutive steady periods: the inverted force and the identified "
                      f"model on the same bandwidth ({bandwidth_text(last)}; solid), the model at full bandwidth "
                      "(dashed)" + (", the simulation's true force (grey)" if last.truth is not None else "")
                      + ". At matched bandwidth a perfect model lies on the inverted force, ringing included: the "
                        "ringing is the finite bandwidth, not noise"))
    parts.append(_img(folder, figures["phase_portraits"],
                      "Phase portraits as in the paper's figures S1.1-S1.8: (a) the measured periods (transient ones "
                      "apart, when the record has them) and the identified model re-simulated with the fitted drive; "
                      "(b) zoom on the turn at the sample, where the tip-sample force bends the orbit; (c) the "
                      "model's deflection minus the measured mean steady orbit over the drive phase with the first "
                      "harmonic taken out (the amplitude and phase of a re-simulated orbit follow the drive and the "
                      "calibration: their differences are printed in the panel, not judged), against ±2σ of the "
                      "measured mean: a model that misses an effect bends the orbit's shape outside this band "
                      "(the panel says whether this one does)"))
    parts.append(_img(folder, figures["observables"],
                      "Tapping-mode observables per period, measured (dots) and as the identified model predicts "
                      "(dashed; the model re-simulated)" + (", truth grey (the simulation's noise-free deflection through the "
                      "same formulas, periods and drive as the measured dots: they differ by the detector noise)"
                      if last.truth is not None else "") + ": "
                      "(a) amplitude A/A0 and (b) phase φ − φ0 of the deflection's first harmonic vs the free "
                      "oscillation (A0, φ0: the cantilever model k, f0, Q driven by the drive); (c) power dissipated "
                      "in the sample, π A (F0 sin φ − c ω A) f (Cleveland et al. 1998), and (d) the virial "
                      "((k − m ω²) A² − F0 A cos φ)/2 (San Paulo and Garcia 2001). (c) and (d) depend on the drive "
                      "F0, which afmid fits together with the force law unless a calibrated drive is given, and on "
                      "k, f0, Q; summary.json has them ('observables')"))
    parts.append(_img(folder, figures["coefficients"], "Coefficients with bootstrap standard errors, 1 σ (truth when simulated)"))
    parts.append("<h2>Where the model fails</h2>")
    parts.append(f"<p>{_rich(diag.get('description', '') or describe_residual(local, last))}.</p>")
    parts.append(_table(REGION_HEADER, region_rows(local)))
    parts.append(_img(folder, figures["residual"], residual_caption(local)))
    eV = 1.602176634e-19
    parts.append("<h2>Energy check (dissipated per period)</h2>")
    parts.append("<p>Energy the sample takes from the tip per period, estimated from the inverted force, from the "
                 "cantilever's energy balance and from the model; they agree when the model captures the "
                 "dissipation.</p>")
    parts.append(_table(["from", "depends on", "energy"], [
        [what, depends, format_number(energy[key] / eV, "eV")
         + (f" ± {format_number(energy[sigma] / eV, 'eV')} (1σ, drive calibration)" if sigma else "")]
        for what, depends, key, sigma in energy_rows(energy, last.drive_calibrated)]))
    parts.append(f"<p>For scale: the drive does {format_number(energy['drive_work'] / eV, 'eV')} of work per period. "
                 f"{energy_caveat(last.drive_calibrated)}</p>")
    parts.append(_img(folder, figures["periods"], "Per period: residual, model force extremes, dissipated energy"))
    if summary.get("tried"):
        parts.append("<h2>Effects tried</h2>")
        parts.append(f"<p>Each catalog effect the model lacks was added and the trace refitted. Accepted: BIC lower by "
                     f"more than {BIC_EVIDENCE:g} (counting nonlinear shape parameters), the effect's terms selected, "
                     "a lower cross-validated error and physically possible parameter values; ranked by BIC.</p>")
        if "suggestions" in figures:
            parts.append(_img(folder, figures["suggestions"], SUGGESTIONS_CAPTION))
        rows = [[t["effect"], format_number(t["error_after"], digits=3),
                 format_delta_bic(t["delta_bic"]) if t["delta_bic"] is not None else "–",
                 "yes" if t["significant"] else "no",
                 fitted_text(t),
                 t["evidence"]] for t in summary["tried"]]
        parts.append(_table(["effect", "error after", "ΔBIC", "accepted", "fitted", "evidence"], rows))
    parts.append("</body></html>")
    return "\n".join(parts)


def fitted_text(tried: dict) -> str:
    """A candidate's fitted values in the 'Effects tried' table: its read-outs and its shape parameters, each in
    the display unit of its declared unit (a relaxation time in µs, a decay length in nm)."""
    readouts = [f"{k} = {format_value(v['value'], v['unit'])}" for k, v in tried["parameters"].items()
                if v["value"] is not None and math.isfinite(v["value"])]
    return ", ".join(readouts + shape_words(tried["effect"], tried.get("nonlinear", {})))


# --------------------------------------------------------------------------- main
def joint_html(run: RunData) -> str:
    """A joint fit's traces (data.paths): one law, a separation and a cross-validated error per trace."""
    rows = [[Path(t["path"]).name,
             (f"{t['separation'] * 1e9:.4f} ± {t['separation_error'] * 1e9:.4f} nm (1σ)" if t["separation_error"] > 0
              else f"{t['separation'] * 1e9:.4f} nm (given)"),
             format_number(t["cv_error"], digits=3), format_number(t["cv_error_noise_floor"], digits=3),
             "yes" if t["model_limited"] else "no"] for t in run.joint]
    return (f"<h2>Joint fit: one force law, {len(run.joint)} traces ({html.escape(run.path.name)})</h2>"
            "<p>The traces were fitted together (<code>data.paths</code>): one sample, one tip, one set of force-law "
            "coefficients and physical parameters (below: shared by every trace, their 1σ from resampling each "
            "trace's periods within it), a rest separation and a drive per trace. Each trace's error is cross-validated "
            "with the shared law (its held-out periods; the law refitted on every other period of every trace). "
            "The plots below show the first trace; the run file's <code>/joint/trace_&lt;i&gt;</code> holds every "
            "trace's per-period forces.</p>"
            + _table(["trace", "rest separation d", "cv error", "noise floor", "model-limited"], rows))


def resimulate(run: RunData) -> dict | None:
    """Forward simulation of the identified model (one steady period), or None if unavailable."""
    try:
        from afmid.simulate.driver import resimulate_run
    except ImportError:
        return None
    try:
        return resimulate_run(run)
    except Exception as exc:  # the report must not fail because a re-simulation does not settle
        log.warning("re-simulation of the identified model failed: %s", exc)
        return None


def make_report(paths: list[Path], output: Path, overwrite: bool = False, suggest_effects: bool = True,
                progress: bool = False, allow_different_traces: bool = False) -> str:
    """Write the report folder; return the terminal summary table.

    ``output`` must be new, empty, or (with ``overwrite``) a report folder afmid wrote that holds none of the
    inputs: see :mod:`afmid.report.folder`. Runs of different traces are refused unless
    ``allow_different_traces`` (then the report says so).
    """
    runs = [load_run(p) for p in paths]
    notes = check_same_traces(runs, allow_different_traces)
    return write_report(runs, output, overwrite, suggest_effects, progress, notes=notes, names=list(paths),
                        inputs={p: "a run file" for p in paths})


def write_report(runs: list[RunData], output: Path, overwrite: bool = False, suggest_effects: bool = True,
                 progress: bool = False, notes: list[str] | None = None, names: list | None = None,
                 inputs: dict | None = None, traces: list | None = None, jobs: int | None = None) -> str:
    """:func:`make_report` of runs already read (or made in memory, :func:`afmid.runfile.run_data`); return the
    terminal summary table. ``names``: each run as summary.json names it (default: its path); ``inputs``: further
    input files the folder must not hold (path -> what it is), besides the runs' traces; ``traces``: each run's
    trace in memory for its diagnosis (None: read again from its input file, :func:`afmid.diagnosis.diagnose.suggest`);
    ``jobs``: 2 draws the figures that do not need the diagnosis in a forked child while this process diagnoses, 1
    draws them here (default: ``AFMID_REPORT_JOBS``, else 2; :mod:`afmid.report.forked_figures` says when it is
    serial anyway). The files are the same either way.
    """
    output = Path(output)
    notes = notes or []
    traces = traces or [None] * len(runs)
    inputs = {**(inputs or {}), **{r.input_path: f"the trace of {r.path}" for r in runs}}
    with report_folder(output, overwrite, inputs) as tmp:
        last = runs[-1]
        local = localize(last)
        energy = energy_check(last)
        resim = resimulate(last)
        # The figures that need the diagnosis's answer: drawn once it is given (by the child too, whose matplotlib
        # is loaded by then): the effects tried and, with several runs, each earlier run's evidence on the loop.
        later = {"suggestions": lambda answer: fig_suggestions(answer, tmp)}
        if len(runs) > 1:
            later["earlier_runs"] = lambda answer: earlier_run_figures(runs, answer["diagnoses"], answer["localized"],
                                                                       tmp)
        with figures_aside(independent_figures(runs, tmp, local, energy, resim), later, jobs) as aside:
            summary, result, diagnoses, localized = _diagnosed_summary(runs, local, energy, resim, suggest_effects,
                                                                       progress, notes, names, traces)
            figures = dict(aside.get())
            answered = aside.finish({"tried": summary.get("tried"), "diagnosis": summary.get("diagnosis"),
                                     "diagnoses": diagnoses, "localized": localized})
        earlier = answered.pop("earlier_runs", [])
        figures.update(answered)
        evidence = None
        if len(runs) > 1:  # the loop carries each run's own evidence (afmid.report.loop_evidence)
            per_run = earlier + [{"residual": figures["residual"], "suggestions": figures.get("suggestions")}]
            evidence = [run_evidence_html(r, d, loc, f, tmp, _table, _rich)
                        for r, d, loc, f in zip(runs, diagnoses, localized, per_run)]
        truth_q = truth_quantities(last)
        (tmp / "summary.json").write_text(json.dumps(_jsonable(summary), indent=2), encoding="utf-8")
        (tmp / "report.html").write_text(render_html(runs, summary, figures, local, energy, tmp, truth_q, evidence),
                                         encoding="utf-8")
    return terminal_summary(summary, output)


def independent_figures(runs: list[RunData], folder: Path, local: dict, energy: dict, resim: dict | None
                        ) -> dict:
    """The figures that do not depend on the diagnosis, each as a function drawing it into ``folder`` (figure
    name -> its PNG's name): the last run's (from its run file, residual ``local``, energy check and re-simulation
    ``resim``) and, with several runs, the error by run. Drawn beside the diagnosis
    (:func:`afmid.report.forked_figures.figures_aside`)."""
    last = runs[-1]
    draws = {
        "phase_portraits": lambda: fig_phase_portraits(last, folder, resim),
        "observables": lambda: fig_observables(last, folder, resim),
        "force_time": lambda: fig_force_time(last, folder),
        "force_separation": lambda: fig_force_separation(last, folder),
        "coefficients": lambda: fig_coefficients(last, folder, truth_coefficients(last)),
        "residual": lambda: fig_residual(local, folder, last.config.sample.a0),
        "periods": lambda: fig_periods(last, local, folder, energy),
    }
    if len(runs) > 1:
        draws["error_by_run"] = lambda: fig_error_runs(runs, folder)
    return draws


def _diagnosed_summary(runs, local, energy, resim, suggest_effects, progress, notes, names, traces):
    """The diagnosis of the last run (and each run's, for the loop) and summary.json's content:
    (summary, the last run's diagnosis or None, each run's diagnosis, each run's residual)."""
    last = runs[-1]
    result = diagnosed(last, progress=progress, trace=traces[-1]) if suggest_effects else None
    localized = [local if r is last else localize(r) for r in runs] if len(runs) > 1 else [local]
    diagnoses = diagnose_runs(runs, result, local, suggest_effects, progress, traces, localized)
    summary = {"runs": [run_entry(p, r, d) for p, r, d in zip(names or [r.path for r in runs], runs, diagnoses)]}
    if len(runs) > 1:
        summary["loop"] = loop_steps(runs, diagnoses)
    if notes:
        summary["notes"] = notes
    if result is not None:
        summary.update(result)
    summary["energy"] = energy
    summary["intervals"] = intervals_kind(last.config)  # the last run's: statistical only, or with calibration
    summary["afmid_version"] = __version__
    summary["observables"] = summarize_observables(last, resim)
    return summary, result, diagnoses, localized


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    return obj


def terminal_summary(summary: dict, output: Path) -> str:
    """The lines ``afmid report`` prints: the runs (error ± sd over folds, noise floor), the loop when there are
    several runs, the verdict on the last run and its physical parameters in display units (1σ)."""
    lines = [f"{'run':<24} {'effects':<30} {'cv error ± sd over folds':>24} {'floor':>7} {'terms':>5}"]
    for r in summary["runs"]:
        d = r.get("diagnosis") or {}
        error = error_text(r["error"], r.get("error_fold_sd", math.nan), d.get("error_folds", 0))
        error = error.replace("(sd over ", "(")
        lines.append(f"{Path(r['run']).name:<24} {', '.join(r['effects']):<30} {error:>24} "
                     f"{format_number(r.get('noise_floor'), digits=3):>7} {r['n_terms']:>5}")
    for r in summary["runs"]:
        implausible = [k for k, v in r["parameters"].items() if not v.get("plausible", True)]
        if implausible:
            lines.append(f"implausible read-outs in {Path(r['run']).name}: {', '.join(implausible)} (not results; "
                         "reasons in the report)")
    if summary.get("loop"):
        lines.append("the loop:")
        lines.extend(f"  {line}" for line in loop_lines(summary["loop"]))
    last = Path(summary["runs"][-1]["run"]).name if len(summary["runs"]) > 1 else None
    diag = summary.get("diagnosis") or {}
    if "missing_effect" in summary and diag:
        verdict = diag.get("verdict") or ("missing effect" if summary["missing_effect"] else "no effect is missing")
        lines.append(f"last run ({last}): {verdict}" if last else verdict)
        band = band_words(summary["runs"][-1])
        if band:
            lines.append(f"  {band}")
        if summary.get("suggestions"):
            lines.append(f"  {summary['suggestions'][0]['evidence']}")
        elif summary["missing_effect"]:
            lines.append(f"  residual: {diag.get('description', '')}")
        if summary.get("what_to_check"):  # unexplained: the inputs to check, with their evidence
            lines.append("  what to check:")
            lines.extend(f"    {line}" for line in check_lines(summary["what_to_check"]))
    elif summary.get("note"):
        lines.append(summary["note"])
    parameters = summary["runs"][-1]["parameters"]
    if parameters:
        lines.append(f"parameters of {Path(summary['runs'][-1]['run']).name} (± 1σ):")
        tip_radius = summary["runs"][-1].get("tip_radius")
        lines.extend(f"  {name} = {parameter_text(q, name, tip_radius)}" for name, q in parameters.items())
        if summary.get("intervals") == INTERVALS_STATISTICAL:
            lines.append(f"  {STATISTICAL_ONLY_TEXT}")
    lines.extend(f"note: {note}" for note in summary.get("notes", []))
    lines.append(f"report: {output / 'report.html'}")
    return "\n".join(lines)


#: The parameter table's short names of the parts of a read-out's 1 sigma (afmid.fit.uncertainty.one_sigma_parts).
CELL_PART_NAMES = {"statistical": "stat", "calibration": "cal", "separation track": "track", "rest": "rest"}


def quantity_cell(q: dict) -> str:
    """A read-out in the parameter table, in display units: ``303.2 ± 2.6 MPa (1σ)`` (PDG rounding; the 1σ
    split into stat / cal / track in quadrature when a calibration uncertainty was declared or a separation track
    widened it), marked when the run is model-limited."""
    if q.get("determined", True) is False:
        return plausibility.not_determined_text(q, q["unit"])
    kind = "1σ"
    parts = one_sigma_parts(q)
    if parts:
        kind += "; " + " / ".join(f"{CELL_PART_NAMES[label]} {format_value(value, q['unit'], 2)}"
                                  for label, value in parts.items()) + " in quadrature"
    text = format_measurement(q["value"], q["error"], q["unit"], kind=kind)
    if q.get("model_limited"):
        text += " [model-limited]"
    return text


def parameter_text(q: dict, name: str = "", tip_radius: float | None = None) -> str:
    """A read-out as the terminal prints it: :func:`quantity_cell`, or the flag of an implausible value (with the
    range for the declared tip of radius ``tip_radius``, m)."""
    if not q.get("plausible", True):
        return plausibility.flagged_value(name, q, tip_radius)
    return quantity_cell(q)
