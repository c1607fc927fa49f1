"""``mocaprig vicon ...``: commands over Vicon reference files (C3D, Nexus CSV).

Registered through the ``mocaprig.commands`` entry point ``vicon``. Handlers import
:mod:`mocaprig.calib.vicon` (numpy, ezc3d) lazily so ``mocaprig --help`` stays fast.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from mocaprig.cli import add_json_flag, emit_json, usage_handler

if TYPE_CHECKING:
    from mocaprig.calib.vicon import MarkerTrajectories

__all__ = ["register_vicon", "vicon_info", "vicon_info_summary"]

_VICON_EPILOG = """\
examples:
  mocaprig vicon info trial.c3d                  labels, rate, frames, gaps, extent
  mocaprig vicon info trial.c3d --json           the same as one JSON object
  mocaprig vicon info old.c3d --unit mm          POINT:UNITS missing or unreadable: say the unit
  mocaprig vicon info trial.csv --unit mm        Workstation CSV (no units row)
  mocaprig vicon info trial.c3d --keep-virtual   include model outputs and Plug-in Gait bones
"""

_INFO_EPILOG = """\
A C3D file is checked structurally first and decoded in a child process, so a malformed file
gives an error message, never a crash. Positions are reported in metres whatever the file's unit.

examples:
  mocaprig vicon info trial.c3d
  mocaprig vicon info trial.c3d --json | jq .labels
  mocaprig vicon info export.csv --unit mm --keep-unlabeled
"""


def register_vicon(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``vicon`` and its sub-commands to the ``mocaprig`` parser."""
    vicon = subparsers.add_parser(
        "vicon",
        help="inspect Vicon reference files (C3D, Nexus CSV)",
        description="Inspect Vicon reference files (C3D, Nexus CSV).",
        epilog=_VICON_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    vsub = vicon.add_subparsers(dest="vicon_command", metavar="SUBCOMMAND")
    vicon.set_defaults(func=usage_handler(vicon))

    info = vsub.add_parser(
        "info",
        help="what a C3D or Nexus CSV file holds",
        description="Summarise the marker trajectories of a C3D or Nexus CSV file.",
        epilog=_INFO_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    info.add_argument("file", metavar="FILE", help="a .c3d file or a Nexus CSV export")
    info.add_argument(
        "--unit",
        choices=("mm", "cm", "m"),
        default=None,
        help="unit of the file's coordinates when the file does not say (overrides POINT:UNITS)",
    )
    info.add_argument(
        "--keep-virtual",
        action="store_true",
        help="keep model outputs (angles, forces, ...) and virtual points (PELO, ...)",
    )
    info.add_argument(
        "--keep-unlabeled",
        action="store_true",
        help="keep unlabelled trajectories named *NN",
    )
    add_json_flag(info)
    info.set_defaults(func=vicon_info)


def vicon_info_summary(traj: MarkerTrajectories) -> dict[str, Any]:
    """The ``vicon info`` fields of a record, as plain JSON-able values (NaN → None later)."""
    meta = traj.metadata
    return {
        "file": traj.source,
        "format": meta.get("format"),
        "labels": list(traj.labels),
        "markers": traj.n_markers,
        "rate_hz": traj.rate_hz,
        "frames": traj.n_frames,
        "first_frame": traj.first_frame,
        "duration_s": traj.duration_s,
        "source_unit": traj.source_unit,
        "gap_fraction": traj.gap_fraction,
        "extent_m": traj.extent_m,
        "manufacturer": meta.get("manufacturer"),
        "software": meta.get("software"),
        "software_version": meta.get("software_version"),
        "reader": meta.get("reader"),
        "processor": meta.get("processor"),
        "storage": meta.get("storage"),
        "point_scale": float(meta["point_scale"]) if "point_scale" in meta else None,
    }


_PROCESSOR_NAMES = {
    "intel": "Intel (little-endian, IEEE floats)",
    "dec": "DEC VAX (little-endian, VAX floats)",
    "sgi": "SGI/MIPS (big-endian, IEEE floats)",
}


def _storage_line(summary: dict[str, Any]) -> str | None:
    """The ``storage:`` line of a C3D file: processor type and how points are stored."""
    proc = summary["processor"]
    if proc is None:
        return None
    scale = summary["point_scale"]
    if summary["storage"] == "int":
        how = f"16-bit integers x POINT:SCALE {scale:g} {summary['source_unit']}"
    else:
        how = "32-bit floats" + (f" (POINT:SCALE -{scale:g})" if scale is not None else "")
    return f"  storage:   {_PROCESSOR_NAMES.get(proc, proc)}, {how}"


def vicon_info(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig vicon info``: print a summary (text or JSON); return 0."""
    from mocaprig.calib.vicon import read_trajectories

    traj = read_trajectories(
        args.file,
        unit=args.unit,
        keep_virtual=args.keep_virtual,
        keep_unlabeled=args.keep_unlabeled,
        isolate=True,
    )
    summary = vicon_info_summary(traj)
    if args.json:
        emit_json(summary)
        return 0
    software = " ".join(
        str(summary[k]) for k in ("manufacturer", "software", "software_version") if summary[k]
    )
    extent = summary["extent_m"]
    labels = summary["labels"]
    shown = ", ".join(labels[:8]) + (f", ... (+{len(labels) - 8})" if len(labels) > 8 else "")
    lines = [
        f"{traj.source}  ({summary['format']}{', ' + software if software else ''})",
        f"  markers:   {summary['markers']}  [{shown}]",
        (
            f"  frames:    {summary['frames']} at {summary['rate_hz']:g} Hz "
            f"({summary['duration_s']:.2f} s, first frame {summary['first_frame']})"
        ),
        f"  unit:      {summary['source_unit']} in the file (reported in m)",
        *([line] if (line := _storage_line(summary)) else []),
        f"  gaps:      {100 * summary['gap_fraction']:.1f} % of samples",
        f"  extent:    {'n/a' if extent != extent else f'{extent:.3f} m'} (bounding-box diagonal)",
    ]
    print("\n".join(lines))
    return 0
