"""Progress reporting for long work: a callback ``(done, total)`` that draws on stderr.

Library functions take ``progress: Callable[[int, int], None] | None``; the command layer passes a
:class:`ProgressBar`. This module sits at the bottom layer so that library code never imports the
CLI to report progress.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ["ProgressBar", "StatusLine"]


class StatusLine:
    """One line of live status on stderr, rewritten in place.

    The one status line of the toolkit: progress bars, ``record``'s and ``davis stream``'s
    rates and ``democap live``'s figures all draw through it. It draws only on a terminal
    (unless ``force``), at most every ``interval_s`` (``show(..., final=True)`` always), and
    pads to erase a longer previous line; :meth:`done` ends the line.
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
        self._enabled = enabled and (force or self._stream.isatty())
        self._interval_s = interval_s
        self._last = -float("inf")
        self._width = 0
        self._drawn = False

    @property
    def enabled(self) -> bool:
        """Whether anything is drawn (a terminal, or ``force``)."""
        return self._enabled

    def due(self) -> bool:
        """Whether a :meth:`show` now would draw (enabled, and the interval has passed)."""
        return self._enabled and time.monotonic() - self._last >= self._interval_s

    def show(self, text: str, *, final: bool = False) -> None:
        """Draw ``text`` in place of the line (rate-limited unless ``final``)."""
        if not (final and self._enabled) and not self.due():
            return
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
        if self._drawn:
            self._stream.write("\n")
            self._stream.flush()
            self._drawn = False
            self._width = 0


class ProgressBar:
    """A progress callback ``(done, total)`` that draws a bar on the :class:`StatusLine`.

    It redraws at most every 0.2 s and only when stderr is a terminal, unless ``force`` is set,
    so logs and CI output stay readable.
    """

    def __init__(self, label: str, *, stream: TextIO | None = None, force: bool = False) -> None:
        self._label = label
        self._line = StatusLine(stream=stream, interval_s=0.2, force=force)
        self._t0 = time.monotonic()

    def __call__(self, done: int, total: int) -> None:
        if not self._line.enabled:
            return
        frac = done / total if total > 0 else 1.0
        width = 30
        bar = "#" * round(frac * width)
        elapsed = time.monotonic() - self._t0
        text = f"{self._label} [{bar:<{width}}] {done}/{total} {elapsed:5.1f}s"
        self._line.show(text, final=done >= total)
