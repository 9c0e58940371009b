"""Bad input through the command line: one clear line, a non-zero exit, no traceback, no partial output.

Every case runs ``afmid fit CONFIG -o OUT`` in-process via :func:`afmid.cli.main`
and checks the whole contract: exit code 1 (input/output) or 2 (config),
exactly one stderr line ``afmid: error: <file>: <key.path>: <what was
expected>``, no 'Traceback', OUT not created and no ``.afmid-tmp-*`` left.
Loading and validation run before the fit, so these tests never fit anything.
"""

from __future__ import annotations

import errno
import re
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest

from afmid.errors import OutputError
from afmid.io.trace import atomic_hdf5, atomic_path


@pytest.fixture
def fit_cli(tmp_path, write_config, run_cli):
    """``fit_cli(config, *args)`` -> (config path, output path, exit code, stderr) of ``afmid fit``."""

    def run(config, *args, output="out.h5"):
        cfg = write_config(config)
        out = tmp_path / output
        code, _, err = run_cli("fit", cfg, "-o", out, *args)
        return cfg, out, code, err

    return run


@pytest.fixture
def refused(temp_leftovers):
    """``refused(code, err, out, exit_code, file, key, *fragments)`` -> the error line, after checking the contract."""

    def check(code, err, out, exit_code, file, key, *fragments):
        assert "Traceback" not in err
        lines = err.splitlines()
        assert len(lines) == 1, f"expected one line on stderr, got: {err!r}"
        line = lines[0]
        assert line.startswith("afmid: error: "), line
        head = f"afmid: error: {file}: " + (f"{key}: " if key else "")
        assert line.startswith(head), f"{line!r} should start with {head!r}"
        for fragment in fragments:
            assert fragment in line, f"{fragment!r} not in {line!r}"
        assert code == exit_code, line
        assert not Path(out).exists(), "no output on error"
        assert temp_leftovers(Path(out).parent) == []
        return line

    return check


# --------------------------------------------------------------------------- the data file
def test_missing_trace_file(tmp_path, fit_cli, refused, pinned_config):
    _, out, code, err = fit_cli(pinned_config("missing.csv"))
    refused(code, err, out, 1, tmp_path / "missing.csv", "data.path", "trace file not found")


def test_missing_data_path(tmp_path, fit_cli, refused):
    cfg, out, code, err = fit_cli({"cantilever": {"quality_factor": 150}})
    refused(code, err, out, 2, cfg, "data.path", "required key is missing")


@pytest.mark.parametrize("keep", [0.5, 0.01])
def test_truncated_hdf5(tmp_path, fit_cli, refused, pinned_config, make_trace, keep):
    from afmid.io.trace import write_trace_file

    full = write_trace_file(tmp_path / "full.h5", make_trace(periods=40), "")
    data = full.read_bytes()
    (tmp_path / "cut.h5").write_bytes(data[: int(len(data) * keep)])
    _, out, code, err = fit_cli({"data": {"path": "cut.h5"}})
    refused(code, err, out, 1, tmp_path / "cut.h5", "data.path", "not a readable HDF5 file (truncated or corrupt?)")


def test_garbage_with_an_hdf5_suffix(tmp_path, fit_cli, refused):
    (tmp_path / "trace.h5").write_text("time,deflection\n0,1\n")
    _, out, code, err = fit_cli({"data": {"path": "trace.h5"}})
    refused(code, err, out, 1, tmp_path / "trace.h5", "data.path", "not a readable HDF5 file")


def test_text_in_a_number_column(tmp_path, write_csv, fit_cli, refused, pinned_config):
    values = [1.0] * 700
    values[41] = "abc"
    write_csv(values=values)
    _, out, code, err = fit_cli(pinned_config())
    refused(code, err, out, 1, tmp_path / "trace.csv", "data.column",
            "column 'deflection_nm': 'abc', not a number at row 42 (line 43)")


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_nan_or_inf_samples(tmp_path, write_csv, fit_cli, refused, pinned_config, bad):
    values = [0.5] * 700
    values[5] = values[9] = bad
    write_csv(values=values)
    _, out, code, err = fit_cli(pinned_config())
    refused(code, err, out, 1, tmp_path / "trace.csv", "data.column",
            "2 NaN/inf samples in the deflection (first at sample 5)")


