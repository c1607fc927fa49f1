"""Capsule surface: exact ray casting against analytic cases and pinhole rendering."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from mocaprig.errors import ValidationError
from mocaprig.process.body.kinematics import forward_kinematics, neutral_pose, t_pose
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import JOINT_INDEX
from mocaprig.process.body.surface import (
    CAPSULE_NAMES,
    Capsules,
    capsule_template,
    capsules,
    raycast,
    render_pinhole,
    signed_distance,
)
from tests.process.body._body_helpers import random_poses

SHAPE = BodyShape.from_height(1.75)


def _one_capsule(a: tuple[float, ...], b: tuple[float, ...], r: float) -> Capsules:
    return Capsules(
        a_m=np.array([a], dtype=float),
        b_m=np.array([b], dtype=float),
        radius_m=np.array([r]),
        joint=np.array([7]),
    )


UNIT = _one_capsule((-1.0, 0.0, 0.0), (1.0, 0.0, 0.0), 0.5)  # along X, radius 0.5


def _cast(
    origin: tuple[float, ...], direction: tuple[float, ...], caps: Capsules = UNIT
) -> tuple[float, int, npt.NDArray[np.float64]]:
    depth, cid, normal = raycast(np.array([origin]), np.array([direction]), caps)
    return float(depth[0]), int(cid[0]), normal[0]


def test_ray_hits_the_cylinder_at_the_analytic_distance() -> None:
    depth, cid, normal = _cast((0.3, 0.0, 5.0), (0.0, 0.0, -2.0))  # unnormalised on purpose
    assert depth == pytest.approx(4.5, abs=1e-12)
    assert cid == 0
    np.testing.assert_allclose(normal, [0.0, 0.0, 1.0], atol=1e-12)


def test_ray_hits_a_spherical_end_cap() -> None:
    depth, cid, normal = _cast((3.0, 0.0, 0.3), (-1.0, 0.0, 0.0))
    x_hit = 1.0 + np.sqrt(0.5**2 - 0.3**2)  # the sphere around b = (1, 0, 0)
    assert depth == pytest.approx(3.0 - x_hit, abs=1e-12)
    assert cid == 0
    np.testing.assert_allclose(normal, np.array([x_hit - 1.0, 0.0, 0.3]) / 0.5, atol=1e-12)


def test_ray_along_the_axis_hits_the_cap_tip() -> None:
    depth, cid, normal = _cast((5.0, 0.0, 0.0), (-1.0, 0.0, 0.0))
    assert depth == pytest.approx(3.5, abs=1e-12)
    assert cid == 0
    np.testing.assert_allclose(normal, [1.0, 0.0, 0.0], atol=1e-12)


def test_ray_that_misses_reports_no_capsule() -> None:
    depth, cid, normal = _cast((0.0, 0.0, 5.0), (0.0, 1.0, 0.0))
    assert depth == np.inf
    assert cid == -1
    np.testing.assert_array_equal(normal, 0.0)


def test_ray_pointing_away_does_not_hit_behind_its_origin() -> None:
    assert _cast((0.0, 0.0, 5.0), (0.0, 0.0, 1.0))[1] == -1


def test_ray_from_inside_sees_the_exit() -> None:
    depth, cid, normal = _cast((0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    assert depth == pytest.approx(0.5)
    assert cid == 0
    np.testing.assert_allclose(normal, [0.0, 1.0, 0.0], atol=1e-12)


def test_nearest_of_two_capsules_wins() -> None:
    caps = Capsules(
        a_m=np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]]),
        b_m=np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 2.0]]),
        radius_m=np.array([0.2, 0.3]),
        joint=np.array([3, 4]),
    )
    depth, cid, _ = _cast((0.5, 0.0, 10.0), (0.0, 0.0, -1.0), caps)
    assert cid == 1
    assert depth == pytest.approx(10.0 - 2.3)


def test_body_ray_hits_lie_on_the_surface_with_nothing_in_front() -> None:
    rng = np.random.default_rng(30)
    kin = forward_kinematics(random_poses(rng, 1)[0] * [1, 1, 1, 0, 0, 0, *[1] * 27], SHAPE)
    caps = capsules(kin, SHAPE)
    origins = rng.normal(size=(2000, 3)) * 0.3 + [0.0, 3.0, 0.0]
    directions = rng.normal(scale=0.3, size=(2000, 3)) - origins  # towards the body
    depth, cid, normal = raycast(origins, directions, caps)
    hit = cid >= 0
    assert 100 < hit.sum() < 2000
    unit = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
    points = origins + depth[:, None] * unit
    sd = signed_distance(points[hit], caps)
    np.testing.assert_allclose(sd[np.arange(hit.sum()), cid[hit]], 0.0, atol=1e-9)
    assert sd.min() > -1e-9  # the hit point is inside no other capsule
    before = origins + 0.999 * depth[:, None] * unit
    assert signed_distance(before[hit], caps).min() > 0  # nothing crossed on the way
    np.testing.assert_allclose(np.linalg.norm(normal[hit], axis=-1), 1.0, atol=1e-12)
    assert np.all(np.sum(normal[hit] * unit[hit], axis=-1) <= 1e-9)  # facing the ray
    assert np.all(signed_distance(origins[~hit][:200], caps).min(axis=-1) > 0)


def test_raycast_rejects_zero_directions() -> None:
    with pytest.raises(ValidationError, match="zero-length"):
        raycast(np.zeros((1, 3)), np.zeros((1, 3)), UNIT)


def test_template_has_one_capsule_per_bone_and_a_labelled_trunk() -> None:
    t = capsule_template(SHAPE)
    assert t.names == CAPSULE_NAMES
    assert len(CAPSULE_NAMES) == 22
    head = CAPSULE_NAMES.index("head")
    assert t.joint[head] == JOINT_INDEX["Head"]
    assert t.joint[CAPSULE_NAMES.index("left_shank")] == JOINT_INDEX["LeftLeg"]
    assert np.all(t.radius_m > 0)


# --- pinhole rendering ----------------------------------------------------------------------


def _front_camera(distance_m: float, height_m: float = 0.9) -> npt.NDArray[np.float64]:
    """T_cam_world of a camera at (0, distance, height) looking at the subject along -Y."""
    r_world_cam = np.stack([[-1.0, 0, 0], [0, 0, -1.0], [0, -1.0, 0]], axis=1)
    t_world_cam = np.array([0.0, distance_m, height_m])
    t = np.eye(4)
    t[:3, :3] = r_world_cam.T
    t[:3, 3] = -r_world_cam.T @ t_world_cam
    return t


def _k(f: float, width: int, height: int) -> npt.NDArray[np.float64]:
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def test_render_follows_the_opencv_camera_axes() -> None:
    caps = _one_capsule((0.5, 0.0, 4.0), (0.5, 0.0, 4.0), 0.1)  # a ball right of the axis
    r = render_pinhole(caps, _k(100.0, 64, 48), np.eye(4), 64, 48)
    vs, us = np.nonzero(r.segment >= 0)
    assert us.mean() > 31.5 + 10  # +X_cam is image right
    assert abs(vs.mean() - 23.5) < 0.5
    assert r.depth_m[r.segment >= 0].min() == pytest.approx(3.9, abs=5e-3)
    caps = _one_capsule((0.0, 0.5, 4.0), (0.0, 0.5, 4.0), 0.1)
    vs, _ = np.nonzero(render_pinhole(caps, _k(100.0, 64, 48), np.eye(4), 64, 48).segment >= 0)
    assert vs.mean() > 23.5 + 10  # +Y_cam is image down


def test_render_depth_is_z_depth_and_matches_the_ray_caster() -> None:
    caps = capsules(neutral_pose(SHAPE), SHAPE)
    width, height, t_cw = 160, 120, _front_camera(3.0)
    k = _k(130.0, width, height)
    r = render_pinhole(caps, k, t_cw, width, height)
    vs, us = np.nonzero(r.segment >= 0)
    pick = np.random.default_rng(31).choice(vs.size, 50, replace=False)
    pix = np.stack([us[pick], vs[pick], np.ones(50)], axis=-1)
    d_cam = pix @ np.linalg.inv(k).T
    r_wc, c_w = t_cw[:3, :3].T, -t_cw[:3, :3].T @ t_cw[:3, 3]
    dist, cid, _ = raycast(np.tile(c_w, (50, 1)), d_cam @ r_wc.T, caps)
    z = dist / np.linalg.norm(d_cam, axis=-1)  # z-depth along the optical axis
    np.testing.assert_allclose(r.depth_m[vs[pick], us[pick]], z, atol=1e-9)
    np.testing.assert_array_equal(r.segment[vs[pick], us[pick]], caps.joint[cid])


def test_rendered_silhouette_area_is_plausible() -> None:
    """A 1.75 m adult seen from the front at 3 m covers roughly 0.4–0.7 m² of image plane."""
    caps = capsules(neutral_pose(SHAPE), SHAPE)
    width, height, f = 240, 180, 200.0
    r = render_pinhole(caps, _k(f, width, height), _front_camera(3.0), width, height)
    sil = r.segment >= 0
    z_mean = float(r.depth_m[sil].mean())
    area_m2 = sil.sum() * (z_mean / f) ** 2
    assert 0.4 < area_m2 < 0.7
    rows = np.nonzero(sil.any(axis=1))[0]
    tall_m = (rows.max() - rows.min() + 1) * 3.0 / f  # the body is ~3 m from the camera
    assert tall_m == pytest.approx(SHAPE.height_m, rel=0.06)
    assert np.all(r.depth_m[~sil] == 0)
    assert np.all(r.segment[~sil] == -1)
    assert r.segment.dtype == np.int16


def test_render_labels_and_normals_make_sense() -> None:
    caps = capsules(t_pose(SHAPE), SHAPE)
    width, height = 240, 180
    r = render_pinhole(caps, _k(120.0, width, height), _front_camera(3.5), width, height)
    sil = r.segment >= 0
    n = r.normals_cam[sil]
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-9)
    assert np.all(n[:, 2] < 1e-9)  # visible surfaces face the camera (-Z_cam)
    # the subject faces the camera, so the subject's right hand is on the image's left
    right_hand = np.nonzero(r.segment == JOINT_INDEX["RightHand"])
    left_hand = np.nonzero(r.segment == JOINT_INDEX["LeftHand"])
    assert right_hand[1].mean() < width / 2 < left_hand[1].mean()
    head_rows = np.nonzero(r.segment == JOINT_INDEX["Head"])[0]
    foot_rows = np.nonzero(r.segment == JOINT_INDEX["RightFoot"])[0]
    assert head_rows.mean() < foot_rows.mean()


def test_render_skips_capsules_behind_the_camera() -> None:
    caps = capsules(neutral_pose(SHAPE), SHAPE)
    t_cw = _front_camera(3.0)
    t_cw[:3, :3] = -t_cw[:3, :3]  # looking away from the subject
    t_cw[:3, 3] = -t_cw[:3, :3] @ np.array([0.0, 3.0, 0.9])
    r = render_pinhole(caps, _k(100.0, 80, 60), t_cw, 80, 60)
    assert not np.any(r.segment >= 0)


def test_render_rejects_bad_intrinsics() -> None:
    caps = capsules(neutral_pose(SHAPE), SHAPE)
    with pytest.raises(ValidationError, match="K has the wrong shape"):
        render_pinhole(caps, np.eye(4), np.eye(4), 10, 10)
