"""Sync-channel calibration of kept random worlds, told what a scope measures (issue 16).

The sync box's latency and a D415 slave's trigger delay never reach a recording (docs/
calibration.md, "What stays an assumption"): on a real rig they are measured once with a scope
and the LED test of docs/d415-timing.md §4, which also gives the pulse phase, and passed as
``CalibrationOptions.sync_latency_us`` / ``slave_trigger_delay_us`` / ``d415_pulse_at``. This
runs :func:`calib.vicon_calibration.calibrate_vicon` with the sync channel on sessions kept by
``benchmarks/calibrate_worlds.py --keep DIR``, given those three true values of each world
(nothing else: the edge filter, ADC, drifts, jitter and dropped frames stay hidden), and prints
the D415 ↔ Vicon offset errors, so the part of the sync-channel figure that the two
unobservable delays cause can be told from the estimator's own.

    nice -n 5 .venv/bin/python benchmarks/calibrate_worlds_told.py --keep /tmp/wk --seeds 1004 1005
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from mocaprig.calib.vicon_calibration import calibrate_vicon, evaluate_calibration
from mocaprig.calib.vicon_calibration_options import CalibrationOptions
from mocaprig.drivers_mock.session import simulate_session
from mocaprig.errors import MocaprigError


def _told(root: Path) -> dict[str, Any]:
    world = json.loads((root / "truth" / "scenario.json").read_text())["world"]
    opt = CalibrationOptions(
        sync_channel="D415_SYNC",
        sync_latency_us=float(world["sync_latency_us"]),
        slave_trigger_delay_us=float(world["slave_trigger_delay_us"]),
        d415_pulse_at=world["pulse_at"],
    )
    row: dict[str, Any] = {
        "world": root.name,
        "sync_latency_us": world["sync_latency_us"],
        "slave_trigger_delay_us": world["slave_trigger_delay_us"],
    }
    try:
        res = calibrate_vicon(root / "session.mcap", root / "vicon" / "session.c3d", options=opt)
    except MocaprigError as err:
        row["refused"] = str(err)
        return row
    ev = evaluate_calibration(res.calibration, root)
    row["d415_offset_us"] = [
        abs(d.clock_offset_error_ms) * 1e3 for d in ev.devices if d.device.startswith("d415/")
    ]
    return row


def _print_row(seed: int, r: dict[str, Any]) -> None:
    figure = r.get("refused") or f"D415 offset ≤ {max(r['d415_offset_us']):.1f} µs"
    print(f"world {seed} [sync, told latency and slave delay]: {figure}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument(
        "--keep",
        type=Path,
        default=None,
        help="sessions kept by calibrate_worlds.py --keep DIR (default: simulate into a temporary "
        "folder, about 4 GB and 5 min per world)",
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[1004], help="world seeds")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="worlds-told-") as tmp:
        for seed in args.seeds:
            root = (args.keep or Path(tmp)) / f"world{seed}"
            if not (root / "vicon" / "session.c3d").is_file():
                if args.keep is not None:
                    parser.error(f"{root}: no kept session (run calibrate_worlds.py --keep first)")
                simulate_session(
                    root, seed=seed, seconds=30.0, devices=("davis", "d415"), cameras=4,
                    world="random", overwrite=True,
                )  # fmt: skip
            rows.append(_told(root))
            _print_row(seed, rows[-1])
    offs = np.concatenate([r["d415_offset_us"] for r in rows if "d415_offset_us" in r] or [[]])
    out = {
        "benchmark": "calibrate_worlds_told",
        "seeds": args.seeds,
        "refused": sum("refused" in r for r in rows),
        "d415_offset_us": {
            "n": len(offs),
            "p95": float(np.percentile(offs, 95)) if len(offs) else None,
            "worst": float(offs.max()) if len(offs) else None,
        },
        "machine": (
            f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
        ),
        "rows": rows,
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
