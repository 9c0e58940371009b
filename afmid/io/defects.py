"""Defects of measured traces: detection, a one-line explanation, and what to do.

Real deflection traces have problems that simulated ones do not. Each check
here is a plain function that returns :class:`Finding` objects (name,
severity, one-line message, the config key it is about, the numbers behind
it). They are run by :func:`afmid.io.trace.load_trace` / :func:`afmid.io.trace.check_trace`
(errors stop the run as an :class:`~afmid.errors.InputError` naming the file
and key; warnings are logged) and listed by ``afmid inspect``.

Severities:

- ``error``: the trace cannot be fitted as it is; the message says what to do.
- ``warning``: the fit can run but its result is doubtful, or a setting is recommended.
- ``repaired``: a harmless defect that the run's settings already remove
  (an offset with ``fit.baseline: free``, a drift with ``fit.detrend: linear``,
  a drive frequency off the nominal one: the fit uses the measured one).

Offset and drift are never changed silently: the data are passed on as they
are, and the message recommends the ``fit.detrend`` / ``fit.baseline`` setting
that removes the defect. Once that setting is in the config the finding is
reported as ``repaired`` (the fit does the removal).

The signal checks work in samples, not seconds, so they also run on files
without a sample rate (``afmid inspect``). They share one analysis
(:func:`afmid.io.trace_analysis.analyse`, on the engine the fit uses too,
:mod:`afmid.preprocess.harmonics`): per-period amplitude, phase and mean, the harmonics
with their noise, and the model-free force shape. For a loaded trace it runs at
the drive frequency as the fit measures it, measured here once and carried on
the trace (:func:`check_loaded`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from afmid.errors import InputError
from afmid.io.findings import SEVERITIES, Finding, frequency, length, yaml_number  # noqa: F401 (re-exported)
from afmid.io.time_column import TIME_JITTER, check_time  # noqa: F401 (re-exported: the checks on load)
from afmid.preprocess.harmonics import (  # the engine the fit uses too
    DRIVE_SEARCH,
    MIN_SAMPLES_PER_PERIOD,
    MeasuredDrive,
    amplitude_change,
    estimate_drive,
    measure_frequency,
    strongest_peak,
    changes_like_a_transient,
)
from afmid.io.glitches import check_glitches
from afmid.io.oscillation import check_drive_line
from afmid.io.onset import check_build_up, check_onset, jump_check_start
from afmid.preprocess.periods import detrend
from afmid.io.resolution import check_quantization
from afmid.io.trace_analysis import MAX_HARMONIC, MIN_ANALYSABLE_SPP, Analysis, analyse
from afmid.physics.effects import BOLTZMANN

log = logging.getLogger(__name__)

#: Samples per drive period each time-domain differentiator needs (others: MIN_SAMPLES_PER_PERIOD).
#: central: finite differences amplify noise unless sampled far above the drive (its registry note);
#: savgol: the default window (spp / 10, odd, >= 5) must exceed the polynomial order 4 by 3 to smooth.
DIFFERENTIATOR_MIN_SPP = {"central": 500.0, "savgol": 60.0}
#: Below this relative difference the measured and nominal drive frequencies agree.
DRIVE_TOLERANCE = 1e-3
#: An offset is reported when the mean deflection exceeds both this fraction of the amplitude ...
OFFSET_FRACTION = 0.02
#: ... and this multiple of the interaction force range / k (the largest mean a tip-sample force explains).
OFFSET_FORCE_MULTIPLE = 3.0
#: A drift is reported when it exceeds this fraction of the amplitude over the trace and is significant.
DRIFT_FRACTION = 2e-3
DRIFT_SIGMA = 5.0
#: A phase step counts as a jump above this many robust standard deviations and half a sample.
JUMP_SIGMA = 8.0
#: ... and above this many standard deviations of the thermal phase noise (a known scale, not estimated).
THERMAL_JUMP_SIGMA = 5.0
#: A phase step whose amplitude change stands out of the amplitude's noise by this many (robust) standard
#: deviations and is at least this fraction of the step's turn is the lever's motion (an orbit), not dropped or
#: repeated samples (:func:`steps_with_the_amplitude`). A dropped sample at the phase threshold (8 sigma), noise
#: alone in its amplitude, passes both with a probability of about 1 % (3 sigma in the largest of the three or
#: four two-block changes around the step); a larger step needs a larger amplitude change.
ORBIT_AMPLITUDE_SIGMA = 3.0
ORBIT_AMPLITUDE_FRACTION = 0.25


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start indices and lengths of the runs of True in ``mask``."""
    padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    starts, ends = edges[0::2], edges[1::2]
    return starts, ends - starts


