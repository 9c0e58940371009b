"""A model that fails the data is marked model-limited even at its noise floor: the contact-law shape probe
(afmid.fit.contact_probe) and a read-out that only an unphysical value fits (afmid.fit.plausibility.unphysical)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmid.config import load_config
from afmid.fit.contact_probe import (EXPONENT_SHIFTS, ContactProbe, check_contact_law, elastic_power,
                                     probe_expressions)
from afmid.fit.plausibility import unphysical
from afmid.physics.library import build_library
from afmid.physics.tips import tip_geometry
from repo_paths import REPO_ROOT

CONFIGS = REPO_ROOT / "tests" / "configs"


def _library(config_name: str, overrides: list[str] | None = None):
    config = load_config(CONFIGS / config_name, overrides or [])
    return config, build_library(config.model, config.source, tip_geometry(config.cantilever))


def test_the_probes_bracket_the_elastic_power():
    assert probe_expressions(1.5) == ("[z <= a0] * delta^1", "[z <= a0] * delta^2.5")
    assert EXPONENT_SHIFTS[0] < 0 < EXPONENT_SHIFTS[1]


@pytest.mark.parametrize("config_name, power", [("dmt_viscoelastic.yaml", 1.5), ("dmt_cone.yaml", 2.0)])
def test_the_elastic_term_is_found_with_its_power(config_name, power):
    _, library = _library(config_name, ["model.effects=[dmt]", "model.library=null"])
    chosen = np.ones(len(library), dtype=bool)
    label, found = elastic_power(library, chosen)
    assert label == "dmt.hertz" and found == power
    assert elastic_power(library, np.zeros(len(library), dtype=bool)) is None  # not selected: nothing to test


def _run(selected_probes: tuple[str, ...], user_terms=(), preset=None):
    config, library = _library("dmt_viscoelastic.yaml", ["model.effects=[dmt]", "model.library=null"])
    chosen = np.ones(len(library), dtype=bool)
    offered = []

    def select_with(extra):
        offered.extend(extra)
        probed = build_library(config.model.model_copy(update={"terms": list(extra)}), config.source,
                               library.tip)
        mask = np.array([t.expression in selected_probes or t.effect is not None for t in probed.terms])
        return probed, mask

    return check_contact_law(library, chosen, list(user_terms), preset, select_with), offered


def test_a_selected_probe_fails_the_test_and_says_why():
    probe, offered = _run(("[z <= a0] * delta^2.5",))
    assert offered == list(probe_expressions(1.5))
    assert probe.failed and probe.selected == ("[z <= a0] * delta^2.5",)
    assert "dmt.hertz" in probe.warning() and "delta^2.5" in probe.warning()


def test_no_probe_selected_passes():
    probe, _ = _run(())
    assert isinstance(probe, ContactProbe) and not probe.failed and probe.warning() == ""


def test_nothing_is_tested_for_a_preset_or_a_probe_the_user_declared():
    assert _run((), preset="viscoelastic_table2")[0] is None
    assert _run((), user_terms=("[z <= a0] * delta^1",))[0] is None


@pytest.mark.parametrize("quantity, expected", [
    ({"value": -8e7, "ci_low": -1.2e8, "ci_high": -4e7, "effect": "dmt"}, True),   # E* < 0, whole interval too
    ({"value": -8e7, "ci_low": -1.2e8, "ci_high": 1e6, "effect": "dmt"}, False),   # the interval reaches in
    ({"value": 2e7, "ci_low": -1e7, "ci_high": 5e7, "effect": "dmt"}, False),      # physical value
    ({"value": -8e7, "ci_low": math.nan, "ci_high": math.nan, "effect": "dmt"}, False),  # no interval: no evidence
    ({"value": math.nan, "ci_low": -1.0, "ci_high": 1.0, "effect": "dmt", "determined": False}, False),
])
def test_unphysical_needs_the_whole_interval_outside(quantity, expected):
    assert unphysical("E_star", quantity) is expected


def test_unphysical_uses_the_declared_tip():
    adhesion = {"value": 33.1e-6, "ci_low": 32.9e-6, "ci_high": 33.3e-6, "effect": "dmt"}
    assert unphysical("adhesion_force", {**adhesion, "tip_radius": 8e-9})
    assert not unphysical("adhesion_force", {**adhesion, "tip_radius": 5e-6})


#: A soft sample in liquid under a hydration force that keeps growing inside contact (the catalog's hydration
#: law), fitted with a double layer, whose force is held at its contact value there: seeds 1-4 give E* 468-478 MPa
#: for a 20 MPa sample with the error at 1.0-1.2x its floor (docs/lab/2026-11-29-liquid-hydration-contact-law.md).
GROWING_IN_CONTACT = ["sample.medium=liquid", "sample.separation=4.0e-9", "simulate.effects=[hydration]",
                      "simulate.parameters={E_star: 20.0e6, hamaker: 1.0e-20, hydration_force: 0.3e-9, "
                      "hydration_length: 0.5e-9}", "simulate.seed=1", "fit.bootstrap=20"]


@pytest.mark.slow
def test_a_contact_law_the_model_cannot_give_is_model_limited_at_the_floor(tmp_path):
    from afmid.config import dump_config
    from afmid.fit.pipeline import run_fit
    from afmid.io.trace import write_trace_file
    from afmid.simulate.driver import simulate
    from afmid.fit.uncertainty import model_limited

    sim = load_config(CONFIGS / "liquid.yaml", GROWING_IN_CONTACT)
    path = write_trace_file(tmp_path / "t.h5", simulate(sim), dump_config(sim))
    held = run_fit(load_config(CONFIGS / "liquid.yaml", GROWING_IN_CONTACT + [
        f"data.path={path}", "model.effects=[dmt, double_layer]"]))
    assert not model_limited(held.cv_error, held.cv_error_noise_floor)  # the force error cannot see it
    assert held.quantities["E_star"]["value"] > 10 * 20e6
    assert held.model_limited and all(q["model_limited"] for q in held.quantities.values())
    assert any("does not follow the model's contact law" in w for w in held.warnings)
    right = run_fit(load_config(CONFIGS / "liquid.yaml", GROWING_IN_CONTACT + [
        f"data.path={path}", "model.effects=[dmt, hydration]"]))
    assert not right.model_limited, right.warnings
