"""A trace's chunks shared among threads (afmid.threads.map_in_order) give the one-thread fit bit for bit.

Each chunk's computation is the same whichever thread runs it, and the chunks' results are combined in chunk order,
so nothing may differ, not even in the last bit: the fit is compared field by field with exact equality.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from afmid.threads import TRACE_THREADS_ENV, map_in_order, trace_threads
from repo_paths import REPO_ROOT

#: Periods per chunk in this test (the fit's defaults are 256 and 2,048): 60 periods become 8 chunks.
SMALL_CHUNK = 8


@pytest.fixture(scope="module")
def dmt_trace_file(tmp_path_factory):
    """A 60-period simulated DMT trace (configs/dmt.yaml, noise on), as a trace file."""
    from afmid.config import dump_config, load_config
    from afmid.io.trace import write_trace_file
    from afmid.simulate.driver import simulate

    config = load_config(REPO_ROOT / "configs" / "dmt.yaml", ["simulate.periods=60"])
    path = tmp_path_factory.mktemp("threads") / "dmt_60.h5"
    return write_trace_file(path, simulate(config), dump_config(config))


def _fit(path, threads: int, monkeypatch):
    import afmid.fit.forces as forces
    import afmid.fit.prepare as prepare
    import afmid.fit.system as system
    import afmid.preprocess.periods as periods
    from afmid.config import load_config
    from afmid.fit.pipeline import run_fit

    monkeypatch.setenv(TRACE_THREADS_ENV, str(threads))
    for module in (forces, prepare, system, periods):
        monkeypatch.setattr(module, "CHUNK_BLOCKS", SMALL_CHUNK)
    monkeypatch.setattr(forces, "PERIOD_CHUNK", SMALL_CHUNK)
    assert trace_threads() == threads
    config = load_config(REPO_ROOT / "configs" / "dmt.yaml", [f"data.path={path}", "fit.bootstrap=10"])
    return run_fit(config)


def _assert_identical(a, b, where: str) -> None:
    if isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=where, strict=True)
    elif isinstance(a, float):
        assert a == b or (math.isnan(a) and math.isnan(b)), f"{where}: {a!r} != {b!r}"
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            _assert_identical(a[key], b[key], f"{where}[{key}]")


def test_two_threads_fit_the_same_bits_as_one(dmt_trace_file, monkeypatch):
    one = _fit(dmt_trace_file, 1, monkeypatch)
    two = _fit(dmt_trace_file, 2, monkeypatch)
    assert one.prep.blocks.n_blocks > 4 * SMALL_CHUNK  # several chunks to share out
    assert one.selected_terms() == two.selected_terms()
    for field in ("coef", "coef_std", "ci_low", "ci_high", "inclusion", "cv_error", "cv_error_folds",
                  "force_estimate", "force_inverted", "force_statistical_uncertainty", "force_selection_uncertainty",
                  "quantities"):
        _assert_identical(getattr(one, field), getattr(two, field), field)
    _assert_identical(dict(one.periods), dict(two.periods), "periods")
    for f in dataclasses.fields(one.prep):  # the preparation (chunked projections, weak-form rows, row noise)
        _assert_identical(getattr(one.prep, f.name), getattr(two.prep, f.name), f"prep.{f.name}")
    _assert_identical(one.system.theta, two.system.theta, "system.theta")
    assert one.prep.drive.frequency == two.prep.drive.frequency


def test_map_in_order_keeps_the_order_and_runs_every_item():
    def slow_square(i: int) -> int:
        # the first items take longest, so with two threads later items finish first
        sum(range((20 - i) * 20_000))
        return i * i

    assert map_in_order(slow_square, range(20), threads=2) == [i * i for i in range(20)]
    assert map_in_order(slow_square, [], threads=2) == []
    assert map_in_order(slow_square, [3], threads=2) == [9]


def test_trace_threads_reads_the_environment(monkeypatch):
    monkeypatch.setenv(TRACE_THREADS_ENV, "1")
    assert trace_threads() == 1
    monkeypatch.setenv(TRACE_THREADS_ENV, "3")
    assert trace_threads() == 3
    monkeypatch.delenv(TRACE_THREADS_ENV)
    assert 1 <= trace_threads() <= 2


def test_regressor_noise_without_the_velocity_is_the_same_bits(dmt_trace_file):
    """The regressor-noise pass synthesises only x when no kept term reads a velocity (DMT); the pass over the kept
    fine grid (x and xdot) gives the same row weights bit for bit. A velocity-reading library is recognised."""
    import afmid.fit.prepare as prepare
    import afmid.fit.regression as regression
    from afmid.config import ModelConfig, load_config
    from afmid.fit.pipeline import library_parameters
    from afmid.fit.system import build_system
    from afmid.fit.prepare import prepare as prepare_trace
    from afmid.io.trace import load_trace
    from afmid.physics.library import build_library

    config = load_config(REPO_ROOT / "configs" / "dmt.yaml", [f"data.path={dmt_trace_file}"])
    prep = prepare_trace(load_trace(config), config.fit)
    library = build_library(ModelConfig(effects=["dmt"]))
    assert not library.reads_velocity()
    assert build_library(ModelConfig(effects=["viscoelastic"])).reads_velocity()
    params = dict(library_parameters(prep, config, library), d=config.sample.separation)
    system = build_system(prep, library, params)
    coef, _ = regression.subset_fit(regression.combine(system.T_blocks), np.ones(system.protected.size, bool))
    x_only = prepare.with_regressor_noise(prep, library, params, coef)
    with_grid = prepare.with_regressor_noise(prepare.with_fine_grid(prep), library, params, coef)
    assert prepare.with_fine_grid(prep).fine_grid is not None  # the other path was taken
    np.testing.assert_array_equal(x_only.row_sigma, with_grid.row_sigma, strict=True)