def longest_clean(mask_bad: np.ndarray) -> tuple[int, int]:
    """(start, length) of the longest stretch without a bad sample."""
    starts, lengths = _runs(~mask_bad)
    if lengths.size == 0:
        return 0, 0
    i = int(np.argmax(lengths))
    return int(starts[i]), int(lengths[i])


# --------------------------------------------------------------------------- samples and time
def check_values(values: np.ndarray, spp: float | None = None) -> list[Finding]:
    """NaN/inf samples (runs of them: dropouts, overflow). An error: the trace must be cropped."""
    bad = ~np.isfinite(values)
    if not bad.any():
        return []
    starts, lengths = _runs(bad)
    first = int(starts[0])
    clean_start, clean_len = longest_clean(bad)
    longest = int(np.argmax(lengths))
    periods = f", {clean_len / spp:.1f} periods" if spp else ""
    message = (
        f"{int(bad.sum())} NaN/inf samples in the deflection (first at sample {first}) in {len(starts)} "
        f"run{'s' if len(starts) > 1 else ''} (longest {int(lengths[longest])} samples from sample "
        f"{int(starts[longest])}); crop the trace to a clean part (the longest is samples "
        f"{clean_start}-{clean_start + clean_len - 1}{periods}) before fitting"
    )
    numbers = {"n_bad": int(bad.sum()), "first": first, "runs": len(starts), "longest_run": int(lengths[longest]),
               "clean_start": clean_start, "clean_length": clean_len}
    return [Finding("nan", "error", message, "data.column", numbers)]


# --------------------------------------------------------------------------- signal checks
@dataclass
class Settings:
    """What the checks need to know about the run (all optional: ``afmid inspect`` has no config)."""

    units: str | None = "m"  # units of the samples ('m' for a loaded trace)
    sample_rate: float | None = None  # Hz
    nominal_frequency: float | None = None  # Hz (drive.frequency or the trace file's)
    resonance_frequency: float | None = None  # Hz
    quality_factor: float | None = None
    spring_constant: float | None = None  # N/m
    detrend: str = "none"  # fit.detrend
    baseline: str = "zero"  # fit.baseline
    differentiation: str | None = None  # fit.differentiation when the fit differentiates (fit.form: strong)
    positive: str | None = None  # data.positive of the run (None: not chosen yet)
    temperature: float = 300.0  # K, the lever's (fit.temperature; room temperature without a config)


def settings_for(trace, config) -> Settings:
    """Settings for a loaded :class:`afmid.io.trace.Trace` and its run config (or the record's sections alone,
    :class:`afmid.io.sections.RecordSections`, whose ``fit`` is None: then :class:`Settings`' own defaults, which
    are the fit section's, tests/io/test_record_sections.py)."""
    fit = config.fit
    lever = dict(units="m", sample_rate=trace.sample_rate, nominal_frequency=trace.drive_frequency,
                 resonance_frequency=trace.cantilever.resonance_frequency,
                 quality_factor=trace.cantilever.quality_factor, spring_constant=trace.cantilever.spring_constant,
                 positive=config.data.positive)
    if fit is None:
        return Settings(**lever)
    return Settings(
        **lever,
        detrend=fit.detrend,
        baseline=fit.baseline,
        differentiation=fit.differentiation if fit.form == "strong" else None,
        temperature=fit.temperature,
    )


def analyse_with(x: np.ndarray, settings: Settings, cycles_per_sample: float | None = None) -> Analysis | None:
    """:func:`analyse` with the resonance ratio and Q from ``settings`` (when known).

    ``cycles_per_sample``: the oscillation frequency when already measured (else the strongest one).
    """
    f = measure_frequency(x) if cycles_per_sample is None else cycles_per_sample
    if f is None:
        return None
    r = None
    if settings.sample_rate and settings.resonance_frequency:
        r = f * settings.sample_rate / settings.resonance_frequency
    # The lever's thermal motion: on a soft lever in liquid (k 0.8 N/m: 72 pm rms) it makes the periods differ by a
    # few % of the amplitude, which is neither chaos nor a transient.
    return analyse(x, r, settings.quality_factor, cycles_per_sample=f, thermal_variance=thermal_variance(settings))


def thermal_variance(settings: Settings) -> float:
    """The lever's thermal deflection variance k_B T / k in the samples' units squared (m^2), 0 where unknown
    (no spring constant, or samples not in metres)."""
    if settings.units == "m" and settings.spring_constant:
        return BOLTZMANN * settings.temperature / settings.spring_constant
    return 0.0


