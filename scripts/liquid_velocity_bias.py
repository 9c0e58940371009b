"""The thermal force's bias of a velocity-dependent term in liquid (docs/accuracy.md, "The thermal force and
velocity-dependent terms in liquid"): a Kelvin-Voigt sample (tests/configs/liquid.yaml with
``model.effects: [dmt, viscoelastic]``, the simulator's viscoelastic effect, eta 100 Pa s, 50 periods, bootstrap
50) on two levers, seeds 1-6 (fixed in session 11, before the correction existed):

- ``Q4``: liquid.yaml's lever (k 0.8 N/m, f0 25 kHz, Q 4);
- ``Q2``: k 0.3 N/m, Q 2, f0 and the drive at 15 kHz (session 11's soft lever; the rest as liquid.yaml).

Each trace is fitted with the separation given and estimated. Printed per lever and case: eta's mean relative
error, mean z and rms z, z = (eta - truth) / sigma (sigma: the fit's bootstrap error), and one line per fit.

    python scripts/liquid_velocity_bias.py                        # both levers, seeds 1-6
    python scripts/liquid_velocity_bias.py --levers Q2 --seeds 1-3 --thermal-off
    python scripts/liquid_velocity_bias.py --out after.jsonl      # one JSON line per fit as well

``--thermal-off`` switches the simulator's thermal force off and tells the fit so (``fit.thermal_noise: false``).
Run from the repository root (PYTHONPATH=other/checkout measures another version with the same traces).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

from afmid.config import apply_overrides, build_config, dump_config, parse_override, read_yaml  # noqa: E402
from afmid.fit.pipeline import run_fit  # noqa: E402
from afmid.io.trace import write_trace_file  # noqa: E402
from afmid.simulate.driver import simulate  # noqa: E402

LEVERS = {
    "Q4": [],
    "Q2": ["cantilever.quality_factor=2.0", "cantilever.spring_constant=0.3",
           "cantilever.resonance_frequency=15.0e3", "drive.frequency=15.0e3"],
}


def case_config(lever: str, seed: int, viscosity: float, periods: int, bootstrap: int, thermal: bool) -> dict:
    """The raw configuration (simulation and fit) of one trace."""
    raw = read_yaml(ROOT / "tests" / "configs" / "liquid.yaml")
    overrides = LEVERS[lever] + [
        "model.effects=[dmt, viscoelastic]", "simulate.effects=[viscoelastic]",
        f"simulate.parameters.viscosity={viscosity}", f"simulate.seed={seed}", f"simulate.periods={periods}",
        "sample.medium=liquid", f"fit.bootstrap={bootstrap}",
    ]
    if not thermal:
        overrides += ["simulate.noise.thermal=false", "fit.thermal_noise=false"]
    return apply_overrides(copy.deepcopy(raw), [parse_override(o) for o in overrides])


def fit_viscosity(raw: dict, trace_path: Path, folder: Path, separation_given: bool) -> dict:
    """eta (Pa s) and its 1 sigma from one fit of the trace."""
    fit_raw = copy.deepcopy(raw)
    fit_raw["data"] = {"path": str(trace_path)}
    fit_raw["simulate"]["parameters"] = {}
    if not separation_given:
        fit_raw["sample"]["separation"] = None
    config = build_config(fit_raw, source=folder / "fit.yaml", base_dir=folder)
    start = time.process_time()
    result = run_fit(config, uncertainty=True)
    seconds = time.process_time() - start
    q = result.quantities.get("viscosity")
    e_star = result.quantities.get("E_star") or {}
    others = {"E_star": e_star.get("value"), "E_star_error": e_star.get("error")}
    if q is None:
        return {"value": None, "error": None, "cpu_s": seconds, **others}
    return {"value": float(q["value"]), "error": float(q["error"]), "cpu_s": seconds, **others}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--levers", nargs="+", default=list(LEVERS), choices=list(LEVERS))
    parser.add_argument("--seeds", default="1-6", help="first-last")
    parser.add_argument("--viscosity", type=float, default=100.0, help="Pa s, the simulated sample's eta")
    parser.add_argument("--periods", type=int, default=50)
    parser.add_argument("--bootstrap", type=int, default=50)
    parser.add_argument("--thermal-off", action="store_true")
    parser.add_argument("--cases", nargs="+", default=["given", "estimated"], choices=["given", "estimated"])
    parser.add_argument("--out", type=Path, help="JSON lines, one per fit")
    args = parser.parse_args(argv)
    first, last = (int(s) for s in args.seeds.split("-")) if "-" in args.seeds else (int(args.seeds),) * 2
    seeds = range(first, last + 1)
    folder = Path(tempfile.mkdtemp(prefix="liquid_velocity_bias_"))
    out = args.out.open("w") if args.out else None
    rows = []
    for lever in args.levers:
        for seed in seeds:
            raw = case_config(lever, seed, args.viscosity, args.periods, args.bootstrap, not args.thermal_off)
            sim = build_config(copy.deepcopy(raw), source=folder / "sim.yaml", base_dir=folder)
            path = folder / f"{lever}_{seed}.h5"
            write_trace_file(path, simulate(sim), dump_config(sim))
            for case in args.cases:
                r = fit_viscosity(raw, path, folder, case == "given")
                row = {"lever": lever, "seed": seed, "case": case, "truth": args.viscosity,
                       "thermal": not args.thermal_off, **r}
                rows.append(row)
                if out:
                    out.write(json.dumps(row) + "\n")
                    out.flush()
                if r["value"] is None:
                    print(f"{lever} seed {seed} {case:9s}: no viscosity term selected", flush=True)
                    continue
                z = (r["value"] - args.viscosity) / r["error"]
                print(f"{lever} seed {seed} {case:9s}: eta {r['value']:7.2f} +- {r['error']:5.2f} Pa s  z {z:+.2f}"
                      f"  E* {r['E_star'] / 1e6:6.2f} MPa  ({r['cpu_s']:.1f} s CPU in this process)", flush=True)
    print()
    print(f"{'lever':5s} {'separation':10s} {'n':>2s} {'mean rel. error':>15s} {'mean z':>7s} {'rms z':>6s}")
    for lever in args.levers:
        for case in args.cases:
            got = [r for r in rows if r["lever"] == lever and r["case"] == case and r["value"] is not None]
            if not got:
                continue
            rel = np.array([(r["value"] - r["truth"]) / r["truth"] for r in got])
            z = np.array([(r["value"] - r["truth"]) / r["error"] for r in got])
            print(f"{lever:5s} {case:10s} {len(got):2d} {100 * rel.mean():+14.2f}% {z.mean():+7.2f} "
                  f"{np.sqrt(np.mean(z**2)):6.2f}")


if __name__ == "__main__":
    main()
