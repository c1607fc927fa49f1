"""The one error hierarchy of mocaprig.

Every error the toolkit raises on purpose derives from :class:`MocaprigError`. Messages name the
object, say what is wrong and what to do; causes are chained with ``raise ... from err``.
"""

from __future__ import annotations

__all__ = [
    "CalibrationError",
    "DeviceError",
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
    """A device is missing, busy, unreachable or misbehaving."""


class RecordingError(MocaprigError):
    """A recording cannot be written, read or recovered."""


class CalibrationError(MocaprigError):
    """Calibration input is unusable (corrupt reference files, degenerate geometry, ...)."""


class ProcessingError(MocaprigError):
    """A processing stage (body model, DeMoCap, EventCap, metrics) cannot proceed."""
