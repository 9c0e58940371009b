"""Progress (afmid/progress.py): named stages, counts of what is counted, no rates; plain lines (one per stage,
no carriage return) when stderr is not a terminal, one rewritten line erased at the end when it is."""

from __future__ import annotations

import io
import logging
import re

from short_runs import short_dmt_viscoelastic_config

from afmid.progress import Progress, counted


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_not_a_terminal_gives_one_plain_line_per_stage():
    stream = io.StringIO()
    bar = Progress("simulate", stream=stream)
    assert not bar.terminal  # a StringIO is not a terminal
    bar.stage("settling (at most 3000 periods)")
    bar.advance(120)
    bar.stage("recording", total=50, unit="periods")
    for _ in range(50):
        bar.advance()
    bar.stage("selecting terms", step=(4, 6))
    bar.close()
    assert stream.getvalue().splitlines() == [
        "simulate: settling (at most 3000 periods)",
        "simulate: recording (50 periods)",
        "simulate: selecting terms (4/6)",
    ]
    assert "\r" not in stream.getvalue()


def test_a_terminal_line_counts_and_is_erased_at_the_end():
    stream = _Terminal()
    bar = Progress("batch", stream=stream)
    assert bar.terminal
    bar.stage("fitting", total=4, unit="traces")
    bar.advance(3)
    assert bar.text() == "batch: fitting 3/4 traces"
    bar.close()
    shown = stream.getvalue()
    assert "\rbatch: fitting 0/4 traces" in shown
    assert shown.endswith("\r")  # erased: what the command prints next starts on a clean line
    assert not re.search(r"it/s|/s\b|[0-9]period", shown)


def test_a_log_record_erases_the_terminal_line_first():
    stream = _Terminal()
    logger = logging.getLogger("afmid")
    records = io.StringIO()
    handler = logging.StreamHandler(records)
    saved = list(logger.handlers)
    logger.handlers[:] = [handler]
    try:
        with Progress("report", stream=stream) as bar:
            bar.stage("trying effects", total=3, unit="effects")
            logger.warning("a warning")
            assert stream.getvalue().endswith("\r")  # the line was erased before the record
        assert handler.filters == []  # the filter is gone with the progress
    finally:
        logger.handlers[:] = saved


def test_counted_counts_the_items():
    stream = io.StringIO()
    assert list(counted(["a", "b"], "report", "trying effects", "effects", enabled=False)) == ["a", "b"]
    bar = Progress("report", stream=stream)
    bar.stage("trying effects", total=2, unit="effects")
    assert stream.getvalue() == "report: trying effects (2 effects)\n"


def test_simulate_and_fit_without_a_terminal_name_their_stages(tmp_path, run_cli):
    config = short_dmt_viscoelastic_config(tmp_path)
    code, _, err = run_cli("simulate", config, "-o", tmp_path / "trace.h5")
    assert code == 0, err
    assert "\r" not in err
    lines = err.splitlines()
    assert lines[:2] == ["simulate: settling (at most 20000 periods)",  # simulate.max_settle_periods
                         "simulate: thermal warm-up (" + lines[1].split("(")[1]]
    assert "simulate: recording (12 periods)" in lines
    code, _, err = run_cli("fit", config, "-o", tmp_path / "run.h5")
    assert code == 0, err
    assert "\r" not in err
    stages = [line for line in err.splitlines() if line.startswith("fit: ")]
    assert stages == ["fit: preparing periods (1/5)", "fit: searching the drive (2/5)", "fit: selecting terms (3/5)",
                      "fit: error bars (10 resamples) (4/5)", "fit: error and forces (5/5)"]
    assert not re.search(r"it/s|[0-9]period", err)
    code, _, err = run_cli("-q", "fit", config, "-o", tmp_path / "run.h5", "--overwrite")
    assert code == 0 and not [line for line in err.splitlines() if line.startswith("fit: ")]


