"""The run file written by `afmid fit` matches docs/file-formats.md (checked with plain h5py)."""

from __future__ import annotations

import re
from pathlib import Path

import h5py
import numpy as np
import pytest

from afmid.cli import main

DOCS = Path(__file__).resolve().parents[1] / "docs" / "file-formats.md"
OPTIONAL = {  # written only with non-default settings
    "/model/identified_stiffness", "/model/identified_damping", "/model/drive/offset_force",
}


def documented_run_paths() -> set[str]:
    text = DOCS.read_text(encoding="utf-8")
    section = text[text.index("## Run file"):]
    return {p for p in re.findall(r"^\| `(/[a-z_/0-9]+)`", section, flags=re.M) if "*" not in p}


@pytest.fixture(scope="module")
def run_file(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("runfile")
    config = folder / "short.yaml"
    text = (Path(__file__).resolve().parents[1] / "configs" / "dmt_viscoelastic.yaml").read_text()
    text = text.replace("periods: 50 ", "periods: 12 ")
    config.write_text(text + "\ndata: {path: trace.h5}\nfit: {bootstrap: 10}\n")
    assert main(["-q", "simulate", str(config), "-o", str(folder / "trace.h5")]) == 0
    assert main(["-q", "fit", str(config), "-o", str(folder / "run.h5")]) == 0
    return folder / "run.h5"


def test_every_documented_path_exists(run_file):
    with h5py.File(run_file, "r") as h5:
        missing = sorted(p for p in documented_run_paths() - OPTIONAL if p not in h5)
    assert not missing, f"documented but not written: {missing}"


def test_every_written_dataset_is_documented_and_has_units(run_file):
    documented = documented_run_paths()
    undocumented, no_units = [], []

    def visit(name, obj):
        path = "/" + name
        if isinstance(obj, h5py.Dataset):
            if "units" not in obj.attrs:
                no_units.append(path)
            parent = path.rsplit("/", 1)[0]
            if path not in documented and parent not in ("/model/parameters", "/model/nonlinear"):
                undocumented.append(path)

    with h5py.File(run_file, "r") as h5:
        h5.visititems(visit)
    assert not no_units, f"datasets without a units attribute: {no_units}"
    assert not undocumented, f"written but not documented: {undocumented}"


def test_provenance_and_physical_read_out(run_file):
    with h5py.File(run_file, "r") as h5:
        for attr in ("afmid_version", "format", "format_version", "created", "config", "input_path", "input_sha256"):
            assert attr in h5.attrs, attr
        assert h5.attrs["format"] == "afmid-run"
        assert re.match(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d[+-]\d\d:\d\d$", h5.attrs["created"])
        params = h5["model/parameters"]
        assert params["E_star"].attrs["units"] == "Pa"
        assert params["viscosity"].attrs["units"] == "Pa*s"
        estimate = h5["force/estimate"][...]
        assert np.isfinite(estimate).mean() > 0.8  # all whole blocks are estimated
        assert h5["force/estimate"].attrs["positive"] == "repulsive"


def test_parameter_attributes_are_documented_and_hold_the_plausibility_verdict(run_file):
    text = DOCS.read_text(encoding="utf-8")
    section = text[text.index("#### `/model/parameters/*`"):text.index("#### `/model/nonlinear/*`")]
    documented = {name for cell in re.findall(r"^\| (`[^|]+)\|", section, flags=re.M)
                  for name in re.findall(r"`([a-z_]+)`", cell)}
    with h5py.File(run_file, "r") as h5:
        params = h5["model/parameters"]
        for name, ds in params.items():
            assert set(ds.attrs) <= documented, (name, sorted(set(ds.attrs) - documented))
            assert {"plausible", "plausibility"} <= set(ds.attrs), name
            assert (ds.attrs["plausibility"] == "") == bool(ds.attrs["plausible"]), name
        flagged = [n for n, ds in params.items() if not ds.attrs["plausible"]]
        diagnostics = h5["diagnostics"].attrs
        assert diagnostics["n_implausible"] == len(flagged)
        assert sorted(diagnostics.get("implausible", [])) == sorted(params[n].attrs["plausibility"] for n in flagged)
