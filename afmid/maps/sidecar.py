"""The map's sidecar folder ``RESULT.h5.afmid-map/``: afmid's own folder of the finished chunks of an unfinished
``afmid map`` (rules in docs/maps.md, "The sidecar folder"; layout in docs/file-formats.md).

- **Marker.** afmid creates the folder with a marker file (:data:`MARKER_NAME`) before anything else in it. A folder
  of that name without the marker is a user's: refused with one line, nothing in it read, written or deleted. A
  symbolic link at the sidecar's path is refused, never followed; a link inside it (a chunk, the key) is removed
  (the link, not what it points to) and never read.
- **Lock.** A run holds :func:`afmid.batch.folder_lock.folder_lock` on the folder for its whole life: a second run
  on the same output refuses at once, naming the first's pid.
- **Key.** ``key.json`` names what the chunks were fitted for (the input's SHA-256, the config's SHA-256, the map
  shape, the chunking, the pixel fit, the chunk layout). A folder of another key has its chunks discarded: the
  map starts anew.
- **Chunk identity.** Each chunk carries the key and its pixel range inside it, so a chunk is checked by content,
  not by name: an unreadable one (truncated, not an npz) or one whose identity is not this run's chunk of that
  name (another pixel range, another input or config) is discarded with a one-line note and fitted again.

When the map is written the folder is removed (renamed away first, under the lock, so that a run starting
meanwhile never sees a half-removed folder); files in it that afmid did not write are left, with the folder.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import stat
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from afmid.errors import InputError, OutputError

log = logging.getLogger(__name__)

MARKER_NAME = ".afmid-map-sidecar"
#: The marker's first line: what the folder is (a person who finds it reads this).
MARKER_TEXT = ("afmid map sidecar folder: the finished chunks of an unfinished `afmid map`; "
               "run the same command again to resume it, or delete this folder to start anew\n")
#: What a marker must begin with (the rest of its text may change between versions).
MARKER_WORDS = "afmid map sidecar folder"
KEY_NAME = "key.json"
CHUNK_GLOB = "chunk_*.npz"
#: The command-line option a refusal names (the sidecar's path follows from ``afmid map -o``).
OUTPUT_OPTION = "-o"
LINK_REFUSAL = ("is a symbolic link; afmid keeps a map's finished chunks in a folder of this name and never follows "
                "a link there: remove the link or choose another -o")
#: What :func:`~afmid.batch.folder_lock.folder_lock` says a holder is.
WRITER = "afmid map"
#: Why a chunk file cannot be read as one (a truncated or foreign file).
UNREADABLE = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile)


def chunk_name(index: int) -> str:
    return f"chunk_{index:06d}.npz"


def chunk_identity(key: dict, first: int, stop: int) -> dict:
    """What a chunk was fitted for: the map's key and its pixel range [first, stop)."""
    return {"key": key, "first": int(first), "stop": int(stop)}


