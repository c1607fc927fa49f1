"""The DAVIS240C word-stream decoder on hand-built streams (note §6.5 worked encodings)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mocaprig.acquire.davis240c_decode import (
    IMU_SAMPLE_DTYPE,
    SPECIAL_DTYPE,
    DavisDecoder,
    DavisPacket,
    SpecialType,
    decode_words,
)
from mocaprig.acquire.events import EVENT_DTYPE


def raw(*words: int) -> bytes:
    """Words -> bytes on the wire (little-endian)."""
    return np.array(words, dtype="<u2").tobytes()


def events_of(pkt: DavisPacket) -> list[tuple[int, int, int, int]]:
    return [(int(e["t"]), int(e["x"]), int(e["y"]), int(e["p"])) for e in pkt.events]


def specials_of(pkt: DavisPacket) -> list[tuple[int, int]]:
    return [(int(s["t"]), int(s["type"])) for s in pkt.specials]


def merge(packets: list[DavisPacket]) -> DavisPacket:
    return DavisPacket(
        events=np.concatenate([p.events for p in packets]),
        frames=tuple(f for p in packets for f in p.frames),
        imu=np.concatenate([p.imu for p in packets]),
        specials=np.concatenate([p.specials for p in packets]),
    )


# -- worked encodings (§6.5) and timestamps (§7) --------------------------------------------------


def test_worked_encodings_decode_to_their_meaning() -> None:
    # ts 291, row 17, column 200 OFF then ON.
    pkt = decode_words(raw(0x8123, 0x1011, 0x20C8, 0x30C8))
    assert pkt.events.dtype == EVENT_DTYPE
    assert events_of(pkt) == [(291, 200, 17, 0), (291, 200, 17, 1)]


def test_bytes_on_the_wire_are_little_endian() -> None:
    pkt = decode_words(bytes([0x23, 0x81, 0x11, 0x10, 0xC8, 0x30]))
    assert events_of(pkt) == [(291, 200, 17, 1)]


def test_x_words_inherit_the_time_and_row_until_the_next_ones() -> None:
    pkt = decode_words(raw(0x8010, 0x1005, 0x3001, 0x3002, 0x8011, 0x1006, 0x2003, 0x2004))
    assert events_of(pkt) == [(16, 1, 5, 1), (16, 2, 5, 1), (17, 3, 6, 0), (17, 4, 6, 0)]


def test_a_wrap_starts_a_new_epoch_at_zero() -> None:
    # 0xFFFF = highest timestamp, then wrap x1: events without a timestamp word are at 32768.
    pkt = decode_words(raw(0xFFFF, 0x1001, 0x3000, 0x7001, 0x1002, 0x3001, 0x8005, 0x1003, 0x3002))
    assert [e[0] for e in events_of(pkt)] == [32767, 32768, 32773]


def test_a_wrap_word_adds_its_count_of_epochs() -> None:
    pkt = decode_words(raw(0x7003, 0x8001, 0x1000, 0x3000))
    assert events_of(pkt) == [(3 * 32768 + 1, 0, 0, 1)]


def test_big_wrap_is_continuous_in_64_bit_and_exported_as_a_special() -> None:
    # 16 x 4095 + 16 wraps = 65536 wraps = 2^31 µs.
    words = [0x8100, 0x1001, 0x3001] + [0x7FFF] * 16 + [0x7010, 0x8007, 0x1002, 0x3002]
    dec = DavisDecoder()
    pkt = dec.decode(raw(*words))
    assert events_of(pkt) == [(256, 1, 1, 1), ((1 << 31) + 7, 2, 2, 1)]
    assert specials_of(pkt) == [((1 << 31) - 1, SpecialType.TIMESTAMP_WRAP)]
    assert dec.stats.big_wraps == 1
    assert dec.time_us == (1 << 31) + 7


def test_timestamp_reset_restarts_time_and_is_exported() -> None:
    dec = DavisDecoder()
    pkt = dec.decode(raw(0x7002, 0x8100, 0x1001, 0x3001, 0x0001, 0x8003, 0x1002, 0x2002))
    assert events_of(pkt) == [(2 * 32768 + 256, 1, 1, 1), (3, 2, 2, 0)]
    assert specials_of(pkt) == [(0, SpecialType.TIMESTAMP_RESET)]
    assert dec.stats.timestamp_resets == 1


def test_non_monotonic_timestamps_are_counted_but_used() -> None:
    dec = DavisDecoder()
    pkt = dec.decode(raw(0x8010, 0x1001, 0x3001, 0x8008, 0x1001, 0x3002))
    assert [e[0] for e in events_of(pkt)] == [16, 8]
    assert dec.stats.non_monotonic_timestamps == 1


def test_external_input_and_generator_specials_use_libcaer_numbers() -> None:
    pkt = decode_words(raw(0x8010, 0x0003, 0x8011, 0x0002, 0x8012, 0x0004, 0x0011, 0x0010))
    assert specials_of(pkt) == [
        (16, SpecialType.EXTERNAL_INPUT_RISING_EDGE),  # device 3 -> libcaer 2
        (17, SpecialType.EXTERNAL_INPUT_FALLING_EDGE),  # device 2 -> libcaer 3
        (18, SpecialType.EXTERNAL_INPUT_PULSE),
        (18, SpecialType.EXTERNAL_GENERATOR_RISING_EDGE),
        (18, SpecialType.EXTERNAL_GENERATOR_FALLING_EDGE),
    ]
    assert pkt.specials.dtype == SPECIAL_DTYPE


# -- malformed DVS words --------------------------------------------------------------------------


def test_x_before_any_row_is_dropped_and_counted() -> None:
    dec = DavisDecoder()
    pkt = dec.decode(raw(0x8010, 0x3005, 0x1002, 0x3006))
    assert events_of(pkt) == [(16, 6, 2, 1)]
    assert dec.stats.x_without_row == 1
    assert dec.stats.skipped_words == 1


def test_out_of_range_addresses_are_skipped_and_the_last_row_kept() -> None:
    dec = DavisDecoder()
    pkt = dec.decode(raw(0x1002, 0x3001, 0x10B4, 0x3002, 0x30F0))  # row 180, column 240
    assert events_of(pkt) == [(0, 1, 2, 1), (0, 2, 2, 1)]
    assert dec.stats.y_out_of_range == 1
    assert dec.stats.x_out_of_range == 1


def test_a_row_followed_by_a_row_keeps_the_latest() -> None:
    pkt = decode_words(raw(0x1001, 0x1002, 0x3003))
    assert events_of(pkt) == [(0, 3, 2, 1)]


# -- state across packets -------------------------------------------------------------------------


def test_odd_trailing_byte_is_kept_for_the_next_packet() -> None:
    data = raw(0x8123, 0x1011, 0x20C8)
    dec = DavisDecoder()
    a = dec.decode(data[:3])
    b = dec.decode(data[3:])
    assert events_of(a) == []
    assert events_of(b) == [(291, 200, 17, 0)]
    assert dec.stats.odd_trailing_bytes == 1
    assert dec.stats.bytes_in == len(data)


def test_time_and_row_carry_over_packet_boundaries() -> None:
    dec = DavisDecoder()
    dec.decode(raw(0x7001, 0x8010, 0x1009))
    pkt = dec.decode(raw(0x3004))
    assert events_of(pkt) == [(32768 + 16, 4, 9, 1)]


def test_decode_accepts_a_uint16_array_and_leaves_it_untouched() -> None:
    w = np.array([0x8123, 0x1011, 0x20C8], dtype="<u2")
    before = w.copy()
    pkt = DavisDecoder().decode(w)
    assert events_of(pkt) == [(291, 200, 17, 0)]
    np.testing.assert_array_equal(w, before)


# -- APS frames (§9) ------------------------------------------------------------------------------

ROI = (10, 20, 12, 22)  # start column, start row, end column, end row: 3 x 3 pixels
RESET_RAW = np.array([[500, 500, 150], [500, 1000, 500], [500, 500, 500]])  # [column, row]
SIGNAL_RAW = np.array([[100, 600, 100], [0, 100, 250], [500, 499, 1]])


def frame_words(*, signal_columns: int = 3, start: int = 0x0008) -> list[int]:
    w = [0x8064, start, 0x60C0, 0x6075, 0x6000]  # ts 100, frame start, exposure 120000 cycles
    for v in ROI:
        w += [0x5100 | (v >> 8), 0x5200 | (v & 0xFF)]
    for c in range(3):
        w += [0x000B, *(0x4000 | int(v) for v in RESET_RAW[c]), 0x000D]
    w += [0x80C8, 0x000E, 0x9068, 0x000F]  # exposure start at 200, end at 4200
    for c in range(signal_columns):
        w += [0x000C, *(0x4000 | int(v) for v in SIGNAL_RAW[c]), 0x000D]
    w += [0x9388, 0x000A]  # frame end at 5000
    return w


def expected_pixels() -> np.ndarray:
    rst, sig = 2 * RESET_RAW, 2 * SIGNAL_RAW
    pix = np.clip(rst - sig, 0, 1023)
    pix[(rst < 384) | (sig == 0)] = 1023
    out: np.ndarray = pix.T  # [row, column]
    return out


def test_aps_frame_is_reassembled_with_cds_doubling_clamp_and_saturation() -> None:
    dec = DavisDecoder()
    pkt = dec.decode(raw(*frame_words()))
    assert len(pkt.frames) == 1
    f = pkt.frames[0]
    assert (f.t_start_frame_us, f.t_start_exposure_us, f.t_end_exposure_us) == (100, 200, 4200)
    assert f.t_end_frame_us == 5000
    assert f.t_us == 2200
    assert f.exposure_cycles == 120000
    assert (f.position_x, f.position_y) == (10, 20)
    assert f.global_shutter
    assert f.pixels.dtype == np.uint16
    np.testing.assert_array_equal(f.pixels, expected_pixels())
    np.testing.assert_array_equal(f.pixels_16bit, expected_pixels() << 6)
    assert specials_of(pkt) == [
        (100, SpecialType.APS_FRAME_START),
        (200, SpecialType.APS_EXPOSURE_START),
        (4200, SpecialType.APS_EXPOSURE_END),
        (5000, SpecialType.APS_FRAME_END),
    ]
    assert dec.stats.frames == 1
    assert dec.stats.skipped_words == 0


def test_a_frame_with_a_missing_column_is_dropped() -> None:
    dec = DavisDecoder()
    pkt = dec.decode(raw(*frame_words(signal_columns=2)))
    assert pkt.frames == ()
    assert dec.stats.frames_dropped == 1


def test_a_rolling_shutter_frame_start_is_flagged() -> None:
    pkt = decode_words(raw(*frame_words(start=0x0009)))
    assert not pkt.frames[0].global_shutter


def test_aps_words_before_the_first_frame_start_are_ignored() -> None:
    dec = DavisDecoder()
    tail = frame_words()[12:]  # from the middle of the reset read
    pkt = dec.decode(raw(*tail))
    assert pkt.frames == ()
    assert dec.stats.aps_words_skipped > 0
    assert dec.decode(raw(*frame_words())).frames  # the next full frame decodes


def test_a_frame_split_over_one_byte_packets_decodes_the_same() -> None:
    data = raw(*frame_words())
    dec = DavisDecoder()
    got = merge([dec.decode(data[i : i + 1]) for i in range(len(data))])
    np.testing.assert_array_equal(got.frames[0].pixels, expected_pixels())


def test_a_timestamp_reset_inside_a_frame_drops_it_and_waits_for_the_next_start() -> None:
    w = frame_words()
    dec = DavisDecoder()
    pkt = dec.decode(raw(*w[:20], 0x0001, *w[20:]))
    assert pkt.frames == ()
    assert dec.stats.frames_dropped == 1
    assert dec.stats.aps_words_skipped > 0


# -- IMU (§10) ------------------------------------------------------------------------------------


def imu_words(*, accel=(8192, -8192, 0), temp=-1700, gyro=(6554, 0, -655), info=0xE5) -> list[int]:
    regs = [*accel, temp, *gyro]
    data = b"".join(int(v).to_bytes(2, "big", signed=True) for v in regs)
    return [0x8010, 0x0005, 0x5300 | info, *(0x5000 | b for b in data), 0x8020, 0x0007]


def test_imu_sample_in_g_dps_and_celsius_at_the_end_word() -> None:
    dec = DavisDecoder()
    pkt = dec.decode(raw(*imu_words()))
    assert pkt.imu.dtype == IMU_SAMPLE_DTYPE
    assert pkt.imu.size == 1
    s = pkt.imu[0]
    assert s["t"] == 32  # timestamped at the IMU-end word
    np.testing.assert_allclose(s["accel_g"], [1.0, -1.0, 0.0])  # ±4 g: 8192 LSB/g
    np.testing.assert_allclose(s["gyro_dps"], [6554 / 65.536, 0.0, -655 / 65.536])
    assert s["temp_c"] == pytest.approx(-1700 / 340 + 35)


def test_imu_full_scale_codes_from_the_info_word() -> None:
    # info 0xEF: all sensors, accel code 3 (2048 LSB/g), gyro code 3 (16.384 LSB/(°/s)).
    pkt = decode_words(raw(*imu_words(accel=(2048, 0, 0), gyro=(16384, 0, 0), info=0xEF)))
    assert pkt.imu[0]["accel_g"][0] == pytest.approx(1.0)
    assert pkt.imu[0]["gyro_dps"][0] == pytest.approx(1000.0)


def test_imu_with_only_the_gyroscope_on_fills_the_gyro() -> None:
    data = b"".join(v.to_bytes(2, "big", signed=True) for v in (655, 0, 0))
    words = [0x0005, 0x5300 | 0x45, *(0x5000 | b for b in data), 0x0007]
    pkt = decode_words(raw(*words))
    assert pkt.imu[0]["gyro_dps"][0] == pytest.approx(655 / 65.536)
    assert pkt.imu[0]["accel_g"].tolist() == [0.0, 0.0, 0.0]


def test_an_incomplete_imu_sample_is_dropped_and_counted() -> None:
    w = imu_words()
    dec = DavisDecoder()
    pkt = dec.decode(raw(*w[:8], *w[-2:]))
    assert pkt.imu.size == 0
    assert dec.stats.imu_samples_dropped == 1


def test_imu_flip_negates_accel_and_gyro_axes() -> None:
    pkt = DavisDecoder(imu_flip=(True, False, False)).decode(raw(*imu_words()))
    assert pkt.imu[0]["accel_g"][0] == pytest.approx(-1.0)
    assert pkt.imu[0]["gyro_dps"][0] == pytest.approx(-6554 / 65.536)


def test_imu_data_after_a_reset_waits_for_the_next_imu_start() -> None:
    w = imu_words()
    dec = DavisDecoder()
    pkt = dec.decode(raw(*w[:6], 0x0001, *w[6:], *w))
    assert pkt.imu.size == 1
    assert dec.stats.imu_words_skipped > 0


def test_a_gap_drops_the_partial_frame_and_waits_for_the_next_start() -> None:
    w = frame_words()
    dec = DavisDecoder()
    dec.decode(raw(*w[:30]))
    dec.decode_gap()  # the driver lost bytes here
    assert dec.decode(raw(*w[30:])).frames == ()
    assert dec.stats.gaps == 1
    assert dec.stats.frames_dropped == 1
    assert len(dec.decode(raw(*w)).frames) == 1


def test_unknown_specials_and_misc_words_are_counted() -> None:
    dec = DavisDecoder()
    dec.decode(raw(0x0000, 0x0006, 0x0FFF, 0x5F00, 0x6C00))
    assert dec.stats.unknown_words == 5


# -- properties -----------------------------------------------------------------------------------


def mixed_stream() -> bytes:
    dvs = [0x8010, 0x1001, 0x3001, 0x2002, 0x7001, 0x1002, 0x3003, 0x8020, 0x1003, 0x20EF]
    return raw(*dvs, *frame_words(), *imu_words(), 0x0004, *dvs, 0x0001, *dvs, *frame_words())


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cuts=st.lists(st.integers(min_value=0, max_value=len(mixed_stream())), max_size=12))
def test_any_packet_split_decodes_like_the_whole_stream(cuts: list[int]) -> None:
    data = mixed_stream()
    whole = DavisDecoder().decode(data)
    dec = DavisDecoder()
    bounds = [0, *sorted(cuts), len(data)]
    got = merge([dec.decode(data[a:b]) for a, b in itertools.pairwise(bounds)])
    np.testing.assert_array_equal(got.events, whole.events)
    np.testing.assert_array_equal(got.specials, whole.specials)
    np.testing.assert_array_equal(got.imu, whole.imu)
    assert len(got.frames) == len(whole.frames) == 2
    for a, b in zip(got.frames, whole.frames, strict=True):
        np.testing.assert_array_equal(a.pixels, b.pixels)


@settings(max_examples=150, deadline=None)
@given(data=st.lists(st.binary(max_size=300), max_size=6))
def test_random_bytes_never_crash_and_every_word_is_accounted(data: list[bytes]) -> None:
    dec = DavisDecoder()
    n_events = 0
    for chunk in data:
        pkt = dec.decode(chunk)
        n_events += pkt.events.size
        assert pkt.events.dtype == EVENT_DTYPE
        assert (pkt.events["x"] < 240).all()
        assert (pkt.events["y"] < 180).all()
    s = dec.stats
    assert s.bytes_in == sum(len(c) for c in data)
    assert s.words == s.bytes_in // 2
    assert s.events == n_events


_WORDS = st.one_of(
    st.integers(0x8000, 0xFFFF),  # timestamps
    st.integers(0x1000, 0x10C0),  # rows (some out of range)
    st.integers(0x2000, 0x3100),  # columns (some out of range)
    st.integers(0x0000, 0x0013),  # specials incl. resets, frame and IMU markers
    st.integers(0x4000, 0x43FF),  # ADC
    st.integers(0x5000, 0x53FF),  # MISC8
    st.integers(0x6000, 0x6FFF),  # MISC10
    st.integers(0x7000, 0x7FFF),  # wraps
)


@settings(max_examples=150, deadline=None)
@given(words=st.lists(_WORDS, max_size=400))
def test_random_structured_words_never_crash(words: list[int]) -> None:
    dec = DavisDecoder()
    pkt = dec.decode(raw(*words))
    assert dec.stats.words == len(words)
    assert dec.stats.events == pkt.events.size
    for f in pkt.frames:
        assert f.pixels.max(initial=0) <= 1023
