"""Run files as inputs: which versions afmid reads, damage, and whether runs and traces still belong together.

:func:`afmid.runfile.load_run` reads a run file through :class:`RunReader`,
which turns a missing group, dataset or attribute into one line naming the
file and the path inside it. :func:`check_same_traces` refuses to compare runs
made on different traces unless asked to, and :func:`input_unchanged` tells
whether the trace a run was fitted on is still the file at its path (a
simulated trace's ground truth belongs to the trace the run was made from).
"""

from __future__ import annotations

import logging
from pathlib import Path

import yaml

from afmid.errors import ConfigError, InputError
from afmid.io.files import check_format_version
from afmid.io.trace import FORMAT_VERSION, sha256_file

log = logging.getLogger(__name__)

#: format_version values of run files this afmid reads.
READABLE_VERSIONS = (FORMAT_VERSION,)
#: The command-line flag that allows comparing runs of different traces.
ALLOW_DIFFERENT_TRACES = "--allow-different-traces"


def check_version(attrs, path: Path) -> None:
    """InputError unless the file's ``format_version`` is one this afmid reads."""
    check_format_version(attrs, path, READABLE_VERSIONS)


def stored_config(text: str | None, path: Path) -> dict:
    """The run's stored config as a mapping, from the text of its ``config`` attribute (None: the attribute is
    missing); InputError if missing or not YAML."""
    if text is None:
        raise InputError("the stored config attribute is missing (damaged or incomplete run file)", file=path,
                         key="config")
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        problem = getattr(exc, "problem", None) or "syntax error"
        raise InputError(f"the stored config attribute is not valid YAML{where}: {problem}", file=path,
                         key="config") from None
    if not isinstance(raw, dict):
        raise InputError(f"the stored config attribute is not a mapping of sections (got {type(raw).__name__})",
                         file=path, key="config")
    return raw


class RunReader:
    """A group of an open run file whose missing members are one-line InputErrors naming their path."""

    def __init__(self, group, path: Path, prefix: str = "/"):
        self.group, self.path, self.prefix = group, path, prefix

    def __getitem__(self, name: str):
        import h5py

        try:
            member = self.group[name]
        except KeyError:
            raise InputError(f"missing {self.prefix}{name} (damaged or incomplete run file)", file=self.path,
                             key=f"{self.prefix}{name}") from None
        if isinstance(member, h5py.Group):
            return RunReader(member, self.path, f"{self.prefix}{name}/")
        return member

    def __contains__(self, name: str) -> bool:
        return name in self.group

    def items(self):
        return ((name, self[name]) for name in self.group)

    @property
    def attrs(self):
        return self.group.attrs


def check_same_traces(runs, allow: bool) -> list[str]:
    """Refuse (ConfigError) to compare runs whose input traces differ (SHA-256), unless ``allow``.

    Returns a note for the report when they differ and it is allowed, else an empty list.
    """
    digests = {run.input_sha256 for run in runs}
    if len(digests) <= 1:
        return []
    first = runs[0]
    other = next(run for run in runs if run.input_sha256 != first.input_sha256)
    def digest(run) -> str:
        return f"SHA-256 {run.input_sha256[:12]}..." if run.input_sha256 else "SHA-256 not recorded"

    what = (f"{first.path} and {other.path} were fitted on different traces ({first.input_path}, {digest(first)}, "
            f"and {other.input_path}, {digest(other)})")
    if not allow:
        raise ConfigError(f"{what}: comparing them compares the traces, not the models; pass "
                          f"{ALLOW_DIFFERENT_TRACES} to do that on purpose", key=ALLOW_DIFFERENT_TRACES)
    return [f"the runs were fitted on different traces ({len(digests)} distinct input SHA-256): their errors "
            "and parameters compare the traces as much as the models"]


def input_unchanged(input_path: Path | None, input_sha256: str | None) -> bool:
    """True when the run's input trace is at its path with the SHA-256 the run stored."""
    if input_path is None or not input_path.exists():
        return False
    if not input_sha256:
        return True
    try:
        return sha256_file(input_path) == input_sha256
    except OSError:
        return False
