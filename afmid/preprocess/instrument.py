"""The instrument between the tip and the recorded deflection: detector filter and higher flexural modes.

Two optional config declarations (pinned keys)::

    data:
      detector: {bandwidth: HZ, filter: butterworth | bessel | first_order, order: N}
    cantilever:
      higher_modes: [{resonance_frequency: HZ, quality_factor: Q, spring_constant: N/m}, ...]

**Detector.** The photodetector / anti-alias chain is a causal low-pass filter G(s) whose -3 dB point is
``bandwidth``: an analog Butterworth or Bessel (magnitude-normalised, ``scipy.signal.bessel(norm="mag")``) of
the given order, or a first-order RC section (order 1 only). All three are all-pole filters, G(s) = 1 / P(s)
with P a polynomial, so the inverse is the differential operator P(d/dt): stable and exact on a Fourier series.
The recorded deflection y is G * x; the fit recovers the tip deflection per drive harmonic,
X_n = P(i n w) Y_n (:meth:`Instrument.tip_gain`), up to the harmonic where |P| stays below
:data:`MAX_INVERSE_GAIN` (beyond it the harmonics are left as measured and the instrument says so).

**Higher modes.** The tip deflection is the sum of the modes, x = sum_i x_i, each mode an oscillator
k_i (x_i + x_i'' / w_i^2 + x_i' / (w_i Q_i)) = F_tip driven by the same tip force (tip-sample force and drive).
Per harmonic, X(w) = H(w) F_tip(w) with H(w) = sum_i 1 / (k_i (1 - w^2/w_i^2 + i w / (w_i Q_i))). The fit's
equation is the first mode's operator; it stays exact if it acts on the *equivalent single-mode deflection*
x_eq with X_eq(w) = H_1(w) / H(w) X(w) (:meth:`Instrument.equation_gain`): the deflection a single-mode lever
would show under the same tip force. The library is evaluated on the tip deflection x itself.

Orders of magnitude (Euler-Bernoulli rectangular lever, documented in docs/file-formats.md, never assumed
here): f2 = 6.27 f1, k2 ~ 39.3 k1, Q2 ~ 2-3 Q1 in air.

Everything here is SI; frequencies in Hz, responses dimensionless (detector) or m/N (modes).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from afmid.registry import Registry

#: Largest |1 / G| at a harmonic the fit inverts; higher harmonics are left as measured (where the detector
#: passes less than 1 % of the motion, inverting it would multiply the noise by more than 100).
MAX_INVERSE_GAIN = 100.0


@dataclass(frozen=True)
class FilterKind:
    """A detector filter family: its analog prototype (numerator b, denominator a of G(s)) for an order and a
    -3 dB angular frequency wc (rad/s)."""

    name: str
    title: str
    references: str
    analog: Callable[[int, float], tuple[np.ndarray, np.ndarray]]
    max_order: int


def _butterworth(order: int, wc: float):
    from scipy import signal

    return signal.butter(order, wc, btype="low", analog=True)


def _bessel(order: int, wc: float):
    from scipy import signal

    return signal.bessel(order, wc, btype="low", analog=True, norm="mag")


def _first_order(order: int, wc: float):
    return np.array([1.0]), np.array([1.0 / wc, 1.0])


def _check_filter(kind: FilterKind) -> None:
    # What registration can check without designing a filter: designing one imports scipy.signal (~1 s), which
    # every afmid process paid on importing the fit (a map's client and each of its workers). That each family
    # passes DC with gain 1 at every order is held by tests/preprocess/test_instrument.py.
    if not callable(kind.analog):
        raise ValueError("analog must be a function (order, wc) -> (b, a)")
    if not (isinstance(kind.max_order, int) and kind.max_order >= 1):
        raise ValueError(f"max_order must be a positive integer, got {kind.max_order!r}")


FILTERS: Registry[FilterKind] = Registry("detector filter", _check_filter)
FILTERS.register(FilterKind("butterworth", "Butterworth low-pass (maximally flat)", "scipy.signal.butter",
                            _butterworth, 12))
FILTERS.register(FilterKind("bessel", "Bessel low-pass, -3 dB at the bandwidth (maximally flat delay)",
                            "scipy.signal.bessel(norm='mag')", _bessel, 12))
FILTERS.register(FilterKind("first_order", "single-pole RC low-pass", "G = 1 / (1 + s / wc)", _first_order, 1))


@dataclass(frozen=True)
class Detector:
    """A causal low-pass between the deflection and the recorded samples."""

    bandwidth: float  # -3 dB frequency, Hz
    filter: str
    order: int

    def analog(self) -> tuple[np.ndarray, np.ndarray]:
        """(b, a): G(s) = b(s) / a(s), s in rad/s."""
        return FILTERS.get(self.filter).analog(self.order, 2.0 * math.pi * self.bandwidth)

    def response(self, frequency) -> np.ndarray:
        """G(i 2 pi f) at frequencies f (Hz): the complex gain from deflection to recorded samples."""
        b, a = self.analog()
        s = 2j * math.pi * np.asarray(frequency, dtype=float)
        return np.polyval(b, s) / np.polyval(a, s)

    def digital(self, sample_rate: float) -> np.ndarray:
        """Second-order sections of the filter discretised at ``sample_rate`` (Hz) by the bilinear transform
        pre-warped at the bandwidth (so the -3 dB point stays where declared)."""
        from scipy import signal

        b, a = self.analog()
        wc = 2.0 * math.pi * self.bandwidth
        z, p, k = signal.tf2zpk(b, a)
        # Pre-warp: scale s so that wc maps to the digital frequency wc.
        warp = 2.0 * sample_rate * math.tan(wc / (2.0 * sample_rate)) / wc
        z, p, k = z * warp, p * warp, k * warp ** (len(p) - len(z))
        zd, pd, kd = signal.bilinear_zpk(z, p, k, fs=sample_rate)
        return signal.zpk2sos(zd, pd, kd)


@dataclass(frozen=True)
class Mode:
    """A flexural mode of the lever seen at the tip."""

    resonance_frequency: float  # Hz
    quality_factor: float
    spring_constant: float  # N/m

    def compliance(self, frequency) -> np.ndarray:
        """H_i(i 2 pi f) = 1 / (k_i (1 - r^2 + i r / Q_i)), r = f / f_i: deflection per tip force, m/N."""
        r = np.asarray(frequency, dtype=float) / self.resonance_frequency
        return 1.0 / (self.spring_constant * (1.0 - r * r + 1j * r / self.quality_factor))


@dataclass(frozen=True)
class Instrument:
    """The declared instrument: a detector (or None) and the lever's higher modes (may be empty)."""

    detector: Detector | None = None
    higher_modes: tuple[Mode, ...] = ()

    @property
    def ideal(self) -> bool:
        return self.detector is None and not self.higher_modes

    def describe(self) -> str:
        parts = []
        if self.detector is not None:
            d = self.detector
            parts.append(f"detector {d.filter} order {d.order}, bandwidth {d.bandwidth / 1e3:.4g} kHz")
        for m in self.higher_modes:
            parts.append(f"mode at {m.resonance_frequency / 1e3:.4g} kHz (k {m.spring_constant:.3g} N/m, "
                         f"Q {m.quality_factor:.3g})")
        return "; ".join(parts) if parts else "ideal"

    def tip_gain(self, frequency) -> np.ndarray:
        """1 / G(f): recorded -> tip deflection per harmonic (1 where no detector, and where |1/G| exceeds
        :data:`MAX_INVERSE_GAIN`: left as measured)."""
        f = np.asarray(frequency, dtype=float)
        if self.detector is None:
            return np.ones(f.shape, dtype=complex)
        inverse = 1.0 / self.detector.response(f)
        return np.where(np.abs(inverse) <= MAX_INVERSE_GAIN, inverse, 1.0 + 0j)

    def invertible_up_to(self, frequency) -> float:
        """The highest of ``frequency`` (Hz) up to which every detector inverse stays within the limit."""
        f = np.sort(np.asarray(frequency, dtype=float))
        if self.detector is None:
            return float(f[-1])
        ok = np.abs(1.0 / self.detector.response(f)) <= MAX_INVERSE_GAIN
        bad = np.flatnonzero(~ok)
        return float(f[-1]) if bad.size == 0 else (float(f[bad[0] - 1]) if bad[0] > 0 else 0.0)

    def compliance(self, cantilever, frequency) -> np.ndarray:
        """H(f) = sum of the modes' compliances, m/N (the first mode from ``cantilever``: afmid.io.trace.Cantilever)."""
        first = Mode(cantilever.resonance_frequency, cantilever.quality_factor, cantilever.spring_constant)
        return sum((m.compliance(frequency) for m in self.higher_modes), first.compliance(frequency))

    def equation_gain(self, cantilever, frequency) -> np.ndarray:
        """H_1(f) / H(f): tip deflection -> the equivalent single-mode deflection the fit's equation sees."""
        f = np.asarray(frequency, dtype=float)
        if not self.higher_modes:
            return np.ones(f.shape, dtype=complex)
        first = Mode(cantilever.resonance_frequency, cantilever.quality_factor, cantilever.spring_constant)
        return first.compliance(f) / self.compliance(cantilever, f)


