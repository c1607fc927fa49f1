"""Command-line entry points of the simulated world (``mocaprig simulate``).

Handlers are thin: they parse, call a typed function (:func:`drivers_mock.session.simulate_session`)
and print. Heavy modules are imported inside the handlers so ``mocaprig --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

from mocaprig.cli import add_json_flag, emit_json
from mocaprig.progress import ProgressBar

if TYPE_CHECKING:
    from mocaprig.drivers_mock.session import Device

__all__ = ["register_demo", "register_simulate"]

_SIMULATE_EPILOG = """\
examples:
  mocaprig simulate --seconds 5 --out sim
      default scenario, seed 0: truth in sim/truth, Vicon C3D + CSV in sim/vicon
  mocaprig simulate --scenario karate --seed 7 --seconds 20 --out karate --json
      fast strikes; one JSON object with paths, seed, markers, rate and clap times
  mocaprig simulate --motion walk.bvh --seconds 12 --out walk --overwrite
      retarget a BVH clip onto the seeded actor, replacing an earlier run
  mocaprig simulate --seconds 4 --cameras 2 --davis-dvs --out short
      2 D415 + the DAVIS with its DVS events (about 20 s CPU per simulated second)
  mocaprig simulate --seconds 30 --devices none --out vicon-only
      truth + Vicon only, no session.mcap (fast)
  mocaprig simulate --seconds 30 --world random --seed 4 --out w4
      a rig the calibration does not mirror: hidden parameters drawn from seed 4
      (truth/scenario.json "world" says what they were)

Outputs: truth/ (ground truth), vicon/ (C3D + Nexus CSV) and session.mcap, the rig's recording
made through the real drivers talking to the mock devices of the same world (then run e.g.
`mocaprig info sim/session.mcap` or `mocaprig calibrate vicon sim/session.mcap
sim/vicon/session.c3d`). Recording cost on a 2-core machine: ~1.5 s CPU per simulated second
per D415, ~2 s per simulated second for the DAVIS without DVS, ~20 s with --davis-dvs; about
35 MB of MCAP per D415 per second.

scenarios: default (T-pose static start + procedural actions), karate (fast strikes),
tpose (static). The same --seed always gives the same world.
"""


def register_simulate(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``mocaprig simulate``."""
    from mocaprig.drivers_mock.scenario import SCENARIOS

    p = subparsers.add_parser(
        "simulate",
        help="simulate a session: ground truth + Vicon C3D/CSV",
        description=(
            "Simulate a seeded session of the rig (actor, cameras, clocks, clapperboard) and "
            "write its ground truth and the simulated Vicon capture."
        ),
        epilog=_SIMULATE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--scenario",
        choices=sorted(SCENARIOS),
        default="default",
        help="named scenario (default: %(default)s)",
    )
    p.add_argument("--motion", metavar="FILE.bvh", help="BVH motion to retarget onto the actor")
    p.add_argument(
        "--joint-map",
        metavar="FILE.toml",
        default=None,
        help='map our joints onto the BVH\'s (our name = "its name"), for skeletons the '
        "exporter tables do not know",
    )
    p.add_argument("--seed", type=int, default=0, help="world seed (default: %(default)s)")
    p.add_argument("--seconds", type=float, required=True, help="session length in seconds (>= 3)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (must be empty)")
    p.add_argument(
        "--truth-rate", type=float, default=1000.0, metavar="HZ", help="truth sampling rate"
    )
    p.add_argument("--overwrite", action="store_true", help="write into a non-empty folder")
    p.add_argument(
        "--devices",
        default="davis,d415,syncbox",
        metavar="LIST",
        help="devices recorded into session.mcap: a comma list of davis,d415,syncbox, or "
        "'none' for no recording (default: %(default)s)",
    )
    p.add_argument(
        "--cameras", type=int, default=4, metavar="N", help="D415 count, 1..4 (default: 4)"
    )
    p.add_argument(
        "--davis-dvs",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="run the DAVIS DVS module (events; ~10x the DAVIS simulation cost). Off, the DAVIS "
        "still records APS frames, IMU and the trigger input (default: off)",
    )
    p.add_argument(
        "--world",
        choices=("nominal", "random"),
        default="nominal",
        help="hidden world parameters the calibration is never told (sync latency, D415 pulse "
        "phase and slave delay, Vicon analog front end, clap law, DAVIS trigger jitter, "
        "master's dropped first frames, clock drifts, occlusion): 'nominal' keeps the "
        "simulator's long-standing values, so earlier sessions, tests and the demo keep their "
        "figures (the default for that reason); 'random' draws them from --seed over the "
        "ranges of a real rig (docs/simulated-world.md), for testing the estimator. The "
        "values drawn go to truth/scenario.json only (default: %(default)s)",
    )
    add_json_flag(p)
    p.set_defaults(func=_simulate)


