"""Every ``afmid <command>`` the README and docs/ name exists (issue 33: ``afmid diagnose`` was referred to, and
there is no such command).

A command is named in two ways in the Markdown: an inline code span that starts with ``afmid WORD`` and a line of
a shell block (```sh, ```bash, ```console) that starts with ``afmid WORD`` (after an optional ``$``). Prose ("afmid
reads ...") and the run file's layout strings (``afmid joint fit 1``: a name and a version number, not a command)
are not commands. Each word found is run as ``afmid WORD --help`` in-process and must exit 0.
"""

from __future__ import annotations

import re

import pytest
from repo_paths import REPO_ROOT

from afmid.cli import main

SHELL_BLOCK = re.compile(r"^```(?:sh|bash|console|shell)\s*\n(.*?)^```", re.S | re.M)
INLINE = re.compile(r"`afmid ([a-z][a-z-]*)([^`]*)`")
LAYOUT = re.compile(r"^ [a-z ]+ \d+$")  # `afmid joint fit 1`: a layout name with its version
SHELL_LINE = re.compile(r"^\s*(?:\$\s*)?afmid ([a-z][a-z-]*)", re.M)


def documents():
    return [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md"))]


def named_commands(text: str) -> set[str]:
    """The command words ``text`` (Markdown) names as ``afmid WORD`` in code."""
    words = {word for word, rest in INLINE.findall(text) if not LAYOUT.match(f" {word}{rest}")}
    for block in SHELL_BLOCK.findall(text):
        words.update(SHELL_LINE.findall(block))
    return words


def test_the_finder_sees_commands_and_skips_prose_and_layouts():
    """Control: the finder would catch the issue's case and does not take prose or a layout string for one."""
    text = ("Run `afmid diagnose run.h5`; afmid reads files; layout `afmid joint fit 1`.\n"
            "```sh\n$ afmid fit run.yaml -o run.h5\nafmid report run.h5 -o rep/\n```\n"
            "```text\nafmid sees this as prose\n```\n")
    assert named_commands(text) == {"diagnose", "fit", "report"}


def _all_named() -> list[str]:
    found: set[str] = set()
    for path in documents():
        found |= named_commands(path.read_text(encoding="utf-8"))
    return sorted(found)


def test_the_docs_name_the_main_commands():
    assert {"fit", "report", "simulate", "batch", "map", "effects", "inspect", "init-config"} <= set(_all_named())


@pytest.mark.parametrize("word", _all_named())
def test_every_command_the_docs_name_exists(word, capsys):
    where = [p.relative_to(REPO_ROOT).as_posix() for p in documents()
             if word in named_commands(p.read_text(encoding="utf-8"))]
    try:
        code = main([word, "--help"])
    except SystemExit as stop:  # click's standalone mode may exit
        code = stop.code
    out, err = capsys.readouterr()
    assert code == 0 and "Usage:" in out, f"`afmid {word}` named in {where} does not exist: {err.strip()[-300:]}"
