"""Device faults on a schedule, injected at the real boundaries while the mock rig records.

A :class:`FaultSchedule` holds :class:`ScheduledFault` s by time (seconds from :meth:`start`)
and wraps the mocks as proxies, so the drivers above them meet what real hardware does
(the mocks themselves are not edited):

* ``davis-unplug``: :class:`FaultyUsbBackend` around the DAVIS mock's pyusb ``IBackend``. While
  unplugged the bus is empty and every call raises ``usb.core.USBError`` with errno ``ENODEV``
  and ``LIBUSB_ERROR_NO_DEVICE`` (-4), as libusb does for a device gone from the bus; a handle
  opened before the unplug stays dead afterwards (libusb never revives one), the device shows up
  again on the bus when it is plugged back and is opened anew.
* ``d415-disconnect``: :class:`FaultyDepthCamera` around a mock D415. librealsense raises nothing
  when a camera is unplugged while streaming: frames stop (``pipeline.wait_for_frames`` times
  out with ``RuntimeError("Frame didn't arrive within 5000")``, librealsense#7048, #2866; our
  adapter's ``frame_queue.try_wait_for_frame`` just returns nothing). So ``poll`` returns None;
  control calls raise what the adapter makes of the SDK's "No such device" error
  (:class:`~mocaprig.errors.DeviceDisconnectedError`); enumeration (:meth:`find_depth_camera`)
  does not list it until it is back.
* ``syncbox-unplug``: the sync box's serial port, through a pyserial URL handler
  (``serial.serial_for_url("mocaprigfault://<n>/dev/pts/..")``, pyserial's extension point).
  While the cable is out, reads and writes raise ``serial.SerialException`` with the words
  pyserial uses for a vanished USB CDC device, and opening raises ``SerialException(ENOENT)``
  as for a missing ``/dev/ttyACM0``.
* ``disk-full``: the recorder's output file (``Recorder(open_file=...)``). From ``at_s`` on the
  file may grow by ``spare_bytes`` more; a write beyond writes what fits and raises
  ``OSError(ENOSPC)``, as ``write(2)`` does; bytes freed by truncating the file are writable
  again.

Text form (``--mock-faults``): comma-separated ``KIND@AT[+FOR][:TARGET]``, seconds, e.g.
``davis-unplug@0.5+0.4,d415-disconnect@0.6+0.5,syncbox-unplug@0.4+0.3,disk-full@1.5``
(without ``+FOR`` a device never comes back; TARGET: a serial, default every device of the
kind; ``disk-full`` takes ``:SPARE_BYTES``).

Limits: a replugged mock keeps its state (the DAVIS logic's registers, the box's run), where a
real device powers up afresh; the drivers re-configure and the sources stop a left-over run, so
the recording does not depend on it.
"""

from __future__ import annotations

import errno
import io
import itertools
import os
import threading
import time
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Final, Literal, cast, get_args

import serial
import usb.backend

from mocaprig.drivers_mock.davis240c_usb import _no_device
from mocaprig.errors import DeviceDisconnectedError, DeviceNotFoundError, ValidationError

__all__ = [
    "FaultName",
    "FaultSchedule",
    "FaultyDepthCamera",
    "FaultyUsbBackend",
    "ScheduledFault",
    "fault_schedule",
    "serial_class_for_url",
]

FaultName = Literal["davis-unplug", "d415-disconnect", "syncbox-unplug", "disk-full"]
_NAMES: Final[tuple[str, ...]] = get_args(FaultName)

#: What pyserial's POSIX read raises when a USB CDC device vanishes (``serialposix.py``).
_SERIAL_GONE: Final = (
    "device reports readiness to read but returned no data (device disconnected or multiple "
    "access on port?)"
)
#: The URL scheme of the serial proxy (``serial.serial_for_url``).
URL_SCHEME: Final = "mocaprigfault"


