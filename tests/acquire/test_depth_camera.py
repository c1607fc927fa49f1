"""The DepthCamera protocol's records, validation and backend registry."""

from __future__ import annotations

import numpy as np
import pytest

from mocaprig.acquire import camera_backends, mocks
from mocaprig.acquire.camera_backends import CAMERA_BACKENDS, open_cameras, register_camera_backend
from mocaprig.acquire.depth_camera import (
    ALLOWED_MODES,
    CameraInfo,
    D415Frame,
    DepthCamera,
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
from mocaprig.errors import DeviceError, ValidationError


def timing(
    counter: int = 1, *, domain: TimestampDomain = TimestampDomain.HARDWARE_CLOCK
) -> FrameTiming:
    hw = domain is not TimestampDomain.SYSTEM_TIME
    return FrameTiming(
        frame_counter=counter,
        sensor_timestamp_us=1000 if hw else None,
        frame_timestamp_us=13000 if hw else None,
        time_of_arrival_ms=1_767_225_600_000,
        timestamp_domain=domain,
        host_time_ns=5,
    )


@pytest.mark.parametrize(("w", "h", "fps"), sorted(ALLOWED_MODES))
def test_allowed_modes_are_accepted(w: int, h: int, fps: int) -> None:
    assert str(StreamConfig(w, h, fps)) == f"{w}x{h}@{fps}"


def test_default_mode_is_848x480_at_30() -> None:
    assert (StreamConfig().width, StreamConfig().height, StreamConfig().fps) == (848, 480, 30)
    assert StreamConfig().frame_period_us == pytest.approx(33_333.33, abs=0.01)


@pytest.mark.parametrize(("w", "h", "fps"), [(1280, 720, 90), (1280, 720, 60), (640, 480, 30)])
def test_other_modes_are_rejected(w: int, h: int, fps: int) -> None:
    with pytest.raises(ValidationError, match="not supported; choose one of"):
        StreamConfig(w, h, fps)


@pytest.mark.parametrize("value", [0, 1, 2])
def test_sync_modes_zero_to_two_are_valid(value: int) -> None:
    assert check_sync_mode(value) is SyncMode(value)


@pytest.mark.parametrize("value", [3, 4, 258, 260, -1])
def test_sync_modes_above_two_are_rejected_for_a_d415(value: int) -> None:
    with pytest.raises(ValidationError, match="rolling-shutter") as info:
        check_sync_mode(value, serial="8225")
    assert "D415 8225" in str(info.value)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"exposure_us": 0},
        {"exposure_us": 200_000},
        {"gain": 8},
        {"gain": 300},
        {"laser_power_mw": 400},
        {"laser_power_mw": 100},
    ],
)
def test_sensor_options_are_validated(kwargs: dict[str, int]) -> None:
    with pytest.raises(ValidationError):
        SensorOptions(**kwargs)  # type: ignore[arg-type]


def test_exposure_longer_than_the_frame_period_is_refused() -> None:
    SensorOptions(exposure_us=30_000).check_fits(StreamConfig())
    with pytest.raises(ValidationError, match="lower the frame rate"):
        SensorOptions(exposure_us=20_000).check_fits(StreamConfig(848, 480, 90))


def test_records_are_frozen() -> None:
    info = CameraInfo(serial="1")
    with pytest.raises(AttributeError):
        info.serial = "2"  # type: ignore[misc]
    with pytest.raises(ValidationError):
        CameraInfo(serial="")
    assert not CameraInfo(serial="1", usb_type="2.1").is_usb3


def test_intrinsics_and_extrinsics() -> None:
    intr = Intrinsics(848, 480, 623.0, 623.0, 421.6, 239.6)
    assert intr.model is Distortion.BROWN_CONRADY
    np.testing.assert_allclose(intr.camera_matrix()[0], [623.0, 0.0, 421.6])
    with pytest.raises(ValidationError):
        Intrinsics(848, 480, -1.0, 623.0, 421.6, 239.6)
    # column-major rotation: a 90° turn about z
    ext = Extrinsics(rotation=(0, 1, 0, -1, 0, 0, 0, 0, 1), translation_m=(0.055, 0, 0))
    m = ext.matrix()
    np.testing.assert_allclose(m[:3, :3] @ [1, 0, 0], [0, 1, 0])
    np.testing.assert_allclose(m[:3, 3], [0.055, 0, 0])


def test_timing_knows_whether_it_has_hardware_timestamps() -> None:
    assert timing().has_hardware_timestamps
    assert not timing(domain=TimestampDomain.SYSTEM_TIME).has_hardware_timestamps


def test_frameset_checks_streams_dtypes_and_shapes() -> None:
    ir = D415Frame(StreamKind.INFRARED_LEFT, np.zeros((480, 848), np.uint8), timing())
    depth = D415Frame(StreamKind.DEPTH, np.ones((480, 848), np.uint16), timing())
    fs = FrameSet("1", ir, depth, 0.001)
    assert fs.timing is depth.timing
    assert fs.depth_m()[0, 0] == pytest.approx(0.001)
    with pytest.raises(ValidationError, match="uint16"):
        D415Frame(StreamKind.DEPTH, np.zeros((480, 848), np.uint8), timing())
    with pytest.raises(ValidationError, match="wrong shape"):
        D415Frame(StreamKind.INFRARED_LEFT, np.zeros((480, 848, 3), np.uint8), timing())
    with pytest.raises(ValidationError, match="left IR"):
        FrameSet("1", depth, depth, 0.001)
    small = D415Frame(StreamKind.DEPTH, np.ones((240, 424), np.uint16), timing())
    with pytest.raises(ValidationError, match="differ"):
        FrameSet("1", ir, small, 0.001)
    assert StreamKind.INFRARED_LEFT.stream_index == 1
    assert StreamKind.DEPTH.stream_index == 0


def test_registry_has_realsense_and_mock_and_accepts_more() -> None:
    assert {"realsense", "mock"} <= set(CAMERA_BACKENDS)
    register_camera_backend("none", lambda **_k: [])
    try:
        assert open_cameras("none") == []
    finally:
        camera_backends._BACKENDS.pop("none")
    with pytest.raises(ValidationError, match="unknown camera backend"):
        open_cameras("nope")


def test_unknown_mock_name_says_how_to_fix() -> None:
    with pytest.raises(DeviceError, match="reinstall mocaprig"):
        mocks.load_mock_factory("no-such-mock")


def test_mock_backend_yields_protocol_cameras() -> None:
    cams = open_cameras("mock", seed=0, seconds=3.0, images=False)
    assert len(cams) >= 2
    for cam in cams:
        assert isinstance(cam, DepthCamera)
        assert cam.info.name == "Intel RealSense D415"
        with pytest.raises(ValidationError):
            cam.configure(stream=StreamConfig(), options=SensorOptions(), sync_mode=3)  # type: ignore[arg-type]
