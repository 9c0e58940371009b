"""afmid's own files validated before use; refused writes as one line; names echoed without control bytes (issue 32).

- a map result with ``/maps/status`` deleted, a map of the wrong shape, a ``/x`` of the wrong length or a newer
  ``format_version``: one line naming the file and the dataset (the version named), exit 1, no report folder;
- ``-o`` in a folder that cannot be written (a read-only mount, or a folder the user cannot write in): one line
  before any fitting, no temporary file left;
- ``export`` and ``report`` under a file-size limit (RLIMIT_FSIZE, SIGXFSZ ignored so that the write fails with
  EFBIG): one line, no partial output, no temporary file;
- a run file whose stored input path is a FIFO or /dev/zero: ``report`` finishes (the SHA-256 check reads
  regular files only) and says so in one line;
- an ``-o`` name with an ESC: stdout and stderr carry no raw control byte.
"""

from __future__ import annotations

import errno
import os
import resource
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from repo_paths import REPO_ROOT
from tests.cli.test_corpus_config import base_config, write_tapping_csv

MAP_CONFIG = REPO_ROOT / "tests" / "configs" / "map_small.yaml"
#: A command that must end quickly (a hang is the failure this guards against), s on a loaded machine.
TIMEOUT = 300
#: The file-size limit of the EFBIG cases, bytes: below any run file's or export's size, above the probe's 0 bytes.
FILE_SIZE_LIMIT = 2048
#: Control bytes a terminal acts on (C0 but newline and tab, DEL); C1 shows in UTF-8 text as U+0080-U+009F.
RAW_CONTROLS = [chr(c) for c in range(0x20) if chr(c) not in "\n\t"] + [chr(0x7F)] + [chr(c) for c in
                                                                                      range(0x80, 0xA0)]


def afmid(*args, cwd: Path, limit_file_size: int | None = None) -> subprocess.CompletedProcess:
    """``python -m afmid.cli ARGS`` in ``cwd``; ``limit_file_size``: RLIMIT_FSIZE in bytes, with SIGXFSZ ignored so
    that a write past it fails with EFBIG (as on a file system's size limit) instead of killing the process."""
    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_file_size, limit_file_size))

    return subprocess.run([sys.executable, "-m", "afmid.cli", *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, timeout=TIMEOUT, preexec_fn=limit if limit_file_size is not None else None)


def assert_one_line(done: subprocess.CompletedProcess, *expected: str) -> str:
    assert done.returncode in (1, 2), (done.returncode, done.stderr)
    assert "Traceback" not in done.stderr, done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("afmid: error:")]
    assert len(errors) == 1, done.stderr
    for text in expected:
        assert text in errors[0], errors[0]
    return errors[0]


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".afmid-tmp-"))


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def fitted(tmp_path_factory) -> Path:
    """A folder with the corpus tapping trace, its run config and its run file ``r.h5``."""
    folder = tmp_path_factory.mktemp("own-files-run")
    write_tapping_csv(folder)
    (folder / "run.yaml").write_text(yaml.safe_dump(base_config(**{"fit.bootstrap": 8}), sort_keys=False))
    done = afmid("-q", "fit", "run.yaml", "-o", "r.h5", cwd=folder)
    assert done.returncode == 0, done.stderr
    return folder


@pytest.fixture(scope="module")
def map_result(tmp_path_factory) -> Path:
    """The small test map (3x3) fitted on one worker, without the group diagnosis: ``result.h5``."""
    folder = tmp_path_factory.mktemp("own-files-map")
    done = afmid("-q", "simulate", MAP_CONFIG, "-o", "map.h5", cwd=folder)
    assert done.returncode == 0, done.stderr
    done = afmid("-q", "map", MAP_CONFIG, "--input", "map.h5", "-o", "result.h5", "-j", "1", "--no-diagnosis",
                 cwd=folder)
    assert done.returncode == 0, done.stderr
    return folder / "result.h5"


def _edited(result: Path, folder: Path, edit) -> Path:
    copy = folder / "edited.h5"
    shutil.copy(result, copy)
    with h5py.File(copy, "r+") as h5:
        edit(h5)
    return copy


# --------------------------------------------------------------------------- map results validated
def _delete_status(h5):
    del h5["maps/status"]


def _wrong_e_star_shape(h5):
    del h5["maps/E_star"]
    h5["maps"].create_dataset("E_star", data=np.ones((2, 5)))


def _short_x(h5):
    x = h5["x"][()]
    del h5["x"]
    h5.create_dataset("x", data=x[:-1])


