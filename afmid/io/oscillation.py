"""Is there an oscillation at the drive frequency at all? A test against the spectrum of noise.

A trace without one (a slow ramp, white noise, the time column read as the
deflection) can still be "fitted": the regression always returns numbers, and
they are nonsense (a negative modulus, a NaN error metric). This check stops
such a trace before the fit, with the numbers behind the verdict.

The statistic: the power of the Hann-windowed spectrum of the linearly
detrended deflection at the drive frequency (the largest bin within the fit's
search band around the nominal drive frequency) divided by the mean power of
nearby bins that are no drive harmonic (the local noise floor, so a coloured
background such as a random walk or drift leakage is compared with itself).
For Gaussian noise each bin's power is exponentially distributed with the
local mean, so the ratio of one bin to the mean of m independent floor bins
follows an F(2, 2m) distribution. The line counts as real when the ratio
exceeds the F(2, 2m) quantile for a false-alarm probability of
:data:`FALSE_ALARM` shared among the bins of the search band (Bonferroni): the
threshold follows from the statistics of noise, not from examples. Floor bins
are taken two apart so that the Hann window leaves them nearly independent.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from afmid.preprocess.harmonics import hann_window

#: Chance that a trace of pure noise passes the check (the threshold is its F(2, 2m) quantile).
FALSE_ALARM = 1e-6
#: Bins (of the window's main lobe and its first sidelobes) kept away from a drive harmonic in the floor.
GUARD_BINS = 3
#: Floor bins averaged at most (more add little precision and reach farther from the drive frequency).
MAX_FLOOR_BINS = 32
#: Fewer floor bins than this and the trace is too short to judge (other checks cover such traces).
MIN_FLOOR_BINS = 4
#: Bins below this are trend leakage, not noise (the checks ignore anything slower than 2.5 cycles).
FIRST_BIN = 3
#: The spectrum is taken over at most this many samples (the middle of the trace): enough for the test,
#: bounded in time and memory on long traces.
MAX_SAMPLES = 1 << 21


def _detrended(x: np.ndarray) -> np.ndarray:
    """``x`` minus its least-squares straight line."""
    t = np.arange(x.size) - 0.5 * (x.size - 1)
    xc = x - x.mean()
    denom = float(np.dot(t, t))
    return xc - (np.dot(t, xc) / denom) * t if denom else xc


def f_2_isf(probability: float, denominator_dof: int) -> float:
    """The value an F(2, d2) variable exceeds with ``probability``: P(F > x) = (1 + 2 x / d2)^(-d2 / 2), so
    x = (d2 / 2) (p^(-2 / d2) - 1) (scipy.stats.f.isf(p, 2, d2) to rounding; a closed form here, since importing
    scipy.stats cost every afmid process ~0.4 s)."""
    half = 0.5 * denominator_dof
    return float(half * math.expm1(-math.log(probability) / half))


def drive_line_test(x: np.ndarray, sample_rate: float, nominal: float, search: float) -> dict | None:
    """The drive-frequency line against the local noise floor.

    Returns ``{"ratio", "threshold", "floor_bins", "band_bins"}`` (ratio: line power / mean floor power),
    or None when the trace cannot be judged (too short for a floor, or the drive above the Nyquist frequency).
    """
    x = np.asarray(x, dtype=np.float64)
    if x.size > MAX_SAMPLES:
        start = (x.size - MAX_SAMPLES) // 2
        x = x[start:start + MAX_SAMPLES]
    n = x.size
    if n < 16:
        return None
    bins = _line_and_floor_bins(n, sample_rate, nominal, search)
    if bins is None:
        return None
    band, floor_bins = bins
    power = np.abs(np.fft.rfft(hann_window(n) * _detrended(x))) ** 2
    line = float(power[band].max())
    floor = float(power[floor_bins].mean())
    ratio = line / floor if floor > 0 else (math.inf if line > 0 else 0.0)
    m = int(floor_bins.size)
    threshold = f_2_isf(FALSE_ALARM / band.size, 2 * m)
    return {"ratio": ratio, "threshold": threshold, "floor_bins": m, "band_bins": int(band.size)}


@functools.lru_cache(maxsize=8)
def _line_and_floor_bins(n: int, sample_rate: float, nominal: float, search: float
                         ) -> tuple[np.ndarray, np.ndarray] | None:
    """The bins (of the rfft of ``n`` samples) of the drive line's band and of the noise floor around it, read-only;
    None when the floor has too few bins or the band lies beyond the last bin. Facts of the sampling, not of the
    samples: the same for every pixel of a map (kept per process)."""
    last = n // 2 - 1  # the rfft's last bin but the Nyquist one, which has half the degrees of freedom
    drive_bin = nominal * n / sample_rate
    lo, hi = max(int(math.floor(drive_bin * (1 - search))), FIRST_BIN), int(math.ceil(drive_bin * (1 + search)))
    hi = min(hi, last)
    if hi < lo:
        return None
    band = np.arange(lo, hi + 1)
    k = np.arange(FIRST_BIN, last + 1)
    harmonic = np.maximum(np.round(k / drive_bin), 1.0)
    clear = np.abs(k - harmonic * drive_bin) > search * harmonic * drive_bin + GUARD_BINS
    candidates = k[clear]
    candidates = candidates[np.argsort(np.abs(candidates - drive_bin), kind="stable")][:2 * MAX_FLOOR_BINS]
    floor_bins = np.sort(candidates)[::2]
    if floor_bins.size < MIN_FLOOR_BINS:
        return None
    band.flags.writeable = False
    floor_bins.flags.writeable = False
    return band, floor_bins


def check_drive_line(x: np.ndarray, settings, strongest: float | None = None) -> list:
    """An error :class:`afmid.io.defects.Finding` when the trace does not oscillate at the drive frequency.

    ``settings`` is an :class:`afmid.io.defects.Settings`; without a sample rate and nominal drive frequency
    (``afmid inspect`` on a bare file) there is nothing to test against. ``strongest``: the frequency (Hz)
    of the strongest oscillation found in the trace; when that is a real line away from the drive
    frequency, the drive-frequency check says better what to do (set drive.frequency), and this one is quiet.
    """
    from afmid.io.findings import Finding, frequency
    from afmid.preprocess.harmonics import DRIVE_SEARCH

    if not (settings.sample_rate and settings.nominal_frequency) or np.ptp(x) == 0:
        return []  # nothing to test against; a constant channel has its own, plainer message
    test = drive_line_test(x, settings.sample_rate, settings.nominal_frequency, DRIVE_SEARCH)
    if test is None or test["ratio"] > test["threshold"]:
        return []
    if strongest is not None:
        elsewhere = drive_line_test(x, settings.sample_rate, strongest, DRIVE_SEARCH)
        if elsewhere is not None and elsewhere["ratio"] > elsewhere["threshold"]:
            return []
    return [Finding(
        "no_oscillation", "error",
        f"no oscillation at the drive frequency {frequency(settings.nominal_frequency)}: the drive-frequency line "
        f"is {test['ratio']:.3g} times the noise floor around it, need > {test['threshold']:.3g} (noise alone "
        f"exceeds that with probability {FALSE_ALARM:g}); is data.column the deflection, and are drive.frequency "
        "and data.sample_rate right?",
        "data.column", test)]
