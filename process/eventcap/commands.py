"""``mocaprig eventcap ...``: EventCap, 3D motion at 1000 fps from the DAVIS240C.

Registered through the ``mocaprig.commands`` entry point ``eventcap``. Handlers import torch,
OpenCV and the pipeline lazily so ``mocaprig --help`` stays fast. ``eval`` takes its simulated
takes from the ``eventcap-take`` mock (``mocaprig.mocks`` entry points): the product never
imports the simulator. ``run`` processes a recording (:mod:`.run`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from mocaprig.cli import add_json_flag, emit_json, usage_handler
from mocaprig.progress import StageProgress

__all__ = ["eventcap_eval", "eventcap_run", "register_eventcap"]

_EPILOG = """\
examples:
  mocaprig eventcap eval --json                             procedural karate take, seed 0
  mocaprig eventcap eval --motion ../shared/data/motion/corpus/cmu_02_04.bvh --seed 3 --json
  mocaprig eventcap eval --seconds 4 --batches 10 --no-all   a quicker look
  mocaprig eventcap run session.mcap --calib calib.toml --detections det.json --height 1.75 \
      --out results.mcap                                     a recording -> MCAP, C3D, BVH
"""

_RUN_EPILOG = """\
Reads the DAVIS of the recording (one, or --davis SERIAL): its APS frames with their exposure
windows and its DVS events, a batch at a time (memory follows the batch, not the take). The
detections are our JSON (mocaprig.eventcap.detections), an OpenPose --write_json folder or a
COCO keypoint JSON; OpenPose/COCO frame i is the recording's i-th APS frame. The camera is the
calibration's DAVIS entry (mocaprig calibrate board). Writes:
  results.mcap  Foxglove SceneUpdate at 1 kHz on /eventcap/joints (19 keypoints, bones, names)
                and /eventcap/template (the fitted capsules); log time on the calibration's
                reference clock when it maps the DAVIS clock, else DAVIS time (see --json)
  results.c3d   the 19 keypoints at 1000 Hz, mm
  results.bvh   the 33-DoF poses at 1000 Hz on the template's skeleton (Y up, cm)
Progress and a per-stage time breakdown go to stderr (the breakdown also into --json).

examples:
  mocaprig eventcap run sim/session.mcap --calib calib.toml --detections det.json \
      --shape sim/truth/scenario.json --out results.mcap --batches 10 --json
  mocaprig eventcap run take.mcap --calib calib.toml --detections openpose_json/ \
      --height 1.78 --start 12.0 --end 17.0 --out kick.mcap --overwrite
"""

_EVAL_EPILOG = """\
The take is simulated: the realistic DAVIS240C simulator (docs/davis-sim.md) renders the actor
(a BVH clip retargeted onto a sampled body, or a procedural scenario); detections at the APS
frames are synthetic (truth + paper-level noise, labelled "synthetic"). EventCap is scored with
the paper's baselines *_linear and *_all (docs/eventcap.md): AE (MPJPE after Procrustes) and
MPJPE over the 15 body joints on every 10th 1 kHz frame.

examples:
  mocaprig eventcap eval --json
  mocaprig eventcap eval --motion ../shared/data/motion/corpus/cmu_02_05.bvh --seed 1 --json
  mocaprig eventcap eval --scenario default --seconds 6 --batches 20
  mocaprig eventcap eval --seconds 3 --start 1.6 --batches 6        fast strikes, quickly
