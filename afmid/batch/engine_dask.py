"""A :class:`afmid.batch.engine.Engine` on dask.distributed: :class:`DaskEngine`.

Without a scheduler address it starts a ``LocalCluster`` for the run: ``jobs`` worker processes of one thread
each (BLAS and OpenMP single-threaded in each, as :class:`afmid.batch.engine.LocalPoolEngine` does), stopped at
the end. With ``scheduler="tcp://HOST:PORT"`` (or the environment variable ``AFMID_SCHEDULER``) it uses an
existing cluster (started with ``dask scheduler`` and ``dask worker``, or dask-jobqueue on SLURM/PBS): the
workers must import the same afmid and read the input files at the same paths.

Tasks are submitted at once (``pure=False``); outcomes are reported as they complete (``as_completed`` order).
A worker that dies is survived: dask reruns its tasks elsewhere; a task that kills workers repeatedly is reported
as crashed (``KilledWorker``). Ctrl-C cancels what is in flight and reports it as unfinished.

It never waits silently: the address is checked before connecting (:func:`scheduler_address`); the
scheduler must accept a TCP connection and answer dask's ``identity`` request within ``connect_timeout`` (a port
that accepts and never answers, or a server that speaks something else, is refused in one line); while tasks are
pending the scheduler is asked every :data:`WATCH_INTERVAL` s how many workers it has, and a cluster without a
worker for ``worker_timeout`` s (none joined, or all lost), a scheduler that stops answering or is lost (the
client's futures cancelled under it) ends the run with :class:`afmid.errors.EngineError` once every finished
task is reported and the rest reported as unfinished: the caller keeps what finished and the same command
resumes, on this cluster or another.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Sequence

from afmid.batch.engine import Outcome, default_jobs
from afmid.errors import ConfigError, EngineError
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


#: How long a run waits for a worker when the cluster has none (none joined yet, or all were lost), s; the
#: ``--worker-timeout`` option of ``afmid map`` and ``afmid batch``. A minute covers a worker started by hand or
#: a batch job that is about to start; a queue that takes longer needs a longer timeout.
DEFAULT_WORKER_TIMEOUT = 60.0
#: How long the scheduler has to accept a connection and answer, at the start and at every watch, s.
DEFAULT_CONNECT_TIMEOUT = 10.0
#: How often a run asks the scheduler how many workers it has while tasks are pending, s.
WATCH_INTERVAL = 2.0
#: The address schemes of a dask scheduler reached over the network.
SCHEMES = ("tcp", "tls")


def scheduler_address(option: str | None) -> str | None:
    """The scheduler to use: ``--scheduler``, else ``$AFMID_SCHEDULER``, else None (a local cluster).

    The address is checked here, before anything connects: ``tcp://HOST:PORT`` (or ``tls://``), PORT 1-65535,
    an IPv6 HOST in brackets; otherwise a :class:`ConfigError` naming the option or the variable."""
    address = option or os.environ.get(SCHEDULER_ENV) or None
    if address is not None:
        why = _address_problem(address)
        if why:
            raise ConfigError(f"expected a scheduler address like tcp://HOST:PORT, got {address!r} ({why})",
                              key=scheduler_key(option))
    return address


def scheduler_key(option: str | None) -> str:
    """What named the scheduler: the option, or the environment variable when the option was not given."""
    return "--scheduler" if option else SCHEDULER_ENV


def _address_problem(address: str) -> str:
    """Why ``address`` is not ``SCHEME://HOST:PORT`` ('' if it is)."""
    scheme, sep, location = address.partition("://")
    if not sep:
        return "no scheme://"
    if scheme not in SCHEMES:
        return f"the scheme must be one of {', '.join(SCHEMES)}"
    host, port = _host_and_port(location)
    if host is None:
        return "HOST:PORT expected after the scheme; an IPv6 host in brackets, [::1]:8786"
    if not host:
        return "no host"
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        return "PORT must be a number from 1 to 65535"
    return ""


