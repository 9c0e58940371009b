"""Batch runs: many traces with one run config, or many run configs each on its own data; parallel, resumable.

::

    afmid batch CONFIG --inputs 'traces/*.csv' -j 4 -o DIR     # many traces, one config
    afmid batch CONFIG --manifest traces.yaml -j 4 -o DIR      # the same, per-file overrides
    afmid batch --configs 'configs/*.yaml' -j 4 -o DIR         # many configs, each with its own data
    afmid batch --manifest runs.yaml -j 4 -o DIR               # manifest rows naming their config

**One config, many traces.** Each trace is fitted exactly as
``afmid fit CONFIG --set data.path=TRACE`` would fit it (same config layering,
same :func:`afmid.fit.run_fit`, same :func:`afmid.fit.write_run`).

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

Every item runs in a pool of ``spawn``-ed worker processes
(:class:`concurrent.futures.ProcessPoolExecutor`). Each worker imports afmid
once and loads the numba kernels from numba's on-disk cache; BLAS and OpenMP
are limited to one thread per worker (set before NumPy is imported), so N
workers use N cores and the float summation order does not depend on the pool.

Outputs in DIR:

- ``NAME.run.h5``: one run file per item, NAME from the input's stem (an
  afmid ``.trace`` suffix dropped), or from the config's stem for a config run
  on its own data (``configs/dmt.yaml`` -> ``dmt``); stems that collide get
  their parent folders prefixed (``a_trace``, ``b_trace``), identical paths
  listed twice a ``-2``, ``-3`` suffix. A manifest may name an entry explicitly.
- ``NAME.trace.h5``: the simulated trace of a config run on simulated data.
- ``summary.csv`` and ``summary.h5``: one row per item in input order with
  the status (``ok``, ``failed``, ``skipped`` = up to date from an earlier
  run, ``suspect`` = a run file whose read-outs are not all plausible), the
  error message of a failure or the reasons of a suspect item, the config,
  the input, the effects, the error metric, the separation, every physical parameter with its error
  and 95 % interval (the union over all rows: empty / NaN where a run has no
  such quantity), and the time spent per stage. SI units in the CSV headers
  (``E_star [Pa]``) and as ``units`` attributes in the h5. Layout in
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
whole life (:mod:`afmid.folder_lock`), so a second batch on the same folder
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
parent is gone (:mod:`afmid.orphans`). An item whose output does not fit on the
disk fails with "no space left on device".

This module imports nothing heavy at import time: a worker must be able to
set its thread limits before NumPy loads.
"""

from __future__ import annotations

import contextlib
import csv
import glob
import hashlib
import io as _io
import logging
import math
import os
import re
import shutil
import signal
import sys
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import __version__
from .errors import AfmidError, ConfigError, InputError
from .threads import SINGLE_THREAD_ENV

log = logging.getLogger(__name__)

SUMMARY_CSV = "summary.csv"
SUMMARY_H5 = "summary.h5"
SUMMARY_FORMAT = "afmid-batch-summary"
RUN_SUFFIX = ".run.h5"
TRACE_SUFFIX = ".trace.h5"
TMP_PREFIX = ".afmid-tmp-batch-"
#: ok: fitted now; suspect: a run file exists (fitted now or up to date) but a read-out is implausible
#: (afmid.plausibility); failed: no run file; skipped: up to date from an earlier batch.
STATUSES = ("ok", "suspect", "failed", "skipped")
#: For tests only: a worker sleeps this many seconds before each fit, or, for a simulated trace, between writing
#: it to its temporary name and renaming it into place (makes interrupting deterministic).
_DELAY_ENV = "_AFMID_BATCH_TEST_DELAY"


# =========================================================================== planning
@dataclass
class Entry:
    """One input as listed: a trace file and/or a run config, per-file overrides, an optional explicit name.

    ``path`` None: the config's own data (its ``data.path``, or a trace simulated from its ``simulate:``
    section). ``config`` None: the batch's CONFIG.
    """

    path: Path | None
    overrides: list[tuple[list[str], Any]] = field(default_factory=list)
    name: str | None = None
    config: Path | None = None

    @property
    def source(self) -> Path:
        """The file the run is named after: the trace, else the config."""
        return self.path if self.path is not None else self.config  # type: ignore[return-value]

    def override_text(self) -> str:
        return "; ".join(f"{'.'.join(k)}={v!r}" for k, v in self.overrides)


@dataclass
class Item:
    """One run: the trace it fits (simulated first or not), where its run file goes, the config it uses."""

    index: int
    name: str
    entry: Entry
    output: Path
    config_path: Path | None = None  # the run config (the batch's CONFIG or the entry's own)
    raw: dict | None = None  # the merged config mapping (data.path set) or None if invalid
    config_text: str = ""  # the merged config with data.path blanked (part of the key)
    input: Path | None = None  # the trace file fitted (absolute)
    simulate: dict | None = None  # the config mapping to simulate the input from, if it is simulated
    sim_text: str = ""  # what `afmid simulate` stores as the trace's config (decides whether it is current)
    need_simulate: bool = False  # simulate (again) before fitting
    error: str | None = None  # a problem found while planning (bad config or override, missing file)
    crashes: int = 0  # times a worker died while this item was in flight


