"""Running a recording session: open the rig's devices as sources, record them, close them.

:func:`run_recording` records the devices a rig file lists (or the simulated rig's mocks, or
given sources) into one MCAP file (or several when split) and closes what it opened;
:func:`record_to_file` is the recording step alone, for callers that open the devices themselves.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal, TextIO

from mocaprig.acquire.record_sources import DavisSource, DepthCameraSource, SyncBoxSource
from mocaprig.acquire.recorder import (
    Attachment,
    Recorder,
    StreamSource,
    record_sources,
    stop_on_signals,
)
from mocaprig.acquire.recording_format import RecorderStatus, StreamStatus
from mocaprig.acquire.rig_file import RigFile, load_rig_file
from mocaprig.errors import DeviceError, DeviceNotFoundError, ValidationError
from mocaprig.progress import StatusLine

__all__ = ["RecordingSummary", "record_to_file", "run_recording"]

_log = logging.getLogger(__name__)


class _StatusLine:
    """``record``'s live figures on the :class:`~mocaprig.progress.StatusLine`: per-stream rate
    and drops, MB/s, free disk."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self._line = StatusLine(stream=stream, interval_s=0.0)
        self._last: tuple[float, RecorderStatus] | None = None

    def __call__(self, st: RecorderStatus) -> None:
        now = time.monotonic()
        prev = self._last
        self._last = (now, st)
        if not self._line.enabled or prev is None:
            return
        dt = max(now - prev[0], 1e-6)
        before = {s.topic: s.written for s in prev[1].streams}
        parts = []
        for s in st.streams:
            if s.topic in ("/diagnostics", "/log"):
                continue
            rate = (s.written - before.get(s.topic, 0)) / dt
            short = s.topic.rsplit("/", 2)
            parts.append(f"{short[-2]}/{short[-1]} {rate:.0f}/s d{s.dropped}")
        mbps = (st.bytes_written - prev[1].bytes_written) / dt / 1e6
        self._line.show(
            f"{st.elapsed_ns / 1e9:6.1f}s {mbps:6.1f} MB/s free {st.free_disk_bytes / 1e9:.1f} GB "
            f"drops {st.dropped_total} | " + "  ".join(parts)
        )

    def done(self) -> None:
        self._line.done()


def _mock_sources(
    *,
    scenario: str,
    seed: int,
    seconds: float,
    cameras: int,
    syncbox: bool,
    stack: list[tuple[str, Any]],
) -> list[StreamSource]:
    from mocaprig.acquire.camera_backends import open_cameras
    from mocaprig.acquire.davis240c import Davis240C, load_mock_backend
    from mocaprig.acquire.depth_camera import SensorOptions, StreamConfig, SyncMode

    sources: list[StreamSource] = []
    # "asap": the DAVIS simulator cannot render in real time on a small machine.
    backend = load_mock_backend(scenario=scenario, seed=seed, pacing="asap", seconds=seconds + 5.0)
    cam = Davis240C.open(backend=backend)
    stack.append(("davis/" + cam.serial, cam))
    sources.append(DavisSource(cam))
    if cameras > 0:
        d415s = open_cameras(
            "mock", scenario=scenario, seed=seed, count=cameras, pacing="realtime",
            seconds=seconds + 5.0,
        )  # fmt: skip
        for i, d in enumerate(d415s):
            stack.append(("d415/" + d.info.serial, d))
            mode, opts = StreamConfig(), SensorOptions()
            d.configure(
                stream=mode,
                options=opts,
                sync_mode=SyncMode.MASTER if i == 0 else SyncMode.SLAVE,
            )
            sources.append(DepthCameraSource(d, stream=mode, options=opts))
    if syncbox:
        from mocaprig.acquire.syncbox import SyncBox, open_mock_syncbox

        mock_box = open_mock_syncbox(seed=seed)
        stack.append(("syncbox-mock", mock_box))
        box = SyncBox(mock_box.port)
        box.open()
        stack.append(("syncbox", box))
        sources.append(SyncBoxSource(box))
    return sources


_MOCK_D415_MAX = 4  # cameras of the simulated rig