def check_signal(x: np.ndarray, settings: Settings, analysis: Analysis | None = None) -> list[Finding]:
    """Every check on the samples themselves (not NaN, not the time column), in order of importance."""
    x = np.asarray(x, dtype=np.float64)
    if analysis is None:
        analysis = analyse_with(x, settings)

    findings: list[Finding] = []
    findings += check_clipping(x, analysis, settings)
    findings += check_quantization(x)
    if analysis is None:
        findings += _unanalysable(x, settings)
        findings += check_sampling(None, settings)
        return check_drive_line(x, settings) + findings
    findings += check_drive_frequency(analysis, settings)
    findings += check_sampling(analysis, settings)
    findings += check_onset(analysis, settings)
    build_up = check_build_up(analysis, settings, smallest_jump(analysis, settings))
    findings += build_up
    findings += check_jumps(analysis, settings)
    findings += check_steady(analysis, settings)
    findings += check_offset_and_drift(analysis, settings)
    findings += check_contact(analysis, settings)
    findings += check_glitches(x, analysis, settings.units,  # edge transients (not a build-up from rest), glitches
                               head_is_motion=any(f.numbers["first_block"] == 0 for f in build_up))
    strongest = analysis.cycles_per_sample * settings.sample_rate if settings.sample_rate else None
    return check_drive_line(x, settings, strongest) + findings  # the first error is the one reported


def _unanalysable(x: np.ndarray, settings: Settings) -> list[Finding]:
    f = measure_frequency(x)
    if f is None:
        if np.ptp(x) == 0:
            return [Finding("no_oscillation", "error",
                            "the deflection is constant: no oscillation to analyse (wrong channel? check data.column)",
                            "data.column")]
        return [Finding("no_oscillation", "warning",
                        "no oscillation found (fewer than 3 cycles in the trace?); the checks were skipped",
                        "data.column")]
    spp = 1.0 / f
    if spp < MIN_ANALYSABLE_SPP:
        return [Finding("undersampled", "warning",
                        f"the strongest oscillation has only {spp:.2f} samples per period: the signal is far "
                        "undersampled or this is not a deflection channel (check data.column); the checks were skipped",
                        "data.column", {"samples_per_period": spp})]
    return [Finding("too_short", "warning",
                    f"only {x.size / spp:.2f} periods of the oscillation: too short for the checks",
                    "data.path", {"periods": x.size / spp})]


def check_clipping(x: np.ndarray, analysis: Analysis | None, settings: Settings) -> list[Finding]:
    """Flat tops or bottoms at the extreme values: the detector or the ADC saturated. An error.

    Noise makes consecutive samples of a real peak differ; a run of identical
    extreme samples longer than quantisation explains (the samples within one
    ADC step of a sinusoid's peak) means the signal was cut off.
    """
    if x.size < 8:
        return []
    hi, lo = float(x.max()), float(x.min())
    span = hi - lo
    if span <= 0:
        return []
    values = np.unique(x[: min(x.size, 200_000)])
    steps = np.diff(values)
    q = float(steps[steps > 0].min()) if np.any(steps > 0) else span
    quantised = q > 1e-6 * span
    spp = analysis.spp if analysis is not None else None
    amplitude = analysis.amplitude if analysis is not None and analysis.amplitude > 0 else span / 2
    natural = 1.0
    if quantised and spp:
        natural += spp / math.pi * math.sqrt(2 * min(q / amplitude, 1.0))
    minimum = max(4, int(math.ceil(2 * natural)) + 2)
    findings = []
    tol = 1e-9 * span
    for side, level, mask in (("maximum", hi, x >= hi - tol), ("minimum", lo, x <= lo + tol)):
        starts, lengths = _runs(mask)
        if lengths.size == 0 or lengths.max() < minimum:
            continue
        long_runs = int(np.sum(lengths >= minimum))
        count = int(lengths[lengths >= 2].sum())
        where = "tops" if side == "maximum" else "bottoms"
        findings.append(Finding(
            "clipping", "error",
            f"the deflection is clipped: flat {where} at the {side} {length(level, settings.units)} "
            f"({long_runs} run{'s' if long_runs > 1 else ''} of up to {int(lengths.max())} identical samples, "
            f"{count} samples in all, the first at sample {int(starts[np.argmax(lengths >= minimum)])}): the detector "
            "or the ADC saturated; record again with a lower gain or amplitude, or crop to unclipped periods",
            "data.column",
            {"level": level, "longest_run": int(lengths.max()), "runs": long_runs, "samples": count,
             "first": int(starts[np.argmax(lengths >= minimum)])}))
    return findings