def _matching_files(patterns: list[str] | tuple[str, ...], key: str):
    """(path, resolved path) of the files matching the glob ``patterns`` (``**`` recursive), sorted per pattern,
    each file once; a pattern that matches no file is an error (of option ``key``)."""
    seen: set[Path] = set()
    for pattern in patterns:
        matches = sorted(glob.glob(os.path.expanduser(pattern), recursive=True))
        files = [Path(m) for m in matches if Path(m).is_file()]
        if not files:
            raise InputError(f"no files match {pattern!r}", key=key)
        for path in files:
            resolved = path.resolve()
            if resolved not in seen:
                seen.add(resolved)
                yield path, resolved


def expand_inputs(patterns: list[str] | tuple[str, ...], exclude_dir: Path | None = None) -> list[Entry]:
    """Files matching the glob ``patterns`` (``**`` recursive), sorted per pattern, without duplicates.

    Files inside ``exclude_dir`` that are batch outputs (``*.run.h5``, ``summary.*``) are left out.
    """
    excluded = exclude_dir.resolve() if exclude_dir is not None else None
    entries = [Entry(resolved) for path, resolved in _matching_files(patterns, "--inputs")
               if not (resolved.parent == excluded and _is_output_name(path.name))]
    if not entries:
        raise InputError("the input patterns match only batch outputs", key="--inputs")
    return entries


def expand_configs(patterns: list[str] | tuple[str, ...]) -> list[Entry]:
    """One entry per run config matching the glob ``patterns`` (``**`` recursive), sorted per pattern, no duplicates."""
    return [Entry(None, config=path) for path, _ in _matching_files(patterns, "--configs")]


def _is_output_name(name: str) -> bool:
    return name.endswith(RUN_SUFFIX) or name in (SUMMARY_CSV, SUMMARY_H5)


def read_manifest(path: str | Path) -> list[Entry]:
    """Entries of a manifest (paths relative to the manifest's folder).

    YAML: a list (or ``{traces: [...]}`` / ``{runs: [...]}``) of paths or mappings
    ``{path: ..., config: ..., name: ..., set: {key.path: value} | [key.path=value, ...]}``
    with ``path`` (a trace), ``config`` (a run config) or both: a row with only
    ``config`` runs that config on its own data (``data.path`` or simulated), a
    row with only ``path`` fits the trace with the batch's CONFIG.
    CSV: a header with a ``path`` and/or ``config`` column, optional ``name`` and
    ``set`` (``key.path=value`` separated by ``;``) columns, and any number of
    columns headed by a config key path (``sample.separation``) whose cells are
    values (empty: no override).
    """
    from .config import parse_override

    from .files import check_input_file

    path = check_input_file(path, what="manifest", key="--manifest")  # missing, a FIFO (would block), a folder
    base = path.parent
    entries: list[Entry] = []

    def parse_set(value, where: str) -> list[tuple[list[str], Any]]:
        if value is None or value == "":
            return []
        if isinstance(value, str):
            value = [v for v in (s.strip() for s in value.split(";")) if v]
        if isinstance(value, dict):
            return [([p for p in str(k).split(".") if p], v) for k, v in value.items()]
        if isinstance(value, list):
            out = []
            for text in value:
                try:
                    out.append(parse_override(str(text)))
                except ConfigError as exc:
                    raise ConfigError(exc.message.replace("--set", "set"), file=path, key=where) from None
            return out
        raise ConfigError(f"expected key.path=value items or a mapping, got {value!r}", file=path, key=where)

    if path.suffix.lower() == ".csv":
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
        if not rows:
            raise InputError("the manifest lists no traces", file=path, key="--manifest")
        header = list(rows[0])
        if "path" not in header and "config" not in header:
            raise InputError(f"a CSV manifest needs a 'path' or a 'config' column; found {header}", file=path,
                             key="--manifest")
        import yaml

        for i, row in enumerate(rows, start=2):
            trace = (row.get("path") or "").strip()
            config = (row.get("config") or "").strip()
            if not trace and not config:
                continue
            overrides = parse_set((row.get("set") or "").strip(), f"line {i}: set")
            for column in header:
                if column in ("path", "name", "set", "config") or "." not in column:
                    continue
                cell = (row.get(column) or "").strip()
                if cell:
                    overrides.append(([p for p in column.split(".") if p], yaml.safe_load(cell)))
            entries.append(Entry((base / trace).resolve() if trace else None, overrides,
                                 (row.get("name") or "").strip() or None, (base / config).resolve() if config else None))
    else:
        from .config import read_yaml

        try:
            data = read_yaml(path)
        except ConfigError as exc:
            if "top level" not in exc.message:
                raise
            import yaml

            data = yaml.safe_load(path.read_text(encoding="utf-8"))
        if isinstance(data, dict):
            keys = [k for k in ("traces", "runs") if k in data]
            if len(keys) != 1 or len(data) != 1:
                raise ConfigError("expected a list of traces or runs (or one 'traces:' or 'runs:' key)", file=path)
            data = data[keys[0]]
        if not isinstance(data, list) or not data:
            raise InputError("the manifest lists no traces", file=path, key="--manifest")
        for i, item in enumerate(data):
            where = f"[{i}]"
            if isinstance(item, str):
                entries.append(Entry((base / item).resolve()))
                continue
            if not isinstance(item, dict) or not (item.get("path") or item.get("config")):
                raise ConfigError("expected a path or a mapping with 'path' and/or 'config' (and optional 'name', "
                                  "'set')", file=path, key=where)
            unknown = set(item) - {"path", "config", "name", "set"}
            if unknown:
                raise ConfigError(f"unknown keys {sorted(unknown)}; allowed: path, config, name, set", file=path,
                                  key=where)
            entries.append(Entry((base / str(item["path"])).resolve() if item.get("path") else None,
                                 parse_set(item.get("set"), f"{where}.set"),
                                 str(item["name"]) if item.get("name") else None,
                                 (base / str(item["config"])).resolve() if item.get("config") else None))
    return entries


