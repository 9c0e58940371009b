"""``afmid inspect FILE`` and ``afmid init-config --from FILE``: what afmid sees in a data file.

:func:`describe` reads a file the way a run would (reader registry, default
channel, time channel, units, sample rate), runs the defect checks of
:mod:`afmid.io.defects` on it without a config, and measures the oscillation
(frequency, amplitude, samples per period, noise floor, harmonics, contact).
:func:`inspect_file` prints that; :func:`prefill_config` writes the values into
the commented run-config template, line by line, leaving everything else as it is.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import afmid.io.defects as defects
from afmid.errors import ConfigError, InputError

_LENGTH_UNITS = {"m": 1.0, "nm": 1e-9, "pm": 1e-12, "um": 1e-6}


@dataclass
class FileSummary:
    """Everything :func:`describe` found in a file."""

    path: Path
    reader: str
    reader_title: str
    size: int  # bytes
    channels: list[str]
    channel: str | None = None  # the signal read (None: the file has several and none is the default)
    channel_problem: str | None = None
    time_channel: str | None = None  # read as the time axis
    time_problem: str | None = None  # a time-named channel that could not be used
    n_samples: int = 0
    units: str | None = None  # of the samples in the file, normalised (m, nm, V, ...)
    units_source: str | None = None
    sample_rate: float | None = None  # Hz
    rate_source: str | None = None
    is_afmid: bool = False
    simulated: str | None = None  # afmid trace files with /truth: the simulator's model
    cantilever: dict = field(default_factory=dict)  # afmid trace files: k, f0, Q, R
    drive_frequency: float | None = None  # afmid trace files, or an instrument file's header: nominal drive, Hz
    stated: dict = field(default_factory=dict)  # config key -> SI value an instrument file states (readers' 'stated')
    stated_where: dict = field(default_factory=dict)  # config key -> where in the file
    acquisition: str | None = None  # an instrument file's instrument, mode, set-point and scan, one line
    rate_problem: str | None = None  # why the file's stated rates could not be settled
    values: np.ndarray | None = None  # metres if the units are a length, else file units
    display_units: str | None = None  # 'm', the file's units, or None when unknown
    analysed: tuple[int, int] | None = None  # (start, length) of the samples analysed
    analysis: defects.Analysis | None = None
    findings: list[defects.Finding] = field(default_factory=list)
    raw_min: float = math.nan
    raw_max: float = math.nan
    raw_mean: float = math.nan

    @property
    def frequency(self) -> float | None:
        """Measured oscillation frequency, Hz (None without a sample rate or an oscillation)."""
        if self.analysis is None or not self.sample_rate:
            return None
        return self.analysis.cycles_per_sample * self.sample_rate


def _time_candidates(channels: list[str], chosen: str | None) -> list[str]:
    from afmid.io.readers.base import TIME_NAMES, column_stem

    return [c for c in channels if c != chosen and column_stem(c) in TIME_NAMES]


def describe(path: str | Path, column: str | None = None, sample_rate: float | None = None) -> FileSummary:
    """Read ``path`` as a run would and measure what is in it (see the module docstring).

    Raises InputError for a missing or unreadable file, or a ``column`` it does not have, and ConfigError for a
    ``sample_rate`` that is not a positive finite number of Hz (``--sample-rate nan`` printed "nan Hz").
    """
    if sample_rate is not None and not (math.isfinite(sample_rate) and sample_rate > 0):
        raise ConfigError(f"{sample_rate:g} is not a sample rate: expected a positive number of Hz",
                          key="--sample-rate")
    from afmid.io.trace import TRACE_FORMAT, normalise_units
    from afmid.io.readers import list_channels, read_trace, reader_for

    path = Path(path)
    channels = list_channels(path)  # checks that the file exists and is readable
    reader = reader_for(path)
    summary = FileSummary(path=path, reader=reader.name, reader_title=reader.title, size=path.stat().st_size,
                          channels=list(channels))
    try:
        raw = read_trace(path, "auto", column, None)
    except InputError as exc:
        if column is not None or exc.key != "data.column" or not channels:
            raise
        summary.channel_problem = exc.message  # several channels, none is the default
        return summary
    summary.channel = raw.channel
    meta = raw.metadata or {}
    summary.is_afmid = meta.get("format") == TRACE_FORMAT
    candidates = [] if summary.is_afmid else _time_candidates(list(raw.channels), raw.channel)
    if len(candidates) == 1:
        try:
            raw = read_trace(path, "auto", raw.channel, candidates[0])
            summary.time_channel = candidates[0]
        except InputError as exc:
            summary.time_problem = f"{candidates[0]!r} is not usable as time: {exc.message}"

    values = np.asarray(raw.values, dtype=np.float64)
    summary.n_samples = values.size
    finite = values[np.isfinite(values)]
    if finite.size:
        summary.raw_min, summary.raw_max, summary.raw_mean = float(finite.min()), float(finite.max()), float(finite.mean())
    summary.units = normalise_units(raw.units)
    summary.units_source = raw.source.get("units")
    summary.sample_rate, summary.rate_source = raw.sample_rate, raw.source.get("sample_rate")
    summary.rate_problem = meta.get("sample_rate_problem")
    if sample_rate is not None:
        summary.sample_rate, summary.rate_source = float(sample_rate), "command line: --sample-rate"
    if summary.is_afmid:
        cl = meta.get("cantilever", {})
        summary.cantilever = {k: cl[k] for k in ("spring_constant", "resonance_frequency", "quality_factor",
                                                  "tip_radius") if isinstance(cl.get(k), (int, float))
                              and math.isfinite(cl[k])}
        summary.drive_frequency = meta.get("drive", {}).get("frequency")
        if meta.get("truth_datasets"):
            from afmid.io.trace import read_truth

            truth = read_truth(path)  # InputError naming the file if /truth is damaged
            summary.simulated = truth.model if truth is not None and truth.model else "?"
    else:
        summary.stated, summary.stated_where = dict(meta.get("stated") or {}), dict(meta.get("stated_where") or {})
        summary.drive_frequency = summary.stated.get("drive.frequency")
        if "cantilever.spring_constant" in summary.stated:
            summary.cantilever = {"spring_constant": summary.stated["cantilever.spring_constant"]}
        summary.acquisition = raw.source.get("acquisition", "").removeprefix("file:") or None

    if summary.units in _LENGTH_UNITS:
        summary.values, summary.display_units = values * _LENGTH_UNITS[summary.units], "m"
    elif summary.units == "V" and "data.invols" in summary.stated:  # the file's calibrated sensitivity
        summary.values, summary.display_units = values * summary.stated["data.invols"], "m"
    else:
        summary.values, summary.display_units = values, summary.units

    # Defects: NaN runs (then analyse the longest clean stretch), the time axis, the signal.
    rate = summary.sample_rate
    summary.findings += defects.check_values(values)
    x = summary.values
    if summary.findings:
        start, length = defects.longest_clean(~np.isfinite(values))
        x = x[start:start + length]
        summary.analysed = (start, length)
    if raw.time is not None:
        summary.findings += defects.check_time(np.asarray(raw.time, dtype=np.float64))
    settings = defects.Settings(
        units=summary.display_units,
        sample_rate=rate,
        nominal_frequency=summary.drive_frequency,
        resonance_frequency=summary.cantilever.get("resonance_frequency"),
        quality_factor=summary.cantilever.get("quality_factor"),
        spring_constant=summary.cantilever.get("spring_constant"),
    )
    if x.size:
        summary.analysis = defects.analyse_with(x, settings)
        summary.findings += defects.check_signal(x, settings, summary.analysis)
    return summary


# --------------------------------------------------------------------------- inspect
def _quantity(value: float, units: str | None) -> str:
    return defects.length(value, units)


def _force(value: float) -> str:
    for scale, name in ((1e-12, "pN"), (1e-9, "nN"), (1e-6, "uN")):
        if abs(value) < 1000 * scale:
            return f"{value / scale:.3g} {name}"
    return f"{value:.3g} N"


def _size(n: int) -> str:
    for unit, scale in (("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n} B"


def _listing(names: list[str], limit: int = 12) -> str:
    shown = ", ".join(names[:limit]) or "(none)"
    return shown + (f", ... ({len(names) - limit} more)" if len(names) > limit else "")


def inspect_file(file: str | Path, column: str | None = None, sample_rate: float | None = None) -> str:
    """What afmid sees in ``file``, as text for ``afmid inspect``."""
    s = describe(file, column, sample_rate)
    rows: list[tuple[str, str]] = [
        ("file", str(s.path)),
        ("format", f"{s.reader} ({s.reader_title}), {_size(s.size)}"),
        ("channels", f"{len(s.channels)}: {_listing(s.channels)}"),
    ]
    if s.channel is None:
        rows.append(("reading", f"nothing: {s.channel_problem}; pass --column"))
        return _table(rows)
    reading = f"{s.channel!r}"
    if s.time_channel:
        reading += f", time from {s.time_channel!r}"
    elif s.time_problem:
        reading += f" (time channel {s.time_problem})"
    rows.append(("reading", reading))
    rows.append(("samples", f"{s.n_samples}"))
    if s.sample_rate:
        rows.append(("sample rate", f"{defects.frequency(s.sample_rate)} ({s.rate_source or 'file'}); "
                                    f"duration {s.n_samples / s.sample_rate:.4g} s"))
    elif s.rate_problem:
        rows.append(("sample rate", f"unknown: {s.rate_problem}"))
    else:
        rows.append(("sample rate", "unknown: the file does not say; pass --sample-rate or set data.sample_rate"))
    units = s.units or "unknown"
    if s.units is None:
        units += ": the file does not say; set data.units (m, nm, pm, um, V, raw)"
    else:
        units += f" ({s.units_source or 'file'})"
        if s.units == "V" and "data.invols" in s.stated:
            units += (f"; the file's deflection sensitivity {s.stated['data.invols'] * 1e9:.5g} nm/V converts to "
                      "metres")
        elif s.units == "V":
            units += "; set data.invols (m/V) to convert to metres"
        elif s.units not in _LENGTH_UNITS:
            units += "; not a length: set data.units (raw needs data.scale)"
    rows.append(("units", units))
    rows.append(("values", f"{s.raw_min:.6g} to {s.raw_max:.6g}, mean {s.raw_mean:.6g} (file units)"))
    if s.analysed:
        start, length = s.analysed
        rows.append(("analysed", f"samples {start}-{start + length - 1} (the longest stretch without NaN/inf; "
                                 f"the signal checks below count samples from {start})"))
    a = s.analysis
    if a is None:
        rows.append(("oscillation", "none found (see below)"))
    else:
        freq = f"{defects.frequency(s.frequency)}, " if s.frequency else ""
        nominal = ""
        if s.drive_frequency:
            nominal = f"; nominal drive {defects.frequency(s.drive_frequency)} (file)"
            if "drive.frequency" in s.stated_where:
                nominal = nominal[:-1] + f": {s.stated_where['drive.frequency'].removeprefix('file:')})"
        rows.append(("oscillation", f"{freq}{a.spp:.2f} samples per period, {a.periods:.1f} periods{nominal}"))
        rows.append(("amplitude", f"{_quantity(a.amplitude, s.display_units)} (first harmonic, mean over periods)"))
        noise = f"{_quantity(a.noise_rms, s.display_units)} rms"
        if s.sample_rate and s.display_units == "m":
            noise += f" ({a.noise_rms / math.sqrt(s.sample_rate / 2) * 1e15:.3g} fm/sqrt(Hz))"
        if a.amplitude > 0:
            noise += f", {a.noise_rms / a.amplitude:.2g} of the amplitude"
        if a.motion is not None and a.motion.non_periodic:
            noise += "; inflated by the non-periodic motion (see motion), not only detector noise"
        rows.append(("noise floor", f"{noise} (residual of per-period fits with {a.K} harmonics)"))
        if a.motion is not None:
            plain = not (a.motion.non_periodic or a.motion.modulation or a.motion.incoherent)
            rows.append(("motion", "periodic (consecutive periods agree to the noise)" if plain else
                         a.motion.words(s.frequency)))
        rows.append(("harmonics", _harmonics(a)))
        rows.append(("interaction", _interaction(a, s)))
        rows.append(("instrument", _instrument(a, s)))
    if s.acquisition:
        rows.append(("acquisition", s.acquisition))
    if s.stated or s.acquisition:
        rows.append(("calibration", _stated_calibration(s)))
    if s.is_afmid:
        cl = s.cantilever
        parts = [f"{name} = {value}" for name, value in (
            ("k", f"{cl['spring_constant']:g} N/m" if "spring_constant" in cl else None),
            ("f0", defects.frequency(cl["resonance_frequency"]) if "resonance_frequency" in cl else None),
            ("Q", f"{cl['quality_factor']:g}" if "quality_factor" in cl else None),
            ("R", defects.length(cl["tip_radius"]) if "tip_radius" in cl else None)) if value]
        rows.append(("afmid trace", ", ".join(parts) or "no cantilever metadata"))
        if s.simulated:
            rows.append(("simulated", f"yes: ground truth in /truth (model {s.simulated}); not a measurement"))
    text = _table(rows)
    text += "defects:" + (" none found\n" if not s.findings else "\n")
    for finding in s.findings:
        text += f"  {finding.line()}\n"
    text += "config (afmid init-config --from FILE writes these):\n"
    for key, value, comment in _data_values(s, None):
        required = "  # REQUIRED" if value is None and comment and "REQUIRED" in comment else ""
        text += f"  data.{key}: {_yaml_value(value)}{required}\n"
    return text


def _stated_calibration(s: FileSummary) -> str:
    """What an instrument file states of the calibration, and what the config must still give."""
    parts = []
    if "cantilever.spring_constant" in s.stated:
        parts.append(f"k = {s.stated['cantilever.spring_constant']:g} N/m "
                     f"({s.stated_where.get('cantilever.spring_constant', 'file').removeprefix('file:')})")
    if "data.invols" in s.stated:
        parts.append(f"deflection sensitivity {s.stated['data.invols'] * 1e9:.5g} nm/V "
                     f"({s.stated_where.get('data.invols', 'file').removeprefix('file:')})")
    missing = [key for key, present in (("data.invols", "data.invols" in s.stated or s.units != "V"),
                                        ("cantilever.spring_constant", "cantilever.spring_constant" in s.stated))
               if not present]
    missing += ["cantilever.resonance_frequency", "cantilever.quality_factor", "cantilever.tip_radius"]
    return ", ".join(parts + [f"not in the file: {', '.join(missing)} (set them in the config)"])


def _table(rows: list[tuple[str, str]]) -> str:
    width = max(len(k) for k, _ in rows) + 2
    return "".join(f"{(k + ':').ljust(width)} {v}\n" for k, v in rows)


def _harmonics(a: defects.Analysis) -> str:
    if not a.above_noise:
        return f"none of 2..{a.K} above the noise"
    listed = a.above_noise
    text = ", ".join(str(n) for n in listed[:12]) + (", ..." if len(listed) > 12 else "")
    return f"{len(listed)} of 2..{a.K} above the noise (n = {text})"


def _instrument(a: defects.Analysis, s: FileSummary) -> str:
    """A higher eigenmode seen as a resonance bump in the harmonics (afmid.preprocess.instrument)."""
    from afmid.preprocess.instrument import harmonic_resonance

    at = harmonic_resonance(a.harmonic_amplitudes(), a.above_noise)
    if at is None:
        return ("no resonance among the harmonics (a detector low-pass shows only against a force model: "
                "the diagnosis of afmid report)")
    where = f" = {defects.frequency(at * s.frequency)}" if s.frequency else ""
    return (f"a resonance near harmonic {at:.1f}{where}: a higher eigenmode of the lever? If the lever has one "
            "there, declare cantilever.higher_modes")


def _interaction(a: defects.Analysis, s: FileSummary) -> str:
    if a.contact == "none":
        return "no tip-sample force detected (free oscillation)"
    k = s.cantilever.get("spring_constant")
    size = (f"force range {_force(a.force_range * k)}"
            if k and s.display_units == "m" else f"force range / k {_quantity(a.force_range, s.display_units)}")
    side = "at the most negative deflection (sign flipped?)" if a.flipped else "at the closest approach"
    if a.contact == "contact":
        return f"contact: the force turns repulsive {side}; {size} (model-free, from the harmonics)"
    return f"attractive only: the tip never touches the sample; {size} (model-free, from the harmonics)"


# --------------------------------------------------------------------------- init-config --from
def _yaml_value(value) -> str:
    import yaml

    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return defects.yaml_number(value)
    if isinstance(value, int):
        return str(value)
    return yaml.safe_dump([str(value)], default_flow_style=True, width=10_000).strip()[1:-1]


def _data_values(s: FileSummary, config_dir: Path | None) -> list[tuple[str, object, str | None]]:
    """(key, value, comment) for the data section; comment None keeps the template's."""
    if config_dir is None:
        shown = str(s.path)
    else:
        shown = os.path.relpath(s.path.resolve(), Path(config_dir).resolve())
    column: object = s.channel
    column_note = None
    if s.channel_problem:  # no default channel: prefill_config read the first one
        column_note = f"# CHECK: the file has several channels: {_listing(s.channels, 6)}"
    elif s.channels == ["0"]:
        column, column_note = None, "# the file holds one channel"
    rate_note = None
    if s.sample_rate:
        rate_note = f"# Hz, {s.rate_source}" if s.rate_source else "# Hz"
    else:
        rate_note = "# REQUIRED: Hz; the file does not say"
    units = s.units if s.units in ("m", "nm", "pm", "um", "V", "raw") else None
    if units is None:
        units_note = "# REQUIRED: m | nm | pm | um | V (needs invols) | raw (needs scale); the file does not say"
    else:
        units_note = f"# {s.units_source}" if s.units_source else None
    values = [
        ("path", shown, "# pre-filled from this file by afmid init-config --from"),
        ("format", s.reader, f"# {s.reader}: from the suffix {s.path.suffix!r} (auto would find it too)"),
        ("column", column, column_note),
        ("time_column", s.time_channel, "# time axis from the file" if s.time_channel else
         "# no time axis used: the sample rate gives the times"),
        ("sample_rate", float(s.sample_rate) if s.sample_rate else None, rate_note),
        ("units", units, units_note),
    ]
    if units == "V" and "data.invols" in s.stated:
        values.append(("invols", float(s.stated["data.invols"]),
                       f"# m/V, {s.stated_where.get('data.invols', 'file')}"))
    elif units == "V":
        values.append(("invols", None, "# REQUIRED for units V: m/V, inverse optical lever sensitivity"))
    elif units == "raw":
        values.append(("scale", None, "# REQUIRED for units raw: metres per count"))
    if s.analysis is not None and s.analysis.flipped:
        values.append(("positive", "away_from_sample", "# the interaction is at the negative peaks: CHECK"))
    return values


