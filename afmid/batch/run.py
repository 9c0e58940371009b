"""Batch runs: many traces with one run config, or many run configs each on its own data; parallel, resumable.

::

    afmid batch CONFIG --inputs 'traces/*.csv' -j 4 -o DIR     # many traces, one config
    afmid batch CONFIG --manifest traces.yaml -j 4 -o DIR      # the same, per-file overrides
    afmid batch --configs 'configs/*.yaml' -j 4 -o DIR         # many configs, each with its own data
    afmid batch --manifest runs.yaml -j 4 -o DIR               # manifest rows naming their config

**One config, many traces.** Each trace is fitted exactly as
``afmid fit CONFIG --set data.path=TRACE`` would fit it (same config layering,
same :func:`afmid.fit.pipeline.run_fit`, same :func:`afmid.runfile.write_run`).

**Many configs** (``--configs``, or manifest rows with a ``config`` key). Each
config carries its own cantilever, drive, sample and model, and is run on its
own data:

- a config with ``data.path`` (after ``--set``): that file is fitted, exactly as
  ``afmid fit CONFIG`` would fit it;
- a config without ``data.path`` but with a ``simulate:`` section: the trace is
  simulated first, into ``DIR/NAME.trace.h5`` (written to a temporary name and
  renamed into place, exactly what ``afmid simulate CONFIG -o DIR/NAME.trace.h5``
  writes), then fitted as ``afmid fit CONFIG --set data.path=DIR/NAME.trace.h5``;
- neither: the run fails with that message (the batch goes on).

A manifest row with both ``config`` and ``path`` fits that trace with that
config (``data.path`` replaced), e.g. traces taken with different cantilevers.

Every item runs in an execution engine (:mod:`afmid.batch.engine`): by default
a pool of ``spawn``-ed worker processes on this machine
(:class:`afmid.batch.engine.LocalPoolEngine`), another one through
``run_batch(engine=...)``. Each worker imports afmid once and loads the numba
kernels from numba's on-disk cache; BLAS and OpenMP are limited to one thread
per worker (set before NumPy is imported), so N workers use N cores and the
float summation order does not depend on the pool.

The parts: :mod:`afmid.batch.plan` (the items, their names and configs, the
up-to-date checks), :mod:`afmid.batch.engine` (where they run),
:mod:`afmid.batch.task` (what a worker does with one item) and
:mod:`afmid.batch.summary` (the summary rows and files); this module puts them
together, holds the output folder's lock and handles interruptions. Their
public names are importable from here as well.

Outputs in DIR:

- ``NAME.run.h5``: one run file per item, NAME from the input's stem (an
  afmid ``.trace`` suffix dropped), or from the config's stem for a config run
  on its own data (``configs/dmt.yaml`` -> ``dmt``); stems that collide get
  their parent folders prefixed (``a_trace``, ``b_trace``), identical paths
  listed twice a ``-2``, ``-3`` suffix. A manifest may name an entry explicitly.
- ``NAME.trace.h5``: the simulated trace of a config run on simulated data.
- ``summary.csv`` and ``summary.h5``: one row per item in input order with
  the status (``ok``, ``failed``, ``skipped`` = up to date from an earlier
  run, ``model-limited`` = a run file whose model fails the data: cv error
  above its noise-floor limit, ``suspect`` = a run file whose read-outs are
  not all plausible), the error message of a failure or the reasons of a
  suspect or model-limited item, the config,
  the input, the effects, the error metric, the separation, every physical parameter with its error
  and 95 % interval (the union over all rows: empty / NaN where a run has no
  such quantity), and the time spent per stage. SI units at the end of the
  CSV headers (``E_star_Pa``, as ``afmid export`` names its columns) and as
  ``units`` attributes in the h5. Layout in
  docs/file-formats.md.

Resuming: every run file written by a batch carries the attribute
``batch_key`` = SHA-256 of (afmid version, the input file's SHA-256, the
merged config with ``data.path`` blanked). A re-run skips an item whose run
file holds the key it would get now, and refits it if the input, the config,
a per-file override or afmid's version changed. A simulated trace is reused
when its provenance (the ``config`` and ``afmid_version`` attributes every
afmid file carries) equals what ``afmid simulate`` would write now, and
simulated again otherwise; its bytes are then the run's input, so a new trace
means a new fit. ``--force`` simulates and fits everything again. Failed items
are always retried.

Safety: a batch holds an exclusive lock on ``DIR/.afmid-batch.lock`` for its
whole life (:mod:`afmid.batch.folder_lock`), so a second batch on the same folder
fails at once, naming the first, instead of mixing its results in; a batch
that would write a file that is one of its inputs (the manifest, a config, a
trace) is refused before it starts. Workers write into
``DIR/.afmid-tmp-batch-PID/`` and rename each trace and run file into place
when it is complete; the summary is rewritten atomically after completed items
(at most every ``summary_interval`` seconds)
and at the end, so an interrupted batch (Ctrl-C, SIGTERM) leaves only whole
files and a valid summary of what finished; running it again resumes (a trace
simulated before the interruption is not simulated again). An item that fails
(bad file, bad config, bad override, a simulation or fit error) is logged and
listed with its error and does not stop the batch; a worker that dies (killed,
out of memory) is replaced, and the items it may have been running are retried
one at a time to find the culprit, which is then reported as failed. SIGTERM
to the batch exits with 143 instead of Ctrl-C's 130; a batch killed outright
(``kill -9``) cannot stop its workers, so each worker stops itself when its
parent is gone (:mod:`afmid.batch.orphans`). An item whose output does not fit on the
disk fails with "no space left on device".

This module imports nothing heavy at import time: a worker must be able to
set its thread limits before NumPy loads.
"""


