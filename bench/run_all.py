"""Run every benchmark and print one table (``make bench``; ``--quick`` for a smoke run).

Each bench/bench_*.py exposes ``run(quick) -> list[dict]`` with rows holding
``name``, ``afmid_s``, ``reference_s``, ``ratio``, ``notes`` and, for the
benchmarks with a target, ``target`` and ``met``. The table is printed and
also written to bench/results/table.md and bench/results/bench.json.

Run: python bench/run_all.py [--quick] [--only simulate,fit,...] (names: BENCHES below). The heavy ones alone:
``--only report_record`` (the 5e5-sample record's reports, ~3 min of CPU quiet, its trace simulated once),
``--only map_diagnosis`` (a 64x64 map twice, ~6 min of CPU, its map simulated once), ``--only report_hsdc`` (the real
Bruker record's reports; one row saying it is skipped when the record is absent).
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import RESULTS, load_average, machine  # noqa: E402  (sets the BLAS thread count first)

BENCHES = ["simulate", "fit", "selection", "scaling", "coldstart", "batch", "map", "group_diagnosis", "report",
           "report_record", "report_hsdc", "map_diagnosis"]


def _seconds(value, unit: str = "s") -> str:
    if value is None:
        return "-"
    if unit != "s":  # a row measuring something else than time (peak memory in GB)
        return f"{value:.2f} {unit}"
    if value >= 100:
        return f"{value:.0f} s"
    if value >= 1:
        return f"{value:.2f} s"
    return f"{value * 1e3:.1f} ms"


def _ratio(value) -> str:
    if value is None:
        return "-"
    return f"{value:.2f}x" if value < 10 else f"{value:.0f}x"


def table(rows: list[dict]) -> str:
    lines = ["| benchmark | afmid | reference | ratio | target | met |", "| --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        met = {True: "yes", False: "**no**", None: "-"}[r.get("met")]
        lines.append(f"| {r['name']} | {_seconds(r.get('afmid_s'), r.get('unit', 's'))} | "
                     f"{_seconds(r.get('reference_s'), r.get('unit', 's'))} | "
                     f"{_ratio(r.get('ratio'))} | {r.get('target', '')} | {met} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes: a smoke run of every benchmark")
    parser.add_argument("--only", default=",".join(BENCHES), help="comma-separated subset of " + ", ".join(BENCHES))
    args = parser.parse_args()
    chosen = [b.strip() for b in args.only.split(",") if b.strip()]
    unknown = set(chosen) - set(BENCHES)
    if unknown:
        parser.error(f"unknown benchmarks {sorted(unknown)}; choose from {BENCHES}")
    rows: list[dict] = []
    failed = False
    started = time.time()
    print(f"machine: {machine()}; load average at start {load_average()}", flush=True)
    for name in chosen:
        t0 = time.perf_counter()
        print(f"running bench_{name} ...", flush=True)
        try:
            module = importlib.import_module(f"bench_{name}")
            got = module.run(args.quick)
            for r in got:
                r.setdefault("target", "")
                r.setdefault("met", None)
            rows.extend(got)
        except Exception as exc:  # one broken benchmark must not hide the others
            failed = True
            traceback.print_exc()
            rows.append({"name": f"{name}: FAILED ({type(exc).__name__}: {exc})", "afmid_s": None,
                         "reference_s": None, "ratio": None, "target": "", "met": False, "notes": ""})
        print(f"  done in {time.perf_counter() - t0:.0f} s", flush=True)
    text = table(rows)
    notes = "\n".join(f"- {r['name']}: {r['notes']}" for r in rows if r.get("notes"))
    header = (f"machine: {machine()}; load average at the end {load_average()} (other jobs share this machine); "
              f"{'quick' if args.quick else 'full'} run, {time.time() - started:.0f} s")
    print()
    print(header)
    print(text)
    print()
    print(notes)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "table.md").write_text(f"{header}\n\n{text}\n\n{notes}\n", encoding="utf-8")
    (RESULTS / "bench.json").write_text(json.dumps({"machine": machine(), "quick": args.quick, "rows": rows},
                                                   indent=1, default=str), encoding="utf-8")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
