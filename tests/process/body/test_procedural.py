"""Built-in procedural motions: limits, determinism, floor contact, timings."""

from __future__ import annotations

import numpy as np
import pytest

from mocaprig.errors import ValidationError
from mocaprig.process.body.kinematics import forward_kinematics, within_limits
from mocaprig.process.body.motion import Motion
from mocaprig.process.body.procedural import (
    PROCEDURAL_MOTIONS,
    floor_clearance_m,
    make_motion,
    session_motion,
)
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import DOF_NAMES, JOINT_INDEX

SHAPE = BodyShape.from_height(1.75)
RATE = 120.0


def _make(name: str, seed: int, seconds: float = 4.0) -> Motion:
    return make_motion(name, seconds=seconds, rng=np.random.default_rng(seed), rate_hz=RATE)


def _palms(name: str, seed: int) -> tuple[np.ndarray, np.ndarray]:
    p = forward_kinematics(_make(name, seed).poses, SHAPE).positions_m
    j = JOINT_INDEX
    right = 0.5 * (p[:, j["RightHand"]] + p[:, j["RightHandEnd"]])
    left = 0.5 * (p[:, j["LeftHand"]] + p[:, j["LeftHandEnd"]])
    return right, left


@pytest.mark.parametrize("name", PROCEDURAL_MOTIONS)
def test_every_motion_stays_within_limits_and_on_the_floor(name: str) -> None:
    m = _make(name, 3)
    assert m.num_frames == int(4.0 * RATE) + 1
    assert m.rate_hz == RATE
    assert within_limits(m.poses).all()
    kin = forward_kinematics(m.poses, SHAPE)
    clearance = floor_clearance_m(kin, SHAPE)
    assert clearance.min() > -1e-9  # never below the floor
    if name != "jumping_jacks":
        np.testing.assert_allclose(clearance, 0.0, atol=1e-9)  # always standing on it
    feet = kin.positions_m[:, [JOINT_INDEX["RightFoot"], JOINT_INDEX["LeftFoot"]], 2]
    assert feet.min() == pytest.approx(SHAPE.ankle_height_m, abs=0.01)


@pytest.mark.parametrize("name", PROCEDURAL_MOTIONS)
def test_motion_is_deterministic_per_seed_and_differs_across_seeds(name: str) -> None:
    a = _make(name, 11, seconds=1.0)
    b = _make(name, 11, seconds=1.0)
    c = _make(name, 12, seconds=1.0)
    np.testing.assert_array_equal(a.poses, b.poses)
    assert not np.allclose(a.poses, c.poses)


def test_t_pose_holds_arms_out_and_still() -> None:
    m = _make("t_pose", 0)
    for side in ("left", "right"):
        k = 6 + DOF_NAMES.index(f"{side}_shoulder_abduction")
        np.testing.assert_allclose(np.rad2deg(m.poses[:, k]), 90.0, atol=1.5)
    p = forward_kinematics(m.poses, SHAPE).positions_m
    speed = np.linalg.norm(np.diff(p, axis=0), axis=-1) * RATE
    assert speed.max() < 0.05  # tiny sway only


def test_clap_brings_the_palms_together() -> None:
    for seed in range(3):
        right, left = _palms("clap", seed)
        dist = np.linalg.norm(right - left, axis=-1)
        assert dist.min() < 0.05
        assert dist.max() > 0.15
        # every clap cycle (~0.5 s) reaches contact: split into 0.5 s windows of the 4 s take
        per_window = [w.min() for w in np.array_split(dist[: int(3.5 * RATE)], 7)]
        assert max(per_window) < 0.05


def test_jumping_jacks_leave_the_ground_briefly() -> None:
    m = _make("jumping_jacks", 5)
    clearance = floor_clearance_m(forward_kinematics(m.poses, SHAPE), SHAPE)
    airborne = clearance > 0.005
    assert 0.03 < clearance.max() < 0.12
    assert 0.15 < airborne.mean() < 0.5


def test_karate_strikes_are_fast() -> None:
    for seed in range(3):
        right, left = _palms("karate", seed)
        speed = np.linalg.norm(np.diff(np.stack([right, left]), axis=1), axis=-1) * RATE
        assert 5.0 < speed.max() < 10.5


