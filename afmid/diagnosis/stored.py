"""A diagnosis kept: :func:`afmid.diagnosis.diagnose.suggest`'s answer stored with a key of what it depends on,
and reused, not recomputed, while the key matches.

The diagnosis refits the trace once per catalog effect the run lacks: it is the report's cost (the demo's run1: ~20
s; a 600-period record: minutes). ``afmid report run1.h5 run2.h5`` after ``afmid report run1.h5`` asked for run1's
again. Two places keep a diagnosis (docs/file-formats.md, "/diagnosis"; docs/diagnosis.md, "A diagnosis kept"):

* **The run file's /diagnosis group**, written only by a command that writes the run file anyway: the front door's
  :meth:`afmid.api.fit.Fit.save` after :meth:`Fit.diagnose`. ``afmid report`` never writes into a run file (an
  input is never modified).
* **A cache of diagnoses** (:func:`cache_folder`: ``$AFMID_DIAGNOSIS_CACHE``, else ``$XDG_CACHE_HOME/afmid/diagnoses``,
  i.e. ``~/.cache/afmid/diagnoses``; ``AFMID_DIAGNOSIS_CACHE=off`` turns it off), one JSON file per key, written
  atomically by ``afmid report`` after each diagnosis it makes. Deleting the folder only costs time.

The key (:func:`diagnosis_key`) is a SHA-256 over everything the answer depends on: the run's contents as
:func:`afmid.runfile.load_run` reads them (its config, model, coefficients, separation, errors, per-period and
per-sample arrays; not its file name, its creation time or the ground truth), the input trace's recorded SHA-256,
the diagnosis settings, the afmid version and a fingerprint of afmid's own source (so an edited afmid diagnoses
again). A stored answer is used only when its key is the key of the run at hand; a run whose input changed since the
fit is not looked up (:func:`suggest` says so itself).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import math
import os
from pathlib import Path

import numpy as np

from afmid.version import __version__

log = logging.getLogger(__name__)

#: Layout of a stored answer; a change of what is stored bumps it (old entries then no longer match).
STORE_SCHEMA = 1
#: RunData fields the diagnosis does not read (the file's name, the input's location: its SHA-256 is in the key).
_NOT_IN_KEY = {"path", "input_path", "truth", "warnings"}
#: Name of the run file's group (docs/file-formats.md).
GROUP = "diagnosis"


# --------------------------------------------------------------------------- the key
@functools.cache
def code_fingerprint() -> str:
    """SHA-256 of afmid's Python source (every ``afmid/**/*.py``, in path order): a diagnosis made by other code
    is not reused, even under the same version number (an editable install between releases)."""
    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _feed(h, value) -> None:
    """Hash ``value`` (arrays by dtype, shape and bytes; mappings in key order; floats exactly)."""
    if isinstance(value, np.ndarray):
        h.update(f"array{value.dtype.str}{value.shape}".encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, dict):
        h.update(b"{")
        for key in sorted(value, key=str):
            h.update(repr(str(key)).encode())
            _feed(h, value[key])
        h.update(b"}")
    elif isinstance(value, (list, tuple)):
        h.update(b"[")
        for item in value:
            _feed(h, item)
        h.update(b"]")
    elif isinstance(value, (float, np.floating)):
        h.update(float(value).hex().encode())
    else:
        h.update(repr(value).encode())


def diagnosis_key(run, settings: dict | None = None) -> str:
    """The key of ``run``'s diagnosis (hex SHA-256): what the answer depends on (module docstring)."""
    from afmid.config import dump_config

    h = hashlib.sha256()
    _feed(h, {"schema": STORE_SCHEMA, "afmid": __version__, "code": code_fingerprint(), "settings": settings or {}})
    for f in dataclasses.fields(run):
        if f.name in _NOT_IN_KEY:
            continue
        value = getattr(run, f.name)
        h.update(f.name.encode())
        _feed(h, dump_config(value) if f.name == "config" else value)
    return h.hexdigest()


