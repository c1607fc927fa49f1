"""The recording contract per device: typed records out of a recording, never topic strings.

Every consumer of a recording (marker measurement, Vicon calibration, the DeMoCap replay, the
demo's checks, ChArUco) reads devices through this module:

- :class:`DeviceId` builds and parses every topic (``/d415/<serial>/ir``), device label
  (``d415/<serial>``) and metadata record name (``device/d415/<serial>``) of the format
  (``docs/recording-format.md``); nothing else splits topic strings.
- :class:`RecordedD415` gives one camera's intrinsics, its typed settings (:class:`D415Settings`,
  replacing the ``device/d415/<serial>`` string map), a frame index with the device time
  unwrapped once (:class:`D415FrameIndex`), and :class:`~acquire.depth_camera.FrameSet`s with IR
  and depth paired: the same record a live camera's ``poll()`` returns.
  :func:`read_frame_sets` reads several cameras in one pass over the file.
- :class:`RecordedDavis` gives a DAVIS's events, IMU, APS frames and trigger input on its device
  timebase (ns since its last timestamp reset), and the external-input edges after that reset.
- :func:`sync_pulses` gives the sync box's pulse reports.

Usage::

    with Recording(path) as rec:
        for cam in d415_devices(rec):
            d415 = RecordedD415(rec, cam)
            K = d415.intrinsics().k
            for fs in d415.frame_sets(start_ns=t0, end_ns=t1):   # FrameSet, as from a camera
                ...
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final, NamedTuple

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.depth_camera import (
    D415Frame,
    FrameSet,
    FrameTiming,
    SensorOptions,
    StreamConfig,
    StreamKind,
    SyncMode,
    TimestampDomain,
)
from mocaprig.acquire.device_id import DeviceId, DeviceKind
from mocaprig.acquire.events import EVENT_DTYPE
from mocaprig.acquire.recording import Recording
from mocaprig.acquire.recording_format import (
    IMU_DTYPE,
    SPECIAL_DTYPE,
    CameraCalibrationMsg,
    D415FrameInfo,
    DavisFrameInfo,
    ImageMsg,
    SyncPulses,
)
from mocaprig.errors import RecordingError, ValidationError
from mocaprig.timebase import unwrap_u32

__all__ = [
    "D415FrameIndex",
    "D415Intrinsics",
    "D415Settings",
    "DavisFrame",
    "DeviceId",
    "DeviceKind",
    "RecordedD415",
    "RecordedDavis",
    "RecordedFrameSet",
    "d415_devices",
    "davis_devices",
    "devices",
    "frame_timings",
    "read_frame_sets",
    "sync_pulses",
]

_log = logging.getLogger(__name__)

# The stream whose presence makes a device "in the recording" (every recorder writes it).
_PRIMARY: Final[Mapping[str, str]] = {"d415": "ir", "davis": "trigger", "syncbox": "pulses"}
_DAVIS_STREAMS: Final = ("events", "frame", "frame_info", "imu", "trigger")


def devices(rec: Recording, kind: DeviceKind | None = None) -> list[DeviceId]:
    """The devices of a recording (those with their primary stream), sorted."""
    found = set()
    for t in rec.topics:
        parsed = DeviceId.from_topic(t)
        if parsed is None:
            continue
        dev, stream = parsed
        if (kind is None or dev.kind == kind) and stream == _PRIMARY[dev.kind]:
            found.add(dev)
    return sorted(found)


def d415_devices(rec: Recording) -> list[DeviceId]:
    """The D415 cameras of a recording (those with an ``ir`` stream), sorted by serial."""
    return devices(rec, "d415")


def davis_devices(rec: Recording) -> list[DeviceId]:
    """The DAVIS cameras of a recording: any with a DAVIS stream, sorted by serial."""
    found = set()
    for t in rec.topics:
        parsed = DeviceId.from_topic(t)
        if parsed is not None and parsed[0].kind == "davis" and parsed[1] in _DAVIS_STREAMS:
            found.add(parsed[0])
    return sorted(found)


# ---------------------------------------------------------------------------------------------
# D415


@dataclass(frozen=True, slots=True)
class D415Intrinsics:
    """Intrinsics of a D415's IR/depth viewpoint as recorded (OpenCV convention, pixels).

    ``k`` (3, 3) camera matrix; ``distortion`` (5,) k1 k2 p1 p2 k3 (zeros: none).
    """

    width: int
    height: int
    k: npt.NDArray[np.float64] = field(repr=False)
    distortion: npt.NDArray[np.float64] = field(repr=False)


def _typed_dataclass(cls: Any, values: Mapping[str, str], what: str) -> Any:
    """An instance of the (int/bool/float-field) dataclass ``cls`` from its stored strings.

    Fields are looked up by the dataclass's own names, so a renamed field cannot be silently
    missed: a missing one raises ``RecordingError`` naming it.
    """
    kw: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.name not in values:
            msg = f"{what} lacks {f.name!r} (has {sorted(values)})"
            raise RecordingError(msg)
        raw = values[f.name]
        default = f.default
        try:
            if isinstance(default, bool):
                if raw not in ("True", "False"):
                    raise ValueError(raw)
                kw[f.name] = raw == "True"
            elif isinstance(default, int):
                kw[f.name] = int(raw)
            elif isinstance(default, float):
                kw[f.name] = float(raw)
            else:
                kw[f.name] = raw
        except ValueError as err:
            msg = f"{what}: {f.name} = {raw!r} is not a {type(default).__name__}"
            raise RecordingError(msg) from err
    try:
        return cls(**kw)
    except ValidationError as err:
        msg = f"{what}: {err}"
        raise RecordingError(msg) from err


@dataclass(frozen=True, slots=True)
class D415Settings:
    """What a recording says of one D415 (its ``device/d415/<serial>`` record), typed.

    ``stream``/``options`` are None when the recorder was not given them (e.g. imported files);
    ``sync_mode`` None when unknown.
    """

    serial: str
    name: str = ""
    firmware: str = ""
    usb_type: str = ""
    sync_mode: SyncMode | None = None
    depth_scale_m: float | None = None
    stream: StreamConfig | None = None
    options: SensorOptions | None = None
    rig_serial: str = ""
    rig_role: str = ""

    def to_metadata(self) -> dict[str, str]:
        """The string record the recorder writes (inverse of :meth:`from_metadata`)."""
        out = {
            "serial": self.serial,
            "name": self.name,
            "firmware": self.firmware,
            "usb_type": self.usb_type,
        }
        if self.sync_mode is not None:
            out["sync_mode"] = str(int(self.sync_mode))
        if self.depth_scale_m is not None:
            out["depth_scale_m"] = repr(float(self.depth_scale_m))
        for prefix, value in (("stream", self.stream), ("options", self.options)):
            if value is not None:
                for f in dataclasses.fields(value):
                    out[f"{prefix}.{f.name}"] = str(getattr(value, f.name))
        if self.rig_serial:
            out["rig_serial"] = self.rig_serial
        if self.rig_role:
            out["rig_role"] = self.rig_role
        return out

    @classmethod
    def from_metadata(cls, serial: str, meta: Mapping[str, str], *, source: str) -> D415Settings:
        """Parse a ``device/d415/<serial>`` record (empty: nothing known but the serial).

        Raises:
            RecordingError: a value is malformed, or a ``stream.``/``options.`` group is
                incomplete (a renamed field is caught here, not silently defaulted).
        """
        what = f"{source}: device/d415/{serial}"
        groups: dict[str, dict[str, str]] = {"stream": {}, "options": {}}
        for key, value in meta.items():
            prefix, dot, name = key.partition(".")
            if dot and prefix in groups:
                groups[prefix][name] = value
        mode = meta.get("sync_mode")
        try:
            sync_mode = SyncMode(int(mode)) if mode not in (None, "") else None
            scale = meta.get("depth_scale_m")
            depth_scale = float(scale) if scale not in (None, "") else None
        except ValueError as err:
            msg = f"{what}: sync_mode {mode!r} / depth_scale_m is malformed ({err})"
            raise RecordingError(msg) from err
        return cls(
            serial=serial,
            name=meta.get("name", ""),
            firmware=meta.get("firmware", ""),
            usb_type=meta.get("usb_type", ""),
            sync_mode=sync_mode,
            depth_scale_m=depth_scale,
            stream=(
                _typed_dataclass(StreamConfig, groups["stream"], f"{what} stream.*")
                if groups["stream"]
                else None
            ),
            options=(
                _typed_dataclass(SensorOptions, groups["options"], f"{what} options.*")
                if groups["options"]
                else None
            ),
            rig_serial=meta.get("rig_serial", ""),
            rig_role=meta.get("rig_role", ""),
        )


@dataclass(frozen=True, slots=True)
class D415FrameIndex:
    """Every frame of one D415 in a recording, in receive order, no image decoded.

    All arrays have shape (F,). ``t_dev_ns`` is the device time of the frame (hardware
    ``sensor_timestamp``, middle of exposure, unwrapped once, × 1000); when the recording has no
    device stamps for the camera (``hardware_time`` False) it is the image stamp (host clock).
    ``sequence`` is the MCAP sequence that ties IR, depth and frame info of one capture.
    """

    device: DeviceId
    log_time_ns: npt.NDArray[np.int64] = field(repr=False)
    sequence: npt.NDArray[np.int64] = field(repr=False)
    frame_counter: npt.NDArray[np.int64] = field(repr=False)
    t_dev_ns: npt.NDArray[np.int64] = field(repr=False)
    depth_scale_m: float = 0.001
    hardware_time: bool = True

    def __len__(self) -> int:
        return int(self.sequence.size)


class RecordedD415:
    """One D415 of an open recording."""

    def __init__(self, rec: Recording, device: DeviceId | str) -> None:
        """``device``: a :class:`DeviceId` or a label/serial (``d415/123`` or ``123``).

        Raises:
            RecordingError: the recording has no such D415 (the message lists those it has).
        """
        dev = device if isinstance(device, DeviceId) else DeviceId.parse(device, kind="d415")
        if dev.kind != "d415":
            msg = f"{dev} is not a D415"
            raise ValidationError(msg)
        if dev.topic("ir") not in rec.channels:
            have = [d.label for d in d415_devices(rec)]
            msg = f"{rec.path}: no D415 {dev.label!r}; D415 cameras in it: {have or 'none'}"
            raise RecordingError(msg)
        self.rec = rec
        self.device = dev
        self._index: D415FrameIndex | None = None

    @property
    def label(self) -> str:
        return self.device.label

    def intrinsics(self) -> D415Intrinsics:
        """The first ``camera_info`` of the camera.

        Raises:
            RecordingError: no ``camera_info`` topic or message, or an uncalibrated one
                (``k[0] <= 0``).
        """
        topic = self.device.topic("camera_info")
        info: CameraCalibrationMsg | None = None
        if topic in self.rec.channels:
            info = next((p for _, p in self.rec.decoded(topic)), None)
        if info is None or not info.k or info.k[0] <= 0:
            msg = f"{self.rec.path}: {self.label} has no camera_info, so its intrinsics are unknown"
            raise RecordingError(msg)
        dist = np.zeros(5)
        d = np.asarray(info.d, dtype=np.float64)
        dist[: min(5, d.size)] = d[:5]
        k = np.asarray(info.k, dtype=np.float64).reshape(3, 3)
        return D415Intrinsics(int(info.width), int(info.height), k, dist)

    def settings(self) -> D415Settings:
        """The camera's typed settings from its metadata record (empty when not written)."""
        meta = self.rec.metadata().get(self.device.metadata_name, {})
        return D415Settings.from_metadata(self.device.serial, meta, source=str(self.rec.path))

    def frame_index(self) -> D415FrameIndex:
        """Every frame's log time, sequence, counter and device time (cached)."""
        if self._index is None:
            self._index = self._build_index()
        return self._index

    def _build_index(self) -> D415FrameIndex:
        fi_topic = self.device.topic("frame_info")
        rows: list[tuple[int, int, int, int | None, float]] = []
        if fi_topic in self.rec.channels:
            for m in self.rec.messages(fi_topic):
                fi: D415FrameInfo = m.decode()
                rows.append(
                    (
                        m.log_time_ns,
                        int(m.sequence) & 0xFFFFFFFF,
                        int(fi.frame_counter),
                        fi.sensor_timestamp_us,
                        float(fi.depth_scale_m),
                    )
                )
        scale = next((r[4] for r in rows if r[4] > 0), 0.001)
        if rows and all(r[3] is not None for r in rows):
            stamps = unwrap_u32(np.array([r[3] for r in rows], dtype=np.int64))
            return D415FrameIndex(
                self.device,
                np.array([r[0] for r in rows], dtype=np.int64),
                np.array([r[1] for r in rows], dtype=np.int64),
                np.array([r[2] for r in rows], dtype=np.int64),
                stamps * 1000,
                scale,
                True,
            )
        # No device stamps: the image stamps (host clock) of the IR topic stand in.
        log, seq, t = [], [], []
        for m in self.rec.messages(self.device.topic("ir")):
            log.append(m.log_time_ns)
            seq.append(int(m.sequence) & 0xFFFFFFFF)
            t.append(int(m.decode().timestamp_ns))
        _log.warning("%s: no device timestamps in frame_info; using the image stamps", self.label)
        seqs = np.array(seq, dtype=np.int64)
        return D415FrameIndex(
            self.device,
            np.array(log, dtype=np.int64),
            seqs,
            seqs.copy(),
            np.array(t, dtype=np.int64),
            scale,
            False,
        )

    def frame_info_at(self, start_ns: int | None = None) -> tuple[int, D415FrameInfo] | None:
        """``(log_time_ns, frame info)`` of the first frame logged at or after ``start_ns``
        (random access through the index; None past the end or without frame info)."""
        topic = self.device.topic("frame_info")
        if topic not in self.rec.channels:
            return None
        m = next(iter(self.rec.messages(topic, start_ns=start_ns)), None)
        return None if m is None else (m.log_time_ns, m.decode())

    def frame_sets(
        self,
        *,
        start_ns: int | None = None,
        end_ns: int | None = None,
        sequences: Iterable[int] | None = None,
    ) -> Iterator[FrameSet]:
        """The camera's frame sets with log time in ``[start_ns, end_ns)``, in file order.

        ``sequences``: only these MCAP sequences (from :meth:`frame_index`).
        """
        for rfs in read_frame_sets(
            self.rec,
            [self.device],
            start_ns=start_ns,
            end_ns=end_ns,
            sequences=None if sequences is None else {self.device: sequences},
        ):
            yield rfs.frames


