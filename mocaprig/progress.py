"""Progress reporting for long work: callbacks that draw one status line on stderr.

Library functions take ``progress: Callable[[int, int], None] | None`` (``(done, total)``), or
``Callable[[str, int, int], None] | None`` (``(stage, done, total)``) where the work has
stages; the command layer passes a :class:`ProgressBar` or a :class:`StageProgress`. Both show
the stage, items done/total, the rate and the time left.

Whether anything is drawn is decided once per command by :func:`progress_mode` (the CLI's
``--progress``, ``-q`` and ``--json``): ``"auto"`` draws on a terminal only, ``"always"`` draws
on any stream (a log file, a test), ``"never"`` draws nothing. This module sits at the bottom
layer so that library code never imports the CLI to report progress.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import Literal, TextIO, get_args

from mocaprig.errors import ValidationError

__all__ = [
    "ProgressBar",
    "ProgressMode",
    "StageProgress",
    "StatusLine",
    "bind_stage",
    "current_progress_mode",
    "end_status_line",
    "format_progress",
    "progress_mode",
]

#: When status lines draw: on a terminal only, on any stream, or never.
ProgressMode = Literal["auto", "always", "never"]

# One process-wide setting, read when a StatusLine is made: a command's status lines are made
# in its worker threads too, which a context variable would not reach.
_mode: ProgressMode = "auto"
_mode_lock = threading.Lock()
# The status line left unfinished on its stream, which a log record must not run into.
_open_line: StatusLine | None = None


def current_progress_mode() -> ProgressMode:
    """The mode status lines made now follow (``"auto"`` unless :func:`progress_mode` set it)."""
    return _mode


@contextmanager
def progress_mode(mode: ProgressMode) -> Iterator[None]:
    """Make the status lines created inside the block follow ``mode``; restores it after.

    Raises:
        ValidationError: ``mode`` is not one of :data:`ProgressMode`.
    """
    global _mode  # the one process-wide display setting (module doc)
    if mode not in get_args(ProgressMode):
        msg = f"progress mode must be one of {get_args(ProgressMode)}, got {mode!r}"
        raise ValidationError(msg)
    with _mode_lock:
        before, _mode = _mode, mode
    try:
        yield
    finally:
        with _mode_lock:
            _mode = before


#: The shortest elapsed time (s) a rate is shown for.
_MIN_RATE_S = 0.5


def end_status_line() -> None:
    """End the status line being drawn, if any, so that other output (a log record) starts
    on a line of its own; the status line draws again below it."""
    line = _open_line
    if line is not None:
        line.done()


def _duration(seconds: float) -> str:
    s = max(0, round(seconds))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s % 3600 // 60:02d}m"


def format_progress(
    label: str, done: int, total: int, elapsed_s: float, *, unit: str = "", width: int = 20
) -> str:
    """One progress line: label, bar, ``done/total``, rate (per s) and time left.

    The rate and time left appear once something is done and half a second has passed;
    ``total <= 0`` (an unknown amount) shows the count and rate without a bar.
    """
    # A rate over less than half a second is noise (the first items of a stage).
    rate = done / elapsed_s if done > 0 and elapsed_s >= _MIN_RATE_S else None
    per = f" {unit}" if unit else ""
    parts = [label]
    if total > 0:
        frac = min(max(done / total, 0.0), 1.0)
        parts.append(f"[{'#' * round(frac * width):<{width}}] {done}/{total}{per}")
    else:
        parts.append(f"{done}{per}")
    if rate is not None:
        parts.append(f"{rate:.3g}/s" if rate < 1000 else f"{rate:.0f}/s")
        if total > 0 and done < total:
            parts.append(f"{_duration((total - done) / rate)} left")
    parts.append(f"({_duration(elapsed_s)})")
    return " ".join(parts)


class StatusLine:
    """One line of live status on stderr, rewritten in place.

    The one status line of the toolkit: progress bars, ``record``'s and ``davis stream``'s
    rates and ``democap live``'s figures all draw through it. It draws on a terminal, or on any
    stream with ``force`` or under :func:`progress_mode` ``"always"``; never when ``enabled``
    is False or under ``"never"`` (``-q``, ``--json``). It draws at most every ``interval_s``
    (``show(..., final=True)`` always), and pads to erase a longer previous line; :meth:`done`
    ends the line.
    """

    def __init__(
        self,
        *,
        stream: TextIO | None = None,
        interval_s: float = 0.5,
        force: bool = False,
        enabled: bool = True,
    ) -> None:
        self._stream = sys.stderr if stream is None else stream
        mode = current_progress_mode()
        drawable = force or mode == "always" or self._stream.isatty()
        self._enabled = enabled and mode != "never" and drawable
        self._interval_s = interval_s
        self._last = -float("inf")
        self._width = 0
        self._drawn = False

    @property
    def enabled(self) -> bool:
        """Whether anything is drawn."""
        return self._enabled

    def due(self) -> bool:
        """Whether a :meth:`show` now would draw (enabled, and the interval has passed)."""
        return self._enabled and time.monotonic() - self._last >= self._interval_s

    def show(self, text: str, *, final: bool = False) -> None:
        """Draw ``text`` in place of the line (rate-limited unless ``final``)."""
        global _open_line  # see end_status_line
        if not (final and self._enabled) and not self.due():
            return
        if _open_line is not None and _open_line is not self:
            _open_line.done()  # another line left open (its work ended early): keep it
        _open_line = self
        self._last = time.monotonic()
        line = text[:200]
        self._stream.write("\r" + line.ljust(self._width))
        self._width = len(line)
        self._drawn = True
        if final:
            self.done()
        else:
            self._stream.flush()

    def done(self) -> None:
        """End the line (once something was drawn)."""
        global _open_line  # see end_status_line
        if _open_line is self:
            _open_line = None
        if self._drawn:
            self._stream.write("\n")
            self._stream.flush()
            self._drawn = False
            self._width = 0


def bind_stage(
    progress: Callable[[str, int, int], None] | None, stage: str
) -> Callable[[int, int], None] | None:
    """A ``(done, total)`` callback reporting to the stage-aware ``progress`` as ``stage``
    (None when ``progress`` is None: no work is done for a report nobody reads)."""
    if progress is None:
        return None
    report = progress

    def bound(done: int, total: int) -> None:
        report(stage, done, total)

    return bound


class ProgressBar:
    """A progress callback ``(done, total)`` that draws a bar, the rate and the time left on a
    :class:`StatusLine` (at most every 0.2 s; the last state always, ending the line)."""

    def __init__(
        self,
        label: str,
        *,
        stream: TextIO | None = None,
        force: bool = False,
        enabled: bool = True,
        unit: str = "",
    ) -> None:
        self._label = label
        self._unit = unit
        self._line = StatusLine(stream=stream, interval_s=0.2, force=force, enabled=enabled)
        self._t0 = time.monotonic()
        self._last: tuple[int, int] | None = None

    @property
    def enabled(self) -> bool:
        """Whether anything is drawn (see :class:`StatusLine`)."""
        return self._line.enabled

    def __call__(self, done: int, total: int) -> None:
        if not self._line.enabled or (self._last == (done, total) and done >= total > 0):
            return  # the final state is drawn once
        self._last = (done, total)
        elapsed = time.monotonic() - self._t0
        text = format_progress(self._label, done, total, elapsed, unit=self._unit)
        self._line.show(text, final=total > 0 and done >= total)

    def finish(self) -> None:
        """Draw the last state reported and end the line: for work whose last report may fall
        short of its total (rate-limited away, or an estimate), so that the next line starts
        below it. Does nothing after the total was reached."""
        if self._last is None:
            return
        done, total = self._last
        if not (total > 0 and done >= total):
            elapsed = time.monotonic() - self._t0
            text = format_progress(self._label, done, total, elapsed, unit=self._unit)
            self._line.show(text, final=True)


class StageProgress:
    """A progress callback ``(stage, done, total)`` for work in stages, on one
    :class:`StatusLine`: each stage's bar, rate and time left (a stage is timed from the last
    report of the stage before, or from the start); a finished stage's line stays, the next
    draws below it.

    ``labels`` maps stage names to the words shown (default: the name); ``prefix`` goes before
    each (``"demo "``). :meth:`stage` gives a ``(done, total)`` callback bound to one stage;
    :meth:`done` ends an unfinished line.
    """

    def __init__(
        self,
        prefix: str = "",
        *,
        labels: Mapping[str, str] | None = None,
        stream: TextIO | None = None,
        force: bool = False,
        enabled: bool = True,
    ) -> None:
        self._prefix = prefix
        self._labels = dict(labels or {})
        self._line = StatusLine(stream=stream, interval_s=0.2, force=force, enabled=enabled)
        self._stage: str | None = None
        self._t0 = self._last_report = time.monotonic()
        self._lock = threading.Lock()

    @property
    def enabled(self) -> bool:
        """Whether anything is drawn (see :class:`StatusLine`)."""
        return self._line.enabled

    def __call__(self, stage: str, done: int, total: int) -> None:
        if not self._line.enabled:
            return
        # Stages may report from worker threads (a simulator's clock watcher).
        with self._lock:
            now = time.monotonic()
            if stage != self._stage:
                self._line.done()
                self._stage = stage
                # Stages run one after another: this one began with the last report of the
                # one before (its own first report may come only after its first item).
                self._t0 = self._last_report
            self._last_report = now
            label = self._prefix + self._labels.get(stage, stage)
            text = format_progress(label, done, total, now - self._t0)
            self._line.show(text, final=total > 0 and done >= total)

    def stage(self, name: str) -> Callable[[int, int], None]:
        """A ``(done, total)`` callback reporting as stage ``name``."""

        def report(done: int, total: int) -> None:
            self(name, done, total)

        return report

    def done(self) -> None:
        """End the line if a stage left it unfinished."""
        with self._lock:
            self._line.done()