@pytest.mark.parametrize("content, message", [("deflection_nm\n", "no data rows, only a header"),
                                              ("", "no data rows (empty, or only comments)")])
def test_empty_trace(tmp_path, fit_cli, refused, pinned_config, content, message):
    (tmp_path / "trace.csv").write_text(content)
    cfg = pinned_config()
    cfg["data"]["time_column"] = None
    _, out, code, err = fit_cli(cfg)
    refused(code, err, out, 1, tmp_path / "trace.csv", "data.path", message)


def test_too_short_trace(tmp_path, write_csv, fit_cli, refused, pinned_config):
    write_csv(periods=2.5)
    _, out, code, err = fit_cli(pinned_config())
    refused(code, err, out, 1, tmp_path / "trace.csv", "data.path",
            "the trace is too short: 500 samples = 2.50 drive periods, need at least 3")


def test_unknown_column_suggests(tmp_path, write_csv, fit_cli, refused, pinned_config):
    write_csv()
    cfg = pinned_config()
    cfg["data"]["column"] = "deflecton_nm"
    _, out, code, err = fit_cli(cfg)
    refused(code, err, out, 1, tmp_path / "trace.csv", "data.column",
            "no channel 'deflecton_nm' (did you mean 'deflection_nm'?); available: time_s, deflection_nm")


def test_volts_without_invols(tmp_path, write_csv, fit_cli, refused, pinned_config):
    write_csv()
    cfg = pinned_config()
    cfg["data"]["units"] = "V"
    cfg_path, out, code, err = fit_cli(cfg)
    refused(code, err, out, 2, cfg_path, "data.invols", "units V needs data.invols (m/V)")


def test_sample_rate_contradicting_the_time_column(tmp_path, write_csv, fit_cli, refused, pinned_config):
    write_csv()
    cfg = pinned_config()
    cfg["data"]["sample_rate"] = 2e6
    cfg_path, out, code, err = fit_cli(cfg)
    refused(code, err, out, 2, cfg_path, "data.sample_rate", "contradicts the time column 'time_s'")


# --------------------------------------------------------------------------- the config
def test_negative_physical_constant_exact_line(tmp_path, monkeypatch, run_cli, refused, write_csv, pinned_config):
    import yaml

    write_csv("configs/trace.csv")
    cfg = pinned_config()
    cfg["cantilever"]["quality_factor"] = -3
    (tmp_path / "configs" / "x.yaml").write_text(yaml.safe_dump(cfg))
    monkeypatch.chdir(tmp_path)
    code, _, err = run_cli("fit", "configs/x.yaml", "-o", "out.h5")
    line = refused(code, err, tmp_path / "out.h5", 2, "configs/x.yaml", "cantilever.quality_factor")
    assert line == "afmid: error: configs/x.yaml: cantilever.quality_factor: must be > 0, got -3"


def test_unknown_key_with_did_you_mean_and_allowed_keys(fit_cli, refused, pinned_config):
    cfg = pinned_config()
    cfg["cantilever"]["qualty_factor"] = 3
    cfg_path, out, code, err = fit_cli(cfg)
    refused(code, err, out, 2, cfg_path, "cantilever.qualty_factor",
            "unknown key (did you mean 'quality_factor'?); "
            "allowed keys: spring_constant, resonance_frequency, quality_factor, tip_radius, tip_shape, tip_half_angle, "
            "spring_constant_uncertainty, quality_factor_uncertainty, higher_modes")


