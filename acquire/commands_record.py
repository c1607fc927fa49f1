"""``mocaprig record | info | recover | export | import-events``: the recording commands.

Each ``register_*`` function is a ``mocaprig.commands`` entry point; each command is a typed
function returning an exit code. The work is done by library modules: the record sources
(:mod:`mocaprig.acquire.record_sources`), the session runner
(:mod:`mocaprig.acquire.record_session`), RPG events text (:mod:`mocaprig.acquire.rpg_text`) and
the export to files (:mod:`mocaprig.acquire.export`); device modules are imported lazily.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from mocaprig.acquire.export import ExportFormat, ExportResult, export_topic
from mocaprig.acquire.live_view import LiveView, load_live_scene
from mocaprig.acquire.mocks import load_mock_factory
from mocaprig.acquire.record_session import MockFaults, RecordingSummary, run_recording
from mocaprig.acquire.recorder import StreamSource
from mocaprig.acquire.rpg_text import import_events_txt
from mocaprig.cli import add_json_flag, emit_json
from mocaprig.errors import ValidationError
from mocaprig.progress import ProgressBar

if TYPE_CHECKING:
    from mocaprig.acquire.recording import RecordingInfo, TimeBase

__all__ = [
    "export",
    "import_events",
    "info_layout",
    "record",
    "record_outcome",
    "recording_info",
    "recover_command",
    "register_export",
    "register_import_events",
    "register_info",
    "register_record",
    "register_recover",
]

_Sub = "argparse._SubParsersAction[argparse.ArgumentParser]"


# -------------------------------------------------------------------------------------------
# record


def record(
    *,
    out: Path,
    seconds: float,
    mock: bool,
    rig: Path | None,
    scenario: str = "default",
    seed: int = 0,
    cameras: int = 1,
    syncbox: bool = True,
    compression: Literal["zstd", "lz4", "none"] = "lz4",
    split_seconds: float | None = None,
    split_mb: float | None = None,
    min_free_mb: float = 512.0,
    as_json: bool = False,
    sources: Sequence[StreamSource] | None = None,
    mock_faults: MockFaults | str | None = None,
    live: bool = False,
    live_port: int = 8765,
    live_host: str = "127.0.0.1",
    live_calibration: Path | None = None,
) -> int:
    """``mocaprig record``: record the rig (a rig file's devices, the mock rig, or given
    ``sources``) into ``out`` (:func:`mocaprig.acquire.record_session.run_recording`).

    ``mock_faults``: faults to inject into the mock rig, a schedule or its text
    (``--mock-faults``, loaded through the ``mocaprig.mocks`` entry point ``faults``).
    ``live``: serve the streams to Foxglove on ``live_host:live_port`` while recording
    (:class:`mocaprig.acquire.live_view.LiveView`; RecordingError when foxglove-sdk is missing
    or the port is taken). ``live_calibration``: with ``live``, the measured markers, the fused
    cloud and the DeMoCap joints in 3D (the ``mocaprig.live_scene`` entry point ``democap``;
    ValidationError without ``live``).

    Returns the exit code of :func:`record_outcome` (0: as asked; 3: a device was lost, its
    streams have gaps; 128 + the signal: stopped by SIGINT/SIGTERM); a full disk or a write
    error raises RecordingError (the file is finished, or ends at its last complete record).
    """
    faults: MockFaults | None = (
        load_mock_factory("faults")(mock_faults) if isinstance(mock_faults, str) else mock_faults
    )
    if live_calibration is not None and not live:
        msg = "--calib shows the markers and joints on the live view: it needs --live"
        raise ValidationError(msg)
    scene = load_live_scene("democap", live_calibration) if live_calibration is not None else None
    view = LiveView(host=live_host, port=live_port, scene=scene) if live else None
    with view if view is not None else contextlib.nullcontext():
        if view is not None:
            print(f"live view: {view.url} (Foxglove: Open connection -> Foxglove WebSocket)",
                  file=sys.stderr, flush=True)  # fmt: skip
        summary = run_recording(
            out=out,
            seconds=seconds,
            mock=mock,
            rig=rig,
            scenario=scenario,
            seed=seed,
            cameras=cameras,
            syncbox=syncbox,
            compression=compression,
            split_seconds=split_seconds,
            split_mb=split_mb,
            min_free_mb=min_free_mb,
            sources=sources,
            mock_faults=faults,
            live=view,
        )
    code, line = record_outcome(summary)
    if as_json:
        emit_json({**summary.as_dict(), "exit_code": code, "outcome": line})
    else:
        print(line)
        for st in summary.streams:
            print(f"  {st.topic:<36} {st.written:>8} msgs  {st.dropped:>6} dropped")
        if summary.live is not None:
            lv = summary.live
            print(f"live view: {lv.published_total} messages published, {lv.dropped_total} of "
                  "its own dropped (the recording's drops are above)")  # fmt: skip
    return code


def record_outcome(summary: RecordingSummary) -> tuple[int, str]:
    """The exit code and the one line that say how a recording ended.

    0: as asked; 3: a device was lost (its streams have a gap; the faults are in the file);
    128 + signal number (130 SIGINT, 143 SIGTERM): stopped by a signal, the file finished.
    """
    files = ", ".join(str(p) for p in summary.files)
    done = (
        f"{summary.seconds:.1f} s, {summary.bytes / 1e6:.1f} MB, {summary.drops_total} dropped "
        f"-> {files}"
    )
    lost = summary.device_faults
    back = {f.device for f in summary.faults if f.kind == "reconnected"}
    devices = sorted({f.device for f in lost})
    faults = ""
    if devices:
        words = [f"{d} lost{' and back' if d in back else ''}" for d in devices]
        faults = f"; {len(lost)} device fault(s): {', '.join(words)} (`mocaprig info` lists them)"
    if summary.signal is not None:
        signum = int(getattr(signal.Signals, summary.signal, signal.SIGTERM))
        return 128 + signum, f"stopped by {summary.signal}: recorded {done}, file finished{faults}"
    if lost:
        return 3, f"recorded {done}{faults}"
    return 0, f"recorded {done}"


# -------------------------------------------------------------------------------------------
# info / recover


def recording_info(path: Path, *, as_json: bool) -> int:
    """``mocaprig info``: topics, counts, rates, drops, counter gaps, chunks."""
    from mocaprig.acquire.recording import info

    bar = ProgressBar(f"info {path.name}", unit="kB")
    inf = info(path, progress=lambda done, total: bar(done // 1000, total // 1000))
    bar.finish()
    d = inf.as_dict()
    if as_json:
        emit_json(d)
        return 0
    state = "indexed" if inf.indexed else "NO SUMMARY (crashed or unfinished)"
    if inf.recovered:
        state += ", recovered"
    print(f"{path}: format {inf.format_version}, {state}, stop: {inf.stop_reason}")
    print(
        f"  duration {inf.duration_s:.3f} s, {inf.scan.complete_chunks} complete chunks, "
        f"{inf.scan.bad_chunks} bad, truncated: {inf.scan.truncated} "
        f"({inf.scan.bytes_unread} bytes unread)"
    )
    if inf.mixed_time_bases:
        print(_mixed_time_bases_line(inf))
    print(f"  {'topic':<36} {'schema':<26} {'msgs':>8} {'rate Hz':>9} {'drops':>6} {'gaps':>6}")
    for s in inf.streams:
        drops = "?" if s.drops is None else str(s.drops)
        print(
            f"  {s.topic:<36} {s.schema_name:<26} {s.messages:>8} {s.rate_hz:>9.1f} "
            f"{drops:>6} {s.counter_gaps:>6}"
        )
    t0 = inf.start_ns or 0
    for f in inf.faults:
        print(f"  fault: {(f.t_ns - t0) / 1e9:+8.3f} s  {f.device:<24} {f.kind}: {f.detail}")
    for g in inf.gaps:
        until = f"{(g.end_ns - t0) / 1e9:.3f} s" if g.back else "the end (never back)"
        print(
            f"  gap: {g.device:<24} {(g.start_ns - t0) / 1e9:.3f} s .. {until} ({g.seconds:.3f} s)"
        )
    for name in inf.devices:
        print(f"  device: {name}")
    for a in inf.attachments:
        print(f"  attachment: {a}")
    return 0


def info_layout(path: Path, out: Path | None, *, overwrite: bool, as_json: bool) -> int:
    """``mocaprig info FILE --layout [OUT.json]``: write the Foxglove layout for the file
    (:func:`mocaprig.acquire.layout.write_layout`) and print its path."""
    from mocaprig.acquire.layout import write_layout

    res = write_layout(path, out, overwrite=overwrite)
    if as_json:
        emit_json({"layout": str(res.path), "use": res.use, "panels": res.panels})
    else:
        print(f"{res.path}: {res.use} layout, {res.panels} panels")
    return 0


def _clock_words(name: str) -> str:
    return "Unix time" if name == "unix" else "a relative clock"


def _span_words(b: TimeBase) -> str:
    span = f"{(b.end_ns - b.start_ns) / 1e9:.3f} s"
    if b.name == "unix":
        start = datetime.datetime.fromtimestamp(b.start_ns / 1e9, tz=datetime.UTC)
        return f"from {start:%Y-%m-%d %H:%M:%S} UTC, {span}"
    return f"{b.start_ns / 1e9:.3f} .. {b.end_ns / 1e9:.3f} s"


def _mixed_time_bases_line(inf: RecordingInfo) -> str:
    """The warning ``mocaprig info`` prints for a file whose streams are on different clocks."""
    main = inf.time_bases[0]
    parts = "; ".join(
        f"{', '.join(b.topics)} on {_clock_words(b.name)} ({_span_words(b)})"
        for b in inf.time_bases
    )
    return (
        f"  WARNING: mixed time bases (a file written before one clock per file): {parts}; "
        f"the duration is that of {_clock_words(main.name)} ({', '.join(main.topics)}); "
        "times of the other streams cannot be compared with it"
    )


def recover_command(src: Path, out: Path, *, as_json: bool) -> int:
    """``mocaprig recover``: exit 0 = nothing lost, 3 = something lost, 1 = nothing found."""
    from mocaprig.acquire.recording import recover

    bar = ProgressBar(f"recover {src.name}", unit="kB")
    rep = recover(src, out, progress=lambda done, total: bar(done // 1000, total // 1000))
    bar.finish()
    code = 0 if rep.lossless else (3 if rep.messages else 1)
    if as_json:
        emit_json(
            {
                "source": str(src),
                "output": str(out),
                "messages": rep.messages,
                "metadata_records": rep.metadata_records,
                "attachments": rep.attachments,
                "complete_chunks": rep.scan.complete_chunks,
                "bad_chunks": rep.scan.bad_chunks,
                "truncated": rep.scan.truncated,
                "bytes_unread": rep.scan.bytes_unread,
                "lossless": rep.lossless,
            }
        )
    else:
        print(
            f"{out}: {rep.messages} messages from {rep.scan.complete_chunks} complete chunks; "
            f"{rep.scan.bad_chunks} bad chunks, {rep.scan.bytes_unread} bytes unread"
            + ("" if rep.lossless else " (lossy)")
        )
    return code


# -------------------------------------------------------------------------------------------
# import-events / export


def import_events(
    src: Path,
    out: Path,
    *,
    width: int | None,
    height: int | None,
    serial: str = "imported",
    packet_us: int = 10_000,
    epoch_ns: int = 0,
    as_json: bool = False,
) -> int:
    """``mocaprig import-events``: an RPG events text file into a recording
    (:func:`mocaprig.acquire.rpg_text.import_events_txt`), every message on the file's clock
    shifted by ``epoch_ns``."""
    bar = ProgressBar(f"import {src.name}", unit="packets")
    imp = import_events_txt(
        src,
        out,
        width=width,
        height=height,
        serial=serial,
        packet_us=packet_us,
        epoch_ns=epoch_ns,
        progress=bar,
    )
    bar.finish()
    if as_json:
        emit_json({"output": str(out), "events": imp.events, "packets": imp.packets})
    else:
        print(f"{out}: {imp.events} events in {imp.packets} packets ({imp.width}x{imp.height})")
    return 0


def export(
    path: Path,
    *,
    topic_name: str,
    fmt: ExportFormat,
    out: Path,
    fps: float = 30.0,
    txt_header: bool = False,
) -> int:
    """``mocaprig export``: one topic to npz / txt (events) / png (images) / mp4 (images)
    (:func:`mocaprig.acquire.export.export_topic`).

    ``txt`` writes RPG ``t x y p`` lines with the stored ns times (9 decimals) and, only with
    ``txt_header``, a first ``width height`` line.
    """
    unit = {"txt": "events", "npz": "arrays"}.get(fmt, "images")
    bar = ProgressBar(f"export {topic_name}", unit=unit)
    res = export_topic(
        path,
        topic_name=topic_name,
        fmt=fmt,
        out=out,
        fps=fps,
        txt_header=txt_header,
        progress=bar,
    )
    bar.finish()
    print(_export_summary(res))
    return 0


def _export_summary(res: ExportResult) -> str:
    """The line ``export`` prints about what it wrote."""
    if res.fmt == "txt":
        return f"{res.out}: {res.count} events"
    if res.fmt == "npz":
        return f"{res.out}: {', '.join(f'{k} {shape}' for k, shape in res.shapes)}"
    if res.fmt == "png":
        return f"{res.out}: {res.count} PNG files"
    return f"{res.out}: {res.count} frames at {res.fps} fps (8-bit, scaled per frame)"


# -------------------------------------------------------------------------------------------
# argparse


def _parser(sub: Any, name: str, help_: str, examples: str) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        name,
        help=help_,
        description=help_,
        epilog="examples:\n" + examples,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    return p


def register_record(subparsers: Any) -> None:
    """Entry point: ``mocaprig record``."""
    p = _parser(
        subparsers,
        "record",
        "record a session into MCAP (live status line; Ctrl-C finishes the file)",
        "  mocaprig record --rig rig.toml --seconds 60 --out session.mcap\n"
        "  mocaprig record --rig dry-run.toml --seconds 5 --out dry.mcap   # mock = true\n"
        "  mocaprig record --mock --seconds 10 --out session.mcap\n"
        "  mocaprig record --mock --scenario default --cameras 2 --seconds 5 --out s.mcap\n"
        "  mocaprig record --mock --seconds 600 --split-seconds 60 --out long.mcap\n"
        "  mocaprig record --rig rig.toml --seconds 60 --out s.mcap --live   # Foxglove live\n"
        "  mocaprig record --mock --cameras 4 --seconds 30 --out s.mcap --live --port 8766\n"
        "  mocaprig record --mock --seconds 5 --out f.mcap \\\n"
        "      --mock-faults davis-unplug@1+0.5,d415-disconnect@2+1,syncbox-unplug@1.5+0.5\n"
        "\nA device lost while recording (unplugged, cable pulled) is re-opened when it comes\n"
        "back and goes on in the same file; every fault and gap is in the file (/faults,\n"
        "`mocaprig info` lists them). Exit 0: as asked; 3: a device was lost (gaps); 130/143:\n"
        "stopped by SIGINT/SIGTERM, file finished; 1: error (a full disk: the file is\n"
        "finished, or ends at its last complete record).\n"
        "\n--live serves the streams to Foxglove (Open connection -> Foxglove WebSocket,\n"
        "ws://127.0.0.1:8765): D415 IR/depth and DAVIS frames at <= 15 Hz per camera, a 33 ms\n"
        "event image, IMU plots, /live/status; it reads behind the recorder and drops its own\n"
        "frames, never the recording's (needs foxglove-sdk: pip install 'mocaprig[live]').\n",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--rig", type=Path, help="rig file (TOML) listing the devices (docs/rig-file.md)"
    )
    src.add_argument("--mock", action="store_true", help="record the simulated rig")
    p.add_argument("--scenario", default="default", help="mock scenario name")
    p.add_argument("--seed", type=int, default=0, help="mock world seed")
    p.add_argument("--cameras", type=int, default=1, help="--mock: D415 count (0..4)")
    p.add_argument("--no-syncbox", action="store_true", help="--mock: without the sync box")
    p.add_argument("--seconds", type=float, required=True, help="recording length (s)")
    p.add_argument("--out", type=Path, required=True, help="output .mcap (never overwritten)")
    p.add_argument("--compression", choices=["lz4", "zstd", "none"], default="lz4")
    p.add_argument("--split-seconds", type=float, help="start a new numbered file every N s")
    p.add_argument("--split-mb", type=float, help="start a new numbered file every N MB")
    p.add_argument("--min-free-mb", type=float, default=512.0, help="stop when less is free")
    p.add_argument(
        "--mock-faults",
        metavar="SPEC",
        help="mock rig only: inject faults, KIND@AT[+FOR][:TARGET] comma-separated (s), kinds "
        "davis-unplug, d415-disconnect, syncbox-unplug, disk-full",
    )
    p.add_argument(
        "--live",
        action="store_true",
        help="serve the streams to Foxglove over WebSocket while recording (docs/live-view.md)",
    )
    p.add_argument("--port", type=int, default=8765, help="--live: TCP port (0: any free port)")
    p.add_argument(
        "--calib",
        type=Path,
        default=None,
        metavar="CALIB.toml",
        help="--live: also the measured markers and DeMoCap joints in 3D (a rig calibration)",
    )
    p.add_argument(
        "--live-host",
        default="127.0.0.1",
        help="--live: address to listen on (0.0.0.0: every interface; default local only)",
    )
    add_json_flag(p)
    p.set_defaults(
        func=lambda a: record(
            out=a.out,
            seconds=a.seconds,
            mock=a.mock,
            rig=a.rig,
            scenario=a.scenario,
            seed=a.seed,
            cameras=a.cameras,
            syncbox=not a.no_syncbox,
            compression=a.compression,
            split_seconds=a.split_seconds,
            split_mb=a.split_mb,
            min_free_mb=a.min_free_mb,
            as_json=a.json,
            mock_faults=a.mock_faults,
            live=a.live,
            live_port=a.port,
            live_host=a.live_host,
            live_calibration=a.calib,
        )
    )


def register_info(subparsers: Any) -> None:
    """Entry point: ``mocaprig info``."""
    p = _parser(
        subparsers,
        "info",
        "summarise a recording: streams, counts, rates, drops, counter gaps, chunks",
        "  mocaprig info session.mcap\n  mocaprig info crashed.mcap --json\n"
        "\nThe duration and times are those of one clock. A file whose streams are on different\n"
        "clocks (Unix time and a relative clock; older imports) gets a WARNING line naming the\n"
        "streams on each, and mixed_time_bases / time_bases in --json.\n"
        "\n--layout writes a Foxglove layout for the file instead of the summary: a recording\n"
        "check (D415 IR + depth per camera, DAVIS frames, drops, frame counters, sync pulses,\n"
        "recorder status and log), a calibration review (a recording with calibration.toml\n"
        "attached), a DeMoCap replay or an EventCap run (3D panel), with the file's own\n"
        "topics. Default OUT: FILE without .mcap + .layout.json, next to it. In Foxglove:\n"
        "open the file, then Layouts -> Import from file... and pick OUT.json.\n"
        "  mocaprig info session.mcap --layout\n"
        "  mocaprig info results.mcap --layout replay.json --overwrite\n",
    )
    p.add_argument("file", type=Path, help="recording (.mcap), finished or crashed")
    p.add_argument(
        "--layout",
        nargs="?",
        const="",
        default=None,
        metavar="OUT.json",
        help="write the Foxglove layout for FILE (default OUT: FILE.layout.json next to it)",
    )
    p.add_argument("--overwrite", action="store_true", help="--layout: replace OUT.json")
    add_json_flag(p)
    p.set_defaults(
        func=lambda a: (
            recording_info(a.file, as_json=a.json)
            if a.layout is None
            else info_layout(
                a.file, Path(a.layout) if a.layout else None, overwrite=a.overwrite, as_json=a.json
            )
        )
    )


def register_recover(subparsers: Any) -> None:
    """Entry point: ``mocaprig recover``."""
    p = _parser(
        subparsers,
        "recover",
        "rewrite a crashed recording with a full index (exit 3 when data was lost)",
        "  mocaprig recover crashed.mcap fixed.mcap\n",
    )
    p.add_argument("input", type=Path, help="recording without a summary (crash, kill)")
    p.add_argument("output", type=Path, help="new file (never overwritten)")
    add_json_flag(p)
    p.set_defaults(func=lambda a: recover_command(a.input, a.output, as_json=a.json))


def register_export(subparsers: Any) -> None:
    """Entry point: ``mocaprig export``."""
    p = _parser(
        subparsers,
        "export",
        "export one topic: npz (any array topic), txt (events, RPG 't x y p'), png/mp4 (images)",
        "  mocaprig export s.mcap --topic /davis/00000042/events --format txt --out ev.txt\n"
        "  mocaprig export s.mcap --topic /davis/00000042/events --format txt --txt-header \\\n"
        "      --out ev_e2vid.txt\n"
        "  mocaprig export s.mcap --topic /davis/00000042/imu --format npz --out imu.npz\n"
        "  mocaprig export s.mcap --topic /d415/123/depth --format png --out depth_png/\n"
        "  mocaprig export s.mcap --topic /d415/123/ir --format mp4 --out ir.mp4\n",
    )
    p.add_argument("file", type=Path)
    p.add_argument("--topic", required=True)
    p.add_argument("--format", choices=["npz", "txt", "png", "mp4"], required=True)
    p.add_argument("--out", type=Path, required=True, help="file (folder for png)")
    p.add_argument("--fps", type=float, default=30.0, help="mp4 frame rate")
    p.add_argument(
        "--txt-header",
        action="store_true",
        help="txt: write a first 'width height' line (E2VID-style tools); RPG files have none",
    )
    p.set_defaults(
        func=lambda a: export(
            a.file,
            topic_name=a.topic,
            fmt=a.format,
            out=a.out,
            fps=a.fps,
            txt_header=a.txt_header,
        )
    )


def register_import_events(subparsers: Any) -> None:
    """Entry point: ``mocaprig import-events``."""
    p = _parser(
        subparsers,
        "import-events",
        "import an RPG events text file (t x y p; optional 'width height' first line)",
        "  mocaprig import-events events.txt --out events.mcap\n"
        "  mocaprig import-events events.txt --out e.mcap --width 346 --height 260\n"
        "  mocaprig import-events events.txt --out e.mcap --epoch-ns 1589163147355806000\n"
        "\nEvery message of the file is on the file's clock: log_time = epoch + the file's "
        "time\n(default epoch 0: the file's own time; give the Unix time of its t = 0 to put "
        "it on\nUnix time).\n",
    )
    p.add_argument("file", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--width", type=int, help="sensor width (default: file header, else 240)")
    p.add_argument("--height", type=int, help="sensor height (default: file header, else 180)")
    p.add_argument("--serial", default="imported", help="name used in the topic")
    p.add_argument(
        "--epoch-ns",
        type=int,
        default=0,
        help="Unix time (ns) of the file's t = 0, added to every log_time (default 0)",
    )
    add_json_flag(p)
    p.set_defaults(
        func=lambda a: import_events(
            a.file,
            a.out,
            width=a.width,
            height=a.height,
            serial=a.serial,
            epoch_ns=a.epoch_ns,
            as_json=a.json,
        )
    )
