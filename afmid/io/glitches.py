"""Isolated glitches and edge transients: samples that leave the periodic motion for one or a few samples.

A real record can start with a sample from before the acquisition settled (the Bruker HSDC example: sample 0 is
0.012 V between neighbours at -0.369 V) or with a ramp of a filter switched on at the start (on a simulated
record a 10-sample ramp raised the fit's noise estimate 400-fold and moved the separation 2 nm), and a record
can hold an isolated spike. None of these is motion: each is found here and cut (at an edge) or replaced by the
periodic motion there (in the interior), with one finding saying which samples and what was done.

The test: each drive period's motion is predicted from its neighbours (the median of the per-period Fourier
coefficients of the two periods on either side, harmonics as :func:`afmid.io.trace_analysis.analyse` fits them),
so that a glitch does not predict itself and a slow change of the motion (a modulation, a drift) is followed. A
sample is an outlier when it leaves that prediction by more than :func:`threshold` robust standard deviations of
the residual (the Gaussian quantile for a false alarm of :data:`FALSE_ALARM` over the whole record, at least
:data:`MIN_SIGMA`). Tapping impacts repeat every period and so are in the prediction; whatever a period's
harmonics do not hold (the sharpest part of a stiff contact) repeats too: an outlier counts only when no other
outlier lies within one period on either side (isolated). Then:

- an isolated run of outliers that starts within the first (last) :data:`EDGE_SAMPLES` samples and ends within
  a quarter period of that edge is an edge transient: cut, up to the first sample back within
  :data:`SETTLED_SIGMA` of the prediction, unless ``data.start`` (``data.stop``) chooses the part to fit;
- an isolated run of at most :data:`MAX_GLITCH_RUN` samples inside is a glitch: replaced by the prediction;
- more glitches than :data:`MAX_GLITCHES_PER_PERIOD` per period (at least :data:`MIN_REFUSED`): an error, since
  repairing them would put the model in place of the data.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from afmid.io.findings import Finding, length
from afmid.preprocess.harmonics import block_layout, fourier_design, least_squares_projector, rotate_to_global

#: Chance that a record of Gaussian noise holds one outlier anywhere (sets the threshold from its length).
FALSE_ALARM = 1e-3
#: The threshold is at least this many robust standard deviations (real noise has heavier tails than Gauss).
MIN_SIGMA = 6.0
#: Samples within this many robust standard deviations of the prediction are back on the motion (an edge
#: transient is cut up to the first of them).
SETTLED_SIGMA = 3.0
#: An edge transient starts within this many samples of the edge.
EDGE_SAMPLES = 3
#: An interior glitch is at most this many consecutive samples.
MAX_GLITCH_RUN = 2
#: More interior glitches than this per period ...
MAX_GLITCHES_PER_PERIOD = 0.02
#: ... and at least this many are refused: the repaired record would be the model's.
MIN_REFUSED = 5
#: The prediction needs this many periods (a period and the four around it).
MIN_BLOCKS = 6


@dataclasses.dataclass
class Scan:
    """What :func:`scan` found, in sample indices of the scanned array."""

    sigma: float  # robust standard deviation of the residual from the periodic prediction
    threshold: float  # outliers leave the prediction by more than threshold * sigma
    head: int  # samples to cut at the start (0: none)
    tail: int  # samples to cut at the end (0: none)
    glitches: np.ndarray  # indices of isolated interior glitch samples
    replacement: np.ndarray  # the periodic prediction at those samples
    head_size: float = 0.0  # largest deviation within the cut head (samples' units)
    tail_size: float = 0.0
    glitch_size: float = 0.0  # largest deviation of a glitch

    @property
    def found(self) -> bool:
        return bool(self.head or self.tail or self.glitches.size)


def threshold(n_samples: int) -> float:
    """Robust standard deviations an outlier must exceed: the two-sided Gaussian quantile for a false alarm of
    :data:`FALSE_ALARM` among ``n_samples`` samples, at least :data:`MIN_SIGMA`."""
    from scipy.special import erfcinv

    return max(MIN_SIGMA, math.sqrt(2.0) * float(erfcinv(FALSE_ALARM / max(n_samples, 1))))


def blended_series(coefficients: np.ndarray, n_samples: int, cycles_per_sample: float, L: int, start: int
                   ) -> np.ndarray:
    """The Fourier series of per-period ``coefficients`` (B, 2K+1; global phase, time in samples) at every sample,
    the coefficients interpolated linearly between the periods' centres (start + b L + L // 2) and held beyond
    the first and last: continuous, so that a step between two periods' models is not a one-sample outlier."""
    B, K = coefficients.shape[0], (coefficients.shape[1] - 1) // 2
    omega = 2.0 * math.pi * cycles_per_sample
    centres = start + L * np.arange(B) + L // 2
    own = rotate_to_global(coefficients[..., None], -centres.astype(float), omega)[..., 0]  # about each centre
    out = np.empty(n_samples)
    ahead = fourier_design(np.arange(L, dtype=float), omega, K)  # s = 0..L-1 after a centre
    behind = fourier_design(np.arange(-L, 0, dtype=float), omega, K)  # the same samples seen from the next centre
    weight = np.arange(L) / L
    between = (own[:-1] @ ahead.T) * (1.0 - weight) + (own[1:] @ behind.T) * weight
    out[centres[0]:centres[-1]] = between.ravel()
    out[:centres[0]] = fourier_design(np.arange(-centres[0], 0, dtype=float), omega, K) @ own[0]
    out[centres[-1]:] = fourier_design(np.arange(n_samples - centres[-1], dtype=float), omega, K) @ own[-1]
    return out


