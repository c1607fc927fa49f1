"""The recording format: topics, schemas, encoders and decoders (the on-disk contract).

Specified in ``docs/recording-format.md``; this module is its executable form. Every payload is
protobuf. Images and camera calibration use the Foxglove well-known schemas
(``foxglove.RawImage``, ``foxglove.CameraCalibration``, ``foxglove.Log``) so that Foxglove opens
a recording as it is; events, IMU, triggers, sync pulses, per-frame device timing and recorder
status use the project's own schemas in package ``mocaprig`` (source:
``acquire/schemas/mocaprig.proto``; the descriptor is built here, no code generator needed).

Each message kind is a frozen dataclass with ``encode() -> bytes``, ``decode(bytes)`` and
``nbytes`` (the approximate in-memory size the recorder's queues count). Device times and
counters are stored untouched; ``log_time`` (host receive time, ns) lives in the MCAP record.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Final, Literal, Protocol, Self, cast

import numpy as np
import numpy.typing as npt
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf import (  # type: ignore[import-untyped]
    descriptor_pb2,
    descriptor_pool,
    message_factory,
)
from google.protobuf.descriptor_pb2 import (  # type: ignore[import-untyped]
    FieldDescriptorProto as _F,
)
from mcap_protobuf.schema import build_file_descriptor_set

from mocaprig.acquire.device_id import DeviceId, DeviceKind
from mocaprig.acquire.events import EVENT_DTYPE, check_events
from mocaprig.errors import RecordingError, ValidationError

__all__ = [
    "EVENT_ENCODING",
    "FORMAT_VERSION",
    "IMU_DTYPE",
    "IMU_ENCODING",
    "MAX_EVENT_PACKET_SPAN_US",
    "MESSAGE_TYPES",
    "PROFILE",
    "SPECIAL_DTYPE",
    "SPECIAL_ENCODING",
    "CameraCalibrationMsg",
    "D415FrameInfo",
    "DavisFrameInfo",
    "EventPacket",
    "ImageMsg",
    "ImuPacket",
    "LogLevel",
    "LogMsg",
    "RecordedPayload",
    "RecorderStatus",
    "SceneUpdateMsg",
    "SchemaDef",
    "StreamStatus",
    "SyncPulses",
    "TriggerPacket",
    "decode_payload",
    "proto_source",
    "split_events",
    "topic",
]

#: Version of the recording format; stored in the ``mocaprig`` metadata record. Readers accept
#: files with the same major version and refuse newer majors.
FORMAT_VERSION: Final = "1.0"
#: MCAP header profile (empty: protobuf payloads, no ROS profile).
PROFILE: Final = ""

#: Event encoding: ROS ``event_camera_msgs`` ``mono`` layout, one little-endian u64 per event:
#: bit 63 polarity, bits 48–62 y, bits 32–47 x, bits 0–31 ``t - time_base`` in ns.
EVENT_ENCODING: Final = "mono"
#: The longest span of one packet (the 32-bit ns offset): 4,294,967 µs; longer packets are split.
MAX_EVENT_PACKET_SPAN_US: Final = (2**32 - 1) // 1000
# Event times are int64 ns once decoded: a packet's time_base + 32-bit offset must fit.
_MAX_TIME_BASE_NS: Final = 2**63 - 1

#: IMU samples, identical to ``acquire.davis240c_decode.IMU_SAMPLE_DTYPE`` (64 B, packed LE).
IMU_DTYPE: Final = np.dtype(
    [("t", "<i8"), ("accel_g", "<f8", (3,)), ("gyro_dps", "<f8", (3,)), ("temp_c", "<f8")]
)
IMU_ENCODING: Final = "mocaprig_imu6_f64_v1"
#: DAVIS special events (triggers, TS resets), identical to ``SPECIAL_DTYPE`` of the decoder.
SPECIAL_DTYPE: Final = np.dtype([("t", "<i8"), ("type", "u1"), ("data", "<u4")])
SPECIAL_ENCODING: Final = "mocaprig_special13_v1"

_PACKAGE: Final = "mocaprig"
_PROTO_FILE: Final = "mocaprig/recording.proto"


def topic(device: DeviceKind, serial: str, stream: str) -> str:
    """The topic of one device stream, e.g. ``topic("davis", "00000042", "events")``.

    Shorthand for ``DeviceId(device, serial).topic(stream)``; ``syncbox`` topics ignore
    ``serial`` (one box per rig): ``/syncbox/<stream>``.
    """
    return DeviceId(device, "" if device == "syncbox" else serial).topic(stream)


# --------------------------------------------------------------------------------------------
# Project schemas, built as a FileDescriptorProto (mirrors acquire/schemas/mocaprig.proto)

_T = {
    "string": _F.TYPE_STRING,
    "bytes": _F.TYPE_BYTES,
    "uint32": _F.TYPE_UINT32,
    "uint64": _F.TYPE_UINT64,
    "int64": _F.TYPE_INT64,
    "sint64": _F.TYPE_SINT64,
    "bool": _F.TYPE_BOOL,
    "double": _F.TYPE_DOUBLE,
}

# message name -> [(field name, number, type, repeated)]; a type not in _T is a message type.
_MESSAGES: Final[dict[str, list[tuple[str, int, str, bool]]]] = {
    "EventPacket": [
        ("frame_id", 1, "string", False),
        ("width", 2, "uint32", False),
        ("height", 3, "uint32", False),
        ("seq", 4, "uint64", False),
        ("time_base", 5, "uint64", False),
        ("encoding", 6, "string", False),
        ("is_bigendian", 7, "bool", False),
        ("events", 8, "bytes", False),
    ],
    "ImuPacket": [
        ("frame_id", 1, "string", False),
        ("seq", 2, "uint64", False),
        ("encoding", 3, "string", False),
        ("samples", 4, "bytes", False),
    ],
    "TriggerPacket": [
        ("frame_id", 1, "string", False),
        ("seq", 2, "uint64", False),
        ("encoding", 3, "string", False),
        ("specials", 4, "bytes", False),
    ],
    "SyncPulses": [
        ("frame_id", 1, "string", False),
        ("count", 2, "uint64", False),
        ("t_us", 3, "uint64", False),
        ("mode", 4, "string", False),
        ("total", 5, "uint64", False),
        ("host_time_ns", 6, "uint64", False),
    ],
    "DavisFrameInfo": [
        ("frame_id", 1, "string", False),
        ("seq", 2, "uint64", False),
        ("t_start_frame_us", 3, "sint64", False),
        ("t_end_frame_us", 4, "sint64", False),
        ("t_start_exposure_us", 5, "sint64", False),
        ("t_end_exposure_us", 6, "sint64", False),
        ("exposure_cycles", 7, "uint64", False),
        ("position_x", 8, "uint32", False),
        ("position_y", 9, "uint32", False),
        ("global_shutter", 10, "bool", False),
    ],
    "D415FrameInfo": [
        ("frame_id", 1, "string", False),
        ("frame_counter", 2, "uint64", False),
        ("has_sensor_timestamp", 3, "bool", False),
        ("sensor_timestamp_us", 4, "uint64", False),
        ("has_frame_timestamp", 5, "bool", False),
        ("frame_timestamp_us", 6, "uint64", False),
        ("has_time_of_arrival", 7, "bool", False),
        ("time_of_arrival_ms", 8, "uint64", False),
        ("timestamp_domain", 9, "string", False),
        ("timestamp_ms", 10, "double", False),
        ("host_time_ns", 11, "uint64", False),
        ("depth_scale_m", 12, "double", False),
    ],
    "StreamStatus": [
        ("topic", 1, "string", False),
        ("received", 2, "uint64", False),
        ("written", 3, "uint64", False),
        ("dropped", 4, "uint64", False),
        ("queued", 5, "uint64", False),
        ("bytes_written", 6, "uint64", False),
    ],
    "RecorderStatus": [
        ("elapsed_ns", 1, "uint64", False),
        ("free_disk_bytes", 2, "uint64", False),
        ("bytes_written", 3, "uint64", False),
        ("file_index", 4, "uint32", False),
        ("streams", 5, ".mocaprig.StreamStatus", True),
        ("dropped_total", 6, "uint64", False),
    ],
}


def _build_pool() -> tuple[descriptor_pool.DescriptorPool, bytes]:
    fdp = descriptor_pb2.FileDescriptorProto(name=_PROTO_FILE, package=_PACKAGE, syntax="proto3")
    for name, fields in _MESSAGES.items():
        m = fdp.message_type.add(name=name)
        for fname, number, ftype, repeated in fields:
            f = m.field.add(name=fname, number=number, json_name=_camel(fname))
            f.label = _F.LABEL_REPEATED if repeated else _F.LABEL_OPTIONAL
            if ftype in _T:
                f.type = _T[ftype]
            else:
                f.type = _F.TYPE_MESSAGE
                f.type_name = ftype
    pool = descriptor_pool.DescriptorPool()  # private pool: no global state touched
    pool.Add(fdp)
    fds = descriptor_pb2.FileDescriptorSet()
    fds.file.append(fdp)
    return pool, fds.SerializeToString()


def _camel(name: str) -> str:
    head, *rest = name.split("_")
    return head + "".join(p.capitalize() for p in rest)


_POOL, _PROJECT_FDS = _build_pool()


def _project_class(name: str) -> Any:
    return message_factory.GetMessageClass(_POOL.FindMessageTypeByName(f"{_PACKAGE}.{name}"))


_PB: Final[dict[str, Any]] = {name: _project_class(name) for name in _MESSAGES}


@dataclass(frozen=True, slots=True)
class SchemaDef:
    """An MCAP schema: ``name`` (protobuf full name), encoding ``protobuf`` and descriptor bytes."""

    name: str
    data: bytes = field(repr=False)
    encoding: str = "protobuf"


def _foxglove_schema(cls: Any) -> SchemaDef:
    return SchemaDef(cls.DESCRIPTOR.full_name, build_file_descriptor_set(cls).SerializeToString())


def _project_schema(name: str) -> SchemaDef:
    return SchemaDef(f"{_PACKAGE}.{name}", _PROJECT_FDS)


class RecordedPayload(Protocol):
    """What the recorder writes: a message that knows its schema and how to encode itself."""

    SCHEMA: ClassVar[SchemaDef]

    def encode(self) -> bytes:
        """Protobuf bytes of this message."""
        ...

    @property
    def nbytes(self) -> int:
        """Approximate memory held by this message (bytes), counted by the recorder's queues."""
        ...


