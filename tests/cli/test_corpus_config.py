"""Bad-input corpus: run configs (see tests/corpus.py for the contract every case must meet)."""

from __future__ import annotations

import os
from pathlib import Path

import yaml

from tests.conftest import CANTILEVER, DRIVE_FREQUENCY, SAMPLE_RATE, sinusoid
from corpus import Case, check_case, corpus_params
from repo_paths import REPO_ROOT


def write_trace_csv(folder: Path, name: str = "trace.csv", periods: float = 10) -> None:
    """A 10-period drive-frequency sinusoid as CSV (time_s, deflection_nm)."""
    t, x = sinusoid(periods)
    rows = "\n".join(f"{ti!r},{xi!r}" for ti, xi in zip(t.tolist(), x.tolist()))
    (folder / name).write_text("time_s,deflection_nm\n" + rows + "\n")


_TAPPING: dict[str, tuple] = {}  # (time s, deflection nm) of the simulated tapping trace, made once per process


def write_tapping_csv(folder: Path, name: str = "trace.csv") -> None:
    """A real tapping trace (DMT, simulated once per process with the corpus cantilever: 12 periods, 200 samples
    per period) as CSV (time_s, deflection_nm): for cases that need a fit to succeed (a bare sinusoid has no
    tip-sample force, and afmid refuses to fit it)."""
    if "trace" not in _TAPPING:
        from afmid.config import build_config
        from afmid.simulate.driver import simulate

        text = (REPO_ROOT / "configs" / "dmt.yaml").read_text()
        mapping = yaml.safe_load(text)
        mapping["cantilever"] = dict(CANTILEVER)
        mapping["simulate"]["periods"] = 12
        trace = simulate(build_config(mapping))
        _TAPPING["trace"] = (trace.times, trace.deflection * 1e9)
    t, x = _TAPPING["trace"]
    rows = "\n".join(f"{ti!r},{xi!r}" for ti, xi in zip(t.tolist(), x.tolist()))
    (folder / name).write_text("time_s,deflection_nm\n" + rows + "\n")


def base_config(**changes) -> dict:
    """The pinned run config of the corpus; ``changes`` maps dotted keys to values (None deletes)."""
    config = {
        "data": {"path": "trace.csv", "format": "auto", "column": "deflection_nm", "time_column": "time_s",
                 "sample_rate": SAMPLE_RATE, "units": "nm", "positive": "toward_sample"},
        "cantilever": dict(CANTILEVER),
        "drive": {"frequency": DRIVE_FREQUENCY},
        "sample": {"a0": 0.165e-9},
        "model": {"effects": ["dmt"]},
        "fit": {},
    }
    for dotted, value in changes.items():
        *parents, last = dotted.split(".")
        node = config
        for part in parents:
            node = node.setdefault(part, {})
        if value is None:
            node.pop(last, None)
        else:
            node[last] = value
    return config


def fit_workspace(config: dict | str, with_trace: bool = True):
    """A files() callable writing run.yaml (a mapping or raw YAML text) and, optionally, trace.csv."""

    def write(folder: Path) -> None:
        text = config if isinstance(config, str) else yaml.safe_dump(config, sort_keys=False)
        (folder / "run.yaml").write_text(text)
        if with_trace:
            write_trace_csv(folder)

    return write


def fit_case(id: str, config, exit_code: int, key: str | None, *fragments: str, file: str = "run.yaml",
             category: str = "config", extra: tuple[str, ...] = ()) -> Case:
    """``afmid fit run.yaml -o out.h5`` on a workspace with the given config."""
    return Case(id=id, category=category, argv=("fit", "run.yaml", "-o", "out.h5", *extra), files=fit_workspace(config),
                exit_code=exit_code, file=file, key=key, fragments=fragments)


