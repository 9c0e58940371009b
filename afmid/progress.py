"""Progress of the long commands (fit, simulate, the report's effect trials, batch) on stderr.

One small object with named stages and counts of what is counted, used by every command the same way:

    progress = Progress("simulate", enabled=True)
    progress.stage("recording", total=50, unit="periods")   # a counted stage
    progress.advance(10)
    progress.stage("selecting terms", step=(3, 4))           # a step of a fixed sequence
    progress.close()

On a terminal, one line is rewritten in place (``simulate: recording 10/50 periods``, ``fit: selecting terms
(3/4)``) and erased at the end, so the command's own output starts on a clean line; no rates (a rate of
"periods per second" or "it/s" of unequal stages tells nothing). When stderr is not a terminal (a log file, a
pipe, a test's capture), every stage is one plain line when it starts, with its total, and nothing else:
no carriage returns, no redraws. Log records of the ``afmid`` logger erase the terminal line before they are
written (the line comes back on the next update), so a warning never lands in the middle of the line.
"""

from __future__ import annotations

import logging
import sys
import time

from afmid.errors import escape_controls

#: Terminal redraws at most this often, s (a kernel reporting every few periods would flood the terminal).
REDRAW_INTERVAL = 0.1


class _EraseBeforeRecords(logging.Filter):
    """A filter on the ``afmid`` log handlers: the progress line is erased before a record is written."""

    def __init__(self, progress: "Progress"):
        super().__init__()
        self.progress = progress

    def filter(self, record: logging.LogRecord) -> bool:
        self.progress.erase()
        return True


class Progress:
    """Named stages with counts for command ``name`` on ``stream`` (stderr); nothing at all when not ``enabled``.

    ``terminal`` overrides whether the stream is a terminal (default: ``stream.isatty()``).
    """

    def __init__(self, name: str, enabled: bool = True, stream=None, terminal: bool | None = None):
        self.name = name
        self.enabled = bool(enabled)
        self.stream = stream if stream is not None else sys.stderr
        if terminal is None:
            isatty = getattr(self.stream, "isatty", None)
            terminal = bool(isatty()) if callable(isatty) else False
        self.terminal = terminal
        self.label = ""
        self.total: int | None = None
        self.unit = ""
        self.step: tuple[int, int] | None = None
        self.done = 0
        self._shown = 0  # characters of the terminal line now on screen
        self._drawn_at = 0.0
        self._filter = _EraseBeforeRecords(self)
        self._handlers: list[logging.Handler] = []
        if self.enabled and self.terminal:
            self._handlers = list(logging.getLogger("afmid").handlers)
            for handler in self._handlers:
                handler.addFilter(self._filter)

    # ---------------------------------------------------------------- the stages
    def stage(self, label: str, total: int | None = None, unit: str = "", step: tuple[int, int] | None = None) -> None:
        """Start stage ``label``: counted (``total`` of ``unit``; None: open-ended) or step ``(i, n)`` of n."""
        self.label, self.total, self.unit, self.step, self.done = label, total, unit, step, 0
        if not self.enabled:
            return
        if self.terminal:
            self._draw(force=True)
        else:
            self.stream.write(self.text(plain=True) + "\n")
            self.stream.flush()

    def advance(self, count: int = 1) -> None:
        """``count`` more of what the stage counts."""
        self.done += int(count)
        if self.enabled and self.terminal:
            self._draw()

    def text(self, plain: bool = False) -> str:
        """The line of the current stage: as the terminal shows it, or (``plain``) as a log line states it."""
        # escaped: a stage may name an item the user named (a batch's trace), and the line goes to a terminal
        head = escape_controls(f"{self.name}: {self.label}" if self.label else self.name)
        if self.step is not None:
            return f"{head} ({self.step[0]}/{self.step[1]})"
        if plain:
            if self.total is not None:
                return f"{head} ({self.total} {self.unit})".rstrip()
            return head
        if self.total is not None:
            return f"{head} {self.done}/{self.total} {self.unit}".rstrip()
        if self.done:
            return f"{head} {self.done} {self.unit}".rstrip()
        return head

    # ---------------------------------------------------------------- the terminal line
    def _draw(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._drawn_at < REDRAW_INTERVAL:
            return
        self._drawn_at = now
        line = self.text()
        self.stream.write("\r" + line + " " * max(self._shown - len(line), 0) + "\r" + line)
        self.stream.flush()
        self._shown = len(line)

    def erase(self) -> None:
        """Erase the terminal line (before a log record, at the end)."""
        if self._shown:
            self.stream.write("\r" + " " * self._shown + "\r")
            self.stream.flush()
            self._shown = 0
            self._drawn_at = 0.0  # the next update draws again

    def close(self) -> None:
        """End: the terminal line erased, the log handlers as they were. Safe to call twice."""
        if self.enabled and self.terminal:
            self.erase()
        for handler in self._handlers:
            handler.removeFilter(self._filter)
        self._handlers = []

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: A progress that shows nothing (for code that takes a Progress and is called without one).
def silent(name: str = "") -> Progress:
    return Progress(name, enabled=False)


def counted(items, name: str, label: str, unit: str, enabled: bool = True):
    """Iterate over ``items`` with a counted stage ``label`` of command ``name`` (``effects tried 3/12``)."""
    items = list(items)
    with Progress(name, enabled=enabled) as bar:
        bar.stage(label, total=len(items), unit=unit)
        for item in items:
            yield item
            bar.advance()
