"""Bad-input corpus: requests afmid cannot carry out as asked (contradictions, traces with nothing to fit,
terms with nothing to fit, run files it cannot read). See tests/corpus.py for the contract of every case.

Before these fixes each case below was answered with a result (exit 0: a fitted trace of noise, a report
on a damaged file) or with a traceback; now each is one line naming the file and the key.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

import h5py
import numpy as np
import yaml

from tests.conftest import DRIVE_FREQUENCY, SAMPLE_RATE
from corpus import Case, check_case, corpus_params
from tests.cli.test_corpus_config import base_config, fit_case, fit_workspace
from repo_paths import REPO_ROOT

REPO = REPO_ROOT


# --------------------------------------------------------------------------- traces without an oscillation
def write_values_csv(folder: Path, values: np.ndarray, name: str = "trace.csv") -> None:
    """``values`` (nm) at the corpus's sample rate as CSV (time_s, deflection_nm)."""
    t = np.arange(values.size) / SAMPLE_RATE
    rows = "\n".join(f"{ti!r},{xi!r}" for ti, xi in zip(t.tolist(), np.asarray(values, float).tolist()))
    (folder / name).write_text("time_s,deflection_nm\n" + rows + "\n")


def trace_case(id: str, values, *fragments: str, config: dict | None = None, key: str = "data.column",
               exit_code: int = 1, quiet: bool = False) -> Case:
    """``afmid fit`` of a trace made of ``values`` (nm, 200 samples per drive period); ``quiet``: with -q, for
    errors found during the fit (its progress bar shares stderr)."""

    def files(folder: Path) -> None:
        (folder / "run.yaml").write_text(yaml.safe_dump(config or base_config(), sort_keys=False))
        write_values_csv(folder, values)

    return Case(id=id, category="data", argv=("-q",) * quiet + ("fit", "run.yaml", "-o", "out.h5"), files=files,
                exit_code=exit_code, file="trace.csv", key=key, fragments=fragments)


N_SAMPLES = 4000  # 20 drive periods
RNG = np.random.default_rng(11)
NO_LINE = "no oscillation at the drive frequency"
TIME = np.arange(N_SAMPLES) / SAMPLE_RATE
DRIVE = np.sin(2 * np.pi * DRIVE_FREQUENCY * TIME)

TRACE_CASES = [
    trace_case("slow-ramp", np.linspace(0.0, 5.0, N_SAMPLES), NO_LINE, "need >"),
    trace_case("white-noise", RNG.normal(0.0, 1.0, N_SAMPLES), NO_LINE, "noise floor"),
    trace_case("random-walk", np.cumsum(RNG.normal(0.0, 0.1, N_SAMPLES)), NO_LINE),
    trace_case("slow-drift-curved", 3.0 * (np.arange(N_SAMPLES) / N_SAMPLES) ** 2, NO_LINE),
    trace_case("drive-line-buried-in-noise", 0.02 * DRIVE + RNG.normal(0.0, 1.0, N_SAMPLES), NO_LINE),
    # The time column fitted as the deflection (a perfect ramp), named or by index.
    Case(id="time-column-as-deflection", category="data", argv=("fit", "run.yaml", "-o", "out.h5"),
         files=fit_workspace(base_config(**{"data.column": "time_s", "data.time_column": None, "data.units": "nm"})),
         exit_code=1, file="trace.csv", key="data.column", fragments=(NO_LINE,)),
    Case(id="time-column-by-index-as-deflection", category="data", argv=("fit", "run.yaml", "-o", "out.h5"),
         files=fit_workspace(base_config(**{"data.column": 0, "data.time_column": None})),
         exit_code=1, file="trace.csv", key="data.column", fragments=(NO_LINE,)),
    # A free oscillation without any tip-sample force: nothing to identify, the error metric is NaN.
    trace_case("free-oscillation-no-force", 5.0 * DRIVE, "no usable result", "NaN", key="data.path", quiet=True),
    trace_case("free-oscillation-with-noise", 5.0 * DRIVE + RNG.normal(0.0, 0.001, N_SAMPLES), "no usable result",
               key="data.path", quiet=True),
    # YAML booleans where a column is named (no -> False -> column 0, the time column, before).
    fit_case("column-yaml-boolean", base_config(**{"data.column": False}), 2, "data.column", "YAML boolean",
             category="data"),
    fit_case("time-column-yaml-boolean", base_config(**{"data.time_column": True}), 2, "data.time_column",
             "YAML boolean", category="data"),
    fit_case("time-column-is-the-deflection", base_config(**{"data.time_column": "deflection_nm"}), 2,
             "data.time_column", "data.column", category="data"),
]