_NAME_RE = re.compile(r"[^A-Za-z0-9._+-]+")


def _stem(path: Path) -> str:
    stem = path.name[: -len(path.suffix)] if path.suffix else path.name
    if stem.endswith(".trace") and len(stem) > len(".trace"):  # afmid trace files: NAME.trace.h5
        stem = stem[: -len(".trace")]
    return _NAME_RE.sub("_", stem) or "trace"


def assign_names(entries: list[Entry]) -> list[str]:
    """Run names: the input stem; colliding stems get parent folders prefixed, then -2, -3 (input order)."""
    names = [_NAME_RE.sub("_", e.name) if e.name else None for e in entries]
    auto = [i for i, n in enumerate(names) if n is None]
    depth = {i: 0 for i in auto}

    def candidate(i: int) -> str:
        path = entries[i].source
        parts = [_NAME_RE.sub("_", p) for p in path.parent.parts[len(path.parent.parts) - depth[i]:]] if depth[i] else []
        return "_".join(parts + [_stem(path)])

    current = {i: candidate(i) for i in auto}
    for _ in range(64):
        taken: dict[str, list[int]] = {}
        for i in auto:
            taken.setdefault(current[i].lower(), []).append(i)
        fixed = {n.lower() for n in names if n is not None}
        clashes = [group for key, group in taken.items() if len(group) > 1 or key in fixed]
        progressed = False
        for group in clashes:
            if len(group) > 1 and len({entries[i].source for i in group}) == 1:
                continue  # the same file listed twice: numbered below
            for i in group:
                if depth[i] < len(entries[i].source.parent.parts):
                    depth[i] += 1
                    current[i] = candidate(i)
                    progressed = True
        if not clashes or not progressed:
            break
    for i in auto:
        names[i] = current[i]
    # Whatever still collides (the same file listed twice, explicit duplicates): -2, -3 in input order.
    used: dict[str, int] = {}
    out = []
    for name in names:
        key = name.lower()
        used[key] = used.get(key, 0) + 1
        out.append(name if used[key] == 1 else f"{name}-{used[key]}")
    return out


def plan(config_path: Path | None, entries: list[Entry], output_dir: Path,
         overrides: list[str]) -> tuple[list[Item], str]:
    """Items with their merged configs; returns (items, the batch CONFIG's merged text for provenance, or "").

    A bad batch CONFIG or ``--set`` stops the batch; a bad per-entry config or override fails only its item.
    """
    from .config import apply_overrides, build_config, dump_config, parse_override, read_yaml

    common = [parse_override(o) for o in overrides]
    # config file -> (YAML + --set or None, the error or None, whether the YAML itself has a simulate: section)
    bases: dict[Path, tuple[dict | None, str | None, bool]] = {}
    batch_text = ""
    if config_path is not None:
        yaml_raw = read_yaml(config_path)
        has_simulate = "simulate" in yaml_raw
        base_raw = apply_overrides(yaml_raw, _deepcopy(common))
        batch_text = dump_config(build_config(_deepcopy(base_raw), source=config_path))  # a bad config stops the batch
        bases[config_path] = (base_raw, None, has_simulate)

    def base(path: Path) -> tuple[dict | None, str | None, bool]:
        if path not in bases:
            try:
                yaml_raw = read_yaml(path)
                has_simulate = "simulate" in yaml_raw
                bases[path] = (apply_overrides(yaml_raw, _deepcopy(common)), None, has_simulate)
            except ConfigError as exc:
                bases[path] = (None, exc.format(), False)
        return bases[path]

    names = assign_names(entries)
    cache: dict[tuple, tuple[dict | None, str, str | None]] = {}
    items = []
    for index, (entry, name) in enumerate(zip(entries, names)):
        source = entry.config if entry.config is not None else config_path
        item = Item(index, name, entry, output_dir / f"{name}{RUN_SUFFIX}", config_path=source)
        items.append(item)
        if source is None:  # run_batch refuses this before planning
            item.error = ConfigError("no run config for this entry", key="config").format()
            continue
        base_raw, error, has_simulate = base(source)
        if base_raw is None:
            item.error = error
            continue
        entry_overrides = [(list(k), _deepcopy(v)) for k, v in entry.overrides]
        if entry.path is None:
            # Simulated if the config (or the entry's own overrides) has a simulate: section; a --set simulate.x
            # for the whole batch does not make a config without one simulate.
            simulated = has_simulate or any(k and k[0] == "simulate" for k, _ in entry_overrides)
            _plan_own_data(item, apply_overrides(_deepcopy(base_raw), entry_overrides), output_dir, simulated)
            continue
        signature = (source, entry.override_text())
        if signature not in cache:
            raw = apply_overrides(_deepcopy(base_raw), entry_overrides)
            raw.setdefault("data", {})
            if not isinstance(raw["data"], dict):
                raw["data"] = {}
            raw["data"]["path"] = None
            try:
                config = build_config(_deepcopy(raw), source=source)
                cache[signature] = (raw, dump_config(config), None)
            except ConfigError as exc:
                what = "per-file override: " if entry.overrides else ""
                cache[signature] = (None, "", f"{what}{exc.format()}")
        raw, text, error = cache[signature]
        if raw is not None:
            item.raw = _deepcopy(raw)
            item.raw["data"]["path"] = str(entry.path)
            item.config_text = text
            item.input = entry.path
        item.error = error
        if item.error is None and not entry.path.is_file():
            item.error = InputError("trace file not found", file=entry.path, key="data.path").format()
    return items, batch_text