def check_drive_frequency(a: Analysis, s: Settings) -> list[Finding]:
    """The measured oscillation against the nominal drive frequency.

    Outside the fit's search band (+-5 %) it is an error; a smaller
    difference is 'repaired' (the fit uses the measured value).
    """
    if not (s.sample_rate and s.nominal_frequency):
        return []
    measured = a.cycles_per_sample * s.sample_rate
    rel = measured / s.nominal_frequency - 1.0
    numbers = {"measured": measured, "nominal": s.nominal_frequency, "relative": rel}
    if abs(rel) > DRIVE_SEARCH:
        return [Finding(
            "drive_frequency", "error",
            f"the deflection oscillates at {frequency(measured)}, {100 * rel:+.1f} % from the nominal drive "
            f"frequency {frequency(s.nominal_frequency)}; the fit searches only within {100 * DRIVE_SEARCH:.0f} % "
            f"of it: set drive.frequency: {yaml_number(float(f'{measured:.6g}'))} (or check data.sample_rate)",
            "drive.frequency", numbers)]
    if abs(rel) > DRIVE_TOLERANCE:
        return [Finding(
            "drive_frequency", "repaired",
            f"the drive frequency measured from the data, {frequency(measured)}, differs from the nominal "
            f"{frequency(s.nominal_frequency)} by {100 * rel:+.2f} %; the fit uses the measured value",
            "drive.frequency", numbers)]
    return []


def check_sampling(a: Analysis | None, s: Settings) -> list[Finding]:
    """Too few samples per period for the differentiation, or harmonics cut off at Nyquist (aliasing)."""
    findings = []
    # The nominal samples per period when known (the rate and drive the user gave), else the measured one.
    spp = s.sample_rate / s.nominal_frequency if s.sample_rate and s.nominal_frequency else None
    if a is not None and (spp is None or abs(a.spp / spp - 1) > DRIVE_SEARCH):
        spp = a.spp
    if spp is None:
        return []
    method = s.differentiation
    need = DIFFERENTIATOR_MIN_SPP.get(method or "", MIN_SAMPLES_PER_PERIOD)
    rate = f" (at least {frequency(need / spp * s.sample_rate)})" if s.sample_rate else ""
    if method and need > MIN_SAMPLES_PER_PERIOD and spp < need:
        findings.append(Finding(
            "sampling", "error",
            f"{method} differentiation needs at least {need:g} samples per drive period, the trace has "
            f"{spp:.1f}: use fit.form: weak (no derivatives of the data) or fit.differentiation: spectral, or record at a "
            f"higher rate{rate}",
            "fit.differentiation", {"samples_per_period": spp, "needed": need}))
    elif spp < MIN_SAMPLES_PER_PERIOD:
        findings.append(Finding(
            "sampling", "warning",
            f"only {spp:.1f} samples per drive period (< {MIN_SAMPLES_PER_PERIOD}): the sample rate is too low to "
            "resolve the motion well",
            "data.sample_rate", {"samples_per_period": spp, "needed": MIN_SAMPLES_PER_PERIOD}))
    if a is not None and a.K < MAX_HARMONIC and a.K >= 3 and a.above_noise and max(a.above_noise) >= a.K - 1:
        wanted = max(2.0 * spp, MIN_SAMPLES_PER_PERIOD)
        rate = f", at least {frequency(wanted / spp * s.sample_rate)}" if s.sample_rate else ""
        findings.append(Finding(
            "aliasing", "warning",
            f"harmonics up to the highest one the sampling resolves (n = {a.K} at {spp:.1f} samples per period) "
            f"stand above the noise: higher harmonics fold back (aliasing) and bias the force; record at "
            f"{wanted / spp:.2g} x the sample rate or more{rate}",
            "data.sample_rate", {"samples_per_period": spp, "highest_harmonic": a.K}))
    return findings


