"""pyrealsense2 adapter: a real (or played-back) D415 as a ``DepthCamera``.

Pinned to pyrealsense2 **2.59.1.11053** (``pip install 'mocaprig[realsense]'``); see
realsense-d415.md §3. The adapter works at the *sensor* level, not through ``rs.pipeline``:

* the depth sensor ("Stereo Module") is opened with left IR (``rs.stream.infrared`` index 1,
  Y8) and depth (Z16) in one mode; ``inter_cam_sync_mode`` is written **before** ``open`` (it
  is read-only while open, §2.3); manual exposure/gain, laser power and emitter are set too;
* frames go into an ``rs.frame_queue(capacity, keep_frames=True)``: ``keep()`` detaches each
  frame from the SDK's 16-frame pool, so a slow consumer never starves the pool (§3.2), and the
  queue holds ``queue_seconds`` of both streams; IR and depth are paired here (nothing is
  re-emitted, unlike the pipeline aggregator): by the **hardware** frame counter when the
  frames carry metadata, else by their timestamps (nearest within half a frame period), never by
  ``get_frame_number()`` alone: without metadata that is a host-side counter kept per stream, so
  one frame lost on one stream would pair depth ``k`` with IR ``k±1`` for the rest of the run;
* per-frame metadata fills :class:`~acquire.depth_camera.FrameTiming`; drops are counted from
  frame-counter gaps; ``host_time_ns`` is ``time.monotonic_ns()`` when the adapter takes the
  frame off the queue (not the SDK callback instant: a late :meth:`RealSenseCamera.poll` makes
  it late; ``time_of_arrival_ms`` keeps the SDK's own arrival time);
* a camera in master or slave mode **refuses** to deliver frames without hardware timestamps
  (timestamp domain ``system_time``): sync could not be verified (§0.5, §2.6), unless it was
  made with ``allow_no_metadata=True`` (:func:`acquire.d415_sync.configure_rig` sets it); a run
  without metadata is always announced by a warning naming the fix (:data:`METADATA_HINT`).

Errors: pyrealsense2 raises plain ``RuntimeError`` (no error types, no codes), so the adapter
reads the SDK's words to pick the :class:`~mocaprig.errors.DeviceError` subclass (disconnected,
permission, busy, timeout; the text is kept as ``backend_error``); a requested serial that is not
connected is a :class:`~mocaprig.errors.DeviceNotFoundError`.

Anything that is an ``rs.device`` works: a USB camera, an ``rs.software_device`` (tests) or a
playback device from ``rs.context().load_device(path)`` (``.db3``/``.bag``). Playback devices are
read-only: :meth:`RealSenseCamera.configure` checks the recorded sync mode instead of writing it.
"""

from __future__ import annotations

import importlib
import logging
import time
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Final, Self

import numpy as np

from mocaprig.acquire.camera_backends import open_cameras
from mocaprig.acquire.depth_camera import (
    CameraInfo,
    D415Frame,
    Distortion,
    Extrinsics,
    FrameSet,
    FrameTiming,
    Intrinsics,
    SensorOptions,
    StreamConfig,
    StreamKind,
    SyncMode,
    TimestampDomain,
    check_sync_mode,
)
from mocaprig.errors import (
    DeviceBusyError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceNotFoundError,
    DevicePermissionError,
    DeviceTimeoutError,
    ValidationError,
)

__all__ = [
    "METADATA_HINT",
    "MIN_SYNC_FIRMWARE",
    "PINNED_VERSION",
    "CaptureStats",
    "RealSenseCamera",
    "enumerate_cameras",
    "import_pyrealsense2",
    "list_d415_devices",
]

_log = logging.getLogger(__name__)

PINNED_VERSION: Final = "2.59.1"
"""The pyrealsense2 release this adapter is tested against (the wheel 2.59.1.11053)."""

MIN_SYNC_FIRMWARE: Final = (5, 9, 15, 1)
"""D415 hardware sync arrived with firmware 5.9.15.1 (realsense-d415.md §2.3, #2637)."""

