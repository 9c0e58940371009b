"""Why does the selection change with the record length? Measurements behind docs/accuracy.md,
section "Selection as the record grows" (issue 17).

For a config + seed table, simulates the trace at several numbers of periods and seeds and reports,
per fit (bootstrap off):

- the selected support and the law error: the identified force law evaluated on the true trajectory
  (true separation, true velocity) minus the true force, RMS over the samples / peak true force;
- the residual of the chosen support per weak-form window (block): its lag-1..3 autocorrelation across
  windows, the ratio of the variance of block sums of 10 windows to 10x the per-window variance
  (1 = independent) and the residual variance per row against the predicted one (1 = white rows as
  weighted);
- the number of rows n behind BIC's log(n) against an effective n from the per-window residual
  (n_eff = n / (chi^2/dof) / inflation);
- the condition number of the unit-norm library columns;
- for every distractor kept (or the best one added to the true support): the drop of the weighted RSS
  it buys, against the BIC penalty log(n) + 2 ln(odds).

Run:  python scripts/selection_study.py --config configs/lennard_jones.yaml --library lj_table1 \
          --periods 50 500 --seeds 2 3 4 5 6
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_k, "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

TRUE_TERMS = {
    "dmt": {"z^-2", "delta^1.5", "[z<=a0] (bridging)"},
    "lennard_jones": {"z^-2", "z^-8"},
    "dmt_viscoelastic": {"z^-2", "delta^0.5*deltadot", "delta^1.5", "[z<=a0] (bridging)"},
    "dmt_exponential_damping": {"z^-2", "exp(-z/lambda)*zdot", "delta^1.5", "[z<=a0] (bridging)"},
    "jkr": {"z^-2", "delta^1.5", "[z<=a0] (bridging)"},
}


def law_error(result, trace) -> float:
    """RMS over the samples of (identified law - true force) on the true trajectory, / peak true force."""
    lib = result.library
    p = len(lib)
    params = dict(result.system.params)
    d_true = float(trace.truth.extra["separation"])
    params["d"] = d_true
    z = trace.truth.separation
    x = d_true - z
    v = trace.truth.velocity
    cols = lib.evaluate(x, v, trace.times, params)
    coef = np.where(result.selected[:p], result.coef[:p], 0.0)
    F = cols @ coef
    Ft = trace.truth.force
    return float(np.sqrt(np.mean((F - Ft) ** 2)) / np.max(np.abs(Ft)))


def block_stats(result) -> dict:
    import afmid.fit.regression as regression

    sysm = result.system
    Tb = sysm.T_blocks
    mask = result.selected
    coef, rss = regression.subset_fit(regression.combine(Tb), mask)
    r = regression.block_rss(Tb, coef)  # per window
    B = r.size
    n = sysm.n_rows
    rows_per = n / B
    # the residual per window as a signed series: project on a fixed direction is not available from R factors;
    # use the per-window RSS deviations (chi^2 per window) and the sum-of-blocks variance of the RSS.
    s = r - r.mean()
    ac = [float(np.dot(s[:-k], s[k:]) / np.dot(s, s)) if B > k + 2 else math.nan for k in (1, 2, 3)]
    chi2_per_row = float(rss / (n - mask.sum()))
    return dict(B=B, n=n, rows_per=rows_per, chi2=chi2_per_row, ac=ac)


def signed_residual(result) -> np.ndarray:
    """Whitened residual rows (W, rows) of the chosen support, rebuilt from the system's columns."""
    prep, sysm = result.prep, result.system
    A = np.concatenate([sysm.theta, prep.nuisance], axis=2) / prep.row_sigma[None, :, None]
    y = prep.Y / prep.row_sigma[None, :]
    return y - A @ np.where(result.selected, result.coef, 0.0)


