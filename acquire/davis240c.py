"""DAVIS240C event camera over libusb (pyusb): discovery, configuration and streaming.

The protocol is in ``docs/davis240c-usb.md`` (shared docs): vendor request 0xBF reads/writes
one 32-bit register (big-endian), 0xC2 writes several at once; data arrive on bulk EP 0x82 as
16-bit words decoded by :mod:`mocaprig.acquire.davis240c_decode`.

Usage::

    with Davis240C.open() as cam:   # the mock: Davis240C.open(backend=load_mock_backend())
        cam.start()
        for packet in cam.packets(timeout_s=1.0):
            handle(packet.events, packet.frames, packet.imu, packet.specials)

Streaming uses two threads: a *reader* that only keeps EP 0x82 drained (one synchronous
``read_size``-byte bulk read at a time, short timeout) and hands raw chunks over, and a
*decoder* that turns them into :class:`~mocaprig.acquire.davis240c_decode.DavisPacket` objects in a
bounded queue. A slow consumer never blocks either thread: packets that do not fit are dropped
and counted by kind (:class:`StreamStats`); their special events (timestamp resets, triggers)
are kept and delivered with the next packet. A USB error other than a timeout (unplugged cable)
stops the stream cleanly: everything already received is decoded and delivered, then
:meth:`Davis240C.packets` raises :class:`~mocaprig.errors.DeviceError`.
"""

from __future__ import annotations

import collections
import errno
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from importlib.resources import files
from types import TracebackType
from typing import Any, BinaryIO, Final, Self

import numpy as np

from mocaprig.acquire.davis240c_config import (
    ApsParam,
    BiasPreset,
    DavisSettings,
    DeviceClocks,
    DvsParam,
    ExtInputParam,
    ImuParam,
    Module,
    MuxParam,
    RegisterWrite,
    SysInfoParam,
    UsbParam,
    default_config_writes,
)
from mocaprig.acquire.davis240c_decode import DavisDecoder, DavisPacket, DecodeStats
from mocaprig.acquire.events import empty_events
from mocaprig.errors import DeviceError, ValidationError

__all__ = [
    "DATA_ENDPOINT",
    "PRODUCT_ID_FX2",
    "PRODUCT_ID_FX3",
    "REQUIRED_FIRMWARE_FX2",
    "REQUIRED_FIRMWARE_FX3",
    "REQUIRED_LOGIC_PATCH",
    "REQUIRED_LOGIC_VERSION",
    "UDEV_RULE",
    "VENDOR_ID",
    "Davis240C",
    "DavisInfo",
    "DavisPacket",
    "DavisUsbDevice",
    "StreamStats",
    "find_davis",
    "load_mock_backend",
]

_log = logging.getLogger(__name__)

VENDOR_ID: Final = 0x152A
PRODUCT_ID_FX2: Final = 0x841B  # DAVIS240A/B/C cameras
PRODUCT_ID_FX3: Final = 0x841A  # FX3 boards (DAVIS240C chip on an FX3 dev kit: same words)
REQUIRED_FIRMWARE_FX2: Final = 4
REQUIRED_FIRMWARE_FX3: Final = 6
REQUIRED_LOGIC_VERSION: Final = 18
REQUIRED_LOGIC_PATCH: Final = 1
DATA_ENDPOINT: Final = 0x82
VR_FPGA_CONFIG: Final = 0xBF
VR_FPGA_CONFIG_MULTIPLE: Final = 0xC2
_MAX_MULTIPLE: Final = 85  # entries per 0xC2 request (510 bytes; note §2)
_CTRL_TIMEOUT_MS: Final = 1000
_CHIP_ID_DAVIS240C: Final = 2
_MAX_CARRIED_SPECIALS: Final = 65536  # specials kept from dropped packets

#: The udev rule shipped with the package (install it to use the camera without root).
UDEV_RULE = files("acquire") / "data" / "99-mocaprig-davis.rules"

_UDEV_HINT = (
    f"install the udev rule: sudo cp {UDEV_RULE} /etc/udev/rules.d/ && "
    "sudo udevadm control --reload-rules && sudo udevadm trigger, then unplug and replug "
    "the camera"
)
_FLASH_HINT = (
    "reflash it with iniVation's Flashy tool (part of DV) to FX2 firmware "
    f"{REQUIRED_FIRMWARE_FX2} / logic {REQUIRED_LOGIC_VERSION} (patch >= {REQUIRED_LOGIC_PATCH})"
)

# libusb error codes (pyusb ``USBError.backend_error_code``).
_LIBUSB_ERROR_ACCESS = -3
_LIBUSB_ERROR_NO_DEVICE = -4
_LIBUSB_ERROR_BUSY = -6


def load_mock_backend(**kwargs: Any) -> Any:
    """The DAVIS240C mock ``usb.backend.IBackend`` from the ``mocaprig.mocks`` entry point.

    ``kwargs`` go to the factory. acquire/ never imports drivers_mock/ itself.

    Raises:
        DeviceError: no mock is registered (the package is not installed with its mocks).
    """
    try:
        ep = entry_points(group="mocaprig.mocks")["davis240c"]
    except KeyError as err:
        msg = "no 'davis240c' mock in the mocaprig.mocks entry points; run `pip install -e .`"
        raise DeviceError(msg) from err
    try:
        factory: Callable[..., Any] = ep.load()
    except ImportError as err:
        msg = f"the DAVIS240C mock ({ep.value}) cannot be imported: {err}"
        raise DeviceError(msg) from err
    return factory(**kwargs)


