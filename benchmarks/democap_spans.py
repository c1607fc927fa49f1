"""DeMoCap spans on 1, 2, … Dask workers: throughput, efficiency, per-task start-up, and that the
joined spans give the unsplit replay (issue 19).

On one simulated session (``simulate_session``: ``--seconds`` s, ``--cameras`` D415s, seed
``--seed``), calibrated against its own Vicon trial (``calibrate_vicon``):

1. **plan**: the rig instants (``plan_replay``, every ``--every``-th), cut into spans of
   ``--span`` instants;
2. **unsplit**: one span over every instant in this process (one torch thread), the reference;
3. **spans** as tasks of a Dask ``LocalCluster`` of W single-threaded worker processes for each W
   of ``--workers``: wall time from the first submission to the last result (cluster start-up
   excluded), instants per second, efficiency ``T_1 / (W · T_W)``, each task's start-up (network
   load and the recording opened, before its first instant) and the joined joints' largest
   difference from the unsplit replay (must be 0: every instant stands alone).

Prints one line per measurement and one JSON object as its last line::

    nice -n 10 .venv/bin/python benchmarks/democap_spans.py --seconds 8 --span 60 --workers 1 2
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np


def _span_task(
    plan: Any, calibration: str, threads: int = 1
) -> tuple[Any, float, float]:  # pragma: no cover - runs on the workers
    """One span as ``mocaprig process`` runs it; returns it with its start-up and wall (s)."""
    import torch

    from mocaprig.process.democap.infer import DemocapPredictor
    from mocaprig.process.democap.replay import replay_span

    torch.set_num_threads(threads)
    t0 = time.perf_counter()
    predictor = DemocapPredictor()
    startup = time.perf_counter() - t0
    span = replay_span(plan, calibration, predictor=predictor)
    return span, startup, time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=8.0, help="simulated session length (s)")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--cameras", type=int, default=4, help="D415s of the simulated rig")
    ap.add_argument("--every", type=int, default=1, help="every n-th instant")
    ap.add_argument("--span", type=int, default=60, help="instants per span task")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args()

    import torch

    from mocaprig.calib.calibration import write_calibration
    from mocaprig.calib.vicon_calibration import calibrate_vicon
    from mocaprig.drivers_mock import simulate_session
    from mocaprig.process.batch.engines import DaskEngine
    from mocaprig.process.democap.replay import join_spans, output_paths, plan_replay

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory(prefix="democap-spans-") as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        sim = simulate_session(
            root / "sim",
            seed=args.seed,
            seconds=args.seconds,
            devices=("d415",),
            cameras=args.cameras,
        )
        session = sim.out_dir / "session.mcap"
        cal = calibrate_vicon(session, sim.c3d_path).calibration
        calib = str(write_calibration(cal, root / "calib.toml"))
        print(f"simulated and calibrated in {time.perf_counter() - t0:.1f} s", flush=True)

        plan = plan_replay(session, calib, every=args.every)
        spans = plan.spans(args.span)
        n = len(plan.instants)
        print(f"{n} instants, {len(spans)} spans of <= {args.span}", flush=True)
        whole, whole_startup, whole_wall = _span_task(plan, calib)
        print(
            f"unsplit in-process: {whole_wall:.1f} s ({n / whole_wall:.2f} instants/s, "
            f"start-up {whole_startup:.2f} s)",
            flush=True,
        )

        runs: list[dict[str, Any]] = []
        for w in args.workers:
            with DaskEngine.local(w) as engine:
                engine.wait([engine.submit(int, 0)])  # workers up
                t1 = time.perf_counter()
                futures = [engine.submit(_span_task, plan.span(a, b), calib) for a, b in spans]
                pending = set(futures)
                while pending:
                    pending -= engine.wait(pending)
                wall = time.perf_counter() - t1
                done = [f.result() for f in futures]
            joined = join_spans(plan, [d[0] for d in done], outputs=output_paths(root / "x.mcap"))
            diff_mm = float(np.max(np.abs(joined.joints_m - whole.joints_m), initial=0.0)) * 1e3
            same_t = bool(np.array_equal(joined.t_ref_ns, whole.t_ref_ns))
            row = {
                "workers": w,
                "wall_s": round(wall, 2),
                "instants_per_s": round(n / wall, 3),
                "startup_s": [round(d[1], 3) for d in done],
                "task_s": [round(d[2], 3) for d in done],
                "max_joint_diff_mm": diff_mm,
                "same_instants": same_t,
            }
            runs.append(row)
            print(
                f"{w} worker(s): {wall:.1f} s, {n / wall:.2f} instants/s, start-up per task "
                f"{min(row['startup_s'])}-{max(row['startup_s'])} s, joints vs unsplit "
                f"max {diff_mm:.3g} mm, same instants {same_t}",
                flush=True,
            )
        base = next((r for r in runs if r["workers"] == 1), None)
        for r in runs:
            r["efficiency"] = (
                None if base is None else round(base["wall_s"] / (r["workers"] * r["wall_s"]), 3)
            )
            if r["efficiency"] is not None:
                print(f"efficiency at {r['workers']} worker(s): {r['efficiency']}", flush=True)
    out = {
        "benchmark": "democap_spans",
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "python": platform.python_version(),
        "seconds": args.seconds,
        "cameras": args.cameras,
        "instants": n,
        "span": args.span,
        "spans": len(spans),
        "unsplit_s": round(whole_wall, 2),
        "runs": runs,
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
