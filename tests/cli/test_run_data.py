"""A fit's run in memory (``afmid.runfile.run_data``) is the run its file gives back (``load_run`` of
``write_run``'s file), field by field, without the file in between.

The two are made by different code (one from the fit, one from HDF5), so each branch of the writer is covered by a
fit that takes it: a fitted drive with the separation estimated and a linear drift column; a calibrated drive
(phase and amplitude given, no fitted drive columns) with a free baseline (the offset column), the separation given
and a second effect. Tolerance: none. Every number is a float64 written and read back unchanged (HDF5 stores the
IEEE value), every array the same bits and dtype, every dict in the file's order (by name).
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from afmid.config import build_config
from tests.fit.test_declared_drive import demo_raw, simulated

#: RunData fields compared other than by value: the file's own path, and the ground truth (the loaded run reads
#: it from the input file, the run in memory holds the trace's: the same simulation, compared by its arrays).
NOT_BY_VALUE = {"path", "config", "truth"}


def _differences(mine, theirs, where: str) -> list[str]:
    if isinstance(mine, dict) or isinstance(theirs, dict):
        if not (isinstance(mine, dict) and isinstance(theirs, dict)) or list(mine) != list(theirs):
            return [f"{where}: keys {list(mine) if isinstance(mine, dict) else mine} != "
                    f"{list(theirs) if isinstance(theirs, dict) else theirs}"]
        return [d for k in mine for d in _differences(mine[k], theirs[k], f"{where}.{k}")]
    if isinstance(mine, np.ndarray) or isinstance(theirs, np.ndarray):
        a, b = np.asarray(mine), np.asarray(theirs)
        same = (a.dtype == b.dtype and a.shape == b.shape
                and np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"))
        return [] if same else [f"{where}: array {a.dtype}{a.shape} != {b.dtype}{b.shape} or values differ"]
    if isinstance(mine, (list, tuple)):
        if type(mine) is not type(theirs) or len(mine) != len(theirs):
            return [f"{where}: {mine!r} != {theirs!r}"]
        return [d for i, (u, v) in enumerate(zip(mine, theirs)) for d in _differences(u, v, f"{where}[{i}]")]
    if isinstance(mine, float) and isinstance(theirs, float) and math.isnan(mine) and math.isnan(theirs):
        return []
    if type(mine) is not type(theirs) or mine != theirs:
        return [f"{where}: {mine!r} ({type(mine).__name__}) != {theirs!r} ({type(theirs).__name__})"]
    return []


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    folder = tmp_path_factory.mktemp("run_data")
    raw = demo_raw(folder, periods=24)
    simulated(folder, raw)
    return folder, raw


def _calibrated(raw: dict, folder) -> dict:
    """The simulator's own drive declared (phase 0 at the first sample, its F0), the baseline free."""
    from afmid.io.trace import load_trace

    trace = load_trace(build_config(copy.deepcopy(raw), source=folder / "fit.yaml", base_dir=folder))
    raw = copy.deepcopy(raw)
    raw["drive"].pop("free_amplitude")
    raw["drive"].update(phase=0.0, force_amplitude=trace.drive_force_amplitude)
    raw["fit"].update(baseline="free")
    raw["model"] = {"effects": ["dmt", "viscoelastic"]}
    return raw


def _estimated_with_drift(raw: dict, folder) -> dict:
    """[dmt] with the drive fitted, the separation estimated, a linear drift column and a short bootstrap."""
    raw = copy.deepcopy(raw)
    raw["sample"]["separation"] = None
    raw["fit"].update(detrend="linear", bootstrap=8)
    raw["model"] = {"effects": ["dmt"]}
    return raw


@pytest.mark.parametrize("variant", [_estimated_with_drift, _calibrated], ids=["estimated-drift", "calibrated"])
def test_the_run_in_memory_is_the_run_its_file_gives_back(demo, variant):
    from afmid.fit.pipeline import run_fit
    from afmid.runfile import load_run, run_data, write_run

    folder, raw = demo
    name = f"{variant.__name__}.h5"
    config = build_config(variant(raw, folder), source=folder / "fit.yaml", base_dir=folder)
    result = run_fit(config)
    loaded = load_run(write_run(folder / name, result, config, overwrite=True))
    mine = run_data(result, config, name)
    assert mine.path.name == loaded.path.name
    fields = [f for f in vars(loaded) if f not in NOT_BY_VALUE]
    assert fields == [f for f in vars(mine) if f not in NOT_BY_VALUE]
    differences = [d for f in fields for d in _differences(getattr(mine, f), getattr(loaded, f), f)]
    assert differences == []
    assert mine.config.model_dump(mode="json") == loaded.config.model_dump(mode="json")
    assert mine.truth is not None and loaded.truth is not None
    assert _differences(vars(mine.truth), vars(loaded.truth), "truth") == []
    # the branches this fit was chosen for were taken
    if variant is _calibrated:
        assert mine.drive_calibrated and {"phase", "offset_force"} <= set(mine.drive)
        assert not mine.separation_estimated
    else:
        assert "baseline_drift" in mine.drive and mine.separation_estimated and "d" in mine.nonlinear
        assert np.isfinite(mine.force_statistical_uncertainty)