# -- discovery ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DavisUsbDevice:
    """A DAVIS camera seen on the bus (found without claiming it).

    Attributes:
        bus: USB bus number.
        address: USB device address.
        product_id: 0x841B (FX2) or 0x841A (FX3).
        serial: Serial-number string, or None when it could not be read.
        firmware_version: ``bcdDevice & 0xFF``.
        logic_version: SYSINFO LOGIC_VERSION, or None when unreadable.
        logic_patch: SYSINFO LOGIC_PATCH, or None.
        error: Why something could not be read (e.g. permissions), or None.
    """

    bus: int
    address: int
    product_id: int
    serial: str | None
    firmware_version: int
    logic_version: int | None = None
    logic_patch: int | None = None
    error: str | None = None

    @property
    def kind(self) -> str:
        """'DAVIS FX2' or 'DAVIS FX3'."""
        return "DAVIS FX2" if self.product_id == PRODUCT_ID_FX2 else "DAVIS FX3"


def _usb() -> Any:
    import usb.core  # lazy: keep `mocaprig --help` fast
    import usb.util

    return usb


def _error_code(err: BaseException) -> tuple[int | None, int | None]:
    return getattr(err, "errno", None), getattr(err, "backend_error_code", None)


def _is_permission(err: BaseException) -> bool:
    en, code = _error_code(err)
    return en == errno.EACCES or code == _LIBUSB_ERROR_ACCESS


def _is_busy(err: BaseException) -> bool:
    en, code = _error_code(err)
    return en == errno.EBUSY or code == _LIBUSB_ERROR_BUSY


def _is_timeout(err: BaseException) -> bool:
    usb = _usb()
    en, _ = _error_code(err)
    return isinstance(err, usb.core.USBTimeoutError) or en == errno.ETIMEDOUT


def _read_serial(dev: Any) -> str:
    usb = _usb()
    if not dev.iSerialNumber:
        # libcaer 3.3.10+: a session-local name when the descriptor has no serial.
        return f"TMP{(int(dev.bus or 0) << 8) | int(dev.address or 0):05d}"
    serial = usb.util.get_string(dev, dev.iSerialNumber)
    return str(serial)


def _ctrl_read(dev: Any, module: int, param: int) -> int:
    data = dev.ctrl_transfer(0xC0, VR_FPGA_CONFIG, module, param, 4, _CTRL_TIMEOUT_MS)
    if len(data) != 4:
        msg = f"register ({module}, {param}) read returned {len(data)} bytes instead of 4"
        raise DeviceError(msg)
    return int.from_bytes(bytes(data), "big")


def _candidates(backend: Any) -> list[Any]:
    usb = _usb()
    found = usb.core.find(find_all=True, backend=backend, idVendor=VENDOR_ID)
    devs = [d for d in found if d.idProduct in (PRODUCT_ID_FX2, PRODUCT_ID_FX3)]
    return sorted(devs, key=lambda d: (d.idProduct != PRODUCT_ID_FX2, d.bus or 0, d.address or 0))


def find_davis(*, backend: Any = None) -> list[DavisUsbDevice]:
    """Every DAVIS camera (VID 0x152A, PID 0x841B/0x841A) on the bus, FX2 first.

    The interface is not claimed, so a camera in use by another process is still listed.
    Unreadable fields are None and ``error`` says why (usually permissions: the udev rule).
    """
    usb = _usb()
    out = []
    for dev in _candidates(backend):
        serial = logic = patch = None
        error = None
        try:
            serial = _read_serial(dev)
            logic = _ctrl_read(dev, Module.SYSINFO, SysInfoParam.LOGIC_VERSION)
            patch = _ctrl_read(dev, Module.SYSINFO, SysInfoParam.LOGIC_PATCH)
        except (usb.core.USBError, ValueError, DeviceError) as err:
            error = "permission denied; " + _UDEV_HINT if _is_permission(err) else str(err)
        finally:
            usb.util.dispose_resources(dev)
        out.append(
            DavisUsbDevice(
                bus=int(dev.bus or 0),
                address=int(dev.address or 0),
                product_id=int(dev.idProduct),
                serial=serial,
                firmware_version=int(dev.bcdDevice) & 0xFF,
                logic_version=logic,
                logic_patch=patch,
                error=error,
            )
        )
    return out


def _describe_bus(backend: Any) -> str:
    usb = _usb()
    try:
        devs = list(usb.core.find(find_all=True, backend=backend))
    except usb.core.USBError as err:  # pragma: no cover - enumeration itself failed
        return f"(cannot enumerate USB devices: {err})"
    if not devs:
        return "no USB devices at all"
    return ", ".join(
        f"{d.idVendor:04x}:{d.idProduct:04x} (bus {d.bus}, address {d.address})" for d in devs
    )


