"""``export_topic``'s progress: each image as it is written, then the count as the total."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocaprig.acquire.export import ExportFormat, export_topic
from mocaprig.acquire.recorder import Recorder
from mocaprig.acquire.recording_format import IMU_DTYPE, ImageMsg, ImuPacket, topic

_FRAMES = 5


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rng = np.random.default_rng(7)
    path = tmp_path_factory.mktemp("export") / "session.mcap"
    with Recorder(path) as rec:
        frames = rec.add_stream(topic("davis", "00000042", "frame"), ImageMsg)
        imu = rec.add_stream(topic("davis", "00000042", "imu"), ImuPacket)
        for i in range(_FRAMES):
            img = rng.integers(0, 1024, (18, 24)).astype(np.uint16)
            rec.put(frames, ImageMsg(img, "mono16", i * 1000), log_time_ns=(i + 1) * 10**8)
        rec.put(imu, ImuPacket(np.zeros(10, IMU_DTYPE), 0), log_time_ns=10**8)
    return path


@pytest.mark.parametrize("fmt", ["png", "mp4"])
def test_image_export_reports_each_image_then_the_count_as_total(
    recording: Path, tmp_path: Path, fmt: ExportFormat
) -> None:
    calls: list[tuple[int, int]] = []
    out = tmp_path / ("frames" if fmt == "png" else "frames.mp4")
    res = export_topic(
        recording,
        topic_name="/davis/00000042/frame",
        fmt=fmt,
        out=out,
        progress=lambda done, total: calls.append((done, total)),
    )
    assert res.count == _FRAMES
    assert calls == [*((n, 0) for n in range(1, _FRAMES + 1)), (_FRAMES, _FRAMES)]


def test_array_export_reports_its_end(recording: Path, tmp_path: Path) -> None:
    calls: list[tuple[int, int]] = []
    export_topic(
        recording,
        topic_name="/davis/00000042/imu",
        fmt="npz",
        out=tmp_path / "imu.npz",
        progress=lambda done, total: calls.append((done, total)),
    )
    assert len(calls) == 1
    assert calls[0][0] == calls[0][1] > 0
