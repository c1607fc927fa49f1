"""The pose bank: built from clips, saved and read, searched on a cloud, used by the solve."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocaprig.errors import ProcessingError, RecordingError, ValidationError
from mocaprig.process.body import DEMOCAP_JOINTS
from mocaprig.process.body.bvh import BvhClip, parse_bvh
from mocaprig.process.body.bvh_export import bvh_text
from mocaprig.process.body.kinematics import democap_joints, forward_kinematics, within_limits
from mocaprig.process.body.markers import MarkerSet
from mocaprig.process.body.procedural import make_motion
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.democap.pose_bank import (
    DEFAULT_POSE_BANK,
    BankSearch,
    PoseBank,
    bank_starts,
    build_pose_bank,
    load_pose_bank,
    save_pose_bank,
)


def _clip(name: str, seed: int, yaw_deg: float) -> BvhClip:
    shape = BodyShape.from_height(1.7)
    poses = make_motion(name, seconds=2.0, rng=np.random.default_rng(seed), rate_hz=30.0).poses
    poses = poses.copy()
    turn = Rotation.from_euler("z", yaw_deg, degrees=True)
    poses[:, :3] = (turn * Rotation.from_rotvec(poses[:, :3])).as_rotvec()
    poses[:, 3:6] = turn.apply(poses[:, 3:6]) + np.array([1.5, -0.7, 0.0])
    return parse_bvh(bvh_text(poses, shape, rate_hz=30.0), unit_scale=0.01)


def _placed(
    pose: np.ndarray, *, height_m: float, yaw_deg: float, shift_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Markers and joints of a bank pose on a body of ``height_m``, turned and moved."""
    shape = BodyShape.from_height(height_m)
    q = pose.copy()
    q[5] *= height_m / 1.75
    turn = Rotation.from_euler("z", yaw_deg, degrees=True)
    q[:3] = (turn * Rotation.from_rotvec(q[:3])).as_rotvec()
    q[3:6] = turn.apply(q[3:6]) + shift_m
    kin = forward_kinematics(q[None], shape)
    ms = MarkerSet.for_shape(shape)
    ji = ms.joint_index
    mk = kin.positions_m[0, ji] + (kin.rotations[0, ji] @ ms.offsets_m[..., None])[..., 0]
    return mk, democap_joints(kin)[0]


def test_a_built_bank_holds_real_frames_without_heading_at_the_origin() -> None:
    clips = [_clip("squat", 1, 70.0), _clip("wave", 2, -120.0)]
    bank = build_pose_bank(clips, size=6, rate_hz=10.0, seed=0)
    assert 1 <= len(bank) <= 6
    assert bank.source == tuple(c.name for c in clips)
    np.testing.assert_allclose(bank.poses[:, 3:5], 0.0, atol=1e-12)
    fwd = Rotation.from_rotvec(bank.poses[:, :3]).as_matrix()[:, :, 1]
    np.testing.assert_allclose(np.arctan2(-fwd[:, 0], fwd[:, 1]), 0.0, atol=1e-9)
    assert within_limits(bank.poses, tol_rad=1e-6).all()
    # the same clips and seed give the same bank
    again = build_pose_bank(clips, size=6, rate_hz=10.0, seed=0)
    np.testing.assert_array_equal(again.poses, bank.poses)


def test_building_a_bank_larger_than_its_frames_is_refused() -> None:
    with pytest.raises(ValidationError, match="fewer than size"):
        build_pose_bank([_clip("squat", 1, 0.0)], size=500, rate_hz=10.0)
    with pytest.raises(ValidationError, match="at least one clip"):
        build_pose_bank([], size=4)


def test_a_bank_round_trips_and_is_not_overwritten(tmp_path: Path) -> None:
    bank = PoseBank(poses=load_pose_bank().poses[:5], source=("a", "b"))
    path = save_pose_bank(bank, tmp_path / "bank.npz")
    back = load_pose_bank(path)
    np.testing.assert_allclose(back.poses, bank.poses, atol=1e-6)
    assert back.source == ("a", "b")
    with pytest.raises(RecordingError, match="exists"):
        save_pose_bank(bank, path)
    save_pose_bank(bank, path, overwrite=True)


def test_a_corrupt_bank_file_is_named(tmp_path: Path) -> None:
    bad = tmp_path / "bank.npz"
    bad.write_bytes(b"not a bank")
    with pytest.raises(ProcessingError, match=r"bank\.npz.*pose-bank"):
        load_pose_bank(bad)


def test_the_committed_bank_is_the_train_split_s() -> None:
    bank = load_pose_bank(DEFAULT_POSE_BANK)
    assert len(bank) == 256
    assert all(name.startswith("cmu_") for name in bank.source)
    assert within_limits(bank.poses, tol_rad=1e-5).all()


