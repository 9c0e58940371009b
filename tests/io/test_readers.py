"""File readers: every format yields the same samples; every user error is an InputError.

Example files are written in each test with numpy, h5py, scipy.io.savemat and
npTDMS's TdmsWriter. igor2 cannot write .ibw files, so :func:`write_ibw5`
builds a minimal Igor binary wave (version 5) following igor2's header layout
(WaveMetrics Technical Note 003).
"""

from __future__ import annotations

import struct
import subprocess
import sys

import numpy as np
import pytest

from afmid.errors import InputError
from afmid.io.readers import READERS, RawTrace, list_channels, read_trace, reader_for
from repo_paths import REPO_ROOT

N = 400
RATE = 2e6  # Hz
T = np.arange(N) / RATE  # s
SIGNAL = 5e-9 * np.sin(2 * np.pi * 3e5 * T) + 1e-10 * np.cos(2 * np.pi * 7e5 * T)  # m


def error_of(path, **kwargs) -> InputError:
    """The InputError read_trace raises for ``path``; fails the test if it raises nothing."""
    with pytest.raises(InputError) as info:
        read_trace(path, **kwargs)
    err = info.value
    assert err.file == str(path), "the message must name the file"
    assert str(path) in str(err)
    return err


# --------------------------------------------------------------------------- file builders
def write_csv(path, columns: dict[str, np.ndarray], delimiter=",", header=True, preamble=(), fmt="%.17g"):
    lines = list(preamble)
    if header:
        lines.append(delimiter.join(columns))
    data = np.column_stack(list(columns.values()))
    lines += [delimiter.join(fmt % v for v in row) for row in data]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_ibw5(path, data, step=1.0, data_units=b"", x_units=b"", name=b"wave0", labels=None, note=b""):
    """A minimal Igor binary wave, version 5, little-endian, float64 data.

    Layout (TN003, igor2.binarywave): version (int16), BinHeader5 (62 bytes),
    WaveHeader5 (320 bytes), data (column-major), then the optional sections,
    of which only the wave note and the dimension labels (32 bytes each) are written here.
    """
    data = np.asarray(data, dtype="<f8")
    dims = list(data.shape) + [0] * (4 - data.ndim)
    wdata = data.tobytes(order="F")
    label_sizes = [0, 0, 0, 0]
    label_bytes = b""
    if labels is not None:  # column labels: one for the dimension, then one per column
        label_bytes = b"".join(label.ljust(32, b"\0") for label in [b"", *labels])
        label_sizes[1] = len(label_bytes)
    wave_header = (
        struct.pack("<IIIihh6xh32s4xI", 0, 0, 0, data.size, 4, 0, 1, name, 0)  # type 4 = NT_FP64
        + struct.pack("<4i", *dims)
        + struct.pack("<4d", step, 1, 1, 1)  # sfA: x step per dimension
        + struct.pack("<4d", 0, 0, 0, 0)  # sfB: x start
        + data_units.ljust(4, b"\0")
        + x_units.ljust(4, b"\0")
        + b"\0" * 12  # units of dimensions 1-3
    )
    wave_header = wave_header.ljust(320, b"\0")
    bin_header = struct.pack("<hhiiii4i4iiii", 5, 0, 320 + len(wdata), 0, len(note), 0, 0, 0, 0, 0, *label_sizes,
                             0, 0, 0)
    # The checksum makes the int16 sum of both headers zero.
    head = bytearray(bin_header + wave_header)
    checksum = -sum(struct.unpack(f"<{len(head) // 2}h", head)) % 65536
    head[2:4] = struct.pack("<H", checksum)
    path.write_bytes(bytes(head) + wdata + note + label_bytes)  # the note precedes the labels (TN003)
    return path


def write_mat73(path, tree: dict):
    """A MATLAB v7.3 file: HDF5 with a 512-byte user block holding the MAT header.

    Structs are groups; lists become cell arrays (datasets of references into
    '#refs#'); arrays are stored transposed, as MATLAB does.
    """
    import h5py

    with h5py.File(path, "w", userblock_size=512) as h5:
        refs = h5.create_group("#refs#")

        def put(group, name, value):
            if isinstance(value, dict):
                sub = group.create_group(name)
                sub.attrs["MATLAB_class"] = np.bytes_("struct")
                for key, child in value.items():
                    put(sub, key, child)
            elif isinstance(value, list):
                targets = []
                for i, item in enumerate(value):
                    put(refs, f"{name}_{i}", item)
                    targets.append(refs[f"{name}_{i}"].ref)
                ds = group.create_dataset(name, data=np.array([targets], dtype=h5py.ref_dtype).T)
                ds.attrs["MATLAB_class"] = np.bytes_("cell")
            elif isinstance(value, str):
                ds = group.create_dataset(name, data=np.array([[ord(c)] for c in value], dtype=np.uint16))
                ds.attrs["MATLAB_class"] = np.bytes_("char")
            else:
                ds = group.create_dataset(name, data=np.atleast_2d(np.asarray(value, dtype=float)))
                ds.attrs["MATLAB_class"] = np.bytes_("double")

        for key, value in tree.items():
            put(h5, key, value)
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    with open(path, "r+b") as fh:
        fh.write(header.ljust(116, b" ") + b"\0" * 8 + struct.pack("<H", 0x0200) + b"IM")
    return path


