"""The one error hierarchy of mocaprig.

Every error the toolkit raises on purpose derives from :class:`MocaprigError`. Messages name the
object, say what is wrong and what to do; causes are chained with ``raise ... from err``.

A :class:`DeviceError` says *which* device failed; its subclasses say *how*, so a caller can act
on the kind without parsing the message:

- :class:`DeviceNotFoundError`: not on the bus, no such port, a serial not connected;
- :class:`DevicePermissionError`: there, but this user may not open it (udev rule, dialout);
- :class:`DeviceBusyError`: another process holds it;
- :class:`DeviceTimeoutError`: it did not answer in time;
- :class:`DeviceDisconnectedError`: it went away while in use (cable pulled, board reset).

Each keeps what the backend said (``backend_errno``, ``backend_code``, ``backend_error``), taken
from the cause by :meth:`DeviceError.from_cause`.
"""

from __future__ import annotations

from typing import Self

__all__ = [
    "CalibrationError",
    "DeviceBusyError",
    "DeviceDisconnectedError",
    "DeviceError",
    "DeviceNotFoundError",
    "DevicePermissionError",
    "DeviceTimeoutError",
    "MocaprigError",
    "ProcessingError",
    "RecordingError",
    "ValidationError",
]


class MocaprigError(Exception):
    """Base of every error raised by mocaprig."""


class ValidationError(MocaprigError, ValueError):
    """An argument at a public boundary has the wrong shape, dtype, range or type."""


class DeviceError(MocaprigError):
    """A device is missing, busy, unreachable or misbehaving.

    Attributes:
        backend_errno: The POSIX errno the backend reported (``OSError.errno``: pyserial's
            ``SerialException``, pyusb's ``USBError.errno``), or None.
        backend_code: The backend's own numeric code (pyusb's ``USBError.backend_error_code``:
            the libusb error, e.g. -3 ``LIBUSB_ERROR_ACCESS``), or None.
        backend_error: The backend's own words (``strerror``, or the text of a pyrealsense2
            ``RuntimeError``), or None.
    """

    def __init__(
        self,
        *args: object,
        backend_errno: int | None = None,
        backend_code: int | None = None,
        backend_error: str | None = None,
    ) -> None:
        super().__init__(*args)
        self.backend_errno = backend_errno
        self.backend_code = backend_code
        self.backend_error = backend_error

    @classmethod
    def from_cause(cls, message: str, cause: BaseException) -> Self:
        """``cls(message)`` keeping the codes of ``cause``; still chain it with ``from cause``.

        ``backend_errno`` is ``cause.errno``, ``backend_code`` is ``cause.backend_error_code``
        (pyusb) and ``backend_error`` is ``cause.strerror`` or else ``str(cause)``; an attribute
        the cause lacks (or that is not an int) stays None.
        """
        en = getattr(cause, "errno", None)
        code = getattr(cause, "backend_error_code", None)
        text = getattr(cause, "strerror", None)
        if not isinstance(text, str) or not text:
            text = str(cause) or None
        return cls(
            message,
            backend_errno=en if isinstance(en, int) else None,
            backend_code=code if isinstance(code, int) else None,
            backend_error=text,
        )


class DeviceNotFoundError(DeviceError):
    """The device is not there: nothing on the bus, no such port, a serial not connected."""


class DevicePermissionError(DeviceError):
    """The device is there but this user may not open it (udev rule, serial group)."""


class DeviceBusyError(DeviceError):
    """Another process (or another handle) holds the device."""


class DeviceTimeoutError(DeviceError):
    """The device did not answer or deliver within the allowed time."""


class DeviceDisconnectedError(DeviceError):
    """The device went away while in use (cable pulled, board reset, power lost)."""


class RecordingError(MocaprigError):
    """A recording cannot be written, read or recovered."""


class CalibrationError(MocaprigError):
    """Calibration input is unusable (corrupt reference files, degenerate geometry, ...)."""


class ProcessingError(MocaprigError):
    """A processing stage (body model, DeMoCap, EventCap, metrics) cannot proceed."""
