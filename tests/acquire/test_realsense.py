"""The pyrealsense2 adapter, exercised through pyrealsense2's own software device and .db3 playback.

Pinned to pyrealsense2 2.59.1 (realsense-d415.md §3.5, §4.1): a ``software_device`` with a
"Stereo Module" sensor carrying depth Z16 and IR index 1 Y8 streams, D415-like options and
per-frame metadata; frames are injected with ``on_video_frame`` and read back through
:class:`mocaprig.acquire.realsense.RealSenseCamera` exactly as from a USB camera.
"""

from __future__ import annotations

import gc
import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mocaprig.acquire.depth_camera import (
    DepthCamera,
    Distortion,
    SensorOptions,
    StreamConfig,
    SyncMode,
    TimestampDomain,
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

rs = pytest.importorskip(
    "pyrealsense2",
    reason="pyrealsense2 is not importable here (not installed, or libusb-1.0 missing)",
    exc_type=ImportError,
)

from mocaprig.acquire.realsense import RealSenseCamera, enumerate_cameras  # noqa: E402

SERIAL = "822512060411"
W, H, FPS = 848, 480, 30


def _range(lo: float, hi: float, step: float, default: float) -> Any:
    # pyrealsense2 2.59.1's software_sensor.add_option reads option_range's 3rd argument as the
    # default and the 4th as the step (observed: (16, 248, 1, 16) fails "out of range ... def").
    return rs.option_range(float(lo), float(hi), float(default), float(step))


@dataclass
class SwCamera:
    device: Any
    sensor: Any
    depth: Any
    ir: Any

    def inject(
        self,
        counter: int,
        *,
        sensor_ts: int | None = None,
        metadata: bool = True,
        streams: tuple[str, ...] = ("depth", "ir"),
    ) -> None:
        ts = 1_000_000 + 33_333 * counter if sensor_ts is None else sensor_ts
        for name in streams:
            prof, bpp, dtype = (
                (self.depth, 2, np.uint16) if name == "depth" else (self.ir, 1, np.uint8)
            )
            img = np.full((H, W), counter % 200 + 1, dtype)
            frame = rs.software_video_frame()
            frame.pixels = img
            frame.bpp = bpp
            frame.stride = W * bpp
            frame.timestamp = ts / 1000.0
            frame.frame_number = counter
            frame.profile = prof.as_video_stream_profile()
            if name == "depth":
                frame.depth_units = 0.001
            if metadata:
                frame.domain = rs.timestamp_domain.hardware_clock
                md = rs.frame_metadata_value
                self.sensor.set_metadata(md.frame_counter, counter)
                self.sensor.set_metadata(md.sensor_timestamp, ts)
                self.sensor.set_metadata(md.frame_timestamp, ts + 12_000)
                self.sensor.set_metadata(md.time_of_arrival, 1_767_225_600_000 + counter * 33)
            else:
                frame.domain = rs.timestamp_domain.system_time
            self.sensor.on_video_frame(frame)


def make_software_d415(serial: str = SERIAL, *, firmware: str = "5.16.0.1") -> SwCamera:
    dev = rs.software_device()
    sensor = dev.add_sensor("Stereo Module")
    intr = rs.intrinsics()
    intr.width, intr.height = W, H
    intr.fx, intr.fy, intr.ppx, intr.ppy = 623.4, 623.4, 421.6, 239.6
    intr.model = rs.distortion.brown_conrady
    intr.coeffs = [0.0] * 5

    def video(stream: Any, index: int, uid: int, fmt: Any, bpp: int) -> Any:
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = stream, index, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = W, H, FPS, bpp, fmt
        vs.intrinsics = intr
        return vs

    depth = sensor.add_video_stream(video(rs.stream.depth, 0, 0, rs.format.z16, 2), True)
    ir = sensor.add_video_stream(video(rs.stream.infrared, 1, 1, rs.format.y8, 1))
    ext = rs.extrinsics()
    ext.rotation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]
    ext.translation = [0.0, 0.0, 0.0]
    ir.register_extrinsics_to(depth, ext)
    depth.register_extrinsics_to(ir, ext)
    sensor.add_read_only_option(rs.option.depth_units, 0.001)
    for opt, rng in [
        (rs.option.inter_cam_sync_mode, _range(0, 2, 1, 0)),
        (rs.option.exposure, _range(1, 165000, 1, 8500)),
        (rs.option.gain, _range(16, 248, 1, 16)),
        (rs.option.laser_power, _range(0, 360, 30, 150)),
        (rs.option.emitter_enabled, _range(0, 2, 1, 1)),
        (rs.option.enable_auto_exposure, _range(0, 1, 1, 1)),
    ]:
        sensor.add_option(opt, rng, True)
    dev.register_info(rs.camera_info.serial_number, serial)
    dev.register_info(rs.camera_info.name, "Intel RealSense D415")
    dev.register_info(rs.camera_info.firmware_version, firmware)
    dev.register_info(rs.camera_info.usb_type_descriptor, "3.2")
    dev.register_info(rs.camera_info.product_line, "D400")
    return SwCamera(dev, sensor, depth, ir)


