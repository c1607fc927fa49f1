"""The mock sync box over its pseudo-terminal, driven with a real ``serial.Serial``."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
import serial

from mocaprig.acquire.mocks import load_mock_factory
from mocaprig.drivers_mock.syncbox import MockSyncBox, mock_syncbox
from mocaprig.errors import ValidationError


class _Host:
    """A minimal host side of docs/syncbox-protocol.md (files PULSES reports away)."""

    def __init__(self, port: str) -> None:
        self.ser = serial.Serial(port, 115200, timeout=1.0)
        self.reports: list[str] = []

    def send(self, line: str) -> str:
        self.ser.write(line.encode("ascii") + b"\n")
        while True:
            raw = self.ser.readline()
            if not raw:
                return ""  # timeout
            text = str(raw.decode("ascii")).rstrip("\r\n")
            assert raw.endswith(b"\r\n")
            if text.startswith("PULSES "):
                self.reports.append(text)
                continue
            return text

    def close(self) -> None:
        self.ser.close()


@pytest.fixture
def box() -> Iterator[MockSyncBox]:
    with mock_syncbox(seed=2) as b:
        yield b


def test_hello_start_reports_status_stop(box: MockSyncBox) -> None:
    host = _Host(box.port)
    try:
        assert host.send("HELLO") == "MOCAPRIG-SYNCBOX 1 mock toggle"
        assert host.send("REPORT 100") == "OK REPORT 100"
        assert host.send("START 30 100") == "OK START 30 100"
        time.sleep(0.45)
        status = host.send("STATUS").split()
        assert status[:4] == ["STATUS", "GENERATE", "30", "100"]
        assert 11 <= int(status[4]) <= 16  # ~0.45 s at 30 Hz, first pulse a period after START
        assert host.send("START 90 100") == "ERR 3 busy"
        stop = host.send("STOP").split()
        assert stop[:2] == ["OK", "STOP"]
        assert int(stop[2]) >= int(status[4])
        assert len(host.reports) >= 3
        counts = [int(r.split()[1]) for r in host.reports]
        stamps = [int(r.split()[2]) for r in host.reports]
        assert counts == sorted(counts)
        # Consecutive reports: Δt_us matches Δcount / 30 Hz on the box clock (±50 ppm).
        for i in range(1, len(counts)):
            dc = counts[i] - counts[i - 1]
            assert abs((stamps[i] - stamps[i - 1]) - dc * 1e6 / 30) <= 2
        n_reports = len(host.reports)
        assert host.send("STATUS").split()[1:5] == ["IDLE", "0", "0", "0"]
        time.sleep(0.25)
        assert host.send("STATUS").startswith("STATUS IDLE")
        assert len(host.reports) == n_reports  # no report after OK STOP
        assert host.send("STOP") == "OK STOP 0"
    finally:
        host.close()


def test_errors(box: MockSyncBox) -> None:
    host = _Host(box.port)
    try:
        assert host.send("FLY") == "ERR 1 unknown command"
        assert host.send("hello") == "ERR 1 unknown command"
        assert host.send("START 30") == "ERR 2 bad argument"
        assert host.send("START 0 100") == "ERR 2 bad argument"
        assert host.send("START 30 20000") == "ERR 2 bad argument"  # width > period/2
        assert host.send("START -30 100") == "ERR 2 bad argument"
        assert host.send("REPORT 50") == "ERR 2 bad argument"
        assert host.send("HELLO there") == "ERR 2 bad argument"
        assert host.send("X" * 70) == "ERR 4 line too long"
        host.ser.timeout = 0.2
        assert host.send("") == ""  # empty lines are ignored: no reply
        host.ser.timeout = 1.0
        assert host.send("\rHELLO\r") == "MOCAPRIG-SYNCBOX 1 mock toggle"
    finally:
        host.close()


def test_listen_counts_the_external_train() -> None:
    with mock_syncbox(seed=1, listen_hz=90.0) as b:
        host = _Host(b.port)
        try:
            assert host.send("LISTEN") == "OK LISTEN"
            time.sleep(0.3)
            assert host.send("LISTEN") == "ERR 3 busy"
            count = int(host.send("STOP").split()[2])
            assert 20 <= count <= 30
        finally:
            host.close()


def test_no_reply_fault_times_out() -> None:
    with mock_syncbox(fault="no-reply") as b:
        host = _Host(b.port)
        host.ser.timeout = 0.3
        try:
            assert host.send("HELLO") == "MOCAPRIG-SYNCBOX 1 mock toggle"
            assert host.send("STATUS") == ""
        finally:
            host.close()


def test_disconnect_fault_raises_serial_exception() -> None:
    with mock_syncbox(fault="disconnect") as b:
        host = _Host(b.port)
        try:
            assert host.send("HELLO") == "MOCAPRIG-SYNCBOX 1 mock toggle"
            with pytest.raises(serial.SerialException):  # noqa: PT012
                host.send("STATUS")
                host.send("STATUS")
        finally:
            host.close()


def test_entry_point_and_options() -> None:
    factory = load_mock_factory("syncbox")
    with factory(seed=0, fault=None) as b:
        assert b.port.startswith("/dev/")
        with serial.serial_for_url(b.port, 115200, timeout=1.0) as ser:
            ser.write(b"HELLO\n")
            assert ser.readline() == b"MOCAPRIG-SYNCBOX 1 mock toggle\r\n"
    with pytest.raises(ValidationError):
        mock_syncbox(fault="explode")  # type: ignore[arg-type]


def test_listen_counts_a_pulse_source() -> None:
    t0 = time.monotonic_ns()
    period = 10_000_000  # 100 Hz, first edge 5 ms after session 0

    def pulse_at_or_after(t_ns: int) -> int | None:
        k = max(0, -(-(t_ns - 5_000_000) // period))
        return 5_000_000 + k * period

    with mock_syncbox(pulse_source=pulse_at_or_after, session_t0_ns=t0) as b:
        host = _Host(b.port)
        try:
            assert host.send("LISTEN") == "OK LISTEN"
            time.sleep(0.25)
            status = host.send("STATUS").split()
            count = int(host.send("STOP").split()[2])
            assert 20 <= int(status[4]) <= count <= 35
        finally:
            host.close()


class _SessionClock:
    """A session clock the test sets by hand (ns), so the box counts no wall time."""

    def __init__(self) -> None:
        self.now_ns = 0

    def __call__(self) -> int:
        return self.now_ns


def test_the_first_generated_pulse_comes_one_period_after_start() -> None:
    # As the firmware's Timer1: it starts at 0 with D9 low and first reaches TOP after a period.
    clock = _SessionClock()
    with mock_syncbox(seed=5, session_clock_ns=clock) as b:
        host = _Host(b.port)
        try:
            assert host.send("REPORT 0") == "OK REPORT 0"
            assert host.send("START 10 100") == "OK START 10 100"  # period 100 ms
            counts = {}
            # The box clock drifts by at most 20 ppm: 1 % of a period either side is clear.
            for t_ms in (0, 99, 101, 199, 201, 550):
                clock.now_ns = t_ms * 1_000_000
                counts[t_ms] = int(host.send("STATUS").split()[4])
            assert counts == {0: 0, 99: 0, 101: 1, 199: 1, 201: 2, 550: 5}
            clock.now_ns = 550_000_000
            assert host.send("STOP") == "OK STOP 5"
        finally:
            host.close()


def test_reports_stamp_the_last_pulse_on_the_box_clock() -> None:
    clock = _SessionClock()
    with mock_syncbox(seed=6, session_clock_ns=clock) as b:
        host = _Host(b.port)
        try:
            assert host.send("REPORT 100") == "OK REPORT 100"
            t0_us = int(host.send("STATUS").split()[5])  # the box clock at session time 0
            assert host.send("START 30 100") == "OK START 30 100"
            clock.now_ns = 1_050_000_000  # 31.5 periods: 31 pulses, the last at 31/30 s
            deadline = time.monotonic() + 5
            while not host.reports and time.monotonic() < deadline:
                host.ser.timeout = 0.1
                raw = host.ser.readline()
                if raw.startswith(b"PULSES "):
                    host.reports.append(raw.decode("ascii").strip())
            host.ser.timeout = 1.0
            assert host.reports, "no PULSES report"
            _, count, t_us = host.reports[0].split()
            assert int(count) == 31
            assert (int(t_us) - t0_us) % (1 << 32) == round(31 * 1e6 / 30)
        finally:
            host.close()
