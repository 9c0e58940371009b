"""Facts of a record's sampling kept per process (every pixel of a map has the same length, sample rate and drive):
the Hann window, the drive line's band and floor bins, the harmonics' basis of the force-shape analysis. Kept
values must be those a record computes afresh, read-only (a caller cannot change the next record's), and keyed by
every fact they depend on."""

from __future__ import annotations

import numpy as np
import pytest

from afmid.io import oscillation, trace_analysis
from afmid.preprocess.harmonics import CACHED_WINDOW_MAX, DRIVE_SEARCH, hann_window


def test_the_kept_hann_window_is_numpys_and_read_only():
    window = hann_window(9984)
    assert window.tobytes() == np.hanning(9984).tobytes()
    assert hann_window(9984) is window and not window.flags.writeable
    with pytest.raises(ValueError):
        window[0] = 1.0
    assert hann_window(CACHED_WINDOW_MAX + 1) is not hann_window(CACHED_WINDOW_MAX + 1)  # long records: not kept


def test_the_harmonics_basis_is_the_phase_grids_cos_and_sin():
    phase, cos, sin = trace_analysis._phase_basis(7)
    grid = np.linspace(0.0, 2 * np.pi, trace_analysis.PHASE_POINTS, endpoint=False)
    arg = np.outer(grid, np.arange(1, 8))
    assert phase.tobytes() == grid.tobytes()
    assert cos.tobytes() == np.cos(arg).tobytes() and sin.tobytes() == np.sin(arg).tobytes()
    assert not (phase.flags.writeable or cos.flags.writeable or sin.flags.writeable)
    assert trace_analysis._phase_basis(9)[1].shape == (trace_analysis.PHASE_POINTS, 9)


def _record(n: int, cycles_per_sample: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.cos(2 * np.pi * cycles_per_sample * np.arange(n)) + 0.05 * rng.standard_normal(n)


@pytest.mark.parametrize("other", [dict(sample_rate=20e6), dict(nominal=150e3), dict(search=0.2)])
def test_the_drive_line_bins_are_keyed_by_every_fact_of_the_sampling(other):
    """A record judged after another of the same length but another sample rate, drive or search band gets its
    own bins: the same ratio, threshold and bin counts as with nothing kept."""
    facts = dict(sample_rate=38.4e6, nominal=300e3, search=DRIVE_SEARCH)
    x = _record(9984, 300e3 / 38.4e6, 1)
    oscillation._line_and_floor_bins.cache_clear()
    fresh = oscillation.drive_line_test(x, **facts)
    changed = dict(facts, **other)
    oscillation.drive_line_test(_record(9984, changed["nominal"] / changed["sample_rate"], 2), **changed)
    assert oscillation.drive_line_test(x, **facts) == fresh
    oscillation._line_and_floor_bins.cache_clear()
    assert oscillation.drive_line_test(x, **changed) != fresh  # the other facts do give other bins here
