"""The rig's devices as recorder stream sources: the real drivers (or their mocks) -> MCAP.

Each source (:class:`DavisSource`, :class:`DepthCameraSource`, :class:`SyncBoxSource`) is a
:class:`mocaprig.acquire.recorder.StreamSource`: it declares its topics, then runs in its own
thread, reading the device and putting messages into the recorder until told to stop.

A device lost mid-recording (unplugged, a cable pulled, silent) is a ``disconnected``
:class:`~mocaprig.acquire.recorder.Fault` in the file; the source then calls its ``reopen``
(every ``retry_s``) until the device is back, re-opens it as it was configured, writes a
``reconnected`` fault and goes on in the same streams. Without ``reopen`` the source ends after
the fault (the sync box re-opens its own port). The other sources are not affected.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
import time
from collections.abc import Callable
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
from mocaprig.errors import DeviceError

__all__ = ["DavisSource", "DepthCameraSource", "SyncBoxSource"]

_log = logging.getLogger(__name__)


def _wait_for_device(
    reopen: Callable[[], Any], stop: threading.Event, retry_s: float, label: str
) -> Any | None:
    """``reopen()`` every ``retry_s`` until it gives the device (None once ``stop`` is set).
    A :class:`DeviceError` means "not back yet"; anything else is a bug and propagates."""
    last = ""
    while not stop.is_set():
        try:
            return reopen()
        except DeviceError as err:
            if str(err) != last:  # one log line per new reason, not one per retry
                last = str(err)
                _log.info("%s not back yet: %s", label, err)
        stop.wait(retry_s)
    return None


def _gap_words(t_lost_ns: int, t_last_data_ns: int | None, now_ns: int) -> str:
    """How long a device was gone, for the ``reconnected`` fault."""
    words = f"re-opened {(now_ns - t_lost_ns) / 1e9:.3f} s after it was lost"
    if t_last_data_ns is not None:
        words += f", {(now_ns - t_last_data_ns) / 1e9:.3f} s after its last data"
    return words


def _lost_words(err: BaseException | str, t_last_data_ns: int | None, now_ns: int) -> str:
    """The ``disconnected`` fault's detail: the error and the age of the last data."""
    last = (
        "no data before"
        if t_last_data_ns is None
        else f"last data {(now_ns - t_last_data_ns) / 1e9:.3f} s before"
    )
    return f"{err}; {last}"


def _fault_lost(
    recorder: Recorder, device: str, err: BaseException | str, t_last_data_ns: int | None
) -> int:
    """Write the ``disconnected`` fault of ``device`` (now); returns its host time (ns)."""
    t_lost = recorder.clock_ns()
    recorder.fault("disconnected", device, _lost_words(err, t_last_data_ns, t_lost), t_ns=t_lost)
    return t_lost