# -- device information and statistics ---------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DavisInfo:
    """What :meth:`Davis240C.open` read from the camera (libcaer ``caer_davis_info``)."""

    serial: str
    bus: int
    address: int
    product_id: int
    firmware_version: int
    logic_version: int
    logic_patch: int
    chip_id: int
    device_is_master: bool
    mux_has_statistics: bool
    dvs_size_x: int
    dvs_size_y: int
    dvs_orientation: int
    dvs_has_pixel_filter: bool
    dvs_has_background_activity_filter: bool
    dvs_has_roi_filter: bool
    dvs_has_skip_filter: bool
    dvs_has_polarity_filter: bool
    dvs_has_statistics: bool
    aps_size_x: int
    aps_size_y: int
    aps_orientation: int
    aps_color_filter: int
    aps_has_global_shutter: bool
    imu_type: int
    imu_orientation: int
    ext_input_has_generator: bool
    clocks: DeviceClocks

    @property
    def device_string(self) -> str:
        """dv-processing style name, e.g. ``DAVIS240C_00000042``."""
        chip = {0: "DAVIS240A", 1: "DAVIS240B", 2: "DAVIS240C"}.get(self.chip_id, "DAVIS")
        return f"{chip}_{self.serial}"

    def as_dict(self) -> dict[str, Any]:
        """Plain-JSON view (clocks as a nested dict)."""
        out: dict[str, Any] = {k: getattr(self, k) for k in self.__dataclass_fields__}
        c = self.clocks
        out["clocks"] = {
            "logic_mhz": c.logic_mhz,
            "adc_mhz": c.adc_mhz,
            "usb_mhz": c.usb_mhz,
            "deviation_x1000": c.deviation_x1000,
        }
        out["device_string"] = self.device_string
        return out


@dataclass(frozen=True, slots=True)
class StreamStats:
    """A snapshot of the streaming counters since :meth:`Davis240C.start`.

    Attributes:
        running: The reader is running.
        reads: Completed bulk reads.
        bytes_read: Bytes received from EP 0x82.
        read_timeouts: Bulk reads that returned nothing within the read timeout.
        raw_bytes_dropped: Raw bytes dropped because the decoder fell behind.
        bytes_discarded_before_reset: Bytes thrown away before our own timestamp reset.
        packets_delivered: Packets handed to the consumer queue.
        packets_dropped: Packets dropped because the consumer queue was full.
        events_dropped: Polarity events in dropped packets.
        frames_dropped: APS frames in dropped packets.
        imu_dropped: IMU samples in dropped packets.
        specials_dropped: Special events dropped (only beyond the carry-over limit).
        decode: The decoder's counters (malformed/skipped words, dropped frames...).
        error: The error that ended the stream, or None.
    """

    running: bool = False
    reads: int = 0
    bytes_read: int = 0
    read_timeouts: int = 0
    raw_bytes_dropped: int = 0
    bytes_discarded_before_reset: int = 0
    packets_delivered: int = 0
    packets_dropped: int = 0
    events_dropped: int = 0
    frames_dropped: int = 0
    imu_dropped: int = 0
    specials_dropped: int = 0
    decode: DecodeStats = field(default_factory=DecodeStats)
    error: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """Plain-JSON view."""
        out: dict[str, Any] = {
            k: getattr(self, k) for k in self.__dataclass_fields__ if k != "decode"
        }
        out["decode"] = self.decode.as_dict()
        return out


# -- the device --------------------------------------------------------------------------------

_STOP_SEQUENCE: Final[tuple[tuple[int, int], ...]] = (
    (Module.DVS, DvsParam.RUN),
    (Module.APS, ApsParam.RUN),
    (Module.IMU, ImuParam.RUN_ACCELEROMETER),
    (Module.IMU, ImuParam.RUN_GYROSCOPE),
    (Module.IMU, ImuParam.RUN_TEMPERATURE),
    (Module.EXTINPUT, ExtInputParam.RUN_DETECTOR),
    (Module.MUX, MuxParam.RUN),
    (Module.MUX, MuxParam.TIMESTAMP_RUN),
    (Module.USB, UsbParam.RUN),
    (Module.MUX, MuxParam.RUN_CHIP),
)
_PRODUCERS: Final[tuple[tuple[int, int], ...]] = (
    (Module.DVS, DvsParam.RUN),
    (Module.APS, ApsParam.RUN),
    (Module.IMU, ImuParam.RUN_ACCELEROMETER),
    (Module.IMU, ImuParam.RUN_GYROSCOPE),
    (Module.IMU, ImuParam.RUN_TEMPERATURE),
    (Module.EXTINPUT, ExtInputParam.RUN_DETECTOR),
)


