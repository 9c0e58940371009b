"""The report's figures that do not need the diagnosis, drawn on the second core while the diagnosis runs.

``afmid report`` spends its time in two independent parts: the diagnosis of the last run (refits, in this process)
and drawing the figures. Only the effects-tried figure (and, with several runs, the loop's per-run evidence) needs
the diagnosis's answer; the others are drawn from the run file, its residual, its energy check and the model's
re-simulation. :func:`figures_aside` forks a child process that draws those into the report's temporary folder
while the parent diagnoses, then hands back their file names. The files are the ones a serial report writes (same
code, same data: the child is a copy of the parent at the fork).

Serial instead (the same figures drawn in this process when they are asked for), decided by
:func:`serial_reason`: ``AFMID_REPORT_JOBS=1`` (:data:`REPORT_JOBS_ENV`; 2, the default, allows the child); not on
Linux (macOS's system libraries are not fork-safe, Python starts processes there with spawn; Windows has no fork);
fewer than two cores for this process (``taskset``, a batch scheduler's CPU set); a daemonic process (a process
pool's worker, which may not have children) or a dask worker (its cores belong to its cluster).

Interrupts and failures: the child restores the default SIGINT/SIGTERM actions (Ctrl-C reaches the whole process
group and ends it quietly; the parent's own handling, :mod:`afmid.interrupts`, raises in the parent); whatever ends
the parent's block (an interrupt, an error) kills and reaps the child before the block is left, so the report's
temporary folder is removed with nothing writing into it. A child whose parent is gone (``kill -9``) stops at its
next figure. A child that fails (an error in a figure, a full disk, killed) is reported in the log and its figures
are drawn again here, serially: an error then surfaces in this process as it would in a serial report.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
import sys
import traceback
from collections.abc import Callable, Iterator

from afmid.errors import ConfigError

log = logging.getLogger(__name__)

#: Processes ``afmid report`` may use for its figures: 1 (serial) or 2 (the default: a child beside the diagnosis).
REPORT_JOBS_ENV = "AFMID_REPORT_JOBS"
DEFAULT_REPORT_JOBS = 2

#: The signals the child takes with their default actions (and the parent holds while it forks).
_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def report_jobs(environ=None) -> int:
    """The processes allowed by :data:`REPORT_JOBS_ENV` (unset: :data:`DEFAULT_REPORT_JOBS`); ConfigError for
    anything but 1 or 2."""
    text = (os.environ if environ is None else environ).get(REPORT_JOBS_ENV, "").strip()
    if not text:
        return DEFAULT_REPORT_JOBS
    if text not in ("1", "2"):
        raise ConfigError(f"must be 1 (figures drawn serially) or 2 (drawn beside the diagnosis), got {text!r}",
                          key=REPORT_JOBS_ENV)
    return int(text)


def serial_reason(jobs: int) -> str | None:
    """Why the figures are drawn in this process, or None when a forked child may draw them."""
    if jobs < 2:
        return f"{REPORT_JOBS_ENV}=1"
    if not sys.platform.startswith("linux") or "fork" not in multiprocessing.get_all_start_methods():
        return "processes are not forked on this platform"
    if len(os.sched_getaffinity(0)) < 2:
        return "one core for this process"
    if multiprocessing.current_process().daemon:
        return "a daemonic worker process"
    if _inside_dask_worker():
        return "a dask worker"
    return None


def _inside_dask_worker() -> bool:
    distributed = sys.modules.get("distributed")  # only if already imported: a dask worker has imported it
    if distributed is None:
        return False
    try:
        distributed.get_worker()
    except ValueError:  # "No worker found": not in a worker
        return False
    return True


class Figures:
    """The figures drawn aside: :meth:`get` gives ``{name: PNG file name}``, from the child or drawn here."""

    def __init__(self, draws: dict[str, Callable[[], str]], fork: bool):
        self._draws = draws
        self._process = None
        self._receiver = None
        self._got: dict[str, str] | None = None
        if fork:
            self._start()

    def _start(self) -> None:
        context = multiprocessing.get_context("fork")
        receiver, sender = context.Pipe(duplex=False)
        process = context.Process(target=_child, args=(self._draws, sender, os.getpid()), name="afmid-figures",
                                  daemon=True)
        # Held across the fork, so that a Ctrl-C cannot reach the child before it has its default handlers.
        held = signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
        try:
            process.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)
            sender.close()  # the child's end: the parent's copy closed, a dead child reads as end of file
        self._process, self._receiver = process, receiver

    def get(self) -> dict[str, str]:
        """The figures' PNG names by figure name (waits for the child; draws here what it did not give)."""
        if self._got is None:
            self._got = self._from_child() if self._process is not None else None
            if self._got is None:
                self._got = {name: draw() for name, draw in self._draws.items()}
        return self._got

    def _from_child(self) -> dict[str, str] | None:
        try:
            status, payload = self._receiver.recv()
        except EOFError:
            status, payload = "error", "ended without an answer"
        finally:
            self.close()
        if status == "ok":
            return payload
        # Debug only: the figures are drawn again here, and an error that is theirs is raised by that drawing (one
        # line from the command line), not told twice.
        log.debug("drawing the figures in a second process failed, drawing them here:\n%s", payload)
        return None

    def close(self) -> None:
        """Kill the child if it still runs, reap it, then close its pipe (idempotent): nothing writes into the
        report's folder after this."""
        process, self._process = self._process, None
        if process is not None:
            if process.is_alive():
                process.kill()
            process.join()
        if self._receiver is not None:
            self._receiver.close()
            self._receiver = None


def _child(draws: dict[str, Callable[[], str]], sender, parent: int) -> None:
    """The forked child: draw each figure, send ``("ok", {name: PNG})`` or ``("error", traceback text)``."""
    for signum in _STOP_SIGNALS:
        signal.signal(signum, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)
    try:
        got = {}
        for name, draw in draws.items():
            if os.getppid() != parent:  # the parent was killed outright: its report will never be used
                os._exit(1)
            got[name] = draw()
        sender.send(("ok", got))
    except BaseException:  # everything, told to the parent, which draws again and raises there
        sender.send(("error", traceback.format_exc()))
    finally:
        sender.close()


@contextlib.contextmanager
def figures_aside(draws: dict[str, Callable[[], str]], jobs: int | None = None) -> Iterator[Figures]:
    """Start drawing ``draws`` (figure name -> a function that draws it into the report's folder and returns the
    PNG's name) in a forked child when :func:`serial_reason` allows (``jobs``: default :func:`report_jobs`), and
    yield a :class:`Figures`; when the block ends, by any exception too, the child is stopped and reaped."""
    reason = serial_reason(report_jobs() if jobs is None else jobs)
    if reason is not None:
        log.debug("figures drawn serially: %s", reason)
    figures = Figures(draws, fork=reason is None)
    try:
        yield figures
    finally:
        figures.close()
