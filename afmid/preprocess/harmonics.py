"""The harmonic-analysis engine: the drive frequency, Fourier designs and least-squares projectors.

One implementation shared by the defect checks (:mod:`afmid.io.defects`, which work
in samples) and the fit (:mod:`afmid.preprocess.periods`, which works in seconds), so the
two cannot drift apart:

- :func:`estimate_drive`: the drive (response fundamental) frequency near the
  nominal one, with the first-harmonic amplitude, phase and offset (the fit's
  measurement; the trace loader measures it once and the fit reuses it, see
  :class:`MeasuredDrive`);
- :func:`measure_frequency`: the strongest oscillation anywhere in the spectrum,
  cycles per sample (for traces without a trusted nominal frequency);
- :func:`harmonic_cos_sin`, :func:`fourier_design`, :func:`least_squares_projector`, :func:`rotation`,
  :func:`rotate_to_global`, :func:`apply_rows`: per-block Fourier fits.

Both frequency searches are one estimator: a Hann-windowed spectrum finds the
peak, a bounded Brent search of the windowed DFT power refines it far below the
bin width. Traces longer than :data:`EXACT_SPECTRUM_MAX` samples are searched
without zero padding, on block moments (:class:`WindowedPower`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from afmid.errors import InputError

#: Fewer samples per drive period than this cannot resolve the motion's harmonics well.
MIN_SAMPLES_PER_PERIOD = 20
#: A trace must hold at least this many drive periods.
MIN_PERIODS = 3
#: The drive frequency is searched within this relative distance of the nominal one.
DRIVE_SEARCH = 0.05
#: Highest harmonic fitted: at most this fraction of the samples per period (well inside Nyquist, so the
#: least-squares Fourier fit of a block stays well conditioned).
NYQUIST_FRACTION = 0.45
#: Above this many samples the spectral peak is found without zero padding and the bounded search runs on
#: per-block moments (:class:`WindowedPower`): a padded FFT of a 1e7-sample trace (2^27 points) took 16 s and
#: 3 GB, each probe of the search a full-length complex exponential. Up to it the padded FFT costs < 0.5 s and
#: is kept as it was (the estimate, and so every result, is unchanged bit for bit).
EXACT_SPECTRUM_MAX = 2**21
#: Samples per chunk when a whole-trace quantity is accumulated piece by piece (bounds the temporaries).
SAMPLE_CHUNK = 1 << 18


#: Records up to this many samples keep their Hann window for the next record of the same length.
CACHED_WINDOW_MAX = 1 << 20


def hann_window(n: int) -> np.ndarray:
    """``np.hanning(n)`` (the same values), read-only; kept per length for records up to
    :data:`CACHED_WINDOW_MAX` samples: every pixel of a map has the same length, and its checks on load window it
    three times (~0.1 ms each)."""
    return _cached_hann(n) if n <= CACHED_WINDOW_MAX else np.hanning(n)


@functools.lru_cache(maxsize=4)
def _cached_hann(n: int) -> np.ndarray:
    window = np.hanning(n)
    window.flags.writeable = False
    return window


# --------------------------------------------------------------------------- the drive
@dataclass
class DriveEstimate:
    frequency: float  # Hz, measured
    nominal: float  # Hz, from the config or file
    amplitude: float  # m, first-harmonic amplitude of the deflection
    phase: float  # rad, phase of the first harmonic relative to t = 0 (x ~ A cos(w t + phase))
    offset: float  # m, mean deflection

    @property
    def omega(self) -> float:
        return 2.0 * np.pi * self.frequency


@dataclass(frozen=True)
class MeasuredDrive:
    """The drive measured when a trace was loaded, and what it was measured from (to reuse it safely).

    ``estimate`` is :func:`estimate_drive` of ``deflection`` detrended with
    ``detrend`` (fit.detrend) at the times of the trace, searched around the
    nominal frequency ``estimate.nominal``.
    """

    estimate: DriveEstimate
    detrend: str  # fit.detrend the samples were detrended with before the measurement
    deflection: np.ndarray  # the trace's own samples (the same object, not a copy): other samples, other drive
    sample_rate: float  # Hz
    time: np.ndarray | None  # the trace's time column (the same object), if it had one

    def matches(self, deflection: np.ndarray, sample_rate: float, time: np.ndarray | None, nominal: float,
                detrend: str) -> bool:
        """True if these are the samples, times, nominal frequency and detrending it was measured with."""
        return (deflection is self.deflection and time is self.time and sample_rate == self.sample_rate
                and nominal == self.estimate.nominal and detrend == self.detrend)


class WindowedPower:
    """|sum_j y_j exp(-2 pi i f t_j)|^2 for f near ``center``, from per-block moments of y.

    The sum is split into blocks of ``block`` samples with start times t_b;
    within a block exp(-2 pi i (f - center) (t - t_b)) is a Taylor series in
    (t - t_b), so with M_bm = sum_{j in b} y_j exp(-2 pi i center t_j) (t_j - t_b)^m
    every probe costs O(blocks x order) instead of a full-length exponential.
    The series is truncated where its remainder is below 1e-17 for
    |f - center| <= ``reach`` (exact to rounding within it).
    """

    def __init__(self, y: np.ndarray, t: np.ndarray, center: float, reach: float, block: int = 4096):
        n = y.size
        starts = np.arange(0, n, block)
        span = float(np.max(t[np.minimum(starts + block - 1, n - 1)] - t[starts]))  # longest block, s
        arg = 2 * np.pi * reach * span
        order, term = 1, arg  # the remainder after `order` terms is at most arg^order / order!
        while term > 1e-17 and order < 40:
            order += 1
            term *= arg / order
        self.center = center
        self.t_ref = t[starts]
        self.factorial = np.cumprod(np.concatenate([[1.0], np.arange(1.0, order)]))
        moments = np.empty((starts.size, order), dtype=complex)
        step = max(block, SAMPLE_CHUNK // block * block)
        for lo in range(0, n, step):
            hi = min(lo + step, n)
            tt = t[lo:hi]
            local = np.arange(0, hi - lo, block)
            rows = slice(lo // block, lo // block + local.size)
            u = tt - np.repeat(self.t_ref[rows], block)[: hi - lo]
            p = y[lo:hi] * np.exp(-2j * np.pi * center * tt)
            for m in range(order):
                moments[rows, m] = np.add.reduceat(p, local)
                if m + 1 < order:
                    p *= u
        self.moments = moments

    def __call__(self, f: float) -> float:
        delta = f - self.center
        c = (-2j * np.pi * delta) ** np.arange(self.factorial.size) / self.factorial
        return float(np.abs(np.dot(np.exp(-2j * np.pi * delta * self.t_ref), self.moments @ c)) ** 2)


def hann_weighted(x: np.ndarray, offset: float = 0.0, slope: float = 0.0) -> np.ndarray:
    """``np.hanning(n) * (x - offset - slope * (j - (n - 1) / 2))``, built chunk by chunk (no temporaries of n)."""
    n = x.size
    out = np.empty(n)
    for lo in range(0, n, SAMPLE_CHUNK):
        hi = min(lo + SAMPLE_CHUNK, n)
        j = np.arange(lo, hi, dtype=float)
        window = 0.5 + 0.5 * np.cos(np.pi * (2 * j + 1 - n) / (n - 1)) if n > 1 else np.ones(hi - lo)
        centred = x[lo:hi] - offset
        if slope:
            centred -= slope * (j - 0.5 * (n - 1))
        np.multiply(window, centred, out=out[lo:hi])
    return out


def _refine_peak(weighted: np.ndarray, t: np.ndarray, lo: float, hi: float, xatol: float) -> float:
    """The frequency in [lo, hi] (1 / units of t) of the largest windowed DFT power |sum weighted e^(-2 pi i f t)|^2."""
    from scipy.optimize import minimize_scalar

    def negative_power(f: float) -> float:
        return -float(np.abs(np.dot(weighted, np.exp(-2j * np.pi * f * t))) ** 2)

    return float(minimize_scalar(negative_power, bounds=(lo, hi), method="bounded", options={"xatol": xatol}).x)


def _refine_peak_long(weighted: np.ndarray, t: np.ndarray, center: float, df: float, lo: float, hi: float,
                      xatol: float) -> float:
    """:func:`_refine_peak` on block moments, searched as an offset in [lo, hi] from the bin ``center``.

    Bounded Brent stops at sqrt(eps) |x| + xatol / 3, which for the frequency
    itself is 5e-3 Hz at 300 kHz (~1.5e-8, the padded path's real precision);
    for the offset, xatol rules (~1e-11 relative), and each probe costs
    microseconds here.
    """
    from scipy.optimize import minimize_scalar

    power = WindowedPower(weighted, t, center, 2.0 * df)
    res = minimize_scalar(lambda u: -power(center + u), bounds=(lo, hi), method="bounded", options={"xatol": xatol})
    return center + float(res.x)


def _unpadded_spectrum(weighted: np.ndarray) -> tuple[np.ndarray, int]:
    """|rfft| of windowed samples at the next fast length (no zero padding beyond it), and that length."""
    from scipy import fft as sfft

    nfft = sfft.next_fast_len(weighted.size, real=True)
    return np.abs(sfft.rfft(weighted, nfft)), nfft


def estimate_drive(x: np.ndarray, t: np.ndarray, nominal: float, search: float = DRIVE_SEARCH) -> DriveEstimate:
    """Measure the drive (response fundamental) frequency near ``nominal`` (Hz; ``t`` in s).

    A Hann-windowed, zero-padded spectrum finds the peak within ``search``
    (relative) of the nominal frequency; a bounded scalar search of the windowed
    DFT power then refines it far below the bin width (~1e-7 relative on a
    50-period trace). Raises InputError if there is no oscillation.
    Traces longer than :data:`EXACT_SPECTRUM_MAX` samples: unpadded spectrum,
    the search on block moments, amplitude and phase from chunked normal
    equations (same estimator and tolerance, O(n) memory and time).
    """
    if x.size > EXACT_SPECTRUM_MAX:
        return _estimate_drive_long(x, t, nominal, search)
    xc = x - x.mean()
    if not np.any(xc):
        raise InputError("the deflection is constant: no oscillation to analyse", key="data.column")
    n = x.size
    duration = t[-1] - t[0] + (t[1] - t[0])
    window = hann_window(n)
    pad = 8 * int(2 ** np.ceil(np.log2(n)))
    weighted = window * xc
    spectrum = np.abs(np.fft.rfft(weighted, pad))
    freqs = np.fft.rfftfreq(pad, d=duration / n)
    band = (freqs > nominal * (1 - search)) & (freqs < nominal * (1 + search))
    if not band.any():
        raise InputError(
            f"the drive frequency {nominal:g} Hz is outside the sampled band (sample rate {n / duration:g} Hz)",
            key="drive.frequency",
        )
    idx = np.flatnonzero(band)[np.argmax(spectrum[band])]
    df = freqs[1] - freqs[0]
    f = _refine_peak(weighted, t, freqs[idx] - 1.5 * df, freqs[idx] + 1.5 * df, nominal * 1e-10)
    return drive_at(x, t, nominal, f)


def drive_at(x: np.ndarray, t: np.ndarray, nominal: float, frequency: float) -> DriveEstimate:
    """The drive at a known ``frequency`` (Hz; ``t`` in s): the unwindowed least-squares amplitude, phase and offset
    of the first harmonic over the record, as :func:`estimate_drive` gives them at the frequency it measures.
    Traces up to :data:`EXACT_SPECTRUM_MAX` samples (the single-product path of :func:`estimate_drive`)."""
    w = 2 * np.pi * frequency
    design = np.column_stack([np.ones_like(t), np.cos(w * t), np.sin(w * t)])
    coef, *_ = np.linalg.lstsq(design, x, rcond=None)
    amplitude = float(np.hypot(coef[1], coef[2]))
    phase = float(np.arctan2(-coef[2], coef[1]))
    return DriveEstimate(frequency=frequency, nominal=nominal, amplitude=amplitude, phase=phase,
                         offset=float(coef[0]))


def _estimate_drive_long(x: np.ndarray, t: np.ndarray, nominal: float, search: float) -> DriveEstimate:
    """:func:`estimate_drive` for long traces: no zero padding, no full-length temporaries."""
    n = x.size
    mean = x.mean()
    if not np.any(x != mean):
        raise InputError("the deflection is constant: no oscillation to analyse", key="data.column")
    weighted = hann_weighted(x, mean)
    duration = t[-1] - t[0] + (t[1] - t[0])
    spectrum, nfft = _unpadded_spectrum(weighted)
    scale = nfft * duration / n  # bin k is at frequency k / scale
    k0 = max(int(np.floor(nominal * (1 - search) * scale)) - 1, 0)
    k1 = min(int(np.ceil(nominal * (1 + search) * scale)) + 2, spectrum.size)
    freqs = np.arange(k0, max(k1, k0)) / scale
    band = (freqs > nominal * (1 - search)) & (freqs < nominal * (1 + search))
    if not band.any():
        raise InputError(
            f"the drive frequency {nominal:g} Hz is outside the sampled band (sample rate {n / duration:g} Hz)",
            key="drive.frequency",
        )
    idx = np.flatnonzero(band)[np.argmax(spectrum[k0:k1][band])]
    del spectrum
    df = 1.0 / scale
    center = float(freqs[idx])
    f = _refine_peak_long(weighted, t, center, df, -1.5 * df, 1.5 * df, nominal * 1e-10)
    del weighted
    # Unwindowed least-squares amplitude and phase over whole periods (normal equations, chunk by chunk).
    w = 2 * np.pi * f
    gram, rhs = np.zeros((3, 3)), np.zeros(3)
    for lo in range(0, n, SAMPLE_CHUNK):
        tt = t[lo:lo + SAMPLE_CHUNK]
        design = np.column_stack([np.ones_like(tt), np.cos(w * tt), np.sin(w * tt)])
        gram += design.T @ design
        rhs += design.T @ x[lo:lo + SAMPLE_CHUNK]
    coef = np.linalg.solve(gram, rhs)
    amplitude = float(np.hypot(coef[1], coef[2]))
    phase = float(np.arctan2(-coef[2], coef[1]))
    return DriveEstimate(frequency=f, nominal=nominal, amplitude=amplitude, phase=phase, offset=float(coef[0]))


# --------------------------------------------------------------------------- the strongest oscillation
@dataclass
class SpectralPeak:
    """The strongest oscillation's spectral bin, before refinement (see :func:`strongest_peak`)."""

    cycles_per_sample: float  # frequency of the bin, cycles per sample
    weighted: np.ndarray  # the windowed, detrended samples the spectrum was taken of
    lo: float  # search bounds of the refinement, cycles per sample
    hi: float
    long: bool  # found without zero padding (refined on block moments)

    def refine(self) -> float:
        """The peak refined far below the bin width, cycles per sample."""
        f = self.cycles_per_sample
        if self.hi <= self.lo:
            return float(f)
        n = self.weighted.size
        if self.long:
            df = 1.0 / _unpadded_length(n)
            return _refine_peak_long(self.weighted, np.arange(n, dtype=float), f, df, self.lo - f, self.hi - f,
                                     f * 1e-9)
        return _refine_peak(self.weighted, np.arange(n), self.lo, self.hi, f * 1e-9)


def _unpadded_length(n: int) -> int:
    from scipy import fft as sfft

    return sfft.next_fast_len(n, real=True)


def _detrended(x: np.ndarray) -> np.ndarray:
    t = np.arange(x.size) - 0.5 * (x.size - 1)
    xc = x - x.mean()
    denom = float(np.dot(t, t))
    return xc - (np.dot(t, xc) / denom) * t if denom else xc


def strongest_peak(x: np.ndarray) -> SpectralPeak | None:
    """The bin of the strongest oscillation of samples ``x``, or None if there is none (constant, too short).

    The peak of a Hann-windowed, zero-padded spectrum of the linearly detrended
    samples, ignoring anything slower than 2.5 cycles over the trace. Traces
    longer than :data:`EXACT_SPECTRUM_MAX` samples: no zero padding (a padded
    FFT of 1e7 samples took 10 s and 2 GB).
    """
    n = x.size
    if n < 8:
        return None
    x = np.asarray(x, dtype=np.float64)
    if n > EXACT_SPECTRUM_MAX:
        return _strongest_peak_long(x)
    xc = _detrended(x)
    if not np.any(xc) or np.max(np.abs(xc)) <= 1e-12 * max(np.max(np.abs(x)), 1e-300):
        return None
    window = hann_window(n)
    pad = 4 * int(2 ** math.ceil(math.log2(n)))
    weighted = window * xc
    spectrum = np.abs(np.fft.rfft(weighted, pad))
    freqs = np.arange(spectrum.size) / pad
    band = freqs >= 2.5 / n
    if not band.any():
        return None
    i = int(np.flatnonzero(band)[np.argmax(spectrum[band])])
    if spectrum[i] == 0:
        return None
    df = 1.0 / pad
    lo, hi = max(freqs[i] - 1.5 * df, 0.5 / n), min(freqs[i] + 1.5 * df, 0.5)
    return SpectralPeak(float(freqs[i]), weighted, lo, hi, long=False)


def _strongest_peak_long(x: np.ndarray) -> SpectralPeak | None:
    """:func:`strongest_peak` without zero padding or full-length temporaries beyond the windowed samples."""
    n = x.size
    mean = float(x.mean())
    c = 0.5 * (n - 1)
    # Least-squares slope against the centred sample index, then the largest detrended deviation.
    tx = sum(float(np.dot(np.arange(lo, min(lo + SAMPLE_CHUNK, n)) - c, x[lo:lo + SAMPLE_CHUNK]))
             for lo in range(0, n, SAMPLE_CHUNK))
    slope = tx / (n * (n * n - 1.0) / 12.0)
    biggest = max(float(np.max(np.abs(x[lo:lo + SAMPLE_CHUNK] - mean
                                      - slope * (np.arange(lo, min(lo + SAMPLE_CHUNK, n)) - c))))
                  for lo in range(0, n, SAMPLE_CHUNK))
    if biggest == 0 or biggest <= 1e-12 * max(float(np.max(np.abs(x))), 1e-300):
        return None
    weighted = hann_weighted(x, mean, slope)
    spectrum, nfft = _unpadded_spectrum(weighted)
    first = int(math.ceil(2.5 / n * nfft))  # freqs >= 2.5 / n
    if first >= spectrum.size:
        return None
    i = first + int(np.argmax(spectrum[first:]))
    if spectrum[i] == 0:
        return None
    df = 1.0 / nfft
    f_i = i / nfft
    lo, hi = max(f_i - 1.5 * df, 0.5 / n), min(f_i + 1.5 * df, 0.5)
    return SpectralPeak(f_i, weighted, lo, hi, long=True)


def measure_frequency(x: np.ndarray) -> float | None:
    """The strongest oscillation of samples ``x``, cycles per sample, or None if there is none.

    :func:`strongest_peak` refined by a bounded search of the windowed DFT
    power (far below the bin width; on block moments for long traces, same
    estimator and tolerance).
    """
    peak = strongest_peak(x)
    return None if peak is None else peak.refine()


# --------------------------------------------------------------------------- per-block Fourier fits
def highest_harmonic(samples_per_period: float, cap: int) -> int:
    """The highest harmonic a block fit uses: :data:`NYQUIST_FRACTION` x samples per period, at most ``cap``."""
    return int(min(cap, math.floor(NYQUIST_FRACTION * samples_per_period)))


def block_layout(n_samples: int, samples_per_block: float) -> tuple[int, int, int]:
    """(samples per block L, number of whole blocks, first sample used) of a trace cut into blocks.

    L is ``samples_per_block`` rounded; the used part is centred, dropping
    partial blocks at both ends.
    """
    L = int(round(samples_per_block))
    n_blocks = n_samples // L
    return L, n_blocks, (n_samples - n_blocks * L) // 2


#: :func:`harmonic_cos_sin` evaluates cos and sin directly for the first this many harmonics and at every
#: multiple of it; the others by one angle addition from those (~sqrt of the usual 60 harmonics).
HARMONIC_ANCHOR = 8


def harmonic_cos_sin(phase: np.ndarray, K: int, out_cos: np.ndarray | None = None,
                     out_sin: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """cos(n phase) and sin(n phase) for n = 1..K, each (K, phase.size) (into ``out_cos``/``out_sin`` when given,
    any strides); ``phase`` in rad.

    Harmonics 1..B and every multiple of B (B = :data:`HARMONIC_ANCHOR`) are evaluated directly; harmonic
    j B + m as cos(j B phase + m phase) by one angle addition of two direct values (error a few units in the
    last place of 1, as small as the rounding of the argument n phase itself), with ~4x fewer trigonometric
    calls: the Fourier designs and weak-form test functions of a fit were ~8 % of its time in them.
    """
    phase = np.asarray(phase, dtype=float)
    c = np.empty((K, phase.size)) if out_cos is None else out_cos
    s = np.empty((K, phase.size)) if out_sin is None else out_sin
    B = min(HARMONIC_ANCHOR, K)
    first = np.arange(1, B + 1)[:, None] * phase
    np.cos(first, out=c[:B])
    np.sin(first, out=s[:B])
    for k0 in range(B, K, B):  # rows k0 .. k0 + m - 1 hold harmonics k0 + 1 .. k0 + m
        anchor = k0 * phase
        ca, sa = np.cos(anchor), np.sin(anchor)
        m = min(B, K - k0)
        np.multiply(ca, c[:m], out=c[k0:k0 + m])
        c[k0:k0 + m] -= sa * s[:m]
        np.multiply(sa, c[:m], out=s[k0:k0 + m])
        s[k0:k0 + m] += ca * s[:m]
    return c, s


def fourier_design(s: np.ndarray, omega: float, K: int) -> np.ndarray:
    """Columns 1, cos(n w s), sin(n w s) for n = 1..K (interleaved); ``omega`` in radians per unit of ``s``."""
    s = np.asarray(s, dtype=float)
    design = np.empty((s.size, 2 * K + 1))
    design[:, 0] = 1.0
    harmonic_cos_sin(omega * s, K, out_cos=design[:, 1::2].T, out_sin=design[:, 2::2].T)
    return design


def least_squares_projector(design: np.ndarray) -> np.ndarray:
    """(D^T D)^-1 D^T of a design (rows: samples) via QR.

    Well conditioned (a Fourier basis with K <= 0.45 samples per period is nearly
    orthogonal over a period) and far cheaper than an SVD-based pseudo-inverse.
    """
    q, r = np.linalg.qr(design)
    return np.linalg.solve(r, q.T)


def noise_variance_factor(projector: np.ndarray) -> np.ndarray:
    """diag(P P^T): variance of each coefficient per unit white-noise variance of the samples."""
    return np.einsum("kl,kl->k", projector, projector)


def amplitude_change(amplitude: np.ndarray) -> float:
    """Relative change of per-block amplitudes across the trace from a linear fit (0 = steady; < 3 blocks: 0)."""
    if amplitude.size < 3:
        return 0.0
    slope = np.polyfit(np.arange(amplitude.size), amplitude, 1)[0]
    return float(abs(slope) * amplitude.size / amplitude.mean())


#: Relative amplitude change across a record above which it is a transient (the not-steady warning, the drive
#: search, and the averages over periods taken over its settled end only).
TRANSIENT_CHANGE = 0.02
#: The settled end of a transient: the last periods within this fraction of the final amplitude.
SETTLED_FRACTION = 0.05
#: A change of the amplitude must also exceed this many times the lever's thermal rms deflection (relative to the
#: amplitude) to be a transient. The thermal motion moves each period's amplitude by up to ~sqrt(k_B T / k) and
#: wanders over Q / pi periods: a linear fit over the record then reads a "change" of up to ~1.5 of it when the
#: record is shorter than that wander (Q 250 in air), ~0.5-0.8 of it when the periods decorrelate (liquid). A soft
#: lever in liquid (k 0.3-1 N/m: 64-117 pm on a 5 nm amplitude) read 2.2-2.4 % on clean steady records and was
#: taken for a transient (the warning and the drive search); a stiff lever in air (k 40 N/m: 10 pm on 10 nm, a
#: limit of 0.4 %) keeps :data:`TRANSIENT_CHANGE`.
THERMAL_CHANGE_MULTIPLE = 4.0


def transient_limit(amplitude: float, thermal_variance: float = 0.0) -> float:
    """The relative amplitude change above which a record is a transient: :data:`TRANSIENT_CHANGE`, or
    :data:`THERMAL_CHANGE_MULTIPLE` x the thermal rms deflection sqrt(``thermal_variance``) (k_B T / k, m^2; 0
    when unknown) over the mean ``amplitude`` (m) where that is larger."""
    if thermal_variance <= 0 or not amplitude > 0:
        return TRANSIENT_CHANGE
    return max(TRANSIENT_CHANGE, THERMAL_CHANGE_MULTIPLE * math.sqrt(thermal_variance) / amplitude)


def changes_like_a_transient(amplitude: np.ndarray, thermal_variance: float = 0.0) -> bool:
    """True when the per-block ``amplitude`` (m) changes across the record by more than :func:`transient_limit`
    (``thermal_variance``: k_B T / k, m^2; 0 when unknown): not in steady state."""
    return amplitude_change(amplitude) > transient_limit(float(np.mean(amplitude)), thermal_variance)


def settled_start(amplitude: np.ndarray, thermal_variance: float = 0.0) -> int:
    """First block of the settled end of a record (0 if it is steady, :func:`transient_limit`): the last blocks
    within :data:`SETTLED_FRACTION` of the final amplitude, and at least the last fifth (at least 3 blocks).

    Averages over the periods of a transient at equal drive phase mix periods of other amplitudes and phases
    (before the tip reached the sample, while the free response beat with the drive)."""
    B = amplitude.size
    if B < 3 or not changes_like_a_transient(amplitude, thermal_variance):
        return 0
    tail = max(3, B // 5)
    final = float(np.median(amplitude[-tail:]))
    outside = np.flatnonzero(np.abs(amplitude - final) > SETTLED_FRACTION * final)
    first = int(outside[-1]) + 1 if outside.size else 0
    return max(0, min(first, B - tail))


def apply_rows(matrix: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """``matrix`` (r, l) applied to every block (b, l, m) -> (b, r, m), as one BLAS matrix product."""
    b, l, m = blocks.shape
    flat = np.ascontiguousarray(blocks.transpose(1, 0, 2)).reshape(l, b * m)
    return (matrix @ flat).reshape(matrix.shape[0], b, m).transpose(1, 0, 2)


def rotation(start_times: np.ndarray, omega: float, K: int) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin (n, K) of n w t0 for each start time t0: what :func:`rotate_to_global` turns by."""
    theta = np.outer(start_times, np.arange(1, K + 1)) * omega
    return np.cos(theta), np.sin(theta)


def rotate_to_global(local: np.ndarray, start_times: np.ndarray, omega: float,
                     turn: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Turn rows against cos/sin(n w s) of local time s into rows against cos/sin(n w t), t = start + s.

    Layout (n_windows, 2K+1, m) with rows [0, cos 1, sin 1, cos 2, ...]. ``turn``: :func:`rotation` of
    these start times when already at hand (the same values: saves 2 n K cos/sin).
    """
    K = (local.shape[1] - 1) // 2
    c, s = rotation(start_times, omega, K) if turn is None else turn
    c, s = c[:local.shape[0], :, None], s[:local.shape[0], :, None]
    out = np.empty_like(local)  # every row written below (a copy of `local` first was a wasted pass)
    out[:, 0, :] = local[:, 0, :]
    a, b = local[:, 1::2, :], local[:, 2::2, :]
    out[:, 1::2, :] = c * a - s * b
    out[:, 2::2, :] = s * a + c * b
    return out
