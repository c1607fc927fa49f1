"""Rig geometry: camera convention, projection, default layout."""

from __future__ import annotations

import numpy as np
import pytest

from mocaprig.drivers_mock.rig import PinholeCamera, default_rig, look_at, project
from mocaprig.errors import ValidationError


def _camera(T=None, dist=None) -> PinholeCamera:
    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    return PinholeCamera(
        "c", 640, 480, K, np.zeros(5) if dist is None else dist, np.eye(4) if T is None else T
    )


def test_look_at_puts_the_target_on_the_optical_axis_with_image_y_down() -> None:
    T = look_at([2.0, 0.0, 1.5], [0.0, 0.0, 1.0])
    cam = _camera(T)
    uv, z = project(cam, np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0]]))
    np.testing.assert_allclose(uv[0], [320.0, 240.0], atol=1e-9)
    assert z[0] == pytest.approx(np.hypot(2.0, 0.5))
    assert uv[1, 1] < 240.0  # a point above the target is higher in the image (smaller v)


def test_project_matches_the_opencv_equations() -> None:
    dist = np.array([-0.2, 0.05, 0.001, -0.002, 0.0])
    cam = _camera(dist=dist)
    p = np.array([[0.3, -0.2, 2.0]])
    uv, _ = project(cam, p)
    a, b = 0.15, -0.1
    r2 = a * a + b * b
    radial = 1 - 0.2 * r2 + 0.05 * r2 * r2
    ad = a * radial + 2 * 0.001 * a * b + -0.002 * (r2 + 2 * a * a)
    bd = b * radial + 0.001 * (r2 + 2 * b * b) + 2 * -0.002 * a * b
    np.testing.assert_allclose(uv[0], [600 * ad + 320, 600 * bd + 240], atol=1e-9)


def test_points_behind_the_camera_project_to_nan() -> None:
    uv, z = project(_camera(), np.array([[0.0, 0.0, -1.0]]))
    assert np.all(np.isnan(uv))
    assert z[0] < 0


def test_camera_rejects_a_non_rotation_pose() -> None:
    T = np.eye(4)
    T[0, 0] = 2.0
    with pytest.raises(ValidationError, match="rotation"):
        _camera(T)


def test_default_rig_has_a_master_d415_three_slaves_and_a_davis() -> None:
    rig = default_rig(np.random.default_rng(0))
    assert [d.role for d in rig.d415] == ["master", "slave", "slave", "slave"]
    assert [d.sync_mode for d in rig.d415] == [1, 2, 2, 2]
    assert len({d.serial for d in rig.d415}) == 4
    for d in rig.d415:
        assert len(d.serial) == 12
        assert d.serial.isdigit()
        assert d.ir_left.width == 848
        assert d.ir_left.height == 480
        assert d.ir_left.fx == pytest.approx(623.4, rel=0.03)
        assert d.depth_scale_m == 0.001
        assert d.rate_hz == 30.0
        assert d.baseline_m == pytest.approx(0.055, abs=0.001)
        centre = d.ir_left.center_m
        assert np.hypot(*centre[:2]) == pytest.approx(2.5, abs=0.3)
        assert 1.2 < centre[2] < 1.6
        # The right imager sits one baseline to the left imager's right (+X of the camera).
        offset = d.ir_left.T_cam_world @ np.append(d.ir_right.center_m, 1.0)
        np.testing.assert_allclose(offset[:3], [d.baseline_m, 0.0, 0.0], atol=1e-12)
    h, v = rig.davis.camera.fov_deg
    assert 50 < h < 56
    assert 38 < v < 43
    assert np.linalg.norm(rig.davis.camera.center_m[:2]) == pytest.approx(3.0, abs=0.2)


def test_default_rig_differs_across_seeds_and_repeats_for_a_seed() -> None:
    a, b, c = (default_rig(np.random.default_rng(s)) for s in (1, 1, 2))
    np.testing.assert_array_equal(a.d415[0].ir_left.T_world_cam, b.d415[0].ir_left.T_world_cam)
    assert not np.allclose(a.d415[0].ir_left.T_world_cam, c.d415[0].ir_left.T_world_cam)
    assert a.d415[0].serial == b.d415[0].serial != c.d415[0].serial
