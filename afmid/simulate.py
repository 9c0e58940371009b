"""Simulate tapping-mode deflection traces with their ground truth.

The first flexural mode is a driven, damped point mass (SI units, deflection x
positive toward the sample, tip-sample force F_ts on the tip, repulsive
positive)::

    m x'' + (m w0 / Q) x' + k x = -F_ts(z, zdot, states) + F0 cos(w t) + F_th(t),   m = k / w0^2

with the separation z = d - x (d: rest separation) and F_ts the sum of the
force law's terms (:func:`afmid.physics.build_force_law`). The paper's
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
"""

from __future__ import annotations

import logging
import math
import os
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from . import expr
from .config import RunConfig
from .errors import AfmidError, ConfigError
from .files import memory_shortfall
from .io import Cantilever, Trace, Truth
from .kinematics import contact_kinematics, next_gate_state
from .physics import BOLTZMANN, CONTEXT_UNITS, MODELS, ForceLaw, build_force_law, effect_parameter_names
from .registry import unknown_name_message

log = logging.getLogger(__name__)

#: Consecutive periods whose amplitude and phase change by less than the tolerance.
SETTLED_PERIODS = 5
#: Periods integrated per kernel call while settling (the progress granularity).
SETTLE_CHUNK_PERIODS = 10
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
_DELTA_RE = re.compile(r"\bdelta(dot)?\b")


# =========================================================================== the oscillator
@dataclass(frozen=True)
class Oscillator:
    """The cantilever's first mode as a driven, damped point mass (SI)."""

    spring_constant: float  # k, N/m
    resonance_frequency: float  # f0, Hz
    quality_factor: float  # Q
    drive_frequency: float  # f, Hz
    drive_force: float  # F0, N

    @property
    def omega0(self) -> float:
        """w0, rad/s."""
        return 2.0 * math.pi * self.resonance_frequency

    @property
    def omega(self) -> float:
        """Drive angular frequency w, rad/s."""
        return 2.0 * math.pi * self.drive_frequency

    @property
    def mass(self) -> float:
        """Effective mass m = k / w0^2, kg."""
        return self.spring_constant / self.omega0**2

    @property
    def damping(self) -> float:
        """Viscous damping c = m w0 / Q, kg/s."""
        return self.mass * self.omega0 / self.quality_factor

    @property
    def period(self) -> float:
        """Drive period 1/f, s."""
        return 1.0 / self.drive_frequency

    def free_response(self) -> tuple[float, float]:
        """Amplitude (m) and phase lag (rad) of the free linear steady state x = A cos(w t - phi)."""
        r = self.drive_frequency / self.resonance_frequency
        gain = math.hypot(1.0 - r * r, r / self.quality_factor)
        return self.drive_force / (self.spring_constant * gain), math.atan2(r / self.quality_factor, 1.0 - r * r)

    def free_state(self, t: float = 0.0) -> tuple[float, float]:
        """Deflection (m) and velocity (m/s) of the free linear steady state at time t (s)."""
        amplitude, phase = self.free_response()
        return amplitude * math.cos(self.omega * t - phase), -amplitude * self.omega * math.sin(self.omega * t - phase)


def drive_force_for_amplitude(
    spring_constant: float, resonance_frequency: float, quality_factor: float, drive_frequency: float, amplitude: float
) -> float:
    """F0 (N) that drives the free amplitude ``amplitude`` (m): F0 = k A0 sqrt((1 - r^2)^2 + (r/Q)^2), r = f/f0."""
    r = drive_frequency / resonance_frequency
    return spring_constant * amplitude * math.hypot(1.0 - r * r, r / quality_factor)


