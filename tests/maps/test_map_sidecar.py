"""The map's sidecar folder (``RESULT.h5.afmid-map/``) is afmid's own, and nothing in it is lost (issue 32).

- A folder of that name without afmid's marker (a user's) is refused with one line, nothing in it touched; a
  symbolic link at that path is refused, never followed.
- A damaged chunk (truncated npz) or a foreign one (another pixel range, another config) is discarded with a
  one-line note and its pixels fitted again: the resumed maps equal an uninterrupted run's, bit for bit.
- Two runs on one output do not interleave: the second refuses at once, naming the first's pid.
- An engine that loses its tasks (afmid.errors.EngineError) leaves the finished chunks and no result; the same
  command then resumes.

The map is tests/configs/map_small.yaml (3x3 pixels, 5 chunks of 2 pixels), fitted in this process by a serial
engine (same code path as a worker, one BLAS thread), so two runs that fit the same chunks give the same bits.
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from afmid.batch.engine import Outcome
from afmid.errors import OutputError
from repo_paths import REPO_ROOT

CONFIG = REPO_ROOT / "tests" / "configs" / "map_small.yaml"
CHUNK = 2
N_CHUNKS = 5  # 9 pixels in chunks of 2


class SerialEngine:
    """The engine protocol (afmid.batch.engine.Engine) in this process, one chunk after another.

    ``stop_after``: raise ``stop`` once that many chunks are reported (an interrupt, a lost cluster).
    ``between``: called with the count after each report (e.g. a second run started meanwhile).
    ``ran``: the keys of the chunks fitted."""

    scheduler = None

    def __init__(self, stop_after: int | None = None, stop: BaseException | None = None, between=None):
        self.stop_after, self.stop, self.between = stop_after, stop or KeyboardInterrupt(), between
        self.ran: list[int] = []

    def workers_for(self, n_tasks: int) -> int:
        return 1

    def run(self, worker, tasks, report, tick) -> None:
        for count, (key, task) in enumerate(tasks, 1):
            self.ran.append(key)
            report(Outcome(key, worker(task)))
            if self.between is not None:
                self.between(count)
            if count == self.stop_after:
                raise self.stop


class RefusingEngine(SerialEngine):
    """An engine the map must never reach (it has refused before fitting anything)."""

    def run(self, worker, tasks, report, tick) -> None:
        raise AssertionError("the map went on to fit pixels instead of refusing")


def run(workspace: Path, output: str, engine, overrides: tuple[str, ...] = ()) -> dict:
    from afmid.config import dump_config, load_config
    from afmid.maps.run import run_map

    config = load_config(CONFIG, list(overrides))
    return run_map(config, dump_config(config), workspace / "map.h5", workspace / output, engine, chunk=CHUNK,
                   diagnose=False)


def sidecar(workspace: Path, output: str) -> Path:
    return workspace / (output + ".afmid-map")


def chunk_file(workspace: Path, output: str, index: int) -> Path:
    return sidecar(workspace, output) / f"chunk_{index:06d}.npz"


def read_maps(path: Path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as h5:
        return {name: ds[()] for name, ds in h5["maps"].items()}


def assert_identical(a: Path, b: Path) -> None:
    ma, mb = read_maps(a), read_maps(b)
    assert ma.keys() == mb.keys()
    for name in ma:
        np.testing.assert_array_equal(ma[name], mb[name], err_msg=name)


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (links not followed) with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def interrupted(workspace: Path, output: str, after: int, overrides: tuple[str, ...] = ()) -> None:
    """A run stopped by Ctrl-C once ``after`` chunks are saved."""
    with pytest.raises(KeyboardInterrupt):
        run(workspace, output, SerialEngine(stop_after=after), overrides)
    assert sorted(p.name for p in sidecar(workspace, output).glob("chunk_*.npz")) == \
        [f"chunk_{i:06d}.npz" for i in range(after)]


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    ws = tmp_path_factory.mktemp("sidecar")
    done = subprocess.run([sys.executable, "-m", "afmid.cli", "-q", "simulate", str(CONFIG), "-o", "map.h5"],
                          cwd=ws, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return ws


@pytest.fixture(scope="module")
def whole(workspace) -> Path:
    """The map fitted in one uninterrupted run."""
    engine = SerialEngine()
    counts = run(workspace, "whole.h5", engine)
    assert engine.ran == list(range(N_CHUNKS)) and counts["failed"] == 0, counts
    assert not sidecar(workspace, "whole.h5").exists()
    return workspace / "whole.h5"


def one_line_error(exc: pytest.ExceptionInfo) -> str:
    text = exc.value.format()
    assert "\n" not in text
    return text


# --------------------------------------------------------------------------- refused: not afmid's folder
def test_a_users_folder_of_the_sidecars_name_is_refused_and_left_untouched(workspace):
    folder = sidecar(workspace, "notes.h5")
    folder.mkdir()
    (folder / "notes.txt").write_text("my notes on this sample\n")
    (folder / "key.json").write_text("{}")  # even with a file of afmid's names in it
    before = snapshot(folder)
    with pytest.raises(OutputError) as exc:
        run(workspace, "notes.h5", RefusingEngine())
    text = one_line_error(exc)
    assert str(folder) in text and "not afmid's" in text
    assert exc.value.exit_code == 1
    assert snapshot(folder) == before
    assert not (workspace / "notes.h5").exists()


def test_a_symbolic_link_at_the_sidecars_path_is_refused_and_not_followed(workspace, tmp_path):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "data.txt").write_text("somebody else's\n")
    link = sidecar(workspace, "linked.h5")
    link.symlink_to(foreign, target_is_directory=True)
    with pytest.raises(OutputError) as exc:
        run(workspace, "linked.h5", RefusingEngine())
    text = one_line_error(exc)
    assert str(link) in text and "symbolic link" in text
    assert snapshot(foreign) == {"data.txt": b"somebody else's\n"}
    assert link.is_symlink() and os.readlink(link) == str(foreign)


class StoppedAtOnce(SerialEngine):
    """Ctrl-C before any chunk is in."""

    def run(self, worker, tasks, report, tick) -> None:
        raise KeyboardInterrupt


def test_a_run_that_stops_before_its_first_chunk_leaves_no_sidecar(workspace):
    with pytest.raises(KeyboardInterrupt):
        run(workspace, "early.h5", StoppedAtOnce())
    assert not sidecar(workspace, "early.h5").exists()


# --------------------------------------------------------------------------- chunks checked by content
def test_a_damaged_chunk_is_discarded_with_a_note_and_fitted_again(workspace, whole, caplog):
    interrupted(workspace, "damaged.h5", 2)
    path = chunk_file(workspace, "damaged.h5", 1)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # a truncated npz: not a zip file any more
    engine = SerialEngine()
    with caplog.at_level(logging.WARNING, logger="afmid"):
        run(workspace, "damaged.h5", engine)
    assert engine.ran == [1, 2, 3, 4]
    notes = [r.getMessage() for r in caplog.records if "chunk_000001.npz" in r.getMessage()]
    assert len(notes) == 1 and "damaged" in notes[0] and "\n" not in notes[0], notes
    assert not sidecar(workspace, "damaged.h5").exists()
    assert_identical(whole, workspace / "damaged.h5")


def test_a_chunk_of_another_pixel_range_is_discarded_and_fitted_again(workspace, whole, caplog):
    interrupted(workspace, "swapped.h5", 2)
    shutil.copy(chunk_file(workspace, "swapped.h5", 1), chunk_file(workspace, "swapped.h5", 0))
    engine = SerialEngine()
    with caplog.at_level(logging.WARNING, logger="afmid"):
        run(workspace, "swapped.h5", engine)
    assert engine.ran == [0, 2, 3, 4]
    notes = [r.getMessage() for r in caplog.records if "chunk_000000.npz" in r.getMessage()]
    assert len(notes) == 1 and "pixels 2-3" in notes[0], notes
    assert_identical(whole, workspace / "swapped.h5")


def test_a_chunk_of_another_config_is_discarded_and_fitted_again(workspace, whole, caplog):
    """A chunk copied from another run's sidecar, same pixel range, another config (another bootstrap seed)."""
    interrupted(workspace, "other.h5", 1, ("fit.seed=12345",))
    interrupted(workspace, "mixed.h5", 2)
    shutil.copy(chunk_file(workspace, "other.h5", 0), chunk_file(workspace, "mixed.h5", 0))
    engine = SerialEngine()
    with caplog.at_level(logging.WARNING, logger="afmid"):
        run(workspace, "mixed.h5", engine)
    assert engine.ran == [0, 2, 3, 4]
    notes = [r.getMessage() for r in caplog.records if "chunk_000000.npz" in r.getMessage()]
    assert len(notes) == 1 and "another" in notes[0], notes
    assert_identical(whole, workspace / "mixed.h5")


