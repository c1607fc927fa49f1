"""A batch run: every method on every session, on an engine, resumable, failures reported.

Output layout (``OUT`` on a file system the workers see at the same path)::

    OUT/<session>/<method>/          finished: the method's files and done.json (the manifest)
    OUT/<session>/.<method>.part-*/  being written (one folder per attempt)

A method's files are written into its attempt's ``.part`` folder and the whole folder is renamed
to ``<method>/`` once they are all finished (one rename on one file system: all or nothing).
A finished ``<method>/`` is kept and skipped by the next run; a ``.part`` folder is removed when
its attempt fails, and any left by a run that was killed are removed when the method starts
again (one run per output folder at a time).

Each task is tried at most twice: a task that raises, or whose worker died, is submitted once
more; a second failure fails the (session, method) with its stage (``instants``, ``span i``,
``plan``, ``segment i``, ``write``) and the error, and the run goes on with the others.
DeMoCap's instants run in spans of ``democap_span`` as separate tasks, EventCap's batches in
segments; the runner joins the spans (:func:`~mocaprig.process.democap.replay.join_spans`) or
stitches the segments (:mod:`.segments`) and writes the method's files.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import logging
import shutil
import time
import uuid
from collections.abc import Callable, MutableMapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Literal

from mocaprig import __version__
from mocaprig.errors import ProcessingError
from mocaprig.json_values import to_jsonable
from mocaprig.process.batch.engines import Engine
from mocaprig.process.batch.segments import (
    stitch_segments,
    write_eventcap,
)
from mocaprig.process.batch.sessions import SessionInputs
from mocaprig.process.batch.tasks import (
    OUTPUT_STEM,
    Method,
    ProcessSettings,
    democap_calibration,
    democap_plan_task,
    democap_span_task,
    eventcap_inputs,
    eventcap_plan_task,
    eventcap_segment_task,
)
from mocaprig.process.democap.replay import join_spans, output_paths, write_replay

__all__ = [
    "MANIFEST_NAME",
    "TASKS",
    "BatchReport",
    "JobReport",
    "JobStatus",
    "Progress",
    "method_folder",
    "process_sessions",
]

_log = logging.getLogger(__name__)

#: The manifest a finished method folder holds.
MANIFEST_NAME: Final = "done.json"
#: Tries per task (the first and one retry).
_TRIES: Final = 2

#: The worker functions by stage kind: ``instants`` and ``span`` (DeMoCap), ``plan`` and
#: ``segment`` (EventCap). A plain mapping, so that a test can put in its own (``patch.dict``).
TASKS: MutableMapping[str, Callable[..., Any]] = {
    "instants": democap_plan_task,
    "span": democap_span_task,
    "plan": eventcap_plan_task,
    "segment": eventcap_segment_task,
}

#: ``done``: written now; ``skipped``: finished by an earlier run and kept; ``failed``.
JobStatus = Literal["done", "skipped", "failed"]
#: ``(session, method, message)`` as the work goes on.
Progress = Callable[[str, str, str], None]


@dataclass(frozen=True, slots=True)
class JobReport:
    """How one method went on one session.

    Attributes:
        session: The session's name.
        method: The method.
        status: See :data:`JobStatus`.
        outputs: The files in its folder (the manifest last).
        seconds: Wall time in this run (0 when skipped).
        error: What failed (the last try's error), None otherwise.
        stage: The stage that failed, None otherwise.
        retried: Stages tried twice (each with its first error).
        details: The method's own summary (DeMoCap: the replay's; EventCap: batches,
            segments, frames).
    """

    session: str
    method: Method
    status: JobStatus
    outputs: tuple[Path, ...] = ()
    seconds: float = 0.0
    error: str | None = None
    stage: str | None = None
    retried: tuple[str, ...] = ()
    details: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The JSON row of the summary table."""
        return {
            "session": self.session,
            "method": self.method,
            "status": self.status,
            "outputs": [str(p) for p in self.outputs],
            "seconds": round(self.seconds, 3),
            "error": self.error,
            "stage": self.stage,
            "retried": list(self.retried),
            "details": to_jsonable(self.details),
        }


@dataclass(frozen=True, slots=True)
class BatchReport:
    """A batch run's outcome: one :class:`JobReport` per (session, method), in input order."""

    jobs: tuple[JobReport, ...]
    engine: str
    seconds: float

    @property
    def ok(self) -> bool:
        """Whether nothing failed."""
        return all(j.status != "failed" for j in self.jobs)

    def to_json(self) -> dict[str, Any]:
        """The ``--json`` object."""
        counts = {s: sum(j.status == s for j in self.jobs) for s in ("done", "skipped", "failed")}
        return {
            "engine": self.engine,
            "seconds": round(self.seconds, 3),
            **counts,
            "jobs": [j.to_json() for j in self.jobs],
        }


def method_folder(out: Path, session: str, method: Method) -> Path:
    """Where a method's finished outputs of a session are."""
    return out / session / method


