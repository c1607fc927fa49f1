"""DAVIS simulator realism (issue 15): statistics on hand-made events, targets on a small scene."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mocaprig.acquire.events import make_events
from mocaprig.drivers_mock.davis240c_render import DavisLook, log_intensity
from mocaprig.drivers_mock.davis240c_sim import DavisSimulator, DvsNoise
from mocaprig.drivers_mock.davis_activity import DavisActivity
from mocaprig.drivers_mock.davis_stats import (
    as_davis346,
    event_stats,
    fit_contrast,
    isolated_mask,
    ramp_contrast,
    same_pixel_intervals_us,
    static_world,
)
from mocaprig.drivers_mock.scenario import Scenario, build_scenario
from mocaprig.errors import ValidationError
from mocaprig.process.body.motion import Motion

MS_NS = 1_000_000
#: The karate scenario (seed 3) kicks from ≈ 1.8 s.
FAST_NS = 1_800 * MS_NS


# --------------------------------------------------------------------------------------------
# the statistics on hand-made events


def test_same_pixel_intervals_pair_consecutive_events_of_one_pixel() -> None:
    # Pixel (1, 0): events at 0, 500, 2500 µs; pixel (0, 2): 100, 4100; pixel (3, 3): one.
    ev = make_events(
        [0, 100, 500, 2500, 4100, 50],
        [1, 0, 1, 1, 0, 3],
        [0, 2, 0, 0, 2, 3],
        [1, 0, 0, 1, 1, 1],
    )
    got = np.sort(same_pixel_intervals_us(ev, sensor_size=(4, 4)))
    np.testing.assert_array_equal(got, [500, 2000, 4000])
    # Same polarity only: (1, 0) ON at 0 and 2500; (0, 2) OFF then ON: no pair.
    same = same_pixel_intervals_us(ev, sensor_size=(4, 4), same_polarity=True)
    np.testing.assert_array_equal(same, [2500])


def test_isolated_events_have_no_neighbour_within_the_window() -> None:
    ev = make_events(
        [0, 3000, 20_000, 20_000, 40_000, 40_004],
        [5, 6, 0, 9, 2, 4],
        [5, 6, 0, 9, 2, 2],
        [1, 1, 1, 1, 0, 0],
    )
    # (5,5)–(6,6) are diagonal neighbours 3 ms apart; (2,2) and (4,2) are 2 px apart.
    lonely = isolated_mask(ev, sensor_size=(10, 10), window_us=5000)
    np.testing.assert_array_equal(lonely, [False, False, True, True, True, True])
    # A shorter window separates the diagonal pair too.
    short = isolated_mask(ev, sensor_size=(10, 10), window_us=2000)
    np.testing.assert_array_equal(short, [True] * 6)
    # The own pixel counts as a neighbour.
    again = make_events([0, 1000], [3, 3], [3, 3], [1, 1])
    assert not isolated_mask(again, sensor_size=(10, 10)).any()


def test_event_stats_summarise_a_known_stream() -> None:
    # 4 pixels, each firing every 2 ms for 100 ms, alternating ON/OFF; 3 ON-only stray events.
    t = np.repeat(np.arange(0, 100_000, 2000), 4)
    x = np.tile([10, 30, 50, 70], t.size // 4)
    p = (t // 2000) % 2
    stray_t = np.array([10_000, 50_000, 90_000])
    ev = make_events(
        np.concatenate([t, stray_t]),
        np.concatenate([x, [200, 210, 220]]),
        np.concatenate([np.full(t.size, 40), [170, 100, 20]]),
        np.concatenate([p, [1, 1, 1]]),
    )
    st = event_stats(ev, sensor_size=(240, 180), duration_us=100_000)
    assert st.events == 203
    assert st.events_per_s == pytest.approx(2030.0)
    assert st.on_fraction == pytest.approx((100 + 3) / 203)
    assert st.active_pixels == 7
    assert st.interval_count == 4 * 49
    assert st.interval_min_ms == pytest.approx(2.0)
    assert st.interval_p1_ms == pytest.approx(2.0)
    assert st.interval_under_1p5ms == 0.0
    assert st.isolated_fraction == pytest.approx(3 / 203)
    assert st.isolated_hz_per_pixel == pytest.approx(3 / (240 * 180) / 0.1)


def test_event_stats_refuse_events_outside_the_sensor() -> None:
    ev = make_events([0, 10], [300, 1], [10, 1], [1, 0])
    with pytest.raises(ValidationError, match="outside a 240×180 sensor"):
        event_stats(ev, sensor_size=(240, 180))
    assert event_stats(ev, sensor_size=(346, 260)).events == 2


def test_fit_contrast_recovers_thresholds_and_the_dead_band() -> None:
    rng = np.random.default_rng(0)
    h, w = 40, 50
    c_on, c_off, band = 0.25, 0.15, 0.1
    dl = rng.uniform(-1.5, 1.5, (h, w))
    # Each pixel first crosses ``band`` of its dead band, then fires once per threshold from a
    # random level in it (rising: ON and C_on; falling: OFF and C_off).
    c = np.where(dl > 0, c_on, c_off)
    n = np.floor(np.maximum(np.abs(dl) - band, 0.0) / c + rng.random((h, w))).astype(int).ravel()
    pix = np.repeat(np.arange(h * w), n)
    on = np.repeat(dl.ravel() > 0, n)
    ev = make_events(np.zeros(pix.size, int), pix % w, pix // w, on)
    fit = fit_contrast([(ev, dl)], min_change_ln=0.5)
    assert fit.c_on == pytest.approx(c_on, rel=0.05)
    assert fit.c_off == pytest.approx(c_off, rel=0.05)
    assert fit.offset_up_ln == pytest.approx(band, abs=0.04)
    assert fit.offset_down_ln == pytest.approx(band, abs=0.04)
    # Without the intercept the band inflates the thresholds.
    assert fit_contrast([(ev, dl)], min_change_ln=0.5, offsets=False).c_on > 1.05 * c_on
    with pytest.raises(ValidationError, match="pixel samples"):
        fit_contrast([(ev, dl)], min_change_ln=2.0)


# --------------------------------------------------------------------------------------------
# the simulator against the realism targets


@pytest.fixture(scope="module")
def karate() -> Scenario:
    return build_scenario("karate", seed=3, seconds=4.0)


@pytest.fixture(scope="module")
def swing_events(karate: Scenario) -> np.ndarray:
    """30 ms of the kick's limbs going out (to the pose 15 ms later) and back, defaults but for
    a coarser render step (speed)."""
    t = np.arange(31) * 1e-3
    clip_ns = FAST_NS + (15 * MS_NS * 0.5 * (1.0 - np.cos(2.0 * np.pi * t / 0.03))).astype(np.int64)
    world = replace(karate, motion=Motion("swing", 1000.0, karate.pose(clip_ns)))
    sim = DavisSimulator(world, motion_step_px=1.0)
    return np.concatenate([sim.activity(a, a + 10_000).events for a in range(0, 30_000, 10_000)])


def test_moving_scene_has_real_dead_time_and_on_fraction(swing_events: np.ndarray) -> None:
    st = event_stats(swing_events, sensor_size=(240, 180), duration_us=30_000)
    assert st.events > 500
    assert st.interval_count > 200
    # Real DAVIS240C: almost no same-pixel pairs under 1.5 ms, 1st percentile 2–4 ms.
    assert st.interval_p1_ms >= 1.5
    assert st.interval_under_1p5ms < 0.005
    # Out and back: each pixel's net change is zero, so ON events are C_off / (C_on + C_off).
    assert 0.40 <= st.on_fraction <= 0.50


def test_dead_time_binds_on_fast_edges(swing_events: np.ndarray) -> None:
    iv = same_pixel_intervals_us(swing_events, sensor_size=(240, 180))
    # Dead times spread 5 % (σ of the log) about 1.6 ms, minus a few σ of the 10 µs jitter.
    assert iv.min() >= 0.8 * 1600 - 50
    # Fast edges make pixels fire soon after their release: the limit binds (an ideal pixel's
    # 1st percentile is ≈ 0.07 ms here, 0.4 ms with bandwidth alone).
    assert np.percentile(iv, 1.0) < 2 * 1600


def test_static_scene_background_activity_is_about_0p1_hz_per_pixel(karate: Scenario) -> None:
    sim = DavisSimulator(static_world(karate, FAST_NS))
    ev = np.concatenate([sim.activity(a, a + 50_000).events for a in range(0, 300_000, 50_000)])
    st = event_stats(ev, sensor_size=(240, 180), duration_us=300_000)
    assert 0.05 <= st.isolated_hz_per_pixel <= 0.2
    # Nothing but noise moves: almost every event is isolated.
    assert st.isolated_fraction > 0.9


@pytest.mark.parametrize(("c_on", "c_off"), [(0.22, 0.18), (0.30, 0.25)])
def test_contrast_threshold_is_recovered_from_a_slow_light_ramp(
    karate: Scenario, c_on: float, c_off: float
) -> None:
    look = DavisLook(flicker_hz=1.0, flicker_depth=0.5)
    sim = DavisSimulator(
        static_world(karate, FAST_NS), contrast_on=c_on, contrast_off=c_off, look=look
    )
    up, down = ramp_contrast(sim)
    assert up.c_on == pytest.approx(c_on, rel=0.10)
    assert down.c_off == pytest.approx(c_off, rel=0.10)


def test_fast_change_gives_fewer_events_than_contrast_over_threshold(karate: Scenario) -> None:
    world = static_world(karate, FAST_NS)

    def events_per_ln(hz: float, *, ideal: bool = False) -> float:
        look = DavisLook(flicker_hz=hz, flicker_depth=0.5)
        if ideal:
            sim = DavisSimulator(world, look=look, refractory_us=0, cutoff_hz=0.0)
        else:
            sim = DavisSimulator(world, look=look)
        up, _ = ramp_contrast(sim, min_change_ln=0.6)
        return up.events_per_ln

    # A 40 Hz ramp rises by 1.1 ln in 12.5 ms: the dead time and the photoreceptor's
    # bandwidth cost a large part of the events a slow ramp gives.
    slow, fast = events_per_ln(1.0), events_per_ln(40.0)
    assert fast < 0.8 * slow
    # An ideal pixel keeps up.
    ideal = events_per_ln(40.0, ideal=True)
    assert ideal > 0.9 * slow


def _ranked(ev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(key, t)`` of events sorted by pixel then time; key = pixel·10⁶ + rank in the pixel."""
    pix = ev["y"].astype(np.int64) * 240 + ev["x"]
    order = np.lexsort((ev["t"], pix))
    pix, t = pix[order], ev["t"][order].astype(np.int64)
    first = np.searchsorted(pix, pix, side="left")
    return pix * 1_000_000 + (np.arange(pix.size) - first), t


