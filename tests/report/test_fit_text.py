"""What `afmid fit` prints (afmid/report/fit_text.py): the identified law, the parameters in human units with
labelled intervals, plausibility, the model-limited verdict, the error against its floor; `-v` the selection.

Short simulated fits (12 periods, 10 bootstrap draws): a DMT + Kelvin-Voigt trace fitted with [dmt] (the model
misses the viscosity: model-limited) and with [dmt, viscoelastic] (at the
floor); a pure DMT trace fitted with [dmt, viscoelastic] (the viscosity is not determined).
"""

from __future__ import annotations

import math
import re

import pytest

from repo_paths import TEST_CONFIGS


def _short_config(folder, source, effects, trace):
    text = (TEST_CONFIGS / source).read_text()
    text = re.sub(r"(?m)^  periods: 50\b", "  periods: 12", text)
    text = re.sub(r"(?m)^  (library|effects): .*$", f"  effects: [{', '.join(effects)}]", text)
    text = re.sub(r"(?m)^fit:\n(  .*\n)*", "", text)
    assert "periods: 12" in text and "effects: [" in text
    path = folder / f"{source.removesuffix('.yaml')}_{'_'.join(effects)}.yaml"
    path.write_text(text + f"\ndata: {{path: {trace}}}\nfit: {{bootstrap: 10, seed: 0}}\n")
    return path


@pytest.fixture(scope="module")
def traces(tmp_path_factory):
    """The two simulated traces (12 periods each), by name, in one folder."""
    from afmid.cli import main

    folder = tmp_path_factory.mktemp("fit_text")
    for source, name in (("dmt_viscoelastic.yaml", "ve.h5"), ("dmt.yaml", "dmt.h5")):
        config = _short_config(folder, source, ["dmt"], name)
        assert main(["-q", "simulate", str(config), "-o", str(folder / name)]) == 0
    return folder


def _fit(run_cli, folder, source, effects, trace, *flags):
    config = _short_config(folder, source, effects, trace)
    code, out, err = run_cli(*flags, "fit", config, "-o", folder / f"{config.stem}.run.h5", "--overwrite")
    assert code == 0, err
    return out, err


def _parameter(out: str, name: str) -> str:
    (line,) = [x.strip() for x in out.splitlines() if x.strip().startswith((f"{name} =", f"{name}:"))]
    return line


MEASUREMENT = r"-?[0-9.]+ ± [0-9.]+ {unit} \(1σ\), \[-?[0-9.]+, -?[0-9.]+\] {unit} \(95 %\)"


def test_fit_prints_the_law_and_parameters_in_human_units(traces, run_cli):
    out, err = _fit(run_cli, traces, "dmt_viscoelastic.yaml", ["dmt", "viscoelastic"], "ve.h5")
    assert "wrote" in err and "wrote" not in out  # the log line stays on stderr, the read-out is stdout
    law = out.split("physical parameters:")[0]
    assert law.startswith("identified law") and "dmt.hertz:" in law and "viscoelastic.kelvin_voigt:" in law
    assert "N/m^1.5 (1σ) x [z <= a0] * delta^1.5" in law  # coefficient unit, label and the term's expression
    for name, unit in (("E_star", "MPa"), ("hamaker", "zJ"), ("adhesion_force", "nN"), ("viscosity", "Pa s")):
        line = _parameter(out, name)
        assert re.fullmatch(rf"{name} = {MEASUREMENT.format(unit=unit)}; plausible", line), line
    # the numbers are the fit's in the display unit: the simulated E* is 1 GPa (a factor 1000 off would show)
    e_star = float(_parameter(out, "E_star").split(" = ")[1].split(" ±")[0])
    assert 800 < e_star < 1250
    assert "MODEL-LIMITED" not in out and "verdict: at the noise floor" in out
    folds = re.search(r"force error \(cross-validated, relative RMS\) ([0-9.]+) \(folds ([0-9.]+) to ([0-9.]+), "
                      r"5 folds\), noise floor ([0-9.]+)", out)
    assert folds, out
    error, low, high, floor = map(float, folds.groups())
    assert low <= error <= high and floor > 0
    assert "selection:" not in out  # only with -v


