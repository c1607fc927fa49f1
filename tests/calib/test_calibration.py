"""The calibration file: round trips, clock mappings and the errors a bad file gets."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocaprig.calib.calibration import (
    Calibration,
    CameraCalibration,
    ClockMapping,
    calibration_bytes,
    read_calibration,
    write_calibration,
)
from mocaprig.errors import CalibrationError


def _camera(name: str = "d415/123", seed: int = 0) -> CameraCalibration:
    rng = np.random.default_rng(seed)
    t = np.eye(4)
    t[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    t[:3, 3] = rng.uniform(-4, 4, 3)
    k = np.array([[615.0, 0, 424.5], [0, 615.0, 239.5], [0, 0, 1]])
    return CameraCalibration(
        name=name,
        kind="d415",
        serial=name.split("/")[-1],
        width=848,
        height=480,
        K=k,
        distortion=np.zeros(5),
        T_world_cam=t,
        residuals={"reprojection_rms_px": 0.21, "inliers": 40},
        source="vicon",
    )


def _calibration() -> Calibration:
    return Calibration(
        cameras=(_camera("d415/123", 0), _camera("d415/456", 1)),
        clocks=(
            ClockMapping("d415/123", "vicon", offset_ns=-5_000_123, drift_ppm=12.5,
                         anchor_ns=10**12, offset_sigma_ns=80.0, method="clap+xcorr"),
            ClockMapping("davis/0246", "vicon", offset_ns=42, method="pulses"),
        ),
        statistics={"cameras": 2},
        software_version="0.1.0",
    )  # fmt: skip


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_file_round_trips_exactly(tmp_path: Path, suffix: str) -> None:
    cal = _calibration()
    path = write_calibration(cal, tmp_path / f"calib{suffix}")
    back = read_calibration(path)
    assert [c.name for c in back.cameras] == ["d415/123", "d415/456"]
    for a, b in zip(cal.cameras, back.cameras, strict=True):
        np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
        np.testing.assert_array_equal(a.K, b.K)
        assert a.residuals == b.residuals
    assert back.clocks[0] == cal.clocks[0]
    # NaN uncertainties are left out of the file and come back as NaN.
    assert math.isnan(back.clocks[1].offset_sigma_ns)
    assert back.clock("0246").method == "pulses"


def test_attachment_bytes_read_back() -> None:
    cal = _calibration()
    assert read_calibration(calibration_bytes(cal)).camera("456").serial == "456"


def test_refuses_to_overwrite(tmp_path: Path) -> None:
    path = write_calibration(_calibration(), tmp_path / "c.toml")
    with pytest.raises(CalibrationError, match="exists"):
        write_calibration(_calibration(), path)
    write_calibration(_calibration(), path, overwrite=True)


def test_clock_mapping_inverts_and_applies_drift() -> None:
    m = ClockMapping("d415/1", "vicon", offset_ns=1_000_000, drift_ppm=20.0, anchor_ns=5 * 10**9)
    t = np.array([5 * 10**9, 6 * 10**9, 10**12], dtype=np.int64)
    ref = m.to_reference_ns(t)
    # One second after the anchor, 20 ppm is 20 µs.
    assert ref[1] - ref[0] == 10**9 + 20_000
    np.testing.assert_array_equal(m.from_reference_ns(ref), t)


def test_millimetre_translation_is_refused_with_a_hint() -> None:
    t = np.eye(4)
    t[:3, 3] = (1500.0, 0.0, 2000.0)
    with pytest.raises(CalibrationError, match="metres"):
        CameraCalibration("d415/1", "d415", "1", 848, 480, np.eye(3), np.zeros(5), t)


def test_bad_files_name_the_problem(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("this is = = not toml")
    with pytest.raises(CalibrationError, match="not valid TOML"):
        read_calibration(bad)
    newer = tmp_path / "newer.toml"
    newer.write_text("format_version = 99\n")
    with pytest.raises(CalibrationError, match="upgrade mocaprig"):
        read_calibration(newer)
    missing = tmp_path / "missing.json"
    missing.write_text('{"format_version": 1, "cameras": [{"name": "x"}]}')
    with pytest.raises(CalibrationError, match="lacks the key 'kind'"):
        read_calibration(missing)
    with pytest.raises(CalibrationError, match="no camera 'nope'"):
        _calibration().camera("nope")
