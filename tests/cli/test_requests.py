"""Nonsense is not reported as success (issue 11): the tests behind the corpus cases of
tests/cli/test_corpus_requests.py that need more than one command line (statistics, warnings, run files)."""

from __future__ import annotations

import csv
import logging
import shutil

import h5py
import numpy as np
import pytest
import yaml

import afmid.io.oscillation as oscillation
from afmid.config import RunConfig, build_config, dump_config
from afmid.errors import ConfigError, InputError
from tests.conftest import DRIVE_FREQUENCY, SAMPLE_RATE
from tests.cli.test_corpus_config import base_config
from tests.cli.test_corpus_requests import reference_run, write_values_csv


# --------------------------------------------------------------------------- the drive-frequency line test
def test_the_threshold_is_the_f_quantile_of_noise():
    from scipy.stats import f as f_distribution

    test = oscillation.drive_line_test(np.random.default_rng(0).normal(size=20000), SAMPLE_RATE, DRIVE_FREQUENCY,
                                       0.05)
    expected = f_distribution.isf(oscillation.FALSE_ALARM / test["band_bins"], 2, 2 * test["floor_bins"])
    assert test["threshold"] == pytest.approx(expected)


@pytest.mark.parametrize("colour", ["white", "random walk"])
def test_noise_passes_its_own_quantile_as_often_as_the_statistics_say(colour):
    """Under noise the ratio follows F(2, 2m) (max over the band's bins): the 5 % quantile is passed by about
    5 % of noise traces (white), and by no more for a coloured (random walk) background."""
    from scipy.stats import f as f_distribution

    rng = np.random.default_rng(5)
    trials, passed = 400, 0
    for _ in range(trials):
        x = rng.normal(size=8000)
        if colour == "random walk":
            x = np.cumsum(x)
        test = oscillation.drive_line_test(x, SAMPLE_RATE, DRIVE_FREQUENCY, 0.05)
        passed += test["ratio"] > f_distribution.isf(0.05 / test["band_bins"], 2, 2 * test["floor_bins"])
    rate = passed / trials
    sigma = np.sqrt(0.05 * 0.95 / trials)
    assert rate < 0.05 + 3 * sigma


def test_a_noisy_oscillation_at_the_drive_frequency_passes():
    rng = np.random.default_rng(2)
    t = np.arange(4000) / SAMPLE_RATE
    x = np.sin(2 * np.pi * DRIVE_FREQUENCY * 1.01 * t) + rng.normal(0, 0.5, t.size)  # 1 % off nominal
    test = oscillation.drive_line_test(x, SAMPLE_RATE, DRIVE_FREQUENCY, 0.05)
    assert test["ratio"] > test["threshold"]


def test_an_oscillation_elsewhere_is_no_drive_line():
    t = np.arange(4000) / SAMPLE_RATE
    x = np.sin(2 * np.pi * 1.7 * DRIVE_FREQUENCY * t) + np.random.default_rng(3).normal(0, 0.1, t.size)
    test = oscillation.drive_line_test(x, SAMPLE_RATE, DRIVE_FREQUENCY, 0.05)
    assert test["ratio"] < test["threshold"]


def test_a_trace_too_short_to_judge_is_left_to_the_other_checks():
    assert oscillation.drive_line_test(np.zeros(10), SAMPLE_RATE, DRIVE_FREQUENCY, 0.05) is None


# --------------------------------------------------------------------------- batch
def test_a_batch_marks_a_trace_of_noise_failed(tmp_path, run_cli):
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(base_config(**{"data.path": None})))
    write_values_csv(tmp_path, np.random.default_rng(4).normal(size=4000), "noise.csv")
    code, _, err = run_cli("-q", "batch", tmp_path / "run.yaml", "--inputs", tmp_path / "noise.csv",
                           "-o", tmp_path / "out", "-j", "1")
    assert code == 1, err
    with open(tmp_path / "out" / "summary.csv", newline="") as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    assert [r["status"] for r in rows] == ["failed"]
    assert "no oscillation at the drive frequency" in rows[0]["failure"]
    assert not (tmp_path / "out" / "noise.run.h5").exists()


# --------------------------------------------------------------------------- effects and presets
def test_adding_an_effect_already_present_warns_and_changes_nothing(caplog):
    from afmid.fit.pipeline import apply_effect_changes

    config = build_config(base_config(**{"model.effects": ["dmt", "viscoelastic"]}))
    with caplog.at_level(logging.WARNING, logger="afmid"):
        apply_effect_changes(config, ("viscoelastic",), ())
    assert config.model.effects == ["dmt", "viscoelastic"]
    assert "already in model.effects" in caplog.text


def test_a_preset_config_survives_its_own_dump():
    """The run file stores dump_config(); reading it back must not see the default effects as a contradiction."""
    config = build_config(base_config(**{"model.effects": None, "model.library": "lj_table1"}))
    again = build_config(yaml.safe_load(dump_config(config)))
    assert again.model.library == "lj_table1" and again.model.effects == []