def _timing(fi: D415FrameInfo) -> FrameTiming:
    # The recorder stores the member's name (HARDWARE_CLOCK); accept its value too.
    domain = TimestampDomain.__members__.get(fi.timestamp_domain)
    if domain is None:
        try:
            domain = TimestampDomain(fi.timestamp_domain)
        except ValueError:
            domain = TimestampDomain.SYSTEM_TIME
    return FrameTiming(
        frame_counter=int(fi.frame_counter),
        sensor_timestamp_us=fi.sensor_timestamp_us,
        frame_timestamp_us=fi.frame_timestamp_us,
        time_of_arrival_ms=fi.time_of_arrival_ms,
        timestamp_domain=domain,
        host_time_ns=int(fi.host_time_ns),
        timestamp_ms=float(fi.timestamp_ms),
    )


def _host_timing(img: ImageMsg, sequence: int) -> FrameTiming:
    return FrameTiming(
        frame_counter=sequence,
        sensor_timestamp_us=None,
        frame_timestamp_us=None,
        time_of_arrival_ms=None,
        timestamp_domain=TimestampDomain.SYSTEM_TIME,
        host_time_ns=int(img.timestamp_ns),
    )


def frame_timings(
    rec: Recording, cameras: Sequence[DeviceId] | None = None
) -> Iterator[tuple[DeviceId, FrameTiming]]:
    """Every D415 frame's timing (its frame info, device stamps not unwrapped), no image
    decoded, across ``cameras`` (default: all) in file order; cameras without frame info are
    skipped."""
    cams = d415_devices(rec) if cameras is None else list(cameras)
    by_topic = {d.topic("frame_info"): d for d in cams if d.topic("frame_info") in rec.channels}
    if not by_topic:
        return
    for m in rec.messages(sorted(by_topic)):
        yield by_topic[m.topic], _timing(m.decode())


