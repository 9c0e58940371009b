"""Coverage of a separation track's d(t) over fixed seeds of scanning records (docs/lab/2026-11-29-scanning-record.md).

    .venv/bin/python docs/lab/scanning_coverage.py FOLDER SEEDS [--pool FOLDER2 SEEDS2 [--pool FOLDER3 SEEDS3 ...]] [--kinds step,rough]

SEEDS: a range "301-310" or a list "81,82,83". Reads what ``docs/lab/scanning_seeds.py 240 2500 rows KIND SEED``
left in FOLDER (its temp folder: the pickled trace with its truth and the track's run file) and prints, per record,
each block's z = (d - mean true d over the block) / sigma, E* and its z, and the force error (the fitted DMT law
against the true force at the true z(t), RMS over the samples, % of the peak true force); then over all the blocks
the fraction within 1 and 2 sigma with Wilson 95 % intervals, the rms z with its chi-square interval, the records
meeting the Done-when's numbers, and the same per noise seed (step and rough of a seed share the noise draw, and the
four blocks of a record share the law: the blocks are not independent draws; the per-seed mean z is).
"""
import math
import pickle
import sys
from pathlib import Path

import h5py
import numpy as np
from scipy import stats

R, A0 = 1e-8, 0.165e-9  # the records' tip radius and a0 (docs/lab/scanning_seeds.py)
Z95 = 1.959963984540054


def dmt(z, e_star, hamaker):
    far = np.maximum(z, A0)
    return np.where(z >= A0, -hamaker * R / (6 * far ** 2),
                    -hamaker * R / (6 * A0 ** 2) + 4 / 3 * e_star * np.sqrt(R) * np.maximum(A0 - z, 0) ** 1.5)


def wilson(k, n):
    """The Wilson score 95 % interval of k successes in n."""
    if n == 0:
        return (math.nan, math.nan)
    p = k / n
    centre = (p + Z95**2 / (2 * n)) / (1 + Z95**2 / n)
    half = Z95 * math.sqrt(p * (1 - p) / n + Z95**2 / (4 * n * n)) / (1 + Z95**2 / n)
    return (centre - half, centre + half)


def rms_interval(n):
    """The 95 % interval of the rms of n standard normal draws: sqrt(chi2_n quantiles / n)."""
    return tuple(math.sqrt(stats.chi2.ppf(q, n) / n) for q in (0.025, 0.975))


def seeds_of(text):
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def record(folder, kind, seed):
    base = Path(folder) / f"afmid_scan_seeds_{kind}_240_{seed}"
    run = Path(f"{base}_rows.run.h5")
    if not run.exists():
        return None
    with open(f"{base}.pkl", "rb") as handle:
        trace = pickle.load(handle)
    with h5py.File(run, "r") as f:
        g = f["model/separation_track"]
        d, sigma = g["separation"][:], g["separation_error"][:]
        first, stop = g["first_sample"][:], g["stop_sample"][:]
        e = f["model/parameters/E_star"]
        e_star, e_sigma = float(e[()]), float(e.attrs["error"])
        e_track = float(e.attrs.get("error_separation_track", 0.0))  # absent from run files written before it
        hamaker = float(f["model/parameters/hamaker"][()])
    true_d = trace.truth.tracks["rest_separation"][0]
    truth = np.array([true_d[a:b].mean() for a, b in zip(first, stop)])
    zt = true_d - trace.deflection
    err = np.sqrt(np.mean((dmt(zt, e_star, hamaker) - trace.truth.force) ** 2)) / np.max(np.abs(trace.truth.force))
    e_true = float(trace.truth.parameters["E_star"]) if "E_star" in getattr(trace.truth, "parameters", {}) else 2e9
    return dict(kind=kind, seed=seed, z=(d - truth) / sigma, error_pm=(d - truth) * 1e12, sigma_pm=sigma * 1e12,
                e_star=e_star, e_sigma=e_sigma, e_track=e_track, e_z=(e_star - e_true) / e_sigma, force_error=100 * err)