@pytest.mark.parametrize(
    "section, key, value, expected",
    [
        ("cantilever", "spring_constant", "stiff", "expected a number, got 'stiff'"),
        ("cantilever", "quality_factor", True, "expected a number, got True"),
        ("model", "effects", "dmt", "expected a list, got 'dmt'"),
        ("fit", "bootstrap", 2.5, "expected a whole number, got 2.5"),
        ("data", "positive", "up", "must be one of 'toward_sample' or 'away_from_sample', got 'up'"),
    ],
)
def test_wrong_type(fit_cli, refused, pinned_config, section, key, value, expected):
    cfg = pinned_config()
    cfg[section][key] = value
    cfg_path, out, code, err = fit_cli(cfg)
    line = refused(code, err, out, 2, cfg_path, f"{section}.{key}")
    assert line.endswith(f"{section}.{key}: {expected}")


def test_unknown_effect_suggests_the_closest(fit_cli, refused, pinned_config):
    cfg_path, out, code, err = fit_cli(pinned_config(model={"effects": ["dmt", "viscoelastc"]}))
    refused(code, err, out, 2, cfg_path, "model.effects",
            "unknown effect 'viscoelastc' (did you mean 'viscoelastic'?); allowed: dmt, ")


def test_invalid_yaml_syntax_gives_line_and_column(fit_cli, refused):
    cfg_path, out, code, err = fit_cli("data:\n  path: trace.csv\n  units: [nm\ncantilever: {}\n")
    line = refused(code, err, out, 2, cfg_path, None, "invalid YAML: line ")
    assert re.search(r"invalid YAML: line \d+, column \d+: ", line)


def test_key_given_twice(fit_cli, refused):
    cfg_path, out, code, err = fit_cli("cantilever:\n  quality_factor: 150\n  quality_factor: 250\n")
    refused(code, err, out, 2, cfg_path, None, "line 3, column 3: key 'quality_factor' is given twice")


@pytest.mark.parametrize("text, kind", [("- data\n- fit\n", "list"), ("run.csv\n", "str")])
def test_config_that_is_not_a_mapping(fit_cli, refused, text, kind):
    cfg_path, out, code, err = fit_cli(text)
    refused(code, err, out, 2, cfg_path, None, f"expected a mapping of sections at the top level, got {kind}")


def test_config_not_found_or_a_folder(tmp_path, run_cli, refused):
    code, _, err = run_cli("fit", tmp_path / "nope.yaml", "-o", tmp_path / "out.h5")
    refused(code, err, tmp_path / "out.h5", 2, tmp_path / "nope.yaml", None, "config file not found")
    code, _, err = run_cli("fit", tmp_path, "-o", tmp_path / "out.h5")
    refused(code, err, tmp_path / "out.h5", 2, tmp_path, None, "is a directory")


# --------------------------------------------------------------------------- --set and --add
@pytest.mark.parametrize(
    "override, message",
    [
        ("cantilever.quality_factor", "--set expects KEY.PATH=VALUE, got 'cantilever.quality_factor'"),
        ("=3", "--set expects KEY.PATH=VALUE, got '=3'"),
        ("model.effects=[dmt", "--set model.effects: the value '[dmt' is not valid YAML"),
    ],
)
def test_malformed_set(write_csv, fit_cli, refused, pinned_config, override, message):
    write_csv()
    _, out, code, err = fit_cli(pinned_config(), "--set", override)
    refused(code, err, out, 2, "--set", None, message)


@pytest.mark.parametrize(
    "override, key, message",
    [
        ("cantilever.quality_factor=-3", "cantilever.quality_factor", "must be > 0, got -3"),
        ("cantilever.quality_factor=high", "cantilever.quality_factor", "expected a number, got 'high'"),
        ("cantilevr.quality_factor=3", "cantilevr", "unknown key (did you mean 'cantilever'?)"),
        ("model.effects=[viscoelastc]", "model.effects", "(did you mean 'viscoelastic'?)"),
    ],
)
def test_set_with_a_bad_value(write_csv, fit_cli, refused, pinned_config, override, key, message):
    write_csv()
    cfg_path, out, code, err = fit_cli(pinned_config(), "--set", override)
    refused(code, err, out, 2, cfg_path, key, message)


