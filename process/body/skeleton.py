"""The kinematic skeleton: named joints, the 27 bounded joint-angle DoF and the pose layout.

World and body frames are right-handed, Z up, metres. At zero root rotation the subject faces
+Y and +X points to the subject's right. The rest pose (all angles 0) is the anatomical neutral
stance: standing upright, arms hanging at the sides.

A *pose vector* has ``POSE_DIM = 33`` entries::

    [0:3]   root rotation, axis-angle (rad), body -> world
    [3:6]   root (Hips joint) translation in the world (m)
    [6:33]  the 27 joint angles (rad) in ``DOF_NAMES`` order, 0 = neutral; a positive angle
            is the first-named motion of the DoF (flexion, abduction, internal rotation,
            pronation, dorsiflexion, inversion) on both sides.

(``../shared/docs/eventcap-method.md`` §2.1 gives the allocation and the limits.)
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = [
    "DEMOCAP_JOINTS",
    "DEMOCAP_JOINT_INDEX",
    "DEMOCAP_PARENTS",
    "DOF_JOINT",
    "DOF_LIMITS_DEG",
    "DOF_LIMITS_RAD",
    "DOF_NAMES",
    "JOINTS",
    "JOINT_INDEX",
    "NUM_DOF",
    "PARENTS",
    "POSE_DIM",
    "ROOT_DIM",
]

#: Joint names; the order is the index used by every array with a joint axis.
JOINTS: tuple[str, ...] = (
    "Hips",  # 0 pelvis centre, the root
    "Spine1",  # 1 lower thoracic spine
    "Spine2",  # 2 chest (upper thoracic spine)
    "Neck",  # 3 base of the neck (C7 level)
    "Head",  # 4 head centre (atlanto-occipital joint)
    "HeadEnd",  # 5 top of the head
    "RightShoulder",  # 6 sterno-clavicular base of the right clavicle (fixed)
    "RightArm",  # 7 right gleno-humeral joint
    "RightForeArm",  # 8 right elbow
    "RightHand",  # 9 right wrist
    "RightHandEnd",  # 10 right knuckles
    "LeftShoulder",  # 11
    "LeftArm",  # 12
    "LeftForeArm",  # 13
    "LeftHand",  # 14
    "LeftHandEnd",  # 15
    "RightUpLeg",  # 16 right hip joint
    "RightLeg",  # 17 right knee
    "RightFoot",  # 18 right ankle
    "RightToeBase",  # 19 right ball of the foot
    "RightToeEnd",  # 20 right toe tip
    "LeftUpLeg",  # 21
    "LeftLeg",  # 22
    "LeftFoot",  # 23
    "LeftToeBase",  # 24
    "LeftToeEnd",  # 25
)

JOINT_INDEX: dict[str, int] = {name: i for i, name in enumerate(JOINTS)}

#: Parent joint index of each joint (-1 for the root).
PARENTS: tuple[int, ...] = (
    -1, 0, 1, 2, 3, 4,  # spine and head
    2, 6, 7, 8, 9,  # right arm
    2, 11, 12, 13, 14,  # left arm
    0, 16, 17, 18, 19,  # right leg
    0, 21, 22, 23, 24,  # left leg
)  # fmt: skip

ROOT_DIM = 6
NUM_DOF = 27
POSE_DIM = ROOT_DIM + NUM_DOF

#: The 27 bounded DoF: (name, joint whose local rotation it drives, limits in degrees).
_DOF_TABLE: tuple[tuple[str, str, float, float], ...] = (
    ("spine_flexion", "Spine1", -30.0, 90.0),
    ("spine_lateral_bend", "Spine1", -30.0, 30.0),
    ("spine_axial_twist", "Spine1", -30.0, 30.0),
    ("neck_flexion", "Neck", -45.0, 45.0),
    ("neck_axial_rotation", "Neck", -80.0, 80.0),
    ("left_shoulder_flexion", "LeftArm", -50.0, 180.0),
    ("left_shoulder_abduction", "LeftArm", -30.0, 180.0),
    ("left_shoulder_internal_rotation", "LeftArm", -90.0, 90.0),
    ("right_shoulder_flexion", "RightArm", -50.0, 180.0),
    ("right_shoulder_abduction", "RightArm", -30.0, 180.0),
    ("right_shoulder_internal_rotation", "RightArm", -90.0, 90.0),
    ("left_elbow_flexion", "LeftForeArm", 0.0, 145.0),
    ("left_elbow_pronation", "LeftForeArm", -85.0, 80.0),
    ("right_elbow_flexion", "RightForeArm", 0.0, 145.0),
    ("right_elbow_pronation", "RightForeArm", -85.0, 80.0),
    ("left_hip_flexion", "LeftUpLeg", -30.0, 125.0),
    ("left_hip_abduction", "LeftUpLeg", -25.0, 45.0),
    ("left_hip_internal_rotation", "LeftUpLeg", -60.0, 40.0),
    ("right_hip_flexion", "RightUpLeg", -30.0, 125.0),
    ("right_hip_abduction", "RightUpLeg", -25.0, 45.0),
    ("right_hip_internal_rotation", "RightUpLeg", -60.0, 40.0),
    ("left_knee_flexion", "LeftLeg", 0.0, 140.0),
    ("right_knee_flexion", "RightLeg", 0.0, 140.0),
    ("left_ankle_dorsiflexion", "LeftFoot", -45.0, 20.0),
    ("left_ankle_inversion", "LeftFoot", -25.0, 35.0),
    ("right_ankle_dorsiflexion", "RightFoot", -45.0, 20.0),
    ("right_ankle_inversion", "RightFoot", -25.0, 35.0),
)

DOF_NAMES: tuple[str, ...] = tuple(row[0] for row in _DOF_TABLE)
#: Joint index driven by each DoF, shape (27,).
DOF_JOINT: tuple[int, ...] = tuple(JOINT_INDEX[row[1]] for row in _DOF_TABLE)
#: Anatomical limits, shape (27, 2), degrees and radians.
DOF_LIMITS_DEG: npt.NDArray[np.float64] = np.array([row[2:] for row in _DOF_TABLE])
DOF_LIMITS_RAD: npt.NDArray[np.float64] = np.deg2rad(DOF_LIMITS_DEG)
DOF_LIMITS_DEG.setflags(write=False)
DOF_LIMITS_RAD.setflags(write=False)

#: The DeMoCap 19-joint evaluation skeleton in its output order (democap-method.md §6.2) and
#: the joint of ours that stands for each. DeMoCap's "Head" is the source's HeadEnd (index 8).
DEMOCAP_JOINTS: tuple[str, ...] = (
    "Hips", "Spine1", "Spine2", "Neck", "Head",
    "RightArm", "RightForeArm", "RightHand",
    "LeftArm", "LeftForeArm", "LeftHand",
    "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase",
    "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase",
)  # fmt: skip
DEMOCAP_JOINT_INDEX: tuple[int, ...] = tuple(
    JOINT_INDEX["HeadEnd" if name == "Head" else name] for name in DEMOCAP_JOINTS
)


def _democap_parents() -> tuple[int, ...]:
    pos = {j: k for k, j in enumerate(DEMOCAP_JOINT_INDEX)}
    out = []
    for j in DEMOCAP_JOINT_INDEX:
        p = PARENTS[j]
        while p >= 0 and p not in pos:  # skip joints the 19-joint skeleton leaves out
            p = PARENTS[p]
        out.append(pos.get(p, -1))
    return tuple(out)


#: Parent of each DeMoCap joint as an index into :data:`DEMOCAP_JOINTS` (-1 for Hips): our
#: skeleton's parent, skipping the joints DeMoCap leaves out (the clavicles, the head centre),
#: so the arms hang from Spine2 and the head top from the neck.
DEMOCAP_PARENTS: tuple[int, ...] = _democap_parents()

if len(DOF_NAMES) != NUM_DOF or len(PARENTS) != len(JOINTS):  # pragma: no cover - table typo
    msg = "skeleton tables are inconsistent"
    raise RuntimeError(msg)