def test_punch_extension_takes_015_to_025_s() -> None:
    right, _ = _palms("punch_kick", 2)
    speed = np.linalg.norm(np.diff(right, axis=0), axis=-1) * RATE
    fast = speed > 0.2 * speed.max()
    # the first burst of motion of the right hand is the jab's extension
    starts = np.flatnonzero(np.diff(fast.astype(int)) == 1)
    ends = np.flatnonzero(np.diff(fast.astype(int)) == -1)
    ends = ends[ends > starts[0]]
    duration = (ends[0] - starts[0]) / RATE
    assert 0.1 < duration < 0.3


def test_wave_raises_the_right_hand_above_the_elbow() -> None:
    p = forward_kinematics(_make("wave", 0).poses, SHAPE).positions_m
    lift = p[:, JOINT_INDEX["RightHand"], 2] - p[:, JOINT_INDEX["RightForeArm"], 2]
    assert lift.max() > 0.15


def test_unknown_motion_is_rejected() -> None:
    with pytest.raises(ValidationError, match="unknown procedural motion 'moonwalk'"):
        make_motion("moonwalk", seconds=1.0, rng=np.random.default_rng(0))


def test_session_starts_with_a_static_t_pose_and_keeps_feet_up() -> None:
    m = session_motion(["clap", "squat"], seconds=5.0, rng=np.random.default_rng(4), rate_hz=RATE)
    assert m.duration_s == pytest.approx(5.0, abs=2.0 / RATE)
    kin = forward_kinematics(m.poses, SHAPE)
    assert floor_clearance_m(kin, SHAPE).min() > -1e-9
    assert within_limits(m.poses).all()
    start = kin.positions_m[: int(1.5 * RATE)]
    assert np.ptp(start, axis=0).max() < 0.02  # static start
    step = np.linalg.norm(np.diff(m.poses[:, 3:6], axis=0), axis=-1)
    assert step.max() < 2.0 / RATE  # the root never jumps (< 2 m/s)


def test_freestyle_reaches_poses_beyond_the_scored_actions() -> None:
    hand_over_head, foot_lift, crouch = [], [], []
    for seed in range(3):
        m = make_motion("freestyle", seconds=6.0, rng=np.random.default_rng(seed), rate_hz=RATE)
        p = forward_kinematics(m.poses, SHAPE).positions_m
        j = JOINT_INDEX
        hands = np.maximum(p[:, j["RightHand"], 2], p[:, j["LeftHand"], 2])
        hand_over_head.append(float(np.max(hands - p[:, j["Head"], 2])))
        feet = p[:, [j["RightFoot"], j["LeftFoot"]], 2].max(axis=1)
        foot_lift.append(float(feet.max() - SHAPE.ankle_height_m))
        crouch.append(float(p[0, j["Hips"], 2] - p[:, j["Hips"], 2].min()))
        np.testing.assert_allclose(m.poses[0, 6:], 0.0, atol=np.deg2rad(5.0))  # starts standing
    # every take lifts a hand over the head and a foot off the floor at some point, and one
    # of three takes crouches by 5 cm or more: none of the scored actions does all of that
    assert min(hand_over_head) > 0.0
    assert min(foot_lift) > 0.1
    assert max(crouch) > 0.05


def test_freestyle_bends_over_at_the_hips_with_the_feet_under_the_pelvis() -> None:
    tilts, reach = [], []
    for seed in range(4):
        m = make_motion("freestyle", seconds=6.0, rng=np.random.default_rng(seed), rate_hz=RATE)
        assert within_limits(m.poses).all()
        kin = forward_kinematics(m.poses, SHAPE)
        p, j = kin.positions_m, JOINT_INDEX
        torso = p[:, j["Neck"]] - p[:, j["Hips"]]
        tilt = np.degrees(np.arccos(torso[:, 2] / np.linalg.norm(torso, axis=1)))
        bent = tilt > 45.0
        tilts.append(float(tilt.max()))
        if bent.any():
            # forward (+Y, the facing), the pelvis over the feet, and still standing
            assert np.all(torso[bent, 1] > 0.0)
            feet_y = p[bent][:, [j["RightFoot"], j["LeftFoot"]], 1].mean(axis=1)
            assert np.all(np.abs(p[bent, j["Hips"], 1] - feet_y) < 0.35)
            assert floor_clearance_m(kin, SHAPE)[bent].max() < 1e-6
            reach.append(float(p[bent, j["Head"], 2].min()))
    # deep bends (the torso past 60 degrees, the head below 1.2 m) in some takes, not all frames
    assert max(tilts) > 60.0
    assert min(reach) < 1.2
