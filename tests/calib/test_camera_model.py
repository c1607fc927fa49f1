"""Tests of calib.camera_model: the one Brown–Conrady projection, checked against OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mocaprig.calib import camera_model, charuco, registration, time_align
from mocaprig.calib.camera_model import (
    DEFAULT_MIN_DEPTH_M,
    distort_normalized,
    project_camera,
    project_camera_torch,
    project_points,
    project_points_torch,
    world_to_camera,
    world_to_camera_torch,
)
from mocaprig.errors import ValidationError


def _random_camera(
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A zero-skew K, a moderate (k1, k2, p1, p2, k3) and a random pose T_world_cam."""
    K = np.array(
        [
            [rng.uniform(300.0, 900.0), 0.0, rng.uniform(100.0, 500.0)],
            [0.0, rng.uniform(300.0, 900.0), rng.uniform(80.0, 300.0)],
            [0.0, 0.0, 1.0],
        ]
    )
    dist = rng.normal(0.0, [0.2, 0.1, 0.005, 0.005, 0.05])
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, 1.0, 3)).as_matrix()
    T[:3, 3] = rng.normal(0.0, 1.0, 3)
    return K, dist, T


def _points_in_front(rng: np.random.Generator, T: np.ndarray, n: int) -> np.ndarray:
    """World points 0.3–5 m in front of the camera, within ±0.6 of the axis (normalised)."""
    z = rng.uniform(0.3, 5.0, n)
    xy = rng.uniform(-0.6, 0.6, (n, 2)) * z[:, None]
    pc = np.column_stack([xy, z])
    out: np.ndarray = pc @ T[:3, :3].T + T[:3, 3]
    return out


def _cv2_project(pw: np.ndarray, T: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    r_cw = T[:3, :3].T
    rvec = cv2.Rodrigues(r_cw)[0]
    tvec = -r_cw @ T[:3, 3]
    uv, _ = cv2.projectPoints(pw.reshape(-1, 1, 3), rvec, tvec, K, dist)
    out: np.ndarray = uv.reshape(-1, 2)
    return out


@pytest.mark.parametrize("seed", range(8))
def test_matches_cv2_project_points(seed: int) -> None:
    rng = np.random.default_rng(seed)
    K, dist, T = _random_camera(rng)
    pw = _points_in_front(rng, T, 500)
    uv, z = project_points(pw, T, K, dist)
    np.testing.assert_allclose(uv, _cv2_project(pw, T, K, dist), rtol=0, atol=1e-6)
    np.testing.assert_allclose(z, world_to_camera(pw, T)[:, 2], rtol=0, atol=1e-12)
    assert np.all(z > 0.29)
    # No distortion: None and zeros are the same, and equal OpenCV's pinhole.
    uv0, _ = project_points(pw, T, K, None)
    np.testing.assert_array_equal(uv0, project_points(pw, T, K, np.zeros(5))[0])
    np.testing.assert_allclose(uv0, _cv2_project(pw, T, K, np.zeros(5)), rtol=0, atol=1e-6)


def test_distort_normalized_matches_cv2() -> None:
    rng = np.random.default_rng(20)
    dist = rng.normal(0.0, [0.2, 0.1, 0.005, 0.005, 0.05])
    xy = rng.uniform(-0.6, 0.6, (300, 2))
    pts = np.column_stack([xy, np.ones(len(xy))])
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), dist)
    np.testing.assert_allclose(distort_normalized(xy, dist), ref.reshape(-1, 2), atol=1e-12)
    np.testing.assert_array_equal(distort_normalized(xy, None), xy)


def test_skew_is_applied() -> None:
    K = np.array([[600.0, 3.0, 320.0], [0.0, 610.0, 240.0], [0.0, 0.0, 1.0]])
    dist = np.array([0.1, -0.02, 0.001, -0.002, 0.003])
    pc = np.array([[0.2, -0.1, 2.0], [-0.3, 0.4, 1.5]])
    xd = distort_normalized(pc[:, :2] / pc[:, 2:], dist)
    want = np.column_stack([600.0 * xd[:, 0] + 3.0 * xd[:, 1] + 320.0, 610.0 * xd[:, 1] + 240.0])
    np.testing.assert_allclose(project_camera(pc, K, dist), want, rtol=0, atol=1e-12)


