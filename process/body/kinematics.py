"""Forward kinematics of the 26-joint skeleton, in numpy (batched) and torch (differentiable).

Frames. Every joint frame is aligned with the body axes in the rest pose (+X subject's right,
+Y forward, +Z up), so a joint's local rotation is a rotation of the body-aligned frame. For
joint ``j`` with parent ``p``::

    R_world[j] = R_world[p] @ R_local[j]
    x_world[j] = x_world[p] + R_world[p] @ offset[j]          (offset from rest_offsets)

and for the root ``R_world[0] = rotvec_to_matrix(pose[0:3])``, ``x_world[0] = pose[3:6]``.

Local rotations. A joint's DoF act as intrinsic Euler rotations in the fixed order flexion,
abduction, twist: ``R_local = R(flex) @ R(abd) @ R(twist)`` about the local X, Y and Z axes.
Axis signs are mirrored between the sides so a positive angle is the named motion on both:

=========================  ======  ======  =================================================
DoF                        axis R  axis L  positive angle
=========================  ======  ======  =================================================
spine_flexion              -X             chest bends forward (over Spine1 and Spine2, ½ each)
spine_lateral_bend         +Y             chest bends to the subject's right (½ + ½)
spine_axial_twist          +Z             chest turns to the subject's left (½ + ½)
neck_flexion               -X             head bends forward (chin down)
neck_axial_rotation        +Z             head turns to the subject's left
shoulder_flexion           +X      +X     arm swings forward (+Y) and up
shoulder_abduction         -Y      +Y     arm rises sideways away from the body
shoulder_internal_rotation +Z      -Z     a forward-pointing forearm swings to the midline
elbow_flexion              +X      +X     hand comes forward and up
elbow_pronation            +Z      -Z     palm (facing the thigh at rest) turns backwards
hip_flexion                +X      +X     thigh swings forward and up
hip_abduction              -Y      +Y     leg moves sideways away from the body
hip_internal_rotation      +Z      -Z     toes turn towards the midline
knee_flexion               -X      -X     shank bends backwards
ankle_dorsiflexion         +X      +X     toes rise
ankle_inversion            +Y      -Y     sole turns to face the midline
=========================  ======  ======  =================================================

Rest pose: standing, arms hanging, palms facing the thighs (forearm mid-prone, thumbs forward),
feet parallel pointing +Y.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from mocaprig.errors import ValidationError
from mocaprig.process.body.shape import BodyShape, rest_offsets
from mocaprig.process.body.skeleton import (
    DEMOCAP_JOINT_INDEX,
    DOF_JOINT,
    DOF_LIMITS_RAD,
    DOF_NAMES,
    JOINT_INDEX,
    JOINTS,
    NUM_DOF,
    PARENTS,
    POSE_DIM,
    ROOT_DIM,
)
from mocaprig.validation import check_finite, check_shape

__all__ = [
    "EULER_MAP",
    "EVENTCAP_KEYPOINTS",
    "EVENTCAP_KEYPOINT_JOINTS",
    "Kinematics",
    "clamp_to_limits",
    "clamp_to_limits_torch",
    "democap_joints",
    "eventcap_keypoints",
    "eventcap_keypoints_torch",
    "face_offsets",
    "forward_kinematics",
    "forward_kinematics_torch",
    "neutral_pose",
    "rotvec_to_matrix",
    "rotvec_to_matrix_torch",
    "skew_torch",
    "subtree_joints",
    "subtree_kinematics_torch",
    "t_pose",
    "within_limits",
]

FloatArray = npt.NDArray[np.float64]

# --- the DoF -> joint-rotation table --------------------------------------------------------

# (axis, sign on the right/central side) per DoF; the left side flips Y and Z (a mirror in x
# keeps rotations about X and reverses those about Y and Z).
_RIGHT_AXES: dict[str, tuple[int, float]] = {
    "spine_flexion": (0, -1.0),
    "spine_lateral_bend": (1, 1.0),
    "spine_axial_twist": (2, 1.0),
    "neck_flexion": (0, -1.0),
    "neck_axial_rotation": (2, 1.0),
    "shoulder_flexion": (0, 1.0),
    "shoulder_abduction": (1, -1.0),
    "shoulder_internal_rotation": (2, 1.0),
    "elbow_flexion": (0, 1.0),
    "elbow_pronation": (2, 1.0),
    "hip_flexion": (0, 1.0),
    "hip_abduction": (1, -1.0),
    "hip_internal_rotation": (2, 1.0),
    "knee_flexion": (0, -1.0),
    "ankle_dorsiflexion": (0, 1.0),
    "ankle_inversion": (1, 1.0),
}


def _build_euler_map() -> FloatArray:
    """Matrix (27, 26 * 3) mapping the 27 angles to per-joint X, Y, Z Euler angles (rad).

    Entry ``[d, 3 j + k]`` is ``sign * weight`` when DoF ``d`` turns joint ``j`` about its
    local axis ``k``; each joint's DoF are flexion (X), abduction (Y), twist (Z) in that order,
    so ``R_local = Rx @ Ry @ Rz`` of these angles.
    """
    m = np.zeros((NUM_DOF, len(JOINTS) * 3))
    spine2 = JOINT_INDEX["Spine2"]
    for d, (name, joint) in enumerate(zip(DOF_NAMES, DOF_JOINT, strict=True)):
        side, _, rest = name.partition("_")
        key = rest if side in ("left", "right") else name
        axis, sign = _RIGHT_AXES[key]
        if side == "left" and axis != 0:
            sign = -sign
        if key.startswith("spine_"):
            # The spine's 3 DoF bend Spine1 and Spine2 half each so the chest curves.
            m[d, 3 * joint + axis] = 0.5 * sign
            m[d, 3 * spine2 + axis] = 0.5 * sign
        else:
            m[d, 3 * joint + axis] = sign
    return m


_EULER_MAP = _build_euler_map()
_EULER_MAP.setflags(write=False)
#: (27, 26, 3): the Euler angle (local X, Y, Z; ``R_local = Rx·Ry·Rz``) each DoF adds to each
#: joint per radian of the DoF: the axis sign of the module table, ½ for the spine's two
#: joints. Read-only.
EULER_MAP: FloatArray = _EULER_MAP.reshape(NUM_DOF, len(JOINTS), 3)


def _build_levels() -> tuple[tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]], ...]:
    """Joints grouped by depth below the root: ((joints, parents), ...) per level."""
    depth = [0] * len(JOINTS)
    for j in range(1, len(JOINTS)):
        depth[j] = depth[PARENTS[j]] + 1
    levels = []
    for lv in range(1, max(depth) + 1):
        idx = [j for j in range(len(JOINTS)) if depth[j] == lv]
        levels.append(
            (np.array(idx, dtype=np.int64), np.array([PARENTS[j] for j in idx], dtype=np.int64))
        )
    return tuple(levels)


# Evaluating the chain one depth level at a time turns 25 small products into 7 batched ones.
_LEVELS = _build_levels()
# Row order of the level-wise concatenation, and its inverse permutation back to joint order.
_LEVEL_ORDER = np.concatenate([[0], *(idx for idx, _ in _LEVELS)])
_TO_JOINT_ORDER = np.argsort(_LEVEL_ORDER)
#: Per level, the rows of the parents in that concatenation.
_LEVEL_PARENT_ROWS = tuple(_TO_JOINT_ORDER[par] for _, par in _LEVELS)


def _skew(v: FloatArray) -> FloatArray:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3)."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = np.zeros_like(x)
    return np.stack([o, -z, y, z, o, -x, -y, x, o], axis=-1).reshape(*v.shape[:-1], 3, 3)


@dataclass(frozen=True, slots=True, eq=False)
class Kinematics:
    """Posed skeleton in the world frame.

    Attributes:
        positions_m: joint positions (..., 26, 3), world frame, metres.
        rotations: world rotation of each joint frame (..., 26, 3, 3); column k is the joint's
            local axis k (X right, Y forward, Z up at rest) in world coordinates.
    """

    positions_m: FloatArray
    rotations: FloatArray


# --- rotations ------------------------------------------------------------------------------


def rotvec_to_matrix(rotvec: npt.ArrayLike) -> FloatArray:
    """Rotation matrices (..., 3, 3) from axis-angle vectors (..., 3), radians.

    Rodrigues' formula in the half-angle form ``R = I + sinc(θ) K + ½ sinc²(θ/2) K²``; it
    has no cancellation near θ = 0 and is exact at 0.
    """
    v = np.asarray(check_shape(rotvec, ["...", 3], name="rotvec"), dtype=np.float64)
    theta2 = np.sum(v * v, axis=-1)
    small = theta2 < np.finfo(np.float64).eps
    theta = np.sqrt(np.where(small, 1.0, theta2))
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(theta) / theta)
    half = np.where(small, 1.0 - theta2 / 24.0, np.sin(0.5 * theta) / (0.5 * theta))
    b = 0.5 * half * half
    k = _skew(v)
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def skew_torch(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3): ``skew_torch(a) @ b = a × b``."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape[:-1], 3, 3)


def rotvec_to_matrix_torch(rotvec: torch.Tensor) -> torch.Tensor:
    """Differentiable :func:`rotvec_to_matrix` for tensors (..., 3) -> (..., 3, 3).

    Gradients are finite everywhere, including at the zero rotation.
    """
    if rotvec.shape[-1:] != (3,):
        msg = f"rotvec must have shape (..., 3), got {tuple(rotvec.shape)}"
        raise ValidationError(msg)
    theta2 = (rotvec * rotvec).sum(-1)
    small = theta2 < torch.finfo(rotvec.dtype).eps
    # Route the small-angle entries through a dummy value so neither branch produces NaN
    # gradients (torch.where differentiates both).
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    half = torch.where(small, 1.0 - theta2 / 24.0, torch.sin(0.5 * theta) / (0.5 * theta))
    b = 0.5 * half * half
    k = skew_torch(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


# --- forward kinematics ---------------------------------------------------------------------


def _offsets_np(shape_or_offsets: BodyShape | npt.ArrayLike) -> FloatArray:
    if isinstance(shape_or_offsets, BodyShape):
        return rest_offsets(shape_or_offsets)
    off = check_shape(shape_or_offsets, [len(JOINTS), 3], name="offsets")
    return np.asarray(check_finite(off, name="offsets"), dtype=np.float64)


def _euler_xyz_np(e: FloatArray) -> FloatArray:
    """``Rx(e0) @ Ry(e1) @ Rz(e2)`` for Euler angles (..., 3) -> (..., 3, 3)."""
    ca, cb, cc = np.cos(e[..., 0]), np.cos(e[..., 1]), np.cos(e[..., 2])
    sa, sb, sc = np.sin(e[..., 0]), np.sin(e[..., 1]), np.sin(e[..., 2])
    rows = (
        cb * cc, -cb * sc, sb,
        sa * sb * cc + ca * sc, ca * cc - sa * sb * sc, -sa * cb,
        sa * sc - ca * sb * cc, ca * sb * sc + sa * cc, ca * cb,
    )  # fmt: skip
    return np.stack(rows, axis=-1).reshape(*e.shape[:-1], 3, 3)


def _euler_xyz_torch(e: torch.Tensor) -> torch.Tensor:
    """Torch twin of :func:`_euler_xyz_np`."""
    c, s = torch.cos(e), torch.sin(e)
    ca, cb, cc = c[..., 0], c[..., 1], c[..., 2]
    sa, sb, sc = s[..., 0], s[..., 1], s[..., 2]
    rows = (
        cb * cc, -cb * sc, sb,
        sa * sb * cc + ca * sc, ca * cc - sa * sb * sc, -sa * cb,
        sa * sc - ca * sb * cc, ca * sb * sc + sa * cc, ca * cb,
    )  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(*e.shape[:-1], 3, 3)


def _check_pose(pose: npt.ArrayLike) -> FloatArray:
    arr = check_shape(pose, ["...", POSE_DIM], name="pose")
    return np.asarray(check_finite(arr, name="pose"), dtype=np.float64)


def forward_kinematics(pose: npt.ArrayLike, shape: BodyShape | npt.ArrayLike) -> Kinematics:
    """Joint positions and rotations for poses (..., 33).

    Args:
        pose: pose vectors (..., 33) as in :mod:`process.body.skeleton` (root axis-angle rad,
            root translation m, 27 angles rad).
        shape: a :class:`BodyShape`, or rest offsets (26, 3) m as from :func:`rest_offsets`.

    Returns:
        :class:`Kinematics` with positions (..., 26, 3) m and rotations (..., 26, 3, 3).

    Raises:
        ValidationError: wrong shapes or non-finite values.
    """
    q = _check_pose(pose)
    off = _offsets_np(shape)
    batch = q.shape[:-1]
    local = _euler_xyz_np((q[..., ROOT_DIM:] @ _EULER_MAP).reshape(*batch, len(JOINTS), 3))
    rots = np.empty((*batch, len(JOINTS), 3, 3))
    pos = np.empty((*batch, len(JOINTS), 3))
    rots[..., 0, :, :] = rotvec_to_matrix(q[..., 0:3]) @ local[..., 0, :, :]
    pos[..., 0, :] = q[..., 3:6]
    for idx, par in _LEVELS:
        parent_rot = rots[..., par, :, :]
        pos[..., idx, :] = pos[..., par, :] + (parent_rot @ off[idx][..., None])[..., 0]
        rots[..., idx, :, :] = parent_rot @ local[..., idx, :, :]
    return Kinematics(positions_m=pos, rotations=rots)


def forward_kinematics_torch(
    pose: torch.Tensor, offsets: torch.Tensor | BodyShape
) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable forward kinematics for pose tensors (..., 33), float32 or float64.

    Args:
        pose: pose vectors (..., 33) as in :func:`forward_kinematics`.
        offsets: rest offsets (26, 3) m (differentiable, e.g. for shape fitting), or one
            set per pose (..., 26, 3) broadcastable with ``pose``'s batch (a shape per
            problem), or a :class:`BodyShape` (converted to ``pose``'s dtype and device).

    Returns:
        ``(positions (..., 26, 3) m, rotations (..., 26, 3, 3))``, world frame; matches
        :func:`forward_kinematics` to ~1e-12 in float64.

    Raises:
        ValidationError: wrong shapes.
    """
    if pose.shape[-1:] != (POSE_DIM,):
        msg = f"pose must have shape (..., {POSE_DIM}), got {tuple(pose.shape)}"
        raise ValidationError(msg)
    if isinstance(offsets, BodyShape):
        off = torch.as_tensor(rest_offsets(offsets), dtype=pose.dtype, device=pose.device)
    else:
        if tuple(offsets.shape[-2:]) != (len(JOINTS), 3):
            msg = f"offsets must have shape (..., {len(JOINTS)}, 3), got {tuple(offsets.shape)}"
            raise ValidationError(msg)
        off = offsets.to(dtype=pose.dtype, device=pose.device)
    kw: dict[str, Any] = {"dtype": pose.dtype, "device": pose.device}
    batch = pose.shape[:-1]
    euler = (pose[..., ROOT_DIM:] @ torch.tensor(_EULER_MAP, **kw)).reshape(*batch, -1, 3)
    local = _euler_xyz_torch(euler)
    # Build level by level and concatenate (no in-place writes, so autograd stays simple);
    # row r of the concatenation is joint _LEVEL_ORDER[r].
    all_rots = (rotvec_to_matrix_torch(pose[..., 0:3]) @ local[..., 0, :, :])[..., None, :, :]
    all_pos = pose[..., None, 3:6]
    for (idx, _), rows in zip(_LEVELS, _LEVEL_PARENT_ROWS, strict=True):
        parent_rows = torch.as_tensor(rows, device=pose.device)
        parent_rot = all_rots.index_select(-3, parent_rows)
        parent_pos = all_pos.index_select(-2, parent_rows)
        jidx = torch.as_tensor(idx, device=pose.device)
        new_pos = parent_pos + (parent_rot @ off.index_select(-2, jidx)[..., None])[..., 0]
        new_rot = parent_rot @ local.index_select(-3, jidx)
        all_rots = torch.cat([all_rots, new_rot], dim=-3)
        all_pos = torch.cat([all_pos, new_pos], dim=-2)
    order = torch.as_tensor(_TO_JOINT_ORDER, device=pose.device)
    return all_pos.index_select(-2, order), all_rots.index_select(-3, order)