def test_add_unknown_effect(write_csv, fit_cli, refused, pinned_config):
    write_csv()
    cfg_path, out, code, err = fit_cli(pinned_config(), "--add", "viscoelastc")
    refused(code, err, out, 2, cfg_path, "model.effects",
            "--add: unknown effect 'viscoelastc' (did you mean 'viscoelastic'?)")


def test_remove_effect_not_in_the_model(write_csv, fit_cli, refused, pinned_config):
    write_csv()
    cfg_path, out, code, err = fit_cli(pinned_config(), "--remove", "jkr")
    refused(code, err, out, 2, cfg_path, "model.effects", "--remove jkr: not in model.effects ['dmt']")


# --------------------------------------------------------------------------- outputs
def test_existing_output_is_refused_and_kept(tmp_path, write_csv, fit_cli, refused, pinned_config, temp_leftovers):
    write_csv()
    (tmp_path / "out.h5").write_bytes(b"previous run")
    _, out, code, err = fit_cli(pinned_config())
    assert code == 1 and "Traceback" not in err
    assert err == f"afmid: error: {out}: output exists; pass --overwrite to replace it\n"
    assert out.read_bytes() == b"previous run"
    assert temp_leftovers(tmp_path) == []


def test_overwrite_with_bad_input_keeps_the_previous_output(tmp_path, fit_cli, pinned_config, temp_leftovers):
    (tmp_path / "out.h5").write_bytes(b"previous run")
    _, out, code, err = fit_cli(pinned_config("missing.csv"), "--overwrite")
    assert code == 1 and err.startswith("afmid: error: ") and "trace file not found" in err
    assert out.read_bytes() == b"previous run"
    assert temp_leftovers(tmp_path) == []


def test_output_folder_missing(tmp_path, write_csv, fit_cli, refused, pinned_config):
    write_csv()
    _, out, code, err = fit_cli(pinned_config(), output="no/such/out.h5")
    refused(code, err, out, 1, out, None, "output folder")


def test_unwritable_output_folder_is_an_output_error(tmp_path, monkeypatch, run_cli, refused):
    def denied(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(tempfile, "mkstemp", denied)
    with pytest.raises(OutputError, match="cannot write in folder .*: Permission denied"):
        with atomic_path(tmp_path / "x.h5"):
            pass  # pragma: no cover
    code, _, err = run_cli("init-config", "-o", tmp_path / "run.yaml")
    refused(code, err, tmp_path / "run.yaml", 1, tmp_path / "run.yaml", None, "Permission denied")


def test_an_interrupted_write_leaves_nothing(tmp_path, temp_leftovers):
    target = tmp_path / "run.h5"
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_hdf5(target, "afmid-run", "config: {}\n", {"in.csv": "0" * 64}) as h5:
            h5.create_dataset("half", data=np.zeros(10))
            assert temp_leftovers(tmp_path)  # written beside the target meanwhile
            raise RuntimeError("boom")
    assert not target.exists() and temp_leftovers(tmp_path) == []
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_text("partial")
            raise KeyboardInterrupt
    assert not target.exists() and temp_leftovers(tmp_path) == []


def test_a_completed_write_appears_atomically(tmp_path, temp_leftovers):
    target = tmp_path / "run.h5"
    with atomic_hdf5(target, "afmid-run", "config: {}\n", {"in.csv": "0" * 64}) as h5:
        h5["x"] = 1.0
        assert not target.exists()
    with h5py.File(target, "r") as h5:
        assert h5.attrs["format"] == "afmid-run" and h5.attrs["input_sha256"] == "0" * 64
    assert temp_leftovers(tmp_path) == []


# --------------------------------------------------------------------------- verbosity
def test_verbose_adds_the_traceback(tmp_path, fit_cli, run_cli, pinned_config):
    cfg, out, code, err = fit_cli(pinned_config("missing.csv"))
    assert code == 1 and "Traceback" not in err
    code, _, err = run_cli("-v", "fit", cfg, "-o", out)
    assert code == 1
    assert "Traceback" in err and "InputError" in err
    assert err.rstrip().splitlines()[-1] == f"afmid: error: {tmp_path / 'missing.csv'}: data.path: trace file not found"
    assert not out.exists()
