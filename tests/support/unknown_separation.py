"""A simulated trace diagnosed as an experimenter would: the separation NOT given.

Shared by the diagnosis tests that need it (tests/diagnosis/test_diagnose_unknown_d.py, test_false_alarms.py,
and with the separation given or not, tests/physics/test_contact_physics.py, test_relaxing_solid_accuracy.py):
simulate ``raw`` (a run config as a dict, ``simulate:`` section included), fit it with ``sample.separation``
absent and the simulator's parameters removed, write the run file and diagnose it from that file.
"""

from __future__ import annotations

import copy
from pathlib import Path


def diagnose_without_separation(tmp_path: Path, raw: dict):
    """(the diagnosis summary, the fit result) of ``raw`` simulated into ``tmp_path``; bootstrap off."""
    return diagnose_simulated(tmp_path, raw, separation_given=False)


def diagnose_simulated(folder: Path, raw: dict, separation_given: bool, stem: str = "trace"):
    """(the diagnosis summary, the fit result) of ``raw`` simulated into ``folder`` as ``stem``.h5 and fitted
    (bootstrap off, no error bars) with the simulator's parameters removed and, unless ``separation_given``,
    ``sample.separation`` absent; the run file ``stem``.run.h5 is written and diagnosed from that file."""
    import afmid.diagnosis.diagnose as diagnose
    from afmid.config import build_config, dump_config
    from afmid.fit.pipeline import run_fit
    from afmid.runfile import run_data, write_run
    from afmid.io.trace import write_trace_file
    from afmid.simulate.driver import simulate

    raw = copy.deepcopy(raw)
    raw.setdefault("fit", {})["bootstrap"] = 0
    sim_config = build_config(raw, source=folder / f"{stem}.sim.yaml", base_dir=folder)
    trace_path = folder / ("trace.h5" if stem == "trace" else f"{stem}.h5")
    write_trace_file(trace_path, simulate(sim_config), dump_config(sim_config))
    fit_raw = copy.deepcopy(raw)
    fit_raw["data"] = {"path": str(trace_path)}
    fit_raw["simulate"]["parameters"] = {}
    if not separation_given:
        fit_raw["sample"]["separation"] = None
    config = build_config(fit_raw, source=folder / f"{stem}.fit.yaml", base_dir=folder)
    result = run_fit(config, uncertainty=False)
    run_path = folder / ("run.h5" if stem == "trace" else f"{stem}.run.h5")
    write_run(run_path, run_data(result, config))
    return diagnose.suggest(diagnose.load_run(run_path)), result
