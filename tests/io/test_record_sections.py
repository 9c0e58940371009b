"""The record's sections (afmid.io.sections) are the run config's: one schema, so Trace.from_array and a config
file give the same keys, defaults and messages; and the checks on load of a record without a fit section use
exactly the fit section's defaults (Trace.from_array checked a full default run config before issue 30)."""

from __future__ import annotations

import pytest

from afmid.config import FitConfig, RunConfig, build_config
from afmid.errors import ConfigError
from afmid.io.cantilever import Cantilever
from afmid.io.defects import Settings
from afmid.io.sections import RecordSections, record_sections
from afmid.io.trace import Trace


def test_the_run_config_is_made_of_the_record_sections():
    for name in ("data", "cantilever", "drive"):
        assert RunConfig.model_fields[name].annotation is RecordSections.model_fields[name].annotation


def test_the_checks_without_a_fit_section_use_the_fit_sections_defaults():
    fit, defaults = FitConfig(), Settings()
    assert (defaults.detrend, defaults.baseline, defaults.temperature) == (fit.detrend, fit.baseline, fit.temperature)
    assert fit.form == "weak" and defaults.differentiation is None  # the weak form differentiates nothing


@pytest.mark.parametrize("raw, key", [
    ({"data": {"sample_rate": -5.0}}, "data.sample_rate"),
    ({"data": {"sample_rate": True}}, "data.sample_rate"),
    ({"cantilever": {"quality_factor": 0.0}}, "cantilever.quality_factor"),
    ({"drive": {"frequency": 1e12}}, "drive.frequency"),
    ({"drive": {"phase_uncertainty": 0.1}}, "drive"),
    ({"data": {"sample_rte": 1e6}}, "data"),
])
def test_a_bad_record_value_is_the_same_one_line_error_as_in_a_config_file(raw, key):
    with pytest.raises(ConfigError) as from_config:
        build_config(raw, source=None)
    with pytest.raises(ConfigError) as from_record:
        record_sections(raw, source="Trace.from_array")
    assert str(from_record.value).replace("Trace.from_array", "").strip(": ") == str(from_config.value).strip(": ")
    assert key in str(from_record.value) and "\n" not in str(from_record.value)


def test_from_array_names_the_key_of_a_bad_argument():
    lever = Cantilever(spring_constant=40.0, resonance_frequency=3e5, quality_factor=250.0, tip_radius=1e-8)
    with pytest.raises(ConfigError, match=r"Trace\.from_array: data\.sample_rate"):
        Trace.from_array([0.0] * 1000, -1.0, cantilever=lever)
