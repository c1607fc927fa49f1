"""Device drivers, the recorder and the recording format (the on-disk contract).

Imports flow one way: ``process -> calib -> acquire``.
"""

from __future__ import annotations

from acquire.errors import (
    CalibrationError,
    DeviceError,
    MocaprigError,
    ProcessingError,
    RecordingError,
    ValidationError,
)

__all__ = [
    "CalibrationError",
    "DeviceError",
    "MocaprigError",
    "ProcessingError",
    "RecordingError",
    "ValidationError",
]

__version__ = "0.1.0"
