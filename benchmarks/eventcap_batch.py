"""Benchmark EventCap per 40 ms batch (issue 15, speed): wall time by stage, end to end.

A simulated take (the realistic DAVIS simulator, :class:`DavisSimulator`, default settings)
is rendered for ``--batches`` + 1 APS frames from ``--start-s`` into the clip; the synthetic
detector (default noise) gives the detections. The batches run chained as ``run_take`` runs
them (each starts from the previous one's last pose) with the default
:class:`~mocaprig.process.eventcap.pipeline.EventcapOptions`. Per batch it reports the stage
times :func:`run_batch` measures (``edi``, ``init``, ``tracking``, ``batch_fit``,
``association``, ``refine``), the end-to-end wall time and, as a sanity check, the mean
keypoint error against the truth (15 body joints, mm, no alignment).

Prints one line per batch and one JSON object as its last line. Run::

    .venv/bin/python benchmarks/eventcap_batch.py --batches 5
    .venv/bin/python benchmarks/eventcap_batch.py \\
        --motion ../shared/data/motion/corpus/cmu_02_05.bvh
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from mocaprig.calib.camera_model import project_points
from mocaprig.drivers_mock.davis240c_sim import DavisSimulator
from mocaprig.drivers_mock.scenario import build_scenario
from mocaprig.process.body.kinematics import eventcap_keypoints, forward_kinematics
from mocaprig.process.eventcap.camera import EventCamera
from mocaprig.process.eventcap.detections import SyntheticDetections
from mocaprig.process.eventcap.pipeline import ApsFrame, run_batch

_FRAME_US = 40_000  # the simulator's default APS interval


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, default=5)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--scenario", default="karate")
    ap.add_argument("--motion", default=None, help="a BVH clip (default: procedural motion)")
    ap.add_argument("--start-s", type=float, default=1.6, help="clip time of the first frame")
    args = ap.parse_args()

    seconds = max(3.0, args.start_s + (args.batches + 2) * _FRAME_US * 1e-6 + 0.5)
    world = build_scenario(args.scenario, seed=args.seed, seconds=seconds, motion_path=args.motion)
    sim = DavisSimulator(world, reset_session_ns=int(args.start_s * 1e9))
    t_sim = time.perf_counter()
    act = sim.activity(0, (args.batches + 1) * _FRAME_US + 30_000)
    sim_s = time.perf_counter() - t_sim
    exposures = act.exposures[: args.batches + 1]
    frames = [ApsFrame(e.start_us, e.end_us, e.cds) for e in exposures]
    cam = world.rig.davis.camera
    camera = EventCamera(
        K=cam.K, distortion=cam.distortion, T_world_cam=cam.T_world_cam, width=240, height=180
    )

    def truth(t_us: np.ndarray) -> np.ndarray:
        pose = world.pose(np.asarray(sim.session_ns(t_us), dtype=np.int64))
        kp: np.ndarray = eventcap_keypoints(forward_kinematics(pose, world.shape), world.shape)
        return kp

    times = np.array([f.t_us for f in frames], dtype=np.int64)
    kp = truth(times)
    uv, _ = project_points(kp.reshape(-1, 3), cam.T_world_cam, cam.K, cam.distortion)
    detector = SyntheticDetections.from_world(
        times, uv.reshape(-1, 19, 2), kp, cam.T_world_cam, seed=args.seed
    )
    t_ev = act.events["t"]
    stages: dict[str, list[float]] = {}
    totals: list[float] = []
    errors: list[float] = []
    prev = None
    for k in range(len(frames) - 1):
        a, b = frames[k], frames[k + 1]
        events = act.events[(t_ev >= a.exposure_start_us) & (t_ev <= b.exposure_end_us)]
        t0 = time.perf_counter()
        res = run_batch(
            events,
            a,
            b,
            detector.detect(a.t_us),
            detector.detect(b.t_us),
            camera,
            world.shape,
            start_pose=prev,
        )
        totals.append(time.perf_counter() - t0)
        prev = res.poses[-1]
        for name, s in res.stage_seconds.items():
            stages.setdefault(name, []).append(s)
        err = 1000 * np.linalg.norm(res.keypoints_m[:, :15] - truth(res.t_us)[:, :15], axis=-1)
        errors.append(float(err.mean()))
        print(
            f"batch {k}: {totals[-1]:.2f} s, {events.size} events, {res.trajectories} "
            f"trajectories, {res.correspondences} correspondences, error {errors[-1]:.1f} mm, "
            + ", ".join(f"{n} {s:.2f}" for n, s in res.stage_seconds.items()),
            flush=True,
        )
    out = {
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "scenario": args.scenario if args.motion is None else Path(args.motion).name,
        "seed": args.seed,
        "batches": len(totals),
        "simulate_s": round(sim_s, 2),
        "batch_mean_s": round(float(np.mean(totals)), 3),
        "batch_max_s": round(float(np.max(totals)), 3),
        "stage_mean_s": {n: round(float(np.mean(v)), 3) for n, v in stages.items()},
        "stage_max_s": {n: round(float(np.max(v)), 3) for n, v in stages.items()},
        "mean_keypoint_error_mm": round(float(np.mean(errors)), 1),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
