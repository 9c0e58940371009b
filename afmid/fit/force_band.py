"""The force curve's whole 1-sigma band: the statistical share (the bootstrap's coefficients) with the shares of
the estimated separation (:mod:`afmid.fit.separation_share`), of the selection (:func:`selection_share`: terms
the selection dropped from an effect it kept) and of the k / Q calibration.

Each share is relative to the peak |force| and an RMS over the estimated samples, 1 sigma. The statistical
share is the spread of the model force over the bootstrap's coefficient vectors (resampled periods, the
support selected again per resample where the selection does so) at the fitted nonlinear parameters; the
separation share is the force's change along the separation's valley (d +- sigma, coefficients refitted), so
the two are distinct parts and add in quadrature, as does the calibration (a common scale of every force).

Why it matters (measured on the poor instrument, 10 pm detector noise, 50 samples per period, 50
periods, d unknown): the force error was 1.1-9.8 % of the peak where the separation share alone said 5-10 %;
on seeds where d came out within 10 pm of the truth the error (6.5-9 %) was the coefficients' own (E* and H
from 50 noisy periods), which no stated number covered. The total is what the force curve is known to.
"""

from __future__ import annotations

import math

import numpy as np

import afmid.fit.regression as regression
from afmid.fit.forces import estimated_peak, model_force_samples, model_force_spread


def statistical_share(prep, library, system, coef_samples, force_estimate: np.ndarray) -> float:
    """RMS over the estimated samples of the model force's bootstrap standard deviation, over the peak |force|
    of ``force_estimate`` (N; NaN where not estimated): relative, 1 sigma. NaN without resamples."""
    if coef_samples is None or len(coef_samples) < 2:
        return math.nan
    used, peak = estimated_peak(force_estimate)
    if peak <= 0:
        return math.nan
    spread = model_force_spread(prep, library, system, coef_samples)
    # The estimated samples are one run (the used blocks) unless the force is not finite somewhere: then a view of
    # them, not a copy as long as the trace (at 1e7 samples the copy was the fit's peak memory).
    first = int(np.argmax(used))
    stop = used.size - int(np.argmax(used[::-1]))
    values = spread[first:stop] if used[first:stop].all() else spread[used]
    if not np.isfinite(values).all():
        return math.nan
    return float(np.sqrt(np.mean(np.square(values, out=values))) / peak)  # squared in place: no second copy


def selection_share(prep, library, system, mask: np.ndarray, whole: np.ndarray, force_estimate: np.ndarray) -> float:
    """Half the RMS difference between the model force on the support ``mask`` and on ``whole`` (the support
    with the terms the selection dropped from its effects forced in: afmid.fit.undetermined.whole_effects), over the
    peak |force| of ``force_estimate``: relative, 1 sigma (the two supports as the ends of the doubt). 0 when
    nothing was dropped.

    The bootstrap keeps the chosen support, so it cannot see a term the selection dropped although its effect
    is there (the van der Waals term, and with it DMT's adhesion, at 10 pm of detector noise): measured on the
    poor instrument, seeds 2, 253, 255, 256, force errors 9-14 % with the statistical share at 0.4-0.6 %. Where
    the data reject the term its forced coefficient is near 0 and so is this share.
    """
    whole = np.asarray(whole, dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    if np.array_equal(whole, mask):
        return 0.0
    used, peak = estimated_peak(force_estimate)
    if peak <= 0:
        return math.nan
    T = regression.combine(system.T_blocks)
    forces = [model_force_samples(prep, library, system, regression.subset_fit(T, m)[0])[used] for m in (mask, whole)]
    half = 0.5 * (forces[1] - forces[0])
    return float(np.sqrt(np.mean(half**2)) / peak) if np.isfinite(half).all() else math.nan


def total_share(*shares: float) -> float:
    """The shares (relative 1 sigma; NaN: not computed, left out) added in quadrature; NaN when none is known."""
    known = [s for s in shares if math.isfinite(s)]
    return float(math.sqrt(sum(s * s for s in known))) if known else math.nan


#: The force band a longer record is projected to (the separation-limited warning's threshold: 1 % of the peak).
RECORD_TARGET = 0.01


def periods_for_total(periods: int, statistical: float, separation: float, selection: float, calibration: float,
                      target: float = RECORD_TARGET) -> int | None:
    """Drive periods after which the total band would fall to ``target`` (relative 1 sigma), from the shares of
    a record of ``periods`` periods (NaN: not computed, left out). None when the calibration share alone is at
    or above the target (no record length helps).

    The statistical and separation shares fall as 1 / sqrt(periods) (the bootstrap's spread and the
    separation's profile width both come from the periods' count); so does the selection share, to first
    order: a term dropped at this noise is either selected or rejected in a longer record (the poor
    instrument's dropped van der Waals term, seed 2: force error 13.7 % at 50 periods, 0.76 % at 400). The
    calibration share does not change. Checked against records of the projected length on the poor instrument
    (docs/accuracy.md, "Poor instrument").
    """
    calibration = calibration if math.isfinite(calibration) else 0.0
    if calibration >= target:
        return None
    scaling = sum(s * s for s in (statistical, separation, selection) if math.isfinite(s))
    if scaling <= 0:
        return periods
    return max(periods, int(math.ceil(periods * scaling / (target**2 - calibration**2))))
