"""Template placeholders (afmid/placeholders.py): the template's example calibration, marked
'CHECK: template example', stops `afmid fit` with one line (exit 2) until the value is edited or the mark
deleted."""

from __future__ import annotations

import re

import numpy as np
import pytest
import yaml

from short_runs import short_dmt_viscoelastic_config

from afmid.config import load_config, template_text
from afmid.errors import ConfigError
from afmid.placeholders import MARK, marked_keys, placeholders, refuse_placeholders

CANTILEVER = ["cantilever.spring_constant", "cantilever.resonance_frequency", "cantilever.quality_factor",
              "cantilever.tip_radius"]


def test_the_template_marks_its_example_calibration():
    assert marked_keys(template_text()) == CANTILEVER
    assert marked_keys("cantilever:\n  # quality_factor: 150  # CHECK: template example\n") == []  # commented out
    assert marked_keys("cantilever:\n  quality_factor: 150  # CHECK the value\n") == []  # another note, not the mark


def _config(tmp_path, text):
    path = tmp_path / "run.yaml"
    path.write_text(text)
    return path


def test_a_marked_value_is_a_placeholder_until_edited_or_unmarked(tmp_path):
    text = template_text()
    path = _config(tmp_path, text)
    assert placeholders(path, load_config(path)) == CANTILEVER
    edited = text.replace("quality_factor: 150 ", "quality_factor: 250 ")  # the mark stays, the value changed
    path = _config(tmp_path, edited)
    assert placeholders(path, load_config(path)) == [k for k in CANTILEVER if k != "cantilever.quality_factor"]
    unmarked = re.sub(r"(spring_constant: 40\.0 .*); CHECK: template example", r"\1", edited)  # k = 40 is right
    path = _config(tmp_path, unmarked)
    assert placeholders(path, load_config(path)) == ["cantilever.resonance_frequency", "cantilever.tip_radius"]
    overrides = ["cantilever.resonance_frequency=2.9e5", "cantilever.tip_radius=8e-9"]
    refuse_placeholders(path, load_config(path, overrides))  # --set gives the values: nothing left


def test_the_refusal_is_one_line_naming_file_key_and_what_to_do(tmp_path):
    path = _config(tmp_path, template_text())
    with pytest.raises(ConfigError) as info:
        refuse_placeholders(path, load_config(path))
    err = info.value
    assert err.exit_code == 2 and err.file == str(path) and err.key == "cantilever.spring_constant"
    assert "\n" not in str(err)
    assert err.message.startswith("40.0 is the template's example, not a calibration")
    assert "(also cantilever.resonance_frequency, cantilever.quality_factor, cantilever.tip_radius)" in err.message
    assert "put your measured value, or delete the mark if this value is right" in err.message


def test_init_config_from_a_csv_then_fit_stops_until_the_calibration_is_given(tmp_path, run_cli):
    """The whole loop: a measured-like CSV, `init-config --from`, `fit` refused (exit 2, nothing written), the
    calibration completed (Q edited; k, f0 and R are the lever's values too: their marks deleted), `fit` runs."""
    config = short_dmt_viscoelastic_config(tmp_path)
    assert run_cli("-q", "simulate", config, "-o", tmp_path / "trace.h5")[0] == 0
    import h5py

    with h5py.File(tmp_path / "trace.h5", "r") as h5:
        deflection = h5["deflection"][()]
        rate = float(h5["deflection"].attrs.get("sample_rate", h5.attrs.get("sample_rate", np.nan)))
    assert np.isfinite(rate)
    time = np.arange(deflection.size) / rate
    np.savetxt(tmp_path / "measured.csv", np.c_[time, deflection * 1e9], delimiter=",",
               header="time_s,deflection_nm", comments="", fmt="%.12g")
    run = tmp_path / "run.yaml"
    code, _, err = run_cli("init-config", "--from", tmp_path / "measured.csv", "-o", run)
    assert code == 0, err
    assert marked_keys(run.read_text()) == CANTILEVER
    code, out, err = run_cli("fit", run, "-o", tmp_path / "run.h5")
    assert code == 2 and out == "" and not (tmp_path / "run.h5").exists()
    assert err.startswith(f"afmid: error: {run}: cantilever.spring_constant: 40.0 is the template's example")
    assert len(err.splitlines()) == 1
    text = run.read_text().replace("quality_factor: 150 ", "quality_factor: 250 ")
    text = re.sub(r"((spring_constant|resonance_frequency|tip_radius): .*); " + re.escape(MARK), r"\1", text)
    text = text.replace("effects: [dmt]", "effects: [dmt, viscoelastic]")
    run.write_text(text)
    assert yaml.safe_load(run.read_text())["cantilever"]["quality_factor"] == 250
    code, out, err = run_cli("-q", "fit", run, "-o", tmp_path / "run.h5")
    assert code == 0, err
    assert (tmp_path / "run.h5").exists()
