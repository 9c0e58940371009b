"""Benchmark: ``afmid report`` of the demo's loop (issues 30, 31): a two-run report redoes no diagnosis made before.

Workload: the demo (afmid/templates/demo_ldpe.yaml: 50 periods x 200 samples, DMT + hidden Kelvin-Voigt), fitted
with [dmt] (run1) and [dmt, viscoelastic] (run2), as ``make demo`` does. Each command in a fresh process, one BLAS
thread, a fresh diagnosis cache (``AFMID_DIAGNOSIS_CACHE``, afmid.diagnosis.stored):

1. ``afmid report run1.h5`` (diagnoses run1 and keeps it);
2. ``afmid report run1.h5 run2.h5`` after it (run1's diagnosis reused, run2 diagnosed);
3. the same two-run report with the cache off (both diagnosed: what every two-run report cost before).

Target (issue 31): the two-run report <= 12 s and <= 1.3x the one-run report. Checked too: the reused report's
summary.json equals the one made from scratch (timings aside).

Run: python bench/bench_report.py
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import ROOT, SINGLE_THREAD, bench_main, cached_trace, row, timed  # noqa: E402

CONFIG = ROOT / "afmid" / "templates" / "demo_ldpe.yaml"
AFMID = [sys.executable, "-m", "afmid.cli"]
WALL_TARGET, RATIO_TARGET = 12.0, 1.3


def _without_times(obj):
    if isinstance(obj, dict):
        return {k: _without_times(v) for k, v in obj.items() if k != "seconds"}
    if isinstance(obj, list):
        return [_without_times(v) for v in obj]
    return obj


def run(quick: bool = False) -> list[dict]:
    trace = cached_trace(CONFIG, [], "demo_ldpe")
    with tempfile.TemporaryDirectory(prefix="afmid-bench-report-") as tmp:
        tmp = Path(tmp)
        env = dict(SINGLE_THREAD, AFMID_DIAGNOSIS_CACHE=str(tmp / "cache"))
        run1, run2 = tmp / "run1.h5", tmp / "run2.h5"
        for out, extra in ((run1, []), (run2, ["--add", "viscoelastic"])):
            timed(AFMID + ["-q", "fit", str(CONFIG), "--set", f"data.path={trace}", *extra, "-o", str(out)], env)
        one, one_cpu = timed(AFMID + ["-q", "report", str(run1), "-o", str(tmp / "one")], env)
        two, two_cpu = timed(AFMID + ["-q", "report", str(run1), str(run2), "-o", str(tmp / "two")], env)
        fresh, fresh_cpu = timed(AFMID + ["-q", "report", str(run1), str(run2), "-o", str(tmp / "fresh")],
                                 dict(env, AFMID_DIAGNOSIS_CACHE="off"))
        same = (_without_times(json.loads((tmp / "two" / "summary.json").read_text())) ==
                _without_times(json.loads((tmp / "fresh" / "summary.json").read_text())))
    ratio = two / one
    return [
        row("report: demo, afmid report run1 run2 after afmid report run1 (run1's diagnosis reused)", two, one,
            ratio, f"<= {WALL_TARGET:g} s and <= {RATIO_TARGET}x the one-run report",
            two <= WALL_TARGET and ratio <= RATIO_TARGET,
            f"'reference' = the one-run report ({one:.2f} s, CPU {one_cpu:.2f} s); two-run CPU {two_cpu:.2f} s; "
            f"the same two-run report with the cache off (both runs diagnosed, as before issue 30) {fresh:.2f} s "
            f"(CPU {fresh_cpu:.2f} s); summary.json identical to it (timings aside): {same}"),
    ]


def main() -> None:
    bench_main(__doc__, run, "the same (the demo is small)")


if __name__ == "__main__":
    main()
