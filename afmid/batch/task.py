"""One batch item in a worker: simulate its trace if asked, fit it, write the run file (both atomically).

:func:`fit_task` is the default worker of :func:`afmid.batch.run.run_batch`; it runs under any
:class:`afmid.batch.engine.Engine` (one task dict in, one result dict out, never raises for a bad item).
"""

from __future__ import annotations

import logging
import os
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from afmid.batch.engine import WorkerTerminated, set_worker_busy, worker_log_level, worker_stopping
from afmid.batch.plan import RUN_SUFFIX, TRACE_SUFFIX, batch_key
from afmid.batch.summary import read_run_row
from afmid.errors import AfmidError



class _Capture(logging.Handler):
    def __init__(self):
        super().__init__()
        self.records: list[tuple[int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.records.append((record.levelno, record.getMessage()))
        except Exception:  # pragma: no cover - a malformed log call must not fail the fit
            pass


def fit_task(task: dict, pause: Callable[[], None] | None = None) -> dict:
    """Run one item in a worker: simulate its trace if asked (written atomically), load, run_fit, write the run
    file atomically. Never raises for a bad item.

    ``pause``: called once in mid-item, after a simulated trace was written under its temporary name and before
    it is renamed into place, else before the fit (a wrapping worker holds the item there, e.g. to test
    interruptions)."""
    capture = _Capture()
    capture.setLevel(worker_log_level())
    loggers = [logging.getLogger("afmid"), logging.getLogger("py.warnings")]
    for lg in loggers:
        lg.addHandler(capture)
    tmp = Path(task["tmp_dir"]) / f"{task['name']}.{os.getpid()}{RUN_SUFFIX}"
    tmp_trace = Path(task["tmp_dir"]) / f"{task['name']}.{os.getpid()}{TRACE_SUFFIX}"
    out: dict[str, Any] = {"index": task["index"], "status": "failed", "error": "", "times": {}}
    stage = "fit"
    set_worker_busy(True)
    try:
        from afmid.config import build_config
        from afmid.fit.pipeline import run_fit
        from afmid.runfile import run_data, write_run
        from afmid.io.trace import load_trace

        c0 = time.process_time()
        times = {}
        if task.get("simulate") is not None:  # exactly `afmid simulate CONFIG -o TRACE`
            from afmid.config import dump_config
            from afmid.io.trace import write_trace_file
            from afmid.simulate.driver import simulate

            stage = "simulate"
            s0 = time.perf_counter()
            sim_config = build_config(task["simulate"], source=Path(task["config"]))
            simulated = simulate(sim_config)
            write_trace_file(tmp_trace, simulated, dump_config(sim_config), overwrite=True)
            del simulated
            if pause is not None:
                pause()
                pause = None
            os.replace(tmp_trace, task["trace"])
            times["simulate_time"] = time.perf_counter() - s0
            stage = "fit"
        if pause is not None:
            pause()
        t0 = time.perf_counter()
        config = build_config(task["raw"], source=Path(task["config"]))
        trace = load_trace(config)
        t1 = time.perf_counter()
        result = run_fit(config, trace=trace)
        t2 = time.perf_counter()
        key = batch_key(trace.sha256, task["config_text"])
        write_run(tmp, run_data(result, config), overwrite=True, root_attrs={"batch_key": key})
        os.replace(tmp, task["output"])
        t3 = time.perf_counter()
        out["row"] = read_run_row(Path(task["output"]))
        out["status"] = "ok"
        out["times"] = {**times, "load_time": t1 - t0, "fit_time": t2 - t1, "write_time": t3 - t2,
                        "cpu_time": time.process_time() - c0}
    except BaseException as exc:
        if isinstance(exc, WorkerTerminated) or worker_stopping() or not isinstance(exc, Exception):
            # Stopped by the parent (the signal may surface as another exception, e.g. from inside a numba
            # kernel): this is no result, remove the temporary files and go.
            tmp.unlink(missing_ok=True)
            tmp_trace.unlink(missing_ok=True)
            os._exit(143)
        what = "simulation failed: " if stage == "simulate" else ""
        if isinstance(exc, AfmidError):  # named by the files the user will look for, not the temporary ones
            out["error"] = what + exc.format().replace(str(tmp), task["output"]).replace(str(tmp_trace), task["trace"])
        else:  # a bug or an unexpected failure: report it, keep the batch going
            out["error"] = f"{what}{type(exc).__name__}: {exc}"
            capture.records.append((logging.DEBUG, traceback.format_exc()))
    finally:
        set_worker_busy(False)
        tmp.unlink(missing_ok=True)
        tmp_trace.unlink(missing_ok=True)
        for lg in loggers:
            lg.removeHandler(capture)
    out["logs"] = capture.records
    return out

