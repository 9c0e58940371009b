"""Plausibility of the physical read-outs: the registry's ranges, the checker, and where the verdicts go
(run file, terminal, report, batch summary)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import h5py
import pytest
import yaml

from afmid.errors import DefinitionError
from afmid.physics.effects import EFFECTS, Effect, Parameter, Quantity, Term, quantity_range
from afmid.fit.plausibility import check_plausibility, display, flagged_value, judge, plausible_range
from repo_paths import REPO_ROOT

ROOT = REPO_ROOT


# --------------------------------------------------------------------------- the registry
def test_every_reported_quantity_has_a_range_and_parameters_reuse_theirs():
    for effect in EFFECTS:
        names = {p.name for p in effect.parameters}
        for q in effect.quantities:
            low, high = quantity_range(effect, q)
            assert math.isfinite(low) and math.isfinite(high) and low < high, (effect.name, q.name)
            if q.name in names:
                p = effect.parameter(q.name)
                assert (low, high) == (p.low, p.high), (effect.name, q.name)
            assert plausible_range(q.name, effect.name) == (low, high, q.unit)


def _effect(name: str, *quantities: Quantity) -> Effect:
    return Effect(
        name=name, title="a test effect", formula="F = -k_t z",
        parameters=(Parameter("test_stiffness", "N/m", 1.0, 0.0, 10.0, "stiffness"),),
        terms=(Term("spring", "z", lambda p: -p["test_stiffness"], coefficient_unit="N/m"),),
        quantities=quantities,
        readout=lambda c, ctx: {"test_stiffness": -c["spring"], "test_force": 1e-9, "hamaker": 1e-19},
        references=("none",),
    )


@pytest.mark.parametrize("quantity, message", [
    (Quantity("test_force", "N", "a force"), "needs a plausible range"),
    (Quantity("test_force", "N", "a force", 1e-6, 1e-9), "low < high"),
    (Quantity("test_force", "N", "a force", 0.0, math.inf), "low < high"),
    (Quantity("test_stiffness", "N/m", "k", 0.0, 5.0), "takes the parameter's range"),
    (Quantity("test_stiffness", "Pa", "k"), "its parameter in N/m"),
    (Quantity("test_force", "furlong", "a force", 0.0, 1.0), "furlong"),
    (Quantity("hamaker", "J", "H", 0.0, 1.0), "differs from effect"),
], ids=["no-range", "inverted", "infinite", "parameter-with-own-range", "parameter-unit", "unknown-unit",
        "name-with-another-range"])
def test_registration_refuses_a_quantity_without_a_sound_range(quantity, message):
    n = len(EFFECTS)
    with pytest.raises(DefinitionError, match=message):
        EFFECTS.register(_effect("test_plausibility_effect", Quantity("test_stiffness", "N/m", "k"), quantity))
    assert len(EFFECTS) == n and "test_plausibility_effect" not in EFFECTS


# --------------------------------------------------------------------------- the checker
@pytest.mark.parametrize("name, quantity, plausible, fragments", [
    ("viscosity", {"value": -24000.0, "error": 3000.0, "ci_low": -30000.0, "ci_high": -18000.0, "unit": "Pa*s"},
     False, ("viscosity = -24 kPa s", "wrong sign", "[0, 1e5] Pa s", "is outside it too", "quality_factor")),
    ("E_star", 1e13, False, ("E_star = 10 TPa", "outside the plausible range", "[100, 1e12] Pa", "data.units")),
    ("hamaker", {"value": -2e-20, "unit": "J"}, False, ("hamaker = -2e-20 J", "wrong sign", "data.positive")),
    ("adhesion_force", {"value": -1e-9, "ci_low": -3e-9, "ci_high": 1e-9},
     False, ("-1 nN", "only its 95 % interval [-3 nN, 1 nN] reaches into it")),
    ("viscosity", {"value": 3.0, "error": 5.0, "ci_low": -7.0, "ci_high": 13.0}, True, ()),
    ("E_star", {"value": 2e5, "ci_low": 5e4, "ci_high": 4e5}, True, ()),
    ("E_star", {"value": 2e9, "ci_low": 2e12, "ci_high": 3e12}, False, ("whole 95 % interval", "lies outside")),
    ("E_star", 0.0, False, ("E_star = 0 Pa", "not identified")),
    ("viscosity", {"value": 0.0, "error": 5.0, "ci_low": 0.0, "ci_high": 12.0}, True, ()),
    ("sigma", math.nan, False, ("could not be read out",)),
    ("fluid_viscosity", math.inf, False, ("inf",)),
    ("voltage", {"value": 2.0, "error": 5e3}, False, ("2 V ± 5 kV", "unconstrained")),
    ("voltage", {"value": 2.0, "error": math.inf}, False, ("unconstrained",)),
    ("voltage", {"value": 2.0, "error": math.nan}, True, ()),
    ("jkr.hamaker", {"value": 5e-20, "effect": "jkr"}, True, ()),
    ("jkr.hamaker", {"value": 5e-16, "effect": "jkr"}, False, ("hamaker = 5e-16 J",)),
    ("not_a_catalog_quantity", 1e30, True, ()),
], ids=["negative-viscosity", "huge-modulus", "negative-hamaker", "interval-reaches-in", "straddles-zero",
        "straddles-low-bound", "interval-outside", "not-identified", "zero-with-upper-limit", "nan", "inf",
        "unconstrained", "infinite-error", "no-error", "prefixed-name", "prefixed-name-outside", "undeclared"])
def test_check_plausibility(name, quantity, plausible, fragments):
    verdict = check_plausibility({name: quantity})[name]
    assert verdict.plausible is plausible, verdict.reason
    assert (verdict.reason == "") is plausible
    for fragment in fragments:
        assert fragment in verdict.reason, verdict.reason
    if not plausible:
        assert "\n" not in verdict.reason and verdict.reason.count(". ") == 0  # one sentence


# --------------------------------------------------------------------------- a spring constant off by a factor
#: The read-outs of configs/dmt.yaml's trace (E* 2 GPa, H 5e-20 J, 10 nm tip) fitted with cantilever.spring_constant
#: 100x too large and 100x too small (measured with afmid fit; every force read-out scales with k). Before issue
#: 32 both read as plausible: E* 200 GPa and 20 MPa are moduli of real materials.
_K_TIMES_100 = {"hamaker": 5.06e-18, "E_star": 2.0e11, "adhesion_force": 3.10e-7, "surface_energy": 2.46}
_K_OVER_100 = {"hamaker": 4.93e-22, "E_star": 1.98e7, "adhesion_force": 3.02e-11, "surface_energy": 2.40e-4}
_UNITS = {"hamaker": "J", "E_star": "Pa", "adhesion_force": "N", "surface_energy": "J/m^2"}


def _dmt_quantities(values: dict) -> dict:
    return {name: {"value": v, "error": 0.04 * v, "ci_low": 0.92 * v, "ci_high": 1.08 * v, "unit": _UNITS[name],
                   "effect": "dmt", "tip_radius": 10e-9} for name, v in values.items()}


@pytest.mark.parametrize("values, direction, span, example", [
    # H in [1e-21, 1e-18] J: 5.06e-18 J needs k 5.06x to 5060x smaller; the power of ten in the middle is 100.
    (_K_TIMES_100, "large", "5.1x to 5100x", "at 100x too large: hamaker would be 5.06e-20 J and E_star 2 GPa"),
    # 4.93e-22 J needs k 2.03x (1e-21 / 4.93e-22) to 2030x larger; surface_energy 2.4e-4 J/m^2 allows 2.4e-4/1e-4.
    (_K_OVER_100, "small", "2x to 2000x", "at 100x too small: hamaker would be 4.93e-20 J and E_star 1.98 GPa"),
], ids=["k-100x-too-large", "k-100x-too-small"])
def test_a_spring_constant_off_by_a_factor_is_named_as_the_likely_cause(values, direction, span, example):
    verdicts = check_plausibility(_dmt_quantities(values))
    assert not verdicts["hamaker"].plausible
    reason = verdicts["hamaker"].reason
    assert reason.startswith("hamaker = ") and "outside the plausible range" in reason
    assert f"a spring constant {span} too {direction} would explain it" in reason, reason
    assert example in reason and reason.endswith("check cantilever.spring_constant")
    assert "\n" not in reason and reason.count(". ") == 0
    # The finding (the reason without the advice) is unchanged: a trial model's read-out says no more.
    assert "spring constant" not in verdicts["hamaker"].finding


def test_no_spring_constant_cause_when_no_single_factor_explains_the_read_outs():
    """H 100x too large with E* 150 Pa: H needs k at least 5.06x too large, E* (floor 100 Pa) at most 1.5x, so no
    single factor on k brings both into range: the general advice on the calibration stays."""
    values = {**_K_TIMES_100, "E_star": 150.0}
    reason = check_plausibility(_dmt_quantities(values))["hamaker"].reason
    assert "cantilever.spring_constant" in reason and "would explain it" not in reason


def test_read_outs_of_one_term_are_one_piece_of_evidence():
    """H, the adhesion and the surface energy all come from DMT's van der Waals coefficient: when E* is not
    determined (no contact term selected, as on a record the model fails) they are one read-out, and one read-out
    names no spring constant (any factor brings it in). With E* from the Hertz term beside them, they are two."""
    one_term = {name: {**q, "sources": ("dmt.vdw",)} for name, q in _dmt_quantities(_K_TIMES_100).items()
                if name != "E_star"}
    reason = check_plausibility(one_term)["hamaker"].reason
    assert not check_plausibility(one_term)["hamaker"].plausible and "would explain it" not in reason
    two_terms = {**one_term, "E_star": {**_dmt_quantities(_K_TIMES_100)["E_star"], "sources": ("dmt.hertz",)}}
    assert "a spring constant 5.1x to 5100x too large would explain it" in check_plausibility(two_terms)["hamaker"].reason


def test_read_outs_in_range_give_no_cause():
    verdicts = check_plausibility(_dmt_quantities({"hamaker": 5.0e-20, "E_star": 2.0e9, "adhesion_force": 3.1e-9,
                                                   "surface_energy": 0.0246}))
    assert all(v.plausible and v.reason == "" for v in verdicts.values())


# --------------------------------------------------------------------------- forces that grow with the tip
@pytest.mark.parametrize("name, effect, value, radius, plausible", [
    # 4 pi R gamma at gamma = 5 J/m^2: 0.503 uN for an 8 nm tip
    ("adhesion_force", "dmt", 33.11e-6, 8e-9, False),  # a real record read with a wrong calibration
    ("adhesion_force", "dmt", 0.49e-6, 8e-9, True),
    ("adhesion_force", "dmt", 0.52e-6, 8e-9, False),
    ("adhesion_force", "dmt", 33.11e-6, 5e-6, True),  # a 5 um colloidal probe can adhere with 33 uN
    ("adhesion_force", "dmt", 33.11e-6, math.nan, True),  # no radius known: the plain range only
    ("capillary_force", "capillary", 0.1e-6, 8e-9, True),  # 4 pi R (1 N/m): 0.10053 uN
    ("capillary_force", "capillary", 0.11e-6, 8e-9, False),
])
def test_a_force_that_grows_with_the_tip_is_judged_against_the_declared_radius(name, effect, value, radius,
                                                                                plausible):
    verdict = judge(name, {"value": value, "unit": "N", "effect": effect, "tip_radius": radius})
    assert verdict.plausible is plausible, verdict.reason
    if not plausible:
        assert "for the declared tip radius 8 nm" in verdict.reason


def test_high_per_radius_must_agree_across_effects_and_be_positive():
    with pytest.raises(DefinitionError, match="high_per_radius"):
        EFFECTS.register(_effect("tip_bound_negative", Quantity("pulled_force", "N", "a force", 0.0, 1e-6, -1.0)))
    with pytest.raises(DefinitionError, match="adhesion_force"):
        EFFECTS.register(_effect("tip_bound_other", Quantity("adhesion_force", "N", "adhesion", 0.0, 1e-4, 1.0)))


def test_the_range_bounds_themselves_are_plausible():
    for effect in EFFECTS:
        for q in effect.quantities:
            for bound in quantity_range(effect, q):
                if bound != 0:  # 0 is a value the data did not identify only where the range excludes it
                    assert judge(q.name, {"value": bound, "effect": effect.name}).plausible, (q.name, bound)


@pytest.mark.parametrize("value, unit, text", [
    (3.2e-9, "N", "3.2 nN"), (1.5e9, "Pa", "1.5 GPa"), (-24000.0, "Pa*s", "-24 kPa s"), (1e-19, "J", "1e-19 J"),
    (9.9999e-7, "N", "1 µN"), (0.0, "m", "0 m"), (0.3e-9, "m", "300 pm"), (0.024, "J/m^2", "0.024 J/m^2"),
])
def test_display_units(value, unit, text):
    assert display(value, unit) == text


def test_flagged_value_is_never_a_plain_number():
    text = flagged_value("viscosity", {"value": -24000.0, "error": 3000.0, "unit": "Pa*s", "effect": "viscoelastic"})
    assert text == "implausible: -24 kPa s ± 3 kPa s (1σ) (plausible: [0, 1e5] Pa s)"


# --------------------------------------------------------------------------- after a fit
@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """A short simulated DMT trace (a glassy polymer: no viscosity) and a config fitting it with DMT +
    viscoelastic; with the right calibration every read-out is plausible."""
    from afmid.cli import main

    folder = tmp_path_factory.mktemp("plausibility")
    text = (ROOT / "configs" / "dmt.yaml").read_text().replace("periods: 50 ", "periods: 12 ")
    (folder / "sim.yaml").write_text(text)
    assert main(["-q", "simulate", str(folder / "sim.yaml"), "-o", str(folder / "trace.h5")]) == 0
    raw = yaml.safe_load(text)
    raw.pop("simulate")
    raw["data"] = {"path": "trace.h5"}
    raw["fit"] = {"bootstrap": 10}
    raw["model"] = {"effects": ["dmt", "viscoelastic"]}
    (folder / "run.yaml").write_text(yaml.safe_dump(raw))
    return folder


def _parameters(path: Path) -> dict:
    with h5py.File(path, "r") as h5:
        params = {n: {"value": float(d[()]), "plausible": bool(d.attrs["plausible"]),
                      "plausibility": str(d.attrs["plausibility"])} for n, d in h5["model/parameters"].items()}
        diagnostics = h5["diagnostics"].attrs
        return params, int(diagnostics["n_implausible"]), list(diagnostics.get("implausible", []))


def test_a_trace_in_metres_read_as_nm_is_refused_not_flagged(workspace, run_cli):
    """A deflection of 1e-17 m: no force stands above the noise, so there is no result to flag (refused, exit 1)."""
    out = workspace / "run-units.h5"
    code, _, err = run_cli("-q", "fit", workspace / "run.yaml", "-o", out, "--set", "data.units=nm")
    assert code == 1 and "the fit has no usable result" in err and not out.exists()


@pytest.mark.parametrize("overrides, flagged, fragment", [
    ((), set(), None),
    # a quality factor 100x too low: the lever's own damping is overestimated, the sample seems to give energy back
    (("cantilever.quality_factor=2.5",), {"viscosity"}, "wrong sign"),
    # a spring constant 1000x too high: every force, and E*, 1000x too large
    (("cantilever.spring_constant=40000",), {"E_star", "hamaker", "surface_energy"}, "outside the plausible range"),
], ids=["plausible", "wrong-quality-factor", "wrong-spring-constant"])
def test_fit_flags_implausible_read_outs(workspace, run_cli, overrides, flagged, fragment):
    name = "run-" + "-".join(o.split("=")[0] for o in overrides) + ".h5"
    args = [a for o in overrides for a in ("--set", o)]
    code, _, err = run_cli("-q", "fit", workspace / "run.yaml", "-o", workspace / name, "--overwrite", *args)
    assert code == 0, err
    params, count, reasons = _parameters(workspace / name)
    implausible = {n for n, p in params.items() if not p["plausible"]}
    assert flagged <= implausible and implausible <= flagged | {"adhesion_force"}, params
    assert count == len(implausible) == len(reasons)
    warnings = [line for line in err.splitlines() if line.startswith("afmid: warning: implausible read-out: ")]
    assert len(warnings) == len(implausible)
    for n in implausible:
        reason = params[n]["plausibility"]
        assert reason.startswith(f"{n} ") and "[" in reason and fragment in reason
        assert any(reason in line for line in warnings)
    for n in set(params) - implausible:
        assert params[n]["plausibility"] == ""


@pytest.mark.parametrize("spring_constant, direction", [(4000.0, "large"), (0.4, "small")])
def test_fit_names_a_spring_constant_off_by_100x(workspace, run_cli, spring_constant, direction):
    """configs/dmt.yaml's trace fitted with k = 40 N/m declared 100x too large or too small: before issue 32, exit 0
    and every read-out plausible (E* 200 GPa or 20 MPa). Now flagged in the file and the warnings, with the cause."""
    out = workspace / f"run-k{spring_constant:g}.h5"
    code, _, err = run_cli("-q", "fit", workspace / "run.yaml", "-o", out, "--overwrite",
                           "--set", f"cantilever.spring_constant={spring_constant}")
    assert code == 0, err
    params, count, reasons = _parameters(out)
    assert not params["hamaker"]["plausible"] and count >= 1
    reason = params["hamaker"]["plausibility"]
    assert f"too {direction} would explain it" in reason and reason.endswith("check cantilever.spring_constant")
    assert f"at 100x too {direction}: hamaker would be" in reason, reason
    assert any(reason in line for line in err.splitlines() if line.startswith("afmid: warning: implausible"))


def test_report_marks_implausible_values(workspace, run_cli):
    good, bad = workspace / "good.h5", workspace / "bad.h5"
    assert run_cli("-q", "fit", workspace / "run.yaml", "-o", good, "--overwrite")[0] == 0
    assert run_cli("-q", "fit", workspace / "run.yaml", "-o", bad, "--overwrite",
                   "--set", "cantilever.quality_factor=2.5")[0] == 0
    code, out, err = run_cli("report", good, bad, "-o", workspace / "report", "--no-suggest", "--overwrite")
    assert code == 0, err
    assert "implausible read-outs in bad.h5: viscosity" in out
    assert "implausible read-outs in good.h5" not in out
    page = (workspace / "report" / "report.html").read_text(encoding="utf-8")
    table = page[page.index("<h2>Physical parameters</h2>"):page.index("<h2>The last run")]
    row = next(r for r in table.split("<tr>") if r.startswith("<td>viscosity</td>"))
    cells = row.split("<td>")[2:]
    bad_value = _parameters(bad)[0]["viscosity"]["value"]
    assert not cells[0].startswith("implausible") and cells[1].startswith("implausible: ")
    assert "(plausible: [0, 1e5] Pa s)" in cells[1] and f"{bad_value:.4g} Pa*s" not in cells[1]
    assert "Implausible read-outs" in table and "bad.h5: viscosity = " in table
    summary = json.loads((workspace / "report" / "summary.json").read_text())
    good_run, bad_run = summary["runs"]
    assert all(p["plausible"] for p in good_run["parameters"].values())
    assert bad_run["parameters"]["viscosity"]["plausible"] is False
    assert "[0, 1e5] Pa s" in bad_run["parameters"]["viscosity"]["plausibility"]


def test_run_files_without_verdicts_are_judged_when_read(workspace, run_cli):
    """A run file from before the check (no plausible attribute) still shows its implausible values flagged."""
    from afmid.batch.run import read_run_row
    from afmid.runfile import load_run

    old = workspace / "old.h5"
    assert run_cli("-q", "fit", workspace / "run.yaml", "-o", old, "--overwrite",
                   "--set", "cantilever.quality_factor=2.5")[0] == 0
    with h5py.File(old, "r+") as h5:
        for ds in h5["model/parameters"].values():
            del ds.attrs["plausible"], ds.attrs["plausibility"]
    assert load_run(old).quantities["viscosity"]["plausible"] is False
    assert load_run(old).quantities["E_star"]["plausible"] is True
    assert any(r.startswith("viscosity = ") for r in read_run_row(old)["implausible"])


def test_batch_lists_an_implausible_item_as_suspect(workspace, run_cli):
    (workspace / "list.yaml").write_text(yaml.safe_dump([
        {"path": "trace.h5", "name": "right"},
        {"path": "trace.h5", "name": "wrong_q", "set": {"cantilever.quality_factor": 2.5}},
    ]))
    out = workspace / "batch"
    code, _, err = run_cli("-q", "batch", workspace / "run.yaml", "--manifest", workspace / "list.yaml",
                           "-o", out, "-j", "1")
    assert code == 0, err  # suspect items are results, flagged: the batch exits 0 unless an item failed
    assert "afmid: warning: 1 of 2 traces suspect (wrong_q)" in err
    assert "afmid: warning: wrong_q: implausible read-out: viscosity = " in err
    with open(out / "summary.csv", newline="") as f:
        rows = {r["name"]: r for r in csv.DictReader(f)}
    assert rows["right"]["status"] == "ok" and rows["right"]["failure"] == ""
    assert rows["wrong_q"]["status"] == "suspect"
    assert rows["wrong_q"]["failure"].startswith("implausible read-outs: viscosity = ")
    assert Path(rows["wrong_q"]["run_file"]).name == "wrong_q.run.h5" and float(rows["wrong_q"]["viscosity_Pas"]) < 0
    with h5py.File(out / "summary.h5", "r") as h5:
        assert (h5.attrs["n_ok"], h5.attrs["n_suspect"], h5.attrs["n_failed"]) == (1, 1, 0)
    # resumed: the up-to-date suspect item stays suspect, the other is skipped
    code, _, err = run_cli("-q", "batch", workspace / "run.yaml", "--manifest", workspace / "list.yaml",
                           "-o", out, "-j", "1")
    assert code == 0, err
    with open(out / "summary.csv", newline="") as f:
        assert [r["status"] for r in csv.DictReader(f)] == ["skipped", "suspect"]


def test_effects_lists_the_plausible_ranges(run_cli):
    code, out, _ = run_cli("effects", "viscoelastic", "dmt")
    assert code == 0
    assert "yields viscosity [Pa*s]: sample viscosity eta (plausible: [0, 1e5] Pa s)" in out
    assert "yields adhesion_force [N]: adhesion force in contact (positive number) (plausible: [0, 1e-4] N)" in out
    code, out, _ = run_cli("effects", "--json", "jkr")
    (record,) = json.loads(out)
    ranges = {q["name"]: q["plausible_range"] for q in record["quantities"]}
    assert ranges["E_star"] == [1e2, 1e12] and ranges["surface_energy"] == [1e-4, 5.0]


# --------------------------------------------------------------------------- the estimated rest separation
@pytest.mark.parametrize("value, plausible", [(5e-9, True), (1e-12, True), (0.0, False), (-0.86e-9, False),
                                              (math.nan, False)])
def test_an_estimated_rest_separation_at_or_below_zero_is_flagged(value, plausible):
    from afmid.fit.plausibility import judge_separation

    verdict = judge_separation(value, 0.2e-9)
    assert verdict.plausible is plausible
    if not plausible:
        assert "sample.separation" in verdict.reason and "\n" not in verdict.reason
        assert "sample.separation" not in verdict.finding and "rest separation" in verdict.finding
    if value == -0.86e-9:
        assert "d = -860 pm ± 200 pm (1σ)" in verdict.reason


def test_a_run_whose_estimated_separation_is_below_zero_is_suspect(workspace, run_cli):
    """The fit estimated d <= 0 (seen on a Q 2 lever in liquid: -0.86 nm, truth 5 nm): the run file flags it on
    /model/separation and counts it among the implausible read-outs, so a batch lists the item as suspect; a
    positive estimate or a given separation carries no verdict against it."""
    import dataclasses

    from afmid.config import load_config
    from afmid.fit.pipeline import run_fit
    from afmid.runfile import read_summary, run_data, write_run

    config = load_config(workspace / "run.yaml", ["sample.separation=null", "fit.bootstrap=0"])
    result = run_fit(config)
    estimate = result.nonlinear["d"]
    assert estimate.estimated and estimate.value > 0
    good = workspace / "separation-good.h5"
    write_run(good, run_data(result, config), overwrite=True)
    with h5py.File(good, "r") as h5:
        assert h5["model/separation"].attrs["plausible"]
    assert read_summary(good)["implausible"] == []

    negative = dataclasses.replace(estimate, value=-0.86e-9)
    flagged = dataclasses.replace(result, nonlinear={**result.nonlinear, "d": negative})
    bad = workspace / "separation-bad.h5"
    write_run(bad, run_data(flagged, config), overwrite=True)
    with h5py.File(bad, "r") as h5:
        attrs = h5["model/separation"].attrs
        reason = str(attrs["plausibility"])
        assert not attrs["plausible"] and "-860 pm" in reason
        assert h5["diagnostics"].attrs["n_implausible"] == 1
        assert list(h5["diagnostics"].attrs["implausible"]) == [reason]
    assert read_summary(bad)["implausible"] == [reason]
    from afmid.report.fit_text import parameter_lines

    shown = [line for line in parameter_lines(flagged) if "rest separation d" in line]
    assert len(shown) == 1 and "IMPLAUSIBLE: the estimated rest separation d = -860 pm" in shown[0]
    assert not any("IMPLAUSIBLE" in line for line in parameter_lines(result) if "rest separation d" in line)


def test_read_out_records_the_terms_behind_each_read_out_only_when_asked():
    """The final fit's read-outs carry ``sources`` (the selected terms each is computed from: H, the adhesion and
    the surface energy from DMT's van der Waals term, E* from its Hertz term); the read-outs of resamples and
    propagations, made many times per fit, do not probe for them and carry none."""
    import numpy as np

    from afmid.config import ModelConfig
    from afmid.fit.forces import read_out
    from afmid.physics.library import build_library

    library = build_library(ModelConfig(effects=["dmt"]))
    labels = [t.label for t in library.terms]
    assert sorted(labels) == ["hertz", "vdw"]
    coef = np.array([9.5e-6 if label == "hertz" else -1e-29 for label in labels])  # E* > 0, attractive tail
    params = {"R": 1e-8, "a0": 0.165e-9}
    with_sources = read_out(library, coef, None, params, np.ones(len(labels), bool), None, with_sources=True)
    assert {name: q["sources"] for name, q in with_sources.items()} == {
        "hamaker": ("vdw",), "adhesion_force": ("vdw",), "surface_energy": ("vdw",), "E_star": ("hertz",)}
    plain = read_out(library, coef, None, params, np.ones(len(labels), bool), None)
    assert all("sources" not in q for q in plain.values())
    assert {n: q["value"] for n, q in plain.items()} == {n: q["value"] for n, q in with_sources.items()}
    hertz_only = read_out(library, coef, None, params, np.array([label == "hertz" for label in labels]), None,
                          with_sources=True)
    assert hertz_only["E_star"]["sources"] == ("hertz",) and hertz_only["hamaker"]["sources"] == ()


def test_flagged_value_shows_the_declared_tips_bound_the_verdict_used():
    """An adhesion of 34.4 uN for a declared 8 nm tip (Bruker's HSDC record at an assumed calibration) is
    implausible against that tip's bound, and the table and the terminal show that bound, not the catalog's
    tip-independent range (the report printed "(plausible: [0, 1e-4] N)" beside a verdict of [0, 5.027e-7] N)."""
    from afmid.fit.plausibility import range_words, tip_scaled_range
    from afmid.report.page import parameter_text

    q = {"value": 34.4e-6, "error": 131e-6, "unit": "N", "effect": "dmt", "plausible": False}
    low, high, _ = tip_scaled_range("adhesion_force", "dmt", 8e-9)
    assert high < plausible_range("adhesion_force", "dmt")[1]
    tip_bound = f"(plausible: {range_words(low, high, 'N')})"
    assert tip_bound == "(plausible: [0, 5.027e-7] N)"
    assert tip_bound in flagged_value("adhesion_force", q, 8e-9)
    assert tip_bound in flagged_value("adhesion_force", {**q, "tip_radius": 8e-9})
    assert tip_bound in parameter_text(q, "adhesion_force", 8e-9)
    # Without a declared tip the catalog's range is all there is.
    generic = plausible_range("adhesion_force", "dmt")
    assert f"(plausible: {range_words(generic[0], generic[1], 'N')})" in flagged_value("adhesion_force", q)
