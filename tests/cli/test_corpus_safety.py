"""Bad-input corpus, outputs that would destroy data (issue 11: "data loss must never happen").

See tests/corpus.py for the contract: one line, the exit code, and nothing in the workspace changed, removed
or left behind. Three groups:

- an output that is one of the command's inputs (the config, the trace, a run file, the manifest; also
  through a symbolic or hard link, a relative/absolute spelling or a linked folder) is refused even with
  ``--overwrite``, with a line saying it is an input (not "pass --overwrite", which would invite the loss);
- ``afmid report -o DIR --overwrite`` replaces only a report folder afmid wrote (marker ``.afmid-report``)
  that holds no foreign file and no input; an unwritable or missing parent is one line;
- a second ``afmid batch`` on a folder whose lock another process holds fails at once, naming the holder.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
from pathlib import Path

import h5py
import pytest
import yaml

from afmid.io.trace import sha256_file
from corpus import Case, check_case, corpus_params
from tests.cli.test_corpus_config import base_config, write_trace_csv
from repo_paths import REPO_ROOT

ROOT = REPO_ROOT
SIM_CONFIG = ROOT / "configs" / "dmt.yaml"
IS_INPUT = "is an input of this command"
HOLDS_INPUT = "holds an input of this command"
_cache: dict[str, Path] = {}  # "run": a run file fitted once per module (see _fitted_run)
_held_locks: list[int] = []  # lock file descriptors a case holds while afmid runs (closed after each case)


@pytest.fixture(scope="module", autouse=True)
def _fitted_run():
    """One real run file (a simulated tapping trace, fitted once per test process; a bare sinusoid has no force to
    fit), copied into the workspaces that need one."""
    from tests.cli.test_corpus_requests import reference_run

    _cache["run"] = reference_run()
    yield


@pytest.fixture(autouse=True)
def _release_held_locks():
    yield
    while _held_locks:
        os.close(_held_locks.pop())


# --------------------------------------------------------------------------- workspace builders
def files(*writers):
    """A files() callable running each writer on the workspace in turn."""

    def write(folder: Path) -> None:
        for writer in writers:
            writer(folder)

    return write


def config(name: str = "run.yaml", **changes):
    """The corpus run config (``changes`` as in base_config; "{ws}" in them is the workspace folder)."""

    def write(folder: Path) -> None:
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(yaml.safe_dump(base_config(**changes), sort_keys=False).replace("{ws}", str(folder)))

    return write


def trace(name: str = "trace.csv"):
    def write(folder: Path) -> None:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        write_trace_csv(folder, name)

    return write


def text(name: str, content: str = "my notes\n"):
    def write(folder: Path) -> None:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(content)

    return write


def symlink(name: str, target: str):
    def write(folder: Path) -> None:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        os.symlink(target, folder / name)

    return write


def hardlink(name: str, target: str):
    def write(folder: Path) -> None:
        os.link(folder / target, folder / name)

    return write


def sim_config(name: str = "sim.yaml"):
    def write(folder: Path) -> None:
        shutil.copyfile(SIM_CONFIG, folder / name)

    return write


def run_file(name: str = "r.h5", trace_name: str = "trace.csv"):
    """The cached run file, pointing at ``trace_name`` in the workspace: a copy of the trace it was fitted on
    (an afmid trace file with ground truth; the name's suffix does not matter to the run)."""

    def write(folder: Path) -> None:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / trace_name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(_cache["run"], folder / name)
        shutil.copyfile(_cache["run"].parent / "trace.h5", folder / trace_name)
        with h5py.File(folder / name, "r+") as h5:  # the run is of the workspace's trace
            h5.attrs["input_path"] = str((folder / trace_name).resolve())
            h5.attrs["input_sha256"] = sha256_file(folder / trace_name)

    return write


def report_folder(name: str, *extra: str, marker: str | None = None):
    """A report folder as afmid writes it (marker listing report.html and summary.json), plus ``extra`` files."""

    def write(folder: Path) -> None:
        out = folder / name
        out.mkdir(parents=True, exist_ok=True)
        (out / "report.html").write_text("<!doctype html><html></html>\n")
        (out / "summary.json").write_text("{}\n")
        listed = {"format": "afmid-report", "afmid_version": "0.1.0", "created": "2026-11-24T00:00:00+00:00",
                  "files": ["report.html", "summary.json"]}
        (out / ".afmid-report").write_text(marker if marker is not None else json.dumps(listed))
        for extra_name in extra:
            (out / extra_name).write_text("the user's own file\n")

    return write


def held_lock(folder_name: str, holder: str = "pid 4242 on host lab-pc, started 2026-11-24T01:00:00+00:00"):
    """Another batch holding the folder's lock: taken here through a descriptor of our own (flock locks belong to
    the open file, so afmid's own open of the file in this process conflicts with it as another process would)."""

    def write(folder: Path) -> None:
        out = folder / folder_name
        out.mkdir(parents=True, exist_ok=True)
        fd = os.open(out / ".afmid-batch.lock", os.O_RDWR | os.O_CREAT, 0o644)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.write(fd, (holder + "\n").encode())
        _held_locks.append(fd)

    return write


def manifest_csv(name: str, *paths: str):
    def write(folder: Path) -> None:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text("path\n" + "".join(f"{p}\n" for p in paths))

    return write


def case(id: str, argv: tuple[str, ...], writer, file: str, *fragments: str, key: str | None = None,
         exit_code: int = 1) -> Case:
    return Case(id=id, category="output", argv=argv, files=writer, exit_code=exit_code, file=file, key=key,
                fragments=fragments)


FIT = files(config(), trace())
OW = "--overwrite"

CASES = [
    # ---- an output that is an input: fit
    case("fit-output-is-its-config", ("fit", "run.yaml", "-o", "run.yaml", OW), FIT, "run.yaml", IS_INPUT,
         "the run config"),
    case("fit-output-is-its-config-without-overwrite", ("fit", "run.yaml", "-o", "run.yaml"), FIT, "run.yaml",
         IS_INPUT),
    case("fit-output-is-its-trace", ("fit", "run.yaml", "-o", "trace.csv", OW), FIT, "trace.csv", IS_INPUT,
         "data.path"),
    case("fit-output-symlink-to-its-trace", ("fit", "run.yaml", "-o", "link.h5", OW),
         files(config(), trace(), symlink("link.h5", "trace.csv")), "link.h5", IS_INPUT, "the trace file"),
    case("fit-output-hard-link-of-its-trace", ("fit", "run.yaml", "-o", "copy.csv", OW),
         files(config(), trace(), hardlink("copy.csv", "trace.csv")), "copy.csv", IS_INPUT),
    case("fit-output-is-the-trace-set-on-the-command-line",
         ("fit", "run.yaml", "--set", "data.path=other.csv", "-o", "other.csv", OW),
         files(config(), trace(), trace("other.csv")), "other.csv", IS_INPUT, "data.path"),
    case("fit-absolute-data-path-relative-output", ("fit", "run.yaml", "-o", "trace.csv", OW),
         files(config(**{"data.path": "{ws}/trace.csv"}), trace()), "trace.csv", IS_INPUT),
    case("fit-data-path-relative-to-a-config-elsewhere", ("fit", "cfg/run.yaml", "-o", "trace.csv", OW),
         files(config("cfg/run.yaml", **{"data.path": "../trace.csv"}), trace()), "trace.csv", IS_INPUT),
    case("fit-output-config-through-a-linked-folder", ("fit", "run.yaml", "-o", "alias/run.yaml", OW),
         files(config(), trace(), symlink("alias", ".")), "alias/run.yaml", IS_INPUT, "the run config"),
    # ---- simulate, init-config
    case("simulate-output-is-its-config", ("simulate", "sim.yaml", "-o", "sim.yaml", OW), sim_config(), "sim.yaml",
         IS_INPUT, "the config"),
    case("simulate-output-symlink-to-its-config", ("simulate", "sim.yaml", "-o", "link.yaml"),
         files(sim_config(), symlink("link.yaml", "sim.yaml")), "link.yaml", IS_INPUT),
    case("init-config-from-a-trace-onto-itself", ("init-config", "--from", "trace.csv", "-o", "trace.csv", OW),
         trace(), "trace.csv", IS_INPUT, "--from"),
    case("init-config-from-a-trace-onto-itself-without-overwrite",
         ("init-config", "--from", "trace.csv", "-o", "./trace.csv"), trace(), "trace.csv", IS_INPUT),
    # ---- report
    case("report-output-is-the-run-file", ("report", "r.h5", "-o", "r.h5", OW, "--no-suggest"), run_file(), "r.h5",
         IS_INPUT, "a run file"),
    case("report-output-is-the-trace-the-run-points-to", ("report", "r.h5", "-o", "trace.csv", "--no-suggest"),
         run_file(), "trace.csv", IS_INPUT, "the trace of r.h5"),
    case("report-into-the-working-folder-holding-the-run", ("report", "r.h5", "-o", ".", OW, "--no-suggest"),
         files(run_file(), text("notes.txt")), ".", HOLDS_INPUT, "r.h5"),
    case("report-into-a-folder-holding-the-run-deeper-down",
         ("report", "sub/deep/r.h5", "-o", "sub", OW, "--no-suggest"), run_file("sub/deep/r.h5"), "sub",
         HOLDS_INPUT),
    case("report-into-the-folder-of-the-runs-trace", ("report", "r.h5", "-o", "data", OW, "--no-suggest"),
         run_file(trace_name="data/trace.csv"), "data", HOLDS_INPUT, "the trace of r.h5"),
    case("report-over-a-folder-afmid-did-not-write", ("report", "r.h5", "-o", "notes", OW, "--no-suggest"),
         files(run_file(), text("notes/todo.txt")), "notes", "not a report folder afmid wrote"),
    case("report-over-afmids-folder-holding-a-foreign-file",
         ("report", "r.h5", "-o", "rep", OW, "--no-suggest"), files(run_file(), report_folder("rep", "mine.txt")),
         "rep", "did not write (mine.txt)"),
    case("report-over-afmids-folder-holding-a-foreign-folder",
         ("report", "r.h5", "-o", "rep", OW, "--no-suggest"),
         files(run_file(), report_folder("rep"), text("rep/extra/data.csv")), "rep", "did not write (extra)"),
    case("report-over-a-folder-with-a-garbled-marker", ("report", "r.h5", "-o", "rep", OW, "--no-suggest"),
         files(run_file(), report_folder("rep", marker="not json {")), "rep", "not a report folder afmid wrote"),
    case("report-over-afmids-folder-where-a-listed-name-is-now-a-folder",
         ("report", "r.h5", "-o", "rep", OW, "--no-suggest"),
         files(run_file(), report_folder("rep"), lambda ws: (ws / "rep" / "summary.json").unlink(),
               text("rep/summary.json/mine.csv")), "rep", "did not write (summary.json)"),
    case("report-over-the-current-folder-an-afmid-report",
         ("report", "../elsewhere/r.h5", "-o", ".", OW, "--no-suggest"),
         files(run_file("../elsewhere/r.h5", trace_name="../elsewhere/trace.csv"), report_folder(".")), ".",
         "is the current folder"),
    case("report-parent-is-a-file", ("report", "r.h5", "-o", "notes.txt/rep", "--no-suggest"),
         files(run_file(), text("notes.txt")), "notes.txt/rep", "cannot write in folder"),
    case("report-parent-missing", ("report", "r.h5", "-o", "no/such/rep", "--no-suggest"), run_file(),
         "no/such/rep", "cannot write in folder", "No such file or directory"),
    # ---- batch
    case("batch-folder-locked-by-another-batch", ("batch", "run.yaml", "--inputs", "trace.csv", "-o", "out"),
         files(config(), trace(), held_lock("out")), "out", "another afmid batch is writing to this folder",
         "pid 4242 on host lab-pc", key="--output"),
    case("batch-manifest-is-the-summary-it-would-write",
         ("batch", "run.yaml", "--manifest", "out/summary.csv", "-o", "out"),
         files(config(), trace(), manifest_csv("out/summary.csv", "../trace.csv")), "out/summary.csv", IS_INPUT,
         "the manifest", key="--output"),
    case("batch-trace-named-like-the-summary", ("batch", "run.yaml", "--manifest", "list.csv", "-o", "out"),
         files(config(), trace("out/summary.csv"), manifest_csv("list.csv", "out/summary.csv")), "out/summary.csv",
         IS_INPUT, "the trace of summary", key="--output"),
    case("batch-config-data-path-where-another-config-simulates",
         ("batch", "--configs", "cfgs/*.yaml", "-o", "out"),
         files(sim_config("sim.yaml"), lambda ws: (ws / "cfgs").mkdir(),
               lambda ws: shutil.move(ws / "sim.yaml", ws / "cfgs" / "sim.yaml"),
               config("cfgs/mine.yaml", **{"data.path": "../out/sim.trace.h5"}), trace("out/sim.trace.h5")),
         "sim.trace.h5", IS_INPUT, "the trace of mine", key="--output"),
]


@corpus_params(CASES)
def test_safety_case(case, tmp_path, capsys, monkeypatch):
    check_case(case, tmp_path / "ws", capsys, monkeypatch)
