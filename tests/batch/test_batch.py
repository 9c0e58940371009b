"""``afmid batch``: parallel fits equal single runs, resuming, bad traces, interruption, worker crashes.

Behaviour only (timing is in bench/bench_batch.py). One short DMT trace is
simulated per module; the other traces are copies with fresh detector noise,
so every input has its own bytes and its own result. Workers are spawned
processes (about 2 s each to start and load numba's cache), so the batches
here are small.

The second half runs many configs (``--configs``), each with its own model:
DMT and Lennard-Jones configs simulated into the output folder first (20
periods), a config fitting a trace file of its own, and two bad configs.
"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from afmid.batch.run import (RUN_SUFFIX, TRACE_SUFFIX, assign_names, batch_key, read_manifest, read_run_row, run_batch,
                         trace_is_current, Entry)
from afmid.errors import ConfigError, InputError
from repo_paths import REPO_ROOT
from terminal_signals import terminal_signals

pytestmark = pytest.mark.numerics  # floating-point results compared (blas_sensitive ones: make test-kernels runs them again)

ROOT = REPO_ROOT
CONFIG = ROOT / "configs" / "dmt.yaml"
FAST = ["fit.bootstrap=8"]
AFMID = [sys.executable, "-m", "afmid.cli"]
#: What may differ between a batch's run file and a single run's: the creation time and the batch's resume key.
VOLATILE_ROOT_ATTRS = {"created", "batch_key"}
SINGLE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def traces(tmp_path_factory) -> Path:
    """Folder with n01..n05.h5: a 20-period DMT trace and noisy copies of it."""
    from afmid.config import dump_config, load_config
    from afmid.io.trace import write_trace_file
    from afmid.simulate.driver import simulate

    folder = tmp_path_factory.mktemp("traces")
    cfg = load_config(CONFIG, ["simulate.periods=20"])
    trace = simulate(cfg)
    text = dump_config(cfg)
    for i in range(1, 6):
        noisy = np.random.default_rng(i).normal(0.0, 1e-12, trace.deflection.size)
        trace_i = type(trace)(**{**trace.__dict__, "deflection": trace.deflection + noisy})
        write_trace_file(folder / f"n{i:02d}.h5", trace_i, text)
    return folder


def _copy(traces: Path, dest: Path, names: list[str]) -> list[Path]:
    dest.mkdir(parents=True, exist_ok=True)
    out = []
    for name in names:
        target = dest / name
        target.write_bytes((traces / name).read_bytes())
        out.append(target)
    return out


def _summary(folder: Path) -> list[dict]:
    with open(folder / "summary.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def _leftovers(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob(".afmid-tmp-*"))


def _content(path: Path) -> dict:
    """Every dataset and attribute of an HDF5 file as comparable bytes (root attrs minus the volatile ones)."""

    def norm(value):
        a = np.asarray(value)
        if a.dtype.kind == "O":
            return ("text", [v.decode() if isinstance(v, bytes) else v for v in a.ravel().tolist()])
        return (a.dtype.str, a.shape, a.tobytes())

    out = {}
    with h5py.File(path, "r") as h5:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = norm(obj[()])
            out[name + "@"] = {k: norm(obj.attrs[k]) for k in obj.attrs}

        h5.visititems(visit)
        out["/@"] = {k: norm(h5.attrs[k]) for k in h5.attrs if k not in VOLATILE_ROOT_ATTRS}
    return out


def _fit_alone(trace: Path, output: Path, *extra: str) -> None:
    """``afmid fit`` in a fresh process, BLAS on one thread like the batch workers (see bench/README.md)."""
    _afmid_alone("fit", CONFIG, output, *FAST, f"data.path={trace}", *extra)


def _afmid_alone(command: str, config: Path, output: Path, *overrides: str) -> None:
    """``afmid COMMAND CONFIG -o OUTPUT --set ...`` in a fresh process, BLAS on one thread like the batch workers."""
    env = dict(os.environ, **SINGLE_THREAD)
    args = AFMID + ["-q", command, str(config), "-o", str(output)]
    for o in overrides:
        args += ["--set", o]
    subprocess.run(args, check=True, env=env, cwd=ROOT, timeout=120)


# --------------------------------------------------------------------------- results
@pytest.mark.blas_sensitive  # the same bits demanded from worker processes and from in-process runs
def test_parallel_batch_equals_single_runs_bit_for_bit(traces, tmp_path):
    inputs = _copy(traces, tmp_path / "in", ["n01.h5", "n02.h5", "n03.h5"])
    out = tmp_path / "out"
    result = run_batch(CONFIG, out, inputs=[str(tmp_path / "in" / "*.h5")], jobs=2, overrides=FAST)
    assert [r.status for r in result.rows] == ["ok"] * 3
    assert sorted(p.name for p in out.iterdir()) == ["n01.run.h5", "n02.run.h5", "n03.run.h5", "summary.csv",
                                                     "summary.h5"]
    for trace in inputs[:2]:
        single = tmp_path / f"{trace.stem}.single.h5"
        _fit_alone(trace, single)
        batch, alone = _content(out / f"{trace.stem}{RUN_SUFFIX}"), _content(single)
        assert batch.keys() == alone.keys()
        differ = [k for k in batch if batch[k] != alone[k]]
        assert not differ, f"{trace.name}: batch and single run differ in {differ[:10]}"
    # Different inputs give different results (the comparison above is not trivially true).
    assert _content(out / "n01.run.h5")["model/coefficients"] != _content(out / "n03.run.h5")["model/coefficients"]


def test_summary_has_one_row_per_trace_with_si_units(traces, tmp_path):
    _copy(traces, tmp_path / "in", ["n01.h5"])
    (tmp_path / "in" / "broken.h5").write_text("not an HDF5 file\n")
    out = tmp_path / "out"
    result = run_batch(CONFIG, out, inputs=[str(tmp_path / "in" / "*.h5")], jobs=2, overrides=FAST)
    assert [(r.item.name, r.status) for r in result.rows] == [("broken", "failed"), ("n01", "ok")]
    rows = _summary(out)
    assert [r["name"] for r in rows] == ["broken", "n01"]
    header = list(rows[0])
    for column in ("cv_error", "separation_m", "E_star_Pa", "E_star_sigma_Pa", "E_star_ci_low_Pa",
                   "hamaker_J", "adhesion_force_N", "fit_time_s", "status", "failure", "diagnosis"):
        assert column in header, column
    ok = rows[1]
    run = read_run_row(out / "n01.run.h5")
    assert float(ok["E_star_Pa"]) == run["quantities"]["E_star"]["value"]
    assert float(ok["cv_error"]) == run["values"]["cv_error"]
    assert 1e9 < float(ok["E_star_Pa"]) < 3e9  # truth 2 GPa
    assert "not a readable HDF5 file" in rows[0]["failure"] and rows[0]["run_file"] == "" and rows[0]["diagnosis"] == ""
    assert ok["diagnosis"].startswith(("at the noise floor (x", "model-limited (x")), ok["diagnosis"]
    with h5py.File(out / "summary.h5", "r") as h5:
        assert h5.attrs["format"] == "afmid-batch-summary"
        assert [s.decode() for s in h5["status"][...]] == ["failed", "ok"]
        assert h5["parameters/E_star/value"].attrs["units"] == "Pa"
        assert h5["parameters/E_star/sigma"].attrs["units"] == "Pa"
        assert h5["parameters/E_star/sigma"].attrs["error_kind"] == "1 sigma" and "parameters/E_star/error" not in h5
        assert [s.decode() for s in h5["diagnosis"][...]][0] == "" and "model-limited" in h5["diagnosis"].attrs["meaning"]
        assert h5["cv_error"].attrs["units"] == "1"
        assert h5["separation"].attrs["units"] == "m"
        assert np.isnan(h5["parameters/E_star/value"][0]) and h5["parameters/E_star/value"][1] == run["quantities"]["E_star"]["value"]
        for name, obj in h5.items():
            if isinstance(obj, h5py.Dataset):
                assert "units" in obj.attrs, name


# --------------------------------------------------------------------------- resume
def test_rerun_skips_finished_traces_and_refits_changed_ones(traces, tmp_path):
    inputs = _copy(traces, tmp_path / "in", ["n01.h5", "n02.h5"])
    out = tmp_path / "out"
    pattern = [str(tmp_path / "in" / "*.h5")]
    first = run_batch(CONFIG, out, inputs=pattern, jobs=1, overrides=FAST)
    assert [r.status for r in first.rows] == ["ok", "ok"]
    stamps = {p.name: p.stat().st_mtime_ns for p in out.glob(f"*{RUN_SUFFIX}")}
    before = _summary(out)

    again = run_batch(CONFIG, out, inputs=pattern, jobs=1, overrides=FAST)
    assert [r.status for r in again.rows] == ["skipped", "skipped"]
    assert {p.name: p.stat().st_mtime_ns for p in out.glob(f"*{RUN_SUFFIX}")} == stamps
    after = _summary(out)
    for b, a in zip(before, after):  # the same numbers for skipped traces
        assert a["E_star_Pa"] == b["E_star_Pa"] and a["cv_error"] == b["cv_error"]

    # New bytes in one input: only that trace is refitted. A changed config refits everything.
    inputs[1].write_bytes((traces / "n03.h5").read_bytes())
    third = run_batch(CONFIG, out, inputs=pattern, jobs=1, overrides=FAST)
    assert [r.status for r in third.rows] == ["skipped", "ok"]
    fourth = run_batch(CONFIG, out, inputs=pattern, jobs=1, overrides=["fit.bootstrap=6"])
    assert [r.status for r in fourth.rows] == ["ok", "ok"]
    with h5py.File(out / "n01.run.h5", "r") as h5:
        assert h5.attrs["batch_key"] == batch_key(h5.attrs["input_sha256"], _blank_path(h5.attrs["config"]))


def _blank_path(config_text: str) -> str:
    import yaml

    from afmid.config import build_config, dump_config

    raw = yaml.safe_load(config_text)
    raw["data"]["path"] = None
    return dump_config(build_config(raw))


# --------------------------------------------------------------------------- failures
def test_bad_traces_and_overrides_are_reported_and_do_not_stop_the_batch(traces, tmp_path, run_cli):
    _copy(traces, tmp_path / "in", ["n01.h5", "n02.h5"])
    (tmp_path / "in" / "empty.h5").write_bytes(b"")
    manifest = tmp_path / "list.yaml"
    manifest.write_text(
        "- in/n01.h5\n"
        "- {path: in/empty.h5}\n"
        "- {path: in/missing.h5}\n"
        "- {path: in/n02.h5, set: {cantilever.quality_factor: -3}}\n"
        "- {path: in/n02.h5, name: n02_q300, set: [cantilever.quality_factor=300]}\n"
    )
    out = tmp_path / "out"
    code, _, err = run_cli("-q", "batch", CONFIG, "--manifest", manifest, "-o", out, "-j", "2", "--set",
                           FAST[0])
    assert code == 1
    assert "3 of 5 traces failed (empty, missing, n02)" in err
    rows = {r["name"]: r for r in _summary(out)}
    assert list(rows) == ["n01", "empty", "missing", "n02", "n02_q300"]
    assert rows["n01"]["status"] == "ok" and rows["n02_q300"]["status"] == "ok"
    assert rows["empty"]["status"] == "failed" and "empty.h5" in rows["empty"]["failure"]
    assert rows["missing"]["status"] == "failed" and "not found" in rows["missing"]["failure"]
    assert rows["n02"]["status"] == "failed" and "quality_factor" in rows["n02"]["failure"]
    with h5py.File(out / "n02_q300.run.h5", "r") as h5:
        assert "quality_factor: 300" in h5.attrs["config"]
    assert not (out / "n02.run.h5").exists() and not _leftovers(out)


def test_a_worker_that_dies_fails_only_its_trace(traces, tmp_path):
    from batch_workers import DYING_ITEM, fit_task_dying_on_one_item

    assert DYING_ITEM == "n02"
    _copy(traces, tmp_path / "in", ["n01.h5", "n02.h5", "n03.h5"])
    out = tmp_path / "out"
    result = run_batch(CONFIG, out, inputs=[str(tmp_path / "in" / "*.h5")], jobs=2, overrides=FAST,
                       worker=fit_task_dying_on_one_item)  # the worker of n02 SIGKILLs itself
    status = {r.item.name: (r.status, r.failure) for r in result.rows}
    assert status["n01"][0] == "ok" and status["n03"][0] == "ok"
    assert status["n02"][0] == "failed" and "worker process died" in status["n02"][1]
    assert not _leftovers(out)
    assert [r["status"] for r in _summary(out)] == ["ok", "failed", "ok"]


def test_another_engine_runs_the_items(traces, tmp_path):
    from batch_workers import SerialEngine

    _copy(traces, tmp_path / "in", ["n01.h5", "n02.h5", "n03.h5"])
    out = tmp_path / "out"
    engine = SerialEngine()
    first = run_batch(CONFIG, out, inputs=[str(tmp_path / "in" / "n0[12].h5")], overrides=FAST, engine=engine)
    assert engine.ran == [0, 1] and [r.status for r in first.rows] == ["ok", "ok"]
    again = run_batch(CONFIG, out, inputs=[str(tmp_path / "in" / "*.h5")], overrides=FAST, engine=engine)
    assert engine.ran == [0, 1, 2], "only the new item runs: the others are up to date"
    assert [r.status for r in again.rows] == ["skipped", "skipped", "ok"]
    assert [r["status"] for r in _summary(out)] == ["skipped", "skipped", "ok"]
    for name in ("n01", "n02", "n03"):
        read_run_row(out / f"{name}{RUN_SUFFIX}")  # whole, readable run files


def _interrupt_after_first_run(args: list[str], out: Path, env: dict) -> tuple[int, str]:
    """Start ``afmid batch`` in its own process group, Ctrl-C it once a run file exists; (exit code, stderr)."""
    proc = subprocess.Popen(args, env=env, cwd=ROOT, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=terminal_signals)
    try:
        deadline = time.monotonic() + 60
        while not list(out.glob(f"*{RUN_SUFFIX}")) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert list(out.glob(f"*{RUN_SUFFIX}")), "no run finished within 60 s"
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C in a terminal: the whole process group
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    return proc.returncode, err


def test_interrupted_batch_leaves_whole_files_and_a_valid_summary(traces, tmp_path):
    """Ctrl-C at a fixed point: right after the worker of ``INTERRUPTING_ITEM`` renamed its run file into place and
    before the parent has its result (the others held 30 s mid-item, so they never finish). Exit 130, no temporary
    file, that item's run file alone, whole, and listed in the summary, whether the parent got the result or only
    finds the file; a resume skips it and fits the rest."""
    from batch_workers import INTERRUPT_AFTER_RUN_FILE, INTERRUPTING_ITEM

    names = ["n01.h5", "n02.h5", "n03.h5", "n04.h5", "n05.h5"]
    _copy(traces, tmp_path / "in", names)
    out = tmp_path / "out"
    args = INTERRUPT_AFTER_RUN_FILE + [str(CONFIG), "--inputs", str(tmp_path / "in" / "*.h5"), "-o", str(out),
                                       "-j", "2", "--set", FAST[0]]
    proc = subprocess.run(args, env=dict(os.environ), cwd=ROOT, stderr=subprocess.PIPE, text=True,
                          start_new_session=True, preexec_fn=terminal_signals, timeout=120)
    assert proc.returncode == 130, proc.stderr
    assert "interrupted" in proc.stderr
    assert not _leftovers(out)
    finished = sorted(p.name for p in out.glob(f"*{RUN_SUFFIX}"))
    assert finished == [f"{INTERRUPTING_ITEM}{RUN_SUFFIX}"]
    read_run_row(out / finished[0])  # whole and readable
    rows = _summary(out)
    assert [Path(r["run_file"]).name for r in rows] == finished and rows[0]["status"] == "ok"

    again = run_batch(CONFIG, out, inputs=[str(tmp_path / "in" / "*.h5")], jobs=2, overrides=FAST)
    status = {r.item.output.name: r.status for r in again.rows}
    assert status[finished[0]] == "skipped"
    assert sorted(status.values()).count("ok") == len(names) - 1


def test_a_run_file_whose_outcome_the_interrupt_cut_short_is_in_the_summary(traces, tmp_path):
    """Ctrl-C after a worker renamed its run file into place, while the parent was recording its outcome (an engine
    that never reports it): the run file is whole and current, so the summary written on the interrupt lists it
    (it used to list nothing, and only a resume showed the file, as skipped)."""
    from afmid.batch.run import BatchInterrupted
    from batch_workers import EngineLosingItsFirstOutcome

    names = ["n01.h5", "n02.h5"]
    _copy(traces, tmp_path / "in", names)
    out = tmp_path / "out"
    with pytest.raises(BatchInterrupted) as stopped:
        run_batch(CONFIG, out, inputs=[str(tmp_path / "in" / "*.h5")], overrides=FAST,
                  engine=EngineLosingItsFirstOutcome())
    assert [r.item.output.name for r in stopped.value.result.rows] == [f"n01{RUN_SUFFIX}"]
    assert sorted(p.name for p in out.glob(f"*{RUN_SUFFIX}")) == [f"n01{RUN_SUFFIX}"]
    assert not _leftovers(out)
    rows = _summary(out)
    assert [Path(r["run_file"]).name for r in rows] == [f"n01{RUN_SUFFIX}"] and rows[0]["status"] == "ok"


def test_ctrl_c_of_afmid_batch_itself_exits_130_naming_what_finished(traces, tmp_path):
    """The command's own part of an interrupt (the held-worker tests above run run_batch through a test script):
    BatchInterrupted becomes the line of what finished, the hint to resume, and exit 130. One worker, five
    items: when the first run file appears four are still to run, so the Ctrl-C lands inside the batch."""
    names = ["n01.h5", "n02.h5", "n03.h5", "n04.h5", "n05.h5"]
    _copy(traces, tmp_path / "in", names)
    out = tmp_path / "out"
    args = AFMID + ["-q", "batch", str(CONFIG), "--inputs", str(tmp_path / "in" / "*.h5"), "-o", str(out), "-j",
                    "1", "--set", FAST[0]]
    code, err = _interrupt_after_first_run(args, out, dict(os.environ))
    assert code == 130, err
    assert "afmid: batch stopped with " in err and f"of {len(names)} " in err, err
    assert "run the same command again to resume" in err
    assert not _leftovers(out)


# --------------------------------------------------------------------------- planning (no fits)
def test_colliding_stems_get_distinct_stable_names(tmp_path):
    paths = [tmp_path / "a" / "trace.csv", tmp_path / "b" / "trace.csv", tmp_path / "x" / "dmt.trace.h5",
             tmp_path / "x" / "other.h5"]
    entries = [Entry(p) for p in paths] + [Entry(paths[3]), Entry(paths[3], name="mine")]
    assert assign_names(entries) == ["a_trace", "b_trace", "dmt", "other", "other-2", "mine"]


def test_manifests_yaml_and_csv(tmp_path):
    (tmp_path / "m.csv").write_text("path,name,fit.bootstrap,set\n"
                                    "t/a.csv,,20,sample.separation=9.0e-9;model.effects=[dmt]\n"
                                    "t/b.csv,bee,,\n")
    a, b = read_manifest(tmp_path / "m.csv")
    assert a.path == (tmp_path / "t" / "a.csv").resolve() and a.name is None
    assert sorted(a.overrides) == sorted([(["fit", "bootstrap"], 20), (["sample", "separation"], 9e-9),
                                          (["model", "effects"], ["dmt"])])
    assert b.name == "bee" and b.overrides == []
    (tmp_path / "m.yaml").write_text("traces:\n  - t/a.csv\n  - {path: t/b.csv, set: {fit.seed: 3}}\n")
    a, b = read_manifest(tmp_path / "m.yaml")
    assert a.overrides == [] and b.overrides == [(["fit", "seed"], 3)]
    (tmp_path / "bad.yaml").write_text("- {file: x.csv}\n")
    with pytest.raises(ConfigError, match="path"):
        read_manifest(tmp_path / "bad.yaml")
    with pytest.raises(InputError, match="no files match"):
        run_batch(CONFIG, tmp_path / "o", inputs=[str(tmp_path / "nothing" / "*.csv")])


# =========================================================================== many configs (--configs)
#: Settings for every config of the --configs batches: short simulated traces, few bootstrap refits.
CONFIG_SET = FAST + ["simulate.periods=20"]


@pytest.fixture(scope="module")
def config_dir(traces, tmp_path_factory) -> Path:
    """Run configs with their own models and data: DMT and Lennard-Jones to simulate, a config fitting its own
    trace file (``data.path``), an invalid config and one with neither data nor a simulate: section."""
    folder = tmp_path_factory.mktemp("configs")
    for name in ("dmt", "lennard_jones"):
        (folder / f"{name}.yaml").write_text((ROOT / "configs" / f"{name}.yaml").read_text())
    (folder / "measured.h5").write_bytes((traces / "n01.h5").read_bytes())
    (folder / "measured.yaml").write_text("data: {path: measured.h5}\n"
                                          "sample: {separation: 8.5e-9, a0: 0.165e-9}\n"
                                          "model: {effects: [dmt]}\n")
    (folder / "bad.yaml").write_text("cantilever: {quality_factor: -3}\nsimulate: {model: dmt}\n")
    (folder / "nodata.yaml").write_text("model: {effects: [dmt]}\n")
    return folder


@pytest.fixture(scope="module")
def config_batch(config_dir, tmp_path_factory):
    """``afmid batch --configs 'DIR/*.yaml' -j 2`` once per module: (output folder, BatchResult)."""
    out = tmp_path_factory.mktemp("config_batch") / "out"
    result = run_batch(None, out, configs=[str(config_dir / "*.yaml")], jobs=2, overrides=CONFIG_SET)
    return out, result


def test_configs_are_simulated_then_fitted_like_single_runs(config_dir, config_batch, tmp_path):
    out, result = config_batch
    assert [(r.item.name, r.status) for r in result.rows] == [
        ("bad", "failed"), ("dmt", "ok"), ("lennard_jones", "ok"), ("measured", "ok"), ("nodata", "failed")]
    assert result.unit == "runs" and "5 runs (3 ok, 2 failed)" in result.line()
    assert sorted(p.name for p in out.iterdir()) == [
        "dmt.run.h5", "dmt.trace.h5", "lennard_jones.run.h5", "lennard_jones.trace.h5", "measured.run.h5",
        "summary.csv", "summary.h5"]
    # The simulated traces are what `afmid simulate` writes ...
    for name in ("dmt", "lennard_jones"):
        alone = tmp_path / f"{name}{TRACE_SUFFIX}"
        _afmid_alone("simulate", config_dir / f"{name}.yaml", alone, *CONFIG_SET)
        batch, single = _content(out / f"{name}{TRACE_SUFFIX}"), _content(alone)
        assert batch.keys() == single.keys()
        differ = [k for k in batch if batch[k] != single[k]]
        assert not differ, f"{name}: batch and single simulation differ in {differ[:10]}"
    # ... and each run is what `afmid fit` writes, for a simulated trace and for a config's own data file.
    for name, extra in (("dmt", [f"data.path={(out / 'dmt.trace.h5').resolve()}"]), ("measured", [])):
        alone = tmp_path / f"{name}.single.h5"
        _afmid_alone("fit", config_dir / f"{name}.yaml", alone, *CONFIG_SET, *extra)
        batch, single = _content(out / f"{name}{RUN_SUFFIX}"), _content(alone)
        assert batch.keys() == single.keys()
        differ = [k for k in batch if batch[k] != single[k]]
        assert not differ, f"{name}: batch and single run differ in {differ[:10]}"
    with h5py.File(out / "measured.run.h5", "r") as h5:
        assert h5.attrs["input_path"] == str((config_dir / "measured.h5").resolve())


def test_config_summary_has_the_union_of_the_runs_quantities(config_dir, config_batch):
    out, result = config_batch
    rows = {r["name"]: r for r in _summary(out)}
    assert list(rows) == ["bad", "dmt", "lennard_jones", "measured", "nodata"]
    header = list(rows["dmt"])
    for column in ("config", "effects", "E_star_Pa", "E_star_sigma_Pa", "sigma_m", "sigma_ci_high_m",
                   "hamaker_J", "simulate_time_s", "fit_time_s"):
        assert column in header, column
    dmt, lj, measured = rows["dmt"], rows["lennard_jones"], rows["measured"]
    assert dmt["effects"] == "dmt" and lj["effects"] == "lennard_jones"
    assert dmt["config"] == str(config_dir / "dmt.yaml")
    assert dmt["input"] == str((out / "dmt.trace.h5").resolve()) and dmt["run_file"] == str((out / "dmt.run.h5").resolve())
    assert measured["input"] == str((config_dir / "measured.h5").resolve())
    assert 1e9 < float(dmt["E_star_Pa"]) < 3e9 and dmt["sigma_m"] == "" and dmt["sigma_sigma_m"] == ""
    assert 0.25e-9 < float(lj["sigma_m"]) < 0.35e-9 and lj["E_star_Pa"] == "" and lj["E_star_sigma_Pa"] == ""
    assert float(lj["hamaker_J"]) > 0 and float(dmt["hamaker_J"]) > 0  # shared by both models: one column
    assert float(dmt["simulate_time_s"]) > 0 and measured["simulate_time_s"] == ""
    assert rows["bad"]["status"] == "failed" and "quality_factor: must be > 0" in rows["bad"]["failure"]
    assert rows["nodata"]["status"] == "failed" and "no data.path" in rows["nodata"]["failure"]
    assert rows["bad"]["run_file"] == rows["nodata"]["run_file"] == rows["nodata"]["input"] == ""
    # issue 33: a model-limited run was listed 'ok' with nothing beside it saying so
    from afmid.fit.uncertainty import model_limited

    assert "model_limited" in header and rows["bad"]["model_limited"] == ""
    for row in (dmt, lj, measured):
        with h5py.File(row["run_file"], "r") as run:  # the fit's own threshold: its floor's degrees of freedom
            floor_dof = float(run["diagnostics/cv_error_floor_dof"][()])
        limited = model_limited(float(row["cv_error"]), float(row["cv_error_noise_floor"]), floor_dof)
        assert row["model_limited"] == str(int(limited)), row
        assert row["diagnosis"].startswith("model-limited" if limited else "at the noise floor"), row
    with h5py.File(out / "summary.h5", "r") as h5:
        assert h5.attrs["config"] == "" and h5.attrs["n_ok"] == 3 and h5.attrs["n_failed"] == 2
        assert [s.decode() for s in h5["name"][...]] == list(rows)
        assert h5["config"][2].decode() == str(config_dir / "lennard_jones.yaml")
        sigma, e_star = h5["parameters/sigma/value"], h5["parameters/E_star/value"]
        assert sigma.attrs["units"] == "m" and e_star.attrs["units"] == "Pa"
        assert h5["parameters/sigma"].attrs["effect"] == "lennard_jones"
        assert np.isnan(sigma[1]) and sigma[2] == float(lj["sigma_m"]) and np.isnan(e_star[2])
        assert np.isnan(h5["parameters/sigma/sigma"][1]) and np.isnan(h5["simulate_time"][3])
        assert h5["parameters/E_star/value"][1] == read_run_row(out / "dmt.run.h5")["quantities"]["E_star"]["value"]


def test_config_batch_resumes_without_simulating_again(config_dir, config_batch, tmp_path):
    import shutil

    configs, out = tmp_path / "configs", tmp_path / "out"
    shutil.copytree(config_dir, configs)
    shutil.copytree(config_batch[0], out)
    pattern = [str(configs / "*.yaml")]

    def stamps() -> dict:
        return {p.name: p.stat().st_mtime_ns for p in out.glob("*.h5") if not p.name.startswith("summary")}

    before = stamps()
    again = run_batch(None, out, configs=pattern, jobs=2, overrides=CONFIG_SET)
    assert [r.status for r in again.rows] == ["failed", "skipped", "skipped", "skipped", "failed"]
    assert stamps() == before

    # A lost run file: refitted from the trace already simulated. A changed config (the seed): simulated again.
    (out / "dmt.run.h5").unlink()
    lj = configs / "lennard_jones.yaml"
    assert "  seed: 2" in lj.read_text()
    lj.write_text(lj.read_text().replace("  seed: 2", "  seed: 3"))
    third = run_batch(None, out, configs=pattern, jobs=2, overrides=CONFIG_SET)
    assert [r.status for r in third.rows] == ["failed", "ok", "ok", "skipped", "failed"]
    now = stamps()
    assert now["dmt.trace.h5"] == before["dmt.trace.h5"] and now["measured.run.h5"] == before["measured.run.h5"]
    assert now["lennard_jones.trace.h5"] != before["lennard_jones.trace.h5"]
    rows = {r["name"]: r for r in _summary(out)}
    assert rows["dmt"]["simulate_time_s"] == "" and float(rows["lennard_jones"]["simulate_time_s"]) > 0
    with h5py.File(out / "lennard_jones.trace.h5", "r") as h5:
        assert "seed: 3" in h5.attrs["config"]


def test_interrupted_config_batch_leaves_whole_traces_and_resumes(tmp_path):
    configs, out = tmp_path / "configs", tmp_path / "out"
    configs.mkdir()
    text = (ROOT / "configs" / "dmt.yaml").read_text()
    assert "  seed: 1 " in text
    for i in (1, 2, 3):
        (configs / f"s{i}.yaml").write_text(text.replace("  seed: 1 ", f"  seed: {10 + i} "))
    from batch_workers import HOLD_1500MS

    # each worker sleeps 1.5 s holding its simulated trace under a temporary name: Ctrl-C lands mid-item
    args = HOLD_1500MS + ["--configs", str(configs / "*.yaml"), "-o", str(out), "-j", "2"]
    for o in CONFIG_SET:
        args += ["--set", o]
    code, err = _interrupt_after_first_run(args, out, dict(os.environ))
    assert code == 130, err
    assert "interrupted" in err and "of 3 runs" in err
    assert not _leftovers(out)
    finished = sorted(p.name for p in out.glob(f"*{RUN_SUFFIX}"))
    assert 1 <= len(finished) < 3
    assert sorted(Path(r["run_file"]).name for r in _summary(out)) == finished
    traces = {p.name: p.stat().st_mtime_ns for p in out.glob(f"*{TRACE_SUFFIX}")}
    for name in traces:  # whole trace files, each the one its config gives
        config = configs / (name[: -len(TRACE_SUFFIX)] + ".yaml")
        from afmid.config import dump_config, load_config

        assert trace_is_current(out / name, dump_config(load_config(config, CONFIG_SET)))

    again = run_batch(None, out, configs=[str(configs / "*.yaml")], jobs=2, overrides=CONFIG_SET)
    status = {r.item.output.name: r.status for r in again.rows}
    assert all(status[n] == "skipped" for n in finished)
    assert sorted(status.values()).count("ok") == 3 - len(finished)
    for name, stamp in traces.items():  # traces simulated before the interruption are not simulated again
        assert (out / name).stat().st_mtime_ns == stamp


def test_config_manifests_plans_and_usage_errors(traces, tmp_path):
    from afmid.batch.run import plan

    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "a.yaml").write_text((ROOT / "configs" / "dmt.yaml").read_text())
    trace = tmp_path / "t" / "x.h5"
    _copy(traces, tmp_path / "t", ["n01.h5"])[0].rename(trace)
    (tmp_path / "m.yaml").write_text("runs:\n"
                                     "  - {config: c/a.yaml}\n"
                                     "  - {config: c/a.yaml, path: t/x.h5, name: ax, set: {fit.seed: 3}}\n"
                                     "  - t/x.h5\n")
    a, ax, x = read_manifest(tmp_path / "m.yaml")
    assert a.config == (tmp_path / "c" / "a.yaml").resolve() and a.path is None
    assert ax.config == a.config and ax.path == trace.resolve() and ax.name == "ax"
    assert x.config is None and x.path == trace.resolve()
    (tmp_path / "m.csv").write_text("config,path,name,fit.seed\nc/a.yaml,,,\nc/a.yaml,t/x.h5,ax,3\n")
    a2, ax2 = read_manifest(tmp_path / "m.csv")
    assert (a2.config, a2.path) == (a.config, None) and (ax2.path, ax2.overrides) == (ax.path, [(["fit", "seed"], 3)])
    # Names from the config's stem; the same config twice: numbered.
    entries = [Entry(None, config=tmp_path / "c" / "a.yaml"), Entry(None, config=tmp_path / "d" / "a.yaml"),
               Entry(None, config=tmp_path / "c" / "b.yaml"), Entry(None, config=tmp_path / "c" / "b.yaml")]
    assert assign_names(entries) == ["c_a", "d_a", "b", "b-2"]
    # A config without data.path is simulated into the output folder; a row with a trace fits that trace.
    items, text = plan(None, [a, ax], tmp_path / "out", ["simulate.periods=20"])
    assert text == "" and [i.name for i in items] == ["a", "ax"] and all(i.error is None for i in items)
    assert items[0].simulate is not None and items[0].input == (tmp_path / "out" / "a.trace.h5").resolve()
    assert items[0].raw["data"]["path"] == str(items[0].input) and items[0].simulate["simulate"]["periods"] == 20
    assert items[1].simulate is None and items[1].raw["data"]["path"] == str(trace.resolve())
    assert items[1].raw["fit"]["seed"] == 3 and items[1].config_path == a.config
    # Usage errors stop the batch before anything runs.
    out = tmp_path / "o"
    with pytest.raises(ConfigError, match="names no config"):
        run_batch(None, out, manifest=tmp_path / "m.yaml")
    with pytest.raises(ConfigError, match="without CONFIG"):
        run_batch(CONFIG, out, configs=[str(tmp_path / "c" / "*.yaml")])
    with pytest.raises(ConfigError, match="--configs"):
        run_batch(None, out)
    with pytest.raises(ConfigError, match="needs a CONFIG"):
        run_batch(None, out, inputs=[str(trace)])
    with pytest.raises(InputError, match="no files match"):
        run_batch(None, out, configs=[str(tmp_path / "nothing" / "*.yaml")])
    assert not out.exists()


def test_afmid_batch_has_no_hook_for_a_foreign_worker():
    """Issue 30: the tests' workers run through tests/support/batch_with_worker.py; the shipped command line
    imports no file or module named on it."""
    from afmid.cli import cli

    assert [p.name for p in cli.commands["batch"].params if p.name == "worker"] == []
    assert not hasattr(__import__("afmid.batch.run", fromlist=["run"]), "load_worker")
