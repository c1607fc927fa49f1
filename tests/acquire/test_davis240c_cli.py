"""``mocaprig davis ...`` and ``mocaprig devices`` against the mock camera."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

import mocaprig.acquire.davis240c
from mocaprig.acquire.commands import DEVICE_PROBERS, DeviceListing
from mocaprig.acquire.davis240c import Davis240C
from mocaprig.cli import main
from mocaprig.drivers_mock.davis240c_usb import DavisFaults, SyntheticDavisSource, mock_backend
from mocaprig.errors import DeviceDisconnectedError


@pytest.fixture(autouse=True)
def fast_mock(monkeypatch: pytest.MonkeyPatch) -> None:
    """`--mock` gets a cheap synthetic world (the default is the full renderer, ~2 s to build);
    ``monkeypatch.undo()`` restores the real entry point."""

    def factory(**kwargs: Any) -> Any:
        return mock_backend(source=SyntheticDavisSource(seed=5, event_rate_hz=100_000.0))

    monkeypatch.setattr(mocaprig.acquire.davis240c, "load_mock_backend", factory)


def run_json(capsys: pytest.CaptureFixture[str], argv: list[str]) -> dict[str, Any]:
    assert main(argv) == 0
    out: dict[str, Any] = json.loads(capsys.readouterr().out)
    return out


@pytest.mark.parametrize("sub", ["decode", "info", "config", "stream"])
def test_every_subcommand_has_examples(sub: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["davis", sub, "--help"])
    assert exc.value.code == 0
    assert "examples:\n  mocaprig davis " + sub in capsys.readouterr().out


def test_davis_without_subcommand_prints_usage(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["davis"]) == 2
    assert "mocaprig davis stream" in capsys.readouterr().err


def test_info_mock_json_through_the_entry_point(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.undo()  # the registered mock, as a user gets it
    info = run_json(capsys, ["davis", "info", "--mock", "--json"])
    assert info["logic_version"] == 18
    assert info["firmware_version"] == 4
    assert info["device_is_master"] is True
    assert info["chip_id"] == 2
    assert info["clocks"]["logic_mhz"] == 90
    assert info["device_string"] == f"DAVIS240C_{info['serial']}"


def test_info_mock_text(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["davis", "info", "--mock"]) == 0
    out = capsys.readouterr().out
    assert "firmware 4, logic 18.1" in out
    assert "role: master" in out


def test_config_writes_and_reads_back(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["davis", "config", "--mock", "--bias-preset", "pyaer", "--json"]
    argv += ["--set", "APS.EXPOSURE=8000", "--set", "BIAS.ONBN=6/201"]
    out = run_json(capsys, argv)
    assert out["bias_preset"] == "pyaer"
    assert [(w["name"], w["value"], w["readback"]) for w in out["writes"]] == [
        ("APS.EXPOSURE", 240000, 240000),
        ("BIAS.ONBN", 0x6C9F, 0x6C9F),
    ]


def test_config_errors_are_reported_without_a_traceback(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["davis", "config", "--mock", "--set", "APS.SHUTTER=1"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("ERROR: unknown parameter 'SHUTTER' of APS")
    assert main(["davis", "config", "--mock", "--bias-preset", "loud"]) == 1
    assert "default, legacy, pyaer" in capsys.readouterr().err


def test_stream_raw_out_decodes_to_the_same_counts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    raw = tmp_path / "cap.bin"
    stream = run_json(
        capsys, ["davis", "stream", "--mock", "--seconds", "0.5", "--raw-out", str(raw), "--json"]
    )
    assert stream["events"] > 0
    assert stream["error"] is None
    assert stream["stats"]["packets_dropped"] == 0
    assert stream["device_dropped"] == {"dvs": 0, "ext_input": 0}
    assert raw.stat().st_size == stream["stats"]["decode"]["bytes_in"]
    decoded = run_json(
        capsys, ["davis", "decode", str(raw), "--out", str(tmp_path / "cap.npz"), "--json"]
    )
    assert decoded["events"] == stream["events"]
    assert decoded["frames"] == stream["frames"]
    assert decoded["imu_samples"] == stream["imu_samples"]
    assert decoded["skipped_words"] == 0
    assert decoded["specials"]["TIMESTAMP_RESET"] == 1


def test_stream_refuses_to_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    raw = tmp_path / "cap.bin"
    raw.write_bytes(b"keep")
    assert main(["davis", "stream", "--mock", "--seconds", "0.1", "--raw-out", str(raw)]) == 1
    assert "not overwriting" in capsys.readouterr().err
    assert raw.read_bytes() == b"keep"


def test_stream_text_summary(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["davis", "stream", "--mock", "--seconds", "0.2"]) == 0
    assert "events" in capsys.readouterr().out


def test_decode_missing_file_says_how_to_record(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["davis", "decode", str(tmp_path / "nope.bin"), "--out", "x.npz"]) == 1
    assert "mocaprig davis stream" in capsys.readouterr().err


def test_decode_text_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    raw = tmp_path / "tiny.bin"
    raw.write_bytes(bytes([0x23, 0x81, 0x11, 0x10, 0xC8, 0x30]))
    assert main(["davis", "decode", str(raw), "--out", str(tmp_path / "t.npz")]) == 0
    assert "1 events" in capsys.readouterr().out


def test_devices_lists_the_mock_rig(capsys: pytest.CaptureFixture[str]) -> None:
    out = run_json(capsys, ["devices", "--mock", "--json"])
    kinds = [d["kind"] for d in out["devices"]]
    assert kinds.count("D415") == 4
    assert kinds.count("syncbox") == 1
    (dev,) = [d for d in out["devices"] if d["kind"] == "DAVIS240C"]
    assert dev["details"]["logic_version"] == 18
    assert dev["location"].startswith("bus ")
    assert out["prober_errors"] == {}


def test_devices_takes_more_probers(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def d415(mock: bool) -> list[DeviceListing]:
        return [DeviceListing(kind="D415", serial="123", location="bus 2 address 3")]

    monkeypatch.setitem(DEVICE_PROBERS, "d415", d415)
    assert main(["devices", "--mock"]) == 0
    out = capsys.readouterr().out
    assert "DAVIS240C" in out
    assert "D415" in out


def test_stream_reports_a_disconnect_and_fails(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def unplugging(**kwargs: Any) -> Any:
        # The camera is pulled once the host has read 1 MB after the start sequence's
        # timestamp reset: an unplug at a fixed device time, or after 1 MB counted from the
        # first read, cut the start instead on a loaded machine (the host discards what comes
        # before the reset word, and the start's sleeps stretch there).
        source = SyntheticDavisSource(seed=5, event_rate_hz=50_000.0)
        backend = mock_backend(source=source, pacing="realtime")
        read = backend.bulk_read
        taken = [0]

        def bulk_read(dev_handle: Any, ep: int, intf: int, buff: Any, timeout: int) -> int:
            n = read(dev_handle, ep, intf, buff, timeout)
            taken[0] += n if reset[0] else 0
            if taken[0] >= 1_000_000 and backend.faults.unplug_at_us is None:
                backend.faults = DavisFaults(unplug_at_us=backend.uptime_us + 1)
            return n

        backend.bulk_read = bulk_read  # type: ignore[method-assign]
        return backend

    reset = [False]
    timestamp_reset = Davis240C.timestamp_reset

    def resetting(cam: Davis240C) -> None:
        timestamp_reset(cam)
        reset[0] = True

    monkeypatch.setattr(mocaprig.acquire.davis240c, "load_mock_backend", unplugging)
    monkeypatch.setattr(Davis240C, "timestamp_reset", resetting)
    raw = tmp_path / "cap.bin"
    argv = ["davis", "stream", "--mock", "--seconds", "60", "--raw-out", str(raw), "--json"]
    assert main(argv) == 1
    captured = capsys.readouterr()
    assert captured.out, captured.err
    out = json.loads(captured.out)
    assert "disconnected" in out["error"]
    assert out["events"] > 0
    assert "ERROR: DAVIS240C" in captured.err
    assert raw.stat().st_size == out["stats"]["decode"]["bytes_in"]


def test_stream_unplugged_after_its_last_packet_still_reports_json(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The camera goes away between the last packet and the drop-counter read that ends the run
    # (a race a loaded machine hits): the summary is still written, with the error in it.
    def gone(self: Any) -> dict[str, int]:
        msg = "DAVIS240C 00000042: disconnected while reading register (0, 83)"
        raise DeviceDisconnectedError(msg)

    monkeypatch.setattr(mocaprig.acquire.davis240c.Davis240C, "device_drop_counts", gone)
    raw = tmp_path / "cap.bin"
    argv = ["davis", "stream", "--mock", "--seconds", "0.5", "--raw-out", str(raw), "--json"]
    assert main(argv) == 1
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert "disconnected while reading register" in out["error"]
    assert out["device_dropped"] == {}
    assert "ERROR: DAVIS240C" in captured.err
    assert raw.stat().st_size == out["stats"]["decode"]["bytes_in"]
