"""The chunk's drive frequency of the shared pixel fit (afmid.maps.pixel_fit.SharedSupportFit.start_chunk) and the
blocks and test functions its pixels share (afmid.fit.prepare.prepare(layouts=...)).

- Sharing is bookkeeping only: a record prepared with a layouts dict at a given drive is the same, bit for bit, as
  one prepared without it at that drive, and a second record of the same layout gets the very same objects.
- harmonics.drive_at at the measured frequency is the measurement's own amplitude, phase and offset (the same
  least-squares product, so the same bits).
- The chunk's frequency is the median of its pixels' measured ones, and a pixel cut at it is one whose own lies
  within DRIVE_AGREEMENT robust sigmas of their scatter; a pixel further off keeps its own.

Map: tests/configs/map_small.yaml (3x3: a glassy matrix and a soft domain 1 nm higher), simulator seed 7.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from small_map import simulated_pixels


@pytest.fixture(scope="module")
def small_map(tmp_path_factory):
    """(config, library, [trace]) of the small map."""
    return simulated_pixels(tmp_path_factory.mktemp("chunk_drive"))


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
    return a == b


def test_shared_layouts_give_the_same_bits(small_map):
    from afmid.fit.prepare import prepare
    from afmid.preprocess.harmonics import drive_at
    from afmid.preprocess.instrument import from_config
    from afmid.preprocess.periods import detrend

    config, _, traces = small_map
    first, second = traces[0], traces[1]
    x, _ = detrend(second.deflection, second.times, config.fit.detrend)
    common = drive_at(x, second.times, second.drive_frequency, first.drive_for(config.fit.detrend).frequency)
    layouts: dict = {}
    prepare(first, config.fit, from_config(config), layouts=layouts)
    shared = prepare(second, config.fit, from_config(config), drive=common, layouts=layouts)
    alone = prepare(second, config.fit, from_config(config), drive=common)
    assert shared.blocks is next(iter(layouts.values()))[0]  # the first record's blocks, not new ones
    assert shared.windows is next(iter(layouts.values()))[1]
    for f in dataclasses.fields(alone):
        if f.name in ("trace", "blocks", "windows", "drive", "motion", "fine_grid", "removed"):
            continue
        if f.name == "before_instrument":  # it holds the blocks and windows compared below; its samples here
            for part in ("settings", "t", "x"):
                assert _same(getattr(shared.before_instrument, part), getattr(alone.before_instrument, part)), part
            continue
        assert _same(getattr(shared, f.name), getattr(alone, f.name)), f.name
    for f in dataclasses.fields(alone.blocks):
        assert _same(getattr(shared.blocks, f.name), getattr(alone.blocks, f.name)), f.name
    for f in dataclasses.fields(alone.windows):
        assert _same(getattr(shared.windows, f.name), getattr(alone.windows, f.name)), f.name


def test_drive_at_the_measured_frequency_is_the_measurement(small_map):
    from afmid.preprocess.harmonics import drive_at, estimate_drive
    from afmid.preprocess.periods import detrend

    config, _, traces = small_map
    trace = traces[4]
    x, _ = detrend(trace.deflection, trace.times, config.fit.detrend)
    measured = estimate_drive(x, trace.times, trace.drive_frequency)
    assert drive_at(x, trace.times, trace.drive_frequency, measured.frequency) == measured


def test_chunk_frequency_is_the_median_and_an_outlier_keeps_its_own(small_map):
    from afmid.maps.pixel_fit import DRIVE_AGREEMENT, SharedSupportFit

    config, library, traces = small_map
    strategy = SharedSupportFit(config, library)
    strategy.start_chunk(traces)
    own = np.array([t.drive_for(config.fit.detrend).frequency for t in traces])
    assert strategy.drive_frequency == np.median(own)
    spread = strategy.drive_spread
    assert spread == pytest.approx(1.4826 * np.median(np.abs(own - np.median(own))), rel=1e-12)
    for trace, f in zip(traces, own):
        drive = strategy.chunk_drive(trace)
        if abs(f - strategy.drive_frequency) <= DRIVE_AGREEMENT * spread:
            assert drive is not None and drive.frequency == strategy.drive_frequency
        else:
            assert drive is None
    # An outlier: the chunk's frequency moved far from every pixel's own (as a pixel far off it would be).
    strategy.drive_frequency = float(own.max() + 10 * DRIVE_AGREEMENT * spread)
    assert all(strategy.chunk_drive(trace) is None for trace in traces)
    # Too few measured pixels for a scatter: each pixel its own.
    strategy.start_chunk(traces[:2])
    assert strategy.drive_frequency is None and all(strategy.chunk_drive(trace) is None for trace in traces)
