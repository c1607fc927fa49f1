"""Reading recordings: the only way calib/ and process/ read MCAP sessions.

Usage::

    with Recording(Path("session.mcap")) as rec:
        ev = rec.events("/davis/00000042/events", start_ns=t0, end_ns=t1)   # EVENT_DTYPE
        ev, t_ns = rec.events_ns("/davis/imported/events")   # + exact times as stored (ns)
        for log_time_ns, img in rec.images("/d415/1234/depth"):             # ImageMsg
            ...
    summary = info(Path("session.mcap"))       # topics, counts, rates, drops, gaps, chunks
    recover(Path("crashed.mcap"), Path("fixed.mcap"))

Files with a summary are read through their index (only the chunks that overlap the query).
Files without one (a crash, a kill -9, a full disk) are scanned linearly: every complete chunk is
read; a truncated or corrupt chunk is skipped and reported in :attr:`Recording.scan`.
Time ranges are on ``log_time`` (host receive ns): ``start_ns`` inclusive, ``end_ns`` exclusive.
"""

from __future__ import annotations

import io
import logging
import struct
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, Any, BinaryIO, Final, Literal, Self, cast

import lz4.frame
import numpy as np
import numpy.typing as npt
import zstandard
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Attachment as McapAttachment
from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from mocaprig.acquire.events import EVENT_DTYPE
from mocaprig.acquire.recorder import FAULTS_TOPIC, RECORDER_TOPICS, Fault
from mocaprig.acquire.recording_format import (
    FORMAT_VERSION,
    IMU_DTYPE,
    SPECIAL_DTYPE,
    EventPacket,
    ImageMsg,
    ImuPacket,
    LogMsg,
    RecorderStatus,
    TriggerPacket,
    decode_payload,
)
from mocaprig.errors import RecordingError

__all__ = [
    "UNIX_EPOCH_MIN_NS",
    "ChannelInfo",
    "DeviceGap",
    "RecordedAttachment",
    "RecordedMessage",
    "Recording",
    "RecordingInfo",
    "RecoverReport",
    "ScanReport",
    "StreamInfo",
    "TimeBase",
    "TimeBaseName",
    "info",
    "recover",
]

_log = logging.getLogger(__name__)

_MAGIC: Final = b"\x89MCAP0\r\n"
#: What reading a malformed MCAP file raises besides McapError: struct.error on a short field,
#: KeyError on a message of an undeclared channel, UnicodeDecodeError (a ValueError) on a bad
#: string, OverflowError on a huge count; ZstdError and RuntimeError (lz4) on a corrupt chunk.
_MCAP_ERRORS: Final = (
    McapError, ValueError, EOFError, struct.error, KeyError, IndexError, OverflowError,
    zstandard.ZstdError, RuntimeError,
)  # fmt: skip
#: A chunk may declare this many uncompressed bytes whatever its compressed size (our recorder
#: writes 1 MiB chunks; one large image makes a bigger one); beyond, at most _MAX_CHUNK_RATIO
#: times its compressed size. The decompressor allocates what the chunk declares.
_MAX_CHUNK_BYTES: Final = 64 << 20
_MAX_CHUNK_RATIO: Final = 1024


class _BoundedFile:
    """A binary file whose reads never ask for more than what is left of it.

    The mcap reader passes lengths read from the file to ``read``, and a buffered read allocates
    the size asked for before reading: a corrupt length would allocate gigabytes.
    """

    def __init__(self, f: BinaryIO, size: int) -> None:
        self._f = f
        self._size = size

    def read(self, n: int | None = -1) -> bytes:
        if n is None or n < 0:
            return self._f.read()
        return self._f.read(max(0, min(n, self._size - self._f.tell())))

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._f.seek(offset, whence)

    def tell(self) -> int:
        return self._f.tell()

    def seekable(self) -> bool:
        return True


def _chunk_problem(compression: str, uncompressed_size: int, data: bytes, data_size: int) -> str:
    """What is wrong with a chunk's declared sizes ("" when nothing): checked before the
    decompressor allocates ``uncompressed_size`` (or the size its frame header declares).

    ``data`` holds at least the start of the compressed bytes (the frame header); ``data_size``
    is their full length.
    """
    if compression not in ("", "zstd", "lz4"):
        return f"unknown compression {compression!r}"
    if not compression:
        if uncompressed_size != data_size:
            return f"uncompressed chunk of {data_size} bytes declares {uncompressed_size}"
        return ""
    if uncompressed_size > max(_MAX_CHUNK_BYTES, _MAX_CHUNK_RATIO * data_size):
        return f"{data_size} compressed bytes declare {uncompressed_size} uncompressed bytes"
    try:
        if compression == "zstd":
            declared = zstandard.frame_content_size(data)
        else:
            declared = int(lz4.frame.get_frame_info(data)["content_size"]) or -1
    except (zstandard.ZstdError, RuntimeError, ValueError) as err:
        return f"not a {compression} frame ({err})"
    if declared >= 0 and declared != uncompressed_size:
        return f"its {compression} frame declares {declared} bytes, the chunk {uncompressed_size}"
    return ""


