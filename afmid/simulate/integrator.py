"""Running the integration kernel: :class:`Integrator`, and settling to the steady state.

Integration is fixed-step RK4 in a numba kernel (:mod:`afmid.kernels.integrate`)
that steps exactly onto every non-smooth instant (contact, gate flips). By
default the kernel is generated from the force law's compiled programs
(:mod:`afmid.kernels.lawgen`: straight-line code instead of the VM, ~10x faster,
compiled once per force-law structure and cached on disk); the generic kernel
interprets the same programs (``Integrator(kernel="vm")``, or
``AFMID_SIMULATE_KERNEL=vm``) and gives the same numbers. :func:`settle`
integrates whole drive periods until the first harmonic (:func:`first_harmonic`)
stops changing. Part of :mod:`afmid.simulate.driver` (the facade).

numba is imported only when an :class:`Integrator` is made, so importing this
module stays cheap.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from afmid.errors import AfmidError
from afmid.simulate.model import CompiledForceLaw, Oscillator, initial_gates

log = logging.getLogger(__name__)

#: Consecutive periods whose amplitude and phase change by less than the tolerance.
SETTLED_PERIODS = 5
#: Periods integrated per kernel call while settling (the progress granularity).
SETTLE_CHUNK_PERIODS = 10


# =========================================================================== running the kernel
#: Integrator kernel unless one is asked for: "auto", "generated" or "vm" (see :class:`Integrator`).
DEFAULT_KERNEL = os.environ.get("AFMID_SIMULATE_KERNEL", "auto")
_NO_THERMAL = np.zeros(0)


def _kernel_for(compiled: CompiledForceLaw, kind: str):
    """(kernel module, its law tuple, the kind used) for a compiled force law."""
    if kind != "vm":
        from afmid.kernels.lawgen import GenerationError

        try:
            generated = compiled.generated_kernel()
            return generated.module, generated.law, "generated"
        except GenerationError as exc:
            if kind == "generated":
                raise
            log.debug("using the VM kernel: %s", exc)
    from afmid.kernels import integrate as kernel

    return kernel, compiled.vm_law(), "vm"


@dataclass
class Segment:
    """A stretch of integrated trajectory, recorded every ``n_sub`` steps."""

    x: np.ndarray  # m
    v: np.ndarray  # m/s
    force: np.ndarray  # F_ts, N
    gates: np.ndarray  # (n_records, n_gates)
    events: int  # non-smooth instants stepped onto


def dynamics_vector(oscillator: Oscillator, compiled: CompiledForceLaw, separation: float) -> np.ndarray:
    """The kernels' parameter vector of the first mode: mass (kg), damping (kg/s), k (N/m), drive force (N),
    drive angular frequency (rad/s), separation d (m), a0 (m), 1 / mass."""
    o = oscillator
    return np.array([o.mass, o.damping, o.spring_constant, o.drive_force, o.omega, separation,
                     compiled.law.parameters["a0"], 1.0 / o.mass])


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
        self.dyn = dynamics_vector(oscillator, compiled, separation)
        self._kernel, self._law, self.kernel = _kernel_for(compiled, kernel)
        # Carried from run to run: the state at the end of the last run.
        self.x = 0.0
        self.v = 0.0
        self.gates = np.zeros(compiled.n_gates)

    def start(self, x: float, v: float, t: float = 0.0, gates: np.ndarray | None = None) -> None:
        """Set the state; gates default to their initial values at (x, v, t)."""
        self.x, self.v = float(x), float(v)
        self.gates = initial_gates(self.compiled, x, v, t, self.separation) if gates is None else np.array(gates, float)

    def set_separation(self, separation: float) -> None:
        """Move the rest separation d (m) for the following runs (a scanning record's d(t), held over each run)."""
        self.separation = float(separation)
        self.dyn[5] = self.separation

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
    settled: bool = True  # False: the first harmonic still changed when max_periods ran out (see settle)
    amplitude_low: float = math.nan  # unsettled: the smallest and largest first-harmonic amplitude (m) over
    amplitude_high: float = math.nan  # the last ORBIT_WINDOW_PERIODS periods
    orbit_periods: int = 0  # unsettled: the orbit's period in drive periods (0: no repeat within ORBIT_WINDOW_PERIODS / 2)


#: Periods whose first harmonic an unsettled :func:`settle` keeps to describe the orbit it ended on.
ORBIT_WINDOW_PERIODS = 128


def orbit_period(amplitudes: np.ndarray, phases: np.ndarray, tolerance: float) -> int:
    """The smallest lag L (drive periods, 1 .. len / 2) after which the per-period first harmonic repeats: every
    amplitude within ``tolerance`` (relative) and every phase within ``tolerance`` (rad) of the one L periods
    before, over the whole series; 0 when none does (a slow beat, quasi-periodic or chaotic motion)."""
    for lag in range(1, amplitudes.size // 2 + 1):
        d_amp = np.abs(amplitudes[lag:] - amplitudes[:-lag]) / amplitudes[lag:]
        d_phase = np.abs(np.remainder(phases[lag:] - phases[:-lag] + math.pi, 2.0 * math.pi) - math.pi)
        if max(d_amp.max(), d_phase.max()) < tolerance:
            return lag
    return 0


def settle(integrator: Integrator, steps_per_period: int, tolerance: float, max_periods: int,
           tick: Callable[[int], None] = lambda n: None, require_settled: bool = True) -> SteadyState:
    """Integrate whole drive periods until the first harmonic stops changing.

    Settled when the relative amplitude change and the phase change (rad) from
    one period to the next stay below ``tolerance`` for SETTLED_PERIODS periods
    in a row. The transient decays by exp(-pi/Q) per period, so the remaining
    deviation from the steady state is about tolerance * Q / pi. Leaves the
    integrator at a period boundary (drive phase 0). Raises AfmidError if it
    does not settle within ``max_periods``; with ``require_settled`` false it
    returns the state it ended on instead (``settled`` False, the amplitude range
    and the orbit's period over the last ORBIT_WINDOW_PERIODS periods): a
    period-n or aperiodic orbit, as an instrument would record it.
    """
    h = integrator.oscillator.period / steps_per_period
    omega_h = 2.0 * math.pi / steps_per_period
    basis = harmonic_basis(steps_per_period, omega_h)
    previous = None
    calm = 0
    done = 0
    recent_amplitudes: list[float] = []
    recent_phases: list[float] = []
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
            recent_amplitudes.append(amplitude)
            recent_phases.append(phase)
        del recent_amplitudes[:-ORBIT_WINDOW_PERIODS], recent_phases[:-ORBIT_WINDOW_PERIODS]
        done += chunk
        tick(chunk)
        if calm >= SETTLED_PERIODS:
            return SteadyState(done, amplitude, phase)
    if not require_settled:
        amplitudes, phases = np.array(recent_amplitudes), np.array(recent_phases)
        return SteadyState(done, amplitude, phase, settled=False, amplitude_low=float(amplitudes.min()),
                           amplitude_high=float(amplitudes.max()),
                           orbit_periods=orbit_period(amplitudes, phases, tolerance))
    raise AfmidError(
        f"the oscillation did not settle within {max_periods} drive periods (the first harmonic still "
        f"changes by more than simulate.settle_tolerance = {tolerance:g} per period; it may be "
        "period-doubled or chaotic at this separation). Increase simulate.max_settle_periods, loosen "
        "simulate.settle_tolerance, record the orbit as it is (simulate.unsettled: record), or use "
        "simulate.mode: transient",
        key="simulate.max_settle_periods",
    )
