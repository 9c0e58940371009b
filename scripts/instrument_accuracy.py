"""Force error with the instrument declared, the rest separation NOT given (issue 13 part 3).

Traces from tests/configs/hidden_clean.yaml (DMT, E* 2 GPa, A0 10 nm, k 40 N/m, f0 300 kHz, Q 250, thermal noise
at 300 K) through a declared detector (filter, order, bandwidth in units of f0, detector noise) or with a declared
second mode; fitted with ``model.effects: [dmt]``, ``sample.separation`` absent. One JSON line per trace: the force
error (RMS of estimated - true force over the estimated samples / peak), the separation error, the verdict of the
diagnosis when ``--diagnose`` is given (0 false alarms expected on these clean traces).

    python scripts/instrument_accuracy.py --out after.jsonl [--diagnose] [--only butterworth]
    python scripts/instrument_accuracy.py --table after.jsonl [before.jsonl]

Run from the repository root.
"""

from __future__ import annotations

import argparse
import copy
import json
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
F0 = 300e3

#: (name, detector filter, order, bandwidth / f0, detector noise m, seeds): fixed before the runs.
DETECTORS = [
    ("butterworth2-10f0-1pm", "butterworth", 2, 10, 1e-12, (101, 102, 103)),
    ("butterworth2-5f0-1pm", "butterworth", 2, 5, 1e-12, (111, 112)),
    ("butterworth4-20f0-10pm", "butterworth", 4, 20, 10e-12, (121, 122)),
    ("bessel4-8f0-1pm", "bessel", 4, 8, 1e-12, (104, 131)),
    ("bessel2-15f0-5pm", "bessel", 2, 15, 5e-12, (132, 133)),
    ("first_order-5f0-1pm", "first_order", 1, 5, 1e-12, (141, 142)),
    ("first_order-20f0-10pm", "first_order", 1, 20, 10e-12, (143, 144)),
]
SECOND_MODE = ("cantilever.higher_modes=[{resonance_frequency: 1.881e6, quality_factor: 750, "
               "spring_constant: 1572}]")
MODES = [("mode2-6.27f0-1pm", [SECOND_MODE], (105, 106, 107))]
#: The ideal instrument on the same seeds and detector noise: what the noise alone allows with d unknown.
IDEAL = [("ideal-1pm", 1e-12, (101, 102, 141)), ("ideal-5pm", 5e-12, (132, 133)), ("ideal-10pm", 10e-12, (121, 143))]


def cases(only: str | None):
    out = []
    for name, kind, order, bw, noise, seeds in DETECTORS:
        overrides = [f"data.detector={{bandwidth: {bw * F0:.6g}, filter: {kind}, order: {order}}}",
                     f"simulate.noise.detector_rms={noise:.3g}"]
        out += [(name, overrides, seed) for seed in seeds]
    out += [(name, overrides, seed) for name, overrides, seeds in MODES for seed in seeds]
    out += [(name, [f"simulate.noise.detector_rms={noise:.3g}"], seed) for name, noise, seeds in IDEAL for seed in seeds]
    return [c for c in out if only is None or only in c[0]]


def measure(name: str, overrides: list[str], seed: int, folder: Path, diagnose_too: bool) -> dict:
    import numpy as np

    import afmid.diagnosis.diagnose as diagnose
    from afmid.config import apply_overrides, build_config, dump_config, parse_override, read_yaml
    from afmid.fit.pipeline import run_fit
    from afmid.runfile import write_run
    from afmid.io.trace import write_trace_file
    from afmid.simulate.driver import simulate

    raw = apply_overrides(read_yaml(ROOT / "tests" / "configs" / "hidden_clean.yaml"),
                          [parse_override(o) for o in overrides + [f"simulate.seed={seed}"]])
    key = f"{name}-{seed}"
    sim_config = build_config(raw, source=folder / f"{key}.yaml", base_dir=folder)
    trace = simulate(sim_config)
    trace_path = folder / f"{key}.h5"
    write_trace_file(trace_path, trace, dump_config(sim_config))
    fit_raw = copy.deepcopy(raw)
    fit_raw["data"] = {**fit_raw.get("data", {}), "path": str(trace_path)}
    fit_raw["simulate"]["parameters"] = {}
    fit_raw["sample"]["separation"] = None
    config = build_config(fit_raw, source=folder / f"{key}.yaml", base_dir=folder)
    started = time.perf_counter()
    result = run_fit(config, uncertainty=False)
    seconds = time.perf_counter() - started
    truth = trace.truth.force
    used = np.isfinite(result.force_estimate)
    error = float(np.sqrt(np.mean((result.force_estimate[used] - truth[used]) ** 2)) / truth[used].max())
    row = {"case": name, "seed": seed, "force_error": error,
           "d_error_pm": 1e12 * (result.nonlinear["d"].value - float(trace.truth.extra["separation"])),
           "seconds": round(seconds, 1)}
    # the same trace with the separation given: the error the declared instrument leaves when d is known
    given = run_fit(build_config({**fit_raw, "sample": raw["sample"]}, source=folder / f"{key}.yaml", base_dir=folder),
                    uncertainty=False)
    row["force_error_d_given"] = float(np.sqrt(np.mean((given.force_estimate[used] - truth[used]) ** 2))
                                       / truth[used].max())
    if diagnose_too:
        write_run(folder / f"{key}.run.h5", result, config)
        summary = diagnose.suggest(diagnose.load_run(folder / f"{key}.run.h5"))
        row["verdict"] = summary["diagnosis"]["verdict"]
        row["false_alarm"] = bool(summary["suggestions"]) or "instrument" in summary["diagnosis"]
    return row


def table(paths: list[str]) -> str:
    runs = [{(r["case"], r["seed"]): r for r in map(json.loads, Path(p).read_text().splitlines())} for p in paths]
    head = "| case | seed | " + " | ".join(f"force error ({Path(p).stem}), d unknown (given)" for p in paths) + " |"
    lines = [head, "|" + "---|" * (2 + len(paths))]

    def cell(row):
        given = row.get("force_error_d_given")
        return f"{100 * row['force_error']:.2f} %" + ("" if given is None else f" ({100 * given:.2f} %)")

    for key in runs[0]:
        cells = [cell(r[key]) if key in r else "-" for r in runs]
        lines.append(f"| {key[0]} | {key[1]} | " + " | ".join(cells) + " |")
        if "verdict" in runs[0][key]:
            lines[-1] += f" {runs[0][key]['verdict'][:60]} |"
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out")
    parser.add_argument("--only")
    parser.add_argument("--diagnose", action="store_true")
    parser.add_argument("--table", nargs="+")
    args = parser.parse_args()
    if args.table:
        print(table(args.table))
        return
    with tempfile.TemporaryDirectory() as tmp, open(args.out, "a") as out:
        for name, overrides, seed in cases(args.only):
            row = measure(name, overrides, seed, Path(tmp), args.diagnose)
            print(json.dumps(row), file=out, flush=True)
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
