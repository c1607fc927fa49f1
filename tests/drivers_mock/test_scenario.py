"""The seeded world: determinism, sampling API, cameras see the actor."""

from __future__ import annotations

import numpy as np
import pytest

from mocaprig.drivers_mock.noise import NoiseSettings
from mocaprig.drivers_mock.rig import project
from mocaprig.drivers_mock.scenario import SCENARIOS, build_scenario
from mocaprig.errors import ValidationError

SECOND = 1_000_000_000


@pytest.fixture(scope="module")
def default_world():
    return build_scenario("default", seed=11, seconds=6.0)


def test_same_seed_gives_the_same_world() -> None:
    a = build_scenario("karate", seed=5, seconds=4.0)
    b = build_scenario("karate", seed=5, seconds=4.0)
    t = np.arange(0, 4 * SECOND, 50_000_000, dtype=np.int64)
    np.testing.assert_array_equal(a.markers_m(t), b.markers_m(t))
    np.testing.assert_array_equal(a.clapper_markers_m(t), b.clapper_markers_m(t))
    assert a.clap_times_ns == b.clap_times_ns
    assert a.clocks == b.clocks
    np.testing.assert_array_equal(a.camera_pose("d415-1"), b.camera_pose("d415-1"))


def test_different_seeds_give_different_worlds() -> None:
    a = build_scenario("karate", seed=5, seconds=4.0)
    b = build_scenario("karate", seed=6, seconds=4.0)
    t = np.arange(0, 4 * SECOND, 50_000_000, dtype=np.int64)
    assert not np.allclose(a.markers_m(t), b.markers_m(t))
    assert a.shape.height_m != b.shape.height_m
    assert a.clap_times_ns != b.clap_times_ns
    assert a.clocks["davis"].offset_ns != b.clocks["davis"].offset_ns
    assert not np.allclose(a.camera_pose("davis"), b.camera_pose("davis"))


def test_sampling_api_shapes_and_consistency(default_world) -> None:
    t = np.array([0, SECOND // 3, 2 * SECOND, 5 * SECOND], dtype=np.int64)
    w = default_world.sample(t)
    assert w.pose.shape == (4, 33)
    assert w.joints_m.shape == (4, 26, 3)
    assert w.markers_m.shape == (4, 53, 3)
    assert w.clapper_m.shape == (4, 2, 3)
    np.testing.assert_allclose(default_world.pose(t), w.pose)
    np.testing.assert_allclose(default_world.joints_m(t), w.joints_m)
    np.testing.assert_allclose(default_world.markers_m(t), w.markers_m)
    # Any time shape works.
    assert default_world.markers_m(t.reshape(2, 2)).shape == (2, 2, 53, 3)
    np.testing.assert_allclose(np.linalg.norm(w.marker_normals, axis=-1), 1.0, atol=1e-9)


def test_actor_starts_with_a_static_t_pose_and_then_moves(default_world) -> None:
    still = default_world.joints_m(np.arange(0, SECOND // 2, 50_000_000, dtype=np.int64))
    assert np.ptp(still, axis=0).max() < 0.02
    moving = default_world.joints_m(np.arange(2 * SECOND, 5 * SECOND, 50_000_000, dtype=np.int64))
    assert np.ptp(moving, axis=0).max() > 0.2
    hands = still[0, [10, 15]]  # RightHandEnd, LeftHandEnd: arms out in the T-pose
    assert abs(hands[0, 0] - hands[1, 0]) > 1.2


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_every_camera_sees_most_markers_and_the_clapperboard(name: str) -> None:
    world = build_scenario(name, seed=3, seconds=5.0)
    t = np.arange(0, 5 * SECOND, 100_000_000, dtype=np.int64)
    w = world.sample(t)
    for cam_name, cam in world.rig.cameras.items():
        for points, need in ((w.markers_m, 0.9), (w.clapper_m, 1.0)):
            uv, z = project(cam, points)
            inside = (
                (z > 0)
                & (uv[..., 0] >= 0)
                & (uv[..., 0] <= cam.width - 1)
                & (uv[..., 1] >= 0)
                & (uv[..., 1] <= cam.height - 1)
            )
            assert inside.mean(axis=-1).min() >= need, (name, cam_name)


def test_noise_free_world_has_no_placement_jitter_or_clock_jitter() -> None:
    clean = build_scenario("tpose", seed=2, seconds=3.0, noise=NoiseSettings.none())
    noisy = build_scenario("tpose", seed=2, seconds=3.0)
    assert all(c.jitter_ns == 0 for c in clean.clocks.values())
    assert not np.allclose(clean.markers.offsets_m, noisy.markers.offsets_m)


def test_unknown_scenario_is_refused_with_the_choices() -> None:
    with pytest.raises(ValidationError, match="karate"):
        build_scenario("ballet", seed=0, seconds=5.0)


def test_float_session_times_are_refused(default_world) -> None:
    with pytest.raises(ValidationError, match="integer nanoseconds"):
        default_world.markers_m(np.array([0.5]))


def test_camera_lookup_names_the_known_cameras(default_world) -> None:
    with pytest.raises(ValidationError, match="d415-0"):
        default_world.camera("kinect")


@pytest.mark.slow  # the retargeting fit takes ~10 s even for a few frames
def test_bvh_motion_is_retargeted_onto_the_actor(shared_data, tmp_path) -> None:
    # The first 8 frames of a real CMU clip, slowed to 2 Hz so they span the session cheaply.
    text = (shared_data / "motion" / "cmu_131_01_scaled.bvh").read_text()
    head, motion = text.split("MOTION", 1)
    lines = motion.strip().splitlines()
    body = [ln for ln in lines if ln.strip() and not ln.startswith(("Frames", "Frame Time"))]
    clip = head + "MOTION\nFrames: 8\nFrame Time: 0.5\n" + "\n".join(body[:8]) + "\n"
    path = tmp_path / "short.bvh"
    path.write_text(clip)
    world = build_scenario(seed=1, seconds=3.0, motion_path=path)
    assert world.name == "bvh"
    assert world.motion_source == str(path)
    assert world.motion.rate_hz == pytest.approx(2.0)
    t = np.arange(0, 3 * SECOND, 100_000_000, dtype=np.int64)
    joints = world.joints_m(t)
    # Centred at the origin, standing upright: the head well above the hips.
    np.testing.assert_allclose(joints[0, 0, :2], 0.0, atol=1e-9)
    assert np.all(joints[:, 5, 2] - joints[:, 0, 2] > 0.5)
