"""Bad-input corpus: physically absurd instrument values (cantilever, drive), from a run config, a --set
override or a trace file's metadata (see tests/corpus.py for the contract every case must meet).

A resonance frequency of 1e308 Hz or a Q of 1e12 is no AFM: afmid refuses it before fitting, instead of
writing read-outs computed from it. The limits are afmid.io.instrument_limits.INSTRUMENT_LIMITS.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import yaml

from tests.conftest import CANTILEVER, DRIVE_FREQUENCY, SAMPLE_RATE, sinusoid
from corpus import Case, check_case, corpus_params
from tests.cli.test_corpus_config import base_config, fit_case, fit_workspace


def _fit(id: str, key: str, value, *fragments: str) -> Case:
    return fit_case(id, base_config(**{key: value}), 2, key, *fragments, category="request")


def _simulate(id: str, key: str, value, *fragments: str) -> Case:
    changes = {"data.path": None, "drive.free_amplitude": 10e-9, "sample.separation": 8e-9,
               "simulate": {"model": "dmt", "periods": 5}}
    config = base_config(**{**changes, key: value})
    return Case(id=id, category="request", argv=("simulate", "run.yaml", "-o", "sim.h5"),
                files=fit_workspace(config, with_trace=False), exit_code=2, file="run.yaml", key=key,
                fragments=fragments)


def _trace_file_workspace(group: str, name: str, value: float):
    """run.yaml (no cantilever or drive section: the trace file's values are used) and an afmid trace file
    whose /group attribute ``name`` is ``value``."""

    def write(folder: Path) -> None:
        from afmid.io.trace import Cantilever, Trace, write_trace_file

        t, x_nm = sinusoid(12)
        trace = Trace(deflection=x_nm * 1e-9, sample_rate=SAMPLE_RATE, cantilever=Cantilever(**CANTILEVER),
                      drive_frequency=DRIVE_FREQUENCY, time=t)
        write_trace_file(folder / "trace.h5", trace, "")
        with h5py.File(folder / "trace.h5", "r+") as h5:
            h5[group].attrs[name] = np.float64(value)
        config = {"data": {"path": "trace.h5"}, "sample": {"a0": 0.165e-9}, "model": {"effects": ["dmt"]}}
        (folder / "run.yaml").write_text(yaml.safe_dump(config))

    return write


def _trace_file(id: str, group: str, name: str, value: float, *fragments: str) -> Case:
    return Case(id=id, category="request", argv=("fit", "run.yaml", "-o", "out.h5"),
                files=_trace_file_workspace(group, name, value), exit_code=1, file="trace.h5",
                key=f"{group}.{name}", fragments=("the trace file's", *fragments))


CASES = [
    # in the run config: ConfigError, exit 2
    _fit("resonance-frequency-1e308", "cantilever.resonance_frequency", 1e308, "<= 1e+09", "1e+308"),
    _fit("quality-factor-1e12", "cantilever.quality_factor", 1e12, "<= 1e+07"),
    _fit("spring-constant-1e9", "cantilever.spring_constant", 1e9, "<= 1e+06"),
    _fit("tip-radius-one-metre", "cantilever.tip_radius", 1.0, "<= 0.001"),
    _fit("drive-frequency-terahertz", "drive.frequency", 1e12, "<= 1e+09"),
    _simulate("simulate-free-amplitude-one-metre", "drive.free_amplitude", 1.0, "<= 0.0001"),
    _simulate("simulate-force-amplitude-10-newton", "drive.force_amplitude", 10.0, "<= 1"),
    # on the command line
    Case(id="set-quality-factor-1e12", category="request",
         argv=("fit", "run.yaml", "-o", "out.h5", "--set", "cantilever.quality_factor=1.0e12"),
         files=fit_workspace(base_config()), exit_code=2, file="run.yaml", key="cantilever.quality_factor",
         fragments=("<= 1e+07",)),
    Case(id="batch-set-resonance-frequency-1e308", category="request",
         argv=("batch", "run.yaml", "--inputs", "trace.csv", "-o", "out", "--set",
               "cantilever.resonance_frequency=1.0e308"),
         files=fit_workspace(base_config()), exit_code=2, file="run.yaml", key="cantilever.resonance_frequency",
         fragments=("<= 1e+09",)),
    # in a trace file's metadata (no config value to override them): InputError naming the file, exit 1
    _trace_file("trace-file-quality-factor-1e12", "cantilever", "quality_factor", 1e12, "<= 1e+07"),
    _trace_file("trace-file-resonance-frequency-inf", "cantilever", "resonance_frequency", np.inf, "finite"),
    _trace_file("trace-file-negative-spring-constant", "cantilever", "spring_constant", -40.0, "> 0"),
    _trace_file("trace-file-drive-frequency-1e308", "drive", "frequency", 1e308, "<= 1e+09"),
    _trace_file("trace-file-tip-radius-one-metre", "cantilever", "tip_radius", 1.0, "<= 0.001"),
    _trace_file("trace-file-force-amplitude-10-newton", "drive", "force_amplitude", 10.0, "<= 1"),
    # written the YAML 1.1 way (no dot: a string that becomes a number)
    fit_case("yaml-string-resonance-frequency-1e308",
             yaml.safe_dump(base_config()).replace("resonance_frequency: 300000.0", "resonance_frequency: 1e308"),
             2, "cantilever.resonance_frequency", "<= 1e+09", category="request"),
    # a fixed nonlinear parameter outside the range the effect declares (the fit would use it as given)
    fit_case("fixed-negative-damping-length",
             base_config(**{"model.effects": ["dmt", "exponential_damping"],
                            "model.parameters": {"damping_length": -1e-9}}),
             2, "model.parameters.damping_length", "must be in [5e-11, 5e-08] m", category="request"),
    fit_case("fixed-rupture-distance-one-metre",
             base_config(**{"model.effects": ["dmt", "capillary"], "model.parameters": {"rupture_distance": 1.0}}),
             2, "model.parameters.rupture_distance", "got 1", category="request"),
    Case(id="set-negative-neck-length", category="request",
         argv=("fit", "run.yaml", "-o", "out.h5", "--set", "model.parameters.neck_length=-1.0e-9"),
         files=fit_workspace(base_config(**{"model.effects": ["jkr"]})), exit_code=2, file="run.yaml",
         key="model.parameters.neck_length", fragments=("must be in [0, 2e-08] m",)),
]


@corpus_params(CASES)
def test_plausibility_case(case, tmp_path, capsys, monkeypatch):
    check_case(case, tmp_path / "ws", capsys, monkeypatch)
