"""``mocaprig d415 …``: list D415 cameras, stream them, verify their hardware sync.

Thin shell over typed functions returning an exit code (house style habit 19). ``--mock`` loads
the simulated cameras through the ``mocaprig.mocks`` entry point ``d415``; ``acquire`` never
imports ``drivers_mock`` itself.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from mocaprig.acquire.camera_backends import open_cameras
from mocaprig.acquire.d415_sync import (
    SyncFlag,
    SyncHealth,
    SyncReport,
    capture,
    configure_rig,
    run_sync_check,
    start_rig,
)
from mocaprig.acquire.depth_camera import DepthCamera, FrameSet, SensorOptions, StreamConfig
from mocaprig.acquire.realsense import METADATA_HINT
from mocaprig.cli import add_json_flag, emit_json, usage_handler
from mocaprig.errors import ValidationError
from mocaprig.progress import current_progress_mode

__all__ = ["check_sync", "list_cameras", "register_d415", "stream"]

_log = logging.getLogger(__name__)

_EPILOG = """\
examples:
  mocaprig d415 list --json                         serials, firmware, USB link
  mocaprig d415 stream --seconds 5                  live fps and drops per camera
  mocaprig d415 check-sync --seconds 10             is every slave locked to the master?
  mocaprig d415 check-sync --mock --seconds 10 --json
  mocaprig d415 check-sync --mock --mock-fault slave-trigger-cut --seconds 10

