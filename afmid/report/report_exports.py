"""``afmid report RUN... -o DIR --export force-curves,parameters,periods``: the CSV tables of the last run
(:mod:`afmid.report.export`) written into the report folder after the report, and listed in its marker.

Kept apart from :func:`afmid.report.page.make_report` (the page does not need them): the CLI calls
:func:`export_into_report` once the report folder is in place. Each CSV is written whole (temp file +
rename, as ``afmid export``), then the marker is rewritten to list them, so ``afmid report --overwrite``
replaces the folder later as its own.
"""

from __future__ import annotations

from pathlib import Path

from afmid.errors import ConfigError
from afmid.report.export import EXPORTS, export_run
from afmid.report.folder import write_marker


def parse_exports(text: str) -> list[str]:
    """``"force-curves,parameters"`` -> the table names, checked (one-line ConfigError, exit 2, naming the option
    and the allowed names)."""
    names = [part.strip() for part in text.split(",") if part.strip()]
    unknown = [n for n in names if n not in EXPORTS]
    if unknown or not names:
        raise ConfigError(f"must be a comma-separated list of {', '.join(EXPORTS)}, got {text!r}", key="--export")
    return list(dict.fromkeys(names))


def export_file_name(run_path: Path, what: str) -> str:
    """``run2.h5`` + ``force-curves`` -> ``run2.force-curves.csv``."""
    return f"{Path(run_path).stem}.{what}.csv"


def export_into_report(run_path: Path, folder: Path, tables: list[str]) -> list[tuple[str, int]]:
    """Write each table of ``run_path`` into the report ``folder``; return (file name, rows) per table."""
    written = []
    for what in tables:
        name = export_file_name(run_path, what)
        written.append((name, export_run(run_path, what, Path(folder) / name, overwrite=True)))
    write_marker(folder)
    return written
