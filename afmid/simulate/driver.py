"""Simulate tapping-mode deflection traces with their ground truth.

The first flexural mode is a driven, damped point mass (SI units, deflection x
positive toward the sample, tip-sample force F_ts on the tip, repulsive
positive)::

    m x'' + (m w0 / Q) x' + k x = -F_ts(z, zdot, states) + F0 cos(w t) + F_th(t),   m = k / w0^2

with the separation z = d - x (d: rest separation) and F_ts the sum of the
force law's terms (:func:`afmid.physics.effects.build_force_law`). The paper's
nondimensional form is :class:`NondimensionalForm`.

Integration is fixed-step RK4 in a numba kernel (:mod:`afmid.kernels.integrate`)
that steps exactly onto every non-smooth instant (contact, gate flips). By
default the kernel is generated from the force law's compiled programs
(:mod:`afmid.kernels.lawgen`: straight-line code instead of the VM, ~10x faster,
compiled once per force-law structure and cached on disk); the generic kernel
interprets the same programs (``Integrator(kernel="vm")``, or
``AFMID_SIMULATE_KERNEL=vm``) and gives the same numbers. Output samples fall
on step boundaries. Noise: a thermal force (fluctuation-dissipation
consistent with k_B T), white detector noise and ADC rounding, drawn from
``numpy.random.Generator(PCG64(seed))`` in a fixed order, so a seed gives a
bit-identical trace.

numba is imported inside :func:`simulate` (and the helpers that run the kernel),
so importing this module stays cheap.

Layout: this module is the driver (output grid, memory check, thermal and
detector noise, setpoint search, recording, :func:`simulate`,
:func:`resimulate_run`) and the public facade of the simulation; it re-exports
the names of

- :mod:`afmid.simulate.model` -- :class:`Oscillator`, :class:`NondimensionalForm`,
  :func:`resolve_setup` (config to checked :class:`Setup`), :func:`compile_force_law`;
- :mod:`afmid.simulate.integrator` -- :class:`Integrator` (runs the kernel),
  :func:`first_harmonic`, :func:`settle`.

The plain-Python twin of the kernel the tests compare against is test code
(tests/support/reference_integrator.py), not part of the package.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass

import numpy as np

from afmid.config import RunConfig
from afmid.errors import ConfigError
from afmid.io.files import memory_shortfall
from afmid.io.trace import Cantilever, Trace, Truth
from afmid.preprocess.instrument import from_config as instrument_from_config
from afmid.progress import Progress
from afmid.physics.effects import BOLTZMANN
from afmid.simulate.instrument import detect, detector_lead_periods, integrator_for
from afmid.simulate.integrator import (
    ORBIT_WINDOW_PERIODS,
    Integrator,
    Segment,
    settle,
)
from afmid.simulate.model import (
    CompiledForceLaw,
    Oscillator,
    Setup,
    compile_force_law,
    parameter_units,
    resolve_setup,
)

log = logging.getLogger(__name__)

#: Output samples per kernel call while recording (thermal forces are drawn per call).
RECORD_CHUNK_SAMPLES = 8192
#: Periods per kernel call in the thermal warm-up (bounds the thermal-force array).
WARMUP_CHUNK_PERIODS = 64
#: Thermal warm-up length in units of Q / w0 (the decay time of the oscillator's
#: energy): the thermal variance then lacks a fraction exp(-7) < 1e-3 of its value.
THERMAL_WARMUP_ENERGY_TIMES = 7.0
#: Integration steps per period for the steady simulations of the setpoint search.
SEARCH_STEPS_PER_PERIOD = 500
#: Settle tolerance of the setpoint search (looser than the final run's is enough
#: to place the separation; the final run settles to simulate.settle_tolerance).
SEARCH_SETTLE_TOLERANCE = 1e-6


# =========================================================================== the driver
@dataclass(frozen=True)
class Grid:
    """Output sampling and integration step."""

    sample_rate: float  # fs, Hz
    steps_per_sample: int  # n_sub
    n_samples: int

    @property
    def step(self) -> float:
        """Integration step h = 1 / (fs n_sub), s."""
        return 1.0 / (self.sample_rate * self.steps_per_sample)


def output_grid(config: RunConfig, oscillator: Oscillator) -> Grid:
    """fs = data.sample_rate or samples_per_period * f; n_sub = ceil(steps_per_period / (fs / f))."""
    sim = config.simulate
    if config.data.sample_rate is not None:
        fs = float(config.data.sample_rate)
    elif sim.samples_per_period is not None:
        fs = sim.samples_per_period * oscillator.drive_frequency
    else:
        raise ConfigError("required key is missing (output sampling: samples per drive period)",
                          file=config.source, key="simulate.samples_per_period")
    samples_per_period = fs / oscillator.drive_frequency
    if samples_per_period < 2.0:
        raise ConfigError(f"the sample rate {fs:g} Hz gives {samples_per_period:.3g} samples per drive period; "
                          "need at least 2", file=config.source, key="data.sample_rate")
    n_sub = max(1, math.ceil(sim.steps_per_period / samples_per_period - 1e-9))
    n_samples = round(sim.periods * samples_per_period)
    return Grid(fs, n_sub, n_samples)


def check_memory(config: RunConfig, grid: Grid, oscillator: Oscillator, n_gates: int) -> None:
    """Refuse, before integrating, a simulation whose arrays would not fit in the available memory.

    Per output sample: x, v, force and the gates recorded, then the deflection,
    its noise and the separation (8 bytes each); with thermal noise also one
    chunk of random forces per integration step (warm-up or recording).
    """
    sim = config.simulate
    needed = 8.0 * grid.n_samples * (6 + n_gates)
    if sim.noise.thermal:
        needed += 8.0 * max(WARMUP_CHUNK_PERIODS * sim.steps_per_period, RECORD_CHUNK_SAMPLES * grid.steps_per_sample)
    problem = memory_shortfall(needed)
    if problem is None:
        return
    per_period = grid.sample_rate / oscillator.drive_frequency
    sampling_key = "data.sample_rate" if config.data.sample_rate is not None else "simulate.samples_per_period"
    usual = {name: field.default for name, field in type(sim).model_fields.items()}
    steps_factor = sim.steps_per_period / usual["steps_per_period"] if sim.noise.thermal else 0.0
    factors = {"simulate.periods": sim.periods / usual["periods"],
               sampling_key: per_period / usual["samples_per_period"],
               "simulate.steps_per_period": steps_factor}
    key = max(factors, key=factors.get)  # the value furthest above its usual size
    raise ConfigError(f"{sim.periods} periods x {per_period:.4g} samples = {grid.n_samples:.3g} samples "
                      f"({sim.steps_per_period} steps per period) {problem}", file=config.source, key=key)


def thermal_force_std(oscillator: Oscillator, temperature: float, h: float) -> float:
    """Std (N) of the thermal force held constant over each step of h (s).

    Fluctuation-dissipation: a white force of two-sided spectral density
    2 k_B T c (c = m w0 / Q) gives the oscillator the equipartition variance
    <x^2> = k_B T / k. A force constant over each step, independent between
    steps, with variance s^2 has spectral density s^2 h below ~1/h, hence
    s = sqrt(2 k_B T c / h). (Its spectrum rolls off as sinc^2(w h / 2) ~
    1 - (w h)^2 / 12: 3e-4 low at w0 for 100 steps per period, 1e-6 for 2000.)
    """
    return math.sqrt(2.0 * BOLTZMANN * temperature * oscillator.damping / h)


class _Progress:
    """The simulation's stages on an :class:`afmid.progress.Progress`, counting drive periods; callable with a
    number of periods (the integrator's settle loop reports so)."""

    def __init__(self, enabled: bool):
        self.progress = Progress("simulate", enabled=enabled)

    def stage(self, name: str, total: int | None = None) -> None:
        self.progress.stage(name, total=total, unit="periods")

    def __call__(self, periods: int) -> None:
        self.progress.advance(periods)

    def close(self) -> None:
        self.progress.close()


def _search_separation(setup: Setup, compiled: CompiledForceLaw, config: RunConfig, progress: _Progress,
                       make_integrator=Integrator):
    """Rest separation d (m) whose steady amplitude is simulate.setpoint * A0.

    Brent's method on A(d)/A0 - setpoint over steady simulations on a coarser
    grid (SEARCH_STEPS_PER_PERIOD), each warm-started from the previous steady
    state. Returns (d, integrator left in that steady state, evaluations).
    """
    from scipy.optimize import brentq

    sim = config.simulate
    A0 = setup.free_amplitude
    target = sim.setpoint
    tolerance = max(sim.settle_tolerance, SEARCH_SETTLE_TOLERANCE)
    steps = max(SEARCH_STEPS_PER_PERIOD, sim.steps_per_period // 4)
    warm: list = []  # the last steady state, to start the next evaluation from
    evaluations = 0

    def integrator_at(d: float) -> Integrator:
        integrator = make_integrator(setup.oscillator, compiled, d)
        if warm:
            integrator.start(*warm[0])
        else:
            integrator.start(*setup.oscillator.free_state(0.0))
        return integrator

    def mismatch(d: float) -> float:
        nonlocal evaluations
        integrator = integrator_at(d)
        state = settle(integrator, steps, tolerance, sim.max_settle_periods, progress)
        warm[:] = [(integrator.x, integrator.v, 0.0, integrator.gates.copy())]
        evaluations += 1
        log.debug("setpoint search: d = %.6g m gives A/A0 = %.6f", d, state.amplitude / A0)
        return state.amplitude / A0 - target

    def unreachable(detail: str) -> ConfigError:
        return ConfigError(f"setpoint {target} is not reachable: {detail}", file=config.source, key="simulate.setpoint")

    d_hi = A0
    f_hi = mismatch(d_hi)
    for _ in range(6):
        if f_hi > 0:
            break
        d_hi *= 1.5
        f_hi = mismatch(d_hi)
    else:
        raise unreachable(f"the amplitude stays below {target} A0 even at d = {d_hi:.3g} m")
    d_lo = target * A0
    f_lo = mismatch(d_lo)
    while f_lo > 0:
        d_lo -= 0.25 * A0
        if d_lo <= setup.a0:
            raise unreachable("the amplitude stays above it down to contact at rest (d = a0)")
        f_lo = mismatch(d_lo)
    d = brentq(mismatch, d_lo, d_hi, xtol=1e-6 * A0, rtol=1e-12)
    return d, integrator_at(d), evaluations


def simulate(config: RunConfig, progress: bool = False) -> Trace:
    """Simulate the trace described by ``config`` (its ``simulate:`` section); returns it with truth.

    Steady mode: start from the free linear steady state at the rest separation,
    settle (see :func:`settle`), let the thermal noise reach its stationary
    level, then record ``simulate.periods`` periods. Transient mode: record from
    t = 0, starting at rest or in the free steady state placed at separation d
    (the thermal force also starts at t = 0). With ``simulate.setpoint`` the
    separation is searched first (:func:`_search_separation`). The drive is
    F0 cos(2 pi f t) with t = 0 at the first output sample.
    """
    setup = resolve_setup(config)
    sim, noise = config.simulate, config.simulate.noise
    osc = setup.oscillator
    grid = output_grid(config, osc)
    compiled = compile_force_law(setup.force_law)
    check_memory(config, grid, osc, compiled.n_gates)
    rng = np.random.Generator(np.random.PCG64(sim.seed))
    bar = _Progress(progress)
    extra: dict = {}
    declared = instrument_from_config(config)
    make_integrator = functools.partial(integrator_for, declared)
    try:
        if sim.setpoint is not None:
            bar.stage("setpoint search")
            d, integrator, evaluations = _search_separation(setup, compiled, config, bar, make_integrator)
            extra.update(setpoint_target=float(sim.setpoint), setpoint_search_evaluations=evaluations)
        else:
            d = setup.separation
            integrator = make_integrator(osc, compiled, d)
            integrator.start(*osc.free_state(0.0))
        if sim.mode == "transient" and sim.transient_start == "rest":
            integrator.start(0.0, 0.0)
        elif sim.mode == "transient":
            integrator.start(*osc.free_state(0.0))

        if sim.mode == "steady":
            bar.stage(f"settling (at most {sim.max_settle_periods} periods)")
            state = settle(integrator, sim.steps_per_period, sim.settle_tolerance, sim.max_settle_periods, bar,
                           require_settled=sim.unsettled == "fail")
            extra.update(steady_amplitude=state.amplitude, steady_phase=state.phase, settle_periods=state.periods,
                         setpoint=state.amplitude / setup.free_amplitude, settled=state.settled)
            if not state.settled:
                # An instrument records whatever the lever does once the start has died away: a period-n or
                # aperiodic orbit (a capillary neck that forms on some taps only) is recorded as it is.
                extra.update(unsettled_amplitude_low=state.amplitude_low, unsettled_amplitude_high=state.amplitude_high,
                             orbit_periods=state.orbit_periods,
                             start_decay=math.exp(-math.pi * state.periods / osc.quality_factor))
                log.warning("the oscillation did not settle within %d periods (%s); recorded as it is "
                            "(simulate.unsettled: record)", state.periods, unsettled_orbit_text(extra))
            if sim.setpoint is not None and abs(state.amplitude / setup.free_amplitude - sim.setpoint) > 1e-3:
                log.warning("setpoint search reached A/A0 = %.4f instead of %.4f (the amplitude jumps near "
                            "this separation: bistable attractive/repulsive regimes)",
                            state.amplitude / setup.free_amplitude, sim.setpoint)
            if noise.thermal:
                warmup = math.ceil(THERMAL_WARMUP_ENERGY_TIMES * osc.quality_factor / (2.0 * math.pi))
                bar.stage("thermal warm-up", total=warmup)
                h = osc.period / sim.steps_per_period
                sigma = thermal_force_std(osc, noise.temperature, h)
                done = 0
                while done < warmup:  # whole periods per kernel call, t = 0 at each call's start
                    chunk = min(WARMUP_CHUNK_PERIODS, warmup - done)
                    n_steps = chunk * sim.steps_per_period
                    integrator.run(0.0, h, n_steps, n_steps, rng.standard_normal(n_steps) * sigma)
                    done += chunk
                    bar(chunk)
                extra["thermal_warmup_periods"] = warmup
        else:
            extra["transient_start"] = sim.transient_start

        bar.stage("recording", total=round(grid.n_samples * osc.drive_frequency / grid.sample_rate))
        scanned = None
        if sim.scan is not None:
            scanned = _record_scanning(integrator, grid, setup, config, d, extra, rng, bar, declared)
            record = scanned.segment
            deflection = record.x.copy()
        elif declared.detector is None:
            record = _record(integrator, grid, osc, noise, rng, bar)
            deflection = record.x.copy()
        else:
            record, deflection = _record_detected(integrator, grid, osc, noise, rng, bar, declared.detector,
                                                  sim.mode == "steady", config.source)
    finally:
        bar.close()

    detector_rms = noise.detector_rms if noise.detector_density is None else noise.detector_density * math.sqrt(
        grid.sample_rate / 2.0)
    if detector_rms > 0:
        deflection += rng.standard_normal(deflection.size) * detector_rms
    if noise.adc_step > 0:
        deflection = np.round(deflection / noise.adc_step) * noise.adc_step

    law = setup.force_law
    extra.update(
        drive_force_amplitude=osc.drive_force,
        separation=d,
        drive_frequency=osc.drive_frequency,
        free_amplitude=setup.free_amplitude,
        mode=sim.mode,
        drive_convention="F_drive = F0 cos(2 pi f t), t = 0 at the first sample",
        integration_step=grid.step,
        steps_per_sample=grid.steps_per_sample,
        events=record.events,
        thermal_noise=bool(noise.thermal),
        temperature=noise.temperature,
        detector_rms=detector_rms,
        adc_step=noise.adc_step,
        seed=sim.seed,
        units=("drive_force_amplitude: N; separation: m; drive_frequency: Hz; free_amplitude: m; "
               "steady_amplitude: m; steady_phase: rad (lag behind the drive); unsettled_amplitude_low, "
               "unsettled_amplitude_high: m; orbit_periods: drive periods; start_decay: 1; integration_step: s; "
               "temperature: K; detector_rms: m; adc_step: m"),
    )
    if not declared.ideal:
        extra["instrument"] = declared.describe()
    tracks = {}
    if scanned is not None:
        d = scanned.rest_separation
        extra.update(separation=float(np.mean(d)), scan_setpoint_amplitude=scanned.setpoint_amplitude)
        tracks = {"rest_separation": (d, "m"), "surface_height": (scanned.surface, "m"),
                  "piezo": (scanned.piezo, "m"), "lateral_position": (scanned.lateral, "m"),
                  "feedback_amplitude": (scanned.amplitude, "m")}
    truth = Truth(
        tracks=tracks,
        force=record.force,
        separation=d - record.x,
        velocity=record.v,
        model=setup.model,
        effects=list(law.effects),
        parameters={k: float(v) for k, v in law.parameters.items()},
        units=parameter_units(law),
        extra=extra,
    )
    # The config's lever (tip shape, declared uncertainties, higher modes) with the simulated calibration.
    cantilever = Cantilever.from_config(config.cantilever, spring_constant=osc.spring_constant, tip_radius=setup.tip_radius,
                                        resonance_frequency=osc.resonance_frequency, quality_factor=osc.quality_factor)
    return Trace(deflection=deflection, sample_rate=grid.sample_rate, cantilever=cantilever,
                 drive_frequency=osc.drive_frequency, truth=truth, drive_force_amplitude=osc.drive_force)


#: The share of the start's transient (exp(-pi N / Q) after N periods) above which an unsettled orbit is not
#: described by its repeat: the start, not the orbit, would be what the first harmonic shows.
START_LEFT_TO_CLASSIFY = 0.01


def unsettled_orbit_text(extra: dict) -> str:
    """A steady simulation's unsettled orbit in words (``extra``: its truth's extra mapping with the keys
    :func:`simulate` writes when simulate.unsettled is record), for logs and coverage rows; nm in text."""
    period = int(extra.get("orbit_periods", 0))
    window = min(ORBIT_WINDOW_PERIODS, int(extra["settle_periods"]))  # the periods the orbit was looked at over
    low, high = extra["unsettled_amplitude_low"], extra["unsettled_amplitude_high"]
    if extra["start_decay"] > START_LEFT_TO_CLASSIFY:
        shape = "the start still decaying (too few periods to tell the orbit)"
    elif period > 1:
        shape = f"a period-{period} orbit"
    elif period == 1:  # steady over the few periods run, too few to count as settled
        shape = "one period repeating, over too few periods to call it settled"
    else:
        shape = f"no repeat within {window // 2} periods (a slow beat, quasi-periodic or chaotic)"
    return (f"{shape}, first-harmonic amplitude {low * 1e9:.4f}-{high * 1e9:.4f} nm over the last "
            f"{window} periods; {extra['start_decay']:.1e} of the start left")


def _record_scanning(integrator, grid: Grid, setup: Setup, config: RunConfig, d: float, extra: dict, rng,
                     bar: _Progress, declared):
    """:func:`afmid.simulate.scan.record_scanning` from the settled state at separation d (m); the feedback holds
    scan.feedback.setpoint, else simulate.setpoint, else the settled amplitude (times A0)."""
    from afmid.simulate.scan import record_scanning

    sim = config.simulate
    if sim.mode != "steady" or declared.detector is not None:
        raise ConfigError("a scanning record starts from the settled oscillation with an ideal detector: use "
                          "simulate.mode: steady and no data.detector", file=config.source, key="simulate.scan")
    A0 = setup.free_amplitude
    start_amplitude = float(extra["steady_amplitude"])
    feedback = sim.scan.feedback
    if feedback is not None and feedback.setpoint is not None:
        setpoint = feedback.setpoint * A0
    elif sim.setpoint is not None:
        setpoint = sim.setpoint * A0
    else:
        setpoint = start_amplitude
    osc = setup.oscillator
    sigma = thermal_force_std(osc, sim.noise.temperature, grid.step) if sim.noise.thermal else 0.0
    return record_scanning(integrator, grid, osc, sim.scan, d, start_amplitude, setpoint, sigma, rng, bar, sim.seed)


def _record_detected(integrator, grid: Grid, osc: Oscillator, noise, rng, bar: _Progress, detector, steady: bool,
                     source=None):
    """Record the tip on the integration grid, pass it through the detector (:func:`sim_instrument.detect`) and
    keep the output samples; the truth (force, velocity, tip) at the output samples. In steady mode whole drive
    periods run through the filter first (its start-up transient gone); a transient record starts the filter
    at rest with the motion. Returns (record at the output samples, detected deflection)."""
    n_sub = grid.steps_per_sample
    if detector.bandwidth >= 0.25 * grid.sample_rate * n_sub:
        raise ConfigError(f"the detector bandwidth {detector.bandwidth:g} Hz is not below a quarter of the "
                          f"integration rate {grid.sample_rate * n_sub:g} Hz, where the simulator filters; raise "
                          "simulate.steps_per_period or leave the detector out (it is then ideal)",
                          file=source, key="data.detector.bandwidth")
    fine_per_period = grid.sample_rate * n_sub / osc.drive_frequency
    lead_samples = 0
    if steady and abs(fine_per_period - round(fine_per_period)) < 1e-9 * fine_per_period:
        # Whole periods from the settled state (drive phase 0), so the recording starts at drive phase 0.
        lead_samples = detector_lead_periods(detector, osc.drive_frequency) * round(fine_per_period)
    elif steady:
        log.warning("the detector filter starts at rest at the first sample: %.6g integration steps per drive "
                    "period is not a whole number, so no whole periods can run through it first", fine_per_period)
    fine_grid = Grid(grid.sample_rate * n_sub, 1, (grid.n_samples - 1) * n_sub + 1)
    head = None
    if lead_samples:
        head = _record(integrator, Grid(fine_grid.sample_rate, 1, lead_samples + 1), osc, noise, rng, bar)
    fine = _record(integrator, fine_grid, osc, noise, rng, bar)
    tip = fine.x if head is None else np.concatenate([head.x[:-1], fine.x])
    deflection = detect(tip, fine_grid.sample_rate, n_sub, detector, lead_samples)
    record = Segment(fine.x[::n_sub].copy(), fine.v[::n_sub].copy(), fine.force[::n_sub].copy(),
                     fine.gates[::n_sub].copy(), fine.events)
    return record, deflection


def _record(integrator: Integrator, grid: Grid, osc: Oscillator, noise, rng, bar: _Progress) -> Segment:
    """Integrate and record grid.n_samples samples from t = 0, in chunks (thermal forces per chunk)."""
    n = grid.n_samples
    n_gates = integrator.compiled.n_gates
    record = Segment(np.empty(n), np.empty(n), np.empty(n), np.empty((n, n_gates)), 0)
    h = grid.step
    sigma = thermal_force_std(osc, noise.temperature, h) if noise.thermal else 0.0
    samples_per_period = grid.sample_rate / osc.drive_frequency
    start = 0
    while start < n - 1:
        count = min(RECORD_CHUNK_SAMPLES, n - 1 - start)
        n_steps = count * grid.steps_per_sample
        thermal = rng.standard_normal(n_steps) * sigma if noise.thermal else None
        view = Segment(record.x[start:start + count + 1], record.v[start:start + count + 1],
                       record.force[start:start + count + 1], record.gates[start:start + count + 1], 0)
        integrator.run(start / grid.sample_rate, h, n_steps, grid.steps_per_sample, thermal, out=view)
        record.events += view.events
        start += count
        bar(round(count / samples_per_period))
    return record


# =========================================================================== re-simulation of a fit
def identified_law(run):
    """The identified force law of a run (:class:`afmid.runfile.RunData`) as a simulator's
    :class:`afmid.physics.effects.ForceLaw`: the selected terms with their coefficients (SI), the run's nonlinear
    parameters, the fixed ones, a0 and the tip radius, and the states its terms use."""
    from afmid.physics.effects import EFFECTS, ForceLaw

    params = {"a0": run.config.sample.a0, "R": run.cantilever.get("tip_radius", math.nan)}
    params.update(run.config.model.parameters)  # fixed nonlinear parameters (e.g. a Debye length of sample.ionic_strength)
    params.update({k: v["value"] for k, v in run.nonlinear.items() if k != "d"})
    terms = tuple(("fit", name, expression, float(c))
                  for name, expression, c, s in zip(run.terms, run.expressions, run.coefficients, run.selected) if s)
    states = tuple(g for e in run.effects if e in EFFECTS for g in EFFECTS.get(e).states
                   if any(g.name in t[2] for t in terms))
    return ForceLaw(tuple(run.effects), params, terms, states)


def resimulate_run(run, steps_per_period: int = 2000) -> dict:
    """Steady periodic motion of an identified model (a :class:`afmid.diagnosis.diagnose.RunData`), for the report.

    Uses the run's cantilever, fitted drive amplitude, separation, nonlinear
    parameters and the selected terms with their coefficients. Returns one
    period: deflection x (m), velocity v (m/s), acceleration a (m/s^2), force
    (N), and the first-harmonic amplitude (m). The drive phase is irrelevant for
    phase portraits and is not reproduced.
    """
    cl = run.cantilever
    force_amplitude = math.hypot(run.drive["cos"], run.drive["sin"])
    oscillator = Oscillator(cl["spring_constant"], cl["resonance_frequency"], cl["quality_factor"],
                            run.drive["frequency"], force_amplitude)
    law = identified_law(run)
    integrator = Integrator(oscillator, compile_force_law(law), run.separation)
    x0, v0 = oscillator.free_state(0.0)
    integrator.start(x0, v0, 0.0)
    steady = settle(integrator, steps_per_period, 1e-7, 20000)
    h = oscillator.period / steps_per_period
    seg = integrator.run(0.0, h, steps_per_period, 1)
    t = np.arange(seg.x.size) * h
    drive = force_amplitude * np.cos(oscillator.omega * t)
    acceleration = (drive - oscillator.damping * seg.v - oscillator.spring_constant * seg.x - seg.force) / oscillator.mass
    return {"x": seg.x, "v": seg.v, "a": acceleration, "force": seg.force, "amplitude": steady.amplitude}