class Davis240C:
    """One opened DAVIS240C (FX2, logic 18); a context manager that stops and closes it.

    Keyword-only options:
        serial: Open the camera with this serial number (default: the first one found).
        bus, address: Open the camera at this USB bus/address.
        backend: A pyusb ``IBackend`` (e.g. :func:`load_mock_backend`); None = libusb.
        bias_preset: Biases written by :meth:`send_default_config` (``BiasPreset`` or name).
        settings: Full settings (overrides ``bias_preset``).
        send_default_config: Write the settings at open (libcaer's ``sendDefaultConfig``).
        read_size: Bytes per bulk read (a multiple of 512).
        read_timeout_ms: Bulk read timeout; bounds how fast :meth:`stop` reacts.
        queue_packets: Capacity of the consumer queue (decoded packets).
        queue_bytes: Capacity of the consumer queue in payload bytes (events, frame pixels,
            IMU samples); whichever limit is reached first drops the next packet.
        raw_queue_bytes: Capacity of the reader -> decoder hand-off (bytes).
        settle_delays_s: (FIFO drain, bias settle, mux start) sleeps of the start sequence.
        raw_sink: A binary file that receives the raw bulk bytes the decoder sees (from the
            timestamp reset on), written by the decoder thread; for ``mocaprig davis decode``.

    Raises:
        DeviceError: not found (lists what is on the bus), permission denied (how to install
            the udev rule), busy, wrong firmware/logic (how to reflash), or not a DAVIS240C.
    """

    def __init__(
        self,
        *,
        serial: str | None = None,
        bus: int | None = None,
        address: int | None = None,
        backend: Any = None,
        bias_preset: BiasPreset | str = BiasPreset.DEFAULT,
        settings: DavisSettings | None = None,
        send_default_config: bool = True,
        read_size: int = 65536,
        read_timeout_ms: int = 100,
        queue_packets: int = 4096,
        queue_bytes: int = 128 << 20,
        raw_queue_bytes: int = 64 << 20,
        settle_delays_s: tuple[float, float, float] = (0.010, 0.200, 0.050),
        raw_sink: BinaryIO | None = None,
    ) -> None:
        if read_size <= 0 or read_size % 512:
            msg = f"read_size {read_size} must be a positive multiple of 512 bytes"
            raise ValidationError(msg)
        if queue_packets < 1 or queue_bytes < 1 or raw_queue_bytes < read_size:
            msg = "queue_packets and queue_bytes must be >= 1 and raw_queue_bytes >= read_size"
            raise ValidationError(msg)
        self._backend = backend
        self._settings = (
            settings if settings is not None else DavisSettings.from_preset(bias_preset)
        )
        self._read_size = read_size
        self._read_timeout_ms = read_timeout_ms
        self._queue_packets = queue_packets
        self._queue_bytes = queue_bytes
        self._raw_queue_bytes = raw_queue_bytes
        self._delays = settle_delays_s
        self._raw_sink = raw_sink
        self._dev: Any = None
        self._claimed = False
        self._lock = threading.Lock()  # serialises control transfers
        self._stream: _Stream | None = None
        self._dev = self._open(serial=serial, bus=bus, address=address)
        try:
            self._info = self._read_info()
            if send_default_config:
                self.send_default_config()
        except BaseException:
            self.close()
            raise

    @classmethod
    def open(cls, **options: Any) -> Self:
        """Open a camera (same keyword options as the constructor)."""
        return cls(**options)

    # -- lifecycle ------------------------------------------------------------------------------

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
        """Stop streaming (if running), release interface 0 and free the handle. Idempotent."""
        if self._dev is None:
            return
        try:
            self.stop()
        finally:
            usb = _usb()
            dev, self._dev = self._dev, None
            try:
                if self._claimed:
                    usb.util.release_interface(dev, 0)
            except usb.core.USBError as err:
                _log.debug("release_interface failed (device gone?): %s", err)
            usb.util.dispose_resources(dev)
            self._claimed = False

    @property
    def closed(self) -> bool:
        """True after :meth:`close`."""
        return self._dev is None

    def _open(self, *, serial: str | None, bus: int | None, address: int | None) -> Any:
        usb = _usb()
        try:
            devs = _candidates(self._backend)
        except usb.core.NoBackendError as err:
            msg = "no libusb backend available; install libusb-1.0 (apt install libusb-1.0-0)"
            raise DeviceError(msg) from err
        devs = [
            d
            for d in devs
            if (bus is None or d.bus == bus) and (address is None or d.address == address)
        ]
        if not devs:
            msg = (
                "no DAVIS camera found (USB 152a:841b or 152a:841a"
                + (f" at bus {bus} address {address}" if bus or address else "")
                + f"); on the bus: {_describe_bus(self._backend)}. Check the cable and power "
                "(`lsusb` should list 152a:841b)"
            )
            raise DeviceError(msg)
        seen: list[str] = []
        for dev in devs:
            where = f"bus {dev.bus} address {dev.address}"
            try:
                sn = _read_serial(dev)
            except (usb.core.USBError, ValueError) as err:
                if isinstance(err, ValueError) or _is_permission(err):
                    msg = f"DAVIS camera at {where}: permission denied; {_UDEV_HINT}"
                    raise DeviceError(msg) from err
                msg = f"DAVIS camera at {where}: cannot read serial: {err}"
                raise DeviceError(msg) from err
            seen.append(sn)
            if serial is None or sn == serial:
                if serial is None and len(devs) > 1:
                    _log.info("%d DAVIS cameras found; opening %s at %s", len(devs), sn, where)
                self._serial = sn
                self._claim(dev, where)
                return dev
            usb.util.dispose_resources(dev)
        msg = (
            f"no DAVIS camera with serial {serial!r}; found serial(s) {', '.join(seen)}. "
            "Run `mocaprig devices` to list them"
        )
        raise DeviceError(msg)

    def _claim(self, dev: Any, where: str) -> None:
        usb = _usb()
        name = f"DAVIS240C {self._serial} at {where}"
        try:
            try:
                cfg = dev.get_active_configuration()
                value = cfg.bConfigurationValue
            except usb.core.USBError:
                value = None
            if value != 1:
                dev.set_configuration(1)
            usb.util.claim_interface(dev, 0)
            self._claimed = True
        except usb.core.USBError as err:
            usb.util.dispose_resources(dev)
            if _is_permission(err):
                msg = f"{name}: permission denied; {_UDEV_HINT}"
            elif _is_busy(err):
                msg = (
                    f"{name} is busy: another process holds it (a running mocaprig, DV, jAER "
                    "or a ROS driver); close that program and try again"
                )
            else:
                msg = f"{name}: cannot claim interface 0: {err}"
            raise DeviceError(msg) from err
        fw = int(dev.bcdDevice) & 0xFF
        required = (
            REQUIRED_FIRMWARE_FX2 if dev.idProduct == PRODUCT_ID_FX2 else (REQUIRED_FIRMWARE_FX3)
        )
        if fw < required:
            usb.util.release_interface(dev, 0)
            usb.util.dispose_resources(dev)
            self._claimed = False
            msg = f"{name} has firmware {fw}, this driver needs >= {required}; {_FLASH_HINT}"
            raise DeviceError(msg)

    # -- register access ------------------------------------------------------------------------

    def _require_open(self) -> Any:
        if self._dev is None:
            msg = "the DAVIS240C is closed; open it again with Davis240C.open()"
            raise DeviceError(msg)
        return self._dev

    def config_get(self, module: int, param: int) -> int:
        """Read one 32-bit register (0xBF IN)."""
        dev = self._require_open()
        usb = _usb()
        try:
            with self._lock:
                return _ctrl_read(dev, module, param)
        except usb.core.USBError as err:
            what = f"reading register ({module}, {param})"
            raise self._usb_error(what, err) from err

    def config_get64(self, module: int, param: int) -> int:
        """Read a 64-bit statistics register pair (upper at ``param``, lower at ``param+1``)."""
        for _ in range(4):
            hi = self.config_get(module, param)
            lo = self.config_get(module, param + 1)
            if self.config_get(module, param) == hi:
                return (hi << 32) | lo
        msg = f"64-bit register ({module}, {param}) kept changing while being read"
        raise DeviceError(msg)

    def config_set(self, module: int, param: int, value: int) -> None:
        """Write one 32-bit register (0xBF OUT, value big-endian)."""
        wr = RegisterWrite(int(module), int(param), int(value))
        dev = self._require_open()
        usb = _usb()
        try:
            with self._lock:
                dev.ctrl_transfer(
                    0x40,
                    VR_FPGA_CONFIG,
                    wr.module,
                    wr.param,
                    wr.value.to_bytes(4, "big"),
                    _CTRL_TIMEOUT_MS,
                )
        except usb.core.USBError as err:
            what = f"writing register ({module}, {param})"
            raise self._usb_error(what, err) from err

    def config_set_many(self, writes: Sequence[RegisterWrite]) -> None:
        """Write several registers in order with 0xC2 (atomic batches of up to 85)."""
        dev = self._require_open()
        usb = _usb()
        for i in range(0, len(writes), _MAX_MULTIPLE):
            batch = writes[i : i + _MAX_MULTIPLE]
            payload = b"".join(
                bytes([w.module, w.param]) + w.value.to_bytes(4, "big") for w in batch
            )
            try:
                with self._lock:
                    dev.ctrl_transfer(
                        0x40, VR_FPGA_CONFIG_MULTIPLE, len(batch), 0, payload, _CTRL_TIMEOUT_MS
                    )
            except usb.core.USBError as err:
                what = f"writing {len(batch)} registers"
                raise self._usb_error(what, err) from err

    def _usb_error(self, what: str, err: BaseException) -> DeviceError:
        _, code = _error_code(err)
        en = getattr(err, "errno", None)
        if code == _LIBUSB_ERROR_NO_DEVICE or en == errno.ENODEV:
            return DeviceError(
                f"DAVIS240C {self._serial}: disconnected while {what}; replug it and reopen"
            )
        return DeviceError(f"DAVIS240C {self._serial}: USB error while {what}: {err}")

    # -- information ----------------------------------------------------------------------------

    def _read_info(self) -> DavisInfo:
        g = self.config_get
        S = Module.SYSINFO
        dev = self._dev
        logic = g(S, SysInfoParam.LOGIC_VERSION)
        patch = g(S, SysInfoParam.LOGIC_PATCH)
        name = f"DAVIS240C {self._serial}"
        if logic != REQUIRED_LOGIC_VERSION or patch < REQUIRED_LOGIC_PATCH:
            msg = (
                f"{name} has logic {logic}.{patch}, this driver needs {REQUIRED_LOGIC_VERSION}"
                f".{REQUIRED_LOGIC_PATCH} or a later patch; {_FLASH_HINT}"
            )
            raise DeviceError(msg)
        chip = g(S, SysInfoParam.CHIP_IDENTIFIER)
        if chip != _CHIP_ID_DAVIS240C:
            _log.warning("%s reports chip id %d, not a DAVIS240C (2)", name, chip)
        D, A = Module.DVS, Module.APS
        dvs_orient = g(D, DvsParam.ORIENTATION_INFO)
        aps_orient = g(A, ApsParam.ORIENTATION_INFO)
        dvs_x, dvs_y = g(D, DvsParam.SIZE_COLUMNS), g(D, DvsParam.SIZE_ROWS)
        aps_x, aps_y = g(A, ApsParam.SIZE_COLUMNS), g(A, ApsParam.SIZE_ROWS)
        if dvs_orient & 4:
            dvs_x, dvs_y = dvs_y, dvs_x
        if aps_orient & 4:
            aps_x, aps_y = aps_y, aps_x
        return DavisInfo(
            serial=self._serial,
            bus=int(dev.bus or 0),
            address=int(dev.address or 0),
            product_id=int(dev.idProduct),
            firmware_version=int(dev.bcdDevice) & 0xFF,
            logic_version=logic,
            logic_patch=patch,
            chip_id=chip,
            device_is_master=bool(g(S, SysInfoParam.DEVICE_IS_MASTER)),
            mux_has_statistics=bool(g(Module.MUX, MuxParam.HAS_STATISTICS)),
            dvs_size_x=dvs_x,
            dvs_size_y=dvs_y,
            dvs_orientation=dvs_orient,
            dvs_has_pixel_filter=bool(g(D, DvsParam.HAS_PIXEL_FILTER)),
            dvs_has_background_activity_filter=bool(g(D, DvsParam.HAS_BACKGROUND_ACTIVITY_FILTER)),
            dvs_has_roi_filter=bool(g(D, DvsParam.HAS_ROI_FILTER)),
            dvs_has_skip_filter=bool(g(D, DvsParam.HAS_SKIP_FILTER)),
            dvs_has_polarity_filter=bool(g(D, DvsParam.HAS_POLARITY_FILTER)),
            dvs_has_statistics=bool(g(D, DvsParam.HAS_STATISTICS)),
            aps_size_x=aps_x,
            aps_size_y=aps_y,
            aps_orientation=aps_orient,
            aps_color_filter=g(A, ApsParam.COLOR_FILTER),
            aps_has_global_shutter=bool(g(A, ApsParam.HAS_GLOBAL_SHUTTER)),
            imu_type=g(Module.IMU, ImuParam.TYPE),
            imu_orientation=g(Module.IMU, ImuParam.ORIENTATION_INFO),
            ext_input_has_generator=bool(g(Module.EXTINPUT, ExtInputParam.HAS_GENERATOR)),
            clocks=DeviceClocks(
                logic_mhz=g(S, SysInfoParam.LOGIC_CLOCK),
                adc_mhz=g(S, SysInfoParam.ADC_CLOCK),
                usb_mhz=g(S, SysInfoParam.USB_CLOCK),
                deviation_x1000=g(S, SysInfoParam.CLOCK_DEVIATION),
            ),
        )

    @property
    def info(self) -> DavisInfo:
        """Device information read at open."""
        return self._info

    @property
    def serial(self) -> str:
        """The serial-number string."""
        return self._serial

    @property
    def settings(self) -> DavisSettings:
        """The settings last written by :meth:`send_default_config`."""
        return self._settings

    def device_drop_counts(self) -> dict[str, int]:
        """Events the device itself dropped while USB was stalled (MUX statistics, 64-bit).

        Keys ``dvs`` and ``ext_input``; empty when the logic has no statistics
        (MUX HAS_STATISTICS = 0).
        """
        if not self._info.mux_has_statistics:
            return {}
        return {
            "dvs": self.config_get64(Module.MUX, MuxParam.STATISTICS_DVS_DROPPED),
            "ext_input": self.config_get64(Module.MUX, MuxParam.STATISTICS_EXTINPUT_DROPPED),
        }

    def is_master(self) -> bool:
        """Read DEVICE_IS_MASTER now (a camera becomes slave when it sees a sync clock)."""
        return bool(self.config_get(Module.SYSINFO, SysInfoParam.DEVICE_IS_MASTER))

    # -- configuration --------------------------------------------------------------------------

    def send_default_config(self, settings: DavisSettings | None = None) -> None:
        """Write biases, chip, MUX, DVS, APS, IMU, EXTINPUT and USB defaults (note §5.2)."""
        if settings is not None:
            self._settings = settings
        for wr in default_config_writes(self._settings, clocks=self._info.clocks):
            self.config_set(wr.module, wr.param, wr.value)

    def timestamp_reset(self) -> None:
        """Pulse MUX TIMESTAMP_RESET atomically (0xC2 [1, 0]); slaves follow the master."""
        self.config_set_many(
            [
                RegisterWrite(Module.MUX, MuxParam.TIMESTAMP_RESET, 1),
                RegisterWrite(Module.MUX, MuxParam.TIMESTAMP_RESET, 0),
            ]
        )

    # -- streaming ------------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        """True between :meth:`start` and :meth:`stop` while the reader is alive."""
        return self._stream is not None and self._stream.reader_alive()

    def start(self, *, timestamp_reset: bool = True) -> None:
        """Start the data stream: libcaer's ``dataStart`` sequence (note §5.3).

        With ``timestamp_reset`` (default), a master camera resets its timestamp once the
        producers run, and everything before the TS-reset word is discarded (stale FIFO data,
        libcaer#69). A slave waits for its master's reset the same way.
        """
        dev = self._require_open()
        if self._stream is not None:
            if self._stream.reader_alive():
                msg = f"DAVIS240C {self._serial} is already streaming; stop() it first"
                raise DeviceError(msg)
            self._stream.join()
        usb = _usb()
        drain, settle, mux = self._delays
        for module, param in _STOP_SEQUENCE:
            self.config_set(module, param, 0)
        time.sleep(drain)
        try:
            with self._lock:
                dev.clear_halt(DATA_ENDPOINT)
        except usb.core.USBError as err:
            what = "clearing the halt on EP 0x82"
            raise self._usb_error(what, err) from err
        flip = self._info.imu_orientation
        decoder = DavisDecoder(imu_flip=(bool(flip & 4), bool(flip & 2), bool(flip & 1)))
        self._stream = _Stream(
            dev,
            decoder,
            read_size=self._read_size,
            read_timeout_ms=self._read_timeout_ms,
            queue_packets=self._queue_packets,
            queue_bytes=self._queue_bytes,
            raw_queue_bytes=self._raw_queue_bytes,
            discard_until_reset=timestamp_reset,
            name=self._serial,
            raw_sink=self._raw_sink,
        )
        self._stream.start()
        try:
            self.config_set(Module.MUX, MuxParam.RUN_CHIP, 1)
            time.sleep(settle)
            self.config_set(Module.USB, UsbParam.RUN, 1)
            self.config_set(Module.MUX, MuxParam.TIMESTAMP_RUN, 1)
            self.config_set(Module.MUX, MuxParam.RUN, 1)
            time.sleep(mux)
            for module, param in _PRODUCERS:
                self.config_set(module, param, 1)
            if timestamp_reset:
                if self.is_master():
                    self.timestamp_reset()
                else:
                    _log.info("%s is a slave: waiting for the master's TS reset", self._serial)
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        """Stop the producers and the reader (libcaer ``dataStop``); queued packets stay.

        Safe to call after a disconnect (the register writes are then skipped).
        """
        stream = self._stream
        if stream is None:
            return
        if stream.reader_alive() and self._dev is not None and stream.error is None:
            try:
                for module, param in _STOP_SEQUENCE:
                    self.config_set(module, param, 0)
            except DeviceError as err:
                _log.warning("stopping %s: %s", self._serial, err)
        stream.request_stop()
        stream.join()

    def get_packet(self, timeout_s: float | None = None) -> DavisPacket | None:
        """The next packet, or None if none came within ``timeout_s`` or the stream ended.

        Raises:
            DeviceError: the stream ended with a USB error (after every packet was taken).
        """
        stream = self._require_stream()
        return stream.get(timeout_s)

    def packets(self, *, timeout_s: float | None = None) -> Iterator[DavisPacket]:
        """Iterate over packets until the stream stops.

        Every decoded USB read is one packet (even an empty one: a running camera sends a
        wrap word every 32.768 ms), so ``timeout_s`` without any packet means a stall.

        Raises:
            DeviceError: the camera was disconnected or failed (after delivering everything
                received before), or no data arrived for ``timeout_s``.
        """
        stream = self._require_stream()
        while True:
            pkt = stream.get(timeout_s)
            if pkt is not None:
                yield pkt
                continue
            if stream.finished():
                return
            msg = (
                f"DAVIS240C {self._serial} sent nothing for {timeout_s} s although a running "
                "camera sends a wrap word every 32.768 ms: the device or its USB link stalled; "
                "stop(), replug the camera and start again"
            )
            raise DeviceError(msg)

    def stats(self) -> StreamStats:
        """Streaming counters (all zero before the first :meth:`start`)."""
        return StreamStats() if self._stream is None else self._stream.stats()

    def _require_stream(self) -> _Stream:
        if self._stream is None:
            msg = f"DAVIS240C {self._serial} is not streaming; call start() first"
            raise DeviceError(msg)
        return self._stream


