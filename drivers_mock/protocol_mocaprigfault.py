"""pyserial's URL handler for ``mocaprigfault://`` (the sync box behind a fault schedule).

pyserial imports ``<package>.protocol_<scheme>`` for each package listed in
``serial.protocol_handler_packages`` (:mod:`.faults` adds this package); the handler itself
lives in :mod:`.faults`.
"""

from __future__ import annotations

from mocaprig.drivers_mock.faults import serial_class_for_url

__all__ = ["serial_class_for_url"]
