"""Joint fits through the front door: ``afmid.ForceModel(...).fit([trace1, trace2])`` is ``afmid fit`` of
``data.paths`` (the same parameters to the bit, the same per-trace rows), its record is the joint one (what
``afmid.joint_runfile`` writes: ``/joint``), ``.print()`` shows the traces' table, ``.save()`` and
``afmid.load()`` give it back; bad lists get one-line errors."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

import afmid
from afmid.errors import ConfigError, InputError
from tests.api.test_front_door import LEVER, SIMULATION

#: Two set-points of one sample and lever (A/A0 0.8 sits farther from the sample than 0.6).
SETPOINTS = (0.8, 0.6)
JOINT_MODEL = {"effects": ["dmt"], "fit": {"bootstrap": 10}}


def _simulation(setpoint: float) -> dict:
    sample = {k: v for k, v in SIMULATION["sample"].items() if k != "separation"}
    return {**SIMULATION, "sample": sample, "simulate": {**SIMULATION["simulate"], "setpoint": setpoint}}


@pytest.fixture(scope="module")
def traces():
    return [afmid.simulate_trace(_simulation(s)) for s in SETPOINTS]


@pytest.fixture(scope="module")
def array_traces(traces):
    """The same samples as arrays (no file behind them), one lever."""
    lever = afmid.Cantilever(**LEVER)
    return [afmid.Trace.from_array(t.deflection, t.sample_rate, cantilever=lever, drive_frequency=t.drive_frequency)
            for t in traces]


@pytest.fixture(scope="module")
def joint_fit(array_traces):
    """Both separations estimated on the joint residual."""
    return afmid.ForceModel(**JOINT_MODEL).fit(array_traces)


def _truth_separations(traces) -> list[float]:
    return [float(t.truth.extra["separation"]) for t in traces]


def test_a_list_of_traces_is_afmid_fit_of_data_paths(traces, tmp_path, run_cli):
    """The front door and ``afmid fit`` of ``data.paths`` run the same joint fit on the same samples: the same
    shared parameters and per-trace rows to the bit, and the command prints the fit's text."""
    from afmid.io.trace import write_trace_file

    paths = [write_trace_file(tmp_path / f"trace{i}.h5", t, "") for i, t in enumerate(traces)]
    given = _truth_separations(traces)
    config = {"cantilever": LEVER, "drive": SIMULATION["drive"], "data": {"paths": [str(p) for p in paths]},
              "sample": {"separation": given}, "model": {"effects": JOINT_MODEL["effects"]},
              "fit": JOINT_MODEL["fit"]}
    config_path = tmp_path / "joint.yaml"
    config_path.write_text(yaml.safe_dump(config))
    code, out, err = run_cli("fit", config_path, "-o", tmp_path / "cli.h5")
    assert code == 0, err
    fit = afmid.ForceModel(**JOINT_MODEL).fit([afmid.read(p) for p in paths], separations=given)
    cli = afmid.load(tmp_path / "cli.h5")
    assert fit.parameters == cli.parameters and len(fit.parameters) >= 4
    rows = [{k: v for k, v in row.items() if k != "periods"} for row in fit.joint]
    assert rows == [{k: v for k, v in row.items() if k != "periods"} for row in cli.joint]
    assert [row["separation"] for row in rows] == given and not any(row["separation_estimated"] for row in rows)
    assert [row["path"] for row in rows] == [str(p.resolve()) for p in paths]
    # what the command printed is the fit's text (the record's read-out, then the traces' table)
    assert out.strip() == fit.text().strip()
    assert "joint fit of 2 traces" in out and "trace1.h5: d = " in out and "(given)" in out
    assert fit.summary_line() == cli.summary_line() == f"joint fit of 2 traces; terms: {', '.join(fit.terms)}"


def test_a_joint_fit_is_its_joint_record(joint_fit, array_traces):
    """The Fit of a joint fit holds the joint record: trace 0's single-trace part, every trace's row; the
    separations are estimated, each with a 1 sigma, and order as the set-points do."""
    rows = joint_fit.joint
    assert len(rows) == 2 and joint_fit.run.joint_attrs["n_traces"] == 2
    assert joint_fit.trace is array_traces[0]
    assert all(row["separation_estimated"] and row["separation_error"] > 0 for row in rows)
    assert rows[0]["separation"] > rows[1]["separation"]
    assert joint_fit.run.separation == rows[0]["separation"]  # the single-trace part is trace 0's
    assert all(row["path"] == "" and row["sha256"] == "" for row in rows)  # arrays: no file
    lines = joint_fit.text().splitlines()
    table = lines.index("joint fit of 2 traces, one force law (the parameters above are shared):")
    assert [line.split(":")[0].strip() for line in lines[table + 1:]] == ["trace 0", "trace 1"]
    assert all(": -: d = " in line for line in lines[table + 1:])  # no file name
    for row, line in zip(rows, lines[table + 1:]):
        assert f"d = {row['separation'] * 1e9:.3f} ± {row['separation_error'] * 1e9:.3f} nm" in line


def test_save_and_load_give_the_joint_fit_back(joint_fit, tmp_path):
    again = afmid.load(joint_fit.save(tmp_path / "joint.h5"))
    assert again.parameters == joint_fit.parameters  # float64 through HDF5 and back: bit for bit
    assert again.summary_line() == joint_fit.summary_line()
    assert sorted(again.text().splitlines()) == sorted(joint_fit.text().splitlines())
    for mine, read in zip(joint_fit.joint, again.joint):
        assert {k: v for k, v in mine.items() if k != "periods"} == {k: v for k, v in read.items() if k != "periods"}
        assert mine["periods"].keys() == read["periods"].keys()
        assert all(np.array_equal(mine["periods"][k], read["periods"][k]) for k in mine["periods"])


def test_bad_lists_get_one_line_errors(array_traces, simulated_other_lever):
    model = afmid.ForceModel(**JOINT_MODEL)
    with pytest.raises(ConfigError, match="the list is empty"):
        model.fit([])
    with pytest.raises(ConfigError, match=r"fit\(traces\[1\]\).*expected an afmid.Trace"):
        model.fit([array_traces[0], array_traces[1].deflection])
    with pytest.raises(InputError, match=r"cantilever.spring_constant is 30.0 here but 40.0 in traces\[0\]: a joint "
                                         "fit needs the traces of one cantilever and one tip"):
        model.fit([array_traces[0], simulated_other_lever])
    with pytest.raises(ConfigError, match="1 separation"):
        model.fit(array_traces, separations=[12e-9])
    with pytest.raises(ConfigError, match="one separation for several traces"):
        afmid.ForceModel(**JOINT_MODEL, separation=12e-9).fit(array_traces)
    with pytest.raises(ConfigError, match="separations are given per trace of a joint fit"):
        model.fit(array_traces[0], separations=[12e-9])


@pytest.fixture(scope="module")
def simulated_other_lever(traces):
    lever = afmid.Cantilever(**{**LEVER, "spring_constant": 30.0})
    return afmid.Trace.from_array(traces[0].deflection, traces[0].sample_rate, cantilever=lever,
                                  drive_frequency=traces[0].drive_frequency)
