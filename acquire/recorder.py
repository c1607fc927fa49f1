"""The session recorder: device streams into MCAP without ever blocking a device reader.

Usage::

    with Recorder(Path("session.mcap"), metadata={"rig": {"name": "lab-a"}}) as rec:
        events = rec.add_stream(topic("davis", serial, "events"), EventPacket)
        ...                                   # in the device reader thread:
        rec.put(events, EventPacket(ev, seq=n), log_time_ns=host_ns)   # never blocks

Design (``docs/recording-format.md`` §Recorder):

* One writer thread owns the :class:`mcap.writer.Writer` (it is not thread-safe). Device threads
  only call :meth:`Recorder.put`, which appends to the stream's bounded queue under a lock held
  for a few instructions and returns at once. A full queue (by message count or bytes) drops
  the message, counts it per stream, and returns ``False``.
* Encoding to protobuf happens in the writer thread.
* Chunks are closed by size (``chunk_size_bytes``) and by age (``max_chunk_age_s``, via
  ``Writer.flush()``), which bounds what a crash can lose (see :attr:`Recorder.crash_loss_bound`).
* A ``/diagnostics`` message (:class:`~acquire.recording_format.RecorderStatus`) with per-stream
  received/written/dropped counts is written every ``status_interval_s``; recorder events (a
  source died, a disk stop, a split) go to ``/log`` (``foxglove.Log``); the final counts go into
  the ``mocaprig.summary`` metadata record written just before the file is finished.
* Free disk is watched; below ``min_free_disk_bytes`` the recorder stops, finishes the file and
  :meth:`Recorder.__exit__` raises :class:`~mocaprig.errors.RecordingError` saying so. A write
  that fails with ``ENOSPC`` anyway (the probe lied, another program filled the disk) cuts the
  file back to its last flushed record and ends it there without an index (:meth:`_Part.salvage`):
  readable as it is, ``mocaprig recover`` rebuilds the index.
* Faults (a device lost and back, a full disk, a signal) are :class:`Fault` records on ``/faults``
  (``foxglove.Log``, declared at the first fault), each with its host time; see
  ``docs/recording-format.md`` §Faults.
* Optional splitting by size or duration into numbered files ``<stem>_000.mcap``, ... Each
  part is self-contained (schemas, channels, metadata and attachments repeated).

Memory bound: ``sum(queue_bytes of every stream) + ~3 × (chunk_size_bytes + largest message)``
(open chunk, its compressed copy, the message being encoded) plus the writer's chunk index,
about 100 B + 10 B per channel per chunk for the life of one file (split files to bound it).

Library code never installs signal handlers; the CLI uses :func:`stop_on_signals`, whose handler
only notes the signal (no lock is taken in a handler); the writer thread records it and stops.
"""

from __future__ import annotations

import collections
import contextlib
import enum
import errno
import logging
import os
import shutil
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any, BinaryIO, Final, Literal, Protocol, Self, cast, get_args

from mcap.data_stream import RecordBuilder
from mcap.records import Channel, DataEnd, Footer, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from mocaprig import __version__
from mocaprig.acquire.recording_format import (
    FORMAT_VERSION,
    PROFILE,
    LogLevel,
    LogMsg,
    RecordedPayload,
    RecorderStatus,
    SchemaDef,
    StreamStatus,
)
from mocaprig.errors import RecordingError, ValidationError

__all__ = [
    "DIAGNOSTICS_TOPIC",
    "FAULTS_TOPIC",
    "LOG_TOPIC",
    "RECORDER_TOPICS",
    "Attachment",
    "Compression",
    "Fault",
    "FaultKind",
    "Recorder",
    "StopReason",
    "StreamHandle",
    "StreamSource",
    "Tap",
    "record_sources",
    "split_path",
    "stop_on_signals",
]

_log = logging.getLogger(__name__)

DIAGNOSTICS_TOPIC: Final = "/diagnostics"
LOG_TOPIC: Final = "/log"
FAULTS_TOPIC: Final = "/faults"
#: The recorder's own topics (every other topic is a device's data).
RECORDER_TOPICS: Final = frozenset({DIAGNOSTICS_TOPIC, LOG_TOPIC, FAULTS_TOPIC})
_MCAP_MAGIC: Final = b"\x89MCAP0\r\n"

Compression = Literal["zstd", "lz4", "none"]
#: The live hook, ``(topic, payload, encoded bytes, log_time_ns)``: called by the writer thread
#: after each message it has written; it must return at once (``acquire/live_view.py``).
Tap = Callable[[str, RecordedPayload, bytes, int], None]
_COMPRESSION: Final = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}


class StopReason(enum.Enum):
    """Why a recording ended."""

    REQUESTED = "requested"  # stop() or leaving the with-block
    DISK_FULL = "disk-full"  # free disk fell below the margin
    WRITE_ERROR = "write-error"  # the file could not be written
    SIGNAL = "signal"  # SIGINT / SIGTERM through stop_on_signals()


FaultKind = Literal[
    "disconnected", "reconnected", "source-died", "disk-full", "write-error", "signal"
]
_FAULT_KINDS: Final[frozenset[str]] = frozenset(get_args(FaultKind))
#: The kinds that lose a device's data (its streams have a gap until ``reconnected``).
_LOST_KINDS: Final[frozenset[str]] = frozenset(("disconnected", "source-died"))
#: Log level of each fault kind on ``/faults`` (a device back is good news: INFO).
_FAULT_LEVEL: Final[dict[str, LogLevel]] = {
    "disconnected": "ERROR",
    "reconnected": "INFO",
    "source-died": "ERROR",
    "disk-full": "FATAL",
    "write-error": "FATAL",
    "signal": "WARNING",
}


