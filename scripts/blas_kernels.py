"""Print the OpenBLAS kernels (OPENBLAS_CORETYPE values) that this CPU can run besides the one NumPy picks.

Used by ``.ci/run`` to run the numerically sensitive tests again under other kernels: a test that demands the
same bits from two different computations passes on one CPU family and fails on another (issue 11: chunked vs
whole products differed in the last bits on AVX-512). Each candidate is started in a child process and kept
only if OpenBLAS reports that kernel (it silently ignores names it does not know), it differs from the native
one and from the kernels already chosen, and a matrix product under it agrees with an exact sum (math.fsum) to
rounding, so a kernel that crashes or computes wrong on this CPU is never used.

Usage: ``python scripts/blas_kernels.py [N]`` prints up to N (default 2) names, one per line; prints nothing
when NumPy does not use OpenBLAS.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

#: Candidates in order of preference with the CPU feature each needs (x86-64 /proc/cpuinfo flags).
X86_CANDIDATES = (("Haswell", "avx2"), ("SandyBridge", "avx"), ("SkylakeX", "avx512f"), ("Nehalem", "sse4_2"),
                  ("Prescott", "sse3"))
ARM_CANDIDATES = (("ARMV8", None), ("NEOVERSEN1", "asimd"), ("CORTEXA57", None))

_PROBE = r"""
import json, math, numpy as np, threadpoolctl
info = [i for i in threadpoolctl.threadpool_info() if i.get("internal_api") == "openblas"]
rng = np.random.default_rng(0)
a, b = rng.standard_normal((67, 129)), rng.standard_normal((129, 45))
c = a @ b
exact = np.array([[math.fsum(a[i] * b[:, j]) for j in range(45)] for i in range(67)])
bound = 129 * np.finfo(float).eps * (np.abs(a) @ np.abs(b))
print(json.dumps({"architecture": info[0].get("architecture") if info else None,
                  "correct": bool(np.all(np.abs(c - exact) <= bound))}))
"""


def cpu_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith(("flags", "Features")):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def run_probe(source: str, env: dict[str, str]) -> dict | None:
    """The JSON object a child ``python -c source`` prints last, run with ``env``; None when it fails, hangs
    (120 s) or prints none (also used by scripts/numpy_dispatch.py)."""
    try:
        done = subprocess.run([sys.executable, "-c", source], env=env, capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        return None
    if done.returncode != 0:
        return None
    try:
        found = json.loads(done.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return None
    return found if isinstance(found, dict) else None


def probe(coretype: str | None) -> dict | None:
    """The kernel OpenBLAS runs with OPENBLAS_CORETYPE=coretype (None: as the environment says), or None."""
    env = dict(os.environ)
    if coretype is not None:
        env["OPENBLAS_CORETYPE"] = coretype
    return run_probe(_PROBE, env)


def other_kernels(count: int = 2) -> list[str]:
    native = probe(None)
    if native is None or native["architecture"] is None:
        return []
    machine = platform.machine().lower()
    candidates = X86_CANDIDATES if machine in ("x86_64", "amd64", "i686") else ARM_CANDIDATES
    flags = cpu_flags()
    seen = {native["architecture"].lower()}
    chosen = []
    for name, needs in candidates:
        if needs is not None and flags and needs not in flags:
            continue
        result = probe(name)
        if result is None or not result["correct"] or result["architecture"] is None:
            continue
        if result["architecture"].lower() in seen:
            continue
        seen.add(result["architecture"].lower())
        chosen.append(name)
        if len(chosen) == count:
            break
    return chosen


if __name__ == "__main__":
    print("\n".join(other_kernels(int(sys.argv[1]) if len(sys.argv) > 1 else 2)))