METADATA_HINT: Final = (
    "per-frame UVC metadata is not enabled (the pyrealsense2 wheel uses the kernel's V4L2 "
    "backend, whose stock uvcvideo drops it). On Linux install the RealSense kernel patch "
    "(apt install librealsense2-dkms, or librealsense's "
    "scripts/patch-realsense-ubuntu-lts-hwe.sh), or use a pyrealsense2 built with the RSUSB "
    "backend (cmake -DFORCE_RSUSB_BACKEND=ON), which reads metadata without a kernel patch; on "
    "Windows add the metadata registry keys (librealsense's "
    "scripts/realsense_metadata_win10.ps1 -op install_all); then replug the camera"
)

_INSTALL_HINT: Final = (
    "pip install 'mocaprig[realsense]' (pins pyrealsense2==2.59.1.11053); the wheel also needs "
    "libusb-1.0 (Debian/Ubuntu: apt install libusb-1.0-0)"
)


# Words of librealsense errors (its own messages and the errno text it appends as "Last Error:
# ...") -> the DeviceError subclass they mean; first match wins. "open(...) failed. UVC device
# is streaming!" is what opening a sensor that another handle streams from says.
_SDK_ERROR_WORDS: Final[tuple[tuple[tuple[str, ...], type[DeviceError]], ...]] = (
    (("disconnected", "no such device", "not connected"), DeviceDisconnectedError),
    (("permission denied", "access denied", "insufficient permission"), DevicePermissionError),
    (("busy", "device is streaming"), DeviceBusyError),
    (("timeout", "timed out", "didn't arrive", "did not arrive"), DeviceTimeoutError),
)


def _sdk_error(message: str, err: BaseException) -> DeviceError:
    """``message`` as the :class:`DeviceError` subclass the SDK's words in ``err`` stand for,
    keeping them as ``backend_error``; raise it ``from err``."""
    text = str(err).lower()
    for words, cls in _SDK_ERROR_WORDS:
        if any(w in text for w in words):
            return cls.from_cause(message, err)
    return DeviceError.from_cause(message, err)


def import_pyrealsense2() -> Any:
    """Import pyrealsense2 lazily.

    Raises:
        DeviceError: it is not installed or its shared libraries (libusb-1.0) are missing.
    """
    try:
        rs = importlib.import_module("pyrealsense2")
    except ImportError as err:
        msg = f"cannot import pyrealsense2 ({err}); {_INSTALL_HINT}"
        raise DeviceError(msg) from err
    version = str(getattr(rs, "__version__", ""))
    if version and not version.startswith(PINNED_VERSION):
        _log.warning(
            "pyrealsense2 %s is installed; mocaprig is tested with %s", version, PINNED_VERSION
        )
    return rs


@dataclass(frozen=True, slots=True)
class CaptureStats:
    """Counts of one camera since :meth:`RealSenseCamera.start`."""

    framesets: int
    """Complete IR + depth framesets delivered."""
    dropped_frames: int
    """Captures missing from the frame-counter sequence (gaps; both streams)."""
    incomplete_framesets: int
    """Captures of which only one stream arrived (discarded)."""
    counter_resets: int
    """Times the hardware frame counter went backwards (ESD, restart; §2.4)."""


def _firmware_tuple(text: str) -> tuple[int, ...] | None:
    try:
        return tuple(int(p) for p in text.strip().split("."))
    except ValueError:
        return None


