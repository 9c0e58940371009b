"""Benchmark: ``afmid report`` of the demo's loop (issues 30, 31), against the fit and against the previous release.

Workload: the demo (afmid/templates/demo_ldpe.yaml: 50 periods x 200 samples, DMT + hidden Kelvin-Voigt), fitted
with [dmt] (run1) and [dmt, viscoelastic] (run2), as ``make demo`` does. Each command in a fresh process, one BLAS
thread, a fresh diagnosis cache (``AFMID_DIAGNOSIS_CACHE``, afmid.diagnosis.stored); wall, CPU (user + sys) and
peak RSS of each process (bench/common.py ``measured``):

1. ``afmid fit`` run1 and run2;
2. ``afmid report run1.h5`` (diagnoses run1 and keeps it);
3. ``afmid report run1.h5 run2.h5`` after it (run1's diagnosis reused, run2 diagnosed);
4. the same two-run report with the cache off (both diagnosed: what every two-run report cost before issue 30);
5. ``afmid report run1.h5`` again, run1's diagnosis kept: the report without its diagnosis. The diagnosis's CPU
   per trace is (2) - (5);
6. the previous release (bench/common.py ``PREVIOUS_RELEASE``, ``AFMID_BENCH_PREVIOUS``), the same commands from
   its own source tree in this environment: a warm-up fit (its numba caches), then (1), (2), (3) with its own
   run files. Not with --quick.

Targets (issue 31): the one-run report <= 10 s and <= 3.5x the fit's wall time; the two-run report <= 12 s and
<= 1.3x the one-run report. Checked too: the reused report's summary.json equals the one made from scratch
(timings aside). The 5e5-sample record's rows are in bench_report_record.py.

Run: python bench/bench_report.py [--quick]
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import ROOT, SINGLE_THREAD, bench_main, cached_trace, measured, previous_release, row  # noqa: E402

CONFIG = ROOT / "afmid" / "templates" / "demo_ldpe.yaml"
AFMID = [sys.executable, "-m", "afmid.cli", "-q"]
ONE_RUN_TARGET_S, FIT_RATIO_TARGET = 10.0, 3.5
TWO_RUN_TARGET_S, RATIO_TARGET = 12.0, 1.3


def without_times(obj):
    """A summary.json without its timings (the only part that differs between equal reports)."""
    if isinstance(obj, dict):
        return {k: without_times(v) for k, v in obj.items() if k != "seconds"}
    if isinstance(obj, list):
        return [without_times(v) for v in obj]
    return obj


def same_summary(a: Path, b: Path) -> bool:
    return (without_times(json.loads((a / "summary.json").read_text())) ==
            without_times(json.loads((b / "summary.json").read_text())))


def fit_and_report(trace: Path, folder: Path, env: dict, cwd: Path = ROOT) -> dict:
    """Fit run1 ([dmt]) and run2 (+ viscoelastic), then the one-run and the two-run report: each one measured."""
    run1, run2 = folder / "run1.h5", folder / "run2.h5"
    got = {}
    for key, out, extra in (("fit1", run1, []), ("fit2", run2, ["--add", "viscoelastic"])):
        got[key] = measured(AFMID + ["fit", str(CONFIG), "--set", f"data.path={trace}", *extra, "-o", str(out)],
                            env, cwd=cwd)
    got["one"] = measured(AFMID + ["report", str(run1), "-o", str(folder / "one")], env, cwd=cwd)
    got["two"] = measured(AFMID + ["report", str(run1), str(run2), "-o", str(folder / "two")], env, cwd=cwd)
    return got


def described(m: dict) -> str:
    return f"{m['wall']:.2f} s (CPU {m['cpu']:.2f} s, {m['rss_gb']:.2f} GB)"


def run(quick: bool = False) -> list[dict]:
    trace = cached_trace(CONFIG, [], "demo_ldpe")
    previous = None if quick else previous_release()
    with tempfile.TemporaryDirectory(prefix="afmid-bench-report-") as tmp:
        tmp = Path(tmp)
        env = dict(SINGLE_THREAD, AFMID_DIAGNOSIS_CACHE=str(tmp / "cache"))
        new = fit_and_report(trace, tmp, env)
        fresh = measured(AFMID + ["report", str(tmp / "run1.h5"), str(tmp / "run2.h5"), "-o", str(tmp / "fresh")],
                         dict(env, AFMID_DIAGNOSIS_CACHE="off"))
        kept = measured(AFMID + ["report", str(tmp / "run1.h5"), "-o", str(tmp / "kept")], env)
        same = same_summary(tmp / "two", tmp / "fresh")
        old = None
        if previous is not None:
            commit, tree = previous
            (tmp / "previous").mkdir()
            warm_up = tmp / "previous" / "warm"
            warm_up.mkdir()
            measured(AFMID + ["fit", str(CONFIG), "--set", f"data.path={trace}", "-o", str(warm_up / "run.h5")],
                     SINGLE_THREAD, cwd=tree)  # its numba caches made, not timed
            old = fit_and_report(trace, tmp / "previous", SINGLE_THREAD, cwd=tree)
            old["commit"] = commit[:12]
    fit, one, two = new["fit1"], new["one"], new["two"]
    fit_ratio, two_ratio = one["wall"] / fit["wall"], two["wall"] / one["wall"]
    diagnosis_cpu = one["cpu"] - kept["cpu"]

    def against(key: str) -> str:
        if old is None:
            return "previous release not run (--quick or AFMID_BENCH_PREVIOUS=none)"
        return (f"previous release ({old['commit']}) {described(old[key])}: "
                f"{old[key]['wall'] / new[key]['wall']:.2f}x the wall, {old[key]['cpu'] / new[key]['cpu']:.2f}x the CPU")

    return [
        row("report: demo, afmid fit run1.h5 ([dmt], 10,000 samples)", fit["wall"],
            old["fit1"]["wall"] if old else None, old["fit1"]["wall"] / fit["wall"] if old else None,
            "report only", None, f"{described(fit)}; run2 (+ viscoelastic) {described(new['fit2'])}; {against('fit1')}",
            cpu_s=fit["cpu"]),
        row("report: demo, afmid report run1.h5 (diagnosis made), ratio to the fit", one["wall"], fit["wall"],
            fit_ratio, f"<= {ONE_RUN_TARGET_S:g} s and <= {FIT_RATIO_TARGET}x the fit's wall time",
            one["wall"] <= ONE_RUN_TARGET_S and fit_ratio <= FIT_RATIO_TARGET,
            f"'reference' = the fit's wall time, 'ratio' = report / fit; report {described(one)}, CPU ratio "
            f"{one['cpu'] / fit['cpu']:.2f}x; {against('one')}", cpu_s=one["cpu"], rss_gb=one["rss_gb"]),
        row("report: demo, afmid report run1 run2 after afmid report run1 (run1's diagnosis reused)", two["wall"],
            one["wall"], two_ratio, f"<= {TWO_RUN_TARGET_S:g} s and <= {RATIO_TARGET}x the one-run report",
            two["wall"] <= TWO_RUN_TARGET_S and two_ratio <= RATIO_TARGET,
            f"'reference' = the one-run report; two-run {described(two)}; with the cache off (both runs diagnosed, as "
            f"before issue 30) {described(fresh)}, summary.json identical to it (timings aside): {same}; "
            f"{against('two')}", cpu_s=two["cpu"], rss_gb=two["rss_gb"]),
        row("report: demo, diagnosis CPU per trace (one-run report minus the same report with its diagnosis kept)",
            diagnosis_cpu, None, None, "report only", None,
            f"one-run report CPU {one['cpu']:.2f} s, with run1's diagnosis kept {kept['cpu']:.2f} s "
            f"(wall {kept['wall']:.2f} s)"),
    ]


def main() -> None:
    bench_main(__doc__, run, "without the previous release")


if __name__ == "__main__":
    main()
