"""Analytic derivatives of points on the posed skeleton with respect to the pose.

The pose increment is the one the solvers step with: a world-frame rotation increment ``δω``
of the root (``R ← exp(δω)·R``, no singularity at π), the root translation ``δt`` and the 27
joint angles ``δθ`` of :mod:`process.body.skeleton` (33 numbers, in that order). A world
point ``x`` riding on segment ``s`` (the frame of joint ``s``) moves with the root as
``δω × (x − t) + δt`` and with each angle as ``a × (x − p_j)`` for every Euler axis ``a`` of
every joint ``j`` at or above ``s`` that the angle turns (axes and pivots from the posed
skeleton). A joint's own position rides on its parent's segment: its own rotation does not
move it. Tests check every column against autograd through
:func:`process.body.kinematics.forward_kinematics_torch`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import torch
from scipy.spatial.transform import Rotation

from mocaprig.process.body.kinematics import forward_kinematics, skew_torch
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import JOINTS, NUM_DOF, PARENTS, POSE_DIM, ROOT_DIM

__all__ = [
    "JOINT_SEGMENT",
    "PoseGeometry",
    "point_jacobian",
    "pose_geometry",
]

FloatArray = npt.NDArray[np.float64]


def _euler_map() -> FloatArray:
    """(27, 26, 3): the Euler angles (X, Y, Z order) each DoF gives each joint, per radian.

    Derived from the public forward kinematics (its documented ``R_local = Rx·Ry·Rz``): with
    one DoF at a test angle and all others 0, every joint's local rotation turns about one
    axis, so its rotation vector divided by the angle is that DoF's column of the map.
    """
    test = 0.3
    poses = np.zeros((NUM_DOF, POSE_DIM))
    poses[:, ROOT_DIM:] = np.eye(NUM_DOF) * test
    rots = forward_kinematics(poses, BodyShape.from_height(1.75)).rotations
    par = np.array([max(p, 0) for p in PARENTS])
    local = np.swapaxes(rots[:, par], -1, -2) @ rots
    local[:, 0] = rots[:, 0]  # the root's "parent" is the world
    rv = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_rotvec().reshape(NUM_DOF, -1, 3)
    out = np.asarray(rv, dtype=np.float64) / test
    out[np.abs(out) < 1e-9] = 0.0
    return out


def _ancestors() -> npt.NDArray[np.bool_]:
    """(26, 26): ``[s, j]`` is True when joint ``j`` is ``s`` or one of its ancestors."""
    a = np.zeros((len(JOINTS), len(JOINTS)), dtype=bool)
    for s in range(len(JOINTS)):
        j = s
        while j >= 0:
            a[s, j] = True
            j = PARENTS[j]
    return a


_EULER = _euler_map()
# [s, d, j, k]: how much DoF d turns joint j about its Euler axis k, for points on segment s.
_COEFF = torch.from_numpy(
    (_ancestors()[:, None, :, None] * _EULER[None]).reshape(len(JOINTS) * NUM_DOF, -1)
)  # (26 * 27, 26 * 3)
_EULER_FLAT = torch.from_numpy(_EULER.reshape(NUM_DOF, -1).copy())

#: The segment each joint's *position* rides on (its parent's; the root's own): the index to
#: pass to :func:`point_jacobian` for joint positions.
JOINT_SEGMENT: tuple[int, ...] = tuple(max(p, 0) for p in PARENTS)
_PARENT_OR_ROOT = torch.tensor(JOINT_SEGMENT)


@dataclass(frozen=True, slots=True)
class PoseGeometry:
    """Posed skeleton of every problem (frame) and its derivative operators.

    ``d_mat[f, s, d] @ x - d_vec[f, s, d]`` is the derivative of a world point ``x`` riding
    on segment ``s`` at frame ``f`` with respect to angle ``d``.
    """

    pos: torch.Tensor  # (F, 26, 3) m
    rot: torch.Tensor  # (F, 26, 3, 3)
    root_t: torch.Tensor  # (F, 3) m
    d_mat: torch.Tensor  # (F, 26, 27, 3, 3)
    d_vec: torch.Tensor  # (F, 26, 27, 3)


def pose_geometry(
    pos: torch.Tensor,
    rot: torch.Tensor,
    root_r: torch.Tensor,
    root_t: torch.Tensor,
    angles: torch.Tensor,
) -> PoseGeometry:
    """The derivative operators of F posed skeletons (float64).

    Args:
        pos: joint positions (F, 26, 3), world, m.
        rot: joint rotations (F, 26, 3, 3), world.
        root_r: root rotations (F, 3, 3); root_t: root translations (F, 3), m.
        angles: the 27 joint angles (F, 27), rad.
    """
    e = (angles @ _EULER_FLAT).reshape(angles.shape[0], len(JOINTS), 3)
    par_rot = rot[:, _PARENT_OR_ROOT]
    par_rot = torch.cat([root_r[:, None], par_rot[:, 1:]], dim=1)  # (F, 26, 3, 3)
    ca, sa = torch.cos(e[..., 0]), torch.sin(e[..., 0])
    cb, sb = torch.cos(e[..., 1]), torch.sin(e[..., 1])
    zero, one = torch.zeros_like(ca), torch.ones_like(ca)
    local_axes = torch.stack(
        [
            torch.stack([one, zero, zero], -1),  # X
            torch.stack([zero, ca, sa], -1),  # Rx·Y
            torch.stack([sb, -sa * cb, ca * cb], -1),  # Rx·Ry·Z
        ],
        dim=-2,
    )  # (F, 26, 3 axes, 3)
    axes = (par_rot[:, :, None] @ local_axes[..., None])[..., 0]  # world axes (F, 26, 3, 3)
    moment = torch.linalg.cross(axes, pos[:, :, None].expand_as(axes))  # a × pivot
    n_f, n_j = pos.shape[0], len(JOINTS)
    d_mat = (_COEFF @ skew_torch(axes).reshape(n_f, n_j * 3, 9)).reshape(n_f, n_j, NUM_DOF, 3, 3)
    d_vec = (_COEFF @ moment.reshape(n_f, n_j * 3, 3)).reshape(n_f, n_j, NUM_DOF, 3)
    return PoseGeometry(pos=pos, rot=rot, root_t=root_t, d_mat=d_mat, d_vec=d_vec)


def point_jacobian(
    geo: PoseGeometry, frame: torch.Tensor, segment: torch.Tensor, x: torch.Tensor
) -> torch.Tensor:
    """d x / d (the 33-number pose increment, module doc) for world points ``x`` (..., 3) on
    ``segment`` (...,) of ``frame`` (...,): (..., 3, 33)."""
    j_root_r = -skew_torch(x - geo.root_t[frame])  # δω × (x − t)
    j_root_t = torch.eye(3, dtype=x.dtype).expand(j_root_r.shape)
    n_f, n_j = geo.d_mat.shape[:2]
    d_mat = geo.d_mat.reshape(n_f, n_j, NUM_DOF * 3, 3)[frame, segment]  # (..., 81, 3)
    j_ang = (d_mat @ x[..., None])[..., 0].reshape(*x.shape[:-1], NUM_DOF, 3)
    j_ang = j_ang - geo.d_vec[frame, segment]
    return torch.cat([j_root_r, j_root_t, j_ang.transpose(-1, -2)], dim=-1)
