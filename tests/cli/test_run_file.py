"""The run file written by `afmid fit` matches docs/file-formats.md (checked with plain h5py)."""

from __future__ import annotations

import re
from pathlib import Path

import h5py
import numpy as np
import pytest

from afmid.cli import main
from repo_paths import REPO_ROOT

DOCS = REPO_ROOT / "docs" / "file-formats.md"
OPTIONAL = {  # written only with non-default settings
    "/model/identified_stiffness", "/model/identified_damping", "/model/drive/offset_force",
    "/model/drive/frequency_sigma", "/model/drive/response_frequency",  # a transient record (drive searched)
    "/diagnostics/path/votes",  # only when at least two period groups voted (this trace has 12 periods: one)
    "/model/drive/baseline_drift",
    # a calibrated drive (drive.phase): tests/fit/test_declared_drive.py writes and checks them
    "/model/drive/phase", "/model/drive/force_amplitude_uncertainty", "/model/drive/phase_uncertainty",
    # a joint fit (data.paths): tests/fit/test_joint_cli.py writes and checks them
    "/joint/paths", "/joint/sha256", "/joint/separation", "/joint/separation_error", "/joint/cv_error",
    "/joint/cv_error_noise_floor", "/joint/model_limited",
    # the diagnosis kept by the front door's save() after diagnose(): tests/diagnosis/test_stored.py writes and checks it
    "/diagnosis/answer", "/diagnosis/tried_effect", "/diagnosis/tried_delta_bic", "/diagnosis/tried_error_after",
    "/diagnosis/suggested", "/diagnosis/verdict",
}


def documented_run_paths() -> set[str]:
    text = DOCS.read_text(encoding="utf-8")
    section = text[text.index("## Run file"):]
    return {p for p in re.findall(r"^\| `(/[a-z_/0-9]+)`", section, flags=re.M) if "*" not in p}


