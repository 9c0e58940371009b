"""Simulation-based calibration of afmid's error bars (``afmid coverage``).

Draw experiments from a declared distribution around a run config (:mod:`afmid.sections.coverage`,
:mod:`afmid.coverage.draws`), simulate each with :func:`afmid.simulate.driver.simulate`, fit it with
:func:`afmid.fit.pipeline.run_fit` as the config says (the separation estimated), compare every read-out, the
separation and the force curve with the simulation's truth (:mod:`afmid.coverage.compare`), and count how often
the truth lies within 1 and 2 reported sigma (:mod:`afmid.coverage.summary`). :func:`run_coverage` (in
:mod:`afmid.coverage.run`) does all of it; ``afmid coverage`` is its command line.

The ``coverage:`` section's schema is :mod:`afmid.sections.coverage` (the run config's layer, read by
:mod:`afmid.config`).
"""

from __future__ import annotations


def __getattr__(name: str):
    """``afmid.coverage.run_coverage`` and ``CoverageResult`` without importing the engine with the package."""
    if name in ("run_coverage", "CoverageResult"):
        import afmid.coverage.run as run

        return getattr(run, name)
    raise AttributeError(f"module 'afmid.coverage' has no attribute {name!r}")