#: (id, dotted key, bad value, fragment of the message): one value a user could plausibly write per case.
BAD_VALUES = [
    ("spring-constant-zero", "cantilever.spring_constant", 0, "must be > 0"),
    ("spring-constant-negative", "cantilever.spring_constant", -1.0, "must be > 0"),
    ("spring-constant-text", "cantilever.spring_constant", "forty", "number"),
    ("spring-constant-yaml-bool", "cantilever.spring_constant", True, "expected a number"),
    ("spring-constant-nan", "cantilever.spring_constant", float("nan"), "got nan"),
    ("resonance-inf", "cantilever.resonance_frequency", float("inf"), "finite"),
    ("quality-factor-negative", "cantilever.quality_factor", -3, "must be > 0"),
    ("tip-radius-list", "cantilever.tip_radius", [1e-8], "number"),
    ("k-uncertainty-as-percent", "cantilever.spring_constant_uncertainty", 10, "must be < 1"),
    ("q-uncertainty-negative", "cantilever.quality_factor_uncertainty", -0.1, "must be >= 0"),
    ("q-uncertainty-yaml-bool", "cantilever.quality_factor_uncertainty", True, "expected a number"),
    ("k-uncertainty-nan", "cantilever.spring_constant_uncertainty", float("nan"), "got nan"),
    ("invols-uncertainty-as-percent", "data.invols_uncertainty", 5, "must be < 1"),
    ("drive-frequency-zero", "drive.frequency", 0, "must be > 0"),
    ("drive-amplitude-negative", "drive.force_amplitude", -1e-9, "must be > 0"),
    ("separation-negative", "sample.separation", -8e-9, "must be > 0"),
    ("a0-zero", "sample.a0", 0.0, "must be > 0"),
    ("data-units-unknown", "data.units", "mm", "m"),
    ("data-positive-unknown", "data.positive", "up", "toward_sample"),
    ("sample-rate-negative", "data.sample_rate", -6e7, "must be > 0"),
    ("invols-zero", "data.invols", 0, "must be > 0"),
    ("offset-inf", "data.offset", float("-inf"), "finite"),
    ("form-unknown", "fit.form", "medium", "weak"),
    ("method-unknown", "fit.method", "magic", "exhaustive"),
    ("selection-unknown", "fit.selection", "aic", "bic"),
    ("max-harmonic-one", "fit.max_harmonic", 1, "must be >= 2"),
    ("max-harmonic-huge", "fit.max_harmonic", 100000, "must be <= 500"),
    ("folds-one", "fit.folds", 1, "must be >= 2"),
    ("bootstrap-negative", "fit.bootstrap", -5, "must be >= 0"),
    ("bootstrap-float", "fit.bootstrap", 2.5, "expected a whole number"),
    ("distractor-odds-below-one", "fit.distractor_odds", 0.5, "must be >= 1"),
    ("thresholds-negative", "fit.thresholds", [0.1, -0.2], "fit.thresholds.1: must be >= 0"),
    ("phase-points-tiny", "fit.phase_points", 3, "must be >= 16"),
    ("detrend-unknown", "fit.detrend", "quadratic", "linear"),
    ("cantilever-mode-unknown", "fit.cantilever", "loose", "free"),
    ("effects-not-a-list", "model.effects", "dmt", "list"),
    ("simulate-periods-two", "simulate.periods", 2, "must be >= 3"),
    ("simulate-mode-unknown", "simulate.mode", "pulsed", "steady"),
    ("setpoint-above-one", "simulate.setpoint", 1.5, "must be < 1"),
    ("noise-negative", "simulate.noise.detector_rms", -1e-12, "must be >= 0"),
    # Beyond any detector: 1e300 m rms gave a trace of +-3e300 m (issue 32).
    ("noise-beyond-any-detector", "simulate.noise.detector_rms", 1e300, "must be <= 0.0001"),
    ("noise-density-beyond-any-detector", "simulate.noise.detector_density", 1e300, "must be <= 1e-07"),
    ("adc-step-beyond-any-detector", "simulate.noise.adc_step", 1e300, "must be <= 0.0001"),
]

#: (id, custom term, fragment of the message): the term language is parsed, never evaluated as Python.
BAD_TERMS = [
    ("python-call", "__import__('os').system('ls')", "unexpected character"),
    ("gate-dividing-by-zero", "[1/0 > 0] * z", "the constant 1/0 is not finite"),
    ("lambda", "lambda: 1", "unexpected character ':'"),
    ("matmul-operator", "z @ 2", "unexpected character '@'"),
    ("dangling-operator", "delta^1.5 +", "found end of expression"),
    ("double-power", "delta^^2", "found '^'"),
    ("unclosed-parenthesis", "sqrt(delta", "expected ')'"),
    ("unknown-name", "foo * delta", "unknown name 'foo'"),
    ("unknown-function", "sinh(z/a0)", "did you mean 'sin'"),
    ("exp-of-a-length", "exp(z)", "must be dimensionless"),
    ("fitted-parameter-in-term", "delta^1.5 * hamaker", "'hamaker' is a parameter the fit determines"),
    ("fitted-parameter-squared", "E_star^2 * delta", "'E_star' is a parameter the fit determines"),
]

