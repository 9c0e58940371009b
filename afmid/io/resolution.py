"""Detector resolution: a trace recorded with too few ADC levels across its swing.

A deflection that takes only a few distinct values (an 8-bit ADC, or a 16-bit one at a gain that uses a few
of its codes) carries quantization noise of step/sqrt(12) rms, correlated with the motion rather than white,
which the fit's noise model does not describe: its forces and read-outs are then limited by the ADC, not by
the physics (a 1 nm step on a 9 nm amplitude gave E* = -270 GPa). The check counts the distinct sample
values; afmid warns, since the user may still want the fit, and the read-outs are checked for plausibility.
"""

from __future__ import annotations

import numpy as np

from afmid.io.findings import Finding, length

#: Fewer distinct values than this across the trace's swing (8 bits) is a coarse recording.
MIN_LEVELS = 256


def check_quantization(x: np.ndarray) -> list[Finding]:
    """A warning when the deflection ``x`` (m) uses fewer than MIN_LEVELS distinct values across its range."""
    x = np.asarray(x, dtype=np.float64)
    if x.size < 4 * MIN_LEVELS:
        return []
    levels = np.unique(x)
    if levels.size >= MIN_LEVELS or levels.size < 2:
        return []  # finely resolved (a float trace has ~one value per sample), or constant (another check's)
    step = float(np.min(np.diff(levels)))
    swing = float(levels[-1] - levels[0])
    message = (f"the deflection takes only {levels.size} distinct values across its {length(swing)} swing "
               f"(ADC step {length(step)}, quantization noise {length(step / np.sqrt(12))} rms): forces and "
               f"read-outs are limited by the detector's resolution; record with more ADC bits or gain")
    return [Finding("quantization", "warning", message, "data.path",
                    {"levels": int(levels.size), "step": step, "swing": swing})]
