"""Bruker NanoScope high-speed data captures (``.hsdc``): a text header, then one binary block per channel.

The header is Latin-1 text, one ``\\Key: value`` per line, in sections opened by
``\\*Section name`` and closed by ``\\*File list end``. Parameter lines
``\\@[group:]Name: TYPE [soft scale] (hard scale) value unit`` hold the
controller's settings (group 2 is the main scan, 3 the interleave). Each channel
is a ``\\*Ciao HSDC list`` section: ``Data offset`` and ``Data length`` (bytes)
locate its block, ``Bytes/pixel`` its integers (little-endian; afmid reads the
2-byte layout of Bruker's example file), ``High Speed Data Type`` names it
('Vertical Deflection', 'Lateral Deflection') and ``High Speed Data Hard Scale``
(e.g. '-4 V') is the voltage of 2^16 counts: volts = counts x hard scale / 65536.

- Channel: by its type ('Vertical Deflection', case-insensitive) or its letter
  ('A'); the vertical deflection by default. Values in V.
- Sample rate: the capture's ``Hsdc Rate`` and the channel's ``High Speed Data
  Channel Rate`` (and the rate ``Number of samples`` implies over the block's
  values). Where these disagree, the rate that puts the oscillation at the
  declared drive frequency is used and said in one warning; none fitting leaves
  the rate unset with the reason (``metadata['sample_rate_problem']``).
- What the header states for the config (``metadata['stated']``, SI; where each is in
  ``metadata['stated_where']``): the drive
  frequency (``CantFrequency``), a calibrated deflection sensitivity (``Sens.
  DeflSens`` in nm/V, not the uncalibrated 1.0) as ``data.invols``, a ``Spring
  Constant``; the set-point, scan and instrument in ``metadata['acquisition']``.

No calibration is guessed: a sensitivity of 1.0 means volts stay volts.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from afmid.errors import InputError
from afmid.io.readers.base import (
    COLUMN_KEY,
    RawTrace,
    Reader,
    as_samples,
    check_array_size,
    listing,
    no_time_channel,
    not_readable,
    quoted,
    resolve_channel,
)

log = logging.getLogger(__name__)

_KIND = "NanoScope HSDC"
_HEADER_START = b"\\*"
_HEADER_END = b"\\*File list end"
#: NanoScope headers are tens of kB (Bruker's example: 24 kB); the end marker is looked for this far at most.
MAX_HEADER_BYTES = 1 << 20
_CHANNEL_SECTION = "ciao hsdc list"
_CAPTURE_SECTION = "hsdc list"
_COUNTS_PER_HARD_SCALE = 65536  # the hard scale is the voltage of the 16-bit range
_DTYPES = {2: np.dtype("<i2")}  # bytes per sample -> stored integers (the layout of the public example)
#: A stated rate "fits" when it puts the measured oscillation within this of the declared drive (the fit's own
#: drive search spans +-5 % of drive.frequency).
RATE_TOLERANCE = 0.05
#: The oscillation is measured on at most this many samples (a bounded FFT, ample for a 5 % decision).
_RATE_SAMPLES = 1 << 20
_VERTICAL = "vertical deflection"

_LINE = re.compile(r"^\\(?P<key>[^\r\n]*?):(?:[ \t]+|$)(?P<value>.*)$")
_NUMBER_UNIT = re.compile(r"^\s*(?P<number>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(?P<unit>\S*)\s*$")
_PARAMETER = re.compile(
    r"^(?P<type>[A-Z])\s*(?:\[(?P<soft>[^\]]*)\])?\s*(?:\((?P<hard>[^)]*)\))?\s*(?P<rest>.*?)\s*$")
_FREQUENCY_UNITS = {"": 1.0, "hz": 1.0, "khz": 1e3, "mhz": 1e6, "ghz": 1e9}
_LENGTH_UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "~m": 1e-6, "µm": 1e-6, "nm": 1e-9, "pm": 1e-12}
_VOLT_UNITS = {"v": 1.0, "mv": 1e-3}


@dataclass(frozen=True)
class _Channel:
    """One ``\\*Ciao HSDC list`` section: where its block is and what it holds."""

    name: str
    letter: str
    fields: dict[str, str]  # the section's lines, keys lower-case


@dataclass(frozen=True)
class _Header:
    sections: list[tuple[str, dict[str, str]]]  # (name, {lower-case key: value}) in file order
    end: int  # byte offset just past the end marker
    file_size: int

    def first(self, *keys: str, section: str | None = None) -> tuple[str, str] | None:
        """(key as asked, value) of the first of ``keys`` found (in a section named ``section``, if given)."""
        for key in keys:
            for name, fields in self.sections:
                if (section is None or name.lower() == section) and key.lower() in fields:
                    return key, fields[key.lower()]
        return None

    def channels(self) -> list[_Channel]:
        found = [fields for name, fields in self.sections if name.lower() == _CHANNEL_SECTION]
        channels = []
        for i, fields in enumerate(found):
            letter = fields.get("high speed data channel", "").strip() or chr(ord("A") + i)
            name = fields.get("high speed data type", "").strip() or f"Channel {letter}"
            channels.append(_Channel(name, letter, fields))
        names = [c.name for c in channels]
        # Two blocks of one type (vertical deflection twice) are told apart by their letters.
        return [c if names.count(c.name) == 1 else _Channel(f"{c.name} {c.letter}", c.letter, c.fields)
                for c in channels]


# --------------------------------------------------------------------------- header
def _read_header(path: Path) -> _Header:
    """The header's sections; a file without a NanoScope header or its end marker is not readable."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(MAX_HEADER_BYTES)
    if not head.startswith(_HEADER_START):
        raise not_readable(_KIND, path, ValueError("no NanoScope header: the file does not start with '\\*File list'"))
    end = head.find(_HEADER_END)
    if end < 0:
        raise not_readable(_KIND, path, ValueError(
            f"the header has no end marker '\\*File list end' in its first {len(head)} bytes"))
    sections: list[tuple[str, dict[str, str]]] = []
    for line in head[:end].decode("latin-1").splitlines():
        line = line.strip()
        if line.startswith("\\*"):
            sections.append((line[2:].strip(), {}))
            continue
        match = _LINE.match(line)
        if match and sections:
            sections[-1][1].setdefault(" ".join(match["key"].split()).lower(), match["value"].strip())
    return _Header(sections, end + len(_HEADER_END), size)


