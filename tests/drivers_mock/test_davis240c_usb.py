"""The mock DAVIS240C pyusb backend: descriptors, vendor requests, gating, faults.

Everything goes through real pyusb (``usb.core.find(backend=...)``), as a driver would.
"""

from __future__ import annotations

import contextlib
import errno
import importlib.metadata
import time

import numpy as np
import pytest
import usb.core
import usb.util

from mocaprig.acquire.events import make_events
from mocaprig.drivers_mock.davis240c_usb import (
    DAVIS240C_PID,
    DAVIS_VID,
    Davis240CBackend,
    DavisFaults,
    SyntheticDavisSource,
    mock_backend,
)
from mocaprig.drivers_mock.davis_activity import DavisActivity
from tests.drivers_mock.test_davis240c_encoder import host_decode

MUX, DVS, APS, IMU, EXTINPUT, BIAS, SYSINFO, USBMOD = 0, 1, 2, 3, 4, 5, 6, 9


class ScriptedSource:
    """A deterministic source: one DVS event every ``period_us`` at (x=7, y=9), ON."""

    def __init__(self, period_us: int = 100) -> None:
        self.period_us = period_us
        self.resets: list[int] = []
        self.windows: list[tuple[int, int]] = []

    def activity(self, t0_us: int, t1_us: int) -> DavisActivity:
        self.windows.append((t0_us, t1_us))
        first = -(-t0_us // self.period_us) * self.period_us
        t = np.arange(first, t1_us, self.period_us)
        ev = make_events(t, np.full(t.size, 7), np.full(t.size, 9), np.ones(t.size))
        return DavisActivity(t0_us=t0_us, t1_us=t1_us, events=ev)

    def reset(self, *, session_ns: int) -> None:
        self.resets.append(session_ns)


def find(backend: Davis240CBackend) -> usb.core.Device:
    dev = usb.core.find(idVendor=DAVIS_VID, idProduct=DAVIS240C_PID, backend=backend)
    assert dev is not None
    return dev


def write(dev, module: int, param: int, value: int) -> None:
    assert dev.ctrl_transfer(0x40, 0xBF, module, param, value.to_bytes(4, "big"), 1000) == 4


def read(dev, module: int, param: int) -> int:
    return int.from_bytes(bytes(dev.ctrl_transfer(0xC0, 0xBF, module, param, 4, 1000)), "big")


def data_start(dev) -> None:
    """The MUX drop flags of sendDefaultConfig (note §5.2 step 3), then dataStart (§5.3)."""
    write(dev, MUX, 4, 1)
    write(dev, MUX, 5, 1)
    for module, param in [
        (MUX, 3), (USBMOD, 0), (MUX, 1), (MUX, 0),
        (DVS, 3), (APS, 4), (IMU, 2), (IMU, 3), (IMU, 4), (EXTINPUT, 0),
    ]:  # fmt: skip
        write(dev, module, param, 1)


def read_for(dev, n_reads: int, size: int = 65536, timeout: int = 100) -> bytes:
    out = bytearray()
    for _ in range(n_reads):
        with contextlib.suppress(usb.core.USBTimeoutError):
            out += bytes(dev.read(0x82, size, timeout))
    return bytes(out)


@pytest.fixture
def scripted():
    source = ScriptedSource()
    backend = Davis240CBackend(source, serial="04010098", latency_us=0)
    return source, backend, find(backend)


# -- descriptors ---------------------------------------------------------------------------------


def test_descriptors_through_pyusb():
    backend = mock_backend(source=ScriptedSource(), serial="00000042")
    dev = find(backend)
    assert (dev.idVendor, dev.idProduct, dev.bcdDevice, dev.bcdUSB) == (
        0x152A, 0x841B, 0x0004, 0x0200,
    )  # fmt: skip
    assert (dev.bDeviceClass, dev.bMaxPacketSize0, dev.bNumConfigurations) == (0, 64, 1)
    assert isinstance(dev.bus, int)
    assert isinstance(dev.address, int)
    assert dev.speed == usb.util.SPEED_HIGH
    assert usb.util.get_string(dev, dev.iSerialNumber) == "00000042"
    cfg = dev.get_active_configuration()
    assert cfg.bConfigurationValue == 1
    interfaces = list(cfg)
    assert [(i.bInterfaceNumber, i.bAlternateSetting) for i in interfaces] == [(0, 0)]
    (ep,) = list(interfaces[0])
    assert ep.bEndpointAddress == 0x82
    assert usb.util.endpoint_type(ep.bmAttributes) == usb.util.ENDPOINT_TYPE_BULK
    assert usb.util.endpoint_direction(ep.bEndpointAddress) == usb.util.ENDPOINT_IN
    assert ep.wMaxPacketSize == 512


def test_raw_descriptor_requests():
    dev = find(mock_backend(source=ScriptedSource()))
    raw = bytes(dev.ctrl_transfer(0x80, 6, 0x0100, 0, 18))
    assert raw[:2] == bytes([18, 1])
    assert raw[8:14] == bytes.fromhex("2a151b840400")
    cfg = bytes(dev.ctrl_transfer(0x80, 6, 0x0200, 0, 64))
    assert len(cfg) == 25
    assert cfg[9 + 9 + 2] == 0x82


def test_entry_point_is_the_factory():
    (ep,) = [
        e for e in importlib.metadata.entry_points(group="mocaprig.mocks") if e.name == "davis240c"
    ]
    assert ep.load() is mock_backend


def test_serial_defaults_from_seed_and_is_validated():
    assert mock_backend(source=ScriptedSource(), seed=3).serial == "00000045"
    with pytest.raises(ValueError, match="8 ASCII"):
        mock_backend(source=ScriptedSource(), serial="123456789")


# -- registers -----------------------------------------------------------------------------------


def test_sysinfo_and_sizes(scripted):
    _, _, dev = scripted
    assert [read(dev, SYSINFO, p) for p in range(8)] == [18, 2, 1, 90, 30, 30, 1000, 1]
    assert [read(dev, DVS, 0), read(dev, DVS, 1), read(dev, DVS, 2)] == [240, 180, 1]
    assert [read(dev, APS, 0), read(dev, APS, 1), read(dev, APS, 6)] == [240, 180, 1]
    assert read(dev, IMU, 0) == 1
    assert read(dev, MUX, 80) == 1


def test_power_on_state(scripted):
    _, _, dev = scripted
    assert [read(dev, MUX, p) for p in range(4)] == [0, 0, 0, 0]
    assert read(dev, USBMOD, 0) == 1
    assert read(dev, USBMOD, 1) == 30000
    assert [read(dev, APS, p) for p in (7, 8, 9, 10, 11)] == [1, 0, 0, 239, 179]


def test_register_write_read_back_big_endian(scripted):
    _, backend, dev = scripted
    write(dev, BIAS, 0, 0x427F)
    assert read(dev, BIAS, 0) == 0x427F
    dev.ctrl_transfer(0x40, 0xBF, APS, 12, bytes([0x00, 0x01, 0xD4, 0xC0]))
    assert backend.registers.read(APS, 12) == 120000


def test_read_only_writes_are_ignored_and_unknown_reads_zero(scripted):
    _, _, dev = scripted
    write(dev, SYSINFO, 0, 99)
    write(dev, DVS, 0, 5)
    assert read(dev, SYSINFO, 0) == 18
    assert read(dev, DVS, 0) == 240
    assert read(dev, 7, 3) == 0
    assert read(dev, APS, 99) == 0


@pytest.mark.parametrize("length", [0, 3, 5])
def test_wrong_length_stalls_ep0(scripted, length):
    _, _, dev = scripted
    with pytest.raises(usb.core.USBError) as info:
        dev.ctrl_transfer(0x40, 0xBF, MUX, 0, bytes(length))
    assert info.value.errno == errno.EPIPE


def test_batch_request_applies_entries_in_order(scripted):
    _, _, dev = scripted
    entries = (
        bytes([APS, 8, 0, 0, 0, 5]) + bytes([APS, 8, 0, 0, 0, 6]) + bytes([IMU, 7, 0, 0, 0, 2])
    )
    assert dev.ctrl_transfer(0x40, 0xC2, 3, 0, entries) == 18
    assert read(dev, APS, 8) == 6
    assert read(dev, IMU, 7) == 2
    with pytest.raises(usb.core.USBError):
        dev.ctrl_transfer(0x40, 0xC2, 2, 0, entries)  # count and length disagree
    with pytest.raises(usb.core.USBError):
        dev.ctrl_transfer(0xC0, 0xC2, 1, 0, 6)  # 0xC2 is OUT only


def test_timestamp_reset_via_batch_pulse(scripted):
    source, _, dev = scripted
    data_start(dev)
    before = read_for(dev, 3)
    assert before
    dev.ctrl_transfer(0x40, 0xC2, 2, 0, bytes([MUX, 2, 0, 0, 0, 1, MUX, 2, 0, 0, 0, 0]))
    assert read(dev, MUX, 2) == 0
    after = read_for(dev, 2)
    assert np.frombuffer(after, "<u2")[0] == 0x0001
    assert len(source.resets) == 2  # power-on and the pulse
    host = host_decode(after)
    assert host.resets == 1
    assert host.events[0][0] == 0


def test_statistics_registers_are_64_bit_pairs():
    backend = mock_backend(
        source=ScriptedSource(period_us=1),
        faults=DavisFaults(bandwidth_bytes_per_s=500_000.0),
        latency_us=0,
    )
    dev = find(backend)
    data_start(dev)
    read_for(dev, 5)
    hi, lo = read(dev, MUX, 83), read(dev, MUX, 84)
    assert hi == 0
    assert lo > 0
    assert lo == backend.registers.read(MUX, 84)
    write(dev, MUX, 84, 0)  # read-only
    assert read(dev, MUX, 84) == lo


# -- gating --------------------------------------------------------------------------------------


def test_no_data_before_start(scripted):
    source, _, dev = scripted
    with pytest.raises(usb.core.USBTimeoutError):
        dev.read(0x82, 4096, 100)
    write(dev, MUX, 0, 1)  # MUX RUN without TIMESTAMP_RUN: the counter does not run
    with pytest.raises(usb.core.USBTimeoutError):
        dev.read(0x82, 4096, 100)
    assert source.windows == []


def test_dvs_needs_its_run_bit_and_the_chip(scripted):
    _, _, dev = scripted
    for module, param in [(USBMOD, 0), (MUX, 1), (MUX, 0), (DVS, 3)]:
        write(dev, module, param, 1)  # RUN_CHIP still 0
    w = np.frombuffer(read_for(dev, 3, timeout=100), "<u2")
    assert set((w >> 12).tolist()) <= {7}  # only wrap words: the MUX runs, the chip does not
    write(dev, MUX, 3, 1)
    w = np.frombuffer(read_for(dev, 2), "<u2")
    assert np.any((w >> 12) == 3)


def test_mux_run_off_throws_data_away(scripted):
    _, _, dev = scripted
    data_start(dev)
    assert read_for(dev, 1)
    write(dev, MUX, 0, 0)
    with pytest.raises(usb.core.USBTimeoutError):
        dev.read(0x82, 4096, 50)


def test_idle_running_device_sends_wraps():
    backend = mock_backend(source=ScriptedSource(period_us=10**9), latency_us=0)
    dev = find(backend)
    data_start(dev)
    data = read_for(dev, 4, timeout=40)
    # The event at 0 µs, then one wrap per 32.768 ms over ~120 ms of otherwise idle time.
    assert np.frombuffer(data, "<u2").tolist() == [0x1009, 0x3007] + [0x7001] * 3


def test_clear_halt_drops_unsent_data(scripted):
    _, backend, dev = scripted
    data_start(dev)
    dev.read(0x82, 8, 100)  # leaves most of the step's data waiting
    assert backend._out
    dev.clear_halt(0x82)
    assert not backend._out


def test_reads_return_whole_words_and_respect_the_request(scripted):
    _, _, dev = scripted
    data_start(dev)
    for size in (2, 7, 512, 4096):
        got = dev.read(0x82, size, 100)
        assert len(got) <= size
        assert len(got) % 2 == 0
        assert len(got) > 0


def test_asap_pacing_is_deterministic():
    def run() -> bytes:
        dev = find(mock_backend(source=SyntheticDavisSource(seed=4, event_rate_hz=20_000.0)))
        data_start(dev)
        return read_for(dev, 5)

    assert run() == run()


def test_synthetic_source_stream_decodes():
    backend = mock_backend(
        source=SyntheticDavisSource(seed=1, event_rate_hz=50_000.0), latency_us=30_000
    )
    dev = find(backend)
    data_start(dev)
    data = bytearray()
    while backend.uptime_us < 150_000:
        data += read_for(dev, 1, size=1 << 18)
    host = host_decode(bytes(data))
    assert len(host.events) > 1000
    assert len(host.imu) > 50
    assert {code for _, code in host.specials} >= {4, 8, 10, 14, 15}
    times = [e[0] for e in host.events]
    assert times == sorted(times)
    pulses = np.array([t for t, code in host.specials if code == 4])
    np.testing.assert_allclose(np.diff(pulses), 1e6 / 30, atol=1)  # the D415 master's 30 Hz


def test_realtime_pacing_follows_the_wall_clock():
    dev = find(mock_backend(source=ScriptedSource(), pacing="realtime", latency_us=0))
    data_start(dev)
    got = bytes(dev.read(0x82, 1 << 20, 200))
    host = host_decode(got)
    assert 0 < host.events[-1][0] < 500_000


class SlowSource(ScriptedSource):
    """A source that costs 4 ms of wall time per 1 ms window: a machine too loaded to keep up."""

    def activity(self, t0_us: int, t1_us: int) -> DavisActivity:
        time.sleep(0.004 * (t1_us - t0_us) / 1000)
        return super().activity(t0_us, t1_us)


def test_realtime_pacing_slower_than_the_wall_clock_still_serves_every_read(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # A catch-up of all the wall time due in one read never ends once simulating is slower
    # than real time (each read owes more than the last): the host starved and the CLI hung
    # until the CI timeout. Reads must keep returning data while device time falls behind.
    source = SlowSource(period_us=10)
    dev = find(mock_backend(source=source, pacing="realtime", latency_us=0))
    data_start(dev)
    chunks: list[bytes] = []
    with caplog.at_level("WARNING"):
        for _ in range(400):
            chunks.append(bytes(dev.read(0x82, 1 << 16, 1000)))
            if "slower than real time" in caplog.text:
                break
    assert "slower than real time" in caplog.text
    assert all(chunks)
    times = [e[0] for e in host_decode(b"".join(chunks)).events]
    assert times == sorted(times)
    assert times[-1] - times[0] > 100_000  # device time ran on, event after event


# -- faults --------------------------------------------------------------------------------------


def test_unplug_raises_enodev_and_the_device_disappears():
    backend = Davis240CBackend(
        ScriptedSource(), faults=DavisFaults(unplug_at_us=5000), latency_us=0
    )
    dev = find(backend)
    data_start(dev)
    with contextlib.suppress(usb.core.USBTimeoutError):
        dev.read(0x82, 4096, 100)
    for _ in range(5):  # the device goes at 5 ms of uptime
        with contextlib.suppress(usb.core.USBError):
            dev.read(0x82, 4096, 1)
    with pytest.raises(usb.core.USBError) as info:
        dev.read(0x82, 4096, 100)
    assert info.value.errno == errno.ENODEV
    assert "No such device (it may have been disconnected)" in str(info.value)
    assert not isinstance(info.value, usb.core.USBTimeoutError)
    with pytest.raises(usb.core.USBError, match="No such device"):
        read(dev, SYSINFO, 0)
    assert usb.core.find(idVendor=DAVIS_VID, backend=backend) is None


def test_stall_times_out_then_resumes_with_drops_counted():
    backend = Davis240CBackend(
        ScriptedSource(), faults=DavisFaults(stall_at_us=3000, stall_us=20_000), latency_us=0
    )
    dev = find(backend)
    data_start(dev)
    got = bytearray()
    timeouts = 0
    for _ in range(40):
        try:
            got += bytes(dev.read(0x82, 65536, 5))
        except usb.core.USBTimeoutError:
            timeouts += 1
    assert timeouts >= 3
    host = host_decode(bytes(got))
    times = np.array([e[0] for e in host.events])
    assert not np.any((times >= 3000) & (times < 23_000))  # DVS dropped while stalled
    assert times.max() > 23_000
    assert read(dev, MUX, 84) == 200  # one event per 100 µs for 20 ms


def test_odd_length_transfer_splits_a_word():
    backend = Davis240CBackend(
        ScriptedSource(), faults=DavisFaults(odd_packet_at_us=2000), latency_us=0
    )
    dev = find(backend)
    data_start(dev)
    lengths, data = [], bytearray()
    for _ in range(10):
        chunk = bytes(dev.read(0x82, 4096, 100))
        lengths.append(len(chunk))
        data += chunk
    odd = [i for i, n in enumerate(lengths) if n % 2]
    assert len(odd) == 2
    assert odd[1] == odd[0] + 1
    host = host_decode(bytes(data))
    assert [e[1:] for e in host.events] == [(7, 9, 1)] * len(host.events)


def test_device_side_timestamp_reset_mid_stream():
    source = ScriptedSource()
    backend = Davis240CBackend(
        source, faults=DavisFaults(timestamp_reset_at_us=10_000), latency_us=0
    )
    dev = find(backend)
    data_start(dev)
    w = np.frombuffer(read_for(dev, 20), "<u2")
    assert (w == 0x0001).sum() == 1
    assert len(source.resets) == 2
    assert source.resets[1] == 10_000 * 1000


def test_bandwidth_cap_drops_dvs_events():
    backend = Davis240CBackend(
        ScriptedSource(period_us=1),
        faults=DavisFaults(bandwidth_bytes_per_s=1_000_000.0),
        latency_us=0,
    )
    dev = find(backend)
    data_start(dev)
    data = read_for(dev, 4, size=1 << 16)
    uptime_s = backend.uptime_us * 1e-6
    assert len(data) <= 1_000_000.0 * uptime_s * 1.05
    assert read(dev, MUX, 84) > 0


def test_wrap_race_fault_produces_0xffff():
    backend = Davis240CBackend(
        ScriptedSource(period_us=8), faults=DavisFaults(wrap_race=True), latency_us=0
    )
    dev = find(backend)
    data_start(dev)
    w = np.frombuffer(read_for(dev, 2, size=1 << 16), "<u2").tolist()
    i = w.index(0x7001)
    assert w[i - 3 : i] == [0xFFFF, 0x1009, 0x3007]  # the event at 32768 µs, latched


def test_faults_are_validated():
    with pytest.raises(ValueError, match="stall_us"):
        DavisFaults(stall_us=-1)
    with pytest.raises(ValueError, match="bandwidth"):
        DavisFaults(bandwidth_bytes_per_s=0.0)


def test_realtime_device_drops_dvs_when_the_host_stops_reading():
    backend = Davis240CBackend(
        ScriptedSource(period_us=10), pacing="realtime", latency_us=0, buffer_bytes=4096
    )
    dev = find(backend)
    data_start(dev)
    dev.read(0x82, 512, 200)
    time.sleep(0.05)  # ~50 ms of 100 keps while nobody reads: the buffers overflow
    dev.read(0x82, 512, 200)
    assert read(dev, MUX, 84) > 0
