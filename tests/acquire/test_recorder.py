"""The recorder: never blocks, counts drops, bounds crash loss, stops cleanly, splits."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
from mcap.reader import make_reader

from mocaprig.acquire.events import make_events
from mocaprig.acquire.recorder import Recorder, StopReason, StreamSource, record_sources, split_path
from mocaprig.acquire.recording import Recording, info, recover
from mocaprig.acquire.recording_format import EventPacket, ImageMsg, LogMsg, SchemaDef, SyncPulses
from mocaprig.errors import RecordingError, ValidationError


def _events(i: int, n: int = 100) -> EventPacket:
    t = np.arange(n, dtype=np.int64) + i * n
    return EventPacket(make_events(t, t % 240, t % 180, t % 2), seq=i, frame_id="davis_1")


@dataclass(frozen=True)
class _Blocking:
    """A payload whose encoding waits: stalls the writer thread like a slow disk."""

    SCHEMA: ClassVar[SchemaDef] = SyncPulses.SCHEMA
    gate: threading.Event
    entered: threading.Event = field(default_factory=threading.Event)

    @property
    def nbytes(self) -> int:
        return 10

    def encode(self) -> bytes:
        self.entered.set()
        self.gate.wait(10)
        return SyncPulses(1, 2).encode()


def _wait_for(condition: Callable[[], bool], timeout_s: float = 10.0) -> None:
    """Wait until ``condition()`` holds (the writer thread got there), failing after a timeout."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out waiting for the writer thread"
        time.sleep(0.01)


def _complete_chunks(path: Path) -> int:
    with Recording(path) as r:
        return r.scan.complete_chunks


def test_recorder_refuses_existing_path(tmp_path: Path) -> None:
    p = tmp_path / "a.mcap"
    p.write_bytes(b"x")
    with pytest.raises(RecordingError, match="not overwriting"):
        Recorder(p)


def test_recorder_refuses_reserved_metadata_and_bad_options(tmp_path: Path) -> None:
    with pytest.raises(ValidationError, match="reserved"):
        Recorder(tmp_path / "a.mcap", metadata={"mocaprig": {}})
    with pytest.raises(ValidationError, match="max_chunk_age_s"):
        Recorder(tmp_path / "a.mcap", max_chunk_age_s=0)


def test_put_never_blocks_and_counts_drops(tmp_path: Path) -> None:
    p = tmp_path / "a.mcap"
    gate = threading.Event()
    with Recorder(p, queue_messages=5) as rec:
        slow = rec.add_stream("/syncbox/pulses", SyncPulses)
        ev = rec.add_stream("/davis/1/events", EventPacket)
        blocking = _Blocking(gate)
        rec.put(slow, blocking)
        assert blocking.entered.wait(10)  # the writer is now stuck in encode()
        t0 = time.perf_counter()
        results = [rec.put(ev, _events(i), sequence=i) for i in range(50)]
        elapsed = time.perf_counter() - t0
        gate.set()
    assert elapsed < 0.05, f"50 put() calls took {elapsed:.3f} s with a stalled writer"
    assert results.count(True) == 5
    st = {s.topic: s for s in rec.status().streams}
    assert st["/davis/1/events"].dropped == 45
    assert st["/davis/1/events"].written == 5
    inf = info(p)
    drops = {s.topic: s.drops for s in inf.streams}
    assert drops["/davis/1/events"] == 45
    with Recording(p) as r:
        assert r.metadata()["mocaprig.summary"]["dropped:/davis/1/events"] == "45"


def test_queue_bytes_bound_drops_large_messages(tmp_path: Path) -> None:
    gate = threading.Event()
    with Recorder(tmp_path / "a.mcap", queue_bytes=3_000_000) as rec:
        slow = rec.add_stream("/syncbox/pulses", SyncPulses)
        depth = rec.add_stream("/d415/1/depth", ImageMsg)
        blocking = _Blocking(gate)
        rec.put(slow, blocking)
        assert blocking.entered.wait(10)
        img = ImageMsg(np.zeros((720, 1280), np.uint16), "16UC1")
        ok = [rec.put(depth, img) for _ in range(4)]
        gate.set()
    assert ok == [True, False, False, False]  # 1.84 MB each: only one fits in 3 MB
    assert rec.memory_bound_bytes >= 3_000_000


