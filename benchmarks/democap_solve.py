"""Benchmark the DeMoCap skeleton solve against the network it follows, on the same clouds.

Held-out simulated clouds (the ``in-distribution`` test stream, seed ``--seed``, 4 cameras)
go through the committed ``lite`` network (the 3-turn ensemble, as shipped) and then through
:func:`mocaprig.process.democap.solve.solve_skeleton` with 1 start (the ensemble's estimate),
the default starts (the ensemble's and each turn's, and each of them bent at the hips: 8) with
and without the limb search after them, and configurations in between; then the predictor's
whole solve stage (:class:`DemocapPredictor`: six turns for a sparse cloud) without and with
the pose bank's second solve (:mod:`mocaprig.process.democap.pose_bank`; the bank placed at
the estimated height only, and at the three heights of the default), and with the
re-solve from its own solution after it (``DemocapPredictor.resolve_rounds``), without and
with the pose prior (:mod:`mocaprig.process.democap.pose_prior`; the default), its
time read from ``last_timings_s["solve_s"]`` (the network's passes left out); each is timed in
rounds that interleave them (a shared machine: a load change hits all alike), as seconds
per frame and as a ratio to the network's time in the same round, with its MPJPE against
the truth (17 joints; a sanity figure, the evaluations are ``mocaprig democap eval``).

Run (≈ 1 min on the 2-core machine)::

    .venv/bin/python benchmarks/democap_solve.py --frames 48 --rounds 3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time

import numpy as np
import torch

from mocaprig.process.democap.dataset import simulate_sample
from mocaprig.process.democap.evaluate import EVAL_JOINTS, held_out_pool
from mocaprig.process.democap.infer import DemocapPredictor
from mocaprig.process.democap.pose_bank import BankSearch
from mocaprig.process.democap.solve import SolveOptions, solve_skeleton


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=48, help="clouds (spread over 6 takes)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    load_start = os.getloadavg()
    pool = held_out_pool(args.seed)
    rng = np.random.default_rng([args.seed, 7, 4])
    per_take = max(1, args.frames // len(pool))
    clouds, truth = [], []
    for take in pool:
        for i in np.linspace(0, take.num_frames - 1, per_take).round().astype(int):
            s = simulate_sample(take, int(i), rng, augment=False)
            if s is not None:
                clouds.append(s.raw_m)
                truth.append(s.joints_m)
    true_j = np.array(truth)
    net = DemocapPredictor(solve=False)
    k = net.rotations

    def hypotheses() -> tuple[np.ndarray, np.ndarray, float]:
        """The ensemble's estimate, then each turn's, and the network's wall time."""
        t0 = time.perf_counter()
        markers, joints, mk, jt = net.hypotheses(clouds)
        wall = time.perf_counter() - t0
        return np.concatenate([markers[None], mk]), np.concatenate([joints[None], jt]), wall

    hm, hj, _ = hypotheses()
    bare = SolveOptions(limb_search=False)
    configs = {
        "1 start, no bent one, no limb search": (
            1,
            SolveOptions(bend_starts_rad=(), limb_search=False),
        ),
        "1 start + bent, no limb search": (1, bare),
        f"{k + 1} starts, no bent one, no limb search": (
            k + 1,
            SolveOptions(bend_starts_rad=(), limb_search=False),
        ),
        f"{k + 1} starts + bent, no limb search": (k + 1, bare),
        f"{k + 1} starts + bent + limb search, best node only": (
            k + 1,
            SolveOptions(limb_keep=(1,)),
        ),
        f"{k + 1} starts + bent + limb search (default)": (k + 1, SolveOptions()),
    }
    predictors = {
        "predictor solve stage, no pose bank": DemocapPredictor(pose_bank=False),
        "predictor solve stage + pose bank, no re-solve": DemocapPredictor(resolve_rounds=0),
        "predictor solve stage + pose bank at the estimated height only + re-solve": (
            DemocapPredictor(bank_search=BankSearch(height_scales=(1.0,)))
        ),
        "predictor solve stage + pose bank + re-solve, no pose prior": DemocapPredictor(
            pose_prior=False
        ),
        "predictor solve stage + pose bank + re-solve + pose prior (default)": DemocapPredictor(),
    }
    rows: dict[str, list[float]] = {c: [] for c in [*configs, *predictors]}
    net_s: list[float] = []
    err: dict[str, float] = {}
    keep = list(EVAL_JOINTS)

    def mpjpe(j: np.ndarray) -> float:
        return float(np.linalg.norm(j[:, keep] - true_j[:, keep], axis=-1).mean() * 1000.0)

    for _ in range(args.rounds):
        _, _, wall = hypotheses()
        net_s.append(wall / len(clouds))
        for name, (n, opt) in configs.items():
            t0 = time.perf_counter()
            res = solve_skeleton(clouds, hm[:n], hj[:n], options=opt)
            rows[name].append((time.perf_counter() - t0) / len(clouds))
            err[name] = mpjpe(res.joints_m)
        for name, pred in predictors.items():
            out = pred.predict_many(clouds)
            rows[name].append(pred.last_timings_s["solve_s"] / len(clouds))
            err[name] = mpjpe(np.array([p.joints_m for p in out]))
    err["network (ensemble)"] = mpjpe(hj[0])
    load_end = os.getloadavg()
    net_med = float(np.median(net_s))
    print(
        f"{len(clouds)} clouds; network (all {k} turns + ensemble) {1000 * net_med:.1f} ms a frame"
    )
    out_rows = {}
    for name, t in rows.items():
        med = float(np.median(t))
        out_rows[name] = {
            "ms_per_frame": round(1000 * med, 1),
            "ratio_to_network": round(med / net_med, 2),
            "mpjpe_mm": round(err[name], 1),
        }
        print(
            f"  {name:55s} {1000 * med:7.1f} ms a frame ({med / net_med:4.2f}x the network), "
            f"MPJPE {err[name]:.1f} mm"
        )
    print(f"  network alone: MPJPE {err['network (ensemble)']:.1f} mm")
    print(f"load average {load_start[0]:.2f} at the start, {load_end[0]:.2f} at the end")
    print(
        json.dumps(
            {
                "benchmark": "democap_solve",
                "machine": platform.machine(),
                "cpu_count": os.cpu_count(),
                "threads": args.threads,
                "load_avg_start_end": [round(load_start[0], 2), round(load_end[0], 2)],
                "frames": len(clouds),
                "rounds": args.rounds,
                "network_ms_per_frame": round(1000 * net_med, 1),
                "network_mpjpe_mm": round(err["network (ensemble)"], 1),
                "solve": out_rows,
                "options": dataclasses.asdict(SolveOptions()),
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
