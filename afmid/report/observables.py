"""The standard tapping-mode observables of a run, measured and as the identified model predicts them.

Per period, from the first harmonic of the deflection x = A cos(w t - phi) (x positive toward the sample, phi the
lag behind the drive F_drive = F0 cos(w t - phi_drive)) and the point-mass cantilever
m x'' + c x' + k x = F_drive - F_ts (F_ts the force on the tip, positive = repulsive; m = k / w0^2, c = m w0 / Q):

- amplitude ratio A / A0 and phase shift phi - phi0 against the FREE oscillation (A0, phi0), which is the
  cantilever model's linear response to the drive (:func:`free_oscillation`): it depends on k, f0, Q and the drive
  (F0, f), not on any tip-sample force;
- energy dissipated in the sample per period (energy balance over a steady period; Cleveland et al., Appl. Phys.
  Lett. 72, 2613 (1998); Garcia and San Paulo, Phys. Rev. B 60, 4961 (1999); San Paulo and Garcia, Phys. Rev. B
  64, 193411 (2001))::

      E_dis = closed integral of F_ts dx = pi A (F0 sin(phi) - c w A)          (J)
      P_dis = E_dis f                                                           (W)

- virial of the tip-sample force about the mean deflection (San Paulo and Garcia 2001)::

      V = (1/T) integral of (-F_ts) (x - <x>) dt = ((k - m w^2) A^2 - F0 A cos(phi)) / 2     (J)

  negative when the repulsive force dominates, positive when the attraction does.

Both formulas are exact for a steady period up to the higher harmonics of x (their share, pi c w sum n^2 A_n^2 and
sum (k - m n^2 w^2) A_n^2 / 2, is of order (A_2 / A)^2 ~ 1e-6 of the terms kept) and depend on the drive's F0 and
phase and on the calibration k, f0, Q: with the drive FITTED together with the force law (afmid's default), E_dis
and V inherit that fit; E_dis is a small difference of the drive work and the viscous loss, so a 1 % error of F0 is
an error of (drive work / E_dis) % in E_dis. The model's prediction is the same formulas applied to the steady
motion of the identified model re-simulated (:func:`afmid.simulate.driver.resimulate_run`) with the same drive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afmid.io.cantilever import FirstMode

#: What each observable depends on (said in summary.json and the figure's caption).
DEPENDS_ON = {
    "amplitude_ratio": "the deflection's first harmonic; A0 from the cantilever model (k, f0, Q) and the drive (F0, f)",
    "phase_shift": "the deflection's first harmonic and the drive's phase; phi0 from the cantilever model and the drive",
    "dissipated_energy": "A, phi, the drive F0 and phase, k, f0, Q (energy balance; Cleveland et al. 1998)",
    "dissipated_power": "as dissipated_energy, times the drive frequency",
    "virial": "A, phi, the drive F0 and phase, k, f0 (San Paulo and Garcia 2001)",
}

UNITS = {"amplitude": "m", "phase": "rad", "amplitude_ratio": "1", "phase_shift": "rad", "dissipated_energy": "J",
         "dissipated_power": "W", "virial": "J"}


@dataclass(frozen=True)
class DrivenLever(FirstMode):
    """The point-mass model of the cantilever's first mode and its drive (SI): the lever of a run file's
    ``cantilever`` with the drive; mass and damping as :class:`afmid.io.cantilever.Cantilever` computes them."""

    spring_constant: float  # k, N/m
    resonance_frequency: float  # f0, Hz
    quality_factor: float  # Q, 1
    drive_frequency: float  # f, Hz
    force_amplitude: float  # F0, N
    drive_phase: float = 0.0  # phi_drive, rad: F_drive = F0 cos(w t - phi_drive)

    @property
    def omega(self) -> float:
        """w = 2 pi f, rad/s."""
        return 2.0 * math.pi * self.drive_frequency


def free_oscillation(lever: DrivenLever) -> tuple[float, float]:
    """Amplitude A0 (m) and phase lag phi0 (rad, behind the drive) of the free linear steady state."""
    stiffness = lever.spring_constant - lever.mass * lever.omega ** 2
    loss = lever.damping * lever.omega
    return lever.force_amplitude / math.hypot(stiffness, loss), math.atan2(loss, stiffness)


def first_harmonic(curves: np.ndarray, phase: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Amplitude (m) and phase (rad) of x = A cos(theta - phi_x) for each row of ``curves`` (periods, points)
    sampled at the drive phases ``phase`` (rad, an even grid over one period: the rectangle rule is then exact for
    the harmonics below half the points)."""
    curves = np.atleast_2d(np.asarray(curves, dtype=float))
    a = 2.0 / phase.size * curves @ np.cos(phase)
    b = 2.0 / phase.size * curves @ np.sin(phase)
    return np.hypot(a, b), np.arctan2(b, a)