def test_chunks_reach_the_file_on_the_age_timer(tmp_path: Path) -> None:
    p = tmp_path / "a.mcap"
    with Recorder(p, max_chunk_age_s=0.1, chunk_size_bytes=64 << 20) as rec:
        ev = rec.add_stream("/davis/1/events", EventPacket)
        for i in range(10):
            rec.put(ev, _events(i))
        _wait_for(lambda: _complete_chunks(p) >= 1)  # the age timer closed a chunk
        with Recording(p) as r:  # no summary yet: linear scan of what is on disk
            assert not r.indexed
            assert r.events("/davis/1/events").size == 1000
            assert r.scan.complete_chunks >= 1


def test_disk_full_stops_cleanly_with_a_clear_error(tmp_path: Path) -> None:
    p = tmp_path / "a.mcap"
    free = [10**9]
    rec = Recorder(p, min_free_disk_bytes=10**8, disk_free_bytes=lambda _: free[0])
    rec.start()
    ev = rec.add_stream("/davis/1/events", EventPacket)
    for i in range(20):
        rec.put(ev, _events(i))
    _wait_for(lambda: {s.topic: s.written for s in rec.status().streams}["/davis/1/events"] == 20)
    free[0] = 10**7
    assert rec.stopped.wait(2.0)
    assert not rec.put(ev, _events(99))
    rec.close()
    with pytest.raises(RecordingError, match="stopped early: free disk"):
        rec.raise_if_failed()
    assert rec.stop_reason is StopReason.DISK_FULL
    with Recording(p) as r:
        assert r.indexed
        assert r.events("/davis/1/events").size == 2000
        assert r.metadata()["mocaprig.summary"]["stop_reason"] == "disk-full"
        logs = [m.decode() for m in r.messages("/log")]
    assert any(isinstance(m, LogMsg) and "free disk" in m.message for m in logs)


def test_start_refuses_when_disk_already_full(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "a.mcap", min_free_disk_bytes=10, disk_free_bytes=lambda _: 1)
    with pytest.raises(RecordingError, match="margin"):
        rec.start()
    assert not (tmp_path / "a.mcap").exists()


def test_split_by_size_writes_numbered_standalone_files(tmp_path: Path) -> None:
    p = tmp_path / "s.mcap"
    with Recorder(p, split_bytes=200_000, metadata={"rig": {"name": "lab"}}) as rec:
        depth = rec.add_stream("/d415/1/depth", ImageMsg)
        img = np.random.default_rng(0).integers(0, 4000, (240, 320)).astype(np.uint16)
        for i in range(12):
            assert rec.put(depth, ImageMsg(img, "16UC1"), sequence=i)
            time.sleep(0.02)
    files = rec.files
    assert len(files) >= 2
    assert files[0] == split_path(p, 0) == tmp_path / "s_000.mcap"
    total = 0
    for f in files:
        with Recording(f) as r:
            assert r.indexed
            assert r.metadata()["rig"] == {"name": "lab"}
            total += (
                sum(1 for _ in r.messages("/d415/1/depth")) if "/d415/1/depth" in r.topics else 0
            )
    assert total == 12


class _Source:
    def __init__(self, name: str, *, die_after: int | None) -> None:
        self.name = name
        self.die_after = die_after
        self.metadata: dict[str, dict[str, str]] = {}

    def declare(self, recorder: Recorder) -> None:
        self.h = recorder.add_stream(f"/davis/{self.name}/events", EventPacket)

    def run(self, recorder: Recorder, stop: threading.Event) -> None:
        i = 0
        while not stop.is_set():
            if self.die_after is not None and i == self.die_after:
                raise OSError("USB cable pulled")
            recorder.put(self.h, _events(i), sequence=i)
            i += 1
            time.sleep(0.005)


def test_a_dying_source_is_logged_and_the_rest_keeps_recording(tmp_path: Path) -> None:
    p = tmp_path / "a.mcap"
    sources: list[StreamSource] = [_Source("good", die_after=None), _Source("bad", die_after=5)]
    with Recorder(p) as rec:
        hung = record_sources(rec, sources, seconds=0.6, status_period_s=0.05)
    assert hung == ()
    with Recording(p) as r:
        good = sum(1 for _ in r.messages("/davis/good/events"))
        bad = sum(1 for _ in r.messages("/davis/bad/events"))
        logs = [m.decode().message for m in r.messages("/log")]
    assert bad == 5
    assert good > 20
    assert any("bad died" in m and "USB cable pulled" in m for m in logs)


