"""Poor signals (issue 13 part 4): the poor instrument (10 pm detector noise, 50 samples per period) and a soft
lever in liquid (Q 4), with the rest separation NOT given.

Cases (fixed before any result was looked at):

- ``poor-clean-{a,b,c}``: tests/configs/hidden_clean.yaml with the CLEAN variants of tests/diagnosis/test_diagnose.py,
  detector 10 pm rms, 50 samples per period; model [dmt]. Expected: nothing named.
- ``poor-visco-{a,b,c}``: tests/configs/hidden_viscoelastic.yaml with its VARIANTS, same instrument; model
  [dmt]. Expected: "viscoelastic" named or nothing named (the data cannot decide); never another effect.
- ``liquid-d{3,4,5,5.5}-s{1,2,3}``: tests/configs/liquid.yaml (k 0.8 N/m, f0 25 kHz, Q 4, R 10 nm, A0 5 nm,
  E* 50 MPa, H 1e-20 J, 5 pm detector) at d 3 / 4 / 5 / 5.5 nm (5 nm: indentation ~0.3 nm, barely touching;
  5.5 nm: the tip never reaches a0, no contact), seeds 1-3; model [dmt]. Expected: nothing named.

For each case: fit with the error bars (bootstrap 50), write the run file, diagnose (afmid.diagnosis.diagnose.suggest).
One JSON line per case: named effects and verdict, selected terms and their inclusion probabilities, E* and H
(value, 1 sigma, 95 % interval, whether determined), the force error vs the simulator's truth (RMS over the
estimated samples / max |true force|), and the separation error.

    python scripts/poor_signals.py --out poor.jsonl [--only liquid]
    python scripts/poor_signals.py --coverage liquid-d4 --seeds 1-12 --out cov.jsonl   # fits only
    python scripts/poor_signals.py --table poor.jsonl
    python scripts/poor_signals.py --compare before.jsonl after.jsonl
    python scripts/poor_signals.py --smoother 1-8 [--unknown] --out smoother.jsonl   # the poor instrument's fit
        with the default smoother's trajectory, none, and the true motion (tests/support/smoother_oracle.py)

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

POOR = ["simulate.noise.detector_rms=1.0e-11", "simulate.samples_per_period=50", "fit.bootstrap=50"]
LIQUID_SEPARATIONS = {"d3": 3.0e-9, "d4": 4.0e-9, "d5": 5.0e-9, "d5.5": 5.5e-9}
TRUTH = {"E_star": "E_star", "hamaker": "hamaker"}


def cases(only: str | None):
    from tests.diagnosis.test_diagnose import CLEAN, VARIANTS

    out = [(f"poor-clean-{v}", "hidden_clean", POOR + o, None) for v, o in CLEAN.items()]
    out += [(f"poor-visco-{v}", "hidden_viscoelastic", POOR + o, "viscoelastic")
            for v, o in VARIANTS["viscoelastic"].items()]
    out += [(f"liquid-{name}-s{seed}", "liquid", [f"sample.separation={d}", f"simulate.seed={seed}"], None)
            for name, d in LIQUID_SEPARATIONS.items() for seed in (1, 2, 3)]
    return [c for c in out if only is None or c[0].startswith(only)]


def force_error(result, trace) -> float:
    import numpy as np

    truth = trace.truth.force
    used = np.isfinite(result.force_estimate)
    peak = float(np.abs(truth[used]).max())
    return float(np.sqrt(np.mean((result.force_estimate[used] - truth[used]) ** 2)) / peak)


def simulated(config_name: str, overrides: list[str], key: str, folder: Path):
    from afmid.config import apply_overrides, build_config, dump_config, parse_override, read_yaml
    from afmid.io.trace import write_trace_file
    from afmid.simulate.driver import simulate

    raw = apply_overrides(read_yaml(ROOT / "tests" / "configs" / f"{config_name}.yaml"),
                          [parse_override(o) for o in overrides])
    sim_config = build_config(raw, source=folder / f"{key}.yaml", base_dir=folder)
    trace = simulate(sim_config)
    trace_path = folder / f"{key}.h5"
    write_trace_file(trace_path, trace, dump_config(sim_config))
    fit_raw = copy.deepcopy(raw)
    fit_raw["data"] = {"path": str(trace_path)}
    truth = dict(fit_raw["simulate"]["parameters"])
    fit_raw["simulate"]["parameters"] = {}
    fit_raw["sample"]["separation"] = None
    return trace, build_config(fit_raw, source=folder / f"{key}.yaml", base_dir=folder), truth


def quantity_entry(q: dict) -> dict:
    keys = ("value", "error", "ci_low", "ci_high", "determined", "upper_95")
    return {k: (float(q[k]) if isinstance(q.get(k), (int, float)) and not isinstance(q.get(k), bool) else q.get(k))
            for k in keys if k in q}


def fit_entry(key: str, config, trace, truth: dict, result) -> dict:
    d_true = float(trace.truth.extra["separation"])
    n = result.n_library
    return {"case": key, "terms": result.selected_terms(),
            "inclusion": {name: round(float(p), 3) for name, p in zip(result.library.names, result.inclusion[:n])},
            "quantities": {name: quantity_entry(result.quantities[name]) for name in TRUTH if name in result.quantities},
            "truth": {name: float(truth[name]) if truth.get(name) is not None else None for name in TRUTH},
            "force": force_error(result, trace), "cv_error": result.cv_error, "floor": result.cv_error_noise_floor,
            "d_error": float(result.system.params["d"]) - d_true,
            "d_sigma": float(result.nonlinear["d"].sigma) if "d" in result.nonlinear else math.nan,
            "warnings": [w for w in result.warnings if "not determined" in w or "cannot decide" in w]}


def measure(key: str, config_name: str, overrides: list[str], expected, folder: Path, diagnose_too: bool) -> dict:
    import afmid.diagnosis.diagnose as diagnose
    from afmid.fit.pipeline import run_fit
    from afmid.runfile import write_run

    trace, config, truth = simulated(config_name, overrides, key, folder)
    started = time.perf_counter()
    result = run_fit(config)
    entry = fit_entry(key, config, trace, truth, result)
    entry["expected"] = expected
    if diagnose_too:
        write_run(folder / f"{key}.run.h5", result, config)
        summary = diagnose.suggest(diagnose.load_run(folder / f"{key}.run.h5"))
        entry["named"] = [s["effect"] for s in summary["suggestions"]]
        entry["verdict"] = summary["diagnosis"]["verdict"]
    entry["seconds"] = time.perf_counter() - started
    return entry


def _fmt_q(q: dict | None, truth) -> str:
    truth = float(truth) if truth is not None else None
    if not q:
        return "—"
    if q.get("determined") is False:
        bound = q.get("upper_95")
        return "not determined" + (f" (< {bound:.3g})" if isinstance(bound, float) and math.isfinite(bound) else "")
    rel = 100 * (q["value"] - truth) / truth if truth else math.nan
    sig = 100 * q["error"] / truth if truth and q.get("error") is not None else math.nan
    return f"{rel:+.1f} % ± {sig:.1f}"


def table(path: Path) -> str:
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    for r in rows:
        r.setdefault("truth", {})
        r["truth"] = {k: float(v) if v is not None else None for k, v in r["truth"].items()}
    out = ["| case | named (verdict) | terms (inclusion) | E* error ± 1 sigma | H error ± 1 sigma | force % | d error pm |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        if "failed" in r:
            out.append(f"| {r['case']} | failed: {r['failed'][:80]} |")
            continue
        named = ", ".join(r.get("named", [])) or "—"
        verdict = r.get("verdict", "")[:40]
        incl = ", ".join(f"{k} {v:.2f}" for k, v in r["inclusion"].items())
        out.append(f"| {r['case']} | {named} ({verdict}) | {incl} | "
                   f"{_fmt_q(r['quantities'].get('E_star'), r['truth'].get('E_star'))} | "
                   f"{_fmt_q(r['quantities'].get('hamaker'), r['truth'].get('hamaker'))} | {100 * r['force']:.2f} | "
                   f"{1e12 * r['d_error']:+.0f} |")
    ok = [r for r in rows if "failed" not in r]
    wrong = sum(1 for r in ok if any(n != r["expected"] for n in r.get("named", [])))
    zero = sum(1 for r in ok for q in r["quantities"].values()
               if q.get("determined") is not False and q.get("value") == 0 and (q.get("error") or 0) == 0)
    cover = [(r, name) for r in ok for name, q in r["quantities"].items()
             if q.get("determined") is not False and q.get("error") and r["truth"].get(name)]
    inside = sum(abs(r["quantities"][n]["value"] - r["truth"][n]) < 2 * r["quantities"][n]["error"] for r, n in cover)
    out.append(f"\nwrong effects named: {wrong}/{len(ok)}; read-outs '0 ± 0': {zero}; "
               f"|error| < 2 sigma: {inside}/{len(cover)}")
    return "\n".join(out)


def compare(before: Path, after: Path) -> str:
    """One markdown table: each case before and after (two runs of this script on two versions)."""
    def load(path):
        out = {}
        for line in path.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                r["truth"] = {k: float(v) if v is not None else None for k, v in r.get("truth", {}).items()}
                out[r["case"]] = r
        return out

    def named(r):
        if "failed" in r:
            return "refused: " + r["failed"].split(": ")[-1][:60]
        verdict = r.get("verdict", "")
        if r.get("named"):
            return ", ".join(r["named"])
        return "cannot decide" if "cannot decide" in verdict else "—"

    def q(r, name):
        return "—" if "failed" in r else _fmt_q(r["quantities"].get(name), r["truth"].get(name))

    old, new = load(before), load(after)
    out = ["| case | named: before / after | E* ± 1σ: before / after | H ± 1σ: before / after | incl. Hertz, vdW after | "
           "force % | d error pm |", "|---|---|---|---|---|---|---|"]
    for case, b in new.items():
        a = old.get(case, {"failed": "not measured"})
        incl = ("—" if "failed" in b else
                f"{b['inclusion'].get('dmt.hertz', float('nan')):.2f}, {b['inclusion'].get('dmt.vdw', float('nan')):.2f}")
        force = "—" if "failed" in b else f"{100 * b['force']:.2f}"
        derr = "—" if "failed" in b else f"{1e12 * b['d_error']:+.0f}"
        out.append(f"| {case} | {named(a)} / {named(b)} | {q(a, 'E_star')} / {q(b, 'E_star')} | "
                   f"{q(a, 'hamaker')} / {q(b, 'hamaker')} | {incl} | {force} | {derr} |")
    return "\n".join(out)


def smoother(seeds: str, separation_given: bool, out: Path | None) -> None:
    """The poor instrument (hidden_clean.yaml, seeds ``lo-hi``): force, E*, H and separation errors with each
    trajectory for the force law (does the default smoother bias the fit? issue 13)."""
    from smoother_oracle import fit_three_ways

    lo, hi = map(int, seeds.split("-"))
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(lo, hi + 1):
            entry = {"seed": seed, "separation_given": separation_given,
                     **fit_three_ways(Path(tmp), seed, separation_given=separation_given)}
            print(json.dumps(entry), flush=True)
            if out:
                with out.open("a") as fh:
                    fh.write(json.dumps(entry) + "\n")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--only")
    parser.add_argument("--table", type=Path)
    parser.add_argument("--compare", type=Path, nargs=2, metavar=("BEFORE", "AFTER"))
    parser.add_argument("--coverage", help="a liquid separation name (d3, d4, d5, d5.5): fits only, over --seeds")
    parser.add_argument("--seeds", default="1-12")
    parser.add_argument("--smoother", metavar="LO-HI", help="seeds: default smoother vs none vs the true motion")
    parser.add_argument("--unknown", action="store_true", help="with --smoother: the separation NOT given")
    args = parser.parse_args(argv)
    if args.smoother:
        smoother(args.smoother, not args.unknown, args.out)
        return 0
    if args.table:
        print(table(args.table))
        return 0
    if args.compare:
        print(compare(*args.compare))
        return 0
    if args.coverage:
        lo, hi = map(int, args.seeds.split("-"))
        d = LIQUID_SEPARATIONS[args.coverage.removeprefix("liquid-")]
        todo = [(f"liquid-{args.coverage.removeprefix('liquid-')}-s{s}", "liquid",
                 [f"sample.separation={d}", f"simulate.seed={s}"], None) for s in range(lo, hi + 1)]
        diagnose_too = False
    else:
        todo, diagnose_too = cases(args.only), True
    done = set()
    if args.out and args.out.exists():
        done = {json.loads(line)["case"] for line in args.out.read_text().splitlines() if line.strip()}
    with tempfile.TemporaryDirectory() as tmp:
        for key, config_name, overrides, expected in todo:
            if key in done:
                continue
            try:
                entry = measure(key, config_name, overrides, expected, Path(tmp), diagnose_too)
            except Exception as exc:  # record and go on
                entry = {"case": key, "failed": repr(exc)}
            print(json.dumps(entry), flush=True)
            if args.out:
                with args.out.open("a") as fh:
                    fh.write(json.dumps(entry) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
