"""Why PySINDy's weak form does not find the Lennard-Jones law of table I (issue 17; docs/accuracy.md).

On draws 2-11 of configs/lennard_jones.yaml (the bench uses 21-30), at 50 or 500 periods, for PySINDy's
default subdomains and for one-period test functions (bench/bench_selection.py builds both), and for the STLSQ
ridge alpha 0.05 (default) and 0: how many draws reach the right terms (z^-2, z^-8) at ANY of 31 thresholds
(an oracle: the truth picks the threshold), how many with the threshold chosen by BIC on the weak rows, the
median law error of the BIC choice, and the median law error of a least-squares fit of the same columns on
the true terms (how good PySINDy's columns are, apart from the selection).

Run: python scripts/pysindy_study.py [--periods 50] [--draws 10]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import numpy as np  # noqa: E402

import bench_selection as bench  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--periods", type=int, default=50)
    parser.add_argument("--draws", type=int, default=10)
    args = parser.parse_args()
    seeds = range(2, 2 + args.draws)
    for subdomains in ("default", "period"):
        for alpha in (0.05, 0.0):
            oracle = chosen_right = 0
            laws, true_laws = [], []
            for seed in seeds:
                trace = bench._load(bench._trace(args.periods, seed))
                d = float(trace.truth.extra["separation"])
                A, y = bench.pysindy_columns(trace, d, subdomains)
                path = bench.stlsq_path(A, y, alpha)
                oracle += any(bench._support(c) == bench.TRUE_POWERS for c in path)
                coef = min(path, key=lambda c: bench.bic(A, y, c))
                chosen_right += bench._support(coef) == bench.TRUE_POWERS
                laws.append(bench._law_error(coef, trace))
                cols = [bench.POWERS.index(q) for q in sorted(bench.TRUE_POWERS)]
                norms = np.linalg.norm(A[:, cols], axis=0)
                on_truth = np.zeros(len(bench.POWERS))
                on_truth[cols] = np.linalg.lstsq(A[:, cols] / norms, y, rcond=None)[0] / norms
                true_laws.append(bench._law_error(on_truth, trace))
            print(f"{args.periods} periods, subdomains {subdomains}, ridge alpha {alpha:g}: right at some threshold "
                  f"{oracle}/{len(seeds)}, by BIC {chosen_right}/{len(seeds)}, BIC law error (median) "
                  f"{100 * np.median(laws):.3g} %, columns on the true terms {100 * np.median(true_laws):.3g} %",
                  flush=True)


if __name__ == "__main__":
    main()
