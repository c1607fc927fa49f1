"""The DAVIS240C driver: one contract suite (mock always, a real camera with --hardware),
then discovery/open errors and stream faults injected through the mock's pyusb backend."""

from __future__ import annotations

import array
import errno
import time
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import usb.backend
import usb.core

from mocaprig.acquire.davis240c import (
    PRODUCT_ID_FX2,
    REQUIRED_LOGIC_VERSION,
    UDEV_RULE,
    Davis240C,
    find_davis,
    load_mock_backend,
)
from mocaprig.acquire.davis240c_config import (
    ApsParam,
    ApsSettings,
    BiasParam,
    DavisSettings,
    Module,
    MuxParam,
    RegisterWrite,
    SysInfoParam,
    bias_set,
)
from mocaprig.acquire.davis240c_decode import DavisPacket, SpecialType
from mocaprig.drivers_mock.davis240c_usb import Davis240CBackend, DavisFaults, SyntheticDavisSource
from mocaprig.errors import (
    DeviceBusyError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceNotFoundError,
    DevicePermissionError,
    DeviceTimeoutError,
    ValidationError,
)

#: Start-sequence sleeps for the mock (the real camera keeps libcaer's 10/200/50 ms).
FAST = (0.0, 0.0, 0.0)


def mock(*, faults: DavisFaults | None = None, rate: float = 100_000.0, **kw: Any) -> Any:
    """The registered mock with a cheap synthetic world."""
    source = SyntheticDavisSource(seed=3, event_rate_hz=rate)
    return load_mock_backend(source=source, faults=faults, **kw)


def open_mock(backend: Any = None, **options: Any) -> Davis240C:
    options.setdefault("settle_delays_s", FAST)
    return Davis240C.open(backend=backend if backend is not None else mock(), **options)


def take(cam: Davis240C, n: int, *, timeout_s: float = 30.0) -> list[DavisPacket]:
    out = []
    for pkt in cam.packets(timeout_s=timeout_s):
        out.append(pkt)
        if len(out) >= n:
            break
    return out


# -- the contract: any DAVIS240C, simulated or real ---------------------------------------------


@pytest.fixture(params=["mock", "hardware"])
def camera(request: pytest.FixtureRequest) -> Iterator[Davis240C]:
    """An opened camera with default settings: the mock, or a real one with --hardware."""
    if request.param == "hardware":
        if not request.config.getoption("--hardware"):
            pytest.skip("real DAVIS240C not requested (run pytest with --hardware)")
        cam = Davis240C.open()
    else:
        cam = open_mock()
    with cam:
        yield cam


