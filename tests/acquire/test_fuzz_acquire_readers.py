"""Readers of outside data in ``acquire`` on the inputs the fuzz campaign found them failing on
(``benchmarks/fuzz_readers.py``): each gives a clean error naming the file, or reads."""

from __future__ import annotations

import struct
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from mocaprig.acquire.events import make_events
from mocaprig.acquire.recorder import Recorder
from mocaprig.acquire.recording import RecordedMessage, Recording, info
from mocaprig.acquire.recording_format import EventPacket, topic
from mocaprig.acquire.rig_file import parse_rig_file
from mocaprig.acquire.rpg_text import read_events_txt
from mocaprig.errors import RecordingError, ValidationError

_TOPIC = topic("davis", "00000042", "events")


def _recording(path: Path, compression: str) -> Path:
    rng = np.random.default_rng(0)
    t = np.sort(rng.integers(0, 100_000, 300)).astype(np.int64)
    ev = make_events(t, rng.integers(0, 240, 300), rng.integers(0, 180, 300), t % 2)
    with Recorder(path, compression=compression, chunk_size_bytes=2048,  # type: ignore[arg-type]
                  min_free_disk_bytes=0) as rec:  # fmt: skip
        h = rec.add_stream(_TOPIC, EventPacket)
        for i in range(3):
            rec.put(h, EventPacket(ev[i * 100 : (i + 1) * 100], seq=i), log_time_ns=(i + 1) * 10**6,
                    sequence=i)  # fmt: skip
    return path


def _peak_bytes(fn: object) -> int:
    tracemalloc.start()
    try:
        assert callable(fn)
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_a_huge_footer_length_is_not_allocated(tmp_path: Path) -> None:
    p = _recording(tmp_path / "r.mcap", "zstd")
    data = bytearray(p.read_bytes())
    footer = len(data) - 8 - 29  # opcode, length, 20 bytes of fields; then the magic
    assert data[footer] == 0x02
    struct.pack_into("<Q", data, footer + 1, 2**31)
    p.write_bytes(bytes(data))

    def read() -> None:
        with Recording(p) as r:
            assert len(r.events(_TOPIC)) == 300

    assert _peak_bytes(read) < 32 << 20


def test_a_chunk_declaring_a_huge_uncompressed_size_is_skipped(tmp_path: Path) -> None:
    p = _recording(tmp_path / "r.mcap", "zstd")
    data = bytearray(p.read_bytes())
    chunks, pos = [], 8
    while pos + 9 <= len(data):
        if data[pos] == 0x06:
            chunks.append(pos)
        pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
    assert len(chunks) >= 2
    struct.pack_into("<Q", data, chunks[1] + 9 + 16, 2**33)  # after message start/end times
    p.write_bytes(bytes(data))

    def read() -> None:
        with Recording(p) as r:
            assert not r.indexed
            assert r.scan.bad_chunks == 1
            assert 0 < len(r.events(_TOPIC)) < 300

    assert _peak_bytes(read) < 32 << 20


def test_a_file_shorter_than_a_footer_is_scanned(tmp_path: Path) -> None:
    p = _recording(tmp_path / "r.mcap", "lz4")
    p.write_bytes(p.read_bytes()[:20])
    rep = info(p)
    assert rep.scan.truncated
    assert rep.streams == ()


def test_a_corrupt_payload_error_names_the_file_and_topic() -> None:
    msg = RecordedMessage("/davis/x/imu", "mocaprig.ImuPacket", 5, 0, b"\xff\xff", "/data/r.mcap")
    with pytest.raises(RecordingError, match=r"^/data/r\.mcap: the /davis/x/imu message at 5 ns"):
        msg.decode()


def test_rpg_text_with_a_non_ascii_byte_names_the_file_and_line(tmp_path: Path) -> None:
    p = tmp_path / "ev.txt"
    p.write_bytes(b"240 180\n0.000001 1 2 1\n0.000002 \xb53 4 0\n")
    with pytest.raises(RecordingError, match=r"ev\.txt:3: byte 0xb5 is not ASCII"):
        read_events_txt(p)


@pytest.mark.parametrize("x", ["-1", "65536"])
def test_rpg_text_with_an_impossible_coordinate_is_refused(tmp_path: Path, x: str) -> None:
    p = tmp_path / "ev.txt"
    p.write_text(f"0.000001 1 2 1\n0.000002 {x} 4 0\n")
    with pytest.raises(RecordingError, match=rf"ev\.txt:2: .*x = {x} is not a pixel coordinate"):
        read_events_txt(p)


def test_rig_file_integer_beyond_64_bits_is_refused_by_name() -> None:
    text = 'format_version = 1\n[syncbox]\nport = "/dev/ttyACM0"\nrate_hz = 99999999999999999999\n'
    with pytest.raises(ValidationError, match=r"rig\.toml: 'syncbox\.rate_hz' = 9+ is beyond"):
        parse_rig_file(text)
