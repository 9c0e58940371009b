"""The separation track on a short scanning record, with d per period (issue 29; docs/lab/2026-11-29-scanning-record.md).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python docs/lab/scanning_track_probe.py PERIODS BANDWIDTH SEED step|rough|flat GAIN MODE

MODE: plain (d constant per block), oracle (the true per-period d given inside the fit), estimate (one refit with the
unsmoothed mean-force offsets), track (fit_separation_track with within_block: mean_force). Prints per block d - truth
and its sigma, then E*, the law error (RMS over the samples at the true z, % of the peak force), model-limited blocks.
The simulated trace is cached in the temp folder.
"""
import copy, sys, time, logging, os, pickle
import numpy as np
from afmid.config import build_config
from afmid.simulate.driver import simulate
from afmid.io.trace import check_trace
from afmid.fit.separation_track import cut_blocks, block_periods_for
from afmid.fit.joint import fit_traces_jointly
from afmid.fit.period_separation import with_period_separation, block_means
periods, bw, seed, kind, gain, mode = int(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]), sys.argv[4], float(sys.argv[5]), sys.argv[6]
BASE = {"cantilever": {"spring_constant": 40.0, "resonance_frequency": 3e5, "quality_factor": 250.0, "tip_radius": 1e-8},
        "drive": {"frequency": 3e5, "free_amplitude": 1e-8}, "sample": {"a0": 0.165e-9, "separation": 8.5e-9},
        "model": {"effects": ["dmt"]}, "fit": {"bootstrap": 0, "seed": 0},
        "simulate": {"model": "dmt", "parameters": {"E_star": 2e9, "hamaker": 5e-20}, "periods": periods,
                     "samples_per_period": 100, "steps_per_period": 2000, "setpoint": 0.85,
                     "noise": {"thermal": True, "detector_rms": 1e-12}, "seed": seed}}
SCANS = {"step": {"speed": 4e-6, "start": -5e-9, "step": {"height": 2e-9, "position": 0.0, "width": 5e-9}},
         "rough": {"speed": 4e-6, "rough": {"rms": 0.5e-9, "correlation_length": 5e-9}}, "flat": {"speed": 4e-6}}
logging.getLogger("afmid").setLevel(logging.ERROR)
raw = copy.deepcopy(BASE); raw["simulate"]["scan"] = dict(SCANS[kind])
if gain > 0: raw["simulate"]["scan"]["feedback"] = {"gain": gain, "bandwidth": 10e3}
import tempfile
cache = f"{tempfile.gettempdir()}/afmid_scan_trace_{kind}_{periods}_{seed}_{gain:g}.pkl"
t0 = time.process_time()
if os.path.exists(cache):
    trace = pickle.load(open(cache, "rb"))
else:
    trace = simulate(build_config(raw)); pickle.dump(trace, open(cache, "wb"))
fit_raw = copy.deepcopy(raw); del fit_raw["sample"]["separation"]
config = build_config(fit_raw)
trace = check_trace(trace, config)
blocks = [check_trace(b, config) for b in cut_blocks(trace, block_periods_for(bw, trace.drive_frequency))]
adjust = None
if mode == "oracle":
    def adjust(i, prep):
        d = blocks[i].truth.tracks["rest_separation"][0]
        assert d.size == prep.x.size, (d.size, prep.x.size)
        per = block_means(prep, d)
        return with_period_separation(prep, per - per.mean())
if mode == "track":
    from afmid.fit.separation_track import fit_separation_track
    track = fit_separation_track(config, trace, bw, within_block="mean_force")
    joint = track.joint
    for i, t in enumerate(joint.traces):
        d = blocks[i].truth.tracks["rest_separation"][0]
        per = block_means(t.prep, d); per -= per.mean(); off = track.period_offsets[i]
        print(f"block {i}: offsets vs true: rms error {1e12*np.sqrt(np.mean((off-per)**2)):.1f} pm, true sd {1e12*per.std():.1f} pm", flush=True)
else:
    joint = fit_traces_jointly(config, [config] * len(blocks), blocks, False, mode != "estimate", adjust)
if mode == "estimate":
    from afmid.fit.period_separation import mean_force_offsets
    p = len(joint.library)
    coef = np.where(joint.selected[:p], joint.coef[:p], 0.0)
    found = []
    for i, t in enumerate(joint.traces):
        off = mean_force_offsets(t.prep, joint.library, coef, t.params)
        d = blocks[i].truth.tracks["rest_separation"][0]
        per = block_means(t.prep, d); per -= per.mean()
        print(f"block {i}: offsets estimated vs true: rms error {1e12*np.sqrt(np.mean((off-per)**2)):.1f} pm, true sd {1e12*per.std():.1f} pm, corr {np.corrcoef(off, per)[0,1]:.3f}", flush=True)
        found.append(off)
    adjust = lambda i, prep: with_period_separation(prep, found[i])
    joint = fit_traces_jointly(config, [config] * len(blocks), blocks, False, True, adjust)
ok = 0
E, H, R, a0 = joint.quantities["E_star"]["value"], joint.quantities["hamaker"]["value"], 1e-8, 0.165e-9
def dmt(z, E, H):
    zz = np.maximum(z, a0)
    return np.where(z >= a0, -H * R / (6 * zz**2), -H * R / (6 * a0**2) + 4 / 3 * E * np.sqrt(R) * np.maximum(a0 - z, 0) ** 1.5)
errs = []
for i, (b, t) in enumerate(zip(blocks, joint.traces)):
    d = b.truth.tracks["rest_separation"][0]
    off = t.separation.value - d.mean()
    ok += abs(off) <= 2 * t.separation.sigma
    z = d - b.deflection
    ft = b.truth.force; ff = dmt(z, E, H)
    errs.append((np.sqrt(np.mean((ff - ft) ** 2)), np.max(np.abs(ft))))
    chaos = [w for w in joint.warnings if "chaos" in w]
    print(f"block {i}: d-true {off*1e12:+.0f} pm sigma {t.separation.sigma*1e12:.0f} pm; true d sd {d.std()*1e12:.0f} pm; cv {t.cv_error:.3f} floor {t.cv_error_noise_floor:.3f}")
rms = np.sqrt(np.mean([e[0]**2 for e in errs])); peak = max(e[1] for e in errs)
print(f"{kind} gain {gain:g} seed {seed} periods {periods} bw {bw:g} mode {mode}: {ok}/{len(blocks)} within 2 sigma; "
      f"E* {E/1e9:.3f} GPa +- {joint.quantities['E_star'].get('error', float('nan'))/1e9:.3f}; H {H:.3g}; law error {100*rms/peak:.2f} % of peak; "
      f"model-limited blocks {sum(t.model_limited for t in joint.traces)}; terms {joint.selected_terms()}; cpu {time.process_time()-t0:.0f} s", flush=True)
