"""afmid: quantitative tip-sample forces from dynamic AFM deflection traces.

Importing the package is cheap on purpose: numba, scipy, h5py and matplotlib are
imported by the modules that need them, so ``afmid --help`` stays fast. The Python
front door (``afmid.Trace``, ``afmid.read``, ``afmid.ForceModel``, ``afmid.load``, ...:
:mod:`afmid.api`, docs/python.md) is imported on first use of one of its names.
"""

from afmid.version import __version__

#: The front door's names (:mod:`afmid.api`), loaded on first access (PEP 562).
_FRONT_DOOR = ("Cantilever", "Diagnosis", "Fit", "ForceCurve", "ForceModel", "HigherMode", "Parameter", "Parameters",
               "Trace", "load", "read", "simulate_trace")

__all__ = ["__version__", *_FRONT_DOOR]


def __getattr__(name: str):
    if name in _FRONT_DOOR:
        import afmid.api as api

        value = getattr(api, name)
        globals()[name] = value  # looked up once
        return value
    raise AttributeError(f"module 'afmid' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_FRONT_DOOR))