from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from afmid.batch.engine import Engine, LocalPoolEngine, Outcome, default_jobs
from afmid.batch.plan import (
    RUN_SUFFIX,
    TRACE_SUFFIX,
    Entry,
    Item,
    assign_names,
    batch_key,
    expand_configs,
    expand_inputs,
    plan,
    read_manifest,
    refuse_outputs_on_inputs,
    run_key,
    trace_is_current,
)
from afmid.batch.summary import (
    FIXED_COLUMNS,
    QUANTITY_FIELDS,
    STATUSES,
    SUMMARY_CSV,
    SUMMARY_FORMAT,
    SUMMARY_H5,
    TIME_COLUMNS,
    Row,
    read_run_row,
    run_file_row,
    write_summary,
)
from afmid.batch.task import fit_task
from afmid.errors import ConfigError, EngineError, InputError, OutputError

__all__ = [
    "FIXED_COLUMNS", "QUANTITY_FIELDS", "RUN_SUFFIX", "STATUSES", "SUMMARY_CSV", "SUMMARY_FORMAT", "SUMMARY_H5",
    "TIME_COLUMNS", "TMP_PREFIX", "TRACE_SUFFIX", "BatchInterrupted", "BatchResult", "Engine", "Entry", "Item",
    "LocalPoolEngine", "Outcome", "Row", "assign_names", "batch_key", "default_jobs", "expand_configs",
    "expand_inputs", "fit_task", "plan", "read_manifest", "read_run_row", "refuse_outputs_on_inputs",
    "run_batch", "run_file_row", "run_key", "trace_is_current", "write_summary",
]

log = logging.getLogger(__name__)

TMP_PREFIX = ".afmid-tmp-batch-"


@dataclass
class BatchResult:
    rows: list[Row]  # finished items (all of them unless interrupted), input order
    output_dir: Path
    seconds: float
    total: int  # items in the batch
    interrupted: bool = False
    unit: str = "traces"  # what the items are called in messages: traces (one config) or runs (own configs)

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.rows)

    def line(self) -> str:
        parts = [f"{self.count(s)} {s}" for s in STATUSES if self.count(s)]
        done = f"{len(self.rows)} of {self.total} {self.unit}" if self.interrupted else f"{self.total} {self.unit}"
        done += f" ({', '.join(parts)})" if parts else ""
        return f"{done} in {self.seconds:.1f} s; summary in {self.output_dir / SUMMARY_CSV}"