def test_a_model_limited_fit_says_so_on_every_parameter(traces, run_cli):
    out, err = _fit(run_cli, traces, "dmt_viscoelastic.yaml", ["dmt"], "ve.h5", "-v")
    for name in ("E_star", "hamaker", "adhesion_force"):
        assert _parameter(out, name).endswith("; MODEL-LIMITED (biased beyond its error bar)")
    verdict = next(x for x in out.splitlines() if x.startswith("verdict:"))
    assert verdict.startswith("verdict: MODEL-LIMITED: x") and "the floor" in verdict
    assert "model-limited" in err  # the warning stays on stderr
    # -v: the selection's candidates with their criterion relative to the chosen one, the dropped terms
    selection = out.split("selection: ")[1]
    assert selection.startswith("criterion bic,") and "chosen: dmt.vdw, dmt.hertz" in selection
    rows = [x for x in selection.splitlines() if "ΔBIC" in x]
    assert len(rows) >= 2 and rows[0].lstrip().startswith("* ΔBIC       0")
    assert all(float(x.split("ΔBIC")[1].split()[0]) >= 0 for x in rows)  # ranked best first
    assert "dropped: " in selection


def test_a_term_not_selected_reads_not_determined(traces, run_cli):
    out, _ = _fit(run_cli, traces, "dmt.yaml", ["dmt", "viscoelastic"], "dmt.h5")
    line = _parameter(out, "viscosity")
    assert line.startswith("viscosity: NOT DETERMINED (viscoelastic.kelvin_voigt not selected, inclusion probability")
    assert re.search(r"with its term forced in: \[-?[0-9.]+, -?[0-9.]+\] Pa s \(95 %\)", line), line
    assert not re.search(r"± 0(\.0*)? |-0 ", out)  # no zero error bar, no negative zero
    assert _parameter(out, "E_star").endswith("; plausible")


def test_quantity_line_flags_an_implausible_read_out():
    from afmid.report.fit_text import quantity_line

    q = {"value": -24e3, "error": 3e3, "ci_low": -30e3, "ci_high": -18e3, "unit": "Pa*s", "effect": "viscoelastic",
         "model_limited": False}
    line = quantity_line("viscosity", q)
    assert line.startswith("viscosity = (-2.40 ± 0.30)e4 Pa s (1σ)") or line.startswith("viscosity = -24000 ± 3000")
    assert "IMPLAUSIBLE: viscosity" in line and "wrong sign" in line
    q_nan = dict(q, value=math.nan)
    assert "IMPLAUSIBLE" in quantity_line("viscosity", q_nan)


def test_the_one_sigma_split_names_the_part_added_after_it():
    """The HSDC record's first half (k 0.8 N/m, 50 nm/V, calibration uncertainties declared) read "hamaker = (0 ±
    4)e7 zJ (1σ); of the 1σ: statistical 87000 zJ, calibration 34 zJ": the model-limited separation's widening,
    added after the split, was in neither part. Now the rest is named: sqrt(4.19e-14^2 - 8.7e-17^2 - 3.4e-20^2) J
    = 4.19e-14 J to 3 digits; without a rest (the parts make the 1 sigma) nothing is added; the table's cell
    likewise."""
    from afmid.report.fit_text import quantity_line
    from afmid.report.page import quantity_cell

    q = {"value": 3.43e-19, "error": 4.19e-14, "error_statistical": 8.7e-17, "error_calibration": 3.4e-20,
         "ci_low": -8.2e-14, "ci_high": 8.2e-14, "unit": "J", "effect": "dmt", "model_limited": True}
    line = quantity_line("hamaker", q)
    assert "of the 1σ, in quadrature: statistical 87000 zJ, calibration 34 zJ, the rest 4.2e7 zJ" in line, line
    assert "stat 87000 zJ / cal 34 zJ / rest 4.2e7 zJ in quadrature" in quantity_cell(q), quantity_cell(q)
    made_up = dict(q, error=math.hypot(8.7e-17, 3.4e-20))
    assert "the rest" not in quantity_line("hamaker", made_up) and "rest" not in quantity_cell(made_up)


