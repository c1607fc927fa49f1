"""Device clocks: affine map, drift, jitter, round trip, defaults."""

from __future__ import annotations

import numpy as np
import pytest

from mocaprig.drivers_mock.clock import DeviceClock, d415_clock, davis_clock, vicon_clock
from mocaprig.errors import ValidationError


def test_round_trip_returns_session_time_within_one_tick_and_jitter() -> None:
    clock = DeviceClock("davis", offset_ns=7_123_456_789, drift_ppm=23.0, jitter_ns=1000.0, seed=3)
    t = np.arange(0, 60_000_000_000, 7_777_777, dtype=np.int64)
    back = clock.session_ns(clock.device_ticks(t))
    err = back - t
    assert np.max(np.abs(err)) < 1000 + 6 * 1000  # one µs tick + 6 σ of jitter
    assert abs(np.mean(err) + 500) < 100  # floor() biases by half a tick


def test_round_trip_without_jitter_is_exact_to_the_tick() -> None:
    clock = DeviceClock("d", offset_ns=123_000_000_000, drift_ppm=-47.5, jitter_ns=0.0)
    t = np.arange(0, 100_000_000_000, 999_999_937, dtype=np.int64)
    err = clock.session_ns(clock.device_ticks(t)) - t
    assert np.all((err <= 1) & (err > -1001))


def test_drift_accumulates_as_ppm_of_elapsed_time() -> None:
    clock = DeviceClock("d", offset_ns=0, drift_ppm=50.0, jitter_ns=0.0, unit_ns=1)
    t = np.array([0, 100_000_000_000], dtype=np.int64)
    d = clock.device_ns(t)
    assert d[1] - d[0] - 100_000_000_000 == 5_000_000  # 50 ppm of 100 s = 5 ms


def test_jitter_is_deterministic_per_instant_and_has_the_stated_sigma() -> None:
    clock = DeviceClock("d", offset_ns=0, drift_ppm=0.0, jitter_ns=5000.0, unit_ns=1, seed=9)
    t = np.arange(0, 2_000_000_000, 100_000, dtype=np.int64)
    a = clock.device_ticks(t)
    np.testing.assert_array_equal(a, clock.device_ticks(t))
    noise = a - t
    assert 4500 < np.std(noise) < 5500
    assert abs(np.mean(noise)) < 200
    other = DeviceClock("d", offset_ns=0, drift_ppm=0.0, jitter_ns=5000.0, unit_ns=1, seed=10)
    assert not np.array_equal(a, other.device_ticks(t))


def test_clock_rejects_float_times_with_fractions() -> None:
    clock = DeviceClock("d", offset_ns=0, drift_ppm=0.0)
    with pytest.raises(ValidationError, match="integers"):
        clock.device_ticks(np.array([0.5]))


def test_clock_rejects_negative_jitter() -> None:
    with pytest.raises(ValidationError, match="jitter_ns"):
        DeviceClock("d", offset_ns=0, drift_ppm=0.0, jitter_ns=-1.0)


def test_default_clocks_have_realistic_parameters() -> None:
    rng = np.random.default_rng(0)
    davis = davis_clock(rng)
    d415 = d415_clock(rng, name="d415-0")
    vicon = vicon_clock(rng, rate_hz=120.0)
    assert davis.unit_ns == 1000
    assert abs(davis.drift_ppm) <= 30
    assert d415.unit_ns == 1000
    assert abs(d415.drift_ppm) <= 50
    assert vicon.jitter_ns == 0
    assert abs(vicon.drift_ppm) <= 10
    # The Vicon offset is a whole number of 120 Hz frames.
    frames = vicon.offset_ns * 120 / 1e9
    assert abs(frames - round(frames)) < 1e-6


def test_clock_dict_round_trip() -> None:
    clock = d415_clock(np.random.default_rng(4), name="d415-2")
    assert DeviceClock.from_dict(clock.to_dict()) == clock
