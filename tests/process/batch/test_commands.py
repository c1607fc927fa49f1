"""``mocaprig process`` (``process.batch.commands``) on a parser of its own, with the cheap
worker functions of ``fake_tasks``."""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator
from pathlib import Path
from unittest.mock import patch

import pytest

from mocaprig.calib.calibration import write_calibration
from mocaprig.errors import ValidationError
from mocaprig.process.batch import runner
from mocaprig.process.batch.commands import register_process
from mocaprig.progress import progress_mode
from tests.process.batch import fake_tasks


@pytest.fixture(autouse=True)
def fake_replay() -> Iterator[None]:
    with patch.dict(runner.TASKS, {"instants": fake_tasks.instants, "span": fake_tasks.span}):
        yield


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="mocaprig")
    register_process(parser.add_subparsers())
    return parser.parse_args(["process", *argv])


def _sessions(root: Path, modes: dict[str, str]) -> list[str]:
    write_calibration(fake_tasks.calibration(), root / "calib.toml")
    for name, mode in modes.items():
        (root / name).mkdir()
        (root / name / "session.mcap").write_bytes(b"")
        (root / name / "mode").write_text(mode)
    return [str(root / n) for n in modes]


def _argv(root: Path, sessions: list[str], *extra: str) -> list[str]:
    calib = ["--calib", str(root / "calib.toml")]
    return [*sessions, *calib, "--methods", "democap", "--out", str(root / "out"), *extra]


def test_json_summary_has_a_row_per_session_and_method(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = _parse(_argv(tmp_path, _sessions(tmp_path, {"a": "ok", "b": "always"}), "--json"))
    assert args.func(args) == 1
    out = json.loads(capsys.readouterr().out)
    assert (out["done"], out["skipped"], out["failed"]) == (1, 0, 1)
    a, b = out["jobs"]
    assert (a["session"], a["method"], a["status"], a["error"]) == ("a", "democap", "done", None)
    assert a["outputs"][-1] == str(tmp_path / "out/a/democap/done.json")
    assert (b["status"], b["stage"]) == ("failed", "span 0")
    assert b["error"] == "RuntimeError: b cannot be replayed"
    assert b["outputs"] == []


def test_table_and_progress_per_session(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = _parse(_argv(tmp_path, _sessions(tmp_path, {"a": "ok"})))
    with progress_mode("always"):
        assert args.func(args) == 0
        assert args.func(args) == 0  # everything finished: kept
    captured = capsys.readouterr()
    assert "a democap: done in" in captured.err
    assert "a democap: finished earlier; kept (remove" in captured.err
    assert "engine: in-process (1 worker)" in captured.err
    lines = captured.out.splitlines()
    assert lines[1].split()[:3] == ["a", "democap", "done"]
    assert lines[-1].startswith("0 done, 1 kept from earlier, 0 failed (in-process")


def test_unknown_methods_are_refused(tmp_path: Path) -> None:
    args = _parse(_argv(tmp_path, _sessions(tmp_path, {"a": "ok"}), "--methods", "vicon"))
    with pytest.raises(ValidationError, match="choose from democap,eventcap"):
        args.func(args)


def test_help_names_the_side_files_and_engines(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        _parse(["--help"])
    text = capsys.readouterr().out
    side = ("eventcap_detections.json", "eventcap_shape.json", "calib.toml", "democap_subject.json")
    for word in (*side, "tcp://"):
        assert word in text
