"""Readers of outside data in ``calib`` on the inputs the fuzz campaign found them failing on
(``benchmarks/fuzz_readers.py``): each gives a clean error naming the file."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from mocaprig.calib.calibration import read_calibration
from mocaprig.calib.nexus_csv import read_nexus_csv
from mocaprig.calib.vicon_records import ViconFileError
from mocaprig.errors import CalibrationError


def _csv(tmp_path: Path, rows: list[str]) -> Path:
    head = ["Trajectories", "100", ",,S:a,,", "Frame,Sub Frame,X,Y,Z", ",,mm,mm,mm"]
    p = tmp_path / "t.csv"
    p.write_text("\n".join(head + rows) + "\n\n")
    return p


def test_nexus_csv_infinite_coordinate_names_the_file_and_line(tmp_path: Path) -> None:
    p = _csv(tmp_path, ["1,0,1.0,2.0,3.0", "2,0,1.0,-Infinity,3.0"])
    with pytest.raises(ViconFileError, match=r"t\.csv: .*\(line 7\).*is infinite"):
        read_nexus_csv(p)


def test_nexus_csv_infinite_frame_number_is_refused(tmp_path: Path) -> None:
    p = _csv(tmp_path, ["1,0,1.0,2.0,3.0", "inf,0,1.0,2.0,3.0"])
    with pytest.raises(ViconFileError, match=r"t\.csv: .*frame number 'inf'"):
        read_nexus_csv(p)


def test_nexus_csv_frame_numbers_far_apart_are_refused_without_allocating(tmp_path: Path) -> None:
    p = _csv(tmp_path, ["1,0,1.0,2.0,3.0", "1e12,0,1.0,2.0,3.0"])
    t0 = time.perf_counter()
    with pytest.raises(ViconFileError, match=r"t\.csv: .*run from 1 to 1000000000000 .*damaged"):
        read_nexus_csv(p)
    assert time.perf_counter() - t0 < 1.0


def test_nexus_csv_a_few_absent_rows_are_still_gaps(tmp_path: Path) -> None:
    traj = read_nexus_csv(_csv(tmp_path, ["1,0,1.0,2.0,3.0", "4,0,1.0,2.0,3.0"]))
    assert traj.positions_m.shape == (4, 1, 3)


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_calibration_with_an_infinite_count_names_the_file(tmp_path: Path, suffix: str) -> None:
    cam = {"name": "d415/1", "kind": "d415", "serial": "1", "width": float("-inf"), "height": 480,
           "K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "distortion": [0] * 5,
           "T_world_cam": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}  # fmt: skip
    p = tmp_path / f"cal{suffix}"
    if suffix == ".json":
        import json

        p.write_text(json.dumps({"format_version": 1, "cameras": [cam]}))
    else:
        rows = "\n".join(f"{k} = {v!r}".replace("'", '"') for k, v in cam.items())
        p.write_text("format_version = 1\n[[cameras]]\n" + rows.replace("-inf", "-inf") + "\n")
    with pytest.raises(CalibrationError, match=rf"cal\{suffix}: invalid value"):
        read_calibration(p)
