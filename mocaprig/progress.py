"""Progress reporting for long work: a callback ``(done, total)`` that draws on stderr.

Library functions take ``progress: Callable[[int, int], None] | None``; the command layer passes a
:class:`ProgressBar`. This module sits at the bottom layer so that library code never imports the
CLI to report progress.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ["ProgressBar"]


class ProgressBar:
    """A progress callback ``(done, total)`` that draws on stderr.

    It redraws at most every 0.2 s and only when stderr is a terminal, unless ``force`` is set,
    so logs and CI output stay readable.
    """

    def __init__(self, label: str, *, stream: TextIO | None = None, force: bool = False) -> None:
        self._label = label
        self._stream = sys.stderr if stream is None else stream
        self._enabled = force or self._stream.isatty()
        self._last = 0.0
        self._t0 = time.monotonic()

    def __call__(self, done: int, total: int) -> None:
        if not self._enabled:
            return
        now = time.monotonic()
        if done < total and now - self._last < 0.2:
            return
        self._last = now
        frac = done / total if total > 0 else 1.0
        width = 30
        bar = "#" * round(frac * width)
        self._stream.write(
            f"\r{self._label} [{bar:<{width}}] {done}/{total} {now - self._t0:5.1f}s"
        )
        if done >= total:
            self._stream.write("\n")
        self._stream.flush()