# =========================================================================== nondimensional form
@dataclass(frozen=True)
class NondimensionalForm:
    """The paper's form of the equation of motion (supplement eqs. 1-5)::

        xi'' + D xi' + K xi = f_ts + B cos(Omega tau),   tau = w0 t,  xi = x / L

    with D = 1/Q, K = 1, Omega = w / w0, B = F0 / (k L) and f_ts = -F_ts / (k L):
    the tip-sample force toward the sample (the paper's sign, attraction
    positive) in units of k L. Primes are d/dtau. ``length`` L is any length
    scale (the free amplitude by default in :meth:`from_oscillator`).
    """

    length: float  # L, m
    omega0: float  # w0, rad/s
    spring_constant: float  # k, N/m
    damping: float  # D = 1/Q
    drive: float  # B
    drive_frequency: float  # Omega = w / w0
    stiffness: float = 1.0  # K: k / (m w0^2) = 1 with m = k / w0^2

    @classmethod
    def from_oscillator(cls, oscillator: Oscillator, length: float | None = None) -> NondimensionalForm:
        L = oscillator.free_response()[0] if length is None else float(length)
        return cls(
            length=L,
            omega0=oscillator.omega0,
            spring_constant=oscillator.spring_constant,
            damping=1.0 / oscillator.quality_factor,
            drive=oscillator.drive_force / (oscillator.spring_constant * L),
            drive_frequency=oscillator.omega / oscillator.omega0,
        )

    def to_nondimensional(self, t, x, xdot, force=None):
        """SI (t s, x m, xdot m/s[, F_ts N]) -> (tau, xi, xi'[, f_ts])."""
        out = (np.multiply(t, self.omega0), np.divide(x, self.length), np.divide(xdot, self.length * self.omega0))
        if force is None:
            return out
        return (*out, np.negative(force) / (self.spring_constant * self.length))

    def to_si(self, tau, xi, xi_prime, f_ts=None):
        """(tau, xi, xi'[, f_ts]) -> SI (t s, x m, xdot m/s[, F_ts N, repulsive positive])."""
        out = (np.divide(tau, self.omega0), np.multiply(xi, self.length), np.multiply(xi_prime, self.length * self.omega0))
        if f_ts is None:
            return out
        return (*out, -np.multiply(f_ts, self.spring_constant * self.length))

    def acceleration(self, tau, xi, xi_prime, f_ts):
        """xi'' of the nondimensional equation of motion."""
        return f_ts + self.drive * np.cos(self.drive_frequency * tau) - self.damping * xi_prime - self.stiffness * xi


# =========================================================================== configuration
@dataclass(frozen=True)
class Setup:
    """Everything a simulation needs, resolved from a config and checked."""

    oscillator: Oscillator
    force_law: ForceLaw
    model: str
    free_amplitude: float  # A0, m: the linear response to F0
    separation: float | None  # d, m; None when it is searched for simulate.setpoint
    a0: float  # m
    tip_radius: float  # R, m


def _required(config: RunConfig, key: str, value, what: str):
    if value is None:
        raise ConfigError(f"required key is missing ({what})", file=config.source, key=key)
    return float(value)


def resolve_setup(config: RunConfig) -> Setup:
    """Check the config for a simulation and resolve the force law; raises ConfigError."""
    c, drive, sim = config.cantilever, config.drive, config.simulate
    k = _required(config, "cantilever.spring_constant", c.spring_constant, "spring constant k, N/m")
    f0 = _required(config, "cantilever.resonance_frequency", c.resonance_frequency, "resonance frequency f0, Hz")
    Q = _required(config, "cantilever.quality_factor", c.quality_factor, "quality factor Q")
    R = _required(config, "cantilever.tip_radius", c.tip_radius, "tip radius R, m")
    f = _required(config, "drive.frequency", drive.frequency, "drive frequency, Hz")
    if drive.force_amplitude is None and drive.free_amplitude is None:
        raise ConfigError(
            "required key is missing: give drive.force_amplitude (N) or drive.free_amplitude (m)",
            file=config.source,
            key="drive.free_amplitude",
        )
    F0_from_A0 = None if drive.free_amplitude is None else drive_force_for_amplitude(k, f0, Q, f, drive.free_amplitude)
    if drive.force_amplitude is not None:
        F0 = float(drive.force_amplitude)
        if F0_from_A0 is not None and not math.isclose(F0, F0_from_A0, rel_tol=1e-6):
            raise ConfigError(
                f"drive.force_amplitude = {F0!r} N contradicts drive.free_amplitude, which needs "
                f"F0 = {F0_from_A0!r} N; give only one of them",
                file=config.source,
                key="drive.force_amplitude",
            )
    else:
        F0 = F0_from_A0
    oscillator = Oscillator(k, f0, Q, f, F0)

    if sim.setpoint is None:
        d = _required(config, "sample.separation", config.sample.separation, "rest separation d, m, or simulate.setpoint")
    else:
        d = None

    if sim.model not in MODELS:
        raise ConfigError(unknown_name_message("model", sim.model, MODELS.names()), file=config.source, key="simulate.model")
    model = MODELS.get(sim.model)
    repeated = [e for e in sim.effects if e in model.effects]
    if repeated:
        raise ConfigError(
            f"effect(s) {repeated} are already part of model {model.name!r} ({', '.join(model.effects)})",
            file=config.source,
            key="simulate.effects",
        )
    effects = (*model.effects, *sim.effects)
    context = {"R": R, "a0": float(config.sample.a0)}
    try:
        law = build_force_law(effects, {**model.defaults, **sim.parameters}, context, model.derived_defaults)
    except ValueError as exc:
        raise ConfigError(str(exc), file=config.source, key="simulate.parameters") from None
    return Setup(oscillator, law, model.name, oscillator.free_response()[0], d, context["a0"], R)


