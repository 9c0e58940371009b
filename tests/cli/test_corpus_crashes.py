"""Bad-input corpus: crashes and hangs where one line is promised, and special files (issue 11).

Seeds out of range, simulations and arrays larger than the memory, lying or
damaged file headers, FIFOs, devices, symbolic link loops, unreadable files,
files that are not data (whose content must not be echoed) and special files
given as outputs. See tests/corpus.py for the contract every case must meet;
:data:`NOT_ECHOED` adds, for some cases, text the error line must not contain.
"""

from __future__ import annotations

import io
import os
import re
import struct
from pathlib import Path

import numpy as np
import yaml

from tests.conftest import CANTILEVER, DRIVE_FREQUENCY, SAMPLE_RATE, sinusoid
from corpus import Case, check_case, corpus_params
from tests.cli.test_corpus_config import base_config, fit_case, fit_workspace
from tests.io.test_hsdc import counts as hsdc_counts
from tests.io.test_hsdc import write_hsdc
from tests.io.test_readers import write_mat73
from repo_paths import REPO_ROOT

REPO = REPO_ROOT
#: A regular file the kernel refuses to open for reading, even to root (a write-only sysctl).
UNREADABLE_FILE = "/proc/sys/vm/compact_memory"
#: Samples a lying header claims: 8 TB of float64, more than any test machine has.
HUGE = 10**12


# --------------------------------------------------------------------------- workspace builders
def simulate_config(**changes) -> dict:
    """configs/dmt.yaml (a fast steady DMT simulation) with dotted-key ``changes``."""
    config = yaml.safe_load((REPO / "configs" / "dmt.yaml").read_text())
    for dotted, value in changes.items():
        *parents, last = dotted.split(".")
        node = config
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = value
    return config


def simulate_case(id: str, config: dict, key: str, *fragments: str, extra: tuple[str, ...] = ()) -> Case:
    """``afmid simulate sim.yaml -o out.h5`` refused with a config error naming ``key``."""

    def files(folder: Path) -> None:
        (folder / "sim.yaml").write_text(yaml.safe_dump(config, sort_keys=False))

    return Case(id=id, category="config", argv=("simulate", "sim.yaml", "-o", "out.h5", *extra), files=files,
                exit_code=2, file=None if key.startswith("--") else "sim.yaml", key=key, fragments=fragments)


def data_case(id: str, write, exit_code: int, key: str | None, *fragments: str, data_path: str = "trace.h5",
              file: str | None = None, **config_changes) -> Case:
    """``afmid fit run.yaml`` whose data.path is ``data_path``, written into the workspace by ``write(folder)``."""
    changes = {"data.path": data_path, "data.column": None, "data.time_column": None, **config_changes}

    def files(folder: Path) -> None:
        fit_workspace(base_config(**changes), with_trace=False)(folder)
        write(folder)

    return Case(id=id, category="data", argv=("fit", "run.yaml", "-o", "out.h5"), files=files, exit_code=exit_code,
                file=file or data_path, key=key, fragments=fragments)


def command_case(id: str, command: tuple[str, ...], write, *fragments: str, target: str = "trace.h5",
                 key: str | None = None, skip_unless=None) -> Case:
    """``afmid inspect TARGET`` or ``afmid init-config --from TARGET`` refused with an input error."""
    return Case(id=id, category="data", argv=(*command, target), files=write, exit_code=1, file=target, key=key,
                fragments=fragments, skip_unless=skip_unless)


def afmid_trace_file(path: Path) -> None:
    """A valid afmid trace file (with /truth) as afmid.io.trace.write_trace_file writes it."""
    from afmid.io.trace import Cantilever, Trace, Truth, write_trace_file

    _, x_nm = sinusoid(30)  # > 4096 samples: stored compressed in chunks
    x = x_nm * 1e-9
    truth = Truth(force=np.zeros_like(x), separation=1e-8 - x, velocity=np.gradient(x) * SAMPLE_RATE, model="dmt",
                  effects=["dmt"], parameters={"E_star": 1e9}, units={"E_star": "Pa"})
    trace = Trace(deflection=x, sample_rate=SAMPLE_RATE, cantilever=Cantilever(**CANTILEVER),
                  drive_frequency=DRIVE_FREQUENCY, truth=truth)
    write_trace_file(path, trace, "{}\n")


