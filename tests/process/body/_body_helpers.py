"""Shared helpers for the body-model tests: seeded random poses within the joint limits, our
own motions written as BVH clips."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from mocaprig.process.body.bvh import BvhClip
from mocaprig.process.body.kinematics import forward_kinematics
from mocaprig.process.body.shape import BodyShape, rest_offsets
from mocaprig.process.body.skeleton import DOF_LIMITS_RAD, JOINTS, PARENTS, POSE_DIM, ROOT_DIM


def random_poses(rng: np.random.Generator, n: int) -> npt.NDArray[np.float64]:
    """``n`` pose vectors: random root rotation and translation, angles uniform in limits."""
    q = np.zeros((n, POSE_DIM))
    q[:, 0:3] = rng.normal(scale=1.5, size=(n, 3))
    q[:, 3:6] = rng.normal(scale=2.0, size=(n, 3))
    lo, hi = DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1]
    q[:, ROOT_DIM:] = rng.uniform(lo, hi, size=(n, lo.size))
    return q


#: BVH axes (Y up, CMU) -> body axes (Z up).
BVH_TO_BODY = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])


def motion_as_bvh(
    poses: npt.NDArray[np.float64], shape: BodyShape, rate_hz: float, *, name: str = "ours"
) -> BvhClip:
    """Our own skeleton and poses as a Y-up BVH clip (CMU axes), ZXY channels."""
    c = BVH_TO_BODY
    kin = forward_kinematics(poses, shape)
    offsets = rest_offsets(shape) @ c  # rows: C^T offset
    cols = []
    for j, p in enumerate(PARENTS):
        r = (
            kin.rotations[:, j]
            if p < 0
            else np.swapaxes(kin.rotations[:, p], 1, 2) @ kin.rotations[:, j]
        )
        euler = Rotation.from_matrix(c.T @ r @ c).as_euler("ZXY", degrees=True)
        if p < 0:
            cols.append(kin.positions_m[:, 0] @ c)
        cols.append(euler)
    channels = tuple(
        (("Xposition", "Yposition", "Zposition") if p < 0 else ())
        + ("Zrotation", "Xrotation", "Yrotation")
        for p in PARENTS
    )
    return BvhClip(
        name=name,
        joint_names=JOINTS,
        parents=PARENTS,
        offsets_m=offsets,
        channels=channels,
        frames=np.concatenate(cols, axis=1),
        frame_time_s=1.0 / rate_hz,
    )
