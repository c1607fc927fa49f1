"""Baselines on one held-out test set: what DeMoCap's staged markers-to-pose design buys here.

Trains each network variant (``DemocapConfig.variant``: ``markers-to-pose``, the paper's
``pose`` and ``markers+pose`` of Table 2, and a direct-regression network) from scratch with
the same seed, the same simulated training data (the batches depend only on the seed, the
epoch and the step, so every variant sees the same samples in the same order) and the same
budget (epochs × samples per epoch), then evaluates each on the same held-out test set
(:func:`mocaprig.process.democap.evaluate`: ``--subjects`` rounds of the six actions on new bodies,
``--frames`` frames per take, ``--cameras`` D415s, fixed ``--test-seed``).

Per variant: MPJPE (17 joints), MPMPE (53 markers; None for ``pose``, which predicts no
markers), PCK3D@50 mm, MPJAE (None for ``pose``: the segment frames need markers), the
parameter count, the training time (wall and CPU, including the per-epoch validation) and
the inference time per frame (one cloud at a time, median wall and CPU time, normalisation
and rendering included; on a shared machine the CPU times are the comparable ones). The
default budget is small enough for one CPU thread in about 10 minutes; at such a budget the
ranking says little about converged models (docs/democap.md, "Baselines").

A reference row needs no training: a constant prediction (the mean normalised skeleton and
markers of training samples, un-normalised with each test cloud's own box), i.e. what the
normalisation alone gives. ``--variants ''`` computes only that row.

Prints a table, then one JSON object as its last line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from mocaprig.process.democap.checkpoint import Checkpoint
from mocaprig.process.democap.config import VARIANTS, DemocapConfig, Variant, config_by_name
from mocaprig.process.democap.dataset import make_pool, make_sample, prepare_cloud
from mocaprig.process.democap.evaluate import evaluate, held_out_pool
from mocaprig.process.democap.geometry import to_world_frame
from mocaprig.process.democap.infer import DemocapPredictor, Prediction
from mocaprig.process.democap.model import build_network
from mocaprig.process.democap.simdata import Box, Camera
from mocaprig.process.democap.train import TrainOptions, train


class _MeanPose(DemocapPredictor):
    """No network: every cloud gets one constant normalised skeleton and marker set (the mean
    over training samples), un-normalised with that cloud's own box. What a model gets from
    the normalisation alone, without learning anything about the pose or the heading."""

    def __init__(self, cfg: DemocapConfig, markers_n: np.ndarray, joints_n: np.ndarray) -> None:
        super().__init__(Checkpoint(config=cfg, model=build_network(cfg)), rotations=1)
        self._markers_n, self._joints_n = markers_n, joints_n

    def predict_many(
        self,
        clouds: Sequence[npt.ArrayLike],
        *,
        views: Sequence[Sequence[Camera]] | None = None,  # no solve: nothing to tell it
        crop_box_m: Box | None = None,
    ) -> list[Prediction]:
        out = []
        for c in clouds:
            _, _, norm, centre = prepare_cloud(np.asarray(c, np.float64), size_px=self.size_px)
            out.append(
                Prediction(
                    markers_m=to_world_frame(norm.invert(self._markers_n) + centre),
                    joints_m=to_world_frame(norm.invert(self._joints_n) + centre),
                )
            )
        return out


def _mean_pose_reference(args: argparse.Namespace, pool: list[Any]) -> dict[str, Any]:
    """The constant-prediction reference on the same test set (training-sample means)."""
    cfg = config_by_name(args.config)
    train_pool = make_pool(args.seed, "train", takes=args.takes)
    rng = np.random.default_rng([args.seed, 1000])
    ms, js = [], []
    for _ in range(min(args.epochs * args.samples_per_epoch, 1024)):
        take = train_pool[int(rng.integers(len(train_pool)))]
        s = make_sample(take, int(rng.integers(take.num_frames)), rng, size_px=cfg.input_px)
        ms.append(s.markers_n)
        js.append(s.joints_n)
    pred = _MeanPose(cfg, np.mean(ms, axis=0), np.mean(js, axis=0))
    rep = evaluate(
        pred, seed=args.test_seed, num_cameras=args.cameras, frames_per_take=args.frames, pool=pool
    )
    return {**_figures(rep.metrics), "test_frames": rep.metrics.frames}


def _figures(m: Any) -> dict[str, Any]:
    """The accuracy figures of a report's metrics (``mocaprig.process.metrics.PoseMetrics``)."""
    return {
        "mpjpe_mm": m.mpjpe_mm,
        "mpmpe_mm": m.mpmpe_mm,
        "pck50": m.pck50,
        "pck_auc": m.pck_auc,
        "mpjae_deg": m.mpjae_deg,
    }


def _infer_ms(pred: DemocapPredictor, clouds: list[np.ndarray]) -> tuple[float, float]:
    """Median wall and CPU ms of one ``predict`` (one cloud at a time)."""
    for c in clouds[:3]:  # warm-up
        pred.predict(c)
    wall, cpu = [], []
    for c in clouds:
        t0, c0 = time.perf_counter(), time.process_time()
        pred.predict(c)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return 1e3 * float(np.median(wall)), 1e3 * float(np.median(cpu))


