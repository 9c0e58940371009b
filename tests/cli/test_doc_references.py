"""Every module, folder and Python name that README.md and docs/*.md point a reader to exists.

A renamed or moved module leaves docs naming code that is gone (the README's layout once listed stages that no
longer existed); this test reads the docs the way a new engineer would follow them: ``afmid/fit/profile.py`` and
``afmid/maps/`` must be in the tree, ``afmid.fit.profile.profile_separation`` must import. The dated notes in
docs/lab/ are history and may name code as it was.
"""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PATH = re.compile(r"(?<![\w/.-])afmid/(?:[\w]+/)*(?:[\w]+\.py)?")
DOTTED = re.compile(r"(?<![\w/.-])afmid(?:\.[A-Za-z_]\w*)+")


def _resolves(dotted: str) -> bool:
    """True when the longest importable prefix of ``dotted`` has the rest as attributes."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        try:
            for name in parts[cut:]:
                obj = getattr(obj, name)
        except AttributeError:
            return False
        return True
    return False


def _references(pattern: re.Pattern) -> list[tuple[str, str]]:
    found = []
    for doc in DOCS:
        for match in pattern.finditer(doc.read_text()):
            found.append((doc.name, match.group(0)))
    return found


def test_the_docs_name_some_code():
    """The patterns match what the docs write (a pattern that matches nothing would pass vacuously)."""
    assert len(_references(PATH)) > 20 and len(_references(DOTTED)) > 5


def test_every_path_named_in_the_docs_exists():
    missing = [f"{doc}: {path}" for doc, path in _references(PATH) if not (ROOT / path).exists()]
    assert missing == []


def test_every_python_name_in_the_docs_imports():
    # A placeholder in capitals (``afmid.NAME`` in a sentence about names) is not a reference.
    missing = [f"{doc}: {name}" for doc, name in _references(DOTTED)
               if not name.split(".")[-1].isupper() and not _resolves(name.rstrip("."))]
    assert missing == []


@pytest.mark.parametrize("name", ["afmid/nowhere.py", "afmid.fit.nowhere"])
def test_a_missing_name_is_caught(name):
    if name.endswith(".py"):
        assert not (ROOT / name).exists()
    else:
        assert not _resolves(name)
