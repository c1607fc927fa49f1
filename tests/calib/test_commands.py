"""Tests of ``mocaprig vicon info`` through the real dispatcher."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mocaprig.calib.vicon import MarkerTrajectories, write_c3d
from mocaprig.cli import main


@pytest.fixture
def c3d_file(tmp_path: Path) -> Path:
    rng = np.random.default_rng(11)
    pos = rng.uniform(0.0, 1.0, (50, 2, 3))
    pos[10:15, 1] = np.nan
    traj = MarkerTrajectories(
        labels=("Sub:LASI", "Sub:RASI"),
        rate_hz=200.0,
        positions_m=pos,
        residuals_m=np.zeros((50, 2)),
    )
    return write_c3d(tmp_path / "trial.c3d", traj)


def test_info_json_reports_the_summary(c3d_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["vicon", "info", str(c3d_file), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["labels"] == ["Sub:LASI", "Sub:RASI"]
    assert (out["markers"], out["frames"], out["rate_hz"], out["first_frame"]) == (2, 50, 200.0, 1)
    assert out["source_unit"] == "mm"
    assert out["duration_s"] == pytest.approx(0.25)
    assert out["gap_fraction"] == pytest.approx(5 / 100)
    assert 0.0 < out["extent_m"] < np.sqrt(3)
    assert out["software"] == "mocaprig"


def test_info_text_is_a_short_summary(c3d_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["vicon", "info", str(c3d_file)]) == 0
    out = capsys.readouterr().out
    assert "markers:   2" in out
    assert "50 at 200 Hz" in out
    assert "gaps:      5.0 %" in out


def test_info_on_a_broken_file_prints_an_error_and_returns_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.c3d"
    bad.write_bytes(b"\x02\x50" + b"\x00" * 100)
    assert main(["vicon", "info", str(bad)]) == 1
    err = capsys.readouterr().err
    assert "ERROR: " in err
    assert "bad.c3d" in err


def test_info_workstation_csv_needs_unit_flag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "ws.csv"
    path.write_text("TRAJECTORIES,,,\n100,Hz,,\n,LFHD,,\nField #,X,Y,Z\n1,1,2,3\n")
    assert main(["vicon", "info", str(path)]) == 1
    assert "--unit" in capsys.readouterr().err
    assert main(["vicon", "info", str(path), "--unit", "mm", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["source_unit"] == "mm"


def test_info_help_shows_examples(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["vicon", "info", "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert "examples:" in out
    assert "mocaprig vicon info trial.c3d --json" in out


def test_real_file_info_json(shared_data: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = shared_data / "vicon" / "nexus24_markers_analogs.c3d"
    assert main(["vicon", "info", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["markers"], out["frames"], out["rate_hz"]) == (51, 580, 100.0)
    assert out["manufacturer"] == "Vicon"
    assert out["extent_m"] == pytest.approx(1.743, abs=1e-3)
