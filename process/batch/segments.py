"""EventCap on a long take as independent segments, stitched into one take's output.

:func:`~mocaprig.process.eventcap.take.iter_take` chains its batches: each starts from the
previous batch's last pose, so one take is one sequential computation. To spread a take over
workers it is cut into **segments** of whole batches (:func:`plan_segments`). A segment starts
fresh, like a take's first batch (no pose handed on; the first batch's left/right vote), from
``overlap`` batches *before* the batches it keeps: those warm-up batches are run and thrown away,
so that the first kept batch starts from a pose the warm-up tracked, as in the unsplit take.

The **boundary** between two segments is a batch boundary fixed by the plan alone (the take's
batch count, ``segment_batches`` and ``overlap``), never by the engine or the number of
workers: the in-process, pool and distributed runs compute the same segments and give the same
output. Each shared APS-frame instant is reported once, by the later batch (as in
:func:`iter_take`): a segment that is not the take's last drops its last instant, which the
next segment's first kept batch reports.

What stitching costs against the unsplit take (the pose after ``overlap`` warm-up batches is
not the pose after all the batches before it) is measured by ``benchmarks/process_scaling.py``
and reported in ``docs/cluster.md``.

Inputs are read where they are: a segment task gets paths (:class:`EventcapInputs`) and reads
only its own frames and events from the recording (:class:`~.eventcap.run.RecordingFrames`,
:class:`~.eventcap.run.RecordingEventSource`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Final, overload

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ProcessingError, ValidationError

if TYPE_CHECKING:
    from mocaprig.process.eventcap.pipeline import ApsFrame, EventcapOptions

__all__ = [
    "DEFAULT_DEMOCAP_SPAN",
    "DEFAULT_OVERLAP",
    "DEFAULT_SEGMENT_BATCHES",
    "EventcapInputs",
    "EventcapPlan",
    "Segment",
    "SegmentResult",
    "StitchedTake",
    "plan_eventcap",
    "plan_segments",
    "run_segment",
    "stitch_segments",
    "write_eventcap",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Batches a segment keeps (25 batches = 1 s of a 25 Hz APS take).
DEFAULT_SEGMENT_BATCHES: Final = 25
#: Warm-up batches run before a segment's kept batches (thrown away).
DEFAULT_OVERLAP: Final = 1
#: DeMoCap instants per task (10 s of a 30 fps rig: 15–40 s of work here at 7.5–20 instants/s,
#: against 0.2–0.7 s to load the network and open the recording; benchmarks/democap_spans.py).
#: Here beside the EventCap segment sizes so that the command line reads them without torch.
DEFAULT_DEMOCAP_SPAN: Final = 300
#: Host time (ns) around a segment's frames whose event packets it indexes: a packet is
#: recorded within milliseconds of its events; 2 s covers a stalled USB queue.
_EVENT_LOG_MARGIN_NS: Final = 2_000_000_000


@dataclass(frozen=True, slots=True)
class Segment:
    """Batches ``[first, end)`` of a take are run; ``[keep, end)`` are kept.

    Attributes:
        index: The segment's place in the take.
        first: First batch run (``keep - first`` warm-up batches before the kept ones).
        keep: First batch kept.
        end: One past the last batch run and kept.
        last: Whether this is the take's last segment (its last instant is kept).
    """

    index: int
    first: int
    keep: int
    end: int
    last: bool

    @property
    def warmup(self) -> int:
        """Batches run and thrown away."""
        return self.keep - self.first

    @property
    def batches_run(self) -> int:
        """Batches this segment runs (warm-up included)."""
        return self.end - self.first


def plan_segments(
    batches: int, *, segment_batches: int = DEFAULT_SEGMENT_BATCHES, overlap: int = DEFAULT_OVERLAP
) -> tuple[Segment, ...]:
    """Cut a take of ``batches`` batches into segments of ``segment_batches`` kept batches,
    each run from ``overlap`` batches earlier (module doc). A take no longer than one segment
    is one segment, the unsplit take.

    Raises:
        ValidationError: ``batches`` or ``segment_batches`` below 1, or ``overlap`` below 0.
    """
    for name, value, low in (
        ("batches", batches, 1),
        ("segment_batches", segment_batches, 1),
        ("overlap", overlap, 0),
    ):
        if isinstance(value, bool) or int(value) != value or value < low:
            msg = f"{name} must be an integer >= {low}, got {value!r}"
            raise ValidationError(msg)
    starts = range(0, batches, segment_batches)
    return tuple(
        Segment(
            index=i,
            first=max(0, k - overlap),
            keep=k,
            end=min(k + segment_batches, batches),
            last=k + segment_batches >= batches,
        )
        for i, k in enumerate(starts)
    )


@dataclass(frozen=True, slots=True)
class EventcapInputs:
    """What an EventCap task reads (local paths; a worker reads them where they are).

    Attributes:
        session: The recording (``.mcap``).
        calibration: Its calibration file (with the DAVIS entry).
        detections: Detections file or folder (:func:`~.eventcap.run.load_detector`).
        shape: A body-shape JSON (:func:`~.eventcap.run.load_shape`), or None with ``height_m``.
        height_m: The actor's standing height (m) when there is no ``shape``.
        davis: The DAVIS serial when the recording has several.
        start_s, end_s: Use the APS frames exposed inside this span of the DAVIS timeline (s).
        batches: Run only the first N batches of the span.
        options: Pipeline settings (``step_us`` 1000; None: the defaults).
    """

    session: Path
    calibration: Path
    detections: Path
    shape: Path | None = None
    height_m: float | None = None
    davis: str | None = None
    start_s: float | None = None
    end_s: float | None = None
    batches: int | None = None
    options: EventcapOptions | None = None


@dataclass(frozen=True, slots=True)
class EventcapPlan:
    """A take's batch count and its segments (:func:`plan_eventcap`)."""

    batches: int
    segments: tuple[Segment, ...]


