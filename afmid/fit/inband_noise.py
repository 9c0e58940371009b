"""The noise inside the drive harmonics' band, measured from the record when the prediction understates it.

The weak-form rows' noise (``Prepared.row_sigma``) and the per-period inverted force's (``block_sigma``) are
predicted from ``noise_rms``, the per-period Fourier fits' residual, which lies mostly above the highest
harmonic. That is the noise at the harmonics only for white detector noise. A real detector's noise is
coloured: on Bruker's HSDC record the rows' period-to-period scatter is 5-11x (in sd) the prediction at every
harmonic (11x at the 1st, 9x at the 10th, 6x at the 30th). With the prediction, the error's noise floor is that
much too low, and the signal gate (a harmonic's mean above its per-period noise) lets in harmonics whose mean
is 2.5 measured sigmas of the held-out average: on that record's second half harmonics 15, 17 and 25 (0.85-1.4
MHz, where the inverted force multiplies the deflection by n^2) took 60 % of the counted force and 99 % of the
floor, which stood 5x the first half's with the same noise rms.

What is measured: each row's second difference across periods, X[b+1] - 2 X[b] + X[b-1], whose variance is 6x
a white noise's and almost nothing for a motion that changes slowly (a settling amplitude, a scan's
modulation, a drift). It is used only when the excess is the noise's:

- in the quiet harmonics (those whose mean over the record stays below one predicted per-period sigma: no
  force there), the measured variance over the predicted, averaged over the harmonics, exceeds 1 by
  :data:`MIN_EXCESS` - 1 and by
  :data:`SIGNIFICANCE` standard errors of its estimate (white noise never does);
- and there it is independent from harmonic to harmonic (:func:`afmid.preprocess.motion.moves_incoherently`):
  a change of orbit (a transient's decaying free oscillation, chaos) moves the harmonics together.

Then each harmonic's noise variance is its measured one (cos and sin pooled), no less than predicted; a
harmonic that carries force is capped at the largest quiet harmonic's factor (its scatter beyond that may be
the motion changing, not noise). A noise-free record (``noise_rms`` at its numerical floor) is left as is.
"""

from __future__ import annotations

import math

import numpy as np

from afmid.preprocess.motion import moves_incoherently

#: The pooled quiet harmonics' measured variance must exceed the prediction by this factor (in variance: 1.4x in
#: sd); below it the floor moves by less than the chi-square scatter of a right model's error at ~30 degrees of
#: freedom, and the prediction stands.
MIN_EXCESS = 2.0
#: ... and by this many standard errors of the estimate (a white record's pooled ratio never reaches it).
SIGNIFICANCE = 5.0
#: Fewer periods than this: nothing is measured.
MIN_PERIODS = 12
#: Variance of the mean of N squared second differences of white noise, times N / (6 sigma^2)^2: 2 (1 + 2 sum
#: rho_k^2) with the second difference's lag correlations rho_1 = -4/6, rho_2 = 1/6.
SECOND_DIFFERENCE_SPREAD = 2.0 * (1.0 + 2.0 * (16.0 + 1.0) / 36.0)


def excess_variance(values: np.ndarray, predicted_variance: np.ndarray, harmonics: np.ndarray,
                    noise_free: bool = False) -> np.ndarray:
    """The factor (>= 1, one per row) by which each row's noise variance exceeds ``predicted_variance``.

    ``values`` (periods, rows): per-period coefficients of one quantity (the weak-form rows, N s, or the
    inverted force, N); ``predicted_variance`` (rows,) their predicted per-period noise variance in the same
    units squared; ``harmonics`` (rows,) each row's harmonic. All ones unless the quiet harmonics show a
    significant, incoherent excess (module docstring) or when ``noise_free``."""
    rows = values.shape[1]
    ones = np.ones(rows)
    periods = values.shape[0]
    if noise_free or periods < MIN_PERIODS or not np.all(predicted_variance > 0):
        return ones
    second = values[2:] - 2.0 * values[1:-1] + values[:-2]
    measured = np.mean(second**2, axis=0) / 6.0
    mean = np.abs(values.mean(axis=0))
    orders = np.unique(harmonics)
    quiet_orders = [n for n in orders if n > 0
                    and np.all(mean[harmonics == n] < np.sqrt(predicted_variance[harmonics == n]))]
    quiet = np.isin(harmonics, quiet_orders)
    if quiet.sum() < 2:
        return ones
    ratio = {n: float(measured[harmonics == n].sum() / predicted_variance[harmonics == n].sum()) for n in orders}
    # each quiet harmonic counts once: the rows' noise grows steeply with n (the weak form's derivatives), so a
    # variance-weighted pool would be the highest harmonics' alone, above a coloured noise's band
    pooled = float(np.mean([ratio[n] for n in quiet_orders]))
    spread = math.sqrt(SECOND_DIFFERENCE_SPREAD / (second.shape[0] * int(quiet.sum())))
    if pooled < max(MIN_EXCESS, 1.0 + SIGNIFICANCE * spread) or not moves_incoherently(values[:, quiet]):
        return ones
    factor = ones.copy()
    by_order = {n: max(r, 1.0) for n, r in ratio.items()}
    cap = max(by_order[n] for n in quiet_orders)
    for n, ratio in by_order.items():
        factor[harmonics == n] = ratio if n in quiet_orders else min(ratio, cap)
    return factor


def measured_noise_words(factor: np.ndarray, harmonics: np.ndarray) -> str | None:
    """The fit's line when :func:`excess_variance` raised any harmonic's noise (``factor`` its result), else None."""
    raised = factor > 1.0
    if not np.any(raised):
        return None
    sd = np.sqrt(factor[raised])
    orders = np.unique(harmonics[raised])
    return (f"coloured detector noise: at harmonics {orders.min()}-{orders.max()} the record's noise (measured "
            f"across its periods) is {sd.min():.2g}-{sd.max():.2g}x in sd what the per-period fits' residual "
            "shows; the error's noise floor and the harmonics it counts use the measured noise, the "
            "regression's weights the residual's (afmid.fit.inband_noise)")
