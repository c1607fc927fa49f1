"""Device faults mid-recording, injected at the mocks' real boundaries (drivers_mock.faults):
the other streams keep recording, a device that comes back goes on in the same file, every
fault and gap is in the file, and what was recorded before a fault stays intact."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mocaprig.acquire.commands_record import record_outcome, recording_info
from mocaprig.acquire.events import make_events
from mocaprig.acquire.record_session import RecordingSummary, run_recording
from mocaprig.acquire.record_sources import DavisSource, DepthCameraSource, SyncBoxSource
from mocaprig.acquire.recorder import (
    Fault,
    Recorder,
    StopReason,
    StreamSource,
    record_sources,
)
from mocaprig.acquire.recording import Recording, RecordingInfo, info, recover
from mocaprig.acquire.recording_format import EventPacket
from mocaprig.drivers_mock.faults import FaultName, FaultSchedule, ScheduledFault
from mocaprig.errors import RecordingError, ValidationError

_FAR = 1e6  # a schedule time no recording reaches (s)


class _Switch:
    """A schedule clock the test flips: before the fault (0), during it (1), after it (2)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _schedule(kind: FaultName, **kw: Any) -> tuple[FaultSchedule, _Switch]:
    clock = _Switch()
    sched = FaultSchedule([ScheduledFault(kind, 1.0, 1.0, **kw)], clock=clock)
    sched.start()
    return sched, clock