def _quantity(text: str) -> tuple[float, str] | None:
    """('50 MHz') -> (50.0, 'MHz'); None if ``text`` is not a finite number with an optional unit."""
    match = _NUMBER_UNIT.match(text or "")
    if not match:
        return None
    number = float(match["number"])
    return (number, match["unit"]) if math.isfinite(number) else None


def _scaled(text: str, units: dict[str, float]) -> float | None:
    """``text`` as a number in SI by ``units`` (lower-case unit -> factor), else None."""
    parsed = _quantity(text)
    if parsed is None or parsed[1].lower() not in units:
        return None
    return parsed[0] * units[parsed[1].lower()]


def _parameter(text: str) -> tuple[str, str]:
    """A ``\\@`` line's value: ('V', '56.85609 kHz') for 'V (0.0000116415 kHz/LSB) 56.85609 kHz'; ('S', 'Tapping')
    for 'S [TMMode] "Tapping"'."""
    match = _PARAMETER.match(text or "")
    if not match:
        return "", text or ""
    rest = match["rest"]
    if match["type"] == "S" and len(rest) >= 2 and rest[0] == rest[-1] == '"':
        rest = rest[1:-1]
    return match["type"], rest


def _integer(channel: _Channel, key: str, path: Path) -> int:
    text = channel.fields.get(key.lower())
    value = _quantity(text) if text is not None else None
    if value is None or value[1] or value[0] != int(value[0]) or value[0] < 0:
        stated = "is missing" if text is None else f"= {quoted(text)} is not a byte count"
        raise not_readable(_KIND, path, ValueError(f"channel {quoted(channel.name)}: '\\{key}' {stated}"))
    return int(value[0])


