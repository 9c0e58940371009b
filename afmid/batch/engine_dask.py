"""A :class:`afmid.batch.engine.Engine` on dask.distributed: :class:`DaskEngine`.

Without a scheduler address it starts a ``LocalCluster`` for the run: ``jobs`` worker processes of one thread
each (BLAS and OpenMP single-threaded in each, as :class:`afmid.batch.engine.LocalPoolEngine` does), stopped at
the end. With ``scheduler="tcp://HOST:PORT"`` (or the environment variable ``AFMID_SCHEDULER``) it uses an
existing cluster (started with ``dask scheduler`` and ``dask worker``, or dask-jobqueue on SLURM/PBS): the
workers must import the same afmid and read the input files at the same paths.

Tasks are submitted at once (``pure=False``); outcomes are reported as they complete (``as_completed`` order).
A worker that dies is survived: dask reruns its tasks elsewhere; a task that kills workers repeatedly is reported
as crashed (``KilledWorker``). Ctrl-C cancels what is in flight and reports it as unfinished.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence

from afmid.batch.engine import Outcome, default_jobs
from afmid.errors import ConfigError
from afmid.threads import SINGLE_THREAD_ENV

log = logging.getLogger(__name__)

#: Environment variable naming an existing scheduler (``tcp://HOST:PORT``) when ``--scheduler`` is not given.
SCHEDULER_ENV = "AFMID_SCHEDULER"
#: dask's statistical profiler samples each worker's task thread every 10 ms, taking the GIL to walk its Python
#: stack: measured on the 64x64 blend map (bench conditions, 2 local workers, quiet machine) 91.6-94.1 s with it,
#: 86.6 s without, CPU 176 -> 169 s, maps bit-identical. afmid's local cluster runs without it (its nannies hand
#: the workers the dask config of this process as it is when they are made); a cluster afmid did not start keeps
#: its own setting (docs/maps.md).
WORKER_PROFILER_OFF = {"distributed.worker.profile.enabled": False}


def scheduler_address(option: str | None) -> str | None:
    """The scheduler to use: ``--scheduler``, else ``$AFMID_SCHEDULER``, else None (a local cluster)."""
    address = option or os.environ.get(SCHEDULER_ENV) or None
    if address is not None and "://" not in address:
        key = "--scheduler" if option else SCHEDULER_ENV
        raise ConfigError(f"expected a scheduler address like tcp://HOST:PORT, got {address!r}", key=key)
    return address


class DaskEngine:
    """Runs tasks on dask.distributed workers: a local cluster of ``jobs`` processes, or the cluster at
    ``scheduler``."""

    def __init__(self, jobs: int | None = None, scheduler: str | None = None, connect_timeout: float = 10.0):
        self.jobs = max(1, jobs or default_jobs())
        self.scheduler = scheduler
        self.connect_timeout = connect_timeout
        self.n_workers_seen = 0

    def workers_for(self, n_tasks: int) -> int:
        """Local cluster: the worker processes started; a remote cluster: its workers when last connected."""
        if self.scheduler is None:
            return min(self.jobs, max(1, n_tasks))
        return self.n_workers_seen

    def _client(self, n_tasks: int):
        import dask
        from distributed import Client, LocalCluster

        if self.scheduler is not None:
            try:
                client = Client(self.scheduler, timeout=self.connect_timeout, set_as_default=False)
            except (OSError, TimeoutError) as exc:
                raise ConfigError(f"cannot reach the dask scheduler at {self.scheduler}: {exc}",
                                  key="--scheduler") from None
            self.n_workers_seen = len(client.scheduler_info().get("workers", {}))
            return client, None
        # A terminal's Ctrl-C reaches the whole process group: the workers ignore it (afmid.batch.dask_worker_setup)
        # and leave it to this process, which cancels the tasks and keeps what finished.
        with dask.config.set(WORKER_PROFILER_OFF):
            cluster = LocalCluster(n_workers=self.workers_for(n_tasks), threads_per_worker=1, processes=True,
                                   dashboard_address=None, env=dict(SINGLE_THREAD_ENV), silence_logs=logging.ERROR,
                                   preload=["afmid.batch.dask_worker_setup"])
        self.n_workers_seen = len(cluster.workers)
        return Client(cluster, set_as_default=False), cluster

    def run(self, worker: Callable[[dict], dict], tasks: Sequence[tuple[int, dict]],
            report: Callable[[Outcome], None], tick: Callable[[], None]) -> None:
        """See :meth:`afmid.batch.engine.Engine.run`."""
        if not tasks:
            return
        from distributed import as_completed

        import afmid.interrupts as interrupts

        saved_env = {k: os.environ.get(k) for k in SINGLE_THREAD_ENV}
        os.environ.update(SINGLE_THREAD_ENV)  # inherited by the local cluster's worker processes
        client, cluster = None, None
        futures: dict = {}
        reported: set[int] = set()
        try:
            client, cluster = self._client(len(tasks))
            for key, task in tasks:
                futures[client.submit(run_in_worker, worker, task, pure=False)] = key
            pending = as_completed(list(futures), loop=client.loop, with_results=False)
            while not pending.is_empty():
                interrupts.raise_if_pending()
                batch = pending.next_batch(block=False)
                if not batch:
                    _wait_a_little(pending)
                for fut in batch:
                    key = futures[fut]
                    reported.add(key)
                    report(_outcome(key, fut))
                tick()
        except BaseException:
            for fut, key in futures.items():
                if key in reported:
                    continue
                if fut.status == "finished":
                    report(_outcome(key, fut))
                else:
                    fut.cancel()
                    report(Outcome(key))
            raise
        finally:
            futures.clear()
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()
            for k, v in saved_env.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v


def run_in_worker(worker: Callable[[dict], dict], task: dict) -> dict:
    """``worker(task)`` in a dask worker, with glibc's allocator keeping freed arrays for reuse
    (:mod:`afmid.batch.allocator`: dask's nanny starts workers with a setting that made a map 1.6x slower), and
    one thread per trace unless the worker's environment says otherwise (a worker is one of N single-threaded
    processes filling N cores: on a cluster afmid did not start, :data:`afmid.threads.TRACE_THREADS_ENV` is not
    set by afmid's local cluster, and a long trace would take two threads per worker)."""
    from afmid.batch.allocator import keep_freed_memory_for_reuse
    from afmid.threads import TRACE_THREADS_ENV

    keep_freed_memory_for_reuse()
    os.environ.setdefault(TRACE_THREADS_ENV, "1")
    return worker(task)


def _wait_a_little(pending) -> None:
    """Block up to about a second for the next completion (tick stays about once a second)."""
    import time

    deadline = time.monotonic() + 1.0
    while pending.count() and not pending.has_ready() and time.monotonic() < deadline:
        time.sleep(0.05)


def _outcome(key: int, fut) -> Outcome:
    """The outcome of a completed future: its result, or why it has none."""
    try:
        return Outcome(key, fut.result())
    except Exception as exc:  # the task raised, or killed its workers (KilledWorker)
        from distributed import KilledWorker

        if isinstance(exc, KilledWorker):
            return Outcome(key, crashed="the task killed the dask workers that ran it (crashed or out of memory)")
        return Outcome(key, crashed=f"{type(exc).__name__}: {exc}")