def _parse_devices(text: str) -> tuple[Device, ...]:
    from mocaprig.drivers_mock.session import DEVICES
    from mocaprig.errors import ValidationError

    if text.strip().lower() == "none":
        return ()
    names = [t.strip() for t in text.split(",") if t.strip()]
    out: list[Device] = []
    for n in names:
        if n not in DEVICES:
            msg = f"--devices: unknown device {n!r}; choose from {', '.join(DEVICES)} or none"
            raise ValidationError(msg)
        out.append(n)
    return tuple(out)


def _stage_progress(label: str) -> ProgressBar:
    """One progress bar per stage of ``simulate`` (stage, items done/total on stderr)."""
    return ProgressBar(f"simulate {label}")


def _simulate(args: argparse.Namespace) -> int:
    from mocaprig.drivers_mock.session import simulate_session
    from mocaprig.process.body.bvh import load_joint_map

    result = simulate_session(
        args.out,
        scenario=args.scenario,
        seed=args.seed,
        seconds=args.seconds,
        motion_path=args.motion,
        joint_map=None if args.joint_map is None else load_joint_map(args.joint_map),
        truth_rate_hz=args.truth_rate,
        overwrite=args.overwrite,
        progress=None if args.json or getattr(args, "quiet", False) else _stage_progress,
        devices=_parse_devices(args.devices),
        cameras=args.cameras,
        davis_dvs=args.davis_dvs,
        world=args.world,
    )
    if args.json:
        emit_json(result.to_dict())
        return 0
    rec = result.recording
    rec_line = (
        "  recording:  none (--devices none)"
        if rec is None
        else (
            f"  recording:  {rec.path} ({', '.join(rec.devices)}; {rec.cameras} D415; DVS "
            f"{'on' if rec.davis_dvs else 'off'}; {rec.bytes / 1e6:.0f} MB, "
            f"{sum(m for _, m, _ in rec.streams)} messages, {rec.drops_total} dropped)"
        )
    )
    claps = ", ".join(f"{t * 1e-9:.3f} s" for t in result.clap_times_ns)
    print(
        f"simulated {result.seconds:g} s of scenario {result.scenario.name!r} (seed {result.seed})"
        f" in {result.elapsed_s:.1f} s\n"
        f"  truth:      {result.truth_dir}\n"
        f"  Vicon C3D:  {result.c3d_path} ({result.vicon_frames} frames at "
        f"{result.vicon_rate_hz:g} Hz, {result.num_body_markers} body + "
        f"{result.num_clapper_markers} clapperboard markers, "
        f"{100 * result.vicon_gap_fraction:.1f} % gaps)\n"
        f"  Nexus CSV:  {result.csv_path}\n"
        f"  claps at:   {claps}\n"
        f"{rec_line}",
        file=sys.stdout,
    )
    return 0


_DEMO_EPILOG = """\
examples:
  mocaprig demo --out demo-out
      simulate a 10 s session, record it through the drivers and the mock devices (4 D415,
      DAVIS without DVS, sync box), check the recording, read the Vicon exports back,
      compare with the truth, write demo-out/summary.png and demo-out/report.json
  mocaprig demo --scenario karate --seed 3 --seconds 6 --out karate-demo --json
      the same on fast strikes; one JSON object with every figure
  mocaprig demo --out quick-demo --real-frames 3
      the real-motion figures on 3 frames a clip instead of 8: a minute or two quicker

The demo runs the whole toolkit as far as it exists: simulate, record, check the recording,
Vicon I/O, calibration, DeMoCap on held-out simulated takes, the DeMoCap replay of the recording
(demo-out/results.mcap, .c3d, .csv; every 3rd rig instant), the actor calibrated from the
recording (demo-out/democap_subject.json) and the replay solved as them, 1 s of `democap live`
on the mock rig of the same world (demo-out/live.mcap), then EventCap on a short simulated
DAVIS take of fast strikes, scored with the paper's *_linear and *_all baselines (synthetic
detections); with --davis-dvs, `eventcap run` on the demo's own recording too.
Every DeMoCap figure is labelled with its protocol: the simulated ones are in-distribution
(simulated actions, bodies and D415 model like training's); where the motion corpus is beside
the clone (../shared/data/motion/corpus, or --corpus DIR), the committed checkpoint is also
scored on its test split, real motion of performers it never saw (unseen-real, 8 frames per
clip; the full figure: `mocaprig democap eval --protocol unseen-real`, docs/democap.md).
"""


