"""Running EventCap over a take: the event window reader and the checks at the boundary."""

from __future__ import annotations

import numpy as np
import pytest

from mocaprig.acquire.events import make_events
from mocaprig.errors import ValidationError
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.eventcap.camera import EventCamera
from mocaprig.process.eventcap.detections import SyntheticDetections
from mocaprig.process.eventcap.evaluate import TakeWithTruth
from mocaprig.process.eventcap.pipeline import ApsFrame, BatchResult
from mocaprig.process.eventcap.take import array_source, iter_take, run_take

CAMERA = EventCamera(
    K=np.array([[200.0, 0.0, 120.0], [0.0, 200.0, 90.0], [0.0, 0.0, 1.0]]),
    distortion=np.zeros(5),
    T_world_cam=np.eye(4),
    width=240,
    height=180,
)


def _events(t_us: list[int]) -> np.ndarray:
    n = len(t_us)
    return make_events(t=t_us, x=np.zeros(n), y=np.zeros(n), p=np.ones(n, dtype=bool))


def test_array_source_returns_the_closed_window_without_copying_the_take() -> None:
    ev = _events([0, 5, 10, 10, 15, 20])
    window = array_source(ev)
    np.testing.assert_array_equal(window(5, 15)["t"], [5, 10, 10, 15])
    np.testing.assert_array_equal(window(11, 14)["t"], [])
    assert np.shares_memory(window(0, 20), ev)


def _detector() -> SyntheticDetections:
    t = np.array([0, 40_000])
    return SyntheticDetections(t, np.full((2, 19, 2), 100.0), seed=0)


def test_run_take_needs_two_frames_in_time_order() -> None:
    img = np.zeros((180, 240))
    a, b = ApsFrame(0, 0, img), ApsFrame(40_000, 40_000, img)
    shape = BodyShape.from_height(1.75)
    source = array_source(_events([]))
    with pytest.raises(ValidationError, match="at least two APS frames"):
        run_take(source, [a], _detector(), CAMERA, shape)
    with pytest.raises(ValidationError, match="increasing time order"):
        run_take(source, [b, a], _detector(), CAMERA, shape)


def test_aps_frame_time_is_the_exposure_midpoint_and_order_is_checked() -> None:
    assert ApsFrame(1000, 5000, np.zeros((2, 2))).t_us == 3000
    with pytest.raises(ValidationError, match="before it starts"):
        ApsFrame(5000, 1000, np.zeros((2, 2)))


def test_take_with_truth_maps_times_onto_its_millisecond_grid() -> None:
    t = np.arange(10_000, 20_000, 1000)
    take = TakeWithTruth(
        label="grid",
        events=_events([]),
        frames=(),
        camera=CAMERA,
        shape=BodyShape.from_height(1.75),
        truth_t_us=t,
        truth_keypoints_m=np.zeros((t.size, 19, 3)),
        truth_keypoints_px=np.zeros((t.size, 19, 2)),
    )
    np.testing.assert_array_equal(take.truth_index([10_000, 19_000]), [0, 9])
    with pytest.raises(ValidationError, match="1 ms truth grid"):
        take.truth_index([10_500])
    with pytest.raises(ValidationError, match="1 ms truth grid"):
        take.truth_index([20_000])
    with pytest.raises(ValidationError, match="every 1000"):
        TakeWithTruth(
            label="uneven",
            events=_events([]),
            frames=(),
            camera=CAMERA,
            shape=BodyShape.from_height(1.75),
            truth_t_us=np.array([0, 1000, 3000]),
            truth_keypoints_m=np.zeros((3, 19, 3)),
            truth_keypoints_px=np.zeros((3, 19, 2)),
        )


class _CountingFrames(list[ApsFrame]):
    """Frames that record which index was asked for (the take must ask as it goes)."""

    def __init__(self, frames: list[ApsFrame]) -> None:
        super().__init__(frames)
        self.asked: list[int] = []

    def __getitem__(self, k):
        self.asked.append(k)
        return super().__getitem__(k)


def test_iter_take_streams_batches_reporting_each_shared_frame_once(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import mocaprig.process.eventcap.take as take_module

    starts: list[object] = []

    def fake_batch(window, a, b, det_a, det_b, camera, shape, **kw):
        # A stand-in for the solver: poses carry their frame time, so the stitching shows.
        starts.append(kw["start_pose"])
        t = np.arange(a.t_us, b.t_us + 1, 1000, dtype=np.int64)
        poses = np.repeat(t[:, None].astype(float), 33, axis=1)
        kp = np.repeat(poses[:, :19, None], 3, axis=2)
        return BatchResult(t, poses, kp, (0.1, 0.1), 0, 0, 0, 0, "synthetic", None, {"edi": 0.0})  # type: ignore[arg-type]

    monkeypatch.setattr(take_module, "run_batch", fake_batch)
    img = np.zeros((180, 240))
    frames = _CountingFrames([ApsFrame(t, t, img) for t in (0, 40_000, 80_000, 120_000)])
    t_det = np.array([0, 40_000, 80_000, 120_000])
    det = SyntheticDetections(t_det, np.full((4, 19, 2), 100.0), seed=0)
    source = array_source(_events([]))
    it = iter_take(source, frames, det, CAMERA, BodyShape.from_height(1.75))
    first = next(it)
    assert max(frames.asked) == 2  # frames a, b and the first batch's lookahead only
    assert (first.batch, first.batches) == (0, 3)
    assert first.t_us.tolist() == list(range(0, 40_000, 1000))  # its last frame is the next's
    rest = list(it)
    assert rest[-1].t_us[-1] == 120_000  # the take's last frame is reported
    t = np.concatenate([first.t_us] + [c.t_us for c in rest])
    np.testing.assert_array_equal(t, np.arange(0, 120_001, 1000))
    np.testing.assert_array_equal(np.concatenate([first.poses] + [c.poses for c in rest])[:, 0], t)
    assert starts[0] is None
    assert [float(s[0]) for s in starts[1:]] == [40_000.0, 80_000.0]  # type: ignore[index]
    whole = run_take(source, frames, det, CAMERA, BodyShape.from_height(1.75))
    np.testing.assert_array_equal(whole.t_us, t)
    assert len(whole.batches) == 3
