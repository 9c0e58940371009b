"""Compile the default model's generated kernels ahead of the first fit: ``python -m afmid.fit.warm``.

:mod:`afmid.kernels.warm` compiles the kernels every fit runs whatever its force law. A fit also runs kernels
generated for its library's structure (:mod:`afmid.kernels.termgen`, :mod:`afmid.kernels.lawgen`), which the
kernels layer cannot build: it knows no effects. This module builds them for the model a config without a
``model`` section fits (``model.effects: [dmt]``, a spherical tip, in air; ``make demo``'s first fit is that model)
and calls them with the argument types and layouts the fit passes, so that numba's on-disk cache holds them:

* the library's term kernel (``eval_rows``, one signature given ahead, and ``stiffness_squares``, the
  regressor-noise pass: C-contiguous rows as :mod:`afmid.fit.prepare` passes them);
* the contact-law probe's library (the library plus :func:`afmid.fit.contact_probe.probe_expressions` of the
  elastic term's power): its term kernel;
* the information bound's integration kernel for the law of all the library's terms (a fit whose support holds
  every term of the default model, as the demo's does), run for a few steps through
  :class:`afmid.simulate.integrator.Integrator` as the bound's steady states run it.

Parameter values are not part of a generated kernel (they are passed at run time), so the values used here do not
matter; the structure does: another model, tip or support compiles its own kernels on its first fit, as before.
The command runs :func:`afmid.kernels.warm.warm` first (``make venv`` runs it once; bench/README.md "Cold start").
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from afmid.config import ModelConfig, SampleConfig
from afmid.fit.contact_probe import elastic_power, probe_expressions
from afmid.physics.effects import ForceLaw
from afmid.physics.library import Library, build_library
from afmid.physics.medium import relative_permittivity
from afmid.physics.tips import SPHERE
from afmid.simulate.integrator import Integrator
from afmid.simulate.model import Oscillator, compile_force_law

#: A representative stiff tapping lever (N/m, Hz, Q) and tip radius (m): values only, the kernels do not depend on them.
_LEVER = (40.0, 3.0e5, 250.0)
_TIP_RADIUS = 10e-9
_SEPARATION = 10e-9  # m
#: Integration steps run on the law kernel: enough to pass through its code once (compiling does not depend on it).
_STEPS = 16


def default_library() -> tuple[Library, dict]:
    """The library a config without a ``model`` section fits and parameters (SI) as the fit passes them
    (:func:`afmid.fit.pipeline.library_parameters`' keys, the separation ``d`` included)."""
    sample = SampleConfig()
    library = build_library(ModelConfig(), None, SPHERE)
    params = {"a0": sample.a0, "w": 2.0 * math.pi * _LEVER[1], "eps_r": relative_permittivity(sample),
              "R": _TIP_RADIUS, **library.nonlinear, "d": _SEPARATION}
    return library, params


def _rows(n_rows: int = 2, n: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Trajectory rows (x m, xdot m/s, t s), C-contiguous (rows, n): the tip swings into contact and out."""
    t = np.ascontiguousarray(np.tile(np.linspace(0.0, 1.0 / _LEVER[1], n), (n_rows, 1)))
    x = 12e-9 * np.cos(2.0 * math.pi * _LEVER[1] * t)
    return np.ascontiguousarray(x), np.ascontiguousarray(np.gradient(x, axis=1)), t


def _term_kernel(library: Library, params: dict) -> None:
    kernel = library.term_kernel(params)
    if kernel is None:  # a library the VM evaluates: nothing generated to compile
        return
    x, xdot, t = _rows()
    out = np.empty((x.shape[1], x.shape[0], len(library))).transpose(1, 0, 2)  # sample-major, as the weak form's
    kernel.eval_rows(x, xdot, t, params["d"], params["a0"], out)
    kernel.stiffness_squares(np.ones(len(library)), x, xdot, t, params["d"], params["a0"], 1e-12)


def _library() -> None:
    _term_kernel(*default_library())


def _contact_probe() -> None:
    library, params = default_library()
    found = elastic_power(library, np.ones(len(library), dtype=bool))
    if found is None:
        return
    probed = build_library(ModelConfig(terms=list(probe_expressions(found[1]))), None, library.tip)
    _term_kernel(probed, params)


def _information_bound() -> None:
    library, params = default_library()
    # every term in the support, as fit_bound builds the law of the selected ones (coefficients: any values)
    terms = tuple((term.effect or "fit", term.name, term.expression, 1.0) for term in library.terms)
    law = ForceLaw(tuple(library.effects), {k: float(v) for k, v in params.items() if k != "d"}, terms,
                   tuple(library.states))
    oscillator = Oscillator(*_LEVER, _LEVER[1], 1e-9)
    integrator = Integrator(oscillator, compile_force_law(law), params["d"])
    integrator.start(*oscillator.free_state(0.0))
    integrator.run(0.0, oscillator.period / _STEPS, _STEPS, 1)


#: name -> the function that compiles those kernels (in the order a fit first calls them)
KERNELS = {"library": _library, "contact_probe": _contact_probe, "information_bound": _information_bound}


def warm_default_model(names=None, stream=None) -> dict[str, float]:
    """Compile (or load from numba's cache) the default model's generated kernels of ``names`` (default: all of
    :data:`KERNELS`); returns the seconds each took (a compilation ~0.5-3 s, a cache load ~10-50 ms)."""
    from afmid.kernels.warm import warm

    return warm(names, stream, kernels=KERNELS, label="afmid default model")


def main(argv=None) -> int:
    from afmid.kernels.warm import warm

    parser = argparse.ArgumentParser(prog="python -m afmid.fit.warm", description=__doc__.splitlines()[0])
    parser.add_argument("--model-only", action="store_true",
                        help="only the default model's kernels, not afmid.kernels.warm's library-independent ones")
    args = parser.parse_args(argv)
    if not args.model_only:
        warm(stream=sys.stderr)
    warm_default_model(stream=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
