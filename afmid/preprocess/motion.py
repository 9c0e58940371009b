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

PERIODIC, PERIOD_DOUBLING, NON_PERIODIC = "periodic", "period doubling", "non-periodic"


@dataclass
class Motion:
    """What the per-period coefficients say about the motion."""

    kind: str  # PERIODIC, PERIOD_DOUBLING or NON_PERIODIC
    change: float  # rms second difference of the per-period coefficients / amplitude (median over periods)
    expected: float  # the same expected from noise and thermal wander
    two_period_ratio: float  # median |X[b+2] - X[b]|^2 / median |X[b+1] - X[b]|^2

    @property
    def non_periodic(self) -> bool:
        return self.kind != PERIODIC

    def words(self) -> str:
        """One phrase for the console: what was found and how large it is."""
        if not self.non_periodic:
            return "periodic"
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
    if second <= threshold:
        kind = PERIODIC
    elif ratio < PERIOD_TWO_RATIO:
        kind = PERIOD_DOUBLING
    else:
        kind = NON_PERIODIC
    return Motion(kind, change, math.sqrt(expected) / amplitude, ratio)


def fit_warning(motion: Motion, noise_rms: float) -> str:
    """The fit's warning for non-periodic motion (``noise_rms``: the per-period fits' residual, m)."""
    return (f"warning: {motion.words()}; the trajectory is not smoothed across periods. The per-period Fourier "
            f"series cannot follow motion that does not repeat within a period: their residual "
            f"({noise_rms * 1e12:.3g} pm rms) counts as detector noise, so the noise floor is overstated and an "
            "error at the floor does not prove the model (on simulated chaotic traces H stayed 18 % off)")