class _FrameSpan(Sequence["ApsFrame"]):
    """Frames ``[lo, hi)`` of a lazy frame sequence, still lazy (a batch decodes its own)."""

    def __init__(self, frames: Sequence[ApsFrame], lo: int, hi: int) -> None:
        self._frames, self._lo, self._n = frames, lo, hi - lo

    def __len__(self) -> int:
        return self._n

    @overload
    def __getitem__(self, index: int) -> ApsFrame: ...

    @overload
    def __getitem__(self, index: slice) -> Sequence[ApsFrame]: ...

    def __getitem__(self, index: int | slice) -> ApsFrame | Sequence[ApsFrame]:
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(self._n))]
        if not -self._n <= index < self._n:
            msg = f"frame {index} outside a span of {self._n}"
            raise IndexError(msg)
        return self._frames[self._lo + index % self._n]

    def __iter__(self) -> Iterator[ApsFrame]:
        for i in range(self._n):
            yield self[i]


def plan_eventcap(
    inputs: EventcapInputs,
    *,
    segment_batches: int = DEFAULT_SEGMENT_BATCHES,
    overlap: int = DEFAULT_OVERLAP,
) -> EventcapPlan:
    """Index the take once: its batch count (frames in the span, minus one), every used frame
    covered by a detection, the calibration's DAVIS entry present; then the segments.

    Raises:
        RecordingError: no DAVIS, no APS frames or no events. CalibrationError: no DAVIS
            entry in the calibration. ProcessingError: fewer than 2 frames in the span, or
            detections that do not cover them. ValidationError: a bad option.
    """
    # The pipeline (torch, OpenCV) is imported by the task that runs it, not by whoever
    # unpickles a task's records.
    from mocaprig.acquire.recording import Recording
    from mocaprig.calib.calibration import read_calibration
    from mocaprig.process.eventcap.run import (
        check_coverage,
        davis_calibration,
        load_detector,
        load_shape,
        select_davis,
        select_frames,
    )

    load_shape(height_m=inputs.height_m, shape_path=inputs.shape)
    cal = read_calibration(inputs.calibration)
    with Recording(inputs.session) as rec:
        dav = select_davis(rec, inputs.davis)
        davis_calibration(cal, dav, str(inputs.calibration))
        frames = select_frames(
            dav, start_s=inputs.start_s, end_s=inputs.end_s, batches=inputs.batches
        )
        n = len(frames)
        if n < 2:
            msg = (
                f"{inputs.session}: {n} APS frame(s) of DAVIS {dav.device.serial} in the selected "
                "span; EventCap needs at least 2 (widen --eventcap-start/--eventcap-end)"
            )
            raise ProcessingError(msg)
        detector = load_detector(inputs.detections, frames.all_times_us)
        check_coverage(detector, frames, str(inputs.detections))
    return EventcapPlan(
        n - 1, plan_segments(n - 1, segment_batches=segment_batches, overlap=overlap)
    )