IDEAL = Instrument()


def from_config(config) -> Instrument:
    """The instrument a :class:`afmid.config.RunConfig` declares (IDEAL when nothing is)."""
    det = config.data.detector
    detector = None if det is None else Detector(float(det.bandwidth), det.filter, int(det.resolved_order))
    modes = tuple(Mode(float(m.resonance_frequency), float(m.quality_factor), float(m.spring_constant))
                  for m in config.cantilever.higher_modes)
    return Instrument(detector, modes)


def apply_per_harmonic(coef: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """Multiply Fourier coefficients (..., 2K+1, m) laid out [c0, a1, b1, ..., aK, bK] (cos/sin of n w t) by a
    complex gain per harmonic (``gain``: K+1 values, harmonic 0..K): a linear time-invariant filter acting on the
    series, a_n cos + b_n sin -> Re(g) (a cos + b sin) + Im(g) (b cos - a sin)."""
    out = coef * gain[0].real
    a, b = coef[..., 1::2, :], coef[..., 2::2, :]
    g = gain[1:][:, None]
    out[..., 1::2, :] = g.real * a + g.imag * b
    out[..., 2::2, :] = g.real * b - g.imag * a
    return out


@dataclass
class DeflectionViews:
    """The samples the fit works on when an instrument is declared (:func:`deflection_views`)."""

    tip: np.ndarray  # m, the tip deflection (detector inverted per harmonic): the library's trajectory
    equation: np.ndarray  # m, the equivalent single-mode deflection: the equation of motion's left side
    equation_gain: np.ndarray | None  # (K+1,) complex, H_1 / H per harmonic (None: no higher mode)
    highest_inverted: int  # the highest harmonic whose detector response was inverted (K: all)

    tip_gain: np.ndarray | None = None  # (K+1,) complex, recorded -> tip per harmonic (None: ideal)
    #: m^2, sum of squared residuals of the *recorded* samples about the fit's block series (None: ideal, the
    #: fit computes it): the detector noise is measured before the inverse amplifies it
    residual_sum_squares: float | None = None

    @property
    def amplifies_noise(self) -> bool:
        """True when a detector was undone: some harmonic's noise is multiplied by |1 / G| > 1."""
        return self.tip_gain is not None and bool(np.any(np.abs(self.tip_gain) > 1.0))

    def noise_gain(self, harmonics: np.ndarray) -> np.ndarray | None:
        """|gain|^2 from the recorded samples to the equation's deflection, per row of harmonic number
        ``harmonics``: the factor on the detector noise variance of each row (None: ideal, 1 everywhere)."""
        if self.tip_gain is None:
            return None
        gain = self.tip_gain if self.equation_gain is None else self.tip_gain * self.equation_gain
        return np.abs(gain[harmonics]) ** 2

    def equation_coefficients(self, X: np.ndarray) -> np.ndarray:
        """Per-block coefficients (B, 2K+1, m) of the tip -> those of the equivalent single-mode deflection."""
        return X if self.equation_gain is None else apply_per_harmonic(X, self.equation_gain)


def crossfaded_series(blocks, coef: np.ndarray, n_samples: int) -> np.ndarray:
    """Samples (n_samples,) of per-block series ``coef`` (B, 2K+1, 1), global phase, blended from block to block.

    Each block's series is evaluated over its block and half a block on either side, weighted by
    sin^2(pi (j + 1/2) / 2L) (j = 0 .. 2L-1), so neighbouring weights add to 1: the result is continuous
    where the blocks' series differ (a correction made block by block would otherwise jump at every block
    boundary when the motion wanders, and a jump feeds every harmonic of the weak form). At the two ends the
    single block's series, normalised by its weight.
    """
    from afmid.preprocess.periods import fourier_design

    L, B = blocks.L, blocks.n_blocks
    half = L // 2
    local = blocks.to_local(coef)[..., 0]  # (B, 2K+1), against cos/sin of n w s from each block's start
    s = (np.arange(2 * L) - half) * blocks.dt
    design = fourier_design(s, blocks.omega, blocks.K)
    weight = np.sin(np.pi * (np.arange(2 * L) + 0.5) / (2 * L)) ** 2
    total = np.zeros(n_samples + 4 * L)  # padded on both sides: windows may reach past the trace
    weights = np.zeros_like(total)
    origin = 2 * L + blocks.start - half  # index in ``total`` of block 0's window start
    for parity in (0, 1):
        chosen = np.arange(parity, B, 2)
        if chosen.size == 0:
            continue
        values = (local[chosen] @ design.T) * weight  # (n, 2L)
        first = origin + chosen[0] * L
        span = slice(first, first + chosen.size * 2 * L)
        total[span] += values.ravel()
        weights[span] += np.tile(weight, chosen.size)
    total, weights = total[2 * L:2 * L + n_samples], weights[2 * L:2 * L + n_samples]
    return np.divide(total, weights, out=np.zeros(n_samples), where=weights > 0)


@dataclass(frozen=True)
class RecordedSeries:
    """What :func:`deflection_views` takes of the recorded samples before any instrument is undone: the same for
    every instrument, so refits of one record with other instruments declared (the diagnosis's search for an
    undeclared one) make it once (:func:`recorded_series`)."""

    x: np.ndarray  # m, the recorded samples
    measured: np.ndarray  # (B, 2K+1, 1) m, their block series' coefficients, global phase
    spectrum: np.ndarray  # rfft of the residual about the crossfaded block series (m)
    frequency: np.ndarray  # Hz, the spectrum's frequencies
    residual_sum_squares: float  # m^2, of the used samples about the block series

    def made_from(self, x: np.ndarray, blocks) -> bool:
        """Whether this is the series of samples ``x`` on ``blocks`` (the same arrays, not equal copies)."""
        return self.x is x and self.measured.shape[0] == blocks.n_blocks


def recorded_series(x: np.ndarray, blocks) -> RecordedSeries:
    """The instrument-free part of :func:`deflection_views` for samples ``x`` (m) on ``blocks``."""
    measured = blocks.project(x)
    spectrum = np.fft.rfft(x - crossfaded_series(blocks, measured, x.size))
    residual = x[blocks.used] - blocks.synthesize(measured)[:, 0]
    return RecordedSeries(x, measured, spectrum, np.fft.rfftfreq(x.size, blocks.dt), float(np.dot(residual, residual)))


def deflection_views(x: np.ndarray, blocks, instrument: Instrument | None, cantilever,
                     recorded: RecordedSeries | None = None, equation_only: bool = False) -> DeflectionViews:
    """Undo the declared instrument on the samples ``x`` (m), block by block and harmonic by harmonic.

    ``blocks`` (afmid.preprocess.periods.HarmonicBlocks) gives the per-period Fourier fits; on the used samples the
    tip is x + sum over harmonics of (1/G - 1) X_n, the equation's deflection x + (H_1/H / G - 1) X_n (the
    residual of each block fit, noise and harmonics above K, is left as measured). Ideal instrument: ``x``
    itself for both (the same array: nothing changes). ``recorded``: :func:`recorded_series` of ``x`` on
    ``blocks`` when at hand (the same values; made here otherwise). ``equation_only``: only the equation's view
    is wanted (``tip`` is then ``x`` whatever the detector).
    """
    K = blocks.K
    if instrument is None or instrument.ideal:
        return DeflectionViews(x, x, None, K)
    if recorded is None or not recorded.made_from(x, blocks):
        recorded = recorded_series(x, blocks)
    f = np.arange(K + 1) * blocks.omega / (2.0 * math.pi)
    tip_gain = instrument.tip_gain(f)
    equation_gain = None if not instrument.higher_modes else instrument.equation_gain(cantilever, f)
    measured, spectrum = recorded.measured, recorded.spectrum
    tip_coef = apply_per_harmonic(measured, tip_gain)
    # The motion is not exactly periodic (thermal wander): what the block series leave out, the residual about
    # them, goes through the same gains by FFT, up to harmonic K + 1/2 (above it the samples stay as measured).
    # Each frequency takes the gain of its nearest harmonic: the noise model of the rows is per harmonic, and
    # between harmonics the modes' gain H_1 / H can be huge (at an antiresonance the tip does not move, and
    # inverting there would amplify the noise without bound).
    tip_fft, eq_fft = gains_between_harmonics(instrument, cantilever, f[1], tip_gain, equation_gain,
                                              recorded.frequency)
    if instrument.detector is None or (equation_only and equation_gain is not None):
        # No detector: every tip gain is 1, so the corrections below are zeros and x + 0 is x (the same bits).
        tip = x
    else:
        tip = x + crossfaded_series(blocks, tip_coef - measured, x.size) + _irfft(spectrum * (tip_fft - 1), x.size)
    if equation_gain is None:
        equation = tip
    else:
        equation = (x + crossfaded_series(blocks, apply_per_harmonic(tip_coef, equation_gain) - measured, x.size)
                    + _irfft(spectrum * (eq_fft - 1), x.size))
    inverted = instrument.invertible_up_to(f)
    return DeflectionViews(tip, equation, equation_gain, int(round(inverted / f[1])), tip_gain,
                           recorded.residual_sum_squares)


def _irfft(spectrum: np.ndarray, n: int) -> np.ndarray:
    """The real series of ``n`` samples with rfft ``spectrum``: scipy's pocketfft, the same values as numpy.fft.irfft
    and twice as fast at a prime ``n`` (the noise probe of :func:`row_noise_gain`, 353,359 samples on the HSDC
    record: 0.05 s instead of 0.09 s, once per instrument a diagnosis tries)."""
    import scipy.fft

    return scipy.fft.irfft(spectrum, n, workers=1)


def gains_between_harmonics(instrument: Instrument, cantilever, drive_frequency: float, tip_gain: np.ndarray,
                            equation_gain: np.ndarray | None, frequency: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(recorded -> tip, recorded -> equation's deflection) gains at ``frequency`` (Hz) for what the block
    series leave out (:func:`deflection_views`), given the per-harmonic gains (K + 1 values).

    Each frequency takes the detector inverse of its nearest harmonic (the noise model of the rows is per
    harmonic, and beyond harmonic K + 1/2 the samples stay as measured); the modes' gain is the exact
    H_1 / H (a higher mode's ringing between harmonics is taken out), its size capped by the larger of the two
    neighbouring harmonics' (no blow-up at an antiresonance)."""
    K = tip_gain.size - 1
    f = np.asarray(frequency, dtype=float)
    nearest = np.rint(f / drive_frequency).astype(int)
    in_band = nearest <= K
    tip_fft = np.where(in_band, tip_gain[np.minimum(nearest, K)], 1.0)
    if equation_gain is None:
        return tip_fft, tip_fft
    # The modes' gain only in the band (up to harmonic K + 1/2 of a record's ~10^5-10^6 frequencies: 14 % at the
    # 60 harmonics of an 880-sample period); every operation is elementwise, so the same values as over all.
    band = np.flatnonzero(in_band)
    f_band = f[band]
    below = np.minimum(np.floor(f_band / drive_frequency).astype(int), K)
    cap = np.maximum(np.abs(equation_gain[below]), np.abs(equation_gain[np.minimum(below + 1, K)]))
    exact = instrument.equation_gain(cantilever, f_band)
    size = np.abs(exact)
    gain = np.ones(f.shape, dtype=complex)
    gain[band] = np.where(size > cap, exact * cap / np.maximum(size, 1e-300), exact)
    # As NumPy computes tip_fft * (a temporary): into the temporary, taken as the first operand. Its complex
    # product rounds differently with the operands swapped or into a new array (measured: a third of the values
    # differ in the last bit), and the rows' weights are kept to the bit.
    return tip_fft, np.multiply(gain, tip_fft, out=gain)


#: White noise passed through the views to measure the weak-form rows' noise gain (:func:`row_noise_gain`): about
#: this many windows (2 x as many rows per harmonic: the gain known to ~5 %), at most NOISE_PROBE_SAMPLES samples.
NOISE_PROBE_WINDOWS = 400
NOISE_PROBE_SAMPLES = 400_000
#: The probe's noise is drawn from this seed: the same trace gives the same row weights (bit for bit).
NOISE_PROBE_SEED = 13


@dataclass(frozen=True)
class NoiseProbe:
    """The white noise :func:`row_noise_gain` passes through the views, on blocks like a record's: it depends on
    the record's block layout only, so refits of one record with other instruments share it (:func:`noise_probe`)."""

    blocks: object  # afmid.preprocess.periods.HarmonicBlocks laid over the probe
    noise: np.ndarray  # the probe's samples (unit variance)
    recorded: RecordedSeries  # their instrument-free part (:func:`recorded_series`)
    index: np.ndarray  # (windows, 2L + 1) sample indices of the probe's weak-form windows
    #: the rows' power on the noise itself, per weight matrix (:meth:`noise_power`): the same for every instrument
    _noise_powers: dict = dataclasses.field(default_factory=dict, compare=False, repr=False)

    def noise_power(self, weights: np.ndarray) -> np.ndarray:
        """Per row of ``weights`` (rows, 2L + 1): its summed square over the probe's windows of the noise itself
        (:func:`row_noise_gains`' denominator), made once per weight matrix."""
        key = (weights.shape, weights.tobytes())
        if key not in self._noise_powers:
            self._noise_powers[key] = _row_power(weights, self.noise[self.index])
        return self._noise_powers[key]

    def fits(self, blocks) -> bool:
        """Whether this probe was laid out for ``blocks`` (same samples per block, harmonics, projector)."""
        return (self.blocks.L == blocks.L and self.blocks.K == blocks.K and self.blocks.dt == blocks.dt
                and self.blocks.omega == blocks.omega and self.blocks.projector is blocks.projector)


def noise_probe(blocks) -> NoiseProbe:
    """The probe of :func:`row_noise_gain` for ``blocks``: NOISE_PROBE_WINDOWS windows of seeded white noise."""
    import dataclasses

    L = blocks.L
    n_windows = max(8, min(NOISE_PROBE_WINDOWS, NOISE_PROBE_SAMPLES // L - 2))
    # the same blocks (projector, harmonics) laid over the probe: n_windows + 2 blocks from its first sample
    probe = dataclasses.replace(blocks, start=0, n_blocks=n_windows + 2, t0=0.0)
    noise = np.random.default_rng(NOISE_PROBE_SEED).standard_normal(probe.n_blocks * L + 1)
    count = probe.n_blocks - 1
    index = probe.start + np.arange(count)[:, None] * L + np.arange(2 * L + 1)[None, :]
    return NoiseProbe(probe, noise, recorded_series(noise, probe), index)


def row_noise_gain(instrument: Instrument, cantilever, blocks, rows: np.ndarray, probe: NoiseProbe | None = None
                   ) -> np.ndarray | None:
    """Per weak-form row (``rows``: (rows, 2L + 1) weights over a window's samples, harmonic-interleaved as the
    windows' rows): the variance of the row on the equation's deflection of white detector noise over its
    variance on the noise itself, averaged over each cos/sin pair (None: ideal instrument, 1).

    A row of harmonic n integrates over two periods, so it sees the noise from about n - 1 to n + 1 times the
    drive frequency, and the views pass it through the gains of the neighbouring harmonics too (the block
    series' leakage, the gain between harmonics of what they leave out). Where the gain changes fast from
    harmonic to harmonic (near a higher mode the equation's gain H_1 / H is -0.105 at harmonic 6 and -1.47 at
    5 for f2 = 6.27 f0) the gain at n alone understated the row's noise: whitened residual power 5-7 at
    harmonic 6 on clean two-mode traces (1 elsewhere), the chi-square test's false alarm. Measured, not
    modelled: white noise through :func:`deflection_views` on blocks like ``blocks`` (the map is linear), the
    rows' mean squares over NOISE_PROBE_WINDOWS windows. ``probe``: :func:`noise_probe` of ``blocks`` when at
    hand (the same values; made here otherwise).
    """
    if instrument is None or instrument.ideal:
        return None
    return row_noise_gains(instrument, cantilever, blocks, [rows], probe)[0]


def row_noise_gains(instrument: Instrument, cantilever, blocks, rows: list[np.ndarray],
                    probe: NoiseProbe | None = None) -> list[np.ndarray]:
    """:func:`row_noise_gain` of each of ``rows`` (weight matrices), the probe passed through the views once."""
    if probe is None or not probe.fits(blocks):
        probe = noise_probe(blocks)
    equation = deflection_views(probe.noise, probe.blocks, instrument, cantilever, probe.recorded,
                                equation_only=True).equation
    gains = []
    windows = equation[probe.index]
    for weights in rows:
        power = [_row_power(weights, windows), probe.noise_power(weights)]
        pair = [p.copy() for p in power]
        for q, p in zip(pair, power):
            q[1::2] = q[2::2] = p[1::2] + p[2::2]
        gains.append(pair[0] / pair[1])
    return gains


def _row_power(weights: np.ndarray, windows: np.ndarray) -> np.ndarray:
    """Per row of ``weights`` (rows, 2L + 1), its summed square over ``windows`` (n, 2L + 1) of samples."""
    return np.sum((weights @ windows.T) ** 2, axis=1)


#: ``afmid inspect``: a bump in the harmonic amplitudes counts as a resonance when, at two neighbouring
#: harmonics n, n+1, the products of their ratios to the geometric mean of the harmonics two away exceed this.
#: (Measured: a second mode at 6.27 f gives 44-54; the lobes of plain contact spectra stay below 9.)
RESONANCE_BUMP = 20.0


def harmonic_resonance(amplitudes: np.ndarray, above_noise: list[int]) -> float | None:
    """Where the harmonic amplitudes (index = harmonic number) show a resonance bump, in units of the drive
    frequency, or None: a higher eigenmode between two harmonics amplifies both (no fit needed)."""
    A = np.asarray(amplitudes, dtype=float)
    ok = set(above_noise)
    best = (0.0, None)
    for n in range(3, A.size - 3):
        if not {n - 2, n - 1, n, n + 1, n + 2, n + 3} <= ok:
            continue
        ratio = [A[k] / math.sqrt(A[k - 2] * A[k + 2]) for k in (n, n + 1)]
        product = ratio[0] * ratio[1]
        if product > best[0]:
            best = (product, n + ratio[1] / (ratio[0] + ratio[1]))
    return best[1] if best[0] >= RESONANCE_BUMP else None
