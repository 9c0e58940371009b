"""The cross-validated error of a right model over its noise floor, on many clean traces (issue 13 false alarms).

A clean trace (the simulator's DMT sample, fitted with ``model.effects: [dmt]``, separation NOT given) is
fitted by a model that has every force there is: its cross-validated error should sit at the noise floor, at a
ratio of about 1 with a spread set by the noise alone. For each trace (seeds, lengths, samples per period,
detector and thermal noise levels, noise-free, transients from rest and from free oscillation) this prints one
JSON line: the fit's cv error, its noise floor as afmid computes it (``floor``), and, recomputed from the fit's
own system, the held-out periods' predicted noise alone (the floor before issue 13's audit, without the noise
of the model fitted on the other periods) and the measured one (the scatter of the held-out residual from
period to period), the ratio of predicted to measured per-period noise, and the effective degrees of freedom
nu of the error's noise sum (nu = (sum s)^2 / sum s^2 over the weighted noise variances s of its terms: for a
right model error^2 / floor^2 ~ chi2_nu / nu).

    python scripts/floor_study.py --out floor.jsonl [--quick]
    python scripts/floor_study.py --table floor.jsonl
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "scripts"))


def traces(quick: bool) -> list[tuple[str, dict]]:
    """(name, raw config) of the clean traces, fixed before the results were seen."""
    from experiment_table import _transient

    from afmid.config import apply_overrides, parse_override, read_yaml

    base = read_yaml(ROOT / "tests" / "configs" / "hidden_clean.yaml")
    samples = [  # (E*, H, d, seed)
        (2.0e9, 5.0e-20, 8.5e-9), (3.0e9, 4.0e-20, 8.5e-9), (1.5e9, 6.0e-20, 8.0e-9), (5.0e9, 5.0e-20, 8.0e-9)]
    settings = [  # (periods, samples per period, detector rms, thermal)
        (50, 200, 1e-12, True), (100, 200, 1e-12, True), (50, 50, 1e-12, True), (50, 100, 3e-12, True),
        (50, 200, 0.0, True), (50, 200, 1e-12, False), (200, 100, 1e-12, True), (50, 50, 1e-11, True),
        (50, 200, 0.0, False)]
    out = []
    seed = 300
    for periods, spp, rms, thermal in settings:
        for E, H, d in (samples[:2] if quick else samples):
            seed += 1
            raw = apply_overrides(copy.deepcopy(base), [parse_override(o) for o in (
                f"simulate.parameters.E_star={E}", f"simulate.parameters.hamaker={H}", f"sample.separation={d}",
                f"simulate.periods={periods}", f"simulate.samples_per_period={spp}",
                f"simulate.noise.detector_rms={rms}", f"simulate.noise.thermal={'true' if thermal else 'false'}",
                f"simulate.seed={seed}")])
            out.append((f"steady {periods}p {spp}spp {rms * 1e12:g}pm {'thermal' if thermal else 'no thermal'} "
                        f"E{E / 1e9:g} seed{seed}", raw))
    transients = [_transient(250, 10e-9, 6.5e-9, 300e3, 120, 200, "rest", 401),
                  _transient(120, 15e-9, 9e-9, 299.4e3, 80, 100, "rest", 402),
                  _transient(250, 10e-9, 4.5e-9, 300e3, 100, 200, "free", 403),
                  _transient(400, 8e-9, 5e-9, 300.6e3, 150, 50, "rest", 404)]
    for raw in (transients[:2] if quick else transients):
        s = raw["simulate"]
        out.append((f"transient from {s['transient_start']} {s['periods']}p {s['samples_per_period']}spp "
                    f"Q{raw['cantilever']['quality_factor']:g} seed{s['seed']}", raw))
    return out


def floors(result) -> dict:
    """The predicted and the measured noise floor of ``result``'s cv error, from its own system."""
    import afmid.fit.regression as regression

    prep, system, mask, rows = result.prep, result.system, result.selected, result.signal_rows
    harmonics = prep.blocks.harmonics
    w = np.where(harmonics == 0, 1.0, 0.5)
    p = system.theta.shape[2]
    folds = regression.fold_slices(system.T_blocks.shape[0], result.config.fit.folds)
    residuals, keeps, sizes = [], [], []
    den = predicted = fourth = 0.0
    for test in folds:
        train = regression.training_blocks(system.T_blocks.shape[0], test)
        coef, _ = regression.subset_fit(regression.combine(system.T_blocks[train]), mask)
        free_b = prep.Y[test] - np.einsum("bkm,m->bk", prep.nuisance[test], coef[p:])
        model_b = np.einsum("bkm,m->bk", system.theta[test], coef[:p])
        free = free_b.mean(axis=0)
        sigma = prep.row_sigma / math.sqrt(test.size)
        keep = rows & (np.abs(free) > 3 * sigma)
        for n in np.unique(harmonics[keep]):
            keep[harmonics == n] = True
        residuals.append(free_b - model_b)
        keeps.append(keep)
        sizes.append(test.size)
        den += float(np.sum((w * np.where(harmonics == 0, 0.0, free) ** 2)[keep]))
        predicted += float(np.sum((w * sigma**2)[keep]))
        fourth += float(np.sum(((w * sigma**2)[keep]) ** 2))
    # Measured per-period noise of each row: successive differences within each fold (slow changes cancel).
    diffs = np.concatenate([np.diff(r, axis=0) for r in residuals if r.shape[0] > 1])
    measured_var = np.mean(diffs**2, axis=0) / 2
    plain_var = np.concatenate([r - r.mean(axis=0) for r in residuals]).var(axis=0) * (
        sum(sizes) / max(sum(sizes) - len(sizes), 1))
    measured = sum(float(np.sum((w * measured_var / n)[k])) for k, n in zip(keeps, sizes))
    plain = sum(float(np.sum((w * plain_var / n)[k])) for k, n in zip(keeps, sizes))
    union = np.any(keeps, axis=0)
    return {"floor_predicted": math.sqrt(predicted / den), "floor_measured": math.sqrt(measured / den),
            "floor_plain": math.sqrt(plain / den),
            "noise_ratio": float(np.sum((w * prep.row_sigma**2)[union]) / np.sum((w * measured_var)[union])),
            "kept_rows": int(np.mean([k.sum() for k in keeps])), "nu_eff": predicted**2 / fourth}