def _wait(cond: Callable[[], bool], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            msg = "timed out waiting for the recording"
            raise TimeoutError(msg)
        time.sleep(0.02)


def _written(rec: Recorder, topic: str) -> int:
    return next((s.written for s in rec.status().streams if s.topic == topic), 0)


def _fault_then_back(rec: Recorder, clock: _Switch, device: str, topic: str) -> None:
    """Once ``topic`` has data: pull the device; once its loss is recorded and the other
    streams went on for a while: plug it back; then let it record again."""
    _wait(lambda: _written(rec, topic) >= 3)
    clock.t = 1.0
    _wait(lambda: any(f.kind == "disconnected" and f.device == device for f in rec.faults))
    time.sleep(0.4)
    clock.t = 2.0
    _wait(lambda: any(f.kind == "reconnected" and f.device == device for f in rec.faults))
    n = _written(rec, topic)
    _wait(lambda: _written(rec, topic) >= n + 3)


def _record(
    path: Path, sources: Sequence[StreamSource], drive: Callable[[Recorder], None]
) -> Recorder:
    """Record ``sources`` while ``drive(recorder)`` runs the faults; stop when it is done."""
    rec = Recorder(path, max_chunk_age_s=0.1, status_interval_s=0.2)
    with rec:
        done = threading.Event()
        errors: list[BaseException] = []

        def driver() -> None:
            try:
                drive(rec)
            except BaseException as err:  # reported by the test below
                errors.append(err)
            finally:
                done.set()

        th = threading.Thread(target=driver, daemon=True)
        th.start()
        record_sources(rec, [_Until(done)], seconds=None, status_period_s=0.05, followers=sources)
        th.join(5)
    if errors:
        raise errors[0]
    return rec


class _Until:
    """The leading source: ends when the fault driver is done, which ends the recording (the
    devices follow it)."""

    name = "until"

    def __init__(self, done: threading.Event) -> None:
        self.done = done

    def declare(self, recorder: Recorder) -> None:
        pass

    def run(self, recorder: Recorder, stop: threading.Event) -> None:
        while not (stop.is_set() or self.done.is_set()):
            time.sleep(0.02)


def _syncbox(stack: list[Any], sched: FaultSchedule | None = None) -> SyncBoxSource:
    from mocaprig.acquire.syncbox import SyncBox, open_mock_syncbox

    mock = open_mock_syncbox(seed=0)
    stack.append(mock)
    port = str(mock.port) if sched is None else sched.serial_port(str(mock.port))
    box = SyncBox(port)
    box.open()
    stack.append(box)
    return SyncBoxSource(box, report_interval_ms=100)


def _d415(stack: list[Any], sched: FaultSchedule | None = None) -> DepthCameraSource:
    from mocaprig.acquire.camera_backends import open_cameras
    from mocaprig.acquire.depth_camera import SensorOptions, StreamConfig, SyncMode

    # images=False: all-zero images, the timing of real ones (rendering is not under test).
    (cam,) = open_cameras("mock", count=1, pacing="realtime", seconds=30.0, images=False)
    if sched is not None:
        cam = sched.depth_camera(cam)
    stack.append(cam)
    mode, opts = StreamConfig(), SensorOptions()
    cam.configure(stream=mode, options=opts, sync_mode=SyncMode.MASTER)
    serial = str(cam.info.serial)
    finder = None if sched is None else (lambda: sched.find_depth_camera(serial))
    return DepthCameraSource(cam, stream=mode, options=opts, reopen=finder, stall_s=0.3)


def _davis(stack: list[Any], sched: FaultSchedule | None = None) -> DavisSource:
    from mocaprig.acquire.davis240c import Davis240C
    from mocaprig.drivers_mock.davis240c_usb import SyntheticDavisSource, mock_backend

    backend: Any = mock_backend(source=SyntheticDavisSource(seed=0, seconds=30.0), pacing="asap")
    if sched is not None:
        backend = sched.davis_backend(backend)
    cam = Davis240C.open(backend=backend, settle_delays_s=(0.0, 0.0, 0.0))
    stack.append(cam)
    serial = cam.serial
    return DavisSource(
        cam,
        reopen=lambda: Davis240C.open(
            backend=backend, serial=serial, settle_delays_s=(0.0, 0.0, 0.0)
        ),
    )


@pytest.fixture
def stack() -> Iterator[list[Any]]:
    """Devices and mocks a test opened, closed at its end (last first)."""
    opened: list[Any] = []
    yield opened
    for dev in reversed(opened):
        dev.close()


def _one_loss_and_back(inf: RecordingInfo, device: str) -> tuple[int, int]:
    kinds = [(f.device, f.kind) for f in inf.faults]
    assert kinds == [(device, "disconnected"), (device, "reconnected")], kinds
    (gap,) = inf.gaps
    assert gap.device == device
    assert gap.back
    assert gap.seconds > 0.3
    return gap.start_ns, gap.end_ns


def _times(path: Path, topic: str) -> np.ndarray:
    with Recording(path) as r:
        return np.array([m.log_time_ns for m in r.messages(topic)], np.int64)


def _assert_goes_on_across(path: Path, topic: str, start_ns: int, end_ns: int) -> None:
    """``topic`` has messages before ``start_ns`` and after ``end_ns`` (the same stream)."""
    t = _times(path, topic)
    assert (t < start_ns).sum() >= 3, topic
    assert (t > end_ns).sum() >= 3, topic


def _assert_recorded_during(path: Path, topic: str, start_ns: int, end_ns: int) -> None:
    t = _times(path, topic)
    assert ((t > start_ns) & (t < end_ns)).sum() >= 1, f"{topic} stopped during the gap"


def test_davis_unplugged_and_back_goes_on_in_the_same_file(
    tmp_path: Path, stack: list[Any]
) -> None:
    sched, clock = _schedule("davis-unplug")
    davis = _davis(stack, sched)
    box = _syncbox(stack)
    events = f"/davis/{davis.serial}/events"
    p = tmp_path / "a.mcap"
    rec = _record(p, [davis, box], lambda r: _fault_then_back(r, clock, davis.name, events))
    assert rec.stop_reason is StopReason.REQUESTED
    inf = info(p)
    assert inf.indexed
    lost, back = _one_loss_and_back(inf, davis.name)
    assert "No such device" in inf.faults[0].detail
    _assert_goes_on_across(p, events, lost, back)
    _assert_recorded_during(p, "/syncbox/pulses", lost, back)
    with Recording(p) as r:
        seqs = [m.sequence for m in r.messages(events)]
        packets = [m.decode() for m in r.messages(events)]
    # One stream across the re-open: its counter goes on, every packet before the loss intact.
    assert seqs == sorted(seqs)
    assert len(set(seqs)) == len(seqs)
    assert all(p.events.size > 0 for p in packets)
    streams = {s.topic: s for s in inf.streams}
    assert streams[events].counter_gaps == streams[events].drops


def test_d415_disconnected_and_back_goes_on_in_the_same_file(
    tmp_path: Path, stack: list[Any]
) -> None:
    sched, clock = _schedule("d415-disconnect")
    cam = _d415(stack, sched)
    box = _syncbox(stack)
    depth = f"/d415/{cam.serial}/depth"
    p = tmp_path / "a.mcap"
    _record(p, [cam, box], lambda r: _fault_then_back(r, clock, cam.name, depth))
    inf = info(p)
    lost, back = _one_loss_and_back(inf, cam.name)
    assert "no frames for" in inf.faults[0].detail
    _assert_goes_on_across(p, depth, lost, back)
    _assert_recorded_during(p, "/syncbox/pulses", lost, back)
    streams = {s.topic: s.messages for s in inf.streams}
    assert streams[depth] == streams[depth.replace("depth", "ir")]
    assert streams[depth.replace("depth", "camera_info")] == 2  # again after the re-open
    with Recording(p) as r:
        counters = [
            m.decode().frame_counter for m in r.messages(depth.replace("depth", "frame_info"))
        ]
        assert all(img.image.shape == (480, 848) for _, img in r.images(depth))
    restart = counters.index(min(counters[1:]), 1)  # the re-opened camera counts from its start
    assert counters[:restart] == list(range(counters[0], counters[0] + restart))


def test_syncbox_cable_pulled_and_back_goes_on_in_the_same_file(
    tmp_path: Path, stack: list[Any]
) -> None:
    sched, clock = _schedule("syncbox-unplug")
    box = _syncbox(stack, sched)
    box.box._max_reopen = 0  # the driver's own re-open would hide the pull for ~1.4 s
    davis = _davis(stack)
    p = tmp_path / "a.mcap"
    _record(p, [box, davis], lambda r: _fault_then_back(r, clock, "syncbox", "/syncbox/pulses"))
    inf = info(p)
    lost, back = _one_loss_and_back(inf, "syncbox")
    assert "device disconnected" in inf.faults[0].detail
    _assert_goes_on_across(p, "/syncbox/pulses", lost, back)
    _assert_recorded_during(p, f"/davis/{davis.serial}/events", lost, back)


def test_device_that_never_comes_back_leaves_a_gap_to_the_end(
    tmp_path: Path, stack: list[Any]
) -> None:
    clock = _Switch()
    sched = FaultSchedule([ScheduledFault("davis-unplug", 1.0)], clock=clock)  # for good
    davis = _davis(stack, sched)
    box = _syncbox(stack)
    events = f"/davis/{davis.serial}/events"

    def drive(rec: Recorder) -> None:
        _wait(lambda: _written(rec, events) >= 3)
        clock.t = 1.0
        _wait(lambda: bool(rec.faults))
        n = _written(rec, "/syncbox/pulses")
        _wait(lambda: _written(rec, "/syncbox/pulses") >= n + 3)

    p = tmp_path / "a.mcap"
    _record(p, [davis, box], drive)
    inf = info(p)
    assert [f.kind for f in inf.faults] == ["disconnected"]
    (gap,) = inf.gaps
    assert not gap.back
    assert gap.end_ns == inf.end_ns
    assert (_times(p, "/syncbox/pulses") > gap.start_ns).sum() >= 3


def test_info_lists_faults_and_gaps(
    tmp_path: Path, stack: list[Any], capsys: pytest.CaptureFixture[str]
) -> None:
    sched, clock = _schedule("syncbox-unplug")
    box = _syncbox(stack, sched)
    box.box._max_reopen = 0
    p = tmp_path / "a.mcap"
    _record(p, [box], lambda r: _fault_then_back(r, clock, "syncbox", "/syncbox/pulses"))
    assert recording_info(p, as_json=False) == 0
    out = capsys.readouterr().out
    assert "syncbox                  disconnected: sync box on mocaprigfault://" in out
    assert "syncbox                  reconnected: re-opened" in out
    gap_lines = [ln for ln in out.splitlines() if ln.startswith("  gap: syncbox")]
    assert len(gap_lines) == 1
    assert "never back" not in gap_lines[0]


def _feeder(n_max: int = 10**6) -> StreamSource:
    class Feeder:
        """Event packets as fast as the recorder takes them, numbered."""

        name = "feeder"

        def declare(self, recorder: Recorder) -> None:
            self.h = recorder.add_stream("/davis/1/events", EventPacket)

        def run(self, recorder: Recorder, stop: threading.Event) -> None:
            rng = np.random.default_rng(0)
            for i in range(n_max):
                if stop.is_set():
                    return
                t = np.sort(rng.integers(0, 10_000, 2000)) + i * 10_000
                ev = make_events(t, t % 240, t % 180, t % 2)
                recorder.put_wait(self.h, EventPacket(ev, seq=i), sequence=i)

    return Feeder()


def _on_disk(path: Path) -> int:
    """Event packets already in the file being written (its complete chunks)."""
    with Recording(path) as r:
        if "/davis/1/events" not in r.channels:  # its first chunk is not written yet
            return 0
        return sum(1 for _ in r.messages("/davis/1/events"))


def _disk_full(path: Path, *, spare_bytes: int) -> tuple[Recorder, int]:
    """Fill the disk once some packets are on it; returns the recorder and that count."""
    sched, clock = _schedule("disk-full", spare_bytes=spare_bytes)
    rec = Recorder(path, max_chunk_age_s=0.05, chunk_size_bytes=64 << 10, open_file=sched.open_file)
    before: list[int] = []

    def drive(r: Recorder) -> None:
        _wait(lambda: _on_disk(path) >= 20)
        before.append(_on_disk(path))
        clock.t = 1.0

    rec.start()
    threading.Thread(target=drive, args=(rec,), daemon=True).start()
    record_sources(rec, [_feeder()], seconds=10.0, status_period_s=0.05)
    rec.close()
    with pytest.raises(RecordingError, match="the disk is full") as exc:
        rec.raise_if_failed()
    assert isinstance(exc.value.__cause__, OSError)
    assert exc.value.__cause__.errno == errno.ENOSPC
    assert rec.stop_reason is StopReason.DISK_FULL
    return rec, before[0]


def _assert_events_intact(path: Path) -> int:
    """Every event packet in the file decodes and they are 0..n-1 with nothing missing."""
    with Recording(path) as r:
        seqs = [m.sequence for m in r.messages("/davis/1/events")]
        sizes = {m.decode().events.size for m in r.messages("/davis/1/events")}
    assert seqs == list(range(len(seqs)))
    assert sizes == {2000}
    return len(seqs)


def test_disk_full_ends_the_file_with_the_fault_and_every_message_before(
    tmp_path: Path,
) -> None:
    p = tmp_path / "a.mcap"
    rec, before = _disk_full(p, spare_bytes=8192)
    inf = info(p)
    assert not inf.scan.truncated
    assert inf.scan.bad_chunks == 0
    assert inf.stop_reason == "disk-full"
    assert [f.kind for f in inf.faults] == ["disk-full"]
    assert "No space left on device" in inf.faults[0].detail
    n = _assert_events_intact(p)
    assert n >= before  # every packet on disk before the fault is still there
    assert rec.status().streams[-1].topic == "/faults"
    fixed = tmp_path / "fixed.mcap"
    assert recover(p, fixed).lossless
    assert info(fixed).indexed


def test_disk_full_without_room_for_the_ending_stays_readable_and_recoverable(
    tmp_path: Path,
) -> None:
    p = tmp_path / "a.mcap"
    rec, before = _disk_full(p, spare_bytes=0)
    assert rec.faults[0].kind == "disk-full"  # known to the caller, not in the file
    inf = info(p)
    assert inf.scan.bad_chunks == 0
    assert inf.stop_reason in (None, "disk-full")  # the ending fits only if enough was freed
    n = _assert_events_intact(p)
    assert n >= before  # every packet on disk before the fault is still there
    fixed = tmp_path / "fixed.mcap"
    rep = recover(p, fixed)
    assert rep.messages >= n


_SIGNAL_SCRIPT = """
import sys, threading, time
from pathlib import Path
from mocaprig.acquire.commands_record import record
from mocaprig.acquire.recording_format import SyncPulses

class Ticker:
    name = "ticker"
    def declare(self, recorder):
        self.h = recorder.add_stream("/syncbox/pulses", SyncPulses)
    def run(self, recorder, stop):
        i = 0
        while not stop.is_set():
            recorder.put(self.h, SyncPulses(i, i * 1000), sequence=i)
            i += 1
            if i == 20:
                print("recording", flush=True)
            time.sleep(0.005)

sys.exit(record(out=Path(sys.argv[1]), seconds=60, mock=False, rig=None, sources=[Ticker()]))
"""


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signal_finishes_the_file_and_says_so(tmp_path: Path, sig: int, code: int) -> None:
    p = tmp_path / "a.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(_SIGNAL_SCRIPT), str(p)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "recording"
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == code, err
    name = signal.Signals(sig).name
    assert out.splitlines()[0].startswith(f"stopped by {name}: recorded "), out
    assert "file finished" in out.splitlines()[0]
    inf = info(p)
    assert inf.indexed
    assert inf.stop_reason == "signal"
    (fault,) = inf.faults
    assert (fault.kind, fault.device) == ("signal", "recorder")
    assert fault.detail.startswith(name)
    with Recording(p) as r:
        seqs = [m.sequence for m in r.messages("/syncbox/pulses")]
    assert len(seqs) >= 20
    assert seqs == list(range(len(seqs)))


def _summary(faults: tuple[Fault, ...] = (), signal_name: str | None = None) -> RecordingSummary:
    return RecordingSummary(
        files=(Path("s.mcap"),),
        stop_reason="signal" if signal_name else "requested",
        seconds=6.0,
        bytes=9_300_000,
        drops_total=0,
        streams=(),
        faults=faults,
        signal=signal_name,
    )


def test_outcome_exit_codes_say_what_happened() -> None:
    lost = Fault("disconnected", "davis/1", 1, "gone")
    back = Fault("reconnected", "davis/1", 2, "back")
    never = Fault("disconnected", "syncbox", 3, "gone")
    assert record_outcome(_summary()) == (0, "recorded 6.0 s, 9.3 MB, 0 dropped -> s.mcap")
    code, line = record_outcome(_summary((lost, back, never)))
    assert code == 3
    assert line.endswith(
        "; 2 device fault(s): davis/1 lost and back, syncbox lost (`mocaprig info` lists them)"
    )
    code, line = record_outcome(_summary((Fault("signal", "recorder", 4, "SIGINT"),), "SIGINT"))
    assert code == 130
    assert line == "stopped by SIGINT: recorded 6.0 s, 9.3 MB, 0 dropped -> s.mcap, file finished"
    assert record_outcome(_summary(signal_name="SIGTERM"))[0] == 143


def test_fault_injection_needs_the_mock_rig(tmp_path: Path) -> None:
    sched = FaultSchedule.parse("davis-unplug@1")
    with pytest.raises(ValidationError, match="needs the mock rig"):
        run_recording(out=tmp_path / "a.mcap", seconds=1.0, mock=False, rig=None, mock_faults=sched)
