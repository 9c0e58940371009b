"""Issue 29: a record no catalog model explains, and a fit without contact.

A short DMT trace simulated with the tip 1.35 nm above contact at its closest approach (A0 15 nm, d 16.5 nm,
Hamaker 3e-19 J) and fitted with [dmt]: only the van der Waals tail is selected, so the fit has no contact.
Its run (in memory) is used for the force-vs-separation window (the old window ran from the closest approach
to 4 nm above a0: empty, lo > hi, without contact) and for what an unexplained record's report lists: the
calibration (with the implausible read-out of a tip radius declared 50x too small as its evidence), the
channel (the model-free look sees no force 1.35 nm above contact; a flipped sign when the deflection is
negated) and non-stationarity (a slow modulation as on the Bruker HSDC record); never an instrument declaration.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from repo_paths import TEST_CONFIGS

CONFIG_KEYS = ["sample.separation=16.5e-9", "fit.bootstrap=10", "model.library=null", "model.effects=[dmt]"]
UNEXPLAINED = {"missing_effect": True, "suggestions": [],
               "diagnosis": {"explained_by_catalog": False, "verdict": "not explained by the catalog: a significant "
                             "residual that no catalog effect explains", "description": "in contact"}}


@pytest.fixture(scope="module")
def no_contact():
    """(the fit, its run data) of the no-contact trace, fitted with a tip radius of 0.2 nm (truth 10 nm)."""
    from afmid.config import load_config
    from afmid.fit.pipeline import run_fit
    from afmid.runfile import run_data
    from afmid.simulate.driver import simulate

    sim = load_config(TEST_CONFIGS / "dmt.yaml", [*CONFIG_KEYS, "simulate.periods=20",
                                                  "simulate.parameters.hamaker=3e-19"])
    trace = simulate(sim)
    # The experimenter declares a tip 50x too small: the Hamaker read-out H = 6 C / R grows 50x, past 1e-17 J.
    believed = dataclasses.replace(trace, cantilever=dataclasses.replace(trace.cantilever, tip_radius=0.2e-9))
    config = load_config(TEST_CONFIGS / "dmt.yaml", CONFIG_KEYS)
    result = run_fit(config, trace=believed)
    return result, run_data(result, config, "no_contact.h5")


def test_the_fit_has_no_contact(no_contact):
    from afmid.report.plots import contact_gap, no_contact_note

    result, run = no_contact
    assert result.selected_terms() == ["dmt.vdw"]
    assert contact_gap(run) > 0.5e-9  # 1.35 nm measured
    assert no_contact_note(run).startswith("no contact: the closest approach stays ")


def test_force_separation_window_holds_the_curves_without_contact(no_contact, tmp_path):
    from afmid.report.plots import _branch_curves, fig_force_separation, separation_window

    _, run = no_contact
    lo, hi = separation_window(run)
    assert lo < hi
    for approach in (True, False):
        z, force, _ = _branch_curves(run, run.periods["force_inverted"], approach)
        inside = (z >= lo) & (z <= hi)
        assert inside.sum() >= 10, f"{inside.sum()} points of {z.size} in [{lo:.3g}, {hi:.3g}] nm"
        assert np.all(np.isfinite(force[inside]))
        assert np.min(force[inside]) < 0  # the attractive branch is what there is
    name = fig_force_separation(run, tmp_path)
    assert (tmp_path / name).stat().st_size > 0 and (tmp_path / name).with_suffix(".svg").exists()


def test_force_separation_window_with_contact_starts_below_contact():
    """With contact the window is unchanged: 0.2 nm below the closest approach of any period to 4 nm above a0."""
    from afmid.report.plots import separation_window

    a0 = 0.165e-9
    z = np.array([[-1.0e-9, 2e-9, 20e-9]])
    run = SimpleNamespace(periods={"separation": z}, config=SimpleNamespace(sample=SimpleNamespace(a0=a0)))
    assert separation_window(run) == pytest.approx((-1.2, (a0 + 4e-9) * 1e9))


def test_an_unexplained_record_lists_what_to_check_with_its_evidence(no_contact):
    from afmid.diagnosis.checklist import check_lines, with_what_to_check

    result, run = no_contact
    assert not run.quantities["hamaker"]["plausible"]
    summary = with_what_to_check(UNEXPLAINED, run, result.prep, {})
    items = {item["check"]: item for item in summary["what_to_check"]}
    assert list(items) == ["calibration", "channel", "non-stationarity"]  # the one with evidence first
    calibration = items["calibration"]
    assert {"cantilever.spring_constant", "cantilever.quality_factor", "cantilever.tip_radius"} <= set(
        calibration["keys"])
    assert any("hamaker" in e for e in calibration["evidence"])
    assert not any("E_star" in e for e in calibration["evidence"])  # a term not selected is no calibration evidence
    assert "no calibration uncertainty is declared" in calibration["what"]
    # 1.35 nm above contact the model-free look at the harmonics sees no tip-sample force: said, as it is
    assert items["channel"]["keys"] == ["data.column", "data.positive"]
    assert items["channel"]["evidence"] == ["no tip-sample force is seen in the harmonics (a free oscillation, or "
                                            "another channel)"]
    assert not items["non-stationarity"]["evidence"]  # a steady simulation
    lines = check_lines(summary["what_to_check"])
    assert len(lines) == 3 and lines[2].endswith("Evidence: no evidence against it found here.")
    text = " ".join(lines)
    for instrument_key in ("data.detector", "higher_modes", "second mode"):  # never without its own evidence
        assert instrument_key not in text


def test_a_flipped_channel_is_named_as_evidence(no_contact):
    from afmid.diagnosis.checklist import what_to_check

    from afmid.config import load_config
    from afmid.simulate.driver import simulate

    result, run = no_contact
    trace = simulate(load_config(TEST_CONFIGS / "dmt.yaml", ["simulate.periods=12"]))  # in contact
    flipped = SimpleNamespace(trace=dataclasses.replace(trace, deflection=-trace.deflection), motion=None,
                              drive=result.prep.drive)
    (channel,) = [i for i in what_to_check(run, flipped, {}) if i["check"] == "channel"]
    assert any("sign flipped" in e for e in channel["evidence"])


def test_a_slow_modulation_is_named_as_non_stationarity(no_contact):
    from afmid.diagnosis.checklist import what_to_check
    from afmid.preprocess.motion import PERIODIC, Modulation, Motion

    result, run = no_contact
    modulation = Modulation(amplitude_sd=0.0065, correlation_periods=12, bandwidth_cycles=0.015, lag1=0.9)  # HSDC's
    modulated = SimpleNamespace(trace=result.prep.trace, drive=result.prep.drive,
                                motion=Motion(PERIODIC, 0.058, 0.0085, 1.0, modulation))
    (item,) = [i for i in what_to_check(run, modulated, {}) if i["check"] == "non-stationarity"]
    assert item["evidence"] and item["evidence"][0].startswith("the motion: periodic; ")


def test_an_explained_record_gets_no_checklist(no_contact):
    from afmid.diagnosis.checklist import with_what_to_check

    result, run = no_contact
    explained = {**UNEXPLAINED, "diagnosis": {**UNEXPLAINED["diagnosis"], "explained_by_catalog": True},
                 "suggestions": [{"effect": "viscoelastic"}]}
    assert "what_to_check" not in with_what_to_check(explained, run, result.prep, {})
    instrument = {**UNEXPLAINED, "diagnosis": {**UNEXPLAINED["diagnosis"], "instrument": {"kind": "detector"}}}
    assert "what_to_check" not in with_what_to_check(instrument, run, result.prep, {})


def test_the_verdict_box_and_the_terminal_list_the_checks(no_contact, tmp_path):
    from afmid.diagnosis.checklist import check_lines, with_what_to_check
    from afmid.fit.uncertainty import INTERVALS_STATISTICAL, STATISTICAL_ONLY_TEXT
    from afmid.report.page import _verdict_box, terminal_summary

    result, run = no_contact
    summary = with_what_to_check(UNEXPLAINED, run, result.prep, {})
    box = _verdict_box(summary)
    assert "What to check" in box and box.count("<li>") == 3
    summary.update(runs=[{"run": "no_contact.h5", "effects": ["dmt"], "error": 0.5, "n_terms": 1,
                          "parameters": {}}], intervals=INTERVALS_STATISTICAL)
    text = terminal_summary(summary, tmp_path)
    assert "what to check:" in text
    for line in check_lines(summary["what_to_check"]):
        assert line in text
    assert STATISTICAL_ONLY_TEXT not in text  # said with the parameters; this run lists none
