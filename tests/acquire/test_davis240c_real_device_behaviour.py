"""DAVIS240C behaviour that matters on real devices (issue 13), checked on the mocks: lost raw
chunks keep time exact, several queued bulk transfers keep their order, a host stall costs
events only on the device, orientation registers, chip identity, paired/pulsed registers and
the DVS filter reset at open."""

from __future__ import annotations

import ctypes
import errno
import io
import threading
import time
from typing import Any

import numpy as np
import pytest

from mocaprig.acquire.davis240c import Davis240C, load_mock_backend
from mocaprig.acquire.davis240c_config import (
    ApsParam,
    ChipParam,
    DvsParam,
    Module,
    MuxParam,
    parse_setting,
)
from mocaprig.acquire.davis240c_decode import (
    DavisDecoder,
    SpecialType,
    scan_dropped,
)
from mocaprig.acquire.davis240c_libusb import (
    AsyncBulkReader,
    LibusbHandle,
    _Transfer,
    is_no_device,
)
from mocaprig.acquire.davis240c_reader import DavisStream
from mocaprig.drivers_mock.davis240c_encoder import DavisWordEncoder
from mocaprig.drivers_mock.davis240c_usb import SyntheticDavisSource
from mocaprig.errors import DeviceError

FAST = (0.0, 0.0, 0.0)


def _words(*w: int) -> bytes:
    return np.array(w, "<u2").tobytes()


def _stream(seconds_us: int, *, rate: float, seed: int) -> bytes:
    """A deterministic encoded stream (1 ms windows) of the synthetic world."""
    src = SyntheticDavisSource(seed=seed, event_rate_hz=rate)
    enc = DavisWordEncoder(seed=seed)
    parts = [enc.encode(src.activity(t, t + 1000)) for t in range(0, seconds_us, 1000)]
    parts.append(enc.flush())
    return b"".join(parts)


def _stream_session(decoder: DavisDecoder) -> DavisStream:
    """A DavisStream driven by hand (no device, no threads)."""
    return DavisStream(
        object(),
        decoder,
        read_size=512,
        read_timeout_ms=10,
        queue_packets=1 << 20,
        queue_bytes=1 << 40,
        raw_queue_bytes=1 << 30,
        discard_until_reset=False,
        name="test",
        raw_sink=None,
    )


# -- a dropped chunk ----------------------------------------------------------------------------


