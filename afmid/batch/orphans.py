"""Worker processes that stop when their parent is gone.

A batch's workers wait for items from their parent. If the parent is killed outright (``kill -9``, the
out-of-memory killer, a job scheduler's hard limit) it cannot stop them, and they used to live on for
minutes, holding memory and cores. :func:`exit_with_parent` makes a worker send itself SIGTERM (its
handler removes its temporary file and exits) as soon as the parent dies: on Linux through
``prctl(PR_SET_PDEATHSIG)``, elsewhere (or if that call fails) by a daemon thread that checks the parent
process id every :data:`POLL_SECONDS`.

Linux sends the signal when the *thread* that started the process ends. The batch starts its workers from
its main thread (``ProcessPoolExecutor.submit``, which spawns workers as needed; without
``max_tasks_per_child`` the pool's manager thread never spawns one), so that is when the batch process ends.
"""

from __future__ import annotations

import os
import signal
import sys
import threading

#: How often the portable fallback looks at the parent process id, s.
POLL_SECONDS = 0.5
_PR_SET_PDEATHSIG = 1  # from <linux/prctl.h>


def _set_parent_death_signal(signum: int) -> bool:
    """Ask Linux to send ``signum`` to this process when its parent dies; False where that is not possible."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(_PR_SET_PDEATHSIG, signum, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch_parent(parent_pid: int) -> None:
    import time

    while os.getppid() == parent_pid:
        time.sleep(POLL_SECONDS)
    os.kill(os.getpid(), signal.SIGTERM)


def exit_with_parent(parent_pid: int, use_prctl: bool = True) -> str:
    """Make this process receive SIGTERM when process ``parent_pid`` (its parent) dies; returns the mechanism
    used ("prctl" or "thread"; ``use_prctl=False`` chooses the thread, as on systems without prctl)."""
    how = "prctl" if use_prctl and _set_parent_death_signal(signal.SIGTERM) else "thread"
    if how == "thread":
        threading.Thread(target=_watch_parent, args=(parent_pid,), name="afmid-parent-watch", daemon=True).start()
    if os.getppid() != parent_pid:  # the parent died before the request above took effect
        os.kill(os.getpid(), signal.SIGTERM)
    return how
