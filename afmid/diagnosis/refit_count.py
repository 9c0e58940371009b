"""How many refits the diagnoses of this process have made: a diagnosis reused from where it was kept
(afmid.diagnosis.stored) makes none, and the tests count refits rather than time them."""

from __future__ import annotations

_made = [0]


def count_refit() -> None:
    """One more refit (the base model, a candidate, a set, an instrument)."""
    _made[0] += 1


def refits_made() -> int:
    """Refits made so far in this process."""
    return _made[0]