class TestDavis240CContract:
    """What every DAVIS240C (FX2, logic 18) must do through this driver."""

    def test_info_identifies_a_davis240c(self, camera: Davis240C) -> None:
        info = camera.info
        assert info.product_id == PRODUCT_ID_FX2
        assert info.logic_version == REQUIRED_LOGIC_VERSION
        assert info.logic_patch >= 1
        assert info.firmware_version >= 4
        assert info.chip_id == 2
        assert (info.dvs_size_x, info.dvs_size_y) == (240, 180)
        assert (info.aps_size_x, info.aps_size_y) == (240, 180)
        assert info.aps_has_global_shutter
        assert 1 <= len(info.serial) <= 8
        assert info.device_string == f"DAVIS240C_{info.serial}"
        assert (info.clocks.logic_mhz, info.clocks.adc_mhz, info.clocks.usb_mhz) == (90, 30, 30)

    def test_registers_read_back_what_was_written(self, camera: Davis240C) -> None:
        camera.config_set(Module.APS, ApsParam.EXPOSURE, 8000 * 30)
        assert camera.config_get(Module.APS, ApsParam.EXPOSURE) == 240000
        camera.config_set_many(
            [
                RegisterWrite(Module.APS, ApsParam.EXPOSURE, 4000 * 30),
                RegisterWrite(Module.APS, ApsParam.FRAME_INTERVAL, 20000 * 30),
            ]
        )
        assert camera.config_get(Module.APS, ApsParam.EXPOSURE) == 120000
        assert camera.config_get(Module.APS, ApsParam.FRAME_INTERVAL) == 600000

    def test_default_config_writes_the_libcaer_biases(self, camera: Davis240C) -> None:
        for param, bias in bias_set().items():
            assert camera.config_get(Module.BIAS, param) == bias.encode(), param.name

    def test_sysinfo_is_read_only_and_master_role_is_readable(self, camera: Davis240C) -> None:
        camera.config_set(Module.SYSINFO, SysInfoParam.LOGIC_VERSION, 3)
        assert camera.config_get(Module.SYSINFO, SysInfoParam.LOGIC_VERSION) == 18
        assert camera.is_master() is camera.info.device_is_master
        assert camera.config_get(Module.MUX, MuxParam.TIMESTAMP_RESET) == 0

    def test_stream_starts_at_our_timestamp_reset_and_delivers_events(
        self, camera: Davis240C
    ) -> None:
        camera.start()
        packets = take(camera, 30)
        camera.stop()
        assert not camera.running
        # Reads that end before our reset come out as empty "still alive" packets; nothing
        # from before the reset may reach the consumer, and the reset opens the stream.
        lead = next(i for i, p in enumerate(packets) if not p.empty)
        assert all(p.empty for p in packets[:lead])
        first = packets[lead].specials
        assert first.size
        assert first["type"][0] == SpecialType.TIMESTAMP_RESET
        events = np.concatenate([p.events for p in packets])
        assert events.size > 0
        assert (events["x"] < 240).all()
        assert (events["y"] < 180).all()
        assert (np.diff(events["t"]) >= 0).all()
        assert all(p.host_time_ns > 0 for p in packets)
        s = camera.stats()
        assert s.reads > 0
        assert s.bytes_read > 0
        assert s.decode.skipped_words == 0
        assert s.error is None

    def test_timestamp_reset_while_streaming_is_seen_in_the_stream(self, camera: Davis240C) -> None:
        camera.start()
        take(camera, 3)
        camera.timestamp_reset()
        seen = False
        for i, pkt in enumerate(camera.packets(timeout_s=30)):
            if SpecialType.TIMESTAMP_RESET in pkt.specials["type"] or i > 2000:
                seen = i <= 2000
                break
        camera.stop()
        assert seen

    def test_start_twice_is_refused_and_stop_is_idempotent(self, camera: Davis240C) -> None:
        camera.start()
        with pytest.raises(DeviceError, match="already streaming"):
            camera.start()
        camera.stop()
        camera.stop()
        camera.start()  # and it restarts
        assert take(camera, 2)
        camera.stop()

    def test_device_drop_statistics_are_readable(self, camera: Davis240C) -> None:
        drops = camera.device_drop_counts()
        if camera.info.mux_has_statistics:
            assert set(drops) == {"dvs", "ext_input"}
            assert all(v >= 0 for v in drops.values())
        else:
            assert drops == {}

    def test_a_closed_camera_says_so(self, camera: Davis240C) -> None:
        camera.close()
        assert camera.closed
        with pytest.raises(DeviceError, match="closed"):
            camera.config_get(Module.MUX, MuxParam.RUN)
        camera.close()  # idempotent


# -- discovery and open errors (mock only) ---------------------------------------------------------


class _EmptyBus(usb.backend.IBackend):  # type: ignore[misc]
    def enumerate_devices(self) -> list[object]:
        return []


def test_find_lists_the_mock_with_versions() -> None:
    (dev,) = find_davis(backend=mock(serial="00001234"))
    assert (dev.serial, dev.firmware_version, dev.logic_version, dev.logic_patch) == (
        "00001234",
        4,
        18,
        1,
    )
    assert dev.kind == "DAVIS FX2"
    assert dev.error is None


def test_not_found_says_what_is_on_the_bus() -> None:
    with pytest.raises(DeviceError, match=r"no DAVIS camera found.*no USB devices at all"):
        Davis240C.open(backend=_EmptyBus())


def test_wrong_serial_lists_the_serials_found() -> None:
    with pytest.raises(DeviceError, match="00000042"):
        open_mock(mock(serial="00000042"), serial="99999999")


def test_open_by_serial() -> None:
    with open_mock(mock(serial="00000777"), serial="00000777") as cam:
        assert cam.serial == "00000777"


class _Refusing(Davis240CBackend):
    """The mock, but claiming interface 0 fails with ``code``/``errno``."""

    refuse: tuple[str, int, int] = ("Access denied (insufficient permissions)", -3, errno.EACCES)

    def claim_interface(self, dev_handle: Any, intf: int) -> None:
        raise usb.core.USBError(*self.refuse)


