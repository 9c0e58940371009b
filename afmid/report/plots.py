"""The single-run report's figures (``afmid report``): each ``fig_*`` draws one figure of the last run (or of
all runs) and writes it with :func:`afmid.report.figures.save_figure` (PNG + SVG), returning the PNG's name.

Forces are shown in nN, separations and deflections in nm (the page's units); the run data stay SI.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np

from afmid.diagnosis.diagnose import BIC_EVIDENCE
from afmid.diagnosis.localize import band_limit
from afmid.report import observables
from afmid.report.figures import FULL_WIDTH, log_axis, pyplot, save_figure
from afmid.quantity_text import display_unit, format_delta_bic
from afmid.runfile import RunData

NN = 1e9  # N -> nN for display
NM = 1e9  # m -> nm

def _plt():
    return pyplot()


# --------------------------------------------------------------------------- figures
APPROACH, RETRACTION, MODEL, TRUTH, MEASURED = "C0", "C3", "C1", "0.35", "C0"
FORCE_LABEL = "force on tip (nN, repulsive +)"


def _save(fig, folder: Path, name: str) -> str:
    return save_figure(fig, folder, name)


def _contact_line(ax, a0: float) -> None:
    ax.axvline(a0 * NM, color="k", lw=0.7, ls=":")
    ax.text(a0 * NM, 1.0, " contact (z = a0)", transform=ax.get_xaxis_transform(), fontsize=7, va="top", ha="left")


def signal_harmonics(run: RunData) -> list[int]:
    """The drive harmonics the inverted force keeps (those above the noise), ascending; [] if the run file
    does not say."""
    if run.harmonics is None or run.signal_rows is None:
        return []
    return sorted(int(n) for n in np.unique(run.harmonics[run.signal_rows]))


def bandwidth_text(run: RunData) -> str:
    """The inverted force's bandwidth in words: "drive harmonics 0-7 (up to 2.1 MHz)"."""
    kept = signal_harmonics(run)
    if not kept:
        return "the drive harmonics of the inverted force"
    top = kept[-1] * run.drive["frequency"]
    span = f"{kept[0]}–{kept[-1]}" if kept == list(range(kept[0], kept[-1] + 1)) else ", ".join(map(str, kept))
    return f"drive harmonics {span} (up to {top / 1e6:.3g} MHz)"


