"""Benchmark: fit time and peak memory against trace length (1e4 ... 1e7 samples).

Trace: the DMT model of configs/dmt.yaml (thermal + 1 pm detector noise),
simulated once in steady state for 5,000 periods at exactly 200 samples per
period (1e6 samples); the shorter traces are its first 50 and 500 periods, the
1e7 trace is it tiled 10 times (whole periods, so the joins are seamless up to
the thermal wander between the end and the start). Trace files hold the
deflection only (no ground truth), as a measured trace would.

Each size is fitted in a fresh process (``run_fit`` with ``sample.separation``
given, ``fit.bootstrap`` = 10, everything else default; one BLAS thread, see
bench/README.md; the fit shares a long trace's chunks among two threads of its
own, each calling one-thread BLAS (afmid.threads.trace_threads); extra rows repeat
1e7 with one such thread and 1e5 with the default BLAS thread count), after a warm-up fit of the 1e4 trace in the
same process (JIT warm). Reported: wall time and CPU time of the fit (including
loading the file; on a shared machine the CPU time is the one to compare), and
the process's peak resident memory (``ru_maxrss``, what ``/usr/bin/time -v``
calls maximum resident set size).

``--profile`` prints a cProfile (CPU time) of the 1e7 fit; ``--memory`` the
peak resident memory, wall, CPU and system time and minor page faults at each
stage boundary of the 1e7 fit (Linux: the peak is reset between stages through
/proc/self/clear_refs).

Run: python bench/bench_scaling.py [--quick] [--profile] [--memory]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import CONFIGS, RESULTS, ROOT as ROOT_DIR, cached_trace, machine, row, run_python  # noqa: E402

CONFIG = CONFIGS / "dmt.yaml"
PERIODS = 5000
SAMPLES_PER_PERIOD = 200
FIT = ["fit.bootstrap=10"]
SIZES = [10_000, 100_000, 1_000_000, 10_000_000]
TARGET_S, TARGET_GB = 10.0, 1.5


def traces(sizes: list[int]) -> dict[int, Path]:
    """Trace files of each size (cached in bench/results/)."""
    import h5py
    import numpy as np

    from afmid.config import dump_config, load_config
    from afmid.io.trace import load_trace, write_trace_file

    base = cached_trace(CONFIG, [f"simulate.periods={PERIODS}"], f"dmt_{PERIODS}periods")
    cfg = load_config(CONFIG, [f"data.path={base}"])
    out = {}
    with h5py.File(base, "r") as h5:
        sha = h5.attrs.get("created")
    for n in sizes:
        path = RESULTS / f"scaling_{n:.0e}.trace.h5".replace("+", "")
        if path.exists():
            with h5py.File(path, "r") as h5:
                if h5.attrs.get("source_created") == sha:
                    out[n] = path
                    continue
        trace = load_trace(cfg)
        x = trace.deflection
        reps = -(-n // x.size)
        trace.deflection = np.tile(x, reps)[:n]
        trace.truth = None
        trace.time = None
        write_trace_file(path, trace, dump_config(cfg), overwrite=True)
        with h5py.File(path, "r+") as h5:
            h5.attrs["source_created"] = sha
        out[n] = path
    return out


FIT_CODE = """
import json, resource, sys, time
sys.path.insert(0, {root!r})
from afmid.config import load_config
from afmid.fit.pipeline import run_fit
def cfg(path):
    return load_config({config!r}, ["data.path=" + path] + {fit!r})
run_fit(cfg({warm!r}))  # JIT warm, imports
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
c0, t0 = time.process_time(), time.perf_counter()
result = run_fit(cfg({path!r}))
seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({{"seconds": seconds, "cpu": cpu, "peak_kb": peak, "warm_peak_kb": before,
                  "summary": result.summary_line()}}))
"""

PROFILE_CODE = """
import cProfile, pstats, sys, time
sys.path.insert(0, {root!r})
from afmid.config import load_config
from afmid.fit.pipeline import run_fit
def cfg(path):
    return load_config({config!r}, ["data.path=" + path] + {fit!r})
