"""The Python front door (afmid.api): cheap to import, the same numbers as the command line, a run file round
trip that gives the same table, short reprs, and one-line errors for bad arrays."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

import afmid
from afmid.errors import ConfigError, InputError
from repo_paths import REPO_ROOT

HEAVY = ("numba", "scipy", "h5py", "matplotlib")
LEVER = {"spring_constant": 40.0, "resonance_frequency": 3.0e5, "quality_factor": 250.0, "tip_radius": 10e-9}
#: A clean DMT trace (E* 1 GPa, H 1e-19 J, d 12 nm), short: 20 periods.
SIMULATION = {"cantilever": LEVER, "drive": {"frequency": 3.0e5, "free_amplitude": 15e-9},
              "sample": {"separation": 12e-9},
              "simulate": {"model": "dmt", "periods": 20, "seed": 1, "noise": {"detector_rms": 1e-12},
                           "parameters": {"E_star": 1.0e9, "hamaker": 1.0e-19}}}


@pytest.fixture(scope="module")
def simulated():
    return afmid.simulate_trace(SIMULATION)


@pytest.fixture(scope="module")
def dmt_fit(simulated):
    return afmid.ForceModel(["dmt"], fit={"bootstrap": 10}).fit(simulated)


def test_import_afmid_loads_no_heavy_module():
    """``import afmid`` and the front door's names load none of numba, scipy, h5py, matplotlib (the CLI's
    start-up and a notebook's first cell stay fast); they come with the first fit."""
    code = ("import sys, afmid; before = [m for m in {heavy} if m in sys.modules]; "
            "afmid.Trace, afmid.ForceModel, afmid.Fit, afmid.load; "
            "after = [m for m in {heavy} if m in sys.modules]; print(before, after)").format(heavy=HEAVY)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO_ROOT)
    assert out.stdout.strip() == "[] []"


def test_the_package_lists_its_front_door():
    assert set(afmid.__all__) >= {"Trace", "Cantilever", "ForceModel", "Fit", "read", "load", "simulate_trace"}
    assert set(afmid.__all__) <= set(dir(afmid))
    assert afmid.Trace is afmid.api.Trace and afmid.Cantilever is afmid.io.trace.Cantilever
    with pytest.raises(AttributeError, match="no attribute 'Trcae'"):
        afmid.Trcae  # noqa: B018


def test_a_fit_is_one_short_line(dmt_fit):
    text = repr(dmt_fit)
    assert "\n" not in text and len(text) < 300, text
    assert text.startswith("<afmid.Fit 'dmt'")


def test_save_and_load_give_the_same_table_and_text(dmt_fit, tmp_path):
    path = dmt_fit.save(tmp_path / "run.h5")
    again = afmid.load(path)
    assert again.parameters == dmt_fit.parameters  # float64 through HDF5 and back: bit for bit
    assert again.cv_error == dmt_fit.cv_error and again.terms == dmt_fit.terms
    # the same lines, the record-length clause included; the file orders the parameters by name
    assert sorted(again.text().splitlines()) == sorted(dmt_fit.text().splitlines())
    with pytest.raises(ConfigError, match="a loaded fit is its run file already"):
        again.save(tmp_path / "other.h5")


def test_a_loaded_fit_says_what_the_fit_said(simulated, tmp_path):
    """The fit's verdicts outside its text (the implausible read-outs' reasons, its warnings, its log line) come
    from the fit itself and from a loaded fit's run file alike. The lever declared 1000x too stiff makes every
    force 1000x too large: the Hamaker constant and the surface energy leave their plausible ranges
    (tests/fit/test_plausibility.py), so the lists compared are not empty."""
    stiff = afmid.Cantilever(40000.0, LEVER["resonance_frequency"], LEVER["quality_factor"],
                             tip_radius=LEVER["tip_radius"])
    trace = afmid.Trace.from_array(simulated.deflection, simulated.sample_rate, cantilever=stiff,
                                   drive_frequency=simulated.drive_frequency)
    fit = afmid.ForceModel(["dmt"], fit={"bootstrap": 0}).fit(trace)
    again = afmid.load(fit.save(tmp_path / "stiff.h5"), trace=trace)
    assert {"hamaker", "surface_energy"} <= {reason.split(" ")[0] for reason in fit.implausible}
    assert sorted(again.implausible) == sorted(fit.implausible)
    assert again.warnings == fit.warnings
    assert again.summary_line() == fit.summary_line() == (f"cv_error {fit.cv_error:.4f}; terms: "
                                                          f"{', '.join(fit.terms)}")
    assert sorted(again.text().splitlines()) == sorted(fit.text().splitlines())


