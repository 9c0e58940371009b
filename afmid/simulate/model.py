"""The simulated system: the oscillator, its configuration and the compiled force law.

The first flexural mode is a driven, damped point mass (SI units, deflection x
positive toward the sample, tip-sample force F_ts on the tip, repulsive
positive)::

    m x'' + (m w0 / Q) x' + k x = -F_ts(z, zdot, states) + F0 cos(w t) + F_th(t),   m = k / w0^2

with the separation z = d - x (d: rest separation) and F_ts the sum of the
force law's terms (:func:`afmid.physics.effects.build_force_law`). This module holds
:class:`Oscillator`, the paper's :class:`NondimensionalForm`, the checked
:class:`Setup` resolved from a config (:func:`resolve_setup`), and the force
law compiled to VM programs (:func:`compile_force_law`) with its NumPy
evaluation (:func:`force_numpy`). Part of :mod:`afmid.simulate.driver` (the facade).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

import afmid.terms.expr as expr
from afmid.config import RunConfig
from afmid.errors import ConfigError
from afmid.io.cantilever import Cantilever, FirstMode
from afmid.terms.kinematics import contact_kinematics
import afmid.physics.medium as medium
from afmid.physics.effect_types import RelaxingState
from afmid.physics.effects import CONTEXT_UNITS, MODELS, ForceLaw, build_force_law, effect_parameter_names
from afmid.physics.tips import tip_geometry
from afmid.registry import unknown_name_message

_DELTA_RE = re.compile(r"\bdelta(dot)?\b")


# =========================================================================== the oscillator
@dataclass(frozen=True)
class Oscillator(FirstMode):
    """The cantilever's first mode as a driven, damped point mass (SI): the lever's calibration
    (:class:`afmid.io.cantilever.Cantilever`, :meth:`of`) with the drive; mass and damping computed as there."""

    spring_constant: float  # k, N/m
    resonance_frequency: float  # f0, Hz
    quality_factor: float  # Q
    drive_frequency: float  # f, Hz
    drive_force: float  # F0, N

    @property
    def omega(self) -> float:
        """Drive angular frequency w, rad/s."""
        return 2.0 * math.pi * self.drive_frequency

    @classmethod
    def of(cls, cantilever: Cantilever, drive_frequency: float, drive_force: float) -> "Oscillator":
        """The first mode of ``cantilever`` driven at ``drive_frequency`` (Hz) with ``drive_force`` (N)."""
        return cls(cantilever.spring_constant, cantilever.resonance_frequency, cantilever.quality_factor,
                   drive_frequency, drive_force)

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
    if drive.phase is not None and drive.phase != 0.0:
        raise ConfigError(f"the simulator drives with F0 cos(2 pi f t), t = 0 at the first sample (phase 0), got "
                          f"{drive.phase!r} rad; drive.phase is for fitting a calibrated drive",
                          file=config.source, key="drive.phase")
    lever = Cantilever.from_config(c, spring_constant=k, resonance_frequency=f0, quality_factor=Q, tip_radius=R)
    oscillator = Oscillator.of(lever, f, F0)

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
    context = {"R": R, "a0": float(config.sample.a0), "eps_r": medium.relative_permittivity(config.sample)}
    implied = medium.simulator_defaults(config.sample, effects)  # the Debye length of sample.ionic_strength, ...
    try:
        law = build_force_law(effects, {**model.defaults, **implied, **sim.parameters}, context, model.derived_defaults,
                              tip_geometry(config.cantilever))
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
        """Gate slots: one per gate, three per relaxing state (:func:`gate_slot_names`)."""
        return len(gate_slot_names(self.law.states))

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
        from afmid.kernels import lawgen

        return lawgen.law_kernel(self.terms, self.switching, self.conditions, self.coefficients, self.n_gates)


def _bundle(programs) -> tuple:
    s = expr.ProgramSet(list(programs))
    return (s.code, s.code_offsets, s.consts, s.const_offsets)


#: The slots a relaxing state takes after its value: its source at its last update and the time of that update.
RELAXING_SLOTS = ("__source", "__clock")


def gate_slot_names(states) -> tuple[str, ...]:
    """The kernel's gate slots of a law's states: a gate's name; a relaxing state's name and its two bookkeeping
    slots (:func:`afmid.kernels.integrate.start_relaxation_clocks`), which no term reads."""
    return tuple(name for s in states
                 for name in ((s.name, *(s.name + suffix for suffix in RELAXING_SLOTS))
                              if isinstance(s, RelaxingState) else (s.name,)))


def _state_conditions(state, params, slots):
    """A state's (program, kind-of-condition text) pairs for the kernel: a gate's on and off conditions; a
    relaxing state's source and minus its time constant (the kernel's marker), then two idle pairs."""
    if isinstance(state, RelaxingState):
        idle = expr.compile_expression("0", params, slots)
        return [expr.compile_expression(state.source, params, slots),
                expr.compile_expression(f"-{state.time}", params, slots), idle, idle, idle, idle]
    return [expr.compile_expression(f"[{cond}]", params, slots) for cond in (state.on, state.off)]


def _relaxing_states_within_step(text: str, states) -> str:
    """A term's text for the kernel: a relaxing state q, advanced exactly only at the ends of (sub-)steps, read
    inside a step at t as q + (t - t_q) (g_q - q) / tau (its value and source at its last update t_q, the
    kernel's bookkeeping slots): first order in (t - t_q), so the force's error over a step is O(h^2) (held at
    q, the error was O(h): the state half a step late)."""
    for state in states:
        if isinstance(state, RelaxingState):
            source, clock = (state.name + suffix for suffix in RELAXING_SLOTS)
            text = re.sub(rf"\b{state.name}\b",
                          f"({state.name} + (t - {clock}) * ({source} - {state.name}) / {state.time})", text)
    return text


def compile_force_law(law: ForceLaw) -> CompiledForceLaw:
    """Compile a force law's terms, switching functions and gate conditions."""
    params = dict(law.parameters)
    states = gate_slot_names(law.states)
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
        text = _relaxing_states_within_step(text, law.states)
        terms.append(expr.compile_expression(text, params, states))
        coefficients.append(coefficient)
        add(expr.switching_programs(text, params, states), -1)
        if _DELTA_RE.search(text):
            # delta = max(a0 - z, 0) and deltadot kink at contact, out of sight of the term's text.
            add(expr.switching_programs("[z <= a0]", params, states), -1)
    conditions = []
    for gate in law.states:
        g = len(conditions) // 2
        conditions.extend(_state_conditions(gate, params, states))
        if isinstance(gate, RelaxingState):
            continue  # a lagging value: nothing switches
        for kind, cond in enumerate((gate.on, gate.off)):
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
    first = [float(expr.evaluate_numpy(compiled.conditions[2 * g], variables)[0]) for g in range(compiled.n_gates)]
    values, g = [], 0
    for state in compiled.law.states:
        if isinstance(state, RelaxingState):  # relaxed: its source's value (the clock slots are set by the kernel)
            values += [first[g], first[g], t]
            g += 3
        else:
            values.append(float(first[g] != 0.0))
            g += 1
    return np.array(values)
