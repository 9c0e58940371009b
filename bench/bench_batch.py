"""Benchmark: ``afmid batch`` over 1,000 traces of 10,000 samples on 2 worker processes.

Traces: 20 distinct DMT traces are simulated (configs/dmt.yaml, 50 periods at
200 samples per period, E* from 1.5 to 3.4 GPa and a different noise seed
each; cached in bench/results/), then each is written 50 times with fresh white
detector noise (1 pm rms, seed per copy) added to its deflection: 1,000 trace
files (deflection only, like measured data) with distinct bytes and results.

Timed: ``afmid -q batch configs/dmt.yaml --inputs '...*.h5' -j 2 -o DIR``
end to end (process start to exit, a fresh DIR). Reference: the same work as a
shell loop of ``afmid fit`` (one process per trace), estimated from 5 such runs.
Per-trace breakdown from the summary's load/fit/write columns. Identity: 3
traces are fitted alone with ``afmid fit`` (one BLAS thread, as the workers)
and their run files compared with the batch's, dataset by dataset and attribute
by attribute (creation time and the batch key excepted).

Run: python bench/bench_batch.py [--quick]   (quick: 40 traces)
"""

from __future__ import annotations

import csv
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (CONFIGS, RESULTS, SINGLE_THREAD, bench_main, cached_trace, differing, load_average,  # noqa: E402
                    median, met_word, row, timed, wall)

CONFIG = CONFIGS / "dmt.yaml"
AFMID = [sys.executable, "-m", "afmid.cli"]
TARGET_S = 60.0


def make_traces(n_distinct: int, copies: int) -> Path:
    """bench/results/batch_<n>/ with n_distinct * copies trace files (cached)."""
    import numpy as np

    from afmid.config import dump_config, load_config
    from afmid.io.trace import load_trace, write_trace_file

    folder = RESULTS / f"batch_{n_distinct * copies}"
    marker = folder / ".complete"
    spec = f"{n_distinct} x {copies} v1"
    if marker.exists() and marker.read_text() == spec:
        return folder
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for i in range(n_distinct):
        overrides = [f"simulate.parameters.E_star={1.5e9 + 0.1e9 * i}", f"simulate.seed={100 + i}"]
        base = cached_trace(CONFIG, overrides, f"batch_base_{i:02d}")
        cfg = load_config(CONFIG, [f"data.path={base}"])
        trace = load_trace(cfg)
        x = trace.deflection.copy()
        trace.truth = None
        text = dump_config(cfg)
        for j in range(copies):
            noise = np.random.default_rng(1000 * i + j).normal(0.0, 1e-12, x.size)
            trace.deflection = x + noise
            write_trace_file(folder / f"t{i:02d}_{j:02d}.h5", trace, text, overwrite=True)
    marker.write_text(spec)
    return folder


def _summary(out: Path) -> list[dict]:
    with open(out / "summary.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def run(quick: bool = False) -> list[dict]:
    n_distinct, copies = (2, 20) if quick else (20, 50)
    folder = make_traces(n_distinct, copies)
    n = n_distinct * copies
    out = RESULTS / "batch_out"
    shutil.rmtree(out, ignore_errors=True)
    cmd = AFMID + ["-q", "batch", str(CONFIG), "--inputs", str(folder / "*.h5"), "-j", "2", "-o", str(out)]
    load_before = load_average()
    seconds, cpu = timed(cmd, timeout=3600)
    rows = _summary(out)
    statuses = statistics.multimode([r["status"] for r in rows])
    fitted_now = ("ok", "model-limited")  # a run file written by this batch (model-limited: flagged, still timed)
    n_ok = sum(r["status"] in fitted_now for r in rows)

    def mean(col):
        return statistics.fmean(float(r[col]) for r in rows if r["status"] in fitted_now)

    load, fit, write = mean("load_time_s"), mean("fit_time_s"), mean("write_time_s")
    cpu_trace = mean("cpu_time_s")
    per_trace = load + fit + write
    overhead = seconds - n * per_trace / 2
    # Reference: one `afmid fit` process per trace.
    files = sorted(folder.glob("*.h5"))
    with tempfile.TemporaryDirectory(prefix="afmid-bench-") as tmp:
        loop = [wall(AFMID + ["-q", "fit", str(CONFIG), "--set", f"data.path={f}", "-o", str(Path(tmp) / "r.h5"),
                              "--overwrite"], SINGLE_THREAD) for f in files[:5]]
        # Bit-identity with single runs (one BLAS thread, as the workers).
        mismatches = []
        for f in (files[0], files[len(files) // 2], files[-1]):
            single = Path(tmp) / f"{f.stem}.single.h5"
            wall(AFMID + ["-q", "fit", str(CONFIG), "--set", f"data.path={f}", "-o", str(single)], SINGLE_THREAD)
            diff = differing(single, out / f"{f.stem}.run.h5")
            if diff:
                mismatches.append(f"{f.stem}: {diff[:5]}")
    loop_estimate = median(loop) * n
    identical = not mismatches
    return [row(
        f"batch: {n} traces x 10,000 samples, afmid batch -j 2",
        seconds, loop_estimate, loop_estimate / seconds,
        f"< {TARGET_S:g} s end to end (1,000 traces); identical to single runs" if not quick else "smoke run",
        (seconds < TARGET_S and identical and n_ok == n) if not quick else None,
        (f"{n_ok}/{n} ok (status {statuses}); per trace in a worker: load {load * 1e3:.0f} ms + fit {fit * 1e3:.0f} ms "
         f"+ write {write * 1e3:.0f} ms = {per_trace:.2f} s, i.e. {n * per_trace / 2:.0f} s on 2 workers; the rest "
         f"({overhead:.0f} s) is start-up, scheduling and summaries. CPU: {cpu_trace * 1e3:.0f} ms per trace in the "
         f"worker, {cpu:.0f} s for the whole batch (all processes), i.e. >= {cpu / 2:.0f} s on 2 idle cores; load "
         f"average before {load_before}, after {load_average()}. Reference = {n} x `afmid fit` processes "
         f"(median {median(loop):.2f} s each). Run files identical to single runs (3 checked): "
         f"{'yes' if identical else 'NO: ' + '; '.join(mismatches)}"),
        per_trace_s=per_trace,
    )]


def main() -> None:
    bench_main(__doc__, run, "40 traces instead of 1,000",
               lambda r: f"{r['name']}: {r['afmid_s']:.1f} s ({met_word(r['met'])})\n  {r['notes']}")


if __name__ == "__main__":
    main()
