"""A calibrated drive (``drive.force_amplitude`` + ``drive.phase``, afmid/fit/declared_drive.py).

Issue 15: with the drive fitted, the inverted force F = F_drive - (m x'' + c x' + k x) depends on the force model
(the demo's [dmt] fit of a viscoelastic sample: 3.4 eV dissipated per period, truth 56.7 eV). With the
simulator's own drive declared (phase 0 at the first sample, the file's F0) it must not.

Tolerances, fixed from the arithmetic before the seeds below were run:
- model independence: the inverted force with a declared drive is Y_block (no fitted column enters it with
  fit.baseline: zero), the same code path for every library and separation: the same bits.
- accuracy against the truth: the energy from a 50-period record carries the change of the lever's
  mechanical energy across the record, which thermal motion sets: sigma_E ~ k A sqrt(2 kB T / k) / N per
  period (0.6 eV for the demo lever); the truth itself is a trapezoid of -F dz on 200 samples per period
  (measured against the true motion's energy balance: up to 4 % on the stiffest set, where contact is
  sharpest). Allowed: 3 sigma_E + 5 % of the truth.
- miscalibration: the drive enters the inverted force linearly, so F0 (1 + e) moves the energy by e times the
  drive's work per period, to rounding (1e-9 relative).
"""

from __future__ import annotations

import copy
import math

import h5py
import numpy as np
import pytest
import yaml

from afmid.config import build_config, dump_config
from afmid.errors import ConfigError
from afmid.io.trace import write_trace_file
from repo_paths import REPO_ROOT

BOLTZMANN = 1.380649e-23
EV = 1.602176634e-19
#: (E_star Pa, viscosity Pa s, free amplitude m, separation m): the demo's soft polymer and a stiffer one.
PARAMETER_SETS = {"soft": (0.35e9, 40.0, 15e-9, 10.5e-9), "stiffer": (1.0e9, 100.0, 12e-9, 9.5e-9)}
SEEDS = (11, 12, 13)


def demo_raw(folder, seed=7, parameters=PARAMETER_SETS["soft"], periods=50) -> dict:
    raw = yaml.safe_load((REPO_ROOT / "afmid" / "templates" / "demo_ldpe.yaml").read_text())
    E, eta, A0, d = parameters
    raw["simulate"]["parameters"].update(E_star=E, viscosity=eta)
    raw["simulate"].update(seed=seed, periods=periods)
    raw["drive"]["free_amplitude"] = A0
    raw["sample"]["separation"] = d
    raw["data"] = {"path": str(folder / "trace.h5")}
    raw["fit"] = {"bootstrap": 0}
    return raw


def simulated(folder, raw: dict):
    from afmid.simulate.driver import simulate

    config = build_config(copy.deepcopy(raw), source=folder / "sim.yaml", base_dir=folder)
    write_trace_file(folder / "trace.h5", simulate(config), dump_config(config))


def fitted(folder, raw: dict, *, phase=None, amplitude=None, effects=("dmt",), d_given=True, name="run.h5"):
    """(fit result, energy_check of its run file)."""
    from afmid.diagnosis.localize import energy_check
    from afmid.fit.pipeline import run_fit
    from afmid.runfile import run_data, write_run
    from afmid.runfile import load_run

    raw = copy.deepcopy(raw)
    raw["model"] = {"effects": list(effects)}
    if phase is not None:
        raw["drive"]["phase"] = phase
    if amplitude is not None:
        raw["drive"].pop("free_amplitude")
        raw["drive"]["force_amplitude"] = amplitude
    if not d_given:
        raw["sample"]["separation"] = None
    config = build_config(raw, source=folder / "fit.yaml", base_dir=folder)
    result = run_fit(config, uncertainty=False)
    write_run(folder / name, run_data(result, config), overwrite=True)
    return result, energy_check(load_run(folder / name))


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    folder = tmp_path_factory.mktemp("declared_drive")
    raw = demo_raw(folder, periods=30)
    simulated(folder, raw)
    return folder, raw


