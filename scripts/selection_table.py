"""Before/after table of issue 17 over the cases of tests/fit/test_selection_consistency.py (seeds 101-110):
right support and median law error at 50 and 500 periods, for fit.selection_scope vote and record.

Run: python scripts/selection_table.py [--scopes vote record] [--periods 50 500] [--cases ...]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_k, "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "support"))

import numpy as np  # noqa: E402

from tests.fit.test_selection_consistency import CASES, SEEDS, law_error  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scopes", nargs="+", default=["vote", "record"])
    ap.add_argument("--periods", type=int, nargs="+", default=[50, 500])
    ap.add_argument("--cases", nargs="+", default=list(CASES))
    a = ap.parse_args()
    from afmid.config import load_config
    from afmid.fit.pipeline import run_fit
    from afmid.simulate.driver import simulate

    print("| case | periods | scope | right | median law error % | median wrong terms (max) | median fit s |")
    print("|---|---|---|---|---|---|---|")
    for case in a.cases:
        path, overrides, truth = CASES[case]
        for P in a.periods:
            traces = {}
            for scope in a.scopes:
                right, laws, wrong, secs = 0, [], [], []
                for seed in SEEDS:
                    cfg = load_config(path, overrides + [f"simulate.periods={P}", f"simulate.seed={seed}",
                                                         "fit.bootstrap=0", f"fit.selection_scope={scope}"])
                    trace = traces.get(seed) or simulate(cfg)
                    traces[seed] = trace
                    t0 = time.perf_counter()
                    res = run_fit(cfg, trace=trace, uncertainty=False)
                    secs.append(time.perf_counter() - t0)
                    sel = set(res.selected_terms())
                    right += sel == truth
                    wrong.append(len(sel ^ truth))
                    laws.append(law_error(res, trace))
                print(f"| {case} | {P} | {scope} | {right}/{len(SEEDS)} | {100 * np.median(laws):.3f} | "
                      f"{np.median(wrong):g} ({max(wrong)}) | {np.median(secs):.2f} |", flush=True)


if __name__ == "__main__":
    main()
