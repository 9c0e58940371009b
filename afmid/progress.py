"""Progress of the long commands (fit, simulate, the report's effect trials, batch) on stderr.

One small object with named stages and counts of what is counted, used by every command the same way:

    progress = Progress("simulate", enabled=True)
    progress.stage("recording", total=50, unit="periods")   # a counted stage
    progress.advance(10)
    progress.stage("selecting terms", step=(3, 4))           # a step of a fixed sequence
    progress.close()

A counted stage may name the item it works on (``progress.item("viscoelastic")``: the diagnosis's candidate
effect), and then says when each one is done.

On a terminal, one line is rewritten in place (``simulate: recording 10/50 periods``, ``fit: selecting terms
(3/4) 2 s``, ``report: trying effects 3/7 effects: viscoelastic, ETA 25 s``) and erased at the end, so the
command's own output starts on a clean line; a step shows its elapsed seconds, a counted stage its estimated time
left once one item is done (the mean time of the items done so far times the items left); no rates (a rate of
"periods per second" or "it/s" of unequal stages tells nothing). When stderr is not a terminal (a log file, a
pipe, a test's capture), every stage is one plain line when it starts, with its total, and every named item one
line when it is done (``report: trying effects: viscoelastic done (3/7 effects, 4.2 s)``), and nothing else: no
carriage returns, no redraws. Log records of the ``afmid`` logger erase the terminal line before they are
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
        self.current = ""  # the item of the counted stage being worked on ("" none)
        self._started = self._item_started = time.monotonic()
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
        self.current = ""
        self._started = self._item_started = time.monotonic()
        if not self.enabled:
            return
        if self.terminal:
            self._draw(force=True)
        else:
            self.stream.write(self.text(plain=True) + "\n")
            self.stream.flush()

    def item(self, name: str) -> None:
        """The counted stage now works on ``name`` (shown on a terminal; on a pipe, said when it is done)."""
        self.current, self._item_started = str(name), time.monotonic()
        if self.enabled and self.terminal:
            self._draw(force=True)

    def advance(self, count: int = 1) -> None:
        """``count`` more of what the stage counts (the named item, if any, is done)."""
        self.done += int(count)
        if self.enabled and not self.terminal and self.current:
            of = f"{self.done}/{self.total} {self.unit}".rstrip() if self.total is not None else f"{self.done}"
            seconds = time.monotonic() - self._item_started
            self.stream.write(f"{self.name}: {self.label}: {self.current} done ({of}, {seconds:.1f} s)\n")
            self.stream.flush()
        self.current = ""
        if self.enabled and self.terminal:
            self._draw()

    def eta(self) -> float | None:
        """Estimated seconds left in a counted stage: the mean time per item done so far times the items left
        (None before the first item is done, in the stage's first second: too early to say, or without a total)."""
        elapsed = time.monotonic() - self._started
        if self.total is None or self.done <= 0 or self.done >= self.total or elapsed < 1.0:
            return None
        return elapsed / self.done * (self.total - self.done)

    def text(self, plain: bool = False) -> str:
        """The line of the current stage: as the terminal shows it, or (``plain``) as a log line states it."""
        # escaped: a stage may name an item the user named (a batch's trace), and the line goes to a terminal
        head = escape_controls(f"{self.name}: {self.label}" if self.label else self.name)
        if self.step is not None:
            elapsed = time.monotonic() - self._started
            shown = "" if plain or elapsed < 1.0 else f" {_duration(elapsed)}"  # a long step: how long so far
            return f"{head} ({self.step[0]}/{self.step[1]}){shown}"
        if plain:
            if self.total is not None:
                return f"{head} ({self.total} {self.unit})".rstrip()
            return head
        if self.total is not None:
            line = f"{head} {self.done}/{self.total} {self.unit}".rstrip()
        elif self.done:
            line = f"{head} {self.done} {self.unit}".rstrip()
        else:
            return head
        if self.current:
            line += f": {self.current}"
        left = self.eta()
        return line + (f", ETA {_duration(left)}" if left is not None else "")

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


def _duration(seconds: float) -> str:
    """``12 s`` or ``3 min 5 s`` (whole seconds: an estimate, not a measurement)."""
    whole = int(round(seconds))
    return f"{whole // 60} min {whole % 60} s" if whole >= 60 else f"{whole} s"


#: A progress that shows nothing (for code that takes a Progress and is called without one).
def silent(name: str = "") -> Progress:
    return Progress(name, enabled=False)


def counted(items, name: str, label: str, unit: str, enabled: bool = True, named: bool = False):
    """Iterate over ``items`` with a counted stage ``label`` of command ``name`` (``effects tried 3/12``);
    ``named``: each item is named (``str(item)``) while it is worked on, with an ETA on a terminal and one line
    when it is done on a pipe."""
    items = list(items)
    with Progress(name, enabled=enabled) as bar:
        bar.stage(label, total=len(items), unit=unit)
        for item in items:
            if named:
                bar.item(str(item))
            yield item
            bar.advance()
