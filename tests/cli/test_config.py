"""Run configs: schema, layering, error messages, the template, and how a config meets the data.

Covers the foundation contract of afmid.config and afmid.io.trace.load_trace:
defaults < YAML < --set; paths relative to the config file; every error one
line ``file: key.path: what was expected``; the pinned CSV form and afmid
trace files loading to SI metres, positive toward the sample; the trace file
layout on disk.
"""

from __future__ import annotations

import datetime as dt
import logging
import re
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from afmid.config import RunConfig, build_config, dump_config, load_config, parse_override, read_yaml, template_text
from afmid.errors import AfmidError, ConfigError, InputError
from afmid.io.trace import FORMAT_VERSION, TRACE_FORMAT, load_trace, write_trace_file
from afmid.physics.effects import EFFECTS
from repo_paths import REPO_ROOT

ROOT = REPO_ROOT


def config_error(raw: dict, source="configs/x.yaml") -> ConfigError:
    with pytest.raises(ConfigError) as info:
        build_config(raw, source=Path(source))
    return info.value


# --------------------------------------------------------------------------- layering
def test_defaults_are_the_schema_defaults():
    cfg = build_config({})
    assert cfg.data.path is None and cfg.data.positive == "toward_sample" and cfg.data.offset == 0.0
    assert cfg.sample.a0 == pytest.approx(0.165e-9)
    assert cfg.model.effects == ["dmt"]
    assert cfg.fit.bootstrap == 100 and cfg.fit.max_harmonic == 60
    assert cfg.cantilever.quality_factor is None


def test_yaml_overrides_defaults_and_set_overrides_yaml(write_config):
    path = write_config({"cantilever": {"quality_factor": 150, "spring_constant": 40.0}, "fit": {"bootstrap": 50}})
    cfg = load_config(path)
    assert cfg.cantilever.quality_factor == 150 and cfg.fit.bootstrap == 50 and cfg.fit.folds == 5

    cfg = load_config(
        path,
        [
            "cantilever.quality_factor=200",  # YAML value replaced
            "fit.seed=7",  # default replaced, section present in YAML
            "drive.frequency=3e5",  # section absent from the YAML is created
            "model.effects=[dmt, viscoelastic]",  # values are parsed as YAML
            "sample.separation=8e-9",  # YAML 1.1 reads 8e-9 as text; the schema takes it as a number
        ],
    )
    assert cfg.cantilever.quality_factor == 200
    assert cfg.cantilever.spring_constant == 40.0  # the rest of the YAML section is kept
    assert cfg.fit.bootstrap == 50 and cfg.fit.seed == 7 and cfg.fit.folds == 5
    assert cfg.drive.frequency == 3e5
    assert cfg.model.effects == ["dmt", "viscoelastic"]
    assert cfg.sample.separation == pytest.approx(8e-9)


def test_later_set_wins_and_set_is_validated_like_yaml(write_config):
    path = write_config({"cantilever": {"quality_factor": 150}})
    cfg = load_config(path, ["cantilever.quality_factor=200", "cantilever.quality_factor=250"])
    assert cfg.cantilever.quality_factor == 250
    with pytest.raises(ConfigError) as info:
        load_config(path, ["cantilever.quality_factor=-3"])
    assert info.value.format() == f"{path}: cantilever.quality_factor: must be > 0, got -3"
    with pytest.raises(ConfigError) as info:
        load_config(path, ["cantilevr.quality_factor=3"])
    assert "cantilevr: unknown key (did you mean 'cantilever'?)" in info.value.format()


def test_parse_override():
    assert parse_override("cantilever.quality_factor=150") == (["cantilever", "quality_factor"], 150)
    assert parse_override("data.column=deflection [nm]") == (["data", "column"], "deflection [nm]")
    assert parse_override("data.sample_rate=") == (["data", "sample_rate"], None)
    assert parse_override("data.path=a=b.csv") == (["data", "path"], "a=b.csv")  # split at the first '='
    assert parse_override(" model.effects = [dmt] ") == (["model", "effects"], ["dmt"])