def test_the_search_places_a_bank_pose_where_its_cloud_is() -> None:
    bank = load_pose_bank()
    rng = np.random.default_rng(4)
    # the most bent pose of the bank, on a shorter body, turned onto a grid heading
    tilt = np.degrees(
        np.arccos(Rotation.from_rotvec(bank.poses[:, :3]).as_matrix()[:, 2, 2].clip(-1, 1))
    )
    k = int(np.argmax(tilt))
    shift = np.array([0.4, -0.3, 0.0])
    mk, jt = _placed(bank.poses[k], height_m=1.62, yaw_deg=150.0, shift_m=shift)
    seen = rng.random(len(mk)) < 0.7
    cloud = mk[seen] + rng.normal(0.0, 0.003, (int(seen.sum()), 3))
    sm, sj = bank_starts([cloud], [1.62], bank, search=BankSearch(starts=2, height_scales=(1.0,)))
    assert sm.shape == (2, 1, 53, 3)
    assert sj.shape == (2, 1, len(DEMOCAP_JOINTS), 3)
    assert np.linalg.norm(sj[0, 0] - jt, axis=-1).mean() < 0.01
    assert np.linalg.norm(sm[0, 0] - mk, axis=-1).mean() < 0.01


def test_the_screen_keeps_the_placement_that_sliding_every_one_finds() -> None:
    bank = load_pose_bank()
    rng = np.random.default_rng(9)
    clouds, truth = [], []
    for k, yaw in ((17, 40.0), (101, 200.0), (230, 310.0)):
        mk, jt = _placed(bank.poses[k], height_m=1.8, yaw_deg=yaw, shift_m=np.array([0.2, 0.5, 0]))
        seen = rng.random(len(mk)) < 0.7
        # a few projector-dot strays about the body
        strays = mk.mean(0) + rng.uniform(-0.8, 0.8, (5, 3))
        clouds.append(
            np.concatenate([mk[seen] + rng.normal(0.0, 0.004, (int(seen.sum()), 3)), strays])
        )
        truth.append(jt)
    every = len(bank) * BankSearch().headings
    at = (1.0,)  # the bodies' own height: the screen is what is tested
    _, full = bank_starts(
        clouds, [1.8] * 3, bank, search=BankSearch(screen=every, height_scales=at)
    )
    _, screened = bank_starts(clouds, [1.8] * 3, bank, search=BankSearch(height_scales=at))
    for b in range(3):
        # the yaws are 10 degrees off the search's 30-degree headings: a few cm at the limbs
        assert np.linalg.norm(full[0, b] - truth[b], axis=-1).mean() < 0.08
        assert np.linalg.norm(screened[0, b] - full[0, b], axis=-1).mean() < 0.005


def test_a_body_solved_too_short_is_found_at_a_scaled_height() -> None:
    """A 2.05 m subject whose first solve said 1.75 m: the bank is also placed 15 % taller."""
    bank = load_pose_bank()
    rng = np.random.default_rng(8)
    mk, jt = _placed(bank.poses[60], height_m=2.05, yaw_deg=90.0, shift_m=np.array([0.3, 0, 0]))
    seen = rng.random(len(mk)) < 0.7
    cloud = mk[seen] + rng.normal(0.0, 0.003, (int(seen.sum()), 3))
    one = BankSearch(starts=2, height_scales=(1.0,))
    _, at_estimate = bank_starts([cloud], [1.75], bank, search=one)
    sm, sj = bank_starts([cloud], [1.75], bank, search=BankSearch(starts=2))
    assert sm.shape == (6, 1, 53, 3)  # 2 starts at each of the 3 heights
    np.testing.assert_array_equal(sj[2:4], at_estimate)  # the estimate's own, in the middle
    err = np.linalg.norm(sj[:, 0] - jt, axis=-1).mean(axis=1)
    assert err[4] < 0.5 * err[2]  # 1.75 x 1.15 = 2.01 m: far nearer the subject
    assert err[4] < 0.04


def test_bad_search_options_are_refused() -> None:
    for scales in ((), (1.0, 0.0), (float("nan"),)):
        with pytest.raises(ValidationError, match="height_scales"):
            BankSearch(height_scales=scales)
    with pytest.raises(ValidationError, match="starts"):
        BankSearch(starts=0)


def test_the_search_refuses_heights_that_do_not_match_the_clouds() -> None:
    bank = load_pose_bank()
    cloud = np.zeros((10, 3))
    with pytest.raises(ValidationError, match="heights_m"):
        bank_starts([cloud, cloud], [1.7], bank)
    with pytest.raises(ValidationError, match="positive"):
        bank_starts([cloud], [0.0], bank)
    with pytest.raises(ValidationError, match="no point"):
        bank_starts([np.zeros((0, 3))], [1.7], bank)
