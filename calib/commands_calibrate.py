"""``mocaprig calibrate ...``: rig calibration commands.

Registered through the ``mocaprig.commands`` entry point ``calibrate``. Sub-commands:

* ``vicon``: the D415 poses (and, where available, clocks) against a Vicon trial
  (:func:`mocaprig.calib.vicon_calibration.calibrate_vicon`);
* ``evaluate``: a calibration scored against a simulated session's truth;
* ``intrinsics`` and ``board``: ChArUco calibration, from :mod:`calib.commands_charuco` when
  that module is installed.

Handlers import numpy/scipy/OpenCV lazily so ``mocaprig --help`` stays fast.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

from mocaprig.calib.commands_charuco import add_board_parser, add_intrinsics_parser
from mocaprig.calib.vicon_calibration_options import D415_PULSE_CONVENTIONS, SLAVE_TRIGGER_DELAY_US
from mocaprig.cli import add_json_flag, emit_json, usage_handler
from mocaprig.progress import ProgressBar

__all__ = ["calibrate_evaluate", "calibrate_vicon_command", "register_calibrate"]

_log = logging.getLogger(__name__)

_EPILOG = """\
examples:
  mocaprig calibrate vicon session.mcap trial.c3d --out calib.toml
  mocaprig calibrate vicon session.mcap trial.c3d --out calib.toml --report report/ --json
  mocaprig calibrate evaluate calib.toml --truth sim/ --json
  mocaprig calibrate intrinsics --help           ChArUco intrinsics (when installed)
  mocaprig calibrate board --help                ChArUco extrinsics without Vicon
