"""When the data cannot decide between candidate effects (poor signals).

On a poor trace (10 pm of detector noise, 50 samples per period) several catalog effects can each explain a
residual to its noise floor: a hidden viscoelastic sample was read as "missing effect: capillary" because the
capillary refit beat the viscoelastic one by 14 BIC units. Such a difference between two non-nested models
carries its own sampling error, which BIC does not state. Vuong's test (Econometrica 57, 307 (1989)) measures
it: with the per-period (per-block) chi-square of both refits, the difference of their fits is compared with
the standard deviation of the summed per-block differences, sqrt(B * var(d_b)).

A BIC difference has two parts, and only one of them is random: the difference of the fits (the summed
chi-square difference, whose spread Vuong's statistic measures) and the penalty for the parameters each
candidate needs (ln n per parameter, fixed). The best candidate is told apart from a rival when

- it fits better by at least :data:`VUONG_SIGMAS` of the per-block evidence, or
- the rival needs more parameters and does not fit better by that much (parsimony: a candidate with a free
  decay length that fits no better than one without is not the simpler explanation), or
- the rival, taken as the truth, is refuted while the best, taken as the truth, is not (Cox's test,
  :mod:`afmid.diagnosis.rival_truth`): were the rival the truth its refit would fit better than the best's by
  the squared distance D_r of its fitted force from the best's model; it fits worse, and the observed
  difference lies :data:`VUONG_SIGMAS` of the per-period spread above -D_r, while it meets the best's own
  prediction D_b within that spread.

Otherwise (the rival is as simple or simpler, and the fits are within :data:`VUONG_SIGMAS`) the diagnosis says
that the data cannot decide between them and names none. Measured on the poor-signal table with the separation not
given: a hidden viscoelastic sample against exponential damping (chi-square 1.4 in favour of exponential
damping over 49 periods, 0.4 sigma, with one parameter more) and hydration against capillary (7.6 in favour of
hydration, 0.7 sigma, one more) are decided by parsimony; the penalised statistic alone (BIC gap / sd: 1.9 and
1.4 sigma) had named neither.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

import afmid.fit.regression as regression
from afmid.diagnosis.rival_truth import Predictions, predictions, spread

#: A rival whose fit is within this many standard deviations of the summed per-block chi-square difference of
#: the best candidate is not told apart from it by the fit (two-sided 5 % for a normal statistic: 1.96).
VUONG_SIGMAS = 2.0


def block_chi2(result, reference_sigma: np.ndarray | None = None) -> np.ndarray:
    """Per-block weighted residual sum of squares of a fit (its whitened rows; length = blocks), plus the block's
    :func:`weighting_deviance` against ``reference_sigma`` (None: none), so that refits whose rows carry different
    predicted noise compare as Gaussian deviances (-2 ln L up to one constant for all of them)."""
    rss = regression.block_rss(result.system.T_blocks, result.coef)
    return rss if reference_sigma is None else rss + weighting_deviance(result, reference_sigma)


def weighting_deviance(result, reference_sigma: np.ndarray) -> float:
    """2 sum_r ln(sigma_r / reference_r) over one block's rows (1): what a fit's own row noise adds to its Gaussian
    deviance, -2 ln L = chi^2 + sum ln sigma^2, beyond that of rows weighted by ``reference_sigma``.

    Each refit weights its rows with the noise its own model inherits from the trajectory (errors in variables,
    :func:`afmid.fit.prepare.with_regressor_noise`: the model's stiffness times the trajectory's noise). Its chi^2
    alone then rewards a model for predicting more noise: a contact damping of 1.4e-4 kg/s (a thousand times the
    plausible) on a tip that touches by a few pm has a stiffness that widens the first harmonics' rows 12.7-fold,
    and won by chi^2 465 over the capillary meniscus that had been hidden (loop_air draw 2), whose refit at the
    true separation and rupture distance has the lower cross-validated error. With the deviance the meniscus is
    ahead by about 1000. Equal weights (the same noise model) add nothing."""
    sigma = np.asarray(result.prep.row_sigma, dtype=float)
    return float(2.0 * np.sum(np.log(sigma / np.asarray(reference_sigma, dtype=float))))


@dataclass(frozen=True)
class Comparison:
    """The best candidate against a rival, over the same blocks (periods)."""

    fit_difference: float  # summed chi-square of the rival minus the best's (> 0: the best fits better)
    fit_sd: float  # standard deviation of that sum from the scatter of the per-block differences
    extra_parameters: int  # parameters the rival needs beyond the best's (terms + nonlinear shape parameters)
    #: what each taken as the truth predicts for the fit difference (afmid.diagnosis.rival_truth; None: not known)
    predictions: Predictions | None = None
    spread: float = math.nan  # sd of the summed difference, neighbouring periods' correlation counted

    @property
    def rival_refuted_sigmas(self) -> float:
        """How far (in spreads) the observed difference lies above what the rival, taken as the truth, predicts
        (-D_r, less one chi-square unit of noise absorbed per extra parameter of the rival); NaN when not known."""
        if self.predictions is None or not self.spread > 0:
            return math.nan
        expected = -self.predictions.rival_as_truth - self.extra_parameters
        return (self.fit_difference - expected) / self.spread

    @property
    def best_met_sigmas(self) -> float:
        """How far (in spreads) the observed difference lies below what the best, taken as the truth, predicts
        (+D_b, less one chi-square unit of noise absorbed per extra parameter of the rival); NaN when not known."""
        if self.predictions is None or not self.spread > 0:
            return math.nan
        expected = self.predictions.best_as_truth - self.extra_parameters
        return (expected - self.fit_difference) / self.spread

    @property
    def by_rival_refuted(self) -> bool:
        """The rival taken as the truth is refuted by :data:`VUONG_SIGMAS`, the best taken as the truth is not."""
        return self.rival_refuted_sigmas >= VUONG_SIGMAS and self.best_met_sigmas < VUONG_SIGMAS

    @property
    def fit_sigmas(self) -> float:
        """Vuong's statistic of the fits alone (> 0: the best fits better)."""
        if self.fit_sd > 0:
            return self.fit_difference / self.fit_sd
        return math.copysign(math.inf, self.fit_difference) if self.fit_difference else 0.0

    @property
    def by_fit(self) -> bool:
        """The best fits better by at least :data:`VUONG_SIGMAS`."""
        return self.fit_sigmas >= VUONG_SIGMAS

    @property
    def by_parsimony(self) -> bool:
        """The rival needs more parameters and does not fit better by :data:`VUONG_SIGMAS`."""
        return self.extra_parameters > 0 and self.fit_sigmas > -VUONG_SIGMAS

    @property
    def told_apart(self) -> bool:
        return self.by_fit or self.by_parsimony or self.by_rival_refuted


