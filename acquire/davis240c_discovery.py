"""Finding DAVIS cameras on the USB bus without claiming them: descriptors, serials, udev hints.

:func:`find_davis` lists every DAVIS (VID 0x152A, PID 0x841B/0x841A) with what can be read
without claiming interface 0 (serial, firmware, logic version), so a camera held by another
process is still listed. :func:`load_mock_backend` gives the pyusb backend of the registered mock
camera (the ``mocaprig.mocks`` entry point ``davis240c``); ``acquire`` never imports
``drivers_mock`` itself. :data:`UDEV_RULE` is the rule that lets a user open the camera without
root; :data:`UDEV_HINT` says how to install it.

Opening a camera is :class:`mocaprig.acquire.davis240c.Davis240C`'s job; the helpers it shares
with this module (:func:`candidate_devices`, :func:`read_serial`, :func:`describe_bus`) are here.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib.resources import files
from typing import Any

from mocaprig.acquire.davis240c_config import Module, SysInfoParam
from mocaprig.acquire.davis240c_libusb import (
    PRODUCT_ID_FX2,
    PRODUCT_ID_FX3,
    VENDOR_ID,
    ctrl_read,
    is_permission,
    usb_module,
)
from mocaprig.acquire.mocks import load_mock_factory
from mocaprig.errors import DeviceError

__all__ = [
    "UDEV_HINT",
    "UDEV_RULE",
    "DavisUsbDevice",
    "candidate_devices",
    "describe_bus",
    "find_davis",
    "load_mock_backend",
    "read_serial",
]

#: The udev rule shipped with the package (install it to use the camera without root).
UDEV_RULE = files("mocaprig.acquire") / "data" / "99-mocaprig-davis.rules"

#: What to do about "permission denied" (how to install :data:`UDEV_RULE`).
UDEV_HINT = (
    f"install the udev rule: sudo cp {UDEV_RULE} /etc/udev/rules.d/ && "
    "sudo udevadm control --reload-rules && sudo udevadm trigger, then unplug and replug "
    "the camera"
)


def load_mock_backend(**kwargs: Any) -> Any:
    """The DAVIS240C mock ``usb.backend.IBackend`` from the ``mocaprig.mocks`` entry point.

    ``kwargs`` go to the factory. acquire/ never imports drivers_mock/ itself.

    Raises:
        DeviceError: no mock is registered (the package is not installed with its mocks).
    """
    return load_mock_factory("davis240c")(**kwargs)


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


def read_serial(dev: Any) -> str:
    """The serial-number string descriptor of ``dev`` (pyusb errors and ValueError propagate).

    Like libcaer 3.3.10+, a device without a serial descriptor gets a session-local name
    ``TMP<bus << 8 | address>``.
    """
    usb = usb_module()
    if not dev.iSerialNumber:
        return f"TMP{(int(dev.bus or 0) << 8) | int(dev.address or 0):05d}"
    serial = usb.util.get_string(dev, dev.iSerialNumber)
    return str(serial)


def candidate_devices(backend: Any) -> list[Any]:
    """The pyusb devices with a DAVIS VID/PID, FX2 first, then by bus and address."""
    usb = usb_module()
    found = usb.core.find(find_all=True, backend=backend, idVendor=VENDOR_ID)
    devs = [d for d in found if d.idProduct in (PRODUCT_ID_FX2, PRODUCT_ID_FX3)]
    return sorted(devs, key=lambda d: (d.idProduct != PRODUCT_ID_FX2, d.bus or 0, d.address or 0))


def find_davis(*, backend: Any = None) -> list[DavisUsbDevice]:
    """Every DAVIS camera (VID 0x152A, PID 0x841B/0x841A) on the bus, FX2 first.

    The interface is not claimed, so a camera in use by another process is still listed.
    Unreadable fields are None and ``error`` says why (usually permissions: the udev rule).
    """
    usb = usb_module()
    out = []
    for dev in candidate_devices(backend):
        serial = logic = patch = None
        error = None
        try:
            serial = read_serial(dev)
            logic = ctrl_read(dev, Module.SYSINFO, SysInfoParam.LOGIC_VERSION)
            patch = ctrl_read(dev, Module.SYSINFO, SysInfoParam.LOGIC_PATCH)
        except (usb.core.USBError, ValueError, DeviceError) as err:
            # pyusb raises ValueError ("The device has no langid") when it may not read the
            # string descriptors: a permission problem, as Davis240C.open says too.
            denied = isinstance(err, ValueError) or is_permission(err)
            error = "permission denied; " + UDEV_HINT if denied else str(err)
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


def describe_bus(backend: Any) -> str:
    """Every device on the bus as ``vid:pid (bus B, address A)``, for "not found" messages."""
    usb = usb_module()
    try:
        devs = list(usb.core.find(find_all=True, backend=backend))
    except usb.core.USBError as err:  # pragma: no cover - enumeration itself failed
        return f"(cannot enumerate USB devices: {err})"
    if not devs:
        return "no USB devices at all"
    return ", ".join(
        f"{d.idVendor:04x}:{d.idProduct:04x} (bus {d.bus}, address {d.address})" for d in devs
    )
