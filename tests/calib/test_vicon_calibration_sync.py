"""``calibrate_vicon`` with the Vicon sync channel (D415_SYNC) on a short simulated session, and
without it (the video clocks and a note)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocaprig.calib.vicon import MarkerTrajectories, read_c3d, read_c3d_analogs, write_c3d
from mocaprig.calib.vicon_calibration import (
    CalibrationOptions,
    ViconCalibrationResult,
    _sync_channel_edges,
    calibrate_vicon,
    evaluate_calibration,
)


@pytest.fixture(scope="module")
def session(rig_session: Path) -> Path:
    """The shared 6 s session (seed 5, two D415s and the DAVIS; tests/conftest.py): recording,
    Vicon C3D with the D415_SYNC channel, truth. 6 s rather than 4 s: a slave is tied to the
    master by frame counters only over ≥ 5 s of frames."""
    return rig_session


@pytest.fixture(scope="module")
def with_sync(session: Path) -> ViconCalibrationResult:
    return calibrate_vicon(session / "session.mcap", session / "vicon" / "session.c3d")


@pytest.mark.slow
def test_the_sync_channel_gives_every_d415_its_clock_to_microseconds(
    session: Path, with_sync: ViconCalibrationResult
) -> None:
    clocks = {k.device: k for k in with_sync.calibration.clocks if k.device.startswith("d415/")}
    assert len(clocks) == 2
    methods = sorted(k.method for k in clocks.values())
    assert methods[0] == "sync channel D415_SYNC"
    assert methods[1].startswith("sync channel D415_SYNC via d415/")
    assert any("from the Vicon sync channel 'D415_SYNC'" in n for n in with_sync.notes)
    ev = evaluate_calibration(with_sync.calibration, session)
    d415 = [d for d in ev.devices if d.device.startswith("d415/")]
    assert len(d415) == 2
    for d in d415:
        # Measured (6 s, seed 5, with the DAVIS): offsets +0.2 / +1.2 µs, drifts +0.31 / +0.11
        # ppm (σ 0.21 ppm). The video clocks of a D415-only session: −123 / −46 µs, +197 ppm.
        assert abs(d.clock_offset_error_ms) < 0.02, d
        assert abs(d.drift_error_ppm) < 1.0, d
        assert d.rotation_error_deg < 0.1, d
        assert d.translation_error_mm < 2.0, d
    for k in clocks.values():
        assert k.offset_sigma_ns < 10_000.0
        assert k.drift_sigma_ppm < 1.0


@pytest.mark.slow
def test_without_the_channel_the_clocks_come_from_the_video_with_a_note(
    session: Path, tmp_path: Path
) -> None:
    plain = write_c3d(tmp_path / "no_sync.c3d", read_c3d(session / "vicon" / "session.c3d"))
    assert read_c3d_analogs(plain).n_channels == 0
    result = calibrate_vicon(session / "session.mcap", plain)
    d415 = [k for k in result.calibration.clocks if k.device.startswith("d415/")]
    assert len(d415) == 2
    assert all(k.method.startswith("reprojection") for k in d415)
    assert any("no analog channel 'D415_SYNC'" in n and "video" in n for n in result.notes)
    ev = evaluate_calibration(result.calibration, session)
    assert all(abs(d.clock_offset_error_ms) < 1.0 for d in ev.devices)


def test_an_absent_disabled_or_unreadable_channel_is_a_note_not_an_error(tmp_path: Path) -> None:
    pos = np.random.default_rng(0).uniform(-1.0, 1.0, (5, 2, 3))
    path = write_c3d(tmp_path / "t.c3d", MarkerTrajectories(("a", "b"), 120.0, pos, pos[..., 0]))
    edges, note = _sync_channel_edges(path, CalibrationOptions())
    assert edges is None
    assert "no analog channel 'D415_SYNC'" in note
    assert "docs/wiring.md" in note
    edges, note = _sync_channel_edges(path, CalibrationOptions(sync_channel=None))
    assert edges is None
    assert "not used" in note
    csv = tmp_path / "t.csv"
    csv.write_text("Trajectories\n100\n", encoding="utf-8")
    edges, note = _sync_channel_edges(csv, CalibrationOptions())
    assert edges is None
    assert "a Nexus CSV export holds no analog channel" in note
    garbage = tmp_path / "g.c3d"
    garbage.write_bytes(b"\x00" * 2048)
    edges, note = _sync_channel_edges(garbage, CalibrationOptions())
    assert edges is None
    assert note.startswith("clock: no sync channel: ")
    assert "video" in note


def test_sync_clocks_fix_a_prior_a_period_out_and_map_a_slave_through_its_tie() -> None:
    """The master's video prior 41 ms off (more than a quarter period): the edges pair one
    period out and the reprojection score (here: the true error) moves it back; a slave tied to
    the master by frame counters gets the master's clock plus its 100 µs trigger delay."""
    from mocaprig.calib.calibration import ClockMapping
    from mocaprig.calib.time_align import find_sync_edges
    from mocaprig.calib.vicon_calibration import _sync_clocks, _SyncInputs, _Tie
    from tests.calib.test_sync_channel import _prior, _rig

    rig = _rig(11)
    edges = find_sync_edges(rig.t_ns, rig.volts, channel="D415_SYNC")
    s_off, s_rate, delay = 2.2e12, 1.0 + 17e-6, 100_000.0

    def slave_truth(t_c: float) -> float:
        return rig.vic_offset_ns + (t_c - s_off) / s_rate * rig.vic_rate

    def master_stamp(t_c: float) -> float:  # the master's stamp of the slave stamp's frame
        return rig.dev_offset_ns + rig.dev_rate * ((t_c - s_off) / s_rate - delay)

    centre = s_off + 15e9 * s_rate
    tie = _Tie(
        master_stamp(centre) - centre,
        rig.dev_rate / s_rate - 1.0,
        centre,
        300,
        5_000.0,
        0,
    )
    truths = {"m": rig.true_mapping, "s": slave_truth}
    mid = {"m": float(np.median(rig.frames_dev_ns)), "s": centre}

    def error_ns(name: str, m: ClockMapping) -> float:
        t = mid[name]
        return abs(float(m.to_reference_ns(np.array([round(t)]))[0]) - truths[name](t))

    prior_m = _prior(rig, offset_err_ns=41e6, drift_err_ppm=5.0)
    prior_s = ClockMapping("s", "vicon", round(slave_truth(centre) - centre), 0.0, round(centre))
    sync = _SyncInputs(edges, "m", rig.frames_dev_ns, 4_250_000, {"s": delay})
    out, notes = _sync_clocks(
        sync,
        {"m": prior_m, "s": prior_s},
        {"m": _Tie(0.0, 0.0, 0.0, 300, 0.0, 0), "s": tie},
        CalibrationOptions(),
        error_ns,
    )
    assert error_ns("m", out["m"]) < 5_000.0
    assert error_ns("s", out["s"]) < 5_000.0
    assert out["s"].drift_ppm == pytest.approx((rig.vic_rate / s_rate - 1.0) * 1e6, abs=0.3)
    assert out["s"].method == "sync channel D415_SYNC via m (frame tie)"
    assert any("whole edge periods chosen by the reprojection cost" in n for n in notes)
    # Without the score the period stays wrong (what the fix is for).
    out2, _ = _sync_clocks(sync, {"m": prior_m, "s": prior_s}, {}, CalibrationOptions())
    assert error_ns("m", out2["m"]) > 30e6
    assert out2["s"] is prior_s  # no tie: the video clock stays
