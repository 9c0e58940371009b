"""Ctrl-C as a terminal delivers it, for the tests that send SIGINT.

A suite started in the background by a non-interactive shell (``cmd &`` in a CI script or a tool's job runner)
inherits SIGINT ignored, and Python then leaves it ignored: a test that sends SIGINT would see nothing happen
(session 10's Haswell run failed four signal tests that way). These restore what an interactive terminal gives.
"""

from __future__ import annotations

import signal
from contextlib import contextmanager


def terminal_signals() -> None:
    """``preexec_fn`` of a child process: SIGINT at its default, so the child's Python installs its handler."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@contextmanager
def ctrl_c_raises():
    """In this process: SIGINT raises KeyboardInterrupt (Python's own handler) for the block, then as before."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)
