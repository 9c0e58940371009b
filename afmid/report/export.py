"""``afmid export RUN.h5 --what force-curves|parameters|periods -o FILE.csv``: a run file's tables as CSV.

For other tools (a spreadsheet, pandas, Origin, MATLAB): one header line of column names, the unit at the end
of each name (``separation_m``, ``force_N``; pinned), then one row per record, numbers in SI written
with Python's shortest round-trip form (the CSV's numbers are the run file's, bit for bit), an empty field
where the run file has no finite value, ``true``/``false`` for flags. Layout in docs/file-formats.md.

- ``force-curves``: F(z) per period, every sample of the period grid, each marked ``approach`` (the tip moving
  toward the sample: dz/dt < 0, i.e. dx/dt > 0) or ``retract``. Columns ``period, branch, separation_m,
  force_N`` (pinned) then ``phase_rad`` (drive phase within the period) and ``force_inverted_N``.
  ``force_N`` is the identified model's force along the measured trajectory (full bandwidth, the report's
  "model" curve, ``/periods/force_model``); ``force_inverted_N`` is the inverted force F_drive - (m x'' + c x'
  + k x) limited to the harmonics above the noise (``/periods/force_inverted``), which depends on the model
  through the drive when the drive was fitted (``/model/drive`` attribute ``source``), not with a calibrated drive.
- ``parameters``: the physical read-outs, then the nonlinear shape parameters: ``name, value, sigma_1,
  ci95_low, ci95_high, unit, determined, model_limited`` (pinned) then ``plausible``; ``sigma_1`` is the
  1-sigma error, ``ci95_*`` the 95 % interval; a nonlinear parameter (a decay length, the separation d) has
  neither an interval nor a plausibility verdict in the run file (empty fields) and is model-limited when
  its run is.
- ``periods``: one row per period with every per-period quantity of ``/periods`` (peak and adhesion force,
  indentation, contact time, dissipated energy and virial from the model and the inverted force, amplitude, ...).

The output is written under a temporary name and renamed when complete; an existing file is replaced only
with ``overwrite``, an input never.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Iterator
from pathlib import Path

# afmid's one column-naming rule for its CSVs (the batch summary names its columns with it too)
from afmid.quantity_text import column_name

#: What ``afmid export --what`` can write (name -> one line for the help).
EXPORTS = {
    "force-curves": "F(z) per period and branch (approach / retract): model force and inverted force",
    "parameters": "the physical parameters: value, 1-sigma error, 95 % interval, unit, flags",
    "periods": "one row per period: the per-period quantities of the run file",
}
FORCE_CURVE_COLUMNS = ("period", "branch", "separation_m", "force_N", "phase_rad", "force_inverted_N")
PARAMETER_COLUMNS = ("name", "value", "sigma_1", "ci95_low", "ci95_high", "unit", "determined", "model_limited",
                     "plausible")


def export_run(run_path: Path, what: str, output: Path, overwrite: bool = False) -> int:
    """Write table ``what`` (a key of :data:`EXPORTS`) of the run file ``run_path`` to ``output`` as CSV;
    return the number of data rows. One-line :class:`afmid.errors.AfmidError` for a file that is not a run
    file (a force-map result is named as such), an unknown ``what``, or an output that exists (without
    ``overwrite``) or is an input."""
    from afmid.errors import ConfigError
    from afmid.io.trace import atomic_path, check_output_path

    if what not in EXPORTS:
        raise ConfigError(f"must be one of {', '.join(EXPORTS)}, got {what!r}", key="--what")
    run_path, output = Path(run_path), Path(output)
    check_output_path(output, overwrite, inputs={run_path: "the run file"})
    run = _load(run_path)
    header, rows = TABLES[what](run)
    count = 0
    with atomic_path(output) as tmp:
        with open(tmp, "w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh, lineterminator="\n")
            writer.writerow(header)
            for row in rows:
                writer.writerow([cell(v) for v in row])
                count += 1
    return count


def _load(path: Path):
    from afmid.errors import InputError
    from afmid.report.maps import is_map_result
    from afmid.runfile import load_run

    if is_map_result(path):  # a force map's result (afmid map): its tables are maps, not one run's
        raise InputError("is a force-map result (afmid map), not a run file: export reads run files (afmid fit); "
                         "the map's values are the datasets /maps/NAME of the result file, or use "
                         "'afmid report RESULT.h5'", file=path)
    return load_run(path)


def cell(value) -> str:
    """A CSV field: numbers in their shortest round-trip form, '' for NaN / infinity / None, true / false."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return value
    if isinstance(value, int):
        return str(value)
    number = float(value)
    return repr(number) if math.isfinite(number) else ""


# --------------------------------------------------------------------------- the tables
def force_curves(run) -> tuple[list[str], Iterator[list]]:
    """F(z) of every period: (header, rows), rows period by period, samples in the order of the period grid."""
    periods = run.periods
    separation, velocity = periods["separation"], periods["velocity"]
    model, inverted, phase = periods["force_model"], periods["force_inverted"], periods["phase"]

    def rows() -> Iterator[list]:
        for k in range(separation.shape[0]):
            for j in range(separation.shape[1]):
                branch = "approach" if velocity[k, j] > 0 else "retract"  # dz/dt = -dx/dt
                yield [k, branch, separation[k, j], model[k, j], phase[j], inverted[k, j]]

    return list(FORCE_CURVE_COLUMNS), rows()


def parameters(run) -> tuple[list[str], Iterable[list]]:
    """The read-outs (``/model/parameters``), then the nonlinear parameters not among them."""
    rows = []
    for name, q in run.quantities.items():
        rows.append([name, q["value"], q["error"], q["ci_low"], q["ci_high"], q["unit"], q.get("determined", True),
                     q.get("model_limited", False), q.get("plausible", True)])
    for name, q in run.nonlinear.items():
        if name in run.quantities:
            continue
        # the run file keeps no interval and no plausibility verdict for them: those fields stay empty
        rows.append([name, q["value"], q["error"], None, None, q["unit"], True, run.model_limited, None])
    return list(PARAMETER_COLUMNS), rows


def period_table(run) -> tuple[list[str], Iterable[list]]:
    """Every per-period dataset of ``/periods`` (one value per period) as a column, in the run file's units."""
    from afmid.runfile import PERIOD_UNITS

    n_periods = run.periods["separation"].shape[0]
    names = [n for n in PERIOD_UNITS if n in run.periods and run.periods[n].shape == (n_periods,)]
    header = ["period"] + [column_name(n, PERIOD_UNITS[n]) for n in names]
    return header, ([k] + [run.periods[n][k] for n in names] for k in range(n_periods))


TABLES = {"force-curves": force_curves, "parameters": parameters, "periods": period_table}
