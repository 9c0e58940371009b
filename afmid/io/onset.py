"""Where the oscillation starts, and the part of a record the fit uses (``data.start`` / ``data.stop``).

A record of the paper's transient identification may begin before the drive is
switched on: the cantilever rests (thermal and detector noise only), then the
drive starts and the amplitude grows into tapping. Before the onset the phase
of each period is that of noise, so the phase-jump check (dropped samples) must
not read it; and the fit's drive columns assume the drive on throughout, so the
record before the onset must not be fitted. :func:`find_onset` finds the first
period from which the first-harmonic amplitude stays far above what noise
gives; :func:`crop` cuts a loaded trace (deflection, time, truth) to a part of
it, keeping the file's time base (``Trace.first_sample``).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from afmid.io.findings import Finding

#: A period moves when its first-harmonic amplitude exceeds this many times the amplitude noise alone gives.
ONSET_SNR = 10.0


def amplitude_noise(a) -> float:
    """Standard deviation (trace units) of one period's first-harmonic amplitude from white noise alone:
    a least-squares cos/sin pair over L samples has variance 2 sigma^2 / L per coefficient."""
    return float(a.noise_rms * math.sqrt(2.0 / max(a.L, 1)))


def moving_blocks(a) -> np.ndarray:
    """bool per block of an :class:`afmid.io.trace_analysis.Analysis`: the oscillation stands above the noise."""
    return a.block_amplitude > ONSET_SNR * amplitude_noise(a)


def find_onset(a) -> int | None:
    """The first block of the oscillation after a record that starts at rest, or None (no quiet start).

    Only a quiet start counts: the blocks before the last quiet one of the
    leading run. A record that moves from its first period has no onset.
    """
    moving = moving_blocks(a)
    if moving.size < 3 or moving[0] or not moving.any():
        return None
    first = int(np.argmax(moving))
    return first if moving[first:].all() else None


def check_onset(a, settings) -> list[Finding]:
    """A quiet start: where the drive starts and from where a fit uses the record (``numbers['sample']``: the
    start of the second period after the first one that moves, so that the drive is on in every fitted sample:
    a period's amplitude can rise above the noise with the motion that starts early in the next one, as the
    per-period fits reach slightly beyond their period)."""
    first = find_onset(a)
    if first is None:
        return []
    sample = int(a.start + (first + 2) * a.L)
    rate = settings.sample_rate
    when = f" (t = {sample / rate * 1e6:.4g} us)" if rate else ""
    return [Finding(
        "onset", "warning",
        f"the cantilever rests for the first {first} periods and the oscillation starts in period {first + 1} of "
        f"{a.n_blocks} (the drive switched on mid-record): the fit uses the record from sample {sample}{when} on, "
        "where the drive is on throughout (set data.start to choose another start)",
        "data.start", {"block": first, "sample": sample})]


def crop(trace, first: int, stop: int | None = None):
    """``trace`` (an :class:`afmid.io.trace.Trace`) cut to samples ``first``..``stop`` (its own indices), as a new
    trace: deflection, time column and simulator truth alike; ``first_sample`` keeps the file's time base."""
    stop = trace.n_samples if stop is None else stop
    part = slice(first, stop)
    truth = trace.truth
    if truth is not None:
        truth = dataclasses.replace(truth, force=truth.force[part], separation=truth.separation[part],
                                    velocity=truth.velocity[part])
    return dataclasses.replace(
        trace, deflection=trace.deflection[part], time=None if trace.time is None else trace.time[part],
        truth=truth, first_sample=trace.first_sample + first, findings=[], drive=None)


def sample_index(trace, seconds: float) -> int:
    """The first sample at or after ``seconds`` from the trace's first sample (s)."""
    if trace.time is not None:
        return int(np.searchsorted(trace.time - trace.time[0], seconds - 1e-12 / trace.sample_rate))
    return int(math.ceil(seconds * trace.sample_rate - 1e-9))

