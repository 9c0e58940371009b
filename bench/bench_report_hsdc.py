"""Benchmark: ``afmid report`` of the real Bruker HSDC record (issue 29, item 4): CPU and peak memory.

Workload: the Bruker NanoScope high-speed data capture of docs/lab/2026-11-29-hsdc-real-record.md (524,288 samples
at 50 MHz, 596 periods of 56.856 kHz), not in the repository: ``$AFMID_BENCH_HSDC``, else
../shared/data/bruker-hsdc/HSDC.hsdc beside the repository; absent, the benchmark gives one row saying so. The lab
note's calibration A (k 2.8 N/m, f0 57 kHz, Q 150, R 8 nm, invols 60 nm/V), ``model.effects: [dmt]``, the
separation estimated. Each command in a fresh process, one BLAS thread, the diagnosis cache off (every report
diagnoses its runs); CPU (user + sys), wall and peak RSS of each process tree (bench/common.py ``measured``):

1. ``afmid fit`` of the whole record and of its halves (``data.stop`` / ``data.start`` 5.24288e-3 s);
2. ``afmid report whole.h5``;
3. ``afmid report half1.h5 half2.h5`` (both diagnosed).

Targets (issue 29, item 4, on 2 cores): one-run report <= 60 s, two-run <= 90 s, peak RSS <= 2 GB. The rows judge
the wall time on the 2 cores (the report draws its figures in a forked child beside the diagnosis, and a second
forked child shares the diagnosis's independent searches, afmid/diagnosis/forked_work.py), but only when the
machine was otherwise quiet: when other processes kept more than QUIET_CORES of a core busy on average meanwhile
(bench/common.py ``measured``'s ``others_cores``), the wall time is theirs too and the row is not judged (its notes
give the CPU time, which does not depend on the load). Memory: ``os.wait4``'s peak RSS is the largest single
process's; with forked children sharing the parent's pages, the report's footprint is the summed PSS (proportional
set size: shared pages split among the processes) of its process tree, sampled every 0.5 s from /proc (Linux; the
notes give both). --quick: the fits only.

Run: python bench/bench_report_hsdc.py [--quick]
"""

from __future__ import annotations

import os
import sys
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_report import AFMID, described  # noqa: E402
from common import ROOT, SINGLE_THREAD, bench_main, measured, met_word, row  # noqa: E402

ONE_RUN_TARGET_S, TWO_RUN_TARGET_S, RSS_TARGET_GB = 60.0, 90.0, 2.0
#: Cores other processes may keep busy, on average, while a report is timed, for its wall time to be judged.
QUIET_CORES = 0.25
#: The middle of the record, s: its halves' boundary (2^18 samples at 50 MHz).
HALF = 5.24288e-3


def record_path() -> Path:
    return Path(os.environ.get("AFMID_BENCH_HSDC") or ROOT.parent / "shared" / "data" / "bruker-hsdc" / "HSDC.hsdc")


def calibration_a(record: Path) -> str:
    """The run config of the lab note's calibration A for ``record`` (what `afmid init-config --from` writes, the
    calibration filled in)."""
    return f"""data:
  path: {record}
  format: hsdc
  column: Vertical Deflection
  sample_rate: 5.0e+07
  units: V
  invols: 60.0e-9
  positive: toward_sample
cantilever:
  spring_constant: 2.8
  resonance_frequency: 57.0e+3
  quality_factor: 150
  tip_radius: 8.0e-9
drive:
  frequency: 56856.09
sample:
  a0: 0.165e-9
  medium: air
model:
  effects: [dmt]
fit: {{}}
"""


@contextmanager
def peak_summed_pss(marker: str):
    """Yield a dict whose ``gb`` is, after the block, the largest summed PSS (GB) seen of the processes whose command
    line holds ``marker`` (a report's output folder: its forked children carry the parent's command line), sampled
    every 0.5 s; NaN where /proc has no smaps_rollup."""
    seen = {"gb": float("nan")}
    stop = threading.Event()

    def sample() -> None:
        peak = None
        while not stop.wait(0.5):
            total, found = 0, False
            for pid in filter(str.isdigit, os.listdir("/proc")):
                try:
                    with open(f"/proc/{pid}/cmdline", "rb") as f:
                        if marker.encode() not in f.read():
                            continue
                    with open(f"/proc/{pid}/smaps_rollup") as f:
                        total += sum(int(line.split()[1]) for line in f if line.startswith("Pss:"))
                    found = True
                except OSError:  # gone, or no smaps_rollup
                    continue
            if found:
                peak = max(peak or 0, total)
        if peak is not None:
            seen["gb"] = peak * 1024 / 1e9

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        yield seen
    finally:
        stop.set()
        sampler.join()