def _host_and_port(location: str) -> tuple[str | None, str]:
    """``HOST:PORT`` split (brackets of an IPv6 host removed); (None, '') when it has no such form."""
    if location.startswith("["):
        host, sep, rest = location[1:].partition("]")
        if not sep or not rest.startswith(":"):
            return None, ""
        return host, rest[1:]
    host, sep, port = location.rpartition(":")
    if not sep or "/" in location or ":" in host:
        return None, ""
    return host, port


class DaskEngine:
    """Runs tasks on dask.distributed workers: a local cluster of ``jobs`` processes, or the cluster at
    ``scheduler`` (named by ``scheduler_key``, the option or variable an error names).

    ``connect_timeout``: s the scheduler has to accept a connection and answer; ``worker_timeout``: s a run waits
    while the cluster has no worker before it ends with :class:`afmid.errors.EngineError` (None:
    :data:`DEFAULT_WORKER_TIMEOUT`)."""

    def __init__(self, jobs: int | None = None, scheduler: str | None = None,
                 connect_timeout: float = DEFAULT_CONNECT_TIMEOUT, worker_timeout: float | None = None,
                 scheduler_key: str = "--scheduler"):
        self.jobs = max(1, jobs or default_jobs())
        self.scheduler = scheduler
        self.scheduler_key = scheduler_key
        self.connect_timeout = connect_timeout
        self.worker_timeout = DEFAULT_WORKER_TIMEOUT if worker_timeout is None else worker_timeout
        self.n_workers_seen = 0
        self._keep = False  # inside kept_running(): run() leaves its client (and local cluster) open
        self._kept = None  # (client, cluster or None) left open by the last run() inside kept_running()

    @contextlib.contextmanager
    def kept_running(self):
        """Within this block successive :meth:`run` calls share one client and, without a scheduler address, one
        local cluster (started by the first run, stopped when the block ends): a second run (e.g. a map's group
        diagnosis after its pixels) does not pay for new worker processes that import afmid and load its kernels
        again. A run that ends with an exception closes them; the next run starts anew."""
        self._keep = True
        try:
            yield self
        finally:
            self._keep = False
            kept, self._kept = self._kept, None
            if kept is not None:
                _close(kept[0], kept[1], self.connect_timeout)

    def workers_for(self, n_tasks: int) -> int:
        """Local cluster: the worker processes started; a remote cluster: its workers when last connected."""
        if self.scheduler is None:
            return min(self.jobs, max(1, n_tasks))
        return self.n_workers_seen

    def _client(self, n_tasks: int):
        import dask
        from distributed import Client, LocalCluster

        if self.scheduler is not None:
            self.n_workers_seen = _ask_scheduler(self.scheduler, self.connect_timeout, self.scheduler_key)
            try:
                client = Client(self.scheduler, timeout=self.connect_timeout, set_as_default=False)
            except (OSError, TimeoutError) as exc:
                raise EngineError(f"cannot connect to the dask scheduler at {self.scheduler}: {exc}",
                                  key=self.scheduler_key) from None
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
        """See :meth:`afmid.batch.engine.Engine.run`. Raises :class:`afmid.errors.EngineError` (after reporting
        every task) when the cluster cannot go on: see the module's docstring."""
        if not tasks:
            return
        from distributed import as_completed

        import afmid.interrupts as interrupts

        saved_env = {k: os.environ.get(k) for k in SINGLE_THREAD_ENV}
        os.environ.update(SINGLE_THREAD_ENV)  # inherited by the local cluster's worker processes
        quiet = _QuietDask()
        client, cluster = None, None
        futures: dict = {}
        reported: set[int] = set()
        keep = False  # whether this run leaves its client and cluster open for the next (kept_running)
        try:
            if self._kept is not None and self._kept[0].status == "running":
                client, cluster = self._kept
            else:
                client, cluster = self._client(len(tasks))
            self._kept = None
            watch = _Watch(self, client, len(tasks))
            for key, task in tasks:
                futures[client.submit(run_in_worker, worker, task, pure=False)] = key
            pending = as_completed(list(futures), loop=client.loop, with_results=False)
            while not pending.is_empty():
                interrupts.raise_if_pending()
                batch = pending.next_batch(block=False)
                if not batch:
                    _wait_a_little(pending)
                for fut in batch:
                    if fut.status == "cancelled":  # not by this run: the client lost its scheduler
                        raise watch.lost_scheduler(len(reported))
                    key = futures[fut]
                    reported.add(key)
                    report(_outcome(key, fut))
                watch.check(len(reported))
                tick()
            keep = self._keep
        except BaseException:
            connected = client is not None and client.status == "running"
            for fut, key in futures.items():
                if key in reported:
                    continue
                if fut.status == "finished":
                    report(_outcome(key, fut))
                else:
                    if connected:
                        _quietly(fut.cancel)
                    report(Outcome(key))
            raise
        finally:
            futures.clear()
            if keep:
                self._kept = (client, cluster)
            else:
                _close(client, cluster, self.connect_timeout)
            quiet.restore()
            for k, v in saved_env.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v


