"""``afmid report``: figures, a self-contained HTML page and summary.json for one or more runs.

The last run is diagnosed (:mod:`afmid.diagnose`); all runs are compared by
their cross-validated error and physical parameters. Outputs (pinned):
``DIR/report.html`` (figures embedded, opens offline), ``DIR/*.png`` and
``DIR/summary.json``. The folder is written under a temporary name and renamed
into place when complete.
"""

from __future__ import annotations

import base64
import html
import json
import logging
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from . import __version__
from .diagnose import RunData, energy_check, load_run, localize, suggest
from .errors import OutputError
from .io import now_iso
from .physics import EFFECTS

log = logging.getLogger(__name__)
NN = 1e9  # N -> nN for display
NM = 1e9  # m -> nm


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"figure.dpi": 110, "font.size": 9, "axes.grid": True, "grid.alpha": 0.3})
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
            term = next((t for t in EFFECTS.get(effect).terms if t.label == label), None)
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
        effect = EFFECTS.get(effect_name)
        coefs = {t.label: t.coefficient(params) for t in effect.terms}
        with np.errstate(all="ignore"):
            out.update({k: float(v) for k, v in effect.readout(coefs, params).items()})
    return out


# --------------------------------------------------------------------------- figures
def _save(fig, folder: Path, name: str) -> str:
    path = folder / f"{name}.png"
    fig.savefig(path, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path.name


def fig_phase_portraits(run: RunData, folder: Path, resim: dict | None) -> str:
    plt = _plt()
    P = run.periods
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    x, v, a = P["deflection"], P["velocity"], P["acceleration"]
    for i in range(0, x.shape[0], max(1, x.shape[0] // 10)):
        axes[0].plot(x[i] * NM, v[i], color="C0", lw=0.6, alpha=0.5)
        axes[1].plot(v[i], a[i], color="C0", lw=0.6, alpha=0.5)
    axes[0].plot([], [], color="C0", label="measured")
    if resim is not None:
        axes[0].plot(resim["x"] * NM, resim["v"], color="C1", lw=1.2, ls="--", label="identified (re-simulated)")
        axes[1].plot(resim["v"], resim["a"], color="C1", lw=1.2, ls="--")
    axes[0].set(xlabel="deflection x (nm)", ylabel="dx/dt (m/s)", title="(x, x')")
    axes[1].set(xlabel="dx/dt (m/s)", ylabel="d²x/dt² (m/s²)", title="(x', x'')")
    axes[0].legend(loc="best", fontsize=8)
    return _save(fig, folder, "phase_portraits")


def fig_force_time(run: RunData, folder: Path) -> str:
    plt = _plt()
    F = run.force
    ok = np.isfinite(F["estimate"])
    idx = np.flatnonzero(ok)
    spp = 1.0 / (run.drive["frequency"] * (F["time"][1] - F["time"][0]))
    sel = idx[: int(3 * spp)]
    fig, ax = plt.subplots(figsize=(9, 3.2))
    t = (F["time"][sel] - F["time"][sel[0]]) * 1e6
    ax.plot(t, F["direct"][sel] * NN, color="C0", lw=1, label="model-free (equation of motion)")
    ax.plot(t, F["estimate"][sel] * NN, color="C1", lw=1, ls="--", label="model")
    ax.set(xlabel="time (µs)", ylabel="force on tip (nN, repulsive +)", title="Tip-sample force over three periods")
    ax.legend(fontsize=8)
    return _save(fig, folder, "force_time")


def fig_force_separation(run: RunData, folder: Path) -> str:
    plt = _plt()
    P = run.periods
    z, zdot = P["separation"], -P["velocity"]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), sharey=True)
    for ax, sel, title in ((axes[0], zdot < 0, "approach"), (axes[1], zdot >= 0, "retraction")):
        zz, fd, fm = z[sel] * NM, P["force_direct"][sel] * NN, P["force_model"][sel] * NN
        order = np.argsort(zz)
        ax.scatter(zz, fd, s=1, color="C0", alpha=0.3, label="model-free")
        ax.plot(zz[order], fm[order], ".", ms=1.5, color="C1", label="model")
        ax.axvline(run.config.sample.a0 * NM, color="k", lw=0.6, ls=":")
        ax.set(xlabel="separation z (nm)", title=title)
    axes[0].set_ylabel("force on tip (nN, repulsive +)")
    axes[0].legend(fontsize=8, markerscale=5)
    zmax = run.config.sample.a0 + 4e-9
    for ax in axes:
        ax.set_xlim(z.min() * NM - 0.2, zmax * NM)
    return _save(fig, folder, "force_separation")


def fig_coefficients(run: RunData, folder: Path, truth: dict[str, float]) -> str:
    plt = _plt()
    n = len(run.terms)
    fig, ax = plt.subplots(figsize=(max(5, 0.7 * n + 2), 3.4))
    scale = np.array([abs(truth.get(t, 0.0)) or abs(c) or 1.0 for t, c in zip(run.terms, run.coefficients)])
    pos = np.arange(n)
    ax.bar(pos - 0.2, run.coefficients / scale, 0.4, yerr=run.errors / scale, color="C1", label="identified", capsize=2)
    if truth:
        ax.bar(pos + 0.2, np.array([truth.get(t, 0.0) for t in run.terms]) / scale, 0.4, color="C0", label="truth")
    ax.set_xticks(pos, run.terms, rotation=35, ha="right")
    ax.set(ylabel="coefficient / |reference|", title="Coefficients (normalised per term)")
    ax.legend(fontsize=8)
    return _save(fig, folder, "coefficients")


def fig_residual(local: dict, folder: Path) -> str:
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.2))
    regions = list(local["by_region"])
    app = [local["by_region"][r]["rms_approach"] * NN for r in regions]
    ret = [local["by_region"][r]["rms_retraction"] * NN for r in regions]
    pos = np.arange(len(regions))
    axes[0].bar(pos - 0.2, app, 0.4, label="approach")
    axes[0].bar(pos + 0.2, ret, 0.4, label="retraction")
    axes[0].set_xticks(pos, regions)
    axes[0].set(ylabel="residual rms (nN)", title="By region and direction")
    axes[0].legend(fontsize=8)
    ph = local["by_phase"]
    axes[1].bar(np.arange(ph.size) * 360 / ph.size, ph * NN, width=360 / ph.size * 0.9, align="edge")
    axes[1].set(xlabel="drive phase (deg)", ylabel="residual rms (nN)", title="By phase in the period")
    hh = local["by_harmonic"][: min(31, local["by_harmonic"].size)]
    axes[2].bar(np.arange(hh.size), hh * NN)
    axes[2].set(xlabel="harmonic of the drive", ylabel="amplitude (nN)", title="By harmonic")
    return _save(fig, folder, "residual")


