"""``afmid map``: fit every pixel of a force map on an engine and write the maps (layout in docs/file-formats.md).

The map is cut into chunks of pixels (row-major ranges), one engine task each (:func:`afmid.maps.task.fit_chunk`).
Each finished chunk is saved as it arrives, atomically, in a sidecar folder beside the output
(``RESULT.h5.afmid-map/``, afmid's own: marker, lock, a ``key.json`` naming the input's SHA-256, the merged config
and the chunking, each chunk carrying its identity: :mod:`afmid.maps.sidecar`); a re-run of the same command with
the same input and config skips the finished chunks (a Ctrl-C, a killed client or a lost cluster
(:class:`afmid.errors.EngineError`) leave a resumable state, never a half-written ``RESULT.h5``). When every chunk
is in, the result file is written atomically with its provenance and the sidecar removed.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
from pathlib import Path

import numpy as np

from afmid.errors import ConfigError, EngineError, InputError
from afmid.maps.group_diagnosis import write_groups
from afmid.maps.pixel_fit import ROUTES
from afmid.maps.sidecar import Sidecar, held_sidecar
from afmid.maps.task import STATUS_FAILED, STATUS_NAMES, STATUS_OK, STATUS_SUSPECT, fit_chunk, spring_constant_summary

log = logging.getLogger(__name__)

MAP_RESULT_FORMAT = "afmid-map-result"
SIDECAR_SUFFIX = ".afmid-map"
#: What a saved chunk holds (in the sidecar's key: chunks of an older layout are fitted again, not misread).
#: 2: with the residual signature (afmid.maps.residual); 3: with its identity (afmid.maps.sidecar); 4: with each
#: pixel's force curves (afmid.maps.pixel_curves).
CHUNK_LAYOUT = 4
#: Largest chunk (pixels) chosen by default: enough tasks to balance the workers, few enough to share the setup.
MAX_DEFAULT_CHUNK = 128
#: Smallest chunk chosen by default (unless the map is smaller): the shared pixel fit searches each chunk's first
#: pixel in full (afmid.maps.pixel_fit), so a chunk of a few pixels would pay that search for most of its pixels.
MIN_DEFAULT_CHUNK = 8
#: What /maps/NAME_sigma is, per pixel-fit strategy.
SIGMA_MEANING = {"full": "1 sigma (bootstrap standard deviation, separation's profile sigma propagated)",
                 "shared": "1 sigma (least-squares covariance of the support, separation's profile sigma propagated)"}


def default_chunk(n_pixels: int) -> int:
    """Pixels per task: about 32 tasks per map, :data:`MIN_DEFAULT_CHUNK` (or the whole map when smaller) to
    :data:`MAX_DEFAULT_CHUNK` pixels each (independent of the worker count, so that a re-run with another -j
    resumes)."""
    return max(1, min(n_pixels, max(MIN_DEFAULT_CHUNK, min(MAX_DEFAULT_CHUNK, math.ceil(n_pixels / 32)))))


def sidecar_for(output: Path) -> Path:
    """The folder of finished chunks of an unfinished ``afmid map`` to ``output``."""
    return output.with_name(output.name + SIDECAR_SUFFIX)


def run_map(config, config_text: str, input_path: Path, output: Path, engine, chunk: int | None = None,
            overwrite: bool = False, pixel_fit: str | None = None, diagnose: bool = True) -> dict:
    """Fit the map ``input_path`` with ``config`` on ``engine`` and write ``output``; returns the pixel counts.

    ``pixel_fit``: the strategy of :data:`afmid.maps.pixel_fit.PIXEL_FITS` (None: the default, ``shared``).
    ``diagnose``: run the catalog diagnosis on the model-limited groups of pixels (afmid.maps.group_diagnosis);
    the groups themselves are always formed."""
    from afmid.maps.pixel_fit import DEFAULT_PIXEL_FIT
    from afmid.io.trace import check_output_path, sha256_file
    from afmid.maps.input_file import open_map

    if config.drive.phase is not None:  # the shared pixel fit builds its own systems: it would ignore it silently
        raise ConfigError("a calibrated drive (drive.phase) is for single traces (afmid fit): a map fits the drive "
                          "of every pixel; leave drive.phase out", file=config.source, key="drive.phase")
    source = open_map(input_path, config)
    output = check_output_path(output, overwrite, inputs={config.source: "the config", input_path: "the map"})
    if separation_ignored(config):
        log.warning("sample.separation (%.4g m) is not used: the separation is estimated per pixel (topography)",
                    config.sample.separation)
    n = source.n_pixels
    chunk = chunk or default_chunk(n)
    bounds = [(lo, min(n, lo + chunk)) for lo in range(0, n, chunk)]
    key = {"input_sha256": sha256_file(source.path), "config_sha256": hashlib.sha256(config_text.encode()).hexdigest(),
           "shape": [source.rows, source.cols, source.samples], "chunk": chunk,
           "pixel_fit": pixel_fit or DEFAULT_PIXEL_FIT, "chunk_layout": CHUNK_LAYOUT}
    # The group diagnosis runs on the same workers after the pixels: an engine that can keep them keeps them.
    kept = getattr(engine, "kept_running", None)
    with held_sidecar(sidecar_for(output), key, bounds) as sidecar, (kept() if kept else contextlib.nullcontext()):
        return _run_chunks(sidecar, source, config, config_text, output, engine, diagnose)


def _run_chunks(sidecar: Sidecar, source, config, config_text: str, output: Path, engine, diagnose: bool) -> dict:
    """Fit the chunks not yet in the (claimed, locked) ``sidecar`` on ``engine``, then write ``output``."""
    bounds, key, folder = sidecar.bounds, sidecar.key, sidecar.folder
    done = sidecar.finished()
    if done:
        log.info("resuming: %d of %d chunks already fitted (%s)", len(done), len(bounds), folder)
    tasks = [(i, {"input": str(source.path.resolve()), "config": config_text,
                  "source": str(config.source) if config.source else None, "first": lo, "stop": hi,
                  "pixel_fit": key["pixel_fit"]})
             for i, (lo, hi) in enumerate(bounds) if i not in done]
    where = (f"the dask cluster at {engine.scheduler}" if getattr(engine, "scheduler", None)
             else f"{engine.workers_for(len(tasks)) if tasks else 0} local workers")
    log.info("map %dx%d (%d samples per pixel): %d chunks of %d pixels to fit on %s", source.rows, source.cols,
             source.samples, len(tasks), key["chunk"], where)
    progress = {"done": len(done)}
    saved = set(done)

    def report(outcome) -> None:
        lo, hi = bounds[outcome.key]
        if outcome.result is None and not outcome.crashed:
            return  # stopped before it finished: fitted again on the next run
        result = outcome.result if outcome.result is not None else _crashed_chunk(lo, hi, outcome.crashed)
        sidecar.save(outcome.key, _chunk_arrays(result))
        saved.add(outcome.key)
        progress["done"] += 1
        failed = int(np.count_nonzero(np.asarray(result["status"]) == STATUS_FAILED))
        log.info("chunk %d/%d: pixels %d-%d fitted (%d failed)", progress["done"], len(bounds), lo, hi - 1, failed)

    try:
        engine.run(fit_chunk, tasks, report, lambda: None)
    except KeyboardInterrupt:
        log.warning("interrupted: %d of %d chunks are saved in %s; run the same command again to resume",
                    progress["done"], len(bounds), folder)
        raise
    except EngineError:  # the cluster lost its tasks: they are not "failed pixels"; the same command resumes
        log.warning("the engine lost the map's tasks: %d of %d chunks are saved in %s; run the same command again "
                    "(on a working cluster) to resume", progress["done"], len(bounds), folder)
        raise
    if len(saved) < len(bounds):  # an engine that gave up on tasks without raising: never a map with holes
        raise EngineError(f"the engine finished without the results of {len(bounds) - len(saved)} of {len(bounds)} "
                          f"chunks; the {len(saved)} finished ones are saved in {folder}: run the same command again "
                          "to resume", file=output)
    return write_map_result(output, source, config, config_text, sidecar, diagnose=diagnose, engine=engine)


def separation_ignored(config) -> bool:
    """Whether ``sample.separation`` is set for nothing: a map estimates the separation per pixel. A config that
    also simulates the map (``simulate.map``) needs it for the simulation (the matrix's rest separation), so it is
    not said to be unused there."""
    simulates_map = config.simulate is not None and getattr(config.simulate, "map", None) is not None
    return config.sample.separation is not None and not simulates_map


def _chunk_arrays(result: dict) -> dict[str, np.ndarray]:
    """A chunk's result (afmid.maps.task.fit_chunk) as the arrays saved in the sidecar."""
    from afmid.maps.residual import SIGNATURE
    from afmid.maps.pixel_curves import CHUNK_KEYS

    arrays = {k: np.asarray(result[k]) for k in ("status", "separation", "separation_sigma", "cv_error",
                                                 "cv_error_noise_floor", "selected", "route", "evaluations",
                                                 *SIGNATURE, *CHUNK_KEYS)}
    arrays["message"] = np.array(result["message"], dtype=str)
    arrays["range"] = np.array([result["first"], result["stop"]])
    arrays["terms"] = np.array(result["terms"] or [""], dtype=str)
    arrays["names"] = np.array(result["names"] or [""], dtype=str)
    arrays["units"] = np.array(result["units"] or [""], dtype=str)
    arrays["effects"] = np.array(result["effects"] or [""], dtype=str)
    n = result["stop"] - result["first"]
    arrays["values"] = np.asarray(result["values"]) if result["values"] is not None else np.zeros((0, n))
    arrays["sigmas"] = np.asarray(result["sigmas"]) if result["sigmas"] is not None else np.zeros((0, n))
    return arrays


def _crashed_chunk(first: int, stop: int, why: str) -> dict:
    from afmid.maps.pixel_curves import collect
    from afmid.maps.residual import SIGNATURE, empty_signature

    n = stop - first
    nan = np.full(n, np.nan)
    unfitted = empty_signature()
    return {"first": first, "stop": stop, "status": np.full(n, STATUS_FAILED, np.int8), "message": [why] * n,
            **collect([None] * n),
            **{k: np.full(n, unfitted[k]) for k in SIGNATURE},
            "separation": nan, "separation_sigma": nan, "cv_error": nan, "cv_error_noise_floor": nan,
            "selected": np.zeros(n, np.int64), "route": np.full(n, -1, np.int8), "evaluations": np.zeros(n, np.int32),
            "terms": [], "names": [], "units": [], "effects": [], "values": None, "sigmas": None}


def _load_chunks(sidecar: Sidecar) -> list[dict]:
    chunks = sidecar.load_all()
    for chunk in chunks:
        for k in ("terms", "names", "units", "effects"):
            chunk[k] = [str(v) for v in chunk[k] if str(v)]
    return chunks


def write_map_result(output: Path, source, config, config_text: str, sidecar: Sidecar, diagnose: bool = True,
                     engine=None) -> dict:
    """Assemble the saved chunks into ``output`` (atomically, with provenance), with the pixels' groups and their
    verdicts (``diagnose``: the catalog diagnosis of the model-limited groups, on ``engine``, None: in this
    process); returns the pixel counts."""
    from afmid.io.trace import atomic_hdf5, write_dataset
    from afmid.maps.pixel_curves import merge_chunks, write_pixel_curves
    from afmid.maps.residual import CODED, SIGNATURE

    chunks = _load_chunks(sidecar)
    key = sidecar.key
    shape = (source.rows, source.cols)
    n = source.n_pixels
    terms = next((c["terms"] for c in chunks if c["terms"]), [])
    if any(c["terms"] and c["terms"] != terms for c in chunks):
        raise InputError("chunks of this map were fitted with different libraries; remove the sidecar folder",
                         file=sidecar.folder)
    names, units, effects = [], {}, {}
    for c in chunks:
        for name, unit, effect in zip(c["names"], c["units"], c["effects"]):
            if name not in units:
                names.append(name)
                units[name], effects[name] = unit, effect
    flat = {k: np.full(n, np.nan) for k in ("separation", "separation_sigma", "cv_error", "cv_error_noise_floor",
                                            *SIGNATURE)}
    status = np.full(n, STATUS_FAILED, np.int8)
    selected = np.zeros(n, np.int64)
    route = np.full(n, -1, np.int8)
    evaluations = np.zeros(n, np.int32)
    message = np.full(n, "", dtype=object)
    values = {name: np.full(n, np.nan) for name in names}
    sigmas = {name: np.full(n, np.nan) for name in names}
    for c in chunks:
        lo, hi = (int(v) for v in c["range"])
        for k in flat:
            flat[k][lo:hi] = c[k]
        status[lo:hi] = c["status"]
        selected[lo:hi] = c["selected"]
        route[lo:hi] = c["route"]
        evaluations[lo:hi] = c["evaluations"]
        message[lo:hi] = [str(m) for m in c["message"]]
        for k, name in enumerate(c["names"]):
            values[name][lo:hi] = c["values"][k]
            sigmas[name][lo:hi] = c["sigmas"][k]
    counts = {name: int(np.count_nonzero(status == code)) for code, name in enumerate(STATUS_NAMES)}
    grouping, verdicts = _groups(source, config, config_text, flat, values, sigmas, names, status, diagnose, engine)
    with atomic_hdf5(output, MAP_RESULT_FORMAT, config_text, {str(source.path): key["input_sha256"]}) as h5:
        h5.attrs["rows"], h5.attrs["cols"], h5.attrs["samples"] = source.rows, source.cols, source.samples
        h5.attrs["chunk_pixels"] = key["chunk"]
        h5.attrs["pixel_fit"] = key["pixel_fit"]
        for name, count in counts.items():
            h5.attrs[f"n_{name}"] = count
        maps = h5.create_group("maps")
        for name in names:
            write_dataset(maps, name, values[name].reshape(shape), units[name], effect=effects[name])
            write_dataset(maps, f"{name}_sigma", sigmas[name].reshape(shape), units[name],
                          meaning=SIGMA_MEANING[key["pixel_fit"]])
        write_dataset(maps, "separation", flat["separation"].reshape(shape), "m",
                      meaning="rest tip-sample separation d estimated per pixel (topography: the sample is higher "
                              "where d is smaller)")
        write_dataset(maps, "separation_sigma", flat["separation_sigma"].reshape(shape), "m",
                      meaning="1 sigma (profile width)")
        write_dataset(maps, "cv_error", flat["cv_error"].reshape(shape), "1",
                      definition="normalised cross-validated force error")
        write_dataset(maps, "cv_error_noise_floor", flat["cv_error_noise_floor"].reshape(shape), "1",
                      definition="expected cv_error of a perfect model at the estimated noise")
        write_dataset(maps, "selected", selected.reshape(shape), "1",
                      meaning="bit k set: /model/terms[k] selected at this pixel")
        write_dataset(maps, "status", status.reshape(shape), "1",
                      meaning=", ".join(f"{code}: {name}" for code, name in enumerate(STATUS_NAMES)))
        write_dataset(maps, "message", message.astype(str).reshape(shape), "1",
                      meaning="why a pixel failed or is suspect (empty when ok)")
        write_dataset(maps, "fit_route", route.reshape(shape), "1",
                      meaning=", ".join(f"{code}: {name}" for code, name in enumerate(ROUTES)) + ", -1: not fitted")
        write_dataset(maps, "evaluations", evaluations.reshape(shape), "1",
                      meaning="library evaluations (regression systems built) the pixel's fit cost")
        for name, (unit, meaning) in SIGNATURE.items():
            data = flat[name].reshape(shape)
            if name in CODED:  # codes into REGIONS / CHARACTERS, -1 where not fitted
                data = np.where(np.isfinite(data), data, -1).astype(np.int8)
            write_dataset(maps, name, data, unit, meaning=meaning)
        write_groups(h5, grouping, verdicts)
        write_pixel_curves(h5, merge_chunks(chunks), shape)
        model = h5.create_group("model")
        write_dataset(model, "terms", np.array(terms or [""]), "1")
        if source.x is not None:
            write_dataset(h5, "x", source.x, "m")
        if source.y is not None:
            write_dataset(h5, "y", source.y, "m")
    log.info("wrote %s: %d pixels ok, %d suspect, %d failed", output, counts["ok"], counts["suspect"],
             counts["failed"])
    if (calibration := spring_constant_summary(message)) is not None:
        log.warning("%s: %s", output, calibration)
    return counts


def _groups(source, config, config_text: str, flat: dict, values: dict, sigmas: dict, names: list[str],
            status: np.ndarray, diagnose: bool, engine=None):
    """The pixels' groups and (``diagnose``) their verdicts (afmid.maps.groups, afmid.maps.group_diagnosis; the
    representatives diagnosed on ``engine``)."""
    from afmid.maps.group_diagnosis import diagnose_groups
    from afmid.maps.groups import group_pixels

    fitted = status != STATUS_FAILED
    maps = {**flat, **values, **{f"{name}_sigma": sigma for name, sigma in sigmas.items()}}
    grouping = group_pixels(maps, names, fitted, (source.rows, source.cols), seed=config.fit.seed)
    log.info("%d group(s) of pixels by residual signature and parameters (silhouette %.2f)", grouping.n_groups,
             grouping.silhouette)
    verdicts = diagnose_groups(grouping, maps, source, config_text, str(config.source) if config.source else None,
                               diagnose=diagnose, engine=engine)
    return grouping, verdicts


__all__ = ["run_map", "write_map_result", "default_chunk", "sidecar_for", "STATUS_OK", "STATUS_SUSPECT"]