class RecordedFrameSet(NamedTuple):
    """A frame set as recorded: its log time (ns, host) and MCAP sequence beside the frames."""

    log_time_ns: int
    sequence: int
    frames: FrameSet


def read_frame_sets(
    rec: Recording,
    cameras: Sequence[DeviceId],
    *,
    start_ns: int | None = None,
    end_ns: int | None = None,
    sequences: Mapping[DeviceId, Iterable[int]] | None = None,
) -> Iterator[RecordedFrameSet]:
    """The frame sets of several D415s in one pass over the file, in file order.

    IR, depth and frame info of one capture share the MCAP sequence; a set is yielded when its
    last part arrives (the depth scale is that frame's, or the camera's recorded one). A camera
    without frame info (an imported file) gets host timing from the image stamps.
    ``sequences`` restricts a camera to those sequences (others are skipped undecoded).
    """
    wanted = {
        d: None if sequences is None or d not in sequences else set(sequences[d]) for d in cameras
    }
    by_topic: dict[str, tuple[DeviceId, str]] = {}
    has_info: dict[DeviceId, bool] = {}
    scale: dict[DeviceId, float] = {}
    meta = rec.metadata()
    for dev in cameras:
        if dev.topic("ir") not in rec.channels:
            have = [d.label for d in d415_devices(rec)]
            msg = f"{rec.path}: no D415 {dev.label!r}; D415 cameras in it: {have or 'none'}"
            raise RecordingError(msg)
        for stream in ("ir", "depth", "frame_info"):
            if dev.topic(stream) in rec.channels:
                by_topic[dev.topic(stream)] = (dev, stream)
        has_info[dev] = dev.topic("frame_info") in rec.channels
        recorded = meta.get(dev.metadata_name, {}).get("depth_scale_m")
        try:
            scale[dev] = float(recorded) if recorded else 0.001
        except ValueError:
            scale[dev] = 0.001
    need = {d: ({"ir", "depth", "frame_info"} if has_info[d] else {"ir", "depth"}) for d in cameras}
    pending: dict[tuple[DeviceId, int], dict[str, Any]] = {}
    for m in rec.messages(sorted(by_topic), start_ns=start_ns, end_ns=end_ns):
        dev, stream = by_topic[m.topic]
        seq = int(m.sequence) & 0xFFFFFFFF
        keep = wanted[dev]
        if keep is not None and seq not in keep:
            continue
        key = (dev, seq)
        slot = pending.setdefault(key, {})
        slot[stream] = m.decode()
        if not need[dev] <= slot.keys():
            continue
        del pending[key]
        ir: ImageMsg = slot["ir"]
        depth: ImageMsg = slot["depth"]
        fi: D415FrameInfo | None = slot.get("frame_info")
        timing = _host_timing(ir, seq) if fi is None else _timing(fi)
        s = fi.depth_scale_m if fi is not None and fi.depth_scale_m > 0 else scale[dev]
        yield RecordedFrameSet(
            m.log_time_ns,
            seq,
            FrameSet(
                dev.serial,
                D415Frame(StreamKind.INFRARED_LEFT, ir.image, timing),
                D415Frame(StreamKind.DEPTH, depth.image, timing),
                s,
            ),
        )


