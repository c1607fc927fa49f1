"""The template rasteriser: silhouettes, local surface points, boundary normals."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest
import torch

from mocaprig.errors import ValidationError
from mocaprig.process.body.kinematics import neutral_pose
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import DOF_NAMES, ROOT_DIM
from mocaprig.process.body.surface import capsules, raycast, render_pinhole, signed_distance
from mocaprig.process.eventcap.camera import EventCamera
from mocaprig.process.eventcap.raster import (
    pose_local_points,
    pose_local_points_torch,
    rasterize,
)

SHAPE = BodyShape.from_height(1.75)
DISTORTION = np.array([-0.25, 0.08, 0.001, -0.0015, 0.0])


def _camera(
    width: int = 240, height: int = 180, distortion: npt.ArrayLike | None = None
) -> EventCamera:
    """A camera 3.2 m in front of the subject (world -Y), 1 m up, looking along +Y."""
    t = np.eye(4)
    t[:3, :3] = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    t[:3, 3] = (0.0, -3.2, 1.0)
    f = 200.0 * width / 240
    k = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    d = np.zeros(5) if distortion is None else np.asarray(distortion, dtype=np.float64)
    return EventCamera(K=k, distortion=d, T_world_cam=t, width=width, height=height)


def _pose() -> npt.NDArray[np.float64]:
    q = neutral_pose(SHAPE)
    for name, deg in (
        ("right_shoulder_abduction", 35.0),
        ("left_shoulder_flexion", 25.0),
        ("left_elbow_flexion", 50.0),
        ("right_hip_abduction", 10.0),
    ):
        q[ROOT_DIM + DOF_NAMES.index(name)] = np.deg2rad(deg)
    q[0:3] = (0.0, 0.0, 0.3)  # turned 17° about the vertical
    return q


@pytest.mark.parametrize(("width", "height"), [(240, 180), (346, 260)])
def test_silhouette_segments_and_depth_match_render_pinhole(width: int, height: int) -> None:
    cam = _camera(width, height)
    q = _pose()
    r = rasterize(q, SHAPE, cam)
    ref = render_pinhole(capsules(q, SHAPE), cam.K, np.linalg.inv(cam.T_world_cam), width, height)
    assert r.mask.shape == (height, width)
    assert r.mask.sum() > 1000
    np.testing.assert_array_equal(r.mask, ref.segment >= 0)
    np.testing.assert_array_equal(r.segment, ref.segment)
    np.testing.assert_allclose(r.depth_m, ref.depth_m, atol=1e-9)
    # Rays were cast in a box around the body, not the whole image.
    u0, u1, v0, v1 = r.box
    assert (u1 - u0) * (v1 - v0) < 0.6 * width * height


def test_local_points_reposed_at_the_same_pose_are_the_ray_cast_world_points() -> None:
    cam = _camera(distortion=DISTORTION)
    q = _pose()
    r = rasterize(q, SHAPE, cam)
    v, u = np.nonzero(r.mask)
    world = pose_local_points(q, SHAPE, r.segment[v, u], r.local_points_m[v, u])
    # Independent cast in the world frame from the camera centre through the same pixels.
    dirs_cam = cam.pixel_rays(np.stack([u, v], axis=-1).astype(np.float64))
    dirs = dirs_cam @ cam.T_world_cam[:3, :3].T
    origins = np.broadcast_to(cam.T_world_cam[:3, 3], dirs.shape)
    depth, cid, _ = raycast(origins, dirs, capsules(q, SHAPE))
    assert np.all(cid >= 0)
    np.testing.assert_array_equal(cid, r.capsule_id[v, u])
    hits = origins + depth[:, None] * dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    np.testing.assert_allclose(world, hits, atol=1e-9)


def test_boundary_surface_points_project_back_onto_their_pixels_through_the_lens() -> None:
    cam = _camera(distortion=DISTORTION)
    q = _pose()
    r = rasterize(q, SHAPE, cam)
    uv, _ = cam.project(pose_local_points(q, SHAPE, r.boundary_segment, r.boundary_local_m))
    np.testing.assert_allclose(uv, r.boundary_uv, atol=1e-6)


def test_local_points_stay_on_their_capsule_when_reposed_at_another_pose() -> None:
    cam = _camera()
    q = _pose()
    r = rasterize(q, SHAPE, cam)
    v, u = np.nonzero(r.mask)
    other = q.copy()
    other[ROOT_DIM + DOF_NAMES.index("left_elbow_flexion")] += 0.7
    other[3:6] += (0.3, -0.1, 0.05)
    world = pose_local_points(other, SHAPE, r.segment[v, u], r.local_points_m[v, u])
    sd = signed_distance(world, capsules(other, SHAPE))
    own = sd[np.arange(u.size), r.capsule_id[v, u]]
    np.testing.assert_allclose(own, 0.0, atol=1e-9)


def test_boundary_is_the_silhouette_minus_its_erosion_with_outward_normals() -> None:
    r = rasterize(_pose(), SHAPE, _camera())
    bu, bv = r.boundary_uv[:, 0], r.boundary_uv[:, 1]
    assert np.all(r.mask[bv, bu])
    # Each boundary pixel has a 4-neighbour outside the silhouette.
    pad = np.pad(r.mask, 1)
    nb_out = ~(pad[bv, bu + 1] & pad[bv + 2, bu + 1] & pad[bv + 1, bu] & pad[bv + 1, bu + 2])
    assert np.all(nb_out)
    np.testing.assert_allclose(np.linalg.norm(r.boundary_normals, axis=-1), 1.0, atol=1e-12)
    h, w = r.mask.shape

    def inside(points: npt.NDArray[np.float64]) -> npt.NDArray[np.bool_]:
        p = np.rint(points).astype(int)
        ok = (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
        return np.where(ok, r.mask[p[:, 1].clip(0, h - 1), p[:, 0].clip(0, w - 1)], False)

    out_step = inside(r.boundary_uv + 2.0 * r.boundary_normals)
    in_step = inside(r.boundary_uv - 2.0 * r.boundary_normals)
    assert out_step.mean() < 0.05
    assert in_step.mean() > 0.9


def test_torch_reposing_matches_numpy_and_is_differentiable() -> None:
    q = _pose()
    r = rasterize(q, SHAPE, _camera())
    other = q + np.random.default_rng(3).normal(scale=0.05, size=q.shape)
    expected = pose_local_points(other, SHAPE, r.boundary_segment, r.boundary_local_m)
    pose_t = torch.tensor(other, dtype=torch.float64, requires_grad=True)
    got = pose_local_points_torch(pose_t, SHAPE, r.boundary_segment, r.boundary_local_m)
    np.testing.assert_allclose(got.detach().numpy(), expected, atol=1e-12)
    (grad,) = torch.autograd.grad(got[:, 0].sum(), pose_t)
    assert torch.all(torch.isfinite(grad))
    assert float(grad[3]) == pytest.approx(r.boundary_segment.size)  # d x / d root x


def test_torch_reposing_takes_a_batch_of_poses_and_differentiable_local_points() -> None:
    q = _pose()
    r = rasterize(q, SHAPE, _camera())
    poses = np.stack([q, q + 0.02])
    expected = pose_local_points(poses, SHAPE, r.boundary_segment, r.boundary_local_m)
    local = torch.tensor(r.boundary_local_m, requires_grad=True)
    got = pose_local_points_torch(
        torch.tensor(poses, dtype=torch.float64), SHAPE, torch.tensor(r.boundary_segment), local
    )
    assert tuple(got.shape) == (2, r.boundary_segment.size, 3)
    np.testing.assert_allclose(got.detach().numpy(), expected, atol=1e-12)
    (grad,) = torch.autograd.grad(got.sum(), local)
    assert torch.all(torch.isfinite(grad))


def test_a_body_behind_the_camera_rasterises_to_nothing() -> None:
    q = _pose()
    q[4] = -6.0  # 2.8 m behind the camera
    r = rasterize(q, SHAPE, _camera())
    assert not r.mask.any()
    assert r.boundary_uv.shape == (0, 2)
    assert np.all(r.segment == -1)


def test_rasterize_rejects_a_pose_of_the_wrong_length() -> None:
    with pytest.raises(ValidationError, match="pose"):
        rasterize(np.zeros(32), SHAPE, _camera())


def test_camera_rejects_a_non_positive_focal_length() -> None:
    k = np.diag([-200.0, 200.0, 1.0])
    with pytest.raises(ValidationError, match="fx, fy > 0"):
        EventCamera(K=k, distortion=np.zeros(5), T_world_cam=np.eye(4), width=240, height=180)


def test_reposing_rejects_joint_indices_out_of_range() -> None:
    with pytest.raises(ValidationError, match="joint indices"):
        pose_local_points(_pose(), SHAPE, np.array([0, 99]), np.zeros((2, 3)))
