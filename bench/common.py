"""Helpers shared by the benchmarks: cached simulated traces, timing, subprocess measurements.

Simulated traces are cached in bench/results/ (git-ignored) together with the
merged config that made them; a cached trace is reused only if that config is
unchanged.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import textwrap
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
RESULTS = BENCH / "results"
CONFIGS = ROOT / "configs"
sys.path.insert(0, str(ROOT))

#: One BLAS/OpenMP thread, as in `afmid batch` workers (and for bit-identical comparisons).
SINGLE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
# The benchmarks run with one BLAS thread (unless the caller sets these): afmid's fit does thousands of small
# matrix products, for which multi-threaded OpenBLAS is slower, and on a shared machine up to 30x slower
# (threads spin waiting for a busy core; see bench/README.md). Must happen before NumPy is imported.
for _key, _value in SINGLE_THREAD.items():
    os.environ.setdefault(_key, _value)


def machine() -> str:
    from bench_simulate import machine as _machine

    return _machine()


def load_average() -> str:
    try:
        return " ".join(f"{v:.1f}" for v in os.getloadavg())
    except OSError:  # pragma: no cover
        return "n/a"


def cached_trace(config: Path, overrides: list[str], name: str) -> Path:
    """An afmid trace file simulated from ``config`` + ``overrides``, cached as bench/results/NAME.trace.h5."""
    import h5py

    from afmid.config import dump_config, load_config
    from afmid.io.trace import write_trace_file
    from afmid.simulate.driver import simulate

    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.trace.h5"
    cfg = load_config(config, overrides)
    text = dump_config(cfg)
    if path.exists():
        try:
            with h5py.File(path, "r") as h5:
                if h5.attrs.get("config") == text:
                    return path
        except OSError:
            pass
    trace = simulate(cfg)
    write_trace_file(path, trace, text, overwrite=True)
    return path


def best_of(fn, repeat: int):
    """(best wall time in s, result of the last call) over ``repeat`` calls."""
    best, result = math.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - start)
    return best, result


def run_python(code: str, env: dict | None = None, timeout: float = 1800, drop: tuple[str, ...] = ()) -> dict:
    """Run ``code`` in a fresh interpreter (cwd = repository root); it must print one JSON object last.

    ``drop``: environment variables to remove (e.g. the BLAS thread limits, to measure the defaults)."""
    full_env = {k: v for k, v in dict(os.environ, **(env or {})).items() if k not in drop}
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          env=full_env, cwd=ROOT, timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"benchmark subprocess failed ({proc.returncode}):\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def wall(args: list[str], env: dict | None = None, timeout: float = 600) -> float:
    """Wall time of a command (s); raises if it fails."""
    start = time.perf_counter()
    proc = subprocess.run(args, capture_output=True, text=True, env=dict(os.environ, **(env or {})), cwd=ROOT,
                          timeout=timeout)
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(map(str, args))} failed ({proc.returncode}):\n{proc.stderr[-4000:]}")
    return elapsed


def timed(args: list[str], env: dict | None = None, timeout: float = 3600) -> tuple[float, float]:
    """(wall time, CPU time of the process and all its waited-for descendants) of a command, s."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    seconds = wall(args, env, timeout)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return seconds, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def machine_busy_seconds() -> float:
    """CPU seconds every process of this machine has used since boot (/proc/stat's ``cpu`` line: user, nice,
    system, irq, softirq and steal ticks); NaN where there is no /proc/stat."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            fields = f.readline().split()
    except OSError:
        return math.nan
    user, nice, system, _idle, _iowait, irq, softirq, steal = (int(v) for v in fields[1:9])
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def measured(args: list[str], env: dict | None = None, timeout: float = 3600, cwd: Path = ROOT,
             ok_codes: tuple[int, ...] = (0,)) -> dict:
    """Wall time (s), CPU time (user + sys, s) and peak resident memory (GB) of one command, and ``others_cores``:
    the cores other processes of the machine kept busy meanwhile, on average (its CPU use over the wall time less
    the command's; NaN without /proc/stat). A wall time is the command's own only when that is near 0.

    The usage is the one ``os.wait4`` returns for the command's process: its own plus that of the descendants it
    waited for (peak RSS: the largest of them), so other benchmarks' processes are not counted. Raises if the
    command's exit code is not in ``ok_codes``; kills it after ``timeout`` s. ``python -m`` puts ``cwd`` first on
    the module path: run another source tree with ``cwd`` set to it."""
    import tempfile
    import threading

    with tempfile.TemporaryFile() as err:
        busy_before = machine_busy_seconds()
        start = time.perf_counter()
        proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=err, env=dict(os.environ, **(env or {})),
                                cwd=cwd)
        killer = threading.Timer(timeout, proc.kill)
        killer.start()
        try:
            _, status, usage = os.wait4(proc.pid, 0)
        finally:
            killer.cancel()
        elapsed = time.perf_counter() - start
        busy = machine_busy_seconds() - busy_before
        proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait for it again
        if proc.returncode not in ok_codes:
            err.seek(0)
            raise RuntimeError(f"{' '.join(map(str, args))} failed ({proc.returncode}):\n"
                               f"{err.read().decode(errors='replace')[-4000:]}")
    cpu = usage.ru_utime + usage.ru_stime
    return {"wall": elapsed, "cpu": cpu, "rss_gb": usage.ru_maxrss * 1024 / 1e9, "code": proc.returncode,
            "others_cores": max(busy - cpu, 0.0) / elapsed if elapsed > 0 else math.nan}


#: The previous release the report rows compare against: the repository's published main before the issue 30/31
#: work (2026-11-25; the project has no release tags). ``AFMID_BENCH_PREVIOUS`` names another commit, ``none`` skips it.
PREVIOUS_RELEASE = "c502dadba00feca3f7391dded19d6d0fcd5fcdad"


def previous_release() -> tuple[str, Path] | None:
    """(commit, source tree) of the previous release, extracted once into bench/results/ by ``git archive``.

    Run it with this environment's Python and ``PYTHONPATH`` set to the tree (its dependencies are this one's);
    None when ``AFMID_BENCH_PREVIOUS=none``."""
    commit = os.environ.get("AFMID_BENCH_PREVIOUS", PREVIOUS_RELEASE)
    if commit.lower() == "none":
        return None
    commit = subprocess.run(["git", "rev-parse", "--verify", f"{commit}^{{commit}}"], capture_output=True, text=True,
                            cwd=ROOT, check=True).stdout.strip()
    tree = RESULTS / f"previous-{commit[:12]}"
    if not (tree / "afmid" / "cli.py").exists():
        partial = RESULTS / f"previous-{commit[:12]}.partial"
        partial.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "archive", commit, "afmid"], capture_output=True, cwd=ROOT, check=True)
        subprocess.run(["tar", "-x", "-C", str(partial)], input=archive.stdout, check=True)
        partial.rename(tree)
    return commit, tree


def median(values) -> float:
    return float(statistics.median(values))


def h5_content(path: Path, volatile: set[str] = frozenset({"created", "batch_key"})) -> dict:
    """Every dataset and attribute of an HDF5 file as comparable bytes (root attributes minus ``volatile``)."""
    import h5py
    import numpy as np

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
        out["/@"] = {k: norm(h5.attrs[k]) for k in h5.attrs if k not in volatile}
    return out


def differing(a: Path, b: Path) -> list[str]:
    """Datasets/attribute sets that differ between two afmid files (ignoring creation time and batch key)."""
    ca, cb = h5_content(a), h5_content(b)
    return sorted(set(ca) ^ set(cb)) + [k for k in ca if k in cb and ca[k] != cb[k]]


def row(name: str, afmid_s: float | None, reference_s: float | None, ratio: float | None, target: str,
        met: bool | None, notes: str, **extra) -> dict:
    """A table row (see run_all.py)."""
    return {"name": name, "afmid_s": afmid_s, "reference_s": reference_s, "ratio": ratio, "target": target,
            "met": met, "notes": notes, **extra}


def met_word(met: bool | None) -> str:
    """A row's verdict on its target: 'met', 'missed', or '-' for a row without one."""
    return "met" if met else "missed" if met is False else "-"


def bench_main(doc: str, run, quick_help: str, describe=None) -> None:
    """A benchmark file's command line: ``--quick`` (``quick_help``: what it leaves out), then the machine and each
    row of ``run(quick)``, as ``describe(row)`` or by default ``name: afmid_s s (met)`` with the notes below."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=quick_help)
    args = parser.parse_args()
    rows = run(args.quick)
    print(f"machine: {machine()}")
    for r in rows:
        print(describe(r) if describe else f"{r['name']}: {r['afmid_s']:.2f} s ({met_word(r['met'])})\n  {r['notes']}")