def _rig_sources(
    rig: RigFile,
    *,
    scenario: str,
    seed: int,
    seconds: float,
    stack: list[tuple[str, Any]],
) -> list[StreamSource]:
    """Open the devices ``rig`` lists (real ones, or the simulated rig's mocks when
    ``rig.mock``), configured as the file says; opened devices go on ``stack`` (the caller
    closes them, also when this raises).

    Raises:
        DeviceError: a listed device is not connected (the message lists what is) or cannot be
            opened.
        ValidationError: a mock rig file asks for more cameras than the simulated rig has.
    """
    from mocaprig.acquire import camera_backends, davis240c
    from mocaprig.acquire.depth_camera import SyncMode

    sources: list[StreamSource] = []
    if rig.davis is not None:
        entry = rig.davis
        if rig.mock:
            backend = davis240c.load_mock_backend(
                scenario=scenario, seed=seed, pacing="asap", serial=entry.serial,
                seconds=seconds + 5.0,
            )  # fmt: skip
            cam = davis240c.Davis240C.open(backend=backend, bias_preset=entry.bias_preset)
        else:
            found = davis240c.find_davis()
            serials = sorted(d.serial or "?" for d in found)
            if entry.serial not in serials:
                msg = (
                    f"DAVIS {entry.serial} listed in {rig.source} is not connected; connected: "
                    f"{serials}; run `mocaprig devices`"
                )
                raise DeviceNotFoundError(msg)
            cam = davis240c.Davis240C.open(serial=entry.serial, bias_preset=entry.bias_preset)
        stack.append(("davis/" + cam.serial, cam))
        sources.append(DavisSource(cam))
    if rig.d415:
        if rig.mock:
            if len(rig.d415) > _MOCK_D415_MAX:
                msg = (
                    f"{rig.source} lists {len(rig.d415)} D415s but the simulated rig has "
                    f"{_MOCK_D415_MAX}; list at most {_MOCK_D415_MAX} with mock = true"
                )
                raise ValidationError(msg)
            found_cams = camera_backends.open_cameras(
                "mock", scenario=scenario, seed=seed, count=len(rig.d415), pacing="realtime",
                seconds=seconds + 5.0,
            )  # fmt: skip
            # The mocks carry the simulated rig's serials: rig-file cameras map onto them in
            # order (the rig-file serial is kept in the device metadata as rig_serial).
            pairs = list(zip(rig.d415, found_cams, strict=True))
        else:
            found_cams = camera_backends.open_cameras("realsense")
            by_serial = {c.info.serial: c for c in found_cams}
            missing = [e.serial for e in rig.d415 if e.serial not in by_serial]
            if missing:
                for c in found_cams:
                    c.close()
                msg = (
                    f"D415 {', '.join(missing)} listed in {rig.source} is not connected; "
                    f"connected: {sorted(by_serial)}; run `mocaprig devices`"
                )
                raise DeviceNotFoundError(msg)
            wanted = {e.serial for e in rig.d415}
            for c in found_cams:
                if c.info.serial not in wanted:
                    c.close()
            pairs = [(e, by_serial[e.serial]) for e in rig.d415]
        for _, d in pairs:
            stack.append(("d415/" + d.info.serial, d))
        # Slaves first: a slave configured after the master could miss its first pulses.
        for e, d in sorted(pairs, key=lambda p: p[0].role == "master"):
            mode = SyncMode.MASTER if e.role == "master" else SyncMode.SLAVE
            d.configure(stream=e.stream, options=e.options, sync_mode=mode)
        for e, d in pairs:
            src = DepthCameraSource(d, stream=e.stream, options=e.options)
            src.set_rig_entry(e.serial, e.role)
            sources.append(src)
    if rig.syncbox is not None:
        from mocaprig.acquire.syncbox import SyncBox, open_mock_syncbox

        sb = rig.syncbox
        if rig.mock:
            # The simulated master's pulses: its frame rate (or the file's rate without one).
            master = rig.master
            listen_hz = float(master.stream.fps if master is not None else sb.rate_hz)
            mock_box = open_mock_syncbox(seed=seed, listen_hz=listen_hz)
            stack.append(("syncbox-mock", mock_box))
            port = str(mock_box.port)
        else:
            port = sb.port
        box = SyncBox(port)
        try:
            box.open()
        except DeviceError as err:
            msg = f"sync box on {port} listed in {rig.source} cannot be opened: {err}"
            raise DeviceError(msg) from err
        stack.append(("syncbox", box))
        sources.append(SyncBoxSource(box, mode=sb.mode, hz=sb.rate_hz, width_us=sb.width_us))
    return sources


