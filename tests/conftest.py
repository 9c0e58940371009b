"""Shared fixtures: small synthetic inputs and a way to run the CLI in-process.

Kept generic on purpose: a sinusoidal deflection written as a CSV, a run
config written as YAML, an in-memory :class:`afmid.io.trace.Trace` with ground
truth, and ``run_cli`` which calls :func:`afmid.cli.main` and captures its
output. Every CLI call reconfigures the ``afmid`` logger; the autouse fixture
puts it back so tests do not depend on their order.
"""

from __future__ import annotations

import logging
from pathlib import Path

from afmid.threads import limit_native_threads

# As the CLI does: one BLAS / OpenMP / numba thread, set before NumPy loads.
limit_native_threads()

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import yaml  # noqa: E402

#: Drive frequency and sample rate of the synthetic traces (200 samples per period, as the template).
DRIVE_FREQUENCY = 3.0e5  # Hz
SAMPLE_RATE = 6.0e7  # Hz
AMPLITUDE_NM = 5.0  # nm
CANTILEVER = {"spring_constant": 40.0, "resonance_frequency": 3.0e5, "quality_factor": 150.0, "tip_radius": 10e-9}


def sinusoid(periods: float = 10, samples_per_period: float = SAMPLE_RATE / DRIVE_FREQUENCY):
    """(time in s, deflection in nm) of a pure drive-frequency sinusoid."""
    rate = samples_per_period * DRIVE_FREQUENCY
    n = int(round(periods * samples_per_period))
    t = np.arange(n) / rate
    return t, AMPLITUDE_NM * np.sin(2 * np.pi * DRIVE_FREQUENCY * t)


@pytest.fixture
def write_csv(tmp_path):
    """``write_csv(name, periods=10, samples_per_period=200, time=True, values=None)`` -> path.

    Columns ``time_s`` (optional) and ``deflection_nm``; ``values`` replaces the
    sinusoid (any sequence, written with ``repr``-exact floats or as given if str).
    """

    def write(name="trace.csv", periods=10, samples_per_period=SAMPLE_RATE / DRIVE_FREQUENCY, time=True, values=None):
        t, x = sinusoid(periods, samples_per_period)
        if values is not None:
            x = list(values)
            t = np.arange(len(x)) / (samples_per_period * DRIVE_FREQUENCY)
        lines = ["time_s,deflection_nm" if time else "deflection_nm"]
        for ti, xi in zip(t, x):
            value = xi if isinstance(xi, str) else repr(float(xi))
            lines.append(f"{float(ti)!r},{value}" if time else value)
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines) + "\n")
        return path

    return write


def _pinned_config(data_path="trace.csv", **sections) -> dict:
    config = {
        "data": {
            "path": str(data_path),
            "format": "auto",
            "column": "deflection_nm",
            "time_column": "time_s",
            "sample_rate": SAMPLE_RATE,
            "units": "nm",
            "positive": "toward_sample",
        },
        "cantilever": dict(CANTILEVER),
        "drive": {"frequency": DRIVE_FREQUENCY},
        "sample": {"a0": 0.165e-9},
        "model": {"effects": ["dmt"]},
        "fit": {},
    }
    config.update(sections)
    return config


@pytest.fixture
def pinned_config():
    """``pinned_config(data_path='trace.csv', **sections)`` -> a run config mapping in the pinned form
    matching :func:`write_csv` traces; ``sections`` replace whole sections."""
    return _pinned_config


@pytest.fixture
def write_config(tmp_path):
    """``write_config(mapping_or_text, name='run.yaml')`` -> path of the YAML file."""

    def write(content, name="run.yaml"):
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        text = content if isinstance(content, str) else yaml.safe_dump(content, sort_keys=False)
        path.write_text(text)
        return path

    return write