def test_a_preset_with_an_explicitly_empty_effects_list_is_no_contradiction():
    config = RunConfig.model_validate({"model": {"library": "jkr_table4", "effects": []}})
    assert config.model.library == "jkr_table4"


def test_non_finite_coefficients_are_refused():
    from afmid.fit.orchestration import refuse_unusable
    from afmid.io.trace import Trace, Cantilever
    from afmid.physics.library import build_library

    config = build_config(base_config())
    library = build_library(config.model)
    trace = Trace(deflection=np.zeros(8), sample_rate=SAMPLE_RATE, cantilever=Cantilever(40.0, 3e5, 150.0, 1e-8),
                  drive_frequency=DRIVE_FREQUENCY)
    coef = np.ones(len(library))
    refuse_unusable(trace, library, coef, 0.1)  # a usable result passes
    coef[1] = np.inf
    with pytest.raises(InputError, match=library.names[1]):
        refuse_unusable(trace, library, coef, 0.1)
    with pytest.raises(InputError, match="NaN"):
        refuse_unusable(trace, library, np.ones(len(library)), float("nan"))


def test_differentiation_options_valid_ones_still_pass():
    config = build_config(base_config(**{"fit.differentiation_options": {"window": 9, "order": 3}}))
    assert config.fit.differentiation_options == {"window": 9.0, "order": 3.0}
    with pytest.raises(ConfigError, match="did you mean 'order'"):
        build_config(base_config(**{"fit.differentiation_options": {"ordr": 3}}))


def test_an_integer_column_index_is_still_a_column():
    config = build_config(base_config(**{"data.column": 1, "data.time_column": 0}))
    assert (config.data.column, config.data.time_column) == (1, 0)


# --------------------------------------------------------------------------- run files
@pytest.fixture
def run_with_own_trace(tmp_path):
    """A copy of the reference run whose input is a copy of its trace in tmp_path."""
    shutil.copyfile(reference_run(), tmp_path / "run.h5")
    shutil.copyfile(reference_run().with_name("trace.h5"), tmp_path / "trace.h5")
    with h5py.File(tmp_path / "run.h5", "r+") as h5:
        h5.attrs["input_path"] = str(tmp_path / "trace.h5")
    return tmp_path / "run.h5"


def test_the_truth_of_an_unchanged_trace_is_read(run_with_own_trace):
    from afmid.runfile import load_run

    assert load_run(run_with_own_trace).truth is not None


def test_the_truth_of_a_changed_trace_is_ignored_with_a_warning(run_with_own_trace, caplog):
    from afmid.runfile import load_run

    with h5py.File(run_with_own_trace.with_name("trace.h5"), "r+") as h5:
        h5["truth/force"][0] += 1e-9  # the trace file changed after the fit
    with caplog.at_level(logging.WARNING, logger="afmid"):
        run = load_run(run_with_own_trace)
    assert run.truth is None
    assert "changed since the fit" in caplog.text and "ground truth is ignored" in caplog.text


def test_runs_of_different_traces_are_compared_only_when_allowed(tmp_path, run_cli):
    shutil.copyfile(reference_run(), tmp_path / "a.h5")
    shutil.copyfile(reference_run(), tmp_path / "b.h5")
    with h5py.File(tmp_path / "b.h5", "r+") as h5:
        h5.attrs["input_sha256"] = "f" * 64
    code, out, err = run_cli("-q", "report", tmp_path / "a.h5", tmp_path / "b.h5", "-o", tmp_path / "rep",
                             "--no-suggest", "--allow-different-traces")
    assert code == 0, err
    assert "fitted on different traces" in out
    summary = (tmp_path / "rep" / "summary.json").read_text()
    assert "different traces" in summary
    assert "different traces" in (tmp_path / "rep" / "report.html").read_text()


def test_runs_of_the_same_trace_need_no_flag(tmp_path, run_cli):
    shutil.copyfile(reference_run(), tmp_path / "a.h5")
    shutil.copyfile(reference_run(), tmp_path / "b.h5")
    code, out, err = run_cli("-q", "report", tmp_path / "a.h5", tmp_path / "b.h5", "-o", tmp_path / "rep",
                             "--no-suggest")
    assert code == 0, err
    assert "different traces" not in out


def test_no_effects_are_suggested_from_a_changed_trace(run_with_own_trace, caplog):
    from afmid.diagnosis.diagnose import suggest
    from afmid.runfile import load_run

    run = load_run(run_with_own_trace)
    with h5py.File(run_with_own_trace.with_name("trace.h5"), "r+") as h5:
        h5.attrs["note"] = "edited after the fit"
    with caplog.at_level(logging.WARNING, logger="afmid"):
        out = suggest(run)
    assert out["suggestions"] == [] and "changed since the run was made" in out["note"]
