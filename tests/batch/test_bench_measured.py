"""bench/common.py's ``measured``: the wall time, CPU and peak memory `make bench`'s report rows are built on
(issue 31's peak-RSS and CPU columns), and the table's unit for a memory row."""

from __future__ import annotations

import os
import sys

import pytest

from repo_paths import REPO_ROOT

sys.path.insert(0, str(REPO_ROOT / "bench"))

from common import measured  # noqa: E402
from run_all import table  # noqa: E402

ALLOCATE_MB = 400
# A child that touches ALLOCATE_MB of fresh memory (every page written), then spins for CPU_S of CPU time.
CHILD = f"""
import time
block = bytearray({ALLOCATE_MB} * 2**20)
for i in range(0, len(block), 4096):
    block[i] = 1
start = time.process_time()
while time.process_time() - start < 0.5:
    pass
"""


def test_measured_counts_the_childs_memory_and_cpu():
    got = measured([sys.executable, "-c", CHILD])
    # Peak RSS: the block plus the interpreter (~10-30 MB); the kernel counts in kB pages, so the block's
    # 400 MiB = 0.419 GB is a lower bound, and 0.419 + 0.1 GB a generous upper one.
    assert ALLOCATE_MB * 2**20 / 1e9 <= got["rss_gb"] <= ALLOCATE_MB * 2**20 / 1e9 + 0.1
    # CPU: the 0.5 s spin plus start-up and page faults (<< 1 s); wall >= CPU for one thread.
    assert 0.5 <= got["cpu"] <= 0.5 + 1.5
    assert got["wall"] >= 0.5 and got["code"] == 0
    # The other processes' cores: at least 0 and at most the machine's (the sum of ticks over all its cores).
    assert 0.0 <= got["others_cores"] <= os.cpu_count(), got


def test_measured_raises_on_failure_unless_the_code_is_allowed():
    fail = [sys.executable, "-c", "import sys; sys.stderr.write('broken input'); sys.exit(1)"]
    with pytest.raises(RuntimeError, match="broken input"):
        measured(fail)
    assert measured(fail, ok_codes=(0, 1))["code"] == 1


def test_a_memory_row_is_shown_in_its_unit():
    rows = [{"name": "peak", "afmid_s": 0.734, "reference_s": None, "ratio": None, "target": "<= 2 GB", "met": True,
             "unit": "GB"},
            {"name": "time", "afmid_s": 21.9, "reference_s": 28.0, "ratio": 1.28, "target": "", "met": None}]
    text = table(rows)
    assert "| peak | 0.73 GB | - | - | <= 2 GB | yes |" in text
    assert "| time | 21.90 s | 28.00 s | 1.28x |  | - |" in text