@dataclass(frozen=True, slots=True, eq=False)
class SegmentResult:
    """The kept 1 kHz output of one segment (:func:`run_segment`).

    Attributes:
        segment: The segment.
        t_us: (n,) tracking frame times, DAVIS µs, increasing every ``step_us``.
        poses: (n, 33) poses (world, m, rad).
        keypoints_m: (n, 19, 3) EventCap keypoints, world m.
        davis: The DAVIS (``davis/<serial>``).
        detection_source: The detector's label.
        seconds: Wall time of the segment task (warm-up included).
        compute_s: The batches' own stage times, summed (warm-up included); ``seconds``
            minus this is the task's overhead (reading the calibration, indexing the
            recording, loading the detections).
    """

    segment: Segment
    t_us: I64 = field(repr=False)
    poses: F64 = field(repr=False)
    keypoints_m: F64 = field(repr=False)
    davis: str
    detection_source: str
    seconds: float
    compute_s: float = 0.0


def run_segment(inputs: EventcapInputs, segment: Segment) -> SegmentResult:
    """Run one segment of a take (module doc): its warm-up and kept batches, fresh from its
    first batch (with the next frame's detection for its vote, as the take's first batch);
    keep the kept batches' output, without the last instant unless the segment is the take's
    last.

    Raises:
        RecordingError, CalibrationError, ValidationError: unreadable or wrong inputs.
        ProcessingError: a batch failed, or the segment was not planned on this take.
    """
    from mocaprig.acquire.recording import Recording
    from mocaprig.calib.calibration import read_calibration
    from mocaprig.process.eventcap.camera import EventCamera
    from mocaprig.process.eventcap.run import (
        RecordingEventSource,
        davis_calibration,
        load_detector,
        load_shape,
        select_davis,
        select_frames,
    )
    from mocaprig.process.eventcap.take import iter_take

    t0 = time.perf_counter()
    shape = load_shape(height_m=inputs.height_m, shape_path=inputs.shape)
    cal = read_calibration(inputs.calibration)
    with Recording(inputs.session) as rec:
        dav = select_davis(rec, inputs.davis)
        camera = EventCamera.from_calibration(davis_calibration(cal, dav, str(inputs.calibration)))
        frames = select_frames(
            dav, start_s=inputs.start_s, end_s=inputs.end_s, batches=inputs.batches
        )
        n = len(frames)
        if segment.end + 1 > n or segment.last != (segment.end == n - 1):
            msg = (
                f"{inputs.session}: segment {segment.index} ends at batch {segment.end} "
                f"(last: {segment.last}), the take has {n - 1}; plan the segments on this take "
                "(plan_eventcap)"
            )
            raise ProcessingError(msg)
        detector = load_detector(inputs.detections, frames.all_times_us)
        # One frame past the segment when the take has one (every segment but the last): the
        # segment's first batch then votes with the next frame's detection as the take's first
        # batch does, and iter_take leaves the last instant to the next segment, as the unsplit
        # take leaves it to the next batch. The batch that frame would end is never run.
        span = _FrameSpan(frames, segment.first, min(segment.end + 2, n))
        kept: list[tuple[I64, F64, F64]] = []
        compute_s = 0.0
        # Only the events recorded around the segment's frames are indexed (a long take's
        # segment need not decode the whole take); a window past them indexes the rest.
        lo_ns, hi_ns = frames.log_span_ns(segment.first, min(segment.end + 2, n))
        events = RecordingEventSource(
            dav, start_ns=lo_ns - _EVENT_LOG_MARGIN_NS, end_ns=hi_ns + _EVENT_LOG_MARGIN_NS
        )
        for chunk in iter_take(events, span, detector, camera, shape, options=inputs.options):
            compute_s += sum(chunk.result.stage_seconds.values())
            if chunk.batch >= segment.warmup:
                kept.append((chunk.t_us, chunk.poses, chunk.keypoints_m))
            if chunk.batch == segment.batches_run - 1:
                break
    t_us = np.concatenate([k[0] for k in kept])
    poses = np.concatenate([k[1] for k in kept])
    keypoints = np.concatenate([k[2] for k in kept])
    seconds = time.perf_counter() - t0
    _log.info(
        "%s: segment %d (batches %d-%d, %d warm-up): %d frames, %.1f s",
        inputs.session,
        segment.index,
        segment.keep,
        segment.end - 1,
        segment.warmup,
        t_us.size,
        seconds,
    )
    return SegmentResult(
        segment, t_us, poses, keypoints, dav.device.label, detector.source, seconds, compute_s
    )


