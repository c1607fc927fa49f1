"""The error hierarchy: the device-error kinds a user can act on and the codes they keep."""

from __future__ import annotations

import errno
import pickle

import pytest
import serial
import usb.core

import mocaprig
from mocaprig import errors
from mocaprig.errors import (
    DeviceBusyError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceNotFoundError,
    DevicePermissionError,
    DeviceTimeoutError,
    MocaprigError,
)

KINDS = (
    DeviceNotFoundError,
    DevicePermissionError,
    DeviceBusyError,
    DeviceTimeoutError,
    DeviceDisconnectedError,
)


@pytest.mark.parametrize("cls", KINDS)
def test_every_kind_is_a_device_error_and_nothing_else(cls: type[DeviceError]) -> None:
    assert issubclass(cls, DeviceError)
    assert issubclass(cls, MocaprigError)
    # Not an OSError: drivers catch OSError from their backends to retry or reopen.
    assert not issubclass(cls, OSError)
    assert [k for k in KINDS if issubclass(cls, k)] == [cls]
    with pytest.raises(DeviceError, match="camera 7: gone"):
        raise cls("camera 7: gone")


@pytest.mark.parametrize("cls", KINDS)
def test_every_kind_is_exported(cls: type[DeviceError]) -> None:
    assert cls.__name__ in errors.__all__
    assert cls.__name__ in mocaprig.__all__
    assert getattr(mocaprig, cls.__name__) is cls


def test_codes_default_to_none_and_are_keyword_only() -> None:
    err = DeviceError("sync box on /dev/ttyACM0 is not open")
    assert (err.backend_errno, err.backend_code, err.backend_error) == (None, None, None)
    assert err.args == ("sync box on /dev/ttyACM0 is not open",)
    err = DeviceBusyError("busy", backend_errno=errno.EBUSY, backend_error="Resource busy")
    assert (err.backend_errno, err.backend_code, err.backend_error) == (
        errno.EBUSY,
        None,
        "Resource busy",
    )
    assert str(err) == "busy"


def test_from_cause_keeps_pyusb_errno_and_libusb_code() -> None:
    cause = usb.core.USBError("Access denied (insufficient permissions)", -3, errno.EACCES)
    err = DevicePermissionError.from_cause("DAVIS240C 1: permission denied", cause)
    assert type(err) is DevicePermissionError
    assert str(err) == "DAVIS240C 1: permission denied"
    assert err.backend_errno == errno.EACCES
    assert err.backend_code == -3
    assert err.backend_error == "Access denied (insufficient permissions)"


def test_from_cause_keeps_a_usb_timeout() -> None:
    cause = usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
    err = DeviceTimeoutError.from_cause("timed out", cause)
    assert (err.backend_errno, err.backend_code) == (errno.ETIMEDOUT, -7)


def test_from_cause_keeps_pyserial_errno() -> None:
    cause = serial.SerialException(errno.ENOENT, "could not open port /dev/ttyACM9")
    err = DeviceNotFoundError.from_cause("sync box port /dev/ttyACM9 does not exist", cause)
    assert err.backend_errno == errno.ENOENT
    assert err.backend_code is None
    assert err.backend_error == "could not open port /dev/ttyACM9"


def test_from_cause_keeps_the_text_of_an_sdk_runtime_error() -> None:
    cause = RuntimeError("xioctl(VIDIOC_S_FMT) failed Last Error: Device or resource busy")
    err = DeviceBusyError.from_cause("D415 1: cannot open", cause)
    assert err.backend_errno is None
    assert err.backend_code is None
    assert err.backend_error == str(cause)


def test_from_cause_ignores_codes_that_are_not_integers() -> None:
    class Odd(Exception):
        errno = "ENODEV"
        backend_error_code = None

    err = DeviceDisconnectedError.from_cause("gone", Odd())
    assert (err.backend_errno, err.backend_code, err.backend_error) == (None, None, None)


@pytest.mark.parametrize("cls", [DeviceError, *KINDS])
def test_a_device_error_survives_pickling_with_its_codes(cls: type[DeviceError]) -> None:
    cause = usb.core.USBError("No such device", -4, errno.ENODEV)
    back = pickle.loads(pickle.dumps(cls.from_cause("DAVIS240C 1: disconnected", cause)))
    assert type(back) is cls
    assert str(back) == "DAVIS240C 1: disconnected"
    assert (back.backend_errno, back.backend_code, back.backend_error) == (
        errno.ENODEV,
        -4,
        "No such device",
    )
