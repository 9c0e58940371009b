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
import struct
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path

from afmid.errors import InputError
from afmid.io.files import check_input_file
from afmid.registry import Registry
import afmid.io.readers.csv as csv
import afmid.io.readers.hdf5 as hdf5
import afmid.io.readers.hsdc as hsdc
import afmid.io.readers.igor as igor
import afmid.io.readers.matlab as matlab
import afmid.io.readers.numpy as numpy
import afmid.io.readers.tdms as tdms
from afmid.io.readers.base import TIME_KEY, RawTrace, Reader, not_readable

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
for _module in (csv, numpy, hdf5, matlab, igor, tdms, hsdc):
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
    """``path`` if it is a readable regular file (no FIFO, device, folder, link loop), else an InputError."""
    return check_input_file(path, what="file", key="data.path", allow_empty=True)


#: What parsers raise on a damaged file (h5py: RuntimeError and KeyError on broken object headers).
_DAMAGED_FILE_ERRORS = (
    KeyError, ValueError, RuntimeError, EOFError, IndexError, OverflowError, struct.error, zlib.error,
    zipfile.BadZipFile,
)
#: The kind of file named in "not a readable ... file" messages, by reader name.
_KINDS = {"csv": "text", "npy": "NumPy", "hdf5": "HDF5", "mat": "MATLAB", "ibw": "Igor binary wave", "tdms": "TDMS", "hsdc": "NanoScope HSDC"}


@contextlib.contextmanager
def _reader_errors(path: Path, reader: Reader) -> Iterator[None]:
    """Failures of a third-party parser on a damaged file, permission and I/O errors: one InputError naming the file.

    Each reader turns the failures it expects into InputErrors itself; this
    catches what a corrupt file provokes elsewhere in h5py, scipy, igor2 or npTDMS.
    """
    try:
        yield
    except InputError:
        raise
    except OSError as exc:
        if exc.errno is None:  # not the operating system's: h5py's word for damaged content
            raise not_readable(_KINDS.get(reader.name, reader.name), path, exc) from exc
        raise InputError(f"cannot read the file: {exc.strerror or exc}", file=path) from exc
    except MemoryError:
        raise InputError("not enough memory to read the file (corrupt sizes in it?)", file=path) from None
    except _DAMAGED_FILE_ERRORS as exc:
        raise not_readable(_KINDS.get(reader.name, reader.name), path, exc) from exc


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
    with _reader_errors(path, reader):
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
    with _reader_errors(path, reader):
        return reader.list_channels(path)
