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

from afmid import __version__
import afmid.fit.plausibility as plausibility
from afmid.report.energy_rows import energy_caveat, energy_rows, inverted_force_name
from afmid.diagnosis.diagnose import BIC_EVIDENCE, band_limit, describe_residual, energy_check, localize, suggest
from afmid.io.trace import now_iso
from afmid.physics.effects import EFFECTS
from afmid.physics.tips import effect_for, tip_geometry
from afmid.report.figures import figure_html, save_figure
from afmid.report.folder import report_folder
from afmid.runcheck import check_same_traces
from afmid.runfile import RunData, load_run
from afmid.fit.uncertainty import ERROR_LABEL

log = logging.getLogger(__name__)
NN = 1e9  # N -> nN for display
NM = 1e9  # m -> nm


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"figure.dpi": 110, "font.size": 9, "axes.grid": True, "grid.alpha": 0.3,
                         "figure.constrained_layout.use": True})
    return plt


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


# --------------------------------------------------------------------------- figures
APPROACH, RETRACTION, MODEL, TRUTH = "C0", "C3", "C1", "0.25"


def _save(fig, folder: Path, name: str) -> str:
    return save_figure(fig, folder, name)


def _contact_line(ax, a0: float) -> None:
    ax.axvline(a0 * NM, color="k", lw=0.7, ls=":")
    ax.text(a0 * NM, 1.0, " contact (z = a0)", transform=ax.get_xaxis_transform(), fontsize=7, va="top", ha="left")