@dataclass(frozen=True, slots=True)
class ScheduledFault:
    """One fault of a schedule.

    Attributes:
        kind: Which boundary fails (module doc).
        at_s: When, in seconds from :meth:`FaultSchedule.start`.
        duration_s: How long (s) until the device is plugged back (or the disk has room
            again); None: for the rest of the session.
        target: The device serial it hits (DAVIS, D415); None: every device of the kind.
        spare_bytes: ``disk-full`` only: bytes the file may still grow by after ``at_s``.
    """

    kind: FaultName
    at_s: float
    duration_s: float | None = None
    target: str | None = None
    spare_bytes: int = 0

    def __post_init__(self) -> None:
        if self.kind not in _NAMES:
            msg = f"unknown fault kind {self.kind!r}; choose one of {', '.join(_NAMES)}"
            raise ValidationError(msg)
        if not self.at_s >= 0 or (self.duration_s is not None and not self.duration_s > 0):
            msg = (
                f"fault {self.kind}: at_s must be >= 0 and duration_s > 0, got {self.at_s}, "
                f"{self.duration_s}"
            )
            raise ValidationError(msg)
        if self.spare_bytes < 0:
            msg = f"fault {self.kind}: spare_bytes must be >= 0, got {self.spare_bytes}"
            raise ValidationError(msg)

    def active(self, t_s: float) -> bool:
        """Whether the fault holds at ``t_s`` (schedule seconds)."""
        return t_s >= self.at_s and (self.duration_s is None or t_s < self.at_s + self.duration_s)

    def hits(self, serial: str | None) -> bool:
        """Whether the fault concerns the device ``serial``."""
        return self.target is None or self.target == serial

    @classmethod
    def parse(cls, text: str) -> ScheduledFault:
        """``KIND@AT[+FOR][:TARGET]`` (module doc).

        Raises:
            ValidationError: not of that form, or values out of range.
        """
        head, _, target = text.strip().partition(":")
        kind, at_sep, when = head.partition("@")
        at, _, dur = when.partition("+")
        try:
            at_s = float(at)
            duration_s = float(dur) if dur else None
            spare = int(target) if kind == "disk-full" and target else 0
        except ValueError as err:
            msg = (
                f"cannot read the fault {text!r}: write KIND@AT[+FOR][:TARGET] in seconds, e.g. "
                "davis-unplug@0.5+0.4 or disk-full@2:4096"
            )
            raise ValidationError(msg) from err
        if not at_sep:
            msg = f"fault {text!r} has no time: write KIND@AT[+FOR], e.g. davis-unplug@0.5+0.4"
            raise ValidationError(msg)
        return cls(
            cast(FaultName, kind),
            at_s,
            duration_s,
            target=None if kind == "disk-full" or not target else target,
            spare_bytes=spare,
        )


_SCHEDULES: weakref.WeakValueDictionary[int, FaultSchedule] = weakref.WeakValueDictionary()
_IDS = itertools.count(1)