def test_the_front_door_gives_the_numbers_of_afmid_fit(tmp_path, run_cli, simulated):
    """``afmid fit CONFIG -o run.h5`` and ``ForceModel.from_config(config).fit(afmid.read(trace))``: the same
    computation on the same samples, so the same parameters to the bit."""
    import yaml

    from afmid.config import load_config
    from afmid.io.trace import write_trace_file

    trace_path = write_trace_file(tmp_path / "trace.h5", simulated, "")
    config = {**SIMULATION, "data": {"path": str(trace_path)}, "model": {"effects": ["dmt"]},
              "fit": {"bootstrap": 10}}
    config_path = tmp_path / "run.yaml"
    config_path.write_text(yaml.safe_dump(config))
    code, _, err = run_cli("-q", "fit", config_path, "-o", tmp_path / "cli.h5")
    assert code == 0, err
    fit = afmid.ForceModel.from_config(load_config(config_path)).fit(afmid.read(trace_path))
    assert fit.parameters == afmid.load(tmp_path / "cli.h5").parameters
    assert len(fit.parameters) >= 4


def test_parameters_table(dmt_fit, monkeypatch):
    table = dmt_fit.parameters
    hamaker = table["hamaker"]
    assert hamaker.unit == "J" and hamaker.interval == "1 sigma" and hamaker.sigma > 0
    assert hamaker.ci95[0] < hamaker.value < hamaker.ci95[1]
    assert table["d"].flags == ("estimated",) and table["d"].unit == "m"
    rows = table.to_dicts()
    assert [r["name"] for r in rows] == table.names() and rows[0].keys() == set(table.COLUMNS)
    with pytest.raises(KeyError, match="no parameter 'viscosity'"):
        table["viscosity"]  # noqa: B018
    monkeypatch.setitem(sys.modules, "pandas", None)  # as if pandas were not installed
    with pytest.raises(ImportError, match="needs pandas.*to_dicts"):
        table.to_pandas()


def test_parameters_to_pandas(dmt_fit):
    pandas = pytest.importorskip("pandas")
    frame = dmt_fit.parameters.to_pandas()
    assert isinstance(frame, pandas.DataFrame)
    assert frame.loc["hamaker", "value"] == dmt_fit.parameters["hamaker"].value


def test_a_plain_fit_names_no_separation_track_share(dmt_fit, tmp_path):
    """A fit without a separation track: its read-outs' track share is 0 in the table and summary.json, NaN for
    the estimated d (not split), and neither the fit's text nor the report's cells name a track."""
    from afmid.report.page import quantity_cell
    from afmid.report.story import run_entry

    assert "track" not in dmt_fit.text()
    entry = run_entry(tmp_path / "plain.h5", dmt_fit.run, {"error_fold_sd": 0.0, "error_spread_kind": ""})
    for name, q in dmt_fit.run.quantities.items():
        assert dmt_fit.parameters[name].sigma_separation_track == 0.0
        assert entry["parameters"][name]["error_separation_track"] == 0.0
        assert entry["parameters"][name]["error_statistical"] == q["error"]  # no part to take out
        assert "track" not in quantity_cell(q) and "track" not in quantity_cell(entry["parameters"][name])
    assert np.isnan(dmt_fit.parameters["d"].sigma_separation_track)


def test_predict_is_the_identified_law(dmt_fit):
    """Out of contact the DMT law is -H R / (6 z^2), its Hamaker read-out H = -6 c / R from the same coefficient c:
    the two agree to rounding (a few ulps of each step)."""
    z = np.array([1e-9, 2e-9, 5e-9])
    hamaker = dmt_fit.parameters["hamaker"].value
    expected = -hamaker * LEVER["tip_radius"] / (6 * z**2)
    assert np.allclose(dmt_fit.predict(z), expected, rtol=1e-12, atol=0)
    assert dmt_fit.predict(1e-9, velocity=[0.0, 1.0]).shape == (2,)  # DMT does not depend on the rate


def test_force_curve(dmt_fit):
    curve = dmt_fit.force_curve()
    assert curve.separation.shape == curve.force.shape == curve.phase.shape and curve.periods >= 10
    # the model's mean force over the periods reaches the repulsive contact and the attractive neck
    assert curve.force.max() > 0 > curve.force.min()
    assert np.all(np.isfinite(curve.force_inverted_sigma)) and curve.approaching.any() and (~curve.approaching).any()
    assert "phase points" in repr(curve)