def test_timestamp_jitter_has_the_configured_spread(karate: Scenario) -> None:
    def run(jitter_us: float) -> DavisActivity:
        sim = DavisSimulator(
            karate,
            reset_session_ns=FAST_NS,
            noise=DvsNoise.none(),
            latency_us=100,
            jitter_us=jitter_us,
            motion_step_px=1.0,
        )
        return sim.activity(0, 10_000)

    clean, noisy = run(0.0), run(20.0)
    # Stamping happens after the pixel model: the same events, only their times move (away
    # from the window's end, where an event may cross it).
    ka, ta = _ranked(clean.events[clean.events["t"] < 9_000])
    kb, tb = _ranked(noisy.events)
    common, ia, ib = np.intersect1d(ka, kb, return_indices=True)
    assert common.size == ka.size > 500
    d = (tb[ib] - ta[ia]).astype(np.float64)
    assert abs(d.mean()) < 2.0
    assert 15.0 < d.std() < 25.0


def test_exposure_burst_fires_off_at_start_and_on_at_end(karate: Scenario) -> None:
    sim = DavisSimulator(
        static_world(karate, FAST_NS),
        noise=DvsNoise.none(),
        aps_burst_fraction=0.01,
        exposure_offset_us=5000,
        exposure_us=4000,
    )
    act = sim.activity(0, 20_000)
    ev = act.events
    assert [e.start_us for e in act.exposures] == [5000]
    at_start = ev[(ev["t"] >= 5000) & (ev["t"] < 5300)]
    at_end = ev[(ev["t"] >= 9000) & (ev["t"] < 9300)]
    # 1 % of 43,200 pixels at each edge; nothing else happens in a still, noise-free world.
    assert at_start.size == pytest.approx(432, rel=0.2)
    assert at_end.size == pytest.approx(432, rel=0.2)
    assert at_start.size + at_end.size == ev.size
    assert not at_start["p"].any()
    assert at_end["p"].all()


def test_sensor_size_follows_the_rig_camera(karate: Scenario) -> None:
    # No exposure in the window: ApsExposure still takes 180×240 frames only (see the docs).
    sim = DavisSimulator(
        as_davis346(karate), reset_session_ns=FAST_NS, exposure_offset_us=1_000_000
    )
    assert sim.shape == (260, 346)
    ev = sim.activity(0, 10_000).events
    assert ev.size > 100
    assert int(ev["x"].max()) >= 240
    assert int(ev["y"].max()) >= 180
    assert int(ev["x"].max()) < 346
    assert int(ev["y"].max()) < 260
    img = sim.render_intensity(FAST_NS)
    assert img.shape == (260, 346)
    assert np.isfinite(log_intensity(img)).all()
