"""afmid.kernels.warm (issue 31): the library-independent kernels compiled into numba's on-disk cache ahead of the
first fit, and loaded from it by the next process."""

import json
import os
import subprocess
import sys

CHECK = """
import json, sys
from afmid.kernels.warm import warm
from afmid.kernels import periodic, sparse, switching
warm()
kernels = {"periodic_prediction": periodic.periodic_prediction, "subset_rss_qr": sparse.subset_rss_qr, "subset_lstsq": sparse.subset_lstsq, "stlsq_factor": sparse.stlsq_factor,
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


SYNC = """
import importlib, json, pkgutil, sys
import afmid.kernels
from numba.core.registry import CPUDispatcher
from afmid.config import load_config
from afmid.fit.pipeline import run_fit
from afmid.kernels.warm import warm

def compiled() -> dict:
    # every kernel of the afmid.kernels modules (the generated ones live in modules of their own) with its signatures
    found = {}
    for info in pkgutil.iter_modules(afmid.kernels.__path__):
        module = importlib.import_module(f"afmid.kernels.{info.name}")
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.py_func.__module__ == module.__name__:
                found[f"{info.name}.{name}"] = sorted(str(s) for s in value.signatures)
    return found

if sys.argv[2] == "warm":
    warm()
before = compiled()
result = run_fit(load_config(sys.argv[1], ["fit.bootstrap=5"]))
after = compiled()
from afmid.kernels import periodic, sparse, switching
twins = {"periodic": periodic.periodic_prediction_or_twin.twin_seconds, "walk": sparse._subset_rss_walk.twin_seconds, "cells": switching.switching_cells_or_twin.twin_seconds,
         "subsamples": switching.cell_subsamples_or_twin.twin_seconds}
numbers = [float(c).hex() for c in (*result.coef, *result.coef_std, result.cv_error)]
print(json.dumps({"added": {name: [s for s in after[name] if s not in before[name]] for name in after},
                  "twin_seconds": twins, "numbers": numbers}))
"""


def _fit_in_a_new_process(how: str, env: dict) -> dict:
    from repo_paths import REPO_ROOT

    out = subprocess.run([sys.executable, "-c", SYNC, str(REPO_ROOT / "configs" / "ldpe_like.yaml"), how], env=env,
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_the_warm_step_prepares_every_library_independent_kernel_the_demo_fit_runs():
    """After ``warm()``, the demo's fit (configs/ldpe_like.yaml: the demo's physics and record) calls no kernel of
    afmid.kernels with a signature the warm step did not compile or load: a kernel added to the fit, or one called
    with another layout, must be added to afmid.kernels.warm too (or the first fit after `make venv` compiles it).
    Only the kernels generated per library structure (afmid.kernels.termgen's modules) are left to the fit; the
    kernels with a same-bits twin (afmid.kernels.twin) run themselves, the twins not at all."""
    found = _fit_in_a_new_process("warm", dict(os.environ, OPENBLAS_NUM_THREADS="1"))
    assert {name: sigs for name, sigs in found["added"].items() if sigs} == {}
    assert found["twin_seconds"] == {"periodic": 0.0, "walk": 0.0, "cells": 0.0, "subsamples": 0.0}


def test_a_first_ever_fit_runs_the_twins_and_gives_the_warm_fits_numbers(tmp_path):
    """An empty numba cache (a new install without the warm step): the glitch scan's prediction, the subset walk
    and the switching cells run their twins (nothing of theirs compiled) and the fit's coefficients, their sigmas and its error are the warm
    fit's bit for bit."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    cold = _fit_in_a_new_process("cold", dict(env, NUMBA_CACHE_DIR=str(tmp_path), AFMID_KERNEL_DIR=str(tmp_path / "k")))
    assert all(seconds > 0.0 for seconds in cold["twin_seconds"].values()), cold["twin_seconds"]
    assert not cold["added"]["sparse.subset_rss_qr"] and not cold["added"]["switching.switching_cells"]
    assert not cold["added"]["switching.cell_subsamples"] and not cold["added"]["periodic.periodic_prediction"]
    warm = _fit_in_a_new_process("warm", env)
    assert cold["numbers"] == warm["numbers"]