def test_points_behind_the_camera() -> None:
    rng = np.random.default_rng(3)
    K, dist, _ = _random_camera(rng)
    T = np.eye(4)  # world = camera: the depths below are exact
    pc = np.array(
        [
            [0.1, 0.2, 2.0],  # in front
            [0.1, 0.2, 0.0],  # at the centre's plane
            [0.1, 0.2, -2.0],  # behind
            [0.1, 0.2, 0.5 * DEFAULT_MIN_DEPTH_M],  # nearer than the limit
            [0.1, 0.2, 0.03],  # in front, but nearer than a 5 cm limit
            [np.nan, 0.2, 2.0],  # NaN coordinate, finite depth
            [0.1, 0.2, np.nan],  # NaN depth
        ]
    )
    with np.errstate(all="raise"):  # no warning for the invalid points
        uv, z = project_points(pc, T, K, dist)
        uv5 = project_camera(pc, K, dist, min_depth_m=0.05)
    np.testing.assert_array_equal(z[:5], pc[:5, 2])
    assert np.isnan(z[5:]).all()  # a NaN coordinate spreads through the rigid transform
    assert np.isfinite(uv[[0, 4]]).all()
    assert np.isnan(uv[1:4]).all()
    assert np.isnan(uv[5:]).all()
    assert np.isfinite(uv5[0]).all()
    assert np.isnan(uv5[1:]).all()
    # Without the test, a point behind the camera is mirrored through it, as OpenCV does.
    raw = project_camera(pc[[0, 2]], K, dist, min_depth_m=None)
    ref = _cv2_project(pc[[0, 2]], np.eye(4), K, dist)
    np.testing.assert_allclose(raw, ref, atol=1e-6)
    mirrored = project_camera(-pc[0], K, dist, min_depth_m=None)
    np.testing.assert_allclose(mirrored, raw[0], rtol=0, atol=1e-9)
    with np.errstate(all="raise"):
        assert not np.isfinite(project_camera(pc[1], K, dist, min_depth_m=None)).all()


def test_inputs_are_not_modified() -> None:
    rng = np.random.default_rng(4)
    K, dist, T = _random_camera(rng)
    pw = _points_in_front(rng, T, 50)
    pw[3] = T[:3, 3] - T[:3, 2]  # behind the camera: its output is written NaN
    pw[4] = np.nan
    args = [pw, T, K, dist]
    before = [a.copy() for a in args]
    for a in args:
        a.setflags(write=False)
    uv, z = project_points(pw, T, K, dist)
    pc = world_to_camera(pw, T)
    project_camera(pc, K, dist, min_depth_m=None)
    project_camera(pc, K, dist, min_depth_m=0.05)
    distort_normalized(pc[:, :2], dist)
    for a, b in zip(args, before, strict=True):
        np.testing.assert_array_equal(a, b)
    assert np.isnan(uv[3]).all()
    assert not np.shares_memory(z, pc)


def test_broadcasting_over_points_and_per_point_intrinsics() -> None:
    rng = np.random.default_rng(5)
    cams = [_random_camera(rng) for _ in range(3)]
    pcs = [world_to_camera(_points_in_front(rng, T, 40), T) for _, _, T in cams]
    pc = np.concatenate(pcs)
    Ks = np.concatenate([np.repeat(K[None], 40, axis=0) for K, _, _ in cams])
    Ds = np.concatenate([np.repeat(d[None], 40, axis=0) for _, d, _ in cams])
    got = project_camera(pc, Ks, Ds)
    want = np.concatenate([project_camera(p, K, d) for p, (K, d, _) in zip(pcs, cams, strict=True)])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    # Leading axes (frames, markers) and a single point.
    K, dist, T = cams[0]
    pw = _points_in_front(rng, T, 60).reshape(4, 15, 3)
    uv, z = project_points(pw, T, K, dist)
    assert uv.shape == (4, 15, 2)
    assert z.shape == (4, 15)
    np.testing.assert_allclose(uv.reshape(-1, 2), project_points(pw.reshape(-1, 3), T, K, dist)[0])
    one, z1 = project_points(pw[0, 0], T, K, dist)
    assert one.shape == (2,)
    assert z1.shape == ()
    np.testing.assert_allclose(one, uv[0, 0])
    empty, ze = project_points(np.zeros((0, 3)), T, K, dist)
    assert empty.shape == (0, 2)
    assert ze.shape == (0,)


def test_shape_errors() -> None:
    K = np.eye(3)
    with pytest.raises(ValidationError, match="points_cam"):
        project_camera(np.zeros((4, 2)), K)
    with pytest.raises(ValidationError, match="K must"):
        project_camera(np.ones((4, 3)), np.eye(4))
    with pytest.raises(ValidationError, match="distortion"):
        project_camera(np.ones((4, 3)), K, np.zeros(4))
    with pytest.raises(ValidationError, match="T_world_cam"):
        world_to_camera(np.ones((4, 3)), np.eye(3))
    with pytest.raises(ValidationError, match="xy"):
        distort_normalized(np.ones((4, 3)), None)


