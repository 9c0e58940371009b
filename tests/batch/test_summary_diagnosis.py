"""The batch summary's diagnosis column (afmid/batch/summary.py, diagnosis_text): what afmid says of a run
without refitting candidate effects. A 12-period DMT + Kelvin-Voigt trace fitted with [dmt] misses the
viscosity: model-limited, its residual in contact and dissipative; fitted with [dmt, viscoelastic] it is at the
noise floor. A file that is not a run file: not diagnosed, said so."""

from __future__ import annotations

import re

from short_runs import short_dmt_viscoelastic_config

from afmid.batch.summary import DIAGNOSIS_MEANING, diagnosis_text, read_run_row


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
