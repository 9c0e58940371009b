"""The poor instrument's traces and three trajectories for the force law (issue 13: does the default smoother
bias the fit?): the default Kalman smoother's, none (``fit.smooth_periods: 1``), and the simulator's true motion
(the noise-free deflection through the same per-period projection: what no smoother can beat).

Shared by tests/preprocess/test_smoother_bias.py and ``scripts/poor_signals.py --smoother``.
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
from repo_paths import TEST_CONFIGS

#: The poor instrument: 10 pm rms detector noise, 50 samples per period (50 periods, tests/configs/hidden_clean.yaml).
POOR = ["simulate.noise.detector_rms=1.0e-11", "simulate.samples_per_period=50"]
#: The trajectories the library can be evaluated on.
TRAJECTORIES = ("default", "none", "truth")


def simulate_poor(folder: Path, seed: int, overrides: list[str] = (), separation_given: bool = True):
    """Simulate hidden_clean.yaml on the poor instrument; return (trace as simulated, fit config, true
    parameters). The trace file is written to ``folder``."""
    from afmid.config import apply_overrides, build_config, dump_config, parse_override, read_yaml
    from afmid.io.trace import write_trace_file
    from afmid.simulate.driver import simulate

    raw = apply_overrides(read_yaml(TEST_CONFIGS / "hidden_clean.yaml"),
                          [parse_override(o) for o in [*POOR, *overrides, f"simulate.seed={seed}"]])
    key = f"poor-{seed}-{abs(hash(tuple(overrides))) % 10**8}"
    sim_config = build_config(raw, source=folder / f"{key}.yaml", base_dir=folder)
    trace = simulate(sim_config)
    path = folder / f"{key}.h5"
    if not path.exists():
        write_trace_file(path, trace, dump_config(sim_config))
    fit_raw = copy.deepcopy(raw)
    fit_raw["data"] = {"path": str(path)}
    truth = {k: float(v) for k, v in fit_raw["simulate"]["parameters"].items()}
    fit_raw["simulate"]["parameters"] = {}
    if not separation_given:
        fit_raw["sample"]["separation"] = None
    return trace, build_config(fit_raw, source=folder / f"{key}.yaml", base_dir=folder), truth


def prepared_with(trajectory: str, loaded_trace, truth_trace, fit_config):
    """:func:`afmid.fit.prepare.prepare` of ``loaded_trace`` (the trace as the fit reads it) with the library's
    trajectory taken from ``trajectory`` (one of :data:`TRAJECTORIES`); the rows (the equation's side) are the
    recorded deflection's in all three."""
    from afmid.fit.prepare import prepare

    if trajectory == "default":
        return prepare(loaded_trace, fit_config)
    unsmoothed = fit_config.model_copy(update={"smooth_periods": 1})
    prep = prepare(loaded_trace, unsmoothed)
    if trajectory == "none":
        return prep
    motion = float(truth_trace.truth.extra["separation"]) - truth_trace.truth.separation  # x = d - z
    true = prepare(dataclasses.replace(loaded_trace, deflection=motion), unsmoothed)
    return dataclasses.replace(prep, X_traj=true.X_traj, V_traj=true.V_traj, xdot_used=true.xdot_used)


def force_error(result, trace) -> float:
    """RMS of (estimated - true force) over the estimated samples / the largest |true force| there."""
    truth = trace.truth.force
    used = np.isfinite(result.force_estimate)
    return float(np.sqrt(np.mean((result.force_estimate[used] - truth[used]) ** 2)) / np.abs(truth[used]).max())


def fit_three_ways(folder: Path, seed: int, overrides: list[str] = (), separation_given: bool = True) -> dict:
    """Fit one poor-instrument trace with each trajectory (no error bars): {trajectory: {force error, relative
    E* and H errors, separation error m}}."""
    from afmid.fit.pipeline import run_fit

    trace, config, truth = simulate_poor(folder, seed, overrides, separation_given)
    loaded = run_fit(config, uncertainty=False)
    out = {}
    for trajectory in TRAJECTORIES:
        result = loaded if trajectory == "default" else run_fit(
            config, uncertainty=False, prepared=prepared_with(trajectory, loaded.prep.trace, trace, config.fit))
        out[trajectory] = {
            "force": force_error(result, trace),
            **{name: (result.quantities[name]["value"] - truth[name]) / truth[name]
               for name in ("E_star", "hamaker") if name in result.quantities and truth.get(name)},
            "d_error": float(result.system.params["d"]) - float(trace.truth.extra["separation"]),
            "terms": result.selected_terms(),
        }
    return out