OPTIONS = SensorOptions(exposure_us=5000, gain=32, laser_power_mw=210)


def started(sw: SwCamera, mode: SyncMode = SyncMode.SLAVE) -> RealSenseCamera:
    cam = RealSenseCamera(sw.device)
    cam.configure(stream=StreamConfig(), options=OPTIONS, sync_mode=mode)
    cam.start()
    return cam


def test_adapter_satisfies_the_protocol() -> None:
    cam = RealSenseCamera(make_software_d415().device)
    assert isinstance(cam, DepthCamera)
    assert cam.info.serial == SERIAL
    assert cam.info.name == "Intel RealSense D415"
    assert cam.info.is_usb3
    assert cam.depth_scale_m == pytest.approx(0.001)


def test_configure_sets_sync_mode_and_manual_options() -> None:
    sw = make_software_d415()
    cam = RealSenseCamera(sw.device)
    cam.configure(stream=StreamConfig(), options=OPTIONS, sync_mode=SyncMode.MASTER)
    get = sw.sensor.get_option
    assert get(rs.option.inter_cam_sync_mode) == 1
    assert get(rs.option.enable_auto_exposure) == 0
    assert get(rs.option.exposure) == 5000
    assert get(rs.option.gain) == 32
    assert get(rs.option.laser_power) == 210
    assert get(rs.option.emitter_enabled) == 1
    assert cam.sync_mode is SyncMode.MASTER


def test_sync_mode_above_two_is_rejected_for_a_d415() -> None:
    cam = RealSenseCamera(make_software_d415().device)
    with pytest.raises(ValidationError, match=r"only 0 .*1 .*2"):
        cam.configure(stream=StreamConfig(), options=OPTIONS, sync_mode=3)  # type: ignore[arg-type]


def test_mode_the_device_lacks_is_refused() -> None:
    cam = RealSenseCamera(make_software_d415().device)
    with pytest.raises(DeviceError, match=rf"{SERIAL} offers no infrared .*1280x720@30"):
        cam.configure(stream=StreamConfig(1280, 720, 30), options=OPTIONS, sync_mode=SyncMode.SLAVE)


def test_old_firmware_cannot_sync() -> None:
    cam = RealSenseCamera(make_software_d415(firmware="5.9.14.0").device)
    with pytest.raises(DeviceError, match=r"5\.9\.15\.1"):
        cam.configure(stream=StreamConfig(), options=OPTIONS, sync_mode=SyncMode.SLAVE)


def test_configure_while_streaming_is_refused() -> None:
    cam = started(make_software_d415())
    try:
        with pytest.raises(DeviceError, match="read-only while the sensor is open"):
            cam.configure(stream=StreamConfig(), options=OPTIONS, sync_mode=SyncMode.MASTER)
    finally:
        cam.stop()