def damaged_trace_file(signature: bytes, occurrence: int = 0):
    """A trace file with one bit flipped in the ``occurrence``-th HDF5 structure marked ``signature``
    (b'HEAP': a group's local heap, b'TREE': a B-tree node, b'SNOD': a symbol table node)."""

    def write(folder: Path) -> None:
        path = folder / "trace.h5"
        afmid_trace_file(path)
        data = bytearray(path.read_bytes())
        offset = [m.start() for m in re.finditer(re.escape(signature), data)][occurrence]
        data[offset + 1] ^= 0x10
        path.write_bytes(bytes(data))

    return write


def damaged_truth_chunk(folder: Path) -> None:
    """A trace file whose compressed /truth/force data has bytes flipped (the deflection is intact)."""
    import h5py

    path = folder / "trace.h5"
    afmid_trace_file(path)
    with h5py.File(path, "r") as h5:
        info = h5["truth/force"].id.get_chunk_info(0)
    data = bytearray(path.read_bytes())
    for i in range(16):
        data[info.byte_offset + info.size // 2 + i] ^= 0xFF
    path.write_bytes(bytes(data))


def npy_header(shape: tuple[int, ...]) -> bytes:
    """A .npy version 1.0 header for float64 of ``shape``."""
    from numpy.lib import format as npy_format

    buffer = io.BytesIO()
    npy_format.write_array_header_1_0(buffer, {"descr": "<f8", "fortran_order": False, "shape": shape})
    return buffer.getvalue()


def lying_npy(folder: Path) -> None:
    """80 bytes of data behind a header claiming 10^12 samples."""
    (folder / "trace.npy").write_bytes(npy_header((HUGE,)) + bytes(80))


def npy_with_broken_header(folder: Path) -> None:
    """A .npy header cut off inside its dictionary (numpy's literal parser raises TokenError)."""
    header = npy_header((100,))
    broken = header.replace(b"(100,)", b"(100, ").replace(b"}", b" ")
    (folder / "trace.npy").write_bytes(broken + bytes(800))


def lying_npz(folder: Path) -> None:
    """An .npz archive whose member deflection.npy claims 10^12 samples."""
    import zipfile

    with zipfile.ZipFile(folder / "trace.npz", "w") as archive:
        archive.writestr("deflection.npy", npy_header((HUGE,)) + bytes(80))
        archive.writestr("sample_rate.npy", npy_header(()) + struct.pack("<d", SAMPLE_RATE))


def huge_hdf5_dataset(folder: Path) -> None:
    """A tiny HDF5 file declaring a 10^12-sample chunked dataset that was never written (reads as zeros)."""
    import h5py

    with h5py.File(folder / "trace.h5", "w") as h5:
        h5.attrs["sample_rate"] = SAMPLE_RATE
        ds = h5.create_dataset("deflection", shape=(HUGE,), dtype="f8", chunks=(1 << 16,))
        ds.attrs["units"] = "nm"


def huge_mat73_variable(folder: Path) -> None:
    """A MATLAB v7.3 file whose variable 'deflection' declares 10^12 values and stores none."""
    import h5py

    path = write_mat73(folder / "trace.mat", {"sample_rate": SAMPLE_RATE})
    with h5py.File(path, "r+") as h5:
        ds = h5.create_dataset("deflection", shape=(1, HUGE), dtype="f8", chunks=(1, 1 << 16))
        ds.attrs["MATLAB_class"] = np.bytes_("double")


def mat73_with_damaged_group(folder: Path) -> None:
    """A MATLAB v7.3 file (HDF5) with a struct whose local heap signature is damaged."""
    path = write_mat73(folder / "trace.mat", {"deflection": np.arange(100.0), "settings": {"gain": 2.0}})
    data = bytearray(path.read_bytes())
    offset = [m.start() for m in re.finditer(b"HEAP", data)][-1]
    data[offset + 1] ^= 0x10
    path.write_bytes(bytes(data))


def truncated_tdms(folder: Path) -> None:
    """A TDMS file cut in its data (an interrupted acquisition): npTDMS warns, then reads what is there."""
    from tests.io.test_readers import write_tdms

    _, x_nm = sinusoid(30)
    path = write_tdms(folder / "trace.tdms", {("AFM", "deflection"): (x_nm, {"wf_increment": 1 / SAMPLE_RATE,
                                                                          "unit_string": "nm"})})
    os.truncate(path, path.stat().st_size - 1001)


def nptdms_missing() -> str | None:
    try:
        import nptdms  # noqa: F401
    except ImportError:
        return "npTDMS is not installed"
    return None


def fifo(name: str):
    def write(folder: Path) -> None:
        os.mkfifo(folder / name)

    return write


def symlink_loop(name: str):
    """``name`` -> ``name``.loop -> ``name``."""

    def write(folder: Path) -> None:
        os.symlink(f"{name}.loop", folder / name)
        os.symlink(name, folder / f"{name}.loop")

    return write


def dangling_link(name: str, target: str):
    def write(folder: Path) -> None:
        os.symlink(target, folder / name)

    return write


def both(*writers):
    def write(folder: Path) -> None:
        for writer in writers:
            writer(folder)

    return write


def csv_text(text: str, name: str = "trace.csv"):
    def write(folder: Path) -> None:
        (folder / name).write_text(text)

    return write


def unreadable_available() -> str | None:
    """Skip reason unless UNREADABLE_FILE exists and cannot be opened (as on Linux, even by root)."""
    try:
        with open(UNREADABLE_FILE, "rb"):
            return f"{UNREADABLE_FILE} is readable here"
    except FileNotFoundError:
        return f"no {UNREADABLE_FILE} on this system"
    except OSError:
        return None


def etc_passwd_available() -> str | None:
    return None if Path("/etc/passwd").is_file() else "no /etc/passwd on this system"


#: A secret that must never appear in an error line.
SECRET = "hunter2-" + "s3cr3t" * 30
LONG_NAME = "deflection_" + "x" * 500


def hsdc_file(**header):
    """A NanoScope high-speed capture trace.hsdc (tests/io/test_hsdc.py) with ``header`` changes."""
    return lambda folder: write_hsdc(folder / "trace.hsdc", **header)


#: A capture's config: volts (the header's hard scale) with an invols, the rate and drive left to the header.
HSDC_CONFIG = {"data.units": None, "data.sample_rate": None, "data.invols": 5e-8, "drive.frequency": None}


# --------------------------------------------------------------------------- the cases
CASES = [
    # 1. seeds
    simulate_case("simulate-seed-option-negative", simulate_config(), "--seed", "from 0 to 4294967295",
                  extra=("--seed", "-1")),
    simulate_case("simulate-seed-option-too-large", simulate_config(), "--seed", "got '18446744073709551616'",
                  extra=("--seed", str(2**64))),
    simulate_case("simulate-seed-option-not-a-number", simulate_config(), "--seed", "got '1.5'",
                  extra=("--seed", "1.5")),
    simulate_case("simulate-seed-negative-in-config", simulate_config(**{"simulate.seed": -1}), "simulate.seed",
                  "must be >= 0, got -1"),
    fit_case("fit-seed-negative", base_config(**{"fit.seed": -3}), 2, "fit.seed", "must be >= 0, got -3"),
    # 2. simulation size against the available memory
    simulate_case("simulate-periods-beyond-memory", simulate_config(**{"simulate.periods": 10**9}),
                  "simulate.periods", "1000000000 periods x 200 samples", "this machine has"),
    simulate_case("simulate-samples-per-period-beyond-memory",
                  simulate_config(**{"simulate.samples_per_period": 1.0e9}), "simulate.samples_per_period",
                  "needs ~", "available"),
    simulate_case("simulate-sample-rate-beyond-memory", simulate_config(**{"data.sample_rate": 3.0e16}),
                  "data.sample_rate", "needs ~", "available"),
    # 3. headers that promise more than the file holds or the memory can take
    data_case("npy-header-claims-1e12-samples", lying_npy, 1, "data.path", "promises 8000000000000 bytes",
              data_path="trace.npy", **{"data.units": "m"}),
    data_case("npz-member-claims-1e12-samples", lying_npz, 1, "data.path", "'deflection' promises",
              data_path="trace.npz", **{"data.units": "m"}),
    data_case("npy-header-cut-off", npy_with_broken_header, 1, "data.path", "not a readable NumPy file",
              data_path="trace.npy", **{"data.units": "m"}),
    data_case("hdf5-dataset-beyond-memory", huge_hdf5_dataset, 1, "data.column", "'/deflection' has 1e+12 values",
              "this machine has"),
    data_case("mat73-variable-beyond-memory", huge_mat73_variable, 1, "data.column", "'deflection' has 1e+12",
              "this machine has", data_path="trace.mat", **{"data.units": "m"}),
    # 4. damaged files
    data_case("hdf5-trace-local-heap-bit-flipped", damaged_trace_file(b"HEAP"), 1, "data.path",
              "not a readable HDF5 file", "bad local heap signature"),
    data_case("hdf5-trace-btree-bit-flipped", damaged_trace_file(b"TREE", 1), 1, "data.path",
              "not a readable HDF5 file", "B-tree"),
    data_case("hdf5-trace-truth-chunk-damaged", damaged_truth_chunk, 1, "data.path", "/truth", "corrupt"),
    command_case("inspect-hdf5-symbol-table-bit-flipped", ("inspect",), damaged_trace_file(b"SNOD"),
                 "not a readable HDF5 file"),
    command_case("init-config-from-hdf5-bit-flipped", ("init-config", "--from"), damaged_trace_file(b"HEAP", 2),
                 "not a readable HDF5 file"),
    data_case("mat73-struct-heap-bit-flipped", mat73_with_damaged_group, 1, "data.path", "not a readable MATLAB file",
              data_path="trace.mat", **{"data.units": "m"}),
    data_case("hsdc-block-beyond-the-file", hsdc_file(lengths=[10**9, 16000]), 1, "data.path",
              "not a readable NanoScope HSDC file", "ends at byte", data_path="trace.hsdc", **HSDC_CONFIG),
    # Rates of 2 MHz and 250 kHz, an oscillation at 30 kHz of a declared 50 kHz drive: no rate fits.
    data_case("hsdc-no-stated-rate-fits-the-drive",
              hsdc_file(channels={"Vertical Deflection": hsdc_counts(frequency=30e3)}, channel_rate="2.5e+005"), 1,
              "data.sample_rate", "none puts the oscillation", "set data.sample_rate", data_path="trace.hsdc",
              **HSDC_CONFIG),
    command_case("inspect-hsdc-without-header-end", ("inspect",), hsdc_file(end_marker=False),
                 "not a readable NanoScope HSDC file", "no end marker", target="trace.hsdc"),
    command_case("inspect-truncated-tdms-one-line", ("inspect",), truncated_tdms, "not a readable TDMS file",
                 target="trace.tdms", skip_unless=nptdms_missing),
    # 5. FIFOs and devices are never opened
    Case(id="config-is-a-fifo", category="config", argv=("fit", "run.yaml", "-o", "out.h5"), files=fifo("run.yaml"),
         exit_code=2, file="run.yaml", key=None, fragments=("not a regular file (a FIFO)",)),
    data_case("trace-is-a-fifo", fifo("trace.csv"), 1, "data.path", "not a regular file (a FIFO)",
              data_path="trace.csv"),
    command_case("inspect-a-fifo", ("inspect",), fifo("trace.csv"), "not a regular file (a FIFO)",
                 target="trace.csv"),
    command_case("init-config-from-a-fifo", ("init-config", "--from"), fifo("trace.csv"),
                 "not a regular file (a FIFO)", target="trace.csv"),
    data_case("trace-is-dev-zero", lambda folder: None, 1, "data.path", "not a regular file (a character device)",
              data_path="/dev/zero", **{"data.format": "npy"}),
    # 6. symbolic links
    Case(id="config-symlink-loop", category="config", argv=("fit", "run.yaml", "-o", "out.h5"),
         files=symlink_loop("run.yaml"), exit_code=2, file="run.yaml", key=None, fragments=("symbolic link loop",)),
    data_case("trace-symlink-loop", symlink_loop("trace.csv"), 1, "data.path", "symbolic link loop",
              data_path="trace.csv"),
    data_case("trace-dangling-symlink", dangling_link("trace.csv", "moved/trace.csv"), 1, "data.path",
              "link to missing file moved/trace.csv", data_path="trace.csv"),
    command_case("inspect-symlink-loop", ("inspect",), symlink_loop("trace.h5"), "symbolic link loop"),
    Case(id="config-dangling-symlink", category="config", argv=("fit", "run.yaml", "-o", "out.h5"),
         files=dangling_link("run.yaml", "old/run.yaml"), exit_code=2, file="run.yaml", key=None,
         fragments=("link to missing file old/run.yaml",)),
    # 7. no content of files that are not data
    Case(id="data-path-etc-passwd", category="data", argv=("fit", "run.yaml", "-o", "out.h5"),
         files=fit_workspace(base_config(**{"data.path": "/etc/passwd", "data.format": "csv"}), with_trace=False),
         exit_code=1, file="/etc/passwd", key="data.path", fragments=("not a table of numbers",),
         skip_unless=etc_passwd_available),
    data_case("csv-secret-in-a-number-column",
              csv_text("time_s,deflection_nm\n0,1\n1e-8,2\n2e-8," + SECRET + "\n"), 1, "data.column",
              "column 'deflection_nm'", "not a number at row 3", data_path="trace.csv",
              **{"data.column": "deflection_nm", "data.time_column": "time_s"}),
    data_case("csv-header-name-of-500-characters", csv_text(f"time_s,{LONG_NAME}\n0,1\n1e-8,2\n"), 1,
              "data.column", "no channel 'deflection_nm'", data_path="trace.csv",
              **{"data.column": "deflection_nm"}),
    data_case("csv-header-with-terminal-escape", csv_text("time_s,\x1b]0;owned\x07\x1b[2Jdeflection\n0,1\n1e-8,2\n"),
              1, "data.column", "available: time_s, ?]0;owned??[2Jdeflection", data_path="trace.csv",
              **{"data.column": "deflection_nm"}),
    # 8. unreadable files and binary configs
    command_case("inspect-unreadable-even-by-root", ("inspect",), lambda folder: None,
                 "cannot open the file: Permission denied", target=UNREADABLE_FILE, key="data.path",
                 skip_unless=unreadable_available),
    Case(id="config-unreadable-even-by-root", category="config", argv=("fit", UNREADABLE_FILE, "-o", "out.h5"),
         files=lambda folder: None, exit_code=2, file=UNREADABLE_FILE, key=None,
         fragments=("cannot open the config file: Permission denied",), skip_unless=unreadable_available),
    Case(id="config-utf16", category="config", argv=("fit", "run.yaml", "-o", "out.h5"),
         files=lambda folder: (folder / "run.yaml").write_bytes("data:\n  path: t.csv\n".encode("utf-16")),
         exit_code=2, file="run.yaml", key=None, fragments=("byte 0xff at offset 0 is not UTF-8",)),
    # special files as outputs: never replaced, even with --overwrite
    Case(id="output-is-a-fifo", category="output", argv=("init-config", "-o", "out.yaml", "--overwrite"),
         files=fifo("out.yaml"), exit_code=1, file="out.yaml", key=None,
         fragments=("not a regular file (a FIFO)",)),
    Case(id="simulate-output-is-a-fifo", category="output",
         argv=("simulate", "sim.yaml", "-o", "out.h5", "--overwrite"),
         files=both(fifo("out.h5"), lambda folder: (folder / "sim.yaml").write_text(
             yaml.safe_dump(simulate_config()))),
         exit_code=1, file="out.h5", key=None, fragments=("not a regular file (a FIFO)",)),
]

#: Text the error line of a case must not contain: file content that is not the user's to see there.
NOT_ECHOED = {
    "data-path-etc-passwd": ("root:", "/bin/", "nologin"),
    "csv-secret-in-a-number-column": ("s3cr3ts3cr3ts3cr3t",),
    "csv-header-name-of-500-characters": ("x" * 61,),
    "csv-header-with-terminal-escape": ("\x1b", "\x07"),
}


@corpus_params(CASES)
def test_crashes_case(case, tmp_path, capsys, monkeypatch):
    line = check_case(case, tmp_path / "ws", capsys, monkeypatch)
    for text in NOT_ECHOED.get(case.id, ()):
        assert text not in line, f"the error line echoes file content {text!r}: {line!r}"
