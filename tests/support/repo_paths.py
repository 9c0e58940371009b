"""Folders the tests read, named once: the test modules sit in tests/<package>/ and the helpers in tests/support/,
so a path counted from a file's own location would change with every move."""

from __future__ import annotations

from pathlib import Path

#: tests/
TESTS_DIR = Path(__file__).resolve().parents[1]
#: The repository's root (configs/, data/, docs/, scripts/, afmid/).
REPO_ROOT = TESTS_DIR.parent
#: The tests' own run configs (accuracy cases, hidden-effect traces, map_small).
TEST_CONFIGS = TESTS_DIR / "configs"
#: A PYTHONPATH folder whose sitecustomize.py sends a child process a signal (the fault corpus).
SIGNAL_CHILD = TESTS_DIR / "signal_child"