def write_afmid_trace(path, with_truth=True):
    import h5py

    with h5py.File(path, "w") as h5:
        h5.attrs["format"] = "afmid-trace"
        h5.attrs["format_version"] = np.int64(1)
        h5.attrs["sample_rate"] = np.float64(RATE)
        h5.create_dataset("deflection", data=SIGNAL).attrs["units"] = "m"
        h5.create_dataset("time", data=T).attrs["units"] = "s"
        cl = h5.create_group("cantilever")
        cl.attrs["spring_constant"] = np.float64(40.0)
        cl.attrs["quality_factor"] = np.float32(400.0)
        h5.create_group("drive").attrs["frequency"] = np.float64(3e5)
        if with_truth:
            tg = h5.create_group("truth")
            tg.create_dataset("force", data=np.zeros(N))
            tg.create_dataset("separation", data=np.ones(N))
            tg.create_group("parameters").attrs["E"] = 1e9
    return path


def write_tdms(path, channels: dict[tuple[str, str], tuple[np.ndarray, dict]], file_props=None):
    nptdms = pytest.importorskip("nptdms")
    objects = [nptdms.RootObject(properties=file_props or {})]
    for (group, name), (data, props) in channels.items():
        objects.append(nptdms.ChannelObject(group, name, data, properties=props))
    with nptdms.TdmsWriter(str(path)) as writer:
        writer.write_segment(objects)
    return path


# --------------------------------------------------------------------------- registry
def test_registry_declares_every_format():
    assert READERS.names() == ["csv", "npy", "hdf5", "mat", "ibw", "tdms", "hsdc"]
    for reader in READERS:
        assert reader.title and reader.references and reader.suffixes
        assert all(s.startswith(".") and s == s.lower() for s in reader.suffixes)
    assert READERS.get("ibw").extra == READERS.get("tdms").extra == "formats"
    assert READERS.get("csv").extra is None


@pytest.mark.parametrize(
    "name, expected",
    [("a.csv", "csv"), ("a.TSV", "csv"), ("a.dat", "csv"), ("a.npz", "npy"), ("a.hdf", "hdf5"),
     ("a.mat", "mat"), ("a.ibw", "ibw"), ("a.tdms", "tdms"), ("a.HSDC", "hsdc")],
)
def test_reader_for_suffix(tmp_path, name, expected):
    assert reader_for(tmp_path / name).name == expected


def test_reader_for_unknown_suffix_and_format(tmp_path):
    with pytest.raises(InputError) as info:
        reader_for(tmp_path / "trace.xyz")
    assert info.value.key == "data.format" and "trace.xyz" in str(info.value)
    assert "csv, npy, hdf5, mat, ibw, tdms" in str(info.value)
    with pytest.raises(InputError) as info:
        reader_for(tmp_path / "trace.csv", "hdf")
    assert info.value.key == "data.format" and "did you mean 'hdf5'" in str(info.value)
    assert reader_for(tmp_path / "trace.bin", "HDF5").name == "hdf5"


def test_importing_readers_does_not_import_optional_or_heavy_packages():
    code = (
        "import sys, afmid.io.readers; "
        "print(sorted(m for m in ('h5py', 'scipy', 'igor2', 'nptdms') if m in sys.modules))"
    )
    root = REPO_ROOT
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=root).stdout
    assert out.strip() == "[]"


# --------------------------------------------------------------------------- same samples everywhere
def _csv(tmp_path):
    return write_csv(tmp_path / "t.csv", {"time": T, "deflection": SIGNAL}), {}


def _npy(tmp_path):
    np.save(tmp_path / "t.npy", SIGNAL)
    return tmp_path / "t.npy", {}


def _npy_2d(tmp_path):
    np.save(tmp_path / "t2.npy", np.column_stack([T, SIGNAL]))
    return tmp_path / "t2.npy", {"channel": 1}


def _npz(tmp_path):
    np.savez(tmp_path / "t.npz", t=T, deflection=SIGNAL)
    return tmp_path / "t.npz", {}


def _hdf5(tmp_path):
    return write_afmid_trace(tmp_path / "t.h5"), {}


def _mat(tmp_path):
    from scipy.io import savemat

    savemat(tmp_path / "t.mat", {"dev1234": {"demods": {"sample": {"x": SIGNAL, "timestamp": np.arange(N)}}}})
    return tmp_path / "t.mat", {"channel": "dev1234.demods.sample.x"}


def _mat73(tmp_path):
    return write_mat73(tmp_path / "t73.mat", {"dev1234": {"demods": {"sample": {"x": SIGNAL}}}}), {
        "channel": "dev1234.demods.sample.x"
    }


def _ibw(tmp_path):
    pytest.importorskip("igor2")
    return write_ibw5(tmp_path / "t.ibw", SIGNAL, step=1 / RATE, data_units=b"m", x_units=b"s"), {}


def _tdms(tmp_path):
    return write_tdms(tmp_path / "t.tdms", {("AFM", "deflection"): (SIGNAL, {"wf_increment": 1 / RATE})}), {}


@pytest.mark.parametrize("build", [_csv, _npy, _npy_2d, _npz, _hdf5, _mat, _mat73, _ibw, _tdms])
def test_every_reader_returns_the_same_samples(tmp_path, build):
    path, kwargs = build(tmp_path)
    trace = read_trace(path, **kwargs)
    assert isinstance(trace, RawTrace)
    assert trace.values.dtype == np.float64 and trace.values.ndim == 1
    np.testing.assert_array_equal(trace.values, SIGNAL)
    assert trace.channel in trace.channels
    assert trace.channels == list_channels(path)
    assert trace.source["values"].startswith("file:")


