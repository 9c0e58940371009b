"""One draw of ``afmid coverage``: simulate it, check and fit it as ``afmid fit`` would, compare with the truth.

:func:`run_draw` takes one task dict and returns one plain dict (picklable, JSON-able); it runs in this process
or in a worker of :class:`afmid.batch.engine.LocalPoolEngine`, and never raises for a draw that fails: the
failure is its result (status ``failed`` and why), counted and listed by the caller.
"""

from __future__ import annotations

import logging
import os
import time
import traceback
from pathlib import Path

from afmid.batch.engine import set_worker_busy, worker_stopping
from afmid.errors import AfmidError


def draw_task(index: int, seed: int, values: dict, simulated: dict, fitted: dict, source: Path | None,
              separation_given: bool) -> dict:
    """The task dict of one draw: its index, simulation seed, drawn values, the simulation's and the fit's config
    mappings (:func:`afmid.coverage.draws.apply_draw`) and the config file they came from (for messages)."""
    return {"index": index, "seed": seed, "values": values, "simulate": simulated, "fit": fitted,
            "source": None if source is None else str(source), "separation_given": separation_given}


def recorded_text(extra: dict) -> str:
    """What the simulated record of a draw holds, in words (``extra``: its truth's extra mapping): 'steady
    state', 'from rest', 'from the free oscillation', or 'unsettled orbit: ...' for a steady simulation that
    did not settle (:func:`afmid.simulate.driver.unsettled_orbit_text`)."""
    from afmid.simulate.driver import unsettled_orbit_text

    if extra.get("mode") == "transient":
        return "from rest" if extra.get("transient_start") == "rest" else "from the free oscillation"
    if extra.get("settled", True):
        return "steady state"
    return (f"unsettled orbit, recorded as it is after {extra['settle_periods']} periods (steady state not "
            f"reached): {unsettled_orbit_text(extra)}")


def run_draw(task: dict) -> dict:
    """Simulate, check (:func:`afmid.io.trace.check_trace`: a record from rest is fitted from its onset, as on
    loading a file), fit (:func:`afmid.fit.pipeline.run_fit`) and compare (:func:`afmid.coverage.compare.compare`)
    one draw. Returns {index, seed, values, status (ok / failed), error, stage, recorded (:func:`recorded_text`,
    once simulated), numbers, cv_error, cv_error_noise_floor, warnings, seconds}."""
    out = {"index": task["index"], "seed": task["seed"], "values": task["values"], "status": "failed", "error": "",
           "stage": "simulate", "numbers": {}, "warnings": [], "seconds": {}}
    if task.get("loop"):  # the effect hidden in the simulation, kept even if the draw fails
        out.update(hidden=task["hidden"], hidden_parameters=task["hidden_parameters"])
    source = None if task.get("source") is None else Path(task["source"])
    quiet = logging.getLogger("afmid")
    level = quiet.level
    set_worker_busy(True)
    try:
        from afmid.config import build_config
        from afmid.coverage.compare import compare
        from afmid.fit.pipeline import run_fit
        from afmid.io.trace import check_trace
        from afmid.physics.tips import tip_geometry
        from afmid.runfile import run_data
        from afmid.simulate.driver import simulate

        # A draw's findings and warnings are its results (kept in `warnings`), not lines for the terminal.
        quiet.setLevel(logging.ERROR)
        started = time.process_time()
        trace = simulate(build_config(task["simulate"], source=source))
        out["seconds"]["simulate"] = time.process_time() - started
        out["recorded"] = recorded_text(trace.truth.extra)
        out["stage"] = "fit"
        config = build_config(task["fit"], source=source)
        started = time.process_time()
        trace = check_trace(trace, config)
        result = run_fit(config, trace=trace)
        out["seconds"]["fit"] = time.process_time() - started
        out["stage"] = "compare"
        run = run_data(result, config, name=f"draw{task['index']}.h5")
        out["numbers"] = compare(run, trace, tip_geometry(config.cantilever), task["separation_given"])
        if task.get("loop"):  # the blind loop (afmid.coverage.loop): diagnose, add the top suggestion, refit
            from afmid.coverage.loop import run_loop

            out["stage"] = "diagnose"
            started = time.process_time()
            out["loop"] = run_loop(config, trace, run, task, source)
            out["seconds"]["loop"] = time.process_time() - started
        out.update(status="ok", stage="", cv_error=float(run.cv_error),
                   cv_error_noise_floor=float(run.cv_error_noise_floor),
                   warnings=list(run.warnings))  # the trace's findings are among them
    except Exception as exc:  # a failing draw is a result: counted and listed, never dropped
        if worker_stopping():  # stopped by the parent (afmid.batch.engine): no result at all
            os._exit(143)
        out["error"] = exc.format() if isinstance(exc, AfmidError) else f"{type(exc).__name__}: {exc}"
        if not isinstance(exc, AfmidError):
            out["traceback"] = traceback.format_exc()
    finally:
        quiet.setLevel(level)
        set_worker_busy(False)
    return out