def test_the_one_sigma_split_names_a_separation_track_s_share():
    """A separation track's read-out stores its share (``error_separation_track``) and no statistical part: the
    split names both, the statistical part being what the 1 sigma holds beyond the share in quadrature,
    sqrt(130^2 - 45^2) MPa = 121.96 MPa (120 MPa at 2 digits). With a calibration part too, all three are named and
    the rest is what none of them holds: sqrt(5^2 - 3^2 - 2^2 - 1^2) MPa = sqrt(11) = 3.3 MPa (2 digits each). A read-out with
    neither a calibration nor a track part has no split, and no text names a track."""
    from afmid.report.fit_text import quantity_line
    from afmid.report.page import quantity_cell

    track = {"value": 2.15e9, "error": 130e6, "error_separation_track": 45e6, "ci_low": 1.9e9, "ci_high": 2.39e9,
             "unit": "Pa", "effect": "dmt", "model_limited": False}
    line = quantity_line("E_star", track)
    assert "; of the 1σ, in quadrature: statistical 120 MPa, separation track 45 MPa; plausible" in line, line
    assert quantity_cell(track) == "2150 ± 130 MPa (1σ; stat 120 MPa / track 45 MPa in quadrature)", quantity_cell(track)
    three = dict(track, error=5e6, error_statistical=3e6, error_calibration=2e6, error_separation_track=1e6)
    assert ("of the 1σ, in quadrature: statistical 3.0 MPa, calibration 2.0 MPa, separation track 1.0 MPa, the rest "
            "3.3 MPa (widened after them") in quantity_line("E_star", three), quantity_line("E_star", three)
    assert "(1σ; stat 3.0 MPa / cal 2.0 MPa / track 1.0 MPa / rest 3.3 MPa in quadrature)" in quantity_cell(three)
    # the parts make up the 1 sigma: no rest
    made_up = dict(three, error=math.sqrt(3e6**2 + 2e6**2 + 1e6**2))
    assert "rest" not in quantity_line("E_star", made_up) and "rest" not in quantity_cell(made_up)
    for plain in (dict(track, error_separation_track=0.0), {k: v for k, v in track.items() if k != "error_separation_track"}):
        assert "of the 1σ" not in quantity_line("E_star", plain) and "track" not in quantity_line("E_star", plain)
        assert quantity_cell(plain) == "2150 ± 130 MPa (1σ)", quantity_cell(plain)


def test_fit_says_once_that_intervals_are_statistical_only_without_a_declared_calibration(traces, run_cli):
    """Issue 29: without k, Q or invols uncertainties the read-out and the run file say the intervals hold noise
    only; with one declared (here invols, on a config that has none) neither says it."""
    import h5py

    from afmid.fit.uncertainty import INTERVALS_STATISTICAL, INTERVALS_WITH_CALIBRATION, STATISTICAL_ONLY_TEXT

    out, _ = _fit(run_cli, traces, "dmt.yaml", ["dmt"], "dmt.h5")
    assert out.count(STATISTICAL_ONLY_TEXT) == 1
    assert "declare cantilever.spring_constant_uncertainty, cantilever.quality_factor_uncertainty, " \
           "data.invols_uncertainty to include it" in STATISTICAL_ONLY_TEXT
    with h5py.File(traces / "dmt_dmt.run.h5") as h5:
        assert h5.attrs["intervals"] == INTERVALS_STATISTICAL
    config = _short_config(traces, "dmt.yaml", ["dmt"], "dmt.h5")
    code, out, err = run_cli("fit", config, "-o", traces / "dmt_dmt.run.h5", "--overwrite",
                             "--set", "data.invols_uncertainty=0.03")
    assert code == 0, err
    assert STATISTICAL_ONLY_TEXT not in out
    assert "calibration" in _parameter(out, "E_star")  # the share shown beside the statistical part
    with h5py.File(traces / "dmt_dmt.run.h5") as h5:
        assert h5.attrs["intervals"] == INTERVALS_WITH_CALIBRATION
