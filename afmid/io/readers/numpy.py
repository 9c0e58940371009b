"""NumPy ``.npy`` arrays and ``.npz`` archives.

- ``.npy``, 1-D: the trace itself (``channel`` is ignored; the channel is '0').
- ``.npy``, 2-D: one column per channel, chosen by 0-based index; rows are samples.
- ``.npz``: one array per channel, chosen by name. Scalar arrays are not
  channels but metadata; ``sample_rate`` (Hz) or ``dt``/``time_step`` (s) among
  them set the sample rate. Units may be given in array names (``deflection_nm``).

A time array (``t``, ``time``, or a column) is read only when asked for.
Arrays are loaded with ``allow_pickle=False``: a data file never runs code.
"""

from __future__ import annotations

import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from afmid.errors import InputError
from afmid.io.readers.base import (
    COLUMN_KEY,
    RawTrace,
    Reader,
    as_samples,
    check_array_size,
    choose_channels,
    no_time_channel,
    not_readable,
    plain,
    rate_from_fields,
    settle_rate,
    split_units,
    time_axis,
)

# What np.load raises on damaged files (zlib.error: a damaged np.savez_compressed member; TokenError and
# SyntaxError: a damaged header, which numpy parses as a Python literal).
_LOAD_ERRORS = (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error, tokenize.TokenError, SyntaxError)
_NPY_MAGIC = b"\x93NUMPY"
_ZIP_MAGIC = b"PK\x03\x04"


def _checked(path: Path, name: str, load, *args, **kwargs):
    """``load(*args, **kwargs)`` reading array ``name`` of ``path``.

    An object array (needs pickle) is 'not numeric'; any other failure means a damaged file.
    """
    try:
        return load(*args, **kwargs)
    except _LOAD_ERRORS as exc:
        if "allow_pickle" in str(exc):
            raise InputError(f"array {name!r} holds Python objects, not numbers", file=path, key=COLUMN_KEY) from None
        raise not_readable("NumPy", path, exc) from None


