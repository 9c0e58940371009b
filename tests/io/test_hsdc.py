"""Bruker NanoScope high-speed data captures (.hsdc): Bruker's public example file, and files built here from the
format as that file's header describes it (a Latin-1 ``\\Key: value`` header in sections, then int16 blocks).

The example file (../shared/data/bruker-hsdc/HSDC.hsdc beside the repository, see its README.md there) has a
self-contradicting header: 'Hsdc Rate' 50 MHz but 'High Speed Data Channel Rate' 6.25 MHz; only 50 MHz puts the
oscillation at the declared drive (CantFrequency 56.85609 kHz).
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
import yaml

from afmid.config import build_config, template_text
from afmid.errors import ConfigError, InputError
from afmid.io.inspect import inspect_file, prefill_config
from afmid.io.readers import list_channels, read_trace, reader_for
from afmid.io.readers.hsdc import MAX_HEADER_BYTES, RATE_TOLERANCE, dominant_cycles_per_sample
from afmid.io.trace import load_trace
from repo_paths import REPO_ROOT
from tests.io.test_readers import error_of

EXAMPLE = REPO_ROOT / ".." / "shared" / "data" / "bruker-hsdc" / "HSDC.hsdc"
needs_example = pytest.mark.skipif(not EXAMPLE.is_file(), reason=f"Bruker's example file is not at {EXAMPLE}")

VOLTS_PER_COUNT = -4.0 / 65536  # the example's hard scale, -4 V over the 16-bit range: -2^-14 V, exact in binary
DRIVE = 50e3  # Hz, the built files' declared drive
RATE = 2e6  # Hz, their true sample rate: 40 samples per period
N = 8000  # samples: 200 periods


def counts(frequency=DRIVE, rate=RATE, n=N, amplitude=6000, phase=0.3) -> np.ndarray:
    """An int16 oscillation at ``frequency`` sampled at ``rate``."""
    t = np.arange(n) / rate
    return np.round(amplitude * np.cos(2 * np.pi * frequency * t + phase)).astype("<i2")


def write_hsdc(path, channels=None, *, hsdc_rate="2 MHz", channel_rate="2e+006", number_of_samples=None,
               drive_khz=DRIVE / 1e3, sensitivity="1.000000 ", spring_constant=None, hard_scale="-4 V",
               bytes_per_pixel=2, header_size=8192, offsets=None, lengths=None, end_marker=True, tail=b""):
    """A capture written from the format as Bruker's example states it: the header's sections (CRLF lines), the
    end marker, padding to ``header_size``, then each channel's int16 block. ``channels`` maps a type
    ('Vertical Deflection') to its counts; ``offsets`` / ``lengths`` replace the stated block positions (damage)."""
    channels = {"Vertical Deflection": counts(), "Lateral Deflection": counts(amplitude=900, phase=1.0)} \
        if channels is None else channels
    lines = ["\\*File list", "\\Version: 0x07000200", "\\Date: 03:12:16 PM Tue Mar 21 2006",
             f"\\Data length: {header_size}", "\\*Equipment list", "\\Description: Dimension V",
             "\\Microscope: D3100", "\\*Ciao scan list", "\\Operating mode: Image", "\\Scan Size: 2000 nm",
             "\\Samps/line: 256", "\\Lines: 256", "\\Scan Rate: 0.997564",
             '\\@MicroscopeList: S [TMMode] "Tapping"', '\\@2:SPMFeedbackList: S [SPMFb] "Amplitude"',
             f"\\@Sens. DeflSens: V {sensitivity}", "\\@2:TMSetAmplitude: V (0.06103516 mV/LSB) 400.0000 mV"]
    if drive_khz is not None:
        lines += [f"\\@2:CantFrequency: V (0.0000116415 kHz/LSB) {drive_khz:.7g} kHz",
                  "\\@3:CantFrequency: V (0.0000116415 kHz/LSB) 0.5000000 kHz"]
    if spring_constant is not None:
        lines.append(f"\\Spring Constant: {spring_constant}")
    lines += ["\\*HSDC list", "\\Hsdc Z Move: Off"] + ([f"\\Hsdc Rate: {hsdc_rate}"] if hsdc_rate else [])
    offset = header_size
    blocks = []
    for i, (name, data) in enumerate(channels.items()):
        data = np.asarray(data, dtype="<i2")
        length = data.size * bytes_per_pixel if lengths is None else lengths[i]
        lines += ["\\*Ciao HSDC list", f"\\Data offset: {offset if offsets is None else offsets[i]}",
                  f"\\Data length: {length}", f"\\Bytes/pixel: {bytes_per_pixel}",
                  f"\\High Speed Data Channel: {chr(ord('A') + i)}", f"\\High Speed Data Type: {name}"]
        if channel_rate:
            lines.append(f"\\High Speed Data Channel Rate: {channel_rate}")
        if hard_scale:
            lines += [f"\\High Speed Data Hard Scale: {hard_scale}", f"\\High Speed Data Soft Scale: {hard_scale}"]
        lines.append(f"\\Number of samples: {data.size if number_of_samples is None else number_of_samples}")
        blocks.append(data.tobytes() if bytes_per_pixel == 2 else data.astype("<i4").tobytes())
        offset += len(blocks[-1])
    header = ("\r\n".join(lines) + "\r\n" + ("\\*File list end\r\n" if end_marker else "")).encode("latin-1")
    assert len(header) <= header_size or not end_marker
    path.write_bytes(header.ljust(header_size, b"\x00") + b"".join(blocks) + tail)
    return path


def config_for(path, **data):
    """A run config for ``path``: the lever from the config, the rest (rate, drive) left to the file."""
    return build_config({"data": {"path": str(path), **data},
                         "cantilever": {"spring_constant": 2.0, "resonance_frequency": 52e3, "quality_factor": 300.0},
                         "model": {"effects": ["dmt"]}}, source=path.parent / "run.yaml")


def rate_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if "the header gives" in r.getMessage()]


# --------------------------------------------------------------------------- Bruker's example file
@needs_example
def test_example_file_reads_both_channels_in_volts_at_the_rate_that_fits_the_drive(caplog):
    caplog.set_level(logging.WARNING)
    assert reader_for(EXAMPLE).name == "hsdc"
    assert list_channels(EXAMPLE) == ["Vertical Deflection", "Lateral Deflection"]
    trace = read_trace(EXAMPLE)
    assert trace.channel == "Vertical Deflection" and trace.units == "V" and trace.values.size == 524288
    # 50 MHz ('Hsdc Rate', and 'Number of samples' 65536 at 6.25 MHz over 524288 values), not 6.25 MHz.
    assert trace.sample_rate == 50e6
    assert "'Hsdc Rate'" in trace.source["sample_rate"] and "not 6.25 MHz" in trace.source["sample_rate"]
    (line,) = rate_warnings(caplog)
    assert "50 MHz" in line and "6.25 MHz" in line and "56.856 kHz" in line and "using 50 MHz" in line
    assert "\n" not in line
    # Volts are counts x (-2^-14 V): exact, so every value is a whole number of counts of the int16 range.
    counts_read = trace.values / VOLTS_PER_COUNT
    np.testing.assert_array_equal(counts_read, np.round(counts_read))
    assert -32768 <= counts_read.min() and counts_read.max() <= 32767
    assert trace.values.min() == pytest.approx(-0.406494140625, abs=0) and trace.values.max() == 0.4736328125
    assert trace.metadata["stated"] == {"drive.frequency": pytest.approx(56856.09, rel=1e-12)}
    acquisition = trace.metadata["acquisition"]
    assert acquisition["amplitude_setpoint_V"] == pytest.approx(0.4, rel=1e-12)
    assert acquisition["scan_size_m"] == pytest.approx(2e-6, rel=1e-12) and acquisition["scan_lines"] == 256
    assert acquisition["mode"] == "Tapping" and acquisition["instrument"] == "Dimension V"


@needs_example
def test_example_file_first_harmonic_matches_the_amplitude_setpoint():
    """The hard-scale convention (-4 V over 65536 counts) checked against the header: amplitude feedback held the
    first harmonic at the 400 mV set-point. The other conventions one might guess (-4 V over 32768 counts, or
    over 2^16 but twice) would give 0.8 V or 0.2 V: a factor 2, so 10 % tells them apart with room for the
    feedback's error and the frequency's drift over the record."""
    trace = read_trace(EXAMPLE)
    cycles = dominant_cycles_per_sample(trace.values)
    assert cycles * 50e6 == pytest.approx(56856.09, rel=1e-3)  # a bin of the 524288-point FFT is 1.7e-3 of it
    n = np.arange(trace.values.size)
    first = 2 * abs(np.mean((trace.values - trace.values.mean()) * np.exp(-2j * np.pi * cycles * n)))
    assert first == pytest.approx(0.4, rel=0.1)


@needs_example
def test_example_file_lateral_channel_by_name_or_letter():
    lateral = read_trace(EXAMPLE, channel="lateral deflection")
    assert lateral.channel == "Lateral Deflection" and lateral.sample_rate == 50e6
    assert read_trace(EXAMPLE, channel="B").channel == "Lateral Deflection"
    assert not np.array_equal(lateral.values, read_trace(EXAMPLE).values)


@needs_example
def test_example_file_loads_for_a_fit_with_the_drive_from_the_header(tmp_path):
    config = config_for(EXAMPLE, invols=50e-9)
    trace = load_trace(config)
    assert trace.sample_rate == 50e6 and trace.drive_frequency == pytest.approx(56856.09, rel=1e-12)
    assert trace.sources["frequency"] == "file:\\@2:CantFrequency (56.85609 kHz)"
    assert trace.sources["sample_rate"].startswith("file:'Hsdc Rate'")
    assert "amplitude set-point 400 mV" in trace.sources["acquisition"]
    assert np.max(np.abs(trace.deflection)) <= 0.48 * 50e-9  # volts x invols


@needs_example
def test_example_file_inspect_and_init_config(tmp_path):
    text = inspect_file(EXAMPLE)
    assert "hsdc (Bruker NanoScope" in text and "50 MHz" in text and "amplitude set-point 400 mV" in text
    assert "not in the file: data.invols, cantilever.spring_constant" in text
    written = prefill_config(EXAMPLE, template_text(), config_dir=tmp_path)
    data = yaml.safe_load(written)
    assert data["data"]["format"] == "hsdc" and data["data"]["sample_rate"] == 50e6
    assert data["data"]["units"] == "V" and data["data"]["invols"] is None
    assert data["drive"]["frequency"] == pytest.approx(56856.09, rel=1e-12)


# --------------------------------------------------------------------------- files built from the format
def test_consistent_header_is_read_without_a_warning(tmp_path, caplog):
    caplog.set_level(logging.WARNING)
    path = write_hsdc(tmp_path / "c.hsdc")
    trace = read_trace(path)
    assert trace.sample_rate == RATE
    assert trace.source["sample_rate"] == "file:'Hsdc Rate', also 'High Speed Data Channel Rate'"
    np.testing.assert_array_equal(trace.values, counts() * VOLTS_PER_COUNT)
    assert trace.channels == ["Vertical Deflection", "Lateral Deflection"] == list_channels(path)
    assert rate_warnings(caplog) == [] and "sample_rate_problem" not in trace.metadata


@pytest.mark.parametrize("hard_scale, volts_per_count", [("-4 V", -4 / 65536), ("10 V", 10 / 65536),
                                                          ("500 mV", 0.5 / 65536)])
def test_hard_scale_is_the_voltage_of_the_16_bit_range(tmp_path, hard_scale, volts_per_count):
    trace = read_trace(write_hsdc(tmp_path / "s.hsdc", hard_scale=hard_scale))
    np.testing.assert_allclose(trace.values, counts() * volts_per_count, rtol=4 * np.finfo(float).eps)


def test_without_a_hard_scale_the_counts_are_raw(tmp_path):
    trace = read_trace(write_hsdc(tmp_path / "r.hsdc", hard_scale=None))
    assert trace.units == "raw"
    np.testing.assert_array_equal(trace.values, counts())


@pytest.mark.parametrize("hsdc_rate, channel_rate, stated_samples, wrong", [
    ("2 MHz", "2.5e+005", N // 8, "250 kHz"),  # the example's pattern: the capture's rate is right
    ("16 MHz", "2e+006", None, "16 MHz"),  # the other way round: the channel's rate is right
])
def test_contradicting_rates_are_settled_by_the_declared_drive(tmp_path, caplog, hsdc_rate, channel_rate,
                                                               stated_samples, wrong):
    caplog.set_level(logging.WARNING)
    path = write_hsdc(tmp_path / "x.hsdc", hsdc_rate=hsdc_rate, channel_rate=channel_rate,
                      number_of_samples=stated_samples)
    trace = read_trace(path)
    assert trace.sample_rate == RATE
    assert f"not {wrong}" in trace.source["sample_rate"]
    (line,) = rate_warnings(caplog)
    assert str(path) in line and f"{wrong} would put it at" in line and "using 2 MHz" in line


def test_rates_of_which_none_fits_the_drive_ask_for_data_sample_rate(tmp_path):
    # The oscillation at 30 kHz of a declared 50 kHz drive: neither 2 MHz (30 kHz) nor 250 kHz (3.75 kHz) fits.
    path = write_hsdc(tmp_path / "n.hsdc", channels={"Vertical Deflection": counts(frequency=30e3)},
                      channel_rate="2.5e+005")
    trace = read_trace(path)
    assert trace.sample_rate is None
    assert "set data.sample_rate" in trace.metadata["sample_rate_problem"]
    with pytest.raises(InputError) as info:
        load_trace(config_for(path, invols=50e-9))
    assert info.value.key == "data.sample_rate" and info.value.file == str(path)
    assert "none puts the oscillation" in str(info.value) and "\n" not in str(info.value)
    assert "unknown: the header gives" in inspect_file(path)
    # The user's rate settles it (and the declared drive still comes from the header).
    user_rate = RATE * DRIVE / 30e3  # puts the 30 kHz-at-2 MHz oscillation at the 50 kHz drive
    trace = load_trace(config_for(path, invols=50e-9, sample_rate=user_rate))
    assert trace.sample_rate == user_rate and trace.sources["sample_rate"] == "config:data.sample_rate"


@pytest.mark.parametrize("offset, accepted", [(-0.04, True), (0.04, True), (-0.06, False), (0.06, False)])
def test_a_rate_fits_when_it_puts_the_oscillation_inside_the_fits_drive_search_band(tmp_path, offset, accepted):
    """RATE_TOLERANCE is the fit's own drive search band (+-5 % of drive.frequency): a rate is accepted when the
    fit could then find the drive. 1 % of the drive either side of the edge is 2 bins of the 8000-sample FFT
    (250 Hz each), and the interpolated peak of a pure tone is within a small fraction of a bin of it."""
    assert RATE_TOLERANCE == 0.05
    path = write_hsdc(tmp_path / "t.hsdc", channels={"Vertical Deflection": counts(frequency=DRIVE * (1 + offset))},
                      channel_rate="2.5e+005")
    trace = read_trace(path)
    assert (trace.sample_rate == RATE) is accepted
    assert ("sample_rate_problem" in trace.metadata) is not accepted


def test_contradicting_rates_without_a_declared_drive_ask_for_data_sample_rate(tmp_path):
    path = write_hsdc(tmp_path / "d.hsdc", channel_rate="2.5e+005", drive_khz=None)
    trace = read_trace(path)
    assert trace.sample_rate is None and "no drive frequency" in trace.metadata["sample_rate_problem"]


def test_user_sample_rate_that_contradicts_the_file_is_said_and_recorded(tmp_path, caplog):
    caplog.set_level(logging.WARNING)
    path = write_hsdc(tmp_path / "u.hsdc")
    trace = load_trace(config_for(path, invols=50e-9, sample_rate=2.1e6))
    assert trace.sample_rate == 2.1e6 and "data.sample_rate" in trace.overridden
    assert any("overrides the file's 2e+06 Hz" in r.getMessage() for r in caplog.records)


def test_uncalibrated_sensitivity_needs_data_invols(tmp_path):
    path = write_hsdc(tmp_path / "v.hsdc")
    assert "data.invols" not in read_trace(path).metadata["stated"]
    with pytest.raises(ConfigError) as info:
        load_trace(config_for(path))
    assert info.value.key == "data.invols"


def test_calibrated_sensitivity_and_spring_constant_are_used_and_prefilled(tmp_path, caplog):
    # On the 'afmid' logger itself: a CLI run earlier in the same worker may have stopped its propagation.
    caplog.set_level(logging.INFO, logger="afmid")
    logging.getLogger("afmid").addHandler(caplog.handler)
    path = write_hsdc(tmp_path / "k.hsdc", sensitivity="45.30000 nm/V", spring_constant="0.4")
    stated = read_trace(path).metadata["stated"]
    assert stated["data.invols"] == pytest.approx(45.3e-9, rel=1e-12)
    assert stated["cantilever.spring_constant"] == 0.4
    config = build_config({"data": {"path": str(path)},
                           "cantilever": {"resonance_frequency": 52e3, "quality_factor": 300.0},
                           "model": {"effects": ["dmt"]}}, source=tmp_path / "run.yaml")
    trace = load_trace(config)
    np.testing.assert_allclose(trace.deflection, counts() * VOLTS_PER_COUNT * 45.3e-9, rtol=1e-12)
    assert trace.cantilever.spring_constant == 0.4
    assert trace.sources["invols"] == "file:\\@Sens. DeflSens (45.30000 nm/V)"
    assert trace.sources["spring_constant"] == "file:\\Spring Constant"
    assert any("deflection sensitivity 45.3 nm/V from the file" in r.getMessage() for r in caplog.records)
    # The config's own value wins, and the override is recorded.
    config = config_for(path, invols=50e-9)
    trace = load_trace(config)
    assert trace.cantilever.spring_constant == 2.0 and {"data.invols", "cantilever.spring_constant"} <= set(
        trace.overridden)
    written = prefill_config(path, template_text(), config_dir=tmp_path)
    data = yaml.safe_load(written)
    assert data["data"]["invols"] == pytest.approx(45.3e-9, rel=1e-12)
    assert data["cantilever"]["spring_constant"] == 0.4
    spring_line = next(line for line in written.splitlines() if line.strip().startswith("spring_constant:"))
    assert "CHECK: template example" not in spring_line and "Spring Constant" in spring_line
    assert "deflection sensitivity 45.3 nm/V" in inspect_file(path)


def test_lateral_channel_is_never_scaled_by_the_deflection_sensitivity(tmp_path):
    path = write_hsdc(tmp_path / "l.hsdc", sensitivity="45.30000 nm/V")
    assert "data.invols" not in read_trace(path, channel="Lateral Deflection").metadata["stated"]


@pytest.mark.parametrize("wanted, expected", [("Vertical Deflection", "Vertical Deflection"),
                                              ("lateral deflection", "Lateral Deflection"),
                                              ("A", "Vertical Deflection"), ("b", "Lateral Deflection")])
def test_channel_by_name_or_letter(tmp_path, wanted, expected):
    assert read_trace(write_hsdc(tmp_path / "n.hsdc"), channel=wanted).channel == expected


def test_unknown_channel_and_time_channel_are_one_line(tmp_path):
    path = write_hsdc(tmp_path / "n.hsdc")
    err = error_of(path, channel="Height")
    assert err.key == "data.column" and "Vertical Deflection, Lateral Deflection" in str(err)
    assert error_of(path, time_channel="time").key == "data.time_column"


def test_without_a_vertical_deflection_the_channel_must_be_named(tmp_path):
    path = write_hsdc(tmp_path / "t.hsdc", channels={"Lateral Deflection": counts(), "Height": counts()})
    err = error_of(path)
    assert err.key == "data.column" and "choose one" in str(err)


# --------------------------------------------------------------------------- damaged files: one line each
@pytest.mark.parametrize("damage, expected", [
    (dict(lengths=[10**9, 2 * N]), "ends at byte"),  # a block longer than the file holds
    (dict(offsets=[10**12, 8192 + 2 * N]), "ends at byte"),
    (dict(offsets=[100, 8192 + 2 * N]), "lies inside the header"),
    (dict(lengths=[2 * N - 1, 2 * N]), "not a multiple"),
    (dict(end_marker=False), "no end marker"),
    (dict(bytes_per_pixel=4), "4 bytes per sample"),
])
def test_damaged_header_or_blocks_are_one_input_error(tmp_path, damage, expected):
    path = write_hsdc(tmp_path / "bad.hsdc", **damage)
    err = error_of(path)
    assert expected in str(err) and "\n" not in str(err)


def test_truncated_file_and_foreign_file_are_one_input_error(tmp_path):
    whole = write_hsdc(tmp_path / "whole.hsdc").read_bytes()
    cut = tmp_path / "cut.hsdc"
    cut.write_bytes(whole[: len(whole) - 10])
    assert "ends at byte" in str(error_of(cut, channel="Lateral Deflection"))
    foreign = tmp_path / "foreign.hsdc"
    foreign.write_bytes(b"PK\x03\x04" + bytes(100))
    assert "no NanoScope header" in str(error_of(foreign))
    assert "no NanoScope header" in str(pytest.raises(InputError, list_channels, foreign).value)


def test_header_end_is_looked_for_in_a_bounded_prefix(tmp_path):
    path = tmp_path / "endless.hsdc"
    path.write_bytes(b"\\*File list\r\n" + b"\\Note: x\r\n" * (MAX_HEADER_BYTES // 10 + 10))
    assert "no end marker" in str(error_of(path))


# --------------------------------------------------------------------------- the commands take the file directly
def test_inspect_and_init_config_commands_on_a_contradicting_capture(tmp_path, run_cli):
    path = write_hsdc(tmp_path / "x.hsdc", channel_rate="2.5e+005", number_of_samples=N // 8)
    code, out, err = run_cli("inspect", path)
    assert code == 0 and "sample rate:  2 MHz" in out and "nominal drive 50 kHz" in out
    (warning,) = err.splitlines()
    assert warning.startswith("afmid: warning: ") and "using 2 MHz" in warning
    code, out, err = run_cli("init-config", "--from", path, "-o", tmp_path / "run.yaml")
    assert code == 0
    written = yaml.safe_load((tmp_path / "run.yaml").read_text())
    assert written["data"]["path"] == "x.hsdc" and written["data"]["sample_rate"] == RATE
    assert written["drive"]["frequency"] == DRIVE and written["data"]["invols"] is None