def test_named_items_on_a_pipe_give_one_line_per_finished_item():
    """issue 31: `afmid report`'s candidates on a pipe: the stage's line, then one line per candidate when done."""
    stream = io.StringIO()
    bar = Progress("report", stream=stream)
    bar.stage("trying effects", total=3, unit="effects")
    for effect in ("viscoelastic", "capillary", "hydration"):
        bar.item(effect)
        assert stream.getvalue().count("\n") == 1 + ["viscoelastic", "capillary", "hydration"].index(effect)
        bar.advance()
    bar.close()
    lines = stream.getvalue().splitlines()
    assert lines[0] == "report: trying effects (3 effects)"
    assert [re.sub(r", [0-9.]+ s\)$", ", T s)", line) for line in lines[1:]] == [
        "report: trying effects: viscoelastic done (1/3 effects, T s)",
        "report: trying effects: capillary done (2/3 effects, T s)",
        "report: trying effects: hydration done (3/3 effects, T s)"]
    assert "\r" not in stream.getvalue() and "ETA" not in stream.getvalue()


PTY_CHILD = r"""
import sys, time
from afmid.progress import counted
for effect in counted(["viscoelastic", "capillary", "hydration"], "report", "trying effects", "effects", named=True):
    time.sleep(0.6)  # an item of 0.6 s: the ETA is shown from the stage's second second on
print("done", file=sys.stderr)
"""


def test_on_a_pseudo_terminal_the_bar_names_the_candidate_and_an_eta():
    """issue 31: a real pseudo-terminal (pty) as stderr: the rewritten line names the candidate being refitted and,
    once one is done and a second has passed, the estimated time left; the line is erased at the end."""
    import os
    import pty
    import subprocess
    import sys

    master, slave = pty.openpty()
    try:
        child = subprocess.Popen([sys.executable, "-c", PTY_CHILD], stdin=subprocess.DEVNULL,
                                 stdout=subprocess.DEVNULL, stderr=slave, close_fds=True)
        os.close(slave)
        shown = b""
        while True:
            try:
                chunk = os.read(master, 4096)
            except OSError:  # EIO: the child closed the terminal
                break
            if not chunk:
                break
            shown += chunk
        assert child.wait(timeout=120) == 0
    finally:
        os.close(master)
    text = shown.decode()
    assert "\rreport: trying effects 0/3 effects: viscoelastic" in text
    assert "report: trying effects 1/3 effects: capillary" in text
    assert re.search(r"report: trying effects 2/3 effects: hydration, ETA [0-9]+ s", text), text
    assert " done (" not in text  # the pipe's lines are not written to a terminal
    assert text.replace("\r\n", "\n").rstrip("\n").endswith("\rdone")  # the terminal turns \n into \r\n
    assert "\r" + " " * 20 in text  # the line erased before the command's output


def test_report_on_a_pipe_says_each_candidate_when_it_is_done(tmp_path, run_cli, monkeypatch):
    """issue 31: `afmid report`'s diagnosis on a pipe (stderr captured): the stage line with the number of
    candidates, then exactly one line per candidate effect when its refit is done, no carriage return."""
    monkeypatch.setenv("AFMID_DIAGNOSIS_CACHE", str(tmp_path / "diagnoses"))  # diagnosed here, not reused
    config = short_dmt_viscoelastic_config(tmp_path)
    code, _, err = run_cli("-q", "simulate", config, "-o", tmp_path / "trace.h5")
    assert code == 0, err
    code, _, err = run_cli("-q", "fit", config, "-o", tmp_path / "run.h5", "--remove", "viscoelastic")
    assert code == 0, err
    code, _, err = run_cli("report", tmp_path / "run.h5", "-o", tmp_path / "report")
    assert code == 0, err
    assert "\r" not in err
    stage = [line for line in err.splitlines() if line.startswith("report: trying effects (")]
    assert len(stage) == 1, err
    total = int(re.match(r"report: trying effects \((\d+) effects\)", stage[0]).group(1))
    done = [line for line in err.splitlines() if line.startswith("report: trying effects: ")]
    assert len(done) == total >= 2, err
    for k, line in enumerate(done, start=1):
        assert re.fullmatch(rf"report: trying effects: [a-z_]+ done \({k}/{total} effects, [0-9]+\.[0-9] s\)", line)
    assert "report: trying effects: viscoelastic done" in err  # the effect the run lacks is among them