# --------------------------------------------------------------------------- the answer as text
def _plain(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    raise TypeError(f"{type(value).__name__} in a diagnosis")


def encode(answer: dict) -> str:
    """:func:`suggest`'s answer as JSON text; NaN and infinities kept (Python's JSON reads them back), so the
    answer read back gives the page and summary.json the same numbers as the one made."""
    return json.dumps(answer, default=_plain, allow_nan=True, ensure_ascii=False)


def decode(text: str) -> dict:
    return json.loads(text)


# --------------------------------------------------------------------------- the cache folder
def cache_folder() -> Path | None:
    """Where ``afmid report`` keeps diagnoses (module docstring); None when turned off."""
    chosen = os.environ.get("AFMID_DIAGNOSIS_CACHE")
    if chosen is not None:
        return None if chosen.strip().lower() in ("", "off", "0", "no") else Path(chosen)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "afmid" / "diagnoses"


def cached(key: str) -> dict | None:
    """The cached answer of ``key``, or None (none kept, unreadable, or made for another key)."""
    folder = cache_folder()
    if folder is None:
        return None
    path = folder / f"{key}.json"
    try:
        entry = decode(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(entry, dict) or entry.get("key") != key or not isinstance(entry.get("answer"), dict):
        return None
    return entry["answer"]


def remember(key: str, answer: dict, run_name: str) -> Path | None:
    """Keep ``answer`` under ``key`` in the cache folder (atomically); None when the cache is off or not writable
    (the report goes on: a cache that cannot be written costs only time next time)."""
    from afmid.errors import OutputError
    from afmid.io.trace import atomic_path, now_iso

    folder = cache_folder()
    if folder is None:
        return None
    path = folder / f"{key}.json"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            tmp.write_text(encode({"key": key, "afmid_version": __version__, "made": now_iso(), "run": run_name,
                                   "answer": answer}), encoding="utf-8")
    except (OSError, OutputError) as exc:
        log.info("the diagnosis of %s is not cached (%s)", run_name, exc)
        return None
    return path


# --------------------------------------------------------------------------- the run file's group
def write_group(h5, answer: dict, key: str, settings: dict | None = None) -> None:
    """``answer`` as the run file's /diagnosis group (docs/file-formats.md): the whole answer as JSON text, and the
    candidates tried as columns (ΔBIC and the error after, dimensionless) for a reader without JSON."""
    from afmid.io.trace import now_iso

    g = h5.create_group(GROUP)
    g.attrs["key"] = key
    g.attrs["afmid_version"] = __version__
    g.attrs["made"] = now_iso()
    g.attrs["settings"] = json.dumps(settings or {})
    g.attrs["meaning"] = ("afmid.diagnosis.diagnose.suggest's answer for this run (summary.json's diagnosis, "
                          "suggestions, tried); reused by afmid report while 'key' matches the run")
    tried = answer.get("tried", [])
    columns = {
        "answer": encode(answer),
        "tried_effect": [t["effect"] for t in tried],
        **{f"tried_{name}": np.asarray([math.nan if t.get(name) is None else float(t[name]) for t in tried],
                                       dtype=np.float64) for name in ("delta_bic", "error_after")},
        "suggested": [s["effect"] for s in answer.get("suggestions", [])],
        "verdict": (answer.get("diagnosis") or {}).get("verdict") or answer.get("note", ""),
    }
    for name, data in columns.items():  # every dataset has units (the file convention); these are all "1"
        numeric = isinstance(data, np.ndarray)
        ds = g.create_dataset(name, data=data, dtype=None if numeric else _text_type())
        ds.attrs["units"] = "1"


def _text_type():
    import h5py

    return h5py.string_dtype("utf-8")


def read_group(path: Path, key: str) -> dict | None:
    """The answer the run file at ``path`` stores for ``key``, or None (no group, another key, not readable)."""
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            g = h5.get(GROUP)
            if g is None or str(g.attrs.get("key", "")) != key:
                return None
            raw = g["answer"][()]
    except (OSError, KeyError, ValueError, TypeError):
        return None
    try:
        answer = decode(raw.decode("utf-8") if isinstance(raw, bytes) else str(raw))
    except ValueError:
        return None
    return answer if isinstance(answer, dict) else None


# --------------------------------------------------------------------------- the one entry point
def diagnosed(run, progress: bool = False, trace=None) -> dict:
    """:func:`afmid.diagnosis.diagnose.suggest`'s answer for ``run``: the one its run file or the cache keeps for
    this run's key, else made now (and cached). ``trace`` as :func:`suggest` takes it."""
    from afmid.diagnosis.diagnose import suggest
    from afmid.io.files import is_regular_file
    from afmid.io.trace import sha256_file

    if trace is None and run.input_path is not None and is_regular_file(run.input_path) and run.input_sha256 \
            and sha256_file(run.input_path) != run.input_sha256:
        return suggest(run, progress=progress, trace=trace)  # it says the input changed; nothing to reuse
    key = diagnosis_key(run)
    kept = read_group(run.path, key) if Path(run.path).is_file() else None
    where = f"{run.path}'s /diagnosis"
    if kept is None:
        kept, where = cached(key), f"the diagnosis cache ({cache_folder()})"
    if kept is not None:
        log.info("%s: the diagnosis kept in %s is reused (no candidate refit)", run.path.name, where)
        return kept
    # Read back as a kept one would be (lists, plain floats, NaN kept): a report shows the same whether its
    # diagnosis was made now or reused.
    answer = decode(encode(suggest(run, progress=progress, trace=trace)))
    if "note" not in answer:  # a note-only answer (a preset library, a changed input) costs nothing to make again
        remember(key, answer, run.path.name)
    return answer
