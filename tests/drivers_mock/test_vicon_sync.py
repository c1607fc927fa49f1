"""The simulated Vicon sync channel (drivers_mock.vicon.simulate_sync_channel) and the sessions
that carry it: the analog edges are the D415 master's pulses, sampled on the Vicon clock."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from mocaprig.acquire.recording import Recording
from mocaprig.acquire.recording_format import topic
from mocaprig.calib.time_align import analog_times_ns, find_sync_edges
from mocaprig.calib.vicon import read_c3d, read_c3d_analogs
from mocaprig.drivers_mock import simulate_session
from mocaprig.drivers_mock.clock import DeviceClock
from mocaprig.drivers_mock.noise import NoiseSettings
from mocaprig.drivers_mock.rig import ViconSpec
from mocaprig.drivers_mock.truth import read_truth
from mocaprig.drivers_mock.vicon import (
    SYNC_CHANNEL,
    SyncWiring,
    ViconCapture,
    capture_markers,
    simulate_sync_channel,
    write_c3d,
)
from mocaprig.errors import ValidationError

I64 = npt.NDArray[np.int64]
F64 = npt.NDArray[np.float64]
SECOND = 1_000_000_000


def _still(t_ns: I64) -> tuple[F64, None]:
    return np.tile([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0]], (t_ns.size, 1, 1)), None


def _capture(seconds: float = 5.0) -> tuple[ViconCapture, DeviceClock]:
    clock = DeviceClock("vicon", offset_ns=round(54_321 * 1e9 / 120), drift_ppm=-6.0, unit_ns=1)
    cap = capture_markers(
        _still,
        ["s:a", "s:b"],
        spec=ViconSpec(),
        clock=clock,
        start_ns=SECOND // 5,
        end_ns=round(seconds * SECOND),
        noise=NoiseSettings(),
        rng=np.random.default_rng(0),
    )
    return cap, clock


def _pulses(seconds: float = 5.0, drift_ppm: float = 31.0) -> I64:
    """A D415 master's train: 1/30 s of its own crystal, from 60 ms + a phase."""
    period = 1e9 / 30.0 / (1.0 + drift_ppm * 1e-6)
    n = int((seconds * SECOND - 71e6) / period)
    out: I64 = np.round(71e6 + np.arange(n) * period).astype(np.int64)
    return out


def test_sync_channel_edges_are_the_pulses_on_the_vicon_clock() -> None:
    cap, clock = _capture()
    pulses = _pulses()
    sync = simulate_sync_channel(cap, clock, pulses, rng=np.random.default_rng(1))
    assert sync.labels == (SYNC_CHANNEL,)
    assert sync.units == ("V",)
    assert sync.values.shape == (cap.num_frames * 20, 1)
    assert sync.rate_hz == 2400.0
    assert np.all(np.abs(sync.edges_ns - pulses - 2_000) <= 1_000)  # the box's latency
    assert sync.tau_ns == pytest.approx(470_000, rel=0.05)
    # Sample s of the trial is at Vicon device time ((start_field - 1)·20 + s) / 2400 s.
    n = (cap.start_field - 1) * 20 + np.arange(sync.values.shape[0])
    t_vicon = np.round(n * (1e9 / 2400.0))
    edges = find_sync_edges(t_vicon, sync.values[:, 0], channel=SYNC_CHANNEL)
    truth = clock.device_ns(sync.edges_ns).astype(np.float64)
    inside = truth[(truth > t_vicon[0] + 1e6) & (truth < t_vicon[-1] - 1e6)]
    assert edges.count == inside.size
    err = edges.t_ns - inside
    assert float(np.max(np.abs(err))) < 5_000.0  # measured: 1.5 µs
    assert edges.tau_ns == pytest.approx(sync.tau_ns, rel=0.02)
    assert edges.high == pytest.approx(SyncWiring().high_v, abs=0.01)


