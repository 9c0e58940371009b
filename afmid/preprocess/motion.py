"""Is the motion periodic? Period doubling and chaos from the per-period Fourier coefficients.

Tapping can bifurcate: a soft lever with strong adhesion, driven below
resonance, alternates between two periods (period doubling) or never repeats
(chaos). The fit's smoother (a Kalman smoother across periods, which assumes
the motion wanders slowly around one periodic orbit) then averages different
orbits into one that does not exist and biases the force law (the Hamaker
constant by +11 % on such a trace); ``inspect`` would count the
period-to-period change as noise.

The statistic is the second difference of each period's coefficient vector,
X[b+1] - 2 X[b] + X[b-1]: white detector noise gives it 6 x the coefficient
noise variance, thermal motion at most 6 x its variance k_B T / k (periods
fully decorrelated: driven off resonance, the thermal motion near f0 beats
against the drive within a few periods; an Ornstein-Uhlenbeck wander with the
lever's correlation time, the smoother's model, underestimates it: it flagged
noisy periodic traces of a 2 N/m lever at Q 30 driven at 0.9 f0), and a slow change of the
motion (a settling amplitude, a drift, the onset of tapping taken over a few
periods) almost nothing; alternating or chaotic periods make it as large as
the change itself. The median over periods is compared with that expectation
(and with :data:`RELATIVE_FLOOR` of the amplitude, so a noise-free trace's
numerical residue does not count). Period doubling: the coefficients two
periods apart agree (their median squared difference is below
:data:`PERIOD_TWO_RATIO` of the one-period difference); otherwise the motion
is non-periodic (chaotic or of a longer period).

Two checks keep a noisy or slowly modulated record from being called chaos (a real record, whose
per-period amplitude wanders by 0.75 % with a lag-1 autocorrelation of 0.74 under the amplitude feedback of a
scanning tip, was "chaos: no two periods repeat"):

- **Coherence.** A change of orbit (period doubling, chaos, the tip's thermal wander) moves the harmonics
  together: the correlation matrix of the second differences across the coefficients has one eigenvalue far
  above the rest (70-75 of 91 on the chaotic and bifurcated simulated traces). Noise moves each coefficient on
  its own; its largest eigenvalue stays below the Marchenko-Pastur edge (1 + sqrt(C / N))^2 of independent
  columns (C coefficients, N rows: every third second difference, which are independent for noise that does not
  correlate across periods). Detector noise is coloured (on the real record its power falls 1000-fold from
  0.1 to 20 MHz), so the per-period fits' residual, which is mostly the noise above the harmonics, understates
  the noise of the coefficients (there 60-fold in variance) and the second differences exceed the expectation;
  an excess that is incoherent (largest eigenvalue below :data:`COHERENCE_MARGIN` times the edge) and below
  :data:`INCOHERENT_CEILING` of the amplitude is that noise, not a non-periodic motion.
- **Slow modulation.** The first-harmonic amplitude varies from period to period with a lag-1 autocorrelation of
  at least :data:`MODULATION_CORRELATION` (and 4 standard errors of a white series, 4 / sqrt(B)), and its slowly
  varying part (the lag-1 autocovariance: the period-to-period noise does not correlate) exceeds
  :data:`MODULATION_NOISE_FACTOR` times the amplitude noise and the lever's thermal wander: the feedback or the
  topography under a scanning tip changes the motion over many periods. It is named with its size, correlation
  time (the lag where the autocorrelation falls to 1/e of its lag-1 value) and bandwidth (the frequency below
  which half of the amplitude's variance above its white level lies). Such a motion still wanders around one
  periodic orbit: the fit's smoother (built for that) stays on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: The median squared second difference must exceed its noise expectation by this factor (5 sigma in rms).
NOISE_FACTOR = 25.0
#: ... and its rms must exceed this fraction of the oscillation amplitude (where the thermal motion is not
#: known, as in ``inspect``, this alone guards against it; the bifurcated traces of the tests change by
#: 20-100 % of the amplitude from one period to the next).
RELATIVE_FLOOR = 0.02
#: Period doubling when the two-period change is below this fraction of the one-period change (squared).
PERIOD_TWO_RATIO = 0.1
#: Fewer periods than this and the motion is not judged.
MIN_PERIODS = 8

#: An incoherent excess counts as noise while the largest eigenvalue of the second differences' correlation matrix
#: stays below this multiple of the Marchenko-Pastur edge (its Tracy-Widom fluctuations and the rows' finite
#: number; measured: 2.6 on the real record against an edge of 3.2; 72-76 on the simulated chaos and doubling).
COHERENCE_MARGIN = 1.5
#: ... and the change stays below this fraction of the amplitude: no usable detector adds noise that changes the
#: periods by a fifth of the amplitude; beyond it the verdict stays non-periodic.
INCOHERENT_CEILING = 0.2
#: Coefficients whose second differences vary less than this fraction of the loudest one's (in variance) are left
#: out of the coherence test.
QUIET_COLUMN = 0.1
#: Rows (every third second difference) needed for the coherence test.
MIN_COHERENCE_ROWS = 8
#: A slow modulation: the amplitude's lag-1 autocorrelation is at least this ...
MODULATION_CORRELATION = 0.5
#: ... and its slowly varying part exceeds this many times the amplitude noise and thermal wander (in sd).
MODULATION_NOISE_FACTOR = 3.0

PERIODIC, PERIOD_DOUBLING, NON_PERIODIC = "periodic", "period doubling", "non-periodic"


@dataclass
class Modulation:
    """A slow modulation of the first-harmonic amplitude (periods, fractions of the amplitude)."""

    amplitude_sd: float  # sd of the slowly varying part / the median amplitude
    correlation_periods: float  # lag (periods) where the autocorrelation falls to 1/e of its lag-1 value
    bandwidth_cycles: float  # cycles per period below which half the excess variance lies
    lag1: float  # lag-1 autocorrelation of the amplitude

    def words(self, drive_frequency: float | None = None) -> str:
        band = (f"~{_hz(self.bandwidth_cycles * drive_frequency)}" if drive_frequency
                else f"~{self.bandwidth_cycles:.2g} cycles per period")
        return (f"slow modulation (amplitude sd {100 * self.amplitude_sd:.2g} %, correlation time "
                f"~{self.correlation_periods:.0f} periods, bandwidth {band}: a feedback or topography under a "
                "scanning tip)")


def _hz(value: float) -> str:
    return f"{float(f'{value / 1e3:.2g}'):g} kHz" if value >= 1e3 else f"{float(f'{value:.2g}'):g} Hz"


@dataclass
class Motion:
    """What the per-period coefficients say about the motion."""

    kind: str  # PERIODIC, PERIOD_DOUBLING or NON_PERIODIC
    change: float  # rms second difference of the per-period coefficients / amplitude (median over periods)
    expected: float  # the same expected from noise and thermal wander
    two_period_ratio: float  # median |X[b+2] - X[b]|^2 / median |X[b+1] - X[b]|^2
    modulation: Modulation | None = None  # a slow modulation of the amplitude (None: none found)
    incoherent: bool = False  # the change exceeds the noise expectation but independently per coefficient (noise)

    @property
    def non_periodic(self) -> bool:
        return self.kind != PERIODIC

    def words(self, drive_frequency: float | None = None) -> str:
        """One phrase for the console: what was found and how large it is (``drive_frequency``, Hz: the
        modulation's bandwidth in Hz)."""
        if not self.non_periodic:
            parts = ["periodic"]
            if self.modulation is not None:
                parts.append(self.modulation.words(drive_frequency) + ", not chaos")
            if self.incoherent:
                parts.append(f"the periods differ by {100 * self.change:.2g} % of the amplitude (white noise would "
                             f"make {100 * self.expected:.2g} %) but independently at every harmonic: noise stronger "
                             "within the harmonics' band than the per-period fits' residual shows, not a change of "
                             "orbit")
            return "; ".join(parts)
        what = ("non-periodic motion (period doubling: consecutive periods alternate between two orbits)"
                if self.kind == PERIOD_DOUBLING else
                "non-periodic motion (chaos: no two periods repeat), not noise")
        return (f"{what}; the periods differ by {100 * self.change:.2g} % of the amplitude (noise would make "
                f"{100 * self.expected:.2g} %)")


def classify(coef: np.ndarray, noise_var: np.ndarray, thermal_var: float = 0.0) -> Motion | None:
    """Classify the motion from per-period coefficients ``coef`` (B, 2K+1) [c0, a1, b1, ...] in global phase.

    ``noise_var`` (2K+1,) is the white-noise variance of each coefficient; ``thermal_var`` the variance of the
    thermal deflection (k_B T / k, m^2; 0 when unknown).
    None when there are fewer than :data:`MIN_PERIODS` periods.
    """
    B = coef.shape[0]
    if B < MIN_PERIODS:
        return None
    amplitude = float(np.median(np.hypot(coef[:, 1], coef[:, 2]))) if coef.shape[1] > 2 else 0.0
    if amplitude <= 0:
        return None
    second = np.median(np.sum((coef[2:] - 2 * coef[1:-1] + coef[:-2]) ** 2, axis=1))
    one = np.median(np.sum((coef[1:] - coef[:-1]) ** 2, axis=1))
    two = np.median(np.sum((coef[2:] - coef[:-2]) ** 2, axis=1))
    expected = 6.0 * (float(np.sum(noise_var)) + thermal_var)
    change = math.sqrt(second) / amplitude
    threshold = max(NOISE_FACTOR * expected, (RELATIVE_FLOOR * amplitude) ** 2)
    ratio = float(two / one) if one > 0 else 1.0
    incoherent = False
    if second <= threshold:
        kind = PERIODIC
    elif ratio < PERIOD_TWO_RATIO:
        kind = PERIOD_DOUBLING
    else:
        kind = NON_PERIODIC
        incoherent = change < INCOHERENT_CEILING and moves_incoherently(coef)
        if incoherent:
            kind = PERIODIC
    modulation = slow_modulation(coef, noise_var, thermal_var) if kind == PERIODIC else None
    return Motion(kind, change, math.sqrt(expected) / amplitude, ratio, modulation, incoherent)


def moves_incoherently(coef: np.ndarray) -> bool:
    """The period-to-period change of ``coef`` (B, C) is independent across the coefficients (noise), not a change
    of orbit: the largest eigenvalue of the correlation matrix of every third second difference stays below
    :data:`COHERENCE_MARGIN` times the Marchenko-Pastur edge (1 + sqrt(C / N))^2. False when there are too few
    rows to tell."""
    second = (coef[2:] - 2 * coef[1:-1] + coef[:-2])[::3]
    rows, columns = second.shape
    spread = second.std(axis=0)
    # Columns far quieter than the loudest carry none of the excess: normalised, a tiny coherent part there (the
    # thermal wander of the orbit under band-limited noise) would pass for a change of orbit.
    used = spread**2 >= QUIET_COLUMN * float(np.max(spread**2)) if spread.size else spread > 0
    used &= spread > 0
    if rows < MIN_COHERENCE_ROWS or used.sum() < 2:
        return False
    z = (second[:, used] - second[:, used].mean(axis=0)) / spread[used]
    columns = int(used.sum())
    # the largest eigenvalue of the correlation matrix = the largest squared singular value of z / sqrt(rows)
    largest = float(np.linalg.svd(z, compute_uv=False)[0] ** 2 / rows)
    edge = (1.0 + math.sqrt(columns / rows)) ** 2
    return largest < COHERENCE_MARGIN * edge


def slow_modulation(coef: np.ndarray, noise_var: np.ndarray, thermal_var: float = 0.0) -> Modulation | None:
    """A slow modulation of the first-harmonic amplitude of ``coef`` (B, 2K+1), or None (see the module
    docstring: lag-1 autocorrelation, the slow part's size against the noise and the thermal wander)."""
    B = coef.shape[0]
    amplitude = np.hypot(coef[:, 1], coef[:, 2])
    typical = float(np.median(amplitude))
    centred = amplitude - amplitude.mean()
    variance = float(np.mean(centred**2))
    if B < MIN_PERIODS or typical <= 0 or variance <= 0:
        return None
    autocovariance = np.array([np.mean(centred[lag:] * centred[:B - lag]) for lag in range(1, B // 2)])
    lag1 = float(autocovariance[0] / variance)
    slow = max(float(autocovariance[0]), 0.0)  # the noise does not correlate from one period to the next
    # amplitude noise: half the first harmonic's cos/sin variance (the part along the phasor) and the thermal
    # in-phase wander k_B T / (2 k)
    floor = 0.5 * float(noise_var[1] + noise_var[2]) + 0.5 * thermal_var
    if lag1 < max(MODULATION_CORRELATION, 4.0 / math.sqrt(B)) or slow <= MODULATION_NOISE_FACTOR**2 * floor:
        return None
    below = np.flatnonzero(autocovariance < autocovariance[0] / math.e)
    correlation = float(below[0] + 1) if below.size else float(B // 2)
    power = np.abs(np.fft.rfft(centred)) ** 2
    cycles = np.fft.rfftfreq(B)  # cycles per period
    white = float(np.median(power[power.size // 2:]))  # the fastest half: noise
    excess = np.clip(power[1:] - white, 0.0, None)
    if excess.sum() <= 0:
        return None
    half = int(np.searchsorted(np.cumsum(excess) / excess.sum(), 0.5))
    return Modulation(math.sqrt(slow) / typical, correlation, float(cycles[1:][half]), lag1)


def fit_warning(motion: Motion, noise_rms: float) -> str:
    """The fit's warning for non-periodic motion (``noise_rms``: the per-period fits' residual, m)."""
    return (f"warning: {motion.words()}; the trajectory is not smoothed across periods. The per-period Fourier "
            f"series cannot follow motion that does not repeat within a period: their residual "
            f"({noise_rms * 1e12:.3g} pm rms) counts as detector noise, so the noise floor is overstated and an "
            "error at the floor does not prove the model (on simulated chaotic traces H stayed 18 % off)")
