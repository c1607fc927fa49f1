"""Motion clips: validation, interpolation, resampling and concatenation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocaprig.errors import ValidationError
from mocaprig.process.body.motion import Motion, blend_poses, concatenate
from mocaprig.process.body.skeleton import DOF_LIMITS_RAD, POSE_DIM


def _random_motion(rng: np.random.Generator, frames: int, rate_hz: float = 100.0) -> Motion:
    poses = np.zeros((frames, POSE_DIM))
    base = rng.normal(size=3)
    poses[:, 0:3] = base + 0.05 * np.cumsum(rng.normal(size=(frames, 3)), axis=0)
    poses[:, 3:6] = np.cumsum(rng.normal(scale=0.01, size=(frames, 3)), axis=0)
    poses[:, 5] += 0.9
    lo, hi = DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1]
    poses[:, 6:] = lo + (hi - lo) * rng.uniform(size=(frames, 27))
    return Motion("random", rate_hz, poses)


def test_motion_copies_and_freezes_poses() -> None:
    src = np.zeros((4, POSE_DIM))
    m = Motion("m", 50.0, src)
    src[0, 0] = 1.0
    assert m.poses[0, 0] == 0.0
    with pytest.raises(ValueError, match="read-only"):
        m.poses[0, 0] = 2.0


def test_motion_rejects_wrong_shape_and_rate() -> None:
    with pytest.raises(ValidationError, match="wrong shape"):
        Motion("m", 50.0, np.zeros((4, 32)))
    with pytest.raises(ValidationError, match="rate_hz"):
        Motion("m", 0.0, np.zeros((4, POSE_DIM)))
    with pytest.raises(ValidationError, match="no frames"):
        Motion("m", 50.0, np.zeros((0, POSE_DIM)))


def test_times_and_duration_follow_rate() -> None:
    m = Motion("m", 20.0, np.zeros((11, POSE_DIM)))
    assert m.duration_s == pytest.approx(0.5)
    np.testing.assert_allclose(m.times_s, np.arange(11) / 20.0)


@pytest.mark.parametrize("method", ["linear", "cubic"])
def test_sample_reproduces_frames_at_frame_times(method: str) -> None:
    m = _random_motion(np.random.default_rng(1), 12)
    got = m.sample(m.times_s, method=method)  # type: ignore[arg-type]
    np.testing.assert_allclose(got[:, 3:], m.poses[:, 3:], atol=1e-12)
    delta = Rotation.from_rotvec(got[:, :3]).inv() * Rotation.from_rotvec(np.array(m.poses[:, :3]))
    assert np.max(delta.magnitude()) < 1e-9


def test_sample_midpoint_is_linear_and_slerped() -> None:
    poses = np.zeros((2, POSE_DIM))
    poses[1, 0:3] = [0.0, 0.0, np.pi / 2]  # 90 deg about z
    poses[1, 3:6] = [1.0, 2.0, 3.0]
    poses[1, 6:] = 0.2
    m = Motion("m", 10.0, poses)
    mid = m.sample(0.05)
    assert mid.shape == (POSE_DIM,)
    np.testing.assert_allclose(mid[3:6], [0.5, 1.0, 1.5])
    np.testing.assert_allclose(mid[6:], 0.1)
    np.testing.assert_allclose(mid[0:3], [0.0, 0.0, np.pi / 4], atol=1e-12)


def test_sample_clamps_or_raises_outside_the_clip() -> None:
    m = _random_motion(np.random.default_rng(2), 5)
    np.testing.assert_allclose(m.sample([-1.0, 10.0])[:, 3:], m.poses[[0, -1], 3:])
    with pytest.raises(ValidationError, match="covers"):
        m.sample(10.0, out_of_range="raise")


def test_cubic_sampling_stays_within_limits() -> None:
    m = _random_motion(np.random.default_rng(3), 20)
    got = m.sample(np.linspace(0.0, m.duration_s, 301), method="cubic")
    assert np.all(got[:, 6:] >= DOF_LIMITS_RAD[:, 0] - 1e-12)
    assert np.all(got[:, 6:] <= DOF_LIMITS_RAD[:, 1] + 1e-12)


def test_resample_keeps_start_and_duration() -> None:
    m = _random_motion(np.random.default_rng(4), 101, rate_hz=100.0)
    r = m.resample(240.0)
    assert r.rate_hz == 240.0
    assert r.num_frames == 241
    np.testing.assert_allclose(r.poses[0], m.poses[0])
    np.testing.assert_allclose(r.poses[-1, 3:], m.poses[-1, 3:], atol=1e-12)


def test_blend_poses_endpoints() -> None:
    rng = np.random.default_rng(5)
    a = _random_motion(rng, 3).poses
    b = _random_motion(rng, 3).poses
    np.testing.assert_allclose(blend_poses(a, b, 0.0), a, atol=1e-12)
    got = blend_poses(a, b, 1.0)
    np.testing.assert_allclose(got[:, 3:], b[:, 3:], atol=1e-12)
    delta = Rotation.from_rotvec(got[:, :3]).inv() * Rotation.from_rotvec(np.array(b[:, :3]))
    assert np.max(delta.magnitude()) < 1e-9


def _walk(rate_hz: float, frames: int, start_x: float, velocity: float, angle: float) -> Motion:
    poses = np.zeros((frames, POSE_DIM))
    poses[:, 3] = start_x + velocity * np.arange(frames) / rate_hz
    poses[:, 5] = 0.9
    poses[:, 6 + 21] = angle  # left knee
    return Motion("walk", rate_hz, poses)


def test_concatenate_root_does_not_jump() -> None:
    rate = 100.0
    a = _walk(rate, 100, 0.0, 1.0, 0.1)
    b = _walk(rate, 100, 5.0, 1.0, 1.0)  # starts 5 m away
    out = concatenate([a, b], blend_s=0.2)
    assert out.num_frames == 200 - 20
    step = np.diff(out.poses[:, 3:6], axis=0)
    assert np.max(np.linalg.norm(step, axis=1)) < 1.5 * 1.0 / rate
    knee = out.poses[:, 6 + 21]
    assert np.max(np.abs(np.diff(knee))) < 0.9 / 20 * 2.0  # spread over the blend
    assert knee[0] == pytest.approx(0.1)
    assert knee[-1] == pytest.approx(1.0)


def test_concatenate_without_blend_butts_clips() -> None:
    a = _walk(50.0, 10, 0.0, 0.0, 0.0)
    b = _walk(50.0, 10, 3.0, 0.0, 0.5)
    out = concatenate([a, b], blend_s=0.0)
    assert out.num_frames == 20
    np.testing.assert_allclose(out.poses[:, 3], 0.0)


def test_concatenate_resamples_to_the_first_rate() -> None:
    a = _walk(100.0, 101, 0.0, 0.0, 0.0)
    b = _walk(50.0, 51, 0.0, 0.0, 0.0)
    out = concatenate([a, b], blend_s=0.1)
    assert out.rate_hz == 100.0
    assert out.duration_s == pytest.approx(2.0 - 0.1, abs=0.011)


def test_concatenate_rejects_empty_and_negative_blend() -> None:
    with pytest.raises(ValidationError, match="at least one"):
        concatenate([])
    with pytest.raises(ValidationError, match="blend_s"):
        concatenate([_walk(50.0, 3, 0, 0, 0)], blend_s=-1.0)
