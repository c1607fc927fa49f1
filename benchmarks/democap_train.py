"""DeMoCap training speed: seconds per training step and per epoch, on the CPU and on a GPU.

Times :func:`mocaprig.process.democap.train.train` itself, configuration after configuration
in one process (the ratios are the comparable figures on a shared machine): for each
``--configs`` network size, each device this machine has (``cpu``; ``cuda`` when torch sees a
GPU, with mixed precision as ``train`` uses it) and each ``--workers`` count of data-simulation
processes, a new run of ``--steps`` steps of the config's batch, seed 0, in a temporary folder.
The step times come from ``train``'s progress callback; the first ``--warmup`` steps (worker
start-up, allocator warm-up) are left out. An epoch is the config's ``samples_per_epoch``
(1,024 for ``lite``, 8,165 for ``paper``) at the median step time, validation not included.

The training pool is ``--takes`` procedural takes (12 by default, 96 in a real run: the pool's
size does not change a step's cost, only the time to build it); no corpus clip (a corpus
frame is simulated like a procedural one once retargeted).

    .venv/bin/python benchmarks/democap_train.py   # lite, every device, 0 and 1 worker
    .venv/bin/python benchmarks/democap_train.py --configs lite paper --devices cuda --workers 0 8

Prints a table, then one JSON object as its last line.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from mocaprig.process.democap.config import config_by_name
from mocaprig.process.democap.train import Device, TrainOptions, train


def _run(config: str, device: Device, workers: int, args: argparse.Namespace) -> dict[str, Any]:
    cfg = config_by_name(config)
    stamps: list[float] = []

    def progress(done: int, total: int) -> None:
        stamps.append(time.perf_counter())

    opts = TrainOptions(
        epochs=1,
        seed=0,
        takes=args.takes,
        samples_per_epoch=args.steps * cfg.batch_size,
        threads=args.threads,
        device=device,
        data_workers=workers,
    )
    cpu0 = time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        train(Path(tmp) / "bench.pt", opts, config=cfg, progress=progress)
    cpu_s = time.process_time() - cpu0
    steps = [b - a for a, b in zip(stamps[args.warmup :], stamps[args.warmup + 1 :], strict=False)]
    if not steps:
        msg = f"--steps {args.steps} leaves no step after --warmup {args.warmup}"
        raise SystemExit(msg)
    step_s = statistics.median(steps)
    return {
        "config": config,
        "device": device,
        "data_workers": workers,
        "batch": cfg.batch_size,
        "steps_timed": len(steps),
        "step_s_median": round(step_s, 4),
        "step_s_p90": round(sorted(steps)[int(0.9 * (len(steps) - 1))], 4),
        "samples_per_s": round(cfg.batch_size / step_s, 1),
        "samples_per_epoch": cfg.samples_per_epoch,
        "epoch_s": round(cfg.samples_per_epoch / cfg.batch_size * step_s, 1),
        "process_cpu_s": round(cpu_s, 1),
    }


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--configs", nargs="+", default=["lite"], choices=("lite", "paper"))
    ap.add_argument("--workers", nargs="+", type=int, default=[0, 1], help="data workers")
    ap.add_argument("--steps", type=int, default=14, help="training steps per configuration")
    ap.add_argument("--warmup", type=int, default=3, help="first steps left out of the times")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--takes", type=int, default=12, help="procedural takes in the pool")
    ap.add_argument(
        "--devices",
        nargs="+",
        default=None,
        choices=("cpu", "cuda"),
        help="where to train (default: the CPU, and CUDA when torch sees a GPU)",
    )
    args = ap.parse_args(argv)
    cuda = torch.cuda.is_available()
    devices: list[Device] = args.devices or (["cpu", "cuda"] if cuda else ["cpu"])
    if "cuda" in devices and not cuda:
        msg = "--devices cuda: torch sees no CUDA GPU on this machine"
        raise SystemExit(msg)
    rows = []
    for config in args.configs:
        for device in devices:
            for workers in args.workers:
                row = _run(config, device, workers, args)
                rows.append(row)
                print(
                    f"{config:6s} {device:5s} workers {workers:2d}: "
                    f"step {row['step_s_median']:.3f} s "
                    f"(p90 {row['step_s_p90']:.3f}), {row['samples_per_s']:.1f} samples/s, "
                    f"epoch of {row['samples_per_epoch']} samples {row['epoch_s']:.0f} s",
                    file=sys.stderr,
                )
    out = {
        "benchmark": "democap_train",
        "machine": {
            "cpu_count": os.cpu_count(),
            "platform": platform.platform(),
            "torch": torch.__version__,
            "gpu": torch.cuda.get_device_name(0) if cuda else None,
            "load_avg_1m": round(os.getloadavg()[0], 2),
        },
        "threads": args.threads,
        "rows": rows,
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
