"""The DAVIS240C event camera over libusb (pyusb): open, configure, start, stop, packets.

:class:`Davis240C` is one opened camera. The protocol is in ``docs/davis240c-usb.md`` (shared
docs): vendor request 0xBF reads/writes one 32-bit register (big-endian), 0xC2 writes several at
once; data arrive on bulk EP 0x82 as 16-bit words decoded by
:mod:`mocaprig.acquire.davis240c_decode`.

Usage::

    with Davis240C.open() as cam:   # the mock: Davis240C.open(backend=load_mock_backend())
        cam.start()
        for packet in cam.packets(timeout_s=1.0):
            handle(packet.events, packet.frames, packet.imu, packet.specials)

The driver is split along its seams; this module re-exports the public names of the others, so
``from mocaprig.acquire.davis240c import X`` works for all of them:

- :mod:`mocaprig.acquire.davis240c_libusb`: USB ids, endpoint, vendor requests, and which
  :class:`~mocaprig.errors.DeviceError` subclass a libusb error becomes;
- :mod:`mocaprig.acquire.davis240c_discovery`: :func:`find_davis`, :class:`DavisUsbDevice`,
  :func:`load_mock_backend`, the udev rule (:data:`UDEV_RULE`);
- :mod:`mocaprig.acquire.davis240c_reader`: the reader and decoder threads, their bounded queues
  and drop counting (:class:`StreamStats`).

Failures are :class:`~mocaprig.errors.DeviceError` subclasses that keep the libusb code
(``backend_code``) and errno (``backend_errno``): :class:`~mocaprig.errors.DeviceNotFoundError`
(no camera, wrong serial), :class:`~mocaprig.errors.DevicePermissionError` (the udev rule),
:class:`~mocaprig.errors.DeviceBusyError` (another process holds it),
:class:`~mocaprig.errors.DeviceTimeoutError` (a control transfer or the stream stalled) and
:class:`~mocaprig.errors.DeviceDisconnectedError` (unplugged; while streaming it is raised by
:meth:`Davis240C.packets` after everything received before was delivered).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any, BinaryIO, Final, Self

from mocaprig.acquire.davis240c_config import (
    ApsParam,
    BiasPreset,
    ChipParam,
    DavisSettings,
    DeviceClocks,
    DvsFilters,
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
from mocaprig.acquire.davis240c_decode import DavisDecoder, DavisPacket, SensorOrientation
from mocaprig.acquire.davis240c_discovery import (
    UDEV_HINT,
    UDEV_RULE,
    DavisUsbDevice,
    candidate_devices,
    describe_bus,
    find_davis,
    load_mock_backend,
    read_serial,
)
from mocaprig.acquire.davis240c_libusb import (
    CTRL_TIMEOUT_MS,
    DATA_ENDPOINT,
    PRODUCT_ID_FX2,
    PRODUCT_ID_FX3,
    VENDOR_ID,
    VR_FPGA_CONFIG,
    VR_FPGA_CONFIG_MULTIPLE,
    ctrl_read,
    device_error,
    is_busy,
    is_no_device,
    is_permission,
    usb_module,
)
from mocaprig.acquire.davis240c_reader import DavisStream, StreamStats
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

REQUIRED_FIRMWARE_FX2: Final = 4
REQUIRED_FIRMWARE_FX3: Final = 6
REQUIRED_LOGIC_VERSION: Final = 18
REQUIRED_LOGIC_PATCH: Final = 1
_MAX_MULTIPLE: Final = 85  # entries per 0xC2 request (510 bytes; note §2)
_CHIP_ID_DAVIS240C: Final = 2
#: SYSINFO CHIP_IDENTIFIER values (note §3.6), for the messages.
_CHIP_NAMES: Final = {
    0: "DAVIS240A",
    1: "DAVIS240B",
    2: "DAVIS240C",
    3: "DAVIS128",
    4: "DAVIS346A",
    5: "DAVIS346B",
    6: "DAVIS640",
    7: "DAVIS640H",
    8: "DAVIS208",
    9: "DAVIS346C",
}
_DVS_SIZE: Final = (240, 180)
#: libcaer keeps these two equal (``davisConfigSet`` APS GLOBAL_SHUTTER, note §3.3).
_GLOBAL_SHUTTER_PAIR: Final = (
    (int(Module.APS), int(ApsParam.GLOBAL_SHUTTER)),
    (int(Module.BIAS), int(ChipParam.GLOBAL_SHUTTER)),
)

_FLASH_HINT = (
    "reflash it with iniVation's Flashy tool (part of DV) to FX2 firmware "
    f"{REQUIRED_FIRMWARE_FX2} / logic {REQUIRED_LOGIC_VERSION} (patch >= {REQUIRED_LOGIC_PATCH})"
)


# -- device information ------------------------------------------------------------------------


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
    def orientation(self) -> SensorOrientation:
        """The ORIENTATION_INFO registers as the decoder applies them."""
        return SensorOrientation.from_registers(
            self.dvs_orientation, self.aps_orientation, self.imu_orientation
        )

    @property
    def dvs_filters(self) -> DvsFilters:
        """The DVS filters the logic has (HAS_* registers)."""
        return DvsFilters(
            pixel=self.dvs_has_pixel_filter,
            background_activity=self.dvs_has_background_activity_filter,
            roi=self.dvs_has_roi_filter,
            skip=self.dvs_has_skip_filter,
            polarity=self.dvs_has_polarity_filter,
        )

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
        read_size: Bytes per synchronous bulk read (a multiple of 512); used when the backend
            has no libusb asynchronous API (the mock).
        read_timeout_ms: Synchronous bulk read timeout; bounds how fast :meth:`stop` reacts.
        transfers: Bulk transfers kept queued on a real device (libcaer: 8).
        transfer_bytes: Size of each queued transfer (a multiple of 512; libcaer: 8192).
        queue_packets: Capacity of the consumer queue (decoded packets).
        queue_bytes: Capacity of the consumer queue in payload bytes (events, frame pixels,
            IMU samples); whichever limit is reached first drops the next packet.
        raw_queue_bytes: Capacity of the reader -> decoder hand-off (bytes).
        settle_delays_s: (FIFO drain, bias settle, mux start) sleeps of the start sequence.
        raw_sink: A binary file that receives the raw bulk bytes the decoder sees (from the
            timestamp reset on), written by the decoder thread; for ``mocaprig davis decode``.

    Raises:
        DeviceNotFoundError: no camera (lists what is on the bus), or none with ``serial``.
        DevicePermissionError: the user may not open it (how to install the udev rule).
        DeviceBusyError: another process holds it.
        DeviceError: wrong firmware/logic (how to reflash), another chip than a DAVIS240C
            (a DAVIS346 on an FX3 board...: its bias table, sizes and shutter differ), or
            another USB failure (then the subclass its libusb code stands for, e.g.
            :class:`DeviceDisconnectedError`).
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
        transfers: int = 8,
        transfer_bytes: int = 8192,
    ) -> None:
        if transfers < 1 or transfer_bytes <= 0 or transfer_bytes % 512:
            msg = (
                f"transfers {transfers} must be >= 1 and transfer_bytes {transfer_bytes} a "
                "positive multiple of 512 bytes (libcaer: 8 x 8192)"
            )
            raise ValidationError(msg)
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
        self._transfers = transfers
        self._transfer_bytes = transfer_bytes
        self._dev: Any = None
        self._claimed = False
        self._lock = threading.Lock()  # serialises control transfers
        self._stream: DavisStream | None = None
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
            usb = usb_module()
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
        usb = usb_module()
        try:
            devs = candidate_devices(self._backend)
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
                + f"); on the bus: {describe_bus(self._backend)}. Check the cable and power "
                "(`lsusb` should list 152a:841b)"
            )
            raise DeviceNotFoundError(msg)
        seen: list[str] = []
        for dev in devs:
            where = f"bus {dev.bus} address {dev.address}"
            try:
                sn = read_serial(dev)
            except (usb.core.USBError, ValueError) as err:
                # pyusb raises ValueError ("The device has no langid") when it may not read
                # the string descriptors: a permission problem too.
                if isinstance(err, ValueError) or is_permission(err):
                    msg = f"DAVIS camera at {where}: permission denied; {UDEV_HINT}"
                    raise DevicePermissionError.from_cause(msg, err) from err
                msg = f"DAVIS camera at {where}: cannot read serial: {err}"
                raise device_error(msg, err) from err
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
        raise DeviceNotFoundError(msg)

    def _claim(self, dev: Any, where: str) -> None:
        usb = usb_module()
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
            cls: type[DeviceError] | None = None  # by the libusb code
            if is_permission(err):
                cls, msg = DevicePermissionError, f"{name}: permission denied; {UDEV_HINT}"
            elif is_busy(err):
                cls = DeviceBusyError
                msg = (
                    f"{name} is busy: another process holds it (a running mocaprig, DV, jAER "
                    "or a ROS driver); close that program and try again"
                )
            else:
                msg = f"{name}: cannot claim interface 0: {err}"
            raise device_error(msg, err, cls) from err
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
        usb = usb_module()
        try:
            with self._lock:
                return ctrl_read(dev, module, param)
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
        """Set one 32-bit register the way libcaer's ``davisConfigSet`` does.

        Two registers are not plain writes: MUX TIMESTAMP_RESET = 1 is the pulse of
        :meth:`timestamp_reset` (0 sends nothing: the register always reads 0), and APS
        GLOBAL_SHUTTER / CHIP GLOBAL_SHUTTER are kept equal (CHIP 142, then APS 7). Every
        other register is one 0xBF OUT write (value big-endian).

        Raises:
            DeviceError: GLOBAL_SHUTTER on a chip without one, or a USB failure.
        """
        m, p, v = int(module), int(param), int(value)
        if (m, p) == (Module.MUX, MuxParam.TIMESTAMP_RESET):
            RegisterWrite(m, p, v)  # validates the value
            if v:
                self.timestamp_reset()
            return
        if (m, p) in _GLOBAL_SHUTTER_PAIR:
            if not self._info.aps_has_global_shutter:
                msg = (
                    f"DAVIS240C {self._serial} has no global shutter (APS HAS_GLOBAL_SHUTTER "
                    "= 0); leave APS.GLOBAL_SHUTTER / CHIP.GLOBAL_SHUTTER unset"
                )
                raise DeviceError(msg)
            self._write(Module.BIAS, ChipParam.GLOBAL_SHUTTER, v)
            self._write(Module.APS, ApsParam.GLOBAL_SHUTTER, v)
            return
        self._write(m, p, v)

    def _write(self, module: int, param: int, value: int) -> None:
        """One 0xBF OUT register write."""
        wr = RegisterWrite(int(module), int(param), int(value))
        dev = self._require_open()
        usb = usb_module()
        try:
            with self._lock:
                dev.ctrl_transfer(
                    0x40,
                    VR_FPGA_CONFIG,
                    wr.module,
                    wr.param,
                    wr.value.to_bytes(4, "big"),
                    CTRL_TIMEOUT_MS,
                )
        except usb.core.USBError as err:
            what = f"writing register ({module}, {param})"
            raise self._usb_error(what, err) from err

    def config_set_many(self, writes: Sequence[RegisterWrite]) -> None:
        """Write several registers in order with 0xC2 (atomic batches of up to 85)."""
        dev = self._require_open()
        usb = usb_module()
        for i in range(0, len(writes), _MAX_MULTIPLE):
            batch = writes[i : i + _MAX_MULTIPLE]
            payload = b"".join(
                bytes([w.module, w.param]) + w.value.to_bytes(4, "big") for w in batch
            )
            try:
                with self._lock:
                    dev.ctrl_transfer(
                        0x40, VR_FPGA_CONFIG_MULTIPLE, len(batch), 0, payload, CTRL_TIMEOUT_MS
                    )
            except usb.core.USBError as err:
                what = f"writing {len(batch)} registers"
                raise self._usb_error(what, err) from err

    def _usb_error(self, what: str, err: BaseException) -> DeviceError:
        """The :class:`DeviceError` subclass for a failed transfer, keeping the libusb codes."""
        if is_no_device(err):
            msg = f"DAVIS240C {self._serial}: disconnected while {what}; replug it and reopen"
            return device_error(msg, err, DeviceDisconnectedError)
        msg = f"DAVIS240C {self._serial}: USB error while {what}: {err}"
        return device_error(msg, err)

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
        D, A = Module.DVS, Module.APS
        if chip != _CHIP_ID_DAVIS240C:
            chip_name = _CHIP_NAMES.get(chip, "an unknown chip")
            msg = (
                f"DAVIS camera {self._serial} (USB PID {int(dev.idProduct):#06x}) reports chip "
                f"id {chip} ({chip_name}); this driver supports only the DAVIS240C (chip id 2, "
                "240x180, DAVIS240 biases, global shutter) on an FX2 (PID 0x841b) or FX3 "
                "(0x841a) board. Other chips need their own bias table, sizes and shutter "
                "settings: use iniVation's DV / libcaer for this camera"
            )
            raise DeviceError(msg)
        dvs_orient = g(D, DvsParam.ORIENTATION_INFO)
        aps_orient = g(A, ApsParam.ORIENTATION_INFO)
        dvs_x, dvs_y = g(D, DvsParam.SIZE_COLUMNS), g(D, DvsParam.SIZE_ROWS)
        aps_x, aps_y = g(A, ApsParam.SIZE_COLUMNS), g(A, ApsParam.SIZE_ROWS)
        if dvs_orient & 4:
            dvs_x, dvs_y = dvs_y, dvs_x
        if aps_orient & 4:
            aps_x, aps_y = aps_y, aps_x
        if (dvs_x, dvs_y) != _DVS_SIZE or (aps_x, aps_y) != _DVS_SIZE:
            msg = (
                f"{name} reports DVS {dvs_x}x{dvs_y} and APS {aps_x}x{aps_y} pixels, not the "
                "DAVIS240C's 240x180; this driver decodes only 240x180. Check the camera "
                "with `mocaprig davis info` and use iniVation's DV / libcaer for other chips"
            )
            raise DeviceError(msg)
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
        """Write biases, chip, MUX, DVS, APS, IMU, EXTINPUT and USB defaults (note §5.2).

        The DVS filters the logic has (HAS_* registers) are reset to libcaer's defaults, so a
        filter set-up left by another program does not persist.
        """
        if settings is not None:
            self._settings = settings
        writes = default_config_writes(
            self._settings, clocks=self._info.clocks, dvs_filters=self._info.dvs_filters
        )
        for wr in writes:
            self._write(wr.module, wr.param, wr.value)

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
        usb = usb_module()
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
        decoder = DavisDecoder(orientation=self._info.orientation)
        self._stream = DavisStream(
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
            transfers=self._transfers,
            transfer_bytes=self._transfer_bytes,
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
            DeviceDisconnectedError: the camera was unplugged (after every packet was taken).
            DeviceError: the stream ended on another USB error (after every packet was taken).
        """
        stream = self._require_stream()
        return stream.get(timeout_s)

    def packets(self, *, timeout_s: float | None = None) -> Iterator[DavisPacket]:
        """Iterate over packets until the stream stops.

        Every decoded USB read is one packet (even an empty one: a running camera sends a
        wrap word every 32.768 ms), so ``timeout_s`` without any packet means a stall.

        Raises:
            DeviceDisconnectedError: the camera was unplugged (after delivering everything
                received before).
            DeviceTimeoutError: no data arrived for ``timeout_s``.
            DeviceError: the stream ended on another USB error.
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
            raise DeviceTimeoutError(msg)

    def stats(self) -> StreamStats:
        """Streaming counters (all zero before the first :meth:`start`)."""
        return StreamStats() if self._stream is None else self._stream.stats()

    def _require_stream(self) -> DavisStream:
        if self._stream is None:
            msg = f"DAVIS240C {self._serial} is not streaming; call start() first"
            raise DeviceError(msg)
        return self._stream
