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

A record whose drive starts at its first sample (or at the onset) begins with the build-up from rest: the
lever's free response, started against the drive, rings down in Q / pi periods while the tip starts to touch and
the phase settles. On a lever of low Q (in liquid, Q 2-8) that takes a few periods, faster than the phase-jump
check's models of smooth motion follow: :func:`find_build_up` says how many periods of the build-up the check
must leave out (physics, not a defect); the fit uses them (its drive columns hold from the first sample).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from afmid.io.findings import Finding

#: A build-up from rest: the first checked period's amplitude lies at least this fraction below the settled one
#: (a period's amplitude scatters by 1-2 % with the thermal motion of a soft lever in liquid: 72 pm rms at 5 nm).
BUILD_UP_DEFICIT = 0.1
#: The phase-jump check's models of smooth motion reach this many periods either side (a quadratic through
#: neighbours 2..5 periods away; a running median of 7): a lever ringing down in Q / pi periods or more is
#: followed by them (measured: a Q 250 record from rest), a faster one is not (Q 2-8: steps of 5-25 deg read).
FOLLOWED_RING_DOWN = 5.0
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


@dataclasses.dataclass(frozen=True)
class BuildUp:
    """The build-up from rest at the start of the checked blocks: ``first`` (block where it starts), ``periods``
    (blocks from ``first`` until its rotation falls below the smallest step the phase-jump check reports),
    ``deficit`` (1 - the first block's amplitude over the settled one) and the lever's ``quality_factor``."""

    first: int
    periods: int
    deficit: float
    quality_factor: float


def find_build_up(a, quality_factor: float | None, smallest_step: float) -> BuildUp | None:
    """The build-up from rest of an :class:`afmid.io.trace_analysis.Analysis` whose lever (``quality_factor``)
    rings down faster than the phase-jump check follows, or None.

    It starts at the onset (+2 blocks, where a fit starts) or at block 0, when that block's amplitude lies
    :data:`BUILD_UP_DEFICIT` or more below the settled one (median of the last half). The free response that
    makes up the deficit decays as exp(-pi n / Q) per period and turns the oscillation's complex amplitude by at
    most its relative size (rad), so after n = Q / pi ln(deficit / ``smallest_step``) periods (``smallest_step``
    in rad) it turns less than any step the check reports; one period more for the block's own averaging.
    """
    if not quality_factor or quality_factor / math.pi > FOLLOWED_RING_DOWN:
        return None
    onset = find_onset(a)
    first = 0 if onset is None else onset + 2
    amplitude = a.block_amplitude[first:]
    if amplitude.size < 4:
        return None
    settled = float(np.median(amplitude[amplitude.size // 2:]))
    deficit = 1.0 - float(amplitude[0]) / settled if settled > 0 else 0.0
    if deficit < BUILD_UP_DEFICIT or smallest_step <= 0:
        return None
    periods = math.ceil(quality_factor / math.pi * math.log(deficit / smallest_step)) + 1
    return BuildUp(first, max(periods, 1), deficit, float(quality_factor))


def jump_check_start(a, quality_factor: float | None, smallest_step: float) -> int:
    """The first block the phase-jump check reads: after the quiet start (the onset + 2, where a fit starts) and
    after a fast build-up from rest (:func:`find_build_up`)."""
    build_up = find_build_up(a, quality_factor, smallest_step)
    if build_up is not None:
        return build_up.first + build_up.periods
    onset = find_onset(a)
    return 0 if onset is None else onset + 2


def check_build_up(a, settings, smallest_step: float) -> list[Finding]:
    """A warning saying what a fast build-up from rest changes: the phase-jump check starts after it, the fit
    uses the whole record (the transient is fitted). ``smallest_step``: rad, as for :func:`find_build_up`."""
    build_up = find_build_up(a, settings.quality_factor, smallest_step)
    if build_up is None:
        return []
    end = build_up.first + build_up.periods
    sample = int(a.start + end * a.L)
    checked = "" if a.n_blocks - end >= 9 else " (fewer than 9 periods remain: no phase-jump check)"
    return [Finding(
        "build_up", "warning",
        f"the oscillation builds up from rest over the first {build_up.periods} periods (Q {build_up.quality_factor:.3g}:"
        f" {100 * build_up.deficit:.0f} % below its settled amplitude at the start, a ring-down of "
        f"{build_up.quality_factor / math.pi:.2g} periods): the phase-jump check reads the record from sample "
        f"{sample} on{checked}, where the settling phase turns less than a step it reports; the fit uses the whole "
        "record (a transient from rest)",
        "data.start", {"first_block": build_up.first, "periods": build_up.periods, "sample": sample,
                       "deficit": build_up.deficit})]


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