def check_jumps(a: Analysis, s: Settings | None = None) -> list[Finding]:
    """Phase steps between periods: dropped or repeated samples (or a re-locked drive). An error.

    With the lever known (``s``: spring constant and Q), a step must also stand out of the thermal phase
    noise (:func:`thermal_phase_step`): on a soft lever in liquid it is ~1 deg per period, a sample's worth.
    A step whose amplitude steps with it is the lever's own motion, a period-n orbit, and no defect
    (:func:`steps_with_the_amplitude`).
    """
    # Before the onset the phase is that of noise, and a fast build-up from rest settles its phase: both are left.
    first = jump_check_start(a, s.quality_factor if s else None, smallest_jump(a, s))
    B = a.n_blocks - first
    if B < 9:
        return []
    trend, path, trend_radial, path_radial = change_residuals(a.block_amplitude[first:], a.block_phase[first:])
    by_path = np.abs(path) < np.abs(trend)
    res = np.where(by_path, path, trend)  # what neither model of smooth motion explains
    radial = np.minimum(np.abs(path_radial), np.abs(trend_radial))  # the amplitude's change neither explains
    mad = float(np.median(np.abs(trend - np.median(trend))))
    one = 2 * np.pi / a.spp  # phase of one sample
    threshold = max(smallest_jump(a, s), JUMP_SIGMA * 1.4826 * mad)
    hits = np.flatnonzero(np.abs(res) > threshold)
    if hits.size == 0:
        return []
    groups = np.split(hits, np.flatnonzero(np.diff(hits) > 2) + 1)
    amplitude_noise = max(1.4826 * float(np.median(np.abs(radial - np.median(radial)))),
                          thermal_phase_step(s, float(np.median(a.block_amplitude))))
    # A step between two blocks changes the two two-block differences that span it; a hit may be only one of them.
    around = [np.arange(max(g[0] - 1, 0), min(g[-1] + 2, radial.size)) for g in groups]
    groups = [g for g, near in zip(groups, around)
              if not steps_with_the_amplitude(res[g], radial[near], amplitude_noise)]
    if not groups:
        return []
    peaks = [int(g[np.argmax(np.abs(res[g]))]) for g in groups]
    sizes = [float(res[p] / one) for p in peaks]
    sample = a.start + (first + peaks[0] + 1) * a.L + a.L // 2  # the middle of the period the jump falls in
    kind = "dropped" if sizes[0] > 0 else "repeated"
    return [Finding(
        "phase_jump", "error",
        f"the oscillation phase jumps by {np.degrees(res[peaks[0]]):+.3g} deg ({sizes[0]:+.2g} samples) near "
        f"sample {sample} (period {sample / a.spp:.0f} of {a.periods:.0f})"
        f"{f' and at {len(peaks) - 1} more places' if len(peaks) > 1 else ''}: "
        f"samples were {kind} (or the drive was re-locked); crop the trace to one side of the jump",
        "data.path", {"jumps": len(peaks), "first_sample": sample, "samples": sizes[0]})]


def steps_with_the_amplitude(turn: np.ndarray, radial: np.ndarray, amplitude_noise: float) -> bool:
    """Whether a phase step (``turn``: its unexplained turns, rad; ``radial``: the unexplained relative amplitude
    changes of the two-block changes around it, 1) is the lever's own motion rather than a sampling defect.

    Dropped or repeated samples shift the record in time: every later period keeps the step, and the amplitude
    is untouched (a block holding the step has its first harmonic shortened by at most 1 - cos(step / 2), about
    step^2 / 8, of the amplitude: a ratio step / 8 to the turn, 0.04 for one sample at 20 samples per period). A
    meniscus that forms on some taps only takes energy on those taps: the phase steps there and ramps back within
    the orbit's period, and the amplitude steps with it (0.4-0.7 of the turn on the grazing orbits measured,
    docs/coverage.md). So a step is the motion's when its amplitude change stands out of the amplitude's own
    noise (:data:`ORBIT_AMPLITUDE_SIGMA` x ``amplitude_noise``, a relative 1 sigma), is at least
    :data:`ORBIT_AMPLITUDE_FRACTION` of the turn, and at least 4x what a time shift of that size makes."""
    k = int(np.argmax(np.abs(turn)))
    step = abs(float(turn[k]))
    change = float(np.max(np.abs(radial)))
    return change > max(ORBIT_AMPLITUDE_SIGMA * amplitude_noise, ORBIT_AMPLITUDE_FRACTION * step, step**2 / 2)


def smallest_jump(a: Analysis, s: Settings | None) -> float:
    """The smallest phase step (rad) :func:`check_jumps` reports: half a sample, and out of the thermal noise."""
    thermal = THERMAL_JUMP_SIGMA * thermal_phase_step(s, float(np.median(a.block_amplitude)))
    return max(np.pi / a.spp, thermal)


#: Offsets (blocks) of the neighbours that predict a two-block change; -1..1 are left out, since samples
#: dropped inside block m change the two-block differences centred on m-1, m and m+1.
_NEIGHBOURS = np.array([-5, -4, -3, -2, 2, 3, 4, 5])