@dataclass(eq=False)
class _Job:
    session: SessionInputs
    method: Method
    final: Path
    t0: float = 0.0
    staging: Path | None = None
    plan: Any = None  # the DeMoCap ReplayPlan or the EventCap EventcapPlan
    parts: dict[int, Any] = field(default_factory=dict)  # ReplaySpan / SegmentResult by index
    expected: int = 0  # parts planned
    retried: list[str] = field(default_factory=list)
    report: JobReport | None = None

    def new_staging(self) -> Path:
        self.drop_staging()
        self.staging = self.final.parent / f".{self.method}.part-{uuid.uuid4().hex[:12]}"
        self.staging.mkdir(parents=True)
        return self.staging

    def drop_staging(self) -> None:
        if self.staging is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging = None


@dataclass(frozen=True, slots=True, eq=False)
class _Try:
    job: _Job
    stage: str
    attempt: int
    args: tuple[Any, ...]


def _describe(err: BaseException) -> str:
    text = str(err) or type(err).__name__
    return text if isinstance(err, ProcessingError) else f"{type(err).__name__}: {text}"


def _method_settings(job: _Job, settings: ProcessSettings) -> dict[str, Any]:
    """The settings that shape a method's outputs (kept in its manifest)."""
    if job.method == "democap":
        # the spans do not change the files
        return {"democap_every": settings.democap_every, "subject": job.session.subject}
    return {
        k: getattr(settings, k)
        for k in (
            "height_m",
            "eventcap_start_s",
            "eventcap_end_s",
            "eventcap_batches",
            "segment_batches",
            "overlap",
            "template",
        )
    }


def _finished_before(job: _Job, settings: ProcessSettings) -> JobReport | None:
    """The report of a method folder an earlier run finished, None when there is none
    (``details["other_settings"]`` when it was made with other settings).

    Raises:
        ProcessingError: the folder exists without a manifest (not written by this command).
    """
    if not job.final.exists():
        return None
    manifest = job.final / MANIFEST_NAME
    if not manifest.is_file():
        msg = (
            f"{job.final} exists but has no {MANIFEST_NAME}, so mocaprig process did not "
            "finish it; move it away or remove it to process this method again"
        )
        raise ProcessingError(msg)
    outputs = tuple(sorted(p for p in job.final.iterdir() if p.name != MANIFEST_NAME))
    try:
        made_with = json.loads(manifest.read_text(encoding="utf-8")).get("settings")
    except (OSError, ValueError, AttributeError):
        made_with = None
    now = to_jsonable(_method_settings(job, settings))
    details = {} if made_with == now else {"other_settings": made_with}
    return JobReport(job.session.name, job.method, "skipped", (*outputs, manifest), details=details)


def _plan(job: _Job) -> Any:
    if job.plan is None:
        msg = f"{job.session.name} {job.method}: a part finished before the work was planned"
        raise ProcessingError(msg)
    return job.plan


def _remove_stale_parts(job: _Job) -> None:
    for stale in job.final.parent.glob(f".{job.method}.part-*"):
        _log.warning("removing %s, left by an interrupted run", stale)
        shutil.rmtree(stale, ignore_errors=True)


