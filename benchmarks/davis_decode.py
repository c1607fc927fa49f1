"""Benchmark the DAVIS240C word-stream decoder (issue 3).

Builds a realistic polarity-dominated stream the way the device logic serialises it (bursts of
one row word and several column words, a timestamp word whenever the time changed, a wrap word
every 32768 µs, a sprinkle of ext-input pulses and IMU samples), then decodes it on one core in
USB-sized chunks through one :class:`mocaprig.acquire.davis240c_decode.DavisDecoder` (state carried
across chunks, as in a live stream). Prints one JSON object as its last line (``events_per_s``).
"""

from __future__ import annotations

import argparse
import errno
import json
import platform
import time
from typing import Any

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.davis240c_decode import DavisDecoder


def polarity_stream(
    *, events: int, rate_eps: float, seed: int = 0, extras_every_us: int = 1000
) -> tuple[npt.NDArray[np.uint16], int]:
    """A word stream of about ``events`` DVS events at ``rate_eps``; returns (words, events).

    Rows carry 1-8 columns (mean 4.5); one IMU sample and one ext-input pulse every
    ``extras_every_us`` µs of device time.
    """
    rng = np.random.default_rng(seed)
    nx = rng.integers(1, 9, size=max(1, int(events / 4.5)))
    n_bursts = nx.size
    total = int(nx.sum())
    duration_us = max(1, round(total / rate_eps * 1e6))
    t = np.sort(rng.integers(1, duration_us, size=n_bursts))
    y = rng.integers(0, 180, size=n_bursts)
    prev_t = np.concatenate([[0], t[:-1]])
    wraps = (t >> 15) - (prev_t >> 15)
    need_ts = (t != prev_t) & ((t & 0x7FFF) != 0)
    head = (wraps > 0).astype(np.int64) + need_ts + 1
    size = head + nx
    start = np.concatenate([[0], np.cumsum(size)[:-1]])
    words = np.empty(int(size.sum()), np.uint16)
    # Columns first (the bulk), then the heads overwrite their slots.
    x_owner = np.repeat(np.arange(n_bursts), nx)
    x_rank = np.arange(total) - np.repeat(np.cumsum(nx) - nx, nx)
    x_pos = start[x_owner] + head[x_owner] + x_rank
    words[x_pos] = (0x2000 | rng.integers(0, 2, total) << 12 | rng.integers(0, 240, total)).astype(
        np.uint16
    )
    pos = start.copy()
    w = wraps > 0
    words[pos[w]] = (0x7000 | wraps[w]).astype(np.uint16)
    pos += w
    words[pos[need_ts]] = (0x8000 | (t[need_ts] & 0x7FFF)).astype(np.uint16)
    pos += need_ts
    words[pos] = (0x1000 | y).astype(np.uint16)
    extras = _extras(t, every_us=extras_every_us)
    cut = np.searchsorted(start, np.linspace(0, n_bursts, num=len(extras) + 2)[1:-1].astype(int))
    pieces = np.split(words, start[np.minimum(cut, n_bursts - 1)])
    out = [pieces[0]]
    for extra, piece in zip(extras, pieces[1:], strict=True):
        out.extend([extra, piece])
    return np.concatenate(out), total


