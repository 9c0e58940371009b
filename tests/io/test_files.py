"""afmid.io.files: the checks every input file passes, the memory guard, and what a message may quote of a file."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import numpy as np
import pytest

from afmid.errors import ConfigError, InputError, OutputError
from afmid.io.files import (
    available_memory,
    check_input_file,
    check_output_target,
    format_bytes,
    memory_shortfall,
    safe_excerpt,
)
from afmid.io.readers import read_trace
from afmid.io.readers.base import check_array_size, listing
from repo_paths import REPO_ROOT


def message_of(path, **kwargs) -> str:
    with pytest.raises(InputError) as info:
        check_input_file(path, **kwargs)
    assert info.value.file == str(path)
    return info.value.message


def test_a_regular_file_passes_and_is_returned_as_a_path(tmp_path):
    path = tmp_path / "trace.csv"
    path.write_text("1\n")
    assert check_input_file(str(path)) == path


def test_missing_file_dangling_link_and_missing_folder(tmp_path):
    assert message_of(tmp_path / "nope.csv", what="trace file") == "trace file not found"
    (tmp_path / "link.csv").symlink_to("elsewhere/trace.csv")
    assert message_of(tmp_path / "link.csv") == "symbolic link to missing file elsewhere/trace.csv"
    assert "the folder" in message_of(tmp_path / "no-such-folder" / "trace.csv")


def test_symbolic_link_loop_is_not_reported_as_missing(tmp_path):
    (tmp_path / "a").symlink_to("b")
    (tmp_path / "b").symlink_to("a")
    assert message_of(tmp_path / "a").startswith("symbolic link loop")


def test_folder_fifo_socket_and_device_are_refused_without_being_opened(tmp_path):
    assert message_of(tmp_path, what="config file") == "is a directory (folder), not a config file"
    os.mkfifo(tmp_path / "pipe")
    assert message_of(tmp_path / "pipe").startswith("not a regular file (a FIFO)")  # would block if opened
    with socket.socket(socket.AF_UNIX) as server:
        server.bind(str(tmp_path / "sock"))
        assert message_of(tmp_path / "sock").startswith("not a regular file (a socket)")
    assert message_of(Path("/dev/zero")).startswith("not a regular file (a character device)")


def test_empty_files_only_where_allowed(tmp_path):
    path = tmp_path / "empty.yaml"
    path.write_bytes(b"")
    assert message_of(path, what="trace file") == "the trace file is empty (0 bytes)"
    assert check_input_file(path, allow_empty=True) == path


def test_error_class_and_key_are_the_callers(tmp_path):
    with pytest.raises(ConfigError) as info:
        check_input_file(tmp_path / "run.yaml", what="config file", error=ConfigError, key="--config")
    assert info.value.exit_code == 2 and info.value.key == "--config"


@pytest.mark.skipif(not Path("/proc/sys/vm/compact_memory").exists(), reason="needs Linux procfs")
def test_a_file_even_root_cannot_open():
    # Write-only sysctl: open() for reading fails with EACCES, also for root (unlike chmod 000).
    assert message_of(Path("/proc/sys/vm/compact_memory")).startswith("cannot open the file: Permission denied")


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads files whatever their mode")
def test_chmod_000(tmp_path):
    path = tmp_path / "locked.csv"
    path.write_text("1\n")
    path.chmod(0)
    assert "Permission denied" in message_of(path)


def test_special_outputs_are_refused(tmp_path):
    os.mkfifo(tmp_path / "out.h5")
    with pytest.raises(OutputError, match=r"not a regular file \(a FIFO\)"):
        check_output_target(tmp_path / "out.h5")
    with pytest.raises(OutputError, match="character device"):
        check_output_target("/dev/null")
    check_output_target(tmp_path / "new.h5")  # missing: fine
    (tmp_path / "old.h5").write_bytes(b"x")
    check_output_target(tmp_path / "old.h5")  # a regular file: the --overwrite rules apply


def test_safe_excerpt_is_short_printable_ascii():
    assert safe_excerpt("deflection [nm]") == "deflection [nm]"
    assert safe_excerpt("a\x1b[31mb\nc\u00e9") == "a?[31mb?c?"
    cut = safe_excerpt("x" * 500)
    assert len(cut) == 60 and cut.endswith("...")
    assert safe_excerpt("abcdef", limit=5) == "ab..."


def test_channel_listings_are_sanitised_and_bounded():
    names = ["ok", "bad\x07name", "y" * 200] + [f"c{i}" for i in range(40)]
    shown = listing(names)
    assert "bad?name" in shown and "y" * 61 not in shown and len(shown) < 400
    assert shown.endswith("more)")


def test_memory_shortfall_and_sizes():
    available = available_memory()
    assert available is None or available > 0
    assert memory_shortfall(1) is None
    if available is not None:
        problem = memory_shortfall(10 * available)
        assert problem.startswith("needs ~") and problem.endswith("available")
    assert format_bytes(2.5e9) == "2.5 GB" and format_bytes(512) == "512 B"


def test_array_size_is_checked_before_reading(tmp_path):
    check_array_size((1000,), np.float32, file=tmp_path / "f", channel="x")
    with pytest.raises(InputError, match=r"channel 'x' has 1e\+12 values .*needs ~"):
        check_array_size((10**6, 10**6), np.float64, file=tmp_path / "f", channel="x")


def test_npy_whose_data_really_is_too_large_is_refused_without_reading(tmp_path):
    """A consistent header over a sparse 800 GB file: refused for memory, not as corrupt, and never read."""
    from numpy.lib import format as npy_format

    path = tmp_path / "huge.npy"
    with open(path, "wb") as fh:
        npy_format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False, "shape": (10**11,)})
        fh.truncate(fh.tell() + 8 * 10**11)
    with pytest.raises(InputError, match="this machine has") as info:
        read_trace(path)
    assert info.value.key == "data.column"


def test_csv_of_something_else_is_refused_without_quoting_it(tmp_path):
    path = tmp_path / "accounts.csv"
    path.write_text("root:x:0:0:root:/root:/bin/bash\ndaemon:x:1:1:daemon:/usr/sbin:/usr/sbin/nologin\n")
    with pytest.raises(InputError) as info:
        read_trace(path)
    assert "not a table of numbers" in info.value.message and "bash" not in str(info.value)


def test_csv_too_large_for_the_memory_is_refused_before_parsing(tmp_path):
    """A sparse 1 TB CSV: the row count estimated from the first rows says it cannot fit; np.loadtxt never runs."""
    path = tmp_path / "huge.csv"
    with open(path, "wb") as fh:
        fh.write(b"time_s,deflection_nm\n" + b"".join(b"%d,%d\n" % (i, i % 7) for i in range(20000)))
        fh.truncate(10**12)  # zeros past the first 64 kB, which is all the encoding probe reads
    with pytest.raises(InputError, match="this machine has") as info:
        read_trace(path, channel="deflection_nm")
    assert info.value.key == "data.column" and "'deflection_nm'" in info.value.message


def test_igor_wave_file_too_large_for_the_memory_is_refused_before_loading(tmp_path):
    pytest.importorskip("igor2")
    from tests.io.test_readers import write_ibw5

    path = write_ibw5(tmp_path / "huge.ibw", np.arange(10.0))
    os.truncate(path, 10**12)
    with pytest.raises(InputError, match="this machine has") as info:
        read_trace(path)
    assert info.value.key == "data.path"


def test_simulation_sized_before_integrating_names_the_key_too_large():
    """steps_per_period only allocates the thermal forces of one chunk, but 10^12 steps cannot fit either."""
    import yaml

    from afmid.config import build_config
    from afmid.simulate.driver import check_memory, compile_force_law, output_grid, resolve_setup

    raw = yaml.safe_load((REPO_ROOT / "configs" / "dmt.yaml").read_text())
    config = build_config(raw)
    setup = resolve_setup(config)
    n_gates = compile_force_law(setup.force_law).n_gates
    check_memory(config, output_grid(config, setup.oscillator), setup.oscillator, n_gates)  # the example fits
    raw["simulate"]["steps_per_period"] = 10**12
    config = build_config(raw)
    with pytest.raises(ConfigError, match="needs ~") as info:
        check_memory(config, output_grid(config, setup.oscillator), setup.oscillator, n_gates)
    assert info.value.key == "simulate.steps_per_period"
    raw["simulate"]["noise"]["thermal"] = False  # no random forces: only the recorded samples count
    config = build_config(raw)
    check_memory(config, output_grid(config, setup.oscillator), setup.oscillator, n_gates)
