"""The diagnosis (afmid report) of separation-track run files (issue 29 item 2; docs/lab/2026-11-29-scanning-record.md).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python docs/lab/scanning_diagnosis.py viscoelastic SEED
    OPENBLAS_NUM_THREADS=1 .venv/bin/python docs/lab/scanning_diagnosis.py report RUN.h5 [RUN.h5 ...]

"viscoelastic": simulates the 2 nm step of docs/lab/scanning_seeds.py (feedback on, 240 periods) on a sample with
a hidden Kelvin-Voigt viscosity (DMT E* 2 GPa, H 5e-20 J, viscosity 150 Pa s: configs/dmt_viscoelastic.yaml's),
fits it with [dmt], the separation unknown, a track of 2500 Hz with ``within_block: rows``, writes the trace and
the run file to the temp folder and reports it. "report": `afmid report` of each run file; prints the verdict
line of summary.json (the effect named first, or none) and the CPU time.
"""
import copy, json, os, subprocess, sys, tempfile, time, logging
from pathlib import Path
from afmid.config import build_config
from afmid.simulate.driver import simulate
from afmid.io.trace import check_trace, load_trace, write_trace_file
from afmid.joint_runfile import write_track_run
from afmid.fit.separation_track import fit_separation_track

logging.getLogger("afmid").setLevel(logging.ERROR)
BASE = {"cantilever": {"spring_constant": 40.0, "resonance_frequency": 3e5, "quality_factor": 250.0, "tip_radius": 1e-8},
        "drive": {"frequency": 3e5, "free_amplitude": 1e-8}, "sample": {"a0": 0.165e-9, "separation": 8.5e-9},
        "model": {"effects": ["dmt"]}, "fit": {"bootstrap": 0, "seed": 0},
        "simulate": {"model": "dmt_viscoelastic", "parameters": {"E_star": 2e9, "hamaker": 5e-20, "viscosity": 150.0},
                     "periods": 240, "samples_per_period": 100, "steps_per_period": 2000, "setpoint": 0.85,
                     "noise": {"thermal": True, "detector_rms": 1e-12},
                     "scan": {"speed": 4e-6, "start": -5e-9, "step": {"height": 2e-9, "position": 0.0, "width": 5e-9},
                              "feedback": {"gain": 6000.0, "bandwidth": 10e3}}}}


def report(run: str) -> None:
    folder = Path(tempfile.gettempdir()) / (Path(run).stem + "_report")
    started = time.time()
    done = subprocess.run([str(Path(sys.executable).parent / "afmid"), "report", run, "-o", str(folder),
                           "--overwrite"], capture_output=True, text=True)
    cpu = os.times().children_user + os.times().children_system
    if done.returncode != 0:
        print(f"{run}: afmid report failed ({done.returncode}): {done.stderr.strip()[-400:]}", flush=True)
        return
    summary = json.loads((folder / "summary.json").read_text())
    named = [s["effect"] for s in summary.get("suggestions") or []]
    verdict = (summary.get("diagnosis") or {}).get("verdict") or summary.get("note")
    print(f"{run}: named {named or 'nothing'}; missing_effect {summary.get('missing_effect')}; "
          f"what_to_check {summary.get('what_to_check') or '-'}; verdict: {verdict}; "
          f"wall {time.time() - started:.0f} s, children cpu so far {cpu:.0f} s", flush=True)


if sys.argv[1] == "viscoelastic":
    seed = int(sys.argv[2])
    raw = copy.deepcopy(BASE)
    raw["simulate"]["seed"] = seed
    stem = f"{tempfile.gettempdir()}/afmid_scan_viscoelastic_240_{seed}"
    if not os.path.exists(stem + ".h5"):
        write_trace_file(stem + ".h5", simulate(build_config(raw)), "")
    fit_raw = copy.deepcopy(raw)
    del fit_raw["sample"]["separation"]
    fit_raw["data"] = {"path": stem + ".h5"}
    fit_raw["fit"]["separation_track"] = {"bandwidth": 2500.0, "within_block": "rows"}
    config = build_config(fit_raw)
    t0 = time.process_time()
    track = fit_separation_track(config, check_trace(load_trace(config), config), 2500.0)
    write_track_run(stem + "_rows.run.h5", track, overwrite=True)
    print(f"viscoelastic seed {seed}: track fitted in {time.process_time() - t0:.0f} s CPU; terms "
          f"{track.joint.selected_terms()}; model-limited blocks {sum(t.model_limited for t in track.joint.traces)}",
          flush=True)
    report(stem + "_rows.run.h5")
else:
    for run in sys.argv[2:]:
        report(run)