def _close(client, cluster, timeout: float) -> None:
    """Close a run's client and the local cluster it started (either may be None). afmid's own local cluster has
    no task left when it is closed: its workers' dask loggers are raised first (not with ``-v``), since a worker's
    heartbeat cut by the scheduler's close is logged by dask with its traceback on the terminal the workers share,
    after a finished map as after an interrupted one."""
    if (cluster is not None and client is not None and client.status == "running"
            and logging.getLogger("afmid").getEffectiveLevel() > logging.DEBUG):
        _quietly(client.run, silence_dask_logs, callback_timeout=timeout)
    if client is not None:
        _quietly(client.close, timeout=timeout)
    if cluster is not None:
        cluster.close()


def _ask_scheduler(address: str, timeout: float, key: str) -> int:
    """The number of workers of the scheduler at ``address``, asked before the dask client connects (the
    client's connection has no bound on a server that accepts and never answers, and a server that speaks
    something else makes it raise whatever the garbage decodes to). :class:`EngineError` naming ``key`` when
    nothing listens there, nothing answers within ``timeout`` s, or what answers is not a dask scheduler."""
    import asyncio
    import socket

    host, port = _host_and_port(address.partition("://")[2])
    try:  # a plain TCP connect first: "nothing listens" is a different fix from "something else listens"
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as exc:
        raise EngineError(f"cannot reach the dask scheduler at {address}: {exc.strerror or exc}", key=key) from None

    async def identity() -> object:
        from distributed.comm import connect
        from distributed.security import Security

        # dask's own bound is longer than this function's: a silent server is then told by asyncio.wait_for
        # below ("did not answer"), and an error from dask's connect means a server that answered something else
        comm = await connect(address, timeout=2 * timeout, **Security().get_connection_args("client"))
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    async def bounded() -> object:
        return await asyncio.wait_for(identity(), timeout)

    from concurrent.futures import ThreadPoolExecutor

    try:  # in a thread of its own: the caller's thread may already run an event loop (a notebook)
        with ThreadPoolExecutor(1) as thread:
            answer = thread.submit(asyncio.run, bounded()).result()
    except (asyncio.TimeoutError, TimeoutError):
        raise EngineError(f"the server at {address} accepted a connection but did not answer as a dask scheduler "
                          f"within {timeout:g} s", key=key) from None
    except Exception as exc:  # noqa: BLE001 - whatever a server that speaks something else makes dask's decoder raise
        raise EngineError(f"the server at {address} is not a dask scheduler (its answer could not be read: "
                          f"{type(exc).__name__})", key=key) from None
    if not isinstance(answer, dict) or answer.get("type") != "Scheduler":
        raise EngineError(f"the server at {address} is not a dask scheduler (it answered as "
                          f"{answer.get('type') if isinstance(answer, dict) else type(answer).__name__})",
                          key=key) from None
    return int(answer.get("n_workers", len(answer.get("workers", {}))))


