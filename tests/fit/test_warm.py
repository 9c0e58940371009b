"""afmid.fit.warm (issue 31): after the install's warm-up (``python -m afmid.fit.warm``, which ``make venv`` runs)
the first fit of the default model compiles nothing, the kernels generated for its library structure included."""

import json
import os
import subprocess
import sys

from repo_paths import REPO_ROOT

DEMO_CONFIGS = [REPO_ROOT / "configs" / "ldpe_like.yaml", REPO_ROOT / "afmid" / "templates" / "demo_ldpe.yaml"]

FIT_AND_COUNT = """
import json, sys
from afmid.config import load_config
from afmid.fit.pipeline import run_fit
from numba.core.registry import CPUDispatcher

result = run_fit(load_config(sys.argv[1], ["fit.bootstrap=5"]))
counts = {}
for name, module in list(sys.modules.items()):
    if module is None or not name.startswith("afmid"):  # afmid's modules and the generated afmid_law_* ones
        continue
    for attr, value in list(vars(module).items()):
        if isinstance(value, CPUDispatcher) and value.py_func.__module__ == name:
            counts[f"{name}.{attr}"] = [sum(value.stats.cache_hits.values()), sum(value.stats.cache_misses.values())]
print(json.dumps({"counts": counts, "terms": result.selected_terms(), "library": result.library.names}))
"""


def test_the_demo_fits_the_default_model_the_warm_up_prepares():
    """The warm-up compiles the model of a config without a model section: the demo's first fit must be it."""
    from afmid.config import ModelConfig, SampleConfig, load_config
    from afmid.physics.tips import SPHERE, tip_geometry

    for path in DEMO_CONFIGS:
        config = load_config(path)
        assert config.model == ModelConfig(), path
        assert tip_geometry(config.cantilever) == SPHERE, path
        assert config.sample.medium == SampleConfig().medium, path


def test_after_the_install_warm_up_the_demos_first_fit_compiles_nothing(tmp_path):
    """An empty numba cache and kernel folder (a fresh install), ``python -m afmid.fit.warm`` in one process, the
    demo's fit (configs/ldpe_like.yaml: the demo's physics and record) in the next: no numba dispatcher of afmid
    or of a generated kernel module misses the cache, and the generated modules' kernels were loaded from it."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), AFMID_KERNEL_DIR=str(tmp_path / "kernels"),
               OPENBLAS_NUM_THREADS="1")
    warm = subprocess.run([sys.executable, "-m", "afmid.fit.warm"], env=env, capture_output=True, text=True,
                          timeout=900)
    assert warm.returncode == 0, warm.stderr[-2000:]
    for group in ("switching", "sparse", "library", "contact_probe", "information_bound"):
        assert f": {group} ready in" in warm.stderr, warm.stderr
    generated = sorted(p.name for p in (tmp_path / "kernels").glob("afmid_law_*.py"))
    assert len(generated) == 3, generated  # the library's terms, the contact probe's terms, the bound's law

    fit = subprocess.run([sys.executable, "-c", FIT_AND_COUNT, str(DEMO_CONFIGS[0])], env=env, capture_output=True,
                         text=True, timeout=900)
    assert fit.returncode == 0, fit.stderr[-2000:]
    found = json.loads(fit.stdout.strip().splitlines()[-1])
    counts = found["counts"]
    assert {name: c for name, c in counts.items() if c[1]} == {}  # compiled in the fit: none
    loaded = {name.split(".")[0] for name, (hits, _) in counts.items() if name.startswith("afmid_law_") and hits}
    assert sorted(f"{m}.py" for m in loaded) == generated  # each warmed module used by the fit, from the cache
    assert sorted(p.name for p in (tmp_path / "kernels").glob("afmid_law_*.py")) == generated  # none added
    # the bound's law was warmed for a support of every term: the demo's fit selects them all
    assert found["terms"] == found["library"], found