def parameter_units(law: ForceLaw) -> dict[str, str]:
    """SI units of every parameter of a force law (context R and a0 included)."""
    units = dict(CONTEXT_UNITS)
    units.update({name: p.unit for name, p in effect_parameter_names(law.effects).items()})
    return {name: units[name] for name in law.parameters}


# =========================================================================== compiled force law
@dataclass(frozen=True)
class CompiledForceLaw:
    """A force law as VM programs for the integration kernel.

    ``switching`` are the functions whose sign changes mark non-smooth instants;
    ``owners[j]`` is -1 for a term's own, 2 g / 2 g + 1 for gate g's on / off
    condition (only looked at while the gate is off / on). ``conditions`` are
    the gates' indicator programs, on and off interleaved.
    """

    law: ForceLaw
    terms: tuple[expr.Program, ...]
    coefficients: np.ndarray  # SI, one per term
    switching: tuple[expr.Program, ...]
    owners: np.ndarray  # int64
    conditions: tuple[expr.Program, ...]

    @property
    def n_gates(self) -> int:
        return len(self.law.states)

    def vm_law(self) -> tuple:
        """The ``law`` argument of the generic (VM) kernel: (force bundle, terms + switching bundle,
        coefficients, condition bundle)."""
        return (
            _bundle(self.terms),
            _bundle(self.terms + self.switching),
            self.coefficients,
            _bundle(self.conditions),
        )

    def generated_kernel(self):
        """The kernel generated from these programs (:func:`afmid.kernels.lawgen.law_kernel`).

        Raises :class:`afmid.kernels.lawgen.GenerationError` when it cannot be made.
        """
        from .kernels import lawgen

        return lawgen.law_kernel(self.terms, self.switching, self.conditions, self.coefficients, self.n_gates)


def _bundle(programs) -> tuple:
    s = expr.ProgramSet(list(programs))
    return (s.code, s.code_offsets, s.consts, s.const_offsets)


def compile_force_law(law: ForceLaw) -> CompiledForceLaw:
    """Compile a force law's terms, switching functions and gate conditions."""
    params = dict(law.parameters)
    states = law.state_names
    terms, coefficients = [], []
    switching: dict[tuple[bytes, bytes], tuple[expr.Program, int]] = {}

    def add(programs, owner):
        for p in programs:
            key = (p.code.tobytes(), p.consts.tobytes())
            if key not in switching:
                switching[key] = (p, owner)
            elif switching[key][1] != owner:
                # Shared by several owners (a term and a gate, or a gate whose on and
                # off conditions coincide): it matters in every state.
                switching[key] = (switching[key][0], -1)

    for _effect, _label, text, coefficient in law.terms:
        terms.append(expr.compile_expression(text, params, states))
        coefficients.append(coefficient)
        add(expr.switching_programs(text, params, states), -1)
        if _DELTA_RE.search(text):
            # delta = max(a0 - z, 0) and deltadot kink at contact, out of sight of the term's text.
            add(expr.switching_programs("[z <= a0]", params, states), -1)
    conditions = []
    for g, gate in enumerate(law.states):
        for kind, cond in enumerate((gate.on, gate.off)):
            conditions.append(expr.compile_expression(f"[{cond}]", params, states))
            add(expr.switching_programs(f"[{cond}]", params, states), 2 * g + kind)
    return CompiledForceLaw(
        law=law,
        terms=tuple(terms),
        coefficients=np.array(coefficients, dtype=np.float64),
        switching=tuple(p for p, _ in switching.values()),
        owners=np.array([o for _, o in switching.values()], dtype=np.int64),
        conditions=tuple(conditions),
    )


