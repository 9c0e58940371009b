"""The bad-input corpus: one table of cases, one contract checked for each.

A :class:`Case` names an ``afmid`` command line, the files it finds in a fresh workspace folder and what
the user must see: the exit code (1 input/output, 2 config/usage, 130 interrupt, 143 SIGTERM), exactly one line on
stderr (143 after SIGTERM), ``afmid: error: ...`` naming the file and the config key, and no traceback. After the command,
:func:`check_case` also asserts that *nothing was lost or left*: every file of the workspace is byte for
byte what it was (inputs are hashed before and after), and no file appeared (no output, no
``.afmid-tmp-*``), unless the case lists it in ``leaves``.

Cases are declared in ``tests/cli/test_corpus_*.py`` files (one per category or area) as module-level
``CASES`` lists and run through :func:`corpus_params` + :func:`check_case`. Placeholders ``{ws}`` in
``argv``, ``file`` and ``fragments`` are replaced by the workspace path. In-process cases call
:func:`afmid.cli.main` (fast) under an alarm so that a case that blocks fails instead of hanging the
suite; ``subprocess=True`` cases run ``python -m afmid`` in a child (signals, environment, stdin).
"""

from __future__ import annotations

import hashlib
import os
import re
import signal
import subprocess
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import pytest

#: A progress line of a command (afmid/progress.py): `fit: selecting terms (4/6)`.
PROGRESS_LINE = re.compile(r"^(fit|simulate|report|batch): ")

#: A case that takes longer than this fails (a FIFO or a lock that blocks forever must not hang the suite).
CASE_TIMEOUT_S = 120

CATEGORIES = ("config", "data", "terms", "runfile", "output", "signal", "diskfull", "request")


@dataclass(frozen=True)
class Case:
    """One bad input and what afmid must answer."""

    id: str
    category: str  # one of CATEGORIES
    argv: tuple[str, ...]  # afmid arguments (after "afmid"); "{ws}" is the workspace folder
    files: Callable[[Path], None]  # writes the inputs into the workspace (the cwd of the command)
    exit_code: int
    file: str | None  # must appear in the error line (e.g. "{ws}/run.yaml")
    key: str | None  # config key or option the line must name, e.g. "data.path" or "--seed"
    fragments: tuple[str, ...] = ()  # further text the line must hold
    subprocess: bool = False  # run in a child process (signals, stdin)
    leaves: tuple[str, ...] = ()  # workspace paths (relative) the command may create
    env: dict[str, str] = field(default_factory=dict)  # extra environment (subprocess cases)
    skip_unless: Callable[[], str | None] | None = None  # returns a reason to skip, or None
    #: A further check of the workspace after the command (e.g. that a file it may leave is whole and listed).
    then: Callable[[Path], None] | None = None

    def __post_init__(self):
        if self.category not in CATEGORIES:
            raise ValueError(f"case {self.id}: category {self.category!r} not in {CATEGORIES}")
        if self.exit_code not in (1, 2, 130, 143):
            raise ValueError(f"case {self.id}: exit code {self.exit_code} (the contract allows 1, 2, 130, 143)")


def corpus_params(cases: Iterable[Case]):
    """``pytest.mark.parametrize`` arguments for a list of cases (ids are the case ids)."""
    cases = list(cases)
    ids = [c.id for c in cases]
    duplicates = {i for i in ids if ids.count(i) > 1}
    if duplicates:
        raise ValueError(f"duplicate corpus case ids: {sorted(duplicates)}")
    return pytest.mark.parametrize("case", cases, ids=ids)


def snapshot(folder: Path) -> dict[str, str]:
    """Relative path -> SHA-256 (or 'dir' / 'link:...' / 'special') of everything under ``folder``."""
    state: dict[str, str] = {}
    for root, dirs, files in os.walk(folder, followlinks=False):
        for name in dirs + files:
            path = Path(root) / name
            rel = str(path.relative_to(folder))
            if path.is_symlink():
                state[rel] = f"link:{os.readlink(path)}"
            elif path.is_dir():
                state[rel] = "dir"
            elif path.is_file():
                state[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
            else:
                state[rel] = "special"
    return state


def _fill(text: str, workspace: Path) -> str:
    return text.replace("{ws}", str(workspace))


class _Timeout(Exception):
    pass


def _run_in_process(argv: list[str], capsys) -> tuple[int, str]:
    from afmid.cli import main

    def on_alarm(signum, frame):
        raise _Timeout()

    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(CASE_TIMEOUT_S)
    try:
        capsys.readouterr()
        code = main(argv)
    except _Timeout:
        pytest.fail(f"afmid {' '.join(argv)} did not finish within {CASE_TIMEOUT_S} s (blocked?)")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    _, err = capsys.readouterr()
    return code, err


def _run_subprocess(argv: list[str], workspace: Path, env: dict[str, str]) -> tuple[int, str]:
    child_env = dict(os.environ, **env)
    proc = subprocess.run([sys.executable, "-m", "afmid.cli", *argv], cwd=workspace, env=child_env,
                          stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=CASE_TIMEOUT_S)
    return proc.returncode, proc.stderr


def check_case(case: Case, workspace: Path, capsys, monkeypatch) -> str:
    """Run ``case`` in ``workspace`` and assert the whole contract; returns the error line."""
    if case.skip_unless is not None:
        reason = case.skip_unless()
        if reason:
            pytest.skip(reason)
    workspace.mkdir(parents=True, exist_ok=True)
    case.files(workspace)
    before = snapshot(workspace)
    argv = [_fill(a, workspace) for a in case.argv]
    if case.subprocess:
        code, err = _run_subprocess(argv, workspace, case.env)
    else:
        monkeypatch.chdir(workspace)
        for name, value in case.env.items():
            monkeypatch.setenv(name, value)
        code, err = _run_in_process(argv, capsys)
    after = snapshot(workspace)

    assert "Traceback" not in err, err
    # The stages a command reached before it stopped (afmid/progress.py, plain lines when stderr is not a
    # terminal) are progress, not part of the error: set aside like warnings.
    lines = [line for line in err.splitlines() if line.strip() and not PROGRESS_LINE.match(line)]
    errors = [line for line in lines if line.startswith(("afmid: error: ", "afmid: interrupted", "afmid: terminated"))]
    assert len(errors) == 1, f"expected one error line on stderr, got: {err!r}"
    line = errors[0]
    if case.exit_code not in (130, 143):
        assert len(lines) == 1 or all(ln.startswith("afmid: warning: ") for ln in lines if ln != line), (
            f"expected one line on stderr (warnings aside), got: {err!r}")
    assert code == case.exit_code, f"exit {code}, expected {case.exit_code}: {line}"
    if case.file is not None:
        assert _fill(case.file, workspace) in line, f"{_fill(case.file, workspace)!r} not named in {line!r}"
    if case.key is not None:
        assert case.key in line, f"{case.key!r} not named in {line!r}"
    for fragment in case.fragments:
        assert _fill(fragment, workspace) in line, f"{_fill(fragment, workspace)!r} not in {line!r}"

    changed = sorted(k for k in before if k in after and after[k] != before[k])
    removed = sorted(k for k in before if k not in after)
    created = sorted(k for k in after if k not in before and not any(Path(k).match(p) for p in case.leaves))
    assert not changed, f"inputs changed: {changed}"
    assert not removed, f"files removed: {removed}"
    assert not created, f"left behind: {created}"
    if case.then is not None:
        case.then(workspace)
    return line
