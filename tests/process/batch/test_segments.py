"""``process.batch.segments``: the segment plan, the lazy frame span, the stitching, and
``run_segment``'s frames and batches on a small recording with ``iter_take`` stood in for (the
segments of a real take run in tests/e2e/test_process_batch.py)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from mocaprig.acquire.events import make_events
from mocaprig.acquire.recorder import Recorder
from mocaprig.acquire.recording_format import DavisFrameInfo, EventPacket, ImageMsg
from mocaprig.calib.calibration import write_calibration
from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.batch.segments import (
    EventcapInputs,
    Segment,
    SegmentResult,
    _FrameSpan,
    plan_segments,
    run_segment,
    stitch_segments,
)
from mocaprig.process.eventcap.detections import Detection, write_detections_json
from mocaprig.process.eventcap.take import TakeChunk
from tests.process.batch import fake_tasks


def test_segments_keep_every_batch_once_and_warm_up_before_it() -> None:
    segs = plan_segments(7, segment_batches=3, overlap=1)
    assert [(s.first, s.keep, s.end, s.last) for s in segs] == [
        (0, 0, 3, False),
        (2, 3, 6, False),
        (5, 6, 7, True),
    ]
    kept = [b for s in segs for b in range(s.keep, s.end)]
    assert kept == list(range(7))
    assert [s.warmup for s in segs] == [0, 1, 1]


def test_a_take_within_one_segment_is_the_unsplit_take() -> None:
    (seg,) = plan_segments(4, segment_batches=25, overlap=2)
    assert seg == Segment(index=0, first=0, keep=0, end=4, last=True)


def test_warm_up_never_reaches_before_the_take() -> None:
    segs = plan_segments(6, segment_batches=2, overlap=5)
    assert [s.first for s in segs] == [0, 0, 0]
    assert [s.batches_run for s in segs] == [2, 4, 6]


@pytest.mark.parametrize(
    ("batches", "segment_batches", "overlap", "what"),
    [(0, 2, 1, "batches"), (5, 0, 1, "segment_batches"), (5, 2, -1, "overlap")],
)
def test_bad_plans_are_refused(batches: int, segment_batches: int, overlap: int, what: str) -> None:
    with pytest.raises(ValidationError, match=what):
        plan_segments(batches, segment_batches=segment_batches, overlap=overlap)


class _Counting(list[int]):
    def __init__(self, n: int) -> None:
        super().__init__(range(n))
        self.asked: list[int] = []

    def __getitem__(self, i):
        self.asked.append(i)
        return super().__getitem__(i)


def test_frame_span_reads_only_the_frames_asked_for() -> None:
    frames = _Counting(10)
    stand_in: Any = frames  # ints stand in for the APS frames
    span: Any = _FrameSpan(stand_in, 4, 7)
    assert len(span) == 3
    assert span[0] == 4
    assert span[-1] == 6
    assert frames.asked == [4, 6]
    with pytest.raises(IndexError):
        span[3]


def _result(index: int, t0: int, n: int, *, last: bool) -> SegmentResult:
    rng = np.random.default_rng(index)
    seg = Segment(index=index, first=0, keep=0, end=1, last=last)
    t = 1000 * np.arange(t0, t0 + n, dtype=np.int64)
    return SegmentResult(seg, t, rng.normal(size=(n, 33)), rng.normal(size=(n, 19, 3)), "d", "s", 1)


def test_stitching_joins_segments_in_take_order() -> None:
    a, b = _result(0, 0, 40, last=False), _result(1, 40, 41, last=True)
    take = stitch_segments([b, a], batches=2)
    assert take.t_us.size == 81
    np.testing.assert_array_equal(take.poses[:40], a.poses)
    np.testing.assert_array_equal(take.keypoints_m[40:], b.keypoints_m)
    assert take.batches == 2


def test_stitching_refuses_a_gap() -> None:
    with pytest.raises(ProcessingError, match="not contiguous at 39000"):
        stitch_segments([_result(0, 0, 40, last=False), _result(1, 41, 40, last=True)])


def test_stitching_refuses_a_missing_segment() -> None:
    with pytest.raises(ProcessingError, match="do not make a whole take"):
        stitch_segments([_result(0, 0, 40, last=False)])


# ------------------------------------------------------------------ run_segment on a recording

_FRAMES = 5  # 4 batches
_PERIOD_US = 40_000


@pytest.fixture(scope="module")
def take(tmp_path_factory: pytest.TempPathFactory) -> EventcapInputs:
    """A DAVIS recording of 5 APS frames (40 ms apart, 5 ms exposure) and a few events, its
    calibration and detections at every frame."""
    root = tmp_path_factory.mktemp("segment-take")
    rng = np.random.default_rng(3)
    t = np.sort(rng.integers(0, _FRAMES * _PERIOD_US, 500))
    events = make_events(t, rng.integers(0, 240, 500), rng.integers(0, 180, 500), np.ones(500))
    times = []
    with Recorder(root / "session.mcap", min_free_disk_bytes=0) as rec:
        hf = rec.add_stream(f"/davis/{fake_tasks.SERIAL}/frame", ImageMsg)
        hi = rec.add_stream(f"/davis/{fake_tasks.SERIAL}/frame_info", DavisFrameInfo)
        he = rec.add_stream(f"/davis/{fake_tasks.SERIAL}/events", EventPacket)
        for k in range(_FRAMES):
            start, end = k * _PERIOD_US + 1000, k * _PERIOD_US + 6000
            times.append((start + end) // 2)
            log = 1_000_000_000 + k * 1_000_000
            img = ImageMsg(np.full((180, 240), 100, np.uint16), "mono16", times[-1] * 1000)
            rec.put_wait(hf, img, log_time_ns=log, sequence=k)
            info = DavisFrameInfo(k, start - 100, end + 100, start, end, 1)
            rec.put_wait(hi, info, log_time_ns=log, sequence=k)
        rec.put_wait(he, EventPacket(events, seq=0), log_time_ns=2_000_000_000, sequence=0)
    write_calibration(fake_tasks.calibration(), root / "calib.toml")
    dets = [Detection(t, np.full((19, 2), 100.0), np.ones(19), source="synthetic") for t in times]
    write_detections_json(root / "det.json", dets)
    return EventcapInputs(
        session=root / "session.mcap",
        calibration=root / "calib.toml",
        detections=root / "det.json",
        height_m=1.75,
    )


@dataclass
class _FakeTake:
    """Stands in for ``iter_take``: each batch gives its 1 kHz instants (a batch's last one
    only when it is the last batch of the frames it was given), counting the batches run."""

    frames_given: list[int] = field(default_factory=list)
    batches_run: int = 0

    def __call__(self, events: Any, frames: Any, *args: Any, **kwargs: Any) -> Iterator[Any]:
        self.frames_given.append(len(frames))
        total = len(frames) - 1
        for k in range(total):
            self.batches_run += 1
            n = _PERIOD_US // 1000 + (1 if k == total - 1 else 0)
            t = frames[k].t_us + 1000 * np.arange(n, dtype=np.int64)
            pose = np.zeros((n, 33))
            result = SimpleNamespace(stage_seconds={"fit": 0.5})
            yield TakeChunk(k, total, t, pose, np.zeros((n, 19, 3)), result)  # type: ignore[arg-type]


def test_a_segment_reads_the_next_frame_but_never_runs_its_batch(
    take: EventcapInputs, monkeypatch: pytest.MonkeyPatch
) -> None:
    fake = _FakeTake()
    monkeypatch.setattr("mocaprig.process.eventcap.take.iter_take", fake)
    seg = plan_segments(4, segment_batches=1, overlap=1)[1]  # batch 1, warmed up on batch 0
    res = run_segment(take, seg)
    assert fake.frames_given == [4]  # frames 0..3: batches 0 and 1, and frame 3 for the vote
    assert fake.batches_run == 2
    assert res.compute_s == pytest.approx(1.0)
    # Batch 1's instants without its last one, which the next segment reports.
    assert res.t_us.size == 40
    assert res.t_us[0] == 3500 + _PERIOD_US  # frame 1, the exposure midpoint


def test_the_last_segment_keeps_the_last_instant(
    take: EventcapInputs, monkeypatch: pytest.MonkeyPatch
) -> None:
    fake = _FakeTake()
    monkeypatch.setattr("mocaprig.process.eventcap.take.iter_take", fake)
    segs = plan_segments(4, segment_batches=2, overlap=1)
    results = [run_segment(take, s) for s in segs]
    assert fake.frames_given == [4, 4]  # 0..3 (frame 3 for the vote), then 1..4
    whole = stitch_segments(results, batches=4)
    assert whole.t_us.size == 4 * 40 + 1
    assert whole.t_us[-1] == 3500 + 4 * _PERIOD_US


def test_a_segment_planned_on_another_take_is_refused(
    take: EventcapInputs, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("mocaprig.process.eventcap.take.iter_take", _FakeTake())
    with pytest.raises(ProcessingError, match="plan the segments on this take"):
        run_segment(take, plan_segments(6, segment_batches=2)[1])
