"""The sync box driver against an in-test pty fake and against engineer E's mock."""

from __future__ import annotations

import contextlib
import errno
import os
import threading
import time
import tty
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import serial

from mocaprig.acquire.syncbox import (
    PROTOCOL_VERSION,
    SyncBox,
    SyncBoxError,
    SyncBoxMode,
    open_mock_syncbox,
)
from mocaprig.errors import (
    DeviceBusyError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceNotFoundError,
    DevicePermissionError,
    DeviceTimeoutError,
    ValidationError,
)

Responder = Callable[[str], list[str]]


class FakeBox:
    """A pty whose far side answers each line with ``responder(line)`` (run from a thread)."""

    def __init__(self, responder: Responder, *, link: Path | None = None) -> None:
        self.responder = responder
        self.received: list[str] = []
        self.pending_out: list[str] = []
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        if link is not None:
            if link.is_symlink():
                link.unlink()
            link.symlink_to(self.port)
            self.port = str(link)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def push(self, line: str) -> None:
        self.pending_out.append(line)

    def _serve(self) -> None:
        buf = b""
        while not self._stop.is_set():
            while self.pending_out:
                os.write(self._master, (self.pending_out.pop(0) + "\r\n").encode())
            try:
                data = os.read(self._master, 256)
            except BlockingIOError:
                time.sleep(0.002)
                continue
            except OSError:
                return
            buf += data
            while b"\n" in buf:
                raw, buf = buf.split(b"\n", 1)
                line = raw.decode().strip()
                if not line:
                    continue
                self.received.append(line)
                for out in self.responder(line):
                    os.write(self._master, (out + "\r\n").encode())

    def hang_up(self) -> None:
        """Close the box side, like a pulled USB cable."""
        self._stop.set()
        self._thread.join(timeout=2)
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)

    close = hang_up


def protocol_box() -> Responder:
    state = {"mode": "IDLE", "count": 0}

    def respond(line: str) -> list[str]:
        parts = line.split()
        cmd = parts[0]
        if cmd == "HELLO":
            return [f"MOCAPRIG-SYNCBOX {PROTOCOL_VERSION} fake"]
        if cmd == "START":
            if state["mode"] != "IDLE":
                return ["ERR 3 busy"]
            state["mode"] = "GENERATE"
            return ["PULSES 0 100", f"OK START {parts[1]} {parts[2]}", "PULSES 30 1000100"]
        if cmd == "STOP":
            state["mode"] = "IDLE"
            return ["OK STOP 42"]
        if cmd == "STATUS":
            return [f"STATUS {state['mode']} 30 100 7 4294967000"]
        if cmd == "REPORT":
            return [f"OK REPORT {parts[1]}"]
        return ["ERR 1 unknown command"]

    return respond


@pytest.fixture
def fake() -> Iterator[FakeBox]:
    box = FakeBox(protocol_box())
    yield box
    box.close()


def test_hello_identifies_the_box(fake: FakeBox) -> None:
    with SyncBox(fake.port, timeout_s=0.5) as box:
        assert box.identity is not None
        assert box.identity.board == "fake"
        assert box.identity.features == ()
        assert box.identity.version == PROTOCOL_VERSION


def test_start_status_stop_and_interleaved_reports(fake: FakeBox) -> None:
    with SyncBox(fake.port, timeout_s=0.5) as box:
        box.start(hz=30, width_us=100)
        status = box.status()
        assert status.mode is SyncBoxMode.GENERATE
        assert (status.hz, status.width_us, status.count) == (30, 100, 7)
        reports = box.read_reports(0.05)
        assert [r.count for r in reports] == [0, 30]
        assert box.stop() == 42
        assert not box.running
    assert fake.received == ["HELLO", "START 30 100", "STATUS", "STOP"]


def test_report_clock_is_unwrapped(fake: FakeBox) -> None:
    with SyncBox(fake.port, timeout_s=0.5) as box:
        fake.push("PULSES 1 4294967000")
        fake.push("PULSES 31 703")
        reports = box.read_reports(0.1)
        assert [r.t_us for r in reports] == [4294967000, (1 << 32) + 703]