class _Stream:
    """Reader + decoder threads and the two hand-off queues of one streaming session."""

    def __init__(
        self,
        dev: Any,
        decoder: DavisDecoder,
        *,
        read_size: int,
        read_timeout_ms: int,
        queue_packets: int,
        queue_bytes: int,
        raw_queue_bytes: int,
        discard_until_reset: bool,
        name: str,
        raw_sink: BinaryIO | None,
    ) -> None:
        self._dev = dev
        self._raw_sink = raw_sink
        self._decoder = decoder
        self._read_size = read_size
        self._read_timeout_ms = read_timeout_ms
        self._queue_packets = queue_packets
        self._queue_bytes = queue_bytes
        self._out_bytes = 0
        self._raw_limit = raw_queue_bytes
        self._discard = discard_until_reset
        self._discard_carry = b""
        self._name = name
        self._stop = threading.Event()
        self._raw: collections.deque[tuple[int, bytes]] = collections.deque()
        self._raw_bytes = 0
        self._raw_cond = threading.Condition()
        self._reader_done = False
        self._out: collections.deque[DavisPacket] = collections.deque()
        self._out_cond = threading.Condition()
        self._decoder_done = False
        self._carry_specials: list[Any] = []
        self.error: BaseException | None = None
        self._c = dict.fromkeys(
            (
                "reads",
                "bytes_read",
                "read_timeouts",
                "raw_bytes_dropped",
                "bytes_discarded_before_reset",
                "packets_delivered",
                "packets_dropped",
                "events_dropped",
                "frames_dropped",
                "imu_dropped",
                "specials_dropped",
            ),
            0,
        )
        self._reader = threading.Thread(target=self._read_loop, name=f"davis-{name}-reader")
        self._decoder_thread = threading.Thread(
            target=self._decode_loop, name=f"davis-{name}-decoder"
        )
        self._reader.daemon = True
        self._decoder_thread.daemon = True

    def start(self) -> None:
        self._reader.start()
        self._decoder_thread.start()

    def reader_alive(self) -> bool:
        return self._reader.is_alive()

    def request_stop(self) -> None:
        self._stop.set()

    def join(self) -> None:
        self._stop.set()
        self._reader.join()
        self._decoder_thread.join()

    def finished(self) -> bool:
        with self._out_cond:
            return self._decoder_done and not self._out

    # -- reader thread --------------------------------------------------------------------------

    def _read_loop(self) -> None:
        usb = _usb()
        try:
            while not self._stop.is_set():
                t_call = time.monotonic()
                try:
                    data = self._dev.read(DATA_ENDPOINT, self._read_size, self._read_timeout_ms)
                except usb.core.USBError as err:
                    if _is_timeout(err):
                        self._c["read_timeouts"] += 1
                        # A backend that reports a timeout at once (a mock, a device with the
                        # mux off) must not make this thread spin.
                        if time.monotonic() - t_call < self._read_timeout_ms / 2000:
                            time.sleep(0.002)
                        continue
                    self.error = err
                    _log.error("DAVIS240C %s: bulk read failed, stopping: %s", self._name, err)
                    break
                t_ns = time.time_ns()
                chunk = bytes(data)
                self._c["reads"] += 1
                self._c["bytes_read"] += len(chunk)
                if not chunk:
                    continue
                with self._raw_cond:
                    if self._raw_bytes + len(chunk) > self._raw_limit:
                        self._c["raw_bytes_dropped"] += len(chunk)
                        self._raw.append((t_ns, b""))  # a gap marker for the decoder
                    else:
                        self._raw.append((t_ns, chunk))
                        self._raw_bytes += len(chunk)
                    self._raw_cond.notify()
        except Exception as err:  # pragma: no cover - a bug or a backend misbehaving
            self.error = err
            _log.exception("DAVIS240C %s: reader thread crashed", self._name)
        finally:
            with self._raw_cond:
                self._reader_done = True
                self._raw_cond.notify()

    # -- decoder thread -------------------------------------------------------------------------

    def _decode_loop(self) -> None:
        try:
            while True:
                with self._raw_cond:
                    while not self._raw and not self._reader_done:
                        self._raw_cond.wait()
                    if not self._raw:
                        break
                    t_ns, chunk = self._raw.popleft()
                    self._raw_bytes -= len(chunk)
                if not chunk:
                    self._decoder.decode_gap()
                    continue
                if self._discard:
                    chunk = self._skip_until_reset(chunk)
                    if not chunk:  # still before the reset: show the consumer we are alive
                        self._deliver(DavisPacket(events=empty_events(), host_time_ns=t_ns))
                        continue
                if self._raw_sink is not None:
                    self._raw_sink.write(chunk)
                pkt = self._decoder.decode(chunk)
                self._deliver(
                    DavisPacket(
                        events=pkt.events,
                        frames=pkt.frames,
                        imu=pkt.imu,
                        specials=pkt.specials,
                        host_time_ns=t_ns,
                    )
                )
        except Exception as err:  # pragma: no cover - a decoder bug must not hang consumers
            self.error = self.error or err
            _log.exception("DAVIS240C %s: decoder thread crashed", self._name)
        finally:
            with self._out_cond:
                self._decoder_done = True
                self._out_cond.notify_all()

    def _skip_until_reset(self, chunk: bytes) -> bytes:
        data = self._discard_carry + chunk
        even = len(data) - len(data) % 2
        words = np.frombuffer(data[:even], dtype="<u2")
        hit = np.flatnonzero(words == 0x0001)
        if hit.size == 0:
            self._discard_carry = data[even:]
            self._c["bytes_discarded_before_reset"] += even
            return b""
        self._discard = False
        start = 2 * int(hit[0])
        self._c["bytes_discarded_before_reset"] += start
        return data[start:]

    def _deliver(self, pkt: DavisPacket) -> None:
        with self._out_cond:
            if self._carry_specials:
                merged = np.concatenate([*self._carry_specials, pkt.specials])
                pkt = DavisPacket(
                    events=pkt.events,
                    frames=pkt.frames,
                    imu=pkt.imu,
                    specials=merged,
                    host_time_ns=pkt.host_time_ns,
                )
                self._carry_specials = []
            size = _payload_bytes(pkt)
            full = len(self._out) >= self._queue_packets
            if full or (self._out and self._out_bytes + size > self._queue_bytes):
                c = self._c
                c["packets_dropped"] += 1
                c["events_dropped"] += int(pkt.events.size)
                c["frames_dropped"] += len(pkt.frames)
                c["imu_dropped"] += int(pkt.imu.size)
                if pkt.specials.size:
                    carried = sum(int(s.size) for s in self._carry_specials)
                    if carried + pkt.specials.size <= _MAX_CARRIED_SPECIALS:
                        self._carry_specials.append(pkt.specials)
                    else:
                        c["specials_dropped"] += int(pkt.specials.size)
                return
            self._out.append(pkt)
            self._out_bytes += size
            self._c["packets_delivered"] += 1
            self._out_cond.notify()

    # -- consumer side --------------------------------------------------------------------------

    def get(self, timeout_s: float | None) -> DavisPacket | None:
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._out_cond:
            while not self._out and not self._decoder_done:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._out_cond.wait(remaining)
            if self._out:
                pkt = self._out.popleft()
                self._out_bytes -= _payload_bytes(pkt)
                return pkt
        if self.error is not None:
            err = self.error
            en, code = _error_code(err)
            if en == errno.ENODEV or code == _LIBUSB_ERROR_NO_DEVICE:
                what = "was disconnected while streaming"
            else:
                what = "stopped streaming after a USB error"
            msg = (
                f"DAVIS240C {self._name} {what} ({err}); everything received before was "
                "delivered. Replug the camera and open it again"
            )
            raise DeviceError(msg) from err
        return None

    def stats(self) -> StreamStats:
        c = self._c
        return StreamStats(
            running=self._reader.is_alive(),
            decode=self._decoder.stats,
            error=None if self.error is None else str(self.error),
            **c,
        )


def _payload_bytes(pkt: DavisPacket) -> int:
    """Memory a queued packet holds (events, frame pixels, IMU samples, specials)."""
    return (
        pkt.events.nbytes
        + pkt.imu.nbytes
        + pkt.specials.nbytes
        + sum(f.pixels.nbytes for f in pkt.frames)
    )
