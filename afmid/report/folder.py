"""The folder ``afmid report`` writes: made under a temporary name, swapped in whole, replaced only if afmid's own.

A report folder afmid wrote holds the marker file ``.afmid-report`` (JSON: format, afmid version, creation
time and the list of the files afmid wrote there; layout in docs/file-formats.md). ``--overwrite`` replaces
such a folder and nothing else: a folder without the marker, one holding a file the marker does not list
(the user's notes, a run file copied in) or one holding an input of the report is refused, and nothing is
deleted. The new report is written into a temporary sibling ``.afmid-tmp-NAME.*`` and swapped in only when
complete (with Ctrl-C and SIGTERM held for the two renames), so an interrupted or failed report leaves the
previous one as it was and no temporary folder behind.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

from afmid.version import __version__
from afmid.errors import OutputError
from afmid.interrupts import raise_if_pending
from afmid.io.trace import lies_inside, now_iso, refuse_input_as_output
from afmid.tempfiles import prefix_for, remove_stale

MARKER = ".afmid-report"
MARKER_FORMAT = "afmid-report"
#: Foreign files named in a refusal, at most.
_NAMED = 3


def read_marker(folder: Path) -> dict | None:
    """The marker of a report folder afmid wrote, or None if ``folder`` has none (or an unreadable one)."""
    try:
        marker = json.loads((Path(folder) / MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(marker, dict) or marker.get("format") != MARKER_FORMAT or not isinstance(marker.get("files"),
                                                                                                 list):
        return None
    return marker


def check_report_folder(output: Path, overwrite: bool, inputs: dict[str | Path, str] | None = None) -> None:
    """OutputError unless the report may be written to ``output``: a new or empty folder, or, with
    ``overwrite``, a report folder afmid wrote that holds only afmid's files and none of the ``inputs``."""
    output = Path(output)
    refuse_input_as_output(output, inputs, folder=True)
    try:
        cwd = Path.cwd()
    except OSError:  # the current folder was removed: nothing to protect
        cwd = None
    if cwd is not None and lies_inside(cwd, output):  # replacing it would leave the user's shell in a removed folder
        raise OutputError("is the current folder or holds it; give a report folder elsewhere", file=output)
    if not output.exists():
        return
    if not output.is_dir():
        raise OutputError("exists and is not a folder", file=output)
    try:
        names = sorted(p.name for p in output.iterdir())
    except OSError as exc:
        raise OutputError(f"cannot read the folder: {exc.strerror or exc}", file=output) from None
    if not names:
        return
    marker = read_marker(output)
    if marker is None:
        raise OutputError(f"folder is not empty and is not a report folder afmid wrote (no {MARKER} file); afmid "
                          "replaces only its own report folders: choose a new folder", file=output)
    # A listed name that is now a folder is not what afmid wrote either (afmid writes files only).
    foreign = [n for n in names if n != MARKER and (n not in marker["files"] or (output / n).is_dir())]
    if foreign:
        more = ", ..." if len(foreign) > _NAMED else ""
        raise OutputError(f"holds files afmid did not write ({', '.join(foreign[:_NAMED])}{more}); move them away "
                          "or choose a new folder", file=output)
    if not overwrite:
        raise OutputError("report folder exists; pass --overwrite to replace it", file=output)


@contextlib.contextmanager
def report_folder(output: Path, overwrite: bool, inputs: dict[str | Path, str] | None = None) -> Iterator[Path]:
    """Check ``output`` (:func:`check_report_folder`), yield a new temporary folder beside it to write the report
    into, then write the marker and swap the folder in. On any error or interrupt the temporary folder is removed
    and ``output`` is left as it was."""
    output = Path(output)
    check_report_folder(output, overwrite, inputs)
    real = output.resolve()  # a symbolic link to a folder: the report replaces the folder it points to
    try:
        remove_stale(real.parent)  # report folders of afmid processes killed outright (kill -9)
        tmp = Path(tempfile.mkdtemp(prefix=prefix_for(real), dir=real.parent))
    except OSError as exc:  # read-only file system, no permission, missing parent: the user's environment
        raise OutputError(f"cannot write in folder {real.parent}: {exc.strerror or exc}", file=output) from None
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes the folder private; give it the permissions the umask allows
        yield tmp
        write_marker(tmp)
        with _signals_held():
            check_report_folder(output, overwrite)  # again: files may have been put there while the report was made
            raise_if_pending()  # an interrupt Python swallowed while the report was written (a weakref callback)
            _swap(tmp, real, output)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_marker(folder: Path) -> None:
    """Write the marker listing every file now in ``folder`` (call it last)."""
    files = sorted(p.name for p in Path(folder).iterdir() if p.name != MARKER)
    marker = {"format": MARKER_FORMAT, "afmid_version": __version__, "created": now_iso(), "files": files}
    (Path(folder) / MARKER).write_text(json.dumps(marker, indent=1) + "\n", encoding="utf-8")


def _swap(new: Path, real: Path, output: Path) -> None:
    """Put folder ``new`` at ``real``; the folder there before (afmid's own report, or empty) is removed."""
    old = None
    try:
        if real.exists():
            # not in the temporary-name form: if afmid is killed between the two renames, the old report stays
            # (never removed as stale) for the user to find
            old = real.parent / f".afmid-tmp-{real.name}.old-{os.getpid()}-{secrets.token_hex(4)}"
            os.rename(real, old)
        try:
            os.rename(new, real)
        except OSError:
            if old is not None:
                os.rename(old, real)
                old = None
            raise
    except OSError as exc:
        raise OutputError(f"cannot replace the folder: {exc.strerror or exc}", file=output) from None
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Block Ctrl-C and SIGTERM (main thread only) so the swap is never cut between its two renames; a signal that
    came meanwhile is delivered when the block ends."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
