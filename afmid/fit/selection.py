"""How a fit chooses its sparse support: the selection settings of one fit, as one object.

The fit selects three times on systems of the same library (first pass, after
the regressors' own noise enters the row weights, after the nonlinear
parameters are refined) and bags once; all of them use the same method,
criterion, thresholds, folds, per-column penalties and rules, held here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

import afmid.fit.regression as regression
from afmid.physics.library import Library
from afmid.fit.selection_strategies import RecordSelection, strategy_for

#: Libraries up to this many terms are searched exhaustively (2^14 small least-squares problems).
EXHAUSTIVE_MAX_TERMS = 14


def term_penalties(library: Library, n_nuisance: int, odds: float) -> np.ndarray:
    """BIC penalty per column: 2 ln(odds) for terms that belong to no catalog effect (distractors)."""
    extra = 2.0 * math.log(odds)
    return np.array([0.0 if t.effect else extra for t in library.terms] + [0.0] * n_nuisance)


@dataclass(frozen=True)
class SelectionSettings:
    """Everything :func:`afmid.fit.regression.select` and :func:`afmid.fit.regression.bag` need besides the system.

    ``method`` is resolved ("auto" -> "exhaustive" up to :data:`EXHAUSTIVE_MAX_TERMS`
    terms, else "stlsq"); ``penalty`` and ``rules`` cover the library's columns
    followed by the nuisance columns.
    """

    method: str  # "stlsq", "lasso" or "exhaustive"
    criterion: str  # "bic", "aicc" or "cv"
    thresholds: np.ndarray  # STLSQ thresholds (relative)
    folds: int  # cross-validation folds (contiguous groups of periods)
    penalty: np.ndarray  # per column, added to the information criteria of a support that uses it
    rules: list  # [(condition masks, then mask), ...] (Library.selection_rules)
    #: where the support is decided (afmid.fit.selection_strategies: the whole record, or a vote of period groups)
    strategy: object = field(default_factory=RecordSelection)
    periods_per_block: int = 1  # drive periods per regression block (fit.periods_per_block)

    @classmethod
    def for_library(cls, fit, library: Library, n_nuisance: int) -> SelectionSettings:
        """The settings of the fit section ``fit`` (afmid.config.FitConfig) for ``library`` plus ``n_nuisance`` columns."""
        method = fit.method
        if method == "auto":
            method = "exhaustive" if len(library) <= EXHAUSTIVE_MAX_TERMS else "stlsq"
        thresholds = np.asarray(fit.thresholds) if fit.thresholds else regression.default_thresholds()
        return cls(method, fit.selection, thresholds, fit.folds,
                   term_penalties(library, n_nuisance, fit.distractor_odds), library.selection_rules(n_nuisance),
                   strategy_for(fit.selection_scope).configured(fit), fit.periods_per_block)

    def select(self, system) -> regression.Selection:
        """The sparsity path of ``system`` (an afmid.fit.pipeline.System) scored and the support chosen by the strategy."""
        return self.strategy.select(self, system)

    def weighting_support(self, system) -> np.ndarray:
        """A support to weight the rows by (:func:`afmid.fit.prepare.with_regressor_noise`), not the fit's: the
        whole record's criterion without the diagnostics (BIC for "cv").

        The weights take one number from it, the model's mean squared stiffness along the trajectory, which the
        distractors a long record's criterion may add hardly move (they fit the same data); the strategy's own
        selection (a vote of period groups) would cost as much as the final one (bench_selection).
        """
        return regression.pick_support(regression.combine(system.T_blocks), system.protected, self.method,
                                       regression.resample_key(self.criterion), self.thresholds, system.n_rows,
                                       self.penalty, self.rules)

    def bag(self, system, chosen: np.ndarray, n_boot: int, rng: np.random.Generator) -> regression.Bagging:
        """Bootstrap over periods of ``system``: inclusion probabilities and the spread of the ``chosen`` support.

        Each re-selection uses BIC when the criterion is "cv" (a cross-validation per resample would cost folds x
        resamples selections; :func:`afmid.fit.regression.resample_key`), AICc when it is "aicc"; what is resampled
        is the strategy's (:mod:`afmid.fit.selection_strategies`).
        """
        return self.strategy.bag(self, system, chosen, n_boot, rng)