@pytest.mark.parametrize("text", ["cantilever.quality_factor", "=3", "...=3", "cantilever.quality_factor=[1", "x={a"])
def test_malformed_set_is_a_config_error(text):
    with pytest.raises(ConfigError) as info:
        parse_override(text)
    err = info.value
    assert err.key == "--set" and err.exit_code == 2
    assert "\n" not in err.format()
    assert repr(text.split("=", 1)[-1]) in err.message or repr(text) in err.message


def test_paths_are_relative_to_the_config_file(tmp_path, monkeypatch, write_csv, write_config, pinned_config):
    write_csv("sub/trace.csv")
    cfg_path = write_config(pinned_config("trace.csv"), name="sub/run.yaml")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    cfg = load_config(cfg_path)
    assert cfg.source == cfg_path
    assert cfg.resolve_path(cfg.data.path) == tmp_path / "sub" / "trace.csv"
    trace = load_trace(cfg)
    assert trace.path == tmp_path / "sub" / "trace.csv"

    # --set paths are relative to the config file too; absolute paths are kept.
    write_csv("sub/data/other.csv")
    assert load_trace(load_config(cfg_path, ["data.path=data/other.csv"])).path == tmp_path / "sub/data/other.csv"
    absolute = tmp_path / "sub" / "data" / "other.csv"
    cfg = load_config(cfg_path, [f"data.path={absolute}"])
    assert cfg.resolve_path(cfg.data.path) == absolute

    # A relative config path given on the command line: relative to the cwd, then to the config.
    monkeypatch.chdir(tmp_path)
    assert load_trace(load_config(Path("sub/run.yaml"))).path == Path("sub/trace.csv")


def test_dump_config_round_trips_through_build_config(pinned_config):
    raw = pinned_config(
        "data/trace.csv",
        model={"effects": ["dmt", "viscoelastic"], "parameters": {"decay_length": 1e-9}},
        fit={"bootstrap": 7, "separation_window": [5e-9, 2e-9], "thresholds": [0.01, 0.1]},
        simulate={"model": "dmt", "noise": {"detector_rms": 1e-12}, "setpoint": 0.9},
    )
    cfg = build_config(raw)
    text = dump_config(cfg)
    again = build_config(yaml.safe_load(text))
    assert again.model_dump() == cfg.model_dump()
    assert dump_config(again) == text
    assert again.data.path == Path("data/trace.csv")
    # The dump is complete: every section and key of the schema is spelled out.
    dumped = yaml.safe_load(text)
    assert set(dumped) == set(RunConfig.model_fields)
    assert set(dumped["fit"]) == set(type(cfg.fit).model_fields)


@pytest.mark.parametrize("name", sorted(p.name for p in (ROOT / "configs").glob("*.yaml")))
def test_shipped_configs_validate(name):
    cfg = load_config(ROOT / "configs" / name)
    assert cfg.cantilever.spring_constant > 0


# --------------------------------------------------------------------------- error messages
def test_negative_constant_exact_shape(tmp_path, monkeypatch):
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "x.yaml").write_text("cantilever:\n  quality_factor: -3\n")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError) as info:
        load_config("configs/x.yaml")
    assert str(info.value) == "configs/x.yaml: cantilever.quality_factor: must be > 0, got -3"
    assert info.value.exit_code == 2


@pytest.mark.parametrize(
    "section, key, value, expected",
    [
        ("cantilever", "spring_constant", -40.0, "must be > 0, got -40.0"),
        ("cantilever", "resonance_frequency", 0, "must be > 0, got 0"),
        ("cantilever", "tip_radius", -1e-8, "must be > 0, got -1e-08"),
        ("drive", "frequency", -3e5, "must be > 0, got -300000.0"),
        ("sample", "a0", -1.65e-10, "must be > 0, got -1.65e-10"),
        ("data", "sample_rate", -6e7, "must be > 0, got -60000000.0"),
        ("fit", "bootstrap", -1, "must be >= 0, got -1"),
        ("simulate", "setpoint", 1.5, "must be < 1, got 1.5"),
        ("simulate", "settle_tolerance", 0, "must be > 0, got 0"),
    ],
)
def test_out_of_range_values(section, key, value, expected):
    err = config_error({section: {key: value}})
    assert err.format() == f"configs/x.yaml: {section}.{key}: {expected}"


