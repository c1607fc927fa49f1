"""``mocaprig process``: every pipeline on every recording, here or on a cluster.

Registered through the ``mocaprig.commands`` entry point ``process``. The handler imports the
pipelines lazily so ``mocaprig --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from mocaprig.cli import add_json_flag, emit_json
from mocaprig.progress import StatusLine

__all__ = ["process", "register_process"]

_EPILOG = """\
Sessions: a recording (.mcap) or a folder holding session.mcap (mocaprig record/simulate) or
session/session.mcap (mocaprig demo). Paths or fsspec URLs (s3://, gs://...: read by the worker
that needs them). Side files, looked up in the session's folder:
  calib.toml                 its own calibration (used instead of --calib)
  eventcap_calib.toml        the calibration with the DAVIS entry, for EventCap
  eventcap_detections.json   EventCap's detections (ours or COCO), or
  eventcap_detections/       an OpenPose --write_json folder; required for EventCap
  eventcap_shape.json        the actor's template (BodyShape fields); else --height
  democap_subject.json       the actor's subject file (mocaprig democap subject): DeMoCap
                             solves every instant as that body
Outputs: OUT/<session>/<method>/ (democap.mcap/.c3d/.csv; eventcap.mcap/.c3d/.bvh) and a
done.json manifest. Finished methods are kept and skipped; a method is written into a hidden
.part folder and renamed into place when all its files are done. A failed task is retried once,
then reported by session and stage; the other sessions go on (exit code 1 if any failed).
DeMoCap runs a recording's instants in spans of --democap-span (each instant is independent)
and joins them; EventCap splits a take into segments of --segment-batches batches, each run
from --overlap batches earlier, and stitches them: the same output on every engine
(docs/cluster.md).

Engines (--cluster): auto (default: $DASK_SCHEDULER_ADDRESS when set, else a local process pool
when --workers > 1, else in-process), in-process, local (a process pool of --workers), or a Dask
scheduler address (tcp://host:8786; OUT must be on a file system every worker sees).

examples:
  mocaprig process sim1 sim2 --calib calib.toml --methods democap --out results
  mocaprig process demo-out --methods democap,eventcap --out results --json
  mocaprig process takes/*/ --height 1.75 --methods eventcap --workers 2 --out results
  mocaprig process s3://lab/2026-11-26/take*/ --cluster tcp://10.0.0.5:8786 --out /shared/res
"""


def register_process(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``process`` to the ``mocaprig`` parser."""
    from mocaprig.process.batch.segments import (
        DEFAULT_DEMOCAP_SPAN,
        DEFAULT_OVERLAP,
        DEFAULT_SEGMENT_BATCHES,
    )

    p = subparsers.add_parser(
        "process",
        help="run DeMoCap and EventCap on many recordings (resumable; a process pool or Dask)",
        description="Every method on every recording: resumable, in-process, a local process "
        "pool or a Dask cluster, with a summary table.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("sessions", nargs="+", metavar="SESSION", help="recordings or session folders")
    p.add_argument(
        "--calib",
        default=None,
        metavar="CALIB.toml",
        help="calibration for the sessions without their own calib.toml",
    )
    p.add_argument(
        "--methods",
        default="democap,eventcap",
        metavar="LIST",
        help="comma list of democap,eventcap (default: both)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--cluster",
        default="auto",
        metavar="auto|in-process|local|ADDRESS",
        help="where the tasks run (default: auto; see below)",
    )
    p.add_argument("--workers", type=int, default=None, metavar="N", help="local pool size")
    p.add_argument(
        "--democap-every", type=int, default=1, metavar="N", help="DeMoCap: every n-th instant"
    )
    p.add_argument(
        "--democap-span",
        type=int,
        default=DEFAULT_DEMOCAP_SPAN,
        metavar="N",
        help=f"DeMoCap instants per task (default {DEFAULT_DEMOCAP_SPAN})",
    )
    p.add_argument(
        "--height",
        type=float,
        default=None,
        metavar="M",
        help="EventCap: actor height (m) for sessions without eventcap_shape.json",
    )
    p.add_argument(
        "--eventcap-start", type=float, default=None, metavar="S", help="DAVIS timeline start (s)"
    )
    p.add_argument(
        "--eventcap-end", type=float, default=None, metavar="S", help="DAVIS timeline end (s)"
    )
    p.add_argument(
        "--eventcap-batches",
        type=int,
        default=None,
        metavar="N",
        help="EventCap: only the first N batches of the span",
    )
    p.add_argument(
        "--segment-batches",
        type=int,
        default=DEFAULT_SEGMENT_BATCHES,
        metavar="N",
        help=f"EventCap batches per segment task (default {DEFAULT_SEGMENT_BATCHES})",
    )
    p.add_argument(
        "--overlap",
        type=int,
        default=DEFAULT_OVERLAP,
        metavar="N",
        help=f"warm-up batches before each segment (default {DEFAULT_OVERLAP})",
    )
    p.add_argument(
        "--no-template", action="store_true", help="EventCap: leave the capsules out of its MCAP"
    )
    add_json_flag(p)
    p.set_defaults(func=process)


def process(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig process``: 0 when every method finished (now or before), 1 when
    one failed (the table says which, where and why).

    Raises:
        ValidationError: a bad option or session. ProcessingError: no engine.
    """
    from mocaprig.process.batch.engines import open_engine
    from mocaprig.process.batch.runner import process_sessions
    from mocaprig.process.batch.sessions import find_sessions
    from mocaprig.process.batch.tasks import ProcessSettings

    settings = ProcessSettings(
        methods=tuple(m.strip() for m in args.methods.split(",") if m.strip()),
        democap_every=args.democap_every,
        democap_span=args.democap_span,
        height_m=args.height,
        eventcap_start_s=args.eventcap_start,
        eventcap_end_s=args.eventcap_end,
        eventcap_batches=args.eventcap_batches,
        segment_batches=args.segment_batches,
        overlap=args.overlap,
        template=not args.no_template,
    )
    sessions = find_sessions(args.sessions, calib=args.calib)
    status = StatusLine()

    def progress(session: str, method: str, message: str) -> None:
        final = message.startswith(("done", "failed", "finished"))
        status.show(f"{session} {method}: {message}", final=final)

    with open_engine(args.cluster, workers=args.workers) as engine:
        print(f"engine: {engine.describe()}", file=sys.stderr)
        report = process_sessions(
            sessions, out=args.out, settings=settings, engine=engine, progress=progress
        )
    status.done()
    out: dict[str, Any] = report.to_json()
    if args.json:
        emit_json(out)
        return 0 if report.ok else 1
    print(f"{'session':<20} {'method':<9} {'status':<8} {'seconds':>8}  outputs / error")
    for j in out["jobs"]:
        what = (
            f"{j['stage']}: {j['error']}"
            if j["status"] == "failed"
            else f"{len(j['outputs'])} files in {_folder(j['outputs'])}"
        )
        print(f"{j['session']:<20} {j['method']:<9} {j['status']:<8} {j['seconds']:>8.1f}  {what}")
    print(
        f"{out['done']} done, {out['skipped']} kept from earlier, {out['failed']} failed "
        f"({out['engine']}, {out['seconds']:.1f} s)"
    )
    return 0 if report.ok else 1


def _folder(outputs: list[str]) -> str:
    from pathlib import Path

    return str(Path(outputs[0]).parent) if outputs else "-"