"""

_VICON_EPILOG = """\
The actor must stand still (T-pose) for the first second of both the recording and the Vicon
trial: each D415 is registered on that static start without an initial pose (distance-triplet
RANSAC + ICP), matched to the Vicon markers under a strict gate and bundle-adjusted with the
Vicon markers and the intrinsics fixed. A camera whose reprojection RMS exceeds --max-rms-px
(default 1.5 px) or with fewer than --min-inliers observations is refused (exit 1) unless
--force is given. Clocks: from the video (reprojection); when the C3D has the analog channel
--sync-channel (default D415_SYNC: the sync box's toggle output, docs/wiring.md §7), the D415
clocks come from its edges instead (µs, sub-ppm); the notes say which was used. Relating a
D415 frame (stamped mid-exposure) to a sync pulse needs where the master's pulse falls, which
is undocumented for the D415: exposure-start or readout-start (Intel's answers for the D4xx
family). The calibration makes the clocks under both and keeps the one the data tell (the
master's own video clock, else its reprojection cost); when nothing tells and a slave or the
DAVIS depends on it, the calibration is refused (exit 1) naming it: measure it once with the
LED test of docs/d415-timing.md §4 and pass --d415-pulse-at with --no-measure-pulse-phase
(--force keeps --d415-pulse-at, default exposure-start, with a note). A wrong one moves the
sync-channel and DAVIS clocks by about one exposure, or leaves them unpaired. The sync box's
latency (--sync-latency-us) and a slave's trigger delay are not visible in a recording: they
stay assumptions, each noted with its effect. The calibration file records the convention
used (statistics d415_pulse_at_readout_start, d415_slave_trigger_delay_us).

examples:
  mocaprig calibrate vicon session.mcap trial.c3d --out calib.toml
  mocaprig calibrate vicon session.mcap trial.c3d --out calib.json --json
  mocaprig calibrate vicon session.mcap trial.c3d --out calib.toml --attach-to calibrated.mcap
  mocaprig calibrate vicon session.mcap old.c3d --unit mm --out calib.toml --overwrite
  mocaprig calibrate vicon session.mcap trial.c3d --out calib.toml --report report/
  mocaprig calibrate vicon session.mcap trial.c3d --out calib.toml --sync-channel "Sync.1"
  mocaprig calibrate vicon session.mcap trial.c3d --out calib.toml --sync-channel none
  mocaprig calibrate vicon session.mcap trial.c3d --out calib.toml --d415-pulse-at readout-start
  mocaprig calibrate vicon session.mcap trial.c3d --out calib.toml --d415-pulse-at readout-start \
      --no-measure-pulse-phase
  mocaprig calibrate vicon session.mcap trial.c3d --out calib.toml --slave-trigger-delay-us 790
  mocaprig calibrate vicon session.mcap trial.c3d --out calib.toml --sync-latency-us 12.5
"""

_EVALUATE_EPILOG = """\
Per device of the simulated session: rotation error (deg), camera-centre error (mm), and for
each clock mapping the mapped-time error at the session midpoint (ms) and the drift error (ppm).

examples:
  mocaprig calibrate evaluate calib.toml --truth sim/
  mocaprig calibrate evaluate calib.toml --truth sim/truth --json
"""


def register_calibrate(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``calibrate`` and its sub-commands to the ``mocaprig`` parser."""
    cal = subparsers.add_parser(
        "calibrate",
        help="calibrate the rig (Vicon registration, evaluation against truth)",
        description="Calibrate the rig: camera poses and clocks.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = cal.add_subparsers(dest="calibrate_command", metavar="SUBCOMMAND")
    cal.set_defaults(func=usage_handler(cal))

    vic = sub.add_parser(
        "vicon",
        help="D415 poses against a Vicon trial of the same session",
        description="Register every D415 of a recording to the markers of a Vicon trial.",
        epilog=_VICON_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    vic.add_argument("session", metavar="SESSION.mcap", type=Path, help="the recording")
    vic.add_argument("vicon", metavar="VICON.c3d", type=Path, help="the Vicon trial (C3D or CSV)")
    vic.add_argument("--out", type=Path, required=True, help="calibration file (.toml or .json)")
    vic.add_argument(
        "--attach-to",
        type=Path,
        default=None,
        metavar="OUT.mcap",
        help="also write a copy of the recording with the calibration attached",
    )
    vic.add_argument(
        "--report",
        type=Path,
        default=None,
        metavar="DIR",
        help="write a report: figures, summary.json and index.html (open it in a browser)",
    )
    vic.add_argument(
        "--force",
        action="store_true",
        help="write even above the thresholds or with an unobservable pulse phase (noted)",
    )
    vic.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    vic.add_argument("--max-rms-px", type=float, default=None, help="refusal threshold (px)")
    vic.add_argument("--min-inliers", type=int, default=None, help="refusal threshold")
    vic.add_argument(
        "--unit", choices=("mm", "cm", "m"), default=None, help="Vicon unit when the file lacks one"
    )
    vic.add_argument("--camera", action="append", default=None, help="only this D415 (repeat)")
    vic.add_argument("--seed", type=int, default=0, help="seed of the coarse alignment")
    vic.add_argument(
        "--sync-channel",
        default="D415_SYNC",
        metavar="LABEL",
        help="Vicon analog channel with the D415 frame pulses (default D415_SYNC; none: video "
        "clocks only)",
    )
    vic.add_argument(
        "--d415-pulse-at",
        choices=D415_PULSE_CONVENTIONS,
        default=D415_PULSE_CONVENTIONS[0],
        help="where the D415 master's sync pulse falls: at its exposure start (default) or at "
        "its readout start, i.e. the end of its exposure (Intel's answers for the D4xx family); "
        "measure it with the LED test, docs/d415-timing.md §4",
    )
    vic.add_argument(
        "--slave-trigger-delay-us",
        type=float,
        default=None,
        metavar="US",
        help="a D415 slave's exposure start after the pulse (µs; default: the convention's, "
        f"{SLAVE_TRIGGER_DELAY_US['exposure-start']:g} for exposure-start, "
        f"{SLAVE_TRIGGER_DELAY_US['readout-start']:g} for readout-start)",
    )
    vic.add_argument(
        "--sync-latency-us",
        type=float,
        default=None,
        metavar="US",
        help="the sync wiring's delay from the master's pulse to the Vicon channel's edge (µs; "
        "default 2, the project's sync box). No recording shows it: measure pulse in vs toggle "
        "out with a scope; a wrong value shifts every D415 clock by the difference",
    )
    vic.add_argument(
        "--no-measure-pulse-phase",
        dest="measure_pulse_phase",
        action="store_false",
        help="use --d415-pulse-at as given instead of choosing the convention the clocks fit",
    )
    add_json_flag(vic)
    vic.set_defaults(func=calibrate_vicon_command)

    ev = sub.add_parser(
        "evaluate",
        help="score a calibration against a simulated session's truth",
        description="Compare a calibration with the truth of `mocaprig simulate` output.",
        epilog=_EVALUATE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ev.add_argument("calibration", metavar="CALIB", type=Path, help="calibration file")
    ev.add_argument("--truth", type=Path, required=True, metavar="SIMDIR", help="session folder")
    add_json_flag(ev)
    ev.set_defaults(func=calibrate_evaluate)

    add_intrinsics_parser(sub)
    add_board_parser(sub)


def calibrate_vicon_command(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig calibrate vicon``; returns the exit code."""
    from mocaprig.calib.calibration import write_calibration
    from mocaprig.calib.vicon_calibration import (
        CalibrationOptions,
        attach_calibration,
        calibrate_vicon,
    )

    out: Path = args.out
    if out.suffix not in (".toml", ".json"):
        from mocaprig.errors import ValidationError

        msg = f"--out {out}: a calibration file is .toml or .json"
        raise ValidationError(msg)
    for p in (out, args.attach_to):
        if p is not None and p.exists() and not args.overwrite:
            from mocaprig.errors import CalibrationError

            msg = f"{p} exists; pass --overwrite to replace it"
            raise CalibrationError(msg)
    kw: dict[str, Any] = {"force": args.force, "seed": args.seed, "unit": args.unit}
    kw["sync_channel"] = None if args.sync_channel.lower() == "none" else args.sync_channel
    kw["d415_pulse_at"] = args.d415_pulse_at
    kw["slave_trigger_delay_us"] = args.slave_trigger_delay_us
    kw["measure_pulse_phase"] = args.measure_pulse_phase
    if args.sync_latency_us is not None:
        kw["sync_latency_us"] = args.sync_latency_us
    if args.max_rms_px is not None:
        kw["max_rms_px"] = args.max_rms_px
    if args.min_inliers is not None:
        kw["min_inliers"] = args.min_inliers
    if args.camera:
        kw["cameras"] = tuple(args.camera)
    bar = ProgressBar("calibrate vicon", unit="steps")
    result = calibrate_vicon(
        args.session, args.vicon, options=CalibrationOptions(**kw), progress=bar
    )
    bar.finish()
    write_calibration(result.calibration, out, overwrite=args.overwrite)
    if args.attach_to is not None:
        attach_calibration(
            args.session, args.attach_to, result.calibration, overwrite=args.overwrite
        )
    summary = result.summary()
    summary["out"] = str(out)
    summary["attached_to"] = None if args.attach_to is None else str(args.attach_to)
    figures: list[str] = []
    index: str | None = None
    if args.report is not None:
        from mocaprig.calib.report import write_report

        report = write_report(
            result,
            args.report,
            overwrite=args.overwrite,
            summary=summary,
            progress=ProgressBar("calibration report", unit="files"),
        )
        figures = [str(p) for p in report.figures]
        index = str(report.index)
    summary["figures"] = figures
    summary["report"] = index
    if args.json:
        emit_json(summary)
        return 0
    print(f"calibration -> {out}")
    for c in summary["cameras"]:
        print(
            f"  {c['name']}: {c['reprojection_rms_px']:.3f} px RMS, {c['inliers']:.0f} inliers "
            f"({c['markers']:.0f} markers, {c['static_frames']} still frames), "
            f"σ {c['rotation_sigma_deg']:.4f}° / {c['translation_sigma_mm']:.2f} mm"
        )
    for k in summary["clocks"]:
        print(f"  clock {k['device']}: offset {k['offset_ns']} ns, drift {k['drift_ppm']:.2f} ppm")
    for r in summary["refused"]:
        print(f"  WARNING {r}: above the thresholds, written because of --force")
    for n in summary["notes"]:
        print(f"  note: {n}")
    if args.attach_to is not None:
        print(f"  recording with the calibration attached -> {args.attach_to}")
    if index is not None:
        print(f"  report: {len(figures)} figures and the summary -> {index}")
    return 0


def calibrate_evaluate(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig calibrate evaluate``; returns 0."""
    from mocaprig.calib.calibration import read_calibration
    from mocaprig.calib.vicon_calibration import evaluate_calibration

    ev = evaluate_calibration(read_calibration(args.calibration), args.truth)
    if args.json:
        emit_json(ev.as_dict())
        return 0

    def fmt(x: float, spec: str) -> str:
        return "n/a" if x != x else format(x, spec)

    print(f"{args.calibration} against {ev.truth_dir}")
    print(
        f"  {'device':<24} {'truth':<8} {'rot deg':>9} {'trans mm':>9} {'clock ms':>9} {'ppm':>7}"
    )
    for d in ev.devices:
        print(
            f"  {d.device:<24} {d.truth_name:<8} {fmt(d.rotation_error_deg, '9.4f')} "
            f"{fmt(d.translation_error_mm, '9.2f')} {fmt(d.clock_offset_error_ms, '9.3f')} "
            f"{fmt(d.drift_error_ppm, '7.2f')}"
            + (
                f"  (vs the device it was mapped through: {d.clock_error_vs_via_us:+.2f} µs)"
                if d.clock_error_vs_via_us == d.clock_error_vs_via_us
                else ""
            )
        )
    for m in ev.missing:
        print(f"  {m}: not in the calibration")
    return 0