def _plan_own_data(item: Item, raw: dict, output_dir: Path, simulated: bool) -> None:
    """A config run on its own data: its ``data.path``, or a trace simulated into DIR from its ``simulate:``."""
    from .config import build_config, dump_config

    source = item.config_path
    try:
        config = build_config(_deepcopy(raw), source=source)
    except ConfigError as exc:
        item.error = f"{'per-file override: ' if item.entry.overrides else ''}{exc.format()}"
        return
    data_path = config.data.path
    config.data.path = None
    text = dump_config(config)
    if data_path is not None:  # fitted as `afmid fit CONFIG` fits it (data.path as written, relative to CONFIG)
        item.raw = raw
        item.config_text = text
        item.input = config.resolve_path(data_path).resolve()
        if not item.input.is_file():
            item.error = InputError("trace file not found (remove data.path to simulate the trace from the "
                                    "simulate: section)" if simulated else "trace file not found",
                                    file=item.input, key="data.path").format()
        return
    if not simulated:
        item.error = ConfigError("no data.path to fit and no simulate: section to simulate a trace from",
                                 file=source, key="data.path").format()
        return
    # `afmid simulate CONFIG -o DIR/NAME.trace.h5`, then `afmid fit CONFIG --set data.path=<that file, absolute>`.
    trace = (output_dir / f"{item.name}{TRACE_SUFFIX}").resolve()
    item.simulate = raw
    item.sim_text = text  # data.path is absent here: the config `afmid simulate` would store
    item.config_text = text
    item.raw = _deepcopy(raw)
    if not isinstance(item.raw.get("data"), dict):
        item.raw["data"] = {}
    item.raw["data"]["path"] = str(trace)
    item.input = trace


def trace_is_current(path: Path, sim_text: str) -> bool:
    """Whether ``path`` is the afmid trace file ``afmid simulate`` would write now from config text ``sim_text``."""
    import h5py

    if not path.is_file():
        return False
    try:
        with h5py.File(path, "r") as h5:
            return (_text(h5.attrs.get("format", "")) == "afmid-trace"
                    and _text(h5.attrs.get("afmid_version", "")) == __version__
                    and _text(h5.attrs.get("config", "")) == sim_text
                    and "deflection" in h5)
    except (OSError, KeyError):
        return False


def _deepcopy(value):
    import copy

    return copy.deepcopy(value)


def batch_key(input_sha256: str, config_text: str) -> str:
    """What a run file must match to be up to date: afmid version, input bytes, merged config (path blanked)."""
    h = hashlib.sha256()
    for part in (f"afmid {__version__}", input_sha256, config_text):
        h.update(part.encode("utf-8"))
        h.update(b"\0")
    return h.hexdigest()


# =========================================================================== run files -> rows
def read_run_row(path: Path) -> dict:
    """The summary values of one run file: {'key', 'values', 'quantities'} (SI)."""
    import h5py
    import numpy as np

    from . import plausibility

    with h5py.File(path, "r") as h5:
        key = h5.attrs.get("batch_key")
        key = key.decode() if isinstance(key, bytes) else key
        diag = h5["diagnostics"]
        model = h5["model"]
        terms = [t.decode() if isinstance(t, bytes) else str(t) for t in model["terms"][...]]
        selected = model["selected"][...]
        sep = model["separation"]
        effects = [_text(e) for e in model["effects"][...]] if "effects" in model else []
        values = {
            "input_sha256": _text(h5.attrs.get("input_sha256", "")),
            "effects": ";".join(e for e in effects if e),
            "cv_error": float(diag["cv_error"][()]),
            "cv_error_noise_floor": float(diag["cv_error_noise_floor"][()]),
            "chi2_reduced": float(diag["chi2_reduced"][()]),
            "terms": ";".join(t for t, s in zip(terms, selected) if s),
            "separation": float(sep[()]),
            "separation_error": float(sep.attrs.get("error", np.nan)),
        }
        quantities = {}
        implausible = []
        for name, ds in model["parameters"].items():
            quantities[name] = {
                "value": float(ds[()]),
                "error": float(ds.attrs.get("error", np.nan)),
                "ci_low": float(ds.attrs.get("ci_low", np.nan)),
                "ci_high": float(ds.attrs.get("ci_high", np.nan)),
                "unit": _text(ds.attrs.get("units", "")),
                "effect": _text(ds.attrs.get("effect", "")),
            }
            verdict = plausibility.read_verdict(name, ds)
            if not verdict.plausible:
                implausible.append(verdict.reason)
    return {"key": key, "values": values, "quantities": quantities, "implausible": implausible}