def measure(name: str, raw: dict, folder: Path) -> dict:
    from afmid.config import build_config, dump_config
    from afmid.fit.pipeline import run_fit
    from afmid.io.trace import write_trace_file
    from afmid.simulate.driver import simulate

    folder = Path(tempfile.mkdtemp(dir=folder))
    sim_config = build_config(raw, source=folder / "sim.yaml", base_dir=folder)
    trace = simulate(sim_config)
    write_trace_file(folder / "t.h5", trace, dump_config(sim_config))
    fit_raw = copy.deepcopy(raw)
    fit_raw["data"] = {"path": str(folder / "t.h5")}
    fit_raw["simulate"]["parameters"] = {}
    fit_raw["sample"]["separation"] = None
    fit_raw.setdefault("fit", {})["bootstrap"] = 0
    result = run_fit(build_config(fit_raw, source=folder / "fit.yaml", base_dir=folder), uncertainty=False)
    entry = {"trace": name, "error": result.cv_error, "floor": result.cv_error_noise_floor, **floors(result)}
    entry["ratio"] = entry["error"] / entry["floor"]
    entry["ratio_predicted"] = entry["error"] / entry["floor_predicted"]
    entry["ratio_measured"] = entry["error"] / entry["floor_measured"]
    return entry


def table(rows: list[dict]) -> str:
    out = ["| clean trace | cv error | floor (afmid) | ratio | predicted floor: ratio | measured floor: ratio | "
           "predicted / measured noise | kept rows | nu_eff |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['trace']} | {r['error']:.4g} | {r['floor']:.4g} | {r['ratio']:.3f} | "
                   f"{r['floor_predicted']:.4g}: {r['ratio_predicted']:.3f} | {r['floor_measured']:.4g}: "
                   f"{r['ratio_measured']:.3f} | {r['noise_ratio']:.3f} | {r['kept_rows']} | {r.get('nu_eff', math.nan):.1f} |")
    for key in ("ratio", "ratio_predicted", "ratio_measured"):
        v = np.array([r[key] for r in rows])
        out.append(f"\n{key}: n {v.size}, mean {v.mean():.3f}, sd {v.std(ddof=1):.3f}, min {v.min():.3f}, "
                   f"max {v.max():.3f}, above 1.3: {int(np.sum(v > 1.3))}")
    return "\n".join(out)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--table", type=Path)
    args = parser.parse_args(argv)
    if args.table:
        print(table([json.loads(line) for line in args.table.read_text().splitlines() if line.strip()]))
        return 0
    done = set()
    if args.out and args.out.exists():
        done = {json.loads(line)["trace"] for line in args.out.read_text().splitlines() if line.strip()}
    with tempfile.TemporaryDirectory() as tmp:
        for name, raw in traces(args.quick):
            if name in done:
                continue
            try:
                entry = measure(name, raw, Path(tmp))
            except Exception as exc:  # record and go on
                entry = {"trace": name, "failed": repr(exc)}
            print(json.dumps(entry), flush=True)
            if args.out:
                with args.out.open("a") as fh:
                    fh.write(json.dumps(entry) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