def steady_periods(run: RunData) -> np.ndarray:
    """Which periods are steady (bool per period): all but a leading run of periods whose first-harmonic
    amplitude differs from the record's last half by more than 5 times its period-to-period spread (a transient:
    the record starts before the oscillation has settled)."""
    amplitude = np.asarray(run.periods["amplitude"], dtype=float)
    tail = amplitude[amplitude.size // 2:]
    centre = float(np.median(tail))
    spread = 1.4826 * float(np.median(np.abs(tail - centre))) if tail.size > 2 else 0.0
    off = np.abs(amplitude - centre) > max(5.0 * spread, 1e-4 * abs(centre))
    n_transient = int(np.argmin(off)) if not off.all() else amplitude.size // 2
    steady = np.ones(amplitude.size, dtype=bool)
    steady[:n_transient] = False
    return steady


def _three_periods(run: RunData) -> np.ndarray:
    """Indices of three consecutive steady periods (contiguous in time when the record has them)."""
    start = np.asarray(run.periods["period_start_time"], dtype=float)
    period = 1.0 / run.drive["frequency"]
    candidates = np.flatnonzero(steady_periods(run))
    n = start.size
    middle = candidates[candidates.size // 2] if candidates.size else n // 2
    for first in sorted(candidates, key=lambda k: abs(k - middle)):
        if first + 2 < n and np.allclose(np.diff(start[first:first + 3]), period, rtol=1e-3):
            return np.arange(first, first + 3)
    return np.arange(max(0, min(middle, n - 3)), min(n, max(0, min(middle, n - 3)) + 3))


def _on_time_axis(run: RunData, rows: np.ndarray, curves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Period curves of ``rows`` laid end to end on the time axis (µs from the first), NaN between periods that
    are not contiguous."""
    P = run.periods
    omega = 2 * np.pi * run.drive["frequency"]
    t = P["period_start_time"][rows, None] + (P["phase"] - P["phase"][0])[None, :] / omega
    t, y = t.copy(), np.asarray(curves, dtype=float).copy()
    t = np.concatenate([t, t[:, -1:] + (t[:, 1:2] - t[:, :1])], axis=1)  # close each period at its end
    y = np.concatenate([y, y[:, :1]], axis=1)
    gap = np.r_[np.diff(P["period_start_time"][rows]) > 1.001 / run.drive["frequency"], False]
    y[gap, -1] = np.nan
    return (t.ravel() - t[0, 0]) * 1e6, y.ravel()


def fig_phase_portraits(run: RunData, folder: Path, resim: dict | None) -> str:
    """As the paper's figures S1.1-S1.8 (a, b): the measured orbit (transient periods, if the record has them,
    apart from the steady ones) with the identified model re-simulated over it, a zoom on the turn near the
    sample where the tip-sample force bends the orbit, and the model's deviation from the measured steady orbit
    over the drive phase, its first harmonic taken out, against ±2σ of the measured mean (:func:`orbit_deviation`)."""
    plt = _plt()
    P = run.periods
    x, v = P["deflection"], P["velocity"]
    steady = steady_periods(run)
    fig, axes = plt.subplots(1, 3, figsize=(FULL_WIDTH, 2.6), gridspec_kw={"width_ratios": [1.15, 1, 1.1]})
    MS = 1e3  # m/s -> mm/s
    every = max(1, int(steady.sum()) // 12)
    for ax in axes[:2]:
        for i in np.flatnonzero(~steady):
            ax.plot(x[i] * NM, v[i] * MS, color="C2", lw=0.5, alpha=0.6)
        for i in np.flatnonzero(steady)[::every]:
            ax.plot(x[i] * NM, v[i] * MS, color=MEASURED, lw=0.6, alpha=0.6)
    axes[0].plot([], [], color=MEASURED, label="measured (steady)")
    if (~steady).any():
        axes[0].plot([], [], color="C2", label=f"measured (transient, {int((~steady).sum())})")
    theta = P["phase"]
    model_x = model_v = None
    if resim is not None:
        drive_phase = math.atan2(run.drive["sin"], run.drive["cos"])
        phase_model, x_model, v_model = observables.model_period(resim)  # the model driven by F0 cos(w t)
        at = np.remainder(theta - drive_phase, 2 * np.pi)  # the measured drive is F0 cos(theta - drive_phase)
        model_x = np.interp(at, phase_model, x_model, period=2 * np.pi)
        model_v = np.interp(at, phase_model, v_model, period=2 * np.pi)
        for ax in axes[:2]:
            ax.plot(np.r_[model_x, model_x[:1]] * NM, np.r_[model_v, model_v[:1]] * MS, color=MODEL, lw=1.1,
                    ls="--", label="model, re-simulated" if ax is axes[0] else None)
    else:
        axes[0].plot([], [], " ", label="(model re-simulation not available)")
    axes[0].set(xlabel="deflection x (nm, + toward the sample)", ylabel="velocity dx/dt (mm/s)",
                title="(a) phase portrait")
    axes[0].legend(loc="center", fontsize=6.5)
    # (b) zoom on the lower turning point (largest x: the tip at the sample), where contact bends the orbit
    xs, vs = x[steady], v[steady]
    top = float(np.max(xs)) * NM
    width = 0.12 * (top - float(np.min(xs)) * NM)
    vmax = float(np.max(np.abs(vs))) * MS
    axes[1].set_xlim(top - width, top + 0.15 * width)
    axes[1].set_ylim(-0.55 * vmax, 0.55 * vmax)
    axes[1].set(xlabel="deflection x (nm)", title="(b) zoom: the turn at the sample")
    # (c) the model's orbit shape against the measured mean's, judged against the band drawn (orbit_deviation)
    deg = np.degrees(theta)
    PM = 1e12  # m -> pm
    if model_x is not None:
        dev = orbit_deviation(run, model_x)
        axes[2].fill_between(deg, -dev["band"] * PM, dev["band"] * PM, color=MEASURED, alpha=0.2, lw=0,
                             label=f"±2σ of the measured mean ({dev['periods']} periods)")
        axes[2].plot(deg, dev["shape"] * PM, color=MODEL, lw=1.1, label="model − measured, first harmonic out")
        axes[2].text(0.02, 0.98, "\n".join(textwrap.wrap(dev["words"], 44)), transform=axes[2].transAxes,
                     fontsize=6.0, va="top", ha="left", color="0.2",
                     bbox={"facecolor": "white", "alpha": 0.75, "edgecolor": "none", "pad": 1.5})
    axes[2].axhline(0, color="k", lw=0.6)
    axes[2].set(xlabel="drive phase (degrees)", ylabel="deflection difference (pm)",
                title="(c) orbit shape: model − measured", xlim=(0, 360), xticks=[0, 90, 180, 270, 360])
    axes[2].legend(fontsize=6.0, loc="lower left")
    return _save(fig, folder, "phase_portraits")


def orbit_deviation(run: RunData, model_x: np.ndarray) -> dict:
    """The re-simulated model's steady orbit against the measured one (the mean over the steady periods of
    ``/periods/deflection``, m, at the drive phases ``/periods/phase``; ``model_x`` on the same phases).

    Split in two because the two parts say different things. The first harmonic (amplitude, phase) of a
    re-simulated orbit is set by the drive and the lever's calibration as much as by the force law: on the demo the
    right model's stands 21 pm (0.16 % of A) off, the wrong one's 500 pm, and both far outside any noise band, so
    it cannot judge a model and is given in numbers (``amplitude_difference`` m, ``phase_difference`` rad). The
    rest, ``shape`` (m per phase), is how the force law bends the orbit within the period; it is judged against
    the band it is drawn with, ``band`` = 2 sd / sqrt(P) of the measured mean over P steady periods (the noise of
    the curve it is compared with; not the spread of single periods): ``ratio`` = max |shape| / mean band,
    ``inside`` = ratio <= 1, ``words`` the verdict for the figure."""
    steady = steady_periods(run)
    xs = np.asarray(run.periods["deflection"], dtype=float)[steady]
    theta = np.asarray(run.periods["phase"], dtype=float)
    mean_x = xs.mean(axis=0)
    periods = int(xs.shape[0])
    band = (2 * xs.std(axis=0, ddof=1) / math.sqrt(periods)) if periods > 1 else np.zeros_like(mean_x)
    diff = np.asarray(model_x, dtype=float) - mean_x
    columns = np.stack([np.ones_like(theta), np.cos(theta), np.sin(theta)], axis=1)
    coef = np.linalg.lstsq(columns, diff, rcond=None)[0]
    shape = diff - columns @ coef  # the mean offset and the first harmonic taken out
    (a_model, model_lag), (a_meas, meas_lag) = (observables.first_harmonic(model_x, theta),
                                                observables.first_harmonic(mean_x, theta))
    amplitude_difference = float(a_model[0] - a_meas[0])
    phase_difference = float((model_lag[0] - meas_lag[0] + math.pi) % (2 * math.pi) - math.pi)
    scale = float(np.mean(band))
    ratio = float(np.max(np.abs(shape)) / scale) if scale > 0 else math.inf
    inside = ratio <= 1.0
    words = (f"first harmonic: model A {amplitude_difference * 1e12:+.3g} pm "
             f"({100 * amplitude_difference / a_meas[0]:+.2g} %), phase {1e3 * phase_difference:+.3g} mrad (drive "
             f"and calibration, not judged). Shape: max {np.max(np.abs(shape)) * 1e12:.2g} pm, "
             + ("inside the band" if inside else f"{ratio:.2g}x the band: outside"))
    return {"shape": shape, "band": band, "periods": periods, "amplitude_difference": amplitude_difference,
            "phase_difference": phase_difference, "ratio": ratio, "inside": inside, "words": words}


def fig_force_time(run: RunData, folder: Path) -> str:
    """Three consecutive steady periods: the inverted force and the identified model on the SAME drive
    harmonics (matched bandwidth), the model at full bandwidth dashed, and the simulation's true force."""
    plt = _plt()
    P = run.periods
    rows = _three_periods(run)
    fig, ax = plt.subplots(figsize=(FULL_WIDTH, 2.5))
    t, measured = _on_time_axis(run, rows, P["force_inverted"][rows])
    _, matched = _on_time_axis(run, rows, band_limit(P["force_model"][rows], run))
    _, full = _on_time_axis(run, rows, P["force_model"][rows])
    truth = run.truth
    F = run.force
    if truth is not None and truth.force.size == F["time"].size:
        t_abs = t * 1e-6 + P["period_start_time"][rows[0]]
        inside = (t_abs >= F["time"][0]) & (t_abs <= F["time"][-1])
        true_force = np.where(inside, np.interp(t_abs, F["time"], truth.force), np.nan)
        ax.plot(t, true_force * NN, color=TRUTH, lw=0.8, label="true force (simulation)")
    ax.plot(t, full * NN, color=MODEL, lw=0.8, ls="--", label="identified model, full bandwidth")
    ax.plot(t, measured * NN, color=MEASURED, lw=1.3, label="inverted force (equation of motion)")
    ax.plot(t, matched * NN, color=MODEL, lw=1.3, label="identified model, same harmonics")
    ax.set(xlabel="time (µs)", ylabel=FORCE_LABEL,
           title=f"Tip-sample force, three steady periods (solid: {bandwidth_text(run)})")
    ax.set_xlim(t[0], np.nanmax(t))
    fig.legend(loc="outside lower center", ncol=2, fontsize=6.5)
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


#: How far above the contact distance (or, without contact, above the closest approach) the force-vs-separation
#: panels reach, m: the range where tip-sample forces are strong.
SEPARATION_WINDOW = 4e-9


def contact_gap(run: RunData) -> float:
    """How far the period-mean closest approach stays above the contact distance a0, m (<= 0: the tip reaches
    contact)."""
    return float(np.nanmin(run.periods["separation"].mean(axis=0)) - run.config.sample.a0)


def no_contact_note(run: RunData) -> str:
    """The sentence the force-vs-separation figure carries when the fit has no contact ("" when it has)."""
    gap = contact_gap(run)
    if not gap > 0:
        return ""
    return (f"no contact: the closest approach stays {gap * NM:.3g} nm above the contact distance a0 = "
            f"{run.config.sample.a0 * NM:.3g} nm, so only the attractive (non-contact) branch is drawn")


def separation_window(run: RunData) -> tuple[float, float]:
    """The force-vs-separation panels' range, nm: from 0.2 nm below the closest approach to
    :data:`SEPARATION_WINDOW` above the contact distance a0, or, when the fit has no contact (a0 below the whole
    orbit, where that range would be empty), above the closest approach."""
    if contact_gap(run) > 0:  # from the period-mean closest approach: where the drawn (period-mean) curves start
        z_min = float(np.nanmin(run.periods["separation"].mean(axis=0)))
        return z_min * NM - 0.2, (z_min + SEPARATION_WINDOW) * NM
    return float(np.nanmin(run.periods["separation"])) * NM - 0.2, (run.config.sample.a0 + SEPARATION_WINDOW) * NM


def fig_force_separation(run: RunData, folder: Path) -> str:
    """Approach and retraction in separate panels: inverted-force mean with its noise band, model, truth. From
    just below the closest approach to :data:`SEPARATION_WINDOW` above the contact distance; a fit without
    contact is drawn from its closest approach up, with the note of :func:`no_contact_note` on the figure."""
    plt = _plt()
    P = run.periods
    band = band_limit(P["force_model"], run)
    fig, axes = plt.subplots(1, 2, figsize=(FULL_WIDTH, 2.8), sharey=True)
    truth = run.truth
    for ax, approach, title, colour in ((axes[0], True, "approach (tip moving toward the sample)", APPROACH),
                                         (axes[1], False, "retraction (tip moving away)", RETRACTION)):
        z, m, s = _branch_curves(run, P["force_inverted"], approach)
        ax.fill_between(z, m - s, m + s, color=colour, alpha=0.25, lw=0)
        ax.plot(z, m, color=colour, lw=1.4, label="inverted force, period mean ± 2σ")
        zb, mb, _ = _branch_curves(run, band, approach)
        ax.plot(zb, mb, color=MODEL, lw=1.2, label="model, same harmonics")
        zf, mf, _ = _branch_curves(run, P["force_model"], approach)
        ax.plot(zf, mf, color=MODEL, lw=0.8, ls="--", label="model, full bandwidth")
        true_curve = _true_branch(run, approach)
        if true_curve is not None:  # a line, drawn last: single pixels of every sample were invisible
            ax.plot(*true_curve, color=TRUTH, lw=1.0, label="true force (simulation, one steady period)", zorder=5)
        ax.set(xlabel="separation z (nm)", title=title)
    axes[0].set_ylabel(FORCE_LABEL)
    axes[0].legend(fontsize=6.5, loc="lower right")
    kept = signal_harmonics(run)
    if kept:  # the band-limited curves ring: attraction far out, a zero crossing below contact
        axes[1].text(0.98, 0.03, textwrap.fill(f"solid: drive harmonics ≤ {max(kept)} only; their ripples (attraction "
                                               "far from the sample, crossings below contact) are this bandwidth, "
                                               "not the force; dashed and grey: full bandwidth", 48),
                     transform=axes[1].transAxes, fontsize=6.2, va="bottom", ha="right", color="0.25")
    note = no_contact_note(run)
    for ax in axes:
        if not note:
            _contact_line(ax, run.config.sample.a0)
        ax.set_xlim(*separation_window(run))
    if note:
        axes[0].text(0.02, 0.98, textwrap.fill(note, 60), transform=axes[0].transAxes, fontsize=6.5, va="top",
                     ha="left")
    return _save(fig, folder, "force_separation")


def _true_branch(run: RunData, approach: bool) -> tuple[np.ndarray, np.ndarray] | None:
    """(z nm, F nN) of the simulation's true force over one steady period in the middle of the record, on one
    branch (approach: dz/dt < 0), sorted by separation; None without a truth aligned with the samples."""
    truth, F = run.truth, run.force
    if truth is None or not (truth.force.size == truth.separation.size == truth.velocity.size == F["time"].size):
        return None
    starts = run.periods["period_start_time"]
    middle = starts[starts.size // 2]
    period = 1.0 / run.drive["frequency"]
    inside = (F["time"] >= middle) & (F["time"] < middle + period)
    moving = truth.velocity > 0 if approach else truth.velocity <= 0  # dz/dt = -dx/dt: approach has dx/dt > 0
    sel = inside & moving
    if sel.sum() < 2:
        return None
    order = np.argsort(truth.separation[sel])
    return truth.separation[sel][order] * NM, truth.force[sel][order] * NN


def fig_coefficients(run: RunData, folder: Path, truth: dict[str, float]) -> str:
    plt = _plt()
    n = len(run.terms)
    fig, ax = plt.subplots(figsize=(min(FULL_WIDTH, max(3.4, 0.55 * n + 1.5)), 2.6))
    scale = np.array([abs(truth.get(t, 0.0)) or abs(c) or 1.0 for t, c in zip(run.terms, run.coefficients)])
    pos = np.arange(n)
    err = np.where(np.isfinite(run.errors), run.errors, 0.0) / scale
    ax.bar(pos - 0.2, run.coefficients / scale, 0.4, yerr=err, color=MODEL, label="identified (± bootstrap σ)", capsize=2)
    if truth:
        ax.bar(pos + 0.2, np.array([truth.get(t, 0.0) for t in run.terms]) / scale, 0.4, color="C0", label="truth")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xticks(pos, run.terms, rotation=30, ha="right", fontsize=6.5)
    ref = "|truth|" if truth else "|identified|"
    ax.set(ylabel=f"coefficient / {ref} (1)", title="Coefficients, each divided by its reference value")
    ax.legend(fontsize=6.5)
    return _save(fig, folder, "coefficients")


def compared_harmonics(local: dict) -> np.ndarray:
    """The drive harmonics on the residual's harmonic axis: 0 up to the highest one the comparison keeps
    (``max_signal_harmonic``; else the highest with a residual), never past the spectrum."""
    spectrum = np.asarray(local["by_harmonic"], dtype=float)
    present = np.flatnonzero(spectrum > 0)
    limit = local.get("max_signal_harmonic")
    top = int(limit) if limit else (int(present[-1]) if present.size else 0)
    return np.arange(min(top, spectrum.size - 1) + 1)


def fig_residual(local: dict, folder: Path, a0: float | None = None, name: str = "residual") -> str:
    """Systematic residual vs separation by direction, by region and direction, by harmonic (the axis runs over
    the harmonics the comparison keeps); written as ``name`` (.png, .svg)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(FULL_WIDTH, 2.6), gridspec_kw={"width_ratios": [1.5, 1, 0.9]})
    z, r, noise, zdot = (local["mean_separation"], local["mean_residual"], local["mean_noise"], local["mean_rate"])
    ax = axes[0]
    for sel, label, colour in ((zdot < 0, "approach", APPROACH), (zdot >= 0, "retraction", RETRACTION)):
        order = np.argsort(z[sel])
        zz, rr, nn = z[sel][order] * NM, r[sel][order] * NN, 2 * noise[sel][order] * NN
        ax.fill_between(zz, -nn, nn, color=colour, alpha=0.15, lw=0)
        ax.plot(zz, rr, color=colour, lw=1.2, label=f"{label} (band: ±2σ noise)")
    ax.axhline(0, color="k", lw=0.6)
    if a0 is not None:
        _contact_line(ax, a0)
        ax.set_xlim(z.min() * NM - 0.2, (a0 + 4e-9) * NM)
    limit = local.get("max_signal_harmonic")
    band = f" (harmonics ≤ {limit})" if limit else ""
    ax.set(xlabel="separation z (nm)", ylabel="residual (nN, inverted − model)",
           title=f"(a) vs separation{band}")
    ax.legend(fontsize=6.5)
    regions = list(local["by_region"])
    app = [local["by_region"][k]["rms_approach"] * NN for k in regions]
    ret = [local["by_region"][k]["rms_retraction"] * NN for k in regions]
    noi = [local["by_region"][k]["noise_rms"] * NN for k in regions]
    pos = np.arange(len(regions))
    axes[1].bar(pos - 0.2, app, 0.4, color=APPROACH, label="approach")
    axes[1].bar(pos + 0.2, ret, 0.4, color=RETRACTION, label="retraction")
    axes[1].plot(pos, noi, "k_", ms=16, mew=1.5, label="noise level")
    axes[1].set_xticks(pos, [f"{k}\n{100 * local['by_region'][k]['share_of_residual']:.0f} %"
                             for k in regions], fontsize=6.5)
    axes[1].set(ylabel="residual rms (nN)", title="(b) by region, share")
    axes[1].legend(fontsize=6.5)
    spectrum = np.asarray(local["by_harmonic"], dtype=float)
    harmonics = compared_harmonics(local)
    top = int(harmonics[-1])
    axes[2].bar(harmonics, spectrum[harmonics] * NN, 0.7, color="C2")
    axes[2].set_xlim(-0.6, top + 0.6)
    from matplotlib.ticker import MaxNLocator

    axes[2].xaxis.set_major_locator(MaxNLocator(integer=True, nbins=min(top + 1, 10)))
    axes[2].grid(axis="x", visible=False)
    axes[2].set(xlabel="harmonic of the drive", ylabel="residual amplitude (nN)",
                title=f"(c) by harmonic (0–{top})")
    return _save(fig, folder, name)


def fig_periods(run: RunData, local: dict, folder: Path, energy: dict | None = None) -> str:
    plt = _plt()
    P = run.periods
    fig, axes = plt.subplots(1, 3, figsize=(FULL_WIDTH, 2.3))
    k = np.arange(P["peak_force"].size)
    axes[0].plot(k, local["per_period_rms"] * NN, ".-", lw=0.8)
    axes[0].set(xlabel="period", ylabel="residual rms (nN, incl. noise)", title="residual per period")
    axes[1].plot(k, P["peak_force"] * NN, ".-", lw=0.8, label="peak repulsion")
    axes[1].plot(k, -P["adhesion_force"] * NN, ".-", lw=0.8, label="largest attraction (−)")
    axes[1].set(xlabel="period", ylabel="model force (nN)", title="model force extremes")
    axes[1].legend(fontsize=6.5)
    eV = 1.602176634e-19
    axes[2].plot(k, P["dissipated_energy_inverted"] / eV, ".-", lw=0.8, label="inverted force")
    axes[2].plot(k, P["dissipated_energy"] / eV, ".-", lw=0.8, label="model")
    if energy and "truth" in energy:
        axes[2].axhline(energy["truth"] / eV, color=TRUTH, lw=1, ls="--", label="truth (simulation, mean)")
    axes[2].set(xlabel="period", ylabel="energy per period (eV)", title="dissipated, −∮F dz")
    axes[2].legend(fontsize=6.5)
    return _save(fig, folder, "periods")


def fig_observables(run: RunData, folder: Path, resim: dict | None) -> str:
    """The tapping-mode observables per period (:mod:`afmid.report.observables`): A/A0 and the phase shift
    against the free oscillation, the dissipated power and the virial; measured (dots), the identified model's
    prediction (dashed) and, for a simulated trace, the truth (grey)."""
    plt = _plt()
    lever = observables.run_lever(run)
    measured = observables.measured_observables(run, lever)
    model = observables.model_observables(resim, lever) if resim is not None else {}
    truth = {k: float(np.mean(v)) for k, v in observables.truth_observables(run, lever).items()}
    power_scale, power_unit = display_unit("W")
    energy_scale, energy_unit = display_unit("J")
    panels = (("amplitude_ratio", 1.0, "A / A0 (1)", "(a) amplitude vs the free oscillation"),
              ("phase_shift", 180 / math.pi, "φ − φ0 (degrees, lag +)", "(b) phase vs the free oscillation"),
              ("dissipated_power", power_scale, f"dissipated power ({power_unit})", "(c) power dissipated in the sample"),
              ("virial", energy_scale, f"virial ({energy_unit})", "(d) virial of the tip-sample force"))
    fig, axes = plt.subplots(2, 2, figsize=(FULL_WIDTH, 4.0), sharex=True)
    axes = axes.ravel()
    k = np.arange(measured["amplitude"].size)
    for ax, (name, scale, label, title) in zip(axes, panels):
        ax.plot(k, measured[name] * scale, ".", color=MEASURED, label="measured")
        if name in model:
            ax.axhline(model[name] * scale, color=MODEL, ls="--", lw=1.1, label="identified model")
        if name in truth:
            ax.axhline(truth[name] * scale, color=TRUTH, lw=1.0, label="truth (simulation)")
        ax.set(ylabel=label, title=title)
        ax.ticklabel_format(axis="y", useOffset=False)
    for ax in axes[2:]:
        ax.set_xlabel("period")
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncol=3, fontsize=6.5)
    return _save(fig, folder, "observables")


def fig_error_runs(runs: list[RunData], folder: Path, summary: dict | None = None) -> str:
    """Cross-validated error of each run with each fold's value beside it and ± their standard deviation (the
    spread over folds, when the run file has them), and the run's noise floor."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(min(FULL_WIDTH, max(3.4, 1.2 * len(runs) + 1.6)), 2.6))
    labels = [f"{r.path.name}\n[{', '.join(r.effects) or 'library'}]" for r in runs]
    pos = np.arange(len(runs))
    ax.plot(pos, [r.cv_error for r in runs], "o-", color="C0", ms=5, label="cross-validated error")
    first = True
    for x, r in zip(pos, runs):
        folds = getattr(r, "cv_error_folds", None)
        if folds is not None and np.size(folds) > 1:
            folds = np.asarray(folds, dtype=float)
            jitter = np.linspace(-0.12, 0.12, folds.size)
            ax.plot(x + 0.18 + jitter * 0.5, folds, ".", color="C0", alpha=0.5, ms=3,
                    label=f"each fold ({folds.size} folds)" if first else None)
            sd = float(np.std(folds, ddof=1))
            ax.errorbar(x, r.cv_error, yerr=sd, color="C0", capsize=3, lw=1,
                        label="± sd over folds" if first else None)
            first = False
    ax.plot(pos, [r.cv_error_noise_floor for r in runs], "k_", ms=16, mew=1.5, label="noise floor")
    for x, r in zip(pos, runs):
        ax.annotate(f"{r.cv_error:.3g}", (x, r.cv_error), textcoords="offset points", xytext=(-8, 4), fontsize=7,
                    ha="right")
    ax.set_xticks(pos, labels, fontsize=6.5)
    ax.margins(x=0.2)
    ax.set(ylabel="force error (1 = no better than a constant)", title="Error by run, in the order given")
    ax.legend(fontsize=6.5)
    log_axis(ax, "y")
    return _save(fig, folder, "error_by_run")


def fig_suggestions(summary: dict, folder: Path, name: str = "suggestions") -> str | None:
    """Every candidate effect: the evidence for it (−ΔBIC, bars from 0 on a symlog axis: right = evidence for,
    left = against) and the cross-validated error after adding it; ``summary``: a diagnosis with ``tried`` and
    ``diagnosis`` (its ``error``, ``noise_floor``); written as ``name`` (.png, .svg), None when nothing was tried."""
    tried = summary.get("tried") or []
    diag = summary.get("diagnosis") or {}
    if not tried:
        return None
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(FULL_WIDTH, 0.3 * len(tried) + 1.3), sharey=True)
    names = [t["effect"] for t in tried][::-1]
    pos = np.arange(len(names))
    colours = ["C2" if t["significant"] else "0.6" for t in tried][::-1]
    evidence = np.array([-t["delta_bic"] if t["delta_bic"] is not None else 0.0 for t in tried][::-1])
    axes[0].barh(pos, evidence, left=0.0, color=colours, height=0.7)
    for y, value in zip(pos, evidence):
        axes[0].text(value, y, f" {format_delta_bic(value)} ",
                     va="center", ha="left" if value >= 0 else "right", fontsize=6.5)
    axes[0].axvline(0, color="k", lw=0.7)
    axes[0].axvline(BIC_EVIDENCE, color="k", lw=0.8, ls="--")
    axes[0].text(BIC_EVIDENCE, 0.0, f" threshold {BIC_EVIDENCE:g}", transform=axes[0].get_xaxis_transform(),
                 fontsize=6.5, va="bottom")
    axes[0].set_xscale("symlog", linthresh=BIC_EVIDENCE)
    axes[0].set_yticks(pos, names)
    axes[0].grid(axis="y", visible=False)
    high = max(10 * BIC_EVIDENCE, float(np.max(evidence)) * 8)
    low = min(0.0, float(np.min(evidence)) * 8)
    axes[0].set_xlim(low, high)
    axes[0].set(xlabel="−ΔBIC when added (larger = stronger evidence)", title="evidence for each candidate")
    err = [t["error_after"] for t in tried][::-1]
    axes[1].barh(pos, err, color=colours, height=0.7)
    if diag.get("error") is not None:
        axes[1].axvline(diag["error"], color="k", lw=1, label="current model")
    if diag.get("noise_floor") is not None:
        axes[1].axvline(diag["noise_floor"], color="k", lw=1, ls=":", label="noise floor")
    axes[1].grid(axis="y", visible=False)
    axes[1].set(xlabel="cross-validated error after adding it", title="error with the candidate added")
    axes[1].legend(fontsize=6.5, loc="upper right")
    return _save(fig, folder, name)
