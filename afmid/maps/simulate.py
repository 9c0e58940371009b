"""A simulated force map (``simulate.map``, :mod:`afmid.sections.map_simulation`): a trace per pixel over a sample of phases.

Each pixel is simulated by :func:`afmid.simulate.driver.simulate` with its phase's parameters (merged over
``simulate.parameters``), its rest separation ``sample.separation - height`` and its own seed
(``simulate.seed + pixel``); the file holds ``/deflection`` (rows, cols, samples) and the ground truth:
``/truth/phase`` (index into ``/truth/phase_names``), ``/truth/separation`` and ``/truth/NAME`` for each
parameter of the model (SI, ``units`` on every dataset).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from afmid.errors import ConfigError

log = logging.getLogger(__name__)

MAP_FORMAT = "afmid-map"


def phase_map(spec) -> np.ndarray:
    """Index of the phase at each pixel (rows, cols): the matrix (0), then each round domain drawn over it."""
    y, x = np.mgrid[0:spec.rows, 0:spec.cols] * spec.pixel_size
    phase = np.zeros((spec.rows, spec.cols), dtype=np.int16)
    for k, p in enumerate(spec.phases[1:], start=1):
        inside = (x - p.center[0]) ** 2 + (y - p.center[1]) ** 2 <= p.radius ** 2
        phase[inside] = k
    return phase


def simulate_map(config, progress: bool = False) -> dict:
    """Simulate every pixel; returns ``{"deflection", "truth": {name: (map, unit)}, "phase", "sample_rate",
    "cantilever", "drive_frequency", "x", "y"}`` (SI)."""
    from afmid.simulate.driver import simulate

    spec = config.simulate.map
    if config.simulate.setpoint is not None:
        raise ConfigError("a map is simulated at sample.separation minus each phase's height, not at a setpoint; "
                          "remove simulate.setpoint", file=config.source, key="simulate.setpoint")
    if config.sample.separation is None:
        raise ConfigError("required for a map: the rest separation over a phase of height 0 (m)",
                          file=config.source, key="sample.separation")
    phase = phase_map(spec)
    base_params = dict(config.simulate.parameters)
    base_d, base_seed = config.sample.separation, config.simulate.seed
    names = sorted(set(base_params).union(*(p.parameters for p in spec.phases)))
    truth = {name: np.full(phase.shape, np.nan) for name in names}
    separation = np.empty(phase.shape)
    traces = None
    first = None
    try:
        for r in range(spec.rows):
            for c in range(spec.cols):
                p = spec.phases[phase[r, c]]
                params = dict(base_params, **p.parameters)
                config.simulate.parameters = params
                config.sample.separation = base_d - p.height
                config.simulate.seed = (base_seed + r * spec.cols + c) % (2**32)
                trace = simulate(config)
                if traces is None:
                    first = trace
                    traces = np.empty((spec.rows, spec.cols, trace.n_samples))
                traces[r, c] = trace.deflection
                separation[r, c] = config.sample.separation
                for name in names:
                    truth[name][r, c] = trace.truth.parameters.get(name, params.get(name, np.nan))
            if progress:
                log.info("simulated row %d of %d", r + 1, spec.rows)
    finally:
        config.simulate.parameters, config.sample.separation, config.simulate.seed = base_params, base_d, base_seed
    units = dict(first.truth.units)
    missing = [name for name in names if name not in units]
    if missing:  # a phase parameter the model does not have: the simulator would have ignored it
        raise ConfigError(f"not a parameter of simulate.model {config.simulate.model!r}: {', '.join(missing)}",
                          file=config.source, key="simulate.map.phases")
    out_truth = {name: (truth[name], units[name]) for name in names}
    out_truth["separation"] = (separation, "m")
    return {"deflection": traces, "truth": out_truth, "phase": phase, "phase_names": [p.name for p in spec.phases],
            "sample_rate": first.sample_rate, "cantilever": first.cantilever, "drive_frequency": first.drive_frequency,
            "x": np.arange(spec.cols) * spec.pixel_size, "y": np.arange(spec.rows) * spec.pixel_size}


def write_map_file(path: str | Path, simulated: dict, config_text: str, overwrite: bool = False) -> Path:
    """Write a map file readable by ``afmid map --input`` (with the ground truth under /truth)."""
    from afmid.io.trace import atomic_hdf5, check_output_path, write_dataset

    path = check_output_path(path, overwrite)
    cl = simulated["cantilever"]
    with atomic_hdf5(path, MAP_FORMAT, config_text) as h5:
        h5.attrs["sample_rate"] = float(simulated["sample_rate"])
        h5.attrs["drive_frequency"] = float(simulated["drive_frequency"])
        h5.attrs["spring_constant"] = cl.spring_constant
        h5.attrs["resonance_frequency"] = cl.resonance_frequency
        h5.attrs["quality_factor"] = cl.quality_factor
        h5.attrs["tip_radius"] = np.nan if cl.tip_radius is None else cl.tip_radius
        h5.attrs["units_of_attributes"] = ("sample_rate: Hz; drive_frequency: Hz; spring_constant: N/m; "
                                           "resonance_frequency: Hz; quality_factor: 1; tip_radius: m")
        write_dataset(h5, "deflection", simulated["deflection"], "m", positive="toward_sample")
        write_dataset(h5, "x", simulated["x"], "m")
        write_dataset(h5, "y", simulated["y"], "m")
        tg = h5.create_group("truth")
        write_dataset(tg, "phase", simulated["phase"], "1", meaning="index into /truth/phase_names")
        write_dataset(tg, "phase_names", np.array(simulated["phase_names"]), "1")
        for name, (values, unit) in simulated["truth"].items():
            write_dataset(tg, name, values, unit)
    return path
