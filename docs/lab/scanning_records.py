"""What the fit does on records taken while scanning (issue 29 item 2; docs/lab/2026-11-29-scanning-record.md).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python docs/lab/scanning_records.py PERIODS [NAME ...]

Simulates each record of SCANS (a DMT sample, A0 10 nm, A/A0 0.85, thermal noise, seed 61), fits it with [dmt] and
the separation unknown (one d for the record: the fit as it is), and prints d(t)'s range, the feedback amplitude's
dip, the force error (RMS over the samples, % of the peak) and the separation against the mean of d(t).
"""
import copy, math, sys, time, logging
import numpy as np
from afmid.config import build_config
from afmid.coverage.compare import compare
from afmid.fit.pipeline import run_fit
from afmid.io.trace import check_trace
from afmid.physics.tips import tip_geometry
from afmid.simulate.driver import simulate

PERIODS = int(sys.argv[1]) if len(sys.argv) > 1 else 800
BASE = {"cantilever": {"spring_constant": 40.0, "resonance_frequency": 3e5, "quality_factor": 250.0, "tip_radius": 1e-8},
        "drive": {"frequency": 3e5, "free_amplitude": 1e-8}, "sample": {"a0": 0.165e-9, "separation": 8.5e-9},
        "model": {"effects": ["dmt"]}, "fit": {"bootstrap": 20, "seed": 0},
        "simulate": {"model": "dmt", "parameters": {"E_star": 2e9, "hamaker": 5e-20}, "periods": PERIODS,
                     "samples_per_period": 100, "steps_per_period": 2000, "setpoint": 0.85,
                     "noise": {"thermal": True, "detector_rms": 1e-12}, "seed": 61}}
SCANS = {
  "flat (no scan)": None,
  "flat, scanning + feedback": {"speed": 4e-6, "feedback": {"gain": 6000.0, "bandwidth": 10e3}},
  "2 nm step + feedback": {"speed": 4e-6, "start": -5e-9, "step": {"height": 2e-9, "position": 0.0, "width": 5e-9},
                            "feedback": {"gain": 6000.0, "bandwidth": 10e3}},
  "rough 0.5 nm/5 nm + feedback": {"speed": 4e-6, "rough": {"rms": 0.5e-9, "correlation_length": 5e-9},
                                    "feedback": {"gain": 6000.0, "bandwidth": 10e3}},
}
logging.getLogger("afmid").setLevel(logging.ERROR)
which = sys.argv[2:] or list(SCANS)
for name in which:
    scan = SCANS[name]
    raw = copy.deepcopy(BASE)
    if scan: raw["simulate"]["scan"] = scan
    t0 = time.process_time()
    trace = simulate(build_config(raw))
    fit_raw = copy.deepcopy(raw); del fit_raw["sample"]["separation"]
    config = build_config(fit_raw)
    result = run_fit(config, trace=check_trace(trace, config))
    nums = compare(result, trace, tip_geometry(config.cantilever), False)
    if trace.truth.tracks:
        d = trace.truth.tracks["rest_separation"][0]; amp = trace.truth.tracks["feedback_amplitude"][0]
        dd = f"d(t) range {1e9*(d.max()-d.min()):.3f} nm, amplitude dip {100*(1-amp.min()/amp.max()):.2f} %"
    else:
        dd = "d constant"
    s, f = nums["separation"], nums["force_curve"]
    print(f"{name:30s} {PERIODS} periods: {dd}; force error {100*f['error_relative']:.2f} % of peak "
          f"(claimed {100*f['sigma_relative']:.2f} %), separation {1e12*(s['estimate']-s['truth']):+.0f} pm off "
          f"mean d(t) at sigma {1e12*s['sigma']:.0f} pm (z {s['z']:+.1f}); cv {result.cv_error:.3f} floor "
          f"{result.cv_error_noise_floor:.3f}; model_limited {result.model_limited}; cpu {time.process_time()-t0:.0f} s",
          flush=True)
