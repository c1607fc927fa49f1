"""The analytic pose Jacobian of points on the skeleton, against autograd."""

from __future__ import annotations

import numpy as np
import torch

from mocaprig.process.body import (
    DOF_LIMITS_RAD,
    JOINTS,
    BodyShape,
    forward_kinematics_torch,
    rest_offsets,
    rotvec_to_matrix_torch,
)
from mocaprig.process.body.jacobian import JOINT_SEGMENT, point_jacobian, pose_geometry


def _posed(
    d: torch.Tensor,
    root_r: torch.Tensor,
    root_t: torch.Tensor,
    ang: torch.Tensor,
    off: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Joints and rotations after the increment ``d`` (F, 33): exp(δω)·R, t + δt, θ + δθ."""
    r = rotvec_to_matrix_torch(d[:, :3]) @ root_r
    local = torch.cat([torch.zeros_like(d[:, :6]), ang + d[:, 6:]], dim=1)
    pos_b, rot_b = forward_kinematics_torch(local, off)
    return (r[:, None] @ pos_b[..., None])[..., 0] + (root_t + d[:, 3:6])[:, None], r[
        :, None
    ] @ rot_b


def test_point_jacobians_of_joints_and_riding_points_match_autograd() -> None:
    rng = np.random.default_rng(0)
    f = 3
    off = torch.from_numpy(rest_offsets(BodyShape.sample(rng)))
    root_r = rotvec_to_matrix_torch(torch.from_numpy(rng.normal(0, 1, (f, 3))))
    root_t = torch.from_numpy(rng.normal(0, 1, (f, 3)))
    lo, hi = DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1]
    ang = torch.from_numpy(rng.uniform(lo, hi, (f, 27)))
    local_pt = torch.from_numpy(rng.normal(0, 0.1, (len(JOINTS), 3)))  # one point per segment
    zero = torch.zeros(f, 33, dtype=torch.float64)
    pos, rot = _posed(zero, root_r, root_t, ang, off)
    geo = pose_geometry(pos, rot, root_r, root_t, ang)
    frames = torch.arange(f)[:, None].expand(f, len(JOINTS))
    segs = torch.arange(len(JOINTS)).expand(f, -1)
    riding = pos + (rot @ local_pt[..., None])[..., 0]
    j_ride = point_jacobian(geo, frames, segs, riding)
    j_joint = point_jacobian(geo, frames, torch.tensor(JOINT_SEGMENT).expand(f, -1), pos)

    def points(d: torch.Tensor) -> torch.Tensor:
        p, r = _posed(d, root_r, root_t, ang, off)
        return torch.cat([p + (r @ local_pt[..., None])[..., 0], p], dim=1)

    full = torch.autograd.functional.jacobian(points, zero)  # type: ignore[no-untyped-call]
    want = torch.stack([full[i, :, :, i] for i in range(f)])
    torch.testing.assert_close(j_ride, want[:, : len(JOINTS)], rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(j_joint, want[:, len(JOINTS) :], rtol=1e-9, atol=1e-10)


def test_forward_kinematics_takes_a_shape_per_pose() -> None:
    rng = np.random.default_rng(1)
    shapes = [BodyShape.sample(rng) for _ in range(3)]
    pose = torch.from_numpy(rng.normal(0, 0.3, (3, 33)))
    off = torch.from_numpy(np.stack([rest_offsets(s) for s in shapes]))
    pos, rot = forward_kinematics_torch(pose, off)
    for i, s in enumerate(shapes):
        p1, r1 = forward_kinematics_torch(pose[i], s)
        torch.testing.assert_close(pos[i], p1)
        torch.testing.assert_close(rot[i], r1)
