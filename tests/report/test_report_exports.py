"""`afmid report RUN... -o DIR --export force-curves,parameters,periods` (afmid/report/report_exports.py): the
last run's CSV tables in the report folder, the same bytes as `afmid export`, listed in the folder's marker so
that `--overwrite` replaces the folder later."""

from __future__ import annotations

import json

from short_runs import short_dmt_viscoelastic_config


def test_report_exports_the_last_runs_tables(tmp_path, run_cli):
    config = short_dmt_viscoelastic_config(tmp_path)
    assert run_cli("-q", "simulate", config, "-o", tmp_path / "trace.h5")[0] == 0
    assert run_cli("-q", "fit", config, "-o", tmp_path / "run2.h5")[0] == 0
    report = tmp_path / "report"
    code, _, err = run_cli("-q", "report", tmp_path / "run2.h5", "-o", report, "--no-suggest",
                           "--export", "force-curves,parameters,periods")
    assert code == 0, err
    names = ["run2.force-curves.csv", "run2.parameters.csv", "run2.periods.csv"]
    for name, what in zip(names, ["force-curves", "parameters", "periods"]):
        alone = tmp_path / f"alone.{what}.csv"
        assert run_cli("-q", "export", tmp_path / "run2.h5", "--what", what, "-o", alone)[0] == 0
        assert (report / name).read_bytes() == alone.read_bytes()  # the same code path: the same bytes
    marker = json.loads((report / ".afmid-report").read_text())
    assert set(names) <= set(marker["files"]) and "report.html" in marker["files"]
    # the folder is afmid's as a whole: replaced with --overwrite, here without the CSVs
    code, _, err = run_cli("-q", "report", tmp_path / "run2.h5", "-o", report, "--no-suggest", "--overwrite")
    assert code == 0, err
    assert not any((report / n).exists() for n in names)


def test_report_export_names_are_checked_before_the_work(tmp_path, run_cli):
    code, out, err = run_cli("report", tmp_path / "missing.h5", "-o", tmp_path / "r", "--export", "curves")
    assert code == 2 and out == ""
    assert err == ("afmid: error: --export: must be a comma-separated list of force-curves, parameters, periods, "
                   "got 'curves'\n")
    assert not (tmp_path / "r").exists()