def tapping_observables(amplitude, lag, lever: DrivenLever) -> dict[str, np.ndarray]:
    """The observables for first-harmonic amplitudes ``amplitude`` (m) and lags ``lag`` behind the drive (rad):
    ``amplitude_ratio`` (1), ``phase_shift`` = lag - phi0 (rad), ``dissipated_energy`` per period (J),
    ``dissipated_power`` (W), ``virial`` (J); formulas in the module's docstring."""
    A = np.asarray(amplitude, dtype=float)
    phi = np.asarray(lag, dtype=float)
    a0, phi0 = free_oscillation(lever)
    F0, w = lever.force_amplitude, lever.omega
    energy = math.pi * A * (F0 * np.sin(phi) - lever.damping * w * A)
    virial = 0.5 * ((lever.spring_constant - lever.mass * w ** 2) * A ** 2 - F0 * A * np.cos(phi))
    return {"amplitude": A, "phase": phi, "amplitude_ratio": A / a0, "phase_shift": _wrap(phi - phi0),
            "dissipated_energy": energy, "dissipated_power": energy * lever.drive_frequency, "virial": virial}


def _wrap(angle):
    return np.remainder(np.asarray(angle) + math.pi, 2.0 * math.pi) - math.pi


def run_lever(run, force_amplitude: float | None = None, drive_phase: float | None = None) -> DrivenLever:
    """The cantilever model and drive of a run (:class:`afmid.runfile.RunData`): its calibration and its fitted
    drive (``cos``, ``sin``: F_drive = cos cos(w t) + sin sin(w t)), unless a drive is given."""
    cl, drive = run.cantilever, run.drive
    return DrivenLever(cl["spring_constant"], cl["resonance_frequency"], cl["quality_factor"], drive["frequency"],
                      math.hypot(drive["cos"], drive["sin"]) if force_amplitude is None else force_amplitude,
                      math.atan2(drive["sin"], drive["cos"]) if drive_phase is None else drive_phase)


def first_harmonic_per_period(time: np.ndarray, deflection: np.ndarray, starts: np.ndarray, frequency: float
                              ) -> tuple[np.ndarray, np.ndarray]:
    """Amplitude (m) and phase (rad) of x = A cos(w t - phi_x) + offset fitted by least squares to the samples
    (``time`` s, ``deflection`` m) of each period [start, start + 1/f) (``starts`` s): a lock-in over one period,
    exact for any number of samples per period up to the leakage of the higher harmonics (order 1/samples)."""
    t = np.asarray(time, dtype=float)
    x = np.asarray(deflection, dtype=float)
    period = 1.0 / frequency
    dt = float(t[1] - t[0])
    first = np.searchsorted(t, np.asarray(starts) - dt / 2)
    stop = np.searchsorted(t, np.asarray(starts) + period - dt / 2)
    theta = 2.0 * math.pi * frequency * t
    c, s = np.cos(theta), np.sin(theta)
    sums = {}
    for name, values in (("1", np.ones_like(t)), ("c", c), ("s", s), ("cc", c * c), ("ss", s * s), ("cs", c * s),
                         ("x", x), ("xc", x * c), ("xs", x * s)):
        cumulative = np.r_[0.0, np.cumsum(values)]
        sums[name] = cumulative[stop] - cumulative[first]
    normal = np.stack([np.stack([sums["1"], sums["c"], sums["s"]], -1), np.stack([sums["c"], sums["cc"], sums["cs"]], -1),
                       np.stack([sums["s"], sums["cs"], sums["ss"]], -1)], -2)
    rhs = np.stack([sums["x"], sums["xc"], sums["xs"]], -1)[..., None]
    coef = np.linalg.solve(normal, rhs)[..., 0]
    return np.hypot(coef[:, 1], coef[:, 2]), np.arctan2(coef[:, 2], coef[:, 1])