def _parse(cls: Any, data: bytes, what: str) -> Any:
    msg = cls()
    try:
        msg.ParseFromString(data)
    except Exception as err:  # protobuf raises DecodeError (a plain Exception subclass)
        text = f"cannot decode a {what} payload ({len(data)} bytes): {err}; the file is corrupt"
        raise RecordingError(text) from err
    return msg


def _blob(arr: npt.NDArray[Any], dtype: np.dtype[Any], what: str) -> bytes:
    a = np.asarray(arr)
    if a.dtype != dtype or a.ndim != 1:
        msg = f"{what} must be a 1-D array of dtype {dtype.descr}, got {a.dtype} {a.shape}"
        raise ValidationError(msg)
    return np.ascontiguousarray(a).tobytes()


def _from_blob(data: bytes, dtype: np.dtype[Any], encoding: str, want: str) -> npt.NDArray[Any]:
    if encoding != want:
        msg = f"unknown encoding {encoding!r} (this reader knows {want!r}); upgrade mocaprig"
        raise RecordingError(msg)
    if len(data) % dtype.itemsize:
        msg = f"{want} payload of {len(data)} bytes is not a multiple of {dtype.itemsize}"
        raise RecordingError(msg)
    return np.frombuffer(data, dtype=dtype).copy()


