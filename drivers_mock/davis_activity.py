"""What a DAVIS240C sensor does in a time window, before the device logic serialises it.

This is the hand-off between the DAVIS simulator (which renders the simulated world into
events, APS exposures, IMU samples and trigger edges) and the USB mock device (whose encoder
turns them into the 16-bit word stream of the bulk endpoint). Everything is in **device time**:
integer µs of the DAVIS timestamp counter, 0 at the last timestamp reset.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Protocol

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.events import check_events, empty_events
from mocaprig.errors import ValidationError
from mocaprig.validation import check_shape

__all__ = [
    "EXT_INPUT_DTYPE",
    "IMU_DTYPE",
    "ApsExposure",
    "DavisActivity",
    "DavisActivitySource",
    "ExtInputEdge",
    "empty_activity",
]

#: One IMU sample in the IMU's own axes (MPU-6050 on the DAVIS240C board).
IMU_DTYPE = np.dtype(
    [("t", "<i8"), ("accel_g", "<f8", (3,)), ("gyro_dps", "<f8", (3,)), ("temp_c", "<f8")]
)


class ExtInputEdge(IntEnum):
    """Edges seen by the external-input detector (values are not the wire codes)."""

    RISING = 1
    FALLING = 2
    PULSE = 3


#: One external-input (trigger connector) edge: ``t`` µs, ``edge`` an :class:`ExtInputEdge`.
EXT_INPUT_DTYPE = np.dtype([("t", "<i8"), ("edge", "u1")])


@dataclass(frozen=True, slots=True, eq=False)
class ApsExposure:
    """One global-shutter APS exposure.

    Attributes:
        start_us: Exposure start, device µs.
        end_us: Exposure end, device µs (``end_us - start_us`` = the configured exposure).
        cds: The frame as libcaer reports it before the 16-bit shift: reset minus signal
            (correlated double sampling), ADC counts in [0, 1023], shape (H, W) of the sensor
            ((180, 240) on a DAVIS240C), row 0 = top. The encoder turns it into raw
            reset/signal reads.
    """

    start_us: int
    end_us: int
    cds: npt.NDArray[np.float64] = field(repr=False)

    def __post_init__(self) -> None:
        check_shape(self.cds, ["H", "W"], name="ApsExposure.cds")
        if self.end_us < self.start_us:
            msg = f"ApsExposure ends ({self.end_us} µs) before it starts ({self.start_us} µs)"
            raise ValidationError(msg)


@dataclass(frozen=True, slots=True, eq=False)
class DavisActivity:
    """Sensor activity in the half-open device-time window ``[t0_us, t1_us)``.

    Attributes:
        t0_us: Window start (µs).
        t1_us: Window end (µs).
        events: DVS events, :data:`mocaprig.acquire.events.EVENT_DTYPE`, sorted by ``t``.
        exposures: APS exposures that *end* inside the window, in time order.
        imu: IMU samples (:data:`IMU_DTYPE`) inside the window, in time order.
        ext_input: Trigger edges (:data:`EXT_INPUT_DTYPE`) inside the window, in time order.
    """

    t0_us: int
    t1_us: int
    events: npt.NDArray[np.void] = field(repr=False)
    exposures: tuple[ApsExposure, ...] = ()
    imu: npt.NDArray[np.void] = field(default_factory=lambda: np.empty(0, IMU_DTYPE), repr=False)
    ext_input: npt.NDArray[np.void] = field(
        default_factory=lambda: np.empty(0, EXT_INPUT_DTYPE), repr=False
    )

    def __post_init__(self) -> None:
        check_events(self.events, name="DavisActivity.events")
        if self.t1_us < self.t0_us:
            msg = f"DavisActivity window ends ({self.t1_us}) before it starts ({self.t0_us})"
            raise ValidationError(msg)
        if self.imu.dtype != IMU_DTYPE or self.ext_input.dtype != EXT_INPUT_DTYPE:
            msg = "DavisActivity.imu / ext_input must use IMU_DTYPE / EXT_INPUT_DTYPE"
            raise ValidationError(msg)


def empty_activity(t0_us: int, t1_us: int) -> DavisActivity:
    """A window in which the sensor did nothing."""
    return DavisActivity(t0_us=t0_us, t1_us=t1_us, events=empty_events())


class DavisActivitySource(Protocol):
    """Anything that can say what the sensor did between two device times.

    Calls come with consecutive, non-overlapping windows; ``reset`` starts device time again at
    0 (a timestamp reset), ``session_ns`` telling the source which session instant that is.
    """

    def activity(self, t0_us: int, t1_us: int) -> DavisActivity:
        """The activity in ``[t0_us, t1_us)`` device µs."""
        ...

    def reset(self, *, session_ns: int) -> None:
        """Device time 0 is now session time ``session_ns``."""
        ...