def periodic_prediction(x: np.ndarray, cycles_per_sample: float) -> np.ndarray | None:
    """Each sample of ``x`` predicted from the neighbouring periods: the median of the record one and two periods
    before and after it (the nearest four periods on the record at its ends), at the same phase (cubic Lagrange
    interpolation between samples: the period is not a whole number of them). A sample does not predict itself,
    whatever repeats every period (a tapping impact, however sharp) predicts itself exactly, and the prediction
    is continuous (a Fourier fit per period has errors at its window's ends). None for fewer than
    :data:`MIN_BLOCKS` periods. Computed by :mod:`afmid.kernels.periodic` (a numba kernel, or its same-bits NumPy
    twin while the kernel is not compiled): this runs on every pixel of a map."""
    from afmid.kernels.periodic import periodic_prediction_or_twin

    period = 1.0 / cycles_per_sample
    if x.size < MIN_BLOCKS * period:
        return None
    return periodic_prediction_or_twin(np.ascontiguousarray(x, dtype=np.float64), period)


#: A sample's residual is compared with the mean of the residuals this many samples before and after it (the
#: closest ones are left out: a glitch of two samples would hide in them).
_AROUND = np.array([-3, -2, 2, 3])


def scan(x: np.ndarray, cycles_per_sample: float, head_is_motion: bool = False) -> Scan | None:
    """Edge transients and isolated glitches of ``x`` (see the module docstring); None when the record is too
    short to predict or its residual has no spread. With an edge transient found, the record without it is
    scanned again for the glitches (a transient disturbs the prediction of the samples one and two periods on).
    ``head_is_motion``: the record starts with a build-up from rest (:func:`afmid.io.onset.find_build_up`), which
    its neighbouring periods do not predict: its start is motion the fit uses, not an edge transient."""
    first = _scan_once(np.asarray(x, dtype=np.float64), cycles_per_sample, head_is_motion)
    if first is None or not (first.head or first.tail):
        return first
    stop = x.size - first.tail
    again = _scan_once(np.asarray(x[first.head:stop], dtype=np.float64), cycles_per_sample)
    if again is None:
        return dataclasses.replace(first, glitches=np.zeros(0, dtype=int), replacement=np.zeros(0), glitch_size=0.0)
    return Scan(first.sigma, first.threshold, first.head + again.head, first.tail + again.tail,
                again.glitches + first.head, again.replacement, max(first.head_size, again.head_size),
                max(first.tail_size, again.tail_size), again.glitch_size)