def run_batch(
    config: str | Path | None,
    output_dir: str | Path,
    inputs: list[str] | tuple[str, ...] = (),
    manifest: str | Path | None = None,
    jobs: int | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    force: bool = False,
    progress: bool = False,
    summary_interval: float = 2.0,
    configs: list[str] | tuple[str, ...] = (),
    worker: Callable[[dict], dict] = fit_task,
    engine: Engine | None = None,
) -> BatchResult:
    """Fit every input with ``config``, or run every config in ``configs`` (glob patterns) on its own data (its
    ``data.path``, or a trace it simulates into ``output_dir`` first), in ``jobs`` worker processes; see the
    module docstring. ``overrides`` (``key.path=value``) apply to every config.

    ``worker`` runs one item in a worker process (a module-level function, pickled to spawned workers): one
    task dict in, one result dict out, as :func:`fit_task`, which it may wrap (e.g. to inject a fault).

    ``engine`` runs the items (:class:`afmid.batch.engine.Engine`); None: a :class:`LocalPoolEngine` of ``jobs``
    worker processes (``jobs`` is not used when an engine is given)."""
    start = time.perf_counter()
    config_path = None if config is None else Path(config)
    output_dir = Path(output_dir)
    if configs:
        if config_path is not None or inputs or manifest is not None:
            raise ConfigError("runs each config on its own data: give it without CONFIG, --inputs or --manifest",
                              key="--configs")
    elif config_path is None:
        if inputs:
            raise ConfigError("needs a CONFIG to fit the traces with", key="--inputs")
        if manifest is None:
            raise ConfigError("give a CONFIG with --inputs or --manifest, or run configs on their own data with "
                              "--configs 'configs/*.yaml'")
    elif bool(inputs) == (manifest is not None):
        raise ConfigError("give the traces either with --inputs or with --manifest", key="--inputs")
    if output_dir.exists() and not output_dir.is_dir():
        raise InputError("the output exists and is not a folder", file=output_dir, key="--output")
    if configs:
        entries = expand_configs(list(configs))
    elif manifest is not None:
        entries = read_manifest(manifest)
        if config_path is None:
            orphans = [i for i, e in enumerate(entries) if e.config is None]
            if orphans:
                raise ConfigError(f"entry [{orphans[0]}] names no config and no CONFIG was given (add a 'config' to "
                                  f"every entry, or give the CONFIG to fit them with)", file=Path(manifest))
    else:
        entries = expand_inputs(list(inputs), output_dir)
    unit = "runs" if any(e.config is not None for e in entries) else "traces"
    items, batch_text = plan(config_path, entries, output_dir, list(overrides))
    refuse_outputs_on_inputs(items, output_dir, config_path, None if manifest is None else Path(manifest))
    try:
        output_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder: {exc.strerror or exc}", file=output_dir,
                         key="--output") from None
    from afmid.batch.folder_lock import folder_lock

    with folder_lock(output_dir, key="--output"):  # one batch per folder: a second one would mix its results in
        return _run_in_folder(items, output_dir, batch_text, unit, engine or LocalPoolEngine(jobs), force, progress,
                              summary_interval, start, worker)


def _run_in_folder(items: list[Item], output_dir: Path, batch_text: str, unit: str, engine: Engine, force: bool,
                   progress: bool, summary_interval: float, start: float,
                   worker: Callable[[dict], dict] = fit_task) -> BatchResult:
    """The part of :func:`run_batch` that writes in ``output_dir``, under its lock."""
    _remove_stale_tmp(output_dir)
    rows: dict[int, Row] = {}
    todo: list[Item] = []

    for item in items:
        if item.error is not None:
            rows[item.index] = Row(item, "failed", item.error)
            log.warning("%s: failed: %s", item.name, item.error)
            continue
        if item.simulate is not None:  # a trace simulated before (and still what the config gives) is reused
            item.need_simulate = force or not trace_is_current(item.input, item.sim_text)
        if not force and not item.need_simulate and item.output.is_file():
            from afmid.io.trace import sha256_file

            existing = run_key(item.output)
            if existing is not None and existing == batch_key(sha256_file(item.input), item.config_text):
                try:
                    got = read_run_row(item.output)
                    rows[item.index] = run_file_row(item, got, "skipped")
                    continue
                except (OSError, KeyError):
                    pass  # unreadable: fit again
        todo.append(item)
    n_sim = sum(item.need_simulate for item in todo)
    log.info("batch: %d %s: %d to fit%s in %d worker processes, %d up to date, %d failed before fitting",
             len(items), unit, len(todo), f" ({n_sim} simulated first)" if n_sim else "",
             engine.workers_for(len(todo)), sum(r.status == "skipped" for r in rows.values()),
             sum(r.status == "failed" for r in rows.values()))

    state = {"last": time.monotonic(), "dirty": True, "cost": 0.0}

    def ordered() -> list[Row]:
        return [rows[i] for i in sorted(rows)]

    def flush(force_write: bool = False) -> None:
        # At most every summary_interval seconds, and spending at most ~5 % of the main process on summaries
        # (a summary of 1,000 rows takes ~65 ms to write).
        interval = max(summary_interval, 20.0 * state["cost"])
        if force_write or (state["dirty"] and time.monotonic() - state["last"] >= interval):
            start = time.monotonic()
            try:
                with _interrupts_held():
                    write_summary(output_dir, ordered(), batch_text)
            except OutputError as exc:
                if force_write:
                    raise
                # A summary written on the way is a courtesy: a disk filled for a moment by a worker's run file
                # must not stop the batch. The final summary (force_write) must be written, or the batch fails.
                log.warning("the summary could not be updated now (%s); trying again later", exc)
            else:
                state["dirty"] = False
            state["last"] = time.monotonic()
            state["cost"] = state["last"] - start

    from afmid.progress import Progress

    import afmid.interrupts as interrupts

    interrupted: KeyboardInterrupt | None = None
    tmp_dir = output_dir / f"{TMP_PREFIX}{os.getpid()}"
    handling = contextlib.ExitStack()
    handling.enter_context(interrupts.handled())  # Ctrl-C and SIGTERM raise, and are never lost
    bar = None
    try:
        if todo:
            tmp_dir.mkdir(exist_ok=True)
            bar = Progress("batch", enabled=progress)
            bar.stage(f"fitting ({len(rows)} up to date)" if rows else "fitting", total=len(items), unit=unit)
            bar.advance(len(rows))
            by_index = {item.index: item for item in todo}

            def report(outcome: Outcome) -> None:
                item = by_index[outcome.key]
                if outcome.result is None and not outcome.crashed:  # stopped before it reported
                    _record_if_written(item, rows)
                    return
                if outcome.result is not None:
                    _record(item, outcome.result, rows)
                else:
                    rows[item.index] = Row(item, "failed", outcome.crashed)
                    log.warning("%s: %s", item.name, outcome.crashed)
                bar.advance(1)
                state["dirty"] = True

            engine.run(worker, [(item.index, _task(item, tmp_dir)) for item in todo], report, flush)
        flush(force_write=True)
    except EngineError:  # the dask cluster cannot go on: the finished items' run files stay, and their summary
        with _interrupts_held(reraise=False):
            write_summary(output_dir, ordered(), batch_text)
        raise
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (interrupts.Terminated)
        interrupted = exc
        interrupts.clear()  # handled here: the summary below must not be stopped by it again
        with _interrupts_held(reraise=False):  # a second Ctrl-C must not spoil the summary
            # The engine has stopped its workers: a run file renamed into place after the engine reported its task
            # in flight (a worker slower to stop than the engine waits), or whose outcome the interrupt cut short
            # while it was being recorded, is whole and current, and the summary lists it.
            for item in todo:
                if item.index not in rows:
                    _record_if_written(item, rows)
            write_summary(output_dir, ordered(), batch_text)
    finally:
        if bar is not None:
            bar.close()
        shutil.rmtree(tmp_dir, ignore_errors=True)
        handling.close()
    result = BatchResult(ordered(), output_dir, time.perf_counter() - start, len(items), interrupted is not None,
                         unit)
    if interrupted is not None:
        raise BatchInterrupted(result, terminated=isinstance(interrupted, interrupts.Terminated))
    return result


class BatchInterrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGTERM: ``terminated``) during a batch, after the workers were stopped and the summary of what
    finished was written."""

    def __init__(self, result: BatchResult, terminated: bool = False):
        super().__init__()
        self.result = result
        self.terminated = terminated


def _remove_stale_tmp(output_dir: Path) -> None:
    """Temporary folders of batches that were killed outright (their process is gone)."""
    for path in output_dir.glob(f"{TMP_PREFIX}*"):
        try:
            pid = int(path.name[len(TMP_PREFIX):])
            os.kill(pid, 0)
            continue  # that batch still runs
        except (ValueError, ProcessLookupError):
            shutil.rmtree(path, ignore_errors=True)
        except PermissionError:
            continue


def _task(item: Item, tmp_dir: Path) -> dict:
    """What a worker gets for ``item`` (picklable; temporary files go into ``tmp_dir``)."""
    return {"index": item.index, "name": item.name, "raw": item.raw, "config": str(item.config_path),
            "config_text": item.config_text, "output": str(item.output), "tmp_dir": str(tmp_dir),
            "simulate": item.simulate if item.need_simulate else None, "trace": str(item.input)}


def _record_if_written(item: Item, rows: dict) -> None:
    """After an interrupt: record an item whose worker did not report but whose run file was renamed into place
    (the summary must list every run file the batch wrote)."""
    from afmid.io.trace import sha256_file

    if item.output.is_file() and item.input is not None and item.input.is_file():
        try:
            if run_key(item.output) == batch_key(sha256_file(item.input), item.config_text):
                got = read_run_row(item.output)
                rows[item.index] = run_file_row(item, got, "ok")
        except (OSError, KeyError):
            pass


def _record(item: Item, out: dict, rows: dict) -> None:
    for level, message in out.get("logs", []):
        if level == logging.DEBUG and message.startswith("Traceback"):
            log.debug("%s: %s", item.name, message)
        else:
            log.log(level, "%s: %s", item.name, message)
    if out["status"] == "ok":
        rows[item.index] = run_file_row(item, out["row"], "ok", out.get("times", {}))
    else:
        rows[item.index] = Row(item, "failed", out["error"])
        log.warning("%s: failed: %s", item.name, out["error"])


@contextlib.contextmanager
def _interrupts_held(reraise: bool = True):
    """Hold Ctrl-C and SIGTERM while a summary is written, so that an interrupt never lands inside the write (a
    half-made temporary file); with ``reraise``, one that came meanwhile is raised as KeyboardInterrupt after."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = {s: signal.signal(s, lambda signum, frame: caught.append(signum))
                for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    if caught and reraise:
        from afmid.interrupts import Terminated

        raise Terminated() if signal.SIGTERM in caught else KeyboardInterrupt()
