"""Per block of 60 periods: the per-period mean force's scatter against its white-noise model (block_sigma[0]) and
its lag-1 correlation, on records cached by docs/lab/scanning_seeds.py (docs/lab/2026-11-29-scanning-record.md).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python docs/lab/scanning_mean_force_noise.py nofeedback_240_61 step_240_71
"""
import copy, pickle, sys, logging
import numpy as np
sys.path.insert(0, "tests/fit")
from test_separation_track import RAW
from afmid.config import build_config
from afmid.io.trace import check_trace
from afmid.fit.separation_track import cut_blocks
from afmid.fit.prepare import prepare
logging.getLogger("afmid").setLevel(logging.ERROR)
raw = copy.deepcopy(RAW); del raw["sample"]["separation"]
config = build_config(raw)
for name in sys.argv[1:]:
    trace = check_trace(pickle.load(open(f"/tmp/afmid_scan_seeds_{name}.pkl", "rb")), config)
    for i, block in enumerate(cut_blocks(trace, 60)):
        prep = prepare(check_trace(block, config), config.fit)
        f = prep.Y_block[:, 0]; c = f - f.mean()
        lag1 = np.mean(c[1:] * c[:-1]) / np.var(f)
        xm = prep.X[:, 0] - prep.X[:, 0].mean(); xt = prep.X_traj[:, 0] - prep.X_traj[:, 0].mean()
        print(f"{name} block {i}: mean-force sd {1e12*f.std():.1f} pN vs block_sigma[0] {1e12*prep.block_sigma[0]:.1f} pN, lag-1 corr {lag1:.2f}; "
              f"per-period mean x sd {1e12*xm.std():.2f} pm, smoothed {1e12*xt.std():.2f} pm, k*(x - smoothed) sd {40e12*(xm-xt).std():.1f} pN", flush=True)
