"""One writer per output folder: an exclusive lock on a file inside it, held while a batch writes there.

``afmid batch`` takes the lock on ``DIR/.afmid-batch.lock`` (:func:`fcntl.flock`, exclusive,
non-blocking) before it writes anything in DIR and holds it for its whole life. The file says who holds
it, in one line (``pid 123 on host lab-pc, started 2026-11-24T02:00:00+00:00``), so that a second batch on
the same folder can name the first when it refuses at once. The kernel releases a flock when its process
ends, however it ends, so a lock file left by a killed batch (a stale lock) blocks nothing: the next batch
simply takes it. A batch that finishes removes the file.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import socket
from collections.abc import Iterator
from pathlib import Path

from afmid.errors import OutputError
from afmid.io.trace import now_iso
from afmid.tempfiles import is_write_refused, write_refused_error

LOCK_NAME = ".afmid-batch.lock"


@contextlib.contextmanager
def folder_lock(folder: Path, key: str | None = None, writer: str = "afmid batch") -> Iterator[Path]:
    """Hold the exclusive lock of ``folder`` (an existing folder) for the block; yields the lock file's path.

    OutputError at once, naming the folder and the holder (pid, host, start time), if another process holds it;
    ``writer`` says what the holder is in that message (``afmid map`` locks its sidecar folder with it too).
    """
    path = Path(folder) / LOCK_NAME
    fd = _acquire(path, Path(folder), key, writer)
    try:
        try:
            os.ftruncate(fd, 0)
            os.write(fd, f"pid {os.getpid()} on host {socket.gethostname()}, started {now_iso()}\n".encode())
        except OSError as exc:  # a full disk, a size limit: say so (the lock is released and its file removed below)
            if is_write_refused(exc):
                raise write_refused_error(exc, path) from None
            raise OutputError(f"cannot write the lock file {LOCK_NAME}: {exc.strerror or exc}", file=folder,
                              key=key) from None
        yield path
    finally:
        # Remove the file while still holding the lock: a process that opened it meanwhile finds, once it gets
        # the lock, that the file it locked is no longer the one at the path, and tries again (see _acquire).
        with contextlib.suppress(OSError):
            os.unlink(path)
        os.close(fd)


def _acquire(path: Path, folder: Path, key: str | None, writer: str) -> int:
    """Open and lock ``path``; a file descriptor holding the lock on the file that is now at ``path``."""
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise OutputError(f"cannot create the lock file {LOCK_NAME}: {exc.strerror or exc}", file=folder,
                              key=key) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = _holder(fd)
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise OutputError(f"another {writer} is writing to this folder ({holder}); wait for it to finish "
                                  "or choose another output folder", file=folder, key=key) from None
            raise OutputError(f"cannot lock the folder: {exc.strerror or exc}", file=folder, key=key) from None
        try:
            current = os.stat(path)
        except FileNotFoundError:
            current = None
        mine = os.fstat(fd)
        if current is not None and (current.st_dev, current.st_ino) == (mine.st_dev, mine.st_ino):
            return fd
        os.close(fd)  # the holder removed the file after we opened it: lock the new one


def _holder(fd: int) -> str:
    """What the lock file says about its holder, e.g. 'pid 123 on host lab-pc, started 2026-11-24T02:00:00+00:00'."""
    try:
        text = os.pread(fd, 400, 0).decode("utf-8", "replace").strip()
    except OSError:
        text = ""
    return text.splitlines()[0] if text else "a process that has not yet said who it is"