def _newer_version(h5):
    h5.attrs["format_version"] = int(h5.attrs["format_version"]) + 1


@pytest.mark.parametrize("edit, expected", [
    (_delete_status, ["/maps/status", "missing"]),
    (_wrong_e_star_shape, ["/maps/E_star", "(2, 5)", "(3, 3)"]),
    (_short_x, ["/x", "(2,)", "(3,)"]),
    (_newer_version, ["format_version", "is not one this afmid"]),
], ids=["status-deleted", "E_star-wrong-shape", "x-wrong-length", "newer-format-version"])
def test_a_damaged_or_newer_map_result_is_refused_in_one_line(map_result, tmp_path, edit, expected):
    edited = _edited(map_result, tmp_path, edit)
    done = afmid("report", edited, "-o", "rep", cwd=tmp_path)
    line = assert_one_line(done, str(edited), *expected)
    if edit is _newer_version:  # the newer version is named
        with h5py.File(edited, "r") as h5:
            assert str(int(h5.attrs["format_version"])) in line
    assert not (tmp_path / "rep").exists() and leftovers(tmp_path) == []


def test_a_map_file_whose_x_has_the_wrong_length_is_refused_before_fitting(map_result, tmp_path):
    edited = _edited(map_result.parent / "map.h5", tmp_path, _short_x)
    done = afmid("map", MAP_CONFIG, "--input", edited, "-o", "result.h5", "-j", "1", "--no-diagnosis", cwd=tmp_path)
    assert_one_line(done, str(edited), "/x", "(2,)", "(3,)")
    assert not (tmp_path / "result.h5").exists() and "chunks of" not in done.stderr


