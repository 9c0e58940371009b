"""The information bound: the Cramér-Rao bound of a fitted record, used as a floor under the fit's 1-sigma.

No unbiased estimator of the separation d or of a force-law coefficient has a standard deviation below the
square root of the diagonal of the inverse Fisher information of the record. This module computes it for the
fitted model and the record's noise:

* **model**: the deflection x(t; theta) is the steady state of the driven lever (afmid.simulate: the first mode,
  RK4 with steps onto every non-smooth instant) with the fitted force law (the selected terms, their coefficients,
  the fitted nonlinear parameters), at the fitted separation and drive. theta = the estimated nonlinear parameters
  (d, decay lengths), the selected terms' coefficients and, when the drive is fitted rather than calibrated, the
  drive force's amplitude F0 (N) and phase (rad) as nuisance parameters. A preset library is bounded with the law of
  the catalog effects it stands for (all their terms), the law the fit pins d with (afmid.fit.pipeline.profile_library:
  a preset's split columns, e.g. a free adhesion constant in contact, trade off with d; measured on
  tests/configs/dmt.yaml, seed 1: 100 pm with the selected bridging constant free, 22 pm with DMT's law).
* **sensitivities**: the complex amplitudes c_k (m; x = Re sum_k c_k exp(i k w t)) of harmonics k = 1..K below
  the record's Nyquist frequency, differentiated by central differences of steady states (:func:`steady_harmonics`:
  a periodic orbit found by shooting, so a perturbed state settles in a few periods whatever Q is); the phase
  derivative is exact: dc_k / dphase = -i k c_k.
* **noise**: one-sided PSD at the harmonics (:func:`deflection_noise_psd`): the detector's white noise
  2 sigma^2 / fs (sigma the fit's noise estimate per sample), plus the thermal force's 4 k_B T c (c = k / (Q w0))
  through the free lever's |H(f)|^2 = 1 / |k - m w^2 + i c w|^2 and, behind a declared detector, its |G(f)|^2
  (the signal's harmonics are multiplied by G(f_k)). The lever's response to the thermal force is the free
  lever's: the contact stiffens the lever for part of each period, which lowers its response near resonance, so
  the true thermal motion at the harmonics is smaller than assumed here; a larger assumed noise gives a smaller
  Fisher information, so this part of the bound errs on the large (pessimistic, conservative-for-a-floor) side only
  where the thermal noise dominates the detector's; with a detector-limited record (the poor instrument, air) it
  changes nothing visible.
* **Fisher information** of a real record of duration T = P / f in stationary Gaussian noise of one-sided PSD S:
  I = 4 Re integral_0^inf dS(f)^H dS(f) / S(f) df; a harmonic c_k exp(i k w t) over T carries |c_k|^2 T / 4 of
  that integral's |S(f)|^2 near f_k, so I_ij = T sum_k Re(conj(dc_k/dtheta_i) dc_k/dtheta_j) / S(f_k)
  (:func:`fisher_information`). Check: a sinusoid's amplitude in white noise of variance sigma^2 per sample at
  fs (S = 2 sigma^2 / fs, T = N / fs) gives I = N / (2 sigma^2), the known sigma_A = sqrt(2 sigma^2 / N)
  (tests/fit/test_information_bound.py). The mean deflection (k = 0) counts only where the fit reads it
  (fit.detrend none: no offset or drift column); with an unknown offset it carries nothing about d.
  The detector's noise is the record's white floor between the harmonics far above resonance
  (:func:`detector_noise_rms`), not the fit's block residual, which also holds the lever's thermal wander.
* **bound** = sqrt(diag(I^-1)); a read-out's bound is the linear propagation J I^-1 J^T of its derivatives with
  respect to theta (:func:`readout_bounds`).

Not included (each makes the bound smaller than the record's true one, never larger, except the thermal
approximation above): the drive frequency (measured, nearly orthogonal to the rest), higher eigenmodes (no bound is
computed when one is declared: :func:`bound_applies`), the harmonics' aliasing above the Nyquist frequency when a
period does not hold a whole number of samples (with a whole number, the sampled period's spectrum is used).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from afmid.fit.uncertainty import Z95
from afmid.io.cantilever import lever_damping, lever_mass
from afmid.physics.effects import BOLTZMANN, ForceLaw
from afmid.quantity_text import format_value
from afmid.simulate.integrator import Integrator, settle
from afmid.simulate.model import CompiledForceLaw, Oscillator, compile_force_law

log = logging.getLogger(__name__)

#: Integration steps per drive period of the steady states (RK4 with steps onto every contact instant: its error
#: ~ (w h)^4 ~ 1e-9 of the amplitude at 2000 steps, far below the central differences' ~1e-5).
STEPS_PER_PERIOD = 2000
#: Central-difference step relative to each parameter's scale (its value; the contact length a0 or the decay length
#: for a separation). Truncation error ~ (h / scale)^2 / 6 = 1.7e-5 of the derivative; the steady states are found
#: to ~1e-12 of the amplitude (:data:`ORBIT_TOLERANCE`), so rounding adds ~1e-12 / 1e-2 = 1e-10: negligible.
#: Halving it changes the bound by < 1e-3 (tests/fit/test_information_bound.py checks).
RELATIVE_STEP = 1e-2
#: Relative change per period at which the nominal orbit's settling hands over to shooting (its deviation from the
#: steady state is then ~ tolerance * Q / pi: well inside the shooting's basin).
SETTLE_TOLERANCE = 1e-5
#: The periodic orbit's (x, v) at the period boundary is accepted when a Newton step moves it by less than this
#: fraction of the amplitude.
ORBIT_TOLERANCE = 1e-12
#: Newton iterations of the shooting before giving up on a periodic orbit (a period-doubled or chaotic motion).
MAX_SHOOTING_ITERATIONS = 30
#: The most settling periods for the nominal orbit (in units of Q: the energy decays by exp(-2 pi) per Q periods).
MAX_SETTLE_Q = 12


@dataclass(frozen=True)
class NoiseModel:
    """What the record's noise is made of (SI): white detector noise per sample and the lever's thermal force."""

    detector_rms: float  # m, per recorded sample
    sample_rate: float  # Hz
    spring_constant: float  # N/m
    omega0: float  # rad/s
    quality_factor: float
    temperature: float | None  # K; None: no thermal force
    detector_response: Callable[[np.ndarray], np.ndarray] | None = None  # G(f), f in Hz; None: ideal detector


def deflection_noise_psd(noise: NoiseModel, frequency: np.ndarray) -> np.ndarray:
    """One-sided PSD of the recorded deflection's noise at ``frequency`` (Hz), m^2/Hz: detector white noise
    2 sigma^2 / fs, plus the thermal force 4 k_B T c through the free lever (and the detector's |G|^2)."""
    f = np.asarray(frequency, dtype=float)
    psd = np.full(f.shape, 2.0 * noise.detector_rms**2 / noise.sample_rate)
    if noise.temperature is not None:
        k, w0, q = noise.spring_constant, noise.omega0, noise.quality_factor
        mass, damping = lever_mass(k, w0), lever_damping(k, w0, q)
        w = 2.0 * math.pi * f
        lever = np.abs(1.0 / (k - mass * w**2 + 1j * damping * w)) ** 2
        gain = 1.0 if noise.detector_response is None else np.abs(noise.detector_response(f)) ** 2
        psd = psd + 4.0 * BOLTZMANN * noise.temperature * damping * lever * gain
    return psd


def fisher_information(derivatives: np.ndarray, psd: np.ndarray, duration: float) -> np.ndarray:
    """I_ij = T sum_k Re(conj(D_ik) D_jk) / S_k for a real record of ``duration`` T (s).

    ``derivatives`` D (n_params, K): d c_k / d theta_i of the complex harmonic amplitudes (x = Re sum c_k e^{ikwt});
    ``psd`` S (K,): the noise's one-sided PSD at the harmonics (m^2/Hz). See the module's docstring for the factor.
    """
    d = np.asarray(derivatives, dtype=complex)
    weighted = d / np.asarray(psd, dtype=float)[None, :]
    return duration * np.real(np.conj(d) @ weighted.T)


def bound_from_information(information: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(covariance I^-1, its diagonal's square root); scaled to unit diagonal first so that parameters of very
    different units invert accurately. A singular direction (no information) gives an infinite bound."""
    scale = np.sqrt(np.diag(information))
    if np.any(~np.isfinite(scale)) or np.any(scale <= 0):
        n = information.shape[0]
        return np.full((n, n), math.inf), np.full(n, math.inf)
    normalized = information / np.outer(scale, scale)
    covariance = np.linalg.pinv(normalized, rcond=1e-13, hermitian=True) / np.outer(scale, scale)
    return covariance, np.sqrt(np.maximum(np.diag(covariance), 0.0))


# --------------------------------------------------------------------------- the steady states
@dataclass
class Orbit:
    """A periodic orbit at the period boundary (drive phase 0): deflection x (m), velocity v (m/s), gate values."""

    x: float
    v: float
    gates: np.ndarray


class SteadyStateModel:
    """The fitted law's steady-state harmonics c_k (m) as a function of the parameters theta.

    ``law``: the force law (selected terms, SI coefficients, all parameters but d); ``oscillator``: the lever
    with the drive force amplitude; ``harmonics``: K. Each evaluation starts from the nominal orbit and finds the
    perturbed one by shooting (Newton on the period map of (x, v), its Jacobian the nominal's), so it costs a few
    periods whatever the quality factor.
    """

    def __init__(self, law: ForceLaw, oscillator: Oscillator, separation: float, harmonics: int,
                 samples_per_period: float | None = None):
        self.law = law
        # The record's samples on the integration grid when a period holds a whole number M of them: the harmonics
        # are then the sampled record's, aliasing included (a sharp contact at 50 samples per period has harmonics
        # above the Nyquist frequency that fold onto the ones below); else the fine grid's. "Whole" within 1e-3
        # sample: the measured drive frequency is off the nominal by ppm, a slip of < 0.1 sample over 100 periods.
        whole = samples_per_period is not None and abs(samples_per_period - round(samples_per_period)) < 1e-3
        self.samples = int(round(samples_per_period)) if whole else None
        self.steps = self.samples * math.ceil(STEPS_PER_PERIOD / self.samples) if whole else STEPS_PER_PERIOD
        self.oscillator = oscillator
        self.separation = separation
        self.harmonics = harmonics
        self.compiled = compile_force_law(law)
        self.simulated_periods = 0
        nominal = Integrator(oscillator, self.compiled, separation)
        x0, v0 = oscillator.free_state(0.0)
        nominal.start(x0, v0, 0.0)
        amplitude = oscillator.free_response()[0]
        self.scale = np.array([amplitude, amplitude * oscillator.omega])
        steady = settle(nominal, self.steps, SETTLE_TOLERANCE,
                        max(200, int(MAX_SETTLE_Q * oscillator.quality_factor)))
        self.simulated_periods += steady.periods
        start = Orbit(nominal.x, nominal.v, nominal.gates.copy())
        self.jacobian = self._period_jacobian(nominal, start)
        self.orbit = self._shoot(nominal, start)

    # one period from an orbit's state
    def _period(self, integrator: Integrator, state: Orbit, record: bool = False):
        integrator.start(state.x, state.v, 0.0, state.gates)
        h = self.oscillator.period / self.steps
        segment = integrator.run(0.0, h, self.steps, 1)
        self.simulated_periods += 1
        end = np.array([integrator.x, integrator.v])
        return (end, integrator.gates.copy(), segment) if record else (end, integrator.gates.copy())

    def _period_jacobian(self, integrator: Integrator, state: Orbit) -> np.ndarray:
        """d(period map)/d(x, v) by central differences of 1e-6 of the amplitude (the map is smooth at that scale
        between contact instants, which the kernel steps onto)."""
        columns = []
        for i in range(2):
            step = np.zeros(2)
            step[i] = 1e-6 * self.scale[i]
            ends = [self._period(integrator, Orbit(state.x + s * step[0], state.v + s * step[1], state.gates))[0]
                    for s in (1.0, -1.0)]
            columns.append((ends[0] - ends[1]) / (2.0 * step[i]))
        return np.array(columns).T

    def _shoot(self, integrator: Integrator, start: Orbit) -> Orbit:
        y = np.array([start.x, start.v])
        gates = start.gates
        newton = self.jacobian - np.eye(2)
        for _ in range(MAX_SHOOTING_ITERATIONS):
            end, end_gates = self._period(integrator, Orbit(y[0], y[1], gates))
            move = -np.linalg.solve(newton, end - y)
            y = y + move
            gates = end_gates
            if np.all(np.abs(move) <= ORBIT_TOLERANCE * self.scale):
                return Orbit(y[0], y[1], gates)
        raise ArithmeticError("no periodic orbit: the motion is not periodic at the drive period")

    def nominal_period(self):
        """One period of the nominal orbit on the integration grid: (t (s), x (m), v (m/s), gates), the last
        sample (the next period's first) left out."""
        integrator = Integrator(self.oscillator, self.compiled, self.separation)
        _, _, segment = self._period(integrator, self.orbit, record=True)
        t = np.arange(self.steps) * (self.oscillator.period / self.steps)
        return t, segment.x[:-1], segment.v[:-1], segment.gates[:-1]

    def harmonics_at(self, separation: float | None = None, coefficients: np.ndarray | None = None,
                     parameters: dict | None = None, drive_force: float | None = None) -> np.ndarray:
        """c_k, k = 1..K (complex, m) of the steady state with the given changes from the nominal."""
        compiled = self.compiled
        if parameters:
            compiled = compile_force_law(replace(self.law, parameters={**self.law.parameters, **parameters}))
        if coefficients is not None:
            compiled = CompiledForceLaw(compiled.law, compiled.terms, np.asarray(coefficients, float),
                                        compiled.switching, compiled.owners, compiled.conditions)
        oscillator = self.oscillator if drive_force is None else replace(self.oscillator, drive_force=drive_force)
        integrator = Integrator(oscillator, compiled, self.separation if separation is None else separation)
        orbit = self._shoot(integrator, self.orbit)
        _, _, segment = self._period(integrator, orbit, record=True)
        x = segment.x[:-1] if self.samples is None else segment.x[:-1:self.steps // self.samples]
        spectrum = np.fft.rfft(x) * (2.0 / x.size)
        spectrum[0] *= 0.5  # the mean deflection, m
        return spectrum[:self.harmonics + 1]


# --------------------------------------------------------------------------- the bound of a fit
@dataclass(frozen=True)
class Parameter:
    """One component of theta: its name, unit, value and central-difference step (SI)."""

    name: str
    unit: str
    value: float
    step: float


@dataclass
class InformationBound:
    """The Cramér-Rao bound of a fitted record (SI). ``sigma[i]`` bounds the 1-sigma of ``parameters[i]``;
    ``quantities`` bound the read-outs (name -> sigma in the read-out's unit)."""

    parameters: tuple[Parameter, ...]
    #: I^-1 of each noise taken alone: the detector's (white, the fit's noise estimate) and, with a thermal force,
    #: the thermal force's with a perfect detector. Each alone carries at least the information of the record with
    #: both, so each bound is a lower bound and ``sigma`` is the larger of them.
    covariances: tuple[np.ndarray, ...]
    sigma: np.ndarray
    harmonics: int
    duration: float  # s
    simulated_periods: int
    cpu_seconds: float
    quantities: dict[str, float] = field(default_factory=dict)

    def of(self, name: str) -> float:
        """The bound of parameter ``name`` (NaN when it is not part of theta)."""
        for p, s in zip(self.parameters, self.sigma):
            if p.name == name:
                return float(s)
        return math.nan


def sensitivities(model: SteadyStateModel, parameters: tuple[Parameter, ...], coefficient_names: list[str],
                  relative_step: float = 1.0) -> np.ndarray:
    """dc_k / dtheta (n_params, K) by central differences (steps scaled by ``relative_step``); the drive phase's
    analytically. ``coefficient_names`` are the parameters that are the law's term coefficients, in its order."""
    nominal = model.harmonics_at()
    k = np.arange(model.harmonics + 1)
    coefficients = model.compiled.coefficients
    rows = []
    for p in parameters:
        if p.name == "drive_phase":
            rows.append(-1j * k * nominal)
            continue
        h = p.step * relative_step
        sides = []
        for sign in (1.0, -1.0):
            value = p.value + sign * h
            if p.name == "d":
                sides.append(model.harmonics_at(separation=value))
            elif p.name == "drive_force":
                sides.append(model.harmonics_at(drive_force=value))
            elif p.name in coefficient_names:
                changed = coefficients.copy()
                changed[coefficient_names.index(p.name)] = value
                sides.append(model.harmonics_at(coefficients=changed))
            else:
                sides.append(model.harmonics_at(parameters={p.name: value}))
        rows.append((sides[0] - sides[1]) / (2.0 * h))
    return np.array(rows)


def force_sensitivities(model: SteadyStateModel, parameters: tuple[Parameter, ...],
                        coefficient_names: list[str]) -> tuple[np.ndarray, float]:
    """(dr/dtheta (n_params, n_steps) in N per unit of theta, the step dt (s)) of the equation's residual
    r = m x'' + c x' + k x + F_ts(x, v; theta) - F_drive(theta) along the nominal orbit held fixed: with a perfect
    detector the record gives x exactly and r is the thermal force itself (white). Its derivative is the force
    law's at fixed motion: a term's value for its coefficient, central differences in d and a decay length, and
    -cos(w t), -F0 sin(w t) for the drive's amplitude and phase."""
    from afmid.simulate.model import force_numpy

    t, x, v, gates = model.nominal_period()
    w = model.oscillator.omega
    coefficients = model.compiled.coefficients
    rows = []
    for p in parameters:
        if p.name == "drive_force":
            rows.append(-np.cos(w * t))
        elif p.name == "drive_phase":
            rows.append(-model.oscillator.drive_force * np.sin(w * t))
        elif p.name in coefficient_names:
            unit = np.zeros_like(coefficients)
            unit[coefficient_names.index(p.name)] = 1.0
            compiled = CompiledForceLaw(model.compiled.law, model.compiled.terms, unit, model.compiled.switching,
                                        model.compiled.owners, model.compiled.conditions)
            rows.append(force_numpy(compiled, x, v, t, model.separation, gates))
        elif p.name == "d":
            sides = [force_numpy(model.compiled, x, v, t, p.value + sign * p.step, gates) for sign in (1.0, -1.0)]
            rows.append((sides[0] - sides[1]) / (2.0 * p.step))
        else:
            sides = [force_numpy(compile_force_law(replace(model.law, parameters={**model.law.parameters,
                                                                                  p.name: p.value + sign * p.step})),
                                 x, v, t, model.separation, gates) for sign in (1.0, -1.0)]
            rows.append((sides[0] - sides[1]) / (2.0 * p.step))
    return np.array(rows), model.oscillator.period / model.steps


def compute_bound(law: ForceLaw, oscillator: Oscillator, separation: float, parameters: tuple[Parameter, ...],
                  coefficient_names: list[str], noise: NoiseModel, periods: float,
                  relative_step: float = 1.0, mean_known: bool = True) -> InformationBound:
    """The bound of ``parameters`` for a record of ``periods`` drive periods with ``noise``.

    ``law`` holds the coefficients in the order of ``coefficient_names`` (the parameters that are coefficients).
    Harmonics below the record's Nyquist frequency are used: K = ceil(fs / (2 f)) - 1; the mean deflection too when
    ``mean_known`` (the record's zero is the lever's rest: fit.detrend none, where the fit uses it): a real
    amplitude, twice the weight of a harmonic's part (its variance per record is sigma^2 / N, not 2 sigma^2 / N).
    """
    started = time.process_time()
    f = oscillator.drive_frequency
    harmonics = max(1, math.ceil(noise.sample_rate / (2.0 * f)) - 1)
    harmonics = min(harmonics, STEPS_PER_PERIOD // 4)
    model = SteadyStateModel(law, oscillator, separation, harmonics, noise.sample_rate / f)
    derivatives = sensitivities(model, parameters, coefficient_names, relative_step)
    frequencies = f * np.arange(harmonics + 1)
    if noise.detector_response is not None:  # the record is the detector's output: G(f_k) c_k
        derivatives = derivatives * noise.detector_response(frequencies)[None, :]
    duration = periods / f
    detector_only = replace(noise, temperature=None)
    psd = deflection_noise_psd(detector_only, frequencies)
    psd[0] = psd[0] / 2.0 if mean_known else math.inf
    information = fisher_information(derivatives, psd, duration)
    covariances = [bound_from_information(information)[0]]
    if noise.temperature is not None:
        residual, dt = force_sensitivities(model, parameters, coefficient_names)
        damping = lever_damping(noise.spring_constant, noise.omega0, noise.quality_factor)
        # white force of two-sided PSD 2 k_B T c: I = integral of dr_i dr_j dt / (2 k_B T c), periods x one period
        thermal = periods * (residual @ residual.T) * dt / (2.0 * BOLTZMANN * noise.temperature * damping)
        covariances.append(bound_from_information(thermal)[0])
    sigma = np.max([np.sqrt(np.maximum(np.diag(c), 0.0)) for c in covariances], axis=0)
    return InformationBound(parameters, tuple(covariances), sigma, harmonics, duration, model.simulated_periods,
                            time.process_time() - started)


def readout_bounds(bound: InformationBound, read_out: Callable[[dict], dict[str, float]]) -> dict[str, float]:
    """Each read-out's bound: J C J^T with J its derivatives with respect to theta (central differences of
    ``read_out``, which maps {parameter name: value} to {quantity: value}; 1e-6 relative steps: the read-outs are
    algebraic in the coefficients)."""
    values = {p.name: p.value for p in bound.parameters}
    central = read_out(values)
    jacobian: dict[str, np.ndarray] = {name: np.zeros(len(bound.parameters)) for name in central}
    for i, p in enumerate(bound.parameters):
        h = 1e-6 * (abs(p.value) if p.value != 0 else p.step)
        if h == 0:  # the drive phase: no read-out depends on it
            continue
        up = read_out({**values, p.name: p.value + h})
        down = read_out({**values, p.name: p.value - h})
        for name in central:
            jacobian[name][i] = (up.get(name, math.nan) - down.get(name, math.nan)) / (2.0 * h)
    out = {}
    for name, j in jacobian.items():
        if not np.all(np.isfinite(j)) or not math.isfinite(central[name]) or not np.any(j):
            continue
        used = j != 0  # a read-out that does not depend on a parameter with no information keeps its bound finite
        out[name] = max(float(math.sqrt(max(float(j[used] @ c[np.ix_(used, used)] @ j[used]), 0.0)))
                        for c in bound.covariances)
    return out


def raise_to_bound(name: str, unit: str, sigma: float, bound: float) -> tuple[float, str | None]:
    """(the sigma to report, the warning when it was raised): a 1-sigma below the information bound is below what
    any unbiased estimator reaches on this record, so it is raised to the bound."""
    if not (math.isfinite(bound) and bound > 0) or (math.isfinite(sigma) and sigma >= bound):
        return sigma, None
    own = format_value(sigma, unit) if math.isfinite(sigma) else "none"
    return bound, (f"{name}'s sigma raised to the information bound ({format_value(bound, unit)}; the fit's own "
                   f"{own}): no unbiased estimate is more precise on this record")


# --------------------------------------------------------------------------- the fit's record
#: The detector's white noise is read from the record's spectrum above this multiple of the higher of the drive
#: and resonance frequencies, where the lever's thermal motion is < 1/(3^2 - 1)^2 = 1.6 % of its static response's
#: PSD and the tapping signal only has its harmonics (left out).
QUIET_ABOVE = 3.0


def detector_noise_rms(deflection: np.ndarray, sample_rate: float, drive_frequency: float,
                       resonance_frequency: float) -> float:
    """The detector's white noise (m per sample) from the record's periodogram between the drive harmonics above
    :data:`QUIET_ABOVE` x max(f, f0): the median bin over ln 2 (a white noise's periodogram bins are exponential,
    their median ln 2 of the mean). NaN when there are fewer than 20 such bins. The fit's own noise estimate (its
    per-period block residual) also holds the lever's thermal wander near resonance, which the bound must not count
    as detector noise."""
    x = np.asarray(deflection, dtype=float)
    x = x - x.mean()
    n = x.size
    power = np.abs(np.fft.rfft(x)) ** 2 / n  # mean sigma^2 for white noise of variance sigma^2
    frequency = np.fft.rfftfreq(n, 1.0 / sample_rate)
    resolution = sample_rate / n
    nearest = np.abs(frequency / drive_frequency - np.round(frequency / drive_frequency)) * drive_frequency
    quiet = ((frequency > QUIET_ABOVE * max(drive_frequency, resonance_frequency))
             & (frequency < 0.5 * sample_rate - resolution) & (nearest > 2.5 * resolution))
    if np.count_nonzero(quiet) < 20:
        return math.nan
    return float(math.sqrt(np.median(power[quiet]) / math.log(2.0)))


#: Why no bound is computed for a fit (the reason, or None when it applies).
def bound_applies(prep, config, instrument, drive_search) -> str | None:
    """None when the bound can be computed for this fit, else why not: a record that is not in steady state (a
    transient, non-periodic motion), a lever identified by the fit, or a declared higher mode (not modelled here)."""
    if drive_search is not None:
        return "the record is not in steady state (its drive frequency was searched)"
    if prep.motion is not None and prep.motion.non_periodic:
        return "the motion is not periodic"
    if config.fit.cantilever == "free":
        return "the lever is identified by the fit (fit.cantilever: free)"
    if instrument is not None and instrument.higher_modes:
        return "a higher eigenmode is declared (the bound models the first mode only)"
    if config.fit.separation_track is not None:
        return "the separation is tracked per block"
    return None


def fit_bound(prep, library, config, system, coef: np.ndarray, chosen: np.ndarray, params: dict,
              nonlinear: dict, instrument, read_out: Callable[[dict, dict], dict]) -> InformationBound:
    """The information bound of a fit: theta = the estimated nonlinear parameters (d, decay lengths), the selected
    terms' coefficients and (a fitted drive) the drive force's amplitude and phase, at the fitted values.

    ``read_out(coef, params)`` gives {read-out name: value} for changed coefficients (all columns) and parameters.
    Raises ArithmeticError when the fitted law has no periodic orbit, afmid.errors.AfmidError when it diverges.
    """
    trace = prep.trace
    n = len(library)
    selected = [j for j in range(n) if chosen[j]]
    law_parameters = {k: float(v) for k, v in params.items() if k != "d" and np.isscalar(v)}
    terms = tuple((library.terms[j].effect or "fit", library.names[j], library.terms[j].expression, float(coef[j]))
                  for j in selected)
    states = tuple(s for s in library.states if any(s.name in t[2] for t in terms))
    law = ForceLaw(tuple(library.effects), law_parameters, terms, states)
    contact_length = float(params.get("a0", 0.0)) or 1e-10
    theta = [Parameter(name, est.unit, float(params[name]),
                       RELATIVE_STEP * (contact_length if name == "d" else abs(float(params[name]))))
             for name, est in nonlinear.items() if est.estimated and float(params.get(name, 0.0)) != 0.0]
    coefficient_names = [library.names[j] for j in selected]
    theta += [Parameter(library.names[j], library.terms[j].coefficient_unit, float(coef[j]),
                        RELATIVE_STEP * abs(float(coef[j]))) for j in selected]
    names = list(system.names)
    if prep.declared_drive is None:
        drive_force = math.hypot(coef[names.index("drive_cos")], coef[names.index("drive_sin")])
        theta += [Parameter("drive_force", "N", drive_force, RELATIVE_STEP * drive_force),
                  Parameter("drive_phase", "rad", 0.0, 0.0)]
    else:
        drive_force = math.hypot(prep.declared_drive.cos, prep.declared_drive.sin)
    lever = trace.cantilever
    oscillator = Oscillator(lever.spring_constant, lever.resonance_frequency, lever.quality_factor,
                            prep.drive.frequency, drive_force)
    detector = instrument.detector if instrument is not None else None
    quiet_rms = detector_noise_rms(prep.x, trace.sample_rate, prep.drive.frequency, lever.resonance_frequency)
    detector_rms = min(prep.noise_rms, quiet_rms) if math.isfinite(quiet_rms) else prep.noise_rms
    noise = NoiseModel(detector_rms, trace.sample_rate, lever.spring_constant,
                       2.0 * math.pi * lever.resonance_frequency, lever.quality_factor,
                       config.fit.temperature if config.fit.thermal_noise else None,
                       detector.response if detector is not None else None)
    mean_known = not {"offset", "drift"} & set(names)  # no offset column: the fit reads d from the mean too
    bound = compute_bound(law, oscillator, float(params["d"]), tuple(theta), coefficient_names, noise,
                          prep.blocks.n_blocks, mean_known=mean_known)

    def quantities_at(values: dict) -> dict:
        changed = np.array(coef, dtype=float)
        for j in selected:
            changed[j] = values[library.names[j]]
        trial = dict(params, **{p.name: values[p.name] for p in bound.parameters
                                if p.name in params and p.name not in coefficient_names})
        return read_out(changed, trial)

    bound.quantities = readout_bounds(bound, quantities_at)
    return bound


def apply_bound(bound: InformationBound, quantities: dict, nonlinear: dict, warnings: list[str]) -> None:
    """Store the bound beside each sigma and raise a sigma below it to it (in place): a nonlinear estimate's
    ``sigma`` (``information_bound`` set on it), a read-out's statistical error (``error_statistical``, then
    ``error`` = it and the calibration share in quadrature; ``information_bound`` in its dict) with its 95 %
    interval widened to at least value +- 1.96 x the new error. One warning per raised number."""
    for name, est in nonlinear.items():
        b = bound.of(name)
        est.information_bound = b
        sigma, warning = raise_to_bound(name, est.unit, est.sigma, b)
        if warning:
            est.sigma = sigma
            warnings.append("warning: " + warning)
    for name, q in quantities.items():
        b = bound.quantities.get(name, math.nan)
        q["information_bound"] = b
        if not q.get("determined", True) or not math.isfinite(q.get("value", math.nan)):
            continue
        # The bound is on the data's share: a declared calibration share adds to it in quadrature.
        statistical = "error_statistical" in q
        sigma, warning = raise_to_bound(name, q["unit"], q["error_statistical" if statistical else "error"], b)
        if warning:
            if statistical:
                q["error_statistical"] = sigma
                sigma = math.hypot(sigma, q.get("error_calibration", 0.0))
            q["error"] = sigma
            half = Z95 * sigma
            q["ci_low"] = min(q["ci_low"], q["value"] - half) if math.isfinite(q["ci_low"]) else q["value"] - half
            q["ci_high"] = max(q["ci_high"], q["value"] + half) if math.isfinite(q["ci_high"]) else q["value"] + half
            warnings.append("warning: " + warning)


def floor_at_bound(prep, library, config, system, coef, chosen, params: dict, nonlinear: dict, quantities: dict,
                   warnings: list[str], drive_search,
                   read_out: Callable[[dict, dict], dict]) -> InformationBound | None:
    """The fit's bound (:func:`fit_bound`) applied to its sigmas (:func:`apply_bound`); None (and the sigmas
    unchanged) where it does not apply (:func:`bound_applies`) or the fitted law has no steady state to linearize."""
    from afmid.errors import AfmidError
    from afmid.preprocess.instrument import from_config as instrument_from_config

    instrument = instrument_from_config(config)
    why_not = bound_applies(prep, config, instrument, drive_search)
    if why_not is not None:
        log.info("no information bound: %s", why_not)
        return None
    try:
        bound = fit_bound(prep, library, config, system, coef, chosen, params, nonlinear, instrument, read_out)
    except (ArithmeticError, AfmidError, np.linalg.LinAlgError) as exc:
        log.info("no information bound: the fitted law's steady state: %s", exc)
        return None
    log.debug("information bound: %s (%d harmonics, %d simulated periods, %.2f s CPU)",
              ", ".join(f"{p.name} {s:.3g} {p.unit}" for p, s in zip(bound.parameters, bound.sigma)),
              bound.harmonics, bound.simulated_periods, bound.cpu_seconds)
    apply_bound(bound, quantities, nonlinear, warnings)
    return bound
