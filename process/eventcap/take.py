"""EventCap over a whole take: batches streamed between consecutive APS frames.

Memory follows the batch, not the take: the events of one batch are asked of an
:data:`EventSource` (a recording's time-window reader, or an in-memory array through
:func:`array_source`) when the batch runs, and only the 1 kHz poses are kept. Batches share
their end frames: frame ``b`` of one batch is frame ``a`` of the next, the next batch starts
from the previous one's last pose, and each shared instant is reported once (the later batch's
estimate, which saw detections on both sides of it). :func:`iter_take` yields each batch's
output as it is done (a caller that streams it to files holds one batch);
:func:`run_take` collects the whole take.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.eventcap.camera import EventCamera
from mocaprig.process.eventcap.detections import Detection, Detector
from mocaprig.process.eventcap.pipeline import (
    ApsFrame,
    BatchResult,
    EventcapOptions,
    run_batch,
)

__all__ = [
    "EventSource",
    "TakeChunk",
    "TakeResult",
    "array_source",
    "iter_take",
    "run_take",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: ``(t0_us, t1_us) ->`` the events with ``t0_us <= t <= t1_us`` (canonical dtype, sorted).
EventSource = Callable[[int, int], npt.NDArray[np.void]]


def array_source(events: npt.NDArray[np.void]) -> EventSource:
    """An :data:`EventSource` over an in-memory array sorted by ``t`` (not copied)."""
    t = events["t"]

    def window(t0_us: int, t1_us: int) -> npt.NDArray[np.void]:
        i0 = int(np.searchsorted(t, t0_us, side="left"))
        i1 = int(np.searchsorted(t, t1_us, side="right"))
        return events[i0:i1]

    return window


@dataclass(frozen=True, slots=True, eq=False)
class TakeResult:
    """EventCap output over a take.

    Attributes:
        t_us: (T,) tracking frame times, µs, increasing, every ``step_us``.
        poses: (T, 33) poses (world, m, rad).
        keypoints_m: (T, 19, 3) EventCap keypoints, world frame, m.
        batches: Per-batch summaries (the poses are in the arrays above).
        detection_source: The detector's label.
        seconds: Wall time of the whole take.
    """

    t_us: I64 = field(repr=False)
    poses: F64 = field(repr=False)
    keypoints_m: F64 = field(repr=False)
    batches: tuple[BatchResult, ...] = field(repr=False)
    detection_source: str
    seconds: float

    def stage_seconds(self) -> dict[str, float]:
        """Wall time per stage summed over the batches."""
        out: dict[str, float] = {}
        for b in self.batches:
            for k, v in b.stage_seconds.items():
                out[k] = out.get(k, 0.0) + v
        return out


@dataclass(frozen=True, slots=True, eq=False)
class TakeChunk:
    """What one batch adds to a take's 1 kHz output (:func:`iter_take`).

    Attributes:
        batch: The batch's index in the take.
        batches: Batches in the take.
        t_us: (n,) tracking frame times, µs: the batch's frames without its last one, which the
            next batch reports (all of them for the take's last batch).
        poses: (n, 33) poses (world, m, rad).
        keypoints_m: (n, 19, 3) EventCap keypoints, world frame, m.
        result: The batch's whole result (its summary and fit; not kept by streaming callers).
    """

    batch: int
    batches: int
    t_us: I64 = field(repr=False)
    poses: F64 = field(repr=False)
    keypoints_m: F64 = field(repr=False)
    result: BatchResult = field(repr=False)


def iter_take(
    events: EventSource,
    frames: Sequence[ApsFrame],
    detector: Detector,
    camera: EventCamera,
    shape: BodyShape,
    *,
    options: EventcapOptions | None = None,
) -> Iterator[TakeChunk]:
    """Run :func:`~.pipeline.run_batch` on every pair of consecutive frames, yielding each
    batch's output as it is done (memory follows the batch; :func:`run_take` collects them).

    Args:
        events: Window reader of the take's events.
        frames: The APS frames in time order (at least 2); each is asked for when its batch
            runs (``frames[k]`` may decode the image then).
        detector: Detections at each frame's time (``Detector.detect(frame.t_us, image)``).
        camera: The DAVIS.
        shape: The actor's template.
        options: Settings.

    Raises:
        ValidationError: fewer than two frames, or frames out of order.
        ProcessingError: a batch failed (its time is named).
    """
    opt = options if options is not None else EventcapOptions()
    if len(frames) < 2:
        msg = f"EventCap needs at least two APS frames, got {len(frames)}"
        raise ValidationError(msg)
    total = len(frames) - 1
    # Frames and detections are asked for as the batches reach them; the three a batch needs
    # (a, b and the first batch's lookahead) are kept.
    kept: dict[int, tuple[ApsFrame, Detection]] = {}

    def frame(k: int) -> tuple[ApsFrame, Detection]:
        if k not in kept:
            f = frames[k]
            if k > 0 and f.t_us <= frame(k - 1)[0].t_us:
                msg = "APS frames must be in strictly increasing time order"
                raise ValidationError(msg)
            kept[k] = (f, detector.detect(int(f.t_us), f.image_dn))
        return kept[k]

    prev: F64 | None = None
    for k in range(total):
        (a, det_a), (b, det_b) = frame(k), frame(k + 1)
        lookahead = frame(k + 2)[1] if prev is None and k + 2 < len(frames) else None
        window = events(a.exposure_start_us, b.exposure_end_us)
        try:
            res = run_batch(
                window,
                a,
                b,
                det_a,
                det_b,
                camera,
                shape,
                options=opt,
                start_pose=prev,
                lookahead=lookahead,
            )
        except ProcessingError as err:
            msg = f"EventCap batch {k} ({a.t_us}–{b.t_us} µs) failed: {err}"
            raise ProcessingError(msg) from err
        del window
        for old in [j for j in kept if j < k]:
            del kept[old]
        prev = res.poses[-1]
        _log.info(
            "batch %d/%d: %d trajectories, %d correspondences, %.2f s",
            k + 1,
            total,
            res.trajectories,
            res.correspondences,
            sum(res.stage_seconds.values()),
        )
        # Shared end frames: the later batch's frame 0 is reported, the earlier batch's last not.
        n = res.t_us.size if k == total - 1 else res.t_us.size - 1
        yield TakeChunk(
            batch=k,
            batches=total,
            t_us=res.t_us[:n],
            poses=res.poses[:n],
            keypoints_m=res.keypoints_m[:n],
            result=res,
        )


def run_take(
    events: EventSource,
    frames: Sequence[ApsFrame],
    detector: Detector,
    camera: EventCamera,
    shape: BodyShape,
    *,
    options: EventcapOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> TakeResult:
    """Run :func:`iter_take` and keep the whole take's output and every batch's result.

    Args:
        events: Window reader of the take's events.
        frames: The APS frames in time order (at least 2).
        detector: Detections at each frame's time (``Detector.detect(frame.t_us, image)``).
        camera: The DAVIS.
        shape: The actor's template.
        options: Settings.
        progress: ``(batches_done, batches_total)`` after each batch.

    Raises:
        ValidationError: fewer than two frames, or frames out of order.
        ProcessingError: a batch failed (its time is named).
    """
    start = time.perf_counter()
    chunks: list[TakeChunk] = []
    for chunk in iter_take(events, frames, detector, camera, shape, options=options):
        chunks.append(chunk)
        if progress is not None:
            progress(chunk.batch + 1, chunk.batches)
    return TakeResult(
        t_us=np.concatenate([c.t_us for c in chunks]),
        poses=np.concatenate([c.poses for c in chunks]),
        keypoints_m=np.concatenate([c.keypoints_m for c in chunks]),
        batches=tuple(c.result for c in chunks),
        detection_source=detector.source,
        seconds=time.perf_counter() - start,
    )
