"""A simulated trace diagnosed as an experimenter would: the separation NOT given.

Shared by the diagnosis tests that need it (tests/diagnosis/test_diagnose_unknown_d.py, test_false_alarms.py):
simulate ``raw`` (a run config as a dict, ``simulate:`` section included), fit it with ``sample.separation``
absent and the simulator's parameters removed, write the run file and diagnose it from that file.
"""

from __future__ import annotations

import copy
from pathlib import Path


def diagnose_without_separation(tmp_path: Path, raw: dict):
    """(the diagnosis summary, the fit result) of ``raw`` simulated into ``tmp_path``; bootstrap off."""
    import afmid.diagnosis.diagnose as diagnose
    from afmid.config import build_config, dump_config
    from afmid.fit.pipeline import run_fit, write_run
    from afmid.io.trace import write_trace_file
    from afmid.simulate.driver import simulate

    raw = copy.deepcopy(raw)
    raw.setdefault("fit", {})["bootstrap"] = 0
    sim_config = build_config(raw, source=tmp_path / "sim.yaml", base_dir=tmp_path)
    write_trace_file(tmp_path / "trace.h5", simulate(sim_config), dump_config(sim_config))
    fit_raw = copy.deepcopy(raw)
    fit_raw["data"] = {"path": str(tmp_path / "trace.h5")}
    fit_raw["simulate"]["parameters"] = {}
    fit_raw["sample"]["separation"] = None
    config = build_config(fit_raw, source=tmp_path / "fit.yaml", base_dir=tmp_path)
    result = run_fit(config, uncertainty=False)
    write_run(tmp_path / "run.h5", result, config)
    return diagnose.suggest(diagnose.load_run(tmp_path / "run.h5")), result
