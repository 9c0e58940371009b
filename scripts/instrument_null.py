"""The undeclared-detector search on clean traces: the null of its screen and its false alarms (issue 13).

For clean traces of an ideal instrument (tests/configs/hidden_clean.yaml with test_diagnose's CLEAN variants a-c,
seeds 61 / 62 / 63 + 100 j), the separation NOT given: fit with ``model.effects: [dmt]``, write the run file,
refit as the diagnosis does, and print the chi-square the low-pass shape removes from the residual
(afmid.diagnosis.instrument_signature.screen: the statistic DETECTOR_SCREEN_CHI2 thresholds), then run the
instrument search with the detector screen forced open (threshold 0: the refits run on every trace) and print
what it finds. A finding here is a false alarm the screen's threshold alone would have to prevent.

    python scripts/instrument_null.py --from 0 --to 4 --out null.jsonl         # screen statistic only
    python scripts/instrument_null.py --from 0 --to 2 --search --out s.jsonl   # and the forced-open search

Run from the repository root.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests" / "support"))
sys.path.insert(0, str(ROOT))


def measure(overrides: list[str], search: bool, folder: Path) -> dict:
    import afmid.diagnosis.diagnose as diagnose
    import afmid.diagnosis.instrument_signature as signature
    from afmid.config import apply_overrides, build_config, dump_config, parse_override, read_yaml
    from afmid.fit.pipeline import run_fit
    from afmid.fit.prepare import prepare
    from afmid.runfile import write_run
    from afmid.io.trace import load_trace, write_trace_file
    from afmid.preprocess.instrument import from_config
    from afmid.simulate.driver import simulate

    raw = apply_overrides(read_yaml(ROOT / "tests" / "configs" / "hidden_clean.yaml"),
                          [parse_override(o) for o in overrides + ["fit.bootstrap=0"]])
    sim = build_config(raw, source=folder / "sim.yaml", base_dir=folder)
    trace = simulate(sim)
    write_trace_file(folder / "trace.h5", trace, dump_config(sim))
    raw["data"] = {"path": str(folder / "trace.h5")}
    raw["simulate"]["parameters"] = {}
    raw["sample"]["separation"] = None
    config = build_config(raw, source=folder / "fit.yaml", base_dir=folder)
    started = time.process_time()
    result = run_fit(config, uncertainty=False)
    s = signature.screen(result, trace.cantilever, result.prep.drive.frequency)
    entry = {"chi2": s.chi2, "dof": s.dof, "detector_chi2": s.detector_chi2, "mode_chi2": s.mode_chi2,
             "error_over_floor": result.cv_error / result.cv_error_noise_floor}
    if search:
        write_run(folder / "run.h5", result, config)
        run = diagnose.load_run(folder / "run.h5")
        base_config = diagnose.refit_config(run, run.effects)
        prepared = prepare(load_trace(base_config), base_config.fit, from_config(base_config))
        base = diagnose._fit_quick(base_config, prepared)
        signature.DETECTOR_SCREEN_CHI2 = 0.0  # the study: the detector refits on every trace
        finding = signature.undeclared(base_config, prepared, base, base.selection.best.bic, [],
                                       diagnose._fit_quick, diagnose.BIC_EVIDENCE, diagnose.BIC_DISTINCT, True)
        entry["finding"] = finding.record() if finding else None
    entry["cpu_seconds"] = time.process_time() - started
    return entry


def main(argv=None) -> int:
    from tests.diagnosis.test_diagnose import CLEAN

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--from", dest="first", type=int, default=0)
    parser.add_argument("--to", type=int, default=4)
    parser.add_argument("--search", action="store_true", help="also run the search with the screen forced open")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    for j in range(args.first, args.to):
        for variant, overrides in CLEAN.items():
            seed = {"a": 61, "b": 62, "c": 63}[variant] + 100 * j
            chosen = [o for o in overrides if not o.startswith("simulate.seed")] + [f"simulate.seed={seed}"]
            with tempfile.TemporaryDirectory() as tmp:
                entry = {"variant": variant, "seed": seed, **measure(chosen, args.search, Path(tmp))}
            print(json.dumps(entry), flush=True)
            if args.out:
                with args.out.open("a") as fh:
                    fh.write(json.dumps(entry) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