def subtree_joints(top: int) -> tuple[int, ...]:
    """Joint ``top`` and every joint below it, in joint order (parents first)."""
    under = np.zeros(len(JOINTS), dtype=bool)
    under[top] = True
    for j in range(top + 1, len(JOINTS)):  # parents come before their children
        under[j] = under[PARENTS[j]]
    return tuple(int(j) for j in np.flatnonzero(under))


def subtree_kinematics_torch(
    angles: torch.Tensor,
    offsets: torch.Tensor,
    parent_pos: torch.Tensor,
    parent_rot: torch.Tensor,
    *,
    top: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The world pose of joint ``top`` (not the root) and the joints below it
    (:func:`subtree_joints` order) when only their angles change: what
    :func:`forward_kinematics_torch` gives for those joints, without the rest of the chain.

    Args:
        angles: (..., 27) rad; only the DoF of the subtree's joints are read.
        offsets: (..., 26, 3) rest offsets (m), broadcast against ``angles``.
        parent_pos, parent_rot: (..., 3), (..., 3, 3) world pose of ``top``'s parent.

    Returns:
        Positions (..., S, 3) and rotations (..., S, 3, 3), world frame.

    Raises:
        ValidationError: ``top`` is the root or not a joint.
    """
    if not 0 < top < len(JOINTS):
        msg = f"subtree_kinematics_torch: top must be a joint below the root, got {top!r}"
        raise ValidationError(msg)
    joints = subtree_joints(top)
    row = {j: k for k, j in enumerate(joints)}
    emap = torch.as_tensor(EULER_MAP[:, list(joints)], dtype=angles.dtype, device=angles.device)
    local = _euler_xyz_torch(torch.einsum("...d,dsk->...sk", angles, emap))
    pos: list[torch.Tensor] = []
    rot: list[torch.Tensor] = []
    for k, j in enumerate(joints):
        if j == top:
            pp, pr = parent_pos, parent_rot
        else:
            pp, pr = pos[row[PARENTS[j]]], rot[row[PARENTS[j]]]
        pos.append(pp + (pr @ offsets[..., j, :, None])[..., 0])
        rot.append(pr @ local[..., k, :, :])
    # the top joint's position does not depend on its own angles: broadcast it to the rest
    batch = np.broadcast_shapes(*(x.shape[:-1] for x in pos), *(r.shape[:-2] for r in rot))
    return (
        torch.stack([x.expand(*batch, 3) for x in pos], dim=-2),
        torch.stack([r.expand(*batch, 3, 3) for r in rot], dim=-3),
    )


# --- limits and canonical poses -------------------------------------------------------------


def clamp_to_limits(pose: npt.ArrayLike) -> FloatArray:
    """A copy of ``pose`` (..., 33) with the 27 angles clipped into ``DOF_LIMITS_RAD``."""
    q = np.array(_check_pose(pose), dtype=np.float64)  # copy: never write into the input
    q[..., ROOT_DIM:] = np.clip(q[..., ROOT_DIM:], DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1])
    return q


def clamp_to_limits_torch(pose: torch.Tensor) -> torch.Tensor:
    """:func:`clamp_to_limits` for tensors (..., 33); out-of-range angles get zero gradient."""
    lim = torch.tensor(DOF_LIMITS_RAD, dtype=pose.dtype, device=pose.device)
    angles = torch.clamp(pose[..., ROOT_DIM:], lim[:, 0], lim[:, 1])
    return torch.cat([pose[..., :ROOT_DIM], angles], dim=-1)


def within_limits(pose: npt.ArrayLike, *, tol_rad: float = 1e-9) -> npt.NDArray[np.bool_]:
    """Whether every angle of each pose (..., 33) lies within its limits (± ``tol_rad``)."""
    a = _check_pose(pose)[..., ROOT_DIM:]
    ok = (a >= DOF_LIMITS_RAD[:, 0] - tol_rad) & (a <= DOF_LIMITS_RAD[:, 1] + tol_rad)
    return np.asarray(np.all(ok, axis=-1))


def neutral_pose(shape: BodyShape | None = None) -> FloatArray:
    """The rest pose (33,): identity root, all angles 0.

    With a ``shape`` the root is raised to ``shape.hips_height_m`` so the feet stand flat on
    the floor (z = 0) at the origin; without one the Hips joint is at the origin.
    """
    q = np.zeros(POSE_DIM)
    if shape is not None:
        q[5] = shape.hips_height_m
    return q


def t_pose(shape: BodyShape | None = None) -> FloatArray:
    """The T-pose (33,): :func:`neutral_pose` with both arms abducted 90° (palms down)."""
    q = neutral_pose(shape)
    for side in ("left", "right"):
        q[ROOT_DIM + DOF_NAMES.index(f"{side}_shoulder_abduction")] = np.pi / 2
    return q


# --- keypoints ------------------------------------------------------------------------------

#: EventCap keypoint order: 15 body joints then 4 face points (eventcap-method.md §2.2). The
#: face points are fixed offsets in the Head frame (:func:`face_offsets`).
EVENTCAP_KEYPOINTS: tuple[str, ...] = (
    "pelvis",
    "neck",
    "head",
    "right_shoulder",
    "right_elbow",
    "right_wrist",
    "left_shoulder",
    "left_elbow",
    "left_wrist",
    "right_hip",
    "right_knee",
    "right_ankle",
    "left_hip",
    "left_knee",
    "left_ankle",
    "right_eye",
    "left_eye",
    "right_ear",
    "left_ear",
)
#: The skeleton joint standing for each of the 15 body keypoints.
EVENTCAP_KEYPOINT_JOINTS: tuple[int, ...] = tuple(
    JOINT_INDEX[n]
    for n in (
        "Hips",
        "Neck",
        "Head",
        "RightArm",
        "RightForeArm",
        "RightHand",
        "LeftArm",
        "LeftForeArm",
        "LeftHand",
        "RightUpLeg",
        "RightLeg",
        "RightFoot",
        "LeftUpLeg",
        "LeftLeg",
        "LeftFoot",
    )
)
_NUM_BODY_KP = len(EVENTCAP_KEYPOINT_JOINTS)


def face_offsets(shape: BodyShape) -> FloatArray:
    """Right eye, left eye, right ear, left ear (4, 3) in the Head frame, metres.

    Eyes sit on the face 0.026H above the Head joint (eye level 0.936H of the standard figure)
    and 0.36 head radii either side; ears at the sides of the head near the joint's level.
    """
    r = shape.head_radius_m
    fwd = shape.head_forward_m
    eye_z = 0.29 * shape.head_length_m
    ear_z = 0.06 * shape.head_length_m
    return np.array(
        [
            (0.36 * r, fwd + 0.92 * r, eye_z),
            (-0.36 * r, fwd + 0.92 * r, eye_z),
            (0.98 * r, fwd - 0.2 * r, ear_z),
            (-0.98 * r, fwd - 0.2 * r, ear_z),
        ]
    )


def eventcap_keypoints(kin: Kinematics, shape: BodyShape) -> FloatArray:
    """The 19 EventCap keypoints (..., 19, 3), world frame, m, in :data:`EVENTCAP_KEYPOINTS`."""
    head = JOINT_INDEX["Head"]
    body = kin.positions_m[..., list(EVENTCAP_KEYPOINT_JOINTS), :]
    face = (
        kin.positions_m[..., head, None, :]
        + (kin.rotations[..., head, None, :, :] @ face_offsets(shape)[..., None])[..., 0]
    )
    return np.concatenate([body, face], axis=-2)


def eventcap_keypoints_torch(
    positions: torch.Tensor, rotations: torch.Tensor, shape: BodyShape
) -> torch.Tensor:
    """:func:`eventcap_keypoints` from :func:`forward_kinematics_torch` outputs -> (..., 19, 3)."""
    head = JOINT_INDEX["Head"]
    face_off = torch.as_tensor(face_offsets(shape), dtype=positions.dtype, device=positions.device)
    body = positions[..., list(EVENTCAP_KEYPOINT_JOINTS), :]
    face = (
        positions[..., head, None, :]
        + (rotations[..., head, None, :, :] @ face_off[..., None])[..., 0]
    )
    return torch.cat([body, face], dim=-2)


def democap_joints(kin: Kinematics) -> FloatArray:
    """DeMoCap's 19 evaluation joints (..., 19, 3) in ``skeleton.DEMOCAP_JOINTS`` order, m."""
    return kin.positions_m[..., list(DEMOCAP_JOINT_INDEX), :]


if len(EVENTCAP_KEYPOINTS) != _NUM_BODY_KP + 4:
    msg = "kinematics tables are inconsistent"  # pragma: no cover - table typo
    raise RuntimeError(msg)
