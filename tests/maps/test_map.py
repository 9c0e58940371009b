"""``afmid map`` on real dask.distributed components: a local cluster, a ``dask scheduler`` with two
``dask worker`` processes on 127.0.0.1, a worker killed mid-run, an interrupted and resumed map, a failing
pixel, and the map's parameters against the simulator's truth per phase.

The map (tests/configs/map_small.yaml) is 3x3 pixels of short traces; pixel (2, 2) is spoiled with NaNs. Every
run fits the same pixels by the same code path (one-thread BLAS in every worker), so the maps of different runs
must be bit-identical when they cut the map into the same chunks (the default pixel fit carries its start and
support from pixel to pixel within a chunk: afmid.maps.pixel_fit). Map runs are child processes (``python -m afmid.cli``): dask's worker processes are spawned.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from afmid.io.trace import sha256_file
from afmid.threads import SINGLE_THREAD_ENV
from repo_paths import REPO_ROOT, SIGNAL_CHILD
from terminal_signals import terminal_signals

REPO = REPO_ROOT
CONFIG = REPO / "tests" / "configs" / "map_small.yaml"
BAD_PIXEL = (2, 2)
#: Fixed before the first run: median over a phase's pixels vs the phase's truth.
E_STAR_TOLERANCE = 0.20  # relative
HAMAKER_TOLERANCE = 0.20  # relative
SEPARATION_TOLERANCE = 0.2e-9  # m
RUN_TIMEOUT = 600  # s, a whole map run on a loaded machine


def afmid(*args: str, cwd: Path, env: dict | None = None, timeout: float = RUN_TIMEOUT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "afmid.cli", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, env=dict(os.environ, **(env or {})))


def start_map(*args: str, cwd: Path) -> subprocess.Popen:
    """A map run in its own process group (a terminal's Ctrl-C reaches the whole group)."""
    return subprocess.Popen([sys.executable, "-m", "afmid.cli", *args], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=terminal_signals)


def wait_for_chunks(sidecar: Path, n: int, proc: subprocess.Popen, timeout: float = RUN_TIMEOUT) -> None:
    deadline = time.monotonic() + timeout
    while len(list(sidecar.glob("chunk_*.npz"))) < n:
        assert proc.poll() is None, f"the map ended before {n} chunks were saved: {proc.communicate()}"
        assert time.monotonic() < deadline, "no chunk saved in time"
        time.sleep(0.02)  # short: the tests that act on the n-th chunk must act before the last chunk is in


def read_maps(path: Path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as h5:
        return {name: ds[()] for name, ds in h5["maps"].items()}


def assert_identical(a: Path, b: Path) -> None:
    ma, mb = read_maps(a), read_maps(b)
    assert ma.keys() == mb.keys()
    for name in ma:
        np.testing.assert_array_equal(ma[name], mb[name], err_msg=name)


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    """The simulated map (with truth) and a copy with a NaN pixel, ``map.h5``."""
    ws = tmp_path_factory.mktemp("map")
    done = afmid("-q", "simulate", str(CONFIG), "-o", "clean.h5", cwd=ws)
    assert done.returncode == 0, done.stderr
    shutil.copy(ws / "clean.h5", ws / "map.h5")
    with h5py.File(ws / "map.h5", "r+") as h5:
        trace = h5["deflection"][BAD_PIXEL]
        trace[50:60] = np.nan
        h5["deflection"][BAD_PIXEL] = trace
    return ws


@pytest.fixture(scope="module")
def local_result(workspace) -> Path:
    """The map fitted on a local cluster of 2 workers (exit 1: one pixel failed)."""
    done = afmid("map", str(CONFIG), "--input", "map.h5", "-o", "local.h5", "-j", "2", "--chunk", "2", cwd=workspace)
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr
    return workspace / "local.h5"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class DaskCluster:
    """A ``dask scheduler`` and ``dask worker`` processes (one thread each, no nanny) on 127.0.0.1."""

    def __init__(self, dask: str, folder: Path):
        self.dask, self.folder = dask, folder
        self.address = f"tcp://127.0.0.1:{free_port()}"
        self.env = dict(os.environ, **SINGLE_THREAD_ENV)
        self.scheduler = subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port",
                                           self.address.rsplit(":", 1)[1], "--no-dashboard"], cwd=folder,
                                          env=self.env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.workers: list[subprocess.Popen] = []

    def add_worker(self) -> subprocess.Popen:
        proc = subprocess.Popen([self.dask, "worker", self.address, "--nthreads", "1", "--no-nanny", "--host",
                                 "127.0.0.1", "--no-dashboard"], cwd=self.folder, env=self.env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.workers.append(proc)
        return proc

    def wait_for_workers(self, n: int, timeout: float = 120.0) -> None:
        from distributed import Client

        with Client(self.address, timeout=timeout) as client:
            client.wait_for_workers(n, timeout=timeout)

    def stop(self) -> None:
        for proc in [*self.workers, self.scheduler]:
            if proc.poll() is None:
                proc.terminate()
        for proc in [*self.workers, self.scheduler]:
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@pytest.fixture(scope="module")
def dask_cluster(tmp_path_factory):
    dask = shutil.which("dask", path=str(Path(sys.executable).parent)) or shutil.which("dask")
    if dask is None:
        pytest.skip("the dask command line is not installed (pip install 'dask[distributed]')")
    cluster = DaskCluster(dask, tmp_path_factory.mktemp("dask"))
    try:
        cluster.add_worker()
        cluster.add_worker()
        cluster.wait_for_workers(2)
        yield cluster
    finally:
        cluster.stop()


# --------------------------------------------------------------------------- tests
def test_local_map_fits_every_pixel_and_fails_the_nan_pixel_alone(workspace, local_result):
    maps = read_maps(local_result)
    status = maps["status"]
    assert status[BAD_PIXEL] == 2
    assert "NaN" in maps["message"][BAD_PIXEL].decode() and "pixel (2, 2)" in maps["message"][BAD_PIXEL].decode()
    others = np.ones(status.shape, bool)
    others[BAD_PIXEL] = False
    assert np.all(status[others] < 2), maps["message"]
    assert np.all(np.isfinite(maps["E_star"][others])) and np.isnan(maps["E_star"][BAD_PIXEL])
    assert np.all(maps["E_star_sigma"][others] > 0)
    with h5py.File(local_result, "r") as h5:
        for name, ds in h5["maps"].items():
            assert "units" in ds.attrs, name
        assert "1 sigma" in h5["maps/E_star_sigma"].attrs["meaning"]
        assert h5["maps/E_star"].attrs["units"] == "Pa" and h5["maps/separation"].attrs["units"] == "m"
        terms = [t.decode() for t in h5["model/terms"][()]]
        assert h5.attrs["format"] == "afmid-map-result" and h5.attrs["afmid_version"]
        assert h5.attrs["input_sha256"] == sha256_file(workspace / "map.h5")
        assert "dmt" in h5.attrs["config"] and h5.attrs["created"]
        assert (h5.attrs["n_ok"] + h5.attrs["n_suspect"], h5.attrs["n_failed"]) == (8, 1)
    # every selected-term bit names a term of the library
    assert np.all(maps["selected"][others] > 0) and np.all(maps["selected"] < (1 << len(terms)))
    assert not (workspace / "local.h5.afmid-map").exists()


def test_map_parameters_match_the_simulated_truth_per_phase(workspace, local_result):
    maps = read_maps(local_result)
    with h5py.File(workspace / "clean.h5", "r") as h5:
        truth = {name: h5["truth"][name][()] for name in ("phase", "E_star", "hamaker", "separation")}
    ok = maps["status"] < 2
    for phase in np.unique(truth["phase"]):
        pixels = ok & (truth["phase"] == phase)
        assert pixels.sum() >= 3
        for name, tol in (("E_star", E_STAR_TOLERANCE), ("hamaker", HAMAKER_TOLERANCE)):
            want = np.unique(truth[name][pixels])
            assert want.size == 1
            got = np.median(maps[name][pixels])
            assert abs(got / want[0] - 1) < tol, (phase, name, got, want[0])
        error = np.median(np.abs(maps["separation"][pixels] - truth["separation"][pixels]))
        assert error < SEPARATION_TOLERANCE, (phase, error)


def test_a_map_through_a_scheduler_and_two_workers_equals_the_local_map(workspace, local_result, dask_cluster):
    done = afmid("map", str(CONFIG), "--input", "map.h5", "-o", "remote.h5", "--scheduler", dask_cluster.address,
                 "--chunk", "2", cwd=workspace)
    assert done.returncode == 1, done.stderr
    assert "dask cluster at " + dask_cluster.address in done.stderr
    assert_identical(local_result, workspace / "remote.h5")
    # the environment variable names the scheduler too
    done = afmid("map", str(CONFIG), "--input", "map.h5", "-o", "remote_env.h5", "--chunk", "2", cwd=workspace,
                 env={"AFMID_SCHEDULER": dask_cluster.address})
    assert done.returncode == 1, done.stderr
    assert "dask cluster at " in done.stderr
    assert_identical(local_result, workspace / "remote_env.h5")


def test_a_worker_killed_mid_map_is_survived(workspace, local_result, dask_cluster):
    """The victim is frozen (SIGSTOP) before the map starts: the tasks the scheduler hands it wait there, so the
    map cannot finish before the victim is killed (with both workers running, this test's poll of the sidecar
    could come after the last chunk under load)."""
    out = workspace / "killed.h5"
    victim = dask_cluster.workers[0]
    victim.send_signal(signal.SIGSTOP)
    proc = start_map("map", str(CONFIG), "--input", "map.h5", "-o", out.name, "--scheduler", dask_cluster.address,
                     "--chunk", "2", cwd=workspace)
    try:
        sidecar = workspace / "killed.h5.afmid-map"
        wait_for_chunks(sidecar, 1, proc)
        victim.kill()  # SIGKILL (a stopped process dies too): no goodbye to the scheduler
        victim.wait()
        assert len(list(sidecar.glob("chunk_*.npz"))) < 5, "the map was over before the worker was killed"
        _, err = proc.communicate(timeout=RUN_TIMEOUT)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        dask_cluster.add_worker()  # back to two workers for whatever runs next
    assert proc.returncode == 1, err
    assert_identical(local_result, out)


def test_an_interrupted_map_resumes_from_its_finished_chunks(workspace, local_result):
    """Ctrl-C once the first chunk is saved. The signal comes from inside the map's process
    (tests/signal_child/sitecustomize.py: when the main thread renames the first chunk into place), not from
    this process polling the sidecar: a poll lost the race under load (the map finished first, sessions 10-11);
    the workers ignore a terminal's Ctrl-C (afmid.batch.dask_worker_setup), so the map's process is the one
    that gets it."""
    out = workspace / "resumed.h5"
    sidecar = workspace / "resumed.h5.afmid-map"
    args = ("map", str(CONFIG), "--input", "map.h5", "-o", out.name, "-j", "2", "--chunk", "2")
    interrupted = afmid(*args, cwd=workspace, env={"PYTHONPATH": str(SIGNAL_CHILD), "PYTHONDONTWRITEBYTECODE": "1",
                                                   "AFMID_TEST_SIGNAL": "SIGINT",
                                                   "AFMID_TEST_SIGNAL_WHEN": "audit:os.rename:chunk_"})
    err = interrupted.stderr
    assert interrupted.returncode == 130, err
    # afmid's lines only: no traceback and no line of dask's loggers (a worker's heartbeat cut by the cluster's
    # close was logged with its traceback once; tests/batch/test_engine_interrupt.py makes that noise on purpose)
    assert "Traceback" not in err and " - distributed." not in err and " - tornado" not in err, err
    assert [line for line in err.splitlines() if line.strip()][-1].startswith("afmid: interrupted"), err
    assert not out.exists()
    saved = sorted(p.name for p in sidecar.glob("chunk_*.npz"))
    assert 1 <= len(saved) < 5 and not list(workspace.glob(".afmid-tmp*"))
    done = afmid(*args, cwd=workspace)
    assert done.returncode == 1, done.stderr
    assert f"resuming: {len(saved)} of 5 chunks already fitted" in done.stderr
    assert not sidecar.exists()
    assert_identical(local_result, out)


def test_a_batch_runs_on_the_dask_cluster_as_on_the_local_pool(workspace, dask_cluster):
    """``afmid batch --scheduler``: the same engine interface; the run files equal the local pool's."""
    import yaml

    raw = yaml.safe_load(CONFIG.read_text())
    del raw["simulate"]["map"]
    folder = workspace / "batch_configs"
    folder.mkdir()
    for seed in (1, 2):
        raw["simulate"]["seed"] = seed
        (folder / f"item{seed}.yaml").write_text(yaml.safe_dump(raw))
    runs = {}
    for name, extra in (("remote", ("--scheduler", dask_cluster.address)), ("pool", ("-j", "2"))):
        done = afmid("-q", "batch", "--configs", str(folder / "*.yaml"), "-o", name, *extra, cwd=workspace)
        assert done.returncode == 0, done.stderr
        runs[name] = sorted((workspace / name).glob("*.run.h5"))
        assert len(runs[name]) == 2
    for remote, pool in zip(runs["remote"], runs["pool"]):
        with h5py.File(remote, "r") as a, h5py.File(pool, "r") as b:
            for key in ("model/coefficients", "model/separation", "diagnostics/cv_error"):
                np.testing.assert_array_equal(a[key][()], b[key][()], err_msg=f"{remote.name}:{key}")


# --------------------------------------------------------------------------- pieces, in process
def test_a_spring_constant_100x_too_large_makes_every_pixel_suspect_and_is_named(workspace, tmp_path):
    """The clean map fitted with cantilever.spring_constant 4000 N/m (truth 40): before issue 32 every pixel was ok
    (E* 200 GPa and H 5e-18 J were inside their ranges). Now every pixel is suspect with the cause, and the map
    says it once in a warning."""
    config = tmp_path / "map_k.yaml"
    config.write_text(CONFIG.read_text().replace("spring_constant: 40.0", "spring_constant: 4000.0"))
    assert "spring_constant: 4000.0" in config.read_text()
    done = afmid("map", str(config), "--input", str(workspace / "clean.h5"), "-o", str(tmp_path / "k.h5"),
                 "-j", "1", cwd=tmp_path)
    assert done.returncode == 0, done.stderr  # suspect pixels are results, flagged, not failures
    with h5py.File(tmp_path / "k.h5", "r") as h5:
        assert (h5.attrs["n_ok"], h5.attrs["n_suspect"], h5.attrs["n_failed"]) == (0, 9, 0)
        messages = [m.decode() if isinstance(m, bytes) else str(m) for m in h5["maps/message"][()].ravel()]
    assert all("too large would explain it" in m and "check cantilever.spring_constant" in m for m in messages)
    warnings = [line for line in done.stderr.splitlines() if "implausible read-outs in 9 of 9 pixels" in line]
    assert len(warnings) == 1 and "at 100x too large: hamaker would be" in warnings[0], done.stderr


def test_phases_are_drawn_as_round_domains_over_the_matrix():
    from afmid.config import load_config
    from afmid.maps.simulate import phase_map

    spec = load_config(CONFIG).simulate.map
    # domain centre (0, 0), radius 25 nm, pixels 20 nm apart: (0,0), (0,1), (1,0) inside; (1,1) at 28 nm is not
    np.testing.assert_array_equal(phase_map(spec), [[1, 1, 0], [1, 0, 0], [0, 0, 0]])


def test_scheduler_address_and_default_chunking():
    from afmid.batch.engine_dask import scheduler_address
    from afmid.errors import ConfigError
    from afmid.maps.run import default_chunk

    assert scheduler_address("tcp://127.0.0.1:8786") == "tcp://127.0.0.1:8786"
    with pytest.raises(ConfigError, match="--scheduler"):
        scheduler_address("127.0.0.1:8786")
    assert [default_chunk(n) for n in (1, 5, 16, 32, 33, 512, 4096, 10**6)] == [1, 5, 8, 8, 8, 16, 128, 128]


def test_a_npy_map_gives_the_pixels_of_the_hdf5_map(workspace, tmp_path):
    """The .npy layout (everything but the samples from the config) fits a pixel exactly as the HDF5 layout."""
    import yaml

    from afmid.config import dump_config, load_config
    from afmid.maps.task import fit_chunk

    with h5py.File(workspace / "clean.h5", "r") as h5:
        np.save(tmp_path / "map.npy", h5["deflection"][()])
        rate = float(h5.attrs["sample_rate"])
    raw = yaml.safe_load(CONFIG.read_text())
    raw["data"] = {"sample_rate": rate, "units": "m"}
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(raw))
    config_text = dump_config(load_config(tmp_path / "run.yaml"))
    got = {name: fit_chunk({"input": str(path), "config": config_text, "source": None, "first": 4, "stop": 5})
           for name, path in (("npy", tmp_path / "map.npy"), ("h5", workspace / "clean.h5"))}
    assert got["npy"]["status"][0] == 0, got["npy"]["message"]
    np.testing.assert_array_equal(got["npy"]["values"], got["h5"]["values"])
    np.testing.assert_array_equal(got["npy"]["separation"], got["h5"]["separation"])


@pytest.mark.parametrize("path", sorted((REPO / "configs" / "maps").glob("*.yaml")), ids=lambda p: p.name)
def test_shipped_map_configs_validate(path):
    from afmid.config import load_config
    from afmid.maps.simulate import phase_map

    spec = load_config(path).simulate.map
    assert spec is not None and len(np.unique(phase_map(spec))) == len(spec.phases)  # every phase has pixels