class _Watch:
    """What a run learns from its scheduler while tasks are pending: whether it still answers, and how long it
    has had no worker."""

    def __init__(self, engine: DaskEngine, client, n_tasks: int):
        import time

        self.engine, self.client, self.n_tasks = engine, client, n_tasks
        self.address = engine.scheduler or client.scheduler.address
        self.clock = time.monotonic
        self.last_asked = self.clock()
        self.last_worker = self.clock() if engine.n_workers_seen else None
        self.since = self.clock()  # when the run started waiting (no worker yet: the timeout counts from here)
        self.any_worker = engine.n_workers_seen > 0

    def check(self, n_done: int) -> None:
        """Raise :class:`EngineError` if the scheduler is lost, does not answer, or has had no worker for the
        worker timeout. Asks the scheduler at most every :data:`WATCH_INTERVAL` s."""
        if self.client.status != "running":
            raise self.lost_scheduler(n_done)
        now = self.clock()
        if now - self.last_asked < WATCH_INTERVAL:
            return
        self.last_asked = now
        try:
            info = self.client.sync(self.client.scheduler.identity, n_workers=0,
                                    callback_timeout=self.engine.connect_timeout)
            n_workers = int(info["n_workers"])
        except Exception:  # noqa: BLE001 - no answer in time, a closed connection: the scheduler is gone to us
            raise self.lost_scheduler(n_done) from None
        now = self.clock()
        if n_workers:
            self.engine.n_workers_seen = n_workers
            self.last_worker, self.any_worker = now, True
            return
        waited = now - (self.last_worker if self.last_worker is not None else self.since)
        if waited < self.engine.worker_timeout:
            return
        timeout = self.engine.worker_timeout
        if not self.any_worker:
            raise EngineError(f"no dask worker joined the scheduler at {self.address} within {timeout:g} s (start "
                              f"workers with 'dask worker {self.address}', or wait longer with --worker-timeout)",
                              key="--worker-timeout")
        raise EngineError(f"no dask worker at {self.address} for {timeout:g} s: all workers were lost; "
                          f"{self._resume(n_done)}", key="--worker-timeout")

    def lost_scheduler(self, n_done: int) -> EngineError:
        return EngineError(f"lost the dask scheduler at {self.address} (killed, or the network to it is down); "
                           f"{self._resume(n_done)}", key=self.engine.scheduler_key)

    def _resume(self, n_done: int) -> str:
        return (f"{n_done} of {self.n_tasks} tasks had finished and are kept; run the same command again, on this "
                "or another cluster, to resume")


class _QuietDask:
    """dask's own loggers silenced for a run (what goes wrong reaches the user as afmid's one line; a lost
    scheduler would add dask's reconnect errors on stderr), unless afmid logs at DEBUG (``-v``) and not
    ``always``."""

    ROOTS = ("distributed", "tornado")

    def __init__(self, always: bool = False):
        # dask's logging config gives some children their own level (distributed.client: warning): each is set
        names = [n for n in list(logging.root.manager.loggerDict) if n.split(".")[0] in self.ROOTS]
        self.levels = {name: logging.getLogger(name).level for name in {*self.ROOTS, *names}}
        if always or logging.getLogger("afmid").getEffectiveLevel() > logging.DEBUG:
            for name in self.levels:
                logging.getLogger(name).setLevel(logging.CRITICAL + 1)

    def restore(self) -> None:
        for name, level in self.levels.items():
            logging.getLogger(name).setLevel(level)


def silence_dask_logs() -> None:
    """Raise dask's loggers (:attr:`_QuietDask.ROOTS` and their children) in this process above CRITICAL: run in
    the workers of afmid's local cluster just before it is closed (:func:`_close`), whose shutdown would otherwise
    print dask's tracebacks of connections closed under it. Never while a run goes on: a running worker's errors are shown."""
    _QuietDask(always=True)


def _quietly(call: Callable, *args, **kwargs) -> None:
    """``call``, whose failure changes nothing for the user (a cancel or close towards a lost scheduler)."""
    try:
        call(*args, **kwargs)
    except Exception:  # noqa: BLE001
        log.debug("ignored while stopping the dask client", exc_info=True)


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
