"""Faults: interrupts at any moment of a write, stale temporary files, orphaned batch workers, a full disk.

The contract seen by the user (one line, exit code, nothing left) is in tests/cli/test_corpus_faults.py; these
tests look at the mechanisms: afmid/interrupts.py, afmid/tempfiles.py, afmid/batch/orphans.py and atomic_path /
atomic_hdf5 in afmid/io/trace.py, with real signals, real processes and a real full file system (a small tmpfs,
root only).
"""

from __future__ import annotations

import csv
import errno
import io
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from afmid import interrupts, tempfiles
from afmid.errors import OutputError
from afmid.io.trace import atomic_hdf5, atomic_path
from tests.cli.test_corpus_faults import RUN_CONFIG, fill_disk, mounted_tmpfs, trace_file_bytes
from repo_paths import SIGNAL_CHILD
from terminal_signals import ctrl_c_raises

SIGNAL_CHILD = SIGNAL_CHILD


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob(".afmid-tmp-*"))


def _dead_pid() -> int:
    """The id of a process that has exited (and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


# --------------------------------------------------------------------------- temporary names, stale files
def test_temporary_names_tell_host_and_process(tmp_path):
    with atomic_path(tmp_path / "out.v2.h5") as tmp:
        assert tmp.name.startswith(".afmid-tmp-out.v2.h5.")
        assert tempfiles.owner(tmp.name) == (tempfiles.host_tag(), os.getpid())
    assert tempfiles.owner(".afmid-tmp-out.h5.abc123") is None  # the old form: nobody's
    assert "." not in tempfiles.host_tag()


def test_a_new_write_removes_only_temporary_files_of_dead_processes_of_this_host(tmp_path, caplog):
    here = tempfiles.host_tag()
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        dead = tmp_path / f".afmid-tmp-run.h5.{here}.{_dead_pid()}.k2j4h5l6"
        live = tmp_path / f".afmid-tmp-run.h5.{here}.{sleeper.pid}.a1b2c3d4"
        other_host = tmp_path / f".afmid-tmp-run.h5.{here}x-other.{_dead_pid()}.z9y8x7w6"
        old_form = tmp_path / ".afmid-tmp-run.h5.q1w2e3r4"
        for path in (dead, live, other_host, old_form):
            path.write_bytes(b"partial HDF5")
        with caplog.at_level(logging.INFO, logger="afmid"):
            with atomic_path(tmp_path / "new.yaml") as tmp:
                tmp.write_text("x: 1\n")
        assert not dead.exists()
        assert live.exists() and other_host.exists() and old_form.exists()
        assert (tmp_path / "new.yaml").read_text() == "x: 1\n"
        assert [r.levelno for r in caplog.records if str(dead) in r.getMessage()] == [logging.INFO]
    finally:
        sleeper.kill()
        sleeper.wait()


def test_a_report_folder_left_by_a_dead_process_is_removed_by_the_next_report_write(tmp_path):
    """A report is made in a temporary folder; after kill -9 the next report written beside it removes it (a live
    process's folder and a folder of the old-report form are kept)."""
    from afmid.report.folder import report_folder

    here = tempfiles.host_tag()
    dead = tmp_path / f".afmid-tmp-rep.{here}.{_dead_pid()}.k2j4h5l6"
    live = tmp_path / f".afmid-tmp-rep.{here}.{os.getppid()}.a1b2c3d4"
    old_report = tmp_path / f".afmid-tmp-rep.old-{_dead_pid()}-1a2b3c4d"  # left between the swap's two renames
    for folder in (dead, live, old_report):
        folder.mkdir()
        (folder / "report.html").write_text("<html></html>")
    with report_folder(tmp_path / "rep2", overwrite=False) as tmp:
        assert tempfiles.owner(tmp.name) == (here, os.getpid())
        (tmp / "report.html").write_text("<html>new</html>")
    assert not dead.exists()
    assert live.exists() and old_report.exists()
    assert (tmp_path / "rep2" / "report.html").read_text() == "<html>new</html>"


def test_fit_killed_outright_leaves_a_temporary_file_the_next_run_removes(tmp_path):
    """kill -9 cannot be handled: the next write in the folder cleans up after it."""
    _fit_workspace(tmp_path)
    env = dict(os.environ, PYTHONPATH=str(SIGNAL_CHILD), PYTHONDONTWRITEBYTECODE="1", AFMID_TEST_SIGNAL="SIGKILL",
               AFMID_TEST_SIGNAL_WHEN=".afmid-tmp-*", AFMID_TEST_SIGNAL_NONEMPTY="1")
    killed = subprocess.Popen([sys.executable, "-m", "afmid.cli", "-q", "fit", "run.yaml", "-o", "out.h5"],
                              cwd=tmp_path, env=env, stderr=subprocess.DEVNULL)
    assert killed.wait(timeout=120) == -signal.SIGKILL
    left = _leftovers(tmp_path)
    assert len(left) == 1 and tempfiles.owner(left[0]) == (tempfiles.host_tag(), killed.pid)
    done = subprocess.run([sys.executable, "-m", "afmid.cli", "fit", "run.yaml", "-o", "out2.h5"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert _leftovers(tmp_path) == []
    assert f"{left[0]}, a temporary file left by process {killed.pid}, which no longer runs" in done.stderr


# --------------------------------------------------------------------------- interrupts
def test_an_interrupt_lost_in_a_weakref_callback_still_stops_the_write(tmp_path):
    import weakref

    class Released:
        pass

    with ctrl_c_raises(), interrupts.handled():
        with pytest.raises(KeyboardInterrupt):
            with atomic_path(tmp_path / "out.yaml") as tmp:
                tmp.write_text("x: 1\n")
                obj = Released()
                ref = weakref.ref(obj, lambda _: os.kill(os.getpid(), signal.SIGINT))  # raises inside the callback
                del obj, ref
                assert interrupts.pending() == signal.SIGINT  # Python swallowed it; afmid did not
        assert interrupts.pending() == signal.SIGINT
    assert interrupts.pending() is None  # cleared when the outermost block ends
    assert list(tmp_path.iterdir()) == []


def test_an_interrupt_swallowed_in_a_c_callback_ends_the_command_as_interrupted(monkeypatch, capsys):
    """numba's compiler receives a kernel's object code from LLVM in a C callback; a SIGTERM there is swallowed
    and the compile then fails ("no compiled object yet for <Library 'subset_rss'>"): seen as a traceback in the
    corpus case fit-sigterm-during-write with a cold kernel cache. The command ends as terminated instead."""
    import ctypes
    import ctypes.util

    import afmid.cli as cli

    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    compare_type = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_int))

    def compare(a, b):
        os.kill(os.getpid(), signal.SIGTERM)  # afmid's handler raises inside the C callback: swallowed there
        return a[0] - b[0]

    def work_broken_by_the_signal(argv):
        values = (ctypes.c_int * 2)(2, 1)
        libc.qsort(values, 2, ctypes.sizeof(ctypes.c_int), compare_type(compare))
        raise RuntimeError("no compiled object yet")  # what the half-done work raises next

    monkeypatch.setattr(cli, "_run", work_broken_by_the_signal)
    assert cli.main(["version"]) == interrupts.EXIT_TERMINATED
    assert "afmid: terminated" in capsys.readouterr().err
    assert interrupts.pending() is None


def test_signals_during_an_hdf5_write_wait_for_the_file_to_be_closed(tmp_path):
    """Neither Ctrl-C (default handler) nor SIGTERM (afmid's handler) lands inside the HDF5 library."""
    with ctrl_c_raises(), pytest.raises(KeyboardInterrupt):
        with atomic_hdf5(tmp_path / "a.h5", "test", "") as h5:
            os.kill(os.getpid(), signal.SIGINT)
            h5.create_dataset("x", data=np.arange(10.0))  # still written: the interrupt waits
            assert "x" in h5
    with interrupts.handled():
        with pytest.raises(interrupts.Terminated):
            with atomic_hdf5(tmp_path / "b.h5", "test", "") as h5:
                os.kill(os.getpid(), signal.SIGTERM)
                h5.create_dataset("x", data=np.arange(10.0))
    assert list(tmp_path.iterdir()) == []


def test_sigterm_is_restored_after_the_command(tmp_path):
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    from afmid.cli import main

    assert main(["init-config", "-o", str(tmp_path / "x.yaml")]) == 0
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before


@pytest.fixture(scope="module")
def trace_bytes() -> bytes:
    """The fault corpus's trace file (the example DMT config, 20 periods), simulated once per session."""
    return trace_file_bytes()


def _fit_workspace(folder: Path, trace: bytes | None = None) -> None:
    (folder / "trace.h5").write_bytes(trace_file_bytes() if trace is None else trace)
    (folder / "run.yaml").write_text(yaml.safe_dump(RUN_CONFIG))


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_a_signal_at_any_moment_of_the_write_phase_leaves_nothing_or_a_whole_file(sig, tmp_path, trace_bytes):
    """Measured before the fix: 5 of 6 Ctrl-Cs 10-50 ms into fit's write phase were swallowed (exit 0, output
    written), SIGTERM left the temporary file. Now: the signal stops the run (nothing written) or, if it comes
    after the output was renamed into place, the run has finished with a whole file; never a temporary file."""
    _fit_workspace(tmp_path, trace_bytes)
    code = {"SIGINT": 130, "SIGTERM": 143}[sig]
    outcomes = []
    for delay in (0.0, 0.005, 0.01, 0.02, 0.04):
        (tmp_path / "out.h5").unlink(missing_ok=True)
        env = dict(os.environ, PYTHONPATH=str(SIGNAL_CHILD), PYTHONDONTWRITEBYTECODE="1", AFMID_TEST_SIGNAL=sig,
                   AFMID_TEST_SIGNAL_WHEN=".afmid-tmp-*", AFMID_TEST_SIGNAL_NONEMPTY="1",
                   AFMID_TEST_SIGNAL_DELAY=str(delay))
        proc = subprocess.run([sys.executable, "-m", "afmid.cli", "-q", "fit", "run.yaml", "-o", "out.h5"],
                              cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
        assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr, proc.stderr
        assert _leftovers(tmp_path) == []
        if proc.returncode in (0, -signal.Signals[sig].value):
            # Finished before the signal came (0), or the command had finished and restored the default handlers
            # when the signal came, and it ended the interpreter on its way out (-signal): a whole file either way.
            with h5py.File(tmp_path / "out.h5", "r") as h5:
                assert "diagnostics/cv_error" in h5
        else:
            assert proc.returncode == code, proc.stderr
            assert not (tmp_path / "out.h5").exists()
            assert proc.stderr.strip().splitlines()[-1].endswith("no partial output was written")
        outcomes.append(proc.returncode)
    assert outcomes[0] == code  # the signal as the write begins always stops it


# --------------------------------------------------------------------------- orphaned batch workers
def _children(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
                cmdline = (entry / "cmdline").read_bytes()
            except OSError:
                continue
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            if ppid == pid and b"multiprocessing" in cmdline and b"spawn_main" in cmdline:
                out.append(int(entry.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc to find the worker processes")
def test_batch_workers_exit_when_the_parent_is_killed(tmp_path, trace_bytes):
    (tmp_path / "in").mkdir()
    for i in range(3):
        (tmp_path / "in" / f"t{i}.h5").write_bytes(trace_bytes)
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(RUN_CONFIG))
    from batch_workers import HOLD_30S

    # afmid batch's run_batch with a worker that sits in its item for 30 s
    parent = subprocess.Popen(HOLD_30S + ["run.yaml", "--inputs", "in/*.h5", "-o", "out", "-j", "2"],
                              cwd=tmp_path, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        workers: list[int] = []
        while len(workers) < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
            workers = _children(parent.pid)
        assert len(workers) == 2, "the batch did not start its two workers within 60 s"
        time.sleep(2.0)  # the workers are in their items now
        parent.kill()
        parent.wait()
        deadline = time.monotonic() + 5.0
        while any(_alive(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [w for w in workers if _alive(w)], "workers outlived their killed parent by 5 s"
    finally:
        if parent.poll() is None:
            parent.kill()
        for w in _children(parent.pid):
            os.kill(w, signal.SIGKILL)


def test_the_portable_fallback_watches_the_parent(tmp_path):
    """Where prctl is not available: a thread that sees the parent gone sends SIGTERM to its own process."""
    script = (
        "import os, subprocess, sys, time\n"
        "child = subprocess.Popen([sys.executable, '-c', 'import os, signal, sys, time\\n"
        "from afmid.batch.orphans import exit_with_parent\\n"
        "signal.signal(signal.SIGTERM, lambda *a: (open(sys.argv[1], \"w\").write(\"bye\"), os._exit(143)))\\n"
        "assert exit_with_parent(os.getppid(), use_prctl=False) == \"thread\"\\n"
        "open(sys.argv[1] + \".ready\", \"w\").close()\\n"
        "time.sleep(60)', sys.argv[1]])\n"
        "while not os.path.exists(sys.argv[1] + '.ready'): time.sleep(0.05)\n"
        "print(child.pid, flush=True)\n"
        "os._exit(0)\n"
    )
    marker = tmp_path / "exited"
    out = subprocess.run([sys.executable, "-c", script, str(marker)], capture_output=True, text=True, timeout=60)
    child = int(out.stdout.strip())
    deadline = time.monotonic() + 5.0
    while not marker.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    try:
        assert marker.exists() and marker.read_text() == "bye"
    finally:
        if _alive(child):
            os.kill(child, signal.SIGKILL)


# --------------------------------------------------------------------------- a full disk
@pytest.fixture
def small_disk(tmp_path):
    """A 4 MB tmpfs at tmp_path/disk (unmounted after the test); skips where mount is not permitted."""
    folder = tmp_path / "disk"
    folder.mkdir()
    with mounted_tmpfs(folder, "size=4m"):
        yield folder


class _DiskOf(io.BytesIO):
    """An in-memory file on a 'disk' of ``capacity`` bytes: writes past it fail with ENOSPC (no mount needed)."""

    def __init__(self, capacity: int):
        super().__init__()
        self.capacity = capacity

    def write(self, data) -> int:
        if self.tell() + memoryview(data).nbytes > self.capacity:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(data)


def test_the_hdf5_library_never_sees_a_failed_write():
    data = np.random.default_rng(2).normal(size=50_000)
    disk = _DiskOf(100_000)
    sink = tempfiles.ErrorHoldingFile(disk)
    with h5py.File(sink, "w") as h5:  # would print HDF5 errors and crash at close with the bare file object
        h5.create_dataset("x", data=data, chunks=(5_000,), compression="gzip")
        h5.create_dataset("y", data=data[:100])
        h5.attrs["note"] = "written after the disk filled up"
    assert isinstance(sink.error, OSError) and sink.error.errno == errno.ENOSPC
    # On a disk with room, the same file object changes nothing.
    room = _DiskOf(10**8)
    roomy = tempfiles.ErrorHoldingFile(room)
    with h5py.File(roomy, "w") as h5:
        h5.create_dataset("x", data=data, chunks=(5_000,), compression="gzip")
    assert roomy.error is None
    with h5py.File(io.BytesIO(room.getvalue()), "r") as h5:
        assert np.array_equal(h5["x"][...], data)


def test_hdf5_on_a_full_disk_is_one_error_and_nothing_left(small_disk):
    fill_disk(small_disk, 64_000)
    data = np.random.default_rng(1).normal(size=200_000)  # 1.6 MB, does not compress
    with pytest.raises(OutputError) as info:
        with atomic_hdf5(small_disk / "big.h5", "test", "") as h5:
            h5.create_dataset("x", data=data)
            h5.attrs["after"] = "the failed write: the library must not notice"
    assert info.value.file == str(small_disk / "big.h5") and tempfiles.NO_SPACE_TEXT in info.value.message
    assert sorted(p.name for p in small_disk.iterdir()) == ["filler.bin"]
    # What fits is written as before.
    with atomic_hdf5(small_disk / "small.h5", "test", "") as h5:
        h5.create_dataset("x", data=data[:1000])
    with h5py.File(small_disk / "small.h5", "r") as h5:
        assert np.array_equal(h5["x"][...], data[:1000])


def test_text_output_on_a_full_disk(small_disk):
    fill_disk(small_disk, 0)
    with pytest.raises(OutputError, match=tempfiles.NO_SPACE_TEXT):
        with atomic_path(small_disk / "notes.txt") as tmp:
            tmp.write_text("x" * 100_000)
    assert sorted(p.name for p in small_disk.iterdir()) == ["filler.bin"]


def test_a_batch_item_that_does_not_fit_says_so_in_the_summary(small_disk, trace_bytes):
    from afmid.batch.run import run_batch

    (small_disk / "trace.h5").write_bytes(trace_bytes)
    (small_disk / "run.yaml").write_text(yaml.safe_dump(RUN_CONFIG))
    fill_disk(small_disk, 120_000)  # the summary fits, the run file (~400 kB) does not
    result = run_batch(small_disk / "run.yaml", small_disk / "out", inputs=[str(small_disk / "trace.h5")], jobs=1)
    assert [r.status for r in result.rows] == ["failed"]
    assert tempfiles.NO_SPACE_TEXT in result.rows[0].failure and "trace.run.h5" in result.rows[0].failure
    with open(small_disk / "out" / "summary.csv", newline="") as fh:
        (row,) = list(csv.DictReader(fh))
    assert row["status"] == "failed" and tempfiles.NO_SPACE_TEXT in row["failure"]
    assert sorted(p.name for p in (small_disk / "out").iterdir()) == ["summary.csv", "summary.h5"]


class _EngineFillingTheDiskMidItem:
    """An engine that, before running each item, fills the disk for a moment and lets the batch update its summary
    (what happens when a worker's run file fills the disk while the summary's 2 s interval comes round)."""

    def __init__(self, disk: Path):
        self.disk = disk

    def workers_for(self, n_tasks: int) -> int:
        return min(1, n_tasks)

    def run(self, worker, tasks, report, tick) -> None:
        from afmid.batch.engine import Outcome

        for key, task in tasks:
            fill_disk(self.disk, 0)
            tick()  # the summary is due (interval 0): it cannot be written now
            (self.disk / "filler.bin").unlink()
            report(Outcome(key, worker(task)))
            tick()


def test_a_summary_update_on_a_momentarily_full_disk_does_not_stop_the_batch(small_disk, trace_bytes, caplog):
    from afmid.batch.run import run_batch
    from afmid.batch.task import fit_task

    (small_disk / "trace.h5").write_bytes(trace_bytes)
    (small_disk / "run.yaml").write_text(yaml.safe_dump(RUN_CONFIG))
    with caplog.at_level("WARNING", logger="afmid"):
        result = run_batch(small_disk / "run.yaml", small_disk / "out", inputs=[str(small_disk / "trace.h5")],
                           engine=_EngineFillingTheDiskMidItem(small_disk), worker=fit_task, summary_interval=0.0)
    assert [r.status for r in result.rows] == ["ok"]
    assert any("summary could not be updated now" in r.getMessage() for r in caplog.records)
    with open(small_disk / "out" / "summary.csv", newline="") as fh:
        (row,) = list(csv.DictReader(fh))
    assert row["status"] == "ok"
    assert sorted(p.name for p in (small_disk / "out").iterdir()) == ["summary.csv", "summary.h5", "trace.run.h5"]


def test_a_finished_command_ignores_signals_on_its_way_out():
    """Run as the process's command, afmid ignores SIGINT and SIGTERM once the command is over: before, a
    SIGTERM in that window killed a run that had written its whole output (exit -15 instead of 0) and a
    Ctrl-C printed a traceback (seen once in 10 runs of the test above under load). Called with argv, the
    handlers from before come back (test_sigterm_is_restored_after_the_command)."""
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    try:
        with interrupts.handled(then_ignore=True):
            assert signal.getsignal(signal.SIGTERM) is not signal.SIG_IGN
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, before[0])
        signal.signal(signal.SIGINT, before[1])