class RealSenseCamera:
    """One D415 behind pyrealsense2, implementing :class:`~acquire.depth_camera.DepthCamera`.

    Args:
        device: an ``rs.device`` (USB camera, ``rs.software_device`` or playback device).
        queue_seconds: seconds of both streams the frame queue holds before the SDK drops.
        allow_no_metadata: deliver frames without hardware timestamps even in master/slave
            mode (a warning is logged); otherwise :meth:`poll` refuses them.
    """

    def __init__(
        self, device: Any, *, queue_seconds: float = 2.0, allow_no_metadata: bool = False
    ) -> None:
        #: Deliver synced frames without metadata (``True``) or refuse them (``False``).
        self.allow_no_metadata = bool(allow_no_metadata)
        self._rs = import_pyrealsense2()
        self._device = device
        self._queue_seconds = float(queue_seconds)
        self._info = self._read_info()
        self._sensor = self._find_depth_sensor()
        self._is_playback = bool(device.is_playback()) if hasattr(device, "is_playback") else False
        self._stream: StreamConfig | None = None
        self._profiles: tuple[Any, Any] | None = None  # (ir, depth)
        self._sync_mode = SyncMode.DEFAULT
        self._queue: Any = None
        self._streaming = False
        self._pending: dict[int, dict[StreamKind, D415Frame]] = {}
        self._by_time: dict[StreamKind, deque[D415Frame]] = {k: deque() for k in StreamKind}
        self._last_counter: int | None = None
        self._framesets = 0
        self._dropped = 0
        self._incomplete = 0
        self._resets = 0
        self._warned_no_metadata = False

    # -- identity --------------------------------------------------------------------------

    def _get_info(self, key: str, default: str = "") -> str:
        field = getattr(self._rs.camera_info, key)
        try:
            if self._device.supports(field):
                return str(self._device.get_info(field))
        except RuntimeError:
            pass
        return default

    def _read_info(self) -> CameraInfo:
        serial = self._get_info("serial_number")
        if not serial:
            msg = "a RealSense device reports no serial number; replug it and retry"
            raise DeviceError(msg)
        return CameraInfo(
            serial=serial,
            name=self._get_info("name", "unknown"),
            firmware=self._get_info("firmware_version"),
            usb_type=self._get_info("usb_type_descriptor"),
            product_line=self._get_info("product_line"),
        )

    def _find_depth_sensor(self) -> Any:
        try:
            return self._device.first_depth_sensor()
        except RuntimeError as err:
            for sensor in self._device.query_sensors():
                if str(sensor.get_info(self._rs.camera_info.name)) == "Stereo Module":
                    return sensor
            msg = f"D415 {self._info.serial} has no depth sensor ('Stereo Module'); replug it"
            raise _sdk_error(msg, err) from err

    @property
    def info(self) -> CameraInfo:
        """Identity strings of the device."""
        return self._info

    @property
    def sync_mode(self) -> SyncMode:
        """The ``inter_cam_sync_mode`` set by :meth:`configure`."""
        return self._sync_mode

    @property
    def is_streaming(self) -> bool:
        """``True`` between :meth:`start` and :meth:`stop`."""
        return self._streaming

    @property
    def depth_scale_m(self) -> float:
        """Metres per Z16 unit (``depth_sensor.get_depth_scale()``)."""
        try:
            return float(self._sensor.get_depth_scale())
        except (RuntimeError, AttributeError) as err:
            msg = f"D415 {self._info.serial}: cannot read the depth scale ({err})"
            raise _sdk_error(msg, err) from err

    @property
    def stats(self) -> CaptureStats:
        """Frame counts since :meth:`start`."""
        return CaptureStats(self._framesets, self._dropped, self._incomplete, self._resets)

    # -- configuration ---------------------------------------------------------------------

    def _find_profile(self, kind: StreamKind, stream: StreamConfig) -> Any:
        rs = self._rs
        want_type = rs.stream.infrared if kind is StreamKind.INFRARED_LEFT else rs.stream.depth
        want_fmt = rs.format.y8 if kind is StreamKind.INFRARED_LEFT else rs.format.z16
        for prof in self._sensor.get_stream_profiles():
            if (
                prof.stream_type() == want_type
                and prof.stream_index() == kind.stream_index
                and prof.format() == want_fmt
                and prof.fps() == stream.fps
            ):
                video = prof.as_video_stream_profile()
                if video.width() == stream.width and video.height() == stream.height:
                    return video
        link = (
            f" (USB {self._info.usb_type} link: use a USB 3 port)" if not self._info.is_usb3 else ""
        )
        msg = (
            f"D415 {self._info.serial} offers no {kind.value} index {kind.stream_index} "
            f"{'Y8' if kind is StreamKind.INFRARED_LEFT else 'Z16'} profile at {stream}{link}; "
            "choose another mode"
        )
        raise DeviceError(msg)

    def _set_option(self, name: str, value: float) -> None:
        option = getattr(self._rs.option, name)
        if not self._sensor.supports(option):
            msg = f"D415 {self._info.serial}: the depth sensor has no option '{name}'"
            raise DeviceError(msg)
        try:
            self._sensor.set_option(option, float(value))
        except RuntimeError as err:
            msg = (
                f"D415 {self._info.serial}: cannot set {name} = {value} ({err}); "
                "check the range with `rs-enumerate-devices -o`"
            )
            raise _sdk_error(msg, err) from err

    def _get_option(self, name: str) -> float | None:
        option = getattr(self._rs.option, name)
        if not self._sensor.supports(option):
            return None
        return float(self._sensor.get_option(option))

    def configure(
        self, *, stream: StreamConfig, options: SensorOptions, sync_mode: SyncMode
    ) -> None:
        """Select the mode, set exposure/gain/laser and ``inter_cam_sync_mode`` (before open).

        Raises:
            ValidationError: sync mode > 2, or an exposure longer than the frame period.
            DeviceError: streaming; no such profile; an option cannot be set; firmware too old
                for hardware sync; a playback file recorded with another sync mode.
        """
        serial = self._info.serial
        mode = check_sync_mode(sync_mode, serial=serial)
        options.check_fits(stream)
        if self._streaming:
            msg = (
                f"D415 {serial}: cannot configure while streaming (inter_cam_sync_mode is "
                "read-only while the sensor is open); call stop() first"
            )
            raise DeviceError(msg)
        if mode is not SyncMode.DEFAULT and not self._is_playback:
            fw = _firmware_tuple(self._info.firmware)
            if fw is not None and fw < MIN_SYNC_FIRMWARE:
                msg = (
                    f"D415 {serial}: firmware {self._info.firmware} predates hardware sync "
                    "(needs ≥ 5.9.15.1); update it with rs-fw-update or the RealSense Viewer"
                )
                raise DeviceError(msg)
        profiles = (
            self._find_profile(StreamKind.INFRARED_LEFT, stream),
            self._find_profile(StreamKind.DEPTH, stream),
        )
        if self._is_playback:
            recorded = self._get_option("inter_cam_sync_mode")
            if recorded is not None and int(recorded) != int(mode):
                msg = (
                    f"D415 {serial}: the playback file was recorded with inter_cam_sync_mode "
                    f"{int(recorded)}, not {int(mode)}"
                )
                raise DeviceError(msg)
            _log.debug("D415 %s is a playback device: options are read-only, not set", serial)
        else:
            # Order matters: the sync mode must be written while the sensor is closed (§2.3).
            self._set_option("inter_cam_sync_mode", int(mode))
            self._set_option("enable_auto_exposure", 0)
            self._set_option("exposure", options.exposure_us)
            self._set_option("gain", options.gain)
            self._set_option("emitter_enabled", 1 if options.emitter_enabled else 0)
            if options.emitter_enabled:
                self._set_option("laser_power", options.laser_power_mw)
        self._stream = stream
        self._profiles = profiles
        self._sync_mode = mode
        _log.info(
            "D415 %s configured: %s, sync mode %s, exposure %d µs, gain %d, laser %d mW",
            serial,
            stream,
            mode.name,
            options.exposure_us,
            options.gain,
            options.laser_power_mw if options.emitter_enabled else 0,
        )

    # -- streaming -------------------------------------------------------------------------

    def start(self) -> None:
        """Open the depth sensor with IR(1) Y8 + depth Z16 and start into a frame queue.

        Raises:
            DeviceError: not configured, already streaming, or the SDK refuses to open/start
                (:class:`DeviceBusyError`, :class:`DeviceDisconnectedError`, ... when the SDK's
                words say which).
        """
        serial = self._info.serial
        if self._profiles is None or self._stream is None:
            msg = f"D415 {serial}: call configure() before start()"
            raise DeviceError(msg)
        if self._streaming:
            msg = f"D415 {serial} is already streaming"
            raise DeviceError(msg)
        capacity = max(32, round(2 * self._stream.fps * self._queue_seconds))
        queue = self._rs.frame_queue(capacity, keep_frames=True)
        try:
            self._sensor.open(list(self._profiles))
        except RuntimeError as err:
            msg = (
                f"D415 {serial}: cannot open the depth sensor ({err}); is another program using it?"
            )
            raise _sdk_error(msg, err) from err
        try:
            self._sensor.start(queue)
        except RuntimeError as err:
            self._sensor.close()
            msg = f"D415 {serial}: cannot start streaming ({err}); replug the camera"
            raise _sdk_error(msg, err) from err
        self._queue = queue
        self._streaming = True
        self._pending.clear()
        for q in self._by_time.values():
            q.clear()
        self._warned_no_metadata = False
        self._last_counter = None
        self._framesets = self._dropped = self._incomplete = self._resets = 0
        _log.info("D415 %s streaming (frame queue of %d frames)", serial, capacity)

    def stop(self) -> None:
        """Stop streaming and close the sensor (no-op when stopped)."""
        if not self._streaming:
            return
        self._streaming = False
        try:
            self._sensor.stop()
            self._sensor.close()
        except RuntimeError as err:
            msg = f"D415 {self._info.serial}: stopping failed ({err})"
            raise _sdk_error(msg, err) from err
        finally:
            self._queue = None
            self._pending.clear()
            for q in self._by_time.values():
                q.clear()

    def close(self) -> None:
        """Stop and release the device."""
        self.stop()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def poll(self, timeout_s: float = 0.0) -> FrameSet | None:
        """The next complete frameset, or ``None`` if none completes within ``timeout_s``.

        Raises:
            DeviceError: not streaming; or the camera is a sync master/slave and its frames carry
                no hardware timestamps (metadata disabled): synced recording is refused.
        """
        if not self._streaming or self._queue is None:
            msg = f"D415 {self._info.serial} is not streaming; call start() first"
            raise DeviceError(msg)
        deadline = time.monotonic() + max(0.0, timeout_s)
        while True:
            remaining_ms = max(0, round((deadline - time.monotonic()) * 1000))
            ok, frame = self._queue.try_wait_for_frame(remaining_ms)
            if not ok:
                return None
            done = self._accept(frame)
            if done is not None:
                return done

    def __iter__(self) -> Iterator[FrameSet]:
        """Yield framesets while streaming (blocks up to 1 s per frameset; stops on timeout)."""
        while self._streaming:
            fs = self.poll(1.0)
            if fs is None:
                return
            yield fs

    # -- frame conversion ------------------------------------------------------------------

    def _timing(self, frame: Any, host_time_ns: int) -> tuple[FrameTiming, bool]:
        """The frame's timing, and whether its counter is the hardware ``frame_counter``."""
        md = self._rs.frame_metadata_value

        def meta(name: str) -> int | None:
            key = getattr(md, name)
            if frame.supports_frame_metadata(key):
                return int(frame.get_frame_metadata(key))
            return None

        counter = meta("frame_counter")
        domain = TimestampDomain(str(frame.get_frame_timestamp_domain()).rsplit(".", 1)[-1])
        timing = FrameTiming(
            frame_counter=int(frame.get_frame_number()) if counter is None else counter,
            sensor_timestamp_us=meta("sensor_timestamp"),
            frame_timestamp_us=meta("frame_timestamp"),
            time_of_arrival_ms=meta("time_of_arrival"),
            timestamp_domain=domain,
            host_time_ns=host_time_ns,
            timestamp_ms=float(frame.get_timestamp()),
        )
        return timing, counter is not None

    def _accept(self, frame: Any) -> FrameSet | None:
        rs = self._rs
        host_ns = time.monotonic_ns()
        prof = frame.get_profile()
        if prof.stream_type() == rs.stream.depth:
            kind = StreamKind.DEPTH
            dtype: type[np.generic] = np.uint16
        elif prof.stream_type() == rs.stream.infrared and prof.stream_index() == 1:
            kind = StreamKind.INFRARED_LEFT
            dtype = np.uint8
        else:
            return None
        timing, hw_counter = self._timing(frame, host_ns)
        if not timing.has_hardware_timestamps:
            self._refuse_or_warn(timing)
        image = np.asanyarray(frame.get_data()).astype(dtype, copy=True)  # own the bytes
        got = D415Frame(kind, image, timing)
        pair = self._pair_by_counter(got) if hw_counter else self._pair_by_time(got)
        if pair is None:
            return None
        ir, depth = pair
        self._framesets += 1
        scale = frame.as_depth_frame().get_units() if kind is StreamKind.DEPTH else None
        return FrameSet(
            serial=self._info.serial,
            infrared=ir,
            depth=depth,
            depth_scale_m=float(scale) if scale else self.depth_scale_m,
        )

    def _pair_by_counter(self, got: D415Frame) -> tuple[D415Frame, D415Frame] | None:
        """Pair by the hardware ``frame_counter`` (one capture, one counter, both streams)."""
        counter = got.timing.frame_counter
        if self._last_counter is not None and counter < self._last_counter - 1:
            self._resets += 1
            self._incomplete += len(self._pending)
            self._pending.clear()
            _log.warning(
                "D415 %s: frame counter went back from %d to %d (ESD or restart)",
                self._info.serial,
                self._last_counter,
                counter,
            )
            self._last_counter = None
        slot = self._pending.setdefault(counter, {})
        slot[got.stream] = got
        if len(slot) < 2:
            return None
        del self._pending[counter]
        stale = [c for c in self._pending if c < counter]
        for c in stale:
            del self._pending[c]
        self._incomplete += len(stale)
        if self._last_counter is not None and counter > self._last_counter + 1:
            self._dropped += counter - self._last_counter - 1 - len(stale)
        self._last_counter = counter
        return slot[StreamKind.INFRARED_LEFT], slot[StreamKind.DEPTH]

    def _pair_by_time(self, got: D415Frame) -> tuple[D415Frame, D415Frame] | None:
        """Pair frames without a hardware counter by timestamp: the other stream's frame
        nearest in time, within half a frame period (the SDK's timestamp-matcher rule, §3.2).

        Without metadata ``get_frame_number()`` counts frames on the host, per stream, so a
        frame lost on one stream shifts that stream's numbers by one for the rest of the run;
        the timestamps (host receive times, ``system_time``) still tell captures apart. Frames of
        the other stream too old to match are discarded as incomplete; drops stay invisible.
        """
        fps = self._stream.fps if self._stream is not None else 30
        half_ms = 500.0 / fps
        t = got.timing.timestamp_ms
        other = (
            StreamKind.DEPTH if got.stream is StreamKind.INFRARED_LEFT else StreamKind.INFRARED_LEFT
        )
        waiting = self._by_time[other]
        while waiting and waiting[0].timing.timestamp_ms <= t - half_ms:
            waiting.popleft()
            self._incomplete += 1
        best: int | None = None
        for i, cand in enumerate(waiting):
            dt = abs(cand.timing.timestamp_ms - t)
            if dt < half_ms and (best is None or dt < abs(waiting[best].timing.timestamp_ms - t)):
                best = i
        if best is None:
            mine = self._by_time[got.stream]
            mine.append(got)
            while len(mine) > 4 * fps:  # the other stream stopped: keep a bounded backlog
                mine.popleft()
                self._incomplete += 1
            return None
        match = waiting[best]
        for _ in range(best + 1):  # the match, and anything of that stream older than it
            waiting.popleft()
        self._incomplete += best
        mine = self._by_time[got.stream]
        while mine and mine[0].timing.timestamp_ms <= t:  # older frames of this stream
            mine.popleft()
            self._incomplete += 1
        if got.stream is StreamKind.INFRARED_LEFT:
            return got, match
        return match, got

    def _refuse_or_warn(self, timing: FrameTiming) -> None:
        serial = self._info.serial
        why = (
            f"timestamp domain is {timing.timestamp_domain.value}"
            if timing.timestamp_domain is TimestampDomain.SYSTEM_TIME
            else "the frame metadata lacks sensor/frame timestamps"
        )
        if self._sync_mode is not SyncMode.DEFAULT and not self.allow_no_metadata:
            msg = (
                f"D415 {serial} ({self._sync_mode.name.lower()}): frames carry no hardware "
                f"timestamps ({why}), so hardware sync cannot be verified and synced recording "
                f"is refused (allow_no_metadata=True / --allow-no-metadata forces it): "
                f"{METADATA_HINT}"
            )
            raise DeviceError(msg)
        if not self._warned_no_metadata:
            self._warned_no_metadata = True
            _log.warning(
                "D415 %s (%s): NO FRAME METADATA (%s): IR and depth are paired by timestamp, "
                "drops are invisible and hardware sync cannot be verified: %s",
                serial,
                self._sync_mode.name.lower(),
                why,
                METADATA_HINT,
            )

    # -- calibration -----------------------------------------------------------------------

    def _configured_profiles(self) -> tuple[Any, Any]:
        if self._profiles is None:
            msg = (
                f"D415 {self._info.serial}: call configure() first (intrinsics depend on the mode)"
            )
            raise DeviceError(msg)
        return self._profiles

    def intrinsics(self) -> Intrinsics:
        """Intrinsics of the configured depth stream (identical to the left IR's on a D415)."""
        _ir, depth = self._configured_profiles()
        intr = depth.get_intrinsics()
        return Intrinsics(
            width=int(intr.width),
            height=int(intr.height),
            fx=float(intr.fx),
            fy=float(intr.fy),
            ppx=float(intr.ppx),
            ppy=float(intr.ppy),
            model=Distortion(str(intr.model).rsplit(".", 1)[-1]),
            coeffs=tuple(float(c) for c in intr.coeffs),
        )

    def extrinsics_ir_to_depth(self) -> Extrinsics:
        """Left IR → depth extrinsics from the calibration table (identity on a D415)."""
        ir, depth = self._configured_profiles()
        try:
            ext = ir.get_extrinsics_to(depth)
        except RuntimeError as err:
            msg = f"D415 {self._info.serial}: the SDK has no IR→depth extrinsics ({err})"
            raise _sdk_error(msg, err) from err
        return Extrinsics(
            rotation=tuple(float(v) for v in ext.rotation),
            translation_m=(
                float(ext.translation[0]),
                float(ext.translation[1]),
                float(ext.translation[2]),
            ),
        )

    def __repr__(self) -> str:
        return f"RealSenseCamera(serial={self._info.serial!r}, name={self._info.name!r})"