def measured_observables(run, lever: DrivenLever | None = None) -> dict[str, np.ndarray]:
    """Per period observables of a run from its recorded deflection (``/force/deflection`` at ``/force/time``)
    over the run's periods (``/periods/period_start_time``), with the run's fitted drive unless ``lever`` is
    given. (Not from the smoothed per-period Fourier curves of ``/periods``: those are the fit's trajectory.)"""
    lever = run_lever(run) if lever is None else lever
    amplitude, phase_x = first_harmonic_per_period(run.force["time"], run.force["deflection"],
                                                   run.periods["period_start_time"], lever.drive_frequency)
    return tapping_observables(amplitude, _wrap(phase_x - lever.drive_phase), lever)


def truth_observables(run, lever: DrivenLever | None = None) -> dict[str, np.ndarray]:
    """Per period observables of a simulated run's TRUE deflection (x = d - z of the simulation's truth, no
    detector noise), computed exactly as :func:`measured_observables` computes the measured ones: the same
    periods, the same first-harmonic fit and the same lever and drive (the run's fitted drive unless ``lever`` is
    given). Measured minus truth is then the detector noise alone (the thermal motion is in both), so the two
    agree within the noise; {} for a run without a truth aligned with its samples."""
    truth = run.truth
    if truth is None or "separation" not in truth.extra or truth.separation.size != run.force["time"].size:
        return {}
    lever = run_lever(run) if lever is None else lever
    deflection = truth.extra["separation"] - truth.separation  # x = d - z, positive toward the sample
    amplitude, phase_x = first_harmonic_per_period(run.force["time"], deflection, run.periods["period_start_time"],
                                                   lever.drive_frequency)
    return tapping_observables(amplitude, _wrap(phase_x - lever.drive_phase), lever)


def model_period(resimulated: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drive phase (rad), deflection x (m) and velocity (m/s) of the identified model's steady period re-simulated
    with the drive F0 cos(w t) (:func:`afmid.simulate.driver.resimulate_run`, whose arrays run from t = 0 to
    t = T inclusive: the end point, a repeat of the start, is dropped here so the grid is an even one)."""
    x = np.asarray(resimulated["x"], dtype=float)[:-1]
    v = np.asarray(resimulated["v"], dtype=float)[:-1]
    return 2.0 * math.pi * np.arange(x.size) / x.size, x, v


def model_observables(resimulated: dict, lever: DrivenLever) -> dict[str, float]:
    """The observables of the identified model's steady period re-simulated with the drive F0 cos(w t)
    (``resimulated`` as :func:`afmid.simulate.driver.resimulate_run` returns it: see :func:`model_period`)."""
    phase, x, _ = model_period(resimulated)
    amplitude, lag = first_harmonic(x, phase)
    free_drive = DrivenLever(lever.spring_constant, lever.resonance_frequency, lever.quality_factor,
                            lever.drive_frequency, lever.force_amplitude, 0.0)
    return {k: float(v[0]) for k, v in tapping_observables(amplitude, lag, free_drive).items()}


def summarize(run, resimulated: dict | None) -> dict:
    """The ``observables`` entry of summary.json: the free oscillation, each observable's unit, the measured mean
    and standard deviation over periods, the identified model's prediction (None without a re-simulation), for a
    simulation the truth (:func:`truth_observables`, mean over periods) and what it depends on."""
    lever = run_lever(run)
    a0, phi0 = free_oscillation(lever)
    measured = measured_observables(run, lever)
    model = model_observables(resimulated, lever) if resimulated is not None else {}
    truth = truth_observables(run, lever)
    out = {"free_oscillation": {"amplitude": a0, "phase": phi0, "unit_amplitude": "m", "unit_phase": "rad",
                                "depends_on": "k, f0, Q and the drive (F0, f): the cantilever model, no tip force"},
           "drive": {"force_amplitude": lever.force_amplitude, "phase": lever.drive_phase, "frequency":
                     lever.drive_frequency, "source": "fitted with the force law"},
           "convention": "x = A cos(w t - phi), phi the lag behind the drive; E_dis = closed integral of F dx; "
                         "V = (1/T) integral of -F (x - <x>) dt; F positive = repulsive, x toward the sample"}
    for name, values in measured.items():
        entry = {"unit": UNITS[name], "measured_mean": float(np.mean(values)),
                 "measured_sd": float(np.std(values, ddof=1)) if values.size > 1 else None,
                 "model": model.get(name)}
        if name in truth:  # a simulation: the noise-free deflection through the same estimator and drive
            entry["truth"] = float(np.mean(truth[name]))
        if name in DEPENDS_ON:
            entry["depends_on"] = DEPENDS_ON[name]
        out[name] = entry
    return out
