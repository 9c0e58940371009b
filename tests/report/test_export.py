"""``afmid export RUN.h5 --what force-curves|parameters|periods -o FILE.csv`` (issue 15).

Round trip: the CSV's numbers are the run file's, read here with h5py directly (not through afmid's reader),
exactly (the CSV writes the shortest form that reads back to the same float); the column names carry the
run file's units; the approach / retract marks follow the sign of dz/dt. Bad input (the corpus contract,
tests/corpus.py): not a run file, a force-map result, an unknown --what, an existing output without
--overwrite, the input given as output; nothing written or changed.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
from short_runs import short_dmt_viscoelastic_config

from afmid.cli import main
from corpus import Case, check_case, corpus_params


@pytest.fixture(scope="module")
def run_file(tmp_path_factory) -> Path:
    """A short dmt + viscoelastic run (12 periods, 10 bootstrap draws), fitted by the command line."""
    folder = tmp_path_factory.mktemp("export")
    config = short_dmt_viscoelastic_config(folder)
    assert main(["-q", "simulate", str(config), "-o", str(folder / "trace.h5")]) == 0
    assert main(["-q", "fit", str(config), "-o", str(folder / "run.h5")]) == 0
    return folder / "run.h5"


def export(run_file: Path, what: str, out: Path) -> tuple[list[str], list[list[str]]]:
    assert main(["-q", "export", str(run_file), "--what", what, "-o", str(out)]) == 0
    with open(out, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def number(field: str) -> float:
    return math.nan if field == "" else float(field)


def same(a: float, b: float) -> bool:
    return (math.isnan(a) and not math.isfinite(b)) or a == b


def test_force_curves_are_the_run_files_per_period_curves(run_file, tmp_path):
    header, rows = export(run_file, "force-curves", tmp_path / "curves.csv")
    assert header[:4] == ["period", "branch", "separation_m", "force_N"]  # pinned
    col = {name: i for i, name in enumerate(header)}
    with h5py.File(run_file, "r") as h5:
        p = h5["periods"]
        separation, velocity, phase = p["separation"][()], p["velocity"][()], p["phase"][()]
        model, inverted = p["force_model"][()], p["force_inverted"][()]
        assert p["separation"].attrs["units"] == "m" and p["force_model"].attrs["units"] == "N"
    n_periods, n_samples = separation.shape
    assert len(rows) == n_periods * n_samples
    table = np.array([[number(r[col[c]]) for c in ("period", "separation_m", "force_N", "phase_rad",
                                                   "force_inverted_N")] for r in rows]).reshape(n_periods, n_samples, 5)
    np.testing.assert_array_equal(table[..., 0], np.repeat(np.arange(n_periods), n_samples).reshape(n_periods, -1))
    np.testing.assert_array_equal(table[..., 1], separation)
    np.testing.assert_array_equal(table[..., 2], model)
    np.testing.assert_array_equal(table[..., 3], np.broadcast_to(phase, separation.shape))
    np.testing.assert_array_equal(table[..., 4], inverted)
    branch = np.array([r[col["branch"]] for r in rows]).reshape(n_periods, n_samples)
    assert set(np.unique(branch)) == {"approach", "retract"}
    np.testing.assert_array_equal(branch == "approach", velocity > 0)
    # approach = the separation falling: the periodic central difference of z agrees away from the turning points
    dz = np.roll(separation, -1, axis=1) - np.roll(separation, 1, axis=1)
    assert np.mean((dz < 0) == (branch == "approach")) > 0.95


def test_parameters_are_the_run_files_read_outs(run_file, tmp_path):
    header, rows = export(run_file, "parameters", tmp_path / "parameters.csv")
    assert header[:8] == ["name", "value", "sigma_1", "ci95_low", "ci95_high", "unit", "determined",
                          "model_limited"]  # pinned
    by_name = {r[0]: dict(zip(header, r)) for r in rows}
    with h5py.File(run_file, "r") as h5:
        stored = h5["model/parameters"]
        assert set(stored) <= set(by_name) and len(stored) >= 3  # E_star, viscosity, ... all there
        for name, ds in stored.items():
            row = by_name[name]
            assert same(number(row["value"]), float(ds[()])), name
            for column, attr in (("sigma_1", "error"), ("ci95_low", "ci_low"), ("ci95_high", "ci_high")):
                assert same(number(row[column]), float(ds.attrs[attr])), (name, column)
            assert row["unit"] == ds.attrs["units"]
            assert row["determined"] == ("true" if ds.attrs.get("determined", True) else "false")
            assert row["model_limited"] == ("true" if ds.attrs.get("model_limited", False) else "false")
            assert row["plausible"] == ("true" if ds.attrs.get("plausible", True) else "false")
        for name, ds in h5["model/nonlinear"].items():
            if name not in stored:
                assert same(number(by_name[name]["value"]), float(ds[()]))
                assert by_name[name]["ci95_low"] == by_name[name]["ci95_high"] == ""  # no interval in the file


def test_periods_are_the_run_files_per_period_values(run_file, tmp_path):
    header, rows = export(run_file, "periods", tmp_path / "periods.csv")
    assert header[0] == "period"
    with h5py.File(run_file, "r") as h5:
        p = h5["periods"]
        n_periods = p["separation"].shape[0]
        per_period = {name: ds for name, ds in p.items() if ds.shape == (n_periods,)}
        assert {"peak_force", "dissipated_energy", "virial", "amplitude"} <= set(per_period)
        assert len(header) == 1 + len(per_period) and len(rows) == n_periods
        columns = {name: [number(r[i]) for r in rows] for i, name in enumerate(header)}
        assert columns["period"] == list(range(n_periods))
        for name, ds in per_period.items():
            unit = ds.attrs["units"]
            column = f"{name}_{unit}" if unit != "1" else name  # every /periods unit here is a plain symbol
            assert column in columns, (column, header)
            assert all(same(a, b) for a, b in zip(columns[column], ds[()])), name
    assert "peak_force_N" in header and "dissipated_energy_J" in header and "contact_time_s" in header


def test_overwrite_replaces_an_earlier_export_and_leaves_no_temporary_file(run_file, tmp_path):
    out = tmp_path / "p.csv"
    out.write_text("old\n")
    assert main(["-q", "export", str(run_file), "--what", "parameters", "-o", str(out), "--overwrite"]) == 0
    assert out.read_text().startswith("name,value,sigma_1,")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.csv"]


# --------------------------------------------------------------------------- bad input
def run_like(format_attr: str, name: str = "run.h5"):
    def write(folder: Path) -> None:
        with h5py.File(folder / name, "w") as h5:
            h5.attrs["format"] = format_attr
            h5.create_dataset("maps/E_star", data=np.zeros((2, 2)))
    return write


def text_file(name: str, content: str):
    def write(folder: Path) -> None:
        (folder / name).write_text(content)
    return write


def both(*writers):
    def write(folder: Path) -> None:
        for w in writers:
            w(folder)
    return write


EXPORT = ("export", "run.h5", "--what", "parameters", "-o", "out.csv")
CASES = [
    Case("export-run-missing", "runfile", EXPORT, lambda folder: None, 1, "run.h5", None, ("not found",)),
    Case("export-not-hdf5", "runfile", EXPORT, text_file("run.h5", "time,deflection\n0,1\n"), 1, "run.h5", None,
         ("expected a run file from afmid fit", "not an HDF5 file")),
    Case("export-not-a-run-file", "runfile", EXPORT, run_like("something-else"), 1, "run.h5", None,
         ("not an afmid run file",)),
    Case("export-map-result", "runfile", EXPORT, run_like("afmid-map-result"), 1, "run.h5", None,
         ("force-map result", "afmid report RESULT.h5")),
    Case("export-unknown-what", "request", ("export", "run.h5", "--what", "curves", "-o", "out.csv"),
         run_like("afmid-run"), 2, None, "--what", ("force-curves",)),
    Case("export-output-exists", "output", EXPORT, both(run_like("afmid-run"), text_file("out.csv", "mine\n")),
         1, "out.csv", None, ("--overwrite",)),
    Case("export-output-is-the-input", "output", ("export", "run.h5", "--what", "periods", "-o", "run.h5",
                                                  "--overwrite"), run_like("afmid-run"), 1, "run.h5", None,
         ("run file",)),
]


@corpus_params(CASES)
def test_export_bad_input(case, tmp_path, capsys, monkeypatch):
    check_case(case, tmp_path / "ws", capsys, monkeypatch)