def program_variables(x, v, t, d: float, a0: float, gates) -> np.ndarray:
    """The programs' variable rows (expr.VARIABLES, then the gates) for states x (m), v (m/s), t (s).

    Arrays broadcast; returns shape (7 + n_gates, N).
    """
    x, v, t = np.broadcast_arrays(np.atleast_1d(np.asarray(x, float)), np.asarray(v, float), np.asarray(t, float))
    rows = [*contact_kinematics(x, v, d, a0), x, v, t]
    gates = np.asarray(gates, float)
    if gates.ndim == 1:
        rows += [np.full(x.shape, g) for g in gates]
    else:  # one row of gate values per sample
        rows += list(gates.T)
    return np.vstack(rows)


def force_numpy(compiled: CompiledForceLaw, x, v, t, d: float, gates) -> np.ndarray:
    """F_ts (N, repulsive positive) by the NumPy twin of the VM (for checks and the reference)."""
    variables = program_variables(x, v, t, d, compiled.law.parameters["a0"], gates)
    values = [expr.evaluate_numpy(p, variables) for p in compiled.terms]
    return np.sum([c * val for c, val in zip(compiled.coefficients, values)], axis=0)


def initial_gates(compiled: CompiledForceLaw, x: float, v: float, t: float, d: float) -> np.ndarray:
    """Gate values at the start: off unless the on-condition holds there."""
    variables = program_variables(x, v, t, d, compiled.law.parameters["a0"], np.zeros(compiled.n_gates))
    return np.array([float(expr.evaluate_numpy(compiled.conditions[2 * g], variables)[0] != 0.0)
                     for g in range(compiled.n_gates)])


# =========================================================================== running the kernel
#: Integrator kernel unless one is asked for: "auto", "generated" or "vm" (see :class:`Integrator`).
DEFAULT_KERNEL = os.environ.get("AFMID_SIMULATE_KERNEL", "auto")
_NO_THERMAL = np.zeros(0)


def _kernel_for(compiled: CompiledForceLaw, kind: str):
    """(kernel module, its law tuple, the kind used) for a compiled force law."""
    if kind != "vm":
        from .kernels.lawgen import GenerationError

        try:
            generated = compiled.generated_kernel()
            return generated.module, generated.law, "generated"
        except GenerationError as exc:
            if kind == "generated":
                raise
            log.debug("using the VM kernel: %s", exc)
    from .kernels import integrate as kernel

    return kernel, compiled.vm_law(), "vm"


@dataclass
class Segment:
    """A stretch of integrated trajectory, recorded every ``n_sub`` steps."""

    x: np.ndarray  # m
    v: np.ndarray  # m/s
    force: np.ndarray  # F_ts, N
    gates: np.ndarray  # (n_records, n_gates)
    events: int  # non-smooth instants stepped onto