# ---------------------------------------------------------------------------------------------
# DAVIS


@dataclass(frozen=True, slots=True)
class DavisFrame:
    """One APS frame: ``image`` (H, W) uint16, exposure middle ``t_ns`` on the DAVIS timebase,
    and its frame info (exposure start/end...) when recorded."""

    log_time_ns: int
    t_ns: int
    image: npt.NDArray[np.uint16] = field(repr=False)
    info: DavisFrameInfo | None = None


class RecordedDavis:
    """One DAVIS of an open recording; times are DAVIS µs/ns since its timestamp reset.

    The decoder stamps every event, IMU sample, frame and trigger on one 64-bit timebase (the
    wrap words are unwrapped at decode time, ``davis240c-usb.md`` §7), so nothing is unwrapped
    here; ``start_ns``/``end_ns`` select by log time.
    """

    def __init__(self, rec: Recording, device: DeviceId | str) -> None:
        dev = device if isinstance(device, DeviceId) else DeviceId.parse(device, kind="davis")
        if dev.kind != "davis":
            msg = f"{dev} is not a DAVIS"
            raise ValidationError(msg)
        if not any(dev.topic(s) in rec.channels for s in _DAVIS_STREAMS):
            have = [d.label for d in davis_devices(rec)]
            msg = f"{rec.path}: no DAVIS {dev.label!r}; DAVIS cameras in it: {have or 'none'}"
            raise RecordingError(msg)
        self.rec = rec
        self.device = dev

    def has(self, stream: str) -> bool:
        """Whether the recording holds this stream (``events``, ``frame``, ``imu``, ``trigger``)."""
        return self.device.topic(stream) in self.rec.channels

    def count(self, stream: str) -> int:
        """Messages of one stream (0 when it is not recorded), counted without decoding."""
        if not self.has(stream):
            return 0
        return sum(1 for _ in self.rec.messages(self.device.topic(stream)))

    def settings(self) -> dict[str, str]:
        """The register settings the recorder wrote (``settings/davis/<serial>``), as stored:
        ``MODULE.PARAMETER`` keys of the logic's configuration map (``davis240c-usb.md``)."""
        return dict(self.rec.metadata().get(self.device.settings_name, {}))

    def events(self, *, start_ns: int | None = None, end_ns: int | None = None) -> Any:
        """Events as one :data:`~acquire.events.EVENT_DTYPE` array (t µs), file order."""
        if not self.has("events"):
            return np.empty(0, EVENT_DTYPE)
        return self.rec.events(self.device.topic("events"), start_ns=start_ns, end_ns=end_ns)

    def imu(self, *, start_ns: int | None = None, end_ns: int | None = None) -> Any:
        """IMU samples as one ``IMU_DTYPE`` array (t µs)."""
        if not self.has("imu"):
            return np.empty(0, IMU_DTYPE)
        return self.rec.imu(self.device.topic("imu"), start_ns=start_ns, end_ns=end_ns)

    def triggers(self, *, start_ns: int | None = None, end_ns: int | None = None) -> Any:
        """Special events (trigger input edges, timestamp resets) as one ``SPECIAL_DTYPE`` array."""
        if not self.has("trigger"):
            return np.empty(0, SPECIAL_DTYPE)
        return self.rec.triggers(self.device.topic("trigger"), start_ns=start_ns, end_ns=end_ns)

    def frames(
        self, *, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[DavisFrame]:
        """APS frames in file order, each with its frame info (same MCAP sequence) when present."""
        if not self.has("frame"):
            return
        topics = [self.device.topic("frame")]
        info_topic = self.device.topic("frame_info")
        if info_topic in self.rec.channels:
            topics.append(info_topic)
        pending: dict[int, dict[str, Any]] = {}
        for m in self.rec.messages(topics, start_ns=start_ns, end_ns=end_ns):
            slot = pending.setdefault(int(m.sequence), {})
            slot[m.topic] = (m.log_time_ns, m.decode())
            if len(slot) < len(topics):
                continue
            del pending[int(m.sequence)]
            log_ns, img = slot[topics[0]]
            info = slot[info_topic][1] if len(topics) == 2 else None
            yield DavisFrame(log_ns, int(img.timestamp_ns), img.image, info)

    def external_edges_ns(self, *, pulse_us: float = 0.0) -> tuple[npt.NDArray[np.int64], str]:
        """Rising edges of the trigger input after the last timestamp reset, DAVIS ns, unique.

        Rising-edge events are used as they are; when the input detector reports whole pulses
        only (stamped at the trailing edge) they are moved back by ``pulse_us``. Returns the
        edges and, when there are none, why.
        """
        from mocaprig.acquire.davis240c_decode import SpecialType

        sp = self.triggers()
        if not sp.size:
            return np.zeros(0, dtype=np.int64), "its trigger topic holds no special events"
        ty = sp["type"].astype(np.int64)
        tus = sp["t"].astype(np.int64)
        resets = np.flatnonzero(ty == int(SpecialType.TIMESTAMP_RESET))
        start = int(resets[-1]) + 1 if resets.size else 0
        ty, tus = ty[start:], tus[start:]
        rising = tus[ty == int(SpecialType.EXTERNAL_INPUT_RISING_EDGE)]
        if rising.size:
            return np.unique(rising * 1000), ""
        pulses = tus[ty == int(SpecialType.EXTERNAL_INPUT_PULSE)]
        if pulses.size:
            return np.unique(pulses * 1000 - round(pulse_us * 1000.0)), ""
        return (
            np.zeros(0, dtype=np.int64),
            "its trigger topic holds no external-input edges after the last reset",
        )


# ---------------------------------------------------------------------------------------------
# Sync box


def sync_pulses(rec: Recording) -> list[tuple[int, SyncPulses]]:
    """``(log_time_ns, SyncPulses)`` of the sync box, in file order (empty without a box)."""
    topic = DeviceId("syncbox").topic("pulses")
    if topic not in rec.channels:
        return []
    return list(rec.decoded(topic))