def test_frames_with_metadata_fill_the_timing() -> None:
    sw = make_software_d415()
    with started(sw) as cam:
        for c in range(100, 104):
            sw.inject(c)
        sets = [cam.poll(1.0) for _ in range(4)]
    assert all(s is not None for s in sets)
    first = sets[0]
    assert first is not None
    assert first.serial == SERIAL
    assert first.infrared.image.shape == (H, W)
    assert first.infrared.image.dtype == np.uint8
    assert first.depth.image.dtype == np.uint16
    assert int(first.depth.image[0, 0]) == 101
    assert first.depth_scale_m == pytest.approx(0.001)
    t = first.timing
    assert t.frame_counter == 100
    assert t.sensor_timestamp_us == 1_000_000 + 33_333 * 100
    assert t.frame_timestamp_us == t.sensor_timestamp_us + 12_000
    assert t.time_of_arrival_ms == 1_767_225_600_000 + 3300
    assert t.timestamp_domain is TimestampDomain.HARDWARE_CLOCK
    assert t.has_hardware_timestamps
    assert [s.timing.frame_counter for s in sets if s] == [100, 101, 102, 103]
    assert first.infrared.timing.frame_counter == first.depth.timing.frame_counter


def test_missing_metadata_refuses_synced_recording_and_says_why() -> None:
    sw = make_software_d415()
    cam = started(sw, SyncMode.SLAVE)
    try:
        sw.inject(7, metadata=False)
        with pytest.raises(DeviceError, match=r"no hardware timestamps.*librealsense2-dkms"):
            cam.poll(1.0)
    finally:
        cam.stop()


def test_missing_metadata_in_default_mode_delivers_system_time() -> None:
    sw = make_software_d415()
    with started(sw, SyncMode.DEFAULT) as cam:
        sw.inject(7, metadata=False)
        fs = cam.poll(1.0)
    assert fs is not None
    assert fs.timing.timestamp_domain is TimestampDomain.SYSTEM_TIME
    assert fs.timing.sensor_timestamp_us is None
    assert not fs.timing.has_hardware_timestamps


def test_counter_gaps_and_lone_streams_are_counted() -> None:
    sw = make_software_d415()
    with started(sw) as cam:
        sw.inject(10)
        sw.inject(11, streams=("depth",))  # IR of capture 11 never arrives
        sw.inject(12)
        sw.inject(15)  # 13 and 14 lost on USB
        counters = []
        while (fs := cam.poll(0.3)) is not None:
            counters.append(fs.timing.frame_counter)
        stats = cam.stats
    assert counters == [10, 12, 15]
    assert stats.framesets == 3
    assert stats.incomplete_framesets == 1
    assert stats.dropped_frames == 2


def test_poll_before_start_is_an_error() -> None:
    cam = RealSenseCamera(make_software_d415().device)
    with pytest.raises(DeviceError, match="not streaming"):
        cam.poll(0.0)
    with pytest.raises(DeviceError, match="configure"):
        cam.start()


def test_intrinsics_and_extrinsics_are_read_from_the_profiles() -> None:
    cam = RealSenseCamera(make_software_d415().device)
    cam.configure(stream=StreamConfig(), options=OPTIONS, sync_mode=SyncMode.DEFAULT)
    intr = cam.intrinsics()
    assert (intr.width, intr.height) == (W, H)
    assert intr.fx == pytest.approx(623.4)
    assert intr.ppx == pytest.approx(421.6)
    assert intr.model is Distortion.BROWN_CONRADY
    assert intr.coeffs == (0.0,) * 5
    ext = cam.extrinsics_ir_to_depth()
    np.testing.assert_allclose(ext.matrix(), np.eye(4))


def _record(path: Path, n: int, *, mode: int = 2) -> None:
    sw = make_software_d415()
    rec = rs.recorder(str(path), sw.device)
    sensor = rec.query_sensors()[0]
    sensor.set_option(rs.option.inter_cam_sync_mode, mode)
    queue = rs.frame_queue(64, keep_frames=True)
    sensor.open(sensor.get_stream_profiles())
    sensor.start(queue)
    for c in range(500, 500 + n):
        sw.inject(c)
    while queue.poll_for_frame():
        pass
    sensor.stop()
    sensor.close()
    del sensor, rec, queue
    gc.collect()  # the recorder writes the .db3 when it is destroyed


