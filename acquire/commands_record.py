"""``mocaprig record | info | recover | export | import-events``: the recording commands.

Each ``register_*`` function is a ``mocaprig.commands`` entry point; each command is a typed
function returning an exit code. Device modules are imported lazily.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import decimal
import itertools
import logging
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal, TextIO

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.events import check_events, make_events
from mocaprig.acquire.recorder import (
    Attachment,
    Recorder,
    StreamSource,
    record_sources,
    stop_on_signals,
)
from mocaprig.acquire.recording_format import (
    MAX_EVENT_PACKET_SPAN_US,
    CameraCalibrationMsg,
    D415FrameInfo,
    DavisFrameInfo,
    EventPacket,
    ImageMsg,
    ImuPacket,
    RecorderStatus,
    StreamStatus,
    SyncPulses,
    TriggerPacket,
    split_events,
    topic,
)
from mocaprig.acquire.rig_file import RigFile, load_rig_file
from mocaprig.cli import add_json_flag, emit_json
from mocaprig.errors import DeviceError, RecordingError, ValidationError
from mocaprig.validation import check_range

__all__ = [
    "DavisSource",
    "DepthCameraSource",
    "RecordingSummary",
    "RpgEventText",
    "SyncBoxSource",
    "export",
    "export_events_txt",
    "import_events",
    "read_events_txt",
    "record",
    "record_to_file",
    "recording_info",
    "recover_command",
    "register_export",
    "register_import_events",
    "register_info",
    "register_record",
    "register_recover",
]

_log = logging.getLogger(__name__)

ExportFormat = Literal["npz", "txt", "png", "mp4"]
_Sub = "argparse._SubParsersAction[argparse.ArgumentParser]"


# -------------------------------------------------------------------------------------------
# Sources: real drivers (or their mocks) -> recorder


class DavisSource:
    """A DAVIS240C (:class:`acquire.davis240c.Davis240C`, opened) as a :class:`StreamSource`.

    Topics: ``/davis/<serial>/{events,frame,frame_info,imu,trigger}``.

    Keyword options:
        events_per_packet_max: Split larger event packets.
        manage_streaming: ``run`` starts the camera and stops it at the end (default); with
            ``False`` the caller has started it and stops it after ``run`` returned.
        dvs: ``False`` switches the DVS module off after the start (register DVS RUN = 0, a
            real device configuration): APS frames, IMU and the external input keep running.
        offline: The camera is a simulated device paced as fast as possible: messages go in
            with :meth:`Recorder.put_wait` (back-pressure instead of drops) and the source ends
            at ``end_t_us`` (device µs) or when the stream ends.
        end_t_us: Offline end: stop after the first packet reaching this device time (µs).
    """

    def __init__(
        self,
        cam: Any,
        *,
        events_per_packet_max: int = 200_000,
        manage_streaming: bool = True,
        dvs: bool = True,
        offline: bool = False,
        end_t_us: int | None = None,
    ) -> None:
        self.cam = cam
        self.manage_streaming = manage_streaming
        self.dvs = dvs
        self.offline = offline
        self.end_t_us = end_t_us
        self.serial: str = cam.serial
        self.name = f"davis/{self.serial}"
        self.frame_id = f"davis_{self.serial}"
        self._max = events_per_packet_max
        info = cam.info
        self.width: int = int(info.dvs_size_x)
        self.height: int = int(info.dvs_size_y)
        self.metadata: dict[str, dict[str, str]] = {
            f"device/{self.name}": {k: str(v) for k, v in info.as_dict().items()},
            f"settings/{self.name}": {**_davis_settings(cam), "dvs.run": str(dvs).lower()},
        }
        self._h: dict[str, Any] = {}

    def declare(self, recorder: Recorder) -> None:
        meta = {"serial": self.serial, "device": "DAVIS240C", "frame_id": self.frame_id}
        for stream, cls, kw in (
            ("events", EventPacket, {}),
            ("frame", ImageMsg, {"queue_messages": 256}),
            ("frame_info", DavisFrameInfo, {}),
            ("imu", ImuPacket, {}),
            ("trigger", TriggerPacket, {}),
        ):
            self._h[stream] = recorder.add_stream(
                topic("davis", self.serial, stream), cls, metadata=meta, **kw
            )

    def run(self, recorder: Recorder, stop: threading.Event) -> None:
        cam = self.cam
        if self.manage_streaming:
            cam.start()
            if not self.dvs:
                from mocaprig.acquire.davis240c_config import DvsParam, Module

                cam.config_set(Module.DVS, DvsParam.RUN, 0)
        put = recorder.put_wait if self.offline else recorder.put
        seq = {"events": 0, "frame": 0, "imu": 0, "trigger": 0}
        h = self._h
        try:
            while not stop.is_set():
                pkt = cam.get_packet(timeout_s=0.1)
                if pkt is None:
                    if self.offline and not cam.running:
                        break  # the simulated device ended (or failed: stats are logged)
                    continue
                t = pkt.host_time_ns or None
                if pkt.events.size:
                    for ev in _chunks(pkt.events, self._max):
                        for part in split_events(ev):
                            p = EventPacket(
                                part, self.width, self.height, seq["events"], self.frame_id
                            )
                            put(h["events"], p, log_time_ns=t, sequence=seq["events"])
                            seq["events"] += 1
                for fr in pkt.frames:
                    n = seq["frame"]
                    img = ImageMsg(fr.pixels_16bit, "mono16", fr.t_us * 1000, self.frame_id)
                    put(h["frame"], img, log_time_ns=t, sequence=n)
                    fi = DavisFrameInfo(
                        n,
                        fr.t_start_frame_us,
                        fr.t_end_frame_us,
                        fr.t_start_exposure_us,
                        fr.t_end_exposure_us,
                        fr.exposure_cycles,
                        fr.position_x,
                        fr.position_y,
                        fr.global_shutter,
                        self.frame_id,
                    )
                    put(h["frame_info"], fi, log_time_ns=t, sequence=n)
                    seq["frame"] += 1
                if pkt.imu.size:
                    imu = ImuPacket(pkt.imu, seq["imu"], self.frame_id)
                    put(h["imu"], imu, log_time_ns=t, sequence=seq["imu"])
                    seq["imu"] += 1
                if pkt.specials.size:
                    tr = TriggerPacket(pkt.specials, seq["trigger"], self.frame_id)
                    put(h["trigger"], tr, log_time_ns=t, sequence=seq["trigger"])
                    seq["trigger"] += 1
                if self.end_t_us is not None and _packet_end_us(pkt) >= self.end_t_us:
                    break
        finally:
            if self.manage_streaming:
                cam.stop()
            stats = cam.stats()
            recorder.log(
                "INFO",
                f"DAVIS {self.serial} driver counters: packets dropped {stats.packets_dropped}, "
                f"events dropped {stats.events_dropped}, raw bytes dropped "
                f"{stats.raw_bytes_dropped}",
                name=self.name,
            )


def _davis_settings(cam: Any) -> dict[str, str]:
    """Biases and module settings as written to the camera (strings, for MCAP metadata)."""
    settings = cam.settings
    out = {f"bias.{getattr(k, 'name', k)}": str(v) for k, v in settings.biases.items()}
    for section in ("aps", "imu", "ext_input"):
        value = getattr(settings, section, None)
        if value is not None and dataclasses.is_dataclass(value):
            for f in dataclasses.fields(value):
                out[f"{section}.{f.name}"] = str(getattr(value, f.name))
    out["early_packet_delay_125us"] = str(settings.early_packet_delay_125us)
    return out


def _packet_end_us(pkt: Any) -> int:
    """The latest device time (µs) a DAVIS packet carries (-1 when it carries none)."""
    latest = -1
    for arr in (pkt.events, pkt.imu, pkt.specials):
        if arr.size:
            latest = max(latest, int(arr["t"][-1]))
    for fr in pkt.frames:
        latest = max(latest, int(fr.t_us))
    return latest


def _chunks(arr: npt.NDArray[Any], n: int) -> list[npt.NDArray[Any]]:
    return [arr[i : i + n] for i in range(0, arr.size, n)] if arr.size > n else [arr]


class DepthCameraSource:
    """A D415 (:class:`mocaprig.acquire.depth_camera.DepthCamera`, configured) as a stream source.

    Topics: ``/d415/<serial>/{ir,depth,frame_info,camera_info}``; ``camera_info`` is written
    once at start (and is the same for IR and depth on a D415).
    """

    def __init__(
        self,
        cam: Any,
        *,
        stream: Any = None,
        options: Any = None,
        manage_streaming: bool = True,
        offline: bool = False,
    ) -> None:
        """``stream``/``options``: the StreamConfig and SensorOptions the camera was configured
        with, stored in its metadata record (mode, exposure, gain, laser power).

        ``manage_streaming``: ``run`` starts and stops the camera (default); ``False``: the
        caller does (e.g. to start every camera of a simulated rig at the same instant).
        ``offline``: a simulated camera paced as fast as possible: messages go in with
        :meth:`Recorder.put_wait` (back-pressure, no drops) and ``poll() -> None`` means the
        simulated session is over (the source ends)."""
        self.cam = cam
        self.manage_streaming = manage_streaming
        self.offline = offline
        cinfo = cam.info
        self.serial: str = cinfo.serial
        self.name = f"d415/{self.serial}"
        self.frame_id = f"d415_{self.serial}"
        self.metadata: dict[str, dict[str, str]] = {
            f"device/{self.name}": {
                "serial": cinfo.serial,
                "name": cinfo.name,
                "firmware": cinfo.firmware,
                "usb_type": cinfo.usb_type,
                "sync_mode": str(int(cam.sync_mode)),
                "depth_scale_m": repr(float(cam.depth_scale_m)),
            }
        }
        for prefix, value in (("stream", stream), ("options", options)):
            if value is not None and dataclasses.is_dataclass(value):
                for f in dataclasses.fields(value):
                    self.metadata[f"device/{self.name}"][f"{prefix}.{f.name}"] = str(
                        getattr(value, f.name)
                    )
        self._h: dict[str, Any] = {}

    def declare(self, recorder: Recorder) -> None:
        meta = {"serial": self.serial, "device": "D415", "frame_id": self.frame_id}
        for stream, cls, q in (
            ("ir", ImageMsg, 64),
            ("depth", ImageMsg, 64),
            ("frame_info", D415FrameInfo, 1024),
            ("camera_info", CameraCalibrationMsg, 16),
        ):
            self._h[stream] = recorder.add_stream(
                topic("d415", self.serial, stream), cls, metadata=meta, queue_messages=q
            )

    def run(self, recorder: Recorder, stop: threading.Event) -> None:
        cam, h = self.cam, self._h
        if self.manage_streaming:
            cam.start()
        put = recorder.put_wait if self.offline else recorder.put
        try:
            k = cam.intrinsics()
            calib = CameraCalibrationMsg(
                int(k.width),
                int(k.height),
                (k.fx, 0.0, k.ppx, 0.0, k.fy, k.ppy, 0.0, 0.0, 1.0),
                tuple(float(c) for c in getattr(k, "coeffs", ())),
                "plumb_bob",
                self.frame_id,
            )
            put(h["camera_info"], calib)
            while not stop.is_set():
                fs = cam.poll(0.1)
                if fs is None:
                    if self.offline:
                        break  # the simulated session is over: no frame will come
                    continue
                tm = fs.timing
                n = int(tm.frame_counter)
                stamp = (
                    tm.sensor_timestamp_us * 1000
                    if tm.sensor_timestamp_us is not None
                    else tm.host_time_ns
                )
                # log_time: the recorder's host clock at receive (the camera's host_time_ns is
                # monotonic, or simulated in a mock; it is kept in frame_info).
                t = recorder.clock_ns()
                ir = ImageMsg(fs.infrared.image, "mono8", stamp, self.frame_id)
                depth = ImageMsg(fs.depth.image, "16UC1", stamp, self.frame_id)
                put(h["ir"], ir, log_time_ns=t, sequence=n)
                put(h["depth"], depth, log_time_ns=t, sequence=n)
                info = D415FrameInfo(
                    n,
                    tm.sensor_timestamp_us,
                    tm.frame_timestamp_us,
                    tm.time_of_arrival_ms,
                    str(tm.timestamp_domain.name),
                    float(tm.timestamp_ms),
                    int(tm.host_time_ns),
                    float(fs.depth_scale_m),
                    self.frame_id,
                )
                put(h["frame_info"], info, log_time_ns=t, sequence=n)
        finally:
            if self.manage_streaming:
                cam.stop()


class SyncBoxSource:
    """A sync box (:class:`mocaprig.acquire.syncbox.SyncBox`, opened) as a stream source.

    Topic ``/syncbox/pulses``: one message per ``PULSES`` report. ``mode`` ``listen`` counts
    the D415 master's pulses; ``generate`` drives the trigger at ``hz``.
    """

    def __init__(
        self,
        box: Any,
        *,
        mode: Literal["listen", "generate"] = "listen",
        hz: int = 30,
        width_us: int = 100,
        report_interval_ms: int = 200,
    ) -> None:
        self.box = box
        self.name = "syncbox"
        self.mode = mode
        self.hz = hz
        self.width_us = width_us
        self.report_interval_ms = report_interval_ms
        ident = box.identity
        self.metadata: dict[str, dict[str, str]] = {
            "device/syncbox": {
                "port": str(box.port),
                "protocol_version": str(getattr(ident, "version", "")),
                "board": str(getattr(ident, "board", "")),
                "mode": mode,
                "hz": str(hz) if mode == "generate" else "",
                "width_us": str(width_us) if mode == "generate" else "",
                "report_interval_ms": str(report_interval_ms),
            }
        }
        self._h: Any = None

    def declare(self, recorder: Recorder) -> None:
        self._h = recorder.add_stream(
            topic("syncbox", "", "pulses"), SyncPulses, metadata={"device": "syncbox"}
        )

    def run(self, recorder: Recorder, stop: threading.Event) -> None:
        box = self.box
        box.set_report_interval(self.report_interval_ms)
        if self.mode == "generate":
            box.start(hz=self.hz, width_us=self.width_us)
        else:
            box.listen()
        mode = self.mode.upper() if self.mode == "listen" else "GENERATE"
        n = 0
        try:
            while not stop.is_set():
                for rep in box.read_reports(0.1):
                    msg = SyncPulses(
                        rep.count, rep.t_us, mode, "syncbox", rep.total, rep.host_time_ns
                    )
                    recorder.put(self._h, msg, sequence=n)
                    n += 1
        finally:
            count = box.stop()
            recorder.log("INFO", f"sync box run ended with {count} pulses", name=self.name)


# -------------------------------------------------------------------------------------------
# record


class _StatusLine:
    """Live status on stderr (terminal only): per-stream rate and drops, MB/s, free disk."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self._out = sys.stderr if stream is None else stream
        self._on = self._out.isatty()
        self._last: tuple[float, RecorderStatus] | None = None

    def __call__(self, st: RecorderStatus) -> None:
        now = time.monotonic()
        prev = self._last
        self._last = (now, st)
        if not self._on or prev is None:
            return
        dt = max(now - prev[0], 1e-6)
        before = {s.topic: s.written for s in prev[1].streams}
        parts = []
        for s in st.streams:
            if s.topic in ("/diagnostics", "/log"):
                continue
            rate = (s.written - before.get(s.topic, 0)) / dt
            short = s.topic.rsplit("/", 2)
            parts.append(f"{short[-2]}/{short[-1]} {rate:.0f}/s d{s.dropped}")
        mbps = (st.bytes_written - prev[1].bytes_written) / dt / 1e6
        line = (
            f"{st.elapsed_ns / 1e9:6.1f}s {mbps:6.1f} MB/s free {st.free_disk_bytes / 1e9:.1f} GB "
            f"drops {st.dropped_total} | " + "  ".join(parts)
        )
        self._out.write("\r" + line[:200].ljust(200))
        self._out.flush()

    def done(self) -> None:
        if self._on:
            self._out.write("\n")
            self._out.flush()


