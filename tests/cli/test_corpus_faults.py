"""Fault corpus: Ctrl-C and SIGTERM in the middle of a command, and a full disk (tests/corpus.py: the contract).

Signals are real: the child ``python -m afmid.cli`` imports tests/signal_child/sitecustomize.py, which sends
it SIGINT or SIGTERM when a file matching a glob appears in its working folder (its write phase has begun)
or after a delay. A full disk is a real one: each ``diskfull`` case runs in a small tmpfs mounted for it
(root only: skipped with the reason where mounting is not permitted), filled up to what the case leaves
free by an input file that must stay untouched like every other input.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
from functools import lru_cache
from pathlib import Path

import pytest
import yaml

from corpus import Case, check_case, corpus_params
from repo_paths import REPO_ROOT, SIGNAL_CHILD

ROOT = REPO_ROOT
SIGNAL_CHILD = SIGNAL_CHILD
#: The trace every case fits: the example DMT config simulated for 20 periods (4,000 samples).
SIMULATE_SET = ("--set", "simulate.periods=20")
RUN_CONFIG = {
    "data": {"path": "trace.h5"},
    "cantilever": {"spring_constant": 40.0, "resonance_frequency": 300.0e3, "quality_factor": 250.0,
                   "tip_radius": 10.0e-9},
    "drive": {"frequency": 300.0e3},
    "sample": {"a0": 0.165e-9},
    "model": {"effects": ["dmt"]},
    "fit": {"bootstrap": 8},
}
TMPFS_SIZE = "4m"
#: Mount options of cases that need more than a small size.
MOUNT_OPTIONS = {"fit-no-free-inode": f"size={TMPFS_SIZE},nr_inodes=16"}
NO_SPACE = "no space left on device"


# --------------------------------------------------------------------------- inputs
@lru_cache(maxsize=None)
def trace_file_bytes() -> bytes:
    """An afmid trace file (simulated once per session)."""
    import tempfile

    from afmid.config import dump_config, load_config
    from afmid.io.trace import write_trace_file
    from afmid.simulate.driver import simulate

    cfg = load_config(ROOT / "configs" / "dmt.yaml", ["simulate.periods=20"])
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "trace.h5"
        write_trace_file(path, simulate(cfg), dump_config(cfg))
        return path.read_bytes()


@lru_cache(maxsize=None)
def _run_bytes() -> bytes:
    """A run file of that trace (fitted once per session)."""
    import tempfile

    from afmid.config import build_config
    from afmid.fit.pipeline import run_fit
    from afmid.runfile import run_data, write_run

    with tempfile.TemporaryDirectory() as folder:
        (Path(folder) / "trace.h5").write_bytes(trace_file_bytes())
        config = build_config(yaml.safe_load(yaml.safe_dump(RUN_CONFIG)), source=Path(folder) / "run.yaml")
        path = Path(folder) / "run.h5"
        write_run(path, run_data(run_fit(config), config))
        return path.read_bytes()


def fill_disk(folder: Path, leave: int) -> None:
    """Fill the file system of ``folder`` until ``leave`` bytes are free (an input file, filler.bin)."""
    stat = os.statvfs(folder)
    free = stat.f_bavail * stat.f_frsize
    with open(folder / "filler.bin", "wb") as fh:
        fh.write(b"\0" * max(0, free - leave))


def _use_all_inodes(folder: Path) -> None:
    """Create empty files until the file system has no free inode."""
    for i in range(1_000):
        try:
            (folder / f"empty{i:03d}").touch()
        except OSError:
            return


def workspace(*, trace: bool = True, run_file: bool = False, config: bool = True, existing_output: bool = False,
              sim_config: bool = False, leave: int | None = None, no_inodes: bool = False):
    """A files() callable: run.yaml, trace.h5, optionally run.h5 / out.h5 / sim.yaml, then the disk filled."""

    def write(folder: Path) -> None:
        if config:
            (folder / "run.yaml").write_text(yaml.safe_dump(RUN_CONFIG, sort_keys=False))
        if trace:
            (folder / "trace.h5").write_bytes(trace_file_bytes())
        if run_file:
            (folder / "run.h5").write_bytes(_run_bytes())
        if existing_output:
            (folder / "out.h5").write_bytes(b"an earlier result that must survive\n")
        if sim_config:
            (folder / "configs").mkdir()
            (folder / "configs" / "sim.yaml").write_text((ROOT / "configs" / "dmt.yaml").read_text())
        if leave is not None:
            fill_disk(folder, leave)
        if no_inodes:
            _use_all_inodes(folder)

    return write


def signalled(signal_name: str, when: str = ".afmid-tmp-*", delay: float = 0.0) -> dict[str, str]:
    """Environment for a child that receives ``signal_name`` once ``when`` matches (+ ``delay`` s)."""
    path = os.pathsep.join([str(SIGNAL_CHILD)] + [p for p in [os.environ.get("PYTHONPATH")] if p])
    return {"PYTHONPATH": path, "PYTHONDONTWRITEBYTECODE": "1", "AFMID_TEST_SIGNAL": signal_name,
            "AFMID_TEST_SIGNAL_WHEN": when, "AFMID_TEST_SIGNAL_DELAY": str(delay)}


def at_event(signal_name: str, event: str = "tempfile.mkstemp", in_callback: bool = False) -> dict[str, str]:
    """Environment for a child that receives ``signal_name`` when it raises the audit event ``event`` (by
    default: as the temporary file of its output is made), from inside a weakref callback if asked."""
    env = signalled(signal_name, when="")
    env.update(AFMID_TEST_SIGNAL_AT=event, AFMID_TEST_SIGNAL_IN_CALLBACK="1" if in_callback else "0")
    return env


def in_callback(signal_name: str) -> dict[str, str]:
    return at_event(signal_name, in_callback=True)


FIT = ("-q", "fit", "run.yaml", "-o", "out.h5")
INTERRUPTED = "afmid: interrupted; no partial output was written"
TERMINATED = "afmid: terminated; no partial output was written"
BATCH_OUT = ("out", "out/summary.csv", "out/summary.h5")


def finished_runs_are_whole_and_listed(workspace: Path) -> None:
    """A batch stopped while its one item ran may stop before or after the worker moved the run file into place
    (the worker can finish in less than the signal's delay): either way every run file it left is whole and the
    summary lists it as finished, and an item the summary lists as finished has its run file."""
    import csv

    from afmid.runfile import load_run

    out = workspace / "out"
    with open(out / "summary.csv", encoding="utf-8") as fh:
        rows = {row["name"]: row for row in csv.DictReader(fh)}
    run_file = out / "trace.run.h5"
    if run_file.exists():
        assert rows["trace"]["status"] in ("ok", "suspect"), rows["trace"]
        assert load_run(run_file).coefficients is not None
    else:
        assert rows.get("trace", {}).get("status") not in ("ok", "suspect"), rows.get("trace")

SIGNAL_CASES = [
    Case("fit-sigterm-during-write", "signal", FIT, workspace(), 143, None, None, (TERMINATED,),
         subprocess=True, env=signalled("SIGTERM")),
    Case("fit-sigterm-as-temporary-file-is-made", "signal", FIT, workspace(), 143, None, None, (TERMINATED,),
         subprocess=True, env=at_event("SIGTERM")),
    Case("fit-sigterm-while-fitting", "signal", FIT, workspace(), 143, None, None, (TERMINATED,),
         subprocess=True, env=signalled("SIGTERM", when="audit:open:trace.h5", delay=0.2)),
    Case("fit-ctrl-c-lost-in-a-weakref-callback", "signal", FIT, workspace(), 130, None, None, (INTERRUPTED,),
         subprocess=True, env=in_callback("SIGINT")),
    Case("fit-sigterm-lost-in-a-weakref-callback", "signal", FIT, workspace(), 143, None, None, (TERMINATED,),
         subprocess=True, env=in_callback("SIGTERM")),
    Case("simulate-ctrl-c-lost-in-a-weakref-callback", "signal",
         ("-q", "simulate", str(ROOT / "configs" / "dmt.yaml"), "-o", "sim.h5", *SIMULATE_SET),
         workspace(trace=False), 130, None, None, (INTERRUPTED,), subprocess=True, env=in_callback("SIGINT")),
    Case("init-config-ctrl-c-lost-in-a-weakref-callback", "signal", ("-q", "init-config", "-o", "new.yaml"),
         workspace(trace=False, config=False), 130, None, None, (INTERRUPTED,), subprocess=True,
         env=in_callback("SIGINT")),
    Case("simulate-sigterm-as-temporary-file-is-made", "signal",
         ("-q", "simulate", str(ROOT / "configs" / "dmt.yaml"), "-o", "sim.h5", *SIMULATE_SET), workspace(trace=False),
         143, None, None, (TERMINATED,), subprocess=True, env=at_event("SIGTERM")),
    Case("report-sigterm-while-drawing", "signal", ("-q", "report", "run.h5", "-o", "rep", "--no-suggest"),
         workspace(run_file=True), 143, None, None, (TERMINATED,), subprocess=True,
         env=signalled("SIGTERM", when=".afmid-tmp-rep.*", delay=0.5)),
    Case("report-ctrl-c-lost-in-a-weakref-callback", "signal", ("-q", "report", "run.h5", "-o", "rep", "--no-suggest"),
         workspace(run_file=True), 130, None, None, (INTERRUPTED,), subprocess=True,
         env=at_event("SIGINT", event="tempfile.mkdtemp", in_callback=True)),
    Case("batch-parent-sigterm", "signal", ("-q", "batch", "run.yaml", "--inputs", "trace.h5", "-o", "out", "-j", "1"),
         workspace(), 143, None, None, (TERMINATED,), subprocess=True, leaves=BATCH_OUT + ("out/trace.run.h5",),
         env=signalled("SIGTERM", when="out/.afmid-tmp-batch-*", delay=1.0), then=finished_runs_are_whole_and_listed),
]

DISKFULL_CASES = [
    Case("fit-disk-full", "diskfull", FIT, workspace(leave=0), 1, "out.h5", None, (NO_SPACE,), subprocess=True),
    Case("fit-run-file-does-not-fit", "diskfull", FIT, workspace(leave=100_000), 1, "out.h5", None, (NO_SPACE,),
         subprocess=True),
    Case("fit-overwrite-keeps-old-output-on-full-disk", "diskfull", FIT + ("--overwrite",),
         workspace(existing_output=True, leave=50_000), 1, "out.h5", None, (NO_SPACE,), subprocess=True),
    Case("fit-no-free-inode", "diskfull", FIT, workspace(no_inodes=True), 1, "out.h5", None, (NO_SPACE,),
         subprocess=True),
    Case("simulate-trace-does-not-fit", "diskfull",
         ("-q", "simulate", str(ROOT / "configs" / "dmt.yaml"), "-o", "sim.h5", *SIMULATE_SET),
         workspace(trace=False, config=False, leave=30_000), 1, "sim.h5", None, (NO_SPACE,), subprocess=True),
    Case("init-config-disk-full", "diskfull", ("-q", "init-config", "-o", "new.yaml"),
         workspace(trace=False, config=False, leave=0), 1, "new.yaml", None, (NO_SPACE,), subprocess=True),
    Case("init-config-from-trace-disk-full", "diskfull", ("-q", "init-config", "--from", "trace.h5", "-o", "new.yaml"),
         workspace(config=False, leave=0), 1, "new.yaml", None, (NO_SPACE,), subprocess=True),
    Case("report-does-not-fit", "diskfull", ("-q", "report", "run.h5", "-o", "rep", "--no-suggest"),
         workspace(run_file=True, leave=60_000), 1, "rep", None, (NO_SPACE,), subprocess=True),
    Case("batch-run-file-does-not-fit", "diskfull",
         ("-q", "batch", "run.yaml", "--inputs", "trace.h5", "-o", "out", "-j", "1"), workspace(leave=120_000), 1,
         "out/summary.csv", None, ("1 of 1 traces failed (trace)", NO_SPACE), subprocess=True, leaves=BATCH_OUT),
    Case("batch-on-a-full-disk", "diskfull",  # the first thing a batch writes is its lock file
         ("-q", "batch", "run.yaml", "--inputs", "trace.h5", "-o", "out", "-j", "1"), workspace(leave=0), 1,
         "out/.afmid-batch.lock", None, (NO_SPACE,), subprocess=True, leaves=("out",)),
    Case("batch-simulated-trace-does-not-fit", "diskfull",
         ("-q", "batch", "--configs", "configs/*.yaml", "-o", "out", "-j", "1", *SIMULATE_SET),
         workspace(trace=False, config=False, sim_config=True, leave=80_000), 1, "out/summary.csv", None,
         ("1 of 1 runs failed (sim)", NO_SPACE), subprocess=True, leaves=BATCH_OUT),
]


CASES = SIGNAL_CASES + DISKFULL_CASES  # the whole file's corpus (tests/cli/test_corpus_size.py counts it)


@corpus_params(SIGNAL_CASES)
def test_signal_case(case, tmp_path, capsys, monkeypatch):
    check_case(case, tmp_path / "ws", capsys, monkeypatch)


@pytest.fixture
def small_disk(tmp_path, request):
    """A tmpfs mounted at tmp_path/ws for one case (unmounted after it); skips where mount is not permitted."""
    folder = tmp_path / "ws"
    folder.mkdir()
    with mounted_tmpfs(folder, MOUNT_OPTIONS.get(request.node.callspec.params["case"].id, f"size={TMPFS_SIZE}")):
        yield folder


@contextlib.contextmanager
def mounted_tmpfs(folder: Path, options: str):
    """A tmpfs mounted at ``folder`` with ``options`` for the block (unmounted after); skips the test where
    mount is not permitted."""
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)], capture_output=True,
                             text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs to fill up (needs root): {mounted.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=False)


@corpus_params(DISKFULL_CASES)
def test_diskfull_case(case, small_disk, capsys, monkeypatch):
    check_case(case, small_disk, capsys, monkeypatch)
