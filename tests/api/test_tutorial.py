"""docs/python.md's tutorial runs as written: its ```python blocks, in order, in one namespace, in an empty folder
(array -> fit -> print -> diagnose -> add the suggested effect -> refit -> report -> save -> load). Its own asserts
are the checks (the suggestion, the viscosity within 5 sigma of the simulated 150 Pa s, the table read back); this
test adds that it imports nothing from below ``afmid.`` and that its outputs exist."""

from __future__ import annotations

import ast
import re

from repo_paths import REPO_ROOT

TUTORIAL = REPO_ROOT / "docs" / "python.md"


def tutorial_blocks() -> list[str]:
    """The ```python blocks of the tutorial section (before the reference)."""
    text = TUTORIAL.read_text(encoding="utf-8")
    tutorial = text.split("\n## Reference", 1)[0]
    return re.findall(r"```python\n(.*?)```", tutorial, flags=re.S)


def test_the_tutorial_imports_only_the_front_door():
    blocks = tutorial_blocks()
    assert len(blocks) >= 5
    imported = {alias.name for node in ast.walk(ast.parse("\n".join(blocks)))
                if isinstance(node, (ast.Import, ast.ImportFrom))
                for alias in (node.names if isinstance(node, ast.Import) else [ast.alias(node.module or "")])}
    assert imported == {"afmid", "numpy"}, imported
    assert "afmid." not in "".join(re.findall(r"(?:from|import) (afmid\.\w+)", "\n".join(blocks)))


def test_the_tutorial_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    for i, block in enumerate(tutorial_blocks()):
        exec(compile(block, f"{TUTORIAL}:block {i + 1}", "exec"), namespace)  # noqa: S102 - the docs' own code
    out = capsys.readouterr().out
    assert "identified law" in out and "MODEL-LIMITED" in out  # fit1.print(): afmid fit's text
    assert (tmp_path / "report" / "report.html").is_file() and (tmp_path / "run2.h5").is_file()
    assert namespace["again"].name == "run2.h5"
