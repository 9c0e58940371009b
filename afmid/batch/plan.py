"""Batch planning: the items of ``afmid batch`` from ``--inputs``, ``--configs`` or ``--manifest``, their run
names, merged configs and up-to-date checks (see :mod:`afmid.batch.run` for the whole story).

Nothing here runs a fit: :func:`plan` turns entries into :class:`Item` objects, :func:`batch_key`,
:func:`run_key` and :func:`trace_is_current` decide what an earlier batch already did. Imports nothing heavy at
import time (a worker sets its thread limits before NumPy loads).
"""

from __future__ import annotations

import csv
import glob
import hashlib
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from afmid.version import __version__
from afmid.errors import ConfigError, InputError

RUN_SUFFIX = ".run.h5"
TRACE_SUFFIX = ".trace.h5"
#: The batch's summary files in its output folder (written by :mod:`afmid.batch.summary`; never an input).
SUMMARY_CSV = "summary.csv"
SUMMARY_H5 = "summary.h5"


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
    from afmid.config import parse_override

    from afmid.io.files import check_input_file

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
        from afmid.config import read_yaml

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
    from afmid.config import apply_overrides, build_config, dump_config, parse_override, read_yaml

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
    from afmid.config import build_config, dump_config

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

    from afmid.runfile import text  # an HDF5 string attribute (bytes or str) as str

    if not path.is_file():
        return False
    try:
        with h5py.File(path, "r") as h5:
            return (text(h5.attrs.get("format", "")) == "afmid-trace"
                    and text(h5.attrs.get("afmid_version", "")) == __version__
                    and text(h5.attrs.get("config", "")) == sim_text
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


def run_key(path: Path) -> str | None:
    """The ``batch_key`` attribute of a run file (None if absent or unreadable): :func:`afmid.runfile.read_batch_key`."""
    from afmid.runfile import read_batch_key

    return read_batch_key(path)


def refuse_outputs_on_inputs(items: list[Item], output_dir: Path, config_path: Path | None,
                             manifest: Path | None) -> None:
    """OutputError if a file the batch would write (a run file, a simulated trace, the summary) is one of its
    inputs: the batch CONFIG, the manifest, an entry's config or a trace it fits (e.g. ``DIR/a.run.h5`` listed as
    a trace, or a config's data.path where another config's trace is simulated)."""
    from afmid.io.trace import refuse_input_as_output

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

