"""The topic docs state rules and current numbers; the measurement history lives in docs/lab/.

A topic doc (docs/*.md and bench/README.md; not docs/lab/, whose pages are the dated history) that reads as a lab
notebook buries what afmid does now under who measured what when. The rule (docs/lab/README.md, "What a topic doc
may not hold"), checked outside fenced code blocks:

- no line names a work session: ``session <number>``, ``this session``, ``(this session``, ``work log``;
- no paragraph names more than ``MAX_COMMITS_PER_PARAGRAPH`` distinct commits. A commit is a word of 7-40
  lower-case hex digits with at least one digit and one letter a-f (so neither a number nor a word such as
  "defaced" counts; a commit written in digits alone is missed, which the session rule and review catch). A
  paragraph is a run of non-blank lines; each table row is a paragraph of its own, so a table of current numbers
  may give each row its code commit.

A current number's one line (date, code commit, conditions) names one commit, or two for a before/after pair.
"""

from __future__ import annotations

import re

import pytest
from repo_paths import REPO_ROOT

#: More distinct commits than this in one paragraph is a before/after history, not a current number's line.
MAX_COMMITS_PER_PARAGRAPH = 2

SESSION = re.compile(r"\bsession\s+\d+|\bthis session\b|\bwork ?log\b", re.IGNORECASE)
COMMIT = re.compile(r"(?<![\w./-])(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}(?![\w/-])")
FENCE = re.compile(r"^\s*(```|~~~)")


def topic_docs() -> list:
    """docs/*.md (docs/lab/ is the history, one level down) and bench/README.md."""
    return [*sorted((REPO_ROOT / "docs").glob("*.md")), REPO_ROOT / "bench" / "README.md"]


def prose_lines(text: str) -> list[tuple[int, str]]:
    """The 1-based numbered lines of Markdown ``text`` outside fenced code blocks."""
    lines, fenced = [], False
    for number, line in enumerate(text.splitlines(), 1):
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            lines.append((number, line))
    return lines


def paragraphs(text: str) -> list[tuple[int, str]]:
    """(first line number, text) of each paragraph of the prose; a table row is a paragraph of its own."""
    found: list[tuple[int, str]] = []
    current: list[tuple[int, str]] = []
    for number, line in prose_lines(text) + [(0, "")]:
        is_row = line.lstrip().startswith("|")
        if not line.strip() or is_row:
            if current:
                found.append((current[0][0], "\n".join(part for _, part in current)))
            current = []
            if is_row:
                found.append((number, line))
            continue
        current.append((number, line))
    return found


def worklog_offences(text: str) -> list[str]:
    """Where ``text`` (a topic doc's Markdown) reads as a work log: 'line N: ...' per offence."""
    offences = [f"line {number}: names a session: {SESSION.search(line).group(0)!r}"
                for number, line in prose_lines(text) if SESSION.search(line)]
    for number, paragraph in paragraphs(text):
        commits = sorted(set(COMMIT.findall(paragraph)))
        if len(commits) > MAX_COMMITS_PER_PARAGRAPH:
            offences.append(f"line {number}: a paragraph naming {len(commits)} commits ({', '.join(commits)})")
    return offences


def test_the_rule_sees_each_form_and_passes_a_current_number():
    """Control: each form of a work log is caught; a current number's line, code and tables of hashes are not."""
    log = ("Session 11 (2026-11-25): faster.\n\nMeasured (this session): 3 s.\n\nSee the work log.\n\n"
           "Before 617530a, after 5964157 and 01800d5, then a7b32cc and c83d1ff.\n")
    assert [offence.split(":")[0] for offence in worklog_offences(log)] == ["line 1", "line 3", "line 5", "line 7"]
    current = ("Measured 2026-11-29 on afmid c83d1ff (2 cores, load 1-2): 0.96.\n\n"
               "| row | code |\n|---|---|\n| air | c83d1ff |\n| poor | a7b32cc |\n| liquid | 3b25b36 |\n\n"
               "```\nsession 12 a7b32cc c83d1ff 3b25b36 617530a\n```\n"
               "A sessions file, the defaced facade, seed 20261129, 1234567, sha256 of deadbeef.\n")
    assert worklog_offences(current) == []


@pytest.mark.parametrize("doc", topic_docs(), ids=lambda path: path.relative_to(REPO_ROOT).as_posix())
def test_a_topic_doc_does_not_read_as_a_work_log(doc):
    offences = worklog_offences(doc.read_text(encoding="utf-8"))
    assert offences == [], (f"{doc.relative_to(REPO_ROOT)} reads as a work log (move the dated history into "
                            f"docs/lab/, see docs/lab/README.md): " + "; ".join(offences))
