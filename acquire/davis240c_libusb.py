"""The DAVIS240C's USB link as pyusb sees it: ids, endpoint, vendor requests and libusb errors.

Shared by discovery (:mod:`mocaprig.acquire.davis240c_discovery`), the device
(:mod:`mocaprig.acquire.davis240c`) and the reader threads
(:mod:`mocaprig.acquire.davis240c_reader`). The protocol is in ``docs/davis240c-usb.md``: vendor
request 0xBF reads/writes one 32-bit register (big-endian), 0xC2 writes several at once; data
arrive on bulk EP 0x82.

A libusb failure reaches Python as ``usb.core.USBError`` with ``backend_error_code`` (the libusb
code) and ``errno``; :func:`device_error_class` says which
:class:`~mocaprig.errors.DeviceError` subclass it becomes, and :func:`device_error` builds it
keeping both codes. pyusb is imported lazily (:func:`usb_module`) to keep ``mocaprig --help`` fast.
"""

from __future__ import annotations

import errno
from typing import Any, Final

from mocaprig.errors import (
    DeviceBusyError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceNotFoundError,
    DevicePermissionError,
    DeviceTimeoutError,
)

__all__ = [
    "CTRL_TIMEOUT_MS",
    "DATA_ENDPOINT",
    "LIBUSB_ERROR_ACCESS",
    "LIBUSB_ERROR_BUSY",
    "LIBUSB_ERROR_NOT_FOUND",
    "LIBUSB_ERROR_NO_DEVICE",
    "LIBUSB_ERROR_TIMEOUT",
    "PRODUCT_ID_FX2",
    "PRODUCT_ID_FX3",
    "VENDOR_ID",
    "VR_FPGA_CONFIG",
    "VR_FPGA_CONFIG_MULTIPLE",
    "ctrl_read",
    "device_error",
    "device_error_class",
    "is_busy",
    "is_no_device",
    "is_permission",
    "is_timeout",
    "usb_module",
]

VENDOR_ID: Final = 0x152A
PRODUCT_ID_FX2: Final = 0x841B  # DAVIS240A/B/C cameras
PRODUCT_ID_FX3: Final = 0x841A  # FX3 boards (DAVIS240C chip on an FX3 dev kit: same words)
DATA_ENDPOINT: Final = 0x82
VR_FPGA_CONFIG: Final = 0xBF
VR_FPGA_CONFIG_MULTIPLE: Final = 0xC2
CTRL_TIMEOUT_MS: Final = 1000

# libusb error codes (pyusb ``USBError.backend_error_code``).
LIBUSB_ERROR_ACCESS: Final = -3
LIBUSB_ERROR_NO_DEVICE: Final = -4
LIBUSB_ERROR_NOT_FOUND: Final = -5
LIBUSB_ERROR_BUSY: Final = -6
LIBUSB_ERROR_TIMEOUT: Final = -7


def usb_module() -> Any:
    """The ``usb`` package with ``usb.core`` and ``usb.util`` loaded (imported on first use)."""
    import usb.core  # lazy: keep `mocaprig --help` fast
    import usb.util

    return usb


def _codes(err: BaseException) -> tuple[int | None, int | None]:
    """(errno, libusb code) of a pyusb error; None where the error has none."""
    return getattr(err, "errno", None), getattr(err, "backend_error_code", None)


def is_permission(err: BaseException) -> bool:
    """LIBUSB_ERROR_ACCESS / EACCES: the udev rule is missing."""
    en, code = _codes(err)
    return en == errno.EACCES or code == LIBUSB_ERROR_ACCESS


def is_busy(err: BaseException) -> bool:
    """LIBUSB_ERROR_BUSY / EBUSY: another process claimed the interface."""
    en, code = _codes(err)
    return en == errno.EBUSY or code == LIBUSB_ERROR_BUSY


def is_timeout(err: BaseException) -> bool:
    """``usb.core.USBTimeoutError``, LIBUSB_ERROR_TIMEOUT or ETIMEDOUT."""
    usb = usb_module()
    en, code = _codes(err)
    return (
        isinstance(err, usb.core.USBTimeoutError)
        or en == errno.ETIMEDOUT
        or code == LIBUSB_ERROR_TIMEOUT
    )


def is_no_device(err: BaseException) -> bool:
    """LIBUSB_ERROR_NO_DEVICE / ENODEV: the device is gone (unplugged)."""
    en, code = _codes(err)
    return en == errno.ENODEV or code == LIBUSB_ERROR_NO_DEVICE


def _is_not_found(err: BaseException) -> bool:
    en, code = _codes(err)
    return en == errno.ENOENT or code == LIBUSB_ERROR_NOT_FOUND


def device_error_class(err: BaseException) -> type[DeviceError]:
    """The :class:`~mocaprig.errors.DeviceError` subclass a pyusb error stands for.

    ACCESS -> permission, BUSY -> busy, TIMEOUT -> timeout, NO_DEVICE -> disconnected,
    NOT_FOUND -> not found; anything else is a plain :class:`~mocaprig.errors.DeviceError`.
    """
    if is_permission(err):
        return DevicePermissionError
    if is_busy(err):
        return DeviceBusyError
    if is_timeout(err):
        return DeviceTimeoutError
    if is_no_device(err):
        return DeviceDisconnectedError
    if _is_not_found(err):
        return DeviceNotFoundError
    return DeviceError


def device_error(
    message: str, err: BaseException, cls: type[DeviceError] | None = None
) -> DeviceError:
    """``cls`` (default: :func:`device_error_class` of ``err``) with ``message`` and the codes
    of ``err`` (``backend_errno``, ``backend_code``); raise it ``from err``."""
    return (cls or device_error_class(err)).from_cause(message, err)


def ctrl_read(dev: Any, module: int, param: int) -> int:
    """Read one 32-bit register with vendor request 0xBF (IN); pyusb errors propagate.

    Raises:
        DeviceError: the device returned another length than 4 bytes.
    """
    data = dev.ctrl_transfer(0xC0, VR_FPGA_CONFIG, module, param, 4, CTRL_TIMEOUT_MS)
    if len(data) != 4:
        msg = f"register ({module}, {param}) read returned {len(data)} bytes instead of 4"
        raise DeviceError(msg)
    return int.from_bytes(bytes(data), "big")