CASES = [
    fit_case("unknown-top-level-key", base_config(fitt={}), 2, "fitt"),
    fit_case("unknown-nested-key", base_config(**{"cantilever.springconstant": 40.0}), 2, "cantilever.springconstant"),
    fit_case("missing-data-path", base_config(**{"data.path": None}), 2, "data.path", "required key is missing"),
    fit_case("section-not-a-mapping", base_config(cantilever=[40.0]), 2, "cantilever"),
    fit_case("yaml-syntax-error", "data: [unclosed\n", 2, None, "invalid YAML"),
    fit_case("yaml-top-level-list", "- data\n- fit\n", 2, None),
    fit_case("unknown-effect", base_config(**{"model.effects": ["dmtt"]}), 2, "model.effects", "dmt"),
    fit_case("unknown-library", base_config(**{"model.library": "table9"}), 2, "model.library"),
    *[fit_case(f"value-{id}", base_config(**{key: value}), 2, key, fragment) for id, key, value, fragment in BAD_VALUES],
    *[fit_case(f"term-{id}", base_config(**{"model.terms": [term]}), 2, "model.terms[0]", fragment, category="terms")
      for id, term, fragment in BAD_TERMS],
]


def fifo(name: str):
    """files(): a named pipe (opening it for reading would block until a writer comes)."""

    def write(folder: Path) -> None:
        os.mkfifo(folder / name)

    return write


CASES += [
    Case(id="report-of-a-fifo", category="runfile", argv=("report", "run.h5", "-o", "rep"), files=fifo("run.h5"),
         exit_code=1, file="run.h5", key=None, fragments=("not a regular file (a FIFO)",)),
    Case(id="report-of-a-folder", category="runfile", argv=("report", "run.h5", "-o", "rep"),
         files=lambda folder: (folder / "run.h5").mkdir(), exit_code=1, file="run.h5", key=None,
         fragments=("is a directory",)),
    Case(id="option-not-a-number", category="request", argv=("inspect", "trace.csv", "--sample-rate", "abc"),
         files=fit_workspace(base_config()), exit_code=2, file=None, key="--sample-rate",
         fragments=("not a valid float", "see 'afmid inspect --help'")),
    *[Case(id=f"option-sample-rate-{shown}", category="request", argv=("inspect", "trace.csv", "--sample-rate", word),
           files=fit_workspace(base_config()), exit_code=2, file=None, key="--sample-rate",
           fragments=(f"{shown} is not a sample rate: expected a positive number of Hz",))
      for word, shown in (("nan", "nan"), ("inf", "inf"), ("-6e7", "-6e+07"), ("0", "0"))],
    Case(id="missing-output-option", category="request", argv=("fit", "run.yaml"), files=fit_workspace(base_config()),
         exit_code=2, file=None, key="'-o'", fragments=("Missing option",)),
    Case(id="unknown-option", category="request", argv=("fit", "run.yaml", "-o", "out.h5", "--bootstrap", "5"),
         files=fit_workspace(base_config()), exit_code=2, file=None, key="--bootstrap",
         fragments=("No such option",)),
    Case(id="jobs-zero", category="request", argv=("batch", "run.yaml", "--inputs", "*.csv", "-o", "out", "-j", "0"),
         files=fit_workspace(base_config()), exit_code=2, file=None, key="'-j'", fragments=("0 is not in the range",)),
    Case(id="batch-manifest-is-a-fifo", category="request",
         argv=("batch", "run.yaml", "--manifest", "list.csv", "-o", "out"),
         files=lambda folder: (fit_workspace(base_config())(folder), fifo("list.csv")(folder)), exit_code=1,
         file="list.csv", key="--manifest", fragments=("not a regular file (a FIFO)",)),
]


@corpus_params(CASES)
def test_config_case(case, tmp_path, capsys, monkeypatch):
    check_case(case, tmp_path / "ws", capsys, monkeypatch)
