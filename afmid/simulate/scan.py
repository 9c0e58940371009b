"""Recording while scanning: a rest separation d(t) that follows the topography and an amplitude feedback.

The tip moves laterally at the scan speed, x_lat(t) = start + speed t, over a surface of height h(x_lat) (m,
positive = toward the tip; :func:`surface_height`). The z piezo holds the lever's rest position z_piezo(t), so the
rest separation is d(t) = z_piezo(t) - h(x_lat(t)). An integral amplitude feedback
(:class:`afmid.sections.scan.AmplitudeFeedback`) demodulates the first harmonic of the tip's deflection over
each drive period (a lock-in on the recorded samples of that period; the detector noise is not in it), low-passes
it at its bandwidth (first order, once per period) and moves the piezo as dz/dt = -gain (A_filtered - A_set).

The kernel takes one separation per call (:meth:`afmid.simulate.integrator.Integrator.set_separation`), so d is
held constant over each output sample's integration steps and changes between samples: z_piezo changes once per
period, h at every sample. At 4 um/s and 200 samples per period of a 300 kHz drive the tip moves 0.07 pm per
sample, so a 2 nm edge 5 nm wide moves d by < 0.03 pm per sample (the piecewise-constant d's error in the force is
that times the contact stiffness: far below the thermal noise). Part of :mod:`afmid.simulate.driver`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afmid.simulate.integrator import Segment
from afmid.sections.scan import ScanSimulation

#: tanh(u) = 0.8 at u = atanh(0.8): a step's 10-90 % width spans 2 atanh(0.8) of the tanh's argument.
_TANH_10_90 = 2.0 * math.atanh(0.8)
#: Grid points per correlation length on which a rough surface is drawn (linear interpolation in between:
#: its error is ~ (1/8)^2 / 8 of the curvature term, < 0.3 % of the rms).
_ROUGH_POINTS_PER_LENGTH = 8
#: The Gaussian smoothing kernel is cut at this many of its standard deviations (the rest weighs < 1e-8).
_KERNEL_HALF_WIDTH_SIGMAS = 6.0


def surface_height(scan: ScanSimulation, lateral: np.ndarray, default_seed: int) -> np.ndarray:
    """The sample's height h (m, positive = toward the tip) at the lateral positions ``lateral`` (m).

    A step is height * (1 + tanh((x - position) / s)) / 2 with s = width / (2 atanh 0.8) (10-90 % over ``width``).
    A rough surface is white noise on a grid of correlation_length / 8 smoothed by a Gaussian kernel of standard
    deviation correlation_length / 2, so its correlation is rms^2 exp(-r^2 / correlation_length^2), scaled to
    the expected rms (not the drawn one), from its own generator PCG64(seed) (the simulation's noise stream is
    untouched). Flat (zeros) without a profile.
    """
    lateral = np.asarray(lateral, dtype=float)
    if scan.step is not None:
        step = scan.step
        scale = step.width / _TANH_10_90
        return step.height * 0.5 * (1.0 + np.tanh((lateral - step.position) / scale))
    if scan.rough is None or scan.rough.rms == 0.0:
        return np.zeros_like(lateral)
    rough = scan.rough
    spacing = rough.correlation_length / _ROUGH_POINTS_PER_LENGTH
    kernel_sigma = 0.5 * rough.correlation_length
    half = math.ceil(_KERNEL_HALF_WIDTH_SIGMAS * kernel_sigma / spacing)
    lo, hi = float(lateral.min()), float(lateral.max())
    n_grid = math.ceil((hi - lo) / spacing) + 1
    rng = np.random.Generator(np.random.PCG64(default_seed if rough.seed is None else rough.seed))
    white = rng.standard_normal(n_grid + 2 * half)
    offsets = np.arange(-half, half + 1) * spacing
    kernel = np.exp(-0.5 * (offsets / kernel_sigma) ** 2)
    kernel *= rough.rms / math.sqrt(np.sum(kernel**2))
    grid_heights = np.convolve(white, kernel, mode="valid")
    return np.interp(lateral, lo + np.arange(n_grid) * spacing, grid_heights)


@dataclass
class ScanRecord:
    """What a scanning record adds to the tip's :class:`Segment`: per output sample (m)."""

    segment: Segment
    rest_separation: np.ndarray  # d(t) used for the steps after each sample, m
    surface: np.ndarray  # h(x_lat(t)), m
    piezo: np.ndarray  # z_piezo(t), m
    lateral: np.ndarray  # x_lat(t), m
    amplitude: np.ndarray  # the feedback's filtered amplitude after each period, held per sample, m
    setpoint_amplitude: float  # A_set, m