def quiet(measurement: dict) -> bool:
    """Whether the machine was otherwise quiet while ``measurement`` ran: other processes kept at most QUIET_CORES
    busy on average (False when unknown)."""
    return measurement["others_cores"] <= QUIET_CORES


def wall_met(measurement: dict, target_s: float) -> bool | None:
    """Whether ``measurement``'s wall time meets ``target_s``; None (not judged) when the machine was not quiet."""
    return measurement["wall"] <= target_s if quiet(measurement) else None


def timed(measurement: dict) -> str:
    """The row's notes: wall, CPU and memory, and the other processes' load meanwhile."""
    judged = ("" if quiet(measurement)
              else f"; not judged: other processes kept {measurement['others_cores']:.2f} cores busy meanwhile")
    return f"{described(measurement)}, others {measurement['others_cores']:.2f} cores{judged}"


def run(quick: bool = False) -> list[dict]:
    record = record_path()
    if not record.is_file():
        return [row(f"report HSDC record: skipped, {record} not found (set AFMID_BENCH_HSDC to the Bruker record)",
                    None, None, None, "", None, "")]
    with tempfile.TemporaryDirectory(prefix="afmid-bench-hsdc-") as tmp:
        tmp = Path(tmp)
        config = tmp / "hsdc_a.yaml"
        config.write_text(calibration_a(record), encoding="utf-8")
        env = dict(SINGLE_THREAD, AFMID_DIAGNOSIS_CACHE="off")
        runs = {"whole": [], "half1": ["--set", f"data.stop={HALF}"], "half2": ["--set", f"data.start={HALF}"]}
        fits = {name: measured(AFMID + ["fit", str(config), *sets, "-o", str(tmp / f"{name}.h5")], env)
                for name, sets in runs.items()}
        fit_notes = "; ".join(f"{name} {described(m)}" for name, m in fits.items())
        rows = [row("report HSDC record: afmid fit, whole record and halves ([dmt], d estimated), CPU",
                    fits["whole"]["cpu"], None, None, "report only", None, fit_notes, rss_gb=fits["whole"]["rss_gb"])]
        if quick:
            return rows
        with peak_summed_pss(str(tmp / "one")) as one_pss:
            one = measured(AFMID + ["report", str(tmp / "whole.h5"), "-o", str(tmp / "one")], env)
        with peak_summed_pss(str(tmp / "two")) as two_pss:
            two = measured(AFMID + ["report", str(tmp / "half1.h5"), str(tmp / "half2.h5"), "-o", str(tmp / "two")],
                           env)
    # The footprint of a process tree: its summed PSS where sampled, never below the largest single process's RSS.
    one_gb = max(one["rss_gb"], one_pss["gb"]) if one_pss["gb"] == one_pss["gb"] else one["rss_gb"]
    two_gb = max(two["rss_gb"], two_pss["gb"]) if two_pss["gb"] == two_pss["gb"] else two["rss_gb"]
    peak = max(one_gb, two_gb)
    return rows + [
        row("report HSDC record: afmid report whole.h5, wall on 2 cores", one["wall"], None, None,
            f"<= {ONE_RUN_TARGET_S:g} s", wall_met(one, ONE_RUN_TARGET_S), timed(one), cpu_s=one["cpu"],
            rss_gb=one["rss_gb"]),
        row("report HSDC record: afmid report half1.h5 half2.h5 (both diagnosed), wall on 2 cores", two["wall"], None,
            None, f"<= {TWO_RUN_TARGET_S:g} s", wall_met(two, TWO_RUN_TARGET_S), timed(two), cpu_s=two["cpu"],
            rss_gb=two["rss_gb"]),
        row("report HSDC record: peak RSS of the reports (GB, not s)", peak, None, None, f"<= {RSS_TARGET_GB:g} GB",
            peak <= RSS_TARGET_GB, f"one-run {one_gb:.2f} GB, two-run {two_gb:.2f} GB (summed PSS of the process "
            f"tree {one_pss['gb']:.2f} / {two_pss['gb']:.2f} GB; largest process RSS {one['rss_gb']:.2f} / "
            f"{two['rss_gb']:.2f} GB)", unit="GB"),
    ]


def main() -> None:
    bench_main(__doc__, run, "the fits only",
               describe=lambda r: (f"{r['name']}: {r['afmid_s']:.2f} ({met_word(r['met'])})\n  {r['notes']}"
                                   if r["afmid_s"] is not None else r["name"]))


if __name__ == "__main__":
    main()
