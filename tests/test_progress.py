"""The one status line and the progress bar drawn on it."""

from __future__ import annotations

import io

from mocaprig.progress import ProgressBar, StatusLine


def test_status_line_rewrites_one_line_in_place_and_pads_longer_text_away() -> None:
    out = io.StringIO()
    line = StatusLine(stream=out, interval_s=0.0, force=True)
    line.show("a long first status")
    line.show("short")
    line.done()
    text = out.getvalue()
    assert text == "\ra long first status\rshort" + " " * 14 + "\n"


def test_status_line_is_rate_limited_but_always_draws_the_final_state() -> None:
    out = io.StringIO()
    line = StatusLine(stream=out, interval_s=3600.0, force=True)
    line.show("first")
    line.show("dropped: too soon")
    line.show("final", final=True)
    assert out.getvalue() == "\rfirst\rfinal\n"


def test_status_line_draws_nothing_off_a_terminal_or_when_disabled() -> None:
    out = io.StringIO()  # not a tty
    StatusLine(stream=out).show("x", final=True)
    StatusLine(stream=out, force=True, enabled=False).show("y", final=True)
    assert out.getvalue() == ""


def test_progress_bar_ends_its_line_when_done() -> None:
    out = io.StringIO()
    bar = ProgressBar("work", stream=out, force=True)
    bar(0, 2)
    bar(2, 2)
    assert out.getvalue().endswith("] 2/2   0.0s\n")
    assert out.getvalue().count("\n") == 1