def test_db3_playback_through_the_adapter(tmp_path: Path) -> None:
    path = tmp_path / "sw.db3"
    _record(path, 8)
    playback = rs.context().load_device(str(path))
    playback.as_playback().set_real_time(False)
    cam = RealSenseCamera(playback)
    assert cam.info.serial == SERIAL
    cam.configure(stream=StreamConfig(), options=OPTIONS, sync_mode=SyncMode.SLAVE)
    counters, stamps = [], []
    with cam:
        cam.start()
        while (fs := cam.poll(0.5)) is not None:
            counters.append(fs.timing.frame_counter)
            stamps.append(fs.timing.sensor_timestamp_us)
            assert fs.timing.timestamp_domain is TimestampDomain.HARDWARE_CLOCK
    assert counters == list(range(500, 508))
    assert stamps == [1_000_000 + 33_333 * c for c in range(500, 508)]
    assert cam.stats.dropped_frames == 0


def test_playback_recorded_with_another_sync_mode_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "master.db3"
    _record(path, 2, mode=1)
    playback = rs.context().load_device(str(path))
    cam = RealSenseCamera(playback)
    with pytest.raises(DeviceError, match="recorded with inter_cam_sync_mode 1"):
        cam.configure(stream=StreamConfig(), options=OPTIONS, sync_mode=SyncMode.SLAVE)


def test_enumerate_without_cameras_is_empty() -> None:
    class NoDevices:
        def query_devices(self) -> list[Any]:
            return []

    assert enumerate_cameras(context=NoDevices()) == []
    with pytest.raises(DeviceError, match="not connected"):
        enumerate_cameras(context=NoDevices(), serials=["123"])


def test_missing_pyrealsense2_gives_the_install_hint(monkeypatch: pytest.MonkeyPatch) -> None:
    from mocaprig.acquire import realsense

    real = importlib.import_module

    def fake_import(name: str, package: str | None = None) -> Any:
        if name == "pyrealsense2":
            raise ImportError("libusb-1.0.so.0: cannot open shared object file")
        return real(name, package)

    monkeypatch.setattr(importlib, "import_module", fake_import)
    with pytest.raises(DeviceError, match=r"mocaprig\[realsense\].*libusb"):
        realsense.import_pyrealsense2()


def test_two_software_cameras_through_the_adapter_pass_the_sync_check() -> None:
    """Master + slave software devices → adapter → SyncChecker (slave clock +40 ppm)."""
    from mocaprig.acquire.d415_sync import SyncCheckConfig, SyncChecker

    master_sw, slave_sw = make_software_d415("100000000001"), make_software_d415("100000000002")
    master, slave = started(master_sw, SyncMode.MASTER), started(slave_sw, SyncMode.SLAVE)
    checker = SyncChecker(
        {"100000000001": SyncMode.MASTER, "100000000002": SyncMode.SLAVE}, SyncCheckConfig(fps=30)
    )
    rng = np.random.default_rng(4)
    try:
        for k in range(90):
            t_us = 33_333.333 * k
            master_sw.inject(200 + k, sensor_ts=round(5_000_000 + t_us + rng.normal(0, 3)))
            slave_sw.inject(
                7 + k, sensor_ts=round(90_000_000 + 120 + t_us * (1 + 40e-6) + rng.normal(0, 3))
            )
            for cam in (master, slave):
                fs = cam.poll(1.0)
                assert fs is not None
                checker.feed(fs.serial, fs.timing)
    finally:
        master.stop()
        slave.stop()
    report = checker.report()
    assert report.ok, report.to_dict()
    found = report.cameras["100000000002"]
    assert found.matched_pairs == 90
    assert found.drift_ppm == pytest.approx(40.0, abs=3.0)


def test_enumerate_skips_other_models_and_filters_serials() -> None:
    d415 = make_software_d415("300000000001")
    other = rs.software_device()
    other.register_info(rs.camera_info.name, "Intel RealSense T265")

    class Ctx:
        def query_devices(self) -> list[Any]:
            return [other, d415.device]

    cams = enumerate_cameras(context=Ctx())
    assert [c.info.serial for c in cams] == ["300000000001"]
    assert (
        enumerate_cameras(context=Ctx(), serials=["300000000001"])[0].info.serial == "300000000001"
    )