run_fit(cfg({warm!r}))
prof = cProfile.Profile(time.process_time)  # CPU time: the machine may be shared
prof.enable()
run_fit(cfg({path!r}))
prof.disable()
pstats.Stats(prof).sort_stats("cumulative").print_stats(45)
pstats.Stats(prof).sort_stats("tottime").print_stats(25)
print("{{}}")
"""


STAGES_CODE = """
import functools, json, sys, time
sys.path.insert(0, {root!r})
import resource
import afmid.io.defects, afmid.fit.pipeline as F, afmid.fit.prepare as P, afmid.fit.regression
from afmid.config import load_config
def cfg(path):
    return load_config({config!r}, ["data.path=" + path] + {fit!r})
F.run_fit(cfg({warm!r}))
def gb(key):
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith(key)) / 1024**2
def reset():  # VmHWM := VmRSS
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")
events, depth = [], [0]
def mark(label):
    usage = resource.getrusage(resource.RUSAGE_SELF)
    events.append((label, depth[0], gb("VmHWM:"), gb("VmRSS:"), time.process_time(), usage.ru_stime,
                   usage.ru_minflt, time.perf_counter()))
    reset()
def wrap(module, name):
    fn = getattr(module, name)
    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        mark("> " + name)
        depth[0] += 1
        try:
            return fn(*args, **kwargs)
        finally:
            depth[0] -= 1
            mark("< " + name)
    setattr(module, name, wrapped)
for name in ("load_trace", "prepare", "estimate_nonlinear", "build_system", "settle_drive_frequency",
             "with_regressor_noise", "force_cv_error", "per_sample_forces", "statistical_share", "selection_share",
             "period_curves"):
    wrap(F, name)
for name in ("estimate_drive", "ou_smooth"):  # looked up in afmid.fit.prepare
    wrap(P, name)
