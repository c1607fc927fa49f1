"""Tests of drivers_mock.charuco_render: board renders, pose trajectories, the board recording."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocaprig.acquire.recording import Recording
from mocaprig.calib.charuco import CharucoBoardSpec, detect_charuco
from mocaprig.drivers_mock.charuco_render import (
    intrinsics_poses,
    render_board,
    shared_poses,
    write_board_recording,
)
from mocaprig.drivers_mock.rig import default_rig, project
from mocaprig.drivers_mock.scenario import stream_rng
from mocaprig.errors import RecordingError

SPEC = CharucoBoardSpec(6, 5, 0.15, 0.1125, "DICT_4X4_50")
RIG = default_rig(stream_rng(0, "rig"))


def test_render_is_a_pure_function_of_the_seed() -> None:
    cam = RIG.davis.camera
    T = intrinsics_poses(cam, SPEC, 1, seed=4, fill=(0.6, 0.8))[0]
    a = render_board(cam, SPEC, T, rng=np.random.default_rng(7))
    b = render_board(cam, SPEC, T, rng=np.random.default_rng(7))
    c = render_board(cam, SPEC, T, rng=np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert a.shape == (180, 240)
    assert a.dtype == np.uint16


def test_d415_render_is_an_8_bit_ir_image_of_the_device_size() -> None:
    cam = RIG.d415[0].ir_left
    T = intrinsics_poses(cam, SPEC, 1, seed=0)[0]
    img = render_board(cam, SPEC, T, rng=np.random.default_rng(0))
    assert img.shape == (480, 848)
    assert img.dtype == np.uint8
    assert int(img.max()) > 150
    assert int(img.min()) < 40


def test_distorted_davis_render_puts_corners_where_the_rig_projects_them() -> None:
    # Near the image corners the DAVIS's barrel distortion moves points by several pixels.
    cam = RIG.davis.camera
    errs = []
    for T in intrinsics_poses(cam, SPEC, 8, seed=1, fill=(0.6, 0.9)):
        v = detect_charuco(render_board(cam, SPEC, T, rng=np.random.default_rng(1)), SPEC)
        if v.n_corners:
            uv, _ = project(cam, v.object_points @ T[:3, :3].T + T[:3, 3])
            errs.append(np.linalg.norm(uv - v.image_points, axis=1))
    e = np.concatenate(errs)
    assert e.size > 40
    assert float(np.sqrt(np.mean(e**2))) < 0.3


def test_board_behind_the_camera_renders_background_only() -> None:
    cam = RIG.d415[0].ir_left
    T = np.eye(4)
    T[:3, 3] = cam.T_world_cam[:3, 3] - 2.0 * cam.T_world_cam[:3, 2]
    img = render_board(cam, SPEC, T, rng=np.random.default_rng(0))
    assert detect_charuco(img, SPEC).n_corners == 0
    assert int(img.max()) < 200  # no white board


def test_intrinsics_poses_spread_over_the_image() -> None:
    cam = RIG.d415[0].ir_left
    centres = []
    for T in intrinsics_poses(cam, SPEC, 12, seed=0):
        uv, z = project(cam, T[:3, :3] @ np.array([0.45, 0.375, 0.0]) + T[:3, 3])
        assert z > 0
        centres.append(uv)
    c = np.array(centres)
    assert np.ptp(c[:, 0]) > 0.5 * cam.width
    assert np.ptp(c[:, 1]) > 0.4 * cam.height


def test_shared_poses_are_seen_by_every_camera() -> None:
    cams = [RIG.d415[0].ir_left, RIG.davis.camera]
    for T in shared_poses(cams, SPEC, 4, seed=0):
        for cam in cams:
            uv, z = project(cam, SPEC.corners_m @ T[:3, :3].T + T[:3, 3])
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0)
            assert np.mean(inside & (uv[:, 1] < cam.height) & (z > 0)) >= 0.75


def test_board_recording_holds_ir_and_aps_frames_at_shared_log_times(tmp_path: Path) -> None:
    path = tmp_path / "board.mcap"
    rec = write_board_recording(path, SPEC, seed=0, intrinsics_views=2, shared_views=2)
    d415 = f"/d415/{RIG.d415[0].serial}/ir"
    davis = f"/davis/{RIG.davis.serial}/frame"
    with Recording(path) as r:
        assert {d415, davis} <= set(r.topics)
        t_ir = [t for t, m in r.images(d415)]
        t_aps = [t for t, m in r.images(davis)]
        encodings = {m.encoding for _, m in r.images(davis)}
    assert t_ir == t_aps == rec.t_ns.tolist()
    assert encodings == {"mono16"}
    assert rec.poses.shape == (6, 4, 4)
    with pytest.raises(RecordingError, match="not overwriting"):
        write_board_recording(path, SPEC, seed=0, intrinsics_views=1, shared_views=1)
