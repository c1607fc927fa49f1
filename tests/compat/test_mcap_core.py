"""Independent readers decode every channel: TypeScript @mcap/core (+ protobufjs from the
schemas stored in the file) and the Python mcap reader (+ mcap_protobuf's dynamic decoder).

The npm packages are installed once into tests/compat/node_modules (``npm ci``, lockfile
pinned); the test is skipped, visibly, when node/npm are missing or the install fails.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from mocaprig.acquire.events import make_events
from mocaprig.acquire.recorder import Attachment, Recorder
from mocaprig.acquire.recording import Recording
from mocaprig.acquire.recording_format import (
    IMU_DTYPE,
    SPECIAL_DTYPE,
    CameraCalibrationMsg,
    D415FrameInfo,
    DavisFrameInfo,
    EventPacket,
    ImageMsg,
    ImuPacket,
    SyncPulses,
    TriggerPacket,
)


def _node(script: Path, mode: str, path: Path) -> Any:
    res = subprocess.run(
        ["node", str(script), mode, str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        cwd=script.parent,
    )
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout)


@pytest.fixture(scope="module")
def every_channel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("compat") / "all.mcap"
    rng = np.random.default_rng(3)
    imu = np.zeros(10, IMU_DTYPE)
    imu["t"] = np.arange(10)
    sp = np.zeros(2, SPECIAL_DTYPE)
    sp["type"] = 2
    with Recorder(
        p,
        compression="zstd",
        chunk_size_bytes=8192,
        metadata={"rig": {"name": "lab"}},
        attachments=[Attachment("calibration/rig.json", "application/json", b"{}")],
    ) as rec:
        h = {
            "ev": rec.add_stream("/davis/1/events", EventPacket),
            "fr": rec.add_stream("/davis/1/frame", ImageMsg),
            "fi": rec.add_stream("/davis/1/frame_info", DavisFrameInfo),
            "imu": rec.add_stream("/davis/1/imu", ImuPacket),
            "tr": rec.add_stream("/davis/1/trigger", TriggerPacket),
            "ir": rec.add_stream("/d415/2/ir", ImageMsg),
            "de": rec.add_stream("/d415/2/depth", ImageMsg),
            "di": rec.add_stream("/d415/2/frame_info", D415FrameInfo),
            "ci": rec.add_stream("/d415/2/camera_info", CameraCalibrationMsg),
            "sy": rec.add_stream("/syncbox/pulses", SyncPulses),
        }
        rec.put(h["ci"], CameraCalibrationMsg(64, 48, (50.0, 0, 32, 0, 50, 24, 0, 0, 1)))
        for i in range(20):
            t = np.arange(300, dtype=np.int64) + i * 300
            ev = make_events(t, t % 240, t % 180, t % 2)
            rec.put(h["ev"], EventPacket(ev, seq=i), sequence=i)
            img16 = rng.integers(0, 1024, (180, 240)).astype(np.uint16)
            rec.put(h["fr"], ImageMsg(img16, "mono16", i), sequence=i)
            rec.put(h["fi"], DavisFrameInfo(i, 1, 2, 3, 4, 5), sequence=i)
            rec.put(h["imu"], ImuPacket(imu, i), sequence=i)
            rec.put(h["tr"], TriggerPacket(sp, i), sequence=i)
            ir = rng.integers(0, 255, (48, 64)).astype(np.uint8)
            rec.put(h["ir"], ImageMsg(ir, "mono8"), sequence=i)
            rec.put(h["de"], ImageMsg(ir.astype(np.uint16) * 7, "16UC1"), sequence=i)
            info = D415FrameInfo(i, 5, None, 7, "HARDWARE_CLOCK", 1.0, 2, 0.001, "d415_2")
            rec.put(h["di"], info, sequence=i)
            rec.put(h["sy"], SyncPulses(i, 2**32 - 1), sequence=i)
        rec.log("ERROR", "source d415/3 died: OSError()")
    return p


def _python_counts(path: Path) -> dict[str, int]:
    counts: dict[str, int] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, decoded in reader.iter_decoded_messages():
            assert decoded is not None
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return counts


def test_mcap_core_indexed_reader_decodes_every_channel(
    mcap_core_reader: Path, every_channel: Path
) -> None:
    ts = _node(mcap_core_reader, "indexed", every_channel)
    channels = ts["channels"]
    assert isinstance(channels, dict)
    py = _python_counts(every_channel)
    assert {k: v["count"] for k, v in channels.items()} == py
    assert len(py) == 12  # 10 device streams + /diagnostics + /log
    ev = channels["/davis/1/events"]
    assert ev["first"]["encoding"] == "mono"
    assert ev["first"]["width"] == 240
    assert ev["bytes"] == 20 * 300 * 8
    depth = channels["/d415/2/depth"]["first"]
    assert (depth["encoding"], depth["width"], depth["height"], depth["step"]) == (
        "16UC1",
        64,
        48,
        128,
    )
    assert channels["/davis/1/frame"]["first"]["encoding"] == "mono16"
    assert channels["/d415/2/camera_info"]["first"]["K"][0] == 50.0
    assert channels["/d415/2/frame_info"]["first"]["has_frame_timestamp"] is False
    assert channels["/syncbox/pulses"]["first"]["t_us"] == str(2**32 - 1)
    assert "died" in channels["/log"]["first"]["message"]
    assert set(ts["metadata"]) >= {"mocaprig", "rig", "mocaprig.summary"}
    assert ts["attachments"] == ["calibration/rig.json"]


def test_mcap_core_stream_reader_reads_a_truncated_file(
    mcap_core_reader: Path, every_channel: Path, tmp_path: Path
) -> None:
    data = every_channel.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    ts = _node(mcap_core_reader, "stream", cut)
    assert ts["done"] is False
    channels = ts["channels"]
    assert isinstance(channels, dict)
    with Recording(cut) as r:
        assert r.scan.truncated
        ours: dict[str, int] = {}
        for m in r.messages():
            ours[m.topic] = ours.get(m.topic, 0) + 1
    assert {k: v["count"] for k, v in channels.items()} == ours
