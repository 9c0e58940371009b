"""Input and output: the trace a run works on, and afmid's HDF5 file formats.

Data flow: a config's ``data`` section -> :func:`load_trace` (reader registry,
unit conversion to metres, sign to "positive toward the sample", metadata
merging) -> :class:`Trace`. Outputs are written by :func:`atomic_hdf5`: to a
temporary file in the destination folder, renamed into place only when
complete, so an interrupted run never leaves a half-written file.

File layouts are documented in docs/file-formats.md (keep the two in sync).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import logging
import os
import stat
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from afmid.version import __version__
from afmid.errors import ConfigError, InputError, OutputError
# The lever's type lives in afmid.io.cantilever; `from afmid.io.trace import Cantilever` keeps working.
from afmid.io.cantilever import Cantilever
from afmid.io.file_values import check_file_instrument_value, merge_cantilever, merged_value, same_value
from afmid.io.files import (FORMAT_VERSION, check_folder_writable, check_input_file, check_output_target,
                             is_regular_file)
from afmid.preprocess.harmonics import MIN_PERIODS  # the least a trace must hold (the harmonic analysis needs it too)

log = logging.getLogger(__name__)

TRACE_FORMAT = "afmid-trace"
RUN_FORMAT = "afmid-run"

_UNIT_SCALE = {"m": 1.0, "nm": 1e-9, "pm": 1e-12, "um": 1e-6}


@dataclass
class Truth:
    """Ground truth stored by the simulator."""

    force: np.ndarray  # N, repulsive positive, per sample
    separation: np.ndarray  # m
    velocity: np.ndarray  # dx/dt, m/s
    model: str
    effects: list[str]
    parameters: dict[str, float]  # SI
    units: dict[str, str]
    extra: dict[str, Any] = field(default_factory=dict)  # drive force amplitude, separation, ...
    #: Per-sample truth beyond the tip's: name -> (array, unit); a scanning record's rest separation d(t), surface
    #: height, z piezo, lateral position (afmid.simulate.scan). Stored as /truth/tracks/NAME.
    tracks: dict[str, tuple[np.ndarray, str]] = field(default_factory=dict)


@dataclass
class Trace:
    """A deflection trace in SI, positive toward the sample."""

    deflection: np.ndarray  # m
    sample_rate: float  # Hz
    cantilever: Cantilever
    drive_frequency: float  # Hz (nominal; the fit re-estimates it)
    time: np.ndarray | None = None  # s, when the file had a time axis
    truth: Truth | None = None
    path: Path | None = None
    sha256: str | None = None
    sources: dict[str, str] = field(default_factory=dict)  # value -> where it came from
    overridden: list[str] = field(default_factory=list)  # config keys that overrode file metadata
    drive_force_amplitude: float | None = None  # N, if known
    findings: list = field(default_factory=list)  # afmid.io.defects.Finding: defects found on loading
    #: afmid.preprocess.harmonics.MeasuredDrive: the drive measured on loading (by the defect checks, as the fit measures it)
    drive: Any = None
    first_sample: int = 0  # index in the file of the first sample kept (data.start, or the onset of the motion)
    #: the config's ``data:`` keys the trace was read with (empty for an array): a fit of it stores how to read it
    reading: dict = field(default_factory=dict)

    @classmethod
    def from_array(cls, deflection, sample_rate: float, *, cantilever: Cantilever | None = None,
                   drive_frequency: float | None = None, units: str = "m", positive: str = "toward_sample",
                   drive_force_amplitude: float | None = None) -> "Trace":
        """A trace from an array of deflection samples, checked as a file's trace is on loading (:func:`check_trace`).

        ``deflection`` in ``units`` (m, nm, pm or um), its sign ``positive`` toward_sample or away_from_sample;
        ``sample_rate`` in Hz; ``cantilever`` the lever (:class:`Cantilever`, required); ``drive_frequency`` in Hz
        (default: the lever's resonance frequency); ``drive_force_amplitude`` in N, if known.
        """
        return trace_from_array(deflection, sample_rate, cantilever, drive_frequency, units, positive,
                                drive_force_amplitude)

    def drive_for(self, detrend: str):
        """The drive measured on loading (an :class:`afmid.preprocess.harmonics.DriveEstimate`), if it holds for a fit with
        fit.detrend ``detrend`` on these very samples, times and nominal frequency; else None (measure it)."""
        if self.drive is None or not self.drive.matches(self.deflection, self.sample_rate, self.time,
                                                        self.drive_frequency, detrend):
            return None
        return self.drive.estimate

    @property
    def n_samples(self) -> int:
        return int(self.deflection.size)

    @property
    def times(self) -> np.ndarray:
        """Sample times, s (from the time column, else from the sample rate)."""
        if self.time is not None:
            return self.time
        return (self.first_sample + np.arange(self.n_samples)) / self.sample_rate

    @property
    def samples_per_period(self) -> float:
        return self.sample_rate / self.drive_frequency

    @property
    def n_periods(self) -> float:
        return self.n_samples / self.samples_per_period


# --------------------------------------------------------------------------- helpers
def sha256_file(path: str | Path) -> str:
    """The SHA-256 of regular file ``path`` (InputError for anything else: a FIFO or a device is never read)."""
    if not is_regular_file(path):
        raise InputError("not a regular file (a FIFO, a device, a folder or missing): its SHA-256 is not taken",
                         file=path)
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # non-blocking: a FIFO swapped in after the check cannot block
    if not stat.S_ISREG(os.fstat(fd).st_mode):  # replaced between the check and the open
        os.close(fd)
        raise InputError("not a regular file: its SHA-256 is not taken", file=path)
    h = hashlib.sha256()
    with os.fdopen(fd, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def now_iso() -> str:
    """Current time, ISO 8601 with the local zone offset."""
    return _dt.datetime.now().astimezone().isoformat(timespec="seconds")


def _file_id(path: str | Path) -> tuple[int, int] | None:
    """(device, inode) of an existing file (following symbolic links), else None."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


def _real(path: str | Path) -> Path:
    """``path`` with symbolic links resolved (as far as they resolve: a link loop stays as written)."""
    try:
        return Path(path).resolve()
    except (OSError, RuntimeError):
        return Path(path).absolute()


def lies_inside(path: str | Path, folder: str | Path) -> bool:
    """Whether ``path`` is ``folder`` or anywhere below it, comparing real paths."""
    return _real(path).is_relative_to(_real(folder))


def refuse_input_as_output(outputs: str | Path | list[str | Path], inputs: dict[str | Path | None, str] | None,
                           folder: bool = False, key: str | None = None) -> None:
    """OutputError if an output path (one, or a list) is one of the command's ``inputs`` (input path -> what it
    is, e.g. ``"the run config"``; None paths are ignored), whether or not ``--overwrite`` was given: afmid never
    replaces or deletes an input. Every command checks its outputs with this before writing.

    Paths are compared as real files: the same device and inode (symbolic and hard links included), else the
    same resolved path (for files that do not exist). A ``folder`` output (the report folder) is also refused
    when an input lies anywhere inside it.
    """
    named = [(Path(p), what) for p, what in (inputs or {}).items() if p is not None]
    by_id: dict[tuple[int, int], tuple[Path, str]] = {}
    by_path: dict[Path, tuple[Path, str]] = {}
    for input_path, what in named:
        file_id = _file_id(input_path)
        if file_id is not None:
            by_id.setdefault(file_id, (input_path, what))
        by_path.setdefault(_real(input_path), (input_path, what))
    for output in [outputs] if isinstance(outputs, (str, Path)) else outputs:
        file_id = _file_id(output)
        hit = (by_id.get(file_id) if file_id is not None else None) or by_path.get(_real(output))
        if hit is not None:
            raise OutputError(f"is an input of this command ({hit[1]}); write the output elsewhere", file=output,
                              key=key)
        for input_path, what in named if folder else ():
            if lies_inside(input_path, Path(output)):
                raise OutputError(f"holds an input of this command ({what}: {input_path}); write the output "
                                  "elsewhere", file=output, key=key)


def check_output_path(path: str | Path, overwrite: bool, inputs: dict[str | Path, str] | None = None) -> Path:
    """The output file ``path``, after refusing an input (``inputs``: path -> what it is, see
    :func:`refuse_input_as_output`), an existing file without ``overwrite``, a folder and a missing parent."""
    path = Path(path)
    refuse_input_as_output(path, inputs)
    check_output_target(path)  # a FIFO or device: refused even with --overwrite
    if path.exists() and not overwrite:
        raise OutputError("output exists; pass --overwrite to replace it", file=path)
    if path.exists() and path.is_dir():
        raise OutputError("output path is a directory", file=path)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.exists():
        raise OutputError(f"output folder {parent} does not exist", file=path)
    check_folder_writable(path)  # now, not after the work (a read-only place)
    return path


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it into place on success only.

    The temporary name tells host and process (:mod:`afmid.tempfiles`); temporary files that processes gone
    since left in the folder are removed first. A full disk is one :class:`OutputError` naming ``path``; an
    interrupt, even one that Python swallowed on the way (:mod:`afmid.interrupts`), leaves nothing.
    """
    import afmid.interrupts as interrupts
    import afmid.tempfiles as tempfiles

    interrupts.raise_if_pending()  # an interrupt swallowed earlier in the run: do not even start
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    tempfiles.remove_stale(folder)
    held = contextlib.ExitStack()  # a signal while the file is made must not leave it nameless
    held.enter_context(interrupts.deferred())
    try:
        fd, tmp = tempfile.mkstemp(prefix=tempfiles.prefix_for(path), dir=folder)
    except OSError as exc:  # unwritable or vanished folder: the user's environment, not a bug
        held.close()
        if tempfiles.is_write_refused(exc):
            raise tempfiles.write_refused_error(exc, path) from None
        raise OutputError(f"cannot write in folder {path.parent}: {exc.strerror or exc}", file=path) from exc
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        held.close()  # delivers a signal that came meanwhile, here, where the file is removed
        yield tmp_path
        interrupts.raise_if_pending()
        # mkstemp creates the file private (0600); give the output the permissions the umask allows.
        umask = os.umask(0)
        os.umask(umask)
        if tmp_path.is_file():
            os.chmod(tmp_path, 0o666 & ~umask)
        os.replace(tmp_path, path)
    except BaseException as exc:
        tmp_path.unlink(missing_ok=True)
        if tempfiles.is_write_refused(exc):
            raise tempfiles.write_refused_error(exc, path) from None
        raise


@contextlib.contextmanager
def atomic_hdf5(path: str | Path, file_format: str, config_text: str, inputs: dict[str, str] | None = None):
    """Open a new afmid HDF5 file for writing, with provenance root attributes.

    ``inputs`` maps input paths to their SHA-256. The file appears at ``path``
    only if the block completes. The HDF5 library writes through a file object that holds a failed write
    (a full disk) instead of failing it, and Ctrl-C / SIGTERM wait until the file is closed: either could
    otherwise make the library crash (:mod:`afmid.tempfiles`, :mod:`afmid.interrupts`).
    """
    import h5py

    import afmid.interrupts as interrupts
    from afmid.tempfiles import ErrorHoldingFile

    with atomic_path(path) as tmp, open(tmp, "r+b", buffering=0) as raw:
        sink = ErrorHoldingFile(raw)
        with interrupts.deferred():
            try:
                with h5py.File(sink, "w") as h5:
                    h5.attrs["afmid_version"] = __version__
                    h5.attrs["format"] = file_format
                    h5.attrs["format_version"] = FORMAT_VERSION
                    h5.attrs["created"] = now_iso()
                    h5.attrs["config"] = config_text
                    for i, (ipath, digest) in enumerate((inputs or {}).items()):
                        suffix = "" if i == 0 else f"_{i}"
                        h5.attrs[f"input_path{suffix}"] = str(Path(ipath).resolve())
                        h5.attrs[f"input_sha256{suffix}"] = digest
                    yield h5
            except Exception:
                if sink.error is None:
                    raise
                # The library failed after a write was held (it read back what never reached the disk): the
                # held error is the cause.
            sink.flush()
            if sink.error is not None:
                _raise_held(sink.error, path)


def _raise_held(error: BaseException, path: Path | str) -> None:
    """Raise what went wrong while the HDF5 library wrote ``path``: an interrupt as it is, a full disk for
    :func:`atomic_path` to report, any other failed write as one error line naming the output."""
    from afmid.tempfiles import is_write_refused

    if isinstance(error, OSError) and not is_write_refused(error):
        raise OutputError(f"cannot write: {error.strerror or error}", file=path) from error
    raise error


def write_dataset(group, name: str, data, units: str, **attrs):
    """Create a dataset with its mandatory ``units`` attribute."""
    arr = np.asarray(data)
    if arr.dtype.kind == "U":
        import h5py

        ds = group.create_dataset(name, data=arr.astype(object), dtype=h5py.string_dtype())
    else:
        kwargs = {"compression": "gzip", "compression_opts": 4, "shuffle": True} if arr.size > 4096 else {}
        ds = group.create_dataset(name, data=arr, **kwargs)
    ds.attrs["units"] = units
    for key, value in attrs.items():
        ds.attrs[key] = value
    return ds


def create_dataset(group, name: str, shape: tuple[int, ...], dtype, units: str, **attrs):
    """An empty dataset laid out and compressed as :func:`write_dataset` would store an array of this shape,
    to be filled in slices (long outputs written chunk by chunk; the stored values are the same)."""
    size = int(np.prod(shape))
    kwargs = {"compression": "gzip", "compression_opts": 4, "shuffle": True} if size > 4096 else {}
    ds = group.create_dataset(name, shape=shape, dtype=dtype, **kwargs)
    ds.attrs["units"] = units
    for key, value in attrs.items():
        ds.attrs[key] = value
    return ds


# --------------------------------------------------------------------------- trace files
def write_trace_file(path: str | Path, trace: Trace, config_text: str, overwrite: bool = False) -> Path:
    """Write an afmid trace file (layout in docs/file-formats.md)."""
    path = check_output_path(path, overwrite)
    inputs = {str(trace.path): trace.sha256} if trace.path and trace.sha256 else None
    with atomic_hdf5(path, TRACE_FORMAT, config_text, inputs) as h5:
        h5.attrs["sample_rate"] = float(trace.sample_rate)
        write_dataset(h5, "deflection", trace.deflection, "m", positive="toward_sample")
        if trace.time is not None:
            write_dataset(h5, "time", trace.time, "s")
        cl = h5.create_group("cantilever")
        cl.attrs["spring_constant"] = float(trace.cantilever.spring_constant)
        cl.attrs["resonance_frequency"] = float(trace.cantilever.resonance_frequency)
        cl.attrs["quality_factor"] = float(trace.cantilever.quality_factor)
        cl.attrs["tip_radius"] = np.nan if trace.cantilever.tip_radius is None else float(trace.cantilever.tip_radius)
        cl.attrs["units"] = "spring_constant: N/m; resonance_frequency: Hz; quality_factor: 1; tip_radius: m"
        dr = h5.create_group("drive")
        dr.attrs["frequency"] = float(trace.drive_frequency)
        if trace.drive_force_amplitude is not None:
            dr.attrs["force_amplitude"] = float(trace.drive_force_amplitude)
        dr.attrs["units"] = "frequency: Hz; force_amplitude: N"
        if trace.truth is not None:
            t = trace.truth
            tg = h5.create_group("truth")
            write_dataset(tg, "force", t.force, "N", positive="repulsive")
            write_dataset(tg, "separation", t.separation, "m")
            write_dataset(tg, "velocity", t.velocity, "m/s", definition="dx/dt, positive toward the sample")
            tg.attrs["model"] = t.model
            tg.attrs["effects"] = list(t.effects)
            pg = tg.create_group("parameters")
            for name, value in t.parameters.items():
                pg.attrs[name] = value
            pg.attrs["units"] = "; ".join(f"{k}: {v}" for k, v in t.units.items())
            for name, value in t.extra.items():
                tg.attrs[name] = value
            if t.tracks:
                track_group = tg.create_group("tracks")
                for name, (values, unit) in t.tracks.items():
                    write_dataset(track_group, name, values, unit)
    return path


def _attr(group, name: str):
    value = group.attrs.get(name)
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


def read_truth(path: str | Path) -> Truth | None:
    """The ``/truth`` group of an afmid trace file, or None (also for a file that is not HDF5: a measured trace
    in another format has no ground truth); InputError naming the file if it is damaged."""
    import h5py

    try:
        if not h5py.is_hdf5(path):
            return None
        return _read_truth(path)
    except (OSError, KeyError, ValueError, RuntimeError, TypeError) as exc:  # what h5py raises on a damaged file
        detail = " ".join(str(exc).split())[:160] or type(exc).__name__
        raise InputError(f"cannot read the ground truth (/truth) of this afmid trace file (corrupt?): {detail}",
                         file=path, key="data.path") from exc


def _read_truth(path: str | Path) -> Truth | None:
    import h5py

    with h5py.File(path, "r") as h5:
        if "truth" not in h5:
            return None
        tg = h5["truth"]
        pg = tg["parameters"]
        units = dict(
            item.split(": ", 1) for item in str(_attr(pg, "units") or "").split("; ") if ": " in item
        )
        extra = {k: _attr(tg, k) for k in tg.attrs if k not in ("model", "effects")}
        return Truth(
            force=tg["force"][...],
            separation=tg["separation"][...],
            velocity=tg["velocity"][...],
            model=str(_attr(tg, "model")),
            effects=[str(e) for e in tg.attrs.get("effects", [])],
            parameters={k: float(_attr(pg, k)) for k in pg.attrs if k != "units"},
            units=units,
            extra=extra,
            tracks={name: (ds[...], str(_attr(ds, "units"))) for name, ds in tg["tracks"].items()}
            if "tracks" in tg else {},
        )


# --------------------------------------------------------------------------- loading
def _convert_units(values: np.ndarray, units: str | None, config, file: Path, invols: float | None) -> np.ndarray:
    """``values`` in metres; ``invols`` (m/V) is data.invols or the file's calibrated sensitivity."""
    data = config.data
    if units is None:
        raise ConfigError(
            "the file does not state the deflection units; set data.units to one of m, nm, pm, um, V, raw",
            file=config.source,
            key="data.units",
        )
    values = values - data.offset  # a new array: scaled in place below (one array as long as the trace, not two)
    if units in _UNIT_SCALE:
        return np.multiply(values, _UNIT_SCALE[units], out=values)
    if units == "V":
        if invols is None:
            raise ConfigError("units V needs data.invols (m/V) to convert to metres", file=config.source, key="data.invols")
        return np.multiply(values, invols, out=values)
    if units == "raw":
        if data.scale is None:
            raise ConfigError("units raw needs data.scale (m per count)", file=config.source, key="data.scale")
        return np.multiply(values, data.scale, out=values)
    raise InputError(f"cannot convert deflection units {units!r}; set data.units", file=file, key="data.units")


def normalise_units(units: str | None) -> str | None:
    if units is None:
        return None
    u = units.strip().replace("µ", "u").replace("μ", "u")
    return {"meter": "m", "meters": "m", "metre": "m", "volt": "V", "volts": "V", "v": "V"}.get(u.lower(), u)


def load_trace(config) -> Trace:
    """Load the trace named by ``config.data`` into SI units, positive toward the sample.

    Metadata found in the file (sample rate, units, and for afmid trace files the
    cantilever and drive) is used; values in the config override it, and the
    override is recorded in ``Trace.overridden``.
    """
    from afmid.io.readers import read_trace

    data = config.data
    if data.path is None:
        raise ConfigError("required key is missing (the trace file to fit)", file=config.source, key="data.path")
    path = check_input_file(config.resolve_path(data.path), what="trace file", key="data.path", allow_empty=True)
    try:
        raw = read_trace(path, data.format, data.column, data.time_column)
    except InputError as exc:
        if exc.key is not None:
            raise
        # A problem with the file as a whole (truncated, no data rows): name the key that chose it.
        raise InputError(exc.message, file=exc.file, key="data.path") from exc.__cause__
    sources = dict(raw.source)
    overridden: list[str] = []
    meta = raw.metadata or {}
    is_afmid = meta.get("format") == TRACE_FORMAT
    # Config values an instrument file states (SI; a NanoScope header's drive frequency, sensitivity, k).
    stated = {} if is_afmid else dict(meta.get("stated") or {})
    stated_where = dict(meta.get("stated_where") or {})

    values = np.asarray(raw.values, dtype=np.float64)
    import afmid.io.defects as defects

    defects.report(defects.check_values(values), path)  # NaN/inf runs: where, and the longest clean part

    units = normalise_units(raw.units)
    if data.units is not None:
        if units is not None and units != data.units:
            overridden.append("data.units")
        units = data.units
        sources["units"] = "config:data.units"
    invols = data.invols
    if units == "V" and "data.invols" in stated:
        if invols is None:
            invols = stated["data.invols"]
            sources["invols"] = stated_where.get("data.invols", "file")
            log.info("%s: deflection sensitivity %.5g nm/V from the file (%s)", path, invols * 1e9,
                     sources["invols"].removeprefix("file:"))
        elif not same_value(invols, stated["data.invols"]):
            overridden.append("data.invols")
    deflection = _convert_units(values, units, config, path, invols)
    if data.positive == "away_from_sample":
        deflection = -deflection

    time = None if raw.time is None else np.asarray(raw.time, dtype=np.float64)
    sample_rate = raw.sample_rate
    if data.sample_rate is not None:
        if sample_rate is not None and not np.isclose(sample_rate, data.sample_rate, rtol=1e-9):
            overridden.append("data.sample_rate")
        file_rate, file_rate_source = sample_rate, sources.get("sample_rate", "file")
        sample_rate = data.sample_rate
        sources["sample_rate"] = "config:data.sample_rate"
        from afmid.io.readers.base import rate_from_time

        time_rate = None if time is None else rate_from_time(time)
        if time_rate is not None and not np.isclose(time_rate, data.sample_rate, rtol=0.01):
            # The fit uses both the time axis and the rate: they must agree.
            raise ConfigError(
                f"{data.sample_rate:g} Hz contradicts the time column {data.time_column!r} "
                f"({time_rate:g} Hz); remove data.sample_rate or data.time_column",
                file=config.source,
                key="data.sample_rate",
            )
        if file_rate is not None and not np.isclose(file_rate, data.sample_rate, rtol=0.01):
            # A rate the file states, contradicted (beyond a rounding): say so. A time column's is an error above.
            log.warning("%s: data.sample_rate %g Hz overrides the file's %g Hz (%s)", path, data.sample_rate,
                        file_rate, file_rate_source)
    if sample_rate is None:
        if time is not None:  # a time column that gives no rate: say what is wrong with it
            defects.report(defects.check_time(time), path)
        if meta.get("sample_rate_problem"):  # the file states rates that contradict each other and the data
            raise InputError(meta["sample_rate_problem"], file=path, key="data.sample_rate")
        raise ConfigError(
            "the file has no time axis or sample rate; set data.sample_rate (Hz) or data.time_column",
            file=config.source,
            key="data.sample_rate",
        )

    stated_cantilever = {"spring_constant": stated["cantilever.spring_constant"]} \
        if "cantilever.spring_constant" in stated else {}
    cantilever = merge_cantilever(config, meta.get("cantilever", {}) if is_afmid else stated_cantilever, sources,
                                   overridden)
    reading = {**config.data.model_dump(mode="json", exclude_none=True), "path": str(path)}
    drive_meta = meta.get("drive", {}) if is_afmid else {"frequency": stated.get("drive.frequency")}
    drive_frequency = merged_value(
        config, "drive.frequency", config.drive.frequency, drive_meta.get("frequency"), sources, overridden
    )
    for key in ("cantilever.spring_constant", "drive.frequency"):  # say where in the file, not only "file"
        name = key.split(".")[-1]
        if sources.get(name) == "file" and key in stated_where:
            sources[name] = stated_where[key]
    force_amplitude = config.drive.force_amplitude
    file_amplitude = drive_meta.get("force_amplitude")
    if force_amplitude is not None:
        if file_amplitude is not None and not same_value(force_amplitude, file_amplitude):
            overridden.append("drive.force_amplitude")
        sources["force_amplitude"] = "config:drive.force_amplitude"
    elif file_amplitude is not None:
        check_file_instrument_value(config, "drive.force_amplitude", file_amplitude)
        force_amplitude = file_amplitude
        sources["force_amplitude"] = "file"

    trace = Trace(
        deflection=deflection,
        sample_rate=float(sample_rate),
        cantilever=cantilever,
        drive_frequency=float(drive_frequency),
        time=time,
        truth=read_truth(path) if is_afmid and meta.get("truth_datasets") else None,
        path=path,
        sha256=sha256_file(path),
        sources=sources,
        overridden=overridden,
        drive_force_amplitude=None if force_amplitude is None else float(force_amplitude),
        reading=reading,
    )
    if data.start is not None or data.stop is not None:
        trace = _cropped_by_config(trace, config)
    return check_trace(trace, config)


def _cropped_by_config(trace: Trace, config) -> Trace:
    """The part of ``trace`` between data.start and data.stop (s from its first sample)."""
    from afmid.io.onset import crop, sample_index

    data = config.data
    duration = trace.n_samples / trace.sample_rate
    for key, value in (("data.start", data.start), ("data.stop", data.stop)):
        if value is not None and value >= duration:
            raise ConfigError(f"{value:g} s is beyond the end of the record ({duration:g} s long)",
                              file=config.source, key=key)
    first = 0 if data.start is None else sample_index(trace, data.start)
    stop = None if data.stop is None else sample_index(trace, data.stop)
    trace = crop(trace, first, stop)
    trace.sources["crop"] = f"config: samples {first} to {first + trace.n_samples} of the file"
    return trace


def trace_from_array(deflection, sample_rate: float, cantilever: Cantilever | None, drive_frequency: float | None,
                     units: str = "m", positive: str = "toward_sample",
                     drive_force_amplitude: float | None = None) -> Trace:
    """:meth:`Trace.from_array`: the arguments as a run config's data, cantilever and drive keys would give them
    (validated by the same schemas, afmid.io.sections, so a bad value is the same one-line error naming the key;
    the checks on load then use the fit's defaults)."""
    from afmid.io.sections import record_sections

    where = "Trace.from_array"
    if not isinstance(cantilever, Cantilever):
        raise ConfigError(f"expected an afmid.Cantilever (k, f0, Q of the lever), got {type(cantilever).__name__}",
                          file=where, key="cantilever")
    if units not in _UNIT_SCALE:
        raise ConfigError(f"expected one of {', '.join(_UNIT_SCALE)}, got {units!r}", file=where, key="units")
    values = np.array(deflection, dtype=np.float64)  # a copy: the caller's array is never changed
    if values.ndim != 1:
        raise InputError(f"expected a 1-D array of deflection samples, got shape {values.shape}", file=where,
                         key="deflection")
    drive = {"frequency": cantilever.resonance_frequency if drive_frequency is None else drive_frequency}
    if drive_force_amplitude is not None:
        drive["force_amplitude"] = drive_force_amplitude
    config = record_sections({"data": {"sample_rate": sample_rate, "units": units, "positive": positive},
                              "cantilever": cantilever.config_section(), "drive": drive}, source=Path(where))
    import afmid.io.defects as defects

    defects.report(defects.check_values(values), Path(where))  # NaN/inf runs: where, and the longest clean part
    values *= _UNIT_SCALE[units] * (-1.0 if positive == "away_from_sample" else 1.0)
    trace = Trace(deflection=values, sample_rate=float(config.data.sample_rate),
                  cantilever=Cantilever.from_config(config.cantilever), drive_frequency=float(config.drive.frequency),
                  drive_force_amplitude=config.drive.force_amplitude,
                  sources={"sample_rate": where, "units": where, "cantilever": where})
    return check_trace(trace, config)


def check_trace(trace: Trace, config) -> Trace:
    """Reject traces that cannot be fitted; warn about doubtful ones.

    The defects (afmid.io.defects: time gaps, clipping, drive frequency, sampling,
    phase jumps, steady state, offset and drift, contact) are stored in
    ``trace.findings``; the first error is raised, otherwise warnings are logged.
    """
    import afmid.io.defects as defects

    path = trace.path
    n = trace.n_samples
    if n == 0:
        raise InputError("the trace is empty", file=path, key="data.column")
    if trace.time is not None:
        if trace.time.size != n:
            raise InputError("time and deflection columns differ in length", file=path, key="data.time_column")
        defects.report(defects.check_time(trace.time), path)  # NaN, order, gaps, duplicates, jitter
    if trace.n_periods < MIN_PERIODS:
        raise InputError(
            f"the trace is too short: {n} samples = {trace.n_periods:.2f} drive periods, need at least {MIN_PERIODS}",
            file=path,
            key="data.path",
        )
    trace.findings, trace.drive = defects.check_loaded(trace, config)  # findings include the samples-per-period warning
    onset = next((f for f in trace.findings if f.name == "onset"), None)
    if onset is not None and config.data.start is None:
        # The record starts at rest: fit it from the onset on (reported, not an error).
        from afmid.io.onset import crop

        first = trace.first_sample
        trace = crop(trace, onset.numbers["sample"])
        trace.sources["crop"] = f"onset of the oscillation: samples {trace.first_sample} to " \
                                f"{trace.first_sample + trace.n_samples} of the file (from sample {first})"
        if trace.n_periods < MIN_PERIODS:
            raise InputError(f"{onset.message}; then only {trace.n_periods:.2f} drive periods remain, need at least "
                             f"{MIN_PERIODS}", file=path, key="data.start")
        trace.findings, trace.drive = defects.check_loaded(trace, config)
        trace.findings.insert(0, replace(onset, severity="repaired"))
    glitches = next((f for f in trace.findings if f.name == "glitches" and f.severity == "warning"), None)
    if glitches is not None and not any(f.severity == "error" for f in trace.findings):
        from afmid.io.glitches import cleaned  # edge transients cut, isolated glitches replaced: one finding

        earlier = [f for f in trace.findings if f.name == "onset"]
        trace, done = cleaned(trace, config, glitches)
        trace.findings, trace.drive = defects.check_loaded(trace, config)
        trace.findings = earlier + [done] + trace.findings
    defects.report(trace.findings, path)
    return trace
