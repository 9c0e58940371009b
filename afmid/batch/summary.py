"""Batch summary: one row per item (status ok / model-limited / suspect / failed / skipped, the read-outs of its
run file, the time per stage) written as ``summary.csv`` and ``summary.h5`` (layout in docs/file-formats.md).
CSV headers name the unit at the end (``E_star_Pa``, ``fit_time_s``), as ``afmid export`` does
(:func:`afmid.quantity_text.column_name`).

Imports nothing heavy at import time.
"""

from __future__ import annotations

import csv
import io as _io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from afmid.batch.plan import SUMMARY_CSV, SUMMARY_H5, Item

SUMMARY_FORMAT = "afmid-batch-summary"
#: ok: fitted now; skipped: up to date from an earlier batch; model-limited: a run file exists (fitted now or up
#: to date) but its model fails the data (cv error above its threshold x its noise floor, afmid.fit.uncertainty.floor_threshold: the parameters are biased
#: beyond their error bars); suspect: a run file exists but a read-out is implausible (afmid.fit.plausibility),
#: model-limited or not; failed: no run file. A row says the worst that holds: a result afmid cannot stand
#: behind never reads as a plain ok or skipped.
STATUSES = ("ok", "model-limited", "suspect", "failed", "skipped")
MODEL_LIMITED = "model-limited"


def status_count_attribute(status: str) -> str:
    """summary.h5's root attribute counting the rows of ``status``: ``n_ok``, ``n_model_limited``, ..."""
    return "n_" + status.replace("-", "_")


def read_run_row(path: Path) -> dict:
    """The summary values of one run file: {'key', 'values', 'quantities', 'implausible'} (SI), read by the run
    file's owner (:func:`afmid.runfile.read_summary`), with the summary's names (``*_sigma`` for 1-sigma errors)
    and the :func:`diagnosis_text` of the run."""
    from afmid.runfile import read_summary

    got = read_summary(path)
    values = got["values"]
    values["separation_sigma"] = values.pop("separation_error", math.nan)
    values["diagnosis"] = diagnosis_text(path)
    return got


#: What the diagnosis column says (the h5 dataset's ``meaning``; docs/file-formats.md).
DIAGNOSIS_MEANING = (
    "what afmid says of the fit without the costly refits of candidate effects: 'at the noise floor' (the model "
    "explains the force: cv_error within 1.45 x its noise floor), or 'model-limited' with where the systematic "
    "residual (model-free minus model force, averaged over periods) sits - its share in each region, contact / near "
    "(within 2 nm of contact) / far, largest first - and its character (conservative: the same on approach and "
    "retraction; dissipative: reverses with the motion; mixed; none beyond the noise); `afmid report RUN` tries "
    "the candidate effects and names the missing one")


def diagnosis_text(path: Path) -> str:
    """One cell: the run's standing against its noise floor and, when model-limited, where its residual sits and
    of what character (:func:`afmid.diagnosis.localize.localize`); no refits, a few ms per run file."""
    from afmid.diagnosis.localize import localize
    from afmid.errors import AfmidError
    from afmid.fit.uncertainty import model_limited
    from afmid.runfile import load_run

    try:
        run = load_run(path)
        ratio = run.cv_error / run.cv_error_noise_floor
        if not model_limited(run.cv_error, run.cv_error_noise_floor, run.cv_error_floor_dof):
            return f"at the noise floor (x{ratio:.2g})"
        local = localize(run)
    except (AfmidError, OSError, KeyError, ValueError, ZeroDivisionError) as exc:  # older or damaged: no verdict
        return f"not diagnosed ({exc})"
    # every region's share, largest first: the band-limited residual of a contact force also spreads
    shares = sorted(local["by_region"].items(), key=lambda kv: -kv[1]["share_of_residual"])
    where = ", ".join(f"{name} {100 * r['share_of_residual']:.0f} %" for name, r in shares)
    character = local["character"] if local["character"] != "none" else "no character beyond the noise"
    return f"model-limited (x{ratio:.2g} the floor): residual {where}; {character}"


def run_file_row(item: "Item", got: dict, status: str, times: dict | None = None) -> "Row":
    """The summary row of an item whose run file exists (``got`` from :func:`read_run_row`): ``status`` (ok or
    skipped) when afmid stands behind it; ``model-limited`` when its cv error stands above its noise-floor limit;
    ``suspect`` when a read-out is implausible; the reasons in the failure column (both when both hold)."""
    reasons = []
    if got.get("implausible"):
        reasons.append("implausible read-outs: " + "; ".join(got["implausible"]))
    limited = model_limited_reason(got["values"])
    if limited:
        reasons.append(limited)
    if got.get("implausible"):
        status = "suspect"
    elif limited:
        status = MODEL_LIMITED
    return Row(item, status, "; ".join(reasons), got["values"], got["quantities"], times or {})


def model_limited_reason(values: dict) -> str:
    """The failure cell of a model-limited run (its cv error and floor in ``values``), "" for one that is not."""
    from afmid.fit.uncertainty import floor_threshold

    if _model_limited_flag(values) != 1:
        return ""
    ratio = values["cv_error"] / values["cv_error_noise_floor"]
    limit = floor_threshold(values.get("cv_error_floor_dof", math.nan))
    return (f"model-limited: cv_error {ratio:.2g}x its noise floor (limit {limit:.3g}x): the model misses part "
            f"of the force, its parameters are biased beyond their error bars (where: diagnosis column)")