# --------------------------------------------------------------------------- channels and samples
def _choose(channels: list[_Channel], wanted: str | int | None, path: Path) -> _Channel:
    names = [c.name for c in channels]
    if not channels:
        raise not_readable(_KIND, path, ValueError("the header describes no channel ('\\*Ciao HSDC list')"))
    if wanted is None:
        vertical = [c for c in channels if c.name.lower().startswith(_VERTICAL)]
        if len(vertical) == 1 or len(channels) == 1:
            return (vertical or channels)[0]
        raise InputError(f"the file holds {len(channels)} channels and no single vertical deflection; choose one: "
                         f"{listing(names)}", file=path, key=COLUMN_KEY)
    letters = [c for c in channels if isinstance(wanted, str) and c.letter.lower() == wanted.strip().lower()]
    if len(letters) == 1:
        return letters[0]
    return channels[resolve_channel(names, wanted, file=path)]


def _samples(header: _Header, channel: _Channel, path: Path) -> np.ndarray:
    """The channel's stored integers, after checking that its block lies inside the file and fits in memory."""
    offset = _integer(channel, "Data offset", path)
    length = _integer(channel, "Data length", path)
    width = _integer(channel, "Bytes/pixel", path)
    if width not in _DTYPES:
        raise InputError(f"channel {quoted(channel.name)} has {width} bytes per sample; afmid reads the 2-byte "
                         "(int16) high-speed captures only", file=path, key=COLUMN_KEY)
    if length % width:
        raise not_readable(_KIND, path, ValueError(
            f"channel {quoted(channel.name)}: 'Data length' {length} is not a multiple of 'Bytes/pixel' {width}"))
    if offset < header.end:
        raise not_readable(_KIND, path, ValueError(
            f"channel {quoted(channel.name)}: 'Data offset' {offset} lies inside the header ({header.end} bytes)"))
    if offset + length > header.file_size:
        raise not_readable(_KIND, path, ValueError(
            f"channel {quoted(channel.name)} ends at byte {offset + length} but the file has {header.file_size} "
            "bytes"))
    count = length // width
    check_array_size((count,), _DTYPES[width], file=path, channel=channel.name)
    return np.fromfile(path, dtype=_DTYPES[width], count=count, offset=offset)


def _volts_per_count(channel: _Channel) -> float | None:
    """V per count from the channel's hard scale ('-4 V' is the voltage of 65536 counts), None if not stated."""
    volts = _scaled(channel.fields.get("high speed data hard scale", ""), _VOLT_UNITS)
    return None if volts is None or volts == 0 else volts / _COUNTS_PER_HARD_SCALE


# --------------------------------------------------------------------------- the sample rate
def _hz(value: float) -> str:
    for scale, unit in ((1e9, "GHz"), (1e6, "MHz"), (1e3, "kHz")):
        if abs(value) >= scale:
            return f"{value / scale:.5g} {unit}"
    return f"{value:.5g} Hz"


def _stated_rates(header: _Header, channel: _Channel, count: int) -> list[tuple[float, str]]:
    """(Hz, where) of every rate the header states for this channel, equal ones merged."""
    found: list[tuple[float, str]] = []
    capture = header.first("Hsdc Rate", section=_CAPTURE_SECTION)
    if capture and (rate := _scaled(capture[1], _FREQUENCY_UNITS)):
        found.append((rate, "'Hsdc Rate'"))
    channel_rate = _scaled(channel.fields.get("high speed data channel rate", ""), _FREQUENCY_UNITS)
    if channel_rate:
        found.append((channel_rate, "'High Speed Data Channel Rate'"))
        stated_count = _quantity(channel.fields.get("number of samples", ""))
        if stated_count and stated_count[0] > 0 and stated_count[0] != count:
            # The capture's duration as 'Number of samples' at the channel rate, over the values the block holds.
            found.append((channel_rate * count / stated_count[0],
                          f"the block's {count} values in the time of 'Number of samples' {stated_count[0]:g} at "
                          "'High Speed Data Channel Rate'"))
    merged: list[tuple[float, str]] = []
    for rate, where in found:
        if rate <= 0:
            continue
        same = next((i for i, (r, _) in enumerate(merged) if math.isclose(r, rate, rel_tol=1e-9)), None)
        if same is None:
            merged.append((rate, where))
        else:
            merged[same] = (merged[same][0], f"{merged[same][1]}, also {where}")
    return merged


def _drive_frequency(header: _Header) -> tuple[float, str] | None:
    """(Hz, where) of the declared drive frequency: the main scan's CantFrequency, else a plain one."""
    for key in ("@2:CantFrequency", "@CantFrequency"):
        found = header.first(key)
        if found and (hz := _scaled(_parameter(found[1])[1], _FREQUENCY_UNITS)) and hz > 0:
            return hz, f"\\{key} ({_parameter(found[1])[1]})"
    found = header.first("Drive frequency")
    if found and (hz := _scaled(found[1], _FREQUENCY_UNITS)) and hz > 0:
        return hz, f"\\Drive frequency ({found[1]})"
    return None


def dominant_cycles_per_sample(values: np.ndarray) -> float:
    """Frequency of the strongest spectral line of ``values`` (mean removed, Hann window), in cycles per sample,
    refined between bins by a parabola through the log powers; on at most the first 2^20 samples."""
    x = np.asarray(values[:_RATE_SAMPLES], dtype=np.float64)
    x = (x - x.mean()) * np.hanning(x.size)
    power = np.abs(np.fft.rfft(x)) ** 2
    if power.size < 4:
        return math.nan
    peak = int(np.argmax(power[1:-1])) + 1
    a, b, c = np.log(power[peak - 1:peak + 2] + 1e-300)
    shift = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) < 0 else 0.0
    return (peak + shift) / x.size


def _resolve_rate(rates: list[tuple[float, str]], header: _Header, oscillation: np.ndarray,
                  path: Path) -> tuple[float | None, str | None, str | None]:
    """(rate Hz, source, problem): the one stated rate, or the one of several that puts the measured oscillation at
    the declared drive (said in one warning); a problem (why none) when they disagree and none fits."""
    if not rates:
        return None, None, None
    if len(rates) == 1:
        return rates[0][0], f"file:{rates[0][1]}", None
    stated = " and ".join(f"{_hz(rate)} ({where})" for rate, where in rates)
    drive = _drive_frequency(header)
    if drive is None:
        return None, None, (f"the header gives {stated} and no drive frequency (CantFrequency) to tell which is "
                            "right; set data.sample_rate (Hz)")
    cycles = dominant_cycles_per_sample(oscillation)
    implied = [(rate, where, cycles * rate) for rate, where in rates]
    fitting = sorted((abs(f / drive[0] - 1.0), rate, where, f) for rate, where, f in implied
                     if abs(f / drive[0] - 1.0) <= RATE_TOLERANCE)
    if not fitting:
        at = ", ".join(f"{_hz(f)} at {_hz(rate)}" for rate, _, f in implied)
        return None, None, (f"the header gives {stated}; none puts the oscillation ({1 / cycles:.4g} samples per "
                            f"period) within {RATE_TOLERANCE:.0%} of the declared drive {_hz(drive[0])} ({at}); "
                            "set data.sample_rate (Hz)")
    _, rate, where, at = fitting[0]
    others = ", ".join(f"{_hz(r)} would put it at {_hz(f)}" for r, _, f in implied if r != rate)
    log.warning("%s: the header gives %s; %s puts the oscillation at %s, the declared drive %s (%s; %s): using %s",
                path, stated, _hz(rate), _hz(at), _hz(drive[0]), drive[1], others, _hz(rate))
    rejected = " or ".join(f"{_hz(r)} ({w.split(', also ')[0]})" for r, w, _ in implied if r != rate)
    source = (f"file:{where.split(', also ')[0]} ({_hz(rate)}, not {rejected}: the rate that puts the oscillation "
              f"at the declared drive {_hz(drive[0])})")
    return rate, source, None