def _mock_sources(
    *,
    scenario: str,
    seed: int,
    seconds: float,
    cameras: int,
    syncbox: bool,
    stack: list[tuple[str, Any]],
) -> list[StreamSource]:
    from mocaprig.acquire.davis240c import Davis240C, load_mock_backend
    from mocaprig.acquire.depth_camera import SensorOptions, StreamConfig, SyncMode, open_cameras

    sources: list[StreamSource] = []
    # "asap": the DAVIS simulator cannot render in real time on a small machine.
    backend = load_mock_backend(scenario=scenario, seed=seed, pacing="asap", seconds=seconds + 5.0)
    cam = Davis240C.open(backend=backend)
    stack.append(("davis/" + cam.serial, cam))
    sources.append(DavisSource(cam))
    if cameras > 0:
        d415s = open_cameras(
            "mock", scenario=scenario, seed=seed, count=cameras, pacing="realtime",
            seconds=seconds + 5.0,
        )  # fmt: skip
        for i, d in enumerate(d415s):
            stack.append(("d415/" + d.info.serial, d))
            mode, opts = StreamConfig(), SensorOptions()
            d.configure(
                stream=mode,
                options=opts,
                sync_mode=SyncMode.MASTER if i == 0 else SyncMode.SLAVE,
            )
            sources.append(DepthCameraSource(d, stream=mode, options=opts))
    if syncbox:
        from mocaprig.acquire.syncbox import SyncBox, open_mock_syncbox

        mock_box = open_mock_syncbox(seed=seed)
        stack.append(("syncbox-mock", mock_box))
        box = SyncBox(mock_box.port)
        box.open()
        stack.append(("syncbox", box))
        sources.append(SyncBoxSource(box))
    return sources


