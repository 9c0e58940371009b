"""National Instruments TDMS files, read with the optional package npTDMS.

- Channel: 'group/channel', or just the channel name if no other group has it.
- Sample rate: the channel's ``wf_increment`` property (s per sample).
- Units: the channel's ``unit_string`` property.
- Metadata: file, group and channel properties.

Only the chosen channels are read from disk. A file whose last segment is
incomplete (acquisition interrupted) is reported as truncated, because its
last samples may be misaligned between channels.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from afmid.io.readers.base import (
    RawTrace,
    Reader,
    as_samples,
    check_array_size,
    choose_channels,
    missing_package,
    not_readable,
    plain,
    settle_rate,
    time_axis,
)

_TDMS_EPOCH = np.datetime64("1904-01-01T00:00:00", "ns")

# npTDMS logs (and then works around) a damaged file instead of raising; these
# phrases in its warnings mean that data are missing.
_TRUNCATION_PHRASES = ("less data than expected", "incomplete", "Cropping data", "not a multiple of the chunk size")


class _Warnings(logging.Handler):
    """Collects npTDMS's warnings while a file is read."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@contextlib.contextmanager
def _open(path: Path) -> Iterator[object]:
    """The open TdmsFile; parse failures and truncation become InputErrors."""
    try:
        from nptdms import TdmsFile
    except ImportError:
        raise missing_package("npTDMS", ".tdms", path) from None
    collector = _Warnings()
    logger = logging.getLogger("nptdms")
    logger.addHandler(collector)
    muted = _mute_console_handlers()
    try:
        try:
            # Raw timestamps keep their 2^-64 s resolution; npTDMS would round them to 1 us.
            tdms = TdmsFile.open(path, raw_timestamps=True)
        except Exception as exc:  # npTDMS raises value, EOF and struct errors on damaged files
            raise not_readable("TDMS", path, exc) from None
        with tdms:
            yield tdms
            problems = [m for m in collector.messages if any(p in m for p in _TRUNCATION_PHRASES)]
            if problems:
                raise not_readable("TDMS", path, RuntimeError(problems[0]))
    finally:
        logger.removeHandler(collector)
        for module_logger, handler in muted:
            module_logger.addHandler(handler)


def _mute_console_handlers() -> list[tuple[logging.Logger, logging.Handler]]:
    """Detach npTDMS's own stderr handlers (it prints raw bytes of a damaged file); returns them to re-attach.

    Its warnings still reach the collector of :func:`_open` through the 'nptdms' logger.
    """
    muted = []
    for name, module_logger in list(logging.Logger.manager.loggerDict.items()):
        if name.startswith("nptdms.") and isinstance(module_logger, logging.Logger):
            for handler in list(module_logger.handlers):
                if isinstance(handler, logging.StreamHandler):
                    module_logger.removeHandler(handler)
                    muted.append((module_logger, handler))
    return muted


def _channels(tdms) -> dict[str, tuple[object, object]]:
    """'group/channel' -> (group, channel)."""
    return {
        f"{group.name}/{channel.name}": (group, channel) for group in tdms.groups() for channel in group.channels()
    }


def _data(channel, path: Path):
    """A channel's samples; timestamps as datetime64[ns]."""
    try:
        length, dtype = len(channel), channel.dtype
    except Exception as exc:  # as below: the segment index of a damaged file
        raise not_readable("TDMS", path, exc) from None
    check_array_size((length,), dtype if dtype is not None else np.float64, file=path, channel=channel.name)
    try:
        data = channel[:]
    except Exception as exc:  # as in _open: a damaged segment fails in many ways
        raise not_readable("TDMS", path, exc) from None
    return _timestamps(data) if hasattr(data, "second_fractions") else data


def _timestamps(raw) -> np.ndarray:
    """Raw TDMS timestamps (s since 1904 plus 2^-64 s fractions) as datetime64[ns], rounded.

    npTDMS's own conversion truncates, which makes evenly spaced timestamps
    come out 1 ns short every other sample.
    """
    fraction_ns = np.rint(raw.second_fractions.astype(np.float64) * (1e9 / 2.0**64)).astype(np.int64)
    ns = raw.seconds.astype(np.int64) * 1_000_000_000 + fraction_ns
    return _TDMS_EPOCH + ns.astype("timedelta64[ns]")


def _properties(obj) -> dict:
    """Properties as plain values, timestamps as ISO 8601 text."""
    return {
        str(key): str(value.as_datetime64("us")) if hasattr(value, "as_datetime64") else plain(value)
        for key, value in obj.properties.items()
    }


def list_channels(path: Path) -> list[str]:
    """'group/channel' names of all channels."""
    with _open(path) as tdms:
        return list(_channels(tdms))


def read(path: Path, channel: str | None = None, time_channel: str | None = None) -> RawTrace:
    """Read one channel (file units) and optionally a time channel (s)."""
    with _open(path) as tdms:
        channels = _channels(tdms)
        names = list(channels)
        index, t_index = choose_channels(names, channel, time_channel, file=path)
        name = names[index]
        group, chosen = channels[name]
        values = as_samples(_data(chosen, path), file=path, channel=name)
        properties = _properties(chosen)
        source = {"values": f"file:{name}"}

        units = properties.get("unit_string") or None
        if units:
            source["units"] = f"file:{name}/unit_string"

        time = t_name = None
        if t_index is not None:
            t_name = names[t_index]
            t_channel = channels[t_name][1]
            t_units = _properties(t_channel).get("unit_string") or None
            time = time_axis(_data(t_channel, path), t_units, file=path, channel=t_name)
            source["time"] = f"file:{t_name}" + ("" if t_units else " (taken as s)")

        increment = properties.get("wf_increment")  # s per sample, set for LabVIEW waveforms
        stated = None
        if isinstance(increment, (int, float)) and increment > 0:
            stated = 1.0 / increment, f"file:{name}/wf_increment"
        sample_rate = settle_rate(stated, time, t_name, source)

        metadata = {
            "file": _properties(tdms),
            "group": _properties(group),
            "channel": properties,
        }
    return RawTrace(values, time, sample_rate, units, name, names, metadata, source)


READER = Reader(
    name="tdms",
    title="National Instruments TDMS",
    suffixes=(".tdms",),
    read=read,
    list_channels=list_channels,
    extra="formats",
    references=(
        "National Instruments, TDMS File Format Internal Structure, https://www.ni.com/en/support/documentation/"
        "supplemental/07/tdms-file-format-internal-structure.html",
        "npTDMS, https://nptdms.readthedocs.io",
    ),
)