def test_a_linked_chunk_is_removed_not_followed_and_fitted_again(workspace, whole, tmp_path, caplog):
    interrupted(workspace, "linkedchunk.h5", 2)
    target = tmp_path / "elsewhere.npz"
    shutil.copy(chunk_file(workspace, "linkedchunk.h5", 1), target)  # a valid chunk of this run, but behind a link
    chunk_file(workspace, "linkedchunk.h5", 1).unlink()
    chunk_file(workspace, "linkedchunk.h5", 1).symlink_to(target)
    before = target.read_bytes()
    engine = SerialEngine()
    with caplog.at_level(logging.WARNING, logger="afmid"):
        run(workspace, "linkedchunk.h5", engine)
    assert engine.ran == [1, 2, 3, 4]
    assert any("chunk_000001.npz is not a regular file" in r.getMessage() for r in caplog.records)
    assert target.read_bytes() == before
    assert_identical(whole, workspace / "linkedchunk.h5")


# --------------------------------------------------------------------------- one run per output
def test_a_second_run_on_the_same_output_refuses_naming_the_first(workspace, whole):
    refusals = []

    def second_run(count: int) -> None:
        if count == 1:  # the first run holds its sidecar with one chunk saved; a run with another config starts
            with pytest.raises(OutputError) as exc:
                run(workspace, "shared.h5", RefusingEngine(), ("fit.seed=12345",))
            refusals.append(one_line_error(exc))
            assert sorted(p.name for p in sidecar(workspace, "shared.h5").glob("chunk_*.npz")) == ["chunk_000000.npz"]

    engine = SerialEngine(between=second_run)
    run(workspace, "shared.h5", engine)
    assert len(refusals) == 1 and f"pid {os.getpid()}" in refusals[0], refusals
    assert engine.ran == list(range(N_CHUNKS))
    assert not sidecar(workspace, "shared.h5").exists()
    assert_identical(whole, workspace / "shared.h5")