def _fault_back(
    recorder: Recorder, device: str, t_lost_ns: int, t_last_data_ns: int | None
) -> None:
    """Write the ``reconnected`` fault of ``device`` (now), lost since ``t_lost_ns``."""
    now = recorder.clock_ns()
    recorder.fault("reconnected", device, _gap_words(t_lost_ns, t_last_data_ns, now))


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
        reopen: Opens the same camera again (by serial, same settings) after it was lost;
            raises :class:`DeviceError` while it is not back. ``None``: the source ends at a
            device fault. A re-opened camera is started here and closed at the end of ``run``;
            its device time restarts at 0 (a timestamp reset).
        retry_s: Period of the ``reopen`` attempts (s).
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
        reopen: Callable[[], Any] | None = None,
        retry_s: float = 0.2,
    ) -> None:
        self.cam = cam
        self.reopen = reopen
        self.retry_s = retry_s
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
        self._first = cam
        self._last_ns: int | None = None  # host time of the last packet (ns)

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
        seq = {"events": 0, "frame": 0, "imu": 0, "trigger": 0}  # go on across a re-open
        cam = self.cam
        manage = self.manage_streaming
        while True:
            try:
                self._stream(cam, recorder, stop, seq, manage=manage)
                return
            except DeviceError as err:
                t_lost = _fault_lost(recorder, self.name, err, self._last_ns)
                with contextlib.suppress(Exception):  # the handle is dead; free what is left
                    cam.close()
                if self.reopen is None:
                    return
                cam = _wait_for_device(self.reopen, stop, self.retry_s, self.name)
                if cam is None:
                    return
                self.cam, manage = cam, True  # a camera opened here is started and closed here
                _fault_back(recorder, self.name, t_lost, self._last_ns)

    def _stream(
        self,
        cam: Any,
        recorder: Recorder,
        stop: threading.Event,
        seq: dict[str, int],
        *,
        manage: bool,
    ) -> None:
        """Read ``cam`` until ``stop`` (or the offline end); a device error propagates."""
        if manage:
            cam.start()
            if not self.dvs:
                from mocaprig.acquire.davis240c_config import DvsParam, Module

                cam.config_set(Module.DVS, DvsParam.RUN, 0)
        put = recorder.put_wait if self.offline else recorder.put
        h = self._h
        try:
            while not stop.is_set():
                pkt = cam.get_packet(timeout_s=0.1)
                if pkt is None:
                    if self.offline and not cam.running:
                        break  # the simulated device ended (or failed: stats are logged)
                    continue
                t = pkt.host_time_ns or None
                self._last_ns = recorder.clock_ns()
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
            if manage:
                cam.stop()
            stats = cam.stats()
            recorder.log(
                "INFO",
                f"DAVIS {self.serial} driver counters: packets dropped {stats.packets_dropped}, "
                f"events dropped {stats.events_dropped}, raw bytes dropped "
                f"{stats.raw_bytes_dropped}",
                name=self.name,
            )
        if cam is not self._first:
            cam.close()  # a camera re-opened here is closed here; the first one is the caller's


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
        reopen: Callable[[], Any] | None = None,
        retry_s: float = 0.2,
        stall_s: float | None = None,
    ) -> None:
        """``stream``/``options``: the StreamConfig and SensorOptions the camera was configured
        with, stored in its metadata record (mode, exposure, gain, laser power).

        ``manage_streaming``: ``run`` starts and stops the camera (default); ``False``: the
        caller does (e.g. to start every camera of a simulated rig at the same instant).
        ``offline``: a simulated camera paced as fast as possible: messages go in with
        :meth:`Recorder.put_wait` (back-pressure, no drops) and ``poll() -> None`` means the
        simulated session is over (the source ends).

        A live camera that delivers nothing for ``stall_s`` (default: 1 s, at least 5 frame
        periods) is lost: librealsense's frame queue goes silent when a camera is unplugged, it
        raises nothing. ``reopen`` finds the same camera again (raising :class:`DeviceError`
        while it is not connected); it is configured as before (mode, options, sync mode),
        started, and closed at the end of ``run``. Without ``reopen`` the silence is recorded
        and polling goes on (frames that come back are recorded, with a ``reconnected``
        fault)."""
        self.cam = cam
        self.reopen = reopen
        self.retry_s = retry_s
        fps = float(getattr(stream, "fps", 0) or 30)
        self.stall_s = stall_s if stall_s is not None else max(1.0, 5.0 / fps)
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
        self._last_ns: int | None = None  # host time of the last frame (ns)

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
        cam, manage, first = self.cam, self.manage_streaming, self.cam
        while True:
            lost: BaseException | str | None = None
            try:
                lost = self._stream(cam, recorder, stop, manage=manage)
            finally:
                if lost is None and cam is not first:
                    cam.close()  # a camera re-opened here is closed here (on an error too)
            if lost is None:
                return
            t_lost = _fault_lost(recorder, self.name, lost, self._last_ns)
            with contextlib.suppress(Exception):  # the camera is gone: free what is left
                cam.close()
            if self.reopen is None:
                return
            found = _wait_for_device(self.reopen, stop, self.retry_s, self.name)
            if found is None:
                return
            try:
                found.configure(
                    stream=self.settings.stream,
                    options=self.settings.options,
                    sync_mode=self.settings.sync_mode,
                )
            except DeviceError as err:
                with contextlib.suppress(Exception):
                    found.close()
                recorder.fault("disconnected", self.name, f"re-opened but cannot configure: {err}")
                return
            self.cam, cam, manage = found, found, True
            _fault_back(recorder, self.name, t_lost, self._last_ns)

    def _stream(
        self,
        cam: Any,
        recorder: Recorder,
        stop: threading.Event,
        *,
        manage: bool,
    ) -> BaseException | str | None:
        """Record ``cam`` until ``stop`` (or the offline end): None; or until it is lost (an
        error, or silence when there is a ``reopen``): the error or what the silence was.
        Without ``reopen`` a silence is recorded as a fault and polling goes on."""
        h = self._h
        put = recorder.put_wait if self.offline else recorder.put
        try:
            if manage:
                cam.start()
            k = cam.intrinsics()
        except DeviceError as err:
            return err
        silent_since: int | None = None  # host ns of a recorded silence (without reopen)
        try:
            calib = CameraCalibrationMsg(
                int(k.width),
                int(k.height),
                (k.fx, 0.0, k.ppx, 0.0, k.fy, k.ppy, 0.0, 0.0, 1.0),
                tuple(float(c) for c in getattr(k, "coeffs", ())),
                "plumb_bob",
                self.frame_id,
            )
            put(h["camera_info"], calib)
            since = time.monotonic()  # the last frame, or the start
            while not stop.is_set():
                try:
                    fs = cam.poll(0.1)
                except DeviceError as err:
                    return err
                if fs is None:
                    if self.offline:
                        break  # the simulated session is over: no frame will come
                    silent = time.monotonic() - since
                    if silent >= self.stall_s:
                        why = f"no frames for {silent:.2f} s (unplugged or stalled)"
                        if self.reopen is not None:
                            return why
                        if silent_since is None:
                            silent_since = _fault_lost(recorder, self.name, why, self._last_ns)
                    continue
                since = time.monotonic()
                if silent_since is not None:
                    now = recorder.clock_ns()
                    detail = "frames again, " + _gap_words(silent_since, self._last_ns, now)
                    recorder.fault("reconnected", self.name, detail)
                    silent_since = None
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
                self._last_ns = t
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
            if manage:
                with contextlib.suppress(DeviceError):  # a lost camera may refuse to stop
                    cam.stop()
        return None


