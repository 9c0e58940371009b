"""The output file of ``afmid coverage -o``: every draw's drawn values, estimates, 1-sigma errors, truths, z and
flags, the summary per quantity and the provenance (merged config, afmid version, creation time). SI units.

``.json``: one document (NaN written as null). ``.h5`` / ``.hdf5``: the same in HDF5, format ``afmid-coverage``::

    /draws/index, seed, status, stage, error, cv_error, cv_error_noise_floor   one row per draw; recorded: what
                          the simulated record holds ('steady state', 'unsettled orbit, recorded as it is ...')
    /drawn/KEY            the drawn value of each varied key (KEY as in the config, '.' kept), NaN where failed
    /numbers/NAME/estimate, sigma (1 sigma), truth, z, ci95_low, ci95_high   (NaN where the draw has none)
    /numbers/NAME/in_ci95 (1 inside, 0 outside, -1 no interval), flags (comma-separated)
    /summary/NAME         attributes: n, flagged, within_1, within_2, fractions and their 95 % Wilson intervals, ...
    /loop/hidden, suggested, error_before, error_after, named_first, raised, false_alarm, ...   the blind loop's
                          rows (afmid.coverage.loop), its counts as JSON in the attribute ``summary``

Both are written to a temporary name and renamed into place when complete (afmid.io.trace.atomic_path).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from afmid.errors import ConfigError
from afmid.io.trace import atomic_hdf5, atomic_path, write_dataset

FILE_FORMAT = "afmid-coverage"
SUFFIXES = (".json", ".h5", ".hdf5")


def check_suffix(path: Path) -> None:
    """Refuse an output name whose suffix says no format afmid coverage writes."""
    if path.suffix.lower() not in SUFFIXES:
        raise ConfigError(f"{path}: expected a file ending in {', '.join(SUFFIXES)} (JSON or HDF5)", key="-o")


def _plain(value: Any) -> Any:
    """JSON-safe: NaN and inf as null, tuples as lists, numpy scalars as Python numbers."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def document(result) -> dict:
    """The coverage run as one JSON-able mapping (what the .json file holds)."""
    return _plain({
        "format": FILE_FORMAT, "afmid_version": result.version, "created": result.created,
        "units": "SI (m, N, Pa, J, ...; each number's unit beside it); sigma is 1 sigma, ci95 a 95 % interval",
        "config": result.config_text, "coverage": result.section.model_dump(mode="json"),
        "distributions": result.distributions, "seconds": result.seconds,
        "summary": [s.as_dict() for s in result.summaries],
        "summary_unflagged": [s.as_dict() for s in result.unflagged],
        "loop": result.loop,
        "draws": result.draws,
    })


def write_output(path: Path, result) -> None:
    """Write ``result`` (a :class:`afmid.coverage.run.CoverageResult`) to ``path`` (.json or .h5)."""
    check_suffix(path)
    if path.suffix.lower() == ".json":
        text = json.dumps(document(result), indent=1, allow_nan=False)
        with atomic_path(path) as tmp:
            tmp.write_text(text + "\n", encoding="utf-8")
        return
    _write_hdf5(path, result)


def _column(draws: list[dict], get, fill=math.nan) -> np.ndarray:
    values = []
    for one in draws:
        try:
            value = get(one)
        except (KeyError, TypeError):
            value = fill
        values.append(fill if value is None else value)
    return np.asarray(values, dtype=float)


def _write_hdf5(path: Path, result) -> None:
    draws = result.draws
    keys = list(result.distributions)
    with atomic_hdf5(path, FILE_FORMAT, result.config_text) as h5:
        h5.attrs["coverage_seed"] = result.section.seed
        h5.attrs["separation"] = result.section.separation
        h5.attrs["distributions"] = json.dumps(result.distributions)
        table = h5.create_group("draws")
        write_dataset(table, "index", np.array([d["index"] for d in draws], dtype=np.int64), "1")
        write_dataset(table, "seed", np.array([d["seed"] for d in draws], dtype=np.int64), "1",
                      description="simulate.seed of the draw")
        for name in ("status", "stage", "error", "recorded"):
            write_dataset(table, name, np.array([str(d.get(name, "")) for d in draws]), "")
        for name in ("cv_error", "cv_error_noise_floor"):
            write_dataset(table, name, _column(draws, lambda d, n=name: d[n]), "1")
        drawn = h5.create_group("drawn")
        for key in keys:
            values = [d["values"].get(key) for d in draws]
            if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
                write_dataset(drawn, key, np.asarray(values, dtype=float), "SI, as the config key")
            else:  # a choice of mappings or words: each as YAML flow text
                write_dataset(drawn, key, np.array([json.dumps(_plain(v)) for v in values]), "",
                              description="the drawn value as JSON")
        numbers = h5.create_group("numbers")
        for summary in result.summaries:
            name, group = summary.name, numbers.create_group(summary.name)
            for field in ("estimate", "sigma", "truth", "ci95_low", "ci95_high"):
                write_dataset(group, field, _column(draws, lambda d, f=field: d["numbers"][name][f]), summary.unit)
            write_dataset(group, "z", _column(draws, lambda d: d["numbers"][name]["z"]), "1",
                          description="(estimate - truth) / sigma")
            inside = _column(draws, lambda d: int(d["numbers"][name]["in_ci95"]), fill=-1)
            write_dataset(group, "in_ci95", inside.astype(np.int8), "1", description="1 inside, 0 outside, -1 none")
            write_dataset(group, "flags", np.array([",".join(d["numbers"].get(name, {}).get("flags", []))
                                                    for d in draws]), "")
        if result.loop is not None:
            _write_loop(h5.create_group("loop"), draws, result.loop)
        summary_group = h5.create_group("summary")
        for summary in result.summaries:
            group = summary_group.create_group(summary.name)
            for key, value in _plain(summary.as_dict()).items():
                group.attrs[key] = json.dumps(value) if isinstance(value, (list, dict)) or value is None else value


def _write_loop(group, draws: list[dict], summary: dict) -> None:
    """/loop: one row per draw (hidden effect, suggestion, errors before and after, verdicts) and the counts."""
    loops = [d.get("loop") or {} for d in draws]
    write_dataset(group, "hidden", np.array([str(d.get("hidden", "")) for d in draws]), "",
                  description="the effect hidden in the simulation ('none': nothing hidden)")
    write_dataset(group, "suggested", np.array([str(one.get("suggested") or "") for one in loops]), "",
                  description="the diagnosis's top suggestion ('' none)")
    for name in ("error_before", "error_after", "noise_floor_before", "noise_floor_after"):
        write_dataset(group, name, _column(loops, lambda one, n=name: one[n]), "1",
                      description="cross-validated relative RMS force error (NaN: no refit)")
    write_dataset(group, "delta_bic", _column(loops, lambda one: one["delta_bic"]), "1",
                  description="BIC change of the top suggestion (NaN: none)")
    for name in ("named_first", "raised", "false_alarm", "residual_alarm", "undecided"):
        flags = _column(loops, lambda one, n=name: int(one[n]), fill=-1)
        write_dataset(group, name, flags.astype(np.int8), "1", description="1 yes, 0 no, -1 no loop record")
    group.attrs["summary"] = json.dumps(_plain(summary))

