"""A diagnosis kept (afmid.diagnosis.stored): a report of several runs redoes no run's diagnosis that was made
before, counted in refits (afmid.diagnosis.refit_count.refits_made), not timed.

The runs are tests/report/test_report.py's pair (a glassy polymer, 30 periods: run1 [dmt] misses viscoelasticity,
run2 [dmt, viscoelastic]). Checked: a first report of run1 makes refits; the pair's report after it refits only
run2 and tells run1 exactly as the first report did; a third report refits nothing and writes the same summary as
one made from scratch; the key follows the run's contents, not its file name; the front door's save() after
diagnose() stores the answer in the run file (/diagnosis, numeric datasets with units), reused with the cache off;
an input changed since the fit is not looked up.
"""

from __future__ import annotations

import json
import shutil

import h5py
import pytest

from afmid.diagnosis.diagnose import candidate_effects
from afmid.diagnosis.refit_count import refits_made
from tests.report.test_report import runs  # noqa: F401  (the module-scoped pair of run files)

pytestmark = pytest.mark.slow


def _report(paths, out):
    from afmid.report.page import make_report

    before = refits_made()
    make_report(list(paths), out)
    return refits_made() - before, json.loads((out / "summary.json").read_text())


def _without_times(summary: dict) -> dict:
    """summary.json without what differs between two reports of the same runs: times (the diagnosis's seconds are
    the kept diagnosis's own), run paths."""
    text = json.dumps(summary, sort_keys=True)
    data = json.loads(text)
    data.pop("seconds", None)
    for entry in data.get("tried", []) + data.get("suggestions", []) + data.get("undecided", []):
        entry.pop("seconds", None)
    return data


def test_a_report_of_two_runs_refits_only_the_run_not_diagnosed_before(runs, tmp_path, monkeypatch):  # noqa: F811
    from afmid.runfile import load_run

    from afmid.io.trace import sha256_file

    monkeypatch.setenv("AFMID_DIAGNOSIS_CACHE", str(tmp_path / "cache"))
    run1, run2 = runs
    inputs = {p: sha256_file(p) for p in runs}
    first, single = _report([run1], tmp_path / "r1")
    assert first > 0 and single["suggestions"][0]["effect"] == "viscoelastic"
    paired, pair = _report([run1, run2], tmp_path / "pair")
    second = load_run(run2)
    # run2's own diagnosis only: its base refit and at most one refit per candidate it lacks, sets and instrument
    # aside (there are none: run2 explains the data); far fewer than run1's plus run2's
    lacking = len(candidate_effects(second.effects, second.config.sample.medium))
    assert 1 <= paired <= 1 + lacking
    assert pair["runs"][0]["diagnosis"] == single["runs"][0]["diagnosis"]
    again, pair_again = _report([run1, run2], tmp_path / "pair_again")
    assert again == 0
    assert _without_times(pair_again) == _without_times(pair)
    monkeypatch.setenv("AFMID_DIAGNOSIS_CACHE", "off")  # the same report from scratch: the same numbers
    fresh, pair_fresh = _report([run1, run2], tmp_path / "pair_fresh")
    assert fresh == first + paired
    assert _without_times(pair_fresh) == _without_times(pair)
    assert {p: sha256_file(p) for p in runs} == inputs  # the kept diagnoses are not written into the run files
    assert len(list((tmp_path / "cache").glob("*.json"))) == 2  # one per run diagnosed


def test_the_key_is_the_run_contents_not_its_name(runs, tmp_path):  # noqa: F811
    from afmid.diagnosis.stored import diagnosis_key
    from afmid.runfile import load_run

    run1, run2 = runs
    copy = tmp_path / "renamed.h5"
    shutil.copyfile(run1, copy)
    key = diagnosis_key(load_run(run1))
    assert diagnosis_key(load_run(copy)) == key
    assert diagnosis_key(load_run(run2)) != key
    assert diagnosis_key(load_run(run1), {"quick_shape": False}) != key
    changed = load_run(run1)
    changed.coefficients = changed.coefficients * (1 + 1e-15)
    assert diagnosis_key(changed) != key


def test_a_changed_input_is_not_looked_up(runs, tmp_path, monkeypatch):  # noqa: F811
    from afmid.diagnosis.stored import diagnosed, diagnosis_key, remember
    from afmid.runfile import load_run

    monkeypatch.setenv("AFMID_DIAGNOSIS_CACHE", str(tmp_path / "cache"))
    folder = tmp_path / "moved"
    folder.mkdir()
    run = load_run(runs[1])
    trace = folder / "trace.h5"
    shutil.copyfile(run.input_path, trace)
    run.input_path = trace
    kept = {"missing_effect": False, "suggestions": [], "tried": [], "diagnosis": {"verdict": "kept"}}
    remember(diagnosis_key(run), kept, "run2.h5")
    before = refits_made()
    assert diagnosed(run) == kept and refits_made() == before
    with h5py.File(trace, "a") as h5:  # another trace under the same name
        h5.attrs["changed"] = 1
    answer = diagnosed(run)
    assert refits_made() == before and "changed since the run was made" in answer["note"]


def test_save_after_diagnose_keeps_the_answer_in_the_run_file(runs, tmp_path, monkeypatch):  # noqa: F811
    import afmid
    from afmid.config import build_config, read_yaml
    from afmid.report.page import make_report
    from afmid.runfile import load_run
    from tests.report.test_report import CONFIG

    monkeypatch.setenv("AFMID_DIAGNOSIS_CACHE", "off")
    raw = read_yaml(CONFIG)
    raw["data"] = {"path": str(load_run(runs[0]).input_path)}
    raw["model"]["effects"] = ["dmt"]
    raw["sample"]["separation"] = 8.0e-9
    fit = afmid.Fit.from_config(build_config(raw, source=CONFIG, base_dir=tmp_path))
    made = fit.diagnose()
    saved = fit.save(tmp_path / "saved.h5")
    with h5py.File(saved, "r") as h5:
        group = h5["diagnosis"]
        assert group.attrs["afmid_version"] == afmid.__version__
        numeric = [ds for ds in group.values() if ds.dtype.kind == "f"]
        assert numeric and all(ds.attrs["units"] == "1" for ds in numeric)
        assert [e.decode() for e in group["tried_effect"][...]] == [t["effect"] for t in made.details["tried"]]
    before = refits_made()
    loaded = afmid.load(saved).diagnose()
    assert refits_made() == before
    assert loaded.details == made.details and loaded.suggested == "viscoelastic"
    make_report([saved], tmp_path / "report")
    assert refits_made() == before
    summary = json.loads((tmp_path / "report" / "summary.json").read_text())
    assert [t["delta_bic"] for t in summary["tried"]] == [t["delta_bic"] for t in made.details["tried"]]
