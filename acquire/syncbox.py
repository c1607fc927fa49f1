"""Driver of the mocaprig sync box (pyserial), speaking ``docs/syncbox-protocol.md`` version 1.

The box generates the rig's frame trigger (``START <hz> <width_us>``) or counts the D415
master's pulses (``LISTEN``), and reports ``PULSES <count> <t_us>`` periodically. Open it by
device path (``/dev/ttyACM0``, ``COM5``) or any ``serial.serial_for_url`` URL::

    with SyncBox("/dev/ttyACM0") as box:
        box.start(hz=30, width_us=100)
        ...
        total = box.stop()

Every failure is a :class:`~mocaprig.errors.DeviceError` naming the port, what is wrong and what
to do; the subclass says which kind (keeping pyserial's errno as ``backend_errno``): no such port
(:class:`~mocaprig.errors.DeviceNotFoundError`), permission denied
(:class:`~mocaprig.errors.DevicePermissionError`), port held by another program
(:class:`~mocaprig.errors.DeviceBusyError`), no answer in time
(:class:`~mocaprig.errors.DeviceTimeoutError`), I/O failed and could not be reopened
(:class:`~mocaprig.errors.DeviceDisconnectedError`). A ``serial.SerialException`` during I/O
(cable pulled, board reset) triggers a bounded reopen with exponential backoff; a run interrupted
that way is not restarted silently unless ``restart_after_reopen=True``.
"""

from __future__ import annotations

import contextlib
import enum
import errno
import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Final, Self

from mocaprig.acquire.mocks import load_mock_factory
from mocaprig.errors import (
    DeviceBusyError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceNotFoundError,
    DevicePermissionError,
    DeviceTimeoutError,
    ValidationError,
)
from mocaprig.timebase import U32Unwrapper
from mocaprig.validation import check_positive, check_range

__all__ = [
    "BANNER",
    "BAUDRATE",
    "PROTOCOL_VERSION",
    "PulseReport",
    "SyncBox",
    "SyncBoxError",
    "SyncBoxIdentity",
    "SyncBoxMode",
    "SyncBoxStatus",
    "find_syncboxes",
    "open_mock_syncbox",
]

_log = logging.getLogger(__name__)

PROTOCOL_VERSION: Final = 1
BANNER: Final = "MOCAPRIG-SYNCBOX"
BAUDRATE: Final = 115200
LINE_MAX: Final = 64
#: After the banner, how long the line must stay quiet before a command is sent: replies to
#: earlier ``HELLO``s (a second banner, ``ERR 1`` for one the bootloader garbled) come within
#: the box's 100 ms answer time and are dropped, not taken as the next command's reply.
SETTLE_S: Final = 0.15


class SyncBoxError(DeviceError):
    """The box answered ``ERR <code> <text>``; ``code`` and ``text`` keep its words."""

    def __init__(self, message: str, *, code: int, text: str) -> None:
        super().__init__(message)
        self.code = code
        self.text = text


class SyncBoxMode(enum.Enum):
    """What the box is doing (``STATUS`` reply)."""

    IDLE = "IDLE"
    GENERATE = "GENERATE"
    LISTEN = "LISTEN"


@dataclass(frozen=True, slots=True)
class SyncBoxIdentity:
    """The ``HELLO`` reply."""

    port: str
    version: int
    board: str
    features: tuple[str, ...] = ()
    """Feature tokens after the board (``"toggle"``: pin D10 flips at every pulse, for a
    Vicon analog input; docs/syncbox-protocol.md)."""


@dataclass(frozen=True, slots=True)
class SyncBoxStatus:
    """The ``STATUS`` reply."""

    mode: SyncBoxMode
    hz: int
    width_us: int
    count: int
    t_us: int
    """Box clock now (µs, u32 as sent)."""


@dataclass(frozen=True, slots=True)
class PulseReport:
    """One ``PULSES`` report."""

    count: int
    """Pulses since the run started (restarts at 0 after a reconnect)."""
    total: int
    """Pulses across reconnects of this :class:`SyncBox`."""
    t_us: int
    """Box clock at the last pulse's rising edge, unwrapped (µs)."""
    host_time_ns: int
    """Host monotonic clock when the line arrived."""


#: Each command's reply starts with this (else it is ``ERR <code> <text>``).
_EXPECTED: Final[dict[str, str]] = {
    "START": "OK START ",
    "LISTEN": "OK LISTEN",
    "STOP": "OK STOP ",
    "STATUS": "STATUS ",
    "REPORT": "OK REPORT ",
}


def _serial_module() -> Any:
    import serial  # pyserial is a core dependency; imported here to keep startup light

    return serial


