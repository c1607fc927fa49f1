"""Time alignment (calib/time_align.py) against the simulated world's clocks and claps."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from mocaprig.calib.calibration import ClockMapping
from mocaprig.calib.markers import MarkerFrame
from mocaprig.calib.time_align import (
    ClapDetection,
    clock_from_claps,
    clock_from_pulses,
    find_claps_d415,
    find_claps_davis,
    find_claps_vicon,
    refine_by_reprojection,
    refine_by_speed,
    speed_from_frames,
    speed_from_trajectories,
    vicon_times_ns,
)
from mocaprig.calib.vicon import MarkerTrajectories, read_trajectories
from mocaprig.drivers_mock.clock import DeviceClock
from mocaprig.drivers_mock.scenario import Scenario, build_scenario
from mocaprig.drivers_mock.vicon import ViconCapture, simulate_vicon, write_c3d
from mocaprig.errors import CalibrationError, ValidationError
from tests.calib.test_markers import render_frames


def _trajectories(cap: ViconCapture, *, scale: float = 1.0) -> MarkerTrajectories:
    res = np.where(cap.residuals_mm < 0, np.nan, cap.residuals_mm / 1000.0)
    return MarkerTrajectories(
        labels=cap.labels,
        rate_hz=cap.rate_hz,
        positions_m=cap.points_m * scale,
        residuals_m=res,
        first_frame=cap.start_field,
    )


def _truth_mapping_error_ns(
    m: ClockMapping, dev: DeviceClock, ref: DeviceClock, t_dev_ns: int
) -> tuple[float, float]:
    """(offset error at t_dev (ns), drift error (ppm)) of a mapping against the true clocks."""
    truth = ref.offset_ns + (t_dev_ns - dev.offset_ns) / dev.rate * ref.rate
    est = float(m.to_reference_ns(np.array([t_dev_ns]))[0])
    return est - truth, m.drift_ppm - (ref.rate / dev.rate - 1.0) * 1e6


@pytest.fixture(scope="module")
def vicon_sessions() -> list[tuple[Scenario, ViconCapture]]:
    out = []
    for seed in range(3):
        sc = build_scenario("default", seed=seed, seconds=5)
        out.append((sc, simulate_vicon(sc)))
    return out


# ------------------------------------------------------------------------------- Vicon


def test_vicon_times_follow_the_vicon_frame_clock(
    vicon_sessions: list[tuple[Scenario, ViconCapture]],
) -> None:
    sc, cap = vicon_sessions[0]
    t = vicon_times_ns(_trajectories(cap))
    truth = sc.clocks["vicon"].device_ns(cap.frame_t_ns)
    assert np.max(np.abs(t - truth)) <= 1


def test_find_claps_vicon_locates_both_contacts_sub_frame(
    vicon_sessions: list[tuple[Scenario, ViconCapture]],
) -> None:
    errors = []
    for sc, cap in vicon_sessions:
        claps = find_claps_vicon(_trajectories(cap))
        truth = sc.clocks["vicon"].device_ns(np.array(sc.clap_times_ns))
        assert len(claps) == 2
        for c, t in zip(claps, truth, strict=True):
            assert c.device == "vicon"
            assert c.curve.size == c.curve_t_ns.size > 10
            errors.append(abs(c.t_ns - int(t)))
            assert abs(c.t_ns - int(t)) < max(4.0 * c.sigma_ns, 0.5e6)
    # A 120 Hz frame is 8.3 ms; the fitted contact is good to a fraction of a millisecond.
    assert np.mean(errors) < 0.6e6
    assert np.max(errors) < 1.5e6


def test_find_claps_vicon_reads_a_c3d(
    vicon_sessions: list[tuple[Scenario, ViconCapture]], tmp_path: Path
) -> None:
    sc, cap = vicon_sessions[1]
    path = write_c3d(cap, tmp_path / "session.c3d")
    claps = find_claps_vicon(read_trajectories(path))
    truth = sc.clocks["vicon"].device_ns(np.array(sc.clap_times_ns))
    assert np.max(np.abs(np.array([c.t_ns for c in claps]) - truth)) < 1.5e6


def test_find_claps_vicon_explains_what_it_saw(
    vicon_sessions: list[tuple[Scenario, ViconCapture]],
) -> None:
    _, cap = vicon_sessions[0]
    traj = _trajectories(cap)
    # Clapper held closed: the TOP marker replaced by BOTTOM + contact offset.
    pos = np.array(traj.positions_m)
    i_top, i_bot = traj.index("clapper:TOP"), traj.index("clapper:BOTTOM")
    pos[:, i_top] = pos[:, i_bot] + np.array([0.0, 0.0, 0.034])
    closed = MarkerTrajectories(
        traj.labels, traj.rate_hz, pos, traj.residuals_m, traj.first_frame, source="s.c3d"
    )
    with pytest.raises(
        CalibrationError, match=r"no clap in s\.c3d.*clapper:TOP/clapper:BOTTOM.*34 mm"
    ):
        find_claps_vicon(closed)
    # Millimetre numbers handed over as metres.
    with pytest.raises(CalibrationError, match="wrong units"):
        find_claps_vicon(_trajectories(cap, scale=1000.0))
    with pytest.raises(CalibrationError, match="not found"):
        find_claps_vicon(traj, labels=("clap:A", "clap:B"))


# ------------------------------------------------------------------------------- D415


@pytest.fixture(scope="module")
def d415_clap_frames() -> tuple[Scenario, list[MarkerFrame], int]:
    sc = build_scenario("default", seed=0, seconds=4)
    tc = sc.clap_times_ns[0]
    frames, _ = render_frames(sc, 3, tc - 800_000_000, tc + 250_000_000, phase_ns=7_000_000)
    return sc, frames, 3


def test_find_claps_d415_fits_the_closing_of_unlabelled_markers(
    d415_clap_frames: tuple[Scenario, list[MarkerFrame], int],
) -> None:
    sc, frames, cam = d415_clap_frames
    claps = find_claps_d415(frames)
    assert len(claps) == 1
    clock = sc.clocks[sc.rig.d415[cam].name]
    truth = int(clock.device_ns(np.array([sc.clap_times_ns[0]]))[0])
    err = claps[0].t_ns - truth
    # One 30 Hz frame is 33 ms; the fitted closing puts the contact within a few ms, and the
    # reported sigma covers the error.
    assert abs(err) < 5e6
    assert abs(err) < 3.0 * claps[0].sigma_ns
    assert claps[0].device == frames[0].camera


def _random_frames(n: int, *, seed: int) -> list[MarkerFrame]:
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        uv = rng.uniform(0, 800, (20, 2))
        xyz = np.column_stack([(uv - 400) / 600 * 2.5, np.full(20, 2.5)])
        out.append(MarkerFrame("d415/1", k * 33_333_333, k, uv, xyz, np.full(20, 9.0)))
    return out


def test_find_claps_d415_says_where_it_looked_when_there_is_no_clapper() -> None:
    with pytest.raises(CalibrationError, match=r"no clap in d415/1: looked for the clapperboard"):
        find_claps_d415(_random_frames(40, seed=1))
    with pytest.raises(CalibrationError, match="only 3 marker frames"):
        find_claps_d415(_random_frames(3, seed=1))


# ------------------------------------------------------------------------------ clocks


def _clap(device: str, t_ns: int, sigma_ns: float = 1e5) -> ClapDetection:
    return ClapDetection(device, t_ns, sigma_ns, 1.0, np.zeros(0, np.int64), np.zeros(0))


def test_clock_from_claps_recovers_offset_and_drift_from_two_claps() -> None:
    dev = DeviceClock("d415-0", offset_ns=123_456_789_000, drift_ppm=31.0)
    ref = DeviceClock("vicon", offset_ns=9_876_543_210, drift_ppm=-4.0, unit_ns=1)
    claps = np.array([1_800_000_000, 58_500_000_000])
    m = clock_from_claps(
        "d415/1",
        [_clap("d415/1", int(t)) for t in dev.device_ns(claps)],
        [_clap("vicon", int(t)) for t in ref.device_ns(claps)],
    )
    err_ns, err_ppm = _truth_mapping_error_ns(m, dev, ref, int(dev.device_ns(np.array([30e9]))[0]))
    assert abs(err_ns) < 2
    assert abs(err_ppm) < 0.01
    assert m.method == "clap"
    assert m.reference == "vicon"
    assert math.isfinite(m.offset_sigma_ns)
    assert math.isfinite(m.drift_sigma_ppm)


def test_clock_from_claps_pairs_unequal_lists_and_warns_on_a_single_pair(
    caplog: pytest.LogCaptureFixture,
) -> None:
    dev = [_clap("d", 5_000_000_000)]
    ref = [_clap("vicon", 1_000_000_000), _clap("vicon", 60_000_000_000)]
    with caplog.at_level(logging.WARNING):
        m = clock_from_claps("d", dev, ref)
    assert m.drift_ppm == 0.0
    assert math.isnan(m.drift_sigma_ppm)
    assert m.offset_ns in (-4_000_000_000, 55_000_000_000)
    assert "offset only" in caplog.text
    # Three device claps, two of them match the reference's spacing.
    dev3 = [_clap("d", t) for t in (1_000, 20_000_000_000, 59_000_000_000)]
    ref2 = [_clap("vicon", t + 7_000_000) for t in (1_000, 59_000_000_000)]
    m3 = clock_from_claps("d", dev3, ref2)
    assert m3.offset_ns == pytest.approx(7_000_000, abs=2)
    with pytest.raises(CalibrationError, match="need at least one"):
        clock_from_claps("d", [], ref)


def test_clock_from_claps_refuses_an_implausible_drift() -> None:
    dev = [_clap("d", 0), _clap("d", 1_000_000)]  # 1 ms apart on the device
    ref = [_clap("vicon", 0), _clap("vicon", 30_000_000)]  # but 30 ms on the reference
    with pytest.raises(CalibrationError, match="ppm"):
        clock_from_claps("d", dev, ref, pair_tol_ns=100_000_000)


# ------------------------------------------------------------------------------ speed


def test_refine_by_speed_brings_a_clap_prior_within_a_few_ms(
    vicon_sessions: list[tuple[Scenario, ViconCapture]],
) -> None:
    """Device speeds from the true markers at 30 Hz (with noise) against the Vicon's speeds."""
    for seed, (sc, cap) in enumerate(vicon_sessions):
        rng = np.random.default_rng(seed)
        traj = _trajectories(cap)
        body = [x for x in traj.labels if x.startswith("actor:")]
        ref_t, ref_v = speed_from_trajectories(traj, labels=body)
        dev = DeviceClock(
            "d415-0", offset_ns=777_000_000_000, drift_ppm=float(rng.uniform(-50, 50))
        )
        vicon = sc.clocks["vicon"]
        # Frame k's displacement speed between consecutive 30 Hz frames (session times).
        t_frames = np.arange(int(0.3e9), int(sc.duration_ns - 0.3e9), 33_333_333, dtype=np.int64)
        pos = sc.markers_m(t_frames)
        v = np.linalg.norm(np.diff(pos, axis=0), axis=2).mean(axis=1) / (1 / 30)
        v = v + rng.normal(0.0, 0.02, v.shape)
        t_mid = (t_frames[1:] + t_frames[:-1]) // 2
        dev_t = dev.device_ns(t_mid)
        # A clap-grade prior: 8 ms and 40 ppm off.
        truth_off = int(vicon.device_ns(np.array([t_mid[0]]))[0]) - int(dev_t[0])
        prior = ClockMapping(
            "d415/x",
            "vicon",
            truth_off + 8_000_000,
            (vicon.rate / dev.rate - 1) * 1e6 + 40.0,
            int(dev_t[0]),
            method="clap",
        )
        m = refine_by_speed(prior, dev_t, v, ref_t, ref_v)
        mid = int(dev_t[dev_t.size // 2])
        err_ns, err_ppm = _truth_mapping_error_ns(m, dev, vicon, mid)
        # The speed signals of the two devices differ in shape (frame differences vs central
        # differences of noisy positions), which leaves a bias of a few milliseconds on a 5 s
        # session: the speed correlation is a prior for refine_by_reprojection, not the answer.
        assert abs(err_ns) < 3e6, f"seed {seed}: offset error {err_ns / 1e6:.3f} ms"
        # A 5 s session cannot tell drift: the correction stays within its prior.
        assert abs(err_ppm) < 45.0, f"seed {seed}: drift error {err_ppm:.1f} ppm"
        assert m.method == "clap+xcorr"


def _projected_frames(
    sc: Scenario, cam: int, t_session: npt.NDArray[np.int64], *, noise_px: float, seed: int
) -> list[MarkerFrame]:
    """Marker frames of one D415 made by projecting the true markers (blob-detector noise)."""
    from mocaprig.drivers_mock.rig import project

    rng = np.random.default_rng(seed)
    spec = sc.rig.d415[cam]
    clock = sc.clocks[spec.name]
    out = []
    for k, t in enumerate(t_session):
        w = sc.sample(np.array([t]))
        pts = np.concatenate([w.markers_m[0], w.clapper_m[0]])
        uv, z = project(spec.ir_left, pts)
        ok = np.isfinite(uv).all(axis=1) & (z > 0)
        uv = uv[ok] + rng.normal(0.0, noise_px, (int(ok.sum()), 2))
        xyz = np.column_stack([uv, z[ok]])  # depth unused by the refinement
        area = np.pi * (spec.ir_left.fx * 0.007 / z[ok]) ** 2  # a whole 7 mm marker's disc
        t_dev = int(clock.device_ticks(np.array([t]))[0]) * 1000
        out.append(MarkerFrame("d415/x", t_dev, k, uv, xyz, area))
    return out


@pytest.mark.slow
def test_refine_by_reprojection_pins_offset_and_drift() -> None:
    sc = build_scenario("default", seed=3, seconds=20)
    cap = simulate_vicon(sc)
    traj = _trajectories(cap)
    spec = sc.rig.d415[1]
    dev, vicon = sc.clocks[spec.name], sc.clocks["vicon"]
    t = np.arange(int(0.4e9), int(19.6e9), 100_000_000, dtype=np.int64)
    frames = _projected_frames(sc, 1, t, noise_px=0.2, seed=3)
    mid = frames[len(frames) // 2].t_dev_ns
    truth_off = vicon.offset_ns + (mid - dev.offset_ns) / dev.rate * vicon.rate - mid
    # A clap-grade prior: 6 ms and 60 ppm off.
    prior = ClockMapping(
        "d415/x",
        "vicon",
        round(truth_off) + 6_000_000,
        (vicon.rate / dev.rate - 1) * 1e6 + 60.0,
        mid,
        3e6,
        60.0,
        "clap",
    )
    m = refine_by_reprojection(prior, frames, traj, spec.ir_left.K, spec.ir_left.T_world_cam)
    assert m.method == "clap+reproj"
    # Measured over 20 s with 0.2 px blob noise and the Vicon's 0.5 mm noise: ≈ 0.1 ms and
    # 5–16 ppm (the drift is the weak part; see docs/calibration.md).
    for tt in (frames[0].t_dev_ns, mid, frames[-1].t_dev_ns):
        err_ns, err_ppm = _truth_mapping_error_ns(m, dev, vicon, tt)
        assert abs(err_ns) < 250_000, f"{err_ns / 1e3:.1f} µs"
    assert abs(err_ppm) < 25.0
    assert m.offset_sigma_ns < 50_000
    wrong = np.array(spec.ir_left.T_world_cam)
    wrong[:3, 3] += 0.5  # extrinsics off by half a metre
    with pytest.raises(CalibrationError, match="project within"):
        refine_by_reprojection(prior, frames, traj, spec.ir_left.K, wrong)


def test_refine_by_speed_refuses_signals_that_do_not_match() -> None:
    rng = np.random.default_rng(4)
    t = np.arange(0, 20_000_000_000, 33_333_333, dtype=np.int64)
    tr = np.arange(0, 20_000_000_000, 8_333_333, dtype=np.int64)
    m = ClockMapping("d", "vicon", 0)
    with pytest.raises(CalibrationError, match="correlation"):
        refine_by_speed(m, t, rng.random(t.size), tr, rng.random(tr.size))
    with pytest.raises(ValidationError, match="increasing"):
        refine_by_speed(m, t[::-1], np.ones(t.size), tr, np.ones(tr.size))


def test_speed_from_frames_measures_lateral_speed() -> None:
    rng = np.random.default_rng(5)
    base = rng.uniform(100, 700, (15, 2))
    frames = []
    f_px, z = 600.0, 2.0
    for k in range(10):
        uv = base + np.array([3.0 * k, 0.0])  # 3 px per frame at 2 m, 30 Hz
        xyz = np.column_stack([(uv - [424, 240]) / f_px * z, np.full(15, z)])
        frames.append(MarkerFrame("c", k * 33_333_333, k, uv, xyz, np.full(15, 9.0)))
    t, v = speed_from_frames(frames)
    assert t.size == 9
    assert np.allclose(v, 3.0 * z / f_px * 30.0, rtol=1e-3)


# ------------------------------------------------------------------------------ pulses


def _pulse_train(
    seed: int, *, drops: bool = True
) -> tuple[DeviceClock, DeviceClock, npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """DAVIS rising edges (DAVIS ns, µs ticks) of the D415 master's pulses, and the master's
    frame stamps (mid-exposure, µs ticks), as the mocks make them; with drops on both sides."""
    rng = np.random.default_rng(seed)
    davis = DeviceClock(
        "davis", int(rng.uniform(0.5e9, 20e9)), float(rng.uniform(-30, 30)), 1.0, seed=seed
    )
    master = DeviceClock(
        "d415-0", int(rng.uniform(10e9, 3000e9)), float(rng.uniform(-50, 50)), 5.0, seed=seed + 1
    )
    period = 1e9 / 30
    k0 = math.ceil(master.device_ns(np.array([0]))[0] / period)
    k = np.arange(k0, k0 + 900)
    pulse_master = np.round(k * period).astype(np.int64)
    pulse_session = master.session_ns(pulse_master, unit_ns=1)
    edges = davis.device_ticks(pulse_session) * 1000
    frames = master.device_ticks(pulse_session + 4_250_000) * 1000  # exposure 8.5 ms
    if drops:
        keep_e = rng.random(edges.size) > 0.03
        keep_f = rng.random(frames.size) > 0.03
        edges, frames = edges[keep_e], frames[keep_f]
    return davis, master, edges, frames


@pytest.mark.parametrize("seed", range(5))
def test_clock_from_pulses_maps_davis_within_50_us(seed: int) -> None:
    davis, master, edges, frames = _pulse_train(seed)
    vicon = DeviceClock("vicon", 123_000_000_000, 3.0, unit_ns=1)
    # The master's mapping onto Vicon, exact here, so the error is the pulses' alone.
    m_d415 = ClockMapping(
        "d415/m",
        "vicon",
        int(vicon.offset_ns - master.offset_ns / master.rate * vicon.rate),
        (vicon.rate / master.rate - 1) * 1e6,
        0,
    )
    prior = int(frames[0] - 4_250_000 - edges[0]) + 3_000_000  # a clap-grade prior, 3 ms off
    m = clock_from_pulses(
        "davis/1",
        edges,
        frames,
        d415_mapping=m_d415,
        frame_delay_ns=4_250_000,
        prior_offset_ns=prior,
    )
    assert m.method == "pulses"
    assert m.reference == "vicon"
    for t_s in (1e9, 15e9, 29e9):
        t_dev = int(davis.device_ns(np.array([int(t_s)]))[0])
        err_ns, _ = _truth_mapping_error_ns(m, davis, vicon, t_dev)
        assert abs(err_ns) < 50_000, f"{err_ns / 1e3:.1f} µs at {t_s / 1e9:.0f} s"
    _, err_ppm = _truth_mapping_error_ns(m, davis, vicon, int(edges[0]))
    assert abs(err_ppm) < 2.0
    # Without a prior the whole-period shift cannot be told.
    with pytest.raises(CalibrationError, match="ambiguous by whole periods"):
        clock_from_pulses("davis/1", edges, frames, d415_mapping=m_d415)


def test_clock_from_pulses_refuses_foreign_trains() -> None:
    _, _, edges, frames = _pulse_train(0, drops=False)
    m = ClockMapping("d415/m", "vicon", 0)
    prior = int(frames[0] - edges[0])
    with pytest.raises(CalibrationError, match="not the frame pulse"):
        clock_from_pulses("davis/1", edges[::2], frames, d415_mapping=m, prior_offset_ns=prior)
    with pytest.raises(CalibrationError, match="at least 10"):
        clock_from_pulses("davis/1", edges[:5], frames, d415_mapping=m, prior_offset_ns=prior)
    with pytest.raises(CalibrationError, match="pair with a frame"):
        clock_from_pulses(
            "davis/1", edges, frames, d415_mapping=m, prior_offset_ns=prior + 16_000_000
        )


# ------------------------------------------------------------------------------- DAVIS


def test_find_claps_davis_needs_events() -> None:
    from mocaprig.acquire.events import make_events

    ev = make_events(np.arange(10), np.zeros(10), np.zeros(10), np.ones(10))
    with pytest.raises(CalibrationError, match="only 10 events"):
        find_claps_davis(ev)
