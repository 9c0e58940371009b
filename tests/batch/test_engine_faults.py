"""The dask engine never waits silently and never tracebacks (issue 32).

Real ``dask scheduler`` / ``dask worker`` processes on 127.0.0.1 (tests/maps/test_map.py's ``DaskCluster``) and
plain socket servers: an address that is not ``tcp://HOST:PORT``, a port that accepts and never answers, a server
that speaks garbage, a scheduler with no worker, all workers killed mid-map, the scheduler killed mid-map and the
same command run again on a new cluster. Each must end with one line and exit 1 (2 for a malformed address)
within a bound (generous, a loaded machine: the point is that it ends, not how fast).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from corpus import Case, check_case
from repo_paths import TEST_CONFIGS
from tests.cli.test_corpus_map import MAP, files
from tests.maps.test_map import DaskCluster, start_map, wait_for_chunks

#: The bound on a run that must end by itself once the fault is there: the worker / scheduler timeouts the test
#: sets (a few s) plus the map's start (imports, a connect of up to 10 s) on a loaded 2-core machine.
ENDS_WITHIN = 60.0  # s
#: What the tests set ``--worker-timeout`` to: small, so that the wait for a worker is short.
WORKER_TIMEOUT = "3"
MAP_CONFIG = TEST_CONFIGS / "map_small.yaml"


def dask_command() -> str:
    dask = shutil.which("dask", path=str(Path(sys.executable).parent)) or shutil.which("dask")
    if dask is None:
        pytest.skip("the dask command line is not installed (pip install 'dask[distributed]')")
    return dask


@pytest.fixture
def cluster(tmp_path):
    """A scheduler with no worker yet (each test adds what it needs); stopped at the end."""
    started = DaskCluster(dask_command(), tmp_path)
    try:
        yield started
    finally:
        started.stop()


class SocketServer:
    """A TCP server on 127.0.0.1 in a thread: ``reply`` None accepts and never answers; bytes are sent to every
    connection (junk), then the connection is held open."""

    def __init__(self, reply: bytes | None):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.address = f"tcp://127.0.0.1:{self.sock.getsockname()[1]}"
        self.connections: list[socket.socket] = []
        self.reply = reply
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:  # closed
                return
            self.connections.append(conn)
            if self.reply is not None:
                try:
                    conn.sendall(self.reply)
                except OSError:
                    pass

    def close(self) -> None:
        self.sock.close()
        for conn in self.connections:
            conn.close()


def run_case(case: Case, tmp_path: Path, capsys, monkeypatch) -> tuple[str, float]:
    start = time.monotonic()
    line = check_case(case, tmp_path / "ws", capsys, monkeypatch)
    return line, time.monotonic() - start


# --------------------------------------------------------------------------- addresses, before connecting
MALFORMED = ["tcp://", "tcp://127.0.0.1:notaport", "inproc://x", "tcp://[::1", "tcp://127.0.0.1:99999",
             "127.0.0.1:8786"]


@pytest.mark.parametrize("address", MALFORMED)
@pytest.mark.parametrize("how", ["option", "environment"])
def test_a_malformed_scheduler_address_is_one_line_before_connecting(address, how, tmp_path, capsys, monkeypatch):
    key = "--scheduler" if how == "option" else "AFMID_SCHEDULER"
    argv = MAP + (("--scheduler", address) if how == "option" else ())
    env = {"AFMID_SCHEDULER": address} if how == "environment" else {}
    case = Case(id=f"map-scheduler-{address}", category="config", argv=argv, files=files(), exit_code=2, file=None,
                key=key, fragments=("tcp://HOST:PORT", address), env=env)
    _, took = run_case(case, tmp_path, capsys, monkeypatch)
    assert took < 30.0, f"a malformed address took {took:.1f} s to refuse (it must not be connected to)"


@pytest.mark.parametrize("address", ["tcp://127.0.0.1:8786", "tcp://[::1]:8786", "tls://scheduler.cluster:8786",
                                     "tcp://node-07:1"])
def test_a_well_formed_scheduler_address_is_taken_as_it_is(address, monkeypatch):
    from afmid.batch.engine_dask import scheduler_address

    monkeypatch.delenv("AFMID_SCHEDULER", raising=False)
    assert scheduler_address(address) == address
    monkeypatch.setenv("AFMID_SCHEDULER", address)
    assert scheduler_address(None) == address


def test_the_worker_timeout_and_its_default_are_in_the_help():
    from click.testing import CliRunner

    from afmid.batch.engine_dask import DEFAULT_WORKER_TIMEOUT
    from afmid.cli import cli

    for command in ("map", "batch"):
        text = " ".join(CliRunner().invoke(cli, [command, "--help"]).output.split())
        assert "--worker-timeout SECONDS" in text, command
        assert f"(default: {DEFAULT_WORKER_TIMEOUT:g})" in text, command


# --------------------------------------------------------------------------- servers that are not a scheduler
@pytest.mark.parametrize("reply", [None, b"HTTP/1.0 200 OK\r\n\r\n" + b"garbage " * 512],
                         ids=["accepts-and-never-answers", "speaks-garbage"])
def test_a_server_that_is_not_a_dask_scheduler_is_one_line(reply, tmp_path, capsys, monkeypatch):
    server = SocketServer(reply)
    try:
        case = Case(id="map-scheduler-not-dask", category="request", argv=("-q",) + MAP + ("--scheduler", server.address),
                    files=files(), exit_code=1, file=None, key="--scheduler",
                    fragments=(server.address, "dask scheduler"), subprocess=True)
        _, took = run_case(case, tmp_path, capsys, monkeypatch)
    finally:
        server.close()
    assert took < ENDS_WITHIN


# --------------------------------------------------------------------------- a real scheduler without workers
def test_a_scheduler_with_no_worker_is_one_line_after_the_worker_timeout(cluster, tmp_path, capsys, monkeypatch):
    case = Case(id="map-scheduler-no-worker", category="request",
                argv=("-q",) + MAP + ("--scheduler", cluster.address, "--worker-timeout", WORKER_TIMEOUT), files=files(),
                exit_code=1, file=None, key="--worker-timeout",
                fragments=(cluster.address, "no dask worker", f"{WORKER_TIMEOUT} s"), subprocess=True)
    _, took = run_case(case, tmp_path, capsys, monkeypatch)
    assert took < ENDS_WITHIN


def test_a_batch_at_a_scheduler_with_no_worker_is_one_line(cluster, tmp_path):
    """``afmid batch --scheduler`` shares the engine: the same line; the summary of what finished (nothing) is
    written, so that the next run resumes."""
    import yaml

    raw = yaml.safe_load(MAP_CONFIG.read_text())
    del raw["simulate"]["map"]
    (tmp_path / "item.yaml").write_text(yaml.safe_dump(raw))
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "afmid.cli", "-q", "batch", "--configs", "item.yaml", "-o", "out",
                           "--scheduler", cluster.address, "--worker-timeout", WORKER_TIMEOUT], cwd=tmp_path,
                          capture_output=True, text=True, timeout=ENDS_WITHIN * 2)
    took = time.monotonic() - start
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr
    assert len(lines) == 1 and lines[0].startswith("afmid: error: "), done.stderr
    assert "no dask worker" in lines[0] and "--worker-timeout" in lines[0], lines[0]
    assert (tmp_path / "out" / "summary.csv").is_file(), "the summary of what finished was not written"
    assert not list((tmp_path / "out").glob("*.run.h5"))
    assert took < ENDS_WITHIN


# --------------------------------------------------------------------------- faults in the middle of a map
@pytest.fixture(scope="module")
def map_file(tmp_path_factory) -> Path:
    """The 3x3 test map (tests/configs/map_small.yaml) with pixel (2, 2) spoiled with NaNs, as test_map's."""
    folder = tmp_path_factory.mktemp("faultmap")
    done = subprocess.run([sys.executable, "-m", "afmid.cli", "-q", "simulate", str(MAP_CONFIG), "-o", "map.h5"],
                          cwd=folder, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    with h5py.File(folder / "map.h5", "r+") as h5:
        trace = h5["deflection"][2, 2]
        trace[50:60] = np.nan
        h5["deflection"][2, 2] = trace
    return folder / "map.h5"


def map_args(map_file: Path, out: str, scheduler: str, quiet: bool = True) -> tuple[str, ...]:
    """The map's command; ``quiet``: no progress lines (what is left on stderr is afmid's error and warnings)."""
    return ("-q",) * quiet + ("map", str(MAP_CONFIG), "--input", str(map_file), "-o", out, "--scheduler", scheduler, "--chunk", "1",
            "--worker-timeout", WORKER_TIMEOUT, "--no-diagnosis")


def wait_for_tasks(cluster: DaskCluster, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    """Until the map's tasks are on the scheduler."""
    from distributed import Client

    deadline = time.monotonic() + timeout
    with Client(cluster.address, timeout=30, set_as_default=False) as client:
        while not any(client.processing().values()):
            assert proc.poll() is None, f"the map ended before submitting: {proc.communicate()}"
            assert time.monotonic() < deadline, "the map submitted nothing in time"
            time.sleep(0.1)


def ended(proc: subprocess.Popen, since: float) -> tuple[int, str, float]:
    try:
        _, err = proc.communicate(timeout=ENDS_WITHIN * 2)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
        pytest.fail(f"the map was still waiting {ENDS_WITHIN * 2:.0f} s after the fault: {err[-2000:]}")
    return proc.returncode, err, time.monotonic() - since


def one_error_line(err: str) -> str:
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if line.startswith("afmid: error: ")]
    assert len(errors) == 1, err
    others = [line for line in err.splitlines() if line.strip() and not line.startswith("afmid: ")]
    assert not others, f"lines not from afmid on stderr: {others}"
    return errors[0]


def test_all_workers_killed_mid_map_is_one_line_after_the_worker_timeout(cluster, map_file, tmp_path):
    worker = cluster.add_worker()
    cluster.wait_for_workers(1)
    worker.send_signal(signal.SIGSTOP)  # the map's tasks wait in the frozen worker
    proc = start_map(*map_args(map_file, "out.h5", cluster.address), cwd=tmp_path)
    try:
        wait_for_tasks(cluster, proc)
        worker.kill()  # the only worker, without a goodbye
        worker.wait()
        code, err, took = ended(proc, time.monotonic())
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    line = one_error_line(err)
    assert code == 1, err
    assert "no dask worker" in line and "--worker-timeout" in line and cluster.address in line, line
    assert not (tmp_path / "out.h5").exists()
    assert took < ENDS_WITHIN


def test_a_scheduler_that_stops_answering_mid_map_is_one_line(cluster, map_file, tmp_path):
    """The scheduler frozen (SIGSTOP) while the map's tasks are on it: its connections stay open and nothing
    answers; the map's watch gets no answer within the connect timeout (10 s)."""
    worker = cluster.add_worker()
    cluster.wait_for_workers(1)
    worker.send_signal(signal.SIGSTOP)  # no chunk finishes: the map is surely still running when the scheduler stops
    proc = start_map(*map_args(map_file, "out.h5", cluster.address), cwd=tmp_path)
    try:
        wait_for_tasks(cluster, proc)
        cluster.scheduler.send_signal(signal.SIGSTOP)
        code, err, took = ended(proc, time.monotonic())
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        cluster.scheduler.kill()  # a stopped process dies too
        worker.kill()
    line = one_error_line(err)
    assert code == 1, err
    assert cluster.address in line and "--scheduler" in line, line
    assert not (tmp_path / "out.h5").exists()
    assert took < ENDS_WITHIN


def test_the_scheduler_killed_mid_map_keeps_the_chunks_and_the_next_cluster_resumes(map_file, tmp_path):
    dask = dask_command()
    first = DaskCluster(dask, tmp_path)
    try:
        first.add_worker()
        first.wait_for_workers(1)
        proc = start_map(*map_args(map_file, "out.h5", first.address), cwd=tmp_path)
        try:
            sidecar = tmp_path / "out.h5.afmid-map"
            wait_for_chunks(sidecar, 1, proc)
            for worker in first.workers:
                worker.send_signal(signal.SIGSTOP)  # no further chunk before the scheduler is gone
            saved = len(list(sidecar.glob("chunk_*.npz")))
            assert saved < 9, "the map was over before the scheduler was killed"
            first.scheduler.kill()
            first.scheduler.wait()
            code, err, took = ended(proc, time.monotonic())
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
    finally:
        first.stop()
    line = one_error_line(err)
    assert code == 1, err
    assert first.address in line and "scheduler" in line, line
    assert not (tmp_path / "out.h5").exists(), "a result was written from a map whose scheduler was lost"
    kept = sorted(p.name for p in sidecar.glob("chunk_*.npz"))
    assert len(kept) >= saved
    for name in kept:  # the chunks kept are fitted ones, not chunks of pixels marked failed by the lost scheduler
        with np.load(sidecar / name) as chunk:
            assert "Cancelled" not in " ".join(str(m) for m in chunk["message"]), name
    assert took < ENDS_WITHIN

    second = DaskCluster(dask, tmp_path)
    try:
        second.add_worker()
        second.wait_for_workers(1)
        done = subprocess.run([sys.executable, "-m", "afmid.cli", *map_args(map_file, "out.h5", second.address, quiet=False)],
                              cwd=tmp_path, capture_output=True, text=True, timeout=600)
    finally:
        second.stop()
    assert done.returncode == 1, done.stderr  # pixel (2, 2) fails: its trace holds NaNs
    assert f"resuming: {len(kept)} of 9 chunks already fitted" in done.stderr, done.stderr
    with h5py.File(tmp_path / "out.h5", "r") as h5:
        assert (h5.attrs["n_ok"] + h5.attrs["n_suspect"], h5.attrs["n_failed"]) == (8, 1)