def fig_periods(run: RunData, local: dict, folder: Path) -> str:
    plt = _plt()
    P = run.periods
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.0))
    k = np.arange(P["peak_force"].size)
    axes[0].plot(k, local["per_period_rms"] * NN, ".-")
    axes[0].set(xlabel="period", ylabel="residual rms (nN)", title="Error per period")
    axes[1].plot(k, P["peak_force"] * NN, ".-", label="peak")
    axes[1].plot(k, -P["adhesion_force"] * NN, ".-", label="-adhesion")
    axes[1].set(xlabel="period", ylabel="force (nN)", title="Force per period")
    axes[1].legend(fontsize=8)
    eV = 1.602176634e-19
    axes[2].plot(k, P["dissipated_energy_direct"] / eV, ".-", label="model-free")
    axes[2].plot(k, P["dissipated_energy"] / eV, ".-", label="model")
    axes[2].set(xlabel="period", ylabel="eV", title="Dissipated energy per period")
    axes[2].legend(fontsize=8)
    return _save(fig, folder, "periods")


def fig_error_runs(runs: list[RunData], folder: Path) -> str:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(max(4, 1.2 * len(runs) + 2), 3.0))
    labels = [f"{r.path.name}\n[{', '.join(r.effects)}]" for r in runs]
    ax.plot(range(len(runs)), [r.cv_error for r in runs], "o-")
    ax.set_xticks(range(len(runs)), labels, fontsize=7)
    ax.set_yscale("log")
    ax.set(ylabel="cross-validated force error", title="Error by run")
    return _save(fig, folder, "error_by_run")


# --------------------------------------------------------------------------- html
def _img(folder: Path, name: str, caption: str) -> str:
    data = base64.b64encode((folder / name).read_bytes()).decode()
    return f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(caption)}"><figcaption>{html.escape(caption)}</figcaption></figure>'


