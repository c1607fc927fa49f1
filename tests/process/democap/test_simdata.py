"""Tests of process.democap.simdata: rig, visibility, D415 measurement model, fusion."""

from __future__ import annotations

import numpy as np
import pytest

from acquire.errors import ValidationError
from process.body import BodyShape, MarkerSet, make_motion
from process.democap.simdata import (
    BASELINE_M,
    SUBPIXEL_RMS_PX,
    Camera,
    PoseFrames,
    merge_views,
    observe,
    pose_frames,
    sample_rig,
    visibility,
)


def _camera_at(x: float) -> Camera:
    """A camera on the +x... axis looking along -x (towards the origin), world Z up."""
    c = np.array([x, 0.0, 0.0])
    z = -c / np.linalg.norm(c)
    xx = np.cross(z, [0.0, 0.0, 1.0])
    xx /= np.linalg.norm(xx)
    return Camera(centre_m=c, r_cw=np.stack([xx, np.cross(z, xx), z]), focal_px=623.0)


def _take(seed: int = 0) -> PoseFrames:
    rng = np.random.default_rng(seed)
    shape = BodyShape.sample(rng)
    markers = MarkerSet.for_shape(shape).jittered(rng)
    motion = make_motion("squat", seconds=1.0, rng=rng, rate_hz=30.0, shape=shape)
    return pose_frames(motion, shape, markers)


def test_rig_layout_and_camera_counts() -> None:
    rng = np.random.default_rng(0)
    cams = sample_rig(rng)
    assert len(cams) == 4
    for c in cams:
        assert 2.2 < np.hypot(*c.centre_m[:2]) < 2.8
        # each camera looks roughly at the actor's centre
        to_centre = np.array([0.0, 0.0, 0.9]) - c.centre_m
        assert c.r_cw[2] @ to_centre / np.linalg.norm(to_centre) > 0.99
    assert len(sample_rig(rng, num_cameras=3)) == 3
    two = sample_rig(rng, num_cameras=2)
    assert two[0].centre_m[:2] @ two[1].centre_m[:2] < 0  # an opposing pair
    with pytest.raises(ValidationError, match="num_cameras"):
        sample_rig(rng, num_cameras=5)


def test_capsule_between_camera_and_marker_occludes() -> None:
    marker = np.array([[0.0, 0.0, 1.0]])
    normal = np.array([[1.0, 0.0, 0.0]])
    cam = _camera_at(2.5)
    cam = Camera(centre_m=np.array([2.5, 0.0, 1.0]), r_cw=_camera_at(2.5).r_cw, focal_px=623.0)
    none = np.zeros((0, 3))
    assert visibility(marker, normal, none, none, np.zeros(0), [cam])[0, 0]
    # a vertical capsule of radius 5 cm at x = 1 m blocks the line of sight
    a, b = np.array([[1.0, 0.0, 0.5]]), np.array([[1.0, 0.0, 1.5]])
    assert not visibility(marker, normal, a, b, np.array([0.05]), [cam])[0, 0]
    # moved aside, it no longer does
    shift = np.array([0.0, 0.2, 0.0])
    a2, b2 = a + shift, b + shift
    assert visibility(marker, normal, a2, b2, np.array([0.05]), [cam])[0, 0]
    # a marker facing away is not detected
    assert not visibility(marker, -normal, none, none, np.zeros(0), [cam])[0, 0]


def test_body_self_occludes_some_markers_from_each_camera() -> None:
    take = _take()
    cams = sample_rig(np.random.default_rng(2))
    vis = visibility(
        take.markers_m[0],
        take.normals[0],
        take.caps_a_m[0],
        take.caps_b_m[0],
        take.caps_radius_m,
        cams,
    )
    per_cam = vis.mean(axis=1)
    assert np.all((per_cam > 0.2) & (per_cam < 0.8))  # a camera sees one side of the body
    assert vis.any(axis=0).mean() > 0.85  # the rig as a whole sees most markers


def test_depth_noise_grows_with_distance_squared() -> None:
    rng = np.random.default_rng(3)
    spread = []
    for x in (1.5, 3.0):
        cam = Camera(centre_m=np.array([x, 0.0, 1.0]), r_cw=_camera_at(x).r_cw, focal_px=623.0)
        take = PoseFrames(
            markers_m=np.array([[[0.0, 0.0, 1.0]]]),
            normals=np.array([[[1.0, 0.0, 0.0]]]),
            joints_m=np.zeros((1, 19, 3)),
            caps_a_m=np.zeros((1, 0, 3)),
            caps_b_m=np.zeros((1, 0, 3)),
            caps_radius_m=np.zeros(0),
            action="test",
        )
        xs = [observe(take, 0, [cam], rng, realistic=False)[0][0][0, 0] for _ in range(400)]
        spread.append(float(np.std(xs)))
    sigma = [np.hypot(z * z * SUBPIXEL_RMS_PX / (623.0 * BASELINE_M), 0.002) for z in (1.5, 3.0)]
    np.testing.assert_allclose(spread, sigma, rtol=0.15)
    assert spread[1] / spread[0] > 2.5


def test_merge_joins_close_points_of_different_cameras_only() -> None:
    a = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 1.0]])
    b = np.array([[0.006, 0.0, 1.0], [0.5, 0.03, 1.0]])
    merged = merge_views([a, b])
    assert len(merged) == 3  # (0,0,1) joined with its 6 mm twin; the 30 mm pair stays apart
    assert np.any(np.all(np.isclose(merged, [0.003, 0.0, 1.0]), axis=1))
    same_cam = merge_views([np.array([[0.0, 0.0, 1.0], [0.005, 0.0, 1.0]])])
    assert len(same_cam) == 2
    # points outside the capture box are dropped
    assert len(merge_views([np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 1.0]])])) == 1


def test_observation_is_deterministic_for_a_seed() -> None:
    take = _take(4)
    cams = sample_rig(np.random.default_rng(5))
    v1, _ = observe(take, 10, cams, np.random.default_rng(6))
    v2, _ = observe(take, 10, cams, np.random.default_rng(6))
    for p, q in zip(v1, v2, strict=True):
        np.testing.assert_array_equal(p, q)


def test_fused_cloud_is_close_to_the_markers() -> None:
    take = _take(7)
    rng = np.random.default_rng(8)
    cams = sample_rig(rng)
    views, vis = observe(take, 5, cams, rng)
    cloud = merge_views(views)
    d = np.linalg.norm(cloud[:, None] - take.markers_m[5][None], axis=-1).min(axis=1)
    # most points lie within a few cm of a true marker (ghosts and gross errors excepted)
    assert np.mean(d < 0.04) > 0.85
    assert len(cloud) >= vis.any(axis=0).sum() * 0.8