@pytest.fixture(scope="module")
def run_file(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("runfile")
    config = folder / "short.yaml"
    text = (REPO_ROOT / "configs" / "dmt_viscoelastic.yaml").read_text()
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


# --------------------------------------------------------------------------- afmid.runfile: the one reader and writer
def test_the_old_import_paths_name_the_one_reader_and_writer():
    """The diagnosis (above the run files) still names their reader; the fit (below them) no longer re-exports
    ``write_run`` (docs/architecture.md, Layers)."""
    import afmid.diagnosis.diagnose
    import afmid.fit.pipeline
    import afmid.runfile

    assert not hasattr(afmid.fit.pipeline, "write_run")
    assert afmid.diagnosis.diagnose.load_run is afmid.runfile.load_run
    assert afmid.diagnosis.diagnose.RunData is afmid.runfile.RunData


def test_text_decodes_what_h5py_returns_for_strings():
    from afmid.runfile import text

    assert text("Pa*s") == "Pa*s"
    assert text(b"Pa*s") == "Pa*s"
    assert text(np.bytes_(b"dmt")) == "dmt"  # fixed-length strings come back as numpy.bytes_
    assert text("µm".encode()) == "µm"
    assert text(3) == "3"
    assert text(b"a\xffb", errors="replace") == "a\ufffdb"
    with pytest.raises(UnicodeDecodeError):
        text(b"a\xffb")


def test_strings_stored_as_bytes_are_read_as_text(run_file, tmp_path):
    """Text written by another tool as fixed-length bytes reads as the same str (not "b'...'")."""
    import shutil

    from afmid.runfile import load_run, read_summary

    copy = tmp_path / "bytes.h5"
    shutil.copyfile(run_file, copy)
    reference = load_run(run_file)
    with h5py.File(copy, "r+") as h5:
        for ds in h5["model/parameters"].values():
            for name in ("units", "effect", "plausibility"):
                ds.attrs[name] = np.bytes_(str(ds.attrs[name]).encode())
        h5.attrs["input_sha256"] = np.bytes_(h5.attrs["input_sha256"].encode())
        h5.attrs["batch_key"] = np.bytes_(b"0123")
    again = load_run(copy)
    assert again.quantities == reference.quantities
    assert again.input_sha256 == reference.input_sha256
    summary = read_summary(copy)
    assert summary["key"] == "0123"
    assert summary["values"]["input_sha256"] == reference.input_sha256
    assert {name: (q["unit"], q["effect"]) for name, q in summary["quantities"].items()} == \
        {name: (q["unit"], q["effect"]) for name, q in reference.quantities.items()}


def test_the_summary_row_agrees_with_the_full_reader(run_file):
    from afmid.runfile import load_run, read_batch_key, read_summary

    run, summary = load_run(run_file), read_summary(run_file)
    assert summary["key"] is None and read_batch_key(run_file) is None  # `afmid fit` writes no batch key
    values = summary["values"]
    assert values["input_sha256"] == run.input_sha256
    assert values["effects"] == ";".join(run.effects)
    assert values["terms"] == ";".join(run.selected_terms)
    assert (values["cv_error"], values["cv_error_noise_floor"], values["chi2_reduced"], values["separation"]) == \
        (run.cv_error, run.cv_error_noise_floor, run.chi2_reduced, run.separation)
    assert set(summary["quantities"]) == set(run.quantities)
    for name, q in summary["quantities"].items():
        full = run.quantities[name]
        assert {k: q[k] for k in ("value", "error", "ci_low", "ci_high", "unit", "effect")} == \
            {k: full[k] for k in ("value", "error", "ci_low", "ci_high", "unit", "effect")}, name
    assert summary["implausible"] == [q["plausibility"] for q in run.quantities.values() if not q["plausible"]]


def test_a_missing_batch_key_or_unreadable_file_has_no_key(tmp_path):
    from afmid.runfile import read_batch_key

    (tmp_path / "not.h5").write_bytes(b"not HDF5")
    assert read_batch_key(tmp_path / "not.h5") is None
    assert read_batch_key(tmp_path / "missing.h5") is None


def test_a_voted_selection_records_its_votes(tmp_path):
    """With fit.selection_scope: vote (the default) on a record of two groups or more, the run file holds each
    term's vote share and the scope."""
    config = tmp_path / "votes.yaml"
    text = (REPO_ROOT / "configs" / "dmt_viscoelastic.yaml").read_text()
    text = text.replace("periods: 50 ", "periods: 30 ")
    config.write_text(text + "\ndata: {path: trace.h5}\nfit: {bootstrap: 0}\n")
    assert main(["-q", "simulate", str(config), "-o", str(tmp_path / "trace.h5")]) == 0
    assert main(["-q", "fit", str(config), "-o", str(tmp_path / "run.h5")]) == 0
    with h5py.File(tmp_path / "run.h5", "r") as h5:
        path = h5["diagnostics/path"]
        assert path.attrs["scope"] == "vote"
        votes = path["votes"][()]
        assert path["votes"].attrs["units"] == "1"
        assert votes.shape == (path["masks"].shape[1],)
        assert np.all((votes >= 0) & (votes <= 1))


def test_a_trace_given_to_report_is_named_as_not_a_run_file(run_cli, write_csv, tmp_path):
    """Issue 33: ``afmid report trace.csv`` said "not a readable HDF5 file (truncated or corrupt?)": the file is
    fine, it is the wrong kind. One line naming the file and what was expected, exit 1, nothing written."""
    import h5py

    csv = write_csv("trace.csv")
    trace_h5 = tmp_path / "trace.h5"
    with h5py.File(trace_h5, "w") as h5:
        h5.attrs["format"] = "afmid-trace"
    for given, kind in ((csv, "not an HDF5 file"), (trace_h5, "an afmid trace file")):
        code, out, err = run_cli("report", given, "-o", tmp_path / "rep", "--no-suggest")
        assert code == 1 and "Traceback" not in err, err
        line = err.strip()
        assert "\n" not in line and str(given.name) in line, line
        assert "expected a run file from afmid fit" in line and kind in line, line
        assert "truncated or corrupt" not in line, line
        assert not (tmp_path / "rep").exists()