def test_err_reply_raises_with_code(fake: FakeBox) -> None:
    with SyncBox(fake.port, timeout_s=0.5) as box:
        box.start(hz=30, width_us=100)
        with pytest.raises(SyncBoxError, match="ERR 3 busy") as info:
            box.start(hz=90, width_us=100)
        assert info.value.code == 3


def test_close_stops_an_active_run(fake: FakeBox) -> None:
    with SyncBox(fake.port, timeout_s=0.5) as box:
        box.start(hz=30, width_us=100)
    assert fake.received[-1] == "STOP"


@pytest.mark.parametrize(
    ("hz", "width_us"), [(0, 100), (2000, 100), (30, 5), (30, 20_000), (29.97, 100)]
)
def test_bad_arguments_are_rejected_before_sending(fake: FakeBox, hz: float, width_us: int) -> None:
    with SyncBox(fake.port, timeout_s=0.5) as box, pytest.raises(ValidationError):
        box.start(hz=hz, width_us=width_us)  # type: ignore[arg-type]
    assert not any(r.startswith("START") for r in fake.received)


def test_wrong_device_is_named() -> None:
    other = FakeBox(lambda line: ["Arduino ready", "?"])
    try:
        with pytest.raises(DeviceError, match=r"not a mocaprig sync box.*Arduino ready"):
            SyncBox(other.port, boot_timeout_s=0.3).open()
    finally:
        other.close()


def test_silent_device_times_out() -> None:
    silent = FakeBox(lambda line: [])
    try:
        with pytest.raises(DeviceError, match="no answer to HELLO"):
            SyncBox(silent.port, boot_timeout_s=0.3).open()
    finally:
        silent.close()


def test_protocol_version_mismatch() -> None:
    future = FakeBox(lambda line: ["MOCAPRIG-SYNCBOX 2 uno"])
    try:
        with pytest.raises(DeviceError, match="protocol version 2"):
            SyncBox(future.port, boot_timeout_s=0.3).open()
    finally:
        future.close()


def test_reply_timeout_names_the_command() -> None:
    def respond(line: str) -> list[str]:
        return ["MOCAPRIG-SYNCBOX 1 fake"] if line == "HELLO" else []

    box_side = FakeBox(respond)
    try:
        with (
            SyncBox(box_side.port, timeout_s=0.2) as box,
            pytest.raises(DeviceError, match="did not answer STATUS"),
        ):
            box.status()
    finally:
        box_side.close()


def test_missing_port_says_so(tmp_path: Path) -> None:
    with pytest.raises(DeviceError, match="does not exist"):
        SyncBox(str(tmp_path / "ttyACM9")).open()


def test_permission_denied_hints_dialout(monkeypatch: pytest.MonkeyPatch) -> None:
    def deny(*_a: object, **_k: object) -> None:
        raise serial.SerialException(errno.EACCES, "could not open port: Permission denied")

    monkeypatch.setattr(serial, "serial_for_url", deny)
    with pytest.raises(DeviceError, match="dialout"):
        SyncBox("/dev/ttyACM0").open()


def test_reconnect_after_hangup_reopens_with_backoff(tmp_path: Path) -> None:
    link = tmp_path / "ttySYNC"
    first = FakeBox(protocol_box(), link=link)
    second: FakeBox | None = None
    try:
        with SyncBox(str(link), timeout_s=0.3, backoff_s=0.05, max_reopen=3) as box:
            first.hang_up()
            second = FakeBox(protocol_box(), link=link)  # the board re-enumerates
            status = box.status()
            assert status.mode is SyncBoxMode.IDLE
            assert box.reconnects == 1
    finally:
        first.close()
        if second is not None:
            second.close()


