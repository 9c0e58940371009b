"""The selection scopes (afmid.fit.selection_strategies) on small synthetic problems.

The mechanism of issue 17 in miniature: a misfit that is the same in every block (systematic) and that a
distractor column can absorb. Its gain grows with the number of blocks, the whole-record BIC's penalty only
like log(n): the record takes the distractor once the record is long, the vote of 10-block groups does not.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

import afmid.fit.regression as regression
from afmid.fit.selection import SelectionSettings
from afmid.fit.selection_strategies import (SELECTION_STRATEGIES, PeriodVote, RecordSelection, period_groups,
                                           strategies_by_declared_name, strategy_for)
from afmid.sections.selection_scopes import SELECTION_SCOPES

ROWS = 20  # whitened rows per block
NAMES = ["true_a", "true_b", "absorber", "noise_term", "drive"]


def _system(n_blocks: int, seed: int, misfit: float = 0.12):
    """Blocks of ROWS unit-variance rows: y = 3 a + 1 b + misfit * m + drive + noise, where m (the same in
    every block) is what the distractor "absorber" = m + its own noise can take up."""
    rng = np.random.default_rng(seed)
    m = rng.standard_normal(ROWS)
    m /= np.linalg.norm(m) / math.sqrt(ROWS)
    A = np.empty((n_blocks, ROWS, 5))
    A[..., 0] = rng.standard_normal((n_blocks, ROWS))
    A[..., 1] = rng.standard_normal((n_blocks, ROWS))
    A[..., 2] = m + 0.5 * rng.standard_normal((n_blocks, ROWS))
    A[..., 3] = rng.standard_normal((n_blocks, ROWS))
    A[..., 4] = np.cos(np.arange(ROWS) / 3.0) + 0.1 * rng.standard_normal((n_blocks, ROWS))
    y = 3 * A[..., 0] + 1 * A[..., 1] + misfit * m + A[..., 4] + rng.standard_normal((n_blocks, ROWS))
    protected = np.array([False, False, False, False, True])
    system = SimpleNamespace(T_blocks=regression.factor_blocks(A, y), protected=protected,
                             n_rows=n_blocks * ROWS, names=NAMES)
    return system


def _settings(strategy, method: str = "exhaustive") -> SelectionSettings:
    penalty = np.array([0.0, 0.0, 2 * math.log(10), 2 * math.log(10), 0.0])  # two distractors, odds 10
    return SelectionSettings(method, "bic", regression.default_thresholds(), 5, penalty, [], strategy, 1)


def _chosen(selection) -> list[str]:
    return [n for n, m, p in zip(NAMES, selection.best.mask, _system(12, 0).protected) if m and not p]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_record_takes_the_absorber_on_a_long_record_the_vote_does_not(seed):
    long = _system(2000, seed)
    assert _chosen(_settings(RecordSelection()).select(long)) == ["true_a", "true_b", "absorber"]
    vote = _settings(PeriodVote(periods=10)).select(long)
    assert _chosen(vote) == ["true_a", "true_b"]
    assert vote.votes[2] < 0.5 and vote.votes[0] == vote.votes[1] == 1.0
    assert any(np.array_equal(c.mask, vote.best.mask) for c in vote.candidates)
    assert math.isfinite(vote.best.bic) and math.isfinite(vote.best.cv_rss)


@pytest.mark.parametrize("method", ["exhaustive", "stlsq"])
def test_a_record_shorter_than_two_groups_is_decided_by_the_record(method):
    short = _system(15, 4)  # one group of 10
    vote = _settings(PeriodVote(periods=10), method).select(short)
    record = _settings(RecordSelection(), method).select(short)
    assert vote.votes is None
    assert np.array_equal(vote.best.mask, record.best.mask)


def test_vote_support_exhaustive_and_path_agree_on_clear_votes():
    """The same clear majority gives the same support whether every subset or a path is searched."""
    system = _system(300, 5)
    T = regression.combine(system.T_blocks)
    penalty = _settings(None).penalty
    votes = np.array([1.0, 0.9, 0.1, 0.0, 1.0])
    masks = [regression.vote_support(T, system.protected, votes, method, "bic", regression.default_thresholds(),
                                     system.n_rows, penalty, [], extra=[votes > 0.5])
             for method in ("exhaustive", "stlsq")]
    assert np.array_equal(masks[0], masks[1])
    assert masks[0].tolist() == [True, True, False, False, True]


def test_undecided_votes_go_to_the_record_criterion():
    """Columns within the undecided band take the whole record's BIC choice."""
    system = _system(300, 6)
    T = regression.combine(system.T_blocks)
    penalty = _settings(None).penalty
    record = regression.pick_support(T, system.protected, "exhaustive", "bic", regression.default_thresholds(),
                                     system.n_rows, penalty, [])
    votes = np.array([1.0, 1.0, 0.45, 0.55, 1.0])
    mask = regression.vote_support(T, system.protected, votes, "exhaustive", "bic", regression.default_thresholds(),
                                   system.n_rows, penalty, [], undecided=0.1)
    assert np.array_equal(mask, record)


