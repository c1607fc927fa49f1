"""mocaprig: acquire, calibrate and process a DAVIS240C + RealSense D415 + Vicon rig.

The import tree (``docs/architecture.md``):

- bottom layer, used by every package: :mod:`mocaprig.errors`, :mod:`mocaprig.validation`,
  :mod:`mocaprig.timebase`, :mod:`mocaprig.progress`, :mod:`mocaprig.json_values`;
- :mod:`mocaprig.acquire` (drivers, recorder, recording contract) <- :mod:`mocaprig.calib` <-
  :mod:`mocaprig.process`; :mod:`mocaprig.drivers_mock` (the simulated world and the mock
  devices) is never imported by the other three;
- top: :mod:`mocaprig.cli`, the ``mocaprig`` command, which finds the command groups through
  entry points.
"""

from __future__ import annotations

from mocaprig.errors import (
    CalibrationError,
    DeviceBusyError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceNotFoundError,
    DevicePermissionError,
    DeviceTimeoutError,
    MocaprigError,
    ProcessingError,
    RecordingError,
    ValidationError,
)

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
    "__version__",
]

__version__ = "0.1.0"
