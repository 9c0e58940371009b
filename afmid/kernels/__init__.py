"""Numba kernels. Only modules in this package import numba."""
