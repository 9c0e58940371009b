"""Where the residual of a fit sits: by region (contact, near, far), approach / retraction, conservative /
dissipative, drive phase and harmonic (:func:`localize`); and the energy the sample takes per period three ways
(:func:`energy_check`). The diagnosis (:mod:`afmid.diagnosis.diagnose`) and the report read these.
"""

from __future__ import annotations

import math

import numpy as np

from afmid.preprocess.harmonics import settled_start
from afmid.runfile import RunData

#: Separations within this distance above a0 count as "near" the surface, m.
NEAR_RANGE = 2e-9


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(a)))) if np.size(a) else 0.0


def band_limit(force: np.ndarray, run: RunData) -> np.ndarray:
    """Per-period curves (periods, phase points) limited to the drive harmonics of the inverted force.

    The inverted force only keeps the harmonics that stand above the noise
    (/diagnostics/signal_rows); the model force is evaluated from the force law
    and has all of them. Comparing the two directly would show the model's own
    high harmonics (the sharp contact) as a residual even for a perfect model.
    """
    if run.harmonics is None or run.signal_rows is None:
        return force
    n_phase = force.shape[-1]
    keep = np.zeros(n_phase // 2 + 1, dtype=bool)
    for n in np.unique(run.harmonics[run.signal_rows]):
        if n < keep.size:
            keep[n] = True
    spectrum = np.fft.rfft(force, axis=-1)
    spectrum[..., ~keep] = 0.0
    return np.fft.irfft(spectrum, n=n_phase, axis=-1)


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    if a.size < 8 or np.std(a) == 0 or np.std(b) == 0:
        return math.nan
    return float(np.corrcoef(a, b)[0, 1])


def localize(run: RunData) -> dict:
    """Residual (inverted minus model force, N) by region, direction, phase, harmonic and character.

    ``rms`` and the per-region numbers describe the systematic residual (the
    period average at equal drive phase); ``noise_rms`` is the noise left in
    that average, so ``snr`` = rms / noise_rms says whether anything
    systematic is there at all (about 1 for a perfect model).
    """
    P = run.periods
    # A transient: the average at equal drive phase over its settled end only (afmid.preprocess.harmonics.settled_start).
    first = settled_start(0.5 * (P["separation"].max(axis=1) - P["separation"].min(axis=1)))
    r_every = P["force_inverted"] - band_limit(P["force_model"], run)  # (periods, phase)
    f_inverted = P["force_inverted"][first:]
    r_all = r_every[first:]
    n_periods = r_all.shape[0]
    r = r_all.mean(axis=0)
    noise = r_all.std(axis=0, ddof=1) / math.sqrt(n_periods) if n_periods > 1 else np.zeros_like(r)
    z = P["separation"][first:].mean(axis=0)
    zdot = -P["velocity"][first:].mean(axis=0)  # dz/dt; the separation falls on approach
    force = f_inverted.mean(axis=0)
    a0 = run.config.sample.a0
    regions = {
        "contact": z <= a0,
        "near": (z > a0) & (z <= a0 + NEAR_RANGE),
        "far": z > a0 + NEAR_RANGE,
    }
    total = float(np.sum(r**2)) or 1e-300
    by_region = {}
    for name, sel in regions.items():
        app, ret = sel & (zdot < 0), sel & (zdot >= 0)
        by_region[name] = {
            "fraction_of_time": float(sel.mean()),
            "share_of_residual": float(np.sum(r[sel] ** 2) / total),
            "rms": _rms(r[sel]),
            "rms_force": _rms(force[sel]),
            "mean": float(r[sel].mean()) if sel.any() else 0.0,
            "rms_approach": _rms(r[app]),
            "rms_retraction": _rms(r[ret]),
            "noise_rms": _rms(noise[sel]),
            "rate_correlation": _corr(r[sel], zdot[sel]),
        }
    # Conservative / dissipative split: approach and retraction compared at equal separation (the retraction
    # branch interpolated onto the approach points), on the lower half of the swing where the tip interacts.
    lower = z <= np.percentile(z, 50)
    app, ret = lower & (zdot < 0), lower & (zdot >= 0)
    cons = diss = centres = split_noise = np.zeros(0)
    if app.sum() > 4 and ret.sum() > 4:
        za, order = z[app], np.argsort(z[ret])
        zr = z[ret][order]
        inside = (za >= zr[0]) & (za <= zr[-1])
        r_ret = np.interp(za[inside], zr, r[ret][order])
        n_ret = np.interp(za[inside], zr, noise[ret][order])
        cons = 0.5 * (r[app][inside] + r_ret)
        diss = 0.5 * (r[app][inside] - r_ret)
        centres = za[inside]
        split_noise = 0.5 * np.hypot(noise[app][inside], n_ret)
    cons_rms, diss_rms, split_rms = _rms(cons), _rms(diss), _rms(split_noise)
    # significant: above 3x the noise, and (for the smaller part) above 5 % of the larger one (interpolation)
    sig_cons = cons_rms > 3 * split_rms and cons_rms > 0.05 * diss_rms
    sig_diss = diss_rms > 3 * split_rms and diss_rms > 0.05 * cons_rms
    if not (sig_cons or sig_diss):
        character = "none"
    elif sig_diss and (not sig_cons or diss_rms > 2.0 * cons_rms):
        character = "dissipative"
    elif not sig_diss:
        character = "conservative"
    else:
        character = "mixed"
    period = 1.0 / run.drive["frequency"]
    dt = period / r_all.shape[1]
    residual_dissipation = float(-np.sum(r * zdot) * dt)
    spectrum = np.abs(np.fft.rfft(r)) / r.size
    spectrum[1:] *= 2
    phase_bins = 16 if r.size % 16 == 0 else 1
    by_phase = np.sqrt(np.mean(r.reshape(phase_bins, -1) ** 2, axis=1))
    main_region = max(by_region, key=lambda k: by_region[k]["share_of_residual"])
    noise_rms = _rms(noise)
    interacting = z <= a0 + NEAR_RANGE
    limit = None
    if run.harmonics is not None and run.signal_rows is not None and run.signal_rows.any():
        limit = int(np.max(run.harmonics[run.signal_rows]))
    return {
        "rms": _rms(r),
        "noise_rms": noise_rms,
        "max_signal_harmonic": limit,
        "snr": _rms(r) / noise_rms if noise_rms > 0 else math.inf,
        "rms_force": _rms(force),
        "rms_per_period": _rms(r_all),
        "by_region": by_region,
        "region": main_region,
        "character": character,
        "conservative_rms": cons_rms,
        "dissipative_rms": diss_rms,
        "split_noise_rms": split_rms,
        "conservative_mean": float(np.mean(cons)) if cons.size else 0.0,
        "split_separation": np.asarray(centres),
        "split_conservative": np.asarray(cons),
        "split_dissipative": np.asarray(diss),
        "residual_dissipated_energy": residual_dissipation,
        "rate_correlation": by_region["contact"]["rate_correlation"],
        "rate_correlation_interacting": _corr(r[interacting], zdot[interacting]),
        "by_harmonic": spectrum,
        "by_phase": by_phase,
        "per_period_rms": np.sqrt(np.mean(r_every**2, axis=1)),  # every period, the transient's too
        "mean_residual": r,
        "mean_noise": noise,
        "mean_separation": z,
        "mean_rate": zdot,
    }


def energy_check(run: RunData) -> dict:
    """Energy the sample takes from the tip per period (J), three ways, plus the truth of a simulation.

    - ``inverted``: -closed integral of F dz of the inverted force F = F_drive - (m x'' + c x' + k x);
    - ``energy_balance``: the work of the drive on the lever minus its
      own viscous loss, from the measured motion: on a steady periodic orbit the
      spring and inertia terms do no net work, so this equals ``inverted`` up
      to the harmonics the inverted force leaves out (a check of the
      processing, not an independent measurement);
    - ``model``: -closed integral of F dz of the identified force law: the
      independent one, it agrees with the other two when the model captures
      the dissipation;
    - ``truth`` (simulated traces only): from the simulator's true force;
    - ``drive_calibration_sigma`` (a calibrated drive only): 1 sigma of the first two from the declared
      uncertainties of F0 and the phase (the drive enters them linearly: through its work per period).

    The first two use the run's drive: with the drive fitted (``run.drive_calibrated`` False) its amplitude
    and phase are fitted together with the force law, so a model that lacks a dissipative effect pulls them
    towards its own (too small) value; with a calibrated drive (:mod:`afmid.fit.declared_drive`) they do
    not depend on the model.
    """
    P = run.periods
    out = {
        "inverted": float(np.mean(P["dissipated_energy_inverted"])),
        "model": float(np.mean(P["dissipated_energy"])),
    }
    x = P["deflection"]
    v = P["velocity"]
    phase = P["phase"]
    omega = 2 * np.pi * run.drive["frequency"]
    period = 2 * np.pi / omega
    drive = run.drive["cos"] * np.cos(phase) + run.drive["sin"] * np.sin(phase)  # curves are at w t = phase
    cl = run.cantilever
    damping = cl["spring_constant"] / (cl["quality_factor"] * 2 * np.pi * cl["resonance_frequency"])
    work = np.mean(np.sum(drive * v, axis=1)) * period / x.shape[1]
    viscous = damping * np.mean(np.sum(v**2, axis=1)) * period / x.shape[1]
    out["energy_balance"] = float(work - viscous)
    out["drive_work"] = float(work)
    if run.drive_calibrated:  # both drive-based rows move with the drive's work: F0 scales it, the phase turns it
        turned = run.drive["sin"] * np.cos(phase) - run.drive["cos"] * np.sin(phase)  # dF_drive / dphase
        work_turned = np.mean(np.sum(turned * v, axis=1)) * period / x.shape[1]
        out["drive_calibration_sigma"] = float(math.hypot(work * run.drive.get("force_amplitude_uncertainty", 0.0),
                                                          work_turned * run.drive.get("phase_uncertainty", 0.0)))
    truth = run.truth
    if truth is not None and truth.force.size == truth.separation.size > 1 and "time" in run.force:
        t = run.force["time"]
        dt = float(t[1] - t[0]) if t.size > 1 else math.nan
        periods = truth.force.size * dt * run.drive["frequency"]
        if math.isfinite(periods) and periods > 0:
            f_mid = 0.5 * (truth.force[1:] + truth.force[:-1])
            out["truth"] = float(-np.sum(f_mid * np.diff(truth.separation)) / periods)
    return out


# --------------------------------------------------------------------------- suggestions
