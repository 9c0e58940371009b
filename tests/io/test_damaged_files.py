"""Damaged data files: whatever bytes are flipped or cut, a reader answers with data or one InputError.

Each valid file (every format afmid reads, including an afmid trace file) is
damaged in a fixed set of ways (seeded bit flips near the start, where the
headers are, and anywhere; truncation), and read with read_trace and
list_channels. Anything but an InputError escaping is a crash the user would
see as a traceback.
"""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import pytest

from afmid.errors import InputError
from afmid.io.readers import list_channels, read_trace
from tests.io.test_hsdc import write_hsdc
from tests.io.test_readers import SIGNAL, write_afmid_trace, write_ibw5, write_mat73, write_tdms

DAMAGES_PER_FILE = 60


def _npz(path: Path) -> Path:
    np.savez(path, deflection=SIGNAL, sample_rate=2e6)
    return path


def _npz_compressed(path: Path) -> Path:
    np.savez_compressed(path, deflection=SIGNAL, time=np.arange(SIGNAL.size) / 2e6)
    return path


def _npy(path: Path) -> Path:
    np.save(path, SIGNAL)
    return path


def _mat(path: Path) -> Path:
    from scipy.io import savemat

    savemat(path, {"deflection": SIGNAL, "sample_rate": 2e6, "settings": {"gain": 2.0}}, do_compression=True)
    return path


BUILDERS = {
    "trace.npz": _npz,
    "compressed.npz": _npz_compressed,
    "trace.npy": _npy,
    "trace.mat": _mat,
    "v73.mat": lambda path: write_mat73(path, {"deflection": SIGNAL, "settings": {"gain": 2.0}}),
    "trace.h5": write_afmid_trace,
    "trace.ibw": lambda path: write_ibw5(path, SIGNAL, step=5e-7, data_units=b"m", x_units=b"s"),
    "trace.tdms": lambda path: write_tdms(path, {("AFM", "deflection"): (SIGNAL, {"wf_increment": 5e-7})}),
    # A short header (bit flips near the start hit it) and contradicting rates (the flips may hit the drive, the
    # rates or the block positions the resolution depends on).
    "trace.hsdc": lambda path: write_hsdc(path, channel_rate="2.5e+005", header_size=1280),
}


def damaged(original: bytes, seed: int) -> bytes:
    """``original`` with a few bits flipped (near the start for odd seeds) or, every fifth seed, cut short."""
    rnd = random.Random(seed)
    data = bytearray(original)
    if seed % 5 == 4:
        return bytes(data[: rnd.randrange(1, len(data))])
    start = rnd.randrange(0, min(len(data) - 16, 1200)) if seed % 2 else rnd.randrange(0, len(data) - 16)
    for _ in range(6):
        data[start + rnd.randrange(16)] ^= 1 << rnd.randrange(8)
    return bytes(data)


@pytest.mark.parametrize("name", list(BUILDERS))
def test_damaged_files_give_data_or_one_input_error(tmp_path, name):
    if name.endswith((".ibw", ".tdms")):
        pytest.importorskip("igor2" if name.endswith(".ibw") else "nptdms")
    original = BUILDERS[name](tmp_path / name).read_bytes()
    path = tmp_path / f"damaged-{name}"
    refused = 0
    for seed in range(DAMAGES_PER_FILE):
        path.write_bytes(damaged(original, seed))
        for read in (read_trace, list_channels):
            try:
                read(path)
            except InputError as exc:
                refused += 1
                assert exc.file == str(path) and "\n" not in str(exc) and len(str(exc)) < 500, str(exc)
    assert refused > 0, "no damage was detected at all: the test damages nothing"
