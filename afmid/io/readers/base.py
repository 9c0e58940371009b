"""Types and helpers shared by the file readers.

Every reader turns one file into a :class:`RawTrace`: the samples of one
channel in the file's own units, plus whatever the file states about them
(units, sample rate, time axis) and where each of those came from. Converting
units and checking the samples (NaN, length, sampling) is the caller's job.

Channel names are matched the same way in every format (see
:func:`resolve_channel`), so ``data.column: deflection`` finds a CSV column
``deflection [nm]``, an HDF5 dataset ``/deflection`` or a TDMS channel
``AFM/deflection`` alike.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from afmid.errors import InputError
from afmid.io.files import memory_shortfall, safe_excerpt
from afmid.registry import closest

COLUMN_KEY = "data.column"
TIME_KEY = "data.time_column"

#: Time units a time channel may declare, as factors to seconds.
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "μs": 1e-6, "ns": 1e-9}
_RATE_UNITS = {"hz": 1.0, "khz": 1e3, "mhz": 1e6, "ghz": 1e9}  # also in any case: "MHZ", "khz" (older files)
#: Counts a rate may be written in: "60 MS/s", "2 MSa/s", "1e6 samples/s" (dimensionless, with SI prefixes).
SAMPLE_COUNT_SYMBOLS = ("S", "Sa", "sample", "samples")
#: What a sample rate or time step may be written in, for messages.
RATE_UNIT_WORDS = "Hz, kHz, MHz, S/s, kS/s, MS/s, Sa/s, MSa/s or s^-1"
STEP_UNIT_WORDS = "s, ms, us, µs or ns"

# Name suffixes read as units ("deflection_nm", "time_s"). A closed list on
# purpose: "_x" or "_raw" end many channel names without being units.
_SUFFIX_UNITS = frozenset({"m", "mm", "um", "µm", "nm", "pm", "V", "mV", "s", "ms", "us", "ns"})
_BRACKETED_UNIT = re.compile(r"^(?P<base>.*?\S)\s*[\[(](?P<unit>[^\[\]()]+)[\])]\s*$")
_NUMBER_WITH_UNIT = re.compile(
    r"^\s*(?P<number>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(?P<unit>[A-Za-zµμ(1][A-Za-zµμ0-9/*^() -]*)?\s*$")

#: Names that mark a time axis; such channels are never picked as the default signal.
TIME_NAMES = frozenset({"t", "time", "times", "timestamp"})
_DEFAULT_NAME = "deflection"
_LISTED_NAMES = 20  # longer channel lists are cut in messages
_LISTING_CHARS = 300  # and so are lists of long names


@dataclass
class RawTrace:
    """One channel read from a file, not yet converted or checked.

    ``values`` are in the file's units (``units``, e.g. 'm', 'nm', 'V'); ``time``
    is in seconds; ``sample_rate`` in Hz. ``source`` says where each of
    ``values``, ``units``, ``sample_rate`` and ``time`` came from.

    An instrument file's reader may also fill ``metadata['stated']`` (config key ->
    SI value the file states: 'drive.frequency', 'cantilever.spring_constant',
    'data.invols'), ``metadata['stated_where']`` (config key -> where in the file)
    and ``metadata['sample_rate_problem']`` (why its stated rates give no rate);
    :func:`afmid.io.trace.load_trace` and ``afmid inspect`` / ``init-config --from`` use them.
    """

    values: np.ndarray
    time: np.ndarray | None
    sample_rate: float | None
    units: str | None
    channel: str
    channels: list[str]
    metadata: dict = field(default_factory=dict)
    source: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Reader:
    """A file format: ``read(path, channel, time_channel) -> RawTrace``."""

    name: str
    title: str
    suffixes: tuple[str, ...]
    read: Callable[..., RawTrace]
    list_channels: Callable[[Path], list[str]]
    extra: str | None
    references: tuple[str, ...]


# --------------------------------------------------------------------------- names and units
def split_units(name: str) -> tuple[str, str | None]:
    """``'deflection [nm]'``, ``'deflection (nm)'``, ``'deflection_nm'`` -> ``('deflection', 'nm')``."""
    match = _BRACKETED_UNIT.match(name)
    if match:
        return match["base"], match["unit"].strip()
    head, sep, tail = name.rpartition("_")
    if sep and head and tail in _SUFFIX_UNITS:
        return head, tail
    return name, None


def column_stem(name: str) -> str:
    """Lower-case last component of a channel name without units: '/AFM/Defl_nm' -> 'defl'."""
    base = split_units(name)[0]
    return re.split(r"[/.]", base)[-1].strip().lower()


def listing(names: Sequence[str]) -> str:
    """Channel names for a message (each as :func:`afmid.io.files.safe_excerpt`), cut after a screenful."""
    parts: list[str] = []
    for name in names[:_LISTED_NAMES]:
        shown_name = safe_excerpt(name)
        if parts and sum(len(p) + 2 for p in parts) + len(shown_name) > _LISTING_CHARS:
            break
        parts.append(shown_name)
    shown = ", ".join(parts) or "(none)"
    if len(names) > len(parts):
        shown += f", ... ({len(names) - len(parts)} more)"
    return shown


def quoted(name: object) -> str:
    """A name read from a file, quoted for a message: printable ASCII, at most 60 characters."""
    return repr(safe_excerpt(name))


def resolve_channel(
    names: Sequence[str],
    wanted: str | int,
    *,
    file: Path,
    key: str = COLUMN_KEY,
    positional: bool = False,
    listed: Sequence[str] | None = None,
) -> int:
    """Index into ``names`` of the channel the user asked for.

    ``wanted`` may be the exact name, the name in another case, the name
    without its units ('deflection' for 'deflection [nm]') or its last
    component ('x' for 'dev1.demods.sample.x'), as long as that is unambiguous.
    With ``positional`` (columns without meaningful names), an int or a digit
    string is a 0-based index. ``listed`` are the names offered in messages
    (default: ``names``).
    """
    listed = list(names) if listed is None else list(listed)
    if isinstance(wanted, int) or (isinstance(wanted, str) and wanted.strip().isdecimal()):
        index = int(wanted)
        if not positional:
            raise InputError(
                f"channels in this format are chosen by name, not by index {index}; available: {listing(listed)}",
                file=file,
                key=key,
            )
        if not 0 <= index < len(names):
            raise InputError(
                f"column index {index} is out of range: the file has {len(names)} columns ({listing(listed)})",
                file=file,
                key=key,
            )
        return index
    text = str(wanted).strip()
    tiers: tuple[Callable[[str], bool], ...] = (
        lambda n: n == text,
        lambda n: n.lower() == text.lower(),
        lambda n: split_units(n)[0].lower() == text.lower(),
        lambda n: column_stem(n) == text.lower(),
    )
    for matches_tier in tiers:
        hits = [i for i, name in enumerate(names) if matches_tier(name)]
        if len(hits) == 1:
            return hits[0]
        if len(hits) > 1:
            raise InputError(
                f"channel {quoted(text)} is ambiguous: it matches {listing([names[i] for i in hits])}",
                file=file,
                key=key,
            )
    hint = closest(text, listed)
    suggestion = f" (did you mean {quoted(hint)}?)" if hint else ""
    raise InputError(f"no channel {quoted(text)}{suggestion}; available: {listing(listed)}", file=file, key=key)


def default_channel(names: Sequence[str], *, file: Path, exclude: str | None = None) -> int:
    """Index of the channel to read when none is named.

    A channel named 'deflection' (with or without units) wins; otherwise the
    only channel that is not a time axis. ``exclude`` (the chosen time
    channel) is never picked. Anything else is ambiguous.
    """
    pool = [i for i, name in enumerate(names) if name != exclude]
    named = [i for i in pool if column_stem(names[i]) == _DEFAULT_NAME]
    if len(named) == 1:
        return named[0]
    signals = [i for i in pool if column_stem(names[i]) not in TIME_NAMES]
    if len(signals) == 1:
        return signals[0]
    if not pool:
        raise InputError("the file holds no numeric channel", file=file, key=COLUMN_KEY)
    offered = [names[i] for i in pool]
    raise InputError(
        f"the file has {len(offered)} channels; choose one with data.column: {listing(offered)}",
        file=file,
        key=COLUMN_KEY,
    )


def choose_channels(
    names: Sequence[str],
    channel: str | int | None,
    time_channel: str | int | None,
    *,
    file: Path,
    positional: bool = False,
    listed: Sequence[str] | None = None,
) -> tuple[int, int | None]:
    """Indices into ``names`` of the signal and of the time channel (None if not asked for).

    Names are resolved by :func:`resolve_channel`; without ``channel`` the
    signal is the :func:`default_channel` among ``listed`` (default: all
    ``names``), never the time channel.
    """
    kwargs = {"file": file, "positional": positional, "listed": listed}
    time_index = None
    if time_channel is not None:
        time_index = resolve_channel(names, time_channel, key=TIME_KEY, **kwargs)
    if channel is not None:
        return resolve_channel(names, channel, **kwargs), time_index
    pool = list(names) if listed is None else list(listed)
    exclude = None if time_index is None else names[time_index]
    return list(names).index(pool[default_channel(pool, file=file, exclude=exclude)]), time_index


# --------------------------------------------------------------------------- samples
def as_samples(array: Any, *, file: Path, channel: str, key: str = COLUMN_KEY) -> np.ndarray:
    """``array`` as 1-D float64, or an InputError saying why it is not a trace.

    Singleton axes are dropped, because MATLAB and HDF5 exports often store a
    vector as an N x 1 or 1 x N matrix.
    """
    arr = np.asarray(array)
    if arr.dtype.kind not in "iuf":
        raise InputError(f"channel {quoted(channel)} is not numeric (dtype {arr.dtype})", file=file, key=key)
    if arr.ndim > 1 and sum(n > 1 for n in arr.shape) <= 1:
        arr = arr.reshape(-1)
    if arr.ndim == 0:
        raise InputError(f"channel {quoted(channel)} is a single value, not a trace", file=file, key=key)
    if arr.ndim != 1:
        raise InputError(
            f"channel {quoted(channel)} has shape {arr.shape}; a trace must be 1-D", file=file, key=key
        )
    if arr.size == 0:
        raise InputError(f"channel {quoted(channel)} is empty", file=file, key=key)
    return arr.astype(np.float64, copy=False)


def time_axis(array: Any, units: str | None, *, file: Path, channel: str) -> np.ndarray:
    """A time channel in seconds.

    Declared units are converted; timestamps become seconds since the first
    sample. Integers without units are refused rather than taken as seconds:
    they are usually clock ticks or sample numbers.
    """
    arr = np.asarray(array)
    if arr.dtype.kind == "M" and arr.size:
        seconds = (arr - arr.flat[0]) / np.timedelta64(1, "ns") * 1e-9
        return as_samples(seconds, file=file, channel=channel, key=TIME_KEY)
    if units:
        scale = TIME_UNITS.get(units.strip())
        if scale is None:
            raise InputError(
                f"time channel {quoted(channel)} has units {quoted(units)}, not a time unit ({', '.join(TIME_UNITS)})",
                file=file,
                key=TIME_KEY,
            )
        return as_samples(arr, file=file, channel=channel, key=TIME_KEY) * scale
    if arr.dtype.kind in "iu":
        raise InputError(
            f"time channel {quoted(channel)} holds integers without units (clock ticks or sample numbers?); "
            "give data.sample_rate instead of data.time_column",
            file=file,
            key=TIME_KEY,
        )
    return as_samples(arr, file=file, channel=channel, key=TIME_KEY)


def rate_from_time(time: np.ndarray) -> float | None:
    """Sample rate in Hz of a uniform time axis (s), else None.

    The step is the mean over the whole span, and steps may deviate from it
    by 1 %: time columns written as text are rounded, which makes single
    steps jitter although the sampling is uniform.
    """
    if time.size < 2:
        return None
    step = (time[-1] - time[0]) / (time.size - 1)
    if not (math.isfinite(step) and step > 0):
        return None
    # Written as "not all within" so that NaN steps also mean "not uniform".
    if not np.all(np.abs(np.diff(time) - step) <= 0.01 * step):
        return None
    return float(1.0 / step)


def settle_rate(
    stated: tuple[float, str] | None, time: np.ndarray | None, time_name: str | None, source: dict
) -> float | None:
    """The stated sample rate (Hz), else one derived from a uniform time axis, else None.

    ``stated`` is (rate, source) as from :func:`rate_from_fields`; the source
    of the result is recorded in ``source['sample_rate']``.
    """
    if stated:
        rate, source["sample_rate"] = stated
        return rate
    rate = None if time is None else rate_from_time(time)
    if rate is not None:
        source["sample_rate"] = f"derived:uniform time channel {time_name!r}"
    return rate


# --------------------------------------------------------------------------- metadata
def _unit_factor(unit: str, unit_scales: Mapping[str, float], dimension: str) -> float | None:
    """The factor to SI of ``unit`` (a rate: s^-1, or a step: s), else None.

    The older table first (case-insensitive: "mhz" has always meant MHz in afmid), then the unit parsed with SI
    prefixes (afmid.terms.units.parse_scaled_unit), counts of samples allowed: "MS/s", "kSa/s", "s^-1", "µs".
    """
    if unit.lower() in unit_scales:
        return unit_scales[unit.lower()]
    from afmid.terms.units import DIMENSIONLESS, parse_scaled_unit, parse_unit

    try:
        factor, parsed = parse_scaled_unit(unit, {name: DIMENSIONLESS for name in SAMPLE_COUNT_SYMBOLS})
    except ValueError:
        return None
    return factor if parsed == parse_unit(dimension) else None


def _number(value: Any, unit_scales: Mapping[str, float], dimension: str = "s^-1") -> float | None:
    """A positive finite number from an attribute value, optionally with a unit ('2 MHz', '60 MS/s') of
    ``dimension``."""
    if isinstance(value, (list, tuple, np.ndarray)) and np.size(value) == 1:
        value = np.ravel(value)[0]  # one-element attribute arrays, 1 x 1 MATLAB matrices
    value = plain(value)
    if isinstance(value, str):
        match = _NUMBER_WITH_UNIT.match(value)
        if not match:
            return None
        scale = _unit_factor(match["unit"].strip(), unit_scales, dimension) if match["unit"] else unit_scales.get("")
        if scale is None:
            return None
        value = float(match["number"]) * scale
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) and value > 0 else None


def rate_from_fields(
    fields: Mapping[str, Any], where: Callable[[str], str], *, file: Path
) -> tuple[float, str] | None:
    """Sample rate (Hz) and its source, from a field ``sample_rate`` (Hz) or ``dt``/``time_step`` (s).

    ``fields`` are attributes, scalar variables or ``key: value`` header lines;
    ``where(name)`` says where the field is, for messages and ``RawTrace.source``.
    A field that is present but unusable is an error, not silently skipped.
    """
    seconds = {"": 1.0, **{u.lower(): f for u, f in TIME_UNITS.items()}}
    for name, scales, invert in (
        ("sample_rate", {"": 1.0, **_RATE_UNITS}, False),
        ("dt", seconds, True),
        ("time_step", seconds, True),
    ):
        if name not in fields:
            continue
        number = _number(fields[name], scales, "s^-1" if name == "sample_rate" else "s")
        if number is None:
            expected = (f"a positive number of Hz, or one with a rate unit ({RATE_UNIT_WORDS})"
                        if name == "sample_rate" else
                        f"a positive number of seconds, or one with a time unit ({STEP_UNIT_WORDS})")
            raise InputError(f"{where(name)} = {quoted(plain(fields[name]))} is not {expected}", file=file)
        return (1.0 / number if invert else number), f"file:{where(name)}"
    return None


def plain(value: Any) -> Any:
    """Metadata as plain Python values: numpy scalars -> int/float/str, bytes -> str, arrays -> lists."""
    if isinstance(value, (bytes, np.bytes_)):
        return bytes(value).decode("utf-8", "replace")
    if isinstance(value, np.datetime64):
        return str(value)
    if isinstance(value, np.generic):
        return plain(value.item())
    if isinstance(value, np.ndarray):
        return plain(value.tolist()) if value.dtype.kind != "M" else [str(v) for v in value.ravel()]
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return value


# --------------------------------------------------------------------------- errors
def not_readable(kind: str, file: Path, exc: BaseException) -> InputError:
    """The error for a file the format's parser rejects (the parser's complaint cut to one short line)."""
    detail = " ".join(str(exc).split()) or type(exc).__name__
    return InputError(f"not a readable {kind} file (truncated or corrupt?): {safe_excerpt(detail, 160)}", file=file)


def check_array_size(shape: Sequence[int], dtype: Any, *, file: Path, channel: str, key: str = COLUMN_KEY) -> None:
    """Refuse to read an array of ``shape`` and ``dtype`` that would not fit in the available memory.

    Counts the array as stored plus its float64 copy (:func:`as_samples`), so
    that a file whose header claims 10^12 samples is refused before anything
    is allocated.
    """
    count = math.prod(int(n) for n in shape)
    itemsize = np.dtype(dtype).itemsize if np.dtype(dtype).kind in "iufcb" else 8
    needed = count * (itemsize + (0 if np.dtype(dtype) == np.float64 else 8))
    problem = memory_shortfall(needed)
    if problem:
        raise InputError(
            f"channel {quoted(channel)} has {count:.3g} values (shape {tuple(int(n) for n in shape)}); "
            f"reading it {problem}",
            file=file,
            key=key,
        )


def missing_package(package: str, suffix: str, file: Path) -> InputError:
    """The error for a format whose optional dependency is not installed."""
    return InputError(
        f"reading {suffix} files needs the optional package {package}: pip install 'afmid[formats]'",
        file=file,
    )


def no_time_channel(file: Path, why: str) -> InputError:
    """The error for a time channel requested from a file that cannot have one."""
    return InputError(f"the file has no time channel: {why}", file=file, key=TIME_KEY)
