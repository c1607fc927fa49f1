"""The simulated Vicon capture on synthetic trajectories, and its C3D/CSV exports."""

from __future__ import annotations

import csv

import ezc3d
import numpy as np
import numpy.typing as npt
import pytest

from mocaprig.drivers_mock.clock import DeviceClock
from mocaprig.drivers_mock.noise import NoiseSettings
from mocaprig.drivers_mock.rig import ViconSpec
from mocaprig.drivers_mock.vicon import (
    ViconCapture,
    capture_markers,
    vicon_frame_times_ns,
    write_c3d,
    write_nexus_csv,
)

SECOND = 1_000_000_000


def _circle(t_ns: npt.NDArray[np.int64]) -> tuple[npt.NDArray[np.float64], None]:
    t = t_ns.astype(float) * 1e-9
    rings = [
        np.stack([np.cos(t + k), np.sin(t + k), np.full_like(t, 1.0 + 0.05 * k)], -1)
        for k in range(20)
    ]
    return np.stack(rings, axis=1), None


def _capture(
    noise: NoiseSettings | None = None, seed: int = 0, seconds: int = 10
) -> tuple[ViconCapture, DeviceClock]:
    clock = DeviceClock("vicon", offset_ns=round(12_345 * 1e9 / 120), drift_ppm=7.0, unit_ns=1)
    return capture_markers(
        _circle,
        [f"s:M{k}" for k in range(20)],
        spec=ViconSpec(),
        clock=clock,
        start_ns=SECOND // 10,
        end_ns=seconds * SECOND,
        noise=NoiseSettings() if noise is None else noise,
        rng=np.random.default_rng(seed),
    ), clock


def test_frames_are_120_hz_in_the_vicon_clock_and_start_at_the_first_frame_after_start() -> None:
    clock = DeviceClock("vicon", offset_ns=round(500 * 1e9 / 120), drift_ppm=-8.0, unit_ns=1)
    n0, t = vicon_frame_times_ns(clock, rate_hz=120.0, start_ns=SECOND // 10, end_ns=3 * SECOND)
    assert t[0] >= SECOND // 10
    assert t[-1] <= 3 * SECOND
    dev = clock.device_ns(t)
    np.testing.assert_allclose(dev, np.round((n0 + np.arange(t.size)) * 1e9 / 120), atol=1)
    # In session time the period carries the drift.
    period = np.mean(np.diff(t))
    assert period == pytest.approx(1e9 / 120 / (1 + (-8.0e-6)), abs=0.5)


def test_noise_and_gaps_have_the_stated_statistics() -> None:
    cap, _ = _capture(seconds=60)
    err = cap.points_m - cap.clean_m
    rms = np.sqrt(np.nanmean(err**2))
    assert rms == pytest.approx(0.0005, rel=0.05)
    assert 0.006 < cap.gap_fraction < 0.015
    gaps = np.isnan(cap.points_m[..., 0])
    np.testing.assert_array_equal(gaps, cap.residuals_mm < 0)
    assert np.all(cap.residuals_mm[~gaps] > 0)
    assert np.mean(cap.residuals_mm[~gaps]) == pytest.approx(0.8, abs=0.05)
    runs = []
    for col in gaps.T.astype(int):
        d = np.diff(np.r_[0, col, 0])
        runs += list(np.flatnonzero(d == -1) - np.flatnonzero(d == 1))
    assert min(runs) >= 1
    assert max(runs) <= 70 + 70
    assert np.median(runs) < 20  # mostly short


def test_noise_free_settings_give_the_clean_trajectories() -> None:
    cap, _ = _capture(noise=NoiseSettings.none(), seconds=3)
    np.testing.assert_array_equal(cap.points_m, cap.clean_m)


def test_c3d_round_trip_through_ezc3d(tmp_path) -> None:
    cap, _ = _capture(seconds=3)
    path = write_c3d(cap, tmp_path / "t.c3d", subject="s")
    c3d = ezc3d.c3d(str(path))
    params = c3d["parameters"]
    assert params["POINT"]["UNITS"]["value"] == ["mm"]
    assert params["POINT"]["RATE"]["value"][0] == 120.0
    assert params["POINT"]["SCALE"]["value"][0] < 0  # float storage
    assert params["POINT"]["LABELS"]["value"] == list(cap.labels)
    assert params["MANUFACTURER"]["COMPANY"]["value"] == ["mocaprig"]
    assert params["MANUFACTURER"]["SOFTWARE"]["value"] == ["simulated Vicon"]
    low, high = (int(v) for v in params["TRIAL"]["ACTUAL_START_FIELD"]["value"])
    assert (low & 0xFFFF) + (high << 16) == cap.start_field == 12_345 + 13 + 1
    pts = np.transpose(c3d["data"]["points"][:3], (2, 1, 0)) / 1000.0
    np.testing.assert_allclose(pts, cap.points_m, atol=1e-7, equal_nan=True)
    res = c3d["data"]["meta_points"]["residuals"][0].T
    np.testing.assert_allclose(res, cap.residuals_mm, atol=1e-6)


def test_nexus_csv_holds_the_same_values_with_empty_gap_cells(tmp_path) -> None:
    cap, _ = _capture(seconds=3)
    path = write_nexus_csv(cap, tmp_path / "t.csv")
    rows = list(csv.reader(path.open()))
    assert rows[0] == ["Trajectories"]
    assert rows[1] == ["120"]
    assert rows[2][2::3] == list(cap.labels)
    assert rows[3][:5] == ["Frame", "Sub Frame", "X", "Y", "Z"]
    assert rows[4][2] == "mm"
    data = rows[5 : 5 + cap.num_frames]
    assert data[0][0] == "1"
    assert data[-1][0] == str(cap.num_frames)
    values = np.array([[float(v) if v else np.nan for v in r[2:]] for r in data]) / 1000.0
    np.testing.assert_allclose(
        values.reshape(cap.points_m.shape), cap.points_m, atol=1e-8, equal_nan=True
    )


def test_markers_facing_away_from_the_cameras_drop_out_more_often() -> None:
    def sample(
        t_ns: npt.NDArray[np.int64],
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64] | None]:
        pts, _ = _circle(t_ns)
        normals = np.zeros_like(pts)
        normals[:, :10, 2] = 1.0  # facing up, towards the ring of cameras at 2.6 m
        normals[:, 10:, 2] = -1.0  # facing the floor
        return pts, normals

    clock = DeviceClock("vicon", offset_ns=0, drift_ppm=0.0, unit_ns=1)
    cap = capture_markers(
        sample,
        [f"s:M{k}" for k in range(20)],
        spec=ViconSpec(),
        clock=clock,
        start_ns=0,
        end_ns=120 * SECOND,
        noise=NoiseSettings(),
        rng=np.random.default_rng(1),
    )
    gaps = cap.residuals_mm < 0
    assert gaps[:, 10:].mean() > 2.0 * gaps[:, :10].mean()
    assert 0.006 < gaps.mean() < 0.015  # the overall fraction stays on target
