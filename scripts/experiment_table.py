"""Issue 13's table re-measured with the separation NOT given (the normal experimental case).

Every row of the issue's table (hidden electrostatic 3 V at 200 and 50 samples/period; hidden viscoelastic /
exponential damping / capillary / hydration; a transient from rest, clean and with hidden viscoelasticity; a
2-pole detector low-pass at 10 f0, alone and with hidden viscoelasticity, undeclared and declared; a second
flexural mode at 6.27 f0, undeclared and declared; 10 pm detector noise at 50 samples/period, clean and with
hidden viscoelasticity; a soft lever in liquid at Q 4), each on three variants (seeds and parameters fixed
before the results were seen). For each trace: simulate, fit with ``model.effects: [dmt]`` and
``sample.separation`` absent, write the run file, diagnose (afmid.diagnosis.diagnose.suggest), and when a sample effect
is named, refit with it added (separation still estimated). Printed: what afmid says (the named effect or
instrument and the verdict), the force error vs the simulator's truth (RMS over the estimated samples / the
largest |true force|, % of the peak) and the cross-validated error over its noise floor, each for the [dmt]
fit and with the named effect.

    python scripts/experiment_table.py --out table.jsonl          # all rows, three variants each
    python scripts/experiment_table.py --quick --out quick.jsonl  # one variant per row
    python scripts/experiment_table.py --table table.jsonl        # the markdown table of a finished run
    python scripts/experiment_table.py --seed-offset 500 --out new.jsonl  # the same rows on new noise

Run from the repository root (PYTHONPATH=other/checkout measures another version with the same traces).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# The tests package (tests.diagnosis.test_diagnose holds the variants) and its helpers (tests/support).
sys.path.insert(0, str(ROOT / "tests" / "support"))
sys.path.insert(0, str(ROOT))

DETECTOR = "data.detector={bandwidth: 3.0e6, filter: butterworth, order: 2}"  # 2-pole low-pass at 10 f0
SECOND_MODE = "cantilever.higher_modes=[{resonance_frequency: 1.881e6, quality_factor: 750, spring_constant: 1572}]"
#: Added to every trace's simulator seed (--seed-offset): the same rows on other noise realisations.
SEED_OFFSET = 0
NOISY = ["simulate.noise.detector_rms=1.0e-11", "simulate.samples_per_period=50"]  # 10 pm, 50 samples/period


def _transient(Q, A0, d, drive, periods, spp, start, seed, effects=(), **parameters) -> dict:
    """A record of the transient into tapping (tests/preprocess/test_transient.py's shape)."""
    return {
        "cantilever": {"spring_constant": 40.0, "resonance_frequency": 300e3, "quality_factor": Q, "tip_radius": 10e-9},
        "drive": {"frequency": drive, "free_amplitude": A0},
        "sample": {"separation": d, "a0": 0.165e-9},
        "model": {"effects": ["dmt"]},
        "fit": {"bootstrap": 0},
        "simulate": {"model": "dmt", "effects": list(effects),
                     "parameters": {"E_star": 1.5e9, "hamaker": 8e-20, **parameters}, "mode": "transient",
                     "transient_start": start, "periods": periods, "samples_per_period": spp,
                     "steps_per_period": 2000, "seed": seed,
                     "noise": {"thermal": True, "temperature": 300.0, "detector_rms": 1e-12}},
    }


def _liquid(d, seed, E_star=50e6) -> dict:
    """A soft lever in liquid: k 0.8 N/m, f0 25 kHz, Q 4, a soft sample, 5 pm detector noise."""
    return {
        "cantilever": {"spring_constant": 0.8, "resonance_frequency": 25e3, "quality_factor": 4.0, "tip_radius": 10e-9},
        "drive": {"frequency": 25e3, "free_amplitude": 5e-9},
        "sample": {"separation": d, "a0": 0.165e-9},
        "model": {"effects": ["dmt"]},
        "fit": {"bootstrap": 0},
        "simulate": {"model": "dmt", "effects": [], "parameters": {"E_star": E_star, "hamaker": 1e-20},
                     "mode": "steady", "periods": 50, "samples_per_period": 200, "steps_per_period": 2000,
                     "seed": seed, "noise": {"thermal": True, "temperature": 300.0, "detector_rms": 5e-12}},
    }


@dataclass
class Case:
    """One trace: a base config (a tests/configs name or a raw dict), simulator overrides, the instrument the
    simulator has, whether the fit declares it, and what afmid should name (None: nothing)."""
    row: str
    variant: str
    base: str | dict
    overrides: list[str] = field(default_factory=list)
    instrument: list[str] = field(default_factory=list)
    declared: bool = False
    expected: str | None = None


def _hidden(effect: str) -> dict[str, list[str]]:
    from tests.diagnosis.test_diagnose import VARIANTS

    return {v: VARIANTS[effect][v] for v in ("a", "b", "c")}


def cases() -> list[Case]:
    from tests.diagnosis.test_diagnose import CLEAN

    out: list[Case] = []
    volts = {"a": ["simulate.seed=35"],
             "b": ["simulate.seed=37", "simulate.parameters.E_star=2.0e9", "simulate.parameters.hamaker=5.0e-20"],
             "c": ["simulate.seed=38", "sample.separation=8.0e-9", "simulate.parameters.E_star=1.5e9"]}
    for spp, bump in ((200, 0), (50, 10)):
        for v, o in volts.items():
            seed = int(o[0].split("=")[1]) + bump
            out.append(Case(f"hidden electrostatic 3 V, {spp} samples/period", v, "hidden_electrostatic",
                            ["simulate.parameters.voltage=3.0", f"simulate.samples_per_period={spp}",
                             f"simulate.seed={seed}"] + o[1:], expected="electrostatic"))
    for effect in ("viscoelastic", "exponential_damping", "capillary", "hydration"):
        for v, o in _hidden(effect).items():
            out.append(Case(f"hidden {effect}", v, f"hidden_{effect}", o, expected=effect))
    rest = {"a": _transient(250, 10e-9, 6.5e-9, 300e3, 120, 200, "rest", 11),
            "b": _transient(120, 15e-9, 9e-9, 299.4e3, 80, 100, "rest", 12),
            "c": _transient(400, 8e-9, 5e-9, 300.6e3, 150, 50, "rest", 14)}
    for v, raw in rest.items():
        out.append(Case("transient from rest", v, raw))
    visco = {"a": _transient(250, 10e-9, 6.5e-9, 300e3, 120, 200, "rest", 15, ["viscoelastic"], viscosity=150.0),
             "b": _transient(120, 15e-9, 9e-9, 299.4e3, 80, 100, "rest", 16, ["viscoelastic"], viscosity=80.0),
             "c": _transient(250, 10e-9, 6.0e-9, 300e3, 120, 100, "rest", 17, ["viscoelastic"], viscosity=300.0)}
    for v, raw in visco.items():
        out.append(Case("transient from rest, hidden viscoelastic", v, raw, expected="viscoelastic"))
    for declared in (False, True):
        word = "declared" if declared else "undeclared"
        for v, o in CLEAN.items():
            out.append(Case(f"detector 2-pole 10 f0, {word}", v, "hidden_clean", list(o), [DETECTOR], declared,
                            None if declared else "instrument"))
        for v, o in _hidden("viscoelastic").items():
            out.append(Case(f"detector 2-pole 10 f0 + hidden viscoelastic, {word}", v, "hidden_viscoelastic", o,
                            [DETECTOR], declared, "viscoelastic"))
        for v, o in CLEAN.items():
            out.append(Case(f"second mode f2 = 6.27 f0, {word}", v, "hidden_clean", list(o), [SECOND_MODE], declared,
                            None if declared else "instrument"))
    for v, o in CLEAN.items():
        out.append(Case("10 pm detector noise, 50 samples/period", v, "hidden_clean", list(o) + NOISY))
    for v, o in _hidden("viscoelastic").items():
        out.append(Case("10 pm detector noise, 50 samples/period, hidden viscoelastic", v, "hidden_viscoelastic",
                        o + NOISY, expected="viscoelastic"))
    for v, (d, seed) in zip("abc", ((4.0e-9, 1), (3.5e-9, 2), (3.0e-9, 3))):
        out.append(Case("low Q liquid (Q 4, k 0.8 N/m)", v, _liquid(d, seed)))
    return out


def force_error(result, trace) -> float:
    import numpy as np

    truth = trace.truth.force
    used = np.isfinite(result.force_estimate)
    peak = float(np.abs(truth[used]).max())
    return float(np.sqrt(np.mean((result.force_estimate[used] - truth[used]) ** 2)) / peak)


def _raw(case: Case, with_instrument: bool) -> dict:
    from afmid.config import apply_overrides, parse_override, read_yaml

    base = (copy.deepcopy(case.base) if isinstance(case.base, dict)
            else read_yaml(ROOT / "tests" / "configs" / f"{case.base}.yaml"))
    overrides = case.overrides + (case.instrument if with_instrument else [])
    raw = apply_overrides(base, [parse_override(o) for o in overrides])
    raw["simulate"]["seed"] = int(raw["simulate"].get("seed", 0)) + SEED_OFFSET
    return raw


def measure(case: Case, folder: Path) -> dict:
    import afmid.diagnosis.diagnose as diagnose
    from afmid.config import build_config, dump_config
    from afmid.fit.pipeline import run_fit
    from afmid.runfile import write_run
    from afmid.io.trace import write_trace_file
    from afmid.simulate.driver import simulate

    key = f"{case.row}-{case.variant}".replace(" ", "_").replace("/", "")
    sim_config = build_config(_raw(case, True), source=folder / f"{key}.yaml", base_dir=folder)
    trace = simulate(sim_config)
    trace_path = folder / f"{key}.h5"
    write_trace_file(trace_path, trace, dump_config(sim_config))
    fit_raw = _raw(case, case.declared)
    fit_raw["data"] = {**fit_raw.get("data", {}), "path": str(trace_path)}
    fit_raw["simulate"]["parameters"] = {}
    fit_raw["sample"]["separation"] = None
    fit_raw.setdefault("fit", {})["bootstrap"] = 0
    config = build_config(fit_raw, source=folder / f"{key}.yaml", base_dir=folder)
    started = time.perf_counter()
    result = run_fit(config, uncertainty=False)
    write_run(folder / f"{key}.run.h5", result, config)
    summary = diagnose.suggest(diagnose.load_run(folder / f"{key}.run.h5"))
    named = [s["effect"] for s in summary["suggestions"]]
    diagnosis = summary["diagnosis"]
    instrument = diagnosis.get("instrument")
    entry = {"row": case.row, "variant": case.variant, "expected": case.expected, "named": named,
             "instrument": instrument.get("kind") if isinstance(instrument, dict) else None,
             "verdict": diagnosis["verdict"], "compared": summary.get("compared_with_best"),
             "tried": [{k: t[k] for k in ("effect", "delta_bic", "significant", "explains_residual")}
                       for t in summary["tried"]],
             "error": result.cv_error, "floor": result.cv_error_noise_floor,
             "force": force_error(result, trace)}
    entry["undecided"] = [t["effect"] for t in summary.get("undecided", [])]
    refit = named or entry["undecided"][:1]  # undecided: the force error with the candidate ranked first
    if refit:
        after_config = copy.deepcopy(config)
        after_config.model.effects = list(config.model.effects) + refit
        after = run_fit(after_config, uncertainty=False)
        entry.update(error_after=after.cv_error, floor_after=after.cv_error_noise_floor,
                     force_after=force_error(after, trace))
    entry["seconds"] = time.perf_counter() - started
    return entry


def _undecided(r: dict) -> list[str]:
    """The candidates the data cannot tell apart, ranked by BIC (from the comparisons for older lines)."""
    if "undecided" in r:
        return r["undecided"]
    if not r["verdict"].startswith("missing effect, but the data cannot decide") or not r.get("compared"):
        return []
    return [r["compared"]["best"]] + [c["effect"] for c in r["compared"]["rivals"] if not c["told_apart"]]


def _says(r: dict) -> str:
    verdict = r["verdict"]
    if _undecided(r):
        return "cannot decide: " + ", ".join(_undecided(r))
    if r["instrument"]:
        return verdict.split(" (")[0]
    if r["named"]:
        kind = "missing effect" if verdict.startswith("missing effect") else "part"
        return f"{', '.join(r['named'])} ({kind})"
    if verdict.startswith("no effect"):
        return "no effect is missing"
    return "not explained" if "not explained" in verdict or "no catalog effect" in verdict else verdict[:60]


def _right(r: dict) -> bool:
    if r["expected"] is None:
        return not r["named"] and not r["instrument"] and r["verdict"].startswith("no effect")
    if r["expected"] == "instrument":
        return bool(r["instrument"])
    return bool(r["named"]) and r["named"][0] == r["expected"]


def _first_undecided(r: dict) -> bool:
    """The data cannot decide, and the true effect ranks first among the candidates."""
    return r["expected"] not in (None, "instrument") and _undecided(r)[:1] == [r["expected"]]


def table(rows: list[dict]) -> str:
    out = ["| trace (separation not given) | variant | afmid says | right? | force error % of peak: [dmt] -> "
           "with the named effect | cv error / floor: [dmt] -> with it |", "|---|---|---|---|---|---|"]
    for r in rows:
        if "failed" in r:
            out.append(f"| {r['row']} | {r['variant']} | FAILED: {r['failed'][:80]} | | | |")
            continue
        force = f"{100 * r['force']:.2f}" + (f" -> {100 * r['force_after']:.2f}" if "force_after" in r else "")
        ratio = f"{r['error'] / r['floor']:.2f}" + (
            f" -> {r['error_after'] / r['floor_after']:.2f}" if "error_after" in r else "")
        right = "yes" if _right(r) else "first, undecided" if _first_undecided(r) else "NO"
        out.append(f"| {r['row']} | {r['variant']} | {_says(r)} | {right} | {force} | {ratio} |")
    ok = [r for r in rows if "failed" not in r]
    hidden = [r for r in ok if r["expected"] not in (None, "instrument")]
    clean = [r for r in ok if r["expected"] is None]
    out.append(f"\nhidden effects named first: {sum(map(_right, hidden))}/{len(hidden)} (and ranked first where the data "
               f"cannot decide: {sum(map(_first_undecided, hidden))}); clean traces without alarm: "
               f"{sum(map(_right, clean))}/{len(clean)}; undeclared instruments named: "
               f"{sum(_right(r) for r in ok if r['expected'] == 'instrument')}/"
               f"{sum(r['expected'] == 'instrument' for r in ok)}; failed: {len(rows) - len(ok)}")
    return "\n".join(out)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="append one JSON line per trace (resumes: done traces are skipped)")
    parser.add_argument("--quick", action="store_true", help="one variant per row")
    parser.add_argument("--only", help="rows whose name contains this")
    parser.add_argument("--table", type=Path, help="print the markdown table of a finished --out file")
    parser.add_argument("--seed-offset", type=int, default=0,
                        help="add this to every simulator seed (the same rows on new noise)")
    args = parser.parse_args(argv)
    global SEED_OFFSET
    SEED_OFFSET = args.seed_offset
    if args.table:
        print(table([json.loads(line) for line in args.table.read_text().splitlines() if line.strip()]))
        return 0
    chosen = [c for c in cases() if (not args.quick or c.variant == "a") and (not args.only or args.only in c.row)]
    done = set()
    if args.out and args.out.exists():
        done = {(r["row"], r["variant"]) for r in map(json.loads, args.out.read_text().splitlines()) if r}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for case in chosen:
            if (case.row, case.variant) in done:
                continue
            try:
                entry = measure(case, Path(tmp))
            except Exception as exc:  # record and go on: one failing trace must not stop the measurement
                entry = {"row": case.row, "variant": case.variant, "expected": case.expected, "failed": repr(exc)}
            rows.append(entry)
            print(json.dumps(entry), file=sys.stderr, flush=True)
            if args.out:
                with args.out.open("a") as fh:
                    fh.write(json.dumps(entry) + "\n")
    if args.out:
        rows = [json.loads(line) for line in args.out.read_text().splitlines() if line.strip()]
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
