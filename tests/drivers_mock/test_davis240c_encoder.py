"""The DAVIS240C word encoder against davis240c-usb.md (§6.5 worked encodings, §7.1 rules).

``host_decode`` below is a small, deliberately plain re-statement of libcaer's host algorithm
(note §7.2, §9.2, §10) used as the oracle; it is independent of ``acquire`` and of the encoder.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mocaprig.acquire.events import make_events
from mocaprig.drivers_mock.davis240c_encoder import (
    TIMESTAMP_WRAP_US,
    DavisWordEncoder,
    EncoderConfig,
    encode_stream,
)
from mocaprig.drivers_mock.davis_activity import (
    EXT_INPUT_DTYPE,
    IMU_DTYPE,
    ApsExposure,
    DavisActivity,
    ExtInputEdge,
    empty_activity,
)
from mocaprig.errors import ValidationError

INT32_MAX = 2**31 - 1


@dataclass
class HostFrame:
    """An APS frame as the host assembles it (raw samples already doubled, §9.2)."""

    start: int
    exp: list[int] = field(default_factory=list)  # MISC10 exposure slices
    roi: list[int] = field(default_factory=list)  # MISC8 ROI bytes
    reset: list[list[int]] = field(default_factory=list)  # per column, per row
    signal: list[list[int]] = field(default_factory=list)
    exp_start: int = -1
    exp_end: int = -1
    end: int = -1
    reading_reset: bool = True

    @property
    def exposure_cycles(self) -> int:
        return sum(v << (10 * i) for i, v in enumerate(self.exp))

    def cds(self) -> npt.NDArray[np.int64]:
        """libcaer's CDS (§9.2): reset − signal, white on saturation, clamped to 0..1023."""
        reset = np.array(self.reset, np.int64).T
        signal = np.array(self.signal, np.int64).T
        img: npt.NDArray[np.int64] = np.clip(reset - signal, 0, 1023)
        img[(reset < 384) | (signal == 0)] = 1023
        return img


@dataclass
class HostView:
    """What a libcaer-like host makes of a word stream (times are 64-bit µs)."""

    events: list[tuple[int, int, int, int]] = field(default_factory=list)  # t, x, y, p
    specials: list[tuple[int, int]] = field(default_factory=list)  # t, device code
    frames: list[HostFrame] = field(default_factory=list)
    imu: list[tuple[int, list[int], int]] = field(default_factory=list)  # t, raw values, info
    resets: int = 0


