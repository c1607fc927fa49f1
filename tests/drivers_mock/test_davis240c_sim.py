"""DAVIS240C simulator: events on moving edges, noise, APS, IMU, trigger edges, determinism."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mocaprig.acquire.events import EVENT_DTYPE
from mocaprig.drivers_mock.davis240c_render import DavisRenderer
from mocaprig.drivers_mock.davis240c_sim import (
    DavisSimulator,
    DvsNoise,
    edge_fraction,
    photoreceptor_lowpass,
    simulate_davis,
)
from mocaprig.drivers_mock.davis_activity import DavisActivity, ExtInputEdge
from mocaprig.drivers_mock.scenario import Scenario, build_scenario
from mocaprig.errors import ValidationError
from mocaprig.process.body.motion import Motion

MS_NS = 1_000_000
#: A fast stretch of the karate scenario (seed 3): a kick starts ≈ 1.8 s.
FAST_NS = 1_800 * MS_NS


@pytest.fixture(scope="module")
def karate() -> Scenario:
    return build_scenario("karate", seed=3, seconds=4.0)


def _frozen(sc: Scenario, t_ns: int) -> Scenario:
    """The world with the actor holding its pose at ``t_ns`` (the clapperboard is still closed
    before ≈ 1 s, so the first few hundred ms are a static scene)."""
    pose = sc.pose(np.array([t_ns], dtype=np.int64))
    return replace(sc, motion=Motion("frozen", 1.0, pose))


def _retimed(sc: Scenario, speed: float) -> Scenario:
    m = sc.motion
    return replace(sc, motion=Motion(m.name, m.rate_hz * speed, m.poses))


@pytest.fixture(scope="module")
def static_run(karate: Scenario) -> tuple[DavisSimulator, DavisActivity]:
    """200 ms of a frozen world, default noise, in 20 ms windows."""
    sim = DavisSimulator(_frozen(karate, FAST_NS), exposure_us=3000, frame_interval_us=20_000)
    acts = [sim.activity(i * 20_000, (i + 1) * 20_000) for i in range(10)]
    merged = DavisActivity(
        t0_us=0,
        t1_us=200_000,
        events=np.concatenate([a.events for a in acts]),
        exposures=tuple(e for a in acts for e in a.exposures),
        imu=np.concatenate([a.imu for a in acts]),
        ext_input=np.concatenate([a.ext_input for a in acts]),
    )
    return sim, merged


@pytest.fixture(scope="module")
def fast_run(karate: Scenario) -> tuple[DavisSimulator, DavisActivity]:
    """20 ms of a kick, default settings, one window."""
    sim = DavisSimulator(karate, reset_session_ns=FAST_NS)
    return sim, sim.activity(0, 20_000)


@pytest.mark.slow
def test_output_is_a_valid_activity(fast_run) -> None:
    _, act = fast_run
    assert isinstance(act, DavisActivity)
    ev = act.events
    assert ev.dtype == EVENT_DTYPE
    assert ev.size > 100
    assert np.all(np.diff(ev["t"]) >= 0)
    assert ev["t"].min() >= 0
    assert ev["t"].max() < 20_000
    assert ev["x"].max() < 240
    assert ev["y"].max() < 180


def test_static_world_gives_only_noise_at_the_configured_rate(static_run) -> None:
    sim, act = static_run
    rate = act.events.size / 0.2
    expected = sim.noise.total_hz
    assert 0.8 * expected < rate < 1.2 * expected
    # Shot noise is half ON, leak all ON.
    on = (0.5 * sim.noise.shot_hz + sim.noise.leak_hz) / (sim.noise.shot_hz + sim.noise.leak_hz)
    assert act.events["p"].mean() == pytest.approx(on, abs=0.05)


def test_static_world_without_noise_is_silent(karate: Scenario) -> None:
    act = simulate_davis(_frozen(karate, FAST_NS), t0_us=0, t1_us=30_000, noise=DvsNoise.none())
    assert act.events.size == 0


@pytest.mark.slow
def test_event_rate_grows_with_motion_speed(karate: Scenario) -> None:
    # An ideal pixel (no dead time, no bandwidth limit): the rate follows the speed. With the
    # realistic defaults fast edges saturate the pixels (test_davis240c_sim_realism.py).
    rates = []
    for speed in (0.5, 1.0):
        sc = _retimed(karate, speed)
        # The same stretch of the clip, played at half and at full speed.
        dur_us = int(20_000 / speed)
        act = simulate_davis(
            sc,
            t0_us=0,
            t1_us=dur_us,
            reset_session_ns=int(FAST_NS / speed),
            noise=DvsNoise.none(),
            motion_step_px=1.0,
            refractory_us=0,
            cutoff_hz=0.0,
        )
        rates.append(act.events.size / (dur_us * 1e-6))
    assert rates[1] > 1.6 * rates[0]


def test_polarity_balance_for_a_back_and_forth_motion(karate: Scenario) -> None:
    # Out to the pose 15 ms later and back again, over 30 ms.
    t = np.arange(31) * 1e-3
    clip_ns = FAST_NS + (15 * MS_NS * 0.5 * (1.0 - np.cos(2.0 * np.pi * t / 0.03))).astype(np.int64)
    sc = replace(karate, motion=Motion("swing", 1000.0, karate.pose(clip_ns)))
    act = simulate_davis(sc, t0_us=0, t1_us=30_000, noise=DvsNoise.none(), motion_step_px=1.0)
    assert act.events.size > 500
    assert 0.4 < act.events["p"].mean() < 0.6


def test_events_lie_on_moving_edges(fast_run) -> None:
    sim, act = fast_run
    score = edge_fraction(sim, act.events, t0_us=0, t1_us=20_000, slice_us=5000)
    assert score.events > 500
    assert score.fraction >= 0.8
    assert score.chance < 0.2


def test_aps_exposures_follow_the_schedule(static_run) -> None:
    sim, act = static_run
    starts = [e.start_us for e in act.exposures]
    # exposure_offset 18 ms, interval 20 ms: starts 18, 38, …, 178 ms (ends < 200 ms).
    assert starts == list(range(18_000, 180_001, 20_000))
    assert all(e.end_us - e.start_us == 3000 for e in act.exposures)
    cds = act.exposures[0].cds
    assert cds.shape == (180, 240)
    assert cds.min() >= 0.0
    assert cds.max() <= 1023.0
    assert 100.0 < cds.mean() < 700.0
    # A static scene: the frame is the irradiance times the gain, plus noise and FPN.
    img = sim.render_intensity(int(sim.session_ns(18_000)))
    assert np.corrcoef(img.ravel(), cds.ravel())[0, 1] > 0.99


def test_aps_frame_is_motion_blurred(karate: Scenario) -> None:
    sim = DavisSimulator(
        karate,
        reset_session_ns=FAST_NS,
        exposure_us=10_000,
        exposure_offset_us=0,
        noise=DvsNoise.none(),
        motion_step_px=1.0,
    )
    act = sim.activity(0, 12_000)
    (exp,) = act.exposures
    frames = [sim.render_intensity(int(sim.session_ns(u))) for u in (0, 5000, 10_000)]
    gain = 900.0 * 10_000 / 4000
    blurred = exp.cds / gain
    # The exposure average sits between the frames at its start and end.
    err_mid = np.abs(blurred - frames[1]).mean()
    err_start = np.abs(blurred - frames[0]).mean()
    assert err_mid < err_start


def test_imu_at_rest_measures_gravity(static_run) -> None:
    _, act = static_run
    imu = act.imu
    assert imu.size == 199  # samples at 1, 2, …, 199 ms
    assert np.all(np.diff(imu["t"]) == 1000)
    norm = np.linalg.norm(imu["accel_g"], axis=1)
    assert norm.mean() == pytest.approx(1.0, abs=0.04)
    # The camera looks roughly horizontally: +1 g mostly on the IMU's y (up) axis.
    assert imu["accel_g"][:, 1].mean() > 0.95
    assert np.all(np.abs(imu["gyro_dps"].mean(axis=0)) < 3.0)
    assert imu["temp_c"].min() >= 30.0
    assert imu["temp_c"].max() <= 35.5


def test_ext_input_edges_at_30_hz(static_run) -> None:
    _, act = static_run
    ext = act.ext_input
    rise = ext["t"][ext["edge"] == int(ExtInputEdge.RISING)]
    fall = ext["t"][ext["edge"] == int(ExtInputEdge.FALLING)]
    assert rise.size >= 5
    assert np.all(np.abs(np.diff(rise) - 1e6 / 30.0) <= 2.0)
    n = min(rise.size, fall.size)
    width = fall[:n] - rise[:n] if fall[0] > rise[0] else fall[1 : n + 1] - rise[:n]
    assert np.all(np.abs(width - 50) <= 1)


def test_same_seed_same_output_and_windowing_does_not_matter(karate: Scenario, fast_run) -> None:
    _, one = fast_run
    # A second simulator of the same world, fed ragged windows (one of them empty).
    sim = DavisSimulator(karate, reset_session_ns=FAST_NS)
    parts = [sim.activity(a, b) for a, b in ((0, 3_500), (3_500, 3_500), (3_500, 20_000))]
    split = np.concatenate([p.events for p in parts])
    np.testing.assert_array_equal(one.events, split)
    np.testing.assert_array_equal(one.imu, np.concatenate([p.imu for p in parts]))
    np.testing.assert_array_equal(one.ext_input, np.concatenate([p.ext_input for p in parts]))


def test_reset_restarts_device_time(karate: Scenario) -> None:
    sim = DavisSimulator(_frozen(karate, FAST_NS), noise=DvsNoise.none())
    sim.activity(0, 10_000)
    sim.reset(session_ns=50 * MS_NS)
    assert int(sim.session_ns(0)) == 50 * MS_NS
    drift = karate.clocks["davis"].rate
    assert float(sim.device_us(50 * MS_NS + 1_000_000_000)) == pytest.approx(1e6 * drift)
    act = sim.activity(0, 5_000)
    assert act.t0_us == 0


def test_windows_must_not_overlap(karate: Scenario) -> None:
    sim = DavisSimulator(_frozen(karate, FAST_NS), noise=DvsNoise.none())
    sim.activity(0, 5_000)
    with pytest.raises(ValidationError, match="overlap"):
        sim.activity(4_000, 6_000)
    with pytest.raises(ValidationError):
        sim.activity(6_000, 5_000)


def test_bad_options_are_rejected(karate: Scenario) -> None:
    with pytest.raises(ValidationError, match="frame_interval_us"):
        DavisSimulator(karate, exposure_us=50_000, frame_interval_us=40_000)
    with pytest.raises(ValidationError):
        DvsNoise(shot_hz=-1.0)


def test_texture_moves_with_the_body(karate: Scenario) -> None:
    r = DavisRenderer(karate)
    a, b = r.render_batch(np.array([FAST_NS, FAST_NS + 10 * MS_NS]))
    assert a.shape == (180, 240)
    assert a.min() > 0.0
    assert a.max() < 2.0
    # Inside the silhouette there is texture: the log image has strong gradients there.
    assert r.edge_map(FAST_NS, threshold=0.2).mean() > 0.02
    assert np.abs(np.log(a) - np.log(b)).max() > 0.2


def test_configure_changes_the_aps_schedule(karate: Scenario) -> None:
    sim = DavisSimulator(_frozen(karate, FAST_NS), noise=DvsNoise.none())
    first = sim.activity(0, 50_000).exposures
    assert [(e.start_us, e.end_us) for e in first] == [(18_000, 22_000)]
    sim.configure(exposure_us=2000, frame_interval_us=10_000)
    later = sim.activity(50_000, 100_000).exposures
    starts = [e.start_us for e in later]
    assert starts[0] >= 50_000
    assert np.all(np.diff(starts) == 10_000)
    assert all(e.end_us - e.start_us == 2000 for e in later)
    # Half the exposure, half the signal.
    assert later[0].cds.mean() == pytest.approx(first[0].cds.mean() / 2, rel=0.05)
    with pytest.raises(ValidationError):
        sim.configure(exposure_us=20_000)


def test_sync_pulses_can_come_from_the_d415_timeline(karate: Scenario) -> None:
    period, phase = 20_000_000, 5_000_000

    def pulse_at_or_after(t_ns: int) -> int:
        return phase + max(0, -(-(t_ns - phase) // period)) * period

    sim = DavisSimulator(
        _frozen(karate, FAST_NS), noise=DvsNoise.none(), sync_source=pulse_at_or_after
    )
    ext = sim.activity(0, 60_000).ext_input
    rate = karate.clocks["davis"].rate
    want = np.array([5_000, 5_050, 25_000, 25_050, 45_000, 45_050]) * rate
    np.testing.assert_allclose(ext["t"], np.floor(want), atol=1)
    assert list(ext["edge"]) == [1, 2] * 3


def test_hot_pixels_fire_at_their_rate(karate: Scenario) -> None:
    noise = DvsNoise(shot_hz=0.0, leak_hz=0.0, hot_pixels=3, hot_pixel_hz=200.0)
    act = simulate_davis(_frozen(karate, FAST_NS), t0_us=0, t1_us=100_000, noise=noise)
    pix = np.unique(act.events["y"].astype(np.int64) * 240 + act.events["x"])
    assert pix.size == 3
    assert 30 < act.events.size < 90  # 3 × 200 Hz × 0.1 s = 60


def test_photoreceptor_lowpass_is_exact_for_ramps() -> None:
    x0, y0 = np.array([0.0, 1.0]), np.array([0.0, 0.0])
    # A held step: y approaches x as 1 - exp(-t/τ), in one step or in many.
    one = photoreceptor_lowpass(x0 + 1.0, x0 + 1.0, y0, 3000.0, 1000.0)
    y = y0
    for _ in range(30):
        y = photoreceptor_lowpass(x0 + 1.0, x0 + 1.0, y, 100.0, 1000.0)
    np.testing.assert_allclose(one, y, rtol=1e-12)
    np.testing.assert_allclose(one[0], 1.0 - np.exp(-3.0))
    # A long ramp of slope m: the output lags by m·τ.
    m, tau = 1e-3, 500.0
    ramp = photoreceptor_lowpass(np.zeros(1), np.full(1, m * 1e5), np.zeros(1), 1e5, tau)
    np.testing.assert_allclose(ramp, m * 1e5 - m * tau, rtol=1e-9)


def test_low_cutoff_slows_the_response(karate: Scenario) -> None:
    opts = {"reset_session_ns": FAST_NS, "noise": DvsNoise.none(), "motion_step_px": 1.0}
    fast = simulate_davis(karate, t0_us=0, t1_us=10_000, **opts)
    slow = simulate_davis(karate, t0_us=0, t1_us=10_000, cutoff_hz=20.0, **opts)
    assert slow.events.size < 0.7 * fast.events.size
