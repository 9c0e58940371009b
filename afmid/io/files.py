"""Checks every input file passes before afmid reads it, and what may be shown of a file in a message.

:func:`check_input_file` is used by the config loader, :func:`afmid.io.trace.load_trace`
(through :func:`afmid.io.readers.read_trace`), ``afmid inspect`` and
``afmid init-config --from``. It refuses, with one line each, what would
otherwise block, crash or be misreported:

- a missing file, a dangling symbolic link ("link to missing file X") and a
  symbolic link loop (reported as such, not as "not found");
- a folder, a FIFO, a socket or a device (``/dev/zero``): opening a FIFO blocks
  until a writer appears, a device never ends; such files are never opened;
- a file the user (even root) cannot open or read;
- an empty file, where an empty file cannot be valid.

:func:`available_memory` and :func:`memory_shortfall` let readers and the
simulator refuse an array before allocating it.

:func:`safe_excerpt` is the policy for echoing file content in messages: only
short, printable-ASCII excerpts, so that pointing afmid at a file that is not
data (``/etc/passwd``, a key file) never copies its content to the terminal or
a log.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from afmid.errors import AfmidError, InputError, OutputError

#: Layout version of the HDF5 files afmid writes (trace, run, map, map result; docs/file-formats.md).
FORMAT_VERSION = 1
#: Longest excerpt of a file shown in a message (characters).
EXCERPT_CHARS = 60

_SPECIAL_KINDS = (
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)


def safe_excerpt(text: object, limit: int = EXCERPT_CHARS) -> str:
    """``text`` as printable ASCII (anything else becomes '?'), cut to ``limit`` characters with '...'."""
    shown = "".join(c if " " <= c <= "~" else "?" for c in str(text))
    return shown if len(shown) <= limit else shown[: max(limit - 3, 1)] + "..."


def _missing_message(path: Path, what: str) -> str:
    """Why ``path`` (which stat cannot find) is missing: a dangling link, a missing folder, or no file."""
    try:
        if path.is_symlink():
            return f"symbolic link to missing file {safe_excerpt(os.readlink(path), 200)}"
    except OSError:
        pass
    parent = path.parent
    if not parent.exists():
        return f"{what} not found (the folder {safe_excerpt(parent, 200)} does not exist)"
    return f"{what} not found"


def check_input_file(
    path: str | Path,
    *,
    what: str = "file",
    error: type[AfmidError] = InputError,
    key: str | None = None,
    allow_empty: bool = False,
) -> Path:
    """``path`` if it is an existing, readable regular file, else ``error`` (one line naming it and ``key``).

    ``what`` names the file in messages ("config file", "trace file"). The file
    is opened (non-blocking, so a FIFO swapped in after the check cannot block)
    and one byte is read, so that a file the kernel refuses even to root
    (``/proc/sys/vm/compact_memory``) is reported here, not as a traceback later.
    """
    path = Path(path)

    def fail(message: str) -> AfmidError:
        return error(message, file=path, key=key)

    try:
        info = os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise fail("symbolic link loop (the link points back to itself through other links)") from None
        if exc.errno in (errno.ENOENT, errno.ENOTDIR):
            raise fail(_missing_message(path, what)) from None
        raise fail(f"cannot access the {what}: {exc.strerror or exc}") from None
    if stat.S_ISDIR(info.st_mode):
        raise fail(f"is a directory (folder), not a {what}")
    for is_kind, kind in _SPECIAL_KINDS:
        if is_kind(info.st_mode):
            raise fail(f"not a regular file ({kind}); give a {what} saved on disk")
    if not stat.S_ISREG(info.st_mode):
        raise fail(f"not a regular file; give a {what} saved on disk")
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as exc:
        raise fail(f"cannot open the {what}: {exc.strerror or exc}") from None
    try:
        opened = os.fstat(fd)
        if not stat.S_ISREG(opened.st_mode):  # replaced between stat and open
            raise fail("not a regular file")
        first = os.read(fd, 1)
    except OSError as exc:
        raise fail(f"cannot read the {what}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if not first and not allow_empty:
        raise fail(f"the {what} is empty (0 bytes)")
    return path


def check_output_target(path: str | Path) -> None:
    """Refuse an output path that is a FIFO, socket or device (or a link to one), even with --overwrite.

    afmid writes outputs to a temporary file and renames it into place, which
    would replace the special file itself (``-o /dev/null --overwrite`` run as
    root would replace /dev/null).
    """
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return  # missing (or unreachable): the writer reports what applies
    for is_kind, kind in _SPECIAL_KINDS:
        if is_kind(mode):
            raise OutputError(f"not a regular file ({kind}); afmid never replaces a special file with its output",
                              file=path)


def check_format_version(attrs, path: str | Path, readable: tuple[int, ...] = (FORMAT_VERSION,)) -> None:
    """InputError unless the ``format_version`` attribute of afmid's own HDF5 file ``path`` is ``readable`` here: a
    file of a newer afmid is refused with its version named, not read as if its layout were this one's."""
    from afmid.version import __version__

    version = attrs.get("format_version")
    try:
        number = int(version)
    except (TypeError, ValueError):
        number = None
    if number not in readable:
        known = ", ".join(str(v) for v in readable)
        shown = number if number is not None else repr(version)  # 2, not np.int64(2)
        why = ("written by a newer afmid: update afmid to read it" if number is not None and number > max(readable)
               else "was it written by another afmid version?")
        raise InputError(f"format_version {shown} is not one this afmid ({__version__}) reads (it reads {known}); "
                         f"{why}", file=path, key="format_version")


