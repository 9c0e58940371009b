"""Where a fit's sparse support is decided: on the whole record at once, or by a majority vote of period groups.

Both strategies are objects with the protocol ``select(settings, system) -> Selection`` and
``bag(settings, system, chosen, n_boot, rng) -> Bagging`` (``settings`` is the fit's
:class:`afmid.fit.selection.SelectionSettings`: method, criterion, penalties, rules). Their names, titles and
references are declared in :data:`afmid.sections.selection_scopes.SELECTION_SCOPES` (below the config, which
checks ``fit.selection_scope`` against them); here each declared name gets its object (:data:`SELECTION_STRATEGIES`,
:func:`strategy_for`).

Why a vote (docs/accuracy.md, "Selection as the record grows"): the weak-form rows of a tapping trace carry a
systematic misfit that does not average out over periods (the thermal motion seen through the stiff
short-range terms, through the per-period trajectory reconstruction). A term of the library that absorbs part
of it lowers the residual in proportion to the record's length, while BIC's penalty grows only like log(n):
on the whole record, every such distractor is eventually selected (Lennard-Jones, table I: right support in
6/10 draws at 50 periods, 0/10 at 500). Within a group of a fixed number of periods the misfit's gain stays
below the penalty (and the distractor prior), and a real term of the force law stays above it; so the
majority of the groups' own selections converges on the distractors as the groups multiply. The physical
(catalog) terms, which carry no such prior and may be too weak to be seen in one group, are then chosen
on the whole record, and the coefficients are fitted on it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import afmid.fit.regression as regression
from afmid.errors import DefinitionError
from afmid.sections.selection_scopes import SELECTION_SCOPES


@dataclass(frozen=True)
class RecordSelection:
    """The support chosen by the criterion on all periods at once (afmid's original selection)."""

    name: str = "record"

    def configured(self, fit) -> RecordSelection:
        return self

    def select(self, settings, system) -> regression.Selection:
        return regression.select(system.T_blocks, system.protected, settings.method, settings.criterion,
                                 settings.thresholds, n_rows=system.n_rows, folds=settings.folds,
                                 penalty=settings.penalty, rules=settings.rules)

    def bag(self, settings, system, chosen: np.ndarray, n_boot: int, rng: np.random.Generator) -> regression.Bagging:
        """Bootstrap over periods; each resample re-selects on the whole resampled record."""
        return regression.bag(system.T_blocks, system.protected, chosen, system.names, settings.method,
                              settings.criterion, settings.thresholds, n_boot, rng, system.n_rows, settings.penalty,
                              settings.rules)


def period_groups(n_blocks: int, group_blocks: int) -> list[np.ndarray]:
    """Contiguous groups of about ``group_blocks`` blocks each (at least one group; the remainder spread)."""
    n_groups = max(1, n_blocks // max(group_blocks, 1))
    return [g for g in np.array_split(np.arange(n_blocks), n_groups) if g.size]


def group_factors(T_blocks: np.ndarray, groups: list[np.ndarray]) -> list[np.ndarray]:
    """:func:`afmid.fit.regression.combine` of each group's block factors, in group order: one LAPACK call per
    group size (:func:`afmid.fit.regression.combine_each`, the same bits) instead of one per group."""
    out: list = [None] * len(groups)
    by_size: dict[int, list[int]] = {}
    for i, g in enumerate(groups):
        by_size.setdefault(g.size, []).append(i)
    for members in by_size.values():
        for i, R in zip(members, regression.combine_each(T_blocks[np.stack([groups[i] for i in members])])):
            out[i] = R
    return out


#: Where PeriodVote keeps a system's last group selections (an attribute of the system: gone with it).
_PICKS_MEMO = "_period_vote_picks"


@dataclass(frozen=True)
class PeriodVote:
    """The support held by the majority of the selections made on groups of ``periods`` periods each.

    Each group selects with the fit's criterion on its own rows (BIC with ``n`` the group's rows); a
    distractor (a term of no catalog effect) is kept when clearly more than half of the groups chose it and
    dropped when clearly fewer did ("clearly": by more than one binomial standard error 0.5 / sqrt(groups));
    the other distractors and every physical (catalog) term are then chosen by the criterion on the whole
    record, among the supports the rules allow. Records shorter than two
    groups are decided by the whole record's criterion alone. The candidates, criteria and CV errors kept for
    the diagnostics are those of the whole record (the voted support among them).
    """

    periods: int = 6  # fit.vote_periods' default (docs/accuracy.md: 6 rather than 10, measured)
    name: str = "vote"

    def configured(self, fit) -> PeriodVote:
        return PeriodVote(periods=fit.vote_periods)

    def _groups(self, settings, system) -> list[np.ndarray]:
        windows = max(1, round(self.periods / max(settings.periods_per_block, 1)))
        return period_groups(system.T_blocks.shape[0], windows)

    def _picks(self, settings, system, groups) -> np.ndarray:
        # select() and bag() of one system ask for the same picks (thousands of groups on a long record): the
        # last ones are kept on the system itself, with the settings and group sizes they were made for.
        # Every system (afmid.fit.system.System, afmid.fit.joint.JointSystem) has a __dict__.
        sizes = tuple(g.size for g in groups)
        memo = vars(system)
        kept = memo.get(_PICKS_MEMO)
        if kept is not None and kept[0] is settings and kept[1] == sizes:
            return kept[2].copy()
        key = regression.resample_key(settings.criterion)
        n_blocks = system.T_blocks.shape[0]
        picks = regression.pick_supports(group_factors(system.T_blocks, groups),
                                         [max(int(system.n_rows * g.size / n_blocks), 1) for g in groups],
                                         system.protected, settings.method, key, settings.thresholds,
                                         settings.penalty, settings.rules)
        memo[_PICKS_MEMO] = (settings, sizes, picks.copy())
        return picks

    def _vote(self, settings, system, T: np.ndarray, picks: np.ndarray) -> np.ndarray:
        # A majority overrules the whole record's criterion only when it is clear: more than one binomial
        # standard error of a fair vote (0.5 / sqrt(groups)) away from one half. With 4-5 groups (50 periods)
        # only near-unanimous votes count; as the groups multiply, any majority does.
        # Only the distractors (terms of no catalog effect, settings.penalty > 0) are put to the vote: the
        # physical terms are chosen by the record's criterion given the voted distractors, so a weak real term
        # (a van der Waals tail at the poor instrument) keeps the power of the whole record.
        votes = np.where(np.asarray(settings.penalty) > 0, picks.mean(axis=0), 0.5)
        return regression.vote_support(T, system.protected, votes, settings.method,
                                       regression.resample_key(settings.criterion), settings.thresholds,
                                       system.n_rows, settings.penalty, settings.rules, extra=list(picks),
                                       undecided=0.5 / np.sqrt(len(picks)))

    def select(self, settings, system) -> regression.Selection:
        record = RecordSelection().select(settings, system)
        groups = self._groups(settings, system)
        if len(groups) < 2:
            return record
        picks = self._picks(settings, system, groups)
        mask = self._vote(settings, system, regression.combine(system.T_blocks), picks)
        cands = list(record.candidates)
        index = next((i for i, c in enumerate(cands) if np.array_equal(c.mask, mask)), None)
        if index is None:
            cands.append(regression.scored_candidate(system.T_blocks, system.protected, mask, system.n_rows,
                                                     settings.penalty, settings.folds))
            index = len(cands) - 1
        return regression.Selection(cands, index, record.criterion, votes=picks.mean(axis=0))

    def bag(self, settings, system, chosen: np.ndarray, n_boot: int, rng: np.random.Generator) -> regression.Bagging:
        """Coefficients: the ``chosen`` support refitted on resamples of the periods; inclusion: the vote
        repeated on resamples of the groups' own selections (the groups are the units of the vote), the
        record's criterion on a resample of the periods."""
        coef_samples = regression.resampled_coefficients(system.T_blocks, chosen, n_boot, rng)
        groups = self._groups(settings, system)
        if len(groups) < 2:
            record = RecordSelection().bag(settings, system, chosen, n_boot, rng)
            return regression.Bagging(record.inclusion, coef_samples, n_boot, record.supports)
        picks = self._picks(settings, system, groups)
        counts = np.zeros(picks.shape[1])
        supports: dict[tuple, int] = {}
        n_blocks = system.T_blocks.shape[0]
        for _ in range(n_boot):
            drawn = rng.integers(0, len(groups), len(groups))
            # The record the physical terms are chosen on is resampled too (blocks drawn with replacement, as
            # the record's own bootstrap): their inclusion is then a real frequency, not the whole record's one
            # verdict repeated (on poor signals a Hertz term the data barely support shows it).
            multiplicity = rng.multinomial(n_blocks, np.full(n_blocks, 1.0 / n_blocks)).astype(float)
            T = regression.combine(system.T_blocks, multiplicity)
            mask = self._vote(settings, system, T, picks[drawn])
            counts += mask
            support = tuple(n for n, m, prot in zip(system.names, mask, system.protected) if m and not prot)
            supports[support] = supports.get(support, 0) + 1
        return regression.Bagging(counts / n_boot, coef_samples, n_boot, supports)


def strategies_by_declared_name(*strategies) -> dict:
    """The strategy objects keyed by their declared scope names; a declared name without an object, or an object
    whose name is not declared, fails at import (a definition error, caught by the tests)."""
    by_name = {strategy.name: strategy for strategy in strategies}
    declared = set(SELECTION_SCOPES.names())
    if set(by_name) != declared:
        raise DefinitionError(f"selection scopes declared {sorted(declared)} but strategies given for "
                              f"{sorted(by_name)} (afmid.sections.selection_scopes)")
    return by_name


#: Declared scope name -> the strategy object that runs it.
SELECTION_STRATEGIES: dict = strategies_by_declared_name(PeriodVote(), RecordSelection())


def strategy_for(name: str):
    """The strategy object of the declared scope ``name``; an unknown name raises KeyError with the registry's
    did-you-mean message."""
    SELECTION_SCOPES.get(name)
    return SELECTION_STRATEGIES[name]
