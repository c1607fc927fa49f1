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

import logging
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO, Final, Self

import numpy as np
import numpy.typing as npt
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Attachment as McapAttachment
from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from mocaprig.acquire.events import EVENT_DTYPE
from mocaprig.acquire.recording_format import (
    FORMAT_VERSION,
    IMU_DTYPE,
    SPECIAL_DTYPE,
    EventPacket,
    ImageMsg,
    ImuPacket,
    RecorderStatus,
    TriggerPacket,
    decode_payload,
)
from mocaprig.errors import RecordingError

__all__ = [
    "ChannelInfo",
    "RecordedAttachment",
    "RecordedMessage",
    "Recording",
    "RecordingInfo",
    "RecoverReport",
    "ScanReport",
    "StreamInfo",
    "info",
    "recover",
]

_log = logging.getLogger(__name__)

_MAGIC: Final = b"\x89MCAP0\r\n"


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

    def decode(self) -> Any:
        """The payload as a :mod:`mocaprig.acquire.recording_format` message object."""
        return decode_payload(self.schema_name, self.data)


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

    def __init__(self, path: Path) -> None:
        self.path = path
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
            reader = StreamReader(f, emit_chunks=True, record_size_limit=1 << 31)
            it = iter(reader.records)
            while True:
                try:
                    rec = next(it)
                except StopIteration:
                    good_end = size
                    break
                except (McapError, ValueError, EOFError) as err:
                    error = f"{type(err).__name__}: {err}"
                    break
                good_end = f.tell()
                if isinstance(rec, DataEnd):
                    in_summary = True
                elif isinstance(rec, Footer):
                    good_end = size
                    break
                if in_summary:
                    continue
                if isinstance(rec, Chunk):
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
        f = self.path.open("rb")
        if f.read(len(_MAGIC)) != _MAGIC:
            f.close()
            msg = f"{self.path} is not an MCAP file (bad magic); check the path"
            raise RecordingError(msg)
        f.seek(0)
        try:
            reader = make_reader(f)
            summary = reader.get_summary()
        except (McapError, ValueError, EOFError):
            summary = None
        if summary is not None and summary.chunk_indexes:
            self._file, self._reader, self.indexed = f, reader, True
            for ch in summary.channels.values():
                sch = summary.schemas.get(ch.schema_id)
                self._channels[ch.topic] = ChannelInfo(
                    ch.topic, sch.name if sch else "", dict(ch.metadata)
                )
            for m in reader.iter_metadata():
                self._metadata[m.name] = dict(m.metadata)
            for a in reader.iter_attachments():
                self._attachments.append(
                    RecordedAttachment(a.name, a.media_type, a.log_time, bytes(a.data))
                )
        else:
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
                        channel.topic, schema.name if schema else "", m.log_time, m.sequence, m.data
                    )
            except McapError as err:
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
                ch.topic, sch.name if sch else "", rec.log_time, rec.sequence, rec.data
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


@dataclass(frozen=True, slots=True)
class RecordingInfo:
    """What :func:`info` reports about one recording."""

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
        }


def info(path: Path) -> RecordingInfo:
    """Summarise a recording by reading every complete chunk (works without a summary).

    Raises:
        RecordingError: the file is missing or not MCAP.
    """
    path = Path(path)
    with Recording(path) as r:
        indexed = r.indexed
        channels = r.channels
        meta = r.metadata()
        attachments = tuple(a.name for a in r.attachments())
    scan = _LinearScan(path)
    counts: dict[str, int] = {}
    nbytes: dict[str, int] = {}
    first: dict[str, int] = {}
    last: dict[str, int] = {}
    last_seq: dict[str, int] = {}
    gaps: dict[str, int] = {}
    last_status: bytes | None = None
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
        prev = last_seq.get(t)
        if prev is not None:
            diff = (rec.sequence - prev) % (1 << 32)
            if 1 < diff < (1 << 31):
                gaps[t] = gaps.get(t, 0) + diff - 1
        last_seq[t] = rec.sequence
        if t == "/diagnostics":
            last_status = rec.data
    drops = _drops(meta.get("mocaprig.summary"), last_status)
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
    return RecordingInfo(
        path=path,
        indexed=indexed,
        recovered="mocaprig.recovery" in meta,
        format_version=meta.get("mocaprig", {}).get("format_version"),
        stop_reason=meta.get("mocaprig.summary", {}).get("stop_reason"),
        start_ns=min(first.values()) if first else None,
        end_ns=max(last.values()) if last else None,
        scan=report,
        streams=tuple(streams),
        devices=devices,
        attachments=attachments,
        metadata=meta,
    )


def _drops(summary: Mapping[str, str] | None, last_status: bytes | None) -> dict[str, int] | None:
    if summary is not None:
        return {
            k[len("dropped:") :]: int(v) for k, v in summary.items() if k.startswith("dropped:")
        }
    if last_status is not None:  # a crashed file: the last live status is the best we have
        status = RecorderStatus.decode(last_status)
        return {s.topic: s.dropped for s in status.streams}
    return None


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


def recover(source: Path, output: Path, *, compression: str = "zstd") -> RecoverReport:
    """Rewrite a recording (typically one that crashed) into a new file with a full index.

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
    scan = _LinearScan(source)
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
