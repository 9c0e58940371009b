"""File readers: one small module per format, declared in :data:`READERS`.

Each reader turns a file into a :class:`RawTrace` (one channel, in the file's
units, with what the file says about units, sample rate and time).
:func:`read_trace` picks the reader by suffix (or by name) and turns every
problem with the file into an :class:`~afmid.errors.InputError` naming it.

Importing this package is cheap: h5py, scipy, igor2 and npTDMS are imported
inside the read functions that need them.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from ..errors import InputError
from ..registry import Registry
from . import csv, hdf5, igor, matlab, numpy, tdms
from .base import TIME_KEY, RawTrace, Reader

__all__ = ["READERS", "RawTrace", "Reader", "list_channels", "read_trace", "reader_for"]


def _check(reader: Reader) -> None:
    if not reader.suffixes:
        raise ValueError("needs at least one suffix")
    for suffix in reader.suffixes:
        if not suffix.startswith(".") or suffix != suffix.lower():
            raise ValueError(f"suffix {suffix!r} must be lower-case and start with '.'")
        for other in READERS:
            if suffix in other.suffixes:
                raise ValueError(f"suffix {suffix!r} is already read by {other.name!r}")
    if not (callable(reader.read) and callable(reader.list_channels)):
        raise ValueError("read and list_channels must be callable")


READERS: Registry[Reader] = Registry("file format", validate=_check)
for _module in (csv, numpy, hdf5, matlab, igor, tdms):
    READERS.register(_module.READER)


def reader_for(path: str | Path, fmt: str = "auto") -> Reader:
    """The reader for ``path``: by its suffix when ``fmt`` is 'auto', else by name."""
    path = Path(path)
    allowed = ", ".join(READERS.names())
    if fmt in (None, "auto"):
        suffix = path.suffix.lower()
        for reader in READERS:
            if suffix in reader.suffixes:
                return reader
        raise InputError(
            f"cannot tell the format from the suffix {suffix or '(none)'!r}; set data.format to one of: {allowed}",
            file=path,
            key="data.format",
        )
    try:
        return READERS.get(str(fmt).lower())
    except KeyError as exc:
        raise InputError(exc.args[0], file=path, key="data.format") from None


def _existing(path: str | Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise InputError("file not found", file=path, key="data.path")
    if path.is_dir():
        raise InputError("is a folder, not a data file", file=path, key="data.path")
    return path


@contextlib.contextmanager
def _os_errors(path: Path) -> Iterator[None]:
    """Permission and I/O errors are the user's environment, not a bug: report them as InputError."""
    try:
        yield
    except OSError as exc:
        raise InputError(f"cannot read the file: {exc.strerror or exc}", file=path) from exc


def read_trace(
    path: str | Path,
    fmt: str = "auto",
    channel: str | int | None = None,
    time_channel: str | int | None = None,
) -> RawTrace:
    """Read one channel (and optionally a time channel) from a data file.

    ``channel`` names the signal (column name or 0-based index, dataset path,
    dotted MATLAB path, 'group/channel'); None picks 'deflection' or the only
    signal. ``time_channel`` is read only when given, and returned in seconds.
    Raises InputError for a missing, unreadable or unsuitable file.
    """
    path = _existing(path)
    reader = reader_for(path, fmt)
    with _os_errors(path):
        trace = reader.read(path, channel, time_channel)
    if trace.time is not None and trace.time.size != trace.values.size:
        raise InputError(
            f"the time channel has {trace.time.size} samples but {trace.channel!r} has {trace.values.size}",
            file=path,
            key=TIME_KEY,
        )
    return trace


def list_channels(path: str | Path, fmt: str = "auto") -> list[str]:
    """Every channel the file offers (for ``afmid inspect``), with read_trace's checks and errors."""
    path = _existing(path)
    reader = reader_for(path, fmt)
    with _os_errors(path):
        return reader.list_channels(path)