"""


def register_eventcap(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``eventcap`` and its sub-commands to the ``mocaprig`` parser."""
    ec = subparsers.add_parser(
        "eventcap",
        help="EventCap: 3D human motion at 1000 fps from the DAVIS240C (evaluate)",
        description="EventCap (Xu et al., CVPR 2020) on DAVIS240C events and APS frames.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = ec.add_subparsers(dest="eventcap_command", metavar="SUBCOMMAND")
    ec.set_defaults(func=usage_handler(ec))

    ev = sub.add_parser(
        "eval",
        help="score EventCap and its baselines on a simulated take with truth",
        description="Simulate a DAVIS take with ground truth and score EventCap against it.",
        epilog=_EVAL_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ev.add_argument(
        "--motion", type=Path, default=None, metavar="FILE.bvh", help="actor motion (BVH)"
    )
    ev.add_argument(
        "--joint-map",
        type=Path,
        default=None,
        metavar="FILE.toml",
        help='map our joints onto the BVH\'s (our name = "its name"), for skeletons the '
        "exporter tables do not know",
    )
    ev.add_argument(
        "--scenario",
        default="karate",
        help="procedural scenario when no --motion is given (default: karate)",
    )
    ev.add_argument("--seed", type=int, default=0, help="world and detector seed")
    ev.add_argument("--seconds", type=float, default=4.0, help="take length (s, >= 3)")
    ev.add_argument(
        "--start",
        type=float,
        default=0.0,
        metavar="S",
        help="simulate the DAVIS from this instant of the take (s; a cheaper excerpt)",
    )
    ev.add_argument(
        "--batches",
        type=int,
        default=None,
        metavar="N",
        help="score only the first N batches (default: the whole take)",
    )
    ev.add_argument("--no-all", action="store_true", help="skip the *_all baseline")
    ev.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    add_json_flag(ev)
    ev.set_defaults(func=eventcap_eval)

    rn = sub.add_parser(
        "run",
        help="run EventCap on a recording's DAVIS; write MCAP, C3D and BVH results",
        description="EventCap on a recording: 1000 Hz joints and the fitted template.",
        epilog=_RUN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    rn.add_argument("session", type=Path, metavar="SESSION.mcap", help="the recording")
    rn.add_argument(
        "--calib", type=Path, required=True, metavar="CALIB.toml", help="its calibration"
    )
    rn.add_argument(
        "--detections",
        type=Path,
        required=True,
        metavar="PATH",
        help="detections: our JSON, an OpenPose --write_json folder or a COCO keypoint JSON",
    )
    rn.add_argument(
        "--detections-format",
        choices=("auto", "json", "openpose", "coco"),
        default="auto",
        help="format of --detections (default: auto)",
    )
    rn.add_argument("--out", type=Path, required=True, metavar="OUT.mcap", help="results MCAP")
    rn.add_argument("--c3d", type=Path, default=None, help="results C3D (default: beside --out)")
    rn.add_argument("--bvh", type=Path, default=None, help="results BVH (default: beside --out)")
    body = rn.add_mutually_exclusive_group(required=True)
    body.add_argument("--height", type=float, default=None, metavar="M", help="actor height (m)")
    body.add_argument(
        "--shape",
        type=Path,
        default=None,
        metavar="FILE.json",
        help="actor body shape (BodyShape fields, or a simulated truth/scenario.json)",
    )
    rn.add_argument("--davis", default=None, metavar="SERIAL", help="the DAVIS when several")
    rn.add_argument(
        "--batches", type=int, default=None, metavar="N", help="run only the first N batches"
    )
    rn.add_argument(
        "--start", type=float, default=None, metavar="S", help="DAVIS timeline start (s)"
    )
    rn.add_argument("--end", type=float, default=None, metavar="S", help="DAVIS timeline end (s)")
    rn.add_argument(
        "--no-template",
        action="store_true",
        help="leave the fitted capsules out of the MCAP (joints only)",
    )
    rn.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    rn.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_json_flag(rn)
    rn.set_defaults(func=eventcap_run)


def _mm(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def eventcap_eval(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig eventcap eval``; returns 0.

    Raises:
        ValidationError: a bad option; DeviceError: the simulator (``eventcap-take`` mock) is
            not installed.
    """
    from mocaprig.acquire.mocks import load_mock_factory
    from mocaprig.errors import ValidationError
    from mocaprig.process.body.bvh import load_joint_map
    from mocaprig.process.eventcap.evaluate import evaluate_take

    if args.threads < 1:
        msg = f"--threads must be >= 1, got {args.threads}"
        raise ValidationError(msg)
    if args.batches is not None and args.batches < 1:
        msg = f"--batches must be >= 1, got {args.batches}"
        raise ValidationError(msg)
    if args.motion is not None and not args.motion.is_file():
        msg = f"--motion {args.motion}: no such file; give a BVH clip"
        raise ValidationError(msg)
    import torch

    # Batches are many small solves: one thread avoids the contention two threads cause.
    torch.set_num_threads(args.threads)
    simulate = load_mock_factory("eventcap-take")
    progress = StageProgress("eventcap eval: ")
    progress("simulating the DAVIS (µs)", 0, round(args.seconds * 1e6))
    take = simulate(
        seed=args.seed,
        seconds=args.seconds,
        motion_path=args.motion,
        joint_map=None if args.joint_map is None else load_joint_map(args.joint_map),
        scenario=args.scenario,
        start_s=args.start,
        # With --batches, the DAVIS is simulated only until their frames are complete.
        max_frames=None if args.batches is None else args.batches + 1,
        progress=progress.stage("simulating the DAVIS (µs)"),
    )
    result = evaluate_take(
        take,
        protocol="simulated take, realistic DAVIS240C, synthetic detections",
        seed=args.seed,
        max_batches=args.batches,
        with_all=not args.no_all,
        progress=progress,
    )
    progress.done()
    out: dict[str, Any] = result.to_json()
    if args.json:
        emit_json(out)
        return 0
    print(f"take: {out['take']}  ({out['protocol']}; detections: {out['detections']})")
    print(f"batches: {out['batches']}, {out['seconds_per_batch']} s per batch")
    print(f"{'method':<10} {'AE mm':>14} {'MPJPE mm':>14} {'AE raw':>8} {'AE nonRaw':>10}")
    for name in ("ours", "linear", "all"):
        e = out[name]
        if e is None:
            continue
        print(
            f"{name:<10} {e['ae_mm']:>7.1f} ± {e['ae_std_mm']:<5.1f}"
            f"{e['mpjpe_mm']:>7.1f} ± {e['mpjpe_std_mm']:<5.1f}"
            f"{_mm(e['ae_raw_mm']):>8} {_mm(e['ae_nonraw_mm']):>10}"
        )
    print(f"AE ours / linear: {out['ae_ratio_to_linear']}")
    print(
        f"Size.sec: {out['size_sec_mb']} MB/s (1000 fps frames: "
        f"{out['size_sec_reference_mb']} MB/s)"
    )
    stages = ", ".join(f"{k} {v:.2f} s" for k, v in out["stage_seconds_per_batch"].items())
    print(f"per batch: {stages}")
    return 0


def eventcap_run(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig eventcap run``; returns 0.

    Raises:
        ValidationError, RecordingError, CalibrationError, ProcessingError: from
            :func:`~.run.run_eventcap` (each names the input and what to do).
    """
    from mocaprig.errors import ValidationError
    from mocaprig.process.eventcap.run import run_eventcap

    if args.threads < 1:
        msg = f"--threads must be >= 1, got {args.threads}"
        raise ValidationError(msg)
    if not args.session.is_file():
        msg = f"{args.session}: no such recording; give a .mcap from mocaprig record/simulate"
        raise ValidationError(msg)
    import torch

    # Batches are many small solves: one thread avoids the contention two threads cause.
    torch.set_num_threads(args.threads)
    labels = {"index": "indexing frames and events", "write": "finishing the files"}
    progress = StageProgress("eventcap run: ", labels=labels)
    result = run_eventcap(
        args.session,
        args.calib,
        out=args.out,
        detections=args.detections,
        detections_format=args.detections_format,
        c3d=args.c3d,
        bvh=args.bvh,
        davis=args.davis,
        height_m=args.height,
        shape_path=args.shape,
        batches=args.batches,
        start_s=args.start,
        end_s=args.end,
        template="none" if args.no_template else "capsules",
        overwrite=args.overwrite,
        progress=progress,
    )
    progress.done()
    out: dict[str, Any] = result.summary()
    stages = ", ".join(f"{k.removesuffix('_s')} {v:.2f} s" for k, v in out["timings_s"].items())
    print(f"time per stage: {stages}", file=sys.stderr)
    if args.json:
        emit_json(out)
        return 0
    print(f"session: {out['session']} ({out['davis']}, detections: {out['detections']})")
    print(
        f"batches: {out['batches']} of {out['frames_total'] - 1}, "
        f"{out['tracking_frames']} frames at 1000 Hz, time base: {out['time_base']}"
    )
    for kind, path in out["outputs"].items():
        print(f"{kind}: {path}")
    return 0
