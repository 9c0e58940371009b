"""Benchmark: ``afmid report`` of a record as long as the real HSDC record (issue 31): time and peak memory.

Workload: bench/record_5e5.yaml, simulated once and cached in bench/results/: 600 periods at the HSDC record's
rate (50 MHz) and drive (56.856 kHz), 879.4 samples per period, 527,648 samples; lever 2.8 N/m, 57 kHz, Q 150;
DMT + hidden Kelvin-Voigt, fitted with [dmt] (run1) and [dmt, viscoelastic] (run2). Each command in a fresh
process, one BLAS thread, a fresh diagnosis cache; wall, CPU (user + sys) and peak RSS of each process tree
(bench/common.py ``measured``):

1. ``afmid fit`` run1 and run2;
2. ``afmid report run1.h5`` (run1 diagnosed and kept);
3. ``afmid report run1.h5 run2.h5`` after it (run1 reused, run2 diagnosed);
4. the same two-run report with the cache off: both diagnosed, what the two-run report cost before issue 30 (the
   "previous" of the two-run row; with --quick not run);
5. ``afmid report run1.h5`` again with run1's diagnosis kept: the report without its diagnosis; the diagnosis's
   CPU per trace is (2) - (5).

The previous release itself (bench/common.py ``PREVIOUS_RELEASE``) on this record took 6 min 44 s one run and
13 min two runs (issue 31's measurement); it runs here only with ``AFMID_BENCH_PREVIOUS_RECORD=1`` (then steps
1-3 from its source tree too), to keep ``make bench`` bounded.

Targets (issue 31): one-run report <= 60 s, two-run <= 90 s, peak RSS <= 2 GB. --quick: 60 periods (no target).

Run: python bench/bench_report_record.py [--quick]
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_report import AFMID, described, same_summary  # noqa: E402
from common import BENCH, ROOT, SINGLE_THREAD, bench_main, cached_trace, measured, met_word, previous_release, row  # noqa: E402

CONFIG = BENCH / "record_5e5.yaml"
ONE_RUN_TARGET_S, TWO_RUN_TARGET_S, RSS_TARGET_GB = 60.0, 90.0, 2.0


def fit_and_report(config: Path, overrides: list[str], trace: Path, folder: Path, env: dict,
                   cwd: Path = ROOT) -> dict:
    run1, run2 = folder / "run1.h5", folder / "run2.h5"
    sets = [item for o in [*overrides, f"data.path={trace}"] for item in ("--set", o)]
    got = {}
    for key, out, extra in (("fit1", run1, []), ("fit2", run2, ["--add", "viscoelastic"])):
        got[key] = measured(AFMID + ["fit", str(config), *sets, *extra, "-o", str(out)], env, cwd=cwd)
    got["one"] = measured(AFMID + ["report", str(run1), "-o", str(folder / "one")], env, cwd=cwd)
    got["two"] = measured(AFMID + ["report", str(run1), str(run2), "-o", str(folder / "two")], env, cwd=cwd)
    return got


def run(quick: bool = False) -> list[dict]:
    periods = 60 if quick else 600
    overrides = [f"simulate.periods={periods}"]
    trace = cached_trace(CONFIG, overrides, f"record_5e5_{periods}")
    old = None
    with tempfile.TemporaryDirectory(prefix="afmid-bench-record-") as tmp:
        tmp = Path(tmp)
        env = dict(SINGLE_THREAD, AFMID_DIAGNOSIS_CACHE=str(tmp / "cache"))
        new = fit_and_report(CONFIG, overrides, trace, tmp, env)
        kept = measured(AFMID + ["report", str(tmp / "run1.h5"), "-o", str(tmp / "kept")], env)
        fresh = same = None
        if not quick:
            fresh = measured(AFMID + ["report", str(tmp / "run1.h5"), str(tmp / "run2.h5"), "-o",
                                      str(tmp / "fresh")], dict(env, AFMID_DIAGNOSIS_CACHE="off"))
            same = same_summary(tmp / "two", tmp / "fresh")
        previous = previous_release() if os.environ.get("AFMID_BENCH_PREVIOUS_RECORD") == "1" else None
        if previous is not None:
            (tmp / "previous").mkdir()
            old = fit_and_report(CONFIG, overrides, trace, tmp / "previous", SINGLE_THREAD, cwd=previous[1])
            old["commit"] = previous[0][:12]
    one, two = new["one"], new["two"]
    samples = f"{periods} periods, {periods * 5e7 / 56856.09:,.0f} samples"
    target = not quick

    def against(key: str) -> str:
        if old is None:
            return "previous release not run (AFMID_BENCH_PREVIOUS_RECORD=1 runs it: ~20 min)"
        return (f"previous release ({old['commit']}) {described(old[key])}: "
                f"{old[key]['wall'] / new[key]['wall']:.2f}x the wall")

    fresh_note = (f"with the cache off (both diagnosed, as before issue 30) {described(fresh)}, summary.json identical "
                  f"to it (timings aside): {same}" if fresh else "cache-off report not run (--quick)")
    peak = max(one["rss_gb"], two["rss_gb"])
    return [
        row(f"report record: {samples} at 50 MHz, afmid fit run1.h5 ([dmt])", new["fit1"]["wall"], None, None,
            "report only", None, f"{described(new['fit1'])}; run2 (+ viscoelastic) {described(new['fit2'])}; "
            f"{against('fit1')}", cpu_s=new["fit1"]["cpu"], rss_gb=new["fit1"]["rss_gb"]),
        row(f"report record: {samples}, afmid report run1.h5", one["wall"], new["fit1"]["wall"],
            one["wall"] / new["fit1"]["wall"], f"<= {ONE_RUN_TARGET_S:g} s" if target else "(quick: none)",
            one["wall"] <= ONE_RUN_TARGET_S if target else None,
            f"'reference' = the fit, 'ratio' = report / fit; {described(one)}; {against('one')}",
            cpu_s=one["cpu"], rss_gb=one["rss_gb"]),
        row(f"report record: {samples}, afmid report run1 run2 after afmid report run1", two["wall"],
            fresh["wall"] if fresh else None, fresh["wall"] / two["wall"] if fresh else None,
            f"<= {TWO_RUN_TARGET_S:g} s" if target else "(quick: none)",
            two["wall"] <= TWO_RUN_TARGET_S if target else None,
            f"'reference' = the two-run report with the cache off, 'ratio' = reference / afmid; {described(two)}; "
            f"{fresh_note}; {against('two')}", cpu_s=two["cpu"], rss_gb=two["rss_gb"]),
        row(f"report record: {samples}, peak RSS of the reports (GB, not s)", peak, None, None,
            f"<= {RSS_TARGET_GB:g} GB" if target else "(quick: none)", peak <= RSS_TARGET_GB if target else None,
            f"one-run {one['rss_gb']:.2f} GB, two-run {two['rss_gb']:.2f} GB, both kept {kept['rss_gb']:.2f} GB; "
            f"fit {new['fit1']['rss_gb']:.2f} GB", unit="GB"),
        row(f"report record: {samples}, diagnosis CPU per trace (one-run report minus it with the diagnosis kept)",
            one["cpu"] - kept["cpu"], None, None, "report only", None,
            f"one-run report CPU {one['cpu']:.2f} s, with run1's diagnosis kept {kept['cpu']:.2f} s "
            f"(wall {kept['wall']:.2f} s, {kept['rss_gb']:.2f} GB)"),
    ]


def main() -> None:
    bench_main(__doc__, run, "60 periods",
               describe=lambda r: f"{r['name']}: {r['afmid_s']:.2f} ({met_word(r['met'])})\n  {r['notes']}")


if __name__ == "__main__":
    main()
