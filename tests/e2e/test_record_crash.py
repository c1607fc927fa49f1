"""`kill -9` of a running `mocaprig record` process: `mocaprig info` (a separate process) lists
every complete chunk of the crashed file and `mocaprig recover` writes an indexed file."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader

from mocaprig.cli import main

_RIG = "format_version = 1\nmock = true\n[syncbox]\nport = 'mock'\n"


def _complete_chunks(path: Path) -> tuple[int, int]:
    """(complete chunks, messages in them), counted with the mcap library's stream reader
    independently of mocaprig: records are read until the truncated tail fails to parse."""
    chunks = messages = 0
    with path.open("rb") as f:
        try:
            for rec in StreamReader(f, emit_chunks=True).records:
                if isinstance(rec, Chunk):
                    chunks += 1
        except Exception:
            pass
    with path.open("rb") as f:
        try:
            for rec in StreamReader(f).records:
                messages += type(rec).__name__ == "Message"
        except Exception:
            pass
    return chunks, messages


def _cli(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """The mocaprig CLI in this process (the recorder is the separate, killed process)."""
    code = main(list(args))
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.slow  # a mocaprig process start (~2-8 s) and a few chunk ages
def test_kill_9_mid_recording_info_lists_complete_chunks_and_recover_indexes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text(_RIG)
    crashed = tmp_path / "crashed.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-m", "mocaprig.cli", "record", "--rig", str(rig), "--seconds", "120",
         "--out", str(crashed)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                break
            if crashed.exists() and _complete_chunks(crashed)[0] >= 3:
                break
            time.sleep(0.2)
        assert proc.poll() is None, f"mocaprig record ended early (exit {proc.returncode})"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    chunks, messages = _complete_chunks(crashed)
    assert chunks >= 3
    assert messages > 0

    code, out, err = _cli(capsys, "info", str(crashed), "--json")
    assert code == 0, err
    inf = json.loads(out)
    assert inf["indexed"] is False
    assert inf["complete_chunks"] == chunks
    assert sum(s["messages"] for s in inf["streams"]) == messages
    assert "/syncbox/pulses" in {s["topic"] for s in inf["streams"]}

    fixed = tmp_path / "fixed.mcap"
    code, out, err = _cli(capsys, "recover", str(crashed), str(fixed), "--json")
    assert code in (0, 3), err  # 3: the torn tail was lost
    rep = json.loads(out)
    assert rep["messages"] == messages
    with fixed.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    assert summary.chunk_indexes
    assert summary.statistics is not None
    assert summary.statistics.message_count == messages
    code, out, err = _cli(capsys, "info", str(fixed), "--json")
    assert code == 0, err
    fixed_info = json.loads(out)
    assert fixed_info["indexed"] is True
    assert fixed_info["recovered"] is True
