"""Tests of calib.charuco: board files, detection, intrinsics and board extrinsics vs truth.

Images come from drivers_mock.charuco_render (the simulated rig's cameras, with the DAVIS's
barrel distortion); accuracy is checked against the rig's K, distortion and T_world_cam over
several seeds.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocaprig.calib.charuco import (
    BoardView,
    CharucoBoardSpec,
    IntrinsicsResult,
    calibrate_extrinsics,
    calibrate_intrinsics,
    detect_charuco,
    group_views_by_time,
    read_board_spec,
    read_intrinsics,
    write_board_spec,
    write_intrinsics,
)
from mocaprig.drivers_mock.charuco_render import intrinsics_poses, render_board, shared_poses
from mocaprig.drivers_mock.rig import PinholeCamera, Rig, default_rig, project
from mocaprig.drivers_mock.scenario import stream_rng
from mocaprig.errors import CalibrationError, ValidationError

#: The board of the tests: 0.9 × 0.75 m, 20 inner corners (big enough for the DAVIS at 2.5 m).
SPEC = CharucoBoardSpec(6, 5, 0.15, 0.1125, "DICT_4X4_50")


@functools.cache
def _rig(seed: int) -> Rig:
    return default_rig(stream_rng(seed, "rig"))


def _cam(seed: int, which: str) -> PinholeCamera:
    rig = _rig(seed)
    return rig.davis.camera if which == "davis" else rig.d415[0].ir_left


def _label(seed: int, which: str) -> str:
    rig = _rig(seed)
    return f"davis/{rig.davis.serial}" if which == "davis" else f"d415/{rig.d415[0].serial}"


@functools.cache
def _intrinsic_views(seed: int, which: str, n: int) -> tuple[BoardView, ...]:
    cam = _cam(seed, which)
    fill = (0.55, 0.9) if which == "davis" else (0.35, 0.7)
    poses = intrinsics_poses(cam, SPEC, n, seed=seed, fill=fill)
    rng = np.random.default_rng(seed)
    return tuple(detect_charuco(render_board(cam, SPEC, T, rng=rng), SPEC) for T in poses)


@functools.cache
def _intrinsics(seed: int, which: str) -> IntrinsicsResult:
    cam = _cam(seed, which)
    n = 30 if which == "davis" else 16
    views = _intrinsic_views(seed, which, n)
    return calibrate_intrinsics(views, (cam.width, cam.height), SPEC, camera=_label(seed, which))


@functools.cache
def _shared_views(seed: int, n: int) -> dict[str, tuple[BoardView, ...]]:
    cams = {_label(seed, w): _cam(seed, w) for w in ("d415", "davis")}
    poses = shared_poses(list(cams.values()), SPEC, n, seed=seed)
    rng = np.random.default_rng(seed + 1000)
    out: dict[str, list[BoardView]] = {k: [] for k in cams}
    for i, T in enumerate(poses):
        for label, cam in cams.items():
            img = render_board(cam, SPEC, T, rng=rng)
            out[label].append(detect_charuco(img, SPEC, t_ns=i * 100_000_000 + len(out[label])))
    return {k: tuple(v) for k, v in out.items()}


def _pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    rot = Rotation.from_matrix(T_true[:3, :3].T @ T_est[:3, :3]).magnitude()
    return float(np.degrees(rot)), float(1000.0 * np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))


# --------------------------------------------------------------------------------------------
# board description


def test_board_spec_round_trips_through_toml(tmp_path: Path) -> None:
    spec = CharucoBoardSpec(8, 6, 0.04, 0.03, "DICT_5X5_100", legacy_pattern=True)
    path = tmp_path / "board.toml"
    write_board_spec(path, spec)
    assert read_board_spec(path) == spec
    with pytest.raises(ValidationError, match="not overwriting"):
        write_board_spec(path, spec)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"square_length_m": 40.0, "marker_length_m": 30.0}, "millimetres"),
        ({"marker_length_m": 0.2}, "smaller than"),
        ({"dictionary": "DICT_9X9_1"}, "unknown dictionary"),
        ({"squares_x": 2}, "squares_x"),
        ({"squares_x": 20, "squares_y": 20}, "larger dictionary"),
    ],
)
def test_board_spec_refuses_invalid_descriptions(kwargs: dict[str, object], match: str) -> None:
    base: dict[str, object] = {
        "squares_x": 6,
        "squares_y": 5,
        "square_length_m": 0.15,
        "marker_length_m": 0.1125,
        "dictionary": "DICT_4X4_50",
    }
    with pytest.raises(ValidationError, match=match):
        CharucoBoardSpec(**{**base, **kwargs})  # type: ignore[arg-type]


def test_board_file_with_unknown_key_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "b.toml"
    path.write_text("[board]\nsquares_x = 6\nsquares_y = 5\nsquare_length_m = 0.1\n"
                    "marker_length_m = 0.07\nmarker_size = 3\n")  # fmt: skip
    with pytest.raises(ValidationError, match="unknown keys"):
        read_board_spec(path)


# --------------------------------------------------------------------------------------------
# detection


@pytest.mark.parametrize("which", ["d415", "davis"])
def test_detected_corners_lie_where_the_rig_projects_them(which: str) -> None:
    cam = _cam(0, which)
    fill = (0.6, 0.8) if which == "davis" else (0.4, 0.6)
    T = intrinsics_poses(cam, SPEC, 1, seed=3, fill=fill, tilt_deg=(10.0, 20.0))[0]
    view = detect_charuco(render_board(cam, SPEC, T, rng=np.random.default_rng(0)), SPEC)
    assert view.n_corners >= 12
    uv, _ = project(cam, view.object_points @ T[:3, :3].T + T[:3, 3])
    err = np.linalg.norm(uv - view.image_points, axis=1)
    assert float(np.sqrt(np.mean(err**2))) < 0.25
    np.testing.assert_allclose(view.object_points, SPEC.corners_m[view.corner_ids])


def test_wrong_dictionary_or_square_count_detects_no_corner() -> None:
    cam = _cam(0, "d415")
    T = intrinsics_poses(cam, SPEC, 1, seed=1, tilt_deg=(5.0, 10.0))[0]
    img = render_board(cam, SPEC, T, rng=np.random.default_rng(1))
    other_dict = dataclasses.replace(SPEC, dictionary="DICT_6X6_50")
    assert detect_charuco(img, other_dict).n_corners == 0
    other_size = dataclasses.replace(SPEC, squares_x=9, squares_y=7)
    assert detect_charuco(img, other_size).n_corners == 0
    assert detect_charuco(img, other_size).markers_seen > 0


def test_legacy_pattern_boards_are_found_only_with_the_legacy_flag() -> None:
    legacy = CharucoBoardSpec(6, 4, 0.1, 0.075, "DICT_4X4_50", legacy_pattern=True)
    modern = dataclasses.replace(legacy, legacy_pattern=False)
    cam = _cam(0, "d415")
    T = intrinsics_poses(cam, legacy, 1, seed=0, tilt_deg=(5.0, 10.0))[0]
    img = render_board(cam, legacy, T, rng=np.random.default_rng(0))
    assert detect_charuco(img, legacy).n_corners == legacy.n_corners
    wrong = detect_charuco(img, modern)
    assert wrong.n_corners == 0
    assert wrong.markers_seen > 0


def test_ten_bit_aps_frames_and_float_images_are_accepted() -> None:
    cam = _cam(0, "davis")
    T = intrinsics_poses(cam, SPEC, 1, seed=2, fill=(0.6, 0.8), tilt_deg=(5.0, 15.0))[0]
    img = render_board(cam, SPEC, T, rng=np.random.default_rng(0))
    assert img.dtype == np.uint16
    assert int(img.max()) <= 1023
    a = detect_charuco(img, SPEC)
    b = detect_charuco(img.astype(np.float64) / 1023.0, SPEC)
    assert a.n_corners > 0
    assert a.n_corners == b.n_corners


# --------------------------------------------------------------------------------------------
# intrinsics


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_intrinsics_recover_the_d415_camera_matrix(seed: int) -> None:
    cam = _cam(seed, "d415")
    r = _intrinsics(seed, "d415")
    assert r.rms_px < 0.2
    assert abs(r.K[0, 0] - cam.fx) / cam.fx < 0.003  # measured ≤ 0.2 %
    assert abs(r.K[1, 1] - cam.fy) / cam.fy < 0.003
    assert abs(r.K[0, 2] - cam.cx) < 1.5  # measured ≤ 0.9 px
    assert abs(r.K[1, 2] - cam.cy) < 1.5
    assert np.all(np.abs(r.distortion[:4]) < 0.01)  # rectified stream: no distortion


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_intrinsics_recover_the_davis_camera_matrix_and_barrel_distortion(seed: int) -> None:
    cam = _cam(seed, "davis")
    r = _intrinsics(seed, "davis")
    assert r.rms_px < 0.35
    assert abs(r.K[0, 0] - cam.fx) / cam.fx < 0.015  # measured ≤ 0.9 % (240×180 px)
    assert abs(r.K[0, 2] - cam.cx) < 4.0  # measured ≤ 2.2 px
    assert abs(r.K[1, 2] - cam.cy) < 4.0
    # The lens model itself: radial displacement at the image corner within 1 px of truth.
    corner = np.array([[0.0, 0.0]])
    ab = (corner - cam.K[:2, 2]) / np.diag(cam.K)[:2]
    r2 = float(np.sum(ab**2))
    k1, k2 = cam.distortion[:2]
    e1, e2 = r.distortion[:2]
    true_shift = cam.fx * np.sqrt(r2) * (k1 * r2 + k2 * r2 * r2)
    est_shift = cam.fx * np.sqrt(r2) * (e1 * r2 + e2 * r2 * r2)
    assert abs(true_shift - est_shift) < 1.0


def test_intrinsics_file_round_trips(tmp_path: Path) -> None:
    r = _intrinsics(0, "d415")
    path = tmp_path / "intr.toml"
    write_intrinsics(path, r)
    back = read_intrinsics(path)
    np.testing.assert_array_equal(back.K, r.K)
    np.testing.assert_array_equal(back.distortion, r.distortion)
    assert back.board == SPEC
    assert back.camera == r.camera
    assert back.rms_px == r.rms_px


def test_intrinsics_refuse_too_few_views() -> None:
    views = _intrinsic_views(0, "d415", 16)[:4]
    with pytest.raises(CalibrationError, match=r"usable views .* need ≥ 8"):
        calibrate_intrinsics(views, (848, 480), SPEC)


def test_intrinsics_say_when_the_board_was_never_seen() -> None:
    cam = _cam(0, "d415")
    rng = np.random.default_rng(0)
    far_away = np.eye(4)
    far_away[:3, 3] = cam.T_world_cam[:3, 3] - 5.0 * cam.T_world_cam[:3, 2]  # behind it
    views = [detect_charuco(render_board(cam, SPEC, far_away, rng=rng), SPEC) for _ in range(3)]
    with pytest.raises(CalibrationError, match="never seen"):
        calibrate_intrinsics(views, (848, 480), SPEC)


def test_intrinsics_with_a_wrong_board_description_point_at_the_board_file() -> None:
    cam = _cam(0, "d415")
    wrong = dataclasses.replace(SPEC, squares_x=9, squares_y=7)
    poses = intrinsics_poses(cam, SPEC, 3, seed=0)
    rng = np.random.default_rng(0)
    views = [detect_charuco(render_board(cam, SPEC, T, rng=rng), wrong) for T in poses]
    with pytest.raises(CalibrationError, match="check the board description"):
        calibrate_intrinsics(views, (848, 480), wrong)


def test_intrinsics_refuse_fronto_parallel_views() -> None:
    cam = _cam(0, "d415")
    poses = intrinsics_poses(cam, SPEC, 12, seed=5, tilt_deg=(0.0, 0.0), roll_deg=30.0)
    rng = np.random.default_rng(5)
    views = [detect_charuco(render_board(cam, SPEC, T, rng=rng), SPEC) for T in poses]
    with pytest.raises(CalibrationError, match="fronto-parallel"):
        calibrate_intrinsics(views, (848, 480), SPEC)


def test_intrinsics_refuse_views_covering_a_small_part_of_the_image() -> None:
    views = list(_intrinsic_views(0, "d415", 16))
    # Keep only corners in the top-left quarter of the image.
    small = []
    for v in views:
        keep = (v.image_points[:, 0] < 424) & (v.image_points[:, 1] < 240)
        small.append(BoardView(v.corner_ids[keep], v.image_points[keep], v.object_points[keep]))
    with pytest.raises(CalibrationError, match="cover"):
        calibrate_intrinsics(small, (848, 480), SPEC, min_views=3)


def test_intrinsics_refuse_a_fit_above_the_rms_ceiling_unless_forced() -> None:
    views = _intrinsic_views(0, "d415", 16)
    with pytest.raises(CalibrationError, match="ceiling"):
        calibrate_intrinsics(views, (848, 480), SPEC, max_rms_px=0.01)
    r = calibrate_intrinsics(views, (848, 480), SPEC, max_rms_px=0.01, force=True)
    assert r.rms_px > 0.01


# --------------------------------------------------------------------------------------------
# extrinsics


def test_views_are_grouped_by_time_within_the_skew() -> None:
    def v(t: int) -> BoardView:
        return BoardView(np.arange(4, dtype=np.int32), np.zeros((4, 2)), np.zeros((4, 3)), 4, t)

    views = {"a": [v(0), v(1000), v(5000)], "b": [v(300), v(5400)], "c": [v(9000)]}
    groups = group_views_by_time(views, max_skew_ns=500)
    assert [sorted(g) for g in groups] == [["a", "b"], ["a", "b"]]
    assert groups[1]["b"].t_ns == 5400


@pytest.mark.parametrize("seed", [0, 1])
def test_davis_d415_extrinsics_with_true_intrinsics_are_within_01_deg_2_mm(seed: int) -> None:
    truth = {
        w: dataclasses.replace(
            _intrinsics(seed, w), K=_cam(seed, w).K, distortion=_cam(seed, w).distortion
        )
        for w in ("d415", "davis")
    }
    intr = {r.camera: r for r in truth.values()}
    cal = calibrate_extrinsics(_shared_views(seed, 40), intr)
    d415, davis = _cam(seed, "d415"), _cam(seed, "davis")
    T_true = np.linalg.inv(d415.T_world_cam) @ davis.T_world_cam
    rot, trans = _pose_error(cal.camera(_label(seed, "davis")).T_world_cam, T_true)
    assert rot < 0.1  # measured 0.014–0.033°
    assert trans < 2.0  # measured 0.7–1.2 mm
    assert cal.world_frame == _label(seed, "d415")
    np.testing.assert_allclose(cal.camera(_label(seed, "d415")).T_world_cam, np.eye(4))


@pytest.mark.parametrize("seed", [0, 1])
def test_davis_d415_extrinsics_with_calibrated_intrinsics(seed: int) -> None:
    intr = {r.camera: r for r in (_intrinsics(seed, "d415"), _intrinsics(seed, "davis"))}
    cal = calibrate_extrinsics(_shared_views(seed, 40), intr)
    d415, davis = _cam(seed, "d415"), _cam(seed, "davis")
    T_true = np.linalg.inv(d415.T_world_cam) @ davis.T_world_cam
    cam = cal.camera(_label(seed, "davis"))
    rot, trans = _pose_error(cam.T_world_cam, T_true)
    # Dominated by the DAVIS intrinsics (1 px of cx ≈ 0.24°); see docs/calibration.md.
    assert rot < 1.0
    assert trans < 20.0
    assert cam.residuals["reprojection_rms_px"] < 0.6
    assert cam.source == "charuco"


def test_board_world_frame_keeps_the_relative_poses() -> None:
    intr = {r.camera: r for r in (_intrinsics(0, "d415"), _intrinsics(0, "davis"))}
    views = _shared_views(0, 40)
    a = calibrate_extrinsics(views, intr)
    b = calibrate_extrinsics(views, intr, world="board")
    assert b.world_frame == "board"
    la, lb = _label(0, "d415"), _label(0, "davis")
    rel_a = np.linalg.inv(a.camera(la).T_world_cam) @ a.camera(lb).T_world_cam
    rel_b = np.linalg.inv(b.camera(la).T_world_cam) @ b.camera(lb).T_world_cam
    np.testing.assert_allclose(rel_a, rel_b, atol=1e-6)
    # The board is in front of every camera: its origin has positive depth in each.
    for c in b.cameras:
        assert (c.T_cam_world @ np.array([0.0, 0.0, 0.0, 1.0]))[2] > 0.3


def test_extrinsics_refuse_a_camera_sharing_no_view() -> None:
    intr = {r.camera: r for r in (_intrinsics(0, "d415"), _intrinsics(0, "davis"))}
    views = dict(_shared_views(0, 40))
    lb = _label(0, "davis")
    views[lb] = tuple(v.with_time(int(v.t_ns or 0) + 50_000_000) for v in views[lb])
    with pytest.raises(CalibrationError, match="share no board view"):
        calibrate_extrinsics(views, intr, max_skew_ns=2_000_000)


def test_extrinsics_refuse_views_without_intrinsics() -> None:
    intr = {r.camera: r for r in (_intrinsics(0, "d415"), _intrinsics(0, "davis"))}
    views = {**_shared_views(0, 40), "d415/000000000001": ()}
    with pytest.raises(ValidationError, match="no intrinsics"):
        calibrate_extrinsics(views, intr)