class SyncBoxSource:
    """A sync box (:class:`mocaprig.acquire.syncbox.SyncBox`, opened) as a stream source.

    Topic ``/syncbox/pulses``: one message per ``PULSES`` report. ``mode`` ``listen`` counts
    the D415 master's pulses; ``generate`` drives the trigger at ``hz``.

    A port that fails beyond the driver's own re-open (cable pulled for longer than its
    backoff) or a run the box lost (a board that reset) is a ``disconnected`` fault; the source
    then re-opens the port every ``retry_s`` (when ``reopen`` is True), stops whatever run the
    box still has and starts its run again (a ``reconnected`` fault). Pulse counts restart.
    """

    def __init__(
        self,
        box: Any,
        *,
        mode: Literal["listen", "generate"] = "listen",
        hz: int = 30,
        width_us: int = 100,
        report_interval_ms: int = 200,
        reopen: bool = True,
        retry_s: float = 0.2,
    ) -> None:
        self.box = box
        self.reopen = reopen
        self.retry_s = retry_s
        self._last_ns: int | None = None
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
        n = 0  # the stream's sequence goes on across a re-open
        while True:
            try:
                n = self._listen(box, recorder, stop, n)
                return
            except DeviceError as err:
                t_lost = _fault_lost(recorder, self.name, err, self._last_ns)
                box.close()  # best effort; the port is closed whatever the box said
                if not self.reopen:
                    return
                if _wait_for_device(lambda: self._reopen(box), stop, self.retry_s, self.name):
                    _fault_back(recorder, self.name, t_lost, self._last_ns)
                    continue
                return

    def _reopen(self, box: Any) -> bool:
        """Open the port again and leave the box idle (a board that kept power keeps its run)."""
        from mocaprig.acquire.syncbox import SyncBoxError

        box.open()
        try:
            box.stop()
        except SyncBoxError:
            pass  # nothing was running
        except DeviceError:
            box.close()
            raise
        return True

    def _listen(self, box: Any, recorder: Recorder, stop: threading.Event, n: int) -> int:
        """Start the run and record its reports until ``stop``; returns the next sequence."""
        box.set_report_interval(self.report_interval_ms)
        if self.mode == "generate":
            box.start(hz=self.hz, width_us=self.width_us)
        else:
            box.listen()
        mode = self.mode.upper() if self.mode == "listen" else "GENERATE"
        while not stop.is_set():
            for rep in box.read_reports(0.1):
                msg = SyncPulses(rep.count, rep.t_us, mode, "syncbox", rep.total, rep.host_time_ns)
                recorder.put(self._h, msg, sequence=n)
                self._last_ns = recorder.clock_ns()
                n += 1
        count = box.stop()
        recorder.log("INFO", f"sync box run ended with {count} pulses", name=self.name)
        return n