The first camera (sorted by serial, or --master) is the sync master (inter_cam_sync_mode 1),
the others slaves (2); see docs/wiring.md for the sync cable.
"""


def _parse_mode(text: str) -> StreamConfig:
    try:
        size, fps = text.split("@")
        width, height = size.lower().split("x")
        return StreamConfig(width=int(width), height=int(height), fps=int(fps))
    except ValueError as err:
        msg = f"mode {text!r}: expected WIDTHxHEIGHT@FPS, e.g. 848x480@30 ({err})"
        raise argparse.ArgumentTypeError(msg) from err


def _open(*, mock: bool, seed: int, fault: str | None, seconds: float | None) -> list[DepthCamera]:
    """The real cameras, or the mock rig (``no-metadata`` as a fault emulates a kernel without
    the metadata patch)."""
    if fault is not None and not mock:
        msg = "--mock-fault needs --mock"
        raise ValidationError(msg)
    if not mock:
        return open_cameras("realsense")
    options: dict[str, Any] = {"seed": seed, "fault": fault, "images": False}
    if seconds is not None:
        # The simulated session outlasts the capture and is long enough for its clapperboard.
        options["seconds"] = max(seconds + 1.0, 3.0)
    return open_cameras("mock", **options)


def _close(cameras: Sequence[DepthCamera]) -> None:
    for cam in cameras:
        cam.close()


def list_cameras(*, mock: bool = False, seed: int = 0, as_json: bool = False) -> int:
    """``mocaprig d415 list``."""
    cameras = _open(mock=mock, seed=seed, fault=None, seconds=None)
    try:
        rows = [
            {
                "serial": c.info.serial,
                "name": c.info.name,
                "firmware": c.info.firmware,
                "usb_type": c.info.usb_type,
                "product_line": c.info.product_line,
            }
            for c in cameras
        ]
    finally:
        _close(cameras)
    if as_json:
        emit_json({"cameras": rows})
    elif not rows:
        print("no D415 found (check USB 3 cabling; `rs-enumerate-devices` lists what the SDK sees)")
    else:
        for r in rows:
            print(f"{r['serial']}  {r['name']}  fw {r['firmware']}  USB {r['usb_type']}")
    return 0


@dataclass
class _Rate:
    frames: int = 0
    drops: int = 0
    last_counter: int | None = None
    first_ns: int | None = None
    last_ns: int | None = None
    window_frames: int = 0


def stream(
    *,
    seconds: float,
    mode: StreamConfig | None = None,
    options: SensorOptions | None = None,
    mock: bool = False,
    seed: int = 0,
    fault: str | None = None,
    allow_no_metadata: bool = False,
    as_json: bool = False,
) -> int:
    """``mocaprig d415 stream``: fps and counter-gap drops per camera, live and at the end.

    Synced cameras without frame metadata are refused unless ``allow_no_metadata``.
    """
    cameras = _open(mock=mock, seed=seed, fault=fault, seconds=seconds)
    rates: dict[str, _Rate] = {c.info.serial: _Rate() for c in cameras}
    next_print = [1.0]
    t0: list[int] = []
    live_lines = not as_json and current_progress_mode() != "never"  # quiet under -q

    def on_frameset(fs: FrameSet) -> None:
        r = rates[fs.serial]
        counter, now = fs.timing.frame_counter, fs.timing.host_time_ns
        if r.last_counter is not None and counter > r.last_counter + 1:
            r.drops += counter - r.last_counter - 1
        r.last_counter = counter
        r.frames += 1
        r.window_frames += 1
        r.first_ns = now if r.first_ns is None else r.first_ns
        r.last_ns = now
        if not t0:
            t0.append(now)
        if live_lines and (now - t0[0]) / 1e9 >= next_print[0]:
            next_print[0] += 1.0
            line = "  ".join(
                f"{s}: {v.window_frames:3d} fps {v.drops} drops" for s, v in rates.items()
            )
            print(f"t={(now - t0[0]) / 1e9:5.1f}s  {line}", file=sys.stderr)
            for v in rates.values():
                v.window_frames = 0

    try:
        configure_rig(cameras, stream=mode, options=options, allow_no_metadata=allow_no_metadata)
        start_rig(cameras)
        try:
            capture(cameras, seconds=seconds, on_frameset=on_frameset)
        finally:
            for cam in cameras:
                cam.stop()
    finally:
        _close(cameras)
    result: dict[str, Any] = {}
    for serial, r in rates.items():
        span = None if r.first_ns is None or r.last_ns is None else (r.last_ns - r.first_ns) / 1e9
        fps = (r.frames - 1) / span if span else None
        result[serial] = {"frames": r.frames, "drops": r.drops, "fps": fps}
    if as_json:
        emit_json({"seconds": seconds, "cameras": result})
    else:
        for serial, v in result.items():
            fps_text = "n/a" if v["fps"] is None else f"{v['fps']:.2f}"
            print(f"{serial}: {v['frames']} framesets, {fps_text} fps, {v['drops']} dropped")
    return 0


def _print_report(report: SyncReport) -> None:
    print(f"sync {'OK' if report.ok else 'FAILED'} over {report.duration_s:.1f} s")
    for serial, c in report.cameras.items():
        parts = [f"{serial} {c.role.name.lower():7s} {c.frames} frames, {c.drops} drops"]
        if c.drift_ppm is not None:
            parts.append(f"drift {c.drift_ppm:+.1f} ppm")
        if c.walk_ppm is not None:
            parts.append(f"walk {c.walk_ppm:+.1f} ppm ({c.rate_reference})")
        if c.max_phase_error_us is not None:
            parts.append(f"max phase error {c.max_phase_error_us:.0f} µs")
        if c.free_running_since_s is not None:
            parts.append(f"FREE-RUNNING since {c.free_running_since_s:.2f} s")
        if c.flags:
            parts.append("flags: " + ", ".join(f.value for f in c.flags))
        print("  " + "; ".join(parts))
    flags = {f for c in report.cameras.values() for f in c.flags}
    if SyncFlag.NO_HARDWARE_TIMESTAMPS in flags:
        print(f"no hardware timestamps: {METADATA_HINT}")
    if SyncFlag.FREE_RUNNING in flags:
        print(
            "free-running: a synced slave's hardware timestamps drift slowly against the "
            "master's and its exposures do not walk against them; check the sync cable "
            "(docs/wiring.md)"
        )
    if SyncFlag.SYNC_UNVERIFIED in flags:
        print("sync-unverified: the crystals agree; verify with the LED test (docs/d415-timing.md)")
    if SyncFlag.TOO_SHORT in flags:
        print("too-short: run longer (--seconds 10) for the rate check")


def check_sync(
    *,
    seconds: float,
    mode: StreamConfig | None = None,
    options: SensorOptions | None = None,
    mock: bool = False,
    seed: int = 0,
    fault: str | None = None,
    external_trigger: bool = False,
    as_json: bool = False,
) -> int:
    """``mocaprig d415 check-sync``: 0 when every camera is locked, 1 otherwise."""
    cameras = _open(mock=mock, seed=seed, fault=fault, seconds=seconds)

    live_lines = not as_json and current_progress_mode() != "never"  # quiet under -q

    def live(h: SyncHealth) -> None:
        if not live_lines:
            return
        states = []
        for s, c in h.cameras.items():
            lock = {None: "-", True: "locked", False: "FREE-RUNNING"}[c.locked]
            states.append(f"{s} {lock} {c.drops} drops")
        print(f"t={h.elapsed_s:5.1f}s  " + "  ".join(states), file=sys.stderr)

    try:
        report = run_sync_check(
            cameras,
            seconds=seconds,
            stream=mode,
            options=options,
            on_health=live,
            external_trigger=external_trigger,
        )
    finally:
        _close(cameras)
    if as_json:
        emit_json(report.to_dict())
    else:
        _print_report(report)
    return 0 if report.ok else 1


# ---------------------------------------------------------------------------------------------


def _add_common(p: argparse.ArgumentParser, *, capture_opts: bool) -> None:
    p.add_argument("--mock", action="store_true", help="use the simulated cameras")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated world (--mock)")
    if capture_opts:
        p.add_argument(
            "--mock-fault",
            metavar="FAULT",
            help="fault injected into the mock, e.g. slave-trigger-cut or drops:rate=0.05",
        )
        p.add_argument("--seconds", type=float, default=10.0, help="capture length (default 10)")
        p.add_argument(
            "--mode",
            type=_parse_mode,
            default=StreamConfig(),
            help="848x480@30 (default), 1280x720@30 or 848x480@90",
        )
        p.add_argument(
            "--exposure-us",
            type=int,
            default=SensorOptions().exposure_us,
            help="manual exposure in µs (default %(default)s; at most the frame period)",
        )
        p.add_argument(
            "--gain", type=int, default=SensorOptions().gain, help="16..248 (default %(default)s)"
        )
        p.add_argument(
            "--laser-power",
            type=int,
            default=SensorOptions().laser_power_mw,
            help="projector power, 0..360 mW in steps of 30 (default %(default)s)",
        )
    add_json_flag(p)


def _options(args: argparse.Namespace) -> SensorOptions:
    return SensorOptions(
        exposure_us=args.exposure_us, gain=args.gain, laser_power_mw=args.laser_power
    )


def register_d415(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``mocaprig d415 {list,stream,check-sync}``."""
    parser = sub.add_parser(
        "d415",
        help="RealSense D415 cameras: list, stream, verify hardware sync",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    d415 = parser.add_subparsers(dest="d415_command", metavar="SUBCOMMAND")

    parser.set_defaults(func=usage_handler(parser))

    raw = argparse.RawDescriptionHelpFormatter
    p_list = d415.add_parser(
        "list",
        help="connected D415 cameras",
        description="List the connected D415s: serial, name, firmware, USB link.",
        epilog="examples:\n  mocaprig d415 list\n  mocaprig d415 list --json\n"
        "  mocaprig d415 list --mock          the simulated rig's four cameras\n",
        formatter_class=raw,
    )
    _add_common(p_list, capture_opts=False)
    p_list.set_defaults(func=lambda a: list_cameras(mock=a.mock, seed=a.seed, as_json=a.json))

    p_stream = d415.add_parser(
        "stream",
        help="stream every camera; live fps and drops",
        description="Stream every camera (first = sync master): live fps and counter drops.",
        epilog="examples:\n  mocaprig d415 stream --seconds 5\n"
        "  mocaprig d415 stream --seconds 10 --mode 848x480@90 --json\n"
        "  mocaprig d415 stream --mock --mock-fault drops --seconds 5\n",
        formatter_class=raw,
    )
    _add_common(p_stream, capture_opts=True)
    p_stream.add_argument(
        "--allow-no-metadata",
        action="store_true",
        help="stream synced cameras even without per-frame metadata (no hardware counters or "
        "timestamps: sync unverifiable, drops invisible; the fix is the RealSense kernel patch "
        "or the RSUSB backend)",
    )
    p_stream.set_defaults(
        func=lambda a: stream(
            seconds=a.seconds,
            mode=a.mode,
            options=_options(a),
            mock=a.mock,
            seed=a.seed,
            fault=a.mock_fault,
            allow_no_metadata=a.allow_no_metadata,
            as_json=a.json,
        )
    )

    p_check = d415.add_parser(
        "check-sync",
        help="verify hardware sync (counters, drift, free-running slaves); exit 1 if bad",
        description="Verify on the stream that every slave is locked to the master.",
        epilog="examples:\n  mocaprig d415 check-sync --seconds 10\n"
        "  mocaprig d415 check-sync --external-trigger --seconds 10   all slaves of the box\n"
        "  mocaprig d415 check-sync --mock --mock-fault slave-trigger-cut --seconds 10 --json\n",
        formatter_class=raw,
    )
    _add_common(p_check, capture_opts=True)
    p_check.add_argument(
        "--external-trigger",
        action="store_true",
        help="every camera is a slave of the sync box (docs/wiring.md topology B)",
    )
    p_check.set_defaults(
        func=lambda a: check_sync(
            seconds=a.seconds,
            mode=a.mode,
            options=_options(a),
            mock=a.mock,
            seed=a.seed,
            fault=a.mock_fault,
            external_trigger=a.external_trigger,
            as_json=a.json,
        )
    )
