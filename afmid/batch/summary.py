"""Batch summary: one row per item (status ok / suspect / failed / skipped, the read-outs of its run file, the
time per stage) written as ``summary.csv`` and ``summary.h5`` (layout in docs/file-formats.md).

Imports nothing heavy at import time.
"""

from __future__ import annotations

import csv
import io as _io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from afmid.batch.plan import Item

SUMMARY_CSV = "summary.csv"
SUMMARY_H5 = "summary.h5"
SUMMARY_FORMAT = "afmid-batch-summary"
#: ok: fitted now; suspect: a run file exists (fitted now or up to date) but a read-out is implausible
#: (afmid.fit.plausibility); failed: no run file; skipped: up to date from an earlier batch.
STATUSES = ("ok", "suspect", "failed", "skipped")


def read_run_row(path: Path) -> dict:
    """The summary values of one run file: {'key', 'values', 'quantities', 'implausible'} (SI), read by the run
    file's owner (:func:`afmid.runfile.read_summary`)."""
    from afmid.runfile import read_summary

    return read_summary(path)


def run_file_row(item: "Item", got: dict, status: str, times: dict | None = None) -> "Row":
    """The summary row of an item whose run file exists (``got`` from :func:`read_run_row`): ``status``, or
    ``suspect`` with the reasons in the error column when a read-out is implausible."""
    if got.get("implausible"):
        return Row(item, "suspect", "implausible read-outs: " + "; ".join(got["implausible"]), got["values"],
                   got["quantities"], times or {})
    return Row(item, status, "", got["values"], got["quantities"], times or {})


def attr_text(value) -> str:
    """An HDF5 string attribute (bytes or str) as str (:func:`afmid.runfile.text`)."""
    from afmid.runfile import text

    return text(value)


FIXED_COLUMNS = [  # (name, unit or None for text)
    ("name", None), ("status", None), ("error", None), ("config", None), ("input", None), ("run_file", None),
    ("input_sha256", None), ("effects", None), ("cv_error", "1"), ("cv_error_noise_floor", "1"),
    ("chi2_reduced", "1"), ("terms", None), ("separation", "m"), ("separation_error", "m"),
]
#: Wall time of each stage in the worker (simulate_time only for simulated traces), and the worker's CPU time
#: for the item.
TIME_COLUMNS = [("simulate_time", "s"), ("load_time", "s"), ("fit_time", "s"), ("write_time", "s"),
                ("cpu_time", "s")]
QUANTITY_FIELDS = ("value", "error", "ci_low", "ci_high", "determined")
#: What the error and interval fields are (attributes of their datasets in summary.h5).
FIELD_MEANINGS = {"error": {"error_kind": "1 sigma"}, "ci_low": {"interval": "95 %, lower end"},
                  "ci_high": {"interval": "95 %, upper end"},
                  "determined": {"meaning": "1: read out from selected terms; 0: its term was not selected, the "
                                            "value is NaN and ci_low..ci_high is the 95 % interval with the term "
                                            "forced in"}}


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

    from afmid.io.trace import atomic_hdf5, atomic_path, write_dataset

    quantities = _quantity_columns(rows)
    header = [_column_title(n, u) for n, u in FIXED_COLUMNS]
    for name, unit, _ in quantities:
        header += [_column_title(name if f == "value" else f"{name}_{f}", None if f == "determined" else unit)
                   for f in QUANTITY_FIELDS]
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
            line += [_fmt(q.get(f)) if q else "" for f in QUANTITY_FIELDS]
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
        pg.attrs["meaning"] = ("physical parameters per row: value, error (1 sigma: bootstrap, profiles of the "
                               "nonlinear parameters and the declared calibration), 95 % interval; the union over "
                               "all rows, NaN where a run has no such quantity")
        for name, unit, group in quantities:
            g = pg.create_group(group)
            found = [_quantity(r, name, unit) for r in rows]
            g.attrs["effect"] = ";".join(sorted({q["effect"] for q in found if q and q["effect"]}))
            for f in QUANTITY_FIELDS:
                data = np.array([_float(q.get(f)) if q else math.nan for q in found], dtype=float)
                write_dataset(g, f, data, "1" if f == "determined" else unit, **FIELD_MEANINGS.get(f, {}))


def _float(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan

