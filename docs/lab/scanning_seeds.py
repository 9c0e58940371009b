"""The separation track on scanning records over fixed seeds (issue 29 item 2; docs/lab/2026-11-29-scanning-record.md).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python docs/lab/scanning_seeds.py PERIODS BANDWIDTH MODE step|rough|flat SEED [SEED ...]

MODE: a fit.separation_track.within_block value, or "default" (the config's default). Per record (a DMT sample,
E* 2 GPa, H 5e-20 J, A0 10 nm, A/A0 0.85, thermal noise + 1 pm detector, feedback gain 6000 /s, demodulator
10 kHz; fit [dmt], separation unknown, no bootstrap) prints: blocks whose d is within 2 sigma of the block's mean
true d(t), the blocks' z, E*, the force error (the fitted law against the true force at the true z(t), RMS over
the samples, % of the peak true force), model-limited blocks, inspect's motion line and, with rows, the
offsets' share of each level's sigma and the linearised joint minimum's remaining step (afmid.fit.separation_track). The simulated trace is
cached in the temp folder (keyed by surface, periods, seed), and the track's run file written beside it
(..._MODE.run.h5: afmid report diagnoses it).
"""
import copy, dataclasses, sys, time, logging, os, pickle, tempfile
from pathlib import Path
import numpy as np
from afmid.config import build_config
from afmid.simulate.driver import simulate
from afmid.io.trace import check_trace, sha256_file, write_trace_file
from afmid.joint_runfile import write_track_run
from afmid.io.inspect import inspect_file
from afmid.fit.separation_track import fit_separation_track, offsets_share

periods, bandwidth, mode, kind = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3], sys.argv[4]
seeds = [int(s) for s in sys.argv[5:]]
BASE = {"cantilever": {"spring_constant": 40.0, "resonance_frequency": 3e5, "quality_factor": 250.0, "tip_radius": 1e-8},
        "drive": {"frequency": 3e5, "free_amplitude": 1e-8}, "sample": {"a0": 0.165e-9, "separation": 8.5e-9},
        "model": {"effects": ["dmt"]}, "fit": {"bootstrap": 0, "seed": 0},
        "simulate": {"model": "dmt", "parameters": {"E_star": 2e9, "hamaker": 5e-20}, "periods": periods,
                     "samples_per_period": 100, "steps_per_period": 2000, "setpoint": 0.85,
                     "noise": {"thermal": True, "detector_rms": 1e-12}}}
FEEDBACK = {"gain": 6000.0, "bandwidth": 10e3}
SCANS = {"step": {"speed": 4e-6, "start": -5e-9, "step": {"height": 2e-9, "position": 0.0, "width": 5e-9},
                  "feedback": FEEDBACK},
         "rough": {"speed": 4e-6, "rough": {"rms": 0.5e-9, "correlation_length": 5e-9}, "feedback": FEEDBACK},
         # no feedback, a flat surface: the piezo still, d constant (what a track must not make worse)
         "flat": {"speed": 4e-6},
         # no feedback: the piezo still, d drops 0.4 nm mid-record (tests/fit/test_separation_track.py's record)
         "nofeedback": {"speed": 4e-6, "start": -1.6e-9, "step": {"height": 0.4e-9, "position": 0.0, "width": 0.1e-9}}}
logging.basicConfig(format="%(message)s"); logging.getLogger("afmid").setLevel(logging.ERROR); logging.getLogger("afmid.fit.separation_track").setLevel(logging.INFO)
R, A0 = 1e-8, 0.165e-9


def dmt(z, e_star, hamaker):
    far = np.maximum(z, A0)
    return np.where(z >= A0, -hamaker * R / (6 * far ** 2),
                    -hamaker * R / (6 * A0 ** 2) + 4 / 3 * e_star * np.sqrt(R) * np.maximum(A0 - z, 0) ** 1.5)


for seed in seeds:
    raw = copy.deepcopy(BASE)
    raw["simulate"]["seed"] = seed
    raw["simulate"]["scan"] = SCANS[kind]
    t0 = time.process_time()
    cache = f"{tempfile.gettempdir()}/afmid_scan_seeds_{kind}_{periods}_{seed}.pkl"
    if os.path.exists(cache):
        with open(cache, "rb") as handle:
            trace = pickle.load(handle)
    else:
        trace = simulate(build_config(raw))
        with open(cache, "wb") as handle:
            pickle.dump(trace, handle)
    t_sim = time.process_time() - t0
    h5 = f"{tempfile.gettempdir()}/afmid_scan_seeds_{kind}_{periods}_{seed}.h5"
    if not os.path.exists(h5):
        write_trace_file(h5, trace, "")
    motion = [line.strip() for line in inspect_file(h5).splitlines() if line.strip().startswith("motion")]
    fit_raw = copy.deepcopy(raw)
    del fit_raw["sample"]["separation"]
    fit_raw["fit"]["separation_track"] = {"bandwidth": bandwidth, "within_block": "constant" if mode == "default" else mode}
    config = build_config(fit_raw)
    # The trace file's path and digest: the run file written below points at it (afmid report refits from it).
    trace = check_trace(dataclasses.replace(trace, path=Path(h5), sha256=sha256_file(h5)), config)
    t1 = time.process_time()
    track = fit_separation_track(config, trace, bandwidth, within_block=None if mode == "default" else mode)
    joint = track.joint
    d = trace.truth.tracks["rest_separation"][0]
    truth = np.array([d[a:b].mean() for a, b in zip(track.first_sample, track.stop_sample)])
    z = (track.separation - truth) / track.sigma
    e_star, hamaker = joint.quantities["E_star"]["value"], joint.quantities["hamaker"]["value"]
    zt = d - trace.deflection
    err = np.sqrt(np.mean((dmt(zt, e_star, hamaker) - trace.truth.force) ** 2)) / np.max(np.abs(trace.truth.force))
    limited = sum(t.model_limited for t in joint.traces)
    print(f"{kind} seed {seed} {periods} periods bw {bandwidth:g} {mode}: within 2 sigma {np.sum(np.abs(z) <= 2)}/{z.size}; "
          f"d-truth pm {np.round((track.separation - truth) * 1e12).astype(int).tolist()} sigma pm "
          f"{np.round(track.sigma * 1e12).astype(int).tolist()} z {np.round(z, 2).tolist()}; E* {e_star / 1e9:.3f} +- {joint.quantities['E_star']['error'] / 1e9:.3f} GPa; force error "
          f"{100 * err:.2f} % of peak; model-limited {limited}/{z.size}; terms {joint.selected_terms()}; "
          f"bound pm {np.round(track.information_bound * 1e12, 1).tolist()}; {motion[0] if motion else 'motion: -'}; cpu sim {t_sim:.0f} s fit {time.process_time() - t1:.0f} s"
          + (f"; offsets' share of sigma pm {np.round(np.sqrt(offsets_share(track.level_step)) * 1e12, 1).tolist()}, "
             f"joint minimum's step pm {np.round(track.level_step.level_change * 1e12, 1).tolist()}"
             if track.level_step is not None else ""),
          flush=True)
    write_track_run(f"{tempfile.gettempdir()}/afmid_scan_seeds_{kind}_{periods}_{seed}_{mode}.run.h5", track,
                    overwrite=True)