class Integrator:
    """Runs the integration kernel for one setup at separation d (m).

    ``kernel`` picks the force-law evaluation: ``"generated"`` -- a kernel
    generated from the force law's programs (:mod:`afmid.kernels.lawgen`;
    compiled once per force-law structure, then cached on disk) --, ``"vm"`` --
    the generic kernel, which interprets the programs (:mod:`afmid.kernels.vm`;
    ~10x slower, nothing to compile) --, or ``"auto"`` (the default, from
    $AFMID_SIMULATE_KERNEL if set): generated, or the VM if generation fails.
    Both run the same algorithm text and give the same numbers (the tests
    compare them bit for bit).
    """

    def __init__(self, oscillator: Oscillator, compiled: CompiledForceLaw, separation: float,
                 kernel: str | None = None):
        kernel = kernel or DEFAULT_KERNEL
        if kernel not in ("auto", "generated", "vm"):
            raise ValueError(f"kernel must be 'auto', 'generated' or 'vm', not {kernel!r}")
        self.oscillator = oscillator
        self.compiled = compiled
        self.separation = separation
        o = oscillator
        a0 = compiled.law.parameters["a0"]
        self.dyn = np.array([o.mass, o.damping, o.spring_constant, o.drive_force, o.omega, separation, a0,
                             1.0 / o.mass])
        self._kernel, self._law, self.kernel = _kernel_for(compiled, kernel)
        # Carried from run to run: the state at the end of the last run.
        self.x = 0.0
        self.v = 0.0
        self.gates = np.zeros(compiled.n_gates)

    def start(self, x: float, v: float, t: float = 0.0, gates: np.ndarray | None = None) -> None:
        """Set the state; gates default to their initial values at (x, v, t)."""
        self.x, self.v = float(x), float(v)
        self.gates = initial_gates(self.compiled, x, v, t, self.separation) if gates is None else np.array(gates, float)

    def run(self, t0: float, h: float, n_steps: int, n_sub: int, thermal: np.ndarray | None = None,
            out: Segment | None = None) -> Segment:
        """Integrate n_steps steps of h (s) from the current state at time t0 (s).

        Records 1 + n_steps // n_sub samples (the first is the current state);
        ``out`` may supply the arrays to fill (views into a larger record).
        ``thermal`` is the force (N) held over each step.
        """
        n_rec = n_steps // n_sub + 1
        if out is None:
            out = Segment(np.empty(n_rec), np.empty(n_rec), np.empty(n_rec), np.empty((n_rec, self.compiled.n_gates)), 0)
        thermal = _NO_THERMAL if thermal is None else thermal
        x, v, status, events = self._kernel.integrate(
            self.x, self.v, t0, h, n_steps, n_sub, self.dyn, self.gates, self._law, self.compiled.owners,
            thermal, out.x, out.v, out.force, out.gates)
        if status != self._kernel.OK:
            raise AfmidError(
                f"the integration diverged (non-finite deflection) between t = {t0:.6g} s and "
                f"{t0 + n_steps * h:.6g} s at separation {self.separation:.4g} m: the tip probably reached a "
                "singular force (z <= 0 in a z^-n term); increase sample.separation or reduce the drive, "
                "or check simulate.parameters",
                key="simulate",
            )
        self.x, self.v = x, v
        out.events = events
        return out


