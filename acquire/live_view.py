"""The live view: a recording's streams served to Foxglove while it records (``record --live``).

Usage::

    with LiveView(port=8765) as live, Recorder(path, tap=live.tap) as rec:
        live.follow(rec)                      # /live/status from rec.status()
        ...                                   # sources put() into rec as usual

The live view reads **behind** the recorder: the recorder's writer thread calls :meth:`LiveView.tap`
with each message it has written (payload, encoded bytes, log time). The tap takes a lock for a
few instructions and returns: it decimates images by host time, then puts the message into the
live topic's single slot (latest wins; a message replaced before it was published is the live
view's own drop, counted in :attr:`LiveStats.dropped`). The publisher thread empties the slots
every ``tick_s`` and publishes them outside the lock through foxglove-sdk's WebSocket server,
whose per-client queue (``backlog_messages``) drops the oldest message for a slow client. Nothing
the live view does can hold up the writer or fill a recorder queue.

Published over the Foxglove WebSocket protocol (the app's "Foxglove WebSocket" connection;
foxglove-sdk 0.30 names the subprotocol ``foxglove.sdk.v1`` and refuses ``foxglove.websocket.v1``
alone, :class:`LiveClient` offers both):

* every ``foxglove.RawImage`` stream (D415 IR ``mono8`` and depth ``16UC1``, DAVIS APS
  ``mono16``) on its recorded topic, decimated to ``image_hz`` per topic (the recorded bytes,
  not encoded again); ``foxglove.CameraCalibration``, ``foxglove.Log`` (``/log``, ``/faults``)
  and ``foxglove.SceneUpdate`` as recorded, the calibrations again at ``status_hz`` for clients
  that join late;
* ``<davis>/event_image``: the events of the last ``event_window_ms`` as an ``rgb8`` RawImage
  (ON green, OFF red, both yellow) at ``image_hz``;
* ``<davis>/imu_live``: JSON ``{t_us, accel_g {x,y,z}, gyro_dps {x,y,z}, temp_c}`` (the last
  sample of each IMU packet taken; Plot panel paths such as ``/davis/X/imu_live.accel_g.x``);
* ``/live/status``: JSON at ``status_hz`` with the recorder's per-stream received / written /
  dropped, the sync box state, the faults and the live view's own counts.

foxglove-sdk is optional (``pip install 'mocaprig[live]'``); it is imported by :meth:`start`.
"""

from __future__ import annotations

import base64
import collections
import contextlib
import json
import logging
import os
import socket
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Final, Literal, Protocol, Self

import numpy as np
import numpy.typing as npt
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from mocaprig.acquire.recording_format import (
    EventPacket,
    ImageMsg,
    ImuPacket,
    RecordedPayload,
    SchemaDef,
)
from mocaprig.errors import RecordingError, ValidationError

if TYPE_CHECKING:
    import foxglove

    from mocaprig.acquire.recorder import Recorder

__all__ = [
    "LIVE_SCENE_GROUP",
    "LIVE_STATUS_TOPIC",
    "LiveClient",
    "LiveScene",
    "LiveStats",
    "LiveView",
    "load_live_scene",
]

_log = logging.getLogger(__name__)

LIVE_STATUS_TOPIC: Final = "/live/status"
_RAW_IMAGE: Final = ImageMsg.SCHEMA.name  # foxglove.RawImage
_PASS_SCHEMAS: Final = frozenset(
    {"foxglove.CameraCalibration", "foxglove.Log", "foxglove.SceneUpdate"}
)
_Kind = Literal["image", "pass", "events", "imu", "ignore"]
_IMU_SCHEMA: Final[dict[str, Any]] = {
    "title": "mocaprig.LiveImu",
    "type": "object",
    "properties": {
        "t_us": {"type": "integer", "description": "device time of the sample (µs)"},
        "accel_g": {"type": "object", "description": "acceleration (g), x y z"},
        "gyro_dps": {"type": "object", "description": "angular rate (°/s), x y z"},
        "temp_c": {"type": "number", "description": "IMU temperature (°C)"},
    },
}


