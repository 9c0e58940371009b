"""A fit's run record (``afmid.runfile.run_data``) is the run its file gives back (``load_run`` of
``write_run``'s file), field by field, and the file is the record's serialisation: writing the record read back
gives the same file, dataset by dataset and attribute by attribute (provenance aside), so the file holds nothing
the record lacks. On the demo's fits, on a joint fit of two traces (``afmid.joint_runfile.joint_run_data``) and
on a separation track (``afmid.joint_runfile.track_run``: the blocks' joint record with /model/separation_track).

The two are made by different code (one from the fit, one from HDF5), so each branch of the writer is covered by a
fit that takes it: a fitted drive with the separation estimated and a linear drift column; a calibrated drive
(phase and amplitude given, no fitted drive columns) with a free baseline (the offset column), the separation given
and a second effect. Tolerance: none. Every number is a float64 written and read back unchanged (HDF5 stores the
IEEE value), every array the same bits and dtype, every dict in the file's order (by name).
"""

from __future__ import annotations

import copy
import math

import h5py
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
    loaded = load_run(write_run(folder / name, run_data(result, config), overwrite=True))
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


#: Root attributes of a run file that say when and by what it was written, not what the run is.
PROVENANCE = {"created", "afmid_version"}


def _file_differences(first, second) -> list[str]:
    """Where two HDF5 files differ: members, attributes (:data:`PROVENANCE` aside), dtypes, shapes, values
    (exact, NaN equal to NaN)."""
    import h5py

    def same(a, b) -> bool:
        a, b = np.asarray(a), np.asarray(b)
        return (a.dtype == b.dtype and a.shape == b.shape
                and np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"))

    out: list[str] = []

    def walk(x, y, where: str) -> None:
        ka, kb = set(x.attrs) - PROVENANCE, set(y.attrs) - PROVENANCE
        out.extend(f"{where}@{k}: in one file only" for k in sorted(ka ^ kb))
        out.extend(f"{where}@{k}" for k in sorted(ka & kb) if not same(x.attrs[k], y.attrs[k]))
        if isinstance(x, h5py.Dataset) or isinstance(y, h5py.Dataset):
            if not (isinstance(x, h5py.Dataset) and isinstance(y, h5py.Dataset)) or not same(x[()], y[()]):
                out.append(f"{where}: values")
            return
        out.extend(f"{where}/{k}: in one file only" for k in sorted(set(x) ^ set(y)))
        for k in sorted(set(x) & set(y)):
            walk(x[k], y[k], f"{where}/{k}")

    with h5py.File(first, "r") as f, h5py.File(second, "r") as g:
        walk(f, g, "")
    return out


@pytest.mark.parametrize("variant", [_estimated_with_drift, _calibrated], ids=["estimated-drift", "calibrated"])
def test_the_file_is_the_records_serialisation(demo, variant):
    from afmid.fit.pipeline import run_fit
    from afmid.runfile import load_run, run_data, write_run

    folder, raw = demo
    config = build_config(variant(raw, folder), source=folder / "fit.yaml", base_dir=folder)
    written = write_run(folder / f"{variant.__name__}.first.h5", run_data(run_fit(config), config), overwrite=True)
    again = write_run(folder / f"{variant.__name__}.again.h5", load_run(written), overwrite=True)
    assert _file_differences(written, again) == []
    with h5py.File(written, "r") as h5:  # the branches: the candidate supports, the intervals
        assert h5["diagnostics/path/masks"].shape[0] >= 1 and "coefficients_ci_low" in h5["model"]


@pytest.fixture(scope="module")
def joint_fit(tmp_path_factory):
    """A joint fit of two short DMT traces of one lever and sample at A/A0 = 0.8 and 0.6, the separations given
    (the search is tested in tests/fit/test_joint.py): the joint result and each trace's result."""
    import yaml
    from repo_paths import TEST_CONFIGS

    from afmid.cli import main
    from afmid.fit.joint import run_joint_fit
    from afmid.fit.joint_output import trace_result
    from afmid.io.trace import read_truth

    folder = tmp_path_factory.mktemp("joint_record")
    paths = []
    for name, setpoint in (("a", 0.8), ("b", 0.6)):
        paths.append(folder / f"{name}.h5")
        assert main(["-q", "simulate", str(TEST_CONFIGS / "dmt.yaml"), "-o", str(paths[-1]), "--set",
                     "simulate.periods=20", "--set", "simulate.samples_per_period=100", "--set",
                     f"simulate.setpoint={setpoint}"]) == 0
    raw = yaml.safe_load((TEST_CONFIGS / "dmt.yaml").read_text())
    raw.pop("simulate")
    raw["data"] = {"paths": [str(p) for p in paths]}
    raw["sample"]["separation"] = [float(read_truth(p).extra["separation"]) for p in paths]
    raw["fit"]["bootstrap"] = 8
    raw["model"] = {"effects": ["dmt"]}
    config = build_config(raw, source=folder / "joint.yaml", base_dir=folder)
    result = run_joint_fit(config)
    return folder, result, [trace_result(result, i) for i in range(len(result.traces))]


def test_a_joint_fits_record_is_its_file(joint_fit):
    from afmid.joint_runfile import joint_run_data
    from afmid.runfile import JOINT_TRACE_KEYS, load_run, write_run

    folder, result, per_trace = joint_fit
    mine = joint_run_data(result, per_trace, "joint.h5")
    written = write_run(folder / "joint.h5", mine, overwrite=True)
    loaded = load_run(written)
    fields = [f for f in vars(loaded) if f not in NOT_BY_VALUE]
    assert fields == [f for f in vars(mine) if f not in NOT_BY_VALUE]
    assert [d for f in fields for d in _differences(getattr(mine, f), getattr(loaded, f), f)] == []
    assert len(loaded.joint) == 2 and all(tuple(t) == JOINT_TRACE_KEYS for t in loaded.joint)
    assert loaded.joint[0]["separation"] > loaded.joint[1]["separation"]  # A/A0 0.8 sits farther away
    assert loaded.joint_attrs["n_traces"] == 2
    again = write_run(folder / "joint.again.h5", loaded, overwrite=True)
    assert _file_differences(written, again) == []


@pytest.fixture(scope="module")
def track_fit():
    """The separation track of a 60-period record of a rough surface scanned under an amplitude feedback: two
    blocks of 30 periods, d moved per period from the rows (``within_block: rows``: the per-period offsets written
    too), no bootstrap (the intervals' branch is the single fits' above)."""
    from afmid.fit.separation_track import fit_separation_track
    from afmid.io.trace import check_trace
    from afmid.simulate.driver import simulate
    from tests.fit.test_separation_track import FEEDBACK_ROUGH, RAW

    raw = copy.deepcopy(RAW)
    raw["simulate"].update(periods=60, scan=FEEDBACK_ROUGH, seed=91)
    raw["fit"]["bootstrap"] = 0
    record = simulate(build_config(raw))
    raw.pop("simulate")
    raw["sample"].pop("separation")
    raw["fit"]["separation_track"] = {"bandwidth": 5000.0, "within_block": "rows"}
    config = build_config(raw)
    return fit_separation_track(config, check_trace(record, config), 5000.0)


def test_a_tracks_record_is_its_file(track_fit, tmp_path):
    """A separation track's record (the blocks' joint record with the track, ``afmid.joint_runfile.track_run``) is
    its file read back, field by field, the track included; and writing that gives the same file."""
    from afmid.joint_runfile import track_run
    from afmid.runfile import TRACK_KEYS, load_run, write_run

    mine, _ = track_run(track_fit, "track.h5")
    written = write_run(tmp_path / "track.h5", mine)
    loaded = load_run(written)
    fields = [f for f in vars(loaded) if f not in NOT_BY_VALUE]
    assert fields == [f for f in vars(mine) if f not in NOT_BY_VALUE]
    assert [d for f in fields for d in _differences(getattr(mine, f), getattr(loaded, f), f)] == []
    track = loaded.separation_track
    assert tuple(track) == TRACK_KEYS and track["within_block"] == "rows" and len(track["separation"]) == 2
    assert [o.size for o in track["period_offsets"]] == [30, 30]  # a period's offset each
    assert len(loaded.joint) == 2 and loaded.track_block["stop_sample"] == track["first_sample"][1]
    again = write_run(tmp_path / "track.again.h5", loaded)
    assert _file_differences(written, again) == []
