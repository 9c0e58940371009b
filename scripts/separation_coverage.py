"""Coverage of the rest separation's reported 1-sigma: |d - d_true| < 2 sigma in how many fits?

Simulates short steady traces at several operating points and seeds, fits each with the true model and
``sample.separation`` absent (estimated), and prints one row per fit plus the coverage per operating point.
The operating points and seeds are fixed here (chosen before looking at the results); tests/fit/test_profile.py
runs a subset. Run from the repository root (PYTHONPATH=other/checkout to measure another version):

    python scripts/separation_coverage.py [--seeds 1,2,3,4] [--json out.jsonl]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: (name, config, model effects, overrides). 20 periods each: short, cheap records.
OPERATING_POINTS = [
    ("dmt 2 GPa", "tests/configs/hidden_clean.yaml", "[dmt]", []),
    ("dmt 50 GPa (stiff: V-shaped profile)", "tests/configs/hidden_clean.yaml", "[dmt]",
     ["simulate.parameters.E_star=50e9"]),
    ("dmt + viscoelastic 150 Pa s", "tests/configs/hidden_viscoelastic.yaml", "[dmt,viscoelastic]", []),
    ("dmt + electrostatic 1.5 V", "tests/configs/hidden_electrostatic.yaml", "[dmt,electrostatic]", []),
    ("LDPE demo, 0.1 pm detector, no thermal noise", "afmid/templates/demo_ldpe.yaml", "[dmt,viscoelastic]",
     ["simulate.noise.thermal=false", "simulate.noise.detector_rms=1e-13"]),
]
PERIODS = 20


def fit_one(config_path: str, effects: str, overrides: list[str], seed: int) -> dict:
    from afmid.config import load_config
    from afmid.fit.pipeline import run_fit
    from afmid.simulate.driver import simulate

    common = [f"simulate.seed={seed}", f"simulate.periods={PERIODS}", "fit.bootstrap=0", "data.path=null"] + overrides
    trace = simulate(load_config(ROOT / config_path, common))
    config = load_config(ROOT / config_path, common + [f"model.effects={effects}", "sample.separation=null"])
    started = time.perf_counter()
    result = run_fit(config, trace=trace)
    seconds = time.perf_counter() - started
    d_true = float(trace.truth.extra["separation"])
    est = result.nonlinear["d"]
    return {"error": est.value - d_true, "sigma": est.sigma, "seconds": seconds}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1,2,3,4")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    covered = total = 0
    print("| operating point | seed | d error pm | reported sigma pm | error / sigma | fit s |")
    print("|---|---|---|---|---|---|")
    for name, path, effects, overrides in OPERATING_POINTS:
        for seed in seeds:
            row = fit_one(path, effects, overrides, seed)
            ratio = abs(row["error"]) / row["sigma"] if row["sigma"] > 0 else math.inf
            ok = ratio < 2
            covered += ok
            total += 1
            print(f"| {name} | {seed} | {row['error'] * 1e12:+.2f} | {row['sigma'] * 1e12:.3f} | {ratio:.2f} | "
                  f"{row['seconds']:.1f} |", flush=True)
            if args.json:
                with args.json.open("a") as fh:
                    fh.write(json.dumps({"point": name, "seed": seed, **row}) + "\n")
    print(f"\n|d - d_true| < 2 sigma in {covered}/{total} fits ({100 * covered / total:.0f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