_MOCK_D415_MAX = 4  # cameras of the simulated rig


def _rig_sources(
    rig: RigFile,
    *,
    scenario: str,
    seed: int,
    seconds: float,
    stack: list[tuple[str, Any]],
) -> list[StreamSource]:
    """Open the devices ``rig`` lists (real ones, or the simulated rig's mocks when
    ``rig.mock``), configured as the file says; opened devices go on ``stack`` (the caller
    closes them, also when this raises).

    Raises:
        DeviceError: a listed device is not connected (the message lists what is) or cannot be
            opened.
        ValidationError: a mock rig file asks for more cameras than the simulated rig has.
    """
    from mocaprig.acquire import davis240c, depth_camera
    from mocaprig.acquire.depth_camera import SyncMode

    sources: list[StreamSource] = []
    if rig.davis is not None:
        entry = rig.davis
        if rig.mock:
            backend = davis240c.load_mock_backend(
                scenario=scenario, seed=seed, pacing="asap", serial=entry.serial,
                seconds=seconds + 5.0,
            )  # fmt: skip
            cam = davis240c.Davis240C.open(backend=backend, bias_preset=entry.bias_preset)
        else:
            found = davis240c.find_davis()
            serials = sorted(d.serial or "?" for d in found)
            if entry.serial not in serials:
                msg = (
                    f"DAVIS {entry.serial} listed in {rig.source} is not connected; connected: "
                    f"{serials}; run `mocaprig devices`"
                )
                raise DeviceError(msg)
            cam = davis240c.Davis240C.open(serial=entry.serial, bias_preset=entry.bias_preset)
        stack.append(("davis/" + cam.serial, cam))
        sources.append(DavisSource(cam))
    if rig.d415:
        if rig.mock:
            if len(rig.d415) > _MOCK_D415_MAX:
                msg = (
                    f"{rig.source} lists {len(rig.d415)} D415s but the simulated rig has "
                    f"{_MOCK_D415_MAX}; list at most {_MOCK_D415_MAX} with mock = true"
                )
                raise ValidationError(msg)
            found_cams = depth_camera.open_cameras(
                "mock", scenario=scenario, seed=seed, count=len(rig.d415), pacing="realtime",
                seconds=seconds + 5.0,
            )  # fmt: skip
            # The mocks carry the simulated rig's serials: rig-file cameras map onto them in
            # order (the rig-file serial is kept in the device metadata as rig_serial).
            pairs = list(zip(rig.d415, found_cams, strict=True))
        else:
            found_cams = depth_camera.open_cameras("realsense")
            by_serial = {c.info.serial: c for c in found_cams}
            missing = [e.serial for e in rig.d415 if e.serial not in by_serial]
            if missing:
                for c in found_cams:
                    c.close()
                msg = (
                    f"D415 {', '.join(missing)} listed in {rig.source} is not connected; "
                    f"connected: {sorted(by_serial)}; run `mocaprig devices`"
                )
                raise DeviceError(msg)
            wanted = {e.serial for e in rig.d415}
            for c in found_cams:
                if c.info.serial not in wanted:
                    c.close()
            pairs = [(e, by_serial[e.serial]) for e in rig.d415]
        for _, d in pairs:
            stack.append(("d415/" + d.info.serial, d))
        # Slaves first: a slave configured after the master could miss its first pulses.
        for e, d in sorted(pairs, key=lambda p: p[0].role == "master"):
            mode = SyncMode.MASTER if e.role == "master" else SyncMode.SLAVE
            d.configure(stream=e.stream, options=e.options, sync_mode=mode)
        for e, d in pairs:
            src = DepthCameraSource(d, stream=e.stream, options=e.options)
            src.metadata[f"device/{src.name}"]["rig_serial"] = e.serial
            src.metadata[f"device/{src.name}"]["rig_role"] = e.role
            sources.append(src)
    if rig.syncbox is not None:
        from mocaprig.acquire.syncbox import SyncBox, open_mock_syncbox

        sb = rig.syncbox
        if rig.mock:
            # The simulated master's pulses: its frame rate (or the file's rate without one).
            master = rig.master
            listen_hz = float(master.stream.fps if master is not None else sb.rate_hz)
            mock_box = open_mock_syncbox(seed=seed, listen_hz=listen_hz)
            stack.append(("syncbox-mock", mock_box))
            port = str(mock_box.port)
        else:
            port = sb.port
        box = SyncBox(port)
        try:
            box.open()
        except DeviceError as err:
            msg = f"sync box on {port} listed in {rig.source} cannot be opened: {err}"
            raise DeviceError(msg) from err
        stack.append(("syncbox", box))
        sources.append(SyncBoxSource(box, mode=sb.mode, hz=sb.rate_hz, width_us=sb.width_us))
    return sources