def summary(records, label):
    z = np.concatenate([r["z"] for r in records])
    n = z.size
    print(f"\n{label}: {len(records)} records, {n} blocks")
    for width in (1, 2):
        k = int(np.sum(np.abs(z) <= width))
        lo, hi = wilson(k, n)
        print(f"  blocks within {width} sigma: {k}/{n} = {k / n:.3f} [{lo:.3f}, {hi:.3f}] (Gaussian: "
              f"{math.erf(width / math.sqrt(2)):.3f})")
    lo, hi = rms_interval(n)
    print(f"  rms z over blocks {np.sqrt(np.mean(z**2)):.2f} (interval for {n} independent draws [{lo:.2f}, {hi:.2f}]); "
          f"mean z {z.mean():+.2f}")
    passing = [r for r in records if r["force_error"] <= 2 and np.all(np.abs(r["z"]) <= 2)]
    ok_force = sum(r["force_error"] <= 2 for r in records)
    for name, k in (("records meeting both numbers (force <= 2 %, every block within 2 sigma)", len(passing)),
                    ("records with force error <= 2 %", ok_force)):
        lo, hi = wilson(k, len(records))
        print(f"  {name}: {k}/{len(records)} [{lo:.2f}, {hi:.2f}]")
    fe = np.array([r["force_error"] for r in records])
    print(f"  force error % of peak: median {np.median(fe):.2f}, max {fe.max():.2f}, mean {fe.mean():.2f}")
    ez = np.array([r["e_z"] for r in records])
    es = np.array([r["e_star"] for r in records]) / 1e9
    lo, hi = rms_interval(ez.size)
    k1, k2 = int(np.sum(np.abs(ez) <= 1)), int(np.sum(np.abs(ez) <= 2))
    print(f"  E* {es.min():.3f}-{es.max():.3f} GPa (mean {es.mean():.3f}); E* z rms {np.sqrt(np.mean(ez**2)):.2f} "
          f"[{lo:.2f}, {hi:.2f}], within 1 sigma {k1}/{ez.size} {tuple(round(v, 2) for v in wilson(k1, ez.size))}, "
          f"within 2 sigma {k2}/{ez.size} {tuple(round(v, 2) for v in wilson(k2, ez.size))}")
    seeds = sorted({r["seed"] for r in records})
    per_seed = np.array([np.mean(np.concatenate([r["z"] for r in records if r["seed"] == s])) for s in seeds])
    lo, hi = rms_interval(per_seed.size)
    print(f"  per noise seed (mean z of its records' blocks): {np.round(per_seed, 2).tolist()}; rms {np.sqrt(np.mean(per_seed**2)):.2f} "
          f"(interval for {per_seed.size} draws [{lo:.2f}, {hi:.2f}], if a seed's blocks moved as one); "
          f"mean {per_seed.mean():+.2f} (standard error {per_seed.std(ddof=1) / np.sqrt(per_seed.size) if per_seed.size > 1 else math.nan:.2f})")
    for width in (1, 2):
        k = int(np.sum(np.abs(per_seed) <= width))
        print(f"  seeds whose mean |z| <= {width}: {k}/{per_seed.size} "
              f"{tuple(round(v, 2) for v in wilson(k, per_seed.size))} (Gaussian: {math.erf(width / math.sqrt(2)):.3f})")
    per_record = np.array([r["z"].mean() for r in records])
    lo, hi = rms_interval(per_record.size)
    k2 = int(np.sum(np.abs(per_record) <= 2))
    print(f"  per record (mean z of its blocks): rms {np.sqrt(np.mean(per_record**2)):.2f} [{lo:.2f}, {hi:.2f}]; "
          f"within 2 sigma {k2}/{per_record.size} {tuple(round(v, 2) for v in wilson(k2, per_record.size))}; "
          f"sd of blocks' z within a record {np.mean([r['z'].std() for r in records]):.2f} (mean)")


def main(argv):
    kinds = ["step", "rough"]
    if "--kinds" in argv:
        i = argv.index("--kinds")
        kinds = argv[i + 1].split(",")
        argv = argv[:i] + argv[i + 2:]
    groups = [(argv[0], seeds_of(argv[1]))]
    groups += [(argv[i + 1], seeds_of(argv[i + 2])) for i, word in enumerate(argv) if word == "--pool"]
    all_records = []
    for folder, seeds in groups:
        records = []
        for seed in seeds:
            for kind in kinds:
                r = record(folder, kind, seed)
                if r is None:
                    print(f"{kind} seed {seed}: no run file in {folder}")
                    continue
                records.append(r)
                print(f"{kind:5s} seed {seed}: d - truth pm {np.round(r['error_pm'], 1).tolist()} sigma pm "
                      f"{np.round(r['sigma_pm'], 1).tolist()} z {np.round(r['z'], 2).tolist()}; E* {r['e_star'] / 1e9:.3f} "
                      f"+- {r['e_sigma'] / 1e9:.4f} GPa (track's share {r['e_track'] / 1e9:.4f}; z {r['e_z']:+.2f}); "
                      f"force error {r['force_error']:.2f} %")
        if records:
            summary(records, f"seeds {seeds[0]}-{seeds[-1]} ({folder})")
        all_records += records
    if len(groups) > 1 and all_records:
        summary(all_records, "pooled")


if __name__ == "__main__":
    main(sys.argv[1:])