def fig_phase_portraits(run: RunData, folder: Path, resim: dict | None) -> str:
    plt = _plt()
    P = run.periods
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    x, v, a = P["deflection"], P["velocity"], P["acceleration"]
    for i in range(0, x.shape[0], max(1, x.shape[0] // 10)):
        axes[0].plot(x[i] * NM, v[i], color="C0", lw=0.6, alpha=0.5)
        axes[1].plot(v[i], a[i], color="C0", lw=0.6, alpha=0.5)
    axes[0].plot([], [], color="C0", label="measured (every few periods)")
    if resim is not None:
        axes[0].plot(resim["x"] * NM, resim["v"], color=MODEL, lw=1.2, ls="--", label="identified model, re-simulated")
        axes[1].plot(resim["v"], resim["a"], color=MODEL, lw=1.2, ls="--")
    else:
        axes[0].plot([], [], " ", label="(re-simulation not available)")
    axes[0].set(xlabel="deflection x (nm, + toward the sample)", ylabel="velocity dx/dt (m/s)", title="(x, x')")
    axes[1].set(xlabel="velocity dx/dt (m/s)", ylabel="acceleration d²x/dt² (m/s²)", title="(x', x'')")
    axes[0].legend(loc="center", fontsize=7)
    return _save(fig, folder, "phase_portraits")


def fig_force_time(run: RunData, folder: Path) -> str:
    plt = _plt()
    F = run.force
    ok = np.isfinite(F["estimate"]) & np.isfinite(F["inverted"])
    idx = np.flatnonzero(ok)
    spp = 1.0 / (run.drive["frequency"] * (F["time"][1] - F["time"][0]))
    sel = idx[: int(3 * spp)]
    fig, ax = plt.subplots(figsize=(9, 3.2))
    t = (F["time"][sel] - F["time"][sel[0]]) * 1e6
    ax.plot(t, F["inverted"][sel] * NN, color="C0", lw=1, label="inverted force (cantilever equation, signal harmonics)")
    ax.plot(t, F["estimate"][sel] * NN, color=MODEL, lw=1, ls="--", label="model (full bandwidth)")
    ax.set(xlabel="time (µs)", ylabel="force on tip (nN, repulsive +)", title="Tip-sample force over three periods")
    ax.legend(fontsize=7, loc="lower left")
    return _save(fig, folder, "force_time")


def _branch_curves(run: RunData, force: np.ndarray, approach: bool):
    """Period-averaged force on one branch, sorted by separation: (z nm, mean nN, 2 sigma nN)."""
    P = run.periods
    z = P["separation"].mean(axis=0)
    zdot = -P["velocity"].mean(axis=0)
    sel = zdot < 0 if approach else zdot >= 0
    order = np.argsort(z[sel])
    mean = force.mean(axis=0)[sel][order]
    spread = 2 * force.std(axis=0, ddof=1)[sel][order] / math.sqrt(force.shape[0]) if force.shape[0] > 1 else 0 * mean
    return z[sel][order] * NM, mean * NN, spread * NN


def fig_force_separation(run: RunData, folder: Path) -> str:
    """Approach and retraction in separate panels: inverted-force mean with its noise band, model, truth."""
    plt = _plt()
    P = run.periods
    band = band_limit(P["force_model"], run)
    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.8), sharey=True)
    truth = run.truth
    for ax, approach, title, colour in ((axes[0], True, "approach (tip moving toward the sample)", APPROACH),
                                         (axes[1], False, "retraction (tip moving away)", RETRACTION)):
        z, m, s = _branch_curves(run, P["force_inverted"], approach)
        ax.fill_between(z, m - s, m + s, color=colour, alpha=0.25, lw=0)
        ax.plot(z, m, color=colour, lw=1.4, label="inverted force, period mean ± 2σ")
        zb, mb, _ = _branch_curves(run, band, approach)
        ax.plot(zb, mb, color=MODEL, lw=1.2, ls="--", label="model, same harmonics")
        zf, mf, _ = _branch_curves(run, P["force_model"], approach)
        ax.plot(zf, mf, color=MODEL, lw=0.7, ls=":", label="model, full bandwidth")
        if truth is not None and truth.force.size == truth.separation.size == truth.velocity.size:
            moving = truth.velocity > 0 if approach else truth.velocity <= 0  # dz/dt = -dx/dt: approach has dx/dt > 0
            step = max(1, truth.force.size // 20000)
            ax.plot(truth.separation[moving][::step] * NM, truth.force[moving][::step] * NN, ",", color=TRUTH,
                    alpha=0.5, rasterized=True)  # thousands of points: an image inside the SVG
            ax.plot([], [], ".", color=TRUTH, ms=2, label="true force (simulation)")
        _contact_line(ax, run.config.sample.a0)
        ax.set(xlabel="separation z (nm)", title=title)
    axes[0].set_ylabel("force on tip (nN, repulsive +)")
    axes[0].legend(fontsize=7, loc="lower right")
    z = P["separation"]
    for ax in axes:
        ax.set_xlim(z.min() * NM - 0.2, (run.config.sample.a0 + 4e-9) * NM)
    return _save(fig, folder, "force_separation")


def fig_coefficients(run: RunData, folder: Path, truth: dict[str, float]) -> str:
    plt = _plt()
    n = len(run.terms)
    fig, ax = plt.subplots(figsize=(max(5, 0.8 * n + 2), 3.4))
    scale = np.array([abs(truth.get(t, 0.0)) or abs(c) or 1.0 for t, c in zip(run.terms, run.coefficients)])
    pos = np.arange(n)
    err = np.where(np.isfinite(run.errors), run.errors, 0.0) / scale
    ax.bar(pos - 0.2, run.coefficients / scale, 0.4, yerr=err, color=MODEL, label="identified (± bootstrap σ)", capsize=2)
    if truth:
        ax.bar(pos + 0.2, np.array([truth.get(t, 0.0) for t in run.terms]) / scale, 0.4, color="C0", label="truth")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xticks(pos, run.terms, rotation=30, ha="right")
    ref = "|truth|" if truth else "|identified|"
    ax.set(ylabel=f"coefficient / {ref} (1)", title="Coefficients, each divided by its reference value")
    ax.legend(fontsize=7)
    return _save(fig, folder, "coefficients")


def fig_residual(local: dict, folder: Path, a0: float | None = None) -> str:
    """Systematic residual vs separation by direction, by region and direction, by harmonic."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4), gridspec_kw={"width_ratios": [1.5, 1, 1]})
    z, r, noise, zdot = (local["mean_separation"], local["mean_residual"], local["mean_noise"], local["mean_rate"])
    ax = axes[0]
    for sel, label, colour in ((zdot < 0, "approach", APPROACH), (zdot >= 0, "retraction", RETRACTION)):
        order = np.argsort(z[sel])
        zz, rr, nn = z[sel][order] * NM, r[sel][order] * NN, 2 * noise[sel][order] * NN
        ax.fill_between(zz, -nn, nn, color=colour, alpha=0.15, lw=0)
        ax.plot(zz, rr, color=colour, lw=1.2, label=label)
    ax.axhline(0, color="k", lw=0.6)
    if a0 is not None:
        _contact_line(ax, a0)
        ax.set_xlim(z.min() * NM - 0.2, (a0 + 4e-9) * NM)
    band = f", harmonics ≤ {local['max_signal_harmonic']}" if local.get("max_signal_harmonic") else ""
    ax.set(xlabel="separation z (nm)", ylabel="residual (nN, inverted − model)",
           title=f"Residual vs separation (period mean{band}; ±2σ noise)")
    ax.legend(fontsize=7)
    regions = list(local["by_region"])
    app = [local["by_region"][k]["rms_approach"] * NN for k in regions]
    ret = [local["by_region"][k]["rms_retraction"] * NN for k in regions]
    noi = [local["by_region"][k]["noise_rms"] * NN for k in regions]
    pos = np.arange(len(regions))
    axes[1].bar(pos - 0.2, app, 0.4, color=APPROACH, label="approach")
    axes[1].bar(pos + 0.2, ret, 0.4, color=RETRACTION, label="retraction")
    axes[1].plot(pos, noi, "k_", ms=22, mew=1.5, label="noise level")
    axes[1].set_xticks(pos, [f"{k}\n{100 * local['by_region'][k]['share_of_residual']:.0f} % of residual" for k in regions],
                       fontsize=7)
    axes[1].set(ylabel="residual rms (nN)", title="By region and direction")
    axes[1].legend(fontsize=7)
    hh = local["by_harmonic"][: min(31, local["by_harmonic"].size)]
    axes[2].bar(np.arange(hh.size), hh * NN, color="C2")
    axes[2].set(xlabel="harmonic of the drive", ylabel="residual amplitude (nN)", title="By drive harmonic")
    return _save(fig, folder, "residual")


def fig_periods(run: RunData, local: dict, folder: Path, energy: dict | None = None) -> str:
    plt = _plt()
    P = run.periods
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.0))
    k = np.arange(P["peak_force"].size)
    axes[0].plot(k, local["per_period_rms"] * NN, ".-")
    axes[0].set(xlabel="period", ylabel="residual rms (nN)", title="Residual per period (incl. noise)")
    axes[1].plot(k, P["peak_force"] * NN, ".-", label="peak repulsion")
    axes[1].plot(k, -P["adhesion_force"] * NN, ".-", label="largest attraction (−)")
    axes[1].set(xlabel="period", ylabel="model force (nN)", title="Model force extremes per period")
    axes[1].legend(fontsize=7)
    eV = 1.602176634e-19
    axes[2].plot(k, P["dissipated_energy_inverted"] / eV, ".-", label="inverted force")
    axes[2].plot(k, P["dissipated_energy"] / eV, ".-", label="model")
    if energy and "truth" in energy:
        axes[2].axhline(energy["truth"] / eV, color=TRUTH, lw=1, ls="--", label="truth (simulation, mean)")
    axes[2].set(xlabel="period", ylabel="energy (eV)", title="Energy dissipated in the sample per period")
    axes[2].legend(fontsize=7)
    return _save(fig, folder, "periods")


def fig_error_runs(runs: list[RunData], folder: Path, summary: dict | None = None) -> str:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(max(4.5, 1.4 * len(runs) + 2), 3.2))
    labels = [f"{r.path.name}\n[{', '.join(r.effects) or 'library'}]" for r in runs]
    pos = np.arange(len(runs))
    ax.plot(pos, [r.cv_error for r in runs], "o-", label="cross-validated error")
    ax.plot(pos, [r.cv_error_noise_floor for r in runs], "k_", ms=18, mew=1.5, label="noise floor")
    for x, r in zip(pos, runs):
        ax.annotate(f"{r.cv_error:.3g}", (x, r.cv_error), textcoords="offset points", xytext=(6, 4), fontsize=7)
    ax.set_xticks(pos, labels, fontsize=7)
    ax.set_yscale("log")
    from matplotlib.ticker import FormatStrFormatter

    ax.yaxis.set_major_formatter(FormatStrFormatter("%.2g"))
    ax.yaxis.set_minor_formatter(FormatStrFormatter("%.2g"))
    ax.tick_params(axis="y", which="minor", labelsize=7)
    ax.margins(x=0.15)
    ax.set(ylabel="force error (1 = no better than a constant)", title="Error by run, in the order given")
    ax.legend(fontsize=7)
    return _save(fig, folder, "error_by_run")


def fig_suggestions(summary: dict, folder: Path) -> str | None:
    """Every candidate effect: BIC change and cross-validated error after adding it."""
    tried = summary.get("tried") or []
    diag = summary.get("diagnosis") or {}
    if not tried:
        return None
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(10, 0.45 * len(tried) + 1.6), sharey=True)
    names = [t["effect"] for t in tried][::-1]
    pos = np.arange(len(names))
    colours = ["C2" if t["significant"] else "0.6" for t in tried][::-1]
    dbic = np.array([t["delta_bic"] if t["delta_bic"] is not None else 0.0 for t in tried][::-1])
    axes[0].barh(pos, -dbic, color=colours)
    for y, value in zip(pos, dbic):
        axes[0].text(max(-value, 0.0), y, f" {value:.0f}", va="center", fontsize=7)
    axes[0].axvline(10, color="k", lw=0.8, ls="--")
    axes[0].text(10, 1.0, " evidence threshold", transform=axes[0].get_xaxis_transform(), fontsize=7, va="top")
    axes[0].set_xscale("symlog", linthresh=10)
    axes[0].set_yticks(pos, names)
    axes[0].set(xlabel="BIC decrease when added (larger = better; labels: ΔBIC)", title="Evidence for each candidate")
    err = [t["error_after"] for t in tried][::-1]
    axes[1].barh(pos, err, color=colours)
    if diag.get("error") is not None:
        axes[1].axvline(diag["error"], color="k", lw=1, label="current model")
    if diag.get("noise_floor") is not None:
        axes[1].axvline(diag["noise_floor"], color="k", lw=1, ls=":", label="noise floor")
    axes[1].set(xlabel="cross-validated error after adding it", title="Error with the candidate added")
    axes[1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    axes[0].set_xlim(right=max(20.0, float(np.max(-dbic)) * 3))
    return _save(fig, folder, "suggestions")


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


def _fmt(v: float, unit: str = "") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:.4g}{(' ' + unit) if unit else ''}"


CSS = """body{font-family:system-ui,sans-serif;max-width:1150px;margin:2em auto;color:#222;line-height:1.45}
h1{font-size:1.5em}h2{font-size:1.2em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:left;vertical-align:top}
th{background:#f3f3f3}figure{margin:1em 0}img{max-width:100%}figcaption{font-size:.85em;color:#555}
.verdict{padding:.8em 1em;border-left:6px solid #2a7;background:#f3fbf6;margin:1em 0}
.verdict.found{border-color:#d80;background:#fff8ec}.verdict.unexplained{border-color:#c33;background:#fdf0f0}
.verdict h2{border:none;margin:0 0 .3em 0;font-size:1.15em}.verdict p{margin:.3em 0}
code{background:#f3f3f3;padding:0 .2em}"""


def _verdict_box(summary: dict) -> str:
    diag = summary.get("diagnosis") or {}
    sugg = summary.get("suggestions") or []
    if "missing_effect" not in summary or not diag:
        return ("<div class='verdict'><h2>Verdict: not diagnosed</h2><p>"
                + html.escape(summary.get("note", "suggestions were not requested (--no-suggest)")) + "</p></div>")
    facts = (f"Current model: error {_fmt(diag.get('error'))} (noise floor {_fmt(diag.get('noise_floor'))}), "
             f"reduced χ² {_fmt(diag.get('chi2_reduced'))} (significant above {_fmt(diag.get('chi2_limit'))}).")
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
    return f"<div class='verdict {cls}'><h2>{head}</h2>{body}<p>{html.escape(facts)}</p></div>"


def render_html(runs, summary, figures, local, energy, folder: Path, truth_q: dict) -> str:
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
    parts.append(_verdict_box(summary))
    parts.extend(f"<p><b>Note:</b> {html.escape(note)}</p>" for note in summary.get("notes", []))
    parts.append("<h2>Runs</h2>")
    rows = [[r.path.name, ", ".join(r.effects) or "(library)", _fmt(r.cv_error), _fmt(r.cv_error_noise_floor),
             "yes" if r.model_limited else "no", r.n_terms, _fmt(r.chi2_reduced), ", ".join(r.selected_terms)]
            for r in runs]
    parts.append(_table(["run", "effects", "cv error", "noise floor", "model-limited", "terms", "χ²_red",
                         "selected terms"], rows))
    if "error_by_run" in figures:
        parts.append(_img(folder, figures["error_by_run"], "Cross-validated error of each run, in the order given, "
                                                           "with the error a perfect model would show (noise floor)"))
    parts.append("<h2>Physical parameters</h2>")
    names = sorted({k for r in runs for k in r.quantities}) + sorted(
        {k for r in runs for k in r.nonlinear if k != "d"} - {k for r in runs for k in r.quantities})
    rows = []
    for n in names:
        row = [n]
        for r in runs:
            q = r.quantities.get(n) or r.nonlinear.get(n)
            fixed = r.config.model.parameters.get(n)
            if q and not q.get("plausible", True):
                row.append(plausibility.flagged_value(n, q))
            elif q:
                row.append(quantity_cell(q))
            elif fixed is not None:
                row.append(f"{fixed:.4g} (fixed)")
            else:
                row.append("–")
        if truth_q:
            row.append(_fmt(truth_q.get(n, math.nan)))
        rows.append(row)
    parts.append(_table(["quantity"] + [r.path.name for r in runs] + (["truth"] if truth_q else []), rows))
    parts.append("<p>Errors are 1 σ: the bootstrap over periods (and the nonlinear parameters' profiles), plus, "
                 "where <code>cantilever.spring_constant_uncertainty</code> / <code>quality_factor_uncertainty</code> "
                 "are declared, the calibration's share in quadrature (shown as stat / cal). 95 % intervals are in "
                 "the run file (<code>ci_low</code>, <code>ci_high</code>).</p>")
    limited = [r.path.name for r in runs if r.model_limited]
    if limited:
        parts.append(f"<p><b>Model-limited</b>: {html.escape(', '.join(limited))}: the cross-validated error stands "
                     "above the noise floor, so the model misses part of the force and its parameters are biased by "
                     "more than their error bars (which cover noise and calibration only). Do not publish them as "
                     "measurements.</p>")
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
                      "at full bandwidth" + (", and the true force of the simulation" if last.truth is not None else "")))
    parts.append(_img(folder, figures["force_time"], "Force vs time over three periods: inverted force vs model"))
    parts.append(_img(folder, figures["phase_portraits"], "Phase portraits: measured periods vs the identified model re-simulated"))
    parts.append(_img(folder, figures["coefficients"], "Coefficients with bootstrap standard errors, 1 σ (truth when simulated)"))
    parts.append("<h2>Where the model fails</h2>")
    parts.append(f"<p>{_rich(diag.get('description', '') or describe_residual(local, last))}.</p>")
    rows = [[k, f"{100 * v['fraction_of_time']:.0f} %", f"{100 * v['share_of_residual']:.0f} %", _fmt(v["rms"] * NN, "nN"),
             _fmt(v["noise_rms"] * NN, "nN"), _fmt(v["rms_approach"] * NN, "nN"), _fmt(v["rms_retraction"] * NN, "nN"),
             _fmt(v["rate_correlation"])] for k, v in local["by_region"].items()]
    parts.append(_table(["region", "time", "share of residual", "rms", "noise", "approach", "retraction",
                         "correlation with dz/dt"], rows))
    limit = local.get("max_signal_harmonic")
    parts.append(_img(folder, figures["residual"], "Systematic residual (inverted force − model, averaged over periods): "
                                                   "vs separation for approach and retraction, by region, by harmonic. "
                      + (f"Both forces keep only the drive harmonics up to {limit} (those above the noise), so a "
                         "feature narrower in time than 1/" + str(2 * limit) + " of a period (e.g. a jump at contact) "
                         "is smeared over the neighbouring separations and rings." if limit else "")))
    eV = 1.602176634e-19
    parts.append("<h2>Energy check (dissipated per period)</h2>")
    parts.append("<p>Energy the sample takes from the tip per period, estimated from the inverted force, from the "
                 "cantilever's energy balance and from the model; they agree when the model captures the "
                 "dissipation.</p>")
    parts.append(_table(["from", "depends on", "energy"], [
        [what, depends, _fmt(energy[key] / eV, "eV")
         + (f" ± {_fmt(energy[sigma] / eV, 'eV')} (1σ, drive calibration)" if sigma else "")]
        for what, depends, key, sigma in energy_rows(energy, last.drive_calibrated)]))
    parts.append(f"<p>For scale: the drive does {_fmt(energy['drive_work'] / eV, 'eV')} of work per period. "
                 f"{energy_caveat(last.drive_calibrated)}</p>")
    parts.append(_img(folder, figures["periods"], "Per period: residual, model force extremes, dissipated energy"))
    if summary.get("tried"):
        parts.append("<h2>Effects tried</h2>")
        parts.append(f"<p>Each catalog effect the model lacks was added and the trace refitted. Accepted: BIC lower by "
                     f"more than {BIC_EVIDENCE:g} (counting nonlinear shape parameters), the effect's terms selected, "
                     "a lower cross-validated error and physically possible parameter values; ranked by BIC.</p>")
        if "suggestions" in figures:
            parts.append(_img(folder, figures["suggestions"], "Candidates: BIC decrease (green = accepted) and error after adding each"))
        rows = [[t["effect"], _fmt(t["error_after"]), _fmt(t["delta_bic"]), "yes" if t["significant"] else "no",
                 ", ".join(f"{k} = {v['value']:.3g} {v['unit']}" for k, v in t["parameters"].items()
                           if v["value"] is not None and math.isfinite(v["value"]))
                 + "".join(f", {k} = {v:.3g} m" for k, v in t.get("nonlinear", {}).items()),
                 t["evidence"]] for t in summary["tried"]]
        parts.append(_table(["effect", "error after", "ΔBIC", "accepted", "fitted", "evidence"], rows))
    parts.append("</body></html>")
    return "\n".join(parts)


# --------------------------------------------------------------------------- main
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
    output = Path(output)
    runs = [load_run(p) for p in paths]
    notes = check_same_traces(runs, allow_different_traces)
    inputs = {**{p: "a run file" for p in paths}, **{r.input_path: f"the trace of {r.path}" for r in runs}}
    with report_folder(output, overwrite, inputs) as tmp:
        last = runs[-1]
        local = localize(last)
        energy = energy_check(last)
        summary = {
            "runs": [{"run": str(p), "effects": r.effects, "error": r.cv_error, "noise_floor": r.cv_error_noise_floor,
                      "n_terms": r.n_terms,
                      "terms": r.selected_terms, "chi2_reduced": r.chi2_reduced,
                      "model_limited": r.model_limited,
                      "parameters": {k: {"value": v["value"], "error": v["error"], "error_kind": ERROR_LABEL,
                                         "error_statistical": v.get("error_statistical", v["error"]),
                                         "error_calibration": v.get("error_calibration", 0.0),
                                         "model_limited": v.get("model_limited", False), "unit": v["unit"],
                                         "plausible": v.get("plausible", True),
                                         "plausibility": v.get("plausibility", "")}
                                     for k, v in r.quantities.items()}}
                     for p, r in zip(paths, runs)],
        }
        if notes:
            summary["notes"] = notes
        if suggest_effects:
            summary.update(suggest(last, progress=progress))
        summary["energy"] = energy
        summary["afmid_version"] = __version__
        figures = {
            "phase_portraits": fig_phase_portraits(last, tmp, resimulate(last)),
            "force_time": fig_force_time(last, tmp),
            "force_separation": fig_force_separation(last, tmp),
            "coefficients": fig_coefficients(last, tmp, truth_coefficients(last)),
            "residual": fig_residual(local, tmp, last.config.sample.a0),
            "periods": fig_periods(last, local, tmp, energy),
        }
        if len(runs) > 1:
            figures["error_by_run"] = fig_error_runs(runs, tmp)
        suggestions_fig = fig_suggestions(summary, tmp)
        if suggestions_fig:
            figures["suggestions"] = suggestions_fig
        truth_q = truth_quantities(last)
        (tmp / "summary.json").write_text(json.dumps(_jsonable(summary), indent=2), encoding="utf-8")
        (tmp / "report.html").write_text(render_html(runs, summary, figures, local, energy, tmp, truth_q),
                                         encoding="utf-8")
    return terminal_summary(summary, output)


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
    lines = [f"{'run':<28} {'effects':<34} {'error':>8} {'terms':>5}"]
    for r in summary["runs"]:
        lines.append(f"{Path(r['run']).name:<28} {', '.join(r['effects']):<34} {r['error']:>8.4f} {r['n_terms']:>5}")
    for r in summary["runs"]:
        implausible = [k for k, v in r["parameters"].items() if not v.get("plausible", True)]
        if implausible:
            lines.append(f"implausible read-outs in {Path(r['run']).name}: {', '.join(implausible)} (not results; "
                         "reasons in the report)")
    diag = summary.get("diagnosis") or {}
    if "missing_effect" in summary and diag:
        lines.append(diag.get("verdict") or ("missing effect" if summary["missing_effect"] else "no effect is missing"))
        if summary.get("suggestions"):
            lines.append(f"  {summary['suggestions'][0]['evidence']}")
        elif summary["missing_effect"]:
            lines.append(f"  residual: {diag.get('description', '')}")
    elif summary.get("note"):
        lines.append(summary["note"])
    lines.extend(f"note: {note}" for note in summary.get("notes", []))
    lines.append(f"report: {output / 'report.html'}")
    return "\n".join(lines)


def quantity_cell(q: dict) -> str:
    """A read-out in the parameter table: value ± 1-sigma error (stat / cal when a calibration uncertainty was
    declared) and unit, marked when the run is model-limited."""
    if q.get("determined", True) is False:
        return plausibility.not_determined_text(q, q["unit"])
    text = f"{q['value']:.4g}"
    if math.isfinite(q["error"]):
        text += f" ± {q['error']:.2g} (1σ"
        if q.get("error_calibration", 0.0) > 0:
            text += f"; stat {q.get('error_statistical', math.nan):.2g} / cal {q['error_calibration']:.2g}"
        text += ")"
    text += f" {q['unit']}"
    if q.get("model_limited"):
        text += " [model-limited]"
    return text