@pytest.mark.parametrize("what", ["map", "trace"])
def test_afmids_own_input_of_a_newer_format_version_is_refused_with_the_version(map_result, fitted, tmp_path, what):
    if what == "map":
        edited = _edited(map_result.parent / "map.h5", tmp_path, _newer_version)
        args = ["map", MAP_CONFIG, "--input", edited, "-o", "result.h5", "-j", "1", "--no-diagnosis"]
    else:
        done = afmid("-q", "simulate", MAP_CONFIG, "--set", "simulate.map=null", "-o", "trace.h5", cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        edited = _edited(tmp_path / "trace.h5", tmp_path, _newer_version)
        args = ["inspect", edited]
    done = afmid(*args, cwd=tmp_path)
    assert_one_line(done, str(edited), "format_version 2", "is not one this afmid")


def test_the_untouched_map_result_reports(map_result, tmp_path):
    done = afmid("-q", "report", map_result, "-o", "rep", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "rep" / "report.html").is_file()


# --------------------------------------------------------------------------- read-only outputs
def _unshare_works() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-rm", "true"], capture_output=True, timeout=30)
    return probe.returncode == 0


@pytest.mark.skipif(not _unshare_works(), reason="needs unshare -rm (user and mount namespaces) to mount a "
                                                  "read-only file system without privileges")
def test_map_output_on_a_read_only_file_system_is_one_line_before_fitting(map_result, tmp_path):
    """A real read-only mount (a tmpfs mounted ro in a private mount namespace): EROFS, as root too."""
    folder = map_result.parent
    (tmp_path / "ro").mkdir()
    script = (f"mount -t tmpfs -o ro none {tmp_path / 'ro'} && exec {sys.executable} -m afmid.cli map "
              f"{MAP_CONFIG} --input {folder / 'map.h5'} -o {tmp_path / 'ro' / 'result.h5'} -j 1 --no-diagnosis")
    done = subprocess.run(["unshare", "-rm", "sh", "-c", script], cwd=tmp_path, capture_output=True, text=True,
                          timeout=TIMEOUT)
    assert_one_line(done, str(tmp_path / "ro" / "result.h5"), "read-only file system")
    assert "chunks of" not in done.stderr  # refused before the map's work was planned, let alone fitted


def test_fit_into_a_folder_that_cannot_be_written_is_one_line_before_fitting(fitted, tmp_path):
    """Not root: a chmod'ed folder. Root ignores the permission bits: a folder of /sys, which refuses new files."""
    if os.geteuid() == 0:
        target = Path("/sys/kernel/afmid-test-run.h5")
    else:
        (tmp_path / "locked").mkdir()
        os.chmod(tmp_path / "locked", 0o555)
        target = tmp_path / "locked" / "run.h5"
    done = afmid("fit", fitted / "run.yaml", "-o", target, cwd=tmp_path)
    assert_one_line(done, str(target), "cannot write in folder")
    assert "fit:" not in done.stderr  # no stage of the fit started
    assert not target.exists()


@pytest.mark.parametrize("code, text", [(errno.EROFS, "read-only file system"), (errno.EFBIG, "file too large")])
def test_a_write_refused_while_writing_is_one_line_and_leaves_nothing(tmp_path, code, text):
    """The folder was writable when the command started (the mount turned read-only meanwhile, a limit reached):
    the write's own error is one line naming the output, and its temporary file is removed."""
    from afmid.errors import OutputError
    from afmid.io.trace import atomic_path

    with pytest.raises(OutputError, match=text) as caught:
        with atomic_path(tmp_path / "out.h5") as tmp:
            tmp.write_bytes(b"partial")
            raise OSError(code, os.strerror(code))
    assert caught.value.file == str(tmp_path / "out.h5")
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- EFBIG
def test_export_under_a_file_size_limit_is_one_line_and_leaves_nothing(fitted, tmp_path):
    done = afmid("export", fitted / "r.h5", "--what", "force-curves", "-o", "curves.csv", cwd=tmp_path,
                 limit_file_size=FILE_SIZE_LIMIT)
    assert_one_line(done, "curves.csv", "file too large")
    assert not (tmp_path / "curves.csv").exists() and leftovers(tmp_path) == []


def test_report_under_a_file_size_limit_is_one_line_and_leaves_nothing(fitted, tmp_path):
    done = afmid("report", fitted / "r.h5", "-o", "rep", "--no-suggest", cwd=tmp_path,
                 limit_file_size=FILE_SIZE_LIMIT)
    assert_one_line(done, "rep", "file too large")
    assert not (tmp_path / "rep").exists() and leftovers(tmp_path) == []


def test_a_run_file_under_a_file_size_limit_is_one_line_and_leaves_nothing(fitted, tmp_path):
    done = afmid("fit", fitted / "run.yaml", "-o", tmp_path / "r.h5", cwd=tmp_path, limit_file_size=FILE_SIZE_LIMIT)
    assert_one_line(done, "r.h5", "file too large")
    assert not (tmp_path / "r.h5").exists() and leftovers(tmp_path) == []


# --------------------------------------------------------------------------- the stored input's SHA-256
@pytest.mark.parametrize("kind", ["fifo", "dev-zero"])
def test_a_stored_input_that_is_a_fifo_or_a_device_is_not_read(fitted, tmp_path, kind):
    run = tmp_path / "r.h5"
    shutil.copy(fitted / "r.h5", run)
    if kind == "fifo":
        stored = tmp_path / "trace.fifo"
        os.mkfifo(stored)
    else:
        stored = Path("/dev/zero")
    with h5py.File(run, "r+") as h5:
        h5.attrs["input_path"] = str(stored)
    done = afmid("report", run, "-o", "rep", cwd=tmp_path)  # with suggestions: they would refit from the input
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    assert f"its stored input {stored} is not a regular file" in done.stderr
    assert (tmp_path / "rep" / "report.html").is_file()


# --------------------------------------------------------------------------- control characters
def test_escape_controls_writes_every_control_character_as_an_escape():
    from afmid.errors import escape_controls

    assert escape_controls("run\x1b[2J\x9b\u202e.h5") == "run\\x1b[2J\\x9b\\u202e.h5"
    assert escape_controls("a\nb") == "a\\x0ab" and escape_controls("a\nb", keep="\n") == "a\nb"
    assert escape_controls("\udcff") == "\\udcff"  # a non-UTF-8 byte of a file name
    assert escape_controls("run 1 µm ü.h5") == "run 1 µm ü.h5"  # printable text as it is


@pytest.mark.parametrize("command", ["fit", "fit-exists", "export"])
def test_an_output_name_with_an_escape_sequence_is_never_echoed_raw(fitted, tmp_path, command):
    name = "run\x1b]0;owned\x07\x1b[2J.h5"
    if command == "export":
        args = ["export", fitted / "r.h5", "--what", "parameters", "-o", name[:-3] + ".csv"]
    else:
        args = ["fit", fitted / "run.yaml", "-o", tmp_path / name]
        if command == "fit-exists":  # the refusal's error line names it
            (tmp_path / name).write_bytes(b"the user's file")
    done = afmid(*args, cwd=tmp_path)
    assert done.returncode == (1 if command == "fit-exists" else 0), done.stderr
    for stream in (done.stdout, done.stderr):
        assert not [c for c in RAW_CONTROLS if c in stream], repr(stream[-400:])
    assert "run\\x1b]0;owned\\x07\\x1b[2J" in done.stderr  # named, escaped