def harmonic_basis(n: int, omega_h: float) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of w t at t = i h, i = 0..n-1, for :func:`first_harmonic` (``omega_h`` = w h)."""
    phase = omega_h * np.arange(n)
    return np.cos(phase), np.sin(phase)


def first_harmonic(x: np.ndarray, omega_h: float,
                   basis: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[float, float]:
    """Amplitude (m) and phase lag (rad) of x = A cos(w t - phi) over one period sampled at t = i h.

    ``omega_h`` = w h with w h len(x) = 2 pi (the rectangle rule is exact for
    trigonometric polynomials over a full period). ``basis``: the arrays of
    :func:`harmonic_basis` for len(x), when called for many periods.
    """
    cos, sin = harmonic_basis(x.size, omega_h) if basis is None else basis
    a = 2.0 / x.size * np.dot(x, cos)
    b = 2.0 / x.size * np.dot(x, sin)
    return math.hypot(a, b), math.atan2(b, a)


@dataclass
class SteadyState:
    periods: int  # drive periods integrated to settle
    amplitude: float  # first-harmonic amplitude, m
    phase: float  # its phase lag behind the drive, rad


def settle(integrator: Integrator, steps_per_period: int, tolerance: float, max_periods: int,
           tick: Callable[[int], None] = lambda n: None) -> SteadyState:
    """Integrate whole drive periods until the first harmonic stops changing.

    Settled when the relative amplitude change and the phase change (rad) from
    one period to the next stay below ``tolerance`` for SETTLED_PERIODS periods
    in a row. The transient decays by exp(-pi/Q) per period, so the remaining
    deviation from the steady state is about tolerance * Q / pi. Leaves the
    integrator at a period boundary (drive phase 0). Raises AfmidError if it
    does not settle within ``max_periods``.
    """
    h = integrator.oscillator.period / steps_per_period
    omega_h = 2.0 * math.pi / steps_per_period
    basis = harmonic_basis(steps_per_period, omega_h)
    previous = None
    calm = 0
    done = 0
    while done < max_periods:
        chunk = min(SETTLE_CHUNK_PERIODS, max_periods - done)
        seg = integrator.run(0.0, h, chunk * steps_per_period, 1)
        for p in range(chunk):
            amplitude, phase = first_harmonic(seg.x[p * steps_per_period:(p + 1) * steps_per_period], omega_h, basis)
            if previous is not None:
                d_amp = abs(amplitude - previous[0]) / amplitude
                d_phase = abs(math.remainder(phase - previous[1], 2.0 * math.pi))
                calm = calm + 1 if max(d_amp, d_phase) < tolerance else 0
            previous = (amplitude, phase)
        done += chunk
        tick(chunk)
        if calm >= SETTLED_PERIODS:
            return SteadyState(done, amplitude, phase)
    raise AfmidError(
        f"the oscillation did not settle within {max_periods} drive periods (the first harmonic still "
        f"changes by more than simulate.settle_tolerance = {tolerance:g} per period; it may be "
        "period-doubled or chaotic at this separation). Increase simulate.max_settle_periods, loosen "
        "simulate.settle_tolerance, or use simulate.mode: transient",
        key="simulate.max_settle_periods",
    )


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
    """A tqdm bar counting drive periods, shown only for runs longer than ~2 s."""

    def __init__(self, enabled: bool):
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(unit="period", delay=2.0, leave=False, desc="simulate")

    def stage(self, name: str) -> None:
        if self.bar is not None:
            self.bar.set_description_str(name)

    def __call__(self, periods: int) -> None:
        if self.bar is not None:
            self.bar.update(periods)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _search_separation(setup: Setup, compiled: CompiledForceLaw, config: RunConfig, progress: _Progress):
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
        integrator = Integrator(setup.oscillator, compiled, d)
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
    try:
        if sim.setpoint is not None:
            bar.stage("setpoint search")
            d, integrator, evaluations = _search_separation(setup, compiled, config, bar)
            extra.update(setpoint_target=float(sim.setpoint), setpoint_search_evaluations=evaluations)
        else:
            d = setup.separation
            integrator = Integrator(osc, compiled, d)
            integrator.start(*osc.free_state(0.0))
        if sim.mode == "transient" and sim.transient_start == "rest":
            integrator.start(0.0, 0.0)
        elif sim.mode == "transient":
            integrator.start(*osc.free_state(0.0))

        if sim.mode == "steady":
            bar.stage("settling")
            state = settle(integrator, sim.steps_per_period, sim.settle_tolerance, sim.max_settle_periods, bar)
            extra.update(steady_amplitude=state.amplitude, steady_phase=state.phase, settle_periods=state.periods,
                         setpoint=state.amplitude / setup.free_amplitude)
            if sim.setpoint is not None and abs(state.amplitude / setup.free_amplitude - sim.setpoint) > 1e-3:
                log.warning("setpoint search reached A/A0 = %.4f instead of %.4f (the amplitude jumps near "
                            "this separation: bistable attractive/repulsive regimes)",
                            state.amplitude / setup.free_amplitude, sim.setpoint)
            if noise.thermal:
                bar.stage("thermal warm-up")
                warmup = math.ceil(THERMAL_WARMUP_ENERGY_TIMES * osc.quality_factor / (2.0 * math.pi))
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

        bar.stage("recording")
        record = _record(integrator, grid, osc, noise, rng, bar)
    finally:
        bar.close()

    deflection = record.x.copy()
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
               "steady_amplitude: m; steady_phase: rad (lag behind the drive); integration_step: s; "
               "temperature: K; detector_rms: m; adc_step: m"),
    )
    truth = Truth(
        force=record.force,
        separation=d - record.x,
        velocity=record.v,
        model=setup.model,
        effects=list(law.effects),
        parameters={k: float(v) for k, v in law.parameters.items()},
        units=parameter_units(law),
        extra=extra,
    )
    cantilever = Cantilever(osc.spring_constant, osc.resonance_frequency, osc.quality_factor, setup.tip_radius)
    return Trace(deflection=deflection, sample_rate=grid.sample_rate, cantilever=cantilever,
                 drive_frequency=osc.drive_frequency, truth=truth, drive_force_amplitude=osc.drive_force)


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


# =========================================================================== plain-Python twin
def reference_drive(oscillator: Oscillator, t0: float, h: float, n_steps: int) -> np.ndarray:
    """Plain-Python twin of the kernel's drive: F0 cos(w t) (N) at t = t0 + (i + m/2) h.

    Shape (n_steps, 3), columns m = 0, 1, 2 (the RK4 stage times of step i).
    Exact (``math.cos``) at every DRIVE_ANCHOR_STEPS-th step start, by the
    angle-addition formula with the table of :func:`afmid.kernels.integrate.drive_table`
    in between, as :func:`afmid.kernels.integrate.integrate` computes it.
    """
    from .kernels.integrate import DRIVE_ANCHOR_STEPS as K

    w, F0 = oscillator.omega, oscillator.drive_force
    angles = [w * (0.5 * h * m) for m in range(2 * K + 1)]
    cos_table, sin_table = [math.cos(a) for a in angles], [math.sin(a) for a in angles]
    out = np.empty((n_steps, 3))
    c = s = 0.0
    for i in range(n_steps):
        k = i % K
        if k == 0:
            phase = w * (t0 + i * h)
            c, s = math.cos(phase), math.sin(phase)
        for j in range(3):
            out[i, j] = F0 * (c * cos_table[2 * k + j] - s * sin_table[2 * k + j])
    return out


def reference_integrate(compiled: CompiledForceLaw, oscillator: Oscillator, separation: float,
                        x: float, v: float, t0: float, h: float, n_steps: int, gates=None, thermal=None):
    """Plain NumPy/Python twin of the kernel's RK4 + event logic (slow; for tests).

    Same algorithm as :func:`afmid.kernels.integrate.integrate` and
    :func:`~afmid.kernels.integrate.event_step` (drive included, see
    :func:`reference_drive`), written without numba and evaluating the force
    with :func:`afmid.expr.evaluate_numpy`. Returns arrays x (m), v (m/s) and
    gates at t0 + i h, i = 0..n_steps, and the number of events.
    """
    from .kernels.integrate import EVENT_TOLERANCE, MAX_EVENTS_PER_STEP, MAX_ROOT_ITERATIONS

    o = oscillator
    a0 = compiled.law.parameters["a0"]
    owners = compiled.owners
    gates = initial_gates(compiled, x, v, t0, separation) if gates is None else np.array(gates, float)
    drives = reference_drive(o, t0, h, n_steps)

    def drive(t):
        return o.drive_force * math.cos(o.omega * t)

    inverse_mass = 1.0 / o.mass

    def accel(x, v, t, g, f_th, d):
        f_ts = float(force_numpy(compiled, x, v, t, separation, g)[0])
        return (d + f_th - o.damping * v - o.spring_constant * x - f_ts) * inverse_mass

    def rk4(x, v, t, dt, g, f_th, d1, d2=None, d4=None):
        """One RK4 step; the drive at t + dt/2 and t + dt is evaluated directly unless given."""
        d2 = drive(t + 0.5 * dt) if d2 is None else d2
        d4 = drive(t + dt) if d4 is None else d4
        a1 = accel(x, v, t, g, f_th, d1)
        x2, v2 = x + 0.5 * dt * v, v + 0.5 * dt * a1
        a2 = accel(x2, v2, t + 0.5 * dt, g, f_th, d2)
        x3, v3 = x + 0.5 * dt * v2, v + 0.5 * dt * a2
        a3 = accel(x3, v3, t + 0.5 * dt, g, f_th, d2)
        x4, v4 = x + dt * v3, v + dt * a3
        a4 = accel(x4, v4, t + dt, g, f_th, d4)
        return x + dt / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4), v + dt / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)

    def switching(x, v, t, g):
        variables = program_variables(x, v, t, separation, a0, g)
        return np.array([expr.evaluate_numpy(p, variables)[0] for p in compiled.switching])

    def relevant(owner, g):
        return owner < 0 or (g[owner // 2] == 0.0) == (owner % 2 == 0)

    def flip(x, v, t, g):
        variables = program_variables(x, v, t, separation, a0, g)
        values = [expr.evaluate_numpy(p, variables)[0] for p in compiled.conditions]
        for i in range(g.size):
            g[i] = next_gate_state(g[i], values[2 * i], values[2 * i + 1])

    def crossing(x, v, t, g, f_th, d1, j, s0, s_hi, hi):
        side = s0 > 0.0
        lo, f_lo, f_hi, last = 0.0, s0, s_hi, 0
        for _ in range(MAX_ROOT_ITERATIONS):
            if hi - lo <= EVENT_TOLERANCE * h:
                break
            theta = hi - f_hi * (hi - lo) / (f_hi - f_lo)
            if not (lo < theta < hi):
                theta = 0.5 * (lo + hi)
            f_mid = switching(*rk4(x, v, t, theta, g, f_th, d1), t + theta, g)[j]
            if (f_mid > 0.0) == side:
                lo, f_lo = theta, f_mid
                f_hi = f_hi * 0.5 if last == -1 else f_hi
                last = -1
            else:
                hi, f_hi = theta, f_mid
                f_lo = f_lo * 0.5 if last == 1 else f_lo
                last = 1
        return hi

    xs, vs, gs = [x], [v], [gates.copy()]
    s_now = switching(x, v, t0, gates)
    events = 0
    for i in range(n_steps):
        f_th = 0.0 if thermal is None else float(thermal[i])
        t_now, remaining, n_ev = t0 + i * h, h, 0
        d1 = drives[i, 0]
        x1, v1 = rk4(x, v, t_now, remaining, gates, f_th, d1, drives[i, 1], drives[i, 2])
        while True:
            s_end = switching(x1, v1, t_now + remaining, gates)
            hi, crossed = remaining, False
            if n_ev < MAX_EVENTS_PER_STEP:
                for j in range(len(s_now)):
                    if not relevant(owners[j], gates) or (s_end[j] > 0.0) == (s_now[j] > 0.0):
                        continue
                    if crossed:
                        s_hi = switching(*rk4(x, v, t_now, hi, gates, f_th, d1), t_now + hi, gates)[j]
                        if (s_hi > 0.0) == (s_now[j] > 0.0):
                            continue
                    else:
                        s_hi = s_end[j]
                    hi = crossing(x, v, t_now, gates, f_th, d1, j, s_now[j], s_hi, hi)
                    crossed = True
            if not crossed:
                x, v, s_now = x1, v1, s_end
                flip(x, v, t_now + remaining, gates)
                break
            x, v = rk4(x, v, t_now, hi, gates, f_th, d1)
            t_now += hi
            remaining -= hi
            n_ev += 1
            flip(x, v, t_now, gates)
            s_now = switching(x, v, t_now, gates)
            if remaining <= EVENT_TOLERANCE * h:
                break
            d1 = drive(t_now)
            x1, v1 = rk4(x, v, t_now, remaining, gates, f_th, d1)
        events += n_ev
        xs.append(x)
        vs.append(v)
        gs.append(gates.copy())
    return np.array(xs), np.array(vs), np.array(gs), events


# =========================================================================== re-simulation of a fit
def resimulate_run(run, steps_per_period: int = 2000) -> dict:
    """Steady periodic motion of an identified model (a :class:`afmid.diagnose.RunData`), for the report.

    Uses the run's cantilever, fitted drive amplitude, separation, nonlinear
    parameters and the selected terms with their coefficients. Returns one
    period: deflection x (m), velocity v (m/s), acceleration a (m/s^2), force
    (N), and the first-harmonic amplitude (m). The drive phase is irrelevant for
    phase portraits and is not reproduced.
    """
    from .physics import EFFECTS, ForceLaw

    cl = run.cantilever
    force_amplitude = math.hypot(run.drive["cos"], run.drive["sin"])
    oscillator = Oscillator(cl["spring_constant"], cl["resonance_frequency"], cl["quality_factor"],
                            run.drive["frequency"], force_amplitude)
    params = {"a0": run.config.sample.a0, "R": cl.get("tip_radius", math.nan)}
    params.update({k: v["value"] for k, v in run.nonlinear.items() if k != "d"})
    terms = tuple(("fit", name, expression, float(c))
                  for name, expression, c, s in zip(run.terms, run.expressions, run.coefficients, run.selected) if s)
    states = tuple(g for e in run.effects if e in EFFECTS for g in EFFECTS.get(e).states
                   if any(g.name in t[2] for t in terms))
    law = ForceLaw(tuple(run.effects), params, terms, states)
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
