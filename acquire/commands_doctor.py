"""``mocaprig doctor``: check the capture PC and the rig, each finding with its fix."""

from __future__ import annotations

import argparse
import sys

from mocaprig.cli import add_json_flag, emit_json

__all__ = ["doctor", "register_doctor"]

_EPILOG = """\
Checks, in order: libusb; each DAVIS (udev permissions, chip and logic, a short stream with
drop counts); each D415 (firmware for hardware sync, USB 3 link, per-frame metadata) and the
sync cable (a short check-sync: is every slave really triggered?); the sync box (protocol,
pulses counted in LISTEN). Each line is ok, warn or fix, and a fix says what to do. Exit code
0 when nothing needs fixing, 1 otherwise.

examples:
  mocaprig doctor                                  the devices plugged into this PC
  mocaprig doctor --json                           one JSON object with every finding
  mocaprig doctor --mock                           the simulated rig (all ok)
  mocaprig doctor --mock --fault d415:slave-trigger-cut --fault syncbox:unwired
"""


def doctor(*, mock: bool, faults: list[str], seconds: float, listen_s: float, as_json: bool) -> int:
    """Handler of ``mocaprig doctor``: 0 when nothing needs a fix, 1 otherwise."""
    from mocaprig.acquire.doctor import Finding, run_doctor

    def show(f: Finding) -> None:
        if not as_json:
            print(f"{f.verdict.value:<5} {f.subject:<24} {f.check:<9} {f.detail}", flush=True)

    report = run_doctor(
        mock=mock, faults=faults, seconds=seconds, listen_s=listen_s, on_finding=show
    )
    if as_json:
        emit_json(report.as_dict())
        return 0 if report.ok else 1
    todo: dict[str, list[str]] = {}  # one line per fix, naming everything it applies to
    for f in report.findings:
        if f.fix and f.verdict.value != "ok":
            todo.setdefault(f.fix, []).append(f"{f.subject} {f.check}")
    if todo:
        print("\nto do:")
        for fix, where in todo.items():
            print(f"  {', '.join(where)}:\n      {fix}")
    print("\nready" if report.ok else "\nnot ready: fix the lines marked 'fix'", file=sys.stderr)
    return 0 if report.ok else 1


def register_doctor(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``mocaprig doctor``."""
    from mocaprig.acquire.doctor import DOCTOR_FAULTS

    p = subparsers.add_parser(
        "doctor",
        help="check this PC and the rig (libusb, permissions, firmware, USB, metadata, sync)",
        description="Check the capture PC and every device of the rig; each finding with its fix.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--mock", action="store_true", help="check the simulated rig")
    p.add_argument(
        "--fault",
        action="append",
        default=[],
        choices=DOCTOR_FAULTS,
        metavar="DEVICE:FAULT",
        help=f"with --mock: inject a fault (repeatable): {', '.join(DOCTOR_FAULTS)}",
    )
    p.add_argument(
        "--seconds", type=float, default=2.0, help="length of the D415 sync check (default 2)"
    )
    p.add_argument(
        "--listen-seconds",
        type=float,
        default=1.0,
        help="how long the sync box counts pulses (default 1)",
    )
    add_json_flag(p)
    p.set_defaults(
        func=lambda a: doctor(
            mock=a.mock,
            faults=a.fault,
            seconds=a.seconds,
            listen_s=a.listen_seconds,
            as_json=a.json,
        )
    )
