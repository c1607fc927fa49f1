"""The ``DepthCamera`` protocol: the seam between acquisition and a RealSense D415 (or its mock).

pyrealsense2 has no backend seam like pyusb's, so the toolkit talks to depth cameras through
this small protocol (house style habit 4). Two implementations exist:

* ``acquire.realsense`` wraps pyrealsense2 2.59.1 (sensor-level API, hardware sync, metadata);
  :func:`acquire.camera_backends.open_cameras` opens either by backend name;
* the mock in ``drivers_mock`` (found through the ``mocaprig.mocks`` entry point ``d415``)
  renders the simulated world. ``acquire`` never imports ``drivers_mock``.

Names follow the SDK and the D415 datasheet (realsense-d415.md §1–§3): the left infrared imager is
``rs.stream.infrared`` index 1 (Y8), depth is ``rs.stream.depth`` index 0 (Z16),
``inter_cam_sync_mode`` takes 0 (default), 1 (master) or 2 (slave) on a D415.

Contract every implementation honours (the mock too):

* ``configure(stream=, options=, sync_mode=)`` is called while the camera is stopped; the sync
  mode is applied **before** the sensor is opened (the option is read-only while open, §2.3).
  Calling it while streaming raises :class:`~mocaprig.errors.DeviceError`. Sync mode values above
  2 raise :class:`~mocaprig.errors.ValidationError` (:func:`check_sync_mode`).
* ``start()`` opens the sensor and starts streaming; ``stop()`` stops and closes it; ``close()``
  releases the device (``stop()`` first when streaming). The context manager calls ``close()``.
* ``poll(timeout_s)`` returns the next complete :class:`FrameSet` (left IR + depth of the same
  capture, equal frame counters) or ``None`` when none arrives within ``timeout_s``. Framesets of
  one camera come in capture order; nothing is delivered twice. A simulated camera may return
  immediately (simulated time); callers must not assume framesets of *different* cameras arrive
  in time order, and must measure durations with ``FrameTiming.host_time_ns``, never wall time.
* Failures are :class:`~mocaprig.errors.DeviceError` subclasses that say what a user can act on:
  a camera that went away (cable pulled, ``disconnect`` fault) raises
  :class:`~mocaprig.errors.DeviceDisconnectedError` from then on; a requested serial that is not
  connected, :class:`~mocaprig.errors.DeviceNotFoundError` (the message lists what is); a sensor
  held by another program, :class:`~mocaprig.errors.DeviceBusyError`; a user without access,
  :class:`~mocaprig.errors.DevicePermissionError`. The backend's own words stay in
  ``backend_error`` and the cause is chained. Misuse (configure while streaming, poll before
  start) stays a plain :class:`~mocaprig.errors.DeviceError`.
* Without per-frame metadata a camera in master or slave mode refuses to deliver frames
  (:class:`~mocaprig.errors.DeviceError` naming the kernel fix) unless its
  :class:`MetadataPolicy` ``allow_no_metadata`` is set (``d415_sync.configure_rig`` sets it);
  either way a run without metadata is announced by a warning. IR and depth are then paired by
  timestamp, never by the host-side per-stream frame numbers.
* :class:`FrameTiming` carries the metadata untouched (device counter and µs timestamps, no
  unwrapping of the u32 device clock). When per-frame metadata is missing (no kernel patch), the
  domain is ``SYSTEM_TIME``, the hardware timestamps are ``None`` and the counter is host-made.

The mock factory (entry point ``mocaprig.mocks:d415``) is called with keyword options only.
``mocaprig d415 ... --mock [--mock-fault FAULT]`` passes ``seed``, ``fault`` (``None`` or a fault
name the mock defines, e.g. ``"slave-trigger-cut"``), ``seconds`` (simulated session length) and
``images=False`` (timing-only commands); it returns ``list[DepthCamera]``, unconfigured, and the
command makes the first camera the master.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Final, Protocol, Self, runtime_checkable

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ValidationError
from mocaprig.validation import check_range, check_shape

__all__ = [
    "ALLOWED_MODES",
    "D415_PRODUCT_NAME",
    "CameraInfo",
    "D415Frame",
    "DepthCamera",
    "Distortion",
    "Extrinsics",
    "FrameSet",
    "FrameTiming",
    "Intrinsics",
    "MetadataPolicy",
    "SensorOptions",
    "StreamConfig",
    "StreamKind",
    "SyncMode",
    "TimestampDomain",
    "check_sync_mode",
]

D415_PRODUCT_NAME: Final = "Intel RealSense D415"


# ---------------------------------------------------------------------------------------------
# Closed choices


class SyncMode(enum.IntEnum):
    """``rs.option.inter_cam_sync_mode`` values a D415 accepts (realsense-d415.md §2.3).

    3 (full slave) and 4..260 (genlock) exist only on global-shutter sensors; a D415 rejects them.
    """

    DEFAULT = 0
    """Free-running: no sync output or input."""
    MASTER = 1
    """Drives the sync pin (pin 5, 1.8 V, ~50 µs) once per frame."""
    SLAVE = 2
    """Follows pin 5, but free-runs silently when no trigger arrives (§2.4)."""


def check_sync_mode(value: int, *, serial: str | None = None) -> SyncMode:
    """Return ``value`` as a :class:`SyncMode`, rejecting what a D415 does not support.

    Raises:
        ValidationError: ``value`` is not 0, 1 or 2.
    """
    try:
        return SyncMode(int(value))
    except ValueError as err:
        who = f"D415 {serial}" if serial else "a D415"
        msg = (
            f"inter_cam_sync_mode {value!r} is not supported by {who}: its rolling-shutter "
            "imagers take only 0 (default), 1 (master) or 2 (slave); full slave (3) and genlock "
            "(4..260) exist only on global-shutter cameras such as the D435"
        )
        raise ValidationError(msg) from err


class TimestampDomain(enum.Enum):
    """``rs.timestamp_domain`` members (verified in pyrealsense2 2.59.1)."""

    HARDWARE_CLOCK = "hardware_clock"
    """The camera's own u32 µs clock; needs per-frame metadata."""
    SYSTEM_TIME = "system_time"
    """Host time: per-frame metadata is missing; nothing about sync can be verified."""
    GLOBAL_TIME = "global_time"
    """The camera clock mapped to the host clock by the SDK's global-time keeper (§2.7)."""


