"""The temporary files behind :func:`afmid.io.trace.atomic_path`: their names, stale ones, and a full disk.

- Names: ``.afmid-tmp-<output name>.<host>.<pid>.<random>``, so that a later run can tell whose file it
  is. A process killed outright (``kill -9``, a node failure, SIGTERM before afmid handled it) leaves its
  temporary file behind; :func:`remove_stale` removes those of processes that are gone, when a new write
  starts in the same folder. A file of a live process, of another host (a shared file system) or in the
  old unnamed form is never touched.
- A full disk: :func:`disk_full_error` turns ENOSPC / EDQUOT into one :class:`afmid.errors.OutputError`
  naming the output (:func:`write_refused_error` also EFBIG, a file-size limit, and EROFS, a read-only file
  system); :class:`ErrorHoldingFile` is the file object the HDF5 library writes through, so
  that a failed write never reaches it (measured: HDF5 1.14 via h5py 3.16 prints hundreds of lines of
  errors and then segfaults when a write fails at flush or close).
"""

from __future__ import annotations

import errno
import io
import logging
import os
import re
import shutil
import socket
from pathlib import Path

from afmid.errors import OutputError

log = logging.getLogger(__name__)

PREFIX = ".afmid-tmp-"
#: <output name>.<host>.<pid>.<mkstemp's random part, which has no dots>
_NAME_RE = re.compile(r"^\.afmid-tmp-(?P<name>.+)\.(?P<host>[A-Za-z0-9-]+)\.(?P<pid>\d+)\.(?P<random>[^.]+)$")
#: What every error line about an output that does not fit says (a batch looks for it in its items' errors).
NO_SPACE_TEXT = "no space left on device"
#: errno values that mean the output does not fit, and how the error line says it.
_NO_SPACE = {errno.ENOSPC: NO_SPACE_TEXT, errno.EDQUOT: f"disk quota exceeded ({NO_SPACE_TEXT})"}
#: Every errno of a write the place refuses, whatever the data (a full disk, a file-size limit, a read-only file
#: system): (what happened, what to do), for one error line naming the output.
_WRITE_REFUSED = {
    **{code: (text, "free some space and run again") for code, text in _NO_SPACE.items()},
    errno.EFBIG: ("file too large: the file system's or this process's file-size limit (ulimit -f) was reached",
                  "write it where larger files are allowed, or raise the limit"),
    errno.EROFS: ("read-only file system", "write it to a writable folder"),
}


def host_tag() -> str:
    """This machine's name as it appears in temporary names (dots and other separators replaced by '-')."""
    return (re.sub(r"[^A-Za-z0-9-]+", "-", socket.gethostname()).strip("-") or "localhost")[:40]


def prefix_for(path: Path) -> str:
    """The prefix (for :func:`tempfile.mkstemp`) of this process's temporary files for output ``path``."""
    # Shortened parts keep the name within the 255 bytes a file system allows.
    return f"{PREFIX}{path.name[:120]}.{host_tag()}.{os.getpid()}."


def owner(name: str) -> tuple[str, int] | None:
    """(host, pid) encoded in a temporary file's name, or None if it is not in that form."""
    match = _NAME_RE.match(name)
    return (match["host"], int(match["pid"])) if match else None


def _process_is_gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # PermissionError: alive, another user's
        return False
    return False


def remove_stale(folder: Path) -> list[Path]:
    """Remove the temporary files (and report folders) in ``folder`` left by processes of this host that are gone;
    returns them."""
    here = host_tag()
    removed = []
    try:
        candidates = [p for p in Path(folder).glob(f"{PREFIX}*")]
    except OSError:
        return removed
    for path in candidates:
        who = owner(path.name)
        if who is None or who[0] != here or who[1] == os.getpid() or not _process_is_gone(who[1]):
            continue
        try:
            if path.is_symlink():
                continue
            if path.is_dir():  # a report folder being made (afmid.report.folder)
                shutil.rmtree(path)
            elif path.is_file():
                path.unlink()
            else:
                continue
        except OSError:
            continue
        log.info("removed %s, a temporary file left by process %d, which no longer runs", path, who[1])
        removed.append(path)
    return removed