def _refusing(refuse: tuple[str, int, int]) -> _Refusing:
    be = _Refusing(SyntheticDavisSource(seed=0))
    be.refuse = refuse
    return be


def test_permission_denied_points_to_the_udev_rule() -> None:
    be = _refusing(("Access denied (insufficient permissions)", -3, errno.EACCES))
    with pytest.raises(DeviceError, match=r"permission denied.*udev.*replug") as exc:
        Davis240C.open(backend=be)
    assert str(UDEV_RULE) in str(exc.value)
    assert UDEV_RULE.is_file()
    assert isinstance(exc.value.__cause__, usb.core.USBError)


def test_busy_says_another_process_holds_it() -> None:
    be = _refusing(("Resource busy", -6, errno.EBUSY))
    with pytest.raises(DeviceError, match="busy: another process holds it"):
        Davis240C.open(backend=be)


class _OldFirmware(Davis240CBackend):
    def get_device_descriptor(self, dev: object) -> Any:
        return replace(super().get_device_descriptor(dev), bcdDevice=0x0003)


def test_old_firmware_says_how_to_flash() -> None:
    with pytest.raises(DeviceError, match=r"firmware 3.*Flashy"):
        Davis240C.open(backend=_OldFirmware(SyntheticDavisSource(seed=0)))


def test_wrong_logic_version_says_how_to_flash() -> None:
    be = mock()
    original = be.registers.read
    be.registers.read = lambda m, p: 16 if (m, p) == (6, 0) else original(m, p)
    with pytest.raises(DeviceError, match=r"logic 16.1.*Flashy"):
        open_mock(be)


def test_options_are_validated() -> None:
    with pytest.raises(ValidationError, match="multiple of 512"):
        open_mock(read_size=1000)
    with pytest.raises(ValidationError, match="bias preset"):
        open_mock(bias_preset="loud")


def test_bias_preset_is_written_at_open() -> None:
    with open_mock(bias_preset="pyaer") as cam:
        assert (
            cam.config_get(Module.BIAS, BiasParam.ONBN)
            == bias_set("pyaer")[BiasParam.ONBN].encode()
        )


def test_settings_reach_the_device_in_its_units() -> None:
    settings = DavisSettings(aps=ApsSettings(exposure_us=1000, end_column=99))
    with open_mock(settings=settings) as cam:
        assert cam.config_get(Module.APS, ApsParam.EXPOSURE) == 30000
        assert cam.config_get(Module.APS, ApsParam.END_COLUMN_0) == 99


# -- stream faults (mock only) -------------------------------------------------------------------


def test_unplug_mid_stream_delivers_everything_then_raises() -> None:
    # Real-time pacing so that the unplug cannot overtake the start sequence.
    backend = mock(faults=DavisFaults(unplug_at_us=600_000), rate=50_000.0, pacing="realtime")
    with open_mock(backend) as cam:
        cam.start()
        got: list[DavisPacket] = []
        with pytest.raises(DeviceError, match=r"disconnected while streaming.*Replug") as exc:
            got.extend(cam.packets(timeout_s=30))
        assert isinstance(exc.value.__cause__, usb.core.USBError)
        s = cam.stats()
        assert not cam.running
        assert s.error is not None
        assert s.packets_dropped == 0
        events = np.concatenate([p.events for p in got])
        assert events.size == s.decode.events > 0  # every decoded event was delivered
        assert 0 < events["t"][-1] < 600_000
    # Closing after a disconnect is clean (no second error).


def test_a_stall_raises_a_clear_error_instead_of_hanging() -> None:
    faults = DavisFaults(stall_at_us=100_000, stall_us=10**12)
    with open_mock(mock(faults=faults)) as cam:
        cam.start()
        with pytest.raises(DeviceError, match=r"sent nothing for 0.5 s.*stalled"):
            for _ in cam.packets(timeout_s=0.5):
                pass
        assert cam.stats().read_timeouts > 0