class StreamKind(enum.Enum):
    """The two streams the toolkit records from each D415."""

    INFRARED_LEFT = "infrared"
    """``rs.stream.infrared`` index 1 (left imager = depth viewpoint), ``rs.format.y8``."""
    DEPTH = "depth"
    """``rs.stream.depth`` index 0, ``rs.format.z16`` (0 = no data)."""

    @property
    def stream_index(self) -> int:
        """The SDK stream index (1 for the left IR imager, 0 for depth)."""
        return 1 if self is StreamKind.INFRARED_LEFT else 0


class Distortion(enum.Enum):
    """``rs.distortion`` members (verified in pyrealsense2 2.59.1)."""

    NONE = "none"
    MODIFIED_BROWN_CONRADY = "modified_brown_conrady"
    INVERSE_BROWN_CONRADY = "inverse_brown_conrady"
    FTHETA = "ftheta"
    BROWN_CONRADY = "brown_conrady"
    KANNALA_BRANDT4 = "kannala_brandt4"


# ---------------------------------------------------------------------------------------------
# Records


@dataclass(frozen=True, slots=True)
class CameraInfo:
    """``rs.camera_info`` strings of one device."""

    serial: str
    """``camera_info.serial_number``."""
    name: str = D415_PRODUCT_NAME
    """``camera_info.name``, e.g. ``"Intel RealSense D415"``."""
    firmware: str = ""
    """``camera_info.firmware_version``, e.g. ``"5.16.0.1"``; sync needs ≥ 5.9.15.1."""
    usb_type: str = ""
    """``camera_info.usb_type_descriptor``, e.g. ``"3.2"``; a ``"2.x"`` link limits the modes."""
    product_line: str = "D400"
    """``camera_info.product_line``."""

    def __post_init__(self) -> None:
        if not self.serial:
            msg = "CameraInfo.serial must be a non-empty serial number"
            raise ValidationError(msg)

    @property
    def is_usb3(self) -> bool:
        """``True`` when the link is USB 3 (an empty descriptor counts as unknown → ``True``)."""
        return not self.usb_type or self.usb_type.startswith("3")


ALLOWED_MODES: Final[frozenset[tuple[int, int, int]]] = frozenset(
    {(848, 480, 30), (1280, 720, 30), (848, 480, 90)}
)
"""``(width, height, fps)`` the toolkit records: a subset of the D415 USB3 grid (§1.2)."""


@dataclass(frozen=True, slots=True)
class StreamConfig:
    """One mode for both left IR (Y8) and depth (Z16); every camera of a rig runs the same one.

    Allowed: 848×480 @30 (default), 1280×720 @30, 848×480 @90 (§1.2; 30 fps is the 720p maximum).
    """

    width: int = 848
    height: int = 480
    fps: int = 30

    def __post_init__(self) -> None:
        if (self.width, self.height, self.fps) not in ALLOWED_MODES:
            allowed = ", ".join(f"{w}x{h}@{f}" for w, h, f in sorted(ALLOWED_MODES))
            msg = (
                f"D415 mode {self.width}x{self.height}@{self.fps} is not supported; "
                f"choose one of {allowed}"
            )
            raise ValidationError(msg)

    @property
    def frame_period_us(self) -> float:
        """Nominal frame period in µs."""
        return 1e6 / self.fps

    def __str__(self) -> str:
        return f"{self.width}x{self.height}@{self.fps}"


