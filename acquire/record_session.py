"""Running a recording session: open the rig's devices as sources, record them, close them.

:func:`run_recording` records the devices a rig file lists (or the simulated rig's mocks, or
given sources) into one MCAP file (or several when split) and closes what it opened;
:func:`record_to_file` is the recording step alone, for callers that open the devices themselves.

Every device is opened with a way to open it again (by serial, as configured), so a device lost
mid-recording is re-opened when it comes back (:mod:`mocaprig.acquire.record_sources`). On the
mock rig, :class:`MockFaults` (``drivers_mock.faults.FaultSchedule``) wraps the mocks' real
boundaries (pyusb backend, depth camera, serial port, output file) to inject faults.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, BinaryIO, Literal, Protocol, TextIO

from mocaprig.acquire.live_view import LiveStats, LiveView
from mocaprig.acquire.record_sources import DavisSource, DepthCameraSource, SyncBoxSource
from mocaprig.acquire.recorder import (
    RECORDER_TOPICS,
    Attachment,
    Fault,
    Recorder,
    StreamSource,
    record_sources,
    stop_on_signals,
)
from mocaprig.acquire.recording_format import RecorderStatus, StreamStatus
from mocaprig.acquire.rig_file import RigFile, load_rig_file
from mocaprig.errors import DeviceError, DeviceNotFoundError, ValidationError
from mocaprig.progress import StatusLine

__all__ = ["MockFaults", "RecordingSummary", "record_to_file", "run_recording"]

_log = logging.getLogger(__name__)


class MockFaults(Protocol):
    """Fault injection at the mock rig's real boundaries (``drivers_mock.faults.FaultSchedule``;
    acquire never imports it). Each method wraps one boundary; fault times count from
    :meth:`start`, called when the recording starts."""

    def start(self) -> None:
        """Start the fault clock (idempotent)."""
        ...

    def davis_backend(self, backend: Any) -> Any:
        """The DAVIS mock's pyusb ``IBackend`` behind the fault proxy."""
        ...

    def depth_camera(self, cam: Any) -> Any:
        """A mock D415 (``DepthCamera``) behind the fault proxy."""
        ...

    def find_depth_camera(self, serial: str) -> Any:
        """The D415 ``serial`` again after it was lost (DeviceNotFoundError while it is not)."""
        ...

    def serial_port(self, port: str) -> str:
        """A ``serial.serial_for_url`` URL reaching ``port`` through the fault proxy."""
        ...

    def open_file(self, path: Path, mode: str) -> BinaryIO:
        """The recorder's output file, through the fault proxy (``Recorder(open_file=...)``)."""
        ...


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
            if s.topic in RECORDER_TOPICS:
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
    faults: MockFaults | None = None,
) -> list[StreamSource]:
    from mocaprig.acquire.camera_backends import open_cameras
    from mocaprig.acquire.davis240c import load_mock_backend
    from mocaprig.acquire.depth_camera import SensorOptions, StreamConfig, SyncMode

    sources: list[StreamSource] = []
    # "asap": the DAVIS simulator cannot render in real time on a small machine.
    backend = load_mock_backend(scenario=scenario, seed=seed, pacing="asap", seconds=seconds + 5.0)
    if faults is not None:
        backend = faults.davis_backend(backend)
    sources.append(_davis_source(stack, backend=backend))
    if cameras > 0:
        d415s = open_cameras(
            "mock", scenario=scenario, seed=seed, count=cameras, pacing="realtime",
            seconds=seconds + 5.0,
        )  # fmt: skip
        for i, d in enumerate(d415s):
            if faults is not None:
                d = faults.depth_camera(d)
            stack.append(("d415/" + d.info.serial, d))
            mode, opts = StreamConfig(), SensorOptions()
            d.configure(
                stream=mode,
                options=opts,
                sync_mode=SyncMode.MASTER if i == 0 else SyncMode.SLAVE,
            )
            sources.append(
                DepthCameraSource(d, stream=mode, options=opts, reopen=_d415_finder(d, faults))
            )
    if syncbox:
        from mocaprig.acquire.syncbox import SyncBox, open_mock_syncbox

        mock_box = open_mock_syncbox(seed=seed)
        stack.append(("syncbox-mock", mock_box))
        port = str(mock_box.port)
        box = SyncBox(port if faults is None else faults.serial_port(port))
        box.open()
        stack.append(("syncbox", box))
        sources.append(SyncBoxSource(box))
    return sources


def _davis_source(
    stack: list[tuple[str, Any]], *, bias_preset: Any = None, **where: Any
) -> DavisSource:
    """Open a DAVIS (``where``: ``backend=`` or ``serial=``) as a source that re-opens it by
    serial, with the same biases, after it was lost."""
    from mocaprig.acquire.davis240c import Davis240C

    preset = {} if bias_preset is None else {"bias_preset": bias_preset}
    cam = Davis240C.open(**where, **preset)
    stack.append(("davis/" + cam.serial, cam))
    again = {**where, "serial": cam.serial, **preset}
    return DavisSource(cam, reopen=lambda: Davis240C.open(**again))


def _d415_finder(cam: Any, faults: MockFaults | None) -> Callable[[], Any] | None:
    """How to find the D415 ``cam`` again after it was lost: the fault proxy's enumeration on
    the mock rig with faults; None for a mock without them (it is never lost)."""
    if faults is None:
        return None
    serial = str(cam.info.serial)
    return lambda: faults.find_depth_camera(serial)