# --------------------------------------------------------------------------- contradictory requests
def request_case(id: str, config: dict, key: str, *fragments: str, extra: tuple[str, ...] = ()) -> Case:
    return fit_case(id, config, 2, key, *fragments, category="request", extra=extra)


REQUEST_CASES = [
    request_case("library-and-effects", base_config(**{"model.library": "lj_table1"}), "model.library",
                 "model.effects"),
    request_case("library-and-effects-from-set", base_config(**{"model.library": "jkr_table4", "model.effects": None}),
                 "model.library", "model.effects", "['jkr']", extra=("--set", "model.effects=[jkr]")),
    Case(id="add-and-remove-same-effect", category="request",
         argv=("fit", "run.yaml", "-o", "out.h5", "--add", "dmt", "--remove", "dmt"),
         files=fit_workspace(base_config()), exit_code=2, file=None, key="--add", fragments=("--remove dmt",)),
    Case(id="add-and-remove-new-effect", category="request",
         argv=("fit", "run.yaml", "-o", "out.h5", "--remove", "capillary", "--add", "capillary"),
         files=fit_workspace(base_config(**{"model.effects": ["dmt", "capillary"]})), exit_code=2, file=None,
         key="--add", fragments=("--remove capillary", "contradict")),
    request_case("differentiation-option-misspelt", base_config(**{"fit.differentiation_options": {"windw": 7}}),
                 "fit.differentiation_options.windw", "did you mean 'window'?", "window, order"),
    request_case("spline-lam-negative",
                 base_config(**{"fit.form": "strong", "fit.differentiation": "spline",
                                "fit.differentiation_options": {"lam": -1}}),
                 "fit.differentiation_options.lam", "> 0", "-1"),
    request_case("option-of-another-differentiator",
                 base_config(**{"fit.differentiation": "central", "fit.differentiation_options": {"order": 2}}),
                 "fit.differentiation_options.order", "central", "none"),
    request_case("spectral-snr-zero",
                 base_config(**{"fit.differentiation": "spectral", "fit.differentiation_options": {"snr": 0}}),
                 "fit.differentiation_options.snr", "> 0"),
    request_case("savgol-order-fraction", base_config(**{"fit.differentiation_options": {"order": 2.5}}),
                 "fit.differentiation_options.order", "whole"),
]


# --------------------------------------------------------------------------- custom terms with nothing to fit
def term_case(id: str, term: str, *fragments: str, **changes) -> Case:
    return fit_case(id, base_config(**{"model.terms": [term], **changes}), 2, "model.terms[0]", *fragments,
                    category="terms")


TERM_CASES = [
    term_case("term-zero", "0", "zero for every value"),
    term_case("term-division-by-zero", "1/0", "not finite"),
    term_case("term-cancels", "x - x", "zero for every value"),
    term_case("term-log-of-negative", "log(-1)", "not finite"),
    term_case("term-overflows", "exp(1000)", "not finite"),
    term_case("term-constant-with-free-baseline", "1", "fit.baseline: free", **{"fit.baseline": "free"}),
]


# --------------------------------------------------------------------------- run files afmid cannot read
_REFERENCE: dict[str, Path] = {}


def reference_run() -> Path:
    """A small real run file (simulated DMT + viscoelastic trace, fitted), made once per test process.

    25 periods: 5000 samples, so the per-sample datasets are stored compressed in chunks."""
    from afmid.cli import main

    if "run" not in _REFERENCE:
        folder = Path(tempfile.mkdtemp(prefix="afmid-corpus-run-"))
        atexit.register(shutil.rmtree, folder, True)
        text = (REPO / "configs" / "dmt_viscoelastic.yaml").read_text().replace("periods: 50 ", "periods: 25 ")
        (folder / "run.yaml").write_text(text + "\ndata: {path: trace.h5}\nfit: {bootstrap: 0}\n")
        assert main(["-q", "simulate", str(folder / "run.yaml"), "-o", str(folder / "trace.h5")]) == 0
        assert main(["-q", "fit", str(folder / "run.yaml"), "-o", str(folder / "run.h5")]) == 0
        _REFERENCE["run"] = folder / "run.h5"
    return _REFERENCE["run"]