# --------------------------------------------------------------------------- CSV variants
@pytest.mark.parametrize("delimiter", [",", ";", "\t", " ", "   "])
@pytest.mark.parametrize("header", [True, False])
def test_csv_delimiters_with_and_without_header(tmp_path, delimiter, header):
    path = write_csv(tmp_path / "d.csv", {"time": T, "deflection": SIGNAL}, delimiter=delimiter, header=header)
    trace = read_trace(path, channel=1, time_channel=0)
    np.testing.assert_array_equal(trace.values, SIGNAL)
    np.testing.assert_allclose(trace.time, T, rtol=0, atol=1e-18)
    assert trace.sample_rate == pytest.approx(RATE)
    assert trace.channels == (["time", "deflection"] if header else ["0", "1"])


def test_csv_comment_lines_and_header_fields(tmp_path):
    preamble = ["# exported by the test", "% sample_rate: 2 MHz", "#   InvOLS = 50 nm/V", ""]
    path = write_csv(tmp_path / "c.txt", {"deflection_nm": SIGNAL * 1e9}, preamble=preamble)
    text = path.read_text().splitlines()
    text.insert(10, "# a comment between data rows")
    path.write_text("\n".join(text) + "\n")
    trace = read_trace(path)
    np.testing.assert_allclose(trace.values, SIGNAL * 1e9, rtol=1e-15)
    assert trace.values.size == N
    assert trace.units == "nm" and trace.channel == "deflection_nm"
    assert trace.sample_rate == pytest.approx(RATE)
    assert trace.source["sample_rate"] == "file:comment line 2 (sample_rate)"
    assert trace.metadata["header_fields"] == {"sample_rate": "2 MHz", "invols": "50 nm/V"}


@pytest.mark.parametrize("stated, rate", [
    ("60 MS/s", 60e6), ("60MS/s", 60e6), ("2 MSa/s", 2e6), ("500 kS/s", 5e5), ("250 kSa/s", 2.5e5),
    ("2e6 Sa/s", 2e6), ("2e6 S/s", 2e6), ("1e6 samples/s", 1e6), ("2 MHz", 2e6), ("2 mhz", 2e6), ("2 MHZ", 2e6),
    ("500 kHz", 5e5), ("2e6 Hz", 2e6), ("2e6", 2e6), ("2e6 s^-1", 2e6), ("2e6 1/s", 2e6), ("0.002 GHz", 2e6),
])
def test_csv_header_sample_rate_with_unit_prefixes(tmp_path, stated, rate):
    """`# Sample rate: 60 MS/s` as instruments write it: the unit's SI prefix parsed, samples counted."""
    path = write_csv(tmp_path / "r.csv", {"deflection_nm": SIGNAL * 1e9}, preamble=[f"# Sample rate: {stated}"])
    trace = read_trace(path)
    assert trace.sample_rate == pytest.approx(rate, rel=1e-12)
    assert trace.source["sample_rate"] == "file:comment line 1 (sample_rate)"


@pytest.mark.parametrize("field, stated, step", [("dt", "500 ns", 5e-7), ("dt", "0.5 us", 5e-7),
                                                 ("dt", "0.5 µs", 5e-7), ("time_step", "5e-4 ms", 5e-7)])
def test_csv_header_time_step_with_unit_prefixes(tmp_path, field, stated, step):
    path = write_csv(tmp_path / "r.csv", {"deflection_nm": SIGNAL * 1e9}, preamble=[f"# {field}: {stated}"])
    assert read_trace(path).sample_rate == pytest.approx(1 / step, rel=1e-12)


@pytest.mark.parametrize("field, stated, expected", [
    ("Sample rate", "60 MS", "a positive number of Hz, or one with a rate unit (Hz, kHz, MHz, S/s, kS/s, MS/s"),
    ("Sample rate", "60 ms", "a positive number of Hz, or one with a rate unit"),  # a time is not a rate
    ("Sample rate", "60 furlongs/s", "a positive number of Hz, or one with a rate unit"),
    ("Sample rate", "60 XHz", "a positive number of Hz, or one with a rate unit"),  # not an SI prefix
    ("Sample rate", "-60 MS/s", "a positive number of Hz"),
    ("Sample rate", "fast", "a positive number of Hz"),
    ("dt", "16 MHz", "a positive number of seconds, or one with a time unit (s, ms, us, µs or ns)"),
])
def test_csv_header_rate_in_an_unknown_unit_is_one_line_naming_file_and_line(tmp_path, field, stated, expected):
    path = write_csv(tmp_path / "r.csv", {"deflection_nm": SIGNAL * 1e9},
                     preamble=["# exported by the test", f"# {field}: {stated}"])
    err = error_of(path)
    assert f"comment line 2 ({field.lower().replace(' ', '_')}) = '{stated}' is not {expected}" in err.message
    assert "\n" not in str(err)