def compare(best, rival) -> Comparison | None:
    """The per-block comparison of two trials (None when the per-block values are missing or differ)."""
    a, b = getattr(best, "block_chi2", None), getattr(rival, "block_chi2", None)
    if a is None or b is None or a.shape != b.shape or a.size < 3:
        return None
    diff = b - a
    spaces = getattr(best, "space", None), getattr(rival, "space", None)
    known = predictions(spaces[0](), spaces[1]()) if None not in spaces else None
    return Comparison(float(diff.sum()), math.sqrt(a.size * float(np.var(diff, ddof=1))),
                      int(rival.n_parameters) - int(best.n_parameters), known, spread(diff))


def contenders(best, trials: list) -> list[tuple]:
    """(trial, :class:`Comparison`) for every other candidate that explains the residual (no significant misfit
    left) with plausible values and has per-block values to compare with ``best``'s."""
    out = []
    for t in trials:
        if t is best or t.effect == best.effect or not t.explains or t.implausible:
            continue
        c = compare(best, t)
        if c is not None:
            out.append((t, c))
    return out


def rivals(best, trials: list) -> list:
    """The contenders that the per-block evidence does not tell apart from ``best`` (see the module's rule)."""
    return [t for t, c in contenders(best, trials) if not c.told_apart]


def comparisons(best, trials: list) -> list[dict]:
    """``best`` against every contender: effect, fit_difference (chi-square of the rival minus the best's),
    fit_sd, fit_sigmas, extra_parameters, by_fit, by_parsimony, told_apart (for the record and the tables of
    scripts/experiment_table.py)."""
    return [{"effect": t.effect, "fit_difference": c.fit_difference, "fit_sd": c.fit_sd, "fit_sigmas": c.fit_sigmas,
             "extra_parameters": c.extra_parameters, "by_fit": c.by_fit, "by_parsimony": c.by_parsimony,
             "rival_as_truth": c.predictions.rival_as_truth if c.predictions else None,
             "best_as_truth": c.predictions.best_as_truth if c.predictions else None, "spread": c.spread,
             "rival_refuted_sigmas": c.rival_refuted_sigmas, "best_met_sigmas": c.best_met_sigmas,
             "by_rival_refuted": c.by_rival_refuted, "told_apart": c.told_apart}
            for t, c in contenders(best, trials)]


def _words(c: Comparison) -> str:
    """The rival's fit relative to the best's, in chi-square and in sigmas of the per-period evidence."""
    side = "higher" if c.fit_difference >= 0 else "lower"
    return f"its χ² {abs(c.fit_difference):.1f} {side}, {abs(c.fit_sigmas):.1f} σ of the per-period evidence"


def parsimony_note(best, trials: list) -> str:
    """A clause for the verdict naming the rivals that explain the residual as well as ``best`` and are set
    aside only because they need more parameters, or only because, taken as the truth, they are refuted
    ("" when there are none)."""
    notes, refuted = [], []
    for t, c in contenders(best, trials):
        if c.by_parsimony and not c.by_fit:
            more = f"{c.extra_parameters} more parameter" + ("s" if c.extra_parameters > 1 else "")
            notes.append(f"`{t.effect}` fits as well ({_words(c)}) with {more}")
        elif c.by_rival_refuted and not c.by_fit:
            refuted.append(f"`{t.effect}` ({_words(c)}) would, were it the truth, fit better by χ² "
                           f"{c.predictions.rival_as_truth:.1f}: refuted at {c.rival_refuted_sigmas:.1f} σ, while "
                           f"`{best.effect}` predicts the difference within {max(c.best_met_sigmas, 0.0):.1f} σ")
    text = ("; " + "; ".join(notes) + f": the simpler `{best.effect}` is named") if notes else ""
    return text + ("; " + "; ".join(refuted) if refuted else "")


def verdict(best, others: list) -> str:
    gaps = "; ".join(f"`{t.effect}`: {_words(compare(best, t))}, {compare(best, t).extra_parameters:+d} parameters"
                     for t in others)
    names = ", ".join(f"`{t.effect}`" for t in [best] + others)
    return (f"missing effect, but the data cannot decide which: {names} (ranked by BIC) each explain the residual "
            f"(error {best.error_after:.3g} vs noise floor {best.noise_floor_after:.3g}); none is told apart by a "
            f"better fit ({VUONG_SIGMAS:g} standard deviations of the per-period evidence) or by needing fewer "
            f"parameters ({gaps}); record more periods, with less detector noise or at a higher sample rate, or fix "
            "the separation")