def _extras(t: npt.NDArray[np.int64], *, every_us: int) -> list[npt.NDArray[np.uint16]]:
    """An IMU sample + ext-input pulse block for every ``every_us`` of stream time."""
    n = int(t[-1] // every_us) if every_us > 0 else 0
    block = np.array([0x0005, 0x53E5, *([0x5000 | 0x12] * 14), 0x0007, 0x0004], dtype=np.uint16)
    return [block] * n


def decode_rate(words: npt.NDArray[np.uint16], *, chunk_bytes: int, repeat: int) -> float:
    """Best-of-``repeat`` decode time (s) of ``words`` fed in ``chunk_bytes`` chunks."""
    raw = words.tobytes()
    best = float("inf")
    for _ in range(repeat):
        dec = DavisDecoder()
        t0 = time.perf_counter()
        for off in range(0, len(raw), chunk_bytes):
            dec.decode(raw[off : off + chunk_bytes])
        best = min(best, time.perf_counter() - t0)
    return best


def reader_throughput(
    words: npt.NDArray[np.uint16], *, read_size: int, n_events: int
) -> dict[str, float]:
    """Stream ``words`` through the whole driver (reader thread, hand-off, decoder thread,
    consumer) from the mock DAVIS240C whose bulk endpoint replays them as fast as asked.

    Returns MB/s and events/s delivered to the consumer, and the number of bulk reads.
    """
    import usb.core

    from mocaprig.acquire.davis240c import Davis240C
    from mocaprig.drivers_mock.davis240c_usb import Davis240CBackend, SyntheticDavisSource

    data = np.frombuffer(words.tobytes(), np.uint8)

    class Replay(Davis240CBackend):
        pos = 0

        def bulk_read(self, dev_handle: Any, ep: int, intf: int, buff: Any, timeout: int) -> int:
            n = min(len(buff), data.size - self.pos)
            if n <= 0:
                msg = "Operation timed out"
                raise usb.core.USBTimeoutError(msg, -7, errno.ETIMEDOUT)
            np.frombuffer(buff, np.uint8)[:n] = data[self.pos : self.pos + n]
            self.pos += n
            return n

    backend = Replay(SyntheticDavisSource(seed=0))
    with Davis240C.open(
        backend=backend, read_size=read_size, settle_delays_s=(0.0, 0.0, 0.0)
    ) as cam:
        backend.pos = data.size  # nothing while starting
        cam.start(timestamp_reset=False)
        backend.pos = 0
        got = 0
        t0 = time.perf_counter()
        for pkt in cam.packets(timeout_s=2.0):
            got += pkt.events.size
            if got >= n_events:
                break
        secs = time.perf_counter() - t0
        stats = cam.stats()
    return {
        "read_size": read_size,
        "mb_per_s": data.size / secs / 1e6,
        "events_per_s": got / secs,
        "reads": stats.reads,
        "raw_bytes_dropped": stats.raw_bytes_dropped,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--events", type=int, default=4_000_000)
    parser.add_argument("--rate", type=float, default=5e6, help="events/s of device time")
    parser.add_argument("--chunk", type=int, default=65536, help="bytes per decode call")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument(
        "--reader", action="store_true", help="also measure the driver's reader per read size"
    )
    args = parser.parse_args()
    words, n_events = polarity_stream(events=args.events, rate_eps=args.rate)
    check = DavisDecoder()
    got = sum(check.decode(words[i : i + 65536]).events.size for i in range(0, words.size, 65536))
    if got != n_events or check.stats.skipped_words:
        msg = f"decoder lost events: {got} of {n_events}, stats {check.stats}"
        raise SystemExit(msg)
    results = {}
    for chunk in sorted({args.chunk, 16384, 65536, 131072, 1 << 20}):
        secs = decode_rate(words, chunk_bytes=chunk, repeat=args.repeat)
        results[chunk] = secs
        print(f"chunk {chunk:>8} B: {n_events / secs / 1e6:6.1f} M events/s")
    secs = results[args.chunk]
    reader = []
    if args.reader:
        for size in (8192, 16384, 65536, 262144, 1048576):
            r = max(
                (reader_throughput(words, read_size=size, n_events=n_events) for _ in range(3)),
                key=lambda r: r["mb_per_s"],
            )
            reader.append(r)
            print(
                f"driver, read size {size:>8} B: {r['mb_per_s']:6.1f} MB/s, "
                f"{r['events_per_s'] / 1e6:5.1f} M events/s, {r['reads']} reads"
            )
    print(
        json.dumps(
            {
                "events": n_events,
                "words": int(words.size),
                "words_per_event": round(words.size / n_events, 3),
                "chunk_bytes": args.chunk,
                "seconds": round(secs, 4),
                "events_per_s": round(n_events / secs),
                "events_per_s_by_chunk": {
                    str(k): round(n_events / v) for k, v in sorted(results.items())
                },
                "reader": reader,
                "python": platform.python_version(),
                "numpy": np.__version__,
            }
        )
    )


if __name__ == "__main__":
    main()