_COMMENT_COLUMN = 31  # where the template's comments start
_KEY = re.compile(r"^(?P<indent>\s+)(?P<hash>#\s*)?(?P<key>[A-Za-z_]\w*):(?P<rest>.*)$")
_SECTION = re.compile(r"^(?P<name>[A-Za-z_]\w*):")


def _section_bounds(lines: list[str], section: str) -> tuple[int, int] | None:
    start = next((i for i, line in enumerate(lines) if (m := _SECTION.match(line)) and m["name"] == section), None)
    if start is None:
        return None
    end = next((j for j in range(start + 1, len(lines)) if _SECTION.match(lines[j])), len(lines))
    return start, end


def _set(lines: list[str], section: str, key: str, value, comment: str | None = None) -> None:
    """Set ``section.key`` in template lines, keeping the line's comment column (and comment, unless given).

    A commented-out key (``# invols: ...``) is uncommented; a missing key is
    added at the end of its section; a missing section at the end of the file.
    """
    text = _yaml_value(value)
    bounds = _section_bounds(lines, section)
    if bounds is None:
        lines += ["", f"{section}:", f"  {key}: {text}" + (f"  {comment}" if comment else "")]
        return
    start, end = bounds
    if lines[start].split("#", 1)[0].rstrip().endswith("{}"):  # 'fit: {}': an inline empty section
        head, _, tail = lines[start].partition("#")
        lines[start] = f"{section}:" + (" " * max(1, len(head) - len(section) - 1) + "#" + tail if tail else "")
    last = start
    for i in range(start + 1, end):
        m = _KEY.match(lines[i])
        if not m:
            continue
        if not m["hash"]:
            last = i
        if m["key"] != key:
            continue
        original = m["rest"]
        hash_at = original.find("#")
        old_comment = original[hash_at:] if hash_at >= 0 else None
        column = m.start("rest") + hash_at if hash_at >= 0 else _COMMENT_COLUMN
        new = f"{m['indent']}{key}: {text}"
        note = comment if comment is not None else old_comment
        if note:
            new = new.ljust(max(column, len(new) + 1)) + note
        lines[i] = new
        return
    lines.insert(last + 1, f"  {key}: {text}" + (f"  {comment}" if comment else ""))