def run_file_row(item: "Item", got: dict, status: str, times: dict | None = None) -> "Row":
    """The summary row of an item whose run file exists (``got`` from :func:`read_run_row`): ``status``, or
    ``suspect`` with the reasons in the error column when a read-out is implausible."""
    if got.get("implausible"):
        return Row(item, "suspect", "implausible read-outs: " + "; ".join(got["implausible"]), got["values"],
                   got["quantities"], times or {})
    return Row(item, status, "", got["values"], got["quantities"], times or {})


def _text(value) -> str:
    if isinstance(value, bytes):
        return value.decode()
    return str(value)


def run_key(path: Path) -> str | None:
    """The ``batch_key`` attribute of a run file (None if absent or unreadable)."""
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            return _text(h5.attrs["batch_key"]) if "batch_key" in h5.attrs else None
    except (OSError, KeyError):
        return None


# =========================================================================== the worker
_worker_state: dict[str, Any] = {}


def _init_worker(env: dict[str, str], log_level: int, parent_pid: int | None = None) -> None:
    """Worker start-up: thread limits before NumPy loads, signals, logging, warm imports."""
    os.environ.update(env)
    # The parent stops workers with SIGTERM (see _stop_workers); Ctrl-C in a terminal reaches the whole
    # process group, and the parent decides what to do about it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_sigterm)
    if parent_pid is not None:  # a parent killed outright (kill -9) cannot stop its workers: they stop themselves
        from .orphans import exit_with_parent

        exit_with_parent(parent_pid)
    sys.unraisablehook = _on_unraisable
    logger = logging.getLogger("afmid")
    logger.handlers[:] = []
    logger.setLevel(log_level)
    logger.propagate = False
    logging.captureWarnings(True)
    _worker_state["log_level"] = log_level
    # run_fit makes a (disabled) tqdm bar; tqdm's default lock is a multiprocessing semaphore, which a worker
    # stopped with os._exit would leave registered (the resource tracker then warns). A thread lock suffices.
    import threading

    from tqdm import tqdm

    tqdm.set_lock(threading.RLock())
    # Import once per worker; numba's kernels load from its on-disk cache at their first call.
    from . import fit, io  # noqa: F401


class _Terminated(SystemExit):
    """Raised in a worker by SIGTERM during a fit: unwinds (removing temporary files), then the worker exits."""


def _on_sigterm(signum, frame):
    if not _worker_state.get("busy"):
        os._exit(143)  # idle: nothing to clean up
    _worker_state["terminating"] = True
    raise _Terminated(143)


_default_unraisablehook = sys.unraisablehook


def _on_unraisable(unraisable) -> None:
    """SIGTERM that landed in a callback that cannot raise (a weakref callback, ``__del__``): Python would print it
    as ignored and let the item run on. Exit now instead; the worker's temporary files are all inside the batch's
    temporary folder, which the parent removes."""
    if isinstance(unraisable.exc_value, _Terminated) or _worker_state.get("terminating"):
        os._exit(143)
    _default_unraisablehook(unraisable)


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
        from .interrupts import Terminated

        raise Terminated() if signal.SIGTERM in caught else KeyboardInterrupt()


