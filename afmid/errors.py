"""User-facing errors.

Every problem caused by the user's input (a file, a config value, a command-line
option) is raised as an :class:`AfmidError`. The CLI prints it as one line and
exits with :attr:`AfmidError.exit_code`; no traceback unless ``-v`` is given.
Anything else that escapes is a bug in afmid and is shown with its traceback.
"""

from __future__ import annotations

from pathlib import Path

#: Format characters that reorder what a terminal shows (bidirectional overrides and isolates): a name holding
#: them can make a line read differently from what it says, so they are escaped as control characters are.
_REORDERING = frozenset("\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")


def escape_controls(text: object, keep: str = "") -> str:
    """``text`` with every control character written as an escape (``\\x1b``, ``\\x9b``, ``\\u202e``), for
    echoing a user-given name (an output path, a file name) to a terminal or a log.

    A name is passed on by afmid as the user gave it, but a raw ESC in it would be run by the terminal (colours,
    a moved cursor, a retitled window, a cleared screen): what is shown must be what the name is. ``keep`` lists
    control characters left as they are (``"\\n"`` for a multi-line message whose lines afmid made).
    """
    out = []
    for char in str(text):
        code = ord(char)
        # 0xD800-0xDFFF: a byte of a file name that is not UTF-8 (os.fsdecode's surrogate); printed raw it would
        # stop the output with a UnicodeEncodeError.
        if char in keep or not (code < 0x20 or 0x7F <= code <= 0x9F or 0xD800 <= code <= 0xDFFF
                                or char in _REORDERING):
            out.append(char)
        elif code <= 0xFF:
            out.append(f"\\x{code:02x}")
        else:
            out.append(f"\\u{code:04x}")
    return "".join(out)


class AfmidError(Exception):
    """An error the user can fix. Formats as ``file: key.path: message``."""

    exit_code = 1

    def __init__(self, message: str, *, file: str | Path | None = None, key: str | None = None):
        self.message = message
        self.file = str(file) if file is not None else None
        self.key = key
        super().__init__(self.format())

    def format(self) -> str:
        """The error's one line; control characters (of a user-given name, most often) escaped."""
        parts = [p for p in (self.file, self.key) if p]
        parts.append(self.message)
        return escape_controls(": ".join(parts))


class ConfigError(AfmidError):
    """A run config is invalid (unknown key, wrong type, out-of-range value)."""

    exit_code = 2


class InputError(AfmidError):
    """An input data file is missing, unreadable, or its content is unusable."""

    exit_code = 1


class OutputError(AfmidError):
    """An output cannot be written (exists without --overwrite, unwritable dir)."""

    exit_code = 1


class EngineError(AfmidError):
    """The engine that runs a map's chunks or a batch's items cannot go on: its dask scheduler cannot be reached,
    does not answer, is not a dask scheduler or was lost mid-run, or it has had no worker for the worker timeout.

    Raised by :class:`afmid.batch.engine_dask.DaskEngine` after it has reported every task that finished (the
    others as unfinished); callers keep what finished (the map's chunks in its sidecar folder, the batch's run
    files and summary), so that the same command, run again on any cluster, resumes. ``key`` names the option
    (``--scheduler``, ``AFMID_SCHEDULER`` or ``--worker-timeout``) the user can act on.
    """

    exit_code = 1


class DefinitionError(Exception):
    """A registry declaration is malformed. This is a programming error, not a user error."""