def test_calib_modules_share_the_one_projection() -> None:
    """registration, charuco and time_align project with this module, not copies of it."""
    assert registration.project_points is camera_model.project_points
    assert not hasattr(registration, "_project_cam")
    assert not hasattr(charuco, "_project")
    rng = np.random.default_rng(6)
    K, _, T = _random_camera(rng)
    K[0, 1] = 1.5
    pw = _points_in_front(rng, T, 30).reshape(3, 10, 3)
    pw[0, 0] = T[:3, 3] + 0.04 * T[:3, 2]  # 4 cm in front: under time_align's 5 cm limit
    got = time_align._project(pw, K, T)
    want, _ = project_points(pw, T, K, None, min_depth_m=0.05)
    np.testing.assert_array_equal(got, want)
    assert np.isnan(got[0, 0]).all()
    assert np.isfinite(got.reshape(-1, 2)[1:]).all()


@pytest.mark.parametrize("seed", range(4))
def test_torch_twin_matches_numpy_projection(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    K, dist, T = _random_camera(rng)
    K[0, 1] = 2.0  # the skew term too
    pw = _points_in_front(rng, T, 400)
    uv, z = project_points(pw, T, K, dist)
    t = torch.from_numpy
    uv_t, z_t = project_points_torch(t(pw), t(T), t(K), t(dist))
    assert uv_t.dtype == torch.float64
    np.testing.assert_allclose(uv_t.numpy(), uv, rtol=0, atol=1e-9)
    np.testing.assert_allclose(z_t.numpy(), z, rtol=0, atol=1e-12)
    no_dist, _ = project_points_torch(t(pw), t(T), t(K), None)
    np.testing.assert_allclose(no_dist.numpy(), project_points(pw, T, K)[0], rtol=0, atol=1e-9)
    pc = world_to_camera(pw, T)
    np.testing.assert_allclose(world_to_camera_torch(t(pw), t(T)).numpy(), pc, atol=1e-12)


def test_torch_twin_masks_points_behind_the_camera_like_numpy() -> None:
    rng = np.random.default_rng(7)
    K, dist, _ = _random_camera(rng)
    pc = np.array([[0.1, 0.2, 2.0], [0.1, 0.2, 0.0], [0.1, 0.2, -2.0], [0.1, 0.2, 0.03]])
    t = torch.from_numpy
    for limit in (DEFAULT_MIN_DEPTH_M, 0.05, None):
        want = project_camera(pc[[0, 2, 3]], K, dist, min_depth_m=limit)
        got = project_camera_torch(t(pc[[0, 2, 3]]), t(K), t(dist), min_depth_m=limit).numpy()
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)  # NaN where numpy has NaN
    # Masked points get zero gradients, never NaN ones.
    x = t(pc).clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(project_camera_torch(x, t(K), t(dist)).nan_to_num(0.0).sum(), x)
    assert torch.isfinite(grad).all()
    assert (grad[1:3] == 0).all()
    assert (grad[0] != 0).any()


def test_torch_twin_gradients_match_finite_differences() -> None:
    rng = np.random.default_rng(8)
    K, dist, T = _random_camera(rng)
    pw = torch.from_numpy(_points_in_front(rng, T, 5)).requires_grad_(True)
    k = torch.from_numpy(K).requires_grad_(True)
    d = torch.from_numpy(dist).requires_grad_(True)
    t_wc = torch.from_numpy(T)

    def uv_of(p: torch.Tensor, k: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        return project_points_torch(p, t_wc, k, d)[0]

    assert torch.autograd.gradcheck(uv_of, (pw, k, d))


def test_torch_twin_rejects_wrong_shapes() -> None:
    with pytest.raises(ValidationError, match="points_cam"):
        project_camera_torch(torch.zeros(4, 2), torch.eye(3))
    with pytest.raises(ValidationError, match="K must"):
        project_camera_torch(torch.ones(4, 3), torch.eye(4))
    with pytest.raises(ValidationError, match="distortion"):
        project_camera_torch(torch.ones(4, 3), torch.eye(3), torch.zeros(4))
    with pytest.raises(ValidationError, match="T_world_cam"):
        world_to_camera_torch(torch.ones(4, 3), torch.eye(3))