@dataclass(frozen=True, slots=True)
class ChannelInfo:
    """One channel: topic, schema name and the channel's metadata (device serial...)."""

    topic: str
    schema_name: str
    metadata: Mapping[str, str]


@dataclass(frozen=True, slots=True)
class RecordedMessage:
    """One message as stored; :meth:`decode` gives the typed payload."""

    topic: str
    schema_name: str
    log_time_ns: int
    sequence: int
    data: bytes = field(repr=False)
    #: the recording it came from (named in errors)
    source: str = ""

    def decode(self) -> Any:
        """The payload as a :mod:`mocaprig.acquire.recording_format` message object.

        Raises:
            RecordingError: an unknown schema or a corrupt payload (naming the file, topic and
                time).
        """
        try:
            return decode_payload(self.schema_name, self.data)
        except RecordingError as err:
            where = f"{self.source}: " if self.source else ""
            msg = f"{where}the {self.topic} message at {self.log_time_ns} ns: {err}"
            raise RecordingError(msg) from err


@dataclass(frozen=True, slots=True)
class RecordedAttachment:
    """A file stored in the recording."""

    name: str
    media_type: str
    log_time_ns: int
    data: bytes = field(repr=False)


@dataclass(frozen=True, slots=True)
class ScanReport:
    """What a linear scan found. ``indexed`` files are not scanned (all zeros, ``ok``)."""

    complete_chunks: int
    bad_chunks: int
    truncated: bool
    bytes_unread: int
    error: str | None = None

    @property
    def ok(self) -> bool:
        """True when every byte was read and every chunk was intact."""
        return not (self.truncated or self.bad_chunks or self.error)


class _LinearScan:
    """Linear scan of an MCAP file that tolerates a missing summary and a truncated tail."""

    def __init__(self, path: Path, progress: Callable[[int, int], None] | None = None) -> None:
        self.path = path
        self.progress = progress  # (bytes scanned, file size), after each top-level record
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.report = ScanReport(0, 0, False, 0)

    def records(self) -> Iterator[Message | Metadata | McapAttachment]:
        """Yield messages, metadata and attachments in file order; updates ``report``."""
        size = self.path.stat().st_size
        complete = bad = 0
        good_end = 0
        error: str | None = None
        in_summary = False
        with self.path.open("rb") as f:
            head = f.read(len(_MAGIC))
            if head != _MAGIC:
                msg = f"{self.path} is not an MCAP file (bad magic {head!r}); check the path"
                raise RecordingError(msg)
            f.seek(0)
            stream = cast(IO[bytes], _BoundedFile(f, size))
            reader = StreamReader(stream, emit_chunks=True, record_size_limit=size)
            it = iter(reader.records)
            while True:
                try:
                    rec = next(it)
                except StopIteration:
                    good_end = size
                    break
                except _MCAP_ERRORS as err:
                    error = f"{type(err).__name__}: {err}"
                    break
                good_end = f.tell()
                if self.progress is not None:
                    self.progress(good_end, size)
                if isinstance(rec, DataEnd):
                    in_summary = True
                elif isinstance(rec, Footer):
                    good_end = size
                    break
                if in_summary:
                    continue
                if isinstance(rec, Chunk):
                    problem = _chunk_problem(
                        rec.compression, rec.uncompressed_size, rec.data, len(rec.data)
                    )
                    if problem:
                        bad += 1
                        _log.warning("%s: skipping a corrupt chunk: %s", self.path, problem)
                        continue
                    try:
                        inner = breakup_chunk(rec, validate_crc=True)
                    except Exception as err:  # CRC mismatch, bad compression: lose this chunk only
                        bad += 1
                        _log.warning("%s: skipping a corrupt chunk: %s", self.path, err)
                        continue
                    complete += 1
                    for r in inner:
                        yield from self._take(r)
                else:
                    yield from self._take(rec)
        truncated = good_end < size
        if truncated and error is None:
            error = "file ends inside a record"
        if truncated:
            _log.warning(
                "%s: no summary or a truncated tail; %d bytes after the last complete record "
                "were skipped (%s)",
                self.path,
                size - good_end,
                error,
            )
        self.report = ScanReport(complete, bad, truncated, size - good_end, error)

    def _take(self, rec: Any) -> Iterator[Message | Metadata | McapAttachment]:
        if isinstance(rec, Schema):
            self.schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            self.channels[rec.id] = rec
        elif isinstance(rec, Message | Metadata | McapAttachment):
            yield rec


