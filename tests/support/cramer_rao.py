"""The Cramér-Rao bound of the rest separation on a steady simulated record, independent of afmid's estimator.

The record's information about d (issue 13: is afmid's sigma of d what the record allows, or does its estimator
throw information away?). A steady record is the noise-free periodic response plus noise; its sufficient
statistics for the force law are the Fourier coefficients of the whole record at the drive harmonics (the
record-mean period's spectrum), each with an independent Gaussian noise per cos / sin part:

- the detector noise, white: 2 sigma_det^2 / N per part (N samples);
- the thermal deflection: the thermal force (one-sided PSD 4 kB T c) through the free lever's compliance
  |H(f)|^2 over the record length T (the thermal force drives the tapping lever; its linear response is the
  free lever's, the same approximation as scripts/separation_budget.py's ``--information``).

The Fisher matrix of the parameters theta (the rest separation, every force-law parameter of
``simulate.parameters`` and the drive's amplitude and phase, which afmid fits) is
``F_ij = sum_n Re(dc_n/dtheta_i conj(dc_n/dtheta_j)) / var_n`` from central differences of noise-free
simulations (the drive phase: a time shift of the steady response, dc_n/dphi = i n c_n). The bound of d is
``sqrt(inv(F)[d, d])``: no unbiased estimator of d from this record does better. It is linear: it holds where
the response is smooth in d over the bound (a 2 GPa DMT sample at 1-10 pm detector noise: the steps below are
10x smaller than the bound). SI units throughout.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Central-difference steps: the separation in m, the force-law parameters and the drive amplitude relative.
SEPARATION_STEP = 2e-12
RELATIVE_STEP = 0.005


@dataclass(frozen=True)
class SeparationBound:
    """The Cramér-Rao bound of d (m, 1 sigma) on one record, with the drive fitted and with it known."""

    sigma: float  # every force-law parameter and the drive's amplitude and phase unknown (what afmid fits)
    sigma_drive_known: float  # the drive's amplitude and phase known
    parameters: tuple[str, ...]  # the rows of the Fisher matrix
    fisher: np.ndarray


def _noise_free(raw: dict) -> dict:
    quiet = copy.deepcopy(raw)
    quiet["simulate"]["noise"].update(thermal=False, detector_rms=0.0)
    return quiet


def _harmonic_variance(raw: dict, trace, config) -> np.ndarray:
    """Noise variance (m^2) of each cos / sin part of the record-mean period's Fourier coefficients."""
    from afmid.physics.effects import BOLTZMANN
    from afmid.preprocess.instrument import from_config

    noise = raw["simulate"]["noise"]
    sigma = float(noise.get("detector_rms", 0.0))
    temperature = float(noise.get("temperature", 300.0))
    spp = int(raw["simulate"]["samples_per_period"])
    periods = trace.deflection.size // spp
    n_samples, duration = periods * spp, periods * spp / trace.sample_rate
    f = np.arange(spp // 2 + 1) * trace.drive_frequency
    cl = trace.cantilever
    k, f0, Q = cl.spring_constant, cl.resonance_frequency, cl.quality_factor
    compliance = 1.0 / (k * (1 - (f / f0) ** 2 + 1j * f / (Q * f0)))
    detector = from_config(config).detector
    gain = np.ones(f.size) if detector is None else np.abs(detector.response(f))
    force_psd = 4 * BOLTZMANN * temperature * k / (Q * 2 * math.pi * f0) if noise.get("thermal", True) else 0.0
    variance = 2 * sigma**2 / n_samples + force_psd * np.abs(compliance * gain) ** 2 / duration
    variance[0] *= 0.5  # the mean: one real coefficient
    return variance


def mean_period_spectrum(deflection: np.ndarray, samples_per_period: int) -> np.ndarray:
    """Complex Fourier coefficients (m) of the record-mean period: c_0 the mean, c_n (n >= 1) the amplitude
    of harmonic n (|c_n| = its amplitude)."""
    periods = deflection.size // samples_per_period
    mean_period = deflection[:periods * samples_per_period].reshape(periods, samples_per_period).mean(axis=0)
    c = np.fft.rfft(mean_period) / samples_per_period
    c[1:] *= 2
    return c


def separation_bound(raw: dict, base_dir: Path) -> SeparationBound:
    """The Cramér-Rao bound of the rest separation on the record ``raw`` (a simulation config with
    ``sample.separation`` and ``simulate.parameters``) simulates."""
    from afmid.config import build_config
    from afmid.simulate.driver import simulate

    quiet = _noise_free(raw)
    spp = int(raw["simulate"]["samples_per_period"])

    def spectrum(change) -> np.ndarray:
        alt = copy.deepcopy(quiet)
        change(alt)
        return mean_period_spectrum(simulate(build_config(alt, source=base_dir / "x.yaml",
                                                          base_dir=base_dir)).deflection, spp)

    config = build_config(quiet, source=base_dir / "x.yaml", base_dir=base_dir)
    truth = simulate(config)
    variance = _harmonic_variance(raw, truth, config)
    c = mean_period_spectrum(truth.deflection, spp)
    d = float(raw["sample"]["separation"])

    def setter(section: str, key: str, value: float):
        def change(alt):
            alt[section][key] = value
        return change

    def law(key: str, value: float):
        def change(alt):
            alt["simulate"]["parameters"][key] = value
        return change

    names, derivatives = ["d"], []
    derivatives.append((spectrum(setter("sample", "separation", d + SEPARATION_STEP))
                        - spectrum(setter("sample", "separation", d - SEPARATION_STEP))) / (2 * SEPARATION_STEP))
    for key, value in raw["simulate"]["parameters"].items():
        value = float(value)
        h = RELATIVE_STEP * value  # per unit relative change: dc / (dtheta / theta)
        derivatives.append((spectrum(law(key, value + h)) - spectrum(law(key, value - h))) / (2 * RELATIVE_STEP))
        names.append(key)
    amplitude = float(raw["drive"]["free_amplitude"])
    h = RELATIVE_STEP * amplitude
    derivatives.append((spectrum(setter("drive", "free_amplitude", amplitude + h))
                        - spectrum(setter("drive", "free_amplitude", amplitude - h))) / (2 * RELATIVE_STEP))
    derivatives.append(1j * np.arange(c.size) * c)  # the drive's phase (rad): a time shift of the response
    names += ["drive_amplitude", "drive_phase"]
    J = np.array(derivatives)  # (parameters, harmonics), complex
    fisher = np.real(J @ (np.conj(J) / variance).T)
    law_only = len(names) - 2
    return SeparationBound(float(math.sqrt(np.linalg.inv(fisher)[0, 0])),
                           float(math.sqrt(np.linalg.inv(fisher[:law_only, :law_only])[0, 0])),
                           tuple(names), fisher)