_CHILD = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from pathlib import Path
    from mocaprig.acquire.events import make_events
    from mocaprig.acquire.recorder import Recorder, stop_on_signals
    from mocaprig.acquire.recording_format import EventPacket
    rec = Recorder(Path(sys.argv[1]), max_chunk_age_s=0.1, compression="zstd")
    with rec, stop_on_signals(rec):
        h = rec.add_stream("/davis/1/events", EventPacket)
        i = 0
        while not rec.stopped.is_set():
            t = np.arange(200, dtype=np.int64) + i * 200
            rec.put(h, EventPacket(make_events(t, t % 240, t % 180, t % 2), seq=i), sequence=i)
            i += 1
            if i % 20 == 0:
                print(i, time.time_ns(), flush=True)
            time.sleep(0.002)
    """
)


def _start_child(path: Path) -> tuple[subprocess.Popen[str], int]:
    proc = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(path)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None
    n = 0
    t_end = time.monotonic() + 20
    while n < 200 and time.monotonic() < t_end:  # about 0.5 s of recording
        line = proc.stdout.readline()
        if not line:
            break
        n = int(line.split()[0])
    return proc, n


def test_sigkill_loses_at_most_the_open_chunk_and_recover_indexes(tmp_path: Path) -> None:
    p = tmp_path / "crash.mcap"
    proc, n = _start_child(p)
    assert n >= 200, "the recording child did not start"
    kill_ns = time.time_ns()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(10)
    with pytest.raises(Exception):  # noqa: B017, PT011 - the seeking reader fails on a crash
        make_reader(p.open("rb")).get_summary()
    with Recording(p) as r:
        assert not r.indexed
        msgs = list(r.messages("/davis/1/events"))
    assert len(msgs) >= 100
    seqs = [m.sequence for m in msgs]
    assert seqs == list(range(len(seqs))), "complete chunks must hold a gap-free prefix"
    lost_s = (kill_ns - msgs[-1].log_time_ns) / 1e9
    print(f"SIGKILL: {len(msgs)} messages kept, last {lost_s * 1e3:.0f} ms before the kill lost")
    assert lost_s < 0.2 + 0.5, f"lost {lost_s:.3f} s of data (bound 0.2 s + scheduling slack)"

    out = tmp_path / "fixed.mcap"
    rep = recover(p, out)
    assert rep.messages >= len(msgs)
    with out.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    assert summary.chunk_indexes
    inf = info(out)
    assert inf.indexed
    assert inf.recovered
    assert {s.topic: s.messages for s in inf.streams}["/davis/1/events"] == len(msgs)


def test_sigterm_finishes_the_file(tmp_path: Path) -> None:
    p = tmp_path / "term.mcap"
    proc, n = _start_child(p)
    assert n >= 200
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(20) == 0
    with Recording(p) as r:
        assert r.indexed
        assert r.metadata()["mocaprig.summary"]["stop_reason"] == "signal"
        (fault,) = [m.decode() for m in r.messages("/faults")]
    assert fault.message.startswith("signal: SIGTERM")


def test_truncated_file_reads_complete_chunks_and_reports_the_tail(tmp_path: Path) -> None:
    p = tmp_path / "a.mcap"
    with Recorder(p, chunk_size_bytes=4096) as rec:
        ev = rec.add_stream("/davis/1/events", EventPacket)
        for i in range(100):
            rec.put(ev, _events(i), sequence=i)
    cut = tmp_path / "cut.mcap"
    data = p.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    with Recording(cut) as r:
        got = r.events("/davis/1/events")
        assert r.scan.truncated
        assert r.scan.bytes_unread > 0
    assert 0 < got.size < 10_000
    np.testing.assert_array_equal(got["t"], np.arange(got.size))


@pytest.fixture
def small_fs(tmp_path: Path) -> Iterator[Path]:
    """A 4 MiB tmpfs (needs root and mount rights; skipped visibly otherwise)."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    res = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mnt)],
        capture_output=True,
        text=True,
        check=False,
    )
    if res.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({res.stderr.strip()}); disk-full on a "
                    "real file system is not tested")  # fmt: skip
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


