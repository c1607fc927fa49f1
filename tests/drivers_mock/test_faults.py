"""Fault proxies at the real boundaries: pyusb, the depth camera, pyserial, the output file."""

from __future__ import annotations

import errno
from pathlib import Path
from typing import Any

import pytest
import serial
import usb.core

from mocaprig.acquire.syncbox import SyncBox
from mocaprig.drivers_mock.faults import FaultSchedule, ScheduledFault
from mocaprig.errors import DeviceDisconnectedError, DeviceNotFoundError, ValidationError


class _Clock:
    """A schedule clock the test sets by hand (seconds)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _schedule(*faults: ScheduledFault) -> tuple[FaultSchedule, _Clock]:
    clock = _Clock()
    sched = FaultSchedule(faults, clock=clock)
    sched.start()
    return sched, clock


def test_text_form_reads_every_field() -> None:
    sched = FaultSchedule.parse("davis-unplug@0.5+0.4:00000042, d415-disconnect@1,disk-full@2:4096")
    assert sched.faults == (
        ScheduledFault("davis-unplug", 0.5, 0.4, target="00000042"),
        ScheduledFault("d415-disconnect", 1.0),
        ScheduledFault("disk-full", 2.0, spare_bytes=4096),
    )


@pytest.mark.parametrize("text", ["davis-unplug", "usb-melt@1", "davis-unplug@x", "disk-full@-1"])
def test_text_form_refuses_what_it_cannot_read(text: str) -> None:
    with pytest.raises(ValidationError, match="fault"):
        FaultSchedule.parse(text)


class _Usb:
    """The least of a pyusb backend the proxy forwards to."""

    serial = "00000042"

    def __init__(self) -> None:
        self.closed: list[object] = []

    def enumerate_devices(self) -> list[str]:
        return [self.serial]

    def open_device(self, dev: object) -> object:
        return object()

    def close_device(self, handle: object) -> None:
        self.closed.append(handle)

    def release_interface(self, handle: object, intf: int) -> None:
        pass

    def bulk_read(self, handle: object, ep: int, intf: int, buff: Any, timeout: int) -> int:
        buff[:2] = b"\x01\x02"
        return 2


def test_unplugged_davis_is_off_the_bus_and_raises_enodev_as_libusb() -> None:
    sched, clock = _schedule(ScheduledFault("davis-unplug", 1.0, 1.0))
    inner = _Usb()
    be = sched.davis_backend(inner)
    old = be.open_device("00000042")
    buf = bytearray(4)
    assert be.bulk_read(old, 0x82, 0, buf, 100) == 2
    clock.t = 1.5
    assert be.enumerate_devices() == []
    with pytest.raises(usb.core.USBError) as exc:
        be.bulk_read(old, 0x82, 0, buf, 100)
    assert exc.value.errno == errno.ENODEV
    assert exc.value.backend_error_code == -4  # LIBUSB_ERROR_NO_DEVICE
    clock.t = 2.5  # plugged back: on the bus again, the old handle stays dead
    assert be.enumerate_devices() == ["00000042"]
    with pytest.raises(usb.core.USBError):
        be.bulk_read(old, 0x82, 0, buf, 100)
    be.close_device(old)
    assert inner.closed == [old]  # freeing a dead handle still reaches the device
    new = be.open_device("00000042")
    assert be.bulk_read(new, 0x82, 0, buf, 100) == 2


class _Cam:
    """The least of a DepthCamera."""

    def __init__(self) -> None:
        self.info = type("Info", (), {"serial": "123"})()
        self.streaming = False
        self.closed = False

    def start(self) -> None:
        self.streaming = True

    def stop(self) -> None:
        self.streaming = False

    def close(self) -> None:
        self.closed = True

    def poll(self, timeout_s: float = 0.0) -> str:
        return "frameset"

    def intrinsics(self) -> str:
        return "k"


def test_disconnected_d415_goes_silent_and_is_found_again_once_back() -> None:
    sched, clock = _schedule(ScheduledFault("d415-disconnect", 1.0, 1.0, target="123"))
    inner = _Cam()
    cam = sched.depth_camera(inner)
    cam.start()
    assert cam.poll(0.0) == "frameset"
    clock.t = 1.2
    assert cam.poll(0.01) is None  # librealsense raises nothing: frames stop
    with pytest.raises(DeviceDisconnectedError, match="No such device"):
        cam.intrinsics()
    with pytest.raises(DeviceNotFoundError, match="123 not connected"):
        sched.find_depth_camera("123")
    cam.close()
    assert not inner.closed  # the camera still exists, only this handle is gone
    clock.t = 2.1
    assert cam.is_streaming is False
    again = sched.find_depth_camera("123")
    again.start()
    assert again.poll(0.0) == "frameset"
    again.close()
    assert inner.closed


def test_pulled_syncbox_cable_fails_reads_and_opens_as_pyserial_does() -> None:
    pytest.importorskip("pty")
    from mocaprig.drivers_mock.syncbox import mock_syncbox

    sched, clock = _schedule(ScheduledFault("syncbox-unplug", 1.0, 1.0))
    with mock_syncbox(seed=0) as mock:
        url = sched.serial_port(str(mock.port))
        port = serial.serial_for_url(url, timeout=0.05)
        port.write(b"HELLO\n")
        clock.t = 1.5
        with pytest.raises(serial.SerialException, match="device disconnected"):
            port.read(1)
        port.close()
        with pytest.raises(serial.SerialException) as exc:
            serial.serial_for_url(url)
        assert exc.value.errno == errno.ENOENT
        clock.t = 2.5
        with SyncBox(url) as box:  # back: the driver opens it through the same URL
            assert box.identity is not None
            assert box.identity.board == "mock"


def test_full_disk_writes_what_fits_then_enospc_and_truncating_frees_room(
    tmp_path: Path,
) -> None:
    sched, clock = _schedule(ScheduledFault("disk-full", 1.0, spare_bytes=10))
    p = tmp_path / "a.bin"
    with sched.open_file(p, "xb") as f:
        f.write(b"x" * 100)
        f.flush()
        clock.t = 1.0
        f.write(b"y" * 25)
        with pytest.raises(OSError, match="No space left") as exc:
            f.flush()
        assert exc.value.errno == errno.ENOSPC
        with pytest.raises(OSError, match="No space left"):
            f.close()
    assert p.read_bytes() == b"x" * 100 + b"y" * 10
    with sched.open_file(p, "r+b") as g:
        g.truncate(50)
        g.seek(50)
        g.write(b"z" * 60)  # 50 + 60 = 110: what the disk had room for
        g.flush()
    assert p.stat().st_size == 110
