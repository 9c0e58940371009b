"""Where the separation track's level shift comes from (docs/lab/2026-11-29-scanning-record.md, 2026-11-30).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python docs/lab/scanning_level_shift_probe.py flat SEED

On a record of docs/lab/scanning_seeds.py (its cached trace, run that first: 240 periods, 4 blocks of 60), the
track's passes one by one (``within_block: rows``): the first joint fit (d held per block), the second (offsets
from the first law), the joint step's offsets, then the last fit with variants of those offsets: as found, zero,
negated, randomly permuted (the same values in another order). Prints each fit's levels against the truth and E*.
Then, at the first fit, the offsets' log-determinant's step (afmid.fit.period_separation.joint_level_step with the
design derivatives). ~150 s of CPU.
"""
import logging, pickle, sys, tempfile, time

import numpy as np

from afmid.config import build_config
from afmid.fit import separation_track as st
from afmid.fit.joint import fit_traces_jointly
from afmid.fit.period_separation import joint_level_step, with_period_separation
from afmid.io.trace import check_trace

logging.getLogger("afmid").setLevel(logging.ERROR)
kind, seed = sys.argv[1], int(sys.argv[2])
RAW = {"cantilever": {"spring_constant": 40.0, "resonance_frequency": 3e5, "quality_factor": 250.0, "tip_radius": 1e-8},
       "drive": {"frequency": 3e5, "free_amplitude": 1e-8}, "sample": {"a0": 0.165e-9},
       "model": {"effects": ["dmt"]},
       "fit": {"bootstrap": 0, "seed": 0, "separation_track": {"bandwidth": 2500.0, "within_block": "rows"}}}
config = build_config(RAW)
with open(f"{tempfile.gettempdir()}/afmid_scan_seeds_{kind}_240_{seed}.pkl", "rb") as handle:
    trace = check_trace(pickle.load(handle), config)
blocks = [check_trace(b, config) for b in st.cut_blocks(trace, 60)]
configs = [config] * len(blocks)
d = trace.truth.tracks["rest_separation"][0]
truth = np.array([d[b.first_sample - trace.first_sample:b.first_sample - trace.first_sample + b.n_samples].mean()
                  for b in blocks])


def show(name, joint):
    separation = np.array([t.separation.value for t in joint.traces])
    print(f"{kind} {seed} {name}: d - truth pm {np.round((separation - truth) * 1e12, 1).tolist()}, "
          f"E* {joint.quantities['E_star']['value'] / 1e9:.4f} GPa", flush=True)


def refit(offsets):
    return fit_traces_jointly(config, configs, blocks, False, False,
                              adjust_prepared=lambda i, prep: with_period_separation(prep, offsets[i]))


started = time.process_time()
first = fit_traces_jointly(config, configs, blocks, False, uncertainty=False)
show("first fit (d per block)", first)
unshifted = [t.prep for t in first.traces]
offsets, priors = st.period_offsets(first, unshifted, "rows")
print("priors (sd m, rho)", priors, "offsets' sd pm", [round(float(np.std(o)) * 1e12, 2) for o in offsets])
at_first = joint_level_step(st.linearised_blocks(first, unshifted, [np.zeros_like(o) for o in offsets], priors,
                                                 derivatives=True))
print("at the first fit, the log-determinant's step pm", np.round(at_first.log_det_change * 1e12, 1).tolist())
second = refit(offsets)
show("second fit (offsets from the first law)", second)
offsets, priors = st.period_offsets(second, unshifted, "rows")
found = joint_level_step(st.linearised_blocks(second, unshifted, offsets, priors)).offsets
rng = np.random.default_rng(0)
for name, variant in [("joint step's offsets", found), ("zero", [np.zeros_like(o) for o in found]),
                      ("negated", [-o for o in found]), ("permuted", [rng.permutation(o) for o in found])]:
    show(f"last fit, offsets {name}", refit(variant))
print(f"cpu {time.process_time() - started:.0f} s")
