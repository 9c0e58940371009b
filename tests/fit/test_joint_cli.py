"""``afmid fit`` of ``data.paths`` (several traces, one force law: afmid.fit.joint) end to end, its run file and
its report, and the one-line errors on bad input (an empty list, a missing file, mismatched lengths, traces of
different cantilevers)."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import yaml
from repo_paths import TEST_CONFIGS

from tests.cli.test_run_file import documented_run_paths

#: Short traces: 20 periods at 100 samples per period (the CLI path, not the accuracy, is tested here).
SHORT = ["--set", "simulate.periods=20", "--set", "simulate.samples_per_period=100"]


def _config(base: dict, **changes) -> dict:
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    for section, values in changes.items():
        out.setdefault(section, {}).update(values)
    return out


@pytest.fixture(scope="module")
def traces(tmp_path_factory):
    """Two DMT traces of one sample and lever at A/A0 = 0.8 and 0.6, and one of another lever (k 30 N/m)."""
    from afmid.cli import main

    folder = tmp_path_factory.mktemp("joint_traces")
    out = {}
    for name, extra in (("a", ["simulate.setpoint=0.8"]), ("b", ["simulate.setpoint=0.6"]),
                        ("other_lever", ["simulate.setpoint=0.7", "cantilever.spring_constant=30.0"])):
        sets = [x for e in extra for x in ("--set", e)]
        assert main(["-q", "simulate", str(TEST_CONFIGS / "dmt.yaml"), "-o", str(folder / f"{name}.h5"),
                     *SHORT, *sets]) == 0
        out[name] = folder / f"{name}.h5"
    base = yaml.safe_load((TEST_CONFIGS / "dmt.yaml").read_text())
    base.pop("simulate")
    base["sample"].pop("separation")
    base["fit"]["bootstrap"] = 20
    base["model"] = {"effects": ["dmt"]}
    return folder, out, base


def test_joint_fit_writes_the_shared_law_and_every_trace(traces, run_cli, tmp_path):
    folder, files, base = traces
    config = tmp_path / "joint.yaml"
    from afmid.io.trace import read_truth

    given = [float(read_truth(files[k]).extra["separation"]) for k in ("a", "b")]  # the search: test_joint.py
    config.write_text(yaml.safe_dump(_config(base, data={"paths": [str(files["a"]), str(files["b"])]},
                                             sample={"separation": given})))
    run = tmp_path / "joint.h5"
    code, out, err = run_cli("fit", config, "-o", run)
    assert code == 0, err
    assert "joint fit of 2 traces" in out and "trace 1:" in out
    shared = next(line for line in out.splitlines() if line.strip().startswith("E_star = "))
    assert "(1σ)" in shared and "(95 %)" in shared, shared  # the shared parameters with their intervals shown
    with h5py.File(run, "r") as h5:
        g = h5["joint"]
        assert g.attrs["n_traces"] == 2
        assert list(g["paths"].asstr()[()]) == [str(files["a"].resolve()), str(files["b"].resolve())]
        d = g["separation"][()]
        assert g["separation"].attrs["units"] == "m" and np.all(np.isfinite(d))
        assert d[0] > d[1]  # A/A0 0.8 sits farther from the sample than 0.6
        assert list(d) == given and not np.any(g["separation"].attrs["estimated"])
        assert np.all(np.isfinite(g["cv_error"][()]))
        for i in range(2):
            assert "periods" in g[f"trace_{i}"] and g[f"trace_{i}/separation"][()] == d[i]
        # the single-trace layout holds trace 0 and the shared parameters
        assert h5["model/separation"][()] == d[0]
        e_star = h5["model/parameters/E_star"]
        assert np.isfinite(e_star[()]) and e_star.attrs["error"] > 0
        assert "shared" in h5["model"].attrs["joint"]
        documented = documented_run_paths()
        joint_datasets = [f"/joint/{k}" for k, v in g.items() if isinstance(v, h5py.Dataset)]
        assert joint_datasets and all(p in documented for p in joint_datasets), joint_datasets
        no_units = []
        g.visititems(lambda name, obj: no_units.append(name) if isinstance(obj, h5py.Dataset)
                     and "units" not in obj.attrs else None)
        assert not no_units, no_units
    code, out, err = run_cli("report", run, "-o", tmp_path / "report", "--no-suggest")
    assert code == 0, err
    page = (tmp_path / "report" / "report.html").read_text()
    # the report names the joint fit and every trace with its own separation (given here) and error
    assert "Joint fit: one force law, 2 traces" in page
    for i, k in enumerate(("a", "b")):
        assert files[k].name in page and f"{given[i] * 1e9:.4f} nm (given)" in page
    from afmid.runfile import load_run

    table = load_run(run).joint
    assert [t["separation"] for t in table] == given and all(t["separation_error"] == 0 for t in table)
    assert all(np.isfinite(t["cv_error"]) and t["cv_error_noise_floor"] > 0 for t in table)


@pytest.mark.parametrize("case, key", [
    ("empty", "data.paths"),
    ("missing", "data.paths[1]"),
    ("lengths", "sample.separation"),
    ("list_without_paths", "sample.separation"),
    ("both", "data.paths"),
    ("other_lever", "data.paths[1]"),
])
def test_bad_joint_input_is_one_line(traces, run_cli, tmp_path, case, key):
    folder, files, base = traces
    a, b = str(files["a"]), str(files["b"])
    data, sample = {
        "empty": ({"paths": []}, {}),
        "missing": ({"paths": [a, str(folder / "nowhere.h5")]}, {}),
        "lengths": ({"paths": [a, b]}, {"separation": [10e-9]}),
        "list_without_paths": ({"path": a}, {"separation": [10e-9, 9e-9]}),
        "both": ({"path": a, "paths": [a, b]}, {}),
        "other_lever": ({"paths": [a, str(files["other_lever"])]}, {}),
    }[case]
    config = tmp_path / "bad.yaml"
    config.write_text(yaml.safe_dump(_config(base, data=data, sample=sample)))
    out_path = tmp_path / "out.h5"
    code, out, err = run_cli("fit", config, "-o", out_path)
    assert code in (1, 2)
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert key in lines[0], lines[0]
    assert not out_path.exists()
