"""Batch worker entry points that inject faults or delays, for the batch tests.

A module of its own, importable by name in the spawned workers, so the faults live in the tests, not in afmid:
in-process tests pass them as ``run_batch(worker=...)`` (pytest puts tests/support on the path, and spawned processes
inherit it); a batch subprocess runs them through the test-side script ``batch_with_worker.py`` (:data:`HOLD_1500MS`
etc.: the command that starts it with the worker; afmid's command line has no hook for a foreign worker).
"""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

from afmid.batch.run import fit_task

#: The item whose worker dies.
DYING_ITEM = "n02"


def fit_task_dying_on_one_item(task: dict) -> dict:
    """:func:`afmid.batch.run.fit_task`, except that the worker running item ``DYING_ITEM`` SIGKILLs itself first."""
    if task["name"] == DYING_ITEM:
        os.kill(os.getpid(), signal.SIGKILL)
    return fit_task(task)


def _holding(seconds: float):
    """A worker that holds every item ``seconds`` in mid-item: a simulated trace under its temporary name (before
    it is renamed into place), else before the fit. Makes interrupting a batch mid-item deterministic."""

    def worker(task: dict) -> dict:
        return fit_task(task, pause=lambda: time.sleep(seconds))

    return worker


def fit_task_holding_1500ms(task: dict) -> dict:
    """:func:`afmid.batch.run.fit_task`, held 1.5 s in mid-item (see :func:`_holding`)."""
    return _holding(1.5)(task)


def fit_task_holding_2s(task: dict) -> dict:
    """:func:`afmid.batch.run.fit_task`, held 2 s in mid-item (see :func:`_holding`)."""
    return _holding(2.0)(task)


def fit_task_holding_30s(task: dict) -> dict:
    """:func:`afmid.batch.run.fit_task`, held 30 s in mid-item (see :func:`_holding`)."""
    return _holding(30.0)(task)


#: The item whose worker Ctrl-Cs the batch at a chosen point of its own item (the other items are held 30 s mid-item).
INTERRUPTING_ITEM = "n01"


def _ctrl_c_the_batch() -> None:
    """Ctrl-C as a terminal delivers it: SIGINT to the batch's whole process group (the workers ignore it)."""
    os.killpg(os.getpgid(0), signal.SIGINT)


def fit_task_interrupting_after_its_run_file(task: dict) -> dict:
    """:func:`afmid.batch.run.fit_task`; the worker of ``INTERRUPTING_ITEM`` Ctrl-Cs the batch right after its run file
    is renamed into place, before the parent has its result: a Ctrl-C at a fixed point of the race between a worker's
    run file and the parent's record of it. The other items are held 30 s mid-item, so they are stopped unfinished."""
    if task["name"] != INTERRUPTING_ITEM:
        return fit_task_holding_30s(task)
    out = fit_task(task)
    _ctrl_c_the_batch()
    return out


def _batch_command(function) -> list[str]:
    """The command that runs ``afmid batch``'s :func:`afmid.batch.run.run_batch` with ``function`` as the worker
    (tests/support/batch_with_worker.py); the batch arguments (CONFIG, --inputs, -o, ...) follow it."""
    return [sys.executable, str(Path(__file__).with_name("batch_with_worker.py")), function.__name__]


#: Commands (then the ``afmid batch`` arguments after ``batch``) whose workers hold every item 1.5 s, 2 s or 30 s.
HOLD_1500MS = _batch_command(fit_task_holding_1500ms)
HOLD_2S = _batch_command(fit_task_holding_2s)
HOLD_30S = _batch_command(fit_task_holding_30s)
#: The command whose worker of ``INTERRUPTING_ITEM`` Ctrl-Cs the batch right after writing its run file.
INTERRUPT_AFTER_RUN_FILE = _batch_command(fit_task_interrupting_after_its_run_file)


class SerialEngine:
    """An :class:`afmid.batch.engine.Engine` that runs every task in this process, one after the other (what a
    replacement engine has to implement), recording the keys it ran."""

    def __init__(self):
        self.ran: list[int] = []

    def workers_for(self, n_tasks: int) -> int:
        return min(1, n_tasks)

    def run(self, worker, tasks, report, tick) -> None:
        from afmid.batch.engine import Outcome

        for key, task in tasks:
            self.ran.append(key)
            report(Outcome(key, worker(task)))
            tick()


class EngineLosingItsFirstOutcome:
    """An :class:`afmid.batch.engine.Engine` that runs the first task in this process (its run file is written), then
    is stopped by Ctrl-C before it reports that task's outcome: what the parent of the local pool meets when the
    Ctrl-C lands after the worker wrote its run file and while the outcome is being recorded."""

    def workers_for(self, n_tasks: int) -> int:
        return min(1, n_tasks)

    def run(self, worker, tasks, report, tick) -> None:
        key, task = tasks[0]
        worker(task)
        raise KeyboardInterrupt


#: What :func:`noisy_until_stopped` logs while it runs, and what it logs once its worker is being closed.
RUNNING_ERROR = "a running worker's error (shown)"
TEARDOWN_NOISE = "teardown noise: the connection closed under a heartbeat"


def noisy_until_stopped(task: dict) -> dict:
    """A dask task that logs an error through dask's worker logger while it runs, marks ``task['started']`` and
    waits until its worker is closed; a thread of it then logs what dask logs when a heartbeat's connection is
    closed under it (an exception with its traceback): the noise of a local cluster stopped by a Ctrl-C."""
    import logging
    import threading

    from distributed import get_worker
    from distributed.core import Status

    worker = get_worker()
    log = logging.getLogger("distributed.worker")
    log.error(RUNNING_ERROR)
    stopping = (Status.closing, Status.closed, Status.closing_gracefully, Status.failed)

    def teardown_noise() -> None:
        while worker.status not in stopping:
            time.sleep(0.002)
        try:
            raise OSError("Stream is closed")
        except OSError:
            log.exception(TEARDOWN_NOISE)

    noise = threading.Thread(target=teardown_noise, daemon=True)
    noise.start()
    Path(task["started"]).touch()
    deadline = time.monotonic() + task.get("seconds", 120)
    while worker.status not in stopping and time.monotonic() < deadline:
        time.sleep(0.01)
    noise.join(1.0)
    return {}
