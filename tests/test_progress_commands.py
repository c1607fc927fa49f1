"""Issue 18's acceptance for progress: commands draw progress lines on stderr (forced here with
``--progress always``, stderr being no terminal under pytest) and none under ``--json`` or
``-q``, which keep stdout one JSON object and stderr free of status lines."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from mocaprig.cli import main
from tests.conftest import CalibratedSession

#: One drawn progress line: a label, a bar and ``done/total``.
_BAR = re.compile(r"\r[\w ]+ \[#* *\] \d+/\d+")


def _simulate_argv(out: Path) -> list[str]:
    # The smallest session the simulator makes: truth and Vicon only, in well under a second.
    return ["simulate", "--seconds", "3", "--devices", "none", "--out", str(out), "--overwrite"]


def test_simulate_draws_progress_when_forced(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["--progress", "always", *_simulate_argv(tmp_path / "sim")]) == 0
    err = capsys.readouterr().err
    assert _BAR.search(err), err
    assert "simulate truth [" in err
    assert "simulate vicon [" in err


@pytest.mark.parametrize(
    "argv",
    [
        ["--progress", "always", "--quiet"],
        ["--progress", "always"],  # with --json after the command
    ],
    ids=["quiet", "json"],
)
def test_simulate_is_quiet_under_json_and_quiet(
    argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    as_json = "--quiet" not in argv
    cmd = [*argv, *_simulate_argv(tmp_path / "sim"), *(["--json"] if as_json else [])]
    assert main(cmd) == 0
    out, err = capsys.readouterr()
    assert "\r" not in err
    assert not _BAR.search(err)
    if as_json:
        assert json.loads(out)["seconds"] == 3.0


@pytest.mark.slow
def test_davis_decode_draws_progress_and_is_quiet_under_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    raw = tmp_path / "cap.bin"
    argv = ["davis", "stream", "--mock", "--seconds", "0.3", "--raw-out", str(raw), "--json"]
    assert main(["--progress", "always", *argv]) == 0
    assert "\r" not in capsys.readouterr().err  # the stream's live line is quiet under --json
    decode = ["davis", "decode", str(raw), "--out", str(tmp_path / "a.npz")]
    assert main(["--progress", "always", *decode]) == 0
    err = capsys.readouterr().err
    assert re.search(r"\rdecode \[#+ *\] \d+/\d+ kB", err), err
    decode = ["davis", "decode", str(raw), "--out", str(tmp_path / "b.npz"), "--json"]
    assert main(["--progress", "always", *decode]) == 0
    out, err = capsys.readouterr()
    assert "\r" not in err
    assert json.loads(out)["events"] > 0


@pytest.mark.slow
def test_calibrate_vicon_draws_its_steps_and_the_report_files(
    calibrated_session: CalibratedSession, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sim = calibrated_session.session.parent
    report = tmp_path / "report"
    argv = [
        "--progress", "always", "calibrate", "vicon", str(calibrated_session.session),
        str(sim / "vicon" / "session.c3d"), "--out", str(tmp_path / "c.toml"),
        "--report", str(report),
    ]  # fmt: skip
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert re.search(r"\rcalibrate vicon \[#* *\] \d/7 steps", err), err
    assert re.search(r"\rcalibration report \[#+\] (\d+)/\1 files", err), err
    assert (report / "index.html").is_file()


@pytest.mark.slow
def test_democap_run_draws_its_instants_and_is_quiet_under_json(
    calibrated_session: CalibratedSession, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = ["democap", "run", str(calibrated_session.session), "--calib"]
    argv = [*base, str(calibrated_session.calib), "--every", "30", "--rotations", "1"]
    assert main(["--progress", "always", *argv, "--out", str(tmp_path / "a.mcap")]) == 0
    err = capsys.readouterr().err
    assert re.search(r"\rdemocap run \[#+\] (\d+)/\1 instants", err), err
    assert main(["--progress", "always", *argv, "--out", str(tmp_path / "b.mcap"), "--json"]) == 0
    out, err = capsys.readouterr()
    assert "\r" not in err
    assert json.loads(out)["instants"] > 0


def test_info_and_recover_draw_the_bytes_read_and_are_quiet_under_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import numpy as np

    from mocaprig.acquire.recorder import Recorder
    from mocaprig.acquire.recording_format import ImageMsg

    src = tmp_path / "s.mcap"
    img = np.random.default_rng(0).integers(0, 65535, (120, 160)).astype(np.uint16)
    with Recorder(src, compression="none") as rec:
        h = rec.add_stream("/d415/1/depth", ImageMsg)
        for _ in range(40):
            rec.put(h, ImageMsg(img, "16UC1"))
    assert main(["--progress", "always", "info", str(src)]) == 0
    err = capsys.readouterr().err
    assert re.search(r"\rinfo s\.mcap \[#+\] (\d+)/\1 kB", err), err
    assert main(["--progress", "always", "recover", str(src), str(tmp_path / "r.mcap")]) == 0
    err = capsys.readouterr().err
    assert re.search(r"\rrecover s\.mcap \[#+\] (\d+)/\1 kB", err), err
    assert main(["--progress", "always", "info", str(src), "--json"]) == 0
    out, err = capsys.readouterr()
    assert "\r" not in err
    assert json.loads(out)["indexed"] is True


def test_import_events_draws_the_packets_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    txt = tmp_path / "ev.txt"
    txt.write_text("".join(f"{k * 1e-4:.6f} {k % 240} {k % 180} {k % 2}\n" for k in range(3000)))
    out = tmp_path / "ev.mcap"
    assert main(["--progress", "always", "import-events", str(txt), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert re.search(r"\rimport ev\.txt \[#+\] 30/30 packets", err), err
