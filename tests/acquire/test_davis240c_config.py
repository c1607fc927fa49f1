"""DAVIS240C parameters, bias encoding, presets and the default-config sequence (note §3-§5)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mocaprig.acquire.davis240c_config import (
    BIAS_PRESETS,
    ApsParam,
    BiasCurrentLevel,
    BiasParam,
    BiasPreset,
    BiasSex,
    BiasType,
    ChipParam,
    CoarseFineBias,
    DavisSettings,
    DeviceClocks,
    ImuSettings,
    Module,
    RegisterWrite,
    ShiftedSourceBias,
    ShiftedSourceMode,
    ShiftedSourceVoltage,
    bias_set,
    default_config_writes,
    parse_setting,
    to_device_units,
)
from mocaprig.errors import ValidationError

#: The note's table of libcaer default DAVIS240 bias values (§4).
LIBCAER_DEFAULTS = {
    "DIFFBN": 0x427F,
    "ONBN": 0x5FFF,
    "OFFBN": 0x400F,
    "APSCASEPC": 0x5B9B,
    "DIFFCASBNC": 0x573B,
    "APSROSFBN": 0x6DBF,
    "LOCALBUFBN": 0x5A4F,
    "PIXINVBN": 0x690F,
    "PRBP": 0x23AD,
    "PRSFBP": 0x110D,
    "REFRBP": 0x419D,
    "AEPDBN": 0x65BF,
    "LCOLTIMEOUTBN": 0x531F,
    "AEPUXBP": 0x450D,
    "AEPUYBP": 0x798D,
    "IFTHRBN": 0x5FFF,
    "IFREFRBN": 0x5FFF,
    "PADFOLLBN": 0x7D7F,
    "APSOVERFLOWLEVELBN": 0x6FDF,
    "BIASBUFFER": 0x5FEF,
    "SSP": 0x8410,
    "SSN": 0x8410,
}


@pytest.mark.parametrize(("name", "value"), sorted(LIBCAER_DEFAULTS.items()))
def test_default_biases_encode_to_the_libcaer_values(name: str, value: int) -> None:
    assert bias_set()[BiasParam[name]].encode() == value


def test_sepia_diffbn_value_matches() -> None:
    assert bias_set()[BiasParam.DIFFBN].encode() == (1063 << 4) | 0xF


@given(
    coarse=st.integers(0, 7),
    fine=st.integers(0, 255),
    sex=st.sampled_from(BiasSex),
    kind=st.sampled_from(BiasType),
    level=st.sampled_from(BiasCurrentLevel),
    enabled=st.booleans(),
)
def test_coarse_fine_round_trip(
    coarse: int,
    fine: int,
    sex: BiasSex,
    kind: BiasType,
    level: BiasCurrentLevel,
    enabled: bool,
) -> None:
    b = CoarseFineBias(coarse, fine, sex, kind, level, enabled)
    assert 0 <= b.encode() < 0x8000
    assert CoarseFineBias.decode(b.encode()) == b


@given(
    ref=st.integers(0, 63),
    reg=st.integers(0, 63),
    mode=st.sampled_from(ShiftedSourceMode),
    level=st.sampled_from(ShiftedSourceVoltage),
)
def test_shifted_source_round_trip(
    ref: int, reg: int, mode: ShiftedSourceMode, level: ShiftedSourceVoltage
) -> None:
    b = ShiftedSourceBias(ref, reg, mode, level)
    assert ShiftedSourceBias.decode(b.encode()) == b


def test_bias_values_out_of_range_are_refused() -> None:
    with pytest.raises(ValidationError, match=r"coarse 0..7"):
        CoarseFineBias(8, 0)
    with pytest.raises(ValidationError, match=r"0..63"):
        ShiftedSourceBias(64, 0)


def test_coarse_current_scale() -> None:
    assert CoarseFineBias(7, 255).current_pa == pytest.approx(24.8e6)
    assert CoarseFineBias(4, 0).current_pa == 0.0


def test_presets_differ_only_where_their_sources_say() -> None:
    default, pyaer = bias_set(BiasPreset.DEFAULT), bias_set("pyaer")
    changed = {p.name for p in BiasParam if default[p] != pyaer[p]}
    assert changed == {"ONBN", "PIXINVBN", "PRSFBP"}
    assert pyaer[BiasParam.ONBN] == CoarseFineBias(6, 200)
    assert bias_set("legacy")[BiasParam.PIXINVBN] == CoarseFineBias(5, 129)
    assert set(BIAS_PRESETS) == {"default", "legacy", "pyaer"}
    assert len(default) == 22


def test_unknown_preset_lists_the_known_ones() -> None:
    with pytest.raises(ValidationError, match="default, legacy, pyaer"):
        bias_set("fast")


def test_default_config_sequence_matches_libcaer() -> None:
    writes = default_config_writes()
    as_tuples = [(int(w.module), int(w.param), w.value) for w in writes]
    # Biases first, in register order.
    assert [p for _, p, _ in as_tuples[:22]] == list(range(22))
    assert as_tuples[22:30] == [(5, p, 0) for p in range(128, 136)]
    tail = as_tuples[30:]
    assert tail[:5] == [(5, 136, 1), (5, 137, 0), (5, 138, 1), (5, 140, 0), (5, 141, 0)]
    assert (0, 4, 1) in tail
    assert (0, 5, 1) in tail
    # GLOBAL_SHUTTER: CHIP 142 before APS 7; exposure 4 ms and interval 40 ms in ADC cycles.
    assert tail.index((5, 142, 1)) < tail.index((2, 7, 1))
    assert (2, ApsParam.EXPOSURE, 120000) in tail
    assert (2, ApsParam.FRAME_INTERVAL, 1200000) in tail
    assert (2, 10, 239) in tail
    assert (2, 11, 179) in tail
    assert [t for t in tail if t[0] == 3] == [(3, 5, 0), (3, 6, 1), (3, 7, 1), (3, 10, 1)]
    assert [t for t in tail if t[0] == 4] == [
        (4, 1, 0),
        (4, 2, 0),
        (4, 3, 1),
        (4, 4, 1),
        (4, 5, 900),
    ]
    assert tail[-1] == (9, 1, 30000)
    # Registers libcaer refuses on the 240C are never written.
    assert not any(m == 5 and p in (139, 143, 144) for m, p, _ in as_tuples)


def test_settings_change_the_writes() -> None:
    s = DavisSettings.from_preset("pyaer", imu=ImuSettings(accel_full_scale=3))
    writes = {(int(w.module), int(w.param)): w.value for w in default_config_writes(s)}
    assert writes[(3, 7)] == 3
    assert writes[(5, BiasParam.ONBN)] == CoarseFineBias(6, 200).encode()
    assert ImuSettings(sample_rate_divider=1).rate_hz == 500.0


def test_host_units_convert_with_the_clocks() -> None:
    fx3 = DeviceClocks(logic_mhz=104, adc_mhz=104, usb_mhz=80, deviation_x1000=1008)
    assert to_device_units(Module.APS, ApsParam.EXPOSURE, 4000, DeviceClocks()) == 120000
    assert to_device_units(Module.USB, 1, 8, DeviceClocks()) == 30000
    assert to_device_units(Module.EXTINPUT, 5, 10, DeviceClocks()) == 900
    assert to_device_units(Module.APS, ApsParam.EXPOSURE, 1000, fx3) == round(1000 * 104 * 1.008)
    assert to_device_units(Module.MUX, 0, 1, DeviceClocks()) == 1


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("APS.EXPOSURE=8000", (2, 12, 240000)),
        ("aps.global_shutter=false", (2, 7, 0)),
        ("IMU.ACCEL_FULL_SCALE=0x2", (3, 7, 2)),
        ("BIAS.ONBN=6/200", (5, 1, CoarseFineBias(6, 200).encode())),
        ("BIAS.PRBP=2/58", (5, 8, 0x23AD)),
        ("BIAS.SSP=0x8410", (5, 20, 0x8410)),
        ("CHIP.GLOBAL_SHUTTER=1", (5, ChipParam.GLOBAL_SHUTTER, 1)),
        ("USB.EARLY_PACKET_DELAY=8", (9, 1, 30000)),
        ("EXTINPUT.DETECT_PULSE_LENGTH=10", (4, 5, 900)),
    ],
)
def test_parse_setting(text: str, expected: tuple[int, int, int]) -> None:
    w = parse_setting(text)
    assert (int(w.module), int(w.param), w.value) == expected


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("APS.EXPOSURE", "MODULE.PARAM=VALUE"),
        ("FOO.BAR=1", "unknown module 'FOO'"),
        ("APS.SHUTTER=1", "unknown parameter 'SHUTTER' of APS; known: SIZE_COLUMNS"),
        ("SYSINFO.LOGIC_VERSION=18", "read-only"),
        ("APS.EXPOSURE=soon", "not a number"),
        ("APS.EXPOSURE=-5", "negative"),
        ("BIAS.SSN=1/2", "shifted-source"),
        ("BIAS.ONBN=9/2", "coarse 0..7"),
    ],
)
def test_parse_setting_errors_say_what_is_wrong(text: str, match: str) -> None:
    with pytest.raises(ValidationError, match=match):
        parse_setting(text)


def test_register_write_is_checked() -> None:
    with pytest.raises(ValidationError, match="uint32"):
        RegisterWrite(0, 0, 1 << 32)
    with pytest.raises(ValidationError, match="outside module"):
        RegisterWrite(200, 0, 0)
