"""The single-run report's figures (``afmid report``): each ``fig_*`` draws one figure of the last run (or of
all runs) and writes it with :func:`afmid.report.figures.save_figure` (PNG + SVG), returning the PNG's name.

Forces are shown in nN, separations and deflections in nm (the page's units); the run data stay SI.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from afmid.diagnosis.diagnose import band_limit
from afmid.report.figures import save_figure
from afmid.runfile import RunData

NN = 1e9  # N -> nN for display
NM = 1e9  # m -> nm

def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"figure.dpi": 110, "font.size": 9, "axes.grid": True, "grid.alpha": 0.3,
                         "figure.constrained_layout.use": True})
    return plt


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
    ok = np.isfinite(F["estimate"]) & np.isfinite(F["direct"])
    idx = np.flatnonzero(ok)
    spp = 1.0 / (run.drive["frequency"] * (F["time"][1] - F["time"][0]))
    sel = idx[: int(3 * spp)]
    fig, ax = plt.subplots(figsize=(9, 3.2))
    t = (F["time"][sel] - F["time"][sel[0]]) * 1e6
    ax.plot(t, F["direct"][sel] * NN, color="C0", lw=1, label="model-free (equation of motion, signal harmonics)")
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
    """Approach and retraction in separate panels: model-free mean with its noise band, model, truth."""
    plt = _plt()
    P = run.periods
    band = band_limit(P["force_model"], run)
    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.8), sharey=True)
    truth = run.truth
    for ax, approach, title, colour in ((axes[0], True, "approach (tip moving toward the sample)", APPROACH),
                                         (axes[1], False, "retraction (tip moving away)", RETRACTION)):
        z, m, s = _branch_curves(run, P["force_direct"], approach)
        ax.fill_between(z, m - s, m + s, color=colour, alpha=0.25, lw=0)
        ax.plot(z, m, color=colour, lw=1.4, label="model-free, period mean ± 2σ")
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
    ax.set(xlabel="separation z (nm)", ylabel="residual (nN, model-free − model)",
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
    axes[2].plot(k, P["dissipated_energy_direct"] / eV, ".-", label="model-free")
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
