"""How many refits the diagnoses of this process have made: a diagnosis reused from where it was kept
(afmid.diagnosis.stored) makes none, and the tests count refits rather than time them."""

from __future__ import annotations

_made = [0]


def count_refit() -> None:
    """One more refit (the base model, a candidate, a set, an instrument)."""
    _made[0] += 1


def count_refits(made: int) -> None:
    """``made`` more refits, made for this process's diagnosis by a forked child (afmid.diagnosis.forked_work)."""
    _made[0] += int(made)


def refits_made() -> int:
    """Refits made so far for this process's diagnoses (those of its forked child included)."""
    return _made[0]
