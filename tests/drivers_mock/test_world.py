"""Hidden world parameters: nominal keeps the old world, random draws a rig the calibration does
not mirror, and every mock follows the drawn values."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import cast

import numpy as np
import pytest

from mocaprig.drivers_mock.clock import DeviceClock
from mocaprig.drivers_mock.scenario import build_scenario, stream_rng
from mocaprig.drivers_mock.vicon import SyncWiring, ViconCapture, simulate_sync_channel
from mocaprig.drivers_mock.world import WorldParams
from mocaprig.errors import ValidationError

SECOND = 1_000_000_000


def test_the_nominal_world_is_every_default() -> None:
    nominal = WorldParams.nominal()
    assert nominal == WorldParams()
    assert nominal.kind == "nominal"
    assert nominal.sync_latency_us == 2.0
    assert nominal.antialias_hz is None
    assert nominal.master_dropped_frames == 0
    assert nominal.davis_trigger_jitter_us == 0.0
    assert nominal.pulse_at is None
    assert nominal.d415_drift_ppm is None


def test_random_worlds_stay_within_the_ranges_of_a_real_rig() -> None:
    worlds = [WorldParams.draw(stream_rng(s, "world")) for s in range(200)]
    lat = [w.sync_latency_us for w in worlds]
    assert min(lat) >= 0.0
    assert max(lat) <= 50.0
    assert max(lat) - min(lat) > 40.0
    for w in worlds:
        assert w.kind == "random"
        assert w.pulse_at in ("exposure-start", "readout-start")
        delay = w.slave_trigger_delay_us
        assert delay is not None
        assert (0.0 <= delay <= 200.0) if w.pulse_at == "exposure-start" else (700 <= delay <= 900)
        assert 150.0 <= w.sync_tau_us <= 1000.0
        assert w.antialias_hz is None or 500.0 <= w.antialias_hz <= 5000.0
        assert 1.0 <= w.davis_trigger_jitter_us <= 2.0
        assert 0 <= w.master_dropped_frames <= 5
        assert w.d415_drift_ppm is not None
        assert len(w.d415_drift_ppm) == 4
        drifts = [*w.d415_drift_ppm, w.davis_drift_ppm, w.vicon_drift_ppm]
        assert all(d is not None and abs(d) <= 50.0 for d in drifts)
    # Both conventions, filtered and unfiltered inputs, bounces and dropped frames all occur.
    assert {w.pulse_at for w in worlds} == {"exposure-start", "readout-start"}
    assert any(w.antialias_hz is None for w in worlds)
    assert any(w.antialias_hz is not None for w in worlds)
    assert any(w.clap_bounce_rad > 0 for w in worlds)
    assert {w.master_dropped_frames for w in worlds} == set(range(6))


def test_an_out_of_range_parameter_is_refused_naming_it() -> None:
    with pytest.raises(ValidationError, match="sync_latency_us"):
        WorldParams(sync_latency_us=-1.0)
    with pytest.raises(ValidationError, match="clap_closing_s"):
        WorldParams(clap_closing_s=(0.2, 0.1))
    with pytest.raises(ValidationError, match="one of"):
        build_scenario("default", seed=1, seconds=4.0, world="wild")  # type: ignore[arg-type]


def test_a_random_world_keeps_the_actor_and_the_rig_and_moves_only_the_hidden_values() -> None:
    nominal = build_scenario("default", seed=7, seconds=4.0)
    rand = build_scenario("default", seed=7, seconds=4.0, world="random")
    params = rand.world_params
    t = np.arange(0, 4 * SECOND, 100_000_000, dtype=np.int64)
    np.testing.assert_array_equal(nominal.markers_m(t), rand.markers_m(t))
    np.testing.assert_array_equal(nominal.camera_pose("d415-2"), rand.camera_pose("d415-2"))
    assert nominal.clap_times_ns == rand.clap_times_ns
    for name, clock in nominal.clocks.items():
        assert rand.clocks[name].offset_ns == clock.offset_ns
    assert params.d415_drift_ppm is not None
    assert rand.clocks["d415-1"].drift_ppm == params.d415_drift_ppm[1]
    assert rand.clocks["vicon"].drift_ppm == params.vicon_drift_ppm
    assert rand.rig.d415_timing.pulse_at == params.pulse_at
    assert rand.rig.d415_timing.trigger_to_exposure_us == params.slave_trigger_delay_us
    assert rand.noise.vicon_gap_fraction == params.vicon_gap_fraction
    assert rand.clapperboard.closing_power == params.clap_power
    # The same seed draws the same hidden world.
    assert build_scenario("default", seed=7, seconds=4.0, world="random").world_params == params


def test_a_bouncing_clapperboard_reopens_after_contact_and_keeps_the_contact_instant() -> None:
    params = replace(WorldParams.nominal(), clap_bounce_rad=0.05, clap_bounce_s=0.04)
    world = build_scenario("default", seed=3, seconds=4.0, world=params)
    tc = world.clap_times_ns[0]
    angle = world.clapperboard.angle_rad
    assert angle(np.array([tc])) == pytest.approx(0.0, abs=1e-12)
    assert angle(np.array([tc + 20_000_000]))[0] == pytest.approx(0.05, rel=1e-6)
    assert angle(np.array([tc + 45_000_000]))[0] == 0.0
    assert angle(np.array([tc - 5_000_000]))[0] > 0.0


def test_a_harder_closing_law_is_slower_at_first_and_faster_at_contact() -> None:
    soft = build_scenario("default", seed=3, seconds=4.0)
    hard_params = replace(WorldParams.nominal(), clap_power=4.0)
    hard = build_scenario("default", seed=3, seconds=4.0, world=hard_params)
    tc = soft.clap_times_ns[0]
    closing = round(soft.clapperboard.closing_s[0] * 1e9)
    mid = np.array([tc - closing // 2])
    assert hard.clapperboard.angle_rad(mid)[0] > soft.clapperboard.angle_rad(mid)[0]


def test_the_sync_input_front_end_delays_and_rounds_the_edge() -> None:
    """A 2-pole anti-alias filter after the RC: the signal starts later and more gently than
    the RC alone, an offset moves the levels, a coarse ADC quantises them."""
    # Only the trial's rate, first frame and length matter to the analog samples.
    capture = cast(ViconCapture, SimpleNamespace(rate_hz=120.0, start_field=1, num_frames=240))
    clock = DeviceClock("vicon", 0, 0.0, 0.0, 1, 0)
    pulses = np.array([100_000_000, 200_000_000], dtype=np.int64)
    quiet = {"latency_jitter_us": 0.0, "noise_v": 0.0, "tau_tolerance": 0.0}
    rc = simulate_sync_channel(
        capture, clock, pulses, rng=np.random.default_rng(0), wiring=SyncWiring(**quiet)
    )
    front = SyncWiring(antialias_hz=1000.0, offset_v=0.03, lsb_v=20.0 / 4096, **quiet)
    filt = simulate_sync_channel(capture, clock, pulses, rng=np.random.default_rng(0), wiring=front)
    v_rc, v_f = rc.values[:, 0], filt.values[:, 0]
    after = slice(241, 246)  # samples just after the first switch at 100 ms (2400 Hz)
    assert np.all(v_f[after] < v_rc[after])
    assert np.median(v_f[260:400]) == pytest.approx(4.8 + 0.03, abs=20.0 / 4096)
    assert np.allclose(np.round(v_f / (20.0 / 4096)), v_f / (20.0 / 4096))
    np.testing.assert_array_equal(rc.edges_ns, filt.edges_ns)


def test_the_truth_records_the_drawn_world(tmp_path: Path) -> None:
    from mocaprig.drivers_mock.session import simulate_session

    result = simulate_session(tmp_path / "w", seed=4, seconds=3.0, world="random")
    truth = json.loads((result.truth_dir / "scenario.json").read_text())
    assert truth["world"] == result.scenario.world_params.to_dict()
    assert truth["world"]["kind"] == "random"
    assert truth["rig"]["d415_timing"]["pulse_at"] == truth["world"]["pulse_at"]
    # Nothing of it goes into the Vicon export the calibration reads.
    assert b"sync_latency" not in result.c3d_path.read_bytes()


def test_the_master_loses_its_first_captures_but_still_pulses() -> None:
    from mocaprig.acquire.depth_camera import SensorOptions, StreamConfig, SyncMode
    from mocaprig.drivers_mock.d415 import mock_cameras

    params = replace(WorldParams.nominal(), master_dropped_frames=3)
    world = build_scenario("default", seed=2, seconds=3.0, world=params)
    cams = mock_cameras(scenario=world, count=2, images=False)
    for i, cam in enumerate(cams):
        cam.configure(
            stream=StreamConfig(),
            options=SensorOptions(),
            sync_mode=SyncMode.MASTER if i == 0 else SyncMode.SLAVE,
        )
    for cam in cams:
        cam.start()
    for _ in range(10):
        for cam in cams:
            assert cam.poll() is not None
    master, slave = cams
    outcomes = [c.outcome for c in master.captures]
    assert outcomes[:3] == ["dropped"] * 3
    assert outcomes[3] == "delivered"
    first_pulse = master.pulse_at_or_after(0)
    assert first_pulse is not None
    assert slave.captures[0].pulse_ns == first_pulse  # the slave saw the lost frame's pulse
    assert master.captures[3].exposure_start_ns > first_pulse


@pytest.mark.slow
def test_the_davis_stamps_its_trigger_input_with_jitter_the_same_in_any_window() -> None:
    from mocaprig.drivers_mock.davis240c_sim import DavisSimulator

    def edges(world_params: WorldParams, windows: list[tuple[int, int]]) -> np.ndarray:
        world = build_scenario("default", seed=2, seconds=3.0, world=world_params)
        sim = DavisSimulator(world)
        sim.configure(dvs_enabled=False)
        parts = [sim.activity(t0, t1).ext_input["t"] for t0, t1 in windows]
        return np.concatenate(parts).astype(np.int64)

    jittery = replace(WorldParams.nominal(), davis_trigger_jitter_us=1.5)
    whole = edges(jittery, [(0, 500_000)])
    ideal = edges(WorldParams.nominal(), [(0, 500_000)])
    assert whole.size == ideal.size >= 28
    assert 0.8 < float(np.std(whole - ideal)) < 2.5
    np.testing.assert_array_equal(edges(jittery, [(0, 250_000), (250_000, 500_000)]), whole)