class Sidecar:
    """A claimed, locked sidecar folder of one map run (made by :func:`held_sidecar`).

    ``key``: the run's key (see the module's docstring); ``bounds``: the chunks' pixel ranges, chunk i =
    pixels [bounds[i][0], bounds[i][1]) in row-major order."""

    def __init__(self, folder: Path, key: dict, bounds: list[tuple[int, int]]):
        self.folder, self.key, self.bounds = folder, key, bounds

    def path(self, index: int) -> Path:
        return self.folder / chunk_name(index)

    def finished(self) -> set[int]:
        """The chunks already fitted for this key; a damaged or foreign chunk is discarded with a one-line note."""
        done = set()
        for index in range(len(self.bounds)):
            if self._checked(index) is not None:
                done.add(index)
        return done

    def save(self, index: int, arrays: dict[str, np.ndarray]) -> None:
        """Chunk ``index`` (its arrays), written atomically with its identity."""
        from afmid.io.trace import atomic_path

        lo, hi = self.bounds[index]
        arrays = dict(arrays, identity=np.array(json.dumps(chunk_identity(self.key, lo, hi), sort_keys=True)))
        with atomic_path(self.path(index)) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)

    def load_all(self) -> list[dict[str, np.ndarray]]:
        """Every chunk's arrays, in order. A chunk missing or spoiled since the start of the run (discarded with
        its note) is an InputError: the same command fits it again."""
        chunks = []
        for index in range(len(self.bounds)):
            chunk = self._checked(index)
            if chunk is None:
                raise InputError(f"{chunk_name(index)} was removed or changed while the map ran; run the same "
                                 "command again to fit its pixels", file=self.folder)
            chunks.append(chunk)
        return chunks

    def n_saved(self) -> int:
        return sum(1 for _ in self.folder.glob(CHUNK_GLOB))

    def _checked(self, index: int) -> dict[str, np.ndarray] | None:
        """Chunk ``index``'s arrays if its file is this run's chunk of that index; else None (a bad file removed)."""
        path = self.path(index)
        try:
            mode = os.lstat(path).st_mode
        except FileNotFoundError:
            return None
        lo, hi = self.bounds[index]
        why = None
        if not stat.S_ISREG(mode):
            why = "is not a regular file (a link?)"
        else:
            try:
                with np.load(path, allow_pickle=False) as z:
                    chunk = {k: z[k] for k in z.files}
                identity = json.loads(str(chunk["identity"]))
            except UNREADABLE as exc:
                why = f"is damaged ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else 'unreadable'})"
            else:
                why = self._foreign(identity, chunk, lo, hi)
        if why is None:
            return chunk
        log.warning("%s %s: discarded, its pixels %d-%d are fitted again", path, why, lo, hi - 1)
        with contextlib.suppress(FileNotFoundError):
            path.unlink()  # a link: the link itself, never its target
        return None

    def _foreign(self, identity, chunk: dict, lo: int, hi: int) -> str | None:
        """Why a readable chunk is not this run's chunk of pixels [lo, hi) (None: it is)."""
        if not isinstance(identity, dict) or identity.get("key") != self.key:
            return "was fitted for another input, config or chunking"
        first, stop = identity.get("first"), identity.get("stop")
        if (first, stop) != (lo, hi):
            return f"holds pixels {first}-{stop - 1 if isinstance(stop, int) else stop}, not {lo}-{hi - 1}"
        if np.shape(chunk.get("status")) != (hi - lo,):
            return "is damaged (its status does not have one value per pixel)"
        return None


@contextlib.contextmanager
def held_sidecar(folder: Path, key: dict, bounds: list[tuple[int, int]]) -> Iterator[Sidecar]:
    """Claim and lock the sidecar ``folder`` for a run of ``key`` (see the module's docstring for what is refused).

    On success (the block ends normally) the folder is removed; on an error or interrupt it is kept when it holds a
    chunk (the same command resumes) and removed when it holds none (a run that failed early leaves nothing)."""
    from afmid.batch.folder_lock import folder_lock

    _claim(folder)
    with folder_lock(folder, key=OUTPUT_OPTION, writer=WRITER):
        _check_marker(folder)  # again, now that it is ours: the folder may have changed meanwhile
        sidecar = Sidecar(folder, key, bounds)
        remove = True
        try:
            _adopt_key(folder, key)
            yield sidecar
        except BaseException:
            remove = sidecar.n_saved() == 0
            raise
        finally:
            if remove:
                _remove(folder)


