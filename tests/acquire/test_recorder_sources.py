"""`mocaprig record` wiring: the real DAVIS240C driver and the D415 adapter protocol, each
talking to its mock (entry points ``mocaprig.mocks``), recorded through the Recorder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mocaprig.acquire.recorder import Recorder, StreamSource, record_sources
from mocaprig.acquire.recording import Recording, info
from mocaprig.errors import DeviceError


def _mock_d415() -> Any:
    from mocaprig.acquire.camera_backends import open_cameras
    from mocaprig.acquire.depth_camera import SensorOptions, StreamConfig, SyncMode

    try:
        (cam,) = open_cameras("mock", count=1, pacing="asap", seconds=4.0)
    except DeviceError as err:
        pytest.skip(f"the D415 mock is not available: {err}")
    mode, opts = StreamConfig(), SensorOptions()
    cam.configure(stream=mode, options=opts, sync_mode=SyncMode.MASTER)
    return cam, mode, opts


def test_d415_source_records_ir_depth_timing_and_calibration(tmp_path: Path) -> None:
    from mocaprig.acquire.record_sources import DepthCameraSource

    cam, mode, opts = _mock_d415()
    src = DepthCameraSource(cam, stream=mode, options=opts)
    p = tmp_path / "d415.mcap"
    try:
        with Recorder(p, metadata=src.metadata) as rec:
            sources: list[StreamSource] = [src]
            assert record_sources(rec, sources, seconds=0.8, status_period_s=0.1) == ()
    finally:
        cam.close()
    base = f"/d415/{src.serial}"
    inf = info(p)
    counts = {s.topic: s.messages for s in inf.streams}
    assert counts[f"{base}/depth"] > 0
    assert counts[f"{base}/depth"] == counts[f"{base}/ir"] == counts[f"{base}/frame_info"]
    assert counts[f"{base}/camera_info"] == 1
    dev = inf.devices[f"device/d415/{src.serial}"]
    assert dev["options.exposure_us"] == str(opts.exposure_us)
    assert dev["stream.fps"] == "30"
    with Recording(p) as r:
        (_, depth), *_ = list(r.images(f"{base}/depth"))
        (_, ir), *_ = list(r.images(f"{base}/ir"))
        seq_depth = [m.sequence for m in r.messages(f"{base}/depth")]
        fi = [m.decode() for m in r.messages(f"{base}/frame_info")]
        (ci,) = [m.decode() for m in r.messages(f"{base}/camera_info")]
    assert depth.image.dtype == np.uint16
    assert ir.image.dtype == np.uint8
    assert depth.image.shape == ir.image.shape == (480, 848)
    assert seq_depth == [f.frame_counter & 0xFFFFFFFF for f in fi]
    assert ci.k[0] > 0


@pytest.mark.slow
def test_davis_source_records_through_the_driver_and_usb_mock(tmp_path: Path) -> None:
    from mocaprig.acquire.davis240c import Davis240C, load_mock_backend
    from mocaprig.acquire.record_sources import DavisSource

    try:
        cam = Davis240C.open(backend=load_mock_backend(seconds=6.0))
    except DeviceError as err:
        pytest.skip(f"the DAVIS240C mock is not available: {err}")
    src = DavisSource(cam)
    p = tmp_path / "davis.mcap"
    try:
        with Recorder(p, metadata=src.metadata) as rec:
            sources: list[StreamSource] = [src]
            record_sources(rec, sources, seconds=6.0, status_period_s=0.2)
    finally:
        cam.close()
    base = f"/davis/{src.serial}"
    with Recording(p) as r:
        assert f"{base}/events" in r.topics
        ev = r.events(f"{base}/events")
        imu = r.imu(f"{base}/imu")
    assert ev.size > 0, "no events in 6 s from the DAVIS mock (simulator too slow here?)"
    assert int(ev["x"].max()) < 240
    assert int(ev["y"].max()) < 180
    assert imu.size > 0
    inf = info(p)
    assert inf.streams[0].counter_gaps == 0
    assert f"device/davis/{src.serial}" in inf.devices
    with Recording(p) as r:
        assert any(k.startswith("bias.") for k in r.metadata()[f"settings/davis/{src.serial}"])


def test_syncbox_source_records_pulse_reports(tmp_path: Path) -> None:
    from mocaprig.acquire.record_sources import SyncBoxSource
    from mocaprig.acquire.recording_format import SyncPulses
    from mocaprig.acquire.syncbox import SyncBox, open_mock_syncbox

    try:
        mock = open_mock_syncbox(seed=1)
    except DeviceError as err:
        pytest.skip(f"the sync box mock is not available: {err}")
    p = tmp_path / "sync.mcap"
    with mock, SyncBox(mock.port) as box:
        src = SyncBoxSource(box, report_interval_ms=100)
        with Recorder(p, metadata=src.metadata) as rec:
            sources: list[StreamSource] = [src]
            assert record_sources(rec, sources, seconds=0.8, status_period_s=0.1) == ()
    with Recording(p) as r:
        reports = [m.decode() for m in r.messages("/syncbox/pulses")]
        logs = [m.decode().message for m in r.messages("/log")]
        assert r.metadata()["device/syncbox"]["mode"] == "listen"
    assert len(reports) >= 3
    assert all(isinstance(x, SyncPulses) for x in reports)
    counts = [x.count for x in reports]
    assert counts == sorted(counts)
    assert counts[-1] > 0  # the mock sees a 30 Hz pulse train in LISTEN mode
    assert any("sync box run ended" in m for m in logs)