class _OddReads(Davis240CBackend):
    """The mock, re-chunked so that every 7th bulk read ends in the middle of a word."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._rechunk = bytearray()
        self._reads = 0

    def bulk_read(self, dev_handle: Any, ep: int, intf: int, buff: Any, timeout: int) -> int:
        if len(self._rechunk) < 2:
            tmp = bytearray(len(buff))
            n = super().bulk_read(dev_handle, ep, intf, tmp, timeout)
            self._rechunk += tmp[:n]
        self._reads += 1
        k = min(len(buff), len(self._rechunk))
        if self._reads % 7 == 0 and k > 1 and k % 2 == 0:
            k -= 1
        buff[:k] = array.array("B", self._rechunk[:k])
        del self._rechunk[:k]
        return k


def test_odd_length_transfers_are_reassembled_across_reads() -> None:
    be = _OddReads(SyntheticDavisSource(seed=3, event_rate_hz=100_000.0))
    with open_mock(be) as cam:
        cam.start()
        events = np.concatenate([p.events for p in take(cam, 40)])
        cam.stop()
        s = cam.stats().decode
    assert s.odd_trailing_bytes >= 5
    assert s.skipped_words == 0
    assert s.non_monotonic_timestamps == 0
    assert (np.diff(events["t"]) >= 0).all()


def test_the_mocks_odd_packet_fault_is_survived() -> None:
    with open_mock(mock(faults=DavisFaults(odd_packet_at_us=20_000))) as cam:
        cam.start()
        take(cam, 60, timeout_s=5.0)
        cam.stop()
        s = cam.stats().decode
    assert s.odd_trailing_bytes >= 1
    assert s.skipped_words == 0


def test_a_device_side_timestamp_reset_reaches_the_consumer() -> None:
    with open_mock(mock(faults=DavisFaults(timestamp_reset_at_us=150_000))) as cam:
        cam.start()
        resets = 0
        for i, pkt in enumerate(cam.packets(timeout_s=30)):
            resets += int(np.count_nonzero(pkt.specials["type"] == SpecialType.TIMESTAMP_RESET))
            if resets >= 2 or i > 2000:
                break
        cam.stop()
    assert resets == 2  # ours at start, then the device's


def test_device_side_dvs_drops_are_read_from_the_mux_statistics() -> None:
    backend = mock(faults=DavisFaults(bandwidth_bytes_per_s=50_000.0), rate=2_000_000.0)
    with open_mock(backend) as cam:
        cam.start()
        take(cam, 30)
        drops = cam.device_drop_counts()
        cam.stop()
    assert drops["dvs"] > 0


def test_a_slow_consumer_loses_counted_packets_but_keeps_specials() -> None:
    with open_mock(mock(), queue_packets=2) as cam:
        cam.start()
        # Wait (without consuming) until the queue has overflowed.
        while cam.stats().packets_dropped < 20:
            if not cam.running:  # pragma: no cover - the mock stopped by itself
                break
            time.sleep(0.01)
        cam.stop()
        s = cam.stats()
        delivered = []
        while (pkt := cam.get_packet(0)) is not None:
            delivered.append(pkt)
    assert s.packets_dropped >= 20
    assert s.events_dropped > 0
    assert s.packets_delivered == len(delivered)
    specials = np.concatenate([p.specials for p in delivered])
    assert s.specials_dropped == 0
    # Dropped packets' specials (ext-input pulses at 30 Hz, APS markers) ride on later packets.
    assert specials.size > sum(1 for _ in delivered) // 10


# -- which DeviceError kind, with the libusb code kept (mock only) -------------------------------


def test_no_camera_and_a_wrong_serial_are_not_found_errors() -> None:
    with pytest.raises(DeviceNotFoundError, match="no DAVIS camera found") as exc:
        Davis240C.open(backend=_EmptyBus())
    assert exc.value.backend_code is None
    with pytest.raises(DeviceNotFoundError, match=r"serial '99999999'.*00000042"):
        open_mock(mock(serial="00000042"), serial="99999999")


@pytest.mark.parametrize(
    ("refuse", "kind", "words"),
    [
        (
            ("Access denied (insufficient permissions)", -3, errno.EACCES),
            DevicePermissionError,
            r"permission denied.*udev",
        ),
        (("Resource busy", -6, errno.EBUSY), DeviceBusyError, "busy: another process holds it"),
        (("Entity not found", -5, errno.ENOENT), DeviceNotFoundError, "cannot claim interface 0"),
        (
            ("No such device (it may have been disconnected)", -4, errno.ENODEV),
            DeviceDisconnectedError,
            "cannot claim interface 0",
        ),
        (("Operation timed out", -7, errno.ETIMEDOUT), DeviceTimeoutError, "cannot claim"),
        (("Input/Output Error", -1, errno.EIO), DeviceError, "cannot claim interface 0"),
    ],
)
def test_a_refused_claim_is_the_kind_its_libusb_code_says(
    refuse: tuple[str, int, int], kind: type[DeviceError], words: str
) -> None:
    with pytest.raises(DeviceError, match=words) as exc:
        Davis240C.open(backend=_refusing(refuse))
    assert type(exc.value) is kind
    assert exc.value.backend_code == refuse[1]
    assert exc.value.backend_errno == refuse[2]
    assert exc.value.backend_error == refuse[0]
    assert isinstance(exc.value.__cause__, usb.core.USBError)


class _SlowControl(Davis240CBackend):
    """The mock, but once ``timing_out`` is set every control transfer times out."""

    timing_out = False

    def ctrl_transfer(
        self,
        dev_handle: Any,
        bmRequestType: int,
        bRequest: int,
        wValue: int,
        wIndex: int,
        data: Any,
        timeout: int,
    ) -> int:
        if self.timing_out:
            raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
        return super().ctrl_transfer(
            dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout
        )


class _NoStringAccess(_SlowControl):
    """The mock, but reading a string descriptor (the serial) is denied, as without the rule."""

    def ctrl_transfer(
        self,
        dev_handle: Any,
        bmRequestType: int,
        bRequest: int,
        wValue: int,
        wIndex: int,
        data: Any,
        timeout: int,
    ) -> int:
        if bmRequestType == 0x80 and bRequest == 6 and wValue >> 8 == 3:  # GET_DESCRIPTOR string
            raise usb.core.USBError("Access denied (insufficient permissions)", -3, errno.EACCES)
        return super().ctrl_transfer(
            dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout
        )


def test_an_unreadable_serial_is_a_permission_error_and_find_says_why() -> None:
    be = _NoStringAccess(SyntheticDavisSource(seed=0), serial="00000042")
    with pytest.raises(DevicePermissionError, match=r"DAVIS camera at bus .*permission denied"):
        Davis240C.open(backend=be)
    (dev,) = find_davis(backend=be)
    assert dev.serial is None
    assert dev.error is not None
    assert dev.error.startswith("permission denied; install the udev rule")


def test_a_control_transfer_timeout_is_a_timeout_error() -> None:
    be = _SlowControl(SyntheticDavisSource(seed=0))
    with open_mock(be) as cam:
        be.timing_out = True
        with pytest.raises(DeviceTimeoutError, match=r"USB error while reading register") as exc:
            cam.config_get(Module.MUX, MuxParam.RUN)
        assert (exc.value.backend_code, exc.value.backend_errno) == (-7, errno.ETIMEDOUT)
        assert isinstance(exc.value.__cause__, usb.core.USBTimeoutError)
        with pytest.raises(DeviceTimeoutError, match="while writing 2 registers"):
            cam.timestamp_reset()
        be.timing_out = False


def test_unplugged_while_streaming_is_a_disconnected_error_with_the_libusb_code() -> None:
    # Real-time pacing (as above) so that the unplug cannot overtake the start sequence.
    backend = mock(faults=DavisFaults(unplug_at_us=600_000), rate=50_000.0, pacing="realtime")
    with open_mock(backend) as cam:
        cam.start()
        with pytest.raises(DeviceDisconnectedError, match="disconnected while streaming") as exc:
            for _ in cam.packets(timeout_s=30):
                pass
        assert (exc.value.backend_code, exc.value.backend_errno) == (-4, errno.ENODEV)
        assert exc.value.backend_error == "No such device (it may have been disconnected)"
        # Register access after the unplug names it too.
        with pytest.raises(DeviceDisconnectedError, match="disconnected while reading") as exc2:
            cam.config_get(Module.MUX, MuxParam.RUN)
        assert exc2.value.backend_code == -4


def test_a_stalled_stream_is_a_timeout_error() -> None:
    faults = DavisFaults(stall_at_us=100_000, stall_us=10**12)
    with open_mock(mock(faults=faults)) as cam:
        cam.start()
        with pytest.raises(DeviceTimeoutError, match=r"sent nothing for 0.2 s.*stalled"):
            for _ in cam.packets(timeout_s=0.2):
                pass