def _claim(folder: Path) -> None:
    """Refuse a link or a folder of the name that is not afmid's; create the folder with its marker if absent."""
    try:
        mode = os.lstat(folder).st_mode
    except FileNotFoundError:
        mode = None
    if mode is not None and stat.S_ISLNK(mode):
        raise OutputError(LINK_REFUSAL, file=folder, key=OUTPUT_OPTION)
    if mode is not None:
        _check_marker(folder)
        return
    try:
        folder.mkdir()
    except FileExistsError:  # made meanwhile (another run): it must be afmid's
        _claim(folder)
        return
    except OSError as exc:
        raise OutputError(f"cannot create the map's sidecar folder: {exc.strerror or exc}", file=folder,
                          key=OUTPUT_OPTION) from None
    try:
        _write_atomically(folder / MARKER_NAME, MARKER_TEXT)
    except BaseException:
        with contextlib.suppress(OSError):
            folder.rmdir()
        raise


def _check_marker(folder: Path) -> None:
    """OutputError (nothing touched) unless ``folder`` is a real folder holding afmid's marker file."""
    mode = os.lstat(folder).st_mode
    if stat.S_ISLNK(mode):
        raise OutputError(LINK_REFUSAL, file=folder, key=OUTPUT_OPTION)
    refusal = ("exists and is not afmid's sidecar folder (no marker file " + MARKER_NAME + "); afmid keeps a map's "
               "finished chunks in a folder of this name: move or rename it, or choose another -o")
    if not stat.S_ISDIR(mode):
        raise OutputError(refusal, file=folder, key=OUTPUT_OPTION)
    try:
        fd = os.open(folder / MARKER_NAME, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:
        raise OutputError(refusal, file=folder, key=OUTPUT_OPTION) from None
    try:
        text = os.read(fd, len(MARKER_TEXT.encode()) + 1).decode("utf-8", "replace")
    finally:
        os.close(fd)
    if not text.startswith(MARKER_WORDS):
        raise OutputError(refusal, file=folder, key=OUTPUT_OPTION)


def _adopt_key(folder: Path, key: dict) -> None:
    """Keep the chunks of a folder of this ``key``; discard those of another one and write this key."""
    path = folder / KEY_NAME
    old = None
    with contextlib.suppress(*UNREADABLE):
        if stat.S_ISREG(os.lstat(path).st_mode):
            old = json.loads(path.read_text())
    if old == key:
        return
    chunks = sorted(folder.glob(CHUNK_GLOB))
    if chunks:
        log.warning("%s holds %d chunk(s) of another input, config or chunking: discarded, starting the map anew",
                    folder, len(chunks))
    for chunk in chunks:
        with contextlib.suppress(FileNotFoundError):
            chunk.unlink()
    with contextlib.suppress(FileNotFoundError):
        if not stat.S_ISREG(os.lstat(path).st_mode):
            path.unlink()  # a link or other non-file in afmid's place: the link itself, never its target
    _write_atomically(path, json.dumps(key))


def _write_atomically(path: Path, text: str) -> None:
    from afmid.io.trace import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(text)


def _remove(folder: Path) -> None:
    """Remove the sidecar (still locked): afmid's own files only. A folder with nothing else is renamed to a
    temporary name first (a stale one is removed by the next run, afmid.tempfiles) and then deleted."""
    import afmid.tempfiles as tempfiles
    from afmid.batch.folder_lock import LOCK_NAME

    own = {MARKER_NAME, KEY_NAME, LOCK_NAME}
    others = [p.name for p in folder.iterdir()
              if p.name not in own and not p.match(CHUNK_GLOB) and not p.name.startswith(tempfiles.PREFIX)]
    if others:
        for path in [*folder.glob(CHUNK_GLOB), folder / KEY_NAME]:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
        log.warning("left %s: it holds files afmid did not write (%s)", folder, ", ".join(sorted(others)[:5]))
        return
    try:
        bin_ = Path(tempfile.mkdtemp(prefix=tempfiles.prefix_for(folder), dir=folder.parent))
        os.rename(folder, bin_ / folder.name)
        shutil.rmtree(bin_)
    except OSError as exc:  # the result is written: a folder left over is worth a note, not a failure
        log.warning("could not remove %s: %s", folder, exc.strerror or exc)