@dataclass(frozen=True, slots=True)
class Fault:
    """One fault (or recovery) during a recording, as written on ``/faults``.

    Attributes:
        kind: What happened: a device ``disconnected`` (an error or silence), ``reconnected``
            (re-opened, recording again), its source ``source-died`` (an error no re-open can
            fix), the disk is full (``disk-full``), the file could not be written
            (``write-error``), a ``signal`` stopped the recording.
        device: The device label (``davis/<serial>``, ``d415/<serial>``, ``syncbox``) or
            ``recorder``.
        t_ns: Host time it happened (the recorder's clock, ns); also the message's log_time.
        detail: One line for a person: the error, how long the device was gone...
    """

    kind: FaultKind
    device: str
    t_ns: int
    detail: str

    @property
    def lost(self) -> bool:
        """Whether this fault lost a device's data (``disconnected`` or ``source-died``)."""
        return self.kind in _LOST_KINDS

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: ``kind``, ``device``, ``t_ns``, ``detail``."""
        return {"kind": self.kind, "device": self.device, "t_ns": self.t_ns, "detail": self.detail}

    def to_log(self) -> LogMsg:
        """The ``foxglove.Log`` message: ``name`` = device, ``message`` = ``"<kind>: <detail>"``."""
        return LogMsg(
            _FAULT_LEVEL[self.kind], f"{self.kind}: {self.detail}", self.device, self.t_ns
        )

    @classmethod
    def from_log(cls, msg: LogMsg) -> Fault | None:
        """The fault a ``/faults`` message holds, or None when it is not one (another writer)."""
        kind, sep, detail = msg.message.partition(": ")
        if not sep or kind not in _FAULT_KINDS:
            return None
        return cls(cast(FaultKind, kind), msg.name, msg.timestamp_ns, detail)


@dataclass(frozen=True, slots=True)
class Attachment:
    """A file stored in the recording (rig file, calibration), written at the start."""

    name: str
    media_type: str
    data: bytes = field(repr=False)


@dataclass(frozen=True, slots=True)
class StreamHandle:
    """What :meth:`Recorder.add_stream` returns and :meth:`Recorder.put` takes."""

    topic: str
    schema: SchemaDef = field(repr=False)
    index: int


class _Stream:
    """Mutable per-stream state; every field is guarded by the recorder's lock."""

    __slots__ = (
        "bytes_written",
        "dropped",
        "handle",
        "max_bytes",
        "max_messages",
        "metadata",
        "queue",
        "queued_bytes",
        "received",
        "written",
    )

    def __init__(
        self, handle: StreamHandle, metadata: dict[str, str], max_messages: int, max_bytes: int
    ) -> None:
        self.handle = handle
        self.metadata = metadata
        self.max_messages = max_messages
        self.max_bytes = max_bytes
        self.queue: collections.deque[tuple[int, int, RecordedPayload, int]] = collections.deque()
        self.queued_bytes = 0
        self.received = 0
        self.written = 0
        self.dropped = 0
        self.bytes_written = 0


def split_path(path: Path, index: int) -> Path:
    """The name of part ``index`` of a split recording: ``session.mcap`` → ``session_003.mcap``."""
    return path.with_name(f"{path.stem}_{index:03d}{path.suffix}")