def test_reconnect_during_a_run_is_not_silent(tmp_path: Path) -> None:
    link = tmp_path / "ttySYNC"
    first = FakeBox(protocol_box(), link=link)
    second: FakeBox | None = None
    try:
        box = SyncBox(str(link), timeout_s=0.3, backoff_s=0.05)
        box.open()
        box.start(hz=30, width_us=100)
        first.hang_up()
        second = FakeBox(protocol_box(), link=link)
        with pytest.raises(DeviceError, match="interrupted"):
            box.status()
        assert not box.running
        box.close()
    finally:
        first.close()
        if second is not None:
            second.close()


def test_gives_up_after_bounded_reopens(tmp_path: Path) -> None:
    link = tmp_path / "ttySYNC"
    first = FakeBox(protocol_box(), link=link)
    try:
        box = SyncBox(str(link), timeout_s=0.3, backoff_s=0.01, max_reopen=2)
        box.open()
        first.hang_up()
        with pytest.raises(DeviceError, match="2 reopen attempt"):
            box.status()
        box.close()
    finally:
        first.close()


# -- engineer E's mock (entry point mocaprig.mocks: syncbox) -------------------------------------


def test_mock_syncbox_end_to_end() -> None:
    with open_mock_syncbox(seed=3) as mock, SyncBox(mock.port) as box:
        assert box.identity is not None
        assert box.identity.board == "mock"
        assert box.identity.features == ("toggle",)
        box.set_report_interval(100)
        box.start(hz=30, width_us=100)
        reports: list[object] = []
        deadline = time.monotonic() + 5
        while len(reports) < 2 and time.monotonic() < deadline:
            reports += box.read_reports(0.1)
        assert len(reports) >= 2
        assert box.status().mode is SyncBoxMode.GENERATE
        assert box.stop() >= 1
        box.listen()
        assert box.status().mode is SyncBoxMode.LISTEN
        box.stop()


def test_mock_syncbox_no_reply_fault_times_out() -> None:
    with (
        open_mock_syncbox(fault="no-reply") as mock,
        SyncBox(mock.port, timeout_s=0.2) as box,
        pytest.raises(DeviceError, match="did not answer"),
    ):
        box.status()


def test_mock_syncbox_disconnect_fault_gives_up() -> None:
    with open_mock_syncbox(fault="disconnect") as mock:
        box = SyncBox(mock.port, timeout_s=0.3, backoff_s=0.01, max_reopen=1)
        box.open()
        with pytest.raises(DeviceError, match="sync box on"):
            box.status()
        box.close()


def test_find_syncboxes_lists_port_names() -> None:
    from mocaprig.acquire.syncbox import find_syncboxes

    ports = find_syncboxes()
    assert all(isinstance(p, str) for p in ports)
    assert ports == sorted(ports)


# -- which DeviceError kind, with pyserial's errno kept --------------------------------------------


def test_missing_port_is_a_not_found_error_with_the_errno(tmp_path: Path) -> None:
    with pytest.raises(DeviceNotFoundError, match="does not exist") as exc:
        SyncBox(str(tmp_path / "ttyACM9")).open()
    assert exc.value.backend_errno == errno.ENOENT
    assert exc.value.backend_error is not None
    assert isinstance(exc.value.__cause__, serial.SerialException)


@pytest.mark.parametrize(
    ("code", "text", "kind", "words"),
    [
        (errno.EACCES, "Permission denied: '/dev/ttyACM0'", DevicePermissionError, "dialout"),
        (errno.EBUSY, "Device or resource busy: '/dev/ttyACM0'", DeviceBusyError, "is busy"),
        (errno.ENOENT, "No such file or directory", DeviceNotFoundError, "does not exist"),
        (errno.EIO, "Input/output error", DeviceError, "cannot open sync box port"),
    ],
)
def test_an_open_failure_is_the_kind_its_errno_says(
    monkeypatch: pytest.MonkeyPatch, code: int, text: str, kind: type[DeviceError], words: str
) -> None:
    # pyserial's own wording: SerialException(errno, "could not open port PORT: [Errno N] ...").
    def refuse(*_a: object, **_k: object) -> None:
        raise serial.SerialException(
            code, f"could not open port /dev/ttyACM0: [Errno {code}] {text}"
        )

    monkeypatch.setattr(serial, "serial_for_url", refuse)
    with pytest.raises(DeviceError, match=words) as exc:
        SyncBox("/dev/ttyACM0").open()
    assert type(exc.value) is kind
    assert exc.value.backend_errno == code


