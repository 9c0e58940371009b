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

Targets (issue 29, item 4, on 2 cores): one-run report <= 60 s, two-run <= 90 s, peak RSS <= 2 GB. The machine is
shared with other jobs, so the rows judge the CPU time (the report draws its figures in a forked child beside the
diagnosis: on 2 quiet cores its wall time is at most its CPU time). --quick: the fits only.

Run: python bench/bench_report_hsdc.py [--quick]
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_report import AFMID, described  # noqa: E402
from common import ROOT, SINGLE_THREAD, bench_main, measured, met_word, row  # noqa: E402

ONE_RUN_TARGET_S, TWO_RUN_TARGET_S, RSS_TARGET_GB = 60.0, 90.0, 2.0
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
        one = measured(AFMID + ["report", str(tmp / "whole.h5"), "-o", str(tmp / "one")], env)
        two = measured(AFMID + ["report", str(tmp / "half1.h5"), str(tmp / "half2.h5"), "-o", str(tmp / "two")], env)
    peak = max(one["rss_gb"], two["rss_gb"])
    return rows + [
        row("report HSDC record: afmid report whole.h5, CPU", one["cpu"], None, None,
            f"<= {ONE_RUN_TARGET_S:g} s", one["cpu"] <= ONE_RUN_TARGET_S, described(one),
            cpu_s=one["cpu"], rss_gb=one["rss_gb"]),
        row("report HSDC record: afmid report half1.h5 half2.h5 (both diagnosed), CPU", two["cpu"], None, None,
            f"<= {TWO_RUN_TARGET_S:g} s", two["cpu"] <= TWO_RUN_TARGET_S, described(two),
            cpu_s=two["cpu"], rss_gb=two["rss_gb"]),
        row("report HSDC record: peak RSS of the reports (GB, not s)", peak, None, None, f"<= {RSS_TARGET_GB:g} GB",
            peak <= RSS_TARGET_GB, f"one-run {one['rss_gb']:.2f} GB, two-run {two['rss_gb']:.2f} GB", unit="GB"),
    ]


def main() -> None:
    bench_main(__doc__, run, "the fits only",
               describe=lambda r: (f"{r['name']}: {r['afmid_s']:.2f} ({met_word(r['met'])})\n  {r['notes']}"
                                   if r["afmid_s"] is not None else r["name"]))


if __name__ == "__main__":
    main()