class Recorder:
    """Record device streams into one MCAP file (or numbered parts); a context manager.

    Args:
        path: Output file; must not exist (the recorder never overwrites).
        compression: Chunk compression. ``lz4`` (default) keeps up with several D415 streams on
            two cores; ``zstd`` (level 3) manages ~120 MB/s; ``none`` is disk-bound.
        chunk_size_bytes: Close a chunk once it holds this many uncompressed bytes.
        max_chunk_age_s: Close the open chunk at the latest this long after its first message
            (bounds crash loss in time).
        queue_messages: Default per-stream queue capacity (messages).
        queue_bytes: Default per-stream queue capacity (bytes of queued payloads).
        min_free_disk_bytes: Stop cleanly when the disk holding ``path`` has less free space.
        split_bytes: Start a new numbered part once a part reaches this size (None: never).
        split_seconds: Start a new part after this many seconds (None: never).
        status_interval_s: Period of the ``/diagnostics`` status messages.
        fsync: ``os.fsync`` after every chunk flush (survives power loss; costs throughput).
        metadata: MCAP metadata records (name → string map) written at the start of every part:
            rig, device serials, firmware, biases, exposure... ``mocaprig`` is reserved.
        attachments: Files (rig description, calibration) written at the start of every part.
        clock_ns: Host clock for default ``log_time`` (ns); ``time.time_ns`` by default.
        disk_free_bytes: Free-space probe ``(directory) -> bytes`` (tests inject a fake).
        open_file: Opens an output file ``(path, mode) -> binary file`` with mode ``"xb"``
            (a new part) or ``"r+b"`` (cutting a part back after ``ENOSPC``); the fault
            injection of the mocks wraps it. Default: :meth:`pathlib.Path.open`.
        tap: Called by the writer thread with each message once it is written (the live view,
            :class:`mocaprig.acquire.live_view.LiveView`); it must not block. An exception from
            it is logged and the tap is dropped: it never costs the recording a message.
    """

    def __init__(
        self,
        path: Path,
        *,
        compression: Compression = "lz4",
        chunk_size_bytes: int = 1 << 20,
        max_chunk_age_s: float = 0.5,
        queue_messages: int = 4096,
        queue_bytes: int = 64 << 20,
        min_free_disk_bytes: int = 512 << 20,
        split_bytes: int | None = None,
        split_seconds: float | None = None,
        status_interval_s: float = 1.0,
        fsync: bool = False,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        attachments: Sequence[Attachment] = (),
        clock_ns: Callable[[], int] = time.time_ns,
        disk_free_bytes: Callable[[Path], int] | None = None,
        open_file: Callable[[Path, str], BinaryIO] | None = None,
        tap: Tap | None = None,
    ) -> None:
        if compression not in _COMPRESSION:
            msg = f"compression must be one of {sorted(_COMPRESSION)}, got {compression!r}"
            raise ValidationError(msg)
        for name, value in (
            ("chunk_size_bytes", chunk_size_bytes),
            ("max_chunk_age_s", max_chunk_age_s),
            ("queue_messages", queue_messages),
            ("queue_bytes", queue_bytes),
            ("status_interval_s", status_interval_s),
        ):
            if not value > 0:
                msg = f"{name} must be > 0, got {value!r}"
                raise ValidationError(msg)
        if metadata and "mocaprig" in metadata:
            msg = "metadata name 'mocaprig' is reserved for the recorder; use another name"
            raise ValidationError(msg)
        self.path = Path(path)
        self._split = split_bytes is not None or split_seconds is not None
        first = split_path(self.path, 0) if self._split else self.path
        if first.exists():
            msg = f"{first} exists already; not overwriting a recording (choose another --out)"
            raise RecordingError(msg)
        if not self.path.parent.is_dir():
            msg = f"cannot record to {self.path}: folder {self.path.parent} does not exist"
            raise RecordingError(msg)
        self.compression: Compression = compression
        self.chunk_size_bytes = chunk_size_bytes
        self.max_chunk_age_s = max_chunk_age_s
        self.queue_messages = queue_messages
        self.queue_bytes = queue_bytes
        self.min_free_disk_bytes = min_free_disk_bytes
        self.split_bytes = split_bytes
        self.split_seconds = split_seconds
        self.status_interval_s = status_interval_s
        self.fsync = fsync
        self._metadata = {k: dict(v) for k, v in (metadata or {}).items()}
        self._attachments = list(attachments)
        self._clock_ns = clock_ns
        self._disk_free = disk_free_bytes or (lambda p: shutil.disk_usage(p).free)
        self._open_file: Callable[[Path, str], BinaryIO] = open_file or (
            lambda p, mode: cast(BinaryIO, p.open(mode))
        )

        self._tap = tap
        self._lock = threading.Lock()
        self._room = threading.Condition(self._lock)  # put_wait() waits here for queue room
        self._waiting = 0
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._streams: list[_Stream] = []
        self._thread: threading.Thread | None = None
        self._started_ns = 0
        self._started_mono = 0.0
        self._stop_reason: StopReason | None = None
        self._error: BaseException | None = None
        self._files: list[Path] = []
        self._free_bytes = 0
        self._probe_pos = 0
        self._bytes_done = 0  # bytes of finished parts
        self._file_bytes = 0
        self._peak_queued_bytes = 0
        self._finished = False
        self._faults: list[Fault] = []
        self._faults_stream: StreamHandle | None = None
        self._fault_lock = threading.Lock()
        self._signal: tuple[int, int] | None = None  # (signum, host ns), set by a handler
        self._salvaged: bool | None = None  # after ENOSPC: whether the file's ending fitted
        self._diag = self.add_stream(DIAGNOSTICS_TOPIC, RecorderStatus, queue_messages=64)
        self._logs = self.add_stream(LOG_TOPIC, LogMsg, queue_messages=1024)

    # ---------------------------------------------------------------------------- lifecycle

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
        if exc is None:
            self.raise_if_failed()

    def start(self) -> None:
        """Open the first file and start the writer thread.

        Raises:
            RecordingError: already started, or the file cannot be created.
        """
        if self._thread is not None:
            msg = f"recorder for {self.path} is already started; use one Recorder per session"
            raise RecordingError(msg)
        self._started_ns = self._clock_ns()
        self._started_mono = time.monotonic()
        self._free_bytes = self._probe_disk()
        if self._free_bytes < self.min_free_disk_bytes:
            msg = (
                f"cannot record to {self.path}: only {self._free_bytes / 1e6:.0f} MB free, below "
                f"the {self.min_free_disk_bytes / 1e6:.0f} MB margin; free disk space or lower "
                "min_free_disk_bytes"
            )
            raise RecordingError(msg)
        part = self._open_part(0)  # raises here, in the caller, when the file cannot be made
        self._thread = threading.Thread(
            target=self._run, args=(part,), name="mocaprig-recorder", daemon=True
        )
        self._thread.start()

    def stop(self) -> None:
        """Ask the writer to drain the queues and finish the file (returns at once)."""
        with self._lock:
            if self._stop_reason is None:
                self._stop_reason = StopReason.REQUESTED
        self._stop.set()
        self._wake.set()
        with self._lock:
            self._room.notify_all()

    def close(self) -> None:
        """Stop, drain the queues, finish the file and join the writer thread (idempotent)."""
        self.stop()
        if self._thread is not None:
            self._thread.join()

    def raise_if_failed(self) -> None:
        """Raise if the recording ended early (disk full, write error); the file is valid.

        Raises:
            RecordingError: naming the file, the cause and what to do.
        """
        if self._stop_reason is StopReason.DISK_FULL and self._salvaged is not None:
            state = (
                "the file ends at its last complete record, without an index: readable as it "
                "is; `mocaprig recover` on another disk rebuilds the index"
                if self._salvaged
                else "there was no room for its ending: the file stops at its last complete "
                "record; read it as it is or run `mocaprig recover` on another disk"
            )
            msg = (
                f"recording {self.current_path} stopped early: the disk is full (a write failed "
                f"with ENOSPC: {self._error}); {state}; free space before recording again"
            )
            raise RecordingError(msg) from self._error
        if self._stop_reason is StopReason.DISK_FULL:
            msg = (
                f"recording {self.current_path} stopped early: free disk fell to "
                f"{self._free_bytes / 1e6:.0f} MB (margin {self.min_free_disk_bytes / 1e6:.0f} "
                "MB); the file is finished and readable; free space before recording again"
            )
            raise RecordingError(msg)
        if self._error is not None:
            msg = (
                f"recording {self.current_path} failed: {self._error}; whatever reached the disk "
                f"is readable, run `mocaprig recover {self.current_path} FIXED.mcap` if needed"
            )
            raise RecordingError(msg) from self._error

    # ---------------------------------------------------------------------------- streams

    def add_stream(
        self,
        topic: str,
        message_type: type[RecordedPayload] | SchemaDef,
        *,
        metadata: Mapping[str, str] | None = None,
        queue_messages: int | None = None,
        queue_bytes: int | None = None,
    ) -> StreamHandle:
        """Declare a stream (an MCAP channel); thread-safe, allowed before or while recording.

        Args:
            topic: MCAP topic (see :func:`mocaprig.acquire.recording_format.topic`).
            message_type: A payload class of :mod:`acquire.recording_format` (or its schema).
            metadata: Channel metadata (device serial, stream settings), strings only.
            queue_messages: Queue capacity in messages (default: the recorder's).
            queue_bytes: Queue capacity in bytes (default: the recorder's).

        Raises:
            ValidationError: the topic is already declared.
        """
        schema = message_type if isinstance(message_type, SchemaDef) else message_type.SCHEMA
        with self._lock:
            if any(s.handle.topic == topic for s in self._streams):
                msg = f"stream {topic!r} is declared twice; each topic has one stream"
                raise ValidationError(msg)
            handle = StreamHandle(topic, schema, len(self._streams))
            self._streams.append(
                _Stream(
                    handle,
                    {str(k): str(v) for k, v in (metadata or {}).items()},
                    queue_messages or self.queue_messages,
                    queue_bytes or self.queue_bytes,
                )
            )
        return handle

    def put(
        self,
        stream: StreamHandle,
        message: RecordedPayload,
        *,
        log_time_ns: int | None = None,
        sequence: int = 0,
    ) -> bool:
        """Queue one message; never blocks. Returns ``False`` when it was dropped (and counted).

        Args:
            stream: From :meth:`add_stream`.
            message: The payload (encoded later, in the writer thread; do not mutate it).
            log_time_ns: Host receive time, ns (default: the recorder's clock now).
            sequence: Device counter for this message (MCAP ``sequence``, kept modulo 2**32;
                the payload keeps the full counter).
        """
        t = self._clock_ns() if log_time_ns is None else log_time_ns
        n = message.nbytes
        s = self._streams[stream.index]
        with self._lock:
            s.received += 1
            if (
                self._stop.is_set()
                or len(s.queue) >= s.max_messages
                or s.queued_bytes + n > s.max_bytes
            ):
                s.dropped += 1
                return False
            s.queue.append((t, sequence & 0xFFFFFFFF, message, n))
            s.queued_bytes += n
        self._wake.set()
        return True

    def put_wait(
        self,
        stream: StreamHandle,
        message: RecordedPayload,
        *,
        log_time_ns: int | None = None,
        sequence: int = 0,
    ) -> bool:
        """Queue one message, **waiting** while the stream's queue is full (back-pressure).

        Only for offline sources (a simulated device paced "as fast as possible", a file being
        imported): they can wait, a live device reader must not (use :meth:`put`). Returns
        ``False`` (and counts a drop) only when the recorder stops while waiting or before.
        Arguments as :meth:`put`.
        """
        t = self._clock_ns() if log_time_ns is None else log_time_ns
        n = message.nbytes
        s = self._streams[stream.index]
        with self._lock:
            s.received += 1
            while not self._stop.is_set() and (
                len(s.queue) >= s.max_messages or (s.queue and s.queued_bytes + n > s.max_bytes)
            ):
                self._waiting += 1
                try:
                    self._wake.set()
                    self._room.wait(0.1)
                finally:
                    self._waiting -= 1
            if self._stop.is_set():
                s.dropped += 1
                return False
            s.queue.append((t, sequence & 0xFFFFFFFF, message, n))
            s.queued_bytes += n
        self._wake.set()
        return True

    def log(self, level: LogLevel, message: str, *, name: str = "recorder") -> None:
        """Write a recorder event to ``/log`` (and the Python log); never blocks."""
        _log.log(getattr(logging, "CRITICAL" if level == "FATAL" else level), "%s", message)
        now = self._clock_ns()
        self.put(self._logs, LogMsg(level, message, name, now), log_time_ns=now)

    def fault(self, kind: FaultKind, device: str, detail: str, *, t_ns: int | None = None) -> Fault:
        """Record a fault (or a recovery) on ``/faults`` and in the Python log; never blocks.

        Args:
            kind: See :class:`Fault`.
            device: The device label, or ``recorder``.
            detail: One line for a person.
            t_ns: When it happened (host ns; default: now).
        """
        f = self._note_fault(kind, device, detail, t_ns=t_ns)
        self.put(self._faults_handle(), f.to_log(), log_time_ns=f.t_ns)
        return f

    def _note_fault(
        self, kind: FaultKind, device: str, detail: str, *, t_ns: int | None = None
    ) -> Fault:
        """Keep a fault for :attr:`faults` and the Python log (not yet for the file)."""
        f = Fault(kind, device, self._clock_ns() if t_ns is None else t_ns, detail)
        with self._lock:
            self._faults.append(f)
        level = _FAULT_LEVEL[kind]
        _log.log(getattr(logging, "CRITICAL" if level == "FATAL" else level), "%s: %s: %s",
                 device, kind, detail)  # fmt: skip
        return f

    def _faults_handle(self) -> StreamHandle:
        """The ``/faults`` stream, declared at the first fault (a file without faults has none)."""
        with self._fault_lock:
            if self._faults_stream is None:
                self._faults_stream = self.add_stream(FAULTS_TOPIC, LogMsg, queue_messages=1024)
            return self._faults_stream

    @property
    def faults(self) -> tuple[Fault, ...]:
        """Every fault recorded so far (also those a full disk kept out of the file)."""
        with self._lock:
            return tuple(self._faults)

    def stop_for_signal(self, signum: int) -> None:
        """Stop because of signal ``signum``; safe in a signal handler (takes no lock: the
        writer thread records a ``signal`` fault and stops within ~0.1 s)."""
        if self._signal is None:
            self._signal = (signum, self._clock_ns())

    # ---------------------------------------------------------------------------- state

    def clock_ns(self) -> int:
        """The recorder's host clock now (ns): the clock of default ``log_time`` values."""
        return self._clock_ns()

    @property
    def signal_name(self) -> str | None:
        """The signal that stopped the recording (``"SIGTERM"``...), or None."""
        if self._signal is None or self._stop_reason is not StopReason.SIGNAL:
            return None
        signum = self._signal[0]
        return signal.Signals(signum).name if signum in signal.valid_signals() else str(signum)

    @property
    def stopped(self) -> threading.Event:
        """Set once the recorder stops accepting messages (stop(), disk full, write error)."""
        return self._stop

    @property
    def stop_reason(self) -> StopReason | None:
        """Why the recording ended (``None`` while running)."""
        return self._stop_reason

    @property
    def files(self) -> tuple[Path, ...]:
        """The files written so far (one unless split)."""
        return tuple(self._files)

    @property
    def current_path(self) -> Path:
        """The part being written (or the last one)."""
        return self._files[-1] if self._files else self.path

    @property
    def crash_loss_bound_s(self) -> float:
        """Upper bound on the host time of data a SIGKILL can lose: the open chunk's age limit
        plus one writer wake-up period (queued messages not yet written are lost too)."""
        return self.max_chunk_age_s + min(self.max_chunk_age_s, 0.1)

    @property
    def memory_bound_bytes(self) -> int:
        """Upper bound on the recorder's buffers (queues + chunk builder), see the module doc."""
        with self._lock:
            queues = sum(s.max_bytes for s in self._streams)
        return queues + 3 * self.chunk_size_bytes

    @property
    def peak_queued_bytes(self) -> int:
        """Largest total of queued bytes seen by the writer thread."""
        return self._peak_queued_bytes

    def status(self) -> RecorderStatus:
        """A snapshot of the counters (thread-safe)."""
        with self._lock:
            streams = tuple(
                StreamStatus(
                    s.handle.topic,
                    s.received,
                    s.written,
                    s.dropped,
                    len(s.queue),
                    s.bytes_written,
                )
                for s in self._streams
            )
        elapsed = self._clock_ns() - self._started_ns if self._started_ns else 0
        return RecorderStatus(
            max(elapsed, 0),
            self._free_bytes,
            self._bytes_done + self._file_bytes,
            max(len(self._files) - 1, 0),
            streams,
        )

    # ---------------------------------------------------------------------------- writer

    def _probe_disk(self) -> int:
        try:
            return int(self._disk_free(self.path.parent))
        except OSError as err:
            _log.warning("cannot read free space of %s: %s", self.path.parent, err)
            return 2**63 - 1

    def _open_part(self, index: int) -> _Part:
        path = split_path(self.path, index) if self._split else self.path
        try:
            f = self._open_file(path, "xb")
        except FileExistsError as err:
            msg = f"{path} exists already; not overwriting a recording (choose another --out)"
            raise RecordingError(msg) from err
        except OSError as err:
            msg = f"cannot create recording {path}: {err}"
            raise RecordingError(msg) from err
        self._files.append(path)
        part = _Part(path, f, self, index)
        part.begin(self._metadata, self._attachments)
        return part

    def _run(self, part: _Part) -> None:
        last_status = time.monotonic()
        last_disk = 0.0
        try:
            while True:
                self._take_signal()
                stopping = self._stop.is_set()
                self._wake.wait(timeout=min(self.max_chunk_age_s, 0.1))
                self._wake.clear()
                self._drain(part)
                now = time.monotonic()
                if part.chunk_age(now) >= self.max_chunk_age_s:
                    part.flush()
                if now - last_disk >= 0.1:
                    last_disk = now
                    self._probe(part)
                    self._check_disk(part, 0)
                if now - last_status >= self.status_interval_s or stopping:
                    last_status = now
                    self._write_status(part)
                if stopping and self._queues_empty():
                    self._drain(part)
                    break
                if self._should_split(part, now):
                    part = self._next_part(part)
            part.finish(self._summary_metadata(part))
        except BaseException as err:  # a writer failure must never pass silently
            if _is_disk_full(err):
                self._disk_full(part, err)
                return
            _log.exception("recorder writer failed on %s", part.path)
            f = self._note_fault("write-error", "recorder", f"{err!r} while writing {part.path}")
            fs = self._streams[self._faults_handle().index]
            data = f.to_log().encode()
            written = False
            with contextlib.suppress(Exception):  # into the file if it still takes it
                part.write(fs, f.t_ns, fs.written, data)
                written = True
            with self._lock:
                self._error = err
                if self._stop_reason in (None, StopReason.REQUESTED):
                    self._stop_reason = StopReason.WRITE_ERROR
                # Nothing more is written: what is still queued is counted dropped, and the
                # fault itself as written or dropped (it is in ``faults`` either way).
                for s in self._streams:
                    s.dropped += len(s.queue)
                    s.queue.clear()
                    s.queued_bytes = 0
                fs.received += 1
                if written:
                    fs.written += 1
                    fs.bytes_written += len(data)
                else:
                    fs.dropped += 1
                self._room.notify_all()
            self._stop.set()
            with contextlib.suppress(Exception):
                part.finish(self._summary_metadata(part))
            with contextlib.suppress(Exception):
                part.file.close()

    def _take_signal(self) -> None:
        """Record a signal noted by :meth:`stop_for_signal` (here, not in the handler) and stop."""
        sig = self._signal
        if sig is None:
            return
        with self._lock:
            if self._stop_reason is not None:
                return
            self._stop_reason = StopReason.SIGNAL
        name = self.signal_name
        self.fault("signal", "recorder", f"{name}: stopping and finishing the file", t_ns=sig[1])
        self.stop()

    def _disk_full(self, part: _Part, err: BaseException) -> None:
        """A write failed with ENOSPC: cut the part back to its last flushed record and end it
        there with the fault and the summary (when they fit)."""
        f = self._note_fault(
            "disk-full",
            "recorder",
            f"no space left on the disk of {part.path} ({err}); the file ends here",
        )
        fs = self._streams[self._faults_handle().index]
        data = f.to_log().encode()
        with self._lock:
            self._error = err
            self._stop_reason = StopReason.DISK_FULL
            self._stop.set()
            # Whatever is still queued cannot be written any more: count it dropped.
            for s in self._streams:
                s.dropped += len(s.queue)
                s.queue.clear()
                s.queued_bytes = 0
            fs.received += 1  # the fault goes into the file's ending, if that fits
            fs.written += 1
            fs.bytes_written += len(data)
            if not part.finished:
                # The cut back to the last whole record loses what was written since.
                for s in self._streams:
                    n, b = part.pending.get(s.handle.index, (0, 0))
                    s.written -= n
                    s.dropped += n
                    s.bytes_written -= b
            self._room.notify_all()
        if part.finished:  # the next part could not be made: this one is complete
            self._salvaged = True
            return
        self._salvaged = part.salvage([(fs, f.t_ns, data)], self._summary_metadata(part))
        _log.error(
            "%s: disk full; %s", part.path,
            "file ended at its last complete record" if self._salvaged
            else "no room for the ending: the file stops at its last complete record",
        )  # fmt: skip

    def _probe(self, part: _Part) -> None:
        self._free_bytes = self._probe_disk()
        self._probe_pos = self._bytes_done + part.tell()

    def _check_disk(self, part: _Part, incoming: int) -> bool:
        """Stop (DISK_FULL) when writing ``incoming`` more bytes, plus the open chunk, would
        leave less than the margin; estimated from the last probe and the bytes written since.
        Returns True when the recorder is (now) stopped for a full disk."""
        if self._stop_reason is StopReason.DISK_FULL:
            return True
        written = self._bytes_done + part.tell() - self._probe_pos
        free = self._free_bytes - written - self.chunk_size_bytes - incoming
        if free >= self.min_free_disk_bytes:
            return False
        with self._lock:
            self._stop_reason = StopReason.DISK_FULL
        msg = (
            f"free disk (about {max(free, 0) / 1e6:.0f} MB after the open chunk) fell below "
            f"the margin {self.min_free_disk_bytes / 1e6:.0f} MB; stopping the recording, "
            "queued messages are dropped"
        )
        self.log("ERROR", msg)
        self._stop.set()
        return True

    def _queues_empty(self) -> bool:
        with self._lock:
            return all(not s.queue for s in self._streams)

    def _write_status(self, part: _Part) -> None:
        # Written directly (not queued) so the last status gets in after stop().
        s = self._streams[self._diag.index]
        data = self.status().encode()
        part.write(s, self._clock_ns(), s.written & 0xFFFFFFFF, data)
        with self._lock:
            s.received += 1
            s.written += 1
            s.bytes_written += len(data)

    def _drain(self, part: _Part) -> None:
        with self._lock:
            streams = list(self._streams)
            queued = sum(s.queued_bytes for s in streams)
        self._peak_queued_bytes = max(self._peak_queued_bytes, queued)
        if part.n_channels < len(streams):
            # Every declared stream gets its channel, so a stream that never delivered (a dead
            # source) still shows up, with 0 messages, in the summary.
            for s in streams:
                part.channel(s)
        for s in streams:
            while True:
                with self._lock:
                    if not s.queue:
                        break
                    log_time, seq, message, n = s.queue.popleft()
                    if self._waiting:
                        self._room.notify_all()
                disk_full = self._stop_reason is StopReason.DISK_FULL
                if disk_full and not self._kept_on_full_disk(s):
                    with self._lock:  # no room left: drop what is still queued
                        s.queued_bytes -= n
                        s.dropped += 1
                    continue
                try:
                    data = message.encode()
                except Exception as err:
                    with self._lock:
                        s.queued_bytes -= n
                        s.dropped += 1
                    self.log("ERROR", f"cannot encode a message for {s.handle.topic}: {err}")
                    continue
                if not disk_full and self._check_disk(part, len(data)):
                    with self._lock:
                        s.queued_bytes -= n
                        s.dropped += 1
                    continue
                try:
                    part.write(s, log_time, seq, data)
                except BaseException:
                    with self._lock:  # the message in hand is lost with the write: count it
                        s.queued_bytes -= n
                        s.dropped += 1
                    raise
                with self._lock:
                    s.queued_bytes -= n
                    s.written += 1
                    s.bytes_written += len(data)
                tap = self._tap
                if tap is not None:
                    self._call_tap(tap, s.handle.topic, message, data, log_time)
        self._file_bytes = part.tell()

    def _kept_on_full_disk(self, s: _Stream) -> bool:
        """Whether ``s`` is still written once the disk is full (``/log`` and ``/faults``)."""
        fs = self._faults_stream
        return s.handle.index == self._logs.index or (fs is not None and s.handle.index == fs.index)

    def _call_tap(
        self, tap: Tap, topic: str, message: RecordedPayload, data: bytes, log_time: int
    ) -> None:
        """Hand a written message to the tap; a failing tap is dropped, the recording goes on."""
        try:
            tap(topic, message, data, log_time)
        except Exception as err:
            self._tap = None
            _log.exception("the live tap failed on %s; recording goes on without it", topic)
            self.log("WARNING", f"live view stopped: {err!r} on {topic}; recording goes on")

    def _should_split(self, part: _Part, now: float) -> bool:
        if self.split_bytes is not None and part.tell() >= self.split_bytes:
            return True
        return self.split_seconds is not None and now - part.opened_mono >= self.split_seconds

    def _next_part(self, part: _Part) -> _Part:
        part.finish(self._summary_metadata(part))
        self._bytes_done += part.tell()
        self._file_bytes = 0
        nxt = self._open_part(part.index + 1)
        self.log("INFO", f"split: continuing in {nxt.path.name} after {part.path.name}")
        return nxt

    def _summary_metadata(self, part: _Part) -> dict[str, str]:
        with self._lock:
            out = {
                "format_version": FORMAT_VERSION,
                "stop_reason": (self._stop_reason or StopReason.REQUESTED).value,
                "file_index": str(part.index),
                "ended_ns": str(self._clock_ns()),
            }
            for s in self._streams:
                t = s.handle.topic
                out[f"received:{t}"] = str(s.received)
                out[f"written:{t}"] = str(s.written)
                out[f"dropped:{t}"] = str(s.dropped)
            out["faults"] = str(len(self._faults))
        if self._error is not None:
            out["error"] = str(self._error)
        return out


