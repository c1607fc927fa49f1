"""Recorder throughput against the rig's data rate and the raw disk, in one run.

Cells (all with the recorder's defaults: lz4, 1 MiB chunks, one writer thread):

1. **raw disk**: 4 MiB blocks written to the output folder, then ``fsync``: MB/s.
2. **rig**: the mock rig of issue 5 for ``--seconds`` (default 30): 4 × D415 848×480@30 (IR
   mono8 + depth 16UC1) and a DAVIS240C at 5 M events/s (1 kHz packets) + 240×180 frames at
   25 Hz + IMU at 1 kHz (100 packets/s), each stream from its own producer thread paced on the
   wall clock with pre-built payloads, ``put()`` never blocking. Per-stream drops, achieved
   MB/s on disk (file bytes / wall time including the final ``fsync``).
3. **saturation**: depth frames put as fast as the recorder accepts (5 s): the recorder's
   ceiling in MB/s on disk, and its ratio to the raw disk speed of cell 1.
4. **largest rig**: 10 s each of 1–4 × D415 848×480@30, 4 × 1280×720@30 and 4 × 848×480@90
   (+ the DAVIS): the largest data rate that records with zero drops on this machine (the
   per-stream queues hold ~2 s of frames, so a cell of 10 s shows a sustained deficit).

5. **live view** (``--live``): the rig of cell 2 recorded again, for as long, with the Foxglove
   live view behind the recorder (``acquire/live_view.py``) and a WebSocket client subscribed to
   every channel: the recorder's drops with and without it, and the rate each live image topic
   reached the client (docs/live-view.md).

Run: ``.venv/bin/python benchmarks/record_rig.py [--seconds 30] [--dir DIR] [--live]``. The last
line is one JSON object (``drops_total``, ``mb_per_s``, ``disk_mb_per_s``, ``ratio_to_disk``,
with ``--live`` also ``live``: drops with and without it, client rates per topic, ...).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.events import make_events
from mocaprig.acquire.live_view import LiveClient, LiveView
from mocaprig.acquire.recorder import Recorder, StreamHandle
from mocaprig.acquire.recording_format import IMU_DTYPE, EventPacket, ImageMsg, ImuPacket


def _depth_like(rng: np.random.Generator, h: int, w: int) -> npt.NDArray[np.uint16]:
    yy, xx = np.mgrid[0:h, 0:w]
    z = 1500 + 2 * xx + yy + rng.normal(0, 4, (h, w))
    z[rng.random((h, w)) < 0.03] = 0
    out: npt.NDArray[np.uint16] = z.astype(np.uint16)
    return out


def _ir_like(rng: np.random.Generator, h: int, w: int) -> npt.NDArray[np.uint8]:
    img = rng.normal(60, 12, (h, w)).clip(0, 255)
    for _ in range(40):  # saturated marker blobs
        y, x = rng.integers(5, h - 5), rng.integers(5, w - 5)
        img[y - 3 : y + 3, x - 3 : x + 3] = 255
    return img.astype(np.uint8)


@dataclass(frozen=True)
class _Stream:
    topic: str
    kind: type
    hz: float
    payloads: list[Any]
    queue_messages: int = 4096


def _rig_streams(
    rng: np.random.Generator,
    cams: int,
    w: int,
    h: int,
    fps: int,
    *,
    events_per_s: int = 5_000_000,
) -> list[_Stream]:
    """Paced streams of the rig: ``cams`` D415s (IR + depth at ``w``×``h``@``fps``) and the
    DAVIS (``events_per_s`` in 1 kHz packets, frames at 25 Hz, IMU at 1 kHz in 100 packets/s)."""
    out: list[_Stream] = []
    for c in range(cams):
        ir = [ImageMsg(_ir_like(rng, h, w), "mono8") for _ in range(4)]
        depth = [ImageMsg(_depth_like(rng, h, w), "16UC1") for _ in range(4)]
        out.append(_Stream(f"/d415/cam{c}/ir", ImageMsg, fps, ir, 64))
        out.append(_Stream(f"/d415/cam{c}/depth", ImageMsg, fps, depth, 64))
    n_ev = events_per_s // 1000  # 1 kHz packets
    packets = []
    for i in range(8):
        t = np.sort(rng.integers(0, 1000, n_ev)).astype(np.int64) + i * 1000
        ev = make_events(t, rng.integers(0, 240, n_ev), rng.integers(0, 180, n_ev), t % 2)
        packets.append(EventPacket(ev, seq=i))
    out.append(_Stream("/davis/x/events", EventPacket, 1000.0, packets))
    frames = [ImageMsg(rng.integers(0, 1024, (180, 240)).astype(np.uint16), "mono16")]
    out.append(_Stream("/davis/x/frame", ImageMsg, 25.0, frames, 256))
    imu = np.zeros(10, IMU_DTYPE)
    imu["t"] = np.arange(10) * 1000
    out.append(_Stream("/davis/x/imu", ImuPacket, 100.0, [ImuPacket(imu, 0)]))
    return out


def _payload_rate(streams: list[_Stream]) -> float:
    """The rig's data rate in MB/s of encoded payload (what the recorder must write)."""
    return sum(s.hz * float(np.mean([len(p.encode()) for p in s.payloads])) for s in streams) / 1e6


