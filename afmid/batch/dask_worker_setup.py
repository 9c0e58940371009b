"""Preloaded in each worker process of the local cluster that :class:`afmid.batch.engine_dask.DaskEngine` starts.

A terminal's Ctrl-C reaches the whole process group; the workers leave it to the ``afmid map`` process, which
cancels the tasks, keeps the finished chunks and stops the cluster (a worker interrupted on its own would print a
traceback and could lose a finished result on the way back).
"""

from __future__ import annotations

import signal


def dask_setup(worker) -> None:  # the name dask's preload mechanism calls, in the worker's main thread
    signal.signal(signal.SIGINT, signal.SIG_IGN)