# --------------------------------------------------------------------------- bad input: one line each
@pytest.mark.parametrize("drive, fit, key, words", [
    ({"phase": 0.0}, {}, "drive.force_amplitude", "needs its amplitude"),
    ({"phase": 0.0, "force_amplitude": 2.4e-9}, {"cantilever": "free"}, "drive.phase", "fit.cantilever: fixed"),
    ({"phase": 0.0, "force_amplitude": 2.4e-9}, {"drive_frequency": "search"}, "fit.drive_frequency", "auto or nominal"),
])
def test_an_unusable_declaration_is_one_config_error(tmp_path, drive, fit, key, words):
    from afmid.fit.declared_drive import declared_drive

    raw = {"data": {"path": "x.h5"}, "drive": {"frequency": 3e5, **drive}, "fit": fit}
    config = build_config(raw, source=tmp_path / "fit.yaml", base_dir=tmp_path)

    class NoAmplitudeTrace:
        drive_force_amplitude = None
        drive_frequency = 3e5

    with pytest.raises(ConfigError) as caught:
        declared_drive(config, NoAmplitudeTrace())
    assert caught.value.key == key and words in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize("drive, words", [
    ({"force_amplitude_uncertainty": 0.02}, "needs drive.phase"),
    ({"phase": 0.0, "phase_uncertainty": -0.1}, "drive.phase_uncertainty: must be >= 0"),
    ({"phase": ".nan"}, "finite"),
    ({"phase": 0.0, "force_amplitude_uncertainty": 2.0}, "drive.force_amplitude_uncertainty: must be < 1"),
])
def test_bad_drive_keys_are_refused_on_one_line(tmp_path, drive, words):
    text = yaml.safe_dump({"data": {"path": "x.h5"}, "drive": {"frequency": 3e5, **drive}}).replace("'.nan'", ".nan")
    (tmp_path / "fit.yaml").write_text(text)
    from afmid.config import load_config

    with pytest.raises(ConfigError) as caught:
        load_config(tmp_path / "fit.yaml")
    message = str(caught.value)
    assert words in message and "drive." in message and "\n" not in message


def test_the_simulator_refuses_a_drive_phase_it_cannot_make(tmp_path):
    from afmid.simulate.model import resolve_setup

    raw = demo_raw(tmp_path)
    raw["drive"]["phase"] = 0.3
    with pytest.raises(ConfigError) as caught:
        resolve_setup(build_config(raw, source=tmp_path / "sim.yaml", base_dir=tmp_path))
    assert caught.value.key == "drive.phase" and "phase 0" in str(caught.value)
    raw["drive"]["phase"] = 0.0  # the simulator's own convention: accepted, so one config serves both
    resolve_setup(build_config(raw, source=tmp_path / "sim.yaml", base_dir=tmp_path))


# --------------------------------------------------------------------------- what depends on what
def test_with_a_declared_drive_the_inverted_force_does_not_depend_on_the_model(demo):
    folder, raw = demo
    dmt, _ = fitted(folder, raw, phase=0.0)
    both, _ = fitted(folder, raw, phase=0.0, effects=("dmt", "viscoelastic"))
    unknown_d, _ = fitted(folder, raw, phase=0.0, d_given=False)
    np.testing.assert_array_equal(dmt.force_inverted, both.force_inverted)
    np.testing.assert_array_equal(dmt.force_inverted, unknown_d.force_inverted)
    for name in ("force_inverted", "dissipated_energy_inverted"):
        np.testing.assert_array_equal(dmt.periods[name], both.periods[name])
    # and with the drive fitted it does (the complaint): the [dmt] fit's drive takes up the dissipation
    # [dmt] cannot describe, so the energy from its inverted force falls far below the full model's
    _, free_dmt = fitted(folder, raw)
    _, free_both = fitted(folder, raw, effects=("dmt", "viscoelastic"))
    assert free_both["inverted"] - free_dmt["inverted"] > 0.5 * free_both["truth"]


def test_the_run_file_says_which_drive_the_inverted_force_used(demo):
    from afmid.runfile import DRIVE_CALIBRATED, DRIVE_FITTED, load_run

    folder, raw = demo
    result, _ = fitted(folder, raw, phase=0.0, name="declared.h5")
    F0 = result.prep.trace.drive_force_amplitude
    with h5py.File(folder / "declared.h5") as h5:
        drive = h5["model/drive"]
        assert drive.attrs["source"] == DRIVE_CALIBRATED and drive.attrs["force_amplitude_source"] == "file"
        assert drive["force_amplitude"][()] == pytest.approx(F0, rel=1e-12)
        assert drive["cos"][()] == pytest.approx(F0, rel=1e-12) and drive["sin"][()] == 0.0
        assert drive["phase"][()] == 0.0 and drive["phase"].attrs["units"] == "rad"
        assert drive.attrs["frequency_source"].startswith("nominal")
        assert h5["force/inverted"].attrs["drive"] == "calibrated"
        assert "not on the force model" in h5["force/inverted"].attrs["meaning"]
    assert load_run(folder / "declared.h5").drive_calibrated
    fitted(folder, raw, name="fitted.h5")
    with h5py.File(folder / "fitted.h5") as h5:
        assert h5["model/drive"].attrs["source"] == DRIVE_FITTED and h5["force/inverted"].attrs["drive"] == "fitted"
        assert "phase" not in h5["model/drive"]
    assert not load_run(folder / "fitted.h5").drive_calibrated


