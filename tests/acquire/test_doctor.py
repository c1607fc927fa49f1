"""``mocaprig doctor`` on the simulated rig: every injected fault is reported with its fix."""

from __future__ import annotations

import json
from typing import Any

import pytest

from mocaprig.acquire.doctor import Verdict, check_libusb, run_doctor
from mocaprig.cli import main
from mocaprig.errors import ValidationError


def _fixes(report: Any) -> dict[tuple[str, str], str]:
    return {
        (f.subject.split("/")[0].split(" ")[0], f.check): f.fix
        for f in report.findings
        if f.verdict is Verdict.FIX
    }


@pytest.mark.slow
def test_doctor_on_the_healthy_mock_rig_finds_nothing_to_fix(
    capsys: pytest.CaptureFixture[str],
) -> None:
    if check_libusb().verdict is Verdict.FIX:  # the doctor is right to report it then
        pytest.skip(
            "libusb-1.0 is not installed on this host (Debian: apt-get install libusb-1.0-0; "
            ".ci/run installs it): the rig is not healthy without it"
        )
    assert main(["doctor", "--mock", "--seconds", "1", "--listen-seconds", "0.5", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is True
    checks = {(f["subject"].split("/")[0].split(" ")[0], f["check"]) for f in out["findings"]}
    for want in [("host", "libusb"), ("davis", "identity"), ("davis", "stream"),
                 ("d415", "firmware"), ("d415", "usb"), ("d415", "metadata"), ("d415 rig", "sync"),
                 ("syncbox", "protocol"), ("syncbox", "pulses")]:  # fmt: skip
        assert want in checks or (want[0].split(" ")[0], want[1]) in checks, want


@pytest.mark.slow
def test_doctor_reports_missing_metadata_and_an_unwired_box_with_their_fixes() -> None:
    report = run_doctor(
        mock=True, faults=["d415:no-metadata", "syncbox:unwired"], seconds=1.0, listen_s=0.5
    )
    assert not report.ok
    fixes = _fixes(report)
    assert "kernel patch" in fixes["d415", "metadata"]
    assert "no hardware timestamps" in next(f.detail for f in report.findings if f.check == "sync")
    assert "wire the master D415" in fixes["syncbox", "pulses"]


@pytest.mark.slow
def test_doctor_reports_a_silent_box_and_a_camera_that_disconnects() -> None:
    report = run_doctor(
        mock=True, faults=["syncbox:no-reply", "d415:disconnect"], seconds=1.0, listen_s=0.5
    )
    fixes = _fixes(report)
    assert "flash firmware/syncbox" in fixes["syncbox", "protocol"]
    assert "USB cables" in fixes["d415", "stream"]


def test_doctor_without_libusb_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    import usb.backend.libusb1

    monkeypatch.setattr(usb.backend.libusb1, "get_backend", lambda *a, **k: None)
    finding = check_libusb()
    assert finding.verdict is Verdict.FIX
    assert "libusb-1.0-0" in finding.fix


def test_devices_without_libusb_ends_with_a_clear_message_not_a_traceback(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import usb.backend.libusb1

    monkeypatch.setattr(usb.backend.libusb1, "get_backend", lambda *a, **k: None)
    assert main(["devices", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert "libusb-1.0-0" in out["prober_errors"]["davis"]


def test_doctor_refuses_unknown_faults_and_faults_without_the_mock() -> None:
    with pytest.raises(ValidationError, match="unknown fault"):
        run_doctor(mock=True, faults=["d415:melted"])
    with pytest.raises(ValidationError, match="--mock"):
        run_doctor(mock=False, faults=["d415:no-metadata"])


@pytest.mark.slow
def test_doctor_reports_an_unplugged_davis_and_an_untriggered_slave() -> None:
    report = run_doctor(
        mock=True, faults=["davis:unplug", "d415:slave-trigger-cut"], seconds=1.0, listen_s=0.2
    )
    fixes = _fixes(report)
    assert "USB cable" in fixes.get(("davis", "stream"), ""), report.findings
    assert "sync cable" in fixes["d415", "sync"]
    sync = next(f for f in report.findings if f.check == "sync")
    assert "free-running" in sync.detail


@pytest.mark.slow
def test_doctor_warns_of_events_the_davis_dropped_on_the_device() -> None:
    report = run_doctor(mock=True, faults=["davis:usb-bandwidth"], seconds=1.0, listen_s=0.2)
    stream = next(
        f for f in report.findings if f.subject.startswith("davis/") and f.check == "stream"
    )
    assert stream.verdict is Verdict.WARN
    assert "on the device" in stream.detail
    assert "own USB controller" in stream.fix