def _table(header: list[str], rows: list[list]) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _fmt(v: float, unit: str = "") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:.4g}{(' ' + unit) if unit else ''}"


CSS = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;color:#222;line-height:1.45}
h1{font-size:1.5em}h2{font-size:1.2em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:left}
th{background:#f3f3f3}figure{margin:1em 0}img{max-width:100%}figcaption{font-size:.85em;color:#555}
.verdict{padding:.8em 1em;border-left:4px solid #2a7;background:#f3fbf6}.warn{border-color:#d80;background:#fff8ec}
code{background:#f3f3f3;padding:0 .2em}"""


def render_html(runs, summary, figures, local, energy, folder: Path, truth_q: dict) -> str:
    last = runs[-1]
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>afmid report</title><style>{CSS}</style></head><body>",
             f"<h1>afmid report</h1><p>{len(runs)} run(s); afmid {__version__}; made {now_iso()}. "
             "Forces are on the tip, positive = repulsive. The model-free force is "
             "F = drive − (m x'' + c x' + k x), band-limited to the drive harmonics above the noise.</p>"]
    diag = summary.get("diagnosis", {})
    if summary.get("suggestions"):
        top = summary["suggestions"][0]
        verdict = f"<b>Missing effect: <code>{html.escape(top['effect'])}</code>.</b> {html.escape(top['evidence'])}"
        parts.append(f"<div class='verdict warn'>{verdict}</div>")
    elif summary.get("missing_effect") is False and diag:
        if diag.get("explained_by_catalog", True):
            parts.append("<div class='verdict'><b>No effect is missing:</b> the model explains the data to the noise "
                         f"level (error {diag['error']:.3g}, noise floor {diag['noise_floor']:.3g}); adding catalog "
                         "effects does not help.</div>")
        else:
            parts.append("<div class='verdict warn'><b>A significant residual that no catalog effect explains:</b> "
                         f"{html.escape(diag['description'])}.</div>")
    parts.append("<h2>Runs</h2>")
    rows = [[r.path.name, ", ".join(r.effects) or "(library)", _fmt(r.cv_error), _fmt(r.cv_error_noise_floor),
             r.n_terms, _fmt(r.chi2_reduced), ", ".join(r.selected_terms)] for r in runs]
    parts.append(_table(["run", "effects", "cv error", "noise floor", "terms", "χ²_red", "selected terms"], rows))
    if "error_by_run" in figures:
        parts.append(_img(folder, figures["error_by_run"], "Cross-validated error of each run, in the order given"))
    parts.append("<h2>Physical parameters</h2>")
    names = sorted({k for r in runs for k in r.quantities})
    rows = []
    for n in names:
        row = [n]
        for r in runs:
            q = r.quantities.get(n)
            row.append(f"{q['value']:.4g} ± {q['error']:.2g} {q['unit']}" if q else "–")
        if truth_q:
            row.append(_fmt(truth_q.get(n, math.nan)))
        rows.append(row)
    parts.append(_table(["quantity"] + [r.path.name for r in runs] + (["truth"] if truth_q else []), rows))
    parts.append(f"<h2>The last run: {html.escape(last.path.name)}</h2>")
    parts.append(_img(folder, figures["phase_portraits"], "Phase portraits: measured periods vs the identified model re-simulated"))
    parts.append(_img(folder, figures["force_time"], "Force vs time: model-free vs model"))
    parts.append(_img(folder, figures["force_separation"], "Force vs separation, approach and retraction drawn separately"))
    parts.append(_img(folder, figures["coefficients"], "Coefficients with bootstrap standard errors (truth when simulated)"))
    parts.append("<h2>Where the model fails</h2>")
    parts.append(f"<p>{html.escape(diag.get('description', ''))}</p>")
    rows = [[k, f"{100 * v['fraction_of_time']:.0f} %", f"{100 * v['share_of_residual']:.0f} %", _fmt(v["rms"] * NN, "nN"),
             _fmt(v["rms_approach"] * NN, "nN"), _fmt(v["rms_retraction"] * NN, "nN")] for k, v in local["by_region"].items()]
    parts.append(_table(["region", "time", "share of residual", "rms", "approach", "retraction"], rows))
    parts.append(_img(folder, figures["residual"], "Residual by region and direction, by phase, by harmonic"))
    eV = 1.602176634e-19
    parts.append("<h2>Energy check (dissipated per period)</h2>")
    parts.append(_table(["from", "energy"], [
        ["model-free force (−∮F dz)", _fmt(energy["model_free"] / eV, "eV")],
        ["cantilever balance (drive work − viscous loss)", _fmt(energy["energy_balance"] / eV, "eV")],
        ["model", _fmt(energy["model"] / eV, "eV")],
    ]))
    parts.append(_img(folder, figures["periods"], "Per-period error, forces and dissipation"))
    if summary.get("tried"):
        parts.append("<h2>Effects tried</h2>")
        rows = [[t["effect"], _fmt(t["error_after"]), f"{t['delta_bic']:.0f}", "yes" if t["significant"] else "no",
                 t["evidence"]] for t in summary["tried"]]
        parts.append(_table(["effect", "error after", "ΔBIC", "accepted", "evidence"], rows))
    parts.append("</body></html>")
    return "\n".join(parts)


# --------------------------------------------------------------------------- main
def resimulate(run: RunData) -> dict | None:
    """Forward simulation of the identified model (one steady period), or None if unavailable."""
    try:
        from .simulate import resimulate_run
    except ImportError:
        return None
    try:
        return resimulate_run(run)
    except Exception as exc:  # the report must not fail because a re-simulation does not settle
        log.warning("re-simulation of the identified model failed: %s", exc)
        return None


def make_report(paths: list[Path], output: Path, overwrite: bool = False, suggest_effects: bool = True,
                progress: bool = False) -> str:
    """Write the report folder; return the terminal summary table."""
    output = Path(output)
    if output.exists() and not output.is_dir():
        raise OutputError("exists and is not a folder", file=output)
    if output.exists() and any(output.iterdir()) and not overwrite:
        raise OutputError("report folder exists and is not empty; pass --overwrite to replace it", file=output)
    runs = [load_run(p) for p in paths]
    last = runs[-1]
    local = localize(last)
    energy = energy_check(last)
    summary = {
        "runs": [{"run": str(p), "effects": r.effects, "error": r.cv_error, "noise_floor": r.cv_error_noise_floor,
                  "n_terms": r.n_terms,
                  "terms": r.selected_terms, "chi2_reduced": r.chi2_reduced,
                  "parameters": {k: {"value": v["value"], "error": v["error"], "unit": v["unit"]}
                                 for k, v in r.quantities.items()}}
                 for p, r in zip(paths, runs)],
    }
    if suggest_effects:
        summary.update(suggest(last, progress=progress))
    summary["energy"] = energy
    summary["afmid_version"] = __version__
    parent = output.parent if str(output.parent) else Path(".")
    tmp = Path(tempfile.mkdtemp(prefix=f".afmid-tmp-{output.name}.", dir=parent))
    try:
        figures = {
            "phase_portraits": fig_phase_portraits(last, tmp, resimulate(last)),
            "force_time": fig_force_time(last, tmp),
            "force_separation": fig_force_separation(last, tmp),
            "coefficients": fig_coefficients(last, tmp, truth_coefficients(last)),
            "residual": fig_residual(local, tmp),
            "periods": fig_periods(last, local, tmp),
        }
        if len(runs) > 1:
            figures["error_by_run"] = fig_error_runs(runs, tmp)
        truth_q = truth_quantities(last)
        (tmp / "summary.json").write_text(json.dumps(_jsonable(summary), indent=2), encoding="utf-8")
        (tmp / "report.html").write_text(render_html(runs, summary, figures, local, energy, tmp, truth_q),
                                         encoding="utf-8")
        if output.exists():
            shutil.rmtree(output)
        os.replace(tmp, output)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
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
    if summary.get("suggestions"):
        top = summary["suggestions"][0]
        lines.append(f"missing effect: {top['effect']} (error after adding it: {top['error_after']:.4f})")
        lines.append(f"  {top['evidence']}")
    elif "missing_effect" in summary:
        d = summary["diagnosis"]
        if d["explained_by_catalog"]:
            lines.append("no effect is missing: the model explains the data to the noise level")
        else:
            lines.append("significant residual, not explained by any catalog effect: " + d["description"])
    lines.append(f"report: {output / 'report.html'}")
    return "\n".join(lines)