# -- which DeviceError kind, with the SDK's words kept ---------------------------------------------


def test_a_serial_that_is_not_connected_is_a_not_found_error() -> None:
    d415 = make_software_d415("300000000001")

    class Ctx:
        def query_devices(self) -> list[Any]:
            return [d415.device]

    with pytest.raises(DeviceNotFoundError, match=r"D415 300000000009 not connected") as exc:
        enumerate_cameras(context=Ctx(), serials=["300000000009"])
    assert "300000000001" in str(exc.value)


def test_a_sensor_streamed_by_another_handle_is_busy() -> None:
    sw = make_software_d415()
    first = started(sw)
    second = RealSenseCamera(sw.device)
    second.configure(stream=StreamConfig(), options=OPTIONS, sync_mode=SyncMode.SLAVE)
    try:
        with pytest.raises(DeviceBusyError, match="is another program using it") as exc:
            second.start()
        assert exc.value.backend_error is not None
        assert "is streaming" in exc.value.backend_error  # the SDK's own words
        assert isinstance(exc.value.__cause__, RuntimeError)
    finally:
        first.stop()


class _FailingSensor:
    """A software sensor whose methods named in ``fail`` raise ``RuntimeError(message)``."""

    def __init__(self, sensor: Any, message: str, fail: tuple[str, ...]) -> None:
        self._sensor = sensor
        self._message = message
        self._fail = fail

    def __getattr__(self, name: str) -> Any:
        if name in self._fail:

            def failing(*_args: Any) -> None:
                raise RuntimeError(self._message)

            return failing
        return getattr(self._sensor, name)


class _DeviceWith:
    """An ``rs.device`` stand-in handing out a given depth sensor (everything else delegated)."""

    def __init__(self, device: Any, sensor: Any) -> None:
        self._device = device
        self._sensor = sensor

    def first_depth_sensor(self) -> Any:
        return self._sensor

    def __getattr__(self, name: str) -> Any:
        return getattr(self._device, name)


def failing_camera(message: str, *fail: str) -> tuple[SwCamera, RealSenseCamera]:
    sw = make_software_d415()
    cam = RealSenseCamera(_DeviceWith(sw.device, _FailingSensor(sw.sensor, message, fail)))
    cam.configure(stream=StreamConfig(), options=OPTIONS, sync_mode=SyncMode.SLAVE)
    return sw, cam


# librealsense's words (its messages, with the errno text after "Last Error:").
_GONE = "xioctl(VIDIOC_STREAMON) failed, errno=19 Last Error: No such device"
_BUSY = "xioctl(VIDIOC_S_FMT) failed, errno=16 Last Error: Device or resource busy"


@pytest.mark.parametrize(
    ("message", "kind"),
    [
        (_GONE, DeviceDisconnectedError),
        ("Camera disconnected!", DeviceDisconnectedError),
        (_BUSY, DeviceBusyError),
        ("Failed to open /dev/video2, Last Error: Permission denied", DevicePermissionError),
        ("USB CAM overflow: Operation timed out", DeviceTimeoutError),
        ("hwmon command 0x80 failed. Error type: No data to return (-21).", DeviceError),
    ],
)
def test_an_sdk_failure_is_the_kind_its_words_say(message: str, kind: type[DeviceError]) -> None:
    _, cam = failing_camera(message, "start")
    with pytest.raises(DeviceError, match=r"cannot start streaming .*replug") as exc:
        cam.start()
    assert type(exc.value) is kind
    assert exc.value.backend_error == message
    assert exc.value.backend_errno is None


def test_stopping_a_camera_that_went_away_is_a_disconnected_error() -> None:
    sw, cam = failing_camera(_GONE, "stop")
    cam.start()
    with pytest.raises(DeviceDisconnectedError, match="stopping failed") as exc:
        cam.stop()
    assert exc.value.backend_error == _GONE
    assert not cam.is_streaming
    sw.sensor.stop()
    sw.sensor.close()