@dataclass(frozen=True, slots=True, eq=False)
class StitchedTake:
    """A take's 1 kHz output from its segments (:func:`stitch_segments`)."""

    t_us: I64 = field(repr=False)
    poses: F64 = field(repr=False)
    keypoints_m: F64 = field(repr=False)
    davis: str
    detection_source: str
    batches: int


def stitch_segments(
    results: Sequence[SegmentResult], *, step_us: int = 1000, batches: int | None = None
) -> StitchedTake:
    """Join the segments' outputs in take order: one instant every ``step_us`` with no gap
    and no repeat (each boundary instant once, from the later segment).

    Raises:
        ProcessingError: a segment missing or twice, or their times not one contiguous grid.
    """
    if not results:
        msg = "no segment results to stitch"
        raise ProcessingError(msg)
    ordered = sorted(results, key=lambda r: r.segment.index)
    indices = [r.segment.index for r in ordered]
    if indices != list(range(len(ordered))) or not ordered[-1].segment.last:
        msg = f"segments {indices} do not make a whole take (0..last, each once)"
        raise ProcessingError(msg)
    t_us = np.concatenate([r.t_us for r in ordered])
    steps = np.diff(t_us)
    if steps.size and not np.all(steps == step_us):
        bad = int(np.flatnonzero(steps != step_us)[0])
        msg = (
            f"stitched segments are not contiguous at {t_us[bad]} µs (step {steps[bad]} µs, "
            f"expected {step_us}); were they planned on the same take and options?"
        )
        raise ProcessingError(msg)
    return StitchedTake(
        t_us=t_us,
        poses=np.concatenate([r.poses for r in ordered]),
        keypoints_m=np.concatenate([r.keypoints_m for r in ordered]),
        davis=ordered[0].davis,
        detection_source=ordered[0].detection_source,
        batches=batches if batches is not None else ordered[-1].segment.end,
    )


def write_eventcap(
    inputs: EventcapInputs,
    take: StitchedTake,
    *,
    out: Path,
    template: bool = True,
) -> dict[str, Path]:
    """Write a stitched take as ``eventcap run`` does (MCAP beside C3D and BVH, same stem;
    :class:`~.eventcap.run.EventcapResultsWriter`, all or nothing). Returns the paths.

    Raises:
        ProcessingError: an output exists or a write failed.
    """
    from mocaprig.calib.calibration import read_calibration
    from mocaprig.process.eventcap.run import (
        _RATE_HZ,
        EventcapResultsWriter,
        ResultsHeader,
        default_outputs,
        load_shape,
        results_clock,
        results_ns,
    )

    cal = read_calibration(inputs.calibration)
    shape = load_shape(height_m=inputs.height_m, shape_path=inputs.shape)
    clock, time_base = results_clock(cal, take.davis)
    if clock is None:
        _log.info("the calibration maps no clock for %s; results in DAVIS time", take.davis)
    header = ResultsHeader(
        session=inputs.session,
        davis=take.davis,
        batches=take.batches,
        frames=int(take.t_us.size),
        time_base=time_base,
        t_first_davis_us=int(take.t_us[0]),
        world_frame=cal.world_frame,
        detection_source=take.detection_source,
    )
    t_ns = results_ns(clock, take.t_us)
    c3d, bvh = default_outputs(out)
    with EventcapResultsWriter(
        header,
        shape,
        mcap=out,
        c3d=c3d,
        bvh=bvh,
        calibration=cal,
        template="capsules" if template else "none",
    ) as writer:
        block = 40 * max(1, 40_000 // round(1e6 / _RATE_HZ))
        for i0 in range(0, take.t_us.size, block):
            i1 = i0 + block
            writer.write(t_ns[i0:i1], take.poses[i0:i1], take.keypoints_m[i0:i1])
    return {"mcap": out, "c3d": c3d, "bvh": bvh}