# --------------------------------------------------------------------------- what the header states
def _deflection_sensitivity(header: _Header) -> tuple[float, str] | None:
    """(m/V, where) of a calibrated deflection sensitivity; None for NanoScope's uncalibrated 1.0 (no unit)."""
    found = header.first("@Sens. DeflSens", "@Sens. Deflection")
    if not found:
        return None
    value = _parameter(found[1])[1]
    parsed = _quantity(value)
    if parsed is None or parsed[0] <= 0 or parsed[0] == 1.0 or not parsed[1].lower().endswith("/v"):
        return None
    metres = _LENGTH_UNITS.get(parsed[1][:-2].lower())
    return (parsed[0] * metres, f"\\{found[0]} ({value})") if metres else None


def _stated(header: _Header, channel: _Channel) -> tuple[dict[str, float], dict[str, str]]:
    """Config values the header states (SI) and where each is, for afmid.io.trace and init-config."""
    values: dict[str, float] = {}
    where: dict[str, str] = {}
    drive = _drive_frequency(header)
    if drive:
        values["drive.frequency"], where["drive.frequency"] = drive[0], f"file:{drive[1]}"
    spring = header.first("Spring Constant", "Spring constant")
    if spring and (k := _quantity(spring[1])) and k[0] > 0 and k[1] in ("", "N/m"):
        values["cantilever.spring_constant"], where["cantilever.spring_constant"] = k[0], f"file:\\{spring[0]}"
    sensitivity = _deflection_sensitivity(header)
    if sensitivity and channel.name.lower().startswith(_VERTICAL):
        values["data.invols"], where["data.invols"] = sensitivity[0], f"file:{sensitivity[1]}"
    return values, where


def _acquisition(header: _Header) -> dict:
    """The instrument, mode, set-point and scan as the header states them (SI numbers, text as written)."""
    info: dict = {}
    for name, key in (("instrument", "Description"), ("microscope", "Microscope"), ("controller", "Controller"),
                      ("date", "Date"), ("operating_mode", "Operating mode")):
        if (found := header.first(key)) and found[1]:
            info[name] = found[1]
    for name, key in (("mode", "@MicroscopeList"), ("feedback", "@2:SPMFeedbackList")):
        if (found := header.first(key)) and _parameter(found[1])[1]:
            info[name] = _parameter(found[1])[1]
    if (found := header.first("@2:TMSetAmplitude")) and (volts := _scaled(_parameter(found[1])[1], _VOLT_UNITS)):
        info["amplitude_setpoint_V"] = volts
    if (found := header.first("Scan Size")) and (size := _scaled(found[1], _LENGTH_UNITS)) is not None:
        info["scan_size_m"] = size
    if (found := header.first("Scan Rate")) and (rate := _scaled(found[1], _FREQUENCY_UNITS)) is not None:
        info["scan_rate_Hz"] = rate
    for name, key in (("scan_lines", "Lines"), ("samples_per_line", "Samps/line")):
        if (found := header.first(key)) and (n := _quantity(found[1])) and not n[1]:
            info[name] = int(n[0])
    return info


