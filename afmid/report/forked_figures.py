"""The report's figures that do not need the diagnosis, drawn on the second core while the diagnosis runs.

``afmid report`` spends its time in two independent parts: the diagnosis of the last run (refits, in this process)
and drawing the figures. Only the effects-tried figure (and, with several runs, the loop's per-run evidence) needs
the diagnosis's answer; the others are drawn from the run file, its residual, its energy check and the model's
re-simulation. :func:`figures_aside` forks a child process that draws those into the report's temporary folder
while the parent diagnoses and hands back their file names; given the diagnosis's answer, the same child draws the
effects-tried figure (its matplotlib loaded by then: the parent never imports it). The files are the ones a serial
report writes (same code, same data: the child is a copy of the parent at the fork). ``afmid batch`` and ``afmid
map`` make no reports, so their workers never fork here.

Serial instead (the same figures drawn in this process when they are asked for), decided by
:func:`afmid.diagnosis.forked_work.serial_reason` (the diagnosis shares its independent searches with a child by the
same rule): ``AFMID_REPORT_JOBS=1`` (:data:`afmid.diagnosis.forked_work.REPORT_JOBS_ENV`; 2, the default, allows
the child); not on Linux (macOS's system libraries are not fork-safe, Python starts processes there with spawn;
Windows has no fork);
fewer than two cores for this process (``taskset``, a batch scheduler's CPU set); a daemonic process (a process
pool's worker, which may not have children) or a dask worker (its cores belong to its cluster).

Interrupts and failures: the child restores the default SIGINT/SIGTERM actions (Ctrl-C reaches the whole process
group and ends it quietly; the parent's own handling, :mod:`afmid.interrupts`, raises in the parent); whatever ends
the parent's block (an interrupt, an error) kills and reaps the child before the block is left, so the report's
temporary folder is removed with nothing writing into it. A child whose parent is gone (``kill -9``) stops at its
next figure. A child that fails (an error in a figure, a full disk, killed) is logged (debug) and its figures
are drawn again here, serially: an error then surfaces in this process as it would in a serial report.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import pickle
import signal
import traceback
from collections.abc import Callable, Iterator

# How many processes a report may use and when it stays serial: one setting for the figures and the diagnosis.
from afmid.diagnosis.forked_work import STOP_SIGNALS, report_jobs, serial_reason

log = logging.getLogger(__name__)

class Figures:
    """The figures drawn aside. :meth:`get` gives ``{name: PNG file name}`` of the figures drawn from the start;
    :meth:`finish` hands the diagnosis's answer to the figures that need it and gives theirs. From the child, or
    drawn here when there is no child or it failed."""

    def __init__(self, draws: dict[str, Callable[[], str]], later: dict[str, Callable[[object], str | None]],
                 fork: bool):
        self._draws, self._later = draws, later
        self._process = self._results = self._answers = None
        self._got: dict[str, str] | None = None
        if fork:
            self._start()

    def _start(self) -> None:
        context = multiprocessing.get_context("fork")
        results, child_results = context.Pipe(duplex=False)  # child -> parent: each stage's figures
        child_answers, answers = context.Pipe(duplex=False)  # parent -> child: the answer the later figures need
        process = context.Process(target=_child, name="afmid-figures", daemon=True,
                                  args=(self._draws, self._later, child_results, child_answers, (results, answers),
                                        os.getpid()))
        # Held across the fork, so that a Ctrl-C cannot reach the child before it has its default handlers.
        held = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
        try:
            process.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)
            # The child's ends closed here: a child that dies reads as end of file (and the parent's, in the child)
            child_results.close()
            child_answers.close()
        self._process, self._results, self._answers = process, results, answers

    def get(self) -> dict[str, str]:
        """The first figures' PNG names by figure name (waits for the child; draws them here if it did not)."""
        if self._got is None:
            self._got = self._from_child() if self._process is not None else None
            if self._got is None:
                self.close()
                self._got = {name: draw() for name, draw in self._draws.items()}
        return self._got

    def finish(self, answer) -> dict[str, str]:
        """The later figures drawn for ``answer`` (picklable; None from a figure that has nothing to draw is left
        out): what each draws (a PNG name) by figure name. Ends the child."""
        self.get()
        got = None
        if self._process is not None and self._later:
            try:
                self._answers.send(answer)  # pickled whole before a byte is written
            except (OSError, pickle.PicklingError, TypeError, AttributeError):  # the child gone, or not picklable
                pass
            else:
                got = self._from_child()
        self.close()
        if got is None:
            got = {name: draw(answer) for name, draw in self._later.items()}
        return {name: png for name, png in got.items() if png is not None}

    def _from_child(self) -> dict[str, str] | None:
        try:
            status, payload = self._results.recv()
        except EOFError:
            status, payload = "error", "ended without an answer"
        if status == "ok":
            return payload
        self.close()
        # Debug only: the figures are drawn again here, and an error that is theirs is raised by that drawing (one
        # line from the command line), not told twice.
        log.debug("drawing the figures in a second process failed, drawing them here:\n%s", payload)
        return None

    def close(self) -> None:
        """Kill the child if it still runs, reap it, then close the pipes (idempotent): nothing writes into the
        report's folder after this."""
        process, self._process = self._process, None
        if process is not None:
            if process.is_alive():
                process.kill()
            process.join()
        for end in (self._results, self._answers):
            if end is not None:
                end.close()
        self._results = self._answers = None


def _child(draws, later, results, answers, parent_ends, parent: int) -> None:
    """The forked child: draw each of ``draws``, send ``("ok", {name: PNG})``; then wait for the answer and do the
    same with ``later``; an error is sent as ``("error", traceback text)`` and ends it."""
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    for end in parent_ends:  # so that the parent's death reads as end of file here
        end.close()
    try:
        results.send(("ok", _drawn(draws, (), parent)))
        if later:
            try:
                answer = answers.recv()
            except EOFError:  # the parent stopped waiting for them
                return
            results.send(("ok", _drawn(later, (answer,), parent)))
    except BaseException:  # everything, told to the parent, which draws again and raises there
        try:
            results.send(("error", traceback.format_exc()))
        except OSError:  # the parent is gone
            pass
    finally:
        results.close()
        answers.close()


def _drawn(draws: dict, args: tuple, parent: int) -> dict:
    got = {}
    for name, draw in draws.items():
        if os.getppid() != parent:  # the parent was killed outright: its report will never be used
            os._exit(1)
        got[name] = draw(*args)
    return got


@contextlib.contextmanager
def figures_aside(draws: dict[str, Callable[[], str]], later: dict[str, Callable[[object], str | None]] | None = None,
                  jobs: int | None = None) -> Iterator[Figures]:
    """Start drawing ``draws`` (figure name -> a function that draws it into the report's folder and returns the
    PNG's name) in a forked child when :func:`serial_reason` allows (``jobs``: default :func:`report_jobs`), and
    yield a :class:`Figures`; ``later``: figures drawn from the answer given to :meth:`Figures.finish` (by the same
    child, whose matplotlib is loaded by then). When the block ends, by any exception too, the child is stopped
    and reaped."""
    reason = serial_reason(report_jobs() if jobs is None else jobs)
    if reason is not None:
        log.debug("figures drawn serially: %s", reason)
    figures = Figures(draws, later or {}, fork=reason is None)
    try:
        yield figures
    finally:
        figures.close()
