"""User-facing errors.

Every problem caused by the user's input (a file, a config value, a command-line
option) is raised as an :class:`AfmidError`. The CLI prints it as one line and
exits with :attr:`AfmidError.exit_code`; no traceback unless ``-v`` is given.
Anything else that escapes is a bug in afmid and is shown with its traceback.
"""

from __future__ import annotations

from pathlib import Path


class AfmidError(Exception):
    """An error the user can fix. Formats as ``file: key.path: message``."""

    exit_code = 1

    def __init__(self, message: str, *, file: str | Path | None = None, key: str | None = None):
        self.message = message
        self.file = str(file) if file is not None else None
        self.key = key
        super().__init__(self.format())

    def format(self) -> str:
        parts = [p for p in (self.file, self.key) if p]
        parts.append(self.message)
        return ": ".join(parts)


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
    """An engine lost tasks it had been given (a lost or killed cluster, cancelled work): nothing is wrong with
    the inputs, and a run that keeps its finished work (``afmid map``'s sidecar) resumes when run again."""

    exit_code = 1


class DefinitionError(Exception):
    """A registry declaration is malformed. This is a programming error, not a user error."""