def register_demo(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``mocaprig demo``."""
    p = subparsers.add_parser(
        "demo",
        help="the main job on the simulated rig, with figures against ground truth",
        description=(
            "Simulate a session of the rig, run every stage of the toolkit that exists on it "
            "and report the figures against the simulated ground truth."
        ),
        epilog=_DEMO_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--scenario", default="default", help="simulated scenario (default: %(default)s)"
    )
    p.add_argument("--seed", type=int, default=0, help="world seed (default: %(default)s)")
    p.add_argument(
        "--seconds", type=float, default=10.0, help="session length (default: %(default)s)"
    )
    p.add_argument("--out", default="demo-out", metavar="DIR", help="output folder")
    p.add_argument("--overwrite", action="store_true", help="replace an earlier demo in --out")
    p.add_argument("--cameras", type=int, default=4, metavar="N", help="D415 recorded (default: 4)")
    p.add_argument(
        "--davis-dvs",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="record DAVIS DVS events too (~20 s CPU per simulated second; default: off)",
    )
    p.add_argument(
        "--corpus",
        metavar="DIR",
        default=None,
        help=(
            "the motion corpus for the unseen-real DeMoCap figure (default: "
            "../shared/data/motion/corpus beside the clone, when there; else skipped)"
        ),
    )
    p.add_argument(
        "--real-frames",
        type=int,
        default=8,
        metavar="N",
        help="frames per test clip of the real-motion DeMoCap figures (11 clips; default: "
        "%(default)s; fewer for a quicker demo: that stage is about half its time)",
    )
    add_json_flag(p)
    p.set_defaults(func=_demo)


def _diff_mm(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f} mm"


def _unseen_real_line(ur: dict[str, Any]) -> str:
    if not ur:
        return "  DeMoCap unseen-real: not run (no motion corpus)"
    if "error" in ur:
        return f"  DeMoCap unseen-real: {ur['error']}"

    def inside_text(inside: dict[str, Any]) -> str:
        if inside["mpjpe_mm"] is None:
            return "no frame inside the view"
        return (
            f"inside the view ({100 * inside['share']:.0f} % of frames) MPJPE "
            f"{inside['mpjpe_mm']:.1f} mm, PCK@50 {100 * inside['pck50']:.1f} %"
        )

    solve = ", skeleton solve" if ur.get("solve") else ""
    lines = [
        (
            f"  DeMoCap [{ur['protocol']}] ({ur['config']}, corpus test split: "
            f"{len(ur['clips'])} real clips of unseen performers, {ur['num_cameras']} cameras, "
            f"{ur['rotations']}-turn ensemble{solve}, {ur['frames']} frames): "
            f"{inside_text(ur['inside_volume'])}; all frames {ur['mpjpe_mm']:.1f} mm, "
            f"{100 * ur['pck50']:.1f} %"
        )
    ]
    om = ur.get("off_model")
    if om:
        lines.append(
            f"  DeMoCap [{om['protocol']}] (the same clips on subjects the body model does not "
            f"mirror, {om['frames']} frames): {inside_text(om['inside_volume'])}; all frames "
            f"{om['mpjpe_mm']:.1f} mm, {100 * om['pck50']:.1f} %"
        )
        cal = om.get("subject_calibrated")
        if cal:
            lines.append(
                "  DeMoCap [off-model], each clip's subject calibrated from its frames "
                f"(segment lengths, marker placement): {inside_text(cal['inside_volume'])}; "
                f"all frames {cal['mpjpe_mm']:.1f} mm, {100 * cal['pck50']:.1f} %"
            )
    return "\n".join(lines)


def _demo(args: argparse.Namespace) -> int:
    from mocaprig.drivers_mock.demo import run_demo

    report = run_demo(
        args.out,
        scenario=args.scenario,
        seed=args.seed,
        seconds=args.seconds,
        overwrite=args.overwrite,
        progress=lambda label: ProgressBar(f"demo {label}"),
        cameras=args.cameras,
        davis_dvs=args.davis_dvs,
        corpus_dir=args.corpus,
        real_frames=args.real_frames,
    )
    failed = any(state.startswith("failed") for state in report.stages.values())
    if args.json:
        emit_json(report.to_dict())
        return 1 if failed else 0
    f = report.figures
    r = f["recording"]
    c = f.get("calibration", {})
    d = f.get("democap", {})
    ur = f.get("democap_unseen_real", {})
    rp = f.get("democap_replay", {})
    sj = f.get("democap_subject", {})
    lv = f.get("democap_live", {})
    pr = f.get("process", {})
    ec = f.get("eventcap", {})
    er = f.get("eventcap_run", {})
    lines = [
        f"mocaprig demo: scenario {f['scenario']!r}, seed {f['seed']}, {f['seconds']:g} s",
        "stages:",
        *(f"  {name:<20} {state}" for name, state in report.stages.items()),
        "figures:",
        (
            f"  Vicon C3D: {f['body_markers']} body + {f['clapper_markers']} clapperboard markers, "
            f"{f['vicon_frames']} frames at {f['vicon_rate_hz']:g} Hz"
        ),
        (
            f"  Vicon C3D read back vs truth: {f['vicon_error_rms_mm_per_axis']:.3f} mm RMS "
            "per axis "
            f"(noise set to {f['vicon_noise_sigma_set_mm']:.2f} mm), "
            f"{100 * f['vicon_gap_fraction']:.2f} % gaps"
        ),
        (
            f"  Nexus CSV vs C3D: max {f['csv_vs_c3d_max_abs_mm']:.4f} mm, "
            f"gaps agree: {f['csv_vs_c3d_gaps_agree']}"
        ),
        "  claps at: " + ", ".join(f"{t:.3f} s" for t in f["clap_times_s"]),
        (
            f"  session.mcap: {r['streams']} streams, {r['messages']} messages, "
            f"{r['drops']} dropped, {r['mb']:.0f} MB; D415 sync ok: {r.get('d415_sync_ok')} "
            f"(frames {r.get('d415_frames')})"
        ),
        (
            f"  DAVIS: DVS {r.get('davis_dvs')}, {r.get('davis_events')} events, "
            f"{r.get('davis_frames')} frames, {r.get('davis_imu_samples')} IMU samples, "
            f"{r.get('davis_trigger_pulses')} trigger pulses, {r.get('trigger_frame_pairs')} "
            "paired with D415 master frames"
        ),
        (
            f"  calibration vs truth: {c['cameras']} cameras, worst "
            f"{c['max_rotation_error_deg']:.3f} deg / {c['max_translation_error_mm']:.2f} mm, "
            f"D415 clock offset {c['max_d415_clock_offset_error_ms']:.3f} ms, drift "
            f"{c['max_d415_drift_error_ppm']:.1f} ppm, DAVIS-D415 "
            f"{c['davis_vs_d415_clock_error_us']:.2f} us"
            if "error" not in c and c
            else f"  calibration: {c.get('error', 'not run')}"
        ),
        (
            f"  DeMoCap [{d['protocol']}] ({d['config']}, held-out simulated takes, 4 cameras, "
            f"{d['rotations']}-turn "
            f"ensemble{', skeleton solve' if d.get('solve') else ''}): MPJPE "
            f"{d['mpjpe_mm']:.1f} mm, MPMPE {d['mpmpe_mm']:.1f} mm, PCK@50 "
            f"{100 * d['pck50']:.1f} % (the network alone: {d['network_mpjpe_mm']:.1f} mm, "
            f"{100 * d['network_pck50']:.1f} %; its single shot: "
            f"{d['single_shot_mpjpe_mm']:.1f} mm, {100 * d['single_shot_pck50']:.1f} %)"
            if "error" not in d and d
            else f"  DeMoCap: {d.get('error', 'not run')}"
        ),
        _unseen_real_line(ur),
        (
            f"  DeMoCap replay [{rp['protocol']}] of session.mcap ({rp['cameras']} D415s, "
            "1 instant in "
            f"{rp['every']}): {rp['instants']} instants, MPJPE {rp['mpjpe_mm']:.1f} mm, MPMPE "
            f"{rp['mpmpe_mm']:.1f} mm vs truth, {rp['mean_points_per_instant']:.0f} points per "
            f"cloud, {rp['seconds']:.1f} s"
            if "error" not in rp and rp
            else f"  DeMoCap replay: {rp.get('error', 'not run')}"
        ),
        (
            f"  DeMoCap subject from {sj['instants']} instants: standing height "
            f"{sj['standing_height_m']:.3f} m (true {sj['true_height_m']:.3f} m); the replay "
            f"solved as them (1 instant in {sj['replay_every']}): MPJPE {sj['mpjpe_mm']:.1f} mm, "
            f"MPMPE {sj['mpmpe_mm']:.1f} mm (frame by frame at the same instants "
            f"{sj['frame_by_frame_mpjpe_mm']:.1f} / {sj['frame_by_frame_mpmpe_mm']:.1f} mm)"
            if "error" not in sj and sj
            else f"  DeMoCap subject: {sj.get('error', 'not run')}"
        ),
        (
            f"  DeMoCap live [{lv['protocol']}] on the mock rig ({len(lv['cameras'])} D415s, "
            f"{lv['seconds']:g} s): "
            f"{lv['instants']} instants, MPJPE {lv.get('mpjpe_mm', float('nan')):.1f} mm vs "
            f"truth, {lv['drops']} dropped, {lv['fps']:.1f} instants/s (the simulator renders "
            "on this CPU)"
            if "error" not in lv and lv
            else f"  DeMoCap live: {lv.get('error', 'not run')}"
        ),
        (
            f"  mocaprig process ({pr['engine']}): DeMoCap on 1 instant in {pr['every']}, "
            f"{pr['instants']} instants in {pr['spans']} spans, {pr['outputs']} files in "
            f"{pr['seconds']:.1f} s, vs the unsplit replay at {pr['vs_replay_instants']} shared "
            f"instants: max {_diff_mm(pr['vs_replay_max_diff_mm'])} apart; run again: "
            f"{pr['rerun_kept']} kept, {pr['rerun_seconds']:.1f} s"
            if "error" not in pr and pr
            else f"  mocaprig process: {pr.get('error', 'not run')}"
        ),
        (
            f"  EventCap [{ec['protocol']}; {ec['detections']} detections] {ec['take']}, "
            f"{ec['batches']} batches: AE {ec['ours']['ae_mm']:.1f} mm (*_linear "
            f"{ec['linear']['ae_mm']:.1f}, *_all {ec['all']['ae_mm']:.1f}; ratio to linear "
            f"{ec['ae_ratio_to_linear']:.2f}), MPJPE {ec['ours']['mpjpe_mm']:.1f} mm, "
            f"{ec['seconds_per_batch']:.1f} s per 40 ms batch, "
            f"Size.sec {ec['size_sec_mb']:.2f} MB/s"
            if "error" not in ec and ec
            else f"  EventCap: {ec.get('error', 'not run')}"
        ),
        (
            f"  EventCap run on session.mcap [{er['protocol']}]: {er['batches']} batches, "
            f"{er['tracking_frames']} poses at 1 kHz, MPJPE {er['mpjpe_mm']:.1f} mm vs truth"
            if "error" not in er and er
            else f"  EventCap run: {er.get('error', report.stages.get('eventcap_run', 'not run'))}"
        ),
        "outputs:",
        f"  session (truth + Vicon C3D/CSV + session.mcap): {report.session_dir}",
        f"  calibration: {c.get('calibration_file', '-')}",
        f"  DeMoCap replay: {rp.get('results_mcap', '-')} (+ .c3d, .csv)",
        f"  DeMoCap subject: {sj.get('subject_file', '-')}",
        f"  DeMoCap live:   {lv.get('out', '-')}",
        f"  DeMoCap skeleton vs truth: {rp.get('skeleton_figure', '-')}",
        f"  mocaprig process: {pr.get('out', '-')}",
        f"  EventCap run:   {er.get('outputs', {}).get('mcap', '-')} (+ .c3d, .bvh)",
        f"  calibration report: {report.calibration_report_path or '-'}",
        f"  summary figure: {report.figure_path}",
        f"  report:         {report.report_path}",
    ]
    print("\n".join(lines))
    return 1 if failed else 0
