"""The names of ``fit.selection_scope`` (where a fit's sparse support is decided) with their metadata.

Declared here, below the config that checks a run's choice against them and below the fit that runs them:
afmid.fit.selection_strategies registers one strategy object against each declared name (and refuses to load
if a name has no object or an object no name), so the config never imports the fit.
"""

from __future__ import annotations

from dataclasses import dataclass

from afmid.registry import Registry


@dataclass(frozen=True)
class SelectionScope:
    """A declared selection scope: its config name, a one-line title and the references behind it."""

    name: str
    title: str
    references: tuple[str, ...]


SELECTION_SCOPES: Registry[SelectionScope] = Registry("selection scope")
SELECTION_SCOPES.register(SelectionScope(
    name="vote",
    title="majority vote of the selections on groups of fit.vote_periods periods (default)",
    references=("Meinshausen & Buehlmann, J. R. Stat. Soc. B 72, 417 (2010) (stability selection; here over "
                "contiguous period groups of fixed length)",)))
SELECTION_SCOPES.register(SelectionScope(
    name="record",
    title="one selection on the whole record (BIC / AICc / CV over all periods)",
    references=("Schwarz, Ann. Stat. 6, 461 (1978)",)))