wrap(afmid.io.defects, "analyse_with")
wrap(F.regression, "select")
wrap(F.regression, "bag")
reset()
mark("start")
F.run_fit(cfg({path!r}))
mark("end")
print(json.dumps(events))
"""


def stages(path: Path, warm: Path) -> str:
    """Peak RSS (since the previous event) and CPU time at every stage boundary of one fit (Linux only)."""
    code = STAGES_CODE.format(root=str(ROOT_DIR), config=str(CONFIG), fit=FIT, warm=str(warm), path=str(path))
    events = run_python(code)
    t0, s0, f0, w0 = events[0][4], events[0][5], events[0][6], events[0][7]
    lines = [f"{'wall s':>7s}  {'CPU s':>7s}  {'sys s':>6s}  {'faults':>8s}  {'peak GB':>7s}  {'RSS GB':>6s}  "
             "stage (peak RSS since the line above; CPU includes sys, the kernel's time, mostly page faults)"]
    for label, depth, hwm, rss, cpu, sys_s, faults, wall in events:
        indent = "  " * depth
        lines.append(f"{wall - w0:7.2f}  {cpu - t0:7.2f}  {sys_s - s0:6.2f}  {faults - f0:8d}  {hwm:7.3f}  {rss:6.3f}  "
                     f"{indent}{label}")
    lines.append(f"peak {max(e[2] for e in events):.3f} GB")
    return "\n".join(lines)


def measure(path: Path, warm: Path, env: dict | None = None, default_threads: bool = False) -> dict:
    from common import ROOT, SINGLE_THREAD

    code = FIT_CODE.format(root=str(ROOT), config=str(CONFIG), fit=FIT, warm=str(warm), path=str(path))
    return run_python(code, env=env, drop=tuple(SINGLE_THREAD) if default_threads else ())


def profile(path: Path, warm: Path) -> str:
    import subprocess
    import textwrap

    from common import ROOT

    code = PROFILE_CODE.format(root=str(ROOT), config=str(CONFIG), fit=FIT, warm=str(warm), path=str(path))
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, cwd=ROOT)
    return proc.stdout


def run(quick: bool = False) -> list[dict]:
    sizes = SIZES[:2] if quick else SIZES
    files = traces(sizes)
    warm = files[sizes[0]]
    rows = []
    previous = None
    for n in sizes:
        got = measure(files[n], warm)
        gb = got["peak_kb"] / 1024**2
        ratio = got["seconds"] / previous if previous else None
        is_top = n == SIZES[-1]
        rows.append(row(
            f"fit scaling: {n:.0e} samples ({n // SAMPLES_PER_PERIOD} periods), bootstrap 10",
            got["seconds"], None, ratio,
            f"< {TARGET_S:g} s and < {TARGET_GB:g} GB; linear (ratio to the previous size 10x)" if is_top else
            "linear (ratio to the previous size ~10x)",
            (got["seconds"] < TARGET_S and gb < TARGET_GB) if is_top else None,
            f"peak RSS {gb:.2f} GB (after warm-up {got['warm_peak_kb'] / 1024**2:.2f} GB); CPU {got['cpu']:.1f} s; "
            f"{got['summary']}",
            peak_gb=gb, cpu_s=got["cpu"],
        ))
        previous = got["seconds"]
    if not quick:  # the 1e7 fit with afmid's chunks on one thread (the rows above share them among two)
        n = SIZES[-1]
        got = measure(files[n], warm, env={"AFMID_TRACE_THREADS": "1"})
        two = rows[-1]
        rows.append(row(
            f"fit scaling: {n:.0e} samples with one thread for the chunks (vs two above)", got["seconds"],
            two["afmid_s"], two["afmid_s"] / got["seconds"], "report only", None,
            f"'reference' = the two-thread time; AFMID_TRACE_THREADS=1; peak RSS {got['peak_kb'] / 1024**2:.2f} GB; "
            f"CPU {got['cpu']:.1f} s (two threads: {two['cpu_s']:.1f} s)",
            peak_gb=got["peak_kb"] / 1024**2, cpu_s=got["cpu"],
        ))
    if not quick:  # the same 1e5 fit with the BLAS threads the environment gives by default (all cores)
        n = SIZES[1]
        got = measure(files[n], warm, default_threads=True)
        single = rows[1]["afmid_s"]
        rows.append(row(
            f"fit scaling: {n:.0e} samples with default BLAS threads (vs one thread above)", got["seconds"], single,
            single / got["seconds"], "report only", None,
            f"'reference' = the one-thread time; CPU {got['cpu']:.1f} s; OpenBLAS with {os.cpu_count()} threads on "
            "a shared machine: thousands of small matrix products spin-wait for a busy core",
            cpu_s=got["cpu"],
        ))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1e4 and 1e5 samples only")
    parser.add_argument("--profile", action="store_true", help="cProfile the fit of the largest trace")
    parser.add_argument("--memory", action="store_true", help="peak RSS and CPU time per stage of the largest fit")
    parser.add_argument("--threads1", action="store_true", help="also time the largest trace with one BLAS thread")
    args = parser.parse_args()
    sizes = SIZES[:2] if args.quick else SIZES
    if args.profile or args.memory:
        files = traces(sizes)
        if args.memory:
            print(stages(files[sizes[-1]], files[sizes[0]]))
        if args.profile:
            print(profile(files[sizes[-1]], files[sizes[0]]))
        return
    rows = run(args.quick)
    print(f"machine: {machine()}")
    for r in rows:
        ratio = f"{r['ratio']:.1f}x" if r["ratio"] else "-"
        peak = f"{r['peak_gb']:5.2f} GB" if "peak_gb" in r else " " * 8
        print(f"{r['name']:60s} {r['afmid_s']:8.2f} s  CPU {r['cpu_s']:7.2f} s  {peak}  {ratio:>6s}  {r['notes']}")
    if args.threads1:
        from common import SINGLE_THREAD

        files = traces(sizes)
        got = measure(files[sizes[-1]], files[sizes[0]], env=SINGLE_THREAD)
        print(f"one BLAS thread: {json.dumps(got)}")


if __name__ == "__main__":
    main()