class FaultSchedule:
    """Faults by time, and the proxies that inject them (what ``record_session.MockFaults``
    asks for). Thread-safe.

    Args:
        faults: The faults.
        clock: Monotonic seconds (tests may pass a fake).
    """

    def __init__(
        self, faults: Sequence[ScheduledFault], *, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.faults = tuple(faults)
        self._clock = clock
        self._t0: float | None = None
        self._lock = threading.Lock()
        self._cameras: dict[str, Any] = {}  # serial -> the mock D415 behind the proxies
        self._disk_limit: dict[Path, int] = {}  # path -> the size the file may reach
        self.id = next(_IDS)
        _SCHEDULES[self.id] = self

    @classmethod
    def parse(cls, text: str) -> FaultSchedule:
        """A schedule from its text form (module doc).

        Raises:
            ValidationError: a fault that cannot be read.
        """
        items = [t for t in text.split(",") if t.strip()]
        if not items:
            msg = "no fault given: write KIND@AT[+FOR][:TARGET], comma-separated"
            raise ValidationError(msg)
        return cls([ScheduledFault.parse(t) for t in items])

    # -- time ----------------------------------------------------------------------------------

    def start(self) -> None:
        """Start the schedule's clock (idempotent; the first query starts it otherwise)."""
        with self._lock:
            if self._t0 is None:
                self._t0 = self._clock()

    def elapsed_s(self) -> float:
        """Seconds since :meth:`start` (which this starts, when not yet)."""
        self.start()
        return self._clock() - cast(float, self._t0)

    def active(self, kind: FaultName, serial: str | None = None) -> bool:
        """Whether a ``kind`` fault holds now for device ``serial``."""
        t = self.elapsed_s()
        return any(f.kind == kind and f.hits(serial) and f.active(t) for f in self.faults)

    def generation(self, kind: FaultName, serial: str | None = None) -> int:
        """How many ``kind`` faults for ``serial`` have begun: a handle opened in an earlier
        generation belongs to a device that was unplugged since."""
        t = self.elapsed_s()
        return sum(1 for f in self.faults if f.kind == kind and f.hits(serial) and t >= f.at_s)

    def gone(self, kind: FaultName, serial: str | None = None, opened: int | None = None) -> bool:
        """Whether a ``kind`` fault holds now for device ``serial`` or, for a handle opened in
        generation ``opened``, one has begun since (one clock read for both)."""
        t = self.elapsed_s()
        began = 0
        for f in self.faults:
            if f.kind == kind and f.hits(serial):
                if f.active(t):
                    return True
                if t >= f.at_s:
                    began += 1
        return opened is not None and opened < began

    # -- the boundaries ------------------------------------------------------------------------

    def davis_backend(self, backend: Any) -> FaultyUsbBackend:
        """The DAVIS mock's pyusb backend behind ``davis-unplug`` faults."""
        return FaultyUsbBackend(backend, self)

    def depth_camera(self, cam: Any) -> FaultyDepthCamera:
        """A mock D415 behind ``d415-disconnect`` faults."""
        serial = str(cam.info.serial)
        with self._lock:
            self._cameras[serial] = cam
        return FaultyDepthCamera(cam, self)

    def find_depth_camera(self, serial: str) -> FaultyDepthCamera:
        """Enumerate the D415 ``serial`` (as ``enumerate_cameras(serials=[...])``).

        Raises:
            DeviceNotFoundError: it is unplugged now, or was never wrapped here.
        """
        with self._lock:
            cam = self._cameras.get(serial)
        if cam is None or self.active("d415-disconnect", serial):
            msg = f"D415 {serial} not connected (found: none); check USB"
            raise DeviceNotFoundError(msg)
        return FaultyDepthCamera(cam, self)

    def serial_port(self, port: str) -> str:
        """The URL that opens ``port`` (a path) through ``syncbox-unplug`` faults."""
        _register_url_handler()
        return f"{URL_SCHEME}://{self.id}{port}"

    def open_file(self, path: Path, mode: str) -> BinaryIO:
        """Open the recorder's output ``path`` (``"xb"``, ``"r+b"``) behind ``disk-full``."""
        raw = _FaultyFile(Path(path), mode.replace("b", ""), self)
        return cast(BinaryIO, io.BufferedRandom(raw) if "+" in mode else io.BufferedWriter(raw))

    def _disk_room(self, path: Path, pos: int) -> int | None:
        """Bytes writable at offset ``pos`` of ``path`` (None: no limit now)."""
        t = self.elapsed_s()
        fault = next((f for f in self.faults if f.kind == "disk-full" and f.active(t)), None)
        with self._lock:
            if fault is None:
                self._disk_limit.pop(path, None)
                return None
            limit = self._disk_limit.setdefault(path, pos + fault.spare_bytes)
        return max(limit - pos, 0)


def fault_schedule(spec: str) -> FaultSchedule:
    """The schedule of a ``--mock-faults`` text (the ``mocaprig.mocks`` entry point ``faults``)."""
    return FaultSchedule.parse(spec)


# -------------------------------------------------------------------------------------------
# DAVIS: pyusb backend


class FaultyUsbBackend(usb.backend.IBackend):  # type: ignore[misc]
    """A pyusb ``IBackend`` that forwards to ``inner`` unless the device is unplugged.

    Handles are tagged with the plug generation they were opened in; one from before an unplug
    raises ``ENODEV`` for good (closing and releasing it still reach ``inner``, to free it).
    """

    def __init__(self, inner: Any, schedule: FaultSchedule) -> None:
        super().__init__()
        self.inner = inner
        self.schedule = schedule
        self.serial: str | None = getattr(inner, "serial", None)
        self._handles: dict[int, int] = {}  # id(handle) -> generation at open

    def _gone(self, handle: Any = None) -> bool:
        opened = None if handle is None else self._handles.get(id(handle))
        return self.schedule.gone("davis-unplug", self.serial, opened)

    def _check(self, handle: Any = None) -> None:
        if self._gone(handle):
            raise _no_device()

    def enumerate_devices(self) -> Any:
        """Nothing while unplugged."""
        return [] if self._gone() else self.inner.enumerate_devices()

    def get_device_descriptor(self, dev: Any) -> Any:
        """The descriptor pyusb cached at enumeration (readable after an unplug too)."""
        return self.inner.get_device_descriptor(dev)

    def get_configuration_descriptor(self, dev: Any, config: int) -> Any:
        """As ``inner``."""
        return self.inner.get_configuration_descriptor(dev, config)

    def get_interface_descriptor(self, dev: Any, intf: int, alt: int, config: int) -> Any:
        """As ``inner``."""
        return self.inner.get_interface_descriptor(dev, intf, alt, config)

    def get_endpoint_descriptor(self, dev: Any, ep: int, intf: int, alt: int, config: int) -> Any:
        """As ``inner``."""
        return self.inner.get_endpoint_descriptor(dev, ep, intf, alt, config)

    def open_device(self, dev: Any) -> Any:
        """A new handle of the current plug generation."""
        self._check()
        handle = self.inner.open_device(dev)
        self._handles[id(handle)] = self.schedule.generation("davis-unplug", self.serial)
        return handle

    def close_device(self, dev_handle: Any) -> None:
        """Always frees the handle (libusb_close works on a gone device)."""
        self._handles.pop(id(dev_handle), None)
        self.inner.close_device(dev_handle)

    def release_interface(self, dev_handle: Any, intf: int) -> None:
        """Frees the claim; ``ENODEV`` afterwards when the device is gone."""
        self.inner.release_interface(dev_handle, intf)
        self._check(dev_handle)

    def bulk_read(self, dev_handle: Any, ep: int, intf: int, buff: Any, timeout: int) -> int:
        """As ``inner`` while plugged; ``ENODEV`` (also for a read that was waiting) after."""
        self._check(dev_handle)
        n = int(self.inner.bulk_read(dev_handle, ep, intf, buff, timeout))
        self._check(dev_handle)  # unplugged during the transfer: its data never arrived
        return n

    def ctrl_transfer(
        self,
        dev_handle: Any,
        bmRequestType: int,  # pyusb's names
        bRequest: int,
        wValue: int,
        wIndex: int,
        data: Any,
        timeout: int,
    ) -> Any:
        """As ``inner`` while plugged."""
        self._check(dev_handle)
        return self.inner.ctrl_transfer(
            dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout
        )

    def __getattr__(self, name: str) -> Any:
        # Only reached for names IBackend does not define (the mock's own extras).
        return getattr(self.inner, name)


def _forward(name: str) -> Callable[..., Any]:
    def method(self: FaultyUsbBackend, dev_handle: Any, *args: Any) -> Any:
        self._check(dev_handle)
        return getattr(self.inner, name)(dev_handle, *args)

    method.__name__ = name
    method.__doc__ = f"``inner.{name}`` while plugged, ``ENODEV`` after."
    return method


for _name in (
    "set_configuration",
    "get_configuration",
    "set_interface_altsetting",
    "claim_interface",
    "bulk_write",
    "intr_write",
    "intr_read",
    "iso_write",
    "iso_read",
    "clear_halt",
    "reset_device",
    "is_kernel_driver_active",
    "detach_kernel_driver",
    "attach_kernel_driver",
):
    setattr(FaultyUsbBackend, _name, _forward(_name))


# -------------------------------------------------------------------------------------------
# D415: the DepthCamera protocol


class FaultyDepthCamera:
    """A mock D415 that goes silent when unplugged, as a RealSense camera does.

    One proxy is one opened camera: after an unplug it stays dead (frames never come back
    through it); :meth:`FaultSchedule.find_depth_camera` gives a new one once the camera is
    back. Closing a dead proxy stops the mock without closing it (the device still exists);
    closing a live one closes the mock.
    """

    def __init__(self, inner: Any, schedule: FaultSchedule) -> None:
        self.inner = inner
        self.schedule = schedule
        self.serial = str(inner.info.serial)
        self._generation = schedule.generation("d415-disconnect", self.serial)
        self._closed = False

    def _gone(self) -> bool:
        return self.schedule.gone("d415-disconnect", self.serial, self._generation)

    def _check(self, what: str) -> None:
        if self._closed:
            msg = f"D415 {self.serial} is closed"
            raise DeviceDisconnectedError(msg)
        if self._gone():
            cause = RuntimeError(f"{what}: No such device")
            msg = f"D415 {self.serial}: {what} failed ({cause}); replug the camera"
            raise DeviceDisconnectedError.from_cause(msg, cause) from cause

    @property
    def info(self) -> Any:
        """The camera's identity (known after it is gone, as the adapter keeps it)."""
        return self.inner.info

    @property
    def depth_scale_m(self) -> float:
        """As the mock."""
        return float(self.inner.depth_scale_m)

    @property
    def sync_mode(self) -> Any:
        """As the mock."""
        return self.inner.sync_mode

    @property
    def is_streaming(self) -> bool:
        """False once the camera is gone."""
        return not self._gone() and bool(self.inner.is_streaming)

    def configure(self, *, stream: Any, options: Any, sync_mode: Any) -> None:
        """As the mock while plugged."""
        self._check("configure")
        self.inner.configure(stream=stream, options=options, sync_mode=sync_mode)

    def intrinsics(self) -> Any:
        """As the mock while plugged."""
        self._check("get_intrinsics")
        return self.inner.intrinsics()

    def extrinsics_ir_to_depth(self) -> Any:
        """As the mock while plugged."""
        self._check("get_extrinsics_to")
        return self.inner.extrinsics_ir_to_depth()

    def start(self) -> None:
        """As the mock while plugged."""
        self._check("start")
        self.inner.start()

    def poll(self, timeout_s: float = 0.0) -> Any:
        """The mock's frames while plugged; silence (None after ``timeout_s``) once gone."""
        if self._closed:
            msg = f"D415 {self.serial} is not streaming; call start() first"
            raise DeviceDisconnectedError(msg)
        if self._gone():
            time.sleep(max(0.0, timeout_s))
            return None
        return self.inner.poll(timeout_s)

    def stop(self) -> None:
        """Stop the mock (a gone camera stopped by itself)."""
        if not self._closed:
            self.inner.stop()

    def close(self) -> None:
        """Release the camera (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._gone():
            self.inner.stop()  # the device still exists: a later proxy opens it again
        else:
            self.inner.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def __repr__(self) -> str:
        return f"FaultyDepthCamera({self.inner!r})"


# -------------------------------------------------------------------------------------------
# Sync box: a pyserial URL handler


def _register_url_handler() -> None:
    """Make ``serial.serial_for_url`` find :func:`serial_class_for_url` for ``mocaprigfault://``.

    pyserial imports ``<package>.protocol_<scheme>`` for each package of
    ``serial.protocol_handler_packages`` (its documented extension point); the handler is
    :mod:`.protocol_mocaprigfault`, which re-exports :func:`serial_class_for_url`.
    """
    package = __name__.rpartition(".")[0]
    if package not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(package)


def serial_class_for_url(url: str) -> tuple[str, type[serial.Serial]]:
    """pyserial's handler hook: ``mocaprigfault://<schedule id><path>`` -> the path and a
    ``serial.Serial`` class that fails while the schedule's ``syncbox-unplug`` holds.

    Raises:
        serial.SerialException: an unknown schedule (pyserial's error for a bad URL).
    """
    rest = url.split("://", 1)[1]
    ident, slash, path = rest.partition("/")
    found = _SCHEDULES.get(int(ident)) if ident.isdigit() else None
    if found is None or not slash:
        msg = f"{url!r}: no fault schedule {ident!r} in this process"
        raise serial.SerialException(msg)
    schedule: FaultSchedule = found

    class _Port(_FaultySerial):
        _schedule = schedule

    return "/" + path, _Port


class _FaultySerial(serial.Serial):  # type: ignore[misc]
    """A serial port whose cable the schedule pulls (module doc)."""

    _schedule: FaultSchedule
    _generation = 0

    def _pulled(self) -> bool:
        return self._schedule.gone("syncbox-unplug", opened=self._generation)

    def open(self) -> None:
        """Open the port; ``ENOENT`` while the cable is out (the device node is gone)."""
        if self._schedule.active("syncbox-unplug"):
            err = f"[Errno 2] No such file or directory: {self.port!r}"
            raise serial.SerialException(errno.ENOENT, f"could not open port {self.port}: {err}")
        self._generation = self._schedule.generation("syncbox-unplug")
        super().open()

    def read(self, size: int = 1) -> bytes:
        """As the port while plugged; ``SerialException`` once the cable was pulled."""
        if self._pulled():
            raise serial.SerialException(_SERIAL_GONE)
        return bytes(super().read(size))

    def write(self, b: Any, /) -> int | None:
        """As the port while plugged; ``SerialException`` once the cable was pulled."""
        if self._pulled():
            raise serial.SerialException(errno.EIO, f"write failed: [Errno {errno.EIO}] EIO")
        n: int | None = super().write(b)
        return n

    @property
    def in_waiting(self) -> int:
        """As the port while plugged; ``SerialException`` once the cable was pulled."""
        if self._pulled():
            raise serial.SerialException(_SERIAL_GONE)
        return int(super().in_waiting)


# -------------------------------------------------------------------------------------------
# Disk: the recorder's output file


class _FaultyFile(io.FileIO):
    """The output file's raw I/O: writes beyond the schedule's room write what fits, then
    raise ``OSError(ENOSPC)``."""

    def __init__(self, path: Path, mode: str, schedule: FaultSchedule) -> None:
        super().__init__(path, mode)
        self._path = Path(path)
        self._schedule = schedule

    def write(self, b: Any, /) -> int:
        room = self._schedule._disk_room(self._path, self.tell())
        data = memoryview(b).cast("B")
        if room is not None and len(data) > room:
            if room > 0:
                return int(super().write(data[:room]))  # a short write; the next one fails
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self._path))
        return int(super().write(data))