def test_an_older_run_file_is_read_under_the_new_names(demo):
    from afmid.runfile import load_run

    folder, raw = demo
    fitted(folder, raw, name="old.h5")
    current = load_run(folder / "old.h5")
    with h5py.File(folder / "old.h5", "r+") as h5:  # as afmid wrote it before the names changed
        h5.move("force/inverted", "force/direct")
        for name in ("force", "dissipated_energy", "virial"):
            new = f"{name}_inverted" if name != "force" else "force_inverted"
            h5.move(f"periods/{new}", f"periods/{new.replace('inverted', 'direct')}")
        del h5["model/drive"].attrs["source"]
    old = load_run(folder / "old.h5")
    assert not old.drive_calibrated
    np.testing.assert_array_equal(old.force["inverted"], current.force["inverted"])
    for name in ("force_inverted", "dissipated_energy_inverted", "virial_inverted"):
        np.testing.assert_array_equal(old.periods[name], current.periods[name])


def test_a_miscalibrated_amplitude_moves_the_energy_by_its_share_of_the_drive_work(demo):
    folder, raw = demo
    result, exact = fitted(folder, raw, phase=0.0)
    F0 = result.prep.trace.drive_force_amplitude
    for error in (0.02, 0.05):
        _, off = fitted(folder, raw, phase=0.0, amplitude=F0 * (1 + error))
        assert off["inverted"] - exact["inverted"] == pytest.approx(error * exact["drive_work"], rel=1e-9)
        assert off["energy_balance"] - exact["energy_balance"] == pytest.approx(error * exact["drive_work"], rel=1e-9)


def test_the_drive_calibration_uncertainty_reaches_the_energy(demo, tmp_path):
    """The declared 1 sigma of F0 and phase give the energy's: checked against refits at F0 (1 + s) and phase + s."""
    folder, raw = demo
    result, exact = fitted(folder, raw, phase=0.0)
    F0 = result.prep.trace.drive_force_amplitude
    raw_u = copy.deepcopy(raw)
    raw_u["drive"].update(force_amplitude_uncertainty=0.02, phase_uncertainty=0.01)
    _, stated = fitted(folder, raw_u, phase=0.0)
    _, high_F0 = fitted(folder, raw, phase=0.0, amplitude=F0 * 1.02)
    _, turned = fitted(folder, raw, phase=0.01)
    expected = math.hypot(high_F0["inverted"] - exact["inverted"], turned["inverted"] - exact["inverted"])
    # the phase enters through sin and cos: linear to 1 - cos(0.01) ~ 5e-5 of the turned work
    assert stated["drive_calibration_sigma"] == pytest.approx(expected, rel=1e-3)
    assert exact["drive_calibration_sigma"] == 0.0  # no uncertainty declared


# --------------------------------------------------------------------------- accuracy against the truth
@pytest.mark.parametrize("set_name", sorted(PARAMETER_SETS))
def test_the_declared_drive_gives_the_true_dissipated_energy_with_dmt_alone(tmp_path, set_name):
    """The hidden-viscoelasticity case fitted with [dmt] only, several seeds, the separation given and not."""
    for seed in SEEDS:
        folder = tmp_path / str(seed)
        folder.mkdir()
        raw = demo_raw(folder, seed=seed, parameters=PARAMETER_SETS[set_name])
        simulated(folder, raw)
        result, energy = fitted(folder, raw, phase=0.0, d_given=False)
        cl = result.prep.trace.cantilever
        amplitude = float(np.mean(result.periods["amplitude"]))
        thermal = BOLTZMANN * raw["simulate"].get("noise", {}).get("temperature", 300.0) / cl.spring_constant
        sigma = cl.spring_constant * amplitude * math.sqrt(2 * thermal) / result.prep.blocks.n_blocks
        truth = energy["truth"]
        assert abs(energy["inverted"] - truth) <= 3 * sigma + 0.05 * truth, (seed, energy["inverted"] / EV,
                                                                              truth / EV, sigma / EV)