def _is_disk_full(err: BaseException | None) -> bool:
    """``ENOSPC`` (or ``EDQUOT``, a quota: the same for the recording), also as a cause."""
    while err is not None:
        if isinstance(err, OSError) and err.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        err = err.__cause__
    return False


class _Part:
    """One output file and its mcap Writer; used only by the writer thread (after begin())."""

    def __init__(self, path: Path, f: BinaryIO, rec: Recorder, index: int) -> None:
        self.path = path
        self.file = f
        self.rec = rec
        self.index = index
        self.opened_mono = time.monotonic()
        self.writer = Writer(
            f,
            chunk_size=rec.chunk_size_bytes,
            compression=_COMPRESSION[rec.compression],
        )
        self._schemas: dict[str, int] = {}
        self._channels: dict[int, int] = {}
        self._chunk_since: float | None = None
        self._final_size = 0
        self.durable = 0  # file offset up to which every record reached the OS (a boundary)
        self.finished = False
        # Messages (count, bytes) per stream index written since the last record the OS took
        # whole (:attr:`durable`): what a cut back to it would lose.
        self.pending: dict[int, tuple[int, int]] = {}

    def begin(
        self, metadata: Mapping[str, Mapping[str, str]], attachments: Sequence[Attachment]
    ) -> None:
        rec = self.rec
        self.writer.start(profile=PROFILE, library=f"mocaprig {__version__}")
        self.writer.add_metadata(
            "mocaprig",
            {
                "format_version": FORMAT_VERSION,
                "software_version": __version__,
                "started_ns": str(rec._started_ns),
                "file_index": str(self.index),
                "split": "true" if rec._split else "false",
                "compression": rec.compression,
                "chunk_size_bytes": str(rec.chunk_size_bytes),
                "max_chunk_age_s": str(rec.max_chunk_age_s),
            },
        )
        for name, values in metadata.items():
            self.writer.add_metadata(name, dict(values))
        now = rec._clock_ns()
        for a in attachments:
            self.writer.add_attachment(
                create_time=now, log_time=now, name=a.name, media_type=a.media_type, data=a.data
            )
        self.file.flush()
        self.durable = self.file.tell()

    def channel(self, s: _Stream) -> int:
        """The channel id of ``s`` in this part (registered on first use)."""
        cid = self._channels.get(s.handle.index)
        if cid is None:
            sch = s.handle.schema
            sid = self._schemas.get(sch.name)
            if sid is None:
                sid = self.writer.register_schema(sch.name, sch.encoding, sch.data)
                self._schemas[sch.name] = sid
            cid = self.writer.register_channel(s.handle.topic, "protobuf", sid, s.metadata)
            self._channels[s.handle.index] = cid
        return cid

    @property
    def n_channels(self) -> int:
        return len(self._channels)

    def write(self, s: _Stream, log_time: int, seq: int, data: bytes) -> None:
        cid = self.channel(s)
        self.writer.add_message(
            channel_id=cid, log_time=log_time, publish_time=log_time, data=data, sequence=seq
        )
        pos = self.file.tell()
        if pos != self.durable:
            # The message closed a chunk (by size): push it to the OS, a boundary to cut back to.
            self.file.flush()
            self.durable = pos
            self.pending.clear()
        else:
            n, b = self.pending.get(s.handle.index, (0, 0))
            self.pending[s.handle.index] = (n + 1, b + len(data))
        if self._chunk_since is None:
            self._chunk_since = time.monotonic()

    def chunk_age(self, now: float) -> float:
        return 0.0 if self._chunk_since is None else now - self._chunk_since

    def flush(self) -> None:
        self.writer.flush()  # type: ignore[no-untyped-call]
        if self.rec.fsync:
            os.fsync(self.file.fileno())
        self.durable = self.file.tell()
        self.pending.clear()
        self._chunk_since = None

    def tell(self) -> int:
        return self._final_size if self.file.closed else self.file.tell()

    def salvage(
        self, messages: Sequence[tuple[_Stream, int, bytes]], summary: Mapping[str, str]
    ) -> bool:
        """After a failed write (ENOSPC): cut the file back to :attr:`durable` (the last record
        the OS took whole), then end it with ``messages``, the summary record, DataEnd and a
        Footer without a summary section: a complete MCAP file without an index. Returns
        False when that ending does not fit either (the file then ends at :attr:`durable`).
        """
        with contextlib.suppress(OSError):
            self.file.close()  # its buffer cannot be written; the raw file closes anyway
        tail = RecordBuilder()
        for s, log_time, data in messages:
            sch = s.handle.schema
            cid = self._channels.get(s.handle.index)
            sid = self._schemas.get(sch.name)
            # Ids the writer would not have used: a channel declared only in the lost chunk
            # is declared again here (identical records may repeat in MCAP).
            sid = sid if sid is not None else max(self._schemas.values(), default=0) + 1
            cid = cid if cid is not None else max(self._channels.values(), default=-1) + 1
            Schema(id=sid, name=sch.name, encoding=sch.encoding, data=sch.data).write(tail)
            Channel(
                id=cid,
                topic=s.handle.topic,
                message_encoding="protobuf",
                metadata=dict(s.metadata),
                schema_id=sid,
            ).write(tail)
            Message(
                channel_id=cid, log_time=log_time, data=data, publish_time=log_time, sequence=0
            ).write(tail)
        Metadata(name="mocaprig.summary", metadata=dict(summary)).write(tail)
        DataEnd(data_section_crc=0).write(tail)
        Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(tail)
        ending = bytes(tail.end()) + _MCAP_MAGIC  # type: ignore[no-untyped-call]
        try:
            with self.rec._open_file(self.path, "r+b") as f:
                f.truncate(self.durable)
                f.seek(self.durable)
                try:
                    f.write(ending)
                    f.flush()
                except OSError:
                    f.truncate(self.durable)
                    return False
                finally:
                    self._final_size = f.seek(0, os.SEEK_END)
                if self.rec.fsync:
                    os.fsync(f.fileno())
        except OSError as err:
            _log.error("%s: cannot cut the file back after a full disk: %s", self.path, err)
            return False
        return True

    def finish(self, summary: Mapping[str, str]) -> None:
        self.writer.flush()  # type: ignore[no-untyped-call]
        self.writer.add_metadata("mocaprig.summary", dict(summary))
        self.writer.finish()  # type: ignore[no-untyped-call]
        self.file.flush()
        self._final_size = self.file.tell()
        if self.rec.fsync:
            os.fsync(self.file.fileno())
        self.file.close()
        self.finished = True