# --------------------------------------------------------------------------------------------
# Events


def split_events(
    events: npt.NDArray[np.void], *, max_span_us: int = MAX_EVENT_PACKET_SPAN_US
) -> list[npt.NDArray[np.void]]:
    """Split an event array into pieces whose time span fits one packet (input not modified)."""
    ev = check_events(events)
    if ev.size == 0:
        return [ev]
    t = ev["t"]
    lo, hi = int(t.min()), int(t.max())
    if hi - lo <= max_span_us:
        return [ev]
    order = np.argsort(t, kind="stable")
    ts = t[order]
    out: list[npt.NDArray[np.void]] = []
    start = 0
    while start < ts.size:
        stop = int(np.searchsorted(ts, ts[start] + max_span_us, side="right"))
        out.append(ev[order[start:stop]])
        start = stop
    return out


@dataclass(frozen=True, slots=True, eq=False)
class EventPacket:
    """A packet of DVS events (``mocaprig.EventPacket``, fields of ROS ``EventPacket``).

    Attributes:
        events: :data:`~mocaprig.acquire.events.EVENT_DTYPE` (t µs device clock, untouched).
        width: Sensor columns.
        height: Sensor rows.
        seq: Packet counter of this stream (0, 1, ...; a gap means a dropped packet).
        frame_id: Device name, e.g. ``davis_00000042``.
        t_ns: Optional exact event times (ns, int64, same order as ``events``) for sources finer
            than the µs of :data:`~mocaprig.acquire.events.EVENT_DTYPE` (e.g. imported RPG text, 9
            decimals). When given, ``events["t"] == t_ns // 1000`` (floor) must hold and
            :meth:`encode` stores these ns times; when ``None`` it stores ``events["t"]`` × 1000.
            :meth:`decode` always fills it from the stored ns offsets.

    Raises:
        ValidationError: ``t_ns`` is not a 1-D integer array of the events' length, or
            disagrees with ``events["t"]``.
    """

    SCHEMA: ClassVar[SchemaDef] = _project_schema("EventPacket")

    events: npt.NDArray[np.void] = field(repr=False)
    width: int = 240
    height: int = 180
    seq: int = 0
    frame_id: str = ""
    t_ns: npt.NDArray[np.int64] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.t_ns is None:
            return
        ev = check_events(self.events)
        t_ns = np.asarray(self.t_ns)
        if t_ns.ndim != 1 or t_ns.shape[0] != ev.shape[0] or t_ns.dtype.kind not in "iu":
            msg = (
                f"EventPacket t_ns must be a 1-D integer array of {ev.shape[0]} ns times (one "
                f"per event), got {t_ns.dtype} {t_ns.shape}; pass t_ns=None for µs-only events"
            )
            raise ValidationError(msg)
        t_ns = t_ns.astype(np.int64, copy=False)
        bad = np.flatnonzero(ev["t"] != t_ns // 1000)
        if bad.size:
            i = int(bad[0])
            msg = (
                f"EventPacket t_ns disagrees with events['t'] at {bad.size} event(s), first at "
                f"index {i}: t_ns={int(t_ns[i])} ns but t={int(ev['t'][i])} µs; "
                "events['t'] must equal t_ns // 1000 (floor)"
            )
            raise ValidationError(msg)
        object.__setattr__(self, "t_ns", t_ns)

    @property
    def nbytes(self) -> int:
        extra = 0 if self.t_ns is None else int(self.t_ns.nbytes)
        return int(self.events.nbytes) + extra + 64

    def encode(self) -> bytes:
        ev = check_events(self.events)
        if ev.size:
            if self.t_ns is None:
                t_us = ev["t"]
                t0_us, hi_us = int(t_us.min()), int(t_us.max())
                if t0_us < 0 or hi_us - t0_us > MAX_EVENT_PACKET_SPAN_US:
                    msg = (
                        f"event packet spans {hi_us - t0_us} µs from t={t0_us} µs; it must "
                        f"start at t >= 0 and span at most {MAX_EVENT_PACKET_SPAN_US} µs "
                        "(use split_events)"
                    )
                    raise ValidationError(msg)
                t0_ns = t0_us * 1000
                dt_ns = (t_us - t0_us) * 1000
            else:
                t_ns = self.t_ns
                t0_ns, hi_ns = int(t_ns.min()), int(t_ns.max())
                if t0_ns < 0 or hi_ns - t0_ns >= 2**32:
                    msg = (
                        f"event packet spans {hi_ns - t0_ns} ns from t_ns={t0_ns} ns; it must "
                        "start at t_ns >= 0 and span less than 2**32 ns "
                        f"({MAX_EVENT_PACKET_SPAN_US} µs; split the events and t_ns alike)"
                    )
                    raise ValidationError(msg)
                dt_ns = t_ns - t0_ns
            if t0_ns + 2**32 > _MAX_TIME_BASE_NS:
                msg = f"event time base {t0_ns} ns is beyond the int64 ns range of the format"
                raise ValidationError(msg)
            if int(ev["x"].max()) >= 2**16 or int(ev["y"].max()) >= 2**15:
                msg = "event y must be < 32768 for the mono encoding"
                raise ValidationError(msg)
            words = (
                (ev["p"].astype(np.uint64) & np.uint64(1)) << np.uint64(63)
                | ev["y"].astype(np.uint64) << np.uint64(48)
                | ev["x"].astype(np.uint64) << np.uint64(32)
                | dt_ns.astype(np.uint64)
            )
            blob = words.astype("<u8").tobytes()
            time_base_ns = t0_ns
        else:
            blob, time_base_ns = b"", 0
        pb = _PB["EventPacket"](
            frame_id=self.frame_id,
            width=self.width,
            height=self.height,
            seq=self.seq,
            time_base=time_base_ns,
            encoding=EVENT_ENCODING,
            is_bigendian=False,
            events=blob,
        )
        return bytes(pb.SerializeToString())

    @classmethod
    def decode(cls, data: bytes) -> Self:
        """Decode a payload; ``t_ns = time_base + offset`` exactly, ``events["t"] = t_ns // 1000``.

        Files written before ``t_ns`` existed hold µs-derived times (``time_base`` and every
        offset multiples of 1000 ns), so ``events["t"]`` is what it always was.
        """
        pb = _parse(_PB["EventPacket"], data, "mocaprig.EventPacket")
        if pb.encoding != EVENT_ENCODING or pb.is_bigendian:
            msg = f"event encoding {pb.encoding!r} (big-endian={pb.is_bigendian}) is not 'mono' LE"
            raise RecordingError(msg)
        if len(pb.events) % 8:
            msg = f"event blob of {len(pb.events)} bytes is not a multiple of 8"
            raise RecordingError(msg)
        time_base_ns = int(pb.time_base)
        if time_base_ns + 2**32 > _MAX_TIME_BASE_NS:
            msg = (
                f"event packet time_base {time_base_ns} ns is beyond the int64 ns range; "
                "the file is corrupt or not written by mocaprig"
            )
            raise RecordingError(msg)
        words = np.frombuffer(pb.events, dtype="<u8")
        t_ns = (words & np.uint64(0xFFFFFFFF)).astype(np.int64) + np.int64(time_base_ns)
        out = np.empty(words.size, dtype=EVENT_DTYPE)
        out["t"] = t_ns // 1000
        out["x"] = (words >> np.uint64(32)) & np.uint64(0xFFFF)
        out["y"] = (words >> np.uint64(48)) & np.uint64(0x7FFF)
        out["p"] = words >> np.uint64(63)
        return cls(out, int(pb.width), int(pb.height), int(pb.seq), str(pb.frame_id), t_ns)


# --------------------------------------------------------------------------------------------
# IMU, triggers, sync pulses


@dataclass(frozen=True, slots=True, eq=False)
class ImuPacket:
    """IMU samples (``mocaprig.ImuPacket``): :data:`IMU_DTYPE` packed little-endian."""

    SCHEMA: ClassVar[SchemaDef] = _project_schema("ImuPacket")

    samples: npt.NDArray[np.void] = field(repr=False)
    seq: int = 0
    frame_id: str = ""

    @property
    def nbytes(self) -> int:
        return int(self.samples.nbytes) + 64

    def encode(self) -> bytes:
        blob = _blob(self.samples, IMU_DTYPE, "IMU samples")
        pb = _PB["ImuPacket"](
            frame_id=self.frame_id, seq=self.seq, encoding=IMU_ENCODING, samples=blob
        )
        return bytes(pb.SerializeToString())

    @classmethod
    def decode(cls, data: bytes) -> Self:
        pb = _parse(_PB["ImuPacket"], data, "mocaprig.ImuPacket")
        arr = _from_blob(pb.samples, IMU_DTYPE, pb.encoding, IMU_ENCODING)
        return cls(arr, int(pb.seq), str(pb.frame_id))


@dataclass(frozen=True, slots=True, eq=False)
class TriggerPacket:
    """DAVIS special events (``mocaprig.TriggerPacket``): :data:`SPECIAL_DTYPE` packed LE."""

    SCHEMA: ClassVar[SchemaDef] = _project_schema("TriggerPacket")

    specials: npt.NDArray[np.void] = field(repr=False)
    seq: int = 0
    frame_id: str = ""

    @property
    def nbytes(self) -> int:
        return int(self.specials.nbytes) + 64

    def encode(self) -> bytes:
        blob = _blob(self.specials, SPECIAL_DTYPE, "special events")
        pb = _PB["TriggerPacket"](
            frame_id=self.frame_id, seq=self.seq, encoding=SPECIAL_ENCODING, specials=blob
        )
        return bytes(pb.SerializeToString())

    @classmethod
    def decode(cls, data: bytes) -> Self:
        pb = _parse(_PB["TriggerPacket"], data, "mocaprig.TriggerPacket")
        arr = _from_blob(pb.specials, SPECIAL_DTYPE, pb.encoding, SPECIAL_ENCODING)
        return cls(arr, int(pb.seq), str(pb.frame_id))


@dataclass(frozen=True, slots=True)
class SyncPulses:
    """A sync-box ``PULSES`` report (``mocaprig.acquire.syncbox.PulseReport``).

    ``count``: pulses of the run (as sent); ``total``: across reconnects; ``t_us``: box clock
    at the last rising edge, µs, unwrapped by the driver (the box's u32 = ``t_us % 2**32``);
    ``host_time_ns``: the driver's host monotonic clock when the line arrived.
    """

    SCHEMA: ClassVar[SchemaDef] = _project_schema("SyncPulses")

    count: int
    t_us: int
    mode: str = ""
    frame_id: str = "syncbox"
    total: int = 0
    host_time_ns: int = 0

    @property
    def nbytes(self) -> int:
        return 112

    def encode(self) -> bytes:
        values = {k: getattr(self, k) for k in _field_names("SyncPulses")}
        return bytes(_PB["SyncPulses"](**values).SerializeToString())

    @classmethod
    def decode(cls, data: bytes) -> Self:
        pb = _parse(_PB["SyncPulses"], data, "mocaprig.SyncPulses")
        return cls(**{k: getattr(pb, k) for k in _field_names("SyncPulses")})


# --------------------------------------------------------------------------------------------
# Per-frame device timing


@dataclass(frozen=True, slots=True)
class DavisFrameInfo:
    """Device timing of one DAVIS APS frame (``mocaprig.DavisFrameInfo``), µs device clock."""

    SCHEMA: ClassVar[SchemaDef] = _project_schema("DavisFrameInfo")

    seq: int
    t_start_frame_us: int
    t_end_frame_us: int
    t_start_exposure_us: int
    t_end_exposure_us: int
    exposure_cycles: int
    position_x: int = 0
    position_y: int = 0
    global_shutter: bool = True
    frame_id: str = ""

    @property
    def nbytes(self) -> int:
        return 160

    def encode(self) -> bytes:
        values = {k: getattr(self, k) for k in _field_names("DavisFrameInfo")}
        return bytes(_PB["DavisFrameInfo"](**values).SerializeToString())

    @classmethod
    def decode(cls, data: bytes) -> Self:
        pb = _parse(_PB["DavisFrameInfo"], data, "mocaprig.DavisFrameInfo")
        return cls(**{k: getattr(pb, k) for k in _field_names("DavisFrameInfo")})


@dataclass(frozen=True, slots=True)
class D415FrameInfo:
    """Metadata of one D415 capture (``mocaprig.D415FrameInfo``); ``None`` = not in metadata."""

    SCHEMA: ClassVar[SchemaDef] = _project_schema("D415FrameInfo")

    frame_counter: int
    sensor_timestamp_us: int | None
    frame_timestamp_us: int | None
    time_of_arrival_ms: int | None
    timestamp_domain: str
    timestamp_ms: float
    host_time_ns: int
    depth_scale_m: float
    frame_id: str = ""

    @property
    def nbytes(self) -> int:
        return 200

    def encode(self) -> bytes:
        pb = _PB["D415FrameInfo"](
            frame_id=self.frame_id,
            frame_counter=self.frame_counter,
            timestamp_domain=self.timestamp_domain,
            timestamp_ms=self.timestamp_ms,
            host_time_ns=self.host_time_ns,
            depth_scale_m=self.depth_scale_m,
        )
        for name in ("sensor_timestamp_us", "frame_timestamp_us", "time_of_arrival_ms"):
            value = getattr(self, name)
            if value is not None:
                setattr(pb, name, value)
                setattr(pb, "has_" + name.rsplit("_", 1)[0], True)
        return bytes(pb.SerializeToString())

    @classmethod
    def decode(cls, data: bytes) -> Self:
        pb = _parse(_PB["D415FrameInfo"], data, "mocaprig.D415FrameInfo")

        def opt(name: str) -> int | None:
            has = getattr(pb, "has_" + name.rsplit("_", 1)[0])
            return int(getattr(pb, name)) if has else None

        return cls(
            int(pb.frame_counter),
            opt("sensor_timestamp_us"),
            opt("frame_timestamp_us"),
            opt("time_of_arrival_ms"),
            str(pb.timestamp_domain),
            float(pb.timestamp_ms),
            int(pb.host_time_ns),
            float(pb.depth_scale_m),
            str(pb.frame_id),
        )


def _field_names(message: str) -> list[str]:
    return [f[0] for f in _MESSAGES[message]]


# --------------------------------------------------------------------------------------------
# Recorder status and log


@dataclass(frozen=True, slots=True)
class StreamStatus:
    """Counters of one stream at one moment (messages, except ``bytes_written``)."""

    topic: str
    received: int
    written: int
    dropped: int
    queued: int
    bytes_written: int


@dataclass(frozen=True, slots=True)
class RecorderStatus:
    """The recorder's live status (``mocaprig.RecorderStatus`` on ``/diagnostics``)."""

    SCHEMA: ClassVar[SchemaDef] = _project_schema("RecorderStatus")

    elapsed_ns: int
    free_disk_bytes: int
    bytes_written: int
    file_index: int
    streams: tuple[StreamStatus, ...]

    @property
    def dropped_total(self) -> int:
        return sum(s.dropped for s in self.streams)

    @property
    def nbytes(self) -> int:
        return 128 + 96 * len(self.streams)

    def encode(self) -> bytes:
        pb = _PB["RecorderStatus"](
            elapsed_ns=self.elapsed_ns,
            free_disk_bytes=self.free_disk_bytes,
            bytes_written=self.bytes_written,
            file_index=self.file_index,
            dropped_total=self.dropped_total,
        )
        for s in self.streams:
            pb.streams.add(**{k: getattr(s, k) for k in _field_names("StreamStatus")})
        return bytes(pb.SerializeToString())

    @classmethod
    def decode(cls, data: bytes) -> Self:
        pb = _parse(_PB["RecorderStatus"], data, "mocaprig.RecorderStatus")
        streams = tuple(
            StreamStatus(**{k: getattr(s, k) for k in _field_names("StreamStatus")})
            for s in pb.streams
        )
        return cls(
            int(pb.elapsed_ns),
            int(pb.free_disk_bytes),
            int(pb.bytes_written),
            int(pb.file_index),
            streams,
        )


LogLevel = Literal["DEBUG", "INFO", "WARNING", "ERROR", "FATAL"]
_LOG_LEVELS: Final[dict[str, int]] = {"DEBUG": 1, "INFO": 2, "WARNING": 3, "ERROR": 4, "FATAL": 5}


@dataclass(frozen=True, slots=True)
class LogMsg:
    """A recorder event (``foxglove.Log`` on ``/log``): source died, disk stop, split, ...

    ``timestamp_ns`` is host time; ``name`` the component (``recorder``, a topic, a source).
    """

    SCHEMA: ClassVar[SchemaDef] = _foxglove_schema(Log)

    level: LogLevel
    message: str
    name: str = "recorder"
    timestamp_ns: int = 0

    @property
    def nbytes(self) -> int:
        return 96 + len(self.message)

    def encode(self) -> bytes:
        pb = Log(level=cast(Any, _LOG_LEVELS[self.level]), message=self.message, name=self.name)
        pb.timestamp.FromNanoseconds(self.timestamp_ns)
        return bytes(pb.SerializeToString())

    @classmethod
    def decode(cls, data: bytes) -> Self:
        pb = _parse(Log, data, "foxglove.Log")
        names = {v: k for k, v in _LOG_LEVELS.items()}
        level: Any = names.get(int(pb.level), "INFO")
        return cls(level, str(pb.message), str(pb.name), int(pb.timestamp.ToNanoseconds()))


# --------------------------------------------------------------------------------------------
# Images and calibration (Foxglove well-known schemas)

ImageEncoding = Literal["mono8", "mono16", "16UC1"]
_IMAGE_DTYPES: Final[dict[str, np.dtype[Any]]] = {
    "mono8": np.dtype("u1"),
    "mono16": np.dtype("<u2"),
    "16UC1": np.dtype("<u2"),
}


@dataclass(frozen=True, slots=True, eq=False)
class ImageMsg:
    """An image (``foxglove.RawImage``): IR ``mono8``, depth ``16UC1``, DAVIS APS ``mono16``.

    ``timestamp_ns`` is the device time of the image (DAVIS: exposure middle µs × 1000; D415:
    ``sensor_timestamp`` µs × 1000, or host time when the camera gave none); the full device
    timing is on the companion ``frame_info`` topic with the same MCAP ``sequence``.
    """

    SCHEMA: ClassVar[SchemaDef] = _foxglove_schema(RawImage)

    image: npt.NDArray[Any] = field(repr=False)
    encoding: ImageEncoding
    timestamp_ns: int = 0
    frame_id: str = ""

    @property
    def nbytes(self) -> int:
        return int(self.image.nbytes) + 96

    def encode(self) -> bytes:
        want = _IMAGE_DTYPES.get(self.encoding)
        img = np.asarray(self.image)
        if want is None or img.ndim != 2 or img.dtype.newbyteorder("<") != want:
            msg = (
                f"image for encoding {self.encoding!r} must be 2-D {want}, "
                f"got {img.dtype} {img.shape}"
            )
            raise ValidationError(msg)
        data = np.ascontiguousarray(img, dtype=want).tobytes()
        pb = RawImage(
            frame_id=self.frame_id,
            width=img.shape[1],
            height=img.shape[0],
            encoding=self.encoding,
            step=img.shape[1] * want.itemsize,
            data=data,
        )
        pb.timestamp.FromNanoseconds(self.timestamp_ns)
        return bytes(pb.SerializeToString())

    @classmethod
    def decode(cls, data: bytes) -> Self:
        pb = _parse(RawImage, data, "foxglove.RawImage")
        want = _IMAGE_DTYPES.get(pb.encoding)
        if want is None:
            msg = f"image encoding {pb.encoding!r} is not one of {sorted(_IMAGE_DTYPES)}"
            raise RecordingError(msg)
        h, w, step = int(pb.height), int(pb.width), int(pb.step)
        if step < w * want.itemsize or len(pb.data) < step * h:
            msg = f"RawImage {w}x{h} step {step} has only {len(pb.data)} data bytes"
            raise RecordingError(msg)
        rows = np.frombuffer(pb.data, dtype=np.uint8)[: step * h].reshape(h, step)
        img = rows[:, : w * want.itemsize].copy().view(want).reshape(h, w)
        enc: Any = pb.encoding
        return cls(img, enc, int(pb.timestamp.ToNanoseconds()), str(pb.frame_id))


@dataclass(frozen=True, slots=True)
class CameraCalibrationMsg:
    """Intrinsics of one camera stream (``foxglove.CameraCalibration``), OpenCV convention.

    ``k`` is the 3×3 camera matrix row-major (``k[0] == 0`` = uncalibrated), ``d`` the
    distortion coefficients of ``distortion_model`` (``plumb_bob`` = OpenCV k1 k2 p1 p2 k3).
    """

    SCHEMA: ClassVar[SchemaDef] = _foxglove_schema(CameraCalibration)

    width: int
    height: int
    k: tuple[float, ...]
    d: tuple[float, ...] = ()
    distortion_model: str = "plumb_bob"
    frame_id: str = ""
    timestamp_ns: int = 0

    @property
    def nbytes(self) -> int:
        return 256

    def encode(self) -> bytes:
        if len(self.k) != 9:
            msg = f"camera matrix k must have 9 values (3x3 row-major), got {len(self.k)}"
            raise ValidationError(msg)
        k = list(self.k)
        p = [k[0], k[1], k[2], 0.0, k[3], k[4], k[5], 0.0, k[6], k[7], k[8], 0.0]
        pb = CameraCalibration(
            frame_id=self.frame_id,
            width=self.width,
            height=self.height,
            distortion_model=self.distortion_model,
            D=list(self.d),
            K=k,
            R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            P=p,
        )
        pb.timestamp.FromNanoseconds(self.timestamp_ns)
        return bytes(pb.SerializeToString())

    @classmethod
    def decode(cls, data: bytes) -> Self:
        pb = _parse(CameraCalibration, data, "foxglove.CameraCalibration")
        return cls(
            int(pb.width),
            int(pb.height),
            tuple(float(v) for v in pb.K),
            tuple(float(v) for v in pb.D),
            str(pb.distortion_model),
            str(pb.frame_id),
            int(pb.timestamp.ToNanoseconds()),
        )


#: Schema name -> message class; what :func:`decode_payload` dispatches on.
@dataclass(frozen=True, slots=True, eq=False)
class SceneUpdateMsg:
    """A 3-D scene update (``foxglove.SceneUpdate``): processing results (DeMoCap markers and
    joints, fused clouds) that Foxglove's 3-D panel draws. ``update`` is the protobuf message."""

    SCHEMA: ClassVar[SchemaDef] = _foxglove_schema(SceneUpdate)

    update: Any = field(repr=False)

    @property
    def nbytes(self) -> int:
        return int(self.update.ByteSize())

    def encode(self) -> bytes:
        return bytes(self.update.SerializeToString())

    @classmethod
    def decode(cls, data: bytes) -> Self:
        return cls(_parse(SceneUpdate, data, "foxglove.SceneUpdate"))


MESSAGE_TYPES: Final[Mapping[str, Any]] = {
    cls.SCHEMA.name: cls
    for cls in (
        EventPacket,
        ImuPacket,
        TriggerPacket,
        SyncPulses,
        DavisFrameInfo,
        D415FrameInfo,
        RecorderStatus,
        LogMsg,
        ImageMsg,
        CameraCalibrationMsg,
        SceneUpdateMsg,
    )
}


def decode_payload(schema_name: str, data: bytes) -> Any:
    """Decode one message payload by its MCAP schema name.

    Raises:
        RecordingError: unknown schema (a newer format) or a corrupt payload.
    """
    cls = MESSAGE_TYPES.get(schema_name)
    if cls is None:
        known = ", ".join(sorted(MESSAGE_TYPES))
        msg = f"no decoder for schema {schema_name!r} (known: {known}); upgrade mocaprig"
        raise RecordingError(msg)
    return cls.decode(data)


def proto_source() -> str:
    """The ``.proto`` text of the project schemas (``acquire/schemas/mocaprig.proto``).

    The descriptor stored in recordings is built from the same table; a test keeps the file and
    the table equal. Field comments (units, encodings) live in ``docs/recording-format.md``.
    """
    lines = [
        f"// Project schemas of the mocaprig recording format {FORMAT_VERSION}.",
        "// Generated from acquire/recording_format.py (proto_source()); do not edit by hand.",
        'syntax = "proto3";',
        "",
        f"package {_PACKAGE};",
        "",
    ]
    for name, fields in _MESSAGES.items():
        lines.append(f"message {name} {{")
        for fname, number, ftype, repeated in fields:
            t = ftype.removeprefix(f".{_PACKAGE}.")
            lines.append(f"  {'repeated ' if repeated else ''}{t} {fname} = {number};")
        lines.extend(["}", ""])
    return "\n".join(lines)
