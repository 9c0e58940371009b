"""Benchmark: start-up costs of the command line.

1. ``afmid --help``: wall time of the command in a fresh process (median of 7).
2. The first ``afmid fit`` in a new process with numba's on-disk cache warm,
   against the same fit (``run_fit`` + ``write_run``) run a second time inside one
   process (everything imported, kernels loaded): the difference is what a new
   process adds (interpreter, imports, loading the cached kernels).
3. The first-ever fit of a fresh install (issue 31's target: <= 5 s): the install's warm step
   (``python -m afmid.fit.warm``, which ``make venv`` runs: the library-independent kernels, then the default
   model's generated ones) into an empty ``NUMBA_CACHE_DIR``, then the fit ([dmt], the default model): nothing
   compiles in it.
4. The first-ever fit with no warm step (``pip install`` alone): the same command with
   ``NUMBA_CACHE_DIR`` pointing at an empty folder, so every kernel compiles in the fit (kernels with a
   same-bits twin run the twin instead, afmid.kernels.twin). The generated kernels' folder
   (``AFMID_KERNEL_DIR``, afmid.kernels.lawgen) is set inside the empty folder in both.

Workload: the demo's trace (afmid/templates/demo_ldpe.yaml: 50 periods x 200 samples, DMT + hidden
Kelvin-Voigt), fitted with [dmt] as ``make demo``'s first fit (defaults: 100 bootstrap resamples). One BLAS
thread.

Run: python bench/bench_coldstart.py [--quick]
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import ROOT, SINGLE_THREAD, bench_main, cached_trace, median, row, run_python, timed, wall  # noqa: E402

CONFIG = ROOT / "afmid" / "templates" / "demo_ldpe.yaml"
AFMID = [sys.executable, "-m", "afmid.cli"]  # what the `afmid` script runs, without depending on PATH
HELP_TARGET, FIRST_FIT_TARGET, FIRST_EVER_TARGET = 0.5, 2.0, 5.0

WARM_CODE = """
import json, sys, time
from afmid.config import load_config
from afmid.fit.pipeline import run_fit
from afmid.runfile import run_data, write_run
cfg = load_config({config!r}, ["data.path={trace}"])
def once():
    result = run_fit(cfg)
    write_run({out!r}, run_data(result, cfg), overwrite=True)
start = time.perf_counter(); once(); first = time.perf_counter() - start
best, best_cpu = float("inf"), float("inf")
for _ in range({repeat}):
    start, c0 = time.perf_counter(), time.process_time(); once()
    best, best_cpu = min(best, time.perf_counter() - start), min(best_cpu, time.process_time() - c0)
print(json.dumps({{"first_in_process": first, "warm": best, "warm_cpu": best_cpu}}))
"""


def run(quick: bool = False) -> list[dict]:
    trace = cached_trace(CONFIG, [], "demo_ldpe")
    env = dict(SINGLE_THREAD)
    with tempfile.TemporaryDirectory(prefix="afmid-bench-") as tmp:
        out = Path(tmp) / "run.h5"
        fit_cmd = AFMID + ["-q", "fit", str(CONFIG), "--set", f"data.path={trace}", "-o", str(out), "--overwrite"]
        helps = [wall(AFMID + ["--help"], env) for _ in range(3 if quick else 7)]
        wall(fit_cmd, env)  # make sure numba's cache is warm
        firsts_cpu = [timed(fit_cmd, env) for _ in range(2 if quick else 5)]
        firsts = [w for w, _ in firsts_cpu]
        warm = run_python(WARM_CODE.format(config=str(CONFIG), trace=trace, out=str(out), repeat=2 if quick else 5),
                          env)
        with tempfile.TemporaryDirectory(prefix="afmid-numba-cache-") as cache:
            empty = dict(env, NUMBA_CACHE_DIR=cache, AFMID_KERNEL_DIR=str(Path(cache) / "afmid_kernels"))
            cold, cold_cpu = timed(fit_cmd, empty)
            cold_again = wall(fit_cmd, empty)  # the cache that run filled
        with tempfile.TemporaryDirectory(prefix="afmid-numba-cache-") as cache:
            empty = dict(env, NUMBA_CACHE_DIR=cache, AFMID_KERNEL_DIR=str(Path(cache) / "afmid_kernels"))
            warm_step, warm_step_cpu = timed([sys.executable, "-m", "afmid.fit.warm"], empty)
            after_warm, after_warm_cpu = timed(fit_cmd, empty)
    help_s = median(helps)
    first_s = median(firsts)
    extra = first_s - warm["warm"]
    return [
        row("cold start: afmid --help (fresh process)", help_s, None, None, f"< {HELP_TARGET} s",
            help_s < HELP_TARGET, f"median of {len(helps)}: " + ", ".join(f"{h:.2f}" for h in helps) + " s"),
        row("cold start: first afmid fit in a new process (numba cache warm) vs warm in-process fit",
            first_s, warm["warm"], extra, f"adds < {FIRST_FIT_TARGET} s", extra < FIRST_FIT_TARGET,
            f"'ratio' column = seconds added by a new process ({extra:.2f} s); command median of {len(firsts)} "
            f"({', '.join(f'{f:.2f}' for f in firsts)} s); warm fit + write in one process {warm['warm']:.2f} s "
            f"(its own first call {warm['first_in_process']:.2f} s); CPU: command {median([c for _, c in firsts_cpu]):.2f} s, "
            f"warm fit + write {warm['warm_cpu']:.2f} s; 10,000 samples, bootstrap 100"),
        row("cold start: first-ever afmid fit of a fresh install (`make venv`: the warm step, then the fit)",
            after_warm, cold, cold / after_warm if after_warm else None, f"<= {FIRST_EVER_TARGET} s",
            after_warm <= FIRST_EVER_TARGET,
            f"'reference' = the same fit with no warm step, 'ratio' = that / this; CPU {after_warm_cpu:.2f} s; the "
            f"install's warm step (python -m afmid.fit.warm) itself {warm_step:.2f} s (CPU {warm_step_cpu:.2f} s); "
            f"compiled in the fit: none (the default model's generated kernels are warmed)"),
        row("cold start: first-ever afmid fit with no warm step (pip install alone: empty numba cache)", cold,
            warm["warm"], cold - warm["warm"], "report only", None,
            f"'ratio' column = seconds added to the warm in-process fit ({cold - warm['warm']:.1f} s); CPU "
            f"{cold_cpu:.2f} s; the next run with that cache {cold_again:.2f} s"),
    ]


def main() -> None:
    bench_main(__doc__, run, "fewer repetitions")


if __name__ == "__main__":
    main()
