"""Each candidate taken as the truth (afmid.diagnosis.rival_truth) and the decision it adds to
afmid.diagnosis.decide, checked on linear models where the answer is known.

Two candidates share a base column and add one column each (f and g, equal parameter counts); the truth is one
of them, white noise of unit variance on 49 blocks of 20 rows. The squared distance of one's mean from the
other's space is D ~ 9 (chi-square units), the regime of the undecided hidden-effect cases of issue 13
(viscoelastic vs contact damping at 50 periods: D 8.2, T 8.8). Theory (Cox): the observed difference T of the
rival's chi-square minus the best's is N(+D, 4D) when the best is the truth, N(-D, 4D) when the rival is;
the rule names the first-ranked candidate when T lies 2 spreads above -D_r and within 2 spreads of +D_b:
the truth is named with probability P(z > -1) = 84 %, the wrong candidate with P(z < -2) = 2.3 %; Vuong's rule
alone (T / sd >= 2) names the truth with P(z > 0.5) = 31 %. Tolerances (fixed before the run, 400 traces,
binomial sd ~2 % and ~0.8 %): truth named >= 75 %, wrong named <= 5 %.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import afmid.diagnosis.decide as decide
from afmid.diagnosis.diagnose import Trial
from afmid.diagnosis.rival_truth import ModelSpace, predictions, spread

BLOCKS, ROWS = 49, 20


def _columns(distance_sq: float):
    """Base column, the best's column f and the rival's column g, scaled so that the true mean (coefficient 1 on
    f) lies ``distance_sq`` from span(base, g)."""
    s = np.linspace(0.0, 1.0, BLOCKS * ROWS)
    base = np.ones_like(s)
    f = np.sqrt(s)  # a Kelvin-Voigt-like and a linear column: close but not the same
    g = s
    Q, _ = np.linalg.qr(np.column_stack([base, g]))
    away = f - Q @ (Q.T @ f)
    scale = math.sqrt(distance_sq / float(away @ away))
    return base, scale * f, scale * g


def _fit(columns, y):
    X = np.column_stack(columns)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    resid = y - X @ coef
    return X, X @ coef, (resid**2).reshape(BLOCKS, ROWS).sum(axis=1)


def _trial(effect, X, fitted, block_chi2):
    space = ModelSpace(X, fitted)
    return Trial(effect, 0.1, 0.1, 0.0, 0.0, 1.0, 1.1, True, {}, {}, [], 0.0, explains=True,
                 block_chi2=block_chi2, n_parameters=2, space=lambda: space)


def _named(y, base, f, g):
    """The effect the rule names ("f", "g") or None (the data cannot decide)."""
    Xf, mf, cf = _fit([base, f], y)
    Xg, mg, cg = _fit([base, g], y)
    tf, tg = _trial("f", Xf, mf, cf), _trial("g", Xg, mg, cg)
    best, rival = (tf, tg) if cf.sum() <= cg.sum() else (tg, tf)
    return None if decide.rivals(best, [best, rival]) else best.effect


def test_distances_are_the_squared_gaps_between_the_models():
    base, f, g = _columns(9.0)
    Xf, Xg = np.column_stack([base, f]), np.column_stack([base, g])
    p = predictions(ModelSpace(Xf, f.copy()), ModelSpace(Xg, g.copy()))
    assert p.best_as_truth == pytest.approx(9.0, rel=1e-9)  # f from span(base, g): as constructed
    Q, _ = np.linalg.qr(Xf)
    assert p.rival_as_truth == pytest.approx(float(np.sum((g - Q @ (Q.T @ g)) ** 2)), rel=1e-9)


def test_spread_counts_the_correlation_of_neighbouring_blocks():
    rng = np.random.default_rng(3)
    white = rng.normal(size=4000)
    assert spread(white) == pytest.approx(math.sqrt(4000 * np.var(white, ddof=1)), rel=0.05)
    overlapped = white[1:] + white[:-1]  # neighbours share half: var of the sum ~4 n, not 2 n
    assert spread(overlapped) ** 2 / overlapped.size == pytest.approx(4.0, rel=0.1)


def test_the_truth_is_named_at_the_rate_cox_predicts_and_the_wrong_candidate_rarely():
    rng = np.random.default_rng(2026)
    base, f, g = _columns(9.0)
    outcomes = {"f": 0, "g": 0, None: 0}
    vuong_named = 0
    for _ in range(400):
        y = 0.3 * base + f + rng.normal(size=f.size)  # the truth: f
        outcomes[_named(y, base, f, g)] += 1
        Xf, mf, cf = _fit([base, f], y)
        Xg, mg, cg = _fit([base, g], y)
        c = decide.compare(_trial("f", Xf, mf, cf), _trial("g", Xg, mg, cg))
        vuong_named += c.by_fit
    assert outcomes["f"] >= 0.75 * 400, outcomes
    assert outcomes["g"] <= 0.05 * 400, outcomes
    assert outcomes["f"] > 2 * vuong_named, (outcomes, vuong_named)  # the gain over Vuong's rule alone


def test_both_refuted_leaves_the_decision_to_vuong():
    """Neither candidate is the truth (the mean is far from both spaces' prediction): the rule names none by
    refutation."""
    rng = np.random.default_rng(8)
    base, f, g = _columns(9.0)
    h = 6.0 * np.cos(12 * np.linspace(0, 1, f.size))  # a third law neither candidate has
    y = 0.3 * base + 0.5 * f + 0.5 * g + h + rng.normal(size=f.size)
    Xf, mf, cf = _fit([base, f], y)
    Xg, mg, cg = _fit([base, g], y)
    tf, tg = _trial("f", Xf, mf, cf), _trial("g", Xg, mg, cg)
    best, rival = (tf, tg) if cf.sum() <= cg.sum() else (tg, tf)
    c = decide.compare(best, rival)
    assert not (c.by_rival_refuted and not c.by_fit), (c, c.rival_refuted_sigmas, c.best_met_sigmas)