def check_folder_writable(path: str | Path) -> None:
    """OutputError unless a file can be made in the folder of output ``path`` (an existing folder).

    Checked when the command starts, before minutes of fitting, so that a read-only file system or a folder the
    user cannot write in is said at once; the write itself still turns a refusal into one line
    (:func:`afmid.tempfiles.write_refused_error`). The check makes and removes an empty temporary file of this
    process (``.afmid-tmp-*``), as the write will: permission bits alone do not tell (root ignores them, and
    they say nothing of a read-only mount).
    """
    import tempfile

    from afmid.interrupts import deferred
    from afmid.tempfiles import is_write_refused, prefix_for, write_refused_error

    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    with deferred():  # a Ctrl-C or SIGTERM between making and removing the probe must not leave it behind
        try:
            fd, probe = tempfile.mkstemp(prefix=prefix_for(path), dir=folder)
        except OSError as exc:
            if is_write_refused(exc):
                raise write_refused_error(exc, path) from None
            raise OutputError(f"cannot write in folder {folder}: {exc.strerror or exc}", file=path) from None
        os.close(fd)
        os.unlink(probe)


def is_regular_file(path: str | Path) -> bool:
    """Whether ``path`` is (or links to) a regular file, found without opening it: a FIFO would block the open
    and a device (``/dev/zero``) never ends, so a stored path is checked with this before it is read."""
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except (OSError, ValueError):
        return False


# --------------------------------------------------------------------------- memory
def available_memory() -> int | None:
    """Bytes of memory available to a new allocation without swapping (Linux MemAvailable), None if unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def format_bytes(n: float) -> str:
    """A size for a message: '1.5 GB', '800 MB', '2e+03 TB'."""
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{int(n)} B"


def memory_shortfall(needed_bytes: float) -> str | None:
    """None if ``needed_bytes`` fit in the available memory (or it is unknown), else why not.

    The text reads "needs ~X GB; this machine has Y GB available", for the
    caller to prefix with what needs it.
    """
    available = available_memory()
    if available is None or needed_bytes <= available:
        return None
    return f"needs ~{format_bytes(needed_bytes)}; this machine has {format_bytes(available)} available"