def _scan_once(x: np.ndarray, cycles_per_sample: float, head_is_motion: bool = False) -> Scan | None:
    """One pass of :func:`scan`.

    Both are judged against what remains of the motion's wander after the neighbouring periods' prediction
    (thermal motion, a modulation: smooth over a few samples): a glitch against the residual 2-3 samples on
    either side, an edge transient against the straight line through the residual of the next quarter period.
    """
    prediction = periodic_prediction(x, cycles_per_sample)
    if prediction is None:
        return None
    residual = _without_slow_misfit(x - prediction, cycles_per_sample)
    n, period = x.size, int(round(1.0 / cycles_per_sample))
    inner = np.arange(3, n - 3)
    sharp = np.zeros(n)
    sharp[inner] = residual[inner] - residual[inner[:, None] + _AROUND].mean(axis=1)
    sigma = 1.4826 * float(np.median(np.abs(sharp[inner] - np.median(sharp[inner]))))
    if not sigma > 0:
        return None
    limit = threshold(n)
    # the empirical null: the largest comparison of each period (the motion's own sharp features, such as an
    # impact's shape changing with the thermal wander, stand out of a 0.1 pm detector noise)
    per_period = np.abs(sharp[:n // period * period]).reshape(-1, period).max(axis=1)
    relevant = RELEVANCE * math.sqrt(2.0) * float(np.std(x))  # of the oscillation amplitude
    level = max(limit * sigma, GLITCH_NULL_FACTOR * float(np.median(per_period)), relevant)
    outliers = inner[np.abs(sharp[inner]) > level]
    zone = period // 8  # an edge transient is shorter than an eighth of a period (10 samples at 200 per period)
    head, head_size = _edge(residual, zone, sigma, limit, relevant)
    tail, tail_size = _edge(residual[::-1], zone, sigma, limit, relevant)
    # outliers of the comparison with the samples around within the edge zone belong to the edge (the line test
    # missed a transient that crosses the motion): cut through them
    early = outliers[(outliers < zone) & (outliers >= head + 3)]  # (the 3 after a cut are its echoes)
    if head_is_motion:
        head, head_size, early = 0, 0.0, early[:0]
    if early.size:
        head = int(early[-1]) + 1
        head_size = max(head_size, float(np.max(np.abs(sharp[:head]))))
    late = outliers[(outliers >= n - zone) & (outliers < n - tail - 3)]
    if late.size:
        tail = n - int(late[0])
        tail_size = max(tail_size, float(np.max(np.abs(sharp[n - tail:]))))
    # an edge transient disturbs the comparisons up to 3 samples beyond it; anything else within a period of it
    # makes it no transient
    # (besides its echo in the prediction of the samples one period on: smaller, within 3 samples of it there)
    exact = 1.0 / cycles_per_sample
    echo = (np.abs(sharp[outliers]) < 0.5 * max(head_size, tail_size)) & (
        (np.abs(outliers - exact) <= head + 3) | (np.abs(n - 1 - outliers - exact) <= tail + 3))
    others = outliers[~echo]
    if head and np.any((others >= head + 3) & (others <= head + period)):
        head, head_size = 0, 0.0
    if tail and np.any((others < n - tail - 3) & (others >= n - tail - period)):
        tail, tail_size = 0, 0.0
    outliers = outliers[(outliers >= head + 3) & (outliers < n - tail - 3)]
    glitches: list[int] = []
    groups = np.split(outliers, np.flatnonzero(np.diff(outliers) > 3) + 1) if outliers.size else []
    sizes = [float(np.max(np.abs(sharp[g]))) for g in groups]
    peaks = [int(g[np.argmax(np.abs(sharp[g]))]) for g in groups]
    for i, group in enumerate(groups):
        near = [j for j in range(len(groups)) if j != i and abs(peaks[j] - peaks[i]) <= period + 3
                and not _echo(peaks[j], peaks[i], sizes[j], sizes[i], 1.0 / cycles_per_sample)]
        if near:
            continue  # not isolated: a pattern of the motion (or of the instrument), not a glitch
        size = np.abs(sharp[group])
        core = group[size >= 0.5 * size.max()]  # the glitch; the rest are its echoes in its neighbours' comparison
        if core.size <= MAX_GLITCH_RUN and core[-1] - core[0] < core.size:
            glitches.extend(int(k) for k in core)
    where = np.array(glitches, dtype=int)
    size = float(np.max(np.abs(sharp[where]))) if where.size else 0.0
    return Scan(sigma, limit, head, tail, where, x[where] - sharp[where], head_size, tail_size, size)


#: Glitches and edge transients smaller than this fraction of the oscillation amplitude are left alone: they
#: change little that a fit measures (3 pm on 10 nm adds 9e-4 pm^2 to the noise variance of a 10000-sample record)
#: and a simulator's own sharp features reach 1.7 pm (0.1 pm detector noise, steps at period boundaries).
RELEVANCE = 3e-4
#: A glitch exceeds this many times the median over periods of each period's largest comparison (for Gaussian
#: noise that median is 2.9 sigma at 200 samples per period and 3.3 at 900: the threshold stays 6-7 sigma there;
#: a period's sharp features of the motion raise it, a glitch in a few periods does not).
GLITCH_NULL_FACTOR = 2.0
#: An edge transient leaves the straight line through the residual after it by this factor more than the 99th
#: percentile of the same test anywhere else in the record (the motion's own wander there, with the extrapolation's
#: error: the test's empirical null).
EDGE_NULL_FACTOR = 2.0


def _echo(other: int, peak: int, other_size: float, size: float, period: float) -> bool:
    """The outlier at ``other`` is the echo of the one at ``peak`` in the prediction of the samples one or two
    periods away (a median of four neighbours, one of them the glitch: it moves by part of their spread): smaller
    than half of it and within 3 samples of a whole number (1, 2) of periods from it."""
    shift = abs(other - peak) / period
    return other_size < 0.5 * size and round(shift) in (1, 2) and abs(shift - round(shift)) * period <= 3


def _edge(residual: np.ndarray, zone: int, sigma: float, limit: float, relevant: float) -> tuple[int, float]:
    """(samples to cut, largest deviation) at the start of ``residual`` (a record, or its reverse): within the first
    ``zone`` samples, deviations from the straight line through the next ``zone`` samples beyond ``limit`` x
    ``sigma`` and :data:`EDGE_NULL_FACTOR` times the 99th percentile of the same statistic in every later window
    of the record and ``relevant``, the first within :data:`EDGE_SAMPLES` of the edge; cut up to the first sample
    back within that percentile and :data:`SETTLED_SIGMA` x ``sigma``. (0, 0) when none."""
    windows = (residual.size - 2 * zone) // zone + 1
    if zone < 2 * EDGE_SAMPLES or windows < 100:
        return 0, 0.0
    rows = residual[np.arange(windows)[:, None] * zone + np.arange(2 * zone)]
    later = np.arange(zone, 2 * zone, dtype=float)
    centred = later - later.mean()
    slope = rows[:, zone:] @ centred / float(centred @ centred)
    level = rows[:, zone:].mean(axis=1)
    line = level[:, None] + slope[:, None] * (np.arange(zone) - later.mean())
    deviation = np.abs(rows[:, :zone] - line)
    null = float(np.quantile(deviation[1:].max(axis=1), 0.99))
    edge = deviation[0]
    out = np.flatnonzero(edge > max(limit * sigma, EDGE_NULL_FACTOR * null, relevant))
    if out.size == 0 or out[0] >= EDGE_SAMPLES:
        return 0, 0.0
    cut = int(out[-1]) + 1
    while cut < zone and edge[cut] > max(SETTLED_SIGMA * sigma, null):
        cut += 1
    return cut, float(edge[:cut].max())


#: Harmonics (and the mean) of each period's own residual taken out before the test: the neighbours mispredict a
#: period by the slow wander of its amplitude, phase and mean (thermal motion: 1-17 pm on a 40 N/m lever with
#: 0.1 pm detector noise, largest at the record's ends, where the neighbours are all on one side).
OWN_HARMONICS = 2


def _without_slow_misfit(residual: np.ndarray, cycles_per_sample: float) -> np.ndarray:
    """``residual`` minus its per-period least-squares fit by a mean and :data:`OWN_HARMONICS` harmonics (as
    :func:`blended_series`); the first and last periods fitted with the samples before and after the whole periods
    but without their outer quarter period, so that an edge transient does not hide in the fit."""
    L, B, start = block_layout(residual.size, 1.0 / cycles_per_sample)
    omega = 2.0 * math.pi * cycles_per_sample
    design = fourier_design(np.arange(L, dtype=float), omega, OWN_HARMONICS)
    local = residual[start:start + B * L].reshape(B, L) @ least_squares_projector(design).T
    glob = rotate_to_global(local[..., None], start + L * np.arange(B, dtype=float), omega)[..., 0]
    edge = L // 4
    for b, lo, hi, fitted in ((0, 0, start + L, slice(edge, None)),
                              (B - 1, start + (B - 1) * L, residual.size, slice(None, -edge))):
        part = fourier_design(np.arange(lo, hi, dtype=float), omega, OWN_HARMONICS)  # global time
        glob[b], *_ = np.linalg.lstsq(part[fitted], residual[lo:hi][fitted], rcond=None)
    return residual - blended_series(glob, residual.size, cycles_per_sample, L, start)


def check_glitches(x: np.ndarray, analysis, units: str | None, head_is_motion: bool = False) -> list[Finding]:
    """The finding for ``x`` analysed as ``analysis`` (an :class:`afmid.io.trace_analysis.Analysis`): a warning
    that says what a fit cuts and repairs (numbers: head, tail, glitches, replacement), or an error when the
    glitches are too many to repair; none when nothing is found. ``head_is_motion``: as for :func:`scan`."""
    found = scan(x, analysis.cycles_per_sample, head_is_motion)
    if found is None or not found.found:
        return []
    numbers = {"head": found.head, "tail": found.tail, "glitches": found.glitches.tolist(),
               "replacement": found.replacement.tolist(), "sigma": found.sigma, "threshold": found.threshold,
               "head_size": found.head_size, "tail_size": found.tail_size, "glitch_size": found.glitch_size}
    allowed = max(MIN_REFUSED, MAX_GLITCHES_PER_PERIOD * analysis.periods)
    if found.glitches.size > allowed:
        return [Finding(
            "glitches", "error",
            f"{found.glitches.size} isolated samples leave the periodic motion by more than {found.threshold:.2g} "
            f"times the noise ({length(found.sigma, units)} rms; the first at sample {found.glitches[0]}, up to "
            f"{length(found.glitch_size, units)}): more than {MAX_GLITCHES_PER_PERIOD * 100:g} per 100 periods, too "
            "many to repair from the motion around them without putting the model in place of the data; check the "
            "acquisition (ADC, cabling) or choose a clean part with data.start / data.stop", "data.path", numbers)]
    return [Finding("glitches", "warning", describe(found, x.size, units, done=False), "data.start", numbers)]


def describe(found: Scan, n_samples: int, units: str | None, done: bool, offset: int = 0,
             kept: tuple[bool, bool] = (True, True)) -> str:
    """One line: which samples of a record of ``n_samples`` (``offset`` added: the file's indices), how far off,
    what is (``done``) or would be done; ``kept``: (head, tail) False where data.start / data.stop chose that end
    (then it is left as it is)."""
    parts = []
    if found.head:
        action = ("kept: data.start chose the start" if not kept[0] else "cut" if done else "a fit cuts them")
        parts.append(f"{_samples(offset, found.head)} at the start {_leave(found.head)} the periodic motion by "
                     f"up to {length(found.head_size, units)} (an edge transient: a filter or the acquisition "
                     f"settling; {action})")
    if found.tail:
        first = offset + n_samples - found.tail
        action = ("kept: data.stop chose the end" if not kept[1] else "cut" if done else "a fit cuts them")
        parts.append(f"{_samples(first, found.tail)} at the end {_leave(found.tail)} it by up to "
                     f"{length(found.tail_size, units)} (an edge transient; {action})")
    if found.glitches.size:
        listed = ", ".join(str(offset + int(k)) for k in found.glitches[:5])
        more = f" and {found.glitches.size - 5} more" if found.glitches.size > 5 else ""
        action = "replaced by" if done else "a fit replaces them by"
        parts.append(f"{found.glitches.size} isolated glitch sample{'s' if found.glitches.size > 1 else ''} "
                     f"(sample {listed}{more}; up to {length(found.glitch_size, units)}) {action} the periodic motion "
                     "of the periods around them")
    return ("; ".join(parts) + f" (outliers beyond {found.threshold:.2g} x the noise of "
            f"{length(found.sigma, units)} rms, none other within a period); set data.start / data.stop to choose "
            "the part to fit instead")


def _leave(count: int) -> str:
    return "leaves" if count == 1 else "leave"


def _samples(first: int, count: int) -> str:
    return f"sample {first}" if count == 1 else f"samples {first}-{first + count - 1}"


def cleaned(trace, config, finding: Finding):
    """``trace`` (an :class:`afmid.io.trace.Trace`) with the edge transients of ``finding`` cut (unless
    ``data.start`` / ``data.stop`` chose that end) and its glitches replaced, and the finding of what was done
    (severity 'repaired'). The deflection is a copy: the file is not touched."""
    from afmid.io.onset import crop

    numbers = finding.numbers
    found = Scan(numbers["sigma"], numbers["threshold"], numbers["head"], numbers["tail"],
                 np.asarray(numbers["glitches"], dtype=int), np.asarray(numbers["replacement"], dtype=float),
                 numbers["head_size"], numbers["tail_size"], numbers["glitch_size"])
    offset, n_samples = trace.first_sample, trace.n_samples
    keep = (config.data.start is None, config.data.stop is None)
    if found.glitches.size:
        deflection = trace.deflection.copy()
        deflection[found.glitches] = found.replacement
        trace = dataclasses.replace(trace, deflection=deflection, drive=None)
        trace.sources["repaired"] = (f"samples {', '.join(str(offset + int(k)) for k in found.glitches)} of the file "
                                     "replaced by the periodic motion (isolated glitches)")
    first = found.head if found.head and keep[0] else 0
    stop = trace.n_samples - found.tail if found.tail and keep[1] else trace.n_samples
    if first or stop < trace.n_samples:
        before = trace.first_sample
        trace = crop(trace, first, stop)
        trace.sources["crop"] = (f"edge transients cut: samples {trace.first_sample} to "
                                 f"{trace.first_sample + trace.n_samples} of the file (from sample {before})")
    message = describe(found, n_samples, "m", done=True, offset=offset, kept=keep)
    return trace, Finding("glitches", "repaired", message, "data.start", numbers)