def test_the_vote_bootstrap_resamples_groups_and_keeps_the_coefficient_draws():
    system = _system(200, 7)
    settings = _settings(PeriodVote(periods=10))
    chosen = settings.select(system).best.mask
    bagging = settings.bag(system, chosen, 20, np.random.default_rng(0))
    expected = regression.resampled_coefficients(system.T_blocks, chosen, 20, np.random.default_rng(0))
    np.testing.assert_array_equal(bagging.coef_samples, expected)  # same draws, same code path
    assert bagging.inclusion.shape == (5,) and bagging.inclusion[4] == 1.0
    assert sum(bagging.supports.values()) == 20


def test_period_groups_cover_every_block_once():
    for n, g in [(49, 10), (499, 10), (5, 10), (20, 10), (1, 1)]:
        groups = period_groups(n, g)
        assert np.array_equal(np.concatenate(groups), np.arange(n))
        assert len(groups) == max(1, n // g)


def test_every_declared_scope_has_a_strategy_and_every_strategy_a_declaration():
    """The config checks ``fit.selection_scope`` against the declarations (afmid.sections.selection_scopes); the
    fit runs the objects registered against them: the two sets are one."""
    from afmid.errors import DefinitionError

    assert sorted(SELECTION_STRATEGIES) == sorted(SELECTION_SCOPES.names())
    for name in SELECTION_SCOPES.names():
        assert strategy_for(name).name == name
    with pytest.raises(KeyError, match="did you mean 'record'"):
        strategy_for("records")
    with pytest.raises(DefinitionError, match="declared"):
        strategies_by_declared_name(PeriodVote())  # "record" declared, no object for it
    with pytest.raises(DefinitionError, match="declared"):
        strategies_by_declared_name(PeriodVote(), RecordSelection(), PeriodVote(name="majority"))


def test_the_scope_is_a_registered_config_choice():
    from afmid.config import build_config
    from afmid.errors import ConfigError

    assert set(SELECTION_SCOPES.names()) == {"vote", "record"}
    raw = {"cantilever": {"spring_constant": 40.0, "resonance_frequency": 3e5, "quality_factor": 250.0,
                          "tip_radius": 1e-8},
           "model": {"effects": ["dmt"]}, "fit": {"selection_scope": "votes"}}
    with pytest.raises(ConfigError, match="did you mean 'vote'"):
        build_config(raw)
    raw["fit"] = {"selection_scope": "record", "vote_periods": 25}
    config = build_config(raw)
    assert config.fit.selection_scope == "record"
    scope = strategy_for("vote").configured(config.fit)
    assert isinstance(scope, PeriodVote) and scope.periods == 25