def raw_disk_mb_per_s(folder: Path, total_mb: int = 768) -> float:
    """Raw sequential write speed with fsync (MB/s)."""
    block = np.random.default_rng(1).integers(0, 256, 4 << 20, dtype=np.uint8).tobytes()
    path = folder / "raw_disk.bin"
    n = max(1, total_mb // 4)
    t0 = time.perf_counter()
    with path.open("wb") as f:
        for _ in range(n):
            f.write(block)
        f.flush()
        os.fsync(f.fileno())
    wall = time.perf_counter() - t0
    path.unlink()
    return n * len(block) / wall / 1e6


def start_producers(
    rec: Recorder, streams: list[_Stream], handles: list[StreamHandle], stop: threading.Event
) -> list[threading.Thread]:
    """One started thread per stream putting its payloads at its rate on the wall clock
    (``put()``, never blocking) until ``stop`` is set."""

    def produce(s: _Stream, h: StreamHandle) -> None:
        period = 1.0 / s.hz
        start = time.perf_counter()
        i = 0
        while not stop.is_set():
            due = start + i * period
            now = time.perf_counter()
            if due > now:
                time.sleep(min(due - now, 0.05))
                continue
            rec.put(h, s.payloads[i % len(s.payloads)], sequence=i)
            i += 1

    threads = [
        threading.Thread(target=produce, args=(s, h), daemon=True)
        for s, h in zip(streams, handles, strict=True)
    ]
    for th in threads:
        th.start()
    return threads


def record_cell(
    folder: Path,
    name: str,
    streams: list[_Stream],
    seconds: float,
    *,
    live: LiveView | None = None,
) -> dict[str, Any]:
    """Record paced producers for ``seconds``; drops per stream and MB/s on disk (with fsync).
    With ``live``, the live view is fed behind the recorder (``Recorder(tap=...)``)."""
    path = folder / f"{name}.mcap"
    rec = Recorder(path, min_free_disk_bytes=0, tap=None if live is None else live.tap)
    if live is not None:
        live.follow(rec)
    stop = threading.Event()
    t0 = time.perf_counter()
    with rec:
        handles: list[StreamHandle] = [
            rec.add_stream(s.topic, s.kind, queue_messages=s.queue_messages) for s in streams
        ]

        t0 = time.perf_counter()
        threads = start_producers(rec, streams, handles, stop)
        time.sleep(seconds)
        stop.set()
        for th in threads:
            th.join()
    with path.open("rb+") as f:
        os.fsync(f.fileno())
    wall = time.perf_counter() - t0
    size = path.stat().st_size
    st = {s.topic: s for s in rec.status().streams}
    path.unlink()
    per_stream = {s.topic: st[s.topic].dropped for s in streams}
    received = sum(st[s.topic].received for s in streams)
    return {
        "seconds": round(wall, 2),
        "payload_mb_per_s_nominal": round(_payload_rate(streams), 1),
        "payload_mb_per_s_written": round(
            sum(st[s.topic].bytes_written for s in streams) / wall / 1e6, 1
        ),
        "mb_per_s": round(size / wall / 1e6, 1),
        "drops_total": int(sum(per_stream.values())),
        "drop_fraction": round(sum(per_stream.values()) / max(received, 1), 4),
        "drops_per_stream": per_stream,
        "peak_queued_mb": round(rec.peak_queued_bytes / 1e6, 1),
    }


def live_cell(folder: Path, streams: list[_Stream], seconds: float) -> dict[str, Any]:
    """The rig recorded with the live view and a subscribed client: recorder drops, live rates."""
    with LiveView(port=0) as live, LiveClient("127.0.0.1", live.port) as client:
        cell = record_cell(folder, "rig_live", streams, seconds, live=live)
        stats = live.stats()
        rates = {t: round(client.rate_hz(t, skip_s=1.0), 1) for t in sorted(client.channels)}
    cams = [r for t, r in rates.items() if t.startswith("/d415/")]
    return {
        **cell,
        "live_rates_hz": rates,
        "live_min_camera_rate_hz": min(cams, default=0.0),
        "live_published_total": stats.published_total,
        "live_dropped_total": stats.dropped_total,
        "live_dropped_per_topic": dict(stats.dropped),
        "live_decimated_total": stats.decimated_total,
    }


def saturation_cell(folder: Path, seconds: float) -> dict[str, float]:
    """Depth frames as fast as ``put()`` accepts: the recorder's ceiling on disk (MB/s)."""
    rng = np.random.default_rng(0)
    path = folder / "saturate.mcap"
    rec = Recorder(path, min_free_disk_bytes=0)
    stop = threading.Event()
    msgs = [ImageMsg(_depth_like(rng, 480, 848), "16UC1") for _ in range(8)]
    with rec:
        h = rec.add_stream("/d415/x/depth", ImageMsg, queue_messages=64)

        def produce() -> None:
            i = 0
            while not stop.is_set():
                if not rec.put(h, msgs[i % len(msgs)]):
                    time.sleep(0.001)  # queue full: let the writer run
                i += 1

        th = threading.Thread(target=produce)
        t0 = time.perf_counter()
        th.start()
        time.sleep(seconds)
        stop.set()
        th.join()
    with path.open("rb+") as f:
        os.fsync(f.fileno())
    wall = time.perf_counter() - t0
    size = path.stat().st_size
    path.unlink()
    return {"mb_per_s": round(size / wall / 1e6, 1)}


_CANDIDATES = (
    (1, 848, 480, 30),
    (2, 848, 480, 30),
    (3, 848, 480, 30),
    (4, 848, 480, 30),
    (4, 1280, 720, 30),
    (4, 848, 480, 90),
)
"""Rigs tried for "the largest that holds" (D415 count, width, height, fps; + the DAVIS)."""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=30.0, help="length of the rig cell (s)")
    ap.add_argument("--cell-seconds", type=float, default=10.0, help="other cells (s)")
    ap.add_argument("--dir", type=Path, default=None, help="where to write (default: a temp dir)")
    ap.add_argument(
        "--live", action="store_true", help="also record the rig with the live view and a client"
    )
    args = ap.parse_args()
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        folder = Path(d)
        disk = raw_disk_mb_per_s(folder)
        print(f"raw disk (4 MiB blocks + fsync): {disk:.0f} MB/s", flush=True)
        rng = np.random.default_rng(0)
        rig_streams = _rig_streams(rng, 4, 848, 480, 30)
        rig = record_cell(folder, "rig", rig_streams, args.seconds)
        print("rig 4x848x480@30 + DAVIS 5 Mev/s:", json.dumps(rig), flush=True)
        live: dict[str, Any] | None = None
        if args.live:  # the same rig (its payloads are only read)
            live = live_cell(folder, rig_streams, args.seconds)
            print("rig with the live view + a client:", json.dumps(live), flush=True)
        del rig_streams  # not held through the cells below
        sat = saturation_cell(folder, 5.0)
        print(f"saturation (depth frames, lz4): {sat['mb_per_s']} MB/s", flush=True)
        rigs: dict[str, dict[str, Any]] = {}
        for n, w, h, fps in _CANDIDATES:
            key = f"{n}x{w}x{h}@{fps}"
            cell = record_cell(folder, key, _rig_streams(rng, n, w, h, fps), args.cell_seconds)
            rigs[key] = cell
            print(key, json.dumps(cell), flush=True)
    holding = [k for k, v in rigs.items() if v["drops_total"] == 0]
    largest = max(holding, key=lambda k: rigs[k]["payload_mb_per_s_nominal"], default=None)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3
    result = {
        "benchmark": "record_rig",
        "machine": f"{os.cpu_count()} cores {platform.machine()}, load {load_before[0]:.1f}",
        "load_avg_1min_before": round(load_before[0], 1),
        "load_avg_1min_after": round(os.getloadavg()[0], 1),
        "rig": "4x D415 848x480@30 IR+depth, DAVIS 5 M ev/s + frames 25 Hz + IMU 1 kHz",
        "rig_seconds": rig["seconds"],
        "drops_total": rig["drops_total"],
        "drops_per_stream": rig["drops_per_stream"],
        "payload_mb_per_s_nominal": rig["payload_mb_per_s_nominal"],
        "mb_per_s": rig["mb_per_s"],
        "disk_mb_per_s": round(disk, 1),
        "recorder_max_mb_per_s": sat["mb_per_s"],
        "ratio_to_disk": round(sat["mb_per_s"] / disk, 2),
        "largest_rig_that_holds": largest,
        "rigs": {
            k: {
                "drops_total": v["drops_total"],
                "mb_per_s": v["mb_per_s"],
                "payload_mb_per_s_nominal": v["payload_mb_per_s_nominal"],
            }
            for k, v in rigs.items()
        },
        "peak_rss_mb": round(rss),
    }
    if live is not None:
        result["live"] = {
            "drops_without": rig["drops_total"],
            "drops_with": live["drops_total"],
            "drops_per_stream_with": live["drops_per_stream"],
            "mb_per_s_with": live["mb_per_s"],
            "rates_hz": live["live_rates_hz"],
            "min_camera_rate_hz": live["live_min_camera_rate_hz"],
            "published_total": live["live_published_total"],
            "live_dropped_total": live["live_dropped_total"],
            "live_dropped_per_topic": live["live_dropped_per_topic"],
            "decimated_total": live["live_decimated_total"],
        }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