def host_decode(data: bytes) -> HostView:
    """Decode per note §7.2 (timestamps), §8 (DVS), §9.2 (APS, ×2 and CDS), §10 (IMU)."""
    words: list[int] = np.frombuffer(data[: len(data) // 2 * 2], "<u2").tolist()
    view = HostView()
    wrap_add = current = overflow = 0
    row: int | None = None
    frame: HostFrame | None = None
    imu_bytes: list[int] | None = None
    imu_info = 0

    for w in words:
        now = (overflow << 31) | current
        if w & 0x8000:
            current = wrap_add + (w & 0x7FFF)
            continue
        code, data12 = (w >> 12) & 7, w & 0xFFF
        if code == 7:
            total = wrap_add + 0x8000 * data12
            if total > INT32_MAX:
                overflow += 1
                total -= 2**31
            wrap_add = current = total
        elif code == 0 and data12 == 1:
            wrap_add = current = overflow = 0
            view.resets += 1
            frame = imu_bytes = None
        elif code == 0:
            view.specials.append((now, data12))
            if data12 == 8:
                frame = HostFrame(start=now)
            elif data12 == 5:
                imu_bytes = []
            elif data12 == 7 and imu_bytes is not None:
                vals: list[int] = np.frombuffer(bytes(imu_bytes), ">i2").tolist()
                view.imu.append((now, vals, imu_info))
                imu_bytes = None
            elif frame is not None:
                if data12 in (11, 12):
                    frame.reading_reset = data12 == 11
                    (frame.reset if frame.reading_reset else frame.signal).append([])
                elif data12 == 14:
                    frame.exp_start = now
                elif data12 == 15:
                    frame.exp_end = now
                elif data12 == 10:
                    frame.end = now
                    view.frames.append(frame)
                    frame = None
        elif code == 1:
            row = data12
        elif code in (2, 3):
            assert row is not None, "X word without a row"
            view.events.append((now, data12, row, code & 1))
        elif code == 4 and frame is not None:
            (frame.reset if frame.reading_reset else frame.signal)[-1].append((data12 & 0x3FF) * 2)
        elif code == 5:
            sub, byte = (data12 >> 8) & 0xF, data12 & 0xFF
            if sub == 0 and imu_bytes is not None:
                imu_bytes.append(byte)
            elif sub == 3:
                imu_info = byte
            elif sub in (1, 2) and frame is not None:
                frame.roi.append(byte)
        elif code == 6 and frame is not None:
            frame.exp.append(data12 & 0x3FF)
    return view


def words_of(data: bytes) -> list[int]:
    out: list[int] = np.frombuffer(data, "<u2").tolist()
    return out


def window(t0: int, t1: int, events=None, **kw) -> DavisActivity:
    if events is None:
        events = make_events([], [], [], [])
    return DavisActivity(t0_us=t0, t1_us=t1, events=events, **kw)


# -- §6.5 worked encodings -------------------------------------------------------------------------


def test_worked_dvs_encodings_match_the_note():
    ev = make_events([291, 291], [200, 200], [17, 17], [0, 1])
    data = encode_stream([window(0, 1000, ev)])
    assert data == bytes.fromhex("23811110c820c830")


def test_worked_wrap_encoding_is_0x7001():
    data = encode_stream([empty_activity(0, TIMESTAMP_WRAP_US + 1)])
    assert data == bytes.fromhex("0170")


def test_worked_timestamp_reset_encoding_is_0x0001():
    enc = DavisWordEncoder(latency_us=0)
    enc.encode(empty_activity(0, 100))
    assert enc.reset_timestamps() == bytes.fromhex("0100")


def test_worked_aps_encodings_match_the_note():
    # Exposure 4000 µs = 120000 ADC cycles → 0x60C0 0x6075 0x6000; ROI end column 239 →
    # 0x5100 0x52EF; a signal sample of 512 → 0x4200 (reset 600, cds 176 → 600 − 88 = 512).
    cfg = EncoderConfig(reset_level_adc=600.0, reset_noise_adc=0.0)
    cds = np.full((180, 240), 176.0)
    exp = ApsExposure(20_000, 24_000, cds)
    w = words_of(encode_stream([window(0, 30_000, exposures=(exp,))], config=cfg))
    start = w.index(0x0008)
    assert w[start + 1 : start + 4] == [0x60C0, 0x6075, 0x6000]
    roi = w[start + 4 : start + 12]
    assert roi == [0x5100, 0x5200, 0x5100, 0x5200, 0x5100, 0x52EF, 0x5100, 0x52B3]
    assert 0x4200 in w
    assert 0x4258 in w


def test_worked_imu_info_word_all_sensors_4g_500dps():
    imu = np.zeros(1, IMU_DTYPE)
    imu["t"] = 500
    w = words_of(encode_stream([window(0, 1000, imu=imu)]))
    assert w[:3] == [0x81F4, 0x0005, 0x53E5]
    assert w[-1] == 0x0007


# -- §7.1 timestamp rules --------------------------------------------------------------------------


def test_hand_derived_stream_groups_rows_and_stamps_only_changes():
    ev = make_events([291, 291, 291, 300], [200, 5, 200, 7], [17, 17, 3, 17], [0, 1, 1, 1])
    w = words_of(encode_stream([window(0, 1000, ev)]))
    assert w == [0x8123, 0x1003, 0x30C8, 0x1011, 0x20C8, 0x3005, 0x812C, 0x1011, 0x3007]


def test_no_zero_timestamp_word_at_time_zero_or_after_a_wrap():
    ev = make_events([0, TIMESTAMP_WRAP_US], [1, 2], [3, 4], [1, 0])
    w = words_of(encode_stream([window(0, 40_000, ev)]))
    assert w == [0x1003, 0x3001, 0x7001, 0x1004, 0x2002]
    assert 0x8000 not in w


def test_idle_stream_is_one_wrap_word_every_32768_us():
    w = words_of(encode_stream([empty_activity(0, 10 * TIMESTAMP_WRAP_US + 5)]))
    assert w == [0x7001] * 10


def test_highest_timestamp_then_wrap_then_new_epoch():
    ev = make_events([32767, 32768, 32769], [1, 2, 3], [5, 5, 5], [1, 1, 1])
    w = words_of(encode_stream([window(0, 40_000, ev)]))
    assert w == [0xFFFF, 0x1005, 0x3001, 0x7001, 0x1005, 0x3002, 0x8001, 0x1005, 0x3003]


def test_wrap_race_stamps_0xffff_before_the_wrap():
    ev = make_events([100, 32768], [1, 2], [5, 6], [1, 1])
    w = words_of(encode_stream([window(0, 40_000, ev)], wrap_race=True))
    assert w == [0x8064, 0x1005, 0x3001, 0xFFFF, 0x1006, 0x3002, 0x7001]
    host = host_decode(bytes(np.array(w, "<u2")))
    assert host.events[1][0] == 32767  # reported at the very end of the old epoch


def test_wrap_race_sends_no_second_0xffff():
    ev = make_events([32767, 32768], [1, 2], [5, 6], [1, 1])
    w = words_of(encode_stream([window(0, 40_000, ev)], wrap_race=True))
    assert w == [0xFFFF, 0x1005, 0x3001, 0x1006, 0x3002, 0x7001]


def test_timestamp_words_precede_only_row_and_special_words():
    rng = np.random.default_rng(3)
    n = 5000
    t = np.sort(rng.integers(0, 200_000, n))
    ev = make_events(t, rng.integers(0, 240, n), rng.integers(0, 180, n), rng.integers(0, 2, n))
    imu = np.zeros(20, IMU_DTYPE)
    imu["t"] = np.arange(20) * 9000 + 7
    ext = np.zeros(4, EXT_INPUT_DTYPE)
    ext["t"] = [1000, 1050, 90_000, 90_050]
    ext["edge"] = [ExtInputEdge.RISING, ExtInputEdge.FALLING] * 2
    exp = ApsExposure(60_000, 64_000, rng.uniform(0, 1023, (180, 240)))
    windows = [
        window(
            k * 10_000,
            (k + 1) * 10_000,
            ev[(t >= k * 10_000) & (t < (k + 1) * 10_000)],
            imu=imu[(imu["t"] >= k * 10_000) & (imu["t"] < (k + 1) * 10_000)],
            ext_input=ext[(ext["t"] >= k * 10_000) & (ext["t"] < (k + 1) * 10_000)],
            exposures=(exp,) if k == 6 else (),
        )
        for k in range(20)
    ]
    w = np.array(words_of(encode_stream(windows)))
    ts = np.flatnonzero(w & 0x8000)
    follower = w[ts + 1] >> 12
    assert set(follower.tolist()) <= {0, 1}  # SPECIAL or Y
    assert not np.any(w == 0x8000)
    host = host_decode(w.astype("<u2").tobytes())
    got = sorted(host.events)
    want = sorted(
        zip(t.tolist(), ev["x"].tolist(), ev["y"].tolist(), ev["p"].tolist(), strict=True)
    )
    assert got == want
    times = [e[0] for e in host.events]
    assert times == sorted(times)


def test_big_wrap_after_2_31_us_is_carried_by_wraps_only():
    t_event = 2**31 + 5
    ev = make_events([t_event], [9], [8], [1])
    n_wraps = t_event // TIMESTAMP_WRAP_US
    data = encode_stream([window(0, t_event + 10, ev)])
    w = words_of(data)
    assert w[:n_wraps] == [0x7001] * n_wraps
    host = host_decode(data)
    assert host.events == [(t_event, 9, 8, 1)]


def test_forced_reset_after_4096_pending_wraps():
    enc = DavisWordEncoder(latency_us=0)
    stall_end = 4096 * TIMESTAMP_WRAP_US + 1000
    assert enc.encode(empty_activity(0, stall_end), output_blocked=True) == b""
    assert enc.forced_resets == 1
    ev = make_events([stall_end + 500], [3], [4], [0])
    w = words_of(enc.encode(window(stall_end, stall_end + 2000, ev)))
    # Reset word alone first; the host then counts from the reset instant (4096 wraps in).
    assert w == [0x0001, 0x8000 | 1500, 0x1004, 0x2003]


def test_windows_must_be_consecutive():
    enc = DavisWordEncoder()
    enc.encode(empty_activity(0, 1000))
    with pytest.raises(ValidationError, match="consecutive"):
        enc.encode(empty_activity(500, 2000))


@pytest.mark.parametrize(
    ("t", "x", "y"),
    [([5, 3], [1, 1], [1, 1]), ([1000], [1], [1]), ([5], [240], [1]), ([5], [1], [180])],
)
def test_events_must_be_sorted_in_window_and_on_sensor(t, x, y):
    ev = make_events(t, x, y, [1] * len(t))
    with pytest.raises(ValidationError, match="DavisActivity events"):
        DavisWordEncoder().encode(window(0, 1000, ev))


def test_output_is_independent_of_window_split():
    rng = np.random.default_rng(5)
    t = np.sort(rng.integers(0, 100_000, 3000))
    ev = make_events(t, rng.integers(0, 240, t.size), rng.integers(0, 180, t.size), t % 2)
    one = encode_stream([window(0, 100_000, ev)])
    edges = [0, 777, 5000, 33_000, 65_536, 65_537, 99_999, 100_000]
    many = encode_stream(
        [window(a, b, ev[(t >= a) & (t < b)]) for a, b in itertools.pairwise(edges)]
    )
    assert one == many


# -- APS, IMU, external input ----------------------------------------------------------------------


def test_aps_frame_round_trips_cds_exposure_times_and_roi():
    rng = np.random.default_rng(1)
    cds = rng.uniform(0, 1000, (180, 240))
    cds[10, 20] = 1023.0  # saturated → the signal sample is 0 → white
    exp = ApsExposure(30_000, 34_000, cds)
    host = host_decode(encode_stream([window(0, 40_000, exposures=(exp,))]))
    (frame,) = host.frames
    assert frame.exp_start == 30_000
    assert frame.exp_end == 34_000
    assert frame.start < 30_000 < 34_000 < frame.end
    assert np.array(frame.reset).shape == (240, 180)
    img = frame.cds()
    expected = np.clip(2 * np.rint(cds / 2), 0, 1023)
    expected[10, 20] = 1023
    np.testing.assert_array_equal(img, expected)
    assert np.all(np.array(frame.reset) >= 384)  # never white by a low reset (§12.5)
    assert frame.exposure_cycles == 4000 * 30


def test_aps_roi_limits_columns_and_rows():
    cfg = EncoderConfig(roi=(10, 20, 19, 49))
    exp = ApsExposure(5000, 6000, np.full((180, 240), 300.0))
    host = host_decode(encode_stream([window(0, 8000, exposures=(exp,))], config=cfg))
    (frame,) = host.frames
    assert frame.roi == [0, 10, 0, 20, 0, 19, 0, 49]
    assert np.array(frame.signal).shape == (10, 30)


def test_imu_sample_big_endian_in_register_order():
    imu = np.zeros(1, IMU_DTYPE)
    imu["t"] = 700
    imu["accel_g"] = [1.0, 0.0, -1.0]
    imu["gyro_dps"] = [100.0, -250.0, 0.5]
    imu["temp_c"] = 36.0
    w = words_of(encode_stream([window(0, 1000, imu=imu)]))
    data = [x & 0xFF for x in w[3:-1]]
    assert [x >> 8 for x in w[3:-1]] == [0x50] * 14
    assert data[:6] == [0x20, 0x00, 0x00, 0x00, 0xE0, 0x00]  # ±4 g: 8192 LSB/g
    assert data[6:8] == [0x01, 0x54]  # (36 − 35) · 340 = 340
    host = host_decode(encode_stream([window(0, 1000, imu=imu)]))
    ((t, vals, info),) = host.imu
    assert t == 700
    assert info == 0xE5
    assert vals[4:] == [round(100 * 65.536), round(-250 * 65.536), round(0.5 * 65.536)]


def test_imu_sensors_off_are_left_out():
    imu = np.zeros(2, IMU_DTYPE)
    imu["t"] = [100, 200]
    cfg = EncoderConfig(run_accelerometer=False, run_temperature=False)
    host = host_decode(encode_stream([window(0, 1000, imu=imu)], config=cfg))
    assert [len(v) for _, v, _ in host.imu] == [3, 3]
    assert host.imu[0][2] == 0x45  # gyro only, ±4 g, ±500 °/s


@pytest.mark.parametrize(
    ("cfg", "expected"),
    [
        (EncoderConfig(), [(1050, 4)]),
        (EncoderConfig(detect_rising_edges=True, detect_pulses=False), [(1000, 3)]),
        (EncoderConfig(detect_falling_edges=True, detect_pulses=False), [(1050, 2)]),
        (EncoderConfig(pulse_min_length_us=60), []),
        (EncoderConfig(pulse_active_high=False), []),
    ],
)
def test_ext_input_detector(cfg, expected):
    ext = np.zeros(2, EXT_INPUT_DTYPE)
    ext["t"] = [1000, 1050]
    ext["edge"] = [ExtInputEdge.RISING, ExtInputEdge.FALLING]
    host = host_decode(encode_stream([window(0, 2000, ext_input=ext)], config=cfg))
    assert host.specials == expected


def test_ext_input_pulse_reported_by_the_source():
    ext = np.zeros(1, EXT_INPUT_DTYPE)
    ext["t"] = 1234
    ext["edge"] = ExtInputEdge.PULSE
    w = words_of(encode_stream([window(0, 2000, ext_input=ext)]))
    assert w == [0x8000 | 1234, 0x0004]


def test_ext_input_pulse_spanning_windows():
    ext = np.zeros(2, EXT_INPUT_DTYPE)
    ext["t"] = [990, 1040]
    ext["edge"] = [ExtInputEdge.RISING, ExtInputEdge.FALLING]
    host = host_decode(
        encode_stream([window(0, 1000, ext_input=ext[:1]), window(1000, 2000, ext_input=ext[1:])])
    )
    assert host.specials == [(1040, 4)]


# -- stalls, bandwidth ---------------------------------------------------------------------------


def test_blocked_output_drops_dvs_and_ext_and_delays_aps():
    enc = DavisWordEncoder(latency_us=0)
    ev = make_events([100, 200], [1, 2], [3, 4], [1, 0])
    ext = np.zeros(1, EXT_INPUT_DTYPE)
    ext["t"], ext["edge"] = 300, ExtInputEdge.PULSE
    imu = np.zeros(1, IMU_DTYPE)
    imu["t"] = 400
    assert enc.encode(window(0, 1000, ev, ext_input=ext, imu=imu), output_blocked=True) == b""
    assert (enc.dvs_dropped, enc.extinput_dropped) == (2, 1)
    w = words_of(enc.encode(empty_activity(1000, 2000)))
    assert w[:2] == [0x8000 | 1000, 0x0005]  # the IMU sample waited and is stamped late


def test_blocked_output_keeps_dvs_without_drop_flag():
    enc = DavisWordEncoder(EncoderConfig(drop_dvs_on_transfer_stall=False), latency_us=0)
    ev = make_events([100], [1], [3], [1])
    enc.encode(window(0, 1000, ev), output_blocked=True)
    assert enc.dvs_dropped == 0
    assert words_of(enc.encode(empty_activity(1000, 2000))) == [0x8000 | 1000, 0x1003, 0x3001]


def test_bandwidth_cap_drops_dvs_events():
    rng = np.random.default_rng(2)
    n = 100_000
    t = np.sort(rng.integers(0, 100_000, n))  # 1 Meps
    ev = make_events(t, rng.integers(0, 240, n), rng.integers(0, 180, n), np.ones(n))
    cap = 1_000_000.0  # 1 MB/s: far below the ~6 MB/s this stream needs
    data = encode_stream([window(0, 100_000, ev)], config=EncoderConfig(bandwidth_bytes_per_s=cap))
    assert len(data) <= cap * 0.1 * 1.05
    host = host_decode(data)
    assert 0 < len(host.events) < n


# -- against engineer A's decoder (the driver side) ------------------------------------------------


def test_round_trip_through_the_driver_decoder():
    decode = pytest.importorskip("mocaprig.acquire.davis240c_decode")
    from mocaprig.drivers_mock.davis240c_usb import SyntheticDavisSource

    source = SyntheticDavisSource(seed=2, event_rate_hz=50_000.0)
    source.reset(session_ns=0)
    windows = [source.activity(k * 10_000, (k + 1) * 10_000) for k in range(12)]
    data = encode_stream(windows)
    decoder = decode.DavisDecoder()
    # Feed it in odd-sized pieces: composite records span USB transfers (note §16.11).
    cuts = [*range(0, len(data), 8191), len(data)]
    packets = [decoder.decode(data[a:b]) for a, b in itertools.pairwise(cuts)]
    events = np.concatenate([p.events for p in packets])
    sent = np.concatenate([w.events for w in windows])
    np.testing.assert_array_equal(
        np.sort(events, order=["t", "y", "x"]), np.sort(sent, order=["t", "y", "x"])
    )
    frames = [f for p in packets for f in p.frames]
    exposures = [e for w in windows for e in w.exposures]
    assert len(frames) == len(exposures) == 3
    for frame, exp in zip(frames, exposures, strict=True):
        assert (frame.t_start_exposure_us, frame.t_end_exposure_us) == (exp.start_us, exp.end_us)
        assert frame.exposure_cycles == 30 * (exp.end_us - exp.start_us)
        np.testing.assert_array_equal(frame.pixels, np.clip(2 * np.rint(exp.cds / 2), 0, 1023))
    imu = np.concatenate([p.imu for p in packets])
    sent_imu = np.concatenate([w.imu for w in windows])
    np.testing.assert_array_equal(imu["t"], sent_imu["t"])
    np.testing.assert_allclose(imu["accel_g"], sent_imu["accel_g"], atol=1 / 8192)
    np.testing.assert_allclose(imu["gyro_dps"], sent_imu["gyro_dps"], atol=1 / 65.536)
    np.testing.assert_allclose(imu["temp_c"], sent_imu["temp_c"], atol=1 / 340)
    assert decoder.stats.non_monotonic_timestamps == 0


@settings(max_examples=40, deadline=None)
@given(
    times=st.lists(st.integers(0, 3 * TIMESTAMP_WRAP_US), min_size=1, max_size=60),
    cuts=st.lists(st.integers(1, 3 * TIMESTAMP_WRAP_US), max_size=5),
    race=st.booleans(),
)
def test_any_event_stream_round_trips_with_valid_timestamp_words(times, cuts, race):
    t = np.sort(np.array(times))
    ev = make_events(t, t % 240, (t // 7) % 180, t % 2)
    edges = sorted({0, *cuts, 3 * TIMESTAMP_WRAP_US + 1})
    windows = [window(a, b, ev[(t >= a) & (t < b)]) for a, b in itertools.pairwise(edges)]
    w = np.array(words_of(encode_stream(windows, wrap_race=race)))
    ts = np.flatnonzero(w & 0x8000)
    assert set((w[ts + 1] >> 12).tolist()) <= {0, 1}
    assert not np.any(w == 0x8000)
    assert np.count_nonzero(w == 0x7001) == 3
    host = host_decode(w.astype("<u2").tobytes())
    got = sorted((x, y, p) for _, x, y, p in host.events)
    assert got == sorted(zip(ev["x"].tolist(), ev["y"].tolist(), ev["p"].tolist(), strict=True))
    got_t = [e[0] for e in host.events]
    assert got_t == sorted(got_t)
    if not race:
        assert sorted(got_t) == t.tolist()
    else:  # latched words are reported 1 µs early, at the end of the old epoch (§7.1)
        assert all(0 <= a - b <= 1 for a, b in zip(t.tolist(), got_t, strict=True))