class _Capture(logging.Handler):
    def __init__(self):
        super().__init__()
        self.records: list[tuple[int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.records.append((record.levelno, record.getMessage()))
        except Exception:  # pragma: no cover - a malformed log call must not fail the fit
            pass


def fit_task(task: dict) -> dict:
    """Run one item in a worker: simulate its trace if asked (written atomically), load, run_fit, write the run
    file atomically. Never raises for a bad item."""
    capture = _Capture()
    capture.setLevel(_worker_state.get("log_level", logging.WARNING))
    loggers = [logging.getLogger("afmid"), logging.getLogger("py.warnings")]
    for lg in loggers:
        lg.addHandler(capture)
    tmp = Path(task["tmp_dir"]) / f"{task['name']}.{os.getpid()}{RUN_SUFFIX}"
    tmp_trace = Path(task["tmp_dir"]) / f"{task['name']}.{os.getpid()}{TRACE_SUFFIX}"
    out: dict[str, Any] = {"index": task["index"], "status": "failed", "error": "", "times": {}}
    stage = "fit"
    _worker_state["busy"] = True
    try:
        delay = float(os.environ.get(_DELAY_ENV) or 0.0)
        from .config import build_config
        from .fit import run_fit, write_run
        from .io import load_trace

        c0 = time.process_time()
        times = {}
        if task.get("simulate") is not None:  # exactly `afmid simulate CONFIG -o TRACE`
            from .config import dump_config
            from .io import write_trace_file
            from .simulate import simulate

            stage = "simulate"
            s0 = time.perf_counter()
            sim_config = build_config(task["simulate"], source=Path(task["config"]))
            simulated = simulate(sim_config)
            write_trace_file(tmp_trace, simulated, dump_config(sim_config), overwrite=True)
            del simulated
            if delay:
                time.sleep(delay)
                delay = 0.0
            os.replace(tmp_trace, task["trace"])
            times["simulate_time"] = time.perf_counter() - s0
            stage = "fit"
        if delay:
            time.sleep(delay)
        t0 = time.perf_counter()
        config = build_config(task["raw"], source=Path(task["config"]))
        trace = load_trace(config)
        t1 = time.perf_counter()
        result = run_fit(config, trace=trace)
        t2 = time.perf_counter()
        key = batch_key(trace.sha256, task["config_text"])
        write_run(tmp, result, config, overwrite=True, root_attrs={"batch_key": key})
        os.replace(tmp, task["output"])
        t3 = time.perf_counter()
        out["row"] = read_run_row(Path(task["output"]))
        out["status"] = "ok"
        out["times"] = {**times, "load_time": t1 - t0, "fit_time": t2 - t1, "write_time": t3 - t2,
                        "cpu_time": time.process_time() - c0}
    except BaseException as exc:
        if isinstance(exc, _Terminated) or _worker_state.get("terminating") or not isinstance(exc, Exception):
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
        _worker_state["busy"] = False
        tmp.unlink(missing_ok=True)
        tmp_trace.unlink(missing_ok=True)
        for lg in loggers:
            lg.removeHandler(capture)
    out["logs"] = capture.records
    return out


# =========================================================================== summary
FIXED_COLUMNS = [  # (name, unit or None for text)
    ("name", None), ("status", None), ("error", None), ("config", None), ("input", None), ("run_file", None),
    ("input_sha256", None), ("effects", None), ("cv_error", "1"), ("cv_error_noise_floor", "1"),
    ("chi2_reduced", "1"), ("terms", None), ("separation", "m"), ("separation_error", "m"),
]
#: Wall time of each stage in the worker (simulate_time only for simulated traces), and the worker's CPU time
#: for the item.
TIME_COLUMNS = [("simulate_time", "s"), ("load_time", "s"), ("fit_time", "s"), ("write_time", "s"),
                ("cpu_time", "s")]
QUANTITY_FIELDS = ("value", "error", "ci_low", "ci_high")


@dataclass
class Row:
    item: Item
    status: str
    error: str = ""
    values: dict = field(default_factory=dict)
    quantities: dict = field(default_factory=dict)
    times: dict = field(default_factory=dict)


def _quantity_columns(rows: list[Row]) -> list[tuple[str, str, str]]:
    """The union of the rows' physical quantities, in order of first appearance: (name, unit, h5 group name).

    Runs of different models report different quantities; a row without one gets an empty cell / NaN. A name
    is one column per unit (the catalog gives each name one unit; a second unit would get its own column,
    ``name [unit]`` in the h5).
    """
    seen: dict[tuple[str, str], None] = {}
    for row in rows:
        for name, q in row.quantities.items():
            seen.setdefault((name, q["unit"]), None)
    first_unit: dict[str, str] = {}
    out = []
    for name, unit in seen:
        first_unit.setdefault(name, unit)
        out.append((name, unit, name if first_unit[name] == unit else f"{name} [{unit}]"))
    return out


def _quantity(row: Row, name: str, unit: str) -> dict | None:
    q = row.quantities.get(name)
    return q if q is not None and q["unit"] == unit else None


def _column_title(name: str, unit: str | None) -> str:
    return name if unit is None else f"{name} [{unit}]"


def _fmt(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    return str(value)


def _row_cells(row: Row, output_dir: Path) -> dict[str, Any]:
    item = row.item
    source = item.input if item.input is not None else item.entry.path
    if item.simulate is not None and row.status == "failed" and not item.input.is_file():
        source = None  # the simulation failed: there is no trace
    cells: dict[str, Any] = {
        "name": item.name, "status": row.status, "error": row.error,
        "config": "" if item.config_path is None else str(item.config_path),
        "input": "" if source is None else str(source),
        "run_file": item.output.name if row.status != "failed" else "",
    }
    cells.update(row.values)
    cells.update(row.times)
    return cells


def write_summary(output_dir: Path, rows: list[Row], config_text: str) -> None:
    """summary.csv and summary.h5 (atomically), rows in input order (layout in docs/file-formats.md).

    ``config_text``: the batch CONFIG's merged config, or "" when the items have their own configs.
    """
    import numpy as np

    from .io import atomic_hdf5, atomic_path, write_dataset

    quantities = _quantity_columns(rows)
    header = [_column_title(n, u) for n, u in FIXED_COLUMNS]
    for name, unit, _ in quantities:
        header += [_column_title(name if f == "value" else f"{name}_{f}", unit) for f in QUANTITY_FIELDS]
    header += [_column_title(n, u) for n, u in TIME_COLUMNS]
    buf = _io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    table = []
    for row in rows:
        cells = _row_cells(row, output_dir)
        line = [_fmt(cells.get(n)) for n, _ in FIXED_COLUMNS]
        for name, unit, _ in quantities:
            q = _quantity(row, name, unit)
            line += [_fmt(q[f]) if q else "" for f in QUANTITY_FIELDS]
        line += [_fmt(cells.get(n)) for n, _ in TIME_COLUMNS]
        writer.writerow(line)
        table.append(cells)
    with atomic_path(output_dir / SUMMARY_CSV) as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")

    with atomic_hdf5(output_dir / SUMMARY_H5, SUMMARY_FORMAT, config_text) as h5:
        h5.attrs["n_traces"] = len(rows)
        for status in STATUSES:
            h5.attrs[f"n_{status}"] = sum(r.status == status for r in rows)
        for name, unit in FIXED_COLUMNS + TIME_COLUMNS:
            if unit is None:
                write_dataset(h5, name, np.array([str(c.get(name, "")) for c in table], dtype=str), "1")
            else:
                data = np.array([_float(c.get(name)) for c in table], dtype=float)
                write_dataset(h5, name, data, unit)
        pg = h5.create_group("parameters")
        pg.attrs["meaning"] = ("physical parameters per row: value, bootstrap error, 95 % interval; the union over "
                               "all rows, NaN where a run has no such quantity")
        for name, unit, group in quantities:
            g = pg.create_group(group)
            found = [_quantity(r, name, unit) for r in rows]
            g.attrs["effect"] = ";".join(sorted({q["effect"] for q in found if q and q["effect"]}))
            for f in QUANTITY_FIELDS:
                data = np.array([_float(q[f]) if q else math.nan for q in found], dtype=float)
                write_dataset(g, f, data, unit)


def _float(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


# =========================================================================== the batch
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


def default_jobs() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


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
) -> BatchResult:
    """Fit every input with ``config``, or run every config in ``configs`` (glob patterns) on its own data (its
    ``data.path``, or a trace it simulates into ``output_dir`` first), in ``jobs`` worker processes; see the
    module docstring. ``overrides`` (``key.path=value``) apply to every config.

    ``worker`` runs one item in a worker process (a module-level function, pickled to spawned workers): one
    task dict in, one result dict out, as :func:`fit_task`, which it may wrap (e.g. to inject a fault)."""
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
    from .folder_lock import folder_lock

    with folder_lock(output_dir, key="--output"):  # one batch per folder: a second one would mix its results in
        return _run_in_folder(items, output_dir, batch_text, unit, jobs, force, progress, summary_interval, start,
                              worker)


def refuse_outputs_on_inputs(items: list[Item], output_dir: Path, config_path: Path | None,
                             manifest: Path | None) -> None:
    """OutputError if a file the batch would write (a run file, a simulated trace, the summary) is one of its
    inputs: the batch CONFIG, the manifest, an entry's config or a trace it fits (e.g. ``DIR/a.run.h5`` listed as
    a trace, or a config's data.path where another config's trace is simulated)."""
    from .io import refuse_input_as_output

    inputs: dict[Path | None, str] = {config_path: "the batch config", manifest: "the manifest"}
    for item in items:
        if item.entry.config is not None:
            inputs.setdefault(item.entry.config, f"the config of {item.name}")
        if item.input is not None and item.simulate is None:
            inputs.setdefault(item.input, f"the trace of {item.name}")
    outputs = [output_dir / SUMMARY_CSV, output_dir / SUMMARY_H5]
    outputs += [item.output for item in items]
    outputs += [item.input for item in items if item.simulate is not None and item.input is not None]
    refuse_input_as_output(outputs, inputs, key="--output")


def _run_in_folder(items: list[Item], output_dir: Path, batch_text: str, unit: str, jobs: int | None, force: bool,
                   progress: bool, summary_interval: float, start: float,
                   worker: Callable[[dict], dict] = fit_task) -> BatchResult:
    """The part of :func:`run_batch` that writes in ``output_dir``, under its lock."""
    _remove_stale_tmp(output_dir)
    jobs = max(1, jobs or default_jobs())
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
            from .io import sha256_file

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
             len(items), unit, len(todo), f" ({n_sim} simulated first)" if n_sim else "", min(jobs, len(todo)),
             sum(r.status == "skipped" for r in rows.values()), sum(r.status == "failed" for r in rows.values()))

    state = {"last": time.monotonic(), "dirty": True, "cost": 0.0}

    def ordered() -> list[Row]:
        return [rows[i] for i in sorted(rows)]

    def flush(force_write: bool = False) -> None:
        # At most every summary_interval seconds, and spending at most ~5 % of the main process on summaries
        # (a summary of 1,000 rows takes ~65 ms to write).
        interval = max(summary_interval, 20.0 * state["cost"])
        if force_write or (state["dirty"] and time.monotonic() - state["last"] >= interval):
            start = time.monotonic()
            with _interrupts_held():
                write_summary(output_dir, ordered(), batch_text)
            state["last"] = time.monotonic()
            state["cost"] = state["last"] - start
            state["dirty"] = False

    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    from . import interrupts

    interrupted: KeyboardInterrupt | None = None
    tmp_dir = output_dir / f"{TMP_PREFIX}{os.getpid()}"
    handling = contextlib.ExitStack()
    handling.enter_context(interrupts.handled())  # Ctrl-C and SIGTERM raise, and are never lost
    bar = None
    try:
        if todo:
            tmp_dir.mkdir(exist_ok=True)
            with logging_redirect_tqdm(loggers=[logging.getLogger("afmid")], tqdm_class=tqdm):
                bar = tqdm(total=len(items), initial=len(rows), desc="batch", unit=unit.rstrip("s"),
                           disable=not progress, leave=False, dynamic_ncols=True)
                _run_pool(todo, rows, jobs, tmp_dir, bar, flush, state, worker)
        flush(force_write=True)
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (interrupts.Terminated)
        interrupted = exc
        interrupts.clear()  # handled here: the summary below must not be stopped by it again
        with _interrupts_held(reraise=False):  # a second Ctrl-C must not spoil the summary
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


def _run_pool(todo: list[Item], rows: dict, jobs: int, tmp_dir: Path, bar, flush, state,
              worker: Callable[[dict], dict]) -> None:
    """Keep up to ``jobs`` items in flight; replace the pool if a worker dies (see the module docstring)."""
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    from . import interrupts

    ctx = multiprocessing.get_context("spawn")
    level = logging.getLogger("afmid").getEffectiveLevel()
    pending = deque(todo)
    suspects: deque[Item] = deque()
    n_workers = min(jobs, len(todo))

    def new_pool() -> ProcessPoolExecutor:
        # The thread caps go in the environment the workers are spawned with (so they hold before any import)
        # and again in the initializer.
        return ProcessPoolExecutor(n_workers, mp_context=ctx, initializer=_init_worker,
                                   initargs=(dict(SINGLE_THREAD_ENV), level, os.getpid()))

    def task(item: Item) -> dict:
        return {"index": item.index, "name": item.name, "raw": item.raw, "config": str(item.config_path),
                "config_text": item.config_text, "output": str(item.output), "tmp_dir": str(tmp_dir),
                "simulate": item.simulate if item.need_simulate else None, "trace": str(item.input)}

    saved_env = {k: os.environ.get(k) for k in SINGLE_THREAD_ENV}
    os.environ.update(SINGLE_THREAD_ENV)
    pool = new_pool()
    in_flight: dict = {}  # future -> (item, isolated)
    try:
        while pending or suspects or in_flight:
            if suspects:
                if not in_flight:  # a suspect runs alone: if the worker dies again, it is the culprit
                    item = suspects.popleft()
                    in_flight[pool.submit(worker, task(item))] = (item, True)
            else:
                while pending and len(in_flight) < n_workers:
                    item = pending.popleft()
                    in_flight[pool.submit(worker, task(item))] = (item, False)
            done, _ = wait(list(in_flight), timeout=1.0, return_when=FIRST_COMPLETED)
            interrupts.raise_if_pending()  # a Ctrl-C / SIGTERM that landed where Python could not raise it
            broken = False
            for fut in done:
                item, isolated = in_flight.pop(fut)
                try:
                    out = fut.result()
                except BrokenProcessPool:
                    broken = True
                    item.crashes += 1
                    if isolated:
                        msg = ("the worker process died while running this item (killed, crashed or out of "
                               "memory)")
                        rows[item.index] = Row(item, "failed", msg)
                        log.warning("%s: %s", item.name, msg)
                        bar.update(1)
                        state["dirty"] = True
                    else:
                        suspects.append(item)
                    continue
                _record(item, out, rows)
                bar.update(1)
                state["dirty"] = True
            if broken:
                for fut, (item, isolated) in list(in_flight.items()):  # the pool is gone: requeue the rest
                    in_flight.pop(fut)
                    item.crashes += 1
                    suspects.append(item)
                pool.shutdown(wait=True, cancel_futures=True)
                log.warning("a worker process died; restarting the pool and retrying its items one at a time")
                pool = new_pool()
            flush()
    except BaseException:
        _stop_workers(pool)
        _harvest(in_flight, rows)
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        # Let the pool's queues be finalised now (the traceback of an interrupt keeps this frame alive, and
        # semaphores still registered at exit make multiprocessing's resource tracker complain).
        pool = None
        in_flight.clear()
        import gc

        gc.collect()
        for k, v in saved_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _harvest(in_flight: dict, rows: dict) -> None:
    """After stopping the workers: record the items that finished meanwhile (the summary must list every
    run file that was renamed into place, even if its worker's report did not arrive)."""
    from .io import sha256_file

    for fut, (item, _) in in_flight.items():
        if fut.done() and not fut.cancelled() and fut.exception() is None:
            _record(item, fut.result(), rows)
        elif item.output.is_file() and item.input is not None and item.input.is_file():
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


def _stop_workers(pool) -> None:
    """Stop the workers now (SIGTERM: each removes its temporary file and exits), then reap them."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    for p in procs:
        if p.is_alive():
            p.terminate()
    deadline = time.monotonic() + 5.0
    for p in procs:
        p.join(timeout=max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            p.kill()
            p.join(timeout=5.0)
    pool.shutdown(wait=False, cancel_futures=True)