@dataclass(frozen=True, slots=True)
class SensorOptions:
    """Manual exposure, gain and projector settings of the depth sensor ("Stereo Module").

    Auto-exposure is always disabled when these are applied (markers stay saturated, the
    background dark, rolling-shutter smear small; realsense-d415.md §1.6).
    """

    exposure_us: int = 8500
    """``rs.option.exposure`` in µs, 1..165000; must not exceed the frame period."""
    gain: int = 16
    """``rs.option.gain``, 16..248."""
    laser_power_mw: int = 150
    """``rs.option.laser_power`` (≈ mW), 0..360 in steps of 30."""
    emitter_enabled: bool = True
    """``rs.option.emitter_enabled``: ``True`` = laser (1), ``False`` = off (0)."""

    def __post_init__(self) -> None:
        check_range(self.exposure_us, 1, 165_000, name="exposure_us")
        check_range(self.gain, 16, 248, name="gain")
        check_range(self.laser_power_mw, 0, 360, name="laser_power_mw")
        if self.laser_power_mw % 30:
            msg = f"laser_power_mw must be a multiple of 30 (0..360), got {self.laser_power_mw}"
            raise ValidationError(msg)

    def check_fits(self, stream: StreamConfig) -> None:
        """Reject an exposure longer than the frame period (it silently lowers the fps, §1.6)."""
        if self.exposure_us > stream.frame_period_us:
            msg = (
                f"exposure_us {self.exposure_us} exceeds the frame period of {stream} "
                f"({stream.frame_period_us:.0f} µs) and would lower the frame rate; "
                "shorten the exposure or lower the fps"
            )
            raise ValidationError(msg)


@dataclass(frozen=True, slots=True)
class Intrinsics:
    """``rs.intrinsics`` of one stream (pixels; D415 IR/depth: Brown–Conrady, zero coeffs)."""

    width: int
    height: int
    fx: float
    fy: float
    ppx: float
    ppy: float
    model: Distortion = Distortion.BROWN_CONRADY
    coeffs: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0 or not (self.fx > 0 and self.fy > 0):
            msg = f"intrinsics need positive size and focal lengths, got {self!r}"
            raise ValidationError(msg)
        if len(self.coeffs) != 5:
            msg = f"intrinsics need 5 distortion coefficients, got {len(self.coeffs)}"
            raise ValidationError(msg)

    def camera_matrix(self) -> npt.NDArray[np.float64]:
        """The 3×3 pinhole matrix K (pixels)."""
        return np.array(
            [[self.fx, 0.0, self.ppx], [0.0, self.fy, self.ppy], [0.0, 0.0, 1.0]], np.float64
        )


@dataclass(frozen=True, slots=True)
class Extrinsics:
    """``rs.extrinsics``: maps points of one stream's frame into another's, ``p' = R p + t``.

    ``rotation`` holds 9 floats **column-major** (librealsense convention); ``translation_m``
    is in metres. Depth → left IR is the identity on a D415 (§1.2).
    """

    rotation: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if len(self.rotation) != 9 or len(self.translation_m) != 3:
            msg = "extrinsics need 9 rotation values (column-major) and 3 translation values"
            raise ValidationError(msg)

    def matrix(self) -> npt.NDArray[np.float64]:
        """The 4×4 homogeneous transform (row-major numpy; R transposed from column-major)."""
        out = np.eye(4)
        out[:3, :3] = np.asarray(self.rotation, np.float64).reshape(3, 3).T
        out[:3, 3] = self.translation_m
        return out


@dataclass(frozen=True, slots=True)
class FrameTiming:
    """Timing of one frame, straight from ``rs.frame_metadata_value`` (realsense-d415.md §2.8).

    Device values are the camera's own u32 µs clock, not unwrapped; host values come from the
    host. ``None`` means the attribute was not in this frame's metadata.
    """

    frame_counter: int
    """``frame_counter`` (hardware frame number; host-made when metadata is missing)."""
    sensor_timestamp_us: int | None
    """``sensor_timestamp``: middle of exposure, device clock, µs."""
    frame_timestamp_us: int | None
    """``frame_timestamp``: start of the USB transfer, device clock, µs."""
    time_of_arrival_ms: int | None
    """``time_of_arrival``: host epoch clock, ms."""
    timestamp_domain: TimestampDomain
    """Domain of :attr:`timestamp_ms` (``frame.get_frame_timestamp_domain()``)."""
    host_time_ns: int
    """Host receive time (``time.monotonic_ns()`` on a real rig; the simulated host clock in a
    mock). Durations are measured on this clock."""
    timestamp_ms: float = float("nan")
    """``frame.get_timestamp()`` in ms, in :attr:`timestamp_domain` (global time: host-mapped)."""

    @property
    def has_hardware_timestamps(self) -> bool:
        """``True`` when device timestamps are present and the domain is not ``SYSTEM_TIME``."""
        return (
            self.timestamp_domain is not TimestampDomain.SYSTEM_TIME
            and self.sensor_timestamp_us is not None
            and self.frame_timestamp_us is not None
        )