@dataclass(frozen=True, slots=True)
class LiveStats:
    """What the live view did, per live topic (messages).

    Attributes:
        offered: Messages taken from the recorder (after decimation).
        published: Messages handed to the server while a client was subscribed.
        dropped: Its own drops: replaced by a newer one before publishing (latest wins).
        decimated: Images skipped to hold ``image_hz`` (by design, not drops).
    """

    offered: Mapping[str, int] = field(default_factory=dict)
    published: Mapping[str, int] = field(default_factory=dict)
    dropped: Mapping[str, int] = field(default_factory=dict)
    decimated: Mapping[str, int] = field(default_factory=dict)

    @property
    def dropped_total(self) -> int:
        return sum(self.dropped.values())

    @property
    def published_total(self) -> int:
        return sum(self.published.values())

    @property
    def decimated_total(self) -> int:
        return sum(self.decimated.values())

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready totals and per-topic counts."""
        return {
            "published_total": self.published_total,
            "dropped_total": self.dropped_total,
            "decimated_total": self.decimated_total,
            "published": dict(self.published),
            "dropped": dict(self.dropped),
        }


@dataclass(slots=True)
class _EventWindow:
    """Event packets of one DAVIS, trimmed to the window (publisher thread only)."""

    packets: collections.deque[npt.NDArray[np.void]] = field(
        default_factory=lambda: collections.deque(maxlen=512)
    )
    width: int = 240
    height: int = 180
    frame_id: str = ""
    newest_us: int = -(2**62)
    log_time: int = 0
    rendered: float = 0.0


def _route(topic: str, message: RecordedPayload) -> tuple[_Kind, str]:
    """What the live view does with a recorded topic: (kind, live topic)."""
    name = message.SCHEMA.name
    base = topic.rsplit("/", 1)[0]
    if name == _RAW_IMAGE:
        return "image", topic
    if name in _PASS_SCHEMAS:
        return "pass", topic
    if isinstance(message, EventPacket):
        return "events", f"{base}/event_image"
    if isinstance(message, ImuPacket):
        return "imu", f"{base}/imu_live"
    return "ignore", topic


def _event_image(ev: npt.NDArray[np.void], width: int, height: int) -> npt.NDArray[np.uint8]:
    """(height, width, 3) ``rgb8``: pixels with ON events green, OFF red, both yellow."""
    x = ev["x"].astype(np.intp)
    y = ev["y"].astype(np.intp)
    on = ev["p"] > 0
    inside = (x < width) & (y < height)
    idx = y * width + x
    img = np.zeros((height * width, 3), np.uint8)
    img[np.bincount(idx[inside & on], minlength=height * width) > 0, 1] = 255
    img[np.bincount(idx[inside & ~on], minlength=height * width) > 0, 0] = 255
    return img.reshape(height, width, 3)


def _rgb_raw_image(img: npt.NDArray[np.uint8], timestamp_ns: int, frame_id: str) -> bytes:
    """``foxglove.RawImage`` bytes of an ``rgb8`` image (:class:`ImageMsg` holds mono only)."""
    h, w = img.shape[:2]
    pb = RawImage(frame_id=frame_id, width=w, height=h, encoding="rgb8", step=3 * w)
    pb.data = np.ascontiguousarray(img).tobytes()
    pb.timestamp.FromNanoseconds(max(timestamp_ns, 0))
    return bytes(pb.SerializeToString())


def _xyz(v: npt.NDArray[Any]) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


class LiveScene(Protocol):
    """Something that turns recorded messages into more to show (3D scene updates), without
    making the recorder wait: ``mocaprig record --live --calib`` loads one through the
    ``mocaprig.live_scene`` entry point (``process.democap.live_scene``)."""

    def offer(self, topic: str, message: RecordedPayload, log_time_ns: int) -> None:
        """A message as it is written (writer thread): keep what is needed, return at once."""

    def take(self) -> list[tuple[str, RecordedPayload, int]]:
        """What to publish now (publisher thread): ``(topic, message, log_time_ns)``."""

    def close(self) -> None:
        """Stop its work (the view is closing)."""


#: Entry point group of the live scenes (``democap``: the markers and joints in 3D).
LIVE_SCENE_GROUP: Final = "mocaprig.live_scene"


def load_live_scene(name: str, calibration: Path, **options: Any) -> LiveScene:
    """The live scene ``name`` of the ``mocaprig.live_scene`` entry points, made for the
    calibration file ``calibration``.

    Raises:
        RecordingError: no such entry point, or it cannot be loaded.
        CalibrationError: the calibration cannot be read or has no D415 (from the scene).
    """
    import importlib.metadata

    eps = importlib.metadata.entry_points(group=LIVE_SCENE_GROUP)
    if name not in eps.names:
        msg = (
            f"no live scene '{name}' is registered in the '{LIVE_SCENE_GROUP}' entry points; "
            "reinstall mocaprig (pip install -e .)"
        )
        raise RecordingError(msg)
    try:
        factory = eps[name].load()
    except Exception as err:  # an import error in the process package, whatever its type
        msg = f"cannot load the live scene '{name}' ({eps[name].value}): {err}"
        raise RecordingError(msg) from err
    scene: LiveScene = factory(calibration, **options)
    return scene


class LiveView:
    """A Foxglove WebSocket server fed behind a :class:`~mocaprig.acquire.recorder.Recorder`;
    a context manager (see the module doc).

    Args:
        host: Address to listen on (``0.0.0.0``: every interface).
        port: TCP port (0: any free port, see :attr:`port`).
        image_hz: Most images per second published per image topic (and event images).
        event_window_ms: Time span of events in one event image (ms of device time).
        status_hz: Rate of ``/live/status`` (Hz).
        tick_s: Period of the publisher thread (s).
        backlog_messages: Messages the server queues per client before dropping the oldest.
        name: Server name shown by the Foxglove app.
        scene: A :class:`LiveScene` offered every recorded message, whose scene updates are
            published (``record --live --calib``: the markers and joints in 3D); closed with
            the view. One that raises is dropped (logged), the view goes on without it.

    Raises:
        ValidationError: a rate, window or period is not > 0, or the port is out of range.
    """

    def __init__(
        self,
        *,
        host: str = "127.0.0.1",
        port: int = 8765,
        image_hz: float = 15.0,
        event_window_ms: float = 33.0,
        status_hz: float = 1.0,
        tick_s: float = 0.01,
        backlog_messages: int = 32,
        name: str = "mocaprig record",
        scene: LiveScene | None = None,
    ) -> None:
        for what, value in (
            ("image_hz", image_hz),
            ("event_window_ms", event_window_ms),
            ("status_hz", status_hz),
            ("tick_s", tick_s),
            ("backlog_messages", backlog_messages),
        ):
            if not value > 0:
                msg = f"live view {what} must be > 0, got {value!r}"
                raise ValidationError(msg)
        if not 0 <= port <= 65535:
            msg = f"live view port must be 0..65535 (0: any free port), got {port}"
            raise ValidationError(msg)
        self.host = host
        self.image_hz = image_hz
        self.event_window_ms = event_window_ms
        self.status_hz = status_hz
        self.tick_s = tick_s
        self.backlog_messages = backlog_messages
        self.name = name
        self._want_port = port
        self._period_ns = int(1e9 / image_hz)
        self._tol_ns = self._period_ns // 4
        self._window_us = int(event_window_ms * 1000)
        # Shared with the writer thread (tap), guarded by _lock, held for a few instructions.
        self._lock = threading.Lock()
        self._pending: dict[str, tuple[_Kind, RecordedPayload, bytes, int]] = {}
        self._packets: dict[str, collections.deque[tuple[EventPacket, int]]] = {}
        self._offered: collections.Counter[str] = collections.Counter()
        self._dropped: collections.Counter[str] = collections.Counter()
        self._decimated: collections.Counter[str] = collections.Counter()
        # Writer thread only.
        self._routes: dict[str, tuple[_Kind, str]] = {}
        self._due: dict[str, int] = {}
        # Publisher thread only (and stats()).
        self._published: collections.Counter[str] = collections.Counter()
        self._windows: dict[str, _EventWindow] = {}
        self._channels: dict[str, foxglove.Channel] = {}
        self._latched: dict[str, tuple[bytes, int]] = {}  # camera_info, again at status_hz
        self._sync_seen: tuple[int, float] = (0, 0.0)
        self._recorder: Recorder | None = None
        self._scene = scene
        self._context: foxglove.Context | None = None
        self._server: foxglove.websocket.WebSocketServer | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._closed = False

    # ---------------------------------------------------------------------------- lifecycle

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def start(self) -> None:
        """Start the WebSocket server and the publisher thread.

        Raises:
            RecordingError: foxglove-sdk is not installed, or the port cannot be bound (taken).
        """
        if self._thread is not None:
            msg = "live view is already started; use one LiveView per recording"
            raise RecordingError(msg)
        try:
            import foxglove  # optional extra
        except ImportError as err:
            msg = (
                "--live needs foxglove-sdk, which is not installed: pip install 'mocaprig[live]' "
                f"(or 'foxglove-sdk>=0.30'), or record without --live ({err})"
            )
            raise RecordingError(msg) from err
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(
                name=self.name,
                host=self.host,
                port=self._want_port,
                context=self._context,
                message_backlog_size=self.backlog_messages,
            )
        except Exception as err:
            msg = (
                f"cannot serve the live view on {self.host}:{self._want_port}: {err}; the port "
                "is probably taken (another `record --live`, a Foxglove bridge): choose another "
                "with --port (0: any free port) or stop what holds it"
            )
            raise RecordingError(msg) from err
        # Declared before any client connects: foxglove-sdk 0.30 refuses a subscription to the
        # first channel of a context when it was declared while a client was connected.
        self._channel(LIVE_STATUS_TOPIC, None)
        self._thread = threading.Thread(target=self._run, name="mocaprig-live", daemon=True)
        self._thread.start()
        _log.info("live view: %s (Foxglove: Open connection -> Foxglove WebSocket)", self.url)

    def close(self) -> None:
        """Stop publishing and the server (idempotent)."""
        self._closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self._server is not None:
            with contextlib.suppress(Exception):
                self._server.stop()
            self._server = None
        scene, self._scene = self._scene, None
        if scene is not None:
            with contextlib.suppress(Exception):
                scene.close()

    def follow(self, recorder: Recorder) -> None:
        """Publish ``recorder``'s counters and faults on ``/live/status`` (its messages come
        through :meth:`tap`, given to the recorder as ``Recorder(tap=...)``)."""
        self._recorder = recorder

    @property
    def port(self) -> int:
        """The TCP port served (the one chosen when started with port 0)."""
        return self._server.port if self._server is not None else self._want_port

    @property
    def url(self) -> str:
        """``ws://host:port`` for the Foxglove app."""
        return f"ws://{self.host}:{self.port}"

    def stats(self) -> LiveStats:
        """A snapshot of the counts (thread-safe)."""
        with self._lock:
            offered, dropped = dict(self._offered), dict(self._dropped)
            decimated = dict(self._decimated)
        return LiveStats(offered, dict(self._published), dropped, decimated)

    # ---------------------------------------------------------------------------- tap

    def tap(self, topic: str, message: RecordedPayload, data: bytes, log_time_ns: int) -> None:
        """The recorder's hook (writer thread): keep ``message`` for publishing; returns at once.

        Images are decimated by ``log_time_ns`` to ``image_hz``; a message still waiting in its
        live topic's slot is replaced (counted as a live drop).
        """
        if self._closed:
            return
        scene = self._scene
        if scene is not None:
            try:
                scene.offer(topic, message, log_time_ns)
            except Exception:
                self._scene = None
                _log.exception("live view: the 3D scene failed on %s; going on without it", topic)
                with contextlib.suppress(Exception):
                    scene.close()
        route = self._routes.get(topic)
        if route is None:
            route = self._routes[topic] = _route(topic, message)
        kind, live = route
        if kind == "ignore":
            return
        if kind == "image":
            due = self._due.get(topic)
            if due is not None and log_time_ns < due - self._tol_ns:
                with self._lock:
                    self._decimated[live] += 1
                return
            nxt = log_time_ns + self._period_ns
            self._due[topic] = (
                nxt if due is None else max(due + self._period_ns, nxt - self._tol_ns)
            )
        with self._lock:
            self._offered[live] += 1
            if kind == "events":
                dq = self._packets.get(live)
                if dq is None:
                    dq = self._packets[live] = collections.deque()
                if len(dq) >= 256:  # the publisher is > 0.25 s behind at 1 kHz packets
                    dq.popleft()
                    self._dropped[live] += 1
                dq.append((message, log_time_ns))  # type: ignore[arg-type]  # routed by type
                return
            if live in self._pending:
                self._dropped[live] += 1
            self._pending[live] = (kind, message, data, log_time_ns)

    # ---------------------------------------------------------------------------- publisher

    def _run(self) -> None:
        next_status = time.monotonic()
        failed = False
        while not self._stop.wait(self.tick_s):
            try:
                self._publish_pending()
                now = time.monotonic()
                if now >= next_status:
                    next_status = now + 1.0 / self.status_hz
                    self._publish_status()
                    for live, (data, log_time) in self._latched.items():
                        self._channels[live].log(data, log_time=log_time)
            except Exception:
                if not failed:  # once: a broken publisher must not flood the log
                    _log.exception("live view: publishing failed; it keeps trying")
                failed = True

    def _channel(self, topic: str, schema: SchemaDef | None) -> foxglove.Channel:
        ch = self._channels.get(topic)
        if ch is None:
            import foxglove  # optional extra (there once started)

            if schema is None:
                ch = foxglove.Channel(topic, schema=_json_schema(topic), context=self._context)
            else:
                fg_schema = foxglove.Schema(
                    name=schema.name, encoding=schema.encoding, data=schema.data
                )
                ch = foxglove.Channel(
                    topic, message_encoding="protobuf", schema=fg_schema, context=self._context
                )
            self._channels[topic] = ch
        return ch

    def _publish_pending(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, {}
            packets = {t: list(dq) for t, dq in self._packets.items() if dq}
            for dq in self._packets.values():
                dq.clear()
        for live, (kind, message, data, log_time) in pending.items():
            if kind == "imu":
                ch = self._channel(live, None)
                if ch.has_sinks():
                    ch.log(_imu_json(message), log_time=log_time)
                    self._published[live] += 1
            else:
                ch = self._channel(live, message.SCHEMA)
                if message.SCHEMA.name == "foxglove.CameraCalibration":
                    self._latched[live] = (data, log_time)
                if ch.has_sinks():
                    ch.log(data, log_time=log_time)
                    self._published[live] += 1
        for live, items in packets.items():
            self._events(live, items)
        scene = self._scene
        if scene is not None:
            for live, message, log_time in scene.take():
                ch = self._channel(live, message.SCHEMA)
                if ch.has_sinks():
                    ch.log(message.encode(), log_time=log_time)
                    self._published[live] += 1

    def _events(self, live: str, items: list[tuple[EventPacket, int]]) -> None:
        win = self._windows.get(live)
        if win is None:
            win = self._windows[live] = _EventWindow()
        for pk, log_time in items:
            if not len(pk.events):
                continue
            last = int(pk.events["t"][-1])
            if last < win.newest_us:  # device time went back (a re-open): start again
                win.packets.clear()
            win.packets.append(pk.events)
            win.newest_us, win.log_time = last, log_time
            win.width, win.height, win.frame_id = pk.width, pk.height, pk.frame_id
        start = win.newest_us - self._window_us
        while win.packets and int(win.packets[0]["t"][-1]) < start:
            win.packets.popleft()
        now = time.monotonic()
        if not win.packets or now - win.rendered < 1.0 / self.image_hz:
            return
        win.rendered = now
        ch = self._channel(live, ImageMsg.SCHEMA)
        if not ch.has_sinks():
            return
        ev = np.concatenate(list(win.packets))
        img = _event_image(ev[ev["t"] >= start], win.width, win.height)
        ch.log(_rgb_raw_image(img, win.newest_us * 1000, win.frame_id), log_time=win.log_time)
        self._published[live] += 1

    def _publish_status(self) -> None:
        rec = self._recorder
        if rec is None:
            return
        ch = self._channel(LIVE_STATUS_TOPIC, None)
        if not ch.has_sinks():
            return
        st = rec.status()
        faults = rec.faults
        sync_msgs = sum(s.written for s in st.streams if s.topic.startswith("/syncbox/"))
        box_faults = [f for f in faults if f.device == "syncbox"]
        now = time.monotonic()
        seen, since = self._sync_seen
        if sync_msgs != seen or since == 0.0:
            self._sync_seen = (sync_msgs, now)
            since = now
        if not any(s.topic.startswith("/syncbox/") for s in st.streams):
            sync = "none"
        elif box_faults and box_faults[-1].lost:
            sync = "lost"
        else:
            sync = "ok" if now - since < 2.0 else "stalled"
        live = self.stats()
        msg = {
            "elapsed_s": st.elapsed_ns / 1e9,
            "bytes_written": st.bytes_written,
            "free_disk_bytes": st.free_disk_bytes,
            "file_index": st.file_index,
            "dropped_total": st.dropped_total,
            "streams": [
                {
                    "topic": s.topic,
                    "received": s.received,
                    "written": s.written,
                    "dropped": s.dropped,
                    "queued": s.queued,
                }
                for s in st.streams
            ],
            "sync": {"state": sync, "messages": sync_msgs, "faults": len(box_faults)},
            "faults": len(faults),
            "last_fault": f"{faults[-1].device} {faults[-1].kind}: {faults[-1].detail}"
            if faults
            else "",
            "live": {
                "published": live.published_total,
                "dropped": live.dropped_total,
                "decimated": live.decimated_total,
            },
        }
        ch.log(msg, log_time=rec.clock_ns())


def _json_schema(topic: str) -> dict[str, Any]:
    if topic == LIVE_STATUS_TOPIC:
        return {"title": "mocaprig.LiveStatus", "type": "object"}
    return _IMU_SCHEMA


def _imu_json(message: RecordedPayload) -> dict[str, Any]:
    """The last sample of an :class:`ImuPacket` as JSON (Plot panels)."""
    samples = message.samples  # type: ignore[attr-defined]  # routed by type
    s = samples[-1]
    return {
        "t_us": int(s["t"]),
        "accel_g": _xyz(s["accel_g"]),
        "gyro_dps": _xyz(s["gyro_dps"]),
        "temp_c": float(s["temp_c"]),
        "samples": len(samples),
    }


# -------------------------------------------------------------------------------------------
# A minimal client, for checks, tests and benchmarks


class LiveClient:
    """A minimal Foxglove WebSocket client (``foxglove.sdk.v1``, stdlib only) that
    subscribes to every advertised channel and counts messages per topic; a context manager.

    Args:
        host: Server address.
        port: Server port.
        read_delay_s: Sleep after each message received (a slow client; 0: read at once).
        timeout_s: Connect and handshake timeout (s).

    Raises:
        RecordingError: the server cannot be reached or refuses the protocol.
    """

    def __init__(
        self, host: str, port: int, *, read_delay_s: float = 0.0, timeout_s: float = 5.0
    ) -> None:
        self.host = host
        self.port = port
        self.read_delay_s = read_delay_s
        self.timeout_s = timeout_s
        self._lock = threading.Lock()
        self._channels: dict[int, tuple[str, str]] = {}  # channel id -> (topic, schema name)
        self._subs: dict[int, str] = {}  # subscription id -> topic
        self._times: dict[str, list[float]] = {}
        self._last: dict[str, bytes] = {}
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._closing = threading.Event()

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def connect(self) -> None:
        """Open the connection, do the handshake and start reading (own thread)."""
        key = base64.b64encode(os.urandom(16)).decode()
        request = (
            f"GET / HTTP/1.1\r\nHost: {self.host}:{self.port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
            "Sec-WebSocket-Protocol: foxglove.sdk.v1, foxglove.websocket.v1\r\n\r\n"
        )
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
            sock.sendall(request.encode())
            head = b""
            while b"\r\n\r\n" not in head:
                chunk = sock.recv(1)
                if not chunk:
                    break
                head += chunk
        except OSError as err:
            msg = f"cannot connect to the live view at ws://{self.host}:{self.port}: {err}"
            raise RecordingError(msg) from err
        if b" 101 " not in head.split(b"\r\n", 1)[0]:
            sock.close()
            msg = f"ws://{self.host}:{self.port} refused the Foxglove handshake: {head[:80]!r}"
            raise RecordingError(msg)
        sock.settimeout(None)
        self._sock = sock
        self._thread = threading.Thread(target=self._read, name="live-client", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Close the connection and stop reading."""
        self._closing.set()
        if self._sock is not None:
            with contextlib.suppress(OSError):  # a close frame (masked, empty), then the socket
                self._sock.sendall(bytes([0x88, 0x80]) + os.urandom(4))
            with contextlib.suppress(OSError):
                self._sock.shutdown(socket.SHUT_RDWR)
            self._sock.close()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    @property
    def channels(self) -> dict[str, str]:
        """Advertised topics and their schema names."""
        with self._lock:
            return dict(self._channels.values())

    def counts(self) -> dict[str, int]:
        """Messages received per topic."""
        with self._lock:
            return {t: len(v) for t, v in self._times.items()}

    def rate_hz(self, topic: str, *, skip_s: float = 0.0) -> float:
        """Messages per second received on ``topic`` (after the first ``skip_s`` s of it)."""
        with self._lock:
            times = list(self._times.get(topic, ()))
        times = [t for t in times if times and t >= times[0] + skip_s]
        if len(times) < 2:
            return 0.0
        return (len(times) - 1) / (times[-1] - times[0])

    def last(self, topic: str) -> bytes | None:
        """The payload of the last message received on ``topic``."""
        with self._lock:
            return self._last.get(topic)

    def _send_text(self, text: str) -> None:
        payload = np.frombuffer(text.encode(), np.uint8)
        mask = np.frombuffer(os.urandom(4), np.uint8)
        n = len(payload)
        if n < 126:
            head = bytes([0x81, 0x80 | n])
        elif n < 1 << 16:
            head = bytes([0x81, 0x80 | 126]) + n.to_bytes(2, "big")
        else:
            head = bytes([0x81, 0x80 | 127]) + n.to_bytes(8, "big")
        masked = payload ^ np.resize(mask, n)
        if self._sock is None:
            return
        try:
            self._sock.sendall(head + mask.tobytes() + masked.tobytes())
        except OSError:
            # the server went away (a retried subscription runs on a timer thread, after the
            # connection may have ended): what the client received stays readable
            _log.debug("live client: could not send %d bytes, connection ended", n, exc_info=True)

    def _read(self) -> None:
        assert self._sock is not None
        f = self._sock.makefile("rb")
        try:
            while not self._closing.is_set():
                opcode, payload = _read_frame(f)
                if opcode == 0x8:
                    return
                if opcode == 0x9:  # ping: the reply is a pong frame, sent masked
                    mask = os.urandom(4)
                    body = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
                    self._sock.sendall(bytes([0x8A, 0x80 | len(body)]) + mask + body)
                elif opcode == 0x1:
                    self._on_text(json.loads(payload))
                elif opcode == 0x2 and payload[:1] == b"\x01":
                    sub = int.from_bytes(payload[1:5], "little")
                    with self._lock:
                        topic = self._subs.get(sub)
                        if topic is not None:
                            self._times.setdefault(topic, []).append(time.monotonic())
                            self._last[topic] = payload[13:]
                    if self.read_delay_s:
                        self._closing.wait(self.read_delay_s)
        except (OSError, ValueError, EOFError):
            if not self._closing.is_set():
                _log.debug("live client: connection ended", exc_info=True)
        finally:
            f.close()

    def _on_text(self, msg: dict[str, Any]) -> None:
        text = str(msg.get("message", ""))
        if msg.get("op") == "status" and text.startswith("Unknown channel ID: "):
            # foxglove-sdk 0.30 can advertise a channel a moment before it takes subscriptions
            cid = int(text.rsplit(" ", 1)[1])
            sub = json.dumps({"op": "subscribe", "subscriptions": [{"id": cid, "channelId": cid}]})
            retry = threading.Timer(0.05, self._send_text, args=(sub,))
            retry.daemon = True
            retry.start()
            return
        if msg.get("op") != "advertise":
            return
        subs = []
        with self._lock:
            for ch in msg.get("channels", []):
                cid = int(ch["id"])
                self._channels[cid] = (str(ch["topic"]), str(ch.get("schemaName", "")))
                self._subs[cid] = str(ch["topic"])  # subscription id = channel id
                subs.append({"id": cid, "channelId": cid})
        if subs:
            self._send_text(json.dumps({"op": "subscribe", "subscriptions": subs}))


def _read_frame(f: Any) -> tuple[int, bytes]:
    """One whole WebSocket message (fragments joined): (opcode, payload)."""
    opcode = -1
    out = b""
    while True:
        head = f.read(2)
        if len(head) < 2:
            raise EOFError
        fin, op, n = head[0] & 0x80, head[0] & 0x0F, head[1] & 0x7F
        if n == 126:
            n = int.from_bytes(f.read(2), "big")
        elif n == 127:
            n = int.from_bytes(f.read(8), "big")
        mask = f.read(4) if head[1] & 0x80 else b""
        data = f.read(n)
        if len(data) < n:
            raise EOFError
        if mask:
            data = bytes(b ^ mask[i % 4] for i, b in enumerate(data))
        if op != 0:
            opcode = op
        out += data
        if fin:
            return opcode, out
