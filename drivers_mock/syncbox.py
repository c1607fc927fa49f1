"""Mock sync box: a pseudo-terminal speaking the sync box line protocol (docs/syncbox-protocol.md).

:func:`mock_syncbox` (entry point ``mocaprig.mocks: syncbox``) opens a pty pair and serves the
box's side from a background thread; :attr:`MockSyncBox.port` is the slave path, which
``serial.Serial(port)`` or ``serial.serial_for_url(port)`` opens like a USB CDC port.

Behaviour (protocol version 1, ``<board>`` = ``mock``, feature ``toggle``):

* lines of at most 64 characters, host ``\\n``-terminated, ``\\r`` and empty lines ignored; the box
  ends its lines with ``\\r\\n``; every command gets exactly one reply line (``ERR <code> <text>``
  for unknown commands, bad arguments, ``busy`` runs and over-long lines);
* ``START <hz> <width_us>`` generates pulses on the box's own clock from the command on (count
  reset; the first pulse one period after the command, as the firmware's timer), ``LISTEN``
  counts an external pulse train (``listen_hz``, default 30 Hz: the D415 master's frame pulse;
  ``None`` = nothing wired, the count stays 0; or ``pulse_source``, e.g. a realtime mock D415
  master's ``pulse_at_or_after``),
  ``STOP`` replies with the run's count, ``STATUS`` with mode, rate, width, count and the box
  clock, ``REPORT <ms>`` sets the period of the unsolicited ``PULSES <count> <t_us>`` reports
  (default 1000 ms; sent only during a run, never between ``OK STOP`` and the next run);
* the box clock is µs, u32 (wraps every 2³² µs), with a seeded offset and a drift of ±20 ppm
  against the host's monotonic clock (``clock`` overrides it); ``PULSES``' ``t_us`` is the box
  time of the last counted pulse's rising edge (the report time when the count is 0);
* the DTR auto-reset of an Uno/Nano is not emulated: the box answers ``HELLO`` at once (set
  ``boot_delay_s`` to discard input for that long and then print the banner once, as a booting
  board does).

Faults (``fault=``): ``"no-reply"`` — after ``fault_after_commands`` replies (default 1, so the
``HELLO`` handshake works) the box stays silent (no replies, no reports: the host's reply timeout
fires); ``"disconnect"`` — after that many replies the box closes its side of the pty (the host
sees a hang-up, ``serial.SerialException``, and the port path disappears).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import select
import threading
import time
import tty
from collections.abc import Callable
from types import TracebackType
from typing import Final, Literal, Self, get_args

import numpy as np

from mocaprig.drivers_mock.clock import DeviceClock
from mocaprig.drivers_mock.scenario import stream_rng
from mocaprig.errors import DeviceError, ValidationError

__all__ = [
    "LINE_MAX",
    "PROTOCOL_VERSION",
    "SYNCBOX_FAULTS",
    "MockSyncBox",
    "SyncBoxFault",
    "mock_syncbox",
]

_log = logging.getLogger(__name__)

PROTOCOL_VERSION: Final = 1
#: Longest line (characters before the terminator) the box accepts.
LINE_MAX: Final = 64
_U32: Final = 1 << 32

SyncBoxFault = Literal["no-reply", "disconnect"]
#: Fault names accepted by :func:`mock_syncbox`.
SYNCBOX_FAULTS: Final[tuple[str, ...]] = get_args(SyncBoxFault)

Mode = Literal["IDLE", "GENERATE", "LISTEN"]


class MockSyncBox:
    """A simulated sync box behind a pseudo-terminal (module doc).

    Args:
        seed: Seeds the box clock and the listened pulse train's phase.
        fault: ``None``, ``"no-reply"`` or ``"disconnect"``.
        fault_after_commands: Replies sent before the fault strikes.
        board: The ``<board>`` token of the banner.
        listen_hz: Rate of the external pulse train in ``LISTEN`` mode (``None``: none wired).
        boot_delay_s: Input is discarded for this long after creation, then the banner is
            printed once (0: no boot, no unsolicited banner).
        clock: The box clock (µs ticks); default a seeded one.
        pulse_source: The wired pulse train for ``LISTEN``: ``f(t_ns)`` = the first rising edge
            at or after session time ``t_ns``, or ``None`` (e.g. a mock D415 master's
            ``pulse_at_or_after`` with ``pacing="realtime"``); replaces ``listen_hz``.
        session_t0_ns: The ``time.monotonic_ns()`` reading that is session time 0 (default: the
            box's creation; pass the D415 rig's start to share its timeline).
        session_clock_ns: The session time now (ns), replacing the host's monotonic clock:
            e.g. an asap-paced mock D415 rig's ``now_ns`` (its simulated time), so that the box
            counts the pulses of a simulated session however fast it is simulated.

    Raises:
        ValidationError: unknown fault or bad option.
        DeviceError: no pseudo-terminal could be opened.
    """

    def __init__(
        self,
        *,
        seed: int = 0,
        fault: SyncBoxFault | None = None,
        fault_after_commands: int = 1,
        board: str = "mock",
        listen_hz: float | None = 30.0,
        boot_delay_s: float = 0.0,
        clock: DeviceClock | None = None,
        pulse_source: Callable[[int], int | None] | None = None,
        session_t0_ns: int | None = None,
        session_clock_ns: Callable[[], int] | None = None,
    ) -> None:
        if fault is not None and fault not in SYNCBOX_FAULTS:
            msg = f"unknown sync box fault {fault!r}; choose one of {list(SYNCBOX_FAULTS)}"
            raise ValidationError(msg)
        if fault_after_commands < 0 or boot_delay_s < 0:
            msg = "fault_after_commands and boot_delay_s must be >= 0"
            raise ValidationError(msg)
        if listen_hz is not None and not (0 < listen_hz <= 1000):
            msg = f"listen_hz must lie in (0, 1000] or be None, got {listen_hz!r}"
            raise ValidationError(msg)
        if not board or " " in board:
            msg = f"board must be one token, got {board!r}"
            raise ValidationError(msg)
        rng = stream_rng(seed, "syncbox")
        self.clock = clock or DeviceClock(
            "syncbox",
            offset_ns=int(rng.uniform(1.0, 600.0) * 1e9),
            drift_ppm=float(rng.uniform(-20.0, 20.0)),
            jitter_ns=0.0,
            unit_ns=1000,
            seed=int(rng.integers(0, 2**62)),
        )
        self._listen_phase_ns = int(rng.integers(0, 33_000_000))
        self.fault: SyncBoxFault | None = fault
        self.fault_after_commands = int(fault_after_commands)
        self.board = board
        self.listen_hz = listen_hz
        self.pulse_source = pulse_source
        # (next edge or None when the train ended, count, last counted edge)
        self._listen_cache: tuple[int | None, int, int | None] | None = None
        now_mono = time.monotonic_ns()
        self._t0_ns = now_mono if session_t0_ns is None else int(session_t0_ns)
        self._session_clock = session_clock_ns
        self._boot_until_ns = now_mono + round(boot_delay_s * 1e9)
        self._booted = boot_delay_s == 0
        try:
            self._master, self._slave = os.openpty()
        except OSError as err:
            msg = f"cannot open a pseudo-terminal for the mock sync box: {err}"
            raise DeviceError(msg) from err
        # Raw, no echo: whatever the box writes must not bounce back as input.
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port: str = os.ttyname(self._slave)
        self._mode: Mode = "IDLE"
        self._hz = 0
        self._width_us = 0
        self._run_start_ns = 0
        self._report_ms = 1000
        self._next_report_ns: int | None = None
        self._replies = 0
        self._silent = False
        self._buf = bytearray()
        self._overflow = False
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._closed = False
        #: Every line received (decoded), for tests.
        self.received: list[str] = []
        self._thread = threading.Thread(target=self._serve, name="mock-syncbox", daemon=True)
        self._thread.start()
        _log.debug("mock sync box on %s", self.port)

    # -- lifecycle -----------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the thread and close the pty (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._close_fds()

    def _close_fds(self) -> None:
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = -1

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    @property
    def mode(self) -> Mode:
        """``"IDLE"``, ``"GENERATE"`` or ``"LISTEN"``."""
        return self._mode

    # -- clocks and pulses ------------------------------------------------------------------------

    def _session_ns(self) -> int:
        if self._session_clock is not None:
            return int(self._session_clock())
        return time.monotonic_ns() - self._t0_ns

    def _box_us(self, session_ns: int) -> int:
        return int(self.clock.device_ticks(np.array([session_ns], np.int64))[0])

    def _pulses(self, now_ns: int) -> tuple[int, int | None]:
        """(count, box µs of the last counted pulse) of the current run at session ``now_ns``."""
        if self._mode == "GENERATE" and self._hz > 0:
            # The box's own timer, as the firmware's Timer1: it starts at 0 with the output low
            # and the first pulse rises one period (on the box clock) after the START.
            t0 = self._box_us(self._run_start_ns)
            now = self._box_us(now_ns)
            period_us = 1e6 / self._hz
            n = int((now - t0) // period_us)
            return (n, t0 + round(n * period_us)) if n > 0 else (0, None)
        if self._mode == "LISTEN" and self.pulse_source is not None:
            return self._count_source(now_ns)
        if self._mode == "LISTEN" and self.listen_hz is not None:
            period_ns = 1e9 / self.listen_hz
            first = self._run_start_ns + self._listen_phase_ns % round(period_ns)
            if now_ns < first:
                return 0, None
            n = int((now_ns - first) // period_ns) + 1
            return n, self._box_us(first + round((n - 1) * period_ns))
        return 0, None

    def _count_source(self, now_ns: int) -> tuple[int, int | None]:
        """Edges of ``pulse_source`` since the run started, counted incrementally."""
        source = self.pulse_source
        if source is None:
            return 0, None
        if self._listen_cache is None:
            self._listen_cache = (source(self._run_start_ns), 0, None)
        nxt, count, last = self._listen_cache
        while nxt is not None and nxt <= now_ns:
            count, last = count + 1, nxt
            nxt = source(nxt + 1)
        self._listen_cache = (nxt, count, last)
        return count, None if last is None else self._box_us(last)

    # -- I/O --------------------------------------------------------------------------------------

    def _write(self, line: str) -> None:
        if self._silent or self._master < 0:
            return
        data = (line + "\r\n").encode("ascii")
        try:
            os.write(self._master, data)
        except BlockingIOError:
            _log.warning("mock sync box: the host does not read; dropped %r", line)
        except OSError as err:
            _log.debug("mock sync box: write failed (%s)", err)

    def _serve(self) -> None:
        try:
            while not self._stop.is_set():
                now = self._session_ns()
                if not self._booted and time.monotonic_ns() >= self._boot_until_ns:
                    self._booted = True
                    self._write(self._banner())
                timeout = 0.05
                with self._lock:
                    if self._next_report_ns is not None:
                        timeout = min(timeout, max(0.0, (self._next_report_ns - now) * 1e-9))
                try:
                    ready, _, _ = select.select([self._master], [], [], timeout)
                except (OSError, ValueError):
                    return
                if ready:
                    try:
                        data = os.read(self._master, 4096)
                    except BlockingIOError:
                        data = b""
                    except OSError as err:
                        if err.errno == errno.EIO:  # no host has the port open right now
                            time.sleep(0.01)
                            continue
                        return
                    self._feed(data)
                self._maybe_report()
        finally:
            _log.debug("mock sync box thread ends")

    def _feed(self, data: bytes) -> None:
        for byte in data:
            if byte == 0x0A:  # \n ends a line
                line = self._buf.decode("ascii", errors="replace")
                overflow = self._overflow
                self._buf.clear()
                self._overflow = False
                if not self._booted:
                    continue  # a booting board hears nothing
                if overflow:
                    self._reply("ERR 4 line too long")
                elif line:
                    self.received.append(line)
                    self._reply(self._handle(line))
                if self._master < 0:
                    return
            elif byte == 0x0D or self._overflow:
                continue
            else:
                self._buf.append(byte)
                if len(self._buf) > LINE_MAX:
                    self._overflow = True
                    self._buf.clear()

    def _reply(self, line: str) -> None:
        if self._silent:
            return
        self._write(line)
        self._replies += 1
        if self.fault is not None and self._replies >= self.fault_after_commands:
            if self.fault == "no-reply":
                _log.info("mock sync box: injected fault, no more replies")
                self._silent = True
            else:
                _log.info("mock sync box: injected fault, disconnecting")
                self._silent = True
                time.sleep(0.05)  # let the host read the last reply first
                self._close_fds()
                self._stop.set()

    def _maybe_report(self) -> None:
        with self._lock:
            due = self._next_report_ns
            if due is None or self._mode == "IDLE" or self._report_ms == 0:
                return
            now = self._session_ns()
            if now < due:
                return
            count, t_us = self._pulses(now)
            if t_us is None:
                t_us = self._box_us(now)
            step = self._report_ms * 1_000_000
            self._next_report_ns = due + step * max(1, (now - due) // step + 1)
        self._write(f"PULSES {count % _U32} {t_us % _U32}")

    # -- commands ---------------------------------------------------------------------------------

    def _banner(self) -> str:
        return f"MOCAPRIG-SYNCBOX {PROTOCOL_VERSION} {self.board} toggle"

    def _handle(self, line: str) -> str:
        tokens = line.split(" ")
        cmd, args = tokens[0], tokens[1:]
        if any(not t for t in tokens):
            return "ERR 2 bad argument" if cmd in _COMMANDS else "ERR 1 unknown command"
        if cmd not in _COMMANDS:
            return "ERR 1 unknown command"
        nums = [int(a) if a.isdigit() and a.isascii() else None for a in args]
        with self._lock:
            now = self._session_ns()
            if cmd == "HELLO":
                return self._banner() if not args else "ERR 2 bad argument"
            if cmd == "STATUS":
                if args:
                    return "ERR 2 bad argument"
                count, _ = self._pulses(now)
                return (
                    f"STATUS {self._mode} {self._hz} {self._width_us} {count % _U32} "
                    f"{self._box_us(now) % _U32}"
                )
            if cmd == "STOP":
                if args:
                    return "ERR 2 bad argument"
                count, _ = self._pulses(now)
                self._mode, self._hz, self._width_us = "IDLE", 0, 0
                self._next_report_ns = None
                return f"OK STOP {count % _U32}"
            if cmd == "REPORT":
                if len(nums) != 1 or nums[0] is None:
                    return "ERR 2 bad argument"
                ms = nums[0]
                if ms != 0 and not (100 <= ms <= 60_000):
                    return "ERR 2 bad argument"
                self._report_ms = ms
                if self._mode != "IDLE":
                    self._next_report_ns = None if ms == 0 else now + ms * 1_000_000
                return f"OK REPORT {ms}"
            if self._mode != "IDLE":
                return "ERR 3 busy"
            if cmd == "LISTEN":
                if args:
                    return "ERR 2 bad argument"
                self._begin("LISTEN", 0, 0, now)
                return "OK LISTEN"
            # START <hz> <width_us>
            if len(nums) != 2 or nums[0] is None or nums[1] is None:
                return "ERR 2 bad argument"
            hz, width = nums[0], nums[1]
            if not (1 <= hz <= 1000) or not (10 <= width <= 1e6 / hz / 2):
                return "ERR 2 bad argument"
            self._begin("GENERATE", hz, width, now)
            return f"OK START {hz} {width}"

    def _begin(self, mode: Mode, hz: int, width_us: int, now_ns: int) -> None:
        self._mode, self._hz, self._width_us = mode, hz, width_us
        self._run_start_ns = now_ns
        self._listen_cache = None
        self._next_report_ns = None if self._report_ms == 0 else now_ns + self._report_ms * 10**6


_COMMANDS: Final = frozenset({"HELLO", "START", "LISTEN", "STOP", "STATUS", "REPORT"})


def mock_syncbox(
    *,
    seed: int = 0,
    fault: SyncBoxFault | None = None,
    fault_after_commands: int = 1,
    listen_hz: float | None = 30.0,
    boot_delay_s: float = 0.0,
    board: str = "mock",
    pulse_source: Callable[[int], int | None] | None = None,
    session_t0_ns: int | None = None,
    session_clock_ns: Callable[[], int] | None = None,
) -> MockSyncBox:
    """A running mock sync box (entry point ``mocaprig.mocks: syncbox``); close it when done.

    Args:
        seed: Seeds the box clock.
        fault: ``None``, ``"no-reply"`` or ``"disconnect"`` (module doc).
        fault_after_commands: Replies sent before the fault strikes.
        listen_hz: External pulse rate seen in ``LISTEN`` mode (``None``: nothing wired).
        boot_delay_s: Emulated boot time (module doc).
        board: The banner's board token.
        pulse_source: The pulse train ``LISTEN`` counts (replaces ``listen_hz``; class doc).
        session_t0_ns: ``time.monotonic_ns()`` of session time 0 for ``pulse_source``.
        session_clock_ns: The session time now (ns) instead of the monotonic clock (class doc).

    Returns:
        The box; ``.port`` is the path to open with pyserial.
    """
    return MockSyncBox(
        seed=seed,
        fault=fault,
        fault_after_commands=fault_after_commands,
        board=board,
        listen_hz=listen_hz,
        boot_delay_s=boot_delay_s,
        pulse_source=pulse_source,
        session_t0_ns=session_t0_ns,
        session_clock_ns=session_clock_ns,
    )
