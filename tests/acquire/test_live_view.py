"""The Foxglove live view: latest-wins slots, channels and rates seen by a WebSocket client, and
no recorder drop whatever the client does."""

from __future__ import annotations

import json
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from mocaprig.acquire.commands_record import record
from mocaprig.acquire.events import make_events
from mocaprig.acquire.live_view import LIVE_STATUS_TOPIC, LiveClient, LiveView
from mocaprig.acquire.recorder import Recorder
from mocaprig.acquire.recording import Recording
from mocaprig.acquire.recording_format import (
    IMU_DTYPE,
    DavisFrameInfo,
    EventPacket,
    ImageMsg,
    ImuPacket,
)
from mocaprig.errors import RecordingError

pytest.importorskip("foxglove")

_CAMS = ("c0", "c1")


def _feed(rec: Recorder, seconds: float, *, seed: int = 0, h: int = 120, w: int = 212) -> None:
    """Put a paced rig into ``rec`` from this thread: per camera IR + depth at 30 Hz, DAVIS
    events (33 ms per packet, 30 packets/s), frames and IMU at 30 Hz."""
    rng = np.random.default_rng(seed)
    ir = ImageMsg(rng.integers(0, 255, (h, w), dtype=np.uint8), "mono8")
    depth = ImageMsg(rng.integers(0, 4000, (h, w), dtype=np.uint16), "16UC1")
    aps = ImageMsg(rng.integers(0, 1024, (180, 240), dtype=np.uint16), "mono16")
    imu = ImuPacket(np.zeros(10, IMU_DTYPE))
    hs = {
        t: rec.add_stream(t, ImageMsg) for c in _CAMS for t in (f"/d415/{c}/ir", f"/d415/{c}/depth")
    }
    ev_h = rec.add_stream("/davis/x/events", EventPacket)
    fr_h = rec.add_stream("/davis/x/frame", ImageMsg)
    imu_h = rec.add_stream("/davis/x/imu", ImuPacket)
    t0 = time.monotonic()
    i = 0
    while (due := t0 + i / 30.0) < t0 + seconds:
        time.sleep(max(due - time.monotonic(), 0.0))
        for c in _CAMS:
            rec.put(hs[f"/d415/{c}/ir"], ir, sequence=i)
            rec.put(hs[f"/d415/{c}/depth"], depth, sequence=i)
        n = 3000
        t = np.sort(rng.integers(0, 33_000, n)) + i * 33_000
        ev = make_events(t, rng.integers(0, 240, n), rng.integers(0, 180, n), rng.integers(0, 2, n))
        rec.put(ev_h, EventPacket(ev, seq=i))
        rec.put(fr_h, aps, sequence=i)
        rec.put(imu_h, imu, sequence=i)
        i += 1


def _record(tmp_path: Path, name: str, seconds: float, live: LiveView | None) -> int:
    """Record the feed (with ``live`` behind the recorder when given); the recorder's drops."""
    with Recorder(
        tmp_path / f"{name}.mcap", min_free_disk_bytes=0, tap=None if live is None else live.tap
    ) as rec:
        if live is not None:
            live.follow(rec)
        _feed(rec, seconds)
    return rec.status().dropped_total


def test_slot_latest_wins_and_decimation_drop_only_live_frames() -> None:
    """Unit: the tap keeps one pending image per topic (an older one is the live view's drop)
    and skips frames above ``image_hz``; nothing is published without a started server."""
    view = LiveView(port=0, image_hz=15.0)
    img = ImageMsg(np.zeros((4, 4), np.uint8), "mono8")
    for k in range(10):  # 10 Hz: none decimated, each replaces the last
        view.tap("/d415/c0/ir", img, b"x", k * 100_000_000)
    st = view.stats()
    assert st.offered["/d415/c0/ir"] == 10
    assert st.dropped["/d415/c0/ir"] == 9
    view2 = LiveView(port=0, image_hz=15.0)
    for k in range(300):  # 30 fps for 10 s
        view2.tap("/d415/c0/depth", img, b"x", k * 33_333_333)
    st2 = view2.stats()
    assert 145 <= st2.offered["/d415/c0/depth"] <= 152  # ~15 Hz kept
    assert st2.offered["/d415/c0/depth"] + st2.decimated["/d415/c0/depth"] == 300
    view2.tap("/davis/x/imu", ImuPacket(np.zeros(1, IMU_DTYPE)), b"", 0)
    view2.tap("/davis/x/frame_info", DavisFrameInfo(0, 0, 1, 0, 1, 10), b"", 0)  # not shown live
    assert set(view2.stats().offered) == {"/d415/c0/depth", "/davis/x/imu_live"}


def test_live_channels_arrive_at_rate_with_no_recorder_drop(tmp_path: Path) -> None:
    """A connected client sees every live channel; camera images and the event image arrive at
    >= 10 Hz each; the recorder drops nothing."""
    with LiveView(port=0) as live:
        with LiveClient("127.0.0.1", live.port) as client:
            drops = _record(tmp_path, "live", 3.0, live)
            time.sleep(0.3)
        stats = live.stats()
    chans = client.channels
    want = {f"/d415/{c}/{s}" for c in _CAMS for s in ("ir", "depth")}
    want |= {"/davis/x/frame", "/davis/x/event_image", "/davis/x/imu_live", LIVE_STATUS_TOPIC}
    assert want <= set(chans), chans
    assert chans["/davis/x/event_image"] == "foxglove.RawImage"
    assert drops == 0
    for topic in [*(t for t in want if t.startswith("/d415/")), "/davis/x/event_image"]:
        assert client.rate_hz(topic, skip_s=0.5) >= 10.0, (topic, client.counts())
    last = client.last("/davis/x/event_image")
    assert last is not None
    pb = RawImage.FromString(last)
    assert (pb.encoding, pb.width, pb.height) == ("rgb8", 240, 180)
    assert client.counts()[LIVE_STATUS_TOPIC] >= 2
    assert stats.published_total > 0