# -------------------------------------------------------------------------------------------
# Sources and the CLI's helpers


class StreamSource(Protocol):
    """A device (or simulated device) feeding a recorder; what ``mocaprig record`` runs.

    ``declare`` adds the source's streams (and may return metadata records to add); ``run`` reads
    the device until ``stop`` is set or the device ends, calling :meth:`Recorder.put` only.
    An exception from ``run`` is logged into the file; the other sources keep recording.
    """

    name: str

    def declare(self, recorder: Recorder) -> None:
        """Add this source's streams to ``recorder``."""
        ...

    def run(self, recorder: Recorder, stop: threading.Event) -> None:
        """Read the device and put messages until ``stop`` is set or the device ends."""
        ...


def record_sources(
    recorder: Recorder,
    sources: Sequence[StreamSource],
    *,
    seconds: float | None,
    on_status: Callable[[RecorderStatus], None] | None = None,
    status_period_s: float = 0.5,
    join_timeout_s: float = 5.0,
    followers: Sequence[StreamSource] = (),
) -> tuple[str, ...]:
    """Run ``sources`` (one thread each) into a started ``recorder`` for ``seconds`` (or until
    the recorder stops or every source ends); then stop the sources and return.

    ``followers`` run alongside (one thread each) but never end a recording by themselves:
    they are stopped once every one of ``sources`` has ended (e.g. a sync box that listens to
    simulated cameras for as long as those deliver). With ``seconds=None`` the recording lasts
    until every source ends (offline sources: the end of a simulated session).

    A source that raises is logged into the file's ``/log`` (level ERROR) and the others go on.
    Returns the names of the sources whose thread did not end within ``join_timeout_s`` (a hung
    device call); their devices must not be closed from another thread.
    """
    stop = threading.Event()
    threads: list[threading.Thread] = []

    def runner(src: StreamSource) -> None:
        try:
            src.run(recorder, stop)
        except Exception as err:
            recorder.log("ERROR", f"source {src.name} died: {err!r}", name=src.name)
            recorder.fault("source-died", src.name, f"{err!r}; its streams end here")
        else:
            if not stop.is_set():
                recorder.log("INFO", f"source {src.name} ended", name=src.name)

    everyone = [*sources, *followers]
    for src in everyone:
        src.declare(recorder)
    for src in everyone:
        th = threading.Thread(target=runner, args=(src,), name=f"source-{src.name}", daemon=True)
        th.start()
        threads.append(th)
    leading = threads[: len(sources)]
    t0 = time.monotonic()
    try:
        while True:
            if recorder.stopped.wait(status_period_s):
                break
            if on_status is not None:
                on_status(recorder.status())
            if seconds is not None and time.monotonic() - t0 >= seconds:
                break
            if not any(th.is_alive() for th in leading):
                break
    finally:
        stop.set()
        deadline = time.monotonic() + join_timeout_s
        for th in threads:
            th.join(timeout=max(deadline - time.monotonic(), 0.0))
    hung = tuple(src.name for src, th in zip(everyone, threads, strict=True) if th.is_alive())
    for name in hung:
        recorder.log("WARNING", f"source {name} did not stop within {join_timeout_s} s", name=name)
    return hung


@contextlib.contextmanager
def stop_on_signals(
    recorder: Recorder, signals: Sequence[int] = (signal.SIGINT, signal.SIGTERM)
) -> Iterator[None]:
    """For CLIs only (main thread): SIGINT/SIGTERM stop ``recorder`` cleanly (a ``signal``
    fault in the file, stop reason ``signal``); handlers restored on exit. The library itself
    never installs handlers."""
    previous: dict[int, Any] = {}

    def handler(signum: int, frame: FrameType | None) -> None:
        # Nothing that takes a lock here (logging, Event.set): the main thread may hold it.
        recorder.stop_for_signal(signum)

    for sig in signals:
        previous[sig] = signal.signal(sig, handler)
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
