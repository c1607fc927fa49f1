"""The rig's devices as recorder stream sources: the real drivers (or their mocks) -> MCAP.

Each source (:class:`DavisSource`, :class:`DepthCameraSource`, :class:`SyncBoxSource`) is a
:class:`mocaprig.acquire.recorder.StreamSource`: it declares its topics, then runs in its own
thread, reading the device and putting messages into the recorder until told to stop.
"""

from __future__ import annotations

import dataclasses
import threading
from typing import Any, Literal

import numpy.typing as npt

from mocaprig.acquire.depth_camera import SyncMode
from mocaprig.acquire.device_id import DeviceId
from mocaprig.acquire.device_streams import D415Settings
from mocaprig.acquire.recorder import Recorder
from mocaprig.acquire.recording_format import (
    CameraCalibrationMsg,
    D415FrameInfo,
    DavisFrameInfo,
    EventPacket,
    ImageMsg,
    ImuPacket,
    SyncPulses,
    TriggerPacket,
    split_events,
)

__all__ = ["DavisSource", "DepthCameraSource", "SyncBoxSource"]


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
        self.device = DeviceId("davis", self.serial)
        self.name = self.device.label
        self.frame_id = self.device.frame_id
        self._max = events_per_packet_max
        info = cam.info
        self.width: int = int(info.dvs_size_x)
        self.height: int = int(info.dvs_size_y)
        self.metadata: dict[str, dict[str, str]] = {
            self.device.metadata_name: {k: str(v) for k, v in info.as_dict().items()},
            self.device.settings_name: {**_davis_settings(cam), "dvs.run": str(dvs).lower()},
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
                self.device.topic(stream), cls, metadata=meta, **kw
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
        self.device = DeviceId("d415", self.serial)
        self.name = self.device.label
        self.frame_id = self.device.frame_id
        self.settings = D415Settings(
            serial=cinfo.serial,
            name=cinfo.name,
            firmware=cinfo.firmware,
            usb_type=cinfo.usb_type,
            sync_mode=SyncMode(int(cam.sync_mode)),
            depth_scale_m=float(cam.depth_scale_m),
            stream=stream,
            options=options,
        )
        self._h: dict[str, Any] = {}

    @property
    def metadata(self) -> dict[str, dict[str, str]]:
        """The camera's ``device/d415/<serial>`` record (:class:`D415Settings`, the codec the
        reader parses back)."""
        return {self.device.metadata_name: self.settings.to_metadata()}

    def set_rig_entry(self, serial: str, role: str) -> None:
        """Note the rig file's entry (serial and role) the camera was opened for."""
        self.settings = dataclasses.replace(self.settings, rig_serial=serial, rig_role=role)

    def declare(self, recorder: Recorder) -> None:
        meta = {"serial": self.serial, "device": "D415", "frame_id": self.frame_id}
        for stream, cls, q in (
            ("ir", ImageMsg, 64),
            ("depth", ImageMsg, 64),
            ("frame_info", D415FrameInfo, 1024),
            ("camera_info", CameraCalibrationMsg, 16),
        ):
            self._h[stream] = recorder.add_stream(
                self.device.topic(stream), cls, metadata=meta, queue_messages=q
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
            DeviceId("syncbox").metadata_name: {
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
            DeviceId("syncbox").topic("pulses"), SyncPulses, metadata={"device": "syncbox"}
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
