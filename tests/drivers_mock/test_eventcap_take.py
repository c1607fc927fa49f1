"""The simulated EventCap take: events, blurred frames and 1 kHz truth on the DAVIS timeline."""

from __future__ import annotations

import numpy as np
import pytest

from mocaprig.calib.camera_model import project_points
from mocaprig.drivers_mock.eventcap_take import EventcapTake, simulate_eventcap_take
from mocaprig.errors import ValidationError


@pytest.fixture(scope="module")
def take() -> EventcapTake:
    # Events from 2 s only: the truth still covers the whole take, the simulation costs a third.
    return simulate_eventcap_take(seed=3, seconds=3.0, scenario="karate", start_s=2.0)


@pytest.mark.slow
def test_truth_is_sampled_every_millisecond_over_the_take(take: EventcapTake) -> None:
    assert take.truth_t_us[0] == 0
    assert np.all(np.diff(take.truth_t_us) == 1000)
    assert take.truth_t_us[-1] < take.t1_us <= take.truth_t_us[-1] + 1000
    assert take.truth_pose.shape == (take.truth_t_us.size, 33)
    assert take.truth_keypoints_m.shape == (take.truth_t_us.size, 19, 3)


def test_truth_at_reproduces_the_sampled_truth(take: EventcapTake) -> None:
    idx = np.array([0, 777, take.truth_t_us.size - 1])
    pose, kp = take.truth_at(take.truth_t_us[idx])
    np.testing.assert_allclose(pose, take.truth_pose[idx], atol=1e-12)
    np.testing.assert_allclose(kp, take.truth_keypoints_m[idx], atol=1e-12)


def test_truth_pixels_are_the_camera_projection_of_the_truth_points(take: EventcapTake) -> None:
    cam = take.camera
    uv, depth = project_points(take.truth_keypoints_m[1234], cam.T_world_cam, cam.K, cam.distortion)
    np.testing.assert_allclose(uv, take.truth_keypoints_px[1234], atol=1e-9)
    np.testing.assert_allclose(depth, take.truth_depth_m[1234], atol=1e-12)
    assert np.all(take.truth_depth_m > 1.0)


def test_reference_images_share_the_time_base_of_the_aps_frames(take: EventcapTake) -> None:
    # An APS frame looks like the reference image at its own exposure, not one 200 ms away:
    # the truth, the renders and the frames all sit on the DAVIS's device µs.
    e = take.exposures[10]
    mid = (e.start_us + e.end_us) // 2

    def err(t_us: int) -> float:
        img = take.reference_image(t_us)
        a, b = np.log(1e-3 + img), np.log(1.0 + e.cds)
        return float(np.mean(np.abs((a - a.mean()) - (b - b.mean()))))

    assert err(mid) < 0.8 * err(mid + 200_000)


def test_events_are_sorted_inside_the_take_and_frames_come_at_25_fps(take: EventcapTake) -> None:
    t = take.events["t"]
    assert t.size > 10_000
    assert np.all(np.diff(t) >= 0)
    assert t[0] >= take.t0_us >= 2_000_000 - 1
    assert t[-1] < take.t1_us
    starts = np.array([e.start_us for e in take.exposures])
    np.testing.assert_array_equal(np.diff(starts), 40_000)
    assert all(e.cds.shape == (180, 240) for e in take.exposures)


def test_an_excerpt_ending_early_holds_the_whole_takes_events_frames_and_truth(
    take: EventcapTake,
) -> None:
    part = simulate_eventcap_take(seed=3, seconds=3.0, scenario="karate", start_s=2.0, end_s=2.1)
    assert part.t0_us == take.t0_us
    assert part.t1_us < take.t1_us
    assert part.events.size > 0
    np.testing.assert_array_equal(part.events, take.events[take.events["t"] < part.t1_us])
    done = [e for e in take.exposures if e.end_us < part.t1_us]
    assert [(e.start_us, e.end_us) for e in part.exposures] == [
        (e.start_us, e.end_us) for e in done
    ]
    assert all(np.array_equal(a.cds, b.cds) for a, b in zip(part.exposures, done, strict=True))
    np.testing.assert_array_equal(part.truth_t_us, take.truth_t_us)
    np.testing.assert_array_equal(part.truth_keypoints_m, take.truth_keypoints_m)


def test_an_excerpt_must_end_after_it_starts() -> None:
    with pytest.raises(ValidationError, match=r"end_s=1\.5 s must lie after start_s=2\.0 s"):
        simulate_eventcap_take(seed=3, seconds=3.0, scenario="karate", start_s=2.0, end_s=1.5)


def test_an_excerpt_of_so_many_frames_stops_once_they_are_complete(take: EventcapTake) -> None:
    part = simulate_eventcap_take(seed=3, seconds=3.0, scenario="karate", start_s=2.0, max_frames=2)
    assert take.t0_us == part.t0_us < part.t1_us < take.t1_us
    assert len(part.exposures) >= 2
    assert [(e.start_us, e.end_us) for e in part.exposures] == [
        (e.start_us, e.end_us) for e in take.exposures[: len(part.exposures)]
    ]
    np.testing.assert_array_equal(part.events, take.events[take.events["t"] < part.t1_us])
    with pytest.raises(ValidationError, match="max_frames must be >= 1, got 0"):
        simulate_eventcap_take(seed=3, seconds=3.0, scenario="karate", start_s=2.0, max_frames=0)