@pytest.mark.parametrize(
    "raw, key, expected",
    [
        ({"cantilever": {"quality_factor": "abc"}}, "cantilever.quality_factor", "expected a number, got 'abc'"),
        ({"cantilever": {"spring_constant": True}}, "cantilever.spring_constant", "expected a number, got True"),
        ({"model": {"effects": "dmt"}}, "model.effects", "expected a list, got 'dmt'"),
        ({"model": {"effects": [3]}}, "model.effects.0", "expected a string, got 3"),
        ({"fit": {"bootstrap": 1.5}}, "fit.bootstrap", "expected a whole number, got 1.5"),
        ({"fit": {"thermal_noise": "maybe"}}, "fit.thermal_noise", "expected true or false, got 'maybe'"),
        ({"data": {"column": [1]}}, "data.column", "expected a string or a whole number, got [1]"),
        ({"data": {"path": 3}}, "data.path", "expected a file path, got 3"),
        ({"data": 3}, "data", "expected a mapping of keys, got 3"),
        ({"model": {"parameters": [1]}}, "model.parameters", "expected a mapping of keys, got [1]"),
        ({"data": {"units": "furlong"}}, "data.units",
         "must be one of 'm', 'nm', 'pm', 'um', 'V' or 'raw', got 'furlong'"),
        ({"cantilever": {"quality_factor": float("inf")}}, "cantilever.quality_factor",
         "must be a finite number, got inf"),
        ({"model": {"parameters": {"decay": float("nan")}}}, "model.parameters.decay",
         "must be a finite number, got nan"),
        ({"fit": {"separation_window": [1e-9]}}, "fit.separation_window",
         "expected [below, above] in metres, got [1e-09]"),
    ],
)
def test_wrong_types(raw, key, expected):
    err = config_error(raw)
    assert (err.file, err.key, err.message) == ("configs/x.yaml", key, expected)


@pytest.mark.parametrize(
    "raw, key, hint, allowed",
    [
        ({"cantilever": {"qualty_factor": 3}}, "cantilever.qualty_factor", "quality_factor",
         "spring_constant, resonance_frequency, quality_factor, tip_radius, tip_shape, tip_half_angle, "
         "spring_constant_uncertainty, "
         "quality_factor_uncertainty, higher_modes"),
        ({"datum": {}}, "datum", "data", "data, cantilever, drive, sample, model, fit, simulate, coverage"),
        ({"simulate": {"noise": {"temprature": 300}}}, "simulate.noise.temprature", "temperature",
         "detector_rms, detector_density, thermal, temperature, adc_step"),
    ],
)
def test_unknown_keys_suggest_and_list_allowed(raw, key, hint, allowed):
    err = config_error(raw)
    assert err.key == key
    assert err.message == f"unknown key (did you mean {hint!r}?); allowed keys: {allowed}"


def test_unknown_key_without_a_close_match_still_lists_allowed():
    err = config_error({"model": {"zzzz": 1}})
    assert err.format() == "configs/x.yaml: model.zzzz: unknown key; allowed keys: effects, library, terms, parameters"


@pytest.mark.parametrize("section", ["model", "simulate"])
def test_unknown_effect_suggests_the_closest(section):
    err = config_error({section: {"effects": ["dmt", "viscoelastc"]}})
    assert err.key == f"{section}.effects"
    assert err.message.startswith("unknown effect 'viscoelastc' (did you mean 'viscoelastic'?); allowed: ")
    assert err.message.split("allowed: ")[1].split(", ") == EFFECTS.names()


def test_effect_listed_twice():
    err = config_error({"model": {"effects": ["dmt", "dmt"]}})
    assert err.key == "model.effects" and "listed twice" in err.message


def test_several_errors_are_one_line_with_a_count():
    err = config_error({"data": {"sample_rate": -1, "units": "x"}, "fit": {"folds": 1}})
    text = err.format()
    assert "\n" not in text
    assert text.startswith("configs/x.yaml: data.sample_rate: must be > 0, got -1 (and 2 more: ")
    assert "data.units: must be one of" in text and "fit.folds: must be >= 2, got 1" in text