def run_workspace(change=None, name: str = "run.h5"):
    """files(): a copy of the reference run as ``name``, then ``change(h5py.File)`` applied to it."""

    def write(folder: Path) -> None:
        shutil.copyfile(reference_run(), folder / name)
        if change is not None:
            with h5py.File(folder / name, "r+") as h5:
                change(h5)

    return write


def report_case(id: str, change, key: str | None, *fragments: str) -> Case:
    return Case(id=id, category="runfile", argv=("report", "run.h5", "-o", "rep", "--no-suggest"),
                files=run_workspace(change), exit_code=1, file="run.h5", key=key, fragments=fragments)


def _set_attr(name, value):
    def change(h5):
        h5.attrs[name] = value
    return change


def _delete(path):
    def change(h5):
        del h5[path]
    return change


def _delete_attr(obj_path, name):
    def change(h5):
        del h5[obj_path].attrs[name]
    return change


def _del_root_attr(name):
    def change(h5):
        del h5.attrs[name]
    return change


def _config_with_unknown_key(h5):
    config = yaml.safe_load(h5.attrs["config"])
    config["fitt"] = {}
    h5.attrs["config"] = yaml.safe_dump(config)


def flipped_run(folder: Path) -> None:
    """The reference run with the bytes of one compressed chunk of /force/estimate inverted (bit rot)."""
    shutil.copyfile(reference_run(), folder / "run.h5")
    with h5py.File(folder / "run.h5", "r") as h5:
        info = h5["force/estimate"].id.get_chunk_info(0)
    with open(folder / "run.h5", "r+b") as fh:
        fh.seek(info.byte_offset + 16)
        data = fh.read(64)
        fh.seek(info.byte_offset + 16)
        fh.write(bytes(b ^ 0xFF for b in data))


def two_runs_of_different_traces(folder: Path) -> None:
    """Two copies of the reference run, the second claiming another input trace (another SHA-256)."""
    run_workspace(name="run1.h5")(folder)
    run_workspace(_set_attr("input_sha256", "0" * 64), name="run2.h5")(folder)


RUNFILE_CASES = [
    report_case("run-format-version-99", _set_attr("format_version", 99), "format_version", "reads 1"),
    report_case("run-format-version-missing", _del_root_attr("format_version"), "format_version"),
    report_case("run-missing-coefficients", _delete("model/coefficients"), "/model/coefficients", "missing"),
    report_case("run-missing-diagnostics", _delete("diagnostics"), "/diagnostics", "missing"),
    report_case("run-missing-parameter-units", _delete_attr("model/parameters/E_star", "units"), "units",
                "/model/parameters/E_star"),
    report_case("run-config-bad-yaml", _set_attr("config", "data: [unclosed\n"), "config", "not valid YAML"),
    report_case("run-config-invalid", _config_with_unknown_key, "config", "fitt"),
    report_case("run-config-missing", _del_root_attr("config"), "config", "missing"),
    Case(id="run-bit-flipped", category="runfile", argv=("report", "run.h5", "-o", "rep", "--no-suggest"),
         files=flipped_run, exit_code=1, file="run.h5", key=None, fragments=("damaged run file",)),
    Case(id="report-runs-of-different-traces", category="request",
         argv=("report", "run1.h5", "run2.h5", "-o", "rep", "--no-suggest"), files=two_runs_of_different_traces,
         exit_code=2, file="run1.h5", key="--allow-different-traces", fragments=("run2.h5", "different traces")),
]

CASES = TRACE_CASES + REQUEST_CASES + TERM_CASES + RUNFILE_CASES


@corpus_params(CASES)
def test_requests_case(case, tmp_path, capsys, monkeypatch):
    check_case(case, tmp_path / "ws", capsys, monkeypatch)
