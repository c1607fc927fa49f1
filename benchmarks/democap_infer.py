"""Benchmark DeMoCap inference end to end, per stage, for the ``lite`` and ``paper`` configs.

One frame at a time (the live case, batch 1): the 4 D415 views' lifted marker detections ->
10 mm multi-view merge -> normalisation + front/back rendering -> network (both views in one
batch) -> CoM3D + dual-view fusion -> inverse normalisation to world joints and markers.
Per-view IR blob extraction and depth deprojection (the calibration issue's marker
measurement) is not part of this pipeline yet and is not timed.

The inputs are simulated held-out frames (:mod:`process.democap.simdata`). ``lite`` uses the
committed checkpoint when present (speed does not depend on the weights); ``paper`` uses
random weights. torch runs on ``--threads`` CPU threads (default 1: on a 2-core machine the
second core stays free for acquisition; 2 threads on a busy machine oversubscribe it).
Each stage figure is the median over frames.
Prints one JSON object as its last line (``fps`` = lite end-to-end frames per second).
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np
import torch

from process.democap.checkpoint import DEFAULT_CHECKPOINT, load_checkpoint
from process.democap.config import CONFIGS
from process.democap.dataset import make_pool, prepare_cloud
from process.democap.geometry import to_world_frame
from process.democap.model import (
    DemocapModel,
    DemocapNet,
    DemocapOutput,
    fuse_views_torch,
    view_keypoints,
)
from process.democap.simdata import merge_views, observe, sample_rig


def _views(frames: int, seed: int) -> list[list[np.ndarray]]:
    pool = make_pool(seed, "test", takes=6, seconds=2.0)
    rng = np.random.default_rng(seed)
    out = []
    for i in range(frames):
        take = pool[i % len(pool)]
        cams = sample_rig(rng)
        views, _ = observe(take, int(rng.integers(take.num_frames)), cams, rng)
        out.append(views)
    return out


def _run(net: DemocapModel, size: int, views: list[list[np.ndarray]]) -> dict[str, float]:
    stages: dict[str, list[float]] = {
        k: [] for k in ("merge", "render", "network", "decode", "inverse")
    }
    totals = []
    with torch.inference_mode():
        for v in views:
            t0 = time.perf_counter()
            cloud = merge_views(v)
            t1 = time.perf_counter()
            f, b, norm, centre = prepare_cloud(cloud, size_px=size)
            x = torch.from_numpy(np.stack([f, b]))[:, None]
            t2 = time.perf_counter()
            out: DemocapOutput = net(x)
            t3 = time.perf_counter()
            m, j = view_keypoints(out)
            jt = fuse_views_torch(j[:1], j[1:])[0].double().numpy()
            mk = jt if m is None else fuse_views_torch(m[:1], m[1:])[0].double().numpy()
            t4 = time.perf_counter()
            to_world_frame(norm.invert(mk) + centre)
            to_world_frame(norm.invert(jt) + centre)
            t5 = time.perf_counter()
            for k, a, c in (
                ("merge", t0, t1),
                ("render", t1, t2),
                ("network", t2, t3),
                ("decode", t3, t4),
                ("inverse", t4, t5),
            ):
                stages[k].append(c - a)
            totals.append(t5 - t0)
    res = {f"{k}_ms": 1e3 * float(np.median(v)) for k, v in stages.items()}
    res["total_ms"] = 1e3 * float(np.median(totals))
    res["fps"] = 1e3 / res["total_ms"]
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60, help="frames timed per config")
    ap.add_argument("--paper-frames", type=int, default=6, help="frames timed for paper")
    ap.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch CPU threads (1 leaves the second core to acquisition)",
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    views = _views(args.frames + 5, seed=21)
    torch.manual_seed(0)
    lite = (
        load_checkpoint(DEFAULT_CHECKPOINT).model
        if DEFAULT_CHECKPOINT.is_file()
        else DemocapNet(CONFIGS["lite"])
    ).eval()
    _run(lite, 160, views[:5])  # warm-up
    res_lite = _run(lite, 160, views[5:])
    paper = DemocapNet(CONFIGS["paper"]).eval()
    _run(paper, 160, views[:1])
    res_paper = _run(paper, 160, views[5 : 5 + args.paper_frames])
    lite_params = sum(p.numel() for p in lite.parameters())
    paper_params = sum(p.numel() for p in paper.parameters())
    print(
        f"lite : {res_lite['fps']:.1f} fps, stages (ms): "
        + ", ".join(f"{k} {v:.2f}" for k, v in res_lite.items() if k.endswith("_ms"))
    )
    print(f"paper: {res_paper['fps']:.2f} fps, network {res_paper['network_ms']:.0f} ms")
    result = {
        "benchmark": "democap_infer",
        "machine": platform.machine(),
        "threads": args.threads,
        "frames": args.frames,
        "fps": res_lite["fps"],
        "lite": res_lite,
        "paper": res_paper,
        "lite_params": lite_params,
        "paper_params": paper_params,
        "paper_over_lite_time": res_paper["total_ms"] / res_lite["total_ms"],
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
