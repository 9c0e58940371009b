"""What a task sets up in an engine worker (afmid.batch.engine_dask.run_in_worker, afmid.batch.allocator), and the
local cluster's worker settings.

afmid.batch.allocator: dask's MALLOC_TRIM_THRESHOLD_ in a worker's environment must not make every freed
array go back to the OS (each reuse then page-faults afresh: a map ran 1.6x slower on the local cluster).

Counted, not timed: minor page faults of a loop that allocates and frees a 1 MiB array 200 times. With glibc's
dynamic thresholds the block is reused (a few hundred faults in all); with the variable set it is mapped anew
each time (256 faults per MiB per pass: >= 51,200); with the variable set and the thresholds fixed, reused.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator (Linux)")

LOOP = """
import resource, sys
import numpy as np
from afmid.batch.allocator import keep_freed_memory_for_reuse
applied = keep_freed_memory_for_reuse() if sys.argv[1] == "restore" else None
for _ in range(3):  # settle
    np.ones(1 << 17).sum()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(200):
    np.ones(1 << 17).sum()  # 1 MiB, freed at once
print(applied, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""
PASSES, PAGES_PER_PASS = 200, 256  # 1 MiB in 4 KiB pages


def faults(mode: str, trim_variable: bool) -> tuple[str, int]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    if trim_variable:
        env["MALLOC_TRIM_THRESHOLD_"] = "65536"  # what dask's nanny sets (distributed.nanny.pre-spawn-environ)
    out = subprocess.run([sys.executable, "-c", LOOP, mode], env=env, capture_output=True, text=True, check=True)
    applied, count = out.stdout.split()
    return applied, int(count)


def test_restored_thresholds_reuse_freed_arrays():
    applied, with_variable = faults("plain", trim_variable=True)
    assert with_variable >= 0.9 * PASSES * PAGES_PER_PASS  # the premise: mapped afresh each pass
    applied, restored = faults("restore", trim_variable=True)
    assert applied == "True"
    assert restored < 0.05 * PASSES * PAGES_PER_PASS


def test_fixed_thresholds_without_the_variable():
    applied, count = faults("restore", trim_variable=False)
    assert applied == "True"  # fixed in every worker: the dynamic rule still trims and faults between traces
    assert count < 0.05 * PASSES * PAGES_PER_PASS


def _threads_for_a_trace(task: dict) -> dict:
    from afmid.threads import trace_threads

    return {"threads": trace_threads()}


def test_a_dask_task_fits_a_trace_on_one_thread(monkeypatch):
    """On a cluster afmid did not start, the worker's environment lacks AFMID_TRACE_THREADS: the task sets it to 1
    (N single-threaded workers fill N cores), and keeps a value the worker's owner set."""
    from afmid.batch.engine_dask import run_in_worker
    from afmid.threads import TRACE_THREADS_ENV

    monkeypatch.delenv(TRACE_THREADS_ENV, raising=False)
    assert run_in_worker(_threads_for_a_trace, {}) == {"threads": 1}
    monkeypatch.setenv(TRACE_THREADS_ENV, "2")
    assert run_in_worker(_threads_for_a_trace, {}) == {"threads": 2}


def _profiler_setting(task: dict) -> dict:
    import dask

    return {"profile": dask.config.get("distributed.worker.profile.enabled")}


def test_the_local_clusters_workers_run_without_dasks_statistical_profiler():
    """dask's profiler takes the GIL every 10 ms in each worker to sample its stack (the 64x64 bench map: 91.6-94.1
    s with it, 86.6 s without): afmid's own local cluster switches it off, and leaves this process's config as it
    was."""
    import dask

    from afmid.batch.engine_dask import DaskEngine

    before = dask.config.get("distributed.worker.profile.enabled", default=None)
    seen = []
    DaskEngine(jobs=2).run(_profiler_setting, [(0, {}), (1, {})], seen.append, lambda: None)
    assert sorted(o.key for o in seen) == [0, 1]
    assert all(o.result == {"profile": False} for o in seen), seen
    assert dask.config.get("distributed.worker.profile.enabled", default=None) in (before, True)  # dask's default


def _worker_pid(task: dict) -> dict:
    return {"pid": os.getpid()}


def test_a_dask_engine_kept_running_shares_its_local_cluster_between_runs():
    """A map's group diagnosis runs on the workers that fitted its pixels: inside kept_running() the second run
    gets the first run's worker processes (no new cluster to start); outside it each run starts its own, and the
    block's end stops the kept one."""
    from afmid.batch.engine_dask import DaskEngine

    engine = DaskEngine(jobs=2)
    first, second = [], []
    with engine.kept_running():
        engine.run(_worker_pid, [(k, {}) for k in range(6)], first.append, lambda: None)
        engine.run(_worker_pid, [(0, {}), (1, {})], second.append, lambda: None)
        kept_pids = {o.result["pid"] for o in first}
        assert len(kept_pids) == 2 and {o.result["pid"] for o in second} <= kept_pids
        assert all(alive(pid) for pid in kept_pids)
    assert not any(alive(pid) for pid in kept_pids)  # the block's end stopped the kept cluster
    third = []
    engine.run(_worker_pid, [(0, {})], third.append, lambda: None)
    assert third[0].result["pid"] not in kept_pids  # a new cluster for a run outside the block
    assert not alive(third[0].result["pid"])  # and stopped after it


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True