def record_scanning(integrator, grid, osc, scan: ScanSimulation, start_separation: float, start_amplitude: float,
                    setpoint_amplitude: float, thermal_sigma: float, rng, tick, default_seed: int) -> ScanRecord:
    """Integrate grid.n_samples output samples from t = 0 while scanning (see the module docstring).

    ``start_separation`` (m) is d at the first sample (the settled state's), which fixes z_piezo(0) = d(0) +
    h(x_lat(0)); ``start_amplitude`` (m) starts the feedback's filter; ``setpoint_amplitude`` (m) is what it holds.
    Thermal forces (std ``thermal_sigma`` N per step, 0 = none) are drawn from ``rng`` per drive period.
    """
    n, n_sub, fs = grid.n_samples, grid.steps_per_sample, grid.sample_rate
    n_gates = integrator.compiled.n_gates
    segment = Segment(np.empty(n), np.empty(n), np.empty(n), np.empty((n, n_gates)), 0)
    times = np.arange(n) / fs
    lateral = scan.start + scan.speed * times
    surface = surface_height(scan, lateral, default_seed)
    rest = np.empty(n)
    piezo = np.empty(n)
    amplitude = np.empty(n)
    z = start_separation + surface[0]
    filtered = start_amplitude
    period = 1.0 / osc.drive_frequency
    feedback = scan.feedback
    smoothing = 0.0 if feedback is None else 1.0 - math.exp(-2.0 * math.pi * feedback.bandwidth * period)
    # Each period's samples: those with floor(t f) equal (whole periods from t = 0, the drive's phase 0).
    period_of_sample = np.floor(times * osc.drive_frequency + 1e-9).astype(np.int64)
    boundaries = np.flatnonzero(np.diff(period_of_sample)) + 1  # first sample of each new period
    starts = np.concatenate([[0], boundaries])
    stops = np.concatenate([boundaries, [n]])
    h = grid.step
    for first, stop in zip(starts, stops):
        last = min(stop, n - 1)  # samples first..last-1 start an integration interval in this period
        thermal = rng.standard_normal((last - first) * n_sub) * thermal_sigma if thermal_sigma > 0 else None
        for i in range(first, last):
            d = z - surface[i]
            integrator.set_separation(d)
            rest[i], piezo[i], amplitude[i] = d, z, filtered
            view = Segment(segment.x[i:i + 2], segment.v[i:i + 2], segment.force[i:i + 2], segment.gates[i:i + 2], 0)
            steps = None if thermal is None else thermal[(i - first) * n_sub:(i - first + 1) * n_sub]
            integrator.run(times[i], h, n_sub, n_sub, steps, out=view)
            segment.events += view.events
        if feedback is not None and stop - first >= 2:
            phase = osc.omega * times[first:stop]
            x = segment.x[first:stop]
            in_phase = 2.0 / x.size * np.dot(x, np.cos(phase))
            quadrature = 2.0 / x.size * np.dot(x, np.sin(phase))
            filtered += smoothing * (math.hypot(in_phase, quadrature) - filtered)
            z -= feedback.gain * period * (filtered - setpoint_amplitude)
        tick(1)
    # The last sample ends the last interval: its state (and force) came from d over that interval; its track
    # values keep d = z_piezo - h exactly (they differ from that interval's d by one sample's scan, < 0.1 pm).
    piezo[n - 1], amplitude[n - 1] = piezo[n - 2], amplitude[n - 2]
    rest[n - 1] = piezo[n - 1] - surface[n - 1]
    return ScanRecord(segment, rest, surface, piezo, lateral, amplitude, setpoint_amplitude)
