"""`mocaprig record --rig RIG.toml`: the mock dry-run records every listed stream and the rig
file; a listed real device that is not connected is a clear error."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from mocaprig.acquire import camera_backends, davis240c, depth_camera
from mocaprig.acquire.recording import Recording, info
from mocaprig.cli import main
from mocaprig.errors import DeviceError

_MOCK_RIG = """\
format_version = 1
mock = true

[session]
name = "dry-run"

[[d415]]
serial = "819612070593"
role = "master"
mode = "848x480@30"
exposure_us = 7000
gain = 20

[davis]
serial = "02460045"
bias_preset = "legacy"

[syncbox]
port = "/dev/ttyACM0"
mode = "listen"
"""


@pytest.mark.slow  # builds the simulated world (~4 s) and records 2 s
def test_record_rig_mock_records_every_listed_stream_and_the_rig_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text(_MOCK_RIG)
    out = tmp_path / "s.mcap"
    try:
        code = main(["record", "--rig", str(rig), "--seconds", "2", "--out", str(out), "--json"])
    except DeviceError as err:  # the mocks are entry points of the installed package
        pytest.skip(f"mock devices not available: {err}")
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["drops_total"] == 0
    inf = info(out)
    streams = {s.topic: s for s in inf.streams}
    d415 = [t for t in streams if t.startswith("/d415/")]
    assert {t.rsplit("/", 1)[1] for t in d415} == {"ir", "depth", "frame_info", "camera_info"}
    assert {t for t in streams if t.startswith("/davis/")} == {
        f"/davis/02460045/{s}" for s in ("events", "frame", "frame_info", "imu", "trigger")
    }
    assert "/syncbox/pulses" in streams
    assert all(s.drops == 0 for s in inf.streams), {t: s.drops for t, s in streams.items()}
    ir = next(t for t in d415 if t.endswith("/ir"))
    # The camera was configured, started and read: its calibration is written at start. (How
    # many frames a realtime-paced mock renders in 2 s depends on the machine's load; frame
    # recording itself is checked deterministically in test_recorder_sources.py.)
    assert streams[ir.replace("/ir", "/camera_info")].messages == 1
    assert streams[ir.replace("/ir", "/depth")].messages == streams[ir].messages
    assert streams[ir.replace("/ir", "/frame_info")].messages == streams[ir].messages
    assert streams["/syncbox/pulses"].messages > 0
    with Recording(out) as r:
        att = {a.name: a for a in r.attachments()}
        meta = r.metadata()
        logs = [m.decode().message for m in r.messages("/log")]
    assert any("DAVIS 02460045 driver counters: packets dropped 0" in m for m in logs)
    assert att["rig.toml"].data.decode() == _MOCK_RIG
    assert att["rig.toml"].media_type == "application/toml"
    assert meta["rig"]["d415.0.serial"] == "819612070593"
    assert meta["session"]["name"] == "dry-run"
    assert meta["session"]["mock"] == "true"
    dev = next(v for k, v in meta.items() if k.startswith("device/d415/"))
    assert dev["rig_serial"] == "819612070593"
    assert dev["rig_role"] == "master"
    assert dev["options.exposure_us"] == "7000"
    assert dev["sync_mode"] == str(int(depth_camera.SyncMode.MASTER))
    assert meta["settings/davis/02460045"]["dvs.run"] == "true"
    assert meta["device/syncbox"]["mode"] == "listen"


class _FakeCam:
    def __init__(self, serial: str) -> None:
        self.info = type("Info", (), {"serial": serial})()
        self.closed = False

    def close(self) -> None:
        self.closed = True


def test_record_rig_missing_d415_names_it_and_lists_connected(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    connected = [_FakeCam("819612070111"), _FakeCam("819612070222")]

    def fake_realsense(**_: Any) -> list[Any]:
        return connected

    monkeypatch.setitem(camera_backends._BACKENDS, "realsense", fake_realsense)
    rig = tmp_path / "rig.toml"
    rig.write_text(
        "format_version = 1\n[[d415]]\nserial = '819612070593'\nrole = 'master'\n"
        "[[d415]]\nserial = '819612070222'\nrole = 'slave'\n"
    )
    out = tmp_path / "s.mcap"
    assert main(["record", "--rig", str(rig), "--seconds", "1", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"D415 819612070593 listed in {rig} is not connected" in err
    assert "connected: ['819612070111', '819612070222']" in err
    assert "run `mocaprig devices`" in err
    assert all(c.closed for c in connected)
    assert not out.exists()


def test_record_rig_missing_davis_names_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    seen = davis240c.DavisUsbDevice(bus=1, address=4, product_id=0x841B, serial="02460099",
                                    firmware_version=4)  # fmt: skip
    monkeypatch.setattr(davis240c, "find_davis", lambda **_: [seen])
    rig = tmp_path / "rig.toml"
    rig.write_text("format_version = 1\n[davis]\nserial = '02460045'\n")
    assert main(["record", "--rig", str(rig), "--seconds", "1", "--out", str(tmp_path / "a")]) == 1
    err = capsys.readouterr().err
    assert "DAVIS 02460045 listed in" in err
    assert "connected: ['02460099']" in err


def test_record_rig_missing_syncbox_port_is_a_device_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text(f"format_version = 1\n[syncbox]\nport = '{tmp_path / 'ttyNONE'}'\n")
    assert main(["record", "--rig", str(rig), "--seconds", "1", "--out", str(tmp_path / "a")]) == 1
    err = capsys.readouterr().err
    assert "ttyNONE listed in" in err
    assert "cannot be opened" in err


def test_record_rig_invalid_file_is_a_validation_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text("format_version = 1\n[davis]\nserial = '02460045'\nbias = 'x'\n")
    assert main(["record", "--rig", str(rig), "--seconds", "1", "--out", str(tmp_path / "a")]) == 1
    assert "unknown key 'davis.bias'" in capsys.readouterr().err
