"""Print an NPY_DISABLE_CPU_FEATURES value that makes NumPy run as on a CPU without AVX-512, when this CPU has it.

Used by ``make test-kernels`` (``.ci/run``): NumPy picks its SIMD code at run time, and its AVX-512 exp and pow
differ from the AVX2 / C library ones by ulps (session 11: on a Zen 5, 5 % of exp values; a test comparing a
numba kernel with its NumPy twin bit for bit passed on AVX2 machines and failed there). On an AVX-512 machine
the tests that compare kernels with NumPy twins run again with NumPy's AVX-512 code switched off, so a test that
holds on one of the two CPU families only fails on either. The value is kept only if NumPy then imports, runs
and reports those features as not found (a child process checks); prints nothing otherwise (no AVX-512, or a
NumPy that names its features otherwise).

Usage: ``python scripts/numpy_dispatch.py``
"""

from __future__ import annotations

import os

from blas_kernels import run_probe  # the child-process probe both scripts use (scripts/ is on sys.path)

#: NumPy 2.x's names of its AVX-512 dispatch targets (x86-64-v4 and the later AVX-512 groups).
AVX512_FEATURES = ("X86_V4", "AVX512_ICL", "AVX512_SPR")

_PROBE = r"""
import io, json, contextlib, numpy as np
out = io.StringIO()
with contextlib.redirect_stdout(out):
    np.show_runtime()
text = out.getvalue()
found = text.split("'found':", 1)[1].split("]", 1)[0] if "'found':" in text else ""
np.exp(np.linspace(-1.0, 1.0, 1000)).sum()
print(json.dumps({"found": found}))
"""


def found_features(disabled: str | None) -> str | None:
    """NumPy's 'found' SIMD features (as show_runtime prints them) with ``disabled`` switched off, or None."""
    env = dict(os.environ)
    env.pop("NPY_DISABLE_CPU_FEATURES", None)
    if disabled:
        env["NPY_DISABLE_CPU_FEATURES"] = disabled
    found = run_probe(_PROBE, env)
    return None if found is None else found.get("found")


def without_avx512() -> str:
    native = found_features(None)
    if not native or "X86_V4" not in native:
        return ""
    present = [name for name in AVX512_FEATURES if name in native]
    value = " ".join(present)
    switched = found_features(value)
    if switched is None or any(name in switched for name in present):
        return ""
    return value


if __name__ == "__main__":
    print(without_avx512())
