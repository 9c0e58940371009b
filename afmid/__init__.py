"""afmid: quantitative tip-sample forces from dynamic AFM deflection traces.

Importing the package is cheap on purpose: numba, scipy, h5py and matplotlib are
imported by the modules that need them, so ``afmid --help`` stays fast.
"""

__version__ = "0.1.0"
