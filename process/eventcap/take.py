"""EventCap over a whole take: batches streamed between consecutive APS frames.

Memory follows the batch, not the take: the events of one batch are asked of an
:data:`EventSource` (a recording's time-window reader, or an in-memory array through
:func:`array_source`) when the batch runs, and only the 1 kHz poses are kept. Batches share
their end frames: frame ``b`` of one batch is frame ``a`` of the next, the next batch starts
from the previous one's last pose, and each shared instant is reported once (the later batch's
estimate, which saw detections on both sides of it).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.eventcap.camera import EventCamera
from mocaprig.process.eventcap.detections import Detector
from mocaprig.process.eventcap.pipeline import (
    ApsFrame,
    BatchResult,
    EventcapOptions,
    run_batch,
)

__all__ = ["EventSource", "TakeResult", "array_source", "run_take"]

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
    """Run :func:`~.pipeline.run_batch` on every pair of consecutive frames.

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
    opt = options if options is not None else EventcapOptions()
    if len(frames) < 2:
        msg = f"EventCap needs at least two APS frames, got {len(frames)}"
        raise ValidationError(msg)
    times = np.array([f.t_us for f in frames], dtype=np.int64)
    if np.any(np.diff(times) <= 0):
        msg = "APS frames must be in strictly increasing time order"
        raise ValidationError(msg)
    start = time.perf_counter()
    detections = [detector.detect(int(f.t_us), f.image_dn) for f in frames]
    results: list[BatchResult] = []
    prev: F64 | None = None
    total = len(frames) - 1
    for k in range(total):
        a, b = frames[k], frames[k + 1]
        window = events(a.exposure_start_us, b.exposure_end_us)
        try:
            res = run_batch(
                window,
                a,
                b,
                detections[k],
                detections[k + 1],
                camera,
                shape,
                options=opt,
                start_pose=prev,
                lookahead=detections[k + 2] if prev is None and k + 2 < len(frames) else None,
            )
        except ProcessingError as err:
            msg = f"EventCap batch {k} ({a.t_us}–{b.t_us} µs) failed: {err}"
            raise ProcessingError(msg) from err
        prev = res.poses[-1]
        results.append(res)
        _log.info(
            "batch %d/%d: %d trajectories, %d correspondences, %.2f s",
            k + 1,
            total,
            res.trajectories,
            res.correspondences,
            sum(res.stage_seconds.values()),
        )
        if progress is not None:
            progress(k + 1, total)
    # Shared end frames: keep the later batch's frame 0, drop the earlier batch's last frame.
    t = np.concatenate([r.t_us[:-1] for r in results] + [results[-1].t_us[-1:]])
    poses = np.concatenate([r.poses[:-1] for r in results] + [results[-1].poses[-1:]])
    kp = np.concatenate([r.keypoints_m[:-1] for r in results] + [results[-1].keypoints_m[-1:]])
    return TakeResult(
        t_us=t,
        poses=poses,
        keypoints_m=kp,
        batches=tuple(results),
        detection_source=detector.source,
        seconds=time.perf_counter() - start,
    )
