"""The batch summary's diagnosis column (afmid/batch/summary.py, diagnosis_text): what afmid says of a run
without refitting candidate effects. A 12-period DMT + Kelvin-Voigt trace fitted with [dmt] misses the
viscosity: model-limited, its residual in contact and dissipative; fitted with [dmt, viscoelastic] it is at the
noise floor. A file that is not a run file: not diagnosed, said so. The model-limited run's status in a batch:
`model-limited`, never a plain `ok` (issue 33), also when it is skipped as up to date."""

from __future__ import annotations

import csv
import re

import h5py
import yaml
from short_runs import short_dmt_viscoelastic_config

from afmid.batch.summary import DIAGNOSIS_MEANING, diagnosis_text, read_run_row
from afmid.fit.uncertainty import FLOOR_FACTOR


def test_diagnosis_names_the_model_limited_run_and_where_its_residual_is(tmp_path, run_cli):
    config = short_dmt_viscoelastic_config(tmp_path)
    assert run_cli("-q", "simulate", config, "-o", tmp_path / "trace.h5")[0] == 0
    assert run_cli("-q", "fit", config, "-o", tmp_path / "full.h5")[0] == 0
    assert run_cli("-q", "fit", config, "--remove", "viscoelastic", "-o", tmp_path / "dmt.h5")[0] == 0
    limited = diagnosis_text(tmp_path / "dmt.h5")
    assert re.fullmatch(r"model-limited \(x[0-9.]+ the floor\): residual (contact|near|far) [0-9]+ %, "
                        r"(contact|near|far) [0-9]+ %, (contact|near|far) [0-9]+ %; dissipative", limited), limited
    shares = [int(x) for x in re.findall(r"([0-9]+) %", limited)]
    assert shares == sorted(shares, reverse=True) and abs(sum(shares) - 100) <= 2  # the missing Kelvin-Voigt force
    assert diagnosis_text(tmp_path / "full.h5").startswith("at the noise floor (x")
    row = read_run_row(tmp_path / "dmt.h5")
    assert row["values"]["diagnosis"] == limited and row["values"]["separation_sigma"] != row["values"].get("x")
    assert "separation_error" not in row["values"]
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    assert diagnosis_text(tmp_path / "junk.h5").startswith("not diagnosed (")
    assert "region" in DIAGNOSIS_MEANING and "character" in DIAGNOSIS_MEANING


def _summary_rows(folder):
    with open(folder / "summary.csv", newline="", encoding="utf-8") as f:
        return {r["name"]: r for r in csv.DictReader(f)}


def test_a_model_limited_run_is_listed_as_model_limited_never_as_a_plain_ok(tmp_path, run_cli):
    """The trace with hidden viscosity fitted with [dmt] and with [dmt, viscoelastic] in one batch: the first row
    says `model-limited` (exit 0 and a warning naming it, as a suspect item: a result written and flagged), its
    failure cell the ratio to the floor; the second `ok`. The ratio in the cell is the one of its own cv_error
    columns (printed to 2 significant digits: within 5 % of it). Resumed, the model-limited row stays so."""
    config = short_dmt_viscoelastic_config(tmp_path)
    assert run_cli("-q", "simulate", config, "-o", tmp_path / "trace.h5")[0] == 0
    (tmp_path / "list.yaml").write_text(yaml.safe_dump([
        {"path": "trace.h5", "name": "dmt_only", "set": {"model.effects": ["dmt"]}},
        {"path": "trace.h5", "name": "full"},
    ]))
    out = tmp_path / "batch"
    code, _, err = run_cli("-q", "batch", config, "--manifest", tmp_path / "list.yaml", "-o", out, "-j", "1")
    assert code == 0, err
    assert "afmid: warning: 1 of 2 traces model-limited (dmt_only)" in err, err
    rows = _summary_rows(out)
    limited, full = rows["dmt_only"], rows["full"]
    ratio = float(limited["cv_error"]) / float(limited["cv_error_noise_floor"])
    assert ratio > FLOOR_FACTOR and limited["model_limited"] == "1"
    assert limited["status"] == "model-limited", limited
    shown = float(re.match(r"model-limited: cv_error ([0-9.]+)x its noise floor \(limit 1\.[0-9]+x\)",
                           limited["failure"]).group(1))
    assert abs(shown - ratio) <= 0.05 * ratio, (shown, ratio)
    assert limited["diagnosis"].startswith("model-limited (x")
    assert full["status"] == "ok" and full["failure"] == "" and full["model_limited"] == "0", full
    with h5py.File(out / "summary.h5", "r") as h5:
        assert (h5.attrs["n_ok"], h5.attrs["n_model_limited"], h5.attrs["n_suspect"]) == (1, 1, 0)
        assert [s.decode() for s in h5["status"][...]] == ["model-limited", "ok"]
    code, _, err = run_cli("-q", "batch", config, "--manifest", tmp_path / "list.yaml", "-o", out, "-j", "1")
    assert code == 0, err
    assert [r["status"] for r in _summary_rows(out).values()] == ["model-limited", "skipped"]