def test_silence_and_a_missing_reply_are_timeout_errors() -> None:
    silent = FakeBox(lambda line: [])
    try:
        with pytest.raises(DeviceTimeoutError, match="no answer to HELLO"):
            SyncBox(silent.port, boot_timeout_s=0.3).open()
    finally:
        silent.close()
    with (
        open_mock_syncbox(fault="no-reply") as mock,
        SyncBox(mock.port, timeout_s=0.2) as box,
        pytest.raises(DeviceTimeoutError, match="did not answer STATUS"),
    ):
        box.status()


def test_a_box_that_answers_wrongly_is_a_plain_device_error() -> None:
    other = FakeBox(lambda line: ["Arduino ready"])
    try:
        with pytest.raises(DeviceError, match="not a mocaprig sync box") as exc:
            SyncBox(other.port, boot_timeout_s=0.3).open()
        assert type(exc.value) is DeviceError
    finally:
        other.close()


def test_a_box_gone_for_good_is_a_disconnected_error(tmp_path: Path) -> None:
    link = tmp_path / "ttySYNC"
    first = FakeBox(protocol_box(), link=link)
    try:
        box = SyncBox(str(link), timeout_s=0.3, backoff_s=0.01, max_reopen=1)
        box.open()
        first.hang_up()
        with pytest.raises(DeviceDisconnectedError, match="1 reopen attempt") as exc:
            box.status()
        assert exc.value.backend_error is not None  # pyserial's words about the failed I/O
        assert isinstance(exc.value.__cause__, serial.SerialException | OSError)
        box.close()
    finally:
        first.close()


def test_the_mock_disconnect_fault_is_a_disconnected_error() -> None:
    with open_mock_syncbox(fault="disconnect") as mock:
        box = SyncBox(mock.port, timeout_s=0.3, backoff_s=0.01, max_reopen=1)
        box.open()
        with pytest.raises(DeviceDisconnectedError, match=r"sync box on .*replug"):
            box.status()
        box.close()


class _FailingPort:
    """A port that opens, then fails on ``write`` or ``read`` as pyserial does."""

    in_waiting = 0

    def __init__(self, fail_on: str, err: Exception) -> None:
        self.fail_on = fail_on
        self.err = err

    def write(self, data: bytes) -> int:
        if self.fail_on == "write":
            raise self.err
        return len(data)

    def flush(self) -> None:
        pass

    def read(self, n: int) -> bytes:
        if self.fail_on == "read":
            raise self.err
        return b""

    def close(self) -> None:
        pass


@pytest.mark.parametrize(
    ("fail_on", "err", "kind", "words"),
    [
        (
            "read",
            serial.SerialException("device reports readiness to read but returned no data"),
            DeviceDisconnectedError,
            "I/O failed while identifying it",
        ),
        ("write", serial.SerialTimeoutException("Write timeout"), DeviceTimeoutError, "HELLO"),
    ],
)
def test_io_failing_while_identifying_the_box_is_a_device_error(
    monkeypatch: pytest.MonkeyPatch,
    fail_on: str,
    err: Exception,
    kind: type[DeviceError],
    words: str,
) -> None:
    monkeypatch.setattr(serial, "serial_for_url", lambda *_a, **_k: _FailingPort(fail_on, err))
    with pytest.raises(kind, match=words) as exc:
        SyncBox("/dev/ttyACM0", boot_timeout_s=0.3).open()
    assert exc.value.__cause__ is err
    assert exc.value.backend_error == str(err)


# -- stale lines: a banner or reply that is not the answer to the command just sent ----------------