def test_sync_channel_needs_an_integer_number_of_samples_per_frame() -> None:
    cap, clock = _capture(seconds=1.0)
    with pytest.raises(ValidationError, match="integer multiple of the Vicon frame rate"):
        simulate_sync_channel(
            cap, clock, _pulses(1.0), rng=np.random.default_rng(0), wiring=SyncWiring(2000.0)
        )


def test_simulated_c3d_with_the_sync_channel_reads_back_through_calib(tmp_path: Path) -> None:
    cap, clock = _capture()
    sync = simulate_sync_channel(cap, clock, _pulses(), rng=np.random.default_rng(2))
    path = write_c3d(cap, tmp_path / "s.c3d", analogs=sync)
    an = read_c3d_analogs(path)
    assert an.labels == (SYNC_CHANNEL,)
    assert an.units == ("V",)
    assert (an.rate_hz, an.samples_per_frame, an.first_frame) == (2400.0, 20, cap.start_field)
    np.testing.assert_allclose(an.values, sync.values, atol=1e-6)
    n = (cap.start_field - 1) * 20 + np.arange(an.n_samples)
    np.testing.assert_array_equal(analog_times_ns(an), np.round(n * (1e9 / 2400.0)))
    traj = read_c3d(path)
    plain = read_c3d(write_c3d(cap, tmp_path / "p.c3d"))
    np.testing.assert_array_equal(traj.positions_m, plain.positions_m)


def test_a_session_without_d415_has_no_analog_channel(tmp_path: Path) -> None:
    res = simulate_session(tmp_path, seed=0, seconds=3.0, truth_rate_hz=100.0)
    assert res.recording is None
    assert read_c3d_analogs(res.c3d_path).n_channels == 0
    assert not (tmp_path / "truth" / "vicon_sync.npz").exists()


@pytest.mark.slow
def test_recorded_session_sync_edges_are_the_recorded_master_frames(tmp_path: Path) -> None:
    """Every master frame recorded while the Vicon captured has its edge, 2 µs after the pulse
    (the frame's mid-exposure stamp minus half the exposure, mapped by the true clocks)."""
    res = simulate_session(tmp_path, seed=1, seconds=3.0, devices=("d415",), cameras=1)
    assert res.recording is not None
    truth = read_truth(tmp_path)
    an = read_c3d_analogs(res.c3d_path)
    edges = find_sync_edges(analog_times_ns(an), an.channel(SYNC_CHANNEL), channel=SYNC_CHANNEL)
    with Recording(tmp_path / "session.mcap") as rec:
        serial = next(t.split("/")[2] for t in rec.topics if t.startswith("/d415/"))
        exposure_us = float(rec.metadata()[f"device/d415/{serial}"]["options.exposure_us"])
        stamps = np.array(
            [fi.sensor_timestamp_us for _, fi in rec.decoded(topic("d415", serial, "frame_info"))],
            dtype=np.int64,
        )
    dev, vic = truth.clocks["d415-0"], truth.clocks["vicon"]
    pulse_session = dev.session_ns((stamps * 1000 - round(exposure_us * 500)), unit_ns=1)
    pulse_vicon = vic.device_ns(pulse_session).astype(np.float64)
    t = analog_times_ns(an)
    inside = pulse_vicon[(pulse_vicon > t[0] + 2e6) & (pulse_vicon < t[-1] - 2e6)]
    k = np.clip(np.searchsorted(edges.t_ns, inside), 1, edges.count - 1)
    k = np.where(np.abs(edges.t_ns[k - 1] - inside) < np.abs(edges.t_ns[k] - inside), k - 1, k)
    err = edges.t_ns[k] - inside - 2_000.0
    assert inside.size > 70
    # 5 µs stamp jitter, µs flooring, 1 µs latency jitter: measured max 12.6 µs, mean −0.3 µs.
    assert float(np.max(np.abs(err))) < 30_000.0
    assert abs(float(np.mean(err))) < 3_000.0
    sync_truth = np.load(tmp_path / "truth" / "vicon_sync.npz")
    np.testing.assert_array_equal(sync_truth["pulse_ns"], res.recording.sync_pulses_ns)
    assert str(sync_truth["channel"]) == SYNC_CHANNEL
