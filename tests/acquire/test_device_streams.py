"""The recording contract: DeviceId names and the typed per-device readers."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mocaprig.acquire.depth_camera import SensorOptions, StreamConfig, SyncMode, TimestampDomain
from mocaprig.acquire.device_id import DeviceId
from mocaprig.acquire.device_streams import (
    D415Settings,
    RecordedD415,
    RecordedDavis,
    d415_devices,
    davis_devices,
    frame_timings,
    read_frame_sets,
    sync_pulses,
)
from mocaprig.acquire.recorder import Recorder
from mocaprig.acquire.recording import Recording
from mocaprig.acquire.recording_format import (
    SPECIAL_DTYPE,
    CameraCalibrationMsg,
    D415FrameInfo,
    ImageMsg,
    SyncPulses,
    TriggerPacket,
    topic,
)
from mocaprig.errors import RecordingError, ValidationError
from mocaprig.timebase import U32_US_WRAP

# ------------------------------------------------------------------------------- DeviceId


def test_device_id_builds_every_name_of_the_format() -> None:
    d = DeviceId("d415", "819632342024")
    assert d.label == "d415/819632342024"
    assert d.topic("ir") == "/d415/819632342024/ir"
    assert d.metadata_name == "device/d415/819632342024"
    assert d.settings_name == "settings/d415/819632342024"
    assert d.frame_id == "d415_819632342024"
    assert DeviceId("syncbox").topic("pulses") == "/syncbox/pulses"
    assert topic("davis", "42", "events") == DeviceId("davis", "42").topic("events")


@pytest.mark.parametrize(
    "t", ["/d415/1/ir", "/davis/00000042/trigger", "/syncbox/pulses", "/d415/1/camera_info"]
)
def test_device_id_parses_back_every_topic_it_builds(t: str) -> None:
    parsed = DeviceId.from_topic(t)
    assert parsed is not None
    dev, stream = parsed
    assert dev.topic(stream) == t


@pytest.mark.parametrize("t", ["/diagnostics", "/d415/1", "/foo/1/ir", "d415/1/ir", "/d415//ir"])
def test_device_id_leaves_other_topics_alone(t: str) -> None:
    assert DeviceId.from_topic(t) is None


def test_device_id_parses_labels_and_bare_serials() -> None:
    assert DeviceId.parse("d415/12") == DeviceId("d415", "12")
    assert DeviceId.parse("12", kind="d415") == DeviceId("d415", "12")
    assert DeviceId.parse("syncbox") == DeviceId("syncbox")
    with pytest.raises(ValidationError, match="not a device label"):
        DeviceId.parse("12")
    with pytest.raises(ValidationError, match="is a davis, not a d415"):
        DeviceId.parse("davis/1", kind="d415")
    with pytest.raises(ValidationError, match="must be non-empty"):
        DeviceId("d415", "a/b")
    with pytest.raises(ValidationError, match="not one of"):
        DeviceId("kinect", "1")  # type: ignore[arg-type]


# ------------------------------------------------------------------------------- D415 settings


def test_d415_settings_round_trip_through_the_metadata_record() -> None:
    s = D415Settings(
        serial="1",
        name="Intel RealSense D415",
        sync_mode=SyncMode.SLAVE,
        depth_scale_m=0.001,
        stream=StreamConfig(848, 480, 90),
        options=SensorOptions(exposure_us=3000, gain=32, laser_power_mw=0, emitter_enabled=False),
        rig_role="slave",
    )
    assert D415Settings.from_metadata("1", s.to_metadata(), source="x") == s


def test_a_renamed_or_missing_option_is_an_error_not_a_silent_default() -> None:
    meta = D415Settings(serial="1", options=SensorOptions()).to_metadata()
    del meta["options.exposure_us"]
    meta["options.exposure"] = "8500"
    with pytest.raises(RecordingError, match="exposure_us"):
        D415Settings.from_metadata("1", meta, source="s.mcap")
    bad = D415Settings(serial="1", options=SensorOptions()).to_metadata()
    bad["options.gain"] = "loud"
    with pytest.raises(RecordingError, match="gain = 'loud'"):
        D415Settings.from_metadata("1", bad, source="s.mcap")


# ------------------------------------------------------------------------------- a recording


def _write(path: Path, *, wrap_at: int | None = None, frame_info: bool = True) -> None:
    """Two D415 (3 frames each, interleaved), a DAVIS trigger topic and sync pulses."""
    rng = np.random.default_rng(7)
    settings = D415Settings(serial="A", sync_mode=SyncMode.MASTER, options=SensorOptions())
    meta = {"device/d415/A": settings.to_metadata(), "device/d415/B": {"serial": "B"}}
    with Recorder(path, metadata=meta) as rec:
        h = {}
        for serial in ("A", "B"):
            dev = DeviceId("d415", serial)
            streams = [("ir", ImageMsg), ("depth", ImageMsg), ("camera_info", CameraCalibrationMsg)]
            if frame_info:
                streams.append(("frame_info", D415FrameInfo))
            for stream, cls in streams:
                h[serial, stream] = rec.add_stream(dev.topic(stream), cls)
            k = (600.0, 0.0, 4.0, 0.0, 600.0, 3.0, 0.0, 0.0, 1.0)
            rec.put(h[serial, "camera_info"], CameraCalibrationMsg(8, 6, k, (0.1, 0.0, 0.0)))
        trig = rec.add_stream(DeviceId("davis", "42").topic("trigger"), TriggerPacket)
        pulses = rec.add_stream(DeviceId("syncbox").topic("pulses"), SyncPulses)
        t_log = 1_000_000
        start_us = (U32_US_WRAP - 40_000) if wrap_at is not None else 5_000_000
        for i in range(3):
            for serial in ("A", "B"):
                seq = 100 + i
                stamp = (start_us + i * 33_333) % U32_US_WRAP
                ir = rng.integers(0, 255, (6, 8), dtype=np.uint8)
                depth = rng.integers(0, 4000, (6, 8), dtype=np.uint16)
                t_log += 1000
                rec.put(h[serial, "ir"], ImageMsg(ir, "mono8", stamp * 1000), log_time_ns=t_log,
                        sequence=seq)  # fmt: skip
                rec.put(h[serial, "depth"], ImageMsg(depth, "16UC1", stamp * 1000),
                        log_time_ns=t_log, sequence=seq)  # fmt: skip
                if frame_info:
                    fi = D415FrameInfo(seq, stamp, stamp, None, "HARDWARE_CLOCK", 0.0, t_log, 0.001)
                    rec.put(h[serial, "frame_info"], fi, log_time_ns=t_log, sequence=seq)
        sp = np.zeros(3, SPECIAL_DTYPE)
        sp["t"] = [10, 20, 30]
        sp["type"] = [2, 2, 2]  # rising edges after a reset... (type 1 = reset)
        sp["type"][0] = 1
        rec.put(trig, TriggerPacket(sp), log_time_ns=t_log)
        rec.put(pulses, SyncPulses(count=3, t_us=99), log_time_ns=t_log)


@pytest.fixture
def session(tmp_path: Path) -> Path:
    path = tmp_path / "s.mcap"
    _write(path)
    return path


def test_devices_are_found_without_parsing_topics_by_hand(session: Path) -> None:
    with Recording(session) as rec:
        assert [d.label for d in d415_devices(rec)] == ["d415/A", "d415/B"]
        assert [d.label for d in davis_devices(rec)] == ["davis/42"]
        assert [p.count for _, p in sync_pulses(rec)] == [3]


def test_d415_reader_gives_intrinsics_settings_and_an_unwrapped_index(tmp_path: Path) -> None:
    path = tmp_path / "wrap.mcap"
    _write(path, wrap_at=1)
    with Recording(path) as rec:
        a = RecordedD415(rec, "d415/A")
        intr = a.intrinsics()
        assert intr.k[0, 0] == 600.0
        assert intr.distortion.tolist() == [0.1, 0.0, 0.0, 0.0, 0.0]
        assert a.settings().sync_mode is SyncMode.MASTER
        assert a.settings().options == SensorOptions()
        assert RecordedD415(rec, "B").settings().options is None
        idx = a.frame_index()
        assert idx.hardware_time
        assert idx.sequence.tolist() == [100, 101, 102]
        # The stamps wrap past 2**32 µs between frames 1 and 2; the index is monotonic.
        assert np.all(np.diff(idx.t_dev_ns) == 33_333_000)


def test_frame_sets_pair_ir_and_depth_like_a_live_camera(session: Path) -> None:
    with Recording(session) as rec:
        sets = list(read_frame_sets(rec, d415_devices(rec)))
        assert [(r.frames.serial, r.sequence) for r in sets] == [
            ("A", 100), ("B", 100), ("A", 101), ("B", 101), ("A", 102), ("B", 102)
        ]  # fmt: skip
        fs = sets[0].frames
        assert fs.infrared.image.dtype == np.uint8
        assert fs.depth.image.dtype == np.uint16
        assert fs.timing.timestamp_domain is TimestampDomain.HARDWARE_CLOCK
        assert fs.timing.frame_counter == 100
        only = list(RecordedD415(rec, "A").frame_sets(sequences=[101]))
        assert [f.timing.frame_counter for f in only] == [101]
        timings = [(d.serial, t.frame_counter) for d, t in frame_timings(rec)]
        assert timings[:2] == [("A", 100), ("B", 100)]


def test_frames_without_frame_info_fall_back_to_host_time(tmp_path: Path) -> None:
    path = tmp_path / "nofi.mcap"
    _write(path, frame_info=False)
    with Recording(path) as rec:
        idx = RecordedD415(rec, "A").frame_index()
        assert not idx.hardware_time
        fs = next(iter(RecordedD415(rec, "A").frame_sets()))
        assert fs.timing.timestamp_domain is TimestampDomain.SYSTEM_TIME


def test_a_missing_camera_is_named_with_those_present(session: Path) -> None:
    with Recording(session) as rec, pytest.raises(RecordingError, match=r"d415/Z.*d415/A"):
        RecordedD415(rec, "Z")


def test_davis_reader_gives_trigger_edges_after_the_last_reset(session: Path) -> None:
    with Recording(session) as rec:
        davis = RecordedDavis(rec, "davis/42")
        edges, why = davis.external_edges_ns()
        assert edges.tolist() == [20_000, 30_000]
        assert why == ""
        assert davis.events().size == 0
        assert not davis.has("events")


def test_d415_settings_fields_follow_the_dataclasses() -> None:
    # The record's keys are the dataclass fields: renaming one renames the key on both sides.
    keys = D415Settings(serial="1", options=SensorOptions()).to_metadata()
    assert {k.split(".", 1)[1] for k in keys if k.startswith("options.")} == {
        f.name for f in dataclasses.fields(SensorOptions)
    }