def process_sessions(
    sessions: Sequence[SessionInputs],
    *,
    out: str | Path,
    settings: ProcessSettings,
    engine: Engine,
    progress: Progress | None = None,
) -> BatchReport:
    """Run ``settings.methods`` on every session on ``engine`` (module doc).

    Returns:
        One report per (session, method); failures are in it, not raised.

    Raises:
        ProcessingError: ``out`` cannot be created.
    """
    t_start = time.perf_counter()
    out_dir = Path(out)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        msg = f"--out {out_dir}: cannot create the output folder ({err})"
        raise ProcessingError(msg) from err

    def say(job: _Job, message: str) -> None:
        _log.info("%s %s: %s", job.session.name, job.method, message)
        if progress is not None:
            progress(job.session.name, job.method, message)

    jobs = [
        _Job(s, m, method_folder(out_dir, s.name, m)) for s in sessions for m in settings.methods
    ]
    pending: dict[cf.Future[Any], _Try] = {}

    def launch(job: _Job, stage: str, *args: Any, attempt: int = 1) -> None:
        fn = TASKS[stage.split()[0]]
        pending[engine.submit(fn, *args)] = _Try(job, stage, attempt, args)

    def fail(job: _Job, stage: str, err: BaseException) -> None:
        job.drop_staging()
        for fut, t in list(pending.items()):
            if t.job is job:
                engine.cancel(fut)
                del pending[fut]
        job.report = JobReport(
            job.session.name,
            job.method,
            "failed",
            seconds=time.perf_counter() - job.t0,
            error=_describe(err),
            stage=stage,
            retried=tuple(job.retried),
        )
        say(job, f"failed at {stage}: {job.report.error}")

    def publish(job: _Job, details: dict[str, Any]) -> None:
        staging = job.staging
        if staging is None:  # a job publishes from its staging folder; never without one
            msg = f"{job.final}: nothing staged"
            raise ProcessingError(msg)
        seconds = time.perf_counter() - job.t0
        files = sorted(p.name for p in staging.iterdir())
        manifest = {
            "software_version": __version__,
            "session": job.session.name,
            "recording": job.session.recording,
            "method": job.method,
            "files": files,
            "seconds": seconds,
            "retried": job.retried,
            "settings": _method_settings(job, settings),
            "details": details,
        }
        (staging / MANIFEST_NAME).write_text(
            json.dumps(to_jsonable(manifest), indent=2) + "\n", encoding="utf-8"
        )
        staging.rename(job.final)  # the whole folder at once; refused if it appeared meanwhile
        job.staging = None
        job.report = JobReport(
            job.session.name,
            job.method,
            "done",
            (*(job.final / f for f in files), job.final / MANIFEST_NAME),
            seconds,
            retried=tuple(job.retried),
            details=details,
        )
        say(job, f"done in {seconds:.1f} s")

    def start(job: _Job) -> None:
        job.t0 = time.perf_counter()
        try:
            job.report = _finished_before(job, settings)
        except ProcessingError as err:
            fail(job, "outputs", err)
            return
        if job.report is not None:
            other = " with other settings" if job.report.details else ""
            say(job, f"finished earlier{other}; kept (remove {job.final} to redo it)")
            return
        job.final.parent.mkdir(parents=True, exist_ok=True)
        _remove_stale_parts(job)
        if job.method == "democap":
            launch(job, "instants", job.session, settings)
        else:
            launch(job, "plan", job.session, settings)
        say(job, "started")

    def write_replay_files(job: _Job) -> None:
        plan = _plan(job)
        staging = job.new_staging()
        out = output_paths(staging / f"{OUTPUT_STEM['democap']}.mcap")
        result = join_spans(plan, list(job.parts.values()), outputs=out)
        result = write_replay(result, democap_calibration(job.session))
        details = {k: v for k, v in result.summary().items() if k != "outputs"}
        details["spans"] = len(job.parts)
        publish(job, details)

    def write_take(job: _Job) -> None:
        plan = _plan(job)
        # The batch count is the last segment's end, plan.batches (plan_segments).
        stitched = stitch_segments(list(job.parts.values()))
        staging = job.new_staging()
        stem = OUTPUT_STEM["eventcap"]
        write_eventcap(
            eventcap_inputs(job.session, settings),
            stitched,
            out=staging / f"{stem}.mcap",
            template=settings.template,
        )
        publish(
            job,
            {
                "batches": plan.batches,
                "segments": len(plan.segments),
                "segment_batches": settings.segment_batches,
                "overlap": settings.overlap,
                "tracking_frames": int(stitched.t_us.size),
                "t_first_davis_us": int(stitched.t_us[0]),
                "davis": stitched.davis,
                "detections": stitched.detection_source,
                "segment_seconds": [round(job.parts[i].seconds, 3) for i in sorted(job.parts)],
                "segment_compute_s": [round(job.parts[i].compute_s, 3) for i in sorted(job.parts)],
            },
        )

    def succeeded(t: _Try, value: Any) -> None:
        job = t.job
        kind = t.stage.split()[0]
        if kind == "instants":
            job.plan = value
            spans = value.spans(settings.democap_span)
            n = len(value.instants)
            say(job, f"{n} instant{'s' if n != 1 else ''} in {len(spans)} span(s)")
            for i, (a, b) in enumerate(spans):
                launch(job, f"span {i}", job.session, value.span(a, b))
            job.expected = len(spans)
        elif kind == "plan":
            job.plan = value
            job.expected = len(value.segments)
            n = job.expected
            say(job, f"{value.batches} batches in {n} segment{'s' if n != 1 else ''}")
            for seg in value.segments:
                launch(job, f"segment {seg.index}", job.session, settings, seg)
        else:
            job.parts[int(t.stage.split()[1])] = value
            _plan(job)
            say(job, f"{kind} {len(job.parts)}/{job.expected} done")
            if len(job.parts) == job.expected:
                write = write_replay_files if job.method == "democap" else write_take
                for attempt in range(1, _TRIES + 1):
                    try:
                        write(job)
                        return
                    except Exception as err:
                        if attempt == _TRIES:
                            fail(job, "write", err)
                        else:
                            job.retried.append(f"write: {_describe(err)}")
                            say(job, f"write failed ({_describe(err)}); retrying")

    for job in jobs:
        start(job)
    while pending:
        for fut in engine.wait(list(pending)):
            t = pending.pop(fut, None)
            if t is None or t.job.report is not None:
                continue  # a sibling task's job already failed
            try:
                value = fut.result()
            except (Exception, cf.CancelledError) as err:
                if t.attempt < _TRIES:
                    t.job.retried.append(f"{t.stage}: {_describe(err)}")
                    say(t.job, f"{t.stage} failed ({_describe(err)}); retrying")
                    launch(t.job, t.stage, *t.args, attempt=t.attempt + 1)
                else:
                    fail(t.job, t.stage, err)
                continue
            try:
                succeeded(t, value)
            except Exception as err:
                fail(t.job, t.stage, err)
    reports = tuple(j.report for j in jobs if j.report is not None)
    return BatchReport(reports, engine.describe(), time.perf_counter() - t_start)