@dataclass(frozen=True, slots=True)
class D415Frame:
    """One image of one stream: left IR ``(H, W) uint8`` or depth ``(H, W) uint16``."""

    stream: StreamKind
    image: npt.NDArray[Any] = field(repr=False)
    timing: FrameTiming

    def __post_init__(self) -> None:
        check_shape(self.image, ["H", "W"], name=f"{self.stream.value} image")
        want = np.uint8 if self.stream is StreamKind.INFRARED_LEFT else np.uint16
        if self.image.dtype != want:
            msg = (
                f"{self.stream.value} image must be {np.dtype(want).name}, "
                f"got {self.image.dtype.name}"
            )
            raise ValidationError(msg)


@dataclass(frozen=True, slots=True)
class FrameSet:
    """Left IR and depth of the same capture of one camera (equal frame counters)."""

    serial: str
    infrared: D415Frame
    depth: D415Frame
    depth_scale_m: float
    """Metres per Z16 unit (``depth_frame.get_units()``; 0.001 by default)."""

    def __post_init__(self) -> None:
        if self.infrared.stream is not StreamKind.INFRARED_LEFT:
            msg = "FrameSet.infrared must hold the left IR stream"
            raise ValidationError(msg)
        if self.depth.stream is not StreamKind.DEPTH:
            msg = "FrameSet.depth must hold the depth stream"
            raise ValidationError(msg)
        if self.infrared.image.shape != self.depth.image.shape:
            msg = (
                f"D415 {self.serial}: IR {self.infrared.image.shape} and depth "
                f"{self.depth.image.shape} differ; both streams must run one mode"
            )
            raise ValidationError(msg)
        check_range(self.depth_scale_m, 1e-6, 1e-2, name="depth_scale_m")

    @property
    def timing(self) -> FrameTiming:
        """The depth frame's timing (IR and depth share counter and timestamps)."""
        return self.depth.timing

    def depth_m(self) -> npt.NDArray[np.float64]:
        """Depth in metres (0 where the camera had no data)."""
        return self.depth.image.astype(np.float64) * self.depth_scale_m


# ---------------------------------------------------------------------------------------------
# The protocol


@runtime_checkable
class DepthCamera(Protocol):
    """One D415 (real or simulated); see the module docstring for the contract."""

    @property
    def info(self) -> CameraInfo:
        """Identity strings of the device."""
        ...

    @property
    def depth_scale_m(self) -> float:
        """Metres per Z16 unit."""
        ...

    @property
    def sync_mode(self) -> SyncMode:
        """The ``inter_cam_sync_mode`` currently set."""
        ...

    @property
    def is_streaming(self) -> bool:
        """``True`` between :meth:`start` and :meth:`stop`."""
        ...

    def configure(
        self, *, stream: StreamConfig, options: SensorOptions, sync_mode: SyncMode
    ) -> None:
        """Set mode, manual exposure/gain/laser and the sync mode (before the sensor opens)."""
        ...

    def start(self) -> None:
        """Open the sensor with IR(1) Y8 + depth Z16 and start streaming."""
        ...

    def stop(self) -> None:
        """Stop streaming and close the sensor (no-op when stopped)."""
        ...

    def poll(self, timeout_s: float = 0.0) -> FrameSet | None:
        """The next complete frameset, or ``None`` if none arrives within ``timeout_s``."""
        ...

    def intrinsics(self) -> Intrinsics:
        """Intrinsics of the configured mode (left IR and depth are identical on a D415)."""
        ...

    def extrinsics_ir_to_depth(self) -> Extrinsics:
        """Left IR → depth extrinsics (identity on a D415)."""
        ...

    def close(self) -> None:
        """Stop and release the device."""
        ...

    def __enter__(self) -> Self: ...

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None: ...


@runtime_checkable
class MetadataPolicy(Protocol):
    """A camera that can be told to deliver synced frames without per-frame metadata.

    ``allow_no_metadata`` is ``False`` by default: a master/slave camera whose frames carry no
    hardware timestamps refuses them (sync could not be verified, frames cannot be counted).
    """

    allow_no_metadata: bool
