"""The DAVIS240C (FX2, logic 18) register file behind vendor requests 0xBF / 0xC2.

Every setting is a 32-bit register addressed by (module, parameter) (davis240c-usb.md §2, §3).
Numbers and power-on values are taken from the note, not from the driver: read-only registers
(sizes, orientation, HAS_* flags, SYSINFO, statistics) return the note's DAVIS240C values and
ignore writes; unknown registers read 0 (§2 "Unknown params read as 0"); MUX TIMESTAMP_RESET is a
pulse that always reads 0 (§3.1).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from enum import IntEnum

__all__ = [
    "APS",
    "BIAS",
    "DVS",
    "EXTINPUT",
    "IMU",
    "MUX",
    "SYSINFO",
    "USB",
    "DavisModule",
    "RegisterFile",
]

_log = logging.getLogger(__name__)


class DavisModule(IntEnum):
    """Module addresses (note §3)."""

    MUX = 0
    DVS = 1
    APS = 2
    IMU = 3
    EXTINPUT = 4
    BIAS = 5  # params 0..127; CHIP config is params 128..255 of the same module
    SYSINFO = 6
    USB = 9


class MUX(IntEnum):
    """MUX parameters (note §3.1)."""

    RUN = 0
    TIMESTAMP_RUN = 1
    TIMESTAMP_RESET = 2
    RUN_CHIP = 3
    DROP_EXTINPUT_ON_TRANSFER_STALL = 4
    DROP_DVS_ON_TRANSFER_STALL = 5
    HAS_STATISTICS = 80
    STATISTICS_EXTINPUT_DROPPED = 81
    STATISTICS_DVS_DROPPED = 83


class DVS(IntEnum):
    """DVS parameters (note §3.2)."""

    SIZE_COLUMNS = 0
    SIZE_ROWS = 1
    ORIENTATION_INFO = 2
    RUN = 3
    WAIT_ON_TRANSFER_STALL = 4
    EXTERNAL_AER_CONTROL = 5
    HAS_PIXEL_FILTER = 10
    FILTER_PIXEL_0_ROW = 11  # 11..26: 8 (row, column) pairs
    HAS_BACKGROUND_ACTIVITY_FILTER = 30
    FILTER_BACKGROUND_ACTIVITY = 31
    FILTER_BACKGROUND_ACTIVITY_TIME = 32
    FILTER_REFRACTORY_PERIOD = 33
    FILTER_REFRACTORY_PERIOD_TIME = 34
    HAS_ROI_FILTER = 40
    FILTER_ROI_START_COLUMN = 41
    FILTER_ROI_START_ROW = 42
    FILTER_ROI_END_COLUMN = 43
    FILTER_ROI_END_ROW = 44
    HAS_SKIP_FILTER = 50
    FILTER_SKIP_EVENTS = 51
    FILTER_SKIP_EVENTS_EVERY = 52
    HAS_POLARITY_FILTER = 60
    FILTER_POLARITY_FLATTEN = 61
    FILTER_POLARITY_SUPPRESS = 62
    FILTER_POLARITY_SUPPRESS_TYPE = 63
    HAS_STATISTICS = 80


class APS(IntEnum):
    """APS parameters (note §3.3)."""

    SIZE_COLUMNS = 0
    SIZE_ROWS = 1
    ORIENTATION_INFO = 2
    COLOR_FILTER = 3
    RUN = 4
    WAIT_ON_TRANSFER_STALL = 5
    HAS_GLOBAL_SHUTTER = 6
    GLOBAL_SHUTTER = 7
    START_COLUMN_0 = 8
    START_ROW_0 = 9
    END_COLUMN_0 = 10
    END_ROW_0 = 11
    EXPOSURE = 12
    FRAME_INTERVAL = 13


class IMU(IntEnum):
    """IMU parameters (note §3.4)."""

    TYPE = 0
    ORIENTATION_INFO = 1
    RUN_ACCELEROMETER = 2
    RUN_GYROSCOPE = 3
    RUN_TEMPERATURE = 4
    SAMPLE_RATE_DIVIDER = 5
    ACCEL_DLPF = 6
    ACCEL_FULL_SCALE = 7
    GYRO_DLPF = 9
    GYRO_FULL_SCALE = 10


class EXTINPUT(IntEnum):
    """EXTINPUT parameters (note §3.5)."""

    RUN_DETECTOR = 0
    DETECT_RISING_EDGES = 1
    DETECT_FALLING_EDGES = 2
    DETECT_PULSES = 3
    DETECT_PULSE_POLARITY = 4
    DETECT_PULSE_LENGTH = 5
    HAS_GENERATOR = 10


class SYSINFO(IntEnum):
    """SYSINFO parameters (note §3.6), all read-only."""

    LOGIC_VERSION = 0
    CHIP_IDENTIFIER = 1
    DEVICE_IS_MASTER = 2
    LOGIC_CLOCK = 3
    ADC_CLOCK = 4
    USB_CLOCK = 5
    CLOCK_DEVIATION = 6
    LOGIC_PATCH = 7


class USB(IntEnum):
    """USB module parameters (note §3.7)."""

    RUN = 0
    EARLY_PACKET_DELAY = 1


class BIAS(IntEnum):
    """DAVIS240 bias addresses in module 5 (note §3.8); CHIP config is 128..142."""

    DIFFBN = 0
    ONBN = 1
    OFFBN = 2
    APSCASEPC = 3
    DIFFCASBNC = 4
    APSROSFBN = 5
    LOCALBUFBN = 6
    PIXINVBN = 7
    PRBP = 8
    PRSFBP = 9
    REFRBP = 10
    AEPDBN = 11
    LCOLTIMEOUTBN = 12
    AEPUXBP = 13
    AEPUYBP = 14
    IFTHRBN = 15
    IFREFRBN = 16
    PADFOLLBN = 17
    APSOVERFLOWLEVELBN = 18
    BIASBUFFER = 19
    SSP = 20
    SSN = 21
    CHIP_GLOBAL_SHUTTER = 142


_M = DavisModule

#: Read-only registers and their DAVIS240C values (note §3; HAS_* filter flags and IMU
#: orientation are unknown on real logic-18 units; the note says to serve 0).
_READ_ONLY: dict[tuple[int, int], int] = {
    (_M.MUX, MUX.HAS_STATISTICS): 1,
    (_M.DVS, DVS.SIZE_COLUMNS): 240,
    (_M.DVS, DVS.SIZE_ROWS): 180,
    (_M.DVS, DVS.ORIENTATION_INFO): 0b001,
    (_M.DVS, DVS.HAS_PIXEL_FILTER): 0,
    (_M.DVS, DVS.HAS_BACKGROUND_ACTIVITY_FILTER): 0,
    (_M.DVS, DVS.HAS_ROI_FILTER): 0,
    (_M.DVS, DVS.HAS_SKIP_FILTER): 0,
    (_M.DVS, DVS.HAS_POLARITY_FILTER): 0,
    (_M.DVS, DVS.HAS_STATISTICS): 0,
    (_M.APS, APS.SIZE_COLUMNS): 240,
    (_M.APS, APS.SIZE_ROWS): 180,
    (_M.APS, APS.ORIENTATION_INFO): 0,
    (_M.APS, APS.COLOR_FILTER): 0,
    (_M.APS, APS.HAS_GLOBAL_SHUTTER): 1,
    (_M.IMU, IMU.TYPE): 1,
    (_M.IMU, IMU.ORIENTATION_INFO): 0,
    (_M.EXTINPUT, EXTINPUT.HAS_GENERATOR): 0,
    (_M.SYSINFO, SYSINFO.LOGIC_VERSION): 18,
    (_M.SYSINFO, SYSINFO.CHIP_IDENTIFIER): 2,
    (_M.SYSINFO, SYSINFO.DEVICE_IS_MASTER): 1,
    (_M.SYSINFO, SYSINFO.LOGIC_CLOCK): 90,
    (_M.SYSINFO, SYSINFO.ADC_CLOCK): 30,
    (_M.SYSINFO, SYSINFO.USB_CLOCK): 30,
    (_M.SYSINFO, SYSINFO.CLOCK_DEVIATION): 1000,
    (_M.SYSINFO, SYSINFO.LOGIC_PATCH): 1,
}

#: Statistics counters (64 bit, upper word at P, lower at P+1; note §2, §3.1). Emulated:
#: MUX STATISTICS_EXTINPUT_DROPPED and STATISTICS_DVS_DROPPED.
_STATISTICS = (
    (_M.MUX, MUX.STATISTICS_EXTINPUT_DROPPED),
    (_M.MUX, MUX.STATISTICS_DVS_DROPPED),
)

#: Power-on values of the writable registers (note §12 "Power-on state", §3 defaults).
_POWER_ON: dict[tuple[int, int], int] = {
    (_M.USB, USB.RUN): 1,
    (_M.USB, USB.EARLY_PACKET_DELAY): 30000,
    (_M.APS, APS.WAIT_ON_TRANSFER_STALL): 1,
    (_M.APS, APS.GLOBAL_SHUTTER): 1,
    (_M.APS, APS.END_COLUMN_0): 239,
    (_M.APS, APS.END_ROW_0): 179,
    (_M.APS, APS.EXPOSURE): 4000 * 30,
    (_M.APS, APS.FRAME_INTERVAL): 40000 * 30,
    (_M.IMU, IMU.ACCEL_DLPF): 1,
    (_M.IMU, IMU.ACCEL_FULL_SCALE): 1,
    (_M.IMU, IMU.GYRO_FULL_SCALE): 1,
    (_M.EXTINPUT, EXTINPUT.DETECT_PULSES): 1,
    (_M.EXTINPUT, EXTINPUT.DETECT_PULSE_POLARITY): 1,
    (_M.EXTINPUT, EXTINPUT.DETECT_PULSE_LENGTH): 900,
    (_M.DVS, 31): 1,  # BA filter enable (only meaningful with HAS_BACKGROUND_ACTIVITY_FILTER)
    (_M.DVS, 32): 8,
    (_M.DVS, 34): 1,
    (_M.DVS, 52): 5,
}


class RegisterFile:
    """(module, param) → u32 with the device's read/write semantics.

    Args:
        on_timestamp_reset: Called on a 0→1 write to MUX TIMESTAMP_RESET.
        read_only: Values that replace the note's read-only ones for this instance (or add
            read-only registers), e.g. another ORIENTATION_INFO, HAS_* filter flags, a chip id.
        power_on: Values that replace the power-on values of writable registers (a set-up
            left by another program, e.g. an enabled DVS filter).
    """

    def __init__(
        self,
        *,
        on_timestamp_reset: Callable[[], None] | None = None,
        read_only: Mapping[tuple[int, int], int] | None = None,
        power_on: Mapping[tuple[int, int], int] | None = None,
    ) -> None:
        self._read_only: dict[tuple[int, int], int] = {**_READ_ONLY, **(read_only or {})}
        self._values: dict[tuple[int, int], int] = {**_POWER_ON, **(power_on or {})}
        self._stats: dict[tuple[int, int], int] = dict.fromkeys(_STATISTICS, 0)
        self._on_timestamp_reset = on_timestamp_reset
        self.version = 0
        """Incremented by every accepted write (lets the device model cache derived settings)."""

    def read(self, module: int, param: int) -> int:
        """The value a 0xBF IN request returns (unknown registers read 0)."""
        key = (module, param)
        if key in self._read_only:
            return self._read_only[key]
        for base in _STATISTICS:
            if module == base[0] and param in (base[1], base[1] + 1):
                value = self._stats[base]
                return (value >> 32) & 0xFFFFFFFF if param == base[1] else value & 0xFFFFFFFF
        if key == (DavisModule.MUX, MUX.TIMESTAMP_RESET):
            return 0
        return self._values.get(key, 0)

    def write(self, module: int, param: int, value: int) -> None:
        """Apply a 0xBF OUT write (read-only registers ignore it, as the logic does)."""
        key = (module, param)
        value &= 0xFFFFFFFF
        self.version += 1
        if key in self._read_only or any(
            module == m and param in (p, p + 1) for m, p in _STATISTICS
        ):
            _log.debug("DAVIS mock: write to read-only register %s ignored", key)
            return
        if key == (DavisModule.MUX, MUX.TIMESTAMP_RESET):
            previous = self._values.get(key, 0)
            self._values[key] = value & 1
            if value & 1 and not previous and self._on_timestamp_reset is not None:
                self._on_timestamp_reset()
            return
        self._values[key] = value

    def get(self, module: int, param: int) -> int:
        """The stored value (for the device model; no side effects)."""
        return self.read(module, param)

    def flag(self, module: int, param: int) -> bool:
        """A register used as an on/off bit."""
        return bool(self.read(module, param) & 1)

    def set_statistic(self, module: int, param: int, value: int) -> None:
        """Update a 64-bit statistics counter (upper word at ``param``)."""
        self._stats[(module, param)] = int(value) & 0xFFFFFFFFFFFFFFFF