def test_csv_channel_by_name_index_and_digit_string(tmp_path):
    path = write_csv(tmp_path / "n.csv", {"time (s)": T, "deflection [nm]": SIGNAL, "drive_V": -SIGNAL})
    for channel in ("deflection [nm]", "deflection", "DEFLECTION", 1, "1"):
        trace = read_trace(path, channel=channel)
        assert trace.channel == "deflection [nm]" and trace.units == "nm"
        np.testing.assert_array_equal(trace.values, SIGNAL)
    assert read_trace(path, channel="drive").units == "V"
    assert read_trace(path).channel == "deflection [nm]"  # the default: named 'deflection'


def test_csv_time_units_are_converted_to_seconds(tmp_path):
    path = write_csv(tmp_path / "ms.csv", {"t_ms": T * 1e3, "z": SIGNAL})
    trace = read_trace(path, time_channel="t_ms")
    assert trace.channel == "z"  # the only column that is not a time axis
    np.testing.assert_allclose(trace.time, T, rtol=1e-12, atol=1e-20)
    assert trace.sample_rate == pytest.approx(RATE)
    assert trace.source["sample_rate"] == "derived:uniform time channel 't_ms'"


def test_csv_nonuniform_time_gives_no_sample_rate(tmp_path):
    path = write_csv(tmp_path / "nu.csv", {"time": T**1.5, "deflection": SIGNAL})
    trace = read_trace(path, time_channel="time")
    assert trace.time is not None and trace.sample_rate is None


def test_csv_commented_header_as_savetxt_writes_it(tmp_path):
    path = tmp_path / "s.dat"
    np.savetxt(path, np.column_stack([T, SIGNAL]), header="time deflection")
    trace = read_trace(path, time_channel="time")
    assert trace.channels == ["time", "deflection"] and trace.metadata["header"] == "comment"
    np.testing.assert_array_equal(trace.values, SIGNAL)


def test_csv_bom_crlf_and_quotes(tmp_path):
    rows = "\r\n".join(f'"{t!r}","{x!r}"' for t, x in zip(T.tolist(), SIGNAL.tolist(), strict=True))
    path = tmp_path / "q.csv"
    path.write_bytes(b"\xef\xbb\xbf" + f'"time","deflection"\r\n{rows}\r\n'.encode())
    trace = read_trace(path)
    assert trace.channels == ["time", "deflection"]
    np.testing.assert_array_equal(trace.values, SIGNAL)


def test_csv_whitespace_header_with_bracketed_units(tmp_path):
    path = write_csv(tmp_path / "ws.txt", {"time [ms]": T * 1e3, "deflection [nm]": SIGNAL * 1e9}, delimiter="  ")
    trace = read_trace(path, time_channel="time")
    assert trace.channels == ["time [ms]", "deflection [nm]"] and trace.units == "nm"
    np.testing.assert_allclose(trace.time, T, rtol=1e-12, atol=1e-20)


@pytest.mark.parametrize("encoding", ["latin-1", "utf-8", "utf-16"])
def test_csv_text_encodings(tmp_path, encoding):
    path = tmp_path / f"enc-{encoding}.csv"
    rows = [f"{t!r};{x!r}" for t, x in zip(T.tolist(), SIGNAL.tolist(), strict=True)]
    lines = ["# Gerät: AFM", "t;deflection [µm]", *rows]
    path.write_bytes("\n".join(lines).encode(encoding))
    trace = read_trace(path, time_channel="t")
    assert trace.units == "µm" and trace.metadata["header_fields"] == {"gerät": "AFM"}
    np.testing.assert_array_equal(trace.values, SIGNAL)


def test_csv_single_column_without_header(tmp_path):
    path = write_csv(tmp_path / "one.txt", {"x": SIGNAL}, header=False)
    trace = read_trace(path)
    assert trace.channel == "0" and trace.units is None and trace.sample_rate is None
    np.testing.assert_array_equal(trace.values, SIGNAL)


def test_csv_nan_and_inf_are_read_not_rejected(tmp_path):
    path = tmp_path / "nan.csv"
    path.write_text("deflection\n1.0\nnan\ninf\n-inf\nNaN\n")
    values = read_trace(path).values
    assert np.isnan(values[1]) and np.isposinf(values[2]) and np.isneginf(values[3]) and np.isnan(values[4])


