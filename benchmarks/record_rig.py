"""Recorder throughput on this machine: how many bytes/s and messages/s reach the file.

Feeds the Recorder from producer threads as fast as ``put()`` accepts (never blocking), with
pre-built payloads, and reports what was written, what was dropped, the peak of queued bytes and
the process's peak RSS. Run: ``.venv/bin/python benchmarks/record_rig.py [--seconds 5]``.
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from acquire.events import make_events
from acquire.recorder import Recorder
from acquire.recording_format import EventPacket, ImageMsg


def _depth_like(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    z = 1500 + 2 * xx + yy + rng.normal(0, 4, (h, w))
    z[rng.random((h, w)) < 0.03] = 0
    out: np.ndarray = z.astype(np.uint16)
    return out


def run(kind: str, compression: str, seconds: float) -> dict[str, float]:
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "bench.mcap"
        rec = Recorder(path, compression=compression, min_free_disk_bytes=0)  # type: ignore[arg-type]
        stop = threading.Event()
        with rec:
            if kind == "depth":
                h = rec.add_stream("/d415/x/depth", ImageMsg, queue_messages=64)
                msgs: list[Any] = [ImageMsg(_depth_like(rng, 480, 848), "16UC1") for _ in range(8)]
            else:
                h = rec.add_stream("/davis/x/events", EventPacket)
                t = np.sort(rng.integers(0, 10_000, 10_000)).astype(np.int64)
                ev = make_events(t, rng.integers(0, 240, t.size), rng.integers(0, 180, t.size),
                                 t % 2)  # fmt: skip
                msgs = [EventPacket(ev, seq=i) for i in range(8)]

            def produce() -> None:
                i = 0
                while not stop.is_set():
                    rec.put(h, msgs[i % len(msgs)])
                    i += 1
                    if i % 4 == 0:
                        time.sleep(0.0005)

            th = threading.Thread(target=produce)
            t0 = time.perf_counter()
            th.start()
            time.sleep(seconds)
            stop.set()
            th.join()
        wall = time.perf_counter() - t0
        st = {s.topic: s for s in rec.status().streams}[h.topic]
        size = path.stat().st_size
        payload = st.bytes_written
    return {
        "written_msgs_per_s": st.written / wall,
        "payload_MB_per_s": payload / wall / 1e6,
        "file_MB_per_s": size / wall / 1e6,
        "drop_fraction": st.dropped / max(st.received, 1),
        "peak_queued_MB": rec.peak_queued_bytes / 1e6,
        "memory_bound_MB": rec.memory_bound_bytes / 1e6,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=4.0)
    args = ap.parse_args()
    for kind in ("depth", "events"):
        for comp in ("lz4", "zstd", "none"):
            r = run(kind, comp, args.seconds)
            print(kind, comp, " ".join(f"{k}={v:.3g}" for k, v in r.items()))
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3
    print(f"peak RSS {rss:.0f} MB")


if __name__ == "__main__":
    main()
