"""Hidden-effect hit rate with the rest separation NOT given (the normal experimental case).

For each hidden-effect variant of tests/diagnosis/test_diagnose.py (VARIANTS, CLEAN: a DMT sample with one effect the
model [dmt] lacks, 50 steady periods, thermal noise at 300 K, 1 pm detector noise), plus a 3 V electrostatic
case at 200 and 50 samples per period: simulate, fit with ``model.effects: [dmt]`` and ``sample.separation``
absent, write the run file, diagnose (afmid.diagnosis.diagnose.suggest), then refit with the named effect added
(separation still estimated). One JSON line per trace: what afmid names first, the verdict, the
cross-validated error before / after / noise floor, the force error vs the simulator's truth (RMS over the
estimated samples / peak) before and after adding the named effect, and the separation error.

    python scripts/hidden_effects_unknown_d.py --out hidden.jsonl [--only electrostatic]
    python scripts/hidden_effects_unknown_d.py --table hidden.jsonl   # the markdown table
    python scripts/hidden_effects_unknown_d.py --compare before.jsonl after.jsonl

Run from the repository root (PYTHONPATH=other/checkout measures another version with the same traces).
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# The tests package (tests.diagnosis.test_diagnose holds the variants) and its helpers (tests/support).
sys.path.insert(0, str(ROOT / "tests" / "support"))
sys.path.insert(0, str(ROOT))

#: Extra cases (effect, variant name, overrides of tests/configs/hidden_<effect>.yaml).
EXTRA = [
    ("electrostatic", "3V-200", ["simulate.parameters.voltage=3.0", "simulate.seed=35"]),
    ("electrostatic", "3V-50", ["simulate.parameters.voltage=3.0", "simulate.samples_per_period=50", "simulate.seed=36"]),
]


def cases(only: str | None):
    from tests.diagnosis.test_diagnose import CLEAN, VARIANTS

    out = [(effect, variant, overrides) for effect, table in VARIANTS.items() for variant, overrides in table.items()]
    out += EXTRA
    out += [("clean", variant, overrides) for variant, overrides in CLEAN.items()]
    return [c for c in out if only is None or c[0] == only]


def force_error(result, trace) -> float:
    import numpy as np

    truth = trace.truth.force
    used = np.isfinite(result.force_estimate)
    peak = float(np.abs(truth[used]).max())
    return float(np.sqrt(np.mean((result.force_estimate[used] - truth[used]) ** 2)) / peak)


def measure(effect: str, variant: str, overrides: list[str], folder: Path) -> dict:
    import afmid.diagnosis.diagnose as diagnose
    from afmid.config import apply_overrides, build_config, dump_config, parse_override, read_yaml
    from afmid.fit.pipeline import run_fit
    from afmid.runfile import write_run
    from afmid.io.trace import write_trace_file
    from afmid.simulate.driver import simulate

    raw = apply_overrides(read_yaml(ROOT / "tests" / "configs" / f"hidden_{effect}.yaml"),
                          [parse_override(o) for o in overrides])
    key = f"{effect}-{variant}"
    sim_config = build_config(raw, source=folder / f"{key}.yaml", base_dir=folder)
    trace = simulate(sim_config)
    trace_path = folder / f"{key}.h5"
    write_trace_file(trace_path, trace, dump_config(sim_config))
    fit_raw = copy.deepcopy(raw)
    fit_raw["data"] = {"path": str(trace_path)}
    fit_raw["simulate"]["parameters"] = {}
    fit_raw["sample"]["separation"] = None
    config = build_config(fit_raw, source=folder / f"{key}.yaml", base_dir=folder)
    d_true = float(trace.truth.extra["separation"])
    started = time.perf_counter()
    result = run_fit(config, uncertainty=False)
    write_run(folder / f"{key}.run.h5", result, config)
    run = diagnose.load_run(folder / f"{key}.run.h5")
    summary = diagnose.suggest(run)
    seconds = time.perf_counter() - started
    top = summary["suggestions"][0]["effect"] if summary["suggestions"] else None
    entry = {"case": key, "expected": None if effect == "clean" else effect, "top": top,
             "named": [s["effect"] for s in summary["suggestions"]],
             "verdict": summary["diagnosis"]["verdict"], "error_before": result.cv_error,
             "floor": result.cv_error_noise_floor, "force_before": force_error(result, trace),
             "d_error_before": float(result.system.params["d"]) - d_true, "seconds": seconds}
    if top is not None:
        after_config = copy.deepcopy(config)
        after_config.model.effects = list(config.model.effects) + [s["effect"] for s in summary["suggestions"]]
        after = run_fit(after_config, uncertainty=False)
        entry.update(error_after=after.cv_error, floor_after=after.cv_error_noise_floor,
                     force_after=force_error(after, trace), d_error_after=float(after.system.params["d"]) - d_true)
    return entry


def table(path: Path) -> str:
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    out = ["| trace | named first | cv error before -> after (floor) | after / floor | force error % of peak before -> after | d error pm before -> after |",
           "|---|---|---|---|---|---|"]
    for r in rows:
        after = r.get("error_after", math.nan)
        floor = r.get("floor_after", r["floor"])
        out.append(f"| {r['case']} | {r['top'] or '—'} | {r['error_before']:.4f} -> {after:.4f} ({floor:.4f}) | "
                   f"{after / floor:.2f} | {100 * r['force_before']:.2f} -> {100 * r.get('force_after', math.nan):.2f} | "
                   f"{1e12 * r['d_error_before']:+.0f} -> {1e12 * r.get('d_error_after', math.nan):+.0f} |")
    hidden = [r for r in rows if r["expected"]]
    hits = sum(r["top"] == r["expected"] for r in hidden)
    within = sum(r["top"] == r["expected"] and r["error_after"] <= 1.5 * r["floor_after"] for r in hidden)
    alarms = sum(r["top"] is not None for r in rows if not r["expected"])
    clean = sum(1 for r in rows if not r["expected"])
    out.append(f"\nnamed first: {hits}/{len(hidden)}; named and error within 1.5x the floor: {within}/{len(hidden)}; "
               f"false alarms: {alarms}/{clean}")
    return "\n".join(out)


def compare(before: Path, after: Path) -> str:
    """One markdown table: each trace before and after (two runs of this script on two versions)."""
    def load(path):
        return {r["case"]: r for r in map(json.loads, path.read_text().splitlines()) if "failed" not in r}

    old, new = load(before), load(after)
    out = ["| trace | named first: before / after | cv error -> with the named effect (floor): before / after | "
           "force error % of peak -> with it: before / after | d error pm (run): before / after |",
           "|---|---|---|---|---|"]

    def err(r):
        if r["top"] is None:
            return f"{r['error_before']:.3f} ({r['floor']:.3f})"
        return f"{r['error_before']:.3f} -> {r['error_after']:.3f} ({r['floor_after']:.3f})"

    def force(r):
        text = f"{100 * r['force_before']:.2f}"
        return text + (f" -> {100 * r['force_after']:.2f}" if r["top"] else "")

    def named(r):
        kind = ("" if r["verdict"].startswith("missing effect") else " (part)" if r["top"] else
                " (no effect is missing)" if r["verdict"].startswith("no effect") else " (not explained)")
        return (r["top"] or "—") + kind

    for case in [c for c in new if c in old]:
        a, b = old[case], new[case]
        out.append(f"| {case} | {named(a)} / {named(b)} | {err(a)} / {err(b)} | {force(a)} / {force(b)} | "
                   f"{1e12 * a['d_error_before']:+.0f} / {1e12 * b['d_error_before']:+.0f} |")
    for name, rows in (("before", old), ("after", new)):
        hidden = [r for c, r in rows.items() if r["expected"] and c in new and c in old]
        hits = sum(r["top"] == r["expected"] for r in hidden)
        within = sum(r["top"] == r["expected"] and r["error_after"] <= 1.5 * r["floor_after"] for r in hidden)
        clean = [r for c, r in rows.items() if not r["expected"] and c in new and c in old]
        alarms = sum(r["top"] is not None or not r["verdict"].startswith("no effect") for r in clean)
        explained = sum(r["top"] == r["expected"] and r["verdict"].startswith("missing effect") for r in hidden)
        out.append(f"\n{name}: named first {hits}/{len(hidden)} (verdict \"missing effect\": {explained}); named and "
                   f"error within 1.5x the floor {within}/{len(hidden)}; alarms on clean traces {alarms}/{len(clean)}")
    return "\n".join(out)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--only")
    parser.add_argument("--table", type=Path)
    parser.add_argument("--compare", type=Path, nargs=2, metavar=("BEFORE", "AFTER"))
    args = parser.parse_args(argv)
    if args.compare:
        print(compare(*args.compare))
        return 0
    if args.table:
        print(table(args.table))
        return 0
    done = set()
    if args.out and args.out.exists():  # resume: the cases already measured into --out are skipped
        done = {json.loads(line)["case"] for line in args.out.read_text().splitlines() if line.strip()}
    with tempfile.TemporaryDirectory() as tmp:
        for effect, variant, overrides in cases(args.only):
            if f"{effect}-{variant}" in done:
                continue
            try:
                entry = measure(effect, variant, overrides, Path(tmp))
            except Exception as exc:  # record and go on: one failing trace must not stop the measurement
                entry = {"case": f"{effect}-{variant}", "failed": repr(exc)}
            print(json.dumps(entry), flush=True)
            if args.out:
                with args.out.open("a") as fh:
                    fh.write(json.dumps(entry) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
