"""Every section of a Markdown page that the docs and the tests point a reader to is still on that page.

The docs name a section by its title in quotes after the page: ``docs/accuracy.md, "Poor signals"`` or
``bench/README.md "Cold start"``. When a topic doc's history moves to docs/lab/, a section cited elsewhere must stay
(or the citation follow it); otherwise the reader lands on a page without it. A quoted title resolves when, case and
line breaks aside, it is part of a heading or of a bold paragraph label (``**Threads.**``) of the page. Pages are
looked up from the repository's root, from docs/, and beside the citing file. Checked: README.md, docs/*.md,
bench/README.md, the package's and the tests' modules (docstrings and comments); docs/lab/ is history and may cite a
page as it was. Every relative Markdown link ``[text](path)`` in the same Markdown pages must name a file that
exists.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from repo_paths import REPO_ROOT, TESTS_DIR

#: ``page.md, "Title"``, ``page.md "Title"`` or ``page.md ("Title"``: a page and a section title in quotes.
SECTION_REFERENCE = re.compile(r"((?:[\w.-]+/)*[\w.-]+\.md),? \(?\"([^\"]{3,100})\"")
MARKDOWN_LINK = re.compile(r"\]\(([^)\s]+)\)")
BOLD_LABEL = re.compile(r"\*\*([^*]+)\*\*")
FENCE = re.compile(r"^\s*(```|~~~)")


def markdown_pages() -> list[Path]:
    return [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md")), REPO_ROOT / "bench" / "README.md"]


def citing_files() -> list[Path]:
    """The Markdown pages, the package's modules and the test modules, but this one (its examples cite pages that are not there)."""
    return [*markdown_pages(), *sorted((REPO_ROOT / "afmid").rglob("*.py")),
            *sorted(path for path in TESTS_DIR.rglob("*.py") if path != Path(__file__).resolve())]


def joined(text: str) -> str:
    """``text`` on one line: a reference broken over lines of prose or of ``#`` / ``#:`` comments joined up."""
    return re.sub(r"[ \t]+", " ", re.sub(r"\n\s*(?:#:?\s*)?", " ", text))


def section_titles(page: Path) -> list[str]:
    """The headings and bold paragraph labels of Markdown ``page`` (outside code blocks), lower case."""
    titles, fenced = [], False
    for line in page.read_text(encoding="utf-8").splitlines():
        if FENCE.match(line):
            fenced = not fenced
        elif not fenced:
            if line.startswith("#"):
                titles.append(line.lstrip("#").strip())
            titles.extend(BOLD_LABEL.findall(line))
    return [re.sub(r"\s+", " ", title).lower() for title in titles]


def unresolved_references(citing: Path, text: str) -> list[str]:
    """The section references in ``text`` (from file ``citing``) whose page or section is not there."""
    missing = []
    for name, title in SECTION_REFERENCE.findall(joined(text)):
        page = next((candidate for candidate in (REPO_ROOT / name, REPO_ROOT / "docs" / name, citing.parent / name)
                     if candidate.is_file()), None)
        wanted = re.sub(r"\s+", " ", title).strip().rstrip(".:").lower()
        if page is None:
            missing.append(f"{name} (no such page), \"{title}\"")
        elif not any(wanted in found for found in section_titles(page)):
            missing.append(f"{name}, \"{title}\"")
    return missing


def test_the_reference_finder_sees_a_moved_section_and_passes_a_present_one():
    """Control: a title that is a heading, a bold label, or part of one resolves; a missing one does not."""
    here = REPO_ROOT / "README.md"
    text = ('See docs/accuracy.md, "Poor signals" and bench/README.md "Threads" and\n#: docs/diagnosis.md ("The noise\n'
            '#: floor and its threshold"); docs/coverage.md, "A section that moved away"; docs/nowhere.md, "Intro".')
    assert unresolved_references(here, text) == ['docs/coverage.md, "A section that moved away"',
                                                 'docs/nowhere.md (no such page), "Intro"']


def test_the_docs_and_tests_cite_sections():
    """The pattern matches what the files write (one that matched nothing would pass vacuously)."""
    count = sum(len(SECTION_REFERENCE.findall(joined(path.read_text(encoding="utf-8")))) for path in citing_files())
    assert count > 20


def test_every_cited_section_exists():
    missing = [f"{citing.relative_to(REPO_ROOT)}: {reference}" for citing in citing_files()
               for reference in unresolved_references(citing, citing.read_text(encoding="utf-8"))]
    assert missing == []


@pytest.mark.parametrize("page", markdown_pages(), ids=lambda path: path.relative_to(REPO_ROOT).as_posix())
def test_every_relative_link_names_a_file(page):
    missing = [target for target in MARKDOWN_LINK.findall(page.read_text(encoding="utf-8"))
               if not target.startswith(("http:", "https:", "mailto:", "#"))
               and not (page.parent / target.partition("#")[0]).exists()]
    assert missing == []
