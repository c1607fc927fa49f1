"""The one status line, the progress callbacks drawn on it and the progress mode."""

from __future__ import annotations

import io
import logging

import pytest

from mocaprig.errors import ValidationError
from mocaprig.progress import (
    ProgressBar,
    StageProgress,
    StatusLine,
    bind_stage,
    current_progress_mode,
    end_status_line,
    format_progress,
    progress_mode,
)


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


def test_mode_always_draws_off_a_terminal_and_never_silences_even_forced_lines() -> None:
    out = io.StringIO()
    with progress_mode("always"):
        StatusLine(stream=out).show("drawn", final=True)
    with progress_mode("never"):
        StatusLine(stream=out, force=True).show("silenced", final=True)
    assert out.getvalue() == "\rdrawn\n"


def test_progress_mode_is_restored_after_the_block_even_on_error() -> None:
    assert current_progress_mode() == "auto"

    def fail_inside() -> None:
        with progress_mode("never"):
            assert current_progress_mode() == "never"
            raise RuntimeError

    with pytest.raises(RuntimeError):
        fail_inside()
    assert current_progress_mode() == "auto"


def test_progress_mode_refuses_an_unknown_mode() -> None:
    with pytest.raises(ValidationError, match="'sometimes'"), progress_mode("sometimes"):  # type: ignore[arg-type]
        pass


def test_format_progress_shows_bar_count_rate_and_time_left() -> None:
    text = format_progress("calibrate", 5, 20, 2.0, unit="frames")
    assert text == "calibrate [#####               ] 5/20 frames 2.5/s 6s left (2s)"


def test_format_progress_of_an_unknown_total_shows_count_and_rate_without_bar() -> None:
    assert format_progress("export", 90, 0, 3.0) == "export 90 30/s (3s)"


def test_format_progress_writes_long_times_in_minutes_and_hours() -> None:
    assert format_progress("train", 1, 100, 100.0).endswith("2h45m left (1m40s)")


def test_progress_bar_ends_its_line_when_done_and_draws_the_final_state_once() -> None:
    out = io.StringIO()
    bar = ProgressBar("work", stream=out, force=True)
    bar(0, 2)
    bar(2, 2)
    bar(2, 2)
    assert out.getvalue().endswith("] 2/2 (0s)\n")
    assert out.getvalue().count("\n") == 1
    assert out.getvalue().count("2/2") == 1


def test_progress_bar_finish_ends_a_line_left_short_of_its_total() -> None:
    out = io.StringIO()
    bar = ProgressBar("calibrate", stream=out, force=True)
    bar(6, 7)
    bar.finish()
    assert out.getvalue().count("\n") == 1
    assert "6/7" in out.getvalue().rsplit("\r", 1)[-1]


def test_stage_progress_gives_each_stage_its_own_line_and_labels() -> None:
    out = io.StringIO()
    stages = StageProgress("run ", labels={"index": "indexing"}, stream=out, force=True)
    stages("index", 0, 2)
    stages("batches", 1, 3)  # a new stage ends the unfinished one
    batches = stages.stage("batches")
    batches(3, 3)
    lines = [ln.rsplit("\r", 1)[-1] for ln in out.getvalue().split("\n")[:-1]]
    assert lines[0].startswith("run indexing [")
    assert "0/2" in lines[0]
    assert lines[1].startswith("run batches [")
    assert "3/3" in lines[1]
    assert len(lines) == 2


def test_a_new_line_does_not_overwrite_another_left_open() -> None:
    out = io.StringIO()
    first = ProgressBar("first", stream=out, force=True)
    second = ProgressBar("second", stream=out, force=True)
    first(1, 3)  # never finished
    second(1, 1)
    lines = out.getvalue().split("\n")[:-1]
    assert len(lines) == 2
    assert lines[0].lstrip("\r").startswith("first")
    assert lines[1].lstrip("\r").startswith("second")


def test_end_status_line_lets_other_output_start_on_a_line_of_its_own() -> None:
    out = io.StringIO()
    bar = ProgressBar("work", stream=out, force=True)
    bar(1, 4)
    end_status_line()
    out.write("INFO a log record\n")
    bar(4, 4)
    lines = out.getvalue().split("\n")
    assert lines[1] == "INFO a log record"
    assert "4/4" in lines[2]


def test_the_cli_log_filter_ends_the_status_line_before_a_record(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from mocaprig.cli import _log_below_status_line

    out = io.StringIO()
    handler = logging.StreamHandler(out)
    handler.addFilter(_log_below_status_line)
    log = logging.getLogger("tests.progress")
    log.addHandler(handler)
    log.propagate = False
    try:
        bar = ProgressBar("work", stream=out, force=True)
        bar(1, 4)
        log.warning("a record")
    finally:
        log.removeHandler(handler)
        log.propagate = True
    assert out.getvalue().split("\n")[1] == "a record"


def test_a_stage_is_timed_from_the_last_report_of_the_stage_before(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import types

    import mocaprig.progress

    now = [0.0]
    monkeypatch.setattr(mocaprig.progress, "time", types.SimpleNamespace(monotonic=lambda: now[0]))
    out = io.StringIO()
    stages = StageProgress(stream=out, force=True)
    now[0] = 1.0
    stages("simulate", 4, 4)
    now[0] = 11.0  # the batches' first report comes after their first item
    stages("batches", 1, 2)
    assert out.getvalue().endswith("batches [##########          ] 1/2 0.1/s 10s left (10s)")


def test_bind_stage_reports_as_its_stage_and_passes_none_through() -> None:
    calls: list[tuple[str, int, int]] = []
    bound = bind_stage(lambda *call: calls.append(call), "solve")
    assert bound is not None
    bound(3, 8)
    assert calls == [("solve", 3, 8)]
    assert bind_stage(None, "solve") is None