class Recording:
    """A recording opened for reading (a context manager; also usable without ``with``).

    Args:
        path: An MCAP file written by :class:`mocaprig.acquire.recorder.Recorder` (finished or not).

    Raises:
        RecordingError: the file is missing, not MCAP, or of a newer major format version.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            msg = f"recording {self.path} does not exist"
            raise RecordingError(msg)
        self._file: BinaryIO | None = None
        self._reader: Any = None
        self.indexed = False
        self._channels: dict[str, ChannelInfo] = {}
        self._metadata: dict[str, dict[str, str]] = {}
        self._attachments: list[RecordedAttachment] = []
        self.scan = ScanReport(0, 0, False, 0)
        self._open()

    def _open(self) -> None:
        try:
            f = self.path.open("rb")
        except OSError as err:
            msg = f"cannot open recording {self.path}: {err.strerror or err}; check permissions"
            raise RecordingError(msg) from err
        try:
            if f.read(len(_MAGIC)) != _MAGIC:
                msg = f"{self.path} is not an MCAP file (bad magic); check the path"
                raise RecordingError(msg)
            indexed = self._open_indexed(f)
        except BaseException:
            f.close()
            raise
        if not indexed:
            f.close()
            scan = _LinearScan(self.path)
            for rec in scan.records():
                if isinstance(rec, Metadata):
                    self._metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, McapAttachment):
                    self._attachments.append(
                        RecordedAttachment(rec.name, rec.media_type, rec.log_time, bytes(rec.data))
                    )
            for ch in scan.channels.values():
                sch = scan.schemas.get(ch.schema_id)
                self._channels[ch.topic] = ChannelInfo(
                    ch.topic, sch.name if sch else "", dict(ch.metadata)
                )
            self.scan = scan.report
        version = self._metadata.get("mocaprig", {}).get("format_version")
        if version is not None and version.split(".")[0] != FORMAT_VERSION.split(".")[0]:
            self.close()
            msg = (
                f"{self.path} has recording format {version}; this mocaprig reads "
                f"{FORMAT_VERSION.split('.')[0]}.x; upgrade mocaprig"
            )
            raise RecordingError(msg)

    def _open_indexed(self, f: BinaryIO) -> bool:
        """Read channels, metadata and attachments through the summary; False (nothing kept)
        when there is none or it is inconsistent with the file (then the file is scanned)."""
        size = self.path.stat().st_size
        try:
            f.seek(0)
            reader = make_reader(cast(IO[bytes], _BoundedFile(f, size)))
            summary = reader.get_summary()
            if summary is None or not summary.chunk_indexes:
                return False
            problem = _summary_problem(f, summary, size)
            if problem:
                _log.warning("%s: the summary is unusable (%s); scanning the file", self.path,
                             problem)  # fmt: skip
                return False
            channels = {}
            for ch in summary.channels.values():
                sch = summary.schemas.get(ch.schema_id)
                channels[ch.topic] = ChannelInfo(
                    ch.topic, sch.name if sch else "", dict(ch.metadata)
                )
            metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            attachments = [
                RecordedAttachment(a.name, a.media_type, a.log_time, bytes(a.data))
                for a in reader.iter_attachments()
            ]
        except (*_MCAP_ERRORS, OSError) as err:
            _log.warning("%s: cannot use the summary (%s); scanning the file", self.path, err)
            return False
        self._file, self._reader, self.indexed = f, reader, True
        self._channels, self._metadata, self._attachments = channels, metadata, attachments
        return True

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Release the file (idempotent)."""
        if self._file is not None:
            self._file.close()
            self._file = None

    # ------------------------------------------------------------------------ contents

    @property
    def channels(self) -> Mapping[str, ChannelInfo]:
        """Channels by topic."""
        return dict(self._channels)

    @property
    def topics(self) -> list[str]:
        """Topics, sorted."""
        return sorted(self._channels)

    def metadata(self) -> dict[str, dict[str, str]]:
        """Metadata records by name (``mocaprig``, ``mocaprig.summary``, ``rig``, devices...)."""
        return {k: dict(v) for k, v in self._metadata.items()}

    def attachments(self) -> list[RecordedAttachment]:
        """Attachments (rig file, calibration)."""
        return list(self._attachments)

    def messages(
        self,
        topics: Iterable[str] | str | None = None,
        *,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[RecordedMessage]:
        """Messages of ``topics`` (all when None) with ``start_ns <= log_time < end_ns``.

        Indexed files yield in log-time order; scanned files in file order (per channel, the
        order they were received).

        Raises:
            RecordingError: a topic is not in the recording.
        """
        wanted = [topics] if isinstance(topics, str) else (None if topics is None else list(topics))
        if wanted is not None:
            missing = [t for t in wanted if t not in self._channels]
            if missing:
                msg = f"{self.path} has no topic {missing[0]!r}; topics: {', '.join(self.topics)}"
                raise RecordingError(msg)
        if self.indexed:
            it = self._reader.iter_messages(
                topics=wanted, starting_at=start_ns, ending_before=end_ns, log_time_order=True
            )
            try:
                for schema, channel, m in it:
                    yield RecordedMessage(
                        channel.topic,
                        schema.name if schema else "",
                        m.log_time,
                        m.sequence,
                        m.data,
                        str(self.path),
                    )
            except _MCAP_ERRORS as err:
                msg = f"cannot read {self.path}: {err}; try `mocaprig recover`"
                raise RecordingError(msg) from err
            return
        scan = _LinearScan(self.path)
        want = None if wanted is None else set(wanted)
        for rec in scan.records():
            if not isinstance(rec, Message):
                continue
            ch = scan.channels.get(rec.channel_id)
            if ch is None or (want is not None and ch.topic not in want):
                continue
            if (start_ns is not None and rec.log_time < start_ns) or (
                end_ns is not None and rec.log_time >= end_ns
            ):
                continue
            sch = scan.schemas.get(ch.schema_id)
            yield RecordedMessage(
                ch.topic,
                sch.name if sch else "",
                rec.log_time,
                rec.sequence,
                rec.data,
                str(self.path),
            )

    def decoded(
        self, topic: str, *, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[tuple[int, Any]]:
        """``(log_time_ns, payload)`` pairs of one topic, payloads decoded."""
        for m in self.messages(topic, start_ns=start_ns, end_ns=end_ns):
            yield m.log_time_ns, m.decode()

    def _expect(self, topic: str, cls: Any) -> None:
        ch = self._channels.get(topic)
        if ch is not None and ch.schema_name != cls.SCHEMA.name:
            msg = f"{self.path}: topic {topic} holds {ch.schema_name}, not {cls.SCHEMA.name}"
            raise RecordingError(msg)

    def events(
        self, topic: str, *, start_ns: int | None = None, end_ns: int | None = None
    ) -> npt.NDArray[np.void]:
        """All events of an event topic as one :data:`~acquire.events.EVENT_DTYPE` array."""
        self._expect(topic, EventPacket)
        parts = [p.events for _, p in self.decoded(topic, start_ns=start_ns, end_ns=end_ns)]
        return np.concatenate(parts) if parts else np.empty(0, EVENT_DTYPE)

    def events_ns(
        self, topic: str, *, start_ns: int | None = None, end_ns: int | None = None
    ) -> tuple[npt.NDArray[np.void], npt.NDArray[np.int64]]:
        """All events of an event topic with their exact times as stored (ns).

        Returns ``(events, t_ns)``: ``events`` as from :meth:`events` (t in µs) and ``t_ns``
        (int64 ns, same order), with ``events["t"] == t_ns // 1000``. The ns times carry the
        sub-µs digits of imported sources (RPG text has 9 decimals); for events recorded from a
        DAVIS (µs clock) ``t_ns == events["t"] * 1000``. ``start_ns``/``end_ns`` select by
        ``log_time`` as in :meth:`events`.
        """
        self._expect(topic, EventPacket)
        evs: list[npt.NDArray[np.void]] = []
        tns: list[npt.NDArray[np.int64]] = []
        for _, p in self.decoded(topic, start_ns=start_ns, end_ns=end_ns):
            evs.append(p.events)
            tns.append(p.t_ns if p.t_ns is not None else p.events["t"] * 1000)
        if not evs:
            return np.empty(0, EVENT_DTYPE), np.empty(0, np.int64)
        return np.concatenate(evs), np.concatenate(tns)

    def imu(
        self, topic: str, *, start_ns: int | None = None, end_ns: int | None = None
    ) -> npt.NDArray[np.void]:
        """All IMU samples of a topic as one :data:`~acquire.recording_format.IMU_DTYPE` array."""
        self._expect(topic, ImuPacket)
        parts = [p.samples for _, p in self.decoded(topic, start_ns=start_ns, end_ns=end_ns)]
        return np.concatenate(parts) if parts else np.empty(0, IMU_DTYPE)

    def triggers(
        self, topic: str, *, start_ns: int | None = None, end_ns: int | None = None
    ) -> npt.NDArray[np.void]:
        """All special events (triggers...) as one ``SPECIAL_DTYPE`` array."""
        self._expect(topic, TriggerPacket)
        parts = [p.specials for _, p in self.decoded(topic, start_ns=start_ns, end_ns=end_ns)]
        return np.concatenate(parts) if parts else np.empty(0, SPECIAL_DTYPE)

    def images(
        self, topic: str, *, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[tuple[int, ImageMsg]]:
        """``(log_time_ns, ImageMsg)`` of an image topic; ``ImageMsg.image`` is a 2-D array."""
        self._expect(topic, ImageMsg)
        yield from self.decoded(topic, start_ns=start_ns, end_ns=end_ns)


# -------------------------------------------------------------------------------------------
# info


@dataclass(frozen=True, slots=True)
class StreamInfo:
    """Per-topic summary. ``counter_gaps``: messages missing by the MCAP ``sequence`` (device
    counter); ``drops``: messages the recorder dropped (``None`` when the file does not say)."""

    topic: str
    schema_name: str
    messages: int
    drops: int | None
    counter_gaps: int
    first_log_time_ns: int | None
    last_log_time_ns: int | None
    rate_hz: float
    payload_bytes: int
    metadata: Mapping[str, str]


#: log_time values from here on are Unix-epoch times (2000-01-01T00:00:00Z); below, a clock
#: counted from its own zero (an import's file time, a pipeline's reference clock, a monotonic
#: clock). No recording of this rig is older, and no relative clock runs 30 years.
UNIX_EPOCH_MIN_NS: Final = 946_684_800 * 10**9

TimeBaseName = Literal["unix", "relative"]
"""``"unix"``: ns since the Unix epoch (host receive time); ``"relative"``: another clock's ns."""


@dataclass(frozen=True, slots=True)
class TimeBase:
    """The streams of a recording whose ``log_time`` is on one clock.

    Attributes:
        name: ``"unix"`` (log_time >= :data:`UNIX_EPOCH_MIN_NS`) or ``"relative"``.
        topics: the streams with messages on it, sorted (a stream whose own log_time jumps
            between the two clocks is on both).
        messages: their messages.
        start_ns: first log_time on it.
        end_ns: last log_time on it.
    """

    name: TimeBaseName
    topics: tuple[str, ...]
    messages: int
    start_ns: int
    end_ns: int


@dataclass(frozen=True, slots=True)
class DeviceGap:
    """A span without data from one device: from its ``disconnected`` fault to its
    ``reconnected`` fault, or to the end of the recording when it never came back.

    Attributes:
        device: The device label (``davis/<serial>``...).
        start_ns: Host time the device was found lost (ns).
        end_ns: Host time it recorded again (ns), or the recording's end.
        back: Whether it came back (False: the gap runs to the end).
    """

    device: str
    start_ns: int
    end_ns: int
    back: bool

    @property
    def seconds(self) -> float:
        """The gap's length (s)."""
        return (self.end_ns - self.start_ns) / 1e9


def _gaps(faults: Iterable[Fault], end_ns: int | None) -> tuple[DeviceGap, ...]:
    """Pair each device's ``disconnected`` / ``source-died`` with its next ``reconnected``
    (``faults`` in time order)."""
    open_since: dict[str, int] = {}
    out: list[DeviceGap] = []
    for f in faults:
        if f.lost:
            open_since.setdefault(f.device, f.t_ns)
        elif f.kind == "reconnected" and f.device in open_since:
            out.append(DeviceGap(f.device, open_since.pop(f.device), f.t_ns, back=True))
    for device, t0 in open_since.items():
        out.append(DeviceGap(device, t0, max(t0, end_ns if end_ns is not None else t0), back=False))
    return tuple(sorted(out, key=lambda g: g.start_ns))


def _time_bases(segments: Mapping[tuple[str, TimeBaseName], list[int]]) -> tuple[TimeBase, ...]:
    """Group ``(topic, clock) -> [messages, first, last]`` by clock; the base holding the most
    messages outside the recorder's own topics comes first (it gives the file's duration)."""
    bases = []
    names: tuple[TimeBaseName, ...] = ("unix", "relative")
    for name in names:
        segs = {t: v for (t, b), v in segments.items() if b == name}
        if not segs:
            continue
        base = TimeBase(
            name,
            tuple(sorted(segs)),
            sum(v[0] for v in segs.values()),
            min(v[1] for v in segs.values()),
            max(v[2] for v in segs.values()),
        )
        data = sum(v[0] for t, v in segs.items() if t not in RECORDER_TOPICS)
        bases.append((data, base.messages, base))
    bases.sort(key=lambda x: x[:2], reverse=True)
    return tuple(b for _, _, b in bases)


@dataclass(frozen=True, slots=True)
class RecordingInfo:
    """What :func:`info` reports about one recording.

    ``start_ns``/``end_ns`` (and the duration) are those of one clock: the first of
    ``time_bases``. A file whose streams are on different clocks (written before every message
    of a file was put on one clock) has ``mixed_time_bases`` True, and ``time_bases`` names the
    streams on each. ``faults`` are the ``/faults`` records in time order; ``gaps`` the spans
    each device was lost.
    """

    path: Path
    indexed: bool
    recovered: bool
    format_version: str | None
    stop_reason: str | None
    start_ns: int | None
    end_ns: int | None
    scan: ScanReport
    streams: tuple[StreamInfo, ...]
    devices: Mapping[str, Mapping[str, str]]
    attachments: tuple[str, ...]
    metadata: Mapping[str, Mapping[str, str]]
    time_bases: tuple[TimeBase, ...] = ()
    faults: tuple[Fault, ...] = ()
    gaps: tuple[DeviceGap, ...] = ()

    @property
    def mixed_time_bases(self) -> bool:
        """True when the streams' log_time are not all on one clock (an older file)."""
        return len(self.time_bases) > 1

    @property
    def duration_s(self) -> float:
        """Log-time span of all messages (s)."""
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9

    @property
    def drops_total(self) -> int:
        """Messages dropped by the recorder, all streams."""
        return sum(s.drops or 0 for s in self.streams)

    def as_dict(self) -> dict[str, Any]:
        """Plain-JSON view (the ``mocaprig info --json`` object)."""
        return {
            "path": str(self.path),
            "indexed": self.indexed,
            "recovered": self.recovered,
            "format_version": self.format_version,
            "stop_reason": self.stop_reason,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "duration_s": self.duration_s,
            "drops_total": self.drops_total,
            "counter_gaps_total": sum(s.counter_gaps for s in self.streams),
            "complete_chunks": self.scan.complete_chunks,
            "bad_chunks": self.scan.bad_chunks,
            "truncated": self.scan.truncated,
            "bytes_unread": self.scan.bytes_unread,
            "streams": [
                {
                    "topic": s.topic,
                    "schema": s.schema_name,
                    "messages": s.messages,
                    "drops": s.drops,
                    "counter_gaps": s.counter_gaps,
                    "rate_hz": s.rate_hz,
                    "first_log_time_ns": s.first_log_time_ns,
                    "last_log_time_ns": s.last_log_time_ns,
                    "payload_bytes": s.payload_bytes,
                    "metadata": dict(s.metadata),
                }
                for s in self.streams
            ],
            "devices": {k: dict(v) for k, v in self.devices.items()},
            "attachments": list(self.attachments),
            "mixed_time_bases": self.mixed_time_bases,
            "time_bases": [
                {
                    "time_base": b.name,
                    "topics": list(b.topics),
                    "messages": b.messages,
                    "start_ns": b.start_ns,
                    "end_ns": b.end_ns,
                }
                for b in self.time_bases
            ],
            "faults": [f.as_dict() for f in self.faults],
            "gaps": [
                {
                    "device": g.device,
                    "start_ns": g.start_ns,
                    "end_ns": g.end_ns,
                    "seconds": g.seconds,
                    "back": g.back,
                }
                for g in self.gaps
            ],
        }


def info(path: Path, *, progress: Callable[[int, int], None] | None = None) -> RecordingInfo:
    """Summarise a recording by reading every complete chunk (works without a summary).
    ``progress(bytes_scanned, file_bytes)`` is called as the scan goes.

    Raises:
        RecordingError: the file is missing or not MCAP.
    """
    path = Path(path)
    with Recording(path) as r:
        indexed = r.indexed
        channels = r.channels
        meta = r.metadata()
        attachments = tuple(a.name for a in r.attachments())
    scan = _LinearScan(path, progress)
    counts: dict[str, int] = {}
    nbytes: dict[str, int] = {}
    first: dict[str, int] = {}
    last: dict[str, int] = {}
    last_seq: dict[str, int] = {}
    gaps: dict[str, int] = {}
    last_status: bytes | None = None
    faults: list[Fault] = []
    segments: dict[tuple[str, TimeBaseName], list[int]] = {}  # [messages, first, last]
    for rec in scan.records():
        if not isinstance(rec, Message):
            continue
        ch = scan.channels.get(rec.channel_id)
        if ch is None:
            continue
        t = ch.topic
        counts[t] = counts.get(t, 0) + 1
        nbytes[t] = nbytes.get(t, 0) + len(rec.data)
        first[t] = min(first.get(t, rec.log_time), rec.log_time)
        last[t] = max(last.get(t, rec.log_time), rec.log_time)
        clock: TimeBaseName = "unix" if rec.log_time >= UNIX_EPOCH_MIN_NS else "relative"
        seg = segments.setdefault((t, clock), [0, rec.log_time, rec.log_time])
        seg[0] += 1
        seg[1] = min(seg[1], rec.log_time)
        seg[2] = max(seg[2], rec.log_time)
        prev = last_seq.get(t)
        if prev is not None:
            diff = (rec.sequence - prev) % (1 << 32)
            if 1 < diff < (1 << 31):
                gaps[t] = gaps.get(t, 0) + diff - 1
        last_seq[t] = rec.sequence
        if t == "/diagnostics":
            last_status = rec.data
        elif t == FAULTS_TOPIC:
            fault = _fault(path, rec.data)
            if fault is not None:
                faults.append(fault)
    drops = _drops(path, meta.get("mocaprig.summary"), last_status)
    streams = []
    for topic_name in sorted(set(channels) | set(counts)):
        n = counts.get(topic_name, 0)
        t0, t1 = first.get(topic_name), last.get(topic_name)
        span = (t1 - t0) / 1e9 if t0 is not None and t1 is not None else 0.0
        ch_info = channels.get(topic_name)
        streams.append(
            StreamInfo(
                topic_name,
                ch_info.schema_name if ch_info else "",
                n,
                drops.get(topic_name) if drops is not None else None,
                gaps.get(topic_name, 0),
                t0,
                t1,
                (n - 1) / span if span > 0 and n > 1 else 0.0,
                nbytes.get(topic_name, 0),
                dict(ch_info.metadata) if ch_info else {},
            )
        )
    devices = {k: v for k, v in meta.items() if k.startswith("device/")}
    report = scan.report
    bases = _time_bases(segments)
    if len(bases) > 1:
        _log.debug(  # the caller reports it (``mocaprig info`` prints a warning line)
            "%s mixes time bases: %s; its duration is that of the %s clock",
            path,
            "; ".join(f"{', '.join(b.topics)} on {b.name} time" for b in bases),
            bases[0].name,
        )
    in_order = tuple(sorted(faults, key=lambda f: f.t_ns))
    return RecordingInfo(
        path=path,
        indexed=indexed,
        recovered="mocaprig.recovery" in meta,
        format_version=meta.get("mocaprig", {}).get("format_version"),
        stop_reason=meta.get("mocaprig.summary", {}).get("stop_reason"),
        start_ns=bases[0].start_ns if bases else None,
        end_ns=bases[0].end_ns if bases else None,
        scan=report,
        streams=tuple(streams),
        devices=devices,
        attachments=attachments,
        metadata=meta,
        time_bases=bases,
        faults=in_order,
        gaps=_gaps(in_order, bases[0].end_ns if bases else None),
    )


def _fault(path: Path, data: bytes) -> Fault | None:
    """The fault a ``/faults`` message holds (None, logged, when it cannot be read)."""
    try:
        return Fault.from_log(LogMsg.decode(data))
    except RecordingError as err:
        _log.warning("%s: a /faults message cannot be read: %s", path, err)
        return None


def _drops(
    path: Path, summary: Mapping[str, str] | None, last_status: bytes | None
) -> dict[str, int] | None:
    if summary is not None:
        out = {}
        for k, v in summary.items():
            if k.startswith("dropped:"):
                try:
                    out[k[len("dropped:") :]] = int(v)
                except ValueError:
                    _log.warning("%s: mocaprig.summary %s = %r is not a count", path, k, v)
        return out
    if last_status is not None:  # a crashed file: the last live status is the best we have
        try:
            status = RecorderStatus.decode(last_status)
        except RecordingError as err:
            _log.warning("%s: the last /diagnostics status cannot be read: %s", path, err)
            return None
        return {s.topic: s.dropped for s in status.streams}
    return None


def _summary_problem(f: BinaryIO, summary: Any, size: int) -> str:
    """What makes a summary unusable ("" when nothing): a chunk index pointing outside the file
    or at a record that is not that chunk, or sizes the decompressor must not be trusted with.
    Reads each chunk's record header (about 80 bytes), not its data."""
    for ci in summary.chunk_indexes:
        start, length = ci.chunk_start_offset, ci.chunk_length
        if not len(_MAGIC) <= start < start + length <= size:
            return f"a chunk index points at bytes {start}..{start + length} of {size}"
        f.seek(start)
        head = f.read(min(length, 9 + 8 * 3 + 4 + 4 + 64))
        if len(head) < 41 or head[0] != 0x06:
            return f"no chunk record at byte {start}"
        rec_len, usize = struct.unpack_from("<Q", head, 1)[0], struct.unpack_from("<Q", head, 25)[0]
        n_comp = struct.unpack_from("<I", head, 37)[0]
        if 41 + n_comp + 8 > len(head):
            return f"the chunk at byte {start} has a {n_comp}-byte compression name"
        comp = head[41 : 41 + n_comp].decode("utf-8", errors="replace")
        (n_data,) = struct.unpack_from("<Q", head, 41 + n_comp)
        data_at = start + 41 + n_comp + 8
        if rec_len + 9 != length or data_at + n_data > start + length:
            return f"the chunk at byte {start} does not match its index (length {rec_len})"
        if usize != ci.uncompressed_size or comp != ci.compression:
            return f"the chunk at byte {start} does not match its index (sizes, compression)"
        f.seek(data_at)
        problem = _chunk_problem(comp, usize, f.read(min(n_data, 32)), n_data)
        if problem:
            return f"the chunk at byte {start}: {problem}"
    return ""


# -------------------------------------------------------------------------------------------
# recover


@dataclass(frozen=True, slots=True)
class RecoverReport:
    """What :func:`recover` copied and what it lost."""

    source: Path
    output: Path
    messages: int
    metadata_records: int
    attachments: int
    scan: ScanReport

    @property
    def lossless(self) -> bool:
        """True when the source was read to its end with every chunk intact."""
        return self.scan.ok


def recover(
    source: Path,
    output: Path,
    *,
    compression: str = "zstd",
    progress: Callable[[int, int], None] | None = None,
) -> RecoverReport:
    """Rewrite a recording (typically one that crashed) into a new file with a full index;
    ``progress(bytes_read, source_bytes)`` is called as the source is read.

    Every message of every complete chunk, every metadata record and attachment is copied;
    a truncated or corrupt chunk is lost and reported. A ``mocaprig.recovery`` metadata record
    notes the source and what was lost.

    Raises:
        RecordingError: ``output`` exists (never overwritten), or ``source`` is not MCAP.
    """
    source, output = Path(source), Path(output)
    if output.exists():
        msg = f"{output} exists already; not overwriting (choose another output path)"
        raise RecordingError(msg)
    if not source.is_file():
        msg = f"recording {source} does not exist"
        raise RecordingError(msg)
    comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
    if compression not in comp:
        msg = f"compression must be one of {sorted(comp)}, got {compression!r}"
        raise RecordingError(msg)
    scan = _LinearScan(source, progress)
    n_msg = n_meta = n_att = 0
    try:
        with output.open("xb") as f:
            w = Writer(f, compression=comp[compression])
            w.start(profile="", library="mocaprig recover")
            schema_ids: dict[int, int] = {}
            channel_ids: dict[int, int] = {}
            for rec in scan.records():
                if isinstance(rec, Metadata):
                    w.add_metadata(rec.name, dict(rec.metadata))
                    n_meta += 1
                elif isinstance(rec, McapAttachment):
                    w.add_attachment(
                        create_time=rec.create_time,
                        log_time=rec.log_time,
                        name=rec.name,
                        media_type=rec.media_type,
                        data=rec.data,
                    )
                    n_att += 1
                else:
                    cid = channel_ids.get(rec.channel_id)
                    if cid is None:
                        ch = scan.channels.get(rec.channel_id)
                        if ch is None:
                            continue
                        sid = 0
                        if ch.schema_id:
                            sid = schema_ids.get(ch.schema_id, 0)
                            sch = scan.schemas.get(ch.schema_id)
                            if not sid and sch is not None:
                                sid = w.register_schema(sch.name, sch.encoding, sch.data)
                                schema_ids[ch.schema_id] = sid
                        cid = w.register_channel(
                            ch.topic, ch.message_encoding, sid, dict(ch.metadata)
                        )
                        channel_ids[rec.channel_id] = cid
                    w.add_message(
                        channel_id=cid,
                        log_time=rec.log_time,
                        publish_time=rec.publish_time,
                        data=rec.data,
                        sequence=rec.sequence,
                    )
                    n_msg += 1
            for old_id, ch in scan.channels.items():  # channels that carried no message
                if old_id not in channel_ids:
                    sid = schema_ids.get(ch.schema_id, 0)
                    sch = scan.schemas.get(ch.schema_id)
                    if not sid and sch is not None:
                        sid = w.register_schema(sch.name, sch.encoding, sch.data)
                        schema_ids[ch.schema_id] = sid
                    channel_ids[old_id] = w.register_channel(
                        ch.topic, ch.message_encoding, sid, dict(ch.metadata)
                    )
            rep = scan.report
            w.add_metadata(
                "mocaprig.recovery",
                {
                    "source": source.name,
                    "messages": str(n_msg),
                    "complete_chunks": str(rep.complete_chunks),
                    "bad_chunks": str(rep.bad_chunks),
                    "truncated": "true" if rep.truncated else "false",
                    "bytes_unread": str(rep.bytes_unread),
                },
            )
            w.finish()  # type: ignore[no-untyped-call]
    except OSError as err:
        msg = f"cannot write the recovered file {output}: {err}"
        raise RecordingError(msg) from err
    _log.info(
        "recovered %d messages from %s into %s (%d bytes unread)",
        n_msg,
        source,
        output,
        scan.report.bytes_unread,
    )
    return RecoverReport(source, output, n_msg, n_meta, n_att, scan.report)
