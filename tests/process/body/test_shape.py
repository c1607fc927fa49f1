"""Body shape: Drillis & Contini proportions, standing height, sampling and rest offsets."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mocaprig.errors import ValidationError
from mocaprig.process.body.kinematics import forward_kinematics, neutral_pose
from mocaprig.process.body.shape import (
    DRILLIS_CONTINI_FRACTIONS,
    VERTICAL_CHAIN,
    BodyShape,
    rest_joint_positions,
    rest_offsets,
)
from mocaprig.process.body.skeleton import JOINT_INDEX, JOINTS
from mocaprig.process.body.surface import capsules


def _standing_extent_m(shape: BodyShape) -> tuple[float, float, float]:
    """(lowest surface z, highest surface z, HeadEnd z) of the rest pose on the floor."""
    kin = forward_kinematics(neutral_pose(shape), shape)
    caps = capsules(kin, shape)
    low = np.minimum(caps.a_m[:, 2], caps.b_m[:, 2]) - caps.radius_m
    high = np.maximum(caps.a_m[:, 2], caps.b_m[:, 2]) + caps.radius_m
    return float(low.min()), float(high.max()), float(kin.positions_m[JOINT_INDEX["HeadEnd"], 2])


@pytest.mark.parametrize("height_m", [1.50, 1.75, 2.00])
def test_rest_pose_stands_height_m_tall_with_flat_feet(height_m: float) -> None:
    shape = BodyShape.from_height(height_m)
    floor, top, head_end = _standing_extent_m(shape)
    assert abs(floor) < 1e-9  # soles touch the floor, nothing below it
    assert abs(head_end - height_m) < 0.01
    assert abs(top - height_m) < 0.01


def test_sampled_shapes_stand_their_height_and_stay_in_range() -> None:
    rng = np.random.default_rng(7)
    for _ in range(25):
        shape = BodyShape.sample(rng)
        assert 1.55 <= shape.height_m <= 1.95
        floor, top, head_end = _standing_extent_m(shape)
        assert abs(floor) < 1e-9
        assert abs(head_end - shape.height_m) < 0.01
        assert abs(top - shape.height_m) < 0.01


def test_sampled_segments_vary_by_about_five_percent() -> None:
    rng = np.random.default_rng(11)
    ratios = []
    for _ in range(40):
        shape = BodyShape.sample(rng)
        ratios.append(shape.upper_arm_length_m / (0.186 * shape.height_m))
    ratios_arr = np.array(ratios)
    assert ratios_arr.min() >= 0.95 - 1e-9
    assert ratios_arr.max() <= 1.05 + 1e-9
    assert ratios_arr.std() > 0.01  # it really varies


def test_sampling_is_reproducible_for_a_seed() -> None:
    a = BodyShape.sample(np.random.default_rng(3))
    b = BodyShape.sample(np.random.default_rng(3))
    assert a == b


def test_limb_offsets_follow_drillis_contini() -> None:
    h = 1.80
    off = rest_offsets(BodyShape.from_height(h))
    expected = {
        "RightForeArm": 0.186,  # upper arm
        "RightHand": 0.146,  # forearm
        "RightLeg": 0.245,  # thigh
        "RightFoot": 0.246,  # shank
        "LeftForeArm": 0.186,
        "LeftLeg": 0.245,
    }
    for joint, fraction in expected.items():
        assert np.linalg.norm(off[JOINT_INDEX[joint]]) == pytest.approx(fraction * h, rel=1e-12)


def test_rest_landmark_heights_match_the_standard_figure() -> None:
    h = 1.70
    pos = rest_joint_positions(BodyShape.from_height(h))
    # Drillis & Contini landmark heights (fractions of H): ankle, knee, hip, shoulder, wrist.
    for joint, fraction in [
        ("RightFoot", 0.039),
        ("RightLeg", 0.285),
        ("RightUpLeg", 0.530),
        ("RightArm", 0.818),
        ("RightHand", 0.818 - 0.186 - 0.146),
    ]:
        assert pos[JOINT_INDEX[joint], 2] == pytest.approx(fraction * h, abs=1e-3)


def test_rest_offsets_mirror_left_and_right() -> None:
    off = rest_offsets(BodyShape.from_height(1.7))
    for j, name in enumerate(JOINTS):
        if name.startswith("Right"):
            left = off[JOINT_INDEX["Left" + name.removeprefix("Right")]]
            np.testing.assert_allclose(left, off[j] * [-1, 1, 1], atol=0)


def test_vertical_chain_fractions_sum_to_one() -> None:
    assert sum(DRILLIS_CONTINI_FRACTIONS[k] for k in VERTICAL_CHAIN) == pytest.approx(1.0)


def test_shape_rejects_an_inconsistent_vertical_chain() -> None:
    shape = BodyShape.from_height(1.75)
    with pytest.raises(ValidationError, match="vertical chain"):
        dataclasses.replace(shape, thigh_length_m=shape.thigh_length_m + 0.05)


def test_shape_rejects_non_positive_values() -> None:
    with pytest.raises(ValidationError, match="height_m"):
        BodyShape.from_height(-1.0)


def test_from_height_rejects_unknown_scale_fields() -> None:
    with pytest.raises(ValidationError, match="unknown field"):
        BodyShape.from_height(1.75, segment_scale={"tail_length_m": 1.1})


def test_segment_scale_keeps_the_standing_height() -> None:
    shape = BodyShape.from_height(1.75, segment_scale={"thigh_length_m": 1.05})
    assert sum(getattr(shape, k) for k in VERTICAL_CHAIN) == pytest.approx(1.75, abs=1e-12)
    assert shape.thigh_length_m > 0.245 * 1.75