def _realsense_finder(serial: str) -> Callable[[], Any]:
    """Find the real D415 ``serial`` again (DeviceNotFoundError while it is not connected)."""
    from mocaprig.acquire.camera_backends import open_cameras

    def find() -> Any:
        (cam,) = open_cameras("realsense", serials=[serial])
        return cam

    return find


_MOCK_D415_MAX = 4  # cameras of the simulated rig


def _rig_sources(
    rig: RigFile,
    *,
    scenario: str,
    seed: int,
    seconds: float,
    stack: list[tuple[str, Any]],
    faults: MockFaults | None = None,
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
            if faults is not None:
                backend = faults.davis_backend(backend)
            sources.append(_davis_source(stack, backend=backend, bias_preset=entry.bias_preset))
        else:
            found = davis240c.find_davis()
            serials = sorted(d.serial or "?" for d in found)
            if entry.serial not in serials:
                msg = (
                    f"DAVIS {entry.serial} listed in {rig.source} is not connected; connected: "
                    f"{serials}; run `mocaprig devices`"
                )
                raise DeviceNotFoundError(msg)
            sources.append(_davis_source(stack, serial=entry.serial, bias_preset=entry.bias_preset))
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
            if faults is not None:
                found_cams = [faults.depth_camera(c) for c in found_cams]
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
            finder = _d415_finder(d, faults) if rig.mock else _realsense_finder(e.serial)
            src = DepthCameraSource(d, stream=e.stream, options=e.options, reopen=finder)
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
            if faults is not None:
                port = faults.serial_port(port)
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
        faults: Every fault and recovery, in order (also written on ``/faults``).
        signal: The signal that stopped the recording (``SIGINT``, ``SIGTERM``), or None.
        live: What the live view (``--live``) published and dropped of its own, or None.
    """

    files: tuple[Path, ...]
    stop_reason: str | None
    seconds: float
    bytes: int
    drops_total: int
    streams: tuple[StreamStatus, ...]
    hung_sources: tuple[str, ...] = ()
    faults: tuple[Fault, ...] = ()
    signal: str | None = None
    live: LiveStats | None = None

    @property
    def device_faults(self) -> tuple[Fault, ...]:
        """The faults that lost a device's data (its streams have a gap)."""
        return tuple(f for f in self.faults if f.lost)

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
            "signal": self.signal,
            "faults": [f.as_dict() for f in self.faults],
            **({} if self.live is None else {"live": self.live.as_dict()}),
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
    open_file: Callable[[Path, str], BinaryIO] | None = None,
    live: LiveView | None = None,
) -> RecordingSummary:
    """Record ``sources`` (and ``followers``, see :func:`acquire.recorder.record_sources`) into
    ``out`` for ``seconds`` (``None``: until every source ends, for offline sources).

    The sources' ``metadata`` attributes are added to ``metadata``. Devices are not closed here.
    ``open_file``: see :class:`mocaprig.acquire.recorder.Recorder`. ``live``: a started
    :class:`~mocaprig.acquire.live_view.LiveView` fed behind the recorder (its ``tap``).

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
        open_file=open_file,
        tap=None if live is None else live.tap,
    )
    if live is not None:
        live.follow(recorder)
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
        faults=recorder.faults,
        signal=recorder.signal_name,
        live=None if live is None else live.stats(),
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
    mock_faults: MockFaults | None = None,
    live: LiveView | None = None,
) -> RecordingSummary:
    """Record the rig (a rig file's devices, the mock rig, or given ``sources``) into ``out``
    for ``seconds``, with the live status line (terminal only) and SIGINT/SIGTERM finishing the
    file (what ``mocaprig record`` runs).

    With ``rig``, the rig file is stored as the ``rig.toml`` attachment and its metadata as the
    ``rig`` and ``session`` records. The devices opened here are closed at the end, except those
    whose reader thread is stuck in a device call (logged). A device lost mid-recording is
    re-opened when it comes back. ``mock_faults`` injects faults into the mock rig (``--mock``
    or a rig file with ``mock = true``), its clock started with the recording. ``live``: a
    started live view served while recording (``--live``), see :func:`record_to_file`.

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
    if mock_faults is not None and (sources is not None or (rig is None and not mock)):
        msg = "fault injection (--mock-faults) needs the mock rig: --mock, or a rig file with mock"
        raise ValidationError(msg)
    stack: list[tuple[str, Any]] = []
    summary: RecordingSummary | None = None
    metadata: dict[str, dict[str, str]] = {}
    attachments: list[Attachment] = []
    try:
        if sources is None:
            if rig is not None:
                rig_file = load_rig_file(rig)
                if mock_faults is not None and not rig_file.mock:
                    msg = (
                        f"fault injection (--mock-faults) needs mock = true in {rig}; real "
                        "devices fail on their own"
                    )
                    raise ValidationError(msg)
                sources = _rig_sources(
                    rig_file,
                    scenario=scenario,
                    seed=seed,
                    seconds=seconds,
                    stack=stack,
                    faults=mock_faults,
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
                    faults=mock_faults,
                )
                metadata["session"] = {"mock": "true", "scenario": scenario, "seed": str(seed)}
        if mock_faults is not None:
            mock_faults.start()
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
            open_file=None if mock_faults is None else mock_faults.open_file,
            live=live,
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
