"""Batch execution: where the items of ``afmid batch`` run. One narrow interface, :class:`Engine`, and its first
implementation, :class:`LocalPoolEngine` (``spawn``-ed worker processes on this machine).

An engine gets a module-level worker function (:func:`afmid.batch.task.fit_task` or a wrapper of it) and the
task dicts, runs ``worker(task)`` for each somewhere, and reports each :class:`Outcome` back to the caller as it
completes; what the items are, what their results mean and the summary stay with :mod:`afmid.batch.run`. Another
engine (e.g. dask.distributed) implements the same :meth:`Engine.run` and is passed as
``run_batch(engine=...)``.

:class:`LocalPoolEngine`: each worker imports afmid once and loads the numba kernels from numba's on-disk
cache; BLAS and OpenMP are limited to one thread per worker (set before NumPy is imported), so N workers use N
cores and the float summation order does not depend on the pool. A worker that dies (killed, out of memory) is
replaced, and the tasks it may have been running are retried one at a time to find the culprit, which is
reported as crashed. A worker whose parent is killed outright stops itself (:mod:`afmid.batch.orphans`).

This module imports nothing heavy at import time: a worker must be able to set its thread limits before NumPy
loads.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from afmid.threads import SINGLE_THREAD_ENV

log = logging.getLogger(__name__)

#: What :class:`LocalPoolEngine` reports for a task whose worker died while it ran alone.
WORKER_DIED = "the worker process died while running this item (killed, crashed or out of memory)"


@dataclass
class Outcome:
    """What became of one task.

    ``result``: the worker's return value. ``crashed``: why there is none (the worker died running this task).
    Both empty: the engine was stopped (Ctrl-C, SIGTERM) before the task reported; its output may still have
    been written.
    """

    key: int
    result: dict | None = None
    crashed: str = ""


class Engine(Protocol):
    """Runs batch tasks; :class:`LocalPoolEngine` is the reference implementation."""

    def workers_for(self, n_tasks: int) -> int:
        """How many workers :meth:`run` uses for ``n_tasks`` tasks (for the batch's log line)."""

    def run(self, worker: Callable[[dict], dict], tasks: Sequence[tuple[int, dict]],
            report: Callable[[Outcome], None], tick: Callable[[], None]) -> None:
        """Run ``worker(task)`` for every ``(key, task)`` of ``tasks`` and call ``report`` with each
        :class:`Outcome` as it completes (in any order, in the calling thread). Call ``tick`` about once a
        second while waiting (the caller's periodic work, e.g. the summary). Return when every task has been
        reported.

        ``worker`` is a module-level function (it may be pickled); it never raises for a bad item. A Ctrl-C or
        SIGTERM (KeyboardInterrupt, raised in the calling thread, also from ``report`` or ``tick``) stops the
        workers at once (each removes its temporary files); the engine then reports the tasks in flight
        (finished ones with their result, the others with neither result nor ``crashed``) and re-raises.
        """


class LocalPoolEngine:
    """Up to ``jobs`` ``spawn``-ed worker processes on this machine (:class:`concurrent.futures.ProcessPoolExecutor`).

    ``jobs`` None: one per CPU this process may use.
    """

    def __init__(self, jobs: int | None = None):
        self.jobs = max(1, jobs or default_jobs())

    def workers_for(self, n_tasks: int) -> int:
        """How many worker processes :meth:`run` starts for ``n_tasks`` tasks."""
        return min(self.jobs, n_tasks)

    def run(self, worker: Callable[[dict], dict], tasks: Sequence[tuple[int, dict]],
            report: Callable[[Outcome], None], tick: Callable[[], None]) -> None:
        """See :meth:`Engine.run`. Keeps up to ``jobs`` tasks in flight; replaces the pool if a worker dies."""
        import multiprocessing
        from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
        from concurrent.futures.process import BrokenProcessPool

        import afmid.interrupts as interrupts

        if not tasks:
            return
        ctx = multiprocessing.get_context("spawn")
        level = logging.getLogger("afmid").getEffectiveLevel()
        pending = deque(tasks)
        suspects: deque[tuple[int, dict]] = deque()
        n_workers = self.workers_for(len(tasks))

        def new_pool() -> ProcessPoolExecutor:
            # The thread caps go in the environment the workers are spawned with (so they hold before any
            # import) and again in the initializer.
            return ProcessPoolExecutor(n_workers, mp_context=ctx, initializer=_init_worker,
                                       initargs=(dict(SINGLE_THREAD_ENV), level, os.getpid()))

        saved_env = {k: os.environ.get(k) for k in SINGLE_THREAD_ENV}
        os.environ.update(SINGLE_THREAD_ENV)
        pool = new_pool()
        in_flight: dict = {}  # future -> ((key, task), isolated)

        def submit(job, isolated: bool) -> bool:
            try:
                in_flight[pool.submit(worker, job[1])] = (job, isolated)
                return True
            except BrokenProcessPool:  # a worker died since the last wait: its future says so below
                (suspects if isolated else pending).appendleft(job)
                refused.append(job)
                return False

        refused: list = []  # jobs a broken pool refused since the last restart

        try:
            while pending or suspects or in_flight:
                if suspects:
                    if not in_flight:  # a suspect runs alone: if the worker dies again, it is the culprit
                        submit(suspects.popleft(), True)
                else:
                    while pending and len(in_flight) < n_workers:
                        if not submit(pending.popleft(), False):
                            break
                done, _ = wait(list(in_flight), timeout=1.0, return_when=FIRST_COMPLETED)
                interrupts.raise_if_pending()  # a Ctrl-C / SIGTERM that landed where Python could not raise it
                broken = False
                for fut in done:
                    job, isolated = in_flight.pop(fut)
                    try:
                        out = fut.result()
                    except BrokenProcessPool:
                        broken = True
                        if isolated:
                            report(Outcome(job[0], crashed=WORKER_DIED))
                        else:
                            suspects.append(job)
                        continue
                    report(Outcome(job[0], out))
                broken = broken or bool(refused and not in_flight)  # nothing left to report the death
                if broken:
                    refused.clear()
                    for fut, (job, isolated) in list(in_flight.items()):  # the pool is gone: requeue the rest
                        in_flight.pop(fut)
                        suspects.append(job)
                    pool.shutdown(wait=True, cancel_futures=True)
                    log.warning("a worker process died; restarting the pool and retrying its items one at a time")
                    pool = new_pool()
                tick()
        except BaseException:
            _stop_workers(pool)
            for fut, (job, _) in in_flight.items():
                if fut.done() and not fut.cancelled() and fut.exception() is None:
                    report(Outcome(job[0], fut.result()))
                else:
                    report(Outcome(job[0]))
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
            # Let the pool's queues be finalised now (the traceback of an interrupt keeps this frame alive, and
            # semaphores still registered at exit make multiprocessing's resource tracker complain).
            pool = None
            in_flight.clear()
            import gc

            gc.collect()
            for k, v in saved_env.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v


def default_jobs() -> int:
    """The CPUs this process may run on (at least 1)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _stop_workers(pool) -> None:
    """Stop the workers now (SIGTERM: each removes its temporary file and exits), then reap them."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    for p in procs:
        if p.is_alive():
            p.terminate()
    deadline = time.monotonic() + 5.0
    for p in procs:
        p.join(timeout=max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            p.kill()
            p.join(timeout=5.0)
    pool.shutdown(wait=False, cancel_futures=True)


# =========================================================================== inside a local worker process
_worker_state: dict[str, Any] = {}


def _init_worker(env: dict[str, str], log_level: int, parent_pid: int | None = None) -> None:
    """Worker start-up: thread limits before NumPy loads, signals, logging, warm imports."""
    os.environ.update(env)
    # The parent stops workers with SIGTERM (see _stop_workers); Ctrl-C in a terminal reaches the whole
    # process group, and the parent decides what to do about it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_sigterm)
    if parent_pid is not None:  # a parent killed outright (kill -9) cannot stop its workers: they stop themselves
        from afmid.batch.orphans import exit_with_parent

        exit_with_parent(parent_pid)
    sys.unraisablehook = _on_unraisable
    logger = logging.getLogger("afmid")
    logger.handlers[:] = []
    logger.setLevel(log_level)
    logger.propagate = False
    logging.captureWarnings(True)
    _worker_state["log_level"] = log_level
    from afmid.batch.allocator import keep_freed_memory_for_reuse

    keep_freed_memory_for_reuse()
    # Import once per worker; numba's kernels load from its on-disk cache at their first call.
    import afmid.fit.pipeline as fit  # noqa: F401
    import afmid.io.trace as io  # noqa: F401


class WorkerTerminated(SystemExit):
    """Raised in a worker by SIGTERM during a task: unwinds (removing temporary files), then the worker exits."""


def _on_sigterm(signum, frame):
    if not _worker_state.get("busy"):
        os._exit(143)  # idle: nothing to clean up
    _worker_state["terminating"] = True
    raise WorkerTerminated(143)


_default_unraisablehook = sys.unraisablehook


def _on_unraisable(unraisable) -> None:
    """SIGTERM that landed in a callback that cannot raise (a weakref callback, ``__del__``): Python would print it
    as ignored and let the item run on. Exit now instead; the worker's temporary files are all inside the batch's
    temporary folder, which the parent removes."""
    if isinstance(unraisable.exc_value, WorkerTerminated) or _worker_state.get("terminating"):
        os._exit(143)
    _default_unraisablehook(unraisable)


def set_worker_busy(busy: bool) -> None:
    """A task calls this with True when it starts and False when it is done: SIGTERM to an idle worker exits at
    once, to a busy one raises :class:`WorkerTerminated` so that the task can clean up."""
    _worker_state["busy"] = busy


def worker_stopping() -> bool:
    """Whether this worker was told to stop (SIGTERM): whatever the task raises now is no result."""
    return bool(_worker_state.get("terminating"))


def worker_log_level() -> int:
    """The log level the parent had when it started this worker (WARNING outside a worker)."""
    return _worker_state.get("log_level", logging.WARNING)
