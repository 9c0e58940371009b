"""The simulated instrument: higher flexural modes integrated with the first, and the detector filter.

:class:`MultiModeIntegrator` has the interface of :class:`afmid.simulate.integrator.Integrator` (``start``,
``run``, ``x``, ``v``, ``gates``), so :func:`afmid.simulate.integrator.settle` and the recording loop of
:mod:`afmid.simulate.driver` use it unchanged; it runs :mod:`afmid.kernels.multimode` (every mode driven by the drive
and the tip-sample force at the tip, the tip the sum of the modes; the thermal force on the first mode only:
a higher mode's thermal amplitude sqrt(k_B T / k_i) is small beside the first's, 1/6 of it for a rectangular
lever). :func:`detect` passes the finely integrated tip deflection through the detector's causal filter
(:meth:`afmid.preprocess.instrument.Detector.digital`) and keeps every ``n_sub``-th sample, as an anti-alias filter before
the ADC does. Part of :mod:`afmid.simulate.driver` (the facade).
"""

from __future__ import annotations

import math

import numpy as np

from afmid.errors import AfmidError
from afmid.preprocess.instrument import Detector, Instrument
from afmid.simulate.integrator import Integrator, Segment, dynamics_vector
from afmid.simulate.model import CompiledForceLaw, Oscillator, initial_gates

#: Periods integrated through the detector before recording, per unit of f_drive / bandwidth: the slowest
#: pole of a Butterworth of order 12 decays at 0.13 w_c, so its start-up transient falls below 1e-12 of the
#: signal within 34 / bandwidth seconds.
DETECTOR_SETTLE_PER_BANDWIDTH = 34.0


class MultiModeIntegrator:
    """Integrates the first mode (``oscillator``) and ``instrument.higher_modes`` together at separation d (m)."""

    kernel = "multimode"

    def __init__(self, oscillator: Oscillator, compiled: CompiledForceLaw, separation: float, instrument: Instrument):
        self.oscillator = oscillator
        self.compiled = compiled
        self.separation = separation
        o = oscillator
        self.dyn = dynamics_vector(oscillator, compiled, separation)
        rows = [(o.mass, o.damping, o.spring_constant)]
        for mode in instrument.higher_modes:
            w = 2.0 * math.pi * mode.resonance_frequency
            mass = mode.spring_constant / w**2
            rows.append((mass, mass * w / mode.quality_factor, mode.spring_constant))
        self.modes = np.array(rows, dtype=float)
        self._law = compiled.vm_law()
        self.mode_x = np.zeros(len(rows))
        self.mode_v = np.zeros(len(rows))
        self.gates = np.zeros(compiled.n_gates)

    @property
    def x(self) -> float:
        """Tip deflection (m): the sum of the modes."""
        return float(self.mode_x.sum())

    @property
    def v(self) -> float:
        return float(self.mode_v.sum())

    def start(self, x: float, v: float, t: float = 0.0, gates: np.ndarray | None = None) -> None:
        """Tip state (x m, v m/s) carried by the first mode, the higher modes at rest (they settle within
        Q_i / (pi f_i) seconds); gates default to their values at (x, v, t)."""
        self.mode_x[:] = 0.0
        self.mode_v[:] = 0.0
        self.mode_x[0], self.mode_v[0] = float(x), float(v)
        self.gates = initial_gates(self.compiled, x, v, t, self.separation) if gates is None else np.array(gates, float)

    def set_separation(self, separation: float) -> None:
        """Move the rest separation d (m) for the following runs (a scanning record's d(t), held over each run)."""
        self.separation = float(separation)
        self.dyn[5] = self.separation

    def run(self, t0: float, h: float, n_steps: int, n_sub: int, thermal: np.ndarray | None = None,
            out: Segment | None = None) -> Segment:
        """As :meth:`afmid.simulate.integrator.Integrator.run` (``thermal``: force on the first mode per step)."""
        from afmid.kernels import multimode

        n_rec = n_steps // n_sub + 1
        if out is None:
            out = Segment(np.empty(n_rec), np.empty(n_rec), np.empty(n_rec), np.empty((n_rec, self.compiled.n_gates)), 0)
        thermal = np.zeros(0) if thermal is None else thermal
        status, events = multimode.integrate_modes(
            self.mode_x, self.mode_v, t0, h, n_steps, n_sub, self.dyn, self.modes, self.gates, self._law,
            self.compiled.owners, thermal, out.x, out.v, out.force, out.gates)
        if status != multimode.OK:
            raise AfmidError(f"the integration of the modes diverged between t = {t0:.6g} s and "
                             f"{t0 + n_steps * h:.6g} s at separation {self.separation:.4g} m", key="simulate")
        out.events = events
        return out


def integrator_for(instrument: Instrument, oscillator: Oscillator, compiled: CompiledForceLaw, separation: float):
    """The single-mode :class:`Integrator` when no higher mode is declared, else a :class:`MultiModeIntegrator`."""
    if not instrument.higher_modes:
        return Integrator(oscillator, compiled, separation)
    return MultiModeIntegrator(oscillator, compiled, separation, instrument)


def detector_lead_periods(detector: Detector, drive_frequency: float) -> int:
    """Whole drive periods to run through the detector before the first recorded sample."""
    return 1 + math.ceil(DETECTOR_SETTLE_PER_BANDWIDTH * drive_frequency / detector.bandwidth)


def detect(fine: np.ndarray, fine_rate: float, n_sub: int, detector: Detector, lead: int) -> np.ndarray:
    """The recorded samples: ``fine`` (tip deflection, m, at ``fine_rate`` Hz, starting ``lead`` fine samples
    before the first recorded one, the filter at rest before it) through the detector, every ``n_sub``-th."""
    from scipy import signal

    filtered = signal.sosfilt(detector.digital(fine_rate), fine)
    return np.ascontiguousarray(filtered[lead::n_sub])
