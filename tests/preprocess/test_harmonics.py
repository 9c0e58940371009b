"""The harmonic-analysis engine (afmid.preprocess.harmonics), and the drive measured once: on loading, reused by the fit."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

import afmid.preprocess.harmonics as harmonics
from afmid.config import load_config
from afmid.fit.prepare import prepare
from afmid.io.trace import Cantilever, Trace, load_trace
from afmid.preprocess.periods import detrend

# floating-point results compared; blas_sensitive: make test-kernels runs these again (BLAS/LAPACK on the path)
pytestmark = [pytest.mark.numerics, pytest.mark.blas_sensitive]

F_DRIVE = 300e3  # Hz
SPP = 200  # samples per period
FS = F_DRIVE * SPP


def _long_trace(periods=40, seed=3, detune=2.3e-4) -> Trace:
    """A synthetic tapping deflection (Trace) with harmonics, detector noise and a slow thermal-like wander."""
    rng = np.random.default_rng(seed)
    n = periods * SPP + 37  # partial periods at the ends
    t = np.arange(n) / FS
    w = 2 * np.pi * F_DRIVE * (1 + detune)
    wander = 1 + 1e-3 * np.sin(2 * np.pi * t / t[-1])
    x = (9.4e-9 * wander * np.cos(w * t) + 0.15e-9 * np.cos(2 * w * t + 0.3) + 0.05e-9 * np.cos(3 * w * t)
         + 1e-12 * rng.standard_normal(n))
    return Trace(deflection=x, sample_rate=FS, cantilever=Cantilever(40.0, 300e3, 250.0, 10e-9),
                 drive_frequency=F_DRIVE)


def test_windowed_power_from_block_moments_equals_the_direct_sum():
    rng = np.random.default_rng(2)
    n = 50_003
    t = np.arange(n) / FS
    x = 1e-8 * np.cos(2 * np.pi * 300_017.3 * t + 0.4) + 1e-11 * rng.standard_normal(n)
    np.testing.assert_allclose(harmonics.hann_weighted(x, 0.1e-9), np.hanning(n) * (x - 0.1e-9), rtol=1e-14,
                               atol=1e-30)
    df = FS / n
    power = harmonics.WindowedPower(harmonics.hann_weighted(x), t, 300_000.0, 2 * df, block=512)
    for f in 300_000.0 + df * np.array([-2.0, -0.7, 0.0, 0.3, 1.5, 2.0]):
        direct = float(np.abs(np.dot(np.hanning(n) * x, np.exp(-2j * np.pi * f * t))) ** 2)
        assert power(f) == pytest.approx(direct, rel=1e-11)


@pytest.mark.parametrize("detune", [-4e-4, 1.3e-4])
def test_long_trace_drive_and_frequency_estimates_agree_with_the_padded_ones(monkeypatch, detune):
    """Above EXACT_SPECTRUM_MAX samples: no zero padding, the search on block moments; same estimate."""
    trace = _long_trace(periods=400, detune=detune)
    x, t = trace.deflection, trace.times
    exact = harmonics.estimate_drive(x, t, F_DRIVE)
    f_exact = harmonics.measure_frequency(x)
    monkeypatch.setattr(harmonics, "EXACT_SPECTRUM_MAX", 1000)
    monkeypatch.setattr(harmonics, "SAMPLE_CHUNK", 4096)
    fast = harmonics.estimate_drive(x, t, F_DRIVE)
    assert fast.frequency == pytest.approx(exact.frequency, rel=3e-9)
    assert fast.frequency == pytest.approx(F_DRIVE * (1 + detune), rel=1e-7)
    assert fast.amplitude == pytest.approx(exact.amplitude, rel=1e-12)
    assert fast.phase == pytest.approx(exact.phase, abs=3e-5)
    assert fast.offset == pytest.approx(exact.offset, abs=1e-8 * exact.amplitude)
    assert harmonics.strongest_peak(x).long
    assert harmonics.measure_frequency(x) == pytest.approx(f_exact, rel=3e-8)
    with pytest.raises(Exception, match="outside the sampled band"):
        harmonics.estimate_drive(x, t, 0.6 * FS)
    with pytest.raises(Exception, match="constant"):
        harmonics.estimate_drive(np.full(x.size, 1e-9), t, F_DRIVE)
    assert harmonics.measure_frequency(np.full(x.size, 1e-9)) is None


def test_both_searches_find_the_same_oscillation():
    """The strongest oscillation (cycles per sample) and the drive near the nominal one (Hz) agree."""
    trace = _long_trace(detune=2.3e-4)
    drive = harmonics.estimate_drive(trace.deflection, trace.times, F_DRIVE)
    strongest = harmonics.measure_frequency(trace.deflection) * FS
    assert drive.frequency == pytest.approx(F_DRIVE * (1 + 2.3e-4), rel=1e-7)
    assert strongest == pytest.approx(drive.frequency, rel=1e-7)


def test_the_projector_inverts_the_design():
    design = harmonics.fourier_design(np.arange(97, dtype=float), 2 * np.pi / 96.6, 40)
    np.testing.assert_allclose(harmonics.least_squares_projector(design) @ design, np.eye(81), atol=1e-10)


@pytest.fixture
def loaded(tmp_path):
    """``loaded(x, **fit)`` -> (Trace loaded from an .npy with fit settings ``fit``, its config)."""

    def run(x, **fit):
        np.save(tmp_path / "trace.npy", x)
        config = {
            "data": {"path": "trace.npy", "units": "m", "sample_rate": FS},
            "cantilever": {"spring_constant": 40.0, "resonance_frequency": 300e3, "quality_factor": 250.0,
                           "tip_radius": 10e-9},
            "drive": {"frequency": F_DRIVE},
            "fit": fit,
        }
        (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
        config = load_config(tmp_path / "run.yaml")
        return load_trace(config), config

    return run


@pytest.mark.parametrize("mode", ["none", "offset", "linear"])
def test_the_drive_is_measured_on_loading_as_the_fit_measures_it_and_reused(loaded, mode):
    x = _long_trace(detune=2.3e-3).deflection + 0.3e-9  # off nominal by 0.23 %, and an offset
    trace, config = loaded(x, detrend=mode, baseline="free")
    estimate = trace.drive_for(mode)
    t = trace.times
    expected = harmonics.estimate_drive(detrend(trace.deflection, t, mode)[0], t, F_DRIVE)
    assert estimate == expected  # the same number, bit for bit
    assert prepare(trace, config.fit).drive is estimate  # reused, not measured again
    # The defect checks analysed the trace at that frequency (and report it: 0.23 % from the nominal).
    (finding,) = [f for f in trace.findings if f.name == "drive_frequency"]
    assert finding.severity == "repaired" and finding.numbers["measured"] == estimate.frequency


def test_the_fit_measures_the_drive_itself_when_the_loaded_one_does_not_apply(loaded):
    trace, config = loaded(_long_trace().deflection + 0.3e-9)
    assert trace.drive_for("none") is not None
    assert trace.drive_for("linear") is None  # other samples (detrended otherwise): another measurement
    other = dataclasses.replace(trace, deflection=trace.deflection[::-1].copy())
    assert other.drive_for("none") is None  # other samples
    renamed = dataclasses.replace(trace, drive_frequency=F_DRIVE * 1.01)
    assert renamed.drive_for("none") is None  # another nominal frequency: another search band
    fit = config.fit.model_copy(update={"detrend": "linear"})
    t = trace.times
    measured = harmonics.estimate_drive(detrend(trace.deflection, t, "linear")[0], t, F_DRIVE)
    assert prepare(trace, fit).drive == measured
    assert prepare(other, config.fit).drive == harmonics.estimate_drive(other.deflection, t, F_DRIVE)


def test_a_trace_made_in_memory_has_no_loaded_drive():
    trace = _long_trace()
    assert trace.drive is None and trace.drive_for("none") is None


@pytest.mark.parametrize("K", [1, 7, 8, 9, 17, 60, 61])
def test_harmonic_cos_sin_agrees_with_direct_evaluation_to_the_rounding_of_the_argument(K):
    # The direct cos(n phase) carries the rounding of its argument n phase (half an ulp of it) and the
    # library's own ~1 ulp; the angle addition adds a few ulp of 1. Tolerance: 4 ulp of the largest argument
    # plus 8 ulp of 1 (fixed before comparing).
    phase = np.random.default_rng(K).uniform(-40.0, 40.0, 997)
    cos_n, sin_n = harmonics.harmonic_cos_sin(phase, K)
    n = np.arange(1, K + 1)[:, None]
    tolerance = 4 * np.spacing(np.abs(n * phase).max()) + 8 * np.spacing(1.0)
    assert cos_n.shape == sin_n.shape == (K, phase.size)
    assert np.abs(cos_n - np.cos(n * phase)).max() <= tolerance
    assert np.abs(sin_n - np.sin(n * phase)).max() <= tolerance
    # into strided outputs (the designs' interleaved columns): the same values
    design = np.empty((phase.size, 2 * K + 1))
    harmonics.harmonic_cos_sin(phase, K, out_cos=design[:, 1::2].T, out_sin=design[:, 2::2].T)
    assert np.array_equal(design[:, 1::2].T, cos_n) and np.array_equal(design[:, 2::2].T, sin_n)


# --------------------------------------------------------------------------- per-period curves at the drive's phase
def _two_harmonic_motion(t: np.ndarray, omega: float) -> np.ndarray:
    """10 nm at the drive frequency and 3 nm at twice it (m), a phase that is not a multiple of pi/2."""
    return 10e-9 * np.cos(omega * t + 0.7) + 3e-9 * np.sin(2 * omega * t - 0.2)


@pytest.mark.parametrize("relative_offset", [3.4e-5, -1.0e-4])
def test_per_period_curves_follow_the_drive_when_the_blocks_were_cut_at_another_frequency(relative_offset):
    """The fit's drive may be the nominal frequency while the blocks were cut at the one measured on loading
    (thermal wander moved it by 3.4e-5: 10 Hz at 300 kHz). The curve of period i must be the motion at the drive's
    times (2 pi i + phase) / w_drive. Scale, from the arithmetic: a block fits a sinusoid whose frequency differs by
    the relative offset eps from its basis, so its phase runs about +-pi eps off across the block: a misfit of
    ~pi eps (10 nm + 2 x 3 nm) (harmonic 2 runs twice as fast), 1.7e-12 m at eps 3.4e-5 (the least-squares fit
    leaves up to about twice that at the block ends): tolerance 3 pi |eps| 16 nm. Evaluating the blocks' series at
    the phase alone (the old curves) drifts by 2 pi eps per period: ~1.2e-10 m at the last of 40 periods."""
    periods = 40
    omega_drive = 2 * np.pi * F_DRIVE
    t = np.arange(periods * SPP) / FS
    x = _two_harmonic_motion(t, omega_drive)
    from afmid.preprocess.periods import harmonic_blocks
    blocks = harmonic_blocks(t.size, FS, F_DRIVE * (1 + relative_offset), max_harmonic=8)
    series = blocks.project(x)
    phase = 2 * np.pi * np.arange(64) / 64
    cycles = np.floor(blocks.block_times() * omega_drive / (2 * np.pi))
    curves = blocks.evaluate_in_periods(series, phase, cycles, omega_drive)[..., 0]
    truth = _two_harmonic_motion((2 * np.pi * cycles[:, None] + phase[None, :]) / omega_drive, omega_drive)
    tolerance = 3 * np.pi * abs(relative_offset) * 16e-9
    assert np.max(np.abs(curves - truth)) < tolerance
    old = blocks.evaluate(series, phase)[..., 0]
    assert np.max(np.abs(old[-1] - truth[-1])) > 10 * tolerance  # the drift this replaces, so the test can fail


def test_per_period_curves_at_the_blocks_own_frequency_are_the_plain_evaluation_bit_for_bit():
    """Equal frequencies: no turn (cos 0 = 1, sin 0 = 0 exactly) and the same phase grid, so the same bits."""
    t = np.arange(12 * SPP) / FS
    from afmid.preprocess.periods import harmonic_blocks
    blocks = harmonic_blocks(t.size, FS, F_DRIVE, max_harmonic=8)
    series = blocks.project(_two_harmonic_motion(t, 2 * np.pi * F_DRIVE * (1 + 2e-4)))
    phase = 2 * np.pi * np.arange(64) / 64
    cycles = np.floor(blocks.block_times() * blocks.omega / (2 * np.pi))
    assert np.array_equal(blocks.evaluate_in_periods(series, phase, cycles, blocks.omega), blocks.evaluate(series, phase))
