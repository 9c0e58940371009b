"""The fits' one sequence (afmid.fit.orchestration): each spread strategy against a direct computation on a small
least-squares problem, and the order in which :func:`orchestrate` runs the strategies and steps.

The problem: 12 blocks of 8 rows, 3 columns of unit scale, y = A c + noise (sigma 0.1). Direct computations use
numpy.linalg.lstsq on the stacked rows (weighted by each block's multiplicity), not the block factors the code
combines: both are least squares on well-conditioned columns (condition number < 10), so they agree to a few
hundred ulps of the coefficients (~1e-15); the tolerances 1e-10 leave room for the BLAS's summation order.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import afmid.fit.regression as regression
from afmid.errors import InputError
from afmid.fit.orchestration import (BootstrapBagging, CovarianceDraws, ErrorEstimate, NoSpread, Settled, Spread,
                                     Stages, StratifiedBagging, orchestrate)
from afmid.fit.selection import SelectionSettings
from afmid.fit.selection_strategies import RecordSelection

BLOCKS, ROWS, COLUMNS = 12, 8, 3
TRUE = np.array([1.0, -0.5, 0.25])
CLOSE = 1e-10


class Problem:
    """What the strategies read of a system: ``T_blocks``, ``protected``, ``names``, ``n_rows`` (and a joint
    system's ``block_start``)."""

    def __init__(self, seed: int = 1, groups: tuple[int, ...] = (BLOCKS,)):
        rng = np.random.default_rng(seed)
        self.A = rng.standard_normal((BLOCKS, ROWS, COLUMNS))
        self.y = self.A @ TRUE + 0.1 * rng.standard_normal((BLOCKS, ROWS))
        self.T_blocks = np.concatenate([regression.factor_blocks(self.A[b:b + 1], self.y[b:b + 1])
                                        for b in range(BLOCKS)])
        self.protected = np.zeros(COLUMNS, dtype=bool)
        self.names = ["a", "b", "c"]
        self.n_rows = BLOCKS * ROWS
        self.block_start = np.concatenate([[0], np.cumsum(groups)]).astype(int)

    def lstsq(self, multiplicity: np.ndarray, support: np.ndarray) -> np.ndarray:
        """The support's coefficients on the rows of each block repeated ``multiplicity`` times (zero elsewhere)."""
        w = np.sqrt(np.repeat(multiplicity, ROWS))
        A = self.A.reshape(-1, COLUMNS)[:, support] * w[:, None]
        out = np.zeros(COLUMNS)
        out[support] = np.linalg.lstsq(A, self.y.reshape(-1) * w, rcond=None)[0]
        return out


def settings() -> SelectionSettings:
    return SelectionSettings("exhaustive", "bic", regression.default_thresholds(), 3, np.zeros(COLUMNS), [],
                             RecordSelection())


def coefficients(problem: Problem, support: np.ndarray) -> np.ndarray:
    return regression.subset_fit(regression.combine(problem.T_blocks), support)[0]


def assert_spread_of(spread: Spread, samples: np.ndarray) -> None:
    """The spread's sigma and 95 % interval are those of ``samples`` (the direct computation's)."""
    scale = np.abs(TRUE)
    np.testing.assert_allclose(spread.bagging.coef_samples, samples, rtol=0, atol=CLOSE * scale.max())
    np.testing.assert_allclose(spread.coef_std, samples.std(axis=0, ddof=1), rtol=0, atol=CLOSE * scale.max())
    low, high = np.percentile(samples, [2.5, 97.5], axis=0)
    np.testing.assert_allclose(spread.ci_low, low, rtol=0, atol=CLOSE * scale.max())
    np.testing.assert_allclose(spread.ci_high, high, rtol=0, atol=CLOSE * scale.max())


def test_no_spread_is_the_value_itself():
    problem = Problem()
    support = np.array([True, False, True])
    coef = coefficients(problem, support)
    spread = NoSpread().spread(problem, coef, support)
    assert spread.bagging is None
    assert np.array_equal(spread.coef_std, np.zeros(COLUMNS))
    assert np.array_equal(spread.ci_low, coef) and np.array_equal(spread.ci_high, coef)
    assert np.array_equal(spread.inclusion, [1.0, 0.0, 1.0])


def test_bootstrap_bagging_refits_the_support_on_resampled_periods():
    """Each resample draws every block's multiplicity from a multinomial (the generator seeded with the seed);
    the chosen support refitted on it is one coefficient sample; the inclusion counts the re-selections."""
    problem, n, seed = Problem(), 40, 5
    support = np.ones(COLUMNS, dtype=bool)
    spread = BootstrapBagging(settings(), n, seed).spread(problem, coefficients(problem, support), support)
    rng = np.random.default_rng(seed)
    multiplicities = [rng.multinomial(BLOCKS, np.full(BLOCKS, 1.0 / BLOCKS)).astype(float) for _ in range(n)]
    assert_spread_of(spread, np.array([problem.lstsq(m, support) for m in multiplicities]))
    # all three columns carry signal far above the noise: every resample keeps them
    assert np.array_equal(spread.inclusion, np.ones(COLUMNS))
    assert spread.bagging.n_boot == n


def test_stratified_bagging_resamples_within_each_group():
    """The coefficient samples are drawn after the pooled re-selections from the same generator, each group of
    blocks (a joint fit's trace) keeping its number of blocks."""
    groups = (5, 7)
    problem, n, seed = Problem(seed=2, groups=groups), 30, 9
    support = np.array([True, True, False])
    spread = StratifiedBagging(settings(), n, seed).spread(problem, coefficients(problem, support), support)
    rng = np.random.default_rng(seed)
    for _ in range(n):  # the pooled resamples of the inclusion frequencies come first
        rng.multinomial(BLOCKS, np.full(BLOCKS, 1.0 / BLOCKS))
    samples = []
    for _ in range(n):
        multiplicity = np.concatenate([rng.multinomial(g, np.full(g, 1.0 / g)) for g in groups]).astype(float)
        assert [multiplicity[:5].sum(), multiplicity[5:].sum()] == list(groups)
        samples.append(problem.lstsq(multiplicity, support))
    assert_spread_of(spread, np.array(samples))
    assert np.array_equal(spread.bagging.coef_samples[:, 2], np.zeros(n))  # outside the support: exactly 0


def test_covariance_draws_follow_the_least_squares_covariance():
    """Over 20000 draws the sigma of each coefficient of the support is sqrt(s2 (A^T A)^-1) within sampling error
    (a sample standard deviation of n normal draws has relative sd 1/sqrt(2n) = 0.005: 5 of them allowed), the
    mean the fitted coefficients (within 5 sigma / sqrt(n)); the columns outside the support stay at their value."""
    problem, n = Problem(seed=3), 20000
    support = np.array([True, False, True])
    coef = coefficients(problem, support)
    strategy = CovarianceDraws(n, [0, 14])
    spread = strategy.spread(problem, coef, support)
    A = problem.A.reshape(-1, COLUMNS)[:, support]
    residual = problem.y.reshape(-1) - A @ coef[support]
    s2 = float(residual @ residual) / (problem.n_rows - int(support.sum()))
    sigma = np.sqrt(np.diag(s2 * np.linalg.inv(A.T @ A)))
    np.testing.assert_allclose(spread.coef_std[support], sigma, rtol=5 / math.sqrt(2 * n))
    np.testing.assert_allclose(spread.bagging.coef_samples.mean(axis=0)[support], coef[support],
                               rtol=0, atol=5 * sigma.max() / math.sqrt(n))
    assert np.array_equal(spread.bagging.coef_samples[:, 1], np.full(n, coef[1]))
    assert np.array_equal(spread.inclusion, support.astype(float))
    assert strategy.error_kind == "1 sigma (least-squares covariance)"
    again = CovarianceDraws(n, [0, 14]).spread(problem, coef, support)
    assert np.array_equal(again.bagging.coef_samples, spread.bagging.coef_samples)  # one seed, one set of draws


# --------------------------------------------------------------------------- the sequence
class EmptyLibrary:
    """A library without effects: nothing to read out, so the test sees only what the strategies add."""

    effects: list = []
    names = ["a", "b", "c"]
    terms: list = []

    def __len__(self):
        return COLUMNS


class Recorder:
    """Strategies and steps that note when they run, in one shared list."""

    def __init__(self, problem: Problem, fail: bool = False):
        self.problem, self.fail, self.calls = problem, fail, []

    # separation strategy
    def settle(self):
        self.calls.append("settle")
        prep = type("Prep", (), {"trace": type("Trace", (), {"path": "x.h5"})()})()
        return Settled(prep, self.problem, np.ones(COLUMNS, dtype=bool), {"d": 1e-9}, ["note: start"])

    def propagate(self, state):
        self.calls.append("propagate")
        state.quantities["E_star"] = {"value": 1.0, "error": 0.1}

    # error strategy
    def estimate(self, prep, system, coef, chosen):
        self.calls.append("error")
        if self.fail:
            raise InputError("no usable result", file="x.h5", key="data.path")
        return ErrorEstimate(0.2, np.array([0.2]), 0.1, np.ones(1, dtype=bool))


class Step:
    def __init__(self, name: str, calls: list):
        self.name, self.calls = name, calls

    def apply(self, state):
        self.calls.append(self.name)
        assert "error_kind" in state.quantities["E_star"]  # the spread's label is on before any step
        state.warn(self.name)


class Bar:
    def __init__(self):
        self.lines, self.closed = [], False

    def stage(self, text, step):
        self.lines.append((text, step))

    def close(self):
        self.closed = True


def test_orchestrate_runs_the_strategies_then_the_steps_in_order():
    problem, bar = Problem(), Bar()
    recorder = Recorder(problem)
    steps = [Step("first", recorder.calls), Step("second", recorder.calls)]
    done = orchestrate(None, EmptyLibrary(), recorder, CovarianceDraws(50, 1), recorder, steps, bar,
                       Stages(spread=(4, 5), error=(5, 5)))
    assert recorder.calls == ["settle", "error", "propagate", "first", "second"]
    assert done.state.steps == ["first", "second"]
    assert done.state.warnings == ["note: start", "warning: first", "warning: second"]
    assert done.state.quantities["E_star"]["error_kind"] == CovarianceDraws.error_kind
    assert (done.state.cv_error, done.state.noise_floor) == (0.2, 0.1)
    np.testing.assert_allclose(done.coef, problem.lstsq(np.ones(BLOCKS), np.ones(COLUMNS, bool)), rtol=CLOSE)
    assert bar.lines == [("error and forces", (5, 5))]  # the covariance draws have no stage line of their own
    bagged = orchestrate(None, EmptyLibrary(), Recorder(problem), BootstrapBagging(settings(), 5, 0),
                         Recorder(problem), [], bar, Stages(spread=(4, 5), error=(5, 5)))
    assert bar.lines[1:] == [("error bars (5 resamples)", (4, 5)), ("error and forces", (5, 5))]
    assert "error_kind" not in bagged.state.quantities["E_star"]  # the bootstrap's error is the read-out's own


def test_an_unusable_fit_closes_the_progress_line_before_its_error():
    problem, bar = Problem(), Bar()
    recorder = Recorder(problem, fail=True)
    with pytest.raises(InputError, match="no usable result"):
        orchestrate(None, EmptyLibrary(), recorder, NoSpread(), recorder, [Step("never", recorder.calls)], bar)
    assert bar.closed and recorder.calls == ["settle", "error"]
