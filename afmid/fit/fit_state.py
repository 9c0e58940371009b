"""One chosen support's fit while its read-outs are finished: the one object the finishing steps take.

Every fit (a single trace, a joint fit of several, a map pixel) ends the same way: the coefficients of the chosen
support are read out as physical quantities, and then steps widen their error bars (the separation's sigma, the
calibration), flag them (model-limited, not determined, undecided, unphysical) and add warning lines. Those steps
read the same dozen things (the prepared trace, the library, the system, the coefficients, the support, the
parameters, ...) and change two (``quantities``, ``warnings``): :class:`FitState` holds them, so that a step takes
the state instead of a dozen arguments, and what it changes is visible on one object.

Units: SI throughout (coefficients such that coefficient x term = N, parameters in m, Pa, ...).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from afmid.fit.forces import read_out

if TYPE_CHECKING:  # annotations only
    from afmid.config import RunConfig
    from afmid.fit.prepare import Prepared
    from afmid.io.trace import Trace
    from afmid.physics.library import Library


@dataclass
class FitState:
    """A fit of one support, from its read-out on (SI).

    ``system`` is the fit's regression system (a trace's :class:`afmid.fit.system.System`, or the stacked system
    of a joint fit: the finishing steps read its ``T_blocks``, ``theta``, ``n_rows``); ``prep`` and ``params`` are
    those of the trace the read-outs are evaluated on (a joint fit's first trace). ``mask`` is the support over
    all columns (library, then nuisance); ``inclusion`` per column the fraction of resamples that select it (the
    support itself when nothing was resampled). ``quantities`` (name -> read-out dict, as
    :func:`afmid.fit.forces.read_out` makes them) and ``warnings`` (lines) are changed in place by the steps;
    ``cv_error`` and ``noise_floor`` are the cross-validated error and its floor (relative); ``model_limited``
    and ``force_calibration`` (the force's relative calibration uncertainty, 1 sigma) are set by the steps.
    """

    config: RunConfig
    prep: Prepared
    library: Library
    system: Any
    coef: np.ndarray
    mask: np.ndarray
    params: dict
    quantities: dict
    warnings: list[str]
    inclusion: np.ndarray
    cv_error: float = math.nan
    noise_floor: float = math.nan
    floor_dof: float = math.nan  # the floor's effective degrees of freedom (afmid.fit.uncertainty.floor_threshold)
    model_limited: bool = False
    force_calibration: float = 0.0
    #: read-out steps that ran, in order (their ``name``): what the state went through
    steps: list[str] = field(default_factory=list)

    @property
    def trace(self) -> Trace:
        return self.prep.trace

    def read(self, coef: np.ndarray, params: dict | None = None, mask: np.ndarray | None = None) -> dict[str, dict]:
        """The read-outs of coefficients ``coef`` (no intervals), at ``params`` and with support ``mask`` (the
        state's own when None): :func:`afmid.fit.forces.read_out`."""
        return read_out(self.library, coef, None, self.params if params is None else params,
                        self.mask if mask is None else mask, self.trace)

    def warn(self, line: str) -> None:
        """Append a warning line (``warning: `` + ``line``)."""
        self.warnings.append("warning: " + line)
