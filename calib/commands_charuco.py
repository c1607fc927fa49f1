"""``mocaprig calibrate intrinsics | board``: ChArUco calibration from a recording.

:mod:`mocaprig.calib.commands_calibrate` creates the ``calibrate`` group and calls
:func:`add_intrinsics_parser` and :func:`add_board_parser`. The handlers are thin layers over
:func:`calibrate_intrinsics_command` and :func:`calibrate_board_command` (typed, returning an exit
code), which read images only through :class:`mocaprig.acquire.recording.Recording` and call
:mod:`calib.charuco`. Images: D415 left IR (``/d415/<serial>/ir``, emitter off) and DAVIS APS
frames (``/davis/<serial>/frame``). Views of different cameras are paired by their log time (the
recording PC's one clock), so hold the board still for longer than ``--max-skew-ms``.
"""

from __future__ import annotations

import argparse
import datetime
import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mocaprig.acquire.device_id import DeviceId
from mocaprig.cli import add_json_flag, emit_json
from mocaprig.errors import CalibrationError, ValidationError
from mocaprig.progress import ProgressBar

if TYPE_CHECKING:
    from mocaprig.calib.charuco import BoardView, CharucoBoardSpec

__all__ = [
    "add_board_parser",
    "add_intrinsics_parser",
    "calibrate_board_command",
    "calibrate_intrinsics_command",
    "camera_topic",
    "read_board_views",
]

_log = logging.getLogger(__name__)

_INTRINSICS_EPILOG = """\
Detects the ChArUco board (CharucoDetector -> matchImagePoints) in every image of one camera and
runs cv2.calibrateCamera. Record 30+ views: the board filling a third to two thirds of the image
(the DAVIS: most of it, close up), tilted 20-45 degrees about different axes, over the whole
image including its corners. The fit is refused (exit 1) with fewer than --min-views usable
views, corners covering less than 35 % of the image, no tilted view, or an RMS above --max-rms-px
unless --force.

board.toml:
  [board]
  squares_x = 6
  squares_y = 5
  square_length_m = 0.15      # measured on the print
  marker_length_m = 0.1125
  dictionary = "DICT_4X4_50"
  legacy_pattern = false      # true for pre-OpenCV-4.6 prints with an even row count

examples:
  mocaprig calibrate intrinsics --board board.toml --write-board board.png     to print
  mocaprig calibrate intrinsics s.mcap --camera d415/819612070593 --board board.toml \
      --out d415.toml
  mocaprig calibrate intrinsics s.mcap --camera davis/02460013 --board board.toml \
      --out davis.toml --json
"""

_BOARD_EPILOG = """\
Extrinsics from board views shared in time, intrinsics fixed (from `calibrate intrinsics`):
per view solvePnP, a pose graph through the shared instants, then one least-squares refinement of
all camera and board poses (soft_l1, 3-sigma rejection, refit). Views of different cameras
within --max-skew-ms of log time count as one instant: hold the board still at each pose.
World frame: the first --intrinsics camera (default) or, with --world board, the board at the
instant seen by the most cameras. Refused (exit 1) when a camera shares no view with the others
or the RMS exceeds --max-rms-px, unless --force.

examples:
  mocaprig calibrate board s.mcap --board board.toml --intrinsics d415.toml davis.toml \
      --out calib.toml
  mocaprig calibrate board s.mcap --board board.toml --intrinsics a.toml b.toml c.toml \
      --world board --out calib.json --json
"""


def camera_topic(label: str) -> str:
    """The image topic of a camera label: ``d415/<serial>`` → ``/d415/<serial>/ir``,
    ``davis/<serial>`` → ``/davis/<serial>/frame``.

    Raises:
        ValidationError: another label form.
    """
    try:
        dev = DeviceId.parse(label)
    except ValidationError as err:
        msg = f"camera {label!r}: give it as d415/<serial> or davis/<serial>"
        raise ValidationError(msg) from err
    if dev.kind == "syncbox":
        msg = f"camera {label!r}: give it as d415/<serial> or davis/<serial>"
        raise ValidationError(msg)
    return dev.topic("ir" if dev.kind == "d415" else "frame")