def _fill(rec: Recorder, seconds: float = 5.0) -> None:
    h = rec.add_stream("/d415/1/depth", ImageMsg)
    img = np.random.default_rng(0).integers(0, 65535, (240, 320)).astype(np.uint16)
    t_end = time.monotonic() + seconds
    while not rec.stopped.is_set() and time.monotonic() < t_end:
        rec.put(h, ImageMsg(img, "16UC1"))
        time.sleep(0.002)


def test_small_filesystem_margin_stops_cleanly(small_fs: Path) -> None:
    p = small_fs / "a.mcap"
    rec = Recorder(p, min_free_disk_bytes=1 << 20, compression="none")
    rec.start()
    _fill(rec)
    rec.close()
    assert rec.stop_reason is StopReason.DISK_FULL
    with pytest.raises(RecordingError, match="free disk"):
        rec.raise_if_failed()
    with Recording(p) as r:
        assert r.indexed
        assert sum(1 for _ in r.messages("/d415/1/depth")) > 5


def test_small_filesystem_enospc_ends_the_file_at_its_last_record_with_the_fault(
    small_fs: Path,
) -> None:
    p = small_fs / "a.mcap"
    # The free-space probe lies (as on a network share): the write itself hits ENOSPC.
    rec = Recorder(
        p,
        min_free_disk_bytes=0,
        compression="none",
        max_chunk_age_s=0.05,
        disk_free_bytes=lambda _: 10**12,
    )
    rec.start()
    _fill(rec)
    rec.close()
    assert rec.stop_reason is StopReason.DISK_FULL
    with pytest.raises(RecordingError, match=r"the disk is full .*recover"):
        rec.raise_if_failed()
    # The partial chunk is cut off, which frees room for the ending (no index, the fault).
    inf = info(p)
    assert not inf.scan.truncated
    assert inf.stop_reason == "disk-full"
    assert [f.kind for f in inf.faults] == ["disk-full"]
    with Recording(p) as r:  # no index: read linearly
        in_file = sum(1 for _ in r.messages("/d415/1/depth"))
    assert in_file > 5
    # What the cut back to the last whole record lost is counted dropped, not written.
    depth = next(st for st in rec.status().streams if st.topic == "/d415/1/depth")
    assert depth.written == in_file
    assert depth.received == depth.written + depth.dropped


def test_a_write_error_stops_the_recording_and_accounts_for_every_message(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An I/O error (not a full disk) on a data message: the recorder stops with
    ``write-error``, the fault goes into the file, and every message received is counted
    written or dropped (none vanishes between the two)."""
    import errno

    from mocaprig.acquire import recorder as recorder_mod

    real_write = recorder_mod._Part.write
    calls = {"data": 0}

    def failing_write(part: object, s: object, log_time: int, seq: int, data: bytes) -> None:
        if getattr(getattr(s, "handle", None), "topic", "") != "/faults":
            calls["data"] += 1
            if calls["data"] > 30:
                raise OSError(errno.EIO, "Input/output error")
        real_write(part, s, log_time, seq, data)  # type: ignore[arg-type]

    monkeypatch.setattr(recorder_mod._Part, "write", failing_write)
    p = tmp_path / "a.mcap"
    rec = Recorder(p, compression="none")
    rec.start()
    h = rec.add_stream("/syncbox/pulses", SyncPulses)
    for k in range(500):
        if rec.stopped.is_set():
            break
        rec.put(h, SyncPulses(k, 1000 * k))
        time.sleep(0.001)
    rec.stopped.wait(5.0)
    rec.close()
    assert rec.stop_reason is StopReason.WRITE_ERROR
    with pytest.raises(RecordingError):
        rec.raise_if_failed()
    assert [f.kind for f in rec.faults] == ["write-error"]
    for st in rec.status().streams:
        assert st.received == st.written + st.dropped, st
    faults = next(st for st in rec.status().streams if st.topic == "/faults")
    assert faults.written == 1
    assert "write-error" in [f.kind for f in info(p).faults]