def attr_text(value) -> str:
    """An HDF5 string attribute (bytes or str) as str (:func:`afmid.runfile.text`)."""
    from afmid.runfile import text

    return text(value)


FIXED_COLUMNS = [  # (name, unit or None for text)
    ("name", None), ("status", None), ("model_limited", "1"), ("failure", None), ("config", None), ("input", None),
    ("run_file", None),
    ("input_sha256", None), ("effects", None), ("cv_error", "1"), ("cv_error_noise_floor", "1"),
    ("chi2_reduced", "1"), ("diagnosis", None), ("terms", None), ("separation", "m"), ("separation_sigma", "m"),
]
#: Wall time of each stage in the worker (simulate_time only for simulated traces), and the worker's CPU time
#: for the item.
TIME_COLUMNS = [("simulate_time", "s"), ("load_time", "s"), ("fit_time", "s"), ("write_time", "s"),
                ("cpu_time", "s")]
#: The columns of each quantity (``Q``, ``Q_sigma``, ...) and the run file's field each one holds.
QUANTITY_FIELDS = ("value", "sigma", "ci_low", "ci_high", "determined")
_QUANTITY_KEYS = {"sigma": "error"}  # the read-outs call their 1-sigma error `error`
#: What the sigma and interval fields are (attributes of their datasets in summary.h5).
FIELD_MEANINGS = {"sigma": {"error_kind": "1 sigma"}, "ci_low": {"interval": "95 %, lower end"},
                  "ci_high": {"interval": "95 %, upper end"},
                  "determined": {"meaning": "1: read out from selected terms; 0: its term was not selected, the "
                                            "value is NaN and ci_low..ci_high is the 95 % interval with the term "
                                            "forced in"}}


@dataclass
class Row:
    item: Item
    status: str
    failure: str = ""  # why the item failed, or why a suspect or model-limited one is flagged
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
    """The CSV header of a column: ``name_unit`` (``E_star_Pa``, ``fit_time_s``, ``cv_error``), afmid's one rule
    for its CSVs (:func:`afmid.quantity_text.column_name`; the older ``name [unit]`` headers are gone)."""
    from afmid.quantity_text import column_name

    return column_name(name, unit)


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
        "name": item.name, "status": row.status, "failure": row.failure,
        "config": "" if item.config_path is None else str(item.config_path),
        "input": "" if source is None else str(source),
        # absolute, as the input is (the summary said a bare name here and an absolute path beside it)
        "run_file": str(Path(item.output).resolve()) if row.status != "failed" else "",
    }
    cells.update(row.values)
    cells["model_limited"] = _model_limited_flag(row.values)
    cells.update(row.times)
    return cells


def _model_limited_flag(values: dict):
    """1 when the run's cv error stands above its noise floor by more than the factor afmid allows
    (:func:`afmid.fit.uncertainty.model_limited`: its parameters are biased beyond their error bars), 0 when
    not, None (empty / NaN) without a run file. A row with 1 has the status ``model-limited`` (or ``suspect``
    when a read-out is also implausible), never ``ok``."""
    from afmid.fit.uncertainty import model_limited

    error, floor = values.get("cv_error"), values.get("cv_error_noise_floor")
    if error is None or floor is None or not (math.isfinite(error) and math.isfinite(floor)):
        return None
    return int(bool(model_limited(error, floor, values.get("cv_error_floor_dof", math.nan))))


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
            line += [_fmt(q.get(_QUANTITY_KEYS.get(f, f))) if q else "" for f in QUANTITY_FIELDS]
        line += [_fmt(cells.get(n)) for n, _ in TIME_COLUMNS]
        writer.writerow(line)
        table.append(cells)
    with atomic_path(output_dir / SUMMARY_CSV) as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")

    with atomic_hdf5(output_dir / SUMMARY_H5, SUMMARY_FORMAT, config_text) as h5:
        h5.attrs["n_traces"] = len(rows)
        for status in STATUSES:
            h5.attrs[status_count_attribute(status)] = sum(r.status == status for r in rows)
        for name, unit in FIXED_COLUMNS + TIME_COLUMNS:
            if unit is None:
                meaning = {"meaning": DIAGNOSIS_MEANING} if name == "diagnosis" else {}
                write_dataset(h5, name, np.array([str(c.get(name, "")) for c in table], dtype=str), "1", **meaning)
            else:
                data = np.array([_float(c.get(name)) for c in table], dtype=float)
                write_dataset(h5, name, data, unit)
        pg = h5.create_group("parameters")
        pg.attrs["meaning"] = ("physical parameters per row: value, sigma (1 sigma: bootstrap, profiles of the "
                               "nonlinear parameters and the declared calibration), 95 % interval; the union over "
                               "all rows, NaN where a run has no such quantity")
        for name, unit, group in quantities:
            g = pg.create_group(group)
            found = [_quantity(r, name, unit) for r in rows]
            g.attrs["effect"] = ";".join(sorted({q["effect"] for q in found if q and q["effect"]}))
            for f in QUANTITY_FIELDS:
                data = np.array([_float(q.get(_QUANTITY_KEYS.get(f, f))) if q else math.nan for q in found],
                                dtype=float)
                write_dataset(g, f, data, "1" if f == "determined" else unit, **FIELD_MEANINGS.get(f, {}))


def _float(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan

