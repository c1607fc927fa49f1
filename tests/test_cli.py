"""The dispatcher: help, version, usage errors and error reporting."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from mocaprig.cli import emit_json, main
from mocaprig.json_values import to_jsonable
from mocaprig.progress import ProgressBar


def test_help_lists_the_commands_and_examples(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "examples:" in out
    for command in ("simulate", "vicon"):
        assert command in out


def test_no_command_prints_usage_and_returns_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert "usage: mocaprig" in capsys.readouterr().err


def test_to_jsonable_turns_numpy_and_nan_into_plain_json() -> None:
    obj = {"a": np.float32(1.5), "b": np.arange(3), "c": float("nan"), "d": (np.int64(2),)}
    assert to_jsonable(obj) == {"a": 1.5, "b": [0, 1, 2], "c": None, "d": [2]}


def test_emit_json_writes_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    emit_json({"x": np.float64(2.0)})
    out = capsys.readouterr().out
    assert out.count("\n") == 1
    assert json.loads(out) == {"x": 2.0}


def test_progress_bar_is_silent_when_not_a_terminal(capsys: pytest.CaptureFixture[str]) -> None:
    bar = ProgressBar("work")
    bar(1, 2)
    bar(2, 2)
    assert capsys.readouterr().err == ""


def _leaves(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        return [path]
    out = []
    for name, child in subs[0].choices.items():
        out.extend(_leaves(child, (*path, name)))
    return out


def test_every_command_has_a_handler_and_help_with_examples() -> None:
    from mocaprig.cli import _build_parser

    parser = _build_parser()
    leaves = _leaves(parser)
    assert len(leaves) >= 20
    missing = []
    for path in leaves:
        node = parser
        for name in path:
            sub = next(a for a in node._actions if isinstance(a, argparse._SubParsersAction))
            node = sub.choices[name]
        if node.get_default("func") is None:
            missing.append(" ".join(path) + ": no handler")
        text = node.format_help()
        if "examples:" not in text and "example:" not in text:
            missing.append(" ".join(path) + ": no examples in --help")
    assert not missing, "\n".join(missing)


def test_a_group_without_a_subcommand_prints_its_usage_and_exits_2(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["democap"]) == 2
    assert "usage: mocaprig democap" in capsys.readouterr().err
