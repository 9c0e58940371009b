"""The bad-input corpus as a whole: its size and its spread over the categories the reliability promise covers.

Issue 11 asks for at least 100 cases across configs, data, term language, run files, outputs, signals and disk
full; this keeps the corpus from shrinking unnoticed (each case itself runs in its own test_corpus_*.py file).
"""

from __future__ import annotations

import importlib
from collections import Counter
from pathlib import Path

from corpus import CATEGORIES, Case

MIN_CASES = 100
#: Categories that must each hold cases (the promise of the README's reliability paragraph).
REQUIRED = ("config", "data", "terms", "runfile", "output", "signal", "diskfull", "request")


def all_cases() -> list[Case]:
    cases = []
    for path in sorted(Path(__file__).parent.glob("test_corpus_*.py")):
        if path.stem == "test_corpus_size":
            continue
        cases.extend(importlib.import_module(f"{__package__}.{path.stem}").CASES)
    return cases


def test_corpus_is_large_and_covers_every_category():
    cases = all_cases()
    counts = Counter(case.category for case in cases)
    assert set(REQUIRED) <= set(CATEGORIES)
    missing = [c for c in REQUIRED if counts[c] == 0]
    assert not missing, f"no corpus cases for {missing}; counts {dict(counts)}"
    assert len(cases) >= MIN_CASES, f"{len(cases)} corpus cases, want at least {MIN_CASES}: {dict(counts)}"
    ids = [case.id for case in cases]
    assert len(ids) == len(set(ids)), "case ids are unique across the corpus files"
