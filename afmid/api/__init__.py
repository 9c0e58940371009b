"""afmid's Python front door: what ``import afmid`` offers (``afmid.Trace``, ``afmid.read``, ...).

One name per step of the loop, each the call the command line makes:

- :class:`Trace` (``Trace.from_array``), :func:`read`, :func:`simulate_trace`: a checked trace (SI, positive toward the
  sample) with its :class:`Cantilever`;
- :class:`ForceModel`: the effects to fit (``.add`` for the refit); ``.fit(trace)`` gives a :class:`Fit`;
- :class:`Fit`: ``.print()``, ``.parameters``, ``.force_curve()``, ``.predict()``, ``.diagnose()``,
  ``.report(folder)``, ``.save(path)``; :func:`load` reads a saved fit back.

docs/python.md is the tutorial and the reference. The package sits above fit/, diagnosis/ and report/ (and is
imported by the command line), so none of them imports it.
"""

from afmid.api.fit import Fit, load
from afmid.api.model import ForceModel, read, simulate_trace
from afmid.api.tables import Diagnosis, ForceCurve, Parameter, Parameters
from afmid.io.cantilever import Cantilever, HigherMode
from afmid.io.trace import Trace

__all__ = ["Cantilever", "Diagnosis", "Fit", "ForceCurve", "ForceModel", "HigherMode", "Parameter", "Parameters",
           "Trace", "load", "read", "simulate_trace"]