@pytest.fixture
def make_trace():
    """``make_trace(periods=10, with_truth=True)`` -> an in-memory Trace (SI) with a sinusoid and ground truth."""
    from afmid.io.trace import Cantilever, Trace, Truth

    def make(periods=10, with_truth=True):
        t, x_nm = sinusoid(periods)
        x = x_nm * 1e-9
        separation = 8e-9
        truth = None
        if with_truth:
            truth = Truth(
                force=np.where(separation - x < 0.165e-9, 1e-9, -1e-10),
                separation=separation - x,
                velocity=np.gradient(x, t),
                model="dmt",
                effects=["dmt"],
                parameters={"E_star": 2.0e9, "hamaker": 5.0e-20},
                units={"E_star": "Pa", "hamaker": "J"},
                extra={"separation": separation, "free_amplitude": 10e-9},
            )
        return Trace(
            deflection=x,
            sample_rate=SAMPLE_RATE,
            cantilever=Cantilever(**CANTILEVER),
            drive_frequency=DRIVE_FREQUENCY,
            time=t,
            truth=truth,
            drive_force_amplitude=2e-10,
        )

    return make


@pytest.fixture
def run_cli(capsys):
    """``run_cli(*args)`` -> (exit code, stdout, stderr) of ``afmid args...`` run in-process."""
    from afmid.cli import main

    def run(*args):
        capsys.readouterr()  # drop anything printed before
        code = main([str(a) for a in args])
        out, err = capsys.readouterr()
        return code, out, err

    return run


@pytest.fixture(autouse=True, scope="session")
def _diagnosis_cache_of_the_session(tmp_path_factory):
    """afmid report keeps diagnoses in a cache folder (afmid.diagnosis.stored): the tests use their own, so a test
    run never reuses the diagnoses of an earlier run or fills the user's ~/.cache."""
    import os

    os.environ["AFMID_DIAGNOSIS_CACHE"] = str(tmp_path_factory.mktemp("diagnosis_cache"))


@pytest.fixture(autouse=True)
def _restore_afmid_logging():
    """The CLI replaces the 'afmid' logger's handler and stops propagation; undo it after each test."""
    from afmid.cli import _state

    logger = logging.getLogger("afmid")
    saved = (list(logger.handlers), logger.level, logger.propagate, dict(_state))
    yield
    logger.handlers[:], logger.level, logger.propagate = saved[0], saved[1], saved[2]
    _state.clear()
    _state.update(saved[3])
    logging.captureWarnings(False)


@pytest.fixture
def temp_leftovers():
    """``temp_leftovers(folder)`` -> names of the temporary files an interrupted or refused write left behind."""

    def leftovers(folder: Path) -> list[str]:
        folder = Path(folder)
        if not folder.is_dir():
            return []
        return sorted(p.name for p in folder.iterdir() if p.name.startswith(".afmid-tmp-"))

    return leftovers


def _check_svg_beside_every_png(out: Path) -> None:
    """Every figure of a report folder is also an SVG (same stem) that parses as XML with an <svg> root, is
    listed in the folder's marker and is linked from the page (issue 15, pinned)."""
    import xml.etree.ElementTree as ElementTree

    from afmid.report.folder import read_marker

    pngs = sorted(out.glob("*.png"))
    svgs = sorted(out.glob("*.svg"))
    assert pngs and [p.stem for p in svgs] == [p.stem for p in pngs]
    listed = read_marker(out)["files"]
    page = (out / "report.html").read_text(encoding="utf-8")
    for svg in svgs:
        root = ElementTree.parse(svg).getroot()
        assert root.tag == "{http://www.w3.org/2000/svg}svg", (svg.name, root.tag)
        assert float(root.get("width").removesuffix("pt")) > 0 and float(root.get("height").removesuffix("pt")) > 0
        assert svg.name in listed
        assert f'href="{svg.name}"' in page


@pytest.fixture
def check_report_svgs():
    """The check that a report folder has an SVG beside every PNG (afmid report, run and map reports)."""
    return _check_svg_beside_every_png