# --------------------------------------------------------------------------- YAML files
def test_invalid_yaml_names_line_and_column(write_config):
    path = write_config("data:\n  path: trace.csv\n  column: [deflection\nfit: {}\n")
    with pytest.raises(ConfigError) as info:
        read_yaml(path)
    assert re.fullmatch(rf"{re.escape(str(path))}: invalid YAML: line \d+, column \d+: .+", info.value.format())
    path = write_config("data:\n path: a\n  column: b\n")
    with pytest.raises(ConfigError, match=r"invalid YAML: line 3, column 9: mapping values are not allowed"):
        read_yaml(path)


def test_a_key_given_twice_is_an_error(write_config):
    path = write_config("cantilever:\n  quality_factor: 150\n  spring_constant: 40\n  quality_factor: 250\n")
    with pytest.raises(ConfigError) as info:
        read_yaml(path)
    assert info.value.format() == (
        f"{path}: invalid YAML: line 4, column 3: key 'quality_factor' is given twice in the same section"
    )


def test_yaml_anchors_and_merge_keys_still_work(write_config):
    path = write_config("a: &lever {spring_constant: 40}\ncantilever:\n  <<: *lever\n  quality_factor: 150\n")
    raw = read_yaml(path)
    assert raw["cantilever"] == {"spring_constant": 40, "quality_factor": 150}


