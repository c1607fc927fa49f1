"""The Vicon calibration pipeline's guards, the truth evaluation and the attachment.

The end-to-end run (simulated session → calibrate → evaluate) is in test_commands_calibrate.py.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from scipy.spatial.transform import Rotation

from mocaprig.calib.calibration import Calibration, CameraCalibration, ClockMapping
from mocaprig.calib.vicon import MarkerTrajectories, write_c3d
from mocaprig.calib.vicon_calibration import (
    CalibrationOptions,
    calibrate_vicon,
    evaluate_calibration,
    vicon_static_start,
)
from mocaprig.drivers_mock import build_scenario, look_at
from mocaprig.errors import CalibrationError

F64 = npt.NDArray[np.float64]
U32_NS = (1 << 32) * 1000


def _tpose(seed: int = 0, frames: int = 240) -> tuple[F64, tuple[str, ...]]:
    """A still actor (one T-pose frame held) with 0.5 mm Vicon noise, (F, 53, 3) m."""
    sc = build_scenario("tpose", seed=seed, seconds=3.0)
    ws = sc.sample(np.array([0], dtype=np.int64))
    labels = tuple(f"actor:{n}" for n in sc.marker_names)
    rng = np.random.default_rng(seed)
    held = np.repeat(ws.markers_m, frames, axis=0)
    return held + rng.normal(0, 0.0005, held.shape), labels


def test_static_start_is_found_and_its_cloud_is_the_median() -> None:
    pos, labels = _tpose()
    moving = pos.copy()
    moving[120:] += np.linspace(0, 0.5, 120)[:, None, None]  # everything moves after 1 s
    t = np.arange(len(pos), dtype=np.int64) * 8_333_333
    st = vicon_static_start(moving, labels, t)
    assert 110 <= st.n_frames <= 121
    assert np.allclose(st.cloud_m, np.median(pos[: st.n_frames], axis=0), atol=1e-9)
    assert 0.3 < st.extent_m < 4.0


def test_static_start_refuses_wrong_units() -> None:
    pos, labels = _tpose()
    t = np.arange(len(pos), dtype=np.int64)
    with pytest.raises(CalibrationError, match="units are wrong"):
        vicon_static_start(pos * 1000.0, labels, t)  # millimetres read as metres


def test_static_start_refuses_a_trial_without_one() -> None:
    pos, labels = _tpose()
    walk = pos + np.linspace(0, 2.0, len(pos))[:, None, None]
    with pytest.raises(CalibrationError, match="no static start"):
        vicon_static_start(walk, labels, np.arange(len(pos), dtype=np.int64))


def _trajectories(pos: F64, labels: tuple[str, ...]) -> MarkerTrajectories:
    return MarkerTrajectories(
        labels=labels,
        rate_hz=120.0,
        positions_m=pos,
        residuals_m=np.full(pos.shape[:2], 0.0008),
        first_frame=1000,
    )


def test_calibrate_vicon_says_there_is_no_clap(tmp_path: Path) -> None:
    pos, labels = _tpose()
    c3d = write_c3d(tmp_path / "noclap.c3d", _trajectories(pos, labels))
    with pytest.raises(CalibrationError, match="no clap"):
        calibrate_vicon(tmp_path / "absent.mcap", c3d)


def test_calibrate_vicon_says_a_c3d_in_the_wrong_unit_is_wrong(tmp_path: Path) -> None:
    pos, labels = _tpose()
    # Millimetre values in a file that declares metres (a common export mistake).
    c3d = write_c3d(tmp_path / "mm_as_m.c3d", _trajectories(pos * 1000.0, labels), unit="m")
    with pytest.raises(CalibrationError, match="units are wrong"):
        calibrate_vicon(tmp_path / "absent.mcap", c3d, options=CalibrationOptions())


# ----------------------------------------------------------------------------- evaluation


def _truth_dir(tmp_path: Path) -> tuple[Path, dict[str, object]]:
    T0 = look_at([1.8, 1.8, 1.4], [0, 0, 0.9])
    T1 = look_at([-1.8, 1.8, 1.4], [0, 0, 0.9])
    K = [[623.0, 0.0, 424.0], [0.0, 623.0, 240.0], [0.0, 0.0, 1.0]]
    scen = {
        "duration_ns": 60_000_000_000,
        "rig": {
            "d415": [
                {
                    "name": "d415-0",
                    "serial": "111",
                    "ir_left": {"K": K, "T_world_cam": T0.tolist()},
                },
                {
                    "name": "d415-1",
                    "serial": "222",
                    "ir_left": {"K": K, "T_world_cam": T1.tolist()},
                },
            ],
            "davis": {"name": "davis", "serial": "0246", "camera": {"T_world_cam": T0.tolist()}},
        },
        "clocks": [
            # d415-1's clock has passed its u32 µs wrap (5000 s of uptime > 4295 s).
            {"name": "d415-0", "offset_ns": 2_000_000_000_000, "drift_ppm": 30.0},
            {"name": "d415-1", "offset_ns": 5_000_000_000_000, "drift_ppm": -20.0},
            {"name": "vicon", "offset_ns": 600_000_000_000, "drift_ppm": 5.0},
        ],
    }
    (tmp_path / "truth").mkdir()
    (tmp_path / "truth" / "scenario.json").write_text(json.dumps(scen))
    return tmp_path, scen


def _true_mapping(device: str, off: int, ppm: float, v_off: int, v_ppm: float,
                  wrap: bool) -> ClockMapping:  # fmt: skip
    a, b = ppm * 1e-6, v_ppm * 1e-6
    t_mid = 30_000_000_000
    dev_mid = off + round(t_mid * (1 + a))
    ref_mid = v_off + round(t_mid * (1 + b))
    if wrap:
        dev_mid -= U32_NS
    return ClockMapping(
        device=device,
        reference="vicon",
        offset_ns=ref_mid - dev_mid,
        drift_ppm=((1 + b) / (1 + a) - 1) * 1e6,
        anchor_ns=dev_mid,
    )


def test_evaluate_reports_pose_and_clock_errors_against_truth(tmp_path: Path) -> None:
    root, scen = _truth_dir(tmp_path)
    rig = scen["rig"]
    assert isinstance(rig, dict)
    T0 = np.array(rig["d415"][0]["ir_left"]["T_world_cam"])
    T1 = np.array(rig["d415"][1]["ir_left"]["T_world_cam"])
    bent = T0.copy()
    bent[:3, :3] = Rotation.from_rotvec(np.radians([0.0, 0.0, 0.5])).as_matrix() @ T0[:3, :3]
    bent[:3, 3] += [0.003, 0.0, 0.0]
    K = np.array(rig["d415"][0]["ir_left"]["K"])
    cams = (
        CameraCalibration("d415/111", "d415", "111", 848, 480, K, np.zeros(5), bent),
        CameraCalibration("d415/222", "d415", "222", 848, 480, K, np.zeros(5), T1),
    )
    m0 = _true_mapping("d415/111", 2_000_000_000_000, 30.0, 600_000_000_000, 5.0, False)
    m1 = _true_mapping("d415/222", 5_000_000_000_000, -20.0, 600_000_000_000, 5.0, True)
    m0 = ClockMapping(m0.device, "vicon", m0.offset_ns + 500_000, m0.drift_ppm + 1.0, m0.anchor_ns)
    ev = evaluate_calibration(Calibration(cameras=cams, clocks=(m0, m1)), root)
    by = {d.device: d for d in ev.devices}
    assert by["d415/111"].rotation_error_deg == pytest.approx(0.5, abs=1e-6)
    assert by["d415/111"].translation_error_mm == pytest.approx(3.0, abs=1e-6)
    assert by["d415/111"].clock_offset_error_ms == pytest.approx(0.5, abs=1e-3)
    assert by["d415/111"].drift_error_ppm == pytest.approx(1.0, abs=1e-6)
    assert by["d415/222"].rotation_error_deg == pytest.approx(0.0, abs=1e-6)
    assert by["d415/222"].clock_offset_error_ms == pytest.approx(0.0, abs=1e-3)
    assert ev.missing == ("davis/0246",)
    assert math.isnan(by["d415/222"].drift_error_ppm) is False


def test_evaluate_names_a_folder_without_truth(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match=r"no truth/scenario\.json"):
        evaluate_calibration(Calibration(), tmp_path)


def test_evaluate_scores_a_davis_clock_on_its_reset_time_base(tmp_path: Path) -> None:
    root, _ = _truth_dir(tmp_path)
    # Without truth/davis_clock.json the recorded DAVIS time base is unknown: NaN, not a guess.
    m0 = _true_mapping("d415/111", 2_000_000_000_000, 30.0, 600_000_000_000, 5.0, False)
    reset_ns, ppm = 1_500_000_000, 7.0  # the DAVIS reset 1.5 s into the session
    a, b = ppm * 1e-6, 5e-6
    t_mid = 30_000_000_000
    dav_mid = round((t_mid - reset_ns) * (1 + a))
    ref_mid = 600_000_000_000 + round(t_mid * (1 + b))
    # 20 µs late, mapped through d415/111 whose own mapping is exact.
    drift = ((1 + b) / (1 + a) - 1) * 1e6
    via = "pulses via d415/111"
    dv = ClockMapping("davis/0246", "vicon", ref_mid - dav_mid + 20_000, drift, dav_mid, method=via)
    cal = Calibration(clocks=(m0, dv))
    (d,) = [e for e in evaluate_calibration(cal, root).devices if e.device == "davis/0246"]
    assert math.isnan(d.clock_offset_error_ms)
    (root / "truth" / "davis_clock.json").write_text(
        json.dumps({"device": "davis/0246", "reset_session_ns": reset_ns, "drift_ppm": ppm})
    )
    by = {e.device: e for e in evaluate_calibration(cal, root).devices}
    assert by["davis/0246"].clock_offset_error_ms == pytest.approx(0.020, abs=1e-5)
    assert by["davis/0246"].drift_error_ppm == pytest.approx(0.0, abs=1e-6)
    assert by["davis/0246"].clock_error_vs_via_us == pytest.approx(20.0, abs=0.01)
    assert math.isnan(by["d415/111"].clock_error_vs_via_us)


def test_davis_pulses_refuse_a_train_already_running_at_the_reset() -> None:
    from mocaprig.calib.vicon_calibration import _davis_clock, _DavisPulses

    period = 33_333_333
    frames = 10_000_000_000 + np.arange(60, dtype=np.int64) * period
    master = ClockMapping("d415/111", "vicon", 5_000_000, anchor_ns=int(frames[0]))
    # First edge 10 ms after the reset: the train was already running, pairing is unknowable.
    early = _DavisPulses("davis/0246", 10_000_000 + np.arange(60) * period, "d415/111", 0)
    with pytest.raises(CalibrationError, match="already running"):
        _davis_clock(early, int(frames[0]), frames, master)
    # First edge 100 ms after the reset: edge k is frame k, the mapping is exact.
    late = _DavisPulses("davis/0246", 100_000_000 + np.arange(60) * period, "d415/111", 0)
    m = _davis_clock(late, int(frames[0]), frames, master)
    t = np.array([100_000_000 + 30 * period])
    assert int(m.to_reference_ns(t)[0]) == pytest.approx(frames[30] + 5_000_000, abs=100)
