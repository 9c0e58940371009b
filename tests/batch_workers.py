"""Batch worker entry points that inject faults, for tests/test_batch.py (passed as ``run_batch(worker=...)``).

A module of its own, importable by name in the spawned workers (pytest puts tests/ on the path, and spawned
processes inherit it), so the fault lives in the tests, not in afmid.batch.
"""

from __future__ import annotations

import os
import signal

from afmid.batch import fit_task

#: The item whose worker dies.
DYING_ITEM = "n02"


def fit_task_dying_on_one_item(task: dict) -> dict:
    """:func:`afmid.batch.fit_task`, except that the worker running item ``DYING_ITEM`` SIGKILLs itself first."""
    if task["name"] == DYING_ITEM:
        os.kill(os.getpid(), signal.SIGKILL)
    return fit_task(task)