def acquisition_text(info: dict) -> str:
    """One line for ``afmid inspect`` and the run file's value sources (no ';': that separates the sources)."""
    parts = []
    instrument = " ".join(info[k] for k in ("instrument",) if k in info)
    if "microscope" in info:
        instrument += f" ({info['microscope']})"
    if "controller" in info:
        instrument += f", controller {info['controller']}"
    if instrument.strip():
        parts.append(instrument.strip(" ,"))
    if "date" in info:
        parts.append(info["date"])
    mode = " ".join(f"{info[k]}{' feedback' if k == 'feedback' else ''}" for k in ("mode", "feedback") if k in info)
    if mode:
        parts.append(mode.lower() if mode.startswith("Tapping") else mode)
    if "amplitude_setpoint_V" in info:
        parts.append(f"amplitude set-point {info['amplitude_setpoint_V'] * 1e3:.4g} mV")
    if "scan_size_m" in info:
        scan = f"scan {info['scan_size_m'] * 1e9:.4g} nm"
        if "scan_lines" in info:
            scan += f", {info['scan_lines']} lines"
        if "scan_rate_Hz" in info:
            scan += f" at {info['scan_rate_Hz']:.4g} Hz"
        parts.append(scan)
    return ", ".join(part.replace(";", ",") for part in parts)


# --------------------------------------------------------------------------- the reader
def list_channels(path: Path) -> list[str]:
    """The channels' types ('Vertical Deflection', 'Lateral Deflection'), in file order."""
    return [c.name for c in _read_header(path).channels()]


def read(path: Path, channel: str | int | None = None, time_channel: str | int | None = None) -> RawTrace:
    """One channel in volts (hard scale; raw counts without one) with the sample rate, drive and calibration the
    header states."""
    if time_channel is not None:
        raise no_time_channel(path, "a high-speed capture is sampled at its rate; it has no time channel")
    header = _read_header(path)
    channels = header.channels()
    chosen = _choose(channels, channel, path)
    counts = _samples(header, chosen, path)
    values = as_samples(counts, file=path, channel=chosen.name)
    letter = f"channel {chosen.letter} {chosen.name!r}"
    source = {"values": f"file:{letter}, int16 at byte {chosen.fields.get('data offset')}"}
    scale = _volts_per_count(chosen)
    if scale is None:
        units = "raw"
        source["units"] = f"file:{letter} has no 'High Speed Data Hard Scale': counts"
    else:
        values = values * scale
        units = "V"
        source["units"] = (f"file:'High Speed Data Hard Scale' {chosen.fields['high speed data hard scale']} "
                           f"per {_COUNTS_PER_HARD_SCALE} counts")
    # The rate is the capture's: judge it on the vertical deflection, whichever channel is read.
    vertical = [c for c in channels if c.name.lower().startswith(_VERTICAL)]
    oscillation = values if not vertical or vertical[0] is chosen else _samples(header, vertical[0], path)
    rate, rate_source, problem = _resolve_rate(_stated_rates(header, chosen, counts.size), header, oscillation, path)
    if rate_source:
        source["sample_rate"] = rate_source
    stated, where = _stated(header, chosen)
    acquisition = _acquisition(header)
    if acquisition:
        source["acquisition"] = f"file:{acquisition_text(acquisition)}"
    metadata = {
        "stated": stated,
        "stated_where": where,
        "acquisition": acquisition,
        "channel": dict(chosen.fields),
        "header": [[name, dict(fields)] for name, fields in header.sections],
    }
    if problem:
        metadata["sample_rate_problem"] = problem
    return RawTrace(values, None, rate, units, chosen.name, [c.name for c in channels], metadata, source)


READER = Reader(
    name="hsdc",
    title="Bruker NanoScope high-speed data capture (.hsdc)",
    suffixes=(".hsdc",),
    read=read,
    list_channels=list_channels,
    extra=None,
    references=(
        "Bruker, NanoScope Python Toolbox (PyPI 'nanoscope' 1.2.300, Apache-2.0): the example file HSDC.hsdc",
        "Gwyddion, NanoScope module (the header's \\Key: value lines and \\@ parameter lines), "
        "http://gwyddion.net/documentation/user-guide-en/file-formats.html",
    ),
)
