"""Each candidate taken as the truth: what it predicts for its rival's fit (Cox's test of non-nested models).

:mod:`afmid.diagnosis.decide` compares the best candidate with a rival by the summed per-period chi-square
difference T (the rival's minus the best's) and its spread. Vuong's statistic T / sd asks whether the two are
*equally close* to the truth. But the diagnosis asks another question: which catalog effect is there? If the
rival were the truth, its refit would fit the trace better than the best's by about the squared distance D_r
of the rival's fitted force from everything the best's model can reach (its terms, its separation and its own
shape parameters, linearised), so T would lie near -D_r; if the best is the truth, T lies near +D_b. The two
predictions are 2 D apart while T scatters by sd ~ 2 sqrt(D): the pooled evidence tells the hypotheses apart at
~sqrt(D) sigmas, where Vuong's T / sd reaches only sqrt(D) / 2 (Cox, Proc. 4th Berkeley Symp. 1, 105 (1961);
J. R. Stat. Soc. B 24, 406 (1962); Pesaran, Weeks in A Companion to Theoretical Econometrics (2001), ch. 13).

A rival is excluded when the observed T lies at least :data:`afmid.diagnosis.decide.VUONG_SIGMAS` of the
measured spread above its prediction -D_r, *and* the best's own prediction +D_b is met (T not below it by that
much): when both predictions fail, neither candidate is the truth and the decision stays with Vuong's rule.

Distances are in whitened chi-square units on the weak-form rows (the regression's own metric); the fitted
force of a candidate is its library columns at its separation and shape times its coefficients.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Finite-difference steps of the linearised nonlinear parameters: the separation (m) and, relative, a shape
#: parameter (decay length, rupture distance). Small against every length the force varies on (>= 50 pm).
SEPARATION_STEP = 1e-12
SHAPE_STEP = 1e-3


@dataclass
class ModelSpace:
    """One candidate's refit as a linear space on the whitened rows: ``columns`` (rows, k) span what the model
    reaches near its fit (selected terms, nuisance columns, derivatives of its fitted force in its separation and
    shape parameters); ``fitted`` (rows,) is its fitted mean."""

    columns: np.ndarray
    fitted: np.ndarray

    def distance(self, target: np.ndarray) -> float:
        """Squared distance (chi-square units) of ``target`` (rows,) from the space."""
        scale = np.linalg.norm(self.columns, axis=0)
        scale[scale == 0] = 1.0
        offset = target - self.fitted  # the fitted mean lies in the space: project the (small) difference
        coef, *_ = np.linalg.lstsq(self.columns / scale, offset, rcond=None)
        return float(np.sum((offset - (self.columns / scale) @ coef) ** 2))


def model_space(prep, result, shape_names: list[str], separation_free: bool) -> ModelSpace:
    """The :class:`ModelSpace` of a fit ``result`` (afmid.fit.pipeline.FitResult) on the prepared trace ``prep``;
    ``shape_names`` are the candidate's estimated shape parameters, ``separation_free`` whether the separation was
    estimated (its derivative column is then part of the space)."""
    from afmid.fit.system import library_columns

    sigma = prep.row_sigma[None, :, None]
    p = result.system.theta.shape[2]
    full = np.concatenate([result.system.theta, prep.nuisance], axis=2) / sigma
    mask = np.asarray(result.selected, dtype=bool)
    coef = np.where(mask, result.coef, 0.0)
    fitted = (full @ coef).ravel()
    columns = [full[:, :, mask].reshape(-1, int(mask.sum()))]
    params = dict(result.system.params)
    steps = {"d": SEPARATION_STEP} if separation_free else {}
    steps.update({name: SHAPE_STEP * abs(params[name]) for name in shape_names
                  if name in params and params[name]})
    for name, step in steps.items():
        up = library_columns(prep, result.library, {**params, name: params[name] + step})
        down = library_columns(prep, result.library, {**params, name: params[name] - step})
        columns.append((((up - down) / (2 * step)) / sigma[:, :, :p] @ coef[:p]).reshape(-1, 1))
    return ModelSpace(np.concatenate(columns, axis=1), fitted)


@dataclass(frozen=True)
class Predictions:
    """What each of two candidates, taken as the truth, predicts for the other's fit (chi-square units)."""

    best_as_truth: float  # D_b: the best's fitted force's squared distance from the rival's space
    rival_as_truth: float  # D_r: the rival's fitted force's squared distance from the best's space


def predictions(best: ModelSpace, rival: ModelSpace) -> Predictions:
    return Predictions(rival.distance(best.fitted), best.distance(rival.fitted))


def spread(block_differences: np.ndarray) -> float:
    """Standard deviation of the sum of per-block differences, counting the correlation of neighbouring blocks
    (the weak form's windows span two periods and hop one: neighbours share half their samples, blocks further
    apart none): the long-run variance truncated after lag 1, gamma_0 + 2 gamma_1, never below the
    independent-block value gamma_0."""
    d = np.asarray(block_differences, float) - np.mean(block_differences)
    n = d.size
    gamma0 = float(np.sum(d * d)) / (n - 1)
    gamma1 = float(np.sum(d[1:] * d[:-1])) / (n - 1)
    return math.sqrt(n * max(gamma0 + 2 * gamma1, gamma0))
