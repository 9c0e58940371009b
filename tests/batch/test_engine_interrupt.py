"""A Ctrl-C stops afmid's local dask cluster under running tasks without dask's shutdown noise on the terminal.

Measured: under OPENBLAS_CORETYPE=Haswell an interrupted ``afmid map`` once printed distributed's logged traceback
of a worker heartbeat whose connection the scheduler's close had cut (distributed/comm/tcp.py). The workers share
the terminal (here pytest's captured file descriptor 2): tests/support/batch_workers.noisy_until_stopped logs an
error while it runs, which must be shown, and what dask logs at a heartbeat cut by the close, which must not.
"""

from __future__ import annotations

import pytest

from batch_workers import RUNNING_ERROR, TEARDOWN_NOISE, noisy_until_stopped


def test_an_interrupted_local_cluster_stops_without_dask_tracebacks(tmp_path, capfd):
    from afmid.batch.engine_dask import DaskEngine

    started = tmp_path / "started"
    outcomes = []

    def tick() -> None:  # the Ctrl-C, once the task runs
        if started.exists():
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        DaskEngine(jobs=1).run(noisy_until_stopped, [(0, {"started": str(started)})], outcomes.append, tick)
    err = capfd.readouterr().err
    assert [o.key for o in outcomes] == [0] and outcomes[0].result is None  # reported unfinished
    assert RUNNING_ERROR in err  # a running worker's errors are not hidden
    assert TEARDOWN_NOISE not in err and "Traceback" not in err, err