def _npy_header(fh, path: Path, name: str) -> tuple[tuple[int, ...], np.dtype, int]:
    """(shape, dtype, bytes of data the header promises) of the .npy stream ``fh``, positioned at its start."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fh)
        read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, _, dtype = read_header(fh)
    except _LOAD_ERRORS as exc:
        raise not_readable("NumPy", path, exc) from None
    if dtype.hasobject:
        raise InputError(f"array {name!r} holds Python objects, not numbers", file=path, key=COLUMN_KEY)
    return shape, dtype, int(np.prod(shape, dtype=object)) * dtype.itemsize


def _check_sizes(path: Path, is_npy: bool) -> None:
    """Refuse, before np.load allocates anything, arrays whose header promises more data than the file
    holds (a corrupt or lying header) or than the available memory."""

    def check(shape, dtype, promised: int, held: int, name: str) -> None:
        if promised > held:
            raise not_readable("NumPy", path, ValueError(
                f"the header of {name!r} promises {promised} bytes of data (shape {shape}) but the file holds {held}"))
        check_array_size(shape, dtype, file=path, channel=name)

    if is_npy:
        with open(path, "rb") as fh:
            shape, dtype, promised = _npy_header(fh, path, path.name)
            check(shape, dtype, promised, path.stat().st_size - fh.tell(), path.name)
        return
    try:
        with zipfile.ZipFile(path) as archive:
            for member in archive.infolist():
                if not member.filename.endswith(".npy"):
                    continue
                name = member.filename[: -len(".npy")]
                with archive.open(member) as fh:
                    shape, dtype, promised = _npy_header(fh, path, name)
                    check(shape, dtype, promised, member.file_size - fh.tell(), name)
    except _LOAD_ERRORS as exc:
        raise not_readable("NumPy", path, exc) from None


def _load(path: Path):
    """An ndarray (.npy) or a lazy archive (.npz), told apart by content, not suffix."""
    with open(path, "rb") as fh:
        magic = fh.read(len(_NPY_MAGIC))
    # Without either signature np.load would try to unpickle the file.
    if not magic.startswith((_NPY_MAGIC, _ZIP_MAGIC)):
        raise not_readable("NumPy", path, ValueError("no .npy or .npz signature at the start"))
    _check_sizes(path, magic.startswith(_NPY_MAGIC))
    return _checked(path, path.name, np.load, path, allow_pickle=False)


def _npz_arrays(archive, path: Path) -> dict[str, np.ndarray]:
    """All arrays of an archive (trace archives hold a few arrays; loading them all is cheap)."""
    with archive:
        names = list(archive.files)
        return {name: _checked(path, name, archive.__getitem__, name) for name in names}


def _is_channel(array: np.ndarray) -> bool:
    """Numeric with one axis longer than 1: what can be read as a trace."""
    return array.dtype.kind in "iuf" and sum(n > 1 for n in array.shape) == 1


def list_channels(path: Path) -> list[str]:
    """Array names (.npz), column indices as strings (2-D .npy), or '0' (1-D .npy)."""
    loaded = _load(path)
    if not isinstance(loaded, np.ndarray):
        return [name for name, array in _npz_arrays(loaded, path).items() if _is_channel(array)]
    if loaded.ndim == 2:
        return [str(i) for i in range(loaded.shape[1])]
    return ["0"] if loaded.ndim == 1 else []


def _read_npy(array: np.ndarray, path: Path, channel, time_channel) -> RawTrace:
    metadata = {"shape": list(array.shape)}
    if array.ndim == 1:
        if time_channel is not None:
            raise no_time_channel(path, "a 1-D .npy file holds a single channel")
        values = as_samples(array, file=path, channel="0")
        return RawTrace(values, None, None, None, "0", ["0"], metadata, {"values": "file:array"})
    if array.ndim != 2:
        raise InputError(
            f"the array has shape {array.shape}; expected 1-D (one trace) or 2-D (samples x channels)",
            file=path,
            key=COLUMN_KEY,
        )
    names = [str(i) for i in range(array.shape[1])]
    index, t_index = choose_channels(names, channel, time_channel, file=path, positional=True)
    values = as_samples(array[:, index], file=path, channel=names[index])
    source = {"values": f"file:column {index}"}
    time = t_name = None
    if t_index is not None:
        t_name = names[t_index]
        time = time_axis(array[:, t_index], None, file=path, channel=t_name)
        source["time"] = f"file:column {t_index} (taken as s)"
    sample_rate = settle_rate(None, time, t_name, source)
    return RawTrace(values, time, sample_rate, None, names[index], names, metadata, source)


def _read_npz(archive, path: Path, channel, time_channel) -> RawTrace:
    arrays = _npz_arrays(archive, path)
    names = list(arrays)
    channels = [name for name, array in arrays.items() if _is_channel(array)]
    scalars = {name: plain(array.reshape(())) for name, array in arrays.items() if array.size == 1}
    index, t_index = choose_channels(names, channel, time_channel, file=path, listed=channels)
    name = names[index]
    values = as_samples(arrays[name], file=path, channel=name)
    units = split_units(name)[1]
    source = {"values": f"file:array {name!r}"}
    if units:
        source["units"] = f"file:array name {name!r}"
    time = t_name = None
    if t_index is not None:
        t_name = names[t_index]
        t_units = split_units(t_name)[1]
        time = time_axis(arrays[t_name], t_units, file=path, channel=t_name)
        source["time"] = f"file:array {t_name!r}" + ("" if t_units else " (taken as s)")
    stated = rate_from_fields(scalars, lambda key: f"array {key!r}", file=path)
    sample_rate = settle_rate(stated, time, t_name, source)
    return RawTrace(values, time, sample_rate, units, name, channels, {"scalars": scalars}, source)


def read(path: Path, channel: str | int | None = None, time_channel: str | int | None = None) -> RawTrace:
    """Read one array or column (file units) and optionally a time array or column (s)."""
    loaded = _load(path)
    if isinstance(loaded, np.ndarray):
        return _read_npy(loaded, path, channel, time_channel)
    return _read_npz(loaded, path, channel, time_channel)



READER = Reader(
    name="npy",
    title="NumPy array (.npy) or archive (.npz)",
    suffixes=(".npy", ".npz"),
    read=read,
    list_channels=list_channels,
    extra=None,
    references=(
        "NEP 1, A Simple File Format for NumPy Arrays, https://numpy.org/neps/nep-0001-npy-format.html",
        "numpy.load, https://numpy.org/doc/stable/reference/generated/numpy.load.html",
    ),
)