@pytest.mark.parametrize("text, kind", [("- data\n- fit\n", "list"), ("just text\n", "str"), ("3\n", "int")])
def test_config_that_is_not_a_mapping(write_config, text, kind):
    path = write_config(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert info.value.format() == f"{path}: expected a mapping of sections at the top level, got {kind}"


def test_empty_config_is_all_defaults(write_config):
    assert load_config(write_config("# nothing yet\n")).model_dump() == RunConfig().model_dump()


def test_missing_folder_and_binary_config(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="is a directory"):
        load_config(tmp_path)
    (tmp_path / "bin.yaml").write_bytes(b"\xff\xfe\x00\x81binary")
    with pytest.raises(ConfigError, match="not a text file"):
        load_config(tmp_path / "bin.yaml")


# --------------------------------------------------------------------------- template
PINNED_KEYS = {
    "data": {"path", "format", "column", "time_column", "sample_rate", "units", "positive"},
    "cantilever": {"spring_constant", "resonance_frequency", "quality_factor", "tip_radius"},
    "drive": {"frequency"},
    "sample": {"a0"},
    "model": {"effects"},
}


def test_template_parses_and_has_the_pinned_keys():
    text = template_text()
    raw = yaml.safe_load(text)
    assert isinstance(raw, dict)
    for section, keys in PINNED_KEYS.items():
        assert keys <= set(raw[section]), section
    assert "fit" in raw
    # Documented but commented out: estimated by the fit / only for units V.
    assert re.search(r"^\s*#\s*separation:", text, re.M)
    assert re.search(r"^\s*#\s*invols:", text, re.M)
    assert "separation" not in raw["sample"]
    build_config(raw)  # valid as it stands (no file is read at validation)


def test_template_validates_and_loads_a_real_csv(tmp_path, run_cli, write_csv):
    code, _, err = run_cli("init-config", "-o", tmp_path / "run.yaml")
    assert code == 0, err
    assert (tmp_path / "run.yaml").read_text() == template_text()
    write_csv("my_trace.csv")
    text = (tmp_path / "run.yaml").read_text().replace("path: trace.csv", "path: my_trace.csv", 1)
    (tmp_path / "run.yaml").write_text(text)
    cfg = load_config(tmp_path / "run.yaml")
    trace = load_trace(cfg)
    assert trace.n_samples == 2000 and trace.sample_rate == 6e7 and trace.drive_frequency == 3e5
    assert trace.cantilever.quality_factor == 150 and trace.cantilever.tip_radius == pytest.approx(10e-9)
    assert np.max(trace.deflection) == pytest.approx(5e-9, rel=1e-3)


def test_init_config_to_stdout_and_refusing_to_overwrite(tmp_path, run_cli):
    code, out, _ = run_cli("init-config")
    assert code == 0 and out == template_text()
    target = tmp_path / "run.yaml"
    target.write_text("mine\n")
    code, _, err = run_cli("init-config", "-o", target)
    assert code == 1
    assert err == f"afmid: error: {target}: output exists; pass --overwrite to replace it\n"
    assert target.read_text() == "mine\n"
    assert run_cli("init-config", "-o", target, "--overwrite")[0] == 0
    assert target.read_text() == template_text()


# --------------------------------------------------------------------------- the pinned CSV form
def load(write_config, config: dict):
    return load_trace(load_config(write_config(config)))


def test_pinned_csv_loads_to_si_metres_toward_the_sample(write_csv, write_config, pinned_config):
    write_csv()
    trace = load(write_config, pinned_config())
    t = np.arange(2000) / 6e7
    np.testing.assert_allclose(trace.deflection, 5e-9 * np.sin(2 * np.pi * 3e5 * t), rtol=0, atol=1e-20)
    np.testing.assert_allclose(trace.times, t, rtol=0, atol=1e-18)
    assert trace.sample_rate == 6e7 and trace.drive_frequency == 3e5
    assert trace.samples_per_period == pytest.approx(200) and trace.n_periods == pytest.approx(10)
    assert trace.cantilever.spring_constant == 40.0
    assert trace.cantilever.mass == pytest.approx(40 / (2 * np.pi * 3e5) ** 2)
    assert trace.sha256 and len(trace.sha256) == 64
    assert trace.overridden == []
    assert trace.sources["units"] == "config:data.units"
    assert trace.sources["quality_factor"] == "config:cantilever.quality_factor"


def test_units_from_the_column_name_when_the_config_does_not_say(write_csv, write_config, pinned_config):
    write_csv()
    cfg = pinned_config()
    del cfg["data"]["units"]
    trace = load(write_config, cfg)
    assert np.max(trace.deflection) == pytest.approx(5e-9, rel=1e-3)
    assert trace.sources["units"].startswith("file:")


def test_positive_away_from_sample_flips_the_sign(write_csv, write_config, pinned_config):
    write_csv()
    toward = load(write_config, pinned_config())
    cfg = pinned_config()
    cfg["data"]["positive"] = "away_from_sample"
    away = load(write_config, cfg)
    np.testing.assert_array_equal(away.deflection, -toward.deflection)
    assert np.any(toward.deflection != 0)


@pytest.mark.parametrize("units, scale", [("m", 1.0), ("nm", 1e-9), ("pm", 1e-12), ("um", 1e-6)])
def test_length_units_scale(write_csv, write_config, pinned_config, units, scale):
    write_csv(values=[1.0, -2.0, 3.0] * 200)
    cfg = pinned_config()
    cfg["data"]["units"] = units
    trace = load(write_config, cfg)
    np.testing.assert_allclose(trace.deflection[:3], np.array([1.0, -2.0, 3.0]) * scale, rtol=1e-15)
    assert trace.overridden == ([] if units == "nm" else ["data.units"])  # the column name says nm


def test_offset_is_removed_in_file_units_before_scaling(write_csv, write_config, pinned_config):
    write_csv(values=[11.0, 9.0, 10.0] * 200)
    cfg = pinned_config()
    cfg["data"]["offset"] = 10.0
    trace = load(write_config, cfg)
    np.testing.assert_allclose(trace.deflection[:3], [1e-9, -1e-9, 0.0], atol=1e-24)


def test_volts_with_invols(write_csv, write_config, pinned_config):
    write_csv(values=[0.1, -0.2, 0.05] * 200)
    cfg = pinned_config()
    cfg["data"].update(units="V", invols=50e-9)
    trace = load(write_config, cfg)
    np.testing.assert_allclose(trace.deflection[:3], [5e-9, -10e-9, 2.5e-9], rtol=1e-12)
    cfg["data"]["positive"] = "away_from_sample"
    np.testing.assert_allclose(load(write_config, cfg).deflection[:3], [-5e-9, 10e-9, -2.5e-9], rtol=1e-12)


def test_volts_without_invols_names_data_invols(write_csv, write_config, pinned_config):
    write_csv()
    cfg = pinned_config()
    cfg["data"]["units"] = "V"
    path = write_config(cfg)
    with pytest.raises(ConfigError) as info:
        load_trace(load_config(path))
    assert (info.value.file, info.value.key) == (str(path), "data.invols")
    assert "units V needs data.invols" in info.value.message


def test_raw_without_scale_and_no_units_at_all(write_csv, write_config, pinned_config):
    write_csv(time=False)
    cfg = pinned_config()
    cfg["data"].update(units="raw", time_column=None)
    with pytest.raises(ConfigError) as info:
        load(write_config, cfg)
    assert info.value.key == "data.scale"
    (Path(write_config(cfg)).parent / "plain.csv").write_text("signal\n" + "1.0\n" * 600)
    cfg["data"].update(path="plain.csv", units=None, column="signal")
    with pytest.raises(ConfigError) as info:
        load(write_config, cfg)
    assert info.value.key == "data.units"


def test_sample_rate_from_the_time_column_and_contradictions(write_csv, write_config, pinned_config):
    write_csv()
    cfg = pinned_config()
    cfg["data"]["sample_rate"] = None
    trace = load(write_config, cfg)
    assert trace.sample_rate == pytest.approx(6e7, rel=1e-9)
    assert trace.sources["sample_rate"].startswith("derived:")
    # A stated rate that contradicts the time column would make the fit mix two time bases.
    cfg["data"]["sample_rate"] = 2e6
    with pytest.raises(ConfigError) as info:
        load(write_config, cfg)
    assert info.value.key == "data.sample_rate" and "contradicts the time column" in info.value.message
    # Without a time column and a rate, nothing says how far apart the samples are.
    cfg["data"].update(sample_rate=None, time_column=None)
    with pytest.raises(ConfigError) as info:
        load(write_config, cfg)
    assert info.value.key == "data.sample_rate"


def test_missing_cantilever_value_for_a_csv(write_csv, write_config, pinned_config):
    write_csv()
    cfg = pinned_config()
    del cfg["cantilever"]["quality_factor"]
    path = write_config(cfg)
    with pytest.raises(ConfigError) as info:
        load_trace(load_config(path))
    assert (info.value.file, info.value.key) == (str(path), "cantilever.quality_factor")


def test_low_sample_rate_is_a_warning_not_an_error(write_csv, write_config, pinned_config, caplog):
    write_csv(samples_per_period=10, periods=6)
    cfg = pinned_config()
    cfg["data"]["sample_rate"] = 3e6
    with caplog.at_level(logging.WARNING, logger="afmid"):
        trace = load(write_config, cfg)
    assert trace.samples_per_period == pytest.approx(10)
    warnings = [r for r in caplog.records
                if r.levelno == logging.WARNING and "samples per drive period" in r.getMessage()]
    assert len(warnings) == 1
    assert "only 10.0 samples per drive period (< 20)" in warnings[0].getMessage()
    assert str(trace.path) in warnings[0].getMessage()
    # At 20 samples per period there is nothing to warn about.
    caplog.clear()
    write_csv(samples_per_period=20, periods=6)
    cfg["data"]["sample_rate"] = 6e6
    with caplog.at_level(logging.WARNING, logger="afmid"):
        load(write_config, cfg)
    assert not [r for r in caplog.records if "samples per drive period" in r.getMessage()]


# --------------------------------------------------------------------------- afmid trace files
def test_trace_file_loads_without_cantilever_or_drive_sections(tmp_path, make_trace, write_config):
    original = make_trace()
    write_trace_file(tmp_path / "sim.h5", original, dump_config(RunConfig()))
    trace = load_trace(load_config(write_config({"data": {"path": "sim.h5"}})))
    np.testing.assert_array_equal(trace.deflection, original.deflection)
    assert trace.sample_rate == original.sample_rate and trace.drive_frequency == original.drive_frequency
    assert trace.cantilever == original.cantilever
    assert trace.drive_force_amplitude == original.drive_force_amplitude
    assert trace.overridden == []
    assert {trace.sources[k] for k in ("spring_constant", "quality_factor", "frequency")} == {"file"}
    assert trace.truth is not None and trace.truth.model == "dmt" and trace.truth.effects == ["dmt"]
    np.testing.assert_array_equal(trace.truth.force, original.truth.force)
    np.testing.assert_array_equal(trace.truth.separation, original.truth.separation)
    assert trace.truth.parameters == original.truth.parameters and trace.truth.units == original.truth.units


def test_config_values_override_the_trace_file_and_are_recorded(tmp_path, make_trace, write_config):
    write_trace_file(tmp_path / "sim.h5", make_trace(), dump_config(RunConfig()))
    cfg = {
        "data": {"path": "sim.h5", "sample_rate": 5.9e7},
        "cantilever": {"quality_factor": 100, "spring_constant": 40.0},  # k equals the file's: not an override
        "drive": {"frequency": 3.01e5, "force_amplitude": 3e-10},
    }
    trace = load_trace(load_config(write_config(cfg)))
    assert trace.cantilever.quality_factor == 100 and trace.cantilever.resonance_frequency == 3e5
    assert trace.drive_frequency == 3.01e5 and trace.sample_rate == 5.9e7 and trace.drive_force_amplitude == 3e-10
    assert sorted(trace.overridden) == sorted(
        ["data.sample_rate", "cantilever.quality_factor", "drive.frequency", "drive.force_amplitude"]
    )
    assert trace.sources["quality_factor"] == "config:cantilever.quality_factor"
    assert trace.sources["resonance_frequency"] == "file"


def test_trace_file_without_truth_or_tip_radius(tmp_path, make_trace, write_config):
    original = make_trace(with_truth=False)
    original.cantilever.tip_radius = None
    write_trace_file(tmp_path / "sim.h5", original, "")
    trace = load_trace(load_config(write_config({"data": {"path": "sim.h5"}})))
    assert trace.truth is None and trace.cantilever.tip_radius is None


def test_trace_file_layout(tmp_path, make_trace):
    path = write_trace_file(tmp_path / "sim.h5", make_trace(), "data: {}\n")
    with h5py.File(path, "r") as h5:
        root = h5.attrs
        assert root["format"] == TRACE_FORMAT == "afmid-trace"
        assert root["format_version"] == FORMAT_VERSION
        assert isinstance(root["afmid_version"], str) and root["afmid_version"]
        created = dt.datetime.fromisoformat(root["created"])
        assert created.utcoffset() is not None  # ISO 8601 with a zone offset
        assert re.search(r"[+-]\d\d:\d\d$", root["created"])
        assert root["config"] == "data: {}\n"
        assert root["sample_rate"] == 6e7

        assert h5["deflection"].attrs["units"] == "m" and h5["deflection"].attrs["positive"] == "toward_sample"
        assert h5["deflection"].shape == (2000,) and h5["deflection"].dtype == np.float64
        assert h5["time"].attrs["units"] == "s"
        cl = h5["cantilever"].attrs
        assert (cl["spring_constant"], cl["resonance_frequency"], cl["quality_factor"]) == (40.0, 3e5, 150.0)
        assert cl["tip_radius"] == 10e-9
        assert all(isinstance(cl[k], np.floating) for k in ("spring_constant", "resonance_frequency", "quality_factor"))
        assert "spring_constant: N/m" in cl["units"]
        assert h5["drive"].attrs["frequency"] == 3e5 and h5["drive"].attrs["force_amplitude"] == 2e-10
        assert "frequency: Hz" in h5["drive"].attrs["units"]
        assert h5["truth/force"].attrs["units"] == "N" and h5["truth/force"].attrs["positive"] == "repulsive"
        assert h5["truth/separation"].attrs["units"] == "m"
        assert h5["truth/velocity"].attrs["units"] == "m/s"
        assert h5["truth"].attrs["model"] == "dmt"
        assert h5["truth/parameters"].attrs["E_star"] == 2e9
        assert h5["truth/parameters"].attrs["units"] == "E_star: Pa; hamaker: J"

        datasets = []
        h5.visititems(lambda name, obj: datasets.append(name) if isinstance(obj, h5py.Dataset) else None)
        assert set(datasets) >= {"deflection", "time", "truth/force", "truth/separation", "truth/velocity"}
        missing = [name for name in datasets if "units" not in h5[name].attrs]
        assert missing == [], "every dataset needs a units attribute"


def test_trace_file_records_its_input(tmp_path, make_trace, write_csv):
    trace = make_trace()
    trace.path = write_csv()
    trace.sha256 = "ab" * 32
    path = write_trace_file(tmp_path / "out.h5", trace, "")
    with h5py.File(path, "r") as h5:
        assert Path(h5.attrs["input_path"]).resolve() == trace.path.resolve()
        assert h5.attrs["input_sha256"] == "ab" * 32


def test_file_formats_doc_names_every_trace_file_path(tmp_path, make_trace):
    doc = (ROOT / "docs" / "file-formats.md").read_text()
    trace = make_trace()
    trace.path, trace.sha256 = tmp_path / "in.csv", "0" * 64
    path = write_trace_file(tmp_path / "sim.h5", trace, "")
    # Parameter names and simulator extras depend on the model; every other attribute is fixed.
    variable = set(trace.truth.parameters) | set(trace.truth.extra) | {"units"}
    with h5py.File(path, "r") as h5:
        names = []
        h5.visititems(lambda name, obj: names.append(name))
        attrs = set(h5.attrs) | {a for n in names for a in h5[n].attrs}
    for name in names:
        assert f"/{name}" in doc, f"docs/file-formats.md does not describe /{name}"
    for attr in sorted(attrs - variable):
        assert f"`{attr}`" in doc, f"docs/file-formats.md does not describe the attribute {attr}"


def test_errors_are_afmid_errors_with_exit_codes():
    assert issubclass(ConfigError, AfmidError) and ConfigError.exit_code == 2
    assert issubclass(InputError, AfmidError) and InputError.exit_code == 1
    err = ConfigError("must be > 0, got -3", file=Path("configs/x.yaml"), key="cantilever.quality_factor")
    assert str(err) == err.format() == "configs/x.yaml: cantilever.quality_factor: must be > 0, got -3"
    assert ConfigError("bad").format() == "bad"


def test_init_config_simulate_writes_a_commented_simulate_section_that_runs(tmp_path, run_cli):
    """`init-config --simulate`: the template plus a commented simulate section whose every documented key is
    a SimulateConfig field (commented keys included), valid as written, and simulated after the template's
    placeholders are filled (here: A0 and d given, 6 periods)."""
    from afmid.config import SimulateConfig

    code, out, _ = run_cli("init-config", "--simulate")
    assert code == 0 and out == template_text(simulate=True) and out != template_text()
    section = out[out.index("\nsimulate:\n"):]
    raw = yaml.safe_load(out)
    assert raw["simulate"]["model"] == "dmt" and raw["simulate"]["parameters"] == {"E_star": 2.0e9, "hamaker": 5.0e-20}
    keys = set(re.findall(r"^  #? ?([a-z_]+):", section, re.M))
    assert keys and keys <= set(SimulateConfig.model_fields), keys - set(SimulateConfig.model_fields)
    assert {"setpoint", "effects", "transient_start", "map"} <= keys  # the optional ones are documented too
    # issue 33: simulated as written (it failed on drive.free_amplitude, then sample.separation)
    assert raw["drive"]["free_amplitude"] == 10.0e-9 and raw["sample"]["separation"] == 8.5e-9
    config = tmp_path / "sim.yaml"
    config.write_text(out)
    code, _, err = run_cli("-q", "simulate", config, "-o", tmp_path / "trace.h5", "--set", "simulate.periods=6")
    assert code == 0, err
    plain = yaml.safe_load(template_text())  # without --simulate both stay commented: the fit estimates d
    assert "free_amplitude" not in plain["drive"] and "separation" not in plain["sample"]
    assert "# free_amplitude: 10.0e-9" in template_text()
