"""Bad-input corpus: run configs (see tests/corpus.py for the contract every case must meet)."""

from __future__ import annotations

from pathlib import Path

import yaml

from conftest import CANTILEVER, DRIVE_FREQUENCY, SAMPLE_RATE, sinusoid
from corpus import Case, check_case, corpus_params


def write_trace_csv(folder: Path, name: str = "trace.csv", periods: float = 10) -> None:
    """A 10-period drive-frequency sinusoid as CSV (time_s, deflection_nm)."""
    t, x = sinusoid(periods)
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


CASES = [
    fit_case("unknown-top-level-key", base_config(fitt={}), 2, "fitt"),
    fit_case("missing-data-path", base_config(**{"data.path": None}), 2, "data.path", "required key is missing"),
    fit_case("negative-spring-constant", base_config(**{"cantilever.spring_constant": -1.0}), 2,
             "cantilever.spring_constant"),
    fit_case("yaml-syntax-error", "data: [unclosed\n", 2, None),
]


@corpus_params(CASES)
def test_config_case(case, tmp_path, capsys, monkeypatch):
    check_case(case, tmp_path / "ws", capsys, monkeypatch)
