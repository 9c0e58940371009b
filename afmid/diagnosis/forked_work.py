"""Independent pieces of a diagnosis shared between this process and a forked child: the second core's share.

A diagnosis of a long record is mostly independent searches: each candidate effect's shape and separation search
(:mod:`afmid.diagnosis.candidate_refit`), the undeclared instrument's separation re-estimates
(:func:`afmid.diagnosis.instrument_signature.reprofiled`). :func:`in_order` computes ``[work(item) for item in
items]`` with a forked child taking items beside this process: each process claims the next item not yet claimed
(one counter shared by both), so a long item on one side does not hold the other. The child is a copy of this
process at the fork: ``work`` and ``items`` are not pickled, only each result is (sent back through a pipe), and a
result is the value the same call makes here: the work reads what the fork copied and writes only its own state
(caches of values that are the same whoever computes them). The callers keep every decision that depends on more
than one item in this process, in the items' order, so a report is the same with one process or two.

How many processes: :data:`REPORT_JOBS_ENV` (``AFMID_REPORT_JOBS``: 1 all here, 2 the default) and
:func:`serial_reason` (not on Linux, one core, a daemonic or dask worker: all here). While both processes work, each
gives a trace's chunks one thread (:func:`afmid.threads.cores_shared`; the same bits with any number,
:func:`afmid.threads.map_in_order`), so two processes fill the two cores without four threads contending; once one
has nothing left to do, the other's chunks take both cores again.

Refits made by the child are added to this process's count (:mod:`afmid.diagnosis.refit_count`). Interrupts and
failures: the child takes the default SIGINT/SIGTERM actions (Ctrl-C ends it with the process group; this process
raises); whatever leaves this process's loop (an interrupt, an error, a caller that stops iterating) kills and
reaps the child. A child that dies or cannot send a result (not picklable) is logged (debug) and the items it
claimed and did not return are computed here: an error that is theirs then surfaces here as it would serially. An
exception raised by ``work`` in the child is sent back and raised here at that item, as serially.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import signal
import sys
import traceback
from collections.abc import Callable, Iterable, Iterator

from afmid.errors import ConfigError
from afmid.threads import cores_shared

log = logging.getLogger(__name__)

#: Processes ``afmid report`` may use: 1 (everything in this process) or 2 (the default: a forked child draws the
#: figures beside the diagnosis, and one shares the diagnosis's independent searches).
REPORT_JOBS_ENV = "AFMID_REPORT_JOBS"
DEFAULT_REPORT_JOBS = 2

#: The places of this process and of the child in :attr:`_Shared.working`.
_PARENT, _CHILD = 0, 1

#: The signals a forked child takes with their default actions (and the parent holds while it forks).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def report_jobs(environ=None) -> int:
    """The processes allowed by :data:`REPORT_JOBS_ENV` (unset: :data:`DEFAULT_REPORT_JOBS`); ConfigError for
    anything but 1 or 2."""
    text = (os.environ if environ is None else environ).get(REPORT_JOBS_ENV, "").strip()
    if not text:
        return DEFAULT_REPORT_JOBS
    if text not in ("1", "2"):
        raise ConfigError(f"must be 1 (everything in one process) or 2 (a forked child beside it), got {text!r}",
                          key=REPORT_JOBS_ENV)
    return int(text)


def serial_reason(jobs: int) -> str | None:
    """Why the work stays in this process, or None when a forked child may share it."""
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


def in_order(work: Callable, items: Iterable, jobs: int | None = None) -> list:
    """``[work(item) for item in items]``, the items shared with a forked child when :func:`serial_reason` allows
    (``jobs``: default :func:`report_jobs`)."""
    return list(each_in_order(work, items, jobs))


def each_in_order(work: Callable, items: Iterable, jobs: int | None = None) -> Iterator:
    """:func:`in_order`'s results one by one in the items' order, each as soon as it and those before it are made
    (the caller's own work on a result overlaps the child's on later items)."""
    items = list(items)
    reason = serial_reason(report_jobs() if jobs is None else jobs) if len(items) > 1 else "one item"
    if reason is not None:
        log.debug("diagnosis work in one process: %s", reason)
        for item in items:
            yield work(item)
        return
    yield from _Shared(work, items).results()


class _Shared:
    """One forked child and this process taking ``items`` in turn from a shared counter."""

    def __init__(self, work: Callable, items: list):
        self.work, self.items = work, items
        context = multiprocessing.get_context("fork")
        self.next_item = context.Value("q", 0)  # the next unclaimed item's index (with its own lock)
        #: [this process, the child]: 1 while it works on an item or on what the caller does between results
        #: (read by the other to give its trace's chunks one thread or two: afmid.threads.cores_shared)
        self.working = context.RawArray("b", [1, 1])
        self.context = context

    def claim(self) -> int | None:
        with self.next_item.get_lock():
            index = self.next_item.value
            if index >= len(self.items):
                return None
            self.next_item.value = index + 1
            return index

    def results(self) -> Iterator:
        from afmid.diagnosis.refit_count import count_refits

        done: dict[int, tuple[bool, object] | None] = {}  # index -> (raised, value); None: to be made here
        receiver, sender = self.context.Pipe(duplex=False)
        working = self.working
        process = self.context.Process(target=self._child, args=(sender, receiver, os.getpid()),
                                       name="afmid-diagnosis", daemon=True)
        held = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)  # no Ctrl-C before the child's defaults
        try:
            process.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)
            sender.close()
        child_open = True
        try:
            cores_shared(lambda: bool(working[_CHILD]))  # the child sets its own view
            following = 0
            while following < len(self.items):
                if child_open:
                    child_open = self._receive(receiver, done, count_refits, block=False)
                if following in done and done[following] is None:  # the child could not send it
                    done[following] = self._made(following)
                if following in done:
                    raised, value = done.pop(following)
                    following += 1
                    if raised:
                        raise value
                    yield value
                    continue
                index = self.claim()
                if index is not None:
                    done[index] = self._made(index)
                elif child_open:  # everything is claimed: wait for the child's next result (its chunks on 2 cores)
                    working[_PARENT] = 0
                    try:
                        child_open = self._receive(receiver, done, count_refits, block=True)
                    finally:
                        working[_PARENT] = 1
                else:  # the child is gone: the items it claimed and did not return (all claimed, not done here)
                    if process.is_alive():  # it failed: nothing more is read from it
                        process.kill()
                    working[_CHILD] = 0
                    for lost in range(following, len(self.items)):
                        if lost not in done:
                            done[lost] = self._made(lost)
        finally:
            cores_shared(None)
            if process.is_alive():
                process.kill()
            process.join()
            receiver.close()

    def _made(self, index: int) -> tuple[bool, object]:
        try:
            return False, self.work(self.items[index])
        except Exception as exc:  # raised at its place in the order, as serially
            return True, exc

    @staticmethod
    def _receive(receiver, done: dict, count_refits, block: bool) -> bool:
        """Take the child's results (waiting for one when ``block``); False once the child sends nothing more."""
        while block or receiver.poll():
            block = False
            try:
                kind, index, payload = pickle.loads(receiver.recv_bytes())
            except (EOFError, OSError):
                return False
            if kind == "again":
                done[index] = None  # made here when its turn comes
            elif kind == "result":
                raised, value, refits = payload
                count_refits(refits)
                done[index] = (raised, value)
            elif kind == "failed":  # its traceback text; the items it claimed and did not return are made here
                log.debug("the diagnosis's second process failed, its items are made here:\n%s", payload)
                return False
            else:  # "finished"
                return False
        return True

    def _child(self, sender, receiver, parent: int) -> None:
        """The forked child: claim items until none is left, send each result (an exception ``work`` raised as
        its value) with the refits it made, then "finished"; anything else sent as "failed" with its traceback."""
        from afmid.diagnosis.refit_count import refits_made

        for signum in STOP_SIGNALS:
            signal.signal(signum, signal.SIG_DFL)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
        receiver.close()  # the parent's end
        working = self.working
        cores_shared(lambda: bool(working[_PARENT]))
        try:
            made = refits_made()
            while True:
                if os.getppid() != parent:  # the parent was killed outright: nobody waits for these
                    os._exit(1)
                index = self.claim()
                if index is None:
                    working[_CHILD] = 0
                    break
                try:
                    raised, value = False, self.work(self.items[index])
                except Exception as exc:
                    raised, value = True, exc
                refits, made = refits_made() - made, refits_made()
                try:
                    message = pickle.dumps(("result", index, (raised, value, refits)))
                    pickle.loads(message)  # an exception whose class cannot be made again from its arguments
                except Exception:  # not sent: made again there, where it raises as serially
                    message = pickle.dumps(("again", index, None))
                sender.send_bytes(message)
            sender.send_bytes(pickle.dumps(("finished", -1, None)))
        except BaseException:
            try:
                sender.send_bytes(pickle.dumps(("failed", -1, traceback.format_exc())))
            except (OSError, pickle.PicklingError):
                pass
        finally:
            sender.close()