def test_a_map_command_refuses_while_another_process_holds_the_output(workspace, capsys):
    """Across processes, through the command line: the holder is a child process with the sidecar's lock."""
    from afmid.cli import main

    interrupted(workspace, "held.h5", 1)
    folder = sidecar(workspace, "held.h5")
    holder = subprocess.Popen([sys.executable, "-c",
                               "import sys, time\nfrom pathlib import Path\nfrom afmid.batch.folder_lock import "
                               "folder_lock\nwith folder_lock(Path(sys.argv[1]), writer='afmid map'):\n"
                               "    print('held', flush=True)\n    time.sleep(600)\n", str(folder)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        before = snapshot(folder)
        code = main(["map", str(CONFIG), "--input", str(workspace / "map.h5"), "-o", str(workspace / "held.h5"),
                     "--chunk", str(CHUNK), "--set", "fit.seed=12345"])
    finally:
        holder.kill()
        holder.wait()
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("afmid: error: ")]
    assert code == 1 and len(lines) == 1, err
    assert f"another afmid map is writing to this folder (pid {holder.pid} on host" in lines[0]
    assert str(folder) in lines[0] and "Traceback" not in err
    after = snapshot(folder)
    assert {k: v for k, v in after.items() if k != ".afmid-batch.lock"} == \
        {k: v for k, v in before.items() if k != ".afmid-batch.lock"}
    assert not (workspace / "held.h5").exists()


# --------------------------------------------------------------------------- a lost engine
def test_a_lost_cluster_keeps_the_finished_chunks_and_the_same_command_resumes(workspace, whole, caplog):
    from afmid.errors import EngineError

    lost = EngineError("lost the dask cluster at tcp://127.0.0.1:1 (the scheduler is gone)")
    with caplog.at_level(logging.WARNING, logger="afmid"), pytest.raises(EngineError) as exc:
        run(workspace, "lost.h5", SerialEngine(stop_after=2, stop=lost))
    assert exc.value.exit_code == 1 and "\n" not in exc.value.format()
    assert not (workspace / "lost.h5").exists()
    assert sorted(p.name for p in sidecar(workspace, "lost.h5").glob("chunk_*.npz")) == \
        ["chunk_000000.npz", "chunk_000001.npz"]
    assert any("2 of 5 chunks are saved" in r.getMessage() for r in caplog.records)
    engine = SerialEngine()  # "the same command on a new cluster"
    run(workspace, "lost.h5", engine)
    assert engine.ran == [2, 3, 4]
    assert_identical(whole, workspace / "lost.h5")


class GivingUpEngine(SerialEngine):
    """Fits the first ``fitted`` chunks, then reports the others with neither a result nor a crash and returns
    (an engine that lost them without raising)."""

    def __init__(self, fitted: int):
        super().__init__()
        self.fitted = fitted

    def run(self, worker, tasks, report, tick) -> None:
        for count, (key, task) in enumerate(tasks):
            if count < self.fitted:
                self.ran.append(key)
                report(Outcome(key, worker(task)))
            else:
                report(Outcome(key))


def test_an_engine_that_returns_without_every_chunk_gives_no_result_and_the_same_command_resumes(workspace, whole):
    from afmid.errors import EngineError

    with pytest.raises(EngineError) as exc:
        run(workspace, "holes.h5", GivingUpEngine(fitted=3))
    text = one_line_error(exc)
    assert "2 of 5 chunks" in text and "resume" in text
    assert not (workspace / "holes.h5").exists()
    assert len(list(sidecar(workspace, "holes.h5").glob("chunk_*.npz"))) == 3
    engine = SerialEngine()
    run(workspace, "holes.h5", engine)
    assert engine.ran == [3, 4]
    assert_identical(whole, workspace / "holes.h5")
