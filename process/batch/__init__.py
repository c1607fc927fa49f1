"""Batch processing: every pipeline on every recording, in-process, on a local process pool
or on a Dask cluster (``mocaprig process``; docs/cluster.md).

Modules: :mod:`.sessions` (the sessions and their side files), :mod:`.segments` (EventCap on a
long take as independent segments, stitched), :mod:`.tasks` (what a worker runs),
:mod:`.engines` (where the tasks run), :mod:`.runner` (the resumable run and its report),
:mod:`.commands` (the command line).
"""

from typing import TYPE_CHECKING

from mocaprig.lazy_exports import lazy_getattr

if TYPE_CHECKING:
    from mocaprig.process.batch.engines import (
        DaskEngine,
        Engine,
        InProcessEngine,
        ProcessPoolEngine,
        open_engine,
    )
    from mocaprig.process.batch.runner import BatchReport, JobReport, process_sessions
    from mocaprig.process.batch.segments import (
        EventcapInputs,
        Segment,
        plan_segments,
        run_segment,
        stitch_segments,
    )
    from mocaprig.process.batch.sessions import SessionInputs, find_sessions
    from mocaprig.process.batch.tasks import METHODS, Method, ProcessSettings

#: The public names by submodule, imported on first use (:mod:`mocaprig.lazy_exports`).
_EXPORTS: dict[str, tuple[str, ...]] = {
    "engines": (
        "DaskEngine",
        "Engine",
        "InProcessEngine",
        "ProcessPoolEngine",
        "open_engine",
    ),
    "runner": (
        "BatchReport",
        "JobReport",
        "process_sessions",
    ),
    "segments": (
        "EventcapInputs",
        "Segment",
        "plan_segments",
        "run_segment",
        "stitch_segments",
    ),
    "sessions": (
        "SessionInputs",
        "find_sessions",
    ),
    "tasks": (
        "METHODS",
        "Method",
        "ProcessSettings",
    ),
}
__getattr__ = lazy_getattr(__name__, _EXPORTS)

__all__ = [
    "METHODS",
    "BatchReport",
    "DaskEngine",
    "Engine",
    "EventcapInputs",
    "InProcessEngine",
    "JobReport",
    "Method",
    "ProcessPoolEngine",
    "ProcessSettings",
    "Segment",
    "SessionInputs",
    "find_sessions",
    "open_engine",
    "plan_segments",
    "process_sessions",
    "run_segment",
    "stitch_segments",
]