def test_from_array_checks_and_keeps_the_array(simulated):
    lever = afmid.Cantilever(**LEVER)
    samples = simulated.deflection * 1e9
    kept = samples.copy()
    trace = afmid.Trace.from_array(samples, simulated.sample_rate, units="nm", cantilever=lever,
                                   positive="away_from_sample")
    assert np.array_equal(samples, kept)  # never changed
    assert np.allclose(trace.deflection, -simulated.deflection, rtol=1e-15, atol=0)
    assert trace.drive_frequency == lever.resonance_frequency
    with pytest.raises(InputError, match="Trace.from_array: deflection: expected a 1-D array"):
        afmid.Trace.from_array(samples.reshape(2, -1), simulated.sample_rate, cantilever=lever)
    with pytest.raises(ConfigError, match="Trace.from_array: units: expected one of m, nm"):
        afmid.Trace.from_array(samples, simulated.sample_rate, units="mm", cantilever=lever)
    with pytest.raises(ConfigError, match="Trace.from_array: cantilever: expected an afmid.Cantilever"):
        afmid.Trace.from_array(samples, simulated.sample_rate)
    with pytest.raises(ConfigError, match="cantilever.quality_factor"):
        afmid.Trace.from_array(samples, simulated.sample_rate, cantilever=afmid.Cantilever(40.0, 3e5, -1.0))
    with pytest.raises(InputError, match="too short"):
        afmid.Trace.from_array(samples[:300], simulated.sample_rate, cantilever=lever)


def test_cantilever_is_one_type_with_the_config():
    from afmid.config import build_config

    lever = afmid.Cantilever(**LEVER, spring_constant_uncertainty=0.05,
                             higher_modes=(afmid.HigherMode(1.9e6, 400.0, 1500.0),))
    section = build_config({"cantilever": lever.config_section()}).cantilever
    assert afmid.Cantilever.from_config(section) == lever
    assert math.isclose(lever.damping, lever.mass * lever.omega0 / lever.quality_factor, rel_tol=1e-15)


def test_force_model_checks_its_keys_and_adds_effects():
    model = afmid.ForceModel(["dmt"], separation=8e-9)
    assert model.add("viscoelastic").effects == ["dmt", "viscoelastic"] and model.effects == ["dmt"]
    assert "separation=8e-09 m" in repr(model)
    with pytest.raises(ConfigError, match="ForceModel: model.effects.*did you mean 'viscoelastic'"):
        afmid.ForceModel(["dmt", "viscoelastc"])
    with pytest.raises(ConfigError, match="ForceModel: fit.bootstrap"):
        afmid.ForceModel(fit={"bootstrap": -1})
    with pytest.raises(ConfigError, match="--remove jkr: not in model.effects"):
        model.remove("jkr")


def test_only_the_command_line_and_the_package_import_the_front_door():
    """afmid.api is the top layer: the stages below it never import it (they would then depend on it)."""
    import ast

    package = REPO_ROOT / "afmid"
    importers = set()
    for path in package.rglob("*.py"):
        if path.parent.name == "api":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            if any(n == "afmid.api" or n.startswith("afmid.api.") for n in names):
                importers.add(str(path.relative_to(package)))
    assert importers == {"__init__.py", "cli.py"}


def test_a_loaded_fit_of_an_array_needs_its_trace_to_be_diagnosed(dmt_fit, tmp_path):
    """The run file of an array has no input file to refit the candidates on: one line says so (load(path,
    trace=...) gives the trace back)."""
    path = dmt_fit.save(tmp_path / "array.h5")
    with pytest.raises(InputError, match="array.h5: input_path: the run's input trace is not available"):
        afmid.load(path).diagnose()
    assert afmid.load(path, trace=dmt_fit.trace).trace is dmt_fit.trace


def test_a_report_refuses_fits_of_different_arrays(dmt_fit, simulated, tmp_path):
    lever = afmid.Cantilever(**LEVER)
    other = afmid.Trace.from_array(simulated.deflection * 1.01, simulated.sample_rate, cantilever=lever)
    refit = afmid.ForceModel(["dmt"], fit={"bootstrap": 0}).fit(other, name="other")
    with pytest.raises(ConfigError, match="compare: the fits are of different traces"):
        refit.report(tmp_path / "report", compare=[dmt_fit])
    assert not (tmp_path / "report").exists()


def test_no_front_door_name_is_a_subpackage():
    """Importing afmid.X binds X on the package: a front-door name equal to a module's would be replaced by it
    (``afmid.simulate`` once became the simulator's package after its first use)."""
    modules = {path.stem if path.name != "__init__.py" else path.parent.name
               for path in (REPO_ROOT / "afmid").glob("*") if path.suffix == ".py" or (path / "__init__.py").exists()}
    modules |= {path.name for path in (REPO_ROOT / "afmid").iterdir() if (path / "__init__.py").exists()}
    assert not set(afmid.__all__) & modules