def test_a_free_oscillation_gives_the_simulators_drive(tmp_path):
    """The calibration a user makes: a free oscillation (the tip 1 um away) recorded with the same drive and time
    zero; its first harmonic's amplitude and phase through drive_from_free_oscillation give back the simulator's
    F0 and phase 0. Tolerance: thermal motion moves the amplitude by sqrt(kB T / k) = 1e-11 m (7e-4 of 15 nm;
    the correlation time Q / pi ~ 80 periods leaves no averaging over 30 periods): 5 times that, relative for F0
    and in rad for the phase."""
    from afmid.fit.declared_drive import drive_from_free_oscillation
    from afmid.io.trace import load_trace
    from afmid.preprocess.harmonics import estimate_drive

    raw = demo_raw(tmp_path, periods=30)
    raw["sample"]["separation"] = 1e-6
    simulated(tmp_path, raw)
    trace = load_trace(build_config(copy.deepcopy(raw), source=tmp_path / "fit.yaml", base_dir=tmp_path))
    free = estimate_drive(trace.deflection, trace.times, trace.drive_frequency)
    cl = trace.cantilever
    F0, phase = drive_from_free_oscillation(cl.spring_constant, cl.resonance_frequency, cl.quality_factor,
                                            trace.drive_frequency, free.amplitude, free.phase)
    tolerance = 5 * math.sqrt(BOLTZMANN * 300.0 / cl.spring_constant) / free.amplitude
    assert F0 == pytest.approx(trace.drive_force_amplitude, rel=tolerance)
    assert abs(math.remainder(phase, 2 * math.pi)) < tolerance


def test_a_map_refuses_a_calibrated_drive_instead_of_ignoring_it(tmp_path):
    from afmid.maps.run import run_map

    raw = {"data": {"path": "x.h5"}, "drive": {"frequency": 3e5, "force_amplitude": 2.4e-9, "phase": 0.0}}
    config = build_config(raw, source=tmp_path / "map.yaml", base_dir=tmp_path)
    with pytest.raises(ConfigError) as caught:
        run_map(config, "", tmp_path / "map.h5", tmp_path / "out.h5", engine=None)
    assert caught.value.key == "drive.phase" and "single traces" in str(caught.value)
    assert not (tmp_path / "out.h5").exists()


def test_the_report_of_a_calibrated_run_says_what_its_energy_rows_depend_on(demo):
    """The report of a run with a calibrated drive (its diagnosis refits with the same drive): the header and
    the energy rows name the calibrated drive, and the declared uncertainties give a labelled 1 sigma."""
    from afmid.report.page import make_report

    folder, raw = demo
    raw = copy.deepcopy(raw)
    raw["drive"].update(force_amplitude_uncertainty=0.01, phase_uncertainty=0.01)
    fitted(folder, raw, phase=0.0, name="report_run.h5")
    make_report([folder / "report_run.h5"], folder / "report", suggest_effects=False)
    page = (folder / "report" / "report.html").read_text()
    assert "inverted force (cantilever equation, calibrated drive)" in page
    assert "this force does not depend on the model" in page and "(1σ, drive calibration)" in page
    assert "model-free" not in page


def test_the_drive_calibration_uncertainty_reaches_the_read_outs(demo):
    """The declared 1 sigma of F0 widens E* and the viscosity by their change in refits at F0 (1 +- s) (the
    right model, d given: the support does not change). The propagation solves on the fit's weights; a refit
    re-weights the rows with the new force (second order in s): 10 % agreement."""
    from afmid.config import build_config
    from afmid.fit.pipeline import run_fit

    folder, raw = demo
    effects = ("dmt", "viscoelastic")
    s = 0.02

    def fit(**drive):
        r = copy.deepcopy(raw)
        r["model"] = {"effects": list(effects)}
        r["drive"].update(phase=0.0, **drive)
        return run_fit(build_config(r, source=folder / "fit.yaml", base_dir=folder))

    plain = fit()
    F0 = plain.prep.trace.drive_force_amplitude
    stated = fit(force_amplitude_uncertainty=s)
    up, down = (fit(force_amplitude=F0 * (1 + sign * s)).quantities for sign in (1, -1))
    for name in ("E_star", "viscosity"):
        expected = 0.5 * abs(up[name]["value"] - down[name]["value"])
        q = stated.quantities[name]
        assert q["error_calibration"] == pytest.approx(expected, rel=0.1), name
        statistical = plain.quantities[name]["error"]  # NaN: bootstrap off, the calibration is all there is
        assert q["error"] == pytest.approx(math.hypot(statistical if math.isfinite(statistical) else 0.0, expected),
                                           rel=0.1)
        assert q["ci_high"] - q["ci_low"] >= 2 * 1.96 * q["error_calibration"] * (1 - 1e-9)
