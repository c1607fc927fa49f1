"""Encoders/decoders of the recording format: round trips and pinned bit layouts."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mocaprig.acquire.events import EVENT_DTYPE, make_events
from mocaprig.acquire.recording_format import (
    IMU_DTYPE,
    MAX_EVENT_PACKET_SPAN_US,
    MESSAGE_TYPES,
    SPECIAL_DTYPE,
    CameraCalibrationMsg,
    D415FrameInfo,
    DavisFrameInfo,
    EventPacket,
    ImageMsg,
    ImuPacket,
    LogMsg,
    RecorderStatus,
    StreamStatus,
    SyncPulses,
    TriggerPacket,
    decode_payload,
    split_events,
    topic,
)
from mocaprig.errors import RecordingError, ValidationError


@settings(max_examples=50, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.integers(0, MAX_EVENT_PACKET_SPAN_US),
            st.integers(0, 65535),
            st.integers(0, 32767),
            st.integers(0, 1),
        ),
        max_size=200,
    ),
    st.integers(0, 2**40),
)
def test_event_packet_round_trips_exactly(rows: list[tuple[int, int, int, int]], t0: int) -> None:
    arr = np.asarray(rows, dtype=np.int64).reshape(-1, 4)
    ev = make_events(arr[:, 0] + t0, arr[:, 1], arr[:, 2], arr[:, 3])
    back = EventPacket.decode(EventPacket(ev, 240, 180, 7, "davis_x").encode())
    assert back.events.dtype == EVENT_DTYPE
    np.testing.assert_array_equal(back.events, ev)
    assert (back.width, back.height, back.seq, back.frame_id) == (240, 180, 7, "davis_x")


@settings(max_examples=50, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 2**32 - 1), st.integers(0, 65535), st.integers(0, 32767),
                  st.integers(0, 1)),
        min_size=1,
        max_size=200,
    ),
    st.integers(0, 2**62),
)  # fmt: skip
def test_event_packet_ns_times_round_trip_exactly(
    rows: list[tuple[int, int, int, int]], t0_ns: int
) -> None:
    arr = np.asarray(rows, dtype=np.int64).reshape(-1, 4)
    dt = arr[:, 0] - arr[:, 0].min()  # any span below 2**32 ns, any sub-µs digits
    t_ns = dt + t0_ns
    ev = make_events(t_ns // 1000, arr[:, 1], arr[:, 2], arr[:, 3])
    back = EventPacket.decode(EventPacket(ev, 240, 180, 3, "d", t_ns=t_ns).encode())
    assert back.t_ns is not None
    assert back.t_ns.dtype == np.int64
    np.testing.assert_array_equal(back.t_ns, t_ns)
    np.testing.assert_array_equal(back.events, ev)
    np.testing.assert_array_equal(back.events["t"], back.t_ns // 1000)


def _legacy_encode(ev: np.ndarray) -> bytes:
    """The µs-only encoder as it was before ``t_ns`` (ns = µs × 1000, time_base = t0 × 1000)."""
    from mocaprig.acquire.recording_format import _PB

    t0 = int(ev["t"].min())
    words = (
        (ev["p"].astype(np.uint64) & np.uint64(1)) << np.uint64(63)
        | ev["y"].astype(np.uint64) << np.uint64(48)
        | ev["x"].astype(np.uint64) << np.uint64(32)
        | ((ev["t"] - t0) * 1000).astype(np.uint64)
    )
    pb = _PB["EventPacket"](width=240, height=180, time_base=t0 * 1000, encoding="mono",
                            events=words.astype("<u8").tobytes())  # fmt: skip
    return bytes(pb.SerializeToString())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_files_written_before_t_ns_decode_as_before(seed: int) -> None:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, MAX_EVENT_PACKET_SPAN_US, 500)) + int(rng.integers(0, 2**40))
    ev = make_events(t, rng.integers(0, 240, t.size), rng.integers(0, 180, t.size), t % 2)
    old = _legacy_encode(ev)
    # µs packets are still written byte for byte as before (the format did not change) ...
    assert EventPacket(ev).encode() == old
    # ... and old payloads decode to the same µs (old decoder: offset // 1000 + time_base // 1000;
    # both are multiples of 1000 ns, so that equals the floor of the ns sum the decoder now takes).
    back = EventPacket.decode(old)
    np.testing.assert_array_equal(back.events, ev)
    assert back.t_ns is not None
    np.testing.assert_array_equal(back.t_ns, t * 1000)


def test_event_packet_t_ns_must_agree_with_the_events() -> None:
    ev = make_events([0, 11], [1, 2], [3, 4], [1, 0])
    EventPacket(ev, t_ns=np.array([999, 11_001]))  # floor(999 / 1000) == 0: fine
    with pytest.raises(ValidationError, match=r"index 1: t_ns=12000 ns but t=11 µs"):
        EventPacket(ev, t_ns=np.array([0, 12_000]))
    with pytest.raises(ValidationError, match="floor"):
        EventPacket(ev, t_ns=np.array([-1, 11_000]))  # floor(-1 / 1000) == -1, not 0
    with pytest.raises(ValidationError, match="one per event"):
        EventPacket(ev, t_ns=np.array([0]))
    with pytest.raises(ValidationError, match="integer"):
        EventPacket(ev, t_ns=np.array([0.0, 11_001.0]))


def test_event_packet_ns_span_limit() -> None:
    ev = make_events([0, (2**32 - 1) // 1000], [0, 0], [0, 0], [0, 0])
    EventPacket(ev, t_ns=np.array([0, 2**32 - 1])).encode()
    ev2 = make_events([0, 2**32 // 1000], [0, 0], [0, 0], [0, 0])
    with pytest.raises(ValidationError, match="2\\*\\*32 ns"):
        EventPacket(ev2, t_ns=np.array([0, 2**32])).encode()
    with pytest.raises(ValidationError, match="t_ns >= 0"):
        EventPacket(make_events([-1], [0], [0], [0]), t_ns=np.array([-5])).encode()


def test_event_blob_is_ros_mono_layout() -> None:
    ev = make_events([1000, 1003], [5, 239], [7, 179], [1, 0])
    from mocaprig.acquire.recording_format import _PB

    pb = _PB["EventPacket"]()
    pb.ParseFromString(EventPacket(ev).encode())
    assert pb.encoding == "mono"
    assert not pb.is_bigendian
    assert pb.time_base == 1_000_000  # ns
    words = np.frombuffer(pb.events, "<u8")
    assert int(words[0]) == (1 << 63) | (7 << 48) | (5 << 32) | 0
    assert int(words[1]) == (0 << 63) | (179 << 48) | (239 << 32) | 3000


def test_event_packet_rejects_too_long_span() -> None:
    ev = make_events([0, MAX_EVENT_PACKET_SPAN_US + 1], [0, 0], [0, 0], [0, 0])
    with pytest.raises(ValidationError, match="split_events"):
        EventPacket(ev).encode()


def test_split_events_keeps_every_event_within_span() -> None:
    t = np.arange(0, 20_000_000, 1000)
    ev = make_events(t, t % 240, t % 180, t % 2)
    parts = split_events(ev)
    assert len(parts) == 5
    assert sum(p.size for p in parts) == ev.size
    for p in parts:
        assert int(p["t"].max() - p["t"].min()) <= MAX_EVENT_PACKET_SPAN_US
        EventPacket(p).encode()


@pytest.mark.parametrize(
    ("encoding", "dtype"), [("mono8", np.uint8), ("mono16", np.uint16), ("16UC1", np.uint16)]
)
def test_image_round_trips(encoding: str, dtype: type) -> None:
    img: np.ndarray = np.random.default_rng(0).integers(0, 200, (6, 5)).astype(dtype)
    msg = ImageMsg(img, encoding, 123_000, "cam")  # type: ignore[arg-type]
    back = ImageMsg.decode(msg.encode())
    np.testing.assert_array_equal(back.image, img)
    assert (back.encoding, back.timestamp_ns, back.frame_id) == (encoding, 123_000, "cam")


def test_image_rejects_wrong_dtype() -> None:
    with pytest.raises(ValidationError, match="16UC1"):
        ImageMsg(np.zeros((2, 2), np.uint8), "16UC1").encode()


def test_structured_packets_round_trip() -> None:
    imu = np.zeros(3, IMU_DTYPE)
    imu["t"] = [1, 2, 3]
    imu["accel_g"][:, 2] = 1.0
    np.testing.assert_array_equal(ImuPacket.decode(ImuPacket(imu, 4).encode()).samples, imu)
    sp = np.zeros(2, SPECIAL_DTYPE)
    sp["type"] = [2, 1]
    np.testing.assert_array_equal(TriggerPacket.decode(TriggerPacket(sp).encode()).specials, sp)


@pytest.mark.parametrize(
    "msg",
    [
        SyncPulses(10, 2**32 - 1, "GENERATE"),
        DavisFrameInfo(3, -1, 2, 3, 4, 5, 1, 2, False, "d"),
        D415FrameInfo(9, None, 5, None, "HARDWARE_CLOCK", 1.5, 77, 0.001, "c"),
        D415FrameInfo(9, 4, 5, 6, "GLOBAL_TIME", 1.5, 77, 0.001, "c"),
        RecorderStatus(1, 2, 3, 0, (StreamStatus("/a", 5, 4, 1, 0, 99),)),
        LogMsg("ERROR", "source died", "davis", 5),
        CameraCalibrationMsg(640, 480, (500.0, 0, 320, 0, 500, 240, 0, 0, 1), (0.1,) * 5),
    ],
)
def test_small_messages_round_trip(msg: object) -> None:
    schema = type(msg).SCHEMA.name  # type: ignore[attr-defined]
    assert MESSAGE_TYPES[schema] is type(msg)
    assert decode_payload(schema, msg.encode()) == msg  # type: ignore[attr-defined]


def test_dtypes_match_the_davis_decoder() -> None:
    dec = pytest.importorskip("mocaprig.acquire.davis240c_decode")
    assert dec.IMU_SAMPLE_DTYPE == IMU_DTYPE
    assert dec.SPECIAL_DTYPE == SPECIAL_DTYPE


def test_unknown_schema_and_corrupt_payload_raise() -> None:
    with pytest.raises(RecordingError, match="upgrade mocaprig"):
        decode_payload("nope.Thing", b"")
    with pytest.raises(RecordingError, match="corrupt"):
        decode_payload("mocaprig.EventPacket", b"\xff\xff\xff")


def test_topic_names() -> None:
    assert topic("davis", "00000042", "events") == "/davis/00000042/events"
    assert topic("syncbox", "", "pulses") == "/syncbox/pulses"
    with pytest.raises(ValidationError):
        topic("d415", "a/b", "ir")


def test_proto_file_matches_the_descriptor_table() -> None:
    from pathlib import Path

    import mocaprig.acquire
    from mocaprig.acquire.recording_format import proto_source

    path = Path(mocaprig.acquire.__file__).parent / "schemas" / "mocaprig.proto"
    assert path.read_text() == proto_source(), (
        "acquire/schemas/mocaprig.proto is stale; regenerate it with "
        "python -c 'from mocaprig.acquire.recording_format import proto_source as p; "
        'open("acquire/schemas/mocaprig.proto", "w").write(p())\''
    )