def prefill_config(path: str | Path, template_text: str, config_dir: str | Path | None = None) -> str:
    """The run-config template with the data section (and, for afmid trace files, the cantilever
    and drive) filled in from ``path``; comments list the defects found.

    ``config_dir`` is where the config will be written: data.path is made
    relative to it (default: the path as given, i.e. relative to the current folder).
    """
    s = describe(path)
    if s.channel is None:  # several channels and none is the default: describe the first signal
        pool = [c for c in s.channels if c not in _time_candidates(s.channels, None)] or s.channels
        problem = s.channel_problem
        s = describe(path, column=pool[0])
        s.channel_problem = problem
    lines = template_text.splitlines()
    for key, value, comment in _data_values(s, None if config_dir is None else Path(config_dir)):
        _set(lines, "data", key, value, comment)
    if s.is_afmid:
        note = "# from the trace file"
        for key in ("spring_constant", "resonance_frequency", "quality_factor", "tip_radius"):
            if key in s.cantilever:
                _set(lines, "cantilever", key, float(s.cantilever[key]), note)
        if s.drive_frequency:
            _set(lines, "drive", "frequency", float(s.drive_frequency), "# Hz, from the trace file")
    else:
        if s.drive_frequency:
            _set(lines, "drive", "frequency", float(s.drive_frequency),
                 f"# Hz, {s.stated_where.get('drive.frequency', 'file')}")
        elif s.frequency:
            _set(lines, "drive", "frequency", float(f"{s.frequency:.7g}"),
                 "# Hz, measured from the data by afmid inspect")
        if "cantilever.spring_constant" in s.stated:
            _set(lines, "cantilever", "spring_constant", float(s.stated["cantilever.spring_constant"]),
                 f"# N/m, {s.stated_where.get('cantilever.spring_constant', 'file')}")
        bounds = _section_bounds(lines, "cantilever")
        if bounds:
            read = " (but spring_constant)" if "cantilever.spring_constant" in s.stated else ""
            lines.insert(bounds[0], f"# CHECK the cantilever values{read}: they are the template's examples, not "
                                    f"read from {s.path.name}")
    header = [f"# Pre-filled from {s.path} by `afmid init-config --from` (`afmid inspect` shows the details)."]
    if s.simulated:
        header.append(f"# The file is SIMULATED (ground truth in /truth, model {s.simulated}), not a measurement.")
    for finding in s.findings:
        header.append(f"# afmid inspect: {finding.line()}")
    insert_at = next((i for i, line in enumerate(lines) if line.strip() and not line.startswith("#")), len(lines))
    lines[insert_at:insert_at] = header + [""]
    return "\n".join(lines) + "\n"
