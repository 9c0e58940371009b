"""No file outside afmid's outputs is ever created, changed or deleted (issue 32, "Done when").

One workspace holds the inputs, an output folder and a foreign folder (a sentinel file, a subfolder). User files
and symbolic links (to the foreign folder, to its sentinel, to an input) are planted beside and inside the output
paths of simulate, fit, report, export, map and batch; an output path is itself planted as a link to a foreign
file (``--overwrite`` must replace the link, not write through it). Before and after every command (each run
again with ``--overwrite``, or resumed for batch) the tree is snapshot: every file's bytes and mtime, every
link's target, every folder's presence, and the foreign folder's own mtimes; outside the declared outputs nothing
may differ. Inputs are compared the same way (afmid never writes an input).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from repo_paths import REPO_ROOT
from tests.cli.test_corpus_config import base_config, write_tapping_csv
from tests.conftest import CANTILEVER

MAP_CONFIG = REPO_ROOT / "tests" / "configs" / "map_small.yaml"
TIMEOUT = 600  # s, one command on a loaded machine


def afmid(*args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "afmid.cli", "-q", *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, timeout=TIMEOUT)


def snapshot(root: Path, outputs: list[Path]) -> dict[str, tuple]:
    """Every path under ``root`` but the ``outputs`` (and what is below an output folder): a file's SHA-256 and
    mtime, a link's target (never followed), a folder's presence; the foreign folder's own mtime too (a file made
    and removed there shows only in it)."""
    skipped = [str(p) for p in outputs]

    def declared(path: str) -> bool:
        return any(path == s or path.startswith(s + os.sep) for s in skipped)

    state = {}
    for folder, dirs, files in os.walk(root):
        for name in dirs + files:
            path = os.path.join(folder, name)
            if declared(path):
                continue
            info = os.lstat(path)
            if os.path.islink(path):
                state[path] = ("link", os.readlink(path))
            elif os.path.isdir(path):
                state[path] = ("folder", info.st_mtime_ns if "foreign" in path else None)
            else:
                state[path] = ("file", hashlib.sha256(Path(path).read_bytes()).hexdigest(), info.st_mtime_ns)
    return state


def assert_unchanged(before: dict, after: dict, what: str) -> None:
    created = sorted(set(after) - set(before))
    deleted = sorted(set(before) - set(after))
    changed = sorted(p for p in set(before) & set(after) if before[p] != after[p])
    assert not (created or deleted or changed), f"{what}: created {created}, deleted {deleted}, changed {changed}"


@pytest.fixture
def workspace(tmp_path) -> Path:
    """Inputs (trace.csv, run.yaml, sim.yaml), out/ with planted files and links, foreign/ with a sentinel."""
    ws = tmp_path / "ws"
    ws.mkdir()
    write_tapping_csv(ws)
    (ws / "run.yaml").write_text(yaml.safe_dump(base_config(**{"fit.bootstrap": 4}), sort_keys=False))
    simulated = yaml.safe_load((REPO_ROOT / "configs" / "dmt.yaml").read_text())
    simulated["cantilever"] = dict(CANTILEVER)
    simulated["simulate"]["periods"] = 12
    simulated.get("data", {}).pop("path", None)
    (ws / "sim.yaml").write_text(yaml.safe_dump(simulated, sort_keys=False))
    foreign = ws / "foreign"
    (foreign / "sub").mkdir(parents=True)
    (foreign / "sentinel.txt").write_text("the user's file: afmid must never touch it\n")
    (foreign / "sentinel.h5").write_bytes(b"not afmid's\n")
    (foreign / "sub" / "deep.txt").write_text("deeper\n")
    out = ws / "out"
    out.mkdir()
    (out / "notes.txt").write_text("the user's notes beside the outputs\n")
    (out / "run.h5.bak").write_bytes(b"a backup the user keeps\n")
    os.symlink("../foreign", out / "to_foreign")
    os.symlink("../foreign/sentinel.txt", out / "to_sentinel.txt")
    os.symlink("../trace.csv", out / "to_input.csv")
    os.symlink("../foreign/sentinel.h5", out / "linked.h5")  # an output path that is a link to a foreign file
    batch = out / "batch"  # the batch's output folder, with the user's files inside
    batch.mkdir()
    (batch / "mine.txt").write_text("the user's file inside the batch folder\n")
    os.symlink("../../foreign", batch / "to_foreign")
    os.symlink("../../foreign/sentinel.txt", batch / "trace.run.h5.link")
    return ws


def run_checked(ws: Path, outputs: list[Path], *args, expect: int = 0) -> subprocess.CompletedProcess:
    before = snapshot(ws, outputs)
    done = afmid(*args, cwd=ws)
    assert done.returncode == expect, (args, done.stderr)
    assert "Traceback" not in done.stderr
    assert_unchanged(before, snapshot(ws, outputs), " ".join(map(str, args)))
    return done


def test_no_command_touches_a_file_outside_its_outputs(workspace):
    ws, out = workspace, workspace / "out"
    trace, run, linked = out / "trace.h5", out / "run.h5", out / "linked.h5"
    for extra in ([], ["--overwrite"]):
        run_checked(ws, [trace], "simulate", "sim.yaml", "-o", trace, *extra)
        run_checked(ws, [run], "fit", "run.yaml", "-o", run, *extra)
    # the link at the output path is replaced by the run file; the foreign file it pointed to is not written
    run_checked(ws, [linked], "fit", "run.yaml", "-o", linked, "--overwrite")
    assert not linked.is_symlink() and (ws / "foreign" / "sentinel.h5").read_bytes() == b"not afmid's\n"
    report = out / "rep"
    for extra in ([], ["--overwrite"]):
        run_checked(ws, [report], "report", run, "-o", report, "--no-suggest", *extra)
        run_checked(ws, [out / "params.csv"], "export", run, "--what", "parameters", "-o", out / "params.csv", *extra)
    # a report folder holding the user's file is refused, and nothing is deleted
    (report / "mine.txt").write_text("the user's file in the report folder\n")
    run_checked(ws, [], "report", run, "-o", report, "--no-suggest", "--overwrite", expect=1)
    batch = out / "batch"
    batch_outputs = [batch / "trace.run.h5", batch / "summary.csv", batch / "summary.h5", batch / ".afmid-batch.lock"]
    for extra in ([], [], ["--force"]):  # new, resumed (up to date), forced
        run_checked(ws, batch_outputs, "batch", "run.yaml", "--inputs", "trace.csv", "-o", batch, "-j", "1", *extra)


@pytest.fixture
def map_workspace(workspace) -> Path:
    done = afmid("simulate", MAP_CONFIG, "-o", workspace / "map.h5", cwd=workspace)
    assert done.returncode == 0, done.stderr
    return workspace


def _map(ws: Path, result: Path, *extra) -> None:
    run_checked(ws, [result, Path(f"{result}.afmid-map")], "map", MAP_CONFIG, "--input", "map.h5", "-o", result,
                "-j", "1", "--no-diagnosis", *extra)


def test_map_touches_no_file_outside_its_outputs(map_workspace):
    result = map_workspace / "out" / "result.h5"
    _map(map_workspace, result)
    _map(map_workspace, result, "--overwrite")


def test_a_map_whose_sidecar_path_is_a_link_to_a_foreign_folder_leaves_that_folder_alone(map_workspace):
    """The sidecar's path (RESULT.h5.afmid-map) planted as a link to the foreign folder: the map may refuse it or
    write elsewhere, but never into (or out of) the folder it points to."""
    os.symlink("../foreign", map_workspace / "out" / "linked_result.h5.afmid-map")
    before = snapshot(map_workspace / "foreign", [])
    done = afmid("map", MAP_CONFIG, "--input", "map.h5", "-o", map_workspace / "out" / "linked_result.h5", "-j", "1",
                 "--no-diagnosis", cwd=map_workspace)
    assert "Traceback" not in done.stderr, done.stderr
    assert_unchanged(before, snapshot(map_workspace / "foreign", []), "map with a linked sidecar")


def test_a_folder_of_the_users_at_the_sidecar_path_is_not_deleted(map_workspace):
    """A folder the user made at RESULT.h5.afmid-map (no key.json of afmid's in it) is not afmid's to remove."""
    sidecar = map_workspace / "out" / "mine_result.h5.afmid-map"
    sidecar.mkdir()
    (sidecar / "data.txt").write_text("the user's data\n")
    before = snapshot(sidecar, [])
    done = afmid("map", MAP_CONFIG, "--input", "map.h5", "-o", map_workspace / "out" / "mine_result.h5", "-j", "1",
                 "--no-diagnosis", cwd=map_workspace)
    assert "Traceback" not in done.stderr, done.stderr
    assert (sidecar / "data.txt").is_file()
    assert_unchanged(before, snapshot(sidecar, []), "map with the user's folder at the sidecar path")