@dataclasses.dataclass(frozen=True, slots=True)
class RecordingSummary:
    """What :func:`record_to_file` recorded.

    Attributes:
        files: The file(s) written (several when split).
        stop_reason: Why the recording ended (:class:`mocaprig.acquire.recorder.StopReason` value).
        seconds: Host time recorded (s).
        bytes: Bytes written.
        drops_total: Messages dropped, all streams.
        streams: Final per-stream counters.
        hung_sources: Sources whose thread did not stop (their devices must not be closed).
    """

    files: tuple[Path, ...]
    stop_reason: str | None
    seconds: float
    bytes: int
    drops_total: int
    streams: tuple[StreamStatus, ...]
    hung_sources: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (what ``record --json`` prints)."""
        return {
            "files": [str(p) for p in self.files],
            "stop_reason": self.stop_reason,
            "seconds": self.seconds,
            "bytes": self.bytes,
            "drops_total": self.drops_total,
            "streams": [
                {"topic": s.topic, "messages": s.written, "drops": s.dropped} for s in self.streams
            ],
        }


def record_to_file(
    out: Path,
    sources: Sequence[StreamSource],
    *,
    seconds: float | None,
    followers: Sequence[StreamSource] = (),
    metadata: dict[str, dict[str, str]] | None = None,
    attachments: Sequence[Attachment] = (),
    compression: Literal["zstd", "lz4", "none"] = "lz4",
    split_seconds: float | None = None,
    split_mb: float | None = None,
    min_free_mb: float = 512.0,
    status_line: bool = False,
    handle_signals: bool = False,
) -> RecordingSummary:
    """Record ``sources`` (and ``followers``, see :func:`acquire.recorder.record_sources`) into
    ``out`` for ``seconds`` (``None``: until every source ends, for offline sources).

    The sources' ``metadata`` attributes are added to ``metadata``. Devices are not closed here.

    Raises:
        RecordingError: ``out`` exists, cannot be written, or the recording stopped early
            (disk full, write error; the file is finished and readable).
    """
    meta = dict(metadata or {})
    for src in [*sources, *followers]:
        meta.update(getattr(src, "metadata", {}) or {})
    recorder = Recorder(
        out,
        compression=compression,
        split_seconds=split_seconds,
        split_bytes=None if split_mb is None else int(split_mb * 1e6),
        min_free_disk_bytes=int(min_free_mb * 1e6),
        metadata=meta,
        attachments=attachments,
    )
    status = _StatusLine() if status_line else None
    guard = stop_on_signals(recorder) if handle_signals else contextlib.nullcontext()
    with recorder, guard:
        hung = record_sources(
            recorder, sources, seconds=seconds, on_status=status, followers=followers
        )
    if status is not None:
        status.done()
    final = recorder.status()
    return RecordingSummary(
        files=recorder.files,
        stop_reason=recorder.stop_reason.value if recorder.stop_reason else None,
        seconds=final.elapsed_ns / 1e9,
        bytes=final.bytes_written,
        drops_total=final.dropped_total,
        streams=final.streams,
        hung_sources=hung,
    )


def run_recording(
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
    sources: Sequence[StreamSource] | None = None,
) -> RecordingSummary:
    """Record the rig (a rig file's devices, the mock rig, or given ``sources``) into ``out``
    for ``seconds``, with the live status line (terminal only) and SIGINT/SIGTERM finishing the
    file (what ``mocaprig record`` runs).

    With ``rig``, the rig file is stored as the ``rig.toml`` attachment and its metadata as the
    ``rig`` and ``session`` records. The devices opened here are closed at the end, except those
    whose reader thread is stuck in a device call (logged).

    Returns:
        What was recorded; the recording ended as asked.

    Raises:
        ValidationError: ``seconds`` <= 0; neither ``rig`` nor ``mock`` (nor ``sources``); a bad
            rig file.
        DeviceError: a device the rig file lists is not connected or cannot be opened.
        RecordingError: ``out`` exists, cannot be written, or the recording stopped early.
    """
    if seconds <= 0:
        msg = f"--seconds must be > 0, got {seconds}"
        raise ValidationError(msg)
    stack: list[tuple[str, Any]] = []
    summary: RecordingSummary | None = None
    metadata: dict[str, dict[str, str]] = {}
    attachments: list[Attachment] = []
    try:
        if sources is None:
            if rig is not None:
                rig_file = load_rig_file(rig)
                sources = _rig_sources(
                    rig_file, scenario=scenario, seed=seed, seconds=seconds, stack=stack
                )
                metadata["rig"] = rig_file.metadata()
                metadata["session"] = {
                    "mock": str(rig_file.mock).lower(),
                    "rig_file": str(rig),
                    "name": rig_file.session_name,
                    "notes": rig_file.session_notes,
                    **({"scenario": scenario, "seed": str(seed)} if rig_file.mock else {}),
                }
                attachments.append(
                    Attachment("rig.toml", "application/toml", rig_file.text.encode("utf-8"))
                )
            elif not mock:
                msg = "say what to record: --mock (simulated rig) or --rig RIG.toml"
                raise ValidationError(msg)
            else:
                sources = _mock_sources(
                    scenario=scenario,
                    seed=seed,
                    seconds=seconds,
                    cameras=cameras,
                    syncbox=syncbox,
                    stack=stack,
                )
                metadata["session"] = {"mock": "true", "scenario": scenario, "seed": str(seed)}
        summary = record_to_file(
            out,
            sources,
            seconds=seconds,
            metadata=metadata,
            attachments=attachments,
            compression=compression,
            split_seconds=split_seconds,
            split_mb=split_mb,
            min_free_mb=min_free_mb,
            status_line=True,
            handle_signals=True,
        )
    finally:
        hung = summary.hung_sources if summary is not None else ()
        for name, dev in reversed(stack):
            if name in hung:
                _log.warning("not closing %s: its reader thread is stuck in a device call", name)
                continue
            try:
                dev.close()
            except Exception as err:  # closing must not hide the recording's outcome
                _log.warning("closing %s failed: %s", dev, err)
    return summary