def read_board_views(
    session: Path,
    camera: str,
    spec: CharucoBoardSpec,
    *,
    every: int = 1,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[list[BoardView], tuple[int, int]]:
    """Detect the board in every ``every``-th image of one camera of a recording
    (``progress``: ``(images_done, images_total)``).

    Returns:
        The views (stamped with the log time, ns; empty views where the board was not seen)
        and the image size ``(width, height)``.

    Raises:
        RecordingError: the recording is unreadable or lacks the camera's topic (the message
            lists the topics).
        CalibrationError: the topic holds no image.
    """
    from mocaprig.acquire.device_streams import devices
    from mocaprig.acquire.recording import Recording
    from mocaprig.calib.charuco import detect_charuco

    if every < 1:
        msg = f"--every must be >= 1, got {every}"
        raise ValidationError(msg)
    topic = camera_topic(camera)
    views: list[BoardView] = []
    size: tuple[int, int] | None = None
    with Recording(session) as rec:
        if topic not in rec.topics:
            cams = [d.label for d in devices(rec) if d.kind != "syncbox"]
            msg = f"{session} has no images of camera {camera!r} ({topic}); cameras: {cams}"
            raise CalibrationError(msg)
        total = sum(1 for _ in rec.messages(topic))
        reported = 0
        for i, (t_ns, msg_img) in enumerate(rec.images(topic)):
            if i % every:
                continue
            img = msg_img.image
            size = (int(img.shape[1]), int(img.shape[0]))
            views.append(detect_charuco(img, spec, t_ns=int(t_ns)))
            if progress is not None:
                progress(i + 1, total)
                reported = i + 1
        if progress is not None and reported < total:
            progress(total, total)  # the images skipped by ``every`` are done too
    if size is None:
        msg = f"{session}: topic {topic} holds no image; nothing to calibrate {camera!r} from"
        raise CalibrationError(msg)
    return views, size


def calibrate_intrinsics_command(
    session: Path | None,
    *,
    camera: str | None,
    board: Path,
    out: Path | None,
    write_board: Path | None = None,
    overwrite: bool = False,
    every: int = 1,
    min_views: int = 8,
    max_rms_px: float = 1.0,
    fit_k3: bool = False,
    force: bool = False,
    as_json: bool = False,
) -> int:
    """``mocaprig calibrate intrinsics``: one camera's intrinsics; returns the exit code."""
    from mocaprig.calib.charuco import (
        board_image,
        calibrate_intrinsics,
        read_board_spec,
        write_intrinsics,
    )

    spec = read_board_spec(board)
    summary: dict[str, Any] = {"board": spec.to_dict()}
    if write_board is not None:
        import cv2

        if write_board.exists() and not overwrite:
            msg = f"{write_board} exists; pass --overwrite to replace it"
            raise ValidationError(msg)
        img = board_image(spec)
        if not cv2.imwrite(str(write_board), img):
            msg = f"cannot write the board image to {write_board} (unknown image suffix?)"
            raise ValidationError(msg)
        w_m, h_m = spec.size_m
        summary["board_image"] = str(write_board)
        if not as_json:
            print(
                f"board image -> {write_board} ({img.shape[1]}×{img.shape[0]} px); print the "
                f"squares at {w_m * 1000:.0f}×{h_m * 1000:.0f} mm and measure square_length_m"
            )
    if session is None:
        if write_board is None:
            msg = "give SESSION.mcap (and --camera, --out), or --write-board to print the board"
            raise ValidationError(msg)
        if as_json:
            emit_json(summary)
        return 0
    if camera is None or out is None:
        msg = "calibrating a camera needs --camera d415/<serial>|davis/<serial> and --out FILE"
        raise ValidationError(msg)
    if out.exists() and not overwrite:
        msg = f"{out} exists; pass --overwrite to replace it"
        raise ValidationError(msg)
    views, size = read_board_views(
        session, camera, spec, every=every, progress=ProgressBar("detect", unit="images")
    )
    result = calibrate_intrinsics(
        views,
        size,
        spec,
        camera=camera,
        fix_k3=not fit_k3,
        min_views=min_views,
        max_rms_px=max_rms_px,
        force=force,
    )
    write_intrinsics(out, result, overwrite=overwrite)
    summary.update(
        {
            "camera": camera,
            "out": str(out),
            "images": len(views),
            "views_used": result.n_views,
            "corners": result.n_corners,
            "width": result.width,
            "height": result.height,
            "fx": float(result.K[0, 0]),
            "fy": float(result.K[1, 1]),
            "cx": float(result.K[0, 2]),
            "cy": float(result.K[1, 2]),
            "distortion": result.distortion.tolist(),
            "rms_px": result.rms_px,
            "coverage": result.coverage,
            "max_tilt_deg": result.max_tilt_deg,
            "sigma": dict(result.sigma),
        }
    )
    if as_json:
        emit_json(summary)
    else:
        k = result.K
        print(
            f"{camera}: fx {k[0, 0]:.2f} fy {k[1, 1]:.2f} cx {k[0, 2]:.2f} cy {k[1, 2]:.2f} px, "
            f"distortion {', '.join(f'{d:.4f}' for d in result.distortion)}"
        )
        print(
            f"  RMS {result.rms_px:.3f} px over {result.n_views} views ({result.n_corners} "
            f"corners, {len(views)} images), coverage {result.coverage:.0%} -> {out}"
        )
    return 0


def calibrate_board_command(
    session: Path,
    *,
    board: Path,
    intrinsics: Sequence[Path],
    out: Path,
    world: str = "camera",
    max_skew_ms: float = 5.0,
    every: int = 1,
    max_rms_px: float = 1.5,
    force: bool = False,
    overwrite: bool = False,
    as_json: bool = False,
) -> int:
    """``mocaprig calibrate board``: camera poses from shared board views; returns the exit code."""
    from mocaprig import __version__
    from mocaprig.calib.calibration import write_calibration
    from mocaprig.calib.charuco import calibrate_extrinsics, read_board_spec, read_intrinsics

    if out.suffix not in (".toml", ".json"):
        msg = f"--out {out}: a calibration file is .toml or .json"
        raise ValidationError(msg)
    if out.exists() and not overwrite:
        msg = f"{out} exists; pass --overwrite to replace it"
        raise ValidationError(msg)
    if world not in ("camera", "board"):
        msg = f"--world must be 'camera' or 'board', got {world!r}"
        raise ValidationError(msg)
    spec = read_board_spec(board)
    intr = {}
    for p in intrinsics:
        r = read_intrinsics(p)
        if not r.camera:
            msg = f"intrinsics file {p} names no camera; re-run `calibrate intrinsics --camera`"
            raise CalibrationError(msg)
        if r.camera in intr:
            msg = f"two intrinsics files for camera {r.camera!r}; give one per camera"
            raise ValidationError(msg)
        intr[r.camera] = r
    views = {}
    for cam in intr:
        v, size = read_board_views(
            session, cam, spec, every=every, progress=ProgressBar(cam, unit="images")
        )
        if size != (intr[cam].width, intr[cam].height):
            msg = (
                f"camera {cam}: images are {size[0]}×{size[1]} but its intrinsics are for "
                f"{intr[cam].width}×{intr[cam].height}; calibrate the intrinsics in this mode"
            )
            raise CalibrationError(msg)
        views[cam] = v
    cal = calibrate_extrinsics(
        views,
        intr,
        max_skew_ns=round(max_skew_ms * 1e6),
        world="board" if world == "board" else "camera",
        max_rms_px=max_rms_px,
        force=force,
        software_version=__version__,
        created_utc=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    )
    write_calibration(cal, out, overwrite=overwrite)
    summary = {
        "out": str(out),
        "world_frame": cal.world_frame,
        "statistics": dict(cal.statistics),
        "cameras": [
            {
                "name": c.name,
                "T_world_cam": c.T_world_cam.tolist(),
                "residuals": dict(c.residuals),
            }
            for c in cal.cameras
        ],
    }
    if as_json:
        emit_json(summary)
    else:
        print(
            f"{len(cal.cameras)} cameras, {cal.statistics['shared_views']:.0f} shared views, "
            f"RMS {cal.statistics['reprojection_rms_px']:.3f} px, world = {cal.world_frame} "
            f"-> {out}"
        )
        for c in cal.cameras:
            res = c.residuals
            print(
                f"  {c.name:<22} RMS {res['reprojection_rms_px']:.3f} px  views "
                f"{res['views']:.0f}  σ {res['rotation_sigma_deg']:.3f}° "
                f"{res['translation_sigma_mm']:.1f} mm  centre "
                + ", ".join(f"{x:+.3f}" for x in c.T_world_cam[:3, 3])
                + " m"
            )
    return 0


# --------------------------------------------------------------------------------------------
# argparse


def _intrinsics_handler(args: argparse.Namespace) -> int:
    return calibrate_intrinsics_command(
        args.session,
        camera=args.camera,
        board=args.board,
        out=args.out,
        write_board=args.write_board,
        overwrite=args.overwrite,
        every=args.every,
        min_views=args.min_views,
        max_rms_px=args.max_rms_px,
        fit_k3=args.fit_k3,
        force=args.force,
        as_json=args.json,
    )


def _board_handler(args: argparse.Namespace) -> int:
    return calibrate_board_command(
        args.session,
        board=args.board,
        intrinsics=args.intrinsics,
        out=args.out,
        world=args.world,
        max_skew_ms=args.max_skew_ms,
        every=args.every,
        max_rms_px=args.max_rms_px,
        force=args.force,
        overwrite=args.overwrite,
        as_json=args.json,
    )


def add_intrinsics_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``intrinsics`` to the ``calibrate`` group."""
    p = subparsers.add_parser(
        "intrinsics",
        help="one camera's intrinsics from ChArUco views in a recording",
        description="Calibrate a D415 (left IR) or DAVIS (APS) camera from ChArUco board views.",
        epilog=_INTRINSICS_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("session", metavar="SESSION.mcap", type=Path, nargs="?", default=None)
    p.add_argument("--camera", help="d415/<serial> or davis/<serial>")
    p.add_argument("--board", type=Path, required=True, help="board description (TOML)")
    p.add_argument("--out", type=Path, help="intrinsics file to write (TOML)")
    p.add_argument("--write-board", type=Path, metavar="PNG", help="write the printable board")
    p.add_argument("--every", type=int, default=1, help="use every N-th image (default 1)")
    p.add_argument("--min-views", type=int, default=8, help="fewest usable views (default 8)")
    p.add_argument(
        "--max-rms-px", type=float, default=1.0, help="refuse a larger RMS (default 1.0 px)"
    )
    p.add_argument("--fit-k3", action="store_true", help="fit k3 too (default: k3 = 0)")
    p.add_argument("--force", action="store_true", help="accept a fit above --max-rms-px")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    add_json_flag(p)
    p.set_defaults(func=_intrinsics_handler)


def add_board_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``board`` to the ``calibrate`` group."""
    p = subparsers.add_parser(
        "board",
        help="camera poses from ChArUco views shared by several cameras (no Vicon)",
        description="Extrinsics of D415 and DAVIS cameras from shared ChArUco board views.",
        epilog=_BOARD_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("session", metavar="SESSION.mcap", type=Path)
    p.add_argument("--board", type=Path, required=True, help="board description (TOML)")
    p.add_argument(
        "--intrinsics", type=Path, nargs="+", required=True, metavar="INTR.toml",
        help="intrinsics files of the cameras (the first is the reference)",
    )  # fmt: skip
    p.add_argument("--out", type=Path, required=True, help="calibration file (.toml or .json)")
    p.add_argument(
        "--world", choices=("camera", "board"), default="camera",
        help="world frame: the first camera (default) or the board",
    )  # fmt: skip
    p.add_argument(
        "--max-skew-ms", type=float, default=5.0,
        help="views closer in log time are one instant (default 5 ms)",
    )  # fmt: skip
    p.add_argument("--every", type=int, default=1, help="use every N-th image (default 1)")
    p.add_argument(
        "--max-rms-px", type=float, default=1.5, help="refuse a larger RMS (default 1.5 px)"
    )
    p.add_argument("--force", action="store_true", help="accept a solution above --max-rms-px")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    add_json_flag(p)
    p.set_defaults(func=_board_handler)