@pytest.mark.slow
def test_slow_or_absent_client_never_costs_the_recorder(tmp_path: Path) -> None:
    """The same feed recorded without the live view and with it, served to a client that reads
    one message per 0.2 s and one that stops reading after its first: the recorder drops
    nothing either way."""
    without = _record(tmp_path, "without", 3.0, None)
    with LiveView(port=0, backlog_messages=4) as live:
        with (
            LiveClient("127.0.0.1", live.port, read_delay_s=0.2),
            LiveClient("127.0.0.1", live.port, read_delay_s=10.0),  # absent after one message
        ):
            with_live = _record(tmp_path, "with", 3.0, live)
        stats = live.stats()
    assert (without, with_live) == (0, 0)
    assert stats.offered  # it did take messages


def test_errors_name_the_port_and_the_missing_package(monkeypatch: pytest.MonkeyPatch) -> None:
    first = LiveView(port=0)
    with first, pytest.raises(RecordingError, match=rf"127\.0\.0\.1:{first.port}.*--port"):
        LiveView(port=first.port).start()
    monkeypatch.setitem(sys.modules, "foxglove", None)
    with pytest.raises(RecordingError, match="foxglove-sdk"):
        LiveView(port=0).start()


def test_a_failing_tap_is_dropped_and_the_recording_goes_on(tmp_path: Path) -> None:
    """The recorder's hook: a tap that raises is logged to /log and removed; no message lost."""
    calls: list[str] = []

    def broken(topic: str, message: object, data: bytes, log_time_ns: int) -> None:
        calls.append(topic)
        raise RuntimeError("live view broke")

    with Recorder(tmp_path / "t.mcap", min_free_disk_bytes=0, tap=broken) as rec:
        h = rec.add_stream("/d415/c0/ir", ImageMsg)
        img = ImageMsg(np.zeros((4, 4), np.uint8), "mono8")
        for k in range(20):
            rec.put(h, img, sequence=k)
            time.sleep(0.005)
    st = {s.topic: s for s in rec.status().streams}
    assert (st["/d415/c0/ir"].written, st["/d415/c0/ir"].dropped) == (20, 0)
    assert len(calls) == 1
    assert any("live view stopped" in m for m in _log_messages(tmp_path / "t.mcap"))


def _log_messages(path: Path) -> list[str]:
    with Recording(path) as r:
        return [msg.message for _, msg in r.decoded("/log")]


class _Camera:
    """A stand-in source: one IR stream at 30 Hz."""

    name = "cam"

    def declare(self, recorder: Recorder) -> None:
        self._h = recorder.add_stream("/d415/c0/ir", ImageMsg)

    def run(self, recorder: Recorder, stop: threading.Event) -> None:
        img = ImageMsg(np.zeros((48, 64), np.uint8), "mono8")
        k = 0
        while not stop.wait(1 / 30):
            recorder.put(self._h, img, sequence=k)
            k += 1


def test_record_command_serves_live_and_reports_its_drops(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``record(live=True)`` (what ``--live`` runs): the URL on stderr, the view's counts in the
    JSON summary next to the recording's."""
    code = record(
        out=tmp_path / "s.mcap",
        seconds=1.0,
        mock=False,
        rig=None,
        sources=[_Camera()],
        live=True,
        live_port=0,
        as_json=True,
    )
    out = capsys.readouterr()
    summary = json.loads(out.out)
    assert code == 0
    assert "live view: ws://127.0.0.1:" in out.err
    assert summary["drops_total"] == 0
    assert summary["live"]["dropped_total"] >= 0


class _Scene:
    """A stand-in live scene: counts what it is offered, fails on demand."""

    def __init__(self, *, fail: bool) -> None:
        self.fail = fail
        self.offered: list[str] = []
        self.closed = False

    def offer(self, topic: str, message: object, log_time_ns: int) -> None:
        self.offered.append(topic)
        if self.fail:
            raise RuntimeError("scene broke")

    def take(self) -> list[tuple[str, object, int]]:
        return []

    def close(self) -> None:
        self.closed = True


def test_a_scene_is_offered_every_message_and_a_failing_one_is_dropped(tmp_path: Path) -> None:
    for fail in (False, True):
        scene = _Scene(fail=fail)
        with LiveView(port=0, scene=scene) as live:  # type: ignore[arg-type]
            drops = _record(tmp_path, f"scene{fail}", 0.5, live)
            assert (live._scene is None) == fail
        assert drops == 0
        assert scene.closed
        if fail:
            assert len(scene.offered) == 1
        else:
            assert {"/d415/c0/ir", "/d415/c0/depth", "/davis/x/events"} <= set(scene.offered)


def test_a_client_whose_server_went_away_sends_nothing_and_raises_nothing() -> None:
    client = LiveClient("127.0.0.1", 1)
    mine, theirs = socket.socketpair()
    theirs.close()
    client._sock = mine  # as after connect(), the server gone since
    try:
        for _ in range(3):  # the first send may still be buffered; a later one breaks the pipe
            client._send_text(json.dumps({"op": "subscribe", "subscriptions": []}))
    finally:
        mine.close()
