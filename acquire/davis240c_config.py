"""DAVIS240C configuration: modules, parameters, bias encoding, settings and presets.

Every device setting is a 32-bit register addressed by (module, parameter), written with vendor
request 0xBF (or batched with 0xC2). Names and numbers follow libcaer ``davis.h`` for logic 18
(``docs/davis240c-usb.md`` §3). Host units (µs, 125 µs slots) are converted to device clock
cycles by :func:`to_device_units` (§2.1). Biases use the DAVIS240 coarse-fine and
shifted-source encodings (§4); :data:`BIAS_PRESETS` holds the named bias sets.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from enum import Enum, IntEnum
from types import MappingProxyType
from typing import Final

from mocaprig.errors import ValidationError

__all__ = [
    "BIAS_PRESETS",
    "PARAMETER_GROUPS",
    "READ_ONLY",
    "ApsParam",
    "ApsSettings",
    "BiasCurrentLevel",
    "BiasParam",
    "BiasPreset",
    "BiasSex",
    "BiasType",
    "ChipParam",
    "CoarseFineBias",
    "DavisSettings",
    "DeviceClocks",
    "DvsFilters",
    "DvsParam",
    "ExtInputParam",
    "ExtInputSettings",
    "ImuParam",
    "ImuSettings",
    "Module",
    "MuxParam",
    "RegisterWrite",
    "ShiftedSourceBias",
    "ShiftedSourceMode",
    "ShiftedSourceVoltage",
    "SysInfoParam",
    "UsbParam",
    "bias_set",
    "default_config_writes",
    "dvs_filter_reset_writes",
    "parse_setting",
    "to_device_units",
]


class Module(IntEnum):
    """Module addresses (wValue of 0xBF). CHIP registers live in BIAS at params 128..255."""

    MUX = 0
    DVS = 1
    APS = 2
    IMU = 3
    EXTINPUT = 4
    BIAS = 5
    SYSINFO = 6
    USB = 9


class MuxParam(IntEnum):
    RUN = 0
    TIMESTAMP_RUN = 1
    TIMESTAMP_RESET = 2
    RUN_CHIP = 3
    DROP_EXTINPUT_ON_TRANSFER_STALL = 4
    DROP_DVS_ON_TRANSFER_STALL = 5
    HAS_STATISTICS = 80
    STATISTICS_EXTINPUT_DROPPED = 81
    STATISTICS_DVS_DROPPED = 83


class DvsParam(IntEnum):
    SIZE_COLUMNS = 0
    SIZE_ROWS = 1
    ORIENTATION_INFO = 2
    RUN = 3
    WAIT_ON_TRANSFER_STALL = 4
    EXTERNAL_AER_CONTROL = 5
    HAS_PIXEL_FILTER = 10
    FILTER_PIXEL_0_ROW = 11
    FILTER_PIXEL_0_COLUMN = 12
    FILTER_PIXEL_1_ROW = 13
    FILTER_PIXEL_1_COLUMN = 14
    FILTER_PIXEL_2_ROW = 15
    FILTER_PIXEL_2_COLUMN = 16
    FILTER_PIXEL_3_ROW = 17
    FILTER_PIXEL_3_COLUMN = 18
    FILTER_PIXEL_4_ROW = 19
    FILTER_PIXEL_4_COLUMN = 20
    FILTER_PIXEL_5_ROW = 21
    FILTER_PIXEL_5_COLUMN = 22
    FILTER_PIXEL_6_ROW = 23
    FILTER_PIXEL_6_COLUMN = 24
    FILTER_PIXEL_7_ROW = 25
    FILTER_PIXEL_7_COLUMN = 26
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
    STATISTICS_EVENTS_ROW = 81
    STATISTICS_EVENTS_COLUMN = 83
    STATISTICS_EVENTS_DROPPED = 85


class ApsParam(IntEnum):
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


class ImuParam(IntEnum):
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


class ExtInputParam(IntEnum):
    RUN_DETECTOR = 0
    DETECT_RISING_EDGES = 1
    DETECT_FALLING_EDGES = 2
    DETECT_PULSES = 3
    DETECT_PULSE_POLARITY = 4
    DETECT_PULSE_LENGTH = 5
    HAS_GENERATOR = 10
    RUN_GENERATOR = 11
    GENERATE_PULSE_POLARITY = 12
    GENERATE_PULSE_INTERVAL = 13
    GENERATE_PULSE_LENGTH = 14
    GENERATE_INJECT_ON_RISING_EDGE = 15
    GENERATE_INJECT_ON_FALLING_EDGE = 16


class BiasParam(IntEnum):
    """DAVIS240 bias registers (module BIAS, params 0..21)."""

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


class ChipParam(IntEnum):
    """DAVIS240C chip-configuration registers (module BIAS, params 128..)."""

    DIGITALMUX0 = 128
    DIGITALMUX1 = 129
    DIGITALMUX2 = 130
    DIGITALMUX3 = 131
    ANALOGMUX0 = 132
    ANALOGMUX1 = 133
    ANALOGMUX2 = 134
    BIASMUX0 = 135
    RESETCALIBNEURON = 136
    TYPENCALIBNEURON = 137
    RESETTESTPIXEL = 138
    AERNAROW = 140
    USEAOUT = 141
    GLOBAL_SHUTTER = 142


class SysInfoParam(IntEnum):
    LOGIC_VERSION = 0
    CHIP_IDENTIFIER = 1
    DEVICE_IS_MASTER = 2
    LOGIC_CLOCK = 3
    ADC_CLOCK = 4
    USB_CLOCK = 5
    CLOCK_DEVIATION = 6
    LOGIC_PATCH = 7


class UsbParam(IntEnum):
    RUN = 0
    EARLY_PACKET_DELAY = 1


#: Name used on the command line -> (module address, parameter enum).
PARAMETER_GROUPS: Final[Mapping[str, tuple[Module, type[IntEnum]]]] = MappingProxyType(
    {
        "MUX": (Module.MUX, MuxParam),
        "DVS": (Module.DVS, DvsParam),
        "APS": (Module.APS, ApsParam),
        "IMU": (Module.IMU, ImuParam),
        "EXTINPUT": (Module.EXTINPUT, ExtInputParam),
        "BIAS": (Module.BIAS, BiasParam),
        "CHIP": (Module.BIAS, ChipParam),
        "SYSINFO": (Module.SYSINFO, SysInfoParam),
        "USB": (Module.USB, UsbParam),
    }
)

#: Registers the host must not write (read-only on the device).
READ_ONLY: Final[frozenset[tuple[int, int]]] = frozenset(
    [(Module.SYSINFO, int(p)) for p in SysInfoParam]
    + [(Module.MUX, int(p)) for p in (80, 81, 82, 83, 84)]
    + [(Module.DVS, int(p)) for p in (0, 1, 2, 10, 30, 40, 50, 60, *range(80, 93))]
    + [(Module.APS, int(p)) for p in (0, 1, 2, 3, 6)]
    + [(Module.IMU, 0), (Module.IMU, 1), (Module.EXTINPUT, 10)]
)


@dataclass(frozen=True, slots=True)
class RegisterWrite:
    """One register write: ``value`` (uint32, device units) to (``module``, ``param``)."""

    module: int
    param: int
    value: int

    def __post_init__(self) -> None:
        if not (0 <= self.module <= 127 and 0 <= self.param <= 255):
            msg = f"register ({self.module}, {self.param}) is outside module 0..127 / param 0..255"
            raise ValidationError(msg)
        if not 0 <= self.value <= 0xFFFFFFFF:
            msg = f"value {self.value} for register ({self.module}, {self.param}) is not a uint32"
            raise ValidationError(msg)


# -- clocks and host units ---------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DeviceClocks:
    """Clocks read from SYSINFO (MHz); FX2 DAVIS240C: logic 90, ADC 30, USB 30, exact."""

    logic_mhz: int = 90
    adc_mhz: int = 30
    usb_mhz: int = 30
    deviation_x1000: int = 1000

    def effective_mhz(self, nominal_mhz: int) -> float:
        """``nominal_mhz`` corrected by CLOCK_DEVIATION."""
        return nominal_mhz * self.deviation_x1000 / 1000.0


def to_device_units(module: int, param: int, value: float, clocks: DeviceClocks) -> int:
    """Convert a host-unit value to the register value, as libcaer does (note §2.1).

    APS EXPOSURE / FRAME_INTERVAL: µs -> ADC cycles; USB EARLY_PACKET_DELAY: 125 µs slots ->
    USB cycles; EXTINPUT pulse length / generator interval / length: µs -> logic cycles. Any
    other register is returned as an int unchanged.
    """
    if module == Module.APS and param in (ApsParam.EXPOSURE, ApsParam.FRAME_INTERVAL):
        return round(value * clocks.effective_mhz(clocks.adc_mhz))
    if module == Module.USB and param == UsbParam.EARLY_PACKET_DELAY:
        return round(value * 125 * clocks.effective_mhz(clocks.usb_mhz))
    if module == Module.EXTINPUT and param in (
        ExtInputParam.DETECT_PULSE_LENGTH,
        ExtInputParam.GENERATE_PULSE_INTERVAL,
        ExtInputParam.GENERATE_PULSE_LENGTH,
    ):
        return round(value * clocks.effective_mhz(clocks.logic_mhz))
    return int(value)


# -- biases ------------------------------------------------------------------------------------


class BiasSex(Enum):
    N = "N"
    P = "P"


class BiasType(Enum):
    NORMAL = "normal"
    CASCODE = "cascode"


class BiasCurrentLevel(Enum):
    NORMAL = "normal"
    LOW = "low"


#: libcaer coarse index -> maximum current (pA).
_COARSE_CURRENT_PA: Final = (11, 94, 756, 6054, 48437, 387500, 3100000, 24800000)


@dataclass(frozen=True, slots=True)
class CoarseFineBias:
    """A DAVIS240 coarse-fine current bias (16 bits ``UCCC FFFF FFFF LCSE``).

    Attributes:
        coarse: 0..7 (7 = largest current, 24.8 µA).
        fine: 0..255, linear fraction of the coarse current (0 = off).
        sex: N- or P-type transistor.
        type: NORMAL or CASCODE.
        current_level: NORMAL or LOW.
        enabled: Bias switched on.
    """

    coarse: int
    fine: int
    sex: BiasSex = BiasSex.N
    type: BiasType = BiasType.NORMAL
    current_level: BiasCurrentLevel = BiasCurrentLevel.NORMAL
    enabled: bool = True

    def __post_init__(self) -> None:
        if not (0 <= self.coarse <= 7 and 0 <= self.fine <= 255):
            msg = f"coarse-fine bias ({self.coarse}, {self.fine}) outside coarse 0..7, fine 0..255"
            raise ValidationError(msg)

    def encode(self) -> int:
        """The 16-bit register value (libcaer ``caerBiasCoarseFineGenerate``)."""
        return (
            int(self.enabled)
            | (self.sex is BiasSex.N) << 1
            | (self.type is BiasType.NORMAL) << 2
            | (self.current_level is BiasCurrentLevel.NORMAL) << 3
            | self.fine << 4
            | self.coarse << 12
        )

    @classmethod
    def decode(cls, value: int) -> CoarseFineBias:
        """Inverse of :meth:`encode` (bit 15 is ignored)."""
        return cls(
            coarse=(value >> 12) & 7,
            fine=(value >> 4) & 0xFF,
            sex=BiasSex.N if value & 2 else BiasSex.P,
            type=BiasType.NORMAL if value & 4 else BiasType.CASCODE,
            current_level=BiasCurrentLevel.NORMAL if value & 8 else BiasCurrentLevel.LOW,
            enabled=bool(value & 1),
        )

    @property
    def current_pa(self) -> float:
        """Approximate current (pA): coarse maximum × fine / 255."""
        return _COARSE_CURRENT_PA[self.coarse] * self.fine / 255.0


class ShiftedSourceMode(IntEnum):
    SHIFTED_SOURCE = 0
    HI_Z = 1
    TIED_TO_RAIL = 2


class ShiftedSourceVoltage(IntEnum):
    SPLIT_GATE = 0
    SINGLE_DIODE = 1
    DOUBLE_DIODE = 2


@dataclass(frozen=True, slots=True)
class ShiftedSourceBias:
    """A DAVIS240 shifted-source bias (SSP/SSN), libcaer ``caerBiasShiftedSourceGenerate``."""

    ref_value: int
    reg_value: int
    operating_mode: ShiftedSourceMode = ShiftedSourceMode.SHIFTED_SOURCE
    voltage_level: ShiftedSourceVoltage = ShiftedSourceVoltage.SPLIT_GATE

    def __post_init__(self) -> None:
        if not (0 <= self.ref_value <= 63 and 0 <= self.reg_value <= 63):
            msg = f"shifted-source bias ref {self.ref_value} / reg {self.reg_value} outside 0..63"
            raise ValidationError(msg)

    def encode(self) -> int:
        """The 16-bit register value."""
        return (
            int(self.operating_mode) & 3
            | (int(self.voltage_level) & 3) << 2
            | self.ref_value << 4
            | self.reg_value << 10
        )

    @classmethod
    def decode(cls, value: int) -> ShiftedSourceBias:
        """Inverse of :meth:`encode`."""
        return cls(
            ref_value=(value >> 4) & 0x3F,
            reg_value=(value >> 10) & 0x3F,
            operating_mode=ShiftedSourceMode(value & 3),
            voltage_level=ShiftedSourceVoltage((value >> 2) & 3),
        )


Bias = CoarseFineBias | ShiftedSourceBias

_N, _P = BiasSex.N, BiasSex.P
_CAS = BiasType.CASCODE
_SS = ShiftedSourceBias(ref_value=1, reg_value=33)

#: libcaer 3.3 ``davisCommonSendDefaultChipConfig`` for the DAVIS240 (note §4).
_LIBCAER_DEFAULT: Final[Mapping[BiasParam, Bias]] = MappingProxyType(
    {
        BiasParam.DIFFBN: CoarseFineBias(4, 39, _N),
        BiasParam.ONBN: CoarseFineBias(5, 255, _N),
        BiasParam.OFFBN: CoarseFineBias(4, 0, _N),
        BiasParam.APSCASEPC: CoarseFineBias(5, 185, _N, _CAS),
        BiasParam.DIFFCASBNC: CoarseFineBias(5, 115, _N, _CAS),
        BiasParam.APSROSFBN: CoarseFineBias(6, 219, _N),
        BiasParam.LOCALBUFBN: CoarseFineBias(5, 164, _N),
        BiasParam.PIXINVBN: CoarseFineBias(6, 144, _N),
        BiasParam.PRBP: CoarseFineBias(2, 58, _P),
        BiasParam.PRSFBP: CoarseFineBias(1, 16, _P),
        BiasParam.REFRBP: CoarseFineBias(4, 25, _P),
        BiasParam.AEPDBN: CoarseFineBias(6, 91, _N),
        BiasParam.LCOLTIMEOUTBN: CoarseFineBias(5, 49, _N),
        BiasParam.AEPUXBP: CoarseFineBias(4, 80, _P),
        BiasParam.AEPUYBP: CoarseFineBias(7, 152, _P),
        BiasParam.IFTHRBN: CoarseFineBias(5, 255, _N),
        BiasParam.IFREFRBN: CoarseFineBias(5, 255, _N),
        BiasParam.PADFOLLBN: CoarseFineBias(7, 215, _N),
        BiasParam.APSOVERFLOWLEVELBN: CoarseFineBias(6, 253, _N),
        BiasParam.BIASBUFFER: CoarseFineBias(5, 254, _N),
        BiasParam.SSP: _SS,
        BiasParam.SSN: _SS,
    }
)


class BiasPreset(Enum):
    """Named DAVIS240C bias sets (each from a published source, note §4).

    DEFAULT: libcaer 3.3 defaults. LEGACY: libcaer before 2019 (PIXINVBN 5/129, later raised
    "to prevent line errors"). PYAER: pyaer's ``davis240c_config.json`` (ONBN 6/200,
    PIXINVBN 5/129, PRSFBP 1/33).
    """

    DEFAULT = "default"
    LEGACY = "legacy"
    PYAER = "pyaer"


_PRESET_CHANGES: Final[Mapping[BiasPreset, Mapping[BiasParam, Bias]]] = MappingProxyType(
    {
        BiasPreset.DEFAULT: {},
        BiasPreset.LEGACY: {BiasParam.PIXINVBN: CoarseFineBias(5, 129, _N)},
        BiasPreset.PYAER: {
            BiasParam.ONBN: CoarseFineBias(6, 200, _N),
            BiasParam.PIXINVBN: CoarseFineBias(5, 129, _N),
            BiasParam.PRSFBP: CoarseFineBias(1, 33, _P),
        },
    }
)


def bias_set(preset: BiasPreset | str = BiasPreset.DEFAULT) -> Mapping[BiasParam, Bias]:
    """The 22 DAVIS240 biases of a named preset (read-only mapping).

    Raises:
        ValidationError: unknown preset name; the message lists the known ones.
    """
    try:
        p = preset if isinstance(preset, BiasPreset) else BiasPreset(str(preset).lower())
    except ValueError as err:
        known = ", ".join(x.value for x in BiasPreset)
        msg = f"unknown DAVIS240C bias preset {preset!r}; choose one of: {known}"
        raise ValidationError(msg) from err
    return MappingProxyType({**_LIBCAER_DEFAULT, **_PRESET_CHANGES[p]})


#: Every preset, by name.
BIAS_PRESETS: Final[Mapping[str, Mapping[BiasParam, Bias]]] = MappingProxyType(
    {p.value: bias_set(p) for p in BiasPreset}
)


# -- typed settings ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ApsSettings:
    """APS settings in host units (defaults = libcaer's)."""

    global_shutter: bool = True
    start_column: int = 0
    start_row: int = 0
    end_column: int = 239
    end_row: int = 179
    exposure_us: int = 4000
    frame_interval_us: int = 40000
    wait_on_transfer_stall: bool = True

    def __post_init__(self) -> None:
        if not (0 <= self.start_column <= self.end_column <= 239):
            msg = f"APS ROI columns {self.start_column}..{self.end_column} not within 0..239"
            raise ValidationError(msg)
        if not (0 <= self.start_row <= self.end_row <= 179):
            msg = f"APS ROI rows {self.start_row}..{self.end_row} not within 0..179"
            raise ValidationError(msg)
        if not (0 <= self.exposure_us <= 4194303 and 0 <= self.frame_interval_us <= 8388607):
            msg = (
                f"APS exposure {self.exposure_us} µs / interval {self.frame_interval_us} µs "
                "outside 0..4194303 / 0..8388607"
            )
            raise ValidationError(msg)


@dataclass(frozen=True, slots=True)
class ImuSettings:
    """IMU settings: full-scale codes 0..3 (±2/4/8/16 g, ±250/500/1000/2000 °/s)."""

    sample_rate_divider: int = 0
    accel_dlpf: int = 1
    accel_full_scale: int = 1
    gyro_full_scale: int = 1

    def __post_init__(self) -> None:
        ok = (
            0 <= self.sample_rate_divider <= 255
            and 0 <= self.accel_dlpf <= 7
            and 0 <= self.accel_full_scale <= 3
            and 0 <= self.gyro_full_scale <= 3
        )
        if not ok:
            msg = f"IMU settings out of range: {self}"
            raise ValidationError(msg)

    @property
    def rate_hz(self) -> float:
        """Sample rate (1 kHz gyro output rate / (1 + divider); 8 kHz if DLPF is 0 or 7)."""
        base = 8000.0 if self.accel_dlpf in (0, 7) else 1000.0
        return base / (1 + self.sample_rate_divider)


@dataclass(frozen=True, slots=True)
class ExtInputSettings:
    """External-input (sync connector signal line) detector settings."""

    detect_rising_edges: bool = False
    detect_falling_edges: bool = False
    detect_pulses: bool = True
    pulse_active_high: bool = True
    pulse_length_us: int = 10

    def __post_init__(self) -> None:
        if not 1 <= self.pulse_length_us <= 1048575:
            msg = f"ext-input pulse length {self.pulse_length_us} µs outside 1..1048575"
            raise ValidationError(msg)


@dataclass(frozen=True, slots=True)
class DavisSettings:
    """Everything :meth:`mocaprig.acquire.davis240c.Davis240C.send_default_config` writes."""

    biases: Mapping[BiasParam, Bias] = field(default_factory=bias_set)
    aps: ApsSettings = field(default_factory=ApsSettings)
    imu: ImuSettings = field(default_factory=ImuSettings)
    ext_input: ExtInputSettings = field(default_factory=ExtInputSettings)
    early_packet_delay_125us: int = 8

    @classmethod
    def from_preset(cls, preset: BiasPreset | str, **changes: object) -> DavisSettings:
        """Settings with the biases of ``preset`` (other sections default or ``changes``)."""
        return replace(cls(), biases=bias_set(preset), **changes)  # type: ignore[arg-type]


@dataclass(frozen=True, slots=True)
class DvsFilters:
    """Which DVS filters the logic has (the DVS HAS_* registers, read at open)."""

    pixel: bool = False
    background_activity: bool = False
    roi: bool = False
    skip: bool = False
    polarity: bool = False


def dvs_filter_reset_writes(
    filters: DvsFilters, *, columns: int = 240, rows: int = 180
) -> list[RegisterWrite]:
    """libcaer 3.3's default (= reset) values of the DVS filters the logic has.

    ``davisCommonSendDefaultFPGAConfig``: the 8 suppressed pixels moved out of range (row =
    ``rows``, column = ``columns``), background-activity filter on with 2 ms (8 × 250 µs),
    refractory filter off with 250 µs, ROI = the whole array, skip filter off (every 5th),
    polarity filters off. Filters the logic lacks get no write (libcaer sends none).
    """
    D = Module.DVS
    out: list[RegisterWrite] = []
    if filters.pixel:
        for k in range(8):
            out.append(RegisterWrite(D, DvsParam.FILTER_PIXEL_0_ROW + 2 * k, rows))
            out.append(RegisterWrite(D, DvsParam.FILTER_PIXEL_0_COLUMN + 2 * k, columns))
    if filters.background_activity:
        out += [
            RegisterWrite(D, DvsParam.FILTER_BACKGROUND_ACTIVITY, 1),
            RegisterWrite(D, DvsParam.FILTER_BACKGROUND_ACTIVITY_TIME, 8),
            RegisterWrite(D, DvsParam.FILTER_REFRACTORY_PERIOD, 0),
            RegisterWrite(D, DvsParam.FILTER_REFRACTORY_PERIOD_TIME, 1),
        ]
    if filters.roi:
        out += [
            RegisterWrite(D, DvsParam.FILTER_ROI_START_COLUMN, 0),
            RegisterWrite(D, DvsParam.FILTER_ROI_START_ROW, 0),
            RegisterWrite(D, DvsParam.FILTER_ROI_END_COLUMN, columns - 1),
            RegisterWrite(D, DvsParam.FILTER_ROI_END_ROW, rows - 1),
        ]
    if filters.skip:
        out += [
            RegisterWrite(D, DvsParam.FILTER_SKIP_EVENTS, 0),
            RegisterWrite(D, DvsParam.FILTER_SKIP_EVENTS_EVERY, 5),
        ]
    if filters.polarity:
        out += [
            RegisterWrite(D, DvsParam.FILTER_POLARITY_FLATTEN, 0),
            RegisterWrite(D, DvsParam.FILTER_POLARITY_SUPPRESS, 0),
            RegisterWrite(D, DvsParam.FILTER_POLARITY_SUPPRESS_TYPE, 0),
        ]
    return out


def default_config_writes(
    settings: DavisSettings | None = None,
    *,
    clocks: DeviceClocks | None = None,
    dvs_filters: DvsFilters | None = None,
) -> list[RegisterWrite]:
    """The register writes of libcaer's ``sendDefaultConfig`` for a DAVIS240C (note §5.2).

    The DVS filter registers are reset (:func:`dvs_filter_reset_writes`) for the filters
    ``dvs_filters`` says the logic has, right after the other DVS registers, as libcaer does;
    none without it. Generator (EXTINPUT) registers are not written (the FX2 DAVIS240C has
    no generator).
    """
    s = settings if settings is not None else DavisSettings()
    c = clocks if clocks is not None else DeviceClocks()
    B, M = Module.BIAS, Module
    out = [RegisterWrite(B, int(p), s.biases[p].encode()) for p in BiasParam]
    out += [RegisterWrite(B, int(p), 0) for p in list(ChipParam)[:8]]
    out += [
        RegisterWrite(B, ChipParam.RESETCALIBNEURON, 1),
        RegisterWrite(B, ChipParam.TYPENCALIBNEURON, 0),
        RegisterWrite(B, ChipParam.RESETTESTPIXEL, 1),
        RegisterWrite(B, ChipParam.AERNAROW, 0),
        RegisterWrite(B, ChipParam.USEAOUT, 0),
        RegisterWrite(M.MUX, MuxParam.DROP_EXTINPUT_ON_TRANSFER_STALL, 1),
        RegisterWrite(M.MUX, MuxParam.DROP_DVS_ON_TRANSFER_STALL, 1),
        RegisterWrite(M.DVS, DvsParam.WAIT_ON_TRANSFER_STALL, 0),
        RegisterWrite(M.DVS, DvsParam.EXTERNAL_AER_CONTROL, 0),
    ]
    if dvs_filters is not None:
        out += dvs_filter_reset_writes(dvs_filters)
    a = s.aps
    gs = int(a.global_shutter)

    def aps_us(param: ApsParam, us: int) -> RegisterWrite:
        return RegisterWrite(M.APS, param, to_device_units(M.APS, param, us, c))

    out += [
        RegisterWrite(M.APS, ApsParam.WAIT_ON_TRANSFER_STALL, int(a.wait_on_transfer_stall)),
        RegisterWrite(B, ChipParam.GLOBAL_SHUTTER, gs),
        RegisterWrite(M.APS, ApsParam.GLOBAL_SHUTTER, gs),
        RegisterWrite(M.APS, ApsParam.START_COLUMN_0, a.start_column),
        RegisterWrite(M.APS, ApsParam.START_ROW_0, a.start_row),
        RegisterWrite(M.APS, ApsParam.END_COLUMN_0, a.end_column),
        RegisterWrite(M.APS, ApsParam.END_ROW_0, a.end_row),
        aps_us(ApsParam.EXPOSURE, a.exposure_us),
        aps_us(ApsParam.FRAME_INTERVAL, a.frame_interval_us),
    ]
    i = s.imu
    out += [
        RegisterWrite(M.IMU, ImuParam.SAMPLE_RATE_DIVIDER, i.sample_rate_divider),
        RegisterWrite(M.IMU, ImuParam.ACCEL_DLPF, i.accel_dlpf),
        RegisterWrite(M.IMU, ImuParam.ACCEL_FULL_SCALE, i.accel_full_scale),
        RegisterWrite(M.IMU, ImuParam.GYRO_FULL_SCALE, i.gyro_full_scale),
    ]
    e = s.ext_input
    pulse = to_device_units(M.EXTINPUT, ExtInputParam.DETECT_PULSE_LENGTH, e.pulse_length_us, c)
    out += [
        RegisterWrite(M.EXTINPUT, ExtInputParam.DETECT_RISING_EDGES, int(e.detect_rising_edges)),
        RegisterWrite(M.EXTINPUT, ExtInputParam.DETECT_FALLING_EDGES, int(e.detect_falling_edges)),
        RegisterWrite(M.EXTINPUT, ExtInputParam.DETECT_PULSES, int(e.detect_pulses)),
        RegisterWrite(M.EXTINPUT, ExtInputParam.DETECT_PULSE_POLARITY, int(e.pulse_active_high)),
        RegisterWrite(M.EXTINPUT, ExtInputParam.DETECT_PULSE_LENGTH, pulse),
        RegisterWrite(
            M.USB,
            UsbParam.EARLY_PACKET_DELAY,
            to_device_units(M.USB, UsbParam.EARLY_PACKET_DELAY, s.early_packet_delay_125us, c),
        ),
    ]
    return out


def parse_setting(text: str, *, clocks: DeviceClocks | None = None) -> RegisterWrite:
    """Parse ``MODULE.PARAM=VALUE`` (libcaer names, host units) into a register write.

    VALUE is an integer (``0x`` prefix allowed), ``true``/``false``, µs for APS EXPOSURE /
    FRAME_INTERVAL and EXTINPUT lengths, 125 µs slots for USB EARLY_PACKET_DELAY, and for BIAS
    either the raw 16-bit value or ``COARSE/FINE`` (keeping the default's sex and type).

    Raises:
        ValidationError: unknown module or parameter, read-only register, bad value.
    """
    c = clocks if clocks is not None else DeviceClocks()
    name, sep, raw = text.partition("=")
    group, dot, pname = name.strip().upper().partition(".")
    if not sep or not dot or not raw.strip():
        msg = f"setting {text!r} is not MODULE.PARAM=VALUE (e.g. APS.EXPOSURE=8000)"
        raise ValidationError(msg)
    if group not in PARAMETER_GROUPS:
        msg = f"unknown module {group!r} in {text!r}; known: {', '.join(PARAMETER_GROUPS)}"
        raise ValidationError(msg)
    module, params = PARAMETER_GROUPS[group]
    try:
        param = params[pname]
    except KeyError as err:
        known = ", ".join(p.name for p in params)
        msg = f"unknown parameter {pname!r} of {group}; known: {known}"
        raise ValidationError(msg) from err
    if (int(module), int(param)) in READ_ONLY:
        msg = f"{group}.{pname} is read-only on the DAVIS240C; read it with `mocaprig davis info`"
        raise ValidationError(msg)
    value_text = raw.strip().lower()
    if group == "BIAS" and "/" in value_text:
        coarse, _, fine = value_text.partition("/")
        base = _LIBCAER_DEFAULT[BiasParam(param)]
        if not isinstance(base, CoarseFineBias):
            msg = f"{group}.{pname} is a shifted-source bias; give its raw 16-bit value"
            raise ValidationError(msg)
        try:
            c_val, f_val = int(coarse), int(fine)
        except ValueError as err:
            msg = f"bias value {raw!r} of {group}.{pname} is not COARSE/FINE integers"
            raise ValidationError(msg) from err
        bias = replace(base, coarse=c_val, fine=f_val)
        return RegisterWrite(module, param, bias.encode())
    value: float
    if value_text in ("true", "false"):
        value = float(value_text == "true")
    else:
        try:
            value = float(int(value_text, 0))
        except ValueError:
            try:
                value = float(value_text)
            except ValueError as err:
                msg = f"value {raw!r} of {group}.{pname} is not a number"
                raise ValidationError(msg) from err
    if value < 0:
        msg = f"value {raw!r} of {group}.{pname} is negative"
        raise ValidationError(msg)
    return RegisterWrite(module, param, to_device_units(module, param, value, c))
