"""The example data in data/: every format holds the same motion, and every tool works on each file.

data/ is written by scripts/make_example_data.py from configs/ldpe_like.yaml
(simulated: no measured LDPE trace is public). These tests read the committed
files; they do not re-simulate.
"""

from __future__ import annotations

import importlib.util

import h5py
import numpy as np
import pytest
import yaml

from afmid.config import build_config, load_config, read_yaml, template_text
from afmid.io.trace import load_trace
from repo_paths import REPO_ROOT

ROOT = REPO_ROOT
DATA = ROOT / "data"
FORMATS = ["trace", "csv", "npy", "npz", "hdf5", "mat", "ibw", "tdms"]
FILES = {"trace": "example_trace.h5", "csv": "example.csv", "npy": "example.npy", "npz": "example.npz",
         "hdf5": "example_plain.h5", "mat": "example.mat", "ibw": "example.ibw", "tdms": "example.tdms"}


@pytest.fixture(scope="module")
def reference() -> np.ndarray:
    with h5py.File(DATA / "example_trace.h5", "r") as h5:
        return h5["deflection"][()]


def test_every_format_has_a_file_and_a_config():
    assert sorted(p.name for p in DATA.glob("example_*.yaml")) == sorted(f"example_{f}.yaml" for f in FORMATS)
    for name in FILES.values():
        assert (DATA / name).is_file(), name


@pytest.mark.parametrize("fmt", FORMATS)
def test_each_format_loads_to_the_same_deflection_in_metres(fmt, reference):
    config = load_config(DATA / f"example_{fmt}.yaml")
    trace = load_trace(config)
    assert trace.path.name == FILES[fmt]
    np.testing.assert_allclose(trace.deflection, reference, rtol=1e-12, atol=1e-24)
    assert trace.sample_rate == pytest.approx(3e7, rel=1e-12)
    assert trace.samples_per_period == pytest.approx(100) and trace.n_periods == pytest.approx(20)
    assert trace.findings == [] and trace.overridden == []


@pytest.mark.parametrize("fmt", FORMATS)
def test_inspect_works_on_each_example(fmt, run_cli):
    code, out, err = run_cli("inspect", DATA / FILES[fmt])
    assert code == 0, err
    assert "100.00 samples per period, 20.0 periods" in out
    assert "interaction:  contact: the force turns repulsive" in out
    if fmt == "mat":  # stored positive away from the sample: inspect says so
        assert "warning: sign:" in out
    else:
        assert "defects: none found" in out


@pytest.mark.parametrize("fmt", FORMATS)
def test_init_config_from_each_example_loads_the_same_motion(fmt, tmp_path, reference, run_cli):
    out = tmp_path / "run.yaml"
    code, _, err = run_cli("init-config", "--from", DATA / FILES[fmt], "-o", out)
    assert code == 0, err
    text = out.read_text()
    assert text.count("\n#") >= template_text().count("\n#")  # the template's comments stay
    raw = yaml.safe_load(text)
    example = read_yaml(DATA / f"example_{fmt}.yaml")
    # What no file can say (units of a bare array, its rate, InvOLS) comes from the example config ...
    for key, value in raw["data"].items():
        if value is None and key in example["data"]:
            raw["data"][key] = example["data"][key]
    assert raw["data"].get("positive", "toward_sample") == example["data"].get("positive", "toward_sample")
    # ... and so does the calibration (the template's values are only examples).
    for section in ("cantilever", "drive", "sample", "model", "fit"):
        raw[section] = example[section]
    trace = load_trace(build_config(raw, source=out))
    np.testing.assert_allclose(trace.deflection, reference, rtol=1e-12, atol=1e-24)


def test_the_ldpe_like_trace_is_labelled_simulated_with_its_config_and_truth():
    path = DATA / "ldpe_like_50periods.h5"
    with h5py.File(path, "r") as h5:
        assert h5.attrs["format"] == "afmid-trace"
        assert bool(h5.attrs["simulated"]) and "SIMULATED" in h5.attrs["description"]
        assert "not a measurement" in h5.attrs["description"]
        truth = h5["truth"]
        assert truth.attrs["model"] == "dmt_viscoelastic" and list(truth.attrs["effects"]) == ["dmt", "viscoelastic"]
        params = truth["parameters"].attrs
        assert 0.2e9 <= params["E_star"] <= 0.5e9 and params["viscosity"] > 0
        stored = build_config(yaml.safe_load(h5.attrs["config"]))
        assert h5["deflection"].shape == (10000,) and h5.attrs["sample_rate"] == pytest.approx(6e7)
    config = load_config(ROOT / "configs" / "ldpe_like.yaml")
    assert stored.simulate == config.simulate and stored.sample == config.sample
    assert config.model.effects == ["dmt"]  # the fit misses the viscoelasticity on purpose
    trace = load_trace(config)
    assert trace.n_periods == pytest.approx(50) and trace.overridden == []
    assert trace.findings == [] and trace.truth is not None


def test_readme_and_size():
    readme = (DATA / "README.md").read_text()
    assert "SIMULATED" in readme
    for name in [*FILES.values(), "ldpe_like_50periods.h5", "configs/ldpe_like.yaml", "make_example_data.py"]:
        assert name in readme, name
    total = sum(p.stat().st_size for p in DATA.iterdir() if p.is_file())
    assert total < 2e6


def test_the_script_writes_every_format_from_one_motion(tmp_path, reference):
    spec = importlib.util.spec_from_file_location("make_example_data", ROOT / "scripts" / "make_example_data.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    files = script.write_formats(tmp_path, reference, 3e7)
    script.write_configs(tmp_path, files)
    assert sorted(files) == sorted(f for f in FORMATS if f != "trace")
    for fmt, (name, _) in files.items():
        if fmt in ("csv", "npy", "ibw"):  # no timestamps inside: byte for byte what is committed
            assert (tmp_path / name).read_bytes() == (DATA / name).read_bytes(), name
        trace = load_trace(load_config(tmp_path / f"example_{fmt}.yaml"))
        np.testing.assert_allclose(trace.deflection, reference, rtol=1e-12, atol=1e-24)
