"""The tasks of a batch run: module-level functions of small picklable records, so that any
engine can ship them to a worker. Each reads its inputs where they are (a path on the shared
file system, or an fsspec URL fetched by the worker, :func:`.sessions.local_path`).

* :func:`democap_plan_task` — index one recording's rig instants
  (:func:`~mocaprig.process.democap.replay.plan_replay`).
* :func:`democap_span_task` — DeMoCap on one span of those instants
  (:func:`~mocaprig.process.democap.replay.replay_span`); its results come back (a few kB per
  instant: markers, joints, the fused cloud) and the runner joins the spans and writes the
  replay's files (:func:`~mocaprig.process.democap.replay.write_replay`).
* :func:`eventcap_plan_task` — index one take: its batches and segments (:mod:`.segments`).
* :func:`eventcap_segment_task` — one segment of a take; its 1 kHz output comes back (a few
  tens of kB per batch) and the runner stitches and writes the take.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Final, Literal

from mocaprig.errors import ValidationError
from mocaprig.process.batch.segments import (
    DEFAULT_DEMOCAP_SPAN,
    DEFAULT_OVERLAP,
    DEFAULT_SEGMENT_BATCHES,
    EventcapInputs,
    EventcapPlan,
    Segment,
    SegmentResult,
    plan_eventcap,
    run_segment,
)
from mocaprig.process.batch.sessions import SessionInputs, local_path

# Imported with this module, not in the task: a Dask worker unpickles the next task's
# ReplayPlan on its event-loop thread while a task runs on another, and two threads importing
# the democap package at once can see it half initialised.
from mocaprig.process.democap.infer import DemocapPredictor
from mocaprig.process.democap.replay import ReplayPlan, ReplaySpan, plan_replay, replay_span
from mocaprig.process.democap.subject import load_subject

__all__ = [
    "DEFAULT_DEMOCAP_SPAN",
    "METHODS",
    "OUTPUT_STEM",
    "Method",
    "ProcessSettings",
    "democap_calibration",
    "democap_plan_task",
    "democap_span_task",
    "eventcap_inputs",
    "eventcap_plan_task",
    "eventcap_segment_task",
]

_log = logging.getLogger(__name__)

#: A pipeline a batch run can apply to a recording.
Method = Literal["democap", "eventcap"]
METHODS: Final[tuple[Method, ...]] = ("democap", "eventcap")
#: The outputs' stem in each method's folder (``democap.mcap`` + ``.c3d`` + ``.csv``, ...).
OUTPUT_STEM: Final = {"democap": "democap", "eventcap": "eventcap"}


@dataclass(frozen=True, slots=True)
class ProcessSettings:
    """The settings of a batch run (the ``mocaprig process`` options).

    Attributes:
        methods: The pipelines to run on every session.
        democap_every: DeMoCap processes every n-th rig instant.
        democap_span: DeMoCap instants per task (the unit of parallel work within a session).
        height_m: EventCap's template for sessions without ``eventcap_shape.json`` (m).
        eventcap_start_s, eventcap_end_s: EventCap uses the APS frames exposed in this span of
            the DAVIS timeline (s since its timestamp reset); None: from the start / to the end.
        eventcap_batches: EventCap runs only the first N batches of that span.
        segment_batches: Batches an EventCap segment keeps (the unit of parallel work).
        overlap: Warm-up batches before a segment's kept ones (:mod:`.segments`).
        template: Draw EventCap's fitted capsules in its MCAP.
    """

    methods: tuple[Method, ...] = METHODS
    democap_every: int = 1
    democap_span: int = DEFAULT_DEMOCAP_SPAN
    height_m: float | None = None
    eventcap_start_s: float | None = None
    eventcap_end_s: float | None = None
    eventcap_batches: int | None = None
    segment_batches: int = DEFAULT_SEGMENT_BATCHES
    overlap: int = DEFAULT_OVERLAP
    template: bool = True

    def __post_init__(self) -> None:
        if not self.methods or any(m not in METHODS for m in self.methods):
            msg = f"--methods {','.join(self.methods)}: choose from {','.join(METHODS)}"
            raise ValidationError(msg)
        if len(set(self.methods)) != len(self.methods):
            msg = f"--methods {','.join(self.methods)}: each method once"
            raise ValidationError(msg)
        for name, value, low in (
            ("--democap-every", self.democap_every, 1),
            ("--democap-span", self.democap_span, 1),
            ("--segment-batches", self.segment_batches, 1),
            ("--overlap", self.overlap, 0),
            ("--eventcap-batches", self.eventcap_batches, 1),
        ):
            if value is not None and value < low:
                msg = f"{name} must be >= {low}, got {value}"
                raise ValidationError(msg)
        s, e = self.eventcap_start_s, self.eventcap_end_s
        if s is not None and e is not None and e <= s:
            msg = f"--eventcap-end {e} s must be after --eventcap-start {s} s"
            raise ValidationError(msg)


def democap_calibration(session: SessionInputs) -> Path:
    """The session's calibration as a local path on the calling worker.

    Raises:
        ValidationError: the session has no calibration.
    """
    if session.calibration is None:
        msg = (
            f"{session.name}: no calibration for DeMoCap; give --calib or put calib.toml "
            f"(mocaprig calibrate vicon) in {session.folder}"
        )
        raise ValidationError(msg)
    return local_path(session.calibration)


def democap_plan_task(session: SessionInputs, settings: ProcessSettings) -> ReplayPlan:
    """Index the rig instants of ``session`` (:func:`~mocaprig.process.democap.replay.plan_replay`).

    Raises:
        ValidationError: the session has no calibration. The plan's errors otherwise.
    """
    calibration = democap_calibration(session)
    return plan_replay(local_path(session.recording), calibration, every=settings.democap_every)


def democap_span_task(session: SessionInputs, plan: ReplayPlan) -> ReplaySpan:
    """DeMoCap on every instant of ``plan`` (a span of the session's plan,
    :meth:`~mocaprig.process.democap.replay.ReplayPlan.span`) with the committed network,
    every instant solved as the session's subject where it has a subject file.

    Raises:
        CalibrationError: the subject file is unreadable or not a subject file.
    """
    # The recording as this worker sees it (an fsspec URL is fetched where it runs).
    here = replace(plan, session=Path(local_path(session.recording)))
    predictor = None
    if session.subject is not None:
        predictor = DemocapPredictor(subject=load_subject(local_path(session.subject)))
    return replay_span(here, democap_calibration(session), predictor=predictor)


def eventcap_inputs(session: SessionInputs, settings: ProcessSettings) -> EventcapInputs:
    """EventCap's inputs of a session, as local paths on the calling worker.

    Raises:
        ValidationError: no detections, no calibration, or no template for the session.
    """
    where = session.folder
    if session.detections is None:
        msg = (
            f"{session.name}: no EventCap detections; put eventcap_detections.json (ours or "
            f"COCO) or an OpenPose eventcap_detections/ folder in {where}"
        )
        raise ValidationError(msg)
    if session.eventcap_calibration is None:
        msg = (
            f"{session.name}: no calibration with the DAVIS for EventCap; put "
            f"eventcap_calib.toml (mocaprig calibrate board) in {where} or give --calib"
        )
        raise ValidationError(msg)
    if session.shape is None and settings.height_m is None:
        msg = (
            f"{session.name}: no EventCap template; give --height M or put eventcap_shape.json "
            f"in {where}"
        )
        raise ValidationError(msg)
    return EventcapInputs(
        session=local_path(session.recording),
        calibration=local_path(session.eventcap_calibration),
        detections=local_path(session.detections),
        shape=None if session.shape is None else local_path(session.shape),
        height_m=settings.height_m if session.shape is None else None,
        start_s=settings.eventcap_start_s,
        end_s=settings.eventcap_end_s,
        batches=settings.eventcap_batches,
    )


def eventcap_plan_task(session: SessionInputs, settings: ProcessSettings) -> EventcapPlan:
    """Index a take and cut it into segments (:func:`.segments.plan_eventcap`)."""
    return plan_eventcap(
        eventcap_inputs(session, settings),
        segment_batches=settings.segment_batches,
        overlap=settings.overlap,
    )


def eventcap_segment_task(
    session: SessionInputs, settings: ProcessSettings, segment: Segment
) -> SegmentResult:
    """Run one segment of a take (:func:`.segments.run_segment`)."""
    return run_segment(eventcap_inputs(session, settings), segment)