# -- issue 13: no silent mis-pairing without metadata ----------------------------------------------


def _inject_no_metadata(sw: SwCamera, stream: str, *, number: int, capture: int) -> None:
    """One frame as the V4L2 backend without the kernel patch delivers it: ``system_time``
    stamp (host receive ms) and a host-side frame number counted per stream."""
    prof, bpp, dtype = (sw.depth, 2, np.uint16) if stream == "depth" else (sw.ir, 1, np.uint8)
    frame = rs.software_video_frame()
    frame.pixels = np.full((H, W), capture % 200 + 1, dtype)
    frame.bpp = bpp
    frame.stride = W * bpp
    frame.timestamp = 1_767_225_600_000.0 + capture * 33.333 + (0.4 if stream == "ir" else 0.0)
    frame.frame_number = number
    frame.domain = rs.timestamp_domain.system_time
    frame.profile = prof.as_video_stream_profile()
    if stream == "depth":
        frame.depth_units = 0.001
    sw.sensor.on_video_frame(frame)


def test_a_lost_ir_frame_without_metadata_never_pairs_different_exposures(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Host-side numbers shift by one on the IR stream after its lost frame; pairing by those
    numbers would pair depth k with IR k+1 for the rest of the run."""
    sw = make_software_d415()
    with caplog.at_level("WARNING"), started(sw, SyncMode.DEFAULT) as cam:
        ir_number = 0
        for capture in range(12):
            _inject_no_metadata(sw, "depth", number=capture, capture=capture)
            if capture != 4:  # IR of capture 4 is lost on USB
                _inject_no_metadata(sw, "ir", number=ir_number, capture=capture)
                ir_number += 1
        sets = []
        while (fs := cam.poll(0.3)) is not None:
            sets.append(fs)
    assert len(sets) == 11
    for fs in sets:  # both images of every set come from one capture
        assert int(fs.infrared.image[0, 0]) == int(fs.depth.image[0, 0])
        assert abs(fs.infrared.timing.timestamp_ms - fs.depth.timing.timestamp_ms) < 1.0
    assert [int(fs.depth.image[0, 0]) - 1 for fs in sets] == [c for c in range(12) if c != 4]
    assert cam.stats.incomplete_framesets == 1
    assert "NO FRAME METADATA" in caplog.text
    assert "FORCE_RSUSB_BACKEND" in caplog.text
    assert "librealsense2-dkms" in caplog.text


def test_synced_capture_without_metadata_can_be_forced_and_says_so(
    caplog: pytest.LogCaptureFixture,
) -> None:
    sw = make_software_d415()
    cam = RealSenseCamera(sw.device, allow_no_metadata=True)
    cam.configure(stream=StreamConfig(), options=OPTIONS, sync_mode=SyncMode.SLAVE)
    with caplog.at_level("WARNING"), cam:
        cam.start()
        for capture in range(3):
            _inject_no_metadata(sw, "depth", number=capture, capture=capture)
            _inject_no_metadata(sw, "ir", number=capture, capture=capture)
        got = [cam.poll(0.5) for _ in range(3)]
    assert all(fs is not None and not fs.timing.has_hardware_timestamps for fs in got)
    assert "(slave): NO FRAME METADATA" in caplog.text


def test_configure_rig_refuses_synced_cameras_without_metadata_unless_forced() -> None:
    from mocaprig.acquire.d415_sync import configure_rig, start_rig

    for allow in (False, True):
        sws = [make_software_d415(f"40000000000{i}") for i in range(2)]
        cams = [RealSenseCamera(sw.device) for sw in sws]
        configure_rig(cams, allow_no_metadata=allow)
        assert all(c.allow_no_metadata is allow for c in cams)
        start_rig(cams)
        try:
            _inject_no_metadata(sws[1], "depth", number=0, capture=0)
            if allow:
                _inject_no_metadata(sws[1], "ir", number=0, capture=0)
                assert cams[1].poll(0.5) is not None
            else:
                with pytest.raises(DeviceError, match=r"refused.*--allow-no-metadata"):
                    cams[1].poll(0.5)
        finally:
            for c in cams:
                c.stop()