@dataclasses.dataclass(frozen=True, slots=True)
class RecordingSummary:
    """What :func:`record_to_file` recorded.

    Attributes:
        files: The file(s) written (several when split).
        stop_reason: Why the recording ended (:class:`mocaprig.acquire.recorder.StopReason` value).
        seconds: Host time recorded (s).
        bytes: Bytes written.
        drops_total: Messages dropped, all streams.
        streams: Final per-stream counters.
        hung_sources: Sources whose thread did not stop (their devices must not be closed).
    """

    files: tuple[Path, ...]
    stop_reason: str | None
    seconds: float
    bytes: int
    drops_total: int
    streams: tuple[StreamStatus, ...]
    hung_sources: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (what ``record --json`` prints)."""
        return {
            "files": [str(p) for p in self.files],
            "stop_reason": self.stop_reason,
            "seconds": self.seconds,
            "bytes": self.bytes,
            "drops_total": self.drops_total,
            "streams": [
                {"topic": s.topic, "messages": s.written, "drops": s.dropped} for s in self.streams
            ],
        }


def record_to_file(
    out: Path,
    sources: Sequence[StreamSource],
    *,
    seconds: float | None,
    followers: Sequence[StreamSource] = (),
    metadata: dict[str, dict[str, str]] | None = None,
    attachments: Sequence[Attachment] = (),
    compression: Literal["zstd", "lz4", "none"] = "lz4",
    split_seconds: float | None = None,
    split_mb: float | None = None,
    min_free_mb: float = 512.0,
    status_line: bool = False,
    handle_signals: bool = False,
) -> RecordingSummary:
    """Record ``sources`` (and ``followers``, see :func:`acquire.recorder.record_sources`) into
    ``out`` for ``seconds`` (``None``: until every source ends, for offline sources).

    The sources' ``metadata`` attributes are added to ``metadata``. Devices are not closed here.

    Raises:
        RecordingError: ``out`` exists, cannot be written, or the recording stopped early
            (disk full, write error; the file is finished and readable).
    """
    meta = dict(metadata or {})
    for src in [*sources, *followers]:
        meta.update(getattr(src, "metadata", {}) or {})
    recorder = Recorder(
        out,
        compression=compression,
        split_seconds=split_seconds,
        split_bytes=None if split_mb is None else int(split_mb * 1e6),
        min_free_disk_bytes=int(min_free_mb * 1e6),
        metadata=meta,
        attachments=attachments,
    )
    status = _StatusLine() if status_line else None
    guard = stop_on_signals(recorder) if handle_signals else contextlib.nullcontext()
    with recorder, guard:
        hung = record_sources(
            recorder, sources, seconds=seconds, on_status=status, followers=followers
        )
    if status is not None:
        status.done()
    final = recorder.status()
    return RecordingSummary(
        files=recorder.files,
        stop_reason=recorder.stop_reason.value if recorder.stop_reason else None,
        seconds=final.elapsed_ns / 1e9,
        bytes=final.bytes_written,
        drops_total=final.dropped_total,
        streams=final.streams,
        hung_sources=hung,
    )


def record(
    *,
    out: Path,
    seconds: float,
    mock: bool,
    rig: Path | None,
    scenario: str = "default",
    seed: int = 0,
    cameras: int = 1,
    syncbox: bool = True,
    compression: Literal["zstd", "lz4", "none"] = "lz4",
    split_seconds: float | None = None,
    split_mb: float | None = None,
    min_free_mb: float = 512.0,
    as_json: bool = False,
    sources: Sequence[StreamSource] | None = None,
) -> int:
    """``mocaprig record``: record the rig (a rig file's devices, the mock rig, or given
    ``sources``) into ``out``.

    Returns 0 when the recording ended as asked (stopping early raises RecordingError).
    """
    if seconds <= 0:
        msg = f"--seconds must be > 0, got {seconds}"
        raise ValidationError(msg)
    stack: list[tuple[str, Any]] = []
    summary: RecordingSummary | None = None
    metadata: dict[str, dict[str, str]] = {}
    attachments: list[Attachment] = []
    try:
        if sources is None:
            if rig is not None:
                rig_file = load_rig_file(rig)
                sources = _rig_sources(
                    rig_file, scenario=scenario, seed=seed, seconds=seconds, stack=stack
                )
                metadata["rig"] = rig_file.metadata()
                metadata["session"] = {
                    "mock": str(rig_file.mock).lower(),
                    "rig_file": str(rig),
                    "name": rig_file.session_name,
                    "notes": rig_file.session_notes,
                    **({"scenario": scenario, "seed": str(seed)} if rig_file.mock else {}),
                }
                attachments.append(
                    Attachment("rig.toml", "application/toml", rig_file.text.encode("utf-8"))
                )
            elif not mock:
                msg = "say what to record: --mock (simulated rig) or --rig RIG.toml"
                raise ValidationError(msg)
            else:
                sources = _mock_sources(
                    scenario=scenario,
                    seed=seed,
                    seconds=seconds,
                    cameras=cameras,
                    syncbox=syncbox,
                    stack=stack,
                )
                metadata["session"] = {"mock": "true", "scenario": scenario, "seed": str(seed)}
        summary = record_to_file(
            out,
            sources,
            seconds=seconds,
            metadata=metadata,
            attachments=attachments,
            compression=compression,
            split_seconds=split_seconds,
            split_mb=split_mb,
            min_free_mb=min_free_mb,
            status_line=True,
            handle_signals=True,
        )
    finally:
        hung = summary.hung_sources if summary is not None else ()
        for name, dev in reversed(stack):
            if name in hung:
                _log.warning("not closing %s: its reader thread is stuck in a device call", name)
                continue
            try:
                dev.close()
            except Exception as err:  # closing must not hide the recording's outcome
                _log.warning("closing %s failed: %s", dev, err)
    if as_json:
        emit_json(summary.as_dict())
    else:
        files = ", ".join(str(p) for p in summary.files)
        print(
            f"recorded {summary.seconds:.1f} s, {summary.bytes / 1e6:.1f} MB, "
            f"{summary.drops_total} dropped -> {files}"
        )
        for st in summary.streams:
            print(f"  {st.topic:<36} {st.written:>8} msgs  {st.dropped:>6} dropped")
    return 0


# -------------------------------------------------------------------------------------------
# info / recover


def recording_info(path: Path, *, as_json: bool) -> int:
    """``mocaprig info``: topics, counts, rates, drops, counter gaps, chunks."""
    from mocaprig.acquire.recording import info

    inf = info(path)
    d = inf.as_dict()
    if as_json:
        emit_json(d)
        return 0
    state = "indexed" if inf.indexed else "NO SUMMARY (crashed or unfinished)"
    if inf.recovered:
        state += ", recovered"
    print(f"{path}: format {inf.format_version}, {state}, stop: {inf.stop_reason}")
    print(
        f"  duration {inf.duration_s:.3f} s, {inf.scan.complete_chunks} complete chunks, "
        f"{inf.scan.bad_chunks} bad, truncated: {inf.scan.truncated} "
        f"({inf.scan.bytes_unread} bytes unread)"
    )
    print(f"  {'topic':<36} {'schema':<26} {'msgs':>8} {'rate Hz':>9} {'drops':>6} {'gaps':>6}")
    for s in inf.streams:
        drops = "?" if s.drops is None else str(s.drops)
        print(
            f"  {s.topic:<36} {s.schema_name:<26} {s.messages:>8} {s.rate_hz:>9.1f} "
            f"{drops:>6} {s.counter_gaps:>6}"
        )
    for name in inf.devices:
        print(f"  device: {name}")
    for a in inf.attachments:
        print(f"  attachment: {a}")
    return 0


def recover_command(src: Path, out: Path, *, as_json: bool) -> int:
    """``mocaprig recover``: exit 0 = nothing lost, 3 = something lost, 1 = nothing found."""
    from mocaprig.acquire.recording import recover

    rep = recover(src, out)
    code = 0 if rep.lossless else (3 if rep.messages else 1)
    if as_json:
        emit_json(
            {
                "source": str(src),
                "output": str(out),
                "messages": rep.messages,
                "metadata_records": rep.metadata_records,
                "attachments": rep.attachments,
                "complete_chunks": rep.scan.complete_chunks,
                "bad_chunks": rep.scan.bad_chunks,
                "truncated": rep.scan.truncated,
                "bytes_unread": rep.scan.bytes_unread,
                "lossless": rep.lossless,
            }
        )
    else:
        print(
            f"{out}: {rep.messages} messages from {rep.scan.complete_chunks} complete chunks; "
            f"{rep.scan.bad_chunks} bad chunks, {rep.scan.bytes_unread} bytes unread"
            + ("" if rep.lossless else " (lossy)")
        )
    return code


# -------------------------------------------------------------------------------------------
# events text (RPG format) in and out


@dataclasses.dataclass(frozen=True, slots=True, eq=False)
class RpgEventText:
    """What :func:`read_events_txt` read from an RPG events text file.

    Attributes:
        events: :data:`~acquire.events.EVENT_DTYPE`, file order; ``t`` (µs) is ``t_ns // 1000``
            (floor).
        t_ns: The times exactly as written (int64 ns), same order as ``events``.
        width: From the optional ``width height`` first line, else ``None``.
        height: As ``width``.
    """

    events: npt.NDArray[np.void] = dataclasses.field(repr=False)
    t_ns: npt.NDArray[np.int64] = dataclasses.field(repr=False)
    width: int | None
    height: int | None


def export_events_txt(
    events: npt.NDArray[np.void],
    out: TextIO,
    *,
    t_ns: npt.NDArray[np.int64] | None = None,
    header: tuple[int, int] | None = None,
) -> None:
    """Write events as RPG ``t x y p`` lines, t in s with 9 decimals (``0.000011001 158 145 1``).

    Times come from ``t_ns`` (exact ns, same order as ``events``) when given, else from
    ``events["t"]`` (µs, so the last three decimals are ``000``). ``header=(width, height)``
    writes that first line (E2VID-style tools want it); the RPG dataset's ``events.txt`` has
    none, so by default there is none. Negative times get a leading ``-``.

    Raises:
        ValidationError: ``t_ns`` does not have one entry per event.
    """
    ev = check_events(events)
    if t_ns is None:
        t = ev["t"].astype(np.int64) * 1000
    else:
        t = np.asarray(t_ns, dtype=np.int64)
        if t.shape != ev.shape:
            msg = f"t_ns has shape {t.shape}, events {ev.shape}; give one ns time per event"
            raise ValidationError(msg)
    if header is not None:
        out.write(f"{header[0]} {header[1]}\n")
    a = np.abs(t)
    lines = "".join(
        [
            f"{s}{sec}.{ns:09d} {x} {y} {p}\n"
            for s, sec, ns, x, y, p in zip(
                np.where(t < 0, "-", "").tolist(),
                (a // 1_000_000_000).tolist(),
                (a % 1_000_000_000).tolist(),
                ev["x"].tolist(),
                ev["y"].tolist(),
                ev["p"].tolist(),
                strict=True,
            )
        ]
    )
    out.write(lines)


def read_events_txt(path: Path) -> RpgEventText:
    """Read an RPG events text file: ``t x y p`` per line, t in s; the first line may be
    ``width height``; blank lines and ``#`` comments are skipped.

    Times are parsed exactly to the ns (decimal digits, no float): ``0.000011001`` is 11001 ns.
    Digits beyond the 9th decimal must be zeros (a finer time cannot be represented; the line is
    refused rather than silently rounded). Exponent notation (``1.5e-3``) is accepted and parsed
    exactly too. Negative times are read as such (``import-events`` refuses them).

    Raises:
        RecordingError: a malformed line or a time finer than 1 ns (its line number is given).
    """
    fast = _read_events_txt_fast(path.read_bytes())
    if fast is not None:
        return fast
    return _read_events_txt_lines(path)


def _read_events_txt_fast(data: bytes) -> RpgEventText | None:
    """Vectorised reading of the plain layout (``T X Y P``, single spaces, T as ``digits`` or
    ``digits.digits`` with at most 9 decimals); ``None`` for anything else, which
    :func:`_read_events_txt_lines` then reads (or reports) line by line. Same result as it."""
    lines = data.splitlines()
    width = height = None
    if lines and not lines[0].startswith(b"#") and len(first := lines[0].split()) == 2:
        if not (first[0].isdigit() and first[1].isdigit()):
            return None
        width, height = int(first[0]), int(first[1])
        lines = lines[1:]
    if b"#" in data or b"" in lines:
        lines = [ln for ln in lines if ln and not ln.startswith(b"#")]
    arr = np.array(lines, dtype=np.bytes_)
    if arr.size == 0:
        return None
    if not (np.strings.count(arr, b" ") == 3).all():
        return None
    t, _, rest = np.strings.partition(arr, b" ")
    x, _, rest = np.strings.partition(rest, b" ")
    y, _, p = np.strings.partition(rest, b" ")
    if not all(bool(np.strings.isdigit(c).all()) for c in (x, y, p)):
        return None
    dot = np.strings.find(t, b".")
    n_frac = np.where(dot < 0, 0, np.strings.str_len(t) - dot - 1)
    digits = np.strings.replace(t, b".", b"", 1)
    if (
        not bool(np.strings.isdigit(digits).all())
        or int(n_frac.max()) > 9
        or int((np.strings.str_len(digits) + 9 - n_frac).max()) > 18
        or (x.dtype.itemsize > 18 or y.dtype.itemsize > 18 or p.dtype.itemsize > 18)
    ):
        return None
    t_ns = _digits_to_int(digits) * 10 ** (9 - n_frac).astype(np.int64)
    x_i, y_i, p_i = (_digits_to_int(c) for c in (x, y, p))
    if int(x_i.max()) >= 2**16 or int(y_i.max()) >= 2**16:
        return None
    return RpgEventText(make_events(t_ns // 1000, x_i, y_i, p_i), t_ns, width, height)


def _digits_to_int(col: npt.NDArray[np.bytes_]) -> npt.NDArray[np.int64]:
    """int64 values of a fixed-width bytes array of 1..18 ASCII digits (checked by the caller);
    digit arithmetic on the byte matrix, much faster than ``astype(np.int64)``."""
    width = col.dtype.itemsize
    m = np.ascontiguousarray(col).view(np.uint8).reshape(col.size, width)
    n_digits = np.strings.str_len(col)
    value = np.zeros(col.size, np.int64)
    for j in range(width):
        value = np.where(j < n_digits, value * 10 + (m[:, j].astype(np.int64) - 48), value)
    return value


def _read_events_txt_lines(path: Path) -> RpgEventText:
    width = height = None
    ts: list[int] = []
    xs: list[int] = []
    ys: list[int] = []
    ps: list[int] = []
    with path.open("r", encoding="ascii") as f:
        for lineno, line in enumerate(f, 1):
            tok = line.split()
            if not tok or tok[0].startswith("#"):
                continue
            try:
                if lineno == 1 and len(tok) == 2:
                    width, height = int(tok[0]), int(tok[1])
                    continue
                if len(tok) != 4:
                    bad = f"expected 4 columns, got {len(tok)}"
                    raise ValueError(bad)
                ts.append(_seconds_to_ns(tok[0]))
                xs.append(int(tok[1]))
                ys.append(int(tok[2]))
                ps.append(int(tok[3]))
            except ValueError as err:
                msg = (
                    f"{path}:{lineno}: not an RPG event line ('t x y p', t in s with at most 9 "
                    f"decimals): {line.strip()!r} ({err}); fix or remove that line"
                )
                raise RecordingError(msg) from err
    t_ns = np.asarray(ts, dtype=np.int64)
    return RpgEventText(make_events(t_ns // 1000, xs, ys, ps), t_ns, width, height)


def _seconds_to_ns(text: str) -> int:
    """Exact ns of a decimal seconds string (``-0.000011001`` -> -11001)."""
    neg = text.startswith("-")
    body = text[1:] if text[:1] in "+-" else text
    whole, _, frac = body.partition(".")
    if (whole.isdigit() and (frac.isdigit() or not frac)) or (not whole and frac.isdigit()):
        if len(frac) > 9:
            if frac[9:].strip("0"):
                bad = f"time {text} has digits beyond 9 decimals (finer than 1 ns)"
                raise ValueError(bad)
            frac = frac[:9]
        ns = int(whole or "0") * 1_000_000_000 + int(frac.ljust(9, "0") if frac else "0")
    else:  # exponent form, exact (a precision that holds every digit)
        ctx = decimal.Context(prec=len(body) + 9, traps=[decimal.InvalidOperation])
        try:
            if "_" in body:
                raise decimal.InvalidOperation
            d = ctx.scaleb(ctx.create_decimal(body), 9)
        except ArithmeticError as err:
            bad = f"time {text!r} is not a decimal number of seconds"
            raise ValueError(bad) from err
        if not d.is_finite() or d != d.to_integral_value():
            bad = f"time {text} is not a whole number of ns"
            raise ValueError(bad)
        ns = int(d)
    if ns >= 2**63:
        bad = f"time {text} is beyond the int64 ns range"
        raise ValueError(bad)
    return -ns if neg else ns


def import_events(
    src: Path,
    out: Path,
    *,
    width: int | None,
    height: int | None,
    serial: str = "imported",
    packet_us: int = 10_000,
    as_json: bool = False,
) -> int:
    """``mocaprig import-events``: an RPG events text file into a recording.

    Events go to ``/davis/<serial>/events`` in packets of ``packet_us``, with their exact ns
    times (:attr:`EventPacket.t_ns`), so ``export --format txt`` gives the same lines back;
    there is no host receive time, so ``log_time`` = the packet's first event time (ns,
    clamped at 0).
    """
    check_range(packet_us, 1, MAX_EVENT_PACKET_SPAN_US, name="packet_us")
    txt = read_events_txt(src)
    events, t_ns = txt.events, txt.t_ns
    w = width if width is not None else (txt.width if txt.width is not None else 240)
    h = height if height is not None else (txt.height if txt.height is not None else 180)
    if events.size and (int(events["x"].max()) >= w or int(events["y"].max()) >= h):
        msg = f"{src}: events fall outside {w}x{h}; pass --width/--height"
        raise RecordingError(msg)
    if events.size and int(t_ns.min()) < 0:
        msg = f"{src}: negative timestamps cannot be stored (the mono encoding needs t >= 0)"
        raise RecordingError(msg)
    rec = Recorder(
        out,
        compression="zstd",
        queue_messages=1 << 30,
        queue_bytes=1 << 62,
        min_free_disk_bytes=0,
        metadata={"import": {"source": src.name, "format": "rpg-txt", "width": str(w),
                             "height": str(h)}},
    )  # fmt: skip
    frame_id = f"davis_{serial}"
    n = 0
    with rec:
        hd = rec.add_stream(
            topic("davis", serial, "events"), EventPacket, metadata={"serial": serial}
        )
        if events.size:
            # Runs of one packet_us bin: each spans < packet_us µs <= 2**32 ns (one packet).
            bins = (t_ns - t_ns[0]) // (packet_us * 1000)
            edges = [0, *(np.flatnonzero(np.diff(bins)) + 1).tolist(), events.size]
            for lo, hi in itertools.pairwise(edges):
                ok = rec.put(
                    hd,
                    EventPacket(events[lo:hi], w, h, n, frame_id, t_ns=t_ns[lo:hi]),
                    log_time_ns=max(int(t_ns[lo]), 0),
                    sequence=n,
                )
                if not ok:
                    msg = f"importing {src}: a packet was dropped; this is a bug, report it"
                    raise RecordingError(msg)
                n += 1
    if as_json:
        emit_json({"output": str(out), "events": int(events.size), "packets": n})
    else:
        print(f"{out}: {events.size} events in {n} packets ({w}x{h})")
    return 0


# -------------------------------------------------------------------------------------------
# export


def export(
    path: Path,
    *,
    topic_name: str,
    fmt: ExportFormat,
    out: Path,
    fps: float = 30.0,
    txt_header: bool = False,
) -> int:
    """``mocaprig export``: one topic to npz / txt (events) / png (images) / mp4 (images).

    ``txt`` writes RPG ``t x y p`` lines with the stored ns times (9 decimals) and, only with
    ``txt_header``, a first ``width height`` line.
    """
    from mocaprig.acquire.recording import Recording

    if out.exists() and fmt != "png":
        msg = f"{out} exists already; not overwriting (choose another --out)"
        raise RecordingError(msg)
    with Recording(path) as rec:
        ch = rec.channels.get(topic_name)
        if ch is None:
            msg = f"{path} has no topic {topic_name!r}; topics: {', '.join(rec.topics)}"
            raise RecordingError(msg)
        schema = ch.schema_name
        if fmt == "txt":
            if schema != EventPacket.SCHEMA.name:
                msg = f"--format txt is for event topics; {topic_name} holds {schema}"
                raise RecordingError(msg)
            ev, t_ns = rec.events_ns(topic_name)
            w, h = _event_size(rec, topic_name)
            header = (w, h) if txt_header and w is not None and h is not None else None
            with out.open("x", encoding="ascii") as f:
                export_events_txt(ev, f, t_ns=t_ns, header=header)
            print(f"{out}: {ev.size} events")
            return 0
        if fmt == "npz":
            arrays = _topic_arrays(rec, topic_name, schema)
            with out.open("xb") as f:
                np.savez_compressed(f, **arrays)  # type: ignore[arg-type]
            print(f"{out}: {', '.join(f'{k} {v.shape}' for k, v in arrays.items())}")
            return 0
        if schema != ImageMsg.SCHEMA.name:
            msg = f"--format {fmt} is for image topics; {topic_name} holds {schema}"
            raise RecordingError(msg)
        return _export_images(rec, topic_name, fmt, out, fps)


def _event_size(rec: Any, topic_name: str) -> tuple[int | None, int | None]:
    for _, p in rec.decoded(topic_name):
        return int(p.width), int(p.height)
    return None, None


def _topic_arrays(rec: Any, topic_name: str, schema: str) -> dict[str, npt.NDArray[Any]]:
    if schema == EventPacket.SCHEMA.name:
        ev = rec.events(topic_name)
        return {k: ev[k] for k in ("t", "x", "y", "p")}
    if schema == ImuPacket.SCHEMA.name:
        s = rec.imu(topic_name)
        return {k: s[k] for k in s.dtype.names}
    if schema == TriggerPacket.SCHEMA.name:
        s = rec.triggers(topic_name)
        return {k: s[k] for k in s.dtype.names}
    if schema == ImageMsg.SCHEMA.name:
        times, stamps, imgs = [], [], []
        for t, m in rec.images(topic_name):
            times.append(t)
            stamps.append(m.timestamp_ns)
            imgs.append(m.image)
        return {
            "log_time_ns": np.asarray(times, np.int64),
            "timestamp_ns": np.asarray(stamps, np.int64),
            "images": np.stack(imgs) if imgs else np.empty((0, 0, 0)),
        }
    msg = f"--format npz does not handle {schema} topics; use the Python reader"
    raise RecordingError(msg)


def _to8(img: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    if img.dtype == np.uint8:
        return img
    hi = float(img.max()) if img.size else 0.0
    return (img.astype(np.float64) * (255.0 / hi if hi > 0 else 0.0)).astype(np.uint8)


def _export_images(rec: Any, topic_name: str, fmt: str, out: Path, fps: float) -> int:
    import cv2

    n = 0
    if fmt == "png":
        out.mkdir(parents=True, exist_ok=True)
        for t, m in rec.images(topic_name):
            p = out / f"{n:06d}_{t}.png"
            if p.exists():
                msg = f"{p} exists already; export into an empty folder"
                raise RecordingError(msg)
            cv2.imwrite(str(p), m.image)  # 16-bit PNG for mono16/16UC1
            n += 1
        print(f"{out}: {n} PNG files")
        return 0
    writer: Any = None
    try:
        for _, m in rec.images(topic_name):
            frame = _to8(m.image)
            if writer is None:
                h, w = frame.shape
                fourcc = cv2.VideoWriter_fourcc(*"mp4v")  # type: ignore[attr-defined]
                writer = cv2.VideoWriter(str(out), fourcc, fps, (w, h), isColor=False)
                if not writer.isOpened():
                    msg = f"OpenCV cannot write {out} (mp4v codec missing?)"
                    raise RecordingError(msg)
            writer.write(frame)
            n += 1
    finally:
        if writer is not None:
            writer.release()
    print(f"{out}: {n} frames at {fps} fps (8-bit, scaled per frame)")
    return 0


# -------------------------------------------------------------------------------------------
# argparse


def _parser(sub: Any, name: str, help_: str, examples: str) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        name,
        help=help_,
        description=help_,
        epilog="examples:\n" + examples,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    return p


def register_record(subparsers: Any) -> None:
    """Entry point: ``mocaprig record``."""
    p = _parser(
        subparsers,
        "record",
        "record a session into MCAP (live status line; Ctrl-C finishes the file)",
        "  mocaprig record --rig rig.toml --seconds 60 --out session.mcap\n"
        "  mocaprig record --rig dry-run.toml --seconds 5 --out dry.mcap   # mock = true\n"
        "  mocaprig record --mock --seconds 10 --out session.mcap\n"
        "  mocaprig record --mock --scenario default --cameras 2 --seconds 5 --out s.mcap\n"
        "  mocaprig record --mock --seconds 600 --split-seconds 60 --out long.mcap\n",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--rig", type=Path, help="rig file (TOML) listing the devices (docs/rig-file.md)"
    )
    src.add_argument("--mock", action="store_true", help="record the simulated rig")
    p.add_argument("--scenario", default="default", help="mock scenario name")
    p.add_argument("--seed", type=int, default=0, help="mock world seed")
    p.add_argument("--cameras", type=int, default=1, help="--mock: D415 count (0..4)")
    p.add_argument("--no-syncbox", action="store_true", help="--mock: without the sync box")
    p.add_argument("--seconds", type=float, required=True, help="recording length (s)")
    p.add_argument("--out", type=Path, required=True, help="output .mcap (never overwritten)")
    p.add_argument("--compression", choices=["lz4", "zstd", "none"], default="lz4")
    p.add_argument("--split-seconds", type=float, help="start a new numbered file every N s")
    p.add_argument("--split-mb", type=float, help="start a new numbered file every N MB")
    p.add_argument("--min-free-mb", type=float, default=512.0, help="stop when less is free")
    add_json_flag(p)
    p.set_defaults(
        func=lambda a: record(
            out=a.out,
            seconds=a.seconds,
            mock=a.mock,
            rig=a.rig,
            scenario=a.scenario,
            seed=a.seed,
            cameras=a.cameras,
            syncbox=not a.no_syncbox,
            compression=a.compression,
            split_seconds=a.split_seconds,
            split_mb=a.split_mb,
            min_free_mb=a.min_free_mb,
            as_json=a.json,
        )
    )


def register_info(subparsers: Any) -> None:
    """Entry point: ``mocaprig info``."""
    p = _parser(
        subparsers,
        "info",
        "summarise a recording: streams, counts, rates, drops, counter gaps, chunks",
        "  mocaprig info session.mcap\n  mocaprig info crashed.mcap --json\n",
    )
    p.add_argument("file", type=Path, help="recording (.mcap), finished or crashed")
    add_json_flag(p)
    p.set_defaults(func=lambda a: recording_info(a.file, as_json=a.json))


def register_recover(subparsers: Any) -> None:
    """Entry point: ``mocaprig recover``."""
    p = _parser(
        subparsers,
        "recover",
        "rewrite a crashed recording with a full index (exit 3 when data was lost)",
        "  mocaprig recover crashed.mcap fixed.mcap\n",
    )
    p.add_argument("input", type=Path, help="recording without a summary (crash, kill)")
    p.add_argument("output", type=Path, help="new file (never overwritten)")
    add_json_flag(p)
    p.set_defaults(func=lambda a: recover_command(a.input, a.output, as_json=a.json))


def register_export(subparsers: Any) -> None:
    """Entry point: ``mocaprig export``."""
    p = _parser(
        subparsers,
        "export",
        "export one topic: npz (any array topic), txt (events, RPG 't x y p'), png/mp4 (images)",
        "  mocaprig export s.mcap --topic /davis/00000042/events --format txt --out ev.txt\n"
        "  mocaprig export s.mcap --topic /davis/00000042/events --format txt --txt-header \\\n"
        "      --out ev_e2vid.txt\n"
        "  mocaprig export s.mcap --topic /davis/00000042/imu --format npz --out imu.npz\n"
        "  mocaprig export s.mcap --topic /d415/123/depth --format png --out depth_png/\n"
        "  mocaprig export s.mcap --topic /d415/123/ir --format mp4 --out ir.mp4\n",
    )
    p.add_argument("file", type=Path)
    p.add_argument("--topic", required=True)
    p.add_argument("--format", choices=["npz", "txt", "png", "mp4"], required=True)
    p.add_argument("--out", type=Path, required=True, help="file (folder for png)")
    p.add_argument("--fps", type=float, default=30.0, help="mp4 frame rate")
    p.add_argument(
        "--txt-header",
        action="store_true",
        help="txt: write a first 'width height' line (E2VID-style tools); RPG files have none",
    )
    p.set_defaults(
        func=lambda a: export(
            a.file,
            topic_name=a.topic,
            fmt=a.format,
            out=a.out,
            fps=a.fps,
            txt_header=a.txt_header,
        )
    )


def register_import_events(subparsers: Any) -> None:
    """Entry point: ``mocaprig import-events``."""
    p = _parser(
        subparsers,
        "import-events",
        "import an RPG events text file (t x y p; optional 'width height' first line)",
        "  mocaprig import-events events.txt --out events.mcap\n"
        "  mocaprig import-events events.txt --out e.mcap --width 346 --height 260\n",
    )
    p.add_argument("file", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--width", type=int, help="sensor width (default: file header, else 240)")
    p.add_argument("--height", type=int, help="sensor height (default: file header, else 180)")
    p.add_argument("--serial", default="imported", help="name used in the topic")
    add_json_flag(p)
    p.set_defaults(
        func=lambda a: import_events(
            a.file, a.out, width=a.width, height=a.height, serial=a.serial, as_json=a.json
        )
    )
