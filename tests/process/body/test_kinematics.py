"""Forward kinematics: invariants, numpy/torch agreement, gradients and sign conventions."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from mocaprig.errors import ValidationError
from mocaprig.process.body.kinematics import (
    EVENTCAP_KEYPOINTS,
    clamp_to_limits,
    clamp_to_limits_torch,
    democap_joints,
    eventcap_keypoints,
    eventcap_keypoints_torch,
    forward_kinematics,
    forward_kinematics_torch,
    neutral_pose,
    rotvec_to_matrix,
    rotvec_to_matrix_torch,
    subtree_joints,
    subtree_kinematics_torch,
    t_pose,
    within_limits,
)
from mocaprig.process.body.shape import BodyShape, rest_offsets
from mocaprig.process.body.skeleton import (
    DEMOCAP_JOINT_INDEX,
    DOF_JOINT,
    DOF_LIMITS_RAD,
    DOF_NAMES,
    JOINT_INDEX,
    PARENTS,
    POSE_DIM,
    ROOT_DIM,
)
from tests.process.body._body_helpers import random_poses

SHAPE = BodyShape.from_height(1.75)
J = JOINT_INDEX


def _posed(**angles_deg: float) -> npt.NDArray[np.float64]:
    """Joint positions (26, 3) of the standing neutral pose with some angles set (degrees)."""
    q = neutral_pose(SHAPE)
    for name, deg in angles_deg.items():
        q[ROOT_DIM + DOF_NAMES.index(name)] = np.deg2rad(deg)
    return forward_kinematics(q, SHAPE).positions_m


def _moved(joint: str, **angles_deg: float) -> npt.NDArray[np.float64]:
    """Displacement (3,) of ``joint`` from the neutral pose when the angles are set."""
    return np.asarray(_posed(**angles_deg)[J[joint]] - _posed()[J[joint]])


# --- invariants -----------------------------------------------------------------------------


def test_bone_lengths_are_constant_in_random_poses() -> None:
    rng = np.random.default_rng(0)
    shape = BodyShape.sample(rng)
    kin = forward_kinematics(random_poses(rng, 300), shape)
    expected = np.linalg.norm(rest_offsets(shape), axis=-1)
    for j in range(1, len(PARENTS)):
        bone = kin.positions_m[:, j] - kin.positions_m[:, PARENTS[j]]
        np.testing.assert_allclose(np.linalg.norm(bone, axis=-1), expected[j], atol=1e-12)


def test_joint_rotations_stay_orthonormal() -> None:
    kin = forward_kinematics(random_poses(np.random.default_rng(1), 100), SHAPE)
    r = kin.rotations
    eye = np.broadcast_to(np.eye(3), r.shape)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)


def test_fk_matches_a_joint_by_joint_reference_chain() -> None:
    """An independent per-joint evaluation with scipy (Euler XYZ intrinsic, spine split ½-½)."""
    rng = np.random.default_rng(2)
    q = random_poses(rng, 5)
    kin = forward_kinematics(q, SHAPE)
    off = rest_offsets(SHAPE)
    # Signed axis per DoF, written out from the documented table (R side; L mirrors Y/Z).
    signs = {"flexion": 1, "abduction": -1, "internal_rotation": 1, "pronation": 1}
    for b in range(q.shape[0]):
        a = dict(zip(DOF_NAMES, q[b, ROOT_DIM:], strict=True))
        local = {name: np.eye(3) for name in J}
        spine = Rotation.from_euler(
            "XYZ",
            [-a["spine_flexion"] / 2, a["spine_lateral_bend"] / 2, a["spine_axial_twist"] / 2],
        ).as_matrix()
        local["Spine1"] = local["Spine2"] = spine
        local["Neck"] = Rotation.from_euler(
            "XZ", [-a["neck_flexion"], a["neck_axial_rotation"]]
        ).as_matrix()
        for side, m in (("right", 1), ("left", -1)):
            cap = side.capitalize()
            local[f"{cap}Arm"] = Rotation.from_euler(
                "XYZ",
                [
                    a[f"{side}_shoulder_flexion"],
                    m * signs["abduction"] * a[f"{side}_shoulder_abduction"],
                    m * signs["internal_rotation"] * a[f"{side}_shoulder_internal_rotation"],
                ],
            ).as_matrix()
            local[f"{cap}ForeArm"] = Rotation.from_euler(
                "XZ", [a[f"{side}_elbow_flexion"], m * a[f"{side}_elbow_pronation"]]
            ).as_matrix()
            local[f"{cap}UpLeg"] = Rotation.from_euler(
                "XYZ",
                [
                    a[f"{side}_hip_flexion"],
                    -m * a[f"{side}_hip_abduction"],
                    m * a[f"{side}_hip_internal_rotation"],
                ],
            ).as_matrix()
            local[f"{cap}Leg"] = Rotation.from_euler("X", -a[f"{side}_knee_flexion"]).as_matrix()
            local[f"{cap}Foot"] = Rotation.from_euler(
                "XY", [a[f"{side}_ankle_dorsiflexion"], m * a[f"{side}_ankle_inversion"]]
            ).as_matrix()
        names = list(J)
        rot = [Rotation.from_rotvec(q[b, 0:3]).as_matrix()]
        pos = [q[b, 3:6]]
        for j in range(1, len(names)):
            p = PARENTS[j]
            pos.append(pos[p] + rot[p] @ off[j])
            rot.append(rot[p] @ local[names[j]])
        np.testing.assert_allclose(kin.positions_m[b], np.array(pos), atol=1e-12)
        np.testing.assert_allclose(kin.rotations[b], np.array(rot), atol=1e-12)


def test_fk_keeps_batch_dimensions_and_leaves_input_alone() -> None:
    q = random_poses(np.random.default_rng(3), 6).reshape(2, 3, POSE_DIM)
    before = q.copy()
    kin = forward_kinematics(q, SHAPE)
    assert kin.positions_m.shape == (2, 3, 26, 3)
    assert kin.rotations.shape == (2, 3, 26, 3, 3)
    np.testing.assert_array_equal(q, before)
    single = forward_kinematics(q[1, 2], SHAPE)
    np.testing.assert_allclose(single.positions_m, kin.positions_m[1, 2], atol=1e-14)


def test_fk_accepts_rest_offsets_instead_of_a_shape() -> None:
    q = random_poses(np.random.default_rng(4), 3)
    a = forward_kinematics(q, SHAPE).positions_m
    b = forward_kinematics(q, rest_offsets(SHAPE)).positions_m
    np.testing.assert_array_equal(a, b)


def test_fk_rejects_a_wrong_pose_length() -> None:
    with pytest.raises(ValidationError, match="pose has the wrong shape"):
        forward_kinematics(np.zeros((4, 32)), SHAPE)


def test_fk_rejects_non_finite_poses() -> None:
    q = neutral_pose(SHAPE)
    q[10] = np.nan
    with pytest.raises(ValidationError, match="non-finite"):
        forward_kinematics(q, SHAPE)


# --- limits ---------------------------------------------------------------------------------


def test_clamp_brings_every_angle_within_limits_and_copies() -> None:
    rng = np.random.default_rng(5)
    q = rng.normal(scale=3.0, size=(50, POSE_DIM))
    before = q.copy()
    clamped = clamp_to_limits(q)
    np.testing.assert_array_equal(q, before)
    assert within_limits(clamped).all()
    assert not within_limits(q).all()
    np.testing.assert_array_equal(clamped[:, :ROOT_DIM], q[:, :ROOT_DIM])
    inside = (q[:, ROOT_DIM:] >= DOF_LIMITS_RAD[:, 0]) & (q[:, ROOT_DIM:] <= DOF_LIMITS_RAD[:, 1])
    np.testing.assert_array_equal(clamped[:, ROOT_DIM:][inside], q[:, ROOT_DIM:][inside])


def test_torch_clamp_matches_numpy_clamp() -> None:
    q = np.random.default_rng(6).normal(scale=3.0, size=(20, POSE_DIM))
    out = clamp_to_limits_torch(torch.tensor(q)).numpy()
    np.testing.assert_array_equal(out, clamp_to_limits(q))


def test_within_limits_flags_one_bad_angle() -> None:
    q = np.stack([neutral_pose(), neutral_pose()])
    q[1, ROOT_DIM + DOF_NAMES.index("left_knee_flexion")] = -0.1  # knees do not hyperextend
    np.testing.assert_array_equal(within_limits(q), [True, False])


# --- torch ----------------------------------------------------------------------------------


def test_torch_fk_matches_numpy_in_float64() -> None:
    q = random_poses(np.random.default_rng(8), 64)
    kin = forward_kinematics(q, SHAPE)
    pos, rot = forward_kinematics_torch(torch.tensor(q), SHAPE)
    assert pos.dtype == torch.float64
    np.testing.assert_allclose(pos.numpy(), kin.positions_m, atol=1e-9)
    np.testing.assert_allclose(rot.numpy(), kin.rotations, atol=1e-9)


def test_torch_fk_runs_in_float32() -> None:
    q = random_poses(np.random.default_rng(9), 16)
    kin = forward_kinematics(q, SHAPE)
    pos, rot = forward_kinematics_torch(torch.tensor(q, dtype=torch.float32), SHAPE)
    assert pos.dtype == torch.float32
    assert rot.dtype == torch.float32
    np.testing.assert_allclose(pos.numpy(), kin.positions_m, atol=2e-5)


def test_torch_fk_gradients_pass_gradcheck() -> None:
    rng = np.random.default_rng(10)
    q = torch.tensor(random_poses(rng, 2), requires_grad=True)
    q.data[0, 0:3] = 0.0  # also check the identity root, where axis-angle is singular
    off = torch.tensor(rest_offsets(SHAPE), requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda p, o: forward_kinematics_torch(p, o), (q, off), eps=1e-6, atol=1e-7, fast_mode=True
    )


def test_torch_fk_rejects_wrong_offsets_shape() -> None:
    with pytest.raises(ValidationError, match="offsets must have shape"):
        forward_kinematics_torch(torch.zeros(POSE_DIM), torch.zeros(25, 3))


@pytest.mark.parametrize("top", ["LeftArm", "RightUpLeg", "Neck", "Spine1"])
def test_subtree_kinematics_matches_the_whole_chain_below_its_top(top: str) -> None:
    rng = np.random.default_rng(11)
    base = random_poses(rng, 1)[0]
    joints = subtree_joints(J[top])
    assert joints[0] == J[top]
    assert all(PARENTS[j] in joints for j in joints[1:])
    # candidates: the base pose with the subtree's own angles from random poses
    own = ROOT_DIM + np.flatnonzero(np.isin(DOF_JOINT, joints))
    cand = np.repeat(base[None], 5, axis=0)
    cand[:, own] = random_poses(rng, 5)[:, own]
    off = torch.tensor(rest_offsets(SHAPE))
    pos0, rot0 = forward_kinematics_torch(torch.tensor(base), off)
    want_pos, want_rot = forward_kinematics_torch(torch.tensor(cand), off)
    pos, rot = subtree_kinematics_torch(
        torch.tensor(cand[:, ROOT_DIM:]),
        off,
        pos0[PARENTS[J[top]]],
        rot0[PARENTS[J[top]]],
        top=J[top],
    )
    np.testing.assert_allclose(pos.numpy(), want_pos[:, list(joints)].numpy(), atol=1e-12)
    np.testing.assert_allclose(rot.numpy(), want_rot[:, list(joints)].numpy(), atol=1e-12)


def test_subtree_kinematics_rejects_the_root() -> None:
    with pytest.raises(ValidationError, match="below the root"):
        subtree_kinematics_torch(
            torch.zeros(27), torch.zeros(26, 3), torch.zeros(3), torch.eye(3), top=0
        )


# --- rotations ------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    st.lists(
        st.floats(min_value=-10, max_value=10, allow_nan=False, allow_subnormal=False),
        min_size=3,
        max_size=3,
    )
)
def test_rotvec_to_matrix_matches_scipy(v: list[float]) -> None:
    expected = Rotation.from_rotvec(v).as_matrix()
    np.testing.assert_allclose(rotvec_to_matrix(np.array(v)), expected, atol=1e-12)
    got = rotvec_to_matrix_torch(torch.tensor(v, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(got, expected, atol=1e-12)


@pytest.mark.parametrize("scale", [0.0, 1e-12, 1e-8, 1e-6, 1e-4])
def test_rotvec_to_matrix_is_accurate_near_zero(scale: float) -> None:
    v = scale * np.array([0.3, -0.5, 0.8])
    expected = Rotation.from_rotvec(v).as_matrix()
    np.testing.assert_allclose(rotvec_to_matrix(v), expected, atol=1e-15)
    got32 = rotvec_to_matrix_torch(torch.tensor(v, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(got32, expected, atol=1e-6)


def test_rotvec_gradient_is_finite_at_zero() -> None:
    v = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    rotvec_to_matrix_torch(v)[0, 1].backward()  # type: ignore[no-untyped-call]
    assert v.grad is not None
    # d R[0,1] / d v = d(-v_z) / d v at the identity
    np.testing.assert_allclose(v.grad.numpy(), [0.0, 0.0, -1.0], atol=1e-12)


# --- sign conventions -----------------------------------------------------------------------


def test_positive_knee_flexion_moves_the_ankle_backwards() -> None:
    for side in ("Right", "Left"):
        d = _moved(f"{side}Foot", **{f"{side.lower()}_knee_flexion": 60})
        assert d[1] < -0.3
        assert d[2] > 0.1


@pytest.mark.parametrize("side", ["right", "left"])
def test_positive_shoulder_flexion_moves_the_wrist_forward_and_up(side: str) -> None:
    d = _moved(f"{side.capitalize()}Hand", **{f"{side}_shoulder_flexion": 60})
    assert d[1] > 0.3
    assert d[2] > 0.1
    assert abs(d[0]) < 1e-12


@pytest.mark.parametrize(("side", "sign"), [("right", 1.0), ("left", -1.0)])
def test_positive_shoulder_abduction_moves_the_wrist_away_from_the_body(
    side: str, sign: float
) -> None:
    d = _moved(f"{side.capitalize()}Hand", **{f"{side}_shoulder_abduction": 60})
    assert sign * d[0] > 0.3
    assert d[2] > 0.1


@pytest.mark.parametrize(("side", "sign"), [("right", 1.0), ("left", -1.0)])
def test_positive_hip_abduction_moves_the_foot_away_from_the_body(side: str, sign: float) -> None:
    d = _moved(f"{side.capitalize()}Foot", **{f"{side}_hip_abduction": 30})
    assert sign * d[0] > 0.2


@pytest.mark.parametrize("side", ["right", "left"])
def test_positive_hip_flexion_raises_the_knee_forward(side: str) -> None:
    d = _moved(f"{side.capitalize()}Leg", **{f"{side}_hip_flexion": 90})
    assert d[1] > 0.4
    assert d[2] > 0.4


@pytest.mark.parametrize("side", ["right", "left"])
def test_positive_elbow_flexion_brings_the_hand_forward_and_up(side: str) -> None:
    d = _moved(f"{side.capitalize()}Hand", **{f"{side}_elbow_flexion": 90})
    assert d[1] > 0.2
    assert d[2] > 0.2


@pytest.mark.parametrize(("side", "sign"), [("right", 1.0), ("left", -1.0)])
def test_positive_shoulder_internal_rotation_swings_the_forearm_to_the_midline(
    side: str, sign: float
) -> None:
    flexed = {f"{side}_elbow_flexion": 90.0}
    d = _posed(**flexed, **{f"{side}_shoulder_internal_rotation": 45.0}) - _posed(**flexed)
    assert -sign * d[J[f"{side.capitalize()}Hand"], 0] > 0.1


@pytest.mark.parametrize(("side", "sign"), [("right", 1.0), ("left", -1.0)])
def test_positive_hip_internal_rotation_turns_the_toes_inwards(side: str, sign: float) -> None:
    d = _moved(f"{side.capitalize()}ToeEnd", **{f"{side}_hip_internal_rotation": 30})
    assert -sign * d[0] > 0.05


@pytest.mark.parametrize("side", ["right", "left"])
def test_positive_dorsiflexion_raises_the_toes(side: str) -> None:
    d = _moved(f"{side.capitalize()}ToeEnd", **{f"{side}_ankle_dorsiflexion": 20})
    assert d[2] > 0.05


@pytest.mark.parametrize(("side", "sign"), [("right", 1.0), ("left", -1.0)])
def test_positive_ankle_inversion_turns_the_sole_to_the_midline(side: str, sign: float) -> None:
    q = neutral_pose(SHAPE)
    q[ROOT_DIM + DOF_NAMES.index(f"{side}_ankle_inversion")] = np.deg2rad(30)
    kin = forward_kinematics(q, SHAPE)
    sole = -kin.rotations[J[f"{side.capitalize()}Foot"]][:, 2]  # the foot's down axis
    assert -sign * sole[0] > 0.4


def test_positive_spine_flexion_moves_the_head_forward() -> None:
    d = _moved("HeadEnd", spine_flexion=45)
    assert d[1] > 0.2
    assert d[2] < 0


def test_spine_flexion_curves_the_chest_over_two_joints() -> None:
    q = neutral_pose(SHAPE)
    q[ROOT_DIM + DOF_NAMES.index("spine_flexion")] = np.deg2rad(40)
    r = forward_kinematics(q, SHAPE).rotations
    tilt1 = np.degrees(np.arccos(r[J["Spine1"]][2, 2]))
    tilt2 = np.degrees(np.arccos(r[J["Spine2"]][2, 2]))
    assert tilt1 == pytest.approx(20.0)
    assert tilt2 == pytest.approx(40.0)


def test_positive_neck_flexion_moves_the_head_forward_and_down() -> None:
    d = _moved("HeadEnd", neck_flexion=30)
    assert d[1] > 0.05
    assert d[2] < 0


def test_lateral_bend_and_twist_follow_the_documented_directions() -> None:
    assert _moved("HeadEnd", spine_lateral_bend=20)[0] > 0.1  # towards the subject's right
    # a positive twist turns the chest to the subject's left: the right shoulder comes forward
    assert _moved("RightArm", spine_axial_twist=30)[1] > 0.03
    assert _moved("HeadEnd", neck_axial_rotation=45)[0] < 0  # face turns to the left


def test_root_rotation_of_90_degrees_about_z_turns_the_facing_direction() -> None:
    q = neutral_pose(SHAPE)
    q[0:3] = (0.0, 0.0, np.pi / 2)
    kin = forward_kinematics(q, SHAPE)
    toe = kin.positions_m[J["RightToeEnd"]] - kin.positions_m[J["RightFoot"]]
    np.testing.assert_allclose(toe[:2] / np.linalg.norm(toe[:2]), [-1.0, 0.0], atol=1e-12)
    # the subject's right now points to +Y
    right = kin.positions_m[J["RightUpLeg"]] - kin.positions_m[J["LeftUpLeg"]]
    np.testing.assert_allclose(right / np.linalg.norm(right), [0.0, 1.0, 0.0], atol=1e-12)


def test_neutral_pose_faces_plus_y_with_right_at_plus_x() -> None:
    pos = _posed()
    assert pos[J["RightToeEnd"], 1] > pos[J["RightFoot"], 1]
    assert pos[J["RightArm"], 0] > 0 > pos[J["LeftArm"], 0]


def test_t_pose_holds_both_arms_horizontal() -> None:
    kin = forward_kinematics(t_pose(SHAPE), SHAPE)
    for side in ("Right", "Left"):
        arm = kin.positions_m[J[f"{side}HandEnd"]] - kin.positions_m[J[f"{side}Arm"]]
        assert abs(arm[2]) < 1e-12
        assert abs(arm[1]) < 1e-12
    assert kin.positions_m[J["RightHand"], 0] > 0.5
    assert kin.positions_m[J["LeftHand"], 0] < -0.5


# --- keypoints ------------------------------------------------------------------------------


def test_eventcap_keypoints_come_in_the_documented_order() -> None:
    kin = forward_kinematics(neutral_pose(SHAPE), SHAPE)
    kp = eventcap_keypoints(kin, SHAPE)
    assert kp.shape == (19, 3)
    assert len(EVENTCAP_KEYPOINTS) == 19
    idx = {n: i for i, n in enumerate(EVENTCAP_KEYPOINTS)}
    np.testing.assert_array_equal(kp[idx["pelvis"]], kin.positions_m[J["Hips"]])
    np.testing.assert_array_equal(kp[idx["left_knee"]], kin.positions_m[J["LeftLeg"]])
    head = kin.positions_m[J["Head"]]
    for side, sign in (("right", 1), ("left", -1)):
        eye, ear = kp[idx[f"{side}_eye"]], kp[idx[f"{side}_ear"]]
        assert eye[1] > head[1] + 0.05  # on the face
        assert sign * eye[0] > 0.01
        assert sign * ear[0] > 0.06  # at the sides of the head
        assert abs(eye[2] - SHAPE.height_m * 0.936) < 0.02  # eye height of the standard figure
    np.testing.assert_allclose(kp[idx["left_eye"]], kp[idx["right_eye"]] * [-1, 1, 1])


def test_face_keypoints_turn_with_the_head() -> None:
    q = neutral_pose(SHAPE)
    q[ROOT_DIM + DOF_NAMES.index("neck_axial_rotation")] = np.pi / 2
    kp = eventcap_keypoints(forward_kinematics(q, SHAPE), SHAPE)
    eye = kp[EVENTCAP_KEYPOINTS.index("right_eye")]
    head = forward_kinematics(q, SHAPE).positions_m[J["Head"]]
    assert eye[0] - head[0] < -0.05  # looking to the subject's left (-X)


def test_torch_keypoints_match_numpy() -> None:
    q = random_poses(np.random.default_rng(12), 4)
    kp = eventcap_keypoints(forward_kinematics(q, SHAPE), SHAPE)
    pos, rot = forward_kinematics_torch(torch.tensor(q), SHAPE)
    np.testing.assert_allclose(eventcap_keypoints_torch(pos, rot, SHAPE).numpy(), kp, atol=1e-12)


def test_democap_joints_use_headend_for_the_head() -> None:
    kin = forward_kinematics(neutral_pose(SHAPE), SHAPE)
    dj = democap_joints(kin)
    assert dj.shape == (19, 3)
    assert DEMOCAP_JOINT_INDEX[4] == J["HeadEnd"]
    np.testing.assert_array_equal(dj[4], kin.positions_m[J["HeadEnd"]])
