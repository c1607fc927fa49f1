"""``mocaprig democap ...``: train and evaluate the DeMoCap markers-to-pose network.

Registered through the ``mocaprig.commands`` entry point ``democap``. Handlers import torch
and the pipeline lazily so ``mocaprig --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from acquire.cli import ProgressBar, add_json_flag, emit_json

__all__ = ["democap_eval", "democap_train", "register_democap"]

_EPILOG = """\
examples:
  mocaprig democap train --config lite --out lite.pt --epochs 40
  mocaprig democap train --out lite.pt --epochs 80 --resume     continue a run
  mocaprig democap eval --json                                  committed lite checkpoint
  mocaprig democap eval --cameras 2 --seed 3
  mocaprig democap eval --motion walk.bvh --json                a motion never trained on

Not implemented yet: `democap run SESSION.mcap` (replay on recordings) and the baselines.
"""

_TRAIN_EPILOG = """\
Training data is simulated on the fly (marker-level D415 model, see docs/democap.md) and is
deterministic for --seed. A checkpoint is written after every epoch; --resume continues it.

examples:
  mocaprig democap train --config lite --out lite.pt --epochs 40 --threads 2
  mocaprig democap train --out lite.pt --epochs 80 --resume
  mocaprig democap train --config lite --out lite.pt --overwrite --max-minutes 30
"""

_EVAL_EPILOG = """\
The test set uses subjects, marker placements and takes never used in training (one take per
procedural action and subject), or a BVH motion (--motion) retargeted onto new subjects.
MPJPE is over the paper's 17 joints (no toes), MPMPE over the 53 markers, in mm.

examples:
  mocaprig democap eval
  mocaprig democap eval --ckpt lite.pt --cameras 4 --json
  mocaprig democap eval --all-cameras --json        4-, 3- and 2-camera figures
  mocaprig democap eval --motion ../shared/data/motion/cmu_131_02_scaled.bvh
"""


def register_democap(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``democap`` and its sub-commands to the ``mocaprig`` parser."""
    dm = subparsers.add_parser(
        "democap",
        help="DeMoCap: marker clouds -> labelled markers + joints (train, evaluate)",
        description="DeMoCap markers-to-pose network: train it and evaluate it on simulated data.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = dm.add_subparsers(dest="democap_command", metavar="SUBCOMMAND")
    dm.set_defaults(func=_usage(dm))

    tr = sub.add_parser(
        "train",
        help="train a network on simulated D415 marker data",
        description="Train (or resume) a DeMoCap network on simulated data.",
        epilog=_TRAIN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    tr.add_argument("--config", choices=("lite", "paper"), default="lite", help="network size")
    tr.add_argument("--out", required=True, metavar="CKPT", help="checkpoint file to write")
    tr.add_argument("--epochs", type=int, default=40, help="train until this many epochs")
    tr.add_argument("--resume", action="store_true", help="continue the run stored in --out")
    tr.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    tr.add_argument("--seed", type=int, default=0, help="seed of a new run")
    tr.add_argument("--takes", type=int, default=96, help="training takes (subjects x motions)")
    tr.add_argument("--samples-per-epoch", type=int, default=None, help="override the config")
    tr.add_argument("--batch-size", type=int, default=None, help="override the config")
    tr.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    tr.add_argument("--max-minutes", type=float, default=None, help="stop after this wall time")
    add_json_flag(tr)
    tr.set_defaults(func=democap_train)

    ev = sub.add_parser(
        "eval",
        help="measure a checkpoint on a held-out simulated test set",
        description="Evaluate a checkpoint on held-out simulated sessions with known truth.",
        epilog=_EVAL_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ev.add_argument("--ckpt", default=None, help="checkpoint (default: the committed lite one)")
    ev.add_argument("--motion", default=None, metavar="FILE.bvh", help="test on this BVH motion")
    ev.add_argument("--seed", type=int, default=0, help="seed of the test set")
    ev.add_argument("--cameras", type=int, choices=(2, 3, 4), default=4, help="D415s used")
    ev.add_argument("--all-cameras", action="store_true", help="report 4, 3 and 2 cameras")
    ev.add_argument("--subjects", type=int, default=1, help="subjects (rounds of the actions)")
    ev.add_argument("--frames", type=int, default=40, help="frames per take")
    add_json_flag(ev)
    ev.set_defaults(func=democap_eval)


def _usage(parser: argparse.ArgumentParser) -> Callable[[argparse.Namespace], int]:
    def handler(args: argparse.Namespace) -> int:
        parser.print_help(sys.stderr)
        return 2

    return handler


def democap_train(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig democap train``; returns 0."""
    from process.democap.config import config_by_name
    from process.democap.train import TrainOptions, train

    opts = TrainOptions(
        epochs=args.epochs,
        seed=args.seed,
        takes=args.takes,
        samples_per_epoch=args.samples_per_epoch,
        batch_size=args.batch_size,
        threads=args.threads,
        max_seconds=None if args.max_minutes is None else 60.0 * args.max_minutes,
    )
    ckpt = train(
        Path(args.out),
        opts,
        config=config_by_name(args.config),
        resume=args.resume,
        overwrite=args.overwrite,
        progress=ProgressBar("democap train"),
    )
    last = ckpt.history[-1] if ckpt.history else {}
    summary: dict[str, Any] = {
        "checkpoint": str(args.out),
        "config": ckpt.config.name,
        "epochs": ckpt.epoch,
        "loss": last.get("loss"),
        "val_mpjpe_mm": last.get("val_mpjpe_mm"),
    }
    if args.json:
        emit_json(summary)
    else:
        print(
            f"{args.out}: {ckpt.config.name}, {ckpt.epoch} epochs, loss {summary['loss']}, "
            f"held-out MPJPE {summary['val_mpjpe_mm']} mm"
        )
    return 0


def democap_eval(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig democap eval``; returns 0."""
    from process.body import read_bvh
    from process.democap.evaluate import evaluate, held_out_pool
    from process.democap.infer import DemocapPredictor

    predictor = DemocapPredictor(None if args.ckpt is None else Path(args.ckpt))
    clip = None if args.motion is None else read_bvh(args.motion)
    cams = (4, 3, 2) if args.all_cameras else (args.cameras,)
    pool = held_out_pool(args.seed, motion=clip, subjects=args.subjects)
    reports = {}
    for k in cams:
        rep = evaluate(
            predictor, seed=args.seed, num_cameras=k, frames_per_take=args.frames, pool=pool
        )
        reports[k] = rep.to_dict()
    main = reports[cams[0]]
    out: dict[str, Any] = {
        "checkpoint": str(args.ckpt or "committed lite"),
        "config": predictor.checkpoint.config.name,
        "motion": args.motion or "procedural (held-out)",
        "seed": args.seed,
        **main,
    }
    if len(cams) > 1:
        out["by_cameras"] = {str(k): v for k, v in reports.items()}
    if args.json:
        emit_json(out)
        return 0
    for k, r in reports.items():
        print(
            f"{k} cameras: MPJPE {r['mpjpe_mm']:.1f} mm, RMSPJPE {r['rmspjpe_mm']:.1f} mm, "
            f"MPMPE {r['mpmpe_mm']:.1f} mm, PCK@50 {100 * r['pck50']:.1f} %, "
            f"MPJAE {r['mpjae_deg']:.1f} deg ({r['frames']} frames)"
        )
        acts = ", ".join(f"{a} {v:.1f}" for a, v in r["per_action_mm"].items())
        print(f"  per action (mm): {acts}")
    return 0
