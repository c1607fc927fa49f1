"""EventCap segments on 1, 2, … workers: throughput, efficiency, per-task overhead, and what
the stitching costs against the unsplit take (issue 19).

On one simulated take (``mocaprig simulate --devices davis --davis-dvs``, karate; or
``--session DIR``, a folder with ``session.mcap`` and the EventCap side files of
``mocaprig process``), ``--batches`` batches from ``--start`` s of the DAVIS timeline:

1. **unsplit**: the batches as one segment (the take as ``eventcap run`` chains it);
2. **segments** of ``--segment-batches`` kept batches, each from ``--overlap`` warm-up batches
   earlier, as tasks of a Dask ``LocalCluster`` of W single-threaded worker processes for each
   W of ``--workers``; wall time from the first submission to the last result (cluster
   start-up excluded), batches run per second, efficiency ``T_1 / (W · T_W)``; the stitched
   outputs of every W must be identical;
3. **overhead per task**: the round trip of an empty task on each engine (20 in a row), and in
   a segment task the time not spent in its batches (calibration, recording index, detections);
4. **stitching cost**: the 15 body joints' error against the simulator's truth (mean, mm) of the
   unsplit and the stitched take, their difference per instant (mean and max, mm), and the
   error over the first batch after each boundary.

Prints one line per measurement and one JSON object as its last line. Run with ``nice`` on a
shared machine::

    nice -n 10 .venv/bin/python benchmarks/process_scaling.py --batches 8 --segment-batches 2
    nice -n 10 .venv/bin/python benchmarks/process_scaling.py --session sim --workers 1 2 4 8
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from mocaprig.drivers_mock.eventcap_session import read_session_truth, write_session_inputs
from mocaprig.process.batch.engines import DaskEngine, Engine, InProcessEngine, ProcessPoolEngine
from mocaprig.process.batch.segments import (
    EventcapInputs,
    SegmentResult,
    StitchedTake,
    plan_segments,
    run_segment,
    stitch_segments,
)

_BODY = 15  # the body joints the EventCap figures use


def _simulate(out: Path, seconds: float, seed: int) -> None:
    cmd = [sys.executable, "-m", "mocaprig.cli", "-q", "simulate", "--scenario", "karate"]
    cmd += ["--seed", str(seed), "--seconds", f"{seconds:g}", "--devices", "davis"]
    cmd += ["--davis-dvs", "--out", str(out), "--json"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    write_session_inputs(
        out,
        detections_path=out / "eventcap_detections.json",
        calibration_path=out / "eventcap_calib.toml",
        seed=seed,
    )
    shutil.copy(out / "truth" / "scenario.json", out / "eventcap_shape.json")


def _noop(x: int) -> int:
    return x


def _round_trip_ms(engine: Engine, n: int = 20) -> float:
    engine.wait([engine.submit(_noop, -1)])  # the workers' first task imports and warms up
    t0 = time.perf_counter()
    for i in range(n):
        engine.wait([engine.submit(_noop, i)])
    return (time.perf_counter() - t0) / n * 1e3


def _run_segments(
    engine: Engine, inputs: EventcapInputs, batches: int, seg_batches: int, overlap: int
) -> tuple[StitchedTake, list[SegmentResult], float]:
    plan = plan_segments(batches, segment_batches=seg_batches, overlap=overlap)
    t0 = time.perf_counter()
    futures = [engine.submit(run_segment, inputs, s) for s in plan]
    results = []
    pending = set(futures)
    while pending:
        done = engine.wait(pending)
        pending -= done
        results += [f.result() for f in done]
    wall = time.perf_counter() - t0
    return stitch_segments(results, batches=batches), results, wall


def _error_mm(truth: Any, take: StitchedTake) -> np.ndarray:
    want = truth.keypoints_at(take.t_us)
    return np.asarray(
        1e3 * np.linalg.norm(take.keypoints_m[:, :_BODY] - want[:, :_BODY], axis=-1).mean(axis=1)
    )


def _mean(x: np.ndarray) -> float:
    return round(float(x.mean()), 2)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", type=Path, default=None, help="a session folder (else simulate)")
    ap.add_argument("--seconds", type=float, default=3.0, help="simulated take length (s)")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--start", type=float, default=1.0, help="DAVIS timeline start (s)")
    ap.add_argument("--batches", type=int, default=8)
    ap.add_argument("--segment-batches", type=int, default=2)
    ap.add_argument("--overlap", type=int, default=1)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="process-scaling-"))
    session = args.session
    t_sim = 0.0
    if session is None:
        session = tmp / "take"
        t0 = time.perf_counter()
        _simulate(session, args.seconds, args.seed)
        t_sim = time.perf_counter() - t0
        print(f"simulated {args.seconds:g} s take in {t_sim:.0f} s", flush=True)
    inputs = EventcapInputs(
        session=session / "session.mcap",
        calibration=session / "eventcap_calib.toml",
        detections=session / "eventcap_detections.json",
        shape=session / "eventcap_shape.json",
        start_s=args.start,
        batches=args.batches,
    )
    truth = read_session_truth(session)
    out: dict[str, Any] = {
        "benchmark": "process_scaling",
        "host": platform.node(),
        "cpus": os.cpu_count(),
        "load_avg_start": os.getloadavg()[0],
        "session": str(session),
        "batches": args.batches,
        "start_s": args.start,
        "segment_batches": args.segment_batches,
        "overlap": args.overlap,
        "simulate_s": round(t_sim, 1),
    }

    # 1. The unsplit take (one segment, in this process).
    t0 = time.perf_counter()
    whole = stitch_segments([run_segment(inputs, plan_segments(args.batches)[0])])
    t_unsplit = time.perf_counter() - t0
    print(f"unsplit: {args.batches} batches in {t_unsplit:.1f} s", flush=True)

    # 2. Segments on 1, 2, ... Dask workers.
    plan = plan_segments(args.batches, segment_batches=args.segment_batches, overlap=args.overlap)
    run_batches = sum(s.batches_run for s in plan)
    runs: list[dict[str, Any]] = []
    stitched: StitchedTake | None = None
    identical = True
    for w in args.workers:
        with DaskEngine.local(w) as engine:
            rt_ms = _round_trip_ms(engine)
            take, results, wall = _run_segments(
                engine, inputs, args.batches, args.segment_batches, args.overlap
            )
        if stitched is None:
            stitched = take
        else:
            identical &= bool(
                np.array_equal(stitched.poses, take.poses)
                and np.array_equal(stitched.keypoints_m, take.keypoints_m)
            )
        overhead = [r.seconds - r.compute_s for r in results]
        runs.append(
            {
                "workers": w,
                "wall_s": round(wall, 2),
                "batches_per_s": round(run_batches / wall, 4),
                "task_s": [round(r.seconds, 2) for r in results],
                "task_overhead_s_mean": round(float(np.mean(overhead)), 3),
                "empty_task_round_trip_ms": round(rt_ms, 2),
                "load_avg": os.getloadavg()[0],
            }
        )
        print(
            f"{w} worker(s): {len(plan)} segments, {run_batches} batches run in {wall:.1f} s "
            f"({run_batches / wall:.3f} batches/s); task overhead "
            f"{np.mean(overhead):.2f} s; empty task {rt_ms:.1f} ms",
            flush=True,
        )
    t1 = runs[0]["wall_s"] * runs[0]["workers"]
    for r in runs:
        r["efficiency"] = round(t1 / (r["workers"] * r["wall_s"]), 3)
    out["runs"] = runs
    out["segments"] = len(plan)
    out["batches_run"] = run_batches
    out["outputs_identical_across_workers"] = identical

    # 3. Empty-task round trip of the other engines.
    with InProcessEngine() as e:
        out["empty_task_round_trip_ms_in_process"] = round(_round_trip_ms(e), 3)
    with ProcessPoolEngine(2) as e:
        out["empty_task_round_trip_ms_pool"] = round(_round_trip_ms(e), 2)

    # 4. What the stitching costs.
    if stitched is None or not np.array_equal(stitched.t_us, whole.t_us):
        msg = "the stitched and the unsplit take have different instants"
        raise SystemExit(msg)
    err_whole, err_split = _error_mm(truth, whole), _error_mm(truth, stitched)
    diff = 1e3 * np.linalg.norm(
        stitched.keypoints_m[:, :_BODY] - whole.keypoints_m[:, :_BODY], axis=-1
    ).mean(axis=1)
    step = 40  # instants per batch at 1 kHz with 25 Hz APS frames
    after = [s.keep * step for s in plan[1:]]
    out["stitching"] = {
        "unsplit_error_mm": round(float(err_whole.mean()), 2),
        "stitched_error_mm": round(float(err_split.mean()), 2),
        "difference_mm_mean": round(float(diff.mean()), 2),
        "difference_mm_max": round(float(diff.max()), 2),
        "after_boundary_unsplit_mm": [
            round(float(err_whole[i : i + step].mean()), 2) for i in after
        ],
        "after_boundary_stitched_mm": [
            round(float(err_split[i : i + step].mean()), 2) for i in after
        ],
        "first_segment_identical": bool(
            np.array_equal(
                stitched.keypoints_m[: plan[0].end * step], whole.keypoints_m[: plan[0].end * step]
            )
        ),
    }
    st = out["stitching"]
    print(
        f"stitching: error {st['unsplit_error_mm']} mm unsplit, {st['stitched_error_mm']} mm "
        f"stitched; difference mean {st['difference_mm_mean']} mm, max {st['difference_mm_max']}",
        flush=True,
    )
    out["unsplit_s"] = round(t_unsplit, 1)
    out["load_avg_end"] = os.getloadavg()[0]
    shutil.rmtree(tmp, ignore_errors=True)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