class SyncBox:
    """One sync box on a serial port (a context manager).

    Args:
        port: device path or ``serial.serial_for_url`` URL.
        timeout_s: reply timeout per command.
        boot_timeout_s: how long to retry ``HELLO`` after opening (an Uno resets on open).
        max_reopen: reopen attempts after a ``SerialException`` (0 = none).
        backoff_s: first reopen delay; doubled per attempt.
        restart_after_reopen: re-send the active ``START``/``LISTEN`` after a reopen.
    """

    def __init__(
        self,
        port: str,
        *,
        timeout_s: float = 1.0,
        boot_timeout_s: float = 3.0,
        max_reopen: int = 3,
        backoff_s: float = 0.2,
        restart_after_reopen: bool = False,
    ) -> None:
        check_positive(timeout_s, name="timeout_s")
        check_positive(boot_timeout_s, name="boot_timeout_s")
        check_range(max_reopen, 0, 20, name="max_reopen")
        self.port = port
        self._timeout_s = float(timeout_s)
        self._boot_timeout_s = float(boot_timeout_s)
        self._max_reopen = int(max_reopen)
        self._backoff_s = float(backoff_s)
        self._restart = bool(restart_after_reopen)
        self._serial_mod = _serial_module()
        self._ser: Any = None
        self._buf = b""
        self._reports: deque[PulseReport] = deque(maxlen=10_000)
        self._run: tuple[str, ...] | None = None  # the active START/LISTEN command
        self._total_base = 0
        self._last_count = 0
        self._unwrap = U32Unwrapper()
        self.reconnects = 0
        self.identity: SyncBoxIdentity | None = None

    # -- lifecycle -------------------------------------------------------------------------

    def open(self) -> SyncBoxIdentity:
        """Open the port and identify the box (``HELLO``).

        Raises:
            DeviceNotFoundError: the port does not exist.
            DevicePermissionError: the user may not open the port.
            DeviceBusyError: another program holds the port.
            DeviceTimeoutError: no answer to ``HELLO`` within ``boot_timeout_s``.
            DeviceError: the device is not a sync box (or speaks another protocol version).
        """
        if self._ser is not None:
            msg = f"sync box on {self.port} is already open"
            raise DeviceError(msg)
        self._open_port()
        try:
            self.identity = self._identify()
        except BaseException:
            self._close_port()
            raise
        _log.info(
            "sync box on %s: protocol %d, board %s, features %s",
            self.port,
            self.identity.version,
            self.identity.board,
            " ".join(self.identity.features) or "none",
        )
        return self.identity

    def close(self) -> None:
        """Stop an active run (best effort) and close the port."""
        if self._ser is None:
            return
        try:
            if self._run is not None:
                self.stop()
        except DeviceError as err:
            _log.warning("sync box on %s: could not stop the run on close: %s", self.port, err)
        finally:
            self._close_port()

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _open_port(self) -> None:
        serial = self._serial_mod
        try:
            self._ser = serial.serial_for_url(
                self.port, baudrate=BAUDRATE, timeout=0.05, write_timeout=self._timeout_s
            )
        except (serial.SerialException, OSError, ValueError) as err:
            raise self._open_error(err) from err
        self._buf = b""

    def _open_error(self, err: BaseException) -> DeviceError:
        """The :class:`DeviceError` subclass for a failed open, keeping pyserial's errno."""
        code = getattr(err, "errno", None)
        text = str(err)
        if code == errno.EACCES or "Permission denied" in text:
            return DevicePermissionError.from_cause(
                f"sync box port {self.port}: permission denied; add yourself to the serial "
                "group (sudo usermod -aG dialout $USER; log out and in) or install a udev rule",
                err,
            )
        if code == errno.EBUSY or "busy" in text.lower():
            return DeviceBusyError.from_cause(
                f"sync box port {self.port} is busy; close the other program using it "
                "(serial monitor, ModemManager)",
                err,
            )
        # pyserial words every open failure "could not open port ...": only without an errno
        # (a URL handler's failure) does the text alone mean the port is missing.
        words = "No such file" in text or "could not open port" in text
        if code in (errno.ENOENT, errno.ENODEV, errno.ENXIO) or (code is None and words):
            seen = ", ".join(find_syncboxes()) or "none"
            return DeviceNotFoundError.from_cause(
                f"sync box port {self.port} does not exist (serial ports seen: {seen}); "
                "check the USB cable or pass the right --port",
                err,
            )
        return DeviceError.from_cause(f"cannot open sync box port {self.port}: {text}", err)

    def _close_port(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            with contextlib.suppress(OSError, self._serial_mod.SerialException):
                ser.close()

    # -- line I/O --------------------------------------------------------------------------

    def _write_line(self, line: str) -> None:
        if self._ser is None:
            msg = f"sync box on {self.port} is not open; use it as a context manager"
            raise DeviceError(msg)
        self._ser.write((line + "\n").encode("ascii"))
        self._ser.flush()

    def _read_line(self, deadline: float) -> str | None:
        """One line (without terminator), or ``None`` at the deadline."""
        while True:
            if b"\n" in self._buf:
                raw, self._buf = self._buf.split(b"\n", 1)
                line = raw.replace(b"\r", b"").decode("ascii", errors="replace").strip()
                if line:
                    return line
                continue
            if time.monotonic() >= deadline:
                return None
            if self._ser is None:
                msg = f"sync box on {self.port} is not open"
                raise DeviceError(msg)
            chunk = self._ser.read(max(1, self._ser.in_waiting or 1))
            if chunk:
                self._buf += chunk
                if len(self._buf) > 16 * LINE_MAX and b"\n" not in self._buf:
                    self._buf = b""  # a wrong device streaming binary; drop it

    def _file_report(self, line: str) -> bool:
        """If ``line`` is a ``PULSES`` report, store it and return ``True``."""
        parts = line.split()
        if len(parts) != 3 or parts[0] != "PULSES":
            return False
        try:
            count, t_us = int(parts[1]), int(parts[2])
        except ValueError:
            return False
        self._last_count = count
        self._reports.append(
            PulseReport(count, self._total_base + count, self._unwrap(t_us), time.monotonic_ns())
        )
        return True

    def _discard_stale(self) -> None:
        """Before a command: file the reports already received, drop every other whole line.

        Such a line cannot be the reply to the command about to be sent: a late banner, the
        late reply to a command that timed out. A partial line stays (its reply loop sees it).
        """
        if self._ser is None:
            msg = f"sync box on {self.port} is not open; use it as a context manager"
            raise DeviceError(msg)
        waiting = self._ser.in_waiting
        if waiting:
            self._buf += self._ser.read(waiting)
        while b"\n" in self._buf:
            raw, self._buf = self._buf.split(b"\n", 1)
            line = raw.replace(b"\r", b"").decode("ascii", errors="replace").strip()
            if line and not self._file_report(line):
                _log.info("sync box on %s: dropped the stale line %r", self.port, line)

    def _transact(self, line: str, expect: str) -> str:
        """Send one command and return its reply, the first line starting with ``expect``.

        ``PULSES`` lines on the way are filed; other lines (a late banner or reply) are dropped
        and named in the timeout message if the reply never comes.
        """
        self._discard_stale()
        self._write_line(line)
        deadline = time.monotonic() + self._timeout_s
        dropped: list[str] = []
        while True:
            reply = self._read_line(deadline)
            if reply is None:
                heard = ""
                if dropped:
                    heard = f" (it sent only {'; '.join(repr(d) for d in dropped[:3])})"
                msg = (
                    f"sync box on {self.port} did not answer {line.split()[0]} within "
                    f"{self._timeout_s:.1f} s{heard}; check the cable, or replug the box"
                )
                raise DeviceTimeoutError(msg)
            if self._file_report(reply):
                continue
            if not reply.startswith(("ERR ", expect)):
                _log.info(
                    "sync box on %s: dropped %r while waiting for the reply to %s",
                    self.port,
                    reply,
                    line.split()[0],
                )
                dropped.append(reply)
                continue
            if reply.startswith("ERR "):
                parts = reply.split(maxsplit=2)
                try:
                    code = int(parts[1])
                except (IndexError, ValueError):
                    code = -1
                text = parts[2] if len(parts) > 2 else ""
                msg = f"sync box on {self.port} refused {line!r}: ERR {code} {text}"
                raise SyncBoxError(msg, code=code, text=text)
            return reply

    def _with_reopen(self, fn: Callable[[], str], what: str) -> str:
        serial = self._serial_mod
        attempt = 0
        while True:
            try:
                return fn()
            except (serial.SerialException, OSError) as err:
                self._close_port()
                reopened = False
                while attempt < self._max_reopen and not reopened:
                    delay = self._backoff_s * (2**attempt)
                    attempt += 1
                    _log.warning(
                        "sync box on %s: %s; reopening in %.2f s (attempt %d/%d)",
                        self.port,
                        err,
                        delay,
                        attempt,
                        self._max_reopen,
                    )
                    time.sleep(delay)
                    try:
                        self._open_port()
                        self.identity = self._identify()
                        reopened = True
                    except DeviceError as reopen_err:
                        _log.warning("sync box on %s: reopen failed: %s", self.port, reopen_err)
                        self._close_port()
                if not reopened:
                    self._run = None
                    msg = (
                        f"sync box on {self.port}: I/O failed during {what} ({err}) and "
                        f"{attempt} reopen attempt(s) failed; check the USB cable and replug"
                    )
                    raise DeviceDisconnectedError.from_cause(msg, err) from err
                self.reconnects += 1
                self._after_reconnect(what)

    def _after_reconnect(self, what: str) -> None:
        if self._run is None:
            return
        self._total_base += self._last_count
        self._last_count = 0
        run = " ".join(self._run)
        if not self._restart:
            self._run = None
            msg = (
                f"sync box on {self.port} reconnected during {what}: the {run} run was "
                "interrupted (the board resets on reconnect) and is not restarted; pass "
                "restart_after_reopen=True to resume it automatically"
            )
            raise DeviceError(msg)
        _log.warning("sync box on %s: re-sending %s after the reconnect", self.port, run)
        self._transact(run, _EXPECTED[self._run[0]])

    def _command(self, line: str) -> str:
        """Send ``line`` (reopening the port if it fails) and return its reply."""
        cmd = line.split()[0]
        return self._with_reopen(lambda: self._transact(line, _EXPECTED[cmd]), cmd)

    def _identify(self) -> SyncBoxIdentity:
        """:meth:`_hello`, with an I/O failure on the way turned into a :class:`DeviceError`."""
        serial = self._serial_mod
        try:
            return self._hello()
        except (serial.SerialException, OSError) as err:
            if isinstance(err, serial.SerialTimeoutException):
                msg = (
                    f"sync box on {self.port} did not take HELLO within {self._timeout_s:.1f} s "
                    f"({err}); check the cable, or replug the box"
                )
                raise DeviceTimeoutError.from_cause(msg, err) from err
            msg = (
                f"sync box on {self.port}: I/O failed while identifying it ({err}); check the "
                "USB cable and replug"
            )
            raise DeviceDisconnectedError.from_cause(msg, err) from err

    def _hello(self) -> SyncBoxIdentity:
        """Send ``HELLO`` every 0.5 s until the banner arrives (the board may be booting).

        Bytes before the banner on its line (what a bootloader answered to an early ``HELLO``)
        are ignored. After the banner the line must stay quiet for :data:`SETTLE_S`: what comes
        meanwhile (the replies to the other ``HELLO``s sent while the board booted) is dropped,
        so that it is not taken as the reply to the next command.
        """
        deadline = time.monotonic() + self._boot_timeout_s
        others: list[str] = []
        self._discard_stale()
        while time.monotonic() < deadline:
            self._write_line("HELLO")
            step = min(deadline, time.monotonic() + 0.5)
            while True:
                line = self._read_line(step)
                if line is None:
                    break
                if self._file_report(line):
                    continue
                at = line.find(BANNER)
                if at >= 0:
                    banner = line[at:]
                    identity = self._identity(banner, banner.split())
                    self._settle()
                    return identity
                others.append(line)
        if others:
            heard = "; ".join(repr(o) for o in others[:3])
            msg = (
                f"the device on {self.port} is not a mocaprig sync box: it answered {heard} to "
                "HELLO; check the port (another board?) and flash firmware/syncbox/syncbox.ino"
            )
            raise DeviceError(msg)
        msg = (
            f"no answer to HELLO from {self.port} within {self._boot_timeout_s:.1f} s; is "
            "the sync box firmware flashed (firmware/syncbox/syncbox.ino) and the port right?"
        )
        raise DeviceTimeoutError(msg)

    def _settle(self) -> None:
        """Drop lines until none (but reports) came for :data:`SETTLE_S`; at most 1 s.

        Best effort: an I/O failure meanwhile (the box identified itself, then went away) is
        left to the next command, which reopens the port as any command does.
        """
        serial = self._serial_mod
        end = time.monotonic() + 1.0
        quiet_until = min(end, time.monotonic() + SETTLE_S)
        while True:
            try:
                line = self._read_line(quiet_until)
            except (serial.SerialException, OSError) as err:
                _log.debug("sync box on %s: I/O failed after the banner: %s", self.port, err)
                return
            if line is None:
                return
            if self._file_report(line):
                continue
            _log.info("sync box on %s: dropped %r after the banner", self.port, line)
            quiet_until = min(end, time.monotonic() + SETTLE_S)

    def _identity(self, line: str, parts: list[str]) -> SyncBoxIdentity:
        try:
            version = int(parts[1])
            board = parts[2]
        except (IndexError, ValueError) as err:
            msg = f"sync box on {self.port} sent a malformed banner {line!r}"
            raise DeviceError(msg) from err
        if version != PROTOCOL_VERSION:
            msg = (
                f"sync box on {self.port} speaks protocol version {version}; this mocaprig "
                f"speaks {PROTOCOL_VERSION}: reflash firmware/syncbox/syncbox.ino or update "
                "mocaprig"
            )
            raise DeviceError(msg)
        return SyncBoxIdentity(self.port, version, board, tuple(parts[3:]))

    # -- commands --------------------------------------------------------------------------

    def _expect(self, reply: str, prefix: str) -> list[str]:
        if not reply.startswith(prefix):
            msg = f"sync box on {self.port} answered {reply!r}, expected {prefix!r}…"
            raise DeviceError(msg)
        return reply.split()

    def start(self, *, hz: int, width_us: int = 100) -> None:
        """Generate ``hz`` pulses per second, each ``width_us`` µs wide (D415 slaves: ≥ 100).

        Raises:
            ValidationError: out-of-range values (checked before anything is sent).
            SyncBoxError: the box refused (e.g. ``ERR 3 busy``: call :meth:`stop` first).
        """
        check_range(hz, 1, 1000, name="hz")
        check_range(width_us, 10, 1e6 / hz / 2, name="width_us")
        if int(hz) != hz or int(width_us) != width_us:
            msg = f"hz and width_us must be integers, got {hz!r}, {width_us!r}"
            raise ValidationError(msg)
        line = f"START {int(hz)} {int(width_us)}"
        self._expect(self._command(line), _EXPECTED["START"])
        self._run = tuple(line.split())
        self._last_count = 0

    def listen(self) -> None:
        """Count rising edges on the IN pin (e.g. the D415 master's pulse)."""
        self._expect(self._command("LISTEN"), _EXPECTED["LISTEN"])
        self._run = ("LISTEN",)
        self._last_count = 0

    def stop(self) -> int:
        """End the run; return its pulse count."""
        parts = self._expect(self._command("STOP"), _EXPECTED["STOP"])
        self._run = None
        try:
            count = int(parts[2])
        except (IndexError, ValueError) as err:
            msg = f"sync box on {self.port} sent a malformed STOP reply {' '.join(parts)!r}"
            raise DeviceError(msg) from err
        self._last_count = count
        return count

    def status(self) -> SyncBoxStatus:
        """The ``STATUS`` reply."""
        parts = self._expect(self._command("STATUS"), _EXPECTED["STATUS"])
        try:
            return SyncBoxStatus(
                SyncBoxMode(parts[1]), int(parts[2]), int(parts[3]), int(parts[4]), int(parts[5])
            )
        except (IndexError, ValueError) as err:
            msg = f"sync box on {self.port} sent a malformed STATUS reply {' '.join(parts)!r}"
            raise DeviceError(msg) from err

    def set_report_interval(self, interval_ms: int) -> None:
        """Period of ``PULSES`` reports: 0 (off) or 100..60000 ms."""
        if interval_ms != 0:
            check_range(interval_ms, 100, 60_000, name="interval_ms")
        self._expect(self._command(f"REPORT {int(interval_ms)}"), _EXPECTED["REPORT"])

    def read_reports(self, timeout_s: float = 0.0) -> list[PulseReport]:
        """Read what the box sent within ``timeout_s``; return the reports filed so far."""

        def pump() -> str:
            deadline = time.monotonic() + max(0.0, timeout_s)
            while True:
                line = self._read_line(deadline)
                if line is None:
                    return ""
                if not self._file_report(line):
                    _log.debug("sync box on %s: unexpected line %r", self.port, line)

        self._with_reopen(pump, "reading reports")
        out = list(self._reports)
        self._reports.clear()
        return out

    @property
    def running(self) -> bool:
        """``True`` while a ``START``/``LISTEN`` run is active."""
        return self._run is not None


def find_syncboxes() -> list[str]:
    """Serial ports that may hold a sync box (USB CDC/UART bridges), for ``mocaprig devices``.

    Only lists ports (``serial.tools.list_ports``); opening one resets an Uno, so identification
    is left to :class:`SyncBox`.
    """
    from serial.tools import list_ports

    ports: list[str] = []
    for info in list_ports.comports():
        if info.vid is not None or "ACM" in info.device or "USB" in info.device:
            ports.append(str(info.device))
    return sorted(ports)


def open_mock_syncbox(**options: Any) -> Any:
    """Start the mock box registered as ``mocaprig.mocks: syncbox``; its ``port`` opens it.

    The caller closes it (it is a context manager).
    """
    return load_mock_factory("syncbox")(**options)