def _replying(extra: dict[str, list[str]]) -> Responder:
    """``protocol_box`` whose answers to some commands are replaced by ``extra[command]``."""
    base = protocol_box()

    def respond(line: str) -> list[str]:
        cmd = line.split()[0]
        return extra[cmd] if cmd in extra else base(line)

    return respond


def test_a_second_banner_is_not_taken_as_the_next_reply() -> None:
    # A booting board prints its banner, then answers a HELLO that waited in its buffer.
    banner = f"MOCAPRIG-SYNCBOX {PROTOCOL_VERSION} fake"
    fake = FakeBox(_replying({"HELLO": [banner, banner]}))
    try:
        with SyncBox(fake.port, timeout_s=0.5) as box:
            box.set_report_interval(100)
            assert box.status().mode is SyncBoxMode.IDLE
        assert fake.received == ["HELLO", "REPORT 100", "STATUS"]
    finally:
        fake.close()


def test_an_err_for_a_garbled_hello_is_dropped_after_the_banner() -> None:
    # The bootloader ate the start of a HELLO; the sketch answers "LO" with ERR 1.
    banner = f"MOCAPRIG-SYNCBOX {PROTOCOL_VERSION} fake"
    fake = FakeBox(_replying({"HELLO": [banner, "ERR 1 unknown command"]}))
    try:
        with SyncBox(fake.port, timeout_s=0.5) as box:
            box.start(hz=30, width_us=100)
            assert box.running
    finally:
        fake.close()


def test_bytes_before_the_banner_are_ignored() -> None:
    banner = f"MOCAPRIG-SYNCBOX {PROTOCOL_VERSION} fake toggle"
    fake = FakeBox(_replying({"HELLO": ["\x14\x10" + banner]}))  # a bootloader's STK500 bytes
    try:
        with SyncBox(fake.port, timeout_s=0.5) as box:
            assert box.identity is not None
            assert (box.identity.board, box.identity.features) == ("fake", ("toggle",))
    finally:
        fake.close()


def test_stale_lines_before_a_command_are_dropped_and_reports_kept(fake: FakeBox) -> None:
    with SyncBox(fake.port, timeout_s=0.5) as box:
        fake.push(f"MOCAPRIG-SYNCBOX {PROTOCOL_VERSION} fake")  # late banner
        fake.push("OK STOP 3")  # late reply to a command that timed out
        fake.push("PULSES 5 1000")
        deadline = time.monotonic() + 2
        while fake.pending_out and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.05)
        assert box.stop() == 42  # not the stale "OK STOP 3"
        assert [r.count for r in box.read_reports()] == [5]


def test_a_late_banner_before_the_reply_is_skipped() -> None:
    banner = f"MOCAPRIG-SYNCBOX {PROTOCOL_VERSION} fake"
    fake = FakeBox(_replying({"STATUS": [banner, "STATUS IDLE 0 0 0 12"]}))
    try:
        with SyncBox(fake.port, timeout_s=0.5) as box:
            status = box.status()
            assert (status.mode, status.t_us) == (SyncBoxMode.IDLE, 12)
    finally:
        fake.close()


def test_a_timeout_names_the_lines_dropped_meanwhile() -> None:
    banner = f"MOCAPRIG-SYNCBOX {PROTOCOL_VERSION} fake"
    fake = FakeBox(_replying({"STATUS": [banner]}))
    try:
        with (
            SyncBox(fake.port, timeout_s=0.3) as box,
            pytest.raises(DeviceTimeoutError, match=r"did not answer STATUS.*MOCAPRIG-SYNCBOX"),
        ):
            box.status()
    finally:
        fake.close()


def test_a_booting_mock_is_identified_then_answers_commands() -> None:
    # The mock discards input while it "boots", then prints its banner once (as an Uno does).
    with (
        open_mock_syncbox(seed=4, boot_delay_s=0.7) as mock,
        SyncBox(mock.port, boot_timeout_s=3.0) as box,
    ):
        assert box.identity is not None
        assert box.identity.board == "mock"
        box.set_report_interval(0)
        assert box.status().mode is SyncBoxMode.IDLE