# --------------------------------------------------------------------------- CSV errors
def test_csv_text_in_a_number_column_names_column_and_row(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("# note\ntime,deflection\n0,1\n1,2\n2,oops\n3,4\n")
    err = error_of(path, channel="deflection")
    assert err.key == "data.column"
    assert "'deflection'" in err.message and "'oops'" in err.message and "row 3 (line 5)" in err.message


def test_csv_empty_value_and_decimal_comma(tmp_path):
    path = tmp_path / "empty_field.csv"
    path.write_text("time,deflection\n0,1\n1,\n")
    assert "empty value at row 2" in error_of(path, channel=1).message
    path = tmp_path / "comma.csv"
    path.write_text("time;deflection\n0,0;1,5\n0,1;2,5\n")
    err = error_of(path, channel="deflection")
    assert err.key == "data.column" and "decimal commas" in err.message


@pytest.mark.parametrize("rows", [
    ["1,234", "-0,5", "0,0625", "2,75"],  # one column: comma-split, it looked like two integer columns
    ["1,234 5,678", "0,05 -1,5", "2,5 3,25"],  # spaces between the values
    ["1,234\t5,678", "0,05\t-1,5", "2,5\t3,25"],  # tabs
    ["1,234;5,678", "0,05;-1,5", "2,5;3,25"],  # semicolons
    ["1,5e-09", "2,25e-09", "-3,125e-09"],  # exponents
])
def test_csv_headerless_decimal_commas_are_refused_as_such(tmp_path, rows):
    """A headerless file written with decimal commas: before, the integer part was read as the trace (issue 32).
    The reader refuses it whatever the delimiter (docs/file-formats.md: decimal commas are not read)."""
    path = tmp_path / "dec.csv"
    path.write_text("\n".join(rows) + "\n")
    err = error_of(path)
    assert "decimal commas" in err.message and "export with '.' as the decimal separator" in err.message
    assert err.message.count("\n") == 0


def test_csv_headerless_integer_columns_stay_columns(tmp_path):
    """Two integer columns (a sample counter and ADC counts) are not decimal commas: no leading zero after the
    comma, no exponent, no '-0' before it."""
    path = tmp_path / "ints.csv"
    path.write_text("1,234\n2,250\n3,-17\n4,1234\n")
    trace = read_trace(path, channel=1)
    np.testing.assert_array_equal(trace.values, [234, 250, -17, 1234])


def test_csv_ragged_row(tmp_path):
    path = tmp_path / "ragged.csv"
    path.write_text("a,b,c\n1,2,3\n4,5\n")
    err = error_of(path, channel="c")
    assert err.key == "data.column" and "row 2 (line 3) has 2 values" in err.message


def test_csv_unknown_channel_suggests_and_lists(tmp_path):
    path = write_csv(tmp_path / "u.csv", {"time": T, "deflection": SIGNAL})
    err = error_of(path, channel="deflectoin")
    assert err.key == "data.column"
    assert "did you mean 'deflection'" in err.message and "available: time, deflection" in err.message
    err = error_of(path, channel=5)
    assert err.key == "data.column" and "out of range" in err.message
    err = error_of(path, time_channel="tiem")
    assert err.key == "data.time_column" and "did you mean 'time'" in err.message


def test_csv_default_channel_is_never_the_time_column(tmp_path):
    path = write_csv(tmp_path / "tx.csv", {"a": T, "b": SIGNAL}, header=False)
    trace = read_trace(path, time_channel=0)
    assert trace.channel == "1"
    np.testing.assert_array_equal(trace.values, SIGNAL)


def test_csv_ambiguous_default_channel(tmp_path):
    path = write_csv(tmp_path / "amb.csv", {"a": SIGNAL, "b": SIGNAL}, header=False)
    err = error_of(path)
    assert err.key == "data.column" and "choose one with data.column: 0, 1" in err.message


@pytest.mark.parametrize(
    "content, message",
    [("", "no data rows"), ("# only a comment\n\n", "no data rows"), ("time,deflection\n", "only a header")],
)
def test_csv_without_data(tmp_path, content, message):
    path = tmp_path / "empty.csv"
    path.write_text(content)
    assert message in error_of(path).message


def test_csv_binary_file(tmp_path):
    path = tmp_path / "binary.csv"
    path.write_bytes(b"\x89HDF\r\n\x1a\n\x00\x00\x00")
    assert "not a text file" in error_of(path).message


def test_csv_time_column_with_non_time_units(tmp_path):
    path = write_csv(tmp_path / "tu.csv", {"z_nm": SIGNAL, "deflection": SIGNAL})
    err = error_of(path, time_channel="z_nm")
    assert err.key == "data.time_column" and "not a time unit" in err.message


# --------------------------------------------------------------------------- common errors
def test_missing_file_and_folder(tmp_path):
    err = error_of(tmp_path / "nope.csv")
    assert err.key == "data.path" and "not found" in err.message
    with pytest.raises(InputError, match="not found"):
        list_channels(tmp_path / "nope.h5")
    folder = tmp_path / "folder.h5"
    folder.mkdir()
    assert "folder" in error_of(folder).message


def test_os_errors_become_input_errors(tmp_path, monkeypatch):
    from afmid.io.readers import csv as csv_reader

    def denied(path):
        raise PermissionError(13, "Permission denied", str(path))

    path = write_csv(tmp_path / "locked.csv", {"deflection": SIGNAL})
    monkeypatch.setattr(csv_reader, "_layout", denied)
    err = error_of(path)
    assert "cannot read the file: Permission denied" in err.message


@pytest.mark.parametrize("suffix, kind", [(".h5", "HDF5"), (".npy", "NumPy"), (".npz", "NumPy"), (".mat", "MATLAB")])
def test_truncated_files(tmp_path, suffix, kind):
    full = tmp_path / f"full{suffix}"
    if suffix == ".h5":
        write_afmid_trace(full)
    elif suffix == ".npy":
        np.save(full, SIGNAL)
    elif suffix == ".npz":
        np.savez(full, deflection=SIGNAL)
    else:
        from scipy.io import savemat

        savemat(full, {"deflection": SIGNAL})
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    err = error_of(cut)
    assert f"not a readable {kind} file (truncated or corrupt?)" in err.message


def test_garbage_with_a_known_suffix(tmp_path):
    for suffix in (".h5", ".npy", ".mat"):
        path = tmp_path / f"garbage{suffix}"
        path.write_bytes(b"this is not a data file\n" * 10)
        assert "not a readable" in error_of(path).message


# --------------------------------------------------------------------------- NumPy
def test_npz_names_units_time_and_stated_rate(tmp_path):
    path = tmp_path / "s.npz"
    np.savez(path, time_us=T * 1e6, deflection_nm=SIGNAL * 1e9, dt=np.float64(1 / RATE), label=np.str_("x"))
    trace = read_trace(path, time_channel="time")
    assert trace.channel == "deflection_nm" and trace.units == "nm"
    assert trace.channels == ["time_us", "deflection_nm"]
    np.testing.assert_allclose(trace.time, T, rtol=1e-12, atol=1e-20)
    assert trace.sample_rate == pytest.approx(RATE) and trace.source["sample_rate"] == "file:array 'dt'"
    assert trace.metadata["scalars"]["label"] == "x"


def test_npz_two_dimensional_array_is_not_a_channel(tmp_path):
    path = tmp_path / "img.npz"
    np.savez(path, deflection=SIGNAL, image=np.zeros((3, 4)))
    assert list_channels(path) == ["deflection"]
    err = error_of(path, channel="image")
    assert err.key == "data.column" and "shape (3, 4)" in err.message


def test_npy_errors(tmp_path):
    np.save(tmp_path / "three.npy", np.zeros((4, 3, 2)))
    assert "expected 1-D" in error_of(tmp_path / "three.npy").message
    np.save(tmp_path / "wide.npy", np.zeros((N, 3)))
    err = error_of(tmp_path / "wide.npy")
    assert err.key == "data.column" and "choose one" in err.message
    np.save(tmp_path / "one.npy", SIGNAL)
    assert error_of(tmp_path / "one.npy", time_channel=0).key == "data.time_column"
    np.save(tmp_path / "empty.npy", np.zeros(0))
    assert "empty" in error_of(tmp_path / "empty.npy").message
    np.save(tmp_path / "text.npy", np.array(["a", "b"]))
    assert "not numeric" in error_of(tmp_path / "text.npy").message
    np.save(tmp_path / "obj.npy", np.array([1, "a"], dtype=object), allow_pickle=True)
    assert "Python objects" in error_of(tmp_path / "obj.npy").message


def test_npz_unknown_and_integer_time(tmp_path):
    path = tmp_path / "i.npz"
    np.savez(path, deflection=SIGNAL, ticks=np.arange(N))
    err = error_of(path, channel="deflexion")
    assert err.key == "data.column" and "did you mean 'deflection'" in err.message
    err = error_of(path, time_channel="ticks")
    assert err.key == "data.time_column" and "integers" in err.message


# --------------------------------------------------------------------------- HDF5
def test_afmid_trace_metadata(tmp_path):
    path = write_afmid_trace(tmp_path / "trace.h5")
    trace = read_trace(path, time_channel="time")
    assert trace.channel == "/deflection" and trace.units == "m"
    assert trace.sample_rate == RATE and trace.source["sample_rate"] == "file:/attrs/sample_rate"
    assert trace.source["units"] == "file:/deflection/attrs/units"
    np.testing.assert_array_equal(trace.time, T)
    meta = trace.metadata
    assert meta["format"] == "afmid-trace"
    assert meta["root"]["sample_rate"] == RATE and type(meta["root"]["format_version"]) is int
    assert meta["cantilever"] == {"spring_constant": 40.0, "quality_factor": 400.0}
    assert type(meta["cantilever"]["quality_factor"]) is float
    assert meta["drive"] == {"frequency": 3e5}
    assert meta["truth_datasets"] == ["/truth/force", "/truth/separation"]
    assert "/truth/force" in trace.channels


def test_hdf5_generic_file(tmp_path):
    import h5py

    path = tmp_path / "g.hdf5"
    with h5py.File(path, "w") as h5:
        g = h5.create_group("AFM")
        g.attrs["dt"] = 1 / RATE
        g.create_dataset("z_nm", data=SIGNAL * 1e9)
        g.create_dataset("t", data=T)
        h5.create_dataset("image", data=np.zeros((4, 4)))
        h5.create_dataset("name", data="a string")
    trace = read_trace(path)
    assert trace.channel == "/AFM/z_nm" and trace.units == "nm"
    assert trace.channels == ["/AFM/t", "/AFM/z_nm"]
    assert trace.sample_rate == pytest.approx(RATE) and trace.source["sample_rate"] == "file:/AFM/attrs/dt"
    assert read_trace(path, channel="AFM/z_nm").channel == "/AFM/z_nm"
    assert read_trace(path, channel="z").channel == "/AFM/z_nm"
    err = error_of(path, channel="/AFM/x")
    assert err.key == "data.column" and "available: /AFM/t, /AFM/z_nm" in err.message
    assert "shape (4, 4)" in error_of(path, channel="/image").message
    assert "not numeric" in error_of(path, channel="/name").message
    assert "by name, not by index" in error_of(path, channel=0).message


def test_hdf5_time_length_mismatch_and_bad_rate(tmp_path):
    import h5py

    path = tmp_path / "m.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("deflection", data=SIGNAL)
        h5.create_dataset("time", data=T[:-1])
    err = error_of(path, time_channel="time")
    assert err.key == "data.time_column" and "samples" in err.message
    with h5py.File(path, "a") as h5:
        h5.attrs["sample_rate"] = "fast"
    assert "sample_rate = 'fast' is not a positive number" in error_of(path).message


def test_hdf5_no_channel(tmp_path):
    import h5py

    path = tmp_path / "none.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("a", data=SIGNAL)
        h5.create_dataset("b", data=SIGNAL)
    err = error_of(path)
    assert err.key == "data.column" and "/a, /b" in err.message
    with h5py.File(path, "w") as h5:
        h5.create_dataset("empty", data=np.zeros(0))
    assert "no numeric channel" in error_of(path).message
    assert "is empty" in error_of(path, channel="empty").message


def test_truncated_hdf5_message(tmp_path):
    full = write_afmid_trace(tmp_path / "full.h5")
    cut = tmp_path / "cut.h5"
    cut.write_bytes(full.read_bytes()[:1000])
    assert "not a readable HDF5 file (truncated or corrupt?)" in str(error_of(cut))


# --------------------------------------------------------------------------- MATLAB
def labone_tree():
    return {
        "dev1234": {
            "demods": [
                {"sample": {"x": SIGNAL, "y": -SIGNAL, "frequency": 3e5}},
                {"sample": {"x": 2 * SIGNAL, "y": -2 * SIGNAL, "frequency": 6e5}},
            ],
            "clockbase": 6e7,
            "name": "HF2LI",
        },
        "sample_rate": RATE,
    }


def test_mat_labone_struct_paths(tmp_path):
    from scipy.io import savemat

    path = tmp_path / "labone.mat"
    savemat(path, labone_tree())
    trace = read_trace(path, channel="dev1234.demods.1.sample.x")
    np.testing.assert_array_equal(trace.values, 2 * SIGNAL)
    assert trace.channels == [
        "dev1234.demods.0.sample.x", "dev1234.demods.0.sample.y",
        "dev1234.demods.1.sample.x", "dev1234.demods.1.sample.y",
    ]
    assert trace.sample_rate == RATE and trace.source["sample_rate"] == "file:variable 'sample_rate'"
    assert trace.metadata["scalars"]["dev1234.name"] == "HF2LI"
    assert trace.metadata["scalars"]["dev1234.demods.0.sample.frequency"] == 3e5
    err = error_of(path, channel="x")
    assert err.key == "data.column" and "ambiguous" in err.message
    err = error_of(path, channel="dev1234.demods.2.sample.x")
    assert err.key == "data.column" and "did you mean" in err.message
    assert "single value" in error_of(path, channel="dev1234.clockbase").message
    assert "not numeric" in error_of(path, channel="dev1234.name").message


def test_mat_one_element_struct_array_and_cell_are_stepped_through(tmp_path):
    from scipy.io import savemat

    demods = np.zeros((1, 1), dtype=[("sample", "O")])
    demods[0, 0]["sample"] = {"x": SIGNAL}
    cell = np.empty((1, 1), dtype=object)
    cell[0, 0] = {"t": T}
    path = tmp_path / "one.mat"
    savemat(path, {"dev1": {"demods": demods, "cell": cell}})
    trace = read_trace(path, channel="dev1.demods.sample.x", time_channel="dev1.cell.t")
    np.testing.assert_array_equal(trace.values, SIGNAL)
    assert trace.sample_rate == pytest.approx(RATE)


def test_mat73_struct_and_cell_paths(tmp_path):
    tree = labone_tree()
    path = write_mat73(tmp_path / "v73.mat", tree)
    trace = read_trace(path, channel="dev1234.demods.1.sample.x")
    np.testing.assert_array_equal(trace.values, 2 * SIGNAL)
    assert trace.metadata["version"] == "7.3"
    assert trace.metadata["scalars"]["dev1234.name"] == "HF2LI"
    assert trace.sample_rate == RATE
    assert "dev1234.demods.0.sample.y" in trace.channels
    assert "not numeric" in error_of(path, channel="dev1234.name").message


# --------------------------------------------------------------------------- Igor
def test_ibw_2d_labelled_columns(tmp_path):
    pytest.importorskip("igor2")
    data = np.column_stack([SIGNAL * 10, SIGNAL])
    path = write_ibw5(tmp_path / "force.ibw", data, step=1 / RATE, x_units=b"s", labels=[b"Raw", b"Defl"])
    trace = read_trace(path, channel="Defl")
    np.testing.assert_array_equal(trace.values, SIGNAL)
    assert trace.channels == ["Raw", "Defl"] and trace.sample_rate == pytest.approx(RATE)
    np.testing.assert_array_equal(read_trace(path, channel=0).values, SIGNAL * 10)
    err = error_of(path, channel="Def")
    assert err.key == "data.column" and "did you mean 'Defl'" in err.message


def test_ibw_units_and_scaling(tmp_path):
    pytest.importorskip("igor2")
    path = write_ibw5(tmp_path / "w.ibw", SIGNAL, step=0.5, x_units=b"us", data_units=b"nm", name=b"Defl0")
    trace = read_trace(path)
    assert trace.channel == "Defl0" and trace.units == "nm"
    assert trace.sample_rate == pytest.approx(2e6)
    unscaled = read_trace(write_ibw5(tmp_path / "u.ibw", SIGNAL))
    assert unscaled.sample_rate is None and unscaled.units is None
    assert error_of(path, time_channel="t").key == "data.time_column"


def test_ibw_note_rate_contradicting_the_x_scaling_is_stated(tmp_path, caplog):
    """An Asylum-style wave note declaring twice the x scaling's rate: before, the x scaling was used without a
    word (issue 32). Now one warning and the value source name both rates, which is used and why."""
    pytest.importorskip("igor2")
    note = b"ScanRate: 1\rNumPtsPerSec: 4000000\rSpringConstant: 40\r"
    path = write_ibw5(tmp_path / "w.ibw", SIGNAL, step=1 / RATE, x_units=b"s", data_units=b"m", note=note)
    with caplog.at_level("WARNING", logger="afmid"):
        trace = read_trace(path)
    assert trace.sample_rate == pytest.approx(RATE)
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert str(path) in warning
    assert "the wave note's NumPtsPerSec says 4 MHz, the x scaling (5e-07 s) 2 MHz" in warning
    assert "using the x scaling's 2 MHz" in warning and "data.sample_rate" in warning
    assert "not the note's NumPtsPerSec 4 MHz" in trace.source["sample_rate"]
    # A note that agrees (to the x scaling's float rounding) is no contradiction.
    caplog.clear()
    agreeing = write_ibw5(tmp_path / "a.ibw", SIGNAL, step=1 / RATE, x_units=b"s", note=b"NumPtsPerSec: 2000000\r")
    with caplog.at_level("WARNING", logger="afmid"):
        assert read_trace(agreeing).sample_rate == pytest.approx(RATE)
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
    # Without an x scaling, the note's rate is the rate.
    unscaled = write_ibw5(tmp_path / "n.ibw", SIGNAL, note=b"NumPtsPerSec: 2000000\r")
    trace = read_trace(unscaled)
    assert trace.sample_rate == pytest.approx(RATE) and "NumPtsPerSec" in trace.source["sample_rate"]


def test_ibw_corrupt(tmp_path):
    pytest.importorskip("igor2")
    full = write_ibw5(tmp_path / "full.ibw", SIGNAL)
    cut = tmp_path / "cut.ibw"
    cut.write_bytes(full.read_bytes()[:100])
    assert "not a readable Igor binary wave file" in error_of(cut).message


@pytest.mark.parametrize("module, suffix, package", [("igor2", ".ibw", "igor2"), ("nptdms", ".tdms", "npTDMS")])
def test_missing_optional_package(tmp_path, monkeypatch, module, suffix, package):
    path = tmp_path / f"x{suffix}"
    path.write_bytes(b"\0" * 64)
    monkeypatch.setitem(sys.modules, module, None)  # makes the import fail
    err = error_of(path)
    assert f"reading {suffix} files needs the optional package {package}: pip install 'afmid[formats]'" in str(err)


# --------------------------------------------------------------------------- TDMS
def test_tdms_channels_units_rate_and_metadata(tmp_path):
    path = write_tdms(
        tmp_path / "r.tdms",
        {
            ("AFM", "deflection"): (SIGNAL * 1e9, {"wf_increment": 1 / RATE, "unit_string": "nm"}),
            ("AFM", "z"): (SIGNAL, {}),
            ("Aux", "z"): (SIGNAL, {}),
            ("Aux", "time"): (T * 1e3, {"unit_string": "ms"}),
        },
        file_props={"operator": "test", "started": np.datetime64("2024-01-01T12:00:00.5", "ns")},
    )
    trace = read_trace(path, time_channel="time")
    assert trace.channel == "AFM/deflection" and trace.units == "nm"
    assert trace.sample_rate == pytest.approx(RATE)
    assert trace.source["sample_rate"] == "file:AFM/deflection/wf_increment"
    np.testing.assert_allclose(trace.time, T, rtol=1e-12, atol=1e-20)
    assert trace.metadata["file"] == {"operator": "test", "started": "2024-01-01T12:00:00.500000"}
    assert read_trace(path, channel="Aux/z").channel == "Aux/z"
    err = error_of(path, channel="z")
    assert err.key == "data.column" and "ambiguous" in err.message and "AFM/z, Aux/z" in err.message
    err = error_of(path, channel="AFM/defl")
    assert err.key == "data.column" and "did you mean 'AFM/deflection'" in err.message


def test_tdms_timestamp_time_channel(tmp_path):
    # npTDMS writes timestamps with 1 us resolution, so this trace is sampled at 100 kHz.
    seconds = np.arange(N) * 1e-5
    stamps = np.datetime64("2024-01-01T00:00:00", "us") + np.arange(N) * np.timedelta64(10, "us")
    path = write_tdms(tmp_path / "ts.tdms", {("AFM", "deflection"): (SIGNAL, {}), ("AFM", "time"): (stamps, {})})
    trace = read_trace(path, time_channel="time")
    np.testing.assert_allclose(trace.time, seconds, rtol=0, atol=1e-15)
    assert trace.sample_rate == pytest.approx(1e5, rel=1e-6)
    assert trace.source["sample_rate"] == "derived:uniform time channel 'AFM/time'"


def test_tdms_truncated_and_garbage(tmp_path):
    full = write_tdms(tmp_path / "full.tdms", {("AFM", "deflection"): (SIGNAL, {})})
    cut = tmp_path / "cut.tdms"
    cut.write_bytes(full.read_bytes()[:-100])
    assert "not a readable TDMS file (truncated or corrupt?)" in error_of(cut).message
    garbage = tmp_path / "garbage.tdms"
    garbage.write_bytes(b"not a tdms file" * 10)
    assert "not a readable TDMS file" in error_of(garbage).message
