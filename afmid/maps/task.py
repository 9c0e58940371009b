"""One chunk of a force map, fitted in a worker: :func:`fit_chunk`.

A task names the map file, the merged run config (YAML text) and a range of pixels. The worker reads the map's
metadata and the chunk's traces once, builds the :class:`afmid.physics.library.Library` once, and fits the pixels in order with the task's pixel-fit strategy
(:mod:`afmid.maps.pixel_fit`; the separation is estimated per pixel: it is the topography). A pixel that cannot be fitted is marked failed with its one-line reason; it never stops the chunk.
The result is plain arrays (one value per pixel), small enough to send back to the scheduler.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

#: Status codes of a pixel, stored in /maps/status (names in its ``meaning`` attribute).
STATUS_OK, STATUS_SUSPECT, STATUS_FAILED = 0, 1, 2
STATUS_NAMES = ("ok", "suspect", "failed")


def map_config(config_text: str, source: str | None):
    """The run config of every pixel: the map's merged config with the separation left to the fit."""
    import yaml

    from afmid.config import build_config

    config = build_config(yaml.safe_load(config_text), source=Path(source) if source else None)
    config.sample.separation = None  # estimated per pixel (the topography)
    return config


def fit_chunk(task: dict) -> dict:
    """Fit pixels ``task['first']`` to ``task['stop']`` of ``task['input']``; see the module docstring.

    Returns ``{"first", "stop", "status", "message", "separation", "separation_sigma", "cv_error",
    "cv_error_noise_floor", "selected" (bit mask per pixel), the residual signature (afmid.maps.residual.SIGNATURE),
    "curve_NAME" (each pixel's force curves, pixels first: afmid.maps.pixel_curves.CURVES),
    "terms", "names", "units", "values", "sigmas", "seconds"}`` (values/sigmas: (n_quantities, n_pixels), SI, sigma = 1 sigma bootstrap).
    """
    import time

    import afmid.fit.plausibility as plausibility
    from afmid.fit.separation_share import is_separation_limited
    from afmid.errors import AfmidError
    from afmid.physics.library import build_library
    from afmid.physics.tips import tip_geometry
    from afmid.maps.pixel_fit import DEFAULT_PIXEL_FIT, PIXEL_FITS
    from afmid.maps.input_file import open_map, pixel_trace, read_pixels
    from afmid.maps.pixel_curves import collect
    from afmid.maps.residual import SIGNATURE, empty_signature

    started = time.perf_counter()
    logger = logging.getLogger("afmid")
    level = logger.level
    logger.setLevel(logging.ERROR)  # per-pixel warnings go into the status map, not the worker's log
    try:
        config = map_config(task["config"], task.get("source"))
        source = open_map(task["input"], config)
        library = build_library(config.model, config.source, tip_geometry(config.cantilever))
        first, stop = int(task["first"]), int(task["stop"])
        raw = read_pixels(source, first, stop)
    finally:
        logger.setLevel(level)
    n = stop - first
    out = {
        "first": first, "stop": stop, "status": np.full(n, STATUS_FAILED, np.int8), "message": [""] * n,
        "separation": np.full(n, np.nan), "separation_sigma": np.full(n, np.nan), "cv_error": np.full(n, np.nan),
        "cv_error_noise_floor": np.full(n, np.nan), "selected": np.zeros(n, np.int64),
        "route": np.full(n, -1, np.int8), "evaluations": np.zeros(n, np.int32),
        "terms": list(library.names), "names": [], "units": [], "effects": [], "values": None, "sigmas": None,
    }
    unfitted = empty_signature()
    for name in SIGNATURE:  # the residual's character (afmid.maps.residual): integer codes or floats
        out[name] = np.full(n, unfitted[name], np.int8 if isinstance(unfitted[name], int) else float)
    if len(library.names) > 63:
        raise ValueError("the selected-term bit mask holds at most 63 terms")
    per_pixel: list[dict | None] = [None] * n
    curves: list[dict | None] = [None] * n  # each pixel's force curves (afmid.maps.pixel_curves)
    strategy = PIXEL_FITS.get(task.get("pixel_fit") or DEFAULT_PIXEL_FIT)(config, library)
    failures = (ValueError, FloatingPointError, np.linalg.LinAlgError, ArithmeticError)
    traces: list = [None] * n  # the chunk's traces first: a strategy may use what they share (the drive)
    for i in range(n):
        logger.setLevel(logging.ERROR)
        try:
            traces[i] = pixel_trace(source, raw[i], config, first + i)
        except AfmidError as exc:
            out["message"][i] = exc.message
        except failures as exc:
            out["message"][i] = f"the fit failed: {type(exc).__name__}: {exc}"
        finally:
            logger.setLevel(level)
    strategy.start_chunk([trace for trace in traces if trace is not None])
    for i in range(n):
        if traces[i] is None:
            continue
        pixel = first + i
        logger.setLevel(logging.ERROR)
        try:
            result = strategy.fit(traces[i], pixel)
        except AfmidError as exc:
            out["message"][i] = exc.message
            continue
        except failures as exc:
            out["message"][i] = f"the fit failed: {type(exc).__name__}: {exc}"
            continue
        finally:
            logger.setLevel(level)
        per_pixel[i] = result.quantities
        curves[i] = result.curves
        out["separation"][i] = result.separation
        out["separation_sigma"][i] = result.separation_sigma
        out["cv_error"][i] = result.cv_error
        out["cv_error_noise_floor"][i] = result.cv_error_noise_floor
        out["selected"][i] = int(sum(1 << k for k, m in enumerate(result.selected[:len(library)]) if m))
        out["route"][i] = result.route
        out["evaluations"][i] = result.evaluations
        for name, value in result.signature.items():
            out[name][i] = value
        # Defects the checks only warned about (not those repaired or informational), and implausible read-outs.
        # Not the separation share's warning: it concerns the force curve, and the read-outs' error bars already
        # carry the separation's sigma.
        doubts = [w for w in result.warnings if w.startswith("warning") and not is_separation_limited(w)]
        doubts += [f"implausible: {reason}"
                   for reason in plausibility.violations(plausibility.check_plausibility(result.quantities))]
        separation = plausibility.judge_separation(result.separation, result.separation_sigma)
        if not separation.plausible:  # the topography at this pixel is not a measurement
            doubts.append(f"implausible: {separation.reason}")
        out["status"][i] = STATUS_SUSPECT if doubts else STATUS_OK
        out["message"][i] = "; ".join(doubts)
    names: list[str] = []
    for q in per_pixel:
        for name, item in (q or {}).items():
            if name not in names:
                names.append(name)
                out["units"].append(item["unit"])
                out["effects"].append(item.get("effect") or "")
    out["names"] = names
    values = np.full((len(names), n), np.nan)
    sigmas = np.full((len(names), n), np.nan)
    for i, q in enumerate(per_pixel):
        for k, name in enumerate(names):
            if q and name in q:
                values[k, i] = q[name]["value"]
                sigmas[k, i] = q[name]["error"]
    out["values"], out["sigmas"] = values, sigmas
    out.update(collect(curves))
    out["seconds"] = time.perf_counter() - started
    return out


#: The end of a read-out's reason when a spring constant off by a factor explains it (afmid.fit.plausibility).
_SPRING_CONSTANT_ADVICE = "check cantilever.spring_constant"


def spring_constant_summary(messages) -> str | None:
    """The map's one warning when pixels' read-outs are implausible in a way a spring constant off by a factor
    explains (:func:`afmid.fit.plausibility.spring_constant_cause`): how many pixels, and the first one's clause
    (the factor's interval and what the read-outs would be); None when no pixel says so. A wrong k spoils every
    pixel alike, so the count and one pixel's numbers are the summary."""
    flat = [str(m) for m in np.asarray(messages, dtype=object).ravel()]
    hits = [i for i, m in enumerate(flat) if _SPRING_CONSTANT_ADVICE in m]
    if not hits:
        return None
    first = flat[hits[0]]
    end = first.index(_SPRING_CONSTANT_ADVICE) + len(_SPRING_CONSTANT_ADVICE)
    start = first.rfind("a spring constant ", 0, end)
    return (f"implausible read-outs in {len(hits)} of {len(flat)} pixels (suspect); at pixel {hits[0]}: "
            f"{first[max(start, 0):end]}")