def is_disk_full(exc: BaseException) -> bool:
    return isinstance(exc, OSError) and exc.errno in _NO_SPACE


def disk_full_error(exc: OSError, path: Path | str) -> OutputError:
    """The one-line error for output ``path`` that did not fit (``exc`` is ENOSPC or EDQUOT)."""
    return OutputError(f"{_NO_SPACE[exc.errno]}; nothing was written (free some space and run again)", file=path)


def is_write_refused(exc: BaseException) -> bool:
    """Whether ``exc`` is a write the place refused (full disk, quota, EFBIG, EROFS), not a bug of afmid."""
    return isinstance(exc, OSError) and exc.errno in _WRITE_REFUSED


def write_refused_error(exc: OSError, path: Path | str) -> OutputError:
    """The one-line error for output ``path`` whose write ``exc`` (see :func:`is_write_refused`) was refused."""
    what, advice = _WRITE_REFUSED[exc.errno]
    return OutputError(f"{what}; nothing was written ({advice})", file=path)


class ErrorHoldingFile(io.RawIOBase):
    """A binary file for h5py to write an HDF5 file through, that never fails a write.

    The first error of a write, truncate or flush (e.g. ENOSPC) is kept in :attr:`error` and every later
    write is discarded (the position still moves on), so the HDF5 library finishes and closes cleanly; the
    caller then raises :attr:`error` and deletes the useless file. An exception of any kind (an interrupt)
    inside a call from the library is held the same way, for the caller to raise after closing.
    """

    def __init__(self, raw) -> None:
        super().__init__()
        self._raw = raw
        self.error: BaseException | None = None

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = 0) -> int:
        try:
            return self._raw.seek(offset, whence)
        except BaseException as exc:
            self._hold(exc)
            return offset

    def tell(self) -> int:
        try:
            return self._raw.tell()
        except BaseException as exc:
            self._hold(exc)
            return 0

    def read(self, size: int = -1) -> bytes:
        if size is None or size < 0:  # the rest of the file, as it is (no padding: there is no end to pad to)
            return self._raw.read()
        buffer = bytearray(size)
        self.readinto(buffer)
        return bytes(buffer)

    def readinto(self, buffer) -> int:
        """Fills ``buffer`` whole: bytes past the end of the file read as zeros, as HDF5's own driver reads them."""
        view = memoryview(buffer).cast("B")
        got = 0
        try:
            while got < view.nbytes:
                n = self._raw.readinto(view[got:])
                if not n:
                    break
                got += n
        except BaseException as exc:  # zeros instead: the file is useless already, or will be discarded
            self._hold(exc)
        view[got:] = bytes(view.nbytes - got)
        return view.nbytes

    def write(self, data) -> int:
        size = memoryview(data).nbytes
        try:
            if self.error is None:
                written = 0
                view = memoryview(data).cast("B")
                while written < size:  # a full disk may first show as a short write
                    n = self._raw.write(view[written:])
                    if not n:
                        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                    written += n
                return size
        except BaseException as exc:
            self._hold(exc)
        try:
            self._raw.seek(size, os.SEEK_CUR)
        except BaseException as exc:
            self._hold(exc)
        return size

    def truncate(self, size: int | None = None) -> int:
        try:
            if self.error is None:
                return self._raw.truncate(size)
        except BaseException as exc:
            self._hold(exc)
        return self.tell() if size is None else size

    def flush(self) -> None:
        try:
            if self.error is None:
                self._raw.flush()
        except BaseException as exc:
            self._hold(exc)

    def _hold(self, exc: BaseException) -> None:
        if self.error is None:
            self.error = exc
