"""afmid.diagnosis.forked_work: a diagnosis's independent searches shared with a forked child give what one process
gives, in order, with the refits counted, the errors raised where they would be serially, and no child left.

The last test diagnoses a trace whose candidates' separations are searched and whose undeclared second mode is
searched (d unknown, hidden_clean.yaml with the 6.27 f0 mode of tests/diagnosis/test_instrument_evidence.py left out
of the fit's config): the summary with ``AFMID_REPORT_JOBS=2`` equals the one with 1, to the last digit."""

from __future__ import annotations

import copy
import json
import multiprocessing
import os
import time

import pytest

from afmid.diagnosis.forked_work import REPORT_JOBS_ENV, each_in_order, in_order, serial_reason
from afmid.diagnosis.refit_count import count_refit, refits_made
from afmid.threads import TRACE_THREADS_ENV, trace_threads

FORKS = serial_reason(2) is None
needs_fork = pytest.mark.skipif(not FORKS, reason=f"one process here: {serial_reason(2)}")


def _square_and_pid(item: int) -> tuple[int, int]:
    return item * item, os.getpid()


def test_one_job_makes_everything_here():
    assert in_order(_square_and_pid, range(5), jobs=1) == [(i * i, os.getpid()) for i in range(5)]
    assert serial_reason(1) == f"{REPORT_JOBS_ENV}=1"


@needs_fork
def test_two_jobs_share_the_items_and_give_them_in_order():
    def slow(item: int) -> tuple[int, int, int]:
        time.sleep(0.05)  # long enough that the child takes items while this process works on others
        return (*_square_and_pid(item), trace_threads())

    alone = trace_threads()
    got = in_order(slow, range(12), jobs=2)
    assert [value for value, _, _ in got] == [i * i for i in range(12)]
    pids = {pid for _, pid, _ in got}
    assert os.getpid() in pids and len(pids) == 2, pids
    # One chunk thread per process while both work (unless AFMID_TRACE_THREADS says otherwise), as before after.
    if not os.environ.get(TRACE_THREADS_ENV):
        assert got[0][2] == 1, got
    assert trace_threads() == alone
    assert multiprocessing.active_children() == []


@needs_fork
def test_the_childs_refits_are_counted_here():
    def refit(item: int) -> int:
        count_refit()
        time.sleep(0.05)  # the child takes items while this process works on others
        return os.getpid()

    before = refits_made()
    pids = in_order(refit, range(8), jobs=2)
    assert refits_made() - before == 8 and len(set(pids)) == 2


@needs_fork
def test_an_error_is_raised_at_its_item_after_the_items_before_it():
    def work(item: int) -> int:
        if item == 3:
            raise ValueError("item 3 cannot be made")
        return item

    got = []
    with pytest.raises(ValueError, match="item 3"):
        for value in each_in_order(work, range(8), jobs=2):
            got.append(value)
    assert got == [0, 1, 2]
    assert multiprocessing.active_children() == []


class _Keyed(Exception):
    """An exception that pickles but cannot be made again from its arguments (a keyword-only argument)."""

    def __init__(self, message: str, *, key: str):
        super().__init__(message)
        self.key = key


def _parent_slow(parent: int) -> None:
    """This process takes its time over an item, the child none: the child claims the items after the first."""
    if os.getpid() == parent:
        time.sleep(0.3)


@needs_fork
def test_what_the_child_cannot_send_is_made_here_and_a_dead_childs_items_too(tmp_path):
    """A result that does not pickle (a function) is made again here; so are the items of a child that dies (the
    child is seen to have tried both)."""
    parent = os.getpid()

    def work(item: int):
        _parent_slow(parent)
        if os.getpid() != parent:
            (tmp_path / f"child-{item}").touch()
            if item == 5:
                os._exit(3)  # the child dies
        if item == 2:
            return lambda: item  # not picklable
        return item

    for jobs in (1, 2):
        got = in_order(work, range(8), jobs=jobs)
        assert [g() if callable(g) else g for g in got] == list(range(8))
    assert (tmp_path / "child-2").exists() and (tmp_path / "child-5").exists()
    assert multiprocessing.active_children() == []


@needs_fork
def test_an_exception_that_cannot_be_sent_is_raised_here(tmp_path):
    parent = os.getpid()

    def work(item: int) -> int:
        _parent_slow(parent)
        if os.getpid() != parent:
            (tmp_path / f"child-{item}").touch()
        if item == 4:
            raise _Keyed("item 4", key="k")
        return item

    for jobs in (1, 2):
        got = []
        with pytest.raises(_Keyed, match="item 4"):
            for value in each_in_order(work, range(6), jobs=jobs):
                got.append(value)
        assert got == [0, 1, 2, 3]
    assert (tmp_path / "child-4").exists()
    assert multiprocessing.active_children() == []


def _diagnosed_with(jobs: str, monkeypatch, run_path):
    import afmid.diagnosis.diagnose as diagnose

    monkeypatch.setenv(REPORT_JOBS_ENV, jobs)
    before = refits_made()
    summary = diagnose.suggest(diagnose.load_run(run_path))
    refits = refits_made() - before
    summary.pop("seconds")
    for entry in summary["tried"] + summary["suggestions"]:
        entry.pop("seconds")
    return json.dumps(summary, sort_keys=True, default=repr), refits, summary


@needs_fork
@pytest.mark.numerics
@pytest.mark.slow
def test_the_diagnosis_is_the_same_with_two_processes(tmp_path, monkeypatch):
    from afmid.config import apply_overrides, build_config, dump_config, parse_override, read_yaml
    from afmid.fit.pipeline import run_fit
    from afmid.io.trace import write_trace_file
    from afmid.runfile import run_data, write_run
    from afmid.simulate.driver import simulate
    from repo_paths import TEST_CONFIGS

    raw = apply_overrides(read_yaml(TEST_CONFIGS / "hidden_clean.yaml"), [parse_override(
        "cantilever.higher_modes=[{resonance_frequency: 1.881e6, quality_factor: 750, spring_constant: 1572}]")])
    raw.setdefault("fit", {})["bootstrap"] = 0
    simulated = build_config(raw, source=tmp_path / "sim.yaml", base_dir=tmp_path)
    write_trace_file(tmp_path / "trace.h5", simulate(simulated), dump_config(simulated))
    fit_raw = copy.deepcopy(raw)
    fit_raw["data"] = {"path": str(tmp_path / "trace.h5")}
    fit_raw["simulate"]["parameters"] = {}
    fit_raw["sample"]["separation"] = None  # estimated: every candidate's separation is searched
    fit_raw["cantilever"].pop("higher_modes")  # undeclared: the instrument search runs
    config = build_config(fit_raw, source=tmp_path / "fit.yaml", base_dir=tmp_path)
    write_run(tmp_path / "run.h5", run_data(run_fit(config, uncertainty=False), config))
    serial, serial_refits, summary = _diagnosed_with("1", monkeypatch, tmp_path / "run.h5")
    shared, shared_refits, _ = _diagnosed_with("2", monkeypatch, tmp_path / "run.h5")
    assert summary["diagnosis"]["verdict"].startswith("instrument: second eigenmode"), summary["diagnosis"]["verdict"]
    assert len(summary["tried"]) >= 6 and all(entry["separation"] > 0 for entry in summary["tried"])
    assert shared == serial
    assert shared_refits == serial_refits > 50  # the candidates' and the instrument search's refits
    assert multiprocessing.active_children() == []
