"""afmid.kernels.warm (issue 31): the library-independent kernels compiled into numba's on-disk cache ahead of the
first fit, and loaded from it by the next process."""

import json
import os
import subprocess
import sys

CHECK = """
import json, sys
from afmid.kernels.warm import warm
from afmid.kernels import sparse, switching
warm()
kernels = {"subset_rss_qr": sparse.subset_rss_qr, "subset_lstsq": sparse.subset_lstsq, "stlsq_factor": sparse.stlsq_factor,
           "switching_cells": switching.switching_cells, "cell_subsamples": switching.cell_subsamples}
print(json.dumps({name: [sum(k.stats.cache_hits.values()), sum(k.stats.cache_misses.values())]
                  for name, k in kernels.items()}))
"""


def _run(cache: str) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache, OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", CHECK], env=env, capture_output=True, text=True, timeout=600, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_warm_fills_numbas_cache_and_the_next_process_loads_every_kernel(tmp_path):
    first = _run(str(tmp_path))
    assert all(misses >= 1 and hits == 0 for hits, misses in first.values()), first  # an empty cache: compiled
    assert any(name.startswith("sparse.subset_rss") for name in os.listdir(next(tmp_path.iterdir())))
    second = _run(str(tmp_path))
    assert all(hits >= 1 and misses == 0 for hits, misses in second.values()), second  # loaded, none compiled


def test_warm_command_line_names_each_group(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-m", "afmid.kernels.warm", "switching"], env=env, capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert out.stderr.strip().startswith("afmid kernels: switching ready in") and "sparse" not in out.stderr
    bad = subprocess.run([sys.executable, "-m", "afmid.kernels.warm", "nonsense"], env=env, capture_output=True,
                         text=True, timeout=600)
    assert bad.returncode == 2 and "invalid choice" in bad.stderr and "Traceback" not in bad.stderr
