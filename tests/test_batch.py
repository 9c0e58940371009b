"""``afmid batch``: parallel fits equal single runs, resuming, bad traces, interruption, worker crashes.

Behaviour only (timing is in bench/bench_batch.py). One short DMT trace is
simulated per module; the other traces are copies with fresh detector noise,
so every input has its own bytes and its own result. Workers are spawned
processes (about 2 s each to start and load numba's cache), so the batches
here are small.
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

from afmid.batch import (RUN_SUFFIX, assign_names, batch_key, read_manifest, read_run_row, run_batch, Entry)
from afmid.errors import ConfigError, InputError

ROOT = Path(__file__).resolve().parents[1]
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
    from afmid.io import write_trace_file
    from afmid.simulate import simulate

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
    env = dict(os.environ, **SINGLE_THREAD)
    args = AFMID + ["-q", "fit", str(CONFIG), "--set", f"data.path={trace}", "-o", str(output)]
    for o in FAST + list(extra):
        args += ["--set", o]
    subprocess.run(args, check=True, env=env, cwd=ROOT, timeout=120)


# --------------------------------------------------------------------------- results
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
    for column in ("cv_error [1]", "separation [m]", "E_star [Pa]", "E_star_error [Pa]", "E_star_ci_low [Pa]",
                   "hamaker [J]", "adhesion_force [N]", "fit_time [s]", "status", "error"):
        assert column in header, column
    ok = rows[1]
    run = read_run_row(out / "n01.run.h5")
    assert float(ok["E_star [Pa]"]) == run["quantities"]["E_star"]["value"]
    assert float(ok["cv_error [1]"]) == run["values"]["cv_error"]
    assert 1e9 < float(ok["E_star [Pa]"]) < 3e9  # truth 2 GPa
    assert "not a readable HDF5 file" in rows[0]["error"] and rows[0]["run_file"] == ""
    with h5py.File(out / "summary.h5", "r") as h5:
        assert h5.attrs["format"] == "afmid-batch-summary"
        assert [s.decode() for s in h5["status"][...]] == ["failed", "ok"]
        assert h5["parameters/E_star/value"].attrs["units"] == "Pa"
        assert h5["parameters/E_star/error"].attrs["units"] == "Pa"
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
        assert a["E_star [Pa]"] == b["E_star [Pa]"] and a["cv_error [1]"] == b["cv_error [1]"]

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
    assert rows["empty"]["status"] == "failed" and "empty.h5" in rows["empty"]["error"]
    assert rows["missing"]["status"] == "failed" and "not found" in rows["missing"]["error"]
    assert rows["n02"]["status"] == "failed" and "quality_factor" in rows["n02"]["error"]
    with h5py.File(out / "n02_q300.run.h5", "r") as h5:
        assert "quality_factor: 300" in h5.attrs["config"]
    assert not (out / "n02.run.h5").exists() and not _leftovers(out)


def test_a_worker_that_dies_fails_only_its_trace(traces, tmp_path, monkeypatch):
    _copy(traces, tmp_path / "in", ["n01.h5", "n02.h5", "n03.h5"])
    monkeypatch.setenv("_AFMID_BATCH_TEST_CRASH", "n02")  # that worker SIGKILLs itself
    out = tmp_path / "out"
    result = run_batch(CONFIG, out, inputs=[str(tmp_path / "in" / "*.h5")], jobs=2, overrides=FAST)
    status = {r.item.name: (r.status, r.error) for r in result.rows}
    assert status["n01"][0] == "ok" and status["n03"][0] == "ok"
    assert status["n02"][0] == "failed" and "worker process died" in status["n02"][1]
    assert not _leftovers(out)
    assert [r["status"] for r in _summary(out)] == ["ok", "failed", "ok"]


def test_interrupted_batch_leaves_whole_files_and_a_valid_summary(traces, tmp_path):
    names = ["n01.h5", "n02.h5", "n03.h5", "n04.h5", "n05.h5"]
    _copy(traces, tmp_path / "in", names)
    out = tmp_path / "out"
    args = AFMID + ["-q", "batch", str(CONFIG), "--inputs", str(tmp_path / "in" / "*.h5"), "-o", str(out), "-j",
                    "2", "--set", FAST[0]]
    env = dict(os.environ, _AFMID_BATCH_TEST_DELAY="1.5")  # every fit takes > 1.5 s: Ctrl-C lands mid-fit
    proc = subprocess.Popen(args, env=env, cwd=ROOT, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while not list(out.glob(f"*{RUN_SUFFIX}")) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert list(out.glob(f"*{RUN_SUFFIX}")), "no trace finished within 60 s"
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C in a terminal: the whole process group
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert "interrupted" in err
    assert not _leftovers(out)
    finished = sorted(p.name for p in out.glob(f"*{RUN_SUFFIX}"))
    rows = _summary(out)
    assert 1 <= len(finished) < len(names)
    assert sorted(r["run_file"] for r in rows) == finished and all(r["status"] == "ok" for r in rows)
    for name in finished:
        read_run_row(out / name)  # whole, readable run files

    again = run_batch(CONFIG, out, inputs=[str(tmp_path / "in" / "*.h5")], jobs=2, overrides=FAST)
    status = {r.item.output.name: r.status for r in again.rows}
    assert all(status[n] == "skipped" for n in finished)
    assert sorted(status.values()).count("ok") == len(names) - len(finished)


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
