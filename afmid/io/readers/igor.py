"""Igor Pro binary waves (``.ibw``), read with the optional package igor2.

- A 1-D wave is one channel (``channel`` is ignored; the channel is the wave name).
- A 2-D wave has one channel per column, chosen by its dimension label (as
  Asylum Research force curves label them: 'Raw', 'Defl', 'ZSnsr') or by
  0-based index; a column can also serve as the time channel.
- Sample rate: from the x scaling (``sfA``, ``hsA`` before version 5) when the
  x units are a time unit, or unset with a step other than Igor's default 1;
  else from the wave note (``NumPtsPerSec: 2000000``, as Asylum Research
  writes it, or ``SampleRate``). Where the note and the x scaling disagree, the
  x scaling is used and one warning names both (as the HSDC reader does for its
  header's rates): a contradiction is stated, never resolved in silence.
- Units: the wave's data units (extended units if present). The wave note is
  kept in ``metadata['note']``.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from afmid.errors import InputError
from afmid.io.files import memory_shortfall
from afmid.io.findings import frequency
from afmid.io.readers.base import (
    TIME_UNITS,
    RawTrace,
    Reader,
    as_samples,
    choose_channels,
    missing_package,
    no_time_channel,
    not_readable,
    rate_from_fields,
    settle_rate,
    time_axis,
)

log = logging.getLogger("afmid")

_IGOR_DEFAULT_STEP = 1.0  # x scaling of a wave nobody scaled
#: Wave-note keys that state the acquisition rate in Hz (compared without case, spaces and underscores).
_NOTE_RATE_KEYS = ("numptspersec", "samplerate")
_NOTE_LINE = re.compile(r"^\s*(?P<key>[A-Za-z][\w ]*?)\s*[:=]\s*(?P<value>.*?)\s*$")
#: Rates within this of each other agree: the x scaling is a float64 step, 1/step rounds in the last digits.
_RATE_TOLERANCE = 1e-3


def _text(raw: Any) -> str:
    """Igor strings are bytes, or arrays of single bytes; Igor 7+ writes UTF-8, older versions Latin-1."""
    if isinstance(raw, np.ndarray):
        raw = b"".join(raw.ravel().tolist())
    data = bytes(raw or b"").split(b"\0", 1)[0]
    try:
        return data.decode("utf-8").strip()
    except UnicodeDecodeError:
        return data.decode("latin-1").strip()


def _load(path: Path) -> dict:
    try:
        from igor2 import binarywave
    except ImportError:
        raise missing_package("igor2", ".ibw", path) from None
    problem = memory_shortfall(2 * path.stat().st_size)  # igor2 reads the whole file, then copies the wave
    if problem:
        raise InputError(f"reading this {path.stat().st_size:.3g}-byte wave {problem}", file=path, key="data.path")
    try:
        return binarywave.load(str(path))
    except Exception as exc:  # igor2 signals a damaged file with asserts, struct and value errors
        raise not_readable("Igor binary wave", path, exc) from None


def _wave(path: Path) -> tuple[np.ndarray, dict, list[str]]:
    """(data, header fields, column names) of the wave in ``path``."""
    loaded = _load(path)
    wave = loaded["wave"]
    header = wave["wave_header"]
    data = np.asarray(wave["wData"])
    if loaded["version"] >= 5:
        step, start = float(header["sfA"][0]), float(header["sfB"][0])
        # Units longer than 3 characters are stored in the optional extended fields;
        # igor2 lists extended dimension units only for the dimensions that have them.
        has_extended_x = wave["bin_header"]["dimEUnitsSize"][0] > 0
        data_units = _text(wave.get("data_units")) or _text(header["dataUnits"])
        x_units = _text(wave["dimension_units"][0]) if has_extended_x else _text(header["dimUnits"][0])
    else:
        step, start = float(header["hsA"]), float(header["hsB"])
        data_units, x_units = _text(header["dataUnits"]), _text(header["xUnits"])
    info = {
        "wave_name": _text(header["bname"]),
        "version": int(loaded["version"]),
        "x_step": step,
        "x_start": start,
        "x_units": x_units,
        "data_units": data_units,
        "note": _text(wave.get("note")),
    }
    if data.ndim == 2:
        # Dimension labels: the first names the dimension, then one per column.
        labels = [_text(label) for label in (wave.get("labels") or [[], []])[1][1:]]
        names = labels if len(labels) == data.shape[1] and all(labels) else [str(i) for i in range(data.shape[1])]
    else:
        names = [info["wave_name"] or "0"]
    return data, info, names


def note_rate(note: str) -> tuple[float, str] | None:
    """(Hz, key) of the acquisition rate an (Asylum Research) wave note states, None without a usable one."""
    for line in re.split(r"[\r\n]+", note):
        match = _NOTE_LINE.match(line)
        if not match or re.sub(r"[\s_]", "", match["key"]).lower() not in _NOTE_RATE_KEYS:
            continue
        try:
            stated = rate_from_fields({"sample_rate": match["value"]}, lambda _: match["key"], file=Path("note"))
        except InputError:  # a note's text we cannot read as a rate: the note is a comment, not the data
            continue
        if stated is not None:
            return stated[0], match["key"]
    return None


def _settle_with_note(stated: tuple[float, str] | None, x_scaling: str, info: dict,
                      path: Path) -> tuple[float, str] | None:
    """The x scaling's (rate, source), else the note's; a note that contradicts the x scaling said in one warning
    and in the source (the x scaling is what Igor plots the wave against, and what afmid always used)."""
    found = note_rate(info["note"])
    if found is None:
        return stated
    rate, key = found
    if stated is None:
        return rate, f"file:wave note ({key}: {frequency(rate)})"
    if math.isclose(rate, stated[0], rel_tol=_RATE_TOLERANCE):
        return stated
    log.warning("%s: the wave note's %s says %s, the x scaling (%s) %s: using the x scaling's %s; if the note is "
                "right, set data.sample_rate (Hz)", path, key, frequency(rate), x_scaling, frequency(stated[0]),
                frequency(stated[0]))
    return stated[0], f"{stated[1]} {frequency(stated[0])}, not the note's {key} {frequency(rate)}"


def list_channels(path: Path) -> list[str]:
    """Column labels (or indices) of a 2-D wave; the wave name for a 1-D wave."""
    return _wave(path)[2]


def read(path: Path, channel: str | int | None = None, time_channel: str | int | None = None) -> RawTrace:
    """Read the wave or one of its columns (file units), optionally a time column (s)."""
    data, info, names = _wave(path)
    time = t_name = None
    if data.ndim == 2:
        index, t_index = choose_channels(names, channel, time_channel, file=path, positional=True)
        values = as_samples(data[:, index], file=path, channel=names[index])
        source = {"values": f"file:column {names[index]!r}"}
        if t_index is not None:
            t_name = names[t_index]
            time = time_axis(data[:, t_index], None, file=path, channel=t_name)
            source["time"] = f"file:column {t_name!r} (taken as s)"
    else:
        if time_channel is not None:
            raise no_time_channel(path, "a 1-D wave has one channel; its time axis is the x scaling")
        index = 0
        values = as_samples(data, file=path, channel=names[0])
        source = {"values": "file:wave data"}

    units = info["data_units"] or None
    if units:
        source["units"] = "file:wave data units"
    step, x_units = info["x_step"], info["x_units"]
    stated = None
    x_scaling = f"{step:g} {x_units}" if x_units else f"{step:g}, no units, taken as s"
    if x_units in TIME_UNITS and step > 0:
        stated = 1.0 / (step * TIME_UNITS[x_units]), f"file:x scaling ({x_scaling})"
    elif not x_units and step > 0 and step != _IGOR_DEFAULT_STEP:
        stated = 1.0 / step, f"file:x scaling ({x_scaling})"
    stated = _settle_with_note(stated, x_scaling, info, path)
    sample_rate = settle_rate(stated, time, t_name, source)
    return RawTrace(values, time, sample_rate, units, names[index], names, info, source)


READER = Reader(
    name="ibw",
    title="Igor Pro binary wave (.ibw)",
    suffixes=(".ibw",),
    read=read,
    list_channels=list_channels,
    extra="formats",
    references=(
        "WaveMetrics, Technical Note 003: Igor Binary Format, https://www.wavemetrics.com",
        "igor2 (maintained fork of igor), https://github.com/AFM-analysis/igor2",
    ),
)