def enumerate_cameras(
    *, context: Any = None, serials: Iterable[str] | None = None, queue_seconds: float = 2.0
) -> list[RealSenseCamera]:
    """The connected D415 cameras (sorted by serial), optionally only ``serials``.

    Other RealSense models are skipped with a log line.

    Raises:
        DeviceNotFoundError: a requested serial is not connected.
        DeviceError: pyrealsense2 is missing.
    """
    rs = import_pyrealsense2()
    ctx = rs.context() if context is None else context
    wanted = None if serials is None else set(serials)
    cams: list[RealSenseCamera] = []
    connected: list[str] = []  # every D415, wanted or not, for the "not connected" message
    for dev in ctx.query_devices():
        name = str(dev.get_info(rs.camera_info.name)) if dev.supports(rs.camera_info.name) else ""
        if "D415" not in name:
            _log.info("skipping RealSense device %r: not a D415", name)
            continue
        cam = RealSenseCamera(dev, queue_seconds=queue_seconds)
        connected.append(cam.info.serial)
        if wanted is not None and cam.info.serial not in wanted:
            continue
        if not cam.info.is_usb3:
            _log.warning(
                "D415 %s is on a USB %s link: modes are limited; use a USB 3 port",
                cam.info.serial,
                cam.info.usb_type,
            )
        cams.append(cam)
    if wanted is not None:
        missing = wanted - {c.info.serial for c in cams}
        if missing:
            seen = sorted(connected) or "none"
            msg = f"D415 {', '.join(sorted(missing))} not connected (found: {seen}); check USB"
            raise DeviceNotFoundError(msg)
    return sorted(cams, key=lambda c: c.info.serial)


def list_d415_devices(*, mock: bool = False, **mock_options: Any) -> list[CameraInfo]:
    """Identity of every D415 found (``mocaprig devices``); ``mock=True`` asks the mock.

    Real cameras: an absent pyrealsense2 raises :class:`DeviceError` with the install hint.
    """
    if mock:
        return [cam.info for cam in open_cameras("mock", **mock_options)]
    if mock_options:
        msg = f"options {sorted(mock_options)} apply only with mock=True"
        raise ValidationError(msg)
    return [cam.info for cam in enumerate_cameras()]
