"""End-to-end tests of `mocaprig calibrate intrinsics | board` on a simulated board recording."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocaprig.calib.calibration import read_calibration
from mocaprig.calib.charuco import CharucoBoardSpec, read_intrinsics, write_board_spec
from mocaprig.cli import main
from mocaprig.drivers_mock.charuco_render import BoardRecording, write_board_recording

SPEC = CharucoBoardSpec(6, 5, 0.15, 0.1125, "DICT_4X4_50")


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, BoardRecording]:
    root = tmp_path_factory.mktemp("charuco")
    board = root / "board.toml"
    write_board_spec(board, SPEC)
    rec = write_board_recording(root / "s.mcap", SPEC, seed=0, intrinsics_views=20, shared_views=16)
    return root, board, rec


def _json(capsys: pytest.CaptureFixture[str]) -> dict[str, object]:
    out = capsys.readouterr().out.strip().splitlines()
    data: dict[str, object] = json.loads(out[-1])
    return data


def test_intrinsics_then_board_calibrate_the_recording_end_to_end(
    session: tuple[Path, Path, BoardRecording], capsys: pytest.CaptureFixture[str]
) -> None:
    root, board, rec = session
    mcap = str(rec.path)
    files = []
    for label, name in rec.labels.items():
        out = root / f"{label.replace('/', '_')}.toml"
        args = ["calibrate", "intrinsics", mcap, "--camera", label, "--board", str(board)]
        assert main([*args, "--out", str(out), "--json"]) == 0
        summary = _json(capsys)
        assert summary["camera"] == label
        truth = rec.rig.camera(name.split("/")[0])
        intr = read_intrinsics(out)
        assert abs(intr.K[0, 0] - truth.fx) / truth.fx < 0.015
        files.append(str(out))
    out = root / "calib.toml"
    args = ["calibrate", "board", mcap, "--board", str(board), "--intrinsics", *files]
    assert main([*args, "--out", str(out), "--json"]) == 0
    summary = _json(capsys)
    assert summary["world_frame"] == next(iter(rec.labels))
    cal = read_calibration(out)
    (d415_label, d415_name), (davis_label, _) = rec.labels.items()
    T_true = np.linalg.inv(rec.rig.camera(d415_name.split("/")[0]).T_world_cam)
    T_true = T_true @ rec.rig.davis.camera.T_world_cam
    T_est = cal.camera(davis_label).T_world_cam
    rot = np.degrees(Rotation.from_matrix(T_true[:3, :3].T @ T_est[:3, :3]).magnitude())
    assert rot < 1.0
    assert np.linalg.norm(T_true[:3, 3] - T_est[:3, 3]) < 0.02
    assert cal.camera(d415_label).source == "charuco"
    # Never silently overwritten.
    assert main([*args, "--out", str(out)]) == 1
    assert "exists" in capsys.readouterr().err


def test_intrinsics_of_an_unknown_camera_name_the_recorded_cameras(
    session: tuple[Path, Path, BoardRecording], capsys: pytest.CaptureFixture[str]
) -> None:
    root, board, rec = session
    args = ["calibrate", "intrinsics", str(rec.path), "--camera", "davis/00000000"]
    assert main([*args, "--board", str(board), "--out", str(root / "x.toml")]) == 1
    err = capsys.readouterr().err
    assert "no images of camera 'davis/00000000'" in err
    assert next(iter(rec.labels)) in err


def test_write_board_prints_the_board_image(tmp_path: Path) -> None:
    import cv2

    board = tmp_path / "board.toml"
    write_board_spec(board, SPEC)
    png = tmp_path / "board.png"
    args = ["calibrate", "intrinsics", "--board", str(board), "--write-board", str(png)]
    assert main(args) == 0
    img = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    assert img is not None
    assert img.shape == (3600, 4200)  # 0.9 × 0.75 m + half-square margins at 4000 px/m
    assert main(args) == 1  # exists: not overwritten


@pytest.mark.parametrize("command", ["intrinsics", "board"])
def test_help_shows_examples(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", command, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "examples:" in out
    assert f"mocaprig calibrate {command}" in out
