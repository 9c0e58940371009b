"""Data loss must never happen (issue 11): inputs as outputs, report folders, one batch per folder.

- :func:`afmid.io.trace.refuse_input_as_output` sees through symbolic and hard links and relative spellings;
- ``afmid report --overwrite`` replaces a report folder afmid wrote (marker ``.afmid-report``) and only that,
  by swapping in a complete new folder: an interrupted report, or one whose folder gained a foreign file
  meanwhile, leaves the old report as it was and no temporary folder; an unwritable place is one line;
- two real ``afmid batch`` processes on one folder: the second fails at once naming the first; a lock left by
  a dead process (killed outright, or a leftover file) does not block.

The bad-input side (one line, nothing changed) is in tests/cli/test_corpus_safety.py.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import yaml

from afmid.errors import OutputError
from afmid.io.trace import refuse_input_as_output
from tests.cli.test_corpus_config import base_config, write_tapping_csv
from terminal_signals import ctrl_c_raises

AFMID = [sys.executable, "-m", "afmid.cli"]
LOCK = ".afmid-batch.lock"


def _tmp_leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".afmid-tmp-"))


# --------------------------------------------------------------------------- inputs as outputs
def test_an_input_is_recognised_through_links_and_spellings(tmp_path):
    (tmp_path / "trace.csv").write_text("x\n1\n")
    (tmp_path / "other.csv").write_text("x\n1\n")  # same bytes, another file: not an input
    os.symlink("trace.csv", tmp_path / "soft.csv")
    os.link(tmp_path / "trace.csv", tmp_path / "hard.csv")
    os.symlink(".", tmp_path / "alias")
    inputs = {tmp_path / "trace.csv": "the trace", None: "ignored"}
    for output in ("trace.csv", "soft.csv", "hard.csv", "alias/trace.csv", "sub/../trace.csv"):
        with pytest.raises(OutputError, match=r"is an input of this command \(the trace\)") as caught:
            refuse_input_as_output(tmp_path / output, inputs)
        assert caught.value.file == str(tmp_path / output)
    refuse_input_as_output(tmp_path / "other.csv", inputs)
    refuse_input_as_output(tmp_path / "new.h5", inputs)
    refuse_input_as_output(tmp_path / "report", inputs, folder=True)
    with pytest.raises(OutputError, match="holds an input of this command"):
        refuse_input_as_output(tmp_path, inputs, folder=True)
    with pytest.raises(OutputError, match="is an input"):  # a list of outputs: the one that is an input is named
        refuse_input_as_output([tmp_path / "a.h5", tmp_path / "hard.csv"], inputs, key="--output")


def test_a_missing_input_compares_by_its_resolved_path(tmp_path):
    with pytest.raises(OutputError, match="is an input"):
        refuse_input_as_output(tmp_path / "x" / ".." / "later.h5", {tmp_path / "later.h5": "the trace"})


# --------------------------------------------------------------------------- report folders
@pytest.fixture(scope="module")
def run_path(tmp_path_factory) -> Path:
    """A run file of the corpus tapping trace."""
    from afmid.cli import main

    folder = tmp_path_factory.mktemp("safety-report-run")
    write_tapping_csv(folder)
    (folder / "run.yaml").write_text(yaml.safe_dump(base_config(**{"fit.bootstrap": 8}), sort_keys=False))
    assert main(["-q", "fit", str(folder / "run.yaml"), "-o", str(folder / "r.h5")]) == 0
    return folder / "r.h5"


@pytest.fixture(scope="module")
def made_report(run_path, tmp_path_factory) -> Path:
    """A report folder afmid wrote (kept pristine: tests copy it)."""
    from afmid.report.page import make_report

    out = tmp_path_factory.mktemp("safety-report") / "rep"
    make_report([run_path], out, suggest_effects=False)
    return out


def _copy_report(made: Path, dest: Path) -> dict[str, bytes]:
    dest.mkdir(parents=True)
    for p in made.iterdir():
        (dest / p.name).write_bytes(p.read_bytes())
    return {p.name: p.read_bytes() for p in dest.iterdir()}


def _contents(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def test_the_marker_lists_what_afmid_wrote(made_report):
    marker = json.loads((made_report / ".afmid-report").read_text())
    assert marker["format"] == "afmid-report" and marker["afmid_version"]
    assert sorted(marker["files"]) == sorted(p.name for p in made_report.iterdir() if p.name != ".afmid-report")
    assert {"report.html", "summary.json"} <= set(marker["files"])


def test_overwrite_replaces_afmids_own_report_folder(made_report, run_path, tmp_path, run_cli):
    out = tmp_path / "rep"
    _copy_report(made_report, out)
    marker = json.loads((out / ".afmid-report").read_text())
    (out / "old_figure.png").write_bytes(b"an older report's figure")  # afmid's own, listed in its marker
    marker["files"].append("old_figure.png")
    (out / ".afmid-report").write_text(json.dumps(marker))
    code, stdout, err = run_cli("-q", "report", run_path, "-o", out, "--overwrite", "--no-suggest")
    assert code == 0, err
    assert "report.html" in stdout
    assert not (out / "old_figure.png").exists()
    assert "old_figure.png" not in json.loads((out / ".afmid-report").read_text())["files"]
    assert (out / "report.html").read_text(encoding="utf-8").startswith("<!doctype html>")
    assert _tmp_leftovers(tmp_path) == []


def test_report_through_a_symlink_replaces_the_folder_it_points_to(made_report, run_path, tmp_path, run_cli):
    real = tmp_path / "reports" / "rep"
    _copy_report(made_report, real)
    os.symlink(real, tmp_path / "latest")
    (real / "summary.json").write_text("{}")  # so that the replacement is visible
    code, _, err = run_cli("-q", "report", run_path, "-o", tmp_path / "latest", "--overwrite", "--no-suggest")
    assert code == 0, err
    assert (tmp_path / "latest").is_symlink() and json.loads((real / "summary.json").read_text())["runs"]
    assert _tmp_leftovers(tmp_path) == [] and _tmp_leftovers(real.parent) == []


def test_an_interrupted_report_leaves_the_old_one_and_no_temporary_folder(made_report, run_path, tmp_path,
                                                                          monkeypatch):
    import afmid.report.page
    from afmid.report.page import make_report

    out = tmp_path / "rep"
    before = _copy_report(made_report, out)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(afmid.report.page, "fig_periods", interrupted)
    with ctrl_c_raises(), pytest.raises(KeyboardInterrupt):
        make_report([run_path], out, overwrite=True, suggest_effects=False)
    assert _contents(out) == before
    assert _tmp_leftovers(tmp_path) == []


def test_ctrl_c_during_the_swap_still_leaves_one_whole_report(made_report, run_path, tmp_path, monkeypatch):
    """Ctrl-C right when the old report is removed: the swap finishes first (the new report is whole), then the
    interrupt arrives; never neither report."""
    import shutil

    from afmid.report.page import make_report

    out = tmp_path / "rep"
    _copy_report(made_report, out)
    remove = shutil.rmtree
    sent = []

    def remove_then_ctrl_c(path, *args, **kwargs):
        remove(path, *args, **kwargs)
        if not sent:
            sent.append(path)
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(shutil, "rmtree", remove_then_ctrl_c)
    with ctrl_c_raises(), pytest.raises(KeyboardInterrupt):
        make_report([run_path], out, overwrite=True, suggest_effects=False)
    assert sent, "the old report was never removed"
    marker = json.loads((out / ".afmid-report").read_text())
    assert sorted(marker["files"]) == sorted(p.name for p in out.iterdir() if p.name != ".afmid-report")
    assert (out / "report.html").read_text(encoding="utf-8").rstrip().endswith("</html>")
    assert _tmp_leftovers(tmp_path) == []


def test_a_file_put_in_the_folder_while_the_report_is_made_is_kept(made_report, run_path, tmp_path, monkeypatch):
    import afmid.report.page
    from afmid.report.page import make_report

    out = tmp_path / "rep"
    before = _copy_report(made_report, out)
    draw_periods = afmid.report.page.fig_periods

    def user_saves_a_file_meanwhile(*args, **kwargs):
        (out / "notes.txt").write_text("written by the user while the report ran")
        return draw_periods(*args, **kwargs)

    monkeypatch.setattr(afmid.report.page, "fig_periods", user_saves_a_file_meanwhile)
    with pytest.raises(OutputError, match=r"did not write \(notes.txt\)"):
        make_report([run_path], out, overwrite=True, suggest_effects=False)
    assert _contents(out) == {**before, "notes.txt": b"written by the user while the report ran"}
    assert _tmp_leftovers(tmp_path) == []


def test_unwritable_report_place_is_one_line(run_path, tmp_path, monkeypatch, run_cli):
    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkdtemp", read_only)
    code, _, err = run_cli("report", run_path, "-o", tmp_path / "rep", "--no-suggest")
    assert code == 1
    assert err == (f"afmid: error: {tmp_path / 'rep'}: cannot write in folder {tmp_path}: "
                   "Read-only file system\n")
    assert not (tmp_path / "rep").exists()


def test_report_on_a_really_read_only_file_system(run_path, tmp_path, run_cli):
    mount = tmp_path / "ro"
    mount.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "ro", "tmpfs", str(mount)],
                                           capture_output=True).returncode != 0:
        pytest.skip("needs root to mount a read-only tmpfs")
    try:
        code, _, err = run_cli("report", run_path, "-o", mount / "rep", "--no-suggest")
    finally:
        subprocess.run(["umount", str(mount)], check=True)
    assert code == 1
    assert err == f"afmid: error: {mount / 'rep'}: cannot write in folder {mount}: Read-only file system\n"


# --------------------------------------------------------------------------- one batch per folder
def _batch_workspace(folder: Path, n_traces: int = 2) -> list[str]:
    """run.yaml and traces t1.csv..tN.csv; returns the batch arguments (without -o)."""
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(1, n_traces + 1):
        write_tapping_csv(folder, f"t{i}.csv")
    (folder / "run.yaml").write_text(yaml.safe_dump(base_config(**{"fit.bootstrap": 8}), sort_keys=False))
    return ["-q", "batch", str(folder / "run.yaml"), "--inputs", str(folder / "t*.csv"), "-j", "1"]


def _wait_for(predicate, timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            raise AssertionError("timed out")
        time.sleep(0.05)


def test_a_second_batch_on_the_same_folder_fails_at_once_naming_the_first(tmp_path):
    args = _batch_workspace(tmp_path / "ws")
    out = tmp_path / "out"
    from batch_workers import HOLD_2S

    # the first batch stays busy a few seconds (afmid batch's run_batch with a worker that holds every item 2 s);
    # the second is afmid's own command
    first = subprocess.Popen(HOLD_2S + args[args.index("batch") + 1:] + ["-o", str(out)], stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(lambda: (out / LOCK).is_file() and (out / LOCK).read_text().strip())
        holder = (out / LOCK).read_text().strip()
        assert holder.startswith(f"pid {first.pid} on host ")
        start = time.monotonic()
        second = subprocess.run(AFMID + args + ["-o", str(out)], capture_output=True, text=True, timeout=60)
        took = time.monotonic() - start
        assert first.poll() is None, "the first batch should still be running"
    finally:
        first_err = first.communicate(timeout=300)[1]
    assert second.returncode == 1
    assert second.stderr == (f"afmid: error: {out}: --output: another afmid batch is writing to this folder "
                             f"({holder}); wait for it to finish or choose another output folder\n")
    assert took < 10, f"the second batch took {took:.1f} s to refuse"
    assert first.returncode == 0, first_err
    with open(out / "summary.csv") as fh:
        assert [line.split(",")[1] for line in fh.read().splitlines()[1:]] == ["ok", "ok"]
    assert not (out / LOCK).exists() and not [p for p in out.iterdir() if p.name.startswith(".afmid-tmp-")]


def test_a_lock_left_by_a_killed_process_does_not_block(tmp_path):
    from afmid.batch.run import run_batch

    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\nfrom pathlib import Path\nfrom afmid.batch.folder_lock import folder_lock\n"
        "with folder_lock(Path(sys.argv[1])):\n    print('held', flush=True)\n    time.sleep(600)\n"), str(out)],
        stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(base_config(), sort_keys=False))
    (tmp_path / "list.csv").write_text("path\nmissing.csv\n")
    with pytest.raises(OutputError, match=f"another afmid batch .*pid {holder.pid} on host"):
        run_batch(tmp_path / "run.yaml", out, manifest=tmp_path / "list.csv")
    assert sorted(p.name for p in out.iterdir()) == [LOCK]  # refused before writing anything
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait()
    assert (out / LOCK).is_file()  # the file stays, the lock went with the process
    _run_failing_batch(tmp_path, out)
    assert not (out / LOCK).exists()


def test_a_leftover_lock_file_with_a_dead_pid_does_not_block(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK).write_text("pid 999999 on host gone, started 2026-01-01T00:00:00+00:00\n")
    _run_failing_batch(tmp_path, out)
    assert not (out / LOCK).exists()


def _run_failing_batch(tmp_path: Path, out: Path) -> None:
    """A batch whose one trace is missing: it plans, takes the lock, writes the summary, no worker needed."""
    from afmid.batch.run import run_batch

    (tmp_path / "run.yaml").write_text(yaml.safe_dump(base_config(), sort_keys=False))
    (tmp_path / "list.csv").write_text("path\nmissing.csv\n")
    result = run_batch(tmp_path / "run.yaml", out, manifest=tmp_path / "list.csv")
    assert [r.status for r in result.rows] == ["failed"]
    assert (out / "summary.csv").is_file()