def _run_variant(
    variant: Variant, args: argparse.Namespace, out_dir: Path, pool: list[Any], clouds: list[Any]
) -> dict[str, Any]:
    cfg = dataclasses.replace(config_by_name(args.config), variant=variant)
    opts = TrainOptions(
        epochs=args.epochs,
        seed=args.seed,
        takes=args.takes,
        samples_per_epoch=args.samples_per_epoch,
        batch_size=args.batch_size,
        threads=args.threads,
    )
    path = out_dir / f"{variant.replace('+', '_and_')}.pt"
    t0, c0 = time.monotonic(), time.process_time()
    ck = train(path, opts, config=cfg, overwrite=True)
    train_s, train_cpu_s = time.monotonic() - t0, time.process_time() - c0
    pred = DemocapPredictor(ck, rotations=1, solve=False)  # single shot, as the paper compares
    rep = evaluate(
        pred,
        seed=args.test_seed,
        num_cameras=args.cameras,
        frames_per_take=args.frames,
        pool=pool,
    )
    m = rep.metrics
    infer_ms, infer_cpu_ms = _infer_ms(pred, clouds)
    return {
        **_figures(m),
        "parameters": sum(p.numel() for p in ck.model.parameters()),
        "train_seconds": train_s,
        "train_cpu_seconds": train_cpu_s,
        "infer_ms_per_frame": infer_ms,
        "infer_cpu_ms_per_frame": infer_cpu_ms,
        "val_mpjpe_mm": [h["val_mpjpe_mm"] for h in ck.history],
        "final_loss": ck.history[-1]["loss"],
        "test_frames": m.frames,
    }


def _cell(v: float | None, fmt: str) -> str:
    return "n/a" if v is None else format(v, fmt)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", choices=("lite", "paper"), default="lite", help="network size")
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated variants")
    ap.add_argument("--epochs", type=int, default=4, help="training epochs per variant")
    ap.add_argument("--samples-per-epoch", type=int, default=512, help="samples per epoch")
    ap.add_argument("--batch-size", type=int, default=None, help="default: the config's (16)")
    ap.add_argument("--takes", type=int, default=96, help="training takes")
    ap.add_argument("--seed", type=int, default=0, help="training seed (same for all)")
    ap.add_argument("--test-seed", type=int, default=0, help="held-out test set seed")
    ap.add_argument("--subjects", type=int, default=2, help="test subjects (rounds of 6 takes)")
    ap.add_argument("--frames", type=int, default=20, help="test frames per take")
    ap.add_argument("--cameras", type=int, choices=(2, 3, 4), default=4, help="D415s")
    ap.add_argument("--infer-frames", type=int, default=30, help="frames timed one by one")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--out-dir", type=Path, default=None, help="keep the checkpoints here")
    args = ap.parse_args()
    variants: list[Variant] = []
    for name in filter(None, args.variants.split(",")):
        if name not in VARIANTS:
            ap.error(f"unknown variant {name!r}; choose from {', '.join(VARIANTS)}")
        variants.append(VARIANTS[VARIANTS.index(name)])
    torch.set_num_threads(args.threads)

    pool = held_out_pool(args.test_seed, subjects=args.subjects)
    rng = np.random.default_rng([args.test_seed, 31])
    size = config_by_name(args.config).input_px
    clouds = []
    for i in range(args.infer_frames):
        take = pool[i % len(pool)]
        s = make_sample(take, int(rng.integers(take.num_frames)), rng, augment=False, size_px=size)
        clouds.append(s.raw_m)

    results: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="democap_baselines_") as tmp:
        out_dir = args.out_dir if args.out_dir is not None else Path(tmp)
        out_dir.mkdir(parents=True, exist_ok=True)
        for v in variants:
            print(f"training and evaluating {v} ...", file=sys.stderr, flush=True)
            results[v] = _run_variant(v, args, out_dir, pool, clouds)
            r = results[v]
            print(
                f"  {v}: MPJPE {r['mpjpe_mm']:.1f} mm, {r['train_cpu_seconds']:.0f} s CPU",
                file=sys.stderr,
                flush=True,
            )

    reference = _mean_pose_reference(args, pool)
    samples = args.epochs * args.samples_per_epoch
    print(
        f"{args.config}, {args.epochs} epochs x {args.samples_per_epoch} samples = {samples} "
        f"training samples per variant, seed {args.seed}; held-out test set seed "
        f"{args.test_seed}, {args.cameras} cameras, {reference['test_frames']} frames"
    )
    head = (
        "| variant | parameters | MPJPE mm | MPMPE mm | PCK3D@50 | MPJAE deg "
        "| train s (CPU s) | infer ms/frame (CPU ms) |"
    )
    print(head)
    print("|---|---|---|---|---|---|---|---|")
    for name, r in results.items():
        print(
            f"| {name} | {r['parameters'] / 1e6:.3f} M | {r['mpjpe_mm']:.1f} "
            f"| {_cell(r['mpmpe_mm'], '.1f')} | {100 * r['pck50']:.1f} % "
            f"| {_cell(r['mpjae_deg'], '.1f')} "
            f"| {r['train_seconds']:.0f} ({r['train_cpu_seconds']:.0f}) "
            f"| {r['infer_ms_per_frame']:.1f} ({r['infer_cpu_ms_per_frame']:.1f}) |"
        )
    print(
        f"| mean pose (no network) | 0 | {reference['mpjpe_mm']:.1f} "
        f"| {reference['mpmpe_mm']:.1f} | {100 * reference['pck50']:.1f} % "
        f"| {reference['mpjae_deg']:.1f} | | |"
    )
    for name, r in results.items():
        vals = ", ".join(f"{x:.0f}" for x in r["val_mpjpe_mm"])
        print(f"{name}: held-out MPJPE after each epoch (validation, mm): {vals}")
    summary = {
        "benchmark": "democap_baselines",
        "machine": platform.machine(),
        "config": args.config,
        "epochs": args.epochs,
        "samples_per_epoch": args.samples_per_epoch,
        "batch_size": args.batch_size or config_by_name(args.config).batch_size,
        "takes": args.takes,
        "seed": args.seed,
        "test_seed": args.test_seed,
        "cameras": args.cameras,
        "threads": args.threads,
        "variants": results,
        "mean_pose_reference": reference,
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