def rotation_residuals(amplitude: np.ndarray, phase: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How much each block's oscillation turns beyond what smooth motion explains (rad at the median amplitude),
    for the two-block changes centred on blocks 1..B-2, by two models of smooth motion.

    Dropped or repeated samples turn the oscillation's complex amplitude c = A exp(i phase) by their phase, at
    whatever amplitude; smooth motion does not step. Returned:

    - ``trend``: the two-block phase change weighted by the block's amplitude over the median one (an arc)
      minus its running median of 7. A phase ramp or a change of regime (the tip starting or ceasing to touch:
      a kink) leaves nothing; for a steady record it is the phase change minus the local trend.
    - ``path``: the two-block change of c minus a quadratic through its neighbours at offsets 2..5 on both sides
      (which a step leaves untouched), its part perpendicular to c over the median amplitude. A transient from
      free oscillation carries c past the origin on a smooth path (the phase alone swings by up to 180 deg
      in a few periods) and leaves nothing here. Within 5 blocks of either end it is ``trend``.

    A step stands out of both; smooth motion out of at most one.
    """
    trend, path, _, _ = change_residuals(amplitude, phase)
    return trend, path


def change_residuals(amplitude: np.ndarray, phase: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(trend, path, trend_radial, path_radial): :func:`rotation_residuals`' two residuals of the turn and their
    radial counterparts, the same two models' residuals of the change of the amplitude (relative to the median
    amplitude, 1): ``trend_radial`` the two-block relative amplitude change minus its running median of 7,
    ``path_radial`` the part of the unexplained change of c along c. A dropped sample turns c and leaves its
    length; the lever's own motion (an orbit in which a meniscus forms on some taps) changes both."""
    from scipy.ndimage import median_filter

    typical = max(float(np.median(amplitude)), 1e-300)
    arc = (phase[2:] - phase[:-2]) * amplitude[1:-1] / typical
    trend = arc - median_filter(arc, size=7, mode="nearest")
    stretch = (amplitude[2:] - amplitude[:-2]) / typical
    trend_radial = stretch - median_filter(stretch, size=7, mode="nearest")
    path, path_radial = trend.copy(), trend_radial.copy()
    c = amplitude * np.exp(1j * phase)
    change, centre = c[2:] - c[:-2], c[1:-1]
    inner = np.arange(_NEIGHBOURS.max(), change.size - _NEIGHBOURS.max())
    if inner.size:
        design = np.vander(_NEIGHBOURS.astype(float), 3)  # quadratic in the offset
        predict_at_zero = np.linalg.pinv(design)[-1]  # weights of the neighbours for the fit's value at 0
        expected = change[inner[:, None] + _NEIGHBOURS] @ predict_at_zero
        turned = (change[inner] - expected) * np.conj(centre[inner]) / np.maximum(np.abs(centre[inner]), 1e-300)
        path[inner] = turned.imag / typical
        path_radial[inner] = turned.real / typical
    return trend, path, trend_radial, path_radial


def thermal_phase_step(s: Settings | None, amplitude: float) -> float:
    """Standard deviation (rad) of the phase change across two periods that the thermal force alone makes.

    The quadrature part of the thermal motion has variance kT / (2k) (T: ``s.temperature``) and forgets itself in
    the amplitude decay time (Q / pi periods); over two periods the phase x_perp / A then changes with variance
    2 (kT / (2 k A^2)) (1 - exp(-2 pi * 2 / Q)). Negligible for a lever in air (Q 250, k 40 N/m: 0.01 deg);
    ~0.8 deg for a soft lever in water (k 0.8 N/m, Q 4, A 5 nm). 0 when the lever is unknown.
    """
    if s is None or not s.spring_constant or not s.quality_factor or not amplitude > 0:
        return 0.0
    variance = BOLTZMANN * s.temperature / (s.spring_constant * amplitude**2) * (1.0 - math.exp(-4.0 * math.pi / s.quality_factor))
    return math.sqrt(variance)


def check_steady(a: Analysis, s: Settings) -> list[Finding]:
    """Amplitude still changing (a transient): a warning; the fit searches the drive frequency (afmid.fit.drive_search)."""
    amp = a.block_amplitude
    B = amp.size
    if B < 3 or amp.mean() <= 0:
        return []
    if not changes_like_a_transient(amp, thermal_variance(s)):
        return []
    change = amplitude_change(amp)
    final = float(np.median(amp[-max(3, B // 5):]))
    outside = np.flatnonzero(np.abs(amp - final) > 0.01 * final)
    settled = int(outside[-1]) + 1 if outside.size else 0
    if settled <= B - 3:
        advice = (f"crop the first {settled} periods (the amplitude stays within 1 % of its final value from "
                  f"period {settled} on)")
    else:
        advice = "record after the amplitude has settled"
    return [Finding(
        "not_steady", "warning",
        f"the oscillation amplitude changes by {100 * change:.1f} % over the trace (from "
        f"{length(amp[0], s.units)} to {length(amp[-1], s.units)}): not in steady state; the fit takes the drive "
        f"frequency from the regression (fit.drive_frequency: auto), but per-period results mix different states: "
        f"{advice}",
        "data.path", {"change": change, "settled_period": settled, "first": float(amp[0]), "last": float(amp[-1])})]


def check_offset_and_drift(a: Analysis, s: Settings) -> list[Finding]:
    """A mean deflection beyond what tip-sample forces explain, and a slow linear drift of it.

    Never changed here: the message recommends the setting that removes it,
    and with that setting in the config the finding is 'repaired'.
    """
    findings = []
    B = a.n_blocks
    t = np.arange(B, dtype=float)
    means = a.block_mean
    drift = 0.0
    steady = not check_steady(a, s)
    if B >= 5 and steady:
        slope, intercept = np.polyfit(t, means, 1)
        resid = means - (slope * t + intercept)
        se = float(np.sqrt(np.sum(resid**2) / (B - 2) / np.sum((t - t.mean()) ** 2)))
        drift = float(slope * B)
        significant = abs(slope) > DRIFT_SIGMA * se if se > 0 else slope != 0
        if significant and abs(drift) > DRIFT_FRACTION * a.amplitude:
            numbers = {"drift": drift, "per_period": float(slope), "amplitude": a.amplitude}
            what = (f"the mean deflection drifts by {length(drift, s.units)} over the trace "
                    f"({100 * abs(drift) / a.amplitude:.2g} % of the amplitude; detector or thermal drift)")
            if s.detrend == "linear":
                findings.append(Finding("drift", "repaired", f"{what}; fit.detrend: linear removes it",
                                        "fit.detrend", numbers))
            else:
                findings.append(Finding(
                    "drift", "warning",
                    f"{what}: the fit would read it as a slowly changing force; set fit.detrend: linear "
                    "(the fit then estimates the drift with the force law)", "fit.detrend", numbers))
    offset = a.mean
    if mean_stands_out(a):
        numbers = {"offset": offset, "amplitude": a.amplitude, "limit": offset_limit(a)}
        what = (f"the mean deflection is {length(offset, s.units)} ({100 * abs(offset) / a.amplitude:.2g} % of the "
                "amplitude), more than tip-sample forces explain: the detector zero is off")
        if a.contact == "none":
            # No harmonic out of the noise: nothing bounds the force, and a force that barely changes over the
            # oscillation (a double layer as long as the amplitude on a soft lever in liquid) holds the lever
            # off zero by its mean / k (k x = F on average: the zeroth harmonic of the equation of motion).
            what = (f"the mean deflection is {length(offset, s.units)} ({100 * abs(offset) / a.amplitude:.2g} % of "
                    f"the amplitude) and no harmonic of the oscillation stands above the noise: either a force that "
                    f"barely changes over the oscillation holds the lever{_static_force_words(offset, s)}, or the "
                    "detector zero is off")
        if s.baseline == "free":
            findings.append(Finding("offset", "repaired", f"{what}; fit.baseline: free absorbs it", "fit.baseline",
                                    numbers))
        elif s.detrend == "offset":  # (linear estimates a drift about the record's centre, no offset)
            findings.append(Finding("offset", "repaired", f"{what}; fit.detrend: {s.detrend} removes it "
                                    "(fit.baseline: free would keep the mean force)", "fit.detrend", numbers))
        else:
            when = "if the zero was not set with the tip far from the sample, " if a.contact == "none" else ""
            findings.append(Finding(
                "offset", "warning",
                f"{what}; {when}set fit.baseline: free (or data.offset to the free-oscillation mean, in file units)",
                "fit.baseline", numbers))
    return findings


def offset_limit(a: Analysis) -> float:
    """The largest mean deflection not reported as an offset (samples' units): :data:`OFFSET_FRACTION` of the
    amplitude or :data:`OFFSET_FORCE_MULTIPLE` times the force range the harmonics show, whichever is larger."""
    return max(OFFSET_FRACTION * a.amplitude, OFFSET_FORCE_MULTIPLE * a.force_range)


def mean_stands_out(a: Analysis) -> bool:
    """The mean deflection lies beyond :func:`offset_limit` (an oscillation to compare it with): the offset's
    finding is made."""
    return a.amplitude > 0 and abs(a.mean) > offset_limit(a)


def _static_force_words(offset: float, s: Settings) -> str:
    """' (k x = 0.104 nN, repulsive)': the mean force a mean deflection ``offset`` (m) stands for, where k is
    known (positive deflection is toward the sample: a lever held away feels a repulsion)."""
    if s.units != "m" or not s.spring_constant:
        return ""
    force = -s.spring_constant * offset  # N, positive = repulsive
    return (f" (k x = {abs(force) * 1e9:.3g} nN, {'repulsive' if force > 0 else 'attractive'}: a long-range force "
            "such as a double layer or electrostatics)")


def check_contact(a: Analysis, s: Settings) -> list[Finding]:
    """No tip-sample force at all, or an attractive one only (the tip never touches): warnings.

    Needs at least :data:`MIN_SAMPLES_PER_PERIOD` samples per period to see the harmonics. Without harmonics but
    with a mean deflection beyond :func:`offset_limit`, the offset's finding says it all (a static force or a
    detector zero that is off): "no tip-sample force" would contradict its first half.
    """
    if a.spp < MIN_SAMPLES_PER_PERIOD:
        return []
    if a.contact == "none" and mean_stands_out(a):
        return []
    if a.contact == "none":
        return [Finding(
            "no_interaction", "warning",
            f"no tip-sample force detected: no harmonic of the oscillation stands above the noise "
            f"({length(a.noise_rms, s.units)} rms), so the tip oscillates freely and does not reach the sample (or "
            "its force is below the noise); nothing can be identified: approach the sample, or check data.path and "
            "data.column",
            "data.path", {"noise_rms": a.noise_rms})]
    numbers = {"harmonics": len(a.above_noise), "force_range_over_k": a.force_range}
    if a.contact == "attractive":
        return [Finding(
            "no_contact", "warning",
            "the tip never touches the sample: the force is most attractive at the closest approach (attractive "
            "regime); only the long-range part can be identified, contact terms (dmt, jkr, viscoelastic) are not "
            "constrained by these data",
            "model.effects", numbers)]
    if a.flipped:
        if s.positive is None:
            fix = "the file's deflection is probably positive away from the sample; set data.positive: away_from_sample"
        else:
            other = "away_from_sample" if s.positive == "toward_sample" else "toward_sample"
            fix = f"with data.positive: {s.positive} the deflection has the wrong sign; set data.positive: {other}"
        return [Finding(
            "sign", "warning", f"the tip-sample interaction happens at the most negative deflection: {fix}",
            "data.positive", numbers)]
    return []


# --------------------------------------------------------------------------- loaded traces
def check_loaded(trace, config) -> tuple[list[Finding], MeasuredDrive | None]:
    """The signal checks for a loaded trace (SI, positive toward the sample) with its config, and its drive.

    The drive is measured once, here, as the fit measures it
    (:func:`afmid.preprocess.harmonics.estimate_drive` of the deflection detrended with
    fit.detrend, searched within :data:`DRIVE_SEARCH` of the nominal frequency),
    when the strongest oscillation lies in that band; the checks then analyse
    the trace at that frequency and the fit reuses it (:meth:`afmid.io.trace.Trace.drive_for`).
    Otherwise (no oscillation, or one far from the nominal drive: an error for the
    fit) the checks use the strongest oscillation and the drive is None.
    """
    settings = settings_for(trace, config)
    x = np.asarray(trace.deflection, dtype=np.float64)
    peak = strongest_peak(x)
    drive = None
    if peak is not None and abs(peak.cycles_per_sample * trace.sample_rate / trace.drive_frequency - 1) <= DRIVE_SEARCH:
        drive = measure_drive(trace, settings.detrend)
    if drive is not None:
        f = drive.estimate.frequency / trace.sample_rate
    else:
        f = None if peak is None else peak.refine()
    analysis = None if f is None else analyse_with(x, settings, f)
    return check_signal(x, settings, analysis), drive


def measure_drive(trace, detrend_mode: str) -> MeasuredDrive | None:
    """The fit's drive measurement of a loaded trace (deflection detrended with ``detrend_mode``), None if none.

    The same samples, times and estimator as :func:`afmid.fit.prepare.prepare`, so the
    fit can use the result in place of measuring again.
    """
    t = trace.times
    x, _ = detrend(trace.deflection, t, detrend_mode)
    try:
        estimate = estimate_drive(x, t, trace.drive_frequency)
    except InputError:  # no oscillation in the band: the checks say why, the fit measures (and fails) itself
        return None
    return MeasuredDrive(estimate, detrend_mode, trace.deflection, trace.sample_rate, trace.time)


def report(findings: list[Finding], file, logger: logging.Logger | None = None) -> None:
    """Raise the first error as an InputError naming ``file`` and its key; else log the others.

    Warnings are logged as warnings, 'repaired' findings as information, each
    prefixed with the file.
    """
    logger = logger or log
    for finding in findings:
        if finding.severity == "error":
            raise InputError(finding.message, file=file, key=finding.key)
    for finding in findings:
        if finding.severity == "warning":
            logger.warning("%s: %s", file, finding.message)
        else:
            logger.info("%s: %s", file, finding.message)
