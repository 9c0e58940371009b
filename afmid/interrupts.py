"""Ctrl-C and SIGTERM as exceptions that are never lost, so every output stays all-or-nothing.

An interrupt must end a command with no output and no temporary file: the exception unwinds through
:func:`afmid.io.trace.atomic_path`, which removes its temporary file. Two things defeat that with Python's
default handling, and this module deals with both:

- Python raises the KeyboardInterrupt wherever the main thread happens to be. If that is a weakref
  callback or a ``__del__`` (h5py and NumPy objects are released all the time), Python prints
  "Exception ignored" and carries on: measured, 5 of 6 Ctrl-Cs in ``afmid fit``'s write phase were
  lost that way and the run exited 0 with its output. The handlers installed by :func:`handled`
  therefore *record* every signal before raising, and :func:`raise_if_pending` (called by
  ``atomic_path`` before it renames a file into place, and by the batch loop) raises it again.
- SIGTERM (sent by ``timeout``, SLURM, ``docker stop``) kills Python outright, leaving the temporary
  file. :func:`handled` turns it into :class:`Terminated`.

While the HDF5 library writes a file, an exception raised in Python code it calls back into (the file
object of :func:`afmid.io.trace.atomic_hdf5`) or an abandoned half-flushed file can crash it; :func:`deferred`
holds signals for such a section and delivers them right after it.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator

#: Exit codes of a command stopped by Ctrl-C (SIGINT) and by SIGTERM: 128 + the signal number, as a shell reports.
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised as an exception. A KeyboardInterrupt, so that everything that cleans up after Ctrl-C
    (temporary files, the batch's workers and summary) does the same for SIGTERM; the CLI exits with 143."""


_state: dict = {"depth": 0, "pending": None, "previous": {}, "hook": None}


def _exception_for(signum: int) -> KeyboardInterrupt:
    return Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _on_signal(signum, frame) -> None:
    # Remember it first: if this raise lands where Python cannot propagate it, raise_if_pending raises it again.
    if _state["pending"] is None:
        _state["pending"] = signum
    raise _exception_for(signum)


def _on_unraisable(unraisable) -> None:
    """A recorded interrupt that surfaced in a weakref callback or ``__del__``: already pending, do not print
    it (its "Exception ignored ... Traceback" would look like a crash); anything else as Python would."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt) and _state["pending"] is not None:
        return
    previous = _state["hook"] or sys.__unraisablehook__
    previous(unraisable)


def pending() -> int | None:
    """The signal number of an interrupt received and not yet cleared, or None."""
    return _state["pending"]


def raise_if_pending() -> None:
    """Raise the interrupt that was received (KeyboardInterrupt or :class:`Terminated`) if there is one.

    Called before an output is renamed into place: an interrupt that Python swallowed must still stop it.
    """
    signum = _state["pending"]
    if signum is not None:
        raise _exception_for(signum)


def clear() -> None:
    """Forget the received interrupt (it has been reported)."""
    _state["pending"] = None


@contextlib.contextmanager
def handled(then_ignore: bool = False) -> Iterator[None]:
    """SIGINT and SIGTERM raise (KeyboardInterrupt, :class:`Terminated`) and are remembered until the outermost
    block ends. Nests; does nothing outside the main thread. A SIGINT that was ignored when the process
    started (a job started in the background by a non-interactive shell) stays ignored.

    ``then_ignore``: when the block ends, ignore the two signals instead of restoring the handlers from before
    (for a process whose command is over and that only exits: a signal then must neither print a traceback
    nor turn a finished command's exit code into a kill)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    outermost = _state["depth"] == 0
    if outermost:
        _state["pending"] = None
        _state["hook"] = sys.unraisablehook
        sys.unraisablehook = _on_unraisable
    previous = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        current = signal.getsignal(signum)
        if current is signal.SIG_IGN or current is _on_signal:
            continue
        previous[signum] = signal.signal(signum, _on_signal)
    _state["depth"] += 1
    try:
        yield
    finally:
        _state["depth"] -= 1
        for signum, handler in previous.items():
            signal.signal(signum, signal.SIG_IGN if then_ignore else handler)
        if outermost:
            sys.unraisablehook = _state["hook"] or sys.__unraisablehook__
            _state["hook"] = None
            _state["pending"] = None


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Hold SIGINT and SIGTERM during the block; deliver them after it, to the handlers that were in place.

    For sections that must not be left midway by an exception (the HDF5 library writing a file). A signal
    received meanwhile goes to the previous handler when the block ends (or ends with an exception): a
    raising handler raises there, so the caller's cleanup runs; a default action (SIGTERM without a handler)
    is carried out by sending the signal again. Does nothing outside the main thread.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []

    def hold(signum, frame) -> None:
        if signum not in caught:
            caught.append(signum)

    previous = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        current = signal.getsignal(signum)
        if current is signal.SIG_IGN:
            continue
        previous[signum] = signal.signal(signum, hold)
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        for signum in caught:
            _deliver(signum, previous[signum])


def _deliver(signum: int, handler) -> None:
    import os

    if callable(handler):
        handler(signum, None)
    elif handler == signal.SIG_DFL:
        if signum == signal.SIGINT:
            raise KeyboardInterrupt()
        os.kill(os.getpid(), signum)