@pytest.mark.parametrize("chunk_bytes", [8192, 8191])
def test_a_dropped_chunk_leaves_later_timestamps_exact(chunk_bytes: int) -> None:
    data = _stream(400_000, rate=200_000.0, seed=11)
    chunks = [data[i : i + chunk_bytes] for i in range(0, len(data), chunk_bytes)]
    # Drop the first chunk (after the first ten) that holds a whole wrap word.
    all_words = np.frombuffer(data[: len(data) // 2 * 2], "<u2")
    wrap_bytes = 2 * np.flatnonzero((all_words >> 12) == 7)
    drop = next(
        k
        for k in range(10, len(chunks))
        if ((wrap_bytes >= k * chunk_bytes) & (wrap_bytes + 1 < (k + 1) * chunk_bytes)).any()
    )
    ref = DavisDecoder()
    expected = [ref.decode(c).events for c in chunks]

    stream = _stream_session(DavisDecoder())
    for k, c in enumerate(chunks):
        if k == drop:
            stream._raw_limit = 0  # the decoder has fallen behind: this chunk is dropped
        stream._on_chunk(c, k)
        stream._raw_limit = 1 << 30
    stream._reader_done = True
    stream._decode_loop()
    got = [stream.get(0.0) for _ in chunks]
    stats = stream.stats()
    assert stats.raw_chunks_dropped == 1
    assert stats.raw_bytes_dropped == len(chunks[drop])
    assert stats.decode.gaps == 1
    assert stats.decode.gap_wraps >= 1
    for k in range(drop + 1, len(chunks)):
        pkt = got[k]
        assert pkt is not None
        np.testing.assert_array_equal(pkt.events, expected[k])
    lost = got[drop]
    assert lost is not None
    assert lost.events.size == 0


def test_a_dropped_timestamp_reset_and_wraps_are_applied() -> None:
    dec = DavisDecoder()
    dec.decode(_words(0x8000 | 100, 0x1005, 0x3007, 0x7001))
    lost = _words(0x7002, 0x0001, 0x7003, 0x8000 | 40, 0x1009, 0x2001)  # reset, then 3 wraps
    pkt = dec.decode_gap(scan_dropped(np.frombuffer(lost, "<u2")))
    assert [int(s["type"]) for s in pkt.specials] == [SpecialType.TIMESTAMP_RESET]
    # An X word right after the gap belongs to row 9 at 3 * 32768 + 40 µs.
    after = dec.decode(_words(0x3002, 0x8000 | 41, 0x100A, 0x3003))
    assert after.events["t"].tolist() == [3 * 32768 + 40, 3 * 32768 + 41]
    assert after.events["y"].tolist() == [9, 10]
    assert dec.stats.gap_timestamp_resets == 1
    assert dec.stats.gap_wraps == 3


# -- several queued transfers (libusb asynchronous API through ctypes) --------------------------


class _FakeLibusb:
    """Stands for libusb-1.0: data go to transfers in submission order; completions come in
    a scrambled order; after the last chunk the device is unplugged."""

    def __init__(self, chunks: list[bytes]) -> None:
        self._chunks = list(chunks)
        self._keep: list[Any] = []
        self._queue: list[tuple[Any, bytes | None]] = []
        self._cancelled: set[int] = set()
        self._calls = 0
        self.freed = 0
        self.max_queued = 0

    def libusb_alloc_transfer(self, iso: int) -> Any:
        t = _Transfer()
        self._keep.append(t)
        return ctypes.pointer(t)

    def libusb_free_transfer(self, p: Any) -> None:
        self.freed += 1

    def libusb_submit_transfer(self, p: Any) -> int:
        self._queue.append((p, self._chunks.pop(0) if self._chunks else None))
        self.max_queued = max(self.max_queued, len(self._queue))
        return 0

    def libusb_cancel_transfer(self, p: Any) -> int:
        self._cancelled.add(ctypes.addressof(p.contents))
        return 0

    def libusb_handle_events_timeout_completed(self, ctx: Any, tv: Any, done: Any) -> int:
        if not self._queue:
            time.sleep(0.001)
            return 0
        self._calls += 1
        # Out of order now and then (the unplug itself comes after all data, in order).
        scramble = self._calls % 3 == 0 and self._queue[-1][1] is not None
        i = len(self._queue) - 1 if scramble else 0
        p, data = self._queue.pop(i)
        t = p.contents
        if ctypes.addressof(t) in self._cancelled:
            t.status = 3  # CANCELLED
        elif data is None:
            t.status = 5  # NO_DEVICE
        else:
            ctypes.memmove(t.buffer, data, len(data))
            t.actual_length = len(data)
            t.status = 0
        t.callback(p)
        return 0


def test_queued_transfers_deliver_in_order_and_report_an_unplug() -> None:
    chunks = [bytes([k]) * (100 + k) for k in range(50)]
    lib = _FakeLibusb(chunks)
    got: list[bytes] = []
    errors: list[BaseException] = []
    ended = threading.Event()

    def on_error(err: BaseException) -> None:
        errors.append(err)
        ended.set()

    reader = AsyncBulkReader(
        LibusbHandle(lib=lib, ctx=None, handle=None),
        0x82,
        transfers=8,
        transfer_bytes=8192,
        on_data=lambda data, t_ns: got.append(data),
        on_error=on_error,
        name="fake",
    )
    reader.start()
    assert ended.wait(10.0)
    reader.join(10.0)
    assert not reader.is_alive()
    assert got == chunks  # every chunk, in the order the device sent them
    assert lib.max_queued == 8
    assert len(errors) == 1
    assert is_no_device(errors[0])
    assert getattr(errors[0], "errno", None) == errno.ENODEV
    assert lib.freed == 8


# -- a host stall costs events on the device only -----------------------------------------------


def test_a_host_stall_drops_events_on_the_device_only() -> None:
    be = load_mock_backend(
        source=SyntheticDavisSource(seed=5, event_rate_hz=5_000_000.0), fifo_bytes=4096
    )
    with Davis240C.open(backend=be, settle_delays_s=FAST) as cam:
        be.hold()
        cam.start()
        be.release()
        before = []
        for pkt in cam.packets(timeout_s=10.0):
            before.append(pkt)
            if sum(p.events.size for p in before) > 200_000:
                break
        dropped_before = cam.device_drop_counts()["dvs"]
        t_stall = be.uptime_us
        be.stall_host(50_000)
        after = []
        for pkt in cam.packets(timeout_s=10.0):
            after.append(pkt)
            if be.uptime_us > t_stall + 150_000:
                break
        cam.stop()
        dropped = cam.device_drop_counts()["dvs"] - dropped_before
        stats = cam.stats()
    events = np.concatenate([p.events for p in before + after])
    assert dropped_before == 0
    assert dropped > 100_000  # 50 ms at 5 Mev/s is 250 k events; a 4 KiB FIFO holds ~1 k
    assert stats.raw_bytes_dropped == 0
    assert stats.packets_dropped == 0
    assert stats.decode.gaps == 0
    assert stats.decode.skipped_words == 0
    assert stats.decode.non_monotonic_timestamps == 0
    assert (np.diff(events["t"]) >= 0).all()
    # The hole is in device time: about 50 ms with (almost) no events.
    gaps = np.diff(events["t"])
    assert 40_000 <= int(gaps.max()) <= 60_000


# -- orientation --------------------------------------------------------------------------------


def _session(read_only: dict[tuple[int, int], int]) -> tuple[Any, list[Any], bytes]:
    be = load_mock_backend(
        source=SyntheticDavisSource(seed=9, event_rate_hz=50_000.0), read_only=read_only
    )
    sink = io.BytesIO()
    with Davis240C.open(backend=be, settle_delays_s=FAST, raw_sink=sink) as cam:
        be.hold()
        cam.start()
        be.release()
        events: list[Any] = []
        frames: list[Any] = []
        for pkt in cam.packets(timeout_s=10.0):
            events.append(pkt.events)
            frames += pkt.frames
            if len(frames) >= 2:
                break
        cam.stop()
    ev = np.concatenate(events)
    return ev[ev["t"] < 60_000], frames[:2], sink.getvalue()


_D, _A = int(Module.DVS), int(Module.APS)


@pytest.mark.parametrize(
    ("dvs_orientation", "aps_orientation"), [(0b101, 0b011), (0b001, 0b100), (0b101, 0b111)]
)
def test_mirrored_orientation_registers_give_the_same_frames_and_events(
    dvs_orientation: int, aps_orientation: int
) -> None:
    ref_events, ref_frames, ref_raw = _session({})
    regs = {(_D, 2): dvs_orientation, (_A, 2): aps_orientation}
    if dvs_orientation & 4:  # the chip's own axes: 180 columns of 240 rows
        regs |= {(_D, 0): 180, (_D, 1): 240}
    if aps_orientation & 4:
        regs |= {(_A, 0): 180, (_A, 1): 240}
    events, frames, raw = _session(regs)
    assert raw[:200_000] != ref_raw[:200_000]  # the mock did render it differently
    assert ref_events.size > 1000
    # Same events; within one µs the readout order follows the chip's rows, so sort.
    np.testing.assert_array_equal(
        np.sort(events, order=["t", "x", "y", "p"]), np.sort(ref_events, order=["t", "x", "y", "p"])
    )
    assert len(frames) == len(ref_frames) == 2
    for f, g in zip(frames, ref_frames, strict=True):
        assert f.pixels.shape == (180, 240)
        np.testing.assert_array_equal(f.pixels, g.pixels)


# -- chip identity ------------------------------------------------------------------------------


def test_a_davis346_is_refused_with_what_to_do() -> None:
    be = load_mock_backend(
        source=SyntheticDavisSource(seed=1), read_only={(int(Module.SYSINFO), 1): 5}
    )
    with pytest.raises(DeviceError, match=r"chip id 5 \(DAVIS346B\).*only the DAVIS240C.*DV"):
        Davis240C.open(backend=be, settle_delays_s=FAST)
    assert be._claimed == set()  # closed again


# -- paired and pulsed registers ----------------------------------------------------------------


def _spy(be: Any) -> list[tuple[int, int, int]]:
    writes: list[tuple[int, int, int]] = []
    original = be.registers.write

    def write(module: int, param: int, value: int) -> None:
        writes.append((module, param, value))
        original(module, param, value)

    be.registers.write = write
    return writes


def test_config_set_global_shutter_keeps_both_registers_in_step() -> None:
    be = load_mock_backend(source=SyntheticDavisSource(seed=1))
    with Davis240C.open(backend=be, settle_delays_s=FAST) as cam:
        writes = _spy(be)
        wr = parse_setting("APS.GLOBAL_SHUTTER=0", clocks=cam.info.clocks)  # as `config --set`
        cam.config_set(wr.module, wr.param, wr.value)
        assert writes == [
            (5, int(ChipParam.GLOBAL_SHUTTER), 0),
            (2, int(ApsParam.GLOBAL_SHUTTER), 0),
        ]
        assert cam.config_get(Module.BIAS, ChipParam.GLOBAL_SHUTTER) == 0
        writes.clear()
        cam.config_set(Module.BIAS, ChipParam.GLOBAL_SHUTTER, 1)
        assert writes == [(5, 142, 1), (2, 7, 1)]


def test_a_global_shutter_write_on_a_rolling_shutter_chip_is_refused() -> None:
    be = load_mock_backend(source=SyntheticDavisSource(seed=1), read_only={(_A, 6): 0})
    with (
        Davis240C.open(backend=be, settle_delays_s=FAST, send_default_config=False) as cam,
        pytest.raises(DeviceError, match="no global shutter"),
    ):
        cam.config_set(Module.APS, ApsParam.GLOBAL_SHUTTER, 1)


def test_timestamp_reset_is_pulsed_every_time() -> None:
    be = load_mock_backend(source=SyntheticDavisSource(seed=1))
    resets: list[int] = []
    original = be._timestamp_reset

    def counted() -> None:
        resets.append(1)
        original()

    be.registers._on_timestamp_reset = counted
    with Davis240C.open(backend=be, settle_delays_s=FAST) as cam:
        writes = _spy(be)
        for _ in range(2):
            wr = parse_setting("MUX.TIMESTAMP_RESET=1")
            cam.config_set(wr.module, wr.param, wr.value)
        cam.config_set(Module.MUX, MuxParam.TIMESTAMP_RESET, 0)  # libcaer sends nothing
    ts = int(MuxParam.TIMESTAMP_RESET)
    assert writes == [(0, ts, 1), (0, ts, 0)] * 2
    assert len(resets) == 2


# -- DVS filters --------------------------------------------------------------------------------

_HAS_ALL = {(_D, p): 1 for p in (10, 30, 40, 50, 60)}
_LEFT_BY_ANOTHER_TOOL = {
    (_D, int(DvsParam.FILTER_PIXEL_0_ROW)): 5,
    (_D, int(DvsParam.FILTER_PIXEL_7_COLUMN)): 17,
    (_D, int(DvsParam.FILTER_BACKGROUND_ACTIVITY)): 0,
    (_D, int(DvsParam.FILTER_REFRACTORY_PERIOD)): 1,
    (_D, int(DvsParam.FILTER_ROI_START_COLUMN)): 10,
    (_D, int(DvsParam.FILTER_ROI_END_ROW)): 90,
    (_D, int(DvsParam.FILTER_SKIP_EVENTS)): 1,
    (_D, int(DvsParam.FILTER_POLARITY_FLATTEN)): 1,
    (_D, int(DvsParam.FILTER_POLARITY_SUPPRESS)): 1,
}


def test_dvs_filters_present_in_the_logic_are_reset_at_open() -> None:
    be = load_mock_backend(
        source=SyntheticDavisSource(seed=1), read_only=_HAS_ALL, power_on=_LEFT_BY_ANOTHER_TOOL
    )
    with Davis240C.open(backend=be, settle_delays_s=FAST) as cam:
        g = cam.config_get
        D = Module.DVS
        assert [g(D, DvsParam.FILTER_PIXEL_0_ROW + 2 * k) for k in range(8)] == [180] * 8
        assert [g(D, DvsParam.FILTER_PIXEL_0_COLUMN + 2 * k) for k in range(8)] == [240] * 8
        assert g(D, DvsParam.FILTER_BACKGROUND_ACTIVITY) == 1
        assert g(D, DvsParam.FILTER_BACKGROUND_ACTIVITY_TIME) == 8
        assert g(D, DvsParam.FILTER_REFRACTORY_PERIOD) == 0
        roi = [g(D, DvsParam.FILTER_ROI_START_COLUMN + k) for k in range(4)]
        assert roi == [0, 0, 239, 179]
        assert g(D, DvsParam.FILTER_SKIP_EVENTS) == 0
        assert g(D, DvsParam.FILTER_SKIP_EVENTS_EVERY) == 5
        assert g(D, DvsParam.FILTER_POLARITY_FLATTEN) == 0
        assert g(D, DvsParam.FILTER_POLARITY_SUPPRESS) == 0


def test_filters_the_logic_lacks_get_no_write() -> None:
    be = load_mock_backend(source=SyntheticDavisSource(seed=1))
    writes = _spy(be)
    with Davis240C.open(backend=be, settle_delays_s=FAST):
        pass
    filter_params = {int(p) for p in DvsParam if p.name.startswith("FILTER_")}
    assert not [w for w in writes if w[0] == _D and w[1] in filter_params]
