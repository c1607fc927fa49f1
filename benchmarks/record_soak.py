"""A long recording with flat memory (issue 17 item 6).

The rig is first recorded for ``--check-seconds`` (default 10) to show that it holds on this
machine (0 drops); then the same rig is recorded for ``--minutes`` (default 30) with file
splitting on (``--split-mb``, default 1024), while this process's resident memory is sampled
every ``--sample-s`` seconds (``/proc/self/status`` VmRSS). Finished parts beyond the newest
``--keep-parts`` are checked (their ``mocaprig.summary`` record: 0 dropped) and deleted as the
soak goes, so that 30 minutes fit on the disk.

The producers are the paced threads of ``benchmarks/record_rig.py`` with pre-built payloads
(the recorder's data path, not the devices' renderers: the simulated D415s cannot render in
real time on a 2-core machine). Default rig: 1 × D415 848×480@30 (IR + depth) and a DAVIS240C
at 1 M events/s in 1 kHz packets + frames at 25 Hz + IMU at 1 kHz.

Growth is ``(max RSS after the first minute − RSS at the first minute) / RSS at the first
minute``; the issue's target is < 10 % with 0 drops.

    .venv/bin/python benchmarks/record_soak.py                      # 30 minutes
    .venv/bin/python benchmarks/record_soak.py --minutes 2 --check-seconds 5

Prints a line per minute and one JSON object as its last line.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from record_rig import _rig_streams, _Stream, record_cell, start_producers

from mocaprig.acquire.recorder import Recorder, StreamHandle
from mocaprig.acquire.recording import Recording


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _part_dropped(path: Path) -> int:
    """Messages the part's ``mocaprig.summary`` says were dropped."""
    with Recording(path) as rec:
        summary = rec.metadata().get("mocaprig.summary", {})
    return sum(int(v) for k, v in summary.items() if k.startswith("dropped:"))


def _check_part(path: Path) -> dict[str, Any]:
    """A finished part's name, size (MB) and the drops its summary counts."""
    return {
        "part": path.name,
        "mb": round(path.stat().st_size / 1e6, 1),
        "dropped": _part_dropped(path),
    }


def soak(
    folder: Path,
    streams: list[_Stream],
    *,
    seconds: float,
    split_bytes: int,
    sample_s: float,
    keep_parts: int,
) -> dict[str, Any]:
    """Record ``streams`` for ``seconds``; RSS samples, drops and parts."""
    rec = Recorder(folder / "soak.mcap", split_bytes=split_bytes, min_free_disk_bytes=1 << 30)
    stop = threading.Event()
    samples: list[tuple[float, float]] = []
    parts_checked: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    with rec:
        handles: list[StreamHandle] = [
            rec.add_stream(s.topic, s.kind, queue_messages=s.queue_messages) for s in streams
        ]

        t0 = time.perf_counter()
        threads = start_producers(rec, streams, handles, stop)
        next_minute = 60.0
        while (elapsed := time.perf_counter() - t0) < seconds:
            samples.append((round(elapsed, 1), round(_rss_mb(), 1)))
            # Finished parts (all but the one being written) beyond the newest few: checked
            # and deleted, so the soak fits on the disk.
            finished = rec.files[:-1]
            for old in finished[: max(len(finished) - keep_parts, 0)]:
                if old.exists():
                    parts_checked.append(_check_part(old))
                    old.unlink()
            if elapsed >= next_minute:
                dropped = sum(s.dropped for s in rec.status().streams)
                print(
                    f"{elapsed / 60:5.1f} min: RSS {samples[-1][1]:.1f} MB, "
                    f"{len(rec.files)} parts, {dropped} dropped",
                    flush=True,
                )
                next_minute += 60.0
            time.sleep(sample_s)
        stop.set()
        for th in threads:
            th.join()
    wall = time.perf_counter() - t0
    final = {s.topic: s for s in rec.status().streams}
    for path in rec.files:
        if path.exists():
            parts_checked.append(_check_part(path))
            path.unlink()
    return {
        "seconds": round(wall, 1),
        "samples": samples,
        "received": int(sum(s.received for s in final.values())),
        "written": int(sum(s.written for s in final.values())),
        "drops_total": int(sum(s.dropped for s in final.values())),
        "drops_per_stream": {k: int(v.dropped) for k, v in final.items()},
        "parts": len(parts_checked),
        "parts_dropped": int(sum(p["dropped"] for p in parts_checked)),
        "gb_written": round(sum(p["mb"] for p in parts_checked) / 1e3, 2),
        "memory_bound_mb": round(rec.memory_bound_bytes / 1e6, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--minutes", type=float, default=30.0, help="length of the soak (min)")
    ap.add_argument("--check-seconds", type=float, default=10.0, help="the hold check (s)")
    ap.add_argument("--cams", type=int, default=1, help="D415s")
    ap.add_argument("--size", default="848x480", help="D415 WIDTHxHEIGHT")
    ap.add_argument("--fps", type=int, default=30, help="D415 frame rate")
    ap.add_argument("--events-per-s", type=int, default=1_000_000, help="DAVIS event rate")
    ap.add_argument("--split-mb", type=int, default=1024, help="split parts at this size")
    ap.add_argument("--keep-parts", type=int, default=2, help="finished parts kept on disk")
    ap.add_argument("--sample-s", type=float, default=5.0, help="RSS sampling period (s)")
    ap.add_argument("--dir", type=Path, default=None, help="where to write (default: temp)")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    rig = (
        f"{args.cams}x D415 {w}x{h}@{args.fps} IR+depth, DAVIS {args.events_per_s / 1e6:g} M "
        "ev/s + frames 25 Hz + IMU 1 kHz"
    )
    load_before = os.getloadavg()
    rng = np.random.default_rng(0)
    streams = _rig_streams(rng, args.cams, w, h, args.fps, events_per_s=args.events_per_s)
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        folder = Path(d)
        check = record_cell(folder, "check", streams, args.check_seconds)
        print(f"hold check ({args.check_seconds:g} s): {json.dumps(check)}", flush=True)
        res = soak(
            folder,
            streams,
            seconds=60.0 * args.minutes,
            split_bytes=args.split_mb << 20,
            sample_s=args.sample_s,
            keep_parts=args.keep_parts,
        )
    samples = res.pop("samples")
    after = [rss for t, rss in samples if t >= 60.0]
    # None (not NaN, which is no JSON) for a soak shorter than a minute.
    base = after[0] if after else None
    growth = round((max(after) - after[0]) / after[0], 4) if after else None
    result = {
        "benchmark": "record_soak",
        "machine": f"{os.cpu_count()} cores {platform.machine()}, load {load_before[0]:.1f}",
        "load_avg_1min_after": round(os.getloadavg()[0], 1),
        "rig": rig,
        "check_seconds": args.check_seconds,
        "check_drops": check["drops_total"],
        "minutes": args.minutes,
        **res,
        "rss_at_1min_mb": base,
        "rss_max_after_1min_mb": max(after) if after else None,
        "rss_last_mb": samples[-1][1] if samples else None,
        "rss_growth_after_1min": growth,
        "rss_trace_mb": samples[:: max(1, len(samples) // 60)],
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