def study(config_path, library, model_key, periods, seeds, extra, odds_list):
    from afmid.config import load_config
    from afmid.fit.pipeline import run_fit
    from afmid.simulate.driver import simulate
    import afmid.fit.regression as regression

    rows = []
    for P in periods:
        for seed in seeds:
            over = [f"simulate.periods={P}", f"simulate.seed={seed}", "model.effects=[]", f"model.library={library}",
                    "fit.bootstrap=0"] + extra
            cfg = load_config(config_path, over)
            trace = simulate(cfg)
            t0 = time.perf_counter()
            res = run_fit(cfg, trace=trace, uncertainty=False)
            secs = time.perf_counter() - t0
            sel = set(res.selected_terms())
            truth = TRUE_TERMS[model_key]
            le = law_error(res, trace)
            bs = block_stats(res)
            R = signed_residual(res)  # (W, rows)
            W = R.shape[0]
            # autocorrelation of each row's residual across windows (lag 1..3), averaged over rows
            Rc = R - R.mean(axis=0)
            den = np.sum(Rc**2, axis=0)
            ac = [float(np.mean(np.sum(Rc[:-k] * Rc[k:], axis=0) / den)) for k in (1, 2, 5)]
            # variance inflation of sums over g consecutive windows (row by row), averaged
            g = 10
            m = (W // g) * g
            S = Rc[:m].reshape(-1, g, R.shape[1]).sum(axis=1)
            infl = float(np.mean(np.var(S, axis=0) / (g * np.var(Rc[:m], axis=0))))
            # cross-row correlation inside a window: variance of the window's sum of rows vs sum of variances
            infl_rows = float(np.var(Rc.sum(axis=1)) / np.sum(np.var(Rc, axis=0)))
            n = bs["n"]
            n_eff = n / max(infl, 1.0)
            # conditioning of the library (unit-norm columns)
            T = regression.combine(res.system.T_blocks)
            p = len(res.library)
            Ac = T[:, :p]
            Ac = Ac / np.linalg.norm(Ac, axis=0)
            cond = float(np.linalg.cond(Ac))
            # RSS drop of distractors relative to the true support
            names = res.system.names
            true_mask = np.array([nm in truth for nm in names[:p]] + [True] * (len(names) - p))
            _, rss_true = regression.subset_fit(T, true_mask)
            _, rss_sel = regression.subset_fit(T, res.selected)
            drops = []
            for j in range(p):
                if not true_mask[j]:
                    mk = true_mask.copy()
                    mk[j] = True
                    drops.append((rss_true - regression.subset_fit(T, mk)[1], names[j]))
            drops.sort(reverse=True)
            chi2 = bs["chi2"]
            rows.append(dict(P=P, seed=seed, ok=sel == truth, extra=sorted(sel - truth), missing=sorted(truth - sel),
                             law=le, secs=secs, n=n, W=W, chi2=chi2, ac=ac, infl=infl, infl_rows=infl_rows,
                             n_eff=n_eff, cond=cond, drop_sel=rss_true - rss_sel, k_extra=len(sel - truth),
                             best_drop=drops[0], logn=math.log(n)))
            r = rows[-1]
            print(f"P={P:5d} seed={seed:2d} ok={r['ok']!s:5} +{r['extra']} -{r['missing']} law={100*le:.3f}% "
                  f"t={secs:.2f}s n={n} W={W} chi2/row={chi2:.2f} ac(1,2,5)={ac[0]:+.2f},{ac[1]:+.2f},{ac[2]:+.2f} "
                  f"infl10={infl:.1f} rows-in-window={infl_rows:.1f} cond={cond:.1e} "
                  f"dRSS(true->sel)={r['drop_sel']:.1f} best1={drops[0][0]:.1f}({drops[0][1]}) "
                  f"pen/term=log n {math.log(n):.1f}+2ln odds; in chi2 units dRSS/chi2={r['drop_sel']/chi2:.1f}",
                  flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default="configs/lennard_jones.yaml")
    ap.add_argument("--library", default="lj_table1")
    ap.add_argument("--model", default=None)
    ap.add_argument("--periods", type=int, nargs="+", default=[50, 500])
    ap.add_argument("--seeds", type=int, nargs="+", default=[2, 3, 4, 5, 6])
    ap.add_argument("--set", nargs="*", default=[])
    a = ap.parse_args()
    model = a.model or Path(a.config).stem
    rows = study(a.config, a.library, model, a.periods, a.seeds, a.set, None)
    for P in a.periods:
        rs = [r for r in rows if r["P"] == P]
        print(f"P={P}: right {sum(r['ok'] for r in rs)}/{len(rs)}, median law {100*np.median([r['law'] for r in rs]):.3f} %, "
              f"median extra {np.median([r['k_extra'] for r in rs])}, median time {np.median([r['secs'] for r in rs]):.2f} s, "
              f"median infl10 {np.median([r['infl'] for r in rs]):.1f}, median ac1 {np.median([r['ac'][0] for r in rs]):+.2f}")


if __name__ == "__main__":
    main()


def dump_systems(config_path, library, periods, seeds, extra, out):
    """Save each fit's selection problem (factors, protected, penalty, rules) and the library on the true
    trajectory, for trying selection strategies offline."""
    import pickle

    from afmid.config import load_config
    from afmid.fit.pipeline import run_fit
    from afmid.fit.selection import SelectionSettings
    from afmid.simulate.driver import simulate

    items = []
    for P in periods:
        for seed in seeds:
            over = [f"simulate.periods={P}", f"simulate.seed={seed}", "model.effects=[]", f"model.library={library}",
                    "fit.bootstrap=0"] + extra
            cfg = load_config(config_path, over)
            trace = simulate(cfg)
            res = run_fit(cfg, trace=trace, uncertainty=False)
            st = SelectionSettings.for_library(cfg.fit, res.library, len(res.prep.nuisance_names))
            params = dict(res.system.params)
            d_true = float(trace.truth.extra["separation"])
            params["d"] = d_true
            cols = res.library.evaluate(d_true - trace.truth.separation, trace.truth.velocity, trace.times, params)
            items.append(dict(P=P, seed=seed, T_blocks=res.system.T_blocks, protected=res.system.protected,
                              names=res.system.names, n_rows=res.system.n_rows, penalty=st.penalty, rules=st.rules,
                              cols=cols[::4], force=trace.truth.force[::4], selected=res.selected_terms()))
            print(P, seed, res.selected_terms(), flush=True)
    with open(out, "wb") as fh:
        pickle.dump(items, fh)
